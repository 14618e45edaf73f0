"""perscli correlate on few objects: shot-noise errors when a jackknife is impossible, never a crash."""

import numpy as np
import pytest
from astropy.io import fits

from fits_factory import invoke, one_line_error, run
from perscli import PerscliError
from perscli.stats.shape_changes import ShapeChanges
from perscli.stats.xi import correlate_de

treecorr = pytest.importorskip("treecorr")

RA0, DEC0 = 10.0, -44.0


def pair(folder, n, seed=1, size=1.0):
    """Tables A and B of n objects over size x size degrees; returns (a, b, ra, dec, de1, de2)."""
    rng = np.random.default_rng(seed)
    dec = DEC0 + rng.uniform(-size / 2, size / 2, n)
    ra = RA0 + rng.uniform(-size / 2, size / 2, n) / np.cos(np.radians(DEC0))
    g1b, g2b = rng.normal(0, 0.27, n), rng.normal(0, 0.27, n)
    # shapes have |g| < 1 (correlate refuses others): the rare draws beyond 0.9 are pulled in to it
    shrink = np.minimum(1.0, 0.9 / np.hypot(g1b, g2b))
    g1b, g2b = g1b * shrink, g2b * shrink
    de1, de2 = rng.normal(0, 1e-5, n), rng.normal(0, 1e-5, n)
    paths = []
    for name, g1, g2 in (("a", g1b + de1, g2b + de2), ("b", g1b, g2b)):
        cols = [fits.Column("id", "K", array=np.arange(n)), fits.Column("ra", "D", array=ra),
                fits.Column("dec", "D", array=dec), fits.Column("g1", "D", array=g1),
                fits.Column("g2", "D", array=g2), fits.Column("flags", "K", array=np.zeros(n, int))]
        path = folder / f"{name}{n}_{seed}.fits"
        fits.HDUList([fits.PrimaryHDU(), fits.BinTableHDU.from_columns(cols, name="SHAPES")]).writeto(path)
        paths.append(str(path))
    # De as the tables give it (g(A) - g(B) in float64), for comparisons to the last bit
    return paths[0], paths[1], ra, dec, (g1b + de1) - g1b, (g2b + de2) - g2b


@pytest.mark.parametrize("n, method", [(1, "shot"), (3, "shot"), (10, "shot"), (50, "shot"), (200, "jackknife")])
def test_few_objects_with_20_patches_never_fail(tmp_path, n, method):
    a, b, ra, dec, de1, de2 = pair(tmp_path, n)
    out = tmp_path / "xi.fits"
    said = run("correlate", a, b, "--npatch", 20, "--plots", tmp_path / "figs", "-o", out)
    for name in ("xi.png", "hist_de.png", "bin_theta.png"):
        assert (tmp_path / "figs" / name).read_bytes()[:4] == b"\x89PNG"
    with fits.open(out, checksum=True) as hdul:
        head = hdul[0].header
        assert head["VARMETHD"] == method and hdul["XI"].header["VAR_METH"] == method
        assert hdul["COV"].header["VAR_METH"] == method
        if method == "shot":
            assert head["NPATCH"] == 0 and len(hdul["PATCHES"].data) == 0 and hdul["PATCHES"].header["NPATCH"] == 0
            assert ("too few for a jackknife" in head["VARWHY"] if n < 20
                    else "only 50 objects for 20 jackknife patches" in head["VARWHY"])
            # warned once, saying why
            warned = [line for line in said.stderr.splitlines() if "shot-noise errors" in line]
            assert len(warned) == 1 and head["VARWHY"] in warned[0]
            cov = hdul["COV"].data
            assert np.count_nonzero(cov - np.diag(np.diag(cov))) == 0
        else:
            assert head["NPATCH"] == 20 and "VARWHY" not in head
        xi = hdul["XI"].data
        assert np.all(np.isfinite(xi["xip"])) and np.all(np.isfinite(xi["sigma_xip"]))
        assert np.all(xi["sigma_xip"][xi["npairs"] > 0] > 0)
    # budget reads the result, and says when its errors are shot noise
    result = run("budget", out, "-o", tmp_path / "b.fits", "--plot", tmp_path / "b.png", "--check")
    assert ("errors are shot noise" in result.stderr) == (method == "shot" and n > 1), result.stderr
    if n == 1:
        assert "no bin with pairs" in result.stderr


def test_shot_noise_is_treecorrs(tmp_path):
    a, b, ra, dec, de1, de2 = pair(tmp_path, 40)
    out = tmp_path / "xi.fits"
    run("correlate", a, b, "--min-sep", 1, "--max-sep", 60, "--nbins", 6, "-o", out)
    cat = treecorr.Catalog(ra=ra, dec=dec, ra_units="deg", dec_units="deg", g1=de1, g2=de2)
    gg = treecorr.GGCorrelation(min_sep=1, max_sep=60, nbins=6, sep_units="arcmin", var_method="shot")
    gg.process(cat)
    with fits.open(out) as hdul:
        np.testing.assert_allclose(hdul["XI"].data["xip"], gg.xip, rtol=1e-10, atol=0)
        np.testing.assert_allclose(hdul["XI"].data["sigma_xip"], np.sqrt(gg.varxip), rtol=1e-10, atol=0)
        np.testing.assert_allclose(hdul["COV"].data, gg.cov, rtol=1e-10, atol=0)


