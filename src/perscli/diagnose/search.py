"""Name the effects the data ask for, as a set: forward rounds, backward elimination, a search over sets, checks.

Each round fits every candidate's parameter (one-dimensional: a Newton step
when the Gaussian likelihood, with the model's own variance so that effects
on the noise such as read noise count as much as effects on the mean, is
quadratic over it; a scan and Brent's method when it is not) with the effects
named so far held, and divides its improvement of -2 ln L by the share of its
Fisher information those do not carry (:mod:`perscli.diagnose.joint`): its
improvement with them refitted.  The best candidate is named when that passes
:func:`~perscli.diagnose.candidate_fit.threshold` (a likelihood-ratio test at a false-alarm probability of
1e-3 per candidate), its value is physical and inside its range, an effect on
the signal owes its improvement to the expectation and not to the noise
alone, and refitted together with the named ones (:func:`_confirm`) it still
passes; when no single candidate does, two together may (:func:`_best_pair`).
A named persistence frees its law's shape when the BIC asks for it and is
checked at once against the law's decay and fluence dependence
(:func:`perscli.diagnose.checks.persistence_law`).

Then every named effect is retested beside all the others (backward
elimination), the named set is compared with every other set of one-parameter
candidates (:func:`_best_set`: a set the rounds did not build may describe the
data better), and one joint fit gives the values, marginal errors and
correlations.  Sets within :data:`~perscli.diagnose.candidate_fit.MIN_DELTA_BIC` of the best are what the data
cannot tell apart: their members are listed as degenerate.  The
misspecification checks (:mod:`perscli.diagnose.checks`) run on the final
model: what fires is unexplained, the effects it could be mistaken for are
withdrawn, and the evidence (the checks, the withdrawn fits' significance and
reason) is kept.  The rates of false and missed names are measured by
tests/test_diagnose_calibrated.py.
"""

from __future__ import annotations

import dataclasses
import logging
import math
from dataclasses import dataclass, field
from itertools import combinations

import numpy as np
from scipy.stats import chi2

from .candidate_fit import (FIDELITY, MEAN_EFFECTS, MEAN_SHARE, MIN_DELTA_BIC, Fit, _free_persistence_shape,
                            _mean_only_delta, _reset, _shape_candidate, _unphysical, fit_candidate, threshold)
from .candidates import CANDIDATES, ipc_free_shape
from .checks import persistence_law, run_checks
from .joint import correlations as corr, directions, joint_fit, shared_information
from .likelihood import with_effect
from .noise import dispersion, noise_correlation, significance

log = logging.getLogger(__name__)

@dataclass
class Result:
    """What the search found."""

    found: list                  # dicts: effect, params, errors, delta_chi2, significance, degenerate_with, ...
    candidates: list             # every candidate's fit in the first round (and later ones)
    model: object                # the model with the found effects
    rounds: list
    checks: list = field(default_factory=list)        # the misspecification checks on the final model
    unexplained: list = field(default_factory=list)   # checks that fired, withdrawn fits: the evidence kept
    correlations: dict = field(default_factory=dict)  # between the found effects' parameters (joint fit)
    withdrawn: list = field(default_factory=list)     # effects named, then withdrawn because a check fired
    eliminated: list = field(default_factory=list)    # effects named, then not significant beside the others
    set_aside: dict = field(default_factory=dict)     # fit pixels left out: a persistence no law describes
    alternatives: list = field(default_factory=list)  # sets the data cannot tell from the one named
    hints: list = field(default_factory=list)         # candidates below the naming threshold, above HINT_P


#: a candidate whose Fisher information the named effects carry all but this share of is a combination of
#: them (a correlation above 0.99): the data cannot tell it from them, and it is not tested on its own
DEGENERATE = 0.02
#: candidates tried, best first, for a round's name when the joint refit with the named effects takes the
#: improvement of the ones before below the threshold
CONFIRM_TRIES = 3
#: backward elimination: an effect whose Wald statistic in the final set is below this multiple of the
#: threshold is retested by refitting the others without it (above, the quadratic likelihood settles it)
RETEST_MARGIN = 3.0


def _joint(problem, model, named, progress=None):
    """The named effects fitted by one parameter refitted together (:func:`perscli.diagnose.joint.joint_fit`),
    with the shape parameters a named persistence freed; each entry's values and marginal errors (scaled by
    its noise-correlation dispersion) updated in place.  Returns (model, -2 ln L, covariance, the candidates
    fitted: the named ones first, in order, then the shape parameters)."""
    cands = [c for _, c in named if c.fit is None]
    owners = [next(e for e, cc in named if cc is c) for c in cands]
    for entry, cand in named:
        if cand.name == "persistence" and cand.fit is None:
            for key in entry["params"]:
                if key != cand.param:
                    cands.append(_shape_candidate(key))
                    owners.append(entry)
    if not cands:
        return model, problem.evaluate(model).m2lnl(), np.zeros((0, 0)), cands
    model, values, cov, m2 = joint_fit(problem, model, cands, progress=progress)
    for k, (c, entry) in enumerate(zip(cands, owners)):
        entry["params"][c.param] = float(values[k])
        var = cov[k, k] * entry.get("dispersion", 1.0)
        entry["errors"][c.param] = float(math.sqrt(var)) if var > 0 else float("nan")
    return model, m2, cov, cands


