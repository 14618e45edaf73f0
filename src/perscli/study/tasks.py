"""What each task of a study does: read its inputs' paths, write its product.

Every function here runs in whatever process the scheduler chooses (a Dask
worker, or the command's own): it takes the study folder and the task's
JSON-able parameters, calls the library function behind the matching
command, and returns a record of what it made (bytes, CPU seconds).  Nothing
is passed between tasks but file names.
"""

from __future__ import annotations

import dataclasses
import json
import os
import resource
import time

import numpy as np

from .. import PerscliError
from ..measure.settings import MeasureOptions

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
    from ..executor import keep_freed_memory

    keep_freed_memory()
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
    from ..scene.pointings import write_pointings
    from ..scene.schedule import Pointing

    rows = [Pointing(**{k: v for k, v in r.items() if k != "role"}) for r in p["rows"]]
    write_pointings(rows, out, overwrite=True, step="study: every SCA-exposure rendered",
                    params={"NFINAL": (sum(r["role"] == "final" for r in p["rows"]), "final exposures")})
    return {"n": len(rows)}


def _catalog(study_dir, p, out):
    from ..scene.catalog import make_truth_catalog_file

    from ..scene.starcounts import galactic_star_model

    c = p["catalog"]
    stars = galactic_star_model(c["star_model"]) if c["star_density"] is None and not c["gaia"] else None
    # the footprints of every row of the study's pointings table, each on its own SCA: the same
    # call as `perscli catalog --footprints pointings.fits --bounds ... --margin ...`
    table = make_truth_catalog_file(out, footprints=os.path.join(study_dir, "pointings.fits"), sca=0,
                                    bounds=p["bounds"], margin_arcsec=c["margin_arcsec"], overwrite=True,
                                    galaxy_density=c["galaxy_density"], star_density=c["star_density"],
                                    star_model=stars, gaia=c["gaia"] or None, seed=p["seed"],
                                    galaxy_rows=p.get("galaxy_rows"))
    return {"n": len(table)}


def _render(study_dir, p, out):
    from ..detector.model import load_detector_model
    from ..render.exposure import Exposure
    from ..render.run import render_file
    from ..render.settings import RenderOptions

    pt = p["pointing"]
    exposure = Exposure(ra=pt["ra"], dec=pt["dec"], pa=pt["pa"], sca=p["sca"], filter=pt["filter"],
                        mjd=pt["mjd"], exptime=pt["exptime"],
                        bounds=tuple(p["bounds"]) if p["bounds"] else None, expid=pt["expid"])
    model = load_detector_model("roman", [*p["model"], *p["set"]])
    previous = [os.path.join(study_dir, q) for q in p["previous"]]
    options = RenderOptions(hdus=tuple(p["hdus"]), compress=p["compress"], persistence_source=p["source"])
    summary = render_file(os.path.join(study_dir, p["truth"]), exposure, out, options, model=model, seed=p["seed"],
                          previous=previous, overwrite=True)
    return {"objects": int(summary.get("drawn", summary.get("objects", 0)) or 0), "hdus": list(p["hdus"])}


def _measure(study_dir, p, out):
    from ..measure.shapes import measure_files

    frames = [os.path.join(study_dir, f) for f in p["frames"]]
    options = MeasureOptions(stamp=p["stamp"], joint=p["joint"])
    if p["min_snr"] is not None:
        options = dataclasses.replace(options, min_snr=p["min_snr"])
    summary = measure_files(frames, os.path.join(study_dir, p["truth"]), out, options=options, overwrite=True)
    return {"galaxies": int(summary.get("rows", 0)), "usable": int(summary.get("unflagged", 0)),
            "frames": len(frames)}


def _exposure(p) -> "Exposure":
    from ..render.exposure import Exposure

    pt = p["pointing"] if "pointing" in p else p
    bounds = p.get("bounds")
    return Exposure(ra=pt["ra"], dec=pt["dec"], pa=pt["pa"], sca=pt["sca"] or p.get("sca"), filter=pt["filter"],
                    mjd=pt["mjd"], exptime=pt["exptime"], bounds=tuple(bounds) if bounds else None,
                    expid=pt["expid"])


