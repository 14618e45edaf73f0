"""How a command's setting is declared: its default, its type and range, and its option, in one place.

In the manner of TreeCorr's ``corr2_valid_params`` (each parameter's type,
default and documentation in one table, from which its configuration reader
and its documentation are made), a field of a command's settings dataclass
(:class:`perscli.stats.settings.CorrelateOptions`, ...) declared with
:func:`setting` carries everything the command line needs: its default (the
dataclass's, which the library and a study's section use), the values it
takes and its help.  ``perscli.cli.options.settings_options`` makes the
click options from these fields, so that a new option of a command is one
field of its dataclass.  This module imports nothing heavy (and no click:
the library never does), so that ``--help`` stays fast.
"""

from __future__ import annotations

import dataclasses
import math
import numbers
from dataclasses import dataclass, field

from . import PerscliError

#: the kinds of value a setting takes on the command line
KINDS = ("float", "int", "choice", "flag", "numbers", "text", "file_or")


@dataclasses.dataclass(frozen=True)
class OptionSpec:
    """A setting's command-line option (the default is the field's).

    Attributes
    ----------
    kind : str
        One of :data:`KINDS`: a number ('float', 'int', within ``lo`` and
        ``hi``), one of ``choices``, an on/off 'flag', comma-separated
        'numbers' (a tuple of floats, shown as the command line writes it),
        'text', or 'file_or': a file name or one of ``choices``.
    help : str
        The option's help, one sentence or more.
    flag : str
        The option's name ('--sigma'); default: the field's name with
        dashes.
    metavar : str
        What the help shows for the value.
    values : Param, optional
        The values it takes, as an effect's parameter declares them
        (:class:`Param`: bounds of a number, ``lo_open``/``hi_open``, or
        choices); one description of a range for both.
    case_sensitive : bool
        For 'choice'.
    show_default : bool
        Show the default in the help (False where the help says it).
    check : callable, optional
        For 'text': the library's check of a value, ``check(value) ->
        value``, raising :class:`~perscli.PerscliError` with what is wrong
        (a value a kind and a range cannot describe, such as an address).
    """

    kind: str
    help: str
    flag: str = ""
    metavar: str = ""
    values: "Param | None" = None
    case_sensitive: bool = True
    show_default: bool = True
    check: "object | None" = None

    def __post_init__(self):
        if self.kind not in KINDS:
            raise ValueError(f"option kind {self.kind!r}: one of {', '.join(KINDS)}")
        if self.kind == "choice" and not (self.values and self.values.choices):
            raise ValueError("a 'choice' option needs its choices")


#: the attributes of :class:`Param` a setting's range is given by
_RANGE = ("lo", "hi", "lo_open", "hi_open", "choices")


def setting(default, kind: str, help: str, **option) -> dataclasses.Field:
    """A field of a settings dataclass with its option: ``n_sigma: float = setting(2.0, "float", "...", lo=0)``.

    ``option``: the other attributes of :class:`OptionSpec`, and the range
    (lo, hi, lo_open, hi_open, choices), kept as a :class:`Param`.
    """
    rng = {k: option.pop(k) for k in _RANGE if k in option}
    values = Param("", kind, default, description=help, **rng) if rng else None
    return dataclasses.field(default=default, metadata={"option": OptionSpec(kind, help, values=values, **option)})


def option_fields(cls) -> dict:
    """The fields of a settings dataclass that have an option: name -> (default, :class:`OptionSpec`)."""
    return {f.name: (f.default, f.metadata["option"]) for f in dataclasses.fields(cls) if "option" in f.metadata}


def default_text(values) -> str:
    """A tuple of defaults as the command line writes it: ``1e-8,1e-4``."""
    out = []
    for v in values:
        if v and abs(v) < 0.1:
            mantissa, exponent = f"{v:.0e}".split("e")
            out.append(f"{mantissa}e{int(exponent)}")
        else:
            out.append(f"{v:g}")
    return ",".join(out)


# -- parameter schemas (an effect's parameters, and the range of a command's option) -------------


