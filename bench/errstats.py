#!/usr/bin/env python3
"""Where an image's error is: relMSE against a scene's reference, and how it is distributed.

Usage:
  python3 bench/errstats.py SCENE IMAGE.exr [IMAGE.exr ...] [--map OUT.png]

SCENE is a benchmark scene name (veach-ajar, cornell-box, door-ajar; the reference and
resolution are guided.py's) or a path to a reference image of the same size as the images.
For each image it prints:
  - relMSE = mean((x-ref)^2/(ref^2+1e-2)) over pixels and channels (renderer.py's metric);
  - the share of that error in the worst 1 %, 5 % and 20 % of pixels: near 1 for the 1 % share
    means a few outliers (fireflies) dominate, near 0.01 means the noise is even;
  - relMSE of the 4x4 box-filtered image: what is left after averaging neighbours, a rough split
    between high-frequency noise and low-frequency error (splotches, bias);
  - the image mean over the reference mean (bias or a model difference shows here).
--map writes a PNG per image pair (tonemapped image | log10 per-pixel relative error from 1e-4
(blue) to 1 (red)), stacked, with the reference last; it needs Mitsuba's Bitmap (pip mitsuba).
"""
import argparse
import os
import sys

import numpy as np

HERE = os.path.dirname(os.path.abspath(__file__))
sys.path.insert(0, HERE)
import renderer as R  # noqa: E402


def reference(scene):
    if os.path.exists(scene):
        return R.load_image(scene)
    import guided
    if scene not in guided.SCENES:
        raise SystemExit("unknown scene %r (one of %s, or a reference image path)"
                         % (scene, ", ".join(guided.SCENES)))
    return guided.load_reference(scene)


def stats(x, ref):
    e = ((x - ref) ** 2 / (ref ** 2 + 1e-2)).mean(-1)
    s = np.sort(e.ravel())[::-1]
    tot = s.sum()
    share = [s[:max(1, int(round(f * s.size)))].sum() / tot if tot > 0 else 0.0 for f in (0.01, 0.05, 0.2)]
    h, w = e.shape
    hb, wb = h // 4 * 4, w // 4 * 4
    xb = x[:hb, :wb].reshape(hb // 4, 4, wb // 4, 4, 3).mean((1, 3))
    rb = ref[:hb, :wb].reshape(hb // 4, 4, wb // 4, 4, 3).mean((1, 3))
    block = float(((xb - rb) ** 2 / (rb ** 2 + 1e-2)).mean())
    return float(e.mean()), share, block, float(x.mean() / ref.mean()), e


def error_map(rows, out):
    import mitsuba as mi
    if not mi.variant():
        mi.set_variant("scalar_rgb")

    def tonemap(x):
        return np.clip(x / (1 + x), 0, 1) ** (1 / 2.2)
    panels = []
    for x, e in rows:
        t = np.clip((np.log10(e + 1e-6) + 4) / 4, 0, 1)[..., None]
        heat = np.concatenate([t, 0.3 * t, 1 - t], -1)
        panels.append(np.concatenate([tonemap(x), heat], 1))
    sheet = np.concatenate(panels, 0).astype(np.float32)
    bmp = mi.Bitmap(sheet, pixel_format=mi.Bitmap.PixelFormat.RGB)
    bmp.convert(mi.Bitmap.PixelFormat.RGB, mi.Struct.Type.UInt8, srgb_gamma=False).write(out)


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("scene")
    ap.add_argument("images", nargs="+")
    ap.add_argument("--map", help="write the error maps to this PNG")
    a = ap.parse_args()
    ref = reference(a.scene)
    print("| image | relMSE | worst 1 % share | worst 5 % | worst 20 % | 4x4-box relMSE | mean / ref mean |")
    print("|---|---:|---:|---:|---:|---:|---:|")
    rows = []
    for path in a.images:
        x = R.load_image(path)
        if x.shape != ref.shape:
            raise SystemExit("%s: %s, reference %s" % (path, x.shape, ref.shape))
        rel, share, block, ratio, e = stats(x, ref)
        print("| %s | %.4g | %.2f | %.2f | %.2f | %.4g | %.4f |"
              % (os.path.basename(path), rel, share[0], share[1], share[2], block, ratio))
        rows.append((x, e))
    if a.map:
        rows.append((ref, np.full(ref.shape[:2], 1e-6)))
        error_map(rows, a.map)
        print("error maps: %s" % a.map)


if __name__ == "__main__":
    main()
