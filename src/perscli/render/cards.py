"""The FITS layout of a rendered frame: its HDUs and their header cards.

:func:`perscli.render.run.render_file` computes a frame (the objects drawn,
the detector chain, the persistence of earlier frames); :func:`_frame_hdus`
lays it out: the primary HDU, then SCI, IDEAL, FLUENCE, DRAWN, STARFLU,
PERSIST and MODEL as asked for, each image with the SCA's WCS
(:func:`_wcs_cards`) and the exposure's keywords (:func:`_exposure_cards`).
:func:`_provenance` writes the primary header's record of the run.  The
study's finals (:mod:`perscli.study.differential`) write their windows with
the same cards.
"""

from __future__ import annotations

import datetime as _dt
import os

import galsim
import numpy as np

from ..detector.model import DetectorModel, model_table
from ..io.cards import format_card
from ..io.fitsfile import OutHDU
from ..io.output import add_provenance
from .exposure import Exposure


def _wcs_cards(optics, bounds) -> list:
    """FITS WCS cards of the exposure's SCA for an image with these bounds."""
    xmin, xmax, ymin, ymax = bounds
    header = {}
    optics.wcs.writeToFitsHeader(header, galsim.BoundsI(xmin, xmax, ymin, ymax))
    cards = []
    for key, value in header.items():
        if isinstance(value, tuple):
            value, comment = value
        else:
            comment = None
        if key in ("GS_XMIN", "GS_YMIN", "GS_WCS", "TELESCOP", "INSTRUME"):
            # GalSim's own markers, and instrument names that _exposure_cards writes
            continue
        cards.append(format_card(key, value, comment))
    return cards


def _exposure_cards(exposure: Exposure, optics, seed: int, bunit: str, gain: float) -> list:
    xmin, _, ymin, _ = exposure.full_bounds
    date_obs = (_dt.datetime(1858, 11, 17) + _dt.timedelta(days=exposure.mjd)).isoformat(timespec="milliseconds")
    return [
        format_card("BUNIT", bunit, "units of the data"),
        format_card("GAIN", gain, "[e-/DN]"),
        format_card("EXPTIME", exposure.exptime, "[s] exposure time"),
        format_card("EXPSTART", exposure.mjd, "[MJD] exposure start"),
        format_card("EXPEND", exposure.end, "[MJD] exposure end"),
        format_card("DATE-OBS", date_obs, "UTC start of the exposure"),
        format_card("TELESCOP", "ROMAN"),
        format_card("INSTRUME", "WFI"),
        format_card("SCA", exposure.sca, "sensor chip assembly"),
        format_card("FILTER", exposure.filter),
        format_card("EXPID", exposure.expid, "exposure identifier (e.g. schedule row)"),
        format_card("RA_PNT", exposure.ra, "[deg] pointing of the focal plane"),
        format_card("DEC_PNT", exposure.dec, "[deg] pointing of the focal plane"),
        format_card("PA_PNT", exposure.pa, "[deg] observatory position angle"),
        format_card("ZPT_AB", optics.zeropoint, "AB mag of 1 photon/cm^2/s"),
        format_card("LTV1", float(1 - xmin), "cutout offset: image x = SCA x + LTV1"),
        format_card("LTV2", float(1 - ymin), "cutout offset: image y = SCA y + LTV2"),
        format_card("SEED", int(seed), "random seed"),
    ]


