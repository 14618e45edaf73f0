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
"""

from __future__ import annotations

import logging
import math
import os
from dataclasses import dataclass

import numpy as np

from .. import PerscliError
from ..instrument import ROMAN_PIXEL_SCALE
from .fit import FLAG_EDGE, P_EXP, ExpModel, JointStamp, fit_exp, fit_joint
from .psf import PsfOptions, psf_hdus, psf_model

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
    256: "object outside the frame (rows with --all-rows)",
    512: "another catalogue object within --blend-radius pixels",
    1024: "centre moved more than 3 pixels from the catalogue position",
    2048: "S/N below 5",
    4096: "predicted S/N below --min-snr, not fitted",
}
FLAG_OFF_FRAME = 256
FLAG_HSM = 128
FLAG_BLEND = 512
FLAG_MOVED = 1024
FLAG_LOW_SN = 2048
FLAG_BELOW_CUT = 4096
MAX_MOVE = 3.0
MIN_S2N = 5.0
#: default cut on the predicted S/N (:func:`predicted_snr`).  Why 5: the fitted flux S/N (flux / its
#: error, what flag 2048 tests against 5) is ~0.6 of the predicted optimal S/N, so a galaxy predicted
#: below 5 is fitted at S/N ~3 and is flagged 2048 unless noise lifts it: on a full J129 SCA at the
#: paper's densities 921 of the 2242 galaxies lie below 5, and 4 of them (0.4%) came out unflagged
#: before the cut, at the cost of 86 model evaluations each (62% of all the fitting).  Their shapes
#: carry no information.
MIN_SNR_DEFAULT = 5.0
#: the catalogue's kinds fitted by default (perscli catalog writes 'galaxy' and 'star')
DEFAULT_KINDS = ("galaxy",)
#: stamps of an exp fit: the smallest side on the ladder 16, 24, 32, ... (up to --stamp) whose half
#: holds STAMP_HLR catalogue half-light radii plus STAMP_MARGIN pixels of PSF (:func:`stamp_side`).
#: Noise-free Roman galaxies of hlr 0.15-0.5" fitted on those stamps are within 4e-4 of their g (within
#: 2e-4 on 48-pixel stamps); a 3-hlr rule would reach 8e-4 on 16-pixel stamps.
STAMP_HLR = 4.0
STAMP_MARGIN = 3.0
STAMP_MIN = 16

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
    """astropy WCS of the frame's science header (with SIP), or None (made once per frame)."""
    cached = getattr(frame, "_measure_wcs", False)
    if cached is not False:
        return cached
    from astropy.io import fits
    from astropy.wcs import WCS

    header = fits.Header.fromstring("".join(frame.header.cards))
    wcs = None
    if "CTYPE1" in header:
        import warnings

        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            wcs = WCS(header)
    try:
        frame._measure_wcs = wcs
    except AttributeError:
        pass
    return wcs


def psf_profile(spec: str, frame, *, pixel_scale: float, options=None):
    """The optical PSF (without the pixel response) as a GalSim profile in the frame's pixel units, flux 1.

    What :class:`~perscli.measure.fit.ExpModel` and
    :class:`~perscli.render.draw.StampDrawer` take with their default
    ``pixel=True``.  ``spec``, ``options``: as for
    :func:`perscli.measure.psf.psf_model`, which the command uses (it also
    takes PSF images that include the pixel response).

    Raises
    ------
    PerscliError
        For a PSF image that includes the pixel response: it has no optical
        profile to give, and applying the pixel to it again would widen it.
    """
    made = psf_model(spec, frame, pixel_scale=pixel_scale, options=options)
    if made.pixel_included:
        raise PerscliError(f"{made.source}: this PSF image includes the pixel response, so it is no optical "
                           "PSF: use perscli.measure.psf.psf_model and ExpModel(..., pixel=False)")
    return made.profile


#: the columns read_positions reads from a catalogue (all optional but id and ra/dec or x/y): what
#: ``--columns`` may map
CATALOG_READS = ("id", "ra", "dec", "x", "y", "hlr", "e1", "e2", "kind", "mag_*")


def read_positions(path: str, *, columns=None):
    """The objects of a catalogue: id, ra/dec (degrees) or x/y (pixels, FITS convention), and what it adds.

    Optional columns read when present: hlr (arcsec), e1 and e2 (only
    checked: the fit starts round), kind (lower-cased) and every mag_*.
    Every value is checked by :func:`perscli.scene.check_catalog`, the check
    ``perscli render`` makes of the same catalogue.

    Parameters
    ----------
    path : str
        The catalogue (``perscli catalog``'s TRUTH table, or any table with
        id and ra/dec or x/y).
    columns : dict, optional
        Column mapping {perscli name: file column} (``--columns``; names of
        :data:`CATALOG_READS`).  Given (even empty), a missing column's
        message suggests the option.

    Returns
    -------
    dict
        The columns by perscli name (mag columns lower-cased), plus ``label``
        and ``datasum`` (for provenance).

    Raises
    ------
    PerscliError
        Unreadable, without id or positions, a mapping of a column perscli
        does not read, or values no object can have (repeated ids, positions
        off the sky, hlr < 0, |e| >= 1, ...).
    """
    from ..io.tables import read_table
    from ..scene import check_catalog

    table = read_table(path, what="catalogue (id and ra/dec or x/y)", columns=columns, known=CATALOG_READS)
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
    for optional in ("hlr", "kind", "e1", "e2"):
        if optional in names:
            out[optional] = table.column(optional, kind="text" if optional == "kind" else "number")
    if "kind" in out:
        out["kind"] = np.char.lower(out["kind"])
    mags = [n for n in table.names if n.lower().startswith("mag_")]
    for name in mags:
        out[name.lower()] = table.column(name).astype(np.float64)
    out["label"], out["datasum"] = table.label, table.datasum
    for key in ("ra", "dec", "x", "y"):
        if key in out and not np.all(np.isfinite(out[key])):
            bad = int((~np.isfinite(out[key])).sum())
            raise PerscliError(f"{table.label}: column {key} has {bad} non-finite value(s); drop those rows")
    # the values render would refuse are refused here too (one check for both): repeated ids (whose SHAPES
    # rows correlate refuses), RA/Dec off the sky (WCS tracebacks), negative or zero sizes, |e| >= 1
    check_catalog(table.label, out, header=table.header)
    return out


def select_kinds(cat, kinds=None):
    """Indices of the catalogue rows to measure, and a description for the header.

    Parameters
    ----------
    cat : dict
        From :func:`read_positions`.
    kinds : None, 'all', or sequence of str
        None: the galaxies (``kind == 'galaxy'``) when the catalogue has a
        kind column, every row when it has none.  'all': every row.  A
        list (or a comma-separated string): the rows of those kinds; the
        catalogue must have a kind column.

    Raises
    ------
    PerscliError
        Kinds asked for of a catalogue without a kind column, or a kind that
        is neither in the catalogue nor one perscli writes.
    """
    n = len(cat["id"])
    if isinstance(kinds, str):
        kinds = [k for k in (part.strip().lower() for part in kinds.split(",")) if k]
        if kinds == ["all"]:
            kinds = "all"
    elif kinds is not None:
        kinds = [str(k).strip().lower() for k in kinds]
    if kinds == "all" or (kinds is not None and "all" in kinds):
        if kinds != "all" and len(kinds) > 1:
            raise PerscliError(f"--kinds {','.join(kinds)}: 'all' goes alone")
        return np.arange(n), "all"
    if kinds is None:
        if "kind" not in cat:
            return np.arange(n), "all (no kind column)"
        kinds = list(DEFAULT_KINDS)
    elif not kinds:
        raise PerscliError("--kinds is empty: give galaxy, star, a comma-separated list, or all")
    elif "kind" not in cat:
        raise PerscliError(f"{cat.get('label', 'catalogue')}: no kind column to select --kinds "
                           f"{','.join(kinds)} from; give --kinds all (every row) or a catalogue with kind")
    present = sorted(set(np.unique(cat["kind"]).tolist()))
    unknown = [k for k in kinds if k not in present and k not in ("galaxy", "star")]
    if unknown:
        raise PerscliError(f"--kinds {','.join(kinds)}: the catalogue has no kind {', '.join(unknown)} "
                           f"(its kinds: {', '.join(present) or 'none'})")
    return np.flatnonzero(np.isin(cat["kind"], kinds)), ",".join(kinds)


