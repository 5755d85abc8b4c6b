#!/usr/bin/env python3
"""Statistical cross-check of pathfarm against Mitsuba 3 (scalar_rgb).

Usage:
  crosscheck.py --pathfarm BIN --scene XML [--res W H] [--spp N] [--runs K]
                [--max-depth D] [-D k=v ...] [--pf-spp M] [--out DIR] [--seed S]
                [--mi-seed0 S0]

  --pathfarm may be a command line ("python3 mock_pathfarm.py") - it is shlex-split.
  --res W H      render resolution (default 64 64; pass `--res 0 0` for the XML's defaults)
  --spp N        spp of each Mitsuba run (default 64)
  --runs K       number of independent Mitsuba runs (seeds S0..S0+K-1, default 32, S0=0)
  --pf-spp M     spp for pathfarm (default K*N, i.e. the same total as Mitsuba)
  --max-depth D  sets -D max_depth=D for both renderers (default: the XML's default)
  -D k=v         extra XML parameters, given to both renderers
  --pf-integrator NAME  pathfarm renders with --integrator NAME (guided_path: unbiased, so
                 its image must agree with Mitsuba's path tracer's)

Method
  Mitsuba renders the scene K times with seeds 0..K-1 at N spp. Per pixel:
      a = mean of the K images,  var_a = sample variance (ddof=1) / K  (variance of the mean).
  pathfarm renders once with --aovs; b = RGB, var_b = variance.{R,G,B} AOV (variance of mean).
  (a) image means (per channel, over all pixels) must agree within 1 % (MEAN_TOL).
  (b) Z = (a-b)/sqrt(var_a+var_b) must satisfy |Z| < 3.29 (two-sided p = 0.001) for at least
      99 % of the pixel-channels (PIXEL_FRAC). Pixel-channels where both variances are ~0
      (deterministic, e.g. directly seen constant environment, black) must instead agree to 1e-3
      relative (and count as failures otherwise).

Choice of K (arithmetic)
  var_a is estimated from K samples, so even for a perfect renderer Z is not standard normal.
  Worst case (var_b negligible): Z ~ Student-t with K-1 d.o.f.  P(|t_nu| > 3.29):
      nu=15: 0.50 %   nu=23: 0.32 %   nu=31: 0.25 %   nu=63: 0.16 %   nu=inf: 0.10 %
  With equal total spp (var_b ~ var_a, var_b from thousands of samples) Welch-Satterthwaite
  gives nu ~ 4(K-1) = 124 for K=32 -> 0.13 %.  So K=32 puts the expected failure fraction
  at 0.13-0.25 %, 4-8x below the 1 % allowance; at 64x64x3 = 12288 pixel-channels the
  binomial s.d. of that fraction is ~0.05 %, so a correct renderer fails by chance only if
  heavy tails / pixel correlation (Mitsuba's tent filter splats into neighbours) inflate it
  several-fold.  K >= 24 is the minimum we recommend; the script warns below that.
  Observed with correct renderers: 0.05-0.25 % on cornell-box / materials / caustic /
  white-furnace, ~0.55 % on door-ajar (heavy-tailed pixels: a per-run mean without a firefly also
  has a small sample variance, so Z skews negative) - use more --spp for such scenes.
  Caveat: Mitsuba's splatted pixel = sum(w L)/sum(w) is a ratio estimator with O(1/N) bias;
  with N = 64 spp per run that is << the noise of the K*N-sample mean.
"""
import argparse
import os
import shlex
import subprocess
import sys
import time
import xml.etree.ElementTree as ET

import numpy as np

Z_CRIT = 3.2905          # two-sided 0.001
PIXEL_FRAC = 0.99        # fraction of pixel-channels that must pass
MEAN_TOL = 0.01          # relative tolerance on per-channel image means
DET_REL_TOL = 1e-3       # for deterministic (zero-variance) pixels
DET_SE_REL = 1e-5        # pixel is deterministic if sqrt(var_a+var_b) < DET_SE_REL*|value|
FLOAT_FLOOR = 1e-6       # relative float32 round-off added to the Z denominator
CHANNELS = ("R", "G", "B")


def xml_defaults(path):
    """<default name=... value=...> entries of the scene file (top level)."""
    root = ET.parse(path).getroot()
    return {d.get("name"): d.get("value") for d in root.iter("default")}


