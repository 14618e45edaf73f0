"""perscli.scene.catalog and ``perscli catalog``: counts, magnitude laws, sizes, shapes, positions,
Gaia stars and their colours, reproducibility, errors."""

import math
from functools import partial

import numpy as np
import pytest
from astropy.io import fits
from scipy import stats

from perscli import PerscliError
from perscli.instrument import ROMAN_FILTERS
from perscli.scene import project
from perscli.scene.catalog import (Field, GalaxyModel, cumulative_fraction, draw_galaxies, filter_magnitudes,
                                   make_truth_catalog, power_law_magnitudes, truncated_ellipticities,
                                   truncated_sigma)

import fits_factory
from fits_factory import invoke, raw_cards_masked

RA, DEC = 10.0, -44.0


@pytest.fixture(scope="module")
def big():
    """A 30' x 30' field (900 arcmin^2): ~36,000 galaxies and, at 100 per arcmin^2, ~90,000 stars."""
    return make_truth_catalog(RA, DEC, 30.0, star_density=100.0, seed=11)


def galaxies(table):
    return table[table["kind"] == "galaxy"]


def stars(table):
    return table[table["kind"] == "star"]


def fitted_slope(mags, lo, hi, width=0.5):
    """d log10 N / dm of a histogram, weighted least squares on log counts."""
    edges = np.arange(lo, hi + 1e-9, width)
    counts, _ = np.histogram(mags, edges)
    centres = 0.5 * (edges[1:] + edges[:-1])
    slope, _ = np.polyfit(centres, np.log10(counts), 1, w=np.sqrt(counts))
    return slope


def gnomonic(ra0, dec0, ra, dec):
    """Standard coordinates (radians) by the textbook formulas, independent of perscli.scene.project."""
    a0, d0, a, d = map(np.radians, (ra0, dec0, ra, dec))
    cos_c = np.sin(d0) * np.sin(d) + np.cos(d0) * np.cos(d) * np.cos(a - a0)
    xi = np.cos(d) * np.sin(a - a0) / cos_c
    eta = (np.cos(d0) * np.sin(d) - np.sin(d0) * np.cos(d) * np.cos(a - a0)) / cos_c
    return xi, eta


def box_solid_angle(x1, x2, y1, y2):
    """Solid angle of [x1, x2] x [y1, y2] on the gnomonic plane (unit distance)."""
    f = lambda x, y: math.atan(x * y / math.sqrt(1 + x * x + y * y))   # noqa: E731
    return f(x2, y2) - f(x1, y2) - f(x2, y1) + f(x1, y1)


# -- the field ---------------------------------------------------------------------------------

def test_field_area_is_the_solid_angle_of_the_square():
    fld = Field(RA, DEC, 10.0)
    assert fld.area == pytest.approx(100.0, rel=1e-5)
    big_field = Field(RA, DEC, 2400.0)                   # 40 degrees: far from flat
    a = math.tan(math.radians(20.0))
    assert big_field.area == pytest.approx(4 * box_solid_angle(0, a, 0, a) * (180 * 60 / math.pi) ** 2)
    assert 0.95 < big_field.area / 2400.0 ** 2 < 0.97      # a square of 40 degrees is not 1600 deg^2


@pytest.mark.parametrize("size", [-1.0, 0.0, 3600.0])
def test_field_size_out_of_range(size):
    with pytest.raises(PerscliError, match="field size"):
        Field(RA, DEC, size)


def test_positions_inside_the_field_and_uniform(big):
    fld = Field(RA, DEC, 30.0)
    assert fld.contains(big["ra"], big["dec"]).all()
    xi, eta = gnomonic(RA, DEC, big["ra"], big["dec"])
    a = fld.half_width
    assert np.abs(xi).max() <= a * (1 + 1e-12) and np.abs(eta).max() <= a * (1 + 1e-12)
    # reaches the edges: not a smaller square
    assert np.abs(xi).max() > 0.99 * a and np.abs(eta).max() > 0.99 * a
    for coord in (xi, eta):
        assert stats.kstest(coord, stats.uniform(loc=-a, scale=2 * a).cdf).pvalue > 1e-3
    n = len(big)
    quadrants = np.histogram2d(xi, eta, bins=[[-a, 0, a], [-a, 0, a]])[0].ravel()
    assert np.all(np.abs(quadrants - n / 4) < 4 * np.sqrt(n / 4)), quadrants


def test_positions_are_uniform_in_solid_angle_on_a_wide_field():
    """On a 40-degree field, uniform on the plane would put 1.4x more objects per steradian in the corners."""
    fld = Field(RA, DEC, 2400.0)
    rng = np.random.Generator(np.random.PCG64(5))
    ra, dec = fld.sample(rng, 60000)
    xi, eta = project(RA, DEC, ra, dec)
    a = fld.half_width
    h = a / 4
    centre = (np.abs(xi) < h) & (np.abs(eta) < h)
    corner = (xi > a - 2 * h) & (eta > a - 2 * h)
    density_centre = centre.sum() / box_solid_angle(-h, h, -h, h)
    density_corner = corner.sum() / box_solid_angle(a - 2 * h, a, a - 2 * h, a)
    assert density_corner / density_centre == pytest.approx(1.0, abs=0.08)


@pytest.mark.parametrize("ra, dec", [(0.0, 0.0), (359.99, 30.0), (123.0, 89.95), (200.0, -89.99)])
def test_fields_across_ra_zero_and_at_the_poles(ra, dec):
    table = make_truth_catalog(ra, dec, 20.0, galaxy_density=5.0, seed=2)
    assert len(table) > 1000
    assert np.all((table["ra"] >= 0) & (table["ra"] < 360))
    assert Field(ra, dec, 20.0).contains(table["ra"], table["dec"]).all()
    xi, eta = project(ra, dec, table["ra"], table["dec"])
    a = Field(ra, dec, 20.0).half_width
    assert np.abs(xi).max() > 0.98 * a and np.abs(eta).max() > 0.98 * a


# -- counts ------------------------------------------------------------------------------------

