"""perscli measure when things go wrong, and the inputs that steer it.

Failure handling (blended, edge, faint, empty, masked and off-frame
positions: flags, no crash, the other objects untouched; run with
``--all-rows --min-snr 0`` so that every catalogue object gets its row, as
measure wrote them before issue 10), the rows written by default (objects
on the frame above the predicted-S/N cut), weights from
WHT/VAR/ERR HDUs, masked and non-finite pixels, x/y against ra/dec
catalogues, several frames and the COMBINED table, --workers, and the errors
that stop the command (one line on stderr, exit 1, no output).

The frames are drawn here with GalSim (exponential galaxies through the same
Roman PSF that ``--psf roman`` uses) with the header keywords measure reads:
BUNIT, GAIN, EXPTIME, SKYRATE, SCA, FILTER, ZPT_AB and a TAN WCS.
Catalogues carry mag_J129 so that the fit starts from the true flux.
"""

import numpy as np
import pytest
from astropy.io import fits
from astropy.table import Table
from astropy.wcs import WCS

from fits_factory import one_line_error, run

galsim = pytest.importorskip("galsim")
import galsim.roman as roman  # noqa: E402

from perscli.measure.fit import ExpModel, fit_exp  # noqa: E402

N = 128                # frame side
STAMP = 32             # --stamp for every run (fast)
EXPTIME = 139.8
SKYRATE = 1.0
DARK = 0.015           # measure's default dark current, e-/pixel/s
RN = 8.5               # measure's default read noise, e-
ZPT = 26.0
BKG = (SKYRATE + DARK) * EXPTIME          # the background the noise model subtracts (same operations)
VAR = BKG + RN ** 2                        # and its variance per pixel (same operations as noise_model)
FLAG_EDGE, FLAG_FEW, FLAG_OFF, FLAG_CUT = 2, 16, 256, 4096
#: every catalogue object in the output, fitted whatever its predicted S/N (the failure tests' setting)
EVERY_ROW = ("--all-rows", "--min-snr", "0")
FIT_COLUMNS = ("x", "y", "g1", "g2", "T", "flux", "x_err", "y_err", "g1_err", "g2_err", "T_err", "flux_err",
               "s2n", "chi2")


# -- frames and catalogues --------------------------------------------------------------------------


@pytest.fixture(scope="module")
def psf():
    bandpass = roman.getBandpasses(AB_zeropoint=True)["J129"]
    return roman.getPSF(7, "J129", wavelength=bandpass.effective_wavelength)


def frame_wcs():
    """A TAN WCS of 0.11"/pixel, rotated by 0.5 rad, centred on the frame."""
    w = WCS(naxis=2)
    w.wcs.ctype = ["RA---TAN", "DEC--TAN"]
    w.wcs.crval = [10.0, -44.0]
    w.wcs.crpix = [N / 2 + 0.5, N / 2 + 0.5]
    s, c = np.sin(0.5), np.cos(0.5)
    w.wcs.cd = 0.11 / 3600 * np.array([[-c, s], [s, c]])
    return w


def mag(flux):
    """The catalogue magnitude that start_point turns back into ``flux`` electrons."""
    return ZPT - 2.5 * np.log10(flux / (roman.collecting_area * EXPTIME))


def draw(psf, gals, *, seed=1, noise=True):
    """Electrons: galaxies (x, y FITS pixels, g1, g2, flux; hlr 0.3") + background (+ Gaussian noise)."""
    img = galsim.ImageD(N, N, scale=roman.pixel_scale)  # bounds 1..N: GalSim's pixel centres are FITS pixels
    for x, y, g1, g2, flux in gals:
        gal = galsim.Exponential(half_light_radius=0.3, flux=flux).shear(g1=g1, g2=g2)
        galsim.Convolve(gal, psf).drawImage(image=img, add_to_image=True, center=galsim.PositionD(x, y))
    data = img.array + BKG
    if noise:
        data = data + np.random.default_rng(seed).normal(0.0, np.sqrt(VAR), data.shape)
    return data