def _retest(problem, model, original, named, entry, cand, m2, npix):
    """The improvement of -2 ln L that ``cand`` (named) brings beside all the other named effects: the
    others refitted without it (it reset to the original model's), divided by its dispersion."""
    without = _reset(model, original, cand.name)
    others = [(e, c) for e, c in named if c is not cand]
    if cand.fit is not None:
        # fitted its own way (its own likelihood): refitted on the model with the others as they are
        value, error, fitted, nparams, *more = cand.fit(problem, without)
        more = more[0] if more else {}
        return float(more.get("delta_chi2", problem.evaluate(without).m2lnl() - problem.evaluate(fitted).m2lnl()))
    saved = [(dict(e["params"]), dict(e["errors"])) for e, _ in others]
    _, m2_without, _, _ = _joint(problem, without, others)
    for (e, _), (p, er) in zip(others, saved):
        e["params"], e["errors"] = p, er
    return (m2_without - m2) / entry.get("dispersion", 1.0)


def _confirm(problem, current, named, fit, base, progress=None):
    """``fit``'s candidate refitted together with the named effects: (model, improvement over ``base``
    divided by its dispersion, its value, -2 ln L)."""
    cands = [c for _, c in named if c.fit is None] + [fit.candidate]
    model, values, cov, m2 = joint_fit(problem, fit.model, cands)
    return model, (base - m2) / getattr(fit, "dispersion", 1.0), float(values[-1]), m2


