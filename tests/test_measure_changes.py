"""Shape changes from the reference's minimum: the linear response, checked, against fits from the start.

A variant of a galaxy's data (the reference plus a pixel change: a DN that flips, a few dozen, a ghost) is
fitted from the reference's minimum (perscli.measure.response.fit_changes); the same variant fitted from the
start, as a fit of its data alone is, must give the same De to max(1e-3 |De|, 1e-10), and the same decision at
the paper's thresholds.  The galaxies are GalSim exponentials through the Roman PSF with sky noise rounded to
DN: independent of the fitter's own mixture model.
"""

import numpy as np
import pytest

galsim = pytest.importorskip("galsim")
import galsim.roman as roman  # noqa: E402

from perscli.measure.fit import ExpModel, JointStamp, covariance_map  # noqa: E402
from perscli.measure.response import CHANGE_METHODS, fit_exp_changes, fit_joint_changes  # noqa: E402

N = 32
NOISE = float(np.sqrt(180.0 + 8.5 ** 2))


@pytest.fixture(scope="module")
def psf():
    bandpass = roman.getBandpasses(AB_zeropoint=True)["J129"]
    return roman.getPSF(7, "J129", wavelength=bandpass.effective_wavelength)


@pytest.fixture(scope="module")
def model(psf):
    return ExpModel(galsim.PixelScale(roman.pixel_scale).toImage(psf), N)


def _galaxy(psf, rng, offset=None):
    hlr, flux = rng.uniform(0.15, 0.5), 10 ** rng.uniform(2.5, 4.5)
    g1, g2 = np.clip(rng.normal(0, 0.25, 2), -0.6, 0.6)
    gal = galsim.Exponential(half_light_radius=hlr, flux=flux).shear(g1=g1, g2=g2)
    off = rng.uniform(-0.5, 0.5, 2) if offset is None else offset
    img = galsim.Convolve(gal, psf).drawImage(nx=N, ny=N, scale=roman.pixel_scale, offset=off).array
    return np.round(img + rng.normal(0, NOISE, img.shape)), hlr, flux


def _changes(rng):
    """One DN flipped; 3% of the pixels flipped; a ghost of a few hundred electrons."""
    one = np.zeros((N, N))
    one[rng.integers(0, N), rng.integers(0, N)] = 1.0
    many = (rng.random((N, N)) < 0.03).astype(float)
    yy, xx = np.mgrid[:N, :N]
    ghost = np.round(30 * np.exp(-((xx - rng.uniform(0, N)) ** 2 + (yy - rng.uniform(0, N)) ** 2) / 18.0))
    return [one, many, ghost]


def _agree(de, cold_de):
    tol = max(1e-3 * np.max(np.abs(cold_de)), 1e-10)
    assert np.max(np.abs(de - cold_de)) <= tol, (de, cold_de)
    for threshold in (1e-8, 1e-4):
        assert (np.hypot(*de) >= threshold) == (np.hypot(*cold_de) >= threshold)


def test_the_change_of_a_fit_is_that_of_a_fit_from_the_start(psf, model):
    rng = np.random.default_rng(3)
    methods = []
    for _ in range(40):
        data, hlr, flux = _galaxy(psf, rng)
        weight = np.full(data.shape, 1.0 / NOISE ** 2)
        start = ((N - 1) / 2, (N - 1) / 2, 0.0, 0.0, 2 * (hlr / roman.pixel_scale) ** 2, flux)
        ref, changes, colds = fit_exp_changes(data, weight, model, start, [*_changes(rng), None], cold=True)
        assert changes[-1].method == "same" and changes[-1].result is ref
        for change, cold in zip(changes[:-1], colds):
            methods.append(change.method)
            _agree(change.result.theta[2:4] - ref.theta[2:4], cold.theta[2:4] - ref.theta[2:4])
    # most changes are the linear response (a flip or a few), a ghost on the galaxy is fitted from the start
    assert methods.count("linear") > len(methods) / 3 and "cold" in methods
    assert set(methods) <= set(CHANGE_METHODS)


def test_joint_changes_agree_with_joint_fits_from_the_start(psf, model):
    rng = np.random.default_rng(5)
    for _ in range(8):
        hlr, flux = rng.uniform(0.15, 0.4), 10 ** rng.uniform(2.0, 3.5)
        g1, g2 = np.clip(rng.normal(0, 0.25, 2), -0.6, 0.6)
        gal = galsim.Exponential(half_light_radius=hlr, flux=flux * 139.8).shear(g1=g1, g2=g2)
        stamps = []
        for _ in range(4):
            # another pointing: the galaxy turned on the detector
            angle = rng.uniform(0, np.pi)
            rot = np.array([[np.cos(angle), -np.sin(angle)], [np.sin(angle), np.cos(angle)]])
            wcs = galsim.JacobianWCS(*(rot * roman.pixel_scale).ravel())
            off = rng.uniform(-0.5, 0.5, 2)
            img = galsim.Convolve(wcs.toImage(gal), galsim.PixelScale(roman.pixel_scale).toImage(psf)).drawImage(
                nx=N, ny=N, scale=1.0, offset=off).array
            data = np.round(img + rng.normal(0, NOISE, img.shape))
            ainv = np.linalg.inv(rot * roman.pixel_scale)
            stamps.append(JointStamp(data, np.full(data.shape, 1.0 / NOISE ** 2), model,
                                     ((N - 1) / 2 + off[0], (N - 1) / 2 + off[1]), ainv, 139.8))
        start = (0.0, 0.0, 0.0, 0.0, 2 * hlr ** 2, flux)
        deltas = [[c if k % 2 == 0 else None for k, c in enumerate(_changes(rng) + [np.zeros((N, N))])]
                  for _ in range(2)]
        ref, changes, colds = fit_joint_changes(stamps, start, deltas, cold=True)
        for change, cold in zip(changes, colds):
            _agree(change.result.theta[2:4] - ref.theta[2:4], cold.theta[2:4] - ref.theta[2:4])
    assert covariance_map(np.eye(2)).tolist() == [[1, 0, 0], [0, 1, 0], [0, 0, 1]]
