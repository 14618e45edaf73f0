"""The settings of persistence, with their defaults written once, and of ``perscli apply-persistence``.

The presets of the persistence law (:data:`PRESETS`) and the settings that say
how it is applied (:data:`SETTINGS`, :data:`PRESET_SETTINGS`) are the one home
of those values: the persistence step's schema
(:class:`perscli.detector.effects.Persistence`), the law
(:class:`perscli.detector.persistence.PersistenceModel`) and the loader
(:func:`perscli.detector.model.load_persistence_model`) take them from here.
:class:`ApplyOptions` holds how ``perscli apply-persistence`` writes its result
(:func:`perscli.detector.apply.apply_persistence_files` takes one; the
command's option defaults come from it).  This module imports nothing heavy,
so that ``--help`` stays fast.
"""

from __future__ import annotations

import dataclasses

from .. import instrument as _instrument
from .params import Param

#: Parameter sets of the law.
#:
#: 'typical' and 'pessimistic': the paper's Table 1 (Lin et al., H4RG lab fits;
#: GalSim's Roman module uses 'typical'), with the paper's linear law below
#: half_well = 5e4 e- (its "Implementation of persistence effect").
#:
#: 'wfc3': HST WFC3-IR, the Fermi-function form of Long et al. (2012, SPIE 8442,
#: cited by the paper; the exposure-time dependent version is WFC3 ISR 2015-15)
#: with the parameters of STScI's WFC3 persistence software: norm 0.3 (A, e-/s at
#: t = 1000 s), alpha 0.174, gamma 1.0, x0 9.0e4 e- and dx 2.0e4 e-, in the parametrisation
#: used here.  Long's law has
#: no linear branch: the Fermi function holds down to zero fluence, which
#: half_well = 0 expresses.  STScI's later "A-gamma" model tabulates A and gamma
#: against fluence and exposure time from calibration data that perscli does not
#: hold; these single values are its Fermi-law predecessor.
PRESETS = {
    "typical": dict(A=0.017, x0=6.0e4, dx=5.0e4, alpha=0.045, gamma=1.0, half_well=5.0e4),
    "pessimistic": dict(A=0.086, x0=1.37e5, dx=2.6e4, alpha=0.02, gamma=1.0, half_well=5.0e4),
    "wfc3": dict(A=0.3, x0=9.0e4, dx=2.0e4, alpha=0.174, gamma=1.0, half_well=0.0),
}

#: How a preset is applied when it is chosen by name (``--model wfc3``, or ``base: wfc3`` in a
#: YAML file); the settings of a preset missing here are the defaults of :data:`SETTINGS`.
#: 'wfc3' follows STScI's WFC3-IR persistence pipeline (and the WFC3 Data Handbook, ch. 8): the
#: current at the MIDDLE of the later exposure times its length, the per-pixel MAXIMUM over
#: earlier exposures rather than their sum, every earlier exposure of the last 16 hours
#: (older ones are ignored), however many there are.
PRESET_SETTINGS = {
    "wfc3": dict(time_model="middle", combine="max", max_previous=0, lookback=16.0),
}

#: GalSim's linear persistence coefficients (galsim.roman.persistence_coefficients):
#: the fraction of the i-th most recent earlier exposure added to the current one.
GALSIM_LINEAR_COEFFICIENTS = (
    4.5707683e-4, 1.4959818e-4, 9.115737e-5, 6.56769e-5,
    5.135571e-5, 4.217028e-5, 3.577534e-5, 3.106601e-5,
)

#: GalSim's Roman exposure time (galsim.roman.exptime), used by its 'fermi' method.
GALSIM_EXPTIME = _instrument.ROMAN_EXPTIME

#: The schema of the Fermi parameters: name -> (description, unit).
FERMI_PARAMETERS = {
    "A": ("normalisation of the current at t = 1000 s", "e-/s"),
    "x0": ("fluence of the Fermi step", "e-"),
    "dx": ("width of the Fermi step", "e-"),
    "alpha": ("power-law index of the fluence dependence", ""),
    "gamma": ("power-law index of the decay in time", ""),
    "half_well": ("fluence below which the law is linear (0: the Fermi law down to zero fluence)", "e-"),
}

