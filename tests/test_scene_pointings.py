"""perscli.scene.pointings and ``perscli pointings``: selection from a real schedule, planned dithers,
the pointings table, and errors."""

import math
import os
import shutil
import subprocess
import sys
from functools import partial

import numpy as np
import pytest
from astropy.io import fits

from perscli import PerscliError
from perscli.scene.pointings import read_pointings, write_pointings
from perscli.scene.dithers import plan_dithers
from perscli.scene.footprints import sca_footprint
from perscli.scene.schedule import (Pointing, Schedule, previous_exposures, read_schedule, schedule_pointing,
                                    select_covering)

import fits_factory
from fits_factory import invoke, raw_cards_masked

RA, DEC = 10.0, -44.0
DAY = 86400.0


def distance(ra1, dec1, ra2, dec2):
    """Great-circle distance in degrees (haversine), independent of perscli.scene.separation."""
    a1, d1, a2, d2 = map(np.radians, (ra1, dec1, ra2, dec2))
    h = np.sin((d2 - d1) / 2) ** 2 + np.cos(d1) * np.cos(d2) * np.sin((a2 - a1) / 2) ** 2
    return np.degrees(2 * np.arcsin(np.sqrt(h)))


def schedule_file(path, rows=None, *, drop=None, text=None, extra=()):
    """A small schedule: rows of (date, exptime, ra, dec, pa, filter); ``text`` makes that column a string."""
    if rows is None:
        rows = [(60000.0 + i * 169.8 / DAY, 139.8, RA + 0.3 * (i % 4), DEC, 10.0 * i, f) for i, f in
                enumerate(["J129", "H158", "J129", "J129", "Y106", "J129", "J129", "F184"])]
    cols = []
    for k, (name, fmt) in enumerate([("date", "D"), ("exptime", "D"), ("ra", "D"), ("dec", "D"), ("pa", "D"),
                                     ("filter", "4A")]):
        values = [r[k] for r in rows]
        if name == text:
            cols.append(fits.Column(name, "8A", array=np.array([str(v)[:8] for v in values])))
        elif name != drop:
            cols.append(fits.Column(name, fmt, array=np.array(values)))
    cols.extend(extra)
    fits.HDUList([fits.PrimaryHDU(), fits.BinTableHDU.from_columns(cols)]).writeto(path)
    return str(path)


@pytest.fixture
def was(shared_data):
    """The real Roman Wide Area Survey schedule (skipped without ../shared/data)."""
    return str(shared_data / "roman" / "Roman_WAS_obseq_11_1_23.fits")


# -- selection from a real schedule ------------------------------------------------------------

def test_real_schedule_selection_around_the_gaia_field(was, tmp_path):
    out = tmp_path / "p.fits"
    result = invoke("pointings", "select", "--schedule", was, "--ra", RA, "--dec", DEC, "--radius", 1, "--filter", "J129",
                    "-o", out)
    assert result.exit_code == 0, result.output
    with fits.open(was) as hdul:
        sched = hdul[1].data
    with fits.open(out, checksum=True) as hdul:
        p, hdr = hdul["POINTINGS"].data, hdul["POINTINGS"].header
    assert 200 < len(p) < 400                              # 284 J129 exposures (NOTES.md: ~240)
    assert np.all(np.diff(p["mjd"]) > 0)                   # time order
    assert np.all(distance(RA, DEC, p["ra"], p["dec"]) <= 1.0)
    assert set(np.char.strip(p["filter"])) == {"J129"}
    assert np.all(p["sca"] == 0)
    # expid is the schedule row, and the row's values are copied
    rows = sched[p["expid"]]
    assert np.array_equal(rows["date"], p["mjd"]) and np.array_equal(rows["ra"], p["ra"])
    assert np.array_equal(rows["pa"], p["pa"]) and np.array_equal(rows["exptime"], p["exptime"])
    # nothing is missed: every J129 row within 1 degree is there
    near = (distance(RA, DEC, sched["ra"], sched["dec"]) <= 1.0) & (np.char.strip(sched["filter"]) == "J129")
    assert set(np.flatnonzero(near)) == set(p["expid"])
    assert hdr["PTRADIUS"] == 1.0 and hdr["PTFILTER"] == "J129" and hdr["PTNSCHED"] == 16956
    assert hdr["SCHED"] == "Roman_WAS_obseq_11_1_23.fits" and hdr["SCHEDDS"].isdigit()
    # consecutive exposures of one visit: 139.8 s long, the next ~30 s after the end
    starts = np.diff(p["mjd"]) * DAY
    assert np.median(starts) == pytest.approx(169.8, abs=1.0)


