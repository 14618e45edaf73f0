"""Shape changes De between two measurements: their correlation function and statistics.

The paper measures every galaxy twice, on an exposure with persistence (A)
and on the same exposure without it (B), and studies De = g(A) - g(B):

- the shear-shear correlation function xi+/- of De (TreeCorr's
  ``GGCorrelation``), with a jackknife covariance over k-means patches, or
  shot-noise errors when a jackknife is impossible (:func:`correlate_de`);
- N, the mean intrinsic ellipticity (the mean g of B), the mean De with its
  standard error, and the fraction of objects with |De| above thresholds
  (1e-8 and 1e-4 in the paper);
- the histogram of |De| (the paper's figure hist_de);
- the |De|-weighted distribution of the position angle of De in bins of
  |De|, with bootstrap errors, and a chi2 test against uniform whose
  variance is the one under the uniform hypothesis (the paper's figure
  bin_theta; :func:`theta_distribution`).

:func:`load_shape_changes` reads De from one or two SHAPES tables
(``perscli measure``), :func:`load_pairs` pools the De of many pairs (each
final exposure against its reference) into one catalogue,
:func:`de_statistics`, :func:`de_histogram`, :func:`theta_distribution` and
:func:`correlate_de` compute the pieces, and :func:`correlate_files` is
``perscli correlate`` as a function.

Pooling: every pair contributes one entry per object it measures, so an
object measured in several pairs (several final exposures of the same
galaxy) appears once per pair, at its ra/dec: xi+/- then counts the pairs
of entries, the statistics count entries, and the jackknife puts all of an
object's entries in the same patch.

Orientation: g in a SHAPES table is in the frame's pixel axes unless the
table's header says otherwise (GAXES or GFRAME = 'sky': a joint fit, one row
per galaxy, whose g is in sky axes); De is correlated in the axes it is
given in.  xi+ does not depend on those axes when one rotation takes them to
the local sky axes over the whole catalogue (one detector, one pointing): a
rotation by phi multiplies every De by exp(2i phi) and leaves De De*
unchanged.  If the pixel axes are also mirrored with respect to the sky, xi+
is unchanged in flat geometry and to within the parallel transport between
the two objects' local frames on the sky (well under 1 % at these
separations).  xi- does depend on the orientation: a rotation turns it into
xi- exp(4i phi), mixing its real and imaginary parts.  Catalogues that
combine detectors or pointings with different orientations need g in sky
axes (a joint fit), or De rotated to the sky first (given with --de1/--de2).
"""

from __future__ import annotations

import contextlib
import logging
import math
import os
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
#: the chi2 p-value of a |De| bin comes from the chi2 distribution when the expected (weighted)
#: count per angle bin, n_eff / nangle, is at least this (Pearson's rule of thumb); else from
#: NULL_DRAWS simulations under the uniform hypothesis (see :func:`theta_distribution`)
MIN_EXPECTED = 5.0
NULL_DRAWS = 2_000
#: above this many objects in a |De| bin the simulation would be slow: the chi2 distribution is used
MAX_NULL_OBJECTS = 200_000
SEP_UNITS = ("arcsec", "arcmin", "deg", "rad")
CROSS_PATCH_WEIGHTS = ("simple", "mean", "match")
#: covariance of xi: 'auto' is the jackknife when possible, else shot noise (with a warning)
VAR_METHODS = ("auto", "jackknife", "shot")
#: header keywords that say in which axes g is (values starting 'sky' or 'pix'), table HDU first
G_AXES_KEYWORDS = ("GAXES", "GFRAME")
#: provenance keywords A001/B001 ... name the files of at most this many pairs (all are in PAIRS)
MAX_PAIR_KEYWORDS = 999
#: TUNIT spellings of x/y columns in pixels, and of angles TreeCorr understands
_PIXEL_UNITS = {"", "pix", "pixel", "pixels", "px"}
_ANGLE_UNITS = {"arcsec": "arcsec", "arcmin": "arcmin", "deg": "deg", "degree": "deg", "degrees": "deg",
                "rad": "rad", "radian": "rad", "radians": "rad"}
WHAT = "SHAPES table"


class NoObjects(PerscliError):
    """Two measurements without a single object to correlate: an empty table, or every match flagged.

    Raised like any :class:`perscli.PerscliError`; :func:`load_pairs` catches
    it so that one empty pair among many is a warning, not the end of the run.

    Attributes
    ----------
    inputs : list of (str, str, int)
        The pair's (keyword stem, file name, DATASUM), for provenance.
    counts : dict
        Rows read and matched, as far as they were counted.
    """

    def __init__(self, message: str, *, inputs=(), counts=None):
        super().__init__(message)
        self.inputs = list(inputs)
        self.counts = dict(counts or {})


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
    g_axes : {'pixel', 'sky', 'as given'}
        Axes of g (hence of De): a SHAPES table's pixel axes unless its
        header says sky (:data:`G_AXES_KEYWORDS`); 'as given' for De columns
        whose table does not say.
    pair : ndarray of int or None
        Pooled pairs (:func:`load_pairs`): the pair (0-based) each object comes from.
    pairs : list of dict
        Pooled pairs: per pair a, b (paths), a_datasum, b_datasum, g_axes and
        its counts.
    orientation : (float, int) or None
        How B's pixel axes sit on the sky, when asked for and measurable:
        the angle of the x axis from east towards north (degrees) and the
        parity (+1, or -1 when the axes are mirrored with respect to east,
        north), fitted to the objects' x, y and ra, dec.
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
    g_axes: str = "as given"
    pair: np.ndarray | None = None
    pairs: list = field(default_factory=list)
    orientation: tuple | None = None
    #: Delta|e| = |g(A)| - |g(B)| per object, when the input gives it (a ``dabs`` column)
    dabs: np.ndarray | None = None
    #: tables with De columns pooled: per table its name, DATASUM, rows and objects used
    tables: list = field(default_factory=list)

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
        ra = table.column("ra").astype(np.float64)[rows]
        dec = table.column("dec").astype(np.float64)[rows]
        _check_sky(table, rows, ra, dec)
        return ra, dec, "radec", "deg", {"COORDS": ("radec", "positions: ra, dec (deg), spherical")}
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


def _check_sky(table, rows, ra, dec) -> None:
    """Refuse ra/dec that are numbers but no position on the sky (Dec 100, RA 1e6).

    TreeCorr takes any angle, so Dec 100 (the sphere folded over the pole)
    or RA 1e6 would be correlated as some other position without a word;
    the ranges are those of every perscli input (:data:`perscli.scene.RA_RANGE`,
    :data:`perscli.scene.DEC_RANGE`), refused, never wrapped.  NaN and
    infinite values are left to :func:`_finite_rows` (dropped with a
    warning, as for any column).
    """
    from ..scene import DEC_RANGE, RA_RANGE

    with np.errstate(invalid="ignore"):
        bad = np.isfinite(ra) & ~((ra >= RA_RANGE[0]) & (ra <= RA_RANGE[1]))
        bad |= np.isfinite(dec) & ~((dec >= DEC_RANGE[0]) & (dec <= DEC_RANGE[1]))
    if np.any(bad):
        i = int(np.flatnonzero(bad)[0])
        where = _row_name(table, rows[i])
        raise PerscliError(f"{table.label}: {int(bad.sum())} row(s) with RA outside [0, 360] or Dec outside "
                           f"[-90, 90] degrees (first: {where}, ra={ra[i]:g} dec={dec[i]:g}): not a position on "
                           "the sky; fix or drop those rows (or correlate x/y with --positions xy)")


def _row_name(table, row) -> str:
    """'id N' of a table row when the table has ids, else 'row N' (0-based)."""
    if "id" in _names(table):
        with contextlib.suppress(PerscliError):
            return f"id {int(table.column('id', kind='integer')[row])}"
    return f"row {int(row)}"


def _refuse_beyond(label: str, what: str, values, limit: float, keep, ids, hint: str) -> None:
    """Refuse when ``values`` (a magnitude: |g|, |De|) reach ``limit`` in a row that is used (``keep``).

    NaN never reaches it (non-finite rows are dropped with a warning by
    :func:`_finite_rows`, as before); an infinite value does.  Such a value
    is not a shape: correlated, |g| = 1e300 filled XI, COV and STATS with
    inf and NaN.  The limit itself is refused too: |g| = 1 is an ellipse of
    zero width, which perscli measure never leaves unflagged (flag 32).
    """
    with np.errstate(invalid="ignore"):
        bad = np.asarray(keep, dtype=bool) & (np.asarray(values) >= limit)
    if np.any(bad):
        i = int(np.flatnonzero(bad)[0])
        first = f"id {int(ids[i])}" if ids is not None else f"row {i}"
        raise PerscliError(f"{label}: {int(bad.sum())} unflagged row(s) with {what} >= {limit:g} (first: {first}, "
                           f"{what} = {float(np.asarray(values)[i]):g}): {hint}")


_G_HINT = ("a reduced shear has |g| < 1 (perscli measure flags a fit that reaches 1); the table is corrupt or "
           "its g columns are something else: fix, flag or drop those rows")


