"""``perscli study``: a whole persistence study from one description, serially or on Dask."""

from __future__ import annotations

import os
import shutil
import sys

import click

from ..io.config import STUDY_ITEM
from ..io.output import check_output_folder, write_error
from ..progress import lines
from .helpers import FILE, FOLDER, PerscliCommand, report_errors
from ..study.settings import StudyOptions
from .options import key_values, no_checksum_opt, overwrite_opt, settings_option, verbosity_opts, workers_opt



@click.command("study", cls=PerscliCommand,
               short_help="Run a whole persistence study from one YAML description (Dask or serial).")
@click.argument("description", required=False, metavar="STUDY.yaml", type=FILE)
@click.option("-o", "--output", "outdir", required=True, metavar="DIR", type=FOLDER,
              help="Study folder: every product is written here; a rerun skips what is already made.")
@click.option("--preset", type=click.Choice(["small", "paper", "ci"]), default=None,
              help="Start from a preset (small: a laptop; paper: the paper's 6.25 deg^2 and 18 SCAs; ci: the "
                   "test suite's); STUDY.yaml and --set override it.")
@click.option("--set", "settings", multiple=True, metavar="KEY=VALUE", callback=key_values(STUDY_ITEM),
              help="Override a setting, e.g. exposures.count=5 or persistence.sources=[stars,all]; repeatable.")
@settings_option(StudyOptions, "scheduler")
@workers_opt("worker processes of --scheduler local's Dask LocalCluster, one task each at a time")
@click.option("--dry-run", is_flag=True, help="Print the task graph's size (and with --cost-from its cost); run nothing.")
@click.option("--cost-from", "cost_from", type=click.Path(exists=True, dir_okay=False), default=None,
              metavar="COST.json", help="With --dry-run: project CPU-hours and bytes from the cost.json of "
                                       "an earlier study whose field covers whole SCAs, as the projected one's "
                                       "does (e.g. the small preset's): the fits are scaled by the finals they "
                                       "read, so a field smaller than an SCA, with fewer galaxies on each final, "
                                       "would underestimate them.")
