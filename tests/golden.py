"""Recorded products of perscli, compared with tolerances that fit each product.

A refactoring must not change what the commands write: renders, apply-persistence in
every mode and preset, measure (per frame and joint), and the ``ci`` study.  But the
last bits of floating-point results are not the same on every machine: numpy, OpenBLAS
and FFTW pick their code paths by CPU at run time (SIMD width, fused multiply-add,
summation order), and another library release may round differently.  So the products
are recorded once, here, and compared as astropy's FITSDiff compares files: integers,
strings, booleans, masks and integer-valued images exactly; floating data to a relative
tolerance (``rtol``) plus an absolute one (``atol``, or ``scale`` times the largest
recorded value of that column or image, for numbers that pass through zero) that the
arithmetic making them justifies (:data:`RULES`, each class with its reason); header
values that matter the same way; DATE, CHECKSUM, DATASUM and the DATASUMs of inputs
(which follow the inputs' bytes, themselves compared) ignored, and perscli's version
too.  A difference beyond its tolerance is a changed product: a bug, or a change meant
and then recorded again in the same commit, which says why::

    python tests/golden.py --record            # the commands (~20 s)
    python tests/golden.py --record --study    # and the ci study (~20 s more)

Records live in tests/golden/: FITS products gzipped (``NAME.fits.gz``), JSON and text
as they are, PNG figures as their size and a 16 x 16 grey thumbnail (``NAME.png.json``:
their pixels are matplotlib's rasteriser's; what they show is compared in the FITS
products), and the library versions that made them (``versions.json``, for the reader:
the comparison holds whatever the versions, and a release may move numbers by the
tolerance, never more).  ``python tests/golden.py DIR_A DIR_B`` compares two folders of
products with the same rules (benchmarks/bench_side_by_side.py does).
"""

from __future__ import annotations

import argparse
import fnmatch
import gzip
import json
import math
import os
import re
import shutil
import subprocess
import sys
from dataclasses import dataclass
from pathlib import Path

HERE = Path(__file__).resolve().parent
SAMPLES = HERE.parent / "sample_data"
RECORDS = HERE / "golden"
LIBRARIES = ("numpy", "scipy", "astropy", "fitsio", "galsim", "treecorr", "matplotlib")

POINT = ["--ra", "10", "--dec", "-44", "--pa", "30", "--filter", "J129", "--sca", "7",
         "--bounds", "1001", "1096", "2001", "2096"]
EXPS = [str(SAMPLES / f"exp{i}.fits") for i in (1, 2, 3, 4)]

#: name -> arguments of one perscli run, in order (later runs read earlier products)
COMMANDS = {
    "truth.fits": ["catalog", "--ra", "9.5386", "--dec", "-44.0435", "--size", "1", "--star-density", "10",
                   "--seed", "1"],
    "e0.fits": ["render", "truth.fits", *POINT, "--mjd", "61541.97", "--seed", "11"],
    "e1.fits": ["render", "truth.fits", *POINT, "--mjd", "61541.97196528", "--seed", "12",
                "--previous", "e0.fits"],
    "e1_dark.fits": ["render", "truth.fits", *POINT, "--mjd", "61541.97196528", "--seed", "12",
                     "--set", "dark.current=0.3", "--persistence-source", "all", "--previous", "e0.fits"],
    "add.fits": ["apply-persistence", EXPS[3], *EXPS[:3]],
    "predict.fits": ["apply-persistence", EXPS[3], *EXPS[:3], "--mode", "predict"],
    "subtract_set.fits": ["apply-persistence", EXPS[3], *EXPS[:3], "--mode", "subtract", "--law", "pessimistic",
                          "--set", "persistence.gamma=1.1"],
    "wfc3.fits": ["apply-persistence", EXPS[3], *EXPS[:3], "--law", "wfc3", "--mode", "predict"],
    "shapes.fits": ["measure", "e1.fits", "--catalog", "truth.fits"],
    "joint.fits": ["measure", "e0.fits", "e1.fits", "--catalog", "truth.fits", "--joint"],
}


# =================================================================================================
# Tolerances
# =================================================================================================

