"""The study description: a YAML file checked against a schema, with dotted overrides.

In the manner of GalSim's config: nested sections with defaults, a preset
to start from, ``key.sub=value`` overrides on the command line; unlike it,
every key is checked (a typo is an error naming the closest valid key).
"""

from __future__ import annotations

import copy
import dataclasses
import difflib
import hashlib
import json
import math
import os

import yaml

from .. import PerscliError
from ..detector.model import load_detector_model
from ..instrument import ROMAN_FILTERS as FILTERS, ROMAN_N_SCA, ROMAN_SCA_SIZE
from ..io.config import STUDY_ITEM, parse_value, split_key_value, yaml_problem
from ..measure.settings import MeasureOptions
from ..scene.schedule import BUNDLED_SCHEDULE
from ..scene.settings import CatalogOptions
from ..scene.starcounts import GalacticStarModel, galactic_star_model
from ..stats.budget import _modes_factor, amplitudes
from ..stats.settings import BudgetOptions, CorrelateOptions
from .plan import model_settings

#: the public Roman WAS schedule shipped with perscli (perscli.scene.schedule.BUNDLED_SCHEDULE)
DEFAULT_SCHEDULE = "roman-was"

def _galactic_defaults() -> dict:
    """The Galactic star model's parameters with their defaults (written once, in the model's dataclass)."""
    return {f.name: f.default for f in dataclasses.fields(GalacticStarModel)}


#: the schema: every key with its default; the type of the default is the type required
#: (None: any of str/number/list; a list default: a list)
SCHEMA = {
    "name": "study",
    "seed": 1,
    # realisations: the study again with seeds seed, seed+1, ... (catalogue and noise); the summary gives
    # the scatter across them beside the jackknife errors
    "realisations": 1,
    # differential: render each final only where persistence can reach a galaxy's stamp and measure only
    # the galaxies it changed (every other galaxy has De = 0 exactly); None: when what persists is light
    # drawn from the catalogue (persistence sources drawn and stars)
    "differential": None,
    "field": {
        "ra": 10.0,          # deg, centre of the field
        "dec": -44.0,
        "radius": 0.05,      # deg: finals are exposures whose SCA footprint reaches this circle
    },
    "filter": "J129",
    "scas": [1],
    "exposures": {
        "source": "schedule",    # schedule | plan
        "schedule": DEFAULT_SCHEDULE,
        "after": 0.0,            # MJD: finals start after this
        "count": 2,              # final exposures per SCA (the earliest that reach the field)
        "history": 10,           # earlier exposures of the same SCA counted for persistence
        # plan: a dithered sequence (no schedule needed): every exposure is on the field
        "plan_start": 61541.97,  # MJD
        "plan_pa": 30.0,
        "plan_dither": 30.0,     # arcsec
    },
    "bounds": None,              # [xmin, xmax, ymin, ymax]: render a cutout of each SCA (CI-sized studies)
    "catalog": {
        "galaxy_density": CatalogOptions.galaxy_density,  # per arcmin^2 (the paper)
        # None: stars of the Galactic model (counts per magnitude of the real sky at the field's position;
        # perscli.scene.starcounts), with the parameters of star_model; a number: power-law stars at that
        # density per arcmin^2 (the paper's 2.5 has 1.7 times the real sky's stars brighter than J = 14)
        "star_density": None,
        "star_model": _galactic_defaults(),
        "gaia": [],              # Gaia DR2 chunks: real stars in place of model stars
        "margin_arcsec": 10.0,   # objects just off an SCA still spill light onto it
    },
    "persistence": {
        "models": ["typical", "pessimistic"],
        # what of an earlier exposure persists: drawn (the light drawn on it, galaxies and stars, no sky: the
        # paper's pipeline), stars, all (its whole FLUENCE), or a fluence threshold in electrons
        "sources": ["drawn"],
        # more variants beside the headline, each with every model: name -> detector settings applied after
        # render.set, e.g. {stars: [persistence.source=stars], floor5e4: [persistence.floor=5e4]}
        "bracket": None,
    },
    "render": {
        "compress": "gzip",      # lossless tiles: frames are most of a study's bytes
        # the persistence image of each final (PERSIST): 44 of a final's 58 MB compressed, and
        # nothing downstream reads it; the paper preset would pass 1 TB with it
        "write_persist": False,
        "set": [],               # detector-model overrides, e.g. ["read_noise.sigma=5"]
    },
    "measure": {
        "joint": True,           # one shape per galaxy from all its final exposures (the paper's pipeline)
        "min_snr": None,         # predicted-S/N cut (None: measure's default)
        "stamp": MeasureOptions.stamp,   # measure's own default (perscli.measure.settings)
        # differential joint fits: the galaxies spread over this many strips of the sky (one task each, whose
        # memory holds its galaxies' stamps on every final), each fitting the reference once for every
        # variant; 0: one strip per 0.1 deg^2 of the field (at least 2)
        "parts": 0,
        # this many consecutive finals of an SCA in one task: they share their earlier exposures, whose light
        # is drawn once
        "chunk": 32,
        # differential study: also fit every changed galaxy's variants from the start (as a fit of their data
        # alone is), beside the fit from the reference's minimum: the check of the linear response, in the
        # shape tables (de1_cold, de2_cold) and the summary; ~3 times the fitting time
        "check": False,
    },
    "correlate": {
        # correlate's own defaults (perscli.stats.settings), in arcmin
        "min_sep": CorrelateOptions.min_sep,
        "max_sep": CorrelateOptions.max_sep,
        "nbins": CorrelateOptions.nbins,
        "npatch": CorrelateOptions.npatch,
        # the study's: the paper's fractions and one between them
        "thresholds": [1e-8, 1e-6, 1e-4],
    },
    "budget": {
        "bands": BudgetOptions.bands,
        "modes": BudgetOptions.modes,
    },
}

