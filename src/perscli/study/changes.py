"""Shape changes De measured only where the pixels changed: the differential study's measurement.

A final exposure rendered with and without persistence differs only where
persistence reached (:mod:`perscli.study.differential` writes the
reference's pixels around the galaxies that persistence could reach, and a
variant's only around those whose stamps it changed).  A fit depends on
nothing but its stamp's pixels and the catalogue (:mod:`.shapes`), so a
galaxy whose stamps are the same bits in both has the same fit in both: its
De is exactly 0 and it is not fitted.  The others are fitted twice, on the
reference and on the variant (the reference's pixels where the variant has
none), with the very code of ``perscli measure``.

The result (:func:`measure_changes`) has one row per galaxy of the sample:
every galaxy that ``perscli measure`` would fit (on a frame, predicted S/N
above the cut), fitted or not, so that statistics count all of them, as
the paper does ("all galaxies are used").
"""

from __future__ import annotations

import os

import numpy as np

from .. import PerscliError
from ..executor import run
from ..io.fitsfile import OutHDU, table_hdu
from ..io.frames import open_frame
from ..io.output import add_provenance, check_output, write_hdus
from ..io.tables import read_table
from ..measure.joint import ChangesContext, joint_setup, measure_joint_changes_object
from ..measure.perframe import Windows, frame_setup, measure_object_changes, stamp_window
from ..measure.response import CHANGE_METHODS
from ..measure.selection import read_positions
from ..measure.settings import MIN_SNR_DEFAULT, MeasureOptions
from ..scene import project, within
from .differential import read_stamps, stamp_windows, variant_extname

#: |De| of a galaxy fitted on both: De = g(variant) - g(reference); Delta|e| = |g(variant)| - |g(reference)|
COLUMNS = ("id", "ra", "dec", "expid", "g1", "g2", "g1_ref", "g2_ref", "de1", "de2", "dabs", "e1_true",
           "e2_true", "snr_pred", "fitted", "flags", "method", "bound")
#: with a check of the linear response (``cold``): De of the variant fitted from the start too
COLD_COLUMNS = ("de1_cold", "de2_cold")


def _truth_shapes(catalog: str, n: int):
    table = read_table(catalog, what="truth catalogue")
    names = {c.lower(): c for c in table.names}
    if "e1" in names and "e2" in names:
        return table.column("e1").astype(np.float64), table.column("e2").astype(np.float64)
    return np.full(n, np.nan), np.full(n, np.nan)


_CATALOGUES: dict = {}


def _catalogue(path: str):
    """The catalogue's positions and true shapes, read once per process and file (a study's finals share it)."""
    st = os.stat(path)
    key = (os.path.realpath(path), st.st_size, st.st_mtime_ns)
    if key not in _CATALOGUES:
        _CATALOGUES.clear()
        cat = read_positions(path)
        _CATALOGUES[key] = (cat, *_truth_shapes(path, len(cat["id"])))
    return _CATALOGUES[key]


#: what the study measures with unless told: one fit per galaxy over all its finals (the paper's pipeline)
CHANGES_OPTIONS = MeasureOptions(joint=True)


