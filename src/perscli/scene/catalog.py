"""Truth catalogs: the galaxies and stars of a field, with magnitudes in every Roman filter.

A field is a square of side ``size`` arcmin on the gnomonic (TAN) tangent
plane at its centre, east-west and north-south sides: standard coordinates
|xi|, |eta| <= tan(size/2), so the sides through the centre subtend exactly
``size``.  Its area is the solid angle of that square,
4 arcsin(a^2 / (1 + a^2)) with a = tan(size/2) (99.9999 arcmin^2 for 10').

Positions are uniform in solid angle: points uniform in the tangent-plane
square are kept with probability (1 + xi^2 + eta^2)^(-3/2), the ratio of the
sphere's area element to the plane's, and deprojected.  (Uniform in the plane
alone would over-weight the corners by 1.5 (xi^2 + eta^2): 6e-6 for 10', but
1% for a 5-degree field.)  Counts are Poisson(density x area).

**Galaxies** (:class:`GalaxyModel`): exponential profiles.  J129 (AB) from
dN/dm ∝ 10^(0.28 m) for 20 <= J <= 25.5, the slope of deep near-infrared
(J, H) galaxy counts fainter than ~20 mag (Windhorst et al. 2011, ApJS 193,
27; CANDELS).  The paper drew its galaxies from a CANDELS-based catalogue
that is not public; this law with the paper's 40 galaxies/arcmin^2 gives
7.0 per arcmin^2 brighter than J = 23, 14.5 brighter than J = 24 and 28.7
brighter than J = 25.  J - H ~ N(0.30, 0.15).  Half-light radius:
log10(hlr / arcsec) ~ N(log10(0.35) - 0.08 (J - 23), 0.2), clipped to
[0.08, 1.5] arcsec.  Intrinsic ellipticity: (e1, e2) each N(0, 0.27), the
pair redrawn until |e| <= 0.7 (the paper's truncation); the truncated
distribution has a per-component standard deviation of 0.2532.  e1, e2 are
reduced-shear-style g (|g| = (a - b)/(a + b)), to be used as
``galsim.Shear(g1=e1, g2=e2)``.  No shear is applied.

**Stars** (default: :class:`perscli.scene.starcounts.GalacticStarModel`):
point sources from a Galactic structure model.  The thin disc, thick disc
and halo of Chang, Ko & Peng (2011, ApJ 740, 34; a fit of the whole-sky
2MASS counts), integrated along the line of sight at each position, times a
luminosity function in M_J calibrated on the Gaia DR2 chunks of
the Gaia DR2 chunks 145649 and 145650 (M_J < 8) and taken from Juric et al. (2008) and Covey
et al. (2008) for M dwarfs: the counts per J129 magnitude, and their change
with Galactic latitude and longitude, follow the real sky (module
:mod:`perscli.scene.starcounts` for the sources, constants and checks).  At
RA 10, Dec -44 (b = -73) it gives 24.7 stars per deg^2 brighter than J = 12
and 122 brighter than 14 (Gaia DR2 there: 25 and 126), and 2.5 per arcmin^2
for 4 <= J <= 24.  The density varies over the field: the model is evaluated
on a grid (0.5 deg) and a Poisson process thinned
(:func:`perscli.scene.starcounts.draw_galactic_stars`).  J - H per
luminosity-function bin: of the Gaia stars for M_J < 4, of the mean dwarf
sequence (Pecaut & Mamajek 2013) fainter.  Its parameters can be changed by
name (:func:`perscli.scene.starcounts.galactic_star_model`).

**Power-law stars** (:class:`StarModel`, with an explicit ``star_density``):
J129 (AB) from dN/dm ∝ 10^(0.15 m) for 10 <= J <= 24 at a uniform density,
an approximation to 2MASS and Besançon-model counts at high Galactic
latitude: with the paper's 2.5 stars/arcmin^2 it gives 215 stars per deg^2
brighter than J = 14, 1070 per deg^2 brighter than J = 18 and 0.61 per
arcmin^2 brighter than J = 20 (1.7 times the Gaia counts brighter than 14 at
RA 10, Dec -44, 2.9 times those brighter than 12).  J - H ~ N(0.45, 0.15)
clipped to [0, 1].  Kept for tests and studies that need many stars in a
small field.

**Gaia stars** (:func:`read_gaia_stars`), instead of model stars: Gaia DR2
reference-catalog chunks (LSST format: coord_ra/coord_dec in radians,
phot_{g,bp,rp}_mean_flux in nJy, AB).  AB magnitudes m = 31.4 - 2.5 log10(f/nJy)
are moved to Gaia's Vega system with the differences of the DR2 zero points
(Evans et al. 2018, A&A 616, A4; Gaia DR2 documentation, table 5.3):
G 25.7934 (AB) vs 25.6884 (Vega), BP 25.3806 vs 25.3514, RP 25.1161 vs
24.7619, so G_Vega = G_AB - 0.105 and (BP-RP)_Vega = (BP-RP)_AB + 0.325.
2MASS J and H follow from the DR2 relations (Evans et al. 2018, table A.2):
G - J = -0.01883 + 1.394 X - 0.07893 X^2 and
G - H = -0.1621 + 1.968 X - 0.1328 X^2 with X = (BP-RP)_Vega, X clipped to
the ranges over which they were fitted (table A.1): -0.5 to 5.5 for J, 0.25
to 5.0 for H.  Then J_AB = J_Vega + 0.91 and H_AB = H_Vega + 1.39 (Blanton &
Roweis 2007, AJ 133, 734), and 2MASS J, H stand for Roman J129, H158 (the
bands are similar; colour terms of a few hundredths of a magnitude are
neglected).  Stars without BP or RP flux (NaN or <= 0) get the median colour
of the stars read that have both.  Positions are at the catalogue epoch
(proper motions are not applied).

**Other filters**: each magnitude is interpolated (or extrapolated) linearly
in ln(effective wavelength) through J129 and H158 (wavelengths in
:data:`perscli.scene.EFFECTIVE_WAVELENGTH_UM`): a power-law spectrum, simple
but monotonic and exact at J129 and H158.

**Footprints** instead of a square: the union of detector footprints (convex
quadrilaterals on the sky, e.g. the SCA corners of
:func:`perscli.scene.footprints.sca_footprint`), each grown by a margin
(default :data:`DEFAULT_MARGIN_ARCSEC`) so that objects just off a
detector's edge still spill their light onto it
(:class:`perscli.scene.regions.FootprintUnion`).  Objects are a Poisson
process of the same densities drawn on the union's bounding box on the
tangent plane and kept inside the union: the densities per unit solid angle
are exact, and only the area the exposures see is drawn (not a square
around them all).  Gaia stars are those inside the union.

The random numbers: ``numpy.random.Generator(PCG64)`` streams spawned from
``SeedSequence(seed)``, one for galaxies and one for stars, so that changing
the star model (or its parameters, or using Gaia) leaves the galaxies
unchanged.

The catalogue's FITS file (:func:`truth_hdulist`, :func:`write_truth_catalog`) is
built in :mod:`perscli.scene.truthtable`.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass, field

import numpy as np
from astropy.table import Table

from .. import PerscliError
from ..instrument import ROMAN_FILTERS
from ..io.output import check_output
from ..io.tables import read_table
from . import EFFECTIVE_WAVELENGTH_UM, check_position, deproject, project
from .photometry import DEFAULT_BP_RP, gaia_roman_jh
from .pointings import pointings_footprints
from .regions import FootprintUnion
from .settings import CatalogOptions
from .starcounts import GalacticStarModel, draw_galactic_stars, star_density as model_density
from .truthtable import _COLUMN_INFO, write_truth_catalog

#: arcmin^2 per steradian
ARCMIN2_PER_SR = (180.0 * 60.0 / math.pi) ** 2

#: [arcmin^-2] density of power-law stars when a StarModel is given without one: the paper's
DEFAULT_STAR_DENSITY = 2.5

MAG_COLUMNS = tuple(f"mag_{f}" for f in ROMAN_FILTERS)

COLUMNS = ("id", "ra", "dec", "kind", *MAG_COLUMNS, "hlr", "e1", "e2", "gaia_id")

#: default growth of each footprint, arcsec (stars of J < 14, ~120 per deg^2 at high latitude, spill only
#: their faint outer halo beyond it)
DEFAULT_MARGIN_ARCSEC = CatalogOptions.margin_arcsec


@dataclass(frozen=True)
class GalaxyModel:
    """The galaxy population (see the module docstring for the sources)."""

    mag_slope: float = 0.28     #: d log10 N / dm of J129
    mag_min: float = 20.0       #: brightest J129 (AB)
    mag_max: float = 25.5       #: faintest J129 (AB)
    jh_mean: float = 0.30       #: mean J - H
    jh_sigma: float = 0.15      #: scatter of J - H
    hlr_at_23: float = 0.35     #: median half-light radius at J = 23 (arcsec)
    hlr_slope: float = -0.08    #: d log10(hlr) / dJ
    hlr_sigma: float = 0.2      #: scatter of log10(hlr)
    hlr_min: float = 0.08       #: clip (arcsec)
    hlr_max: float = 1.5        #: clip (arcsec)
    e_sigma: float = 0.27       #: per-component scatter of the intrinsic ellipticity g
    e_max: float = 0.7          #: |g| above this is redrawn


@dataclass(frozen=True)
class StarModel:
    """The power-law star population, used with an explicit star density (see the module docstring)."""

    mag_slope: float = 0.15
    mag_min: float = 10.0
    mag_max: float = 24.0
    jh_mean: float = 0.45
    jh_sigma: float = 0.15
    jh_min: float = 0.0
    jh_max: float = 1.0


@dataclass(frozen=True)
class Field:
    """A square field on the tangent plane at (ra, dec).

    Attributes
    ----------
    ra, dec : float
        Centre in degrees.
    size : float
        Side in arcmin.
    """

    ra: float
    dec: float
    size: float = CatalogOptions.size

    def __post_init__(self):
        check_position(self.ra, self.dec, "field centre")
        if not (0.0 < self.size < 3600.0):
            raise PerscliError(f"field size {self.size} arcmin: must be more than 0 and less than 3600 "
                               "(60 degrees)")
        object.__setattr__(self, "ra", float(self.ra) % 360.0)

    @property
    def half_width(self) -> float:
        """Half-side in standard coordinates (radians on the tangent plane)."""
        return math.tan(math.radians(self.size / 60.0) / 2.0)

    @property
    def area(self) -> float:
        """Solid angle in arcmin^2."""
        a2 = self.half_width ** 2
        return 4.0 * math.asin(a2 / (1.0 + a2)) * ARCMIN2_PER_SR

    def contains(self, ra, dec) -> np.ndarray:
        """Which of the positions (degrees) lie inside the field."""
        xi, eta = project(self.ra, self.dec, ra, dec)
        a = self.half_width
        with np.errstate(invalid="ignore"):
            return (np.abs(xi) <= a) & (np.abs(eta) <= a)

    def poisson_positions(self, rng: np.random.Generator, density: float) -> tuple:
        """Poisson(density x area) positions uniform in solid angle over the field: (ra, dec) in degrees."""
        n = int(rng.poisson(density * self.area))
        return self.sample(rng, n)

    def sample(self, rng: np.random.Generator, n: int) -> tuple:
        """``n`` positions uniform in solid angle over the field: (ra, dec) in degrees."""
        a = self.half_width
        xi = np.empty(0)
        eta = np.empty(0)
        while xi.size < n:
            m = int((n - xi.size) * 1.05) + 16
            x = rng.uniform(-a, a, m)
            y = rng.uniform(-a, a, m)
            keep = rng.random(m) < (1.0 + x * x + y * y) ** -1.5
            xi = np.concatenate([xi, x[keep]])
            eta = np.concatenate([eta, y[keep]])
        return deproject(self.ra, self.dec, xi[:n], eta[:n])


# -- magnitude, size and shape laws -------------------------------------------------------------

def power_law_magnitudes(rng: np.random.Generator, n: int, slope: float, m_min: float,
                         m_max: float) -> np.ndarray:
    """Magnitudes drawn from dN/dm ∝ 10^(slope m) on [m_min, m_max] (inverse CDF)."""
    lo, hi = 10.0 ** (slope * m_min), 10.0 ** (slope * m_max)
    return np.log10(lo + rng.random(n) * (hi - lo)) / slope


def cumulative_fraction(m, slope: float, m_min: float, m_max: float):
    """Fraction of a dN/dm ∝ 10^(slope m) population on [m_min, m_max] brighter than m."""
    m = np.clip(m, m_min, m_max)
    lo, hi = 10.0 ** (slope * m_min), 10.0 ** (slope * m_max)
    return (10.0 ** (slope * m) - lo) / (hi - lo)


def truncated_ellipticities(rng: np.random.Generator, n: int, sigma: float, e_max: float) -> tuple:
    """(e1, e2), each N(0, sigma), pairs redrawn until |e| <= e_max."""
    e = rng.normal(0.0, sigma, (n, 2))
    bad = np.flatnonzero(np.hypot(e[:, 0], e[:, 1]) > e_max)
    while bad.size:
        e[bad] = rng.normal(0.0, sigma, (bad.size, 2))
        bad = bad[np.hypot(e[bad, 0], e[bad, 1]) > e_max]
    return e[:, 0].copy(), e[:, 1].copy()


def truncated_sigma(sigma: float, e_max: float) -> float:
    """Per-component standard deviation of :func:`truncated_ellipticities`.

    |e|^2 of an isotropic 2-D Gaussian is exponential with mean 2 sigma^2;
    the mean of an exponential truncated at T = e_max^2 is
    2 sigma^2 - T exp(-T/2sigma^2) / (1 - exp(-T/2sigma^2)), half of it per
    component.
    """
    mean = 2.0 * sigma ** 2
    t = e_max ** 2
    q = math.exp(-t / mean)
    return math.sqrt((mean - t * q / (1.0 - q)) / 2.0)


def filter_magnitudes(mag_j, mag_h) -> dict:
    """Magnitudes in every Roman filter, linear in ln(wavelength) through J129 and H158."""
    mag_j, mag_h = np.asarray(mag_j, dtype=np.float64), np.asarray(mag_h, dtype=np.float64)
    lj, lh = math.log(EFFECTIVE_WAVELENGTH_UM["J129"]), math.log(EFFECTIVE_WAVELENGTH_UM["H158"])
    out = {}
    for name in ROMAN_FILTERS:
        t = (math.log(EFFECTIVE_WAVELENGTH_UM[name]) - lj) / (lh - lj)
        out[name] = mag_j + t * (mag_h - mag_j)
    out["J129"], out["H158"] = mag_j.copy(), mag_h.copy()
    return out


def draw_galaxies(rng: np.random.Generator, fld, density: float, model: GalaxyModel) -> dict:
    """A Poisson process of galaxies of ``model``, ``density`` per arcmin^2, in ``fld``: columns as arrays.

    ``fld`` is a :class:`Field` or a :class:`~perscli.scene.regions.FootprintUnion`.
    """
    ra, dec = fld.poisson_positions(rng, density)
    n = len(ra)
    mag_j = power_law_magnitudes(rng, n, model.mag_slope, model.mag_min, model.mag_max)
    mag_h = mag_j - rng.normal(model.jh_mean, model.jh_sigma, n)
    log_hlr = rng.normal(math.log10(model.hlr_at_23) + model.hlr_slope * (mag_j - 23.0), model.hlr_sigma)
    hlr = np.clip(10.0 ** log_hlr, model.hlr_min, model.hlr_max)
    e1, e2 = truncated_ellipticities(rng, n, model.e_sigma, model.e_max)
    return {"ra": ra, "dec": dec, "mag_j": mag_j, "mag_h": mag_h, "hlr": hlr, "e1": e1, "e2": e2,
            "gaia_id": np.full(n, -1, dtype=np.int64)}


def draw_stars(rng: np.random.Generator, fld, density: float, model: StarModel) -> dict:
    """A Poisson process of power-law stars, ``density`` per arcmin^2, in ``fld`` (Field or FootprintUnion)."""
    ra, dec = fld.poisson_positions(rng, density)
    n = len(ra)
    mag_j = power_law_magnitudes(rng, n, model.mag_slope, model.mag_min, model.mag_max)
    jh = np.clip(rng.normal(model.jh_mean, model.jh_sigma, n), model.jh_min, model.jh_max)
    return _point_sources(ra, dec, mag_j, mag_j - jh, np.full(n, -1, dtype=np.int64))


def _point_sources(ra, dec, mag_j, mag_h, gaia_id) -> dict:
    n = len(ra)
    return {"ra": ra, "dec": dec, "mag_j": mag_j, "mag_h": mag_h, "hlr": np.zeros(n), "e1": np.zeros(n),
            "e2": np.zeros(n), "gaia_id": gaia_id}


# -- Gaia ---------------------------------------------------------------------------------------

GAIA_COLUMNS = ("id", "coord_ra", "coord_dec", "phot_g_mean_flux", "phot_bp_mean_flux", "phot_rp_mean_flux")


@dataclass
class GaiaStars:
    """Gaia stars inside a field, with the bookkeeping written into the catalog header."""

    columns: dict
    inputs: list = field(default_factory=list)   #: (name, DATASUM) per file
    n_read: int = 0            #: rows read (duplicates across files counted once)
    n_no_flux: int = 0         #: rows without a positive G flux (dropped)
    n_median_colour: int = 0   #: stars in the field given the median colour
    median_bp_rp: float = DEFAULT_BP_RP


def _check_unique_sources(label: str, ids) -> None:
    """Refuse a reference-catalog chunk that holds a source twice: each source is one row of its chunk, so a
    repeated id is a damaged or concatenated file (and which of its rows is right cannot be told)."""
    ids = np.asarray(ids, dtype=np.int64)
    s = np.sort(ids)
    dup = s[1:][s[1:] == s[:-1]]
    if len(dup):
        raise PerscliError(f"{label}: source id {int(dup[0])} appears more than once ({len(np.unique(dup))} "
                           "repeated id(s)); a reference-catalog chunk holds each source once: re-download the "
                           "chunk, or drop the repeated rows")


def read_gaia_stars(paths, fld, *, stdin=None, columns=None) -> GaiaStars:
    """The stars of Gaia DR2 reference-catalog chunks that lie inside ``fld``.

    Parameters
    ----------
    paths : sequence of str
        FITS files (LSST reference-catalog format), '-' for standard input.
    fld : Field or FootprintUnion
        Only stars inside it (its ``contains``) are kept.
    columns : dict, optional
        Column mapping {perscli name: file column} (names of :data:`GAIA_COLUMNS`)
        for a chunk whose columns are named otherwise; units are not converted.

    Raises
    ------
    PerscliError
        A file that cannot be read, lacks a column, or has positions or
        fluxes in other units than radians and nJy.
    """
    chunks = {k: [] for k in GAIA_COLUMNS}
    inputs = []
    for name in paths:
        table = read_table(name, what="Gaia reference catalog", stdin=stdin, columns=columns or {},
                           known=GAIA_COLUMNS)
        for col in GAIA_COLUMNS:
            values = table.column(col, kind="integer" if col == "id" else "number", needed=GAIA_COLUMNS)
            unit = table.unit(col)
            expected = "rad" if col.startswith("coord") else ("nJy" if col.startswith("phot") else None)
            if expected and unit and unit != expected:
                raise PerscliError(f"{table.label}: column '{col}' is in '{unit}' but perscli reads Gaia "
                                   f"reference catalogs with {col} in '{expected}' (LSST format): "
                                   "check that this is such a catalog")
            chunks[col].append(values)
        _check_unique_sources(table.label, chunks["id"][-1])
        inputs.append((name, table.datasum))
    cols = {k: np.concatenate(v) if v else np.empty(0) for k, v in chunks.items()}
    ids = cols["id"].astype(np.int64)
    # chunks of a sky index do not overlap, but the same file given twice must not double its stars; a source in
    # two files with other positions or fluxes is no copy, and which one is right cannot be told
    _, first, inverse = np.unique(ids, return_index=True, return_inverse=True)
    for col in GAIA_COLUMNS:
        values = np.asarray(cols[col], dtype=np.float64)
        kept = values[first][inverse.ravel()]
        differ = ~((values == kept) | (np.isnan(values) & np.isnan(kept)))
        if np.any(differ):
            k = int(np.flatnonzero(differ)[0])
            raise PerscliError(f"source id {int(ids[k])} is in more than one --gaia file with another {col} "
                               f"({kept[k]:.10g} and {values[k]:.10g}): give each chunk once (chunks of a "
                               "reference catalog do not overlap)")
    first.sort()
    cols = {k: v[first] for k, v in cols.items()}
    n_read = first.size
    ra = np.degrees(cols["coord_ra"]) % 360.0
    dec = np.degrees(cols["coord_dec"])
    mag_j, mag_h, bp_rp, has_colour = gaia_roman_jh(cols["phot_g_mean_flux"], cols["phot_bp_mean_flux"],
                                                    cols["phot_rp_mean_flux"])
    median = float(np.median(bp_rp[has_colour])) if has_colour.any() else DEFAULT_BP_RP
    bright = np.isfinite(mag_j)
    keep = bright & fld.contains(ra, dec)
    return GaiaStars(
        columns=_point_sources(ra[keep], dec[keep], mag_j[keep], mag_h[keep], cols["id"][keep].astype(np.int64)),
        inputs=inputs, n_read=int(n_read), n_no_flux=int((~bright).sum()),
        n_median_colour=int((keep & ~has_colour).sum()), median_bp_rp=median)


# -- the catalog --------------------------------------------------------------------------------

def make_truth_catalog(ra: float | None = None, dec: float | None = None, size: float | None = None, *,
                       footprints=None, margin_arcsec: float = DEFAULT_MARGIN_ARCSEC, galaxy_footprints=None,
                       galaxy_density: float = CatalogOptions.galaxy_density, star_density: float | None = None,
                       gaia=None, seed: int = 1, galaxy_model: GalaxyModel = GalaxyModel(), star_model=None,
                       stdin=None, columns=None):
    """A truth catalog of galaxies and stars for a square field or for detector footprints.

    Parameters
    ----------
    ra, dec : float, optional
        Field centre in degrees (needed for a square field).  With
        ``footprints``: the tangent point of the plane they are drawn on
        (default: the mean direction of their corners).
    size : float, optional
        Side of the square field in arcmin (default 10); not with ``footprints``.
    footprints : sequence of (ra, dec), optional
        Instead of a square: the corners (degrees, in order around each) of
        convex footprints, e.g. ``[sca_footprint(p, sca) for p in pointings]``;
        objects are drawn only in their union, each grown by ``margin_arcsec``.
    margin_arcsec : float
        Growth of each footprint in arcsec (default, or None: :data:`DEFAULT_MARGIN_ARCSEC`).
    galaxy_footprints : sequence of (ra, dec), optional
        With ``footprints``: galaxies only in these (each grown by the
        margin), stars in all of ``footprints`` (a study's earlier exposures
        need their stars only).
    galaxy_density : float
        Mean number of galaxies per arcmin^2 (the paper: 40).
    star_density : float, optional
        Power-law stars (:class:`StarModel`) at this mean number per
        arcmin^2 (the paper: 2.5), uniform over the field.  Default: the
        Galactic model, whose density varies with position.  Unused with ``gaia``.
    gaia : sequence of str, optional
        Gaia DR2 reference-catalog chunks: their stars in the field replace the model stars.
    seed : int
        Random seed; the same seed (and inputs) gives the same catalog.
    galaxy_model : GalaxyModel
        Galaxy population parameters (default: the module docstring).
    star_model : GalacticStarModel or StarModel, optional
        The star population: default the Galactic model
        (:class:`perscli.scene.starcounts.GalacticStarModel`, its parameters
        settable by name with :func:`perscli.scene.starcounts.galactic_star_model`);
        a :class:`StarModel` draws power-law stars at ``star_density``
        (2.5 per arcmin^2 if not given).
    stdin : binary file, optional
        Stream for a Gaia file given as '-'.
    columns : dict, optional
        Column mapping of the Gaia files (:func:`read_gaia_stars`).

    Returns
    -------
    astropy.table.Table
        Columns :data:`COLUMNS` (galaxies first, then stars; ``id`` from 1),
        with units; ``meta`` holds the header keywords (field or footprints,
        densities, models (STARMOD galactic or powerlaw, and their
        parameters), counts, Gaia inputs as GA001/GA001DS..., SEED);
        with footprints ``meta['FOOTPRINTS']`` is the list of corners given
        (written as the FOOTPRNT table).

    Raises
    ------
    PerscliError
        A negative density or seed, a bad field or footprint, an unreadable
        Gaia file, or a star density with a Galactic star model.
    """
    star_model, star_density = _star_population(galaxy_density, star_density, star_model, seed)
    fld, gal_fld = _catalog_region(ra, dec, size, footprints, margin_arcsec, galaxy_footprints)
    galaxies, stars, gaia_stars = _draw_sources(fld, gal_fld, seed, galaxy_density, galaxy_model, star_model,
                                                star_density, gaia, stdin=stdin, columns=columns)
    meta = _truth_meta(fld, gal_fld, len(galaxies["ra"]), len(stars["ra"]), gaia_stars, seed=seed,
                       galaxy_density=galaxy_density, galaxy_model=galaxy_model, star_model=star_model,
                       star_density=star_density)
    return _truth_table(galaxies, stars, meta)


def _star_population(galaxy_density, star_density, star_model, seed) -> tuple:
    """The star model and density :func:`make_truth_catalog` draws with, its arguments checked.

    Returns
    -------
    (GalacticStarModel or StarModel, float or None)
        The model (default: Galactic, or power-law with a ``star_density``)
        and the density of power-law stars (None for the Galactic model).

    Raises
    ------
    PerscliError
        A negative density or seed, or a star density with a Galactic model.
    """
    for label, value in (("galaxy density", galaxy_density), ("star density", star_density)):
        if value is not None and not (math.isfinite(value) and value >= 0):
            raise PerscliError(f"{label} {value} per arcmin^2: must be a number >= 0")
    if star_model is None:
        star_model = StarModel() if star_density is not None else GalacticStarModel()
    if isinstance(star_model, GalacticStarModel):
        if star_density is not None:
            raise PerscliError(f"star density {star_density} per arcmin^2 is for power-law stars: give it or a "
                               "Galactic star model, not both")
    elif isinstance(star_model, StarModel):
        star_density = DEFAULT_STAR_DENSITY if star_density is None else star_density
    else:
        raise PerscliError(f"star model {star_model!r}: give a GalacticStarModel or a StarModel")
    if int(seed) < 0:
        raise PerscliError(f"seed {seed}: must be an integer >= 0")
    return star_model, star_density


def _catalog_region(ra, dec, size, footprints, margin_arcsec, galaxy_footprints) -> tuple:
    """The region :func:`make_truth_catalog` draws in: a square :class:`Field` or a footprints' union.

    Returns
    -------
    (Field or FootprintUnion, Field or FootprintUnion)
        The region of the stars, and that of the galaxies (the same object
        unless ``galaxy_footprints`` are given).

    Raises
    ------
    PerscliError
        A bad field or footprint, or a mix of the two ways to give a region.
    """
    if footprints is not None:
        if margin_arcsec is None:
            margin_arcsec = DEFAULT_MARGIN_ARCSEC
        if size is not None:
            raise PerscliError("give a square field (ra, dec, size) or footprints, not both")
        if (ra is None) != (dec is None):
            raise PerscliError("with footprints, give both ra and dec (the tangent point) or neither")
        if ra is not None:
            ra, dec = check_position(ra, dec, "tangent point")
        fld = FootprintUnion(footprints, margin_arcsec, centre=None if ra is None else (ra, dec))
    else:
        if ra is None or dec is None:
            raise PerscliError("give the field centre (ra, dec) of a square field, or footprints")
        fld = Field(ra, dec, 10.0 if size is None else size)
    if galaxy_footprints is None:
        return fld, fld
    if footprints is None:
        raise PerscliError("galaxy footprints go with footprints")
    return fld, FootprintUnion(galaxy_footprints, margin_arcsec, centre=(fld.ra, fld.dec))


def _draw_sources(fld, gal_fld, seed, galaxy_density, galaxy_model, star_model, star_density, gaia, *,
                  stdin=None, columns=None) -> tuple:
    """The galaxies and stars of :func:`make_truth_catalog`, from one random stream each.

    Returns
    -------
    (dict, dict, GaiaStars or None)
        The galaxies' and the stars' columns (:func:`draw_galaxies`), and
        the Gaia stars' bookkeeping when the stars are Gaia's.
    """
    gal_seq, star_seq = np.random.SeedSequence(int(seed)).spawn(2)
    galaxies = draw_galaxies(np.random.Generator(np.random.PCG64(gal_seq)), gal_fld, galaxy_density, galaxy_model)
    if gaia:
        gaia_stars = read_gaia_stars(list(gaia), fld, stdin=stdin, columns=columns)
        return galaxies, gaia_stars.columns, gaia_stars
    star_rng = np.random.Generator(np.random.PCG64(star_seq))
    if isinstance(star_model, StarModel):
        return galaxies, draw_stars(star_rng, fld, star_density, star_model), None
    return galaxies, draw_galactic_stars(star_rng, fld, star_model), None


def _truth_meta(fld, gal_fld, n_gal, n_star, gaia_stars, *, seed, galaxy_density, galaxy_model, star_model,
                star_density) -> dict:
    """The catalog's header keywords, in the order they are written (:func:`make_truth_catalog`'s ``meta``).

    Parameters
    ----------
    fld, gal_fld : Field or FootprintUnion
        The regions of the stars and of the galaxies (:func:`_catalog_region`).
    n_gal, n_star : int
        The numbers drawn.
    gaia_stars : GaiaStars or None
        The Gaia stars' bookkeeping, if the stars are Gaia's.
    seed, galaxy_density, galaxy_model, star_model, star_density
        As :func:`make_truth_catalog` drew with them.

    Returns
    -------
    dict
        Keyword -> value (or (value, comment)); ``FOOTPRINTS``: the corners of footprints.
    """
    footprints = isinstance(fld, FootprintUnion)
    if footprints:
        meta = {"REGION": "footprints", "FIELDRA": fld.ra, "FIELDDEC": fld.dec, "NFOOT": len(fld),
                "FOOTMARG": fld.margin_arcsec, "FIELDAR": round(fld.area, 6),
                "BOXAREA": round(fld.box_area, 6)}
    else:
        meta = {"FIELDRA": fld.ra, "FIELDDEC": float(fld.dec), "FIELDSZ": float(fld.size),
                "FIELDAR": round(fld.area, 6)}
    if gal_fld is not fld:
        meta.update({"NGALFOOT": (len(gal_fld), "footprints holding galaxies (stars: all NFOOT)"),
                     "GALAREA": (round(gal_fld.area, 6), "[arcmin2] their union")})
    meta.update({"POSMODEL": "uniform in solid angle", "GALDENS": float(galaxy_density), "NGAL": n_gal})
    if gaia_stars is not None:
        meta.update({"STARSRC": "gaia", "NSTAR": n_star})
    elif isinstance(star_model, StarModel):
        meta.update({"STARSRC": "model", "STARMOD": "powerlaw", "STARDENS": float(star_density), "NSTAR": n_star})
    else:
        meta.update({"STARSRC": "model", **star_model.meta(),
                     "SDENSC": round(float(model_density(fld.ra, meta["FIELDDEC"], star_model)), 6),
                     "NSTAR": n_star})
    meta.update(_population_cards(galaxy_model, star_model, gaia_stars))
    meta["COLMODEL"] = "linear in ln(lambda)"
    for name in ROMAN_FILTERS:
        meta[f"LEFF{name}"] = EFFECTIVE_WAVELENGTH_UM[name]
    meta["SEED"] = int(seed)
    if footprints:
        meta["FOOTPRINTS"] = [(np.asarray(r, dtype=np.float64), np.asarray(d, dtype=np.float64))
                              for r, d in fld.given]
    return meta


def _population_cards(galaxy_model, star_model, gaia_stars) -> dict:
    """The header keywords of the galaxy model's parameters, then the star model's or the Gaia stars' bookkeeping."""
    gm = asdict(galaxy_model)
    cards = {
        "GPROFILE": "exponential", "GMAGSLP": gm["mag_slope"], "GMAGMIN": gm["mag_min"], "GMAGMAX": gm["mag_max"],
        "GJHMEAN": gm["jh_mean"], "GJHSIG": gm["jh_sigma"], "GHLR23": gm["hlr_at_23"],
        "GHLRSLP": gm["hlr_slope"], "GHLRSIG": gm["hlr_sigma"], "GHLRMIN": gm["hlr_min"],
        "GHLRMAX": gm["hlr_max"], "GESIG": gm["e_sigma"], "GEMAX": gm["e_max"],
        "EDEFN": "reduced shear g",
    }
    if gaia_stars is None and isinstance(star_model, StarModel):
        sm = asdict(star_model)
        cards.update({"SMAGSLP": sm["mag_slope"], "SMAGMIN": sm["mag_min"], "SMAGMAX": sm["mag_max"],
                      "SJHMEAN": sm["jh_mean"], "SJHSIG": sm["jh_sigma"], "SJHMIN": sm["jh_min"],
                      "SJHMAX": sm["jh_max"]})
    elif gaia_stars is not None:
        cards.update({"GAIANIN": gaia_stars.n_read, "GAIANOG": gaia_stars.n_no_flux,
                      "GAIANMED": gaia_stars.n_median_colour, "GAIABPRP": round(gaia_stars.median_bp_rp, 6)})
        for i, (name, datasum) in enumerate(gaia_stars.inputs, 1):
            cards[f"GA{i:03d}"] = "stdin" if name == "-" else name
            cards[f"GA{i:03d}DS"] = str(datasum)
    return cards