def write_frame(path, data, *, wcs=True, hdus=None, drop=(), **keywords):
    """A SCI extension with the keywords measure reads; ``hdus`` = {EXTNAME: array} extra image HDUs."""
    hdr = frame_wcs().to_header() if wcs else fits.Header()
    values = dict(BUNIT="electron", GAIN=1.0, EXPTIME=EXPTIME, SKYRATE=SKYRATE, SCA=7, FILTER="J129", ZPT_AB=ZPT)
    values.update(keywords)
    for key, value in values.items():
        if key not in drop:
            hdr[key] = value
    hdul = [fits.PrimaryHDU(), fits.ImageHDU(np.asarray(data, dtype=np.float64), hdr, name="SCI")]
    for name, array in (hdus or {}).items():
        hdul.append(fits.ImageHDU(np.asarray(array, dtype=np.float64), name=name))
    fits.HDUList(hdul).writeto(path, overwrite=True)
    return path


def write_catalog(path, ids, x, y, flux=None, *, radec=False):
    cols = dict(id=np.asarray(ids, dtype=np.int64))
    if radec:
        ra, dec = frame_wcs().all_pix2world(np.asarray(x, float), np.asarray(y, float), 1)
        cols.update(ra=ra, dec=dec)
    else:
        cols.update(x=np.asarray(x, float), y=np.asarray(y, float))
    if flux is not None:
        cols["mag_J129"] = mag(np.asarray(flux, float))
    Table(cols).write(path, overwrite=True)
    return path


def measure(frames, catalog, out, *extra, code=0):
    frames = frames if isinstance(frames, (list, tuple)) else [frames]
    return run("measure", *frames, "--catalog", catalog, "--stamp", STAMP, *extra, "-o", out, code=code)


def shapes(path, name="SHAPES"):
    """The table as written (NaN kept as NaN, not masked)."""
    return Table(np.asarray(fits.getdata(path, name)))


def assert_rows_equal(a, b, columns=FIT_COLUMNS + ("nfev", "flags")):
    for key in columns:
        np.testing.assert_array_equal(np.asarray(a[key]), np.asarray(b[key]), err_msg=key)


def by_id(table, ident):
    return table[np.asarray(table["id"]) == ident][0]


# -- the failure scene --------------------------------------------------------------------------------

# id: (x, y, g1, g2, flux drawn, catalogue flux)
OBJECTS = {
    1: (25.3, 30.6, 0.2, 0.1, 2e4, 2e4),        # isolated and bright: the control
    2: (95.0, 30.0, -0.1, 0.2, 2e4, 2e4),       # blended pair, 3.4 px apart
    3: (98.0, 31.5, 0.1, 0.0, 1.5e4, 1.5e4),
    4: (2.5, 75.0, 0.0, 0.2, 2e4, 2e4),         # at the edge: the stamp runs off the frame
    5: (20.0, 110.0, 0.1, 0.1, 20.0, 20.0),     # faint (S/N ~ 1)
    6: (110.0, 110.0, 0.0, 0.0, 0.0, 200.0),    # empty position
    7: (-50.0, 60.0, 0.0, 0.0, 0.0, 2e4),       # off the frame
    8: (64.0, 72.0, 0.1, 0.1, 2e4, 2e4),        # inside a block of NaN pixels
    9: (0.4, 40.0, 0.0, 0.0, 0.0, 2e4),         # FITS pixel 1 spans 0.5..1.5: off the frame
    10: (0.6, 50.0, 0.0, 0.0, 0.0, 2e4),        # ... and this one is on it (at the edge)
}
NAN_BLOCK = (slice(52, 92), slice(44, 84))      # rows, columns (0-indexed): covers object 8's whole stamp


@pytest.fixture(scope="module")
def failure_scene(psf, tmp_path_factory):
    tmp = tmp_path_factory.mktemp("failures")
    data = draw(psf, [v[:5] for v in OBJECTS.values() if v[4] > 0], seed=2)
    data[NAN_BLOCK] = np.nan
    frame = write_frame(tmp / "frame.fits", data)
    ids = list(OBJECTS)
    cat = write_catalog(tmp / "cat.fits", ids, *zip(*[(OBJECTS[i][0], OBJECTS[i][1], OBJECTS[i][5]) for i in ids]))
    out = tmp / "shapes.fits"
    measure(frame, cat, out, *EVERY_ROW)
    return tmp, frame, cat, shapes(out)