@pytest.mark.slow  # ~15 s: SCA footprints of every exposure near the field in the real schedule
def test_real_schedule_all_filters_limit_after_and_sca(was):
    sched = read_schedule(was)
    assert len(sched) == 16956
    every = select_covering(sched, RA, DEC, 1.0)
    assert len({p.filter for p in every}) == 6 and len(every) > 1000
    # with an SCA, the exposures that put it on the field (test_real_schedule_sca_footprint_selection);
    # --limit keeps the earliest of those
    first = select_covering(sched, RA, DEC, 1.0, limit=5, sca=7)
    assert first == select_covering(sched, RA, DEC, 1.0, sca=7)[:5]
    assert all(p.sca == 7 for p in first)
    later = select_covering(sched, RA, DEC, 1.0, after=every[2].mjd)
    assert later[0] == every[3] and all(p.mjd > every[2].mjd for p in later)


def test_filter_is_not_case_sensitive(tmp_path):
    sched = read_schedule(schedule_file(tmp_path / "s.fits"))
    upper = select_covering(sched, RA, DEC, 1.0, filter="J129")
    assert [p.expid for p in upper] == [0, 2, 3, 5, 6]
    assert select_covering(sched, RA, DEC, 1.0, filter="j129") == upper


def test_radius_cuts_by_great_circle_distance(tmp_path):
    # rows at RA 10, 10.3, 10.6, 10.9 at Dec -44: 0, 0.216, 0.431, 0.647 degrees away
    sched = read_schedule(schedule_file(tmp_path / "s.fits"))
    got = {p.expid for p in select_covering(sched, RA, DEC, 0.3)}
    assert got == {i for i in range(8) if i % 4 in (0, 1)}


def test_rows_out_of_time_order_are_sorted(tmp_path):
    rows = [(60000.3, 100.0, RA, DEC, 0.0, "J129"), (60000.1, 100.0, RA, DEC, 0.0, "J129"),
            (60000.2, 100.0, RA, DEC, 0.0, "J129")]
    sched = read_schedule(schedule_file(tmp_path / "s.fits", rows))
    assert [p.expid for p in select_covering(sched, RA, DEC, 1.0)] == [1, 2, 0]


def test_empty_selection_is_a_warning_and_an_empty_table(tmp_path):
    path = schedule_file(tmp_path / "s.fits")
    out = tmp_path / "p.fits"
    result = invoke("pointings", "select", "--schedule", path, "--ra", 100, "--dec", 20, "--radius", 1, "-o", out)
    assert result.exit_code == 0
    assert "perscli: warning:" in result.stderr and "no exposure" in result.stderr
    with fits.open(out) as hdul:
        assert len(hdul["POINTINGS"].data) == 0 and hdul["POINTINGS"].header["NEXP"] == 0


# -- planned dithers ---------------------------------------------------------------------------

def test_plan_spacing_offsets_and_columns(tmp_path):
    out = tmp_path / "plan.fits"
    result = invoke("pointings", "plan", "--ra", RA, "--dec", DEC, "--n", 12, "--dither", 30, "--filter", "h158",
                    "--start", 61000.5, "--exptime", 100, "--gap", 20, "--pa", 45, "--sca", 3, "--seed", 4,
                    "-o", out)
    assert result.exit_code == 0, result.output
    with fits.open(out) as hdul:
        p, hdr = hdul["POINTINGS"].data, hdul["POINTINGS"].header
    assert len(p) == 12 and list(p["expid"]) == list(range(12))
    assert p["mjd"][0] == 61000.5
    assert np.allclose(np.diff(p["mjd"]) * DAY, 120.0, atol=1e-4)
    assert np.all(p["exptime"] == 100.0) and np.all(p["pa"] == 45.0) and np.all(p["sca"] == 3)
    assert set(np.char.strip(p["filter"])) == {"H158"}
    # offsets on the tangent plane, east and north, within +-30"
    a0, d0 = math.radians(RA), math.radians(DEC)
    a, d = np.radians(p["ra"]), np.radians(p["dec"])
    cos_c = np.sin(d0) * np.sin(d) + np.cos(d0) * np.cos(d) * np.cos(a - a0)
    xi = np.degrees(np.cos(d) * np.sin(a - a0) / cos_c) * 3600
    eta = np.degrees((np.cos(d0) * np.sin(d) - np.sin(d0) * np.cos(d) * np.cos(a - a0)) / cos_c) * 3600
    assert np.abs(xi).max() <= 30.0 + 1e-6 and np.abs(eta).max() <= 30.0 + 1e-6
    assert np.abs(xi).max() > 10.0 and np.abs(eta).max() > 10.0          # they do dither
    assert len(set(np.round(xi, 6))) == 12
    assert hdr["PTMODE"] == "plan" and hdr["PTDITHER"] == 30.0 and hdr["SEED"] == 4


