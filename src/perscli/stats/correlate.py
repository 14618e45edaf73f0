"""Shape changes De between two measurements: their correlation function and statistics.

The paper measures every galaxy twice, on an exposure with persistence (A)
and on the same exposure without it (B), and studies De = g(A) - g(B):

- the shear-shear correlation function xi+/- of De (TreeCorr's
  ``GGCorrelation``), with a jackknife covariance over k-means patches;
- N, the mean intrinsic ellipticity (the mean g of B), the mean De with its
  standard error, and the fraction of objects with |De| above thresholds
  (1e-8 and 1e-4 in the paper);
- the histogram of |De| (the paper's figure hist_de);
- the |De|-weighted distribution of the position angle of De in bins of
  |De|, with bootstrap errors (the paper's figure bin_theta): uniform if
  persistence has no preferred direction.

:func:`load_shape_changes` reads De from one or two SHAPES tables
(``perscli measure``), :func:`de_statistics`, :func:`de_histogram`,
:func:`theta_distribution` and :func:`correlate_de` compute the pieces, and
:func:`correlate_files` is ``perscli correlate`` as a function.

Orientation: g in a SHAPES table is in the frame's pixel axes, and nothing in
the table says how those axes sit on the sky, so De is correlated as given.
xi+ does not depend on that when one rotation takes the pixel axes to the
local sky axes over the whole catalogue (one detector, one pointing): a
rotation by phi multiplies every De by exp(2i phi) and leaves De De*
unchanged.  If the pixel axes are also mirrored with respect to the sky, xi+
is unchanged in flat geometry and to within the parallel transport between
the two objects' local frames on the sky (well under 1 % at these
separations).  xi- does depend on the orientation: a rotation turns it into
xi- exp(4i phi), mixing its real and imaginary parts.  Catalogues that
combine detectors or pointings with different orientations need their De
rotated to the sky first (and given with --de1/--de2).
"""

from __future__ import annotations

import contextlib
import logging
import math
import os
import tempfile
from dataclasses import dataclass, field

import numpy as np

from .. import PerscliError
from ..executor import threads
from ..instrument import ROMAN_PIXEL_SCALE
from ..io.tables import open_table

log = logging.getLogger("perscli")

#: |De| thresholds of the paper's fractions
DEFAULT_THRESHOLDS = (1e-8, 1e-4)
#: |De| bin edges for the position-angle distribution (|g| <= 1, so |De| <= 2)
DEFAULT_THETA_EDGES = (1e-8, 1e-6, 1e-4, 1e-2, 2.0)
#: position-angle bins over [-90, 90) degrees
N_ANGLE = 18
#: histogram of |De|: log bins from HIST_LO to HIST_HI, HIST_PER_DECADE per decade, plus under/overflow
HIST_LO, HIST_HI, HIST_PER_DECADE = 1e-12, 1.0, 5
#: the jackknife needs objects in every patch: at least this many per patch on average
MIN_PER_PATCH = 10
#: bootstrap over at most this many groups of objects (random groups of equal size above it)
MAX_BOOT_GROUPS = 2_000
SEP_UNITS = ("arcsec", "arcmin", "deg", "rad")
CROSS_PATCH_WEIGHTS = ("simple", "mean", "match")
#: TUNIT spellings of x/y columns in pixels, and of angles TreeCorr understands
_PIXEL_UNITS = {"", "pix", "pixel", "pixels", "px"}
_ANGLE_UNITS = {"arcsec": "arcsec", "arcmin": "arcmin", "deg": "deg", "degree": "deg", "degrees": "deg",
                "rad": "rad", "radian": "rad", "radians": "rad"}
WHAT = "SHAPES table"


@dataclass
class ShapeChanges:
    """De of a set of objects, with their positions and where they came from.

    Attributes
    ----------
    de1, de2 : ndarray
        The shape change per object (float64), in the axes of the input g.
    e1, e2 : ndarray or None
        Intrinsic shape: g of the reference frame B (None when De was given as columns).
    pos1, pos2 : ndarray
        ra, dec in degrees (coords 'radec') or x, y in ``pos_units`` (coords 'xy').
    coords : {'radec', 'xy'}
    pos_units : str
        'deg' for ra/dec; an angle unit TreeCorr knows for x/y.
    ids : ndarray or None
        Object ids (when the input has them).
    counts : dict
        Rows read, matched, flagged, dropped as non-finite, and used.
    inputs : list of (str, str, int)
        (keyword stem, file name, DATASUM) for provenance.
    params : dict
        Header keywords that describe how De was formed.
    source : str
        One line saying what De is, for the HISTORY card and messages.
    """

    de1: np.ndarray
    de2: np.ndarray
    e1: np.ndarray | None
    e2: np.ndarray | None
    pos1: np.ndarray
    pos2: np.ndarray
    coords: str
    pos_units: str
    ids: np.ndarray | None = None
    counts: dict = field(default_factory=dict)
    inputs: list = field(default_factory=list)
    params: dict = field(default_factory=dict)
    source: str = ""

    def __len__(self) -> int:
        return len(self.de1)


# ------------------------------------------------------------------------------------------------
# reading
# ------------------------------------------------------------------------------------------------

def _names(table) -> dict:
    return {n.lower(): n for n in table.names}


def _frame_rows(table, frame, label: str, *, hint: str):
    """Row indices of one frame of a SHAPES table (all rows when it holds one frame)."""
    names = _names(table)
    if "frame" not in names:
        if frame not in (None, 0):
            raise PerscliError(f"{label} has no frame column (it holds one frame, 0), so it has no frame {frame}: "
                               f"{hint}")
        return np.arange(len(table)), label
    frames = table.column("frame", kind="integer")
    present = np.unique(frames)
    listed = ", ".join(str(int(k)) for k in present[:10]) + (", ..." if len(present) > 10 else "")
    if frame is None:
        if len(present) > 1:
            raise PerscliError(f"{label} holds frames {listed}: give --frames A B ({hint})")
        return np.arange(len(table)), label
    rows = np.flatnonzero(frames == frame)
    if len(rows) == 0:
        raise PerscliError(f"{label} has no rows of frame {frame} (it holds frame(s) {listed}): {hint}")
    return rows, f"{label} frame {frame}"


