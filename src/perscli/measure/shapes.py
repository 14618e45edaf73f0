"""Shapes of catalogue objects on frames: stamps, noise model, PSF, fits, catalogue out.

For each frame and each catalogue object on it: a stamp around the object's
position (ra/dec through the frame's WCS, or x/y), the background removed,
weights from a weight/variance HDU or from the frame's noise model, and a fit
(:func:`perscli.measure.fit.fit_exp`, or GalSim's HSM for comparison).

Everything that enters a fit (start, weights, background) depends only on the
catalogue and the frame's headers, never on the noise of its pixels, so that
two frames that differ by a small pattern (persistence) give shape changes
that are that pattern's effect alone.
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass

import numpy as np

from .. import PerscliError
from ..instrument import ROMAN_PIXEL_SCALE
from .fit import FLAG_EDGE, P_EXP, ExpModel, fit_exp

log = logging.getLogger(__name__)

#: Flag bits of the output (``flags`` column), documented in the command's help.
FLAGS = {
    1: "fit did not converge",
    2: "stamp runs off the frame (pixels outside are ignored)",
    4: "size T <= 0",
    8: "flux <= 0",
    16: "too few usable pixels (fewer than 20)",
    32: "|g| reached 1",
    64: "normal matrix singular: no errors",
    128: "HSM failed",
    256: "object outside the frame",
    512: "another catalogue object within --blend-radius pixels",
    1024: "centre moved more than 3 pixels from the catalogue position",
    2048: "S/N below 5",
}
FLAG_OFF_FRAME = 256
FLAG_HSM = 128
FLAG_BLEND = 512
FLAG_MOVED = 1024
FLAG_LOW_SN = 2048
MAX_MOVE = 3.0
MIN_S2N = 5.0

#: mean of the mixture's second moment per axis in units of r_e^2: T = 2 r_e^2 * this
_MIXTURE_MOMENT = float(np.sum(P_EXP * (np.array([0.05072, 0.13756, 0.28781, 0.53195, 0.91209, 1.50157]) ** 2)))


@dataclass
class NoiseModel:
    """Background level and variance per pixel, in the frame's units."""

    background: float
    variance: float
    source: str
    detector: str = ""       # where read noise, dark current and gain came from


def frame_detector_model(frame):
    """The detector model that made ``frame`` (its MODEL table, written by ``perscli render``),
    else the default Roman model: ``(DetectorModel, 'MODEL' or 'roman')``."""
    from ..detector.effects import default_model, model_of_frame

    model = model_of_frame(frame)
    return (model, "MODEL") if model is not None else (default_model(), "roman")


def noise_model(frame, *, sky=None, read_noise=None, dark=None) -> NoiseModel:
    """Background and variance from the frame's headers (never from its pixels).

    Read noise, dark current and gain come from the detector model that made
    the frame (:func:`frame_detector_model`): its read_noise.sigma,
    dark.current and gain.gain (0, 0 and the header's GAIN or 1 for effects
    that are off), or the default Roman model's for frames perscli did not
    render.

    Parameters
    ----------
    frame : perscli.io.frames.Frame
    sky : float, optional
        Background in the frame's units per pixel; default SKYRATE x EXPTIME
        (what ``perscli render`` writes) plus dark current.
    read_noise : float, optional
        Electrons; overrides the model's.
    dark : float, optional
        Dark current, e-/pixel/s; overrides the model's.
    """
    detector, where = frame_detector_model(frame)
    if read_noise is None:
        read_noise = detector.value("read_noise", "sigma", off=0.0)
    if dark is None:
        dark = detector.value("dark", "current", off=0.0)
    if where == "MODEL":
        gain = detector.value("gain", "gain", off=None) or frame.gain or 1.0
    else:
        gain = frame.gain or detector.value("gain", "gain", off=None) or 1.0
    exptime = frame.exptime
    is_dn = frame.unit in ("DN", "DN/s")
    to_units = 1.0 / gain if is_dn else 1.0
    if frame.unit.endswith("/s"):
        raise PerscliError(f"{frame.label}: measure needs a frame in electrons or DN, not a rate ({frame.unit})")
    rate = frame.keyword("SKYRATE")
    if sky is None:
        if rate is None or exptime is None:
            raise PerscliError(f"{frame.label}: no SKYRATE/EXPTIME in the header for the noise model; "
                               "give --sky LEVEL (frame units per pixel) or a WHT/VAR/ERR extension")
        sky_e = (float(rate) + dark) * exptime
        background = sky_e * to_units
        source = "SKYRATE"
    else:
        background = float(sky)
        sky_e = background / to_units
        source = "--sky"
    variance_e = max(sky_e, 0.0) + read_noise ** 2
    return NoiseModel(background=background, variance=variance_e * to_units ** 2, source=source, detector=where)