@dataclass(frozen=True)
class Tol:
    """``|made - recorded| <= atol + scale * max|recorded| + rtol * |recorded|``, elementwise; NaN where NaN."""

    rtol: float = 0.0
    atol: float = 0.0
    scale: float = 0.0
    why: str = ""

    def bound(self, recorded):
        """The allowed difference of each element of ``recorded`` (an array)."""
        import numpy as np

        rec = np.abs(np.asarray(recorded, dtype=np.float64))
        finite = rec[np.isfinite(rec)]
        biggest = float(finite.max()) if finite.size else 0.0
        return self.atol + self.scale * biggest + self.rtol * rec


#: compared bit for bit
EXACT = None

#: float64 results of elementwise arithmetic, numpy's and libm's exp/log/pow/trigonometry (catalogue
#: positions, magnitudes and shapes; WCS and pointing keywords; the budget's Bessel sums; sky rates)
F64 = Tol(rtol=1e-12, scale=1e-13, why=(
    "numpy picks SIMD implementations of exp, log, sin, arctan2... by CPU, which may differ by up to 4 ulp "
    "(4 x 2.2e-16); a product is a chain of at most ~100 such steps, so below 1e-13 relative; 1e-12 leaves 10x. "
    "scale: values that pass near zero by cancellation (e1, e2, offsets) err relative to the column's largest"))

#: float32 images computed in float64 (rendered IDEAL, FLUENCE, STARFLU, PERSIST; apply-persistence's
#: outputs): the float64 result may move by a few ulp, and then round to the neighbouring float32
F32 = Tol(rtol=2 ** -22, scale=1e-12, why=(
    "the float64 value (F64) rounds to the same float32 or to its neighbour: one float32 ulp is 2^-23 = 1.2e-7 "
    "relative, two allowed (a value rounded twice); scale: GalSim's FFT convolutions err by ~1e-15 of the image's "
    "peak (eps log2 N), which is more than an ulp for the faint wings"))

#: sums over many terms in an order that varies with threads and SIMD width (TreeCorr's pair sums and
#: mean separations; the summary's means)
SUMS = Tol(rtol=1e-10, scale=1e-10, why=(
    "a sum of n terms in another order moves by at most n eps relative to the sum of the absolute values: "
    "n <= 1e5 pairs or pixels here, so 1e-11; 1e-10 leaves 10x (observed on other code paths: 1e-13)"))

#: shape fits (measure/fit.py): stopped when a Newton step is below 1e-10 of the parameter's scale
FIT = Tol(rtol=1e-7, atol=1e-7, why=(
    "the fit stops when its step is below xtol = 1e-10 of the parameter's scale (g: 1); another CPU's rounding "
    "may stop it one step earlier or later, and along the flattest direction of a faint galaxy's chi2 "
    "(condition number up to ~1e3) that moves the result by up to 1e-7 of its scale; the errors come from the "
    "Hessian at that point (observed on other code paths: 4e-9 in g, 1.5e-12 relative in the errors)"))

#: De = g(with persistence) - g(reference): two fits of the same galaxy
DE = Tol(atol=2e-7, why="the difference of two fits, each within FIT's 1e-7 of its scale (g: 1)")

#: statistics of the De of a few dozen galaxies: means and their errors, xi+- (weighted means of products
#: De_i De_j), their jackknife errors and covariance, |De|-weighted angle histograms, xi over the budget
DE_STATS = Tol(rtol=5e-2, scale=5e-2, why=(
    "every De may move by 2e-7 (DE), which moves a mean of De by 2e-7 and xi+- by up to 2 x 2e-7 x max|De|: "
    "with the ci study's max|De| = 3e-3 and xi ~ 5e-8 that is 2.6% of the largest xi; 5% covers it and the "
    "smooth functions of them (errors, covariance, weighted histograms, ratios to the budget); observed on "
    "other code paths: 4e-6. A wrong sign, weight, pair or bin moves them by order one"))