@pytest.mark.parametrize("seed, star_density", [(1, None), (2, None), (3, None), (1, 2.5), (2, 7.0)])
def test_counts_are_poisson_with_the_densities(seed, star_density):
    """Power-law stars at the density given; Galactic-model stars (default) at the model's density there."""
    table = make_truth_catalog(RA, DEC, 10.0, seed=seed, star_density=star_density)
    stars_per_arcmin2 = table.meta["SDENSC"] if star_density is None else star_density
    if star_density is None:
        assert stars_per_arcmin2 == pytest.approx(2.504, abs=0.005)      # module docstring of starcounts
    for kind, mean in (("galaxy", 40.0 * 100.0), ("star", stars_per_arcmin2 * 100.0)):
        n = int((table["kind"] == kind).sum())
        assert abs(n - mean) < 4 * math.sqrt(mean), (kind, n)
    assert table.meta["NGAL"] == (table["kind"] == "galaxy").sum()
    assert table.meta["NSTAR"] == (table["kind"] == "star").sum()


def test_zero_density_gives_no_objects():
    table = make_truth_catalog(RA, DEC, 10.0, galaxy_density=0.0, star_density=0.0, seed=1)
    assert len(table) == 0 and table.meta["NGAL"] == 0


@pytest.mark.parametrize("key", ["galaxy_density", "star_density"])
def test_negative_density_is_an_error_in_the_library(key):
    with pytest.raises(PerscliError, match="density -1"):
        make_truth_catalog(RA, DEC, 10.0, **{key: -1.0})


# -- magnitudes --------------------------------------------------------------------------------

def test_galaxy_magnitudes_follow_the_power_law(big):
    j = galaxies(big)["mag_J129"]
    assert j.min() >= 20.0 and j.max() <= 25.5
    assert fitted_slope(j, 20.0, 25.5) == pytest.approx(0.28, abs=0.015)


def test_star_magnitudes_follow_the_power_law(big):
    j = stars(big)["mag_J129"]
    assert j.min() >= 10.0 and j.max() <= 24.0
    assert fitted_slope(j, 14.0, 24.0) == pytest.approx(0.15, abs=0.015)


def test_documented_counts():
    """The numbers the docstrings quote."""
    stars_brighter_than_14 = 2.5 * 3600 * cumulative_fraction(14.0, 0.15, 10.0, 24.0)
    assert stars_brighter_than_14 == pytest.approx(215, abs=1)
    galaxies_brighter_than_24 = 40.0 * cumulative_fraction(24.0, 0.28, 20.0, 25.5)
    assert galaxies_brighter_than_24 == pytest.approx(14.5, abs=0.05)


def test_drawn_counts_brighter_than_a_magnitude_match_the_law(big):
    n = len(galaxies(big))
    expected = n * cumulative_fraction(24.0, 0.28, 20.0, 25.5)
    observed = (galaxies(big)["mag_J129"] < 24.0).sum()
    assert abs(observed - expected) < 4 * math.sqrt(expected)


def test_power_law_sampler_on_its_own():
    m = power_law_magnitudes(np.random.default_rng(3), 200000, 0.4, 18.0, 22.0)
    assert fitted_slope(m, 18.0, 22.0, width=0.25) == pytest.approx(0.4, abs=0.01)


def test_colours(big):
    g, s = galaxies(big), stars(big)
    jh = g["mag_J129"] - g["mag_H158"]
    assert np.mean(jh) == pytest.approx(0.30, abs=0.005) and np.std(jh) == pytest.approx(0.15, abs=0.005)
    sjh = s["mag_J129"] - s["mag_H158"]
    assert sjh.min() >= 0.0 and sjh.max() <= 1.0
    assert np.median(sjh) == pytest.approx(0.45, abs=0.01)


def test_other_filters_are_linear_in_log_wavelength():
    mags = filter_magnitudes([20.0], [19.5])
    lam = {"J129": 1.293, "H158": 1.577, "R062": 0.620, "K213": 2.125, "W146": 1.464}
    for name in ("R062", "K213", "W146"):
        t = math.log(lam[name] / lam["J129"]) / math.log(lam["H158"] / lam["J129"])
        assert mags[name][0] == pytest.approx(20.0 - 0.5 * t, abs=1e-12)
    assert mags["J129"][0] == 20.0 and mags["H158"][0] == 19.5
    assert mags["R062"][0] > mags["Z087"][0] > mags["Y106"][0] > 20.0 > mags["W146"][0] > 19.5


def test_every_roman_filter_has_a_column(big):
    for name in ROMAN_FILTERS:
        assert np.all(np.isfinite(big[f"mag_{name}"]))


# -- sizes and shapes --------------------------------------------------------------------------

def test_half_light_radii(big):
    g, s = galaxies(big), stars(big)
    assert g["hlr"].min() >= 0.08 and g["hlr"].max() <= 1.5
    assert np.all(s["hlr"] == 0) and np.all(s["e1"] == 0) and np.all(s["e2"] == 0)
    near23 = np.abs(g["mag_J129"] - 23.0) < 0.25
    assert np.median(g["hlr"][near23]) == pytest.approx(0.35, rel=0.05)
    faint = np.abs(g["mag_J129"] - 25.0) < 0.25
    # median log size falls by 0.08 dex per magnitude
    assert np.median(np.log10(g["hlr"][faint])) - np.median(np.log10(g["hlr"][near23])) == pytest.approx(
        -0.16, abs=0.03)


def test_truncated_sigma_matches_a_monte_carlo():
    e = np.random.default_rng(0).normal(0, 0.27, (2_000_000, 2))
    e = e[np.hypot(e[:, 0], e[:, 1]) <= 0.7]
    assert truncated_sigma(0.27, 0.7) == pytest.approx(np.std(e[:, 0]), abs=0.001)
    assert truncated_sigma(0.27, 0.7) == pytest.approx(0.2532, abs=1e-4)


def test_ellipticities_are_truncated_at_0_7(big):
    g = galaxies(big)
    e = np.hypot(g["e1"], g["e2"])
    assert e.max() <= 0.7
    assert e.max() > 0.68                                      # the truncation is reached, not a tighter cut
    expected = truncated_sigma(0.27, 0.7)
    for comp in (g["e1"], g["e2"]):
        assert np.std(comp) == pytest.approx(expected, abs=0.004)
        assert abs(np.mean(comp)) < 4 * expected / math.sqrt(len(comp))
    assert np.std(g["e1"]) < 0.262                             # narrower than the untruncated 0.27


