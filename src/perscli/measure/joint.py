"""Joint fits over several frames (``perscli measure --joint``): one shape per galaxy, on the sky.

Each galaxy is fitted once over all the frames it falls on
(:func:`perscli.measure.fit.fit_joint` through :func:`measure_joint_object`),
its centre, shear and size in the tangent plane at its catalogue position
(:func:`local_ainv` maps those to each frame's pixels).  :func:`measure_joint`
reads the frames' headers first, then their pixels one at a time, keeping
only the stamps of the galaxies fitted on each (:class:`~perscli.measure.perframe.Windows`).

"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from .. import PerscliError
from ..executor import run
from ..instrument import ROMAN_PIXEL_SCALE
from ..io.frames import open_frame
from .fit import FLAG_EDGE, ExpModel, JointStamp, covariance_map, fit_joint, shape_covariance
from .noise import (_check_min_snr, _ivar_at, _noise_and_weights, _snr_table, _start_size, catalogue_rate,
                    frame_units_per_rate, predicted_snr)
from .perframe import (FLAG_BELOW_CUT, FLAG_BLEND, FLAG_LOW_SN, FLAG_MOVED, FLAG_OFF_FRAME, MAX_MOVE, MIN_S2N,
                       Windows, _FrameFacts, _gather, _psf_exp_model, cut_stamp, stamp_ladder, stamp_side,
                       stamp_window)
from .response import CHANGE_METHODS, fit_joint_changes
from .selection import _pixel_scale, blended_on_sky, frame_wcs, frame_xy, on_frame, select_kinds
from .settings import MeasureOptions


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


def _joint_stamps(ctx: JointContext, j: int):
    """Selected galaxy ``j``'s stamps on the frames it falls on: (stamps, frame indices, off an edge, frames used)."""
    n = int(ctx.sizes[j])
    stamps, used, edge, nframes = [], [], False, 0
    for k, f in enumerate(ctx.frames):
        if not f.on[j]:
            continue
        xi, yi = float(f.x[j]) - 1.0, float(f.y[j]) - 1.0
        img, wt, x0, y0, off = cut_stamp(f.data, f.weights, f.ivar, f.background, n, xi, yi)
        edge |= off
        nframes += int(np.count_nonzero((wt > 0) & np.isfinite(img)) >= 20)
        stamps.append(JointStamp(img, wt, ctx.models[f.model][n], (xi - x0, yi - y0), f.ainv[j], f.per_rate))
        used.append(k)
    return stamps, used, edge, nframes


def _joint_start(ctx: JointContext, j: int, stamps) -> tuple:
    """The fit's start, from the catalogue alone: (du, dv, g1, g2, T, flux), round."""
    i = int(ctx.rows[j])
    T0 = _start_size(ctx.cat, i, 1.0)               # arcsec^2
    F0 = catalogue_rate(ctx.cat, i, ctx.rate_frame)
    if not (np.isfinite(F0) and F0 > 0):
        F0 = _joint_linear_flux(stamps, T0)
    return (0.0, 0.0, 0.0, 0.0, T0, F0)


def _joint_columns(ctx: JointContext, j: int, res, edge: bool, nframes: int) -> dict:
    """One fit's columns, as 1-element arrays: the sky position, shape, errors and flags."""
    cols = {k: np.full(1, np.nan) for k in _JOINT_FLOAT}
    cols.update({k: np.zeros(1, dtype=np.int32) for k in _JOINT_INT})
    i = int(ctx.rows[j])
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


def measure_joint_object(ctx: JointContext, j: int) -> dict:
    """Joint fit of selected galaxy ``j`` over the frames it falls on: its columns, as 1-element arrays."""
    stamps, _, edge, nframes = _joint_stamps(ctx, j)
    res = fit_joint(stamps, _joint_start(ctx, j, stamps))
    return _joint_columns(ctx, j, res, edge, nframes)


@dataclass
class ChangesContext:
    """A :class:`JointContext` and, per variant, per frame the windows of its pixel change (or None)."""

    joint: JointContext
    deltas: list               # per variant: per frame a Windows of (variant - reference), or None
    changed: list              # per variant: per selected galaxy (index j) whether any of its stamps changed
    cold: bool = False         # also fit every changed variant from the start (the check of the linear response)


