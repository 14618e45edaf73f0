"""Model stars from a Galactic structure model: counts per J129 magnitude anywhere on the sky.

The default stars of a truth catalogue (:func:`perscli.scene.catalog.make_truth_catalog`)
are drawn from :class:`GalacticStarModel`: a thin disc, a thick disc and a
halo whose densities are integrated along the line of sight at each position,
times one luminosity function (LF) in absolute J magnitude.  The expected
number of stars per deg^2 brighter than apparent J at Galactic (l, b) is

    N(<J) = sum over distance d of  Omega rho(d) d^2 dd  F(J - 0.91 - 5 log10(d / 10 pc))

with F(M) the number of stars per pc^3 brighter than M_J (the integral of
the LF) and rho(d) the density relative to the Sun's position, so that the LF
is the LF of all stars at the Sun.  No extinction (see *Limits*).

**Density laws** (:class:`GalacticStarModel`; every default with its source
there).  Exponential discs rho = f exp(-(R - R_sun)/L - (|Z| - Z_sun)/H),
Z = d sin b + Z_sun, and a power-law oblate halo
rho = f_h ((R^2 + (Z/kappa)^2) / (R_sun^2 + (Z_sun/kappa)^2))^(-p/2), the
three-component model of Juric et al. (2008, ApJ 673, 864, eqs. 22-24).
Its parameters are those of the whole-sky fit of the 2MASS K_s counts at
|b| > 30 deg by Chang, Ko & Peng (2011, ApJ 740, 34; arXiv:1107.3884):
thin disc H = 360 pc, L = 3.7 kpc; thick disc H = 1020 pc, L = 5.0 kpc,
local thick/thin density 7%; halo kappa = 0.55, p = 2.6, local halo/thin
density 0.2%.  The Sun's position is that of Juric et al. (2008), Table 10:
R_sun = 8 kpc, Z_sun = 25 pc.  The line of sight is integrated from 3 pc to
``max_distance`` (100 kpc) in steps of 0.02 in distance modulus; the counts
brighter than J = 24 at b = -73 grow by 0.9% to 200 kpc and 1.4% to 1 Mpc.

**Luminosity function** (:data:`LF_TABLE`, absolute 2MASS J, Vega), in two parts:

- M_J < 8: calibrated on Gaia DR2 (Gaia Collaboration, Brown et al. 2018,
  A&A 616, A1): the 1151 stars with J129 < 18 of the two reference-catalogue
  Gaia DR2 chunks (HTM level-7 trixels 145649 and 145650 near
  RA 10, Dec -44, b = -72 and -73, 0.42029 deg^2 each), by
  :func:`fit_luminosity_function`: the Poisson maximum likelihood (EM) of
  the LF in 11 bins given each star's J (perscli's conversion of G and
  BP-RP, :func:`perscli.scene.photometry.gaia_roman_jh`) and parallax (with its
  error, after adding 0.029 mas, the global DR2 zero point of Lindegren et
  al. 2018, A&A 616, A2), with the density laws above.  J129 < 18 is where
  these chunks are complete (their reddest stars there have G < 20.6).
  The Juric et al. LF that the Milky Way models of Juric (galfast) and Green
  et al. (2014) use is, at the bright end, an extrapolation
  (log Phi = C + 0.33 M_r for M_r < 4.9) that gives 1.6 to 8 times the
  giants these Gaia stars show (M_J < 2): the reason for this calibration
  (for 2 < M_J < 8 the two agree within a factor 0.7-1.6).  Fitting one
  chunk and predicting the other gives its counts within 1.6 sigma for
  J < 17 (2.2 sigma at 17-18).
- M_J >= 8 (M3.5 dwarfs and fainter): the LF of M and L dwarfs in M_r of
  Juric et al. (2008, for M_r < 12) and Covey et al. (2008, AJ 136, 1778,
  M_r > 15), joined by Z. Ivezic (2009, file MrLF.MSandRGB_v1.0.dat of
  galfast and of G. Green's bayestar), converted to M_J with the r - J of
  the PS1 + 2MASS stellar templates of bayestar (Green et al. 2014,
  ApJ 783, 114; file data/PS1_2MASS_colors.dat, 2014) at [Fe/H] = -0.6,
  the median disc metallicity at |Z| = 500 pc of Ivezic et al. (2008,
  ApJ 684, 287).  (The templates extrapolate beyond M_r = 13, M_J = 9;
  r_PS1 and r_SDSS differ by ~0.02 mag, neglected.)  Not rescaled: the
  Gaia fit with a free scale on this part gives 0.92, consistent with 1.
  Its first bin continues the Gaia part (1.16e-2 against 0.95e-2 per pc^3
  per mag at M_J = 7-8).  Brown dwarfs fainter than M_J = 13 are left out.

The LF integrates to 0.052 stars per pc^3 (M_J < 13).  One LF serves all
three components, as in Juric et al. (2008).

**Colours**: J - H per LF bin.  Bins brighter than M_J = 4 (giants,
subgiants, F and G stars): the mean and scatter of the Gaia stars of the fit
(each weighted by its probability of belonging to the bin), so the same
conversion as perscli's Gaia stars.  Fainter bins (dwarfs): the mean dwarf
sequence of E. Mamajek (version 2018.08.02, extending Pecaut & Mamajek
2013, ApJS 208, 9; :data:`DWARF_JH`) at the bin's centre, with a nominal
scatter ``dwarf_jh_sigma`` (0.05 mag, chosen here: no source).  (The Gaia
conversion of Evans et al. 2018 gives M dwarfs J - H ~ 1.0 (Vega) where
dwarfs have 0.55-0.6: the reason not to use it there.)  AB: J_AB = J + 0.91,
H_AB = H + 1.39 (Blanton & Roweis 2007).  Each drawn star gets the colour
of its LF bin, the bin drawn given its J from the distances that could give
that J.

**Counts** (per deg^2, J129 AB, :func:`expected_counts`).  At RA 10,
Dec -44 (l = 310.0, b = -73.0), against the calibration chunks (their counts
over their 0.8406 deg^2, +- Poisson): J < 12: 24.7 [25.0 +- 5.5];
12-14: 97.4 [101 +- 11]; 14-16: 351 [389 +- 22]; 16-17: 360 [365 +- 21];
17-18: 535 [489 +- 24].  The total to J = 24 is 2.5 per arcmin^2 there (the
paper's Galaxia stars: 2.5).  At l = 90 and b = 90, 60, 45, 30, 20: J < 14
99, 120, 154, 231, 351; J < 24 2.0, 2.7, 4.0, 7.9, 16.6 per arcmin^2.
tests/test_starcounts.py checks the latitude dependence against the 2MASS
reference fields.

**Limits**: no extinction (dust removes and reddens stars at low latitude),
no bulge or bar (too few stars towards the Galactic centre at low
latitude), no spiral arms, clusters or streams, no white dwarfs, one LF for
young and old stars (fitted where old stars dominate the bright counts), no
binaries as such (the LF counts point sources as Gaia sees them).  Meant for
|b| > ~20 deg.

**Drawing** (:func:`draw_galactic_stars`): the model is evaluated on a grid
on the tangent plane of the field or footprint union (nodes at most 0.5 deg
apart, at least 2 and at most 41 per side); a Poisson process at the grid's largest density
is thinned by the bilinearly interpolated density at each position; each
star's J comes from the magnitude distribution of its nearest node, then its
LF bin and colour as above.  All from one random stream, so the galaxies of a
catalogue do not depend on the stars.
"""

