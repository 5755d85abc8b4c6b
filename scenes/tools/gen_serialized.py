#!/usr/bin/env python3
"""Writes legacy-0.6/meshes/shapes.serialized: a Mitsuba serialized file (format version 4,
two shapes) as Mitsuba 0.6's exporters write it. Shape 0: a flat-shaded octahedron; shape 1:
a torus of 48x24 quads with vertex normals and texture coordinates.

Usage: gen_serialized.py OUT.serialized   (Python 3 standard library only)
"""
import math
import struct
import sys
import zlib

HAS_NORMALS, HAS_TEXCOORDS, SINGLE = 0x0001, 0x0002, 0x1000


def shape(name, positions, triangles, normals=None, uvs=None):
    flags = SINGLE | (HAS_NORMALS if normals else 0) | (HAS_TEXCOORDS if uvs else 0)
    body = struct.pack("<I", flags) + name.encode() + b"\0"
    body += struct.pack("<QQ", len(positions), len(triangles))
    for group in (positions, normals or [], uvs or []):
        for v in group:
            body += struct.pack("<%df" % len(v), *v)
    for t in triangles:
        body += struct.pack("<3I", *t)
    return struct.pack("<HH", 0x041C, 4) + zlib.compress(body, 9)


def octahedron():
    p = [(1, 0, 0), (-1, 0, 0), (0, 1, 0), (0, -1, 0), (0, 0, 1), (0, 0, -1)]
    t = [(0, 2, 4), (2, 1, 4), (1, 3, 4), (3, 0, 4), (2, 0, 5), (1, 2, 5), (3, 1, 5), (0, 3, 5)]
    return p, t


def torus(n=48, m=24, big=1.0, small=0.35):
    p, nrm, uv, t = [], [], [], []
    for i in range(n + 1):
        a = 2 * math.pi * i / n
        for j in range(m + 1):
            b = 2 * math.pi * j / m
            c = (math.cos(a), math.sin(a))
            p.append(((big + small * math.cos(b)) * c[0], small * math.sin(b),
                      (big + small * math.cos(b)) * c[1]))
            nrm.append((math.cos(b) * c[0], math.sin(b), math.cos(b) * c[1]))
            uv.append((i / n, j / m))
    for i in range(n):
        for j in range(m):
            a, b = i * (m + 1) + j, (i + 1) * (m + 1) + j
            t += [(a, a + 1, b), (b, a + 1, b + 1)]
    return p, t, nrm, uv


shapes = [shape("octahedron", *octahedron())]
p, t, nrm, uv = torus()
shapes.append(shape("torus", p, t, nrm, uv))
out, offsets = b"", []
for s in shapes:
    offsets.append(len(out))
    out += s
out += b"".join(struct.pack("<Q", o) for o in offsets) + struct.pack("<I", len(shapes))
open(sys.argv[1], "wb").write(out)
