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
import shutil
import time

import numpy as np

from ..detector.effects import Persistence
from ..detector.model import load_detector_model
from ..executor import keep_freed_memory
from ..io.fitsfile import OutHDU, table_hdu
from ..io.output import write_hdus
from ..io.tables import read_table
from ..measure.settings import MeasureOptions
from ..measure.shapes import measure_files
from ..render.exposure import Exposure, read_truth
from ..render.run import render_file
from ..render.settings import RenderOptions
from ..scene.catalog import make_truth_catalog_file
from ..scene.pointings import write_pointings
from ..scene.schedule import Pointing
from ..scene.starcounts import galactic_star_model
from ..stats.budget import budget_file
from ..stats.correlate import correlate_files
from ..stats.settings import CorrelateOptions
from .changes import write_changes
from .differential import Region, _truth_columns, final_blocks, render_final
from .plan import STATE
from .reach import final_candidates, in_field, plan_regions
from .summary import final_draws, write_summary


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
    rows = [Pointing(**{k: v for k, v in r.items() if k != "role"}) for r in p["rows"]]
    write_pointings(rows, out, overwrite=True, step="study: every SCA-exposure rendered",
                    params={"NFINAL": (sum(r["role"] == "final" for r in p["rows"]), "final exposures")})
    return {"n": len(rows)}


def _catalog(study_dir, p, out):
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
    pt = p["pointing"]
    exposure = Exposure(ra=pt["ra"], dec=pt["dec"], pa=pt["pa"], sca=p["sca"], filter=pt["filter"],
                        mjd=pt["mjd"], exptime=pt["exptime"],
                        bounds=tuple(p["bounds"]) if p["bounds"] else None, expid=pt["expid"])
    # the settings are complete: the law, its source, the study's render.set (plan.variant_settings)
    model = load_detector_model("roman", p["model"])
    previous = [os.path.join(study_dir, q) for q in p["previous"]]
    options = RenderOptions(hdus=tuple(p["hdus"]), compress=p["compress"])
    summary = render_file(os.path.join(study_dir, p["truth"]), exposure, out, options, model=model, seed=p["seed"],
                          previous=previous, overwrite=True)
    return {"objects": int(summary.get("drawn", summary.get("objects", 0)) or 0), "hdus": list(p["hdus"])}


def _measure(study_dir, p, out):
    frames = [os.path.join(study_dir, f) for f in p["frames"]]
    options = MeasureOptions(stamp=p["stamp"], joint=p["joint"])
    if p["min_snr"] is not None:
        options = dataclasses.replace(options, min_snr=p["min_snr"])
    summary = measure_files(frames, os.path.join(study_dir, p["truth"]), out, options=options, overwrite=True)
    return {"galaxies": int(summary.get("rows", 0)), "usable": int(summary.get("unflagged", 0)),
            "frames": len(frames)}


def _exposure(p):
    pt = p["pointing"] if "pointing" in p else p
    bounds = p.get("bounds")
    return Exposure(ra=pt["ra"], dec=pt["dec"], pa=pt["pa"], sca=pt["sca"] or p.get("sca"), filter=pt["filter"],
                    mjd=pt["mjd"], exptime=pt["exptime"], bounds=tuple(bounds) if bounds else None,
                    expid=pt["expid"])


def _detector(settings):
    return load_detector_model("roman", list(settings))


def _regions(study_dir, p, out):
    finals = [(_exposure(dict(f["pointing"], bounds=p["bounds"])),
               [_exposure(dict(q, bounds=p["bounds"])) for q in f["history"]]) for f in p["finals"]]
    floors = [_floor(_detector(m)) for m in p["models"]]
    cols = read_truth(os.path.join(study_dir, p["truth"]), finals[0][0].filter) if finals else None
    sample = in_field(cols, p["field"]) if cols is not None else None
    table, counts = plan_regions(cols, finals, stamp=p["stamp"], joint=p["joint"], sources=p["sources"],
                                 floor=min(floors or [0.0]), sample=sample)
    write_regions_table(out, table, counts)
    return {"galaxies": counts["candidates"], "frames": len(finals)}


def _floor(model) -> float:
    return Persistence.floor(model)