#: presets: overrides of the schema's defaults
PRESETS = {
    # a laptop-sized study: one SCA, its three earliest exposures of the field, each with its 10
    # earlier exposures; both models, the paper's setting (the drawn light of every earlier exposure
    # persisting, one joint shape per galaxy).  SCA 7: of the schedule's J129 exposures, none puts
    # SCA 1 within 0.05 deg of (10, -44); seven put SCA 7 there
    "small": {
        "name": "small",
        "scas": [7],
        "exposures": {"count": 3, "history": 10},
    },
    # the paper's size in the paper's setting: 6.25 deg^2 (a circle of radius 1.41 deg), every J129
    # exposure reaching it on all 18 SCAs, 10 earlier exposures each (any filter), their drawn light
    # persisting through the law with its linear branch, one joint shape per galaxy over all its exposures
    "paper": {
        "name": "paper",
        "field": {"radius": 1.41},
        "scas": list(range(1, 19)),
        "exposures": {"count": 0, "history": 10},   # count 0: every exposure reaching the field
    },
    # the test suite's: a 512-pixel corner of SCA 1 in a planned sequence (no data needed), two
    # finals with three earlier exposures each, small dithers and 8x the stars so that ghosts
    # land on galaxies even on so small an area
    "ci": {
        "name": "ci",
        # a planned sequence points the boresight at the field: the sample's circle must reach SCA 1
        "field": {"radius": 0.6},
        "scas": [1],
        "bounds": [1, 512, 1, 512],
        "exposures": {"source": "plan", "count": 2, "history": 3, "plan_dither": 3.0},
        "catalog": {"galaxy_density": CatalogOptions.galaxy_density, "star_density": 20.0},
        "measure": {"parts": 2},
        "correlate": {"min_sep": 0.1, "max_sep": 1.0, "nbins": 4, "npatch": 4},
    },
}


def _merge(base: dict, over: dict, where: str = "") -> dict:
    out = copy.deepcopy(base)
    for key, value in over.items():
        path = f"{where}{key}"
        if key not in base:
            close = difflib.get_close_matches(str(key), [str(k) for k in base], n=1)
            hint = f" (did you mean {where}{close[0]}?)" if close else ""
            raise PerscliError(f"unknown study setting {path!r}{hint}; valid here: {', '.join(map(str, base))}")
        if isinstance(base[key], dict):
            if not isinstance(value, dict):
                raise PerscliError(f"study setting {path!r} must be a mapping of settings, not {value!r}")
            out[key] = _merge(base[key], value, path + ".")
        else:
            out[key] = _coerce(path, base[key], value)
    return out


def _coerce(path: str, default, value):
    if default is None or value is None:
        return value
    if isinstance(default, bool):
        if isinstance(value, bool):
            return value
        raise PerscliError(f"study setting {path!r} must be true or false, not {value!r}")
    if isinstance(default, (int, float)):
        # true/false are not 1/0 here, nor are NaN and infinity numbers a study can use
        if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
            raise PerscliError(f"study setting {path!r} must be a finite number, not {value!r}")
        if isinstance(default, int):
            if value != int(value):
                raise PerscliError(f"study setting {path!r} must be a whole number, not {value!r}")
            return int(value)
        return float(value)
    if isinstance(default, str):
        if isinstance(value, str):
            return value
        raise PerscliError(f"study setting {path!r} must be a string, not {value!r}")
    if isinstance(default, list):
        if isinstance(value, list):
            return value
        if isinstance(value, (str, int, float)):
            return [value]
        raise PerscliError(f"study setting {path!r} must be a list, not {value!r}")
    return value