def measure_changes(finals, variants, catalog: str, *, options: MeasureOptions = CHANGES_OPTIONS, expids=None,
                    part=None, field=None, workers: int = 1, pixels=None, cold: bool = False) -> dict:
    """De of every galaxy of the sample between each variant and the reference, fitting only those that changed.

    Each galaxy whose stamps any variant changed is fitted once on the
    reference, and each variant that changed it from the reference's minimum
    (:func:`perscli.measure.response.fit_changes`: the linear response of the fit
    to the pixel change, checked by a Newton evaluation on the changed data,
    warm Newton steps or a fit from the start where it is not enough).  A
    galaxy whose stamps a variant left as they were has De = 0 exactly.

    Parameters
    ----------
    finals : sequence of str
        The finals' files (:func:`perscli.study.differential.render_final`):
        SCI (the reference), one HDU per variant, MODEL and CHANGED.
    variants : str or sequence of str
        Which variants (e.g. 'drawn-typical').
    catalog : str
        The truth catalogue.
    options : MeasureOptions
        How to measure, as for ``perscli measure``: ``joint`` (one fit per
        galaxy over all its finals, the paper's pipeline, the default here;
        or one per galaxy and final), ``stamp`` and ``min_snr`` are used.
    expids : sequence of int, optional
        Per final, its exposure id (the ``expid`` column of per-final rows).
    pixels : sequence of dict, optional
        Per final, its images and CHANGED table already in memory
        (:func:`perscli.study.differential.render_final`'s ``pixels``): the
        files then give only their headers.
    part : dict, optional
        Only the galaxies of a strip of the sky: ``ra0``, ``dec0`` (the
        tangent point, degrees), ``xi_lo``, ``xi_hi`` (standard coordinates,
        radians; None: open) of their catalogue positions (a study spreads
        its galaxies over strips, :func:`perscli.study.plan.measure_strips`).
    field : dict, optional
        Only the galaxies within ``radius`` degrees of (``ra``, ``dec``): the
        study's sample.
    workers : int
    cold : bool
        Also fit every changed variant from the start, as a fit of its data
        alone would be (columns :data:`COLD_COLUMNS`): the check of the
        linear response.

    Returns
    -------
    dict
        Variant -> column arrays (:data:`COLUMNS`), one row per galaxy of the
        sample (per galaxy and final without ``joint``), with '_counts': the
        sample, the galaxies fitted and those flagged, and the methods used.
    """
    finals = list(finals)
    variants = [variants] if isinstance(variants, str) else list(variants)
    cat, e1_true, e2_true = _catalogue(catalog)
    subset = _sample(cat, part, field)
    changed, stored = _changed_rows(finals, variants, cat, subset, pixels)
    opts = MeasureOptions(stamp=options.stamp, min_snr=options.min_snr)
    parts = {v: [] for v in variants}
    if options.joint:
        refs = [f"{p}[SCI]" for p in finals]
        per_variant = [np.logical_or.reduce(changed[v]) if finals else np.zeros(len(cat["id"]), dtype=bool)
                       for v in variants]
        ref, var = _joint_changes(refs, variants, cat, per_variant, opts, workers=workers, cold=cold,
                                  pixels=pixels, stored=stored, within=subset)
        for v in variants:
            parts[v].append(_assemble(cat, ref, var[v], subset, -1, e1_true, e2_true))
    else:
        for k, path in enumerate(finals):
            expid = int(expids[k]) if expids is not None else k
            ref, var = _final_changes(path, pixels[k] if pixels is not None else None, variants, cat,
                                      [changed[v][k] for v in variants], opts, workers=workers, cold=cold)
            for v in variants:
                parts[v].append(_assemble(cat, ref, var[v], subset, expid, e1_true, e2_true))
    return {v: _variant_columns(parts[v], cold) for v in variants}


def _sample(cat, part, field) -> np.ndarray:
    """Per catalogue row: in the strip ``part`` and within ``field`` (:func:`measure_changes`)."""
    subset = np.ones(len(cat["id"]), dtype=bool)
    if part is not None:
        xi, _ = project(part["ra0"], part["dec0"], cat["ra"], cat["dec"])
        if part.get("xi_lo") is not None:
            subset &= xi >= part["xi_lo"]
        if part.get("xi_hi") is not None:
            subset &= xi < part["xi_hi"]
    if field is not None:
        subset &= within(field["ra"], field["dec"], cat["ra"], cat["dec"], field["radius"])
    return subset


