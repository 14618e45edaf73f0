"""Persistence on arrays (no files): the same numbers as the file adapter, the model's settings
(time_model, combine, max_previous) from YAML, --set and the command line, and one earlier
exposure given twice refused."""

import numpy as np
import pytest
from astropy.io import fits

from conftest import SAMPLE_DATA, fluence_grid
from fits_factory import run
from perscli import PerscliError
from perscli.detector.model import load_persistence_model as load_model
from perscli.detector.persistence import PersistenceModel, persistence_charge, time_factor
from perscli.detector.settings import PRESETS
from perscli.io.frames import SECONDS_PER_DAY, open_frame

EXP = [str(SAMPLE_DATA / f"exp{k}.fits") for k in (1, 2, 3, 4)]


def arrays(names):
    """(fluence in electrons, end in seconds) of each file, and the current frame's window."""
    out = []
    for name in names:
        with open_frame(name) as f:
            fluence, scale = f.fluence()
            out.append((np.asarray(fluence, dtype=np.float64) * scale, f.end * SECONDS_PER_DAY,
                        f.start * SECONDS_PER_DAY, f.exptime))
    return out


@pytest.mark.parametrize("settings", [[], ["--combine", "max"], ["--time-model", "galsim"], ["--max-previous", "1"],
                                      ["--set", "persistence.gamma=1.2", "--max-previous", "0"]])
def test_arrays_give_what_the_file_adapter_writes(tmp_path, settings):
    run("apply-persistence", EXP[3], *EXP[:3], "--mode", "predict", *settings, "-o", tmp_path / "p.fits")
    with fits.open(tmp_path / "p.fits") as hdul:
        expected = np.asarray(hdul["SCI"].data, dtype=np.float64)
        unit = hdul["SCI"].header["BUNIT"]
    earlier = arrays(EXP[:3])
    (_, _, start, exptime), = arrays(EXP[3:])
    overrides = {"combine": "max"} if "max" in settings else {}
    if "galsim" in settings:
        overrides["time_model"] = "galsim"
    if "--max-previous" in settings:
        overrides["max_previous"] = int(settings[settings.index("--max-previous") + 1])
    if "--set" in settings:
        overrides["gamma"] = 1.2
    model = load_model("typical", overrides)
    charge = persistence_charge([e[0] for e in earlier], [e[1] for e in earlier], start, exptime, model)
    assert charge.shape == (1,) + expected.shape
    assert unit.lower().startswith("electron")
    np.testing.assert_allclose(charge[0], expected, rtol=2e-6, atol=1e-6)
    assert charge.max() > 0


def test_the_array_call_is_the_paper_law_integrated():
    x = fluence_grid((8, 8))
    model = PersistenceModel(**PRESETS["pessimistic"])
    gap, exptime = 30.0, 139.8
    charge = persistence_charge([x], [0.0], gap, exptime, model)[0]
    np.testing.assert_allclose(charge, model.F(x) * time_factor(gap, gap + exptime, 1.0), rtol=1e-12)
    # ramps: one plane per read, the integral up to each read
    reads = [0.0, 10.0, 50.0]
    charge = persistence_charge([x], [0.0], gap, reads, model)
    for k, t in enumerate(reads):
        np.testing.assert_allclose(charge[k], model.F(x) * time_factor(gap, gap + t, 1.0), rtol=1e-12)


def test_max_previous_and_combine_are_model_settings():
    x = [np.full((3, 3), 1e5), np.full((3, 3), 2e5), np.full((3, 3), 3e5)]
    ends = [0.0, 200.0, 400.0]
    base = load_model("typical")
    one = persistence_charge(x, ends, 430.0, 139.8, load_model("typical", {"max_previous": 1}))
    only_last = persistence_charge(x[2:], ends[2:], 430.0, 139.8, base)
    np.testing.assert_array_equal(one, only_last)
    total = persistence_charge(x, ends, 430.0, 139.8, base)
    peak = persistence_charge(x, ends, 430.0, 139.8, load_model("typical", ["combine=max"]))
    assert np.all(total > peak) and np.all(peak >= only_last)


def test_settings_from_yaml_and_their_errors(tmp_path):
    path = tmp_path / "m.yaml"
    path.write_text("base: pessimistic\ntime_model: galsim\ncombine: max\nmax_previous: 0\n")
    model = load_model(str(path))
    assert (model.time_model, model.combine, model.max_previous, model.A) == ("galsim", "max", 0, 0.086)
    assert model.params()["combine"] == "max"
    for bad, needle in (("max_previous: -1", "max_previous"), ("combine: mean", "combine"),
                        ("time_model: midpoint", "time_model"), ("max_previous: 2.5", "max_previous")):
        path.write_text(f"base: typical\n{bad}\n")
        with pytest.raises(PerscliError, match=needle):
            load_model(str(path))
    with pytest.raises(PerscliError, match="unknown persistence parameter"):
        load_model("typical", ["combined=max"])