def test_redraws_keep_every_pair_isotropic():
    e1, e2 = truncated_ellipticities(np.random.default_rng(1), 100000, 0.5, 0.7)   # half the pairs redrawn
    assert np.hypot(e1, e2).max() <= 0.7
    angle = np.arctan2(e2, e1)
    assert stats.kstest(angle, stats.uniform(loc=-np.pi, scale=2 * np.pi).cdf).pvalue > 1e-3


# -- reproducibility ---------------------------------------------------------------------------

def test_same_seed_same_bytes_other_seed_other_catalog(tmp_path):
    out1, out2, out3 = (tmp_path / f"{k}.fits" for k in "abc")
    for out, seed in ((out1, "4"), (out2, "4"), (out3, "5")):
        result = invoke("catalog", "--ra", RA, "--dec", DEC, "--size", 5, "--seed", seed, "-o", out)
        assert result.exit_code == 0, result.output
    assert raw_cards_masked(out1) == raw_cards_masked(out2)
    with fits.open(out1) as a, fits.open(out3) as c:
        assert a["TRUTH"].header["SEED"] == 4 and c["TRUTH"].header["SEED"] == 5
        assert not np.array_equal(a["TRUTH"].data["ra"][:10], c["TRUTH"].data["ra"][:10])


def test_galaxies_do_not_depend_on_the_star_model():
    a = galaxies(make_truth_catalog(RA, DEC, 5.0, star_density=2.5, seed=9))
    b = galaxies(make_truth_catalog(RA, DEC, 5.0, star_density=7.0, seed=9))
    assert len(a) == len(b) and np.array_equal(a["ra"], b["ra"]) and np.array_equal(a["e1"], b["e1"])


def test_model_parameters_are_used_and_recorded():
    table = make_truth_catalog(RA, DEC, 5.0, seed=1, galaxy_model=GalaxyModel(mag_min=22.0, e_max=0.3))
    g = galaxies(table)
    assert g["mag_J129"].min() >= 22.0 and np.hypot(g["e1"], g["e2"]).max() <= 0.3
    assert table.meta["GMAGMIN"] == 22.0 and table.meta["GEMAX"] == 0.3


def test_draw_galaxies_uses_only_its_generator():
    fld = Field(RA, DEC, 3.0)
    a = draw_galaxies(np.random.default_rng(2), fld, 40.0, GalaxyModel())
    b = draw_galaxies(np.random.default_rng(2), fld, 40.0, GalaxyModel())
    assert all(np.array_equal(a[k], b[k]) for k in a)


# -- the output file ---------------------------------------------------------------------------

def test_output_file_columns_units_and_header(tmp_path):
    out = tmp_path / "truth.fits"
    result = invoke("catalog", "--ra", RA, "--dec", DEC, "--size", 4, "--seed", 3, "-o", out)
    assert result.exit_code == 0, result.output
    # stderr: one line, the count of rows written (tests/test_fuzz_values.py checks it against the table)
    assert result.stdout == "" and result.stderr.startswith(f"{out}: ") and result.stderr.count("\n") == 1
    with fits.open(out, checksum=True) as hdul:
        hdu = hdul["TRUTH"]
        data, hdr = hdu.data, hdu.header
        names = data.columns.names
        for col in ("id", "ra", "dec", "kind", "hlr", "e1", "e2", "gaia_id", *(f"mag_{f}" for f in ROMAN_FILTERS)):
            assert col in names
        units = {c.name: c.unit for c in data.columns}
        assert units["ra"] == "deg" and units["dec"] == "deg" and units["hlr"] == "arcsec"
        assert units["mag_J129"] == "mag"
        assert data.columns["id"].format == "K" and data.columns["ra"].format == "D"
        assert len(np.unique(data["id"])) == len(data)
        assert set(np.char.strip(data["kind"])) == {"galaxy", "star"}
        assert np.all(data["gaia_id"] == -1)
        assert hdr["FIELDRA"] == RA and hdr["FIELDDEC"] == DEC and hdr["FIELDSZ"] == 4.0
        assert hdr["GALDENS"] == 40.0 and hdr["STARSRC"] == "model" and hdr["STARMOD"] == "galactic"
        assert "STARDENS" not in hdr and hdr["SDENSC"] == pytest.approx(2.504, abs=0.005)
        assert hdr["GMAGSLP"] == 0.28 and hdr["SGH1"] == 360.0 and hdr["SMAGMIN"] == 4.0 and hdr["GESIG"] == 0.27
        assert hdr["SEED"] == 3 and hdr["CREATOR"].startswith("perscli ")
        history = str(hdr["HISTORY"]).replace("\n", "")
        assert "catalog ra=10.0" in history and "star-model=galactic" in history
        assert "CHECKSUM" in hdr and "DATASUM" in hdr
    # an explicit density: the power-law stars, recorded as before
    out = tmp_path / "powerlaw.fits"
    assert invoke("catalog", "--ra", RA, "--dec", DEC, "--size", 4, "--seed", 3, "--star-density", 2.5,
                  "-o", out).exit_code == 0
    with fits.open(out) as hdul:
        hdr = hdul["TRUTH"].header
        assert hdr["STARDENS"] == 2.5 and hdr["STARSRC"] == "model" and hdr["STARMOD"] == "powerlaw"
        assert hdr["SMAGSLP"] == 0.15 and "SGH1" not in hdr
        assert "star-density=2.5" in str(hdr["HISTORY"]).replace("\n", "")


def test_catalog_to_stdout(tmp_path):
    result = invoke("catalog", "--ra", RA, "--dec", DEC, "--size", 2, "-o", "-")
    assert result.exit_code == 0
    path = tmp_path / "s.fits"
    path.write_bytes(result.stdout_bytes)
    with fits.open(path) as hdul:
        assert hdul["TRUTH"].header["NGAL"] == (np.char.strip(hdul["TRUTH"].data["kind"]) == "galaxy").sum()


# -- Gaia --------------------------------------------------------------------------------------