from __future__ import annotations

import functools
import math
import os
from collections.abc import Mapping
from dataclasses import asdict, dataclass, fields

import numpy as np
from astropy.io import fits

from .. import PerscliError
from ..io.config import STAR_ITEM, split_key_value
from . import deproject, project, unit_vector
from .photometry import gaia_roman_jh

#: deg^2 per steradian
DEG2_PER_SR = (180.0 / math.pi) ** 2

#: 2MASS AB - Vega for J and H (Blanton & Roweis 2007, AJ 133, 734), as perscli.scene.catalog
J_AB_MINUS_VEGA = 0.91
H_AB_MINUS_VEGA = 1.39

#: ICRS -> Galactic rotation: rows are the Galactic x (to l = 0, b = 0), y (l = 90) and z (b = 90) axes in
#: ICRS (ESA 1997, The Hipparcos Catalogue, vol. 1, sect. 1.5.3, eq. 1.5.11: the matrix A_G transposed)
ICRS_TO_GALACTIC = np.array([[-0.0548755604, -0.8734370902, -0.4838350155],
                             [+0.4941094279, -0.4448296300, +0.7469822445],
                             [-0.8676661490, -0.1980763734, +0.4559837762]])

#: [mas] added to Gaia DR2 parallaxes: their global zero point (Lindegren et al. 2018, A&A 616, A2)
GAIA_DR2_PARALLAX_ZERO_POINT = 0.029

#: Distance-modulus grid of the line-of-sight integral: step and start (3 pc)
MU_STEP = 0.02
MU_MIN = -2.5

#: M_J edges of the rows of :data:`LF_TABLE` fitted to Gaia (:func:`fit_luminosity_function`)
GAIA_LF_EDGES = (-6.0, -2.0, -1.0, 0.0, 1.0, 2.0, 3.0, 4.0, 5.0, 6.0, 7.0, 8.0)
#: The rows of :data:`LF_TABLE` from M_J = 8 (M_J low, high, Phi per pc^3 per mag): the LF of Juric et al.
#: (2008) and Covey et al. (2008) in M_r (Ivezic's MrLF.MSandRGB_v1.0.dat), summed into these bins of M_J
#: through r - J of the bayestar PS1 + 2MASS templates at [Fe/H] = -0.6 (module docstring)
TAIL_LF = ((8.0, 8.5, 1.1565e-02), (8.5, 9.0, 8.6840e-03), (9.0, 9.5, 8.4649e-03), (9.5, 10.0, 6.8952e-03),
           (10.0, 10.5, 4.1853e-03), (10.5, 11.0, 1.9036e-03), (11.0, 11.5, 1.5857e-03),
           (11.5, 12.0, 1.1932e-03), (12.0, 12.5, 9.7207e-04), (12.5, 13.0, 5.6275e-04))

#: The luminosity function: (M_J low, M_J high, Phi [stars pc^-3 mag^-1], (J-H)_AB mean, (J-H)_AB sigma),
#: M_J absolute 2MASS J (Vega).  Rows with M_J < 8: :func:`fit_luminosity_function` on the Gaia DR2 chunks
#: 145649 + 145650 (Gaia DR2 chunks) with the default model, 5000 iterations; the colours of the rows
#: brighter than 4 from the same stars, NaN: from :data:`DWARF_JH`.  Rows with M_J >= 8: :data:`TAIL_LF`.
LF_TABLE = (
    # M_J from, to, Phi, (J-H)_AB, sigma         expected Gaia stars of the fit in the bin
    (-6.0, -2.0, 3.4514e-06, -0.009, 0.187),   # 4.8
    (-2.0, -1.0, 3.9230e-05, -0.072, 0.180),   # 10.3
    (-1.0, 0.0, 4.4195e-05, -0.073, 0.160),    # 9.3
    (0.0, 1.0, 3.2023e-05, -0.078, 0.151),     # 5.4
    (1.0, 2.0, 1.4300e-04, -0.095, 0.151),     # 19.3
    (2.0, 3.0, 7.9280e-04, -0.151, 0.151),     # 85.8
    (3.0, 4.0, 1.7460e-03, -0.137, 0.152),     # 148.7
    (4.0, 5.0, 3.8166e-03, math.nan, math.nan),  # 241.0
    (5.0, 6.0, 4.9205e-03, math.nan, math.nan),  # 214.9
    (6.0, 7.0, 7.7627e-03, math.nan, math.nan),  # 208.3
    (7.0, 8.0, 9.5211e-03, math.nan, math.nan),  # 129.9
) + tuple((lo, hi, phi, math.nan, math.nan) for lo, hi, phi in TAIL_LF)

