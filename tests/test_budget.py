"""perscli.stats.budget and ``perscli budget``: the additive shear budget's xi+, its normalisation,
the comparison with a measured xi+ (verdict, --check), the figure, and errors."""

import math

import numpy as np
import pytest
from astropy.io import fits

from fits_factory import invoke, one_line_error
from perscli import PerscliError
from perscli.stats.budget import (BANDS, L_BANDS, LMAX, amplitudes, bin_verdicts, budget_at, compare,
                                  power_spectrum, read_xi, xi_plus)
from perscli.stats.settings import BAND_NAMES

ARCMIN = math.pi / 180 / 60
PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"


def xi_file(path, theta, xip, sigma, *, unit="arcmin", drop=(), weight=None, meanr=None, extname="XI"):
    """A correlate output with TreeCorr's GG columns (``drop``: columns to leave out)."""
    theta = np.asarray(theta, float)
    n = theta.size
    columns = {
        "r_nom": theta, "meanr": theta if meanr is None else np.asarray(meanr, float), "meanlogr": np.log(theta),
        "xip": np.asarray(xip, float), "xim": np.zeros(n), "xip_im": np.zeros(n), "xim_im": np.zeros(n),
        "sigma_xip": np.asarray(sigma, float), "sigma_xim": np.asarray(sigma, float),
        "weight": np.ones(n) if weight is None else np.asarray(weight, float), "npairs": np.full(n, 1e4),
    }
    hdu = fits.BinTableHDU.from_columns([fits.Column(name, "D", array=values) for name, values in columns.items()
                                         if name not in drop], name=extname)
    if unit is not None:
        hdu.header["SEP_UNIT"] = unit
    fits.HDUList([fits.PrimaryHDU(), hdu]).writeto(path)
    return str(path)


THETA = np.geomspace(0.5, 120, 12)                      # arcmin, where the budget is positive
BUDGET = xi_plus(THETA * ARCMIN)


# -- the budget itself ---------------------------------------------------------------------------

@pytest.mark.parametrize("arcmin, reference", [(1, 6.81e-8), (10, 1.87e-8), (100, 8.4e-10)])
def test_reference_values_of_notes_section_6(arcmin, reference):
    value = xi_plus(arcmin * ARCMIN, "dore2018", "E")
    assert value == pytest.approx(reference, rel=0.01)


def test_eb_doubles_the_e_budget():
    theta = np.geomspace(0.1, 300, 20) * ARCMIN
    np.testing.assert_allclose(xi_plus(theta, modes="EB"), 2 * xi_plus(theta, modes="E"), rtol=1e-14)


def test_each_band_carries_its_variance():
    # sum over a band of (2l+1)/(4pi) C_l is the band's contribution to xi+(0) = <g1^2> per
    # component: by construction of N_a it is A_a^2, for any set of amplitudes
    for name, amps in BANDS.items():
        ell, cl = power_spectrum(name)
        for (lo, hi), amp in zip(L_BANDS, amps):
            band = slice(lo, hi + 1)
            assert np.sum((2 * ell[band] + 1) / (4 * math.pi) * cl[band]) == pytest.approx(amp ** 2, rel=1e-12)
            # flat l(l+1) C_l inside the band
            flat = ell[band] * (ell[band] + 1) * cl[band]
            np.testing.assert_allclose(flat, flat[0], rtol=1e-12)
        outside = np.ones(LMAX + 1, bool)
        for lo, hi in L_BANDS:
            outside[lo:hi + 1] = False
        assert not cl[outside].any()
        # J0(0) = 1: xi+(0) is the total variance, the RSS of the bands squared
        assert xi_plus(0.0, name) == pytest.approx(sum(a ** 2 for a in amps), rel=1e-12)


def test_rss_of_the_dore_bands_is_the_quoted_2p7e_4():
    assert math.sqrt(xi_plus(0.0, "dore2018")) == pytest.approx(2.7e-4, rel=0.02)


