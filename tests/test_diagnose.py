"""perscli diagnose on hidden-effect cases: measured frames rendered with one effect at a non-default
strength, simulations with the default model; each case names that effect and only that one,
recovers its parameter within 10% (or 3 sigma), and brings the gap within 5% of 1.  A null case
names nothing; two hidden effects are both found.  Plus the WFC3 ramps, self-predicted, and the
command's outputs and errors.

The scene: a 128 x 128 cutout with stars from J = 14 (saturated cores) to 22 and galaxies, three
exposures 169.8 s apart, dithered by a few pixels so that ghosts of earlier stars fall beside
the stars; measured and simulated noise come from different seeds.
"""

import json
import os

import numpy as np
import pytest
from astropy.table import Table

from fits_factory import invoke, one_line_error, run

RA, DEC, PA, SCA, FILTER = 10.0, -44.0, 30.0, 7, "J129"
MJD1 = 61541.97
STEP = (139.8 + 30.0) / 86400.0
BOUNDS = (1001, 1128, 2001, 2128)



@pytest.fixture(scope="module")
def scene(tmp_path_factory):
    from perscli.render.exposure import Exposure
    from perscli.optics import Optics

    d = tmp_path_factory.mktemp("diagnose")
    optics = Optics(Exposure(ra=RA, dec=DEC, pa=PA, sca=SCA, filter=FILTER, mjd=MJD1))
    rng = np.random.default_rng(3)
    rows = []
    for i in range(40):
        x, y = rng.uniform(BOUNDS[0] + 5, BOUNDS[1] - 5), rng.uniform(BOUNDS[2] + 5, BOUNDS[3] - 5)
        ra, dec = optics.wcs.xyToradec(x, y, units="deg")
        kind = "star" if i < 12 else "galaxy"
        mag = rng.uniform(14, 22) if kind == "star" else rng.uniform(19, 24)
        rows.append((i + 1, float(ra), float(dec), kind, mag, mag + 0.3, rng.uniform(0.2, 0.6),
                     rng.normal(0, 0.2), rng.normal(0, 0.2)))
    t = Table(rows=rows, names=["id", "ra", "dec", "kind", "mag_J129", "mag_H158", "hlr", "e1", "e2"])
    t["id"] = t["id"].astype(np.int64)
    truth = d / "truth.fits"
    t.write(truth, format="fits")
    return {"dir": d, "truth": str(truth)}


def sequence(scene, name, *settings, n=3, seed=100, exptimes=None):
    """n exposures of the scene (each with the earlier ones as --previous), rendered with ``settings``."""
    d = scene["dir"] / name
    if d.exists():
        return sorted(str(p) for p in d.glob("e*.fits"))
    d.mkdir()
    out, mjd = [], MJD1
    for k in range(n):
        exptime = exptimes[k] if exptimes else 139.8
        path = d / f"e{k}.fits"
        # a dither of a few pixels between exposures: ghosts fall beside the stars that made them
        args = ["render", scene["truth"], "--bounds", *BOUNDS, "--ra", RA + k * 1.5e-4, "--dec", DEC, "--pa", PA,
                "--mjd", repr(mjd), "--filter", FILTER, "--sca", SCA, "--seed", seed + k, "--exptime", exptime,
                "--persistence-source", "all", "-o", path]
        # the FLUENCE of earlier exposures persists: the history diagnose's forward model uses (not the default,
        # the stars' light)
        for s in settings:
            args += ["--set", s]
        for p in out:
            args += ["--previous", p]
        run(*args)
        out.append(str(path))
        mjd += (exptime + 30.0) / 86400.0
    return out


def diagnose(scene, measured, simulated, name, *extra):
    outdir = scene["dir"] / f"out_{name}"
    args = ["diagnose", *measured]
    for s in simulated:
        args += ["--simulated", s]
    run(*args, "-o", outdir, "--overwrite", *extra)
    with open(outdir / "report.json") as fh:
        return json.load(fh), outdir


