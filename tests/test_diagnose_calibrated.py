"""diagnose's decisions, calibrated on frames its own effect code did not make (tests/independent_chain.py).

The simulations are perscli renders of one small scene (4 exposures of a 160 x 160 cutout with 40
stars from J = 14 to 22 and 20 galaxies); the "measured" frames are made from their IDEAL by an
independent numpy detector chain with a hidden effect, a new noise seed each time.  The rates
asked of a tool a detector team can trust, over enough seeds to support them:

- null cases (the chain at Roman's values) name nothing in at least 99% of seeds, and each
  candidate's improvement of -2 ln L follows the chi^2 it is tested against;
- each candidate at 5 sigma or more (6 here: its strength six times the error diagnose reports for it) is named
  in at least 95% of seeds, alone;
- effects outside the candidates end in "unexplained", never in a named effect with a parameter;
- correlated pairs are recovered within 3 marginal sigma, nothing else named.

These run a few hundred diagnoses (about 20 minutes on 2 cores): they are marked slow.
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


#: (generator setting, its Roman value, the effect, its parameter, the hidden value): strengths about 6 sigma
#: of the error diagnose reports (measured on one seed at 20-40 sigma and scaled).  The decision's threshold is
#: 3.29 sigma, so an effect at exactly 5 sigma is named in 95.6% of seeds: 20 seeds could not tell that from
#: 90%.  At 6 sigma the rate is 99.7%, and 19 of 20 is then a test that fails only when the rate is wrong.
FIVE_SIGMA = [
    ("dark", {"dark": 0.01728}, "dark", "current", 0.01728),
    ("read_noise", {"read_noise": 8.90}, "read_noise", "sigma", 8.90),
    ("gain", {"gain": 1.0006}, "gain", "gain", 1.0006),
    ("nonlinearity", {"beta": -6.144e-7}, "nonlinearity", "beta", -6.144e-7),
    # reciprocity, nonlinearity and gain are near-degenerate in a field of 40 faint stars: at 6 sigma the wrong
    # one of them leads by more than the degeneracy window in ~1 seed of 20; at 7.5 the right one is named
    # or listed with it every time
    ("reciprocity", {"reciprocity": 0.00695}, "reciprocity", "alpha", 0.00695),
    ("ipc", {"ipc_alpha": 0.014686}, "ipc", "alpha", 0.014686),
    ("offset", {"offset": 0.324}, "offset", "level", 0.324),
    ("brighter_fatter", {"bf": 6.8e-10}, "brighter_fatter", "coefficient", 6.8e-10),
    # its significance grows as the variance, the square of the rms
    ("correlated_read_noise", {"row_noise": 1.55, "col_noise": 1.55}, "correlated_read_noise", "row", 1.55),
    ("persistence", {"persistence_A": 0.0266}, "persistence", "A", 0.0266),
]


@pytest.mark.parametrize("case, hidden, effect, param, truth", FIVE_SIGMA, ids=[c[0] for c in FIVE_SIGMA])
def test_each_candidate_at_five_sigma_is_named_in_95_percent_of_seeds(sims, case, hidden, effect, param, truth):
    hits, wrong, sigmas = 0, [], []
    for s in range(DETECT_SEEDS):
        report = diagnose_case(sims, case, 20_000 + s, **hidden)
        # named: as the effect, or in the group of effects the report says the data cannot tell apart
        # from the one it names (a dark current and an offset with one exposure time; gain and reciprocity
        # near 5 sigma in a field of faint stars): "reciprocity (or gain: the data cannot tell them apart)"
        entry = next((e for e in report["found"] if effect in (e["effect"], *e["degenerate_with"])), None)
        if entry is not None:
            hits += 1
            sigmas.append(entry["significance_sigma"])
            if entry["effect"] == effect:
                # within 4 sigma of the truth (the Roman value is what the model had)
                assert abs(entry["params"][param] - truth) <= 4 * entry["errors"][param], \
                    (entry["params"], entry["errors"])
        # anything else named is a wrong effect stated with confidence
        wrong += [e["effect"] for e in report["found"] if e is not entry]
    assert hits >= 0.95 * DETECT_SEEDS, (case, hits, sigmas)
    # the strengths are about 6 sigma, not far above: the test would not show the rate otherwise
    assert 4.5 < np.median(sigmas) < 9.0, sigmas
    assert not wrong, wrong


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
