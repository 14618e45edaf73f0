"""apply-persistence end to end: the exact time integral, GalSim's numbers, modes, units, order."""

import numpy as np
import pytest
from astropy.io import fits
from scipy import integrate

from perscli.detector.settings import PRESETS

from conftest import fluence_grid
from fits_factory import run
from test_persistence_model import paper_F

DAY = 86400.0
T0 = 61541.972429  # MJD of the first exposure of the public Roman WAS schedule


def sci(path):
    with fits.open(path) as hdul:
        return np.array(hdul["SCI"].data if "SCI" in hdul else hdul[0].data, dtype=np.float64)


def quad_charge(x, params, t_start, t_end, gamma):
    """Charge from fluence x over [t_start, t_end] by numerical integration of P(x, t)."""
    rate_at_1000 = paper_F(x, **params)
    factor, _ = integrate.quad(lambda t: (t / 1000.0) ** (-gamma), t_start, t_end, epsabs=0, epsrel=1e-12)
    return rate_at_1000 * factor


@pytest.mark.parametrize("gamma", [1.0, 0.8, 1.35])
@pytest.mark.parametrize("preset", ["typical", "pessimistic"])
def test_exact_integral_with_irregular_gaps_matches_numerical_integration(frame_writer, tmp_path, gamma, preset):
    # four earlier exposures of different lengths with irregular gaps, given out of order
    rng = np.random.default_rng(7)
    starts = [T0, T0 + 400.0 / DAY, T0 + 1000.0 / DAY, T0 + 1190.0 / DAY]
    lengths = [139.8, 60.0, 139.8, 300.0]
    cur_start, cur_len = T0 + 1495.0 / DAY, 88.4
    fluences = [fluence_grid(seed=s) for s in range(4)]
    paths = [frame_writer(f"p{i}.fits", f, start=s, exptime=ln, bunit="electron")
             for i, (f, s, ln) in enumerate(zip(fluences, starts, lengths))]
    current = frame_writer("cur.fits", rng.normal(500, 20, (16, 16)), start=cur_start, exptime=cur_len)
    out = tmp_path / "pers.fits"
    run("apply-persistence", current, paths[2], paths[0], paths[3], paths[1], "--mode", "predict",
        "--law", preset, "--set", f"persistence.gamma={gamma}", "-o", out)
    params = dict(PRESETS[preset])
    expected = sum(quad_charge(f, params, (cur_start - s) * DAY - ln, (cur_start - s) * DAY - ln + cur_len, gamma)
                   for f, s, ln in zip(fluences, starts, lengths))
    got = sci(out)
    mask = expected > 1e-12
    assert mask.sum() > 200
    np.testing.assert_allclose(got[mask], expected[mask], rtol=1e-6)
    assert np.all(got[~mask] == 0)


def test_ramp_gets_the_cumulative_integral_up_to_each_read(frame_writer, tmp_path):
    fluence = fluence_grid(seed=11)
    prev = frame_writer("prev.fits", fluence, start=T0)
    read_times = np.array([0.0, 2.9, 10.0, 50.0, 139.8])
    cube = np.tile(np.arange(5.0)[:, None, None] * 100.0, (1, 16, 16))
    cur_start = T0 + (139.8 + 31.0) / DAY
    hdr = fits.Header({"BUNIT": "electron", "EXPSTART": cur_start, "EXPEND": cur_start + 139.8 / DAY,
                       "EXPTIME": 139.8})
    table = fits.BinTableHDU.from_columns([fits.Column("TIME", "D", array=read_times)], name="READTIMES")
    path = tmp_path / "ramp.fits"
    fits.HDUList([fits.PrimaryHDU(cube, hdr), table]).writeto(path)
    out = tmp_path / "out.fits"
    run("apply-persistence", path, prev, "-o", out)
    with fits.open(out) as hdul:
        got = hdul[0].data.astype(float) - cube
        assert hdul["READTIMES"].data["TIME"].tolist() == read_times.tolist()
    for k, t in enumerate(read_times):
        expected = quad_charge(fluence, PRESETS["typical"], 31.0, 31.0 + t, 1.0) if t > 0 else 0 * fluence
        np.testing.assert_allclose(got[k], expected, rtol=1e-6, atol=1e-4)


