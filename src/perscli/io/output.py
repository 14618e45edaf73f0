"""Writing FITS outputs: provenance, checksums, atomic and exclusive publication, stdout.

Every output carries ``CREATOR = 'perscli X.Y.Z'``, ``DATE``, a HISTORY card
per processing step, one keyword per parameter, the inputs with their
DATASUM, and CHECKSUM/DATASUM on every HDU.  Files are written to a temporary
file in the destination folder and published under their name only when
complete, so a Makefile never sees a half-written target and an error leaves
nothing behind.

Publishing is exclusive without ``--overwrite``: the finished file is
hard-linked to its name (``link(2)`` fails if the name exists), so of two
commands writing the same ``-o`` at once exactly one succeeds and the other
says the output already exists; with ``--overwrite`` it is renamed over the
old file.  The outputs a command names on its command line (``-o``,
``--plot``; :func:`declare_output`) form one :class:`OutputGroup`: they are
published together when the command succeeds, and none of them is when it
fails, a failing figure included.

Write faults (a full disk, a file-size limit, a read-only or forbidden
folder, ``/dev/full`` or a closed standard output) are reported as
:class:`perscli.PerscliError`, one line naming the output and what to do
(:func:`write_error`).

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
import errno
import io
import os
import secrets
import stat
import sys
import tempfile

from .. import PerscliError, __version__

from .tempfiles import make_temp_file

CREATOR = f"perscli {__version__}"

#: names of standard output besides '-': ``-o /dev/stdout`` is the same as ``-o -`` (the file it
#: points to may be the terminal, a pipe, or a regular file the shell created, which exists)
STDOUT_NAMES = ("-", "/dev/stdout", "/dev/fd/1", "/proc/self/fd/1")

#: what the user reads as the name of standard output in messages
STDOUT_LABEL = "standard output"


def is_stdout(dest) -> bool:
    """Whether ``dest`` names standard output ('-', /dev/stdout, /dev/fd/1, /proc/self/fd/1)."""
    return dest is not None and (str(dest) == "-" or os.path.normpath(str(dest)) in STDOUT_NAMES)


_CLOSED_STDOUT = "standard output is closed (>&-): redirect it to a file or a pipe, or give -o FILE"


class ClosedStdout(io.TextIOBase):
    """What ``sys.stdout`` is when the caller closed standard output (``>&-``): writing to it is an error.

    Python sets ``sys.stdout`` to None for a closed stream; click then drops
    what is echoed (``--version``, ``--help``, a text report) without a word,
    and code that asks ``sys.stdout.isatty()`` fails with an AttributeError.
    The command line installs this object instead (:func:`perscli.cli.main.main`):
    any use of it raises a PerscliError, one line, exit status 1.  ``flush``
    does nothing (nothing was written), so that the interpreter's own flush
    at exit is quiet.
    """

    encoding = "utf-8"
    errors = "strict"

    def _closed(self, *args, **kwargs):
        raise PerscliError(_CLOSED_STDOUT)

    write = writelines = isatty = fileno = _closed

    @property
    def buffer(self):
        self._closed()

    def writable(self) -> bool:
        return False

    def flush(self) -> None:
        return None


class GuardedStdout:
    """Standard output (text) whose write faults are one line: what ``sys.stdout`` is on the command line.

    ``print`` and ``click.echo`` raise a bare OSError when standard output
    cannot take the text (``> /dev/full``, a full disk, a file-size limit),
    which names no file: a command would take it for a fault of its own
    output file.  This wrapper raises it as a PerscliError naming standard
    output (:func:`write_error`).  The fault sticks: text was lost, so every
    later write raises it again (click probes a stream with an empty write
    and ignores what that raises), while ``flush`` does not (the writer was
    told), and file descriptor 1 is pointed at /dev/null so that the
    interpreter's own flush at exit does not fail again.  A reader that
    went away (BrokenPipeError) is left to click.  Everything else is the
    wrapped stream's.

    Parameters
    ----------
    stream : text stream
        The real ``sys.stdout``.
    """

    def __init__(self, stream):
        self._stream = stream
        self._fault = None

    def __getattr__(self, name):
        return getattr(self._stream, name)

    def _guarded(self, call, *args):
        if self._fault is not None:
            raise PerscliError(self._fault)
        try:
            return call(*args)
        except BrokenPipeError:
            raise
        except OSError as exc:
            _silence_stdout()
            self._fault = str(write_error("-", exc))
            raise PerscliError(self._fault) from None

    def write(self, text):
        return self._guarded(self._stream.write, text)

    def writelines(self, lines):
        return self._guarded(self._stream.writelines, lines)

    def flush(self):
        if self._fault is not None:
            return None
        return self._guarded(self._stream.flush)


def stdout_closed() -> bool:
    """Whether standard output was closed by the caller (``sys.stdout`` None or :class:`ClosedStdout`)."""
    return sys.stdout is None or isinstance(sys.stdout, ClosedStdout)


def _check_stdout_open() -> None:
    """Raise a PerscliError when standard output is closed (see :class:`ClosedStdout`)."""
    if stdout_closed():
        raise PerscliError(_CLOSED_STDOUT)


def _stdout_stream():
    """The binary stream of standard output, or a PerscliError when it is closed (``>&-``)."""
    _check_stdout_open()
    buffer = getattr(sys.stdout, "buffer", None)
    if buffer is None:
        raise PerscliError(_CLOSED_STDOUT)
    return buffer


# -- write faults ---------------------------------------------------------------------------------

#: errno values that say the output cannot be written, whatever the program does: reported as one
#: line naming the output; other OSErrors raised while writing keep their own type
WRITE_ERRNOS = frozenset(e for e in (errno.ENOSPC, getattr(errno, "EDQUOT", None), errno.EFBIG, errno.EROFS,
                                     errno.EACCES, errno.EPERM, errno.EIO, errno.ENXIO, errno.EBADF)
                         if e is not None)


def write_error(dest: str, exc: OSError, *, name: str | None = None) -> PerscliError:
    """A write fault as one line naming ``dest`` (or standard output) and what to do about it.

    Parameters
    ----------
    dest : str
        The output as the user named it ('-' for standard output), or the
        file actually written (a scratch copy).
    exc : OSError
        The fault; its errno says which (ENOSPC, EDQUOT, EFBIG, EROFS, EACCES/EPERM, EIO).
    name : str, optional
        How to name the output in the message (default: ``dest``).

    Returns
    -------
    PerscliError
    """
    folder = None if is_stdout(dest) else os.path.dirname(os.path.abspath(str(dest)))
    if name is None:
        name = STDOUT_LABEL if is_stdout(dest) else str(dest)
    code = getattr(exc, "errno", None)
    if code == errno.ENOSPC:
        where = f"on the device of {folder}" if folder else "on the device standard output writes to"
        fix = "free some space or choose another folder" if folder else "free some space or redirect it elsewhere"
        return PerscliError(f"{name}: cannot write: no space left {where}; {fix}")
    if code == getattr(errno, "EDQUOT", -1):
        return PerscliError(f"{name}: cannot write: the disk quota is exceeded; free some space or choose another "
                            "folder")
    if code == errno.EFBIG:
        return PerscliError(f"{name}: cannot write: the file would exceed the file-size limit (ulimit -f, or the "
                            "largest file the file system takes); raise the limit or write elsewhere")
    if code == errno.EROFS:
        return PerscliError(f"{name}: cannot write: {folder or 'it'} is on a read-only file system; choose "
                            "another folder")
    if code in (errno.EACCES, errno.EPERM):
        return PerscliError(f"{name}: cannot write in {folder or 'it'} (permission denied); choose a folder you "
                            "can write to")
    reason = exc.strerror or str(exc) or type(exc).__name__
    return PerscliError(f"{name}: cannot write ({reason}); check the device and the folder, or write elsewhere")


def _as_write_error(dest: str, exc: BaseException):
    """``exc`` as a PerscliError when it is a write fault (see :data:`WRITE_ERRNOS`), else None."""
    if isinstance(exc, OSError) and getattr(exc, "errno", None) in WRITE_ERRNOS:
        return write_error(dest, exc)
    return None


def check_output(dest: str, *, overwrite: bool = False, inputs=()) -> None:
    """Refuse an output before any work is done.

    Parameters
    ----------
    dest : str
        Output path, or '-' (or /dev/stdout) for standard output.
    overwrite : bool
        Allow replacing an existing file.
    inputs : iterable of str
        Input paths (None and '-' are skipped; ``file.fits[SCI]`` is
        ``file.fits``): an output may never replace one of them.

    Raises
    ------
    PerscliError
        Standard output is a terminal or closed; the folder is missing or
        not writable; ``dest`` is a folder, an input, or exists (without
        ``overwrite``).
    """
    if is_stdout(dest):
        _check_stdout_open()
        try:
            tty = sys.stdout.isatty()
        except (OSError, ValueError):   # a stream closed under us: as good as closed
            raise PerscliError("standard output is closed: give -o FILE, or redirect standard output") from None
        if tty:
            raise PerscliError("refusing to write FITS to a terminal: give -o FILE or redirect standard output")
        return
    folder = os.path.dirname(os.path.abspath(dest))
    if not os.path.isdir(folder):
        raise PerscliError(f"{dest}: folder {folder} does not exist; create it or choose another output")
    if os.path.isdir(dest):
        raise PerscliError(f"{dest}: is a directory; give a file name for the output")
    _refuse_special(dest)
    for name in inputs:
        if name is None or name == "-":
            continue
        name = str(name)
        if not os.path.exists(name):
            from .sources import split_selector  # lazy: the entry point imports this module; io.sources imports numpy

            name = split_selector(name)[0]
        if os.path.exists(name) and os.path.exists(dest) and os.path.samefile(name, dest):
            raise PerscliError(f"{dest}: is also an input; inputs are never modified: choose another output")
    if os.path.exists(dest) and not overwrite:
        raise PerscliError(f"{dest}: already exists; use --overwrite to replace it")
    # before any work: a read-only folder (or one on a read-only file system) is known now, not after
    # the work (root passes access(2) on permissions; the write itself then reports the fault)
    if not os.access(folder, os.W_OK | os.X_OK):
        fault = OSError(errno.EROFS if _read_only_fs(folder) else errno.EACCES, "not writable")
        raise write_error(dest, fault)


def _refuse_special(dest: str) -> None:
    """Refuse a destination that exists and is not a regular file (a device, a FIFO, a socket).

    An output is a new file renamed over the old name: done to /dev/null by
    root, it would replace the device with a file.
    """
    try:
        mode = os.stat(dest).st_mode
    except OSError:
        return
    if not stat.S_ISREG(mode) and not stat.S_ISDIR(mode):
        raise PerscliError(f"{dest}: is not a regular file (a device, FIFO or socket): outputs are written as "
                           "files; give a file name, or '-' for standard output")


def _read_only_fs(folder: str) -> bool:
    try:
        return bool(os.statvfs(folder).f_flag & getattr(os, "ST_RDONLY", 1))
    except OSError:
        return False


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


# -- one command's outputs: published together, or not at all ------------------------------------------

class OutputGroup:
    """The outputs a command declared: staged while it runs, published together when it succeeds.

    A command's outputs must appear whole or not at all: a failing
    ``--plot`` must not leave the FITS table written before it.  Each output
    is finished in a temporary file beside its destination (or, for
    standard output, in memory) and staged here; :meth:`commit` publishes
    them all, restoring any file it replaced and removing any it created if
    one of them cannot be published; :meth:`discard` removes them.  Only
    outputs named with :meth:`declare` are staged, so that a command that
    reads back files it wrote (a study's tasks) is unaffected, and only in
    the process that made the group (a forked worker publishes at once).
    When the last declared output is staged the group publishes at once
    (:meth:`complete`): a command that then says what it wrote ("N rows
    written", budget's verdict) says it of files that exist, and a fault in
    publishing them is the only line on stderr.

    Used by the command line (:func:`perscli.cli.helpers.report_errors`);
    library code declares its outputs to the active group with
    :func:`declare_output`.
    """

    def __init__(self):
        self.pid = os.getpid()
        self.declared = set()
        self.files = []        # (tmp, dest, overwrite)
        self.stdout = []       # (bytes, stream or None)
        self.staged = set()    # keys of the declared outputs staged so far

    @staticmethod
    def _key(dest) -> str:
        return "-" if is_stdout(dest) else os.path.abspath(str(dest))

    def declare(self, dest) -> None:
        """Mark ``dest`` (a path, or '-') as one of the command's outputs."""
        if dest is not None:
            self.declared.add(self._key(dest))

    def defers(self, dest) -> bool:
        """Whether writing ``dest`` is staged here rather than published at once."""
        return os.getpid() == self.pid and self._key(dest) in self.declared

    def stage_file(self, tmp: str, dest: str, overwrite: bool) -> None:
        """Take over the finished temporary file ``tmp``, to become ``dest`` at :meth:`commit`."""
        self.files.append((tmp, dest, overwrite))
        self.staged.add(self._key(dest))

    def stage_stdout(self, data, stream=None) -> None:
        """Keep ``data`` for standard output, written at :meth:`commit` after the files."""
        self.stdout.append((bytes(data), stream))
        self.staged.add("-")

    def complete(self) -> bool:
        """Whether every declared output has been staged (nothing is left to fail but publishing)."""
        return bool(self.declared) and self.declared <= self.staged

    def commit(self) -> None:
        """Publish every staged output; if one cannot be, undo the others and raise.

        Files come first (each can be undone: a replaced file is kept under
        a temporary hard link until the end), standard output last (bytes
        sent cannot be taken back).
        """
        files, chunks = self.files, self.stdout
        self.files, self.stdout = [], []
        done, backups = [], []
        try:
            for tmp, dest, overwrite in files:
                backup = None
                if overwrite and os.path.isfile(dest) and not os.path.islink(dest):
                    backup = _backup_link(dest)
                    if backup is not None:
                        backups.append(backup)
                _publish_now(tmp, dest, overwrite)
                done.append((dest, backup))
            for data, stream in chunks:
                send_to_stdout(data, stream)
        except BaseException:
            for dest, backup in reversed(done):
                with contextlib.suppress(OSError):
                    if backup is not None:
                        os.replace(backup, dest)
                    else:
                        os.unlink(dest)
            raise
        finally:
            for tmp, _, _ in files:
                _remove(tmp)
            for backup in backups:
                _remove(backup)

    def discard(self) -> None:
        """Remove every staged output (the command failed)."""
        files, self.files, self.stdout = self.files, [], []
        for tmp, _, _ in files:
            _remove(tmp)

    @contextlib.contextmanager
    def active(self):
        """Make this the group outputs are declared to (:func:`declare_output`) for the duration of the block."""
        global _ACTIVE
        outer, _ACTIVE = _ACTIVE, self
        try:
            yield self
        finally:
            _ACTIVE = outer


_ACTIVE: OutputGroup | None = None


def declare_output(dest) -> None:
    """Make ``dest`` one of the outputs of the running command's group (no-op outside a command)."""
    if _ACTIVE is not None:
        _ACTIVE.declare(dest)


def _remove(path: str) -> None:
    with contextlib.suppress(FileNotFoundError):
        os.unlink(path)


def _backup_link(dest: str) -> str | None:
    """A hard link to the existing ``dest`` under a temporary name, or None where links are not possible."""
    folder = os.path.dirname(os.path.abspath(dest))
    for _ in range(100):
        path = os.path.join(folder, f".perscli-{secrets.token_hex(6)}.old")
        try:
            os.link(dest, path)
            return path
        except FileExistsError:
            continue
        except OSError:
            return None
    return None


def _publish_now(tmp: str, dest: str, overwrite: bool) -> None:
    """Give the finished file ``tmp`` the name ``dest``: exclusively unless ``overwrite``.

    Without ``overwrite`` the name is taken with ``link(2)``, which fails if
    it exists: a check made before the work (:func:`check_output`) cannot
    see another process that writes the same output meanwhile.  File
    systems without hard links get an exclusive ``open(O_EXCL)`` of the name
    and a rename over it.
    """
    try:
        if overwrite:
            os.replace(tmp, dest)
            return
        try:
            os.link(tmp, dest)
        except FileExistsError:
            raise PerscliError(f"{dest}: already exists (another program wrote it meanwhile); use --overwrite to "
                               "replace it") from None
        except OSError as exc:
            if exc.errno not in (errno.EPERM, errno.EOPNOTSUPP, errno.ENOTSUP, errno.EXDEV, errno.EMLINK,
                                 errno.ENOSYS):
                raise
            try:
                fd = os.open(dest, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o666)
            except FileExistsError:
                raise PerscliError(f"{dest}: already exists (another program wrote it meanwhile); use "
                                   "--overwrite to replace it") from None
            os.close(fd)
            os.replace(tmp, dest)
            return
        _remove(tmp)
    except OSError as exc:
        raise write_error(dest, exc) from None


def _publish(tmp: str, dest: str, overwrite: bool) -> bool:
    """Publish ``tmp`` as ``dest`` now, or stage it in the active group; True when the group took it."""
    group = _ACTIVE
    if group is not None and group.defers(dest):
        group.stage_file(tmp, dest, overwrite)
        if group.complete():
            group.commit()
        return True
    _publish_now(tmp, dest, overwrite)
    return False


def deliver_stdout(data, stdout=None, *, dest="-") -> None:
    """Send an output's bytes to standard output: at once, or when the command's group commits."""
    group = _ACTIVE
    if group is not None and group.defers(dest):
        if stdout is None:
            _check_stdout_open()      # closed: said now, before the other outputs are published
        group.stage_stdout(data, stdout)
        if group.complete():
            group.commit()
        return
    send_to_stdout(data, stdout)


@contextlib.contextmanager
def atomic_output(dest: str, *, overwrite: bool = False, stdout=None):
    """A binary stream for ``dest`` that becomes the file only if the block succeeds.

    Parameters
    ----------
    dest : str
        Path, or '-' (or /dev/stdout) for standard output (buffered, written at the end).
    overwrite : bool
        Replace an existing file.
    stdout : binary file, optional
        Stream for '-' (default ``sys.stdout.buffer``).

    Raises
    ------
    PerscliError
        The output cannot be written (see :func:`write_error`) or exists.
    """
    if is_stdout(dest):
        buffer = io.BytesIO()
        yield buffer
        deliver_stdout(buffer.getbuffer(), stdout)
        return
    with atomic_path(dest, overwrite=overwrite) as tmp:
        with open(tmp, "wb") as fh:
            yield fh


def send_to_stdout(data, stdout=None) -> None:
    """Write bytes to standard output; a reader that went away (``| head``) is not an error.

    Raises
    ------
    PerscliError
        Standard output is closed, or cannot take the bytes (``> /dev/full``,
        a full disk, a file-size limit).  What could not be written is
        dropped, so that the interpreter's own flush at exit does not fail
        a second time.
    """
    stream = stdout if stdout is not None else _stdout_stream()
    try:
        stream.write(data)
        stream.flush()
    except BrokenPipeError:
        _silence_stdout()
    except (OSError, ValueError) as exc:
        _silence_stdout()
        if isinstance(exc, ValueError):      # write to a closed file
            raise PerscliError("standard output is closed: give -o FILE, or redirect standard output") from None
        raise write_error("-", exc) from None


def _silence_stdout() -> None:
    """Point file descriptor 1 at /dev/null, so that bytes still buffered for it go nowhere at exit."""
    try:
        fd = sys.stdout.fileno()
    except (AttributeError, OSError, ValueError, io.UnsupportedOperation, PerscliError):
        return
    devnull = os.open(os.devnull, os.O_WRONLY)
    try:
        os.dup2(devnull, fd)
    except OSError:
        pass
    finally:
        os.close(devnull)


@contextlib.contextmanager
def atomic_path(dest: str, *, overwrite: bool = False, suffix: str = ".part"):
    """A temporary path beside ``dest`` that is published as ``dest`` only if the block succeeds.

    The temporary file is removed on any error, including SIGTERM/SIGHUP/SIGINT
    (turned into exceptions by the command line), so a Makefile never sees
    a half-written target.  Without ``overwrite`` the publication is
    exclusive (see :func:`_publish_now`).  Inside a command the output may
    be staged until all the command's outputs are ready (:class:`OutputGroup`).
    ``dest`` naming standard output gets a scratch file sent there afterwards.

    Raises
    ------
    PerscliError
        ``dest`` exists (without ``overwrite``), or a write fault in the
        folder or in the block (:func:`write_error`).
    """
    if is_stdout(dest):
        # a library that writes to a path (matplotlib): a private scratch file, then its bytes
        fd, tmp = _scratch_file(suffix)
        os.close(fd)
        try:
            try:
                yield tmp
            except OSError as exc:
                fault = _as_write_error("-", exc)
                if fault is None:
                    raise
                raise fault from None
            with open(tmp, "rb") as fh:
                data = fh.read()
        finally:
            _remove(tmp)
        deliver_stdout(data)
        return
    if os.path.exists(dest) and not overwrite:
        raise PerscliError(f"{dest}: already exists; use --overwrite to replace it")
    _refuse_special(dest)
    folder = os.path.dirname(os.path.abspath(dest))
    try:
        fd, tmp = make_temp_file(folder, suffix=suffix)
    except OSError as exc:
        raise write_error(dest, exc) from None
    os.close(fd)
    owned = False
    try:
        try:
            yield tmp
        except OSError as exc:
            fault = _as_write_error(dest, exc)
            if fault is None:
                raise
            raise fault from None
        owned = _publish(tmp, dest, overwrite)
    finally:
        if not owned:
            _remove(tmp)


def _scratch_file(suffix: str):
    """A private temporary file in the shared temporary folder (0600 is right for a scratch copy)."""
    try:
        return tempfile.mkstemp(prefix=".perscli-", suffix=suffix)
    except OSError as exc:
        raise PerscliError(f"{STDOUT_LABEL}: cannot make a scratch file in {tempfile.gettempdir()} "
                           f"({exc.strerror}); set TMPDIR to a writable folder") from None


def write_hdus(hdus, dest: str, *, overwrite: bool = False, stdout=None, compress: str = "none") -> None:
    """Write :class:`~perscli.io.fitsfile.OutHDU` s with checksums, atomically or to stdout.

    Parameters
    ----------
    hdus : sequence of OutHDU
    dest : str
        Path, or '-' (or /dev/stdout) for standard output.  A name ending in
        ``.gz`` is written gzip-compressed (no time stamp: equal content,
        equal bytes).
    overwrite : bool
        Replace an existing file (else publication is exclusive: see
        :func:`atomic_path`).
    stdout : binary file, optional
        Stream for standard output (default ``sys.stdout.buffer``).
    compress : {'none', 'gzip', 'rice'}
        Tile compression of image extensions (lossless; see
        :func:`perscli.io.fitsfile.write_fits_path`).

    Raises
    ------
    PerscliError
        The output exists (without ``overwrite``) or cannot be written
        (:func:`write_error`); nothing is left behind.
    """
    from .fitsfile import gzip_file, write_fits_path  # lazy: as in check_output (fitsio, numpy)

    if is_stdout(dest):
        if stdout is None:
            _check_stdout_open()      # a closed standard output is said before the work of writing
        fd, tmp = _scratch_file(".part.fits")
        os.close(fd)
        try:
            try:
                write_fits_path(hdus, tmp, compress=compress)
            except OSError as exc:
                if getattr(exc, "errno", None) not in WRITE_ERRNOS:
                    raise
                # the scratch copy is what could not be written: say where it was
                raise write_error(tmp, exc, name=f"{STDOUT_LABEL} (its scratch copy in "
                                                 f"{os.path.dirname(tmp)}; TMPDIR sets the folder)") from None
            with open(tmp, "rb") as fh:
                data = fh.read()
        finally:
            _remove(tmp)
        deliver_stdout(data, stdout)
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
                _remove(ztmp)


def check_output_folder(dest: str, *, overwrite: bool = False, resume: bool = False, inputs=()) -> None:
    """Refuse an output folder (diagnose's report, a study) before any work is done.

    Parameters
    ----------
    dest : str
        The folder as the user named it.
    overwrite : bool
        Allow an existing folder to be replaced.
    resume : bool
        An existing folder is taken as it is (a study picks up its finished
        products).
    inputs : iterable of str
        Input paths: none may lie inside the folder (it may be replaced).

    Raises
    ------
    PerscliError
        ``dest`` is standard output or a file, exists (without ``overwrite``
        or ``resume``), holds an input, or the folder it goes in is missing
        or not writable.
    """
    if is_stdout(dest):
        raise PerscliError(f"-o {dest}: this command writes a folder of products, not a stream; name a folder")
    target = os.path.abspath(dest)
    if os.path.exists(target) and not os.path.isdir(target):
        raise PerscliError(f"{dest}: is a file; -o names the folder to write")
    if os.path.isdir(target) and not (overwrite or resume):
        raise PerscliError(f"{dest}: already exists; use --overwrite to replace it")
    for name in inputs:
        if name is None or name == "-":
            continue
        path = os.path.abspath(str(name).split("[", 1)[0])
        if path == target or path.startswith(target + os.sep):
            raise PerscliError(f"{dest}: holds the input {name}; inputs are never modified: choose another folder")
    # the nearest folder that exists must take a new entry (a study makes missing parents)
    parent = os.path.dirname(target)
    while not os.path.isdir(parent):
        if os.path.exists(parent):
            raise PerscliError(f"{dest}: {parent} is a file, not a folder; choose another output folder")
        parent = os.path.dirname(parent)
    if not os.path.isdir(target) and not os.access(parent, os.W_OK | os.X_OK):
        fault = OSError(errno.EROFS if _read_only_fs(parent) else errno.EACCES, "not writable")
        raise write_error(dest, fault)
