#!/usr/bin/env python
"""Benchmark: perscli's exponential-profile shape fit per core, side by side with GalSim's HSM.

Run with ``make bench-measure`` (that is, ``.venv/bin/python benchmarks/bench_measure.py``).

The requirement: at least 150 exp fits per second per core on 48x48 stamps
(the speed of ngmix's exp fit with a fixed PSF, ~6 ms per galaxy), measured
side by side with GalSim HSM on the same stamps in one run.

What it does:

1. Stamps.  N (300) 48x48 stamps drawn with GalSim: exponential galaxies with
   hlr uniform in 0.2-0.5 arcsec, |g| uniform up to 0.6 at a uniform angle,
   centre at stamp pixel 24 (0-indexed) plus a uniform sub-pixel offset in
   [-0.499, 0.499) on each axis, convolved with the Roman PSF of SCA 7 in J129 at
   the filter's effective wavelength (``galsim.roman.getPSF``, in pixel units)
   and the pixel; the flux gives an optimal S/N (sqrt(sum model^2) / sigma)
   log-uniform in 20-200; Gaussian noise of known sigma (15 e-, about the sky
   plus read noise of a 140 s J129 exposure), seeded.
2. Timing, in this process, on one core (OMP/OpenBLAS/MKL threads set to 1
   before numpy is imported; CPU time is reported next to wall time):
   (a) ``perscli.measure.fit.fit_exp`` on every stamp, the ``ExpModel`` built
   once outside the timing, weights 1/sigma^2, the start as ``perscli measure``
   makes it from a catalogue (position to 1e-3 px, g = 0, T from the hlr to
   1e-3 arcsec, flux from the magnitude to 1e-3 mag);
   (b) ``galsim.hsm.FindAdaptiveMom``;
   (c) ``galsim.hsm.EstimateShear(..., shear_est='REGAUSS')`` with the PSF
   image ``perscli measure --method hsm`` uses.
   The three are interleaved over ``--repeats`` (3) passes; the best pass of
   each is reported.
3. Accuracy of each method against the true g (|g_fit - g_true|: mean, median,
   fraction within 0.01), on the noisy stamps and on the same stamps without
   noise (the method's own floor; with noise, the noise dominates).
4. The whole ``perscli measure`` process (exp and hsm) on a frame that tiles the
   same noisy stamps, with a WHT extension and a catalogue of x/y, hlr and
   mag_j129 (``--no-process`` to skip); its exp shapes are checked against the
   in-process fits.
5. cProfile of one pass of ``fit_exp`` (``--no-profile`` to skip).
6. Prints a table and PASS/FAIL, exits with status 1 on FAIL, and writes its
   section (``measure``) of ``benchmarks/RESULTS.md``.
"""

from __future__ import annotations

import os

# one core: set before numpy (or anything that imports it) is loaded
for _var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS", "NUMEXPR_NUM_THREADS",
             "VECLIB_MAXIMUM_THREADS", "BLIS_NUM_THREADS"):
    os.environ[_var] = "1"

import argparse  # noqa: E402
import datetime as dt  # noqa: E402
import io  # noqa: E402
import math  # noqa: E402
import sys  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402

import numpy as np  # noqa: E402

from perscli.instrument import ROMAN_EXPTIME, ROMAN_PIXEL_SCALE  # noqa: E402

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))
from bench_apply_persistence import (  # noqa: E402  (helpers shared with the other benchmarks)
    machine, perscli_command, run_child, versions, write_section)

SECTION = "measure"
N_DEFAULT = 300
STAMP = 48
SCA, FILTER = 7, "J129"
SIGMA = 15.0               # e- per pixel: sqrt(sky ~140 e- + read noise 8.5^2) for a 140 s J129 exposure
HLR_RANGE = (0.2, 0.5)     # arcsec
GMAX = 0.6
SNR_RANGE = (20.0, 200.0)  # optimal S/N, log-uniform
OFFSET = 0.499             # sub-pixel offset of the centre: uniform in [-OFFSET, OFFSET) on each axis
SEED = 20240612
REQUIRED = 150.0           # fits per second per core
NGMIX_MS = 6.0             # ngmix exp fit with a fixed PSF, ms per galaxy (NOTES.md section 4)
ZPT_AB, EXPTIME = 26.0, ROMAN_EXPTIME   # header values of the frame of the whole-process run (start flux)
PIXEL_SCALE = ROMAN_PIXEL_SCALE
#: the figures recorded before issue 8 (FITS through fitsio, the measure noise model from the detector model,
#: one executor) on the same machine, RESULTS.md at commit 132d716: the reference of "not slower"
BEFORE = dict(date="2026-11-22 20:21", commit="132d716", rate=183.0, fam=5537.0, regauss=1957.0, t_exp=3.22,
              t_hsm=1.84)


# --------------------------------------------------------------------------------------------
# stamps
# --------------------------------------------------------------------------------------------