def search(problem, model, *, candidates=CANDIDATES, progress=None, max_rounds: int | None = None,
           ramp: bool = False) -> Result:
    """Name effects by likelihood, one set at a time: forward, backward, one joint refit; then check.

    Forward: each round fits every candidate not yet named with the named
    ones held (:func:`~perscli.diagnose.candidate_fit.fit_candidate`), and divides its improvement by the
    share of its information the named effects do not carry (``1 - rho^2``,
    :func:`perscli.diagnose.joint.shared_information`): its improvement with
    them refitted, so that a weak effect beside a strong one is tested at its
    own significance.  The best candidate whose improvement passes
    :func:`~perscli.diagnose.candidate_fit.threshold`, whose value is
    physical (:func:`~perscli.diagnose.candidate_fit._unphysical`) and which, if it acts on the signal, owes its improvement to the expectation
    (else it goes to ``unexplained`` as ``variance_only``), is refitted
    together with the named ones (:func:`perscli.diagnose.joint.joint_fit`);
    it is named when the joint improvement still passes.  Candidates within
    :data:`~perscli.diagnose.candidate_fit.MIN_DELTA_BIC` of it are listed as its degenerate group, and stay
    candidates: a later round tests them beside it.  The rounds go on until
    no candidate passes.

    Backward: every named effect is retested beside all the others (its Wald
    statistic in the joint fit; a likelihood ratio with the others refitted
    when that is within :data:`RETEST_MARGIN` of the threshold); the weakest
    that no longer passes is eliminated, and again, until all pass.  One
    joint refit of the final set gives the values, marginal errors and
    correlations.

    Then the misspecification checks run on the final model: every check
    that fires goes to ``unexplained``, and the named effects it would be
    mistaken for (:attr:`~perscli.diagnose.checks.Check.blocks`) are
    withdrawn: listed under ``withdrawn`` and, with their significance and
    the check's reason, in ``unexplained``; the rest are refitted and checked
    again.  Evidence is never dropped: a check that fired before a withdrawal
    stays in ``unexplained`` whether or not it fires after.
    """
    say = progress or (lambda text: None)
    usable = [c for c in candidates if c.applies(problem.exposures) and problem.allows(c.name)]
    named, rounds = [], []            # named: (entry, candidate)
    variance_only = {}
    disp_of = {}                      # each candidate's noise-correlation dispersion, from its latest fit
    current = model
    max_rounds = max_rounds if max_rounds is not None else len(usable)
    npix = 0
    for round_no in range(max_rounds):
        evaluation = problem.evaluate(current)
        base = evaluation.m2lnl()
        _, npix = evaluation.chi2()
        shared = noise_correlation(problem, current)
        taken = {c.name for _, c in named}
        remaining = [c for c in usable if c.name not in taken]
        if not remaining:
            break
        held_named = [c for _, c in named if c.fit is None]
        rho2 = {}
        others = [c for c in remaining if c.fit is None]
        # the directions of every candidate fitted by one parameter: the named effects' share of each one's
        # information (what holding them costs it), and the pairs' scores
        dirs = directions(problem, current, held_named + others, evaluation=evaluation)
        for c in others:
            rho2[c.name] = shared_information(dirs, c.name, [n.name for n in held_named])
        fits, after = [], {}
        floor = FIDELITY * sum(max(e.get("forward_delta_chi2", 0.0), 0.0) for e, _ in named)
        for cand in remaining:
            k = dirs.index(cand.name) if cand.fit is None else None
            f = fit_candidate(problem, current, cand, base, npix, None if k is None else
                              (dirs.score[k] / dirs.scales[k], dirs.fisher[k, k] / dirs.scales[k] ** 2))
            f.dispersion = 1.0
            if cand.name in MEAN_EFFECTS and f.delta_chi2 > 0.1 * threshold(f.nparams) and f.model is not None:
                # neighbours share noise: the improvement along this candidate's direction is that much larger
                after[cand.name] = getattr(f, "evaluation", None) or problem.evaluate(f.model)
                f.dispersion = dispersion(shared, evaluation, after[cand.name])
                f.delta_chi2 /= f.dispersion
                f.error *= math.sqrt(f.dispersion)
            f.held = f.delta_chi2
            f.floor = floor
            f.rho2 = rho2.get(cand.name, 0.0)
            if f.rho2 > 1.0 - DEGENERATE:
                most = max(held_named, key=lambda n: abs(dirs.fisher[dirs.index(n.name), dirs.index(cand.name)])
                           / math.sqrt(max(dirs.fisher[dirs.index(n.name), dirs.index(n.name)]
                                           * dirs.fisher[dirs.index(cand.name), dirs.index(cand.name)], 1e-300)))
                f.note = f"the named {most.name} carries its information (correlation above 0.99): not told apart"
                f.degenerate_with = most.name
            else:
                f.delta_chi2 = f.held / (1.0 - f.rho2)
            f.delta_bic = f.delta_chi2 - f.nparams * math.log(max(npix, 2))
            fits.append(f)
            disp_of[cand.name] = f.dispersion
            say(f"round {round_no + 1}: {cand.name} {cand.param}={f.value:.6g} delta chi2 {f.delta_chi2:.1f}"
                + (f" (held {f.held:.1f}, rho^2 {f.rho2:.2f})" if f.rho2 else ""))
        fits.sort(key=lambda f: -f.delta_chi2)
        best, tries = None, 0
        for f in fits:
            if not f.significant or f.note:
                continue
            why = _unphysical(f, problem, ramp)
            if not why and f.candidate.name in MEAN_EFFECTS:
                mean_delta = _mean_only_delta(problem, evaluation, f.model, after.get(f.candidate.name))
                if mean_delta / f.dispersion < MEAN_SHARE * f.held:
                    why = "improves the noise model only, not the expectation"
                    variance_only[f.candidate.name] = f.delta_chi2
            if not why and held_named and f.candidate.fit is None:
                if tries >= CONFIRM_TRIES:
                    break
                tries += 1
                joint_model, exact, value, m2j = _confirm(problem, current, named, f, base)
                say(f"round {round_no + 1}: {f.candidate.name} refitted with the named effects: delta chi2 "
                    f"{exact:.1f}")
                f.profile_estimate = f.delta_chi2
                f.delta_chi2 = exact
                f.delta_bic = exact - f.nparams * math.log(max(npix, 2))
                if not f.significant:
                    why = "not significant once the named effects are refitted with it"
                else:
                    f.model, f.value, f.m2lnl = joint_model, value, m2j
            f.note = why
            if not why:
                best = f
                break
        # no single candidate passes: two may, whose signals cancel in part (each weak with the other held)
        pair = None if best is not None else _best_pair(problem, current, named, fits, dirs, evaluation, shared,
                                                        base, npix, ramp, say, round_no)
        rounds.append([f.as_dict() for f in fits])
        if pair is not None:
            (fa, fb), groups = pair
            for f, other, group in ((fa, fb, groups[0]), (fb, fa, groups[1])):
                entry = f.as_dict()
                entry.update(degenerate_with=group, round=round_no + 1, dispersion=f.dispersion,
                             forward_delta_chi2=f.delta_chi2,
                             note=f"named together with {other.candidate.name}: the two improve -2 ln L by "
                                  f"{f.delta_chi2:.1f} (2 parameters), more than any one alone beside the named "
                                  "effects")
                named.append((entry, f.candidate))
            current, _, _, _ = _joint(problem, fa.model, named, progress)
            continue
        if best is None:
            break
        group = [f for f in fits if f.significant and not f.note and f is not best
                 and best.delta_chi2 - f.delta_chi2 < MIN_DELTA_BIC]
        if best.candidate.name == "persistence":
            best = _free_persistence_shape(problem, best, npix, progress)
            if hasattr(problem, "set_aside") and problem.aside is None:
                # the law's shape checked at once: a persistence it cannot describe leaves residuals that every
                # later round would try to explain with something else
                law = [c for c in persistence_law(problem, problem.evaluate(best.model), best.model) if c.fired]
                if law:
                    entry = best.as_dict()
                    entry.update(withdrawn_because=_because(law), checks=[c.name for c in law],
                                 degenerate_with=[], round=round_no + 1)
                    return _without_persistence(problem, model, candidates, law, [entry], best.model, progress,
                                                ramp, rounds)
        extra_note = ""
        if best.candidate.name == "ipc":
            best, extra_note = _ipc_shape(problem, best, progress)
        entry = best.as_dict()
        entry["degenerate_with"] = [f.candidate.name for f in group]
        entry["round"] = round_no + 1
        entry["dispersion"] = best.dispersion
        entry["forward_delta_chi2"] = best.delta_chi2
        if extra_note:
            entry["note"] = extra_note
        named.append((entry, best.candidate))
        current, _, _, _ = _joint(problem, best.model, named, progress)
    original = model
    # backward: every named effect beside all the others; the weakest that no longer passes goes
    eliminated = []
    while len(named) > 1:
        current, m2, cov, cands = _joint(problem, current, named)
        stats = []
        for entry, cand in named:
            if cand.fit is None:
                k = cands.index(cand)
                value, start = entry["params"][cand.param], entry["model_value"]
                wald = (value - start) ** 2 / cov[k, k] / entry.get("dispersion", 1.0) if cov[k, k] > 0 else 0.0
                # an effect whose other parameters were freed (persistence's law) is never judged on one alone
                if len(entry["params"]) > 1:
                    wald = min(wald, threshold(entry["free_parameters"]) * RETEST_MARGIN)
            else:
                wald = 0.0
            stats.append(wald)
        order = np.argsort(stats)
        weakest = None
        for k in order:
            entry, cand = named[k]
            need = threshold(entry["free_parameters"]) + FIDELITY * sum(
                max(e.get("forward_delta_chi2", 0.0), 0.0) for e, c in named if c is not cand)
            if stats[k] >= RETEST_MARGIN * need:
                break
            delta = _retest(problem, current, original, named, entry, cand, m2, npix)
            entry["retest_delta_chi2"] = delta
            say(f"backward: {cand.name} beside the others: delta chi2 {delta:.1f}")
            if delta < need:
                weakest = k
                break
        if weakest is None:
            break
        entry, cand = named.pop(weakest)
        others = ", ".join(c.name for _, c in named)
        eliminated.append({**entry, "eliminated_because": f"not significant beside {others} (delta chi2 "
                                                         f"{entry['retest_delta_chi2']:.1f})"})
        current = _reset(current, original, cand.name)
    # the set as a whole: another set of candidates may describe the data better than the one the rounds built
    # (a gain and reciprocity failure together, where one round took a dark current and the next nonlinearity)
    current, named, alternatives, hints = _best_set(problem, current, original, named, usable, variance_only,
                                                    disp_of, npix, ramp, say)
    current, _, cov, cands = _joint(problem, current, named, progress)
    # the checks on the final model: what they find is unexplained, and what it would pass for is withdrawn
    checks = run_checks(problem, problem.evaluate(current), current, ramp=ramp, final=True)
    fired = {c.name: c for c in checks if c.fired}
    withdrawn = []
    if fired and named:
        keep = []
        for entry, cand in named:
            why = [c for c in fired.values() if cand.name in c.blocks]
            if why:
                withdrawn.append({**entry, "withdrawn_because": _because(why),
                                  "checks": [c.name for c in why]})
            else:
                keep.append((entry, cand))
        if withdrawn:
            named = keep
            current = original
            for entry, cand in named:
                current = _put_entry(current, entry, cand, problem)
            current, _, cov, cands = _joint(problem, current, named, progress)
            checks = run_checks(problem, problem.evaluate(current), current, ramp=ramp, final=True)
            # what fired before stays as evidence; what fires now (the withdrawn fits' signal shows again) joins it
            for c in checks:
                if c.fired:
                    fired[c.name] = c
    law = [c for c in fired.values() if c.name in LAW_CHECKS]
    if law and hasattr(problem, "set_aside") and problem.aside is None:
        return _without_persistence(problem, model, candidates, law, withdrawn, current, progress, ramp, rounds)
    found = [e for e, _ in named]
    correlations = {}
    if len(cands) > 1:
        rho = corr(cov)
        for a in range(len(cands)):
            for b in range(a + 1, len(cands)):
                correlations[f"{cands[a].name}.{cands[a].param}~{cands[b].name}.{cands[b].param}"] = \
                    float(rho[a, b])
    for entry, cand in named:
        _final_significance(entry, cand)
    unexplained = [{"probe": c.name, "significance": c.sigma, "description": c.description, "reason": c.reason}
                   for c in fired.values()]
    for w in withdrawn:
        unexplained.append({"probe": "withdrawn", "effect": w["effect"], "significance": w["significance_sigma"],
                            "reason": w["withdrawn_because"],
                            "description": f"{w['effect']} fitted at {w['significance_sigma']:.1f} sigma and "
                                           f"withdrawn: {w['withdrawn_because']}"})
    named_names = {e["effect"] for e in found}
    for name, delta in variance_only.items():
        if name not in named_names:
            unexplained.append({"probe": "variance_only", "effect": name, "significance": significance(delta),
                                "reason": "noise no candidate describes",
                                "description": f"{name} would improve the fit only through the noise it adds, not "
                                               "the expected signal: noise no candidate describes"})
    return Result(found=found, candidates=rounds[0] if rounds else [], model=current, rounds=rounds,
                  checks=[c.as_dict() for c in checks], unexplained=unexplained, correlations=correlations,
                  withdrawn=withdrawn, eliminated=eliminated, alternatives=alternatives,
                  hints=[h for h in hints if h["effect"] not in {e["effect"] for e in found}])


