"""A study's summary: the paper's numbers beside ours, its figures and what it cost.

``summary.json`` and ``summary.md`` hold the science (the same bytes for
the same settings and seeds, whatever ran them); ``cost.json`` holds what
the run took (CPU seconds and bytes per product, measured, so it varies),
and the projection of that cost to the paper's size.
"""

from __future__ import annotations

import glob
import json
import math
import os
import re

import fitsio
import numpy as np

from .. import PerscliError
from ..stats.budget import bin_verdicts
from .figures import galaxy_beside_ghost, ghost_stamps, xi_against_budget
from .plan import STATE

#: the paper's numbers (Lin et al., Roman HLS, 0.9M galaxies on 6.25 deg^2)
PAPER = {
    "galaxies": 900_000,
    "area_deg2": 6.25,
    "frac_ge_1e-8": 0.01,
    "frac_ge_1e-4": 0.005,
    "de1_mean": -4.8e-6,
    "de2_mean": -2.3e-6,
    "xi_vs_budget": "at least 1, on most scales about 2 orders of magnitude below",
    "theta": "uniform",
}


def _table(path: str, ext: str) -> dict:
    with fitsio.FITS(path) as f:
        if ext not in f:
            return {}
        data = f[ext].read()
    return {name.lower(): data[name] for name in data.dtype.names}


def _header(path: str, ext=0) -> dict:
    with fitsio.FITS(path) as f:
        h = f[ext].read_header()
    return {k: h[k] for k in h.keys() if k not in ("COMMENT", "HISTORY", "")}


def _num(v):
    v = float(v)
    return None if not math.isfinite(v) else v


