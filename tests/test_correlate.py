"""perscli correlate: xi+/- of De against TreeCorr, the jackknife covariance, the De statistics, bad input."""

import os
from functools import partial

import numpy as np
import pytest
from astropy.io import fits

import fits_factory
from fits_factory import invoke, run
from perscli.stats.de_stats import de_histogram, de_statistics, theta_distribution

treecorr = pytest.importorskip("treecorr")

RA0, DEC0 = 10.0, -44.0


def sky(n, rng, size=1.0):
    """n positions uniform over a size x size degree field."""
    dec = DEC0 + rng.uniform(-size / 2, size / 2, n)
    ra = RA0 + rng.uniform(-size / 2, size / 2, n) / np.cos(np.radians(DEC0))
    return ra, dec


def write_table(path, columns, units=None):
    cols = []
    for key, values in columns.items():
        values = np.asarray(values)
        fmt = "K" if values.dtype.kind in "iu" else ("I" if key == "frame" else "D")
        cols.append(fits.Column(key, fmt, array=values, unit=(units or {}).get(key)))
    fits.HDUList([fits.PrimaryHDU(), fits.BinTableHDU.from_columns(cols, name="SHAPES")]).writeto(path)
    return str(path)


def shapes_frames(n=2000, seed=1, de=None, flags_a=None, flags_b=None, ids_b=None, size=1.0):
    """Columns of a SHAPES table with two frames: A = B + De; returns (table, de1, de2, g1b, g2b, ra, dec)."""
    rng = np.random.default_rng(seed)
    ra, dec = sky(n, rng, size)
    g1b, g2b = rng.normal(0, 0.27, n), rng.normal(0, 0.27, n)
    # shapes have |g| < 1 (correlate refuses others): the rare draws beyond 0.9 are pulled in to it
    shrink = np.minimum(1.0, 0.9 / np.hypot(g1b, g2b))
    g1b, g2b = g1b * shrink, g2b * shrink
    de1, de2 = de if de is not None else (rng.normal(0, 1e-5, n), rng.normal(0, 1e-5, n))
    ids = np.arange(1, n + 1)
    frame = {
        0: dict(id=ids, g1=g1b + de1, g2=g2b + de2, flags=flags_a if flags_a is not None else np.zeros(n, int)),
        1: dict(id=ids if ids_b is None else ids_b, g1=g1b, g2=g2b,
                flags=flags_b if flags_b is not None else np.zeros(n, int)),
    }
    x, y = rng.uniform(1, 4088, n), rng.uniform(1, 4088, n)
    table = {k: [] for k in ("id", "frame", "x", "y", "ra", "dec", "g1", "g2", "g1_err", "g2_err", "flags")}
    for k in (0, 1):
        part = dict(frame[k], frame=np.full(n, k, dtype=np.int16), x=x, y=y, ra=ra, dec=dec,
                    g1_err=np.full(n, 0.01), g2_err=np.full(n, 0.01))
        for key in table:
            table[key].append(np.asarray(part[key]))
    table = {k: np.concatenate(v) for k, v in table.items()}
    return table, de1, de2, g1b, g2b, ra, dec


def split(table, k):
    sel = table["frame"] == k
    return {key: v[sel] for key, v in table.items()}


