"""perscli.scene.starcounts: the Galactic star model against Gaia DR2 and 2MASS, its latitude dependence, the
drawing of its stars, parameters by name, and galaxies that do not depend on the stars."""

import math

import numpy as np
import pytest
from astropy.io import fits
from scipy import stats

from perscli import PerscliError
from perscli.scene import starcounts as sc
from perscli.scene.catalog import Field, StarModel, make_truth_catalog
from perscli.scene.photometry import gaia_roman_jh
from perscli.scene.regions import FootprintUnion

from fits_factory import expect_error, invoke, listing

RA, DEC = 10.0, -44.0
CHUNKS = ("145649.fits", "145650.fits")
#: the J129 (AB) bins compared with Gaia: where Gaia is complete and the bright stars that drive persistence
GAIA_BINS = (-np.inf, 12.0, 14.0, 16.0, 17.0)


def gaia_chunk(shared_data, name):
    """(ra, dec, J129 AB) of every star of a chunk, read without perscli's catalogue code."""
    with fits.open(shared_data / "gaia" / name) as hdul:
        d = hdul[1].data
        j, _, _, _ = gaia_roman_jh(d["phot_g_mean_flux"], d["phot_bp_mean_flux"], d["phot_rp_mean_flux"])
        return np.degrees(d["coord_ra"]) % 360.0, np.degrees(d["coord_dec"]), j


# -- (1) the default model against the Gaia DR2 chunks -----------------------------------------------

@pytest.mark.parametrize("name", CHUNKS)
def test_gaia_chunk_is_its_htm_trixel(shared_data, name):
    """Every star of a chunk lies in the trixel its name gives, so the trixel's area is the chunk's."""
    ra, dec, _ = gaia_chunk(shared_data, name)
    trixel = int(name.split(".")[0])
    assert sc.trixel_contains(trixel, ra, dec).all()
    # and not in its neighbours' (the sibling trixels of the same parent)
    for sibling in {(trixel & ~3) | k for k in range(4)} - {trixel}:
        assert not sc.trixel_contains(sibling, ra, dec).any()
    assert sc.trixel_area(trixel) == pytest.approx(0.4202859, rel=1e-6)


def test_trixel_geometry():
    """Children tile their parent; the 8 roots tile the sphere; level 7 averages 4 pi / (8 4^7) sr."""
    parent = 145649 >> 2
    assert sum(sc.trixel_area((parent << 2) | k) for k in range(4)) == pytest.approx(sc.trixel_area(parent),
                                                                                     rel=1e-12)
    assert sum(sc.trixel_area(k) for k in range(8, 16)) == pytest.approx(4 * math.pi * sc.DEG2_PER_SR, rel=1e-12)
    level7 = [sc.trixel_area(k) for k in range(8 << 14, (8 << 14) + 4 ** 5)]
    assert min(level7) > 0.5 * 4 * math.pi * sc.DEG2_PER_SR / (8 * 4 ** 7)
    with pytest.raises(PerscliError, match="not an HTM trixel"):
        sc.htm_trixel(17)


@pytest.mark.parametrize("name", CHUNKS)
def test_default_model_matches_each_gaia_chunk(shared_data, name):
    """Expected counts over the chunk's exact area within 2 sqrt(N) of its Gaia counts, N the Gaia count,
    for J129 < 12, 12-14, 14-16 and 16-17 (all complete in Gaia DR2)."""
    _, _, j = gaia_chunk(shared_data, name)
    trixel = int(name.split(".")[0])
    observed, _ = np.histogram(j, GAIA_BINS)
    ra0, dec0 = sc.trixel_centre(trixel)
    expected = sc.expected_counts(ra0, dec0, GAIA_BINS) * sc.trixel_area(trixel)
    assert np.all(np.abs(expected - observed) <= 2 * np.sqrt(observed)), (expected, observed)
    # the density hardly varies over a trixel: the centre stands for the mean over its area
    corners = sc.htm_trixel(trixel)
    c_ra = np.degrees(np.arctan2(corners[:, 1], corners[:, 0])) % 360
    c_dec = np.degrees(np.arcsin(corners[:, 2]))
    at_corners = sc.expected_counts(c_ra, c_dec, GAIA_BINS) * sc.trixel_area(trixel)
    assert np.all(np.abs(at_corners.mean(axis=0) / expected - 1) < 0.02)


