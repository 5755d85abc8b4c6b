#!/usr/bin/env python3
"""Generate the small procedural texture used by scenes/materials (64x64 8-bit sRGB PNG).

Usage: python3 gen_texture.py OUT.png
Needs numpy and mitsuba (for PNG writing; no PIL dependency).
Pattern: smooth colour gradient + concentric rings + a diagonal stripe, so orientation
errors (u/v flips, row order) are easy to spot.
"""
import sys

import numpy as np


def make(n=64):
    y, x = np.mgrid[0:n, 0:n].astype(np.float64) + 0.5
    u, v = x / n, y / n
    r = np.sqrt((u - 0.35) ** 2 + (v - 0.4) ** 2)
    rings = 0.5 + 0.5 * np.cos(r * 40.0)
    img = np.zeros((n, n, 3))
    img[..., 0] = 0.25 + 0.65 * u
    img[..., 1] = 0.2 + 0.5 * rings * (1 - v) + 0.2 * v
    img[..., 2] = 0.3 + 0.55 * v
    stripe = np.abs((u + v) - 1.0) < 0.06
    img[stripe] = [0.9, 0.85, 0.2]
    # top-left corner marker (first rows of the file): white square
    img[2:10, 2:10] = [0.95, 0.95, 0.95]
    return (np.clip(img, 0, 1) * 255 + 0.5).astype(np.uint8)


def main():
    import mitsuba as mi
    mi.set_variant("scalar_rgb")
    bmp = mi.Bitmap(make())
    bmp.set_srgb_gamma(True)
    bmp.write(sys.argv[1])


if __name__ == "__main__":
    main()
