"""Shapes of catalogue galaxies on frames: selection, stamps, noise model, PSF, fits, catalogue out.

Which objects are fitted: the catalogue rows of the kinds asked for (galaxies
by default, from the truth catalogue's ``kind`` column), whose position falls
on the frame, and whose S/N predicted from the catalogue alone reaches
``min_snr`` (:func:`predicted_snr`: magnitude through ZPT_AB, size, PSF and
noise model; never the pixels, so the cut is the same on frames with and
without persistence).

For each frame and each object fitted on it: a stamp around the object's
position (ra/dec through the frame's WCS, or x/y), the background removed,
weights from a weight/variance HDU or from the frame's noise model, and a fit
(:func:`perscli.measure.fit.fit_exp`, or GalSim's HSM for comparison).  With
``joint``, one fit per galaxy over all the frames it falls on
(:func:`perscli.measure.fit.fit_joint`), its parameters on the sky.

Everything that enters a fit (start, weights, background) depends only on the
catalogue and the frame's headers, never on the noise of its pixels, so that
two frames that differ by a small pattern (persistence) give shape changes
that are that pattern's effect alone.

The code is in modules of one job each: :mod:`perscli.measure.selection`
(the catalogue, the rows to fit, positions on a frame, blends),
:mod:`perscli.measure.noise` (noise model, predicted S/N and its cut),
:mod:`perscli.measure.perframe` (stamps, starts, flags and the fit of one
frame, :func:`measure_frame`) and :mod:`perscli.measure.joint` (the joint
fit, :func:`measure_joint`); this module is the file driver,
:func:`measure_files`, and its output tables.
"""

from __future__ import annotations

import logging
import math
import os
import textwrap

import numpy as np

from .. import PerscliError
from ..io.fitsfile import OutHDU, table_hdu
from ..io.frames import open_frame
from ..io.output import add_provenance, check_output, write_hdus
from .joint import measure_joint
from .noise import _check_min_snr
from .perframe import FLAGS, STAMP_HLR, STAMP_MARGIN, STAMP_MIN, measure_frame
from .psf import psf_hdus
from .selection import _pixel_scale, frame_wcs, read_positions, select_kinds
from .settings import MeasureOptions

log = logging.getLogger(__name__)


# -- the command ---------------------------------------------------------------------------------------------


_SHAPES_UNITS = {"x": "pix", "y": "pix", "ra": "deg", "dec": "deg", "T": "pix2", "x_err": "pix", "y_err": "pix",
                 "T_err": "pix2"}
# flux and flux_err are in electrons per second, but get no TUNIT: the FITS standard has no unit for electrons,
# and astropy's FITS reader warns (UnitsWarning) on 'electron/s', 'electron / s' or any other spelling; 'ct/s'
# would parse, but perscli reads 'counts' as DN (perscli.io.frames.normalize_unit).  The unit is in their
# TTYPE comments (_DESCRIPTIONS) and in the header's COMMENT cards instead
_JOINT_UNITS = {"ra": "deg", "dec": "deg", "ra_err": "arcsec", "dec_err": "arcsec", "T": "arcsec2",
                "T_err": "arcsec2"}
_DESCRIPTIONS = {"snr_pred": "S/N predicted from the catalogue (cut: MINSNR)",
                 "g1": "reduced shear, +g1 along the first axis", "g2": "reduced shear, +g2 along the diagonal",
                 "nframes": "frames the galaxy falls on with >= 20 usable pixels"}


