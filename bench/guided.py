#!/usr/bin/env python3
"""Path-guiding benchmark: pathfarm `path` / `guided_path` (2017, 2019, pathfarm presets) vs Mitsuba 3 `path`.

Usage (from anywhere):
  python3 guided.py [--budgets 30 120] [--reps 3] [--threads 2] [--scenes veach-ajar cornell-box door-ajar]
                    [--configs pf-path pf-2017 pf-2019 pf-pathfarm mi-path] [--resume] [--table-only]
  python3 guided.py --make-door-reference      # (re)generate results/door-ajar-reference.exr

Equal-time relMSE at CPU-second budgets (default 30 and 120). Same conventions as renderer.py:
  - pathfarm: `pathfarm render --time budget/threads --threads threads` (wall-clock budget, so
    30 CPU-s = --time 15 with 2 threads; for guided_path the budget covers training + final
    rendering). CPU-s actually used, spp, training fraction and tree memory come from the
    `summary:` / `guided:` lines. `path` runs on the scene file with -D integrator=path; the
    two guided configurations use a wrapper XML in a temp dir (the scene file with its
    <integrator> block replaced by <integrator type="guided_path"> + preset 2017 / 2019 / pathfarm +
    max_depth; every other entry of the scene dir is symlinked beside it, so relative mesh and
    texture paths resolve).
  - Mitsuba 3 llvm_ad_rgb `path` (one subprocess per run): warm-up render (JIT), 3 throughput
    renders of ~--rate-cpu CPU-s, spp = budget * median samples/CPU-s / pixels, then that render
    (time.process_time(), i.e. CPU-s of all threads; default thread count = all cores).
  - relMSE = mean((x-ref)^2/(ref^2+1e-2)); second column excludes pixels within 1 px of directly
    visible emitters (renderer.emitter_edge_mask).  References: veach-ajar and cornell-box =
    TungstenRender.exr box-downsampled 4x; door-ajar = results/door-ajar-reference.exr (Mitsuba
    3.9.1 llvm_ad_rgb path, max_depth 13, 320x180, 8192 spp = 128 passes x 64 spp with seeds
    0..127, averaged in float64; `--make-door-reference`).
  - Each measurement waits until the machine is otherwise idle: 1-min load average < 1.5, or
    (because our own previous run keeps the 1-min average up for a minute) the whole machine's
    CPU use over a 5-s window < 15 % of all cores. Waits are logged. During each run the CPU
    time of *other* processes is estimated (/proc/stat busy time minus our process' CPU time)
    and stored ("other_cpu_s"; for pathfarm it includes its own scene loading, ~1.5-2 CPU-s on
    veach-ajar, which is not part of the summary's render-phase cpu_s). Runs with other_cpu_s > 3
    are contaminated: move them out of guided.jsonl and re-run with --resume.
  - cornell-box (whose target is a ratio to pathfarm path of at most 1.10, smaller than the
    10-20 % by which throughput drifts between consecutive runs on shared machines): each guided
    configuration runs at the same time as a pathfarm path run with the same seed, both
    single-threaded (`--threads 1 --time budget`), pinned to one core each with taskset, cores
    swapped every repetition. The target line gives the median of these paired ratios; the
    path rows carry "partner_of". `--no-pair-cornell` runs them one after another as above.
  - Repetitions use different seeds; the table shows medians over repetitions.
Raw results: results/guided.jsonl (one line per run); table: results/guided.md; images:
results/renders/guided-*.exr/.png (git-ignored).
"""
import argparse
import json
import os
import re
import shutil
import statistics
import subprocess
import sys
import tempfile
import time

import numpy as np

HERE = os.path.dirname(os.path.abspath(__file__))
sys.path.insert(0, HERE)
import renderer as R  # noqa: E402  (load_image, reference, relmse, emitter_edge_mask, SUMMARY_RE)

SHARED = R.SHARED
PROJECT_SCENES = os.path.normpath(os.path.join(HERE, "..", "scenes"))
RESULTS = os.path.join(HERE, "results")
DOOR_REF = os.path.join(RESULTS, "door-ajar-reference.exr")
# name: (xml, resx, resy, max_depth, reference)
SCENES = {
    "veach-ajar": (os.path.join(SHARED, "veach-ajar", "scene.xml"), 320, 180, 13, "tungsten"),
    "cornell-box": (os.path.join(SHARED, "cornell-box", "scene.xml"), 256, 256, 30, "tungsten"),
    "door-ajar": (os.path.join(PROJECT_SCENES, "door-ajar", "scene.xml"), 320, 180, 13, DOOR_REF),
}
CONFIGS = ["pf-path", "pf-2017", "pf-2019", "pf-pathfarm", "mi-path"]
LABEL = {"pf-path": "pathfarm path", "pf-2017": "pathfarm guided 2017", "pf-2019": "pathfarm guided 2019",
         "pf-pathfarm": "pathfarm guided (preset pathfarm = 2019 + guided RR from depth 3 + splitting + path fallback + cosine-weighted hemisphere + light splitting)",
         "mi-path": "Mitsuba 3 path (llvm_ad_rgb)"}
