#!/usr/bin/env python3
"""Generate the textures of scenes/cutouts and scenes/bumps (64x64 8-bit PNGs).

Usage: python3 gen_detail_textures.py SCENES_DIR
Writes cutouts/leaves.png (an opacity mask: soft-edged discs, grey), bumps/heights.png (a
height field of round bumps, grey, read raw) and bumps/normals.png (the tangent-space normal
map of a tilted wave, RGB, read raw). Needs numpy and mitsuba (for PNG writing).
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


if __name__ == "__main__":
    main()
