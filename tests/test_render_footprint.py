"""Where a frame lands: ``perscli render --dry-run`` (corners, size, objects on the frame, a ds9 region
file), the warning for a frame without objects and ``--strict``, ``perscli pointings --catalog`` counts,
and exposures GalSim cannot make, each refused in one line.

Every number is checked against GalSim's Roman WCS made here, independently of perscli
(``galsim.roman.getWCS`` on a datetime computed here, objects placed one by one with ``toImage``).
"""

import datetime as dt
import re

import numpy as np
import pytest
from astropy.io import fits
from astropy.table import Table

from fits_factory import expect_error, invoke, listing

RA, DEC, PA, SCA, FILTER, MJD = 10.0, -44.0, 30.0, 7, "J129", 61541.97
BOUNDS = (1001, 1128, 2001, 2128)
CENTRE_BOUNDS = (1981, 2108, 1981, 2108)       # holds the SCA centre (2044.5, 2044.5)
EXPOSURE = ["--ra", RA, "--dec", DEC, "--pa", PA, "--mjd", MJD, "--filter", FILTER, "--sca", SCA]


def galsim_wcs(ra=RA, dec=DEC, pa=PA, mjd=MJD, sca=SCA):
    import galsim
    import galsim.roman as roman

    date = dt.datetime(1858, 11, 17) + dt.timedelta(days=mjd)
    world = galsim.CelestialCoord(ra * galsim.degrees, dec * galsim.degrees)
    return roman.getWCS(world_pos=world, PA=pa * galsim.degrees, date=date, SCAs=sca)[sca]


def sky(wcs, x, y):
    import galsim

    c = wcs.toWorld(galsim.PositionD(x, y))
    return c.ra / galsim.degrees % 360.0, c.dec / galsim.degrees


def pixel(wcs, ra, dec):
    """(x, y) of one position, or None when it is more than 2 degrees from the SCA (not on it)."""
    import galsim

    target = galsim.CelestialCoord(ra * galsim.degrees, dec * galsim.degrees)
    centre = wcs.toWorld(galsim.PositionD(2044.5, 2044.5))
    if centre.distanceTo(target) / galsim.degrees > 2.0:
        return None
    p = wcs.toImage(target)
    return p.x, p.y


def inside(xy, bounds):
    if xy is None:
        return False
    xmin, xmax, ymin, ymax = bounds
    return xmin - 0.5 <= xy[0] < xmax + 0.5 and ymin - 0.5 <= xy[1] < ymax + 0.5


def write_truth(path, rows):
    """rows: (kind, ra, dec, J, hlr)."""
    t = Table(rows=[(i, ra, dec, kind, mag, mag + 0.3, hlr, 0.1 if kind == "galaxy" else 0.0, 0.0)
                    for i, (kind, ra, dec, mag, hlr) in enumerate(rows, 1)],
              names=["id", "ra", "dec", "kind", "mag_J129", "mag_H158", "hlr", "e1", "e2"])
    t["id"] = t["id"].astype(np.int64)
    t.write(str(path), format="fits", overwrite=True)
    return str(path)


@pytest.fixture(scope="module")
def work(tmp_path_factory):
    return tmp_path_factory.mktemp("footprint")


@pytest.fixture(scope="module")
def truth(work):
    """Objects on the cutout, just off its edges, near it, and far away: the antipode of the SCA centre and
    a point 60 degrees off, which GalSim's TAN-SIP WCS would fold onto the frame or fail to invert."""
    wcs = galsim_wcs()
    rng = np.random.default_rng(5)
    rows = []
    xmin, xmax, ymin, ymax = BOUNDS
    for k in range(40):
        x, y = rng.uniform(xmin - 40, xmax + 40), rng.uniform(ymin - 40, ymax + 40)
        ra, dec = sky(wcs, x, y)
        rows.append(("star" if k % 4 == 0 else "galaxy", ra, dec, 18.0 + k % 5, 0.3))
    for x, y in [(xmin - 0.6, ymin + 10), (xmax + 0.4, ymin + 10), (xmin + 10, ymax + 0.6)]:   # edges
        rows.append(("galaxy", *sky(wcs, x, y), 20.0, 0.2))
    ra0, dec0 = sky(wcs, 2044.5, 2044.5)
    rows.append(("star", (ra0 + 180.0) % 360.0, -dec0, 12.0, 0.0))          # the antipode of the SCA centre
    rows.append(("galaxy", ra0, dec0 + 60.0, 19.0, 0.4))
    return write_truth(work / "truth.fits", rows)