def test_failure_positions_are_flagged_and_never_stop_the_others(failure_scene):
    tmp, frame, cat, s = failure_scene
    # one row per catalogue object, in catalogue order
    assert list(s["id"]) == list(OBJECTS) and np.all(np.asarray(s["frame"]) == 0)
    flags = dict(zip(np.asarray(s["id"]), np.asarray(s["flags"])))
    # the isolated galaxy is measured well despite its troubled neighbours
    one = by_id(s, 1)
    assert one["flags"] == 0
    assert abs(one["g1"] - 0.2) < 0.03 and abs(one["g2"] - 0.1) < 0.03
    assert abs(one["x"] - 25.3) < 0.2 and abs(one["y"] - 30.6) < 0.2
    # the edge object: flagged, still fitted
    assert flags[4] & FLAG_EDGE and np.isfinite(by_id(s, 4)["g1"])
    assert flags[10] & FLAG_EDGE and not flags[10] & FLAG_OFF
    # off the frame: flagged 256 alone, no values
    for ident in (7, 9):
        assert flags[ident] == FLAG_OFF
        assert all(np.isnan(by_id(s, ident)[key]) for key in ("x", "g1", "g2", "flux", "g1_err"))
    # the masked (NaN) object: too few pixels
    assert flags[8] & FLAG_FEW
    # every row: either flagged, or finite values and errors
    for row in s:
        if row["flags"] == 0:
            assert all(np.isfinite(row[key]) for key in FIT_COLUMNS), row
    # the faint and empty positions come back as rows (with whatever flags), not as an exception
    assert {5, 6} <= set(flags)


def test_each_object_is_independent_of_the_others(failure_scene):
    """The same rows in reverse catalogue order, and the control alone: bit for bit."""
    tmp, frame, cat, s = failure_scene
    ids = list(OBJECTS)[::-1]
    rev = write_catalog(tmp / "reversed.fits", ids, *zip(*[(OBJECTS[i][0], OBJECTS[i][1], OBJECTS[i][5])
                                                          for i in ids]))
    measure(frame, rev, tmp / "reversed_out.fits", *EVERY_ROW)
    r = shapes(tmp / "reversed_out.fits")
    assert list(r["id"]) == ids
    for ident in OBJECTS:
        assert_rows_equal(by_id(r, ident), by_id(s, ident))
    alone = write_catalog(tmp / "alone.fits", [1], [25.3], [30.6], [2e4])
    measure(frame, alone, tmp / "alone_out.fits", *EVERY_ROW)
    a = shapes(tmp / "alone_out.fits")
    assert len(a) == 1
    assert_rows_equal(a[0], by_id(s, 1))


def test_failure_positions_with_hsm_never_crash(failure_scene):
    tmp, frame, cat, _ = failure_scene
    out = tmp / "hsm.fits"
    measure(frame, cat, out, "--method", "hsm", *EVERY_ROW)
    s = shapes(out)
    flags = dict(zip(np.asarray(s["id"]), np.asarray(s["flags"])))
    assert list(s["id"]) == list(OBJECTS)
    assert flags[1] == 0 and abs(by_id(s, 1)["g1"] - 0.2) < 0.05
    assert flags[7] == FLAG_OFF and flags[9] == FLAG_OFF
    assert flags[8] != 0 and flags[4] & FLAG_EDGE


def test_hsm_positions_are_the_objects_centres(failure_scene):
    tmp, frame, cat, _ = failure_scene
    out = tmp / "hsm_xy.fits"
    measure(frame, cat, out, "--method", "hsm")
    one = by_id(shapes(out), 1)
    assert one["flags"] == 0
    assert abs(one["x"] - 25.3) < 0.5 and abs(one["y"] - 30.6) < 0.5


def test_blended_pair_is_flagged(failure_scene):
    _, _, _, s = failure_scene
    for ident in (2, 3):
        row = by_id(s, ident)
        moved = np.hypot(row["x"] - OBJECTS[ident][0], row["y"] - OBJECTS[ident][1])
        assert row["flags"] != 0 or moved < 1.0, (ident, row["x"], row["y"], row["flags"])