def test_galsim_time_model_reproduces_galsim_fermi(frame_writer, tmp_path):
    galsim = pytest.importorskip("galsim")
    import galsim.roman

    rng = np.random.default_rng(5)
    shape = (40, 50)
    prevs = [10 ** rng.uniform(0, 5.5, shape) for _ in range(6)]
    current = rng.normal(1000.0, 30.0, shape)
    paths = [frame_writer(f"p{i}.fits", p.astype(np.float64), start=T0 + i * 169.8 / DAY)
             for i, p in enumerate(prevs)]
    cur = frame_writer("c.fits", current, start=T0 + 6 * 169.8 / DAY)
    out = tmp_path / "o.fits"
    run("apply-persistence", cur, *paths, "--time-model", "galsim", "-o", out)
    image = galsim.Image(current.copy())
    galsim.roman.applyPersistence(image, [galsim.Image(p) for p in prevs[::-1]], method="fermi")
    np.testing.assert_allclose(sci(out) - current, image.array - current, rtol=1e-6, atol=1e-9)

    out_lin = tmp_path / "lin.fits"
    run("apply-persistence", cur, *paths, "--law", "galsim-linear", "--mode", "predict", "-o", out_lin)
    image = galsim.Image(current.copy())
    galsim.roman.applyPersistence(image, [galsim.Image(p) for p in prevs[::-1]], method="linear")
    np.testing.assert_allclose(sci(out_lin), image.array - current, rtol=1e-6, atol=1e-9)


def test_exact_model_is_below_galsim_for_the_real_30s_gap(frame_writer, tmp_path):
    # NOTES: for the most recent exposure with a real 30 s gap the exact integral is ~15% below GalSim
    fluence = np.full((4, 4), 8e4)
    prev = frame_writer("p.fits", fluence, start=T0)
    cur = frame_writer("c.fits", np.zeros((4, 4)), start=T0 + 169.8 / DAY)
    exact, approx = tmp_path / "e.fits", tmp_path / "g.fits"
    run("apply-persistence", cur, prev, "--mode", "predict", "-o", exact)
    run("apply-persistence", cur, prev, "--mode", "predict", "--time-model", "galsim", "-o", approx)
    ratio = sci(exact)[0, 0] / sci(approx)[0, 0]
    assert 0.80 < ratio < 0.90


def test_order_on_the_command_line_does_not_matter_and_max_previous_keeps_the_most_recent(frame_writer, tmp_path):
    rng = np.random.default_rng(8)
    paths = [frame_writer(f"p{i:02d}.fits", 10 ** rng.uniform(2, 5.5, (8, 8)), start=T0 + i * 169.8 / DAY)
             for i in range(12)]
    cur = frame_writer("c.fits", np.zeros((8, 8)), start=T0 + 12 * 169.8 / DAY)
    a, b, c, d = (tmp_path / f"out_{n}.fits" for n in "abcd")
    run("apply-persistence", cur, *paths, "--mode", "predict", "-o", a)
    run("apply-persistence", cur, *paths[::-1], "--mode", "predict", "-o", b)
    run("apply-persistence", cur, *paths[2:], "--mode", "predict", "-o", c)
    run("apply-persistence", cur, *paths, "--mode", "predict", "--max-previous", "0", "-o", d)
    assert np.array_equal(sci(a), sci(b))
    assert np.array_equal(sci(a), sci(c))
    assert np.all(sci(d) > sci(a))
    assert fits.getval(a, "PSNPREV") == 10 and fits.getval(d, "PSNPREV") == 12
    assert fits.getval(a, "PSP01") == "p11.fits"


def test_modes_and_combine(frame_writer, tmp_path):
    rng = np.random.default_rng(9)
    f1, f2 = 10 ** rng.uniform(2, 5.5, (2, 10, 10))
    p1 = frame_writer("p1.fits", f1, start=T0)
    p2 = frame_writer("p2.fits", f2, start=T0 + 169.8 / DAY)
    data = rng.normal(300.0, 10.0, (10, 10))
    cur = frame_writer("c.fits", data, start=T0 + 2 * 169.8 / DAY)
    outs = {name: tmp_path / f"{name}.fits" for name in ("add", "sub", "pred", "max", "only1", "only2")}
    run("apply-persistence", cur, p1, p2, "-o", outs["add"])
    run("apply-persistence", cur, p1, p2, "--mode", "subtract", "-o", outs["sub"])
    run("apply-persistence", cur, p1, p2, "--mode", "predict", "-o", outs["pred"])
    run("apply-persistence", cur, p1, p2, "--mode", "predict", "--combine", "max", "-o", outs["max"])
    run("apply-persistence", cur, p1, p2, "--mode", "predict", "--max-previous", "1", "-o", outs["only2"])
    pred = sci(outs["pred"])
    assert pred.min() >= 0 and pred.max() > 1
    np.testing.assert_allclose(sci(outs["add"]), data + pred, rtol=1e-12)
    np.testing.assert_allclose(sci(outs["sub"]), data - pred, rtol=1e-12)
    # the contribution of p1 alone (as the second most recent exposure) is pred minus p2's part
    only2 = sci(outs["only2"])
    only1 = pred - only2
    np.testing.assert_allclose(sci(outs["max"]), np.maximum(only1, only2), rtol=1e-9)