def stamp_ladder(stamp: int) -> list:
    """The stamp sides an exp fit may use with ``--stamp``: 16, 24, ... below it, and it."""
    return sorted({n for n in range(STAMP_MIN, stamp, 8)} | {int(stamp)})


def stamp_side(cat, i, pixel_scale, ladder) -> int:
    """The stamp side for catalogue row ``i``: the smallest on ``ladder`` that holds the galaxy.

    Why smaller stamps: the model's cost goes with the FFT grid (side + 16)
    squared, and a small galaxy's stamp needs no more than its light (~99%
    within 4 half-light radii of an exponential) and the PSF's core; a
    48-pixel stamp around a 0.2" galaxy mostly holds sky and neighbours,
    which pull faint fits away (flag 1024).  Large galaxies keep --stamp.
    """
    hlr = float(cat["hlr"][i]) if "hlr" in cat and np.isfinite(cat["hlr"][i]) and cat["hlr"][i] > 0 else 0.3
    radius = STAMP_HLR * hlr / pixel_scale + STAMP_MARGIN
    for n in ladder:
        if n / 2 >= radius:
            return n
    return ladder[-1]


def _start_size(cat, i, pixel_scale):
    """T of the start, pixel^2 (arcsec^2 for pixel_scale 1): from the catalogue hlr, else 0.3\"."""
    hlr = float(cat["hlr"][i]) if "hlr" in cat and np.isfinite(cat["hlr"][i]) and cat["hlr"][i] > 0 else 0.3
    return 2.0 * (hlr / pixel_scale) ** 2 * _MIXTURE_MOMENT


def catalogue_rate(cat, i, frame) -> float:
    """The object's flux in e-/s from its catalogue magnitude in the frame's FILTER through ZPT_AB (NaN without)."""
    zpt, filt = frame.keyword("ZPT_AB"), frame.keyword("FILTER")
    mag_col = f"mag_{str(filt).strip().lower()}" if filt else None
    if zpt is None or mag_col not in cat:
        return float("nan")
    import galsim.roman as roman

    rate = 10 ** (-0.4 * (float(cat[mag_col][i]) - float(zpt))) * roman.collecting_area
    return float(rate) if np.isfinite(rate) else float("nan")


def frame_units_per_rate(frame) -> float | None:
    """Frame units per e-/s of source: the exposure time (divided by the gain for a frame in DN)."""
    if not frame.exptime:
        return None
    return frame.exptime / (frame.gain or 1.0) if frame.unit == "DN" else frame.exptime


def start_point(cat, i, x, y, frame, pixel_scale):
    """The fit's starting point from the catalogue and the frame's header only.

    Returns the start and whether its flux came from the catalogue (a
    magnitude through ZPT_AB); without one the caller solves for the flux.
    """
    T0 = _start_size(cat, i, pixel_scale)
    per_rate = frame_units_per_rate(frame)
    flux0 = catalogue_rate(cat, i, frame) * per_rate if per_rate else float("nan")
    if np.isfinite(flux0) and flux0 > 1e-6:
        return (x, y, 0.0, 0.0, T0, float(flux0)), True
    return (x, y, 0.0, 0.0, T0, 1.0), False


def _linear_flux(model, start, img, wt) -> float:
    """Least-squares flux of the start profile (flux is a linear parameter), for starts without a catalogue flux."""
    unit = model.image(start[:5] + (1.0,))
    num, den = float(np.sum(wt * img * unit)), float(np.sum(wt * unit * unit))
    flux = num / den if den > 0 else 0.0
    return flux if np.isfinite(flux) and flux > 0 else 1000.0


def _snr_table(model):
    """The :class:`SnrTable` of a model, made once."""
    table = getattr(model, "_snr_table", None)
    if table is None:
        table = model._snr_table = SnrTable(model)
    return table


class SnrTable:
    """sum(p^2) of a round, centred exponential of size T through one PSF, for :func:`predicted_snr`.

    The optimal S/N of a galaxy of flux F on a background of variance V per
    pixel is F sqrt(sum(p^2) / V), p its normalised image; sum(p^2) depends
    on T only (for a round galaxy) and is tabulated once per PSF, 0.005-20000
    pixel^2, interpolated in log-log.
    """

    def __init__(self, model: ExpModel):
        self.logT = np.linspace(np.log(5e-3), np.log(2e4), 121)
        c = float(model.n // 2)
        values = []
        for T in np.exp(self.logT):
            img = model.image((c, c, 0.0, 0.0, float(T), 1.0))
            values.append(float(np.sum(img * img)))
        self.logS = np.log(np.maximum(values, 1e-300))

    def __call__(self, T) -> np.ndarray:
        logT = np.log(np.clip(np.asarray(T, dtype=np.float64), 5e-3, 2e4))
        return np.exp(np.interp(logT, self.logT, self.logS))


def predicted_snr(cat, rows, frame, pixel_scale, table: SnrTable, ivar) -> np.ndarray:
    """The optimal S/N of catalogue rows on a frame, predicted without looking at its pixels.

    F sqrt(sum(p^2) ivar): F the catalogue magnitude in the frame's FILTER
    through ZPT_AB and the exposure time (frame units), p the normalised
    image of the round exponential of the catalogue's hlr (0.3" without
    one) through the frame's PSF (:class:`SnrTable`), ivar the inverse
    variance per pixel: sky, dark current and read noise of the noise model
    (:func:`noise_model`), or the frame's weight map at the object.  The
    source's own Poisson noise is left out (it matters only far above any
    cut).  NaN where the catalogue has no magnitude (or the frame no
    ZPT_AB/EXPTIME): such objects are not cut.
    """
    rows = np.asarray(rows, dtype=np.int64)
    per_rate = frame_units_per_rate(frame)
    out = np.full(len(rows), np.nan)
    if not per_rate:
        return out
    T = np.array([_start_size(cat, i, pixel_scale) for i in rows])
    rate = np.array([catalogue_rate(cat, i, frame) for i in rows])
    flux = rate * per_rate
    with np.errstate(invalid="ignore"):
        out = flux * np.sqrt(table(T) * np.asarray(ivar, dtype=np.float64))
    return np.where(np.isfinite(out), np.maximum(out, 0.0), np.nan)


def blended(x, y, radius: float, shape=None) -> np.ndarray:
    """True for catalogue objects with another object within ``radius`` pixels.

    ``shape`` (ny, nx): only objects on a frame of that shape or within
    ``radius`` of it are looked at (the others are False): a catalogue of a
    million objects around a frame costs seconds otherwise, and only the
    objects on the frame are fitted.
    """
    from scipy.spatial import cKDTree

    pts = np.column_stack([x, y])
    ok = np.all(np.isfinite(pts), axis=1)
    if shape is not None:
        reach = radius + 1.0
        with np.errstate(invalid="ignore"):
            ok &= (pts[:, 0] >= 0.5 - reach) & (pts[:, 0] <= shape[1] + 0.5 + reach) \
                & (pts[:, 1] >= 0.5 - reach) & (pts[:, 1] <= shape[0] + 0.5 + reach)
    out = np.zeros(len(x), dtype=bool)
    if ok.sum() > 1 and radius > 0:
        tree = cKDTree(pts[ok])
        counts = np.array([len(n) for n in tree.query_ball_point(pts[ok], radius)])
        out[np.flatnonzero(ok)] = counts > 1
    return out


def blended_on_sky(ra, dec, radius_arcsec: float) -> np.ndarray:
    """True for objects with another within ``radius_arcsec`` (chord distance on the unit sphere)."""
    ra_r, dec_r = np.radians(ra), np.radians(dec)
    xyz = np.column_stack([np.cos(dec_r) * np.cos(ra_r), np.cos(dec_r) * np.sin(ra_r), np.sin(dec_r)])
    from scipy.spatial import cKDTree

    out = np.zeros(len(ra), dtype=bool)
    if len(ra) > 1 and radius_arcsec > 0:
        chord = 2.0 * np.sin(np.radians(radius_arcsec / 3600.0) / 2.0)
        counts = np.array([len(n) for n in cKDTree(xyz).query_ball_point(xyz, chord)])
        out = counts > 1
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
                   {k: frame.keyword(k) for k in ("ZPT_AB", "FILTER", "SCA")})

    def keyword(self, name):
        return self.keywords.get(name)