def test_old_power_law_did_not_match_gaia(shared_data):
    """The reason for the change: the power law at 2.5 per arcmin^2 predicts ~3x the Gaia stars brighter than 12."""
    j = np.concatenate([gaia_chunk(shared_data, n)[2] for n in CHUNKS])
    area = sum(sc.trixel_area(int(n.split(".")[0])) for n in CHUNKS)
    gaia_12 = np.sum(j < 12) / area
    power_law_12 = 2.5 * 3600 * (10 ** (0.15 * 12) - 10 ** 1.5) / (10 ** (0.15 * 24) - 10 ** 1.5)
    assert power_law_12 / gaia_12 > 2.5
    assert abs(sc.expected_counts(RA, DEC, [-np.inf, 12])[0] - gaia_12) < 2 * math.sqrt(np.sum(j < 12)) / area


def test_luminosity_function_is_the_fit_to_the_gaia_chunks(shared_data):
    """The rows M_J < 8 of LF_TABLE are what fit_luminosity_function gives on the chunks (their provenance)."""
    fit = sc.fit_luminosity_function([str(shared_data / "gaia" / n) for n in CHUNKS])
    table = np.array(sc.LF_TABLE)
    nb = len(sc.GAIA_LF_EDGES) - 1
    assert fit["n_stars"] == 1151
    np.testing.assert_allclose(fit["phi"], table[:nb, 2], rtol=2e-4)
    bright = table[:nb, 0] < sc.DWARF_COLOUR_FROM
    np.testing.assert_allclose(fit["jh_mean"][bright], table[:nb, 3][bright], atol=6e-4)
    np.testing.assert_allclose(fit["jh_sigma"][bright], table[:nb, 4][bright], atol=6e-4)
    # most stars fitted belong to these rows (the rest to the fixed rows M_J >= 8)
    assert 0.9 * 1151 < fit["n"].sum() < 1151


# -- (2) drawn catalogues against the expected counts ------------------------------------------------

def field_mean_counts(fld, edges, model=None, n=7):
    """Expected counts per deg^2 averaged over an n x n grid of the square field (solid-angle weighted)."""
    from perscli.scene import deproject

    a = fld.half_width
    x = (np.arange(n) + 0.5) / n * 2 * a - a
    gx, gy = np.meshgrid(x, x, indexing="ij")
    w = (1 + gx ** 2 + gy ** 2) ** -1.5
    ra, dec = deproject(fld.ra, fld.dec, gx.ravel(), gy.ravel())
    c = sc.expected_counts(ra, dec, edges, model)
    return (c * w.ravel()[:, None]).sum(axis=0) / w.sum()


def test_drawn_counts_per_magnitude_are_poisson_with_the_model():
    fld = Field(RA, DEC, 60.0)
    table = make_truth_catalog(RA, DEC, 60.0, galaxy_density=0.0, seed=8)
    edges = np.array([4.0, 12, 14, 16, 18, 19, 20, 21, 22, 23, 24])
    observed, _ = np.histogram(table["mag_J129"], edges)
    expected = field_mean_counts(fld, edges) * fld.area / 3600
    assert observed.sum() == len(table) and table["mag_J129"].min() >= 4 and table["mag_J129"].max() <= 24
    chi2 = np.sum((observed - expected) ** 2 / expected)
    assert stats.chi2.sf(chi2, len(expected)) > 1e-3, (observed, expected)
    assert table.meta["NSTAR"] == len(table) and table.meta["STARMOD"] == "galactic"


def test_drawn_density_follows_latitude_across_a_wide_field():
    """A 12-degree field at b ~ 35: the half nearer the plane holds the model's share of the stars."""
    l0, b0 = 90.0, 35.0
    v = np.array([math.cos(math.radians(b0)) * math.cos(math.radians(l0)),
                  math.cos(math.radians(b0)) * math.sin(math.radians(l0)), math.sin(math.radians(b0))])
    icrs = sc.ICRS_TO_GALACTIC.T @ v
    ra0, dec0 = math.degrees(math.atan2(icrs[1], icrs[0])) % 360, math.degrees(math.asin(icrs[2]))
    model = sc.galactic_star_model(mag_max=15.0)
    fld = Field(ra0, dec0, 720.0)
    stars = sc.draw_galactic_stars(np.random.default_rng(4), fld, model)
    _, b = sc.galactic_coordinates(stars["ra"], stars["dec"])
    from perscli.scene import deproject

    a = fld.half_width
    x = (np.arange(40) + 0.5) / 40 * 2 * a - a
    gx, gy = np.meshgrid(x, x, indexing="ij")
    gra, gdec = deproject(ra0, dec0, gx.ravel(), gy.ravel())
    _, gb = sc.galactic_coordinates(gra, gdec)
    dens = sc.star_density(gra, gdec, model) * (1 + gx.ravel() ** 2 + gy.ravel() ** 2) ** -1.5
    low = gb < b0
    share = dens[low].sum() / dens.sum()
    n = len(b)
    assert n > 5000 and share > 0.55                      # the field is far from uniform
    assert abs(np.mean(b < b0) - share) < 4 * math.sqrt(share * (1 - share) / n), (np.mean(b < b0), share)
    assert stars["max_density"] == pytest.approx(max(sc.star_density(*stars["grid"], model)))