#: a pair of candidates is named together, when no single one passes, at this false-alarm probability (two
#: parameters: 21.6 in -2 ln L, twice the single threshold): with nine candidates fitted by one parameter, 36
#: pairs keep false pairs in data sets without a missing effect below 1e-3
PAIR_P = 2e-5
#: pairs refitted exactly, best score first
PAIR_TRIES = 2


def _best_pair(problem, current, named, fits, dirs, evaluation, shared, base, npix, ramp, say, round_no):
    """Two candidates named together when no single one passes: effects whose signals partly cancel
    (brighter-fatter and nonlinearity both lower a star's core; a gain and reciprocity failure both scale a
    star) each look weak beside the other held, and strong together.

    Every pair of candidates fitted by one parameter is scored with the
    named effects free: the improvement of -2 ln L the quadratic likelihood
    predicts (``g' F^-1 g`` over the named ones and the pair, less that over
    the named ones), divided by the larger dispersion of the two.  The best
    pairs whose score passes the threshold of two parameters at
    :data:`PAIR_P` are refitted exactly with the named effects
    (:func:`perscli.diagnose.joint.joint_fit`); the first whose exact
    improvement still passes, with physical values, is returned as
    ``((fit, fit), (group, group))``: each group the candidates that could
    replace that member (pairs with the other member scored within
    :data:`~perscli.diagnose.candidate_fit.MIN_DELTA_BIC` of the best), or None.
    """
    need = float(chi2.isf(PAIR_P, 2)) + FIDELITY * sum(max(e.get("forward_delta_chi2", 0.0), 0.0) for e, _ in named)
    by_name = {f.candidate.name: f for f in fits}
    names = [c.name for c in dirs.candidates]
    s_idx = [names.index(c.name) for _, c in named if c.fit is None]
    g, f = dirs.score, dirs.fisher

    def explained(idx):
        if not idx:
            return 0.0
        sub = f[np.ix_(idx, idx)]
        return float(g[idx] @ np.linalg.lstsq(sub, g[idx], rcond=1e-12)[0])

    base_s = explained(s_idx)
    pool = [k for k, n in enumerate(names) if k not in s_idx and n in by_name and not by_name[n].note]
    scored = []
    for a in range(len(pool)):
        for b in range(a + 1, len(pool)):
            i, j = pool[a], pool[b]
            disp = max(by_name[names[i]].dispersion, by_name[names[j]].dispersion)
            scored.append(((explained(s_idx + [i, j]) - base_s) / disp, i, j))
    scored.sort(reverse=True)
    for score, i, j in scored[:PAIR_TRIES]:
        if not score > need:
            break
        fa, fb = by_name[names[i]], by_name[names[j]]
        cands = [c for _, c in named if c.fit is None] + [fa.candidate, fb.candidate]
        model, values, cov, m2 = joint_fit(problem, current, cands)
        disp = dispersion(shared, evaluation, problem.evaluate(model))
        exact = (base - m2) / disp
        say(f"round {round_no + 1}: {fa.candidate.name} and {fb.candidate.name} together: delta chi2 {exact:.1f} "
            f"(score {score:.1f})")
        if not exact > need:
            continue
        out = []
        for k, fit in ((len(cands) - 2, fa), (len(cands) - 1, fb)):
            trial = Fit(fit.candidate, float(values[k]), float(math.sqrt(max(cov[k, k], 0.0) * disp)), fit.start, m2,
                        nparams=1)
            trial.model, trial.dispersion, trial.delta_chi2 = model, disp, exact
            trial.delta_bic = exact - 2 * math.log(max(npix, 2))
            if _unphysical(trial, problem, ramp):
                break
            out.append(trial)
        if len(out) != 2:
            continue
        groups = ([names[x] for sc, x, y in scored if y == j and x != i and score - sc < MIN_DELTA_BIC]
                  + [names[y] for sc, x, y in scored if x == j and y != i and score - sc < MIN_DELTA_BIC],
                  [names[x] for sc, x, y in scored if y == i and x != j and score - sc < MIN_DELTA_BIC]
                  + [names[y] for sc, x, y in scored if x == i and y != j and score - sc < MIN_DELTA_BIC])
        return tuple(out), groups
    return None