def test_troxel2021_differs_from_dore2018_only_in_the_first_band():
    ell, dore = power_spectrum("dore2018")
    _, troxel = power_spectrum("troxel2021")
    lo, hi = L_BANDS[0]
    first = np.zeros(LMAX + 1, bool)
    first[lo:hi + 1] = True
    np.testing.assert_array_equal(troxel[~first], dore[~first])
    np.testing.assert_allclose(troxel[first] / dore[first], (7.0 / 7.5) ** 2, rtol=1e-12)
    # xi+ is linear in A_a^2: the difference is the first band's template times 7.0^2 - 7.5^2 (x 1e-10)
    theta = np.geomspace(0.5, 300, 15) * ARCMIN
    unit_band1 = xi_plus(theta, (1.0, 0.0, 0.0, 0.0))
    np.testing.assert_allclose(xi_plus(theta, "troxel2021") - xi_plus(theta, "dore2018"),
                               (7.0e-5 ** 2 - 7.5e-5 ** 2) * unit_band1, rtol=1e-9, atol=1e-22)


def test_xi_plus_matches_a_plain_loop_and_keeps_the_shape():
    from scipy.special import j0

    ell, cl = power_spectrum("hirata")
    theta = np.array([[0.3, 3.0], [30.0, 250.0]]) * ARCMIN
    expected = np.array([[np.sum((2 * ell + 1) / (4 * math.pi) * cl * j0(ell * t)) for t in row] for row in theta])
    got = xi_plus(theta, "hirata")
    assert got.shape == (2, 2)
    np.testing.assert_allclose(got, expected, rtol=1e-12)


def test_the_band_names_of_the_cli_are_the_librarys():
    assert set(BAND_NAMES) == set(BANDS)


def test_unknown_bands_or_modes_in_the_library():
    with pytest.raises(PerscliError, match="unknown budget bands 'dore'"):
        amplitudes("dore")
    with pytest.raises(PerscliError, match="unknown modes"):
        xi_plus(1e-3, modes="B")


# -- comparison with a measured xi+ --------------------------------------------------------------

def test_far_below_the_budget(tmp_path):
    path = xi_file(tmp_path / "xi.fits", THETA, BUDGET * 10 ** -1.8, BUDGET * 1e-3)
    result = compare(read_xi(path))
    assert result.n_exceeding == 0 and list(result.verdicts) == ["below"] * 12
    # orders below at 2 sigma: log10(budget / (|xi+| + 2 sigma))
    assert result.orders == pytest.approx(-np.log10(10 ** -1.8 + 2e-3), abs=1e-9)
    assert result.verdict.startswith("below budget at 12 of 12 bins (|xi+| + 2 sigma), by 1.7 orders of magnitude "
                                     "at worst (theta = ")
    np.testing.assert_allclose(result.ratio, 10 ** -1.8, rtol=1e-12)
    np.testing.assert_allclose(result.sigma_ratio, 1e-3, rtol=1e-12)


def test_a_strongly_negative_xi_is_no_better_than_a_positive_one(tmp_path):
    # |xi+| + 2 sigma decides: -0.6 budget with sigma 0.5 budget is 1.6 budgets at 2 sigma, not "below"
    xip, sigma = BUDGET * 0.01, BUDGET * 1e-3
    xip[3], sigma[3] = -0.6 * BUDGET[3], 0.5 * BUDGET[3]
    xip[4], sigma[4] = -0.2 * BUDGET[4], 0.1 * BUDGET[4]
    result = compare(read_xi(xi_file(tmp_path / "xi.fits", THETA, xip, sigma)))
    assert result.verdicts[3] == "cannot tell" and result.verdicts[4] == "below"
    assert f"cannot tell at {THETA[3]:.3g} arcmin" in result.verdict
    assert result.verdict.startswith("below budget at 11 of 12 bins")
    assert bin_verdicts([-3.0], [0.5], [1.0])[0] == "above"