def roman_psf():
    """The Roman PSF of SCA 7 in J129 at the effective wavelength, in pixel units (as measure builds it)."""
    import galsim
    import galsim.roman as roman

    bp = roman.getBandpasses(AB_zeropoint=True)[FILTER]
    psf = roman.getPSF(SCA, FILTER, wavelength=bp.effective_wavelength)
    assert abs(roman.pixel_scale - PIXEL_SCALE) < 1e-12
    return galsim.PixelScale(roman.pixel_scale).toImage(psf), bp.effective_wavelength


def catalogue_mag(flux_e):
    """AB magnitude, to 1e-3 as a catalogue holds it, of a flux in electrons over EXPTIME."""
    import galsim.roman as roman

    return np.round(ZPT_AB - 2.5 * np.log10(flux_e / (roman.collecting_area * EXPTIME)), 3)


def start_of(truth, i, x0=0.0, y0=0.0):
    """The start ``perscli measure`` builds (``shapes.start_point``) from a catalogue row: position
    to 1e-3 px (FITS convention in the catalogue), round, T from the hlr, flux from the magnitude."""
    import galsim.roman as roman
    from perscli.measure.fit import HL_SIGMAS, P_EXP

    moment = float(np.sum(P_EXP * HL_SIGMAS ** 2))
    # catalogue x/y in FITS pixels of a frame whose stamp origin is (x0, y0), 0-indexed
    xc = float(np.round(truth["x"][i] + x0 + 1.0, 3)) - 1.0 - x0
    yc = float(np.round(truth["y"][i] + y0 + 1.0, 3)) - 1.0 - y0
    hlr = float(np.round(truth["hlr"][i], 3))
    T0 = 2.0 * (hlr / PIXEL_SCALE) ** 2 * moment
    flux0 = 10 ** (-0.4 * (truth["mag"][i] - ZPT_AB)) * roman.collecting_area * EXPTIME
    return (xc, yc, 0.0, 0.0, T0, flux0)


def make_stamps(n: int, seed: int, psf):
    """Noise-free and noisy stamps and their truth."""
    import galsim

    rng = np.random.default_rng(seed)
    hlr = rng.uniform(*HLR_RANGE, n)
    gmod = rng.uniform(0.0, GMAX, n)
    beta = rng.uniform(0.0, np.pi, n)
    g1, g2 = gmod * np.cos(2 * beta), gmod * np.sin(2 * beta)
    # not quite +-0.5: a catalogue x rounded across the pixel boundary would make measure cut its stamp
    # one pixel over, and the whole-process check compares with the fits of exactly these stamps
    dx, dy = rng.uniform(-OFFSET, OFFSET, n), rng.uniform(-OFFSET, OFFSET, n)
    snr = np.exp(rng.uniform(np.log(SNR_RANGE[0]), np.log(SNR_RANGE[1]), n))
    # GalSim's default maxk_threshold (1e-3) cuts the larger galaxies' transforms inside the PSF's band
    gsp = galsim.GSParams(maxk_threshold=1e-5)
    clean = np.empty((n, STAMP, STAMP))
    flux = np.empty(n)
    for i in range(n):
        gal = galsim.Exponential(half_light_radius=hlr[i] / PIXEL_SCALE, gsparams=gsp).shear(g1=g1[i], g2=g2[i])
        # a 48x48 image's true centre is stamp index 23.5 (0-indexed): offset 0.5 + d puts it at 24 + d
        img = galsim.Convolve(gal, psf, propagate_gsparams=False).drawImage(
            nx=STAMP, ny=STAMP, scale=1.0, offset=(0.5 + dx[i], 0.5 + dy[i])).array
        flux[i] = snr[i] * SIGMA / math.sqrt(float(np.sum(img * img)))
        clean[i] = img * flux[i]
    noisy = clean + rng.normal(0.0, SIGMA, clean.shape)
    truth = dict(hlr=hlr, g1=g1, g2=g2, x=STAMP // 2 + dx, y=STAMP // 2 + dy, snr=snr, flux=flux,
                 mag=catalogue_mag(flux))
    return clean, noisy, truth


# --------------------------------------------------------------------------------------------
# the three methods
# --------------------------------------------------------------------------------------------

def run_perscli(stamps, weight, model, starts, keep=False):
    from perscli.measure.fit import fit_exp

    out = [] if keep else None
    per = np.empty(len(stamps))
    c0, t0 = time.process_time(), time.perf_counter()
    for i in range(len(stamps)):
        a = time.perf_counter()
        res = fit_exp(stamps[i], weight, model, starts[i])
        per[i] = time.perf_counter() - a
        if keep:
            out.append(res)
    return time.perf_counter() - t0, time.process_time() - c0, per, out


def run_fam(images, wimage, keep=False):
    import galsim

    out = [] if keep else None
    c0, t0 = time.process_time(), time.perf_counter()
    for im in images:
        try:
            res = galsim.hsm.FindAdaptiveMom(im, weight=wimage, strict=False)
        except (galsim.GalSimError, RuntimeError):
            res = None
        if keep:
            out.append(res)
    return time.perf_counter() - t0, time.process_time() - c0, None, out