def test_plan_defaults_are_the_survey_cadence():
    plan = plan_dithers(RA, DEC, 3)
    assert [p.exptime for p in plan] == [139.8] * 3
    assert (plan[1].mjd - plan[0].end) * DAY == pytest.approx(30.0, abs=1e-4)
    assert {p.filter for p in plan} == {"J129"} and {p.sca for p in plan} == {0}


def test_plan_without_dither_points_at_the_centre():
    plan = plan_dithers(RA, DEC, 4, dither=0.0)
    assert all(p.ra == pytest.approx(RA, abs=1e-12) and p.dec == pytest.approx(DEC, abs=1e-12) for p in plan)


def test_plan_same_seed_same_bytes_other_seed_other_offsets(tmp_path):
    outs = [tmp_path / f"{k}.fits" for k in "abc"]
    for out, seed in zip(outs, (8, 8, 9)):
        args = ["pointings", "plan", "--ra", RA, "--dec", DEC, "--n", 5, "--dither", 20, "--seed", seed, "-o", out]
        assert invoke(*args).exit_code == 0
    assert raw_cards_masked(outs[0]) == raw_cards_masked(outs[1])
    with fits.open(outs[0]) as a, fits.open(outs[2]) as c:
        assert not np.array_equal(a[1].data["ra"], c[1].data["ra"])
        assert np.array_equal(a[1].data["mjd"], c[1].data["mjd"])


def test_plan_library_errors():
    with pytest.raises(PerscliError, match="unknown filter 'J130'"):
        plan_dithers(RA, DEC, 2, filter="J130")
    with pytest.raises(PerscliError, match="SCA 19"):
        plan_dithers(RA, DEC, 2, sca=19)
    with pytest.raises(PerscliError, match="gap -1"):
        plan_dithers(RA, DEC, 2, gap=-1.0)


# -- the pointings table -----------------------------------------------------------------------

def test_write_and_read_back(tmp_path):
    plan = plan_dithers(RA, DEC, 6, dither=15.0, filter="W146", sca=12, seed=3)
    out = str(tmp_path / "p.fits")
    write_pointings(plan, out, step="test")
    assert read_pointings(out) == plan
    with fits.open(out) as hdul:
        cols = hdul["POINTINGS"].columns
        assert cols.names == ["expid", "mjd", "exptime", "ra", "dec", "pa", "filter", "sca"]
        assert {c.name: c.unit for c in cols}["mjd"] == "d" and {c.name: c.unit for c in cols}["ra"] == "deg"


def test_read_pointings_takes_a_schedule_row_by_row(tmp_path):
    path = schedule_file(tmp_path / "s.fits")
    with fits.open(path) as hdul:
        rows = hdul[1].data
        pointings = read_pointings(path)
        assert len(pointings) == len(rows)
        assert [p.expid for p in pointings] == list(range(len(rows)))
        assert pointings[3].mjd == rows["date"][3] and pointings[3].sca == 0


def test_read_pointings_names_a_missing_column(tmp_path):
    path = tmp_path / "bad.fits"
    fits.BinTableHDU.from_columns([fits.Column("expid", "K", array=np.arange(3)),
                                   fits.Column("exptime", "D", array=np.ones(3))]).writeto(path)
    with pytest.raises(PerscliError, match="no column 'mjd'"):
        read_pointings(str(path))


def test_schedule_from_stdin(tmp_path):
    path = schedule_file(tmp_path / "s.fits")
    out = tmp_path / "p.fits"
    with open(path, "rb") as fh:
        result = invoke("pointings", "select", "--schedule", "-", "--ra", RA, "--dec", DEC, "--radius", 1, "-o", out,
                        input=fh.read())
    assert result.exit_code == 0, result.output
    with fits.open(out) as hdul:
        assert len(hdul[1].data) == 8 and hdul[1].header["SCHED"] == "stdin"


# -- command-line errors -----------------------------------------------------------------------

#: ``expect_error(tmp_path, ARGS, *needles)``: ``perscli pointings ARGS -o OUT`` fails in one line holding
#: every needle, no output file, inputs unchanged (:func:`fits_factory.expect_error`)
expect_error = partial(fits_factory.expect_error, command="pointings")


@pytest.mark.parametrize("column", ["date", "exptime", "ra", "dec", "pa", "filter"])
def test_schedule_missing_a_column(tmp_path, column):
    path = schedule_file(tmp_path / "s.fits", drop=column)
    expect_error(tmp_path, ["select", "--schedule", path, "--ra", RA, "--dec", DEC, "--radius", 1],
                 path, f"no column '{column}'", "date, exptime, ra, dec, pa, filter", "check that this is a schedule")


