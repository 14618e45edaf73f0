"""perscli measure --joint: one shape per galaxy from several frames, its parameters on the sky.

The frames see the galaxy through different local WCS Jacobians (rotations,
both parities, slightly different pixel scales) and exposure times; the
galaxy is drawn with GalSim exactly as the renderer draws it (its sky profile
mapped into pixels by the local Jacobian, through the Roman PSF), so the
joint g must come back in the sky axes of the truth catalogue: u to the
West, v to the North (+g1 East-West).
"""

import numpy as np
import pytest
from astropy.io import fits
from astropy.table import Table
from astropy.wcs import WCS

from fits_factory import one_line_error, run

galsim = pytest.importorskip("galsim")
import galsim.roman as roman  # noqa: E402

from perscli.measure.fit import ExpModel, JointStamp, fit_joint, covariance_map  # noqa: E402

N = 40                  # stamp side of the library tests
EXPTIMES = (139.8, 100.0, 60.0)
#: local WCS Jacobians d(u, v)/d(x, y) in arcsec/pixel: rotated, one with the other parity, scales 0.11-0.112
ANGLES = (0.3, 1.7, 2.6)
PARITIES = (1, -1, 1)
SCALES = (0.11, 0.111, 0.112)


@pytest.fixture(scope="module")
def psf():
    bandpass = roman.getBandpasses(AB_zeropoint=True)["J129"]
    return roman.getPSF(7, "J129", wavelength=bandpass.effective_wavelength)


@pytest.fixture(scope="module")
def psf_pixels(psf):
    return galsim.PixelScale(roman.pixel_scale).toImage(psf)


@pytest.fixture(scope="module")
def model(psf_pixels):
    return ExpModel(psf_pixels, N)


def jacobian(angle, parity, scale):
    c, s = np.cos(angle), np.sin(angle)
    return scale * np.array([[c, -s * parity], [s, c * parity]])


def draw_stamp(psf_pixels, jac, centre, g1, g2, hlr, flux):
    """The galaxy (sky profile: hlr arcsec, g in (u, v)) seen through ``jac``, centred at stamp ``centre``."""
    gal = galsim.Exponential(half_light_radius=hlr, flux=flux).shear(g1=g1, g2=g2)
    local = galsim.JacobianWCS(jac[0, 0], jac[0, 1], jac[1, 0], jac[1, 1])
    img = galsim.ImageD(galsim.BoundsI(0, N - 1, 0, N - 1), scale=1.0)
    galsim.Convolve(local.toImage(gal), psf_pixels).drawImage(image=img, center=galsim.PositionD(*centre))
    return img.array.copy()


def joint_stamps(psf_pixels, model, g1, g2, hlr=0.3, rate=150.0, du=0.02, dv=-0.03, noise=None, seed=1):
    """Three stamps of one galaxy; its centre offset by (du, dv) arcsec from the catalogue position."""
    rng = np.random.default_rng(seed)
    stamps = []
    for k, (angle, parity, scale) in enumerate(zip(ANGLES, PARITIES, SCALES)):
        jac = jacobian(angle, parity, scale)
        ainv = np.linalg.inv(jac)
        origin = (19.3 + 0.2 * k, 20.1 - 0.3 * k)           # the catalogue position in the stamp
        true_centre = np.array(origin) + ainv @ np.array([du, dv])
        img = draw_stamp(psf_pixels, jac, true_centre, g1, g2, hlr, rate * EXPTIMES[k])
        weight = np.ones_like(img)
        if noise is not None:
            img = img + rng.normal(0.0, noise, img.shape)
            weight = np.full(img.shape, 1.0 / noise ** 2)
        stamps.append(JointStamp(img, weight, model, origin, ainv, EXPTIMES[k]))
    return stamps


def start(hlr=0.3, rate=150.0):
    return (0.0, 0.0, 0.0, 0.0, 2.0 * hlr ** 2 * 1.0421, rate)