def dry_run(truth, *extra, bounds=BOUNDS):
    return invoke("render", truth, *EXPOSURE, "--bounds", *bounds, "--dry-run", *extra)


# -- the report -----------------------------------------------------------------------------------

def test_dry_run_report_against_galsims_wcs(work, truth):
    before = listing(work)
    result = dry_run(truth, "-o", work / "never.fits")
    assert result.exit_code == 0, result.stderr
    assert listing(work) == before                          # nothing written, -o included
    text = result.stdout
    wcs = galsim_wcs()
    xmin, xmax, ymin, ymax = BOUNDS
    corners = re.findall(r"\(([\d.]+), ([\d.]+)\)\s+ra ([\d.]+) dec ([+-][\d.]+)", text)
    assert len(corners) == 5                                 # the centre, then the four corners
    expected = [((xmin + xmax) / 2, (ymin + ymax) / 2), (xmin - 0.5, ymin - 0.5), (xmax + 0.5, ymin - 0.5),
                (xmax + 0.5, ymax + 0.5), (xmin - 0.5, ymax + 0.5)]
    for (x, y, ra, dec), (ex, ey) in zip(corners, expected):
        assert (float(x), float(y)) == (ex, ey)
        era, edec = sky(wcs, ex, ey)
        assert float(ra) == pytest.approx(era, abs=1e-6) and float(dec) == pytest.approx(edec, abs=1e-6)
    assert f"SCA {SCA}" in text and f"frame x {xmin}..{xmax}, y {ymin}..{ymax}: 128 x 128 pixels" in text
    size = re.search(r'\(([\d.]+)" x ([\d.]+)"\)', text)
    assert float(size.group(1)) == pytest.approx(128 * 0.11, rel=0.03)
    # objects whose centre lands on the frame, counted one by one through GalSim's WCS
    cat = Table.read(truth)
    on = [inside(pixel(wcs, r["ra"], r["dec"]), BOUNDS) for r in cat]
    stars = sum(1 for r, o in zip(cat, on) if o and r["kind"].strip() == "star")
    galaxies = sum(1 for r, o in zip(cat, on) if o and r["kind"].strip() == "galaxy")
    assert 10 < stars + galaxies < len(cat) - 5
    match = re.search(r"on frame\s+(\d+) objects centred on the frame \((\d+) stars?, (\d+) galax(?:y|ies)\); "
                      r"(\d+) drawn", text)
    assert match, text
    assert [int(v) for v in match.groups()[:3]] == [stars + galaxies, stars, galaxies]
    assert stars + galaxies < int(match.group(4)) < len(cat) - 1      # stamps reach in from outside, not the far two
    assert f"catalogue   truth.fits: {len(cat)} objects" in text
    assert result.stderr == ""


def test_dry_run_regions_file(work, truth):
    out = work / "frame.reg"
    result = dry_run(truth, "--regions", out)
    assert result.exit_code == 0, result.stderr
    lines = out.read_text().splitlines()
    assert lines[0] == "# Region file format: DS9 version 4.1" and "fk5" in lines
    polygon = next(line for line in lines if line.startswith("polygon("))
    values = [float(v) for v in polygon[len("polygon("):polygon.index(")")].split(",")]
    wcs = galsim_wcs()
    xmin, xmax, ymin, ymax = BOUNDS
    for k, (x, y) in enumerate([(xmin - 0.5, ymin - 0.5), (xmax + 0.5, ymin - 0.5), (xmax + 0.5, ymax + 0.5),
                                (xmin - 0.5, ymax + 0.5)]):
        era, edec = sky(wcs, x, y)
        assert values[2 * k] == pytest.approx(era, abs=1e-7) and values[2 * k + 1] == pytest.approx(edec, abs=1e-7)
    drawn = int(re.search(r"(\d+) drawn", result.stdout).group(1))
    objects = [line for line in lines if line.startswith(("point(", "circle("))]
    assert len(objects) == drawn
    assert all("tag={star}" in line for line in objects if line.startswith("point("))
    assert all("tag={galaxy}" in line for line in objects if line.startswith("circle("))
    assert dry_run(truth, "--regions", out).exit_code == 1                  # exists: --overwrite
    assert dry_run(truth, "--regions", out, "--overwrite").exit_code == 0