def test_shot_noise_asked_for_and_jackknife_insisted_on(tmp_path):
    a, b, *_ = pair(tmp_path, 400)
    out = tmp_path / "shot.fits"
    result = run("correlate", a, b, "--var-method", "shot", "--npatch", 4, "-o", out)
    with fits.open(out) as hdul:
        assert hdul[0].header["VARMETHD"] == "shot" and hdul[0].header["VARASKED"] == "shot"
        assert hdul[0].header["VARWHY"].startswith("shot noise asked for")
    assert "instead of a jackknife" not in result.stderr        # asked for: no warning
    # the jackknife insisted on, with too few objects: one line, exit 1, no output
    few_a, few_b, *_ = pair(tmp_path, 30)
    one_line_error(invoke("correlate", few_a, few_b, "--var-method", "jackknife", "-o", tmp_path / "no.fits"),
                   "only 30 objects for 20 jackknife patches", "--npatch 3 or fewer", out=tmp_path / "no.fits")


def test_a_bin_the_jackknife_cannot_estimate_gets_shot_noise(tmp_path):
    # 30 objects in 2 patches: a bin at 70' holds pairs but its jackknife variance is exactly 0
    rng = np.random.default_rng(1)
    n = 30
    dec = DEC0 + rng.uniform(-0.5, 0.5, n)
    ra = RA0 + rng.uniform(-0.5, 0.5, n) / np.cos(np.radians(DEC0))
    sc = ShapeChanges(de1=rng.normal(0, 1e-5, n), de2=rng.normal(0, 1e-5, n), e1=None, e2=None, pos1=ra, pos2=dec,
                      coords="radec", pos_units="deg")
    settings = dict(npatch=2, min_sep=1, max_sep=100, nbins=20, seed=1)
    gg, cat, insisted = correlate_de(sc, var_method="jackknife", **settings)
    bad = np.flatnonzero((gg.npairs > 0) & (gg.varxip == 0))
    assert len(bad), "the recipe no longer shows the defect"
    assert insisted.shot_bins == [] and np.all(np.diagonal(insisted.cov)[bad] == 0)       # kept, with a warning
    gg, cat, errors = correlate_de(sc, **settings)
    assert errors.method == "jackknife" and errors.reason == "" and errors.shot_bins == list(bad)
    shot = gg.estimate_cov("shot")
    nb = len(gg.npairs)
    for k in bad:
        for i in (k, nb + k):
            assert errors.cov[i, i] == shot[i] > 0
            assert np.count_nonzero(errors.cov[i]) == 1 and np.count_nonzero(errors.cov[:, i]) == 1
    good = np.setdiff1d(np.arange(nb), bad)
    np.testing.assert_array_equal(errors.cov[np.ix_(good, good)], np.asarray(gg.cov)[np.ix_(good, good)])
    # De zero everywhere: zero variances are right, nothing is replaced
    zero = ShapeChanges(de1=np.zeros(n), de2=np.zeros(n), e1=None, e2=None, pos1=ra, pos2=dec, coords="radec",
                        pos_units="deg")
    assert correlate_de(zero, npatch=2, seed=1)[2].shot_bins == []


def test_a_single_pair_at_the_edge_of_the_range_is_repaired_in_the_output(tmp_path):
    # 200 objects, 20 patches: the last bin holds one pair, its jackknife variance ~1e-30 of shot noise
    a, b, *_ = pair(tmp_path, 200)
    out = tmp_path / "xi.fits"
    run("correlate", a, b, "--npatch", 20, "-o", out)
    with fits.open(out) as hdul:
        xi, head = hdul["XI"].data, hdul[0].header
        assert head["VARMETHD"] == "jackknife" and xi["npairs"][-1] == 1
        assert head["SHOTBINS"] == "19" == hdul["XI"].header["SHOTBINS"] == hdul["COV"].header["SHOTBINS"]
        np.testing.assert_allclose(xi["sigma_xip"] ** 2, np.diagonal(hdul["COV"].data)[:20], rtol=1e-12)
        # the repaired error is shot noise: sqrt(2) sigma_e^2 / sqrt(weight) for one pair
        assert xi["sigma_xip"][-1] > 0.1 * np.median(xi["sigma_xip"])


def test_patch_centres_from_a_shot_noise_output_are_refused_clearly(tmp_path):
    a, b, *_ = pair(tmp_path, 15)
    first = tmp_path / "first.fits"
    run("correlate", a, b, "-o", first)
    big_a, big_b, *_ = pair(tmp_path, 300, seed=2)
    result = run("correlate", big_a, big_b, "--patch-centers", first, "-o", tmp_path / "x.fits", code=1)
    assert "0 patch centre(s)" in result.output


def test_library_refuses_bad_var_method():
    sc = ShapeChanges(de1=np.zeros(3), de2=np.zeros(3), e1=None, e2=None, pos1=np.zeros(3), pos2=np.zeros(3),
                      coords="radec", pos_units="deg")
    with pytest.raises(PerscliError, match="--var-method bootstrap"):
        correlate_de(sc, var_method="bootstrap")