def test_faint_and_empty_positions_are_flagged(psf, failure_scene, tmp_path):
    positions = [(20.0, 20.0), (60.0, 20.0), (100.0, 20.0), (60.0, 60.0), (100.0, 60.0), (20.0, 100.0)]
    frame = write_frame(tmp_path / "empty.fits", draw(psf, [], seed=2))
    cat = write_catalog(tmp_path / "cat.fits", range(1, 7), *zip(*positions), [200.0] * 6)
    # by default they are not fitted: 200 e- of a 0.3" galaxy on this sky is a predicted S/N of ~1.5
    measure(frame, cat, tmp_path / "default.fits")
    assert len(shapes(tmp_path / "default.fits")) == 0
    assert fits.getheader(tmp_path / "default.fits")["NCUT01"] == 6
    measure(frame, cat, tmp_path / "listed.fits", "--all-rows")
    listed = shapes(tmp_path / "listed.fits")
    assert list(listed["flags"]) == [FLAG_CUT] * 6 and np.all(np.isnan(listed["g1"]))
    assert np.all((listed["snr_pred"] > 0.5) & (listed["snr_pred"] < 3))
    # fitted anyway (--min-snr 0), they come back flagged
    measure(frame, cat, tmp_path / "out.fits", *EVERY_ROW)
    s = shapes(tmp_path / "out.fits")
    assert len(s) == 6
    rows = [(row, x, y) for row, (x, y) in zip(s, positions)]
    rows += [(by_id(failure_scene[3], ident), *OBJECTS[ident][:2]) for ident in (5, 6)]
    for row, x, y in rows:
        moved = np.hypot(row["x"] - x, row["y"] - y)
        assert row["flags"] != 0, (row["id"], moved, row["s2n"])


def test_a_magnitude_that_is_not_a_number_is_refused_as_render_refuses_it(psf, tmp_path):
    """A NaN magnitude was fitted from the default start, in silence; render refuses the same catalogue."""
    from fits_factory import expect_error

    frame = write_frame(tmp_path / "f.fits", draw(psf, [(25.3, 30.6, 0.2, 0.1, 2e4)], seed=2))
    Table(dict(id=[1, 2], x=[25.3, 25.3], y=[30.6, 30.6], mag_J129=[np.nan, mag(2e4)])).write(tmp_path / "c.fits")
    expect_error(tmp_path, [frame, "--catalog", tmp_path / "c.fits", "--blend-radius", "0"], "mag_J129",
                 "not a magnitude", "id 1", command="measure")


def test_bright_galaxy_converges_without_a_catalogue_flux(psf, tmp_path):
    frame = write_frame(tmp_path / "f.fits", draw(psf, [(25.3, 30.6, 0.2, 0.1, 2e4)], seed=1))
    cat = write_catalog(tmp_path / "c.fits", [1], [25.3], [30.6])  # no magnitude: start flux 1000
    measure(frame, cat, tmp_path / "o.fits")
    row = shapes(tmp_path / "o.fits")[0]
    assert row["flags"] == 0 and abs(row["g1"] - 0.2) < 0.05 and abs(row["g2"] - 0.1) < 0.05


# -- weights, masks and non-finite pixels --------------------------------------------------------------


@pytest.fixture(scope="module")
def galaxy_frame(psf):
    """Two well separated bright galaxies with noise, in electrons with the background."""
    gals = [(40.3, 50.6, 0.2, 0.1, 2e4), (90.0, 80.0, -0.15, 0.05, 1.5e4)]
    return draw(psf, gals, seed=2), gals


def two_galaxy_catalog(path, gals, *, radec=False, flux=True):
    return write_catalog(path, [1, 2], [g[0] for g in gals], [g[1] for g in gals],
                         [g[4] for g in gals] if flux else None, radec=radec)


def test_nan_pixel_is_ignored_like_a_zero_weight(galaxy_frame, tmp_path):
    data, gals = galaxy_frame
    cat = two_galaxy_catalog(tmp_path / "cat.fits", gals)
    clean = write_frame(tmp_path / "clean.fits", data)
    bad = (51, 41)  # rows, columns: one pixel from galaxy 1's centre (index 49.6, 39.3)
    with_nan = data.copy()
    with_nan[bad] = np.nan
    nan_frame = write_frame(tmp_path / "nan.fits", with_nan)
    # the same pixel masked by a WHT of zero instead (its value garbage), the other weights as the noise model's
    wht = np.full(data.shape, 1.0 / VAR)
    wht[bad] = 0.0
    garbage = data.copy()
    garbage[bad] = 1e7
    masked_frame = write_frame(tmp_path / "masked.fits", garbage, hdus={"WHT": wht})
    measure([clean, nan_frame, masked_frame], cat, tmp_path / "o.fits")
    s = shapes(tmp_path / "o.fits")
    c, n, m = (s[np.asarray(s["frame"]) == k] for k in range(3))
    assert np.all(c["flags"] == 0) and np.all(n["flags"] == 0)
    assert all(np.all(np.isfinite(n[key])) for key in FIT_COLUMNS)
    # the NaN pixel changes galaxy 1 a little (one pixel fewer), galaxy 2 not at all
    assert 0 < abs(n["g1"][0] - c["g1"][0]) < 0.01
    assert_rows_equal(n[1:], c[1:])
    # and the fit equals the fit with that pixel's weight set to 0
    assert_rows_equal(n, m)


