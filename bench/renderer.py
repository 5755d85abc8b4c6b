#!/usr/bin/env python3
"""Renderer benchmark: pathfarm `path` vs Mitsuba 3 llvm_ad_rgb / scalar_rgb.

Usage (from /work/main/bench, or anywhere):
  python3 renderer.py [--pathfarm BIN] [--reps 3] [--budget CPU_S] [--rate-cpu S]
                      [--scenes cornell-box veach-ajar] [--renderers pathfarm llvm_ad_rgb scalar_rgb]
                      [--threads N] [--pf-equal {time,spp}] [--out results/renderer.md]

For every scene (shared scenes, fixed resolution/max_depth, see SCENES) and renderer:
  1. throughput: R repetitions (default 3) of a render sized to take ~--rate-cpu CPU-seconds;
     samples/CPU-s = pixels*spp / CPU seconds of the render phase; the median is quoted.
       - pathfarm: a fresh `pathfarm render` process per repetition; CPU seconds and spp come
         from its `summary:` line (render phase only, scene loading/BVH excluded).
       - Mitsuba: one subprocess per variant (variants never mix in one process); scene loaded
         once, then a warm-up render (same resolution and pass size, so the JIT kernels of the
         llvm variant are compiled and cached) and R timed renders with
         time.process_time() around mi.render(...) + the conversion to numpy (forces
         evaluation).  Large spp counts are rendered in passes of <= PASS_SAMPLES samples
         (Mitsuba's llvm wavefront would otherwise need GBs) and averaged.
  2. equal time: each renderer gets the same CPU-second budget (--budget, default 20):
       - Mitsuba: spp = budget * (median samples/CPU-s) / pixels.
       - pathfarm: --pf-equal spp (default): as for Mitsuba, spp = budget * measured rate / pixels;
         --pf-equal time: `--time budget/threads --threads threads` (pathfarm's --time is
         wall-clock, so on a loaded machine it gets fewer CPU-seconds; the CPU-s actually used is
         reported in the table either way).
     relMSE = mean((x-ref)^2 / (ref^2 + 1e-2)) over pixels and channels, against the Tungsten
     reference (TungstenRender.exr beside the scene) box-downsampled to the render resolution.
  3. paired (--paired R, R rounds): the machine's speed drifts by 10-20 % from minute to
     minute, which the sequential runs above see as noise between renderers. So pathfarm and
     Mitsuba llvm_ad_rgb also run *at the same time*, one per core (taskset), single-threaded,
     swapping cores every round: Mitsuba does its warm-up and 3 timed renders of ~--rate-cpu
     CPU-s while pathfarm renders back to back beside it; each round gives one ratio of median
     samples/CPU-s (pathfarm / llvm), and the table quotes the median and range of the ratios.
Output: Markdown table on stdout and in --out (default bench/results/renderer.md).
Internal: `renderer.py _mitsuba_worker ...` is the per-variant subprocess.
"""
import argparse
import json
import os
import re
import statistics
import subprocess
import sys
import time

import numpy as np

HERE = os.path.dirname(os.path.abspath(__file__))
SHARED = os.path.normpath(os.path.join(HERE, "..", "..", "shared", "scenes"))
# name: (xml, resx, resy, max_depth)
SCENES = {
    "cornell-box": (os.path.join(SHARED, "cornell-box", "scene.xml"), 256, 256, 30),
    "veach-ajar": (os.path.join(SHARED, "veach-ajar", "scene.xml"), 320, 180, 13),
}
PASS_SAMPLES = 1 << 21      # max samples per mi.render call (llvm wavefront size)