def _variant_model(settings, extra):
    from ..detector.model import load_detector_model
    from ..render.run import with_persistence_source

    return with_persistence_source(load_detector_model("roman", [*settings, *extra]), "stars")


def _regions(study_dir, p, out):
    from ..render.differential import plan_regions
    from ..render.exposure import read_truth

    finals = [(_exposure(dict(f["pointing"], bounds=p["bounds"])),
               [_exposure(dict(q, bounds=p["bounds"])) for q in f["history"]]) for f in p["finals"]]
    floors = [_floor(_variant_model(m, p["set"])) for m in p["models"]]
    cols = read_truth(os.path.join(study_dir, p["truth"]), finals[0][0].filter) if finals else None
    table, counts = plan_regions(cols, finals, stamp=p["stamp"], joint=p["joint"], floor=min(floors or [0.0]))
    write_regions_table(out, table, counts)
    return {"galaxies": counts["candidates"], "frames": len(finals)}


def _floor(model) -> float:
    from ..detector.effects import Persistence

    return Persistence.floor(model)


def write_regions_table(out: str, table: dict, counts: dict) -> None:
    from ..io.fitsfile import OutHDU, table_hdu
    from ..io.output import write_hdus

    hdu = table_hdu(table, "REGIONS", descriptions={"id": "catalogue id of a galaxy whose stamps are simulated",
                                                     "sca": "detector", "expid": "final exposure"})
    for key, (value, comment) in {
        "NONFRAME": (counts["on_frames"], "galaxy-final pairs with the galaxy's stamp on the frame"),
        "NGALON": (counts["galaxies_on"], "galaxies on at least one final"),
        "NCAND": (counts["candidates"], "galaxies persistence can reach (simulated)"),
        "NREACH": (counts["reached"], "galaxy-final pairs whose stamp persistence can reach"),
        "FPIXRCH": (round(counts["pixel_fraction"], 6), "fraction of final pixels persistence can reach"),
        "FLOOR": (counts["floor"], "[e-] star light at or below this does not persist"),
    }.items():
        hdu[key] = (value, comment)
    write_hdus([OutHDU([]), hdu], out, overwrite=True)


