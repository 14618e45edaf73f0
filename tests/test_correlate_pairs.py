"""perscli correlate with many pairs pooled: --pair, --pairs FILE, correlate_files(pairs=...), joint fits."""

import os
import time

import numpy as np
import pytest
from astropy.io import fits

from fits_factory import invoke, one_line_error, run
from perscli import PerscliError
from perscli.stats.correlate import correlate_files
from perscli.stats.pairs import load_pairs, read_pairs_file
from perscli.stats.settings import CorrelateOptions

treecorr = pytest.importorskip("treecorr")

RA0, DEC0 = 10.0, -44.0
SETTINGS = ["--npatch", 4, "--seed", 3, "--min-sep", 1, "--max-sep", 30, "--nbins", 8]


def shapes_table(path, ids, ra, dec, g1, g2, *, flags=None, x=None, y=None, header=None, frame=None):
    """A SHAPES-like table: id, [frame], [x, y], ra, dec, g1, g2, flags; ``header`` cards on the table HDU."""
    cols = [fits.Column("id", "K", array=np.asarray(ids))]
    if frame is not None:
        cols.append(fits.Column("frame", "I", array=np.full(len(ids), frame)))
    if x is not None:
        cols += [fits.Column("x", "D", array=x, unit="pix"), fits.Column("y", "D", array=y, unit="pix")]
    cols += [fits.Column("ra", "D", array=ra, unit="deg"), fits.Column("dec", "D", array=dec, unit="deg"),
             fits.Column("g1", "D", array=g1), fits.Column("g2", "D", array=g2),
             fits.Column("flags", "K", array=np.zeros(len(ids), int) if flags is None else flags)]
    hdu = fits.BinTableHDU.from_columns(cols, name="SHAPES")
    for key, value in (header or {}).items():
        hdu.header[key] = value
    fits.HDUList([fits.PrimaryHDU(), hdu]).writeto(path)
    return str(path)


def make_pair(folder, k, n=600, *, seed=None, ids=None, ra=None, dec=None, header=None, xy_angle=None,
              frame=None, mirror=False):
    """Tables A (with persistence) and B (reference) of one exposure; returns (a, b, de1, de2, ra, dec, g1b, g2b)."""
    rng = np.random.default_rng(100 + k if seed is None else seed)
    if ra is None:
        dec = DEC0 + rng.uniform(-0.5, 0.5, n)
        ra = RA0 + rng.uniform(-0.5, 0.5, n) / np.cos(np.radians(DEC0))
    n = len(ra)
    ids = np.arange(1, n + 1) if ids is None else ids
    g1b, g2b = rng.normal(0, 0.27, n), rng.normal(0, 0.27, n)
    # shapes have |g| < 1 (correlate refuses others): the rare draws beyond 0.9 are pulled in to it
    shrink = np.minimum(1.0, 0.9 / np.hypot(g1b, g2b))
    g1b, g2b = g1b * shrink, g2b * shrink
    de1, de2 = rng.normal(0, 1e-5, n), rng.normal(0, 1e-5, n)
    x = y = None
    if xy_angle is not None:
        # pixel axes rotated by xy_angle from (east, north), 0.11"/pix
        east = (ra - RA0) * np.cos(np.radians(DEC0)) * 3600 / 0.11
        north = (dec - DEC0) * 3600 / 0.11
        c, s = np.cos(np.radians(xy_angle)), np.sin(np.radians(xy_angle))
        x, y = c * east + s * north + 2000, -s * east + c * north + 2000
        if mirror:
            y = 4000 - y
    a = shapes_table(folder / f"a{k}.fits", ids, ra, dec, g1b + de1, g2b + de2, x=x, y=y, header=header,
                     frame=frame)
    b = shapes_table(folder / f"b{k}.fits", ids, ra, dec, g1b, g2b, x=x, y=y, header=header, frame=frame)
    return a, b, de1, de2, ra, dec, g1b, g2b


@pytest.fixture(scope="module")
def three(tmp_path_factory):
    folder = tmp_path_factory.mktemp("pairs")
    return folder, [make_pair(folder, k) for k in range(3)]


