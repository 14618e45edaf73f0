"""Reading YAML model files (persistence models, detector models) with one clear error line."""

from __future__ import annotations

from .. import PerscliError


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
    import yaml

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