def run_regauss(images, psf_image, wimage, keep=False):
    import galsim

    out = [] if keep else None
    c0, t0 = time.process_time(), time.perf_counter()
    for im in images:
        try:
            res = galsim.hsm.EstimateShear(im, psf_image, weight=wimage, shear_est="REGAUSS", strict=False)
        except (galsim.GalSimError, RuntimeError):
            res = None
        if keep:
            out.append(res)
    return time.perf_counter() - t0, time.process_time() - c0, None, out


def shapes_perscli(results):
    g = np.array([[r.theta[2], r.theta[3]] for r in results])
    flags = np.array([r.flags for r in results])
    return g, flags != 0


def shapes_fam(results):
    g = np.full((len(results), 2), np.nan)
    bad = np.ones(len(results), dtype=bool)
    for i, r in enumerate(results):
        if r is not None and r.moments_status == 0:
            g[i] = r.observed_shape.g1, r.observed_shape.g2
            bad[i] = False
    return g, bad


def shapes_regauss(results):
    g = np.full((len(results), 2), np.nan)
    bad = np.ones(len(results), dtype=bool)
    for i, r in enumerate(results):
        if r is not None and r.correction_status == 0 and not r.error_message:
            e1, e2 = r.corrected_e1, r.corrected_e2
            e = math.hypot(e1, e2)
            if e < 1:
                # distortion e -> reduced shear g, as perscli measure --method hsm does
                f = 1.0 / (1.0 + math.sqrt(1.0 - e * e))
                g[i] = e1 * f, e2 * f
                bad[i] = False
    return g, bad


def accuracy(g, bad, truth):
    dg = np.hypot(g[:, 0] - truth["g1"], g[:, 1] - truth["g2"])
    ok = ~bad & np.isfinite(dg)
    d = dg[ok]
    if d.size == 0:
        return dict(n=0, mean=np.nan, median=np.nan, within=np.nan, rms1=np.nan, bias=np.nan)
    return dict(n=int(ok.sum()), mean=float(d.mean()), median=float(np.median(d)),
                within=float(np.mean(d < 0.01)),
                rms1=float(np.sqrt(np.mean(np.concatenate([g[ok, 0] - truth["g1"][ok],
                                                           g[ok, 1] - truth["g2"][ok]]) ** 2))),
                # multiplicative: slope of g_fit on g_true over both components, minus 1
                bias=float(np.sum(np.concatenate([g[ok, 0] * truth["g1"][ok], g[ok, 1] * truth["g2"][ok]]))
                           / np.sum(np.concatenate([truth["g1"][ok] ** 2, truth["g2"][ok] ** 2])) - 1.0))


# --------------------------------------------------------------------------------------------
# the whole perscli measure process
# --------------------------------------------------------------------------------------------

def write_mosaic(workdir: Path, noisy, truth):
    """A frame tiling the stamps (no overlap: each stamp measure cuts is exactly one tile) and its catalogue."""
    from astropy.io import fits

    n = len(noisy)
    ncol = int(math.ceil(math.sqrt(n)))
    nrow = int(math.ceil(n / ncol))
    data = np.zeros((nrow * STAMP, ncol * STAMP), dtype=np.float32)
    x0 = np.empty(n)
    y0 = np.empty(n)
    for i in range(n):
        r, c = divmod(i, ncol)
        data[r * STAMP:(r + 1) * STAMP, c * STAMP:(c + 1) * STAMP] = noisy[i]
        x0[i], y0[i] = c * STAMP, r * STAMP
    hdr = fits.Header()
    hdr["BUNIT"] = "electron"
    hdr["GAIN"] = 1.0
    hdr["EXPTIME"] = EXPTIME
    hdr["SCA"] = SCA
    hdr["FILTER"] = FILTER
    hdr["ZPT_AB"] = ZPT_AB
    wht = fits.ImageHDU(np.full(data.shape, 1.0 / SIGMA ** 2, dtype=np.float32), name="WHT")
    frame = workdir / "mosaic.fits"
    fits.HDUList([fits.PrimaryHDU(data, header=hdr), wht]).writeto(frame, overwrite=True)
    cols = [fits.Column("id", "K", array=np.arange(1, n + 1)),
            fits.Column("x", "D", array=np.round(truth["x"] + x0 + 1.0, 3)),
            fits.Column("y", "D", array=np.round(truth["y"] + y0 + 1.0, 3)),
            fits.Column("hlr", "D", array=np.round(truth["hlr"], 3)),
            fits.Column("mag_J129", "D", array=truth["mag"])]
    cat = workdir / "mosaic_cat.fits"
    fits.BinTableHDU.from_columns(cols, name="CAT").writeto(cat, overwrite=True)
    # the noisy stamps went through float32 in the frame: the in-process fits for comparison use these
    stamps32 = np.stack([data[int(y0[i]):int(y0[i]) + STAMP, int(x0[i]):int(x0[i]) + STAMP] for i in range(n)])
    return frame, cat, x0, y0, stamps32.astype(np.float64), data.shape


