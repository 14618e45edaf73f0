"""apply-persistence errors: exit 1, one line on stderr naming what is wrong and how to fix it,
no output file, inputs untouched; usage errors exit 2; non-finite pixels are a warning."""

from functools import partial
from pathlib import Path

import numpy as np
import pytest
from astropy.io import fits

import fits_factory
from fits_factory import DAY, SHAPE, T0, frame_file, invoke, snapshot
from fits_factory import collect_leaked_files  # noqa: F401  (fixture)

MID = T0 + 150.0 / DAY      # a 100 s exposure starting here fits between the two of ``good``


@pytest.fixture
def good(tmp_path):
    """A valid earlier exposure (T0 to T0 + 100 s) and a valid current exposure (from T0 + 300 s)."""
    prev = frame_file(tmp_path / "prev.fits", np.full(SHAPE, 3e4), start=T0, exptime=100.0)
    cur = frame_file(tmp_path / "cur.fits", np.full(SHAPE, 50.0), start=T0 + 300.0 / DAY, exptime=100.0)
    return cur, prev


#: words that introduce what to do about an error
FIX_WORDS = ("use ", "give ", "add ", "check", "re-copy", "regenerate", "choose", "extract", "--",
             "must", "valid are", "not the same pixels")


#: ``expect_error(tmp_path, ARGS, *needles, out=, inputs=, any_of=, fix_words=)``: ``perscli apply-persistence
#: ARGS -o OUT`` fails in one line holding every needle (words looked for outside the paths: pytest names
#: tmp_path after the test, 'truncated', ...) and one of :data:`FIX_WORDS` (``fix_words=()``: none needed);
#: inputs (and an existing output) unchanged, no file in ``tmp_path`` (:func:`fits_factory.expect_error`)
expect_error = partial(fits_factory.expect_error, command="apply-persistence", fix_words=FIX_WORDS,
                       words_outside_paths=True)


#: a usage error (exit 2) in one line, nothing written, inputs unchanged (the shared harness's)
expect_usage_error = partial(fits_factory.expect_error, command="apply-persistence", code=2)


def place(role, bad, good):
    """Arguments with ``bad`` as the current exposure or as an earlier one."""
    cur, prev = good
    return [bad, prev] if role == "current" else [cur, bad]


# -- unreadable files --------------------------------------------------------------------------

@pytest.mark.parametrize("role", ["current", "previous"])
def test_corrupt_file(tmp_path, good, role):
    bad = tmp_path / "garbage.fits"
    bad.write_bytes(np.random.default_rng(0).bytes(5000))
    expect_error(tmp_path, place(role, bad, good), str(bad), "FITS")


@pytest.mark.parametrize("role", ["current", "previous"])
def test_text_file_that_starts_like_fits(tmp_path, good, role):
    bad = tmp_path / "fake.fits"
    bad.write_bytes(b"SIMPLE  =                    T" + b" " * 50 + b"not a header " * 300)
    expect_error(tmp_path, place(role, bad, good), str(bad), any_of=("FITS", "truncated"))


@pytest.mark.parametrize("role", ["current", "previous"])
def test_empty_file(tmp_path, good, role):
    bad = tmp_path / "empty.fits"
    bad.write_bytes(b"")
    expect_error(tmp_path, place(role, bad, good), str(bad), any_of=("FITS", "empty"))


@pytest.mark.parametrize("role", ["current", "previous"])
@pytest.mark.parametrize("keep", [2880 * 2 + 1000, 2880 * 2])
def test_truncated_file(tmp_path, good, role, keep, collect_leaked_files):
    bad = frame_file(tmp_path / "cut.fits", np.full(SHAPE, 7.0), start=MID)
    raw = Path(bad).read_bytes()
    assert len(raw) > keep + 2880                          # the cut is inside the data
    with open(bad, "wb") as fh:
        fh.write(raw[:keep])
    expect_error(tmp_path, place(role, bad, good), bad, "truncated")


def test_file_truncated_in_its_extension_header(tmp_path, good, collect_leaked_files):
    bad = frame_file(tmp_path / "cut.fits", np.full(SHAPE, 7.0), start=MID)
    raw = Path(bad).read_bytes()
    with open(bad, "wb") as fh:
        fh.write(raw[:2880 + 1000])                        # primary header + part of the SCI header
    expect_error(tmp_path, place("previous", bad, good), bad, "truncated")


@pytest.mark.parametrize("role", ["current", "previous"])
def test_nonexistent_file(tmp_path, good, role):
    missing = str(tmp_path / "nope.fits")
    expect_error(tmp_path, place(role, missing, good), missing, "no such file", fix_words=())