def test_fit_exp_ignores_nan_pixels_exactly(psf):
    n = 32
    model = ExpModel(galsim.PixelScale(roman.pixel_scale).toImage(psf), n)
    gal = galsim.Exponential(half_light_radius=0.3, flux=1e4).shear(g1=0.1, g2=-0.2)
    img = galsim.Convolve(gal, psf).drawImage(nx=n, ny=n, scale=roman.pixel_scale).array.astype(float)
    img += np.random.default_rng(3).normal(0, 5.0, img.shape)
    weight = np.full(img.shape, 0.04)
    start = ((n - 1) / 2, (n - 1) / 2, 0.0, 0.0, 15.0, 1e4)
    nan_img = img.copy()
    nan_img[17, 15] = np.nan
    zero_w = weight.copy()
    zero_w[17, 15] = 0.0
    a = fit_exp(nan_img, weight, model, start)
    b = fit_exp(img, zero_w, model, start)
    assert a.flags == 0 and np.all(np.isfinite(a.theta)) and np.all(np.isfinite(a.errors))
    np.testing.assert_array_equal(a.theta, b.theta)
    np.testing.assert_array_equal(a.errors, b.errors)
    assert a.chi2 == b.chi2 and a.dof == b.dof == n * n - 1 - 6


def test_weight_hdus_wht_var_err(galaxy_frame, tmp_path):
    """WHT is inverse variance, VAR variance, ERR sigma: the same weights give the same fit."""
    data, gals = galaxy_frame
    cat = two_galaxy_catalog(tmp_path / "cat.fits", gals)
    yy, xx = np.mgrid[0:N, 0:N]
    var = VAR * (1.0 + 0.8 * np.sin(xx / 5.0) ** 2 + 0.5 * (yy > 50))  # variance varying across the galaxies
    frames = [write_frame(tmp_path / "model.fits", data),
              write_frame(tmp_path / "wht.fits", data, hdus={"WHT": 1.0 / var}),
              write_frame(tmp_path / "var.fits", data, hdus={"VAR": var}),
              write_frame(tmp_path / "err.fits", data, hdus={"ERR": np.sqrt(var)}),
              write_frame(tmp_path / "wht4.fits", data, hdus={"WHT": 4.0 / var}),
              write_frame(tmp_path / "flat.fits", data, hdus={"WHT": np.full(data.shape, 1.0 / VAR)})]
    measure(frames, cat, tmp_path / "o.fits")
    s = shapes(tmp_path / "o.fits")
    model, wht, var_, err, wht4, flat = (s[np.asarray(s["frame"]) == k] for k in range(6))
    assert np.all(s["flags"] == 0)
    for other in (var_, err):
        for key in ("x", "y", "g1", "g2", "T", "flux", "g1_err", "g2_err", "chi2"):
            np.testing.assert_allclose(other[key], wht[key], rtol=1e-8, atol=1e-10, err_msg=key)
    # the map is used pixel by pixel: it moves g and the errors away from the uniform noise model's
    assert np.all(np.abs(wht["g1"] - model["g1"]) > 1e-5)
    assert np.all(wht["g1_err"] > model["g1_err"])
    # weights 4x larger: same fit, errors halved, chi2 x4
    np.testing.assert_allclose(wht4["g1"], wht["g1"], rtol=0, atol=1e-8)
    np.testing.assert_allclose(wht4["g1_err"], wht["g1_err"] / 2, rtol=1e-6)
    np.testing.assert_allclose(wht4["chi2"], 4 * wht["chi2"], rtol=1e-8)
    # a uniform WHT equal to the noise model's inverse variance: the noise model's fit exactly
    assert_rows_equal(flat, model)
    hdr = fits.getheader(tmp_path / "o.fits")
    assert hdr["BKG02"] == pytest.approx(BKG) and "SKYRATE" in hdr.comments["BKG02"]


