"""When Roman can look at a field: GalSim's observability as perscli uses it, the start and PA a plan
chooses when none is given, plans refused when Roman could not take them, and a default plan rendered
end to end.

GalSim's Roman module is the reference: ``galsim.roman.allowedPos`` (Sun angle 54 to 126 degrees) and
``galsim.roman.bestPA``, called here directly on datetimes made independently of perscli.
"""

import datetime as dt
import re

import numpy as np
import pytest
from astropy.io import fits

from perscli import PerscliError
from perscli.scene.settings import PLAN_REFERENCE_MJD
from perscli.scene.dithers import plan_dithers
from perscli.scene.observability import best_pa, first_observable_start, observable, sun_angle

from fits_factory import expect_error, invoke, listing

RA, DEC = 10.0, -44.0
DAY = 86400.0


def galsim_date(mjd):
    return dt.datetime(1858, 11, 17) + dt.timedelta(days=mjd)


def galsim_allowed(ra, dec, mjd):
    import galsim
    import galsim.roman as roman

    return roman.allowedPos(galsim.CelestialCoord(ra * galsim.degrees, dec * galsim.degrees), galsim_date(mjd))


def galsim_best(ra, dec, mjd):
    import galsim
    import galsim.roman as roman

    pa = roman.bestPA(galsim.CelestialCoord(ra * galsim.degrees, dec * galsim.degrees), galsim_date(mjd))
    return None if pa is None else (pa / galsim.degrees) % 360.0


# -- GalSim's observability ------------------------------------------------------------------------

@pytest.mark.parametrize("mjd", [60000.0, 60048.0, 61541.972429, 61620.0, 61700.0, 61800.5])
def test_observable_and_best_pa_are_galsims(mjd):
    assert observable(RA, DEC, mjd) == galsim_allowed(RA, DEC, mjd)
    expected = galsim_best(RA, DEC, mjd)
    if expected is None:
        assert best_pa(RA, DEC, mjd) is None
    else:
        assert best_pa(RA, DEC, mjd) == pytest.approx(expected, abs=1e-12)
    # the Sun angle says the same thing as allowedPos
    assert (54.0 <= sun_angle(RA, DEC, mjd) <= 126.0) == galsim_allowed(RA, DEC, mjd)


def test_first_observable_start_is_the_first_day_that_works():
    # MJD 60000 (2023-02-25): RA 10, Dec -44 is 44 degrees from the Sun
    assert not galsim_allowed(RA, DEC, 60000.0)
    start = first_observable_start([RA], [DEC], [0.0], [139.8 / DAY], 60000.0)
    assert start is not None and (start - 60000.0) == int(start - 60000.0)        # whole days after it
    assert galsim_allowed(RA, DEC, start) and galsim_allowed(RA, DEC, start + 139.8 / DAY)
    assert not galsim_allowed(RA, DEC, start - 1.0)
    # already observable: the date itself
    assert first_observable_start([RA], [DEC], [0.0], [0.0], start) == start


def test_a_sequence_longer_than_every_window_has_no_start():
    # the windows of RA 10, Dec -44 last 78 to 107 days: 150 days of exposures never fit
    n = 150
    offsets = np.arange(n) * 1.0
    assert first_observable_start([RA] * n, [DEC] * n, offsets, np.full(n, 139.8 / DAY), PLAN_REFERENCE_MJD) is None


# -- plans ----------------------------------------------------------------------------------------

def test_plan_default_start_and_pa_are_observable_and_deterministic():
    plan = plan_dithers(RA, DEC, 8, dither=30.0, seed=3)
    assert plan == plan_dithers(RA, DEC, 8, dither=30.0, seed=3)
    # the public schedule's first exposure is observable for this field: the plan starts there
    assert plan[0].mjd == PLAN_REFERENCE_MJD
    for p in plan:
        assert galsim_allowed(p.ra, p.dec, p.mjd) and galsim_allowed(p.ra, p.dec, p.end)
    best = galsim_best(plan[0].ra, plan[0].dec, plan[0].mjd)
    assert all(p.pa == pytest.approx(best, abs=1e-12) for p in plan) and len({p.pa for p in plan}) == 1


def test_plan_default_start_skips_to_the_first_observable_day():
    # from a reference at which the field is not observable, the start is the first whole day after it that is
    plan = plan_dithers(RA, DEC, 3, reference=60000.0)
    start = plan[0].mjd
    assert start > 60000.0 and (start - 60000.0) == int(start - 60000.0)
    assert all(galsim_allowed(p.ra, p.dec, p.mjd) and galsim_allowed(p.ra, p.dec, p.end) for p in plan)
    assert not galsim_allowed(plan[0].ra, plan[0].dec, start - 1.0)


def test_plan_keeps_a_given_start_and_pa():
    plan = plan_dithers(RA, DEC, 3, start=61600.5, pa=-120.0)
    assert plan[0].mjd == 61600.5 and {p.pa for p in plan} == {240.0}


def test_plan_refuses_a_start_roman_cannot_observe():
    with pytest.raises(PerscliError) as info:
        plan_dithers(RA, DEC, 2, start=60000.0)
    message = str(info.value)
    assert "\n" not in message and "Roman cannot take the first exposure" in message and "Sun" in message
    suggested = float(re.search(r"--start ([0-9.]+)", message).group(1))
    pa = float(re.search(r"--pa ([0-9.]+)", message).group(1))
    # the suggestion works, and is the best PA there
    plan = plan_dithers(RA, DEC, 2, start=suggested)
    assert plan[0].mjd == suggested
    assert pa == pytest.approx(galsim_best(plan[0].ra, plan[0].dec, suggested), abs=0.006)


