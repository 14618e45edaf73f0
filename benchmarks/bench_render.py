#!/usr/bin/env python
"""Benchmark: ``perscli render`` of a full Roman SCA against a straightforward GalSim loop.

Run with ``make bench-render`` (that is, ``.venv/bin/python benchmarks/bench_render.py``).

The requirement: one full SCA exposure at the paper's densities (about 2,250
galaxies and 140 stars) drawn at least 3x faster than a straightforward GalSim
loop (each object drawn by FFT convolution with the Roman PSF), in one run, at
matching pixel values; the agreement reached is documented.

What it does:

1. Makes a truth catalogue with ``perscli catalog`` (40 galaxies and 2.5 stars
   per arcmin^2, fixed seed) on a square field centred on SCA 7 of the pointing
   ra=10 dec=-44 pa=30 mjd=61541.97, large enough to cover the rotated SCA plus
   a 1 arcmin margin (objects just off the SCA whose stamps reach it are drawn
   too, by both sides).
2. perscli: times ``perscli.render.exposure.draw_sources(cols, exposure)`` in
   this process (sources only: optics, planning and stamps, expected electrons)
   with 1 and 2 workers, and the whole ``perscli render ... --seed 1 -o out.fits``
   process (interpreter start to exit: imports, catalogue, optics, drawing, the
   full Roman detector chain, writing SCI/IDEAL/FLUENCE) with ``--workers 1`` and 2.
3. GalSim: a straightforward loop in the same run with the same optics
   (``Optics``: WCS, the SCA-oriented Roman PSF in pixel units, zeropoint) and the
   same stamps (``plan_objects``): for each object,
   ``galsim.Convolve(profile, psf).drawImage(image=stamp, center=(x, y), method='auto')``
   with a ``galsim.DeltaFunction`` for a star or ``wcs.local(pos).toImage(
   galsim.Exponential(half_light_radius=hlr, flux=f).shear(g1=e1, g2=e2))`` for a
   galaxy, the stamp added to a 4088x4088 image.  Timed like ``draw_sources``:
   building the ``Optics`` and the plan included.  Run once more with the
   galaxies' ``maxk_threshold`` tightened to 1e-5 (GalSim's default, 1e-3, cuts
   the larger galaxies' Fourier transforms inside the PSF's band).
4. Agreement of the images, per object (max |diff| / the object's peak, over
   the whole stamp and over its central half), over the image, in total flux,
   and an experiment that draws a subset with perscli's drawer on GalSim's own
   FFT period to show where the residual comes from.
5. Optionally profiles both (``--no-profile`` to skip), prints a table and
   writes its section of ``benchmarks/RESULTS.md``.
"""

from __future__ import annotations

import argparse
import datetime as dt
import math
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

from perscli.instrument import ROMAN_SCA_SIZE

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))
from bench_apply_persistence import (  # noqa: E402  (helpers shared with the other benchmark)
    _PROFILE,
    git_commit, machine, perscli_command, run_child, versions, write_section)

SECTION = "render"
RA, DEC, PA, MJD = 10.0, -44.0, 30.0, 61541.97
SCA, FILTER = 7, "J129"
GALAXY_DENSITY = 40.0      # per arcmin^2 (the paper's)
STAR_DENSITY = 2.5         # per arcmin^2 (the paper's)
MARGIN_ARCMIN = 1.0        # catalogue field beyond the SCA's corners, each side
CATALOG_SEED = 1
RENDER_SEED = 1
RATIO_REQUIRED = 3.0
INNER_TOL = 1.0e-3         # central half of every stamp: |perscli - GalSim| < INNER_TOL x the object's peak
SAME_PERIOD_TOL = 1.0e-6   # perscli's drawer on GalSim's FFT period: |diff| < this x the peak
ACCURATE_MAXK = 1.0e-5     # GalSim's maxk_threshold for the galaxies in the tightened run (default 1e-3)
SIZE = ROMAN_SCA_SIZE


def exposure_of(bounds=None):
    from perscli.render.exposure import Exposure

    return Exposure(ra=RA, dec=DEC, pa=PA, sca=SCA, filter=FILTER, mjd=MJD, bounds=bounds)


# --------------------------------------------------------------------------------------------
# the catalogue
# --------------------------------------------------------------------------------------------

def make_catalog(workdir: Path, optics, seed: int, bounds) -> tuple[Path, dict]:
    """``perscli catalog`` on a square field (tangent plane) centred on the SCA, covering its corners."""
    import galsim
    from astropy.io import fits

    xmin, xmax, ymin, ymax = bounds
    centre = optics.wcs.toWorld(galsim.PositionD((xmin + xmax) / 2, (ymin + ymax) / 2))
    half = 0.0
    for cx in (xmin - 0.5, xmax + 0.5):
        for cy in (ymin - 0.5, ymax + 0.5):
            u, v = centre.project(optics.wcs.toWorld(galsim.PositionD(cx, cy)), projection="gnomonic")
            half = max(half, abs(u / galsim.arcmin), abs(v / galsim.arcmin))
    size = round(2 * (half + MARGIN_ARCMIN), 2)
    path = workdir / "truth.fits"
    cmd = perscli_command() + ["catalog", "--ra", repr(centre.ra / galsim.degrees),
                               "--dec", repr(centre.dec / galsim.degrees), "--size", str(size),
                               "--galaxy-density", str(GALAXY_DENSITY), "--star-density", str(STAR_DENSITY),
                               "--seed", str(seed), "-o", str(path), "--overwrite"]
    subprocess.run(cmd, check=True, stdout=subprocess.DEVNULL)
    hdr = fits.getheader(path, 1)
    info = dict(ra=centre.ra / galsim.degrees, dec=centre.dec / galsim.degrees, size=size,
                ngal=int(hdr["NGAL"]), nstar=int(hdr["NSTAR"]), area=float(hdr["FIELDAR"]), cmd=cmd)
    return path, info


# --------------------------------------------------------------------------------------------
# the two sides
# --------------------------------------------------------------------------------------------

def perscli_sources(cols, exposure, workers: int) -> tuple[float, np.ndarray, int]:
    from perscli.render.exposure import draw_sources

    t0 = time.perf_counter()
    image, nobj, _ = draw_sources(cols, exposure, workers=workers)
    return time.perf_counter() - t0, image, nobj


