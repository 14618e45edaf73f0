"""The effects diagnose can add to a model or re-tune: one reported parameter of a registered effect each.

A candidate names the detector effect (from the registry render uses), the
parameter it reports, the range it is fitted in, how a value is put into a
model, and the residual probe that separates it from the others.  A new
candidate is one more :class:`Candidate` in :data:`CANDIDATES` (its effect
registered in :mod:`perscli.detector.effects` with ``@register``).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Callable

import numpy as np

from .checks import line_means, line_variance_fit
from .likelihood import with_effect


@dataclass(frozen=True)
class Candidate:
    """One effect's strength, fitted by likelihood.

    Attributes
    ----------
    name : str
        The effect's name in the report (and in the registry).
    param : str
        The parameter reported.
    unit : str
    bounds : (float, float)
        The range searched.
    scale : float
        A typical size of the parameter (sets the fit's tolerance).
    probe : str
        The residual probe that shows this effect.
    meaning : str
    get : callable
        ``get(model, exposures) -> float``: the value the model has (its 'off' value when absent).
    put : callable
        ``put(model, value) -> DetectorModel``: a copy with the effect on at ``value``.
    applies : callable
        ``applies(exposures) -> bool``: whether the data can constrain it.
    fit : callable, optional
        ``fit(problem, model) -> (value, error, model, nparams[, more])`` for
        a candidate fitted its own way (instead of a one-parameter search);
        ``more`` may give ``delta_chi2`` (when the improvement is not that of
        the pixels' likelihood) and ``extra``/``extra_errors`` (its other
        parameters).
    """

    name: str
    param: str
    unit: str
    bounds: tuple
    scale: float
    probe: str
    meaning: str
    get: Callable
    put: Callable
    applies: Callable = lambda exposures: True
    fit: Callable | None = None


def _value(effect, key, off=0.0):
    def get(model, exposures):
        return float(model.value(effect, key, off=off))
    return get


def _set(effect, key):
    def put(model, value):
        return with_effect(model, effect, {key: float(value)})
    return put


# -- persistence: A of the Fermi law, the other parameters held at the model's ---------------------

def _get_persistence(model, exposures):
    return float(model.persistence_model().A) if model.enabled("persistence") else 0.0


def _put_persistence(model, value):
    eff = model.get("persistence")
    params = dict(eff.params) if eff is not None else {}
    params = {k: v for k, v in params.items() if v is not None}
    params["A"] = float(value)
    if params.get("kind", "fermi") != "fermi":
        params = {"A": float(value)}
    return with_effect(model, "persistence", params)


# -- IPC: one coupling strength first (the model's kernel shape scaled), all 8 couplings when the data ask --

_CROSS = np.array([[0.0, 1.0, 0.0], [1.0, 0.0, 1.0], [0.0, 1.0, 0.0]])


def _kernel(model) -> np.ndarray | None:
    if not model.enabled("ipc"):
        return None
    return model.get("ipc").instance().kernel()


def _get_ipc(model, exposures):
    k = _kernel(model)
    return 0.0 if k is None else float((k[0, 1] + k[1, 0] + k[1, 2] + k[2, 1]) / 4.0)


def _put_ipc(model, value):
    """The model's kernel with its couplings scaled so that the 4 nearest neighbours' mean is ``value``
    (a symmetric nearest-neighbour cross when the model has no coupling): the one-parameter template.

    Interpixel capacitance comes from the capacitance between a pixel and its neighbours; a detector whose
    coupling is stronger or weaker than the model's keeps the kernel's shape (its diagonal couplings, ~8% of
    the nearest ones in Roman's kernel, and its small asymmetry) and changes its strength.  One parameter
    has the power of a matched filter; the 8 free couplings of :func:`ipc_free_shape` cost about half of it
    (their mean is correlated with every one of them) and are fitted only when the data ask for them.
    """
    k = _kernel(model)
    shape = _CROSS if k is None or _get_ipc(model, None) <= 0 else k.copy()
    shape = shape.copy()
    shape[1, 1] = 0.0
    nn = (shape[0, 1] + shape[1, 0] + shape[1, 2] + shape[2, 1]) / 4.0
    off = shape * (float(value) / nn)
    kernel = off.copy()
    kernel[1, 1] = 1.0 - off.sum()      # charge is conserved, as in the Roman kernel
    return with_effect(model, "ipc", {"kernel": kernel.tolist(), "alpha": None})


_OFFSETS = [(j, i) for j in range(3) for i in range(3) if (j, i) != (1, 1)]
_NN = [k for k, (j, i) in enumerate(_OFFSETS) if abs(j - 1) + abs(i - 1) == 1]


def ipc_free_shape(problem, model) -> dict:
    """The 8 couplings of a 3x3 kernel fitted freely, against the one-parameter template of ``model``.

    IPC is linear in the kernel, so the expectation is that without IPC plus
    one column per coupling (a neighbour's signal minus the pixel's own:
    charge is conserved); the couplings come from weighted linear least
    squares with the variance of ``model`` held.  The template (the kernel
    of ``model`` scaled, :func:`_put_ipc`) is the same least squares along
    one direction of the 8; the difference of the two chi^2 is the evidence
    for another shape, a chi^2 with 7 degrees of freedom when the template's
    shape is right.

    Returns
    -------
    dict
        ``kernel`` (3x3 list), ``alpha`` (the 4 nearest neighbours' mean
        coupling) and ``error`` (its marginal error, the other 7 free),
        ``delta_chi2`` (chi^2 of the template minus that of the free fit),
        ``model`` (``model`` with the free kernel).
    """
    base = with_effect(model, "ipc", enabled=False)
    ev0 = problem.evaluate(base)
    variances = problem.evaluate(model).variance
    columns = []
    for j, i in _OFFSETS:
        kernel = np.zeros((3, 3))
        kernel[j, i] = 1.0
        # the kernel e_j - e_centre + delta = e_j: what one unit of coupling to neighbour j adds
        moved = problem.evaluate(with_effect(model, "ipc", {"kernel": kernel.tolist(), "alpha": None})).mean
        columns.append([m - m0 for m, m0 in zip(moved, ev0.mean)])
    ata = np.zeros((8, 8))
    atb = np.zeros(8)
    rwr = 0.0
    for piece in range(len(ev0.mean)):
        mask = ev0.mask[piece]
        w = 1.0 / variances[piece][mask]
        r = ev0.data[piece][mask] - ev0.mean[piece][mask]
        cols = np.stack([c[piece][mask] for c in columns])
        ata += (cols * w) @ cols.T
        atb += cols @ (w * r)
        rwr += float(np.sum(w * r * r))
    cov = np.linalg.pinv(ata)
    k = cov @ atb
    free_chi2 = rwr - float(k @ atb)
    # the template's direction in the couplings: the model's off-centre kernel (or the cross), per unit of alpha
    shape = _kernel(_put_ipc(model, 1.0))
    u = np.array([shape[j, i] for j, i in _OFFSETS])
    s = float(u @ atb) / float(u @ ata @ u)
    template_chi2 = rwr - s * float(u @ atb)
    kernel = np.zeros((3, 3))
    for (j, i), v in zip(_OFFSETS, k):
        kernel[j, i] = v
    kernel[1, 1] = 1.0 - k.sum()
    alpha = float(np.mean(k[_NN]))
    error = float(np.sqrt(max(np.sum(cov[np.ix_(_NN, _NN)]) / 16.0, 0.0)))
    return {"kernel": kernel.tolist(), "alpha": alpha, "error": error,
            "delta_chi2": max(template_chi2 - free_chi2, 0.0),
            "model": with_effect(model, "ipc", {"kernel": kernel.tolist(), "alpha": None})}


# -- gain: only when the measured frames are in DN ---------------------------------------------------

def _get_gain(model, exposures):
    if model.enabled("gain"):
        return float(model.value("gain", "gain"))
    gains = [e.gain for e in exposures if e.counts == "DN" and e.gain]
    return float(gains[0]) if gains else 1.0


def _dn(exposures):
    return any(e.counts == "DN" for e in exposures)


# -- correlated read noise: its row and column variances from the residual rows' and columns' means ------

def _fit_correlated(problem, model):
    """The row and column components of the read noise, each the variance the lines' mean residuals have
    beyond white noise (maximum likelihood; the diagonal likelihood cannot see them, so the improvement is
    that of the lines' likelihood, two parameters)."""
    base = with_effect(model, "correlated_read_noise", {"row": 0.0, "column": 0.0})
    lines = line_means(problem, problem.evaluate(base), base)
    g = float(np.mean(lines["gain"])) if lines["gain"] else 1.0
    rv, drow, erow = line_variance_fit(lines["row"])
    cv, dcol, ecol = line_variance_fit(lines["column"])
    row, column = math.sqrt(rv) * g, math.sqrt(cv) * g
    fitted = with_effect(model, "correlated_read_noise", {"row": row, "column": column})
    return row, erow * g, fitted, 2, {"delta_chi2": drow + dcol, "extra": {"column": column},
                                      "extra_errors": {"column": ecol * g}}


CANDIDATES = (
    Candidate("persistence", "A", "e-/s", (0.0, 2.0), 0.02, "history",
              "the paper's Fermi model (x0, dx, alpha, gamma held), exact time integral",
              _get_persistence, _put_persistence, lambda exposures: len(exposures) > 1),
    Candidate("ipc", "alpha", "", (0.0, 0.1), 0.01, "neighbours",
              "mean coupling to the 4 nearest neighbours: the model's kernel scaled (all 8 couplings free when "
              "the data ask for another shape)", _get_ipc, _put_ipc),
    Candidate("nonlinearity", "beta", "1/e-", (-1e-5, 1e-5), 5e-7, "signal",
              "x -> x + beta x^2, per electron", _value("nonlinearity", "beta"), _set("nonlinearity", "beta")),
    Candidate("reciprocity", "alpha", "", (0.0, 0.1), 0.005, "signal",
              "reciprocity failure per decade of flux, as in render", _value("reciprocity", "alpha"),
              _set("reciprocity", "alpha")),
    Candidate("dark", "current", "e-/pixel/s", (0.0, 50.0), 0.05, "exposure_time",
              "dark current, scales with exposure time", _value("dark", "current"), _set("dark", "current")),
    Candidate("offset", "level", "e-", (-5000.0, 5000.0), 5.0, "offset",
              "noiseless level added to every exposure, independent of exposure time",
              _value("offset", "level"), _set("offset", "level")),
    Candidate("read_noise", "sigma", "e-", (0.0, 200.0), 1.0, "excess_variance",
              "Gaussian read noise per pixel", _value("read_noise", "sigma"), _set("read_noise", "sigma")),
    Candidate("brighter_fatter", "coefficient", "1/e-", (0.0, 1e-6), 1e-8, "neighbours",
              "charge-dependent spreading: coefficient/2 (q_j^2 - q_i^2) flows between nearest neighbours",
              _value("brighter_fatter", "coefficient"), _set("brighter_fatter", "coefficient")),
    Candidate("correlated_read_noise", "row", "e-", (0.0, 200.0), 0.5, "rows_columns",
              "read noise common to whole rows (row) and whole columns (column)",
              _value("correlated_read_noise", "row"), _set("correlated_read_noise", "row"), fit=_fit_correlated),
    Candidate("gain", "gain", "e-/DN", (0.05, 50.0), 0.05, "signal",
              "the true e-/DN, when the header's GAIN is wrong", _get_gain, _set("gain", "gain"), _dn),
)

def by_name(name: str) -> Candidate:
    return next(c for c in CANDIDATES if c.name == name)