@dataclass
class FrameContext:
    """Everything the fit of one object on a frame needs, read once by the parent (see :func:`measure_object`).

    Handed to the worker processes of :func:`perscli.executor.run`: the
    frame's pixels are read by the parent (from a file or standard input)
    and never reopened by name.  ``data`` stays in the file's type (float32
    for a rendered frame: half the memory, and no conversion of the whole
    frame); stamps are made float64 as they are cut.  ``weights`` is the
    inverse variance of a WHT/VAR/ERR HDU, or None for the noise model's
    uniform ``ivar``.
    """

    data: np.ndarray
    weights: np.ndarray | None
    ivar: float
    x: np.ndarray
    y: np.ndarray
    blends: np.ndarray
    background: float
    cat: dict
    frame: _FrameFacts
    pixel_scale: float
    method: str
    stamp: int
    models: dict = None        # stamp side -> ExpModel
    sizes: np.ndarray = None   # stamp side of each catalogue row (exp fits)
    psf_image: object = None


def on_frame(x, y, shape) -> np.ndarray:
    """True where FITS pixel position (x, y) falls on a frame of ``shape``: its nearest pixel exists."""
    ny, nx = shape
    ix = np.floor(np.asarray(x, dtype=np.float64) - 0.5)
    iy = np.floor(np.asarray(y, dtype=np.float64) - 0.5)
    with np.errstate(invalid="ignore"):
        return (ix >= 0) & (ix < nx) & (iy >= 0) & (iy < ny)


def cut_stamp(data, weights, ivar, background, stamp, xi, yi):
    """The stamp around 0-indexed position (xi, yi): (image - background, weights, x0, y0, runs off the edge).

    Pixels off the frame and non-finite pixels get weight 0.
    """
    ny, nx = data.shape
    half = stamp // 2
    ix, iy = int(math.floor(xi + 0.5)), int(math.floor(yi + 0.5))
    x0, y0 = ix - half, iy - half
    a0, a1, b0, b1 = max(x0, 0), min(x0 + stamp, nx), max(y0, 0), min(y0 + stamp, ny)
    img = np.zeros((stamp, stamp))
    wt = np.zeros((stamp, stamp))
    sub = np.asarray(data[b0:b1, a0:a1], dtype=np.float64)
    finite = np.isfinite(sub)
    img[b0 - y0:b1 - y0, a0 - x0:a1 - x0] = sub - background
    if weights is None:
        wt[b0 - y0:b1 - y0, a0 - x0:a1 - x0] = np.where(finite, ivar, 0.0)
    else:
        wt[b0 - y0:b1 - y0, a0 - x0:a1 - x0] = np.where(finite, weights[b0:b1, a0:a1], 0.0)
    edge = (a0, b0, a1, b1) != (x0, y0, x0 + stamp, y0 + stamp)
    return img, wt, x0, y0, edge


def stamp_window(shape, stamp, xi, yi) -> tuple:
    """The part of a frame of ``shape`` that :func:`cut_stamp` reads for a stamp at (xi, yi): (b0, b1, a0, a1)."""
    ny, nx = shape
    half = stamp // 2
    x0, y0 = int(math.floor(xi + 0.5)) - half, int(math.floor(yi + 0.5)) - half
    return max(y0, 0), min(y0 + stamp, ny), max(x0, 0), min(x0 + stamp, nx)


class Windows:
    """A frame's pixels kept only inside the stamps to be fitted: what :func:`cut_stamp` reads of it.

    A joint fit over hundreds of frames would otherwise hold every frame
    (67 MB for a 4088^2 float32 SCA); the windows of its galaxies are a few
    percent of that.  Indexing with the slices :func:`stamp_window` gives
    returns the stored pixels; anything else is an error.
    """

    def __init__(self, shape, dtype=np.float32):
        self.shape = tuple(shape)
        self.dtype = np.dtype(dtype)
        self._parts = {}

    def keep(self, data, window) -> None:
        """Store ``data``'s pixels of ``window`` ((b0, b1, a0, a1), e.g. from :func:`stamp_window`)."""
        b0, b1, a0, a1 = window
        self._parts[window] = np.array(data[b0:b1, a0:a1], dtype=self.dtype)

    def __contains__(self, window) -> bool:
        return window in self._parts

    def __getitem__(self, key):
        rows, cols = key
        return self._parts[(rows.start, rows.stop, cols.start, cols.stop)]


#: float columns of one object's measurement, and the integer ones
_FLOAT_COLUMNS = ("x", "y", "g1", "g2", "T", "flux", "x_err", "y_err", "g1_err", "g2_err", "T_err", "flux_err",
                  "s2n", "chi2")
_INT_COLUMNS = ("nfev", "flags")


def measure_object(ctx: FrameContext, i: int) -> dict:
    """Fit catalogue object ``i`` (on the frame) of ``ctx``: its columns, as 1-element arrays."""
    cols = {k: np.full(1, np.nan) for k in _FLOAT_COLUMNS}
    cols.update({k: np.zeros(1, dtype=np.int32) for k in _INT_COLUMNS})
    # 0-indexed array coordinates of the object (FITS pixel 1 is index 0)
    xi, yi = float(ctx.x[i]) - 1.0, float(ctx.y[i]) - 1.0
    n = int(ctx.sizes[i]) if ctx.method == "exp" else ctx.stamp
    img, wt, x0, y0, off_edge = cut_stamp(ctx.data, ctx.weights, ctx.ivar, ctx.background, n, xi, yi)
    edge = (FLAG_EDGE if off_edge else 0) | (FLAG_BLEND if ctx.blends[i] else 0)
    if ctx.method == "exp":
        model = ctx.models[n]
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


#: degrees beyond a frame's half-diagonal: catalogue rows farther from its centre are not placed on it (NaN),
#: as none of them can fall on it, and a catalogue of a study holds a million rows around it
NEAR_FRAME_DEG = 0.5