def _frame_hdus(drawn, exposure: Exposure, model: DetectorModel, seed: int, hdus, source_params) -> list:
    """The frame's HDUs in :data:`HDU_NAMES` order, each with its cards (the primary's provenance not yet).

    Parameters
    ----------
    drawn : perscli.render.run._Drawn
        The frame (:func:`perscli.render.run._render_frame`).
    hdus : tuple of str
        The HDUs asked for (:func:`check_hdus`); PERSIST only with persistence.
    source_params : dict
        What persisted (:func:`_source_params`), the PERSIST HDU's cards.

    Returns
    -------
    list of OutHDU
    """
    result = drawn.result
    gain = model.value("gain", "gain", off=1.0)
    well = model.value("saturation", "full_well")
    common = _wcs_cards(drawn.optics, exposure.full_bounds)
    sci_cards = common + _exposure_cards(exposure, drawn.optics, seed, drawn.unit, gain) + [
        format_card("SKYRATE", drawn.sky_rate or 0.0, "[e-/pixel/s] sky background used"),
        format_card("NOBJ", drawn.nobj, "objects drawn")]
    e_cards = common + _exposure_cards(exposure, drawn.optics, seed, "electron", 1.0)
    source_cards = [format_card(k, v, c) for k, (v, c) in source_params.items()]
    out = [OutHDU([format_card("SIMPLE", True), format_card("BITPIX", 8), format_card("NAXIS", 0),
                   format_card("EXTEND", True)])]

    def image(data, name, cards, dtype=np.float32):
        return OutHDU(list(cards), np.asarray(data, dtype=dtype), extname=name)

    if "SCI" in hdus:
        out.append(image(result.sci, "SCI", sci_cards))
    if "IDEAL" in hdus:
        out.append(image(result.ideal, "IDEAL", e_cards))
    if "FLUENCE" in hdus:
        out.append(image(result.fluence, "FLUENCE", e_cards + [
            format_card("CONTENT", "charge collected, after saturation",
                        "what persists for source all or a threshold"),
            format_card("SATWELL", float(well) if well is not None else 0.0,
                        "[e-] full well FLUENCE is clipped at (0: none)")]))
    if "DRAWN" in hdus:
        out.append(image(drawn.drawn_light, "DRAWN", e_cards + [
            format_card("CONTENT", "expected electrons of every object drawn", "what persists for source drawn"),
            format_card("COMMENT", "galaxies and stars, no sky, noise-free, not clipped at the well: the"),
            format_card("COMMENT", "persistence cap (fluence_cap) applies when it is used")]))
    if "STARFLU" in hdus:
        out.append(image(drawn.star_light, "STARFLU", e_cards + [
            format_card("CONTENT", "expected electrons of the stars alone", "what persists for source stars"),
            format_card("COMMENT", "noise-free, not clipped at the well: the persistence cap applies when used")]))
    if "PERSIST" in hdus and result is not None and result.persistence is not None:
        out.append(image(result.persistence, "PERSIST", e_cards + source_cards))
    if "MODEL" in hdus:
        out.append(_model_hdu(model))
    return out


def _source_params(source: str, threshold, cap) -> dict:
    """Header keywords saying what of the earlier exposures persisted: KEY -> (value, comment)."""
    params = {"PS_SRC": (source, "persisting: drawn, stars (STARFLU), all (FLUENCE), threshold")}
    if threshold is not None:
        params["PS_THR"] = (float(threshold), "[e-] only FLUENCE above this persisted")
    params["PS_CAP"] = (float(cap) if cap is not None else "none", "[e-] fluence fed to the law clipped here")
    return params


def _model_hdu(model: DetectorModel) -> OutHDU:
    """The resolved detector model as a MODEL table: one row per effect parameter, in physical order.

    ``perscli render --model FRAME.fits`` (:func:`~perscli.detector.model.load_detector_model`)
    reads it back; values are JSON text, so every digit survives.
    """
    data, units = model_table(model)
    cards = [format_card("COMMENT", "the detector model that made this frame, one row per parameter in physical"),
             format_card("COMMENT", "order (VALUE: JSON); perscli render --model THIS.fits reproduces it")]
    return OutHDU(cards, data, extname="MODEL", units=units)


def _provenance(primary: OutHDU, truth, truth_datasum, exposure: Exposure, model: DetectorModel, seed, opened,
                used, source_params=None, sky_rate=None, nobj=None, hdus=()):
    params = {
        "DETMODEL": (os.path.basename(model.source)[-68:], "detector model given; as resolved: MODEL table"),
        "FILTER": exposure.filter, "SCA": exposure.sca,
    }
    params["DETNEFF"] = (len(model.effects), "effects in the MODEL table, in physical order")
    if sky_rate is not None:
        params["SKYRATE"] = (float(sky_rate), "[e-/pixel/s] sky background used")
    if nobj is not None:
        params["NOBJ"] = (int(nobj), "objects drawn")
    if hdus:
        params["HDUS"] = (",".join(hdus), "HDUs asked for (PERSIST only with earlier ones)")
    params.update(source_params or {})
    inputs = [("TRUTH", truth, truth_datasum)]
    for i, frame in enumerate(opened, 1):
        inputs.append((f"PRV{i:02d}", frame.name,
                       frame.datasum(frame.provenance_hdu)))
    for i, gap in enumerate(used, 1):
        params[f"PSP{i:02d}DT"] = (round(gap, 6), "[s] delay after an earlier exposure")
    add_provenance(primary, step=f"render sca={exposure.sca} filter={exposure.filter} mjd={exposure.mjd} "
                                 f"model={model.source} previous={len(opened)}",
                   params=params, inputs=inputs, seed=seed)
