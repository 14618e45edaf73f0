"""One meaning per option name, and the older spellings: each still works, with one warning line naming its
replacement and the release that removes it (perscli.deprecation), and none is documented."""

import numpy as np
import pytest
from astropy.io import fits

from perscli.deprecation import REMOVED_IN

from conftest import SAMPLE_DATA
from fits_factory import commands, expect_error, invoke, leaf_commands, raw_cards_masked

EXP = [str(SAMPLE_DATA / f"exp{i}.fits") for i in (1, 2, 3, 4)]


def _warnings(result):
    return [line for line in result.stderr.splitlines() if line.startswith("perscli: warning:")]


def _same_data(a, b):
    with fits.open(a) as x, fits.open(b) as y:
        return all(np.array_equal(p.data, q.data) for p, q in zip(x, y) if p.data is not None)


def test_apply_persistence_model_and_param_are_law_and_set_with_a_warning(tmp_path):
    new, old = tmp_path / "new.fits", tmp_path / "old.fits"
    a = invoke("apply-persistence", EXP[3], EXP[2], "--law", "pessimistic", "--set", "persistence.gamma=1.1",
               "--mode", "predict", "-o", new)
    b = invoke("apply-persistence", EXP[3], EXP[2], "--model", "pessimistic", "--param", "gamma=1.1",
               "--mode", "predict", "-o", old)
    assert a.exit_code == b.exit_code == 0 and a.stderr == "", (a.stderr, b.stderr)
    said = _warnings(b)
    assert said == [f"perscli: warning: apply-persistence --model is deprecated (it stops working in perscli "
                    f"{REMOVED_IN}): use --law",
                    f"perscli: warning: apply-persistence --param KEY=VALUE is deprecated (it stops working in "
                    f"perscli {REMOVED_IN}): use --set persistence.KEY=VALUE"], b.stderr
    assert _same_data(new, old)
    quiet = invoke("-q", "apply-persistence", EXP[3], EXP[2], "--model", "pessimistic", "-o", tmp_path / "q.fits")
    assert quiet.exit_code == 0 and quiet.stderr == ""


def test_law_and_model_together_are_a_usage_error(tmp_path):
    expect_error(tmp_path, [EXP[3], EXP[2], "--law", "typical", "--model", "typical"], "--law", "older spelling",
                 command="apply-persistence", code=2, allow_warnings=True)


def test_catalog_footprints_is_pointings_with_a_warning(tmp_path):
    plan = tmp_path / "plan.fits"
    assert invoke("pointings", "plan", "--ra", 10, "--dec", -44, "--n", 2, "--sca", 7, "-o", plan).exit_code == 0
    a = invoke("catalog", "--pointings", plan, "--bounds", 1, 128, 1, 128, "-o", tmp_path / "a.fits")
    b = invoke("catalog", "--footprints", plan, "--bounds", 1, 128, 1, 128, "-o", tmp_path / "b.fits")
    assert a.exit_code == b.exit_code == 0, (a.stderr, b.stderr)
    assert _warnings(b) == [f"perscli: warning: catalog --footprints POINTINGS.fits is deprecated (it stops working "
                            f"in perscli {REMOVED_IN}): use --pointings POINTINGS.fits"]
    assert _warnings(a) == []
    assert raw_cards_masked(tmp_path / "a.fits") == raw_cards_masked(tmp_path / "b.fits")


def test_model_key_of_a_law_file_is_kind_with_a_warning(tmp_path):
    law = tmp_path / "law.yaml"
    law.write_text("model: linear\ncoefficients: [1.0e-4, 5.0e-5]\n")
    result = invoke("apply-persistence", EXP[3], EXP[2], "--law", law, "--mode", "predict", "-o", tmp_path / "o.fits")
    assert result.exit_code == 0, result.stderr
    assert _warnings(result) == [f"perscli: warning: {law}: 'model:' is deprecated (it stops working in perscli "
                                 f"{REMOVED_IN}): use 'kind:' (fermi or linear)"]
    law.write_text("model: linear\nkind: linear\ncoefficients: [1.0e-4]\n")
    expect_error(tmp_path, [EXP[3], EXP[2], "--law", law], "'model:' and 'kind:'", command="apply-persistence",
                 out="p.fits", inputs=[law])


def test_the_documentation_names_only_the_current_spellings():
    for name, cmd in leaf_commands():
        if name == "pointings":          # the flag form itself: its help says it is deprecated
            continue
        shown = {o for p in cmd.params if not getattr(p, "hidden", False) for o in p.opts}
        if name == "apply-persistence":
            assert "--law" in shown and not {"--model", "--param"} & shown
        if name == "catalog":
            assert "--pointings" in shown and "--footprints" not in shown
    import re

    text = commands()["apply-persistence"].help + commands()["catalog"].help
    # (--model-error is another option: the law's fractional uncertainty)
    assert not re.search(r"--model(?![-\w])|--param\b|catalog --footprints", text)


@pytest.mark.parametrize("name", ["typical", "pessimistic", "nothere"])
def test_an_unknown_detector_model_lists_the_valid_ones(tmp_path, name):
    truth = tmp_path / "t.fits"
    assert invoke("catalog", "--ra", 10, "--dec", -44, "--size", 1, "-o", truth).exit_code == 0
    line = expect_error(tmp_path, [truth, "--ra", 10, "--dec", -44, "--pa", 30, "--mjd", 61541.97, "--filter",
                                   "J129", "--sca", 7, "--bounds", 1, 16, 1, 16, "--seed", 1, "--model", name],
                        f"{name}: no such detector model", "roman", "YAML", "frame perscli rendered",
                        command="render")
    if name != "nothere":
        assert f"--set persistence.base={name}" in line and f"--law {name}" in line


def test_model_means_the_detector_model_wherever_it_is_documented():
    """--model is the detector model in every command that documents it (apply-persistence's law is --law)."""
    for name, cmd in leaf_commands():
        for p in cmd.params:
            if "--model" in p.opts and not p.hidden:
                assert p.help.startswith("Detector model: "), (name, p.help)
