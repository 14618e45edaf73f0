"""perscli measure on rendered frames: the output table, pairing, flags and errors."""

import numpy as np
import pytest
from astropy.io import fits
from astropy.table import Table

from fits_factory import run

galsim = pytest.importorskip("galsim")

BOUNDS = ["--bounds", "1", "160", "1", "160"]
POINTING = ["--ra", "10", "--dec", "-44", "--pa", "30", "--filter", "J129", "--sca", "7"]
MJD = 61541.97


@pytest.fixture(scope="module")
def scene(tmp_path_factory):
    """A bright star and a few galaxies on a 160x160 cutout; exposure 2 with and without persistence."""
    from perscli.render.exposure import Exposure
    from perscli.optics import Optics

    tmp = tmp_path_factory.mktemp("measure")
    optics = Optics(Exposure(ra=10, dec=-44, pa=30, sca=7, filter="J129", mjd=MJD))
    xs = np.array([40.0, 100.0, 120.0, 45.0, 150.0, 3000.0])
    ys = np.array([40.0, 50.0, 110.0, 120.0, 150.0, 3000.0])
    ra, dec = optics.wcs.xyToradec(xs, ys, units="deg")
    kind = np.array(["galaxy", "galaxy", "galaxy", "galaxy", "star", "galaxy"])
    table = Table(dict(id=np.arange(1, 7, dtype=np.int64), ra=ra, dec=dec, kind=kind,
                       mag_J129=np.array([20.0, 20.3, 20.2, 20.4, 16.0, 21.0]),
                       mag_H158=np.array([19.7, 20.0, 19.9, 20.1, 15.8, 20.7]),
                       hlr=np.array([0.3, 0.25, 0.35, 0.3, 0.0, 0.3]),
                       e1=np.array([0.2, -0.1, 0.0, 0.3, 0.0, 0.0]), e2=np.array([0.0, 0.2, -0.3, 0.1, 0.0, 0.0])))
    truth = tmp / "truth.fits"
    table.write(truth)
    e1, e2, e2n = tmp / "e1.fits", tmp / "e2.fits", tmp / "e2n.fits"
    run("render", truth, *POINTING, "--mjd", MJD, *BOUNDS, "--seed", 1, "-o", e1)
    later = MJD + 169.8 / 86400
    run("render", truth, *POINTING, "--mjd", later, *BOUNDS, "--seed", 2, "--previous", e1, "-o", e2)
    run("render", truth, *POINTING, "--mjd", later, *BOUNDS, "--seed", 2, "-o", e2n)
    return tmp, truth, e2, e2n


def test_shapes_table_and_pairing(scene):
    tmp, truth, e2, e2n = scene
    out = tmp / "shapes.fits"
    run("measure", e2, e2n, "--catalog", truth, "-o", out)
    with fits.open(out, checksum=True) as hdul:
        shapes = hdul["SHAPES"].data
        combined = hdul["COMBINED"].data
        assert hdul[0].header["METHOD"] == "exp" and hdul[0].header["NFRAMES"] == 2
        assert hdul[0].header["CAT"] == "truth.fits" and "FRM01DS" in hdul[0].header
    for name in ("id", "frame", "x", "y", "ra", "dec", "g1", "g2", "T", "flux", "g1_err", "g2_err", "s2n",
                 "snr_pred", "chi2", "nfev", "flags"):
        assert name in shapes.columns.names
    a, b = shapes[shapes["frame"] == 0], shapes[shapes["frame"] == 1]
    # the galaxies on the cutout: not the star (5), not the galaxy off the cutout (6)
    assert list(a["id"]) == [1, 2, 3, 4] and list(b["id"]) == [1, 2, 3, 4]
    assert np.all(a["snr_pred"] > 50) and np.array_equal(a["snr_pred"], b["snr_pred"])
    gal = (a["flags"] == 0) & (b["flags"] == 0)
    assert gal.sum() >= 3
    # shapes follow the truth (noise, nonlinearity and IPC included); g is in pixel axes, the catalogue's
    # e in sky axes, so compare the rotation-invariant |g|
    truth_g = np.hypot([0.2, -0.1, 0.0, 0.3], [0.0, 0.2, -0.3, 0.1])
    assert np.all(np.abs(np.hypot(a["g1"], a["g2"])[:4][gal[:4]] - truth_g[gal[:4]]) < 0.05)
    # positions come back in FITS pixels of the cutout
    assert np.all(np.abs(a["x"][:4][gal[:4]] - np.array([40.0, 100.0, 120.0, 45.0])[gal[:4]]) < 0.3)
    # the frame with persistence differs: shape changes are finite and small
    de = np.hypot(a["g1"] - b["g1"], a["g2"] - b["g2"])[gal]
    assert np.all(np.isfinite(de)) and np.all(de < 0.05)
    assert np.array_equal(combined["id"], a["id"]) and combined["nframes"][0] == 2