def _changed_rows(finals: list, variants: list, cat, subset, pixels) -> tuple:
    """Which galaxies of the sample each variant changed on each final, from the finals' CHANGED tables.

    Returns
    -------
    (dict, list)
        Variant -> per final, per catalogue row: changed (and in ``subset``);
        and per final its stamps' tables read (:func:`read_stamps` without
        the pixels; None with ``pixels``).
    """
    index = {int(i): k for k, i in enumerate(cat["id"])}
    changed = {v: [] for v in variants}
    stored = [None] * len(finals)
    for k, path in enumerate(finals):
        if pixels is not None:
            table = pixels[k]["CHANGED"]
        else:
            # the table now, the pixels when the joint fits take this final (one final's at a time in memory)
            stored[k] = read_stamps(path, variants, pixels=False)
            table = stored[k]["table"]
        for v in variants:
            mask = np.zeros(len(cat["id"]), dtype=bool)
            ids = np.asarray(table["id"])[np.asarray(table[variant_extname(v)], dtype=bool)]
            mask[[index[int(i)] for i in ids if int(i) in index]] = True
            changed[v].append(mask & subset)
    return changed, stored


def _final_changes(path: str, mine, variants: list, cat, changed: list, options, *, workers: int = 1,
                   cold: bool = False) -> tuple:
    """One final fitted on its own (:func:`frame_changes`) from its pixels in memory (``mine``)."""
    if mine is None:
        raise PerscliError(f"{path}: finals fitted per exposure are measured from their pixels in memory")
    with open_frame(f"{path}[SCI]") as frame:
        base = mine["SCI"]
        views = [np.where(np.isfinite(mine[variant_extname(v)]), mine[variant_extname(v)], base)
                 for v in variants]
        return frame_changes(frame, cat, variants, changed, views, options, data=base, workers=workers, cold=cold)


def _variant_columns(parts: list, cold: bool) -> dict:
    """A variant's rows of every measurement as columns, with '_counts': the sample, fitted, flagged, methods."""
    columns = COLUMNS + (COLD_COLUMNS if cold else ())
    cols = {c: np.concatenate([p[c] for p in parts]) for c in columns}
    fitted = cols["fitted"].astype(bool)

    cols["_counts"] = {"sample": len(cols["id"]), "fitted": int(fitted.sum()),
                       "flagged": int(np.count_nonzero(fitted & (cols["flags"] != 0))),
                       **{f"method_{m}": int(np.count_nonzero(fitted & (cols["method"] == k)))
                          for k, m in enumerate(CHANGE_METHODS)}}
    return cols


def _delta(ref: np.ndarray, var: np.ndarray) -> np.ndarray:
    """variant - reference where the variant has pixels (its NaN: unchanged), in float32 when that is exact."""
    ref64 = np.asarray(ref, dtype=np.float64)
    d = np.where(np.isfinite(var), np.asarray(var, dtype=np.float64) - ref64, 0.0)
    d[~np.isfinite(d)] = 0.0
    d32 = d.astype(np.float32)
    return d32 if np.array_equal(d32, d) else d


