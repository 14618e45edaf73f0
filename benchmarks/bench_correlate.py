#!/usr/bin/env python
"""Benchmark: the whole ``perscli correlate`` process against TreeCorr's own ``process()``.

Run with ``make bench-correlate`` (that is, ``.venv/bin/python benchmarks/bench_correlate.py``).

The requirement: 0.9 million objects over 6.25 deg^2 with 20 jackknife
patches: the whole ``perscli correlate`` process (interpreter start, imports,
reading and checking the catalogue, k-means patches, xi+/-, the jackknife
covariance, the De statistics, the output with provenance and checksums)
within 1.3x of TreeCorr's ``Catalog`` + ``GGCorrelation.process`` on the same
arrays already in memory, measured side by side in one run with the same
number of threads, and its peak memory under 1.5 GB.

What it does:

1. Catalogue.  A SHAPES-like FITS table (id, frame, x, y, ra, dec, g1, g2,
   g1_err, g2_err, flags, de1, de2) of 0.9M objects uniform over a 2.5 x 2.5
   degree field at (ra, dec) = (10, -44); De1 and De2 ~ N(0, 1e-5), with 1 % of
   the objects drawn 100x larger (~1e-3), seeded.  Reused when present with the
   same recipe (header keyword BENCHTAG).
2. TreeCorr, in this process, on the columns read beforehand (not timed, nor
   the import): ``treecorr.Catalog(ra, dec, g1=de1, g2=de2, npatch=20,
   rng=default_rng(seed))`` (k-means patches) and ``GGCorrelation(min_sep=1,
   max_sep=100, nbins=20, sep_units='arcmin', var_method='jackknife',
   cross_patch_weight='match').process(cat)`` plus ``gg.cov``: the settings
   ``perscli correlate`` uses by default (TreeCorr's default bin_slop).
3. perscli: ``perscli correlate cat.fits --de1 de1 --de2 de2 -o xi.fits
   --overwrite --workers N`` as a subprocess, wall clock from spawn to exit,
   peak RSS of that process alone (``os.wait4`` through a small wrapper, see
   bench_apply_persistence.py).  If ``correlate`` is not registered in the
   ``perscli`` group yet, the click command is run directly by ``python -c``
   (same code path, same imports).
4. Both use ``--workers`` threads (default: all cores).  One untimed warm-up
   of each; ``--repeats`` (5) interleaved rounds; best of each.  Also timed
   for context: TreeCorr as a whole process (a script reading the columns
   with fitsio), and a no-data baseline (python importing what perscli
   correlate imports).
5. Agreement: perscli's xi+/- and covariance against the in-process TreeCorr
   result (same seed, so the same patches).
6. A cProfile run of the perscli command splits its time into phases
   (``--no-profile`` to skip).
7. Prints a table and PASS/FAIL, exits 1 on FAIL, writes its section
   (``correlate``) of ``benchmarks/RESULTS.md``.
"""

from __future__ import annotations

import argparse
import datetime as dt
import os
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

from perscli.instrument import ROMAN_SCA_SIZE

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))
from bench_apply_persistence import machine, perscli_command, run_child, write_section  # noqa: E402

SECTION = "correlate"
N_DEFAULT = 900_000
SIDE_DEG = 2.5             # 6.25 deg^2
RA0, DEC0 = 10.0, -44.0
DE_SIGMA = 1e-5
BIG_FRACTION, BIG_FACTOR = 0.01, 100.0
NPATCH = 20
MIN_SEP, MAX_SEP, NBINS, SEP_UNITS = 1.0, 100.0, 20, "arcmin"
CPW = "match"
SEED = 20241122
RATIO_REQUIRED = 1.3
RSS_LIMIT = 1.5e9


# --------------------------------------------------------------------------------------------
# the catalogue
# --------------------------------------------------------------------------------------------

def recipe_tag(n: int, seed: int) -> str:
    return f"corr-v1 n={n} side={SIDE_DEG} sigma={DE_SIGMA} big={BIG_FRACTION}x{BIG_FACTOR} seed={seed}"