CASES = [
    # (case, measured settings, effect, parameter, true value)
    ("dark", ["dark.current=0.4"], "dark", "current", 0.4),
    ("nonlinearity", ["nonlinearity.beta=-1.6e-6"], "nonlinearity", "beta", -1.6e-6),
    ("reciprocity", ["reciprocity.alpha=0.02"], "reciprocity", "alpha", 0.02),
    ("read_noise", ["read_noise.sigma=12.5"], "read_noise", "sigma", 12.5),
    ("gain", ["gain.gain=1.4"], "gain", "gain", 1.4),
    ("offset", ["offset.level=30"], "offset", "level", 30.0),
    ("ipc", ["ipc.kernel=[[0.002,0.025,0.002],[0.025,0.892,0.025],[0.002,0.025,0.002]]"], "ipc", "alpha", 0.025),
    ("persistence", ["persistence.A=0.15"], "persistence", "A", 0.15),
]


@pytest.fixture(scope="module")
def simulated(scene):
    return sequence(scene, "sim", seed=200)


@pytest.mark.parametrize("case, settings, effect, param, truth", CASES, ids=[c[0] for c in CASES])
def test_a_hidden_effect_is_named_recovered_and_closes_the_gap(scene, simulated, case, settings, effect, param,
                                                                truth):
    measured = sequence(scene, case, *settings)
    report, outdir = diagnose(scene, measured, simulated, case)
    names = [e["effect"] for e in report["found"]]
    assert names == [effect], (names, report["verdict"])
    # what the data cannot tell from the named set replaces it: sets of as many effects, never larger ones
    assert all(len(alt) == len(names) for alt, _ in report.get("alternatives", [])), report["alternatives"]
    found = report["found"][0]
    value, error = found["params"][param], found["errors"][param]
    assert abs(value - truth) <= max(0.1 * abs(truth), 3 * error), (value, error, truth)
    assert report["gap_before"] > report["gap_after"]
    assert abs(report["gap_after"] - 1.0) <= 0.05, report["gap_after"]
    # where the effect acts, the gap shrinks too
    assert abs(found["probe_gap_after"] - 1.0) < abs(found["probe_gap_before"] - 1.0)
    # the model written renders what was fitted
    from perscli.detector.model import load_detector_model

    model = load_detector_model(str(outdir / "model.yaml"))
    from perscli.diagnose.candidates import by_name

    assert by_name(effect).get(model, []) == pytest.approx(value, rel=1e-9, abs=1e-15)
    for name in ("report.md", "gap.png"):
        assert (outdir / name).stat().st_size > 0


def test_the_null_case_names_nothing(scene, simulated):
    measured = sequence(scene, "null", seed=300)
    report, outdir = diagnose(scene, measured, simulated, "null")
    assert report["found"] == [] and report["verdict"] == "no missing effect"
    assert abs(report["gap_before"] - 1.0) < 0.05
    assert "no missing effect" in (outdir / "report.md").read_text()


def test_the_search_says_each_step_on_stderr_without_a_terminal_and_nothing_with_q(scene, simulated, tmp_path):
    """diagnose takes tens of seconds to minutes: one line per step on stderr, in a log as at a terminal."""
    measured = sequence(scene, "steps", seed=400)
    args = ["diagnose", *measured, *[a for s in simulated for a in ("--simulated", s)]]
    result = run(*args, "-o", tmp_path / "d")
    said = result.stderr.splitlines()
    assert said[0].startswith("diagnose: 3 measured exposure(s), ") and said[1].startswith("diagnose: gap before: ")
    rounds = [line for line in said if line.startswith("diagnose: round 1: ")]
    assert len(rounds) >= 8, result.stderr               # every candidate fitted in the first round
    assert said[-1].startswith("no missing effect; gap ")
    quiet = run("-q", *args, "-o", tmp_path / "q")
    assert quiet.stderr == "" and (tmp_path / "q" / "report.md").exists()


def test_two_hidden_effects_are_both_found(scene, simulated):
    measured = sequence(scene, "two", "dark.current=0.3", "nonlinearity.beta=-1.5e-6")
    report, _ = diagnose(scene, measured, simulated, "two")
    found = {e["effect"]: e for e in report["found"]}
    assert set(found) == {"dark", "nonlinearity"}, report["verdict"]
    assert found["dark"]["params"]["current"] == pytest.approx(0.3, rel=0.1)
    assert found["nonlinearity"]["params"]["beta"] == pytest.approx(-1.5e-6, rel=0.1)
    assert abs(report["gap_after"] - 1.0) <= 0.05


