#!/usr/bin/env python3
"""The farm against one process: wall time, peak memory and where each training iteration's
time and bytes go.

Usage:
  python3 bench/farm.py [--scene veach-ajar] [--res 640x360] [--spp 32] [--reps 3]
                        [--workers 2] [--threads-per-worker 1] [--delays 0,10]
                        [--binary target/release/pathfarm] [--out bench/results/farm.md]

Each repetition runs, one after the other (order alternating between repetitions):
  * `pathfarm render --threads W*T` of the job (guided_path, an spp budget, a fixed seed);
  * `pathfarm cluster --workers W --threads-per-worker T` of the same job;
  * for each delay in --delays: a coordinator, W worker processes and `pathfarm submit --wait`
    started by this script, the workers talking to the coordinator through a TCP proxy of
    this script that delays every byte by half the round trip in each direction (so delay 10
    means 10 ms of added round-trip time; 0 means the proxy without delay, its own cost).
Every farm image must be byte-identical to the render's (the script fails otherwise).

Many-jobs mode (`--jobs N`): each repetition renders N jobs of the scene (seeds seed to
seed+N-1) one after another with `pathfarm render --threads W*T`, and submits the same N jobs
together to a coordinator with W workers (`submit --wait` each, all at once); it reports the
wall times (all N jobs), their ratio, the CPU seconds of the renders against the workers'
and the coordinator's, and the scene builds each worker logged.

Batch mode (`--frames N`): N frames of the scene, its camera moved a little further along its
right axis each frame (the files written beside a copy of the scene's folders, so every
frame shares the meshes and textures), rendered one after another by one process against
submitted as one batch (`pathfarm submit FRAMES... --wait -o DIR`); reported as in
many-jobs mode, with the bytes the coordinator sent the workers (scene files, trees,
fractions, estimates: `pathfarm_blob_bytes_sent`) per worker.

Reported: the median wall time of each, the farm/render ratio per repetition, the peak
resident memory of the render, the coordinator and a worker (VmHWM / ru_maxrss), and per
training iteration (medians over repetitions of the coordinator's `unit finished` lines,
summed over the iteration's units): wall seconds, rendering (the workers' seconds in their
render calls / workers: a worker renders one tile at a time on all its threads), and the
farm's own seconds: inputs (workers fetching and decoding trees, fractions, estimates; on
the workers, divided by workers), serialise (workers), receive,
decode and merge (coordinator), records (asking the workers for the iteration's quadtree
records to the last one in: their encoding, transfer, the coordinator's decoding and
adding), end (refinement at the iteration's end), checkpoint, publish (encoding the tree for
broadcast), and the bytes uploaded (tiles and records) and sent.

The machine is shared and noisy: compare the ratios of runs made side by side, never
absolute seconds across sessions; quote medians and the CPU (printed).
"""
import argparse
import asyncio
import json
import os
import re
import shutil
import socket
import statistics
import subprocess
import sys
import tempfile
import threading
import time
import urllib.request

HERE = os.path.dirname(os.path.abspath(__file__))
ROOT = os.path.normpath(os.path.join(HERE, ".."))
SHARED = os.path.normpath(os.path.join(ROOT, "..", "shared", "scenes"))
ANSI = re.compile(r"\x1b\[[0-9;]*m")
UNIT_RE = re.compile(r"unit finished (.*)$")
EMPTY = "''"  # how an empty --delays is written in a command line
RECORDS_RE = re.compile(r"records collected (.*)$")
FIELD_RE = re.compile(r'(\w+)=("[^"]*"|\S+)')
ITER_RE = re.compile(r"iteration (\d+): spp=\d+ .* time=([\d.]+)s")
PEAK_RE = re.compile(r"(coordinator|worker) exiting peak_rss_mb=([\d.]+)")
TOKEN = "farm-bench-token"


def scene_path(name):
    if os.path.exists(name):
        return name
    for base in (SHARED, os.path.join(ROOT, "scenes")):
        p = os.path.join(base, name, "scene.xml")
        if os.path.exists(p):
            return p
    raise SystemExit(f"no scene {name}")


def cpu_name():
    try:
        for line in open("/proc/cpuinfo"):
            if line.startswith("model name"):
                return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return "unknown CPU"