@pytest.mark.parametrize("bunit,gain,factor", [
    ("electron", None, 1.0), ("ELECTRONS", None, 1.0), ("electron/s", None, 100.0), ("ELECTRONS/S", None, 100.0),
    ("DN", 2.0, 2.0), ("COUNTS", 2.0, 2.0), ("DN/s", 2.0, 200.0), ("COUNTS/S", 2.0, 200.0)])
def test_units_in_and_out(frame_writer, tmp_path, bunit, gain, factor):
    fluence_e = fluence_grid(seed=3)
    extra = {"CCDGAIN": gain} if gain else {}
    prev = frame_writer("p.fits", fluence_e / factor, start=T0, exptime=100.0, bunit=bunit, **extra)
    cur = frame_writer("c.fits", np.full((16, 16), 10.0), start=T0 + 130.0 / DAY, exptime=100.0, bunit=bunit,
                       **extra)
    ref_p = frame_writer("rp.fits", fluence_e, start=T0, exptime=100.0)
    ref_c = frame_writer("rc.fits", np.full((16, 16), 10.0 * factor), start=T0 + 130.0 / DAY, exptime=100.0)
    out, ref = tmp_path / "o.fits", tmp_path / "r.fits"
    run("apply-persistence", cur, prev, "-o", out)
    run("apply-persistence", ref_c, ref_p, "-o", ref)
    assert fits.getval(out, "BUNIT", "SCI") == bunit
    # output stays in the input's units: converting back gives the electron result
    np.testing.assert_allclose(sci(out) * factor, sci(ref), rtol=1e-12)


def test_integer_current_frame_becomes_float32_in_same_units(frame_writer, tmp_path):
    prev = frame_writer("p.fits", np.full((6, 6), 9e4), start=T0)
    cur = frame_writer("c.fits", np.full((6, 6), 1000, dtype=np.int16), start=T0 + 169.8 / DAY,
                       bunit="DN", GAIN=1.5)
    out = tmp_path / "o.fits"
    run("apply-persistence", cur, prev, "-o", out)
    with fits.open(out) as hdul:
        assert hdul["SCI"].data.dtype == np.dtype(">f4")
        assert np.all(hdul["SCI"].data > 1000.0)


def test_nonfinite_earlier_pixels_count_as_zero(frame_writer, tmp_path):
    fl = np.full((5, 5), 7e4)
    fl[1, 1], fl[2, 2] = np.nan, np.inf
    prev = frame_writer("p.fits", fl, start=T0)
    cur = frame_writer("c.fits", np.zeros((5, 5)), start=T0 + 169.8 / DAY)
    out = tmp_path / "o.fits"
    result = run("apply-persistence", cur, prev, "--mode", "predict", "-o", out)
    assert "2 non-finite pixels" in result.output
    got = sci(out)
    assert got[1, 1] == 0 and got[2, 2] == 0 and got[0, 0] > 0


def test_gap_option_supplies_timing_in_command_line_order(frame_writer, tmp_path):
    f1, f2 = np.full((4, 4), 6e4), np.full((4, 4), 2e4)
    p1 = frame_writer("p1.fits", f1, exptime=139.8)
    p2 = frame_writer("p2.fits", f2, exptime=139.8)
    cur = frame_writer("c.fits", np.zeros((4, 4)), exptime=139.8)
    out = tmp_path / "o.fits"
    run("apply-persistence", cur, p1, p2, "--gap", "30", "--mode", "predict", "-o", out)
    params = PRESETS["typical"]
    expected = (quad_charge(f2, params, 30.0, 169.8, 1.0)
                + quad_charge(f1, params, 30.0 + 169.8, 169.8 + 169.8, 1.0))
    np.testing.assert_allclose(sci(out), expected, rtol=1e-6)


