#!/usr/bin/env python3
"""Generate the textures of scenes/cutouts and scenes/bumps (64x64 8-bit PNGs).

Usage: python3 gen_detail_textures.py SCENES_DIR
Writes cutouts/leaves.png (an opacity mask: soft-edged discs, grey), cutouts/wall.bmp (a
colour pattern, 8-bit sRGB BMP), bumps/heights.png (a height field of round bumps, grey, read
raw), bumps/normals.png (the tangent-space normal map of a tilted wave, RGB, read raw) and
bumps/sky.hdr (a small sky, Radiance RGBE). Needs numpy and mitsuba (for image writing).
"""
import os
import sys

import numpy as np


def leaves(n=64):
    y, x = np.mgrid[0:n, 0:n].astype(np.float64) + 0.5
    u, v = x / n, y / n
    alpha = np.zeros((n, n))
    for cu, cv, r in [(0.3, 0.3, 0.22), (0.72, 0.35, 0.18), (0.45, 0.75, 0.2), (0.85, 0.85, 0.1)]:
        d = np.sqrt((u - cu) ** 2 + (v - cv) ** 2)
        alpha = np.maximum(alpha, np.clip((r - d) / 0.04, 0.0, 1.0))
    return alpha


def heights(n=64):
    y, x = np.mgrid[0:n, 0:n].astype(np.float64) + 0.5
    u, v = x / n, y / n
    return 0.5 + 0.25 * np.sin(2 * np.pi * 3 * u) * np.sin(2 * np.pi * 2 * v)


def normals(n=64):
    y, x = np.mgrid[0:n, 0:n].astype(np.float64) + 0.5
    u = x / n
    # The normal of a wave along u: tilted by up to 35 degrees.
    slope = np.tan(np.radians(35)) * np.cos(2 * np.pi * 4 * u)
    nn = np.stack([-slope, 0.15 * np.ones_like(slope), np.ones_like(slope)], axis=-1)
    nn /= np.linalg.norm(nn, axis=-1, keepdims=True)
    return nn * 0.5 + 0.5


def wall(n=32):
    y, x = np.mgrid[0:n, 0:n].astype(np.float64) + 0.5
    u, v = x / n, y / n
    img = np.stack([0.3 + 0.5 * u, 0.35 + 0.3 * (np.sin(8 * u) * np.sin(6 * v) > 0), 0.6 - 0.3 * v], -1)
    return img


def sky(w=32, h=16):
    y, x = np.mgrid[0:h, 0:w].astype(np.float32) + 0.5
    up = 1.0 - y / h
    img = np.stack([0.05 + 0.3 * up, 0.08 + 0.35 * up, 0.15 + 0.6 * up], -1)
    img[2:4, 10:12] = [6.0, 5.5, 4.5]  # a bright patch high in the sky
    return img.astype(np.float32)


def write_float(path, img):
    import mitsuba as mi
    mi.set_variant("scalar_rgb")
    mi.Bitmap(img).write(path)


def write_srgb_bmp(path, img):
    """A 24-bit uncompressed BMP of the sRGB-encoded image (Mitsuba writes no BMP)."""
    import struct
    enc = np.where(img <= 0.0031308, 12.92 * img, 1.055 * np.power(np.clip(img, 0, 1), 1 / 2.4) - 0.055)
    data = (np.clip(enc, 0, 1) * 255 + 0.5).astype(np.uint8)
    h, w, _ = data.shape
    row = (w * 3 + 3) & ~3
    pixels = b"".join(
        data[y, :, ::-1].tobytes() + b"\0" * (row - w * 3) for y in range(h - 1, -1, -1))
    header = struct.pack("<2sIHHI", b"BM", 54 + len(pixels), 0, 0, 54)
    info = struct.pack("<IiiHHIIiiII", 40, w, h, 1, 24, 0, len(pixels), 2835, 2835, 0, 0)
    with open(path, "wb") as f:
        f.write(header + info + pixels)


def write(path, img):
    import mitsuba as mi
    mi.set_variant("scalar_rgb")
    data = (np.clip(img, 0, 1) * 255 + 0.5).astype(np.uint8)
    if data.ndim == 2:
        data = data[..., None]
    bmp = mi.Bitmap(data)
    bmp.set_srgb_gamma(False)
    bmp.write(path)


def main():
    root = sys.argv[1]
    write(os.path.join(root, "cutouts", "leaves.png"), leaves())
    write(os.path.join(root, "bumps", "heights.png"), heights())
    write(os.path.join(root, "bumps", "normals.png"), normals())
    write_srgb_bmp(os.path.join(root, "cutouts", "wall.bmp"), wall())
    write_float(os.path.join(root, "bumps", "sky.hdr"), sky())


if __name__ == "__main__":
    main()