def write_regions_table(out: str, table: dict, counts: dict) -> None:
    hdu = table_hdu(table, "REGIONS", descriptions={"id": "catalogue id of a galaxy whose stamps are simulated",
                                                     "sca": "detector", "expid": "final exposure"})
    for key, (value, comment) in {
        "NONFRAME": (counts["on_frames"], "galaxy-final pairs of the sample with the stamp on the frame"),
        "NGALON": (counts["galaxies_on"], "galaxies of the sample on at least one final"),
        "NCAND": (counts["candidates"], "galaxies persistence can reach (simulated)"),
        "NREACH": (counts["reached"], "galaxy-final pairs whose stamp persistence can reach"),
        **({"FPIXRCH": (round(counts["pixel_fraction"], 6), "fraction of final pixels persistence can reach")}
           if np.isfinite(counts["pixel_fraction"]) else {}),
        "FLOOR": (counts["floor"], "[e-] light at or below this does not persist"),
    }.items():
        hdu[key] = (value, comment)
    write_hdus([OutHDU([]), hdu], out, overwrite=True)


def _final(study_dir, p, out):
    """A few consecutive finals of one SCA: with joint fits their stamps kept (one file each in ``out``, a
    folder) for the fit over all finals; without, fitted per exposure and only the shape changes kept."""
    model = _detector(p["model"])
    variants = {name: _detector(settings) for name, settings in p["variants"].items()}
    truth = os.path.join(study_dir, p["truth"])
    sources = sorted({_source(v) for v in variants.values()})
    floor = min(_floor(v) for v in variants.values())
    rows_of, reach = {}, {"on": 0, "reached": 0, "fractions": []}
    regions = None
    if p.get("regions"):
        regions = read_table(os.path.join(study_dir, p["regions"]), what="study regions")
    for f in p["finals"]:
        exposure = _exposure(dict(f, bounds=p["bounds"]))
        cols = _truth_columns(truth, exposure.filter)
        history = [_exposure(dict(q, bounds=p["bounds"])) for q in f["history"]]
        if regions is not None:
            here = (regions.column("sca", kind="integer") == exposure.sca) & \
                (regions.column("expid", kind="integer") == exposure.expid)
            rows = np.isin(cols["id"], regions.column("id", kind="integer")[here])
        else:
            # fitted on this final alone: the galaxies of the sample its own earlier exposures' light reaches
            rows, on, fraction = final_candidates(cols, exposure, history, stamp=p["stamp"], sources=sources,
                                                  floor=floor, sample=in_field(cols, p["field"]))
            reach["on"] += int(on.sum())
            reach["reached"] += int(rows.sum())
            reach["fractions"].append(fraction)
        rows_of[exposure.expid] = (exposure, history, rows, f["seed"])
    # where the task's finals need light: the union of their simulated blocks (an earlier exposure is drawn
    # there only); the finals that are earlier exposures of later ones keep their drawn light
    region = None
    for exposure, _, rows, _ in rows_of.values():
        area, active, _, _ = final_blocks(_truth_columns(truth, exposure.filter), exposure, rows, p["stamp"])
        region = Region(area, active.copy()) if region is None else Region(area, region.blocks | active)
    earlier = {int(q["expid"]) for f in p["finals"] for q in f["history"]}

    draws = len(final_draws(p))
    measure = p.get("measure")
    if measure is None:
        # joint fits: every final's stamps in a file of its own, in the task's folder (written whole again
        # if the task is run again: a folder without the task's record is not a product)
        if os.path.isdir(out):
            shutil.rmtree(out)
        os.makedirs(out)
        rec = {"galaxies": 0, "objects": 0, "blocks": 0, "frames": len(rows_of), "draws": draws, "changed": {}}
        for expid, (exposure, history, rows, seed) in rows_of.items():
            summary = render_final(truth, exposure, os.path.join(out, f"e{expid:06d}_final.fits"), model=model,
                                   variants=variants, seed=seed, histories=history, rows=rows, stamp=p["stamp"],
                                   compress=p["compress"], overwrite=True,
                                   keep_light="drawn" in sources and expid in earlier, region=region)
            rec["galaxies"] += summary["rows"]
            rec["objects"] += summary["objects"]
            rec["blocks"] += summary["blocks"]
            for name, n in summary["changed"].items():
                rec["changed"][name] = rec["changed"].get(name, 0) + n
        return rec
    # fitted per exposure: each final rendered to a scratch file beside the output, measured, and dropped
    frames, arrays, rec = [], [], {"galaxies": 0, "objects": 0, "blocks": 0, "frames": len(rows_of),
                                   "draws": draws}
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
                                   pixels=arrays[-1], keep_light="drawn" in sources and expid in earlier,
                                   region=region)
            for key in ("galaxies", "objects", "blocks"):
                rec[key] += summary["rows" if key == "galaxies" else key]
        header = {"NONFRAME": (reach["on"], "galaxy-final pairs of the sample with the stamp on the final"),
                  "NREACH": (reach["reached"], "of them reached by earlier light")}
        if reach["fractions"] and np.all(np.isfinite(reach["fractions"])):
            header["FPIXRCH"] = (round(float(np.mean(reach["fractions"])), 6),
                                 "mean fraction of the finals' pixels persistence can reach")
        options = MeasureOptions(joint=False, stamp=measure["stamp"], min_snr=measure["min_snr"])
        counts = write_changes(frames, list(variants), truth, out, options=options, expids=list(rows_of),
                               header=header, pixels=arrays, field=p["field"], cold=bool(measure.get("check")))
        rec.update(sample=counts["sample"], fitted=counts["fitted"])
        return rec
    finally:
        for frame in frames:
            if os.path.exists(frame):
                os.unlink(frame)