def _weight_hdu(frame):
    for hdu in frame.hdus:
        if hdu.name in ("WHT", "WEIGHT", "IVAR", "VAR", "VARIANCE", "ERR") and hdu.data_size:
            if hdu.shape[-2:] == frame.shape:
                return hdu
    return None


def frame_wcs(frame):
    """astropy WCS of the frame's science header (with SIP), or None."""
    from astropy.io import fits
    from astropy.wcs import WCS

    header = fits.Header.fromstring("".join(frame.header.cards))
    if "CTYPE1" not in header:
        return None
    import warnings

    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        return WCS(header)


def psf_profile(spec: str, frame, *, pixel_scale: float):
    """The PSF as a GalSim profile in the frame's pixel units.

    Parameters
    ----------
    spec : str
        'roman': galsim.roman.getPSF for the frame's SCA and FILTER at the SCA
        centre and the filter's effective wavelength (what ``perscli render``
        draws with).  Otherwise a FITS image of the optical PSF (without the
        pixel response) with its pixel scale in PIXSCALE (arcsec) or CDELT1
        (degrees); it must be Nyquist sampled (for Roman, 2x or finer; 4x
        reaches the accuracy targets) and is interpolated with a quintic kernel.
    pixel_scale : float
        The frame's pixel scale, arcsec.
    """
    import galsim

    if spec == "roman":
        import galsim.roman as roman

        sca, filt = frame.keyword("SCA"), frame.keyword("FILTER")
        if sca is None or filt is None:
            raise PerscliError(f"{frame.label}: --psf roman needs SCA and FILTER in the header; give --psf PSF.fits")
        bandpasses = roman.getBandpasses(AB_zeropoint=True)
        if str(filt).strip() not in bandpasses:
            raise PerscliError(f"{frame.label}: FILTER={filt!r} is not a Roman filter; give --psf PSF.fits")
        bp = bandpasses[str(filt).strip()]
        psf = roman.getPSF(int(sca), str(filt).strip(), wavelength=bp.effective_wavelength)
        return galsim.PixelScale(roman.pixel_scale).toImage(psf)
    from ..io.frames import open_frame

    try:
        image = open_frame(spec, units="electron")
    except PerscliError as exc:
        raise PerscliError(f"--psf: {exc}") from None
    try:
        data = image.planes()[0].astype(np.float64)
        scale = image.keyword("PIXSCALE")
        if scale is None and image.keyword("CDELT1") is not None:
            scale = abs(float(image.keyword("CDELT1"))) * 3600.0
        if scale is None:
            raise PerscliError(f"{spec}: no PIXSCALE (arcsec) or CDELT1 (deg) keyword: the PSF image's pixel "
                               "scale is needed")
    finally:
        image.close()
    if not np.all(np.isfinite(data)) or data.sum() <= 0:
        raise PerscliError(f"{spec}: the PSF image has non-finite values or no positive flux")
    return galsim.InterpolatedImage(galsim.Image(data, scale=float(scale) / pixel_scale),
                                    x_interpolant="quintic", normalization="flux")