def test_schedule_column_of_the_wrong_type(tmp_path):
    path = schedule_file(tmp_path / "s.fits", text="ra")
    expect_error(tmp_path, ["select", "--schedule", path, "--ra", RA, "--dec", DEC, "--radius", 1],
                 path, "column 'ra'", "holds text", "must hold numbers")


def test_schedule_filter_column_of_numbers(tmp_path):
    rows = [(60000.0, 139.8, RA, DEC, 0.0, 1.0)]
    path = tmp_path / "s.fits"
    cols = [fits.Column(n, "D", array=np.array([v])) for n, v in zip(("date", "exptime", "ra", "dec", "pa",
                                                                        "filter"), rows[0])]
    fits.HDUList([fits.PrimaryHDU(), fits.BinTableHDU.from_columns(cols)]).writeto(path)
    expect_error(tmp_path, ["select", "--schedule", path, "--ra", RA, "--dec", DEC, "--radius", 1],
                 str(path), "column 'filter'", "must hold text")


def test_schedule_that_is_not_fits(tmp_path):
    bad = tmp_path / "bad.fits"
    bad.write_bytes(b"date,exptime,ra,dec,pa,filter\n" * 200)
    expect_error(tmp_path, ["select", "--schedule", bad, "--ra", RA, "--dec", DEC, "--radius", 1], str(bad), "not a FITS file")


def test_schedule_truncated(tmp_path):
    path = schedule_file(tmp_path / "s.fits")
    raw = open(path, "rb").read()
    with open(path, "wb") as fh:
        fh.write(raw[:2880 * 2 + 100])
    expect_error(tmp_path, ["select", "--schedule", path, "--ra", RA, "--dec", DEC, "--radius", 1], path, "truncated")


def test_unknown_filter(tmp_path):
    path = schedule_file(tmp_path / "s.fits")
    msg = expect_error(tmp_path, ["select", "--schedule", path, "--ra", RA, "--dec", DEC, "--radius", 1, "--filter", "J130"],
                       "unknown filter 'J130'", "valid are R062, Z087, Y106, J129, H158, F184, K213, W146")
    assert msg
    expect_error(tmp_path, ["plan", "--ra", RA, "--dec", DEC, "--n", 2, "--filter", "Ks"], "unknown filter 'Ks'")


def test_missing_schedule_file(tmp_path):
    expect_error(tmp_path, ["select", "--schedule", tmp_path / "nope.fits", "--ra", RA, "--dec", DEC, "--radius", 1],
                 "nope.fits", "no such file")


#: a usage error of the flag form (exit 2) in one line, nothing written (the shared harness's)
expect_usage_error = partial(fits_factory.expect_error, command="pointings", code=2)


@pytest.mark.parametrize("args, needle", [
    (["--ra", RA, "--dec", DEC], "either --schedule FILE or --plan"),
    (["--plan", "--schedule", "S", "--ra", RA, "--dec", DEC, "--n", 2], "either --schedule FILE or --plan"),
    (["--plan", "--ra", RA, "--dec", DEC], "--n"),
    (["--plan", "--ra", RA, "--dec", DEC, "--n", 2, "--radius", 1], "--radius is for --schedule"),
    (["--plan", "--ra", RA, "--dec", DEC, "--n", 2, "--limit", 3], "--limit is for --schedule"),
    (["--schedule", "S", "--ra", RA, "--dec", DEC], "--radius"),
    (["--schedule", "S", "--ra", RA, "--dec", DEC, "--radius", 1, "--dither", 5], "--dither is for --plan"),
    (["--schedule", "S", "--ra", RA, "--dec", DEC, "--radius", 1, "--seed", 5], "--seed is for --plan"),
    (["--schedule", "S", "--ra", RA, "--dec", DEC, "--radius", 0], "--radius"),
    (["--plan", "--ra", RA, "--dec", DEC, "--n", 0], "--n"),
    (["--plan", "--ra", RA, "--dec", DEC, "--n", 2, "--sca", 19], "--sca"),
    (["--plan", "--ra", RA, "--dec", DEC, "--n", 2, "--gap", -1], "--gap"),
    (["--plan", "--ra", RA, "--dec", -91, "--n", 2], "--dec"),
    (["--plan", "--dec", DEC, "--n", 2], "--ra"),
])
def test_usage_errors(tmp_path, args, needle):
    args = [schedule_file(tmp_path / "s.fits") if a == "S" else a for a in args]
    expect_usage_error(tmp_path, args, needle)


def test_schedule_dataclass_length():
    s = Schedule(*(np.zeros(3) for _ in range(5)), filter=np.array(["J129"] * 3))
    assert len(s) == 3


PERSCLI = shutil.which("perscli", path=os.path.dirname(sys.executable)) or shutil.which("perscli")


