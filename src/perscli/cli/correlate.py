"""``perscli correlate``: the correlation function and statistics of shape changes De."""

from __future__ import annotations

import logging

import click
from click.core import ParameterSource

from ..stats.settings import CorrelateOptions
from .helpers import FILE, FOLDER, PerscliCommand, check_outputs, report_errors, require_inputs
from .options import (columns_opt, no_checksum_opt, output_opt, overwrite_opt, plot_opt, seed_opt, settings_options,
                      verbosity_opts, workers_opt)

log = logging.getLogger("perscli")

#: the defaults, written once (perscli.stats.settings)
D = CorrelateOptions()


@click.command("correlate", cls=PerscliCommand,
               short_help="Correlation function xi+/- and statistics of shape changes De.")
@click.argument("shapes", nargs=-1, required=False, metavar="[SHAPES_A.fits [SHAPES_B.fits]]", type=FILE)
@click.option("--pair", "pair_list", type=FILE, nargs=2, multiple=True, metavar="A B",
              help="One pair of SHAPES tables, A (with persistence) and B (its reference); repeat for many: the De "
                   "of every pair are pooled into one catalogue.  Not with SHAPES arguments.")
@click.option("--pairs", "pairs_file", metavar="FILE", default=None, type=FILE,
              help="A text file of pairs to pool: 'A.fits B.fits' per line, # comments, names relative to the "
                   "file's folder.  Adds to --pair.")
@click.option("--frames", type=int, nargs=2, default=None, metavar="A B",
              help="Frames (the frame column of perscli measure) to difference: with one table, De = g(frame A) "
                   "- g(frame B) of it; with two (or pairs), frame A of the first minus frame B of the second.")
@click.option("--de1", metavar="COL", default=None, help="One table: the column holding De1.")
@click.option("--de2", metavar="COL", default=None, help="One table: the column holding De2.")
@settings_options(CorrelateOptions, "common_ids", "positions", "pixel_scale", "min_sep", "max_sep", "nbins",
                  "sep_units", "bin_slop", "npatch")
@click.option("--patch-centers", metavar="FILE", default=None, type=FILE,
              help="Jackknife patch centres instead of k-means: TreeCorr's write_patch_centers file, a table "
                   "of ra/dec (degrees), or an earlier perscli correlate output (its PATCHES table).")
@settings_options(CorrelateOptions, "var_method", "cross_patch_weight", "thresholds", "theta_edges", "nboot")
@click.option("--keep-flagged", "keep_flagged", is_flag=True, default=D.flagged == "keep",
              help="Keep objects whose fits carry a flag, with their De (STATS counts the clean ones apart: "
                   "n_clean, n_clean_ge), as a study's sample does; by default they are left out.")
@click.option("--within", type=float, nargs=3, default=None, metavar="RA DEC RADIUS",
              help="Only the objects within RADIUS degrees of (RA, DEC) (degrees): a study's field.")
@columns_opt("the SHAPES tables", "ra=ALPHA_J2000,dec=DELTA_J2000,g1=E1,g2=E2")
@no_checksum_opt
@seed_opt
@plot_opt("xi+/- with its errors")
@click.option("--plots", "plots_dir", metavar="DIR", default=None, type=FOLDER,
              help="Also draw xi.png, hist_de.png and bin_theta.png in DIR (created if needed).")
