"""``perscli diagnose`` as a function: read, search, re-simulate, and write model.yaml, report.json,
report.md and the figures into an output folder that appears whole or not at all."""

from __future__ import annotations

import json
import logging
import math
import os
import shutil
import tempfile
import textwrap

import numpy as np

from .. import PerscliError, __version__
from ..detector.model import load_detector_model, model_to_yaml
from ..io.tempfiles import make_temp_folder
from .candidates import by_name
from .checks import ALPHA as CHECK_ALPHA
from .probes import PROBES, run_probes
from .candidate_fit import MIN_DELTA_CHI2, _reset
from .data import attach_simulations, read_measured
from .likelihood import Problem
from .ramp import RampProblem, ramp_model
from .search import search
from .settings import DiagnoseOptions

log = logging.getLogger(__name__)


def _jsonable(value):
    if isinstance(value, dict):
        return {str(k): _jsonable(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_jsonable(v) for v in value]
    if isinstance(value, (np.floating, float)):
        value = float(value)
        return value if math.isfinite(value) else None
    if isinstance(value, np.integer):
        return int(value)
    if isinstance(value, np.bool_):
        return bool(value)
    return value


def diagnose(measured, *, simulated=(), model_spec=None, options: DiagnoseOptions = DiagnoseOptions(),
             progress=None) -> dict:
    """Find the missing or mis-set detector effects of ``simulated`` against ``measured``.

    Parameters
    ----------
    measured : sequence of str
        Measured frames (any order; put in time order from their headers).
    simulated : sequence of str
        The same exposures rendered by ``perscli render`` (IDEAL, FLUENCE, MODEL);
        empty for a lone ramp, whose expectation is then predicted from its
        own earliest reads.
    model_spec : str, optional
        A detector model overriding the one stored in the simulated frames.
    options : DiagnoseOptions
        How much of the frames the fits use (``fit_pixels``: the gaps use
        every pixel), the gain and exposure time of frames whose headers lack
        them, and ``workers`` (threads over the exposures of each likelihood
        evaluation, compared with simulated frames; the result does not depend
        on it).
    progress : callable, optional
        ``progress(text)`` for messages on the way.

    Returns
    -------
    dict
        The report (see :func:`write_report`), plus the objects the figures need.
    """
    say = progress or (lambda text: None)
    exposures = read_measured(measured, gain=options.gain, exptime=options.exptime)
    if simulated:
        models = attach_simulations(exposures, simulated)
        if model_spec is not None:
            model = load_detector_model(model_spec)
        else:
            stored = [m for m in models if m is not None]
            if not stored:
                raise PerscliError("the simulated frames carry no detector model (MODEL table); give --model")
            model = stored[-1]
        problem = Problem(exposures, fit_pixels=options.fit_pixels, workers=options.workers)
        mode = "simulated"
    else:
        ramps = [e for e in exposures if e.is_ramp]
        if not ramps:
            raise PerscliError("without --simulated frames diagnose needs ramps (MULTIACCUM or cubes) to predict "
                               "from themselves; give the simulated frames of these exposures")
        model = load_detector_model(model_spec) if model_spec is not None else ramp_model(exposures)
        problem = RampProblem(exposures, fit_pixels=options.fit_pixels)
        mode = "self-predicted"
    # said once the inputs are known to make a problem: a refusal stays the one line on stderr
    say(f"{len(exposures)} measured exposure(s), {exposures[0].data.shape[-2]} x {exposures[0].data.shape[-1]} px, "
        f"{mode}")
    chi2, n = problem.chi2_full(model)
    gap_before = chi2 / max(n, 1)
    # chi^2 / N of N independent unit Gaussians scatters by sqrt(2 / N): the gap's own noise
    gap_noise = math.sqrt(2.0 / max(n, 1))
    before_eval = problem.evaluate(model)
    say(f"gap before: chi2/dof = {gap_before:.4g} +- {gap_noise:.2g} over {n} pixels")
    probes_before = run_probes(problem, before_eval)
    result = search(problem, model, progress=say, ramp=mode == "self-predicted")
    chi2_after, n_after = problem.chi2_full(result.model)
    _effect_gaps(problem, model, result, chi2_after / max(n_after, 1), gap_before, gap_noise)
    worse = [e for e in result.found if e["gap_closed"] == "worse"
             and abs(chi2_after / max(n_after, 1) - 1.0) > GAP_VETO * gap_noise]
    if worse:
        # an effect whose addition moved the gap away from 1 by more than its noise, to where pure noise would
        # seldom put it, is not written into model.yaml: its likelihood gain on the fit pixels comes from
        # absorbing what the model lacks.  (Beyond that the gap is no test: two models of the same data differ in
        # it by what they fit, and a right effect moves a gap that noise put below 1 further down.)
        final = result.model
        for e in worse:
            final = _reset(final, model, e["effect"])
            result.withdrawn.append({**e, "withdrawn_because": e["gap_note"], "checks": ["gap"]})
            result.unexplained.append({"probe": "withdrawn", "effect": e["effect"],
                                       "significance": e["significance_sigma"], "reason": e["gap_note"],
                                       "description": f"{e['effect']} fitted at {e['significance_sigma']:.1f} "
                                                      f"sigma and withdrawn: {e['gap_note']}"})
        result.found = [e for e in result.found if e not in worse]
        result.model = final
        result.correlations = {k: v for k, v in result.correlations.items()
                               if not any(k.startswith(e["effect"] + ".") or ("~" + e["effect"] + ".") in k
                                          for e in worse)}
        chi2_after, n_after = problem.chi2_full(result.model)
    # the probes after compare every fit pixel, as the probes before do: pixels a persistence no law describes
    # had set aside, and the levels freed for it, were for the search's fits only
    if hasattr(problem, "aside"):
        problem.aside, problem.free_levels = None, frozenset()
    after_eval = problem.evaluate(result.model)
    nfit = sum(f.get("free_parameters", len(f["params"])) for f in result.found)
    gap_after = chi2_after / max(n_after - nfit, 1)
    probes_after = run_probes(problem, after_eval, reference=before_eval)
    say(f"gap after: chi2/dof = {gap_after:.4g} +- {gap_noise:.2g}")
    for entry in result.found:
        cand = by_name(entry["effect"])
        # one exposure time: a dark current shows as an offset
        entry["probe"] = cand.probe if cand.probe in probes_before else "offset"
        pb, pa = probes_before.get(entry["probe"]), probes_after.get(entry["probe"])
        entry["probe_gap_before"] = pb.gap if pb is not None else None
        entry["probe_gap_after"] = pa.gap if pa is not None else None
        # an effect explains its probe when the binned residuals there are noise once it is added
        entry["probe_explained"] = bool(pa is None or not pa.flagged)
    verdict = _verdict(result.found, result.unexplained)
    report = {
        "perscli": __version__, "mode": mode, "verdict": verdict,
        "measured": [e.label for e in exposures], "simulated": [e.sim for e in exposures],
        "model_source": model.source,
        "found": result.found, "unexplained": result.unexplained, "withdrawn": result.withdrawn,
        "correlations": result.correlations,
        "checks": result.checks, "threshold": {"delta_chi2_one_parameter": MIN_DELTA_CHI2,
                                               "check_p_value": CHECK_ALPHA},
        "gap_before": gap_before, "gap_after": gap_after, "gap_noise": gap_noise,
        "gap_closed": _closed(gap_before, gap_after, gap_noise), "eliminated": result.eliminated,
        "set_aside": result.set_aside, "alternatives": result.alternatives, "below_threshold": result.hints,
        "pixels": n, "candidates": result.candidates, "rounds": result.rounds,
        "probes_before": {k: p.as_dict() for k, p in probes_before.items()},
        "probes_after": {k: p.as_dict() for k, p in probes_after.items()},
    }
    if mode == "self-predicted":
        report["jumps_masked"] = int(problem.jumps)
        report["photon_transfer"] = problem.photon_transfer
    return {"report": report, "model": result.model, "probes_before": probes_before, "probes_after": probes_after}


#: an effect that moves the gap away from 1 is withdrawn when the gap with it is this many times its noise from 1
GAP_VETO = 3.0


def _closed(before: float, after: float, noise: float) -> str:
    """Whether going from gap ``before`` to ``after`` brought it closer to 1 by more than its noise."""
    change = abs(before - 1.0) - abs(after - 1.0)
    if change > noise:
        return "closed"
    if change < -noise:
        return "worse"
    return "within noise"


def _effect_gaps(problem, original, result, gap_after: float, gap_before: float, noise: float) -> None:
    """Each found effect's part in the gap: the gap over every pixel of the final model without it (its value
    reset to the original model's, the others as fitted), against the final model's.

    ``gap_without``, ``gap_change`` (how much closer to 1 the gap is with it),
    ``gap_closed`` ('closed', 'within noise' or 'worse': beyond the gap's
    own noise sqrt(2/N), or not), ``share_of_gap_closed`` (the change over
    the distance of the gap before from 1; only when both that distance and
    the change exceed the noise: a share of noise is no share) and
    ``gap_note`` are set in each entry.
    """
    found = result.found
    for entry in found:
        if len(found) == 1 and not result.withdrawn:
            # the final model without its only effect is the original one
            without = gap_before
        else:
            c2, nn = problem.chi2_full(_reset(result.model, original, entry["effect"]))
            without = c2 / max(nn, 1)
        change = abs(without - 1.0) - abs(gap_after - 1.0)
        entry["gap_without"] = without
        entry["gap_change"] = change
        entry["gap_closed"] = _closed(without, gap_after, noise)
        distance = abs(gap_before - 1.0)
        entry["share_of_gap_closed"] = (min(change / distance, 1.0) if distance > noise and change > noise
                                        else None)
        entry["gap_note"] = {
            "closed": f"brings the gap from {without:.5g} to {gap_after:.5g} (noise {noise:.2g})",
            "within noise": f"moves the gap by less than its noise ({without:.5g} -> {gap_after:.5g}, noise "
                            f"{noise:.2g})",
            "worse": f"adding it moved the gap away from 1 ({without:.5g} -> {gap_after:.5g}, beyond its noise "
                     f"{noise:.2g}): it absorbs what the model lacks"}[entry["gap_closed"]]


def _verdict(found, unexplained) -> str:
    """One line: the effects named (with their degenerate groups), then what stays unexplained (checks that
    fired, fits withdrawn with their significance and reason); "no missing effect" only when neither."""
    parts = []
    if found:
        names = [f"{e['effect']} ({e['significance_sigma']:.0f} sigma)"
                 + (" (or " + ", ".join(e["degenerate_with"]) + ": the data cannot tell them apart)"
                    if e["degenerate_with"] else "") for e in found]
        parts.append("missing or mis-set: " + "; ".join(names))
    if unexplained:
        said = []
        for u in unexplained:
            if u["probe"] == "withdrawn":
                said.append(f"{u['effect']} withdrawn ({u['significance']:.0f} sigma: {u['reason']})")
            elif u.get("reason") and u["reason"] != u.get("description"):
                said.append(f"{u['probe']} ({u['significance']:.0f} sigma: {u['reason']})")
            else:
                said.append(f"{u['probe']} ({u['significance']:.0f} sigma)")
        parts.append("unexplained: " + ", ".join(said) + " (a disagreement no candidate describes; nothing is "
                     "named for it)")
    return "; ".join(parts) if parts else "no missing effect"


def write_report(outcome: dict, outdir: str, *, overwrite: bool = False) -> None:
    """Write OUTDIR (model.yaml, report.json, report.md, PNG figures) atomically: a temporary folder
    beside it renamed into place, so that a failure leaves no half-written OUTDIR."""
    outdir = os.path.abspath(outdir)
    if os.path.exists(outdir) and not overwrite:
        raise PerscliError(f"{outdir}: already exists; use --overwrite to replace it")
    parent = os.path.dirname(outdir)
    if not os.path.isdir(parent):
        raise PerscliError(f"{parent}: folder does not exist; create it or choose another output")

    # a new folder's permissions (0777 less the umask); the files in it get a new file's
    tmp = make_temp_folder(parent, prefix=".perscli-diagnose-")
    try:
        report = outcome["report"]
        with open(os.path.join(tmp, "model.yaml"), "w") as fh:
            fh.write(model_to_yaml(outcome["model"], header=f"perscli {__version__} diagnose: {report['verdict']}\n"
                                   "the simulation's model with the effects found set to their fitted values;\n"
                                   "use it with: perscli render --model model.yaml"))
        figures = _figures(outcome, tmp)
        report["figures"] = figures
        with open(os.path.join(tmp, "report.json"), "w") as fh:
            json.dump(_jsonable(report), fh, indent=1)
        with open(os.path.join(tmp, "report.md"), "w") as fh:
            fh.write(_markdown(report))
        if os.path.exists(outdir):
            old = tempfile.mkdtemp(prefix=".perscli-old-", dir=parent)
            os.rmdir(old)
            os.replace(outdir, old)
            os.replace(tmp, outdir)
            shutil.rmtree(old, ignore_errors=True)
        else:
            os.replace(tmp, outdir)
    finally:
        if os.path.exists(tmp):
            shutil.rmtree(tmp, ignore_errors=True)


def _figures(outcome, folder) -> list:
    """A PNG per flagged probe (before and after) and an overview of the gaps."""
    import matplotlib  # lazy: figures only when a report is written; matplotlib.use is process-wide

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt  # lazy: after the backend is chosen

    before, after = outcome["probes_before"], outcome["probes_after"]
    report = outcome["report"]
    names = []
    found_probes = {e.get("probe") for e in report["found"]}
    for key, pb in before.items():
        if key in ("offset", "excess_variance") or not (pb.flagged or key in found_probes) or pb.dof < 2:
            continue
        pa = after.get(key)
        fig, ax = plt.subplots(figsize=(6.4, 4.0), dpi=110)
        ax.axhline(0.0, color="0.6", lw=0.8)
        ax.errorbar(pb.centres, pb.means, yerr=pb.errors, fmt="o-", ms=4, color="C3",
                    label=f"before (gap {_fmt(pb.gap)})")
        if pa is not None and pa.dof:
            ax.errorbar(pa.centres, pa.means, yerr=pa.errors, fmt="s-", ms=4, color="C0",
                        label=f"after (gap {_fmt(pa.gap)})")
        if pb.log_x and np.all(pb.centres > 0):
            ax.set_xscale("log")
        elif getattr(pb, "symlog_x", False):
            ax.set_xscale("symlog", linthresh=1.0)
        ax.set_xlabel(pb.xlabel or PROBES[key])
        ax.set_ylabel("mean residual (data - model) / sigma")
        ax.set_title(f"probe: {PROBES[key]}", fontsize=10)
        ax.legend(fontsize=8)
        fig.tight_layout()
        name = f"probe_{key}.png"
        fig.savefig(os.path.join(folder, name))
        plt.close(fig)
        names.append(name)
    # overview: the gap overall and per probe, before and after
    keys = [k for k in before if before[k].gap == before[k].gap]

    # the whole verdict, wrapped (cut short it would drop the effects named last)
    title = textwrap.fill(report["verdict"], 72)
    fig, ax = plt.subplots(figsize=(6.4, 3.6 + 0.15 * title.count("\n")), dpi=110)
    xs = np.arange(len(keys) + 1)
    gb = [report["gap_before"]] + [before[k].gap for k in keys]
    ga = [report["gap_after"]] + [after[k].gap if k in after else np.nan for k in keys]
    ax.bar(xs - 0.2, gb, 0.4, color="C3", label="before")
    ax.bar(xs + 0.2, ga, 0.4, color="C0", label="after")
    ax.axhline(1.0, color="k", lw=0.8, ls="--")
    noise = report.get("gap_noise")
    if noise:
        # where the gap over every pixel lies for pure noise: chi^2 / N scatters by sqrt(2 / N)
        ax.axhspan(1.0 - 3.0 * noise, 1.0 + 3.0 * noise, color="0.85", zorder=0,
                   label=f"pure noise, all pixels (1 +- 3 x {noise:.2g})")
    ax.set_xticks(xs)
    ax.set_xticklabels(["all"] + keys, rotation=30, ha="right", fontsize=8)
    ax.set_yscale("log")
    from matplotlib.ticker import FormatStrFormatter  # lazy: matplotlib, as above

    # plain numbers on the log axis (gaps are near 1: 1.05, not 1.05 x 10^0)
    ax.yaxis.set_major_formatter(FormatStrFormatter("%.4g"))
    ax.yaxis.set_minor_formatter(FormatStrFormatter("%.4g"))
    ax.set_ylabel("chi2 per pixel (1: pure noise)")
    ax.set_title(title, fontsize=9)
    ax.legend(fontsize=7, loc="best", framealpha=0.8)
    fig.tight_layout()
    fig.savefig(os.path.join(folder, "gap.png"))
    plt.close(fig)
    return ["gap.png"] + names


def _fmt(v):
    if v is None or (isinstance(v, float) and not math.isfinite(v)):
        return "-"
    return f"{v:.4g}" if isinstance(v, float) else str(v)


_GAP_WORDS = {"closed": "closer to 1 by more than its noise", "within noise": "the change is within its noise",
              "worse": "further from 1 by more than its noise"}


def _share(value) -> str:
    return "-" if value is None else f"{100 * value:.0f} %"


def _markdown(report) -> str:
    lines = [f"# perscli diagnose: {report['verdict']}", "",
             f"- mode: {report['mode']}; measured: {', '.join(report['measured'])}",
             f"- model: {report['model_source']}",
             f"- gap (chi^2 per pixel; 1 for pure noise, within +- {_fmt(report.get('gap_noise'))}, its own noise "
             f"sqrt(2/N)): **{_fmt(report['gap_before'])}** before, **{_fmt(report['gap_after'])}** after, over "
             f"{report['pixels']} pixels: {_GAP_WORDS[report.get('gap_closed', 'within noise')]}", ""]
    if "jumps_masked" in report:
        lines += [f"- pixels masked as jumps (cosmic rays, changes of illumination): {report['jumps_masked']}", ""]
    if report.get("photon_transfer"):
        pt = report["photon_transfer"]
        lines += [f"- photon transfer of the ramp's own reads: {pt.get('verdict', '-')}", ""]
    thr = report.get("threshold", {})
    lines += ["![gaps before and after](gap.png)", "", "## Found", "",
              f"An effect is named when it improves -2 ln L by more than {_fmt(thr.get('delta_chi2_one_parameter'))} "
              "for one free parameter (a false-alarm probability of 1e-3; the same for more) with the effects "
              "already named refitted beside it, its value is physical, no misspecification check it would only "
              "absorb fires, it still passes beside all the others (backward elimination), the set it belongs to "
              "describes the data better than any other set of candidates, and adding it does not move the gap "
              "away from 1 by more than the gap's noise to beyond 3 times it.  Values, errors (marginal) and "
              "significances are those of one joint fit of the final set.", ""]
    if not report["found"]:
        lines += ["Nothing is named" + (": what the data hold that the model lacks is no candidate's (see "
                                        "Unexplained)." if report.get("unexplained") else
                                        ": no candidate improves the likelihood significantly, and every check "
                                        "passes (no missing effect)."), ""]
    else:
        lines += ["| effect | parameter | fitted | error | model had | delta chi2 | significance (sigma) | "
                  "gap without it -> with it | share of gap closed | probe gap before -> after | probe explained | "
                  "degenerate with |",
                  "|" + "---|" * 12]
        for e in report["found"]:
            param = next(iter(e["params"]))
            value = e["params"][param]
            if len(e["params"]) > 1:
                param = ", ".join(e["params"])
                value = ", ".join(_fmt(v) for v in e["params"].values())
                e = dict(e, errors={param: ", ".join(_fmt(v) for v in e["errors"].values())})
            lines.append(f"| {e['effect']} | {param} | {_fmt(value)} | {_fmt(e['errors'][param])} | "
                         f"{_fmt(e['model_value'])} | {_fmt(e['delta_chi2'])} | {_fmt(e.get('significance_sigma'))} | "
                         f"{_fmt(e.get('gap_without'))} -> {_fmt(report['gap_after'])} ({e.get('gap_closed', '-')}) | "
                         f"{_share(e.get('share_of_gap_closed'))} | "
                         f"{e.get('probe')}: {_fmt(e.get('probe_gap_before'))} -> {_fmt(e.get('probe_gap_after'))} | "
                         f"{'yes' if e.get('probe_explained') else 'no: a trend remains'} | "
                         f"{', '.join(e['degenerate_with']) or '-'} |")
        lines.append("")
    if report.get("correlations"):
        lines += ["Correlations of the named effects' parameters (joint fit):", ""]
        lines += [f"- {k}: {_fmt(v)}" for k, v in report["correlations"].items()] + [""]
    if report.get("alternatives"):
        lines += ["Sets of effects the data cannot tell from the one named (their score, -2 ln L plus the threshold "
                  "per effect, within 10 of its):", ""]
        lines += [f"- {', '.join(names) or 'none'} ({_fmt(delta)} more)" for names, delta in report["alternatives"]]
        lines.append("")
    if report.get("below_threshold"):
        lines += ["Below the naming threshold but above p = 0.01 beside the named effects (not named, not in "
                  "model.yaml: where more data would look first):", ""]
        lines += [f"- {h['effect']} {h['param']} ~ {_fmt(h['value'])} ({_fmt(h['significance_sigma'])} sigma)"
                  for h in report["below_threshold"]] + [""]
    if report.get("set_aside"):
        sa = report["set_aside"]
        lines += [f"A persistence the law does not describe was found (see Unexplained): the {sa['pixels']} pixels of "
                  f"the fit rows where the law at A = {_fmt(sa['law_A'])} leaves more than {_fmt(sa['electrons'])} e- "
                  "were set aside and every other effect fitted again without them.", ""]
    if report.get("eliminated"):
        lines += ["Named in the forward search, then not significant beside the others (backward elimination):", ""]
        lines += [f"- {w['effect']}: {w['eliminated_because']}" for w in report["eliminated"]] + [""]
    if report.get("withdrawn"):
        lines += ["Withdrawn (their fits may only absorb what a check found; their evidence is under Unexplained):",
                  ""]
        lines += [f"- {w['effect']} ({_fmt(w.get('significance_sigma'))} sigma): {w['withdrawn_because']}"
                  for w in report["withdrawn"]] + [""]
    lines += ["## Unexplained", ""]
    if not report.get("unexplained"):
        lines += ["Every misspecification check passes on the final model: nothing unexplained.", ""]
    else:
        lines += ["| check | significance (sigma) | what it found |", "|---|---|---|"]
        lines += [f"| {u['probe']} | {_fmt(u['significance'])} | {u['description']} |" for u in report["unexplained"]]
        lines.append("")
    if report.get("checks"):
        lines += ["## Misspecification checks (final model)", "",
                  f"Each fires below p = {_fmt(thr.get('check_p_value'))}.", "",
                  "| check | statistic | dof | p-value | fired |", "|---|---|---|---|---|"]
        lines += [f"| {c['probe']} | {_fmt(c['statistic'])} | {_fmt(c['dof'])} | {c['p_value']:.3g} | "
                  f"{'yes' if c['fired'] else 'no'} |" for c in report["checks"]]
        lines.append("")
    lines += ["## Every candidate (first round)", "",
              "| effect | parameter | fitted | error | model had | delta chi2 | delta BIC | significant |",
              "|" + "---|" * 8]
    for c in report["candidates"]:
        param = next(iter(c["params"]))
        value = c["params"][param]
        lines.append(f"| {c['effect']} | {param} | {_fmt(value)} | {_fmt(c['errors'][param])} | "
                     f"{_fmt(c['model_value'])} | {_fmt(c['delta_chi2'])} | {_fmt(c['delta_bic'])} | "
                     f"{'yes' if c['significant'] else 'no'} |")
    lines += ["", "## Probes", "", "| probe | covariate | chi2 / bins before | flagged | gap before | gap after |",
              "|" + "---|" * 6]
    for key, p in report["probes_before"].items():
        pa = report["probes_after"].get(key, {})
        lines.append(f"| {key} | {p['covariate']} | {_fmt(p['chi2'])} / {p['dof']} | {'yes' if p['flagged'] else 'no'} | "
                     f"{_fmt(p['gap'])} | {_fmt(pa.get('gap'))} |")
    lines.append("")
    for name in report.get("figures", [])[1:]:
        lines += [f"![{name}]({name})", ""]
    lines += ["`model.yaml` is the simulation's model with the effects found set to their fitted values: "
              "`perscli render --model model.yaml` renders what was fitted.", ""]
    return "\n".join(lines)