def measure_joint_changes_object(ctx: ChangesContext, j: int) -> dict:
    """Galaxy ``j`` fitted on the reference and on every variant (:func:`perscli.measure.response.fit_joint_changes`).

    Returns
    -------
    dict
        'ref': the reference's columns; 'variants': per variant its columns
        (with 'method', 'bound' and, with ``cold``, 'g1_cold', 'g2_cold').
    """
    jc = ctx.joint
    stamps, used, edge, nframes = _joint_stamps(jc, j)
    n = int(jc.sizes[j])
    deltas = []
    for v, per_frame in enumerate(ctx.deltas):
        if not ctx.changed[v][j]:
            deltas.append(None)
            continue
        per = []
        for k in used:
            w = per_frame[k]
            f = jc.frames[k]
            if w is None or (getattr(w, "absent_zero", False)
                             and stamp_window(f.shape, n, float(f.x[j]) - 1.0, float(f.y[j]) - 1.0) not in w):
                per.append(None)
                continue
            d, _, _, _, _ = cut_stamp(w, None, 1.0, 0.0, n, float(f.x[j]) - 1.0, float(f.y[j]) - 1.0)
            per.append(d if np.any(d) else None)
        deltas.append(per)
    # the start of perscli measure's own fits (a start nearer the truth can find another minimum where the
    # likelihood has two, and the shape changes must be those of the measure a user would run)
    ref, changes, colds = fit_joint_changes(stamps, _joint_start(jc, j, stamps), deltas, cold=ctx.cold)
    out = {"ref": _joint_columns(jc, j, ref, edge, nframes), "variants": []}
    for change, cold in zip(changes, colds):
        cols = _joint_columns(jc, j, change.result, edge, nframes)
        cols["method"] = np.array([CHANGE_METHODS.index(change.method)], dtype=np.int16)
        cols["bound"] = np.array([change.bound])
        if ctx.cold:
            cols["g1_cold"] = np.array([cold.theta[2] if cold is not None else np.nan])
            cols["g2_cold"] = np.array([cold.theta[3] if cold is not None else np.nan])
        out["variants"].append(cols)
    return out