def test_pooled_pairs_equal_treecorr_on_the_concatenated_catalogue(three):
    folder, pairs = three
    out = folder / "pooled.fits"
    args = [a for p in pairs for a in ("--pair", p[0], p[1])]
    run("correlate", *args, *SETTINGS, "-o", out)
    # De and positions concatenated in pair order: TreeCorr on the same arrays, same seed, same patches
    cat = treecorr.Catalog(ra=np.concatenate([p[4] for p in pairs]), dec=np.concatenate([p[5] for p in pairs]),
                           ra_units="deg", dec_units="deg", g1=np.concatenate([(p[6] + p[2]) - p[6] for p in pairs]),
                           g2=np.concatenate([(p[7] + p[3]) - p[7] for p in pairs]), npatch=4,
                           rng=np.random.default_rng(3))
    gg = treecorr.GGCorrelation(min_sep=1, max_sep=30, nbins=8, sep_units="arcmin", var_method="jackknife",
                                cross_patch_weight="match")
    gg.process(cat)
    with fits.open(out, checksum=True) as hdul:
        assert [h.name for h in hdul] == ["PRIMARY", "XI", "COV", "STATS", "HIST_DE", "THETA_DE", "PATCHES",
                                          "PAIRS"]
        np.testing.assert_allclose(hdul["XI"].data["xip"], gg.xip, rtol=1e-9, atol=0)
        np.testing.assert_allclose(hdul["XI"].data["xim"], gg.xim, rtol=1e-9, atol=0)
        np.testing.assert_allclose(hdul["COV"].data, gg.cov, rtol=1e-9, atol=0)
        head = hdul[0].header
        assert head["NPAIRS"] == 3 and head["NOBJ"] == 1800 and head["DEMODE"] == "pairs"
        assert head["A001"] == "a0.fits" and head["B003"] == "b2.fits" and "A002DS" in head
        assert head["GFRAME"] == "pixel" and head["VARMETHD"] == "jackknife" and head["NPATCH"] == 4
        assert hdul["STATS"].data["n"][0] == 1800 and hdul["STATS"].data["matched"][0] == 1800
        assert hdul["STATS"].header["NPAIRS"] == 3
        np.testing.assert_allclose(hdul["STATS"].data["de1_mean"][0], np.concatenate([p[2] for p in pairs]).mean(),
                                   rtol=1e-6)
        table = hdul["PAIRS"].data
        assert list(table["pair"]) == [1, 2, 3] and list(table["a"]) == ["a0.fits", "a1.fits", "a2.fits"]
        assert list(table["used"]) == [600, 600, 600]
        assert str(table["a_datasum"][1]) == head["A002DS"]
        np.testing.assert_allclose(table["de1_mean"], [p[2].mean() for p in pairs], rtol=1e-6)


def test_pairs_file_is_the_same_as_pair_options(three, tmp_path, monkeypatch):
    folder, pairs = three
    listing = folder / "pairs.txt"
    # names relative to the file's folder, comments and blank lines
    listing.write_text("# final  reference\n" + "".join(
        f"{os.path.basename(p[0])} {os.path.basename(p[1])}  # exposure {k}\n\n" for k, p in enumerate(pairs)))
    assert read_pairs_file(str(listing)) == [(p[0], p[1]) for p in pairs]
    monkeypatch.chdir(tmp_path)                     # elsewhere: names still found beside the list
    run("correlate", "--pairs", listing, *SETTINGS, "-o", tmp_path / "file.fits")
    args = [a for p in pairs for a in ("--pair", p[0], p[1])]
    run("correlate", *args, *SETTINGS, "-o", tmp_path / "options.fits")
    # --pair and --pairs add up: two from the options, one from a file
    part = tmp_path / "one.txt"
    part.write_text(f"{pairs[2][0]} {pairs[2][1]}\n")
    run("correlate", "--pair", pairs[0][0], pairs[0][1], "--pair", pairs[1][0], pairs[1][1], "--pairs", part, *SETTINGS,
        "-o", tmp_path / "both.fits")
    with fits.open(tmp_path / "file.fits") as f1, fits.open(tmp_path / "options.fits") as f2, \
            fits.open(tmp_path / "both.fits") as f3:
        for other in (f2, f3):
            np.testing.assert_allclose(other["XI"].data["xip"], f1["XI"].data["xip"], rtol=1e-10, atol=0)
            np.testing.assert_array_equal(other["XI"].data["npairs"], f1["XI"].data["npairs"])