#: Rows from M_J = 4 on take their J - H from the dwarf sequence
DWARF_COLOUR_FROM = 4.0

#: (M_J, J - H), 2MASS Vega, of the mean dwarf sequence G9V ... L4V of E. Mamajek's "A Modern Mean Dwarf
#: Stellar Color and Effective Temperature Sequence", version 2018.08.02 (extending Pecaut & Mamajek 2013,
#: ApJS 208, 9); M7.5V (M_J 10.68, fainter M7V 10.76) left out so that M_J increases
DWARF_JH = ((4.14, 0.365), (4.29, 0.387), (4.37, 0.402), (4.57, 0.427), (4.76, 0.483), (4.92, 0.544),
            (5.18, 0.568), (5.30, 0.591), (5.41, 0.601), (5.56, 0.613), (5.60, 0.617), (5.78, 0.623),
            (5.92, 0.625), (6.04, 0.626), (6.19, 0.620), (6.51, 0.613), (6.69, 0.607), (6.89, 0.600),
            (7.01, 0.589), (7.40, 0.579), (8.02, 0.558), (8.39, 0.557), (8.79, 0.564), (9.25, 0.580),
            (9.93, 0.588), (10.28, 0.605), (10.47, 0.609), (10.76, 0.613), (11.23, 0.670), (11.45, 0.685),
            (11.53, 0.749), (11.78, 0.826), (11.84, 0.79), (12.14, 0.80), (12.34, 0.87), (12.93, 1.00),
            (13.17, 1.14))


