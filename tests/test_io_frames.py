"""perscli.io.frames: layouts, units, gain, timing, fluence and DATASUM of the frames perscli reads."""

import gc
import io
import os
import warnings
from pathlib import Path

import numpy as np
import pytest
from astropy.io import fits
from astropy.time import Time

from perscli import PerscliError
from perscli.io.frames import open_frame, require_timing

from fits_factory import DAY, SHAPE, T0, cube_file, frame_file, image_file, timing, wfc3_ramp_file
from fits_factory import collect_leaked_files  # noqa: F401  (fixture)


@pytest.fixture
def opened():
    """``opened(path, **kw)``: open_frame, closed again at teardown."""
    frames = []

    def make(path, **kw):
        frame = open_frame(str(path), **kw)
        frames.append(frame)
        return frame

    yield make
    for frame in frames:
        frame.close()


def ramp_reads(n=4, shape=SHAPE):
    """Reads in time order whose values say which read they are: read k is 100 * k + 5 everywhere."""
    return [np.full(shape, 100.0 * k + 5, dtype=np.float32) for k in range(n)]


# -- where the pixels are ----------------------------------------------------------------------

def test_image_in_sci_extension(tmp_path, opened):
    data = np.arange(32 * 32, dtype=np.float32).reshape(SHAPE)
    frame = opened(image_file(tmp_path / "a.fits", data, {"BUNIT": "electron"}))
    assert frame.layout == "image"
    assert frame.sci == [1]
    assert frame.shape == SHAPE
    assert frame.nreads == 1
    assert not frame.is_ramp
    np.testing.assert_array_equal(frame.planes()[0], data)


def test_image_in_primary_hdu(tmp_path, opened):
    data = np.arange(32 * 32, dtype=np.float64).reshape(SHAPE)
    frame = opened(image_file(tmp_path / "a.fits", data, {"BUNIT": "electron"}, primary=True))
    assert frame.layout == "image"
    assert frame.sci == [0]
    np.testing.assert_array_equal(frame.planes()[0], data)


def test_sci_extension_wins_over_primary_data(tmp_path, opened):
    hdul = fits.HDUList([fits.PrimaryHDU(np.zeros((8, 8))),
                         fits.ImageHDU(np.ones(SHAPE), fits.Header({"BUNIT": "electron"}), name="SCI")])
    hdul.writeto(tmp_path / "a.fits")
    frame = opened(tmp_path / "a.fits")
    assert frame.sci == [1]
    assert frame.shape == SHAPE


def test_no_image_anywhere_is_an_error(tmp_path):
    fits.HDUList([fits.PrimaryHDU(header=fits.Header({"BUNIT": "electron"}))]).writeto(tmp_path / "a.fits")
    with pytest.raises(PerscliError, match="no image data"):
        open_frame(str(tmp_path / "a.fits"))


def test_four_axes_is_an_error(tmp_path):
    image_file(tmp_path / "a.fits", np.zeros((2, 2, 4, 4)), {"BUNIT": "electron"})
    with pytest.raises(PerscliError, match="4 axes"):
        open_frame(str(tmp_path / "a.fits"))


def test_cube_with_readtimes_table(tmp_path, opened):
    reads = ramp_reads(5)
    times = [0.0, 2.9, 10.0, 50.0, 139.8]
    frame = opened(cube_file(tmp_path / "c.fits", np.stack(reads), times, {"BUNIT": "electron"}))
    assert frame.layout == "cube"
    assert frame.is_ramp
    assert frame.nreads == 5
    assert frame.shape == SHAPE
    assert frame.read_times.tolist() == times
    assert [float(p[0, 0]) for p in frame.planes()] == [5.0, 105.0, 205.0, 305.0, 405.0]


def test_cube_without_readtimes_is_an_error(tmp_path):
    image_file(tmp_path / "c.fits", np.zeros((3, 8, 8)), {"BUNIT": "electron"}, primary=True)
    with pytest.raises(PerscliError, match="READTIMES"):
        open_frame(str(tmp_path / "c.fits"))


