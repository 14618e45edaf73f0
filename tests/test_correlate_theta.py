"""THETA_DE: the chi2 of De's position angle against uniform uses the variance under uniform angles."""

import numpy as np
import pytest
from astropy.io import fits

from perscli.stats.correlate import correlate_files
from perscli.stats.de_stats import MIN_EXPECTED, N_ANGLE
from perscli.stats.de_stats import chi2_sf, theta_distribution
from perscli.stats.settings import CorrelateOptions

K = N_ANGLE
P0 = 1.0 / K


def de_from(amp, angle):
    """De of amplitude amp at position angle angle (radians)."""
    return amp * np.cos(2 * angle), amp * np.sin(2 * angle)


def one_bin(theta):
    """The per-|De|-bin values of a distribution with one |De| bin."""
    return {k: theta[k][0] for k in ("n", "n_eff", "chi2_uniform", "dof_uniform", "p_uniform", "frac_err_null")}


def test_chi2_survival_function_equals_scipys():
    from scipy.stats import chi2

    for dof in (1, 2, 5, 17, 18, 40):
        for x in (0.0, 1e-3, 0.5, 3.0, dof, 2.0 * dof, 60.0, 200.0):
            assert chi2_sf(x, dof) == pytest.approx(chi2.sf(x, dof), rel=1e-11, abs=1e-300), (x, dof)
    assert chi2_sf(1e4, 17) == 0.0 and np.isnan(chi2_sf(np.nan, 17))


def test_equal_weights_give_pearsons_chi2():
    from scipy.stats import chisquare

    rng = np.random.default_rng(1)
    n = 5000
    angle = rng.uniform(-np.pi / 2, np.pi / 2, n)
    d1, d2 = de_from(np.full(n, 1e-5), angle)
    theta = theta_distribution(d1, d2, edges=(1e-6, 1e-4), nboot=10, seed=1)
    counts = np.round(theta["frac"] * n)
    expected = chisquare(counts)
    got = one_bin(theta)
    assert got["n_eff"] == pytest.approx(n, rel=1e-12) and got["dof_uniform"] == K - 1
    assert got["chi2_uniform"] == pytest.approx(expected.statistic, rel=1e-9)
    assert got["p_uniform"] == pytest.approx(expected.pvalue, rel=1e-6)
    assert theta["p_method"] == ["chi2"]
    np.testing.assert_allclose(theta["frac_err_null"], np.sqrt(P0 * (1 - P0) / n), rtol=1e-12)


def test_weighted_fractions_have_the_null_variance_and_calibrated_p_values():
    # |De| spread over two decades: n_eff well below n; under uniform angles the spread of each fraction
    # over realisations is sqrt(p(1-p)/n_eff), chi2 averages its 17 degrees of freedom and p is uniform
    rng = np.random.default_rng(2)
    n, trials = 400, 600
    amp = 10 ** rng.uniform(-6, -4, n)
    fracs, chi2, pvals = [], [], []
    for _ in range(trials):
        d1, d2 = de_from(amp, rng.uniform(-np.pi / 2, np.pi / 2, n))
        t = theta_distribution(d1, d2, edges=(1e-6, 1e-4), nboot=2, seed=1)
        fracs.append(t["frac"])
        chi2.append(t["chi2_uniform"][0])
        pvals.append(t["p_uniform"][0])
    neff = amp.sum() ** 2 / np.sum(amp ** 2)
    assert neff < 0.6 * n and neff * P0 >= MIN_EXPECTED and t["p_method"] == ["chi2"]
    np.testing.assert_allclose(t["n_eff"][0], neff, rtol=1e-12)
    spread = np.std(np.array(fracs), axis=0, ddof=1)
    np.testing.assert_allclose(spread, np.sqrt(P0 * (1 - P0) / neff), rtol=0.15)
    assert np.mean(chi2) == pytest.approx(K - 1, abs=5 * np.sqrt(2 * (K - 1) / trials))
    pvals = np.array(pvals)
    for level in (0.05, 0.2, 0.5):
        assert abs(np.mean(pvals < level) - level) < 4 * np.sqrt(level * (1 - level) / trials), level


