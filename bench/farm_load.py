#!/usr/bin/env python3
"""The coordinator under load: many workers, several jobs and a very large one being set up.

Usage:
  python3 bench/farm_load.py [--workers 8,32,128] [--jobs 4] [--res 256] [--spp 16]
                             [--big 2048] [--big-spp 4] [--job-memory-mb 20000]
                             [--binary target/release/pathfarm] [--out bench/results/farm-load.md]

For each worker count N, on this machine: one `pathfarm coordinator` process (with
--metrics), N `pathfarm worker --threads 1` processes (real workers: they render real tiles
of a small scene, so every payload is a real one, and they heartbeat as in production), then
`--jobs` guided jobs of scenes/cornell-box at --res x --res and --spp, and one job of
--big x --big at --big-spp (none with --big 0), all submitted at once with
`pathfarm submit --wait`. Each worker process keeps its own copies of what its jobs need
(the large job's pixel estimate among them), so 128 workers with a 2048x2048 job do not fit
in 24 GiB: run the largest worker counts with --big 0. Meanwhile
`pathfarm status` runs every 100 ms (and ten times before the jobs, on the idle farm:
the command's own cost, process start included).

Reported per N: wall seconds until every job is done; tiles accepted per second; the p99 of
`pathfarm status` (wall time of the whole command, process start included: what a user
waits); the p99 of the coordinator's handling of control messages (heartbeats, lease
requests: from its `pathfarm_control_message_seconds` histogram, the upper edge of the bucket
holding the 99th percentile, the state lock's wait included; heartbeats and the other
messages apart); the coordinator's CPU seconds
(user + system) per unit; its peak resident memory (VmHWM). Target: heartbeats and status
under 100 ms at p99 throughout.

With N workers on two cores the workers compete with the coordinator and the probe for the
CPU. On a farm the coordinator has a machine of its own; here the workers run at
niceness --nice (10), so that the coordinator and `pathfarm status` are served first, as
they would be on their own machine. "status served" is the coordinator's own time to answer
the status calls (`pathfarm_status_seconds`, from the handler's start), apart from process
start and CPU contention. Quote medians, name the CPU (printed).
"""
import argparse
import os
import re
import shutil
import statistics
import subprocess
import sys
import tempfile
import threading
import time
import urllib.request

from farm import cpu_name, free_port  # this directory's farm benchmark

HERE = os.path.dirname(os.path.abspath(__file__))
ROOT = os.path.normpath(os.path.join(HERE, ".."))
TOKEN = "farm-load-token"
STATUS_RE = re.compile(r'pathfarm_status_seconds_bucket\{le="([^"]+)"\} (\d+)')
BUCKET_RE = re.compile(
    r'pathfarm_control_message_seconds_bucket\{le="([^"]+)",kind="(\w+)"\} (\d+)')


def proc_cpu_seconds(pid):
    fields = open(f"/proc/{pid}/stat").read().rsplit(")", 1)[1].split()
    ticks = os.sysconf("SC_CLK_TCK")
    return (int(fields[11]) + int(fields[12])) / ticks


def proc_peak_mb(pid):
    for line in open(f"/proc/{pid}/status"):
        if line.startswith("VmHWM:"):
            return int(line.split()[1]) / 1024
    return float("nan")


def scrape(port):
    with urllib.request.urlopen(f"http://127.0.0.1:{port}/metrics", timeout=10) as r:
        return r.read().decode()


def counter(text, name):
    total = 0.0
    for line in text.splitlines():
        if line.startswith(name) and not line.startswith("#"):
            total += float(line.rsplit(" ", 1)[1])
    return total


