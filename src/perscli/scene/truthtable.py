"""The truth catalogue as a FITS file: column descriptions, header keywords, and writing it.

:func:`truth_hdulist` turns a catalogue of
:func:`perscli.scene.catalog.make_truth_catalog` into an empty primary HDU,
the 'TRUTH' table (units and a TCOMMn description per column,
:data:`_COLUMN_INFO`; the ``meta`` keywords with their comments,
:data:`KEYWORD_COMMENTS`, and provenance) and, for footprints, the
'FOOTPRNT' table; :func:`write_truth_catalog` writes it atomically.
"""

from __future__ import annotations

import re

import numpy as np

from ..instrument import ROMAN_FILTERS
from ..io.cards import format_card
from ..io.fitsfile import OutHDU, table_hdu
from ..io.output import add_provenance, write_hdus
from .starcounts import META_KEYWORDS as _STAR_META

#: header keyword -> comment, for the keywords :func:`make_truth_catalog` puts in ``meta``
KEYWORD_COMMENTS = {
    "FIELDRA": "[deg] field centre, RA",
    "FIELDDEC": "[deg] field centre, Dec",
    "FIELDSZ": "[arcmin] side of the square field (TAN plane)",
    "FIELDAR": "[arcmin2] solid angle of the field",
    "REGION": "field: square, or union of footprints",
    "NFOOT": "footprints (table FOOTPRNT)",
    "FOOTMARG": "[arcsec] each footprint grown by this much",
    "BOXAREA": "[arcmin2] bounding box drawn from (TAN plane)",
    "POSMODEL": "positions in the field",
    "GALDENS": "[arcmin-2] mean galaxy density (Poisson)",
    "NGAL": "galaxies in the catalog",
    "STARSRC": "stars: model or gaia",
    "STARMOD": "star model: galactic or powerlaw",
    "STARDENS": "[arcmin-2] power-law stars: density (Poisson)",
    "STARLF": "star model: luminosity function (J band)",
    "SDENSC": "[arcmin-2] star model: density at field centre",
    "NSTAR": "stars in the catalog",
    "GPROFILE": "galaxy light profile",
    "GMAGSLP": "galaxies: dN/dm ~ 10^(GMAGSLP m), J129 AB",
    "GMAGMIN": "galaxies: brightest J129 (AB)",
    "GMAGMAX": "galaxies: faintest J129 (AB)",
    "GJHMEAN": "galaxies: mean J-H",
    "GJHSIG": "galaxies: scatter of J-H",
    "GHLR23": "[arcsec] galaxies: median hlr at J=23",
    "GHLRSLP": "galaxies: d log10(hlr)/dJ",
    "GHLRSIG": "galaxies: scatter of log10(hlr)",
    "GHLRMIN": "[arcsec] galaxies: smallest half-light radius",
    "GHLRMAX": "[arcsec] galaxies: largest half-light radius",
    "GESIG": "galaxies: per-component sigma of intrinsic g",
    "GEMAX": "galaxies: |g| above this is redrawn",
    "EDEFN": "e1, e2 as galsim.Shear(g1=e1, g2=e2)",
    "SMAGSLP": "stars: dN/dm ~ 10^(SMAGSLP m), J129 AB",
    "SMAGMIN": "stars: brightest J129 (AB)",
    "SMAGMAX": "stars: faintest J129 (AB)",
    **{key: comment for key, comment in _STAR_META.values() if key not in ("SMAGMIN", "SMAGMAX")},
    "SJHMEAN": "stars: mean J-H",
    "SJHSIG": "stars: scatter of J-H",
    "SJHMIN": "stars: J-H clipped below",
    "SJHMAX": "stars: J-H clipped above",
    "GAIANIN": "Gaia rows read (distinct ids)",
    "GAIANOG": "Gaia rows without G flux (dropped)",
    "GAIANMED": "Gaia stars in the field given the median colour",
    "GAIABPRP": "median BP-RP (Vega) of the Gaia stars read",
    "COLMODEL": "other filters from J129 and H158",
}

