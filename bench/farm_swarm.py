#!/usr/bin/env python3
"""The coordinator's central work at many workers: simulated workers driving the real
coordinator.

Usage:
  python3 bench/farm_swarm.py [--workers 8,64,256] [--res 1920x1080] [--spp 256]
                              [--seconds-per-sample auto] [--binary target/release/pathfarm]
                              [--out bench/results/farm-swarm.md]

For each worker count N: one `pathfarm coordinator` process and one process of N workers
(`pathfarm worker --instances N --simulate-seconds-per-sample S`). Each simulated worker
is the shipped worker: it registers on its own control stream, takes leases, fetches the
scene and every tree, fraction table and estimate, builds the scene, keeps its tree copy,
takes its statistics, uploads its tiles jointly and hands in its records. Only the render
is simulated: a sleep of S seconds a sample (a tile's real time on one core of this
machine), then zero radiance of the tile's real size and form. So every upload, merge,
unit end, refinement, checkpoint and broadcast is the real coordinator's real work, at the
real sizes of the pixels; what a zero image does not give is a trained tree: the guide
learns nothing, so its statistics and trees stay small (the module `docs/farm-performance.md`
adds their measured cost from real runs).

S (`auto`): measured first by `pathfarm render` of veach-ajar at 320x180, 32 spp, guided_path,
one thread: the render's seconds in its iterations over its samples.

The job: scenes/cornell-box (a small scene to build 256 times in one process) at --res,
--spp, guided_path, seed 1, submitted with `pathfarm submit --wait`.

Reported per N: the job's wall seconds (submit to result); the rendering a worker did
(the simulated seconds of all tiles, from the coordinator's `unit finished` lines, over
N): the wall time of a perfect farm; the share of wall time that is not rendering
(1 - rendering / wall: the central work and every wait on it, start-up included); the
coordinator's CPU seconds and their share of the wall; the bytes the coordinator sent
per worker. Target (issue 46): under 10 % at 64 workers on a 1920x1080 job.

On this 2-core machine the coordinator shares the cores with the simulated workers (their
gRPC, hashing and encoding of zero pixels, their bookkeeping); they run at niceness 10 so
the coordinator is served first, as on a machine of its own. Quote the CPU (printed).
"""
import argparse
import os
import re
import shutil
import signal
import subprocess
import sys
import tempfile
import time

from farm import ANSI, cpu_name, free_port, parse_units  # this directory's farm benchmark
from farm_load import counter, proc_cpu_seconds, report, scrape

HERE = os.path.dirname(os.path.abspath(__file__))
ROOT = os.path.normpath(os.path.join(HERE, ".."))
SHARED = os.path.normpath(os.path.join(ROOT, "..", "shared", "scenes"))
TOKEN = "farm-swarm-token"
ITER_RE = re.compile(r"iteration (\d+): spp=\d+ .* time=([\d.]+)s")


def calibrate(binary, tmp):
    """Seconds a sample of veach-ajar 320x180 with guided_path on one thread."""
    out = os.path.join(tmp, "calibrate.exr")
    env = dict(os.environ, RUST_LOG="info", NO_COLOR="1")
    w, h, spp = 320, 180, 32
    p = subprocess.run([binary, "render", os.path.join(SHARED, "veach-ajar", "scene.xml"), "-D",
                        "integrator=guided_path", "-D", f"resx={w}", "-D", f"resy={h}", "--spp",
                        str(spp), "--threads", "1", "--no-png", "-o", out],
                       env=env, capture_output=True, text=True, check=True)
    secs = sum(float(t) for _, t in ITER_RE.findall(ANSI.sub("", p.stderr)))
    if secs <= 0:
        raise SystemExit("calibration: no iteration times in the render's log")
    return secs / (w * h * spp)


def stop(proc, sig, group):
    """Sends `sig` to `proc`, or to its whole process group (the coordinator's: under a
    --coordinator-prefix command the coordinator is that command's child)."""
    try:
        if group:
            os.killpg(proc.pid, sig)
        else:
            proc.send_signal(sig)
    except ProcessLookupError:
        pass


def minor_faults(pid):
    """The process's minor page faults so far (/proc/PID/stat, field 10)."""
    return int(open(f"/proc/{pid}/stat").read().rsplit(")", 1)[1].split()[7])


