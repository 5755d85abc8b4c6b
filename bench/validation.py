#!/usr/bin/env python3
"""What a submission's validation costs the coordinator: builds side by side.

Usage:
  python3 bench/validation.py BINARY [BINARY ...] [--reps 5]
                              [--scene ../shared/scenes/veach-ajar/scene.xml]
                              [-D integrator=guided_path -D resx=640 -D resy=360]

For each repetition and each build, alternating: a fresh `pathfarm coordinator` with no
workers; the scene submitted once (its files uploaded), then again with another seed (the
files already there: only the validation and the job's admission remain). Reported per
build: the coordinator's CPU seconds over the second submission (from /proc, until 0.3 s
after it returned) and the submission's wall seconds (`pathfarm submit` without --wait
returns once the job is validated and stored), medians and every repetition.
"""
import argparse
import os
import socket
import statistics
import subprocess
import sys
import tempfile
import time

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
TOKEN = "bench-validation"


def free_port():
    s = socket.socket()
    s.bind(("127.0.0.1", 0))
    port = s.getsockname()[1]
    s.close()
    return port


def cpu_seconds(pid):
    fields = open(f"/proc/{pid}/stat").read().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


def wait_listening(port, deadline_s=20.0):
    t0 = time.time()
    while time.time() - t0 < deadline_s:
        try:
            socket.create_connection(("127.0.0.1", port), timeout=0.2).close()
            return
        except OSError:
            time.sleep(0.05)
    raise SystemExit(f"the coordinator did not listen on {port}")


def one(binary, scene, defines):
    data = tempfile.mkdtemp(prefix="pathfarm-validation-")
    port = free_port()
    env = dict(os.environ, PATHFARM_TOKEN=TOKEN, RUST_LOG="info")
    log = open(os.path.join(data, "coordinator.log"), "w")
    listen = f"127.0.0.1:{port}"
    coordinator = subprocess.Popen(
        [binary, "coordinator", "--listen", listen, "--data", os.path.join(data, "c")],
        env=env, stderr=log)
    try:
        wait_listening(port)
        args = [binary, "submit", scene, "--coordinator", f"http://{listen}", "--spp", "32"]
        for d in defines:
            args += ["-D", d]
        first = subprocess.run(args + ["--seed", "99"], env=env, capture_output=True, text=True)
        if first.returncode != 0:
            raise SystemExit(f"{binary}: submit: {first.stderr}")
        time.sleep(0.5)
        c0, t0 = cpu_seconds(coordinator.pid), time.time()
        r = subprocess.run(args, env=env, capture_output=True, text=True)
        wall = time.time() - t0
        time.sleep(0.3)
        cpu = cpu_seconds(coordinator.pid) - c0
        if r.returncode != 0:
            raise SystemExit(f"{binary}: submit: {r.stderr}")
        return cpu, wall
    finally:
        coordinator.terminate()
        coordinator.wait()
        subprocess.run(["rm", "-rf", data])


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("binaries", nargs="+")
    ap.add_argument("--reps", type=int, default=5)
    ap.add_argument("--scene", default=os.path.join(ROOT, "../shared/scenes/veach-ajar/scene.xml"))
    ap.add_argument("-D", dest="defines", action="append",
                    default=None, help="NAME=VALUE (default: guided_path at 640x360)")
    a = ap.parse_args()
    defines = a.defines or ["integrator=guided_path", "resx=640", "resy=360"]
    results = {b: [] for b in a.binaries}
    for _ in range(a.reps):
        for b in a.binaries:
            results[b].append(one(b, a.scene, defines))
    cpu_model = next((l.split(":", 1)[1].strip() for l in open("/proc/cpuinfo")
                      if l.startswith("model name")), "unknown CPU")
    print(f"CPU: {cpu_model}, {os.cpu_count()} cores; {a.reps} repetitions, alternating")
    for b, runs in results.items():
        cpus = [c for c, _ in runs]
        walls = [w for _, w in runs]
        print(f"{b}: coordinator CPU s {statistics.median(cpus):.3f} "
              f"({', '.join(f'{c:.2f}' for c in cpus)}); submission wall s "
              f"{statistics.median(walls):.3f} ({', '.join(f'{w:.2f}' for w in walls)})")


if __name__ == "__main__":
    sys.exit(main())
