"""Writing FITS outputs: provenance, checksums, atomic replacement, stdout.

Every output carries ``CREATOR = 'perscli X.Y.Z'``, ``DATE``, a HISTORY card
per processing step, one keyword per parameter, the inputs with their
DATASUM, and CHECKSUM/DATASUM on every HDU.  Files are written to a temporary
file in the destination folder and renamed into place, so a Makefile never
sees a half-written target and an error leaves nothing behind.

Everything is written by fitsio (:func:`perscli.io.fitsfile.write_fits_path`)
from a list of :class:`perscli.io.fitsfile.OutHDU` (images, and tables built
with :func:`perscli.io.fitsfile.table_hdu`).
``-o NAME.fits.gz`` writes gzip; ``compress=`` tile-compresses images
losslessly.  Files get the permissions of any new file (0666 less the
umask): their temporary files are made by :func:`make_temp_file`, not
:func:`tempfile.mkstemp`, whose files are 0600.
"""

from __future__ import annotations

import contextlib
import datetime as _dt
import io
import os
import secrets
import sys
import tempfile

from .. import PerscliError, __version__

CREATOR = f"perscli {__version__}"


def check_output(dest: str, *, overwrite: bool = False, inputs=()) -> None:
    """Refuse an output before any work is done.

    Parameters
    ----------
    dest : str
        Output path, or '-' for standard output.
    overwrite : bool
        Allow replacing an existing file.
    inputs : iterable of str
        Input paths (None and '-' are skipped; ``file.fits[SCI]`` is
        ``file.fits``): an output may never replace one of them.
    """
    if dest == "-":
        if sys.stdout.isatty():
            raise PerscliError("refusing to write FITS to a terminal: give -o FILE or redirect standard output")
        return
    folder = os.path.dirname(os.path.abspath(dest))
    if not os.path.isdir(folder):
        raise PerscliError(f"{dest}: folder {folder} does not exist; create it or choose another output")
    if os.path.isdir(dest):
        raise PerscliError(f"{dest}: is a directory; give a file name for the output")
    for name in inputs:
        if name is None or name == "-":
            continue
        name = str(name)
        if not os.path.exists(name):
            from .fitsfile import split_selector

            name = split_selector(name)[0]
        if os.path.exists(name) and os.path.exists(dest) and os.path.samefile(name, dest):
            raise PerscliError(f"{dest}: is also an input; inputs are never modified: choose another output")
    if os.path.exists(dest) and not overwrite:
        raise PerscliError(f"{dest}: already exists; use --overwrite to replace it")


def add_provenance(header, *, step: str, params: dict | None = None, inputs=(), seed: int | None = None):
    """Record who made an output, from what and how.

    Parameters
    ----------
    header : perscli.io.fitsfile.OutHDU
        Updated in place (and returned): anything with item assignment of
        ``(value, comment)`` and ``add_history``.
    step : str
        One line for the HISTORY card, e.g. 'apply-persistence mode=add'.
    params : dict
        KEYWORD -> value or (value, comment); keywords of at most 8 characters.
    inputs : iterable of (str, str, int)
        (keyword stem of at most 5 characters, file name, DATASUM).  Writes
        ``<stem>`` = name and ``<stem>DS`` = DATASUM.
    seed : int, optional
        Random seed, written as SEED.
    """
    header["CREATOR"] = (CREATOR, "software that made this file")
    header["DATE"] = (_dt.datetime.now(_dt.timezone.utc).strftime("%Y-%m-%dT%H:%M:%S"),
                      "UTC date this file was written")
    for key, value in (params or {}).items():
        header[key] = value
    for stem, name, datasum in inputs:
        header[stem] = (os.path.basename(name) if name != "-" else "stdin", "input file")
        header[f"{stem}DS"] = (str(datasum), f"DATASUM of {stem}'s data as read")
    if seed is not None:
        header["SEED"] = (int(seed), "random seed")
    # the keywords describe the latest step only (a chained run replaces them); the HISTORY cards
    # keep every step with its inputs, so a chain of commands can be traced back to its files
    header.add_history(f"{CREATOR}: {step}")
    names = [f"{stem}={os.path.basename(name) if name != '-' else 'stdin'} (DATASUM {datasum})"
             for stem, name, datasum in inputs]
    if seed is not None:
        names.append(f"seed={int(seed)}")
    if names:
        header.add_history("  inputs: " + ", ".join(names))
    return header


