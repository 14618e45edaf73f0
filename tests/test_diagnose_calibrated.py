"""diagnose's decisions, calibrated on frames its own effect code did not make (tests/independent_chain.py).

The simulations are perscli renders of one small scene (4 exposures of a 160 x 160 cutout with 40
stars from J = 14 to 22 and 20 galaxies); the "measured" frames are made from their IDEAL by an
independent numpy detector chain with hidden effects, a new noise seed each time.  Every strength is
set in units of the error diagnose itself reports for the effect: one calibration seed at a strong
trial strength gives the error (marginal, beside the other hidden effects of the case), and the case
is made at the number of those errors it asks for.  The rates asked of a tool a detector team can
trust, over enough seeds to support them:

- null cases (the chain at Roman's values) name nothing in at least 99% of seeds, and each
  candidate's improvement of -2 ln L follows the chi^2 it is tested against;
- each candidate at 6 sigma is named in at least 95% of seeds; at 2 sigma nothing false is named (but in the
  1% of data sets in which the threshold of 1e-3 a candidate lets a false name through: one seed of 20 or 25);
- interpixel capacitance at 5.5 and 10 sigma is named as IPC (not brighter-fatter) in at least 90%;
- sets of effects (gain + reciprocity + IPC, brighter-fatter + IPC + nonlinearity) are recovered whole,
  every value within 3 marginal sigma and nothing else named, in at least 4 of 5 seeds; a 4-sigma
  effect beside a 50-sigma one is found in at least 4 of 5;
- effects outside the candidates end in "unexplained", never in a named effect with a parameter; a
  persistence that decays exponentially, or comes from saturated pixels only, is said to be one, with
  the reason, and nothing else named;
- correlated pairs are recovered within 3 marginal sigma, nothing else named.

These run about four hundred diagnoses (about 25 minutes on 2 cores): they are marked slow.
"""

from __future__ import annotations

import numpy as np
import pytest

from diagnose_scene import make_truth, render_sequence
from independent_chain import make_measured

pytestmark = pytest.mark.slow

BOUNDS = (1001, 1160, 2001, 2160)
NULL_SEEDS = 100
DETECT_SEEDS = 20
TWO_SIGMA_SEEDS = 5
IPC_SEEDS = 10
SET_SEEDS = 5
#: of SET_SEEDS, how many must recover the set
SET_PASS = 4
#: of DETECT_SEEDS (20), how many may name a false effect beside the true one
FALSE_SEEDS_PER_20 = 1
LAW_SEEDS = 5
OUTSIDE_SEEDS = 4
PAIR_SEEDS = 5


@pytest.fixture(scope="module")
def sims(tmp_path_factory):
    d = tmp_path_factory.mktemp("calibrated")
    truth = make_truth(d / "truth.fits", bounds=BOUNDS, nstars=40, ngalaxies=20)
    return {"dir": d, "truth": truth, "frames": render_sequence(truth, d / "sim", bounds=BOUNDS, n=4, seed=200)}


def diagnose_case(sims, tag, seed, frames=None, **hidden):
    from perscli.diagnose.report import diagnose

    frames = frames or sims["frames"]
    out = sims["dir"] / f"{tag}_{seed}"
    out.mkdir(exist_ok=True)
    measured = make_measured(frames, out, seed=seed, **hidden)
    report = diagnose(measured, simulated=frames)["report"]
    for p in out.iterdir():
        p.unlink()
    out.rmdir()
    return report


def correlation(report, a, b):
    """The joint fit's correlation of parameters ``a`` and ``b`` ('effect.param'), in either order."""
    table = report["correlations"]
    assert f"{a}~{b}" in table or f"{b}~{a}" in table, (a, b, table)
    return table.get(f"{a}~{b}", table.get(f"{b}~{a}"))