def test_cube_readtimes_row_count_must_match(tmp_path):
    cube_file(tmp_path / "c.fits", np.zeros((3, 8, 8)), [0.0, 1.0], {"BUNIT": "electron"})
    with pytest.raises(PerscliError, match="2 rows but the cube has 3 reads"):
        open_frame(str(tmp_path / "c.fits"))


def test_cube_readtimes_without_time_column_is_an_error(tmp_path):
    cube_file(tmp_path / "c.fits", np.zeros((2, 8, 8)), [0.0, 1.0], {"BUNIT": "electron"}, column="T")
    with pytest.raises(PerscliError, match="no TIME column"):
        open_frame(str(tmp_path / "c.fits"))


def test_cube_readtimes_must_increase(tmp_path):
    cube_file(tmp_path / "c.fits", np.zeros((3, 8, 8)), [0.0, 5.0, 2.0], {"BUNIT": "electron"})
    with pytest.raises(PerscliError, match="increasing"):
        open_frame(str(tmp_path / "c.fits"))


def test_wfc3_ramp_reads_are_ordered_zeroth_first(tmp_path, opened):
    reads = ramp_reads(4)
    samptimes = [0.0, 2.93, 22.9, 52.9]
    path = wfc3_ramp_file(tmp_path / "raw.fits", reads, samptimes, {"BUNIT": "electron"})
    frame = opened(path)
    assert frame.layout == "wfc3-ramp"
    assert frame.nreads == 4
    # SCI,NSAMP (=SCI,4, HDU 10 after PRIMARY and three SCI/ERR/DQ groups) is the zeroth read, SCI,1 the last
    assert frame.sci == [10, 7, 4, 1]
    assert [float(p[0, 0]) for p in frame.planes()] == [5.0, 105.0, 205.0, 305.0]
    assert frame.read_times.tolist() == samptimes


def test_wfc3_ramp_order_comes_from_extver_not_file_position(tmp_path, opened):
    reads = ramp_reads(4)
    path = wfc3_ramp_file(tmp_path / "raw.fits", reads, [0.0, 1.0, 2.0, 3.0], {"BUNIT": "electron"},
                          file_order=[3, 1, 4, 2])
    frame = opened(path)
    assert [float(p[0, 0]) for p in frame.planes()] == [5.0, 105.0, 205.0, 305.0]
    assert frame.read_times.tolist() == [0.0, 1.0, 2.0, 3.0]


def test_several_sci_without_samptime_is_an_error(tmp_path):
    path = wfc3_ramp_file(tmp_path / "raw.fits", ramp_reads(3), [0, 1, 2], {"BUNIT": "electron"}, samptime=False)
    with pytest.raises(PerscliError, match="SAMPTIME") as err:
        open_frame(path)
    assert "3 SCI extensions" in str(err.value)


def test_ramp_truncated_in_the_zeroth_read_header_is_an_error(tmp_path, collect_leaked_files):
    path = wfc3_ramp_file(tmp_path / "raw.fits", ramp_reads(4), [0.0, 1.0, 2.0, 3.0], {"BUNIT": "electron"})
    with fits.open(path) as hdul:
        cut = hdul[("SCI", 4)].fileinfo()["hdrLoc"] + 500     # inside the header of the zeroth read
    raw = Path(path).read_bytes()
    with open(path, "wb") as fh:
        fh.write(raw[:cut])
    with pytest.raises(PerscliError, match="truncated"):
        frame = open_frame(path)
        frame.close()


# -- units -------------------------------------------------------------------------------------

@pytest.mark.parametrize("bunit, unit", [
    ("electron", "electron"), ("electron/s", "electron/s"), ("DN", "DN"), ("DN/s", "DN/s"),
    ("ELECTRONS", "electron"), ("ELECTRONS/S", "electron/s"), ("COUNTS", "DN"), ("COUNTS/S", "DN/s"),
    ("Electrons/s", "electron/s"), ("dn", "DN"), ("dn/S", "DN/s"), ("counts", "DN"), ("Counts/S", "DN/s"),
    ("  electrons  ", "electron"),
])
def test_bunit_spellings(tmp_path, opened, bunit, unit):
    frame = opened(frame_file(tmp_path / "a.fits", bunit=bunit, extra={"GAIN": 2.0}))
    assert frame.unit == unit


