"""The fit of the selected objects on one frame: stamps, starts, flags and :func:`measure_frame`.

For each object: a stamp whose side depends on its catalogue size
(:func:`stamp_side`, cut by :func:`cut_stamp`), the background removed, the
start from the catalogue and the frame's headers (:func:`start_point`), and
a fit (:func:`perscli.measure.fit.fit_exp`, or GalSim's HSM) by
:func:`measure_object` on the workers of :func:`perscli.executor.run`.
The flag bits of the output (:data:`FLAGS`) and the stamp helpers are
shared with the joint fit (:mod:`perscli.measure.joint`).
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass

import galsim
import numpy as np

from .. import PerscliError
from ..executor import run
from .fit import FLAG_EDGE, ExpModel, fit_exp
from .noise import (_check_min_snr, _ivar_at, _noise_and_weights, _snr_table, _start_size, catalogue_rate,
                    frame_units_per_rate, predicted_snr)
from .psf import psf_model
from .response import CHANGE_METHODS, fit_exp_changes
from .selection import _frame_positions, _pixel_scale, blended, frame_wcs, on_frame, select_kinds
from .settings import MeasureOptions

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
#: stamps of an exp fit: the smallest side on the ladder 16, 24, 32, ... (up to --stamp) whose half
#: holds STAMP_HLR catalogue half-light radii plus STAMP_MARGIN pixels of PSF (:func:`stamp_side`).
#: Noise-free Roman galaxies of hlr 0.15-0.5" fitted on those stamps are within 4e-4 of their g (within
#: 2e-4 on 48-pixel stamps); a 3-hlr rule would reach 8e-4 on 16-pixel stamps.
STAMP_HLR = 4.0
STAMP_MARGIN = 3.0
STAMP_MIN = 16


def psf_profile(spec: str, frame, *, pixel_scale: float, options=None):
    """The optical PSF (without the pixel response) as a GalSim profile in the frame's pixel units, flux 1.

    What :class:`~perscli.measure.fit.ExpModel` and
    :class:`~perscli.optics.StampDrawer` take with their default
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

    def __init__(self, shape, dtype=np.float32, *, absent_zero: bool = False):
        self.shape = tuple(shape)
        self.dtype = np.dtype(dtype)
        # a change's windows: only those where something changed are kept, a window absent is all zeros
        self.absent_zero = bool(absent_zero)
        self._parts = {}

    def keep(self, data, window) -> None:
        """Store ``data``'s pixels of ``window`` ((b0, b1, a0, a1), e.g. from :func:`stamp_window`)."""
        b0, b1, a0, a1 = window
        self._parts[window] = np.array(data[b0:b1, a0:a1], dtype=self.dtype)

    def put(self, window, pixels) -> None:
        """Store ``pixels`` as the window ``window`` ((b0, b1, a0, a1)): a window kept elsewhere."""
        b0, b1, a0, a1 = window
        if np.shape(pixels) != (b1 - b0, a1 - a0):
            raise ValueError(f"window {window}: pixels of shape {np.shape(pixels)}")
        # a copy: ``pixels`` is often a view into a final's whole table of windows, which must not stay alive
        self._parts[tuple(window)] = np.array(pixels, dtype=self.dtype)

    def __contains__(self, window) -> bool:
        return window in self._parts

    def __getitem__(self, key):
        rows, cols = key
        return self._parts[(rows.start, rows.stop, cols.start, cols.stop)]


#: float columns of one object's measurement, and the integer ones
_FLOAT_COLUMNS = ("x", "y", "g1", "g2", "T", "flux", "x_err", "y_err", "g1_err", "g2_err", "T_err", "flux_err",
                  "s2n", "chi2")
_INT_COLUMNS = ("nfev", "flags")


def _object_columns(ctx: FrameContext, i: int, res, x0: int, y0: int, start, edge: int) -> dict:
    """One exp fit's columns, as 1-element arrays: frame position, shape, errors and flags."""
    cols = {k: np.full(1, np.nan) for k in _FLOAT_COLUMNS}
    cols.update({k: np.zeros(1, dtype=np.int32) for k in _INT_COLUMNS})
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
    return cols


def _object_start(ctx: FrameContext, i: int, img, wt, x0, y0):
    """An exp fit's stamp model and start (from the catalogue, else the flux solved for)."""
    xi, yi = float(ctx.x[i]) - 1.0, float(ctx.y[i]) - 1.0
    model = ctx.models[int(ctx.sizes[i])]
    start, from_catalogue = start_point(ctx.cat, i, xi - x0, yi - y0, ctx.frame, ctx.pixel_scale)
    if not from_catalogue:
        start = start[:5] + (_linear_flux(model, start, img, wt),)
    return model, start