_COLUMN_INFO = {
    "id": (None, "unique object number"),
    "ra": ("deg", "right ascension (ICRS)"),
    "dec": ("deg", "declination (ICRS)"),
    "kind": (None, "galaxy or star"),
    "hlr": ("arcsec", "half-light radius (0 for stars)"),
    "e1": (None, "intrinsic reduced shear g1 (galsim.Shear)"),
    "e2": (None, "intrinsic reduced shear g2 (galsim.Shear)"),
    "gaia_id": (None, "Gaia DR2 source id (-1: not from Gaia)"),
    **{f"mag_{f}": ("mag", f"AB magnitude in {f}") for f in ROMAN_FILTERS},
}

_INPUT_STEM = re.compile(r"^GA\d{3}$")


def catalog_step(table) -> str:
    """One line for the HISTORY card of a catalog."""
    m = table.meta
    if m.get("STARSRC") == "gaia":
        stars = f"gaia files={sum(1 for k in m if _INPUT_STEM.match(k))}"
    elif m.get("STARMOD") == "galactic":
        stars = "star-model=galactic"
    else:
        stars = f"star-density={m.get('STARDENS')}"
    where = (f"footprints={m['NFOOT']} margin={m['FOOTMARG']}" if m.get("REGION") == "footprints"
             else f"ra={m['FIELDRA']} dec={m['FIELDDEC']} size={m['FIELDSZ']}")
    return f"catalog {where} galaxy-density={m['GALDENS']} {stars} galaxies={m['NGAL']} stars={m['NSTAR']}"


def truth_hdulist(table):
    """The FITS file of a truth catalog: an empty primary HDU and the 'TRUTH' table with provenance.

    Returns
    -------
    list of perscli.io.fitsfile.OutHDU
    """
    columns = {name: np.asarray(table[name]) for name in table.colnames}
    units = {name: str(table[name].unit) for name in table.colnames if table[name].unit is not None}
    cards = [format_card(f"TCOMM{k}", _COLUMN_INFO[name][1]) for k, name in enumerate(table.colnames, 1)]
    hdu = table_hdu(columns, "TRUTH", units=units, cards=cards)
    meta = dict(table.meta)
    seed = meta.pop("SEED", None)
    footprints = meta.pop("FOOTPRINTS", None)
    extra_inputs = meta.pop("INPUTS", [])
    stems = [k for k in meta if _INPUT_STEM.match(k)]
    inputs = [(k, meta.pop(k), meta.pop(f"{k}DS")) for k in stems] + list(extra_inputs)
    params = {}
    for key, value in meta.items():
        comment = KEYWORD_COMMENTS.get(key)
        if key.startswith("LEFF"):
            comment = f"[um] effective wavelength of {key[4:]}"
        params[key] = (value, comment) if comment else value
    add_provenance(hdu, step=catalog_step(table), params=params, inputs=inputs, seed=seed)
    hdus = [OutHDU([]), hdu]
    if footprints is not None:
        # the footprints as given (before the margin), so that the region can be rebuilt
        corners = {"corner_ra": np.array([r for r, _ in footprints], dtype=np.float64).reshape(len(footprints), -1),
                   "corner_dec": np.array([d for _, d in footprints], dtype=np.float64).reshape(len(footprints), -1)}
        hdus.append(table_hdu(corners, "FOOTPRNT", units={"corner_ra": "deg", "corner_dec": "deg"},
                              cards=[format_card("TCOMM1", "footprint corners, in order around it: RA"),
                                     format_card("TCOMM2", "footprint corners: Dec"),
                                     format_card("FOOTMARG", float(table.meta["FOOTMARG"]),
                                                 "[arcsec] objects drawn within this of them")]))
    return hdus


def write_truth_catalog(table, dest: str, *, overwrite: bool = False, stdout=None) -> None:
    """Write a catalog from :func:`make_truth_catalog` atomically (or to standard output for '-')."""
    write_hdus(truth_hdulist(table), dest, overwrite=overwrite, stdout=stdout)