def variant_results(study_dir: str, name: str, prefix: str = "", differential: bool = False) -> dict:
    """What one realisation of the study found for one persistence variant: De statistics, uniformity, budget.

    ``prefix`` is the realisation's folder ('' for a study of one realisation).
    """
    xi_path = os.path.join(study_dir, prefix, "xi", f"{name}.fits")
    stats = _table(xi_path, "STATS")
    out = {"variant": name}
    if stats:
        row = {k: v[0] if np.ndim(v) else v for k, v in stats.items()}
        if "n" in row:
            out["n"] = int(np.asarray(row["n"]).ravel()[0])
        if "n_clean" in row and out.get("n"):
            # flagged fits are kept in the sample (the paper's pipeline kept them): their share
            out["flagged_fraction"] = 1.0 - int(np.asarray(row["n_clean"]).ravel()[0]) / out["n"]
        for key in ("de1_mean", "de1_err", "de2_mean", "de2_err", "e1_mean", "e2_mean", "de_abs_mean"):
            if key in row:
                out[key] = _num(np.asarray(row[key]).ravel()[0])
        thr = np.atleast_1d(stats.get("threshold", [[]])[0]).astype(float)
        for stem in ("", "dabs_"):
            if f"frac_{stem}ge" in stats:
                frac = np.atleast_1d(stats[f"frac_{stem}ge"][0]).astype(float)
                nge = np.atleast_1d(stats[f"n_{stem}ge"][0]).astype(int)
                out[f"frac_{stem}ge"] = {f"{t:.0e}": _num(f) for t, f in zip(thr, frac)}
                out[f"n_{stem}ge"] = {f"{t:.0e}": int(n) for t, n in zip(thr, nge)}
    ext = name.upper()
    tables = (_products(os.path.join(study_dir, prefix, "shapes", "part*.fits"), r"part\d+of\d+\.fits") or
              _products(os.path.join(study_dir, prefix, "shapes", "sca*", "e*.fits"), r"e\d+\.fits")) \
        if differential else []
    if tables:
        # the differential study: every galaxy of the sample is counted, only those whose stamps changed fitted
        heads = [_header(t, ext) for t in tables]
        out["sample"] = sum(int(h.get("NSAMPLE", 0)) for h in heads)
        out["fitted"] = sum(int(h.get("NFITTED", 0)) for h in heads)
        out["fitted_flagged"] = sum(int(h.get("NFLAGGED", 0)) for h in heads)
        out["measured_fraction"] = out["fitted"] / out["sample"] if out["sample"] else None
        out["methods"] = {m: sum(int(h.get(f"NMETH{k}", 0)) for h in heads)
                          for k, m in enumerate(("linear", "newton", "cold"), 1)}
        check = linear_response_check([_table(t, ext) for t in tables])
        if check:
            out["linear_check"] = check
        if str(heads[0].get("GAXES", "sky")) != "sky":
            # fitted per final: each final's own count of the galaxies on it
            prim = [_header(t, 0) for t in tables]
            out["catalogue"] = sum(int(h.get("NONFRAME", 0)) for h in prim)
            out["reach_pixel_fraction"] = _num(np.mean([float(h.get("FPIXRCH", math.nan)) for h in prim]))
            if "n_ge" in out and out["catalogue"]:
                out["frac_ge_catalogue"] = {k: v / out["catalogue"] for k, v in out["n_ge"].items()}
    regions = os.path.join(study_dir, prefix, "regions.fits")
    if os.path.exists(regions):
        h = _header(regions, "REGIONS")
        # the whole catalogue as denominator: every galaxy on a final
        out["catalogue"] = int(h["NGALON"])
        out["reach_pixel_fraction"] = _num(h.get("FPIXRCH", math.nan))
        if "n_ge" in out and out["catalogue"]:
            out["frac_ge_catalogue"] = {k: v / out["catalogue"] for k, v in out["n_ge"].items()}
    theta = _table(xi_path, "THETA_DE")
    if theta and "de_lo" in theta:
        # one row per angle bin and |De| bin: the test against uniform, once per |De| bin
        bins = []
        for k in range(len(theta["de_lo"])):
            key = (float(theta["de_lo"][k]), float(theta["de_hi"][k]))
            if bins and (bins[-1]["de_lo"], bins[-1]["de_hi"]) == key:
                continue
            row = {"de_lo": key[0], "de_hi": key[1]}
            for col in ("n_eff", "chi2_uniform", "dof_uniform", "p_uniform"):
                if col in theta:
                    row[col] = _num(theta[col][k])
            bins.append(row)
        out["theta_uniformity"] = bins
    b_path = os.path.join(study_dir, prefix, "budget", f"{name}.fits")
    if os.path.exists(b_path):
        h = _header(b_path, "BUDGET")
        out["budget_verdict"] = str(h.get("VERDICT", ""))
        if "BUDWORST" in h:
            # min over bins of log10(|budget| / |xi+|): how many orders below the budget
            out["orders_below_budget_min"] = _num(h["BUDWORST"])
        table = _table(b_path, "BUDGET")
        ratio = table.get("ratio")
        if ratio is not None:
            r = np.abs(np.asarray(ratio, dtype=float))
            r = r[np.isfinite(r)]
            if r.size:
                out["xi_over_budget_median"] = _num(np.median(r))
                out["xi_over_budget_max"] = _num(r.max())
        if "theta" in table:
            supported = table.get("supported", np.ones(len(table["theta"]), dtype=bool))
            out["xi_bins"] = [{"theta": _num(t), "xip": _num(x), "sigma_xip": _num(e), "budget": _num(b),
                               "supported": bool(ok)}
                              for t, x, e, b, ok in zip(table["theta"], table["xip"], table["sigma_xip"],
                                                        table["xip_budget"], supported)]
        if "BUDPATCH" in h:
            out["patch_size"] = _num(h["BUDPATCH"])
    return out