#: (product, HDU, column) glob patterns -> class; the first match wins.  Column 'header' is the HDU's
#: header values (floats in it; text with numbers: each number within it, plus half its last digit);
#: images are column '*'.  Integer, string and boolean data are always EXACT.
RULES = [
    # header values: arithmetic (WCS, times, sky rates), but in the statistics of De
    ("xi/*", "*", "header", DE_STATS), ("budget/*", "*", "header", DE_STATS), ("*", "*", "header", F64),
    # rendered frames: SCI is whole DN (integer-valued), the rest float32 of float64 arithmetic
    ("*e[0-9]*.fits", "SCI", "*", EXACT),
    ("frames/*", "SCI", "*", EXACT),
    ("frames/*", "STARS-*", "*", EXACT),               # a final's SCI with persistence: whole DN too
    ("frames/*", "REFPIX", "*", EXACT),                # a final's stamps: the reference's pixels, whole DN
    ("frames/*", "D_*", "*", EXACT),                   # ... and each variant's difference from them, whole DN
    ("*e[0-9]*.fits", "*", "*", F32),
    ("frames/*", "*", "*", F32),
    # apply-persistence: CURRENT's structure, float32 data
    ("add.fits", "*", "*", F32), ("predict.fits", "*", "*", F32), ("subtract_set.fits", "*", "*", F32),
    ("wfc3.fits", "*", "*", F32),
    # measure: fitted values; the catalogue's predicted S/N is arithmetic
    ("shapes.fits", "*", "snr_pred", F64), ("joint.fits", "*", "snr_pred", F64),
    ("shapes.fits", "*", "*", FIT), ("joint.fits", "*", "*", FIT),
    # the study's shape changes: fits, their differences, and arithmetic on the catalogue
    ("shapes/*", "*", "de*", DE), ("shapes/*", "*", "dabs", DE),
    ("shapes/*", "*", "g[12]*", FIT),
    ("shapes/*", "*", "bound", FIT),                   # the last Newton correction: within a fit's tolerance
    ("shapes/*", "*", "*", F64),
    # correlate: TreeCorr's sums; the De statistics
    ("xi/*", "XI", "r_nom", F64), ("xi/*", "XI", "meanr", SUMS), ("xi/*", "XI", "meanlogr", SUMS),
    ("xi/*", "XI", "weight", SUMS), ("xi/*", "XI", "npairs", SUMS),
    ("xi/*", "XI", "*", DE_STATS), ("xi/*", "COV", "*", DE_STATS),
    ("xi/*", "STATS", "e[12]_*", FIT), ("xi/*", "STATS", "threshold", F64), ("xi/*", "STATS", "frac*", F64),
    ("xi/*", "STATS", "*", DE_STATS),
    ("xi/*", "HIST_DE", "de_*", F64), ("xi/*", "HIST_DE", "frac", F64),
    ("xi/*", "THETA_DE", "de_*", F64), ("xi/*", "THETA_DE", "theta_*", F64), ("xi/*", "THETA_DE", "*", DE_STATS),
    ("xi/*", "PATCHES", "*", SUMS),
    # budget: the budget itself is arithmetic; xi+ and what follows from it are De statistics
    ("budget/*", "*", "theta", SUMS), ("budget/*", "*", "xip_budget", F64), ("budget/*", "*", "*", DE_STATS),
    # the summary: fractions are ratios of counts (F64), everything else statistics of De
    ("summary.json", "*", "*/frac*", F64), ("summary.json", "*", "*fraction", F64),
    ("summary.json", "*", "*/theta", SUMS), ("summary.json", "*", "*/budget", F64),
    ("summary.json", "*", "*", DE_STATS),
    ("summary.md", "*", "*", DE_STATS),
    ("*", "*", "*", F64),
]

#: header keywords that change with the clock or with the bytes of an input (themselves compared)
IGNORED_KEYWORDS = {"DATE", "CHECKSUM", "DATASUM"}
#: table columns holding inputs' DATASUMs (correlate's INPUTS)
IGNORED_COLUMNS = {"datasum"}
_VERSION = re.compile(r"perscli \d+\.\d+\.\d+\S*")
_DATASUM_TEXT = re.compile(r"DATASUM \d+")
_NUMBER = re.compile(r"[-+]?(?:\d+\.\d*|\.\d+|\d+)(?:[eE][-+]?\d+)?%?")