def test_footprint_union_of_six_square_degrees_is_drawn_quickly():
    import time

    from perscli.scene import deproject

    t = np.array([0.25, 0.75, 1.25, 1.75]) * np.pi
    h = math.tan(math.radians(1.25)) * math.sqrt(2)
    fps = [deproject(RA, DEC, h * np.cos(t), h * np.sin(t))]
    start = time.perf_counter()
    table = make_truth_catalog(footprints=fps, margin_arcsec=0.0, galaxy_density=0.0, seed=2)
    elapsed = time.perf_counter() - start
    u = FootprintUnion(fps)
    assert u.area / 3600 == pytest.approx(6.249, abs=0.001)
    expected = sc.star_density(RA, DEC) * u.area
    assert abs(len(table) - expected) < 0.02 * expected          # the density hardly varies at b = -73
    assert u.contains(table["ra"], table["dec"]).all()
    assert elapsed < 10.0, elapsed


def test_colours_of_model_stars():
    table = make_truth_catalog(RA, DEC, 60.0, galaxy_density=0.0, seed=3)
    jh = np.asarray(table["mag_J129"] - table["mag_H158"])
    assert np.all(np.isfinite(jh)) and np.all(np.abs(jh) < 1.2)
    faint = table["mag_J129"] > 20                       # mostly K and M dwarfs: (J-H)_Vega 0.45-0.65
    assert 0.45 < np.median(jh[faint]) + 1.39 - 0.91 < 0.65
    lf = sc.luminosity_function()
    assert np.all(np.isfinite(lf["jh_mean"])) and np.all(lf["jh_sigma"] >= 0)


def test_draws_are_reproducible_and_use_only_their_generator():
    fld = Field(RA, DEC, 20.0)
    a = sc.draw_galactic_stars(np.random.default_rng(5), fld)
    b = sc.draw_galactic_stars(np.random.default_rng(5), fld)
    assert all(np.array_equal(a[k], b[k]) for k in ("ra", "dec", "mag_j", "mag_h"))


# -- (3) latitude and longitude -------------------------------------------------------------------------

def test_counts_rise_towards_the_plane():
    edges = [-np.inf, 12, 14, 16]
    for l in (0.0, 90.0, 180.0, 270.0):
        for sign in (1, -1):
            c = np.array([sc.expected_counts(l, sign * b, edges, galactic=True) for b in (90, 70, 50, 35, 20)])
            assert np.all(np.diff(c, axis=0) > 0), (l, sign, c)
    # and towards the inner Galaxy at equal latitude
    inner, outer = (sc.expected_counts(l, 30, [-np.inf, 16], galactic=True)[0] for l in (0, 180))
    assert inner > 1.5 * outer


def test_symmetries():
    model = sc.GalacticStarModel()
    edges = [-np.inf, 12, 16, 20, 24]
    for l, b in ((30, 25), (120, 60), (200, 40)):
        np.testing.assert_allclose(sc.expected_counts(l, b, edges, model, galactic=True),
                                   sc.expected_counts(360 - l, b, edges, model, galactic=True), rtol=1e-12)
    # north and south alike only for a Sun in the plane; 25 pc above it, the south sees a little more disc
    flat = sc.galactic_star_model(sun_height=0)
    for l, b in ((30, 25), (120, 60), (0, 90)):
        np.testing.assert_allclose(sc.expected_counts(l, b, edges, flat, galactic=True),
                                   sc.expected_counts(l, -b, edges, flat, galactic=True), rtol=1e-9)
        north, south = (sc.expected_counts(l, s * b, [-np.inf, 16], model, galactic=True)[0] for s in (1, -1))
        assert 1.0 < south / north < 1.2