def _check_unique(ids, label):
    s = np.sort(ids)
    dup = s[1:][s[1:] == s[:-1]]
    if len(dup):
        raise PerscliError(f"{label}: id {int(dup[0])} appears more than once ({len(np.unique(dup))} repeated ids): "
                           "ids must be unique within a frame; check that this is one SHAPES table of one catalogue")


def _positions(table, rows, mode: str, pixel_scale: float):
    """(pos1, pos2, coords, units, params) for ``rows`` of ``table``."""
    names = _names(table)
    has_radec = {"ra", "dec"} <= set(names)
    has_xy = {"x", "y"} <= set(names)
    if mode == "auto":
        mode = "radec" if has_radec else "xy"
    if mode == "radec":
        if not has_radec:
            raise PerscliError(f"{table.label}: HDU {table.index} has no ra/dec columns for --positions radec; "
                               "use --positions xy (pixel positions) or add ra/dec in degrees")
        return (table.column("ra").astype(np.float64)[rows], table.column("dec").astype(np.float64)[rows],
                "radec", "deg", {"COORDS": ("radec", "positions: ra, dec (deg), spherical")})
    if not has_xy:
        raise PerscliError(f"{table.label}: HDU {table.index} has neither ra/dec nor x/y columns; "
                           "a SHAPES table needs positions")
    unit = table.unit("x").lower()
    x = table.column("x").astype(np.float64)[rows]
    y = table.column("y").astype(np.float64)[rows]
    params = {"COORDS": ("xy", "positions: x, y, flat")}
    if unit in _PIXEL_UNITS:
        params["PIXSCALE"] = (pixel_scale, "[arcsec/pix] converts x, y in pixels to angles")
        return x * pixel_scale, y * pixel_scale, "xy", "arcsec", params
    if unit not in _ANGLE_UNITS:
        raise PerscliError(f"{table.label}: column x has unit '{table.unit('x')}', which is neither pixels nor an "
                           "angle (arcsec, arcmin, deg, rad): fix TUNIT or use --positions radec")
    return x, y, "xy", _ANGLE_UNITS[unit], params


def _finite_rows(columns: dict, keep: np.ndarray, what: str) -> np.ndarray:
    """Drop rows where a needed column is not finite; refuse a column that is never finite."""
    n = int(keep.sum())
    for name, values in columns.items():
        ok = np.isfinite(values)
        if not np.any(ok & keep):
            raise PerscliError(f"{name} is NaN (or infinite) in all {n} {what}: nothing to correlate; "
                               "check the column")
    good = keep.copy()
    for values in columns.values():
        good &= np.isfinite(values)
    dropped = n - int(good.sum())
    if dropped:
        bad = [name for name, values in columns.items() if not np.all(np.isfinite(values[keep]))]
        log.warning("%d of %d %s dropped: not finite in %s", dropped, n, what, ", ".join(bad))
    return good


def load_shape_changes(catalogs, *, frames=None, de_columns=None, common_ids=False, positions="auto",
                       pixel_scale=ROMAN_PIXEL_SCALE, stdin=None) -> ShapeChanges:
    """De from one or two SHAPES tables.

    Parameters
    ----------
    catalogs : sequence of str
        One or two paths ('-' for standard input, at most once).  With two,
        De = g(first) - g(second), objects matched by id.
    frames : (int, int), optional
        Frame numbers (the ``frame`` column of ``perscli measure``) of A and
        B.  With one catalogue: both are taken from it (``perscli measure A B``
        writes A as frame 0 and B as frame 1).  With two: frame A of the first
        and frame B of the second (by default each must hold one frame).
    de_columns : (str, str), optional
        One catalogue only: the columns holding De1 and De2.
    common_ids : bool
        Two measurements: correlate the ids both hold, instead of refusing
        tables whose ids differ.
    positions : {'auto', 'radec', 'xy'}
        ra/dec (degrees, spherical; 'auto' when present) or x/y (flat; in
        pixels times ``pixel_scale``, or in the angle unit of the column's
        TUNIT).  Taken from B (the reference frame) when there are two.
    pixel_scale : float
        Arcsec per pixel for x/y in pixels (Roman: 0.11).

    Only objects with ``flags == 0`` (in both A and B, or in the one table
    when it has a flags column) and finite values are used.

    Raises
    ------
    PerscliError
        Unreadable input, missing columns, ids that do not match, no overlap,
        every object flagged, a needed column without a finite value.
    """
    catalogs = list(catalogs)
    if not 1 <= len(catalogs) <= 2:
        raise PerscliError(f"give one or two SHAPES tables, not {len(catalogs)}")
    if catalogs.count("-") > 1:
        raise PerscliError("only one input can be standard input ('-')")
    if positions not in ("auto", "radec", "xy"):
        raise PerscliError(f"positions must be auto, radec or xy, not {positions!r}")
    if de_columns is not None and (len(catalogs) != 1 or frames is not None):
        raise PerscliError("--de1/--de2 name the De columns of one table; they do not go with two tables or --frames")
    if len(catalogs) == 1 and de_columns is None and frames is None:
        raise PerscliError(f"{catalogs[0]}: one SHAPES table needs --frames A B (two frames of it) or "
                           "--de1 COL --de2 COL (its De columns)")
    with contextlib.ExitStack() as stack:
        tables = [stack.enter_context(open_table(name, what=WHAT, stdin=stdin)) for name in catalogs]
        inputs = [(f"SHAPE{'AB'[k]}" if len(tables) == 2 else "SHAPES", t.name, t.datasum)
                  for k, t in enumerate(tables)]
        if de_columns is not None:
            return _from_columns(tables[0], de_columns, positions, pixel_scale, inputs)
        return _from_frames(tables, frames, common_ids, positions, pixel_scale, inputs)