def linear_response_check(tables) -> dict:
    """How De from the reference's minimum compares with De from fits from the start (``measure.check``).

    Per changed galaxy: |De - De_cold| against max(1e-3 |De_cold|, 1e-10),
    and whether the two agree on |De| >= 1e-8 and >= 1e-4.  Empty without the
    check's columns.
    """
    rows = [t for t in tables if t and "de1_cold" in t]
    if not rows:
        return {}
    de = np.concatenate([np.stack([t["de1"], t["de2"]], axis=1) for t in rows])
    cold = np.concatenate([np.stack([t["de1_cold"], t["de2_cold"]], axis=1) for t in rows])
    method = np.concatenate([t["method"] for t in rows])
    checked = np.all(np.isfinite(cold), axis=1) & (method > 0)
    de, cold = de[checked], cold[checked]
    if not len(de):
        return {"checked": 0}
    err = np.max(np.abs(de - cold), axis=1)
    tol = np.maximum(1e-3 * np.max(np.abs(cold), axis=1), 1e-10)
    a, b = np.hypot(de[:, 0], de[:, 1]), np.hypot(cold[:, 0], cold[:, 1])
    return {"checked": int(len(de)), "within": int(np.count_nonzero(err <= tol)),
            "worst_over_tolerance": _num(np.max(err / tol)),
            "decisions_differ_1e-08": int(np.count_nonzero((a >= 1e-8) != (b >= 1e-8))),
            "decisions_differ_1e-04": int(np.count_nonzero((a >= 1e-4) != (b >= 1e-4))),
            "changed_1e-08": int(np.count_nonzero(b >= 1e-8))}


#: realisations whose scatter gives xi+ an error at every separation (without a jackknife's patch limit)
MIN_REALISATIONS = 3


def combine_realisations(per: list) -> dict:
    """One variant over several realisations: means, their scatter, and xi+ per separation against the budget.

    Parameters
    ----------
    per : list of dict
        :func:`variant_results` of each realisation.

    Returns
    -------
    dict
        ``realisations``; for each fraction and mean, ``mean``, ``scatter``
        (standard deviation across realisations) and ``error`` (of the mean:
        scatter / sqrt(N)) beside the mean of the per-realisation (jackknife,
        standard) errors; ``xi``: per separation bin the mean xi+, its
        realisation scatter, the mean jackknife sigma, the budget, the error
        used (for the mean of N realisations: the larger of the scatter and
        the jackknife where the jackknife's patches are at least the
        separation, the scatter alone beyond them when there are at least
        :data:`MIN_REALISATIONS`) and a verdict
        (:func:`perscli.stats.budget.bin_verdicts`): 'below' when
        |xi+| + 2 error < |budget|, 'above' when |xi+| - 2 error > |budget|,
        'cannot tell' otherwise or where no error holds.
    """
    n = len(per)
    out = {"variant": per[0]["variant"], "realisations": n}

    def stat(values, within=None):
        v = np.array([x for x in values if x is not None], dtype=float)
        if not v.size:
            return None
        d = {"mean": float(v.mean()), "scatter": float(v.std(ddof=1)) if v.size > 1 else None}
        d["error"] = d["scatter"] / math.sqrt(v.size) if d["scatter"] is not None else None
        w = np.array([x for x in (within or []) if x is not None], dtype=float)
        if w.size:
            d["within"] = float(np.sqrt(np.mean(w ** 2)) / math.sqrt(w.size))
        return d

    for key in ("frac_ge", "frac_dabs_ge", "frac_ge_catalogue"):
        thresholds = sorted({t for r in per for t in (r.get(key) or {})}, key=float)
        if thresholds:
            out[key] = {t: stat([(r.get(key) or {}).get(t) for r in per]) for t in thresholds}
    out["flagged_fraction"] = stat([r.get("flagged_fraction") for r in per])
    for key in ("n", "sample", "fitted", "catalogue"):
        values = [r.get(key) for r in per if r.get(key) is not None]
        if values:
            out[key] = int(sum(values))
    if out.get("sample"):
        out["measured_fraction"] = out.get("fitted", 0) / out["sample"]
    for key in ("de1", "de2"):
        out[f"{key}_mean"] = stat([r.get(f"{key}_mean") for r in per], [r.get(f"{key}_err") for r in per])

    bins = [r.get("xi_bins") or [] for r in per]
    nb = min((len(b) for b in bins), default=0)
    xi = []
    for k in range(nb):
        xs = np.array([b[k]["xip"] for b in bins], dtype=float)
        sj = np.array([b[k]["sigma_xip"] for b in bins], dtype=float)
        budget = bins[0][k]["budget"]
        mean = float(np.nanmean(xs))
        scatter = float(np.nanstd(xs, ddof=1)) if n > 1 else math.nan
        jack = float(np.sqrt(np.nanmean(sj ** 2)))
        # the jackknife's error holds where its patches are at least the separation; the scatter of
        # MIN_REALISATIONS or more realisations holds everywhere
        jack_ok = all(b[k].get("supported", True) for b in bins)
        spread_ok = n >= MIN_REALISATIONS and math.isfinite(scatter)
        candidates = ([jack] if jack_ok else []) + ([scatter] if spread_ok or (jack_ok and math.isfinite(scatter))
                                                     else [])
        candidates = [c for c in candidates if math.isfinite(c)]
        supported = bool(candidates)
        error = max(candidates) / math.sqrt(n) if candidates else math.nan
        verdict = str(bin_verdicts([mean], [error], [budget], 2.0, [supported])[0])
        bound = abs(mean) + 2 * error
        xi.append({"theta": bins[0][k]["theta"], "xip": mean, "scatter": _num(scatter), "sigma_jackknife": jack,
                   "error": _num(error), "budget": budget, "verdict": verdict, "supported": supported,
                   "orders_below_at_2sigma": _num(math.log10(abs(budget) / bound))
                   if supported and bound > 0 and budget != 0 else None})
    out["xi"] = xi
    return out