#: the search over sets looks at subsets of at most this many candidates fitted by one parameter (2^9 of them)
SET_SIZE = 9
#: and tries at most this many exact refits of a better set
SET_TRIES = 3
#: another set replaces the named one only when its score is lower by more than this: the rounds and the
#: backward elimination have settled each single addition and removal at the threshold already, and a set that
#: ties with the named one at the threshold's edge (an effect at 3.29 sigma, the dispersion counted a little
#: otherwise) is no better description
SET_MARGIN = 2.0


def _set_values(dirs, offsets, disp, pen):
    """For every subset T of the candidates of ``dirs``: the change of -2 ln L (from the model the directions
    were taken at) of fitting T with the others at the original model's values, by the quadratic likelihood,
    divided by the largest dispersion of the set's members, plus ``pen`` per member.  {frozenset: value}."""
    g, f = dirs.score, dirs.fisher
    n = len(g)
    out = {}
    for size in range(0, n + 1):
        for t in combinations(range(n), size):
            fixed = [k for k in range(n) if k not in t]
            d = -offsets[fixed]
            value = float(-2.0 * g[fixed] @ d + d @ f[np.ix_(fixed, fixed)] @ d)
            if t:
                t = list(t)
                rhs = g[t] - f[np.ix_(t, fixed)] @ d
                value -= float(rhs @ np.linalg.lstsq(f[np.ix_(t, t)], rhs, rcond=1e-10)[0])
            members = list(t) + [k for k in range(n) if offsets[k] != 0.0]
            scale = max([disp[k] for k in members] + [1.0])
            out[frozenset(t)] = value / scale + pen * len(t)
    return out