@pytest.mark.parametrize("role", ["current", "previous"])
def test_directory_as_input(tmp_path, good, role):
    folder = tmp_path / "adir"
    folder.mkdir()
    expect_error(tmp_path, place(role, folder, good), str(folder), "is a directory", fix_words=())


@pytest.mark.parametrize("role", ["current", "previous"])
def test_data_that_do_not_match_their_datasum(tmp_path, good, role):
    bad = frame_file(tmp_path / "flipped.fits", np.full(SHAPE, 7.0), start=MID, checksum=True)
    raw = bytearray(Path(bad).read_bytes())
    raw[2 * 2880 + 100] ^= 0x01                            # one bit of the SCI data, same size
    Path(bad).write_bytes(bytes(raw))
    expect_error(tmp_path, place(role, bad, good), bad, "DATASUM", "re-copy")


# -- units, gain, timing -----------------------------------------------------------------------

@pytest.mark.parametrize("role", ["current", "previous"])
def test_missing_bunit(tmp_path, good, role):
    bad = frame_file(tmp_path / "nounit.fits", bunit=None, start=MID)
    expect_error(tmp_path, place(role, bad, good), bad, "BUNIT", "--units")


def test_missing_bunit_is_fixed_by_units(tmp_path, good):
    cur, _ = good
    prev = frame_file(tmp_path / "nounit.fits", np.full(SHAPE, 3e4), bunit=None, start=T0)
    result = invoke("apply-persistence", cur, prev, "-o", tmp_path / "out.fits", "--units", "electron")
    assert result.exit_code == 0, result.output
    assert (tmp_path / "out.fits").exists()


@pytest.mark.parametrize("role", ["current", "previous"])
def test_unknown_bunit(tmp_path, good, role):
    bad = frame_file(tmp_path / "jy.fits", bunit="Jy", start=MID)
    expect_error(tmp_path, place(role, bad, good), bad, "BUNIT='Jy'", "electron, electron/s, DN or DN/s")


def test_unknown_units_option(tmp_path, good):
    expect_error(tmp_path, [*good, "--units", "Jy"], "--units='Jy'", "electron/s")


@pytest.mark.parametrize("role", ["current", "previous"])
def test_dn_without_gain(tmp_path, good, role):
    bad = frame_file(tmp_path / "dn.fits", np.full(SHAPE, 100.0), bunit="DN", start=MID)
    expect_error(tmp_path, place(role, bad, good), bad, "GAIN", "--gain")


def test_dn_without_gain_is_fixed_by_gain(tmp_path, good):
    cur, _ = good
    prev = frame_file(tmp_path / "dn.fits", np.full(SHAPE, 1e4), bunit="DN", start=T0)
    result = invoke("apply-persistence", cur, prev, "-o", tmp_path / "out.fits", "--gain", "2")
    assert result.exit_code == 0, result.output


@pytest.mark.parametrize("role", ["current", "previous"])
def test_missing_timing(tmp_path, good, role):
    bad = frame_file(tmp_path / "notime.fits", start=None)
    msg = expect_error(tmp_path, place(role, bad, good), bad, "no exposure timing", "EXPSTART/EXPEND",
                       "MJD-BEG/MJD-END", "DATE-OBS", "--gap", "--exptime")
    assert msg.count(bad) == 1


def test_missing_timing_is_fixed_by_gap(tmp_path):
    prev = frame_file(tmp_path / "prev.fits", np.full(SHAPE, 3e4), start=None, exptime=100.0)
    cur = frame_file(tmp_path / "cur.fits", start=None, exptime=None)
    result = invoke("apply-persistence", cur, prev, "-o", tmp_path / "out.fits", "--gap", "30", "--exptime", "50")
    assert result.exit_code == 0, result.output
    with fits.open(tmp_path / "out.fits") as hdul:
        assert hdul[0].header["PSP01DT"] == pytest.approx(30.0)


@pytest.mark.parametrize("role", ["current", "previous"])
def test_bad_date_obs_names_the_file(tmp_path, good, role):
    bad = frame_file(tmp_path / "baddate.fits", start=None, extra={"DATE-OBS": "2023-02-30T00:00:00"})
    expect_error(tmp_path, place(role, bad, good), bad, "DATE-OBS='2023-02-30T00:00:00'", "YYYY-MM-DDThh:mm:ss")