def _parse_override(text: str) -> dict:
    key, raw = split_key_value(text, **STUDY_ITEM)
    value = parse_value(raw, blank="", strict=text)
    out = cur = {}
    parts = key.split(".")
    for part in parts[:-1]:
        cur[part] = {}
        cur = cur[part]
    cur[parts[-1]] = value
    return out


def _deep_update(target: dict, new: dict) -> None:
    for k, v in new.items():
        if isinstance(v, dict) and isinstance(target.get(k), dict):
            _deep_update(target[k], v)
        else:
            target[k] = v


def load_study(path: str | None, *, preset: str | None = None, overrides=()) -> dict:
    """The study settings: schema defaults, then a preset, then the file, then overrides.

    Parameters
    ----------
    path : str or None
        A YAML study description (relative paths in it are taken relative to
        its folder), or None for a preset alone.
    preset : {'small', 'paper', 'ci'}, optional
    overrides : sequence of str
        ``key.sub=value`` (YAML values).

    Returns
    -------
    dict
        Every setting, checked.

    Raises
    ------
    PerscliError
        Unknown keys (with the closest valid one), wrong types, bad values.
    """
    settings = copy.deepcopy(SCHEMA)
    if preset is not None:
        if preset not in PRESETS:
            raise PerscliError(f"unknown --preset {preset!r}: use one of {', '.join(PRESETS)}")
        settings = _merge(settings, PRESETS[preset])
    if path is not None:
        try:
            with open(path, encoding="utf-8") as fh:
                given = yaml.safe_load(fh) or {}
        except OSError as exc:
            raise PerscliError(f"{path}: cannot read the study description: {exc.strerror}") from None
        except UnicodeDecodeError as exc:
            # a UTF-16 file (a BOM of ff fe or fe ff), or Latin-1: YAML here is UTF-8 text
            raise PerscliError(f"{path}: not UTF-8 text (byte {exc.start} is 0x{exc.object[exc.start]:02x}; a "
                               "UTF-16 file?): save the study description as UTF-8") from None
        except yaml.YAMLError as exc:
            raise PerscliError(f"{path}: not valid YAML: {yaml_problem(exc)}") from None
        if not isinstance(given, dict):
            raise PerscliError(f"{path}: a study description is a mapping of settings")
        preset_in_file = given.pop("preset", None)
        if preset_in_file is not None and preset is None:
            if preset_in_file not in PRESETS:
                raise PerscliError(f"{path}: unknown preset {preset_in_file!r}: use one of {', '.join(PRESETS)}")
            settings = _merge(settings, PRESETS[preset_in_file])
        base = os.path.dirname(os.path.abspath(path))
        settings = _merge(settings, given)
        _resolve_paths(settings, base, given)
    updates = {}
    for text in overrides:
        _deep_update(updates, _parse_override(text))
    settings = _merge(settings, updates)
    _check_files(settings)
    check(settings)
    return settings


def _check_files(s: dict) -> None:
    """Files named in the settings that do not exist: one line naming the key to set (before anything is read)."""
    e = s["exposures"]
    schedule = e["schedule"]
    if e["source"] == "schedule" and isinstance(schedule, str) and schedule != BUNDLED_SCHEDULE \
            and not os.path.exists(schedule):
        raise PerscliError(f"exposures.schedule: {schedule}: no such file; set exposures.schedule to a schedule "
                           f"FITS file, or leave it out for the bundled {BUNDLED_SCHEDULE}")
    for m in s["persistence"]["models"]:
        if isinstance(m, str) and m not in ("typical", "pessimistic") and not os.path.exists(m):
            raise PerscliError(f"persistence.models: {m}: no such law or file; set persistence.models to typical, "
                               "pessimistic or persistence law files (YAML)")