def _final(study_dir, p, out):
    """One final (joint fits: its stamps kept for the fit over all finals), or a few fitted per exposure."""
    from ..render.differential import _truth_columns, render_final

    model = _variant_model(p["model"], p["set"])
    variants = {name: _variant_model(settings, p["set"]) for name, settings in p["variants"].items()}
    truth = os.path.join(study_dir, p["truth"])
    finals = p.get("finals") or [p]
    rows_of, reach = {}, {"on": 0, "reached": 0, "fractions": []}
    for f in finals:
        exposure = _exposure(dict(f, bounds=p["bounds"]))
        cols = _truth_columns(truth, exposure.filter)
        history = [_exposure(dict(q, bounds=p["bounds"])) for q in f["history"]]
        if p.get("regions"):
            from ..io.tables import read_table

            regions = read_table(os.path.join(study_dir, p["regions"]), what="study regions")
            here = (regions.column("sca", kind="integer") == exposure.sca) & \
                (regions.column("expid", kind="integer") == exposure.expid)
            rows = np.isin(cols["id"], regions.column("id", kind="integer")[here])
        else:
            # fitted on this final alone: the galaxies its own earlier exposures' star light reaches
            from ..render.differential import final_candidates

            rows, on, fraction = final_candidates(cols, exposure, history, stamp=p["stamp"],
                                                  floor=min(_floor(v) for v in variants.values()))
            reach["on"] += int(on.sum())
            reach["reached"] += int(rows.sum())
            reach["fractions"].append(fraction)
        rows_of[exposure.expid] = (exposure, history, rows, f["seed"])
    measure = p.get("measure")
    if measure is None:
        exposure, history, rows, seed = next(iter(rows_of.values()))
        summary = render_final(truth, exposure, out, model=model, variants=variants, seed=seed, histories=history,
                               rows=rows, stamp=p["stamp"], compress=p["compress"], overwrite=True)
        return {"galaxies": summary["rows"], "objects": summary["objects"], "blocks": summary["blocks"],
                "block_fraction": round(summary["block_fraction"], 6), "changed": summary["changed"]}
    # fitted per exposure: each final rendered to a scratch file beside the output, measured, and dropped
    from ..measure.changes import write_changes

    frames, arrays, rec = [], [], {"galaxies": 0, "objects": 0, "blocks": 0, "frames": len(rows_of)}
    try:
        for expid, (exposure, history, rows, seed) in rows_of.items():
            # NAME.PID.part: a killed run's scratch frames are removed before the next (remove_stale_parts)
            # and never match a product's name
            frame = f"{out}.e{expid:06d}.{os.getpid()}.part"
            frames.append(frame)
            arrays.append({})
            # the scratch file gives the headers; the pixels stay in memory
            summary = render_final(truth, exposure, frame, model=model, variants=variants, seed=seed,
                                   histories=history, rows=rows, stamp=p["stamp"], compress="none", overwrite=True,
                                   pixels=arrays[-1])
            for key in ("galaxies", "objects", "blocks"):
                rec[key] += summary["rows" if key == "galaxies" else key]
        header = {"NONFRAME": (reach["on"], "galaxy-final pairs with the stamp on the final"),
                  "NREACH": (reach["reached"], "of them reached by earlier star light"),
                  "FPIXRCH": (round(float(np.mean(reach["fractions"])), 6),
                              "mean fraction of the finals' pixels persistence can reach")}
        options = MeasureOptions(joint=False, stamp=measure["stamp"], min_snr=measure["min_snr"])
        counts = write_changes(frames, list(variants), truth, out, options=options, expids=list(rows_of),
                               header=header, pixels=arrays)
        rec.update(sample=counts["sample"], fitted=counts["fitted"])
        return rec
    finally:
        for frame in frames:
            if os.path.exists(frame):
                os.unlink(frame)


def _changes(study_dir, p, out):
    from ..measure.changes import write_changes

    finals = [os.path.join(study_dir, f) for f in p["finals"]]
    options = MeasureOptions(joint=p["joint"], stamp=p["stamp"], min_snr=p["min_snr"])
    summary = write_changes(finals, p["variants"], os.path.join(study_dir, p["truth"]), out, options=options,
                            expids=p["expids"], part=p["part"])
    return {"galaxies": summary["sample"], "fitted": summary["fitted"], "frames": len(finals)}


def _correlate(study_dir, p, out):
    from ..stats.correlate import CorrelateOptions, correlate_files

    figures = os.path.join(study_dir, p["figures"])
    os.makedirs(figures, exist_ok=True)
    options = CorrelateOptions(min_sep=p["min_sep"], max_sep=p["max_sep"], nbins=p["nbins"], npatch=p["npatch"],
                               thresholds=tuple(p["thresholds"]), seed=p["seed"])
    if "tables" in p:
        # the differential study's shape changes: one row per galaxy of the sample, De in columns
        summary = correlate_files([os.path.join(study_dir, t) for t in p["tables"]], out,
                                  dataclasses.replace(options, de_columns=("de1", "de2")), plots_dir=figures,
                                  overwrite=True)
        return {"frames": len(p["tables"]), "galaxies": int(summary["n"])}
    pairs = [(os.path.join(study_dir, a), os.path.join(study_dir, b)) for a, b in p["pairs"]]
    correlate_files([], out, options, pairs=pairs, plots_dir=figures, overwrite=True)


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
               budget=_budget, summary=_summary, regions=_regions, final=_final, changes=_changes)


def check_kind(kind: str) -> None:
    if kind not in RUNNERS:
        raise PerscliError(f"unknown task kind {kind!r}")