def rule(product: str, hdu: str, column: str):
    """The class (:class:`Tol` or EXACT) of ``column`` of HDU ``hdu`` of ``product``."""
    for p, h, c, tol in RULES:
        if fnmatch.fnmatch(product, p) and fnmatch.fnmatch(hdu, h) and fnmatch.fnmatch(column, c):
            return tol
    return F64


# =================================================================================================
# Comparison
# =================================================================================================

def _close(made, recorded, tol) -> str | None:
    """None when two arrays agree under ``tol`` (EXACT: bit for bit, NaN where NaN), else how they differ."""
    import numpy as np

    a, b = np.asarray(made), np.asarray(recorded)
    if a.shape != b.shape:
        return f"shape {a.shape} != recorded {b.shape}"
    if a.dtype.kind != b.dtype.kind and not (a.dtype.kind in "fc" and b.dtype.kind in "fc"):
        return f"type {a.dtype} != recorded {b.dtype}"
    if a.dtype.kind not in "fc":
        if np.array_equal(a, b):
            return None
        where = np.argwhere(a != b)
        first = tuple(int(i) for i in where[0]) if where.size else ()
        return f"{len(where)} value(s) differ (first at {first}: {a[first]!r} != recorded {b[first]!r})"
    a, b = a.astype(np.float64), b.astype(np.float64)
    nan_a, nan_b = np.isnan(a), np.isnan(b)
    if not np.array_equal(nan_a, nan_b):
        return f"NaN at {int((nan_a != nan_b).sum())} other place(s)"
    same = (a == b) | (nan_a & nan_b)
    if tol is EXACT:
        bad = ~same
        allowed = np.zeros_like(b)
    else:
        allowed = tol.bound(np.where(nan_b, 0.0, b))
        with np.errstate(invalid="ignore"):
            bad = ~same & ~(np.abs(a - b) <= allowed)
    if not bad.any():
        return None
    i = tuple(int(k) for k in np.argwhere(bad)[0])
    worst = np.unravel_index(int(np.argmax(np.where(bad, np.abs(a - b) - allowed, -np.inf))), a.shape)
    worst = tuple(int(k) for k in worst)
    kind = "exact" if tol is EXACT else f"rtol {tol.rtol:g}, atol {tol.atol:g}, scale {tol.scale:g}"
    return (f"{int(bad.sum())} value(s) beyond the tolerance ({kind}); worst at {worst}: {a[worst]!r} != recorded "
            f"{b[worst]!r} (allowed {float(allowed[worst]):.3g}); first at {i}")


def _printed_step(token: str) -> float:
    """Half the unit of the last digit of a printed float ('5.13e-08' -> 5e-11)."""
    mantissa, _, exponent = token.rstrip("%").lower().partition("e")
    decimals = len(mantissa.split(".", 1)[1]) if "." in mantissa else 0
    return 0.5 * 10.0 ** (int(exponent or 0) - decimals)


def text_differs(made: str, recorded: str, tol) -> str | None:
    """None when two texts agree: the same words, and each printed number within ``tol`` (plus half its last
    digit, which printing rounded away); integers (no point, no exponent) exactly."""
    made, recorded = (_DATASUM_TEXT.sub("DATASUM <n>", _VERSION.sub("perscli <version>", t))
                      for t in (made, recorded))
    if made == recorded:
        return None
    words_a, words_b = _NUMBER.split(made), _NUMBER.split(recorded)
    nums_a, nums_b = _NUMBER.findall(made), _NUMBER.findall(recorded)
    if words_a != words_b or len(nums_a) != len(nums_b):
        return f"{made[:200]!r} != recorded {recorded[:200]!r}"
    for x, y in zip(nums_a, nums_b):
        if x == y:
            continue
        is_float = any(ch in y for ch in ".eE")
        if not is_float or tol is EXACT:
            return f"{x} != recorded {y} in {recorded[:200]!r}"
        a, b = float(x.rstrip("%")), float(y.rstrip("%"))
        allowed = tol.atol + (tol.rtol + tol.scale) * abs(b) + _printed_step(x) + _printed_step(y)
        if not abs(a - b) <= allowed:
            return f"{x} != recorded {y} (allowed {allowed:.3g}) in {recorded[:200]!r}"
    return None