def _joint_changes(refs, variants, cat, per_variant, options, *, workers=1, cold=False, pixels=None, stored=None,
                   within=None):
    """The reference's joint fits and each variant's (:func:`measure_joint_changes_object`), as columns.

    The finals' pixels come from ``pixels`` (whole frames in memory) or
    ``stored`` (their windows, :func:`perscli.study.differential.read_stamps`).
    """
    only = np.logical_or.reduce(per_variant) if per_variant else None
    setup = joint_setup(refs, cat, options, only=only, within=within)
    jc, todo, rows = setup.ctx, setup.todo, setup.rows
    deltas = [[None] * len(refs) for _ in variants]
    for k, f in enumerate(jc.frames):
        here = todo[f.on[todo]]
        if pixels is not None:
            ref = pixels[k]["SCI"]
            f.data = setup.windows_of(ref, k)
            for v, name in enumerate(variants):
                if per_variant[v][rows[here]].any():
                    deltas[v][k] = setup.windows_of(_delta(ref, pixels[k][variant_extname(name)]), k)
            continue
        # measure's stamp of each galaxy, cut from the window the final kept of it
        wanted = {int(cat["id"][rows[j]]): stamp_window(f.shape, int(jc.sizes[j]), float(f.x[j]) - 1.0,
                                                        float(f.y[j]) - 1.0) for j in here}
        if "ref" not in stored[k]:
            stored[k] = read_stamps(stored[k]["path"], variants)
        f.data = Windows(f.shape)
        for window, block in stamp_windows(stored[k], "ref", wanted).items():
            f.data.put(window, block)
        for v, name in enumerate(variants):
            mine = here[per_variant[v][rows[here]]]
            if len(mine):
                # only the galaxies this variant changed are fitted with it: the others' windows are not kept
                # (twenty variants' windows of every final would not fit in a worker's memory)
                w = Windows(f.shape, stored[k]["deltas"][name].dtype, absent_zero=True)
                keep = {int(cat["id"][rows[j]]) for j in mine}
                for window, block in stamp_windows(stored[k], name,
                                                   {g: wd for g, wd in wanted.items() if g in keep}).items():
                    if np.any(block):
                        w.put(window, block)
                deltas[v][k] = w
        # the final's windows are copied into the frames' Windows: its tables can go
        stored[k] = None
    changed = [np.asarray(pv, dtype=bool)[rows] for pv in per_variant]
    ctx = ChangesContext(joint=jc, deltas=deltas, changed=changed, cold=cold)
    results = run(measure_joint_changes_object, todo, context=ctx, workers=workers)
    ref_cols = setup.columns([r["ref"] for r in results])
    var_cols = {}
    for v, name in enumerate(variants):
        fitted = [(j, r["variants"][v]) for j, r in zip(todo, results) if changed[v][j]]
        keys = [j for j, _ in fitted]
        out = _gather_changes([c for _, c in fitted], keys, cold)
        out["id"] = cat["id"][rows[keys]] if keys else np.zeros(0, dtype=np.int64)
        var_cols[name] = out
    return ref_cols, var_cols


def _gather_changes(results, keys, cold: bool) -> dict:
    """A variant's fits (one per changed galaxy) as columns."""
    names = ("g1", "g2", "flags", "method", "bound") + (("g1_cold", "g2_cold") if cold else ())
    out = {}
    for name in names:
        values = [r[name][0] for r in results]
        dtype = np.int32 if name == "flags" else np.int16 if name == "method" else np.float64
        out[name] = np.array(values, dtype=dtype)
    return out


def frame_changes(frame, cat, names, changed, views, options, *, data=None, workers=1, cold=False):
    """One final fitted per exposure: the reference's fits and each variant's, as :func:`_joint_changes` does jointly.

    Parameters
    ----------
    frame : perscli.io.frames.Frame
        The final's reference (SCI).
    names : sequence of str
        The variants.
    changed : sequence of ndarray of bool
        Per variant, per catalogue row: its stamp changed.
    views : sequence
        Per variant its pixels (an array, or a function returning one).
    data : ndarray, optional
        The reference's pixels, when already in memory.
    """
    changed = [np.asarray(c, dtype=bool) for c in changed]
    only = np.logical_or.reduce(changed) if changed else None
    setup = frame_setup(frame, cat, options=options, data=data, only=only)
    todo = setup.todo
    ref = setup.ctx.data
    deltas = []
    for c, view in zip(changed, views):
        if not c[todo].any():
            deltas.append(None)
            continue
        deltas.append(_delta(ref, view() if callable(view) else view))
    setup.changes(deltas, changed, cold)
    results = run(measure_object_changes, todo, context=setup.ctx, workers=workers)
    ref_cols = setup.columns([r["ref"] for r in results])
    var_cols = {}
    for v, name in enumerate(names):
        fitted = [(i, r["variants"][v]) for i, r in zip(todo, results) if changed[v][i]]
        keys = [i for i, _ in fitted]
        out = _gather_changes([c for _, c in fitted], keys, cold)
        out["id"] = cat["id"][keys] if keys else np.zeros(0, dtype=np.int64)
        var_cols[name] = out
    return ref_cols, var_cols