def test_regions_needs_dry_run_and_never_replaces_an_input(work, truth):
    result = invoke("render", truth, *EXPOSURE, "--seed", 1, "--regions", work / "x.reg", "-o", work / "x.fits")
    assert result.exit_code == 2 and "--regions is written by --dry-run" in result.stderr
    result = dry_run(truth, "--regions", truth)
    assert result.exit_code == 1 and "is also an input" in result.stderr


def test_dry_run_needs_neither_output_nor_seed_but_a_render_does(work, truth):
    assert dry_run(truth).exit_code == 0
    result = invoke("render", truth, *EXPOSURE, "--seed", 1)
    assert result.exit_code == 2 and "Missing option '-o'" in result.stderr
    result = invoke("render", truth, *EXPOSURE, "-o", work / "x.fits")
    assert result.exit_code == 2 and "Missing option '--seed'" in result.stderr
    assert not (work / "x.fits").exists()


# -- frames without objects -------------------------------------------------------------------------

@pytest.fixture(scope="module")
def elsewhere(work):
    """A catalogue 0.3 degrees from SCA 7's centre: on no pixel of it."""
    ra0, dec0 = sky(galsim_wcs(), 2044.5, 2044.5)
    rows = [("galaxy", ra0 + dx, dec0 + 0.3 + dy, 20.0, 0.3) for dx in (-0.01, 0.0, 0.01) for dy in (-0.01, 0.01)]
    return write_truth(work / "elsewhere.fits", rows)


def test_no_object_on_the_frame_warns_at_default_verbosity(work, elsewhere):
    out = work / "empty.fits"
    result = invoke("render", elsewhere, *EXPOSURE, "--bounds", *BOUNDS, "--seed", 1, "-o", out)
    assert result.exit_code == 0, result.stderr
    # a short line (what and where), then indented lines saying how to fix it: not one line of 600 characters
    lines = result.stderr.splitlines()
    assert len(lines) == 4 and lines[0].startswith("perscli: warning: no object of ")
    assert all(len(line.replace(str(elsewhere), "CAT")) <= 160 for line in lines)
    assert all(line.startswith("  ") for line in lines[1:])
    ra0, dec0 = sky(galsim_wcs(), (BOUNDS[0] + BOUNDS[1]) / 2, (BOUNDS[2] + BOUNDS[3]) / 2)
    assert f"lands on this cutout of SCA {SCA} (ra {ra0:.4f}, dec {dec0:+.4f})" in lines[0]
    assert "--footprints" in lines[1] and "catalog --pointings" in lines[2]
    assert "--dry-run" in lines[3] and "--strict" in lines[3]
    cat = Table.read(elsewhere)
    assert f"ra {np.mean(cat['ra']):.4f}" in lines[0]                       # where the catalogue is
    with fits.open(out) as hdul:
        assert hdul[0].header["NOBJ"] == 0
    quiet = invoke("render", elsewhere, *EXPOSURE, "--bounds", *BOUNDS, "--seed", 1, "-o", out, "--overwrite", "-q")
    assert quiet.exit_code == 0 and quiet.stderr == ""


def test_strict_refuses_a_frame_without_objects(tmp_path, elsewhere):
    expect_error(tmp_path, ["render", elsewhere, *EXPOSURE, "--bounds", *BOUNDS, "--seed", 1, "--strict"],
                 "--strict: no object of", "lands on this cutout of SCA")


def test_strict_dry_run(work, elsewhere, truth):
    result = invoke("render", elsewhere, *EXPOSURE, "--dry-run", "--strict")
    assert result.exit_code == 1 and result.stdout == ""
    assert result.stderr.startswith("Error: --strict: no object of") and len(result.stderr.splitlines()) == 1
    result = invoke("render", elsewhere, *EXPOSURE, "--dry-run")
    assert result.exit_code == 0 and "0 objects centred on the frame" in result.stdout
    assert result.stderr.startswith("perscli: warning: no object of") and "--dry-run" not in result.stderr
    assert dry_run(truth, "--strict").exit_code == 0