def frame_xy(wcs, shape, ra, dec):
    """FITS pixel positions (first pixel centre at 1) on a frame of ``shape`` of sky positions (degrees).

    NaN for positions more than :data:`NEAR_FRAME_DEG` beyond the frame's
    half-diagonal from its centre.
    """
    from ..scene import separation

    ra, dec = np.asarray(ra, dtype=np.float64), np.asarray(dec, dtype=np.float64)
    x, y = np.full(ra.shape, np.nan), np.full(ra.shape, np.nan)
    ny, nx = shape
    corners = np.array([[(nx + 1) / 2.0, (ny + 1) / 2.0], [0.5, 0.5], [nx + 0.5, ny + 0.5], [0.5, ny + 0.5],
                        [nx + 0.5, 0.5]])
    (ra0, dec0), *edges = wcs.all_pix2world(corners, 1)
    half = max(float(separation(ra0, dec0, e[0], e[1])) for e in edges)
    with np.errstate(invalid="ignore"):
        near = separation(ra0, dec0, ra, dec) <= half + NEAR_FRAME_DEG
    if near.any():
        x[near], y[near] = wcs.all_world2pix(ra[near], dec[near], 1)
    return x, y


def _frame_positions(frame, cat, wcs):
    """x, y (FITS pixels) and ra, dec of every catalogue row on a frame (x, y NaN far from it)."""
    if "ra" in cat:
        if wcs is None:
            raise PerscliError(f"{frame.label}: no WCS in the header to place ra/dec; give a catalogue with x/y")
        x, y = frame_xy(wcs, frame.shape, cat["ra"], cat["dec"])
        return x, y, cat["ra"], cat["dec"]
    x, y = cat["x"], cat["y"]
    if wcs is not None:
        ra, dec = wcs.all_pix2world(x, y, 1)
    else:
        ra = dec = np.full(len(x), np.nan)
    return np.asarray(x, dtype=np.float64), np.asarray(y, dtype=np.float64), ra, dec


def _pixel_scale(wcs) -> float:
    if wcs is None:
        return ROMAN_PIXEL_SCALE
    from astropy.wcs.utils import proj_plane_pixel_scales

    return float(np.mean(proj_plane_pixel_scales(wcs.celestial)) * 3600.0)


def _noise_and_weights(frame, *, sky, read_noise):
    """(NoiseModel, weight map or None, uniform inverse variance): the noise model of a frame."""
    weight_hdu = _weight_hdu(frame)
    if weight_hdu is None:
        noise = noise_model(frame, sky=sky, read_noise=read_noise)
        return noise, None, 1.0 / noise.variance
    w = np.asarray(weight_hdu.read(), dtype=np.float64)
    positive = w > 0
    if weight_hdu.name in ("VAR", "VARIANCE"):
        w = np.where(positive, 1.0 / np.where(positive, w, 1.0), 0.0)
    elif weight_hdu.name == "ERR":
        w = np.where(positive, 1.0 / np.where(positive, w, 1.0) ** 2, 0.0)
    if sky is None and frame.keyword("SKYRATE") is None:
        # a frame that carries its own weights and no sky model: taken as sky subtracted
        noise = NoiseModel(background=0.0, variance=float("nan"), source=weight_hdu.name)
    else:
        noise = noise_model(frame, sky=sky, read_noise=read_noise)
    return noise, w, float("nan")


def _ivar_at(weights, ivar, x, y) -> np.ndarray:
    """Inverse variance at FITS positions: the uniform value, or the median positive weight within 2 pixels."""
    if weights is None:
        return np.full(len(x), ivar)
    ny, nx = weights.shape
    out = np.zeros(len(x))
    for k, (xx, yy) in enumerate(zip(x, y)):
        ix, iy = int(math.floor(xx - 0.5)), int(math.floor(yy - 0.5))
        box = weights[max(iy - 2, 0):min(iy + 3, ny), max(ix - 2, 0):min(ix + 3, nx)]
        box = box[box > 0]
        out[k] = float(np.median(box)) if box.size else 0.0
    return out


def _check_min_snr(min_snr):
    if min_snr is None:
        return MIN_SNR_DEFAULT
    try:
        value = float(min_snr)
    except (TypeError, ValueError):
        raise PerscliError(f"--min-snr {min_snr!r} is not a number") from None
    if not math.isfinite(value) or value < 0:
        raise PerscliError(f"--min-snr {min_snr} must be a finite number >= 0 (0: fit every object on the frame)")
    return value


def _gather(results, fitted, out_rows, float_columns, int_columns) -> dict:
    """Output columns for ``out_rows``: NaN and 0 where nothing was fitted, each fit's values at its row."""
    n = len(out_rows)
    cols = {k: np.full(n, np.nan) for k in float_columns}
    cols.update({k: np.zeros(n, dtype=np.int32) for k in int_columns})
    where = {int(r): k for k, r in enumerate(out_rows)}
    for r, row in zip(fitted, results):
        k = where[int(r)]
        for key, value in row.items():
            cols[key][k] = value[0]
    return cols