def free_port():
    s = socket.socket()
    s.bind(("127.0.0.1", 0))
    p = s.getsockname()[1]
    s.close()
    return p


def timed(cmd, env=None, stderr_path=None):
    """Runs cmd; returns (wall seconds, ru_maxrss KB, stdout, stderr)."""
    err = open(stderr_path, "w+") if stderr_path else subprocess.PIPE
    t0 = time.monotonic()
    p = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=err, env=env, text=True)
    out = p.stdout.read()
    _, status, ru = os.wait4(p.pid, 0)
    wall = time.monotonic() - t0
    p.returncode = os.waitstatus_to_exitcode(status)
    if stderr_path:
        err.seek(0)
        errtext = err.read()
        err.close()
    else:
        errtext = p.stderr.read()
    if p.returncode != 0:
        raise SystemExit(f"{' '.join(cmd)} failed ({p.returncode}):\n{errtext[-4000:]}")
    return wall, ru.ru_maxrss, out, errtext


def job_flags(a):
    w, h = a.res.split("x")
    return [scene_path(a.scene), "-D", "integrator=guided_path", "-D", f"resx={w}", "-D", f"resy={h}",
            "--spp", str(a.spp), "--seed", str(a.seed)]


def parse_lines(text, pattern):
    found = []
    for line in ANSI.sub("", text).splitlines():
        m = pattern.search(line)
        if not m:
            continue
        f = {k: v.strip('"') for k, v in FIELD_RE.findall(m.group(1))}
        found.append(f)
    return found


def parse_units(text):
    return parse_lines(text, UNIT_RE)


def parse_records(text):
    return parse_lines(text, RECORDS_RE)


def parse_peaks(text):
    peaks = {"coordinator": [], "worker": []}
    for m in PEAK_RE.finditer(ANSI.sub("", text)):
        peaks[m.group(1)].append(float(m.group(2)))
    return peaks


def per_iteration(units, workers, records=()):
    """Sums the unit lines of each iteration; its wall time is the span from its first unit's
    offer to its last unit's end (units of an iteration overlap), plus its records
    collection (`records collected` lines: asking the workers, then refinement and the
    checkpoint, which then happen there rather than at the last unit's end)."""
    its = {}
    for u in units:
        k = int(u["iteration"])
        it = its.setdefault(k, {"units": 0, "span": [float("inf"), 0.0]})
        it["units"] += 1
        if "job_s" in u:
            start = float(u["job_s"])
            it["span"] = [min(it["span"][0], start), max(it["span"][1], start + float(u["wall_s"]))]
        for key in ("wall_s", "render_s", "prepare_s", "serialize_s", "receive_s", "decode_s",
                    "merge_s", "end_s", "checkpoint_s", "publish_s", "bytes_up", "bytes_down"):
            v = float(u[key])
            if key in ("render_s", "prepare_s", "serialize_s"):
                v /= workers  # a worker renders one tile at a time on all its threads
            it[key] = it.get(key, 0.0) + v
    for it in its.values():
        lo, hi = it.pop("span")
        if hi >= lo:
            it["wall_s"] = hi - lo
        it.setdefault("records_s", 0.0)
    for r in records:
        it = its.get(int(r["iteration"]))
        if it is None:
            continue
        wait, end, cp = float(r["wait_s"]), float(r["end_s"]), float(r["checkpoint_s"])
        it["records_s"] += wait
        it["end_s"] += end
        it["checkpoint_s"] += cp
        it["wall_s"] += wait + end + cp
        it["bytes_up"] += float(r["bytes"])
    return its


# ----- a delaying TCP proxy -----

class DelayProxy:
    """A child process forwarding 127.0.0.1:port -> 127.0.0.1:target, delaying each chunk by
    one_way seconds (order kept) in each direction."""

    def __init__(self, target, one_way):
        self.port = free_port()
        self.proc = subprocess.Popen([sys.executable, os.path.abspath(__file__), "--proxy",
                                      str(self.port), str(target), str(one_way)])
        for _ in range(200):
            try:
                socket.create_connection(("127.0.0.1", self.port), 0.1).close()
                return
            except OSError:
                time.sleep(0.05)
        raise SystemExit("the delay proxy did not start")

    def stop(self):
        self.proc.kill()
        self.proc.wait()