def gaia_file(path, rows, *, units=("rad", "nJy"), drop=None):
    """A Gaia DR2 chunk in the LSST reference-catalog layout: rows of (id, ra, dec, G, BP, RP) (deg, AB mag)."""
    rows = np.array(rows, dtype=np.float64)
    flux = lambda m: np.where(np.isfinite(m), 10 ** ((31.4 - m) / 2.5), 0.0)   # noqa: E731
    ra_unit, flux_unit = units
    scale = 1.0 if ra_unit == "deg" else np.pi / 180
    cols = [fits.Column("id", "K", array=rows[:, 0].astype(np.int64)),
            fits.Column("coord_ra", "D", unit=ra_unit, array=rows[:, 1] * scale),
            fits.Column("coord_dec", "D", unit=ra_unit, array=rows[:, 2] * scale),
            fits.Column("phot_g_mean_flux", "D", unit=flux_unit, array=flux(rows[:, 3])),
            fits.Column("phot_bp_mean_flux", "D", unit=flux_unit, array=flux(rows[:, 4])),
            fits.Column("phot_rp_mean_flux", "D", unit=flux_unit, array=flux(rows[:, 5]))]
    cols = [c for c in cols if c.name != drop]
    fits.HDUList([fits.PrimaryHDU(), fits.BinTableHDU.from_columns(cols)]).writeto(path)
    return str(path)


# (BP-RP)_AB of a star whose Gaia (Vega) BP-RP is 1: the DR2 zero points 25.3514/25.3806 (BP) and 24.7619/25.1161 (RP)
BPRP_AB_OF_VEGA_1 = 1.0 + ((25.3806 - 25.3514) - (25.1161 - 24.7619))


def test_gaia_colour_of_a_bp_rp_1_star_by_hand(tmp_path):
    rp = 15.0 - 0.5
    path = gaia_file(tmp_path / "g.fits", [(42, RA, DEC, 15.0, rp + BPRP_AB_OF_VEGA_1, rp)])
    table = make_truth_catalog(RA, DEC, 1.0, galaxy_density=0.0, gaia=[path])
    assert len(table) == 1 and table["gaia_id"][0] == 42 and table["kind"][0] == "star"
    # G_Vega = 15 - 0.105; 2MASS J = G - (-0.01883 + 1.394 - 0.07893); J_AB = J_Vega + 0.91
    expected_j = 15.0 - 0.105 - (-0.01883 + 1.394 - 0.07893) + 0.91
    expected_h = 15.0 - 0.105 - (-0.1621 + 1.968 - 0.1328) + 1.39
    assert table["mag_J129"][0] == pytest.approx(expected_j, abs=1e-9)
    assert table["mag_H158"][0] == pytest.approx(expected_h, abs=1e-9)
    assert expected_j == pytest.approx(14.50876, abs=1e-5)
    assert table["hlr"][0] == 0 and table["e1"][0] == 0


def test_gaia_stars_without_colour_get_the_median_and_colours_are_clipped(tmp_path):
    def star(i, x_vega, g=16.0, dra=0.0):
        rp = 15.0
        return (i, RA + dra, DEC, g, rp + x_vega - 0.325, rp)
    rows = [star(1, 1.0), star(2, 1.5), star(3, 2.0), (4, RA, DEC, 16.0, np.nan, 15.0),
            star(5, 7.0), star(6, 1.0, g=np.nan), star(7, 1.0, dra=1.0)]
    path = gaia_file(tmp_path / "g.fits", rows)
    table = make_truth_catalog(RA, DEC, 2.0, galaxy_density=0.0, gaia=[path])
    by_id = {int(r["gaia_id"]): r for r in table}
    assert set(by_id) == {1, 2, 3, 4, 5}                 # 6 has no G flux, 7 is outside the field
    # the median BP-RP of every row read with BP and RP (1, 1.5, 2, 7, 1, 1) is 1.25
    j4 = 16.0 - 0.105 - (-0.01883 + 1.394 * 1.25 - 0.07893 * 1.25 ** 2) + 0.91
    assert by_id[4]["mag_J129"] == pytest.approx(j4, abs=1e-6)
    j5 = 16.0 - 0.105 - (-0.01883 + 1.394 * 5.5 - 0.07893 * 5.5 ** 2) + 0.91   # 7 clipped to 5.5 for J
    h5 = 16.0 - 0.105 - (-0.1621 + 1.968 * 5.0 - 0.1328 * 5.0 ** 2) + 1.39     # and to 5.0 for H
    assert by_id[5]["mag_J129"] == pytest.approx(j5, abs=1e-6)
    assert by_id[5]["mag_H158"] == pytest.approx(h5, abs=1e-6)
    assert table.meta["GAIANMED"] == 1 and table.meta["GAIANOG"] == 1 and table.meta["GAIANIN"] == 7
    assert table.meta["GAIABPRP"] == pytest.approx(1.25, abs=1e-6)


def test_gaia_file_given_twice_counts_its_stars_once(tmp_path):
    path = gaia_file(tmp_path / "g.fits", [(1, RA, DEC, 16, 16.5, 15.5), (2, RA, DEC + 0.001, 17, 17.5, 16.5)])
    table = make_truth_catalog(RA, DEC, 1.0, galaxy_density=0.0, gaia=[path, path])
    assert sorted(table["gaia_id"]) == [1, 2]