def measure_frame(frame, cat, *, psf="roman", method="exp", stamp=48, sky=None, read_noise=None,
                  blend_radius=4.0, progress=None, workers: int = 1, kinds=None, min_snr=MIN_SNR_DEFAULT,
                  all_rows: bool = False, models=None, psf_options=None, psf_used=None, data=None,
                  only=None) -> dict:
    """Measure the selected catalogue objects on one frame.

    The frame is read here, once; the objects are fitted by
    :func:`measure_object` on ``workers`` processes
    (:func:`perscli.executor.run`), with the same results for any number.

    Parameters
    ----------
    frame : perscli.io.frames.Frame
    cat : dict
        From :func:`read_positions`.
    kinds : None, 'all' or sequence of str
        Which rows (:func:`select_kinds`): by default the galaxies, or every
        row of a catalogue without a kind column.
    min_snr : float
        Objects whose :func:`predicted_snr` is below this are not fitted
        (0: no cut; objects without a predicted S/N are always fitted).
    all_rows : bool
        Also return rows, without fits, for the selected objects off the
        frame (flag 256) and below the cut (flag 4096).
    models : dict, optional
        Stamp side -> ExpModel for this frame's PSF, filled here as needed
        (a cache to share between frames of one SCA and filter).
    psf_options : perscli.measure.psf.PsfOptions, optional
        How to read a PSF image (--psf-pixel, --psf-oversampling,
        --allow-undersampled-psf).
    psf_used : list, optional
        Appended with the :class:`perscli.measure.psf.PsfModel` when this
        call makes the models (for --write-psf).
    data : ndarray, optional
        Pixels to fit instead of the frame's own (same shape; its headers,
        WCS and noise model still come from ``frame``): a variant of the
        frame, such as the same exposure with persistence.
    only : ndarray of bool, optional
        Per catalogue row: fit only these of the selected objects (the
        selection and ``_todo`` are unchanged).
    psf, method, stamp, sky, read_noise, blend_radius, progress, workers
        As for :func:`measure_files`.

    Returns
    -------
    dict of column arrays, one row per object fitted (or, with all_rows, per
    selected object), in catalogue order; '_noise' the noise model,
    '_counts' the numbers selected, on the frame, cut and fitted, and
    '_todo' the catalogue rows selected for a fit (on the frame, above the cut).
    """
    from ..executor import run

    min_snr = _check_min_snr(min_snr)
    rows_sel, _ = select_kinds(cat, kinds)
    wcs = frame_wcs(frame)
    x, y, ra, dec = _frame_positions(frame, cat, wcs)
    pixel_scale = _pixel_scale(wcs)
    noise, weights, ivar = _noise_and_weights(frame, sky=sky, read_noise=read_noise)
    data = np.asarray(frame.planes()[0]) if data is None else data
    if data.dtype.kind != "f":
        data = data.astype(np.float64)
    models = {} if models is None else models
    if stamp not in models:
        models[stamp] = _psf_exp_model(psf, frame, pixel_scale, stamp, psf_options, psf_used)
    model = models[stamp]
    facts = _FrameFacts.of(frame)
    on = on_frame(x[rows_sel], y[rows_sel], data.shape)
    rows_on = rows_sel[on]
    snr = np.full(len(cat["id"]), np.nan)
    snr[rows_on] = predicted_snr(cat, rows_on, facts, pixel_scale, _snr_table(model),
                                 _ivar_at(weights, ivar, x[rows_on], y[rows_on]))
    # objects without a predicted S/N (no magnitude) are fitted: the cut only drops what it can predict
    keep = ~(snr[rows_on] < min_snr)
    selected = rows_on[keep]
    todo = selected if only is None else selected[np.asarray(only, dtype=bool)[selected]]
    psf_image = None
    if method == "hsm":
        import galsim

        # HSM takes the PSF as it appears in pixel values: with the pixel response, once
        drawer = model.drawer
        with_pixel = galsim.Convolve(drawer.psf, galsim.Pixel(1.0)) if drawer.pixel else drawer.psf
        psf_image = with_pixel.drawImage(nx=stamp, ny=stamp, scale=1.0, method="no_pixel")
    # neighbours of any kind count: a star beside a galaxy spoils its shape as much as a galaxy does
    blends = blended(x, y, blend_radius, data.shape)
    sizes = None
    if method == "exp":
        ladder = stamp_ladder(stamp)
        sizes = np.full(len(cat["id"]), stamp, dtype=np.int32)
        for i in todo:
            sizes[i] = stamp_side(cat, i, pixel_scale, ladder)
        for n in sorted(set(sizes[todo].tolist())):
            if n not in models:
                # the PSF's transfer for another grid: milliseconds once GalSim has drawn the PSF once
                models[n] = ExpModel(model.drawer.psf, n, pixel=model.drawer.pixel)
    ctx = FrameContext(data=data, weights=weights, ivar=ivar, x=x, y=y, blends=blends,
                       background=float(noise.background), cat=cat, frame=facts, pixel_scale=pixel_scale,
                       method=method, stamp=stamp, models=models if method == "exp" else None, sizes=sizes,
                       psf_image=psf_image)
    results = run(measure_object, todo, context=ctx, workers=workers, progress=progress)
    out_rows = rows_sel if all_rows else todo
    cols = _gather(results, todo, out_rows, _FLOAT_COLUMNS, _INT_COLUMNS)
    if all_rows:
        fitted = np.isin(out_rows, todo)
        on_all = on_frame(x[out_rows], y[out_rows], data.shape)
        cols["flags"][~on_all] = FLAG_OFF_FRAME
        cols["flags"][on_all & ~fitted] = FLAG_BELOW_CUT
    cols["id"] = cat["id"][out_rows]
    cols["ra"] = np.asarray(ra, dtype=np.float64)[out_rows]
    cols["dec"] = np.asarray(dec, dtype=np.float64)[out_rows]
    cols["snr_pred"] = snr[out_rows]
    cols["_noise"] = noise
    cols["_counts"] = {"selected": len(rows_sel), "on": len(rows_on), "cut": int(len(rows_on) - len(selected)),
                       "fitted": len(todo)}
    cols["_todo"] = selected
    return cols


def _psf_exp_model(psf, frame, pixel_scale, stamp, psf_options, psf_used) -> ExpModel:
    """The ExpModel of a frame's PSF (:func:`perscli.measure.psf.psf_model`) for ``stamp``; the PSF
    appended to ``psf_used``.  A PSF that includes the pixel response is not given it again."""
    made = psf_model(psf, frame, pixel_scale=pixel_scale, options=psf_options)
    if psf_used is not None:
        psf_used.append(made)
    return ExpModel(made.profile, stamp, pixel=not made.pixel_included)


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


# -- joint fits over several frames -------------------------------------------------------------------


def local_ainv(wcs, x, y, ra0, dec0, h: float = 0.5) -> np.ndarray:
    """d(x, y)/d(u, v) at FITS pixel positions (x, y) of objects at (ra0, dec0): pixels per arcsec.

    (u, v) is the gnomonic tangent plane at each object, u to the West, v to
    the North (GalSim's world axes), in arcsec.  The WCS (with SIP) is
    differenced over +-``h`` pixels and the 2 x 2 Jacobian inverted.
    Returns an array of shape (N, 2, 2).
    """
    x = np.asarray(x, dtype=np.float64)
    y = np.asarray(y, dtype=np.float64)
    a0, d0 = np.radians(np.asarray(ra0, dtype=np.float64)), np.radians(np.asarray(dec0, dtype=np.float64))

    def uv(xx, yy):
        ra, dec = wcs.all_pix2world(xx, yy, 1)
        a, d = np.radians(ra), np.radians(dec)
        cosc = np.sin(d0) * np.sin(d) + np.cos(d0) * np.cos(d) * np.cos(a - a0)
        xi = np.cos(d) * np.sin(a - a0) / cosc
        eta = (np.cos(d0) * np.sin(d) - np.sin(d0) * np.cos(d) * np.cos(a - a0)) / cosc
        return -np.degrees(xi) * 3600.0, np.degrees(eta) * 3600.0

    up_x, dn_x, up_y, dn_y = uv(x + h, y), uv(x - h, y), uv(x, y + h), uv(x, y - h)
    jac = np.empty((len(x), 2, 2))
    for a in range(2):
        jac[:, a, 0] = (up_x[a] - dn_x[a]) / (2.0 * h)
        jac[:, a, 1] = (up_y[a] - dn_y[a]) / (2.0 * h)
    return np.linalg.inv(jac)


@dataclass
class JointFrame:
    """One frame of a joint fit, read once by the parent: pixels, noise and where each galaxy falls.

    ``data`` is the frame's pixels, or only the :class:`Windows` of the
    galaxies fitted on it (what :func:`measure_joint` keeps).
    """

    data: object
    weights: np.ndarray | None
    ivar: float
    background: float
    model: int                 # index into JointContext.models (one per SCA and filter)
    per_rate: float            # frame units per e-/s
    x: np.ndarray              # FITS pixels of the selected galaxies
    y: np.ndarray
    on: np.ndarray
    ainv: np.ndarray           # (N, 2, 2), zeros off the frame
    snr: np.ndarray            # predicted S/N, NaN off the frame or without a magnitude
    shape: tuple = ()          # the frame's (ny, nx)


@dataclass
class JointContext:
    """Everything :func:`measure_joint_object` needs (handed to the workers once)."""

    frames: list
    models: list               # per PSF: stamp side -> ExpModel
    cat: dict
    rows: np.ndarray           # catalogue rows of the selected galaxies
    sizes: np.ndarray          # stamp side per selected galaxy
    blends: np.ndarray         # per selected galaxy
    rate_frame: _FrameFacts    # ZPT_AB and FILTER for the catalogue flux
    stamp: int
    pixel_scale: float


_JOINT_FLOAT = ("ra", "dec", "g1", "g2", "T", "flux", "ra_err", "dec_err", "g1_err", "g2_err", "T_err", "flux_err",
                "s2n", "chi2")