def _assemble(cat, ref: dict, var: dict, subset: np.ndarray, expid: int, e1_true, e2_true) -> dict:
    """Rows for the sample of one measurement: the De of the galaxies fitted in ``var``, exactly 0 for the others.

    ``ref`` holds the reference's fits of at least the galaxies ``var`` fitted (and its ``_todo``,
    the sample).
    """
    rows = np.asarray(ref["_todo"])
    rows = rows[subset[rows]]
    n = len(rows)
    out = {c: np.full(n, np.nan) for c in ("ra", "dec", "g1", "g2", "g1_ref", "g2_ref", "snr_pred", "bound",
                                           "de1_cold", "de2_cold")}
    out["id"] = np.asarray(cat["id"])[rows].astype(np.int64)
    out["expid"] = np.full(n, expid, dtype=np.int64)
    out["de1"], out["de2"], out["dabs"] = np.zeros(n), np.zeros(n), np.zeros(n)
    out["e1_true"], out["e2_true"] = e1_true[rows], e2_true[rows]
    out["fitted"] = np.zeros(n, dtype=np.int16)
    out["flags"] = np.zeros(n, dtype=np.int32)
    out["method"] = np.zeros(n, dtype=np.int16)
    if "ra" in cat:
        out["ra"], out["dec"] = cat["ra"][rows], cat["dec"][rows]
    pos = {int(r): k for k, r in enumerate(rows)}
    ref_at = {int(i): k for k, i in enumerate(ref["id"])}
    # the reference's flags count for every galaxy of the sample, fitted or not
    for k, i in enumerate(out["id"]):
        if int(i) in ref_at:
            out["flags"][k] = int(np.asarray(ref["flags"])[ref_at[int(i)]])
    k = np.array([pos[int(r)] for r in _rows_of(cat, var["id"]) if int(r) in pos], dtype=np.int64)
    inside = np.array([int(r) in pos for r in _rows_of(cat, var["id"])], dtype=bool)
    j = np.array([ref_at[int(i)] for i in np.asarray(var["id"])[inside]], dtype=np.int64)
    if len(k):
        out["g1"][k], out["g2"][k] = np.asarray(var["g1"])[inside], np.asarray(var["g2"])[inside]
        out["g1_ref"][k], out["g2_ref"][k] = np.asarray(ref["g1"])[j], np.asarray(ref["g2"])[j]
        out["flags"][k] = np.asarray(var["flags"], dtype=np.int32)[inside] | np.asarray(ref["flags"], dtype=np.int32)[j]
        out["snr_pred"][k] = np.asarray(ref["snr_pred"])[j]
        out["method"][k] = np.asarray(var["method"])[inside]
        out["bound"][k] = np.asarray(var["bound"])[inside]
        if "g1_cold" in var:
            out["de1_cold"][k] = np.asarray(var["g1_cold"])[inside] - out["g1_ref"][k]
            out["de2_cold"][k] = np.asarray(var["g2_cold"])[inside] - out["g2_ref"][k]
        out["fitted"][k] = 1
    fit = out["fitted"].astype(bool)
    out["de1"][fit] = out["g1"][fit] - out["g1_ref"][fit]
    out["de2"][fit] = out["g2"][fit] - out["g2_ref"][fit]
    out["dabs"][fit] = np.hypot(out["g1"][fit], out["g2"][fit]) - np.hypot(out["g1_ref"][fit], out["g2_ref"][fit])
    return out


def _rows_of(cat, ids) -> np.ndarray:
    index = {int(i): k for k, i in enumerate(cat["id"])}
    return np.array([index[int(i)] for i in ids], dtype=np.int64)