def _g_axes(table) -> str | None:
    """'sky' or 'pixel' when the table's header (or its file's primary header) says so, else None.

    ``perscli measure --joint`` fits all exposures of a galaxy together and
    gives g in sky axes, which it says in a header keyword; any table that
    names its axes with one of :data:`G_AXES_KEYWORDS` is read the same way.
    """
    headers = [table.header]
    # perscli measure writes its keywords into the primary header; a table made without an open
    # file behind it (no hdu.file) simply has none to look in
    with contextlib.suppress(AttributeError, IndexError, TypeError):
        if table.index != 0:
            headers.append(table.hdu.file.hdus[0].header)
    for header in headers:
        for key in G_AXES_KEYWORDS:
            if key in header:
                value = str(header[key]).strip().lower()
                if value.startswith("sky"):
                    return "sky"
                if value.startswith("pix"):
                    return "pixel"
    return None


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
                       pixel_scale=ROMAN_PIXEL_SCALE, stdin=None, orientation=False, columns=None) -> ShapeChanges:
    """De from one or two SHAPES tables.

    Parameters
    ----------
    catalogs : sequence of str
        One or two paths ('-' for standard input, at most once).  With two,
        De = g(first) - g(second), objects matched by id.  With
        ``de_columns``, any number of tables, pooled (e.g. the per-exposure
        shape changes of a study).
    frames : (int, int), optional
        Frame numbers (the ``frame`` column of ``perscli measure``) of A and
        B.  With one catalogue: both are taken from it (``perscli measure A B``
        writes A as frame 0 and B as frame 1).  With two: frame A of the first
        and frame B of the second (by default each must hold one frame).
    de_columns : (str, str), optional
        The columns holding De1 and De2 (tables with De).  Optional columns
        ``dabs`` (Delta|e|, |g(A)| - |g(B)|) and ``e1_true``/``e2_true`` (the
        intrinsic shapes) are read too when present.
    common_ids : bool
        Two measurements: correlate the ids both hold, instead of refusing
        tables whose ids differ.
    positions : {'auto', 'radec', 'xy'}
        ra/dec (degrees, spherical; 'auto' when present) or x/y (flat; in
        pixels times ``pixel_scale``, or in the angle unit of the column's
        TUNIT).  Taken from B (the reference frame) when there are two.
    pixel_scale : float
        Arcsec per pixel for x/y in pixels (Roman: 0.11).
    stdin : binary file, optional
        Stream read for '-' (default ``sys.stdin.buffer``).
    columns : dict, optional
        Column mapping {perscli name: table column} for tables written by
        another tool (:func:`perscli.io.tables.parse_column_mapping`).
    orientation : bool
        Two measurements with g in pixel axes: also fit how B's pixel axes
        sit on the sky (:attr:`ShapeChanges.orientation`), from x, y and
        ra, dec; for pooling pairs, whose De add up only if their axes agree.

    Only objects with ``flags == 0`` (in both A and B, or in the one table
    when it has a flags column) and finite values are used.

    Raises
    ------
    PerscliError
        Unreadable input, missing columns, ids that do not match, no overlap,
        every object flagged, a needed column without a finite value.
    """
    catalogs = list(catalogs)
    if not catalogs or (len(catalogs) > 2 and de_columns is None):
        raise PerscliError(f"give one or two SHAPES tables (or tables with De columns), not {len(catalogs)}")
    if catalogs.count("-") > 1:
        raise PerscliError("only one input can be standard input ('-')")
    if positions not in ("auto", "radec", "xy"):
        raise PerscliError(f"positions must be auto, radec or xy, not {positions!r}")
    if de_columns is not None and frames is not None:
        raise PerscliError("--de1/--de2 name the De columns of tables; they do not go with --frames")
    if len(catalogs) == 1 and de_columns is None and frames is None:
        raise PerscliError(f"{catalogs[0]}: one SHAPES table needs --frames A B (two frames of it) or "
                           "--de1 COL --de2 COL (its De columns)")
    with contextlib.ExitStack() as stack:
        tables = [stack.enter_context(open_table(name, what=WHAT, stdin=stdin, columns=columns or {}))
                  for name in catalogs]
        inputs = [(f"SHAPE{'AB'[k]}" if len(tables) == 2 else "SHAPES", t.name, t.datasum)
                  for k, t in enumerate(tables)]
        if de_columns is not None:
            parts = [_from_columns(t, de_columns, positions, pixel_scale, inputs) for t in tables]
            if len(parts) == 1:
                return parts[0]
            # many tables (a study's finals): listed with their DATASUMs in an INPUTS table, not as keywords
            records = [{"name": t.label, "datasum": int(t.datasum), "rows": p.counts["rows_a"],
                        "used": p.counts["used"]} for t, p in zip(tables, parts)]
            return _pool_columns(parts, [], records)
        return _from_frames(tables, frames, common_ids, positions, pixel_scale, inputs, orientation)


def _pool_columns(parts, inputs, records) -> ShapeChanges:
    """Shape changes read from several tables with De columns, as one catalogue."""
    coords = {p.coords for p in parts}
    axes = {p.g_axes for p in parts}
    if len(coords) > 1 or len(axes) > 1:
        raise PerscliError("tables with De columns pooled together must all give ra/dec or all x/y, and De in the "
                           f"same axes (here: {', '.join(sorted(coords | axes))})")

    def cat(key):
        values = [getattr(p, key) for p in parts]
        return None if any(v is None for v in values) else np.concatenate(values)

    counts = {k: sum(p.counts.get(k, 0) for p in parts) for k in parts[0].counts}
    return ShapeChanges(de1=cat("de1"), de2=cat("de2"), e1=cat("e1"), e2=cat("e2"), pos1=cat("pos1"),
                        pos2=cat("pos2"), coords=parts[0].coords, pos_units=parts[0].pos_units, ids=cat("ids"),
                        counts=counts, inputs=inputs, params=parts[0].params,
                        source=f"De columns of {len(parts)} tables pooled", g_axes=parts[0].g_axes,
                        dabs=cat("dabs"), tables=records)


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
    names = _names(table)
    all_ids = table.column("id", kind="integer") if "id" in names else None
    # De = g(A) - g(B) with |g| < 1 each: |De| < 2 (and the optional columns within their own ranges)
    _refuse_beyond(table.label, f"|De| = |({c1}, {c2})|", np.hypot(de1, de2), 2.0, good, all_ids,
                   "De is a difference of two shapes with |g| < 1, so |De| < 2; check the --de1/--de2 columns")
    ids = all_ids[good] if all_ids is not None else None
    counts = {"rows_a": n, "rows_b": 0, "matched": n, "flagged": flagged,
              "nonfinite": int(keep.sum() - good.sum()), "used": int(good.sum())}
    params = {"DEMODE": ("columns", "De read from named columns"), "DE1COL": (c1, "column of De1"),
              "DE2COL": (c2, "column of De2"), **pparams}
    extra = {}
    for key, col in (("dabs", "dabs"), ("e1", "e1_true"), ("e2", "e2_true")):
        if col in names:
            extra[key] = table.column(names[col]).astype(np.float64)
    if "dabs" in extra:
        _refuse_beyond(table.label, "|dabs|", np.abs(extra["dabs"]), 1.0, good, all_ids,
                       "dabs = |g(A)| - |g(B)| lies in (-1, 1); check the column")
    if "e1" in extra and "e2" in extra:
        _refuse_beyond(table.label, "|(e1_true, e2_true)|", np.hypot(extra["e1"], extra["e2"]), 1.0, good,
                       all_ids, _G_HINT)
    extra = {key: values[good] for key, values in extra.items()}
    return ShapeChanges(de1=de1[good], de2=de2[good], e1=extra.get("e1"), e2=extra.get("e2"), pos1=pos1[good],
                        pos2=pos2[good], coords=coords, pos_units=units, ids=ids, counts=counts, inputs=inputs,
                        params=params, source=f"De = ({c1}, {c2}) of {os.path.basename(table.label)}",
                        g_axes=_g_axes(table) or "as given", dabs=extra.get("dabs"))


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


def _orientation(table, rows):
    """(angle of the x axis from east towards north in degrees, parity) of a table's pixel axes, or None.

    A least-squares affine fit of the local sky offsets (east, north) to
    (x, y) over at most 10,000 of ``rows``: one detector's WCS is affine to
    far better than the degree that matters here.  None when the table has
    no x, y, ra, dec or the fit is degenerate (objects on a line).
    """
    names = _names(table)
    if not {"x", "y", "ra", "dec"} <= set(names) or len(rows) < 3:
        return None
    pick = rows[np.linspace(0, len(rows) - 1, min(len(rows), 10_000)).astype(np.intp)]
    x, y = (table.column(k).astype(np.float64)[pick] for k in ("x", "y"))
    ra, dec = (table.column(k).astype(np.float64)[pick] for k in ("ra", "dec"))
    ok = np.isfinite(x) & np.isfinite(y) & np.isfinite(ra) & np.isfinite(dec)
    if ok.sum() < 3:
        return None
    x, y, ra, dec = x[ok], y[ok], ra[ok], dec[ok]
    dec0 = float(np.mean(dec))
    # wrap RA offsets into (-180, 180] so that a field across RA = 0 stays contiguous
    east = ((ra - ra[0] + 180.0) % 360.0 - 180.0) * math.cos(math.radians(dec0))
    north = dec - dec0
    design = np.column_stack([x - x.mean(), y - y.mean(), np.ones_like(x)])
    coef, _, rank, _ = np.linalg.lstsq(design, np.column_stack([east, north]), rcond=None)
    if rank < 3:
        return None
    jac = coef[:2].T                        # [[d east/dx, d east/dy], [d north/dx, d north/dy]]
    det = float(np.linalg.det(jac))
    if not np.isfinite(det) or det == 0:
        return None
    return float(np.degrees(np.arctan2(jac[1, 0], jac[0, 0]))), (1 if det > 0 else -1)


def _from_frames(tables, frames, common_ids, positions, pixel_scale, inputs, orientation=False) -> ShapeChanges:
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
    # a table that does not say is perscli measure's per-frame output: g in pixel axes
    axes_a, axes_b = _g_axes(ta) or "pixel", _g_axes(tb) or "pixel"
    if axes_a != axes_b:
        raise PerscliError(f"{label_a} gives g in {axes_a} axes and {label_b} in {axes_b} axes "
                           f"({'/'.join(G_AXES_KEYWORDS)} in their headers): De = g(A) - g(B) needs both in the "
                           "same axes; measure A and B the same way (both joint, or both per frame)")
    a, b = _side(ta, rows_a, label_a), _side(tb, rows_b, label_b)
    if len(a["id"]) == 0 or len(b["id"]) == 0:
        empty = label_a if len(a["id"]) == 0 else label_b
        raise NoObjects(f"{empty} has no rows: nothing to correlate", inputs=inputs,
                        counts={"rows_a": len(rows_a), "rows_b": len(rows_b)})
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
        raise NoObjects(f"all {len(common)} matched objects are flagged in {label_a} or {label_b} "
                        "(flags != 0): nothing to correlate", inputs=inputs,
                        counts={"rows_a": len(rows_a), "rows_b": len(rows_b), "matched": len(common),
                                "flagged": len(common)})
    pos1, pos2, coords, units, pparams = _positions(tb, rows_b[ib], positions, pixel_scale)
    if coords == "radec" and {"ra", "dec"} <= set(_names(ta)):
        # A's positions are not correlated (B's are), but Dec 100 in A is as corrupt as in B
        _check_sky(ta, rows_a[ia], ta.column("ra").astype(np.float64)[rows_a[ia]],
                   ta.column("dec").astype(np.float64)[rows_a[ia]])
    g1a, g2a, g1b, g2b = a["g1"][ia], a["g2"][ia], b["g1"][ib], b["g2"][ib]
    # |g| < 1 for any shape; hypot, not g1^2 + g2^2, so that 1e300 is refused without an overflow warning
    _refuse_beyond(label_a, "|g| = |(g1, g2)|", np.hypot(g1a, g2a), 1.0, keep, common, _G_HINT)
    _refuse_beyond(label_b, "|g| = |(g1, g2)|", np.hypot(g1b, g2b), 1.0, keep, common, _G_HINT)
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
                        counts=counts, inputs=inputs, params=params, source=f"De = g({label_a}) - g({label_b})",
                        g_axes=axes_a,
                        orientation=_orientation(tb, rows_b[ib][good]) if orientation and axes_a == "pixel"
                        else None)