def test_separations_beyond_the_jackknife_patches_cannot_be_told(tmp_path):
    path = tmp_path / "xi.fits"
    xi_file(path, THETA, BUDGET * 0.01, BUDGET * 1e-3)
    with fits.open(path, mode="update") as hdul:
        hdul["XI"].header["VAR_METH"] = "jackknife"
        hdul["XI"].header["PATCHSIZ"] = 10.0           # arcmin: patches 10' wide support separations up to 10'
    result = compare(read_xi(str(path)))
    beyond = THETA > 10.0
    assert not result.supported[beyond].any() and result.supported[~beyond].all()
    assert set(result.verdicts[beyond]) == {"cannot tell"} and set(result.verdicts[~beyond]) == {"below"}
    assert f"{beyond.sum()} bins beyond the jackknife patches' width (10 arcmin): cannot tell there" in result.verdict


def test_separation_units_and_meanr_fallback(tmp_path):
    # the same separations in degrees give the same budget; a NaN meanr falls back to r_nom
    meanr = THETA / 60
    meanr[3] = np.nan
    path = xi_file(tmp_path / "xi.fits", THETA / 60, BUDGET * 0.01, BUDGET * 1e-3, unit="deg", meanr=meanr)
    result = compare(read_xi(path))
    assert result.unit == "deg"
    np.testing.assert_allclose(result.budget, BUDGET, rtol=1e-12)
    # no SEP_UNIT: arcmin
    path = xi_file(tmp_path / "xi2.fits", THETA, BUDGET * 0.01, BUDGET * 1e-3, unit=None)
    assert read_xi(path).unit == "arcmin"


def test_empty_bins_are_skipped(tmp_path):
    xip, sigma, weight = BUDGET * 0.01, BUDGET * 1e-3, np.ones(THETA.size)
    xip[0] = sigma[0] = np.nan
    weight[0] = 0
    path = xi_file(tmp_path / "xi.fits", THETA, xip, sigma, weight=weight)
    result = compare(read_xi(path))
    assert not result.exceeds[0] and np.isnan(result.ratio[0])
    assert "1 empty bin skipped" in result.verdict


def test_cli_below_budget_writes_the_table_and_says_so(tmp_path):
    xi = xi_file(tmp_path / "xi.fits", THETA, BUDGET * 0.01, BUDGET * 1e-3)
    out = tmp_path / "cmp.fits"
    result = invoke("budget", xi, "-o", out, "--check")
    assert result.exit_code == 0, (result.output, result.stderr)
    assert result.stdout == ""
    assert "below budget at 12 of 12 bins (|xi+| + 2 sigma), by 1.9 orders of magnitude at worst" in result.stderr
    with fits.open(out, checksum=True) as hdul:
        table, header = hdul["BUDGET"].data, hdul["BUDGET"].header
        assert table.columns.names == ["theta", "xip_budget", "xip", "sigma_xip", "ratio", "sigma_ratio",
                                       "exceeds", "verdict", "supported"]
        assert list(table["verdict"]) == ["below"] * 12 and table["supported"].all()
        assert table.columns["theta"].unit == "arcmin"
        np.testing.assert_allclose(table["xip_budget"], BUDGET, rtol=1e-12)
        np.testing.assert_allclose(table["ratio"], 0.01, rtol=1e-12)
        assert not table["exceeds"].any()
        assert header["BUDBANDS"] == "dore2018" and header["BUDMODES"] == "E" and header["BUDSIGMA"] == 2.0
        assert header["BUDNEXC"] == 0
        assert header["VERDICT"].startswith("below budget at 12 of 12 bins") and header["BUDNBEL"] == 12
        assert header["CREATOR"].startswith("perscli ") and header["XI"] == "xi.fits" and "XIDS" in header
        assert any("budget bands=dore2018" in h for h in header["HISTORY"])


