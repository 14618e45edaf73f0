"""The detector model: an ordered list of effects, read from YAML or a frame's MODEL table, and written back.

:class:`Effect` (one step: name, parameters, on/off) and
:class:`DetectorModel` (the ordered steps); :func:`default_model` (the Roman
chain), :func:`load_detector_model` (YAML file, rendered FITS frame, and
``--set EFFECT.KEY=VALUE`` overrides), :func:`model_to_yaml`; the schema as
a table (:func:`schema_rows`, :func:`format_schema`: ``perscli render
--list-effects``) and the MODEL binary table of a rendered frame
(:func:`model_table`, :func:`model_from_table`, :func:`model_of_frame`).

The YAML model format and the effects themselves are documented in
:mod:`perscli.detector.effects`, which holds the registry of effects.
"""

from __future__ import annotations

import copy
import dataclasses
import json
import os
import textwrap
from dataclasses import dataclass, field

import numpy as np
import yaml

from .. import PerscliError
from ..deprecation import deprecated
from ..io.config import DETECTOR_ITEM, PERSISTENCE_ITEM, load_yaml, parse_value, split_key_value
from ..io.fitsreader import open_fits
from .effects import DEFAULTS, ORDER, REGISTRY, DetectorEffect, Persistence
from .settings import FERMI_PARAMETERS, PRESETS, SETTINGS, preset_settings

# -- the model -----------------------------------------------------------------------------------


@dataclass
class Effect:
    """One step of a detector model: an effect's name, its parameters and whether it is on."""

    name: str
    params: dict = field(default_factory=dict)
    enabled: bool = True

    @property
    def cls(self):
        return REGISTRY[self.name]

    def resolved(self) -> dict:
        """Every parameter with the value it acts with."""
        return self.cls.resolve(self.params)

    def instance(self) -> DetectorEffect:
        return self.cls(self.resolved())


@dataclass
class DetectorModel:
    """An ordered list of effects."""

    effects: list
    source: str = "roman"

    def get(self, name: str) -> Effect | None:
        for eff in self.effects:
            if eff.name == name:
                return eff
        return None

    def enabled(self, name: str) -> bool:
        eff = self.get(name)
        return eff is not None and eff.enabled

    def value(self, name: str, key: str, off=None):
        """A parameter's resolved value, or ``off`` when the effect is absent or switched off."""
        eff = self.get(name)
        if eff is None or not eff.enabled:
            return off
        return eff.resolved()[key]

    def describe(self) -> list:
        """[(name, enabled, resolved params)], in order: the model as it acts (two equal models describe equal)."""
        return [(e.name, e.enabled, e.resolved()) for e in self.effects]

    def persistence_model(self):
        """The :class:`~perscli.detector.persistence.PersistenceModel` of the persistence step."""
        eff = self.get("persistence")
        return Persistence.model(dict(eff.params) if eff else {}, f"{os.path.basename(self.source)}: persistence")


def default_model() -> DetectorModel:
    """GalSim's Roman chain with saturation at :data:`FULL_WELL`: every registered effect on, except those
    not in the Roman model (``offset``), which are left out."""
    return DetectorModel([Effect(name, copy.deepcopy(DEFAULTS[name])) for name in ORDER
                          if REGISTRY[name].default_enabled], source="roman")


def _plain(value):
    """A parameter value as plain Python (YAML cannot write numpy scalars and arrays)."""
    if isinstance(value, np.ndarray):
        return value.tolist()
    if isinstance(value, np.generic):
        return value.item()
    if isinstance(value, (list, tuple)):
        return [_plain(v) for v in value]
    return value


def model_to_yaml(model: DetectorModel, header: str = "") -> str:
    """The model as the YAML that :func:`load_detector_model` reads back (every parameter resolved).

    Parameters
    ----------
    model : DetectorModel
    header : str
        Comment lines to put first (without '#').
    """
    effects = []
    for name, enabled, params in model.describe():
        entry = {k: _plain(v) for k, v in params.items()}
        if not enabled:
            entry["enabled"] = False
        effects.append({name: entry})
    text = yaml.safe_dump({"effects": effects}, sort_keys=False, default_flow_style=None, width=100)
    lines = "".join(f"# {line}\n" for line in header.splitlines()) if header else ""
    return lines + text


