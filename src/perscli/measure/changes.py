"""Shape changes De measured only where the pixels changed: the differential study's measurement.

A final exposure rendered with and without persistence differs only where
persistence reached (:mod:`perscli.render.differential` writes the
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

import numpy as np

from .. import PerscliError
from .joint import measure_joint
from .noise import MIN_SNR_DEFAULT
from .perframe import measure_frame
from .selection import read_positions
from .settings import MeasureOptions

#: the CHANGED table of a final's file: the catalogue ids whose stamps a variant changed
CHANGED_EXTNAME = "CHANGED"

#: |De| of a galaxy fitted on both: De = g(variant) - g(reference); Delta|e| = |g(variant)| - |g(reference)|
COLUMNS = ("id", "ra", "dec", "expid", "g1", "g2", "g1_ref", "g2_ref", "de1", "de2", "dabs", "e1_true",
           "e2_true", "snr_pred", "fitted", "fit_flags")


def variant_extname(variant: str) -> str:
    """The image HDU of a final's file that holds a variant ('stars-typical' -> 'STARS-TYPICAL')."""
    return variant.upper()


def read_changed(path: str, variant: str) -> np.ndarray:
    """The catalogue ids whose stamps ``variant`` changed in the final's file ``path``."""
    from ..io.tables import read_table

    table = read_table(f"{path}[{CHANGED_EXTNAME}]", what="changed stamps (perscli study)")
    column = variant_extname(variant)
    names = {n.upper(): n for n in table.names}
    if column not in names:
        raise PerscliError(f"{path}: its {CHANGED_EXTNAME} table has no column {column} (variants: "
                           f"{', '.join(n for n in names if n != 'ID')})")
    ids = table.column("id", kind="integer")
    return ids[np.asarray(table.column(names[column], kind="integer"), dtype=bool)]


def _truth_shapes(catalog: str, n: int):
    from ..io.tables import read_table

    table = read_table(catalog, what="truth catalogue")
    names = {c.lower(): c for c in table.names}
    if "e1" in names and "e2" in names:
        return table.column("e1").astype(np.float64), table.column("e2").astype(np.float64)
    return np.full(n, np.nan), np.full(n, np.nan)


_CATALOGUES: dict = {}


def _catalogue(path: str):
    """The catalogue's positions and true shapes, read once per process and file (a study's finals share it)."""
    import os

    st = os.stat(path)
    key = (os.path.realpath(path), st.st_size, st.st_mtime_ns)
    if key not in _CATALOGUES:
        _CATALOGUES.clear()
        cat = read_positions(path)
        _CATALOGUES[key] = (cat, *_truth_shapes(path, len(cat["id"])))
    return _CATALOGUES[key]


def _variant_view(path: str, variant: str):
    """A function giving the variant's pixels of a final: its own where it has them, else the reference's."""

    def read():
        from ..io.frames import open_frame

        with open_frame(f"{path}[SCI]") as ref, open_frame(f"{path}[{variant_extname(variant)}]") as var:
            a = np.asarray(ref.planes()[0], dtype=np.float32)
            b = np.asarray(var.planes()[0], dtype=np.float32)
        return np.where(np.isfinite(b), b, a)

    return read


#: what the study measures with unless told: one fit per galaxy over all its finals (the paper's pipeline)
CHANGES_OPTIONS = MeasureOptions(joint=True)