def measure_files(frames, catalog: str, dest: str, *, options: MeasureOptions | None = None, write_psf=None,
                  workers: int = 1, overwrite: bool = False, progress=None) -> dict:
    """``perscli measure`` as a function: shapes of the catalogue's galaxies on each frame, or jointly.

    Writes a FITS file.  Per frame (the default): a SHAPES table, one row per
    object fitted on each frame (``frame`` = index of the frame in the order
    given) and, for several frames, a COMBINED table: per object, the
    inverse-variance weighted mean of g1 and g2 over the frames where its fit
    has no flag.  With ``joint``: a JOINT table, one row per galaxy, fitted
    on all its frames at once with g on the sky (see
    :func:`perscli.measure.fit.fit_joint`).

    Parameters
    ----------
    frames : sequence of str
    catalog : str
        Truth catalogue (``perscli catalog``) or any table with id and ra/dec or x/y.
    dest : str
    options : perscli.measure.settings.MeasureOptions, optional
        How to select and fit: the command's options (default:
        ``MeasureOptions()``, the command's defaults).  ``joint``: one fit per
        galaxy over all the frames (one FILTER, with WCS and EXPTIME);
        ``columns``: the catalogue's column names (:func:`read_positions`).
    write_psf : str or None
        Also write the PSF images used there, one HDU per PSF
        (:func:`perscli.measure.psf.psf_hdus`), readable as ``options.psf``.
    workers, overwrite, progress
        As the command's options (progress: a callback of
        :func:`perscli.executor.run`).

    Returns
    -------
    dict
        Summary: rows, good (= unflagged: rows with flags 0), frames, and the
        numbers selected, fitted and cut.
    """
    o = options if options is not None else MeasureOptions()
    frames = list(frames)
    min_snr, psf_options = _checked_options(o, frames, catalog, dest, write_psf, overwrite)
    psf_used = []
    cat = read_positions(catalog, columns=o.columns)
    _, kinds_text = select_kinds(cat, o.kinds)       # bad --kinds fail here, before any frame is read
    inputs = [("CAT", catalog, cat["datasum"])]
    measure = _measure_jointly if o.joint else _measure_each_frame
    shapes, noise_sources, counts = measure(frames, cat, o, psf_options=psf_options, psf_used=psf_used,
                                            inputs=inputs, workers=workers, progress=progress)
    hdus = [OutHDU([]), *_shapes_hdus(shapes, o.joint, len(frames))]
    params = _measure_params(o, len(frames), kinds_text, min_snr, psf_options, counts, noise_sources, psf_used)
    add_provenance(hdus[0], step=f"measure method={o.method} psf={params['PSF'][0]} frames={len(frames)}"
                                 f"{' joint' if o.joint else ''} kinds={kinds_text} min_snr={min_snr:g}",
                   params=params, inputs=inputs)
    _document(hdus[0], o.joint)
    if write_psf is not None:
        _write_psf(psf_used, write_psf, o.psf, inputs, overwrite)
    write_hdus(hdus, dest, overwrite=overwrite)
    good = int(np.sum(shapes["flags"] == 0))
    totals = counts if o.joint else {"selected": counts[0]["selected"] if counts else 0,
                                     "fitted": sum(c["fitted"] for c in counts), "cut": sum(c["cut"] for c in counts)}
    return {"rows": len(shapes["id"]), "good": good, "unflagged": good, "frames": len(frames),
            "selected": totals["selected"], "fitted": totals["fitted"], "cut": totals["cut"], "joint": bool(o.joint)}


def _checked_options(o: MeasureOptions, frames: list, catalog: str, dest: str, write_psf, overwrite: bool) -> tuple:
    """Check :func:`measure_files`' options and outputs before anything is read.

    Returns
    -------
    (float, perscli.measure.psf.PsfOptions)
        The S/N cut, and the run's PSF image settings.

    Raises
    ------
    PerscliError
        An option out of range or at odds with another, or an output that
        cannot be written.
    """
    psf, method, stamp, joint, psf_pixel = o.psf, o.method, o.stamp, o.joint, o.psf_pixel
    if method not in ("exp", "hsm"):
        raise PerscliError(f"--method must be exp or hsm, not {method!r}")
    if stamp < 16 or stamp % 2:
        raise PerscliError(f"--stamp {stamp} must be an even number of pixels >= 16")
    min_snr = _check_min_snr(o.min_snr)
    if joint and method != "exp":
        raise PerscliError("--joint fits the exponential model: it does not go with --method hsm")
    if frames.count("-") > 1:
        raise PerscliError("only one frame can be standard input ('-')")
    if psf == "roman":
        given = [name for name, value in (("--psf-pixel", psf_pixel), ("--psf-oversampling", o.psf_oversampling),
                                           ("--allow-undersampled-psf", o.allow_undersampled_psf)) if value]
        if given:
            raise PerscliError(f"{' and '.join(given)} describe{'s' if len(given) == 1 else ''} a PSF image: "
                               "give --psf PSF.fits, or leave it out with --psf roman")
    # one for the run: its frames share the record of the warnings given
    psf_options = o.psf_options()
    read = [catalog, *frames, psf if psf != "roman" else None]
    check_output(dest, overwrite=overwrite, inputs=read)
    if write_psf is not None:
        check_output(write_psf, overwrite=overwrite, inputs=read)
        if write_psf == "-" and dest == "-":
            raise PerscliError("--write-psf and -o cannot both be standard output: give --write-psf a file")
        if write_psf != "-" and dest != "-" and os.path.abspath(write_psf) == os.path.abspath(dest):
            raise PerscliError(f"{write_psf}: --write-psf and -o name the same file: choose another name for the PSF")
    return min_snr, psf_options