def _from_columns(table, de_columns, positions, pixel_scale, inputs) -> ShapeChanges:
    c1, c2 = de_columns
    needed = (c1, c2, "ra/dec or x/y")
    de1 = table.column(c1, needed=needed).astype(np.float64)
    de2 = table.column(c2, needed=needed).astype(np.float64)
    n = len(table)
    if n == 0:
        raise PerscliError(f"{table.label}: HDU {table.index} has no rows: nothing to correlate")
    rows = np.arange(n)
    pos1, pos2, coords, units, pparams = _positions(table, rows, positions, pixel_scale)
    keep = np.ones(n, dtype=bool)
    flagged = 0
    if "flags" in _names(table):
        keep = table.column("flags", kind="integer") == 0
        flagged = n - int(keep.sum())
        if not keep.any():
            raise PerscliError(f"{table.label}: all {n} objects are flagged (flags != 0): nothing to correlate")
    what = f"unflagged objects of {table.label}"
    cols = {f"{table.label}: column '{c1}'": de1, f"{table.label}: column '{c2}'": de2,
            f"{table.label}: position column 1": pos1, f"{table.label}: position column 2": pos2}
    good = _finite_rows(cols, keep, what)
    ids = table.column("id", kind="integer")[good] if "id" in _names(table) else None
    counts = {"rows_a": n, "rows_b": 0, "matched": n, "flagged": flagged,
              "nonfinite": int(keep.sum() - good.sum()), "used": int(good.sum())}
    params = {"DEMODE": ("columns", "De read from named columns"), "DE1COL": (c1, "column of De1"),
              "DE2COL": (c2, "column of De2"), **pparams}
    return ShapeChanges(de1=de1[good], de2=de2[good], e1=None, e2=None, pos1=pos1[good], pos2=pos2[good],
                        coords=coords, pos_units=units, ids=ids, counts=counts, inputs=inputs, params=params,
                        source=f"De = ({c1}, {c2}) of {table.label}")


def _side(table, rows, label):
    needed = ("id", "g1", "g2", "flags")
    out = {"id": table.column("id", kind="integer", needed=needed)[rows]}
    for key in ("g1", "g2"):
        out[key] = table.column(key, needed=needed).astype(np.float64)[rows]
    if "flags" in _names(table):
        out["flags"] = table.column("flags", kind="integer")[rows]
    else:
        out["flags"] = np.zeros(len(rows), dtype=np.int64)
    out["label"] = label
    _check_unique(out["id"], label)
    return out


def _from_frames(tables, frames, common_ids, positions, pixel_scale, inputs) -> ShapeChanges:
    if len(tables) == 1:
        ta = tb = tables[0]
        hint = f"--frames A B picks two of the frames of {ta.label}"
    else:
        ta, tb = tables
        hint = "with two tables --frames A B picks frame A of the first and frame B of the second"
    fa, fb = frames if frames is not None else (None, None)
    if len(tables) == 1 and fa == fb:
        raise PerscliError(f"--frames {fa} {fb}: A and B must be two different frames of {ta.label}")
    rows_a, label_a = _frame_rows(ta, fa, ta.label, hint=hint)
    rows_b, label_b = _frame_rows(tb, fb, tb.label, hint=hint)
    a, b = _side(ta, rows_a, label_a), _side(tb, rows_b, label_b)
    if len(a["id"]) == 0 or len(b["id"]) == 0:
        empty = label_a if len(a["id"]) == 0 else label_b
        raise PerscliError(f"{empty} has no rows: nothing to correlate")
    common, ia, ib = np.intersect1d(a["id"], b["id"], assume_unique=True, return_indices=True)
    if len(common) == 0:
        raise PerscliError(f"{label_a} and {label_b} have no id in common: they are not two measurements of "
                           "the same catalogue")
    only_a, only_b = len(a["id"]) - len(common), len(b["id"]) - len(common)
    if (only_a or only_b) and not common_ids:
        example = np.setdiff1d(a["id"], common)[:1] if only_a else np.setdiff1d(b["id"], common)[:1]
        raise PerscliError(f"ids do not match: {only_a} of {label_a} are not in {label_b} and {only_b} of {label_b} "
                           f"are not in {label_a} (e.g. id {int(example[0])}); both must measure the same "
                           f"catalogue, or give --common-ids to use the {len(common)} ids they share")
    if only_a or only_b:
        log.info("--common-ids: %d ids in both, %d only in %s, %d only in %s", len(common), only_a, label_a,
                 only_b, label_b)
    keep = (a["flags"][ia] == 0) & (b["flags"][ib] == 0)
    if not keep.any():
        raise PerscliError(f"all {len(common)} matched objects are flagged in {label_a} or {label_b} "
                           "(flags != 0): nothing to correlate")
    pos1, pos2, coords, units, pparams = _positions(tb, rows_b[ib], positions, pixel_scale)
    g1a, g2a, g1b, g2b = a["g1"][ia], a["g2"][ia], b["g1"][ib], b["g2"][ib]
    cols = {f"{label_a}: g1": g1a, f"{label_a}: g2": g2a, f"{label_b}: g1": g1b, f"{label_b}: g2": g2b,
            f"{label_b}: position column 1": pos1, f"{label_b}: position column 2": pos2}
    good = _finite_rows(cols, keep, "objects unflagged in both")
    counts = {"rows_a": len(rows_a), "rows_b": len(rows_b), "matched": len(common),
              "flagged": int(len(common) - keep.sum()), "nonfinite": int(keep.sum() - good.sum()),
              "used": int(good.sum())}
    params = {"DEMODE": ("frames", "De = g(A) - g(B), matched by id")}
    if frames is not None:
        params["FRAMEA"] = (int(fa), "frame of A (with persistence)")
        params["FRAMEB"] = (int(fb), "frame of B (reference)")
    params["COMMONID"] = (bool(common_ids), "ids in only one of A, B allowed")
    params.update(pparams)
    return ShapeChanges(de1=g1a[good] - g1b[good], de2=g2a[good] - g2b[good], e1=g1b[good], e2=g2b[good],
                        pos1=pos1[good], pos2=pos2[good], coords=coords, pos_units=units, ids=common[good],
                        counts=counts, inputs=inputs, params=params, source=f"De = g({label_a}) - g({label_b})")