def load_detector_model(spec: str | None = None, overrides=()) -> DetectorModel:
    """Read a detector model and apply ``EFFECT.KEY=VALUE`` overrides.

    Parameters
    ----------
    spec : str, optional
        'roman' (or None) for :func:`default_model`; a YAML file: either a
        list under ``effects:`` (in physical order) of ``{name: {params}}``
        mappings, or a mapping ``name: {params}``, effects not listed are
        off, parameters not given take the defaults; or a FITS frame that
        ``perscli render`` wrote: the model that made it (its MODEL table).
    overrides : sequence of str
        'EFFECT.KEY=VALUE' (e.g. 'read_noise.sigma=5'), 'EFFECT=off' or
        'EFFECT=on'.

    Returns
    -------
    DetectorModel
    """
    if spec in (None, "roman", "default"):
        model = default_model()
    elif _is_fits(spec):
        model = _from_fits(spec)
    elif not spec.lower().endswith((".yaml", ".yml")) and not os.path.exists(spec):
        raise PerscliError(unknown_detector_model(spec))
    else:
        model = _from_yaml(spec)
    for text in overrides:
        _override(model, text)
    return model


def unknown_detector_model(spec: str) -> str:
    """The line for a detector model that is neither a name perscli knows nor a file: the valid names, and
    where a persistence law's name goes instead."""
    laws = (*PRESETS, "galsim-linear")
    hint = ""
    if spec in laws:
        hint = (f"; {spec} is a persistence law, not a detector model: --set persistence.base={spec} (render), "
                f"--law {spec} (apply-persistence)") if spec in PRESETS else (
            f"; {spec} is a persistence law, not a detector model: --law {spec} (apply-persistence)")
    return (f"{spec}: no such detector model: give roman (GalSim's Roman chain), a detector model YAML file, or a "
            f"frame perscli rendered (its MODEL){hint}")


def load_persistence_model(spec: str = "typical", overrides=()):
    """The persistence part of a detector model, in any of the forms a user names one.

    The one loader of persistence models: ``perscli apply-persistence --model``,
    the study's ``persistence.models`` and the figures read them here, with the
    persistence step's schema (:class:`~perscli.detector.effects.Persistence`)
    checking every value, as ``perscli render --model/--set`` does.

    Parameters
    ----------
    spec : str
        A preset: 'typical' or 'pessimistic' (the paper's Table 1), 'wfc3'
        (STScI's WFC3-IR law with the WFC3 pipeline's settings), or
        'galsim-linear' (GalSim's 8 coefficients).  A YAML file: a detector
        model (``effects:``; its persistence step), or the persistence
        parameters at top level or under ``persistence:``, optionally with
        ``base: PRESET`` to start from a preset (and its settings), or
        ``kind: linear`` with ``coefficients: [...]``; without a base, a file
        gives the whole Fermi law (A, x0, dx, alpha, gamma, half_well).  Or a
        frame perscli rendered: the persistence step of its MODEL table.
    overrides : mapping or sequence of 'KEY=VALUE'
        Parameters of the law or settings (time_model, combine, max_previous,
        lookback) that replace those of ``spec``; the model's name records them.

    Returns
    -------
    perscli.detector.persistence.PersistenceModel
    """
    if spec in PRESETS:
        params, name = {"base": spec}, spec
    elif spec == "galsim-linear":
        params, name = {"kind": "linear"}, spec
    elif _is_fits(spec):
        model = load_detector_model(spec)
        eff = model.get("persistence")
        params, name = dict(eff.params) if eff else {}, f"{os.path.basename(model.source)}: persistence"
    elif spec.endswith((".yaml", ".yml")) or os.path.exists(spec):
        params, name = _persistence_from_yaml(spec)
    else:
        raise PerscliError(
            f"unknown persistence model {spec!r}: use typical, pessimistic, wfc3, galsim-linear or a YAML file")
    params.pop("enabled", None)
    params = Persistence.validate(params, spec)
    pmodel = Persistence.model(params, name)
    if not _is_fits(spec):
        pmodel = dataclasses.replace(pmodel, name=name)
    changes = _persistence_overrides(overrides, pmodel)
    if not changes:
        return pmodel
    desc = ",".join(f"{k}={v:g}" if isinstance(v, float) else f"{k}={v}" for k, v in changes.items())
    return dataclasses.replace(Persistence.model({**params, **changes}), name=f"{pmodel.name}+{desc}")


