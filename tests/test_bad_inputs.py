"""Held-out bad inputs (issue 25): each is one line on stderr, exit status 1 (2 for a usage error), no output left,
inputs untouched, no traceback; and a working twin where the refusal could hide one."""

import numpy as np
import pytest
from astropy.io import fits
from astropy.table import Table

from fits_factory import expect_error, invoke, listing
from test_measure_cli import scene  # noqa: F401  (a fixture: truth catalogue and frames of a cutout)
from test_scene_pointings import DAY, DEC, RA, schedule_file

POINT = ["--ra", 10, "--dec", -44, "--pa", 30, "--filter", "J129", "--sca", 7, "--mjd", 61541.97]


# -- resources -----------------------------------------------------------------------------------------------

@pytest.mark.parametrize("command", [["correlate", "S", "--frames", 0, 1], ["render", "T", *POINT, "--seed", 1],
                                     ["measure", "F", "--catalog", "T"], ["apply-persistence", "F", "F"]])
def test_a_million_workers_is_a_usage_error(scene, tmp_path, command):
    """correlate --workers 1000000 crashed the process (SIGSEGV in TreeCorr's OpenMP pool)."""
    _, truth, frame, _ = scene
    files = {"T": truth, "F": frame, "S": truth}
    args = [files.get(a, a) for a in command]
    line = expect_error(tmp_path, [*args[1:], "--workers", 1000000], "--workers", "1<=x<=1024", command=args[0],
                        code=2)
    assert "1000000" in line


def test_the_most_workers_still_work(tmp_path):
    from perscli.executor import MAX_WORKERS, check_workers

    assert check_workers(MAX_WORKERS) == MAX_WORKERS
    with pytest.raises(Exception, match="give 1 to 1024"):
        check_workers(10 ** 6)


# -- study descriptions and --set ----------------------------------------------------------------------------

def test_a_utf16_study_file_is_one_line(tmp_path):
    study = tmp_path / "s.yaml"
    study.write_text("preset: ci\nname: x\n", encoding="utf-16")
    expect_error(tmp_path, [study, "--dry-run"], str(study), "not UTF-8 text", "UTF-16", "save the study description "
                 "as UTF-8", command="study", out="s", inputs=[study])
    study.write_text("preset: ci\nname: x\n", encoding="utf-8")          # the twin: the same text as UTF-8
    result = invoke("-q", "study", study, "-o", tmp_path / "s", "--dry-run")
    assert result.exit_code == 0 and result.stdout.startswith("study x: "), result.stderr


def test_a_utf16_law_file_is_one_line(scene, tmp_path):
    _, _, frame, _ = scene
    law = tmp_path / "law.yaml"
    law.write_text("base: typical\n", encoding="utf-16")
    expect_error(tmp_path, [frame, frame, "--law", law], str(law), "not UTF-8 text", command="apply-persistence",
                 inputs=[frame, law])


@pytest.mark.parametrize("value", ['!!python/object/apply:os.system ["touch pwned"]', "!!python/name:os.system"])
def test_a_set_value_with_an_object_tag_is_refused_in_one_line(tmp_path, value):
    line = expect_error(tmp_path, ["--preset", "ci", "--set", f"name={value}", "--dry-run"], "not a YAML value",
                        command="study", out="s", any_of=("tags that build objects are refused", "constructor"))
    assert not (tmp_path / "pwned").exists() and "Traceback" not in line


def test_an_object_tag_in_a_study_file_is_one_line(tmp_path):
    study = tmp_path / "s.yaml"
    study.write_text('name: !!python/object/apply:os.system ["touch pwned"]\n')
    expect_error(tmp_path, [study, "--dry-run"], "not valid YAML", "tags that build objects are refused",
                 command="study", out="s", inputs=[study])
    assert not (tmp_path / "pwned").exists()


# -- catalogues ----------------------------------------------------------------------------------------------

def _edited_catalogue(truth, path, **rows):
    table = Table.read(truth)
    for column, (row, value) in rows.items():
        table[column][row] = value
    table.write(path)
    return path