# ----------------------------------------------------------------------------------------------
# Mitsuba worker (runs in its own process, one variant)
# ----------------------------------------------------------------------------------------------
def mitsuba_renderer(mi, scene, res, seed):
    """(render, pass_spp) for a loaded Mitsuba scene: render(spp) renders spp samples/pixel in
    passes of pass_spp (at most PASS_SAMPLES samples each, a fresh seed per pass counting up
    from `seed`) and returns (image float64 HxWx3, cpu_s, wall_s)."""
    pass_spp = max(1, PASS_SAMPLES // (res[0] * res[1]))
    next_seed = [seed]

    def render(spp):
        img = np.zeros((res[1], res[0], 3))
        c0, t0 = time.process_time(), time.perf_counter()
        left = spp
        while left > 0:
            n = min(pass_spp, left)
            arr = np.array(mi.render(scene, spp=n, seed=next_seed[0]), dtype=np.float64)[..., :3]
            next_seed[0] += 1
            img += arr * (n / spp)
            left -= n
        return img, time.process_time() - c0, time.perf_counter() - t0

    return render, pass_spp


def mitsuba_worker(a):
    import mitsuba as mi
    mi.set_variant(a.variant)
    if a.threads:
        import drjit as dr
        dr.set_thread_count(a.threads)
    scene = mi.load_file(a.scene, resx=a.res[0], resy=a.res[1], max_depth=a.max_depth)
    pixels = a.res[0] * a.res[1]
    render, pass_spp = mitsuba_renderer(mi, scene, a.res, 1000)

    render(min(pass_spp, 4))        # warm-up: JIT compile (llvm), caches
    if a.rate_spp <= 0:             # probe: size the throughput runs to ~rate_cpu seconds
        _, cpu, _ = render(pass_spp)
        rate = pixels * pass_spp / max(cpu, 1e-6)
        a.rate_spp = max(1, int(round(a.rate_cpu * rate / pixels)))
    runs = []
    for _ in range(a.reps):
        _, cpu, wall = render(a.rate_spp)
        runs.append({"spp": a.rate_spp, "cpu_s": cpu, "wall_s": wall,
                     "samples_per_cpu_s": pixels * a.rate_spp / max(cpu, 1e-9)})
    rate = statistics.median(r["samples_per_cpu_s"] for r in runs)
    eq = None
    if a.budget > 0:
        spp = max(1, int(round(a.budget * rate / pixels)))
        img, cpu, wall = render(spp)
        np.save(a.out, img.astype(np.float32))
        eq = {"spp": spp, "cpu_s": cpu, "wall_s": wall, "image": a.out}
    print("RESULT " + json.dumps({"runs": runs, "rate": rate, "equal_time": eq}))


# ----------------------------------------------------------------------------------------------
# pathfarm
# ----------------------------------------------------------------------------------------------
SUMMARY_RE = re.compile(r"summary:\s+resolution=(\d+)x(\d+)\s+spp=(\d+)\s+wall_s=([\d.eE+-]+)\s+"
                        r"cpu_s=([\d.eE+-]+)\s+samples_per_cpu_s=([\d.eE+-]+)")


def run_pathfarm(binary, xml, res, max_depth, out, threads, spp=None, tlimit=None, seed=1, cpu=None):
    """One `pathfarm render`; `cpu`: pin it to that core (taskset)."""
    args = ["taskset", "-c", str(cpu)] if cpu is not None else []
    args += [binary, "render", xml, "-o", out, "--seed", str(seed), "--threads", str(threads),
            "-D", "resx=%d" % res[0], "-D", "resy=%d" % res[1], "-D", "max_depth=%d" % max_depth]
    if spp is not None:
        args += ["--spp", str(spp)]
    if tlimit is not None:
        args += ["--time", "%.3f" % tlimit]
    p = subprocess.run(args, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    if p.returncode != 0:
        raise RuntimeError("pathfarm failed (%d): %s\n%s" % (p.returncode, " ".join(args), p.stderr[-2000:]))
    m = None
    for line in p.stdout.splitlines():
        m = SUMMARY_RE.search(line) or m
    if not m:
        raise RuntimeError("no summary line in pathfarm output:\n" + p.stdout[-2000:])
    w, h, spp_, wall, cpu, rate = m.groups()
    return {"spp": int(spp_), "wall_s": float(wall), "cpu_s": float(cpu),
            "samples_per_cpu_s": int(w) * int(h) * int(spp_) / max(float(cpu), 1e-9),
            "reported_rate": float(rate)}


def bench_pathfarm(a, name, xml, res, md, workdir):
    pixels = res[0] * res[1]
    out = os.path.join(workdir, "pathfarm-%s.exr" % name)
    probe = run_pathfarm(a.pathfarm, xml, res, md, out, a.threads, spp=4)
    spp = max(1, int(round(a.rate_cpu * probe["samples_per_cpu_s"] / pixels)))
    runs = [run_pathfarm(a.pathfarm, xml, res, md, out, a.threads, spp=spp, seed=10 + i) for i in range(a.reps)]
    rate = statistics.median(r["samples_per_cpu_s"] for r in runs)
    eq = None
    if a.budget > 0:
        if a.pf_equal == "time":
            eq = run_pathfarm(a.pathfarm, xml, res, md, out, a.threads, tlimit=a.budget / a.threads, seed=99)
        else:
            eq = run_pathfarm(a.pathfarm, xml, res, md, out, a.threads,
                              spp=max(1, int(round(a.budget * rate / pixels))), seed=99)
        eq["image"] = out
    return {"runs": runs, "rate": rate, "equal_time": eq}


def bench_mitsuba(a, variant, name, xml, res, md, workdir):
    out = os.path.join(workdir, "%s-%s.npy" % (variant, name))
    args = [sys.executable, os.path.abspath(__file__), "_mitsuba_worker", "--variant", variant,
            "--scene", xml, "--res", str(res[0]), str(res[1]), "--max-depth", str(md),
            "--reps", str(a.reps), "--rate-cpu", str(a.rate_cpu), "--budget", str(a.budget),
            "--out", out]
    if a.mi_threads:
        args += ["--threads", str(a.mi_threads)]
    p = subprocess.run(args, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    lines = [l for l in p.stdout.splitlines() if l.startswith("RESULT ")]
    if p.returncode != 0 or not lines:
        raise RuntimeError("mitsuba %s worker failed:\n%s" % (variant, p.stderr[-3000:]))
    return json.loads(lines[-1][7:])


# ----------------------------------------------------------------------------------------------
def load_image(path):
    if path.endswith(".npy"):
        return np.load(path).astype(np.float64)
    import mitsuba as mi
    if not mi.variant():
        mi.set_variant("scalar_rgb")
    bmp = mi.Bitmap(path)
    names = [f.name for f in bmp.struct_()]
    arr = np.array(bmp, dtype=np.float64)
    return np.stack([arr[..., names.index(c)] for c in "RGB"], -1)


def reference(xml, res):
    ref = load_image(os.path.join(os.path.dirname(xml), "TungstenRender.exr"))
    h, w = ref.shape[:2]
    fx, fy = w // res[0], h // res[1]
    if fx != fy or fx * res[0] != w or fy * res[1] != h:
        raise RuntimeError("reference %dx%d is not an integer multiple of %dx%d" % (w, h, res[0], res[1]))
    return ref.reshape(res[1], fy, res[0], fx, 3).mean((1, 3))


def relmse(x, ref, mask=None):
    e = ((x - ref) ** 2 / (ref ** 2 + 1e-2)).mean(-1)
    return float(e.mean() if mask is None else e[mask].mean())


def emitter_edge_mask(ref, thresh=None):
    """True for pixels NOT within 1 px of a directly visible emitter (ref luminance > thresh,
    default max(2, 20 x median luminance)).
    Excluding them removes the filter mismatch: Mitsuba/pathfarm use the scene's tent filter at
    the render resolution, the reference is a box-downsampled high-res render, so the light's
    edges differ by ~1/8 of the emitted radiance (relMSE floor ~0.024 on cornell-box)."""
    lum = ref.mean(-1)
    if thresh is None:
        thresh = max(2.0, 20.0 * float(np.median(lum)))
    lum = lum > thresh
    pad = np.pad(lum, 1)
    dil = np.zeros_like(lum)
    for dy in range(3):
        for dx in range(3):
            dil |= pad[dy:dy + lum.shape[0], dx:dx + lum.shape[1]]
    return ~dil


def paired(a, name, xml, res, md):
    """Rounds of pathfarm and Mitsuba llvm side by side, one core each: ratios of their rates."""
    pixels = res[0] * res[1]
    out = os.path.join(a.workdir, "paired-pathfarm-%s.exr" % name)
    probe = run_pathfarm(a.pathfarm, xml, res, md, out, 1, spp=4)
    spp = max(1, int(round(a.rate_cpu * probe["samples_per_cpu_s"] / pixels)))
    ratios, pf_rates, mi_rates = [], [], []
    for r in range(a.paired):
        pf_core, mi_core = (0, 1) if r % 2 == 0 else (1, 0)
        args = ["taskset", "-c", str(mi_core), sys.executable, os.path.abspath(__file__), "_mitsuba_worker",
                "--variant", "llvm_ad_rgb", "--scene", xml, "--res", str(res[0]), str(res[1]),
                "--max-depth", str(md), "--reps", "3", "--rate-cpu", str(a.rate_cpu), "--budget", "0",
                "--threads", "1", "--out", os.path.join(a.workdir, "paired-mitsuba.npy")]
        mi_proc = subprocess.Popen(args, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
        rates = []
        while mi_proc.poll() is None:
            try:
                r_ = run_pathfarm(a.pathfarm, xml, res, md, out, 1, spp=spp, seed=100 + len(rates), cpu=pf_core)
            except RuntimeError:
                mi_proc.kill()
                raise
            rates.append(r_["samples_per_cpu_s"])
        mo, me = mi_proc.communicate()
        lines = [l for l in mo.splitlines() if l.startswith("RESULT ")]
        if mi_proc.returncode != 0 or not lines:
            raise RuntimeError("mitsuba worker failed in the paired run:\n" + me[-3000:])
        mi_rate = json.loads(lines[-1][7:])["rate"]
        # The first pathfarm render overlaps Mitsuba's scene loading and JIT warm-up, not
        # its timed renders: leave it out when there are others.
        pf_rate = statistics.median(rates[1:] if len(rates) > 1 else rates)
        pf_rates.append(pf_rate)
        mi_rates.append(mi_rate)
        ratios.append(pf_rate / mi_rate)
        print("[%s/paired] round %d: pathfarm %.4g (%d renders), llvm %.4g, ratio %.3f"
              % (name, r + 1, pf_rate, len(rates), mi_rate, ratios[-1]), file=sys.stderr)
    return ratios, pf_rates, mi_rates


def main():
    if len(sys.argv) > 1 and sys.argv[1] == "_mitsuba_worker":
        ap = argparse.ArgumentParser()
        ap.add_argument("_w")
        ap.add_argument("--variant", required=True)
        ap.add_argument("--scene", required=True)
        ap.add_argument("--res", type=int, nargs=2, required=True)
        ap.add_argument("--max-depth", type=int, required=True)
        ap.add_argument("--reps", type=int, default=3)
        ap.add_argument("--rate-cpu", type=float, default=3.0)
        ap.add_argument("--rate-spp", type=int, default=0)
        ap.add_argument("--budget", type=float, default=0)
        ap.add_argument("--threads", type=int, default=0)
        ap.add_argument("--out", required=True)
        return mitsuba_worker(ap.parse_args())

    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--pathfarm", default=os.path.join(HERE, "..", "target", "release", "pathfarm"))
    ap.add_argument("--reps", type=int, default=3)
    ap.add_argument("--budget", type=float, default=20.0, help="equal-time CPU-seconds budget (0: skip)")
    ap.add_argument("--rate-cpu", type=float, default=3.0, help="target CPU-seconds of each throughput run")
    ap.add_argument("--scenes", nargs="+", default=list(SCENES))
    ap.add_argument("--renderers", nargs="+", default=["pathfarm", "llvm_ad_rgb", "scalar_rgb"])
    ap.add_argument("--threads", type=int, default=os.cpu_count(), help="pathfarm --threads")
    ap.add_argument("--mi-threads", type=int, default=0, help="Mitsuba thread count (0: its default, all cores)")
    ap.add_argument("--pf-equal", choices=["time", "spp"], default="spp",
                    help="spp: spp from pathfarm's measured CPU rate (robust on a shared machine); "
                         "time: --time budget/threads (wall-clock)")
    ap.add_argument("--workdir", default=os.path.join(HERE, "results", "renders"))
    ap.add_argument("--out", default=os.path.join(HERE, "results", "renderer.md"))
    ap.add_argument("--paired", type=int, default=0,
                    help="rounds of pathfarm and Mitsuba llvm run side by side (0: none)")
    a = ap.parse_args()
    os.makedirs(a.workdir, exist_ok=True)

    rows = []
    pairs = []
    for name in a.scenes:
        xml, rx, ry, md = SCENES[name]
        res = (rx, ry)
        ref = reference(xml, res)
        mask = emitter_edge_mask(ref)
        for r in a.renderers:
            t0 = time.time()
            try:
                if r == "pathfarm":
                    if not os.path.exists(a.pathfarm):
                        raise RuntimeError("pathfarm binary not found at %s" % a.pathfarm)
                    res_ = bench_pathfarm(a, name, xml, res, md, a.workdir)
                else:
                    res_ = bench_mitsuba(a, r, name, xml, res, md, a.workdir)
            except Exception as e:  # keep going with the other renderers
                print("[%s/%s] ERROR: %s" % (name, r, str(e).splitlines()[0]), file=sys.stderr)
                rows.append((name, r, None, None, None, None, None, str(e).splitlines()[0]))
                continue
            eq = res_["equal_time"]
            img = load_image(eq["image"]) if eq else None
            err = relmse(img, ref) if eq else None
            err_m = relmse(img, ref, mask) if eq else None
            rates = [x["samples_per_cpu_s"] for x in res_["runs"]]
            print("[%s/%s] %.0fs: rates %s, equal-time spp %s cpu %.1fs relMSE %s"
                  % (name, r, time.time() - t0, ", ".join("%.3g" % x for x in rates),
                     eq and eq["spp"], eq["cpu_s"] if eq else float("nan"), err), file=sys.stderr)
            rows.append((name, r, res_["rate"], err, err_m, eq and eq["spp"], eq and eq["cpu_s"], ""))
        if a.paired > 0:
            pairs.append((name,) + paired(a, name, xml, res, md))

    lines = ["# Renderer benchmark", "",
             "%s; %d repetitions (median); equal-time budget %.1f CPU-s; threads: pathfarm %d, Mitsuba %s; %d CPUs."
             % (time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime()), a.reps, a.budget, a.threads,
                a.mi_threads or "default", os.cpu_count()),
             "relMSE = mean((x-ref)^2/(ref^2+1e-2)) vs the Tungsten reference box-downsampled to the render resolution.",
             "",
             "Second relMSE column excludes pixels within 1 px of directly visible emitters (filter mismatch vs the reference).",
             "",
             "| scene | renderer | samples/CPU-s (median) | relMSE @ equal time | relMSE excl. emitter edges | spp used | CPU-s used |",
             "|---|---|---:|---:|---:|---:|---:|"]
    for name, r, rate, err, err_m, spp, cpu, note in rows:
        if rate is None:
            lines.append("| %s | %s | n/a | n/a | n/a | n/a | n/a (%s) |" % (name, r, note[:80]))
        else:
            lines.append("| %s | %s | %.4g | %s | %s | %s | %s |" % (
                name, r, rate, "%.4g" % err if err is not None else "-",
                "%.4g" % err_m if err_m is not None else "-", spp if spp else "-",
                "%.1f" % cpu if cpu is not None else "-"))
    if pairs:
        lines += ["", "Paired: pathfarm and Mitsuba llvm_ad_rgb at the same time, one core each, "
                  "single-threaded, cores swapped every round (%d rounds)." % a.paired, "",
                  "| scene | pathfarm samples/CPU-s (median) | llvm samples/CPU-s (median) | "
                  "ratio pathfarm / llvm (median) | ratios |",
                  "|---|---:|---:|---:|---|"]
        for name, ratios, pf, mi in pairs:
            lines.append("| %s | %.4g | %.4g | **%.3f** | %s |" % (
                name, statistics.median(pf), statistics.median(mi), statistics.median(ratios),
                " ".join("%.3f" % x for x in ratios)))
    text = "\n".join(lines) + "\n"
    print(text)
    os.makedirs(os.path.dirname(os.path.abspath(a.out)), exist_ok=True)
    with open(a.out, "w") as f:
        f.write(text)
    return 0


if __name__ == "__main__":
    sys.exit(main())
