"""``perscli render``: a Roman SCA exposure of a truth catalogue, through a detector model."""

from __future__ import annotations

import logging

import click

from ..instrument import ROMAN_EXPTIME, ROMAN_FILTERS, ROMAN_N_SCA, ROMAN_SCA_SIZE
from .helpers import check_outputs, progress_reporter, report_errors
from .options import (model_opt, compress_opt, no_checksum_opt, output_opt, overwrite_opt, plot_opt, required_seed_opt,
                      verbosity_opts, workers_opt)

log = logging.getLogger("perscli")


def _list_effects(ctx, param, value):
    """--list-effects: print the registry's schema and stop (no TRUTH.fits, --seed or -o needed)."""
    if not value or ctx.resilient_parsing:
        return
    import shutil

    from ..detector.effects import format_schema

    click.echo(format_schema(width=max(100, shutil.get_terminal_size((120, 24)).columns)), nl=False)
    ctx.exit(0)


@click.command("render", short_help="Draw a Roman SCA exposure of a truth catalogue through a detector model.")
@click.argument("truth", metavar="TRUTH.fits")
@click.option("--pointings", "pointings_file", metavar="FILE",
              help="A pointings table (perscli pointings) or a survey schedule (date, exptime, ra, dec, pa, "
                   "filter) to take the exposure from; see --row.")
@click.option("--row", type=click.IntRange(min=0), default=0, show_default=True, metavar="N",
              help="Row of --pointings (0 is the first; for a schedule, its row number).")
@click.option("--ra", type=float, metavar="DEG", help="Pointing centre of the focal plane, right ascension.")
@click.option("--dec", type=float, metavar="DEG", help="Pointing centre of the focal plane, declination.")
@click.option("--pa", type=float, metavar="DEG", help="Observatory position angle (GalSim's convention).")
@click.option("--mjd", type=float, metavar="MJD", help="Start of the exposure.")
@click.option("--exptime", type=click.FloatRange(min=0, min_open=True), metavar="SECONDS",
              help=f"Exposure time [default: {ROMAN_EXPTIME:g}, or the pointing's].")
@click.option("--filter", "filter_name", metavar="NAME", help=f"Roman filter: {' '.join(ROMAN_FILTERS)}.")
@click.option("--sca", type=click.IntRange(1, ROMAN_N_SCA), metavar="N",
              help=f"Detector 1-{ROMAN_N_SCA} (default: the pointing's sca column).")
@click.option("--bounds", type=int, nargs=4, metavar="XMIN XMAX YMIN YMAX",
              help="Render a cutout: 1-indexed inclusive SCA pixels "
                   f"[default: the full {ROMAN_SCA_SIZE} x {ROMAN_SCA_SIZE}].")
@model_opt("roman", "roman|MODEL.yaml|FRAME.fits",
           "the detector model: GalSim's Roman chain (with saturation), a YAML list of effects in physical "
           "order, or a frame perscli rendered (the model that made it); see --list-effects")
@click.option("--set", "settings", multiple=True, metavar="EFFECT.KEY=VALUE",
              help="Override the model: e.g. read_noise.sigma=5, persistence.base=pessimistic, ipc=off.")
@click.option("--previous", multiple=True, metavar="FRAME",
              help="An earlier exposure of the same SCA (a frame perscli rendered); repeatable. Its FLUENCE "
                   "(STARFLU for --persistence-source stars) leaves persistence in this one.")
@click.option("--persistence-source", "persistence_source", metavar="all|stars|ELECTRONS", default=None,
              help="What of the --previous frames persists: all (their FLUENCE: every photon), stars (their "
                   "STARFLU: the light of stars only, the paper's setting) or a number of electrons (only pixels "
                   "whose FLUENCE exceeds it); same as --set persistence.source=...  [default: the model's, all]")
@click.option("--hdus", metavar="NAME,...", default=None,
              help="The HDUs to write, among SCI,IDEAL,FLUENCE,STARFLU,PERSIST,MODEL (STARFLU: the stars' "
                   "fluence, for later frames rendered with --persistence-source stars)  "
                   "[default: SCI,IDEAL,FLUENCE,PERSIST,MODEL]")
@required_seed_opt
@plot_opt("the frame and its persistence")
@click.option("--list-effects", is_flag=True, expose_value=False, is_eager=True, callback=_list_effects,
              help="Print every effect's parameters (type, unit, default, allowed values) and exit.")
