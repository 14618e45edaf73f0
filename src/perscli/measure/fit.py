"""Exponential-profile shape fits, exact in the PSF and deterministic to 1e-10.

The galaxy is the 6-Gaussian mixture of the exponential profile (Hogg & Lang
2013, the model ngmix calls 'exp') with parameters (x, y, g1, g2, T, flux):
component i has flux fraction p_i and covariance ``f_i (T/2) [[1+e1, e2],
[e2, 1-e1]]`` with e = 2g/(1+|g|^2).  Its Fourier transform is analytic, and
so are the transform's first and second derivatives with respect to every
parameter.  The PSF enters as its Fourier transform times the pixel
response (or alone, for an effective PSF that includes the pixel already:
:mod:`perscli.measure.psf`), tabulated once per stamp size
(:class:`perscli.optics.StampDrawer`, the renderer's own table), and
pixel values come from the fold of the frequencies above Nyquist and one
inverse FFT: no Gaussian approximation of the PSF, whose rings and spikes a
few Gaussians cannot follow (that is where ngmix-style fits lose accuracy on
Roman images).

The fit is a damped Newton method (Levenberg-Marquardt on the full Hessian)
in float64, with an exp accurate to 2 ulp, a step tolerance of 1e-10 and a
starting point that depends only on the object's catalogue values, so that
two images that differ by a tiny pattern give shape changes linear in that
pattern down to ~1e-10.  Why the full Hessian: the Gauss-Newton matrix J^T J
leaves out sum(residual x second derivative), which for a galaxy at S/N ~10
is a good part of the curvature; Gauss-Newton then converges linearly, slowly
(30-90 model evaluations per faint galaxy on a real frame), and stopped on a
flat chi^2 it left g off by ~1e-6.  The missing term is gathered in the same
compiled pass as the model (Parseval: the residual's transform times the
model's second-derivative spectra, no extra inverse FFT), with the residual
of the last accepted point, and the fit converges quadratically to the exact
minimum in about 10 evaluations (90% within 17 on a real frame).

:func:`fit_exp` fits one stamp with g, position and T in that stamp's pixel
axes; :func:`fit_joint` fits one galaxy on several stamps (frames with their
own PSF, pointing and orientation) with common parameters defined on the sky,
mapped into each stamp through its local WCS Jacobian.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import scipy.fft

from .. import _kernels
from ..optics import StampDrawer

#: Hogg & Lang (2013) exponential, M=6: amplitudes and sqrt(variances) in units of r_e.
HL_AMPLITUDES = np.array([0.00735, 0.09481, 0.63572, 2.60077, 5.42848, 3.16445])
HL_SIGMAS = np.array([0.05072, 0.13756, 0.28781, 0.53195, 0.91209, 1.50157])
P_EXP = HL_AMPLITUDES / HL_AMPLITUDES.sum()
F_EXP = HL_SIGMAS ** 2 / np.sum(P_EXP * HL_SIGMAS ** 2)

PARAMS = ("x", "y", "g1", "g2", "T", "flux")

# flags
FLAG_FAILED = 1          # no convergence within the iteration limit
FLAG_EDGE = 2            # the stamp runs off the image
FLAG_BAD_SIZE = 4        # T <= 0 at the end
FLAG_BAD_FLUX = 8        # flux <= 0 at the end
FLAG_FEW_PIXELS = 16     # too few usable pixels
FLAG_SHEAR = 32          # |g| reached 1
FLAG_SINGULAR = 64       # the normal matrix could not be inverted for errors

#: model evaluations allowed per fit (a converging fit needs about 10, 63 at worst on a real frame)
MAX_NFEV = 100
#: smallest usable pixels of a fit
MIN_PIXELS = 20
#: |g|^2 above which a trial step is refused, and at which |g| counts as having reached 1
G2_LIMIT, G2_FLAG = 0.999, 0.998
#: relative rounding of chi^2 (a float64 sum of up to ~1e5 squares): changes below it are not changes
CHI2_ROUNDING = 1e-11


def g_to_e(g1: float, g2: float):
    """Distortion e and its Jacobian d(e1, e2)/d(g1, g2) for a reduced shear g."""
    gg = g1 * g1 + g2 * g2
    den = 1.0 + gg
    e1, e2 = 2.0 * g1 / den, 2.0 * g2 / den
    d = 1.0 / (den * den)
    jac = np.array([[2.0 * (den - 2.0 * g1 * g1) * d, -4.0 * g1 * g2 * d],
                    [-4.0 * g1 * g2 * d, 2.0 * (den - 2.0 * g2 * g2) * d]])
    return e1, e2, jac


def g_to_e_hessian(g1: float, g2: float) -> np.ndarray:
    """Second derivatives of e with respect to g: array [i, a, b] = d^2 e_i / dg_a dg_b."""
    s = 1.0 + g1 * g1 + g2 * g2
    s2, s3 = s * s, s * s * s
    a = -12.0 * g1 / s2 + 16.0 * g1 ** 3 / s3           # d2 e1 / dg1 dg1
    c = -4.0 * g2 / s2 + 16.0 * g1 * g1 * g2 / s3       # d2 e1 / dg1 dg2 = d2 e2 / dg1 dg1
    d = -4.0 * g1 / s2 + 16.0 * g1 * g2 * g2 / s3       # d2 e1 / dg2 dg2 = d2 e2 / dg1 dg2
    e = -12.0 * g2 / s2 + 16.0 * g2 ** 3 / s3           # d2 e2 / dg2 dg2
    return np.array([[[a, c], [c, d]], [[c, d], [d, e]]])


def shape_covariance(g1: float, g2: float, T: float, *, second: bool = False):
    """The mixture's unit covariance (Cxx, Cxy, Cyy) = (T/2) (1+e1, e2, 1-e1) and its derivatives.

    Returns
    -------
    cov : ndarray (3,)
    dcov : ndarray (3, 3)
        d cov_c / d (g1, g2, T)_j, row c.
    d2cov : ndarray (3, 3, 3) or None
        d^2 cov_c / d theta_a d theta_b (with ``second``).
    """
    # plain floats, one array at the end: this runs at every model evaluation
    g1, g2, T = float(g1), float(g2), float(T)
    den = 1.0 + g1 * g1 + g2 * g2
    e1, e2 = 2.0 * g1 / den, 2.0 * g2 / den
    dd = 1.0 / (den * den)
    d11, d12 = 2.0 * (den - 2.0 * g1 * g1) * dd, -4.0 * g1 * g2 * dd
    d21, d22 = d12, 2.0 * (den - 2.0 * g2 * g2) * dd
    h = 0.5 * T
    cov = np.array([h * (1.0 + e1), h * e2, h * (1.0 - e1)])
    dcov = np.array([[h * d11, h * d12, 0.5 * (1.0 + e1)],
                     [h * d21, h * d22, 0.5 * e2],
                     [-h * d11, -h * d12, 0.5 * (1.0 - e1)]])
    if not second:
        return cov, dcov, None
    s2, s3 = dd, dd / den
    a = -12.0 * g1 * s2 + 16.0 * g1 ** 3 * s3
    c = -4.0 * g2 * s2 + 16.0 * g1 * g1 * g2 * s3
    d = -4.0 * g1 * s2 + 16.0 * g1 * g2 * g2 * s3
    e = -12.0 * g2 * s2 + 16.0 * g2 ** 3 * s3
    d2 = np.array([[[h * a, h * c, 0.5 * d11], [h * c, h * d, 0.5 * d12], [0.5 * d11, 0.5 * d12, 0.0]],
                   [[h * c, h * d, 0.5 * d21], [h * d, h * e, 0.5 * d22], [0.5 * d21, 0.5 * d22, 0.0]],
                   [[-h * a, -h * c, -0.5 * d11], [-h * c, -h * d, -0.5 * d12], [-0.5 * d11, -0.5 * d12, 0.0]]])
    return cov, dcov, d2


def covariance_map(ainv) -> np.ndarray:
    """The linear map of a covariance (Cuu, Cuv, Cvv) on the sky to (Cxx, Cxy, Cyy) in pixels.

    ``ainv`` is d(x, y)/d(u, v), the inverse of the local WCS Jacobian:
    C_pix = ainv C_sky ainv^T.
    """
    a00, a01, a10, a11 = float(ainv[0][0]), float(ainv[0][1]), float(ainv[1][0]), float(ainv[1][1])
    return np.array([[a00 * a00, 2.0 * a00 * a01, a01 * a01],
                     [a00 * a10, a00 * a11 + a01 * a10, a01 * a11],
                     [a10 * a10, 2.0 * a10 * a11, a11 * a11]])


def stamp_planes(spec, L: int, n: int, pad: int) -> np.ndarray:
    """``irfft2`` of half-plane spectra (..., L, L/2 + 1), only the stamp [pad, pad + n)^2 of each plane.

    The inverse along the rows first (every column of the half plane), then
    along the columns only for the stamp's n rows of the L: what ``irfft2``
    computes in the same order, without the rows the stamp does not use
    (a third to a half of the second pass at the stamp sizes of a fit).
    """
    rows = scipy.fft.ifft(spec, axis=-2)[..., pad:pad + n, :]
    return scipy.fft.irfft(rows, n=L, axis=-1)[..., pad:pad + n]


class ExpModel:
    """Model images, Jacobians and Hessian terms of the exponential mixture through one PSF, on n x n stamps.

    Parameters
    ----------
    psf : galsim.GSObject
        The PSF in pixel units of the frame, normalised to 1.
    n : int
        Stamp size.
    pad : int
        FFT size is n + 2 pad: the model is periodic on that size, so light
        that leaves the stamp by less than ``pad`` pixels does not come back.
    pixel : bool
        Whether the model multiplies the PSF's transform by the pixel
        response: True for an optical PSF, False for one that includes it
        already (an effective PSF).
    """

    def __init__(self, psf, n: int, pad: int = 8, pixel: bool = True):
        self.n = int(n)
        self.pad = int(pad)
        self.size = self.n + 2 * self.pad
        self.drawer = StampDrawer(psf, pixel=pixel)
        transfer, k = self.drawer.table(self.size)
        self.alias = self.drawer.alias
        self.tr_re = np.ascontiguousarray(transfer.real, dtype=np.float64)
        self.tr_im = np.ascontiguousarray(transfer.imag, dtype=np.float64)
        self.k = np.ascontiguousarray(k, dtype=np.float64)
        half = self.size // 2 + 1
        # weight of each rfft column in a sum over the full plane: the DC and Nyquist columns once
        self.wcol = np.full(half, 2.0)
        self.wcol[0] = self.wcol[-1] = 1.0
        self._spec = np.empty((7, self.size, half), dtype=np.complex128)
        self._work = np.empty(2 * 8 * self.size * half)
        self._grid = np.zeros((self.size, self.size))

    def evaluate(self, centre, cov, flux, dpos, dshape, nfield: int = 7, resid=None):
        """Model stamp and derivatives for a centre, a unit covariance and a flux.

        Parameters
        ----------
        centre : (float, float)
            x, y in stamp pixel coordinates (pixel (i, j) centred at (i, j), 0-indexed).
        cov : sequence of 3 floats
            (Cxx, Cxy, Cyy), pixel^2: component i has covariance f_i C.
        flux : float
        dpos : (2, 2) array
            d(x, y)/d(position parameters).
        dshape : (3, 3) array
            d(Cxx, Cxy, Cyy)/d(shape parameters).
        nfield : {1, 7}
            1: the model only; 7: and its derivatives in the two position
            parameters, the three shape parameters and the flux.
        resid : ndarray, optional
            :meth:`residual_spectrum` of a weighted residual: then the 21
            Hessian sums are returned too.

        Returns
        -------
        images : ndarray (nfield, n, n)
            A view into this model's work space, valid until the next call.
        hsums : ndarray (21,) or None
            Sums for :func:`hessian_term`.
        """
        L, half = self.size, self.size // 2 + 1
        # centre relative to the FFT grid's origin: stamp pixel 0 is grid index pad
        phase_x = np.exp(-1j * self.k * (float(centre[0]) + self.pad))
        phase_y = np.exp(-1j * self.k * (float(centre[1]) + self.pad))
        dp = np.asarray(dpos, dtype=np.float64)
        ds = np.asarray(dshape, dtype=np.float64)
        hess = None if resid is None else np.empty(21 * half)
        spec = self._spec[:nfield]
        _kernels.expmix_eval(spec, self._work, self.tr_re, self.tr_im, self.k,
                             phase_x, phase_y, P_EXP, F_EXP, L, self.alias, nfield,
                             (float(cov[0]), float(cov[1]), float(cov[2]), float(flux)),
                             (dp[0, 0], dp[0, 1], dp[1, 0], dp[1, 1]), tuple(ds.ravel().tolist()),
                             resid, hess, self.wcol)
        if nfield == 7 and flux != 0:
            # the flux derivative is the model over the flux: no inverse transform of its own
            images = np.empty((7, self.n, self.n))
            images[:6] = stamp_planes(spec[:6], L, self.n, self.pad)
            np.divide(images[0], flux, out=images[6])
        else:
            images = stamp_planes(spec, L, self.n, self.pad)
        if hess is None:
            return images, None
        return images, hess.reshape(21, half).sum(axis=1) / (L * L)

    def residual_spectrum(self, u):
        """The rfft2 of a stamp-sized array placed on the FFT grid (for ``resid``)."""
        grid = self._grid
        grid[self.pad:self.pad + self.n, self.pad:self.pad + self.n] = u
        return scipy.fft.rfft2(grid)

    def image(self, theta, jacobian: bool = False):
        """Model stamp (and its Jacobian, shape (n, n, 6)) for parameters theta.

        theta = (x, y, g1, g2, T, flux): x, y the centre in stamp pixel
        coordinates (pixel (i, j) centred at (i, j), 0-indexed), T in pixel^2.
        """
        x, y, g1, g2, T, flux = (float(v) for v in theta)
        cov, dcov, _ = shape_covariance(g1, g2, T)
        images, _ = self.evaluate((x, y), cov, flux, np.eye(2), dcov, 7 if jacobian else 1)
        if not jacobian:
            return images[0].copy()
        return images[0].copy(), np.moveaxis(images[1:], 0, -1).copy()


# hessian_term's map from the 21 sums of the kernel (and a 0 at index 21) to the 6 x 6 second
# derivatives of the model in (cx, cy, Cxx, Cxy, Cyy, flux), with coefficients times the flux and constant
_H_IDX = np.full((6, 6), 21)
_H_FLUX = np.zeros((6, 6))
_H_CONST = np.zeros((6, 6))


def _h_entry(a, b, index, flux_coef=0.0, const=0.0):
    for i, j in ((a, b), (b, a)):
        _H_IDX[i, j], _H_FLUX[i, j], _H_CONST[i, j] = index, flux_coef, const


for _a, _b, _index in ((0, 0, 0), (0, 1, 1), (1, 1, 2)):
    _h_entry(_a, _b, _index, -1.0)
for _c in range(3):
    _h_entry(0, 2 + _c, 3 + _c, -0.5)
    _h_entry(1, 2 + _c, 6 + _c, -0.5)
    _h_entry(2 + _c, 5, 17 + _c, const=-0.5)
for _index, (_a, _b) in enumerate(((0, 0), (0, 1), (0, 2), (1, 1), (1, 2), (2, 2)), 9):
    _h_entry(2 + _a, 2 + _b, _index, 0.25)
_h_entry(0, 5, 15, const=1.0)
_h_entry(1, 5, 16, const=1.0)


def hessian_term(hsums, flux, dpos, dshape, d2shape, flux_scale: float = 1.0) -> np.ndarray:
    """sum(u x d^2 model / d theta d theta) in the fit's parameters, from :meth:`ExpModel.evaluate`'s sums.

    ``u`` is the weighted residual w (model - data) whose spectrum was passed;
    the parameters are two of position (through ``dpos``), three of shape
    (through ``dshape`` and its second derivatives ``d2shape`` [c, a, b]) and
    a flux (the stamp's flux is ``flux_scale`` times it; ``flux`` is the
    stamp's).
    """
    H = np.append(hsums, 0.0)[_H_IDX] * (_H_FLUX * flux + _H_CONST)
    D = np.zeros((6, 6))
    D[0:2, 0:2] = dpos
    D[2:5, 2:5] = dshape
    D[5, 5] = flux_scale
    S = D.T @ H @ D
    # the shape parameters enter the covariance non-linearly: sum_c (u . dm/dC_c) d^2 C_c
    S[2:5, 2:5] += ((-0.5 * flux * hsums[17:20]) @ d2shape.reshape(3, 9)).reshape(3, 3)
    return S


def hessian_terms(hsums, flux, dpos, dshape, d2shape, flux_scale) -> np.ndarray:
    """The sum over stamps of :func:`hessian_term`, for arrays of them (first axis: the stamp)."""
    ns = len(flux)
    H = np.concatenate([hsums, np.zeros((ns, 1))], axis=1)[:, _H_IDX] * \
        (_H_FLUX[None] * np.asarray(flux)[:, None, None] + _H_CONST[None])
    D = np.zeros((ns, 6, 6))
    D[:, 0:2, 0:2] = dpos
    D[:, 2:5, 2:5] = dshape
    D[:, 5, 5] = flux_scale
    S = np.einsum("sji,sjk,skl->il", D, H, D)
    S[2:5, 2:5] += np.einsum("sc,scab->ab", -0.5 * np.asarray(flux)[:, None] * hsums[:, 17:20], d2shape)
    return S


@dataclass
class FitResult:
    """The outcome of one fit."""

    theta: np.ndarray          # (x, y, g1, g2, T, flux), or the sky parameters of a joint fit
    errors: np.ndarray         # 1-sigma, from the inverse of J^T W J
    chi2: float
    dof: int
    nfev: int
    flags: int
    s2n: float


class _Stamp:
    """One stamp's data as the fit uses it: sqrt(weight), weighted data, and its model."""

    def __init__(self, image, weight, model: ExpModel):
        image = np.asarray(image, dtype=np.float64)
        weight = np.asarray(weight, dtype=np.float64)
        good = (weight > 0) & np.isfinite(image)
        self.sw = np.where(good, np.sqrt(np.where(good, weight, 0.0)), 0.0)
        self.swd = np.where(good, image, 0.0) * self.sw
        self.npix = int(good.sum())
        self.model = model


@dataclass
class StampMaps:
    """Where parameters theta put the galaxy in each stamp of a fit (first axis: the stamp)."""

    centres: np.ndarray        # (S, 2) x, y in stamp pixel coordinates
    cov: np.ndarray            # (S, 3) unit covariance (Cxx, Cxy, Cyy), pixel^2
    flux: np.ndarray           # (S,) the stamp's flux
    dpos: np.ndarray           # (S, 2, 2) d(x, y) / d(position parameters)
    dshape: np.ndarray         # (S, 3, 3) d cov / d(shape parameters)
    d2shape: np.ndarray | None  # (S, 3, 3, 3) d^2 cov / d(shape)^2, when asked for
    scale: np.ndarray          # (S,) the stamp's flux per unit of the flux parameter


def stamp_mapping(th, second: bool) -> StampMaps:
    """The mapping of a fit of one stamp in its own pixel axes: theta = (x, y, g1, g2, T, flux)."""
    cov, dcov, d2 = shape_covariance(th[2], th[3], th[4], second=second)
    return StampMaps(np.array([[float(th[0]), float(th[1])]]), cov[None], np.array([float(th[5])]),
                     np.eye(2)[None], dcov[None], None if d2 is None else d2[None], np.ones(1))


class _Problem:
    """Residuals, normal matrix and Hessian term of a set of stamps for common parameters.

    ``mapping(theta, second)`` gives the :class:`StampMaps` of theta: where
    it puts the galaxy in each stamp.
    Stamps of one size and grid (a galaxy's stamps on several frames) are
    evaluated together: one compiled pass over all of them
    (:func:`perscli._kernels.expmix_batch`), one batched inverse FFT, and
    the sums over their pixels as array products.
    """

    def __init__(self, stamps, mapping):
        self.stamps = stamps
        self.mapping = mapping
        self.npix = sum(s.npix for s in stamps)
        m0 = stamps[0].model if stamps else None
        self.batch = len(stamps) > 1 and all(s.model.size == m0.size and s.model.n == m0.n and s.model.alias == m0.alias
                                             and s.model.pad == m0.pad for s in stamps)
        if self.batch:
            self.sw = np.stack([s.sw for s in stamps])
            self.swd = np.stack([s.swd for s in stamps])
            self.transfers = [(s.model.tr_re, s.model.tr_im) for s in stamps]

    def evaluate(self, theta, resid_spectra=None):
        """chi^2, J^T W J, J^T W (data - model), the Hessian term (with spectra), this point's residuals
        and each stamp's sqrt(W) J (6 x pixels)."""
        maps = self.mapping(theta, resid_spectra is not None)
        if self.batch:
            return self._evaluate_batch(maps, resid_spectra)
        A = np.zeros((6, 6))
        b = np.zeros(6)
        S = np.zeros((6, 6)) if resid_spectra is not None else None
        chi2 = 0.0
        us, jts = [], []
        for k, stamp in enumerate(self.stamps):
            flux, dpos, dshape, scale = float(maps.flux[k]), maps.dpos[k], maps.dshape[k], float(maps.scale[k])
            d2shape = None if maps.d2shape is None else maps.d2shape[k]
            images, hs = stamp.model.evaluate(maps.centres[k], maps.cov[k], flux, dpos, dshape, 7,
                                              None if resid_spectra is None else resid_spectra[k])
            r = stamp.swd - images[0] * stamp.sw
            jt = (images[1:] * stamp.sw).reshape(6, -1)
            jt[5] *= scale
            rf = r.ravel()
            chi2 += float(rf @ rf)
            A += jt @ jt.T
            b += jt @ rf
            us.append(r)
            if S is not None:
                S += hessian_term(hs, flux, dpos, dshape, d2shape, scale)
            jts.append(jt)
        return chi2, A, b, S, us, jts

    def _evaluate_batch(self, maps, resid_spectra):
        """:meth:`evaluate` of stamps of one grid, together."""
        m0 = self.stamps[0].model
        L, n, pad = m0.size, m0.n, m0.pad
        ns = len(self.stamps)
        flux, scale, dpos, dshape, d2 = maps.flux, maps.scale, maps.dpos, maps.dshape, maps.d2shape
        spec, hess = self._batch_kernel(maps, resid_spectra, 7)
        jt = np.empty((ns, 6, n, n))
        if np.all(flux != 0):
            # the flux derivative is the model over the flux: no inverse transform of its own
            images = stamp_planes(spec[:, :6], L, n, pad)
            np.multiply(images[:, 0], self.sw * (scale / flux)[:, None, None], out=jt[:, 5])
        else:
            images = stamp_planes(spec, L, n, pad)
            np.multiply(images[:, 6], self.sw * scale[:, None, None], out=jt[:, 5])
        r = self.swd - images[:, 0] * self.sw
        np.multiply(images[:, 1:6], self.sw[:, None], out=jt[:, :5])
        jt = jt.reshape(ns, 6, -1)
        rf = r.reshape(ns, -1)
        chi2 = float(np.einsum("sp,sp->", rf, rf))
        A = np.einsum("skp,slp->kl", jt, jt)
        b = np.einsum("skp,sp->k", jt, rf)
        S = None
        if hess is not None:
            S = hessian_terms(hess / (L * L), flux, dpos, dshape, d2, scale)
        return chi2, A, b, S, r, jt

    def _batch_kernel(self, maps, resid_spectra, nfield: int):
        """:func:`perscli._kernels.expmix_batch` of the stamps: (spectra, Hessian sums or None)."""
        m0 = self.stamps[0].model
        L, pad, half = m0.size, m0.pad, m0.size // 2 + 1
        ns = len(self.stamps)
        params = np.empty((ns, 17))
        params[:, 0:3] = maps.cov
        params[:, 3] = maps.flux
        params[:, 4:8] = maps.dpos.reshape(ns, 4)
        params[:, 8:17] = maps.dshape.reshape(ns, 9)
        phase_x = np.exp(-1j * m0.k[None, :] * (maps.centres[:, 0:1] + pad))
        phase_y = np.exp(-1j * m0.k[None, :] * (maps.centres[:, 1:2] + pad))
        spec = np.empty((ns, nfield, L, half), dtype=np.complex128)
        resid = None if resid_spectra is None else np.ascontiguousarray(resid_spectra)
        hess = None if resid is None else np.empty((ns, 21))
        _kernels.expmix_batch(spec, m0._work, self.transfers, m0.k, L, m0.alias, nfield, params, phase_x, phase_y,
                              resid, hess, m0.wcol, P_EXP, F_EXP)
        return spec, hess

    def second_order(self, theta, resid_spectra) -> np.ndarray:
        """The Hessian's second-order term at theta for the residual whose spectra are given.

        At a point already evaluated, with its own residual: one compiled
        pass over the frequencies, no model planes, no inverse transform.
        """
        maps = self.mapping(theta, True)
        if not self.batch:
            return self.evaluate(theta, resid_spectra)[3]
        m0 = self.stamps[0].model
        _, hess = self._batch_kernel(maps, resid_spectra, 0)
        return hessian_terms(hess / (m0.size * m0.size), maps.flux, maps.dpos, maps.dshape, maps.d2shape, maps.scale)

    def spectra(self, us):
        """The residual spectra of a point (for the Hessian term at the next trial points)."""
        # u = w (model - data) = -sqrt(w) r
        if self.batch:
            m0 = self.stamps[0].model
            grid = np.zeros((len(self.stamps), m0.size, m0.size))
            grid[:, m0.pad:m0.pad + m0.n, m0.pad:m0.pad + m0.n] = -self.sw * us
            return scipy.fft.rfft2(grid, axes=(-2, -1))
        return [s.model.residual_spectrum(-s.sw * r) for s, r in zip(self.stamps, us)]


@dataclass
class Point:
    """What :func:`_newton` knew of its last point: J^T W r, the Hessian's second-order term (with the
    residual of the point before it, as every trial point takes it), the residuals and sqrt(W) J."""

    b: np.ndarray
    S: np.ndarray | None
    us: object
    jts: object


def _newton(problem: _Problem, theta0, floors, valid, *, max_nfev=MAX_NFEV, xtol=1e-10):
    """Damped Newton (Levenberg-Marquardt on J^T W J + the residual's second-order term).

    Returns theta, chi2, A (J^T W J at theta), nfev, flags and the
    :class:`Point` of theta.  Deterministic: every decision depends on the
    data and the start only.

    The second-order term at a trial point is taken with the residual of the
    current point (the only one known when the trial is evaluated in the
    same pass); it is exact at convergence, where the steps vanish, which is
    what quadratic convergence needs.  Where J^T W J + S is not positive
    definite (far from the minimum) the step is Gauss-Newton's.
    """
    theta = np.array(theta0, dtype=np.float64)
    chi2, A, b, S, us, jts = problem.evaluate(theta)
    nfev = 1
    lam = 1e-3
    flags = 0
    converged = False
    while True:
        H = A
        if S is not None:
            try:
                np.linalg.cholesky(A + S)
                H = A + S
            except np.linalg.LinAlgError:
                pass
        diag = np.diag(A).copy()
        diag[diag <= 0] = 1.0
        scale = np.maximum(np.abs(theta), floors)
        # converged when the undamped Newton step from here is below the tolerance: a step shrunk by the
        # damping (after rejected trials) says nothing of how far the minimum is, and stopping on one left
        # g up to ~1e-9 short of it
        try:
            full = np.linalg.solve(H, b)
        except np.linalg.LinAlgError:
            full = None
        if full is not None and np.all(np.abs(full) <= xtol * scale):
            converged = True
            break
        spectra = None
        accepted = False
        while not accepted:
            try:
                step = np.linalg.solve(H + lam * np.diag(diag), b)
            except np.linalg.LinAlgError:
                step = None
            trial = theta + step if step is not None else None
            verdict = valid(trial, theta) if trial is not None else "reject"
            if verdict == "stop":
                # pushing on the |g| = 1 bound from |g|^2 >= 0.998: flagged 32 whatever follows
                converged = True
                break
            if verdict == "reject":
                lam *= 10.0
                if lam > 1e12:
                    break
                continue
            if nfev >= max_nfev:
                break
            if spectra is None:
                spectra = problem.spectra(us)
            chi2_new, A_new, b_new, S_new, us_new, jts_new = problem.evaluate(trial, spectra)
            nfev += 1
            # chi^2 is a sum of ~1e3 squares, good to ~1e-13 of itself: a step whose predicted gain
            # (b . step) is below that cannot be judged by chi^2, and is taken when chi^2 does not rise
            # beyond it (else the last 1e-9 of g would be refused on rounding alone)
            noise = CHI2_ROUNDING * max(chi2, 1.0)
            if chi2_new <= chi2 or (chi2_new <= chi2 + noise and abs(float(b @ step)) <= noise):
                theta, chi2, A, b, S, us, jts = trial, chi2_new, A_new, b_new, S_new, us_new, jts_new
                lam = max(lam / 10.0, 1e-12)
                accepted = True
            else:
                # a rejected Newton step says the local quadratic model is poor: damp at once
                lam = max(lam * 10.0, 1e-3)
                if lam > 1e12:
                    break
        if converged or not accepted:
            if not converged and lam > 1e12:
                converged = bool(np.all(np.abs(b) <= 1e-8 * np.maximum(1.0, np.abs(np.diag(A)))))
            break
    if not converged:
        flags |= FLAG_FAILED
    return theta, chi2, A, nfev, flags, Point(b, S, us, jts)


def _finish(theta, chi2, A, npix, nfev, flags, *, g=(2, 3), size=4, flux=5) -> FitResult:
    try:
        cov = np.linalg.inv(A)
        errors = np.sqrt(np.clip(np.diag(cov), 0.0, None))
    except np.linalg.LinAlgError:
        errors = np.full(6, np.nan)
        flags |= FLAG_SINGULAR
    if theta[size] <= 0:
        flags |= FLAG_BAD_SIZE
    if theta[flux] <= 0:
        flags |= FLAG_BAD_FLUX
    if theta[g[0]] ** 2 + theta[g[1]] ** 2 >= G2_FLAG:
        flags |= FLAG_SHEAR
    s2n = float(theta[flux] / errors[flux]) if np.isfinite(errors[flux]) and errors[flux] > 0 else 0.0
    return FitResult(theta, errors, chi2, npix - 6, nfev, flags, s2n)


def _valid(trial, theta):
    """'ok', 'reject' (outside T > 0, flux > 0, |g| < 1: damp more) or 'stop' (stuck at |g| = 1)."""
    g2_trial = trial[2] ** 2 + trial[3] ** 2
    if g2_trial >= G2_LIMIT and theta[2] ** 2 + theta[3] ** 2 >= G2_FLAG:
        return "stop"
    if trial[4] <= 0 or trial[5] <= 0 or g2_trial >= G2_LIMIT:
        return "reject"
    return "ok"


#: parameter scales below which the step tolerance is absolute: pixels, g, pixel^2, flux
_PIXEL_FLOORS = np.array([1.0, 1.0, 1.0, 1.0, 1e-3, 1e-3])


def fit_exp(image: np.ndarray, weight: np.ndarray, model: ExpModel, start, *, max_nfev: int = MAX_NFEV,
            xtol: float = 1e-10) -> FitResult:
    """Fit of the exponential mixture to one stamp.

    Parameters
    ----------
    image : ndarray (n, n)
        The stamp, sky subtracted.
    weight : ndarray (n, n)
        Inverse variance per pixel; 0 for masked pixels.
    model : ExpModel
        For this stamp size and PSF.
    start : sequence of 6 floats
        Starting (x, y, g1, g2, T, flux): from the catalogue alone, so that
        paired images are fitted from the same point.
    max_nfev : int
        Limit on model evaluations (flag 1 when reached).
    xtol : float
        Converged when a step is below xtol relative to the parameter's
        scale (absolute below 1 pixel, 1 in g and 1e-3 in T and flux).

    Returns
    -------
    FitResult
    """
    stamp = _Stamp(image, weight, model)
    theta = np.array(start, dtype=np.float64)
    if stamp.npix < MIN_PIXELS:
        return FitResult(theta, np.full(6, np.nan), np.nan, 0, 0, FLAG_FEW_PIXELS, 0.0)
    problem = _Problem([stamp], stamp_mapping)
    theta, chi2, A, nfev, flags, _ = _newton(problem, theta, _PIXEL_FLOORS, _valid, max_nfev=max_nfev, xtol=xtol)
    return _finish(theta, chi2, A, stamp.npix, nfev, flags)


@dataclass
class JointStamp:
    """One frame's view of a galaxy for :func:`fit_joint`.

    Attributes
    ----------
    image, weight : ndarray (n, n)
        Sky-subtracted stamp and inverse variance (0: masked).
    model : ExpModel
        For this frame's PSF and the stamp size.
    origin : (float, float)
        The catalogue position in stamp pixel coordinates (0-indexed).
    ainv : (2, 2) array
        d(x, y)/d(u, v): stamp pixels per arcsec of the local tangent plane
        (u to the West, v to the North), the inverse of the WCS Jacobian at
        the galaxy.
    flux_scale : float
        Stamp flux (frame units) per unit of the joint flux (e-/s): the
        exposure time, divided by the gain for a frame in DN.
    """

    image: np.ndarray
    weight: np.ndarray
    model: ExpModel
    origin: tuple
    ainv: np.ndarray
    flux_scale: float


#: joint parameter scales: arcsec (about a pixel), g, arcsec^2, e-/s
_SKY_FLOORS = np.array([0.1, 0.1, 1.0, 1.0, 1e-5, 1e-5])


def fit_joint(stamps, start, *, max_nfev: int = MAX_NFEV, xtol: float = 1e-10) -> FitResult:
    """One exponential-mixture fit of a galaxy to its stamps on several frames.

    The parameters are defined on the sky, in the tangent plane at the
    catalogue position with u to the West and v to the North (GalSim's
    world axes, those of the truth catalogue's e1, e2): (du, dv) the offset
    of the centre (arcsec), (g1, g2) the reduced shear in (u, v) (+g1 along
    u, the East-West axis; +g2 along the diagonal between u and v, North-West),
    T = Cuu + Cvv (arcsec^2) and the flux in e-/s.  Each stamp sees them
    through its own local WCS Jacobian (a rotated, sheared, rescaled copy of
    the same galaxy) and its own PSF.

    Parameters
    ----------
    stamps : sequence of JointStamp
    start : sequence of 6 floats
        (du, dv, g1, g2, T, flux), from the catalogue alone.

    Returns
    -------
    FitResult
        theta and errors in the sky parameters; dof over all stamps.
    """
    problem, npix, _ = joint_problem(stamps)
    theta = np.array(start, dtype=np.float64)
    if problem is None:
        return FitResult(theta, np.full(6, np.nan), np.nan, 0, 0, FLAG_FEW_PIXELS, 0.0)
    theta, chi2, A, nfev, flags, _ = _newton(problem, theta, _SKY_FLOORS, _valid, max_nfev=max_nfev, xtol=xtol)
    return _finish(theta, chi2, A, npix, nfev, flags)


def joint_problem(stamps):
    """The :class:`_Problem` of :func:`fit_joint` for these stamps: (problem, usable pixels), or (None, npix)."""
    fits = [_Stamp(s.image, s.weight, s.model) for s in stamps]
    used = [(f, s) for f, s in zip(fits, stamps) if f.npix >= MIN_PIXELS]
    npix = sum(f.npix for f, _ in used)
    if not used or npix < MIN_PIXELS:
        return None, npix, []
    ainv = np.array([np.asarray(s.ainv, dtype=np.float64) for _, s in used])
    cmaps = np.array([covariance_map(s.ainv) for _, s in used])
    fscale = np.array([float(s.flux_scale) for _, s in used])
    origins = np.array([(float(s.origin[0]), float(s.origin[1])) for _, s in used])
    ns = len(used)

    def mapping(th, second):
        # every stamp at once: the sky parameters through each stamp's local WCS Jacobian
        cov, dcov, d2 = shape_covariance(th[2], th[3], th[4], second=second)
        centres = origins + ainv @ np.array([float(th[0]), float(th[1])])
        d2pix = None if d2 is None else (cmaps @ d2.reshape(3, 9)).reshape(ns, 3, 3, 3)
        return StampMaps(centres, cmaps @ cov, fscale * float(th[5]), ainv, cmaps @ dcov, d2pix, fscale)

    keep = [k for k, f in enumerate(fits) if f.npix >= MIN_PIXELS]
    return _Problem([f for f, _ in used], mapping), npix, keep