def test_library_call_with_pairs_and_a_pairs_file(three, tmp_path):
    folder, pairs = three
    options = CorrelateOptions(npatch=4, seed=3, min_sep=1, max_sep=30, nbins=8)
    summary = correlate_files([], str(tmp_path / "lib.fits"), options, pairs=[(p[0], p[1]) for p in pairs])
    assert summary["n"] == 1800 and summary["npairs"] == 3 and summary["var_method"] == "jackknife"
    assert summary["var_reason"] == "" and summary["npatch"] == 4
    assert [row["dof"] for row in summary["theta"]] == [17] * 4
    listing = tmp_path / "pairs.txt"
    listing.write_text("".join(f"{p[0]} {p[1]}\n" for p in pairs))          # absolute names
    again = correlate_files([], str(tmp_path / "lib2.fits"), options, pairs=str(listing))
    np.testing.assert_allclose(again["xi"]["xip"], summary["xi"]["xip"], rtol=1e-10, atol=0)
    with pytest.raises(PerscliError, match="not both"):
        correlate_files([pairs[0][0]], str(tmp_path / "x.fits"), pairs=[(pairs[1][0], pairs[1][1])])
    with pytest.raises(PerscliError, match="is not two file names"):
        correlate_files([], str(tmp_path / "x.fits"), pairs=["ab"])
    with pytest.raises(PerscliError, match="no pairs given"):
        correlate_files([], str(tmp_path / "x.fits"), pairs=[])
    # a pairs file gets the same checks as a list
    listing.write_text(f"{pairs[0][0]} {pairs[0][1]}\n{pairs[0][0]} {pairs[0][1]}\n")
    with pytest.raises(PerscliError, match="pair 2 repeats pair 1"):
        load_pairs(str(listing))


def test_one_pair_equals_two_positional_tables(three, tmp_path):
    _, pairs = three
    run("correlate", pairs[0][0], pairs[0][1], *SETTINGS, "-o", tmp_path / "positional.fits")
    run("correlate", "--pair", pairs[0][0], pairs[0][1], *SETTINGS, "-o", tmp_path / "pair.fits")
    with fits.open(tmp_path / "positional.fits") as h1, fits.open(tmp_path / "pair.fits") as h2:
        np.testing.assert_allclose(h2["XI"].data["xip"], h1["XI"].data["xip"], rtol=1e-10, atol=0)
        np.testing.assert_allclose(h2["COV"].data, h1["COV"].data, rtol=1e-10, atol=0)
        assert h2[0].header["NPAIRS"] == 1 and len(h2["PAIRS"].data) == 1


def test_an_object_in_several_pairs_appears_once_per_pair(tmp_path):
    # two final exposures of the same 500 galaxies: 1000 entries, 500 distinct ids
    rng = np.random.default_rng(8)
    n = 500
    dec = DEC0 + rng.uniform(-0.4, 0.4, n)
    ra = RA0 + rng.uniform(-0.4, 0.4, n) / np.cos(np.radians(DEC0))
    p1 = make_pair(tmp_path, 1, ra=ra, dec=dec, seed=1)
    p2 = make_pair(tmp_path, 2, ra=ra, dec=dec, seed=2)
    out = tmp_path / "xi.fits"
    run("correlate", "--pair", p1[0], p1[1], "--pair", p2[0], p2[1], *SETTINGS, "-o", out)
    with fits.open(out) as hdul:
        assert hdul[0].header["NOBJ"] == 2 * n and hdul[0].header["NIDS"] == n
        assert hdul["STATS"].data["n"][0] == 2 * n
        assert hdul["HIST_DE"].data["count"].sum() == 2 * n
        assert hdul["THETA_DE"].data["n"][::18].sum() == np.sum(
            (np.hypot(np.r_[p1[2], p2[2]], np.r_[p1[3], p2[3]]) >= 1e-8))