def measure_changes(finals, variants, catalog: str, *, options: MeasureOptions = CHANGES_OPTIONS, expids=None,
                    part=None, workers: int = 1, pixels=None) -> dict:
    """De of every galaxy of the sample between each variant and the reference, fitting only those that changed.

    Parameters
    ----------
    finals : sequence of str
        The finals' files (:func:`perscli.render.differential.render_final`):
        SCI (the reference), one HDU per variant, MODEL and CHANGED.
    variants : str or sequence of str
        Which variants (e.g. 'stars-typical').  The reference is fitted once
        for the galaxies any of them changed.
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
        (:func:`perscli.render.differential.render_final`'s ``pixels``): the
        files then give only their headers.
    part : dict, optional
        Only the galaxies of a strip of the sky: ``ra0``, ``dec0`` (the
        tangent point, degrees), ``xi_lo``, ``xi_hi`` (standard coordinates,
        radians; None: open) of their catalogue positions (a study spreads
        its galaxies over strips, :func:`perscli.study.plan.measure_strips`).
    workers : int

    Returns
    -------
    dict
        Variant -> column arrays (:data:`COLUMNS`), one row per galaxy of the
        sample (per galaxy and final without ``joint``), with '_counts': the
        sample, the galaxies fitted and those flagged.
    """
    finals = list(finals)
    variants = [variants] if isinstance(variants, str) else list(variants)
    cat, e1_true, e2_true = _catalogue(catalog)
    index = {int(i): k for k, i in enumerate(cat["id"])}
    subset = np.ones(len(cat["id"]), dtype=bool)
    if part is not None:
        from ..scene import project

        xi, _ = project(part["ra0"], part["dec0"], cat["ra"], cat["dec"])
        if part.get("xi_lo") is not None:
            subset &= xi >= part["xi_lo"]
        if part.get("xi_hi") is not None:
            subset &= xi < part["xi_hi"]
    changed = {v: [] for v in variants}
    for k, path in enumerate(finals):
        for v in variants:
            mask = np.zeros(len(cat["id"]), dtype=bool)
            if pixels is not None:
                table = pixels[k]["CHANGED"]
                ids = np.asarray(table["id"])[np.asarray(table[variant_extname(v)], dtype=bool)]
            else:
                ids = read_changed(path, v)
            mask[[index[int(i)] for i in ids if int(i) in index]] = True
            changed[v].append(mask & subset)
    joint = options.joint
    kw = dict(options=MeasureOptions(stamp=options.stamp, min_snr=options.min_snr), workers=workers)
    parts = {v: [] for v in variants}
    if joint:
        refs = [f"{p}[SCI]" for p in finals]
        only = {v: np.logical_or.reduce(changed[v]) if finals else np.zeros(len(cat["id"]), dtype=bool)
                for v in variants}
        ref = measure_joint(refs, cat, only=np.logical_or.reduce(list(only.values())), **kw)
        for v in variants:
            var = measure_joint(refs, cat, only=only[v], data=[_variant_view(p, v) for p in finals], **kw)
            parts[v].append(_assemble(cat, ref, var, subset, -1, e1_true, e2_true))
    else:
        from ..io.frames import open_frame

        for k, path in enumerate(finals):
            expid = int(expids[k]) if expids is not None else k
            mine = pixels[k] if pixels is not None else None
            with open_frame(f"{path}[SCI]") as frame:
                # the reference and its variants are one frame: one PSF model for all of them
                models = {}
                base = mine["SCI"] if mine is not None else None
                ref = measure_frame(frame, cat, only=np.logical_or.reduce([changed[v][k] for v in variants]),
                                    models=models, data=base, **kw)
                for v in variants:
                    view = np.where(np.isfinite(mine[variant_extname(v)]), mine[variant_extname(v)], base) \
                        if mine is not None else _variant_view(path, v)()
                    var = measure_frame(frame, cat, only=changed[v][k], data=view, models=models, **kw)
                    parts[v].append(_assemble(cat, ref, var, subset, expid, e1_true, e2_true))
    out = {}
    for v in variants:
        cols = {c: np.concatenate([p[c] for p in parts[v]]) for c in COLUMNS}
        fitted = cols["fitted"].astype(bool)
        cols["_counts"] = {"sample": len(cols["id"]), "fitted": int(fitted.sum()),
                           "flagged": int(np.count_nonzero(fitted & (cols["fit_flags"] != 0)))}
        out[v] = cols
    return out


