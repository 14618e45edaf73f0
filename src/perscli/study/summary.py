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

import numpy as np

#: ../shared/NOTES.md section 7 (Lin et al., Roman HLS, 0.9M galaxies on 6.25 deg^2)
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
    import fitsio

    with fitsio.FITS(path) as f:
        if ext not in f:
            return {}
        data = f[ext].read()
    return {name.lower(): data[name] for name in data.dtype.names}


def _header(path: str, ext=0) -> dict:
    import fitsio

    with fitsio.FITS(path) as f:
        h = f[ext].read_header()
    return {k: h[k] for k in h.keys() if k not in ("COMMENT", "HISTORY", "")}


def _num(v):
    v = float(v)
    return None if not math.isfinite(v) else v


def variant_results(study_dir: str, name: str) -> dict:
    """What the study found for one persistence variant: De statistics, uniformity, budget."""
    xi_path = os.path.join(study_dir, "xi", f"{name}.fits")
    stats = _table(xi_path, "STATS")
    out = {"variant": name}
    if stats:
        row = {k: v[0] if np.ndim(v) else v for k, v in stats.items()}
        if "n" in row:
            out["n"] = int(np.asarray(row["n"]).ravel()[0])
        for key in ("de1_mean", "de1_err", "de2_mean", "de2_err", "e1_mean", "e2_mean", "de_abs_mean"):
            if key in row:
                out[key] = _num(np.asarray(row[key]).ravel()[0])
        thr = np.atleast_1d(stats.get("threshold", [[]])[0]).astype(float)
        frac = np.atleast_1d(stats.get("frac_ge", [[]])[0]).astype(float)
        nge = np.atleast_1d(stats.get("n_ge", [[]])[0]).astype(int)
        out["frac_ge"] = {f"{t:.0e}": _num(f) for t, f in zip(thr, frac)}
        out["n_ge"] = {f"{t:.0e}": int(n) for t, n in zip(thr, nge)}
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
    xi = _table(xi_path, "XI")
    b_path = os.path.join(study_dir, "budget", f"{name}.fits")
    if os.path.exists(b_path):
        h = _header(b_path, "BUDGET")
        out["budget_verdict"] = str(h.get("VERDICT", ""))
        if "BUDWORST" in h:
            # min over bins of log10(|budget| / |xi+|): how many orders below the budget
            out["orders_below_budget_min"] = _num(h["BUDWORST"])
        ratio = _table(b_path, "BUDGET").get("ratio")
        if ratio is not None:
            r = np.abs(np.asarray(ratio, dtype=float))
            r = r[np.isfinite(r)]
            if r.size:
                out["xi_over_budget_median"] = _num(np.median(r))
                out["xi_over_budget_max"] = _num(r.max())
    if xi:
        out["xi_bins"] = int(len(xi.get("xip", [])))
    return out


def write_summary(study_dir: str, params: dict, out: str) -> None:
    """summary.json, summary.md, the paper's Figs. 1-2 and cost.json (atomically each)."""
    results = [variant_results(study_dir, name) for name in params["variants"]]
    summary = {"study": params["name"], "finals": params["finals"], "paper": PAPER, "results": results}
    _write_text(out, json.dumps(summary, indent=1, sort_keys=True) + "\n")
    _write_text(os.path.join(study_dir, "summary.md"), markdown(summary))
    figs = os.path.join(study_dir, "figures")
    os.makedirs(figs, exist_ok=True)
    from .figures import galaxy_beside_ghost, ghost_stamps

    for fname, make in (("ghosts_by_magnitude.png", ghost_stamps), ("galaxy_beside_ghost.png", galaxy_beside_ghost)):
        path = os.path.join(figs, fname)
        if not os.path.exists(path):
            _write_bytes(path, make())
    _write_text(os.path.join(study_dir, "cost.json"), json.dumps(cost(study_dir), indent=1, sort_keys=True) + "\n")