def test_real_gaia_chunks(shared_data, tmp_path):
    files = sorted(str(p) for p in (shared_data / "gaia").glob("*.fits"))
    assert len(files) == 2
    ra0, dec0, size = 10.3, -44.5, 40.0
    out = tmp_path / "truth.fits"
    result = invoke("catalog", "--ra", ra0, "--dec", dec0, "--size", size, "--galaxy-density", 1,
                    *sum((["--gaia", f] for f in files), []), "-o", out)
    assert result.exit_code == 0, result.output
    # the Gaia stars inside the field, found here without perscli
    ids, g_ab, bprp_ab = [], [], []
    for f in files:
        with fits.open(f) as hdul:
            d = hdul[1].data
            xi, eta = gnomonic(ra0, dec0, np.degrees(d["coord_ra"]), np.degrees(d["coord_dec"]))
            half = math.tan(math.radians(size / 60) / 2)
            inside = (np.abs(xi) <= half) & (np.abs(eta) <= half)
            ids.extend(d["id"][inside])
            g_ab.extend(31.4 - 2.5 * np.log10(d["phot_g_mean_flux"][inside]))
            with np.errstate(divide="ignore", invalid="ignore"):
                bprp_ab.extend(-2.5 * np.log10(d["phot_bp_mean_flux"][inside] / d["phot_rp_mean_flux"][inside]))
    with fits.open(out) as hdul:
        data, hdr = hdul["TRUTH"].data, hdul["TRUTH"].header
    s = data[np.char.strip(data["kind"]) == "star"]
    assert len(s) == len(ids) > 100
    assert sorted(s["gaia_id"]) == sorted(ids)
    assert hdr["STARSRC"] == "gaia" and hdr["NSTAR"] == len(ids)
    assert hdr["GA001"] == "145649.fits" and hdr["GA002"] == "145650.fits"
    assert hdr["GA001DS"].isdigit()
    # J - G of stars with their own colour: from about -0.4 (blue) to -1.8 (red M dwarfs), AB
    g_of = dict(zip(ids, g_ab))
    x_of = dict(zip(ids, bprp_ab))
    for row in s[:50]:
        x = x_of[row["gaia_id"]] + 0.325
        if not np.isfinite(x):
            continue
        j_expected = g_of[row["gaia_id"]] - 0.105 - (-0.01883 + 1.394 * min(max(x, -0.5), 5.5)
                                                     - 0.07893 * min(max(x, -0.5), 5.5) ** 2) + 0.91
        assert row["mag_J129"] == pytest.approx(j_expected, abs=1e-6)
        assert -2.5 < row["mag_J129"] - g_of[row["gaia_id"]] < 0.5


# -- command-line errors -----------------------------------------------------------------------

#: ``expect_error(tmp_path, ARGS, *needles)``: ``perscli catalog --ra RA --dec DEC ARGS -o OUT`` fails in one
#: line holding every needle, no output file, inputs unchanged (:func:`fits_factory.expect_error`)
expect_error = partial(fits_factory.expect_error, command=("catalog", "--ra", RA, "--dec", DEC))


#: a usage error (exit 2) in one line, nothing written, inputs unchanged (the shared harness's)
expect_usage_error = partial(fits_factory.expect_error, command="catalog", code=2)


def test_gaia_file_that_is_not_fits(tmp_path):
    bad = tmp_path / "bad.fits"
    bad.write_bytes(b"not a catalog\n" * 300)
    expect_error(tmp_path, ["--gaia", bad], str(bad), "not a FITS file")


def test_gaia_file_that_does_not_exist(tmp_path):
    expect_error(tmp_path, ["--gaia", tmp_path / "nope.fits"], "nope.fits", "no such file")


def test_gaia_file_without_a_column(tmp_path):
    path = gaia_file(tmp_path / "g.fits", [(1, RA, DEC, 16, 16.5, 15.5)], drop="phot_bp_mean_flux")
    expect_error(tmp_path, ["--gaia", path], path, "'phot_bp_mean_flux'", "check that this is a Gaia")


def test_gaia_file_in_degrees(tmp_path):
    path = gaia_file(tmp_path / "g.fits", [(1, RA, DEC, 16, 16.5, 15.5)], units=("deg", "nJy"))
    expect_error(tmp_path, ["--gaia", path], path, "'coord_ra'", "'deg'", "'rad'")


def test_gaia_file_that_is_an_image(tmp_path):
    path = tmp_path / "img.fits"
    fits.PrimaryHDU(np.zeros((4, 4))).writeto(path)
    expect_error(tmp_path, ["--gaia", path], str(path), "no binary table")


def test_existing_output_without_overwrite(tmp_path):
    out = tmp_path / "out.fits"
    out.write_bytes(b"keep")
    result = invoke("catalog", "--ra", RA, "--dec", DEC, "-o", out)
    assert result.exit_code == 1 and "--overwrite" in result.stderr
    assert out.read_bytes() == b"keep"
    assert invoke("catalog", "--ra", RA, "--dec", DEC, "--size", 1, "-o", out, "--overwrite").exit_code == 0


@pytest.mark.parametrize("args, needle", [
    (["--ra", RA, "--dec", DEC, "--galaxy-density", "-1", "-o", "OUT"], "--galaxy-density"),
    (["--ra", RA, "--dec", DEC, "--star-density", "-0.5", "-o", "OUT"], "--star-density"),
    (["--ra", RA, "--dec", DEC, "--size", "0", "-o", "OUT"], "--size"),
    (["--ra", RA, "--dec", "95", "-o", "OUT"], "--dec"),
    (["--ra", RA, "--dec", DEC, "--seed", "-3", "-o", "OUT"], "--seed"),
    (["--dec", DEC, "-o", "OUT"], "--ra"),
    (["--ra", RA, "--dec", DEC], "--output"),
])
def test_usage_errors(tmp_path, args, needle):
    """Option values out of range are usage errors (exit 2), as --gain 0 is for apply-persistence."""
    # the output is given in args (or missing, the error under test)
    expect_usage_error(tmp_path, [tmp_path / "x.fits" if a == "OUT" else a for a in args], needle, out=None)


# -- catalogues of detector footprints ------------------------------------------------------------

from perscli.scene.regions import (ARCMIN2_PER_SR, FootprintUnion, expand_polygon,  # noqa: E402
                                   polygon_area, rectangle_solid_angle)


def square(ra0, dec0, half_deg, rot_deg=0.0):
    """Corners (counter-clockwise) of a square of half-side ``half_deg`` on the TAN plane at (ra0, dec0)."""
    from perscli.scene import deproject

    t = np.radians(rot_deg) + np.array([0.25, 0.75, 1.25, 1.75]) * np.pi
    h = math.tan(math.radians(half_deg)) * math.sqrt(2)
    return deproject(ra0, dec0, h * np.cos(t), h * np.sin(t))