def test_corrupted_data_caught_by_datasum(frame_writer, tmp_path):
    prev = tmp_path / "p.fits"
    fits.HDUList([fits.PrimaryHDU(), fits.ImageHDU(np.full((8, 8), 6e4, dtype=np.float32), fits.Header(
        {"BUNIT": "electron", "EXPTIME": 139.8, "EXPSTART": T0, "EXPEND": T0 + 139.8 / DAY}), name="SCI")]
                 ).writeto(prev, checksum=True)
    cur = frame_writer("c.fits", np.zeros((8, 8)), start=T0 + 169.8 / DAY)
    out = tmp_path / "o.fits"
    run("apply-persistence", cur, prev, "-o", out)  # intact: accepted
    raw = bytearray(prev.read_bytes())
    raw[2 * 2880 + 10] ^= 0xFF  # flip bits inside the data (after two header blocks), headers untouched
    prev.write_bytes(bytes(raw))
    result = run("apply-persistence", cur, prev, "-o", tmp_path / "o2.fits", code=1)
    assert "DATASUM" in result.output and "corrupt" in result.output
    assert not (tmp_path / "o2.fits").exists()


def test_library_persistence_image_equals_the_commands_prediction(frame_writer, tmp_path):
    from perscli.detector.apply import persistence_image
    from perscli.detector.model import load_persistence_model as load_model
    from perscli.io.frames import open_frame

    rng = np.random.default_rng(12)
    paths = [frame_writer(f"p{i}.fits", 10 ** rng.uniform(2, 5.5, (70, 30)), start=T0 + i * 169.8 / DAY)
             for i in range(3)]
    cur = frame_writer("c.fits", np.zeros((70, 30)), start=T0 + 3 * 169.8 / DAY)
    out = tmp_path / "o.fits"
    run("apply-persistence", cur, *paths, "--mode", "predict", "-o", out)
    frames = [open_frame(p) for p in [cur, *paths]]
    try:
        image = persistence_image(frames[0], frames[1:], load_model("typical"), workers=2)
    finally:
        for f in frames:
            f.close()
    assert image.shape == (1, 70, 30)
    np.testing.assert_allclose(image[0], sci(out), rtol=1e-12)


@pytest.mark.parametrize("layout", ["image", "cube", "sci-extensions"])
@pytest.mark.parametrize("workers", [1, 2])
def test_output_checksums_summed_block_by_block_verify_with_astropy(frame_writer, tmp_path, layout, workers):
    # the output's DATASUM is summed in the threads that make each block; 150 rows are not a
    # whole number of 64-row blocks, and a ramp's planes are summed per plane
    import warnings

    rng = np.random.default_rng(5)
    prev = frame_writer("prev.fits", rng.uniform(0, 2e5, (150, 33)), start=T0, bunit="electron")
    start = T0 + 170.0 / DAY
    hdr = {"BUNIT": "electron", "EXPSTART": start, "EXPEND": start + 139.8 / DAY, "EXPTIME": 139.8}
    path = tmp_path / "cur.fits"
    if layout == "image":
        path = frame_writer("cur.fits", rng.normal(500, 20, (150, 33)), start=start)
    elif layout == "cube":
        cube = np.cumsum(rng.uniform(0, 10, (3, 150, 33)), axis=0)
        table = fits.BinTableHDU.from_columns([fits.Column("TIME", "D", array=[0.0, 50.0, 139.8])],
                                              name="READTIMES")
        fits.HDUList([fits.PrimaryHDU(cube, fits.Header(hdr)), table]).writeto(path)
    else:
        exts = [fits.ImageHDU(rng.normal(500, 20, (150, 33)).astype("f4"), name="SCI") for _ in range(2)]
        for k, e in enumerate(exts, 1):
            e.ver = k
        fits.HDUList([fits.PrimaryHDU(header=fits.Header(hdr)), exts[0]]).writeto(path)
    out = tmp_path / "out.fits"
    run("apply-persistence", path, prev, "--workers", workers, "-o", out)
    with warnings.catch_warnings():
        warnings.simplefilter("error")   # astropy warns (does not raise) on a checksum mismatch
        with fits.open(out, checksum=True) as hdul:
            for hdu in hdul:
                assert hdu.header["DATASUM"] and hdu.header["CHECKSUM"]
                if hdu.data is not None:
                    hdu.data  # noqa: B018 -- read, so that the data checksum is verified


# -- the WFC3 conventions on any frames, frames of different areas, flags in any units ------------------