# Default plan: which configs per scene and budget (cornell-box only at the smallest budget).
PLAN = {"veach-ajar": CONFIGS, "cornell-box": ["pf-path", "pf-2019", "pf-pathfarm", "mi-path"], "door-ajar": CONFIGS}
ANSI = re.compile(r"\x1b\[[0-9;]*m")
GUIDED_RE = re.compile(r"guided: training_fraction=([\d.eE+-]+) tree_memory_mb=([\d.eE+-]+) weights=\[([^\]]*)\]")
FALLBACK_RE = re.compile(r"path_fallback=after_iteration_(\d+)")
ITER_RE = re.compile(r"iteration (\d+): spp=(\d+) nodes=(\d+) leaves=(\d+) variance=([\d.eE+-]+|NaN|inf) time=([\d.]+)s")


def log(msg):
    print("[%s] %s" % (time.strftime("%H:%M:%S", time.gmtime()), msg), file=sys.stderr, flush=True)


# ----------------------------------------------------------------------------------------------
# idle check / other-load accounting
# ----------------------------------------------------------------------------------------------
def cpu_busy_s():
    """Busy CPU seconds of the whole machine since boot (all cores), from /proc/stat."""
    with open("/proc/stat") as f:
        v = [int(x) for x in f.readline().split()[1:]]
    idle = v[3] + v[4]
    return (sum(v[:8]) - idle) / os.sysconf("SC_CLK_TCK")


def wait_idle(max_load=1.5, max_busy=0.15):
    t0 = time.time()
    n = os.cpu_count()
    while True:
        l1 = os.getloadavg()[0]
        if l1 < max_load:
            how = "load1=%.2f" % l1
            break
        b0 = cpu_busy_s()
        time.sleep(5)
        busy = (cpu_busy_s() - b0) / (5 * n)
        if busy < max_busy:
            how = "load1=%.2f (our previous run), machine busy %.0f %% over 5 s" % (l1, 100 * busy)
            break
    waited = time.time() - t0
    if waited > 5:
        log("waited %.0f s for an idle machine (%s)" % (waited, how))
    return waited


# ----------------------------------------------------------------------------------------------
# pathfarm
# ----------------------------------------------------------------------------------------------
def guided_wrapper(xml, preset, tmp):
    """Write tmp/<preset>/scene.xml = xml with its <integrator> block replaced by guided_path."""
    d = os.path.join(tmp, "%s-%s" % (os.path.basename(os.path.dirname(xml)), preset))
    if os.path.exists(os.path.join(d, "scene.xml")):
        return os.path.join(d, "scene.xml")
    os.makedirs(d, exist_ok=True)
    src_dir = os.path.dirname(os.path.abspath(xml))
    for e in os.listdir(src_dir):
        if e != os.path.basename(xml):
            os.symlink(os.path.join(src_dir, e), os.path.join(d, e))
    text = open(xml).read()
    block = ('<integrator type="guided_path">\n\t\t<string name="preset" value="%s" />\n'
             '\t\t<integer name="max_depth" value="$max_depth" />\n\t</integrator>' % preset)
    new, n = re.subn(r"<integrator\b.*?</integrator>", block, text, count=1, flags=re.S)
    if n != 1:
        raise RuntimeError("no <integrator> block in %s" % xml)
    with open(os.path.join(d, "scene.xml"), "w") as f:
        f.write(new)
    return os.path.join(d, "scene.xml")


def pathfarm_args(a, xml, res, md, out, tlimit, seed, integrator=None, threads=None, cpu=None):
    threads = threads or a.threads
    args = [a.pathfarm, "render", xml, "-o", out, "--seed", str(seed), "--threads", str(threads),
            "--time", "%.3f" % tlimit,
            "-D", "resx=%d" % res[0], "-D", "resy=%d" % res[1], "-D", "max_depth=%d" % md]
    if integrator:
        args += ["-D", "integrator=%s" % integrator]
    return (["taskset", "-c", str(cpu)] if cpu is not None else []) + args


