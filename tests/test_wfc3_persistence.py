"""What HST users expect (issue 11): the wfc3 model and conventions, subarrays placed by LTV, ERR and DQ.

The real WFC3-IR ramps of ../shared/data/wfc3 (skipped where absent) and small flt/ima-like frames built
here with astropy.  Every expectation is computed independently of perscli: reads with astropy, the law
written out from its documented form (Long et al.'s Fermi function with STScI's parameters, NOTES.md
section 1), time to the middle of the later exposure, per-pixel maximum over earlier exposures.
"""

from pathlib import Path

import numpy as np
import pytest
from astropy.io import fits

from fits_factory import expect_error, one_line_error, run, snapshot

DAY = 86400.0
GAIN = 2.5
T0 = 60000.0
#: the 5-pixel border of reference pixels of WFC3-IR raw/ima frames
BORDER = 5


def long_F(x):
    """STScI's WFC3-IR Fermi law at t = 1000 s, e-/s: norm 0.3, x0 9.0e4, dx 2.0e4, alpha 0.174; no linear part."""
    x = np.asarray(x, dtype=np.float64)
    out = np.zeros_like(x)
    pos = x > 0
    out[pos] = 0.3 / (np.exp(-(x[pos] - 9.0e4) / 2.0e4) + 1.0) * (x[pos] / 9.0e4) ** 0.174
    return out


def middle_factor(gap, window):
    """The WFC3 convention: the current at the middle of the window, times the window (gamma = 1)."""
    return 0.0 if window == 0 else window * 1000.0 / (gap + window / 2.0)


# -- the real ramps ------------------------------------------------------------------------------------

def headers(folder):
    """{name: primary and SCI,1 headers} of every raw file, read with astropy."""
    out = {}
    for path in sorted(Path(folder).glob("*_raw.fits")):
        with fits.open(path) as hdul:
            out[path.name] = (hdul[0].header.copy(), hdul["SCI", 1].header.copy())
    return out


def science_footprint(sci_header):
    """Light-sensitive detector pixels (x0, x1, y0, y1), FITS 1-indexed inclusive: image pixel - LTV, no border."""
    nx, ny = sci_header["NAXIS1"], sci_header["NAXIS2"]
    ltv1, ltv2 = sci_header["LTV1"], sci_header["LTV2"]
    return (1 + BORDER - ltv1, nx - BORDER - ltv1, 1 + BORDER - ltv2, ny - BORDER - ltv2)


def overlaps(a, b):
    return a[0] <= b[1] and b[0] <= a[1] and a[2] <= b[3] and b[2] <= a[3]


def reads_in_time_order(path):
    with fits.open(path) as hdul:
        sci = sorted((h for h in hdul if h.name == "SCI"), key=lambda h: h.ver, reverse=True)
        return [h.data.astype(np.float64) for h in sci], np.array([h.header["SAMPTIME"] for h in sci])


def target_of_ibh7a7lsq(folder):
    """The exposure ibh7a7lsq leaves persistence in: a later one of its visit, else the latest that overlaps."""
    hdrs = headers(folder)
    src_primary, src_sci = hdrs["ibh7a7lsq_raw.fits"]
    # ipppssoot: program ppp and visit ss are characters 1-5 of ROOTNAME
    visit = src_primary["ROOTNAME"][:6].lower()
    later = {n: h for n, h in hdrs.items() if h[0]["EXPSTART"] > src_primary["EXPEND"]}
    same_visit = [n for n, (p, _) in later.items() if p["ROOTNAME"][:6].lower() == visit]
    if same_visit:
        return min(same_visit, key=lambda n: later[n][0]["EXPSTART"]), True
    covering = [n for n, (_, s) in later.items() if overlaps(science_footprint(s), science_footprint(src_sci))]
    return max(covering, key=lambda n: later[n][0]["EXPSTART"]), False


