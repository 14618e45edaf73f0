"""A fit of data changed by a little, from the reference's minimum: the shape changes of a study.

:func:`fit_changes` fits a galaxy's reference stamps as :func:`perscli.measure.fit.fit_joint`
(or :func:`~perscli.measure.fit.fit_exp`) does, then each variant of them (the
reference plus a pixel change, e.g. persistence) from the reference's minimum:
first the fit's linear response to the change, with the full Hessian,
checked by one Newton evaluation on the changed data; further warm Newton
steps, or a fit from the start, where that check asks for them.  The change
of the minimum is what two fits from the start give, to 1e-3 of itself
(tests/test_measure_changes.py), at a fraction of their cost.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from .fit import (_PIXEL_FLOORS, _SKY_FLOORS, FLAG_FAILED, FLAG_FEW_PIXELS, MAX_NFEV, MIN_PIXELS, ExpModel,
                  FitResult, _finish, _newton, _Problem, _Stamp, _valid, joint_problem, stamp_mapping)

#: a change whose linear response moves g by more than this is refitted from the start, as a fit of the
#: changed data alone would be: far from the reference's minimum the warm and the cold fit may not meet
COLD_ABOVE = 1e-2
#: warm Newton evaluations allowed before the change is refitted from the start
MAX_WARM_NFEV = 4
#: the reference of a shape change is fitted to this step tolerance (the exact minimum is one Newton step away:
#: :func:`fit_changes`)
REF_XTOL = 1e-6
#: a change's linear response is taken (with the check's correction) when that correction is below this
#: fraction of the response, component by component: its error is then of the correction's square's order
LINEAR_REL = 1e-2

#: how a change's fit was obtained: no pixel of the stamps changed; the linear response from the
#: reference's minimum, checked by one Newton evaluation (or below the tolerance already); further warm
#: Newton steps; or a fit from the start, as of the changed data alone
CHANGE_METHODS = ("same", "linear", "newton", "cold")


@dataclass
class Change:
    """The fit of one variant of the data (the reference plus a pixel change), and how it was reached.

    Attributes
    ----------
    result : FitResult
    method : str
        One of :data:`CHANGE_METHODS`.
    bound : float
        The largest component, in g, of the last Newton correction computed
        at the reported point: how far the point may be from the exact
        minimum of the changed data (0 for 'same'; for 'linear' the check's
        correction, which is added, so the error left is of its square's
        order).
    """

    result: FitResult
    method: str
    bound: float


def _changed_problem(problem: _Problem, delta) -> _Problem:
    """``problem`` with each stamp's data plus ``delta`` (per stamp an array, or None for no change)."""
    stamps = []
    for st, d in zip(problem.stamps, delta):
        new = object.__new__(_Stamp)
        new.sw, new.npix, new.model = st.sw, st.npix, st.model
        new.swd = st.swd if d is None else st.swd + st.sw * np.where(st.sw > 0, d, 0.0)
        stamps.append(new)
    return _Problem(stamps, problem.mapping)


def _solve(A, S, b):
    """The Newton step: (A + S)^-1 b where A + S is positive definite, else Gauss-Newton's A^-1 b."""
    H = A
    if S is not None:
        try:
            np.linalg.cholesky(A + S)
            H = A + S
        except np.linalg.LinAlgError:
            pass
    return np.linalg.solve(H, b)