def test_bunit_from_primary_header(tmp_path, opened):
    path = image_file(tmp_path / "a.fits", np.ones(SHAPE), {}, primary_keywords={"BUNIT": "COUNTS/S"})
    assert opened(path).unit == "DN/s"


def test_bunit_of_science_header_wins_over_primary(tmp_path, opened):
    path = image_file(tmp_path / "a.fits", np.ones(SHAPE), {"BUNIT": "ELECTRONS"},
                      primary_keywords={"BUNIT": "COUNTS"})
    assert opened(path).unit == "electron"


@pytest.mark.parametrize("override, unit", [("electron/s", "electron/s"), ("COUNTS", "DN"), ("dn/s", "DN/s")])
def test_units_override_bunit(tmp_path, opened, override, unit):
    path = frame_file(tmp_path / "a.fits", bunit="electron")
    assert opened(path, units=override).unit == unit


def test_units_override_needs_no_bunit(tmp_path, opened):
    path = frame_file(tmp_path / "a.fits", bunit=None)
    assert opened(path, units="electron").unit == "electron"


def test_unknown_units_override_names_units_option(tmp_path):
    path = frame_file(tmp_path / "a.fits")
    with pytest.raises(PerscliError, match="--units='furlongs'"):
        open_frame(path, units="furlongs")


def test_unknown_bunit_is_an_error(tmp_path):
    path = frame_file(tmp_path / "a.fits", bunit="Jy")
    with pytest.raises(PerscliError) as err:
        open_frame(path)
    msg = str(err.value)
    assert "BUNIT='Jy'" in msg and path in msg and "electron/s" in msg


def test_missing_bunit_is_an_error(tmp_path):
    path = frame_file(tmp_path / "a.fits", bunit=None)
    with pytest.raises(PerscliError) as err:
        open_frame(path)
    msg = str(err.value)
    assert "BUNIT" in msg and "--units" in msg and path in msg


# -- gain --------------------------------------------------------------------------------------

def test_gain_from_gain(tmp_path, opened):
    assert opened(frame_file(tmp_path / "a.fits", bunit="DN", extra={"GAIN": 2.5})).gain == 2.5


def test_gain_from_ccdgain(tmp_path, opened):
    assert opened(frame_file(tmp_path / "a.fits", bunit="DN", extra={"CCDGAIN": 2.4})).gain == 2.4


def test_gain_wins_over_ccdgain(tmp_path, opened):
    frame = opened(frame_file(tmp_path / "a.fits", bunit="DN", extra={"GAIN": 1.5, "CCDGAIN": 2.4}))
    assert frame.gain == 1.5


def test_gain_from_primary_header(tmp_path, opened):
    path = image_file(tmp_path / "a.fits", np.ones(SHAPE), {"BUNIT": "DN"}, primary_keywords={"CCDGAIN": 2.0})
    assert opened(path).gain == 2.0


def test_gain_override(tmp_path, opened):
    frame = opened(frame_file(tmp_path / "a.fits", bunit="DN", extra={"GAIN": 2.5}), gain=4.0)
    assert frame.gain == 4.0
    data, scale = frame.fluence()
    assert scale == 4.0


def test_dn_without_gain_names_gain_option(tmp_path, opened):
    path = frame_file(tmp_path / "a.fits", bunit="DN")
    frame = opened(path)
    assert frame.gain is None
    with pytest.raises(PerscliError) as err:
        frame.fluence()
    msg = str(err.value)
    assert "--gain" in msg and "GAIN" in msg and "CCDGAIN" in msg and path in msg


@pytest.mark.parametrize("value, match", [(0.0, "must be positive"), (-2.0, "must be positive"),
                                          ("high", "not a number")])
def test_bad_gain_keyword(tmp_path, value, match):
    path = frame_file(tmp_path / "a.fits", bunit="DN", extra={"GAIN": value})
    with pytest.raises(PerscliError, match=match):
        open_frame(path)


# -- timing ------------------------------------------------------------------------------------