def test_weight_hdu_without_skyrate_is_taken_as_sky_subtracted(galaxy_frame, tmp_path):
    data, gals = galaxy_frame
    cat = two_galaxy_catalog(tmp_path / "cat.fits", gals)
    wht = np.full(data.shape, 1.0 / VAR)
    with_sky = write_frame(tmp_path / "sky.fits", data, hdus={"WHT": wht})
    subtracted = write_frame(tmp_path / "sub.fits", data - BKG, hdus={"WHT": wht}, drop=("SKYRATE",))
    measure([with_sky, subtracted], cat, tmp_path / "o.fits")
    s = shapes(tmp_path / "o.fits")
    a, b = s[np.asarray(s["frame"]) == 0], s[np.asarray(s["frame"]) == 1]
    assert np.all(a["flags"] == 0)
    assert_rows_equal(a, b)
    hdr = fits.getheader(tmp_path / "o.fits")
    assert hdr["BKG02"] == 0.0 and "WHT" in hdr.comments["BKG02"]


def test_dn_frame_gives_the_electron_frame_shapes(galaxy_frame, tmp_path):
    """BUNIT DN with GAIN: background, weights and start flux in DN; same g, flux / gain."""
    data, gals = galaxy_frame
    cat = two_galaxy_catalog(tmp_path / "cat.fits", gals)
    electrons = write_frame(tmp_path / "e.fits", data)
    dn = write_frame(tmp_path / "dn.fits", data / 2.0, BUNIT="DN", GAIN=2.0)
    measure([electrons, dn], cat, tmp_path / "o.fits")
    s = shapes(tmp_path / "o.fits")
    a, b = s[np.asarray(s["frame"]) == 0], s[np.asarray(s["frame"]) == 1]
    assert np.all(a["flags"] == 0) and np.all(b["flags"] == 0)
    for key in ("x", "y", "g1", "g2", "T", "g1_err", "g2_err", "s2n", "chi2"):
        np.testing.assert_allclose(b[key], a[key], rtol=1e-7, atol=1e-9, err_msg=key)
    np.testing.assert_allclose(b["flux"], a["flux"] / 2.0, rtol=1e-7)


# -- catalogues: x/y and ra/dec ----------------------------------------------------------------------


def test_xy_and_radec_catalogues_agree_in_fits_pixels(psf, tmp_path):
    # noiseless, at sub-pixel positions: an off-by-one or half-pixel slip in either path would show
    gals = [(40.3, 50.7, 0.2, 0.1, 2e4), (90.0, 80.45, -0.15, 0.05, 1.5e4), (64.6, 20.2, 0.0, 0.3, 1e4)]
    frame = write_frame(tmp_path / "f.fits", draw(psf, gals, noise=False))
    xy = write_catalog(tmp_path / "xy.fits", [1, 2, 3], *zip(*[(g[0], g[1], g[4]) for g in gals]))
    rd = write_catalog(tmp_path / "rd.fits", [1, 2, 3], *zip(*[(g[0], g[1], g[4]) for g in gals]), radec=True)
    measure(frame, xy, tmp_path / "oxy.fits")
    measure(frame, rd, tmp_path / "ord.fits")
    a, b = shapes(tmp_path / "oxy.fits"), shapes(tmp_path / "ord.fits")
    assert np.all(a["flags"] == 0) and np.all(b["flags"] == 0)
    for key in FIT_COLUMNS:
        np.testing.assert_allclose(a[key], b[key], rtol=1e-8, atol=1e-8, err_msg=key)
    # the x/y run writes ra/dec through the WCS: the ra/dec catalogue's values
    cat = Table.read(rd)
    np.testing.assert_allclose(a["ra"], cat["ra"], rtol=0, atol=1e-10)
    np.testing.assert_allclose(a["dec"], cat["dec"], rtol=0, atol=1e-10)
    np.testing.assert_allclose(b["ra"], cat["ra"], rtol=0, atol=0)
    # positions come back in FITS pixels where GalSim drew them
    np.testing.assert_allclose(a["x"], [g[0] for g in gals], atol=0.02)
    np.testing.assert_allclose(a["y"], [g[1] for g in gals], atol=0.02)
    np.testing.assert_allclose(a["g1"], [g[2] for g in gals], atol=0.01)
    np.testing.assert_allclose(a["g2"], [g[3] for g in gals], atol=0.01)