@dataclass(frozen=True)
class GalacticStarModel:
    """The Galactic star population: density laws, luminosity-function scale, magnitude range, colours.

    Attributes
    ----------
    sun_radius : float
        [pc] Galactocentric radius of the Sun, 8000 (Juric et al. 2008, ApJ 673, 864, Table 10).
    sun_height : float
        [pc] height of the Sun above the plane, 25 (Juric et al. 2008, Table 10).
    thin_height : float
        [pc] thin-disc scale height, 360 (Chang, Ko & Peng 2011, ApJ 740, 34: 360 +- 10).
    thin_length : float
        [pc] thin-disc scale length, 3700 (Chang et al. 2011: 3.7 +- 1.0 kpc).
    thick_height : float
        [pc] thick-disc scale height, 1020 (Chang et al. 2011: 1020 +- 30).
    thick_length : float
        [pc] thick-disc scale length, 5000 (Chang et al. 2011: 5.0 +- 1.0 kpc).
    thick_fraction : float
        Thick/thin density at the Sun, 0.07 (Chang et al. 2011: 7 +- 1%).
    halo_fraction : float
        Halo/thin density at the Sun, 0.002 (Chang et al. 2011: 0.20 +- 0.10%).
    halo_axis_ratio : float
        Halo axis ratio c/a (kappa), 0.55 (Chang et al. 2011: 0.55 +- 0.15).
    halo_index : float
        Halo power-law index p, rho ~ r^-p, 2.6 (Chang et al. 2011: 2.6 +- 0.6).
    max_distance : float
        [pc] end of the line-of-sight integral, 100000 (chosen here: to 200 kpc the counts to J = 24 at
        b = -73 would grow by 0.9%).
    lf_scale : float
        Factor on the whole luminosity function, 1 (the LF as calibrated, module docstring).
    mag_min, mag_max : float
        [mag] J129 (AB) range of the stars drawn, 4 and 24 (chosen here: 24 as the power-law model;
        the model has 0.04 stars per deg^2 brighter than 4 at b = -73, 0.25 in a 6.25 deg^2 footprint:
        lower mag_min to draw them).
    dwarf_jh_sigma : float
        [mag] scatter of J - H of the dwarf LF bins (M_J >= 4), 0.05 (nominal, chosen here).
    """

    sun_radius: float = 8000.0
    sun_height: float = 25.0
    thin_height: float = 360.0
    thin_length: float = 3700.0
    thick_height: float = 1020.0
    thick_length: float = 5000.0
    thick_fraction: float = 0.07
    halo_fraction: float = 0.002
    halo_axis_ratio: float = 0.55
    halo_index: float = 2.6
    max_distance: float = 100000.0
    lf_scale: float = 1.0
    mag_min: float = 4.0
    mag_max: float = 24.0
    dwarf_jh_sigma: float = 0.05

    def __post_init__(self):
        for f in fields(self):
            value = getattr(self, f.name)
            if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
                raise PerscliError(f"star-model parameter {f.name}={value!r}: must be a finite number")
            object.__setattr__(self, f.name, float(value))
        positive = ("sun_radius", "thin_height", "thin_length", "thick_height", "thick_length",
                    "halo_axis_ratio", "halo_index")
        for name in positive:
            if getattr(self, name) <= 0:
                raise PerscliError(f"star-model parameter {name}={getattr(self, name):g}: must be > 0")
        for name in ("thick_fraction", "halo_fraction", "lf_scale", "dwarf_jh_sigma"):
            if getattr(self, name) < 0:
                raise PerscliError(f"star-model parameter {name}={getattr(self, name):g}: must be >= 0")
        if not 10.0 < self.max_distance <= 1e6:
            raise PerscliError(f"star-model parameter max_distance={self.max_distance:g} pc: must be more than "
                               "10 and at most 1e6")
        if not self.mag_min < self.mag_max:
            raise PerscliError(f"star-model magnitudes mag_min={self.mag_min:g}, mag_max={self.mag_max:g}: "
                               "mag_min must be less than mag_max")
        if not (-10.0 <= self.mag_min and self.mag_max <= 40.0):
            raise PerscliError(f"star-model magnitudes {self.mag_min:g} to {self.mag_max:g}: must lie within "
                               "-10 to 40")

    @classmethod
    def parameter_names(cls) -> tuple:
        """The names of the parameters, in order."""
        return tuple(f.name for f in fields(cls))

    @classmethod
    def from_mapping(cls, overrides=(), base: "GalacticStarModel | None" = None) -> "GalacticStarModel":
        """A model with some parameters changed.

        Parameters
        ----------
        overrides : mapping, or sequence of 'KEY=VALUE' strings
            Parameter names (:meth:`parameter_names`) and values (numbers, or
            strings that are numbers).
        base : GalacticStarModel, optional
            The model changed (default: the defaults).

        Raises
        ------
        PerscliError
            An unknown name (the message lists the valid ones), a value that
            is not a number, or a value out of range.
        """
        base = cls() if base is None else base
        if isinstance(overrides, Mapping):
            items = list(overrides.items())
        elif isinstance(overrides, str):
            raise PerscliError(f"star-model parameters {overrides!r}: give a mapping or a list of KEY=VALUE")
        else:
            # the values stay text: each is read as a number below, with a message naming its parameter
            items = [split_key_value(text, **STAR_ITEM) for text in overrides]
        valid = cls.parameter_names()
        changes = {}
        for key, value in items:
            if key not in valid:
                raise PerscliError(f"unknown star-model parameter {key!r}: valid are {', '.join(valid)}")
            if isinstance(value, bool):
                number = float("nan")
            else:
                try:
                    number = float(value)
                except (TypeError, ValueError):
                    number = float("nan")
            if not math.isfinite(number):
                raise PerscliError(f"star-model parameter {key}={value!r}: must be a finite number")
            changes[key] = number
        return cls(**{**asdict(base), **changes})

    # -- the line of sight ----------------------------------------------------------------------
    @property
    def mu_grid(self) -> np.ndarray:
        """Distance moduli of the line-of-sight integral (cell centres)."""
        mu_max = 5.0 * math.log10(self.max_distance / 10.0)
        n = max(1, int(math.ceil((mu_max - MU_MIN) / MU_STEP)))
        return MU_MIN + (np.arange(n) + 0.5) * MU_STEP

    def relative_density(self, l, b, d) -> np.ndarray:
        """Density at distance ``d`` (pc) towards Galactic (l, b) (degrees), relative to the Sun's position."""
        lr, br = np.radians(l), np.radians(b)
        d = np.asarray(d, dtype=np.float64)
        x = self.sun_radius - d * np.cos(br) * np.cos(lr)
        y = d * np.cos(br) * np.sin(lr)
        radius = np.hypot(x, y)
        z = d * np.sin(br) + self.sun_height
        height = np.abs(z) - abs(self.sun_height)
        thin = np.exp(-(radius - self.sun_radius) / self.thin_length - height / self.thin_height)
        thick = self.thick_fraction * np.exp(-(radius - self.sun_radius) / self.thick_length
                                             - height / self.thick_height)
        q2 = self.halo_axis_ratio ** 2
        r2_sun = self.sun_radius ** 2 + self.sun_height ** 2 / q2
        halo = self.halo_fraction * ((radius ** 2 + z ** 2 / q2) / r2_sun) ** (-self.halo_index / 2.0)
        return (thin + thick + halo) / (1.0 + self.thick_fraction + self.halo_fraction)

    def line_of_sight(self, l: float, b: float) -> np.ndarray:
        """Volume per unit solid angle of each cell of :attr:`mu_grid`, weighted by the relative density.

        Returns
        -------
        ndarray
            pc^3 per steradian: rho(d) d^3 ln(10)/5 dmu, rho relative to the Sun.
        """
        return _line_of_sight(self, round(float(l) % 360.0, 6), round(float(b), 6))

    def meta(self) -> dict:
        """Header keywords: the model's name and parameters (see :data:`META_KEYWORDS`)."""
        out = {"STARMOD": "galactic", "STARLF": LF_VERSION}
        for name, (key, _) in META_KEYWORDS.items():
            out[key] = getattr(self, name)
        return out


@functools.lru_cache(maxsize=4096)
def _line_of_sight(model: GalacticStarModel, l: float, b: float) -> np.ndarray:
    mu = model.mu_grid
    d = 10.0 ** (mu / 5.0 + 1.0)
    out = model.relative_density(l, b, d) * d ** 3 * (math.log(10.0) / 5.0 * MU_STEP)
    out.setflags(write=False)
    return out


#: Name of the luminosity function, for the catalogue header: fitted to Gaia DR2, Juric 2008 + Covey 2008 tail
LF_VERSION = "gaiadr2-fit+juric08-covey08"