def fit_changes(problem: _Problem, start, floors, npix: int, deltas, *, max_nfev: int = MAX_NFEV,
                xtol: float = 1e-10, cold: bool = False, cold_start=None):
    """The reference fit, and the fit of each variant of its data, each from the reference's minimum.

    The reference is fitted from ``start`` as :func:`fit_joint` / :func:`fit_exp`
    fit.  A variant (the data plus a change ``delta``) is then fitted from
    the reference's minimum theta*: its first step is the linear response
    of the fit to the change, (A + S)^-1 J^T W (r* + delta) with A + S the
    full Hessian at theta* (its residual's second-order term included), the
    exact first-order change of the minimum.  That point is checked with one
    Newton evaluation on the changed data: when the Newton step there is
    below the fit's own tolerance, the point is the changed data's minimum by
    the rule every fit stops on, and the step is added ('linear'); otherwise
    warm Newton steps continue ('newton').  A change whose linear response
    moves g by more than :data:`COLD_ABOVE` (a ghost on the galaxy), or that
    warm steps do not settle within :data:`MAX_WARM_NFEV`, is fitted from
    ``start`` like the reference ('cold'), as a fit of the changed data alone
    would be.  Changes that touch no pixel give the reference's fit ('same').

    Parameters
    ----------
    problem : _Problem
        The reference's stamps.
    start : sequence of 6 floats
    floors : ndarray
        Parameter scales of the tolerance.
    npix : int
        Usable pixels (degrees of freedom).
    deltas : sequence
        Per variant: per stamp of ``problem`` the change (an array of the
        stamp's shape, in the stamp's units), or None for none; or None for a
        variant that changes no stamp.
    cold : bool
        Also fit every changed variant from the start (whatever its linear
        response): the reference for the checks of the linear response.
    cold_start : sequence of 6 floats, optional
        Where a variant's fit from the start starts (default ``start``): the
        start of a fit of its data alone, when ``start`` is nearer the
        minimum than such a fit would start (the same minimum, reached in
        fewer steps).

    Returns
    -------
    (FitResult, list of Change, list of FitResult or None)
        The reference's fit, each variant's :class:`Change`, and with ``cold``
        each variant's fit from ``start`` (None where nothing changed).
    """
    ref, theta, chi2, flags, A, point = _fit_reference(problem, start, floors, npix, max_nfev=max_nfev, xtol=xtol,
                                                       cold_start=cold_start)
    changes, colds = [], []
    state = None
    for delta in deltas:
        if delta is None or all(d is None for d in delta):
            changes.append(Change(ref, "same", 0.0))
            colds.append(None)
            continue
        varied = _changed_problem(problem, delta)

        def from_start():
            th, c2, AA, nf, fl, _ = _newton(varied, start if cold_start is None else cold_start, floors, _valid,
                                           max_nfev=max_nfev, xtol=xtol)
            return _finish(th, c2, AA, npix, nf, fl)

        colds.append(from_start() if cold else None)
        if ref.flags:
            # no minimum to start from: the variant is fitted as the reference was
            changes.append(Change(colds[-1] or from_start(), "cold", math.nan))
            continue
        if state is None:
            state = _reference_minimum(problem, theta, A, point)
            # the reference reported at its exact minimum, as a fit to the tolerance would have it
            ref.theta = theta + state[-1]
            ref.nfev += 1
        change = _warm_change(problem, varied, delta, state, theta=theta, chi2=chi2, flags=flags, floors=floors,
                              npix=npix, xtol=xtol)
        # None: refitted from the start, as a fit of the changed data alone would be
        changes.append(change if change is not None else Change(colds[-1] or from_start(), "cold", math.nan))
    return ref, changes, colds


def _fit_reference(problem: _Problem, start, floors, npix: int, *, max_nfev: int, xtol: float,
                   cold_start=None) -> tuple:
    """The reference's fit for :func:`fit_changes`: to :data:`REF_XTOL` from ``start``.

    Returns
    -------
    (FitResult, ndarray, float, int, ndarray, Point)
        The fit, and the theta, chi2, flags, J^T W J and
        :class:`~perscli.measure.fit.Point` of the last Newton step of
        :func:`perscli.measure.fit._newton`.
    """
    # the reference to REF_XTOL only: the Newton step computed at its minimum for the variants takes it the
    # rest of the way (to the square of where it stopped), so its last steps would be spent twice
    theta, chi2, A, nfev, flags, point = _newton(problem, start, floors, _valid, max_nfev=max_nfev,
                                                 xtol=max(xtol, REF_XTOL))
    ref = _finish(theta, chi2, A, npix, nfev, flags)
    if ref.flags:
        # no clean minimum (a fit that failed, or stopped at |g| = 1): fitted as a fit of the data alone is, and
        # every variant likewise (their difference is then that of two such fits)
        first = start if cold_start is None else cold_start
        theta, chi2, A, nf, flags, point = _newton(problem, first, floors, _valid, max_nfev=max_nfev, xtol=xtol)
        ref = _finish(theta, chi2, A, npix, nfev + nf, flags)
    return ref, theta, chi2, flags, A, point


def _reference_minimum(problem: _Problem, theta, A, point) -> tuple:
    """The reference's minimum: once per galaxy.

    The reference stopped where its next step fell below the tolerance;
    that step (``own``) is what is left to its exact minimum, against which
    a variant's change is measured: De is the change of the minimum, not of
    where two fits happened to stop.  The fit's last point gives J^T W J,
    the gradient and the Jacobians; the Hessian's second-order term is taken
    again with that point's own residual (the fit's is the point before's,
    which can be a step of 1e-3 away and would cost the linear response a
    few 1e-4 of itself): :meth:`~perscli.measure.fit._Problem.second_order`,
    without the model's planes.

    Returns
    -------
    (A0, b0, S0, jts, spectra, own)
        The Gauss-Newton matrix, gradient and second-order term at
        ``theta``, each stamp's Jacobian (transposed), the spectra of its
        residual, and the step to the exact minimum.
    """
    spectra = problem.spectra(point.us)
    A0, b0, jts = A, point.b, point.jts
    S0 = problem.second_order(theta, spectra)
    try:
        own = _solve(A0, S0, b0)
    except np.linalg.LinAlgError:
        own = np.zeros(6)
    if not np.all(np.isfinite(own)):
        own = np.zeros(6)
    return A0, b0, S0, jts, spectra, own


