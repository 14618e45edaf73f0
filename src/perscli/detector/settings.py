"""The settings of persistence, with their defaults written once, and of ``perscli apply-persistence``.

Every parameter of a persistence model is written once, in the table
:data:`PERSISTENCE_PARAMETERS` (corr2's parameter dict is the model: type,
default or per-preset values, bounds, documentation).  The persistence step's
schema (:class:`perscli.detector.effects.Persistence`), the presets
(:data:`PRESETS`, :func:`preset_settings`), the law's defaults
(:class:`perscli.detector.persistence.PersistenceModel`), the loader
(:func:`perscli.detector.model.load_persistence_model`) and
``apply-persistence``'s options are made from it.
:class:`ApplyOptions` holds how ``perscli apply-persistence`` writes its result
(:func:`perscli.detector.apply.apply_persistence_files` takes one; the
command's option defaults come from it).  This module imports nothing heavy,
so that ``--help`` stays fast.
"""

from __future__ import annotations

import dataclasses

from .. import instrument as _instrument
from ..settings import Param
from ..settings import setting

#: The presets of the law, by name.
#:
#: 'typical' and 'pessimistic': the paper's Table 1 (Lin et al., H4RG lab fits;
#: GalSim's Roman module uses 'typical'), with the paper's linear law below
#: half_well = 5e4 e- (its "Implementation of persistence effect").
#:
#: 'wfc3': HST WFC3-IR, the Fermi-function form of Long et al. (2012, SPIE 8442,
#: cited by the paper; the exposure-time dependent version is WFC3 ISR 2015-15)
#: with the parameters of STScI's WFC3 persistence software: norm 0.3 (A, e-/s at
#: t = 1000 s), alpha 0.174, gamma 1.0, x0 9.0e4 e- and dx 2.0e4 e-, in the parametrisation
#: used here.  Long's law has no linear branch: the Fermi function holds down to zero
#: fluence, which half_well = 0 expresses.  STScI's later "A-gamma" model tabulates A and
#: gamma against fluence and exposure time from calibration data that perscli does not
#: hold; these single values are its Fermi-law predecessor.  'wfc3' also brings how STScI's
#: WFC3-IR persistence pipeline applies the law (and the WFC3 Data Handbook, ch. 8): the
#: current at the MIDDLE of the later exposure times its length, the per-pixel MAXIMUM over
#: earlier exposures rather than their sum, every earlier exposure of the last 16 hours
#: (older ones are ignored), however many there are.
PRESET_NAMES = ("typical", "pessimistic", "wfc3")

#: The preset a model starts from when none is named (GalSim's Roman module uses it).
DEFAULT_PRESET = "typical"

#: GalSim's linear persistence coefficients (galsim.roman.persistence_coefficients):
#: the fraction of the i-th most recent earlier exposure added to the current one.
GALSIM_LINEAR_COEFFICIENTS = (
    4.5707683e-4, 1.4959818e-4, 9.115737e-5, 6.56769e-5,
    5.135571e-5, 4.217028e-5, 3.577534e-5, 3.106601e-5,
)

#: GalSim's Roman exposure time (galsim.roman.exptime), used by its 'fermi' method.
GALSIM_EXPTIME = _instrument.ROMAN_EXPTIME

TIME_MODELS = ("exact", "middle", "galsim")
COMBINES = ("sum", "max")
#: what of an earlier exposure persists (besides a number: its FLUENCE above that many electrons)
SOURCES = ("drawn", "stars", "all")
#: how the persistence charge is rounded before it is added (perscli.detector.persistence.round_charge)
ROUNDINGS = ("none", "round", "floor")


def _by_preset(typical, pessimistic, wfc3):
    return dict(zip(PRESET_NAMES, (typical, pessimistic, wfc3)))