@pytest.mark.parametrize("g1, g2", [(0.25, -0.15), (-0.4, 0.1), (0.0, 0.55)])
def test_joint_fit_recovers_the_sky_shape(psf_pixels, model, g1, g2):
    """Noiseless: the same galaxy on three differently oriented frames gives its sky g, centre and flux."""
    res = fit_joint(joint_stamps(psf_pixels, model, g1, g2), start())
    assert res.flags == 0
    assert abs(res.theta[2] - g1) < 5e-4 and abs(res.theta[3] - g2) < 5e-4
    assert abs(res.theta[0] - 0.02) < 1e-3 and abs(res.theta[1] + 0.03) < 1e-3      # arcsec
    assert res.theta[5] == pytest.approx(150.0, rel=0.01)                           # e-/s
    assert res.nfev < 30 and res.dof == 3 * N * N - 6


def test_single_frame_fits_see_rotated_shapes(psf_pixels, model):
    """The frames really differ: each pixel-axis g is the sky g turned by its frame's orientation."""
    from perscli.measure.fit import fit_exp

    stamps = joint_stamps(psf_pixels, model, 0.3, 0.0)
    g = []
    for s in stamps:
        res = fit_exp(s.image, s.weight, model, s.origin + (0.0, 0.0, 4.0, 150.0 * s.flux_scale))
        g.append(res.theta[2:4])
    g = np.array(g)
    assert np.all(np.abs(np.hypot(g[:, 0], g[:, 1]) - 0.3) < 0.01)
    assert np.ptp(g[:, 0]) > 0.3     # the orientations differ a lot


def test_joint_shape_changes_are_linear_down_to_1e_9(psf_pixels, model):
    """De of a joint fit is linear in an added pattern down to a pattern of 1e-9 of the galaxy's peak."""
    stamps = joint_stamps(psf_pixels, model, 0.2, -0.1, rate=60.0, noise=12.0, seed=5)
    st = start(rate=60.0)
    base = fit_joint(stamps, st)
    again = fit_joint(joint_stamps(psf_pixels, model, 0.2, -0.1, rate=60.0, noise=12.0, seed=5), st)
    assert base.flags == 0
    assert again.theta[2] - base.theta[2] == 0.0 and again.theta[3] - base.theta[3] == 0.0
    yy, xx = np.mgrid[0:N, 0:N]
    peak = stamps[1].image.max()
    ghost = peak * np.exp(-((xx - 24) ** 2 + (yy - 15) ** 2) / 8.0)     # on the second frame, beside the galaxy
    slopes = []
    for eps in [1e-2, 1e-4, 1e-6, 1e-8, 1e-9]:
        changed = list(stamps)
        s = stamps[1]
        changed[1] = JointStamp(s.image + eps * ghost, s.weight, s.model, s.origin, s.ainv, s.flux_scale)
        res = fit_joint(changed, st)
        slopes.append(((res.theta[2] - base.theta[2]) / eps, (res.theta[3] - base.theta[3]) / eps))
    slopes = np.array(slopes)
    assert np.all(np.abs(slopes[0]) > 1e-3)                    # the pattern moves g
    assert np.max(np.abs(slopes[-1])) * 1e-9 < 1e-9            # the last change is at or below 1e-9
    np.testing.assert_allclose(slopes, np.broadcast_to(slopes[1], slopes.shape), rtol=0.02)


def test_covariance_map_is_ainv_c_ainv_transposed():
    rng = np.random.default_rng(3)
    ainv = rng.normal(size=(2, 2))
    c = np.array([[2.0, 0.3], [0.3, 1.0]])
    expected = ainv @ c @ ainv.T
    got = covariance_map(ainv) @ np.array([c[0, 0], c[0, 1], c[1, 1]])
    np.testing.assert_allclose(got, [expected[0, 0], expected[0, 1], expected[1, 1]], rtol=1e-14)


# -- the command -----------------------------------------------------------------------------------------

SIDE = 96
ZPT, SKYRATE = 26.0, 1.0


