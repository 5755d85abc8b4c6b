#!/usr/bin/env python3
"""Stand-in for `pathfarm render` built on Mitsuba 3 (scalar_rgb), implementing the same CLI
contract, so that crosscheck.py can be validated before / independently of the Rust renderer:

  mock_pathfarm.py render SCENE.xml -o OUT.exr [--spp N] [--time S] [--seed S] [--threads N]
                   [-D name=value ...] [--aovs]

Writes OUT.exr with channels R,G,B (+ variance.R/G/B = variance of the pixel mean, and spp,
with --aovs) and prints the `summary:` line.  The variance is estimated from M independent
sub-renders (different seeds) of N/M spp each.

Environment knobs for self-tests:
  MOCK_SCALE=1.03       multiply the image by this factor (a deliberately wrong renderer)
  MOCK_SUBRUNS=32       number of sub-renders used for the variance estimate
  MOCK_SAMPLE_BORDER=1  film sample_border=true (filter not truncated at the image edge)
"""
import argparse
import os
import sys
import time

import numpy as np


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("cmd", choices=["render"])
    ap.add_argument("scene")
    ap.add_argument("-o", "--output", required=True)
    ap.add_argument("--spp", type=int, default=None)
    ap.add_argument("--time", type=float, default=None)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--threads", type=int, default=None)
    ap.add_argument("-D", action="append", default=[])
    ap.add_argument("--aovs", action="store_true")
    a = ap.parse_args()

    import mitsuba as mi
    mi.set_variant("scalar_rgb")
    params = {}
    for d in a.D:
        k, v = d.split("=", 1)
        params[k] = v
    if os.environ.get("MOCK_SAMPLE_BORDER"):
        # simulate a renderer that does not truncate the pixel filter at the image edge
        xml = open(a.scene).read().replace('<film type="hdrfilm">',
                                           '<film type="hdrfilm"><boolean name="sample_border" value="true"/>')
        mi.Thread.thread().file_resolver().prepend(os.path.dirname(os.path.abspath(a.scene)))
        scene = mi.load_string(xml, **params)
    else:
        scene = mi.load_file(a.scene, **params)
    spp_total = a.spp if a.spp is not None else scene.sensors()[0].sampler().sample_count()
    m = int(os.environ.get("MOCK_SUBRUNS", "32"))
    m = max(2, min(m, spp_total))
    per = max(1, spp_total // m)
    spp_total = per * m
    scale = float(os.environ.get("MOCK_SCALE", "1.0"))

    t0, c0 = time.time(), time.process_time()
    imgs = []
    for i in range(m):
        # seeds far away from crosscheck's Mitsuba seeds (0..K-1)
        imgs.append(np.array(mi.render(scene, seed=1_000_003 * (a.seed + 1) + i, spp=per)))
    imgs = np.stack(imgs) * scale
    wall, cpu = time.time() - t0, time.process_time() - c0
    mean = imgs.mean(0)
    var_mean = imgs.var(0, ddof=1) / m
    h, w = mean.shape[:2]

    if a.aovs:
        chans = np.concatenate([mean, var_mean, np.full((h, w, 1), spp_total, np.float32)], axis=2)
        names = ["R", "G", "B", "variance.R", "variance.G", "variance.B", "spp"]
    else:
        chans, names = mean, ["R", "G", "B"]
    bmp = mi.Bitmap(chans.astype(np.float32), mi.Bitmap.PixelFormat.MultiChannel, names)
    bmp.write(a.output)
    prev = mi.Bitmap(mean.astype(np.float32)).convert(mi.Bitmap.PixelFormat.RGB, mi.Struct.Type.UInt8, True)
    prev.write(os.path.splitext(a.output)[0] + ".png")
    n = w * h * spp_total
    print("summary: resolution=%dx%d spp=%d wall_s=%.3f cpu_s=%.3f samples_per_cpu_s=%.1f"
          % (w, h, spp_total, wall, cpu, n / max(cpu, 1e-9)))


if __name__ == "__main__":
    sys.exit(main())