#: THE table of persistence parameters: each one's type, unit, allowed values, description and default
#: (a parameter whose value comes with the preset holds it for every preset in ``presets``), written
#: here once.  Made from it: the persistence step's schema (:class:`perscli.detector.effects.Persistence`,
#: so ``render --set persistence.KEY=``, ``--list-effects``, a model file's checks), :data:`PRESETS`, the
#: law's field defaults (:class:`perscli.detector.persistence.PersistenceModel`), ``apply-persistence``'s
#: options of the settings, and the man pages.  ``group``: 'law' (a parameter of the Fermi law),
#: 'setting' (how the law is applied to a sequence of exposures), '' (neither: what persists and how
#: the charge is stored).
PERSISTENCE_PARAMETERS = (
    Param("base", "choice", DEFAULT_PRESET, "", "the paper's parameter set (Table 1) the law starts from",
          choices=PRESET_NAMES),
    Param("kind", "choice", "fermi", "", "fermi: the paper's rate F(x) (t/1000 s)^-gamma; linear: GalSim's "
          "coefficients x fluence", choices=("fermi", "linear")),
    Param("A", "float", None, "e-/s", "normalisation of the current at t = 1000 s", lo=0.0, group="law",
          presets=_by_preset(0.017, 0.086, 0.3)),
    Param("x0", "float", None, "e-", "fluence of the Fermi step", lo=0.0, lo_open=True, group="law",
          presets=_by_preset(6.0e4, 1.37e5, 9.0e4)),
    Param("dx", "float", None, "e-", "width of the Fermi step", lo=0.0, lo_open=True, group="law",
          presets=_by_preset(5.0e4, 2.6e4, 2.0e4)),
    Param("alpha", "float", None, "", "power-law index of the fluence dependence", group="law",
          presets=_by_preset(0.045, 0.02, 0.174)),
    Param("gamma", "float", None, "", "power-law index of the decay in time", group="law",
          presets=_by_preset(1.0, 1.0, 1.0)),
    Param("half_well", "float", None, "e-", "fluence below which the law is linear (0: the Fermi law down to zero "
          "fluence)", lo=0.0, group="law", presets=_by_preset(5.0e4, 5.0e4, 0.0)),
    Param("coefficients", "floats", list(GALSIM_LINEAR_COEFFICIENTS), "",
          "kind linear: fraction of each earlier exposure's fluence, most recent first (galsim.roman)"),
    Param("time_model", "choice", None, "", "exact: the rate integrated over the exposure; middle: the rate at its "
          "middle x its length (the WFC3 pipeline); galsim: GalSim's mid-exposure rate x 139.8 s",
          choices=TIME_MODELS, group="setting", presets=_by_preset("exact", "exact", "middle")),
    Param("combine", "choice", None, "", "sum over earlier exposures (the paper, GalSim) or per-pixel max (WFC3 "
          "pipeline)", choices=COMBINES, group="setting", presets=_by_preset("sum", "sum", "max")),
    Param("max_previous", "int", None, "", "only the N most recent earlier exposures count (0: all; the paper: 10)",
          lo=0, group="setting", presets=_by_preset(10, 10, 0)),
    Param("lookback", "float", None, "h", "hours: earlier exposures that ended longer ago than this before the "
          "current one starts are ignored (0: no limit; WFC3 pipeline: 16)", lo=0.0, group="setting",
          presets=_by_preset(0.0, 0.0, 16.0)),
    Param("source", "float", "drawn", "e-", "what of an earlier exposure persists: drawn (its DRAWN: the "
          "expected light of every object drawn on it, galaxies and stars, no sky: the paper's pipeline and the "
          "study's headline), stars (its STARFLU: the light of stars only), all (its FLUENCE: every photon "
          "collected, the sky's too, after saturation), or a number: only pixels whose FLUENCE exceeds that many "
          "electrons", lo=0.0, choices=SOURCES),
    Param("floor", "float", 0.0, "e-", "pixels of an earlier exposure whose persisting fluence (DRAWN, STARFLU "
          "or FLUENCE) is at or below this leave nothing: how far faint light persists (0: all of it, the linear "
          "law down to zero, as the paper states it)", lo=0.0),
    Param("fluence_cap", "float", "none", "e-", "the fluence fed to the law is at most this: none = no cap "
          "(the paper's pipeline: GalSim's applyPersistence caps nothing, the law is extrapolated beyond the "
          "well), well = saturation.full_well (no cap with saturation off), or electrons", lo=0.0,
          lo_open=True, choices=("well", "none")),
    Param("rounding", "choice", "none", "", "the persistence charge added to a frame: none = as computed; "
          "round = rounded to whole electrons; floor = truncated to whole electrons, as a cast to integers "
          "does (how a pipeline may have stored a persistence image: a bracket of the paper's numbers)",
          choices=ROUNDINGS),
)

#: The persistence step's parameters (:class:`perscli.detector.effects.Persistence`), the one schema
#: of a persistence model: every form of a model is checked with it (the loader, the step's
#: ``--set``, and :class:`perscli.detector.persistence.PersistenceModel` itself).  A parameter whose
#: value comes with the preset has no default of its own here: it is taken from ``base``.
PERSISTENCE_SCHEMA = tuple(
    dataclasses.replace(p, description=f"{p.description} (default: from base)", derived="base") if p.presets else p
    for p in PERSISTENCE_PARAMETERS)