def test_null_cases_name_nothing_and_the_statistics_follow_chi2(sims):
    reports = [diagnose_case(sims, "null", 10_000 + s) for s in range(NULL_SEEDS)]
    named = [r["verdict"] for r in reports if r["found"]]
    # at least 99% name nothing
    assert len(named) <= NULL_SEEDS // 100, named
    assert sum(1 for r in reports if r["unexplained"]) <= NULL_SEEDS // 100, \
        [r["unexplained"] for r in reports if r["unexplained"]]
    # each candidate's improvement is a chi^2 with one degree of freedom (or a boundary mixture with
    # fewer): its mean over the seeds within 3 standard errors of 1
    deltas = {}
    for r in reports:
        for c in r["candidates"]:
            deltas.setdefault(c["effect"], []).append(c["delta_chi2"])
    for effect, values in deltas.items():
        values = np.asarray(values)
        dof = 2 if effect == "correlated_read_noise" else 1
        assert values.mean() < dof + 3 * np.sqrt(2 * dof / len(values)), (effect, values.mean())


#: Roman's nearest-neighbour IPC coupling (the mean of galsim.roman's 4): what the model of the simulations has
ROMAN_IPC = 0.014291

#: effect -> (its parameter in diagnose, the generator's setting, the value the model has, a trial change): the
#: trial is a strong change (20-40 errors) whose fit gives diagnose's error for the effect on this scene
STRENGTH = {
    "dark": ("current", "dark", 0.015, 0.008),
    "read_noise": ("sigma", "read_noise", 8.5, 1.2),
    "gain": ("gain", "gain", 1.0, 0.003),
    "nonlinearity": ("beta", "beta", -6e-7, -7e-8),
    "reciprocity": ("alpha", "reciprocity", 0.0065, 0.002),
    "ipc": ("alpha", "ipc_alpha", ROMAN_IPC, 0.001),
    "offset": ("level", "offset", 0.0, 1.5),
    "brighter_fatter": ("coefficient", "bf", 0.0, 3e-9),
    "persistence": ("A", "persistence_A", 0.017, 0.05),
}

_ERRORS: dict = {}


def errors(sims, effects, **fixed):
    """diagnose's own errors for ``effects`` (names in :data:`STRENGTH`) made together at their trial changes
    (and ``fixed`` generator settings), from one calibration seed: {effect: error}.  Cached per set."""
    key = (tuple(effects), tuple(sorted(fixed.items())))
    if key not in _ERRORS:
        hidden = dict(fixed)
        for name in effects:
            _, setting, model, trial = STRENGTH[name]
            hidden[setting] = model + trial
        report = diagnose_case(sims, "calibration", 90_000 + len(_ERRORS), **hidden)
        found = {e["effect"]: e for e in report["found"]}
        if len(effects) == 1 and effects[0] not in found:
            # named as one it cannot be told from (a dark current as an offset on exposures of one length): its own
            # fit, alone in the first round, gives its error (nothing else is named beside it)
            found = {c["effect"]: c for c in report["candidates"]}
            assert any(effects[0] in e["degenerate_with"] for e in report["found"]), report["verdict"]
        assert set(effects) <= set(found), ("calibration", effects, report["verdict"])
        _ERRORS[key] = {name: found[name]["errors"][STRENGTH[name][0]] for name in effects}
    return _ERRORS[key]


def hidden_at(sims, sigmas: dict, **fixed) -> dict:
    """The generator's settings that put each effect of ``sigmas`` ({effect: how many of its errors}) that many
    of diagnose's own errors from the model's value (the errors of the set, each effect beside the others)."""
    errs = errors(sims, list(sigmas), **fixed)
    out = dict(fixed)
    for name, k in sigmas.items():
        _, setting, model, trial = STRENGTH[name]
        out[setting] = model + np.sign(trial) * k * errs[name]
    return out


def truth(name, hidden):
    return hidden[STRENGTH[name][1]]


