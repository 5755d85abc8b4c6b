#!/usr/bin/env python3
"""How low relMSE against a benchmark reference can go: the error floor of the reference.

Usage:
  python3 bench/floor.py [--scene veach-ajar] [--spp 1024] [--threads 2]

relMSE against a reference image measures noise *and* any difference between the expected
image of the renderer and the reference. If the reference was made by another renderer
(veach-ajar's is Tungsten's), a difference in how the two read the scene stays however long
one renders: a floor under every relMSE, the same for Mitsuba and pathfarm.

The floor is the relMSE of the expected image, F = mean((E[x] - ref)^2 / (ref^2 + 1e-2)).
With two *independent* renders a and b of the same expected image, E[(a - ref)(b - ref)] =
(E[x] - ref)^2 per pixel, so mean((a - ref)(b - ref) / (ref^2 + 1e-2)) is an unbiased estimate
of F whatever the noise. Here a = Mitsuba 3 llvm_ad_rgb `path` and b = pathfarm `path`, both at
--spp on the benchmark's settings (they agree with each other: see the mean ratios printed).
A 95 % interval comes from a bootstrap over image rows, and the share of F in the worst 16x16
block says whether one object carries it.
"""
import argparse
import os
import subprocess
import sys

import numpy as np

HERE = os.path.dirname(os.path.abspath(__file__))
sys.path.insert(0, HERE)
import renderer as R  # noqa: E402
import guided as G  # noqa: E402


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--scene", default="veach-ajar", choices=["veach-ajar", "cornell-box"])
    ap.add_argument("--spp", type=int, default=1024)
    ap.add_argument("--threads", type=int, default=os.cpu_count())
    ap.add_argument("--pathfarm", default=os.path.join(HERE, "..", "target", "release", "pathfarm"))
    ap.add_argument("--workdir", default=os.path.join(HERE, "results", "renders"))
    a = ap.parse_args()
    os.makedirs(a.workdir, exist_ok=True)
    xml, w, h, md, _ = G.SCENES[a.scene]
    ref = G.load_reference(a.scene)

    mi_out = os.path.join(a.workdir, f"floor-mitsuba-{a.scene}.npy")
    code = (
        "import mitsuba as mi, numpy as np\n"
        "mi.set_variant('llvm_ad_rgb')\n"
        f"s = mi.load_file({xml!r}, resx={w}, resy={h}, max_depth={md})\n"
        f"n = max(1, {a.spp} // 128)\n"
        f"img = sum(np.array(mi.render(s, spp={a.spp} // n, seed=k), dtype=np.float64) for k in range(n)) / n\n"
        f"np.save({mi_out!r}, img[..., :3])\n"
    )
    subprocess.run([sys.executable, "-c", code], check=True)
    pf_out = os.path.join(a.workdir, f"floor-pathfarm-{a.scene}.exr")
    R.run_pathfarm(a.pathfarm, xml, (w, h), md, pf_out, a.threads, spp=a.spp, seed=7)

    mi_img = np.load(mi_out)
    pf_img = R.load_image(pf_out)
    d = ref ** 2 + 1e-2
    cross = ((mi_img - ref) * (pf_img - ref) / d).mean(-1)
    floor = float(cross.mean())
    rng = np.random.default_rng(0)
    rows = cross.mean(1)
    boot = [rows[rng.integers(0, len(rows), len(rows))].mean() for _ in range(2000)]
    lo, hi = np.percentile(boot, [2.5, 97.5])
    blocks = cross[: h // 16 * 16, : w // 16 * 16].reshape(h // 16, 16, w // 16, 16).sum((1, 3))
    by, bx = np.unravel_index(np.argmax(blocks), blocks.shape)
    print(f"{a.scene} {w}x{h} max_depth {md}, {a.spp} spp each")
    print(f"relMSE vs reference: Mitsuba {float(((mi_img - ref) ** 2 / d).mean()):.5f}, "
          f"pathfarm {float(((pf_img - ref) ** 2 / d).mean()):.5f}")
    print(f"image mean / reference mean: Mitsuba {mi_img.mean() / ref.mean():.4f}, "
          f"pathfarm {pf_img.mean() / ref.mean():.4f}")
    print(f"floor (relMSE of the expected image vs the reference): {floor:.5f} "
          f"(95 % interval {lo:.5f}..{hi:.5f})")
    print(f"worst 16x16 block: x {bx * 16}..{bx * 16 + 16}, y {by * 16}..{by * 16 + 16}, "
          f"{blocks[by, bx] / cross.sum():.0%} of the floor; mean there Mitsuba / reference "
          f"{mi_img[by * 16:by * 16 + 16, bx * 16:bx * 16 + 16].mean() / ref[by * 16:by * 16 + 16, bx * 16:bx * 16 + 16].mean():.3f}, "
          f"pathfarm / reference "
          f"{pf_img[by * 16:by * 16 + 16, bx * 16:bx * 16 + 16].mean() / ref[by * 16:by * 16 + 16, bx * 16:bx * 16 + 16].mean():.3f}")


if __name__ == "__main__":
    main()