def test_plan_refuses_a_start_whose_later_exposures_roman_cannot_take():
    # find the last whole day of the window that opens after the reference; a plan of 3 days from it leaves it
    day = PLAN_REFERENCE_MJD
    while galsim_allowed(RA, DEC, day + 1.0):
        day += 1.0
    with pytest.raises(PerscliError, match=r"Roman cannot take exposure \d+ of 40 of the plan"):
        plan_dithers(RA, DEC, 40, start=day, exptime=139.8, gap=3 * DAY / 40, dither=0.0)


def test_plan_too_long_for_any_window_says_why():
    with pytest.raises(PerscliError, match="longer than the field's observing windows; shorten it"):
        plan_dithers(RA, DEC, 150, gap=DAY, dither=0.0)


def test_a_long_exposure_is_observable_throughout():
    # a single exposure is checked within, not only at its ends: 200 days straddle a gap between windows
    with pytest.raises(PerscliError, match="longer than the field's observing windows"):
        plan_dithers(RA, DEC, 1, exptime=200 * DAY, dither=0.0)
    p = plan_dithers(RA, DEC, 1, exptime=20 * DAY, dither=0.0)[0]
    assert all(galsim_allowed(RA, DEC, t) for t in np.linspace(p.mjd, p.end, 41))


def test_plan_library_refuses_coordinates_out_of_range():
    for ra, dec, needle in [(370.0, DEC, "RA 370 is not in"), (-1.0, DEC, "RA -1 is not in"),
                            (RA, 91.0, "Dec 91 is not in"), (float("nan"), DEC, "RA nan")]:
        with pytest.raises(PerscliError, match=needle):
            plan_dithers(ra, dec, 2)
    with pytest.raises(PerscliError, match="position angle 400"):
        plan_dithers(RA, DEC, 2, pa=400.0)
    with pytest.raises(PerscliError, match="a Julian Date"):
        plan_dithers(RA, DEC, 2, start=2461542.0)


# -- the command ----------------------------------------------------------------------------------

def test_cli_plan_default_writes_its_choices_into_the_header(tmp_path):
    out = tmp_path / "plan.fits"
    result = invoke("pointings", "plan", "--ra", RA, "--dec", DEC, "--n", 3, "--sca", 7, "-o", out)
    assert result.exit_code == 0, result.stderr
    with fits.open(out) as hdul:
        data, hdr = hdul["POINTINGS"].data, hdul["POINTINGS"].header
    assert data["mjd"][0] == hdr["PTSTART"] == PLAN_REFERENCE_MJD
    assert hdr["PTSTFROM"].startswith("first observable from MJD 61541.972429")
    best = galsim_best(data["ra"][0], data["dec"][0], data["mjd"][0])
    assert np.all(data["pa"] == hdr["PTPA"]) and hdr["PTPA"] == pytest.approx(best, abs=1e-12)
    assert hdr["PTPAFROM"] == "galsim.roman.bestPA" and hdr["PTBESTPA"] == hdr["PTPA"]
    assert 54 <= hdr["PTSUNANG"] <= 126


def test_cli_plan_given_start_and_pa_are_recorded(tmp_path):
    out = tmp_path / "plan.fits"
    result = invoke("pointings", "plan", "--ra", RA, "--dec", DEC, "--n", 2, "--start", 61600.5, "--pa", 240,
                    "-o", out)
    assert result.exit_code == 0, result.stderr
    with fits.open(out) as hdul:
        hdr = hdul["POINTINGS"].header
    assert (hdr["PTSTART"], hdr["PTSTFROM"], hdr["PTPA"], hdr["PTPAFROM"]) == (61600.5, "given", 240.0, "given")
    assert hdr["PTBESTPA"] != 240.0


def test_cli_plan_unobservable_start_is_one_line_naming_the_fix(tmp_path):
    args = ["pointings", "plan", "--ra", RA, "--dec", DEC, "--n", 2, "--sca", 7, "--start", 60000]
    line = expect_error(tmp_path, args, "Roman cannot take", "the Sun is", "--start 60048", "best --pa")
    assert "Traceback" not in line


def test_cli_plan_never_observable_is_one_line(tmp_path):
    expect_error(tmp_path, ["pointings", "plan", "--ra", RA, "--dec", DEC, "--n", 150, "--gap", DAY, "--dither", 0],
                 "shorten it (--n, --exptime, --gap)")


def test_default_plan_then_render_works_end_to_end(tmp_path):
    """The new user's path: plan with defaults, draw a catalogue where SCA 7 lands, render a cutout."""
    plan, truth = tmp_path / "plan.fits", tmp_path / "truth.fits"
    assert invoke("pointings", "plan", "--ra", RA, "--dec", DEC, "--n", 2, "--sca", 7, "-o", plan).exit_code == 0
    result = invoke("catalog", "--pointings", plan, "--bounds", 1, 128, 1, 128, "-o", truth)
    assert result.exit_code == 0, result.stderr
    for row in (0, 1):
        out = tmp_path / f"e{row}.fits"
        extra = ["--previous", tmp_path / "e0.fits"] if row else []
        result = invoke("render", truth, "--pointings", plan, "--row", row, "--bounds", 1, 128, 1, 128, "--seed", 1,
                        "--strict", *extra, "-o", out)
        assert result.exit_code == 0, result.stderr
        assert result.stderr == ""                     # objects landed: no warning
        with fits.open(out) as hdul:
            assert hdul[0].header["NOBJ"] > 0 and hdul["SCI"].data.shape == (128, 128)
            assert hdul["SCI"].header["EXPSTART"] == PLAN_REFERENCE_MJD + row * (139.8 + 30.0) / DAY
    assert listing(tmp_path) == ["e0.fits", "e1.fits", "plan.fits", "truth.fits"]