def test_timing_from_expstart_expend(tmp_path, opened):
    frame = opened(frame_file(tmp_path / "a.fits", start=T0, exptime=139.8))
    assert frame.start == T0
    assert frame.end == pytest.approx(T0 + 139.8 / DAY, abs=1e-12)
    assert frame.exptime == 139.8
    assert frame.timing_source == "EXPSTART/EXPEND"


def test_timing_from_mjd_beg_end(tmp_path, opened):
    path = frame_file(tmp_path / "a.fits", start=None, exptime=None,
                      extra={"MJD-BEG": 59000.25, "MJD-END": 59000.26})
    frame = opened(path)
    assert (frame.start, frame.end) == (59000.25, 59000.26)
    assert frame.timing_source == "MJD-BEG/MJD-END"
    # no EXPTIME: the exposure time is end - start
    assert frame.exptime == pytest.approx(0.01 * DAY, rel=1e-9)


def test_expstart_wins_over_mjd_beg(tmp_path, opened):
    path = frame_file(tmp_path / "a.fits", start=T0, extra={"MJD-BEG": 59000.25, "MJD-END": 59000.26})
    assert opened(path).start == T0


def test_incomplete_expstart_falls_back_to_mjd_beg(tmp_path, opened):
    path = frame_file(tmp_path / "a.fits", start=None,
                      extra={"EXPSTART": T0, "MJD-BEG": 59000.25, "MJD-END": 59000.26})
    frame = opened(path)
    assert (frame.start, frame.end) == (59000.25, 59000.26)


def test_timing_from_date_obs_and_exptime(tmp_path, opened):
    path = frame_file(tmp_path / "a.fits", start=None, exptime=100.0, extra={"DATE-OBS": "2020-01-01T00:00:00"})
    frame = opened(path)
    assert frame.start == pytest.approx(58849.0, abs=1e-10)
    assert frame.end == pytest.approx(58849.0 + 100.0 / DAY, abs=1e-10)
    assert frame.timing_source == "DATE-OBS+EXPTIME"


def test_timing_from_date_obs_plus_time_obs(tmp_path, opened):
    path = frame_file(tmp_path / "a.fits", start=None, exptime=60.0,
                      extra={"DATE-OBS": "2000-01-01", "TIME-OBS": "12:00:00"})
    frame = opened(path)
    assert frame.start == pytest.approx(51544.5, abs=1e-10)
    assert frame.end == pytest.approx(51544.5 + 60.0 / DAY, abs=1e-10)


@pytest.mark.parametrize("date_obs", ["2024-02-29T23:59:59.5", "1999-12-31T06:30:00", "2016-07-04T01:02:03.25Z"])
def test_date_obs_agrees_with_astropy_time(tmp_path, opened, date_obs):
    path = frame_file(tmp_path / "a.fits", start=None, exptime=10.0, extra={"DATE-OBS": date_obs})
    expected = Time(date_obs.rstrip("Z"), format="isot", scale="utc").mjd
    assert opened(path).start == pytest.approx(expected, abs=1e-9)


def test_date_obs_with_xposure(tmp_path, opened):
    path = frame_file(tmp_path / "a.fits", start=None, exptime=None,
                      extra={"DATE-OBS": "2020-01-01T00:00:00", "XPOSURE": 86.4})
    frame = opened(path)
    assert frame.exptime == 86.4
    assert frame.end == pytest.approx(58849.001, abs=1e-10)


def test_date_obs_with_exptime_argument(tmp_path, opened):
    path = frame_file(tmp_path / "a.fits", start=None, exptime=None, extra={"DATE-OBS": "2020-01-01T00:00:00"})
    frame = opened(path, exptime=864.0)
    assert frame.end == pytest.approx(58849.01, abs=1e-10)


def test_header_exptime_wins_over_exptime_argument(tmp_path, opened):
    frame = opened(frame_file(tmp_path / "a.fits", exptime=50.0), exptime=864.0)
    assert frame.exptime == 50.0