def read_positions(path: str):
    """id, and ra/dec (degrees) or x/y (pixels, 1-indexed FITS convention), plus hlr and mag columns if present."""
    from ..io.tables import read_table

    table = read_table(path, what="catalogue (id and ra/dec or x/y)")
    names = {n.lower() for n in table.names}
    out = {"id": table.column("id", kind="integer", needed=("id", "ra", "dec"))}
    if {"ra", "dec"} <= names:
        out["ra"] = table.column("ra").astype(np.float64)
        out["dec"] = table.column("dec").astype(np.float64)
    elif {"x", "y"} <= names:
        out["x"] = table.column("x").astype(np.float64)
        out["y"] = table.column("y").astype(np.float64)
    else:
        raise PerscliError(f"{table.label}: the catalogue needs ra/dec (degrees) or x/y (pixels) columns")
    for optional in ("hlr", "kind"):
        if optional in names:
            out[optional] = table.column(optional, kind="text" if optional == "kind" else "number")
    mags = [n for n in table.names if n.lower().startswith("mag_")]
    for name in mags:
        out[name.lower()] = table.column(name).astype(np.float64)
    out["label"], out["datasum"] = table.label, table.datasum
    for key in ("ra", "dec", "x", "y"):
        if key in out and not np.all(np.isfinite(out[key])):
            bad = int((~np.isfinite(out[key])).sum())
            raise PerscliError(f"{table.label}: column {key} has {bad} non-finite value(s); drop those rows")
    return out


def start_point(cat, i, x, y, frame, pixel_scale):
    """The fit's starting point from the catalogue and the frame's header only.

    Returns the start and whether its flux came from the catalogue (a
    magnitude through ZPT_AB); without one the caller solves for the flux.
    """
    hlr = float(cat["hlr"][i]) if "hlr" in cat and np.isfinite(cat["hlr"][i]) and cat["hlr"][i] > 0 else 0.3
    T0 = 2.0 * (hlr / pixel_scale) ** 2 * _MIXTURE_MOMENT
    zpt, filt = frame.keyword("ZPT_AB"), frame.keyword("FILTER")
    mag_col = f"mag_{str(filt).strip().lower()}" if filt else None
    if zpt is not None and mag_col in cat and frame.exptime:
        import galsim.roman as roman

        electrons = 10 ** (-0.4 * (cat[mag_col][i] - float(zpt))) * roman.collecting_area * frame.exptime
        flux0 = electrons / (frame.gain or 1.0) if frame.unit == "DN" else electrons
        if np.isfinite(flux0) and flux0 > 1e-6:
            return (x, y, 0.0, 0.0, T0, float(flux0)), True
    return (x, y, 0.0, 0.0, T0, 1.0), False


def _linear_flux(model, start, img, wt) -> float:
    """Least-squares flux of the start profile (flux is a linear parameter), for starts without a catalogue flux."""
    unit = model.image(start)
    num, den = float(np.sum(wt * img * unit)), float(np.sum(wt * unit * unit))
    flux = num / den if den > 0 else 0.0
    return flux if np.isfinite(flux) and flux > 0 else 1000.0


def blended(x, y, radius: float) -> np.ndarray:
    """True for catalogue objects with another object within ``radius`` pixels."""
    from scipy.spatial import cKDTree

    pts = np.column_stack([x, y])
    ok = np.all(np.isfinite(pts), axis=1)
    out = np.zeros(len(x), dtype=bool)
    if ok.sum() > 1 and radius > 0:
        tree = cKDTree(pts[ok])
        counts = np.array([len(n) for n in tree.query_ball_point(pts[ok], radius)])
        out[np.flatnonzero(ok)] = counts > 1
    return out


@dataclass
class _FrameFacts:
    """The header values :func:`start_point` reads, detached from the open file (picklable)."""

    label: str
    unit: str
    gain: float | None
    exptime: float | None
    keywords: dict

    @classmethod
    def of(cls, frame):
        return cls(frame.label, frame.unit, frame.gain, frame.exptime,
                   {k: frame.keyword(k) for k in ("ZPT_AB", "FILTER")})

    def keyword(self, name):
        return self.keywords.get(name)


@dataclass
class FrameContext:
    """Everything the fit of one object on a frame needs, read once by the parent (see :func:`measure_object`).

    Handed to the worker processes of :func:`perscli.executor.run`: the
    frame's pixels are read by the parent (from a file or standard input)
    and never reopened by name.
    """

    data: np.ndarray
    weights: np.ndarray
    x: np.ndarray
    y: np.ndarray
    blends: np.ndarray
    background: float
    cat: dict
    frame: _FrameFacts
    pixel_scale: float
    method: str
    stamp: int
    model: object = None
    psf_image: object = None


#: float columns of one object's measurement, and the integer ones
_FLOAT_COLUMNS = ("x", "y", "g1", "g2", "T", "flux", "x_err", "y_err", "g1_err", "g2_err", "T_err", "flux_err",
                  "s2n", "chi2")