def test_time_model_middle_lookback_and_their_note(frame_writer, tmp_path):
    f_old, f_new = np.full((4, 4), 8e4), np.full((4, 4), 3e4)
    old = frame_writer("old.fits", f_old, start=T0)                       # ends 20 h before cur starts
    new = frame_writer("new.fits", f_new, start=T0 + 19 * 3600 / DAY)     # ends about 1 h before
    start = T0 + (20 * 3600 + 139.8) / DAY
    cur = frame_writer("c.fits", np.zeros((4, 4)), start=start)
    out, all_ = tmp_path / "o.fits", tmp_path / "all.fits"
    result = run("apply-persistence", cur, old, new, "--time-model", "middle", "--lookback", "16", "--mode",
                 "predict", "-v", "-o", out)
    assert "old.fits ended 20.0 h before" in result.stderr and "16 h look-back: ignored" in result.stderr
    params = PRESETS["typical"]
    window = 139.8
    gap = (start - (T0 + (19 * 3600 + 139.8) / DAY)) * DAY
    expected = paper_F(f_new, **params) * window * 1000.0 / (gap + window / 2)
    np.testing.assert_allclose(sci(out), expected, rtol=1e-6)
    assert fits.getval(out, "PSNPREV") == 1 and fits.getval(out, "PSLOOKB") == 16.0
    run("apply-persistence", cur, old, new, "--time-model", "middle", "--mode", "predict", "-o", all_)
    assert np.all(sci(all_) > sci(out))  # no look-back by default for the paper's models: both count


def test_a_cutout_gives_persistence_only_to_the_pixels_it_covers(frame_writer, tmp_path):
    # frames without LTV lie where LTV = 0 puts them; a section of one carries its own LTV
    rng = np.random.default_rng(12)
    fluence = 10 ** rng.uniform(2, 5.5, (40, 50))
    prev = frame_writer("p.fits", fluence, start=T0)
    cur = frame_writer("c.fits", np.zeros((40, 50)), start=T0 + 169.8 / DAY)
    whole, part, moved = (tmp_path / f"{n}.fits" for n in ("whole", "part", "moved"))
    run("apply-persistence", cur, prev, "--mode", "predict", "-o", whole)
    run("apply-persistence", cur, f"{prev}[SCI][11:30,6:25]", "--mode", "predict", "-o", part)
    expected = np.zeros((40, 50))
    expected[5:25, 10:30] = sci(whole)[5:25, 10:30]
    np.testing.assert_array_equal(sci(part), expected)
    # the current frame a cutout, the earlier one whole: the cutout's own pixels, from the earlier frame's
    run("apply-persistence", f"{cur}[SCI][11:30,6:25]", prev, "--mode", "predict", "-o", moved)
    np.testing.assert_array_equal(sci(moved), sci(whole)[5:25, 10:30])
    # frames of different shapes, neither placed by LTV: refused
    small = frame_writer("small.fits", fluence[:20], start=T0)
    result = run("apply-persistence", cur, small, "-o", tmp_path / "x.fits", code=1)
    assert "neither has LTV1/LTV2" in result.stderr
    assert not (tmp_path / "x.fits").exists()


def test_flag_threshold_is_in_electrons_per_second_whatever_the_units(frame_writer, tmp_path):
    fluence = fluence_grid(seed=4)
    prev = frame_writer("p.fits", fluence, start=T0)
    start = T0 + 169.8 / DAY
    outs = {}
    for bunit, gain in (("electron", None), ("DN", 2.0), ("DN/s", 2.0)):
        extra = {"GAIN": gain} if gain else {}
        cur = frame_writer(f"c_{bunit[-1]}.fits", np.ones((16, 16)), start=start, exptime=139.8, bunit=bunit,
                           **extra)
        outs[bunit] = tmp_path / f"flag_{bunit[-1]}.fits"
        run("apply-persistence", cur, prev, "--mode", "subtract", "--flag-above", "0.05", "--dq-bit", "32",
            "-o", outs[bunit])
    window = ((start + 139.8 / DAY) - start) * DAY
    gap = (start - (T0 + 139.8 / DAY)) * DAY
    charge = quad_charge(fluence, PRESETS["typical"], gap, gap + window, 1.0)
    expected = np.where(charge / window > 0.05, 32, 0)
    assert 0 < np.count_nonzero(expected) < expected.size
    for bunit, out in outs.items():
        with fits.open(out) as hdul:
            np.testing.assert_array_equal(hdul["DQ"].data, expected, err_msg=bunit)
            assert [h.name for h in hdul] == ["PRIMARY", "SCI", "DQ"]