def markdown(summary: dict) -> str:
    """The comparison with the paper as a Markdown table."""
    lines = [f"# Study {summary['study']}: persistence and galaxy shapes", "",
             f"{len(summary['finals'])} final SCA-exposures.  The paper: Lin et al., 0.9M galaxies on 6.25 deg^2.", "",
             "| variant | galaxies | |De| >= 1e-8 | |De| >= 1e-4 | <De1> | <De2> | xi+ / budget (median) |",
             "|---|---:|---:|---:|---:|---:|---:|",
             f"| paper | {PAPER['galaxies']:,} | ~1% | ~0.5% | {PAPER['de1_mean']:.1e} | {PAPER['de2_mean']:.1e} | "
             "1e-2 (two orders below) |"]
    for r in summary["results"]:
        f = r.get("frac_ge", {})
        lines.append(f"| {r['variant']} | {r.get('n', 0):,} | {_pct(f.get('1e-08'))} | {_pct(f.get('1e-04'))} | "
                     f"{_pm(r, 'de1')} | {_pm(r, 'de2')} | {_g(r.get('xi_over_budget_median'))} |")
    lines += ["", "Position angle of De against uniform (p-values per |De| bin, the test's variance under "
              "uniform angles):", ""]
    for r in summary["results"]:
        bins = r.get("theta_uniformity") or []
        text = ", ".join(f"[{b['de_lo']:.0e}, {b['de_hi']:.0e}): "
                         + (f"p = {_g(b.get('p_uniform'))}" if b.get("n_eff") else "no objects") for b in bins)
        lines.append(f"- {r['variant']}: {text or 'n/a'}")
    lines += ["", "Budget verdicts:", ""]
    lines += [f"- {r['variant']}: {r.get('budget_verdict', 'n/a')}" for r in summary["results"]]
    lines += ["", "In frames rounded to whole DN, |De| >= 1e-8 means in effect that at least one pixel of the "
              "galaxy's stamp changed by one DN.", ""]
    return "\n".join(lines)


def _pct(v):
    return "n/a" if v is None else f"{100 * v:.2f}%"


def _g(v):
    return "n/a" if v is None else f"{v:.2g}"


def _pm(r, key):
    m, e = r.get(f"{key}_mean"), r.get(f"{key}_err")
    if m is None:
        return "n/a"
    return f"{m:.2g} +- {e:.1g}" if e is not None else f"{m:.2g}"


def cost(study_dir: str) -> dict:
    """CPU seconds and bytes per kind of product, measured from this run's task records."""
    from .tasks import STATE

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
    for d in per.values():
        d["cpu_s_per_task"] = d["cpu_s"] / d["tasks"] if d["tasks"] else None
        d["bytes_per_task"] = d["bytes"] / d["tasks"] if d["tasks"] else None
        if d["galaxies"]:
            d["cpu_s_per_galaxy"] = d["cpu_s"] / d["galaxies"]
    return per


def _cost_kind(kind: str, key: str, hdus) -> str:
    # renders differ by what they write: a history frame only its fluence, a final's reference
    # also SCI, a final with persistence SCI alone
    if kind != "render":
        return kind
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


def project(tasks, measured: dict) -> dict:
    """The cost of a task graph from the per-product costs another run measured (its cost.json).

    Renders cost what they cost per task (one SCA-exposure each); measure
    tasks are scaled by the number of frames they read, since their cost is
    per galaxy and galaxies per frame do not depend on the study's size.

    Returns
    -------
    dict
        cpu_hours, terabytes and the per-kind figures used.
    """
    need = {}
    for t in tasks:
        kind = _cost_kind(t["kind"], t["key"], t["params"].get("hdus", []))
        units = len(t["params"].get("frames", [])) if kind == "measure" else 1
        need[kind] = need.get(kind, 0) + max(1, units)
    cpu = bytes_ = 0.0
    per = {}
    for kind, n in need.items():
        m = measured.get(kind)
        if not m:
            continue
        units = m["tasks"] if kind != "measure" else max(1, m.get("frames", m["tasks"]))
        c, b = m["cpu_s"] / units, m["bytes"] / units
        per[kind] = {"units": n, "cpu_s_each": c, "bytes_each": b}
        cpu += n * c
        bytes_ += n * b
    return {"cpu_hours": cpu / 3600.0, "terabytes": bytes_ / 1e12, "per_kind": per}