@output_opt
@overwrite_opt
@workers_opt("TreeCorr's threads (results agree to rounding: threads add pairs up in varying order)")
@verbosity_opts
@click.pass_context
@report_errors
def correlate(ctx, shapes, pair_list, pairs_file, frames, de1, de2, common_ids, positions, pixel_scale, min_sep,
              max_sep, nbins, sep_units, bin_slop, npatch, patch_centers, var_method, cross_patch_weight, thresholds,
              theta_edges, nboot, keep_flagged, within, columns, seed, plot, plots_dir, output, overwrite, workers):
    """Correlation function xi+/- and statistics of the shape changes De.

    De is the change of each object's shape between two measurements:
    De = g(A) - g(B), A measured with persistence and B without (the
    reference), objects matched by id and kept when unflagged (flags == 0)
    in both (every one with --keep-flagged; only those within a circle with
    --within).  A and B are two SHAPES tables (perscli measure), or two frames
    of one (--frames A B: `perscli measure exp.fits exp_nopersist.fits`
    writes them as frames 0 and 1, so --frames 0 1).  One table can also
    hold De itself: --de1 COL --de2 COL (rows with flags != 0, if it has a
    flags column, are left out).

    Many pairs (each final exposure against its reference): --pair A B,
    repeated, and/or --pairs FILE.  Each pair gives De as above and all are
    pooled into one catalogue for xi+/-, STATS, HIST_DE and THETA_DE; an
    object measured in several pairs appears once per pair, at its ra/dec
    (pooled pairs need ra/dec).  A table may be a joint fit (one row per
    galaxy, no frame column needed) whose header says g is in sky axes
    (GAXES or GFRAME = 'sky'); a pair's A and B, and all pairs, must agree
    on the axes.  The output adds a PAIRS table (files, DATASUMs, counts per
    pair).

    xi+/- of De is TreeCorr's GGCorrelation on ra/dec (or x/y) positions
    with log bins --min-sep to --max-sep, and its covariance is the
    jackknife over --npatch k-means patches (or --patch-centers).  When a
    jackknife is impossible (a few dozen objects, say) the errors are
    TreeCorr's shot noise instead, with a warning saying why, and the
    header says so (VARMETHD, VARWHY); --var-method jackknife refuses
    instead.  A separation bin whose jackknife variance is zero though it
    has pairs (a pair or two at the edge of the range) gets its shot noise
    instead (header SHOTBINS).  The output has the HDUs XI (TreeCorr's
    columns: r_nom, meanr, meanlogr, xip, xim, xip_im, xim_im, sigma_xip,
    sigma_xim, weight, npairs; header SEP_UNIT), COV (the covariance, xi+ bins then xi- bins), STATS (N, mean
    intrinsic e = mean g of B, mean De1 and De2 with standard errors, the
    number and fraction of objects with |De| >= each --thresholds), HIST_DE
    (histogram of |De|, log bins 1e-12 to 1 plus under- and overflow),
    THETA_DE (the |De|-weighted distribution of De's position angle
    0.5 atan2(De2, De1) in 18 bins, per --theta-bins |De| bin, with
    bootstrap errors, and a chi2 against uniform with the variance under
    uniform: chi2_uniform, dof_uniform, p_uniform) and PATCHES (the patch
    centres, reusable with --patch-centers).

    Orientation: g in a per-frame SHAPES table is in the frame's pixel
    axes, and De is correlated in the axes it is given in.  xi+ does not depend on that when one rotation
    takes those axes to the sky over the whole catalogue (one detector, one
    pointing); if the axes are also mirrored, xi+ changes only by the small
    parallel-transport terms of the sphere.  xi- does depend on it: a
    rotation by phi turns it into xi- exp(4i phi), mixing xim and xim_im.
    For catalogues that combine orientations, pool joint fits (sky axes),
    or rotate De to the sky first and give it with --de1/--de2; pooled
    pairs in pixel axes whose orientations differ get a warning.

    The same --seed gives the same patches and bootstrap, hence the same
    output (to rounding in the last digits: TreeCorr's threads add up in
    varying order).

    \b
    Examples:
      perscli pointings plan --ra 10 --dec -44 --n 2 --sca 7 -o pair.fits
      perscli catalog --pointings pair.fits --bounds 1 256 1 256 -o truth.fits
      perscli render truth.fits --pointings pair.fits --row 0 --bounds 1 256 1 256 --seed 1 -o frame0.fits
      perscli render truth.fits --pointings pair.fits --row 1 --bounds 1 256 1 256 --seed 2 \\
          --previous frame0.fits -o frame.fits
      perscli render truth.fits --pointings pair.fits --row 1 --bounds 1 256 1 256 --seed 2 \\
          --set persistence=off -o frame_nop.fits
      perscli measure frame.fits --catalog truth.fits -o shapes.fits
      perscli measure frame_nop.fits --catalog truth.fits -o shapes_nop.fits
      perscli measure frame.fits frame_nop.fits --catalog truth.fits -o both.fits
      perscli correlate both.fits --frames 0 1 --min-sep 0.05 --max-sep 2 --nbins 5 -o xi.fits --plots figs
      perscli correlate shapes.fits shapes_nop.fits --min-sep 0.05 --max-sep 2 --nbins 5 -o xi_ab.fits \\
          --plot xi_ab.png
      perscli correlate --pair shapes.fits shapes_nop.fits --min-sep 0.05 --max-sep 2 --nbins 5 -o xi_pairs.fits
      perscli correlate both.fits --de1 g1 --de2 g2 --min-sep 0.05 --max-sep 2 --nbins 5 -o xi_g.fits

    (The first eight make the inputs, as perscli measure --help does: two
    exposures of a 256 x 256 cutout of SCA 7, the second with and without
    the persistence of the first, and their shapes: a dozen galaxies or so,
    hence arcsecond separations and shot-noise errors.  A study pools many
    pairs: --pair A B --pair C D ..., or --pairs FILE with one
    'A.fits B.fits' per line; with --patch-centers an earlier output's
    PATCHES fixes the jackknife patches.  The last example correlates one
    table's own columns, here g itself.)
    """
    from ..stats.correlate import correlate_files
    from ..stats.pairs import read_pairs_file

    # a table that is not there is said first: the options that would go with it come after (--pairs and
    # --patch-centers are checked where they are read, naming the option)
    require_inputs(*shapes, *(name for pair in pair_list for name in pair))
    pooled = bool(pair_list) or pairs_file is not None
    if pooled and shapes:
        raise click.UsageError("give SHAPES tables or --pair/--pairs, not both", ctx)
    if not pooled and not shapes:
        raise click.UsageError("give one or two SHAPES tables, or pairs of them with --pair A B or --pairs FILE",
                               ctx)
    if len(shapes) > 2:
        raise click.UsageError(f"give one or two SHAPES tables, not {len(shapes)} (many pairs: --pair A B, "
                               "repeated, or --pairs FILE)", ctx)
    if (de1 is None) != (de2 is None):
        raise click.UsageError("give both --de1 and --de2", ctx)
    if de1 is not None and (len(shapes) == 2 or frames is not None or pooled):
        raise click.UsageError("--de1/--de2 name the De columns of one table: not with two tables, pairs or "
                               "--frames", ctx)
    if len(shapes) == 1 and de1 is None and frames is None:
        raise click.UsageError("one SHAPES table needs --frames A B (two of its frames) or --de1 COL --de2 COL "
                               "(its De columns)", ctx)
    if patch_centers is not None and ctx.get_parameter_source("npatch") == ParameterSource.COMMANDLINE:
        raise click.UsageError("--patch-centers and --npatch: give one (the centres fix the number of patches)", ctx)
    if min_sep >= max_sep:
        raise click.UsageError(f"--min-sep {min_sep} must be less than --max-sep {max_sep}", ctx)
    if within is not None and not (0 <= within[0] < 360 and -90 <= within[1] <= 90 and within[2] > 0):
        raise click.UsageError(f"--within {' '.join(map(str, within))}: RA in [0, 360), Dec in [-90, 90] and a "
                               "radius > 0, in degrees", ctx)
    pairs = None
    if pooled:
        check_outputs(output, inputs=[pairs_file], plot=plot, overwrite=overwrite)
        pairs = [*pair_list, *(read_pairs_file(pairs_file) if pairs_file is not None else [])]
    inputs = [*shapes, *(name for pair in pairs or () for name in pair), pairs_file, patch_centers]
    check_outputs(output, inputs=inputs, plot=plot, overwrite=overwrite)
    options = CorrelateOptions(
        de_columns=(de1, de2) if de1 is not None else None, common_ids=common_ids, positions=positions,
        pixel_scale=pixel_scale, columns=columns, min_sep=min_sep, max_sep=max_sep, nbins=nbins, sep_units=sep_units,
        bin_slop=bin_slop, npatch=npatch, cross_patch_weight=cross_patch_weight, var_method=var_method,
        thresholds=thresholds, theta_edges=theta_edges, nboot=nboot, seed=seed,
        flagged="keep" if keep_flagged else "drop", within=tuple(within) if within else None)
    summary = correlate_files(shapes, output, options, pairs=pairs, frames=frames, patch_centers=patch_centers,
                              workers=workers, plot=plot, plots_dir=plots_dir, overwrite=overwrite)
    stats = summary["stats"]
    fracs = ", ".join(f">= {t:g}: {f:.3g}" for t, f in zip(stats["threshold"], stats["frac_ge"]))
    errors = (f"jackknife over {summary['npatch']} patches" if summary["var_method"] == "jackknife"
              else "shot-noise errors")
    pooled_from = f" from {summary['npairs']} pairs" if summary["npairs"] else ""
    log.info("%s: %d objects%s, %s; mean De = (%.3g +- %.2g, %.3g +- %.2g); fraction with |De| %s",
             "stdout" if output == "-" else output, summary["n"], pooled_from, errors, stats["de1_mean"],
             stats["de1_err"], stats["de2_mean"], stats["de2_err"], fracs)