def test_cli_one_bin_above_fails_check_but_writes_the_output(tmp_path):
    xip, sigma = BUDGET * 0.01, BUDGET * 1e-3
    xip[5] = 3 * BUDGET[5]
    xi = xi_file(tmp_path / "xi.fits", THETA, xip, sigma)
    out = tmp_path / "cmp.fits"
    result = invoke("budget", xi, "-o", out, "--check")
    assert result.exit_code == 3, (result.output, result.stderr)      # a finding: not 1, an error
    # the verdict names the bin: its separation, xi+ against the budget plus N sigma, and the ratio
    line = result.stderr.strip()
    assert f"exceeds the budget at {THETA[5]:.3g} arcmin (xi+ = {xip[5]:.3g} > {BUDGET[5]:.3g} + 2 sigma" in line
    assert "3 +- 0.001 x the budget" in line and line.endswith("; 1 of 12 bins")
    assert "Error" not in result.stderr
    with fits.open(out) as hdul:
        assert list(np.flatnonzero(hdul["BUDGET"].data["exceeds"])) == [5]
        header = hdul["BUDGET"].header
        assert header["BUDNEXC"] == 1 and header["BUDWBIN"] == 5
        assert header["BUDWSEP"] == pytest.approx(THETA[5]) and header["BUDWRAT"] == pytest.approx(3.0)
        assert header["VERDICT"] == line.split(": ", 1)[1]
    # without --check the finding is reported but the exit status is 0
    again = invoke("budget", xi, "-o", tmp_path / "cmp2.fits")
    assert again.exit_code == 0 and f"exceeds the budget at {THETA[5]:.3g} arcmin" in again.stderr


def test_verdict_names_the_worst_exceeding_bin_not_a_noisy_one(tmp_path):
    xip, sigma = BUDGET * 0.01, BUDGET * 1e-3
    xip[2], sigma[2] = 50 * BUDGET[2], 100 * BUDGET[2]          # far over, but within its (huge) errors
    xip[7] = 4 * BUDGET[7]                                      # over by many sigma
    xip[9] = 2 * BUDGET[9]
    result = compare(read_xi(xi_file(tmp_path / "xi.fits", THETA, xip, sigma)))
    assert result.n_exceeding == 2 and result.worst == 7
    assert result.verdict.startswith(f"exceeds the budget at {THETA[7]:.3g} arcmin (xi+ = {xip[7]:.3g} > "
                                     f"{BUDGET[7]:.3g} + 2 sigma, sigma = {sigma[7]:.2g}: 4 +- 0.001 x the budget)")
    assert result.verdict.endswith(f"; 2 of 12 bins exceed, at {THETA[7]:.3g}, {THETA[9]:.3g} arcmin")
    assert [row["bin"] for row in result.exceeding()] == [7, 9]
    assert result.exceeding()[0]["ratio"] == pytest.approx(4.0)


def test_verdict_where_the_budget_is_negative_compares_magnitudes(tmp_path):
    theta = np.array([200.0, 250.0])                            # arcmin: the budget is negative here
    budget_values = xi_plus(theta * ARCMIN)
    assert np.all(budget_values < 0)
    xi = xi_file(tmp_path / "xi.fits", theta, [-5 * budget_values[0], 0.0], [1e-15, 1e-15])
    result = compare(read_xi(xi))
    assert result.n_exceeding == 1 and result.worst == 0
    assert f"(|xi+| = {abs(5 * budget_values[0]):.3g} > |budget| {abs(budget_values[0]):.3g} + 2 sigma" in \
        result.verdict


def test_verdict_says_when_errors_are_shot_noise(tmp_path):
    path = tmp_path / "xi.fits"
    xi_file(path, THETA, BUDGET * 0.01, BUDGET * 1e-3)
    with fits.open(path, mode="update") as hdul:
        hdul["XI"].header["VAR_METH"] = "shot"
    result = invoke("budget", path, "-o", tmp_path / "cmp.fits")
    assert result.exit_code == 0, result.stderr
    assert result.stderr.strip().endswith("at the median; errors are shot noise (no jackknife)")
    with fits.open(tmp_path / "cmp.fits") as hdul:
        header = hdul["BUDGET"].header
        assert header["BUDVARM"] == "shot"
        # below the budget: the bin closest to it is named
        assert header["BUDWSEP"] == pytest.approx(THETA[header["BUDWBIN"]])


def test_verdict_says_when_the_named_bin_has_a_shot_noise_error(tmp_path):
    xip, sigma = BUDGET * 0.01, BUDGET * 1e-3
    xip[11] = 3 * BUDGET[11]
    path = tmp_path / "xi.fits"
    xi_file(path, THETA, xip, sigma)
    with fits.open(path, mode="update") as hdul:
        hdul["XI"].header["VAR_METH"] = "jackknife"
        hdul["XI"].header["SHOTBINS"] = "11"
    result = compare(read_xi(str(path)))
    assert result.worst == 11 and result.shot_bins == (11,)
    assert result.verdict.endswith("; that bin's error is shot noise (too few pairs there for the jackknife)")