def frame_wcs(angle, parity, crval=(10.0, -44.0)):
    w = WCS(naxis=2)
    w.wcs.ctype = ["RA---TAN", "DEC--TAN"]
    w.wcs.crval = list(crval)
    w.wcs.crpix = [SIDE / 2 + 0.5, SIDE / 2 + 0.5]
    c, s = np.cos(angle), np.sin(angle)
    # parity -1 is the sky as seen (East to the left of North); +1 the mirror image
    w.wcs.cd = 0.11 / 3600 * np.array([[-c * parity, s], [s * parity, c]])
    return w


#: galaxies (ra offset, dec offset in arcsec from the frame centre, g1, g2, hlr, flux e-/s), well apart
GALAXIES = [(-2.2, -1.9, 0.25, -0.15, 0.3, 150.0), (2.4, 1.6, -0.1, 0.3, 0.35, 200.0),
            (-1.8, 2.5, 0.05, 0.2, 0.25, 100.0)]


def _radec(du_east, dv):
    return 10.0 + du_east / 3600.0 / np.cos(np.radians(44.0)), -44.0 + dv / 3600.0


def write_frames(tmp, psf, *, filters=("J129", "J129", "J129"), noise=None):
    paths = []
    for k, (angle, parity, filt) in enumerate(zip(ANGLES, (-1, 1, -1), filters)):
        w = frame_wcs(angle, parity, crval=(10.0 + 3e-5 * k, -44.0 - 3e-5 * k))
        hdr = w.to_header()
        gw = galsim.GSFitsWCS(header=fits.Header(hdr))
        img = galsim.ImageD(SIDE, SIDE, scale=1.0)
        psf_pix = galsim.PixelScale(roman.pixel_scale).toImage(psf)
        for de, dn, g1, g2, hlr, rate in GALAXIES:
            ra, dec = _radec(de, dn)
            x, y = (float(v[0]) for v in w.all_world2pix([ra], [dec], 1))
            gal = galsim.Exponential(half_light_radius=hlr, flux=rate * EXPTIMES[k]).shear(g1=g1, g2=g2)
            prof = gw.local(galsim.PositionD(x, y)).toImage(gal)
            galsim.Convolve(prof, psf_pix).drawImage(image=img, add_to_image=True, center=galsim.PositionD(x, y))
        data = img.array + (SKYRATE + 0.015) * EXPTIMES[k]
        if noise is not None:
            data = data + np.random.default_rng(k).normal(0.0, noise, data.shape)
        for key, value in dict(BUNIT="electron", GAIN=1.0, EXPTIME=EXPTIMES[k], SKYRATE=SKYRATE, SCA=7,
                               FILTER=filt, ZPT_AB=ZPT).items():
            hdr[key] = value
        path = tmp / f"f{k}.fits"
        fits.HDUList([fits.PrimaryHDU(), fits.ImageHDU(data, hdr, name="SCI")]).writeto(path, overwrite=True)
        paths.append(path)
    return paths


def write_truth(path, *, kind=True, extra_star=True):
    rows = GALAXIES + ([(0.0, 0.0, 0.0, 0.0, 0.0, 5e3)] if extra_star else [])
    ra, dec = zip(*[_radec(r[0], r[1]) for r in rows])
    mag = [ZPT - 2.5 * np.log10(r[5] / roman.collecting_area) for r in rows]
    cols = dict(id=np.arange(1, len(rows) + 1, dtype=np.int64), ra=ra, dec=dec, hlr=[r[4] for r in rows],
                mag_J129=mag)
    if kind:
        cols["kind"] = ["galaxy"] * len(GALAXIES) + (["star"] if extra_star else [])
    Table(cols).write(path, overwrite=True)
    return path


@pytest.fixture(scope="module")
def joint_scene(psf, tmp_path_factory):
    tmp = tmp_path_factory.mktemp("joint")
    return tmp, write_frames(tmp, psf), write_truth(tmp / "truth.fits")