def test_the_same_earlier_exposure_given_twice_is_an_error(tmp_path):
    result = run("apply-persistence", EXP[3], EXP[2], EXP[2], "-o", tmp_path / "o.fits", code=1)
    assert "given twice" in result.stderr and not (tmp_path / "o.fits").exists()
    with pytest.raises(PerscliError, match="given twice"):
        persistence_charge([np.ones((2, 2))] * 2, [5.0, 5.0], 50.0, 10.0, load_model("typical"))


def test_an_exposure_that_is_not_earlier_is_refused():
    with pytest.raises(PerscliError, match="not an earlier exposure"):
        persistence_charge([np.ones((2, 2))], [60.0], 50.0, 10.0, load_model("typical"))


def test_model_means_the_same_in_render_and_apply_persistence(tmp_path):
    """apply-persistence --law takes a rendered frame (its MODEL table) or a detector-model YAML, as render does."""
    from perscli.detector.model import load_detector_model

    path = tmp_path / "det.yaml"
    path.write_text("effects:\n  - persistence: {base: pessimistic, combine: max, max_previous: 3}\n")
    model = load_model(str(path))
    assert (model.A, model.combine, model.max_previous) == (0.086, "max", 3)
    from_detector = load_detector_model(str(path)).persistence_model()
    assert from_detector.params() == model.params()


def test_one_loader_reads_a_preset_the_same_way_in_render_and_apply_persistence(tmp_path):
    """base: wfc3 brings the WFC3 pipeline's settings wherever the model is read (they once differed)."""
    from perscli.detector.model import load_detector_model

    by_name = load_model("wfc3")
    in_render = load_detector_model(None, ["persistence.base=wfc3"]).persistence_model()
    path = tmp_path / "det.yaml"
    path.write_text("effects:\n  - persistence: {base: wfc3}\n")
    from_file = load_model(str(path))
    assert by_name.params() == in_render.params() == from_file.params()
    assert (by_name.time_model, by_name.combine, by_name.max_previous, by_name.lookback) == ("middle", "max", 0, 16.0)
    # a setting given beside the base wins, in every form
    over = load_detector_model(None, ["persistence.base=wfc3", "persistence.lookback=2"]).persistence_model()
    assert (over.lookback, load_model("wfc3", ["lookback=2"]).lookback) == (2.0, 2.0)
    # the standalone law file keeps its rules: unknown keys and half a law are refused
    for text, needle in (("A: 0.03\nx_0: 7.0e4\n", "unknown persistence parameter"), ("A: 0.03\n", "missing x0")):
        path.write_text(text)
        with pytest.raises(PerscliError, match=needle):
            load_model(str(path))


def test_the_persistence_step_ignores_earlier_frames_beyond_its_lookback():
    """lookback is a setting of the persistence step, so render honours it as apply-persistence does."""
    ends = [0.0, 3600.0 * 5]
    x = [np.full((2, 2), 1e5), np.full((2, 2), 1e5)]
    start = 3600.0 * 5 + 60.0
    both = persistence_charge(x, ends, start, 139.8, load_model("typical"))
    recent = persistence_charge(x[1:], ends[1:], start, 139.8, load_model("typical"))
    from perscli.detector.model import load_detector_model

    pm = load_detector_model(None, ["persistence.lookback=1"]).persistence_model()
    assert pm.lookback == 1.0
    np.testing.assert_array_equal(persistence_charge(x, ends, start, 139.8, pm), recent)
    assert np.all(both > recent)


def test_model_from_a_rendered_frame(tmp_path):
    """A frame rendered with a tweaked persistence step: apply-persistence --law FRAME.fits uses that step."""
    from test_render import DEC, FILTER, MJD1, PA, RA, SCA

    truth = tmp_path / "truth.fits"
    from astropy.table import Table

    Table({"id": np.array([1], dtype=np.int64), "ra": [RA], "dec": [DEC], "kind": ["star"], "mag_J129": [25.0],
           "hlr": [0.3], "e1": [0.0], "e2": [0.0]}).write(truth, format="fits")
    frame = tmp_path / "f.fits"
    run("render", truth, "--ra", RA, "--dec", DEC, "--pa", PA, "--mjd", MJD1, "--filter", FILTER, "--sca", SCA,
        "--bounds", 1, 16, 1, 16, "--seed", 1, "--set", "persistence.base=pessimistic",
        "--set", "persistence.gamma=1.2", "--set", "persistence.max_previous=4", "-o", frame)
    model = load_model(str(frame))
    assert (model.A, model.gamma, model.max_previous) == (0.086, 1.2, 4)