def _persistence_from_yaml(path: str) -> tuple:
    """(step parameters, model name) of a YAML persistence model or detector model."""
    doc = load_yaml(path, "persistence model")
    if isinstance(doc, dict) and isinstance(doc.get("effects"), list):
        eff = _from_yaml(path).get("persistence")       # a detector model: its persistence step
        return (dict(eff.params) if eff else {}), path
    if isinstance(doc, dict) and isinstance(doc.get("persistence"), dict):
        doc = doc["persistence"]
    if not isinstance(doc, dict):
        raise PerscliError(f"{path}: expected a mapping of persistence parameters (A, x0, dx, alpha, gamma, "
                           "half_well)")
    if "model" in doc:
        if "kind" in doc:
            raise PerscliError(f"{path}: 'model:' and 'kind:' both given; 'model:' is the older spelling of "
                               "'kind:': keep 'kind:'")
        deprecated("'model:'", "'kind:' (fermi or linear)", where=path)
    params = {("kind" if k == "model" else k): v for k, v in doc.items()}
    known = ("base", "kind", "coefficients", "enabled", *FERMI_PARAMETERS, *SETTINGS, "rounding")
    unknown = [str(k) for k in params if k not in known]
    if unknown:
        raise PerscliError(f"{path}: unknown persistence parameter(s) {', '.join(unknown)}; valid are "
                           f"{', '.join(known[:3])}, {', '.join(FERMI_PARAMETERS)}, {', '.join(SETTINGS)}, rounding")
    base, kind = params.get("base"), params.get("kind", "fermi")
    law = [k for k in FERMI_PARAMETERS if k in params]
    missing = [k for k in FERMI_PARAMETERS if k not in params]
    if kind == "fermi" and base is None and law and missing:
        # a law file without a base is the whole law: half a law silently completed by 'typical' is a trap
        raise PerscliError(f"{path}: missing {', '.join(missing)} (or give 'base: typical' to start from a preset)")
    settings = {k: v for k, v in params.items() if k in SETTINGS}
    plain_preset = base is not None and not law and kind == "fermi" and set(params) <= {"base", "kind", *settings} \
        and base in PRESETS and all(preset_settings(base)[k] == v for k, v in settings.items())
    return params, base if plain_preset else path


def _persistence_overrides(overrides, pmodel) -> dict:
    """{key: value} of 'KEY=VALUE' overrides (or a mapping) of a persistence model, checked."""
    if isinstance(overrides, dict):
        items = list(overrides.items())
    else:
        items = []
        for text in overrides:
            key, value = split_key_value(text, **PERSISTENCE_ITEM)
            items.append((key, parse_value(value)))
    changes = {}
    for key, value in items:
        if key not in FERMI_PARAMETERS and key not in SETTINGS and key != "rounding":
            raise PerscliError(f"unknown persistence parameter {key!r}: valid are "
                               f"{', '.join([*FERMI_PARAMETERS, *SETTINGS, 'rounding'])}")
        if key in FERMI_PARAMETERS and pmodel.kind != "fermi":
            raise PerscliError(f"parameter {key} cannot be set for the linear model {pmodel.name!r}; use a Fermi "
                               "model (typical, pessimistic, wfc3 or a YAML file) to set the law's parameters")
        changes.update(Persistence.validate({key: value}, "--set"))
    return changes


def _is_fits(spec: str) -> bool:
    name = spec.split("[", 1)[0]
    if name.lower().endswith((".fits", ".fit", ".fts", ".fits.gz", ".fit.gz", ".fz")):
        return True
    try:
        with open(name, "rb") as fh:
            head = fh.read(9)
    except OSError:
        return False
    return head == b"SIMPLE  =" or head[:2] == b"\x1f\x8b"