# ------------------------------------------------------------------------------------------------
# statistics
# ------------------------------------------------------------------------------------------------

def _mean_err(values):
    n = len(values)
    if n == 0:
        return math.nan, math.nan
    mean = float(np.mean(values))
    err = float(np.std(values, ddof=1) / math.sqrt(n)) if n > 1 else math.nan
    return mean, err


def _abs(de1, de2) -> np.ndarray:
    out = np.multiply(de1, de1)
    out += np.multiply(de2, de2)
    return np.sqrt(out, out=out)


def de_statistics(de1, de2, *, e1=None, e2=None, thresholds=DEFAULT_THRESHOLDS) -> dict:
    """The paper's summary of De.

    Parameters
    ----------
    de1, de2 : ndarray
        Shape changes.
    e1, e2 : ndarray, optional
        Intrinsic shapes (g of the reference frame); NaN means when absent.
    thresholds : sequence of float
        |De| thresholds.

    Returns
    -------
    dict
        n; e1_mean, e1_err, e2_mean, e2_err (standard errors); de1_mean,
        de1_err, de2_mean, de2_err; de_abs_mean, de_abs_max; threshold,
        n_ge and frac_ge (arrays: objects with |De| >= threshold, and their
        fraction of n).
    """
    de1, de2 = np.asarray(de1, dtype=np.float64), np.asarray(de2, dtype=np.float64)
    absde = _abs(de1, de2)
    n = len(absde)
    out = {"n": n}
    for key, values in (("e1", e1), ("e2", e2), ("de1", de1), ("de2", de2)):
        stem = f"{key}_mean"
        mean, err = _mean_err(values) if values is not None else (math.nan, math.nan)
        out[stem], out[f"{key}_err"] = mean, err
    out["de_abs_mean"] = float(absde.mean()) if n else math.nan
    out["de_abs_max"] = float(absde.max()) if n else math.nan
    thresholds = np.asarray(sorted(thresholds), dtype=np.float64)
    out["threshold"] = thresholds
    out["n_ge"] = np.array([np.count_nonzero(absde >= t) for t in thresholds], dtype=np.int64)
    out["frac_ge"] = out["n_ge"] / n if n else np.full(len(thresholds), math.nan)
    return out


def de_histogram(absde, *, lo=HIST_LO, hi=HIST_HI, per_decade=HIST_PER_DECADE) -> dict:
    """Counts of |De| in log bins, with an underflow bin [0, lo) and an overflow bin [hi, inf).

    Returns
    -------
    dict
        de_lo, de_hi (bin edges), count, frac (of all objects).
    """
    nbin = int(round(math.log10(hi / lo) * per_decade))
    edges = np.logspace(math.log10(lo), math.log10(hi), nbin + 1)
    index = np.searchsorted(edges, np.asarray(absde), side="right")
    count = np.bincount(index, minlength=nbin + 2)
    total = max(len(absde), 1)
    return {"de_lo": np.concatenate([[0.0], edges]), "de_hi": np.concatenate([edges, [np.inf]]),
            "count": count.astype(np.int64), "frac": count / total}


def position_angle(de1, de2) -> np.ndarray:
    """Position angle of De in degrees in [-90, 90), from the first axis towards the second."""
    theta = 0.5 * np.degrees(np.arctan2(de2, de1))
    return np.where(theta >= 90.0, theta - 180.0, theta)


def theta_distribution(de1, de2, *, edges=DEFAULT_THETA_EDGES, nangle=N_ANGLE, nboot=200, seed=1,
                       max_groups=MAX_BOOT_GROUPS) -> dict:
    """|De|-weighted distribution of De's position angle in bins of |De|, with bootstrap errors.

    In each |De| bin, ``frac[k]`` = sum of |De| over objects whose angle is
    in angle bin k / sum of |De| over the bin's objects (1/nangle each when
    the angle is uniform).  Errors: standard deviation over ``nboot``
    bootstrap resamples of the bin's objects.  When a bin holds more than
    ``max_groups`` objects, each object is first put into one of
    ``max_groups`` groups at random and the groups are resampled: for
    independent objects the group sums are independent too, so this has
    the same expected variance, at a cost O(nboot x max_groups) instead of
    O(nboot x n).

    Returns
    -------
    dict
        Arrays with one entry per (|De| bin, angle bin): de_lo, de_hi, n
        (objects in the |De| bin), theta_lo, theta_hi (degrees), frac,
        frac_err, chi2_uniform (of the |De| bin, against 1/nangle with the
        bootstrap errors, nangle - 1 degrees of freedom); and ``ngroups``.
    """
    de1, de2 = np.asarray(de1, dtype=np.float64), np.asarray(de2, dtype=np.float64)
    edges = np.asarray(edges, dtype=np.float64)
    absde = _abs(de1, de2)
    inside = (absde >= edges[0]) & (absde < edges[-1])
    if not inside.all():
        absde, de1, de2 = absde[inside], de1[inside], de2[inside]
    # angle bin from atan2 in (-pi, pi]: position angle 0.5 atan2 + 90 deg over the bin width;
    # computed in place, as these arrays can hold millions of objects
    phase = np.arctan2(de2, de1)
    phase += math.pi
    phase *= nangle / (2 * math.pi)
    abin = phase.astype(np.intp)
    del phase
    abin %= nangle          # atan2 = pi (position angle 90) is -90
    debin = np.searchsorted(edges, absde, side="right")
    debin -= 1
    rng = np.random.default_rng(seed)
    width = 180.0 / nangle
    rows = {k: [] for k in ("de_lo", "de_hi", "n", "theta_lo", "theta_hi", "frac", "frac_err", "chi2_uniform")}
    ngroups = []
    for j, (lo, hi) in enumerate(zip(edges[:-1], edges[1:])):
        sel = debin == j
        n = int(np.count_nonzero(sel))
        frac = np.full(nangle, np.nan)
        err = np.full(nangle, np.nan)
        groups = min(n, max_groups)
        if n:
            w, a = absde[sel], abin[sel]
            sums = np.bincount(a, weights=w, minlength=nangle)
            frac = sums / sums.sum()
            index = np.arange(n) if groups == n else rng.integers(0, groups, n)
            index *= nangle
            index += a
            per_group = np.bincount(index, weights=w, minlength=groups * nangle).reshape(groups, nangle)
            del index
            draws = rng.integers(0, groups, size=(nboot, groups), dtype=np.intp)
            draws += np.arange(nboot)[:, None] * groups
            times = np.bincount(draws.ravel(), minlength=nboot * groups).reshape(nboot, groups)
            boot = times.astype(np.float64) @ per_group
            total = boot.sum(axis=1, keepdims=True)
            boot = boot[total[:, 0] > 0] / total[total[:, 0] > 0]
            err = boot.std(axis=0, ddof=1) if len(boot) > 1 else np.full(nangle, np.nan)
        ok = np.isfinite(err) & (err > 0)
        chi2 = float(np.sum(((frac[ok] - 1.0 / nangle) / err[ok]) ** 2)) if ok.any() else math.nan
        ngroups.append(groups)
        rows["de_lo"].append(np.full(nangle, lo))
        rows["de_hi"].append(np.full(nangle, hi))
        rows["n"].append(np.full(nangle, n, dtype=np.int64))
        rows["theta_lo"].append(-90.0 + width * np.arange(nangle))
        rows["theta_hi"].append(-90.0 + width * np.arange(1, nangle + 1))
        rows["frac"].append(frac)
        rows["frac_err"].append(err)
        rows["chi2_uniform"].append(np.full(nangle, chi2))
    out = {k: np.concatenate(v) for k, v in rows.items()}
    out["ngroups"] = ngroups
    return out


