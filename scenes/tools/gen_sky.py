#!/usr/bin/env python3
"""Writes the 16x8 latitude-longitude sky of scenes/envmap-sky (OpenEXR, float RGB).

Rows fall fast from the zenith (row 0) to the horizon and the ground is dim; columns carry
a warm-to-cool sweep and one bright texel, so a half-texel shift in either direction shows.

Usage: gen_sky.py OUT.exr   (needs mitsuba and numpy: pip install mitsuba numpy)
"""
import sys

import mitsuba as mi
import numpy as np

mi.set_variant("scalar_rgb")
W, H = 16, 8
rows = [24.0, 9.0, 3.5, 1.6, 0.6, 0.25, 0.12, 0.08]
img = np.zeros((H, W, 3), dtype=np.float32)
for y in range(H):
    for x in range(W):
        t = x / (W - 1)
        img[y, x] = rows[y] * np.array([1.2 - 0.5 * t, 1.0, 0.6 + 0.6 * t])
img[1, 5] = [60.0, 55.0, 40.0]
mi.Bitmap(img).write(sys.argv[1])
