"""Roman magnitudes of Gaia DR2 stars: Gaia's AB fluxes to 2MASS J, H and on to Roman's J129, H158.

Both the Gaia truth catalogues (:mod:`perscli.scene.catalog`) and the
Gaia reference-catalogue chunks of the star counts
(:mod:`perscli.scene.starcounts`) convert through :func:`gaia_roman_jh`.
"""

from __future__ import annotations

import numpy as np

#: Gaia DR2 zero points (Vega, AB), Evans et al. 2018 / Gaia DR2 documentation table 5.3
GAIA_DR2_ZP = {"G": (25.6884, 25.7934), "BP": (25.3514, 25.3806), "RP": (24.7619, 25.1161)}

#: Gaia DR2 to 2MASS, G - band = c0 + c1 X + c2 X^2 with X = BP-RP (Vega), and the range of X fitted
GAIA_TO_2MASS = {"J": ((-0.01883, 1.394, -0.07893), (-0.5, 5.5)),
                 "H": ((-0.1621, 1.968, -0.1328), (0.25, 5.0))}

#: 2MASS AB - Vega (Blanton & Roweis 2007)
TWOMASS_AB_MINUS_VEGA = {"J": 0.91, "H": 1.39}

#: BP-RP (Vega) for Gaia stars without BP/RP when no star read has both: the median of the DR2 stars
#: of the Gaia DR2 chunks 145649 and 145650 (RA 10, Dec -44, Galactic latitude -73)
DEFAULT_BP_RP = 1.43

#: AB magnitude of 1 nJy
AB_NJY_ZP = 31.4


def ab_magnitude(flux_njy):
    """AB magnitude of a flux density in nJy (NaN for fluxes that are not positive)."""
    flux = np.asarray(flux_njy, dtype=np.float64)
    with np.errstate(divide="ignore", invalid="ignore"):
        return np.where(flux > 0, AB_NJY_ZP - 2.5 * np.log10(np.where(flux > 0, flux, 1.0)), np.nan)


def gaia_ab_to_vega(band: str, mag_ab):
    """A Gaia DR2 AB magnitude in Gaia's Vega system (band 'G', 'BP' or 'RP')."""
    vega, ab = GAIA_DR2_ZP[band]
    return np.asarray(mag_ab) - (ab - vega)


def gaia_to_2mass(g_vega, bp_rp_vega) -> tuple:
    """2MASS (J, H) in Vega magnitudes from Gaia DR2 G and BP-RP (Vega), colours clipped to the fits' ranges."""
    out = []
    for band in ("J", "H"):
        (c0, c1, c2), (lo, hi) = GAIA_TO_2MASS[band]
        x = np.clip(bp_rp_vega, lo, hi)
        out.append(np.asarray(g_vega) - (c0 + c1 * x + c2 * x * x))
    return tuple(out)


def gaia_roman_jh(g_njy, bp_njy, rp_njy, *, fallback_bp_rp: float | None = None) -> tuple:
    """Roman (J129, H158) AB magnitudes of Gaia DR2 stars from their AB fluxes in nJy.

    Parameters
    ----------
    g_njy, bp_njy, rp_njy : array_like
        phot_{g,bp,rp}_mean_flux of an LSST-format Gaia DR2 reference catalog.
    fallback_bp_rp : float, optional
        BP-RP (Vega) for stars without BP or RP flux; default the median of
        those with both (:data:`DEFAULT_BP_RP` if none has).

    Returns
    -------
    mag_j, mag_h : ndarray
        AB; NaN where G is not positive.
    bp_rp : ndarray
        BP-RP (Vega) used, before clipping.
    has_colour : ndarray of bool
        Stars with their own BP-RP.
    """
    g_vega = gaia_ab_to_vega("G", ab_magnitude(g_njy))
    bp_rp = gaia_ab_to_vega("BP", ab_magnitude(bp_njy)) - gaia_ab_to_vega("RP", ab_magnitude(rp_njy))
    has_colour = np.isfinite(bp_rp)
    if fallback_bp_rp is None:
        fallback_bp_rp = float(np.median(bp_rp[has_colour])) if has_colour.any() else DEFAULT_BP_RP
    bp_rp = np.where(has_colour, bp_rp, fallback_bp_rp)
    j_vega, h_vega = gaia_to_2mass(g_vega, bp_rp)
    return j_vega + TWOMASS_AB_MINUS_VEGA["J"], h_vega + TWOMASS_AB_MINUS_VEGA["H"], bp_rp, has_colour