# ------------------------------------------------------------------------------------------------
# correlation
# ------------------------------------------------------------------------------------------------

def _treecorr_logger():
    """TreeCorr logs to stdout unless given a logger: send it to perscli's (stderr), quieter by one level."""
    logger = logging.getLogger("perscli.treecorr")
    logger.setLevel(logging.DEBUG if log.isEnabledFor(logging.DEBUG) else logging.WARNING)
    return logger


def read_patch_centers(path: str, coords: str) -> np.ndarray:
    """Patch centres from a file: TreeCorr's (x, y[, z]) columns or ra/dec in degrees.

    Accepts the file TreeCorr's ``Catalog.write_patch_centers`` writes (FITS
    or ASCII), a FITS table with ra/dec columns (degrees), or a
    ``perscli correlate`` output (its PATCHES table).

    Returns
    -------
    ndarray
        (npatch, 3) unit vectors for coords 'radec'; (npatch, 2) for 'xy'
        (in TreeCorr's internal units, as TreeCorr writes them).
    """
    if not os.path.exists(path):
        raise PerscliError(f"{path}: no such file (--patch-centers)")
    with open(path, "rb") as fh:
        is_fits = fh.read(9) == b"SIMPLE  ="
    if is_fits:
        from ..io.fitsfile import open_fits

        with open_fits(path) as fitsin:
            tables = [h for h in fitsin.hdus if h.kind == "table"]
            named = [h for h in tables if h.name == "PATCHES"]
            if not tables:
                raise PerscliError(f"{path}: has no binary table of patch centres (--patch-centers)")
            hdu = (named or tables)[0]
            try:
                data = {n.lower(): np.asarray(hdu.read_column(n), dtype=np.float64) for n in hdu.colnames}
            except (TypeError, ValueError) as exc:
                raise PerscliError(f"{path}: not a readable FITS table of patch centres ({exc})") from None
    else:
        try:
            arr = np.genfromtxt(path, names=True, dtype=np.float64)
        except (OSError, ValueError) as exc:
            raise PerscliError(f"{path}: not a readable table of patch centres ({exc})") from None
        if arr.dtype.names is None:
            raise PerscliError(f"{path}: no column names: a patch-centre file has columns x y [z] or ra dec")
        data = {n.lower(): np.atleast_1d(arr[n]) for n in arr.dtype.names}
    if coords == "radec":
        if {"x", "y", "z"} <= set(data):
            centers = np.column_stack([data["x"], data["y"], data["z"]])
        elif {"ra", "dec"} <= set(data):
            ra, dec = np.radians(data["ra"]), np.radians(data["dec"])
            centers = np.column_stack([np.cos(dec) * np.cos(ra), np.cos(dec) * np.sin(ra), np.sin(dec)])
        else:
            raise PerscliError(f"{path}: patch centres for ra/dec positions need columns x, y, z (TreeCorr's unit "
                               "vectors) or ra, dec (degrees)")
    else:
        if not {"x", "y"} <= set(data) or "z" in data:
            raise PerscliError(f"{path}: patch centres for x/y positions need columns x, y (and no z)")
        centers = np.column_stack([data["x"], data["y"]])
    if len(centers) < 2:
        raise PerscliError(f"{path}: {len(centers)} patch centre(s); the jackknife needs at least 2")
    if not np.all(np.isfinite(centers)):
        raise PerscliError(f"{path}: patch centres that are not finite")
    return centers