def parse_pathfarm(args, p_returncode, stdout, stderr):
    """The result record of one finished `pathfarm render` (summary and guided lines)."""
    if p_returncode != 0:
        raise RuntimeError("pathfarm failed (%d): %s\n%s" % (p_returncode, " ".join(args), stderr[-2000:]))
    m = None
    for line in stdout.splitlines():
        m = R.SUMMARY_RE.search(line) or m
    if not m:
        raise RuntimeError("no summary line in pathfarm output:\n" + stdout[-2000:])
    w, h, spp, wall, cpu, _ = m.groups()
    r = {"spp": int(spp), "wall_s": float(wall), "cpu_s": float(cpu), "cmd": " ".join(args)}
    err = ANSI.sub("", stderr)
    g = GUIDED_RE.search(err)
    if g:
        r["training_fraction"] = float(g.group(1))
        r["tree_memory_mb"] = float(g.group(2))
        r["weights"] = [float(x) for x in g.group(3).split(",") if x.strip()]
        r["iterations"] = [{"index": int(i), "spp": int(s), "nodes": int(n), "leaves": int(l),
                            "variance": float(v), "seconds": float(t)} for i, s, n, l, v, t in ITER_RE.findall(err)]
        r["final_spp"] = r["iterations"][-1]["spp"] if r["iterations"] else None
        fb = FALLBACK_RE.search(err)
        r["path_fallback"] = fb.group(1) if fb else "no"
    return r