@pytest.mark.skipif(PERSCLI is None, reason="perscli console script not installed")
def test_schedule_through_real_pipes(tmp_path):
    """A schedule read from a real pipe and the table written to one, as in a shell script."""
    path = schedule_file(tmp_path / "s.fits")
    piped, direct = tmp_path / "piped.fits", tmp_path / "direct.fits"
    cmd = (f"cat {path} | {PERSCLI} pointings select --schedule - --ra {RA} --dec {DEC} --radius 0.3 --filter J129 -o - "
           f"| cat > {piped}")
    proc = subprocess.run(["bash", "-o", "pipefail", "-c", cmd], capture_output=True, text=True)
    # stderr holds the count of rows written and nothing else; the table went through stdout
    assert proc.returncode == 0 and proc.stderr == "stdout: 2 rows written (exposures)\n", proc.stderr
    assert invoke("pointings", "select", "--schedule", path, "--ra", RA, "--dec", DEC, "--radius", 0.3, "--filter", "J129",
                  "-o", direct).exit_code == 0
    with fits.open(piped, checksum=True) as a, fits.open(direct) as b:
        assert list(a["POINTINGS"].data["expid"]) == [0, 5]
        assert a["POINTINGS"].data.tobytes() == b["POINTINGS"].data.tobytes()


# -- SCA footprints ------------------------------------------------------------------------------

#: a pointing Roman can observe (RA 10, Dec -44 is 54-126 degrees from the Sun on this date)
P7 = Pointing(expid=0, mjd=61541.97, exptime=139.8, ra=RA, dec=DEC, pa=30.0, filter="J129", sca=7)


def galsim_corners(p, sca, x, y):
    """Sky positions of SCA pixels through GalSim's Roman WCS directly (independent of perscli)."""
    import datetime

    import galsim
    import galsim.roman

    date = datetime.datetime(1858, 11, 17) + datetime.timedelta(days=p.mjd)
    wcs = galsim.roman.getWCS(world_pos=galsim.CelestialCoord(p.ra * galsim.degrees, p.dec * galsim.degrees),
                              PA=p.pa * galsim.degrees, date=date, SCAs=sca)[sca]
    return wcs.xyToradec(np.asarray(x, float), np.asarray(y, float), units="deg")


def test_sca_footprint_is_the_wcs_of_the_outer_pixel_edges():
    ra, dec = sca_footprint(P7, 7)
    gra, gdec = galsim_corners(P7, 7, [0.5, 4088.5, 4088.5, 0.5], [0.5, 0.5, 4088.5, 4088.5])
    np.testing.assert_allclose(ra, gra, rtol=0, atol=1e-12)
    np.testing.assert_allclose(dec, gdec, rtol=0, atol=1e-12)
    # the sides are 4088 pixels of ~0.11" (the plate scale varies by a few per cent over the focal plane)
    sides = distance(ra, dec, np.roll(ra, -1), np.roll(dec, -1)) * 3600
    assert np.all(np.abs(sides / (4088 * 0.11) - 1) < 0.05)
    # the pointing's own SCA is the default, and a cutout has its own corners
    assert np.array_equal(sca_footprint(P7)[0], ra)
    cra, cdec = sca_footprint(P7, 7, bounds=(1, 512, 101, 612))
    gra, gdec = galsim_corners(P7, 7, [0.5, 512.5, 512.5, 0.5], [100.5, 100.5, 612.5, 612.5])
    np.testing.assert_allclose(cra, gra, atol=1e-12)
    np.testing.assert_allclose(cdec, gdec, atol=1e-12)


def test_sca_footprint_margin_and_edges_are_great_circles():
    from perscli.scene import project

    ra, dec = sca_footprint(P7, 7)
    mra, mdec = sca_footprint(P7, 7, margin_arcsec=30.0)
    # each corner moves out diagonally by ~30" x sqrt(2)
    moved = distance(ra, dec, mra, mdec) * 3600
    np.testing.assert_allclose(moved, 30 * math.sqrt(2), rtol=0.05)
    # pixels along the edges lie on the great-circle arcs between the corners (straight on a TAN plane)
    t = np.linspace(0.5, 4088.5, 33)
    ex, ey = np.concatenate([t, np.full(33, 4088.5)]), np.concatenate([np.full(33, 0.5), t])
    era, edec = galsim_corners(P7, 7, ex, ey)
    x, y = project(ra.mean(), dec.mean(), np.concatenate([ra, era]), np.concatenate([dec, edec]))
    cx, cy, px, py = x[:4], y[:4], x[4:], y[4:]
    for (a, b), pts in (((0, 1), slice(0, 33)), ((1, 2), slice(33, 66))):
        d = np.array([cx[b] - cx[a], cy[b] - cy[a]])
        n = np.array([-d[1], d[0]]) / np.hypot(*d)
        off = np.abs((px[pts] - cx[a]) * n[0] + (py[pts] - cy[a]) * n[1])
        assert np.degrees(off.max()) * 3600 < 0.01