def hand_prediction(folder, current, earlier, gaps=None):
    """Per read (time order), DN: max over earlier of F(fluence) x the middle factor, placed at the LTV offsets.

    ``gaps``: seconds from the end of each earlier exposure to the start of ``current`` (default: EXPEND and
    EXPSTART)."""
    cur_path = Path(folder) / current
    with fits.open(cur_path) as hdul:
        cur_hdr, cur_start = hdul["SCI", 1].header, hdul[0].header["EXPSTART"]
    _, samptime = reads_in_time_order(cur_path)
    ny, nx = cur_hdr["NAXIS2"], cur_hdr["NAXIS1"]
    out = np.zeros((len(samptime), ny, nx))
    yy, xx = np.mgrid[0:ny, 0:nx]
    for i, name in enumerate(earlier):
        path = Path(folder) / name
        reads, _ = reads_in_time_order(path)
        with fits.open(path) as hdul:
            hdr, end, gain = hdul["SCI", 1].header, hdul[0].header["EXPEND"], hdul[0].header["CCDGAIN"]
        fluence = (reads[-1] - reads[0]) * gain
        gap = (cur_start - end) * DAY if gaps is None else gaps[i]
        # detector pixel (1-indexed) = image pixel - LTV; its image pixel in the earlier frame = detector + LTV
        ye = yy + 1 - cur_hdr["LTV2"] + hdr["LTV2"] - 1
        xe = xx + 1 - cur_hdr["LTV1"] + hdr["LTV1"] - 1
        pny, pnx = fluence.shape
        inside = ((ye >= BORDER) & (ye < pny - BORDER) & (xe >= BORDER) & (xe < pnx - BORDER)
                  & (yy >= BORDER) & (yy < ny - BORDER) & (xx >= BORDER) & (xx < nx - BORDER)).astype(bool)
        rate = np.zeros((ny, nx))
        rate[inside] = long_F(fluence[ye[inside].astype(int), xe[inside].astype(int)])
        for k, t in enumerate(samptime):
            out[k] = np.maximum(out[k], rate * middle_factor(gap, t))
    return out / GAIN


def test_which_exposure_ibh7a7lsq_leaves_persistence_in(shared_data):
    # no later exposure of visit bh7-a7 is in the folder: the latest exposure whose detector pixels
    # overlap is GJ-1214's ibxy04s4q (266x266 around the 138x138 of XO-1), 377 days later
    target, same_visit = target_of_ibh7a7lsq(shared_data / "wfc3")
    assert (target, same_visit) == ("ibxy04s4q_raw.fits", False)


def test_wfc3_model_on_real_ramps_matches_the_hand_computation_at_the_ltv_offsets(shared_data, tmp_path):
    folder = shared_data / "wfc3"
    target, _ = target_of_ibh7a7lsq(folder)
    out = tmp_path / "pred.fits"
    # the 16 h look-back would ignore an exposure a year old: --lookback 0 looks back without limit
    run("apply-persistence", folder / target, folder / "ibh7a7lsq_raw.fits", "--law", "wfc3", "--lookback", "0",
        "--mode", "predict", "-o", out)
    expected = hand_prediction(folder, target, ["ibh7a7lsq_raw.fits"])
    with fits.open(out) as hdul:
        got = [hdul["SCI", ver].data.astype(np.float64) for ver in range(len(expected), 0, -1)]
        assert (hdul[0].header["PSTIME"], hdul[0].header["PSCOMB"], hdul[0].header["PS_A"]) == ("middle", "max", 0.3)
    for k in range(len(expected)):
        np.testing.assert_allclose(got[k], expected[k], rtol=2e-6, atol=0)
    # the 128x128 science pixels of the subarray, 64 pixels in from the bigger one's corner: nothing elsewhere
    last = got[-1]
    assert np.count_nonzero(last) > 0.9 * 128 * 128
    assert not last[:64 + BORDER].any() and not last[64 + 133:].any()
    assert not last[:, :64 + BORDER].any() and not last[:, 64 + 133:].any()
    assert np.count_nonzero(last[64 + BORDER:64 + 133, 64 + BORDER:64 + 133]) == np.count_nonzero(last)