# eager: in force before anything is read; the runner carries it to every task (serial, LocalCluster or a
# remote scheduler's workers), as the executor does for the other commands
@no_checksum_opt
@overwrite_opt
@verbosity_opts
@report_errors
def study(description, outdir, preset, settings, scheduler, workers, dry_run, cost_from, overwrite):
    """Run the persistence study STUDY.yaml (or a --preset) into DIR.

    The description (GalSim-config style; every key checked, typos named)
    gives the field, filter and SCAs, the final exposures (from a
    schedule, by default roman-was, the Roman project's public Wide Area
    Survey sequence shipped with perscli, or exposures.schedule: FILE:
    those whose SCA footprint reaches the field, each with its N
    previous exposures of the same SCA whatever their filter; or a planned
    dither sequence), the truth catalogue, the persistence models and sources
    (drawn, the default and the paper's pipeline: the light drawn on each
    earlier exposure, galaxies and stars, no sky; stars: star light only;
    all: the whole fluence; or a fluence threshold in electrons), bracket
    variants beside them, measure and correlate settings and the seed.

    It becomes a task graph.  When what persists is light drawn from the
    catalogue (drawn or stars: differential, by default), each final is
    rendered once, for the reference and every variant together, on the
    stamps of the galaxies that earlier light can reach (every pixel the same
    bits as a whole-frame render: noise is keyed on detector blocks); each
    galaxy's shape is fitted once over all its finals (measure.joint, the
    paper's pipeline) and every variant's from the reference fit's linear
    response to the pixels that changed; a galaxy whose stamps did not change
    gets De = 0 exactly and is counted.  Otherwise (differential: false) every
    SCA-exposure is rendered whole without persistence, each final again per
    variant with the same seed, and every galaxy measured in each.  De is
    correlated, compared with the additive-shear budget, and summarised
    beside the paper's numbers (DIR/summary.md, summary.json, figures/,
    cost.json); realisations: N repeats the study with N seeds and gives the
    scatter across them.  Every product is a FITS file with its provenance; a
    rerun skips finished products, so a killed run resumes.  The same seeds
    give the same bytes whatever the scheduler or worker count (cost.json,
    the run's own timings, excepted).  --overwrite makes every product again.

    \b
    Examples:
      perscli study examples/small.yaml -o small_plan --dry-run
      perscli study --preset ci -o ci_study --scheduler serial
      perscli study --preset ci -o ci_dask --scheduler local --workers 2
      perscli study --preset paper -o paper_study --dry-run --cost-from ci_study/cost.json
      perscli study examples/small.yaml -o small_study --workers 2
      perscli study --preset paper -o /scratch/paper --scheduler tcp://HOST:8786

    Run again, a study skips what is made; with a setting changed (--set
    measure.min_snr=10) it remakes the shapes and what follows.  Settings
    for what the paper leaves open: --set 'render.set=[persistence.floor=1e4]'
    (only star light above 1e4 e- per pixel persists), realisations=4,
    measure.joint=false, catalog.star_model.thin_height=300.
    (The last example needs a Dask scheduler running at HOST.  The fourth
    shows the projection; the ci preset is a cutout, with fewer galaxies on
    each final than a whole SCA, so it underestimates the paper's fits:
    project from a study whose finals are whole SCAs, as the small preset's.)
    """
    from ..study.config import dump, load_study
    from ..study.plan import STATE, build
    from ..study.runner import run_study, task_dicts
    from ..study.summary import load_cost, project_cost

    ctx = click.get_current_context(silent=True)
    verbosity = (ctx.find_root().obj or {}).get("verbosity", 0) if ctx else 0
    # before the description is even built: a study's folder may exist (it resumes), never be a file
    check_output_folder(outdir, resume=True, inputs=[description])
    s = load_study(description, preset=preset, overrides=settings)
    # read before anything is planned or printed: a bad file is the only line
    measured = load_cost(cost_from) if dry_run and cost_from else None
    # planning from a schedule takes seconds per SCA (GalSim's WCS of every exposure near the field): a line each,
    # at a terminal or in a log alike, none with -q
    tasks = task_dicts(build(s, progress=lines("study: planning", quiet=verbosity < 0)))
    n = _counts(tasks)
    if dry_run:
        click.echo(f"study {s['name']}: {len(tasks)} tasks: " + ", ".join(f"{v} {k}" for k, v in n.items()))
        if cost_from:
            p = project_cost(tasks, measured)
            click.echo(f"projected from {cost_from}: {p['cpu_hours']:.1f} CPU-hours, {p['terabytes']:.3f} TB")
            if p["missing"]:
                click.echo(f"study: {cost_from} has no {', '.join(p['missing'])} tasks to project from: they are "
                           "not in these figures", err=True)
        return
    os.makedirs(outdir, exist_ok=True)
    if overwrite:
        # forget what was made: every product is made again (and replaced)
        shutil.rmtree(os.path.join(outdir, STATE), ignore_errors=True)
    path = os.path.join(outdir, "study.yaml")
    try:
        # whole or not at all: a full disk must not leave a truncated description beside the products
        tmp = f"{path}.{os.getpid()}.part"
        try:
            with open(tmp, "w") as fh:
                fh.write(dump(s))
            os.replace(tmp, path)
        finally:
            if os.path.exists(tmp):
                os.unlink(tmp)
    except OSError as exc:
        raise write_error(path, exc) from None
    recs = run_study(tasks, outdir, StudyOptions(scheduler=scheduler, workers=workers, quiet=verbosity < 0))
    made = sum(1 for r in recs if not r.get("skipped"))
    print(f"study {s['name']}: {made} products made, {len(tasks) - made} already there; "
          f"summary in {outdir}/summary.md", file=sys.stderr)



def _counts(tasks) -> dict:
    out = {}
    for t in tasks:
        out[t["kind"]] = out.get(t["kind"], 0) + 1
    return out