def sca_footprints(n=4, sca=7, ra=RA, dec=DEC):
    """Footprints of SCA ``sca`` for ``n`` pointings dithered by ~2.5' around (ra, dec) (GalSim's WCS)."""
    from perscli.scene.footprints import sca_footprint
    from perscli.scene.schedule import Pointing

    out = []
    for k in range(n):
        p = Pointing(k, 61541.97 + k * 169.8 / 86400, 139.8, ra + 0.04 * (k % 2), dec + 0.03 * (k // 2), 30.0 + k,
                     "J129", sca)
        out.append(sca_footprint(p))
    return out


def inside_convex(ra0, dec0, corners, ra, dec):
    """Points inside one convex polygon, by the textbook gnomonic formulas (independent of perscli)."""
    x, y = gnomonic(ra0, dec0, np.asarray(ra), np.asarray(dec))
    cx, cy = gnomonic(ra0, dec0, *corners)
    s = np.sign(np.sum(cx * np.roll(cy, -1) - np.roll(cx, -1) * cy))
    ok = np.ones(len(x), dtype=bool)
    for i in range(len(cx)):
        j = (i + 1) % len(cx)
        ok &= s * ((cx[j] - cx[i]) * (y - cy[i]) - (cy[j] - cy[i]) * (x - cx[i])) >= 0
    return ok


def clip(subject, clipper):
    """Sutherland-Hodgman: the intersection of two convex counter-clockwise polygons [(x, y), ...]."""
    out = list(subject)
    for i in range(len(clipper)):
        a, b = clipper[i], clipper[(i + 1) % len(clipper)]
        side = lambda p: (b[0] - a[0]) * (p[1] - a[1]) - (b[1] - a[1]) * (p[0] - a[0])   # noqa: E731
        src, out = out, []
        for k in range(len(src)):
            p, q = src[k], src[(k + 1) % len(src)]
            sp, sq = side(p), side(q)
            if sp >= 0:
                out.append(p)
            if sp * sq < 0:
                t = sp / (sp - sq)
                out.append((p[0] + t * (q[0] - p[0]), p[1] + t * (q[1] - p[1])))
    return out


def test_area_of_one_footprint_is_its_solid_angle():
    for corners in (square(RA, DEC, 0.06, 17.0), square(200.0, 70.0, 5.0, 33.0), *sca_footprints(1)):
        u = FootprintUnion([corners])
        assert u.area == pytest.approx(polygon_area(*corners) * ARCMIN2_PER_SR, rel=1e-10)
    # an axis-aligned square on the plane of its own centre: the closed form of a gnomonic rectangle
    a = math.tan(math.radians(2.0))
    assert FootprintUnion([square(RA, DEC, 2.0)], centre=(RA, DEC)).area == \
        pytest.approx(box_solid_angle(-a, a, -a, a) * ARCMIN2_PER_SR, rel=1e-10)
    assert rectangle_solid_angle(-a, a, -a, a) == pytest.approx(box_solid_angle(-a, a, -a, a), rel=1e-14)


def test_area_of_overlapping_footprints_counts_the_overlap_once():
    from perscli.scene import deproject

    a, b = square(RA, DEC, 0.06, 17.0), square(RA + 0.05, DEC + 0.03, 0.06, 40.0)
    u = FootprintUnion([a, b])
    # the overlap, clipped on the plane where both are straight-sided, then measured on the sphere
    pa = list(zip(*gnomonic(u.ra, u.dec, *a)))
    pb = list(zip(*gnomonic(u.ra, u.dec, *b)))
    both = clip(pa, pb)
    assert len(both) >= 3
    ora, odec = deproject(u.ra, u.dec, [p[0] for p in both], [p[1] for p in both])
    expect = polygon_area(*a) + polygon_area(*b) - polygon_area(ora, odec)
    assert u.area == pytest.approx(expect * ARCMIN2_PER_SR, rel=1e-6)
    # a footprint inside another adds nothing; disjoint ones add up
    assert FootprintUnion([a, square(RA, DEC, 0.01)]).area == pytest.approx(polygon_area(*a) * ARCMIN2_PER_SR,
                                                                             rel=1e-9)
    far = square(RA + 1.0, DEC, 0.06)
    assert FootprintUnion([a, far]).area == pytest.approx((polygon_area(*a) + polygon_area(*far)) * ARCMIN2_PER_SR,
                                                          rel=1e-9)


@pytest.fixture(scope="module")
def footprint_catalog():
    """Four dithered SCA footprints (+30"), galaxies at 40 and stars at 60 per arcmin^2."""
    fps = sca_footprints(4)
    return fps, make_truth_catalog(footprints=fps, margin_arcsec=30.0, star_density=60.0, seed=21)


def test_footprint_catalog_counts_are_poisson_with_the_densities(footprint_catalog):
    fps, table = footprint_catalog
    u = FootprintUnion(fps, 30.0)
    assert table.meta["FIELDAR"] == pytest.approx(u.area, rel=1e-6)
    assert table.meta["REGION"] == "footprints" and table.meta["NFOOT"] == 4 and table.meta["FOOTMARG"] == 30.0
    assert u.area < table.meta["BOXAREA"]
    for kind, density in (("galaxy", 40.0), ("star", 60.0)):
        sub = table[table["kind"] == kind]
        lam = density * u.area
        assert abs(len(sub) - lam) < 4 * math.sqrt(lam), (kind, len(sub), lam)
        # and in each footprint on its own (grown by the margin): Poisson with its own solid angle
        for corners in fps:
            grown = expand_polygon(*corners, 30.0)
            n = inside_convex(u.ra, u.dec, grown, sub["ra"], sub["dec"]).sum()
            lam_k = density * polygon_area(*grown) * ARCMIN2_PER_SR
            assert abs(n - lam_k) < 4 * math.sqrt(lam_k), (kind, n, lam_k)


def test_footprint_catalog_has_nothing_outside_the_grown_footprints(footprint_catalog):
    fps, table = footprint_catalog
    u = FootprintUnion(fps, 30.0)
    grown = [expand_polygon(*c, 30.0) for c in fps]
    inside = np.zeros(len(table), dtype=bool)
    for g in grown:
        inside |= inside_convex(u.ra, u.dec, g, table["ra"], table["dec"])
    assert inside.all()
    # the margin is populated: objects outside every footprint itself, within 30" of one
    bare = np.zeros(len(table), dtype=bool)
    for c in fps:
        bare |= inside_convex(u.ra, u.dec, c, table["ra"], table["dec"])
    assert 0.05 < (~bare).mean() < 0.3
    assert set(table["kind"]) == {"galaxy", "star"}
    assert np.all(table["hlr"][table["kind"] == "star"] == 0) and np.all(table["gaia_id"] == -1)


def test_footprint_positions_are_uniform_in_solid_angle():
    """A 20-degree footprint at Dec 60: counts in its quadrants follow their exact solid angles."""
    from perscli.scene import deproject

    big = square(200.0, 60.0, 10.0, 20.0)
    table = make_truth_catalog(footprints=[big], margin_arcsec=0.0, galaxy_density=0.0, star_density=0.02,
                               seed=5)
    u = FootprintUnion([big])
    cx, cy = gnomonic(u.ra, u.dec, *big)
    mx, my = cx.mean(), cy.mean()
    counts, expect = [], []
    for i in range(4):
        j = (i + 1) % 4
        # the triangle of the centre and side (i, j): straight on the plane, a spherical triangle
        tri = [(mx, my), (cx[i], cy[i]), (cx[j], cy[j])]
        tra, tdec = deproject(u.ra, u.dec, [p[0] for p in tri], [p[1] for p in tri])
        counts.append(inside_convex(u.ra, u.dec, (tra, tdec), table["ra"], table["dec"]).sum())
        expect.append(0.02 * polygon_area(tra, tdec) * ARCMIN2_PER_SR)
    counts, expect = np.array(counts), np.array(expect)
    assert counts.sum() == len(table)
    chi2 = np.sum((counts - expect) ** 2 / expect)
    assert stats.chi2.sf(chi2, len(counts)) > 1e-3, (counts, expect)


def test_expand_polygon_contains_every_point_within_the_margin():
    from perscli.scene import deproject

    corners = sca_footprints(1)[0]
    grown = expand_polygon(*corners, 30.0)
    ra0, dec0 = np.mean(corners[0]), np.mean(corners[1])
    cx, cy = gnomonic(ra0, dec0, *corners)
    m = math.radians(30.0 / 3600.0)
    for i in range(4):
        j = (i + 1) % 4
        mid = np.array([(cx[i] + cx[j]) / 2, (cy[i] + cy[j]) / 2])
        out = mid - np.array([np.mean(cx), np.mean(cy)])
        edge = np.array([cx[j] - cx[i], cy[j] - cy[i]])
        normal = np.array([edge[1], -edge[0]]) / np.hypot(*edge)
        normal *= np.sign(normal @ out)
        for f, want in ((0.98, True), (1.02, False)):
            pra, pdec = deproject(ra0, dec0, *(mid + f * m * normal))
            assert inside_convex(ra0, dec0, grown, [pra], [pdec])[0] == want
    assert polygon_area(*grown) > polygon_area(*corners)
    with pytest.raises(PerscliError, match="margin"):
        expand_polygon(*corners, -1.0)


def test_footprint_catalog_same_seed_same_bytes_and_galaxies_independent_of_stars(tmp_path):
    fps = sca_footprints(2)
    a, b, c = (tmp_path / f"{k}.fits" for k in "abc")
    from perscli.scene.catalog import make_truth_catalog_file

    for out, seed in ((a, 4), (b, 4), (c, 5)):
        make_truth_catalog_file(str(out), footprints=fps, margin_arcsec=10.0, seed=seed)
    assert raw_cards_masked(a) == raw_cards_masked(b) != raw_cards_masked(c)
    g1 = galaxies(make_truth_catalog(footprints=fps, margin_arcsec=10.0, seed=4, star_density=1.0))
    g2 = galaxies(make_truth_catalog(footprints=fps, margin_arcsec=10.0, seed=4, star_density=9.0))
    assert len(g1) > 100 and np.array_equal(g1["ra"], g2["ra"]) and np.array_equal(g1["e1"], g2["e1"])
    # the square field's catalogue is what it always was: no footprint keyword in it
    sq = make_truth_catalog(RA, DEC, 3.0, seed=4)
    assert "REGION" not in sq.meta and "FOOTPRINTS" not in sq.meta and sq.meta["FIELDSZ"] == 3.0


def test_library_call_with_a_field_centre_and_footprints(tmp_path):
    """As a study calls it: the field centre as the tangent point, footprints, margin, densities, seed."""
    from perscli.scene.catalog import make_truth_catalog_file

    out = tmp_path / "truth.fits"
    table = make_truth_catalog_file(str(out), RA, DEC, footprints=sca_footprints(3), margin_arcsec=20.0,
                                    galaxy_density=40.0, star_density=2.5, gaia=None, seed=3, overwrite=True)
    with fits.open(out, checksum=True) as hdul:
        assert [h.name for h in hdul] == ["PRIMARY", "TRUTH", "FOOTPRNT"]
        hdr = hdul["TRUTH"].header
        assert hdr["FIELDRA"] == RA and hdr["FIELDDEC"] == DEC and hdr["NFOOT"] == 3 and hdr["FOOTMARG"] == 20.0
        assert hdr["NGAL"] + hdr["NSTAR"] == len(hdul["TRUTH"].data) == len(table)
        assert "footprints=3 margin=20.0" in str(hdr["HISTORY"])
        corners = hdul["FOOTPRNT"].data
        assert corners["corner_ra"].shape == (3, 4)
        np.testing.assert_array_equal(corners["corner_dec"][1], sca_footprints(3)[1][1])
        assert hdul["FOOTPRNT"].header["FOOTMARG"] == 20.0
    for kwargs, needle in ((dict(footprints=[]), "at least one"),
                           (dict(footprints=[square(RA, DEC, 0.1)], size=5.0), "not both"),
                           (dict(footprints=[(np.array([1.0, 2.0, 2.0, 1.0]), np.array([0.0, 1.0, 0.0, 1.0]))]),
                            "convex"),
                           (dict(footprints=[square(RA, DEC, 0.1), square(RA + 150, 0.0, 0.1)]), "60 degrees"),
                           (dict(footprints=[square(RA, DEC, 0.1)], margin_arcsec=-2.0), "margin")):
        with pytest.raises(PerscliError, match=needle):
            make_truth_catalog(**kwargs)


def test_cli_footprints_of_a_pointings_table(tmp_path):
    from perscli.scene.pointings import read_pointings
    from perscli.scene.footprints import sca_footprint

    ptg = tmp_path / "p.fits"
    assert invoke("pointings", "plan", "--ra", RA, "--dec", DEC, "--n", 3, "--dither", 120, "--start", 61541.97,
                  "--pa", 30, "--sca", 7, "-o", ptg).exit_code == 0
    out, again = tmp_path / "cat.fits", tmp_path / "again.fits"
    for path in (out, again):
        result = invoke("catalog", "--pointings", ptg, "--margin", 15, "--seed", 2, "-o", path)
        assert result.exit_code == 0, result.stderr
    assert raw_cards_masked(out) == raw_cards_masked(again)
    pts = read_pointings(str(ptg))
    with fits.open(out) as hdul:
        hdr = hdul["TRUTH"].header
        assert hdr["PTGS"] == "p.fits" and hdr["PTGSDS"].isdigit() and hdr["FOOTMARG"] == 15.0
        for row, p in zip(hdul["FOOTPRNT"].data, pts):
            np.testing.assert_array_equal(row["corner_ra"], sca_footprint(p)[0])
        data = hdul["TRUTH"].data
    lib = make_truth_catalog(footprints=[sca_footprint(p) for p in pts], margin_arcsec=15.0, seed=2)
    assert np.array_equal(lib["ra"], data["ra"]) and np.array_equal(lib["kind"], np.char.strip(data["kind"]))
    # --sca chooses another detector of the same pointings; --bounds a cutout of it
    assert invoke("catalog", "--pointings", ptg, "--sca", 3, "--bounds", 1, 512, 1, 512, "-o",
                  tmp_path / "cut.fits").exit_code == 0
    with fits.open(tmp_path / "cut.fits") as hdul:
        np.testing.assert_array_equal(hdul["FOOTPRNT"].data["corner_ra"][0],
                                      sca_footprint(pts[0], 3, bounds=(1, 512, 1, 512))[0])


def test_cli_footprints_errors(tmp_path):
    ptg = tmp_path / "p.fits"
    assert invoke("pointings", "plan", "--ra", RA, "--dec", DEC, "--n", 2, "--start", 61541.97,
                  "-o", ptg).exit_code == 0
    # rows without an SCA and no --sca: one line
    expect_error(tmp_path, ["--pointings", ptg], "--sca", command="catalog")
    for args, needle in ((["--pointings", ptg, "--ra", RA], "--ra is for a square field"),
                         (["--pointings", ptg, "--size", 3], "--size is for a square field"),
                         (["--ra", RA, "--dec", DEC, "--margin", 5], "--margin is for --pointings"),
                         (["--ra", RA, "--dec", DEC, "--sca", 3], "--sca is for --pointings"),
                         (["--pointings", ptg, "--sca", 19], "--sca"),
                         (["--pointings", ptg, "--sca", 1, "--margin", -1], "--margin")):
        expect_usage_error(tmp_path, [*args, "-o", tmp_path / "x.fits"], needle)


def test_footprint_catalog_with_gaia_keeps_the_stars_inside(shared_data, tmp_path):
    gaia = [str(shared_data / "gaia" / f) for f in ("145649.fits", "145650.fits")]
    fps = sca_footprints(4, ra=10.5)                    # SCA 7 then lies near RA 10, inside the Gaia chunks
    table = make_truth_catalog(footprints=fps, margin_arcsec=30.0, gaia=gaia, seed=1)
    u = FootprintUnion(fps, 30.0)
    square_cat = make_truth_catalog(u.ra, u.dec, 40.0, gaia=gaia, seed=1)
    s_in = stars(square_cat)[u.contains(stars(square_cat)["ra"], stars(square_cat)["dec"])]
    got = stars(table)
    assert len(got) > 10 and set(got["gaia_id"]) == set(s_in["gaia_id"])
    assert table.meta["STARSRC"] == "gaia" and table.meta["NSTAR"] == len(got)


def test_galaxy_rows_hold_the_galaxies_and_every_row_the_stars(tmp_path):
    """--galaxy-rows: a study's earlier exposures need their stars only."""
    from click.testing import CliRunner

    from perscli.cli.main import cli
    from perscli.scene.pointings import pointings_footprints
    from perscli.scene.regions import FootprintUnion

    plan = tmp_path / "plan.fits"
    r = CliRunner().invoke(cli, ["pointings", "plan", "--ra", "10", "--dec", "-44", "--n", "3", "--dither", "400",
                                 "--sca", "7", "--seed", "3", "-o", str(plan)])
    assert r.exit_code == 0, r.output
    out = tmp_path / "cat.fits"
    r = CliRunner().invoke(cli, ["catalog", "--pointings", str(plan), "--bounds", "1", "256", "1", "256",
                                 "--galaxy-rows", "2", "--star-density", "20", "-o", str(out)])
    assert r.exit_code == 0, r.output
    from astropy.table import Table

    t = Table.read(out, hdu="TRUTH")
    corners, _ = pointings_footprints(str(plan), bounds=(1, 256, 1, 256))
    gal = t[t["kind"] == "galaxy"]
    stars = t[t["kind"] == "star"]
    assert len(gal) > 0 and np.all(FootprintUnion([corners[2]], 30.0).contains(gal["ra"], gal["dec"]))
    others = FootprintUnion(corners[:2], 30.0).contains(stars["ra"], stars["dec"]) \
        & ~FootprintUnion([corners[2]], 30.0).contains(stars["ra"], stars["dec"])
    assert others.any()                                           # stars on the rows without galaxies too
    bad = CliRunner().invoke(cli, ["catalog", "--pointings", str(plan), "--galaxy-rows", "5", "-o",
                                   str(tmp_path / "bad.fits")])
    assert bad.exit_code == 1 and "rows 0 to 2" in bad.output
    bad = CliRunner().invoke(cli, ["catalog", "--ra", "10", "--dec", "-44", "--galaxy-rows", "1", "-o",
                                   str(tmp_path / "bad2.fits")])
    assert bad.exit_code == 2 and "--galaxy-rows is for --pointings" in bad.output
