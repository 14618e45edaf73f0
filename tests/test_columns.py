"""Tables from other tools: --columns mappings, SExtractor FITS_LDAC, and stale checksums."""

import numpy as np
import pytest
from astropy.io import fits
from astropy.table import Table

from fits_factory import invoke
from perscli import PerscliError
from perscli.io.tables import parse_column_mapping, read_table

from test_correlate import SETTINGS, split, shapes_frames, write_table


def test_parse_column_mapping():
    assert parse_column_mapping("ra=ALPHA_J2000, dec=DELTA_J2000") == {"ra": "ALPHA_J2000", "dec": "DELTA_J2000"}
    # repeated options add up; perscli names are case-insensitive, file names kept as written
    assert parse_column_mapping(["ID=NUMBER", "mag_J129=MAG_AUTO"]) == {"id": "NUMBER", "mag_j129": "MAG_AUTO"}
    assert parse_column_mapping(()) == {}
    for bad in ("ra", "=x", "ra=a=b", "ra=a,ra=b", "1ra=x"):
        with pytest.raises(ValueError):
            parse_column_mapping(bad)


@pytest.fixture()
def sextractor(tmp_path):
    """A SExtractor-like catalogue (NUMBER, ALPHA_J2000, DELTA_J2000, MAG_AUTO), also with its own 'ra'."""
    path = tmp_path / "sex.fits"
    Table({"NUMBER": np.arange(1, 4), "ALPHA_J2000": [10.0, 10.1, 10.2], "DELTA_J2000": [-44.0, -44.1, -44.2],
           "MAG_AUTO": [20.0, 21.0, 22.0], "ra": [0.0, 0.0, 0.0]}).write(path)
    return str(path)


def test_mapped_columns_answer_to_perscli_names(sextractor):
    mapping = parse_column_mapping("ra=ALPHA_J2000,dec=DELTA_J2000,id=NUMBER")
    table = read_table(sextractor, what="catalogue", columns=mapping)
    # the file's own 'ra' is shadowed by the mapping
    assert sorted(table.names) == sorted(["id", "ra", "dec", "MAG_AUTO"])
    np.testing.assert_array_equal(table.column("ra"), [10.0, 10.1, 10.2])
    np.testing.assert_array_equal(table.column("id", kind="integer"), [1, 2, 3])
    table.hdu.file.close()


def test_mapping_errors_name_the_column(sextractor):
    with pytest.raises(PerscliError, match=r"--columns ra=ALPHA: the file has no column 'ALPHA'; its columns are "
                                           r"NUMBER, ALPHA_J2000"):
        read_table(sextractor, what="catalogue", columns={"ra": "ALPHA"})
    with pytest.raises(PerscliError, match=r"--columns rra=ALPHA_J2000: a catalogue has no column 'rra' for "
                                           r"perscli to read; it reads id, ra, dec, mag_\*"):
        read_table(sextractor, what="catalogue", columns={"rra": "ALPHA_J2000"}, known=("id", "ra", "dec", "mag_*"))
    # a glob in the known names admits any filter's magnitude
    read_table(sextractor, what="catalogue", columns={"mag_h158": "MAG_AUTO"}, known=("mag_*",)).hdu.file.close()
    # the missing-column message of a command that offers --columns suggests it
    table = read_table(sextractor, what="catalogue", columns={})
    with pytest.raises(PerscliError, match=r"has no column 'dec'.*--columns dec=COLUMN"):
        table.column("dec")
    table.hdu.file.close()
    table = read_table(sextractor, what="catalogue", columns={"dec": "MAG_AUTO"})
    with pytest.raises(PerscliError, match=r"column 'MAG_AUTO' \(--columns dec=MAG_AUTO\) holds"):
        table.column("dec", kind="integer")
    table.hdu.file.close()


def test_ldac_objects_table_is_read(tmp_path):
    """FITS_LDAC: LDAC_IMHEAD (the image header as text) first, then LDAC_OBJECTS."""
    path = tmp_path / "ldac.fits"
    imhead = fits.BinTableHDU.from_columns([fits.Column("Field Header Card", "2880A", array=np.array(["x" * 80]))],
                                           name="LDAC_IMHEAD")
    objects = fits.BinTableHDU.from_columns([fits.Column("NUMBER", "J", array=np.array([7, 8])),
                                             fits.Column("ALPHA_J2000", "D", array=np.array([1.0, 2.0]))],
                                            name="LDAC_OBJECTS")
    fits.HDUList([fits.PrimaryHDU(), imhead, objects]).writeto(path)
    table = read_table(str(path), what="catalogue", columns={"id": "NUMBER"})
    assert table.index == 2
    np.testing.assert_array_equal(table.column("id", kind="integer"), [7, 8])
    table.hdu.file.close()