# ------------------------------------------------------------------------------------------------
# many pairs pooled
# ------------------------------------------------------------------------------------------------

def read_pairs_file(path: str) -> list:
    """The pairs listed in a text file: one pair per line, A (with persistence) then B (reference).

    Names are separated by white space (quote a name that holds spaces);
    ``#`` starts a comment; blank lines are skipped.  A relative name is
    taken relative to the folder of the pairs file, so a study folder can be
    moved or read from anywhere.  CFITSIO's ``file.fits[EXT]`` works as on
    the command line.

    Returns
    -------
    list of (str, str)

    Raises
    ------
    PerscliError
        The file is missing, not text, a FITS file, has a line without
        exactly two names, or lists no pair.
    """
    import shlex

    if not os.path.isfile(path):
        raise PerscliError(f"{path}: no such file (--pairs: a text file with two SHAPES tables per line)")
    try:
        with open(path, "rb") as fh:
            raw = fh.read()
        if raw.startswith(b"SIMPLE  ="):
            raise PerscliError(f"{path}: is a FITS file, not a list of pairs: --pairs takes a text file with "
                               "'A.fits B.fits' per line (or give each pair with --pair A B)")
        text = raw.decode("utf-8")
    except (OSError, UnicodeDecodeError) as exc:
        raise PerscliError(f"{path}: cannot be read as a text file of pairs ({exc})") from None
    folder = os.path.dirname(path)
    pairs = []
    for number, line in enumerate(text.splitlines(), 1):
        try:
            names = shlex.split(line, comments=True)
        except ValueError as exc:
            raise PerscliError(f"{path}: line {number}: {exc}: quote names with spaces in matching quotes") from None
        if not names:
            continue
        if len(names) != 2:
            raise PerscliError(f"{path}: line {number} has {len(names)} name(s); each line holds one pair: "
                               "A.fits (with persistence) then B.fits (its reference)")
        pairs.append(tuple(n if n == "-" or os.path.isabs(n) else os.path.join(folder, n) for n in names))
    if not pairs:
        raise PerscliError(f"{path}: lists no pair (one 'A.fits B.fits' per line)")
    return pairs


def _check_pairs(pairs, frames) -> list:
    """``pairs`` as a list of (str, str), refused with one line when it cannot be what was meant."""
    if isinstance(pairs, (str, os.PathLike)):
        pairs = read_pairs_file(os.fspath(pairs))
    out = []
    for k, pair in enumerate(pairs, 1):
        try:
            if isinstance(pair, (str, bytes)):
                raise TypeError     # a string of two characters would otherwise unpack as a pair
            a, b = (os.fspath(x) for x in pair)
        except (TypeError, ValueError):
            raise PerscliError(f"pair {k}: {pair!r} is not two file names (A with persistence, B its "
                               "reference)") from None
        if a == b and frames is None:
            raise PerscliError(f"pair {k}: A and B are the same file ({a}): De would be zero; give the "
                               "measurement with persistence and its reference, or --frames A B for two frames "
                               "of one table")
        out.append((a, b))
    if not out:
        raise PerscliError("no pairs given: give at least one pair of SHAPES tables (A, B)")
    first = {}
    for k, pair in enumerate(out, 1):
        if pair in first:
            raise PerscliError(f"pair {k} repeats pair {first[pair]} ({pair[0]}, {pair[1]}): each pair counts "
                               "once; remove the repeat")
        first[pair] = k
    if sum(name == "-" for pair in out for name in pair) > 1:
        raise PerscliError("only one input can be standard input ('-')")
    return out


def load_pairs(pairs, *, frames=None, common_ids=False, positions="auto", pixel_scale=ROMAN_PIXEL_SCALE,
               stdin=None, columns=None) -> ShapeChanges:
    """The De of many pairs (each final exposure against its reference), pooled into one catalogue.

    Each pair gives De = g(A) - g(B) exactly as :func:`load_shape_changes`
    does for two tables (matched by id, unflagged in both, finite); the
    pairs' objects are then concatenated.  An object measured in several
    pairs appears once per pair, at its ra/dec: its entries are distinct
    measurements of De (different exposures), and TreeCorr counts every pair
    of entries (two entries of one object are at separation 0, below any
    min_sep, so never with each other).

    Parameters
    ----------
    pairs : sequence of (str, str), or str
        (A, B) paths per pair, or the path of a pairs file
        (:func:`read_pairs_file`).  The tables may be per-frame SHAPES
        tables (``perscli measure``) or joint fits (one row per galaxy, id,
        ra, dec, g1, g2, flags; the frame column is optional).
    frames : (int, int), optional
        Frame A of every A table and frame B of every B table (by default
        each table must hold one frame).
    common_ids : bool
        Within each pair, correlate the ids both hold instead of refusing
        tables whose ids differ.
    positions : {'auto', 'radec', 'xy'}
        With more than one pair, positions are ra/dec (x/y of different
        exposures are not one coordinate system): 'auto' or 'radec'.
    pixel_scale : float
        Arcsec per pixel for x/y (one pair with ``positions='xy'`` only).
    stdin : binary file, optional
        Stream read for a name '-' (at most one).
    columns : dict, optional
        Column mapping, as for :func:`load_shape_changes`.

    Returns
    -------
    ShapeChanges
        With ``pair`` (the pair of each object, 0-based) and ``pairs``
        (per-pair files, DATASUMs, axes and counts); ``counts`` summed over
        the pairs.

    Raises
    ------
    PerscliError
        Any pair that :func:`load_shape_changes` refuses (the message starts
        'pair K of N'), pairs mixing sky and pixel axes, x/y positions with
        several pairs, repeated pairs.  A pair without any usable object
        (a table without rows, every match flagged) is only a warning when
        there are several pairs: its row of ``pairs`` has used = 0.
    """
    pairs = _check_pairs(pairs, frames)
    many = len(pairs) > 1
    if many and positions == "xy":
        raise PerscliError(f"--positions xy with {len(pairs)} pairs: x/y of different exposures are not one "
                           "coordinate system; pooled pairs are placed by ra/dec (--positions radec or auto)")
    parts, empty = [], {}
    for k, (a, b) in enumerate(pairs):
        try:
            sc = load_shape_changes([a, b], frames=frames, common_ids=common_ids, positions=positions,
                                    pixel_scale=pixel_scale, stdin=stdin, orientation=many, columns=columns)
        except NoObjects as exc:
            if not many:
                raise PerscliError(f"pair 1 of 1: {exc}") from None
            # one exposure whose galaxies are all flagged (or a table without rows) is a fact of the
            # data, not a broken input: the other pairs still say what persistence does
            log.warning("pair %d of %d adds no object: %s", k + 1, len(pairs), exc)
            empty[k] = exc
            parts.append(None)
            continue
        except PerscliError as exc:
            raise PerscliError(f"pair {k + 1} of {len(pairs)}: {exc}") from None
        if many and sc.coords != "radec":
            raise PerscliError(f"pair {k + 1} of {len(pairs)}: {b} has no ra/dec columns: pooled pairs are placed "
                               "by ra/dec (degrees), as x/y of different exposures are not one coordinate system")
        parts.append(sc)
    used = [sc for sc in parts if sc is not None]
    if not used:
        raise PerscliError(f"none of the {len(pairs)} pairs has an object to correlate (pair 1: {empty[0]})")
    axes = {sc.g_axes for sc in used}
    if len(axes) > 1:
        sky = next(k for k, sc in enumerate(parts, 1) if sc is not None and sc.g_axes == "sky")
        pix = next(k for k, sc in enumerate(parts, 1) if sc is not None and sc.g_axes != "sky")
        raise PerscliError(f"pairs mix g in sky axes (e.g. pair {sky}) and in pixel axes (e.g. pair {pix}): their "
                           "De cannot be pooled; measure every pair the same way (all joint, or all per frame)")
    if many and axes == {"pixel"} and len(used) > 1:
        _warn_orientations(used)
    keys = ("rows_a", "rows_b", "matched", "flagged", "nonfinite", "used")
    records = []
    for k, ((a, b), sc) in enumerate(zip(pairs, parts)):
        if sc is None:
            exc = empty[k]
            sums = [int(item[2]) for item in exc.inputs] + [0, 0]
            records.append({"a": a, "b": b, "a_datasum": sums[0], "b_datasum": sums[1], "g_axes": "",
                            **{key: int(exc.counts.get(key, 0)) for key in keys},
                            "de1_mean": math.nan, "de2_mean": math.nan, "de_abs_mean": math.nan,
                            "de_abs_max": math.nan})
            continue
        absde = _abs(sc.de1, sc.de2)
        records.append({"a": a, "b": b, "a_datasum": int(sc.inputs[0][2]), "b_datasum": int(sc.inputs[1][2]),
                        "g_axes": sc.g_axes, **{key: int(sc.counts.get(key, 0)) for key in keys},
                        "de1_mean": float(np.mean(sc.de1)), "de2_mean": float(np.mean(sc.de2)),
                        "de_abs_mean": float(np.mean(absde)), "de_abs_max": float(np.max(absde))})
    counts = {key: int(sum(r[key] for r in records)) for key in keys}
    concat = lambda key: np.concatenate([getattr(sc, key) for sc in used])  # noqa: E731
    first = used[0]
    params = {"DEMODE": ("pairs", "De = g(A) - g(B) per pair, pooled"),
              "NPAIRS": (len(pairs), "pairs pooled (table PAIRS)")}
    if frames is not None:
        params["FRAMEA"] = (int(frames[0]), "frame of every A (with persistence)")
        params["FRAMEB"] = (int(frames[1]), "frame of every B (reference)")
    params["COMMONID"] = (bool(common_ids), "ids in only one of A, B allowed")
    for key in ("COORDS", "PIXSCALE"):
        if key in first.params:
            params[key] = first.params[key]
    if len(pairs) <= MAX_PAIR_KEYWORDS:
        inputs = [item for k, r in enumerate(records, 1)
                  for item in ((f"A{k:03d}", r["a"], r["a_datasum"]), (f"B{k:03d}", r["b"], r["b_datasum"]))]
    else:
        inputs = []     # thousands of keywords would swamp the header: the PAIRS table lists them all
    ids = concat("ids") if all(sc.ids is not None for sc in used) else None
    source = (f"De = g(A) - g(B) of {len(pairs)} pair{'s' if many else ''} pooled "
              f"({os.path.basename(pairs[0][0])} - {os.path.basename(pairs[0][1])}{', ...' if many else ''})")
    return ShapeChanges(de1=concat("de1"), de2=concat("de2"), e1=concat("e1"), e2=concat("e2"),
                        pos1=concat("pos1"), pos2=concat("pos2"), coords=first.coords, pos_units=first.pos_units,
                        ids=ids, counts=counts, inputs=inputs, params=params, source=source, g_axes=first.g_axes,
                        pair=np.repeat(np.arange(len(parts)), [len(sc) if sc is not None else 0 for sc in parts]),
                        pairs=records)