def test_date_obs_without_exposure_time_has_no_timing(tmp_path, opened):
    path = frame_file(tmp_path / "a.fits", start=None, exptime=None, extra={"DATE-OBS": "2020-01-01T00:00:00"})
    frame = opened(path)
    assert frame.start is None and frame.end is None


def test_bad_date_obs_is_an_error(tmp_path):
    path = frame_file(tmp_path / "a.fits", start=None, extra={"DATE-OBS": "yesterday"})
    with pytest.raises(PerscliError, match="DATE-OBS='yesterday'"):
        open_frame(path)


def test_missing_timing_is_reported_by_require_timing(tmp_path, opened):
    path = frame_file(tmp_path / "a.fits", start=None)
    frame = opened(path)
    assert frame.start is None and frame.end is None
    assert frame.exptime == 100.0
    with pytest.raises(PerscliError) as err:
        require_timing(frame)
    msg = str(err.value)
    for word in (path, "EXPSTART/EXPEND", "MJD-BEG/MJD-END", "DATE-OBS", "EXPTIME", "--gap", "--exptime"):
        assert word in msg


def test_end_before_start_is_an_error(tmp_path):
    path = frame_file(tmp_path / "a.fits", start=None, extra={"EXPSTART": T0, "EXPEND": T0 - 0.001})
    with pytest.raises(PerscliError, match="ends .* before it starts"):
        open_frame(path)


def test_non_numeric_timing_keyword_is_an_error(tmp_path):
    path = frame_file(tmp_path / "a.fits", start=None, extra={"EXPSTART": "soon", "EXPEND": T0})
    with pytest.raises(PerscliError, match="EXPSTART='soon' is not a number"):
        open_frame(path)


# -- fluence -----------------------------------------------------------------------------------

@pytest.mark.parametrize("bunit, extra, factor", [
    ("electron", {}, 1.0),
    ("ELECTRONS", {}, 1.0),
    ("electron/s", {}, 80.0),            # rate * EXPTIME
    ("ELECTRONS/S", {}, 80.0),
    ("DN", {"GAIN": 2.5}, 2.5),          # DN * gain
    ("COUNTS", {"CCDGAIN": 2.0}, 2.0),
    ("DN/s", {"GAIN": 1.5}, 120.0),      # DN/s * gain * EXPTIME
    ("COUNTS/S", {"CCDGAIN": 2.5}, 200.0),
])
def test_fluence_of_an_image_in_electrons(tmp_path, opened, bunit, extra, factor):
    data = np.random.default_rng(3).uniform(0, 1000, SHAPE).astype(np.float32)
    frame = opened(frame_file(tmp_path / "a.fits", data, exptime=80.0, bunit=bunit, extra=extra))
    array, scale = frame.fluence()
    np.testing.assert_allclose(np.asarray(array, dtype=np.float64) * scale, data.astype(np.float64) * factor,
                               rtol=1e-12)


def test_fluence_of_a_rate_uses_end_minus_start_without_exptime(tmp_path, opened):
    data = np.full(SHAPE, 3.0)
    path = frame_file(tmp_path / "a.fits", data, start=None, exptime=None, bunit="electron/s",
                      extra={"MJD-BEG": T0, "MJD-END": T0 + 50.0 / DAY})
    array, scale = opened(path).fluence()
    np.testing.assert_allclose(array * scale, 150.0, rtol=1e-6)


def test_fluence_of_a_rate_without_exposure_time_names_exptime_option(tmp_path, opened):
    frame = opened(frame_file(tmp_path / "a.fits", start=None, exptime=None, bunit="electron/s"))
    with pytest.raises(PerscliError, match="--exptime"):
        frame.fluence()


def test_fluence_of_integer_data_is_float(tmp_path, opened):
    data = np.arange(32 * 32, dtype=np.int16).reshape(SHAPE)
    frame = opened(frame_file(tmp_path / "a.fits", data, bunit="DN", extra={"GAIN": 2.0}))
    array, scale = frame.fluence()
    assert array.dtype.kind == "f"
    np.testing.assert_array_equal(array * scale, data * 2.0)