def proxy_main(port, target, one_way):
    async def pipe(reader, writer):
        loop = asyncio.get_running_loop()
        q = asyncio.Queue()

        async def sender():
            while True:
                due, data = await q.get()
                if data is None:
                    break
                delay = due - loop.time()
                if delay > 0:
                    await asyncio.sleep(delay)
                writer.write(data)
                await writer.drain()
            writer.close()

        task = asyncio.ensure_future(sender())
        try:
            while True:
                data = await reader.read(1 << 18)
                if not data:
                    break
                q.put_nowait((loop.time() + one_way, data))
        except OSError:
            pass
        q.put_nowait((0, None))
        try:
            await task
        except OSError:
            pass

    async def client(reader, writer):
        try:
            ur, uw = await asyncio.open_connection("127.0.0.1", target)
        except OSError:
            writer.close()
            return
        await asyncio.gather(pipe(reader, uw), pipe(ur, writer))

    async def serve():
        server = await asyncio.start_server(client, "127.0.0.1", port)
        async with server:
            await server.serve_forever()

    asyncio.run(serve())


def wait_listening(port):
    """Waits (at most 10 s) until something accepts connections on 127.0.0.1:port."""
    for _ in range(200):
        try:
            socket.create_connection(("127.0.0.1", port), 0.1).close()
            return
        except OSError:
            time.sleep(0.05)


def run_farm_proxied(a, tmp, delay_ms, tag):
    """Coordinator + workers (through a delaying proxy) + submit --wait; returns wall,
    coordinator log, worker logs, output path."""
    data = os.path.join(tmp, f"farm-{tag}")
    shutil.rmtree(data, ignore_errors=True)
    os.makedirs(data)
    port = free_port()
    env = dict(os.environ, PATHFARM_TOKEN=TOKEN, RUST_LOG="info")
    logs = []
    procs = []
    try:
        clog = open(os.path.join(data, "coordinator.log"), "w+")
        logs.append(clog)
        procs.append(subprocess.Popen([a.binary, "coordinator", "--listen", f"127.0.0.1:{port}",
                                       "--data", os.path.join(data, "coordinator")],
                                      stdout=subprocess.DEVNULL, stderr=clog, env=env))
        wait_listening(port)
        proxy = DelayProxy(port, delay_ms / 2000.0)
        for i in range(a.workers):
            wlog = open(os.path.join(data, f"worker-{i}.log"), "w+")
            logs.append(wlog)
            procs.append(subprocess.Popen(
                [a.binary, "worker", "--coordinator", f"http://127.0.0.1:{proxy.port}",
                 "--threads", str(a.threads_per_worker), "--cache", os.path.join(data, f"cache-{i}")],
                stdout=subprocess.DEVNULL, stderr=wlog, env=env))
        out = os.path.join(data, "farm.exr")
        try:
            wall, _, _, _ = timed([a.binary, "submit"] + job_flags(a) + [
                "--coordinator", f"http://127.0.0.1:{port}", "--wait", "-o", out], env=env)
        finally:
            proxy.stop()
    finally:
        for p in procs[1:] + procs[:1]:
            p.terminate()
            try:
                p.wait(15)
            except subprocess.TimeoutExpired:
                p.kill()
                p.wait()
    texts = []
    for f in logs:
        f.seek(0)
        texts.append(f.read())
        f.close()
    return wall, texts[0], texts[1:], out


def med(xs):
    return statistics.median(xs) if xs else float("nan")