# --------------------------------------------------------------------------------------------
# profile
# --------------------------------------------------------------------------------------------

def profile_fits(stamps, weight, model, starts, workdir: Path):
    import cProfile
    import pstats

    from perscli.measure.fit import fit_exp

    prof = cProfile.Profile()
    prof.enable()
    for i in range(len(stamps)):
        fit_exp(stamps[i], weight, model, starts[i])
    prof.disable()
    out = workdir / "fit_profile.prof"
    prof.dump_stats(str(out))
    stats = pstats.Stats(str(out))
    total = stats.total_tt
    rows = []
    for (fname, line, func), (cc, nc, tt, ct, _) in stats.stats.items():
        rows.append(dict(file=fname, line=line, func=func, ncalls=nc, tottime=tt, cumtime=ct))
    fit_rows = sorted([r for r in rows if r["file"].replace("\\", "/").endswith("perscli/measure/fit.py")],
                      key=lambda r: -r["cumtime"])
    top = sorted(rows, key=lambda r: -r["tottime"])[:15]
    buf = io.StringIO()
    pstats.Stats(str(out), stream=buf).sort_stats("tottime").print_stats(40)
    buf2 = io.StringIO()
    pstats.Stats(str(out), stream=buf2).sort_stats("cumulative").print_stats(40)
    (workdir / "fit_profile.txt").write_text(buf.getvalue() + "\n\n" + buf2.getvalue())
    return total, fit_rows, top


def short_name(r):
    f = r["file"]
    if f == "~":
        return r["func"]
    parts = f.replace("\\", "/").split("/")
    if "site-packages" in parts:
        parts = parts[parts.index("site-packages") + 1:]
    elif "src" in parts:
        parts = parts[parts.index("src") + 1:]
    else:
        parts = parts[-2:]
    return f"{'/'.join(parts)}:{r['line']}({r['func']})"


# --------------------------------------------------------------------------------------------

def thread_info() -> str:
    try:
        from threadpoolctl import threadpool_info
    except ImportError:
        blas = "?"
        try:
            cfg = np.show_config(mode="dicts")
            b = cfg["Build Dependencies"]["blas"]
            blas = f"{b.get('name', '?')} {b.get('version', '')}".strip()
        except Exception:
            pass
        return (f"threadpoolctl not installed; numpy's BLAS: {blas}; "
                f"OMP/OPENBLAS/MKL_NUM_THREADS = 1 set before numpy was imported")
    info = threadpool_info()
    return "threadpoolctl: " + "; ".join(f"{d.get('internal_api')} {d.get('version')} "
                                         f"num_threads={d.get('num_threads')}" for d in info)


def git_commit() -> str:
    import subprocess

    try:
        head = subprocess.run(["git", "rev-parse", "--short", "HEAD"], cwd=HERE, capture_output=True, text=True,
                              check=True).stdout.strip()
        dirty = subprocess.run(["git", "status", "--porcelain", "--", "src"], cwd=HERE.parent, capture_output=True,
                               text=True, check=True).stdout.strip()
        return head + (" + uncommitted changes in src/" if dirty else "")
    except (OSError, subprocess.CalledProcessError):
        return "?"