#: parameter -> (header keyword, comment)
META_KEYWORDS = {
    "sun_radius": ("SGRSUN", "[pc] star model: Galactocentric radius of Sun"),
    "sun_height": ("SGZSUN", "[pc] star model: height of Sun above plane"),
    "thin_height": ("SGH1", "[pc] star model: thin-disc scale height"),
    "thin_length": ("SGL1", "[pc] star model: thin-disc scale length"),
    "thick_height": ("SGH2", "[pc] star model: thick-disc scale height"),
    "thick_length": ("SGL2", "[pc] star model: thick-disc scale length"),
    "thick_fraction": ("SGF2", "star model: thick/thin density at Sun"),
    "halo_fraction": ("SGFH", "star model: halo/thin density at Sun"),
    "halo_axis_ratio": ("SGQH", "star model: halo axis ratio c/a"),
    "halo_index": ("SGNH", "star model: halo power-law index"),
    "max_distance": ("SGDMAX", "[pc] star model: end of line of sight"),
    "lf_scale": ("SGLFSC", "star model: factor on luminosity function"),
    "mag_min": ("SMAGMIN", "stars: brightest J129 (AB)"),
    "mag_max": ("SMAGMAX", "stars: faintest J129 (AB)"),
    "dwarf_jh_sigma": ("SGJHSIG", "star model: J-H scatter of dwarfs (M_J>=4)"),
}


def galactic_star_model(overrides=(), **parameters) -> GalacticStarModel:
    """The Galactic star model with parameters changed by name.

    ``galactic_star_model({'thin_height': 300})``,
    ``galactic_star_model(['thin_height=300'])`` and
    ``galactic_star_model(thin_height=300)`` are the same model.

    Raises
    ------
    PerscliError
        An unknown name (listing the valid ones) or a bad value.
    """
    model = GalacticStarModel.from_mapping(overrides)
    return GalacticStarModel.from_mapping(parameters, base=model) if parameters else model


# -- the luminosity function ----------------------------------------------------------------------

def _lf_arrays():
    table = np.array(LF_TABLE, dtype=np.float64)
    lo, hi, phi, jh_mean, jh_sigma = table.T
    return lo, hi, phi, jh_mean, jh_sigma


def luminosity_function(model: GalacticStarModel | None = None) -> dict:
    """The luminosity function as used: bins of M_J (Vega), Phi (per pc^3 per mag) and (J-H)_AB per bin."""
    model = GalacticStarModel() if model is None else model
    lo, hi, phi, jh_mean, jh_sigma = _lf_arrays()
    centre = 0.5 * (lo + hi)
    dwarf = lo >= DWARF_COLOUR_FROM
    dwarf_jh = np.interp(centre, *np.array(DWARF_JH).T) + J_AB_MINUS_VEGA - H_AB_MINUS_VEGA
    return {"lo": lo, "hi": hi, "phi": phi * model.lf_scale,
            "jh_mean": np.where(dwarf, dwarf_jh, jh_mean),
            "jh_sigma": np.where(dwarf, model.dwarf_jh_sigma, jh_sigma)}


def _cumulative_lf(m, lo, hi, phi) -> np.ndarray:
    """Stars per pc^3 brighter than absolute magnitude ``m`` (piecewise-constant LF)."""
    m = np.asarray(m, dtype=np.float64)
    return np.clip(m[..., None] - lo, 0.0, hi - lo) @ phi


# -- positions ------------------------------------------------------------------------------------

def galactic_coordinates(ra, dec) -> tuple:
    """Galactic (l, b) in degrees of ICRS (ra, dec) in degrees."""
    ra, dec = np.radians(np.asarray(ra, dtype=np.float64)), np.radians(np.asarray(dec, dtype=np.float64))
    v = np.stack([np.cos(dec) * np.cos(ra), np.cos(dec) * np.sin(ra), np.sin(dec)], axis=-1)
    g = v @ ICRS_TO_GALACTIC.T
    return np.degrees(np.arctan2(g[..., 1], g[..., 0])) % 360.0, np.degrees(np.arcsin(np.clip(g[..., 2], -1, 1)))


# -- counts ---------------------------------------------------------------------------------------

def cumulative_counts(ra, dec, mags, model: GalacticStarModel | None = None, *, galactic: bool = False):
    """Expected stars per deg^2 brighter than each J129 (AB) of ``mags`` at each position.

    Parameters
    ----------
    ra, dec : float or array_like
        Positions in degrees (ICRS), or Galactic (l, b) with ``galactic``.
    mags : array_like
        J129 AB magnitudes.
    model : GalacticStarModel, optional
        Default: the defaults.

    Returns
    -------
    ndarray
        Shape ``shape(ra) + shape(mags)``.  The magnitude range of the
        model (mag_min, mag_max) is not applied.
    """
    model = GalacticStarModel() if model is None else model
    l, b = (np.asarray(ra, dtype=np.float64), np.asarray(dec, dtype=np.float64)) if galactic \
        else galactic_coordinates(ra, dec)
    l, b = np.broadcast_arrays(l, b)
    mags = np.asarray(mags, dtype=np.float64)
    lf = luminosity_function(model)
    mu = model.mu_grid
    absolute = mags.reshape(-1)[:, None] - J_AB_MINUS_VEGA - mu[None, :]
    f = _cumulative_lf(absolute, lf["lo"], lf["hi"], lf["phi"])          # (n_mags, n_mu)
    out = np.empty(l.shape + (mags.size,))
    for idx in np.ndindex(l.shape):
        out[idx] = f @ model.line_of_sight(l[idx], b[idx]) / DEG2_PER_SR
    return out.reshape(l.shape + mags.shape)