def correlate_de(sc: ShapeChanges, *, min_sep=1.0, max_sep=100.0, nbins=20, sep_units="arcmin", bin_slop=None,
                 npatch=20, patch_centers=None, cross_patch_weight="match", seed=1, workers=1):
    """xi+/- of De with TreeCorr, and its jackknife covariance.

    Parameters
    ----------
    sc : ShapeChanges
        De and positions.
    min_sep, max_sep, nbins, sep_units, bin_slop
        TreeCorr's log binning (bin_slop None: TreeCorr's default,
        min(1, 0.1 / bin_size)).
    npatch : int
        k-means patches for the jackknife (ignored with ``patch_centers``).
    patch_centers : ndarray, optional
        Patch centres (see :func:`read_patch_centers`).
    cross_patch_weight : {'match', 'simple', 'mean'}
        TreeCorr's weight of pairs across a removed and a kept patch
        ('match': Mohammad & Percival 2022's, recommended for the jackknife).
    seed : int
        Seed of the k-means initialisation (same seed, same patches).
    workers : int
        TreeCorr's OpenMP threads (:func:`perscli.executor.threads`: 1 when
        not given, never all cores unasked).

    Returns
    -------
    (treecorr.GGCorrelation, treecorr.Catalog)
    """
    import treecorr

    if not 0 < min_sep < max_sep:
        raise PerscliError(f"--min-sep {min_sep} and --max-sep {max_sep}: need 0 < min-sep < max-sep")
    if sep_units not in SEP_UNITS:
        raise PerscliError(f"--sep-units {sep_units}: one of {', '.join(SEP_UNITS)}")
    if cross_patch_weight not in CROSS_PATCH_WEIGHTS:
        raise PerscliError(f"--cross-patch-weight {cross_patch_weight}: one of {', '.join(CROSS_PATCH_WEIGHTS)}")
    n = len(sc)
    wanted = len(patch_centers) if patch_centers is not None else npatch
    if wanted < 2:
        raise PerscliError(f"{wanted} patch(es): the jackknife needs at least 2")
    if n < MIN_PER_PATCH * wanted:
        raise PerscliError(f"only {n} objects for {wanted} jackknife patches (at least {MIN_PER_PATCH} per patch "
                           f"needed): use --npatch {max(2, n // MIN_PER_PATCH)} or fewer"
                           if n >= 2 * MIN_PER_PATCH else
                           f"only {n} objects: too few for a jackknife over patches "
                           f"(at least {2 * MIN_PER_PATCH} needed)")
    logger = _treecorr_logger()
    nthreads = threads(workers)
    treecorr.set_omp_threads(nthreads, logger=logger)
    if sc.coords == "radec":
        where = dict(ra=sc.pos1, dec=sc.pos2, ra_units="deg", dec_units="deg")
    else:
        where = dict(x=sc.pos1, y=sc.pos2, x_units=sc.pos_units, y_units=sc.pos_units)
    patches = dict(patch_centers=patch_centers) if patch_centers is not None else dict(npatch=npatch)
    try:
        cat = treecorr.Catalog(g1=sc.de1, g2=sc.de2, rng=np.random.default_rng(seed), logger=logger,
                               **where, **patches)
        gg = treecorr.GGCorrelation(min_sep=min_sep, max_sep=max_sep, nbins=nbins, sep_units=sep_units,
                                    bin_slop=bin_slop, var_method="jackknife",
                                    cross_patch_weight=cross_patch_weight, logger=logger)
        gg.process(cat, num_threads=nthreads)
        gg.cov  # computed here so that a TreeCorr failure is reported as one
    except (ValueError, RuntimeError) as exc:
        raise PerscliError(f"TreeCorr failed on {n} objects: {exc}") from None
    used = int(np.count_nonzero(np.bincount(cat.patch, minlength=wanted)))
    if used < wanted:
        log.warning("%d of %d patches hold no object: the jackknife uses %d", wanted - used, wanted, used)
    if np.any(gg.npairs == 0):
        log.warning("%d of %d separation bins hold no pair: widen the range or use fewer bins",
                    int(np.sum(gg.npairs == 0)), nbins)
    return gg, cat


# ------------------------------------------------------------------------------------------------
# output
# ------------------------------------------------------------------------------------------------

XI_COLUMNS = ("r_nom", "meanr", "meanlogr", "xip", "xim", "xip_im", "xim_im", "sigma_xip", "sigma_xim",
              "weight", "npairs")


def xi_table(gg) -> dict:
    """TreeCorr's output columns of a GGCorrelation (:data:`XI_COLUMNS`), by name."""
    return dict(zip(XI_COLUMNS, (gg.rnom, gg.meanr, gg.meanlogr, gg.xip, gg.xim, gg.xip_im, gg.xim_im,
                                 np.sqrt(gg.varxip), np.sqrt(gg.varxim), gg.weight, gg.npairs)))


def _table_hdu(columns: dict, name: str, units: dict | None = None):
    from ..io.fitsfile import table_hdu

    return table_hdu(columns, name, units=units)


