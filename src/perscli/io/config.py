"""Settings from YAML files and ``KEY=VALUE`` items, each refused in one clear line.

:func:`load_yaml` reads a model or study file; :func:`split_key_value` and
:func:`parse_value` are the one reading of a ``KEY=VALUE`` item, whether it
comes from ``--set`` (render, apply-persistence, study), ``--star-param`` or a
Python caller: the key and value around the first '=', stripped, and the value
typed as YAML (``5`` is an int, ``[a, b]`` a list, ``well`` a string).
"""

from __future__ import annotations

from .. import PerscliError

# How each command's KEY=VALUE items are named when one is refused (split_key_value's what, form and
# example): the library that reads them and the command line's callback (perscli.cli.options.key_values)
# refuse them with the same line.
#: render --set, load_detector_model's overrides
DETECTOR_ITEM = dict(what="--set", form="EFFECT.KEY=VALUE or EFFECT=on|off")
#: a persistence law's overrides (apply-persistence --set persistence.KEY=VALUE and --param KEY=VALUE)
PERSISTENCE_ITEM = dict(what="override", example="--set persistence.gamma=1.1, or --param gamma=1.1")
#: perscli study --set, load_study's overrides
STUDY_ITEM = dict(what="override", example="exposures.count=5")
#: catalog --star-param, the Galactic star model's parameters
STAR_ITEM = dict(what="star-model parameter", example="thin_height=300")


def load_yaml(path: str, what: str):
    """The parsed content of a YAML file.

    Parameters
    ----------
    path : str
        The file.
    what : str
        What it should be ('detector model', 'persistence model'), for messages.

    Raises
    ------
    PerscliError
        Missing file or invalid YAML.
    """
    import yaml  # lazy: --help reads this module's item forms (light module); yaml is ~30 ms

    try:
        with open(path, encoding="utf-8") as fh:
            return yaml.safe_load(fh)
    except FileNotFoundError:
        raise PerscliError(f"{path}: {what} file not found") from None
    except IsADirectoryError:
        raise PerscliError(f"{path}: is a directory, not a {what} file") from None
    except UnicodeDecodeError as exc:
        raise PerscliError(f"{path}: not UTF-8 text (byte {exc.start} is 0x{exc.object[exc.start]:02x}; a UTF-16 "
                           f"file?): save the {what} as UTF-8") from None
    except yaml.YAMLError as exc:
        problem = " ".join(str(getattr(exc, "problem", None) or str(exc).splitlines()[0]).split())
        raise PerscliError(f"{path}: not valid YAML ({problem})") from None


def yaml_problem(exc) -> str:
    """A YAML error in one line: its problem, and for a tag a plain YAML value cannot carry, why it is refused."""
    text = str(getattr(exc, "problem", None) or str(exc).splitlines()[0])
    if "constructor for the tag" in text:
        # safe_load refuses !!python/... and other tags that would build objects: said as such, not as a traceback
        return f"{' '.join(text.split())} (tags that build objects are refused: give plain values)"
    return " ".join(text.split())


def split_key_value(text, *, what: str = "override", form: str = "KEY=VALUE", example: str | None = None) -> tuple:
    """``(key, value)`` of a ``KEY=VALUE`` item: the text around its first '=', both stripped.

    Parameters
    ----------
    text : str
        The item as given ('persistence.gamma=1.1').
    what, form, example : str
        How the refusal names the item, the form it should have and an
        example of it: "override 'x' is not KEY=VALUE (e.g. exposures.count=5)".

    Raises
    ------
    PerscliError
        Not a string, or no '=' in it.
    """
    if not isinstance(text, str) or "=" not in text:
        raise PerscliError(f"{what} {text!r} is not {form}" + (f" (e.g. {example})" if example else ""))
    key, value = text.split("=", 1)
    return key.strip(), value.strip()


def parse_value(value: str, *, blank=None, strict: str | None = None, what: str = "override"):
    """A ``KEY=VALUE`` item's value typed as YAML: '5' -> 5, '1.5' -> 1.5, '[a, b]' -> a list.

    Parameters
    ----------
    value : str
        The value, stripped (:func:`split_key_value`).
    blank
        What an empty value is.
    strict : str, optional
        The item, for a one-line refusal of a value YAML cannot read; None:
        such a value stays the text given (a schema then says what it
        should be).
    what : str
        How the refusal names the item.
    """
    import yaml  # lazy: as in load_yaml

    if not value:
        return blank
    try:
        return yaml.safe_load(value)
    except yaml.YAMLError as exc:
        if strict is None:
            return value
        raise PerscliError(f"{what} {strict!r}: not a YAML value: {yaml_problem(exc)}") from None
