"""Expand a study description into its task graph.

Every task names one product (a FITS file, or a folder of figures) in the
study folder, the tasks it needs, and the parameters that make it; nothing
here runs anything.  The graph:

- ``pointings``: the final exposures of each SCA (those whose footprint
  reaches the field) and, for each, its N previous exposures of the same SCA,
  whatever their filter and wherever they point (the schedule's rows just
  before it);
- ``catalog``: one truth catalogue covering exactly the footprints rendered;
- ``render/ref``: each SCA-exposure once, without persistence: the fluence of
  a history exposure, and the reference of a final one;
- ``render/<source>-<model>``: each final again, with persistence from its
  history, with the same seed as its reference (the two share their noise);
- ``measure``: shapes on the references and on each persistence variant
  (jointly over all finals, or per exposure);
- ``correlate``, ``budget``: De pooled over every final, its xi+/-,
  statistics and the additive-shear budget, per variant;
- ``summary``: the paper's numbers beside ours, the figures, the cost.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass, field

import numpy as np

from .. import PerscliError
from ..detector.effects import Persistence
from ..detector.model import load_detector_model, load_persistence_model
from ..render.settings import SOURCE_HDU
from ..scene import project
from ..scene.dithers import plan_dithers
from ..scene.footprints import sca_footprint
from ..scene.schedule import previous_exposures, read_schedule, select_covering
from .differential import LIGHT_SOURCES, variant_extname

#: the folder of a study's task records (one JSON a finished task), which the runner and the
#: summary both read
STATE = ".state"


@dataclass
class Task:
    """One node of the graph.

    Attributes
    ----------
    key : str
        Unique name, also the name of its record in ``DIR/.state``.
    kind : str
        What makes it: pointings, catalog, render, measure, correlate, budget, summary.
    output : str
        Its product, relative to the study folder.
    params : dict
        JSON-able settings (with the inputs' relative paths).
    deps : list of str
        Keys of the tasks whose products it reads.
    """

    key: str
    kind: str
    output: str
    params: dict = field(default_factory=dict)
    deps: list = field(default_factory=list)


@dataclass
class Exposures:
    """Which SCA-exposures a study renders."""

    finals: dict          # sca -> list of Pointing (time order)
    history: dict         # (sca, expid) -> list of Pointing, most recent first
    all: dict             # (sca, expid) -> Pointing: every SCA-exposure rendered


def frame_seed(seed: int, sca: int, expid: int) -> int:
    """The render seed of one SCA-exposure: the same whether it is history or a final's reference.

    ``(seed * 20 + sca) * 100000 + expid``: distinct for every SCA (1-18) and
    schedule row (< 100000) of a study, below 2**31 for seeds up to 1000, and
    simple enough to write in a Makefile (examples/persistence-study).
    """
    return (int(seed) * 20 + int(sca)) * 100_000 + int(expid)


def variant_name(source, model: str) -> str:
    """'drawn-typical', 'stars-pessimistic', 'above1e+05-typical', 'floor5e4-typical' (file-name safe).

    ``source`` is a persistence source or the name of a bracket variant.
    """
    src = source if isinstance(source, str) else f"above{float(source):.0e}"
    mod = model if "/" not in model and not model.endswith((".yaml", ".yml")) else \
        model.rsplit("/", 1)[-1].rsplit(".", 1)[0]
    return f"{src}-{mod}"


def variant_settings(s: dict) -> dict:
    """Variant name -> (persistence source, detector settings) of every persistence variant of a study.

    The variants are every model of ``persistence.models`` with every source
    of ``persistence.sources`` (the headline), then with every bracket of
    ``persistence.bracket`` (name -> more detector settings, applied after
    ``render.set``).  Each variant's settings are complete: the model's law,
    its source, the study's ``render.set``, the bracket's own.
    """
    p = s["persistence"]
    out = {}
    for m in p["models"]:
        for src in p["sources"]:
            out[variant_name(src, str(m))] = [*model_settings(str(m)), f"persistence.source={src}",
                                              *s["render"]["set"]]
        for name, extra in (p["bracket"] or {}).items():
            out[variant_name(str(name), str(m))] = [*model_settings(str(m)), f"persistence.source={p['sources'][0]}",
                                                    *s["render"]["set"], *extra]
    return {name: (Persistence.fluence_input(load_detector_model("roman", settings))[0], settings)
            for name, settings in out.items()}


def reference_settings(s: dict) -> list:
    """The detector settings of every final's reference (no earlier exposure given: no persistence)."""
    return [*model_settings("typical"), *s["render"]["set"]]


def model_settings(model: str) -> list:
    """Detector-model overrides that make the persistence effect follow ``model``.

    Parameters
    ----------
    model : str
        'typical' or 'pessimistic' (the paper's Table 1), or a persistence
        model file (YAML, as ``perscli apply-persistence --model`` reads it).

    Returns
    -------
    list of str
        ``persistence.KEY=VALUE`` settings for
        :func:`perscli.detector.model.load_detector_model`.
    """
    if model in ("typical", "pessimistic"):
        return [f"persistence.base={model}"]

    pm = load_persistence_model(model)
    if pm.kind == "linear":
        return ["persistence.kind=linear",
                "persistence.coefficients=[" + ", ".join(repr(float(c)) for c in pm.coefficients) + "]"]
    return [f"persistence.{k}={float(getattr(pm, k))!r}" for k in ("A", "x0", "dx", "alpha", "gamma", "half_well")]


def select_exposures(s: dict, progress=None) -> Exposures:
    """The finals and their histories, from the schedule or a planned sequence.

    Parameters
    ----------
    s : dict
        Study settings (:func:`perscli.study.config.load_study`).
    progress : callable, optional
        ``progress(done, total, name)`` after each SCA of a schedule (its footprints take seconds each).

    Returns
    -------
    Exposures
    """
    e, f = s["exposures"], s["field"]
    finals, history, every = {}, {}, {}
    if e["source"] == "plan":
        n = e["count"] + e["history"]
        seq = plan_dithers(f["ra"], f["dec"], n, dither=e["plan_dither"], filter=s["filter"],
                             start=e["plan_start"], pa=e["plan_pa"], seed=s["seed"])
        for sca in s["scas"]:
            finals[sca] = [_with_sca(p, sca) for p in seq[e["history"]:]]
            for k, p in enumerate(seq[e["history"]:], start=e["history"]):
                history[(sca, p.expid)] = [_with_sca(q, sca) for q in seq[max(0, k - e["history"]):k][::-1]]
    else:
        schedule = read_schedule(e["schedule"])
        for k, sca in enumerate(s["scas"]):
            if progress is not None:
                progress(k, len(s["scas"]), f"SCA {sca}: its footprints in {len(schedule)} exposures")
            chosen = select_covering(schedule, f["ra"], f["dec"], f["radius"], filter=s["filter"],
                                       after=e["after"] or None, limit=e["count"] or None, sca=sca)
            if not chosen:
                raise PerscliError(f"no {s['filter']} exposure of the schedule puts SCA {sca} within "
                                   f"{f['radius']} deg of ra={f['ra']} dec={f['dec']}: widen field.radius or "
                                   "choose other scas")
            # in time order: the next final shares all but one of its earlier exposures with the one before
            # (a worker keeps their stars' light), and the study's products are listed as they were taken
            finals[sca] = sorted(chosen, key=lambda p: (p.mjd, p.expid))
            for p in chosen:
                history[(sca, p.expid)] = [_with_sca(q, sca) for q in
                                           previous_exposures(schedule, p.expid, e["history"])] \
                    if e["history"] else []
        if progress is not None:
            progress(len(s["scas"]), len(s["scas"]), f"{sum(map(len, finals.values()))} finals")
    for sca, ps in finals.items():
        for p in ps:
            every[(sca, p.expid)] = p
            for q in history[(sca, p.expid)]:
                every.setdefault((sca, q.expid), q)
    return Exposures(finals=finals, history=history, all=every)


def _with_sca(p, sca: int):
    return dataclasses.replace(p, sca=int(sca))


def frame_path(sca: int, expid: int, variant: str = "ref") -> str:
    return f"frames/sca{sca:02d}/e{expid:06d}_{variant}.fits"


def is_differential(s: dict) -> bool:
    """Whether a study renders only where persistence reaches (``differential``; auto: when every variant's
    persisting light is drawn from the catalogue, persistence sources drawn and stars)."""
    wanted = s.get("differential")
    drawable = all(src in LIGHT_SOURCES for src, _ in variant_settings(s).values())
    if wanted is None:
        return drawable
    if wanted and not drawable:
        raise PerscliError("differential: true needs every variant's persistence source to be drawn or stars (what "
                           "persists is then light drawn from the catalogue); use differential: false for all or a "
                           "threshold")
    return bool(wanted)


def realisation_seeds(s: dict) -> list:
    """The seed of each realisation: seed, seed + 1, ... (``realisations`` of them)."""
    return [int(s["seed"]) + k for k in range(int(s["realisations"]))]


def build(s: dict, exposures: Exposures | None = None, progress=None) -> list:
    """The task graph of a study, in an order where every task follows its dependencies.

    Parameters
    ----------
    s : dict
        Study settings.
    exposures : Exposures, optional
        Already selected (else :func:`select_exposures`, reporting to ``progress``).

    Returns
    -------
    list of Task
        With several realisations, each realisation's products live in
        ``r<seed>/`` and one summary covers them all.
    """
    ex = exposures or select_exposures(s, progress)
    seeds = realisation_seeds(s)
    tasks = [Task("pointings", "pointings", "pointings.fits",
                  params=dict(rows=[_pointing_row(ex, key) for key in sorted(ex.all)]))]
    make = _build_differential if is_differential(s) else _build_full
    prefixes = [f"r{seed:04d}/" if len(seeds) > 1 else "" for seed in seeds]
    nfinals = sum(len(ps) for ps in ex.finals.values())
    for k, (seed, prefix) in enumerate(zip(seeds, prefixes)):
        if progress is not None and nfinals >= 100:   # each final's footprint again: a minute for the paper's
            progress(k, len(seeds), f"the tasks of seed {seed}: the footprints of {nfinals} finals")
        tasks += make(s, ex, seed, prefix)
    finals_sorted = [(sca, p.expid) for sca, ps in sorted(ex.finals.items()) for p in ps]
    variants = list(variant_settings(s))
    tasks.append(Task("summary", "summary", "summary.json", deps=[t.key for t in tasks],
                      params=dict(variants=variants, finals=[list(k) for k in finals_sorted], name=s["name"],
                                  realisations=[dict(seed=seed, prefix=prefix) for seed, prefix in zip(seeds, prefixes)],
                                  differential=is_differential(s), joint=bool(s["measure"]["joint"]),
                                  field=dict(s["field"]),
                                  thresholds=list(s["correlate"]["thresholds"]))))
    return tasks


def _catalog_task(s: dict, ex: Exposures, seed: int, pre: str) -> Task:
    """The truth catalogue of every footprint rendered: stars everywhere, galaxies where they matter.

    When only star light persists, an earlier exposure leaves its stars' light alone: galaxies are drawn
    on the finals' footprints only (the same catalogue however the finals are rendered).
    """
    params = dict(catalog=s["catalog"], bounds=s["bounds"], seed=seed, field=s["field"])
    if all(src == "stars" for src, _ in variant_settings(s).values()):
        finals = {(sca, p.expid) for sca, ps in ex.finals.items() for p in ps}
        params["galaxy_rows"] = [i for i, key in enumerate(sorted(ex.all)) if key in finals]
    return Task(f"{pre}catalog", "catalog", f"{pre}truth.fits", deps=["pointings"], params=params)


def _chunks(ex: Exposures, size: int):
    """Consecutive finals of each SCA, ``size`` at a time: (sca, [Pointing]) (they share earlier exposures)."""
    for sca in sorted(ex.finals):
        ps = ex.finals[sca]
        for k in range(0, len(ps), size):
            yield sca, ps[k:k + size]


def _build_differential(s: dict, ex: Exposures, seed: int, pre: str) -> list:
    """Where persistence reaches, each final on those stamps (its earlier exposures' light drawn in it), De, xi.

    Consecutive finals of an SCA make one task (``measure.chunk`` of them): they share their earlier
    exposures, whose light is drawn once.  With a joint fit, each final's stamps are written
    (frames/scaNN/cEEEEEE/eEEEEEE_final.fits) and tasks by strips of the sky fit the sample's galaxies
    over all their finals; without, each task fits its finals' galaxies right away and writes only their
    shape changes (shapes/scaNN/eNNNNNN.fits), so that a study of thousands of finals keeps no frames.
    """
    tasks = [_catalog_task(s, ex, seed, pre)]
    finals = [(sca, p) for sca, ps in sorted(ex.finals.items()) for p in ps]
    variants = variant_settings(s)
    m = s["measure"]
    sources = sorted({src for src, _ in variants.values()})
    if m["joint"]:
        # a galaxy that persistence can reach on any final is simulated on all its finals: found for all at once
        tasks.append(Task(f"{pre}regions", "regions", f"{pre}regions.fits", deps=[f"{pre}catalog"],
                          params=dict(truth=f"{pre}truth.fits", finals=[dict(pointing=_pointing_dict(p),
                                                   history=[_pointing_dict(q) for q in ex.history[(sca, p.expid)]])
                                              for sca, p in finals],
                                      bounds=s["bounds"], stamp=m["stamp"], joint=True, sources=sources,
                                      models=[list(v[1]) for v in variants.values()], field=s["field"])))
    common = dict(truth=f"{pre}truth.fits", bounds=s["bounds"], model=reference_settings(s),
                  variants={name: list(v[1]) for name, v in variants.items()}, stamp=m["stamp"],
                  compress=s["render"]["compress"], field=s["field"])

    def one(sca, p):
        return dict(pointing=_pointing_dict(p), sca=sca, seed=frame_seed(seed, sca, p.expid),
                    history=[_pointing_dict(q) for q in ex.history[(sca, p.expid)]])

    final_keys, outputs, final_files = [], [], {}
    size = max(1, int(m["chunk"]))
    for sca, group in _chunks(ex, size):
        key = f"{pre}final/sca{sca:02d}/e{group[0].expid:06d}"
        final_keys.append(key)
        if m["joint"]:
            # the chunk's finals, one file each, in a folder of their own (the task's product)
            out = f"{pre}frames/sca{sca:02d}/c{group[0].expid:06d}"
            for p in group:
                final_files[(sca, p.expid)] = (key, f"{out}/e{p.expid:06d}_final.fits")
            tasks.append(Task(key, "final", out, deps=[f"{pre}regions"],
                              params=dict(common, regions=f"{pre}regions.fits", finals=[one(sca, p) for p in group])))
        else:
            # fitted per exposure: the task keeps only its finals' shape changes
            out = f"{pre}shapes/sca{sca:02d}/e{group[0].expid:06d}.fits"
            outputs.append(out)
            tasks.append(Task(key, "final", out, deps=[f"{pre}catalog"],
                              params=dict(common, regions=None, finals=[one(sca, p) for p in group],
                                          measure=dict(min_snr=m["min_snr"], stamp=m["stamp"],
                                                       check=bool(m["check"])))))
    c, b = s["correlate"], s["budget"]
    if m["joint"]:
        # the galaxies spread over tasks by strips of the sky (each fits the reference once for every
        # variant, and reads only the finals that reach its strip)
        parts = []
        nparts = strips(s)
        for k, (strip, used) in enumerate(measure_strips(s, finals, nparts)):
            key, out = f"{pre}measure/part{k + 1}of{nparts}", f"{pre}shapes/part{k + 1}of{nparts}.fits"
            parts.append((key, out))
            files = [final_files[(finals[i][0], finals[i][1].expid)] for i in used]
            tasks.append(Task(key, "changes", out, deps=[f"{pre}catalog", *sorted({dep for dep, _ in files})],
                              params=dict(truth=f"{pre}truth.fits", finals=[path for _, path in files],
                                          expids=[finals[i][1].expid for i in used], variants=list(variants),
                                          joint=True, min_snr=m["min_snr"], stamp=m["stamp"], part=strip,
                                          field=s["field"], check=bool(m["check"]))))
    for name in variants:
        if m["joint"]:
            tables, deps = [f"{out}[{variant_extname(name)}]" for _, out in parts], [key for key, _ in parts]
        else:
            tables, deps = [f"{out}[{variant_extname(name)}]" for out in outputs], final_keys
        tasks.append(Task(f"{pre}correlate/{name}", "correlate", f"{pre}xi/{name}.fits", deps=deps,
                          params=dict(tables=tables, figures=f"{pre}figures/{name}", seed=seed, field=s["field"], **c)))
        tasks.append(Task(f"{pre}budget/{name}", "budget", f"{pre}budget/{name}.fits", deps=[f"{pre}correlate/{name}"],
                          params=dict(xi=f"{pre}xi/{name}.fits", plot=f"{pre}figures/{name}/budget.png", **b)))
    return tasks


#: deg^2 of the field per strip of joint fits when ``measure.parts`` is 0 (a strip's task holds its galaxies'
#: stamps on every final: ~1.5 GB per 0.1 deg^2 with two variants)
STRIP_AREA_DEG2 = 0.1


def strips(s: dict) -> int:
    """How many strips of the sky the joint fits are spread over (``measure.parts``, or by the field's area)."""
    if s["measure"]["parts"]:
        return int(s["measure"]["parts"])
    area = math.pi * s["field"]["radius"] ** 2
    return max(2, math.ceil(area / STRIP_AREA_DEG2))


#: arcsec: a final serves a strip of the sky when its footprint grown by this reaches it (stamps reach
#: a few arcsec beyond a galaxy's position; positions are compared on the tangent plane)
STRIP_MARGIN_ARCSEC = 10.0


def measure_strips(s: dict, finals, n: int) -> list:
    """The sky cut in ``n`` strips of right ascension for the joint fits, and the finals each one needs.

    Parameters
    ----------
    s : dict
        Study settings (the field centre and the frames' bounds).
    finals : list of (int, Pointing)
        (SCA, pointing) of every final.
    n : int

    Returns
    -------
    list of (dict, list of int)
        Per strip: the strip (``ra0``, ``dec0``: the tangent point; ``xi_lo``,
        ``xi_hi``: its edges in standard coordinates, radians, None at the
        ends) and the indices of the finals whose footprints reach it.
    """
    f = s["field"]
    spans = []
    for sca, p in finals:
        ra, dec = sca_footprint(p, sca, bounds=s["bounds"])
        xi, _ = project(f["ra"], f["dec"], ra, dec)
        spans.append((float(np.nanmin(xi)), float(np.nanmax(xi))))
    if not spans:
        return []
    lo, hi = min(a for a, _ in spans), max(b for _, b in spans)
    edges = np.linspace(lo, hi, n + 1)
    margin = math.radians(STRIP_MARGIN_ARCSEC / 3600.0)
    out = []
    for k in range(n):
        a, b = edges[k], edges[k + 1]
        used = [i for i, (u, v) in enumerate(spans) if u - margin <= b and v + margin >= a]
        out.append((dict(ra0=float(f["ra"]), dec0=float(f["dec"]), xi_lo=None if k == 0 else float(a),
                         xi_hi=None if k == n - 1 else float(b)), used))
    return out


def _build_full(s: dict, ex: Exposures, seed: int, pre: str) -> list:
    """Every SCA-exposure rendered whole, every final again per variant, every galaxy measured in each."""
    tasks = []
    final_keys = {(sca, p.expid) for sca, ps in ex.finals.items() for p in ps}
    tasks.append(_catalog_task(s, ex, seed, pre))
    variants = variant_settings(s)
    # what later frames read of an earlier one: the image each variant's source persists from
    light = sorted({SOURCE_HDU[src if isinstance(src, str) else "threshold"] for src, _ in variants.values()})
    # the reference of each SCA-exposure: what later frames need of it (fluence), and for a
    # final what measure needs (SCI)
    for (sca, expid), p in sorted(ex.all.items()):
        is_final = (sca, expid) in final_keys
        # only what later tasks read: a frame's bytes are most of a study's
        # (MODEL with SCI: measure takes its noise model from the frame)
        hdus = (["SCI", "MODEL"] if is_final else []) + light
        tasks.append(Task(f"{pre}render/ref/sca{sca:02d}/e{expid:06d}", "render", f"{pre}{frame_path(sca, expid)}",
                          deps=[f"{pre}catalog"],
                          params=dict(truth=f"{pre}truth.fits", pointing=_pointing_dict(p), sca=sca,
                                      bounds=s["bounds"], seed=frame_seed(seed, sca, expid), previous=[], hdus=hdus,
                                      model=reference_settings(s), compress=s["render"]["compress"],
                                      filter=p.filter)))
    for sca, ps in sorted(ex.finals.items()):
        for p in ps:
            hist = ex.history[(sca, p.expid)]
            prev_keys = [f"{pre}render/ref/sca{sca:02d}/e{q.expid:06d}" for q in hist]
            for name, (_, settings) in variants.items():
                tasks.append(Task(f"{pre}render/{name}/sca{sca:02d}/e{p.expid:06d}", "render",
                                  f"{pre}{frame_path(sca, p.expid, name)}", deps=[f"{pre}catalog", *prev_keys],
                                  params=dict(truth=f"{pre}truth.fits", pointing=_pointing_dict(p), sca=sca,
                                              bounds=s["bounds"], seed=frame_seed(seed, sca, p.expid),
                                              previous=[f"{pre}{frame_path(sca, q.expid)}" for q in hist],
                                              hdus=["SCI", "MODEL"] + (["PERSIST"] if s["render"]["write_persist"] else []),
                                              model=list(settings), compress=s["render"]["compress"],
                                              filter=p.filter)))
    finals_sorted = [(sca, p.expid) for sca, ps in sorted(ex.finals.items()) for p in ps]
    m = s["measure"]
    shape_tasks = {}
    for name in ["ref", *variants]:
        frames = [f"{pre}{frame_path(sca, expid, name)}" for sca, expid in finals_sorted]
        deps = [f"{pre}render/{name}/sca{sca:02d}/e{expid:06d}" for sca, expid in finals_sorted]
        if m["joint"]:
            key = f"{pre}measure/{name}"
            tasks.append(Task(key, "measure", f"{pre}shapes/{name}.fits", deps=[f"{pre}catalog", *deps],
                              params=dict(truth=f"{pre}truth.fits", frames=frames, joint=True, min_snr=m["min_snr"],
                                          stamp=m["stamp"])))
            shape_tasks[name] = [(key, f"{pre}shapes/{name}.fits")]
        else:
            shape_tasks[name] = []
            for (sca, expid), frame, dep in zip(finals_sorted, frames, deps):
                key = f"{pre}measure/{name}/sca{sca:02d}/e{expid:06d}"
                out = f"{pre}shapes/{name}/sca{sca:02d}_e{expid:06d}.fits"
                tasks.append(Task(key, "measure", out, deps=[f"{pre}catalog", dep],
                                  params=dict(truth=f"{pre}truth.fits", frames=[frame], joint=False,
                                              min_snr=m["min_snr"],
                                              stamp=m["stamp"])))
                shape_tasks[name].append((key, out))
    c, b = s["correlate"], s["budget"]
    for name in variants:
        pairs = [[a[1], r[1]] for a, r in zip(shape_tasks[name], shape_tasks["ref"])]
        deps = [a[0] for a in shape_tasks[name]] + [r[0] for r in shape_tasks["ref"]]
        tasks.append(Task(f"{pre}correlate/{name}", "correlate", f"{pre}xi/{name}.fits", deps=deps,
                          params=dict(pairs=pairs, figures=f"{pre}figures/{name}", seed=seed, field=s["field"], **c)))
        tasks.append(Task(f"{pre}budget/{name}", "budget", f"{pre}budget/{name}.fits", deps=[f"{pre}correlate/{name}"],
                          params=dict(xi=f"{pre}xi/{name}.fits", plot=f"{pre}figures/{name}/budget.png", **b)))
    return tasks


def _pointing_dict(p) -> dict:
    return dict(expid=int(p.expid), mjd=float(p.mjd), exptime=float(p.exptime), ra=float(p.ra), dec=float(p.dec),
                pa=float(p.pa), filter=str(p.filter), sca=int(p.sca))


def _pointing_row(ex: Exposures, key) -> dict:
    sca, expid = key
    row = _pointing_dict(ex.all[key])
    finals = {p.expid for p in ex.finals.get(sca, [])}
    row["role"] = "final" if expid in finals else "history"
    return row


def counts(tasks) -> dict:
    """Tasks of each kind (for the cost model and progress)."""
    out = {}
    for t in tasks:
        out[t.kind] = out.get(t.kind, 0) + 1
    return out
