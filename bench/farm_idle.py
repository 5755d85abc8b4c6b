#!/usr/bin/env python3
"""The workers' idle time between tiles in one farm run: a measure of the farm's own
synchronisation that a noisy machine moves much less than wall times.

Usage:
  RUST_LOG=info,pathfarm_farm::coordinator=debug pathfarm cluster ... 2> cluster.log
  python3 bench/farm_idle.py cluster.log [--top 8]

Reads the coordinator's `lease offered ... lease=L worker=W ... unit=U` lines (debug level)
and the workers' `lease L (job J): rendered unit U in R s (inputs I s, ...)` lines (info),
and prints per worker: the seconds it spent in its render calls, the sum of the gaps
between the end of one render call and the start of the next (the start is the end minus
the render time), and its biggest gaps with the unit that followed each and that lease's
input time (fetching and decoding the unit's tree, fractions, estimate). Gaps at an
iteration's first unit are the iteration boundaries; the rest are the farm's per-unit
costs (uploads, the coordinator's unit ends, lease round trips).
"""
import argparse
import datetime
import re

ANSI = re.compile(r"\x1b\[[0-9;]*m")
OFFERED = re.compile(r"lease offered job=\S+ lease=(\d+) worker=(\d+) tile=\d+ unit=(\d+)")
RENDERED = re.compile(r"lease (\d+) \(job \S+\): rendered unit (\d+) in ([\d.]+) s \(inputs ([\d.]+) s")


def stamp(line):
    return datetime.datetime.fromisoformat(line.split()[0].replace("Z", "+00:00")).timestamp()


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("log")
    ap.add_argument("--top", type=int, default=8)
    a = ap.parse_args()
    owner, unit_of, ends = {}, {}, {}
    for raw in open(a.log, errors="replace"):
        line = ANSI.sub("", raw)
        m = OFFERED.search(line)
        if m:
            owner[int(m.group(1))] = int(m.group(2))
            unit_of[int(m.group(1))] = int(m.group(3))
            continue
        m = RENDERED.search(line)
        if m:
            lease = int(m.group(1))
            ends.setdefault(lease, (stamp(line), float(m.group(3)), float(m.group(4))))
    if not owner:
        raise SystemExit("no 'lease offered' lines: run with RUST_LOG=info,pathfarm_farm::coordinator=debug")
    per = {}
    for lease, (t, render, inputs) in ends.items():
        if lease in owner:
            per.setdefault(owner[lease], []).append((t, render, inputs, unit_of[lease]))
    for worker, tiles in sorted(per.items()):
        tiles.sort()
        busy = sum(r for _, r, _, _ in tiles)
        gaps = [(t - r - prev[0], u, i) for prev, (t, r, i, u) in zip(tiles, tiles[1:])]
        idle = sum(g for g, _, _ in gaps)
        print(f"worker {worker}: rendering {busy:.2f} s, gaps {idle:.2f} s between {len(tiles)} tiles")
        top = sorted(gaps, reverse=True)[: a.top]
        print("  biggest gaps (s, next unit, its inputs s):",
              ", ".join(f"{g:.3f} u{u} {i:.3f}" for g, u, i in top))


if __name__ == "__main__":
    main()
