"""Many pairs of SHAPES tables (each final exposure against its reference) pooled into one catalogue.

:func:`read_pairs_file` reads a text file of pairs, :func:`load_pairs` reads
every pair with :func:`perscli.stats.shape_changes.load_shape_changes` and
concatenates their De into one :class:`~perscli.stats.shape_changes.ShapeChanges`
(with per-pair records for the PAIRS table), warning when pairs in pixel
axes do not share one orientation on the sky.

Pooling: every pair contributes one entry per object it measures, so an
object measured in several pairs (several final exposures of the same
galaxy) appears once per pair, at its ra/dec: xi+/- then counts the pairs
of entries, the statistics count entries, and the jackknife puts all of an
object's entries in the same patch.
"""

from __future__ import annotations

import logging
import math
import os
import shlex

import numpy as np

from .. import PerscliError
from ..instrument import ROMAN_PIXEL_SCALE
from .de_stats import _abs
from .shape_changes import NoObjects, ShapeChanges, load_shape_changes

log = logging.getLogger("perscli")

#: provenance keywords A001/B001 ... name the files of at most this many pairs (all are in PAIRS)
MAX_PAIR_KEYWORDS = 999


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
               stdin=None, columns=None, flagged="drop") -> ShapeChanges:
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
    flagged : {'drop', 'keep'}
        As for :func:`load_shape_changes`.

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
                                    pixel_scale=pixel_scale, stdin=stdin, orientation=many, columns=columns,
                                    flagged=flagged)
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
                        pairs=records, flags=concat("flags"), dabs=concat("dabs"))


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
