#!/usr/bin/env python3
"""Paired A/B speed comparison of two pathfarm binaries on the shared scenes.

Usage:
  python3 bench/ab.py A_BINARY B_BINARY [--reps 8] [--scenes cornell-box veach-ajar]
                      [--same-image]

Scenes: the two renderer benchmark scenes with `path`, and veach-ajar with `guided_path`
(`veach-guided-2019`: the 2019 preset; `veach-guided`: the default preset;
`veach-guided-box`: the default preset with `spatial_filter=box`), at a fixed sample budget so
that both binaries train the same schedule.

On a shared, noisy machine, runs of one binary after the other differ by 10-20 % from
minute to minute. So A and B run *at the same time*, one pinned to each of two cores
(`taskset`), single-threaded, same scene, seed and sample count, and swap cores every
repetition; each repetition gives one ratio B/A of samples per CPU-second (from the
`summary:` line), and the median ratio is reported with every single ratio. Effects
under ~3 % stay within the noise of 8 repetitions. `--same-image` also checks that A and B
wrote byte-identical images in every repetition (for changes meant not to alter a bit).
"""
import argparse
import os
import re
import statistics
import subprocess

HERE = os.path.dirname(os.path.abspath(__file__))
SHARED = os.path.normpath(os.path.join(HERE, "..", "..", "shared", "scenes"))
SCENES = {
    "cornell-box": ["-D", "resx=256", "-D", "resy=256", "--spp", "32"],
    "veach-ajar": ["-D", "resx=320", "-D", "resy=180", "-D", "max_depth=13", "--spp", "16"],
    "veach-guided-2019": ["-D", "resx=320", "-D", "resy=180", "-D", "max_depth=13", "-D",
                          "integrator=guided_path", "-D", "preset=2019", "--spp", "24"],
    "veach-guided": ["-D", "resx=320", "-D", "resy=180", "-D", "max_depth=13", "-D",
                     "integrator=guided_path", "--spp", "24"],
    # the pathfarm preset with the spatial box filter (recording-heavy: every record splats
    # into all the leaves its box overlaps)
    "veach-guided-box": ["-D", "resx=320", "-D", "resy=180", "-D", "max_depth=13", "-D",
                         "integrator=guided_path", "-D", "spatial_filter=box", "--spp", "16"],
}
SCENE_FILE = {"veach-guided-2019": "veach-ajar", "veach-guided": "veach-ajar",
              "veach-guided-box": "veach-ajar"}


def start(binary, cpu, scene, seed, tag, tmp):
    cmd = ["taskset", "-c", str(cpu), binary, "render",
           os.path.join(SHARED, SCENE_FILE.get(scene, scene), "scene.xml")]
    cmd += SCENES[scene] + ["--threads", "1", "--seed", str(seed), "-o", os.path.join(tmp, f"ab-{tag}.exr")]
    return subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)


def rate(proc):
    out = proc.communicate()[0]
    m = re.search(r"samples_per_cpu_s=(\d+)", out)
    if proc.returncode != 0 or not m:
        raise SystemExit(f"render failed:\n{out}")
    return int(m.group(1))


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("a")
    ap.add_argument("b")
    ap.add_argument("--reps", type=int, default=8)
    ap.add_argument("--scenes", nargs="+", default=list(SCENES), choices=list(SCENES))
    ap.add_argument("--tmp", default="/tmp")
    ap.add_argument("--same-image", action="store_true", help="require byte-identical images")
    args = ap.parse_args()
    for scene in args.scenes:
        ra, rb = [], []
        for r in range(args.reps):
            ca, cb = (0, 1) if r % 2 == 0 else (1, 0)
            pa = start(args.a, ca, scene, r + 1, "a", args.tmp)
            pb = start(args.b, cb, scene, r + 1, "b", args.tmp)
            ra.append(rate(pa))
            rb.append(rate(pb))
            if args.same_image:
                with open(os.path.join(args.tmp, "ab-a.exr"), "rb") as fa, \
                        open(os.path.join(args.tmp, "ab-b.exr"), "rb") as fb:
                    if fa.read() != fb.read():
                        raise SystemExit(f"{scene} seed {r + 1}: A and B images differ")
        ratios = [b / a for a, b in zip(ra, rb)]
        print(f"{scene:12s} A {statistics.median(ra):10.0f}  B {statistics.median(rb):10.0f}  "
              f"B/A median {statistics.median(ratios):.3f}  [{' '.join('%.3f' % x for x in ratios)}]"
              + ("  images identical" if args.same_image else ""))


if __name__ == "__main__":
    main()