def _warm_change(problem: _Problem, varied: _Problem, delta, state: tuple, *, theta, chi2, flags, floors, npix: int,
                 xtol: float):
    """A variant's fit from the reference's minimum: its linear response, checked, or warm Newton steps.

    Parameters
    ----------
    problem, varied : _Problem
        The reference's stamps, and the variant's (the data plus ``delta``).
    state : tuple
        The reference's minimum (:func:`_reference_minimum`).
    theta, chi2, flags
        The reference's fit (:func:`_fit_reference`).

    Returns
    -------
    Change or None
        'linear' or 'newton'; None where the variant is to be fitted from
        the start ('cold').
    """
    A0, b0, S0, jts, spectra, own = state
    b = np.zeros(6)
    for st, jt, d in zip(problem.stamps, jts, delta):
        if d is not None:
            b += jt @ (st.sw * np.where(st.sw > 0, d, 0.0)).ravel()
    try:
        # the linear response to the change alone, from the reference's exact minimum
        step = _solve(A0, S0, b) + own
    except np.linalg.LinAlgError:
        step = None
    if step is None or not np.all(np.isfinite(step)) or max(abs(step[2]), abs(step[3])) > COLD_ABOVE:
        return None
    scale = np.maximum(np.abs(theta), floors)
    if np.all(np.abs(step) <= xtol * scale):
        # the Newton step from theta* on the changed data is below the tolerance: theta* + step is its
        # minimum by the fitter's own rule (the error left is of the step's square's order)
        th1 = theta + step
        res = _finish(th1, chi2, A0, npix, 1, flags)
        return Change(res, "linear", float(max(abs(step[2]), abs(step[3]))))
    th1 = theta + step
    if _valid(th1, theta) != "ok":
        return None
    # the check: one Newton evaluation at the linear response, on the changed data (the second-order
    # term with the reference's residual, as every trial point of a fit takes the previous point's)
    c1, A1, b1, S1, _, _ = varied.evaluate(th1, spectra)
    try:
        corr = _solve(A1, S1, b1)
    except np.linalg.LinAlgError:
        corr = None
    if corr is not None and np.all(np.isfinite(corr)):
        # th1 + corr is within |corr|^2 (and |corr| times the second-order term's small change with
        # the data) of the minimum: taken when the correction is below the tolerance, or below
        # LINEAR_REL of the change itself (then its error is orders below what the change needs)
        limit = np.maximum(xtol * np.maximum(np.abs(th1), floors), LINEAR_REL * np.abs(step - own))
        if np.all(np.abs(corr) <= limit):
            res = _finish(th1 + corr, c1, A1, npix, 2, flags)
            return Change(res, "linear", float(max(abs(corr[2]), abs(corr[3]))))
    # further warm steps: a damped Newton fit from the linear response
    th, c2, AA, nf, fl, _ = _newton(varied, th1, floors, _valid, max_nfev=MAX_WARM_NFEV, xtol=xtol)
    if fl & FLAG_FAILED:
        return None
    return Change(_finish(th, c2, AA, npix, 2 + nf, fl), "newton", float(max(abs(th[2] - th1[2]), abs(th[3] - th1[3]))))


def fit_joint_changes(stamps, start, deltas, *, max_nfev: int = MAX_NFEV, xtol: float = 1e-10, cold: bool = False,
                      cold_start=None):
    """:func:`fit_joint` of a galaxy and of each variant of its stamps (:func:`fit_changes`).

    Parameters
    ----------
    stamps : sequence of JointStamp
        The reference.
    start : sequence of 6 floats
    deltas : sequence
        Per variant: per stamp of ``stamps`` its change (array or None), or None.
    """
    problem, npix, keep = joint_problem(stamps)
    theta = np.array(start, dtype=np.float64)
    if problem is None:
        few = FitResult(theta, np.full(6, np.nan), np.nan, 0, 0, FLAG_FEW_PIXELS, 0.0)
        return few, [Change(few, "same", 0.0) for _ in deltas], [None for _ in deltas]
    used = [None if d is None else [d[k] for k in keep] for d in deltas]
    return fit_changes(problem, theta, _SKY_FLOORS, npix, used, max_nfev=max_nfev, xtol=xtol, cold=cold,
                       cold_start=cold_start)


def fit_exp_changes(image, weight, model: ExpModel, start, deltas, *, max_nfev: int = MAX_NFEV,
                    xtol: float = 1e-10, cold: bool = False, cold_start=None):
    """:func:`fit_exp` of a stamp and of each variant of it (:func:`fit_changes`); ``deltas``: per variant
    the change (an array of the stamp's shape) or None."""
    stamp = _Stamp(image, weight, model)
    theta = np.array(start, dtype=np.float64)
    if stamp.npix < MIN_PIXELS:
        few = FitResult(theta, np.full(6, np.nan), np.nan, 0, 0, FLAG_FEW_PIXELS, 0.0)
        return few, [Change(few, "same", 0.0) for _ in deltas], [None for _ in deltas]
    problem = _Problem([stamp], stamp_mapping)
    return fit_changes(problem, theta, _PIXEL_FLOORS, stamp.npix, [None if d is None else [d] for d in deltas],
                       max_nfev=max_nfev, xtol=xtol, cold=cold, cold_start=cold_start)