#: the decision's threshold is 3.29 sigma, so an effect at exactly 5 sigma is named in 95.6% of seeds: 20 seeds
#: could not tell that from 90%.  At 6 sigma the rate is 99.7%, and 19 of 20 is then a test that fails only when
#: the rate is wrong.  (Correlated read noise is a variance: its significance grows as the square of its rms,
#: and 1.55 e- row and column noise is about 6 sigma here.)
FIVE_SIGMA = ["dark", "read_noise", "gain", "nonlinearity", "reciprocity", "ipc", "offset", "brighter_fatter",
              "correlated_read_noise", "persistence"]


@pytest.mark.parametrize("effect", FIVE_SIGMA)
def test_each_candidate_at_six_sigma_is_named_in_95_percent_of_seeds(sims, effect):
    if effect == "correlated_read_noise":
        hidden, param, value = {"row_noise": 1.55, "col_noise": 1.55}, "row", 1.55
    else:
        hidden = hidden_at(sims, {effect: 6.0})
        param, value = STRENGTH[effect][0], truth(effect, hidden)
    hits, wrong, sigmas = 0, [], []
    for s in range(DETECT_SEEDS):
        report = diagnose_case(sims, effect, 20_000 + s, **hidden)
        # named: as the effect, or in the group of effects the report says the data cannot tell apart
        # from the one it names (a dark current and an offset with one exposure time; gain and reciprocity
        # near 5 sigma in a field of faint stars): "reciprocity (or gain: the data cannot tell them apart)"
        entry = next((e for e in report["found"] if effect in (e["effect"], *e["degenerate_with"])), None)
        if entry is not None:
            hits += 1
            sigmas.append(entry["significance_sigma"])
            if entry["effect"] == effect:
                # within 4 sigma of the truth (the Roman value is what the model had)
                assert abs(entry["params"][param] - value) <= 4 * entry["errors"][param], \
                    (entry["params"], entry["errors"])
        # anything else named is a wrong effect stated with confidence
        wrong += [(s, e["effect"]) for e in report["found"] if e is not entry]
    assert hits >= 0.95 * DETECT_SEEDS, (effect, hits, sigmas)
    # the strengths are about 6 sigma, not far above: the test would not show the rate otherwise
    assert 4.5 < np.median(sigmas) < 9.0, sigmas
    # the threshold names a candidate that is not there in about 1% of data sets (1e-3 for each of ten): one seed
    # of twenty may (two or more: 1.7% at that rate)
    assert len({s for s, _ in wrong}) <= FALSE_SEEDS_PER_20, wrong


TWO_SIGMA = ["ipc", "dark", "nonlinearity", "brighter_fatter", "persistence"]


def test_at_two_sigma_nothing_false_is_named(sims):
    """An effect at 2 sigma is at the edge of what the data say: it may be named (about one seed in ten, at a
    threshold of 3.29 sigma), nothing else (but in the 1% of data sets the threshold lets through: at most one
    of the 25), and nothing is unexplained."""
    false = []
    for effect in TWO_SIGMA:
        hidden = hidden_at(sims, {effect: 2.0})
        for s in range(TWO_SIGMA_SEEDS):
            report = diagnose_case(sims, f"two_{effect}", 25_000 + s, **hidden)
            if not {e["effect"] for e in report["found"]} <= {effect}:
                false.append(report["verdict"])
            assert not report["unexplained"], report["verdict"]
    assert len(false) <= 1, false


@pytest.mark.parametrize("k", [5.5, 10.0])
def test_ipc_is_named_ipc_not_brighter_fatter(sims, k):
    """Interpixel capacitance is tested by its one-parameter template (the model's kernel scaled): at 5.5 and
    10 sigma it is named, as IPC, in at least 90% of seeds; brighter-fatter, whose flow also goes to the nearest
    neighbours, never takes its place."""
    hidden = hidden_at(sims, {"ipc": k})
    named, other = 0, []
    for s in range(IPC_SEEDS):
        report = diagnose_case(sims, f"ipc_{k}", 60_000 + s, **hidden)
        names = [e["effect"] for e in report["found"]]
        named += names == ["ipc"]
        other += [n for n in names if n != "ipc"]
    assert named >= 0.9 * IPC_SEEDS, (k, named, other)
    assert "brighter_fatter" not in other, other