def _header_differences(made, recorded, tol, where: str) -> list:
    out = []
    keys_a = {k for k in made.keys() if k not in IGNORED_KEYWORDS and not _is_input_digest(made, k)}
    keys_b = {k for k in recorded.keys() if k not in IGNORED_KEYWORDS and not _is_input_digest(recorded, k)}
    for k in sorted(keys_a ^ keys_b):
        out.append(f"{where}: keyword {k} {'added' if k in keys_a else 'missing'}")
    for k in sorted(keys_a & keys_b - {"HISTORY", "COMMENT", ""}):
        a, b = made[k], recorded[k]
        if isinstance(b, bool) or isinstance(a, bool) or isinstance(b, int) and isinstance(a, int):
            if a != b:
                out.append(f"{where}: {k} = {a!r} != recorded {b!r}")
        elif isinstance(b, float) or isinstance(a, float):
            if not (isinstance(a, (int, float)) and isinstance(b, (int, float))):
                out.append(f"{where}: {k} = {a!r} != recorded {b!r}")
            elif tol is EXACT and a != b or tol is not EXACT and not (
                    a == b or abs(a - b) <= tol.atol + (tol.rtol + tol.scale) * abs(b)):
                out.append(f"{where}: {k} = {a!r} != recorded {b!r}")
        else:
            why = text_differs(str(a), str(b), tol)
            if why:
                out.append(f"{where}: {k}: {why}")
    for k in ("HISTORY", "COMMENT"):
        text_a = " ".join(str(v) for v in made.get(k, [])) if k in made else ""
        text_b = " ".join(str(v) for v in recorded.get(k, [])) if k in recorded else ""
        why = text_differs(text_a, text_b, tol)
        if why:
            out.append(f"{where}: {k}: {why}")
    return out


def _is_input_digest(header, key: str) -> bool:
    # TRUTHDS, PRV01DS, XIDS, CATDS...: "DATASUM of X's data as read"
    return header.comments[key].startswith("DATASUM of") if key in header else False


def fits_differences(made: Path, recorded: Path, product: str) -> list:
    """How FITS file ``made`` differs from ``recorded`` under :data:`RULES` (empty: the same product)."""
    import warnings

    from astropy.io import fits

    out = []
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        with fits.open(made, checksum=False) as A, fits.open(recorded, checksum=False) as B:
            names_a = [(h.name, h.ver, type(h).__name__) for h in A]
            names_b = [(h.name, h.ver, type(h).__name__) for h in B]
            if names_a != names_b:
                return [f"{product}: HDUs {names_a} != recorded {names_b}"]
            for ha, hb in zip(A, B):
                where = f"{product}[{ha.name}]"
                out += _header_differences(ha.header, hb.header, rule(product, ha.name, "header"), where)
                if hb.data is None or ha.data is None:
                    if (ha.data is None) != (hb.data is None):
                        out.append(f"{where}: data {'missing' if ha.data is None else 'added'}")
                    continue
                if isinstance(hb, (fits.BinTableHDU, fits.TableHDU)):
                    cols_a, cols_b = list(ha.columns.names), list(hb.columns.names)
                    if cols_a != cols_b:
                        out.append(f"{where}: columns {cols_a} != recorded {cols_b}")
                        continue
                    for name in cols_b:
                        if name in IGNORED_COLUMNS:
                            continue
                        why = _close(ha.data[name], hb.data[name], rule(product, ha.name, name))
                        if why:
                            out.append(f"{where} column {name}: {why}")
                else:
                    why = _close(ha.data, hb.data, rule(product, ha.name, "*"))
                    if why:
                        out.append(f"{where}: {why}")
    return out