def galsim_profile(optics, cols, i, x, y, flux, gsparams=None):
    """The object's profile in image coordinates (pixels), with its flux."""
    import galsim

    if cols["kind"][i] == "star":
        return galsim.DeltaFunction(flux=flux)
    gal = galsim.Exponential(half_light_radius=float(cols["hlr"][i]), flux=flux, gsparams=gsparams)
    gal = gal.shear(g1=float(cols["e1"][i]), g2=float(cols["e2"][i]))
    return optics.wcs.local(galsim.PositionD(x, y)).toImage(gal)


def galsim_convolve(prof, psf, accurate: bool):
    """Convolve(prof, psf); ``accurate``: keep each component's own GSParams (the galaxy's tighter
    maxk_threshold must not be propagated to the PSF, which would rebuild it for every object)."""
    import galsim

    return galsim.Convolve(prof, psf, propagate_gsparams=False) if accurate else galsim.Convolve(prof, psf)


def galsim_loop(cols, exposure, keep: bool = False, subset=None, maxk_threshold=None):
    """The straightforward GalSim loop; returns (seconds, image array, stamps, plan).

    ``maxk_threshold``: GSParams of the galaxies (None: GalSim's default, 1e-3).
    """
    import galsim

    from perscli.optics import Optics
    from perscli.render.exposure import plan_objects

    gsparams = None if maxk_threshold is None else galsim.GSParams(maxk_threshold=maxk_threshold)
    t0 = time.perf_counter()
    optics = Optics(exposure)
    xmin, xmax, ymin, ymax = exposure.full_bounds
    image = galsim.ImageD(galsim.BoundsI(xmin, xmax, ymin, ymax), scale=1.0)
    todo, x, y, flux, sizes = plan_objects(cols, optics, exposure.full_bounds)
    if subset is not None:
        todo = todo[subset]
    psf = optics.psf_pixels          # the SCA-oriented Roman PSF, pixel units
    stamps = []
    for i in todo:
        xi, yi, n = float(x[i]), float(y[i]), int(sizes[i])
        prof = galsim_profile(optics, cols, i, xi, yi, float(flux[i]), gsparams)
        ix, iy = math.floor(xi + 0.5), math.floor(yi + 0.5)
        # the same n x n stamp as perscli: array index [n/2, n/2] is pixel (ix, iy)
        stamp = galsim.ImageD(galsim.BoundsI(ix - n // 2, ix - n // 2 + n - 1, iy - n // 2, iy - n // 2 + n - 1),
                              scale=1.0)
        galsim_convolve(prof, psf, gsparams is not None).drawImage(
            image=stamp, center=galsim.PositionD(xi, yi), method="auto")
        overlap = stamp.bounds & image.bounds
        if overlap.isDefined():
            image[overlap] += stamp[overlap]
        if keep:
            stamps.append(stamp)
    seconds = time.perf_counter() - t0
    return seconds, image.array, stamps, (optics, todo, x, y, flux, sizes)


#: the whole-process figures recorded before issue 8 (FITS through fitsio, effect registry with saturation
#: on by default, one executor) on the same machine, RESULTS.md at commit 132d716: the reference of "not slower"
BEFORE = dict(date="2026-11-22 19:57", commit="132d716", galsim=24.33, s1=2.57, s2=2.72, p1=6.50, rss=1239e6,
              written=200e6)
SIZE_REQUIRED = 0.5        # --compress output / plain output (issue 8)


def _readback(path: Path, plain: dict | None) -> dict:
    """Read ``path`` with astropy (checksums verified, warnings as errors) and fitsio (verify_checksum of
    every HDU); return the SCI/IDEAL/FLUENCE arrays and whether they equal ``plain``'s bit for bit."""
    import warnings

    import fitsio
    from astropy.io import fits

    out = {}
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        with fits.open(path, checksum=True) as hdul:
            astro = {e: np.array(hdul[e].data) for e in ("SCI", "IDEAL", "FLUENCE")}
            nhdu = len(hdul)
    with fitsio.FITS(str(path)) as f:
        for hdu in f:
            hdu.verify_checksum()           # raises on a bad CHECKSUM or DATASUM
        fio = {e: f[e].read() for e in ("SCI", "IDEAL", "FLUENCE")}
    out["same_readers"] = all(np.array_equal(astro[e], fio[e], equal_nan=True) for e in astro)
    out["lossless"] = True if plain is None else all(
        astro[e].dtype.newbyteorder('=') == plain[e].dtype.newbyteorder('=') and np.array_equal(astro[e], plain[e], equal_nan=True) for e in astro)
    out["nhdu"] = nhdu
    out["arrays"] = astro
    return out


def output_sizes(truth: Path, workdir: Path, bounds) -> tuple[str, bool, dict]:
    """The same render written plain, tile-compressed (--compress gzip) and as .fits.gz: sizes, times, and
    whether each reads back in astropy and fitsio with valid checksums and the plain file's pixels."""
    variants = (("plain", "size_plain.fits", []), ("--compress gzip", "size_tiles.fits", ["--compress", "gzip"]),
                ("-o x.fits.gz", "size_whole.fits.gz", []))
    rows, sizes, cmds, plain, checks = [], {}, {}, None, {}
    for label, name, extra in variants:
        dest = workdir / name
        cmd = render_command(truth, dest, 1, bounds) + extra
        wall, rss, _ = run_child(cmd)
        sizes[label] = dest.stat().st_size
        rb = _readback(dest, plain)
        if plain is None:
            plain = rb["arrays"]
        checks[label] = rb["lossless"] and rb["same_readers"]
        cmds[label] = " ".join(["perscli"] + cmd[len(perscli_command()):]).replace(str(workdir) + "/", "")
        rows.append(f"| {label} | {sizes[label] / 1e6:.1f} MB | {sizes[label] / sizes['plain']:.2f} | "
                    f"{sizes[label] / BEFORE['written']:.2f} | {wall:.2f} s | {rss / 1e6:.0f} MB | "
                    f"{'yes' if checks[label] else '**no**'} |")
        print(f"  {label}: {sizes[label] / 1e6:.1f} MB ({sizes[label] / sizes['plain']:.2f} of plain), {wall:.2f} s, "
              f"peak RSS {rss / 1e6:.0f} MB; reads back with valid checksums, same pixels as plain: {checks[label]}",
              flush=True)
    del plain
    ratio = sizes["--compress gzip"] / sizes["plain"]
    ok = ratio <= SIZE_REQUIRED and all(checks.values())
    md = "\n".join([
        "### Output size (issue 8: a full SCA with `--compress` at most half the plain size)", "",
        "The same render (primary, SCI, IDEAL, FLUENCE, MODEL) written three ways, each timed as a whole process "
        "(`--workers 1`) once after the timings above; `--compress gzip` is CFITSIO tile compression of the images "
        "(GZIP_2, lossless: no quantisation), `.fits.gz` gzips the whole file.  Commands:", "",
        *[f"- {label}: `{cmds[label]}`" for label, _, _ in variants], "",
        f"| output | size | / plain | / before issue 8 ({BEFORE['written'] / 1e6:.0f} MB) | whole process | peak RSS | reads back (astropy and "
        "fitsio, checksums verified), same pixels as plain |",
        "|---|---:|---:|---:|---:|---:|---|", *rows, "",
        f"- result: **{'PASS' if ok else 'FAIL'}** (`--compress gzip` / plain = {ratio:.2f}, required <= "
        f"{SIZE_REQUIRED:g}; / the {BEFORE['written'] / 1e6:.0f} MB written before issue 8 = "
        f"{sizes['--compress gzip'] / BEFORE['written']:.2f})"])
    return md, ok, sizes


def render_command(truth: Path, dest: Path, workers: int, bounds) -> list:
    cmd = perscli_command() + ["render", str(truth), "--ra", str(RA), "--dec", str(DEC), "--pa", str(PA),
                               "--mjd", str(MJD), "--filter", FILTER, "--sca", str(SCA),
                               "--seed", str(RENDER_SEED), "-o", str(dest), "--overwrite"]
    if workers != 1:
        cmd += ["--workers", str(workers)]
    if bounds is not None:
        cmd += ["--bounds", *(str(b) for b in bounds)]
    return cmd


# --------------------------------------------------------------------------------------------
# agreement
# --------------------------------------------------------------------------------------------

def perscli_stamp(drawer, optics, cols, i, x, y, flux, n):
    """One object's stamp exactly as ``perscli.render.exposure.draw_sources`` draws it."""
    import galsim

    profile = None
    if cols["kind"][i] == "galaxy":
        gal = galsim.Exponential(half_light_radius=float(cols["hlr"][i]), flux=1.0)
        gal = gal.shear(g1=float(cols["e1"][i]), g2=float(cols["e2"][i]))
        profile = optics.wcs.local(galsim.PositionD(x, y)).toImage(gal)
    ix, iy = math.floor(x + 0.5), math.floor(y + 0.5)
    return drawer.stamp(n, x - ix, y - iy, flux, profile)


def perscli_stamps(cols, exposure, plan, p_image):
    """Every object's perscli stamp, re-drawn one by one; and how far their sum is from ``p_image``."""
    from perscli.optics import StampDrawer

    optics, todo, x, y, flux, sizes = plan
    xmin, xmax, ymin, ymax = exposure.full_bounds
    drawer = StampDrawer(optics.psf_pixels)
    recon = np.zeros_like(p_image)
    stamps = []
    for i in todo:
        n = int(sizes[i])
        p = perscli_stamp(drawer, optics, cols, i, float(x[i]), float(y[i]), float(flux[i]), n)
        x0, y0 = math.floor(x[i] + 0.5) - n // 2, math.floor(y[i] + 0.5) - n // 2
        a0, a1 = max(x0, xmin), min(x0 + n, xmax + 1)
        b0, b1 = max(y0, ymin), min(y0 + n, ymax + 1)
        if a0 < a1 and b0 < b1:
            recon[b0 - ymin:b1 - ymin, a0 - xmin:a1 - xmin] += p[b0 - y0:b1 - y0, a0 - x0:a1 - x0]
        stamps.append(p)
    return stamps, float(np.max(np.abs(recon - p_image)))


def agreement(cols, exposure, plan, p_stamps, p_image, g_stamps, g_image) -> dict:
    """Per-object and image-level comparison of perscli's and GalSim's stamps and images.

    Per object: max |p - g| / peak over the stamp and over its central half (n/4 .. 3n/4 on
    each axis), peak = the object's brightest GalSim pixel; the flux each stamp holds.
    Image: max |P - G| / the peak of the brightest object whose stamp covers the pixel, over
    all pixels and over the pixels that lie in the central half of every stamp covering them.
    """
    optics, todo, x, y, flux, sizes = plan
    xmin, xmax, ymin, ymax = exposure.full_bounds
    peakmap = np.zeros_like(p_image)       # peak of the brightest object whose stamp covers the pixel
    ring = np.zeros(p_image.shape, dtype=np.int32)   # number of stamps whose outer part covers the pixel
    rows = []
    for j, i in enumerate(todo):
        n = int(sizes[i])
        g, p = g_stamps[j].array, p_stamps[j]
        peak = float(g.max())
        d = np.abs(p - g)
        q = slice(n // 4, 3 * n // 4)
        rows.append((cols["kind"][i] == "star", n, peak, d.max() / peak, d[q, q].max() / peak,
                     p.sum() / flux[i], g.sum() / flux[i]))
        x0, y0 = g_stamps[j].bounds.xmin, g_stamps[j].bounds.ymin
        a0, a1 = max(x0, xmin), min(x0 + n, xmax + 1)
        b0, b1 = max(y0, ymin), min(y0 + n, ymax + 1)
        if a0 < a1 and b0 < b1:
            sl = (slice(b0 - ymin, b1 - ymin), slice(a0 - xmin, a1 - xmin))
            np.maximum(peakmap[sl], peak, out=peakmap[sl])
            ring[sl] += 1
            c0, c1 = max(x0 + n // 4, xmin), min(x0 + 3 * n // 4, xmax + 1)
            e0, e1 = max(y0 + n // 4, ymin), min(y0 + 3 * n // 4, ymax + 1)
            if c0 < c1 and e0 < e1:
                ring[e0 - ymin:e1 - ymin, c0 - xmin:c1 - xmin] -= 1
    r = np.array(rows, dtype=[("star", bool), ("n", int), ("peak", float), ("full", float), ("inner", float),
                              ("pflux", float), ("gflux", float)])
    diff = np.abs(p_image - g_image)
    covered = peakmap > 0
    rel = np.zeros_like(diff)
    rel[covered] = diff[covered] / peakmap[covered]
    inner = covered & (ring == 0)
    k = int(np.argmax(diff))
    return dict(
        rows=r,
        img_maxabs=float(diff.max()), img_max=float(g_image.max()),
        img_maxabs_at=(k % diff.shape[1] + xmin, k // diff.shape[1] + ymin),
        img_rel=float(rel.max()), img_rel_inner=float(rel[inner].max()) if np.any(inner) else float("nan"),
        inner_pixels=int(inner.sum()),
        p_sum=float(p_image.sum()), g_sum=float(g_image.sum()),
    )


def same_period(cols, exposure, plan, stride: int, max_n: int, maxk_threshold: float) -> np.ndarray:
    """A subset drawn by GalSim (recording its FFT size N) and by perscli's drawer at n, 2n and N.

    GalSim draws by FFT on an N x N grid (N >= 256 here: the PSF's stepk) and crops the
    n x n stamp, so its stamp is periodic with period N; perscli's is periodic with period n
    (the wings beyond the stamp fold back in).  Drawing perscli's stamp on N x N and
    cropping the centre gives the same period as GalSim: what differs then is the rest.
    GalSim is run with its default GSParams and with ``maxk_threshold`` for the galaxies.
    """
    import galsim

    from perscli.optics import StampDrawer

    optics, todo, x, y, flux, sizes = plan
    drawer = StampDrawer(optics.psf_pixels)
    psf = optics.psf_pixels
    gsp = galsim.GSParams(maxk_threshold=maxk_threshold)
    pick = [i for k, i in enumerate(todo) if (k % stride == 0 or cols["kind"][i] == "star") and sizes[i] <= max_n]
    recorded = {}
    original = galsim.GSObject.drawFFT_makeKImage

    def spy(self, image):
        kimage, wrap = original(self, image)
        recorded["N"] = wrap
        return kimage, wrap

    def gs_stamp(i, xi, yi, n, gsparams):
        ix, iy = math.floor(xi + 0.5), math.floor(yi + 0.5)
        stamp = galsim.ImageD(galsim.BoundsI(ix - n // 2, ix - n // 2 + n - 1, iy - n // 2, iy - n // 2 + n - 1),
                              scale=1.0)
        recorded.clear()
        prof = galsim_profile(optics, cols, i, xi, yi, float(flux[i]), gsparams)
        galsim_convolve(prof, psf, gsparams is not None).drawImage(
            image=stamp, center=galsim.PositionD(xi, yi), method="auto")
        return stamp.array, int(recorded["N"])

    out = []
    galsim.GSObject.drawFFT_makeKImage = spy
    try:
        for i in pick:
            xi, yi, n = float(x[i]), float(y[i]), int(sizes[i])
            g, big_n = gs_stamp(i, xi, yi, n, None)
            ga, big_na = gs_stamp(i, xi, yi, n, gsp)
            res = [cols["kind"][i] == "star", n, big_n, big_na]
            p_by_m = {}
            for m in (n, 2 * n, big_n, big_na):
                if m not in p_by_m:
                    p = perscli_stamp(drawer, optics, cols, i, xi, yi, float(flux[i]), m)
                    c = (m - n) // 2
                    p_by_m[m] = p[c:c + n, c:c + n]
            for ref, m in ((g, n), (g, 2 * n), (g, big_n), (ga, n), (ga, big_na)):
                res.append(float(np.abs(p_by_m[m] - ref).max() / ref.max()))
            out.append(tuple(res))
    finally:
        galsim.GSObject.drawFFT_makeKImage = original
    return np.array(out, dtype=[("star", bool), ("n", int), ("N", int), ("Na", int), ("d_n", float),
                                ("d_2n", float), ("d_N", float), ("a_n", float), ("a_N", float)])


# --------------------------------------------------------------------------------------------
# profiles
# --------------------------------------------------------------------------------------------


#: (label, function name, file name ending); nested entries are indented in the label
RENDER_PHASES = [
    ("imports (after interpreter start)", "_find_and_load", "<frozen importlib._bootstrap>"),
    ("read_truth (catalogue)", "read_truth", "exposure.py"),
    ("draw_sources (optics, plan, stamps, adding them)", "draw_sources", "exposure.py"),
    ("- Optics (WCS, bandpass, getPSF; includes importing galsim)", "__init__", "render/exposure.py"),
    ("- StampDrawer.stamp x objects", "stamp", "draw.py"),
    ("-- PSF x pixel transfer tables (once per stamp size)", "table", "draw.py"),
    ("-- GSObject.drawKImage (galaxies; the PSF for the tables)", "drawKImage", "galsim/gsobject.py"),
    ("run_chain (detector effects)", "run_chain", "detector/chain.py"),
    ("- IPC (3x3 convolution)", "apply_ipc", "effects.py"),
    ("write_hdus (SCI, IDEAL, FLUENCE; checksums)", "write_hdus", "output.py"),
]

GALSIM_PHASES = [
    ("Optics (WCS, bandpass, getPSF)", "__init__", "render/exposure.py"),
    ("Convolve(...).drawImage x objects", "drawImage", "galsim/gsobject.py"),
    ("- sizing the FFT (drawFFT_makeKImage; the first call builds the PSF)", "drawFFT_makeKImage",
     "galsim/gsobject.py"),
    ("- k-image of galaxy x PSF (Convolution._drawKImage)", "_drawKImage", "galsim/convolve.py"),
    ("- wrap + inverse FFT + crop (drawFFT_finish)", "drawFFT_finish", "galsim/gsobject.py"),
]


def _phases(stats, table):
    out = []
    for label, func, fname in table:
        ct = sum(v[3] for (f, _, name), v in stats.stats.items() if name == func and f.endswith(fname))
        out.append((label, ct))
    return out


def profile_render(cmd_args: list, workdir: Path):
    import io
    import pstats

    out = workdir / "render.prof"
    # _PROFILE takes the statistics file as its first argument, then perscli's
    subprocess.run([sys.executable, "-c", _PROFILE, str(out), *cmd_args], check=True,
                   stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    stats = pstats.Stats(str(out))
    buf = io.StringIO()
    pstats.Stats(str(out), stream=buf).sort_stats("cumulative").print_stats(40)
    (workdir / "render_profile.txt").write_text(buf.getvalue())
    return _phases(stats, RENDER_PHASES), stats.total_tt


def profile_galsim(cols, exposure, workdir: Path, stride: int):
    import cProfile
    import io
    import pstats

    prof = cProfile.Profile()
    prof.runcall(galsim_loop, cols, exposure, False, slice(None, None, stride))
    out = workdir / "galsim_loop.prof"
    prof.dump_stats(str(out))
    stats = pstats.Stats(str(out))
    buf = io.StringIO()
    pstats.Stats(str(out), stream=buf).sort_stats("cumulative").print_stats(40)
    (workdir / "galsim_loop_profile.txt").write_text(buf.getvalue())
    return _phases(stats, GALSIM_PHASES), stats.total_tt


# --------------------------------------------------------------------------------------------

def pct(a, q):
    return float(np.percentile(a, q)) if len(a) else float("nan")


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--workdir", type=Path, default=HERE / "work" / "render",
                    help="folder for the catalogue, outputs and profiles (default: benchmarks/work/render)")
    ap.add_argument("--repeats", type=int, default=3,
                    help="timed repeats of the perscli runs, best reported (default 3); the GalSim loop is "
                         "repeated as well unless its first run takes more than --galsim-once seconds")
    ap.add_argument("--galsim-once", type=float, default=30.0, metavar="SECONDS",
                    help="run the GalSim loop only once if it takes longer than this (default 30)")
    ap.add_argument("--seed", type=int, default=CATALOG_SEED, help=f"catalogue seed (default {CATALOG_SEED})")
    ap.add_argument("--bounds", type=int, nargs=4, metavar=("XMIN", "XMAX", "YMIN", "YMAX"),
                    help="a cutout of the SCA instead of all of it (a quick smoke test; writes no results "
                         "unless --results is given)")
    ap.add_argument("--results", type=Path, default=None,
                    help="write the results here (default: benchmarks/RESULTS.md, full SCA only)")
    ap.add_argument("--no-results", action="store_true", help="do not write a results file")
    ap.add_argument("--no-profile", action="store_true", help="skip the cProfile runs of both sides")
    ap.add_argument("--no-sizes", action="store_true",
                    help="skip writing the render plain, with --compress gzip and as .fits.gz (output sizes)")
    args = ap.parse_args(argv)
    if args.repeats < 1:
        ap.error("--repeats must be >= 1")

    from perscli.optics import Optics
    from perscli.render.exposure import read_truth

    workdir = args.workdir.resolve()
    workdir.mkdir(parents=True, exist_ok=True)
    exposure = exposure_of(tuple(args.bounds) if args.bounds else None)
    bounds = exposure.full_bounds
    t0 = time.perf_counter()
    optics = Optics(exposure)        # also warms GalSim's aperture cache for both in-process sides
    optics_s = time.perf_counter() - t0

    truth, cat = make_catalog(workdir, optics, args.seed, bounds)
    cols = read_truth(str(truth), FILTER)
    x, y = optics.positions(cols["ra"], cols["dec"])
    xmin, xmax, ymin, ymax = bounds
    on = (x >= xmin - 0.5) & (x < xmax + 0.5) & (y >= ymin - 0.5) & (y < ymax + 0.5)
    is_star = cols["kind"] == "star"
    sca_area = optics.wcs.pixelArea(optics.centre) * (xmax - xmin + 1) * (ymax - ymin + 1) / 3600.0
    n_on_gal, n_on_star = int(np.sum(on & ~is_star)), int(np.sum(on & is_star))
    print(f"catalogue: {truth} ({cat['ngal']} galaxies, {cat['nstar']} stars on {cat['size']}' x {cat['size']}'); "
          f"centres on the {sca_area:.1f} arcmin^2 image: {n_on_gal} galaxies, {n_on_star} stars")

    cmd_w1 = render_command(truth, workdir / "out.fits", 1, args.bounds)
    cmd_w2 = render_command(truth, workdir / "out_w2.fits", 2, args.bounds)
    print("warm-up (untimed): perscli render once")
    run_child(cmd_w1)

    g_times, s1, s2, p1, p2 = [], [], [], [], []
    g_image = p_image = p2_image = g_stamps = plan = None
    for r in range(args.repeats):
        if r == 0 or g_times[0] <= args.galsim_once:
            t, img, st, pl = galsim_loop(cols, exposure, keep=(r == 0))
            g_times.append(t)
            if r == 0:
                g_image, g_stamps, plan = img, st, pl
            del img, st
        t, img, _ = perscli_sources(cols, exposure, 1)
        s1.append(t)
        if r == 0:
            p_image = img
        t, img, _ = perscli_sources(cols, exposure, 2)
        s2.append(t)
        if r == 0:
            p2_image = img
        del img
        p1.append(run_child(cmd_w1)[:2])
        p2.append(run_child(cmd_w2)[:2])
        print(f"  repeat {r + 1}/{args.repeats}: galsim loop {g_times[-1]:.2f} s"
              f"{'' if len(g_times) == r + 1 else ' (not repeated)'}, draw_sources {s1[-1]:.2f} s, "
              f"workers=2 {s2[-1]:.2f} s; perscli render {p1[-1][0]:.2f} s, --workers 2 {p2[-1][0]:.2f} s",
              flush=True)
    # GalSim with the galaxies' maxk_threshold tightened, once: the accuracy at which it reproduces
    # perscli's pixel values on its own FFT period
    ga_time, ga_image, ga_stamps, _ = galsim_loop(cols, exposure, keep=True, maxk_threshold=ACCURATE_MAXK)
    print(f"  galsim loop, galaxies with maxk_threshold={ACCURATE_MAXK:g} (once): {ga_time:.2f} s", flush=True)

    g_best, s1_best, s2_best = min(g_times), min(s1), min(s2)
    p1_best, p2_best = min(t for t, _ in p1), min(t for t, _ in p2)
    p1_rss = max(m for _, m in p1)
    p2_rss = max(m for _, m in p2)
    ratios = dict(s1=g_best / s1_best, s2=g_best / s2_best, p1=g_best / p1_best, p2=g_best / p2_best,
                  a1=ga_time / s1_best, ap=ga_time / p1_best)

    # ---- agreement --------------------------------------------------------------------------
    print("agreement: perscli vs GalSim, per object and over the image")
    same_workers = bool(np.array_equal(p_image, p2_image))
    del p2_image
    p_stamps, recon_maxabs = perscli_stamps(cols, exposure, plan, p_image)
    ag = agreement(cols, exposure, plan, p_stamps, p_image, g_stamps, g_image)
    del g_stamps, g_image
    aa = agreement(cols, exposure, plan, p_stamps, p_image, ga_stamps, ga_image)
    del ga_stamps, ga_image, p_stamps
    rows, arows = ag["rows"], aa["rows"]
    # the rendered files: IDEAL = sources + sky (float32); --workers 1 and 2 give the same data
    from astropy.io import fits
    with fits.open(workdir / "out.fits") as hd1, fits.open(workdir / "out_w2.fits") as hd2:
        file_same = all(np.array_equal(hd1[e].data, hd2[e].data) for e in ("SCI", "IDEAL", "FLUENCE"))
        ideal = np.asarray(hd1["IDEAL"].data, dtype=np.float64)
        sky_e = float(hd1["SCI"].header["SKYRATE"]) * exposure.exptime
        nobj_file = int(hd1["SCI"].header["NOBJ"])
    ideal_rel = float(np.max(np.abs(ideal - (p_image + sky_e)) / (p_image + sky_e)))
    del ideal
    stride = max(1, len(rows) // 200)
    sp = same_period(cols, exposure, plan, stride, max_n=512, maxk_threshold=ACCURATE_MAXK)

    profile = None
    if not args.no_profile:
        print("profile: perscli render --workers 1 under cProfile; the GalSim loop on every 10th object")
        profile = (profile_render(cmd_w1[len(perscli_command()):], workdir),
                   profile_galsim(cols, exposure, workdir, 10))

    sizes_md, sizes_ok, sizes = "", True, None
    if not args.no_sizes:
        print("output sizes: the same render plain, with --compress gzip and as .fits.gz (read back and compared)")
        sizes_md, sizes_ok, sizes = output_sizes(truth, workdir, args.bounds)
    written = (workdir / "out.fits").stat().st_size

    inner_acc = float(arows["inner"].max())
    sp_max = float(sp["a_N"].max()) if len(sp) else 0.0
    checks_ok = recon_maxabs == 0.0 and same_workers and file_same and ideal_rel < 1e-7 and nobj_file == len(rows)
    agree_ok = inner_acc < INNER_TOL and sp_max < SAME_PERIOD_TOL
    speed_ok = ratios["p1"] >= RATIO_REQUIRED and ratios["s1"] >= RATIO_REQUIRED
    ok = agree_ok and speed_ok and checks_ok and sizes_ok

    # ---- report -----------------------------------------------------------------------------
    n_star, n_gal = int(rows["star"].sum()), int((~rows["star"]).sum())
    size_counts = {int(n): int(np.sum(rows["n"] == n)) for n in np.unique(rows["n"])}
    time_rows = [
        ("GalSim loop: Convolve(obj, psf).drawImage(method='auto') per object, in-process", g_best, None, 1.0),
        (f"GalSim loop, galaxies with maxk_threshold={ACCURATE_MAXK:g} (one run)", ga_time, None, g_best / ga_time),
        ("perscli draw_sources(cols, exposure), in-process", s1_best, None, ratios["s1"]),
        ("perscli draw_sources(..., workers=2), in-process", s2_best, None, ratios["s2"]),
        ("perscli render ... -o out.fits (whole process, detector chain, 3 HDUs)", p1_best, p1_rss, ratios["p1"]),
        ("perscli render ... --workers 2 (whole process)", p2_best, p2_rss, ratios["p2"]),
    ]
    print()
    print(f"objects drawn: {len(rows)} ({n_gal} galaxies, {n_star} stars); stamp sizes {size_counts}")
    print(f"{'':82s} {'best s':>8s} {'GalSim/x':>9s} {'peak RSS':>9s}")
    for label, t, rss, ratio in time_rows:
        print(f"{label:82s} {t:8.2f} {ratio:8.1f}x " + (f"{rss / 1e6:6.0f} MB" if rss else ""))
    print(f"speed ratio required >= {RATIO_REQUIRED:g}x (sources only and whole process, --workers 1); "
          f"against the tightened GalSim: {ratios['a1']:.1f}x, {ratios['ap']:.1f}x")

    def dist(a):
        return f"median {np.median(a):.1e}, 99th pct {pct(a, 99):.1e}, max {np.max(a):.1e}"

    for name, a in (("GalSim default", ag), (f"GalSim maxk_threshold={ACCURATE_MAXK:g}", aa)):
        rr = a["rows"]
        print(f"vs {name}: per object max |diff| / peak: whole stamp {dist(rr['full'])}; "
              f"central half {dist(rr['inner'])}")
        for n in size_counts:
            m = rr["n"] == n
            print(f"    n={n:5d} ({int(m.sum()):4d}): whole {np.max(rr['full'][m]):.1e}, central half "
                  f"{np.max(rr['inner'][m]):.1e}; flux in stamp perscli {np.median(rr['pflux'][m]):.5f}, "
                  f"GalSim {np.median(rr['gflux'][m]):.5f} (median)")
        print(f"    image: max |diff| {a['img_maxabs']:.3g} e- at {a['img_maxabs_at']} (image max "
              f"{a['img_max']:.3g} e-); max |diff| / peak of the brightest object covering the pixel "
              f"{a['img_rel']:.1e} (pixels inside the central half of every stamp covering them: "
              f"{a['img_rel_inner']:.1e}); total flux GalSim/perscli - 1 = {a['g_sum'] / a['p_sum'] - 1:+.2e}")
    print(f"central half vs the tightened GalSim: max {inner_acc:.1e} (required < {INNER_TOL:g})")
    print(f"same period, {len(sp)} objects, max |diff|/peak: vs GalSim default: perscli on n {sp['d_n'].max():.1e}, "
          f"on 2n {sp['d_2n'].max():.1e}, on GalSim's N {sp['d_N'].max():.1e}; vs tightened GalSim: on n "
          f"{sp['a_n'].max():.1e}, on N {sp_max:.1e} (required < {SAME_PERIOD_TOL:g}); "
          f"N {sorted(set(int(v) for v in sp['N']))}")
    print(f"checks: stamps re-drawn one by one sum to draw_sources' image within {recon_maxabs:.1e} e-; "
          f"workers=2 image identical: {same_workers}; render --workers 1/2 HDUs identical: {file_same}; "
          f"render IDEAL - sky vs draw_sources: max relative {ideal_rel:.1e} (float32); NOBJ {nobj_file}")
    print(f"before issue 8 ({BEFORE['date']}, {BEFORE['commit']}): GalSim loop {BEFORE['galsim']:.2f} s, draw_sources "
          f"{BEFORE['s1']:.2f} s, perscli render {BEFORE['p1']:.2f} s ({BEFORE['rss'] / 1e6:.0f} MB); now "
          f"{g_best:.2f} s, {s1_best:.2f} s, {p1_best:.2f} s ({p1_rss / 1e6:.0f} MB)")
    if sizes is not None:
        print(f"output sizes: plain {sizes['plain'] / 1e6:.1f} MB, --compress gzip {sizes['--compress gzip'] / 1e6:.1f} MB "
              f"({sizes['--compress gzip'] / sizes['plain']:.2f}; required <= {SIZE_REQUIRED:g}), .fits.gz "
              f"{sizes['-o x.fits.gz'] / 1e6:.1f} MB; {'PASS' if sizes_ok else 'FAIL'}")
    print("PASS" if ok else "FAIL")
    if profile is not None:
        (rp, rtot), (gp, gtot) = profile
        print(f"\nwhere perscli render spends its time (cProfile, {rtot:.2f} s in Python):")
        for label, t in rp:
            print(f"  {label:58s} {t:7.2f} s {100 * t / rtot:5.1f} %")
        print(f"where the GalSim loop spends its time (cProfile, every 10th object, {gtot:.2f} s):")
        for label, t in gp:
            print(f"  {label:58s} {t:7.2f} s {100 * t / gtot:5.1f} %")

    if args.no_results or (args.results is None and args.bounds is not None):
        return 0 if ok else 1

    # ---- RESULTS.md -------------------------------------------------------------------------
    dest = args.results or HERE / "RESULTS.md"
    v, m = versions(), machine()
    cmd_text = " ".join(["perscli"] + cmd_w1[len(perscli_command()):]).replace(str(workdir) + "/", "")
    cat_text = " ".join(["perscli"] + cat["cmd"][len(perscli_command()):]).replace(str(workdir) + "/", "")
    size_text = ", ".join(f"{c} x {n}" for n, c in size_counts.items())

    def size_row(n):
        a, b = rows[rows["n"] == n], arows[arows["n"] == n]
        return (f"| {n} | {len(a)} | {a['full'].max():.1e} | {a['inner'].max():.1e} | {b['full'].max():.1e} | "
                f"{b['inner'].max():.1e} | {np.median(a['pflux']):.4f} | {np.median(a['gflux']):.4f} |")

    per_size = "\n".join(size_row(n) for n in size_counts)

    def sp_row(n):
        a = sp[sp["n"] == n]
        return (f"| {n} | {', '.join(str(v) for v in sorted(set(int(v) for v in a['N'])))} | {len(a)} | "
                f"{a['d_n'].max():.1e} | {a['d_2n'].max():.1e} | {a['d_N'].max():.1e} | {a['a_n'].max():.1e} | "
                f"{a['a_N'].max():.1e} |")

    sp_sizes = "\n".join(sp_row(n) for n in sorted(set(int(v) for v in sp["n"])))
    profile_md = ""
    if profile is not None:
        (rp, rtot), (gp, gtot) = profile
        profile_md = ("\n### Where the time goes (render)\n\n"
                      f"`perscli render` (`--workers 1`) under cProfile ({rtot:.2f} s inside Python, profiler "
                      "overhead included; nested phases are marked with `-` and `--`; an import done inside a function "
                      "counts in both rows):\n\n"
                      "| phase | seconds | share |\n|---|---:|---:|\n"
                      + "".join(f"| {label} | {t:.2f} | {100 * t / rtot:.0f} % |\n" for label, t in rp)
                      + f"\nThe GalSim loop under cProfile on every 10th object ({gtot:.2f} s):\n\n"
                      "| phase | seconds | share |\n|---|---:|---:|\n"
                      + "".join(f"| {label} | {t:.2f} | {100 * t / gtot:.0f} % |\n" for label, t in gp))
    fmt = lambda t: ", ".join(f"{x:.2f}" for x in t)  # noqa: E731
    text = f"""## render: one full SCA exposure vs a straightforward GalSim loop

Reproduce with `make bench-render` (runs `.venv/bin/python benchmarks/bench_render.py`).

- date: {dt.datetime.now().strftime('%Y-%m-%d %H:%M')}
- machine: {m['arch']}, {m['cpu']}, {m['nproc']} cores (nproc), {m['memory']} RAM, Linux {m['kernel']}
- versions: python {v['python']}, numpy {v['numpy']}, galsim {v['galsim']}, astropy {v['astropy']}, perscli {v['perscli']} (git {git_commit()})
- exposure: SCA {SCA}, {FILTER}, pointing ra={RA} dec={DEC} pa={PA}, mjd={MJD}, {exposure.exptime} s,
  {xmax - xmin + 1}x{ymax - ymin + 1} px ({sca_area:.1f} arcmin^2); PSF `galsim.roman.getPSF` at the SCA centre
  and the filter's effective wavelength, in SCA pixel units.
- catalogue: `{cat_text}`
  (the paper's densities, {GALAXY_DENSITY:g} galaxies and {STAR_DENSITY:g} stars per arcmin^2, on a {cat['size']}' field
  centred on the SCA): **{n_on_gal} galaxies and {n_on_star} stars** with centres on the SCA; {len(rows)} objects drawn
  ({n_gal} galaxies, {n_star} stars: all whose stamps reach the SCA); stamps {size_text} px.
- perscli command timed: `{cmd_text}` (and with `--workers 2`):
  the whole process from spawn to exit, with the full Roman detector chain and SCI + IDEAL + FLUENCE
  written ({written / 1e6:.0f} MB with the MODEL table; saturation at the full well is on in the Roman model
  now, it was not before issue 8).
- GalSim loop, in this process: for each object `galsim.Convolve(obj, psf).drawImage(image=stamp,
  center=(x, y), method='auto')` (FFT convolution with the PSF and the pixel) on the same n x n stamp
  as perscli, `obj` a `DeltaFunction` or `wcs.local(pos).toImage(Exponential(half_light_radius=hlr).shear(g1=e1, g2=e2))`,
  `psf` the same SCA-oriented Roman PSF in pixel units, each stamp added to a 4088x4088 `ImageD`.  Both
  in-process timings include building the optics (WCS, bandpass, PSF) and the plan; `import galsim` is
  not counted.  GalSim's default GSParams; once more with `maxk_threshold={ACCURATE_MAXK:g}` for the galaxies
  (`Convolve(..., propagate_gsparams=False)`), the accuracy at which it reproduces perscli's values.
- repeats: best of {len(g_times)} for the GalSim loop (run once if the first run takes > {args.galsim_once:g} s) and
  of {args.repeats} for perscli, interleaved, after one untimed `perscli render`.

| what | best wall time | GalSim / this | peak RSS |
|---|---:|---:|---:|
| GalSim loop, {len(rows)} objects, default GSParams, in-process | {g_best:.2f} s | 1.0x | |
| GalSim loop, galaxies with `maxk_threshold={ACCURATE_MAXK:g}` (one run) | {ga_time:.2f} s | {g_best / ga_time:.1f}x | |
| `perscli.render.exposure.draw_sources(cols, exposure)` (sources only), in-process | {s1_best:.2f} s | **{ratios['s1']:.1f}x** | |
| same, `workers=2` | {s2_best:.2f} s | {ratios['s2']:.1f}x | |
| `perscli render ...` whole process: detector chain, 3 HDUs written | {p1_best:.2f} s | **{ratios['p1']:.1f}x** | {p1_rss / 1e6:.0f} MB |
| same, `--workers 2` | {p2_best:.2f} s | {ratios['p2']:.1f}x | {p2_rss / 1e6:.0f} MB |

- **speed ratio** GalSim loop / perscli: **{ratios['s1']:.1f}x** sources only, **{ratios['p1']:.1f}x** for the whole
  `perscli render` process (which also runs the detector chain and writes {written / 1e6:.0f} MB); required >= {RATIO_REQUIRED:g}x.
  Against the tightened GalSim loop: {ratios['a1']:.1f}x and {ratios['ap']:.1f}x.
- **before / after** (issue 8): recorded {BEFORE['date']} (commit {BEFORE['commit']}, same machine): GalSim loop
  {BEFORE['galsim']:.2f} s, `draw_sources` {BEFORE['s1']:.2f} s ({BEFORE['galsim'] / BEFORE['s1']:.1f}x), the whole `perscli render`
  {BEFORE['p1']:.2f} s ({BEFORE['galsim'] / BEFORE['p1']:.1f}x) at {BEFORE['rss'] / 1e6:.0f} MB peak RSS, {BEFORE['written'] / 1e6:.0f} MB written; now
  {s1_best:.2f} s ({s1_best / BEFORE['s1']:.2f} of before) and {p1_best:.2f} s ({p1_best / BEFORE['p1']:.2f} of before) at
  {p1_rss / 1e6:.0f} MB, {written / 1e6:.0f} MB written; the GalSim loop took {g_best / BEFORE['galsim']:.2f} of its time before
  (the VM's speed varies between runs).
- **agreement with the default GalSim loop**, per object (max |perscli - GalSim| over the stamp / the object's
  peak pixel, {len(rows)} objects): whole stamp median {np.median(rows['full']):.1e}, 99th percentile
  {pct(rows['full'], 99):.1e}, max {rows['full'].max():.1e}; central half of the stamp median
  {np.median(rows['inner']):.1e}, 99th percentile {pct(rows['inner'], 99):.1e}, max {rows['inner'].max():.1e}.
  Image: max |diff| {ag['img_maxabs']:.3g} e- at pixel {ag['img_maxabs_at']} (image maximum {ag['img_max']:.3g} e-);
  max over pixels of |diff| / the peak of the brightest object whose stamp covers the pixel
  {ag['img_rel']:.1e}, {ag['img_rel_inner']:.1e} over the {ag['inner_pixels']} pixels inside the central half of every
  stamp covering them.  Total flux: perscli {ag['p_sum']:.6e} e-, GalSim {ag['g_sum']:.6e} e-
  (GalSim / perscli - 1 = {ag['g_sum'] / ag['p_sum'] - 1:+.2e}).
- **agreement with the GalSim loop at `maxk_threshold={ACCURATE_MAXK:g}`**: whole stamp median
  {np.median(arows['full']):.1e}, 99th percentile {pct(arows['full'], 99):.1e}, max {arows['full'].max():.1e};
  **central half** median {np.median(arows['inner']):.1e}, 99th percentile {pct(arows['inner'], 99):.1e},
  max **{inner_acc:.1e}** (required < {INNER_TOL:g}); image {aa['img_rel']:.1e} / {aa['img_rel_inner']:.1e}
  (all pixels / central halves), total flux GalSim / perscli - 1 = {aa['g_sum'] / aa['p_sum'] - 1:+.2e}.
- **where the differences come from**, two known causes:
  1. *period*: perscli's stamp is periodic with period n (the PSF wings beyond the stamp fold back in,
     so each stamp holds all of its object's flux, median {np.median(rows['pflux']):.5f}); GalSim draws
     on an N x N FFT grid (N >= 256 here, from the PSF's stepk) and crops the stamp (the wings beyond it
     are lost, median flux in the stamp {np.median(rows['gflux']):.4f}; those beyond N/2 fold back in).
     This is the difference at the stamp edges and the total-flux difference.
  2. *GalSim's galaxy maxk*: with the default `maxk_threshold=1e-3` GalSim cuts each galaxy's Fourier
     transform where it falls below 1e-3, which for the larger galaxies (hlr >~ 0.5") is below the
     PSF's band limit ({optics.psf_pixels.maxk:.1f} rad/pixel): the power it drops reaches
     {rows['inner'].max():.1e} of the peak in the central half of a stamp.  perscli uses the analytic
     transform over the whole band the PSF passes.  With `maxk_threshold={ACCURATE_MAXK:g}` this
     difference goes away (central half: {inner_acc:.1e}, the period alone).
  Drawing a subset of {len(sp)} objects with perscli's drawer on GalSim's own N and cropping the centre,
  against the tightened GalSim: max difference **{sp_max:.1e}** of the peak (required < {SAME_PERIOD_TOL:g}):
  the algorithms give the same pixel values.

| stamp n | objects | vs GalSim default: whole stamp | central half | vs `maxk_threshold={ACCURATE_MAXK:g}`: whole | central half | flux in stamp, perscli | GalSim |
|---:|---:|---:|---:|---:|---:|---:|---:|
{per_size}

Same-period experiment (every {stride}th object and every star, up to n = 512): max |diff| / peak of perscli's
stamp drawn on n, 2n or GalSim's FFT size N and cropped to the central n x n, against GalSim's stamp:

| stamp n | GalSim's N | objects | vs default: on n | on 2n | on N | vs `maxk_threshold={ACCURATE_MAXK:g}`: on n | on N |
|---:|---|---:|---:|---:|---:|---:|---:|
{sp_sizes}

- checks: the stamps re-drawn one by one sum to `draw_sources`' image within {recon_maxabs:.1e} e-;
  `workers=2` gives the same image bytes: {same_workers}; `perscli render` with `--workers 1` and 2 writes the same
  SCI/IDEAL/FLUENCE: {file_same}; the rendered IDEAL minus its sky ({sky_e:.1f} e-) matches `draw_sources` to
  {ideal_rel:.1e} relative (float32); NOBJ = {nobj_file}.
- result: **{'PASS' if ok else 'FAIL'}**

Per-repeat times (s): GalSim loop {fmt(g_times)}; draw_sources {fmt(s1)}; workers=2 {fmt(s2)};
perscli render {fmt([t for t, _ in p1])}; --workers 2 {fmt([t for t, _ in p2])}.  Building the optics alone:
{optics_s:.2f} s (first time in this process).
{profile_md}
{sizes_md}"""
    write_section(dest, SECTION, text)
    print(f"wrote the {SECTION} section of {dest}")
    return 0 if ok else 1


if __name__ == "__main__":
    sys.exit(main())