SETS = [
    ("gain_reciprocity_ipc", {"gain": 10.0, "reciprocity": 10.0, "ipc": 10.0}),
    ("bf_ipc_nonlinearity", {"brighter_fatter": 10.0, "ipc": 10.0, "nonlinearity": 10.0}),
    # a weak effect beside a strong one: found at its own significance once the strong one is in
    ("weak_ipc_beside_nonlinearity", {"ipc": 4.0, "nonlinearity": 50.0}),
    ("weak_persistence_beside_reciprocity", {"persistence": 4.0, "reciprocity": 50.0}),
]


@pytest.mark.parametrize("case, sigmas", SETS, ids=[c[0] for c in SETS])
def test_sets_of_effects_are_recovered_together(sims, case, sigmas):
    """Each effect of the set at the given number of its own errors (marginal, beside the others): in at least
    4 of 5 seeds every one is named (the weak one beside a strong one: named, or listed with one it cannot be
    told from, or reported below the threshold), its value within 3 marginal sigma of the truth, and nothing
    else is named."""
    hidden = hidden_at(sims, sigmas)
    good, verdicts = 0, []
    weak = [n for n, k in sigmas.items() if k < 5.0]
    for s in range(SET_SEEDS):
        report = diagnose_case(sims, case, 70_000 + s, **hidden)
        found = {e["effect"]: e for e in report["found"]}
        # found without being named: listed with a named effect as one the data cannot tell from it, or reported
        # below the naming threshold (above p = 0.01 beside the named effects: a 4-sigma effect passes 3.29 sigma
        # in 76% of data sets, 2.58 sigma in 92%)
        listed = ({d for e in report["found"] for d in e["degenerate_with"]}
                  | {h["effect"] for h in report["below_threshold"]})
        verdicts.append(report["verdict"])
        if weak:
            # the weak effect found, the strong one named, and nothing named that is neither one of them nor a
            # stand-in for the weak one
            ok = (all(n in found or n in listed for n in weak) and all(n in found for n in sigmas if n not in weak)
                  and all(n in sigmas or set(e["degenerate_with"]) & set(weak) for n, e in found.items()))
        else:
            ok = set(found) == set(sigmas)
        for name in sigmas:
            if ok and name in found:
                e, param = found[name], STRENGTH[name][0]
                ok = abs(e["params"][param] - truth(name, hidden)) <= 3 * e["errors"][param]
        good += bool(ok)
    assert good >= SET_PASS, (case, good, verdicts)


def exponential_amplitude(sims, tau: float, k: float) -> float:
    """The generator's A that gives an exponentially decaying persistence the charge, in the exposure after,
    of the law's persistence ``k`` of diagnose's errors above the model's A."""
    from independent_chain import ROMAN, _time_integral

    err = errors(sims, ["persistence"])["persistence"]
    gap = 30.0              # the scene's exposures are 139.8 s long, 30 s apart
    ratio = _time_integral(gap, gap + 139.8, ROMAN, tau) / _time_integral(gap, gap + 139.8, ROMAN, "power")
    return (0.017 + k * err) / ratio


#: (tau, strength): persistence that decays exponentially, as strong in the exposure after as the law's at that
#: many of diagnose's errors.  tau 1000 s decays far slower than the law's 1/t, which no power law follows; tau
#: 120 s decays faster, as t^-1.3 does over the first two exposures after: across the three lags of four
#: exposures the data tell the two apart at about 6 sigma when the persistence is at 100 sigma, not at 40 (there
#: "gamma 1.30 +- 0.05" is what the data support)
EXPONENTIAL = [(1000.0, 40.0), (120.0, 150.0)]