def test_budget_reads_another_tools_xi_table(tmp_path):
    theta, xip, sig = np.array([1.0, 4.0, 16.0]), np.array([1e-9, -2e-9, 3e-10]), np.array([1e-9, 1e-9, 1e-9])
    ours, theirs = tmp_path / "ours.fits", tmp_path / "theirs.fits"
    Table({"meanr": theta, "xip": xip, "sigma_xip": sig}).write(ours)
    Table({"theta": theta, "xi_plus": xip, "sigma": sig}).write(theirs)
    assert invoke("budget", ours, "-o", tmp_path / "a.fits").exit_code == 0
    bad = invoke("budget", theirs, "-o", tmp_path / "b.fits")
    assert bad.exit_code == 1 and "--columns meanr=COLUMN" in bad.output
    ok = invoke("budget", theirs, "--columns", "meanr=theta,xip=xi_plus", "--columns", "sigma_xip=sigma",
                "-o", tmp_path / "b.fits")
    assert ok.exit_code == 0, ok.output
    a, b = fits.getdata(tmp_path / "a.fits", "BUDGET"), fits.getdata(tmp_path / "b.fits", "BUDGET")
    for col in ("theta", "xip", "ratio", "exceeds"):
        np.testing.assert_array_equal(a[col], b[col])
    usage = invoke("budget", theirs, "--columns", "meanr", "-o", tmp_path / "c.fits")
    assert usage.exit_code == 2 and not (tmp_path / "c.fits").exists()


def test_correlate_reads_renamed_shapes_tables(tmp_path):
    table, *_ = shapes_frames(n=600, seed=4)
    a = write_table(tmp_path / "a.fits", split(table, 0))
    b = write_table(tmp_path / "b.fits", split(table, 1))
    renamed = {"id": "NUMBER", "ra": "ALPHA_J2000", "dec": "DELTA_J2000", "g1": "E1", "g2": "E2", "flags": "FLAGS"}
    theirs = []
    for k, name in ((0, "ta.fits"), (1, "tb.fits")):
        cols = {renamed.get(key, key): v for key, v in split(table, k).items()}
        theirs.append(write_table(tmp_path / name, cols))
    assert invoke("correlate", a, b, *SETTINGS, "-o", tmp_path / "xi_ours.fits").exit_code == 0
    mapping = ",".join(f"{k}={v}" for k, v in renamed.items())
    result = invoke("correlate", *theirs, *SETTINGS, "--columns", mapping, "-o", tmp_path / "xi_theirs.fits")
    assert result.exit_code == 0, result.output
    ours, other = fits.getdata(tmp_path / "xi_ours.fits", "XI"), fits.getdata(tmp_path / "xi_theirs.fits", "XI")
    np.testing.assert_array_equal(ours["xip"], other["xip"])
    np.testing.assert_array_equal(ours["npairs"], other["npairs"])


def test_a_stale_checksum_is_called_stale_with_the_fixes(tmp_path):
    """astropy's Table round trip keeps the old CHECKSUM/DATASUM cards on changed data."""
    signed = tmp_path / "signed.fits"
    Table({"meanr": [1.0, 4.0], "xip": [1e-9, 2e-9], "sigma_xip": [1e-9, 1e-9]}).write(signed)
    with fits.open(signed) as hdul:
        hdul.writeto(tmp_path / "signed2.fits", checksum=True)
    edited = Table.read(tmp_path / "signed2.fits")
    assert "DATASUM" in edited.meta
    edited["xip"][0] = 5e-9
    edited.write(tmp_path / "edited.fits")
    result = invoke("budget", tmp_path / "edited.fits", "-o", tmp_path / "out.fits")
    assert result.exit_code == 1 and not (tmp_path / "out.fits").exists()
    line = result.output.strip()
    assert line.count("\n") == 0
    assert "stale" in line and "fitscheck --force" in line and "--no-checksum" in line
    # the option it names exists on the command (not only on the group)
    result = invoke("budget", tmp_path / "edited.fits", "--no-checksum", "-o", tmp_path / "out.fits")
    assert result.exit_code == 0, result.output


def _renamed(src, dest, renames):
    """A copy of a perscli table with columns renamed (as another tool would name them), no checksums."""
    t = Table.read(src, hdu=1)
    for old, new in renames.items():
        t.rename_column(old, new)
    for key in ("CHECKSUM", "DATASUM"):
        t.meta.pop(key, None)
    t.write(dest)
    return str(dest)


SEX = {"ra": "ALPHA_J2000", "dec": "DELTA_J2000", "id": "NUMBER"}
SEX_MAP = "ra=ALPHA_J2000,dec=DELTA_J2000,id=NUMBER"