def _json_differences(a, b, product: str, path: str = "") -> list:
    if isinstance(b, dict):
        if not isinstance(a, dict) or sorted(a) != sorted(b):
            return [f"{product}: {path or '/'}: keys {sorted(a) if isinstance(a, dict) else a!r} != recorded "
                    f"{sorted(b)}"]
        return [d for k in b for d in _json_differences(a[k], b[k], product, f"{path}/{k}")]
    if isinstance(b, list):
        if not isinstance(a, list) or len(a) != len(b):
            return [f"{product}: {path}: {a!r} != recorded {b!r}"]
        return [d for k, (x, y) in enumerate(zip(a, b)) for d in _json_differences(x, y, product, f"{path}/{k}")]
    if isinstance(b, float) and isinstance(a, (int, float)) and not isinstance(a, bool):
        tol = rule(product, "*", path)
        if a == b or (math.isnan(a) and math.isnan(b)) or tol is not EXACT and abs(a - b) <= (
                tol.atol + (tol.rtol + tol.scale) * abs(b)):
            return []
    elif a == b and type(a) is type(b):
        return []
    return [f"{product}: {path}: {a!r} != recorded {b!r}"]


def thumbnail(path: Path) -> dict:
    """A PNG as {'size': [width, height], 'thumb': 16 x 16 mean grey levels 0-255}."""
    import numpy as np
    from matplotlib import image

    img = np.asarray(image.imread(str(path)), dtype=np.float64)
    grey = img[..., :3].mean(axis=-1) if img.ndim == 3 else img
    h, w = grey.shape
    rows = np.array_split(np.arange(h), 16)
    cols = np.array_split(np.arange(w), 16)
    thumb = [[round(float(grey[np.ix_(r, c)].mean()) * 255, 2) for c in cols] for r in rows]
    return {"size": [int(w), int(h)], "thumb": thumb}


#: a figure's thumbnail: mean grey levels of 16 x 16 blocks may move by this much (0-255): data within their
#: tolerances move lines and points by under a pixel, which changes a block's mean by well under one level;
#: a missing curve, axis or legend changes some block by tens of levels
THUMB_LEVELS = 4.0


def png_differences(made: Path, recorded: dict, product: str) -> list:
    import numpy as np

    got = thumbnail(made)
    if got["size"] != recorded["size"]:
        return [f"{product}: size {got['size']} != recorded {recorded['size']}"]
    diff = np.abs(np.array(got["thumb"]) - np.array(recorded["thumb"]))
    if diff.max() > THUMB_LEVELS:
        i = np.unravel_index(int(diff.argmax()), diff.shape)
        return [f"{product}: block {tuple(int(k) for k in i)} of the 16 x 16 thumbnail changed by "
                f"{diff.max():.1f} grey levels (allowed {THUMB_LEVELS:g})"]
    return []


def record_name(product: str) -> str:
    """The name of a product's record: FITS gzipped, PNG as its thumbnail, the rest as it is."""
    if product.endswith(".fits"):
        return product + ".gz"
    if product.endswith(".png"):
        return product + ".json"
    return product


def differences(made: Path, recorded: Path, product: str) -> list:
    """How product file ``made`` differs from its record ``recorded`` (:func:`record_name`)."""
    if not recorded.exists():
        return [f"{product}: not recorded (record it: python tests/golden.py --record)"]
    if not made.exists():
        return [f"{product}: not made"]
    if product.endswith(".fits"):
        return fits_differences(made, recorded, product)
    if product.endswith(".png"):
        rec = thumbnail(recorded) if recorded.suffix == ".png" else json.loads(recorded.read_text())
        return png_differences(made, rec, product)
    if product.endswith(".json"):
        return _json_differences(json.loads(made.read_text()), json.loads(recorded.read_text()), product)
    text_a, text_b = made.read_text(), recorded.read_text()
    why = text_differs(text_a, text_b, rule(product, "*", "*"))
    return [f"{product}: {why}"] if why else []


def products(folder: Path) -> list:
    """The products of a folder (commands or study) that are compared: not the run's records and timings."""
    folder = Path(folder)
    out = []
    for p in sorted(folder.rglob("*")):
        rel = p.relative_to(folder).as_posix()
        if p.is_file() and not rel.startswith(".state") and rel not in ("cost.json", "study.yaml"):
            out.append(rel)
    return out


def compare_tree(made: Path, recorded: Path, names=None) -> list:
    """Every difference between the products in ``made`` and their records in ``recorded``."""
    made, recorded = Path(made), Path(recorded)
    names = products(made) if names is None else list(names)
    recorded_names = {_product_of(p.relative_to(recorded).as_posix()) for p in recorded.rglob("*") if p.is_file()}
    out = [f"{name}: recorded but not made" for name in sorted(recorded_names - set(names))]
    for name in names:
        out += differences(made / name, recorded / record_name(name), name)
    return out


