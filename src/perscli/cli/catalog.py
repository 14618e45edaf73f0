"""``perscli catalog``: a truth catalog of galaxies and stars for a field."""

from __future__ import annotations

import logging

import click
from click.core import ParameterSource

from ..instrument import ROMAN_N_SCA, ROMAN_SCA_SIZE
from ..scene.settings import CatalogOptions
from .helpers import FILE, PerscliCommand, check_outputs, deprecated_option, report_errors
from .options import (columns_opt, dec_opt, no_checksum_opt, output_opt, overwrite_opt, ra_opt, seed_opt,
                      settings_options, verbosity_opts)

log = logging.getLogger("perscli")

#: the defaults, written once (perscli.scene.settings)
D = CatalogOptions()


@click.command("catalog", cls=PerscliCommand,
               short_help="Draw a truth catalog of galaxies and stars for a field.")
@ra_opt("Centre of the square field: right ascension")
@dec_opt("Centre of the square field: declination")
@click.option("--size", type=click.FloatRange(min=0, max=3600, min_open=True, max_open=True), default=None,
              metavar="ARCMIN", help=f"Side of the square field on the tangent plane  [default: {D.size:g}].")
@click.option("--pointings", "pointings_table", metavar="POINTINGS.fits", default=None, type=FILE,
              help="Instead of a square: the union of the SCA footprints of every row of this pointings table "
                   "(perscli pointings, as render --pointings takes), each grown by --margin.")
# the older spelling: --footprints is a flag of perscli pointings (add each row's SCA corners)
@click.option("--footprints", "footprints", default=None, hidden=True, type=FILE,
              callback=deprecated_option("catalog --footprints POINTINGS.fits", "--pointings POINTINGS.fits"))
@click.option("--sca", type=click.IntRange(0, ROMAN_N_SCA), default=0, show_default=True, metavar="N",
              help=f"--pointings: the detector (1-{ROMAN_N_SCA}); 0: each row's own sca.")
@click.option("--margin", type=click.FloatRange(min=0, max=3600), default=None, metavar="ARCSEC",
              help="--pointings: grow each footprint by this much, so that objects just off a detector still "
                   f"spill light onto it  [default: {D.margin_arcsec:g}].")
@click.option("--bounds", type=int, nargs=4, default=None, metavar="XMIN XMAX YMIN YMAX",
              help=f"--pointings: the footprint of this cutout (1-indexed inclusive SCA pixels, as render "
                   f"--bounds) [default: the full {ROMAN_SCA_SIZE} x {ROMAN_SCA_SIZE}].")
@click.option("--galaxy-rows", "galaxy_rows", default=None, metavar="ROWS",
              help="--pointings: galaxies only in the footprints of these rows of the table (0-based, e.g. "
                   "3,4 or 3-9), stars in every row's: earlier exposures whose stars' light alone persists.")
@settings_options(CatalogOptions, "galaxy_density")
@click.option("--star-density", type=click.FloatRange(min=0), default=None, metavar="PER_ARCMIN2",
              help="Instead of the Galactic star model: power-law stars at this mean number per arcmin^2 "
                   "(Poisson, uniform; the paper: 2.5); not used with --gaia.")
@click.option("--star-param", "star_params", multiple=True, metavar="KEY=VALUE",
              help="Set a parameter of the Galactic star model (e.g. thin_height=300, mag_min=8, lf_scale=1.2; "
                   "the names are listed in the description). Repeatable.")
@click.option("--gaia", "gaia", multiple=True, metavar="FILE", type=FILE,
              help="Gaia DR2 reference-catalog chunk (LSST format; '-' for standard input): its stars in the "
                   "field replace the model stars. Repeatable.")