def _resolve_paths(settings: dict, base: str, given: dict) -> None:
    # paths written in the file are relative to the file (the bundled schedule's name is not a path)
    exp = given.get("exposures", {}) or {}
    if "schedule" in exp and not os.path.isabs(settings["exposures"]["schedule"]) \
            and settings["exposures"]["schedule"] != DEFAULT_SCHEDULE:
        settings["exposures"]["schedule"] = os.path.normpath(os.path.join(base, settings["exposures"]["schedule"]))
    models = (given.get("persistence", {}) or {}).get("models") or []
    settings["persistence"]["models"] = [
        os.path.normpath(os.path.join(base, m)) if m in models and isinstance(m, str)
        and m not in ("typical", "pessimistic") and not os.path.isabs(m) else m
        for m in settings["persistence"]["models"]]
    if (given.get("catalog", {}) or {}).get("gaia"):
        settings["catalog"]["gaia"] = [p if os.path.isabs(p) else os.path.normpath(os.path.join(base, p))
                                       for p in settings["catalog"]["gaia"]]


def check(s: dict) -> None:
    """Refuse settings that cannot make a study (one line naming the setting)."""
    if not (isinstance(s["seed"], int) and 0 <= s["seed"] <= 1000):
        raise PerscliError(f"seed {s['seed']!r}: an integer from 0 to 1000 (frame seeds derive from it)")
    r = s["realisations"]
    if not (isinstance(r, int) and not isinstance(r, bool) and 1 <= r and s["seed"] + r - 1 <= 1000):
        raise PerscliError(f"realisations {r!r}: an integer >= 1, with seed + realisations - 1 <= 1000")
    if s["differential"] not in (None, True, False):
        raise PerscliError(f"differential {s['differential']!r}: true, false, or leave it out (true when what "
                           "persists is light drawn from the catalogue: sources drawn and stars)")
    f = s["field"]
    if not (-90 <= f["dec"] <= 90) or not (0 <= f["ra"] < 360):
        raise PerscliError(f"field ra={f['ra']} dec={f['dec']}: ra must be in [0, 360), dec in [-90, 90] degrees")
    if not f["radius"] > 0:
        raise PerscliError(f"field.radius must be > 0 degrees, not {f['radius']}")
    if s["filter"] not in FILTERS:
        raise PerscliError(f"filter {s['filter']!r}: use one of {', '.join(FILTERS)}")
    if not s["scas"] or any(not isinstance(v, int) or not 1 <= v <= ROMAN_N_SCA for v in s["scas"]):
        raise PerscliError(f"scas {s['scas']!r}: a list of Roman SCAs 1-{ROMAN_N_SCA}")
    e = s["exposures"]
    if e["source"] not in ("schedule", "plan"):
        raise PerscliError(f"exposures.source {e['source']!r}: use schedule or plan")
    if e["count"] < 0 or e["history"] < 0:
        raise PerscliError("exposures.count and exposures.history must be >= 0")
    if e["source"] == "plan" and e["count"] < 1:
        raise PerscliError("exposures.count must be >= 1 for a planned sequence")
    if s["bounds"] is not None:
        b = s["bounds"]
        if not (isinstance(b, list) and len(b) == 4 and all(isinstance(v, int) for v in b)
                and 1 <= b[0] < b[1] <= ROMAN_SCA_SIZE and 1 <= b[2] < b[3] <= ROMAN_SCA_SIZE):
            raise PerscliError(f"bounds {b!r}: [xmin, xmax, ymin, ymax], 1-indexed pixels of the "
                               f"{ROMAN_SCA_SIZE}x{ROMAN_SCA_SIZE} SCA")
    p = s["persistence"]
    # YAML reads 1e5 as a string (it wants 1.0e5): a threshold may be written either way
    p["sources"] = [_number_or_text(v) for v in p["sources"]]
    if not p["models"]:
        raise PerscliError("persistence.models is empty: give typical, pessimistic or model files")
    # every model and detector setting is checked now, not hours later in a render
    for m in p["models"]:
        load_detector_model("roman", [*model_settings(str(m)), *s["render"]["set"]])
    if not p["sources"]:
        raise PerscliError("persistence.sources is empty: give drawn, stars, all or a fluence threshold")
    for src in p["sources"]:
        if src not in ("drawn", "stars", "all") and not (isinstance(src, (int, float)) and src > 0):
            raise PerscliError(f"persistence.sources: {src!r} is not drawn, stars, all or a fluence threshold "
                               "(electrons > 0)")
    bracket = p["bracket"]
    if bracket is not None:
        if not isinstance(bracket, dict):
            raise PerscliError("persistence.bracket: a mapping of names to lists of detector settings, e.g. "
                               "{stars: [persistence.source=stars]}")
        for name, extra in bracket.items():
            if not (isinstance(name, str) and name.replace("_", "").replace(".", "").isalnum()):
                raise PerscliError(f"persistence.bracket: {name!r} is not a name of letters, digits, '_' and '.' "
                                   "(it names files)")
            if not (isinstance(extra, list) and all(isinstance(e, str) and "=" in e for e in extra)):
                raise PerscliError(f"persistence.bracket.{name}: a list of KEY=VALUE detector settings, "
                                   f"not {extra!r}")
            for m in p["models"]:
                load_detector_model("roman", [*model_settings(str(m)), *s["render"]["set"], *extra])
    if s["render"]["compress"] not in ("none", "gzip", "rice"):
        raise PerscliError(f"render.compress {s['render']['compress']!r}: use none, gzip or rice")
    cat = s["catalog"]
    if cat["star_density"] is not None:
        if isinstance(cat["star_density"], bool) or not isinstance(cat["star_density"], (int, float)) \
                or not cat["star_density"] >= 0:
            raise PerscliError(f"catalog.star_density {cat['star_density']!r}: a number >= 0 per arcmin^2 (power-law "
                               "stars), or leave it out for the Galactic model")
    else:
        galactic_star_model(cat["star_model"])     # checked now, not when the catalogue is drawn
    for key, least in (("parts", 0), ("chunk", 1)):
        value = s["measure"][key]
        if not (isinstance(value, int) and not isinstance(value, bool) and value >= least):
            raise PerscliError(f"measure.{key} {value!r}: an integer >= {least}" +
                               (" (0: one strip per 0.1 deg^2 of the field)" if key == "parts" else ""))
    c = s["correlate"]
    if not 0 < c["min_sep"] < c["max_sep"] or c["nbins"] < 1:
        raise PerscliError("correlate: need 0 < min_sep < max_sep and nbins >= 1")
    _check_values(s)