def _best_set(problem, current, original, named, usable, variance_only, disp_of, npix, ramp, say):
    """The set of candidates that describes the data best, searched over every subset of those fitted by one
    parameter, not only along the path the rounds took.

    At the current model the directions of every such candidate (but those
    found to act on the noise only) give the quadratic likelihood; each
    subset's best -2 ln L (its members free, the others back at the
    original model's values) plus :func:`~perscli.diagnose.candidate_fit.threshold` per member, the price a
    round asks of each named effect, is its score (:func:`_set_values`).
    When another subset scores lower than the named one, it is fitted exactly
    (:func:`perscli.diagnose.joint.joint_fit`) and taken when its exact score
    is lower too and its values are physical; then again from there.

    Returns (model, named, alternatives): the sets whose score is within
    :data:`~perscli.diagnose.candidate_fit.MIN_DELTA_BIC` of the best one's, which the data cannot tell
    from it ([[names], delta]); the members each alternative replaces are
    listed as degenerate with the named ones they replace.
    """
    fixed_named = [(e, c) for e, c in named if c.fit is not None]
    pool = [c for c in usable if c.fit is None and c.name not in variance_only]
    if len(pool) > SET_SIZE or not pool:
        return current, named, [], []
    pen = threshold(1)
    alternatives = []
    dirs = None
    for _ in range(SET_TRIES):
        held = {c.name for _, c in named if c.fit is None}
        dirs = directions(problem, current, pool)
        # in units of each candidate's typical size, as the directions are
        offsets = np.array([c.get(current, problem.exposures) - c.get(original, problem.exposures) for c in pool]) \
            / dirs.scales
        disp = [disp_of.get(c.name, 1.0) for c in pool]
        scores = _set_values(dirs, offsets, disp, pen)
        mine = frozenset(k for k, c in enumerate(pool) if c.name in held)
        best = min(scores, key=scores.get)
        # what the data cannot tell from the set named (not from the quadratic best, which the exact fit below
        # may refuse): sets of as many effects scoring within MIN_DELTA_BIC of it
        alternatives = sorted(((sorted(pool[k].name for k in t), v - scores[mine]) for t, v in scores.items()
                               if t != mine and v - scores[mine] < MIN_DELTA_BIC and len(t) == len(mine)),
                              key=lambda a: a[1])
        # the forward model's fidelity: a set that differs from the named one by less than that share of what
        # the named effects bring is no better description
        margin = SET_MARGIN + FIDELITY * sum(max(e.get("forward_delta_chi2", 0.0), 0.0) for e, _ in named)
        if best == mine or not scores[mine] - scores[best] > margin:
            break
        # the better set, fitted exactly from the original model's values of what it leaves out
        trial = current
        for c in pool:
            if c.name in held and pool.index(c) not in best:
                trial = _reset(trial, original, c.name)
        cands = [pool[k] for k in sorted(best)]
        base = problem.evaluate(current).m2lnl()
        model, values, cov, m2 = joint_fit(problem, trial, cands)
        worst = max([disp[k] for k in best] + [disp[k] for k in mine] + [1.0])
        exact = (m2 - base) / worst + pen * (len(best) - len(mine))
        names = [c.name for c in cands]
        say(f"sets: {', '.join(names) or 'none'} instead of {', '.join(sorted(held)) or 'none'}: score "
            f"{exact:+.1f} (quadratic {scores[best] - scores[mine]:+.1f})")
        if not exact < -margin:
            break
        entries = []
        physical = True
        for k, c in enumerate(cands):
            old = next((e for e, cc in named if cc is c), None)
            error = float(math.sqrt(max(cov[k, k], 0.0) * disp_of.get(c.name, 1.0)))
            if old is not None:
                old["params"][c.param], old["errors"][c.param] = float(values[k]), error
                entries.append((old, c))
                continue
            start = c.get(original, problem.exposures)
            fit = Fit(c, float(values[k]), error, start, m2)
            fit.model, fit.dispersion = model, disp_of.get(c.name, 1.0)
            fit.delta_chi2 = ((values[k] - start) / error) ** 2 if error > 0 else 0.0
            if _unphysical(fit, problem, ramp):
                physical = False
                break
            entry = fit.as_dict()
            entry.update(degenerate_with=[], round=0, dispersion=fit.dispersion, forward_delta_chi2=0.0,
                         note="named by the search over sets: the set with it describes the data better than "
                              f"the one the rounds built ({', '.join(sorted(held))})")
            entries.append((entry, c))
        if not physical:
            break
        named = entries + fixed_named
        current = model
        for e, c in fixed_named:
            current = _put_entry(current, e, c, problem)
        dirs = None
    if dirs is None:
        dirs = directions(problem, current, pool)
    hints = _hints(dirs, named, disp_of, FIDELITY * sum(max(e.get("forward_delta_chi2", 0.0), 0.0) for e, _ in named))
    by_entry = {c.name: e for e, c in named}
    # the degenerate groups of the rounds were judged beside part of the set: the whole set's alternatives replace
    # them
    for e, c in named:
        if c.fit is None:
            e["degenerate_with"] = []
    for names, _ in alternatives:
        chosen = {c.name for _, c in named if c.fit is None}
        out, into = chosen - set(names), set(names) - chosen
        for name in out:
            by_entry[name]["degenerate_with"] = sorted(set(by_entry[name]["degenerate_with"]) | into)
    return current, named, [[names, float(delta)] for names, delta in alternatives], hints