def ensure_catalog(path: Path, n: int, seed: int, regenerate: bool = False) -> float:
    """Write the SHAPES-like catalogue unless present with the same recipe; returns seconds spent."""
    from astropy.io import fits

    tag = recipe_tag(n, seed)
    if path.exists() and not regenerate:
        try:
            if fits.getheader(path, 1).get("BENCHTAG") == tag:
                return 0.0
        except (OSError, IndexError, KeyError):
            pass
    t0 = time.perf_counter()
    rng = np.random.default_rng(seed)
    dec = DEC0 + rng.uniform(-SIDE_DEG / 2, SIDE_DEG / 2, n)
    ra = RA0 + rng.uniform(-SIDE_DEG / 2, SIDE_DEG / 2, n) / np.cos(np.radians(DEC0))
    de1, de2 = rng.normal(0, DE_SIGMA, n), rng.normal(0, DE_SIGMA, n)
    big = rng.random(n) < BIG_FRACTION
    de1[big] *= BIG_FACTOR
    de2[big] *= BIG_FACTOR
    g1b, g2b = rng.normal(0, 0.27, n), rng.normal(0, 0.27, n)
    cols = [fits.Column("id", "K", array=np.arange(1, n + 1)),
            fits.Column("frame", "I", array=np.zeros(n, dtype=np.int16)),
            fits.Column("x", "D", unit="pix", array=rng.uniform(1, ROMAN_SCA_SIZE, n)),
            fits.Column("y", "D", unit="pix", array=rng.uniform(1, ROMAN_SCA_SIZE, n)),
            fits.Column("ra", "D", unit="deg", array=ra), fits.Column("dec", "D", unit="deg", array=dec),
            fits.Column("g1", "D", array=g1b + de1), fits.Column("g2", "D", array=g2b + de2),
            fits.Column("g1_err", "D", array=np.full(n, 0.01)), fits.Column("g2_err", "D", array=np.full(n, 0.01)),
            fits.Column("flags", "J", array=np.zeros(n, dtype=np.int32)),
            fits.Column("de1", "D", array=de1), fits.Column("de2", "D", array=de2)]
    hdu = fits.BinTableHDU.from_columns(cols, name="SHAPES")
    hdu.header["BENCHTAG"] = tag
    tmp = path.with_name(path.name + ".part")
    fits.HDUList([fits.PrimaryHDU(), hdu]).writeto(tmp, overwrite=True, checksum=True)
    os.replace(tmp, path)
    return time.perf_counter() - t0


# --------------------------------------------------------------------------------------------
# the two sides
# --------------------------------------------------------------------------------------------