def test_every_sca_lies_within_the_focal_plane_reach():
    from perscli.scene.schedule import FPA_REACH_DEG

    for pa in (0.0, 123.0):
        p = Pointing(**{**P7.__dict__, "pa": pa})
        for sca in range(1, 19):
            ra, dec = sca_footprint(p, sca)
            reach = distance(p.ra, p.dec, ra, dec).max()
            assert 0.1 < reach < FPA_REACH_DEG


@pytest.mark.parametrize("kwargs, needle", [
    (dict(sca=0, pointing=Pointing(**{**P7.__dict__, "sca": 0})), "give an SCA"),
    (dict(sca=19), "1 to 18"),
    (dict(sca=7, bounds=(0, 10, 1, 10)), "bounds"),
    (dict(sca=7, margin_arcsec=-1.0), "margin"),
    (dict(sca=7, pointing=Pointing(**{**P7.__dict__, "mjd": 60000.0})), "Roman cannot point at"),
])
def test_sca_footprint_errors(kwargs, needle):
    pointing = kwargs.pop("pointing", P7)
    with pytest.raises(PerscliError, match=needle):
        sca_footprint(pointing, **kwargs)


def test_polygon_meets_circle_exactly():
    from perscli.scene.regions import polygon_meets_circle

    ra, dec = sca_footprint(P7, 7)
    cra, cdec = ra.mean(), dec.mean()
    assert polygon_meets_circle(ra, dec, cra, cdec, 1e-4)                   # the centre inside
    # a circle just short of a side's midpoint, and just past it
    mra, mdec = (ra[0] + ra[1]) / 2, (dec[0] + dec[1]) / 2
    far = 2 * distance(cra, cdec, mra, mdec)
    ora, odec = cra + 2 * (mra - cra), cdec + 2 * (mdec - cdec)          # beyond the side, about as far
    gap = distance(ora, odec, mra, mdec)
    assert not polygon_meets_circle(ra, dec, ora, odec, gap * 0.98)
    assert polygon_meets_circle(ra, dec, ora, odec, gap * 1.02)
    assert far > 0 and not polygon_meets_circle(ra, dec, cra + 5, cdec, 1.0)


@pytest.mark.slow  # ~10 s: SCA footprints of the real schedule
def test_real_schedule_sca_footprint_selection(was):
    """SCA 7 on a small field: every exposure whose SCA 7 footprint (checked independently, pixel by
    pixel along its edges through GalSim) comes within the radius, and no other."""
    sched = read_schedule(was)
    radius = 0.05
    chosen = select_covering(sched, RA, DEC, radius, sca=7)
    assert 3 <= len(chosen) < 200 and all(p.sca == 7 for p in chosen)
    assert np.all(np.diff([p.mjd for p in chosen]) > 0)
    got = {p.expid for p in chosen}
    # independent check of the rows whose boresight is within 1 degree (the SCAs reach 0.45)
    near = np.flatnonzero(distance(RA, DEC, sched.ra, sched.dec) <= radius + 0.6)
    t = np.linspace(0.5, 4088.5, 400)
    edge_x = np.concatenate([t, np.full_like(t, 4088.5), t, np.full_like(t, 0.5)])
    edge_y = np.concatenate([np.full_like(t, 0.5), t, np.full_like(t, 4088.5), t])
    expect = set()
    for i in near:
        p = schedule_pointing(sched, i)
        era, edec = galsim_corners(p, 7, edge_x, edge_y)
        if distance(RA, DEC, era, edec).min() <= radius * 0.999:
            expect.add(int(i))
            continue
        # or the field centre inside the SCA
        import datetime

        import galsim
        import galsim.roman

        date = datetime.datetime(1858, 11, 17) + datetime.timedelta(days=p.mjd)
        wcs = galsim.roman.getWCS(world_pos=galsim.CelestialCoord(p.ra * galsim.degrees, p.dec * galsim.degrees),
                                  PA=p.pa * galsim.degrees, date=date, SCAs=7)[7]
        x, y = wcs.radecToxy(RA, DEC, units="deg")
        if 0.5 <= x <= 4088.5 and 0.5 <= y <= 4088.5:
            expect.add(int(i))
    # rows within a hair of the radius may go either way by the edge sampling; none is here
    assert got == expect
    boresight = {p.expid for p in select_covering(sched, RA, DEC, radius)}
    assert got != boresight