def test_the_antipode_and_far_objects_are_never_drawn(work, truth):
    # only the two far objects: the antipode would land on the SCA centre through the TAN projection
    cat = Table.read(truth)[-2:]
    far = str(work / "far.fits")
    cat.write(far, format="fits", overwrite=True)
    out = work / "far_frame.fits"
    result = invoke("render", far, *EXPOSURE, "--bounds", *CENTRE_BOUNDS, "--seed", 1, "-o", out,
                    "--set", "poisson=off", "--set", "read_noise=off", "--set", "dark=off")
    assert result.exit_code == 0, result.stderr
    assert "no object of" in result.stderr
    with fits.open(out) as hdul:
        assert hdul[0].header["NOBJ"] == 0
        ideal = hdul["IDEAL"].data
        assert ideal.max() < 1.01 * np.median(ideal)                       # sky only: no star at the centre


def test_far_objects_beside_near_ones_render(work, truth):
    out = work / "with_far.fits"
    result = invoke("render", truth, *EXPOSURE, "--bounds", *BOUNDS, "--seed", 1, "--strict", "-o", out)
    assert result.exit_code == 0, result.stderr
    with fits.open(out) as hdul:
        assert hdul[0].header["NOBJ"] > 10


# -- exposures GalSim cannot make ------------------------------------------------------------------

def test_render_at_a_date_roman_cannot_observe_is_one_line(tmp_path, truth):
    args = [truth, "--ra", RA, "--dec", DEC, "--pa", PA, "--mjd", 60000, "--filter", FILTER, "--sca", SCA,
            "--bounds", *BOUNDS, "--seed", 1]
    line = expect_error(tmp_path, ["render", *args], "Roman cannot point at ra=10 dec=-44",
                        "the Sun is 44.5 degrees", "54 to 126", "the first date after it when Roman can is")
    first = float(re.search(r"Roman can is MJD ([0-9.]+)", line).group(1))
    # that date works
    args[args.index("--mjd") + 1] = first
    assert invoke("render", *args, "--dry-run").exit_code == 0
    # the same from a row of a pointings table
    plan = tmp_path / "plan.fits"
    assert invoke("pointings", "plan", "--ra", RA, "--dec", DEC, "--n", 1, "--sca", SCA, "-o", plan).exit_code == 0
    with fits.open(plan, mode="update") as hdul:
        hdul["POINTINGS"].data["mjd"][0] = 60000.0
    expect_error(tmp_path, ["render", truth, "--pointings", plan, "--bounds", *BOUNDS, "--seed", 1],
                 "Roman cannot point at")
    expect_error(tmp_path, ["render", truth, "--pointings", plan, "--dry-run"], "Roman cannot point at")


def test_render_refuses_a_table_row_out_of_range(tmp_path, truth):
    plan = tmp_path / "plan.fits"
    assert invoke("pointings", "plan", "--ra", RA, "--dec", DEC, "--n", 1, "--sca", SCA, "-o", plan).exit_code == 0
    for column, value, needle in [("ra", 370.0, "RA 370 is not in [0, 360]"), ("dec", -95.0, "Dec -95 is not in"),
                                  ("pa", np.nan, "position angle nan"), ("mjd", 2461542.0, "a Julian Date")]:
        with fits.open(plan) as hdul:
            hdul["POINTINGS"].data[column][0] = value
            bad = tmp_path / f"bad_{column}.fits"
            hdul.writeto(bad, output_verify="silentfix", checksum=False)
        expect_error(tmp_path, ["render", truth, "--pointings", bad, "--bounds", *BOUNDS, "--seed", 1, "--no-checksum"],
                     needle)


def test_render_refuses_a_catalogue_with_positions_out_of_range(tmp_path):
    bad = write_truth(tmp_path / "bad.fits", [("star", 365.0, DEC, 18.0, 0.0)])
    expect_error(tmp_path, ["render", bad, *EXPOSURE, "--bounds", *BOUNDS, "--seed", 1],
                 "RA outside [0, 360]", "ra=365")