def _measure_jointly(frames, cat, o: MeasureOptions, *, psf_options, psf_used, inputs, workers, progress) -> tuple:
    """One fit per galaxy over all the frames (:func:`perscli.measure.joint.measure_joint`).

    Returns
    -------
    (dict, list, dict)
        The columns, the noise model of each frame, and the counts
        (selected, on, cut, fitted, models).
    """
    cols = measure_joint(frames, cat, options=o, progress=progress, workers=workers, inputs=inputs,
                         psf_options=psf_options, psf_used=psf_used)
    noise_sources = cols.pop("_noise")
    counts = cols.pop("_counts")
    return cols, noise_sources, counts


def _measure_each_frame(frames, cat, o: MeasureOptions, *, psf_options, psf_used, inputs, workers,
                        progress) -> tuple:
    """The fits on each frame (:func:`perscli.measure.perframe.measure_frame`), one after the other.

    Each frame's input (FRMnn) is appended to ``inputs``.

    Returns
    -------
    (dict, list, list of dict)
        The columns of all the frames' rows (``frame``: the index of the
        frame), the noise model of each frame, and each frame's counts.
    """
    tables, noise_sources, frame_counts = [], [], []
    kwargs = dict(options=o, psf_options=psf_options, psf_used=psf_used)
    models = {}
    for k, name in enumerate(frames):
        frame = open_frame(name)
        try:
            inputs.append((f"FRM{k + 1:02d}", name, frame.datasum(frame.sci[0])))
            # one model (the PSF's table: half a second) per SCA and filter, not per frame
            wcs = frame_wcs(frame)
            key = (str(frame.keyword("SCA")), str(frame.keyword("FILTER")), round(_pixel_scale(wcs), 6))
            cols = measure_frame(frame, cat, progress=progress, workers=workers,
                                 models=models.setdefault(key, {}), **kwargs)
        finally:
            frame.close()
        noise_sources.append(cols.pop("_noise"))
        frame_counts.append(cols.pop("_counts"))
        table = {"id": cols["id"], "frame": np.full(len(cols["id"]), k, dtype=np.int16)}
        table.update({key: cols[key] for key in ("x", "y", "ra", "dec", "g1", "g2", "T", "flux", "x_err",
                                                  "y_err", "g1_err", "g2_err", "T_err", "flux_err", "s2n",
                                                  "snr_pred", "chi2", "nfev", "flags")})
        tables.append(table)
    shapes = {key: np.concatenate([np.asarray(t[key]) for t in tables]) for key in tables[0]}
    return shapes, noise_sources, frame_counts