TIME_MODELS = ("exact", "middle", "galsim")
COMBINES = ("sum", "max")
#: what of an earlier exposure persists (besides a number: its FLUENCE above that many electrons)
SOURCES = ("drawn", "stars", "all")
#: how the persistence charge is rounded before it is added (perscli.detector.persistence.round_charge)
ROUNDINGS = ("none", "round", "floor")

#: How a model is applied (not the law itself): name -> (description, allowed values, default).
#: The one home of these settings: the persistence step's schema (perscli.detector.effects) is made
#: from it; a preset may bring its own values (:data:`PRESET_SETTINGS`).
SETTINGS = {
    "time_model": ("exact: the rate integrated over the exposure; middle: the rate at its middle x its length "
                   "(the WFC3 pipeline); galsim: GalSim's mid-exposure rate x 139.8 s", TIME_MODELS, "exact"),
    "combine": ("sum over earlier exposures (the paper, GalSim) or per-pixel max (WFC3 pipeline)", COMBINES, "sum"),
    "max_previous": ("only the N most recent earlier exposures count (0: all; the paper: 10)", "integer >= 0", 10),
    "lookback": ("hours: earlier exposures that ended longer ago than this before the current one starts are "
                 "ignored (0: no limit; WFC3 pipeline: 16)", "number >= 0", 0.0),
}


def preset_settings(base: str) -> dict:
    """The settings a preset brings: :data:`SETTINGS`' defaults, updated by :data:`PRESET_SETTINGS`."""
    out = {key: default for key, (_, _, default) in SETTINGS.items()}
    out.update(PRESET_SETTINGS.get(base, {}))
    return out


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


def _persistence_schema():
    bounds = {"A": dict(lo=0.0), "x0": dict(lo=0.0, lo_open=True), "dx": dict(lo=0.0, lo_open=True),
              "half_well": dict(lo=0.0)}
    law = tuple(Param(key, "float", None, unit, f"{text} (default: from base)", derived="base", **bounds.get(key, {}))
                for key, (text, unit) in FERMI_PARAMETERS.items())
    return (
        Param("base", "choice", "typical", "", "the paper's parameter set (Table 1) the law starts from",
              choices=tuple(PRESETS)),
        Param("kind", "choice", "fermi", "", "fermi: the paper's rate F(x) (t/1000 s)^-gamma; linear: GalSim's "
              "coefficients x fluence", choices=("fermi", "linear")),
        *law,
        Param("coefficients", "floats", list(GALSIM_LINEAR_COEFFICIENTS), "",
              "kind linear: fraction of each earlier exposure's fluence, most recent first (galsim.roman)"),
        # the settings of how the law is applied: defaults from the base preset (wfc3 brings the WFC3
        # pipeline's), written once in perscli.detector.settings.SETTINGS
        *(Param(key, kind, None, unit, f"{text} (default: from base)", derived="base", **extra)
          for key, (kind, unit, extra) in (("time_model", ("choice", "", dict(choices=TIME_MODELS))),
                                           ("combine", ("choice", "", dict(choices=COMBINES))),
                                           ("max_previous", ("int", "", dict(lo=0))),
                                           ("lookback", ("float", "h", dict(lo=0.0))))
          for text in (SETTINGS[key][0],)),
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
#: ``--set``, and :class:`perscli.detector.persistence.PersistenceModel` itself).
PERSISTENCE_SCHEMA = _persistence_schema()


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

    mode: str = "add"
    model_error: float = DEFAULT_MODEL_ERROR
    flag_above: float | None = None
    dq_bit: int = DEFAULT_DQ_BIT
    units: str | None = None
    gain: float | None = None
    exptime: float | None = None
    gap: float | None = None
    compress: str = "none"