def test_xy_catalogue_on_a_frame_without_wcs(galaxy_frame, tmp_path):
    data, gals = galaxy_frame
    xy = two_galaxy_catalog(tmp_path / "xy.fits", gals)
    rd = two_galaxy_catalog(tmp_path / "rd.fits", gals, radec=True)
    with_wcs = write_frame(tmp_path / "wcs.fits", data)
    without = write_frame(tmp_path / "nowcs.fits", data, wcs=False)
    measure([with_wcs, without], xy, tmp_path / "o.fits")
    s = shapes(tmp_path / "o.fits")
    a, b = s[np.asarray(s["frame"]) == 0], s[np.asarray(s["frame"]) == 1]
    assert np.all(b["flags"] == 0) and np.all(np.isnan(b["ra"])) and np.all(np.isfinite(a["ra"]))
    # 0.11"/pixel assumed without a WCS: the WCS's scale, so the same start and the same fit
    for key in FIT_COLUMNS:
        np.testing.assert_allclose(b[key], a[key], rtol=1e-7, atol=1e-9, err_msg=key)
    # an ra/dec catalogue needs the WCS
    r = measure(without, rd, tmp_path / "o2.fits", code=1)
    assert "no WCS" in r.stderr and "x/y" in r.stderr and not (tmp_path / "o2.fits").exists()


# -- several frames, COMBINED, workers ----------------------------------------------------------------


@pytest.fixture(scope="module")
def three_frames(psf, tmp_path_factory):
    """Three noise realisations; object 3 masked on frame 1 only; object 4 off every frame."""
    tmp = tmp_path_factory.mktemp("multi")
    gals = [(30.0, 30.3, 0.2, 0.1, 1e4), (90.6, 40.0, -0.1, 0.2, 8e3), (60.0, 95.0, 0.05, -0.2, 1.2e4)]
    frames = []
    for k, seed in enumerate((11, 12, 13)):
        data = draw(psf, gals, seed=seed)
        if k == 1:
            data[70:120, 35:85] = np.nan
        frames.append(write_frame(tmp / f"f{k}.fits", data))
    cat = write_catalog(tmp / "cat.fits", [1, 2, 3, 4], [30.0, 90.6, 60.0, 500.0], [30.3, 40.0, 95.0, 500.0],
                        [1e4, 8e3, 1.2e4, 1e4])
    return tmp, frames, cat


def test_several_frames_rows_only_for_objects_on_each_frame(three_frames):
    """By default the object off every frame has no row, in SHAPES or COMBINED."""
    tmp, frames, cat = three_frames
    out = tmp / "default.fits"
    measure(frames, cat, out)
    s, comb = shapes(out), shapes(out, "COMBINED")
    assert list(s["id"]) == [1, 2, 3] * 3 and list(s["frame"]) == [0] * 3 + [1] * 3 + [2] * 3
    assert list(comb["id"]) == [1, 2, 3]
    hdr = fits.getheader(out)
    assert [hdr[f"NON{k:02d}"] for k in (1, 2, 3)] == [3, 3, 3] and hdr["NSEL"] == 4
    # the same fits as with --all-rows
    measure(frames, cat, tmp / "every.fits", "--all-rows")
    every = shapes(tmp / "every.fits")
    assert_rows_equal(s, every[np.asarray(every["id"]) != 4])


def test_several_frames_one_row_per_object_per_frame_and_combined(three_frames):
    tmp, frames, cat = three_frames
    out = tmp / "all.fits"
    measure(frames, cat, out, "--all-rows")
    s, comb = shapes(out), shapes(out, "COMBINED")
    assert len(s) == 12
    assert list(s["frame"]) == [0] * 4 + [1] * 4 + [2] * 4
    assert list(s["id"]) == [1, 2, 3, 4] * 3
    flags = np.asarray(s["flags"]).reshape(3, 4)
    assert np.all(flags[:, :2] == 0) and flags[0, 2] == 0 and flags[2, 2] == 0
    assert flags[1, 2] & FLAG_FEW and np.all(flags[:, 3] == FLAG_OFF)
    # every frame's rows are that frame measured alone
    measure(frames[2], cat, tmp / "only2.fits", "--all-rows")
    assert_rows_equal(s[8:], shapes(tmp / "only2.fits"))
    assert fits.getheader(out)["NFRAMES"] == 3
    # COMBINED: inverse-variance weighted mean of g over the unflagged frames, computed here from SHAPES
    assert list(comb["id"]) == [1, 2, 3, 4] and list(comb["nframes"]) == [3, 3, 2, 0]
    for i, ident in enumerate([1, 2, 3]):
        rows = s[(np.asarray(s["id"]) == ident) & (np.asarray(s["flags"]) == 0)]
        for key in ("g1", "g2"):
            w = 1.0 / np.asarray(rows[f"{key}_err"]) ** 2
            mean = np.sum(w * np.asarray(rows[key])) / np.sum(w)
            assert comb[key][i] == pytest.approx(mean, rel=1e-12, abs=1e-15)
            assert comb[f"{key}_err"][i] == pytest.approx(1.0 / np.sqrt(np.sum(w)), rel=1e-12)
            # a weighted mean, not the plain one (the errors differ between frames)
            assert comb[f"{key}_err"][i] < np.min(rows[f"{key}_err"])
    # object 3's mean leaves out the frame where it is masked; object 4 (never measured) has none
    assert list(s[(np.asarray(s["id"]) == 3) & (np.asarray(s["flags"]) == 0)]["frame"]) == [0, 2]
    assert np.isnan(comb["g1"][3]) and np.isnan(comb["g1_err"][3])