def _from_yaml(path: str) -> DetectorModel:
    doc = load_yaml(path, "detector model")
    if isinstance(doc, dict) and "effects" in doc:
        others = [str(k) for k in doc if k != "effects"]
        if others:
            # a misspelt section would otherwise be ignored in silence
            raise PerscliError(f"{path}: unknown key(s) {', '.join(others)} beside 'effects:'; a detector model "
                               "file holds only 'effects:' (a list of effects in physical order)")
        doc = doc["effects"]
    if isinstance(doc, dict):
        items = list(doc.items())
    elif isinstance(doc, list):
        items = []
        for entry in doc:
            if isinstance(entry, str):
                items.append((entry, {}))
            elif isinstance(entry, dict) and len(entry) == 1:
                items.append(next(iter(entry.items())))
            else:
                raise PerscliError(f"{path}: each effect must be a name or a one-key mapping, not {entry!r}")
    else:
        raise PerscliError(f"{path}: expected 'effects:' with a list of effects in physical order")
    for name, params in items:
        if params is not None and not isinstance(params, dict):
            raise PerscliError(f"{path}: the parameters of {name!r} must be a mapping, not {params!r}")
    return _build([(name, dict(params or {})) for name, params in items], path)


def _build(items, where: str) -> DetectorModel:
    """A model from [(name, {params, optionally 'enabled'})] in the order given, checked."""
    effects, seen = [], set()
    for name, params in items:
        if name not in REGISTRY:
            raise PerscliError(f"{where}: unknown effect {name!r}; known: {', '.join(ORDER)}")
        if name in seen:
            raise PerscliError(f"{where}: effect {name!r} is listed twice")
        seen.add(name)
        params = dict(params)
        enabled = params.pop("enabled", True)
        if not isinstance(enabled, bool):
            raise PerscliError(f"{where}: {name}.enabled must be true or false, not {enabled!r}")
        merged = copy.deepcopy(DEFAULTS[name])
        merged.update(REGISTRY[name].validate(params, where))
        effects.append(Effect(name, merged, enabled))
    order = [ORDER.index(e.name) for e in effects]
    if order != sorted(order):
        raise PerscliError(f"{where}: effects must be listed in physical order: {', '.join(ORDER)}")
    return DetectorModel(effects, source=where)


def _override(model: DetectorModel, text: str) -> None:
    key, value = split_key_value(text, **DETECTOR_ITEM)
    name, _, param = key.partition(".")
    if name not in REGISTRY:
        raise PerscliError(f"--set {text!r}: unknown effect {name!r}; known: {', '.join(ORDER)}")
    eff = model.get(name)
    if eff is None:
        eff = Effect(name, copy.deepcopy(DEFAULTS[name]), enabled=False)
        model.effects.append(eff)
        model.effects.sort(key=lambda e: ORDER.index(e.name))
    if not param:
        if value.lower() not in ("on", "off", "true", "false"):
            raise PerscliError(f"--set {text!r}: use {name}=on or {name}=off")
        eff.enabled = value.lower() in ("on", "true")
        return
    params = dict(eff.params)
    params.update(eff.cls.validate({param: parse_value(value)}, "--set"))
    eff.cls.validate(params, "--set")
    eff.params = params
    eff.enabled = True


# -- the schema as a table, and the model in a FITS file ---------------------------------------

def _show(value) -> str:
    if isinstance(value, float):
        return f"{value:g}"
    if isinstance(value, list):
        return f"[{len(value)} values]" if len(value) > 3 else json.dumps(value)
    return str(value)


def schema_rows() -> list:
    """(effect, parameter, type, unit, default, allowed, description) for every effect and parameter.

    An effect's own row has an empty parameter, 'on' as default and its description.
    """
    rows = []
    for name, cls in REGISTRY.items():
        rows.append((name, "", "", "", "on", "", cls.description))
        for p in cls.schema:
            default = f"({p.derived})" if p.default is None else _show(p.default)
            kind = {"choice": "str", "kernel": "str|3x3", "floats": "list"}.get(p.kind, p.kind)
            rows.append(("", p.name, kind, p.unit, default, p.allowed(), p.description))
    return rows


def format_schema(width: int = 120) -> str:
    """The schema as a plain-text table, in physical order (``perscli render --list-effects``)."""
    head = ("EFFECT", "PARAMETER", "TYPE", "UNIT", "DEFAULT", "ALLOWED", "DESCRIPTION")
    rows = schema_rows()
    widths = [max(len(r[i]) for r in rows + [head]) for i in range(6)]
    indent = sum(widths) + 2 * 6
    desc_width = max(30, width - indent)
    lines = []
    for row in [head] + rows:
        cells = "  ".join(c.ljust(w) for c, w in zip(row[:6], widths))
        wrapped = textwrap.wrap(row[6], desc_width) or [""]
        lines.append(f"{cells}  {wrapped[0]}".rstrip())
        lines.extend((" " * indent + more).rstrip() for more in wrapped[1:])
    lines.append("")
    lines.append("Effects act in this order; --set EFFECT=off|on, --set EFFECT.PARAMETER=VALUE, or a YAML "
                 "model file (--model).")
    return "\n".join(lines) + "\n"