def test_joint_fit_tables_in_sky_axes(tmp_path):
    # one row per galaxy, no frame column, the header saying g is in sky axes
    sky = {"GAXES": "sky"}
    pairs = [make_pair(tmp_path, k, n=400, header=sky) for k in range(2)]
    out = tmp_path / "joint.fits"
    run("correlate", "--pair", pairs[0][0], pairs[0][1], "--pair", pairs[1][0], pairs[1][1], *SETTINGS, "-o", out)
    with fits.open(out) as hdul:
        assert hdul[0].header["GFRAME"] == "sky" and hdul["PAIRS"].header["GFRAME"] == "sky"
        assert any("sky axes" in str(c) for c in hdul[0].header["COMMENT"])
    # GFRAME is read as well as GAXES, from the primary header too (perscli measure --joint writes
    # GAXES = 'sky: u=West, v=North' there, and GAXES = 'pixel' for per-frame fits)
    for key, value, axes in (("GFRAME", "sky (joint fit)", "sky"), ("GAXES", "sky: u=West, v=North", "sky"),
                             ("GAXES", "pixel", "pixel")):
        moved = []
        for k, path in enumerate(pairs[0][:2]):
            moved.append(tmp_path / f"primary_{key}_{axes}_{k}.fits")
            with fits.open(path) as hdul:
                del hdul[1].header["GAXES"]
                hdul[0].header[key] = value
                hdul.writeto(moved[-1])
        run("correlate", "--pair", *moved, *SETTINGS, "-o", tmp_path / f"primary_{key}_{axes}.fits")
        with fits.open(tmp_path / f"primary_{key}_{axes}.fits") as hdul:
            assert hdul[0].header["GFRAME"] == axes
    # A in sky axes, B in pixel axes: refused
    plain = make_pair(tmp_path, 7, n=400)
    one_line_error(invoke("correlate", pairs[0][0], plain[1], "--common-ids", *SETTINGS, "-o", tmp_path / "x.fits"),
                   "sky axes", "pixel axes", "same axes")
    # pairs in sky axes and pairs in pixel axes: refused
    one_line_error(invoke("correlate", "--pair", pairs[0][0], pairs[0][1], "--pair", plain[0], plain[1], *SETTINGS,
                          "-o", tmp_path / "x.fits"), "pairs mix g in sky axes (e.g. pair 1)", "pair 2")
    assert not (tmp_path / "x.fits").exists()


def test_joint_tables_with_a_frame_column_of_one_value(tmp_path):
    pairs = [make_pair(tmp_path, k, n=300, frame=-1, header={"GAXES": "sky"}) for k in range(2)]
    run("correlate", "--pair", pairs[0][0], pairs[0][1], "--pair", pairs[1][0], pairs[1][1], *SETTINGS, "-o",
        tmp_path / "xi.fits")


def test_orientation_of_pixel_axes_is_checked(tmp_path):
    same = [make_pair(tmp_path, k, n=300, xy_angle=30.0) for k in range(2)]
    run("correlate", "--pair", same[0][0], same[0][1], "--pair", same[1][0], same[1][1], *SETTINGS, "-o",
        tmp_path / "same.fits")
    # a half turn is the same orientation for a spin-2 quantity
    half = make_pair(tmp_path, 5, n=300, xy_angle=210.0)
    result = run("correlate", "--pair", same[0][0], same[0][1], "--pair", half[0], half[1], *SETTINGS, "-o",
                 tmp_path / "half.fits")
    assert "orientation" not in result.stderr
    turned = make_pair(tmp_path, 6, n=300, xy_angle=45.0)
    result = run("correlate", "--pair", same[0][0], same[0][1], "--pair", turned[0], turned[1], *SETTINGS, "-o",
                 tmp_path / "turned.fits")
    assert "differ in orientation on the sky by up to 15 deg" in result.stderr
    flipped = make_pair(tmp_path, 8, n=300, xy_angle=30.0, mirror=True)
    result = run("correlate", "--pair", same[0][0], same[0][1], "--pair", flipped[0], flipped[1], *SETTINGS, "-o",
                 tmp_path / "flip.fits")
    assert "are mirrored with respect to pair 1 (pair 2)" in result.stderr
    sc = load_pairs([(same[0][0], same[0][1]), (turned[0], turned[1])])
    assert sc.pairs[1]["used"] == 300 and len(sc) == 600 and list(np.unique(sc.pair)) == [0, 1]