#: a candidate whose improvement beside the named effects passes this false-alarm probability (2.58 sigma) but
#: not the naming threshold is reported below the threshold: never named, never written, said
HINT_P = 0.01


def _hints(dirs, named, disp_of, floor: float = 0.0) -> list:
    """Candidates below the naming threshold (plus ``floor``, :data:`FIDELITY`'s) whose improvement beside the
    named effects (the score test at the final model) still passes :data:`HINT_P`: where more data would look
    first."""
    low, high = float(chi2.isf(HINT_P, 1)), threshold(1) + floor
    names = [c.name for c in dirs.candidates]
    held = [names.index(c.name) for _, c in named if c.fit is None and c.name in names]
    g, f = dirs.score, dirs.fisher

    def explained(idx):
        return float(g[idx] @ np.linalg.lstsq(f[np.ix_(idx, idx)], g[idx], rcond=1e-12)[0]) if idx else 0.0

    base = explained(held)
    out = []
    for k, c in enumerate(dirs.candidates):
        if k in held:
            continue
        delta = (explained(held + [k]) - base) / disp_of.get(c.name, 1.0)
        if low < delta <= high:
            step = np.linalg.lstsq(f[np.ix_(held + [k], held + [k])], g[held + [k]], rcond=1e-12)[0][-1]
            out.append({"effect": c.name, "param": c.param, "value": float(dirs.values[k] + step * dirs.scales[k]),
                        "delta_chi2": float(delta), "significance_sigma": significance(delta)})
    return sorted(out, key=lambda h: -h["delta_chi2"])


#: the checks that find a persistence the law does not describe
LAW_CHECKS = ("persistence_decay", "persistence_fluence")
#: pixels where a persistence no law describes leaves more than this share of the read noise are set aside
ASIDE_READ_NOISE = 0.3