@contextlib.contextmanager
def atomic_output(dest: str, *, overwrite: bool = False, stdout=None):
    """A binary stream for ``dest`` that becomes the file only if the block succeeds.

    Parameters
    ----------
    dest : str
        Path, or '-' for standard output (buffered, written at the end).
    overwrite : bool
        Replace an existing file.
    stdout : binary file, optional
        Stream for '-' (default ``sys.stdout.buffer``).
    """
    if dest == "-":
        buffer = io.BytesIO()
        yield buffer
        send_to_stdout(buffer.getbuffer(), stdout)
        return
    with atomic_path(dest, overwrite=overwrite) as tmp:
        with open(tmp, "wb") as fh:
            yield fh


def send_to_stdout(data, stdout=None) -> None:
    """Write bytes to standard output; a reader that went away (``| head``) is not an error."""
    stream = stdout if stdout is not None else sys.stdout.buffer
    try:
        stream.write(data)
        stream.flush()
    except BrokenPipeError:
        devnull = os.open(os.devnull, os.O_WRONLY)
        try:
            os.dup2(devnull, sys.stdout.fileno())
        except (OSError, ValueError, io.UnsupportedOperation):
            pass
        os.close(devnull)


@contextlib.contextmanager
def atomic_path(dest: str, *, overwrite: bool = False, suffix: str = ".part"):
    """A temporary path beside ``dest`` that is renamed to ``dest`` only if the block succeeds.

    The temporary file is removed on any error, including SIGTERM/SIGHUP
    (turned into exceptions by the command line), so a Makefile never sees
    a half-written target.
    """
    if os.path.exists(dest) and not overwrite:
        raise PerscliError(f"{dest}: already exists; use --overwrite to replace it")
    folder = os.path.dirname(os.path.abspath(dest))
    fd, tmp = make_temp_file(folder, suffix=suffix)
    os.close(fd)
    try:
        yield tmp
        os.replace(tmp, dest)
    finally:
        if os.path.exists(tmp):
            os.unlink(tmp)


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


def write_hdus(hdus, dest: str, *, overwrite: bool = False, stdout=None, compress: str = "none") -> None:
    """Write :class:`~perscli.io.fitsfile.OutHDU` s with checksums, atomically or to stdout.

    Parameters
    ----------
    hdus : sequence of OutHDU
    dest : str
        Path, or '-' for standard output.  A name ending in ``.gz`` is written
        gzip-compressed (no time stamp: equal content, equal bytes).
    compress : {'none', 'gzip', 'rice'}
        Tile compression of image extensions (lossless; see
        :func:`perscli.io.fitsfile.write_fits_path`).
    """
    from .fitsfile import gzip_file, write_fits_path

    if dest == "-":
        # a scratch copy in the shared temporary folder, read back at once: mkstemp's 0600 is right for it
        fd, tmp = tempfile.mkstemp(prefix=".perscli-", suffix=".part.fits")
        os.close(fd)
        try:
            write_fits_path(hdus, tmp, compress=compress)
            with open(tmp, "rb") as fh:
                data = fh.read()
        finally:
            os.unlink(tmp)
        send_to_stdout(data, stdout)
        return
    with atomic_path(dest, overwrite=overwrite, suffix=".part.fits") as tmp:
        write_fits_path(hdus, tmp, compress=compress)
        if dest.endswith(".gz"):
            fd, ztmp = make_temp_file(os.path.dirname(tmp), suffix=".part.gz")
            try:
                gzip_file(tmp, fd)
                os.close(fd)
                fd = None
                os.replace(ztmp, tmp)
            finally:
                if fd is not None:
                    os.close(fd)
                if os.path.exists(ztmp):
                    os.unlink(ztmp)