def histogram_p99(before, after, kind):
    """The upper edge of the bucket holding the 99th percentile of the `kind` messages
    observed between the two scrapes (`kind` None: the status calls)."""
    if kind is None:
        found = lambda text: [(le, n) for le, n in STATUS_RE.findall(text)]
    else:
        found = lambda text: [(le, n) for le, k, n in BUCKET_RE.findall(text) if k == kind]
    b = {le: int(n) for le, n in found(before)}
    a = [(le, int(n) - b.get(le, 0)) for le, n in found(after)]
    if not a or a[-1][1] == 0:
        return float("nan"), 0
    total = a[-1][1]
    for le, n in a:
        if n >= 0.99 * total:
            return (float("inf") if le == "+Inf" else float(le)), total
    return float("inf"), total


def p99(xs):
    xs = sorted(xs)
    return xs[min(len(xs) - 1, int(0.99 * len(xs)))] if xs else float("nan")


def run(a, n, tmp):
    env = dict(os.environ, PATHFARM_TOKEN=TOKEN, NO_COLOR="1", RUST_LOG="warn")
    port, mport = free_port(), free_port()
    url = f"http://127.0.0.1:{port}"
    data = os.path.join(tmp, f"coord-{n}")
    logs = open(os.path.join(tmp, f"coord-{n}.log"), "w")
    coord = subprocess.Popen(
        [a.binary, "coordinator", "--listen", f"127.0.0.1:{port}", "--data", data,
         "--metrics", f"127.0.0.1:{mport}", "--job-memory-mb", str(a.job_memory_mb)],
        env=env, stderr=logs, stdout=subprocess.DEVNULL)
    procs = []
    try:
        for _ in range(100):
            try:
                scrape(mport)
                break
            except OSError:
                time.sleep(0.1)
        for i in range(n):
            w = subprocess.Popen(
                ["nice", "-n", str(a.nice)] * (a.nice > 0) + [a.binary, "worker", "--coordinator", url, "--threads", "1",
                 "--cache", os.path.join(tmp, f"w{n}-{i}"), "--name", f"sim{i}"],
                env=env, stderr=subprocess.DEVNULL, stdout=subprocess.DEVNULL)
            procs.append(w)
        deadline = time.time() + 120
        while counter(scrape(mport), "pathfarm_workers") < n:
            if time.time() > deadline:
                raise SystemExit(f"only {counter(scrape(mport), 'pathfarm_workers')} of {n} workers registered")
            time.sleep(0.2)
        scene = os.path.join(ROOT, "scenes", "cornell-box", "scene.xml")
        idle_ms = []
        for _ in range(10):
            s = time.time()
            subprocess.run([a.binary, "status", "--coordinator", url], env=env,
                           stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
            idle_ms.append((time.time() - s) * 1000)
        before = scrape(mport)
        cpu0 = proc_cpu_seconds(coord.pid)
        t0 = time.time()
        jobs = []
        sizes = ([(a.big, a.big_spp)] if a.big > 0 else []) + [(a.res, a.spp)] * a.jobs
        for k, (res, spp) in enumerate(sizes):
            out = os.path.join(tmp, f"job-{n}-{k}.exr")
            jobs.append(subprocess.Popen(
                [a.binary, "submit", scene, "--coordinator", url, "-D", "integrator=guided_path",
                 "-D", f"resx={res}", "-D", f"resy={res}", "--spp", str(spp), "--seed", str(k + 1),
                 "--wait", "-o", out],
                env=env, stderr=subprocess.PIPE, stdout=subprocess.DEVNULL, text=True))
        status_ms = []
        stop = threading.Event()

        def probe():
            while not stop.is_set():
                s = time.time()
                subprocess.run([a.binary, "status", "--coordinator", url], env=env,
                               stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
                status_ms.append((time.time() - s) * 1000)
                stop.wait(0.1)

        prober = threading.Thread(target=probe)
        prober.start()
        failed = []
        for j in jobs:
            _, err = j.communicate(timeout=3600)
            if j.returncode != 0:
                failed.append(err[-2000:])
        wall = time.time() - t0
        stop.set()
        prober.join()
        after = scrape(mport)
        cpu = proc_cpu_seconds(coord.pid) - cpu0
        peak = proc_peak_mb(coord.pid)
        if failed:
            raise SystemExit(f"{len(failed)} jobs failed:\n" + "\n".join(failed))
        tiles = counter(after, 'pathfarm_tiles_total{outcome="accepted"}') - counter(
            before, 'pathfarm_tiles_total{outcome="accepted"}')
        units = counter(after, "pathfarm_units_total") - counter(before, "pathfarm_units_total")
        hb99, hbn = histogram_p99(before, after, "heartbeat")
        other99, othern = histogram_p99(before, after, "other")
        served99, _ = histogram_p99(before, after, None)
        return {
            "workers": n, "wall_s": wall, "tiles_per_s": tiles / wall, "tiles": tiles,
            "units": units, "status_p99_ms": p99(status_ms), "status_n": len(status_ms),
            "status_idle_ms": statistics.median(idle_ms),
            "heartbeat_p99_ms": hb99 * 1000, "heartbeat_n": hbn,
            "other_p99_ms": other99 * 1000, "other_n": othern,
            "served_p99_ms": served99 * 1000,
            "cpu_s_per_unit": cpu / max(units, 1), "coordinator_cpu_s": cpu, "peak_mb": peak,
        }
    finally:
        for p in procs:
            p.terminate()
        for p in procs:
            try:
                p.wait(timeout=30)
            except subprocess.TimeoutExpired:
                p.kill()
        coord.terminate()
        try:
            coord.wait(timeout=30)
        except subprocess.TimeoutExpired:
            coord.kill()
        logs.close()


def report(text, out):
    """Prints a result table and, with `out`, appends it to that file under a heading of
    the date and the command."""
    print(text)
    if out:
        with open(out, "a") as f:
            f.write(f"\n## {time.strftime('%Y-%m-%d %H:%M')} `{' '.join(sys.argv)}`\n\n{text}\n")


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--workers", default="8,32,128")
    ap.add_argument("--jobs", type=int, default=4)
    ap.add_argument("--res", type=int, default=256)
    ap.add_argument("--spp", type=int, default=16)
    ap.add_argument("--big", type=int, default=2048, help="0: no large job")
    ap.add_argument("--big-spp", type=int, default=4)
    ap.add_argument("--job-memory-mb", type=int, default=20000)
    ap.add_argument("--nice", type=int, default=10,
                    help="the workers' niceness (0: none); see the module doc")
    ap.add_argument("--binary", default=os.path.join(ROOT, "target", "release", "pathfarm"))
    ap.add_argument("--out", default=None)
    a = ap.parse_args()
    tmp = tempfile.mkdtemp(prefix="pathfarm-load-")
    rows = []
    try:
        for n in [int(x) for x in a.workers.split(",")]:
            r = run(a, n, tmp)
            print(r, flush=True)
            rows.append(r)
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    lines = [
        f"CPU: {cpu_name()}, {os.cpu_count()} logical cores. Jobs: {a.jobs} x {a.res}x{a.res} at "
        f"{a.spp} spp and 1 x {a.big}x{a.big} at {a.big_spp} spp (cornell-box, guided_path), "
        "submitted together.",
        "",
        "| workers | wall s | tiles/s | status idle median ms | status p99 ms (n) | status served p99 ms | heartbeat p99 ms (n) | other control msg p99 ms (n) | coordinator CPU s/unit | coordinator peak MB |",
        "|---|---|---|---|---|---|---|---|---|---|",
    ]
    for r in rows:
        lines.append(
            f"| {r['workers']} | {r['wall_s']:.1f} | {r['tiles_per_s']:.1f} | {r['status_idle_ms']:.0f} | "
            f"{r['status_p99_ms']:.0f} ({r['status_n']}) | <= {r['served_p99_ms']:.2f} | "
            f"<= {r['heartbeat_p99_ms']:.2f} ({r['heartbeat_n']}) | "
            f"<= {r['other_p99_ms']:.1f} ({r['other_n']}) | "
            f"{r['cpu_s_per_unit']:.3f} | {r['peak_mb']:.0f} |")
    report("\n".join(lines), a.out)


if __name__ == "__main__":
    main()