def expected_counts(ra, dec, edges, model: GalacticStarModel | None = None, *, galactic: bool = False):
    """Expected stars per deg^2 in each J129 (AB) bin [edges[i], edges[i+1]) at each position.

    ``edges`` may start with -inf.  Shape ``shape(ra) + (len(edges) - 1,)``.
    """
    edges = np.asarray(edges, dtype=np.float64)
    if edges.ndim != 1 or edges.size < 2 or np.any(np.diff(edges) <= 0):
        raise PerscliError("magnitude bin edges must be at least two increasing values")
    finite = np.where(np.isfinite(edges), edges, -100.0)
    c = cumulative_counts(ra, dec, finite, model, galactic=galactic)
    return np.diff(c, axis=-1)


def star_density(ra, dec, model: GalacticStarModel | None = None, *, galactic: bool = False):
    """Expected stars per arcmin^2 between the model's mag_min and mag_max at each position."""
    model = GalacticStarModel() if model is None else model
    c = cumulative_counts(ra, dec, [model.mag_min, model.mag_max], model, galactic=galactic)
    return (c[..., 1] - c[..., 0]) / 3600.0


# -- drawing --------------------------------------------------------------------------------------

#: [deg] largest spacing of the grid the density is evaluated on when drawing, and its largest side
GRID_SPACING_DEG = 0.5
GRID_MAX_NODES = 41


class _Node:
    """The model at one position: cumulative counts on the J grid, and the cumulative line of sight."""

    def __init__(self, model: GalacticStarModel, l: float, b: float, jgrid: np.ndarray, f_conv: np.ndarray):
        self.volume = model.line_of_sight(l, b)
        n_mu = self.volume.size
        # cumulative counts C(J_n) = sum_m V_m F(J_n - 0.91 - mu_m): a convolution, J and mu sharing one step
        c = np.convolve(f_conv, self.volume)[n_mu - 1:n_mu - 1 + jgrid.size] / DEG2_PER_SR
        self.cumulative = c - c[0]
        # the grid may end just past mag_max
        self.total = float(np.interp(model.mag_max, jgrid, self.cumulative))
        self.density = self.total / 3600.0                                      # per arcmin^2
        self.mu_cum = np.concatenate([[0.0], np.cumsum(self.volume)])


def _plane_box(fld) -> tuple:
    if hasattr(fld, "box"):
        return tuple(fld.box)
    a = fld.half_width
    return (-a, a, -a, a)


def draw_galactic_stars(rng: np.random.Generator, fld, model: GalacticStarModel | None = None) -> dict:
    """A Poisson process of stars of the Galactic model in ``fld`` (a Field or a FootprintUnion).

    Returns
    -------
    dict
        ra, dec, mag_j, mag_h (AB), hlr, e1, e2 (zeros) and gaia_id (-1),
        as :func:`perscli.scene.catalog.draw_stars`, plus ``grid`` (the
        (ra, dec) of the nodes the model was evaluated at) and
        ``max_density`` (per arcmin^2, the largest at a node).
    """
    model = GalacticStarModel() if model is None else model
    lf = luminosity_function(model)
    x1, x2, y1, y2 = _plane_box(fld)
    spacing = math.tan(math.radians(GRID_SPACING_DEG))
    nx = min(GRID_MAX_NODES, max(2, int(math.ceil((x2 - x1) / spacing)) + 1))
    ny = min(GRID_MAX_NODES, max(2, int(math.ceil((y2 - y1) / spacing)) + 1))
    gx, gy = np.linspace(x1, x2, nx), np.linspace(y1, y2, ny)
    node_ra, node_dec = deproject(fld.ra, fld.dec, *[a.ravel() for a in np.meshgrid(gx, gy, indexing="ij")])
    node_l, node_b = galactic_coordinates(node_ra, node_dec)

    step = MU_STEP
    n_j = int(math.ceil((model.mag_max - model.mag_min) / step)) + 1
    jgrid = model.mag_min + np.arange(n_j) * step
    mu = model.mu_grid
    # F sampled at M = J_0 - 0.91 - mu_0 + q step, q = -(n_mu - 1) ... n_j - 1 (see _Node)
    q = np.arange(-(mu.size - 1), n_j)
    f_conv = _cumulative_lf(jgrid[0] - J_AB_MINUS_VEGA - mu[0] + q * step, lf["lo"], lf["hi"], lf["phi"])
    nodes = [_Node(model, l, b, jgrid, f_conv) for l, b in zip(node_l, node_b)]
    dens = np.array([n.density for n in nodes]).reshape(nx, ny)
    lam_max = float(dens.max()) if dens.size else 0.0

    ra, dec = fld.poisson_positions(rng, lam_max) if lam_max > 0 else (np.empty(0), np.empty(0))
    x, y = project(fld.ra, fld.dec, ra, dec)
    # bilinear interpolation of the density on the grid (never above the largest node)
    tx = np.clip((x - x1) / (x2 - x1) * (nx - 1), 0, nx - 1 - 1e-12) if nx > 1 else np.zeros_like(x)
    ty = np.clip((y - y1) / (y2 - y1) * (ny - 1), 0, ny - 1 - 1e-12) if ny > 1 else np.zeros_like(y)
    ix, iy = np.floor(tx).astype(int), np.floor(ty).astype(int)
    fx, fy = tx - ix, ty - iy
    lam = (dens[ix, iy] * (1 - fx) * (1 - fy) + dens[ix + 1, iy] * fx * (1 - fy)
           + dens[ix, iy + 1] * (1 - fx) * fy + dens[ix + 1, iy + 1] * fx * fy) if ra.size else np.empty(0)
    keep = rng.random(ra.size) * lam_max < lam
    ra, dec, x, y = ra[keep], dec[keep], x[keep], y[keep]
    n = ra.size
    nearest = (np.rint((x - x1) / (x2 - x1) * (nx - 1)).astype(int) * ny
               + np.rint((y - y1) / (y2 - y1) * (ny - 1)).astype(int)) if n else np.empty(0, dtype=int)

    u_mag = rng.random(n)
    u_bin = rng.random(n)
    z_col = rng.standard_normal(n)
    mag_j = np.empty(n)
    k = np.empty(n, dtype=int)
    mu_edges = np.concatenate([mu - step / 2, [mu[-1] + step / 2]])
    for node_index in np.unique(nearest):
        sel = np.flatnonzero(nearest == node_index)
        node = nodes[node_index]
        mag_j[sel] = np.interp(u_mag[sel] * node.total, node.cumulative, jgrid)
        # the LF bin given J: Phi_k times the line of sight over the distances that put bin k at J
        def g(m):
            return np.interp(m, mu_edges, node.mu_cum)
        top = mag_j[sel, None] - J_AB_MINUS_VEGA - lf["lo"][None, :]
        bottom = mag_j[sel, None] - J_AB_MINUS_VEGA - lf["hi"][None, :]
        w = lf["phi"][None, :] * (g(top) - g(bottom))
        cw = np.cumsum(w, axis=1)
        k[sel] = np.minimum((cw < u_bin[sel, None] * cw[:, -1:]).sum(axis=1), len(lf["phi"]) - 1)
    jh = lf["jh_mean"][k] + lf["jh_sigma"][k] * z_col if n else np.empty(0)
    return {"ra": ra, "dec": dec, "mag_j": mag_j, "mag_h": mag_j - jh, "hlr": np.zeros(n), "e1": np.zeros(n),
            "e2": np.zeros(n), "gaia_id": np.full(n, -1, dtype=np.int64),
            "grid": (node_ra, node_dec), "max_density": lam_max}