_BY_NAME = {p.name: p for p in PERSISTENCE_PARAMETERS}

#: The names of the Fermi law's parameters, in the table's order.
FERMI_PARAMETERS = tuple(p.name for p in PERSISTENCE_PARAMETERS if p.group == "law")

#: The names of the settings of how a law is applied (time_model, combine, max_previous, lookback).
SETTINGS = tuple(p.name for p in PERSISTENCE_PARAMETERS if p.group == "setting")

#: Parameter sets of the law, by preset: name -> {parameter: value} (made from the table).
PRESETS = {name: {key: _BY_NAME[key].presets[name] for key in FERMI_PARAMETERS} for name in PRESET_NAMES}


def preset_settings(base: str) -> dict:
    """The settings a preset brings (time_model, combine, max_previous, lookback), from the table."""
    return {key: _BY_NAME[key].presets[base] for key in SETTINGS}


def persistence_param(name: str) -> Param:
    """The table's entry of one persistence parameter (e.g. for a command option made from it)."""
    return _BY_NAME[name]


def preset_default_text(name: str) -> str:
    """'[default: the law's NAME; VALUE, wfc3: VALUE]': a preset-dependent setting's default as help shows it.

    The default preset's value first, then every preset that brings another one.
    """
    def text(value):
        return f"{value:g}" if isinstance(value, float) else str(value)

    values = _BY_NAME[name].presets
    own = "".join(f", {preset}: {text(value)}" for preset, value in values.items()
                  if value != values[DEFAULT_PRESET])
    return f"[default: the law's {name}; {text(values[DEFAULT_PRESET])}{own}]"


MODES = ("add", "subtract", "predict")

#: Fractional uncertainty of the predicted persistence (the default of ``model_error``): a judgement,
#: not a published or fitted figure.  The WFC3 Data Handbook (ch. 8) gives no
#: number; it says the model can differ from the short-term persistence and underestimates it after
#: spatial scans.  0.3 stands for "good to some tens of per cent"; give your own with --model-error.
DEFAULT_MODEL_ERROR = 0.3

#: The DQ value ORed into pixels flagged for persistence (the default of ``dq_bit``).  In the
#: WFC3 Data Handbook's table of data quality flags, as we recall it (not checked here against
#: the current edition), calwf3 sets 1-512 and 2048-8192 in IR data, while 1024 marks charge
#: traps in UVIS data only, so it is free in IR frames; 32768 does not fit HST's signed 16-bit DQ.
#: Check it against the DQ definitions of your pipeline, or choose another (JWST's stcal names
#: 32 PERSISTENCE).
DEFAULT_DQ_BIT = 1024




@dataclasses.dataclass(frozen=True)
class ApplyOptions:
    """How ``perscli apply-persistence`` reads its inputs and writes its result.

    The law and its settings (time_model, combine, max_previous, lookback) are
    the model's (:class:`~perscli.detector.persistence.PersistenceModel`).

    Attributes
    ----------
    mode : {'add', 'subtract', 'predict'}
        Data plus persistence, data minus persistence, or persistence alone.
    model_error : float
        Fractional uncertainty of the persistence, into ERR
        (see :func:`~perscli.detector.apply.apply_to_frame`).
    flag_above : float or None
        e-/s: flag pixels whose persistence rate exceeds it in DQ (None: no flags).
    dq_bit : int
        The DQ value ``flag_above`` sets.
    units, gain, exptime : optional
        Override BUNIT, GAIN/CCDGAIN and supply EXPTIME for every input.
    gap : float or None
        Ignore header timestamps: the inputs form a regular sequence
        ``previous..., current`` with ``gap`` seconds between exposures.
    compress : {'none', 'gzip', 'rice'}
        Lossless tile compression of the output's images.
    """

    mode: str = setting("add", "choice", "Add persistence, subtract it (a correction), or write the persistence alone.",
                        choices=MODES)
    model_error: float = setting(DEFAULT_MODEL_ERROR, "float", "Fractional uncertainty of the persistence. Where "
                                 "CURRENT has an ERR array (WFC3 flt/ima, JWST): --mode subtract adds FRACTION x "
                                 "persistence to it in quadrature, --mode predict writes FRACTION x persistence; 0 "
                                 "leaves ERR as it is.", lo=0, metavar="FRACTION")
    flag_above: float | None = None
    dq_bit: int = DEFAULT_DQ_BIT
    units: str | None = None
    gain: float | None = None
    exptime: float | None = None
    gap: float | None = None
    compress: str = "none"