@pytest.fixture(scope="module")
def field(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("columns")
    plan, truth = tmp / "plan.fits", tmp / "truth.fits"
    assert invoke("pointings", "plan", "--ra", 10, "--dec", -44, "--n", 2, "--sca", 7, "-o", plan).exit_code == 0
    assert invoke("catalog", "--pointings", plan, "--bounds", 1, 128, 1, 128, "-o", truth).exit_code == 0
    return dict(tmp=tmp, plan=str(plan), truth=str(truth), sex=_renamed(truth, tmp / "sex.fits", SEX))


def test_render_with_a_sextractor_catalogue(field, tmp_path):
    args = ["--pointings", field["plan"], "--row", 0, "--bounds", 1, 128, 1, 128, "--seed", 3]
    ours = invoke("render", field["truth"], *args, "--hdus", "IDEAL", "-o", tmp_path / "ours.fits")
    assert ours.exit_code == 0, ours.output
    refused = invoke("render", field["sex"], *args, "-o", tmp_path / "x.fits")
    assert refused.exit_code == 1 and "--columns id=COLUMN" in refused.output
    assert not (tmp_path / "x.fits").exists()
    theirs = invoke("render", field["sex"], *args, "--columns", SEX_MAP, "--hdus", "IDEAL", "-o", tmp_path / "t.fits")
    assert theirs.exit_code == 0, theirs.output
    np.testing.assert_array_equal(fits.getdata(tmp_path / "ours.fits", "IDEAL"),
                                  fits.getdata(tmp_path / "t.fits", "IDEAL"))
    dry = invoke("render", field["sex"], *args[:-2], "--dry-run", "--columns", SEX_MAP)
    assert dry.exit_code == 0 and "galaxies" in dry.output


def test_pointings_counts_and_schedule_with_other_names(field, tmp_path):
    counted = invoke("pointings", "plan", "--ra", 10, "--dec", -44, "--n", 2, "--sca", 7, "--footprints",
                     "--catalog", field["sex"], "--columns", "ra=ALPHA_J2000,dec=DELTA_J2000", "-o", tmp_path / "c.fits")
    assert counted.exit_code == 0, counted.output
    reference = invoke("pointings", "plan", "--ra", 10, "--dec", -44, "--n", 2, "--sca", 7, "--footprints",
                       "--catalog", field["truth"], "-o", tmp_path / "r.fits")
    assert reference.exit_code == 0
    for col in ("n_star", "n_galaxy"):
        np.testing.assert_array_equal(fits.getdata(tmp_path / "c.fits")[col], fits.getdata(tmp_path / "r.fits")[col])
    assert fits.getdata(tmp_path / "c.fits")["n_galaxy"].sum() > 0
    # a schedule of another survey: the planned rows as a schedule, its columns named otherwise
    plan = fits.getdata(field["plan"])
    names = {"date": "MJD_START", "exptime": "EXP_TIME", "ra": "RA_PNT", "dec": "DEC_PNT", "pa": "PA_APER",
             "filter": "BAND"}
    ours = Table({"date": plan["mjd"], "exptime": plan["exptime"], "ra": plan["ra"], "dec": plan["dec"],
                  "pa": plan["pa"], "filter": plan["filter"]})
    ours.write(tmp_path / "sched.fits")
    ours.rename_columns(list(names), list(names.values()))
    ours.write(tmp_path / "other.fits")
    a = invoke("pointings", "select", "--schedule", tmp_path / "sched.fits", "--ra", 10, "--dec", -44, "--radius", 1,
               "-o", tmp_path / "a.fits")
    mapping = ",".join(f"{k}={v}" for k, v in names.items())
    b = invoke("pointings", "select", "--schedule", tmp_path / "other.fits", "--ra", 10, "--dec", -44, "--radius", 1,
               "--schedule-columns", mapping, "-o", tmp_path / "b.fits")
    assert a.exit_code == 0 and b.exit_code == 0, b.output
    ta, tb = fits.getdata(tmp_path / "a.fits"), fits.getdata(tmp_path / "b.fits")
    assert len(ta) == 2
    for col in ("mjd", "ra", "dec", "pa", "exptime"):
        np.testing.assert_array_equal(ta[col], tb[col])


def test_catalog_reads_renamed_gaia_chunks(shared_data, tmp_path):
    chunk = shared_data / "gaia" / "145649.fits"
    other = _renamed(chunk, tmp_path / "gaia_other.fits", {"coord_ra": "RA_RAD", "coord_dec": "DEC_RAD"})
    args = ["--ra", 10.4, "--dec", -45, "--galaxy-density", 0]
    a = invoke("catalog", *args, "--gaia", chunk, "-o", tmp_path / "a.fits")
    b = invoke("catalog", *args, "--gaia", other, "--columns", "coord_ra=RA_RAD,coord_dec=DEC_RAD",
               "-o", tmp_path / "b.fits")
    assert a.exit_code == 0 and b.exit_code == 0, b.output
    ta, tb = fits.getdata(tmp_path / "a.fits"), fits.getdata(tmp_path / "b.fits")
    assert len(ta) > 0
    np.testing.assert_array_equal(ta["ra"], tb["ra"])
    bad = invoke("catalog", *args, "--gaia", other, "--columns", "ra=RA_RAD", "-o", tmp_path / "c.fits")
    assert bad.exit_code == 1 and "it reads id, coord_ra" in bad.output
