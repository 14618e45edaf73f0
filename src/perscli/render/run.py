"""``perscli render`` as a function: catalogue + exposure + detector model -> FITS frame."""

from __future__ import annotations

import logging
import os

import numpy as np

from .. import PerscliError
from ..detector.effects import DetectorModel, model_table, run_chain
from ..io.fitsfile import OutHDU, format_card
from ..io.output import add_provenance, check_output, write_hdus
from .exposure import Exposure, draw_sources, read_truth

log = logging.getLogger(__name__)


def _wcs_cards(optics, bounds) -> list:
    """FITS WCS cards of the exposure's SCA for an image with these bounds."""
    import galsim

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
    import datetime as _dt

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


def render_file(truth: str, exposure: Exposure, dest: str, *, model: DetectorModel, seed: int,
                previous=(), overwrite: bool = False, workers: int = 1, progress=None,
                plot: str | None = None, compress: str = "none") -> dict:
    """Render ``exposure`` of the truth catalogue ``truth`` and write ``dest``.

    Parameters
    ----------
    truth : str
        FITS truth catalogue (``perscli catalog``).
    exposure : Exposure
    dest : str
        Output path or '-'.
    model : DetectorModel
    seed : int
        Seed of every random stream; the same seed gives the same bytes
        (apart from DATE and CHECKSUM).
    previous : sequence of str
        Earlier exposures of the same SCA area (frames perscli rendered: their
        FLUENCE drives the persistence), for the persistence effect.
    overwrite, workers, progress
        As for every command.
    plot : str, optional
        Also write a PNG of the frame and its persistence.
    compress : {'none', 'gzip', 'rice'}
        Lossless tile compression of the images (a full SCA: ~40% of the plain size with gzip).

    Returns
    -------
    dict
        Summary: objects drawn, sky rate, units, persistence maximum.
    """
    from ..io.frames import open_frame

    check_output(dest, overwrite=overwrite, inputs=[truth, *previous])
    if plot:
        check_output(plot, overwrite=overwrite, inputs=[truth, *previous])
        if dest != "-" and os.path.abspath(plot) == os.path.abspath(dest):
            raise PerscliError(f"{plot}: --plot and -o name the same file: choose another name for the figure")
    cols = read_truth(truth, exposure.filter)
    previous = list(previous)
    if previous and not model.enabled("persistence"):
        log.warning("--previous given but the persistence effect is off in the detector model: ignored")
    opened = []
    try:
        for name in previous if model.enabled("persistence") else []:
            opened.append(open_frame(name))
        sources, nobj, optics = draw_sources(cols, exposure, workers=workers, progress=progress)
        xmin, xmax, ymin, ymax = exposure.full_bounds
        pers_info = []

        def persistence():
            # persistence on arrays: the earlier exposures' FLUENCE (electrons) and their end times
            from ..detector.apply import check_earlier
            from ..detector.persistence import order_earlier, persistence_charge
            from ..io.frames import SECONDS_PER_DAY

            pmodel = model.persistence_model()
            for frame in opened:
                check_earlier(frame, label="the exposure being rendered", shape=sources.shape, detector=exposure.sca,
                              offsets=(1 - xmin, 1 - ymin), start=exposure.mjd)
            # seconds from the start of this exposure (negative: before it), differenced in MJD first as
            # apply-persistence does, so that both give the same bits
            start = 0.0
            ends = [(frame.end - exposure.mjd) * SECONDS_PER_DAY for frame in opened]
            keep, _ = order_earlier(ends, start, pmodel, [f.label for f in opened])
            pers_info.extend(start - ends[i] for i in keep)
            fluences = [frame.fluence() for frame in opened]
            for frame in opened:
                frame.verify(frame.fluence_source)
            # the window from the header times, as for any frame read from a file
            window = (exposure.end - exposure.mjd) * SECONDS_PER_DAY
            return persistence_charge([f for f, _ in fluences], ends, start, window, pmodel,
                                      scales=[scale for _, scale in fluences])[0]

        result = run_chain(sources, model, exptime=exposure.exptime, seed=seed, sky_rate=optics.sky_rate,
                           persistence=persistence if opened else None)
        gain = model.value("gain", "gain", off=1.0)
        common = _wcs_cards(optics, exposure.full_bounds)
        sci_cards = common + _exposure_cards(exposure, optics, seed, result.unit, gain) + [
            format_card("SKYRATE", result.sky_rate, "[e-/pixel/s] sky background used"),
            format_card("NOBJ", nobj, "objects drawn")]
        e_cards = common + _exposure_cards(exposure, optics, seed, "electron", 1.0)
        hdus = [OutHDU([format_card("SIMPLE", True), format_card("BITPIX", 8), format_card("NAXIS", 0),
                        format_card("EXTEND", True)])]

        def image(data, name, cards, dtype=np.float32):
            return OutHDU(list(cards), np.asarray(data, dtype=dtype), extname=name)

        hdus.append(image(result.sci, "SCI", sci_cards))
        hdus.append(image(result.ideal, "IDEAL", e_cards))
        hdus.append(image(result.fluence, "FLUENCE", e_cards))
        if result.persistence is not None:
            hdus.append(image(result.persistence, "PERSIST", e_cards))
        hdus.append(_model_hdu(model))
        _provenance(hdus[0], truth, cols["datasum"], exposure, model, seed, opened, pers_info)
        write_hdus(hdus, dest, overwrite=overwrite, compress=compress)
        if plot:
            from ..io.output import atomic_path
            from .plots import frame_figure

            with atomic_path(plot, overwrite=overwrite, suffix=".part.png") as tmp:
                frame_figure(result.sci, tmp, persist=result.persistence, unit=result.unit,
                             title=f"SCA {exposure.sca} {exposure.filter} MJD {exposure.mjd:.5f} seed {seed}")
        return {"objects": nobj, "sky_rate": result.sky_rate, "unit": result.unit,
                "persistence_max": float(result.persistence.max()) if result.persistence is not None else 0.0}
    finally:
        for frame in opened:
            frame.close()


def _model_hdu(model: DetectorModel) -> OutHDU:
    """The resolved detector model as a MODEL table: one row per effect parameter, in physical order.

    ``perscli render --model FRAME.fits`` (:func:`~perscli.detector.effects.load_detector_model`)
    reads it back; values are JSON text, so every digit survives.
    """
    data, units = model_table(model)
    cards = [format_card("COMMENT", "the detector model that made this frame, one row per parameter in physical"),
             format_card("COMMENT", "order (VALUE: JSON); perscli render --model THIS.fits reproduces it")]
    return OutHDU(cards, data, extname="MODEL", units=units)


def _provenance(primary: OutHDU, truth, truth_datasum, exposure: Exposure, model: DetectorModel, seed, opened,
                used):
    params = {
        "DETMODEL": (os.path.basename(model.source)[-68:], "detector model given; as resolved: MODEL table"),
        "FILTER": exposure.filter, "SCA": exposure.sca,
    }
    params["DETNEFF"] = (len(model.effects), "effects in the MODEL table, in physical order")
    inputs = [("TRUTH", truth, truth_datasum)]
    for i, frame in enumerate(opened, 1):
        inputs.append((f"PRV{i:02d}", frame.name,
                       frame.datasum(frame.provenance_hdu)))
    for i, gap in enumerate(used, 1):
        params[f"PSP{i:02d}DT"] = (round(gap, 6), "[s] delay after an earlier exposure")
    add_provenance(primary, step=f"render sca={exposure.sca} filter={exposure.filter} mjd={exposure.mjd} "
                                 f"model={model.source} previous={len(opened)}",
                   params=params, inputs=inputs, seed=seed)