def main():
    if len(sys.argv) == 5 and sys.argv[1] == "--proxy":
        return proxy_main(int(sys.argv[2]), int(sys.argv[3]), float(sys.argv[4]))
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--scene", default="veach-ajar")
    ap.add_argument("--res", default="640x360")
    ap.add_argument("--spp", type=int, default=32)
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--reps", type=int, default=3)
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--threads-per-worker", type=int, default=1)
    ap.add_argument("--delays", default="0,10", help="added round-trip times in ms for the proxied runs ('' = none)")
    ap.add_argument("--binary", default=os.path.join(ROOT, "target", "release", "pathfarm"))
    ap.add_argument("--out", default=os.path.join(HERE, "results", "farm.md"))
    ap.add_argument("--json", default=None, help="also write every measurement here")
    ap.add_argument("--jobs", type=int, default=0,
                    help="many-jobs mode: N jobs at once against N renders one after another")
    ap.add_argument("--frames", type=int, default=0,
                    help="batch mode: N frames (the camera moved) as one batch against N renders")
    a = ap.parse_args()
    if a.jobs > 0 or a.frames > 0:
        return many_jobs(a)
    delays = [int(x) for x in a.delays.split(",") if x.strip()]
    threads = a.workers * a.threads_per_worker
    tmp = tempfile.mkdtemp(prefix="pathfarm-farm-bench-")
    runs = {"render": [], "cluster": []}
    for d in delays:
        runs[f"proxy{d}"] = []
    try:
        for r in range(a.reps):
            order = list(runs) if r % 2 == 0 else list(reversed(list(runs)))
            for kind in order:
                print(f"rep {r + 1}/{a.reps}: {kind}", file=sys.stderr, flush=True)
                if kind == "render":
                    out = os.path.join(tmp, "render.exr")
                    env = dict(os.environ, RUST_LOG="info")
                    wall, rss, stdout, err = timed([a.binary, "render"] + job_flags(a) + [
                        "--threads", str(threads), "--no-png", "-o", out], env=env)
                    ref = open(out, "rb").read()
                    its = {int(k): float(t) for k, t in ITER_RE.findall(ANSI.sub("", err))}
                    runs["render"].append({"wall": wall, "rss_mb": rss / 1024.0, "iterations": its})
                elif kind == "cluster":
                    out = os.path.join(tmp, "cluster.exr")
                    env = dict(os.environ, RUST_LOG="info")
                    wall, _, _, err = timed([a.binary, "cluster", "--workers", str(a.workers),
                                             "--threads-per-worker", str(a.threads_per_worker)]
                                            + job_flags(a) + ["-o", out], env=env,
                                            stderr_path=os.path.join(tmp, "cluster.log"))
                    runs["cluster"].append({"wall": wall, "image": open(out, "rb").read(),
                                            "units": parse_units(err), "records": parse_records(err),
                                            "peaks": parse_peaks(err)})
                else:
                    d = int(kind[5:])
                    wall, clog, wlogs, out = run_farm_proxied(a, tmp, d, kind)
                    peaks = parse_peaks("\n".join([clog] + wlogs))
                    runs[kind].append({"wall": wall, "image": open(out, "rb").read(),
                                       "units": parse_units(clog), "records": parse_records(clog),
                                       "peaks": peaks})
        # every farm image equals the render's
        for kind, rs in runs.items():
            for i, x in enumerate(rs):
                if "image" in x and x["image"] != ref:
                    raise SystemExit(f"{kind} repetition {i + 1}: the image differs from pathfarm render's")
        report(a, runs, threads)
    finally:
        shutil.rmtree(tmp, ignore_errors=True)


def cpu_seconds(ru):
    return ru.ru_utime + ru.ru_stime


def frame_jobs(a, tmp):
    """The --frames mode's frames: (scene, seed) per frame, files beside a copy of the
    scene's folders, the camera moved by 2 % of its distance from the origin a frame."""
    src = scene_path(a.scene)
    base = os.path.dirname(os.path.abspath(src))
    d = os.path.join(tmp, "frames")
    os.makedirs(d, exist_ok=True)
    for entry in os.listdir(base):  # copies: a bundle's files are confined to its folder
        if os.path.isdir(os.path.join(base, entry)):
            shutil.copytree(os.path.join(base, entry), os.path.join(d, entry))
    text = open(src).read()
    m = re.search(r'(<sensor.*?<matrix value=")([^"]+)(")', text, re.S)
    if not m:
        raise SystemExit(f"{src}: no sensor matrix to move the camera by")
    v = [float(x) for x in m.group(2).split()]
    step = 0.02 * (v[3] ** 2 + v[7] ** 2 + v[11] ** 2) ** 0.5
    jobs = []
    for i in range(a.frames):
        w = list(v)
        for row in range(3):  # along the camera's x axis (the matrix's first column)
            w[4 * row + 3] += i * step * v[4 * row]
        path = os.path.join(d, f"frame-{i + 1:03}.xml")
        with open(path, "w") as f:
            f.write(text[:m.start(2)] + " ".join(repr(x) for x in w) + text[m.end(2):])
        jobs.append((path, a.seed))
    return jobs


