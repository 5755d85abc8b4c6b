#!/usr/bin/env python3
"""A model of the farm at many workers, from the parts bench/farm.py measured.

Usage:
  python3 bench/farm_model.py FARM.json [--workers 2] [--bandwidth-gbit 10] [--scale 1,9]

Reads the `cluster` runs of `bench/farm.py --json FARM.json` (medians over repetitions) and
models a job of the same passes on N single-thread workers:

  wall(N) = render / N + central(N)

where render is the workers' rendering seconds (all units) and central(N) is the
coordinator's serial work, none of it assumed to overlap rendering (an upper bound):
  * merge: receiving, decoding and applying the uploads' statistics and pixels; half of a
    unit's measured merge time is counted per statistics upload, half per pixel. Since
    joint uploads (runs whose ledger has `uploads`), a worker uploads a unit's statistics
    once: N uploads per unit; before them, each tile did: 3 tiles per worker thread per
    unit, the tiler's default before costs are known;
  * records: since records come once an iteration (runs with `records collected` lines),
    each worker hands in its quadtree records once per training iteration: N decodes and
    additions per iteration, each costing the measured seconds per holder;
  * refine and publish: refinement at each iteration's end and encoding the new tree, as
    measured (they do not depend on N);
  * broadcast: every worker fetches each new tree: tree bytes x N / the coordinator's
    bandwidth, once per iteration.
`--scale S` multiplies the image (pixels, so rendering and per-tile pixel payloads) by S:
9 is 1920x1080 for a 640x360 measurement. The tree is kept (it depends on the scene more
than on the resolution).

Prints, for N = 8, 64, 512 and each scale, the central share of wall time and the N at which
it passes 10 %.
"""
import argparse
import json
import statistics


def med(xs):
    return statistics.median(xs) if xs else 0.0


def parts(run):
    units = run["units"]
    tiles = sum(int(u["tiles"]) for u in units)
    # ledgers before joint uploads have no `uploads`: every tile was an upload
    uploads = sum(int(u.get("uploads", u["tiles"])) for u in units)
    joint = all("uploads" in u for u in units)
    merge = sum(float(u["decode_s"]) + float(u["merge_s"]) + float(u["receive_s"]) for u in units)
    its = {}
    for u in units:
        its.setdefault(int(u["iteration"]), []).append(u)
    refine = sum(float(u["end_s"]) + float(u["checkpoint_s"]) for u in units)
    publish = sum(float(u["publish_s"]) for u in units)
    # bytes of a tree: the first unit of an iteration fetches the new tree on every worker
    tree_bytes = [float(v[0]["bytes_down"]) for k, v in sorted(its.items()) if k > 0]
    render = sum(float(u["render_s"]) for u in units)
    records = run.get("records", [])
    holders = sum(int(r["holders"]) for r in records)
    records_s = sum(float(r["decode_s"]) + float(r["merge_s"]) for r in records)
    refine += sum(float(r["end_s"]) + float(r["checkpoint_s"]) for r in records)
    return {
        "record_iterations": sum(1 for r in records if int(r["holders"]) > 0),
        "records_per_holder": records_s / holders if holders else 0.0,
        "units": len(units),
        "tiles_per_unit": tiles / max(len(units), 1),
        "uploads_per_unit": uploads / max(len(units), 1),
        "uploads_per_worker_unit": 1.0 if joint else 3.0,
        "merge_per_unit": merge / max(len(units), 1),
        "refine": refine,
        "publish": publish,
        "tree_bytes": tree_bytes,
        "render": render,
    }


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("json")
    ap.add_argument("--workers", type=int, default=2, help="workers of the measured runs")
    ap.add_argument("--bandwidth-gbit", type=float, default=10.0)
    ap.add_argument("--scale", default="1,9")
    a = ap.parse_args()
    runs = json.load(open(a.json))["cluster"]
    ps = [parts(r) for r in runs]
    keys = ("record_iterations", "records_per_holder", "units", "tiles_per_unit", "uploads_per_unit", "uploads_per_worker_unit", "merge_per_unit",
            "refine", "publish", "render")
    p = {k: med([x[k] for x in ps]) for k in keys}
    trees = [sum(x["tree_bytes"]) / a.workers for x in ps]
    tree_total = med(trees)  # bytes of all tree versions one worker fetches
    bw = a.bandwidth_gbit * 1e9 / 8
    print(f"measured ({a.workers} workers, medians): {p['units']:.0f} units, render {p['render']:.1f} CPU-s, "
          f"merge {p['merge_per_unit'] * 1e3:.0f} ms per unit of {p['tiles_per_unit']:.1f} tiles "
          f"in {p['uploads_per_unit']:.1f} uploads, "
          f"records {p['records_per_holder'] * 1e3:.0f} ms per holder in {p['record_iterations']:.0f} "
          f"iterations, refine+checkpoint {p['refine']:.2f} s, publish {p['publish']:.2f} s, "
          f"trees fetched per worker {tree_total / 1e6:.0f} MB")
    for scale in [float(x) for x in a.scale.split(",")]:
        def central(n):
            # half of a unit's merge is per statistics upload, half per pixel (pixel sums)
            per_upload = 0.5 * p["merge_per_unit"] / p["uploads_per_unit"]
            uploads = p["uploads_per_worker_unit"] * n
            merge = p["units"] * (per_upload * uploads + 0.5 * p["merge_per_unit"] * scale)
            merge += p["record_iterations"] * n * p["records_per_holder"]
            return merge + p["refine"] + p["publish"] + tree_total * n / bw, merge

        def share(n):
            c, _ = central(n)
            return c / (p["render"] * scale / n + c)

        cross = next((n for n in range(1, 100000) if share(n) > 0.10), None)
        row = ", ".join(f"N={n}: {100 * share(n):.1f} % (merge {central(n)[1]:.1f} s, broadcast "
                        f"{tree_total * n / bw:.1f} s, render {p['render'] * scale / n:.1f} s)"
                        for n in (8, 64, 512))
        print(f"image x{scale:g}: central share {row}; passes 10 % at N = {cross}")


if __name__ == "__main__":
    main()