@pytest.mark.slow  # ~25 s: a full search with every candidate and check, on a scene of its own
def test_persistence_with_another_decay_frees_gamma(scene, simulated):
    """The measured persistence decays with gamma = 1.4 (the model holds 1.0): A alone cannot describe it, and
    the BIC supports freeing gamma; both are reported and the gap closes."""
    measured = sequence(scene, "gamma", "persistence.A=0.5", "persistence.gamma=1.4")
    report, _ = diagnose(scene, measured, simulated, "gamma")
    assert [e["effect"] for e in report["found"]] == ["persistence"], report["verdict"]
    params, errors = report["found"][0]["params"], report["found"][0]["errors"]
    assert "gamma" in params, params
    assert abs(params["gamma"] - 1.4) <= max(0.1 * 1.4, 3 * errors["gamma"]), (params, errors)
    assert abs(report["gap_after"] - 1.0) <= 0.05


def test_dark_and_offset_on_one_exposure_time_are_one_degenerate_group(scene, simulated):
    """A small dark current on exposures of one length adds what an offset adds (its noise is too small
    to tell): both are reported, as one group, never a guess."""
    measured = sequence(scene, "small_dark", "dark.current=0.03")
    report, _ = diagnose(scene, measured, simulated, "small_dark")
    assert len(report["found"]) == 1
    group = {report["found"][0]["effect"], *report["found"][0]["degenerate_with"]}
    assert group == {"dark", "offset"}, report["verdict"]
    assert "cannot tell them apart" in report["verdict"]


def test_exposure_times_separate_dark_from_offset(scene):
    """With exposures of different lengths the same dark current is named alone."""
    times = [60.0, 139.8, 300.0]
    simulated = sequence(scene, "sim_times", seed=210, exptimes=times)
    measured = sequence(scene, "dark_times", "dark.current=0.04", exptimes=times)
    report, _ = diagnose(scene, measured, simulated, "dark_times")
    assert [e["effect"] for e in report["found"]] == ["dark"], report["verdict"]
    assert report["found"][0]["degenerate_with"] == []
    assert report["found"][0]["params"]["current"] == pytest.approx(0.04, rel=0.1, abs=3 * report["found"][0]
                                                                    ["errors"]["current"])


def test_the_same_data_in_any_order_give_the_same_report(scene, simulated):
    measured = sequence(scene, "dark", "dark.current=0.4")
    a, _ = diagnose(scene, measured, simulated, "order1")
    b, _ = diagnose(scene, measured[::-1], simulated[::-1], "order2")
    assert a["found"][0]["params"] == b["found"][0]["params"]
    assert a["gap_after"] == b["gap_after"]


def test_the_fitted_model_renders_what_was_fitted(scene, simulated):
    """Re-simulating with OUTDIR/model.yaml: the new simulation is consistent with the measured data."""
    measured = sequence(scene, "nonlinearity", "nonlinearity.beta=-1.6e-6")
    _, outdir = diagnose(scene, measured, simulated, "resim")
    d = scene["dir"] / "resim2"
    d.mkdir(exist_ok=True)
    out, mjd = [], MJD1
    for k in range(3):
        path = d / f"e{k}.fits"
        args = ["render", scene["truth"], "--bounds", *BOUNDS, "--ra", RA + k * 1.5e-4, "--dec", DEC, "--pa", PA,
                "--mjd", repr(mjd), "--filter", FILTER, "--sca", SCA, "--seed", 500 + k, "--model",
                outdir / "model.yaml", "--persistence-source", "all", "-o", path]
        for p in out:
            args += ["--previous", p]
        run(*args)
        out.append(str(path))
        mjd += STEP
    report, _ = diagnose(scene, measured, out, "resim_check")
    assert report["found"] == [], report["verdict"]