_INT_COLUMNS = ("nfev", "flags")


def measure_object(ctx: FrameContext, i: int) -> dict:
    """Fit catalogue object ``i`` on the frame of ``ctx``: its columns, as 1-element arrays."""
    cols = {k: np.full(1, np.nan) for k in _FLOAT_COLUMNS}
    cols.update({k: np.zeros(1, dtype=np.int32) for k in _INT_COLUMNS})
    data, weights, stamp, model = ctx.data, ctx.weights, ctx.stamp, ctx.model
    ny, nx = data.shape
    half = stamp // 2
    # 0-indexed array coordinates of the object (FITS pixel 1 is index 0)
    xi, yi = float(ctx.x[i]) - 1.0, float(ctx.y[i]) - 1.0
    ix, iy = int(math.floor(xi + 0.5)), int(math.floor(yi + 0.5))
    x0, y0 = ix - half, iy - half
    if not (0 <= ix < nx and 0 <= iy < ny):
        cols["flags"][0] = FLAG_OFF_FRAME
        return cols
    a0, a1, b0, b1 = max(x0, 0), min(x0 + stamp, nx), max(y0, 0), min(y0 + stamp, ny)
    img = np.zeros((stamp, stamp))
    wt = np.zeros((stamp, stamp))
    img[b0 - y0:b1 - y0, a0 - x0:a1 - x0] = data[b0:b1, a0:a1] - ctx.background
    wt[b0 - y0:b1 - y0, a0 - x0:a1 - x0] = weights[b0:b1, a0:a1]
    edge = FLAG_EDGE if (a0, b0, a1, b1) != (x0, y0, x0 + stamp, y0 + stamp) else 0
    edge |= FLAG_BLEND if ctx.blends[i] else 0
    if ctx.method == "exp":
        start, from_catalogue = start_point(ctx.cat, i, xi - x0, yi - y0, ctx.frame, ctx.pixel_scale)
        if not from_catalogue:
            start = start[:5] + (_linear_flux(model, start, img, wt),)
        res = fit_exp(img, wt, model, start)
        th, er = res.theta, res.errors
        cols["x"][0], cols["y"][0] = th[0] + x0 + 1.0, th[1] + y0 + 1.0
        for j, key in enumerate(("g1", "g2", "T", "flux"), 2):
            cols[key][0] = th[j]
            cols[f"{key}_err"][0] = er[j]
        cols["x_err"][0], cols["y_err"][0] = er[0], er[1]
        cols["s2n"][0], cols["chi2"][0], cols["nfev"][0] = res.s2n, res.chi2, res.nfev
        moved = math.hypot(th[0] - start[0], th[1] - start[1]) > MAX_MOVE
        cols["flags"][0] = (res.flags | edge | (FLAG_MOVED if moved else 0)
                            | (FLAG_LOW_SN if not res.s2n >= MIN_S2N else 0))
    else:
        _hsm(img, wt, ctx.psf_image, cols, 0, x0, y0, edge)
    return cols