def write_changes(finals, variants, catalog: str, dest: str, *, options: MeasureOptions = CHANGES_OPTIONS,
                  expids=None, part=None, field=None, workers: int = 1, overwrite: bool = True, header=None,
                  pixels=None, cold: bool = False) -> dict:
    """:func:`measure_changes` of each variant, written into ``dest``: one table per variant, named after it.

    Parameters
    ----------
    variants : str or sequence of str
        The variants; each table's EXTNAME is :func:`variant_extname` of its
        variant (one row per galaxy of the sample, :data:`COLUMNS`).
    header : dict, optional
        More keywords for the primary header: KEY -> (value, comment).
    Others as for :func:`measure_changes`.

    Returns
    -------
    dict
        Variant -> the counts of :func:`measure_changes`, and 'sample', 'fitted' summed.
    """
    variants = [variants] if isinstance(variants, str) else list(variants)
    check_output(dest, overwrite=overwrite, inputs=[catalog, *finals])
    descriptions = {
        "de1": "g1 - g1_ref (0: no pixel of the stamps changed)", "de2": "g2 - g2_ref",
        "dabs": "|g| - |g_ref| (Delta|e|)", "g1_ref": "g1 without persistence (NaN: not fitted)",
        "e1_true": "intrinsic e1 of the catalogue", "e2_true": "intrinsic e2 of the catalogue",
        "fitted": "1: stamps changed, fitted with and without", "expid": "final (-1: joint over all)",
        "flags": "flags of the two fits (ORed; of the reference alone when not fitted): kept, as every galaxy of "
                 "the sample counts",
        "method": "how the variant's fit was reached: 0 same pixels, 1 linear response (checked), 2 warm Newton, "
                  "3 from the start",
        "bound": "g: the last Newton correction at the reported point (how far from the exact minimum it may be)",
        "de1_cold": "De1 with the variant fitted from the start (the check of the linear response)",
        "de2_cold": "De2 likewise"}
    primary = OutHDU([])
    hdus, counts = [primary], {}
    joint, min_snr = options.joint, options.min_snr
    measured = measure_changes(finals, variants, catalog, options=options, expids=expids, part=part, field=field,
                               workers=workers, pixels=pixels, cold=cold)

    for variant in variants:
        cols = measured[variant]
        c = counts[variant] = cols.pop("_counts")
        names = COLUMNS + (COLD_COLUMNS if cold else ())
        hdu = table_hdu({k: cols[k] for k in names}, variant_extname(variant), units={"ra": "deg", "dec": "deg"},
                        descriptions=descriptions)
        hdu["GAXES"] = ("sky" if joint else "pixel", "axes of g and De")
        hdu["VARIANT"] = (variant, "persistence variant")
        hdu["NSAMPLE"] = (c["sample"], "galaxies (per final without a joint fit) of the sample")
        hdu["NFITTED"] = (c["fitted"], "of them fitted: their stamps changed")
        hdu["NFLAGGED"] = (c["flagged"], "fitted with a flag (flags; still counted)")
        for k, m in enumerate(CHANGE_METHODS[1:], 1):
            hdu[f"NMETH{k}"] = (c[f"method_{m}"], f"variant fits reached by method {k} ({m})")
        hdus.append(hdu)
    add_provenance(primary.header, step=f"measure changes variants={','.join(variants)} joint={joint}",
                   params={"JOINT": (bool(joint), "one fit per galaxy over its finals"),
                           "GAXES": ("sky" if joint else "pixel", "axes of g and De"),
                           "MINSNR": (float(min_snr) if min_snr is not None else MIN_SNR_DEFAULT,
                                      "cut on the predicted S/N"),
                           "NFINALS": (len(finals), "final exposures' files read"),
                           "XILO": (part.get("xi_lo") if part and part.get("xi_lo") is not None else "none",
                                    "[rad] galaxies' standard coordinate from (strip)"),
                           "XIHI": (part.get("xi_hi") if part and part.get("xi_hi") is not None else "none",
                                    "[rad] to (strip)"),
                           "CAT": (catalog.rsplit("/", 1)[-1][-68:], "truth catalogue"),
                           "FIELDRAD": (float(field["radius"]) if field else "none",
                                        "[deg] galaxies within this of the field centre"),
                           **(header or {})})
    write_hdus(hdus, dest, overwrite=overwrite)
    counts["sample"] = sum(c["sample"] for c in counts.values())
    counts["fitted"] = sum(c["fitted"] for k, c in counts.items() if k != "sample")
    return counts