def _products(pattern: str, name: str) -> list:
    """The files matching ``pattern`` whose name is exactly ``name`` (a regex): products, not what a killed
    task left beside them."""
    return sorted(p for p in glob.glob(pattern) if re.fullmatch(name, os.path.basename(p)))


def write_summary(study_dir: str, params: dict, out: str) -> None:
    """summary.json, summary.md, the paper's Figs. 1-2 and cost.json (atomically each)."""
    reals = params.get("realisations") or [{"seed": None, "prefix": ""}]
    per_real = [[variant_results(study_dir, name, r["prefix"], bool(params.get("differential")))
                 for name in params["variants"]] for r in reals]
    results = per_real[0] if len(reals) == 1 else [combine_realisations([p[k] for p in per_real])
                                                   for k in range(len(params["variants"]))]
    combined = [combine_realisations([p[k] for p in per_real]) for k in range(len(params["variants"]))]
    summary = {"study": params["name"], "finals": params["finals"], "paper": PAPER, "results": results,
               "combined": combined, "realisations": [r["seed"] for r in reals],
               "differential": bool(params.get("differential")), "joint": params.get("joint"),
               "field": params.get("field", {})}
    if len(reals) > 1:
        summary["per_realisation"] = {str(r["seed"]): p for r, p in zip(reals, per_real)}
    _write_text(out, json.dumps(summary, indent=1, sort_keys=True) + "\n")
    _write_text(os.path.join(study_dir, "summary.md"), markdown(summary))
    figs = os.path.join(study_dir, "figures")
    os.makedirs(figs, exist_ok=True)

    for fname, make in (("ghosts_by_magnitude.png", ghost_stamps), ("galaxy_beside_ghost.png", galaxy_beside_ghost)):
        path = os.path.join(figs, fname)
        if not os.path.exists(path):
            _write_bytes(path, make())
    if any(r.get("xi") for r in combined):
        _write_bytes(os.path.join(figs, "xi_against_budget.png"), xi_against_budget(combined, len(reals)))
    _write_text(os.path.join(study_dir, "cost.json"), json.dumps(cost(study_dir), indent=1, sort_keys=True) + "\n")