def measure_frame(frame, cat, *, psf="roman", method="exp", stamp=48, sky=None, read_noise=None,
                  blend_radius=4.0, progress=None, workers: int = 1) -> dict:
    """Measure every catalogue object on one frame.

    The frame is read here, once; the objects are fitted by
    :func:`measure_object` on ``workers`` processes
    (:func:`perscli.executor.run`), with the same results for any number.

    Returns
    -------
    dict of column arrays (one row per catalogue object; objects off the frame are flagged).
    """
    from ..executor import run

    wcs = frame_wcs(frame)
    ny, nx = frame.shape
    if "ra" in cat:
        if wcs is None:
            raise PerscliError(f"{frame.label}: no WCS in the header to place ra/dec; give a catalogue with x/y")
        x, y = wcs.all_world2pix(cat["ra"], cat["dec"], 1)  # FITS: first pixel centre at 1
        ra, dec = cat["ra"], cat["dec"]
    else:
        x, y = cat["x"], cat["y"]
        if wcs is not None:
            ra, dec = wcs.all_pix2world(x, y, 1)
        else:
            ra = dec = np.full(len(x), np.nan)
    pixel_scale = ROMAN_PIXEL_SCALE
    if wcs is not None:
        from astropy.wcs.utils import proj_plane_pixel_scales

        pixel_scale = float(np.mean(proj_plane_pixel_scales(wcs.celestial)) * 3600.0)
    data = np.asarray(frame.planes()[0], dtype=np.float64)
    weight_hdu = _weight_hdu(frame)
    if weight_hdu is not None:
        w = np.asarray(weight_hdu.read(), dtype=np.float64)
        positive = w > 0
        if weight_hdu.name in ("VAR", "VARIANCE"):
            w = np.where(positive, 1.0 / np.where(positive, w, 1.0), 0.0)
        elif weight_hdu.name == "ERR":
            w = np.where(positive, 1.0 / np.where(positive, w, 1.0) ** 2, 0.0)
        weights = w
        if sky is None and frame.keyword("SKYRATE") is None:
            # a frame that carries its own weights and no sky model: taken as sky subtracted
            noise = NoiseModel(background=0.0, variance=float("nan"), source=weight_hdu.name)
        else:
            noise = noise_model(frame, sky=sky, read_noise=read_noise)
    else:
        noise = noise_model(frame, sky=sky, read_noise=read_noise)
        weights = np.full(data.shape, 1.0 / noise.variance)
    weights = np.where(np.isfinite(data), weights, 0.0)
    n = len(x)
    model = ExpModel(psf_profile(psf, frame, pixel_scale=pixel_scale), stamp) if method == "exp" else None
    psf_image = None
    if method == "hsm":
        prof = psf_profile(psf, frame, pixel_scale=pixel_scale)
        import galsim

        psf_image = galsim.Convolve(prof, galsim.Pixel(1.0)).drawImage(nx=stamp, ny=stamp, scale=1.0, method="no_pixel")
    blends = blended(np.asarray(x, dtype=float), np.asarray(y, dtype=float), blend_radius)
    ctx = FrameContext(data=data, weights=weights, x=np.asarray(x, dtype=np.float64),
                       y=np.asarray(y, dtype=np.float64), blends=blends, background=float(noise.background),
                       cat=cat, frame=_FrameFacts.of(frame), pixel_scale=pixel_scale, method=method, stamp=stamp,
                       model=model, psf_image=psf_image)
    rows = run(measure_object, range(n), context=ctx, workers=workers, progress=progress)
    cols = {k: np.full(n, np.nan) for k in _FLOAT_COLUMNS}
    cols.update({k: np.zeros(n, dtype=np.int32) for k in _INT_COLUMNS})
    for i, row in enumerate(rows):
        for key, value in row.items():
            cols[key][i] = value[0]
    cols["id"] = cat["id"]
    cols["ra"], cols["dec"] = np.asarray(ra, dtype=np.float64), np.asarray(dec, dtype=np.float64)
    cols["_noise"] = noise
    return cols


def _hsm(img, wt, psf_image, cols, i, x0, y0, edge):
    import galsim

    try:
        res = galsim.hsm.EstimateShear(galsim.Image(img, scale=1.0), psf_image,
                                       weight=galsim.Image((wt > 0).astype(np.int32), scale=1.0),
                                       shear_est="REGAUSS", strict=True)
    except (galsim.GalSimHSMError, galsim.GalSimError, RuntimeError):
        cols["flags"][i] = FLAG_HSM | edge
        return
    try:
        # EstimateShear leaves moments_centroid unset: the adaptive moments give the centre
        centre = galsim.hsm.FindAdaptiveMom(galsim.Image(img, scale=1.0), strict=True).moments_centroid
    except (galsim.GalSimHSMError, galsim.GalSimError, RuntimeError):
        centre = None
    e1, e2 = res.corrected_e1, res.corrected_e2
    e = math.hypot(e1, e2)
    # REGAUSS returns a distortion e; g = e / (1 + sqrt(1 - e^2)) has the same direction
    factor = 1.0 / (1.0 + math.sqrt(max(1.0 - e * e, 0.0))) if e < 1 else 0.0
    cols["g1"][i], cols["g2"][i] = e1 * factor, e2 * factor
    cols["T"][i] = 2.0 * res.moments_sigma ** 2
    cols["flux"][i] = res.moments_amp
    if centre is not None:
        # GalSim's image origin (1, 1) is stamp index 0, i.e. FITS pixel x0 + 1 of the frame
        cols["x"][i], cols["y"][i] = centre.x + x0, centre.y + y0
    cols["g1_err"][i] = cols["g2_err"][i] = res.corrected_shape_err if res.corrected_shape_err > 0 else np.nan
    cols["flags"][i] = edge | (FLAG_HSM if res.correction_status != 0 else 0)