def test_wfc3_maximum_over_two_earlier_subarrays_of_different_sizes(shared_data, tmp_path):
    # a year and two weeks back, ibh7a7lsq never outshines ibxy01aoq: --gap 30 makes them consecutive
    # (ibh7a7lsq, 30 s, ibxy01aoq, 30 s, ibxy04s4q), so that the maximum picks each somewhere
    folder = shared_data / "wfc3"
    earlier = ["ibh7a7lsq_raw.fits", "ibxy01aoq_raw.fits"]
    out = tmp_path / "pred.fits"
    run("apply-persistence", folder / "ibxy04s4q_raw.fits", *[folder / e for e in earlier], "--law", "wfc3",
        "--gap", "30", "--mode", "predict", "-o", out)
    gaps = [30.0 + fits.getval(folder / earlier[1], "EXPTIME") + 30.0, 30.0]
    each = [hand_prediction(folder, "ibxy04s4q_raw.fits", [e], [g])[-1] for e, g in zip(earlier, gaps)]
    expected = hand_prediction(folder, "ibxy04s4q_raw.fits", earlier, gaps)
    assert np.count_nonzero(each[0] > each[1]) > 100 and np.count_nonzero(each[1] > each[0]) > 100
    with fits.open(out) as hdul:
        last = hdul["SCI", 1].data.astype(np.float64)
        first = hdul["SCI", len(expected)].data
    np.testing.assert_allclose(last, expected[-1], rtol=2e-6, atol=0)
    np.testing.assert_array_equal(expected[-1], np.maximum(*each))
    assert not first.any()  # the zeroth read integrates nothing
    # the maximum, not the sum: where both cover a pixel the sum is larger
    assert np.any(each[0] + each[1] > last * 1.01)


def test_the_16_hour_lookback_ignores_both_with_a_note(shared_data, tmp_path):
    folder = shared_data / "wfc3"
    out = tmp_path / "pred.fits"
    result = run("apply-persistence", folder / "ibxy04s4q_raw.fits", folder / "ibh7a7lsq_raw.fits",
                 folder / "ibxy01aoq_raw.fits", "--law", "wfc3", "--mode", "predict", "-o", out, "-v")
    assert "ibxy01aoq_raw.fits ended 341.4 h before" in result.stderr
    assert "beyond the 16 h look-back: ignored" in result.stderr
    assert "ibh7a7lsq_raw.fits ended" in result.stderr
    with fits.open(out) as hdul:
        assert hdul[0].header["PSNPREV"] == 0 and hdul[0].header["PSLOOKB"] == 16.0
        assert not any(h.data.any() for h in hdul if h.name == "SCI")


# -- small frames built here: flt (rates) and ima (calibrated ramps) ----------------------------------

def flt(path, rate, *, start, exptime=100.0, ltv=None, err=None, dq=None, instrume="WFC3", detector="IR"):
    """An flt-like file: SCI in ELECTRONS/S, optional ERR and DQ, EXPSTART/EXPEND in the primary header."""
    primary = fits.Header()
    primary.update({"INSTRUME": instrume, "DETECTOR": detector, "FILETYPE": "SCI", "EXPSTART": start,
                    "EXPEND": start + exptime / DAY, "EXPTIME": exptime})
    sci = fits.Header()
    sci["BUNIT"] = "ELECTRONS/S"
    if ltv is not None:
        sci["LTV1"], sci["LTV2"] = float(ltv[0]), float(ltv[1])
    hdus = [fits.PrimaryHDU(header=primary), fits.ImageHDU(np.asarray(rate, dtype=np.float32), sci, name="SCI")]
    if err is not None:
        hdus.append(fits.ImageHDU(np.asarray(err, dtype=np.float32), name="ERR"))
    if dq is not None:
        hdus.append(fits.ImageHDU(np.asarray(dq, dtype=np.int16), name="DQ"))
    fits.HDUList(hdus).writeto(path, overwrite=True)
    return str(path)