def test_joint_command_one_row_per_galaxy_with_sky_shapes(joint_scene):
    tmp, frames, truth = joint_scene
    out = tmp / "joint.fits"
    run("measure", *frames, "--catalog", truth, "--joint", "-o", out)
    with fits.open(out, checksum=True) as hdul:
        assert hdul[1].name == "JOINT" and "SHAPES" not in hdul
        t = hdul["JOINT"].data
        hdr = hdul[0].header
        # flux (column 7) is in e-/s, said in its TTYPE comment: FITS has no unit for electrons (a TUNIT
        # 'electron/s' made astropy's reader warn)
        joint = hdul["JOINT"].header
        assert joint["TUNIT6"] == "arcsec2" and "TUNIT7" not in joint and "e-/s" in joint.comments["TTYPE7"]
    assert hdr["JOINT"] is True and hdr["NFIT"] == 3 and hdr["NSEL"] == 3 and hdr["GAXES"].startswith("sky")
    for name in ("id", "ra", "dec", "g1", "g2", "T", "flux", "ra_err", "dec_err", "g1_err", "g2_err", "T_err",
                 "flux_err", "s2n", "snr_pred", "nframes", "chi2", "nfev", "flags"):
        assert name in t.columns.names
    assert list(t["id"]) == [1, 2, 3]             # the star (4) is not a galaxy
    assert np.all(t["flags"] == 0) and np.all(t["nframes"] == 3)
    for row, (de, dn, g1, g2, hlr, rate) in zip(t, GALAXIES):
        assert abs(row["g1"] - g1) < 2e-3 and abs(row["g2"] - g2) < 2e-3
        assert row["flux"] == pytest.approx(rate, rel=0.02)
        ra, dec = _radec(de, dn)
        assert abs((row["ra"] - ra) * 3600 * np.cos(np.radians(dec))) < 2e-3 and abs((row["dec"] - dec) * 3600) < 2e-3


def test_joint_agrees_with_the_single_frame_fits_turned_to_the_sky(joint_scene):
    """Each frame's pixel-axis g, turned into (u, v) with that frame's WCS, is the joint g (noiseless)."""
    tmp, frames, truth = joint_scene
    run("measure", *frames, "--catalog", truth, "-o", tmp / "single.fits")
    s = fits.getdata(tmp / "single.fits", "SHAPES")
    run("measure", *frames, "--catalog", truth, "--joint", "-o", tmp / "joint_again.fits")
    joint = fits.getdata(tmp / "joint_again.fits", "JOINT")
    for k, (angle, parity) in enumerate(zip(ANGLES, (-1, 1, -1))):
        rows = s[s["frame"] == k]
        for row, jrow in zip(rows, joint):
            # pixel g through the frame's CD: u = -dRA cos(dec) (West), v = North; a shear transforms as 2 x angle
            cd = frame_wcs(angle, parity).wcs.cd
            a = np.array([[-1.0, 0.0], [0.0, 1.0]]) @ cd        # d(u, v)/d(x, y) up to scale
            g = complex(row["g1"], row["g2"])
            if np.linalg.det(a) < 0:
                g = g.conjugate()
                a = a @ np.diag([1.0, -1.0])
            phi = np.arctan2(a[1, 0], a[0, 0])
            g_sky = g * np.exp(2j * phi)
            assert abs(g_sky.real - jrow["g1"]) < 3e-3 and abs(g_sky.imag - jrow["g2"]) < 3e-3


def test_joint_same_bytes_with_one_or_two_workers(joint_scene):
    tmp, frames, truth = joint_scene
    for w in (1, 2):
        run("measure", *frames, "--catalog", truth, "--joint", "--workers", w, "-o", tmp / f"w{w}.fits")
    a, b = (fits.getdata(tmp / f"w{w}.fits", "JOINT").tobytes() for w in (1, 2))
    assert a == b