def _warn_orientations(parts) -> None:
    """Warn when pooled pairs in pixel axes do not share one orientation on the sky.

    De in pixel axes of two exposures rotated by dphi with respect to each
    other multiply, in xi+, by exp(2i dphi): the cross terms between the
    exposures are wrong unless dphi is ~0 (mod 180 degrees).  Below 2 degrees
    they lose less than 0.25 % (1 - cos 4 deg): no warning.
    """
    known = [(k, sc.orientation) for k, sc in enumerate(parts, 1) if sc.orientation is not None]
    if len(known) < len(parts):
        log.warning("g of the %d pooled pairs is in pixel axes, and the orientation of %d of them on the sky "
                    "cannot be fitted (no x, y, ra, dec): their De add up in xi+ only if all exposures share one "
                    "orientation; pool joint fits (g in sky axes) otherwise", len(parts), len(parts) - len(known))
        return
    ref_angle, ref_parity = known[0][1]
    # spin 2: a half turn leaves g unchanged, so angles compare modulo 180 degrees
    spread = max(abs((angle - ref_angle + 90.0) % 180.0 - 90.0) for _, (angle, _) in known)
    mirrored = [k for k, (_, parity) in known if parity != ref_parity]
    if mirrored or spread > 2.0:
        what = f"are mirrored with respect to pair 1 (pair {mirrored[0]})" if mirrored else \
            f"differ in orientation on the sky by up to {spread:.2g} deg"
        log.warning("the pixel axes of the %d pooled pairs %s: De in pixel axes of differently oriented exposures "
                    "do not add up in xi+ (cross terms turn by twice the angle) nor in xi-; pool joint fits "
                    "(g in sky axes) or De rotated to the sky", len(parts), what)


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