@dataclass(frozen=True)
class Param:
    """One parameter of an effect: what it is and which values it may take.

    Attributes
    ----------
    name : str
    kind : {'float', 'int', 'choice', 'kernel', 'floats'}
        'float': a finite number; 'int': a whole number; 'choice': one of
        ``choices``; 'kernel': 'roman' or a 3x3 list of numbers; 'floats': a
        non-empty list of finite numbers.
    default
        The value when not given; None for a value taken from another
        parameter (``derived``).
    unit : str
    description : str
    lo, hi : float, optional
        Bounds (None: unbounded).
    lo_open, hi_open : bool
        The bound itself is excluded.
    choices : tuple of str
        Allowed words ('choice'), or words accepted besides numbers (e.g.
        'auto' for the sky level).
    derived : str
        For ``default=None``: where the value comes from (e.g. 'from base').
    group : str
        A family of parameters an effect treats together (persistence: 'law'
        for the Fermi law's, 'setting' for how it is applied), or ''.
    presets : dict, optional
        A value that comes with a named preset: preset name -> value, one for
        every preset (persistence's 'typical', 'pessimistic', 'wfc3').
    """

    name: str
    kind: str
    default: object
    unit: str = ""
    description: str = ""
    lo: float | None = None
    hi: float | None = None
    lo_open: bool = False
    hi_open: bool = False
    choices: tuple = ()
    derived: str = ""
    group: str = ""
    presets: dict | None = field(default=None, hash=False)

    def allowed(self, unit: bool = False) -> str:
        """The allowed values as text, e.g. '(0, inf)' or 'typical | pessimistic' (with the unit if asked)."""
        if self.kind == "choice":
            return " | ".join(self.choices)
        if self.kind == "kernel":
            return "roman | 3x3 list"
        lo = "-inf" if self.lo is None else f"{self.lo:g}"
        hi = "inf" if self.hi is None else f"{self.hi:g}"
        left = "(" if self.lo_open or self.lo is None else "["
        right = ")" if self.hi_open or self.hi is None else "]"
        text = f"{left}{lo}, {hi}{right}"
        if self.kind == "int":
            text = f"integer {text}"
        if self.kind == "floats":
            text = f"list, each {text}"
        if unit and self.unit:
            text += f" {self.unit}"
        if self.choices:
            text += " | " + " | ".join(self.choices)
        return text

    def _requirement(self) -> str:
        if self.kind == "choice":
            return f"must be one of {', '.join(self.choices)}"
        if self.kind == "kernel":
            return "must be 'roman' or a 3x3 list of finite numbers"
        if self.lo == 0 and self.hi is None:
            return "must be positive" if self.lo_open else "must not be negative"
        if self.lo is None and self.hi is None:
            return "must be a finite number"
        return f"must be in {self.allowed()}"

    def check(self, effect: str, value, where: str):
        """``value`` converted to this parameter's type, or a PerscliError naming effect.param, value and range."""
        def fail(requirement):
            allowed = "" if self.kind in ("choice", "kernel") else f" (allowed: {self.allowed(unit=True)})"
            return PerscliError(f"{where}: {effect}.{self.name} {requirement}{allowed}, not {value!r}")

        if value is None and self.default is None:
            return None
        if self.kind == "choice":
            if not isinstance(value, str) or value not in self.choices:
                raise fail(self._requirement())
            return value
        if self.kind == "kernel":
            if value == "roman":
                return value
            import numpy as np  # lazy: --help reads the schemas (light module), numpy is not needed to list them

            arr = np.asarray(value, dtype=float) if isinstance(value, (list, tuple)) and _numbers(value) else None
            if arr is None or arr.shape != (3, 3) or not np.all(np.isfinite(arr)):
                raise fail(self._requirement())
            return [[float(v) for v in row] for row in value]
        if isinstance(value, str) and value in self.choices:
            return value
        if self.kind == "floats":
            if not isinstance(value, (list, tuple)) or not value:
                raise fail("must be a non-empty list of finite numbers")
            return [self._number(effect, v, where, fail) for v in value]
        return self._number(effect, value, where, fail)

    def _number(self, effect, value, where, fail):
        number = value
        if isinstance(number, str):
            # YAML 1.1 reads '-6e-7' (no decimal point) as text: accept any number Python can parse
            try:
                number = float(number)
            except ValueError:
                pass
        if isinstance(number, bool) or not isinstance(number, numbers.Real) \
                or not math.isfinite(number):
            raise fail("must be a whole number" if self.kind == "int" else "must be a finite number")
        if self.kind == "int":
            if number != int(number):
                raise fail("must be a whole number")
            number = int(number)
        else:
            number = float(number)
        if self.lo is not None and (number < self.lo or (self.lo_open and number == self.lo)):
            raise fail(self._requirement())
        if self.hi is not None and (number > self.hi or (self.hi_open and number == self.hi)):
            raise fail(self._requirement())
        return number


def _numbers(rows) -> bool:
    try:
        return all(not isinstance(v, (bool, str)) and isinstance(v, (int, float))
                   for row in rows for v in row)
    except TypeError:
        return False
