"""``perscli catalog``: a truth catalog of galaxies and stars for a field."""

from __future__ import annotations

import logging

import click

from .helpers import check_outputs, report_errors
from .options import dec_opt, output_opt, overwrite_opt, ra_opt, seed_opt, verbosity_opts

log = logging.getLogger("perscli")


@click.command("catalog", short_help="Draw a truth catalog of galaxies and stars for a field.")
@ra_opt
@dec_opt
@click.option("--size", type=click.FloatRange(min=0, max=3600, min_open=True, max_open=True), default=10.0,
              show_default=True, metavar="ARCMIN", help="Side of the square field on the tangent plane.")
@click.option("--galaxy-density", type=click.FloatRange(min=0), default=40.0, show_default=True,
              metavar="PER_ARCMIN2", help="Mean number of galaxies per arcmin^2 (Poisson).")
@click.option("--star-density", type=click.FloatRange(min=0), default=2.5, show_default=True,
              metavar="PER_ARCMIN2", help="Mean number of model stars per arcmin^2 (Poisson); not used with --gaia.")
@click.option("--gaia", "gaia", multiple=True, metavar="FILE",
              help="Gaia DR2 reference-catalog chunk (LSST format; '-' for standard input): its stars in the "
                   "field replace the model stars. Repeatable.")
@seed_opt
@output_opt
@overwrite_opt
@verbosity_opts
@report_errors
def catalog(ra, dec, size, galaxy_density, star_density, gaia, seed, output, overwrite):
    """Draw a truth catalog of galaxies and stars for a square field.

    The field is a square of --size arcmin on the tangent plane at (--ra,
    --dec); positions are uniform in solid angle and counts are Poisson.
    Galaxies are exponential profiles: J129 (AB) from dN/dm ~ 10^(0.28 m)
    for 20 <= J <= 25.5 (deep near-infrared counts), J-H ~ N(0.30, 0.15),
    log10(hlr/arcsec) ~ N(log10(0.35) - 0.08 (J - 23), 0.2) within
    [0.08, 1.5], intrinsic g per component ~ N(0, 0.27) redrawn until
    |g| <= 0.7, no shear.  Model stars: J129 from dN/dm ~ 10^(0.15 m) for
    10 <= J <= 24 (215 per deg^2 brighter than J = 14 at 2.5 per arcmin^2),
    J-H ~ N(0.45, 0.15) within [0, 1].

    With --gaia, the stars are those of Gaia DR2 reference-catalog chunks
    (coord_ra/coord_dec in radians, fluxes in nJy) inside the field, with
    2MASS J, H from Gaia G and BP-RP (Evans et al. 2018) standing for J129,
    H158; stars without BP/RP get the median colour.

    Magnitudes in the other Roman filters are interpolated linearly in
    ln(wavelength) through J129 and H158.  The output is a FITS table
    'TRUTH': id, ra, dec, kind, mag_R062 ... mag_W146, hlr, e1, e2 (as
    galsim.Shear(g1, g2)), gaia_id; its header holds the field, the models
    and the seed.  The same seed gives the same catalog.

    \b
    Examples:
      perscli catalog --ra 10 --dec -44 -o truth.fits
      perscli catalog --ra 10 --dec -44 --size 150 --seed 7 -o field.fits
      perscli catalog --ra 10 --dec -44 --gaia 145649.fits --gaia 145650.fits -o truth.fits
      perscli catalog --ra 10 --dec -44 --galaxy-density 0 -o - | gzip > stars.fits.gz
    """
    from ..scene.catalog import make_truth_catalog_file

    check_outputs(output, inputs=gaia, overwrite=overwrite)
    table = make_truth_catalog_file(output, ra, dec, size, overwrite=overwrite, galaxy_density=galaxy_density,
                                    star_density=star_density, gaia=gaia or None, seed=seed)
    log.info("%s: %d galaxies and %d %s stars in %.6g arcmin^2",
             "stdout" if output == "-" else output, table.meta["NGAL"], table.meta["NSTAR"],
             table.meta["STARSRC"], table.meta["FIELDAR"])
    if gaia and table.meta["NSTAR"] == 0:
        log.warning("no Gaia star of %s lies inside the field; check --ra/--dec/--size", ", ".join(gaia))