def _without_persistence(problem, model, candidates, law, withdrawn, current, progress, ramp, rounds=()) -> Result:
    """The search again without persistence and without the pixels where the persistence the law does not
    describe lies: what the first search named beside it may have absorbed it (a gain a little low makes a
    ghost's residual a little smaller), so everything is measured again on the pixels it leaves alone.

    The pixels set aside are those where the law, at the largest amplitude
    the persistence checks measured, leaves more than :data:`ASIDE_READ_NOISE`
    of the read noise.  The evidence stays: the persistence checks that fired
    and the withdrawn persistence fit go to ``unexplained`` before what the
    second search finds.
    """
    amplitude = max(max(c.detail.get("amplitude", [0.0]) + [0.0]) for c in law)
    pm = current.persistence_model()
    if pm.kind != "fermi" or not amplitude > 0:
        amplitude = max(pm.A, 1e-3)
    sigma = float(current.value("read_noise", "sigma", off=1.0) or 1.0)
    well = current.value("saturation", "full_well", off=None)
    count = problem.set_aside(dataclasses.replace(pm, A=float(amplitude)), ASIDE_READ_NOISE * sigma, well)
    say = progress or (lambda text: None)
    say(f"a persistence no law describes: {count} pixels of the fit rows set aside, the search again without "
        "persistence")
    inner = search(problem, model, candidates=[c for c in candidates if c.name != "persistence"],
                   progress=progress, ramp=ramp)
    evidence = [{"probe": c.name, "significance": c.sigma, "description": c.description, "reason": c.reason}
                for c in law]
    for w in withdrawn:
        if w["effect"] == "persistence":
            evidence.append({"probe": "withdrawn", "effect": "persistence", "significance": w["significance_sigma"],
                             "reason": w["withdrawn_because"],
                             "description": f"persistence fitted at {w['significance_sigma']:.1f} sigma and "
                                            f"withdrawn: {w['withdrawn_because']}"})
            inner.withdrawn.insert(0, w)
    seen = {u["probe"] for u in evidence}
    inner.unexplained = evidence + [u for u in inner.unexplained if u["probe"] not in seen or u["probe"] == "withdrawn"]
    inner.set_aside = {"pixels": count, "law_A": float(amplitude), "electrons": ASIDE_READ_NOISE * sigma}
    if rounds:
        # the rounds of the first search (with persistence) first: where the evidence came from
        inner.rounds = list(rounds) + inner.rounds
        inner.candidates = rounds[0]
    return inner


def _because(checks) -> str:
    """Why a fit is withdrawn, in a few words: the reasons of the checks that say what the data hold instead
    (the persistence law's), and the names of the others (their descriptions are in ``unexplained``)."""
    said = [c.why for c in checks if c.why]
    others = [c.name for c in checks if not c.why]
    if others:
        said.append(f"the {', '.join(others)} check{'s' if len(others) > 1 else ''} fire{'' if len(others) > 1 else 's'}"
                    ": the fit may only absorb what they find")
    return "; ".join(said)


def _put_entry(model, entry, cand, problem):
    """``model`` with a found effect put in at its reported values (all its parameters)."""
    if cand.fit is not None:
        return cand.fit(problem, model)[2]
    if cand.name == "ipc" and "kernel" in entry.get("shape", {}):
        # the freed kernel's shape, at the strength the joint fit gave it
        model = with_effect(model, "ipc", {"kernel": entry["shape"]["kernel"], "alpha": None})
    out = cand.put(model, entry["params"][cand.param])
    extra = {k: v for k, v in entry["params"].items() if k != cand.param}
    return with_effect(out, cand.name, extra) if extra else out


def _final_significance(entry, cand):
    """The entry's significance as it stands in the final set: its value against the model's, over its
    marginal error (the Wald statistic of the joint fit), or its retest's likelihood ratio when one ran."""
    if "retest_delta_chi2" in entry:
        delta = entry["retest_delta_chi2"]
    elif cand.fit is None and len(entry["params"]) == 1:
        err = entry["errors"].get(cand.param)
        delta = ((entry["params"][cand.param] - entry["model_value"]) / err) ** 2 if err and err > 0 else \
            entry["delta_chi2"]
    else:
        delta = entry["delta_chi2"]
    entry["delta_chi2"] = float(delta)
    entry["significance_sigma"] = significance(delta, entry["free_parameters"])
    entry["significant"] = delta > threshold(entry["free_parameters"])


#: the free 8-coupling IPC kernel replaces the one-parameter template when its improvement passes the
#: threshold for its 7 extra parameters
def _ipc_shape(problem, best: Fit, progress=None):
    """A named IPC: its kernel's 8 couplings freed when the data ask for another shape than the model's
    (:func:`perscli.diagnose.candidates.ipc_free_shape`), and the free kernel physical; (fit, note)."""
    shape = ipc_free_shape(problem, best.model)
    delta = shape["delta_chi2"] / best.dispersion
    if delta <= threshold(7):
        return best, ""
    trial = Fit(best.candidate, shape["alpha"], shape["error"] * math.sqrt(best.dispersion), best.start,
                best.m2lnl, nparams=8)
    trial.model = shape["model"]
    why = _unphysical(trial, problem, False)
    if why:
        return best, (f"another kernel shape improves -2 ln L by {delta:.1f} (7 parameters) but is {why}: the "
                      "model's shape is kept")
    if progress is not None:
        progress(f"ipc: the 8 couplings freed (delta chi2 {delta:.1f} over the template)")
    best.model, best.value, best.error = shape["model"], shape["alpha"], trial.error
    best.delta_chi2 += delta
    best.nparams = 8
    best.shape = {"kernel": shape["kernel"], "delta_chi2": delta}
    return best, f"kernel shape freed: its 8 couplings improve -2 ln L by {delta:.1f} over the model's shape"