def ima(path, rates, samptimes, *, start, ltv, err=None):
    """An ima-like WFC3-IR ramp: per read (time order given) SCI in ELECTRONS/S, ERR, DQ, SAMP, TIME;
    SCI,1 is the last read; calwf3 has subtracted the zeroth read (ZOFFCORR = 'COMPLETE')."""
    nsamp = len(rates)
    exptime = float(samptimes[-1])
    primary = fits.Header()
    primary.update({"INSTRUME": "WFC3", "DETECTOR": "IR", "FILETYPE": "SCI", "NSAMP": nsamp, "EXPSTART": start,
                    "EXPEND": start + exptime / DAY, "EXPTIME": exptime, "ZOFFCORR": "COMPLETE"})
    hdus = [fits.PrimaryHDU(header=primary)]
    for ver in range(1, nsamp + 1):
        k = nsamp - ver
        hdr = fits.Header()
        hdr.update({"BUNIT": "ELECTRONS/S", "SAMPTIME": float(samptimes[k]), "LTV1": float(ltv[0]),
                    "LTV2": float(ltv[1])})
        shape = np.shape(rates[k])
        hdus.append(fits.ImageHDU(np.asarray(rates[k], dtype=np.float32), hdr, name="SCI", ver=ver))
        e = np.full(shape, 0.5, np.float32) if err is None else np.asarray(err[k], dtype=np.float32)
        hdus.append(fits.ImageHDU(e, name="ERR", ver=ver))
        hdus.append(fits.ImageHDU(np.zeros(shape, np.int16), name="DQ", ver=ver))
        hdus.append(fits.ImageHDU(np.full(shape, k, np.int16), name="SAMP", ver=ver))
        hdus.append(fits.ImageHDU(np.full(shape, samptimes[k], np.float32), name="TIME", ver=ver))
    fits.HDUList(hdus).writeto(path, overwrite=True)
    return str(path)


def fluence_field(shape, seed, top=3.0e5):
    """Fluences from 0 to ``top`` electrons, across Long's Fermi step."""
    rng = np.random.default_rng(seed)
    return rng.uniform(0.0, top, shape)


@pytest.fixture
def flt_pair(tmp_path):
    """An earlier flt and a later flt with ERR and DQ, an hour apart; the expected persistence in e- and e-/s."""
    shape = (20, 24)
    fluence = fluence_field(shape, 1)
    earlier = flt(tmp_path / "early_flt.fits", fluence / 100.0, start=T0)
    rng = np.random.default_rng(2)
    rate = rng.normal(5.0, 0.5, shape)
    err = rng.uniform(0.05, 0.2, shape)
    dq = np.zeros(shape, np.int16)
    dq[::3, ::4] = 4 | 256  # a bad pixel and saturation, which must stay
    start = T0 + 3700.0 / DAY
    current = flt(tmp_path / "late_flt.fits", rate, start=start, exptime=100.0, err=err, dq=dq)
    # the integration window from the header times, differenced in MJD as the command does
    window = ((start + 100.0 / DAY) - start) * DAY
    gap = (start - (T0 + 100.0 / DAY)) * DAY
    charge = long_F(fluence) * middle_factor(gap, window)
    return dict(earlier=earlier, current=current, rate=rate.astype(np.float32), err=err.astype(np.float32),
                dq=dq, charge=charge, per_second=charge / 100.0, window=window)