def _shapes_hdus(shapes: dict, joint: bool, nframes: int) -> list:
    """The tables of :func:`measure_files`: JOINT, or SHAPES and (for several frames) COMBINED."""
    if joint:
        order = ("id", "ra", "dec", "g1", "g2", "T", "flux", "ra_err", "dec_err", "g1_err", "g2_err", "T_err",
                 "flux_err", "s2n", "snr_pred", "nframes", "chi2", "nfev", "flags")
        table = {key: shapes[key] for key in order}
        descriptions = dict(_DESCRIPTIONS, g1="reduced shear on the sky, +g1 East-West (RA axis)",
                            g2="reduced shear on the sky, +g2 North-West/South-East",
                            ra_err="error of the centre towards the West", dec_err="error towards the North",
                            flux="[e-/s] electrons per second (no FITS unit)", flux_err="[e-/s] error of flux")
        return [table_hdu(table, "JOINT", units=_JOINT_UNITS, descriptions=descriptions)]
    descriptions = dict(_DESCRIPTIONS, g1="reduced shear, +g1 along the frame's x axis",
                        g2="reduced shear, +g2 along the diagonal x = y")
    hdus = [table_hdu(shapes, "SHAPES", units=_SHAPES_UNITS, descriptions=descriptions)]
    if nframes > 1:
        hdus.append(_combined(shapes))
    return hdus


def _measure_params(o: MeasureOptions, nframes: int, kinds_text: str, min_snr: float, psf_options, counts,
                    noise_sources, psf_used) -> dict:
    """The primary header's keywords of :func:`measure_files`: the settings, the counts, flags and backgrounds.

    ``counts``: the joint fit's counts, or each frame's (:func:`_measure_jointly`,
    :func:`_measure_each_frame`).
    """
    psf, joint = o.psf, o.joint
    params = {"METHOD": (o.method, "exp (mixture fit) or hsm (REGAUSS)"),
              "PSF": (psf if psf == "roman" else psf.split("/")[-1], "PSF source"),
              "STAMP": (o.stamp, "[pix] largest stamp side"),
              "STAMPRUL": (f"{STAMP_HLR:g} hlr+{STAMP_MARGIN:g}px" if o.method == "exp" else "fixed",
                           f"exp stamp: smallest {STAMP_MIN},{STAMP_MIN + 8},.. holding it"),
              "RDNOISE": (o.read_noise if o.read_noise is not None else "model",
                                                            "[e-] read noise ('model': the frame's)"),
              "NFRAMES": (nframes, "frames measured"), "XTOL": (1e-10, "relative step tolerance"),
              "BLENDRAD": (o.blend_radius, "[pix] neighbour distance flagged as a blend"),
              "KINDS": (kinds_text, "catalogue kinds fitted"),
              "MINSNR": (min_snr, "cut on the S/N predicted from the catalogue"),
              "SNRPRED": ("mag,hlr,PSF,noise", "predicted S/N from (never the pixels)"),
              "ALLROWS": (bool(o.all_rows), "rows off the frame (256) / below cut (4096)"),
              "JOINT": (bool(joint), "one fit per galaxy over all frames"),
              "PSFPIXEL": (o.psf_pixel or "header", "PSF image includes the pixel (--psf-pixel)"),
              "PSFOVERS": (psf_options.oversampling or "header", "PSF pixels per frame pixel (option)"),
              "PSFUNDER": (bool(o.allow_undersampled_psf), "undersampled PSF image allowed")}
    if joint:
        params.update({"NSEL": (counts["selected"], "catalogue rows of KINDS"),
                       "NONFRM": (counts["on"], "of them on at least one frame"),
                       "NCUT": (counts["cut"], "on a frame, combined predicted S/N < MINSNR"),
                       "NFIT": (counts["fitted"], "galaxies fitted"),
                       "NPSF": (counts["models"], "PSF models (SCA, filter) used"),
                       "GAXES": ("sky: u=West, v=North", "axes of g1, g2 (GalSim's world axes)")})
    else:
        params["NSEL"] = (counts[0]["selected"] if counts else 0, "catalogue rows of KINDS")
        for k, c in enumerate(counts, 1):
            params[f"NON{k:02d}"] = (c["on"], f"of them on frame {k}")
            params[f"NCUT{k:02d}"] = (c["cut"], f"on frame {k}, predicted S/N < MINSNR")
            params[f"NFIT{k:02d}"] = (c["fitted"], f"fitted on frame {k}")
        params["GAXES"] = ("pixel", "axes of g1, g2: the frame's x, y")
    for bit, text in FLAGS.items():
        params[f"FLAG{int(math.log2(bit)):02d}"] = (bit, text[:47])
    for k, noise in enumerate(noise_sources, 1):
        params[f"BKG{k:02d}"] = (float(noise.background), f"background of frame {k} ({noise.source})")
    if psf != "roman":
        # how each PSF image was read: the parameters that produced the shapes
        for k, used in enumerate(psf_used[:99], 1):
            params[f"PSFPX{k:02d}"] = (bool(used.pixel_included), f"PSF {k} includes the pixel response")
            params[f"PSFOV{k:02d}"] = (float(used.oversampling), f"PSF {k}: PSF pixels per frame pixel")
    return params