def test_date_obs_with_a_utc_offset_is_not_a_crash(tmp_path, good):
    _, prev = good
    cur = frame_file(tmp_path / "tz.fits", start=None, exptime=100.0, extra={"DATE-OBS": "2023-02-26T00:00:00+00:00"})
    out = tmp_path / "out.fits"
    result = invoke("apply-persistence", cur, prev, "-o", out)
    assert result.exception is None or isinstance(result.exception, SystemExit), repr(result.exception)
    if result.exit_code == 0:
        with fits.open(out) as hdul:               # 2023-02-26T00:00:00 UTC is MJD 60001
            assert hdul[0].header["PSP01DT"] == pytest.approx(DAY - 100.0)
    else:
        assert result.exit_code == 1
        assert len(result.stderr.splitlines()) == 1 and "DATE-OBS" in result.stderr


def test_previous_ends_after_current_starts(tmp_path, good):
    cur, _ = good
    late = frame_file(tmp_path / "late.fits", start=T0 + 250.0 / DAY, exptime=100.0)   # ends 50 s into cur
    msg = expect_error(tmp_path, [cur, late], late, cur, "not an earlier exposure", "check the order")
    assert msg.index(late) < msg.index(cur)


def test_previous_after_current_given_in_the_wrong_order(tmp_path, good):
    cur, prev = good
    expect_error(tmp_path, [prev, cur], "not an earlier exposure", "check the order or the timestamps")


def test_mismatched_shapes(tmp_path, good):
    cur, _ = good
    small = frame_file(tmp_path / "small.fits", np.ones((16, 32)), start=T0)
    expect_error(tmp_path, [cur, small], small, "(16, 32)", "(32, 32)", "same detector area")


def test_mismatched_subarray_offsets(tmp_path, good):
    cur = frame_file(tmp_path / "cur2.fits", start=T0 + 300.0 / DAY, extra={"LTV1": 0.0, "LTV2": 0.0})
    # a frame placed by LTV1/LTV2 beside the current one, sharing no detector pixel
    apart = frame_file(tmp_path / "apart.fits", start=T0, extra={"LTV1": -40.0, "LTV2": 0.0})
    expect_error(tmp_path, [cur, apart], apart, "LTV1/LTV2", "no pixel in common")


# -- model and parameters ----------------------------------------------------------------------

def test_unknown_model(tmp_path, good):
    expect_error(tmp_path, [*good, "--law", "optimistic"], "'optimistic'", "typical, pessimistic")


def test_param_with_unknown_key(tmp_path, good):
    expect_error(tmp_path, [*good, "--set", "persistence.beta=2"], "'beta'", "valid are A, x0, dx, alpha, gamma, half_well")


def test_param_that_is_not_a_number(tmp_path, good):
    expect_error(tmp_path, [*good, "--set", "persistence.gamma=fast"], "persistence.gamma", "finite number", "'fast'")


@pytest.mark.parametrize("text", ["gamma", "gamma:1.1"])
def test_param_that_is_not_key_value(tmp_path, good, text):
    # the older spelling (--param KEY=VALUE): its deprecation warning, then the one line of the error
    expect_error(tmp_path, [*good, "--param", text], f"'{text}'", "KEY=VALUE", "gamma=1.1", allow_warnings=True)


def test_param_on_the_linear_model(tmp_path, good):
    expect_error(tmp_path, [*good, "--law", "galsim-linear", "--set", "persistence.gamma=1"], "linear model", fix_words=())


# -- outputs -----------------------------------------------------------------------------------

def test_existing_output_without_overwrite(tmp_path, good):
    out = tmp_path / "out.fits"
    out.write_bytes(b"precious")
    expect_error(tmp_path, list(good), str(out), "already exists", "--overwrite", out=out)
    assert out.read_bytes() == b"precious"


def test_existing_output_with_overwrite_is_replaced(tmp_path, good):
    out = tmp_path / "out.fits"
    out.write_bytes(b"precious")
    result = invoke("apply-persistence", *good, "-o", out, "--overwrite")
    assert result.exit_code == 0, result.output
    with fits.open(out) as hdul:
        assert hdul[0].header["PSNPREV"] == 1


@pytest.mark.parametrize("which", ["current", "previous"])
@pytest.mark.parametrize("overwrite", [False, True])
def test_output_equal_to_an_input(tmp_path, good, which, overwrite):
    cur, prev = good
    target = cur if which == "current" else prev
    args = [cur, prev] + (["--overwrite"] if overwrite else [])
    expect_error(tmp_path, args, target, "is also an input", "choose another output", out=target,
                 inputs=[cur, prev])


