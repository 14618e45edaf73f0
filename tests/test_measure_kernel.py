"""The fitter's compiled pass and its Newton step: exp, Hessian term, convergence, predicted S/N."""

import numpy as np
import pytest

galsim = pytest.importorskip("galsim")
import galsim.roman as roman  # noqa: E402

from perscli import _kernels  # noqa: E402
from perscli.measure.fit import (ExpModel, fit_exp, g_to_e, g_to_e_hessian, hessian_term,  # noqa: E402
                                 shape_covariance)

N = 48


@pytest.fixture(scope="module")
def model():
    bandpass = roman.getBandpasses(AB_zeropoint=True)["J129"]
    psf = roman.getPSF(7, "J129", wavelength=bandpass.effective_wavelength)
    return ExpModel(galsim.PixelScale(roman.pixel_scale).toImage(psf), N)


def test_vectorised_exp_is_within_2_ulp_of_libm():
    rng = np.random.default_rng(1)
    x = np.concatenate([-np.logspace(-300, np.log10(707.0), 200_000), rng.uniform(-708, 0, 200_000),
                        [0.0, -0.0, -1e-320, -0.34657359, -0.34657360, -707.9999]])
    out = np.empty_like(x)
    _kernels.exp_nonpos(x, out)
    ref = np.exp(x)
    ulp = np.spacing(ref)
    assert np.max(np.abs(out - ref) / ulp) <= 2.0
    below = np.array([-708.5, -745.0, -1e4, -np.inf])
    _kernels.exp_nonpos(below, out[:4])
    assert np.all(out[:4] == 0.0)


def test_second_derivatives_of_e():
    g1, g2, h = 0.31, -0.22, 1e-6
    num = np.empty((2, 2, 2))
    for a, (d1, d2) in enumerate(((h, 0.0), (0.0, h))):
        up, down = g_to_e(g1 + d1, g2 + d2)[2], g_to_e(g1 - d1, g2 - d2)[2]
        num[:, :, a] = (up - down) / (2 * h)
    np.testing.assert_allclose(g_to_e_hessian(g1, g2), num, rtol=1e-6, atol=1e-9)
    cov, dcov, d2 = shape_covariance(g1, g2, 7.0, second=True)
    theta = np.array([g1, g2, 7.0])
    for a in range(3):
        step = np.zeros(3)
        step[a] = h
        up, down = shape_covariance(*(theta + step))[1], shape_covariance(*(theta - step))[1]
        np.testing.assert_allclose(d2[:, :, a], (up - down) / (2 * h), rtol=1e-6, atol=1e-8)


def test_hessian_term_equals_residual_times_second_derivatives(model):
    """The Parseval sums of the compiled pass give sum(u d2m) as finite differences of the Jacobian do."""
    theta = np.array([23.3, 24.1, 0.21, -0.13, 14.0, 3e4])
    u = np.random.default_rng(1).normal(size=(N, N))
    cov, dcov, d2 = shape_covariance(*theta[2:5], second=True)
    _, sums = model.evaluate(theta[:2], cov, theta[5], np.eye(2), dcov, 7, model.residual_spectrum(u))
    S = hessian_term(sums, theta[5], np.eye(2), dcov, d2)
    steps = [1e-5, 1e-5, 1e-6, 1e-6, 1e-5, 1e-2]
    num = np.zeros((6, 6))
    for a, h in enumerate(steps):
        up, down = theta.copy(), theta.copy()
        up[a] += h
        down[a] -= h
        num[a] = np.tensordot(u, (model.image(up, True)[1] - model.image(down, True)[1]) / (2 * h), axes=2)
    np.testing.assert_allclose(S, num, rtol=1e-6, atol=1e-7 * np.abs(num).max())


def test_newton_converges_fast_at_low_snr(model):
    """S/N ~10 galaxies: Gauss-Newton needed 30-90 evaluations; the full Hessian needs ~8-15."""
    rng = np.random.default_rng(4)
    bandpass = roman.getBandpasses(AB_zeropoint=True)["J129"]
    psf = roman.getPSF(7, "J129", wavelength=bandpass.effective_wavelength)
    nfev = []
    for _ in range(10):
        g1, g2 = rng.uniform(-0.4, 0.4, 2)
        gal = galsim.Exponential(half_light_radius=0.3, flux=900.0).shear(g1=g1, g2=g2)
        img = galsim.Convolve(gal, psf).drawImage(nx=N, ny=N, scale=roman.pixel_scale).array
        img = img + rng.normal(0, 15.0, img.shape)
        res = fit_exp(img, np.full(img.shape, 1 / 225.0), model, ((N - 1) / 2, (N - 1) / 2, 0, 0, 15.0, 900.0))
        nfev.append(res.nfev)
        assert not res.flags & 1
    assert np.mean(nfev) < 16


def test_predicted_snr_matches_the_optimal_snr_of_a_drawn_galaxy(model):
    """predicted_snr is F sqrt(sum p^2 / V) of the round catalogue galaxy through the PSF."""
    from perscli.measure.noise import SnrTable, predicted_snr
    from perscli.measure.perframe import _FrameFacts

    bandpass = roman.getBandpasses(AB_zeropoint=True)["J129"]
    psf = roman.getPSF(7, "J129", wavelength=bandpass.effective_wavelength)
    exptime, zpt, var = 139.8, 26.0, 250.0
    facts = _FrameFacts("f", "electron", 1.0, exptime, {"ZPT_AB": zpt, "FILTER": "J129"})
    hlr = np.array([0.15, 0.3, 0.6])
    flux = np.array([400.0, 1000.0, 3000.0])
    cat = {"hlr": hlr, "mag_j129": zpt - 2.5 * np.log10(flux / (roman.collecting_area * exptime))}
    snr = predicted_snr(cat, [0, 1, 2], facts, roman.pixel_scale, SnrTable(model), np.full(3, 1 / var))
    for k in range(3):
        gal = galsim.Exponential(half_light_radius=hlr[k], flux=flux[k])
        img = galsim.Convolve(gal, psf).drawImage(nx=N, ny=N, scale=roman.pixel_scale).array
        assert snr[k] == pytest.approx(np.sqrt(np.sum(img ** 2) / var), rel=0.01)
    # no magnitude: no prediction (NaN: never cut)
    nomag = predicted_snr({"hlr": hlr}, [0, 1], facts, roman.pixel_scale, SnrTable(model), np.full(2, 1 / var))
    assert np.all(np.isnan(nomag))