def run(a, n, s, tmp):
    env = dict(os.environ, PATHFARM_TOKEN=TOKEN, NO_COLOR="1", RUST_LOG="info")
    port, mport = free_port(), free_port()
    url = f"http://127.0.0.1:{port}"
    clog_path = os.path.join(tmp, f"coord-{n}.log")
    clog = open(clog_path, "w")
    coord = subprocess.Popen(
        a.coordinator_prefix.split() + [a.binary, "coordinator", "--listen", f"127.0.0.1:{port}", "--data",
         os.path.join(tmp, f"coord-{n}"), "--metrics", f"127.0.0.1:{mport}"]
        + a.coordinator_arg,
        env=env, stderr=clog, stdout=subprocess.DEVNULL,
        start_new_session=True)  # its own group: a --coordinator-prefix command's child too
    swarm = None
    try:
        for _ in range(100):
            try:
                scrape(mport)
                break
            except OSError:
                time.sleep(0.1)
        wenv = dict(env, RUST_LOG="warn")
        swarm = subprocess.Popen(
            ["nice", "-n", "10", a.binary, "worker", "--coordinator", url, "--threads", "1",
             "--instances", str(n), "--simulate-seconds-per-sample", repr(s),
             "--cache", os.path.join(tmp, f"swarm-{n}")],
            env=wenv, stderr=open(os.path.join(tmp, f"swarm-{n}.log"), "w"),
            stdout=subprocess.DEVNULL)
        deadline = time.time() + 300
        while counter(scrape(mport), "pathfarm_workers") < n:
            if time.time() > deadline or swarm.poll() is not None:
                raise SystemExit(f"only {counter(scrape(mport), 'pathfarm_workers')} of {n} "
                                 "workers registered")
            time.sleep(0.2)
        before = scrape(mport)
        cpu0, swarm_cpu0 = proc_cpu_seconds(coord.pid), proc_cpu_seconds(swarm.pid)
        faults0 = minor_faults(coord.pid)
        w, h = a.res.split("x")
        t0 = time.time()
        p = subprocess.run(
            [a.binary, "submit", os.path.join(ROOT, "scenes", "cornell-box", "scene.xml"),
             "--coordinator", url, "-D", "integrator=guided_path", "-D", f"resx={w}", "-D",
             f"resy={h}", "--spp", str(a.spp), "--seed", "1", "--wait", "-o",
             os.path.join(tmp, f"job-{n}.exr")],
            env=env, capture_output=True, text=True, timeout=7200)
        wall = time.time() - t0
        if p.returncode != 0:
            raise SystemExit(f"the job failed:\n{p.stderr[-3000:]}")
        cpu = proc_cpu_seconds(coord.pid) - cpu0
        swarm_cpu = proc_cpu_seconds(swarm.pid) - swarm_cpu0
        faults = minor_faults(coord.pid) - faults0
        sent = counter(scrape(mport), "pathfarm_blob_bytes_sent") - counter(
            before, "pathfarm_blob_bytes_sent")
    finally:
        for proc in (swarm, coord):
            if proc is None:
                continue
            stop(proc, signal.SIGTERM, proc is coord)
            try:
                proc.wait(timeout=60)
            except subprocess.TimeoutExpired:
                stop(proc, signal.SIGKILL, proc is coord)
                proc.wait()
        clog.close()
    units = parse_units(open(clog_path).read())
    render = sum(float(u["render_s"]) for u in units)
    return {"workers": n, "wall": wall, "units": len(units), "render": render,
            "rendering_per_worker": render / n, "coordinator_cpu": cpu, "swarm_cpu": swarm_cpu,
            "faults": faults,
            "sent_per_worker": sent / n,
            "merge": sum(float(u["decode_s"]) + float(u["merge_s"]) for u in units),
            "ends": sum(float(u["end_s"]) + float(u["checkpoint_s"]) + float(u["publish_s"])
                        for u in units)}


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--workers", default="8,64,256")
    ap.add_argument("--res", default="1920x1080")
    ap.add_argument("--spp", type=int, default=256)
    ap.add_argument("--seconds-per-sample", default="auto")
    ap.add_argument("--binary", default=os.path.join(ROOT, "target", "release", "pathfarm"))
    ap.add_argument("--out", default=None)
    ap.add_argument("--coordinator-arg", action="append", default=[],
                    help="an argument for `pathfarm coordinator` (repeat for several)")
    ap.add_argument("--coordinator-prefix", default="",
                    help="a command the coordinator runs under (`perf record -g --`, say; the CPU and page-fault columns are then that command's)")
    ap.add_argument("--logs", default=None, help="keep the coordinators' and swarms' logs here")
    a = ap.parse_args()
    tmp = tempfile.mkdtemp(prefix="pathfarm-swarm-")
    rows = []
    try:
        if a.seconds_per_sample == "auto":
            s = calibrate(a.binary, tmp)
        else:
            s = float(a.seconds_per_sample)
        print(f"seconds a sample: {s:.3e}", file=sys.stderr, flush=True)
        for n in [int(x) for x in a.workers.split(",")]:
            r = run(a, n, s, tmp)
            print(r, file=sys.stderr, flush=True)
            rows.append(r)
    finally:
        if a.logs:
            os.makedirs(a.logs, exist_ok=True)
            for f in os.listdir(tmp):
                if f.endswith(".log"):
                    shutil.copy(os.path.join(tmp, f), a.logs)
        shutil.rmtree(tmp, ignore_errors=True)
    lines = [
        f"CPU: {cpu_name()}, {os.cpu_count()} logical cores. One job: scenes/cornell-box "
        f"{a.res}, {a.spp} spp, guided_path; simulated workers of {s * 1e6:.2f} us a sample "
        "(veach-ajar's on this machine, one thread).",
        "",
        "| workers | wall s | units | rendering a worker s | not rendering | coordinator CPU s "
        "(share of wall) | simulated workers' CPU s | decode + merge s | unit ends, checkpoints, publish s | "
        "MB sent a worker | coordinator page faults (thousands) |",
        "|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for r in rows:
        lines.append(
            f"| {r['workers']} | {r['wall']:.1f} | {r['units']} | {r['rendering_per_worker']:.1f} | "
            f"**{100 * (1 - r['rendering_per_worker'] / r['wall']):.1f} %** | "
            f"{r['coordinator_cpu']:.1f} ({100 * r['coordinator_cpu'] / r['wall']:.0f} %) | {r['swarm_cpu']:.1f} | "
            f"{r['merge']:.1f} | {r['ends']:.1f} | {r['sent_per_worker'] / 1e6:.0f} | "
            f"{r['faults'] / 1e3:.0f} |")
    report("\n".join(lines), a.out)


if __name__ == "__main__":
    main()