@pytest.fixture(scope="module")
def two_frames(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("correlate")
    table, de1, de2, g1b, g2b, ra, dec = shapes_frames()
    both = write_table(tmp / "both.fits", table, units={"ra": "deg", "dec": "deg", "x": "pix", "y": "pix"})
    a = write_table(tmp / "a.fits", split(table, 0), units={"x": "pix", "y": "pix"})
    b = write_table(tmp / "b.fits", split(table, 1), units={"x": "pix", "y": "pix"})
    de = write_table(tmp / "de.fits", dict(id=np.arange(1, len(ra) + 1), ra=ra, dec=dec, de1=de1, de2=de2))
    return dict(tmp=tmp, both=both, a=a, b=b, de=de, de1=de1, de2=de2, g1b=g1b, g2b=g2b, ra=ra, dec=dec)


SETTINGS = ["--npatch", 4, "--seed", 3, "--min-sep", 1, "--max-sep", 30, "--nbins", 8]


def direct_treecorr(ra, dec, de1, de2, *, npatch=4, seed=3, min_sep=1.0, max_sep=30.0, nbins=8):
    cat = treecorr.Catalog(ra=ra, dec=dec, ra_units="deg", dec_units="deg", g1=de1, g2=de2, npatch=npatch,
                           rng=np.random.default_rng(seed))
    gg = treecorr.GGCorrelation(min_sep=min_sep, max_sep=max_sep, nbins=nbins, sep_units="arcmin",
                                var_method="jackknife", cross_patch_weight="match")
    gg.process(cat)
    return gg


def test_xi_equals_direct_treecorr(two_frames):
    t = two_frames
    out = t["tmp"] / "xi_frames.fits"
    run("correlate", t["both"], "--frames", 0, 1, *SETTINGS, "-o", out)
    gg = direct_treecorr(t["ra"], t["dec"], (t["g1b"] + t["de1"]) - t["g1b"], (t["g2b"] + t["de2"]) - t["g2b"])
    with fits.open(out) as hdul:
        xi = hdul["XI"].data
        for name in ("r_nom", "meanr", "meanlogr", "xip", "xim", "xip_im", "xim_im", "sigma_xip", "sigma_xim",
                     "weight", "npairs"):
            assert name in xi.columns.names
        np.testing.assert_allclose(xi["xip"], gg.xip, rtol=1e-10, atol=0)
        np.testing.assert_allclose(xi["xim"], gg.xim, rtol=1e-10, atol=0)
        np.testing.assert_allclose(xi["npairs"], gg.npairs, rtol=0)
        np.testing.assert_allclose(xi["sigma_xip"], np.sqrt(gg.varxip), rtol=1e-10)
        np.testing.assert_allclose(hdul["COV"].data, gg.cov, rtol=1e-10, atol=0)
        assert hdul["XI"].header["SEP_UNIT"] == "arcmin"
    # the same De given as columns, or as two files, gives the same xi
    for args in ([t["de"], "--de1", "de1", "--de2", "de2"], [t["a"], t["b"]]):
        out2 = t["tmp"] / f"xi_{len(args)}.fits"
        run("correlate", *args, *SETTINGS, "-o", out2)
        with fits.open(out) as h1, fits.open(out2) as h2:
            np.testing.assert_allclose(h2["XI"].data["xip"], h1["XI"].data["xip"], rtol=1e-9, atol=1e-22)
            np.testing.assert_allclose(h2["XI"].data["xim"], h1["XI"].data["xim"], rtol=1e-9, atol=1e-22)


def test_output_layout_covariance_and_provenance(two_frames):
    t = two_frames
    out = t["tmp"] / "layout.fits"
    run("correlate", t["both"], "--frames", 0, 1, *SETTINGS, "-o", out)
    with fits.open(out, checksum=True) as hdul:
        assert [h.name for h in hdul] == ["PRIMARY", "XI", "COV", "STATS", "HIST_DE", "THETA_DE", "PATCHES"]
        cov = hdul["COV"].data
        assert cov.shape == (16, 16)
        np.testing.assert_allclose(cov, cov.T, rtol=1e-12, atol=0)
        assert np.all(np.diag(cov) > 0)
        assert hdul["COV"].header["ORDER"] == "xip,xim"
        np.testing.assert_allclose(np.sqrt(np.diag(cov)[:8]), hdul["XI"].data["sigma_xip"], rtol=1e-12)
        np.testing.assert_allclose(np.sqrt(np.diag(cov)[8:]), hdul["XI"].data["sigma_xim"], rtol=1e-12)
        head = hdul[0].header
        assert head["CREATOR"].startswith("perscli") and head["SEED"] == 3 and head["NPATCH"] == 4
        assert head["SHAPES"] == "both.fits" and "SHAPESDS" in head and head["FRAMEA"] == 0
        # per-frame SHAPES tables (no GAXES/GFRAME keyword) are in pixel axes
        assert head["GFRAME"] == "pixel" and head["NOBJ"] == 2000
        assert head["VARMETHD"] == "jackknife" and head["VARASKED"] == "auto" and "VARWHY" not in head
        assert len(hdul["PATCHES"].data) == 4 and hdul["PATCHES"].data["nobj"].sum() == 2000
    # the patch centres can be reused: the same patches, the same pairs
    out2 = t["tmp"] / "reuse.fits"
    run("correlate", t["both"], "--frames", 0, 1, "--patch-centers", out, "--seed", 3, "--min-sep", 1, "--max-sep", 30,
        "--nbins", 8, "-o", out2)
    with fits.open(out) as h1, fits.open(out2) as h2:
        np.testing.assert_allclose(h2["COV"].data, h1["COV"].data, rtol=1e-10)
        np.testing.assert_array_equal(h2["XI"].data["npairs"], h1["XI"].data["npairs"])


def test_stats_tables(two_frames):
    t = two_frames
    out = t["tmp"] / "stats.fits"
    run("correlate", t["both"], "--frames", 0, 1, *SETTINGS, "--thresholds", "1e-8,1e-5,1e-4", "-o", out)
    absde = np.hypot(t["de1"], t["de2"])
    with fits.open(out) as hdul:
        s = hdul["STATS"].data[0]
        assert s["n"] == 2000
        np.testing.assert_allclose(s["e1_mean"], t["g1b"].mean(), rtol=1e-12)
        np.testing.assert_allclose(s["de1_mean"], t["de1"].mean(), rtol=1e-6)
        np.testing.assert_allclose(s["de2_err"], t["de2"].std(ddof=1) / np.sqrt(2000), rtol=1e-4)
        np.testing.assert_allclose(s["threshold"], [1e-8, 1e-5, 1e-4])
        np.testing.assert_allclose(s["frac_ge"], [np.mean(absde >= x) for x in (1e-8, 1e-5, 1e-4)], atol=1e-3)
        hist = hdul["HIST_DE"].data
        assert hist["count"].sum() == 2000 and hist["de_lo"][0] == 0 and np.isinf(hist["de_hi"][-1])
        theta = hdul["THETA_DE"].data
        assert len(theta) == 4 * 18 and hdul["THETA_DE"].header["NBOOT"] == 200
        for lo in np.unique(theta["de_lo"]):
            sel = theta["de_lo"] == lo
            if theta["n"][sel][0]:
                np.testing.assert_allclose(theta["frac"][sel].sum(), 1.0, rtol=1e-12)


def test_de_statistics_known_values():
    n = 1000
    de1, de2 = np.zeros(n), np.zeros(n)
    de1[:10] = 1e-3
    de2[10:15] = -2e-6
    s = de_statistics(de1, de2, e1=np.full(n, 0.1), e2=np.full(n, -0.2), thresholds=(1e-4, 1e-8))
    assert s["n"] == n
    np.testing.assert_allclose(s["threshold"], [1e-8, 1e-4])
    np.testing.assert_array_equal(s["n_ge"], [15, 10])
    np.testing.assert_allclose(s["frac_ge"], [0.015, 0.010])
    np.testing.assert_allclose([s["de1_mean"], s["de2_mean"]], [1e-5, -1e-8])
    np.testing.assert_allclose([s["e1_mean"], s["e2_mean"]], [0.1, -0.2])
    assert np.isnan(de_statistics(de1, de2)["e1_mean"])
    hist = de_histogram(np.hypot(de1, de2))
    assert hist["count"][0] == 985 and hist["count"].sum() == n
    k = np.flatnonzero((hist["de_lo"] <= 1e-3) & (hist["de_hi"] > 1e-3))
    assert hist["count"][k] == 10


def test_theta_distribution_uniform_and_aligned():
    rng = np.random.default_rng(4)
    n = 20000
    amp = 10 ** rng.uniform(-7, -3, n)
    angle = rng.uniform(-np.pi / 2, np.pi / 2, n)
    uni = theta_distribution(amp * np.cos(2 * angle), amp * np.sin(2 * angle), nboot=200, seed=1)
    full = uni["n"] > 0
    assert np.all(np.abs(uni["frac"][full] - 1 / 18) < 5 * uni["frac_err"][full])
    chi2 = np.unique(uni["chi2_uniform"][full])
    assert np.all(chi2 < 17 + 5 * np.sqrt(2 * 17))
    # all at +45 degrees: everything in that angle bin
    aligned = theta_distribution(np.zeros(100), np.full(100, 1e-5), nboot=50, seed=1)
    sel = aligned["n"] > 0
    hit = (aligned["theta_lo"] <= 45) & (aligned["theta_hi"] > 45) & sel
    assert aligned["frac"][hit][0] == 1.0 and np.all(aligned["frac"][sel & ~hit] == 0)
    # resampling random groups of objects gives the errors of resampling the objects themselves
    d1, d2 = amp * np.cos(2 * angle), amp * np.sin(2 * angle)
    exact = theta_distribution(d1, d2, edges=(1e-7, 1e-3), nboot=400, seed=2, max_groups=n)
    grouped = theta_distribution(d1, d2, edges=(1e-7, 1e-3), nboot=400, seed=2, max_groups=500)
    np.testing.assert_allclose(grouped["frac_err"], exact["frac_err"], rtol=0.3)


def coherent_catalog(path, *, shuffle, seed=5):
    """A De field coherent over ~20 arcmin plus noise; shuffled among positions, or not.

    The pattern's mean is taken out: a mean De survives shuffling and is itself a
    (scale-independent) xi+ signal.
    """
    rng = np.random.default_rng(seed)
    n = 6000
    ra, dec = sky(n, rng, 1.5)
    x = (ra - RA0) * np.cos(np.radians(DEC0)) * 60
    y = (dec - DEC0) * 60
    phase = 0.5 * np.pi * (np.sin(2 * np.pi * x / 40) + np.cos(2 * np.pi * y / 55))
    p1, p2 = np.cos(2 * phase), np.sin(2 * phase)
    de1 = 1e-5 * (p1 - p1.mean()) + rng.normal(0, 1e-5, n)
    de2 = 1e-5 * (p2 - p2.mean()) + rng.normal(0, 1e-5, n)
    if shuffle:
        order = rng.permutation(n)
        de1, de2 = de1[order], de2[order]
    return write_table(path, dict(id=np.arange(n), ra=ra, dec=dec, de1=de1, de2=de2))


def test_coherent_pattern_is_significant_and_shuffled_is_not(tmp_path):
    z = {}
    for shuffle in (False, True):
        cat = coherent_catalog(tmp_path / f"cat{shuffle}.fits", shuffle=shuffle)
        out = tmp_path / f"xi{shuffle}.fits"
        run("correlate", cat, "--de1", "de1", "--de2", "de2", "--npatch", 10, "--min-sep", 1, "--max-sep", 10,
            "--nbins", 6, "-o", out)
        with fits.open(out) as hdul:
            xi = hdul["XI"].data
            z[shuffle] = xi["xip"] / xi["sigma_xip"]
    # over 30 seeds of this recipe: max xip/sigma 25-67 coherent; max |xip/sigma| 0.7-3.5 shuffled (4.6 once:
    # a 9-patch jackknife variance has few degrees of freedom)
    assert np.max(z[False]) > 5, z[False]
    assert np.max(np.abs(z[True])) < 4, z[True]


def test_xy_positions_and_figures(two_frames, tmp_path):
    t = two_frames
    out = tmp_path / "xy.fits"
    run("correlate", t["both"], "--frames", 0, 1, "--positions", "xy", "--npatch", 4, "--min-sep", 0.5, "--max-sep", 5,
        "--nbins", 5, "--plots", tmp_path / "figs", "--plot", tmp_path / "xi_alone.png", "-o", out)
    with fits.open(out) as hdul:
        assert hdul[0].header["COORDS"] == "xy" and hdul[0].header["PIXSCALE"] == 0.11
        assert np.all(hdul["XI"].data["npairs"] > 0)
    for name in ("xi.png", "hist_de.png", "bin_theta.png"):
        assert (tmp_path / "figs" / name).read_bytes()[:4] == b"\x89PNG"
    assert (tmp_path / "xi_alone.png").stat().st_size > 1000
    assert not [p for p in os.listdir(tmp_path / "figs") if p.startswith(".")]
    # figures are outputs too: not replaced without --overwrite
    result = run("correlate", t["both"], "--frames", 0, 1, "--plots", tmp_path / "figs", "-o", tmp_path / "other.fits",
                 code=1)
    assert "--overwrite" in result.output and not (tmp_path / "other.fits").exists()


def test_fits_to_stdout(two_frames):
    t = two_frames
    result = invoke("correlate", t["de"], "--de1", "de1", "--de2", "de2", *SETTINGS, "-o", "-")
    assert result.exit_code == 0, result.output
    assert result.stdout_bytes[:9] == b"SIMPLE  ="


# ---- bad input: one line, exit 1, no output ------------------------------------------------------


#: ``expect_error(tmp_path, ARGS, *needles)``: ``perscli correlate --npatch 4 ARGS -o OUT`` fails in one line
#: holding every needle, and writes nothing (:func:`fits_factory.expect_error`)
expect_error = partial(fits_factory.expect_error, command=("correlate", "--npatch", 4))


def test_mismatched_ids(tmp_path):
    table, *_ = shapes_frames(n=200, ids_b=np.arange(101, 301))
    a = write_table(tmp_path / "a.fits", split(table, 0))
    b = write_table(tmp_path / "b.fits", split(table, 1))
    expect_error(tmp_path, [a, b], "ids do not match", "100 of", "--common-ids")
    # --common-ids correlates the 100 shared ids
    out = tmp_path / "common.fits"
    run("correlate", a, b, "--common-ids", "--npatch", 4, "--min-sep", 1, "--max-sep", 30, "--nbins", 4, "-o", out)
    with fits.open(out) as hdul:
        assert hdul["STATS"].data["n"][0] == 100 and hdul["STATS"].data["matched"][0] == 100


def test_no_overlap(tmp_path):
    table, *_ = shapes_frames(n=100, ids_b=np.arange(1001, 1101))
    a = write_table(tmp_path / "a.fits", split(table, 0))
    b = write_table(tmp_path / "b.fits", split(table, 1))
    expect_error(tmp_path, [a, b], "no id in common")


def test_duplicate_ids(tmp_path):
    ids = np.arange(1, 101)
    ids[5] = 3
    table, *_ = shapes_frames(n=100, ids_b=ids)
    both = write_table(tmp_path / "both.fits", table)
    expect_error(tmp_path, [both, "--frames", 0, 1], "id 3 appears more than once")


def test_all_flagged(tmp_path):
    table, *_ = shapes_frames(n=100, flags_a=np.r_[np.ones(50, int), np.zeros(50, int)],
                              flags_b=np.r_[np.zeros(50, int), np.full(50, 512)])
    both = write_table(tmp_path / "both.fits", table)
    expect_error(tmp_path, [both, "--frames", 0, 1], "all 100 matched objects are flagged")


def test_nan_column(tmp_path):
    rng = np.random.default_rng(1)
    ra, dec = sky(100, rng)
    cat = write_table(tmp_path / "de.fits", dict(id=np.arange(100), ra=ra, dec=dec, de1=np.full(100, np.nan),
                                                 de2=rng.normal(0, 1e-5, 100)))
    expect_error(tmp_path, [cat, "--de1", "de1", "--de2", "de2"], "column 'de1' is NaN")
    # a few NaN values are dropped with a warning, not an error
    table, *_ = shapes_frames(n=200)
    table["g1"][3] = np.nan
    both = write_table(tmp_path / "some_nan.fits", table)
    out = tmp_path / "ok.fits"
    run("correlate", both, "--frames", 0, 1, "--npatch", 4, "-o", out)
    with fits.open(out) as hdul:
        assert hdul["STATS"].data["n"][0] == 199 and hdul["STATS"].data["nonfinite"][0] == 1


def test_too_few_objects_for_patches(tmp_path):
    # asking for the jackknife insists on it (by default, shot noise takes over: test_correlate_few.py)
    table, *_ = shapes_frames(n=30)
    both = write_table(tmp_path / "both.fits", table)
    expect_error(tmp_path, [both, "--frames", 0, 1, "--var-method", "jackknife"],
                 "only 30 objects for 4 jackknife patches", "--npatch 3")


def test_missing_column_and_frame(tmp_path, two_frames):
    expect_error(tmp_path, [two_frames["de"], "--de1", "e1", "--de2", "de2"], "no column 'e1'")
    expect_error(tmp_path, [two_frames["both"], "--frames", 0, 2], "no rows of frame 2")
    expect_error(tmp_path, [two_frames["both"], two_frames["b"]], "holds frames 0, 1", "--frames")
    (tmp_path / "junk.fits").write_bytes(b"not a fits file at all\n" * 200)
    expect_error(tmp_path, [tmp_path / "junk.fits", "--de1", "a", "--de2", "b"], "junk.fits")


def test_usage_errors(two_frames, tmp_path):
    out = tmp_path / "xi.fits"
    for args in ([two_frames["both"]], [two_frames["both"], "--de1", "de1"],
                 [two_frames["a"], two_frames["b"], "--de1", "a", "--de2", "b"],
                 [two_frames["both"], "--frames", 0, 1, "--min-sep", 10, "--max-sep", 5],
                 [two_frames["both"], "--frames", 0, 1, "--patch-centers", two_frames["both"], "--npatch", 5]):
        run("correlate", *args, "-o", out, code=2)
    assert not out.exists()


def test_existing_output_needs_overwrite(two_frames, tmp_path):
    out = tmp_path / "xi.fits"
    out.write_bytes(b"keep")
    result = run("correlate", two_frames["de"], "--de1", "de1", "--de2", "de2", "-o", out, code=1)
    assert "--overwrite" in result.output and out.read_bytes() == b"keep"


def test_corrupt_table_and_stdin(two_frames, tmp_path):
    # a table whose data no longer match its DATASUM
    good = fits.getdata(two_frames["de"], 1)
    path = tmp_path / "sum.fits"
    fits.HDUList([fits.PrimaryHDU(), fits.BinTableHDU(good, name="SHAPES")]).writeto(path, checksum=True)
    raw = bytearray(path.read_bytes())
    raw[2880 * 3 + 100] ^= 0x40
    path.write_bytes(bytes(raw))
    expect_error(tmp_path, [path, "--de1", "de1", "--de2", "de2"], "do not match their DATASUM")
    # standard input gives what the file gives
    ref_path = tmp_path / "file.fits"
    run("correlate", two_frames["de"], "--de1", "de1", "--de2", "de2", *SETTINGS, "-o", ref_path)
    out = tmp_path / "stdin.fits"
    result = invoke("correlate", "-", "--de1", "de1", "--de2", "de2", *SETTINGS, "-o", out,
                    input=open(two_frames["de"], "rb").read())
    assert result.exit_code == 0, result.output
    with fits.open(out) as hdul, fits.open(ref_path) as ref:
        assert hdul[0].header["SHAPES"] == "stdin"
        # TreeCorr's threads sum in varying order: equal to rounding
        np.testing.assert_allclose(hdul["XI"].data["xip"], ref["XI"].data["xip"], rtol=1e-10, atol=0)


def test_xi_plus_does_not_depend_on_the_axes_of_de(tmp_path):
    """A rotation (or a reflection) of De's axes common to the catalogue leaves xi+ alone; xi- rotates."""
    rng = np.random.default_rng(7)
    n = 3000
    ra, dec = sky(n, rng)
    phase = 0.5 * np.pi * np.sin(2 * np.pi * (ra - RA0) * 60 / 30)
    de = 1e-5 * np.exp(2j * phase) + 1e-6 * (rng.normal(size=n) + 1j * rng.normal(size=n))
    phi = np.radians(25.0)
    xi = {}
    for name, values in (("given", de), ("rotated", de * np.exp(2j * phi)), ("reflected", np.conj(de))):
        cat = write_table(tmp_path / f"{name}.fits", dict(id=np.arange(n), ra=ra, dec=dec, de1=values.real,
                                                          de2=values.imag))
        out = tmp_path / f"xi_{name}.fits"
        run("correlate", cat, "--de1", "de1", "--de2", "de2", "--npatch", 4, "--min-sep", 1, "--max-sep", 20,
            "--nbins", 5, "-o", out)
        with fits.open(out) as hdul:
            xi[name] = {k: np.array(hdul["XI"].data[k]) for k in ("xip", "xim", "xim_im")}
    # a rotation: to 1e-6 (TreeCorr's cell approximations leave ~1e-8); a reflection: only to the
    # parallel transport between the two objects' local frames on the sphere (here < 1 %)
    np.testing.assert_allclose(xi["rotated"]["xip"], xi["given"]["xip"], rtol=1e-6)
    np.testing.assert_allclose(xi["reflected"]["xip"], xi["given"]["xip"], rtol=1e-2)
    xim = xi["given"]["xim"] + 1j * xi["given"]["xim_im"]
    np.testing.assert_allclose(xi["rotated"]["xim"] + 1j * xi["rotated"]["xim_im"], xim * np.exp(4j * phi),
                               rtol=1e-6, atol=1e-6 * np.abs(xim).max())
    assert not np.allclose(xi["rotated"]["xim"], xi["given"]["xim"], rtol=1e-3, atol=0)