def test_few_objects_get_a_simulated_p_value_that_is_calibrated():
    rng = np.random.default_rng(3)
    n, trials = 12, 400
    amp = 10 ** rng.uniform(-6, -4, n)
    pvals = []
    for _ in range(trials):
        d1, d2 = de_from(amp, rng.uniform(-np.pi / 2, np.pi / 2, n))
        t = theta_distribution(d1, d2, edges=(1e-6, 1e-4), nboot=2, seed=int(rng.integers(1 << 30)))
        pvals.append(t["p_uniform"][0])
    assert t["p_method"] == ["null-sim"]
    pvals = np.array(pvals)
    # a simulated p-value of a discrete statistic is valid: P(p <= a) <= a, and not far below it here
    for level in (0.05, 0.2, 0.5):
        assert np.mean(pvals <= level) < level + 4 * np.sqrt(level * (1 - level) / trials), level
        assert np.mean(pvals <= level) > level / 2, level
    # one object says nothing about uniformity: every simulation is as extreme
    t = theta_distribution(np.array([1e-5]), np.array([0.0]), edges=(1e-6, 1e-4), nboot=2)
    assert t["chi2_uniform"][0] == pytest.approx(K - 1) and t["p_uniform"][0] == 1.0


def test_an_aligned_sample_is_rejected_and_empty_bins_are_nan():
    # all at +45 degrees: the bootstrap errors are 0 (every resample is the same), the null's are not
    d1, d2 = np.zeros(100), np.full(100, 1e-5)
    t = theta_distribution(d1, d2, nboot=50, seed=1)
    full = t["n"] > 0
    assert np.all(t["frac_err"][full] == 0)
    assert np.all(t["chi2_uniform"][full] == pytest.approx(100 * (K - 1)))
    assert np.all(t["p_uniform"][full] < 1e-100)
    empty = ~full
    assert np.all(np.isnan(t["chi2_uniform"][empty])) and np.all(np.isnan(t["p_uniform"][empty]))
    assert np.all(t["n_eff"][empty] == 0) and np.all(t["dof_uniform"] == K - 1)
    assert [m for m in t["p_method"] if m] == ["chi2"] and t["p_method"].count("") == 3


def test_output_columns_header_and_summary(tmp_path):
    rng = np.random.default_rng(4)
    n = 3000
    dec = -44 + rng.uniform(-0.5, 0.5, n)
    ra = 10 + rng.uniform(-0.7, 0.7, n)
    # most |De| tiny; 15 objects between 1e-4 and 1e-2: that bin's p-value is simulated
    amp = np.where(np.arange(n) < 15, 10 ** rng.uniform(-4, -2, n), 10 ** rng.uniform(-7, -5, n))
    d1, d2 = de_from(amp, rng.uniform(-np.pi / 2, np.pi / 2, n))
    cols = [fits.Column("id", "K", array=np.arange(n)), fits.Column("ra", "D", array=ra),
            fits.Column("dec", "D", array=dec), fits.Column("de1", "D", array=d1), fits.Column("de2", "D", array=d2)]
    path = tmp_path / "de.fits"
    fits.HDUList([fits.PrimaryHDU(), fits.BinTableHDU.from_columns(cols, name="DE")]).writeto(path)
    summary = correlate_files([str(path)], str(tmp_path / "xi.fits"),
                              CorrelateOptions(de_columns=("de1", "de2"), npatch=4, nbins=5))
    with fits.open(tmp_path / "xi.fits") as hdul:
        table, header = hdul["THETA_DE"].data, hdul["THETA_DE"].header
        for name in ("n_eff", "frac_err_null", "chi2_uniform", "dof_uniform", "p_uniform"):
            assert name in table.columns.names
        assert [header[f"PMETHOD{k}"] for k in range(1, 5)] == ["chi2", "chi2", "null-sim", "none"]
        assert header["NULLSIMS"] == 2000 and header["NDOF"] == K - 1
        assert any("variance under" in str(c) for c in header["COMMENT"])
    rows = summary["theta"]
    assert rows[0]["n"] + rows[1]["n"] == n - 15 and rows[2]["n"] == 15 and rows[3]["n"] == 0
    assert rows[2]["p_method"] == "null-sim" and 0 < rows[2]["p"] <= 1 and rows[2]["dof"] == K - 1
    assert np.isnan(rows[3]["chi2"]) and rows[3]["p_method"] == ""