#: columns of the MODEL table: name, numpy type
MODEL_COLUMNS = ("EFFECT", "ENABLED", "PARAM", "VALUE", "UNIT")


def model_rows(model: DetectorModel) -> list:
    """(effect, enabled, parameter, value as JSON, unit) for every resolved parameter, in order.

    An effect without parameters has one row with an empty parameter, so
    that its place and its on/off state are recorded too.
    """
    rows = []
    for name, enabled, params in model.describe():
        cls = REGISTRY[name]
        if not cls.schema:
            rows.append((name, enabled, "", "", ""))
        for p in cls.schema:
            rows.append((name, enabled, p.name, json.dumps(params[p.name]), p.unit))
    return rows


def model_table(model: DetectorModel) -> tuple:
    """The MODEL binary table of a rendered frame: (structured array, column units)."""
    rows = model_rows(model)

    def width(i):
        return max([1] + [len(r[i]) for r in rows])

    dtype = [("EFFECT", f"S{width(0)}"), ("ENABLED", "?"), ("PARAM", f"S{width(2)}"),
             ("VALUE", f"S{width(3)}"), ("UNIT", f"S{width(4)}")]
    data = np.array([(r[0].encode(), bool(r[1]), r[2].encode(), r[3].encode(), r[4].encode()) for r in rows],
                    dtype=dtype)
    return data, ["", "", "", "", ""]


def model_from_table(columns: dict, where: str) -> DetectorModel:
    """The detector model of a MODEL table's columns (EFFECT, ENABLED, PARAM, VALUE), checked."""
    missing = [c for c in ("EFFECT", "ENABLED", "PARAM", "VALUE") if c not in columns]
    if missing:
        raise PerscliError(f"{where}: the MODEL table lacks column(s) {', '.join(missing)}")

    def text(v):
        return (v.decode("ascii", "replace") if isinstance(v, bytes) else str(v)).strip()

    items, index = [], {}
    for i, (name, enabled, param, value) in enumerate(zip(*(columns[c] for c in ("EFFECT", "ENABLED", "PARAM",
                                                                                   "VALUE"))), 1):
        name, param, value = text(name), text(param), text(value)
        if name not in index:
            index[name] = len(items)
            items.append((name, {"enabled": bool(enabled)}))
        params = items[index[name]][1]
        if params["enabled"] != bool(enabled):
            raise PerscliError(f"{where}: MODEL row {i}: {name} is both on and off")
        if not param:
            continue
        try:
            params[param] = json.loads(value)
        except ValueError:
            raise PerscliError(f"{where}: MODEL row {i}: the value {value!r} of {name}.{param} is not valid JSON; "
                               "the table is corrupt") from None
    return _build(items, where)


def _from_fits(path: str) -> DetectorModel:
    with open_fits(path) as f:
        tables = [h for h in f.hdus if h.name == "MODEL" and h.kind == "table"]
        if not tables:
            raise PerscliError(f"{path}: no MODEL table: not a frame perscli render wrote (or one written before "
                               "models were stored); give 'roman' or a YAML model file")
        hdu = tables[0]
        columns = {name.upper(): hdu.read_column(name) for name in hdu.colnames}
        return model_from_table(columns, path)


def model_of_frame(frame) -> DetectorModel | None:
    """The detector model stored in an opened frame (:class:`perscli.io.frames.Frame`), or None."""
    tables = [h for h in getattr(frame, "hdus", []) or [] if h.name == "MODEL" and h.kind == "table"
              and {"EFFECT", "ENABLED", "PARAM", "VALUE"} <= {c.upper() for c in h.colnames}]
    if not tables:
        return None          # not rendered by perscli (another program's MODEL table is not ours)
    hdu = tables[0]
    columns = {name.upper(): hdu.read_column(name) for name in hdu.colnames}
    return model_from_table(columns, frame.label)