def test_stamp_sides_follow_the_catalogue_size():
    from perscli.measure.perframe import stamp_ladder, stamp_side

    assert stamp_ladder(48) == [16, 24, 32, 40, 48] and stamp_ladder(32) == [16, 24, 32]
    assert stamp_ladder(50) == [16, 24, 32, 40, 48, 50] and stamp_ladder(16) == [16]
    cat = {"hlr": np.array([0.1, 0.3, 0.5, 1.0, np.nan])}
    # half the side >= 4 hlr / 0.11" + 3 pixels; no hlr: 0.3"
    assert [stamp_side(cat, i, 0.11, stamp_ladder(48)) for i in range(5)] == [16, 32, 48, 48, 32]
    assert [stamp_side(cat, i, 0.11, stamp_ladder(24)) for i in range(5)] == [16, 24, 24, 24, 24]


def test_cli_defaults_are_the_library_defaults():
    """Every setting of MeasureOptions is an option of the command, with its default (written once)."""
    import dataclasses

    from perscli.cli.measure import measure
    from perscli.measure.settings import MeasureOptions
    from perscli.measure.settings import MIN_SNR_DEFAULT

    defaults = {p.name: p.default for p in measure.params}
    o = MeasureOptions()
    # --columns is the shared repeatable option (perscli.cli.options.columns_opt): unset gives None
    for field in dataclasses.fields(o):
        if field.name != "columns":
            assert defaults[field.name] == getattr(o, field.name), field.name
    assert o.columns is None and "columns" in defaults
    assert o.min_snr == MIN_SNR_DEFAULT == 5.0


def test_stamp_planes_is_irfft2_cut_to_the_stamp():
    """The pruned inverse (rows first, only the stamp's rows along the columns) is irfft2's stamp."""
    import scipy.fft

    from perscli.measure.fit import stamp_planes
    rng = np.random.default_rng(3)
    L, n, pad = 40, 24, 8
    spec = scipy.fft.rfft2(rng.normal(size=(2, 3, L, L)), axes=(-2, -1))
    full = scipy.fft.irfft2(spec, s=(L, L), axes=(-2, -1))[..., pad:pad + n, pad:pad + n]
    # the same transform in another order of its two passes: equal to a few ulp of the largest value
    np.testing.assert_allclose(stamp_planes(spec, L, n, pad), full, rtol=0, atol=1e-14 * np.abs(full).max())


def _joint_problem_of(model, nstamps=4):
    """A galaxy on a few stamps of one PSF with different WCS Jacobians (and one a plain fit's single stamp)."""
    from perscli.measure.fit import JointStamp, joint_problem
    rng = np.random.default_rng(5)
    stamps = []
    for k in range(nstamps):
        ang = 0.4 * k
        ainv = 9.0 * np.array([[np.cos(ang), -np.sin(ang)], [np.sin(ang), np.cos(ang)]]) @ np.diag([1.0, 1.0 + 0.02 * k])
        img = rng.normal(size=(N, N)) + 50.0 * model.image([23.4 + 0.1 * k, 24.2, 0.2, -0.1, 10.0, 1.0])
        stamps.append(JointStamp(img, np.full((N, N), 1.0 + 0.1 * k), model, (23.5, 24.0), ainv, 140.0 + k))
    problem, _, _ = joint_problem(stamps)
    return problem


def test_batched_evaluation_is_the_per_stamp_one(model):
    """A galaxy's stamps evaluated together (one compiled pass, the flux plane from the model) equal the
    same stamps one at a time (each with its own inverse transform of every plane)."""
    from perscli.measure.fit import _Problem
    problem = _joint_problem_of(model)
    assert problem.batch
    single = _Problem(problem.stamps, problem.mapping)
    single.batch = False
    theta = np.array([0.02, -0.01, 0.15, -0.05, 0.12, 0.33])
    first = problem.evaluate(theta)
    spectra = problem.spectra(first[4])
    got, want = problem.evaluate(theta, spectra), single.evaluate(theta, single.spectra(list(first[4])))
    for a, b in zip(got[:4], want[:4]):
        np.testing.assert_allclose(a, b, rtol=1e-12, atol=1e-12 * np.abs(b).max())
    np.testing.assert_allclose(np.asarray(got[5]), np.asarray(want[5]), rtol=0, atol=1e-12 * np.abs(want[5]).max())


def test_second_order_alone_is_the_evaluations(model):
    """The Hessian-only pass gives the second-order term a full evaluation gives, bit for bit."""
    problem = _joint_problem_of(model)
    theta = np.array([0.02, -0.01, 0.15, -0.05, 0.12, 0.33])
    spectra = problem.spectra(problem.evaluate(theta)[4])
    S = problem.evaluate(theta, spectra)[3]
    assert np.array_equal(problem.second_order(theta, spectra), S)
    assert np.abs(S).max() > 0