def test_pair_errors_are_one_line(three, tmp_path):
    folder, pairs = three
    out = tmp_path / "xi.fits"
    p0 = ("--pair", pairs[0][0], pairs[0][1])
    # a broken table in the second pair: the message says which pair
    junk = tmp_path / "junk.fits"
    junk.write_bytes(b"not a fits file at all\n" * 200)
    one_line_error(invoke("correlate", *p0, "--pair", junk, pairs[1][1], "-o", out), "pair 2 of 2", "junk.fits")
    one_line_error(invoke("correlate", *p0, *p0, "-o", out), "pair 2 repeats pair 1")
    one_line_error(invoke("correlate", "--pair", pairs[0][0], pairs[0][0], "-o", out), "A and B are the same file")
    one_line_error(invoke("correlate", *p0, "--pair", pairs[1][0], pairs[1][1], "--positions", "xy", "-o", out),
                   "--positions xy with 2 pairs")
    # pooled pairs need ra/dec
    rng = np.random.default_rng(1)
    xy = [shapes_table(tmp_path / f"xy{k}.fits", np.arange(50), rng.uniform(0, 1, 50), rng.uniform(0, 1, 50),
                       rng.normal(0, .2, 50), rng.normal(0, .2, 50)) for k in range(2)]
    for k in range(2):
        with fits.open(xy[k]) as hdul:
            cols = [c for c in hdul[1].columns if c.name not in ("ra", "dec")]
            cols += [fits.Column("x", "D", array=rng.uniform(0, 4000, 50)),
                     fits.Column("y", "D", array=rng.uniform(0, 4000, 50))]
            fits.BinTableHDU.from_columns(cols, name="SHAPES").writeto(tmp_path / f"xyonly{k}.fits")
    one_line_error(invoke("correlate", *p0, "--pair", tmp_path / "xyonly0.fits", tmp_path / "xyonly1.fits", "-o", out),
                   "pair 2 of 2", "no ra/dec columns", "pooled pairs are placed by ra/dec")
    # pairs files
    one_line_error(invoke("correlate", "--pairs", tmp_path / "absent.txt", "-o", out), "absent.txt", "no such file")
    bad = tmp_path / "three.txt"
    bad.write_text(f"{pairs[0][0]} {pairs[0][1]}\n{pairs[1][0]} {pairs[1][1]} extra.fits\n")
    one_line_error(invoke("correlate", "--pairs", bad, "-o", out), "three.txt: line 2 has 3 name(s)")
    empty = tmp_path / "empty.txt"
    empty.write_text("# nothing\n\n")
    one_line_error(invoke("correlate", "--pairs", empty, "-o", out), "lists no pair")
    one_line_error(invoke("correlate", "--pairs", pairs[0][0], "-o", out), "is a FITS file, not a list of pairs")
    # an output may not replace an input of any pair, nor the pairs file
    listing = tmp_path / "list.txt"
    listing.write_text(f"{pairs[0][0]} {pairs[0][1]}\n")
    one_line_error(invoke("correlate", *p0, "--pair", pairs[1][0], pairs[1][1], "-o", pairs[1][1], "--overwrite"))
    # -o naming the pairs list: its name says text, not FITS (a usage error); a list without a suffix is "also an
    # input"; either way the list is untouched
    one_line_error(invoke("correlate", "--pairs", listing, "-o", listing, "--overwrite"), "writes FITS", code=2)
    bare = tmp_path / "pairs"
    bare.write_text(f"{pairs[0][0]} {pairs[0][1]}\n")
    one_line_error(invoke("correlate", "--pairs", bare, "-o", bare, "--overwrite"))
    assert bare.read_text().startswith(pairs[0][0])
    assert listing.read_text().startswith(pairs[0][0])
    assert not out.exists() and not [p for p in os.listdir(tmp_path) if p.startswith(".xi.fits")]