def _assemble(cat, ref: dict, var: dict, subset: np.ndarray, expid: int, e1_true, e2_true) -> dict:
    """Rows for the sample of one measurement: the De of the galaxies fitted in ``var``, exactly 0 for the others.

    ``ref`` holds the reference's fits of at least the galaxies ``var`` fitted (and its ``_todo``,
    the sample).
    """
    rows = np.asarray(ref["_todo"])
    rows = rows[subset[rows]]
    n = len(rows)
    out = {c: np.full(n, np.nan) for c in ("ra", "dec", "g1", "g2", "g1_ref", "g2_ref", "snr_pred")}
    out["id"] = np.asarray(cat["id"])[rows].astype(np.int64)
    out["expid"] = np.full(n, expid, dtype=np.int64)
    out["de1"], out["de2"], out["dabs"] = np.zeros(n), np.zeros(n), np.zeros(n)
    out["e1_true"], out["e2_true"] = e1_true[rows], e2_true[rows]
    out["fitted"] = np.zeros(n, dtype=np.int16)
    out["fit_flags"] = np.zeros(n, dtype=np.int32)
    if "ra" in cat:
        out["ra"], out["dec"] = cat["ra"][rows], cat["dec"][rows]
    pos = {int(r): k for k, r in enumerate(rows)}
    ref_at = {int(i): k for k, i in enumerate(ref["id"])}
    k = np.array([pos[int(r)] for r in _rows_of(cat, var["id"])], dtype=np.int64)
    j = np.array([ref_at[int(i)] for i in var["id"]], dtype=np.int64)
    if len(k):
        out["g1"][k], out["g2"][k] = var["g1"], var["g2"]
        out["g1_ref"][k], out["g2_ref"][k] = np.asarray(ref["g1"])[j], np.asarray(ref["g2"])[j]
        out["fit_flags"][k] = np.asarray(var["flags"], dtype=np.int32) | np.asarray(ref["flags"], dtype=np.int32)[j]
        out["snr_pred"][k] = np.asarray(ref["snr_pred"])[j]
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
                  expids=None, part=None, workers: int = 1, overwrite: bool = True, header=None,
                  pixels=None) -> dict:
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
    from ..io.fitsfile import OutHDU, table_hdu
    from ..io.output import add_provenance, check_output, write_hdus

    variants = [variants] if isinstance(variants, str) else list(variants)
    check_output(dest, overwrite=overwrite, inputs=[catalog, *finals])
    descriptions = {
        "de1": "g1 - g1_ref (0: no pixel of the stamps changed)", "de2": "g2 - g2_ref",
        "dabs": "|g| - |g_ref| (Delta|e|)", "g1_ref": "g1 without persistence (NaN: not fitted)",
        "e1_true": "intrinsic e1 of the catalogue", "e2_true": "intrinsic e2 of the catalogue",
        "fitted": "1: stamps changed, fitted with and without", "expid": "final (-1: joint over all)",
        "fit_flags": "flags of the two fits (ORed): kept, as every galaxy of the sample counts"}
    primary = OutHDU([])
    hdus, counts = [primary], {}
    joint, min_snr = options.joint, options.min_snr
    measured = measure_changes(finals, variants, catalog, options=options, expids=expids, part=part, workers=workers,
                               pixels=pixels)
    for variant in variants:
        cols = measured[variant]
        c = counts[variant] = cols.pop("_counts")
        hdu = table_hdu({k: cols[k] for k in COLUMNS}, variant_extname(variant), units={"ra": "deg", "dec": "deg"},
                        descriptions=descriptions)
        hdu["GAXES"] = ("sky" if joint else "pixel", "axes of g and De")
        hdu["VARIANT"] = (variant, "persistence variant")
        hdu["NSAMPLE"] = (c["sample"], "galaxies (per final without a joint fit) of the sample")
        hdu["NFITTED"] = (c["fitted"], "of them fitted: their stamps changed")
        hdu["NFLAGGED"] = (c["flagged"], "fitted with a flag (fit_flags; still counted)")
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
                           "CAT": (catalog.rsplit("/", 1)[-1][-68:], "truth catalogue"), **(header or {})})
    write_hdus(hdus, dest, overwrite=overwrite)
    counts["sample"] = sum(c["sample"] for c in counts.values())
    counts["fitted"] = sum(c["fitted"] for k, c in counts.items() if k != "sample")
    return counts