def quantiles(a, qs=(0, 10, 50, 90, 100)):
    return [float(np.percentile(a, q)) for q in qs]


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--n", type=int, default=N_DEFAULT, help=f"number of stamps (default {N_DEFAULT})")
    ap.add_argument("--repeats", type=int, default=3, help="timed passes of each method; the best is reported")
    ap.add_argument("--seed", type=int, default=SEED, help=f"seed of the stamps and noise (default {SEED})")
    ap.add_argument("--workdir", type=Path, default=HERE / "work" / "measure",
                    help="frame, catalogue, outputs and profile (default: benchmarks/work/measure, git-ignored)")
    ap.add_argument("--results", type=Path, default=None,
                    help="write the results here (default: benchmarks/RESULTS.md, with the default --n only)")
    ap.add_argument("--no-results", action="store_true", help="do not write a results file")
    ap.add_argument("--no-profile", action="store_true", help="skip the cProfile pass of fit_exp")
    ap.add_argument("--no-process", action="store_true", help="skip timing the whole perscli measure process")
    args = ap.parse_args(argv)
    if args.repeats < 1 or args.n < 1:
        ap.error("--repeats and --n must be >= 1")
    workdir = args.workdir.resolve()
    workdir.mkdir(parents=True, exist_ok=True)

    import galsim

    from perscli.measure.fit import ExpModel

    print(f"building {args.n} stamps of {STAMP}x{STAMP} px (GalSim, Roman PSF SCA {SCA} {FILTER})", flush=True)
    t0 = time.perf_counter()
    psf, wavelength = roman_psf()
    clean, noisy, truth = make_stamps(args.n, args.seed, psf)
    stamp_s = time.perf_counter() - t0
    weight = np.full((STAMP, STAMP), 1.0 / SIGMA ** 2)
    starts = [start_of(truth, i) for i in range(args.n)]

    t0 = time.perf_counter()
    model = ExpModel(psf, STAMP)
    model_s = time.perf_counter() - t0
    # the HSM inputs, as perscli measure --method hsm builds them (not timed)
    psf_image = galsim.Convolve(psf, galsim.Pixel(1.0)).drawImage(nx=STAMP, ny=STAMP, scale=1.0, method="no_pixel")
    wimage = galsim.Image(np.ones((STAMP, STAMP), dtype=np.int32), scale=1.0)
    images = [galsim.Image(np.ascontiguousarray(s), scale=1.0) for s in noisy]
    clean_images = [galsim.Image(np.ascontiguousarray(s), scale=1.0) for s in clean]

    print("untimed warm-up pass of each method", flush=True)
    w_pers = run_perscli(noisy[:10], weight, model, starts[:10])
    run_fam(images[:10], wimage)
    run_regauss(images[:10], psf_image, wimage)
    del w_pers

    runs = {"perscli": [], "fam": [], "regauss": []}
    for r in range(args.repeats):
        runs["perscli"].append(run_perscli(noisy, weight, model, starts, keep=(r == 0)))
        runs["fam"].append(run_fam(images, wimage, keep=(r == 0)))
        runs["regauss"].append(run_regauss(images, psf_image, wimage, keep=(r == 0)))
        print(f"  pass {r + 1}/{args.repeats}: perscli {runs['perscli'][-1][0]:.3f} s, "
              f"FindAdaptiveMom {runs['fam'][-1][0]:.3f} s, REGAUSS {runs['regauss'][-1][0]:.3f} s", flush=True)
    best = {k: min(v, key=lambda t: t[0]) for k, v in runs.items()}
    rate = {k: args.n / best[k][0] for k in runs}
    cpu_ratio = {k: best[k][1] / best[k][0] for k in runs}
    per_fit = best["perscli"][2]

    res_p = runs["perscli"][0][3]
    res_f = runs["fam"][0][3]
    res_r = runs["regauss"][0][3]
    nfev = np.array([r.nfev for r in res_p])
    pflags = np.array([r.flags for r in res_p])
    s2n_fit = np.array([r.s2n for r in res_p])
    g_p, bad_p = shapes_perscli(res_p)
    g_f, bad_f = shapes_fam(res_f)
    g_r, bad_r = shapes_regauss(res_r)
    acc = {"perscli": accuracy(g_p, bad_p, truth), "fam": accuracy(g_f, bad_f, truth),
           "regauss": accuracy(g_r, bad_r, truth)}
    badfrac = {"perscli": float(bad_p.mean()), "fam": float(bad_f.mean()), "regauss": float(bad_r.mean())}
    flag_counts = {int(b): int(np.sum((pflags & b) != 0)) for b in (1, 2, 4, 8, 16, 32, 64) if np.any(pflags & b)}
    gerr = np.array([math.hypot(r.errors[2], r.errors[3]) / math.sqrt(2) for r in res_p])

    print("noise-free stamps (accuracy floor, untimed)", flush=True)
    _, _, _, res_p0 = run_perscli(clean, weight, model, starts, keep=True)
    _, _, _, res_f0 = run_fam(clean_images, wimage, keep=True)
    _, _, _, res_r0 = run_regauss(clean_images, psf_image, wimage, keep=True)
    g, bad = shapes_perscli(res_p0)
    acc0 = {"perscli": accuracy(g, bad, truth)}
    nfev0 = float(np.mean([r.nfev for r in res_p0]))
    g, bad = shapes_fam(res_f0)
    acc0["fam"] = accuracy(g, bad, truth)
    g, bad = shapes_regauss(res_r0)
    acc0["regauss"] = accuracy(g, bad, truth)

    # ---- the whole perscli measure process --------------------------------------------------
    proc = None
    if not args.no_process:
        print("whole perscli measure process on a frame tiling the same stamps", flush=True)
        frame, cat, x0, y0, stamps32, fshape = write_mosaic(workdir, noisy, truth)
        exe = perscli_command()
        cmd_exp = exe + ["measure", str(frame), "--catalog", str(cat), "-o", str(workdir / "shapes_exp.fits"),
                         "--overwrite"]
        cmd_hsm = exe + ["measure", str(frame), "--catalog", str(cat), "--method", "hsm",
                         "-o", str(workdir / "shapes_hsm.fits"), "--overwrite"]
        cmd_base = [sys.executable, "-c", "import perscli.cli.main, perscli.measure.shapes, galsim, galsim.roman, "
                    "astropy.io.fits, astropy.table, astropy.wcs"]
        run_child(cmd_exp)                      # warm-up (page cache, pyc)
        t_exp = min(run_child(cmd_exp)[0] for _ in range(2))
        t_hsm = min(run_child(cmd_hsm)[0] for _ in range(2))
        t_base = min(run_child(cmd_base)[0] for _ in range(2))
        from astropy.io import fits

        shp = fits.getdata(workdir / "shapes_exp.fits", "SHAPES")
        # the same fits in this process on the float32 frame's stamps, from the same catalogue start
        starts32 = [start_of(truth, i, x0[i], y0[i]) for i in range(args.n)]
        weight32 = np.full((STAMP, STAMP), np.float32(1.0 / SIGMA ** 2), dtype=np.float64)  # the WHT HDU's
        _, _, _, res32 = run_perscli(stamps32, weight32, model, starts32, keep=True)
        g32 = np.array([[r.theta[2], r.theta[3]] for r in res32])
        dg_proc = float(np.max(np.abs(np.stack([shp["g1"], shp["g2"]], axis=1) - g32)))
        proc = dict(t_exp=t_exp, t_hsm=t_hsm, t_base=t_base, dg=dg_proc, cmd=cmd_exp, frame=frame,
                    good=int(np.sum(shp["flags"] == 0)), shape=fshape)

    prof = None
    if not args.no_profile:
        print("cProfile pass of fit_exp", flush=True)
        prof = profile_fits(noisy, weight, model, starts, workdir)

    # ---- report ------------------------------------------------------------------------------
    passed = rate["perscli"] >= REQUIRED
    verdict = "PASS" if passed else "FAIL"
    mach, ver = machine(), versions()
    threads = thread_info()
    now = dt.datetime.now().strftime("%Y-%m-%d %H:%M")
    sq = quantiles(truth["snr"])
    fq = quantiles(s2n_fit[np.isfinite(s2n_fit)])
    ms = {k: 1e3 / rate[k] for k in rate}

    lines = []
    add = lines.append
    add(f"| method (one core, in-process, {args.n} stamps) | best pass | per stamp | fits/s | "
        f"CPU/wall | flagged | mean abs(dg) | median abs(dg) | abs(dg) < 0.01 | noise-free: mean abs(dg) |")
    add("|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|")
    labels = {"perscli": "perscli `fit_exp` (exp mixture, exact PSF)",
              "fam": "GalSim `hsm.FindAdaptiveMom` (observed shape, no PSF correction)",
              "regauss": "GalSim `hsm.EstimateShear(shear_est='REGAUSS')` with the PSF image"}
    for k in ("perscli", "fam", "regauss"):
        a, a0 = acc[k], acc0[k]
        add(f"| {labels[k]} | {best[k][0]:.3f} s | {ms[k]:.2f} ms | **{rate[k]:.0f}** | {cpu_ratio[k]:.2f} | "
            f"{100 * badfrac[k]:.1f} % | {a['mean']:.4f} | {a['median']:.4f} | {100 * a['within']:.1f} % | "
            f"{a0['mean']:.2e} |")
    table = "\n".join(lines)

    flags_text = ", ".join(f"{n} with bit {b}" for b, n in flag_counts.items()) or "none"
    prof_text = ""
    if prof is not None:
        total, fit_rows, top = prof
        pl = [f"One more pass of `fit_exp` over the {args.n} noisy stamps under cProfile: {total:.2f} s "
              f"({1e3 * total / args.n:.1f} ms per fit with the profiler's overhead; full listing in "
              f"`benchmarks/work/measure/fit_profile.txt`).", "",
              "Functions of `perscli/measure/fit.py` (cumulative: including what they call):", "",
              "| function | calls | calls per fit | own time | cumulative | share of total |",
              "|---|---:|---:|---:|---:|---:|"]
        for r in fit_rows:
            pl.append(f"| `{r['func']}` (line {r['line']}) | {r['ncalls']} | {r['ncalls'] / args.n:.1f} | "
                      f"{r['tottime']:.3f} s | {r['cumtime']:.3f} s | {100 * r['cumtime'] / total:.0f} % |")
        pl += ["", "Top 15 by own time (everything):", "",
               "| function | calls | own time | share |", "|---|---:|---:|---:|"]
        for r in top:
            pl.append(f"| `{short_name(r)}` | {r['ncalls']} | {r['tottime']:.3f} s | "
                      f"{100 * r['tottime'] / total:.0f} % |")
        prof_text = "\n".join(pl)

    proc_text = ""
    if proc is not None:
        pe = proc["t_exp"] - proc["t_base"]
        proc_text = (
            f"- **whole process**: `perscli measure mosaic.fits --catalog mosaic_cat.fits -o shapes.fits "
            f"--overwrite` on a {proc['shape'][1]}x{proc['shape'][0]} float32 frame tiling the same {args.n} noisy stamps "
            f"(one tile = the stamp measure cuts), with a WHT extension (1/sigma^2) and a catalogue of x/y, hlr, "
            f"mag_J129: **{proc['t_exp']:.2f} s** spawn to exit (best of 2, after a warm-up) = "
            f"{args.n / proc['t_exp']:.0f} objects/s including interpreter start, imports, the Roman PSF, the "
            f"model table and writing; python importing perscli, galsim and astropy alone takes "
            f"{proc['t_base']:.2f} s, so {pe:.2f} s = {args.n / pe:.0f} objects/s above that.  "
            f"`--method hsm` (REGAUSS): {proc['t_hsm']:.2f} s.  The process's exp shapes equal this "
            f"process's fits of the same float32 stamps and weights from the same start to max abs(dg) = {proc['dg']:.1e}; "
            f"{proc['good']}/{args.n} rows unflagged.")

    proc_cmp = ""
    if proc is not None:
        proc_cmp = (f"; whole process {proc['t_exp']:.2f} s ({proc['t_exp'] / BEFORE['t_exp']:.2f} of before), "
                    f"`--method hsm` {proc['t_hsm']:.2f} s ({proc['t_hsm'] / BEFORE['t_hsm']:.2f} of before)")
    body = f"""
## measure: exp fits per second per core vs GalSim HSM (48x48 stamps)

Reproduce with `make bench-measure` (runs `.venv/bin/python benchmarks/bench_measure.py`).

- date: {now}
- machine: {mach['arch']}, {mach['cpu']}, {mach['nproc']} cores (nproc), {mach['memory']} RAM, Linux {mach['kernel']}
- versions: python {ver['python']}, numpy {ver['numpy']}, galsim {ver['galsim']}, astropy {ver['astropy']}, perscli {ver['perscli']} (git {git_commit()})
- threads: {threads}.  One process, one core: CPU time / wall time of each timed pass is in the table.
- stamps: {args.n} of {STAMP}x{STAMP} px drawn by GalSim (seed {args.seed}): `Exponential` with hlr uniform in
  {HLR_RANGE[0]}-{HLR_RANGE[1]}" ({HLR_RANGE[0] / PIXEL_SCALE:.1f}-{HLR_RANGE[1] / PIXEL_SCALE:.1f} px), |g| uniform in 0-{GMAX} at a uniform angle,
  centred at stamp pixel 24 (0-indexed) + U(-{OFFSET}, {OFFSET}) px on each axis, convolved with
  `galsim.roman.getPSF({SCA}, '{FILTER}', wavelength={wavelength:.1f} nm)` (the effective wavelength) in pixel units
  and the pixel (`maxk_threshold=1e-5`); Gaussian noise sigma = {SIGMA:.0f} e- (sky + read noise of a 140 s J129
  exposure).  Optimal S/N (sqrt(sum model^2)/sigma) log-uniform in {SNR_RANGE[0]:.0f}-{SNR_RANGE[1]:.0f}: min / 10 % / median / 90 % / max
  = {' / '.join(f'{v:.0f}' for v in sq)}; perscli's fitted flux / flux error: {' / '.join(f'{v:.0f}' for v in fq)}.
  Fluxes {truth['flux'].min():.0f}-{truth['flux'].max():.0f} e-.  Building the stamps: {stamp_s:.1f} s (not timed).
- perscli: `ExpModel(psf, {STAMP})` built once outside the timing ({model_s:.2f} s: FFT grid {model.size}, alias {model.alias}), then
  `fit_exp(stamp, weight, model, start)` per stamp with weight = 1/sigma^2 and the start `perscli measure`
  builds from a catalogue: position to 1e-3 px, g = 0, T from the hlr to 1e-3", flux from the magnitude to
  1e-3 mag.  GalSim: `galsim.Image`s of the same float64 stamps built outside the timing;
  `FindAdaptiveMom(im, weight=w, strict=False)` and `EstimateShear(im, psf_image, weight=w,
  shear_est='REGAUSS', strict=False)`, with the PSF image and the weight image `perscli measure --method hsm`
  uses (PSF x pixel drawn on {STAMP}x{STAMP}, `method='no_pixel'`); REGAUSS's distortion is turned into g as
  `perscli measure` does.
- timing: one untimed warm-up pass of 10 stamps per method, then {args.repeats} pass{'es' if args.repeats > 1 else ''} over all stamps,
  the methods interleaved; best pass reported (per-pass times below).  Per stamp = best pass / N.

{table}

dg = g_fit - g_true (both components; abs(dg) its modulus), over unflagged stamps.  With noise, the
noise dominates every method's error (perscli's median 1-sigma error per component here is
{np.median(gerr[np.isfinite(gerr)]):.3f}, from {np.max(gerr[np.isfinite(gerr)]):.3f} at the lowest S/N to
{np.min(gerr[np.isfinite(gerr)]):.4f} at the highest): the fraction within 0.01 mostly says how many stamps have
S/N high enough.  The last column is each method's floor on the same stamps without noise.
FindAdaptiveMom measures the PSF-convolved shape, so its error against the intrinsic g is
the PSF's rounding, not noise; it is here for its speed.

- **perscli fits per second per core: {rate['perscli']:.0f}** ({ms['perscli']:.2f} ms per fit); required >= {REQUIRED:.0f}
  (ngmix's exp fit with a fixed PSF, ~{NGMIX_MS:.0f} ms).  Per-fit times: median {1e3 * np.median(per_fit):.2f} ms,
  90 % {1e3 * np.percentile(per_fit, 90):.2f} ms, max {1e3 * per_fit.max():.2f} ms.
- perscli model evaluations per fit (`nfev`, the Jacobian ones included): mean {nfev.mean():.1f}, median
  {np.median(nfev):.0f}, max {nfev.max()} (noise-free stamps: mean {nfev0:.1f}); flagged fits: {int(np.sum(pflags != 0))}/{args.n}
  ({flags_text}).  Multiplicative bias (slope of g_fit on g_true - 1): perscli {acc['perscli']['bias']:+.4f},
  REGAUSS {acc['regauss']['bias']:+.4f} (noisy); noise-free perscli {acc0['perscli']['bias']:+.1e}, REGAUSS {acc0['regauss']['bias']:+.1e}.
- relative speed: FindAdaptiveMom is {rate['fam'] / rate['perscli']:.1f}x and REGAUSS {rate['regauss'] / rate['perscli']:.1f}x
  as fast as perscli's fit here ({ms['fam']:.2f} and {ms['regauss']:.2f} ms per stamp; NOTES' anchors ~0.2 and ~0.6 ms).
{proc_text}
- **before / after** (issue 8): recorded {BEFORE['date']} (commit {BEFORE['commit']}, same machine): perscli
  {BEFORE['rate']:.0f} fits/s, FindAdaptiveMom {BEFORE['fam']:.0f}/s, REGAUSS {BEFORE['regauss']:.0f}/s, whole `perscli measure`
  process {BEFORE['t_exp']:.2f} s (`--method hsm` {BEFORE['t_hsm']:.2f} s); now {rate['perscli']:.0f} fits/s ({rate['perscli'] / BEFORE['rate']:.2f}x before),
  FindAdaptiveMom {rate['fam'] / BEFORE['fam']:.2f}x and REGAUSS {rate['regauss'] / BEFORE['regauss']:.2f}x their rates before (the VM's speed
  varies between runs), perscli's rate relative to REGAUSS {(rate['perscli'] / rate['regauss']) / (BEFORE['rate'] / BEFORE['regauss']):.2f} of before{proc_cmp}.
- result: **{verdict}**

Per-pass times (s): perscli {', '.join(f'{t[0]:.3f}' for t in runs['perscli'])}; FindAdaptiveMom
{', '.join(f'{t[0]:.3f}' for t in runs['fam'])}; REGAUSS {', '.join(f'{t[0]:.3f}' for t in runs['regauss'])}.

### Where perscli's fit time goes

{prof_text if prof_text else '(profile skipped: --no-profile)'}
"""
    print(table)
    print(f"perscli: {rate['perscli']:.0f} fits/s per core (required >= {REQUIRED:.0f}); mean nfev "
          f"{nfev.mean():.1f}; flagged {int(np.sum(pflags != 0))}/{args.n}")
    if proc is not None:
        print(f"whole process: exp {proc['t_exp']:.2f} s, hsm {proc['t_hsm']:.2f} s, baseline imports "
              f"{proc['t_base']:.2f} s; max |dg| vs in-process {proc['dg']:.1e}")
    if prof is not None:
        total, fit_rows, top = prof
        print(f"profile: {total:.2f} s")
        for r in fit_rows:
            print(f"  {r['func']:<20} calls {r['ncalls']:>6} own {r['tottime']:.3f} cum {r['cumtime']:.3f}")
        for r in top:
            print(f"  {short_name(r):<70} calls {r['ncalls']:>6} own {r['tottime']:.3f}")
    print(f"before issue 8 ({BEFORE['date']}, {BEFORE['commit']}): {BEFORE['rate']:.0f} fits/s, FindAdaptiveMom "
          f"{BEFORE['fam']:.0f}/s, REGAUSS {BEFORE['regauss']:.0f}/s, whole process {BEFORE['t_exp']:.2f} s; now "
          f"{rate['perscli']:.0f}, {rate['fam']:.0f}, {rate['regauss']:.0f}/s" + (f", {proc['t_exp']:.2f} s" if proc else ""))
    print(verdict)

    dest = args.results
    if dest is None and not args.no_results and args.n == N_DEFAULT:
        dest = HERE / "RESULTS.md"
    if dest is not None and not args.no_results:
        write_section(dest, SECTION, body)
        print(f"wrote section '{SECTION}' of {dest}")
    return 0 if passed else 1


if __name__ == "__main__":
    sys.exit(main())