def _write_psf(psf_used, dest, psf, inputs, overwrite):
    """--write-psf: the PSF images of the fits, one HDU per PSF, with the keywords that read them back."""
    # one image per SCA and FILTER, which is how --psf picks them again (frames of one SCA whose WCS
    # scales differ by 1e-6 have models of their own, of the same PSF)
    distinct = {}
    for used in psf_used:
        distinct.setdefault((used.source, used.sca, used.filter), used)
    psf_used = list(distinct.values())
    primary = OutHDU([])
    add_provenance(primary, step=f"measure --write-psf psf={psf if psf == 'roman' else psf.split('/')[-1]}",
                   params={"NPSF": (len(psf_used), "PSF images (one per SCA and FILTER)")}, inputs=inputs)
    primary.add_comment("Each PSF HDU: a PSF image with PSFPIXEL (includes the pixel response), OVERSAMP (PSF")
    primary.add_comment("pixels per detector pixel), PIXSCALE, SCA and FILTER; perscli measure --psf THIS")
    primary.add_comment("takes, for each frame, the HDU of its SCA and FILTER.")
    write_hdus([primary, *psf_hdus(psf_used)], dest, overwrite=overwrite)


def _document(header, joint: bool):
    """COMMENT cards (72 characters each): what the rows are and the axes of g."""
    text = ("Rows: the objects of KINDS whose position falls on the frame and whose S/N predicted from the "
            "catalogue (magnitude through ZPT_AB, hlr, PSF, sky + dark + read noise; never the pixels) is at "
            "least MINSNR; with ALLROWS also the others, without a fit (flag 256 off the frame, 4096 below "
            "the cut).")
    if joint:
        text += (" JOINT: one fit per galaxy over all the frames, its parameters on the sky: g1, g2 in the "
                 "tangent plane with u to the West and v to the North (+g1 elongated East-West, +g2 "
                 "North-West/South-East: the truth catalogue's e1, e2 axes), T = Cuu + Cvv in arcsec2, flux "
                 "in e-/s, ra/dec the fitted centre.")
    else:
        text += " SHAPES: g1, g2 in the frame's pixel axes (+g1 along x), T in pixel2."
    for line in textwrap.wrap(text, 72):
        header.add_comment(line)


def _combined(shapes):
    """Per object: inverse-variance weighted mean g over frames whose fit has no flag."""
    ids = np.unique(np.asarray(shapes["id"]))
    good = (np.asarray(shapes["flags"]) == 0) & np.isfinite(np.asarray(shapes["g1_err"]))
    out = {"id": ids, "nframes": np.zeros(len(ids), dtype=np.int16)}
    for key in ("g1", "g2"):
        out[key] = np.full(len(ids), np.nan)
        out[f"{key}_err"] = np.full(len(ids), np.nan)
    index = np.searchsorted(ids, np.asarray(shapes["id"]))
    for key in ("g1", "g2"):
        w = np.where(good, 1.0 / np.where(good, np.asarray(shapes[f"{key}_err"]), 1.0) ** 2, 0.0)
        wsum = np.bincount(index, weights=w, minlength=len(ids))
        vsum = np.bincount(index, weights=w * np.where(good, np.asarray(shapes[key]), 0.0), minlength=len(ids))
        ok = wsum > 0
        out[key][ok] = vsum[ok] / wsum[ok]
        out[f"{key}_err"][ok] = 1.0 / np.sqrt(wsum[ok])
    out["nframes"] = np.bincount(index, weights=good.astype(float), minlength=len(ids)).astype(np.int16)
    return table_hdu({key: out[key] for key in ("id", "nframes", "g1", "g1_err", "g2", "g2_err")}, "COMBINED")