def test_joint_all_rows_and_cut(psf, tmp_path):
    """A galaxy off every frame (256) and one below the combined cut (4096) are listed with --all-rows only."""
    frames = write_frames(tmp_path, psf, noise=15.0)
    rows = GALAXIES + [(60.0, 60.0, 0.0, 0.0, 0.3, 100.0), (0.0, 0.0, 0.0, 0.0, 0.3, 0.5)]
    ra, dec = zip(*[_radec(r[0], r[1]) for r in rows])
    Table(dict(id=np.arange(1, 6, dtype=np.int64), ra=ra, dec=dec, hlr=[r[4] for r in rows],
               mag_J129=[ZPT - 2.5 * np.log10(r[5] / roman.collecting_area) for r in rows])).write(
        tmp_path / "cat.fits")
    run("measure", *frames, "--catalog", tmp_path / "cat.fits", "--joint", "-o", tmp_path / "a.fits")
    t = fits.getdata(tmp_path / "a.fits", "JOINT")
    assert list(t["id"]) == [1, 2, 3]
    run("measure", *frames, "--catalog", tmp_path / "cat.fits", "--joint", "--all-rows", "-o", tmp_path / "b.fits")
    t = fits.getdata(tmp_path / "b.fits", "JOINT")
    assert list(t["id"]) == [1, 2, 3, 4, 5] and list(t["flags"][3:]) == [256, 4096]
    assert list(t["nframes"][3:]) == [0, 3] and np.isnan(t["g1"][4])
    # the combined predicted S/N: sqrt of the sum of the frames' squares (each frame's from its own exposure)
    single = fits.getdata(_single(frames, tmp_path), "SHAPES")
    five = single[single["id"] == 5]["snr_pred"]
    assert t["snr_pred"][4] == pytest.approx(np.sqrt(np.sum(five ** 2)), rel=1e-12)


def _single(frames, tmp_path):
    out = tmp_path / "single_all.fits"
    run("measure", *frames, "--catalog", tmp_path / "cat.fits", "--all-rows", "-o", out)
    return out


# -- errors: one line on stderr, exit 1, no output -------------------------------------------------------


def test_error_joint_frames_of_different_filters(psf, tmp_path):
    frames = write_frames(tmp_path, psf, filters=("J129", "H158", "J129"))
    out = tmp_path / "o.fits"
    r = run("measure", *frames, "--catalog", write_truth(tmp_path / "t.fits"), "--joint", "-o", out, code=1)
    one_line_error(r, "--joint", "J129", "H158", "filter", out=out)


def test_error_kinds_without_a_kind_column(joint_scene, tmp_path):
    _, frames, _ = joint_scene
    cat = write_truth(tmp_path / "nokind.fits", kind=False)
    out = tmp_path / "o.fits"
    one_line_error(run("measure", frames[0], "--catalog", cat, "--kinds", "galaxy", "-o", out, code=1),
                   "no kind column", "--kinds all", out=out)
    # without --kinds every row is measured; --kinds all is fine too
    run("measure", frames[0], "--catalog", cat, "-o", tmp_path / "ok.fits")
    assert fits.getheader(tmp_path / "ok.fits")["KINDS"] == "all (no kind column)"
    run("measure", frames[0], "--catalog", cat, "--kinds", "all", "-o", tmp_path / "ok2.fits")


def test_error_unknown_kind(joint_scene, tmp_path):
    _, frames, truth = joint_scene
    out = tmp_path / "o.fits"
    one_line_error(run("measure", frames[0], "--catalog", truth, "--kinds", "galxy", "-o", out, code=1),
                   "galxy", "galaxy, star", out=out)


@pytest.mark.parametrize("value", ["-1", "nan", "inf"])
def test_error_min_snr_negative_or_not_finite(joint_scene, tmp_path, value):
    _, frames, truth = joint_scene
    out = tmp_path / "o.fits"
    one_line_error(run("measure", frames[0], "--catalog", truth, "--min-snr", value, "-o", out, code=1),
                   "--min-snr", out=out)


def test_error_joint_with_hsm_or_xy_catalogue(joint_scene, tmp_path):
    _, frames, _ = joint_scene
    out = tmp_path / "o.fits"
    truth = write_truth(tmp_path / "t.fits")
    one_line_error(run("measure", *frames, "--catalog", truth, "--joint", "--method", "hsm", "-o", out, code=1),
                   "--joint", "hsm", out=out)
    Table(dict(id=[1], x=[40.0], y=[40.0])).write(tmp_path / "xy.fits")
    one_line_error(run("measure", *frames, "--catalog", tmp_path / "xy.fits", "--joint", "-o", out, code=1),
                   "--joint", "ra/dec", out=out)