@output_opt
@compress_opt
@no_checksum_opt
@overwrite_opt
@workers_opt("processes drawing the objects' stamps (the output does not depend on N)")
@verbosity_opts
@report_errors
def render(truth, pointings_file, row, ra, dec, pa, mjd, exptime, filter_name, sca, bounds, model_spec, settings,
           previous, persistence_source, hdus, seed, plot, output, compress, overwrite, workers):
    """Draw a Roman SCA exposure of TRUTH.fits through a detector model.

    Optics from GalSim's Roman module: the SCA's WCS for the pointing, its PSF
    for the filter (at the SCA centre and the filter's effective wavelength),
    the filter's AB zeropoint and the zodiacal plus thermal sky.  Stamps grow
    with flux so that bright stars keep their diffraction spikes, the source of
    their persistence ghosts.  The detector chain (sky, Poisson noise,
    reciprocity failure, dark current, persistence, saturation at the full
    well, nonlinearity, IPC, read noise, gain, quantisation) follows the model
    (--list-effects prints every parameter); each effect has its own random
    stream, so frames rendered with and without persistence share their noise.

    The output has SCI (the frame, DN after gain), IDEAL (noise-free electrons
    from sky and sources), FLUENCE (the charge collected, at most the full
    well: what drives later persistence), with --previous PERSIST (electrons
    of persistence), and MODEL (the resolved detector model, which --model
    FRAME.fits reads back); WCS, timing, SCA, FILTER and GAIN in the headers.
    --hdus chooses among them and STARFLU (the noise-free electrons of the
    stars alone, not clipped at the well).

    What of the --previous frames persists (--persistence-source): all their
    FLUENCE, their STARFLU (stars), or the FLUENCE of pixels above a number
    of electrons; the fluence fed to the persistence law is capped at
    persistence.fluence_cap (default: the saturation full well, 1e5 e-).
    A frame rendered once with FLUENCE and STARFLU serves as the history of
    later frames for any source.

    \b
    Examples:
      perscli render truth.fits --ra 10 --dec -44 --pa 30 --mjd 61541.97 --filter J129 --sca 7 --seed 1 -o e1.fits
      perscli render truth.fits --pointings seq.fits --row 1 --sca 7 --seed 2 --previous e1.fits -o e2.fits
      perscli render truth.fits --pointings seq.fits --row 1 --sca 7 --seed 2 --set persistence=off -o e2_nop.fits
      perscli render truth.fits --pointings seq.fits --sca 7 --bounds 1 512 1 512 --seed 1 -o cutout.fits
      perscli render truth.fits --pointings seq.fits --row 2 --sca 7 --seed 3 --model e2.fits -o e3.fits
      perscli render truth.fits --pointings seq.fits --row 0 --sca 7 --seed 1 --hdus SCI,FLUENCE,STARFLU -o h0.fits
      perscli render truth.fits --pointings seq.fits --row 1 --sca 7 --seed 2 --previous h0.fits \\
          --persistence-source stars --hdus SCI,PERSIST -o e1_stars.fits
      perscli render --list-effects
    """
    from ..detector.effects import load_detector_model
    from ..render.run import render_file

    check_outputs(output, inputs=[truth, pointings_file, model_spec, *previous], plot=plot, overwrite=overwrite)
    exposure = _exposure(pointings_file, row, ra, dec, pa, mjd, exptime, filter_name, sca, bounds)
    model = load_detector_model(model_spec, settings)
    summary = render_file(truth, exposure, output, model=model, seed=seed, previous=previous,
                          overwrite=overwrite, workers=workers, progress=progress_reporter("objects"), plot=plot,
                          compress=compress, persistence_source=persistence_source, hdus=hdus)
    log.info("%s: %d objects, sky %.3f e-/pixel/s, units %s, persistence max %.3g e-",
             "stdout" if output == "-" else output, summary["objects"], summary["sky_rate"], summary["unit"],
             summary["persistence_max"])


def _exposure(pointings_file, row, ra, dec, pa, mjd, exptime, filter_name, sca, bounds):
    from .. import PerscliError
    from ..render.exposure import Exposure

    explicit = {"--ra": ra, "--dec": dec, "--pa": pa, "--mjd": mjd, "--filter": filter_name}
    if pointings_file is not None:
        from ..scene.pointings import read_pointings

        table = read_pointings(pointings_file)
        if row >= len(table):
            raise PerscliError(f"{pointings_file}: --row {row} is past the end ({len(table)} rows)")
        p = table[row]
        values = {"--ra": p.ra, "--dec": p.dec, "--pa": p.pa, "--mjd": p.mjd, "--filter": p.filter}
        values.update({k: v for k, v in explicit.items() if v is not None})
        exptime = exptime if exptime is not None else p.exptime
        sca = sca if sca is not None else (p.sca or None)
        expid = p.expid
    else:
        missing = [k for k, v in explicit.items() if v is None]
        if missing:
            raise click.UsageError(f"give --pointings FILE, or all of --ra --dec --pa --mjd --filter "
                                   f"(missing {' '.join(missing)})")
        values, expid = explicit, -1
    if sca is None:
        raise click.UsageError(f"give --sca N (1-{ROMAN_N_SCA}): the pointing does not name a detector")
    return Exposure(ra=values["--ra"], dec=values["--dec"], pa=values["--pa"], sca=sca,
                    filter=values["--filter"], mjd=values["--mjd"],
                    exptime=exptime if exptime is not None else ROMAN_EXPTIME,
                    bounds=tuple(bounds) if bounds else None, expid=expid)