def test_errors(scene, simulated, tmp_path):
    measured = sequence(scene, "null", seed=300)
    result = run("diagnose", *measured, "--simulated", simulated[0], "-o", tmp_path / "o", code=1)
    assert "simulated" in result.stderr and len(result.stderr.strip().splitlines()) == 1
    assert not (tmp_path / "o").exists()
    result = run("diagnose", *measured, "-o", tmp_path / "o", code=1)
    assert "ramps" in result.stderr and not (tmp_path / "o").exists()
    # an output folder holding an input is refused before anything is done
    result = run("diagnose", *measured, "-o", os.path.dirname(measured[0]), "--overwrite", code=1)
    assert "holds the input" in result.stderr
    assert not [p for p in os.listdir(scene["dir"]) if p.startswith(".perscli-")]


# -- what diagnose refuses before any fit: one line, exit 1 (2 for a bad option), nothing written -----------

def test_bad_options_outputs_and_models_are_refused_before_the_fit(scene, tmp_path):
    sims = sequence(scene, "refusals", n=2)
    args = ["diagnose", *sims, "--simulated", sims[0], "--simulated", sims[1]]
    assert "--gain" in one_line_error(invoke(*args, "--gain", "nan", "-o", tmp_path / "d"), code=2)
    assert "not a stream" in one_line_error(invoke(*args, "-o", "-"), code=1)
    a_file = tmp_path / "a_file"
    a_file.write_text("x")
    assert "is a file" in one_line_error(invoke(*args, "-o", a_file), code=1)
    assert "does not exist" in one_line_error(invoke(*args, "-o", tmp_path / "no" / "such" / "d"), code=1)
    model = tmp_path / "m.yaml"
    model.write_text("effects:\n  - dark: {current: 0.02}\nefects: []\n")
    line = one_line_error(invoke(*args, "--model", model, "-o", tmp_path / "d"), code=1)
    assert "efects" in line
    assert a_file.read_text() == "x" and sorted(p.name for p in tmp_path.iterdir()) == ["a_file", "m.yaml"]


def test_a_shell_glob_after_simulated_is_named_and_an_empty_simulation_refused(scene, tmp_path):
    sims = sequence(scene, "refusals", n=2)
    import shutil

    from astropy.io import fits

    measured = [tmp_path / "m0.fits", tmp_path / "m1.fits"]
    for src, dst in zip(sims, measured):
        shutil.copy(src, dst)
    # `diagnose m*.fits --simulated sim*.fits`: the shell passes the second simulation as a measured frame
    line = one_line_error(invoke("diagnose", *measured, "--simulated", sims[0], sims[1], "-o", tmp_path / "d"),
                          code=1)
    assert "--simulated per file" in line

    empty = tmp_path / "empty_ideal.fits"
    with fits.open(sims[1]) as hdul:
        hdul["IDEAL"].data = np.full(hdul["IDEAL"].data.shape, np.nan, dtype=np.float32)
        hdul.writeto(empty, checksum=True)
    line = one_line_error(invoke("diagnose", *measured, "--simulated", sims[0], "--simulated", empty,
                                 "-o", tmp_path / "d"), code=1)
    assert "IDEAL has no finite pixel" in line
    assert not (tmp_path / "d").exists()


def test_a_ramp_whose_reads_share_one_time_is_refused(tmp_path):
    from fits_factory import wfc3_ramp_file

    rng = np.random.default_rng(5)
    reads = [rng.normal(100.0 * k, 5.0, (32, 32)).astype(np.float32) for k in range(4)]
    prim = {"EXPSTART": MJD1, "EXPEND": MJD1 + 100.0 / 86400.0, "EXPTIME": 100.0, "CCDGAIN": 2.5}
    path = wfc3_ramp_file(tmp_path / "raw.fits", reads, [0.0, 0.0, 0.0, 0.0], {"BUNIT": "COUNTS"},
                          primary_keywords=prim)
    line = one_line_error(invoke("diagnose", path, "-o", tmp_path / "d"), code=1)
    assert "SAMPTIME repeats" in line and "increasing times" in line, line
    assert not (tmp_path / "d").exists()