def measure_files(frames, catalog: str, dest: str, *, psf="roman", method="exp", stamp=48, sky=None,
                  read_noise=None, blend_radius=4.0, workers=1, overwrite=False, progress=None) -> dict:
    """``perscli measure`` as a function: shapes of the catalogue's objects on each frame.

    Writes a FITS file with a SHAPES table (one row per object per frame,
    ``frame`` = index of the frame in the order given) and, for several
    frames, a COMBINED table: per object, the inverse-variance weighted mean
    of g1 and g2 over the frames where its fit has no flag.

    Returns
    -------
    dict
        Summary: rows, unflagged rows, frames.
    """
    from ..io.fitsfile import OutHDU, table_hdu
    from ..io.frames import open_frame
    from ..io.output import add_provenance, check_output, write_hdus

    if method not in ("exp", "hsm"):
        raise PerscliError(f"--method must be exp or hsm, not {method!r}")
    if stamp < 16 or stamp % 2:
        raise PerscliError(f"--stamp {stamp} must be an even number of pixels >= 16")
    frames = list(frames)
    check_output(dest, overwrite=overwrite, inputs=[catalog, *frames, psf if psf != "roman" else None])
    cat = read_positions(catalog)
    tables, inputs, noise_sources = [], [("CAT", catalog, cat["datasum"])], []
    kwargs = dict(psf=psf, method=method, stamp=stamp, sky=sky, read_noise=read_noise, blend_radius=blend_radius)
    for k, name in enumerate(frames):
        frame = open_frame(name)
        try:
            inputs.append((f"FRM{k + 1:02d}", name, frame.datasum(frame.sci[0])))
            cols = measure_frame(frame, cat, progress=progress, workers=workers, **kwargs)
        finally:
            frame.close()
        noise_sources.append(cols.pop("_noise"))
        table = {"id": cols["id"], "frame": np.full(len(cols["id"]), k, dtype=np.int16)}
        table.update({key: cols[key] for key in ("x", "y", "ra", "dec", "g1", "g2", "T", "flux", "x_err", "y_err",
                                                  "g1_err", "g2_err", "T_err", "flux_err", "s2n", "chi2", "nfev",
                                                  "flags")})
        tables.append(table)
    shapes = {key: np.concatenate([np.asarray(t[key]) for t in tables]) for key in tables[0]}
    units = {"x": "pix", "y": "pix", "ra": "deg", "dec": "deg", "T": "pix2", "x_err": "pix", "y_err": "pix",
             "T_err": "pix2"}
    hdus = [OutHDU([]), table_hdu(shapes, "SHAPES", units=units)]
    if len(frames) > 1:
        hdus.append(_combined(shapes))
    params = {"METHOD": (method, "exp (mixture fit) or hsm (REGAUSS)"),
              "PSF": (psf if psf == "roman" else psf.split("/")[-1], "PSF source"),
              "STAMP": (stamp, "[pix] stamp side"), "RDNOISE": (read_noise if read_noise is not None else "model",
                                                            "[e-] read noise ('model': the frame's)"),
              "NFRAMES": (len(frames), "frames measured"), "XTOL": (1e-10, "relative step tolerance"),
              "BLENDRAD": (blend_radius, "[pix] neighbour distance flagged as a blend")}
    for bit, text in FLAGS.items():
        params[f"FLAG{int(math.log2(bit)):02d}"] = (bit, text[:47])
    for k, noise in enumerate(noise_sources, 1):
        params[f"BKG{k:02d}"] = (float(noise.background), f"background of frame {k} ({noise.source})")
    add_provenance(hdus[0], step=f"measure method={method} psf={params['PSF'][0]} frames={len(frames)}",
                   params=params, inputs=inputs)
    write_hdus(hdus, dest, overwrite=overwrite)
    return {"rows": len(shapes["id"]), "good": int(np.sum(shapes["flags"] == 0)), "frames": len(frames)}


def _combined(shapes):
    """Per object: inverse-variance weighted mean g over frames whose fit has no flag."""
    from ..io.fitsfile import table_hdu

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
