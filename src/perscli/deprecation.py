"""Older spellings that still work for a while: one warning line each, naming the replacement and the release
that removes it.

Every deprecated spelling of perscli (an option, a form of a command, a key of a file) goes through
:func:`deprecated`, so that each says the same thing the same way, once per run, on stderr (the perscli
logger: hidden with ``-q``).  :data:`DEPRECATED` lists them, for the documentation and the tests; the help,
man pages and README document only the current spellings.  This module imports nothing heavy.
"""

from __future__ import annotations

import logging

#: the release in which every spelling below stops working
REMOVED_IN = "0.3.0"

_said: set = set()


def deprecated(old: str, new: str, *, where: str = "") -> None:
    """Say once per run, as a warning on stderr, that ``old`` is deprecated: use ``new``; removed in :data:`REMOVED_IN`.

    Parameters
    ----------
    old, new : str
        The older spelling and its replacement, as a user writes them ('--param KEY=VALUE').
    where : str
        The file or command the spelling was met in, put first ('model.yaml: ').
    """
    key = (old, where)
    if key in _said:
        return
    _said.add(key)
    logging.getLogger("perscli").warning("%s%s is deprecated (it stops working in perscli %s): use %s",
                                         f"{where}: " if where else "", old, REMOVED_IN, new)