_JOINT_INT = ("nframes", "nfev", "flags")


def _joint_linear_flux(stamps, T0) -> float:
    """Least-squares joint flux (e-/s) of the start profile, for galaxies without a catalogue magnitude."""
    from .fit import covariance_map, shape_covariance

    cov, dcov, _ = shape_covariance(0.0, 0.0, T0)
    num = den = 0.0
    for s in stamps:
        cmap = covariance_map(s.ainv)
        images, _ = s.model.evaluate(s.origin, cmap @ cov, s.flux_scale, s.ainv, cmap @ dcov, 1)
        unit = images[0]
        w = np.where(np.isfinite(s.image), s.weight, 0.0)
        d = np.where(np.isfinite(s.image), s.image, 0.0)
        num += float(np.sum(w * d * unit))
        den += float(np.sum(w * unit * unit))
    flux = num / den if den > 0 else 0.0
    return flux if np.isfinite(flux) and flux > 0 else 1.0


def measure_joint_object(ctx: JointContext, j: int) -> dict:
    """Joint fit of selected galaxy ``j`` over the frames it falls on: its columns, as 1-element arrays."""
    cols = {k: np.full(1, np.nan) for k in _JOINT_FLOAT}
    cols.update({k: np.zeros(1, dtype=np.int32) for k in _JOINT_INT})
    i = int(ctx.rows[j])
    n = int(ctx.sizes[j])
    stamps, edge, nframes = [], False, 0
    for f in ctx.frames:
        if not f.on[j]:
            continue
        xi, yi = float(f.x[j]) - 1.0, float(f.y[j]) - 1.0
        img, wt, x0, y0, off = cut_stamp(f.data, f.weights, f.ivar, f.background, n, xi, yi)
        edge |= off
        nframes += int(np.count_nonzero((wt > 0) & np.isfinite(img)) >= 20)
        stamps.append(JointStamp(img, wt, ctx.models[f.model][n], (xi - x0, yi - y0), f.ainv[j], f.per_rate))
    T0 = _start_size(ctx.cat, i, 1.0)               # arcsec^2
    F0 = catalogue_rate(ctx.cat, i, ctx.rate_frame)
    if not (np.isfinite(F0) and F0 > 0):
        F0 = _joint_linear_flux(stamps, T0)
    res = fit_joint(stamps, (0.0, 0.0, 0.0, 0.0, T0, F0))
    th, er = res.theta, res.errors
    ra0, dec0 = float(ctx.cat["ra"][i]), float(ctx.cat["dec"][i])
    # (du, dv) in the tangent plane, u to the West: back to ra, dec (offsets below arcseconds)
    cols["ra"][0] = ra0 - th[0] / 3600.0 / math.cos(math.radians(dec0))
    cols["dec"][0] = dec0 + th[1] / 3600.0
    cols["ra_err"][0], cols["dec_err"][0] = er[0], er[1]
    for k, key in enumerate(("g1", "g2", "T", "flux"), 2):
        cols[key][0] = th[k]
        cols[f"{key}_err"][0] = er[k]
    cols["s2n"][0], cols["chi2"][0], cols["nfev"][0] = res.s2n, res.chi2, res.nfev
    cols["nframes"][0] = nframes
    moved = math.hypot(th[0], th[1]) > MAX_MOVE * ctx.pixel_scale
    cols["flags"][0] = (res.flags | (FLAG_EDGE if edge else 0) | (FLAG_BLEND if ctx.blends[j] else 0)
                        | (FLAG_MOVED if moved else 0) | (FLAG_LOW_SN if not res.s2n >= MIN_S2N else 0))
    return cols