def test_fit_stripes_sit_where_the_simulation_is_bright():
    """One stripe in each eighth of the frame, at the rows holding the most bright pixels of the simulation
    or the earlier exposures' fluence (where nonlinearity and persistence show); evenly spaced in a flat field."""
    from types import SimpleNamespace

    from perscli.diagnose.likelihood import BRIGHT_ELECTRONS, _bright_rows, _stripes

    ny, nx = 512, 256
    flat = [SimpleNamespace(data=np.zeros((ny, nx)), ideal=np.full((ny, nx), 100.0), fluence=None) for _ in range(3)]
    even = _stripes(ny, nx, 8 * 8 * nx, _bright_rows(flat))
    assert even == _stripes(ny, nx, 8 * 8 * nx)
    starred = [SimpleNamespace(data=np.zeros((ny, nx)), ideal=np.full((ny, nx), 100.0),
                               fluence=np.full((ny, nx), 100.0)) for _ in range(3)]
    starred[0].ideal[300:303, 10:20] = 2 * BRIGHT_ELECTRONS       # a star in the current exposure's simulation
    starred[1].fluence[40:44, 50:60] = 2 * BRIGHT_ELECTRONS       # an earlier exposure's star: its history
    starred[2].fluence[100:104, 50:60] = 2 * BRIGHT_ELECTRONS     # the last exposure's fluence leaves no history
    rows = _bright_rows(starred)
    assert rows[300] == 10 and rows[41] == 10 and rows[101] == 0
    stripes = _stripes(ny, nx, 8 * 8 * nx, rows)
    kept = [set(range(r.start + a, r.start + b)) for r, a, b in stripes]
    assert all(len(k) == 8 for k in kept)
    assert {300, 301, 302} <= kept[300 * 8 // ny] and {40, 41, 42, 43} <= kept[40 * 8 // ny]
    assert [min(k) // (ny // 8) for k in kept] == list(range(8))                 # one per eighth
    assert [s for k, s in enumerate(stripes) if k not in (0, 4)] == [s for k, s in enumerate(even) if k not in (0, 4)]


@pytest.mark.slow  # ~15 s: the whole diagnose twice
def test_threads_give_the_same_report(scene, simulated):
    """--workers spreads each likelihood evaluation over the exposures: the report is the same, byte for byte."""
    measured = sequence(scene, "persistence", "persistence.A=0.15")
    one, d1 = diagnose(scene, measured, simulated, "workers1", "--fit-pixels", "3000")
    two, d2 = diagnose(scene, measured, simulated, "workers2", "--fit-pixels", "3000", "--workers", "2")
    assert [e["effect"] for e in one["found"]] == ["persistence"], one["verdict"]
    # the law's shape is the model's: the screen leaves it held (the gamma case above frees it)
    assert set(one["found"][0]["params"]) == {"A"}
    assert (d1 / "report.json").read_bytes() == (d2 / "report.json").read_bytes()


# -- the pieces of the decision, on their own (cheap) -------------------------------------------------------------

def _linear_problem(seed=1, n=20000):
    """A likelihood with known answers: pixels y = a + b x + noise of variance v0 (1 + c), three candidates
    (a level, a slope, a variance share) whose model is a dict."""
    from types import SimpleNamespace

    from perscli.diagnose.candidates import Candidate
    from perscli.diagnose.likelihood import Evaluation

    rng = np.random.default_rng(seed)
    x = np.linspace(0.0, 3.0, n)
    v0 = np.full(n, 4.0)
    truth = {"a": 0.3, "b": -0.2, "c": 0.1}
    data = truth["a"] + truth["b"] * x + rng.normal(0.0, np.sqrt(v0 * (1 + truth["c"])))

    def evaluate(model):
        mean = model["a"] + model["b"] * x
        return Evaluation([mean], [v0 * (1 + model["c"])], [data], [np.ones(n, dtype=bool)])

    def cand(name, scale):
        return Candidate(name, name, "", (-5.0, 5.0), scale, "signal", "", lambda m, e: m[name],
                         lambda m, v: {**m, name: float(v)})

    problem = SimpleNamespace(evaluate=evaluate, exposures=[])
    return problem, [cand("a", 0.1), cand("b", 0.1), cand("c", 0.05)], truth, x, v0, data


def test_joint_fit_by_fisher_scoring_gives_the_least_squares_answer_and_its_covariance():
    """The level and slope of a straight line and the noise's variance share, fitted together from zero: the
    values and covariance of weighted least squares (and the variance's maximum-likelihood value)."""
    from perscli.diagnose.joint import correlations, joint_fit

    problem, cands, truth, x, v0, data = _linear_problem()
    model, values, cov, m2 = joint_fit(problem, {"a": 0.0, "b": 0.0, "c": 0.0}, cands)
    c = values[2]
    design = np.stack([np.ones_like(x), x], axis=1)
    w = 1.0 / (v0 * (1 + c))
    ls_cov = np.linalg.inv(design.T @ (design * w[:, None]))
    ls = ls_cov @ design.T @ (w * data)
    assert np.allclose(values[:2], ls, rtol=1e-6, atol=1e-9), (values, ls)
    assert np.allclose(cov[:2, :2], ls_cov, rtol=1e-3)
    resid = data - design @ ls
    assert c == pytest.approx(np.mean(resid ** 2 / v0) - 1.0, abs=2e-3)
    assert all(abs(v - truth[k]) < 4 * np.sqrt(cov[i, i]) for i, (k, v) in enumerate(zip("abc", values)))
    # level and slope share their information: strongly anticorrelated on x in [0, 3]
    assert correlations(cov)[0, 1] < -0.8


def test_a_candidates_improvement_beside_a_named_one_is_its_held_one_over_one_minus_rho2():
    """The slope fitted with the level held at its best (without the slope) recovers only 1 - rho^2 of what the
    two fitted together gain: the profile improvement is the held one divided by it."""
    from perscli.diagnose.joint import directions, joint_fit, shared_information

    problem, cands, truth, x, v0, data = _linear_problem(seed=2)
    level, slope = cands[0], cands[1]
    start = {"a": 0.0, "b": 0.0, "c": truth["c"]}
    with_level, _, _, m2_level = joint_fit(problem, start, [level])
    dirs = directions(problem, with_level, [level, slope])
    rho2 = shared_information(dirs, "b", ["a"])
    held = dirs.score[1] ** 2 / dirs.fisher[1, 1]
    _, _, _, m2_both = joint_fit(problem, with_level, [level, slope])
    assert 0.5 < rho2 < 0.9
    assert held / (1 - rho2) == pytest.approx(m2_level - m2_both, rel=1e-3)


def test_the_verdict_keeps_withdrawn_evidence_and_never_says_no_missing_effect_beside_it():
    from perscli.diagnose.report import _verdict

    withdrawn = {"probe": "withdrawn", "effect": "persistence", "significance": 90.2,
                 "reason": "persistence-like signal whose decay is not the model's law (t^-1)"}
    verdict = _verdict([], [withdrawn])
    assert verdict.startswith("unexplained") and "persistence withdrawn (90 sigma" in verdict
    assert "decay is not the model's law" in verdict
    assert _verdict([], []) == "no missing effect"


def test_the_gap_is_closed_only_beyond_its_noise_and_shares_are_never_negative():
    from types import SimpleNamespace

    from perscli.diagnose.report import _closed, _effect_gaps

    noise = 0.0014
    assert _closed(1.0300, 1.0010, noise) == "closed"
    assert _closed(1.0012, 1.0020, noise) == "within noise"
    assert _closed(1.0012, 1.0100, noise) == "worse"
    # a gap within its noise of 1 before has no share to close: the -136% of a gap going from 1.0012 to 1.0028
    entry = {"effect": "read_noise"}
    result = SimpleNamespace(found=[entry], withdrawn=[], model=None)
    _effect_gaps(None, None, result, 1.0028, 1.0012, noise)
    assert entry["gap_closed"] == "worse" and entry["share_of_gap_closed"] is None
    entry = {"effect": "dark"}
    result = SimpleNamespace(found=[entry], withdrawn=[], model=None)
    _effect_gaps(None, None, result, 1.0009, 1.2000, noise)
    assert entry["gap_closed"] == "closed" and 0.99 < entry["share_of_gap_closed"] <= 1.0
