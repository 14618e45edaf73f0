"""What each task of a study does: read its inputs' paths, write its product.

Every function here runs in whatever process the scheduler chooses (a Dask
worker, or the command's own): it takes the study folder and the task's
JSON-able parameters, calls the library function behind the matching
command, and returns a record of what it made (bytes, CPU seconds).  Nothing
is passed between tasks but file names.
"""

from __future__ import annotations

import json
import os
import resource
import time

from .. import PerscliError

STATE = ".state"


def record_path(study_dir: str, key: str) -> str:
    return os.path.join(study_dir, STATE, key.replace("/", "__") + ".json")


def read_record(study_dir: str, key: str) -> dict | None:
    try:
        with open(record_path(study_dir, key)) as fh:
            return json.load(fh)
    except (OSError, ValueError):
        return None


def is_done(study_dir: str, task: dict) -> bool:
    """A product counts as made when its record matches the task and the product exists.

    Products are written atomically, so an existing one is complete; the
    record's fingerprint (the task's settings and its inputs' fingerprints)
    says it was made from what the study now asks for.
    """
    rec = read_record(study_dir, task["key"])
    return (rec is not None and rec.get("fingerprint") == task["fingerprint"]
            and os.path.exists(os.path.join(study_dir, task["output"])))


def _cpu() -> float:
    me = resource.getrusage(resource.RUSAGE_SELF)
    kids = resource.getrusage(resource.RUSAGE_CHILDREN)
    return me.ru_utime + me.ru_stime + kids.ru_utime + kids.ru_stime


def run_task(task: dict, study_dir: str, *_deps) -> dict:
    """Make one product (unless it is already made) and return its record.

    Parameters
    ----------
    task : dict
        A :class:`perscli.study.plan.Task` as a dict, with its ``fingerprint``.
    study_dir : str
    *_deps
        The records of the tasks it depends on (only there so that a
        scheduler runs it after them).

    Returns
    -------
    dict
        key, output, fingerprint, bytes, cpu_s, wall_s, skipped.
    """
    if is_done(study_dir, task):
        rec = read_record(study_dir, task["key"])
        rec["skipped"] = True
        return rec
    t0, c0 = time.perf_counter(), _cpu()
    out = os.path.join(study_dir, task["output"])
    os.makedirs(os.path.dirname(out) or ".", exist_ok=True)
    extra = RUNNERS[task["kind"]](study_dir, task["params"], out) or {}
    rec = dict(key=task["key"], kind=task["kind"], output=task["output"], fingerprint=task["fingerprint"],
               bytes=_size(out), cpu_s=round(_cpu() - c0, 3), wall_s=round(time.perf_counter() - t0, 3),
               skipped=False, **extra)
    path = record_path(study_dir, task["key"])
    os.makedirs(os.path.dirname(path), exist_ok=True)
    tmp = path + f".{os.getpid()}.part"
    with open(tmp, "w") as fh:
        json.dump(rec, fh, sort_keys=True)
    os.replace(tmp, path)
    return rec


def _size(path: str) -> int:
    if os.path.isdir(path):
        return sum(os.path.getsize(os.path.join(d, f)) for d, _, fs in os.walk(path) for f in fs)
    return os.path.getsize(path) if os.path.exists(path) else 0


# --------------------------------------------------------------------------------------------
# one function per kind
# --------------------------------------------------------------------------------------------

def _pointings(study_dir, p, out):
    from ..scene.pointings import Pointing, write_pointings

    rows = [Pointing(**{k: v for k, v in r.items() if k != "role"}) for r in p["rows"]]
    write_pointings(rows, out, overwrite=True, step="study: every SCA-exposure rendered",
                    params={"NFINAL": (sum(r["role"] == "final" for r in p["rows"]), "final exposures")})
    return {"n": len(rows)}


def _catalog(study_dir, p, out):
    from ..scene.catalog import make_truth_catalog_file

    c = p["catalog"]
    # the footprints of every row of the study's pointings table, each on its own SCA: the same
    # call as `perscli catalog --footprints pointings.fits --bounds ... --margin ...`
    table = make_truth_catalog_file(out, footprints=os.path.join(study_dir, "pointings.fits"), sca=0,
                                    bounds=p["bounds"], margin_arcsec=c["margin_arcsec"], overwrite=True,
                                    galaxy_density=c["galaxy_density"], star_density=c["star_density"],
                                    gaia=c["gaia"] or None, seed=p["seed"])
    return {"n": len(table)}


def _render(study_dir, p, out):
    from ..detector.effects import load_detector_model
    from ..render.exposure import Exposure
    from ..render.run import render_file

    pt = p["pointing"]
    exposure = Exposure(ra=pt["ra"], dec=pt["dec"], pa=pt["pa"], sca=p["sca"], filter=pt["filter"],
                        mjd=pt["mjd"], exptime=pt["exptime"],
                        bounds=tuple(p["bounds"]) if p["bounds"] else None, expid=pt["expid"])
    model = load_detector_model("roman", [*p["model"], *p["set"]])
    previous = [os.path.join(study_dir, q) for q in p["previous"]]
    summary = render_file(os.path.join(study_dir, "truth.fits"), exposure, out, model=model, seed=p["seed"],
                          previous=previous, overwrite=True, compress=p["compress"],
                          persistence_source=p["source"], hdus=tuple(p["hdus"]))
    return {"objects": int(summary.get("drawn", summary.get("objects", 0)) or 0), "hdus": list(p["hdus"])}


def _measure(study_dir, p, out):
    from ..measure.shapes import measure_files

    frames = [os.path.join(study_dir, f) for f in p["frames"]]
    kw = dict(stamp=p["stamp"], joint=p["joint"])
    if p["min_snr"] is not None:
        kw["min_snr"] = p["min_snr"]
    summary = measure_files(frames, os.path.join(study_dir, "truth.fits"), out, overwrite=True, **kw)
    return {"galaxies": int(summary.get("rows", 0)), "usable": int(summary.get("unflagged", 0)),
            "frames": len(frames)}


def _correlate(study_dir, p, out):
    from ..stats.correlate import correlate_files

    pairs = [(os.path.join(study_dir, a), os.path.join(study_dir, b)) for a, b in p["pairs"]]
    figures = os.path.join(study_dir, p["figures"])
    os.makedirs(figures, exist_ok=True)
    correlate_files([], out, pairs=pairs, min_sep=p["min_sep"], max_sep=p["max_sep"], nbins=p["nbins"],
                    npatch=p["npatch"], thresholds=tuple(p["thresholds"]), seed=p["seed"],
                    plots_dir=figures, overwrite=True)


def _budget(study_dir, p, out):
    from ..stats.budget import budget_file

    plot = os.path.join(study_dir, p["plot"])
    os.makedirs(os.path.dirname(plot), exist_ok=True)
    budget_file(out, os.path.join(study_dir, p["xi"]), bands=p["bands"], modes=p["modes"], plot=plot,
                overwrite=True)


def _summary(study_dir, p, out):
    from .summary import write_summary

    write_summary(study_dir, p, out)


RUNNERS = dict(pointings=_pointings, catalog=_catalog, render=_render, measure=_measure, correlate=_correlate,
               budget=_budget, summary=_summary)


def check_kind(kind: str) -> None:
    if kind not in RUNNERS:
        raise PerscliError(f"unknown task kind {kind!r}")