def measure_joint(frames, cat, *, psf="roman", stamp=48, sky=None, read_noise=None, blend_radius=4.0,
                  progress=None, workers: int = 1, kinds=None, min_snr=MIN_SNR_DEFAULT, all_rows: bool = False,
                  inputs=None, psf_options=None, psf_used=None, data=None, only=None) -> dict:
    """One shape per galaxy from all the frames it falls on (``perscli measure --joint``).

    The frames' headers are read first (where each galaxy falls, its
    predicted S/N, the cut); then each frame's pixels, one frame at a time,
    keeping only the :class:`Windows` of the galaxies fitted on it, so that
    memory grows with the galaxies, not with the frames (a 4088^2 float32
    frame is 67 MB).  Galaxies are fitted by :func:`measure_joint_object`
    on ``workers`` processes.  The cut is on the combined predicted S/N,
    sqrt(sum of the frames' :func:`predicted_snr` squared).

    Parameters
    ----------
    frames : sequence of str
        Paths ('-': standard input, once).  All in one FILTER (the flux is
        common), each with a WCS and EXPTIME.
    cat : dict
        From :func:`read_positions`, with ra/dec.
    inputs : list, optional
        Appended with (stem, name, DATASUM) per frame, for provenance.
    psf_options, psf_used
        As for :func:`measure_frame` (one PSF per SCA and filter).
    data : sequence, optional
        Per frame, the pixels to fit instead of the frame's own: an array of
        the frame's shape, or a function of no arguments returning one (called
        once, when that frame's windows are cut): variants of the frames,
        such as the same exposures with persistence.
    only : ndarray of bool, optional
        Per catalogue row: fit only these of the selected galaxies.
    Others as for :func:`measure_frame`.

    Returns
    -------
    dict of column arrays (one row per galaxy fitted, or per selected galaxy
    with ``all_rows``), '_noise' (per frame), '_counts' and '_todo' (the
    catalogue rows selected for a fit).
    """
    from ..executor import run
    from ..io.frames import open_frame

    min_snr = _check_min_snr(min_snr)
    if "ra" not in cat:
        raise PerscliError(f"{cat.get('label', 'catalogue')}: --joint needs ra/dec in the catalogue (x/y are "
                           "pixels of one frame)")
    rows, _ = select_kinds(cat, kinds)
    jframes, models, model_keys, noises, filters, scales = [], [], {}, [], [], []
    rate_frame = None
    for k, name in enumerate(frames):
        frame = open_frame(name)
        try:
            if inputs is not None:
                inputs.append((f"FRM{k + 1:02d}", name, frame.datasum(frame.sci[0])))
            wcs = frame_wcs(frame)
            if wcs is None:
                raise PerscliError(f"{frame.label}: --joint needs a WCS in every frame")
            filt = str(frame.keyword("FILTER") or "").strip()
            filters.append((filt, frame.label))
            if filt != filters[0][0]:
                raise PerscliError(f"--joint: {filters[0][1]} is in FILTER {filters[0][0] or '(none)'} and "
                                   f"{frame.label} in {filt or '(none)'}: a joint fit has one flux, so its frames "
                                   "must share a filter; fit each filter separately")
            facts = _FrameFacts.of(frame)
            per_rate = frame_units_per_rate(facts)
            if not per_rate:
                raise PerscliError(f"{frame.label}: --joint needs EXPTIME (the joint flux is in e-/s)")
            pixel_scale = _pixel_scale(wcs)
            scales.append(pixel_scale)
            noise, weights, ivar = _noise_and_weights(frame, sky=sky, read_noise=read_noise)
            noises.append(noise)
            shape = tuple(frame.shape)
            # standard input cannot be read again: its pixels are kept now
            pixels = _float_pixels(frame) if name == "-" and (data is None or data[k] is None) else None
            key = (psf, str(facts.keyword("SCA")), filt, round(pixel_scale, 6))
            if key not in model_keys:
                model_keys[key] = len(models)
                models.append({stamp: _psf_exp_model(psf, frame, pixel_scale, stamp, psf_options, psf_used)})
            m = model_keys[key]
            x, y = frame_xy(wcs, shape, cat["ra"][rows], cat["dec"][rows])
            on = on_frame(x, y, shape)
            ainv = np.zeros((len(rows), 2, 2))
            snr = np.full(len(rows), np.nan)
            if on.any():
                ainv[on] = local_ainv(wcs, x[on], y[on], cat["ra"][rows[on]], cat["dec"][rows[on]])
                snr[on] = predicted_snr(cat, rows[on], facts, pixel_scale, _snr_table(models[m][stamp]),
                                        _ivar_at(weights, ivar, x[on], y[on]))
            rate_frame = rate_frame or facts
            jframes.append(JointFrame(data=pixels, weights=weights, ivar=ivar, background=float(noise.background),
                                      model=m, per_rate=float(per_rate), x=x, y=y, on=on, ainv=ainv, snr=snr,
                                      shape=shape))
        finally:
            frame.close()
    on_any = np.zeros(len(rows), dtype=bool)
    snr2 = np.zeros(len(rows))
    for f in jframes:
        on_any |= f.on
        snr2 += np.where(f.on, f.snr ** 2, 0.0)   # NaN (no magnitude) stays NaN: not cut
    snr = np.where(on_any, np.sqrt(snr2), np.nan)
    selected = np.flatnonzero(on_any & ~(snr < min_snr))
    todo = selected if only is None else selected[np.asarray(only, dtype=bool)[rows[selected]]]
    pixel_scale = float(np.mean(scales)) if scales else ROMAN_PIXEL_SCALE
    # neighbours of any kind within --blend-radius pixels, on the sky
    blends_all = blended_on_sky(cat["ra"], cat["dec"], blend_radius * pixel_scale)
    ladder = stamp_ladder(stamp)
    sizes = np.full(len(rows), stamp, dtype=np.int32)
    for j in todo:
        sizes[j] = stamp_side(cat, rows[j], pixel_scale, ladder)
    for per_psf in models:
        for n in sorted(set(sizes[todo].tolist()) - set(per_psf)):
            per_psf[n] = ExpModel(per_psf[stamp].drawer.psf, n, pixel=per_psf[stamp].drawer.pixel)
    for k, f in enumerate(jframes):
        given = data[k] if data is not None else None
        pixels = f.data if given is None else (given() if callable(given) else given)
        if pixels is None:
            with open_frame(frames[k]) as frame:
                pixels = _float_pixels(frame)
        f.data = Windows(f.shape, pixels.dtype)
        for j in todo[f.on[todo]]:
            f.data.keep(pixels, stamp_window(f.shape, int(sizes[j]), float(f.x[j]) - 1.0, float(f.y[j]) - 1.0))
        del pixels
    ctx = JointContext(frames=jframes, models=models, cat=cat, rows=rows, sizes=sizes, blends=blends_all[rows],
                       rate_frame=rate_frame, stamp=stamp, pixel_scale=pixel_scale)
    results = run(measure_joint_object, todo, context=ctx, workers=workers, progress=progress)
    out = np.arange(len(rows)) if all_rows else todo
    cols = _gather(results, todo, out, _JOINT_FLOAT, _JOINT_INT)
    if all_rows:
        fitted = np.isin(out, todo)
        cols["ra"][~fitted] = cat["ra"][rows[out[~fitted]]]
        cols["dec"][~fitted] = cat["dec"][rows[out[~fitted]]]
        cols["flags"][~on_any[out]] = FLAG_OFF_FRAME
        cols["flags"][on_any[out] & ~fitted] = FLAG_BELOW_CUT
        for f in jframes:
            cols["nframes"][~fitted] += f.on[out[~fitted]].astype(np.int32)
    cols["id"] = cat["id"][rows[out]]
    cols["snr_pred"] = snr[out]
    cols["_noise"] = noises
    cols["_counts"] = {"selected": len(rows), "on": int(on_any.sum()), "cut": int(on_any.sum() - len(selected)),
                       "fitted": len(todo), "models": len(models)}
    cols["_todo"] = rows[selected]
    return cols


def _float_pixels(frame) -> np.ndarray:
    """A frame's science image as floats (float32 as stored, integers as float64)."""
    pixels = np.asarray(frame.planes()[0])
    return pixels if pixels.dtype.kind == "f" else pixels.astype(np.float64)


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


