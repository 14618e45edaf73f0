"""New files and folders beside an output, to be renamed into place when complete.

:func:`make_temp_file` and :func:`make_temp_folder` are
:func:`tempfile.mkstemp` and :func:`tempfile.mkdtemp` with the permissions of
any new file or folder (0666 or 0777 less the umask, where those of
:mod:`tempfile` are 0600 and 0700), so that the output renamed from them is
readable as any other file.  Used by :mod:`perscli.io.output` for
every output written to a path.
"""

from __future__ import annotations

import os
import secrets


def make_temp_file(folder: str, *, prefix: str = ".perscli-", suffix: str = ".part"):
    """A new, empty file in ``folder`` for an output to be renamed into place: ``(fd, path)``.

    Like :func:`tempfile.mkstemp` (a unique name, created exclusively), but
    with the permissions of any new file, 0666 less the umask (0644 under
    the usual umask 022), where mkstemp's are 0600: the output renamed from
    it would otherwise be readable by its owner only.  The umask is applied
    by the system as the file is created, not read and reset here, which
    would change it for every thread of the process for a moment.

    Parameters
    ----------
    folder : str
        The destination's folder (a rename across file systems is not atomic).
    prefix, suffix : str
        Around a random part of the name; the leading dot hides it from ``ls``.

    Returns
    -------
    (int, str)
        An open descriptor (read-write) and the path.

    Raises
    ------
    OSError
        The folder does not take a new file (permission denied, read-only,
        full): callers say which output it was for (:func:`write_error`).
    """
    flags = os.O_RDWR | os.O_CREAT | os.O_EXCL | getattr(os, "O_NOFOLLOW", 0) | getattr(os, "O_CLOEXEC", 0)
    for _ in range(100):
        path = os.path.join(folder, f"{prefix}{secrets.token_hex(6)}{suffix}")
        try:
            return os.open(path, flags, 0o666), path
        except FileExistsError:
            continue
    raise FileExistsError(f"{folder}: no unused temporary file name (100 tried)")


def make_temp_folder(folder: str, *, prefix: str = ".perscli-") -> str:
    """A new, empty folder in ``folder`` for an output folder to be renamed into place.

    Like :func:`tempfile.mkdtemp`, but with the permissions of any new
    folder, 0777 less the umask (mkdtemp's are 0700); see :func:`make_temp_file`.

    Parameters
    ----------
    folder : str
        The destination's parent folder.
    prefix : str
        Before a random part of the name.

    Returns
    -------
    str
        The new folder's path.
    """
    for _ in range(100):
        path = os.path.join(folder, f"{prefix}{secrets.token_hex(6)}")
        try:
            os.mkdir(path, 0o777)
            return path
        except FileExistsError:
            continue
    raise FileExistsError(f"{folder}: no unused temporary folder name (100 tried)")
