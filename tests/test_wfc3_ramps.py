"""Real HST WFC3-IR MULTIACCUM raw ramps from ../shared/data/wfc3 (skipped where absent)."""

import numpy as np
import pytest
from astropy.io import fits
from click.testing import CliRunner

from perscli.cli.main import cli
from perscli.io.frames import open_frame

from test_persistence_model import paper_F
from perscli.detector.settings import PRESETS

EARLIER, LATER, OTHER = "ibxy01aoq_raw.fits", "ibxy04s4q_raw.fits", "ibh7a7lsq_raw.fits"


def reads_in_time_order(path):
    """(DN arrays, SAMPTIMEs) of a raw file, zeroth read first, read independently of perscli."""
    with fits.open(path) as hdul:
        sci = sorted((h for h in hdul if h.name == "SCI"), key=lambda h: h.ver, reverse=True)
        return [h.data.astype(np.float64) for h in sci], np.array([h.header["SAMPTIME"] for h in sci])


def test_ramp_layout_units_and_timing(shared_data):
    frame = open_frame(str(shared_data / "wfc3" / LATER))
    try:
        assert frame.layout == "wfc3-ramp" and frame.nreads == 14
        assert frame.unit == "DN" and frame.gain == 2.5
        assert frame.read_times[0] == 0.0 and frame.read_times[-1] == pytest.approx(88.435623)
        assert frame.start == pytest.approx(56211.29994182) and frame.end == pytest.approx(56211.30096552)
        fluence, scale = frame.fluence()
        reads, _ = reads_in_time_order(shared_data / "wfc3" / LATER)
        np.testing.assert_array_equal(fluence * scale, (reads[-1] - reads[0]) * 2.5)
        assert 4.0e4 < (fluence * scale).max() < 5.0e4  # NOTES: peak fluence ~4.8e4 e-
    finally:
        frame.close()


@pytest.mark.parametrize("gap", [None, "30"])
def test_persistence_of_a_real_ramp_on_a_real_ramp(shared_data, tmp_path, gap):
    earlier, later = shared_data / "wfc3" / EARLIER, shared_data / "wfc3" / LATER
    out = tmp_path / "pred.fits"
    args = ["apply-persistence", str(later), str(earlier), "--mode", "predict", "-o", str(out)]
    if gap:
        args += ["--gap", gap]
    result = CliRunner().invoke(cli, args)
    assert result.exit_code == 0, result.output

    prev_reads, _ = reads_in_time_order(earlier)
    fluence = (prev_reads[-1] - prev_reads[0]) * 2.5  # DN x CCDGAIN
    _, samptime = reads_in_time_order(later)
    if gap:
        delay = float(gap)
    else:
        delay = (fits.getval(later, "EXPSTART") - fits.getval(earlier, "EXPEND")) * 86400.0
        assert 13 * 86400 < delay < 15 * 86400  # taken 14 days apart
    rate_1000 = paper_F(fluence, **PRESETS["typical"])
    with fits.open(out) as hdul:
        assert len(hdul) == len(fits.open(later))
        assert fits.getval(out, "PSUNIT") == "DN"
        got = {h.ver: h.data.astype(np.float64) for h in hdul if h.name == "SCI"}
    nreads = len(samptime)
    for k, t in enumerate(samptime):
        expected_dn = rate_1000 * 1000.0 * np.log((delay + t) / delay) / 2.5
        # the 5-pixel border of reference pixels sees no light and receives no persistence
        expected_dn[:5], expected_dn[-5:], expected_dn[:, :5], expected_dn[:, -5:] = 0, 0, 0, 0
        np.testing.assert_allclose(got[nreads - k], expected_dn, rtol=2e-6, atol=1e-12)
    if gap:
        # a saturating grism trace 30 s earlier leaves a visible signal in the last read
        assert got[1].max() > 1.0


def test_adding_keeps_every_other_hdu(shared_data, tmp_path):
    earlier, later = shared_data / "wfc3" / EARLIER, shared_data / "wfc3" / LATER
    out = tmp_path / "added.fits"
    result = CliRunner().invoke(cli, ["apply-persistence", str(later), str(earlier), "--gap", "30",
                                      "-o", str(out)])
    assert result.exit_code == 0, result.output
    with fits.open(out, checksum=True) as new, fits.open(later) as old:
        assert [(h.name, h.ver) for h in new] == [(h.name, h.ver) for h in old]
        for h_new, h_old in zip(new, old):
            if h_new.name == "SCI":
                assert h_new.data.dtype.kind == "f"
                diff = h_new.data.astype(float) - h_old.data
                assert diff.min() >= 0
                if h_old.header["SAMPTIME"] == 0:
                    assert diff.max() == 0
                if h_old.header["SAMPTIME"] > 80:
                    assert diff.max() > 0.5
            else:
                assert h_new.header.get("NAXIS") == h_old.header.get("NAXIS")
        assert new[0].header["PSP01"] == EARLIER and new[0].header["PSCUR"] == LATER


