"""Shape changes De from one or two SHAPES tables: :class:`ShapeChanges` and :func:`load_shape_changes`.

The reading half of ``perscli correlate``: De = g(A) - g(B) of two
measurements of one catalogue (two tables, or two frames of one), matched by
id, unflagged and finite, or De read from named columns of one or more
tables; with the objects' positions (ra/dec or x/y), the counts of what was
dropped, and the provenance of the inputs.  :class:`NoObjects` is the error
of a pair without a single usable object.  The axes g is given in (pixel,
sky, as given) are read from the tables' headers; see the module docstring
of :mod:`perscli.stats.correlate` for what they mean for xi+/-.
"""

from __future__ import annotations

import contextlib
import dataclasses
import logging
import math
import os
from dataclasses import dataclass, field

import numpy as np

from .. import PerscliError
from ..instrument import ROMAN_PIXEL_SCALE
from ..io.tables import open_table
from ..scene import DEC_RANGE, RA_RANGE

log = logging.getLogger("perscli")

#: header keywords that say in which axes g is (values starting 'sky' or 'pix'), table HDU first
G_AXES_KEYWORDS = ("GAXES", "GFRAME")
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
    #: per object, the flags of its fits (A's and B's ORed; 0: both clean), when flagged objects are kept
    flags: np.ndarray | None = None

    def select(self, keep: np.ndarray, why: str = "") -> "ShapeChanges":
        """The objects ``keep`` marks (bool per object), every per-object array cut alike.

        ``why`` names the cut in the counts (``counts[why]``: the objects it left out).
        """
        keep = np.asarray(keep, dtype=bool)
        per = {}
        for f in dataclasses.fields(self):
            value = getattr(self, f.name)
            if isinstance(value, np.ndarray) and value.shape[:1] == keep.shape:
                per[f.name] = value[keep]
        counts = dict(self.counts)
        if why:
            counts[why] = int(len(keep) - keep.sum())
        counts["used"] = int(keep.sum())
        return dataclasses.replace(self, counts=counts, **per)

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
                       pixel_scale=ROMAN_PIXEL_SCALE, stdin=None, orientation=False, columns=None,
                       flagged="drop") -> ShapeChanges:
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

    flagged : {'drop', 'keep'}
        'drop': only objects with ``flags == 0`` (in both A and B, or in the
        one table when it has a flags column) are used; 'keep': every
        object, its flags (ORed) in :attr:`ShapeChanges.flags` (a study's
        sample counts every galaxy, as the paper's pipeline did).

    Only objects with finite values are used.

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
            parts = [_from_columns(t, de_columns, positions, pixel_scale, inputs, flagged) for t in tables]
            if len(parts) == 1:
                return parts[0]
            # many tables (a study's finals): listed with their DATASUMs in an INPUTS table, not as keywords
            records = [{"name": t.label, "datasum": int(t.datasum), "rows": p.counts["rows_a"],
                        "used": p.counts["used"]} for t, p in zip(tables, parts)]
            return _pool_columns(parts, [], records)
        return _from_frames(tables, frames, common_ids, positions, pixel_scale, inputs, orientation, flagged)


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
                        dabs=cat("dabs"), tables=records, flags=cat("flags"))


def _from_columns(table, de_columns, positions, pixel_scale, inputs, flagged="drop") -> ShapeChanges:
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
    nflagged = 0
    flags = table.column("flags", kind="integer") if "flags" in _names(table) else np.zeros(n, dtype=np.int64)
    if flagged == "drop":
        keep = flags == 0
        nflagged = n - int(keep.sum())
        if not keep.any():
            raise PerscliError(f"{table.label}: all {n} objects are flagged (flags != 0): nothing to correlate")
    what = f"{'unflagged ' if flagged == 'drop' else ''}objects of {table.label}"
    cols = {f"{table.label}: column '{c1}'": de1, f"{table.label}: column '{c2}'": de2,
            f"{table.label}: position column 1": pos1, f"{table.label}: position column 2": pos2}
    good = _finite_rows(cols, keep, what)
    names = _names(table)
    all_ids = table.column("id", kind="integer") if "id" in names else None
    # De = g(A) - g(B) with |g| < 1 each: |De| < 2 (and the optional columns within their own ranges)
    _refuse_beyond(table.label, f"|De| = |({c1}, {c2})|", np.hypot(de1, de2), 2.0, good, all_ids,
                   "De is a difference of two shapes with |g| < 1, so |De| < 2; check the --de1/--de2 columns")
    ids = all_ids[good] if all_ids is not None else None
    counts = {"rows_a": n, "rows_b": 0, "matched": n, "flagged": nflagged,
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
                        g_axes=_g_axes(table) or "as given", dabs=extra.get("dabs"),
                        flags=np.asarray(flags)[good].astype(np.int64))


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


def _from_frames(tables, frames, common_ids, positions, pixel_scale, inputs, orientation=False,
                 flagged="drop") -> ShapeChanges:
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
    both = a["flags"][ia] | b["flags"][ib]
    keep = both == 0 if flagged == "drop" else np.ones(len(common), dtype=bool)
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
    good = _finite_rows(cols, keep, "objects unflagged in both" if flagged == "drop" else "objects matched")
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
                        else None, flags=np.asarray(both)[good].astype(np.int64),
                        dabs=np.hypot(g1a[good], g2a[good]) - np.hypot(g1b[good], g2b[good]))