def measure_joint(frames, cat, *, options: MeasureOptions | None = None, progress=None, workers: int = 1,
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
    options : perscli.measure.settings.MeasureOptions, optional
        How to select and fit, as for :func:`measure_frame`; ``method`` is
        not read (a joint fit is an exp fit), and ``min_snr`` cuts the
        combined predicted S/N.
    progress, workers
        As for :func:`measure_frame`.
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

    Returns
    -------
    dict of column arrays (one row per galaxy fitted, or per selected galaxy
    with ``all_rows``), '_noise' (per frame), '_counts' and '_todo' (the
    catalogue rows selected for a fit).
    """
    o = options if options is not None else MeasureOptions()
    setup = joint_setup(frames, cat, o, inputs=inputs, psf_options=psf_options, psf_used=psf_used, data=data,
                        only=only)
    ctx, todo = setup.ctx, setup.todo
    setup.keep_windows(frames, data)
    results = run(measure_joint_object, todo, context=ctx, workers=workers, progress=progress)
    return setup.columns(results, o.all_rows)


@dataclass
class JointSetup:
    """What a joint measurement reads before it fits: the frames' facts, the selection, the stamp sizes."""

    ctx: JointContext
    rows: np.ndarray           # catalogue rows of the kinds measured
    todo: np.ndarray           # indices into rows of the galaxies to fit
    selected: np.ndarray       # indices into rows passing the cut
    on_any: np.ndarray
    snr: np.ndarray
    noises: list
    nmodels: int

    def windows_of(self, pixels, k: int) -> Windows:
        """Frame k's pixels (an array of its shape) kept in the windows of the galaxies fitted on it."""
        f = self.ctx.frames[k]
        out = Windows(f.shape, pixels.dtype)
        for j in self.todo[f.on[self.todo]]:
            out.keep(pixels, stamp_window(f.shape, int(self.ctx.sizes[j]), float(f.x[j]) - 1.0,
                                          float(f.y[j]) - 1.0))
        return out

    def keep_windows(self, frames, data=None) -> None:
        """Each frame's pixels (its own, or ``data``'s) read once and kept only in its galaxies' windows."""
        for k, f in enumerate(self.ctx.frames):
            given = data[k] if data is not None else None
            pixels = f.data if given is None else (given() if callable(given) else given)
            if pixels is None:
                with open_frame(frames[k]) as frame:
                    pixels = _float_pixels(frame)
            f.data = self.windows_of(pixels, k)
            del pixels

    def columns(self, results, all_rows: bool = False) -> dict:
        """The fits (one per galaxy of ``todo``) as columns, with the bookkeeping of :func:`measure_joint`."""
        ctx, todo, on_any = self.ctx, self.todo, self.on_any
        out = np.arange(len(self.rows)) if all_rows else todo
        cols = _gather(results, todo, out, _JOINT_FLOAT, _JOINT_INT)
        if all_rows:
            fitted = np.isin(out, todo)
            cols["ra"][~fitted] = ctx.cat["ra"][self.rows[out[~fitted]]]
            cols["dec"][~fitted] = ctx.cat["dec"][self.rows[out[~fitted]]]
            cols["flags"][~on_any[out]] = FLAG_OFF_FRAME
            cols["flags"][on_any[out] & ~fitted] = FLAG_BELOW_CUT
            for f in ctx.frames:
                cols["nframes"][~fitted] += f.on[out[~fitted]].astype(np.int32)
        cols["id"] = ctx.cat["id"][self.rows[out]]
        cols["snr_pred"] = self.snr[out]
        cols["_noise"] = self.noises
        cols["_counts"] = {"selected": len(self.rows), "on": int(on_any.sum()),
                           "cut": int(on_any.sum() - len(self.selected)), "fitted": len(todo),
                           "models": self.nmodels}
        cols["_todo"] = self.rows[self.selected]
        return cols


def joint_setup(frames, cat, o: MeasureOptions, *, inputs=None, psf_options=None, psf_used=None, data=None,
                only=None, within=None) -> JointSetup:
    """Read the frames' headers and choose what a joint measurement fits (:func:`measure_joint`, its parameters).

    The frames' pixels are not read here (but those of standard input,
    which cannot be read twice): :meth:`JointSetup.keep_windows` does.
    ``within`` (a mask over the catalogue) limits the galaxies considered at
    all: each frame keeps positions of those only (a study's part of a field
    among a catalogue of 0.4M objects and 169 frames would otherwise hold
    ~6 GB of them).  ``only`` limits the ones fitted.
    """
    psf, stamp = o.psf, o.stamp
    psf_options = psf_options if psf_options is not None else o.psf_options()
    min_snr = _check_min_snr(o.min_snr)
    if "ra" not in cat:
        raise PerscliError(f"{cat.get('label', 'catalogue')}: --joint needs ra/dec in the catalogue (x/y are "
                           "pixels of one frame)")
    rows, _ = select_kinds(cat, o.kinds)
    if within is not None:
        rows = rows[np.asarray(within, dtype=bool)[rows]]
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
            noise, weights, ivar = _noise_and_weights(frame, sky=o.sky, read_noise=o.read_noise)
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
    blends_all = blended_on_sky(cat["ra"], cat["dec"], o.blend_radius * pixel_scale)
    ladder = stamp_ladder(stamp)
    sizes = np.full(len(rows), stamp, dtype=np.int32)
    for j in todo:
        sizes[j] = stamp_side(cat, rows[j], pixel_scale, ladder)
    for per_psf in models:
        for n in sorted(set(sizes[todo].tolist()) - set(per_psf)):
            per_psf[n] = ExpModel(per_psf[stamp].drawer.psf, n, pixel=per_psf[stamp].drawer.pixel)
    ctx = JointContext(frames=jframes, models=models, cat=cat, rows=rows, sizes=sizes, blends=blends_all[rows],
                       rate_frame=rate_frame, stamp=stamp, pixel_scale=pixel_scale)
    return JointSetup(ctx=ctx, rows=rows, todo=todo, selected=selected, on_any=on_any, snr=snr, noises=noises,
                      nmodels=len(models))


def _float_pixels(frame) -> np.ndarray:
    """A frame's science image as floats (float32 as stored, integers as float64)."""
    pixels = np.asarray(frame.planes()[0])
    return pixels if pixels.dtype.kind == "f" else pixels.astype(np.float64)