def test_cli_above_but_within_errors_passes_check(tmp_path):
    # 1.5 x the budget with an error of one budget: 1.5 - 2 x 1 < 1, not beyond the errors
    xi = xi_file(tmp_path / "xi.fits", THETA, 1.5 * BUDGET, BUDGET)
    result = invoke("budget", xi, "-o", tmp_path / "cmp.fits", "--check")
    assert result.exit_code == 0, (result.output, result.stderr)
    assert "cannot tell at any of 12 bins: |xi+| +- 2 sigma straddles the budget" in result.stderr
    # a tighter --sigma makes it a finding: 1.5 - 0.4 > 1
    tight = invoke("budget", xi, "-o", tmp_path / "cmp2.fits", "--check", "--sigma", "0.4")
    assert tight.exit_code == 3 and "+ 0.4 sigma" in tight.stderr
    assert "12 of 12 bins exceed, at 0.5, 0.823, 1.35, 2.23, 3.67, ... arcmin" in tight.stderr


def test_cli_budget_alone_on_a_grid_and_eb(tmp_path):
    result = invoke("budget", "-o", tmp_path / "e.fits", "--theta-range", 1, 100, "--nbins", 3)
    assert result.exit_code == 0, result.stderr
    assert result.stderr == ""
    eb = invoke("budget", "-o", tmp_path / "eb.fits", "--theta-range", 1, 100, "--nbins", 3, "--modes", "eb")
    assert eb.exit_code == 0, eb.stderr
    with fits.open(tmp_path / "e.fits") as e, fits.open(tmp_path / "eb.fits") as b:
        np.testing.assert_allclose(e["BUDGET"].data["theta"], [1, 10, 100], rtol=1e-12)
        np.testing.assert_allclose(e["BUDGET"].data["xip_budget"], [6.81e-8, 1.87e-8, 8.4e-10], rtol=0.01)
        np.testing.assert_allclose(b["BUDGET"].data["xip_budget"], 2 * e["BUDGET"].data["xip_budget"], rtol=1e-14)
        assert b["BUDGET"].header["BUDMODES"] == "EB"
        assert e["BUDGET"].columns.names == ["theta", "xip_budget"]
    default = invoke("budget", "-o", tmp_path / "d.fits", "--bands", "hirata")
    assert default.exit_code == 0
    with fits.open(tmp_path / "d.fits") as d:
        theta = d["BUDGET"].data["theta"]
        assert len(theta) == 50 and theta[0] == pytest.approx(0.1) and theta[-1] == pytest.approx(300)
        assert d["BUDGET"].header["BUDA1"] == 6.791e-5


def test_cli_plots_are_png(tmp_path):
    xip, sigma = BUDGET * 0.01, BUDGET * 1e-2
    xip[2] = 5 * BUDGET[2]
    xi = xi_file(tmp_path / "xi.fits", THETA, xip, sigma)
    result = invoke("budget", xi, "-o", tmp_path / "cmp.fits", "--plot", tmp_path / "cmp.png")
    assert result.exit_code == 0, result.stderr
    alone = invoke("budget", "-o", tmp_path / "b.fits", "--plot", tmp_path / "b.png")
    assert alone.exit_code == 0, alone.stderr
    for name in ("cmp.png", "b.png"):
        data = (tmp_path / name).read_bytes()
        assert data[:8] == PNG_SIGNATURE and len(data) > 10000


def test_cli_fits_on_stdout(tmp_path):
    import io

    xi = xi_file(tmp_path / "xi.fits", THETA, BUDGET * 0.01, BUDGET * 1e-3)
    result = invoke("budget", xi, "-o", "-")
    assert result.exit_code == 0, result.stderr
    with fits.open(io.BytesIO(result.stdout_bytes)) as hdul:
        assert len(hdul["BUDGET"].data) == THETA.size


# -- errors --------------------------------------------------------------------------------------