def test_sca_selection_on_a_small_schedule(tmp_path):
    # boresights 0.3 degrees apart along RA: at PA 30, SCA 7 lies off the boresight
    rows = [(61541.97 + i * 169.8 / DAY, 139.8, RA + 0.1 * i, DEC, 30.0, "J129") for i in range(-8, 9)]
    sched = read_schedule(schedule_file(tmp_path / "s.fits", rows))
    radius = 0.02
    chosen = select_covering(sched, RA, DEC, radius, sca=7)
    from perscli.scene.regions import polygon_meets_circle

    for i in range(len(sched)):
        p = schedule_pointing(sched, i)
        hit = polygon_meets_circle(*sca_footprint(p, 7), RA, DEC, radius)
        assert hit == (i in {q.expid for q in chosen})
    assert chosen and 8 not in {q.expid for q in chosen}          # the boresight row does not see it


# -- the exposures before a row ----------------------------------------------------------------------

def test_previous_exposures_in_time_order_whatever_filter_and_pointing(tmp_path):
    rows = [(60000.0 + t / DAY, 139.8, ra, DEC, 0.0, f) for t, ra, f in
            [(500, 10, "J129"), (0, 50, "H158"), (1000, 200, "Y106"), (300, 10, "J129"), (1000, 10, "J129"),
             (700, 10, "F184"), (float("nan"), 10, "J129")]]
    sched = read_schedule(schedule_file(tmp_path / "s.fits", rows))
    # row 2 starts at t=1000: the rows starting before it, earliest first; row 4 (same start) is not earlier
    assert [p.expid for p in previous_exposures(sched, 2, 10)] == [1, 3, 0, 5]
    assert [p.expid for p in previous_exposures(sched, 2, 2)] == [0, 5]
    assert [p.expid for p in previous_exposures(sched, 2, 2, sca=7)] == [0, 5]
    assert all(p.sca == 7 for p in previous_exposures(sched, 2, 2, sca=7))
    assert previous_exposures(sched, 1, 3) == [] and previous_exposures(sched, 2, 0) == []
    p = previous_exposures(sched, 0, 1)[0]
    assert p == schedule_pointing(sched, 3) and p.filter == "J129" and p.mjd == rows[3][0]
    for args, needle in (((7, 1), "row 7 does not exist"), ((-1, 1), "does not exist"), ((2, -1), ">= 0"),
                         ((6, 1), "no finite start")):
        with pytest.raises(PerscliError, match=needle):
            previous_exposures(sched, *args)


def test_previous_exposures_of_the_real_schedule(was, tmp_path):
    sched = read_schedule(was)
    prev = previous_exposures(sched, 4183, 10)
    assert [p.expid for p in prev] == list(range(4173, 4183))        # the schedule is in time order
    # the survey changes filter at row 4576 (J129 to H158): the history of row 4578 crosses it
    assert [p.filter for p in previous_exposures(sched, 4578, 4)] == ["J129", "J129", "H158", "H158"]
    out = tmp_path / "prev.fits"
    result = invoke("pointings", "before", "--schedule", was, "--row", 4183, "--n", 10, "--sca", 7, "--footprints",
                    "-o", out)
    assert result.exit_code == 0, result.stderr
    with fits.open(out, checksum=True) as hdul:
        data, hdr = hdul["POINTINGS"].data, hdul["POINTINGS"].header
        assert list(data["expid"]) == list(range(4173, 4183)) and np.all(data["sca"] == 7)
        assert hdr["PTMODE"] == "before" and hdr["PTBEFORE"] == 4183 and hdr["PTN"] == 10
        assert data["corner_ra"].shape == (10, 4)
        ra, dec = sca_footprint(prev[3], 7)
        np.testing.assert_array_equal(data["corner_ra"][3], ra)
        np.testing.assert_array_equal(data["corner_dec"][3], dec)
        assert hdul["POINTINGS"].columns["corner_ra"].unit == "deg"
    # the table reads back as pointings (the corner columns are extra)
    assert read_pointings(str(out)) == [Pointing(**{**p.__dict__, "sca": 7}) for p in prev]


def test_cli_before_warns_when_the_schedule_starts_later(tmp_path):
    path = schedule_file(tmp_path / "s.fits")
    out = tmp_path / "p.fits"
    result = invoke("pointings", "before", "--schedule", path, "--row", 2, "--n", 5, "-o", out)
    assert result.exit_code == 0 and "only 2 exposure(s)" in result.stderr
    with fits.open(out) as hdul:
        assert list(hdul["POINTINGS"].data["expid"]) == [0, 1]
    result = invoke("pointings", "before", "--schedule", path, "--row", 99, "--n", 5, "-o", tmp_path / "q.fits")
    assert result.exit_code == 1 and "row 99 does not exist" in result.stderr
    assert not (tmp_path / "q.fits").exists()