def measure_object(ctx: FrameContext, i: int) -> dict:
    """Fit catalogue object ``i`` (on the frame) of ``ctx``: its columns, as 1-element arrays."""
    # 0-indexed array coordinates of the object (FITS pixel 1 is index 0)
    xi, yi = float(ctx.x[i]) - 1.0, float(ctx.y[i]) - 1.0
    n = int(ctx.sizes[i]) if ctx.method == "exp" else ctx.stamp
    img, wt, x0, y0, off_edge = cut_stamp(ctx.data, ctx.weights, ctx.ivar, ctx.background, n, xi, yi)
    edge = (FLAG_EDGE if off_edge else 0) | (FLAG_BLEND if ctx.blends[i] else 0)
    if ctx.method == "exp":
        model, start = _object_start(ctx, i, img, wt, x0, y0)
        return _object_columns(ctx, i, fit_exp(img, wt, model, start), x0, y0, start, edge)
    cols = {k: np.full(1, np.nan) for k in _FLOAT_COLUMNS}
    cols.update({k: np.zeros(1, dtype=np.int32) for k in _INT_COLUMNS})
    _hsm(img, wt, ctx.psf_image, cols, 0, x0, y0, edge)
    return cols


@dataclass
class ChangesFrameContext(FrameContext):
    """A :class:`FrameContext` and, per variant, its pixel change over the frame (or None), which rows changed."""

    deltas: list = None
    changed: list = None
    cold: bool = False


def measure_object_changes(ctx: ChangesFrameContext, i: int) -> dict:
    """Object ``i`` fitted on the reference and on every variant (:func:`perscli.measure.response.fit_exp_changes`)."""
    xi, yi = float(ctx.x[i]) - 1.0, float(ctx.y[i]) - 1.0
    n = int(ctx.sizes[i])
    img, wt, x0, y0, off_edge = cut_stamp(ctx.data, ctx.weights, ctx.ivar, ctx.background, n, xi, yi)
    edge = (FLAG_EDGE if off_edge else 0) | (FLAG_BLEND if ctx.blends[i] else 0)
    model, start = _object_start(ctx, i, img, wt, x0, y0)
    deltas = []
    for v, full in enumerate(ctx.deltas):
        if full is None or not ctx.changed[v][i]:
            deltas.append(None)
            continue
        d = cut_stamp(full, None, 1.0, 0.0, n, xi, yi)[0]
        deltas.append(d if np.any(d) else None)
    ref, changes, colds = fit_exp_changes(img, wt, model, start, deltas, cold=ctx.cold)
    out = {"ref": _object_columns(ctx, i, ref, x0, y0, start, edge), "variants": []}
    for change, cold in zip(changes, colds):
        cols = _object_columns(ctx, i, change.result, x0, y0, start, edge)
        cols["method"] = np.array([CHANGE_METHODS.index(change.method)], dtype=np.int16)
        cols["bound"] = np.array([change.bound])
        if ctx.cold:
            cols["g1_cold"] = np.array([cold.theta[2] if cold is not None else np.nan])
            cols["g2_cold"] = np.array([cold.theta[3] if cold is not None else np.nan])
        out["variants"].append(cols)
    return out


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


def measure_frame(frame, cat, *, options: MeasureOptions | None = None, progress=None, workers: int = 1,
                  models=None, psf_options=None, psf_used=None, data=None, only=None) -> dict:
    """Measure the selected catalogue objects on one frame.

    The frame is read here, once; the objects are fitted by
    :func:`measure_object` on ``workers`` processes
    (:func:`perscli.executor.run`), with the same results for any number.

    Parameters
    ----------
    frame : perscli.io.frames.Frame
    cat : dict
        From :func:`read_positions`.
    options : perscli.measure.settings.MeasureOptions, optional
        How to select and fit (default: ``MeasureOptions()``, the command's
        defaults): psf, method, stamp, sky, read_noise, blend_radius, kinds
        (which rows, :func:`select_kinds`), min_snr (objects whose
        :func:`predicted_snr` is below it are not fitted; those without one
        always are) and all_rows (also return rows, without fits, for the
        selected objects off the frame, flag 256, and below the cut, flag
        4096); ``joint`` and ``columns`` are not read here.
    progress : callable, optional
        Progress callback of :func:`perscli.executor.run`.
    workers : int
        Processes fitting the objects.
    models : dict, optional
        Stamp side -> ExpModel for this frame's PSF, filled here as needed
        (a cache to share between frames of one SCA and filter).
    psf_options : perscli.measure.psf.PsfOptions, optional
        How to read a PSF image, made from ``options`` by the caller
        (:meth:`MeasureOptions.psf_options`) and shared by the frames of a
        run so that each warning is given once (None: made here).
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

    Returns
    -------
    dict of column arrays, one row per object fitted (or, with all_rows, per
    selected object), in catalogue order; '_noise' the noise model,
    '_counts' the numbers selected, on the frame, cut and fitted, and
    '_todo' the catalogue rows selected for a fit (on the frame, above the cut).
    """
    setup = frame_setup(frame, cat, options=options, models=models, psf_options=psf_options, psf_used=psf_used,
                        data=data, only=only)
    results = run(measure_object, setup.todo, context=setup.ctx, workers=workers, progress=progress)
    o = options if options is not None else MeasureOptions()
    return setup.columns(results, o.all_rows)