# -- HTM trixels (Gaia reference-catalogue chunks) ---------------------------------------------------

_HTM_VERTICES = np.array([[0, 0, 1], [1, 0, 0], [0, 1, 0], [-1, 0, 0], [0, -1, 0], [0, 0, -1]], dtype=np.float64)
#: the 8 root triangles S0..S3, N0..N3 (ids 8..15) as vertex indices, counter-clockwise seen from outside
_HTM_ROOTS = ((1, 5, 2), (2, 5, 3), (3, 5, 4), (4, 5, 1), (1, 0, 4), (4, 0, 3), (3, 0, 2), (2, 0, 1))


def htm_trixel(index: int) -> np.ndarray:
    """Unit vectors (3, 3) of the corners of a Hierarchical Triangular Mesh trixel.

    The HTM of Kunszt, Szalay & Thakar (2001, Mining the Sky, 631), as LSST's
    sphgeom names reference-catalogue chunks: 8 root triangles (ids 8-15)
    each split into 4 by the midpoints of its sides, child i of (v0, v1, v2)
    being (v0, w2, w1), (v1, w0, w2), (v2, w1, w0), (w0, w1, w2) for
    w0 = mid(v1, v2), w1 = mid(v0, v2), w2 = mid(v0, v1); the id gains two
    bits per level.

    Raises
    ------
    PerscliError
        Not an HTM id.
    """
    index = int(index)
    level = (index.bit_length() - 4) // 2
    if index < 8 or (index.bit_length() - 4) % 2:
        raise PerscliError(f"{index} is not an HTM trixel id")
    a, b, c = (_HTM_VERTICES[i] for i in _HTM_ROOTS[(index >> (2 * level)) - 8])
    for shift in range(level - 1, -1, -1):
        child = (index >> (2 * shift)) & 3
        w0, w1, w2 = (v / np.linalg.norm(v) for v in (b + c, a + c, a + b))
        a, b, c = ((a, w2, w1), (b, w0, w2), (c, w1, w0), (w0, w1, w2))[child]
    return np.array([a, b, c])


def trixel_area(index: int) -> float:
    """Solid angle of an HTM trixel in deg^2 (an exact spherical triangle, Van Oosterom & Strackee 1983)."""
    a, b, c = htm_trixel(index)
    return 2.0 * math.atan2(abs(float(a @ np.cross(b, c))), 1.0 + float(a @ b + b @ c + c @ a)) * DEG2_PER_SR


def trixel_contains(index: int, ra, dec) -> np.ndarray:
    """Which positions (degrees) lie in an HTM trixel (edges included)."""
    a, b, c = htm_trixel(index)
    v = unit_vector(np.asarray(ra, dtype=np.float64), np.asarray(dec, dtype=np.float64))
    return (v @ np.cross(a, b) >= 0) & (v @ np.cross(b, c) >= 0) & (v @ np.cross(c, a) >= 0)


def trixel_centre(index: int) -> tuple:
    """(ra, dec) in degrees of the normalised sum of a trixel's corners."""
    v = htm_trixel(index).sum(axis=0)
    v /= np.linalg.norm(v)
    return float(np.degrees(np.arctan2(v[1], v[0])) % 360.0), float(np.degrees(np.arcsin(v[2])))


# -- the calibration of the bright luminosity function ------------------------------------------------

#: [mag] the fit uses stars brighter than this J129 (AB): where the Gaia DR2 chunks are complete
FIT_MAG_LIMIT = 18.0