def build_hdus(sc: ShapeChanges, gg, cat, stats: dict, hist: dict, theta: dict, *, settings: dict, seed: int,
               patch_source: str):
    """The output file: provenance, XI, COV, STATS, HIST_DE, THETA_DE and PATCHES."""
    import treecorr

    from ..io.fitsfile import OutHDU
    from ..io.output import add_provenance

    sep = settings["sep_units"]
    primary = OutHDU([])
    params = {"NOBJ": (len(sc), "objects correlated")}
    params.update(sc.params)
    params.update({
        "GFRAME": ("as given", "axes of De: as input (SHAPES g: pixel axes)"),
        "MINSEP": (settings["min_sep"], f"[{sep}] --min-sep"), "MAXSEP": (settings["max_sep"], f"[{sep}] --max-sep"),
        "NBINS": (settings["nbins"], "--nbins (log bins)"), "SEPUNIT": (sep, "--sep-units"),
        "BINSLOP": (float(gg.bin_slop), "TreeCorr bin_slop used"),
        "VARMETH": ("jackknife", "covariance of xi"), "NPATCH": (int(cat.npatch), "jackknife patches"),
        "PATCHSRC": (patch_source[:68], "k-means, or the --patch-centers file"),
        "CPW": (settings["cross_patch_weight"], "TreeCorr cross_patch_weight"),
        "NBOOT": (settings["nboot"], "bootstrap resamples of THETA_DE"),
        "TREECORR": (treecorr.__version__, "TreeCorr version")})
    for k, t in enumerate(stats["threshold"], 1):
        params[f"THRESH{k}"] = (float(t), "|De| threshold of STATS frac_ge")
    header = add_provenance(primary.header, step=f"correlate {sc.source}", params=params, inputs=sc.inputs,
                            seed=seed)
    header.add_comment("De is correlated in the axes it is given in (SHAPES g: the frame's")
    header.add_comment("pixel axes). xi+ is unchanged by a rotation of those axes common to the")
    header.add_comment("catalogue; xi- is not (it mixes with xim_im).")

    xi = _table_hdu(xi_table(gg), "XI", units={"r_nom": sep, "meanr": sep, "meanlogr": f"log({sep})"})
    xh = xi.header
    xh["SEP_UNIT"] = (sep, "units of r_nom and meanr")
    xh["COORDS"] = (sc.coords, "radec (spherical) or xy (flat)")
    xh["MIN_SEP"] = (settings["min_sep"], f"[{sep}]")
    xh["MAX_SEP"] = (settings["max_sep"], f"[{sep}]")
    xh["NBINS"] = settings["nbins"]
    xh["BIN_SIZE"] = (float(gg.bin_size), "ln(max_sep/min_sep)/nbins")
    xh["BIN_SLOP"] = float(gg.bin_slop)
    xh["VAR_METH"] = "jackknife"
    xh["NPATCH"] = int(cat.npatch)
    xh["NOBJ"] = len(sc)

    cov = OutHDU([], np.asarray(gg.cov, dtype=np.float64), extname="COV")
    cov.header["ORDER"] = ("xip,xim", "rows/columns: xi+ of every bin, then xi-")
    cov.header["NBINS"] = settings["nbins"]
    cov.header["VAR_METH"] = "jackknife"
    cov.header["NPATCH"] = int(cat.npatch)

    scols = {"n": np.array([stats["n"]])}
    for key in ("e1_mean", "e1_err", "e2_mean", "e2_err", "de1_mean", "de1_err", "de2_mean", "de2_err",
                "de_abs_mean", "de_abs_max"):
        scols[key] = np.array([stats[key]])
    scols["threshold"] = stats["threshold"][None, :]
    scols["n_ge"] = stats["n_ge"][None, :].astype(np.int64)
    scols["frac_ge"] = stats["frac_ge"][None, :]
    for key in ("rows_a", "rows_b", "matched", "flagged", "nonfinite"):
        scols[key] = np.array([sc.counts.get(key, 0)], dtype=np.int64)
    stats_hdu = _table_hdu(scols, "STATS")
    stats_hdu.header["COMMENT"] = "e1/e2: mean g of B (the reference frame); NaN when De was given as columns"
    stats_hdu.header["COMMENT"] = "errors: standard errors of the means; frac_ge: fraction with |De| >= threshold"

    hist_hdu = _table_hdu(hist, "HIST_DE")
    hist_hdu.header["COMMENT"] = "|De| histogram: log bins; first row [0, lo) underflow, last [hi, inf) overflow"

    tcols = {k: v for k, v in theta.items() if k != "ngroups"}
    theta_hdu = _table_hdu(tcols, "THETA_DE", units={"theta_lo": "deg", "theta_hi": "deg"})
    theta_hdu.header["NANGLE"] = (N_ANGLE, "position-angle bins per |De| bin")
    theta_hdu.header["NDOF"] = (N_ANGLE - 1, "degrees of freedom of chi2_uniform")
    theta_hdu.header["NBOOT"] = (settings["nboot"], "bootstrap resamples")
    for k, g in enumerate(theta["ngroups"], 1):
        theta_hdu.header[f"NGROUP{k}"] = (int(g), f"groups resampled in |De| bin {k}")
    theta_hdu.header["COMMENT"] = "frac: |De|-weighted fraction of the |De| bin with position angle in the bin;"
    theta_hdu.header["COMMENT"] = "angle 0.5 atan2(De2, De1) from axis 1 towards axis 2; uniform: 1/NANGLE"

    centers = np.asarray(cat.patch_centers, dtype=np.float64)
    pcols = {"patch": np.arange(len(centers), dtype=np.int64), "x": centers[:, 0], "y": centers[:, 1]}
    if centers.shape[1] == 3:
        pcols["z"] = centers[:, 2]
        pcols["ra"] = np.degrees(np.arctan2(centers[:, 1], centers[:, 0])) % 360.0
        pcols["dec"] = np.degrees(np.arcsin(np.clip(centers[:, 2] / np.linalg.norm(centers, axis=1), -1, 1)))
    pcols["nobj"] = np.bincount(cat.patch, minlength=len(centers)).astype(np.int64)
    patches = _table_hdu(pcols, "PATCHES", units={"ra": "deg", "dec": "deg"})
    patches.header["COMMENT"] = "TreeCorr's patch centres (x, y[, z]); reuse with --patch-centers THIS_FILE"
    return [primary, xi, cov, stats_hdu, hist_hdu, theta_hdu, patches]


def _png_targets(plot, plots_dir, overwrite):
    """{kind: path} of the figures to write, checked before any work."""
    targets = {}
    if plot is not None:
        if not plot.lower().endswith(".png"):
            raise PerscliError(f"--plot {plot}: needs a .png file name")
        targets["xi"] = plot
    if plots_dir is not None:
        if os.path.exists(plots_dir) and not os.path.isdir(plots_dir):
            raise PerscliError(f"--plots {plots_dir}: is a file, not a folder")
        parent = os.path.dirname(os.path.abspath(plots_dir))
        if not os.path.isdir(parent):
            raise PerscliError(f"--plots {plots_dir}: folder {parent} does not exist")
        for kind in ("xi", "hist_de", "bin_theta"):
            targets[f"dir:{kind}"] = os.path.join(plots_dir, f"{kind}.png")
    for path in targets.values():
        folder = os.path.dirname(os.path.abspath(path))
        if path == plot and not os.path.isdir(folder):
            raise PerscliError(f"{path}: folder {folder} does not exist; create it or choose another file")
        if os.path.exists(path) and not overwrite:
            raise PerscliError(f"{path}: already exists; use --overwrite to replace it")
    return targets