def markdown(summary: dict) -> str:
    """The comparison with the paper as Markdown: fractions, means and xi+ per separation with their errors."""
    reals = summary.get("realisations") or [None]
    nreal = len(reals)
    lines = [f"# Study {summary['study']}: persistence and galaxy shapes", "",
             f"{len(summary['finals'])} final SCA-exposures"
             + (f", {nreal} realisations (seeds {', '.join(map(str, reals))})" if nreal > 1 else "")
             + ".  The paper: Lin et al., 0.9M galaxies on 6.25 deg^2.", ""]
    joint = summary.get("joint")
    lines += [f"The sample: the galaxies within {_g(summary.get('field', {}).get('radius'))} deg of the field's "
              "centre that measure fits (predicted S/N above its cut), "
              + ("each once, its shape fitted jointly over every final it falls on (the paper's pipeline); "
                 if joint else "each once per final it falls on (one shape per galaxy and exposure); ")
              + "a fit's flag is kept (its share: 'flagged'), as the paper's pipeline kept them.", ""]
    if summary.get("differential"):
        lines += ["Differential: each final simulated only on the windows of the sample's galaxies; a galaxy "
                  "whose stamps no variant changed has De = 0 exactly and is counted without a fit; a changed "
                  "galaxy is fitted on the reference and each variant from the reference's minimum (the fit's "
                  "linear response to the pixel change, checked by a Newton step: the same De as two fits from "
                  "the start, to 1e-3 of itself).", ""]
    # absolute values written with \| so that a Markdown table keeps its columns
    lines += ["| variant | galaxies | measured | flagged | \\|De\\| >= 1e-8 | \\|De\\| >= 1e-4 | "
              "\\|D\\|e\\|\\| >= 1e-8 | \\|D\\|e\\|\\| >= 1e-4 | \\|De\\| >= 1e-8 of catalogue | <De1> | <De2> |",
              "|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|",
              f"| paper | {PAPER['galaxies']:,} | | | ~1% | ~0.5% | ~1% | ~0.5% | | {PAPER['de1_mean']:.1e} | "
              f"{PAPER['de2_mean']:.1e} |"]
    for r in summary["combined"]:
        f, a, c = r.get("frac_ge", {}), r.get("frac_dabs_ge", {}), r.get("frac_ge_catalogue", {})
        measured = r.get("measured_fraction")
        lines.append(f"| {r['variant']} | {r.get('n', 0):,} | {_pct(measured) if measured is not None else 'all'} | "
                     f"{_pct_pm(r.get('flagged_fraction'))} | "
                     f"{_pct_pm(f.get('1e-08'))} | {_pct_pm(f.get('1e-04'))} | {_pct_pm(a.get('1e-08'))} | "
                     f"{_pct_pm(a.get('1e-04'))} | {_pct_pm(c.get('1e-08'))} | {_mean_pm(r.get('de1_mean'))} | "
                     f"{_mean_pm(r.get('de2_mean'))} |")
    lines += ["", "Errors: " + ("the scatter across realisations over sqrt(N)." if nreal > 1 else
                                "the standard error of the mean (one realisation: no scatter across "
                                "realisations; fractions without errors)."), ""]
    lines += ["xi+ of De against the additive budget per separation (mean over realisations; error, for the "
              "mean: the larger of the realisation scatter and the jackknife where the jackknife's patches are at "
              f"least the separation, the scatter alone beyond them with {MIN_REALISATIONS} or more realisations; "
              "verdict at 2 sigma on |xi+|: below when |xi+| + 2 sigma < |budget|, above when |xi+| - 2 sigma > "
              "|budget|, cannot tell otherwise or where no error holds):", ""]
    for r in summary["combined"]:
        lines += [f"**{r['variant']}**", "", "| theta (arcmin) | xi+ | scatter | jackknife | budget | verdict | "
                  "orders below (2 sigma) |", "|---:|---:|---:|---:|---:|---|---:|"]
        for b in r.get("xi", []):
            lines.append(f"| {b['theta']:.3g} | {b['xip']:.2e} | {_e(b.get('scatter'))} | {_e(b['sigma_jackknife'])} | "
                         f"{_e(b['budget'])} | {b['verdict']} | {_g(b.get('orders_below_at_2sigma'))} |")
        told = [b for b in r.get("xi", []) if b["verdict"] != "cannot tell"]
        below = [b for b in told if b["verdict"] == "below"]
        where = ", ".join(f"{b['theta']:.3g}" for b in told)
        lines += ["", f"The data tell xi+ from the budget at {len(told)} of {len(r.get('xi', []))} separations "
                      f"({len(below)} below it)" + (f": {where} arcmin" if told else "") + ".", ""]
    lines += ["Position angle of De against uniform (p-values per |De| bin, first realisation):", ""]
    for r in summary["results"] if nreal == 1 else summary["per_realisation"][str(reals[0])]:
        bins = r.get("theta_uniformity") or []
        text = ", ".join(f"[{b['de_lo']:.0e}, {b['de_hi']:.0e}): "
                         + (f"p = {_g(b.get('p_uniform'))}" if b.get("n_eff") else "no objects") for b in bins)
        lines.append(f"- {r['variant']}: {text or 'n/a'}")
    lines += ["", "In frames rounded to whole DN, |De| >= 1e-8 means in effect that at least one pixel of the "
              "galaxy's stamp changed by one DN.", ""]
    return "\n".join(lines)