def render_mitsuba(xml, params, spp, runs, seed0=0):
    import mitsuba as mi
    mi.set_variant("scalar_rgb")
    scene = mi.load_file(xml, **params)
    imgs = []
    for i in range(runs):
        imgs.append(np.array(mi.render(scene, seed=seed0 + i, spp=spp), dtype=np.float64)[..., :3])
    imgs = np.stack(imgs)
    return imgs.mean(0), imgs.var(0, ddof=1) / runs


def read_pathfarm_exr(path):
    import mitsuba as mi
    bmp = mi.Bitmap(path)
    names = [f.name for f in bmp.struct_()]
    arr = np.array(bmp, dtype=np.float64)
    if arr.ndim == 2:
        arr = arr[..., None]

    def get(n):
        if n not in names:
            raise SystemExit("FAIL: pathfarm EXR %s has no channel '%s' (channels: %s)" % (path, n, names))
        return arr[..., names.index(n)]

    rgb = np.stack([get(c) for c in CHANNELS], -1)
    var = np.stack([get("variance." + c) for c in CHANNELS], -1)
    spp = get("spp") if "spp" in names else None
    return rgb, var, spp


def run_pathfarm(cmd, xml, params, spp, seed, outdir, integrator=None):
    out = os.path.join(outdir, "pathfarm.exr")
    args = shlex.split(cmd) + ["render", xml, "-o", out, "--spp", str(spp), "--seed", str(seed), "--aovs"]
    if integrator:
        args += ["--integrator", integrator]
    for k, v in params.items():
        args += ["-D", "%s=%s" % (k, v)]
    t0 = time.time()
    p = subprocess.run(args, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    dt = time.time() - t0
    if p.returncode != 0:
        sys.stderr.write(p.stdout + p.stderr)
        raise SystemExit("FAIL: pathfarm exited with status %d: %s" % (p.returncode, " ".join(args)))
    summary = [l for l in p.stdout.splitlines() if l.startswith("summary:")]
    return out, (summary[-1] if summary else None), dt


def colormap_diverging(z, lim):
    """blue (-lim) .. white (0) .. red (+lim), uint8 HxWx3."""
    t = np.clip(z / lim, -1, 1)
    r = np.where(t > 0, 1.0, 1.0 + t)
    g = 1.0 - np.abs(t)
    b = np.where(t < 0, 1.0, 1.0 - t)
    return (np.stack([r, g, b], -1) * 255 + 0.5).astype(np.uint8)


def tonemap(img, scale):
    x = np.clip(img * scale, 0, None)
    x = np.where(x <= 0.0031308, 12.92 * x, 1.055 * np.power(x, 1 / 2.4) - 0.055)
    return (np.clip(x, 0, 1) * 255 + 0.5).astype(np.uint8)


def write_png(path, arr_u8):
    """Writes an 8-bit PNG, upscaled (nearest) so small renders stay inspectable."""
    import mitsuba as mi
    f = max(1, 256 // max(arr_u8.shape[:2]))
    if f > 1:
        arr_u8 = np.repeat(np.repeat(arr_u8, f, 0), f, 1)
    bmp = mi.Bitmap(np.ascontiguousarray(arr_u8))
    bmp.write(path)


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--pathfarm", required=True, help="pathfarm binary (or command line)")
    ap.add_argument("--scene", required=True)
    ap.add_argument("--res", type=int, nargs=2, default=[64, 64], metavar=("W", "H"))
    ap.add_argument("--spp", type=int, default=64, help="spp per Mitsuba run")
    ap.add_argument("--runs", type=int, default=32, help="number of Mitsuba runs (K)")
    ap.add_argument("--pf-spp", type=int, default=None, help="pathfarm spp (default runs*spp)")
    ap.add_argument("--max-depth", type=int, default=None)
    ap.add_argument("--seed", type=int, default=7, help="pathfarm seed")
    ap.add_argument("--mi-seed0", type=int, default=0, help="first Mitsuba seed (runs use seed0..seed0+K-1)")
    ap.add_argument("-D", action="append", default=[], metavar="K=V")
    ap.add_argument("--pf-integrator", default=None, metavar="NAME",
                    help="pathfarm renders with --integrator NAME (e.g. guided_path: an unbiased "
                         "estimator of the image Mitsuba's integrator renders)")
    ap.add_argument("--out", default=None, help="output dir for EXR/PNGs (default $TMPDIR/crosscheck-out/<scene>)")
    a = ap.parse_args()

    xml = os.path.abspath(a.scene)
    scene_name = os.path.basename(os.path.dirname(xml)) or "scene"
    outdir = a.out or os.path.join(os.environ.get("TMPDIR", "/tmp"), "crosscheck-out", scene_name)
    os.makedirs(outdir, exist_ok=True)
    if a.runs < 24:
        print("warning: --runs %d < 24: with %d d.o.f. in Mitsuba's variance estimate, up to "
              "~%.1f%% of pixels fail by chance (t-distribution tails)"
              % (a.runs, a.runs - 1, 0.5 if a.runs >= 16 else 1.0 if a.runs >= 8 else 3.0))

    # Parameters passed to both renderers: the XML defaults, overridden by --res/--max-depth/-D.
    defaults = xml_defaults(xml)
    params = {}
    if a.res[0] > 0:
        params["resx"], params["resy"] = str(a.res[0]), str(a.res[1])
    if a.max_depth is not None:
        params["max_depth"] = str(a.max_depth)
    for d in a.D:
        k, v = d.split("=", 1)
        params[k] = v
    mi_params = dict(defaults)
    mi_params.update(params)
    mi_params.pop("spp", None)          # spp is given to mi.render
    pf_spp = a.pf_spp or a.runs * a.spp

    t0 = time.time()
    ma, va = render_mitsuba(xml, mi_params, a.spp, a.runs, a.mi_seed0)
    t_mi = time.time() - t0
    pf_params = {k: v for k, v in params.items() if k != "spp"}
    exr, summary, t_pf = run_pathfarm(a.pathfarm, xml, pf_params, pf_spp, a.seed, outdir,
                                      a.pf_integrator)
    mb, vb, spp_map = read_pathfarm_exr(exr)
    if mb.shape != ma.shape:
        raise SystemExit("FAIL: resolution mismatch: Mitsuba %s vs pathfarm %s"
                         % ("x".join(map(str, ma.shape[1::-1])), "x".join(map(str, mb.shape[1::-1]))))

    ok = True
    msgs = []
    # ---- (a) image means -------------------------------------------------------------------
    h, w = ma.shape[:2]
    npx = h * w
    mean_a, mean_b = ma.reshape(-1, 3).mean(0), mb.reshape(-1, 3).mean(0)
    # standard error of the difference of image means (ignores pixel correlation)
    se = np.sqrt((va + vb).reshape(-1, 3).sum(0)) / npx
    rel = (mean_b - mean_a) / np.maximum(np.abs(mean_a), 1e-12)
    print("scene %s  %dx%d  Mitsuba scalar_rgb %d runs x %d spp (%.1f s)  pathfarm %d spp (%.1f s)"
          % (scene_name, w, h, a.runs, a.spp, t_mi, pf_spp, t_pf))
    if summary:
        print("pathfarm " + summary)
    print("%-4s %12s %12s %9s %10s" % ("ch", "mitsuba", "pathfarm", "rel.diff", "diff/se"))
    for c in range(3):
        small = abs(mean_a[c]) < 1e-6 and abs(mean_b[c]) < 1e-6
        print("%-4s %12.6g %12.6g %+8.3f%% %+10.2f" % (CHANNELS[c], mean_a[c], mean_b[c], 100 * rel[c],
                                                      (mean_b[c] - mean_a[c]) / max(se[c], 1e-30)))
        if not small and abs(rel[c]) > MEAN_TOL:
            ok = False
            msgs.append("check (a) image mean, channel %s: pathfarm differs by %+.2f%% (tolerance %.1f%%; "
                        "%.1f standard errors)" % (CHANNELS[c], 100 * rel[c], 100 * MEAN_TOL,
                                                  (mean_b[c] - mean_a[c]) / max(se[c], 1e-30)))

    # ---- (b) per-pixel Z test ------------------------------------------------------------------
    vsum = va + vb
    scale = np.maximum(np.abs(ma), np.abs(mb))
    # "Deterministic": standard error of the difference below 1e-5 relative (float32
    # accumulation in either renderer leaves ~1e-7 relative junk in supposedly-zero variances).
    det = vsum <= (DET_SE_REL * scale) ** 2 + 1e-30
    z = np.zeros_like(ma)
    z[~det] = (mb - ma)[~det] / np.sqrt(vsum[~det] + (FLOAT_FLOOR * scale[~det]) ** 2)
    det_fail = det & (np.abs(mb - ma) > DET_REL_TOL * np.maximum(scale, 1e-6))
    fail = (~det & (np.abs(z) >= Z_CRIT)) | det_fail
    frac = fail.mean()
    ndet = int(det.sum())
    print("per-pixel: %d pixel-channels, %d deterministic (%d of them differ > %.0e rel)"
          % (fail.size, ndet, int(det_fail.sum()), DET_REL_TOL))
    print("  |Z|>=%.2f: %.3f%% (allowed %.1f%%, expected ~0.1-0.25%%)   mean Z %+.3f   rms Z %.3f"
          % (Z_CRIT, 100 * frac, 100 * (1 - PIXEL_FRAC), z[~det].mean() if (~det).any() else 0.0,
             np.sqrt((z[~det] ** 2).mean()) if (~det).any() else 0.0))
    border = np.zeros(ma.shape[:2], bool)
    border[0, :] = border[-1, :] = border[:, 0] = border[:, -1] = True
    fb, fi = fail[border].mean(), fail[~border].mean()
    print("  failures on the 1-px image border: %.2f%%, interior: %.2f%%" % (100 * fb, 100 * fi))
    if fb > 5 * max(fi, 0.002) and fb > 0.02:
        msgs.append("hint: failures concentrate on the image border - Mitsuba samples only inside "
                    "the film (sample_border=false), i.e. its filter is truncated at the image edge")
    if frac > 1 - PIXEL_FRAC:
        ok = False
        msgs.append("check (b) per-pixel Z: %.2f%% of pixel-channels have |Z| >= %.2f (allowed %.1f%%); "
                    "mean Z %+.2f (positive = pathfarm brighter)"
                    % (100 * frac, Z_CRIT, 100 * (1 - PIXEL_FRAC), z[~det].mean() if (~det).any() else 0.0))
    if spp_map is not None and np.any(spp_map <= 0):
        msgs.append("note: pathfarm spp AOV has %d pixels with 0 samples" % int((spp_map <= 0).sum()))

    # ---- debugging images ---------------------------------------------------------------------
    expo = 0.6 / max(float(np.percentile(ma.mean(-1), 90)), 1e-6)
    write_png(os.path.join(outdir, "mitsuba.png"), tonemap(ma, expo))
    write_png(os.path.join(outdir, "pathfarm.png"), tonemap(mb, expo))
    zl = z.copy()
    zl[det_fail] = np.sign(mb - ma)[det_fail] * 10
    write_png(os.path.join(outdir, "z.png"), colormap_diverging(zl.mean(-1) * np.sqrt(3), 5.0))
    write_png(os.path.join(outdir, "fail.png"), (fail.any(-1)[..., None] * np.array([255, 0, 0]) +
                                                 (~fail.any(-1))[..., None] * tonemap(ma, expo).mean(-1, keepdims=True) * 0.5
                                                 ).astype(np.uint8))
    reld = (mb - ma).mean(-1) / np.maximum(ma.mean(-1), 1e-3)
    write_png(os.path.join(outdir, "reldiff.png"), colormap_diverging(reld, 0.2))
    import mitsuba as mi
    mi.Bitmap(np.concatenate([ma, va, z], -1).astype(np.float32), mi.Bitmap.PixelFormat.MultiChannel,
              ["R", "G", "B", "variance.R", "variance.G", "variance.B", "Z.R", "Z.G", "Z.B"]).write(
        os.path.join(outdir, "mitsuba.exr"))
    print("debug images in %s (z.png: blue = pathfarm darker, red = brighter, saturates at |Z|=5 "
          "of the channel-averaged Z; fail.png; reldiff.png saturates at 20%%)" % outdir)

    for m in msgs:
        if m.startswith(("hint", "note")):
            print(m)
    msgs = [m for m in msgs if not m.startswith(("hint", "note"))]
    if ok:
        print("PASS")
        return 0
    for m in msgs:
        print("FAIL: " + m)
    return 1


if __name__ == "__main__":
    sys.exit(main())