def test_workers_give_identical_bytes(three_frames):
    tmp, frames, cat = three_frames
    one, two = tmp / "w1.fits", tmp / "w2.fits"
    measure(frames[:2], cat, one, "--workers", "1")
    measure(frames[:2], cat, two, "--workers", "2")

    def cards(path):
        raw = path.read_bytes()
        assert len(raw) % 2880 == 0
        blocks = [raw[i:i + 80] for i in range(0, len(raw), 80)]
        # DATE and CHECKSUM change with the time of writing, and so does the comment of DATASUM (its value not)
        return [b"" if b.startswith((b"DATE    =", b"CHECKSUM=")) else b[:30] if b.startswith(b"DATASUM =") else b
                for b in blocks]

    a, b = cards(one), cards(two)
    assert len(a) == len(b)
    differing = [i for i, (x, y) in enumerate(zip(a, b)) if x != y]
    assert differing == [], [(a[i], b[i]) for i in differing]
    assert np.sum(shapes(one)["flags"] == 0) >= 5  # real fits were compared


# -- errors: one line on stderr, exit 1, no output ---------------------------------------------------


@pytest.fixture(scope="module")
def small(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("errors")
    data = np.full((48, 48), BKG)
    cat = write_catalog(tmp / "cat.fits", [1], [20.0], [20.0])
    return tmp, data, cat


def test_error_rate_unit_frame(small):
    tmp, data, cat = small
    frame = write_frame(tmp / "rate.fits", data / EXPTIME, BUNIT="electron/s")
    out = tmp / "o_rate.fits"
    one_line_error(measure(frame, cat, out, code=1), "rate", "electron/s", out=out)


def test_error_no_skyrate_no_weights_needs_sky(small):
    tmp, data, cat = small
    frame = write_frame(tmp / "nosky.fits", data, drop=("SKYRATE",))
    out = tmp / "o_nosky.fits"
    one_line_error(measure(frame, cat, out, code=1), "--sky", "SKYRATE", out=out)
    # with --sky it runs
    measure(frame, cat, out, "--sky", BKG)
    assert fits.getheader(out)["BKG01"] == pytest.approx(BKG) and len(shapes(out)) == 1


def test_error_catalogue_without_id(small):
    tmp, data, cat = small
    frame = write_frame(tmp / "ok.fits", data)
    Table(dict(x=[20.0], y=[20.0])).write(tmp / "noid.fits", overwrite=True)
    out = tmp / "o_noid.fits"
    one_line_error(measure(frame, tmp / "noid.fits", out, code=1), "'id'", out=out)


def test_error_psf_image_without_pixscale(small, psf):
    tmp, data, cat = small
    frame = write_frame(tmp / "ok2.fits", data)
    image = psf.drawImage(nx=64, ny=64, scale=roman.pixel_scale / 4, method="no_pixel").array
    fits.PrimaryHDU(image, fits.Header({"BUNIT": "electron"})).writeto(tmp / "psf.fits", overwrite=True)
    out = tmp / "o_psf.fits"
    one_line_error(measure(frame, cat, out, "--psf", tmp / "psf.fits", code=1), "PIXSCALE", "psf.fits", out=out)


def test_error_nonexistent_frame(small):
    tmp, data, cat = small
    out = tmp / "o_missing.fits"
    one_line_error(measure(tmp / "missing.fits", cat, out, code=1), "missing.fits", "no such file", out=out)