def _e(v):
    return "n/a" if v is None else f"{v:.1e}"


def _pct_pm(d):
    if not d:
        return "n/a"
    text = _pct(d["mean"])
    err = d.get("error") if d.get("error") is not None else None
    return text + (f" +- {100 * err:.2f}" if err is not None else "")


def _mean_pm(d):
    if not d:
        return "n/a"
    err = d.get("error") if d.get("error") is not None else d.get("within")
    return f"{d['mean']:.2g}" + (f" +- {err:.1g}" if err is not None else "")


def _pct(v):
    return "n/a" if v is None else f"{100 * v:.2f}%"


def _g(v):
    return "n/a" if v is None else f"{v:.2g}"


def cost(study_dir: str) -> dict:
    """CPU seconds and bytes per kind of product, measured from this run's task records."""
    per = {}
    for path in sorted(glob.glob(os.path.join(study_dir, STATE, "*.json"))):
        with open(path) as fh:
            rec = json.load(fh)
        kind = _cost_kind(rec["kind"], rec["key"], rec.get("hdus", []))
        d = per.setdefault(kind, {"tasks": 0, "cpu_s": 0.0, "bytes": 0, "galaxies": 0})
        d["tasks"] += 1
        d["cpu_s"] += rec.get("cpu_s", 0.0)
        d["bytes"] += rec.get("bytes", 0)
        d["galaxies"] += rec.get("galaxies", 0)
        d["frames"] = d.get("frames", 0) + rec.get("frames", 0)
        if "draws" in rec:
            d["draws"] = d.get("draws", 0) + rec["draws"]
    for d in per.values():
        d["cpu_s_per_task"] = d["cpu_s"] / d["tasks"] if d["tasks"] else None
        d["bytes_per_task"] = d["bytes"] / d["tasks"] if d["tasks"] else None
        if d["galaxies"]:
            d["cpu_s_per_galaxy"] = d["cpu_s"] / d["galaxies"]
    return per


def _cost_kind(kind: str, key: str, hdus) -> str:
    # renders differ by what they write: an earlier exposure's stars only, a history frame only its
    # fluence, a final's reference also SCI, a final with persistence SCI alone
    if kind != "render":
        return kind
    if "stars/" in key:
        return "render_stars"
    if "/ref/" not in key:
        return "render_persist"
    return "render_ref_final" if "SCI" in hdus else "render_ref_history"


def _write_text(path: str, text: str) -> None:
    _write_bytes(path, text.encode())


def _write_bytes(path: str, data: bytes) -> None:
    tmp = f"{path}.{os.getpid()}.part"
    with open(tmp, "wb") as fh:
        fh.write(data)
    os.replace(tmp, path)