def correlate_command() -> tuple[list, str]:
    """``perscli correlate`` if registered, else the click command run directly."""
    exe = perscli_command()
    probe = subprocess.run([*exe, "correlate", "--help"], stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    if probe.returncode == 0:
        return [*exe, "correlate"], "perscli correlate"
    code = ("import sys; from perscli.cli.helpers import configure_logging; configure_logging(0); "
            "from perscli.cli.correlate import correlate; correlate(prog_name='perscli correlate')")
    return [sys.executable, "-c", code], "python -c '...correlate(...)' (command not registered in perscli yet)"


def treecorr_once(cols: dict, workers: int, seed: int):
    """TreeCorr's own work on arrays in memory: Catalog (k-means patches) + process + covariance."""
    import treecorr

    treecorr.set_omp_threads(workers)
    t0 = time.perf_counter()
    cat = treecorr.Catalog(ra=cols["ra"], dec=cols["dec"], ra_units="deg", dec_units="deg", g1=cols["de1"],
                           g2=cols["de2"], npatch=NPATCH, rng=np.random.default_rng(seed))
    t1 = time.perf_counter()
    gg = treecorr.GGCorrelation(min_sep=MIN_SEP, max_sep=MAX_SEP, nbins=NBINS, sep_units=SEP_UNITS,
                                var_method="jackknife", cross_patch_weight=CPW)
    gg.process(cat, num_threads=workers)
    cov = gg.cov
    t2 = time.perf_counter()
    return t2 - t0, t1 - t0, gg, cov


_TREECORR_SCRIPT = r"""
import sys, numpy as np, fitsio, treecorr
path, workers, seed = sys.argv[1], int(sys.argv[2]), int(sys.argv[3])
d = fitsio.read(path, columns=["ra", "dec", "de1", "de2"], ext=1)
treecorr.set_omp_threads(workers)
cat = treecorr.Catalog(ra=d["ra"], dec=d["dec"], ra_units="deg", dec_units="deg", g1=d["de1"], g2=d["de2"],
                       npatch=%d, rng=np.random.default_rng(seed))
gg = treecorr.GGCorrelation(min_sep=%r, max_sep=%r, nbins=%d, sep_units=%r, var_method="jackknife",
                            cross_patch_weight=%r)
gg.process(cat, num_threads=workers)
gg.cov
""" % (NPATCH, MIN_SEP, MAX_SEP, NBINS, SEP_UNITS, CPW)

# the modules perscli correlate imports are imported (and timed) before profiling, so that each phase's
# time does not include the first import of what it uses
_PROFILE = r"""
import cProfile, sys, time
t0 = time.perf_counter()
import numpy, click, astropy.io.fits, astropy.table, treecorr
import perscli.stats.correlate, perscli.io.tables, perscli.io.output, perscli.io.fitsfile
from perscli.cli.correlate import correlate
open(sys.argv[1] + ".imports", "w").write(repr(time.perf_counter() - t0))
out = sys.argv[1]
sys.argv = ["perscli correlate", *sys.argv[2:]]
prof = cProfile.Profile()
try:
    prof.runcall(correlate, standalone_mode=False)
finally:
    prof.dump_stats(out)
"""

#: (label, [(function name, file name)] whose cumulative times add up to the phase)
PHASES = [
    ("imports left inside the command (first use)", [("_find_and_load", "<frozen importlib._bootstrap>")]),
    ("opening the catalogue (scan, DATASUM, memory map)", [("open_table", "tables.py")]),
    ("De, positions, flags (rest of load_shape_changes)", [("load_shape_changes", "stats/shape_changes.py"),
                                                           ("-open_table", "tables.py")]),
    ("k-means patches (TreeCorr run_kmeans)", [("run_kmeans", "field.py")]),
    ("TreeCorr process (patch trees, all pairs of patches)", [("process", "corr2base.py")]),
    ("jackknife covariance (gg.cov)", [("estimate_cov", "corr2base.py")]),
    ("De statistics, histogram of abs(De), angle bootstrap", [("de_statistics", "stats/de_stats.py"),
                                                        ("de_histogram", "stats/de_stats.py"),
                                                        ("theta_distribution", "stats/de_stats.py")]),
    ("building the output HDUs", [("build_hdus", "stats/correlate_hdus.py")]),
    ("writing (checksums, atomic rename)", [("write_fits", "output.py")]),
]


def profile_perscli(cmd_args: list, workdir: Path):
    """Phases of one perscli correlate run under cProfile: ([(label, s)], total s, listing)."""
    import io
    import pstats

    out = workdir / "correlate.prof"
    subprocess.run([sys.executable, "-c", _PROFILE, str(out), *cmd_args], check=True, stdout=subprocess.DEVNULL)
    stats = pstats.Stats(str(out))
    cum = {}
    for (fname, _, func), (_, _, _, ct, _) in stats.stats.items():
        key = (func, fname if fname.startswith("<") or fname == "~" else os.path.basename(fname))
        cum[key] = max(cum.get(key, 0.0), ct)
    total = max(cum.values())
    imports = float((workdir / "correlate.prof.imports").read_text())
    phases = [("imports (timed before profiling)", imports)]
    for label, parts in PHASES:
        t = 0.0
        for func, fname in parts:
            sign = -1.0 if func.startswith("-") else 1.0
            t += sign * cum.get((func.lstrip("-"), fname), 0.0)
        phases.append((label, t))
    buf = io.StringIO()
    pstats.Stats(str(out), stream=buf).sort_stats("cumulative").print_stats(40)
    return phases, total + imports, buf.getvalue()


def versions() -> dict:
    import platform

    import astropy
    import fitsio
    import treecorr

    out = dict(python=platform.python_version(), numpy=np.__version__, treecorr=treecorr.__version__,
               astropy=astropy.__version__, fitsio=fitsio.__version__)
    try:
        from importlib.metadata import version
        out["perscli"] = version("perscli")
    except Exception:
        out["perscli"] = "?"
    return out


# --------------------------------------------------------------------------------------------
# main
# --------------------------------------------------------------------------------------------

def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--n", type=int, default=N_DEFAULT, help=f"objects (default {N_DEFAULT})")
    ap.add_argument("--repeats", type=int, default=5,
                    help="timed rounds; the best of each side is reported (default 5)")
    ap.add_argument("--workers", type=int, default=os.cpu_count(),
                    help="threads for both TreeCorr and perscli (default: all cores)")
    ap.add_argument("--seed", type=int, default=SEED, help=f"seed of the catalogue and patches (default {SEED})")
    ap.add_argument("--workdir", type=Path, default=HERE / "work" / "correlate",
                    help="catalogue, outputs, profile (default: benchmarks/work/correlate, git-ignored)")
    ap.add_argument("--regenerate", action="store_true", help="remake the catalogue even if present")
    ap.add_argument("--results", type=Path, default=None,
                    help="write the results here (default: benchmarks/RESULTS.md, with the default --n only)")
    ap.add_argument("--no-results", action="store_true", help="do not write a results file")
    ap.add_argument("--no-profile", action="store_true", help="skip the cProfile run")
    args = ap.parse_args(argv)
    if args.repeats < 1 or args.n < NPATCH * 10 or args.workers < 1:
        ap.error(f"--repeats and --workers must be >= 1 and --n >= {NPATCH * 10}")
    workdir = args.workdir.resolve()
    workdir.mkdir(parents=True, exist_ok=True)
    cat_path = workdir / "cat.fits"
    out_path = workdir / "xi.fits"

    print(f"catalogue: {args.n} objects over {SIDE_DEG}x{SIDE_DEG} deg ({cat_path})", flush=True)
    made_s = ensure_catalog(cat_path, args.n, args.seed, args.regenerate)
    if made_s:
        print(f"  written in {made_s:.1f} s")
    size_mb = cat_path.stat().st_size / 1e6

    import fitsio
    import treecorr  # noqa: F401  (imported before the timing, as a library user would have it)

    t0 = time.perf_counter()
    cols = fitsio.read(str(cat_path), columns=["ra", "dec", "de1", "de2"], ext=1)
    cols = {k: np.ascontiguousarray(cols[k], dtype=np.float64) for k in ("ra", "dec", "de1", "de2")}
    load_s = time.perf_counter() - t0

    cmd_prefix, how = correlate_command()
    cmd_args = [str(cat_path), "--de1", "de1", "--de2", "de2", "--seed", str(args.seed), "--workers",
                str(args.workers), "-o", str(out_path), "--overwrite"]
    cmd = [*cmd_prefix, *cmd_args]
    cmd_tc = [sys.executable, "-c", _TREECORR_SCRIPT, str(cat_path), str(args.workers), str(args.seed)]
    cmd_base = [sys.executable, "-c", "import numpy, click, astropy.io.fits, treecorr, perscli.cli.correlate, "
                "perscli.stats.correlate, perscli.io.tables, perscli.io.output"]

    print(f"warm-up (untimed): TreeCorr once, perscli once ({how})", flush=True)
    treecorr_once(cols, args.workers, args.seed)
    run_child(cmd)
    tc, pc, tcp = [], [], []
    for r in range(args.repeats):
        t, t_cat, gg, cov = treecorr_once(cols, args.workers, args.seed)
        tc.append((t, t_cat))
        pc.append(run_child(cmd)[:2])
        tcp.append(run_child(cmd_tc)[:2])
        print(f"  round {r + 1}/{args.repeats}: TreeCorr in-process {t:.3f} s (k-means {t_cat:.3f} s), "
              f"perscli {pc[-1][0]:.3f} s ({pc[-1][1] / 1e9:.2f} GB), TreeCorr script {tcp[-1][0]:.3f} s",
              flush=True)
    base = [run_child(cmd_base)[:2] for _ in range(3)]
    base_wall, base_rss = min(t for t, _ in base), min(m for _, m in base)

    tc_best = min(t for t, _ in tc)
    tc_cat = min(tc)[1]
    pc_best = min(t for t, _ in pc)
    pc_rss = max(m for _, m in pc)
    tcp_best = min(t for t, _ in tcp)
    tcp_rss = max(m for _, m in tcp)
    ratio = pc_best / tc_best

    # agreement with the in-process TreeCorr result (same seed: same patches)
    from astropy.io import fits

    with fits.open(out_path) as hdul:
        xi = hdul["XI"].data
        pcov = np.asarray(hdul["COV"].data)
        stats = hdul["STATS"].data[0]
        d_xip = float(np.max(np.abs(xi["xip"] - gg.xip) / np.sqrt(gg.varxip)))
        d_xim = float(np.max(np.abs(xi["xim"] - gg.xim) / np.sqrt(gg.varxim)))
        rel_xip = float(np.max(np.abs(xi["xip"] - gg.xip)) / np.max(np.abs(gg.xip)))
        rel_cov = float(np.max(np.abs(pcov - cov)) / np.max(np.abs(cov)))
        npairs_same = bool(np.array_equal(xi["npairs"], gg.npairs))
        max_z = float(np.max(np.abs(xi["xip"] / xi["sigma_xip"])))
        frac = dict(zip(np.asarray(stats["threshold"]).tolist(), np.asarray(stats["frac_ge"]).tolist()))
    agree = npairs_same and d_xip < 1e-6 and d_xim < 1e-6

    profile = None
    if not args.no_profile:
        print("profile: perscli correlate once more, under cProfile", flush=True)
        profile = profile_perscli(cmd_args, workdir)

    gb = 1e9
    ok = ratio <= RATIO_REQUIRED and pc_rss < RSS_LIMIT and agree
    rows = [
        (f"TreeCorr in-process: Catalog(npatch={NPATCH}) + GGCorrelation.process + cov", tc_best, None),
        (f"perscli correlate (whole process, {args.workers} threads)", pc_best, pc_rss),
        ("TreeCorr as a whole process (fitsio read + the same)", tcp_best, tcp_rss),
        ("python + perscli correlate's imports only (no data)", base_wall, base_rss),
    ]
    print()
    print(f"{'':78s} {'best s':>8s} {'peak RSS':>10s}")
    for label, t, rss in rows:
        print(f"{label:78s} {t:8.3f} {(f'{rss / gb:7.2f} GB') if rss else ''}")
    print(f"ratio perscli / TreeCorr in-process: {ratio:.2f}x (required <= {RATIO_REQUIRED}x); "
          f"peak RSS {pc_rss / gb:.2f} GB (required < {RSS_LIMIT / gb:.1f} GB)")
    print(f"agreement with in-process TreeCorr (same seed, same patches): npairs identical: {npairs_same}; "
          f"max |dxi+|/sigma {d_xip:.1e}, max |dxi-|/sigma {d_xim:.1e}; max relative covariance difference "
          f"{rel_cov:.1e}")
    print("PASS" if ok else "FAIL")
    profile_md = ""
    if profile is not None:
        phases, total, listing = profile
        rest = total - sum(t for _, t in phases)
        print(f"\nwhere perscli's time goes (one run under cProfile, {total:.3f} s in Python, imports included):")
        for label, t in phases + [("other: TreeCorr's Catalog and GGCorrelation set-up, click, logging", rest)]:
            print(f"  {label:52s} {t:7.3f} s  {100 * t / total:5.1f} %")
        (workdir / "correlate_profile.txt").write_text(listing)
        profile_md = ("\n### Where the perscli process spends its time\n\n"
                      f"One more run under cProfile ({total:.3f} s inside Python, profiler overhead included; "
                      "the imports are timed before profiling, interpreter start-up is not counted):\n\n| phase | seconds | share |\n|---|---:|---:|\n")
        for label, t in phases + [("other: TreeCorr's Catalog and GGCorrelation set-up, click, logging", rest)]:
            profile_md += f"| {label} | {t:.3f} | {100 * t / total:.0f} % |\n"

    if args.no_results or (args.results is None and args.n != N_DEFAULT):
        return 0 if ok else 1
    dest = args.results or HERE / "RESULTS.md"
    v, m = versions(), machine()
    cmd_shown = "perscli correlate cat.fits --de1 de1 --de2 de2 --seed S --workers N -o xi.fits --overwrite"
    text = f"""## correlate: the whole `perscli correlate` process vs TreeCorr's process()

Reproduce with `make bench-correlate` (runs `.venv/bin/python benchmarks/bench_correlate.py`).

- date: {dt.datetime.now().strftime('%Y-%m-%d %H:%M')}
- machine: {m['arch']}, {m['cpu']}, {m['nproc']} cores (nproc), {m['memory']} RAM, Linux {m['kernel']}
- versions: python {v['python']}, numpy {v['numpy']}, treecorr {v['treecorr']}, astropy {v['astropy']}, fitsio {v['fitsio']}, perscli {v['perscli']}
- data: a SHAPES-like table of **{args.n} objects** uniform over {SIDE_DEG} x {SIDE_DEG} deg ({SIDE_DEG ** 2:.2f} deg^2)
  at (ra, dec) = ({RA0}, {DEC0}), 13 columns, {size_mb:.0f} MB; De1, De2 ~ N(0, {DE_SIGMA:g}) with {100 * BIG_FRACTION:g} %
  of the objects {BIG_FACTOR:g}x larger; seed {args.seed}.
- settings (both sides): {NBINS} log bins {MIN_SEP:g}-{MAX_SEP:g} {SEP_UNITS}, TreeCorr's default bin_slop, jackknife over
  {NPATCH} k-means patches (seeded), cross_patch_weight='{CPW}', **{args.workers} threads**.
- perscli command timed: `{cmd_shown}`, run as {how}; wall clock from spawn to exit, peak RSS of that process
  alone (`os.wait4`).
- TreeCorr timed in the benchmark's process: `Catalog(ra, dec, g1=de1, g2=de2, npatch={NPATCH}, rng=...)` +
  `GGCorrelation(...).process(cat)` + `gg.cov`, on arrays read beforehand (reading {load_s:.2f} s and `import treecorr`
  not counted).  The k-means part of it: {tc_cat:.2f} s.
- repeats: one untimed warm-up of each, then best of {args.repeats} interleaved rounds.

| what | best wall time | peak RSS |
|---|---:|---:|
| TreeCorr in-process: Catalog (k-means, {NPATCH} patches) + process + covariance | {tc_best:.3f} s | (in-process, not measured) |
| `perscli correlate` (whole process) | {pc_best:.3f} s | {pc_rss / gb:.2f} GB |
| TreeCorr as a whole process (python script: fitsio read + the same) | {tcp_best:.3f} s | {tcp_rss / gb:.2f} GB |
| baseline: python importing what perscli correlate imports, no data | {base_wall:.3f} s | {base_rss / gb:.2f} GB |

- **time ratio** perscli (whole process) / TreeCorr (in-process): **{ratio:.2f}x**; required <= {RATIO_REQUIRED}x.
- **peak memory** of the perscli process: **{pc_rss / gb:.2f} GB**; required < {RSS_LIMIT / gb:.1f} GB.
- **agreement** with the in-process TreeCorr result (same seed, hence the same patches): npairs identical:
  {npairs_same}; max |xi+ difference| / sigma_xi+ = {d_xip:.1e}, xi- {d_xim:.1e}; max relative xi+ difference
  {rel_xip:.1e}; max relative covariance difference {rel_cov:.1e}.
- the synthetic De (no spatial correlation): max |xi+ / sigma_xi+| over the bins {max_z:.2f};
  fractions with |De| >= {', '.join(f'{k:g}: {f:.4f}' for k, f in frac.items())}.
- result: **{'PASS' if ok else 'FAIL'}**

Per-round times (s): TreeCorr in-process {', '.join(f'{t:.3f}' for t, _ in tc)}; perscli
{', '.join(f'{t:.3f}' for t, _ in pc)}; TreeCorr script {', '.join(f'{t:.3f}' for t, _ in tcp)}.
{profile_md}"""
    write_section(dest, SECTION, text)
    print(f"wrote the {SECTION} section of {dest}")
    return 0 if ok else 1


if __name__ == "__main__":
    sys.exit(main())