@pytest.mark.parametrize("command", ["render", "measure"])
def test_a_magnitude_of_minus_30_is_one_line(scene, tmp_path, command):
    """render raised ValueError('lam value too large') from the Poisson draw; measure fitted it."""
    _, truth, frame, _ = scene
    bad = _edited_catalogue(truth, tmp_path / "m30.fits", mag_J129=(0, -30.0))
    args = [bad, *POINT, "--bounds", 1, 160, 1, 160, "--seed", 1] if command == "render" else \
        [frame, "--catalog", bad]
    expect_error(tmp_path, args, str(bad), "mag_J129", "brighter than any star", "-30", command=command,
                 inputs=[bad, frame])


def test_nan_magnitudes_are_refused_by_measure_as_by_render(scene, tmp_path):
    _, truth, frame, _ = scene
    bad = _edited_catalogue(truth, tmp_path / "nan.fits", mag_J129=(1, np.nan))
    expect_error(tmp_path, [frame, "--catalog", bad], str(bad), "mag_J129", "not a magnitude", "id 2",
                 command="measure", inputs=[bad, frame])
    # the twin: a catalogue without magnitudes at all is measured (the start flux from the data)
    table = Table.read(truth)
    table.remove_columns([c for c in table.colnames if c.startswith("mag_")])
    table.write(tmp_path / "nomag.fits")
    result = invoke("measure", frame, "--catalog", tmp_path / "nomag.fits", "-o", tmp_path / "ok.fits")
    assert result.exit_code == 0, result.stderr


def _gaia_chunk(path, ids):
    n = len(ids)
    rad = np.radians
    cols = [fits.Column("id", "K", array=np.asarray(ids, dtype=np.int64)),
            fits.Column("coord_ra", "D", unit="rad", array=rad(10.0 + 0.001 * np.arange(n))),
            fits.Column("coord_dec", "D", unit="rad", array=rad(np.full(n, -44.0))),
            fits.Column("phot_g_mean_flux", "D", unit="nJy", array=np.full(n, 1e6)),
            fits.Column("phot_bp_mean_flux", "D", unit="nJy", array=np.full(n, 8e5)),
            fits.Column("phot_rp_mean_flux", "D", unit="nJy", array=np.full(n, 1.2e6))]
    fits.HDUList([fits.PrimaryHDU(), fits.BinTableHDU.from_columns(cols)]).writeto(path, checksum=True)
    return path


def test_a_gaia_chunk_with_a_repeated_source_id_is_refused(tmp_path):
    bad = _gaia_chunk(tmp_path / "dup.fits", [11, 12, 11, 13])
    expect_error(tmp_path, ["--ra", 10, "--dec", -44, "--size", 5, "--gaia", bad], str(bad), "source id 11",
                 "more than once", command="catalog", inputs=[bad])
    good = _gaia_chunk(tmp_path / "ok.fits", [11, 12, 13])
    # the twin: a chunk given twice is the same stars once
    result = invoke("catalog", "--ra", 10, "--dec", -44, "--size", 5, "--gaia", good, "--gaia", good,
                    "--galaxy-density", 0, "-o", tmp_path / "c.fits")
    assert result.exit_code == 0, result.stderr
    assert list(fits.getdata(tmp_path / "c.fits", "TRUTH")["gaia_id"]) == [11, 12, 13]


def test_a_source_in_two_chunks_with_other_values_is_refused(tmp_path):
    a = _gaia_chunk(tmp_path / "a.fits", [11, 12])
    b = tmp_path / "b.fits"
    with fits.open(a) as hdul:
        hdul[1].data["phot_g_mean_flux"][0] = 2e6
        hdul.writeto(b, checksum=True)
    expect_error(tmp_path, ["--ra", 10, "--dec", -44, "--size", 5, "--gaia", a, "--gaia", b], "source id 11",
                 "phot_g_mean_flux", command="catalog", inputs=[a, b])


# -- schedules -----------------------------------------------------------------------------------------------