def test_a_pair_without_usable_objects_is_a_warning_among_many(three, tmp_path):
    _, pairs = three
    rng = np.random.default_rng(3)
    n = 200
    dec = DEC0 + rng.uniform(-0.5, 0.5, n)
    ra = RA0 + rng.uniform(-0.5, 0.5, n) / np.cos(np.radians(DEC0))
    g = rng.normal(0, 0.2, n)
    flagged = [shapes_table(tmp_path / f"flagged_{k}.fits", np.arange(n), ra, dec, g, g, flags=np.full(n, 2048))
               for k in "ab"]
    out = tmp_path / "xi.fits"
    result = run("correlate", "--pair", pairs[0][0], pairs[0][1], "--pair", *flagged, "--pair", pairs[1][0],
                 pairs[1][1], *SETTINGS, "-o", out)
    assert "pair 2 of 3 adds no object: all 200 matched objects are flagged" in result.stderr
    with fits.open(out) as hdul:
        table = hdul["PAIRS"].data
        assert list(table["used"]) == [600, 0, 600] and list(table["flagged"]) == [0, 200, 0]
        assert np.isnan(table["de1_mean"][1]) and table["a_datasum"][1] > 0
        assert hdul[0].header["A002"] == "flagged_a.fits" and hdul[0].header["NOBJ"] == 1200
        assert hdul["STATS"].data["flagged"][0] == 200 and hdul["STATS"].data["n"][0] == 1200
    # alone, or when no pair has an object, it is an error
    one_line_error(invoke("correlate", "--pair", *flagged, "-o", tmp_path / "x.fits"), "pair 1 of 1", "flagged")
    other = [shapes_table(tmp_path / f"flagged2_{k}.fits", np.arange(n), ra, dec, g, g, flags=np.ones(n, int))
             for k in "ab"]
    one_line_error(invoke("correlate", "--pair", *flagged, "--pair", *other, "-o", tmp_path / "x.fits"),
                   "none of the 2 pairs has an object to correlate", allow_warnings=True)


def test_pair_usage_errors(three, tmp_path):
    _, pairs = three
    out = tmp_path / "xi.fits"
    for args in ([pairs[0][0], "--pair", pairs[1][0], pairs[1][1]],
                 ["--pair", pairs[0][0], pairs[0][1], "--de1", "a", "--de2", "b"],
                 [],
                 [pairs[0][0], pairs[0][1], pairs[1][0]]):
        result = run("correlate", *args, "-o", out, code=2)
        assert "pair" in result.output.splitlines()[-1], result.output
    assert not out.exists()


def test_twenty_pairs_of_2000_stay_fast(tmp_path):
    pairs = []
    for k in range(20):
        a, b, *_ = make_pair(tmp_path, k, n=2000)
        pairs.append((a, b))
    start = time.perf_counter()
    summary = correlate_files([], str(tmp_path / "xi.fits"), CorrelateOptions(seed=1), pairs=pairs)
    elapsed = time.perf_counter() - start
    assert summary["n"] == 40_000 and summary["npatch"] == 20 and summary["var_method"] == "jackknife"
    # ~0.5 s on a 2-core VM (reading 40 tables, TreeCorr on 40k objects, the angle bootstrap)
    assert elapsed < 30, elapsed



def test_figures_are_readable_by_others_like_every_output(three, tmp_path):
    # mkstemp's 0600 must not leak into the figures (issue 11: correlate wrote PNGs with mode 0600)
    import os
    import stat

    out = tmp_path / "xi.fits"
    args = sum([["--pair", p[0], p[1]] for p in three[1]], [])
    old = os.umask(0o022)
    try:
        run("correlate", *args, "--plots", tmp_path / "figs", "--plot", tmp_path / "xi.png", "-o", out)
    finally:
        os.umask(old)
    for png in [tmp_path / "xi.png", *(tmp_path / "figs").glob("*.png")]:
        assert stat.S_IMODE(os.stat(png).st_mode) == 0o644, png