def test_cli_footprints_of_a_selection_and_a_plan(was, tmp_path):
    out = tmp_path / "sel.fits"
    result = invoke("pointings", "select", "--schedule", was, "--ra", RA, "--dec", DEC, "--radius", 0.05, "--sca", 7,
                    "--filter", "J129", "--footprints", "-o", out)
    assert result.exit_code == 0, result.stderr
    with fits.open(out) as hdul:
        data, hdr = hdul["POINTINGS"].data, hdul["POINTINGS"].header
        assert hdr["PTCOVER"] == "sca footprint" and hdr["PTSCA"] == 7 and len(data) > 0
        for row in data:
            p = Pointing(int(row["expid"]), row["mjd"], row["exptime"], row["ra"], row["dec"], row["pa"],
                         row["filter"].strip(), int(row["sca"]))
            assert np.array_equal(sca_footprint(p)[0], row["corner_ra"])
    plan = tmp_path / "plan.fits"
    result = invoke("pointings", "plan", "--ra", RA, "--dec", DEC, "--n", 2, "--start", 61541.97, "--sca", 3,
                    "--footprints", "-o", plan)
    assert result.exit_code == 0, result.stderr
    with fits.open(plan) as hdul:
        assert hdul["POINTINGS"].data["corner_dec"].shape == (2, 4)


@pytest.mark.parametrize("args, needle", [
    (["--schedule", "S", "--before", 3], "--before needs --n"),
    (["--schedule", "S", "--before", 3, "--n", 2, "--ra", RA], "--ra is not for --before"),
    (["--schedule", "S", "--before", 3, "--n", 2, "--filter", "J129"], "--filter is not for --before"),
    (["--schedule", "S", "--before", 3, "--n", 2, "--seed", 4], "--seed is not for --before"),
    (["--plan", "--ra", RA, "--dec", DEC, "--n", 2, "--before", 1], "--before is for --schedule"),
    (["--schedule", "S", "--ra", RA, "--dec", DEC, "--radius", 1, "--n", 3], "--n is for --plan or --before"),
    (["--schedule", "S", "--ra", RA, "--dec", DEC, "--radius", 1, "--footprints"], "--footprints needs --sca"),
    (["--schedule", "S", "--dec", DEC, "--radius", 1], "--ra"),
])
def test_usage_errors_of_before_and_footprints(tmp_path, args, needle):
    args = [schedule_file(tmp_path / "s.fits") if a == "S" else a for a in args]
    expect_usage_error(tmp_path, args, needle)


def test_plan_on_a_date_roman_cannot_observe_is_one_line(tmp_path):
    # MJD 60000 is too close to the Sun for RA 10, Dec -44: the plan says so before any footprint is asked for
    expect_error(tmp_path, ["plan", "--ra", RA, "--dec", DEC, "--n", 2, "--sca", 7, "--start", 60000, "--footprints"],
                 "Roman cannot take", "--start")


def test_plan_with_footprints_at_the_default_start(tmp_path):
    # the first new-user path: no --start, no --pa; the footprints are GalSim's for the chosen date and PA
    out = tmp_path / "plan.fits"
    result = invoke("pointings", "plan", "--ra", RA, "--dec", DEC, "--n", 2, "--sca", 7, "--footprints", "-o", out)
    assert result.exit_code == 0, result.stderr
    for p, row in zip(read_pointings(str(out)), fits.getdata(out, "POINTINGS")):
        assert np.array_equal(sca_footprint(p)[0], row["corner_ra"])


def test_within_is_separation_below_radius_everywhere_on_the_sphere():
    """scene.within skips the great circle outside the band of declinations that can be near: the same booleans
    as separation(...) <= radius, at the poles, across RA = 0/360, at radius 0 and beyond a hemisphere."""
    import numpy as np

    from perscli.scene import separation, within

    rng = np.random.default_rng(0)
    ra = rng.uniform(0, 360, 200_000)
    dec = np.degrees(np.arcsin(rng.uniform(-1, 1, ra.size)))
    ra[:2000], dec[:2000] = (10 + rng.normal(0, 0.3, 2000)) % 360, np.clip(-44 + rng.normal(0, 0.3, 2000), -90, 90)
    ra[2000:2010], dec[2000:2010] = 10.0, -44.0 + np.array([-0.5, 0.5, 0.5 + 1e-12, -0.5 - 1e-12, 0, 1, -1, 0.25,
                                                             -0.25, 0.4999999])
    for ra0, dec0, radius in [(10, -44, 0.5), (0.1, 89.8, 0.5), (359.9, -89.9, 0.5), (10, -44, 0.0), (180, 0, 3),
                              (10, -44, 120.0)]:
        np.testing.assert_array_equal(within(ra0, dec0, ra, dec, radius), separation(ra0, dec0, ra, dec) <= radius)
    assert within(10, -44, [], [], 1.0).shape == (0,)