def test_error_no_xip_column(tmp_path):
    xi = xi_file(tmp_path / "xi.fits", THETA, BUDGET, BUDGET, drop=("xip",))
    out = tmp_path / "cmp.fits"
    one_line_error(invoke("budget", xi, "-o", out, "--plot", tmp_path / "p.png"), "xi.fits", "no column 'xip'",
                   "perscli correlate")
    assert not out.exists() and not (tmp_path / "p.png").exists()


def test_error_nan_xip_in_a_bin_with_pairs(tmp_path):
    xip = BUDGET * 0.01
    xip[4] = np.nan
    xi = xi_file(tmp_path / "xi.fits", THETA, xip, BUDGET * 1e-3)
    out = tmp_path / "cmp.fits"
    one_line_error(invoke("budget", xi, "-o", out), "column 'xip' is nan in bin 4")
    assert not out.exists()


def test_error_unknown_sep_unit(tmp_path):
    xi = xi_file(tmp_path / "xi.fits", THETA, BUDGET, BUDGET, unit="parsec")
    one_line_error(invoke("budget", xi, "-o", tmp_path / "cmp.fits"), "SEP_UNIT = 'parsec'", "arcmin")


def test_error_existing_output_without_overwrite(tmp_path):
    out = tmp_path / "cmp.fits"
    out.write_bytes(b"keep")
    one_line_error(invoke("budget", "-o", out), "already exists", "--overwrite")
    assert out.read_bytes() == b"keep"
    assert invoke("budget", "-o", out, "--overwrite").exit_code == 0


def test_error_not_fits(tmp_path):
    bad = tmp_path / "xi.fits"
    bad.write_text("not a fits file\n")
    one_line_error(invoke("budget", bad, "-o", tmp_path / "cmp.fits"), "xi.fits")


@pytest.mark.parametrize("args", [["--bands", "dore"], ["--modes", "B"], ["--sigma", "-1"],
                                  ["--theta-range", "10", "1"], ["--plot", "-"]])
def test_usage_errors_exit_2(tmp_path, args):
    result = invoke("budget", *args, "-o", tmp_path / "b.fits")
    assert result.exit_code == 2, (result.exit_code, result.stderr)
    assert not (tmp_path / "b.fits").exists()


def test_grid_options_need_no_xi(tmp_path):
    xi = xi_file(tmp_path / "xi.fits", THETA, BUDGET, BUDGET)
    result = invoke("budget", xi, "--nbins", 5, "-o", tmp_path / "b.fits")
    assert result.exit_code == 2 and "--nbins" in result.stderr


def test_budget_at_other_units():
    np.testing.assert_allclose(budget_at([60.0], "arcsec").budget, budget_at([1.0], "arcmin").budget, rtol=1e-12)


def test_real_pipe_stdin_to_stdout(tmp_path):
    # a real pipe, not the in-process runner: XI on stdin, the table on stdout, the verdict on stderr
    import io
    import subprocess
    import sys

    xi = xi_file(tmp_path / "xi.fits", THETA, BUDGET * 0.01, BUDGET * 1e-3)
    run = subprocess.run([sys.executable, "-c", "from perscli.cli.budget import budget; budget()", "-", "-o", "-",
                          "--check"], input=open(xi, "rb").read(), capture_output=True, timeout=120)
    assert run.returncode == 0, run.stderr
    assert run.stderr.decode().strip().startswith("stdin: below budget at 12 of 12 bins (|xi+| + 2 sigma), by 1.9")
    with fits.open(io.BytesIO(run.stdout)) as hdul:
        assert hdul["BUDGET"].header["XI"] == "stdin"
        np.testing.assert_allclose(hdul["BUDGET"].data["ratio"], 0.01, rtol=1e-12)


def test_the_budgets_the_command_offers_are_the_library_s():
    """perscli budget lists its bands without importing the library (fast --help): the same names."""
    from perscli.stats.budget import BANDS, BAND_SOURCES
    from perscli.stats.settings import BAND_NAMES, BudgetOptions

    assert tuple(BANDS) == BAND_NAMES == tuple(BAND_SOURCES) and BudgetOptions().bands in BAND_NAMES