def test_fluence_of_unsigned_data_with_bzero(tmp_path, opened):
    data = np.array([[0, 40000], [65535, 12]], dtype=np.uint16)
    frame = opened(frame_file(tmp_path / "a.fits", data, bunit="DN", extra={"GAIN": 1.0}))
    array, scale = frame.fluence()
    np.testing.assert_array_equal(array * scale, data.astype(np.float64))


def test_fluence_of_a_cube_is_last_minus_zeroth_read(tmp_path, opened):
    rng = np.random.default_rng(5)
    cube = np.cumsum(rng.uniform(0, 100, (4,) + SHAPE), axis=0) + 1000.0   # zeroth read has a pedestal
    frame = opened(cube_file(tmp_path / "c.fits", cube, [0.0, 1.0, 2.0, 3.0], {"BUNIT": "electron"}))
    array, scale = frame.fluence()
    np.testing.assert_allclose(array * scale, cube[-1] - cube[0], rtol=1e-12)


def test_fluence_of_a_wfc3_ramp_in_dn_is_last_minus_zeroth_read_times_gain(tmp_path, opened):
    rng = np.random.default_rng(6)
    reads = list(np.cumsum(rng.uniform(0, 100, (4,) + SHAPE), axis=0) + 1000.0)
    path = wfc3_ramp_file(tmp_path / "raw.fits", reads, [0.0, 2.9, 5.9, 8.8], {"BUNIT": "COUNTS"},
                          primary_keywords={"CCDGAIN": 2.5})
    array, scale = opened(path).fluence()
    np.testing.assert_allclose(array * scale, (reads[-1] - reads[0]) * 2.5, rtol=1e-12)


def test_fluence_of_a_wfc3_rate_ramp_multiplies_each_read_by_its_samptime(tmp_path, opened):
    # a WFC3 ima file stores each read as charge / SAMPTIME
    charge = [np.full(SHAPE, 50.0), np.full(SHAPE, 250.0), np.full(SHAPE, 650.0)]
    times = [1.0, 5.0, 13.0]
    rates = [c / t for c, t in zip(charge, times)]
    path = wfc3_ramp_file(tmp_path / "ima.fits", rates, times, {"BUNIT": "ELECTRONS/S"})
    array, scale = opened(path).fluence()
    np.testing.assert_allclose(array * scale, 600.0, rtol=1e-12)


def test_fluence_of_a_calibrated_ima_is_its_last_read(tmp_path, opened):
    # calwf3's ZOFFCORR has subtracted the zeroth read from every read: the last read is the signal,
    # in electrons as it is, in e-/s times its SAMPTIME; a raw-like ramp without it is last - zeroth
    reads = [np.full(SHAPE, 40.0), np.full(SHAPE, 240.0), np.full(SHAPE, 640.0)]
    times = [0.0, 5.0, 13.0]
    for zoff, unit, values, expected in (("COMPLETE", "ELECTRONS", reads, 640.0),
                                         ("PERFORM", "ELECTRONS", reads, 600.0),
                                         ("COMPLETE", "ELECTRONS/S", [r / max(t, 1.0) for r, t in zip(reads, times)],
                                          640.0)):
        path = wfc3_ramp_file(tmp_path / f"ima_{zoff}_{unit[-1]}.fits", values, times, {"BUNIT": unit},
                              primary_keywords={"ZOFFCORR": zoff})
        array, scale = opened(path).fluence()
        np.testing.assert_allclose(array * scale, expected, rtol=1e-12, err_msg=f"{zoff} {unit}")


def test_fluence_of_an_flt_is_rate_times_exptime(tmp_path, opened):
    path = frame_file(tmp_path / "flt.fits", np.full(SHAPE, 2.5), bunit="ELECTRONS/S", exptime=302.9)
    array, scale = opened(path).fluence()
    np.testing.assert_allclose(array * scale, 2.5 * 302.9, rtol=1e-6)


# -- placement on the detector -----------------------------------------------------------------

WFC3_IR = {"INSTRUME": "WFC3", "DETECTOR": "IR"}