def test_pointings_before_refuses_exposures_that_overlap(tmp_path):
    rows = [(60000.0 + i * 169.8 / DAY, 139.8, RA, DEC, 0.0, "J129") for i in range(6)]
    rows[3] = (rows[2][0] + 100.0 / DAY, *rows[3][1:])      # starts 100 s into row 2's 139.8 s
    bad = schedule_file(tmp_path / "s.fits", rows)
    expect_error(tmp_path, ["before", "--schedule", bad, "--row", 5, "--n", 4], str(bad), "rows 2 and 3 overlap",
                 "39.8 s", command="pointings", inputs=[bad])
    # the twin: the rows before the overlap are a history
    result = invoke("pointings", "before", "--schedule", bad, "--row", 2, "--n", 2, "-o", tmp_path / "ok.fits")
    assert result.exit_code == 0, result.stderr


def test_the_bundled_schedule_has_no_overlap():
    from perscli.scene.schedule import check_sequence, read_schedule

    s = read_schedule("roman-was")
    order = np.argsort(s.mjd, kind="stable")
    check_sequence(s, order[np.isfinite(s.mjd[order])].tolist())


# -- outputs and messages ------------------------------------------------------------------------------------

@pytest.mark.parametrize("name, kind", [("o33.png", "PNG"), ("shapes.csv", "CSV"), ("s.json", "JSON"),
                                        ("s.txt.gz", "text")])
def test_measure_refuses_an_output_named_for_another_format(scene, tmp_path, name, kind):
    _, truth, frame, _ = scene
    line = expect_error(tmp_path, [frame, "--catalog", truth], name, f"writes FITS, not {kind}", ".fits",
                        command="measure", code=2, out=name)
    assert line.startswith("perscli measure: error: Invalid value for '-o'")


def test_fits_names_are_written(scene, tmp_path):
    _, truth, frame, _ = scene
    for name in ("shapes.fits", "shapes.fits.gz", "shapes"):
        result = invoke("measure", frame, "--catalog", truth, "-o", tmp_path / name)
        assert result.exit_code == 0, (name, result.stderr)


def test_measure_names_the_option_for_missing_columns(scene, tmp_path):
    _, truth, frame, _ = scene
    table = Table.read(truth)
    table.rename_columns(["ra", "dec"], ["ALPHA_J2000", "DELTA_J2000"])
    table.write(tmp_path / "sex.fits")
    expect_error(tmp_path, [frame, "--catalog", tmp_path / "sex.fits"], "no ra/dec", "--columns ra=COLUMN,dec=COLUMN",
                 command="measure")
    result = invoke("measure", frame, "--catalog", tmp_path / "sex.fits", "--columns",
                    "ra=ALPHA_J2000,dec=DELTA_J2000", "-o", tmp_path / "ok.fits")
    assert result.exit_code == 0, result.stderr


def test_a_schedule_missing_a_column_names_schedule_columns(tmp_path):
    bad = schedule_file(tmp_path / "s.fits", drop="date")
    expect_error(tmp_path, ["select", "--schedule", bad, "--ra", RA, "--dec", DEC, "--radius", 1], "no column 'date'",
                 "--schedule-columns date=COLUMN", command="pointings", inputs=[bad])


@pytest.mark.parametrize("extra", [[], ["--frames", 0, 1], ["--de1", "g1", "--de2", "g2"]])
def test_correlate_names_a_missing_table_first(tmp_path, extra):
    expect_error(tmp_path, ["nothere.fits", *extra], "nothere.fits: no such file", command="correlate")
    expect_error(tmp_path, ["--pair", "a.fits", "b.fits", *extra[:3 if len(extra) == 3 else 0]], "a.fits: no such file",
                 command="correlate")


def test_render_previous_given_a_catalogue_says_it_is_a_catalogue(scene, tmp_path):
    _, truth, frame, _ = scene
    line = expect_error(tmp_path, [truth, *POINT, "--bounds", 1, 160, 1, 160, "--seed", 1, "--previous", truth],
                        str(truth), "a catalogue, not a frame", "--previous takes an earlier exposure",
                        command="render")
    assert "STARFLU extension" not in line
    assert listing(tmp_path) == []