#: 2MASS Second Incremental Release, Explanatory Supplement sec. VI.7a (M. Egan; ipac.caltech.edu/2mass/
#: releases/second/doc/sec6_7a.html): point sources within 1 deg of reference fields 2, 3 and 4, one
#: strip of longitude (l = 218, 208, 202) at b = 60, 41, 29.  (Field 1, b = 78, is given as 2989 there and
#: 3701 in sec. VI.6; fields 8 and 9, b = -21 and -37, lie behind the Taurus-Perseus dust.)
TWOMASS_FIELDS = ((217.58, 59.91, 4406), (207.79, 40.80, 6193), (202.27, 28.80, 9403))


def test_latitude_dependence_matches_2mass_reference_fields():
    """N(J < 15.8, the 2MASS 10-sigma limit) relative to the b = 60 field, within 10% of 2MASS's ratios."""
    limit = 15.8 + sc.J_AB_MINUS_VEGA
    model = [sc.cumulative_counts(l, b, [limit], galactic=True)[0] for l, b, _ in TWOMASS_FIELDS]
    twomass = [n for _, _, n in TWOMASS_FIELDS]
    for k in (1, 2):
        ratio_model, ratio_2mass = model[k] / model[0], twomass[k] / twomass[0]
        assert abs(ratio_model / ratio_2mass - 1) < 0.10, (k, ratio_model, ratio_2mass)


def test_galactic_coordinates_agree_with_astropy():
    from astropy.coordinates import SkyCoord

    rng = np.random.default_rng(1)
    ra, dec = rng.uniform(0, 360, 200), np.degrees(np.arcsin(rng.uniform(-1, 1, 200)))
    l, b = sc.galactic_coordinates(ra, dec)
    g = SkyCoord(ra, dec, unit="deg").galactic
    assert np.max(np.abs(b - g.b.deg)) < 1e-4
    dl = (l - g.l.deg + 180) % 360 - 180
    assert np.max(np.abs(dl * np.cos(np.radians(b)))) < 1e-4
    np.testing.assert_allclose(sc.galactic_coordinates(RA, DEC), (310.0, -73.0), atol=0.05)   # docstrings


def test_documented_numbers():
    """The counts the module docstring quotes."""
    c = sc.expected_counts(RA, DEC, [-np.inf, 12, 14, 16, 17, 18])
    np.testing.assert_allclose(c, [24.7, 97.4, 351, 360, 535], rtol=0.005)
    assert sc.star_density(RA, DEC) == pytest.approx(2.50, abs=0.01)
    j14 = [sc.cumulative_counts(90, b, [14.0], galactic=True)[0] for b in (90, 60, 45, 30, 20)]
    np.testing.assert_allclose(j14, [99, 120, 154, 231, 351], rtol=0.01)
    dens = [sc.star_density(90, b, galactic=True) for b in (90, 60, 45, 30, 20)]
    np.testing.assert_allclose(dens, [2.0, 2.7, 4.0, 7.9, 16.6], rtol=0.02)
    lf = sc.luminosity_function()
    assert np.sum(lf["phi"] * (lf["hi"] - lf["lo"])) == pytest.approx(0.052, abs=0.0005)
    far = sc.galactic_star_model(max_distance=200000)
    assert sc.star_density(RA, DEC, far) / sc.star_density(RA, DEC) == pytest.approx(1.009, abs=0.002)


# -- (4) parameters by name ---------------------------------------------------------------------------

def test_parameters_by_name():
    a = sc.galactic_star_model({"thin_height": 300, "mag_min": "8"})
    b = sc.galactic_star_model(["thin_height=300", "mag_min = 8"])
    c = sc.galactic_star_model(thin_height=300.0, mag_min=8)
    d = sc.GalacticStarModel.from_mapping({"thin_height": 300, "mag_min": 8})
    assert a == b == c == d and a.thin_height == 300.0 and a.mag_min == 8.0 and a.thick_height == 1020.0
    assert sc.galactic_star_model() == sc.GalacticStarModel()
    # the parameter is used: a thinner disc gives fewer stars at the pole
    assert sc.star_density(0, 90, a, galactic=True) < sc.star_density(0, 90, galactic=True)
    assert sc.star_density(RA, DEC, sc.galactic_star_model(lf_scale=2)) == pytest.approx(
        2 * sc.star_density(RA, DEC))
    # and recorded in the catalogue
    table = make_truth_catalog(RA, DEC, 5.0, seed=1, star_model=a)
    assert table.meta["SGH1"] == 300.0 and table.meta["SMAGMIN"] == 8.0 and table["mag_J129"][
        table["kind"] == "star"].min() >= 8.0
    assert set(sc.META_KEYWORDS) == set(sc.GalacticStarModel.parameter_names())