@columns_opt("the --gaia files", "id=source_id,coord_ra=ra_rad,coord_dec=dec_rad")
@no_checksum_opt
@seed_opt
@output_opt
@overwrite_opt
@verbosity_opts
@click.pass_context
@report_errors
def catalog(ctx, ra, dec, size, pointings_table, footprints, sca, margin, bounds, galaxy_rows, galaxy_density, star_density,
            star_params, gaia, columns, seed, output, overwrite):
    """Draw a truth catalog of galaxies and stars for a square field or detector footprints.

    The field is a square of --size arcmin on the tangent plane at (--ra,
    --dec), or with --pointings POINTINGS.fits the union of the SCA
    footprints (GalSim's Roman WCS) of every row of that table (for --sca N,
    or each row's own sca), each grown by --margin arcsec (default 30) so
    that objects just off an edge still spill light onto the detector: only
    what the exposures see is drawn.  Positions are uniform in solid angle
    (stars: at the model's density, which varies over the field) and counts
    are Poisson, at the same densities in both cases.
    Galaxies are exponential profiles: J129 (AB) from dN/dm ~ 10^(0.28 m)
    for 20 <= J <= 25.5 (deep near-infrared counts), J-H ~ N(0.30, 0.15),
    log10(hlr/arcsec) ~ N(log10(0.35) - 0.08 (J - 23), 0.2) within
    [0.08, 1.5], intrinsic g per component ~ N(0, 0.27) redrawn until
    |g| <= 0.7, no shear.

    Model stars (default) come from a Galactic structure model: the thin
    disc, thick disc and halo of Chang, Ko & Peng (2011; a fit of the
    whole-sky 2MASS counts) integrated along the line of sight, times a
    luminosity function in M_J calibrated on Gaia DR2 (M_J < 8) and taken
    from Juric et al. (2008) and Covey et al. (2008) for M dwarfs, so that
    their counts per magnitude and their rise towards the Galactic plane
    follow the real sky: at RA 10, Dec -44 (b = -73) 25 stars per deg^2
    brighter than J129 = 12, 122 brighter than 14 (Gaia DR2: 25, 126) and
    2.5 per arcmin^2 for 4 <= J <= 24.  The density varies over the field
    (model on a 0.5-degree grid, Poisson process thinned).  J-H per
    luminosity-function bin (Gaia stars for M_J < 4, the mean dwarf sequence
    fainter).  --star-param KEY=VALUE sets its parameters: sun_radius,
    sun_height, thin_height, thin_length, thick_height, thick_length (pc),
    thick_fraction, halo_fraction, halo_axis_ratio, halo_index,
    max_distance (pc), lf_scale, mag_min, mag_max (J129 AB, default 4 and
    24), dwarf_jh_sigma.  --star-density N draws instead power-law stars,
    J129 from dN/dm ~ 10^(0.15 m) for 10 <= J <= 24 at N per arcmin^2
    uniformly, J-H ~ N(0.45, 0.15) within [0, 1] (at the paper's 2.5 per
    arcmin^2, 215 per deg^2 brighter than J = 14: 1.7 times Gaia DR2 at
    b = -73).

    With --gaia, the stars are those of Gaia DR2 reference-catalog chunks
    (coord_ra/coord_dec in radians, fluxes in nJy) inside the field, with
    2MASS J, H from Gaia G and BP-RP (Evans et al. 2018) standing for J129,
    H158; stars without BP/RP get the median colour.

    Magnitudes in the other Roman filters are interpolated linearly in
    ln(wavelength) through J129 and H158.  The output is a FITS table
    'TRUTH': id, ra, dec, kind, mag_R062 ... mag_W146, hlr, e1, e2 (as
    galsim.Shear(g1, g2)), gaia_id; its header holds the field, the models
    and the seed (with --pointings also a table FOOTPRNT of their corners).
    The same seed gives the same catalog.

    A square field at the pointing of an exposure is not where its SCAs
    look (they lie up to 0.45 degrees from the centre of the focal plane):
    --pointings draws the catalogue where they land, and perscli render
    --dry-run shows how much of a catalogue a frame covers.

    \b
    Examples:
      perscli catalog --ra 10 --dec -44 -o cat.fits
      perscli catalog --ra 10 --dec -44 --size 150 --seed 7 --galaxy-density 1 -o cat_wide.fits
      perscli catalog --ra 10 --dec -44 --gaia 145649.fits --gaia 145650.fits -o cat_gaia.fits
      perscli catalog --ra 10 --dec -44 --galaxy-density 0 -o - | gzip > cat_stars.fits.gz
      perscli catalog --ra 150 --dec 2 --star-param thin_height=300 --star-param mag_min=10 -o cat_cosmos.fits
      perscli catalog --ra 10 --dec -44 --size 5 --star-density 20 -o cat_dense_stars.fits
      perscli pointings plan --ra 10 --dec -44 --n 2 --sca 7 -o cat_plan.fits
      perscli catalog --pointings cat_plan.fits --margin 30 --gaia 145649.fits --gaia 145650.fits -o cat_sca7.fits
      perscli catalog --pointings cat_plan.fits --sca 1 --bounds 1 128 1 128 -o cat_sca1_cut.fits

    (145649.fits and 145650.fits are chunks of the Gaia DR2 reference
    catalog in LSST's format, the two that cover RA 10, Dec -44,
    downloaded into the current folder.)
    """
    from ..scene.catalog import DEFAULT_MARGIN_ARCSEC, make_truth_catalog_file
    from ..scene.starcounts import galactic_star_model

    given = {name for name in ctx.params
             if ctx.get_parameter_source(name) not in (ParameterSource.DEFAULT, ParameterSource.DEFAULT_MAP)}
    if footprints is not None and pointings_table is not None:
        raise click.UsageError("--pointings and --footprints name the same table (--footprints is its older "
                               "spelling): give --pointings", ctx)
    footprints = pointings_table if pointings_table is not None else footprints
    if footprints is not None:
        wrong = [name for name in ("ra", "dec", "size") if name in given]
        if wrong:
            raise click.UsageError(f"--{wrong[0]} is for a square field, not --pointings", ctx)
    else:
        wrong = [name for name in ("sca", "margin", "bounds", "galaxy_rows") if name in given]
        if wrong:
            raise click.UsageError(f"--{wrong[0].replace('_', '-')} is for --pointings", ctx)
        for name, value in (("ra", ra), ("dec", dec)):
            if value is None:
                raise click.UsageError(f"Missing option '--{name}': give --ra and --dec (a square field) or "
                                       "--pointings POINTINGS.fits", ctx)
    if star_params and star_density is not None:
        raise click.UsageError("--star-param sets the Galactic star model and --star-density selects power-law "
                               "stars: give one of them", ctx)
    if star_params and gaia:
        raise click.UsageError("--star-param is for model stars, not --gaia", ctx)
    star_model = galactic_star_model(star_params) if star_density is None else None
    check_outputs(output, inputs=[*gaia, footprints], overwrite=overwrite)
    if footprints is not None:
        table = make_truth_catalog_file(output, footprints=footprints, sca=sca, bounds=bounds,
                                        margin_arcsec=DEFAULT_MARGIN_ARCSEC if margin is None else margin,
                                        overwrite=overwrite, galaxy_density=galaxy_density,
                                        star_density=star_density, star_model=star_model, gaia=gaia or None,
                                        seed=seed, columns=columns, galaxy_rows=_rows(galaxy_rows, ctx))
    else:
        table = make_truth_catalog_file(output, ra, dec, size, overwrite=overwrite, galaxy_density=galaxy_density,
                                        star_density=star_density, star_model=star_model, gaia=gaia or None,
                                        seed=seed, columns=columns)
    # what was written, in one line on stderr (stdout may be the table itself), unless -q
    verbosity = (ctx.find_root().obj or {}).get("verbosity", 0)
    if verbosity >= 0:
        meta = table.meta
        stars = "gaia" if meta["STARSRC"] == "gaia" else meta["STARMOD"]
        click.echo(f"{'stdout' if output == '-' else output}: {len(table)} rows written ({meta['NGAL']} galaxies, "
                   f"{meta['NSTAR']} {stars} stars in {meta['FIELDAR']:.6g} arcmin^2)", err=True)
    if gaia and table.meta["NSTAR"] == 0:
        log.warning("no Gaia star of %s lies inside the field; check %s", ", ".join(gaia),
                    "--pointings" if footprints else "--ra/--dec/--size")


def _rows(text, ctx):
    """'3,4' or '3-9' (0-based rows) as a list of ints; None for None."""
    if text is None:
        return None
    rows = []
    try:
        for part in str(text).split(","):
            part = part.strip()
            if "-" in part[1:]:
                a, b = part.split("-", 1)
                rows.extend(range(int(a), int(b) + 1))
            elif part:
                rows.append(int(part))
    except ValueError:
        raise click.BadParameter(f"{text!r}: row numbers (0-based) such as 3,4 or 3-9", ctx,
                                 param_hint="--galaxy-rows") from None
    if not rows or min(rows) < 0:
        raise click.BadParameter(f"{text!r}: row numbers (0-based) such as 3,4 or 3-9", ctx,
                                 param_hint="--galaxy-rows")
    return sorted(set(rows))