def de_statistics(de1, de2, *, e1=None, e2=None, thresholds=DEFAULT_THRESHOLDS, dabs=None) -> dict:
    """The paper's summary of De.

    Parameters
    ----------
    de1, de2 : ndarray
        Shape changes.
    e1, e2 : ndarray, optional
        Intrinsic shapes (g of the reference frame); NaN means when absent.
    thresholds : sequence of float
        |De| thresholds.
    dabs : ndarray, optional
        Delta|e| = |g(A)| - |g(B)| per object (the paper's text says both
        |De| and Delta|e|): then also n_dabs_ge and frac_dabs_ge, objects
        with |Delta|e|| >= threshold.

    Returns
    -------
    dict
        n; e1_mean, e1_err, e2_mean, e2_err (standard errors); de1_mean,
        de1_err, de2_mean, de2_err; de_abs_mean, de_abs_max; threshold,
        n_ge and frac_ge (arrays: objects with |De| >= threshold, and their
        fraction of n); with ``dabs``, n_dabs_ge and frac_dabs_ge.
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
    if dabs is not None:
        a = np.abs(np.asarray(dabs, dtype=np.float64))
        out["n_dabs_ge"] = np.array([np.count_nonzero(a >= t) for t in thresholds], dtype=np.int64)
        out["frac_dabs_ge"] = out["n_dabs_ge"] / n if n else np.full(len(thresholds), math.nan)
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
                       max_groups=MAX_BOOT_GROUPS, null_draws=NULL_DRAWS) -> dict:
    """|De|-weighted distribution of De's position angle in bins of |De|, and its test against uniform.

    In each |De| bin, ``frac[k]`` = sum of |De| over objects whose angle is
    in angle bin k / sum of |De| over the bin's objects (1/nangle each when
    the angle is uniform).

    Errors of the measured fractions (``frac_err``, drawn in the figure):
    standard deviation over ``nboot`` bootstrap resamples of the bin's
    objects.  When a bin holds more than ``max_groups`` objects, each object
    is first put into one of ``max_groups`` groups at random and the groups
    are resampled: for independent objects the group sums are independent
    too, so this has the same expected variance, at a cost O(nboot x
    max_groups) instead of O(nboot x n).

    The test against uniform uses the variance under the uniform hypothesis,
    not the bootstrap's (which is that of the observed fractions and would
    shrink with any excess).  Under the hypothesis the angles are
    independent of |De| and uniform, so given the weights w_i = |De_i| the
    indicator of object i in angle bin k is Bernoulli(p), p = 1/nangle, and
    ``frac[k] = sum_i w_i I_ik / W`` (W = sum w_i) has mean p and covariance
    ``(p delta_kl - p^2) / n_eff`` with ``n_eff = W^2 / sum w_i^2`` (Kish's
    effective number; n_eff = n for equal weights): the multinomial's, with
    n_eff in place of n.  ``frac_err_null`` is ``sqrt(p (1 - p) / n_eff)``
    and the chi2 is the Mahalanobis distance of frac from p in that
    (singular) covariance::

        chi2 = n_eff * sum_k (frac[k] - p)^2 / p,   nangle - 1 degrees of freedom

    (Pearson's statistic when the weights are equal).  Its p-value comes
    from the chi2 distribution when n_eff p >= :data:`MIN_EXPECTED` (the
    expected weighted count per angle bin); for fewer objects, where that
    approximation fails, from ``null_draws`` simulations of the statistic
    with the same weights and uniform angles (p = (1 + number of simulated
    chi2 >= the observed) / (1 + null_draws)).  Both assume independent
    objects: De of neighbours touched by one ghost, or of one object in
    several pooled pairs, are not, and then the test is too liberal.

    Returns
    -------
    dict
        Arrays with one entry per (|De| bin, angle bin): de_lo, de_hi, n
        (objects in the |De| bin), n_eff, theta_lo, theta_hi (degrees),
        frac, frac_err (bootstrap), frac_err_null (under uniform),
        chi2_uniform, dof_uniform and p_uniform (of the |De| bin; NaN when it
        is empty); and, per |De| bin, ``ngroups`` and ``p_method`` ('chi2' or
        'null-sim', '' when empty).
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
    # its own stream, so that the bootstrap draws do not depend on which bins were simulated
    null_rng = np.random.default_rng([int(seed), 2])
    width = 180.0 / nangle
    p0 = 1.0 / nangle
    keys = ("de_lo", "de_hi", "n", "n_eff", "theta_lo", "theta_hi", "frac", "frac_err", "frac_err_null",
            "chi2_uniform", "dof_uniform", "p_uniform")
    rows = {k: [] for k in keys}
    ngroups, methods = [], []
    for j, (lo, hi) in enumerate(zip(edges[:-1], edges[1:])):
        sel = debin == j
        n = int(np.count_nonzero(sel))
        frac = np.full(nangle, np.nan)
        err = np.full(nangle, np.nan)
        groups = min(n, max_groups)
        neff, chi2, pvalue, method = 0.0, math.nan, math.nan, ""
        if n:
            w, a = absde[sel], abin[sel]
            sums = np.bincount(a, weights=w, minlength=nangle)
            total = float(sums.sum())
            if total > 0:
                frac = sums / total
                neff = total ** 2 / float(np.dot(w, w))
                chi2 = float(neff * np.sum((frac - p0) ** 2) / p0)
                if neff * p0 >= MIN_EXPECTED or n > MAX_NULL_OBJECTS:
                    pvalue, method = chi2_sf(chi2, nangle - 1), "chi2"
                else:
                    pvalue, method = _null_pvalue(chi2, w, nangle, null_draws, null_rng), "null-sim"
                err = _bootstrap_errors(w, a, nangle, groups, nboot, rng)
        ngroups.append(groups)
        methods.append(method)
        rows["de_lo"].append(np.full(nangle, lo))
        rows["de_hi"].append(np.full(nangle, hi))
        rows["n"].append(np.full(nangle, n, dtype=np.int64))
        rows["n_eff"].append(np.full(nangle, neff))
        rows["theta_lo"].append(-90.0 + width * np.arange(nangle))
        rows["theta_hi"].append(-90.0 + width * np.arange(1, nangle + 1))
        rows["frac"].append(frac)
        rows["frac_err"].append(err)
        rows["frac_err_null"].append(np.full(nangle, math.sqrt(p0 * (1 - p0) / neff) if neff > 0 else np.nan))
        rows["chi2_uniform"].append(np.full(nangle, chi2))
        rows["dof_uniform"].append(np.full(nangle, nangle - 1, dtype=np.int64))
        rows["p_uniform"].append(np.full(nangle, pvalue))
    out = {k: np.concatenate(v) for k, v in rows.items()}
    out["ngroups"] = ngroups
    out["p_method"] = methods
    return out


def chi2_sf(x: float, dof: int) -> float:
    """P(X >= x) for X ~ chi2 with an integer number of degrees of freedom.

    Exact closed form, Q(dof/2, x/2) from Q(1/2, h) = erfc(sqrt(h)) or
    Q(1, h) = exp(-h) and Q(a + 1, h) = Q(a, h) + h^a exp(-h) / Gamma(a + 1):
    a sum of positive terms, so accurate to rounding; scipy.special would
    add ~0.1 s of import to every ``perscli correlate``.
    """
    if math.isnan(x):
        return math.nan
    if x <= 0:
        return 1.0
    h = 0.5 * x
    a, q = (0.5, math.erfc(math.sqrt(h))) if dof % 2 else (1.0, math.exp(-h))
    while a < 0.5 * dof - 1e-9:
        q += math.exp(a * math.log(h) - h - math.lgamma(a + 1))
        a += 1.0
    return min(q, 1.0)


def _bootstrap_errors(w, a, nangle, groups, nboot, rng) -> np.ndarray:
    """Standard deviation of the weighted angle fractions over bootstrap resamples of (groups of) objects."""
    n = len(w)
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
    return boot.std(axis=0, ddof=1) if len(boot) > 1 else np.full(nangle, np.nan)


def _null_pvalue(chi2: float, w: np.ndarray, nangle: int, draws: int, rng) -> float:
    """P(chi2 >= observed) under uniform angles with the same weights, by simulation."""
    n = len(w)
    total = float(w.sum())
    neff = total ** 2 / float(np.dot(w, w))
    p0 = 1.0 / nangle
    # chunks of at most ~4 million simulated angles keep memory flat for any n
    chunk = max(1, min(draws, 4_000_000 // max(n, 1)))
    hits = done = 0
    offsets = None
    while done < draws:
        m = min(chunk, draws - done)
        sim = rng.integers(0, nangle, size=(m, n), dtype=np.intp)
        if offsets is None or len(offsets) != m:
            offsets = (np.arange(m) * nangle)[:, None]
        sim += offsets
        sums = np.bincount(sim.ravel(), weights=np.broadcast_to(w, (m, n)).ravel(),
                           minlength=m * nangle).reshape(m, nangle)
        t = neff * np.sum((sums / total - p0) ** 2, axis=1) / p0
        # ties are common with few objects: count them as at least as extreme (rounding aside)
        hits += int(np.count_nonzero(t >= chi2 * (1 - 1e-9) - 1e-12))
        done += m
    return (1 + hits) / (1 + draws)


# ------------------------------------------------------------------------------------------------
# correlation
# ------------------------------------------------------------------------------------------------

def _treecorr_logger():
    """TreeCorr logs to stdout unless given a logger: send it to perscli's (stderr), quieter by one level."""
    logger = logging.getLogger("perscli.treecorr")
    logger.setLevel(logging.DEBUG if log.isEnabledFor(logging.DEBUG) else logging.WARNING)
    return logger


#: the largest text file of patch centres read (bytes): TreeCorr's text file of 10,000 centres is ~0.7 MB
MAX_PATCH_TEXT = 16 << 20

#: what --patch-centers takes, for messages
_PATCH_FILE = ("TreeCorr's write_patch_centers file, a table of ra/dec or an earlier perscli correlate output "
               "(--patch-centers)")


def check_patch_centers_file(path: str) -> None:
    """Refuse, before anything is read, a --patch-centers name that is not a regular file.

    The checks every input of perscli makes before reading it
    (:func:`perscli.io.fitsfile.open_source`), in one line each: missing, a
    broken or looping symbolic link, a directory, a device (/dev/null,
    /dev/zero: read for ever), a socket, an empty file.  A named pipe is
    refused too, without waiting for a writer: a patch-centre file may be
    FITS or text, which is told from its first bytes and then read again
    from the start, and a pipe cannot be read twice (give the file, or
    ``<(...)`` into a temporary file).

    Raises
    ------
    PerscliError
        One line naming the file and what to give instead.
    """
    import errno
    import stat

    try:
        st = os.stat(path)
    except FileNotFoundError:
        if os.path.islink(path):
            raise PerscliError(f"{path}: a broken symbolic link; point it at {_PATCH_FILE}") from None
        raise PerscliError(f"{path}: no such file; give {_PATCH_FILE}") from None
    except OSError as exc:
        if exc.errno == errno.ELOOP:
            raise PerscliError(f"{path}: a loop of symbolic links; point it at {_PATCH_FILE}") from None
        raise PerscliError(f"{path}: cannot be read ({exc.strerror}); give {_PATCH_FILE}") from None
    if stat.S_ISDIR(st.st_mode):
        raise PerscliError(f"{path}: is a directory, not a file of patch centres; give {_PATCH_FILE}")
    if stat.S_ISFIFO(st.st_mode):
        raise PerscliError(f"{path}: is a named pipe (FIFO), which cannot be read twice as a patch-centre file "
                           f"is; write it to a file first and give {_PATCH_FILE}")
    if not stat.S_ISREG(st.st_mode):
        raise PerscliError(f"{path}: is not a regular file (a device or socket); give {_PATCH_FILE}")
    if st.st_size == 0:
        raise PerscliError(f"{path}: the file is empty; give {_PATCH_FILE}")
    if not os.access(path, os.R_OK):
        raise PerscliError(f"{path}: cannot be read (permission denied); give {_PATCH_FILE}")


def read_patch_center_columns(path: str) -> dict:
    """The columns of a patch-centre file, by lower-case name (see :func:`read_patch_centers`).

    Checked as every input is (:func:`check_patch_centers_file`), then read
    as FITS (through :func:`perscli.io.fitsfile.open_fits`: structure and
    checksums verified) when it starts with a SIMPLE card (or is gzip
    compressed), else as a whitespace-separated text table with a header
    line of column names (at most :data:`MAX_PATCH_TEXT` bytes).

    Parameters
    ----------
    path : str
        The file (``--patch-centers``).

    Returns
    -------
    dict of str -> ndarray
        Every column of the table, as float64.

    Raises
    ------
    PerscliError
        Not a regular file, unreadable, no table, a text file too large to
        be one, or columns that are not numbers.
    """
    check_patch_centers_file(path)
    try:
        with open(path, "rb") as fh:
            head = fh.read(9)
        # FITS, plain or gzip-compressed (open_fits decompresses it): a text file starts otherwise
        is_fits = head == b"SIMPLE  =" or head[:2] == b"\x1f\x8b"
    except OSError as exc:
        raise PerscliError(f"{path}: cannot be read ({exc.strerror}); give {_PATCH_FILE}") from None
    if is_fits:
        from ..io.fitsfile import open_fits

        with open_fits(path) as fitsin:
            tables = [h for h in fitsin.hdus if h.kind == "table"]
            named = [h for h in tables if h.name == "PATCHES"]
            if not tables:
                raise PerscliError(f"{path}: has no binary table of patch centres (--patch-centers)")
            hdu = (named or tables)[0]
            try:
                return {n.lower(): np.asarray(hdu.read_column(n), dtype=np.float64) for n in hdu.colnames}
            except (TypeError, ValueError) as exc:
                raise PerscliError(f"{path}: not a readable FITS table of patch centres ({exc})") from None
    import io

    try:
        with open(path, "rb") as fh:
            # a text table of a few thousand centres is well under a megabyte: a file larger than the cap
            # (a disk image given by mistake, say) is refused instead of being read into memory
            raw = fh.read(MAX_PATCH_TEXT + 1)
        if len(raw) > MAX_PATCH_TEXT:
            raise PerscliError(f"{path}: over {MAX_PATCH_TEXT >> 20} MiB of text: not a file of patch centres; "
                               f"give {_PATCH_FILE}")
        text = raw.decode("utf-8")
    except OSError as exc:
        raise PerscliError(f"{path}: cannot be read ({exc.strerror}); give {_PATCH_FILE}") from None
    except UnicodeDecodeError:
        raise PerscliError(f"{path}: neither FITS nor text: not a file of patch centres; give {_PATCH_FILE}") \
            from None
    import warnings

    try:
        with warnings.catch_warnings():
            # numpy warns (and returns nothing) for a file without data lines: the check below says it
            warnings.simplefilter("ignore")
            arr = np.genfromtxt(io.StringIO(text), names=True, dtype=np.float64)
    except (OSError, ValueError) as exc:
        raise PerscliError(f"{path}: not a readable table of patch centres ({exc})") from None
    if arr.dtype.names is None:
        raise PerscliError(f"{path}: no column names: a patch-centre file has columns x y [z] or ra dec")
    return {n.lower(): np.atleast_1d(arr[n]) for n in arr.dtype.names}


def patch_center_vectors(data: dict, coords: str, path: str) -> np.ndarray:
    """Patch centres in TreeCorr's units from the columns of a patch-centre file (see :func:`read_patch_centers`).

    Parameters
    ----------
    data : dict of str -> ndarray
        The file's columns (:func:`read_patch_center_columns`).
    coords : {'radec', 'xy'}
        The positions the centres are for.
    path : str
        The file, for the messages.

    Returns
    -------
    ndarray
        (npatch, 3) unit vectors for 'radec', (npatch, 2) for 'xy'.

    Raises
    ------
    PerscliError
        Columns that do not fit ``coords``, fewer than 2 centres, values
        that are not finite, or ra/dec off the sky.
    """
    if coords == "radec":
        if {"x", "y", "z"} <= set(data):
            centers = np.column_stack([data["x"], data["y"], data["z"]])
        elif {"ra", "dec"} <= set(data):
            from ..scene import DEC_RANGE, RA_RANGE

            # the ranges of every position perscli reads: refused, never wrapped (Dec 100 would fold over the
            # pole into another centre without a word)
            with np.errstate(invalid="ignore"):
                off = (np.abs(data["dec"]) > DEC_RANGE[1]) | (data["ra"] < RA_RANGE[0]) | (data["ra"] > RA_RANGE[1])
            if np.any(off):
                raise PerscliError(f"{path}: {int(off.sum())} patch centre(s) with RA outside [0, 360] or Dec "
                                   "outside [-90, 90] degrees: not positions on the sky")
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


def read_patch_centers(path: str, coords: str) -> np.ndarray:
    """Patch centres from a file: TreeCorr's (x, y[, z]) columns or ra/dec in degrees.

    Accepts the file TreeCorr's ``Catalog.write_patch_centers`` writes (FITS
    or ASCII), a FITS table with ra/dec columns (degrees), or a
    ``perscli correlate`` output (its PATCHES table).  The name must be a
    regular file (:func:`check_patch_centers_file`).

    Returns
    -------
    ndarray
        (npatch, 3) unit vectors for coords 'radec'; (npatch, 2) for 'xy'
        (in TreeCorr's internal units, as TreeCorr writes them).

    Raises
    ------
    PerscliError
        See :func:`read_patch_center_columns` and :func:`patch_center_vectors`.
    """
    return patch_center_vectors(read_patch_center_columns(path), coords, path)


@dataclass
class Errors:
    """How the covariance of xi was estimated, and why.

    Attributes
    ----------
    method : {'jackknife', 'shot'}
        What TreeCorr's covariance is: the jackknife over patches, or shot
        noise (the variance of De over the pairs of each bin, every object
        independent: diagonal, and too small wherever De is spatially
        coherent).
    reason : str
        Why shot noise was used ('' for the jackknife).
    npatch : int
        Patches the jackknife used (0 for shot noise).
    asked : {'auto', 'jackknife', 'shot'}
        The ``var_method`` asked for.
    cov : ndarray or None
        The covariance written (xi+ bins, then xi- bins): TreeCorr's, with
        the rows and columns of ``shot_bins`` replaced by their shot noise.
    shot_bins : list of int
        Separation bins whose variance the jackknife could not estimate
        (zero to rounding, or not finite, though the bin has pairs: a bin
        with a pair or two at the edge of the range), given shot noise
        instead; empty when the whole covariance is one method.
    """

    method: str
    reason: str = ""
    npatch: int = 0
    asked: str = "auto"
    cov: np.ndarray | None = None
    shot_bins: list = field(default_factory=list)


def _too_few(n: int, wanted: int) -> tuple:
    """(why ``n`` objects cannot be cut into ``wanted`` jackknife patches, what would allow it or '')."""
    if n < 2 * MIN_PER_PATCH:
        return (f"only {n} object{'s' if n != 1 else ''}: too few for a jackknife over patches "
                f"(at least {2 * MIN_PER_PATCH} needed)"), ""
    return (f"only {n} objects for {wanted} jackknife patches (at least {MIN_PER_PATCH} per patch needed)",
            f"--npatch {max(2, n // MIN_PER_PATCH)} or fewer")


def correlate_de(sc: ShapeChanges, *, min_sep=1.0, max_sep=100.0, nbins=20, sep_units="arcmin", bin_slop=None,
                 npatch=20, patch_centers=None, cross_patch_weight="match", var_method="auto", seed=1, workers=1):
    """xi+/- of De with TreeCorr, and its covariance: the jackknife, or shot noise when that is impossible.

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
    var_method : {'auto', 'jackknife', 'shot'}
        'jackknife' insists on it (an error when impossible); 'shot' asks for
        TreeCorr's shot noise; 'auto' (default) is the jackknife unless it is
        impossible, then shot noise with a warning that says why: fewer than
        :data:`MIN_PER_PATCH` objects per patch (a CI-sized study of a few
        dozen galaxies), fewer than 2 patches holding objects, or TreeCorr's
        jackknife failing.  A separation bin whose jackknife variance is
        zero to rounding (below 1e-6 of its shot noise) or not finite,
        though it has pairs (a pair or two at the edge of the range: too
        few per patch), gets its shot noise instead, with a warning: a zero
        error would make any value there significant.  'jackknife' keeps it
        (with the warning).
    seed : int
        Seed of the k-means initialisation (same seed, same patches).
    workers : int
        TreeCorr's OpenMP threads (:func:`perscli.executor.threads`: 1 when
        not given, never all cores unasked).

    Returns
    -------
    (treecorr.GGCorrelation, treecorr.Catalog, Errors)
        The catalogue has patches only when the jackknife was used; the
        covariance to use is ``Errors.cov`` (it differs from ``gg.cov`` in
        ``Errors.shot_bins``).

    Raises
    ------
    PerscliError
        Bad settings, the jackknife asked for and impossible, or TreeCorr failing.
    """
    import treecorr

    if not 0 < min_sep < max_sep:
        raise PerscliError(f"--min-sep {min_sep} and --max-sep {max_sep}: need 0 < min-sep < max-sep")
    if sep_units not in SEP_UNITS:
        raise PerscliError(f"--sep-units {sep_units}: one of {', '.join(SEP_UNITS)}")
    if cross_patch_weight not in CROSS_PATCH_WEIGHTS:
        raise PerscliError(f"--cross-patch-weight {cross_patch_weight}: one of {', '.join(CROSS_PATCH_WEIGHTS)}")
    if var_method not in VAR_METHODS:
        raise PerscliError(f"--var-method {var_method}: one of {', '.join(VAR_METHODS)}")
    n = len(sc)
    if n == 0:
        raise PerscliError("no objects to correlate")
    wanted = len(patch_centers) if patch_centers is not None else npatch
    if var_method != "shot" and wanted < 2:
        raise PerscliError(f"{wanted} patch(es): the jackknife needs at least 2")
    logger = _treecorr_logger()
    nthreads = threads(workers)
    treecorr.set_omp_threads(nthreads, logger=logger)
    if sc.coords == "radec":
        where = dict(ra=sc.pos1, dec=sc.pos2, ra_units="deg", dec_units="deg")
    else:
        where = dict(x=sc.pos1, y=sc.pos2, x_units=sc.pos_units, y_units=sc.pos_units)
    binning = dict(min_sep=min_sep, max_sep=max_sep, nbins=nbins, sep_units=sep_units, bin_slop=bin_slop,
                   logger=logger)

    def run(method, patches):
        try:
            cat = treecorr.Catalog(g1=sc.de1, g2=sc.de2, rng=np.random.default_rng(seed), logger=logger,
                                   **where, **patches)
            extra = dict(cross_patch_weight=cross_patch_weight) if method == "jackknife" else {}
            gg = treecorr.GGCorrelation(var_method=method, **binning, **extra)
            gg.process(cat, num_threads=nthreads)
            gg.cov  # computed here so that a TreeCorr failure is reported as one
        except (ValueError, RuntimeError, ZeroDivisionError) as exc:
            raise PerscliError(f"TreeCorr failed on {n} objects ({method} errors): {exc}") from None
        return gg, cat

    errors = Errors("jackknife", npatch=wanted, asked=var_method)
    if var_method == "shot":
        errors = Errors("shot", reason="shot noise asked for (var_method 'shot')", asked=var_method)
    elif n < MIN_PER_PATCH * wanted:
        why, fix = _too_few(n, wanted)
        if var_method == "jackknife":
            raise PerscliError(f"{why}: use {fix}" if fix else why)
        errors = Errors("shot", reason=f"{why}; {fix} would allow one" if fix else why, asked=var_method)
    if errors.method == "jackknife":
        patches = dict(patch_centers=patch_centers) if patch_centers is not None else dict(npatch=npatch)
        try:
            gg, cat = run("jackknife", patches)
        except PerscliError as exc:
            if var_method == "jackknife":
                raise
            errors = Errors("shot", reason=f"the jackknife failed ({exc})", asked=var_method)
        else:
            used = int(np.count_nonzero(np.bincount(cat.patch, minlength=wanted)))
            errors.npatch = used
            if used < 2:
                if var_method == "jackknife":
                    raise PerscliError(f"only {used} of {wanted} patches hold objects: the jackknife needs 2")
                errors = Errors("shot", reason=f"only {used} of {wanted} patches hold objects (the jackknife "
                                "needs 2)", asked=var_method)
            else:
                if used < wanted:
                    log.warning("%d of %d patches hold no object: the jackknife uses %d", wanted - used, wanted,
                                used)
                errors.cov = np.array(gg.cov, dtype=np.float64)
                _repair_bins(gg, errors, float(cat.varg), sep_units, keep=var_method == "jackknife")
    if errors.method == "shot":
        if var_method == "auto":
            log.warning("shot-noise errors for xi instead of a jackknife: %s (shot noise counts every object as "
                        "independent: too small where De is spatially coherent)", errors.reason)
        gg, cat = run("shot", {})
        errors.cov = np.array(gg.cov, dtype=np.float64)
    if np.any(gg.npairs == 0):
        empty = int(np.sum(gg.npairs == 0))
        if empty < nbins:
            log.warning("%d of %d separation bins hold no pair: widen the range or use fewer bins", empty, nbins)
        else:
            log.warning("no separation bin holds a pair: no two of the %d object(s) are %g to %g %s apart", n,
                        min_sep, max_sep, sep_units)
    return gg, cat, errors


def _repair_bins(gg, errors: Errors, varg: float, sep_units: str, *, keep: bool) -> None:
    """Give shot noise to the bins whose jackknife variance is zero to rounding though they have pairs.

    A bin holding a pair or two (at the edge of the range) leaves every
    jackknife sample with the same value, or none: its jackknife variance
    comes out as 0 or ~1e-30 of its shot noise, and an error of zero would
    make any xi there significant.  Such a bin's rows and columns of
    ``errors.cov`` (xi+ and xi-) become its shot-noise variance, listed in
    ``errors.shot_bins``; with ``keep`` (the jackknife insisted on) they are
    only reported.  With De zero everywhere (varg 0) zero variances are right.
    """
    nb = len(gg.npairs)
    has_pairs = np.asarray(gg.npairs) > 0
    var = np.diagonal(errors.cov)
    shot = np.asarray(gg.estimate_cov("shot"), dtype=np.float64)
    with np.errstate(invalid="ignore"):
        bad = ~np.isfinite(var) | ((varg > 0) & (var < 1e-6 * shot))
    bins = np.flatnonzero(has_pairs & (bad[:nb] | bad[nb:]))
    if not len(bins):
        return
    seps = ", ".join(f"{gg.rnom[k]:.3g}" for k in bins[:4]) + (", ..." if len(bins) > 4 else "")
    what = (f"the jackknife variance is zero to rounding (or not finite) in {len(bins)} of "
            f"{int(has_pairs.sum())} bins with pairs (theta = {seps} {sep_units}: too few pairs per patch)")
    if keep:
        log.warning("jackknife asked for, kept although %s", what)
        return
    for k in bins:
        for i in (k, nb + k):
            errors.cov[i, :] = 0.0
            errors.cov[:, i] = 0.0
            errors.cov[i, i] = shot[i]
    errors.shot_bins = [int(k) for k in bins]
    log.warning("%s: shot noise there instead", what)


# ------------------------------------------------------------------------------------------------
# output
# ------------------------------------------------------------------------------------------------

XI_COLUMNS = ("r_nom", "meanr", "meanlogr", "xip", "xim", "xip_im", "xim_im", "sigma_xip", "sigma_xim",
              "weight", "npairs")


def xi_table(gg, cov=None) -> dict:
    """TreeCorr's output columns of a GGCorrelation (:data:`XI_COLUMNS`), by name.

    With ``cov`` (xi+ bins then xi- bins, e.g. :attr:`Errors.cov`) the
    errors are the square roots of its diagonal instead of TreeCorr's.
    """
    if cov is None:
        sigp, sigm = np.sqrt(gg.varxip), np.sqrt(gg.varxim)
    else:
        diag = np.sqrt(np.diagonal(cov))
        sigp, sigm = diag[:len(gg.xip)], diag[len(gg.xip):]
    return dict(zip(XI_COLUMNS, (gg.rnom, gg.meanr, gg.meanlogr, gg.xip, gg.xim, gg.xip_im, gg.xim_im,
                                 sigp, sigm, gg.weight, gg.npairs)))


def _comment(hdu, text: str) -> None:
    """COMMENT cards holding ``text``, wrapped at 72 characters (a card holds no more)."""
    import textwrap

    for line in textwrap.wrap(text, 72):
        hdu.header.add_comment(line)


def _table_hdu(columns: dict, name: str, units: dict | None = None):
    from ..io.fitsfile import table_hdu

    return table_hdu(columns, name, units=units)


_AXES_COMMENTS = {
    "pixel": "De is in the pixel axes of the frames measured. xi+ is unchanged by a rotation of those axes "
             "common to the catalogue; xi- is not (it mixes with xim_im).",
    "as given": "De is correlated in the axes it is given in. xi+ is unchanged by a rotation of those axes "
                "common to the catalogue; xi- is not (it mixes with xim_im).",
    "sky": "De is in sky axes (g of joint fits): xi+ and xi- are defined on the sky.",
}


def build_hdus(sc: ShapeChanges, gg, cat, stats: dict, hist: dict, theta: dict, *, settings: dict, seed: int,
               patch_source: str, errors: Errors | None = None):
    """The output file: provenance, XI, COV, STATS, HIST_DE, THETA_DE, PATCHES and, for pooled pairs, PAIRS."""
    import treecorr

    from ..io.fitsfile import OutHDU
    from ..io.output import add_provenance

    if errors is None:
        errors = Errors(str(gg.var_method), npatch=int(cat.npatch) if gg.var_method == "jackknife" else 0)
    jackknife = errors.method == "jackknife"
    sep = settings["sep_units"]
    primary = OutHDU([])
    params = {"NOBJ": (len(sc), "objects correlated (entries, pooled pairs)")}
    params.update(sc.params)
    if sc.ids is not None and sc.pair is not None:
        params["NIDS"] = (int(len(np.unique(sc.ids))), "distinct ids over the pooled pairs")
    params.update({
        "GFRAME": (sc.g_axes, "axes of De: pixel, sky or as given (De columns)"),
        "MINSEP": (settings["min_sep"], f"[{sep}] --min-sep"), "MAXSEP": (settings["max_sep"], f"[{sep}] --max-sep"),
        "NBINS": (settings["nbins"], "--nbins (log bins)"), "SEPUNIT": (sep, "--sep-units"),
        "BINSLOP": (float(gg.bin_slop), "TreeCorr bin_slop used"),
        "VARMETHD": (errors.method, "covariance of xi: jackknife or shot"),
        "VARASKED": (errors.asked, "--var-method asked for"),
        "NPATCH": (errors.npatch, "jackknife patches used (0: shot noise)")})
    if errors.reason:
        params["VARWHY"] = (errors.reason, "why shot noise")
    if errors.shot_bins:
        params["SHOTBINS"] = (",".join(str(k) for k in errors.shot_bins), "bins whose jackknife variance was 0")
    if jackknife:
        params["PATCHSRC"] = (patch_source[:68], "k-means, or the --patch-centers file")
        params["CPW"] = (settings["cross_patch_weight"], "TreeCorr cross_patch_weight")
    params.update({
        "NBOOT": (settings["nboot"], "bootstrap resamples of THETA_DE"),
        "TREECORR": (treecorr.__version__, "TreeCorr version")})
    for k, t in enumerate(stats["threshold"], 1):
        params[f"THRESH{k}"] = (float(t), "|De| threshold of STATS frac_ge")
    header = add_provenance(primary.header, step=f"correlate {sc.source}", params=params, inputs=sc.inputs,
                            seed=seed)
    if sc.pairs and not sc.inputs:
        header.add_history(f"  inputs: {len(sc.pairs)} pairs, listed with their DATASUMs in the PAIRS table")
    if sc.tables:
        header.add_history(f"  inputs: {len(sc.tables)} tables, listed with their DATASUMs in the INPUTS table")
    _comment(primary, _AXES_COMMENTS.get(sc.g_axes, _AXES_COMMENTS["as given"]))
    if not jackknife:
        _comment(primary, "Errors of xi are shot noise (VARWHY): every object independent, so too small where "
                          "De is spatially coherent; COV is diagonal.")
    elif errors.shot_bins:
        _comment(primary, "SHOTBINS: separation bins (0-based) with pairs whose jackknife variance was zero to "
                          "rounding (too few pairs per patch); their xi+ and xi- have shot-noise errors and no "
                          "covariance with other bins.")

    cov_matrix = errors.cov if errors.cov is not None else np.asarray(gg.cov, dtype=np.float64)
    xi = _table_hdu(xi_table(gg, cov_matrix), "XI", units={"r_nom": sep, "meanr": sep, "meanlogr": f"log({sep})"})
    xh = xi.header
    xh["SEP_UNIT"] = (sep, "units of r_nom and meanr")
    xh["COORDS"] = (sc.coords, "radec (spherical) or xy (flat)")
    xh["MIN_SEP"] = (settings["min_sep"], f"[{sep}]")
    xh["MAX_SEP"] = (settings["max_sep"], f"[{sep}]")
    xh["NBINS"] = settings["nbins"]
    xh["BIN_SIZE"] = (float(gg.bin_size), "ln(max_sep/min_sep)/nbins")
    xh["BIN_SLOP"] = float(gg.bin_slop)
    xh["VAR_METH"] = (errors.method, "sigma_xip, sigma_xim: jackknife or shot")
    xh["NPATCH"] = errors.npatch
    if errors.shot_bins:
        xh["SHOTBINS"] = (",".join(str(k) for k in errors.shot_bins), "rows with shot-noise errors")
    xh["NOBJ"] = len(sc)

    cov = OutHDU([], cov_matrix, extname="COV")
    cov.header["ORDER"] = ("xip,xim", "rows/columns: xi+ of every bin, then xi-")
    cov.header["NBINS"] = settings["nbins"]
    cov.header["VAR_METH"] = errors.method
    cov.header["NPATCH"] = errors.npatch
    if errors.shot_bins:
        cov.header["SHOTBINS"] = (",".join(str(k) for k in errors.shot_bins), "bins (xi+ and xi-) with shot noise")

    scols = {"n": np.array([stats["n"]])}
    for key in ("e1_mean", "e1_err", "e2_mean", "e2_err", "de1_mean", "de1_err", "de2_mean", "de2_err",
                "de_abs_mean", "de_abs_max"):
        scols[key] = np.array([stats[key]])
    scols["threshold"] = stats["threshold"][None, :]
    scols["n_ge"] = stats["n_ge"][None, :].astype(np.int64)
    scols["frac_ge"] = stats["frac_ge"][None, :]
    if "n_dabs_ge" in stats:
        scols["n_dabs_ge"] = stats["n_dabs_ge"][None, :].astype(np.int64)
        scols["frac_dabs_ge"] = stats["frac_dabs_ge"][None, :]
    for key in ("rows_a", "rows_b", "matched", "flagged", "nonfinite"):
        scols[key] = np.array([sc.counts.get(key, 0)], dtype=np.int64)
    stats_hdu = _table_hdu(scols, "STATS")
    _comment(stats_hdu, "e1/e2: mean g of B (the reference frame); NaN when De was given as columns. "
                        "errors: standard errors of the means; frac_ge: fraction with |De| >= threshold.")
    if sc.pairs:
        stats_hdu.header["NPAIRS"] = (len(sc.pairs), "pairs pooled: counts are sums over them")
        _comment(stats_hdu, "pooled pairs: an object measured in several pairs counts once per pair.")

    hist_hdu = _table_hdu(hist, "HIST_DE")
    _comment(hist_hdu, "|De| histogram: log bins; first row [0, lo) underflow, last [hi, inf) overflow.")

    tcols = {k: v for k, v in theta.items() if k not in ("ngroups", "p_method")}
    theta_hdu = _table_hdu(tcols, "THETA_DE", units={"theta_lo": "deg", "theta_hi": "deg"})
    th = theta_hdu.header
    th["NANGLE"] = (N_ANGLE, "position-angle bins per |De| bin")
    th["NDOF"] = (N_ANGLE - 1, "degrees of freedom of chi2_uniform")
    th["NBOOT"] = (settings["nboot"], "bootstrap resamples (frac_err)")
    th["NULLSIMS"] = (NULL_DRAWS, "simulations under uniform for p_uniform (null-sim)")
    th["MINEXPEC"] = (MIN_EXPECTED, "chi2 p-value when n_eff/NANGLE >= this")
    for k, (g, method) in enumerate(zip(theta["ngroups"], theta["p_method"]), 1):
        th[f"NGROUP{k}"] = (int(g), f"groups resampled in |De| bin {k}")
        th[f"PMETHOD{k}"] = (method or "none", f"p_uniform of |De| bin {k}: chi2 or null-sim")
    _comment(theta_hdu, "frac: |De|-weighted fraction of the |De| bin with position angle in the bin; angle "
                        "0.5 atan2(De2, De1) from axis 1 towards axis 2; uniform: 1/NANGLE. frac_err: bootstrap "
                        "error of frac. The test against uniform uses the variance under uniform angles: "
                        "frac_err_null = sqrt(p(1-p)/n_eff), p = 1/NANGLE, n_eff = (sum |De|)^2 / sum |De|^2; "
                        "chi2_uniform = n_eff sum (frac - p)^2 / p with dof_uniform = NANGLE - 1; p_uniform from "
                        "the chi2 distribution (PMETHODk = chi2) or, for few objects, from NULLSIMS simulations "
                        "with uniform angles (null-sim).")

    if jackknife:
        centers = np.asarray(cat.patch_centers, dtype=np.float64)
        counts = np.bincount(cat.patch, minlength=len(centers)).astype(np.int64)
    else:
        centers = np.zeros((0, 3 if sc.coords == "radec" else 2))
        counts = np.zeros(0, dtype=np.int64)
    pcols = {"patch": np.arange(len(centers), dtype=np.int64), "x": centers[:, 0], "y": centers[:, 1]}
    if centers.shape[1] == 3:
        pcols["z"] = centers[:, 2]
        with np.errstate(invalid="ignore", divide="ignore"):
            pcols["ra"] = np.degrees(np.arctan2(centers[:, 1], centers[:, 0])) % 360.0
            pcols["dec"] = np.degrees(np.arcsin(np.clip(centers[:, 2] / np.linalg.norm(centers, axis=1), -1, 1)))
    pcols["nobj"] = counts
    patches = _table_hdu(pcols, "PATCHES", units={"ra": "deg", "dec": "deg"})
    patches.header["NPATCH"] = (len(centers), "patches (0: shot-noise errors, no jackknife)")
    _comment(patches, "TreeCorr's patch centres (x, y[, z]); reuse with --patch-centers THIS_FILE.")
    hdus = [primary, xi, cov, stats_hdu, hist_hdu, theta_hdu, patches]
    if sc.pairs:
        hdus.append(_pairs_hdu(sc.pairs, sc.g_axes))
    if sc.tables:
        from ..io.fitsfile import table_hdu

        hdus.append(table_hdu({"name": np.array([os.path.basename(r["name"]) for r in sc.tables]),
                               "datasum": np.array([r["datasum"] for r in sc.tables], dtype=np.int64),
                               "rows": np.array([r["rows"] for r in sc.tables], dtype=np.int64),
                               "used": np.array([r["used"] for r in sc.tables], dtype=np.int64)}, "INPUTS",
                              descriptions={"name": "table pooled (file[EXT])", "used": "objects pooled from it"}))
    return hdus


def _pairs_hdu(records: list, g_axes: str):
    """PAIRS: one row per pooled pair, its files with their DATASUMs and what it contributed."""
    cols = {"pair": np.arange(1, len(records) + 1, dtype=np.int64),
            "a": np.array([os.path.basename(r["a"]) if r["a"] != "-" else "stdin" for r in records]),
            "b": np.array([os.path.basename(r["b"]) if r["b"] != "-" else "stdin" for r in records]),
            "a_datasum": np.array([r["a_datasum"] for r in records], dtype=np.int64),
            "b_datasum": np.array([r["b_datasum"] for r in records], dtype=np.int64)}
    for key in ("rows_a", "rows_b", "matched", "flagged", "nonfinite", "used"):
        cols[key] = np.array([r[key] for r in records], dtype=np.int64)
    for key in ("de1_mean", "de2_mean", "de_abs_mean", "de_abs_max"):
        cols[key] = np.array([r[key] for r in records], dtype=np.float64)
    descriptions = {"pair": "1-based, as listed", "a": "SHAPES table with persistence", "b": "reference",
                    "used": "objects pooled from this pair"}
    from ..io.fitsfile import table_hdu

    hdu = table_hdu(cols, "PAIRS", descriptions=descriptions)
    hdu.header["NPAIRS"] = (len(records), "pairs pooled")
    hdu.header["GFRAME"] = (g_axes, "axes of g in every pair")
    _comment(hdu, "used = 0: the pair had no usable object (a table without rows, or every match flagged); "
                  "its means are NaN.")
    return hdu


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


def correlate_files(catalogs, dest: str, *, pairs=None, frames=None, de_columns=None, common_ids=False,
                    positions="auto", pixel_scale=ROMAN_PIXEL_SCALE, min_sep=1.0, max_sep=100.0, nbins=20,
                    sep_units="arcmin", bin_slop=None, npatch=20, patch_centers=None, cross_patch_weight="match",
                    var_method="auto", thresholds=DEFAULT_THRESHOLDS, theta_edges=DEFAULT_THETA_EDGES, nboot=200,
                    seed=1, workers=1, plot=None, plots_dir=None, overwrite=False, stdin=None,
                    columns=None) -> dict:
    """``perscli correlate`` as a function: xi+/- of De, its covariance and the De statistics.

    Writes ``dest`` (FITS; '-' for standard output) with the HDUs XI
    (TreeCorr's columns), COV (covariance, [xi+, xi-]), STATS, HIST_DE,
    THETA_DE, PATCHES and, for pooled pairs, PAIRS; and optionally the
    figures: ``plot`` (xi alone) and ``plots_dir``/{xi,hist_de,bin_theta}.png.
    Nothing is written unless everything succeeds.

    Parameters
    ----------
    catalogs : sequence of str
        One or two SHAPES tables (:func:`load_shape_changes`); empty when
        ``pairs`` is given.
    dest : str
        Output path, '-' for standard output.
    pairs : sequence of (str, str), or str, optional
        Many pairs pooled into one catalogue (:func:`load_pairs`): (A, B)
        paths, or the path of a pairs file.  Not with ``catalogs`` or
        ``de_columns``.
    var_method : {'auto', 'jackknife', 'shot'}
        Covariance of xi (:func:`correlate_de`): 'auto' falls back to shot
        noise, with a warning, when a jackknife is impossible.
    frames, de_columns, common_ids, positions, pixel_scale, columns
        See :func:`load_shape_changes`.
    min_sep, max_sep, nbins, sep_units, bin_slop, npatch, patch_centers, cross_patch_weight, seed, workers
        See :func:`correlate_de` (``patch_centers`` is a file here).
    thresholds
        See :func:`de_statistics`.
    theta_edges, nboot
        See :func:`theta_distribution` (``edges``).
    plot, plots_dir, overwrite, stdin
        Figures, replacing existing outputs, the stream read for '-'.

    Returns
    -------
    dict
        n (objects; entries when pairs are pooled), npairs (0 without
        ``pairs``), counts, stats, the xi table, npatch, var_method and
        var_reason (why shot noise, '' for the jackknife), shot_bins
        (separation bins given shot noise inside a jackknife), theta (per
        |De| bin: de_lo, de_hi, n, n_eff, chi2, dof, p, p_method), figures
        and source.
    """
    from ..io.output import check_output, make_temp_file, write_hdus

    catalogs = list(catalogs or ())
    if pairs is not None:
        if catalogs:
            raise PerscliError("give SHAPES tables or pairs, not both")
        if de_columns is not None:
            raise PerscliError("--de1/--de2 name the De columns of one table; they do not go with pairs")
        pairs = _check_pairs(pairs, frames)
    if var_method not in VAR_METHODS:
        raise PerscliError(f"--var-method {var_method}: one of {', '.join(VAR_METHODS)}")
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
    inputs = [*catalogs, *(name for pair in (pairs or ()) for name in pair), patch_centers]
    check_output(dest, overwrite=overwrite, inputs=inputs)
    pngs = _png_targets(plot, plots_dir, overwrite)
    for path in pngs.values():
        if os.path.exists(path):
            check_output(path, overwrite=overwrite, inputs=inputs)
        if dest != "-" and os.path.abspath(path) == os.path.abspath(dest):
            raise PerscliError(f"{path}: a figure and the -o output name the same file: choose another name")

    # the patch centres are read first: a bad --patch-centers (a FIFO without a writer, /dev/zero, a folder)
    # is one line before any table is read, never a hang or a traceback after it
    centre_columns = read_patch_center_columns(patch_centers) if patch_centers is not None else None
    if pairs is not None:
        sc = load_pairs(pairs, frames=frames, common_ids=common_ids, positions=positions, pixel_scale=pixel_scale,
                        stdin=stdin, columns=columns)
    else:
        sc = load_shape_changes(catalogs, frames=frames, de_columns=de_columns, common_ids=common_ids,
                                positions=positions, pixel_scale=pixel_scale, stdin=stdin, columns=columns)
    centers = patch_center_vectors(centre_columns, sc.coords, patch_centers) if patch_centers is not None else None
    log.info("%s: %d objects (%d matched, %d flagged, %d not finite)", sc.source, len(sc), sc.counts["matched"],
             sc.counts["flagged"], sc.counts["nonfinite"])
    gg, cat, errors = correlate_de(sc, min_sep=min_sep, max_sep=max_sep, nbins=nbins, sep_units=sep_units,
                                   bin_slop=bin_slop, npatch=npatch, patch_centers=centers,
                                   cross_patch_weight=cross_patch_weight, var_method=var_method, seed=seed,
                                   workers=workers)
    stats = de_statistics(sc.de1, sc.de2, e1=sc.e1, e2=sc.e2, thresholds=thresholds, dabs=sc.dabs)
    hist = de_histogram(_abs(sc.de1, sc.de2))
    theta = theta_distribution(sc.de1, sc.de2, edges=theta_edges, nboot=nboot, seed=seed)
    settings = dict(min_sep=float(min_sep), max_sep=float(max_sep), nbins=int(nbins), sep_units=sep_units,
                    cross_patch_weight=cross_patch_weight, nboot=int(nboot))
    source = os.path.basename(patch_centers) if patch_centers is not None else f"kmeans npatch={npatch}"
    hdul = build_hdus(sc, gg, cat, stats, hist, theta, settings=settings, seed=seed, patch_source=source,
                      errors=errors)
    xi = xi_table(gg, errors.cov)

    # figures first, into temporary files beside their targets, renamed once the FITS file is in place
    temps, made_dir = {}, None
    try:
        if pngs:
            from . import plots

            if plots_dir is not None and not os.path.isdir(plots_dir):
                os.mkdir(plots_dir)
                made_dir = plots_dir
            errs = "jackknife errors" if errors.method == "jackknife" else "shot-noise errors"
            figures = {"xi": lambda p: plots.xi_figure(xi, p, sep_units=sep_units, title=sc.source, errors=errs),
                       "hist_de": lambda p: plots.hist_de_figure(hist, p, thresholds=thresholds, n=len(sc)),
                       "bin_theta": lambda p: plots.theta_figure(theta, p)}
            for key, path in pngs.items():
                # a new file's permissions (0666 less the umask), as for every output
                fd, tmp = make_temp_file(os.path.dirname(os.path.abspath(path)),
                                         prefix=f".{os.path.basename(path)}.", suffix=".png")
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
    return {"n": len(sc), "npairs": len(sc.pairs), "counts": sc.counts, "stats": stats, "xi": xi,
            "npatch": errors.npatch, "var_method": errors.method, "var_reason": errors.reason,
            "shot_bins": list(errors.shot_bins),
            "theta": theta_summary(theta), "figures": list(pngs.values()), "source": sc.source}


def theta_summary(theta: dict) -> list:
    """Per |De| bin of a :func:`theta_distribution`: de_lo, de_hi, n, n_eff, chi2, dof, p, p_method."""
    nangle = len(theta["p_method"]) and len(theta["de_lo"]) // len(theta["p_method"])
    out = []
    for k, method in enumerate(theta["p_method"]):
        i = k * nangle
        out.append({"de_lo": float(theta["de_lo"][i]), "de_hi": float(theta["de_hi"][i]), "n": int(theta["n"][i]),
                    "n_eff": float(theta["n_eff"][i]), "chi2": float(theta["chi2_uniform"][i]),
                    "dof": int(theta["dof_uniform"][i]), "p": float(theta["p_uniform"][i]), "p_method": method})
    return out