def _positive(value) -> bool:
    return isinstance(value, (int, float)) and not isinstance(value, bool) and math.isfinite(value) and value > 0


def _check_values(s: dict) -> None:
    """The settings every later step takes: checked before anything runs, so that a bad one fails the
    dry run and not a task after hours of renders."""
    p = s["persistence"]
    for m in p["models"]:
        if not isinstance(m, str):
            raise PerscliError(f"persistence.models: {m!r} is not a model name (typical, pessimistic) or a file")
    cat = s["catalog"]
    if not (_positive(cat["galaxy_density"]) or cat["galaxy_density"] == 0):
        raise PerscliError(f"catalog.galaxy_density {cat['galaxy_density']!r}: a number >= 0 per arcmin^2")
    if not (cat["margin_arcsec"] >= 0):
        raise PerscliError(f"catalog.margin_arcsec {cat['margin_arcsec']!r}: a number >= 0")
    for path in cat["gaia"]:
        if not isinstance(path, str) or not os.path.isfile(path):
            raise PerscliError(f"catalog.gaia: {path!r} is not a file; give Gaia DR2 chunks (FITS) that exist")
    m = s["measure"]
    if not (isinstance(m["stamp"], int) and 16 <= m["stamp"] <= 512):
        raise PerscliError(f"measure.stamp {m['stamp']!r}: a whole number of pixels from 16 to 512")
    if m["min_snr"] is not None and not _positive(m["min_snr"]):
        raise PerscliError(f"measure.min_snr {m['min_snr']!r}: a number > 0, or leave it out for measure's default")
    c = s["correlate"]
    if not (isinstance(c["npatch"], int) and c["npatch"] >= 1):
        raise PerscliError(f"correlate.npatch {c['npatch']!r}: a whole number >= 1 (1: no jackknife)")
    if not c["thresholds"] or not all(_positive(t) for t in c["thresholds"]):
        raise PerscliError(f"correlate.thresholds {c['thresholds']!r}: a list of numbers > 0 (|De| thresholds)")

    amplitudes(s["budget"]["bands"])
    _modes_factor(s["budget"]["modes"])


def _number_or_text(value):
    if isinstance(value, str):
        try:
            return float(value)
        except ValueError:
            return value
    return value


def fingerprint(obj) -> str:
    """A short stable hash of settings (what a product was made from)."""
    text = json.dumps(obj, sort_keys=True, default=str)
    return hashlib.sha256(text.encode()).hexdigest()[:16]


def dump(settings: dict) -> str:
    """The settings as YAML (written into the study folder)."""
    return yaml.safe_dump(settings, sort_keys=False)