def _source(model) -> str:
    return Persistence.fluence_input(model)[0]


def _changes(study_dir, p, out):
    finals = [os.path.join(study_dir, f) for f in p["finals"]]
    options = MeasureOptions(joint=p["joint"], stamp=p["stamp"], min_snr=p["min_snr"])
    summary = write_changes(finals, p["variants"], os.path.join(study_dir, p["truth"]), out, options=options,
                            expids=p["expids"], part=p["part"], field=p["field"], cold=bool(p.get("check")))
    return {"galaxies": summary["sample"], "fitted": summary["fitted"], "frames": len(finals)}


def _correlate(study_dir, p, out):
    figures = os.path.join(study_dir, p["figures"])
    os.makedirs(figures, exist_ok=True)
    f = p["field"]
    # the study's sample: the galaxies in the field, every one of them (a flagged fit is kept with its flag,
    # as the paper's pipeline kept them): the same rows whether the finals were rendered whole or not
    options = CorrelateOptions(min_sep=p["min_sep"], max_sep=p["max_sep"], nbins=p["nbins"], npatch=p["npatch"],
                               thresholds=tuple(p["thresholds"]), seed=p["seed"], flagged="keep",
                               within=(f["ra"], f["dec"], f["radius"]))
    if "tables" in p:
        # the differential study's shape changes: one row per galaxy of the sample, De in columns
        summary = correlate_files([os.path.join(study_dir, t) for t in p["tables"]], out,
                                  dataclasses.replace(options, de_columns=("de1", "de2")), plots_dir=figures,
                                  overwrite=True)
        return {"frames": len(p["tables"]), "galaxies": int(summary["n"])}
    pairs = [(os.path.join(study_dir, a), os.path.join(study_dir, b)) for a, b in p["pairs"]]
    summary = correlate_files([], out, options, pairs=pairs, plots_dir=figures, overwrite=True)
    return {"frames": len(pairs), "galaxies": int(summary["n"])}


def _budget(study_dir, p, out):
    plot = os.path.join(study_dir, p["plot"])
    os.makedirs(os.path.dirname(plot), exist_ok=True)
    budget_file(out, os.path.join(study_dir, p["xi"]), bands=p["bands"], modes=p["modes"], plot=plot,
                overwrite=True)


def _summary(study_dir, p, out):
    write_summary(study_dir, p, out)


RUNNERS = dict(pointings=_pointings, catalog=_catalog, render=_render, measure=_measure, correlate=_correlate,
               budget=_budget, summary=_summary, regions=_regions, final=_final, changes=_changes)