def measure_files(frames, catalog: str, dest: str, *, psf="roman", method="exp", stamp=48, sky=None,
                  read_noise=None, blend_radius=4.0, workers=1, overwrite=False, progress=None, kinds=None,
                  min_snr=MIN_SNR_DEFAULT, all_rows: bool = False, joint: bool = False, psf_pixel=None,
                  psf_oversampling=None, allow_undersampled_psf: bool = False, write_psf=None,
                  columns=None) -> dict:
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
    kinds : None, 'all', str or sequence of str
        Rows to fit (:func:`select_kinds`): default the galaxies, or every row
        of a catalogue without a kind column.
    min_snr : float
        Cut on the S/N predicted from the catalogue (:func:`predicted_snr`);
        default :data:`MIN_SNR_DEFAULT`; 0 fits everything on the frame.
    all_rows : bool
        Write rows, without a fit, for selected objects off the frame (flag
        256) and below the cut (flag 4096) too.
    joint : bool
        One fit per galaxy over all the frames (one FILTER, with WCS and EXPTIME).
    psf : str
        'roman' or a PSF image (:func:`perscli.measure.psf.psf_model`).
    psf_pixel : {'included', 'excluded'} or None
        Whether the PSF image includes the pixel response (None: its
        PSFPIXEL keyword, else inferred with a warning).
    psf_oversampling : float or None
        PSF pixels per frame pixel of the PSF image (None: its header).
    allow_undersampled_psf : bool
        Use an undersampled PSF image with a warning instead of refusing it.
    write_psf : str or None
        Also write the PSF images used there, one HDU per PSF
        (:func:`perscli.measure.psf.psf_hdus`), readable as ``psf``.
    columns : dict, optional
        Column mapping {perscli name: catalogue column} for a catalogue
        another tool wrote (``--columns``; see :func:`read_positions`).
    method, stamp, sky, read_noise, blend_radius, workers, overwrite, progress
        As the command's options.

    Returns
    -------
    dict
        Summary: rows, good (= unflagged: rows with flags 0), frames, and the
        numbers selected, fitted and cut.
    """
    from ..io.fitsfile import OutHDU, table_hdu
    from ..io.frames import open_frame
    from ..io.output import add_provenance, check_output, write_hdus

    if method not in ("exp", "hsm"):
        raise PerscliError(f"--method must be exp or hsm, not {method!r}")
    if stamp < 16 or stamp % 2:
        raise PerscliError(f"--stamp {stamp} must be an even number of pixels >= 16")
    min_snr = _check_min_snr(min_snr)
    if joint and method != "exp":
        raise PerscliError("--joint fits the exponential model: it does not go with --method hsm")
    frames = list(frames)
    if frames.count("-") > 1:
        raise PerscliError("only one frame can be standard input ('-')")
    if psf == "roman":
        given = [name for name, value in (("--psf-pixel", psf_pixel), ("--psf-oversampling", psf_oversampling),
                                           ("--allow-undersampled-psf", allow_undersampled_psf)) if value]
        if given:
            raise PerscliError(f"{' and '.join(given)} describe{'s' if len(given) == 1 else ''} a PSF image: "
                               "give --psf PSF.fits, or leave it out with --psf roman")
    psf_options = PsfOptions(pixel=psf_pixel, oversampling=psf_oversampling,
                             allow_undersampled=allow_undersampled_psf)
    read = [catalog, *frames, psf if psf != "roman" else None]
    check_output(dest, overwrite=overwrite, inputs=read)
    if write_psf is not None:
        check_output(write_psf, overwrite=overwrite, inputs=read)
        if write_psf == "-" and dest == "-":
            raise PerscliError("--write-psf and -o cannot both be standard output: give --write-psf a file")
        if write_psf != "-" and dest != "-" and os.path.abspath(write_psf) == os.path.abspath(dest):
            raise PerscliError(f"{write_psf}: --write-psf and -o name the same file: choose another name for the PSF")
    psf_used = []
    cat = read_positions(catalog, columns=columns)
    _, kinds_text = select_kinds(cat, kinds)       # bad --kinds fail here, before any frame is read
    inputs = [("CAT", catalog, cat["datasum"])]
    params = {"METHOD": (method, "exp (mixture fit) or hsm (REGAUSS)"),
              "PSF": (psf if psf == "roman" else psf.split("/")[-1], "PSF source"),
              "STAMP": (stamp, "[pix] largest stamp side"),
              "STAMPRUL": (f"{STAMP_HLR:g} hlr+{STAMP_MARGIN:g}px" if method == "exp" else "fixed",
                           f"exp stamp: smallest {STAMP_MIN},{STAMP_MIN + 8},.. holding it"),
              "RDNOISE": (read_noise if read_noise is not None else "model",
                                                            "[e-] read noise ('model': the frame's)"),
              "NFRAMES": (len(frames), "frames measured"), "XTOL": (1e-10, "relative step tolerance"),
              "BLENDRAD": (blend_radius, "[pix] neighbour distance flagged as a blend"),
              "KINDS": (kinds_text, "catalogue kinds fitted"),
              "MINSNR": (min_snr, "cut on the S/N predicted from the catalogue"),
              "SNRPRED": ("mag,hlr,PSF,noise", "predicted S/N from (never the pixels)"),
              "ALLROWS": (bool(all_rows), "rows off the frame (256) / below cut (4096)"),
              "JOINT": (bool(joint), "one fit per galaxy over all frames"),
              "PSFPIXEL": (psf_pixel or "header", "PSF image includes the pixel (--psf-pixel)"),
              "PSFOVERS": (psf_options.oversampling or "header", "PSF pixels per frame pixel (option)"),
              "PSFUNDER": (bool(allow_undersampled_psf), "undersampled PSF image allowed")}
    hdus = [OutHDU([])]
    if joint:
        cols = measure_joint(frames, cat, psf=psf, stamp=stamp, sky=sky, read_noise=read_noise,
                             blend_radius=blend_radius, progress=progress, workers=workers, kinds=kinds,
                             min_snr=min_snr, all_rows=all_rows, inputs=inputs, psf_options=psf_options,
                             psf_used=psf_used)
        noise_sources = cols.pop("_noise")
        counts = cols.pop("_counts")
        order = ("id", "ra", "dec", "g1", "g2", "T", "flux", "ra_err", "dec_err", "g1_err", "g2_err", "T_err",
                 "flux_err", "s2n", "snr_pred", "nframes", "chi2", "nfev", "flags")
        table = {key: cols[key] for key in order}
        descriptions = dict(_DESCRIPTIONS, g1="reduced shear on the sky, +g1 East-West (RA axis)",
                            g2="reduced shear on the sky, +g2 North-West/South-East",
                            ra_err="error of the centre towards the West", dec_err="error towards the North",
                            flux="[e-/s] electrons per second (no FITS unit)", flux_err="[e-/s] error of flux")
        hdus.append(table_hdu(table, "JOINT", units=_JOINT_UNITS, descriptions=descriptions))
        params.update({"NSEL": (counts["selected"], "catalogue rows of KINDS"),
                       "NONFRM": (counts["on"], "of them on at least one frame"),
                       "NCUT": (counts["cut"], "on a frame, combined predicted S/N < MINSNR"),
                       "NFIT": (counts["fitted"], "galaxies fitted"),
                       "NPSF": (counts["models"], "PSF models (SCA, filter) used"),
                       "GAXES": ("sky: u=West, v=North", "axes of g1, g2 (GalSim's world axes)")})
        rows = len(table["id"])
        good = int(np.sum(table["flags"] == 0))
    else:
        tables, noise_sources, frame_counts = [], [], []
        kwargs = dict(psf=psf, method=method, stamp=stamp, sky=sky, read_noise=read_noise,
                      blend_radius=blend_radius, kinds=kinds, min_snr=min_snr, all_rows=all_rows,
                      psf_options=psf_options, psf_used=psf_used)
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
        descriptions = dict(_DESCRIPTIONS, g1="reduced shear, +g1 along the frame's x axis",
                            g2="reduced shear, +g2 along the diagonal x = y")
        hdus.append(table_hdu(shapes, "SHAPES", units=_SHAPES_UNITS, descriptions=descriptions))
        if len(frames) > 1:
            hdus.append(_combined(shapes))
        params["NSEL"] = (frame_counts[0]["selected"] if frame_counts else 0, "catalogue rows of KINDS")
        for k, c in enumerate(frame_counts, 1):
            params[f"NON{k:02d}"] = (c["on"], f"of them on frame {k}")
            params[f"NCUT{k:02d}"] = (c["cut"], f"on frame {k}, predicted S/N < MINSNR")
            params[f"NFIT{k:02d}"] = (c["fitted"], f"fitted on frame {k}")
        params["GAXES"] = ("pixel", "axes of g1, g2: the frame's x, y")
        rows = len(shapes["id"])
        good = int(np.sum(shapes["flags"] == 0))
        counts = {"selected": params["NSEL"][0], "fitted": sum(c["fitted"] for c in frame_counts),
                  "cut": sum(c["cut"] for c in frame_counts)}
    for bit, text in FLAGS.items():
        params[f"FLAG{int(math.log2(bit)):02d}"] = (bit, text[:47])
    for k, noise in enumerate(noise_sources, 1):
        params[f"BKG{k:02d}"] = (float(noise.background), f"background of frame {k} ({noise.source})")
    if psf != "roman":
        # how each PSF image was read: the parameters that produced the shapes
        for k, used in enumerate(psf_used[:99], 1):
            params[f"PSFPX{k:02d}"] = (bool(used.pixel_included), f"PSF {k} includes the pixel response")
            params[f"PSFOV{k:02d}"] = (float(used.oversampling), f"PSF {k}: PSF pixels per frame pixel")
    add_provenance(hdus[0], step=f"measure method={method} psf={params['PSF'][0]} frames={len(frames)}"
                                 f"{' joint' if joint else ''} kinds={kinds_text} min_snr={min_snr:g}",
                   params=params, inputs=inputs)
    _document(hdus[0], joint)
    if write_psf is not None:
        _write_psf(psf_used, write_psf, psf, inputs, overwrite)
    write_hdus(hdus, dest, overwrite=overwrite)
    return {"rows": rows, "good": good, "unflagged": good, "frames": len(frames), "selected": counts["selected"],
            "fitted": counts["fitted"], "cut": counts["cut"], "joint": bool(joint)}


def _write_psf(psf_used, dest, psf, inputs, overwrite):
    """--write-psf: the PSF images of the fits, one HDU per PSF, with the keywords that read them back."""
    from ..io.fitsfile import OutHDU
    from ..io.output import add_provenance, write_hdus

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
    import textwrap

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