@pytest.mark.parametrize("overrides, needles", [
    ({"thin_hight": 3}, ["unknown star-model parameter 'thin_hight'", "valid are sun_radius", "dwarf_jh_sigma"]),
    (["thin_height"], ["is not KEY=VALUE"]),
    ({"thin_height": "abc"}, ["thin_height='abc'", "finite number"]),
    ({"thin_height": -1}, ["thin_height=-1", "> 0"]),
    ({"halo_fraction": -0.1}, ["halo_fraction", ">= 0"]),
    ({"mag_min": 25}, ["mag_min must be less than mag_max"]),
    ({"max_distance": 5}, ["max_distance"]),
    ({"lf_scale": True}, ["lf_scale", "finite number"]),
])
def test_bad_parameters_are_one_line_errors(overrides, needles):
    with pytest.raises(PerscliError) as err:
        sc.galactic_star_model(overrides)
    message = str(err.value)
    assert "\n" not in message
    for needle in needles:
        assert needle in message


def test_star_density_and_galactic_model_together_is_an_error():
    with pytest.raises(PerscliError, match="not both"):
        make_truth_catalog(RA, DEC, 5.0, star_density=2.0, star_model=sc.GalacticStarModel())
    # a power-law model without a density: the paper's 2.5
    table = make_truth_catalog(RA, DEC, 5.0, seed=1, star_model=StarModel())
    assert table.meta["STARMOD"] == "powerlaw" and table.meta["STARDENS"] == 2.5


def test_cli_star_parameters(tmp_path):
    out = tmp_path / "cat.fits"
    result = invoke("catalog", "--ra", RA, "--dec", DEC, "--size", 3, "--star-param", "thin_height=300",
                    "--star-param", "mag_max=20", "-o", out)
    assert result.exit_code == 0, result.output
    with fits.open(out) as hdul:
        hdr, data = hdul["TRUTH"].header, hdul["TRUTH"].data
        assert hdr["STARMOD"] == "galactic" and hdr["SGH1"] == 300.0 and hdr["SMAGMAX"] == 20.0
        assert data["mag_J129"][np.char.strip(data["kind"]) == "star"].max() <= 20.0
    expect_error(tmp_path, ["catalog", "--ra", RA, "--dec", DEC, "--star-param", "thin_hight=3"],
                 "unknown star-model parameter 'thin_hight'", "valid are")
    expect_error(tmp_path, ["catalog", "--ra", RA, "--dec", DEC, "--star-param", "mag_min=abc"], "mag_min='abc'")
    for args, needle in ((["--star-param", "thin_height=300", "--star-density", "2"], "--star-density"),
                         (["--star-param", "thin_height=300", "--gaia", out], "--gaia")):
        files = listing(tmp_path)
        result = invoke("catalog", "--ra", RA, "--dec", DEC, *args, "-o", tmp_path / "x.fits")
        assert result.exit_code == 2 and len(result.stderr.splitlines()) == 1 and needle in result.stderr
        assert listing(tmp_path) == files


# -- (5) galaxies do not depend on the stars -----------------------------------------------------------

def test_galaxies_are_the_same_whatever_the_star_model():
    def galaxies(table):
        return table[table["kind"] == "galaxy"]

    variants = [dict(), dict(star_density=2.5), dict(star_density=20.0),
                dict(star_model=sc.galactic_star_model(thin_height=250, mag_min=12))]
    tables = [make_truth_catalog(RA, DEC, 8.0, seed=13, **kw) for kw in variants]
    ref = galaxies(tables[0])
    assert len(ref) > 2000
    for t in tables[1:]:
        g = galaxies(t)
        for col in ref.colnames:
            assert np.array_equal(np.asarray(g[col]), np.asarray(ref[col])), col
        assert t.meta["NGAL"] == tables[0].meta["NGAL"]
    # the stars differ, and each set is reproducible
    assert len({t.meta["NSTAR"] for t in tables}) > 1
    again = make_truth_catalog(RA, DEC, 8.0, seed=13)
    assert np.array_equal(np.asarray(again["mag_J129"]), np.asarray(tables[0]["mag_J129"]))