@pytest.mark.parametrize("size, ltv, offset, border", [
    (138, (-438.0, -438.0), (438.0, 438.0), 5),     # raw/ima SQ128SUB, reference pixels around
    (128, (-443.0, -443.0), (443.0, 443.0), 0),     # its flt: trimmed, LTV moved by 5
    (1024, None, (-5.0, -5.0), 5),                  # raw/ima full frame without LTV: 5 (reference pixels)
    (1014, None, (0.0, 0.0), 0),                    # flt full frame without LTV: 0, as in the archive
    (100, None, None, 0),                           # any other size: unknown
])
def test_wfc3_ir_placement(tmp_path, opened, size, ltv, offset, border):
    extra = {"BUNIT": "ELECTRONS/S"}
    if ltv is not None:
        extra.update(LTV1=ltv[0], LTV2=ltv[1])
    path = image_file(tmp_path / "f.fits", np.zeros((size, size), np.float32), extra, primary_keywords=WFC3_IR)
    frame = opened(path)
    placement = frame.placement()
    assert frame.reference_border == border
    assert placement.offset == offset
    assert placement.science == (border, size - border, border, size - border)


def test_placement_of_other_frames_and_of_sections(tmp_path, opened):
    # a non-WFC3 frame of a WFC3 raw size has no reference border; LTV from the header (x, y)
    path = image_file(tmp_path / "sim.fits", np.zeros((138, 120), np.float32),
                      {"BUNIT": "electron", "LTV1": -10.0, "LTV2": 3.0})
    placement = opened(path).placement()
    assert placement.offset == (-3.0, 10.0) and placement.science == (0, 138, 0, 120)
    # a section of a WFC3 raw subarray: LTV moves with it, and the border stays where it was
    raw = image_file(tmp_path / "raw.fits", np.zeros((138, 138), np.float32),
                     {"BUNIT": "COUNTS", "LTV1": -438.0, "LTV2": -438.0}, primary_keywords=WFC3_IR)
    cut = opened(f"{raw}[1][3:40,101:138]").placement()      # FITS x 3-40, y 101-138
    assert cut.offset == (438.0 + 100, 438.0 + 2)
    assert cut.science == (0, 38 - 5, 3, 38)
    binned = image_file(tmp_path / "bin.fits", np.zeros((8, 8), np.float32), {"BUNIT": "electron", "LTM1_1": 0.5})
    assert opened(binned).placement().scale == (1.0, 0.5)


# -- DATASUM -----------------------------------------------------------------------------------

@pytest.mark.parametrize("dtype", [np.float32, np.float64, np.int16, np.int32, np.uint16, np.uint8])
@pytest.mark.parametrize("primary", [False, True])
def test_datasum_equals_astropy_datasum(tmp_path, opened, dtype, primary):
    rng = np.random.default_rng(11)
    shape = (31, 33)      # an odd number of bytes for uint8
    if np.dtype(dtype).kind == "f":
        data = rng.normal(0, 1e6, shape).astype(dtype)
    else:
        info = np.iinfo(dtype)
        data = rng.integers(info.min, info.max, shape, endpoint=True).astype(dtype)
    path = image_file(tmp_path / "a.fits", data, {"BUNIT": "electron"}, primary=primary, checksum=True)
    frame = opened(path)
    with fits.open(path) as hdul:
        expected = int(hdul[frame.sci[0]].header["DATASUM"])
    assert expected != 0
    assert frame.datasum(frame.sci[0]) == expected


def test_datasum_of_all_ones_words_folds_the_carries_like_astropy(tmp_path, opened):
    data = np.full((64, 64), -1, dtype=np.int32)         # every word 0xFFFFFFFF
    path = image_file(tmp_path / "a.fits", data, {"BUNIT": "DN"}, checksum=True)
    frame = opened(path)
    with fits.open(path) as hdul:
        assert frame.datasum(1) == int(hdul[1].header["DATASUM"])


def test_datasum_of_an_hdu_without_data_is_zero(tmp_path, opened):
    frame = opened(frame_file(tmp_path / "a.fits"))
    assert frame.datasum(0) == 0