def test_kinds_and_all_rows(scene):
    """--kinds all fits the star too; --all-rows lists the object off the cutout, flagged 256 alone."""
    tmp, truth, e2, _ = scene
    out = tmp / "every.fits"
    run("measure", e2, "--catalog", truth, "--kinds", "all", "--all-rows", "-o", out)
    s = fits.getdata(out, "SHAPES")
    assert list(s["id"]) == [1, 2, 3, 4, 5, 6]
    assert s["flags"][5] == 256 and np.isnan(s["g1"][5])
    assert np.isfinite(s["g1"][4])  # the star, fitted as a (small) galaxy
    hdr = fits.getheader(out)
    assert hdr["KINDS"] == "all" and hdr["ALLROWS"] is True and hdr["NSEL"] == 6 and hdr["NON01"] == 5
    stars = tmp / "stars.fits"
    run("measure", e2, "--catalog", truth, "--kinds", "star", "-o", stars)
    assert list(fits.getdata(stars, "SHAPES")["id"]) == [5]
    # the galaxies' rows of the default run, bit for bit
    default = tmp / "default.fits"
    run("measure", e2, "--catalog", truth, "-o", default)
    d = fits.getdata(default, "SHAPES")
    for key in ("g1", "g2", "T", "flux", "flags", "nfev"):
        assert np.array_equal(d[key], s[key][:4]), key


def test_identical_frames_give_exactly_zero(scene):
    tmp, truth, e2, _ = scene
    out = tmp / "same.fits"
    run("measure", e2, e2, "--catalog", truth, "-o", out)
    s = fits.getdata(out, "SHAPES")
    a, b = s[s["frame"] == 0], s[s["frame"] == 1]
    ok = a["flags"] == 0
    assert ok.sum() >= 3
    assert np.array_equal(a["g1"][ok], b["g1"][ok]) and np.array_equal(a["g2"][ok], b["g2"][ok])


def test_hsm_method_runs(scene):
    tmp, truth, e2, _ = scene
    out = tmp / "hsm.fits"
    run("measure", e2, "--catalog", truth, "--method", "hsm", "-o", out)
    s = fits.getdata(out, "SHAPES")
    assert np.sum(s["flags"] == 0) >= 3 and fits.getval(out, "METHOD") == "hsm"


def test_errors(scene, tmp_path):
    _, truth, e2, _ = scene
    bad = tmp_path / "bad.fits"
    Table(dict(id=np.arange(3), flux=np.ones(3))).write(bad)
    r = run("measure", e2, "--catalog", bad, "-o", tmp_path / "o.fits", code=1)
    assert "ra/dec" in r.stderr and not (tmp_path / "o.fits").exists()
    r = run("measure", e2, "--catalog", truth, "--stamp", "15", "-o", tmp_path / "o.fits", code=1)
    assert "--stamp" in r.stderr
    r = run("measure", e2, "--catalog", truth, "--psf", str(tmp_path / "none.fits"), "-o", tmp_path / "o.fits",
            code=1)
    assert "no such file" in r.stderr
    run("measure", e2, "-o", tmp_path / "o.fits", code=2)