def test_subtract_updates_err_in_quadrature_and_sets_the_dq_bit(flt_pair, tmp_path):
    p = flt_pair
    out = tmp_path / "corrected.fits"
    before = snapshot(p["earlier"], p["current"])
    run("apply-persistence", p["current"], p["earlier"], "--law", "wfc3", "--mode", "subtract",
        "--model-error", "0.2", "--flag-above", "0.01", "-o", out)
    assert snapshot(p["earlier"], p["current"]) == before
    flagged = p["charge"] / p["window"] > 0.01
    assert 0 < flagged.sum() < flagged.size  # the threshold cuts through the field
    with fits.open(out, checksum=True) as hdul:
        assert [h.name for h in hdul] == ["PRIMARY", "SCI", "ERR", "DQ"]
        np.testing.assert_allclose(hdul["SCI"].data, p["rate"] - p["per_second"], rtol=1e-6, atol=1e-6)
        np.testing.assert_allclose(hdul["ERR"].data, np.sqrt(p["err"].astype(float) ** 2
                                                            + (0.2 * p["per_second"]) ** 2), rtol=1e-6)
        assert hdul["ERR"].data.dtype == np.dtype(">f4") and hdul["DQ"].data.dtype == np.dtype(">i2")
        np.testing.assert_array_equal(hdul["DQ"].data, p["dq"] | np.where(flagged, 1024, 0))
        hdr = hdul[0].header
        assert (hdr["PSMERR"], hdr["PSFLAG"], hdr["PSDQBIT"], hdr["PSNFLAG"]) == (0.2, 0.01, 1024, flagged.sum())


def test_predict_writes_the_model_uncertainty_as_err_and_add_keeps_err(flt_pair, tmp_path):
    p = flt_pair
    run("apply-persistence", p["current"], p["earlier"], "--law", "wfc3", "--mode", "predict",
        "-o", tmp_path / "pred.fits")
    run("apply-persistence", p["current"], p["earlier"], "--law", "wfc3", "-o", tmp_path / "added.fits")
    with fits.open(tmp_path / "pred.fits") as pred, fits.open(tmp_path / "added.fits") as added:
        np.testing.assert_allclose(pred["SCI"].data, p["per_second"], rtol=1e-6, atol=1e-9)
        # the default fractional uncertainty, 0.3
        np.testing.assert_allclose(pred["ERR"].data, 0.3 * p["per_second"], rtol=1e-6, atol=1e-9)
        np.testing.assert_array_equal(pred["DQ"].data, p["dq"])  # no --flag-above: DQ as it was
        np.testing.assert_array_equal(added["ERR"].data, p["err"])
        np.testing.assert_allclose(added["SCI"].data, p["rate"] + p["per_second"], rtol=1e-6, atol=1e-6)


def test_a_frame_without_dq_gets_one_and_model_error_0_leaves_err(flt_pair, tmp_path):
    p = flt_pair
    with fits.open(p["current"]) as hdul:
        bare = tmp_path / "no_dq_flt.fits"
        fits.HDUList([hdul[0].copy(), hdul["SCI"].copy(), hdul["ERR"].copy()]).writeto(bare)
    out = tmp_path / "flagged.fits"
    run("apply-persistence", bare, p["earlier"], "--law", "wfc3", "--mode", "subtract", "--model-error", "0",
        "--flag-above", "0.05", "--dq-bit", "16384", "-o", out)
    with fits.open(out, checksum=True) as hdul:
        assert [(h.name, h.ver) for h in hdul] == [("PRIMARY", 1), ("SCI", 1), ("ERR", 1), ("DQ", 1)]
        np.testing.assert_array_equal(hdul["ERR"].data, p["err"])
        np.testing.assert_array_equal(hdul["DQ"].data, np.where(p["charge"] / p["window"] > 0.05, 16384, 0))
        assert hdul["DQ"].data.dtype.kind == "i" and hdul["DQ"].data.dtype.itemsize == 2