def test_sky_level_is_galsims_on_the_exposure_date(tmp_path):
    import galsim
    import galsim.roman as roman

    from perscli.render.exposure import Exposure
    from perscli.optics import Optics

    optics = Optics(Exposure(ra=RA, dec=DEC, pa=PA, sca=SCA, filter=FILTER, mjd=MJD))
    wcs = galsim_wcs()
    centre = galsim.PositionD(2044.5, 2044.5)
    date = dt.datetime(1858, 11, 17) + dt.timedelta(days=MJD)
    bandpass = roman.getBandpasses(AB_zeropoint=True)[FILTER]
    zodi = roman.getSkyLevel(bandpass, world_pos=wcs.toWorld(centre), exptime=1.0, date=date)
    assert optics.sky_rate() == pytest.approx(zodi * wcs.pixelArea(centre) + roman.thermal_backgrounds[FILTER],
                                              rel=1e-12)
    # RA 0, Dec 0 at the June solstice: 90 degrees from the Sun; GalSim without the date puts the Sun at the
    # vernal equinox, on top of it, and refuses
    june = 61578.0
    world = galsim.CelestialCoord(0 * galsim.degrees, 0 * galsim.degrees)
    with pytest.raises(galsim.GalSimError):
        roman.getSkyLevel(bandpass, world_pos=world, exptime=1.0)
    truth = write_truth(tmp_path / "t.fits", [("star", 0.001, 0.001, 20.0, 0.0)])
    result = invoke("render", truth, "--ra", 0, "--dec", 0, "--pa", 0, "--mjd", june, "--filter", FILTER,
                    "--sca", SCA, "--bounds", 1, 32, 1, 32, "--seed", 1, "-o", tmp_path / "june.fits")
    assert result.exit_code == 0, result.stderr
    assert fits.getheader(tmp_path / "june.fits", 0)["SKYRATE"] > 0


# -- pointings --catalog ----------------------------------------------------------------------------

def test_pointings_catalog_counts_against_galsims_wcs(tmp_path):
    plan, cat = tmp_path / "plan.fits", tmp_path / "cat.fits"
    assert invoke("pointings", "plan", "--ra", RA, "--dec", DEC, "--n", 3, "--sca", SCA, "--dither", 120,
                  "-o", plan).exit_code == 0
    result = invoke("catalog", "--ra", 10.5, "--dec", -44.05, "--size", 9, "--galaxy-density", 3,
                    "--star-density", 1, "-o", cat)
    assert result.exit_code == 0, result.stderr
    out = tmp_path / "counts.fits"
    result = invoke("pointings", "plan", "--ra", RA, "--dec", DEC, "--n", 3, "--sca", SCA, "--dither", 120,
                    "--footprints", "--catalog", cat, "-o", out)
    assert result.exit_code == 0, result.stderr
    table = Table.read(cat)
    with fits.open(out) as hdul:
        rows, hdr = hdul["POINTINGS"].data, hdul["POINTINGS"].header
        assert "TRUTH=cat.fits" in str(hdul["POINTINGS"].header["HISTORY"])
    full = (1, 4088, 1, 4088)
    totals = []
    for row in rows:
        wcs = galsim_wcs(row["ra"], row["dec"], row["pa"], row["mjd"], SCA)
        on = np.array([inside(pixel(wcs, r["ra"], r["dec"]), full) for r in table])
        stars = int(np.sum(on & (np.char.strip(np.asarray(table["kind"]).astype(str)) == "star")))
        assert (row["n_star"], row["n_galaxy"]) == (stars, int(on.sum()) - stars)
        totals.append(int(on.sum()))
    assert min(totals) > 50 and len(set(totals)) > 1           # the dithers move objects on and off
    assert hdr["PTNCAT"] == len(table) and hdr["PTNSTAR"] == rows["n_star"].sum()


def test_pointings_catalog_elsewhere_warns_and_needs_footprints(tmp_path, elsewhere):
    out = tmp_path / "counts.fits"
    result = invoke("pointings", "plan", "--ra", 200, "--dec", 30, "--n", 2, "--sca", SCA, "--footprints",
                    "--catalog", elsewhere, "-o", out)
    assert result.exit_code == 0, result.stderr
    assert result.stderr.startswith("perscli: warning: no object of") and "perscli catalog --pointings" in \
        result.stderr
    assert list(fits.getdata(out, "POINTINGS")["n_galaxy"]) == [0, 0]
    result = invoke("pointings", "plan", "--ra", RA, "--dec", DEC, "--n", 2, "--sca", SCA, "--catalog", elsewhere,
                    "-o", tmp_path / "no.fits")
    assert result.exit_code == 2 and "--catalog needs --footprints" in result.stderr
    assert not (tmp_path / "no.fits").exists()