def read_gaia_chunk(path: str) -> dict:
    """J, H (AB), parallax and its error (mas), and the HTM trixel of a Gaia DR2 reference-catalogue chunk.

    The chunk's file name is its trixel id (LSST convention, e.g. 145649.fits).
    """
    stem = os.path.basename(path).split(".")[0]
    if not stem.isdigit():
        raise PerscliError(f"{path}: a Gaia chunk is named by its HTM trixel id (e.g. 145649.fits)")
    with fits.open(path) as hdul:
        data = hdul[1].data
        units = {c.name: c.unit for c in hdul[1].columns}
        for col in ("parallax", "parallaxErr"):
            if units.get(col) not in (None, "rad"):
                raise PerscliError(f"{path}: column {col} is in {units.get(col)!r}, expected 'rad'")
        rad_to_mas = math.degrees(1.0) * 3.6e6
        j, h, _, has_colour = gaia_roman_jh(data["phot_g_mean_flux"], data["phot_bp_mean_flux"],
                                            data["phot_rp_mean_flux"])
        err = np.asarray(data["parallaxErr"], dtype=np.float64) * rad_to_mas
        return {"trixel": int(stem), "j": j, "h": h, "has_colour": has_colour,
                "parallax": np.asarray(data["parallax"], dtype=np.float64) * rad_to_mas
                + GAIA_DR2_PARALLAX_ZERO_POINT,
                "parallax_error": err, "has_parallax": err > 0,
                "ra": np.degrees(np.asarray(data["coord_ra"], dtype=np.float64)) % 360.0,
                "dec": np.degrees(np.asarray(data["coord_dec"], dtype=np.float64))}


def fit_luminosity_function(paths, model: GalacticStarModel | None = None, *, edges=GAIA_LF_EDGES,
                            mag_limit: float = FIT_MAG_LIMIT, iterations: int = 5000) -> dict:
    """Fit the bright luminosity function to Gaia DR2 chunks: how the rows M_J < 8 of :data:`LF_TABLE` were made.

    Poisson maximum likelihood, by expectation-maximisation, of Phi in the
    bins ``edges`` (the rows of :data:`TAIL_LF` below them held fixed),
    given each star's J and parallax: star i contributes
    sum_k Phi_k A_ik with A_ik = Omega sum_d rho(d) d^2 dd [J_i - mu(d) in bin k]
    N(parallax_i | 1000/d, sigma_i) (no parallax term for stars without a
    parallax), and the expected count over J < ``mag_limit`` is
    sum_k Phi_k E_k.

    Returns
    -------
    dict
        ``edges``, ``phi`` (per pc^3 per mag), ``n`` (expected stars of
        each bin in the sample), ``jh_mean``, ``jh_sigma`` ((J-H)_AB of the
        stars with their own colour, weighted by their probability of
        being in each bin), ``n_stars``.
    """
    model = GalacticStarModel() if model is None else model
    edges = np.asarray(edges, dtype=np.float64)
    tail = np.array(TAIL_LF, dtype=np.float64)
    lo = np.concatenate([edges[:-1], tail[:, 0]])
    hi = np.concatenate([edges[1:], tail[:, 1]])
    nb = edges.size - 1
    mu = model.mu_grid
    d = 10.0 ** (mu / 5.0 + 1.0)
    rows, expected, jh, has_colour = [], np.zeros(lo.size), [], []
    for path in paths:
        chunk = read_gaia_chunk(path)
        ra0, dec0 = trixel_centre(chunk["trixel"])
        l, b = galactic_coordinates(ra0, dec0)
        volume = model.line_of_sight(float(l), float(b)) * (trixel_area(chunk["trixel"]) / DEG2_PER_SR)
        sel = np.isfinite(chunk["j"]) & (chunk["j"] < mag_limit)
        absolute = (chunk["j"][sel] - J_AB_MINUS_VEGA)[:, None] - mu[None, :]
        sigma = np.where(chunk["has_parallax"][sel], chunk["parallax_error"][sel], 1.0)[:, None]
        like = np.where(chunk["has_parallax"][sel][:, None],
                        np.exp(-0.5 * ((chunk["parallax"][sel][:, None] - 1000.0 / d[None, :]) / sigma) ** 2)
                        / sigma, 1.0) * volume[None, :]
        a = np.empty((sel.sum(), lo.size))
        for k in range(lo.size):
            a[:, k] = np.where((absolute >= lo[k]) & (absolute < hi[k]), like, 0.0).sum(axis=1)
            top = np.minimum(hi[k], mag_limit - J_AB_MINUS_VEGA - mu)
            expected[k] += float(np.clip(top - lo[k], 0.0, None) @ volume)
        rows.append(a)
        jh.append((chunk["j"] - chunk["h"])[sel])
        has_colour.append(chunk["has_colour"][sel])
    a = np.vstack(rows)
    jh, has_colour = np.concatenate(jh), np.concatenate(has_colour)
    phi = np.concatenate([np.full(nb, 1e-3), tail[:, 2]])
    for _ in range(iterations):
        r = a * phi
        r /= np.where(r.sum(axis=1, keepdims=True) > 0, r.sum(axis=1, keepdims=True), 1.0)
        phi[:nb] = r[:, :nb].sum(axis=0) / expected[:nb]
    r = a * phi
    r /= np.where(r.sum(axis=1, keepdims=True) > 0, r.sum(axis=1, keepdims=True), 1.0)
    w = r * has_colour[:, None]
    n_w = w.sum(axis=0)
    mean = (w * jh[:, None]).sum(axis=0) / np.where(n_w > 0, n_w, 1.0)
    sig = np.sqrt((w * (jh[:, None] - mean) ** 2).sum(axis=0) / np.where(n_w > 0, n_w, 1.0))
    return {"edges": edges, "phi": phi[:nb], "n": r.sum(axis=0)[:nb], "jh_mean": mean[:nb],
            "jh_sigma": sig[:nb], "n_stars": int(a.shape[0])}
