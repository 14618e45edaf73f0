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
    lo, hi : float, optional
        Bounds of a number (None: unbounded); ``lo_open``/``hi_open``
        exclude the bound itself.
    choices : tuple of str
    case_sensitive : bool
        For 'choice'.
    show_default : bool
        Show the default in the help (False where the help says it).
    """

    kind: str
    help: str
    flag: str = ""
    metavar: str = ""
    lo: float | None = None
    hi: float | None = None
    lo_open: bool = False
    hi_open: bool = False
    choices: tuple = ()
    case_sensitive: bool = True
    show_default: bool = True

    def __post_init__(self):
        if self.kind not in KINDS:
            raise ValueError(f"option kind {self.kind!r}: one of {', '.join(KINDS)}")
        if self.kind == "choice" and not self.choices:
            raise ValueError("a 'choice' option needs its choices")


def setting(default, kind: str, help: str, **option) -> dataclasses.Field:
    """A field of a settings dataclass with its option: ``n_sigma: float = setting(2.0, "float", "...", lo=0)``.

    ``option``: the other attributes of :class:`OptionSpec`.
    """
    return dataclasses.field(default=default, metadata={"option": OptionSpec(kind, help, **option)})


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