@dataclass
class FrameSetup:
    """What a measurement of one frame reads before it fits (:func:`frame_setup`)."""

    ctx: FrameContext
    todo: np.ndarray           # catalogue rows to fit
    selected: np.ndarray       # catalogue rows on the frame and above the cut
    rows_sel: np.ndarray       # catalogue rows of the kinds measured
    rows_on: np.ndarray
    ra: np.ndarray
    dec: np.ndarray
    snr: np.ndarray
    noise: object

    @property
    def rows(self) -> np.ndarray:
        """Catalogue rows by the index :attr:`todo` uses (here: themselves)."""
        return np.arange(len(self.ctx.cat["id"]))

    def changes(self, deltas, changed, cold: bool = False) -> None:
        """Make the context one of shape changes: per variant its pixel change (or None) and which rows changed."""
        self.ctx = ChangesFrameContext(**{f.name: getattr(self.ctx, f.name) for f in dataclasses.fields(FrameContext)},
                                       deltas=list(deltas), changed=list(changed), cold=cold)

    def columns(self, results, all_rows: bool = False) -> dict:
        """The fits (one per row of ``todo``) as columns, with the bookkeeping of :func:`measure_frame`."""
        ctx, todo = self.ctx, self.todo
        out_rows = self.rows_sel if all_rows else todo
        cols = _gather(results, todo, out_rows, _FLOAT_COLUMNS, _INT_COLUMNS)
        if all_rows:
            fitted = np.isin(out_rows, todo)
            on_all = on_frame(ctx.x[out_rows], ctx.y[out_rows], ctx.data.shape)
            cols["flags"][~on_all] = FLAG_OFF_FRAME
            cols["flags"][on_all & ~fitted] = FLAG_BELOW_CUT
        cols["id"] = ctx.cat["id"][out_rows]
        cols["ra"] = np.asarray(self.ra, dtype=np.float64)[out_rows]
        cols["dec"] = np.asarray(self.dec, dtype=np.float64)[out_rows]
        cols["snr_pred"] = self.snr[out_rows]
        cols["_noise"] = self.noise
        cols["_counts"] = {"selected": len(self.rows_sel), "on": len(self.rows_on),
                           "cut": int(len(self.rows_on) - len(self.selected)), "fitted": len(todo)}
        cols["_todo"] = self.selected
        return cols


def frame_setup(frame, cat, *, options: MeasureOptions | None = None, models=None, psf_options=None, psf_used=None,
                data=None, only=None) -> FrameSetup:
    """Read a frame and choose what :func:`measure_frame` fits (its parameters)."""
    o = options if options is not None else MeasureOptions()
    psf, method, stamp, blend_radius = o.psf, o.method, o.stamp, o.blend_radius
    psf_options = psf_options if psf_options is not None else o.psf_options()
    min_snr = _check_min_snr(o.min_snr)
    rows_sel, _ = select_kinds(cat, o.kinds)
    wcs = frame_wcs(frame)
    x, y, ra, dec = _frame_positions(frame, cat, wcs)
    pixel_scale = _pixel_scale(wcs)
    noise, weights, ivar = _noise_and_weights(frame, sky=o.sky, read_noise=o.read_noise)
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
    return FrameSetup(ctx=ctx, todo=todo, selected=selected, rows_sel=rows_sel, rows_on=rows_on, ra=ra, dec=dec,
                      snr=snr, noise=noise)


def _psf_exp_model(psf, frame, pixel_scale, stamp, psf_options, psf_used) -> ExpModel:
    """The ExpModel of a frame's PSF (:func:`perscli.measure.psf.psf_model`) for ``stamp``; the PSF
    appended to ``psf_used``.  A PSF that includes the pixel response is not given it again."""
    made = psf_model(psf, frame, pixel_scale=pixel_scale, options=psf_options)
    if psf_used is not None:
        psf_used.append(made)
    return ExpModel(made.profile, stamp, pixel=not made.pixel_included)


def _hsm(img, wt, psf_image, cols, i, x0, y0, edge):
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