def test_a_subarray_of_another_size_is_placed_by_ltv_not_refused(shared_data, tmp_path):
    # ibh7a7lsq (138x138, LTV -438) lies inside ibxy04s4q's 266x266 (LTV -374): it gives persistence
    # to the pixels it covers, shifted by 64, and to no others (tests/test_wfc3_persistence.py checks
    # the values)
    out = tmp_path / "x.fits"
    result = CliRunner().invoke(cli, ["apply-persistence", str(shared_data / "wfc3" / LATER),
                                      str(shared_data / "wfc3" / OTHER), "--mode", "predict", "-o", str(out)])
    assert result.exit_code == 0, result.output
    with fits.open(out) as hdul:
        last = hdul["SCI", 1].data
        assert fits.getval(out, "PSP01SX") == -64 and fits.getval(out, "PSP01SY") == -64
    inside = np.zeros(last.shape, dtype=bool)
    inside[64 + 5:64 + 133, 64 + 5:64 + 133] = True
    assert np.all(last[~inside] == 0) and np.count_nonzero(last[inside]) > 0.9 * inside.sum()


def _photon_transfer_read_noise(shared_data):
    """The read noise of one read, e-, from the two XO-1 ramps' first reads (independently of perscli): the
    difference of their (read 1 - read 0) images holds four reads' noise and almost no signal."""
    cds = []
    for name in (EARLIER, LATER):
        reads, _ = reads_in_time_order(shared_data / "wfc3" / name)
        cds.append((reads[1] - reads[0])[5:-5, 5:-5])
    d = (cds[0] - cds[1]).ravel()
    for _ in range(5):
        d = d[np.abs(d - d.mean()) < 4 * d.std()]
    return float(np.sqrt(d.var() / 4.0)) * 2.5


# the pair (~15 s: two 266 x 266 ramps of 14 reads) is slow; one ramp of each subarray stays in the fast suite
@pytest.mark.parametrize("files", [[OTHER], [LATER], pytest.param([EARLIER, LATER], marks=pytest.mark.slow)],
                         ids=["ibh7a7lsq", "ibxy04s4q", "pair"])
def test_diagnose_keeps_the_header_gain_and_measures_the_read_noise(shared_data, tmp_path, files):
    """The real grism ramps: no effect is named with a gain far from the header's 2.5 e-/DN, the read noise
    agrees with a photon-transfer estimate, and what the ramps hold that no candidate describes (light
    that changes during a grism time series, hot pixels, 1/f noise) is said, not absorbed."""
    import json

    from perscli.detector.model import load_detector_model

    out = tmp_path / "w"
    result = CliRunner().invoke(cli, ["diagnose", *[str(shared_data / "wfc3" / f) for f in files], "-o", str(out)])
    assert result.exit_code == 0, result.output
    report = json.loads((out / "report.json").read_text())
    assert report["mode"] == "self-predicted" and report["jumps_masked"] > 0
    model = load_detector_model(str(out / "model.yaml"))
    gain = model.value("gain", "gain")
    assert abs(gain / 2.5 - 1.0) <= 0.05, (gain, report["verdict"])
    for e in report["found"]:
        assert e["effect"] != "gain" or abs(e["params"]["gain"] / 2.5 - 1.0) <= 0.05
    # the reads hold no photon-transfer case, and the report says why instead of giving a gain: each ramp's light
    # arrives as the spatial scan passes (NOTES section 11), and the two GJ 1214 ramps, 14 days apart, hold
    # scenes that differ by more than their noise
    pt = report["photon_transfer"]
    assert not pt["trusted"] and pt["gain"] is None, pt["verdict"]
    assert "header gain (2.5) is kept" in pt["verdict"]
    why = "scenes differ" if len(files) > 1 else "changes during the ramp"
    assert why in pt["verdict"], pt["verdict"]
    reference = _photon_transfer_read_noise(shared_data)
    assert 13.0 < reference < 18.0          # WFC3-IR: ~21-23 e- CDS, 15-16 e- a read
    assert abs(model.value("read_noise", "sigma") / reference - 1.0) <= 0.15, \
        (model.value("read_noise", "sigma"), reference)
    assert report["unexplained"] and "unexplained" in report["verdict"]
    if len(files) > 1:
        assert "persistence" in {c["effect"] for c in report["candidates"]}