@pytest.mark.parametrize("tau, k", EXPONENTIAL, ids=[f"tau{t:g}" for t, _ in EXPONENTIAL])
def test_exponential_persistence_is_unexplained_with_the_reason(sims, tau, k):
    """Persistence that decays exponentially: never named (not absorbed into gamma either), reported as
    unexplained with the reason, the withdrawn fit's significance kept, nothing else named."""
    hidden = {"persistence_A": exponential_amplitude(sims, tau, k), "persistence_tau": tau}
    for s in range(LAW_SEEDS):
        report = diagnose_case(sims, f"tau_{tau:g}", 80_000 + s, **hidden)
        assert report["found"] == [], report["verdict"]
        reasons = [u for u in report["unexplained"] if "decay is not the model's law" in u.get("reason", "")]
        assert reasons, report["verdict"]
        assert "decay is not the model's law" in report["verdict"]
        assert report["verdict"] != "no missing effect"


def test_persistence_from_saturated_pixels_only_is_said_to_be_so(sims):
    """Only the pixels that reached the full well persist (the law has every fluence persist): reported as
    'persistence from saturated pixels only', not as outliers, and nothing else named."""
    err = errors(sims, ["persistence"])["persistence"]
    hidden = {"persistence_A": 0.017 + 40.0 * err, "persistence_saturated_only": True}
    for s in range(LAW_SEEDS):
        report = diagnose_case(sims, "saturated_only", 85_000 + s, **hidden)
        assert report["found"] == [], report["verdict"]
        assert "persistence from saturated pixels only" in report["verdict"], report["verdict"]
        assert not any(u["probe"] == "outliers" for u in report["unexplained"]), report["verdict"]


OUTSIDE = [
    ("one_over_f", {"one_over_f": 6.0}),
    ("hot_pixels", {"hot_fraction": 0.003, "hot_dark": 5.0}),
    ("flat_field", {"flat_rms": 0.01}),
    ("psf_shift", {"shift": 0.05}),
    ("cosmic_rays", {"cosmic_rays": 40}),
    ("exponential_persistence", {"persistence_A": 0.3, "persistence_tau": 300.0}),
]


@pytest.mark.parametrize("case, hidden", OUTSIDE, ids=[c[0] for c in OUTSIDE])
def test_effects_no_candidate_describes_end_unexplained(sims, case, hidden):
    for s in range(OUTSIDE_SEEDS):
        report = diagnose_case(sims, case, 30_000 + s, **hidden)
        # never a wrong effect with a parameter; said out loud
        assert report["found"] == [], (case, report["verdict"])
        assert report["unexplained"], (case, report["verdict"])
        assert report["verdict"].startswith("unexplained")


def test_dark_and_offset_with_two_exposure_times_are_both_recovered(sims):
    times = [60.0, 300.0, 60.0, 300.0]
    frames = render_sequence(sims["truth"], sims["dir"] / "sim_times", bounds=BOUNDS, n=4, seed=300, exptimes=times)
    for s in range(PAIR_SEEDS):
        report = diagnose_case(sims, "dark_offset", 40_000 + s, frames=frames, dark=0.025, offset=5.0)
        found = {e["effect"]: e for e in report["found"]}
        assert set(found) == {"dark", "offset"}, report["verdict"]
        for effect, param, truth in (("dark", "current", 0.025), ("offset", "level", 5.0)):
            e = found[effect]
            assert abs(e["params"][param] - truth) <= 3 * e["errors"][param], (effect, e["params"], e["errors"])
        # the joint fit says how they trade: anticorrelated
        corr = correlation(report, "dark.current", "offset.level")
        assert corr < -0.3, corr


def test_gain_and_nonlinearity_together_are_both_recovered(sims):
    for s in range(PAIR_SEEDS):
        report = diagnose_case(sims, "gain_nl", 50_000 + s, gain=1.02, beta=-1.6e-6)
        found = {e["effect"]: e for e in report["found"]}
        assert set(found) == {"gain", "nonlinearity"}, report["verdict"]
        for effect, param, truth in (("gain", "gain", 1.02), ("nonlinearity", "beta", -1.6e-6)):
            e = found[effect]
            assert abs(e["params"][param] - truth) <= 3 * e["errors"][param], (effect, e["params"], e["errors"])
        assert np.isfinite(correlation(report, "gain.gain", "nonlinearity.beta"))