def test_dq_and_model_error_options_are_checked(flt_pair, tmp_path):
    p = flt_pair
    out = tmp_path / "x.fits"
    for bad in (["--flag-above", "0.01", "--dq-bit", "3"], ["--dq-bit", "1024"], ["--model-error", "-1"]):
        result = run("apply-persistence", p["current"], p["earlier"], *bad, "-o", out, code=2)
        assert result.stderr.startswith("perscli apply-persistence: error: ") and len(result.stderr.splitlines()) == 1
    # 16-bit DQ (HST's) cannot hold 65536: one line, nothing written
    result = run("apply-persistence", p["current"], p["earlier"], "--flag-above", "0.01", "--dq-bit", "65536",
                 "-o", out, code=1)
    one_line_error(result, "DQ", "65536", "choose a bit up to 16384")
    assert not out.exists()


def test_cli_defaults_are_the_librarys(tmp_path):
    """The command's defaults are ApplyOptions' (written once): the help shows them, a run uses them."""
    from perscli.cli.apply_persistence import apply_persistence
    from perscli.detector.settings import DEFAULT_DQ_BIT, DEFAULT_MODEL_ERROR, ApplyOptions

    options = {p.name: p for p in apply_persistence.params}
    assert options["mode"].default == ApplyOptions().mode == "add"
    assert options["model_error"].default == ApplyOptions().model_error == DEFAULT_MODEL_ERROR
    assert f"default: {DEFAULT_DQ_BIT}" in options["dq_bit"].help
    assert "the law's lookback; 0, wfc3: 16" in options["lookback"].help


# -- subarrays and full frames, raw/ima and flt -------------------------------------------------------

IMA_LTV = (-438.0, -438.0)   # the 128x128 subarray of ibh7a7lsq, 138x138 with its reference pixels
SAMPTIMES = [0.0, 7.0, 20.0, 50.0]


def test_ima_subarray_onto_a_full_frame_flt(tmp_path):
    # earlier: an ima of the 128 subarray (its last read's accumulated signal is the fluence); later: a
    # full-frame flt, 1014x1014 with LTV 0 (as STScI's archive writes it) or without LTV at all
    rng = np.random.default_rng(5)
    fluence = rng.uniform(0.0, 2.5e5, (138, 138))
    # a constant-rate ramp: every read holds the rate fluence / 50 s (the zeroth read, at 0 s, holds 0)
    rates = [np.zeros((138, 138))] + [fluence / SAMPTIMES[-1]] * (len(SAMPTIMES) - 1)
    earlier = ima(tmp_path / "sub_ima.fits", rates, SAMPTIMES, start=T0, ltv=IMA_LTV)
    start = T0 + 200.0 / DAY
    full = np.full((1014, 1014), 1.0)
    gap = (start - (T0 + 50.0 / DAY)) * DAY
    window = ((start + 100.0 / DAY) - start) * DAY
    expected = np.zeros((1014, 1014))
    # flt pixel x (0-indexed) is detector pixel x + 1; the ima's pixel detector - 438, 0-indexed - 1,
    # and its science pixels (inside the 5-pixel border) are detector pixels 444-571
    inner = slice(438 + 5, 438 + 133)
    f32 = np.float32(fluence / SAMPTIMES[-1]).astype(np.float64) * SAMPTIMES[-1]
    expected[inner, inner] = long_F(f32[5:133, 5:133]) * middle_factor(gap, window) / 100.0
    for ltv, name in (((0.0, 0.0), "with"), (None, "without")):
        later = flt(tmp_path / f"full_{name}_flt.fits", full, start=start, ltv=ltv)
        out = tmp_path / f"pred_{name}.fits"
        run("apply-persistence", later, earlier, "--law", "wfc3", "--mode", "predict", "-o", out)
        got = fits.getdata(out, "SCI").astype(np.float64)
        np.testing.assert_allclose(got, expected, rtol=2e-6, atol=0, err_msg=name)
        assert np.count_nonzero(got) == 128 * 128