def with_job(a, scene, seed):
    b = argparse.Namespace(**vars(a))
    b.scene, b.seed = scene, seed
    return b


def many_jobs_sequential(a, tmp, jobs, threads):
    """N renders one after another: (wall, CPU seconds, images)."""
    t0, cpu, images = time.monotonic(), 0.0, []
    for i, (scene, seed) in enumerate(jobs):
        out = os.path.join(tmp, f"render-{i}.exr")
        b = with_job(a, scene, seed)
        p = subprocess.Popen([a.binary, "render"] + job_flags(b) + ["--threads", str(threads), "--no-png",
                              "-o", out], stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
        err = p.stderr.read()
        _, status, ru = os.wait4(p.pid, 0)
        if os.waitstatus_to_exitcode(status) != 0:
            raise SystemExit(f"render failed:\n{err[-4000:]}")
        cpu += cpu_seconds(ru)
        images.append(open(out, "rb").read())
    return time.monotonic() - t0, cpu, images


def many_jobs_farm(a, tmp, jobs):
    """A coordinator, W workers and the N jobs submitted at once (`submit --wait` each; one
    batch `submit` in --frames mode): (wall, worker CPU s, coordinator CPU s, images, scene
    builds per worker, blob bytes sent)."""
    data = tempfile.mkdtemp(prefix="farm-jobs-", dir=tmp)
    port, mport = free_port(), free_port()
    env = dict(os.environ, PATHFARM_TOKEN=TOKEN, RUST_LOG="info")
    coord = subprocess.Popen([a.binary, "coordinator", "--listen", f"127.0.0.1:{port}", "--data",
                              os.path.join(data, "coordinator"), "--metrics", f"127.0.0.1:{mport}"],
                             stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, env=env)
    workers, logs, sent = [], [], float("nan")
    try:
        wait_listening(port)
        for i in range(a.workers):
            path = os.path.join(data, f"worker-{i}.log")
            logs.append(path)
            workers.append(subprocess.Popen(
                [a.binary, "worker", "--coordinator", f"http://127.0.0.1:{port}", "--threads",
                 str(a.threads_per_worker), "--cache", os.path.join(data, f"cache-{i}")],
                stdout=subprocess.DEVNULL, stderr=open(path, "w"), env=env))
        time.sleep(0.5)
        t0 = time.monotonic()
        coordinator = ["--coordinator", f"http://127.0.0.1:{port}", "--wait"]
        if a.frames:
            outdir = os.path.join(data, "frames-out")
            flags = job_flags(a)[1:]  # the frames replace the scene
            subs = [(None, subprocess.Popen([a.binary, "submit"] + [s for s, _ in jobs] + flags
                                            + coordinator + ["--batch", "bench", "-o", outdir],
                                            stdout=subprocess.DEVNULL, stderr=subprocess.PIPE,
                                            env=env, text=True))]
            outs = [os.path.join(outdir, os.path.splitext(os.path.basename(s))[0] + ".exr")
                    for s, _ in jobs]
        else:
            subs, outs = [], []
            for i, (scene, seed) in enumerate(jobs):
                out = os.path.join(data, f"farm-{i}.exr")
                outs.append(out)
                subs.append((out, subprocess.Popen(
                    [a.binary, "submit"] + job_flags(with_job(a, scene, seed)) + coordinator
                    + ["-o", out], stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, env=env,
                    text=True)))
        for _, p in subs:
            err = p.stderr.read()
            if p.wait() != 0:
                raise SystemExit(f"submit failed:\n{err[-4000:]}")
        wall = time.monotonic() - t0
        images = [open(out, "rb").read() for out in outs]
        with urllib.request.urlopen(f"http://127.0.0.1:{mport}/metrics", timeout=10) as r:
            for line in r.read().decode().splitlines():
                if line.startswith("pathfarm_blob_bytes_sent"):
                    sent = float(line.rsplit(" ", 1)[1])
    finally:
        worker_cpu, coord_cpu = 0.0, 0.0
        for p in workers + [coord]:
            p.terminate()
            try:
                _, _, ru = os.wait4(p.pid, 0)
            except ChildProcessError:
                continue
            if p is coord:
                coord_cpu = cpu_seconds(ru)
            else:
                worker_cpu += cpu_seconds(ru)
    builds = []
    for path in logs:
        text = open(path).read()
        scenes = text.count("built ahead in") + text.count("scene built in")
        builds.append(f"{scenes} ({text.count('world built in')})")
    return wall, worker_cpu, coord_cpu, images, builds, sent


def many_jobs(a):
    threads = a.workers * a.threads_per_worker
    tmp = tempfile.mkdtemp(prefix="pathfarm-farm-jobs-")
    if a.frames:
        jobs = frame_jobs(a, tmp)
        what = f"a batch of {a.frames} frames (the camera moved)"
        mode = f"--frames {a.frames}"
    else:
        jobs = [(a.scene, s) for s in range(a.seed, a.seed + a.jobs)]
        what = f"{a.jobs} jobs at once"
        mode = f"--jobs {a.jobs}"
    rows = []
    try:
        for r in range(a.reps):
            kinds = ["render", "farm"] if r % 2 == 0 else ["farm", "render"]
            row = {}
            for kind in kinds:
                print(f"rep {r + 1}/{a.reps}: {kind}", file=sys.stderr, flush=True)
                if kind == "render":
                    row["render"] = many_jobs_sequential(a, tmp, jobs, threads)
                else:
                    row["farm"] = many_jobs_farm(a, tmp, jobs)
            if row["farm"][3] != row["render"][2]:
                raise SystemExit(f"repetition {r + 1}: a farm image differs from pathfarm render's")
            rows.append(row)
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    seeds = sorted({s for _, s in jobs})
    lines = [f"# {what} on the farm against one after another in one process",
             "", f"CPU: {cpu_name()}; {a.scene} {a.res}, {a.spp} spp, guided_path, seeds {seeds[0]}-{seeds[-1]}; "
             f"farm: {a.workers} workers x {a.threads_per_worker} threads; render: --threads {threads}.",
             f"Command: `python3 bench/farm.py {mode} --scene {a.scene} --res {a.res} --spp {a.spp} "
             f"--reps {a.reps} --workers {a.workers} --threads-per-worker {a.threads_per_worker}`", "",
             "| rep | renders, one after another (s) | farm (s) | farm / renders | render CPU s | "
             "worker CPU s | coordinator CPU s | scene builds (of them worlds) per worker | MB sent per worker |",
             "|---|---|---|---|---|---|---|---|---|"]
    for i, row in enumerate(rows):
        rw, rc, _ = row["render"]
        fw, wc, cc, _, builds, sent = row["farm"]
        lines.append(f"| {i + 1} | {rw:.2f} | {fw:.2f} | {fw / rw:.3f} | {rc:.1f} | {wc:.1f} | {cc:.1f} | "
                     f"{', '.join(map(str, builds))} | {sent / a.workers / 1e6:.1f} |")
    ratios = [row["farm"][0] / row["render"][0] for row in rows]
    lines += ["", f"Median farm / renders: **{med(ratios):.3f}**; every farm image equals pathfarm render's."]
    text = "\n".join(lines) + "\n"
    print(text)
    name = "farm-frames.md" if a.frames else "farm-jobs.md"
    out = a.out[:-len("farm.md")] + name if a.out.endswith("farm.md") else a.out
    os.makedirs(os.path.dirname(out) or ".", exist_ok=True)
    with open(out, "w") as f:
        f.write(text)


def report(a, runs, threads):
    lines = []
    say = lines.append
    say(f"# Farm benchmark: {a.scene} {a.res}, guided_path, {a.spp} spp, seed {a.seed}")
    say("")
    say(f"CPU: {cpu_name()}, {os.cpu_count()} cores. {a.reps} repetitions, run side by side in "
        f"alternating order. `pathfarm render --threads {threads}` against {a.workers} worker processes "
        f"of {a.threads_per_worker} thread(s). Every farm image was byte-identical to the render's.")
    say("")
    say(f"Command: `python3 bench/farm.py --scene {a.scene} --res {a.res} --spp {a.spp} --reps {a.reps} "
        f"--workers {a.workers} --threads-per-worker {a.threads_per_worker} --delays {a.delays or EMPTY}`")
    say("")
    rw = [x["wall"] for x in runs["render"]]
    say("| run | wall s (median) | per repetition | ratio to render (median of paired) | peak memory MB |")
    say("|---|---|---|---|---|")
    say(f"| render | {med(rw):.2f} | {', '.join('%.2f' % x for x in rw)} | 1 | "
        f"{med([x['rss_mb'] for x in runs['render']]):.0f} |")
    for kind, rs in runs.items():
        if kind == "render":
            continue
        ws = [x["wall"] for x in rs]
        ratios = [x / y for x, y in zip(ws, rw)]
        cpk = med([max(x["peaks"]["coordinator"] or [float("nan")]) for x in rs])
        wpk = med([max(x["peaks"]["worker"] or [float("nan")]) for x in rs])
        label = "cluster" if kind == "cluster" else f"farm, +{kind[5:]} ms RTT (proxy)"
        say(f"| {label} | {med(ws):.2f} | {', '.join('%.2f' % x for x in ws)} | {med(ratios):.3f} "
            f"({', '.join('%.3f' % x for x in ratios)}) | coordinator {cpk:.0f}, worker {wpk:.0f} |")
    say("")
    for kind, rs in runs.items():
        if kind == "render":
            continue
        say(f"## Per training iteration: {kind}")
        say("")
        say("Seconds are medians over repetitions of the sums over the iteration's units; worker "
            "seconds (render, inputs, serialise) are divided by the workers. `one process s`: "
            "the iteration's time in `pathfarm render` (its log line); wall / one process is the "
            "farm's cost of the iteration, e.g. the final pass's throughput is its inverse.")
        say("")
        its = [per_iteration(x["units"], a.workers, x.get("records", [])) for x in rs]
        keys = sorted({k for it in its for k in it})
        cols = ["units", "wall_s", "render_s", "prepare_s", "serialize_s", "receive_s", "decode_s",
                "merge_s", "records_s", "end_s", "checkpoint_s", "publish_s", "bytes_up", "bytes_down"]
        say("| iteration | one process s | " + " | ".join(c.replace("_s", "") for c in cols) + " | overhead |")
        say("|" + "---|" * (len(cols) + 3))
        tot = {c: 0.0 for c in cols}
        for k in keys:
            row = {c: med([it[k][c] for it in its if k in it]) for c in cols}
            for c in cols:
                tot[c] += row[c]
            over = (row["wall_s"] - row["render_s"]) / row["wall_s"] if row["wall_s"] else 0
            cells = [f"{row[c]:.0f}" if c in ("units",) else
                     (f"{row[c] / 1e6:.1f} MB" if c.startswith("bytes") else f"{row[c]:.3f}") for c in cols]
            one = med([r["iterations"][k] for r in runs["render"] if k in r.get("iterations", {})])
            say(f"| {k} | {one:.3f} | " + " | ".join(cells) + f" | {100 * over:.1f} % |")
        over = (tot["wall_s"] - tot["render_s"]) / tot["wall_s"] if tot["wall_s"] else 0
        cells = [f"{tot[c]:.0f}" if c == "units" else
                 (f"{tot[c] / 1e6:.1f} MB" if c.startswith("bytes") else f"{tot[c]:.3f}") for c in cols]
        one = med([sum(r.get("iterations", {}).values()) for r in runs["render"]])
        say(f"| all | {one:.3f} | " + " | ".join(cells) + f" | {100 * over:.1f} % |")
        say("")
        walls = [x["wall"] for x in rs]
        say(f"Outside the units (start-up, scene upload and validation, assembling, download): "
            f"{med(walls) - tot['wall_s']:.2f} s of {med(walls):.2f} s.")
        say("")
    text = "\n".join(lines) + "\n"
    print(text)
    if a.out:
        os.makedirs(os.path.dirname(a.out), exist_ok=True)
        with open(a.out, "w") as f:
            f.write(text)
    if a.json:
        with open(a.json, "w") as f:
            json.dump({k: [{kk: vv for kk, vv in x.items() if kk != "image"} for x in v]
                       for k, v in runs.items()}, f)


if __name__ == "__main__":
    main()