def load_cost(path: str) -> dict:
    """Read and check a study's cost.json (what :func:`cost` wrote) for :func:`project_cost`.

    Raises
    ------
    PerscliError
        The file is not JSON, or not a cost.json: an object of kinds of
        product, each with non-negative numbers ``tasks``, ``cpu_s`` and
        ``bytes``.
    """
    try:
        with open(path, encoding="utf-8") as fh:
            data = json.load(fh)
    except OSError as exc:
        raise PerscliError(f"{path}: cannot read ({exc.strerror or exc}); give the cost.json a study wrote") from None
    except (UnicodeDecodeError, json.JSONDecodeError) as exc:
        where = f" at line {exc.lineno} column {exc.colno}" if isinstance(exc, json.JSONDecodeError) else ""
        raise PerscliError(f"{path}: not JSON{where}; give the cost.json a finished study wrote") from None
    if not isinstance(data, dict) or not data:
        raise PerscliError(f"{path}: not a study's cost.json (expected an object of product kinds); give the "
                           "cost.json a finished study wrote")
    for kind, d in data.items():
        ok = isinstance(d, dict) and all(
            isinstance(d.get(k), (int, float)) and not isinstance(d.get(k), bool) and math.isfinite(d[k])
            and d[k] >= 0 for k in ("tasks", "cpu_s", "bytes"))
        if not ok or d["tasks"] == 0:
            raise PerscliError(f"{path}: entry {kind!r} lacks non-negative tasks, cpu_s and bytes; give the "
                               "cost.json a finished study wrote")
    return data


#: kinds of task whose cost goes as the frames or tables they read
SCALED_KINDS = ("measure", "changes", "regions", "correlate")


def final_draws(params: dict) -> set:
    """The SCA-exposures a final task draws: its finals and their earlier exposures, each once."""
    finals = params.get("finals") or [params]
    return {int(f["pointing"]["expid"] if "pointing" in f else f["expid"]) for f in finals} | \
        {int(q["expid"]) for f in finals for q in f.get("history", [])}


def project_cost(tasks, measured: dict) -> dict:
    """The cost of a task graph from the per-product costs another run measured (its cost.json).

    Renders cost what they cost per task (one SCA-exposure each); a chunk of
    finals goes as the SCA-exposures it draws (:func:`final_draws`); measure,
    regions and correlate tasks are scaled by the number of frames or tables
    they read, since their cost is per galaxy and galaxies per frame do not
    depend on the study's size.

    Returns
    -------
    dict
        cpu_hours, terabytes, the per-kind figures used, and ``missing``: the
        kinds of task the measured run had none of (not in the totals).
    """
    need = {}
    for t in tasks:
        kind = _cost_kind(t["kind"], t["key"], t["params"].get("hdus", []))
        scaled = kind in SCALED_KINDS
        if kind == "final":
            # a chunk of finals draws each of its SCA-exposures once: its cost goes as those
            units = len(final_draws(t["params"]))
        elif scaled:
            units = len(t["params"].get("frames", t["params"].get("finals", t["params"].get("tables", []))))
        else:
            units = 1
        need[kind] = need.get(kind, 0) + max(1, units)
    cpu = bytes_ = 0.0
    per, missing = {}, []
    for kind, n in need.items():
        m = measured.get(kind)
        if not m:
            missing.append(kind)
            continue
        if kind == "final" and m.get("draws"):
            units = m["draws"]
        elif kind in SCALED_KINDS:
            units = max(1, m.get("frames", m["tasks"]))
        else:
            units = m["tasks"]
        c, b = m["cpu_s"] / units, m["bytes"] / units
        per[kind] = {"units": n, "cpu_s_each": c, "bytes_each": b}
        cpu += n * c
        bytes_ += n * b
    return {"cpu_hours": cpu / 3600.0, "terabytes": bytes_ / 1e12, "per_kind": per, "missing": sorted(missing)}