def _product_of(record: str) -> str:
    for suffix in (".fits.gz", ".png.json"):
        if record.endswith(suffix):
            return record[: -len(suffix) + (5 if suffix == ".fits.gz" else 4)]
    return record


def record_tree(made: Path, dest: Path) -> None:
    """Write the records of every product of ``made`` into ``dest`` (replacing what was there)."""
    made, dest = Path(made), Path(dest)
    if dest.exists():
        shutil.rmtree(dest)
    for name in products(made):
        target = dest / record_name(name)
        target.parent.mkdir(parents=True, exist_ok=True)
        if name.endswith(".fits"):
            # mtime 0: the same product gives the same record bytes
            with open(made / name, "rb") as src, open(target, "wb") as raw, \
                    gzip.GzipFile(fileobj=raw, mode="wb", mtime=0, compresslevel=9) as out:
                shutil.copyfileobj(src, out)
        elif name.endswith(".png"):
            target.write_text(json.dumps(thumbnail(made / name)) + "\n")
        else:
            shutil.copy(made / name, target)


# =================================================================================================
# Making the products
# =================================================================================================

def versions():
    """The versions of the libraries whose arithmetic the products depend on."""
    from importlib.metadata import version

    return {name: version(name) for name in LIBRARIES}


def run_commands(workdir, env=None) -> Path:
    """Run :data:`COMMANDS` in ``workdir``; returns it."""
    workdir = Path(workdir)
    workdir.mkdir(parents=True, exist_ok=True)
    for name, args in COMMANDS.items():
        proc = subprocess.run([sys.executable, "-m", "perscli", *args, "-o", name, "--overwrite"], cwd=workdir,
                              env=env, capture_output=True, text=True)
        if proc.returncode:
            raise RuntimeError(f"perscli {' '.join(args)} -o {name}: exit {proc.returncode}: {proc.stderr[-2000:]}")
    return workdir


def run_study(dest, settings, env=None) -> Path:
    """Run the ci study serially into ``dest`` with ``settings`` (--set strings); returns ``dest``."""
    args = [sys.executable, "-m", "perscli", "-q", "study", "--preset", "ci", "-o", str(dest), "--scheduler",
            "serial"]
    for s in settings:
        args += ["--set", s]
    proc = subprocess.run(args, env=env, capture_output=True, text=True)
    if proc.returncode:
        raise RuntimeError(f"perscli study --preset ci: exit {proc.returncode}: {proc.stderr[-2000:]}")
    return Path(dest)


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("folders", nargs="*", metavar="DIR",
                        help="compare two folders of products (made, recorded-as-made) instead")
    parser.add_argument("--record", action="store_true", help="write the records into tests/golden/")
    parser.add_argument("--study", action="store_true", help="also the ci study")
    parser.add_argument("--workdir", default="golden_work")
    a = parser.parse_args(argv)
    if a.folders:
        if len(a.folders) != 2:
            parser.error("give two folders")
        found = [d for name in products(Path(a.folders[0]))
                 for d in differences(Path(a.folders[0]) / name, Path(a.folders[1]) / name, name)]
        print("\n".join(found) or "the same products, within the tolerances")
        return 1 if found else 0
    work = Path(a.workdir)
    made = {"commands": run_commands(work / "commands")}
    if a.study:
        sys.path.insert(0, str(HERE))
        from test_study import CI

        made["study"] = run_study(work / "study", CI)
    for kind, folder in made.items():
        found = compare_tree(folder, RECORDS / kind)
        print(f"{kind}: " + ("the recorded products, within the tolerances" if not found else
                             f"{len(found)} difference(s):\n  " + "\n  ".join(found)))
        if a.record:
            record_tree(folder, RECORDS / kind)
            print(f"{kind}: recorded in {RECORDS / kind}")
    if a.record:
        (RECORDS / "versions.json").write_text(json.dumps(versions(), indent=1, sort_keys=True) + "\n")
    return 0


if __name__ == "__main__":
    os.environ.setdefault("PYTHONHASHSEED", "0")
    sys.exit(main())