def correlate_files(catalogs, dest: str, *, frames=None, de_columns=None, common_ids=False, positions="auto",
                    pixel_scale=ROMAN_PIXEL_SCALE, min_sep=1.0, max_sep=100.0, nbins=20, sep_units="arcmin", bin_slop=None,
                    npatch=20, patch_centers=None, cross_patch_weight="match", thresholds=DEFAULT_THRESHOLDS,
                    theta_edges=DEFAULT_THETA_EDGES, nboot=200, seed=1, workers=1, plot=None, plots_dir=None,
                    overwrite=False, stdin=None) -> dict:
    """``perscli correlate`` as a function: xi+/- of De, its covariance and the De statistics.

    Writes ``dest`` (FITS; '-' for standard output) with the HDUs XI
    (TreeCorr's columns), COV (jackknife covariance, [xi+, xi-]), STATS,
    HIST_DE, THETA_DE and PATCHES, and optionally the figures: ``plot`` (xi
    alone) and ``plots_dir``/{xi,hist_de,bin_theta}.png.  Nothing is written
    unless everything succeeds.  Parameters: see :func:`load_shape_changes`,
    :func:`correlate_de`, :func:`de_statistics` and :func:`theta_distribution`.

    Returns
    -------
    dict
        n (objects), counts, stats, the xi table and the output paths.
    """
    from ..io.output import check_output, write_hdus

    thresholds = tuple(float(t) for t in thresholds)
    if not thresholds or any(not (t > 0 and math.isfinite(t)) for t in thresholds):
        raise PerscliError(f"--thresholds {thresholds}: need one or more positive numbers")
    theta_edges = tuple(float(t) for t in theta_edges)
    if len(theta_edges) < 2 or any(b <= a for a, b in zip(theta_edges[:-1], theta_edges[1:])) or theta_edges[0] < 0:
        raise PerscliError(f"--theta-bins {theta_edges}: need two or more increasing edges >= 0")
    if nboot < 2:
        raise PerscliError(f"--nboot {nboot}: need at least 2 resamples")
    if not 0 < min_sep < max_sep:
        raise PerscliError(f"--min-sep {min_sep} and --max-sep {max_sep}: need 0 < min-sep < max-sep")
    inputs = [*catalogs, patch_centers]
    check_output(dest, overwrite=overwrite, inputs=inputs)
    pngs = _png_targets(plot, plots_dir, overwrite)
    for path in pngs.values():
        if os.path.exists(path):
            check_output(path, overwrite=overwrite, inputs=inputs)
        if dest != "-" and os.path.abspath(path) == os.path.abspath(dest):
            raise PerscliError(f"{path}: a figure and the -o output name the same file: choose another name")

    sc = load_shape_changes(catalogs, frames=frames, de_columns=de_columns, common_ids=common_ids,
                            positions=positions, pixel_scale=pixel_scale, stdin=stdin)
    centers = read_patch_centers(patch_centers, sc.coords) if patch_centers is not None else None
    log.info("%s: %d objects (%d matched, %d flagged, %d not finite)", sc.source, len(sc), sc.counts["matched"],
             sc.counts["flagged"], sc.counts["nonfinite"])
    gg, cat = correlate_de(sc, min_sep=min_sep, max_sep=max_sep, nbins=nbins, sep_units=sep_units,
                           bin_slop=bin_slop, npatch=npatch, patch_centers=centers,
                           cross_patch_weight=cross_patch_weight, seed=seed, workers=workers)
    stats = de_statistics(sc.de1, sc.de2, e1=sc.e1, e2=sc.e2, thresholds=thresholds)
    hist = de_histogram(_abs(sc.de1, sc.de2))
    theta = theta_distribution(sc.de1, sc.de2, edges=theta_edges, nboot=nboot, seed=seed)
    settings = dict(min_sep=float(min_sep), max_sep=float(max_sep), nbins=int(nbins), sep_units=sep_units,
                    cross_patch_weight=cross_patch_weight, nboot=int(nboot))
    source = os.path.basename(patch_centers) if patch_centers is not None else f"kmeans npatch={npatch}"
    hdul = build_hdus(sc, gg, cat, stats, hist, theta, settings=settings, seed=seed, patch_source=source)
    xi = xi_table(gg)

    # figures first, into temporary files beside their targets, renamed once the FITS file is in place
    temps, made_dir = {}, None
    try:
        if pngs:
            from . import plots

            if plots_dir is not None and not os.path.isdir(plots_dir):
                os.mkdir(plots_dir)
                made_dir = plots_dir
            figures = {"xi": lambda p: plots.xi_figure(xi, p, sep_units=sep_units, title=sc.source),
                       "hist_de": lambda p: plots.hist_de_figure(hist, p, thresholds=thresholds, n=len(sc)),
                       "bin_theta": lambda p: plots.theta_figure(theta, p)}
            for key, path in pngs.items():
                fd, tmp = tempfile.mkstemp(prefix=f".{os.path.basename(path)}.", suffix=".png",
                                           dir=os.path.dirname(os.path.abspath(path)))
                os.close(fd)
                temps[tmp] = path
                figures[key.removeprefix("dir:")](tmp)
        write_hdus(hdul, dest, overwrite=overwrite)
        for tmp, path in temps.items():
            os.replace(tmp, path)
        temps.clear()
        made_dir = None
    finally:
        for tmp in temps:
            if os.path.exists(tmp):
                os.unlink(tmp)
        if made_dir is not None:
            os.rmdir(made_dir)
    return {"n": len(sc), "counts": sc.counts, "stats": stats, "xi": xi, "npatch": int(cat.npatch),
            "figures": list(pngs.values()), "source": sc.source}