def test_datasum_from_standard_input(tmp_path, opened):
    data = np.random.default_rng(2).normal(0, 100, SHAPE).astype(np.float32)
    path = image_file(tmp_path / "a.fits", data, {"BUNIT": "electron", **timing(T0)}, checksum=True)
    raw = Path(path).read_bytes()
    frame = opened("-", stdin=io.BytesIO(raw))
    assert frame.name == "-"
    assert frame.start == T0
    with fits.open(path) as hdul:
        assert frame.datasum(1) == int(hdul[1].header["DATASUM"])


def test_empty_standard_input_is_an_error():
    with pytest.raises(PerscliError, match="stdin: the input is empty"):
        open_frame("-", stdin=io.BytesIO(b""))


# -- unreadable files ----------------------------------------------------------------------------

def test_truncated_data_is_an_error(tmp_path, collect_leaked_files):
    path = frame_file(tmp_path / "a.fits")
    size = os.path.getsize(path)
    with open(path, "r+b") as fh:
        fh.truncate(size - 2880 - 1000)
    with pytest.raises(PerscliError, match="truncated"):
        open_frame(path)


def _cut(path, size):
    raw = Path(path).read_bytes()
    Path(path).write_bytes(raw[:size])
    return path


def test_truncated_file_is_closed_after_the_error(tmp_path, collect_leaked_files):
    path = _cut(frame_file(tmp_path / "a.fits"), 2 * 2880 + 1000)
    gc.collect()
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        with pytest.raises(PerscliError, match="truncated"):
            open_frame(path)
        still_open = _open_descriptors(path)
        gc.collect()
    leaked = [str(w.message) for w in caught if issubclass(w.category, ResourceWarning)]
    assert leaked == []
    assert still_open == 0


def test_a_warning_about_another_file_is_not_blamed_on_this_one(tmp_path, monkeypatch, opened):
    path = frame_file(tmp_path / "good.fits")
    real_exists = os.path.exists
    emitted = []

    def exists_while_gc_runs(name):
        # what the garbage collector emits when it closes a file leaked elsewhere, while perscli opens a file
        warnings.warn("unclosed file <_io.FileIO name='/data/truncated_runs/old.fits' mode='rb'>",
                      ResourceWarning)
        emitted.append(name)
        return real_exists(name)

    monkeypatch.setattr(os.path, "exists", exists_while_gc_runs)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", ResourceWarning)
        frame = opened(path)
    assert emitted                           # the warning was raised while the file was being opened
    assert frame.layout == "image"


def _open_descriptors(path):
    """How many of this process's file descriptors point at ``path``."""
    folder = "/proc/self/fd"
    if not os.path.isdir(folder):
        pytest.skip("needs /proc/self/fd")
    target = os.path.realpath(path)
    count = 0
    for fd in os.listdir(folder):
        try:
            if os.readlink(os.path.join(folder, fd)) == target:
                count += 1
        except OSError:
            pass
    return count


@pytest.mark.parametrize("broken", ["no-bunit", "jy", "bad-gain", "bad-date", "no-readtimes", "no-image",
                                    "truncated", "header-cut"])
def test_a_failed_open_releases_the_file(tmp_path, broken, collect_leaked_files):
    path = str(tmp_path / "broken.fits")
    if broken == "no-bunit":
        frame_file(path, bunit=None)
    elif broken == "jy":
        frame_file(path, bunit="Jy")
    elif broken == "bad-gain":
        frame_file(path, bunit="DN", extra={"GAIN": -1.0})
    elif broken == "bad-date":
        frame_file(path, start=None, extra={"DATE-OBS": "tomorrow"})
    elif broken == "no-readtimes":
        image_file(path, np.zeros((3, 8, 8)), {"BUNIT": "electron"}, primary=True)
    elif broken == "no-image":
        fits.HDUList([fits.PrimaryHDU()]).writeto(path)
    else:
        _cut(frame_file(path), 2 * 2880 + 1000 if broken == "truncated" else 2880 + 1000)
    with pytest.raises(PerscliError):
        open_frame(path)
    assert _open_descriptors(path) == 0


def test_closing_a_frame_releases_the_file(tmp_path):
    path = frame_file(tmp_path / "a.fits")
    frame = open_frame(path)
    frame.fluence()
    frame.close()
    assert _open_descriptors(path) == 0