def test_output_in_a_missing_folder(tmp_path, good):
    out = tmp_path / "missing" / "out.fits"
    expect_error(tmp_path, list(good), "does not exist", str(tmp_path / "missing"), out=out, fix_words=())


@pytest.mark.parametrize("overwrite", [False, True])
def test_output_that_is_a_directory(tmp_path, good, overwrite):
    folder = tmp_path / "outdir"
    folder.mkdir()
    args = list(good) + (["--overwrite"] if overwrite else [])
    expect_error(tmp_path, args, str(folder), "directory", out=folder)


# -- usage errors: exit 2 ----------------------------------------------------------------------

def test_missing_output_option(tmp_path, good):
    expect_usage_error(tmp_path, list(good), "Missing option '-o' / '--output'", out=None)


def test_missing_previous(tmp_path, good):
    cur, _ = good
    expect_usage_error(tmp_path, [cur, "-o", tmp_path / "out.fits"], "PREVIOUS")


@pytest.mark.parametrize("option, value, needle", [
    ("--mode", "multiply", "'multiply' is not one of 'add', 'subtract', 'predict'"),
    ("--time-model", "approx", "--time-model"),
    ("--combine", "mean", "--combine"),
    ("--max-previous", "-1", "--max-previous"),
    ("--gain", "0", "--gain"),
    ("--gain", "abc", "--gain"),
    ("--gap", "-5", "--gap"),
    ("--workers", "0", "--workers"),
])
def test_bad_option_values(tmp_path, good, option, value, needle):
    expect_usage_error(tmp_path, [*good, "-o", tmp_path / "out.fits", option, value], needle)


def test_unknown_option(tmp_path, good):
    expect_usage_error(tmp_path, [*good, "-o", tmp_path / "out.fits", "--frobnicate"], "No such option")


# -- non-finite pixels: a warning, not an error --------------------------------------------------

def test_nan_pixels_in_an_earlier_frame_count_as_zero_with_a_warning(tmp_path, good):
    cur, _ = good
    data = np.full(SHAPE, 3e4)
    data[0, 0] = np.nan
    data[5, 7] = np.inf
    data[9, 9] = -np.inf
    prev = frame_file(tmp_path / "nan.fits", data, start=T0)
    before = snapshot(cur, prev)
    out = tmp_path / "pers.fits"
    result = invoke("apply-persistence", cur, prev, "-o", out, "--mode", "predict")
    assert result.exit_code == 0, result.output
    lines = result.stderr.splitlines()
    assert len(lines) == 1, result.stderr
    assert "non-finite" in lines[0] and prev in lines[0] and "3 non-finite" in lines[0]
    assert lines[0].startswith("perscli: warning:")
    with fits.open(out) as hdul:
        pers = hdul[1].data
        assert np.all(np.isfinite(pers))
        assert pers[0, 0] == 0 and pers[5, 7] == 0 and pers[9, 9] == 0
        assert pers[1, 1] > 0
    assert snapshot(cur, prev) == before


def test_blank_pixels_in_an_integer_earlier_frame_count_as_zero_with_a_warning(tmp_path, good):
    cur, _ = good
    stored = np.full(SHAPE, 10000, dtype=np.int16)               # 20000 DN with BSCALE = 2
    stored[4, 4] = 32767                                          # = BLANK: 65534 DN if misread
    hdr = fits.Header({"BUNIT": "DN", "GAIN": 2.0, "EXPSTART": T0, "EXPEND": T0 + 100.0 / DAY, "EXPTIME": 100.0})
    sci = fits.ImageHDU(stored, hdr, name="SCI")
    sci.header["BSCALE"] = 2.0
    sci.header["BZERO"] = 0.0
    sci.header["BLANK"] = 32767
    prev = str(tmp_path / "blank.fits")
    fits.HDUList([fits.PrimaryHDU(), sci]).writeto(prev)
    with fits.open(prev) as hdul:
        assert np.isnan(hdul[1].data[4, 4]) and hdul[1].data[0, 0] == 20000     # what the file means
    out = tmp_path / "pers.fits"
    result = invoke("apply-persistence", cur, prev, "-o", out, "--mode", "predict")
    assert result.exit_code == 0, result.output
    assert "1 non-finite" in result.stderr
    with fits.open(out) as hdul:
        assert hdul[1].data[4, 4] == 0
        assert hdul[1].data[0, 0] > 0


def test_finite_earlier_frames_give_no_warning(tmp_path, good):
    result = invoke("apply-persistence", *good, "-o", tmp_path / "out.fits")
    assert result.exit_code == 0
    assert result.stderr == ""
    assert result.stdout == ""