def test_full_frame_flt_onto_an_ima_subarray_reference_pixels_get_nothing_and_err_per_read(tmp_path):
    rng = np.random.default_rng(6)
    fluence = rng.uniform(0.0, 2.5e5, (1014, 1014))
    earlier = flt(tmp_path / "full_flt.fits", fluence / 100.0, start=T0, ltv=(0.0, 0.0))
    start = T0 + 300.0 / DAY
    rates = [np.full((138, 138), 2.0)] * len(SAMPTIMES)
    err = [np.full((138, 138), 0.1)] * len(SAMPTIMES)
    later = ima(tmp_path / "sub_ima.fits", rates, SAMPTIMES, start=start, ltv=IMA_LTV, err=err)
    out = tmp_path / "corrected.fits"
    run("apply-persistence", later, earlier, "--law", "wfc3", "--mode", "subtract", "--flag-above", "0.5",
        "-o", out)
    gap = (start - (T0 + 100.0 / DAY)) * DAY
    # ima pixel y (0-indexed): detector y + 1 + 438; the flt's, 0-indexed: detector - 1 = y + 438
    f = (np.float32(fluence / 100.0).astype(np.float64) * 100.0)[438:438 + 138, 438:438 + 138]
    rate = long_F(f)
    rate[:BORDER], rate[-BORDER:], rate[:, :BORDER], rate[:, -BORDER:] = 0, 0, 0, 0
    with fits.open(out, checksum=True) as hdul:
        for k, t in enumerate(SAMPTIMES):
            ver = len(SAMPTIMES) - k
            per_second = rate * middle_factor(gap, t) / t if t > 0 else 0 * rate
            np.testing.assert_allclose(hdul["SCI", ver].data, 2.0 - per_second, rtol=1e-6, atol=1e-6)
            np.testing.assert_allclose(hdul["ERR", ver].data, np.hypot(np.float32(0.1), 0.3 * per_second),
                                       rtol=1e-6)
        # every read's DQ gets the flags of the exposure: its mean persistence rate up to the last read
        flagged = rate * middle_factor(gap, SAMPTIMES[-1]) / SAMPTIMES[-1] > 0.5
        assert 0 < flagged.sum() < (138 - 2 * BORDER) ** 2
        for ver in range(1, len(SAMPTIMES) + 1):
            np.testing.assert_array_equal(hdul["DQ", ver].data, np.where(flagged, 1024, 0))
        assert np.all(hdul["SCI", 1].data[:BORDER] == 2.0) and np.all(hdul["SCI", 1].data[:, -BORDER:] == 2.0)
        assert np.all(hdul["SCI", 1].data[BORDER:-BORDER, BORDER:-BORDER] < 2.0)


def test_frames_with_no_pixel_in_common_or_of_another_detector_are_refused(tmp_path):
    data = np.full((64, 64), 50.0)
    current = flt(tmp_path / "cur_flt.fits", data, start=T0 + 1.0, ltv=(-500.0, -500.0))
    cases = [
        (flt(tmp_path / "apart_flt.fits", data * 1e3, start=T0, ltv=(-10.0, -500.0)), ("no pixel in common",
                                                                                      "x 11-74, y 501-564")),
        (flt(tmp_path / "uvis_flt.fits", data, start=T0, ltv=(-500.0, -500.0), detector="UVIS"),
         ("DETECTOR=UVIS", "same detector")),
        (flt(tmp_path / "acs_flt.fits", data, start=T0, ltv=(-500.0, -500.0), instrume="ACS"),
         ("INSTRUME=ACS", "same detector")),
    ]
    for earlier, needles in cases:
        expect_error(tmp_path, ["apply-persistence", current, earlier], Path(earlier).name, *needles)
    # side by side with one detector column in common (x 501): only that column receives persistence
    touching = flt(tmp_path / "touch_flt.fits", np.full((64, 64), 3000.0), start=T0, ltv=(-437.0, -500.0))
    run("apply-persistence", current, touching, "--mode", "predict", "-o", tmp_path / "touch.fits")
    got = fits.getdata(tmp_path / "touch.fits", "SCI")
    assert np.all(got[:, 0] > 0) and np.all(got[:, 1:] == 0)
