"""The public Roman WAS schedule ships with perscli (``roman-was``): the default of pointings select/before and of a
study, the same table as the file it was made from; a study naming a file that is not there says which key to set."""

import gzip
import hashlib

import numpy as np
import pytest
from astropy.io import fits

from perscli.scene.schedule import BUNDLED_SCHEDULE, read_schedule, schedule_path

from fits_factory import expect_error, invoke, raw_cards_masked


def test_the_bundled_schedule_is_the_public_file_unchanged(shared_data):
    """The package data is Roman_WAS_obseq_11_1_23.fits gzipped, byte for byte (when ../shared/data has it)."""
    original = (shared_data / "roman" / "Roman_WAS_obseq_11_1_23.fits").read_bytes()
    with gzip.open(schedule_path(BUNDLED_SCHEDULE)) as fh:
        assert hashlib.sha256(fh.read()).hexdigest() == hashlib.sha256(original).hexdigest()


def test_the_bundled_schedule_is_the_2023_sequence():
    s = read_schedule(BUNDLED_SCHEDULE)
    assert len(s) == 16956
    assert s.name.endswith("Roman_WAS_obseq_11_1_23.fits.gz")
    assert np.nanmin(s.mjd) == pytest.approx(61541.972429, abs=1e-6)      # 2027-05-16, the plan's reference


@pytest.mark.parametrize("words", [["select", "--ra", 10, "--dec", -44, "--radius", 0.05, "--sca", 7, "--filter",
                                    "J129"],
                                   ["before", "--row", 4183, "--n", 3, "--sca", 7]])
def test_pointings_take_the_bundled_schedule_by_default(tmp_path, words):
    a, b = tmp_path / "default.fits", tmp_path / "named.fits"
    assert invoke("pointings", *words, "-o", a).exit_code == 0
    assert invoke("pointings", words[0], "--schedule", "roman-was", *words[1:], "-o", b).exit_code == 0
    assert raw_cards_masked(a) == raw_cards_masked(b)
    rows = fits.getdata(a, "POINTINGS")
    assert len(rows) == (7 if words[0] == "select" else 3)
    if words[0] == "before":
        assert list(rows["expid"]) == [4180, 4181, 4182]


def test_the_help_says_where_the_schedule_comes_from():
    for sub in ("select", "before"):
        text = " ".join(invoke("pointings", sub, "--help").stdout.split())
        assert "roman-was" in text and "Roman_WAS_obseq_11_1_23.fits of 2023-11-01" in text, sub


def test_a_study_names_the_key_of_a_schedule_that_is_not_there(tmp_path):
    study = tmp_path / "s.yaml"
    study.write_text("preset: small\nexposures:\n  schedule: nothere.fits\n")
    line = expect_error(tmp_path, [study, "--dry-run"], "exposures.schedule:", "nothere.fits: no such file",
                        "set exposures.schedule to a schedule FITS file", "leave it out for the bundled roman-was",
                        command="study", out="s", inputs=[study])
    assert "s.yaml" not in line.split("exposures.schedule")[0]


def test_a_study_names_the_key_of_a_law_file_that_is_not_there(tmp_path):
    expect_error(tmp_path, ["--preset", "ci", "--set", "persistence.models=[typical, nothere.yaml]", "--dry-run",
                            "-o", tmp_path / "s"],
                 "persistence.models: nothere.yaml: no such law or file", command="study", out=None)


def test_the_small_preset_plans_from_the_bundled_schedule(tmp_path):
    result = invoke("study", "--preset", "small", "-o", tmp_path / "s", "--dry-run")
    assert result.exit_code == 0, result.stderr
    assert result.stdout.startswith("study small: ") and " tasks: " in result.stdout