def _truth_table(galaxies, stars, meta) -> Table:
    """The catalog's table: galaxies then stars, ``id`` from 1, magnitudes in every filter, units and descriptions."""
    n_gal, n_star = len(galaxies["ra"]), len(stars["ra"])
    both = {k: np.concatenate([galaxies[k], stars[k]]) for k in galaxies}
    mags = filter_magnitudes(both["mag_j"], both["mag_h"])
    data = {
        "id": np.arange(1, n_gal + n_star + 1, dtype=np.int64),
        "ra": both["ra"].astype(np.float64),
        "dec": both["dec"].astype(np.float64),
        "kind": np.array(["galaxy"] * n_gal + ["star"] * n_star, dtype="U6"),
        **{f"mag_{f}": mags[f] for f in ROMAN_FILTERS},
        "hlr": both["hlr"].astype(np.float64),
        "e1": both["e1"].astype(np.float64),
        "e2": both["e2"].astype(np.float64),
        "gaia_id": both["gaia_id"].astype(np.int64),
    }
    table = Table(data, names=COLUMNS, meta=meta)
    for name, (unit, desc) in _COLUMN_INFO.items():
        if unit:
            table[name].unit = unit
        table[name].description = desc
    return table


def make_truth_catalog_file(dest: str, ra: float | None = None, dec: float | None = None,
                            size: float | None = None, *, footprints=None,
                            margin_arcsec: float = DEFAULT_MARGIN_ARCSEC, sca: int = 0, bounds=None,
                            overwrite: bool = False, stdin=None, stdout=None, **kw):
    """Check ``dest``, make a catalog (:func:`make_truth_catalog`) and write it.

    Parameters
    ----------
    dest : str
        Output path, '-' for standard output.
    ra, dec, size, margin_arcsec
        As :func:`make_truth_catalog`.
    footprints : sequence of (ra, dec), or str, optional
        The footprints' corners, or the path of a pointings table
        (``perscli pointings``) whose rows' SCA footprints
        (:func:`perscli.scene.pointings.pointings_footprints`) make the
        region; the table is recorded as an input (PTGS, PTGSDS).
    sca : int
        With a pointings table: the SCA (0: each row's own).
    bounds : (xmin, xmax, ymin, ymax), optional
        With a pointings table: the footprint of this cutout of the SCA.
    overwrite, stdin, stdout
        As for every command.
    **kw
        The other arguments of :func:`make_truth_catalog`.

    Returns
    -------
    astropy.table.Table
        The catalog written.
    """
    galaxy_rows = kw.pop("galaxy_rows", None)
    table_path = footprints if isinstance(footprints, (str, bytes)) else None
    check_output(dest, overwrite=overwrite, inputs=list(kw.get("gaia") or ()) + ([table_path] if table_path else []))
    inputs = []
    if table_path is not None:
        footprints, datasum = pointings_footprints(table_path, sca=sca, bounds=bounds, stdin=stdin)
        inputs.append(("PTGS", table_path, datasum))
    elif sca or bounds is not None:
        raise PerscliError("sca and bounds choose the footprints of a pointings table: give its path as footprints")
    if galaxy_rows is not None:
        # galaxies only in some rows' footprints (a study's finals), stars in every row's
        if footprints is None:
            raise PerscliError("galaxy rows are rows of a footprints table: give footprints")
        bad = [i for i in galaxy_rows if not 0 <= int(i) < len(footprints)]
        if bad:
            raise PerscliError(f"galaxy rows {bad}: the footprints table has rows 0 to {len(footprints) - 1}")
        kw["galaxy_footprints"] = [footprints[int(i)] for i in galaxy_rows]
    table = make_truth_catalog(ra, dec, size, footprints=footprints, margin_arcsec=margin_arcsec, stdin=stdin, **kw)
    if inputs:
        table.meta["INPUTS"] = inputs
    write_truth_catalog(table, dest, overwrite=overwrite, stdout=stdout)
    return table