def run_pathfarm(a, xml, res, md, out, tlimit, seed, integrator=None):
    args = pathfarm_args(a, xml, res, md, out, tlimit, seed, integrator)
    b0, c0 = cpu_busy_s(), time.time()
    p = subprocess.run(args, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    busy = cpu_busy_s() - b0
    r = parse_pathfarm(args, p.returncode, p.stdout, p.stderr)
    r.update({"other_cpu_s": max(0.0, busy - r["cpu_s"]), "elapsed_s": time.time() - c0})
    return r


def run_pathfarm_pair(a, jobs, budget):
    """Runs two `pathfarm render`s at the same time, single-threaded, one pinned to each core,
    each with the whole CPU-second budget as its wall-clock limit: both see the same machine
    (consecutive runs differ by 10-20 % in throughput on shared machines, which is the size of
    the Cornell target). jobs = [(xml, res, md, out, seed, integrator, cpu)] x 2."""
    procs = []
    b0, c0 = cpu_busy_s(), time.time()
    for xml, res, md, out, seed, integ, cpu in jobs:
        args = pathfarm_args(a, xml, res, md, out, budget, seed, integ, threads=1, cpu=cpu)
        procs.append((args, subprocess.Popen(args, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)))
    outs = [(args, p.communicate(), p.returncode) for args, p in procs]
    busy = cpu_busy_s() - b0
    rs = [parse_pathfarm(args, rc, o, e) for args, (o, e), rc in outs]
    other = max(0.0, busy - sum(r["cpu_s"] for r in rs))
    for r, job in zip(rs, jobs):
        r.update({"other_cpu_s": other, "elapsed_s": time.time() - c0, "threads": 1, "cpu": job[6]})
    return rs


# ----------------------------------------------------------------------------------------------
# Mitsuba (subprocess per run)
# ----------------------------------------------------------------------------------------------
def mitsuba_worker(a):
    import mitsuba as mi
    mi.set_variant("llvm_ad_rgb")
    scene = mi.load_file(a.scene, resx=a.res[0], resy=a.res[1], max_depth=a.max_depth, integrator="path")
    pixels = a.res[0] * a.res[1]
    render, pass_spp = R.mitsuba_renderer(mi, scene, a.res, a.seed)

    render(min(pass_spp, 4))                      # warm-up (JIT)
    _, cpu, _ = render(pass_spp)                  # probe
    rate_spp = max(1, int(round(a.rate_cpu * pixels * pass_spp / max(cpu, 1e-6) / pixels)))
    rates = []
    for _ in range(3):
        _, cpu, _ = render(rate_spp)
        rates.append(pixels * rate_spp / max(cpu, 1e-9))
    rate = statistics.median(rates)
    spp = max(1, int(round(a.budget * rate / pixels)))
    print("EQUAL " + json.dumps({"rate": rate, "spp": spp}), flush=True)   # parent starts idle accounting
    img, cpu, wall = render(spp)
    np.save(a.out, img.astype(np.float32))
    bmp = mi.Bitmap(img.astype(np.float32), pixel_format=mi.Bitmap.PixelFormat.RGB)
    bmp.convert(mi.Bitmap.PixelFormat.RGB, mi.Struct.Type.UInt8, srgb_gamma=True).write(a.out[:-4] + ".png")
    print("RESULT " + json.dumps({"rate": rate, "rates": rates, "spp": spp, "cpu_s": cpu, "wall_s": wall}), flush=True)


def mitsuba_preflight():
    """Stops the benchmark before its first run if Mitsuba's llvm_ad_rgb cannot render here.

    With only libLLVM 14/15 installed, Dr.Jit loads one of those and every render dies in
    LLVM's instruction selection ("Cannot select ... fminimum"), which would leave the table
    without its reference column after an hour of pathfarm runs.
    """
    code = ("import mitsuba as mi\nmi.set_variant('llvm_ad_rgb')\n"
            "mi.render(mi.load_dict(mi.cornell_box()), spp=1)\n")
    p = subprocess.run([sys.executable, "-c", code], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    if p.returncode != 0:
        raise SystemExit("Mitsuba llvm_ad_rgb cannot render on this machine (install Debian's libllvm19: "
                         "`apt-get install libllvm19`):\n" + p.stderr[-1500:])


def run_mitsuba(a, xml, res, md, out, budget, seed):
    args = [sys.executable, os.path.abspath(__file__), "_mitsuba_worker", "--scene", xml,
            "--res", str(res[0]), str(res[1]), "--max-depth", str(md), "--rate-cpu", str(a.rate_cpu),
            "--budget", str(budget), "--seed", str(seed), "--out", out]
    c0 = time.time()
    p = subprocess.Popen(args, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    b0 = None
    res_ = None
    for line in p.stdout:
        if line.startswith("EQUAL "):
            b0 = cpu_busy_s()
        elif line.startswith("RESULT "):
            busy = cpu_busy_s() - b0 if b0 is not None else float("nan")
            res_ = json.loads(line[7:])
    err = p.stderr.read()
    p.wait()
    if p.returncode != 0 or res_ is None:
        raise RuntimeError("mitsuba worker failed:\n%s" % err[-3000:])
    res_["other_cpu_s"] = max(0.0, busy - res_["cpu_s"])
    res_["elapsed_s"] = time.time() - c0
    res_["cmd"] = " ".join(args)
    return res_


# ----------------------------------------------------------------------------------------------
def load_reference(name):
    xml, rx, ry, md, ref = SCENES[name]
    if ref == "tungsten":
        return R.reference(xml, (rx, ry))
    if not os.path.exists(ref):
        raise RuntimeError("missing %s (run guided.py --make-door-reference)" % ref)
    return R.load_image(ref)


def make_door_reference(spp=8192, pass_spp=64):
    import mitsuba as mi
    mi.set_variant("llvm_ad_rgb")
    xml, rx, ry, md, out = SCENES["door-ajar"]
    scene = mi.load_file(xml, resx=rx, resy=ry, max_depth=md, integrator="path")
    acc, n, t0 = None, spp // pass_spp, time.time()
    for i in range(n):
        arr = np.array(mi.render(scene, spp=pass_spp, seed=i), dtype=np.float64)[..., :3]
        acc = arr if acc is None else acc + arr
        if i % 8 == 0 or i == n - 1:
            log("door-ajar reference: pass %d/%d (%d spp) %.0f s" % (i + 1, n, pass_spp, time.time() - t0))
    mi.Bitmap((acc / n).astype(np.float32)).write(out)
    log("wrote %s" % out)


def fmt(x, f="%.4g"):
    return "-" if x is None or (isinstance(x, float) and x != x) else f % x


def med(rows, key):
    v = [r[key] for r in rows if r.get(key) is not None]
    return statistics.median(v) if v else None


def write_table(a):
    path = os.path.join(RESULTS, "guided.jsonl")
    rows = [json.loads(l) for l in open(path)] if os.path.exists(path) else []
    groups = {}
    for r in rows:
        groups.setdefault((r["scene"], r["budget"], r["config"]), []).append(r)
    order = {s: i for i, s in enumerate(SCENES)}
    keys = sorted(groups, key=lambda k: (order.get(k[0], 99), k[1], CONFIGS.index(k[2])))
    lines = ["# Path-guiding benchmark", "",
             "%s; pathfarm `--threads %d --time budget/%d` (wall-clock, so a 30 CPU-s budget is `--time %g`, 120 CPU-s is "
             "`--time %g`); Mitsuba 3.9.1 `llvm_ad_rgb` `path` with spp = budget x its measured samples/CPU-s; %d CPUs. "
             "Medians over repetitions (n = reps, different seeds)."
             % (time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime()), a.threads, a.threads, 30 / a.threads,
                120 / a.threads, os.cpu_count()),
             "",
             "relMSE = mean((x-ref)^2/(ref^2+1e-2)); references: veach-ajar / cornell-box = Tungsten box-downsampled 4x, "
             "door-ajar = `results/door-ajar-reference.exr` (Mitsuba path, 8192 spp). \"excl. edges\" excludes pixels within "
             "1 px of directly visible emitters (only cornell-box has any); the ratio vs Mitsuba uses that column. "
             "spp = total spp (guided: training + final), final = spp of the last iteration. "
             "other CPU-s = CPU time of other processes during the run (should be ~0). "
             "fallback = runs (of n) in which the path fallback rendered the rest as plain path tracing.",
             ""]
    if any(r.get("partner_of") for r in rows):
        lines += ["cornell-box: each guided run was made at the same time as a path run (same seed, `--threads 1 "
                  "--time budget` each, one core each, cores swapped per repetition); the path row holds all of "
                  "them, and the target lines use the per-pair ratios.", ""]
    lines += [
             "| scene | budget CPU-s | renderer | relMSE | relMSE excl. edges | ratio vs Mitsuba path | spp (final) | CPU-s used | "
             "training fraction | tree MB | fallback | n | other CPU-s (max) |",
             "|---|---:|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|"]
    meds = {}
    for k in keys:
        g = groups[k]
        meds[k] = {key: med(g, key) for key in ("relmse", "relmse_masked", "spp", "final_spp", "cpu_s",
                                                 "training_fraction", "tree_memory_mb")}
        meds[k]["n"] = len(g)
        meds[k]["other"] = max(r.get("other_cpu_s", 0) or 0 for r in g)
        fbs = [r for r in g if r.get("path_fallback", "no") != "no"]
        meds[k]["fallback"] = ("%d" % len(fbs)) if "training_fraction" in g[0] else "-"
        meds[k]["all"] = [r["relmse_masked"] for r in g]
    for k in keys:
        m = meds[k]
        mi_ = meds.get((k[0], k[1], "mi-path"))
        ratio = m["relmse_masked"] / mi_["relmse_masked"] if mi_ and mi_["relmse_masked"] else None
        spp = fmt(m["spp"], "%d") + (" (%s)" % fmt(m["final_spp"], "%d") if m["final_spp"] is not None else "")
        lines.append("| %s | %g | %s | %s | %s | %s | %s | %s | %s | %s | %s | %d | %s |" % (
            k[0], k[1], LABEL[k[2]], fmt(m["relmse"]), fmt(m["relmse_masked"]), fmt(ratio, "%.3f"), spp,
            fmt(m["cpu_s"], "%.1f"), fmt(m["training_fraction"], "%.3f"), fmt(m["tree_memory_mb"], "%.2f"),
            m["fallback"], m["n"], fmt(m["other"], "%.1f")))
    lines += ["", "## Targets", ""]
    targets = [(b, gc, gl) for b in sorted({k[1] for k in keys})
               for gc, gl in (("pf-2019", "guided 2019"), ("pf-pathfarm", "guided pathfarm"))]
    for b, gc, gl in targets:
        g, mi_ = meds.get(("veach-ajar", b, gc)), meds.get(("veach-ajar", b, "mi-path"))
        if g and mi_:
            f = mi_["relmse_masked"] / g["relmse_masked"]
            lines.append("- veach-ajar @ %g CPU-s: Mitsuba path relMSE / %s relMSE = %.2f (target >= 5: %s%s)."
                         % (b, gl, f, "met" if f >= 5 else "MISSED", "" if f >= 5 else
                            "; %s is %.2fx *higher*" % (gl, 1 / f) if f < 1 else ", %.1fx short" % (5 / f)))
        pairs = [(r, p) for r in groups.get(("cornell-box", b, gc), [])
                 for p in groups.get(("cornell-box", b, "pf-path"), [])
                 if p.get("partner_of") == gc and p["rep"] == r["rep"]]
        g, p = meds.get(("cornell-box", b, gc)), meds.get(("cornell-box", b, "pf-path"))
        if pairs:
            # Runs made side by side: the median of the per-pair ratios.
            f1 = statistics.median(r["relmse_masked"] / p["relmse_masked"] for r, p in pairs)
            f0 = statistics.median(r["relmse"] / p["relmse"] for r, p in pairs)
            lines.append("- cornell-box @ %g CPU-s: %s / pathfarm path relMSE = %.3f excl. emitter edges, %.3f plain "
                         "(target <= 1.10: %s); median of %d ratios of runs made side by side: %s; spp guided / "
                         "path: %s." % (b, gl, f1, f0, "met" if f1 <= 1.10 else "MISSED", len(pairs),
                                        ", ".join("%.3f" % (r["relmse_masked"] / p["relmse_masked"]) for r, p in pairs),
                                        ", ".join("%d/%d" % (r["spp"], p["spp"]) for r, p in pairs)))
        elif g and p:
            f1 = g["relmse_masked"] / p["relmse_masked"]
            f0 = g["relmse"] / p["relmse"]
            lines.append("- cornell-box @ %g CPU-s: %s / pathfarm path relMSE = %.3f excl. emitter edges, %.3f plain "
                         "(target <= 1.10: %s)." % (b, gl, f1, f0, "met" if f1 <= 1.10 else "MISSED"))
    lines += ["", "Per-repetition relMSE (excl. edges):", ""]
    for k in keys:
        lines.append("- %s %g %s: %s" % (k[0], k[1], k[2], ", ".join("%.4g" % x for x in meds[k]["all"])))
    text = "\n".join(lines) + "\n"
    with open(a.out, "w") as f:
        f.write(text)
    return text


def contact_sheets(a):
    """results/renders/guided-sheet-<scene>-<budget>.png: repetition 0 of every config side by side
    (order pf-path, pf-2017, pf-2019, pf-pathfarm, mi-path; reference last), sRGB, no exposure change."""
    import mitsuba as mi
    if not mi.variant():
        mi.set_variant("scalar_rgb")
    path = os.path.join(RESULTS, "guided.jsonl")
    rows = [json.loads(l) for l in open(path)] if os.path.exists(path) else []
    for name, b in sorted({(r["scene"], r["budget"]) for r in rows}):
        ims = []
        for c in CONFIGS:
            stem = os.path.join(a.workdir, "guided-%s-%g-%s-r0" % (name, b, c))
            for ext in (".exr", ".npy"):
                if os.path.exists(stem + ext):
                    ims.append(R.load_image(stem + ext))
        if not ims:
            continue
        ims.append(load_reference(name))
        sheet = np.concatenate([np.pad(x, ((0, 0), (0, 4), (0, 0))) for x in ims], 1).astype(np.float32)
        bmp = mi.Bitmap(sheet, pixel_format=mi.Bitmap.PixelFormat.RGB)
        bmp.convert(mi.Bitmap.PixelFormat.RGB, mi.Struct.Type.UInt8, srgb_gamma=True).write(
            os.path.join(a.workdir, "guided-sheet-%s-%g.png" % (name, b)))


# Colours and markers of the curves (one per configuration).
STYLE = {"pf-path": ("#1f77b4", "path"), "pf-2017": ("#9467bd", "guided 2017"),
         "pf-2019": ("#d62728", "guided 2019"), "pf-pathfarm": ("#2ca02c", "guided pathfarm"),
         "mi-path": ("#555555", "Mitsuba path")}


def write_curves(a):
    """results/guided-curves.svg: relMSE (excl. emitter edges) against CPU seconds, log-log, one
    panel per scene: a line through each configuration's medians, its repetitions as dots.
    Written without a plotting library (plain SVG), so it needs nothing beyond the benchmark."""
    import math
    path = os.path.join(RESULTS, "guided.jsonl")
    rows = [json.loads(l) for l in open(path)] if os.path.exists(path) else []
    scenes = [s for s in SCENES if any(r["scene"] == s for r in rows)]
    if not rows or not scenes:
        return None
    W, H, ML, MR, MT, MB = 430, 330, 62, 14, 30, 46
    out = ['<svg xmlns="http://www.w3.org/2000/svg" width="%d" height="%d" font-family="sans-serif" '
           'font-size="11">' % (W * len(scenes), H + 24), '<rect width="100%" height="100%" fill="white"/>']
    for si, scene in enumerate(scenes):
        rs = [r for r in rows if r["scene"] == scene and r.get("relmse_masked")]
        xs = [r["budget"] for r in rs]
        ys = [r["relmse_masked"] for r in rs]
        x0, x1 = math.log10(min(xs)) - 0.08, math.log10(max(xs)) + 0.08
        y0, y1 = math.floor(math.log10(min(ys)) * 4) / 4, math.ceil(math.log10(max(ys)) * 4) / 4
        if x1 - x0 < 0.3:
            x0, x1 = x0 - 0.15, x1 + 0.15
        if y1 - y0 < 0.5:
            y0, y1 = y0 - 0.25, y1 + 0.25
        ox = si * W

        def px(x):
            return ox + ML + (math.log10(x) - x0) / (x1 - x0) * (W - ML - MR)

        def py(y):
            return MT + (y1 - math.log10(y)) / (y1 - y0) * (H - MT - MB)
        out.append('<text x="%g" y="18" font-size="13" font-weight="bold">%s</text>' % (ox + ML, scene))
        out.append('<rect x="%g" y="%g" width="%g" height="%g" fill="none" stroke="#999"/>'
                   % (ox + ML, MT, W - ML - MR, H - MT - MB))
        for e in range(int(math.floor(y0)), int(math.ceil(y1)) + 1):
            for m in (1, 2, 3, 5):
                v = m * 10.0 ** e
                if y0 <= math.log10(v) <= y1:
                    out.append('<line x1="%g" x2="%g" y1="%g" y2="%g" stroke="#eee"/>'
                               % (ox + ML, ox + W - MR, py(v), py(v)))
                    out.append('<text x="%g" y="%g" text-anchor="end">%g</text>' % (ox + ML - 4, py(v) + 4, v))
        for b in sorted(set(xs)):
            out.append('<line x1="%g" x2="%g" y1="%g" y2="%g" stroke="#eee"/>' % (px(b), px(b), MT, H - MB))
            out.append('<text x="%g" y="%g" text-anchor="middle">%g</text>' % (px(b), H - MB + 14, b))
        out.append('<text x="%g" y="%g" text-anchor="middle">CPU seconds (equal time)</text>'
                   % (ox + (ML + W - MR) / 2, H - 8))
        out.append('<text x="%g" y="%g" text-anchor="middle" transform="rotate(-90 %g %g)">relMSE</text>'
                   % (ox + 14, (MT + H - MB) / 2, ox + 14, (MT + H - MB) / 2))
        present = [c for c in CONFIGS if any(r["config"] == c for r in rs)]
        for ci, c in enumerate(present):
            cr = [r for r in rs if r["config"] == c]
            colour, label = STYLE[c]
            for r in cr:
                out.append('<circle cx="%.1f" cy="%.1f" r="2" fill="%s" fill-opacity="0.35"/>'
                           % (px(r["budget"]), py(r["relmse_masked"]), colour))
            pts = [(b, statistics.median(r["relmse_masked"] for r in cr if r["budget"] == b))
                   for b in sorted({r["budget"] for r in cr})]
            out.append('<polyline fill="none" stroke="%s" stroke-width="2" points="%s"/>'
                       % (colour, " ".join("%.1f,%.1f" % (px(b), py(y)) for b, y in pts)))
            for b, y in pts:
                out.append('<circle cx="%.1f" cy="%.1f" r="3.5" fill="%s"/>' % (px(b), py(y), colour))
            # legend in the lower left corner, where falling curves are not
            ly = H - MB - 8 - 14 * (len(present) - 1 - ci)
            out.append('<line x1="%g" x2="%g" y1="%g" y2="%g" stroke="%s" stroke-width="2"/>'
                       % (ox + ML + 8, ox + ML + 26, ly - 4, ly - 4, colour))
            out.append('<text x="%g" y="%g">%s</text>' % (ox + ML + 30, ly, label))
    out.append('<text x="6" y="%d" fill="#555">relMSE (excl. emitter edges) vs equal CPU time; lines: medians '
               'over repetitions, dots: single runs. Made by bench/guided.py from results/guided.jsonl.</text>'
               % (H + 16))
    out.append("</svg>")
    svg = os.path.join(os.path.dirname(a.out), "guided-curves.svg")
    with open(svg, "w") as f:
        f.write("\n".join(out) + "\n")
    return svg


def main():
    if len(sys.argv) > 1 and sys.argv[1] == "_mitsuba_worker":
        ap = argparse.ArgumentParser()
        ap.add_argument("_w")
        ap.add_argument("--scene", required=True)
        ap.add_argument("--res", type=int, nargs=2, required=True)
        ap.add_argument("--max-depth", type=int, required=True)
        ap.add_argument("--rate-cpu", type=float, default=3.0)
        ap.add_argument("--budget", type=float, required=True)
        ap.add_argument("--seed", type=int, default=1000)
        ap.add_argument("--out", required=True)
        return mitsuba_worker(ap.parse_args())

    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--pathfarm", default=os.path.join(HERE, "..", "target", "release", "pathfarm"))
    ap.add_argument("--budgets", type=float, nargs="+", default=[30, 120], help="CPU-second budgets")
    ap.add_argument("--reps", type=int, default=3)
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--rate-cpu", type=float, default=3.0, help="CPU-s of each Mitsuba throughput render")
    ap.add_argument("--scenes", nargs="+", default=list(SCENES))
    ap.add_argument("--configs", nargs="+", default=CONFIGS)
    ap.add_argument("--cornell-all-budgets", action="store_true", help="also run cornell-box at budgets > the smallest")
    ap.add_argument("--resume", action="store_true", help="keep results/guided.jsonl and skip runs already in it")
    ap.add_argument("--table-only", action="store_true")
    ap.add_argument("--no-pair-cornell", dest="pair_cornell", action="store_false",
                    help="run cornell-box's path and guided configurations one after another (default: each "
                         "guided configuration at the same time as a path run, one core each)")
    ap.add_argument("--no-wait", action="store_true", help="do not wait for an idle machine (testing only)")
    ap.add_argument("--make-door-reference", action="store_true")
    ap.add_argument("--workdir", default=os.path.join(RESULTS, "renders"))
    ap.add_argument("--out", default=os.path.join(RESULTS, "guided.md"))
    a = ap.parse_args()
    if a.make_door_reference:
        return make_door_reference()
    if a.table_only:
        contact_sheets(a)
        print(write_table(a))
        log("curves: %s" % write_curves(a))
        return 0
    os.makedirs(a.workdir, exist_ok=True)
    jl = os.path.join(RESULTS, "guided.jsonl")
    done = set()
    if a.resume and os.path.exists(jl):
        for l in open(jl):
            r = json.loads(l)
            # (a path run beside a guided one is done with its guided partner)
            done.add((r["scene"], r["budget"], r["config"], r["rep"], r.get("partner_of", "")))
    elif os.path.exists(jl):
        os.rename(jl, jl + ".old")
    import hashlib
    binary_sha = hashlib.sha256(open(a.pathfarm, "rb").read()).hexdigest()[:16]
    log("pathfarm binary %s sha256 %s" % (a.pathfarm, binary_sha))
    if "mi-path" in a.configs:
        mitsuba_preflight()
    refs = {}
    tmp = tempfile.mkdtemp(prefix="pathfarm-guided-")
    t_start = time.time()
    try:
        for b in a.budgets:
            for rep in range(a.reps):
                for name in a.scenes:
                    if name == "cornell-box" and b != min(a.budgets) and not a.cornell_all_budgets:
                        continue
                    xml, rx, ry, md, _ = SCENES[name]
                    res = (rx, ry)
                    if name not in refs:
                        ref = load_reference(name)
                        refs[name] = (ref, R.emitter_edge_mask(ref))
                    ref, mask = refs[name]
                    for c in PLAN[name]:
                        paired = a.pair_cornell and name == "cornell-box" and "pf-path" in a.configs
                        if paired and c == "pf-path":
                            continue  # runs beside each guided configuration (below)
                        if c not in a.configs or (name, b, c, rep, "") in done:
                            continue
                        stem = os.path.join(a.workdir, "guided-%s-%g-%s-r%d" % (name, b, c, rep))
                        if not a.no_wait:
                            wait_idle()
                        t0 = time.time()
                        runs = []  # (record, image path, partner_of)
                        try:
                            if c == "mi-path":
                                r = run_mitsuba(a, xml, res, md, stem + ".npy", b, seed=100000 * (rep + 1))
                                runs.append((r, stem + ".npy", None))
                            elif paired:
                                # Guided and path at the same time, one core each; the cores
                                # swap every repetition.
                                cpus = (0, 1) if rep % 2 == 0 else (1, 0)
                                gx = guided_wrapper(xml, c[3:], tmp)
                                rg, rp = run_pathfarm_pair(a, [
                                    (gx, res, md, stem + ".exr", 100 + rep, None, cpus[0]),
                                    (xml, res, md, stem + "-path.exr", 100 + rep, "path", cpus[1])], b)
                                runs += [(rg, stem + ".exr", None), (rp, stem + "-path.exr", c)]
                            else:
                                if c == "pf-path":
                                    x, integ = xml, "path"
                                else:
                                    x, integ = guided_wrapper(xml, c[3:], tmp), None
                                r = run_pathfarm(a, x, res, md, stem + ".exr", b / a.threads, seed=100 + rep,
                                                 integrator=integ)
                                runs.append((r, stem + ".exr", None))
                        except Exception as e:
                            log("[%s %g %s r%d] ERROR %s" % (name, b, c, rep, str(e)[:500]))
                            continue
                        for r, img_path, partner_of in runs:
                            img = R.load_image(img_path)
                            cfg = "pf-path" if partner_of else c
                            r.update({"scene": name, "budget": b, "config": cfg, "rep": rep,
                                      "relmse": R.relmse(img, ref), "relmse_masked": R.relmse(img, ref, mask),
                                      "mean_rgb": [float(x) for x in img.reshape(-1, 3).mean(0)],
                                      "ref_mean_rgb": [float(x) for x in ref.reshape(-1, 3).mean(0)],
                                      "time_utc": time.strftime("%H:%M:%S", time.gmtime()),
                                      "pathfarm_sha256": binary_sha})
                            if partner_of:
                                r["partner_of"] = partner_of
                            with open(jl, "a") as f:
                                f.write(json.dumps(r) + "\n")
                            log("[%s %g %s%s r%d] %.0fs: relMSE %.4g (excl. edges %.4g) spp %s cpu %.1f%s other %.1f"
                                % (name, b, cfg, " (beside %s)" % partner_of if partner_of else "", rep,
                                   time.time() - t0, r["relmse"], r["relmse_masked"], r["spp"], r["cpu_s"],
                                   " train %.3f tree %.2f MB" % (r["training_fraction"], r["tree_memory_mb"])
                                   if "training_fraction" in r else "", r.get("other_cpu_s", 0)))
                write_table(a)
                write_curves(a)
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    log("total %.0f s" % (time.time() - t_start))
    contact_sheets(a)
    print(write_table(a))
    log("curves: %s" % write_curves(a))
    return 0


if __name__ == "__main__":
    sys.exit(main())
