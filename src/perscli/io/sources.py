"""FITS input sources: a path, ``-`` (standard input), a FIFO or a gzip file, as one seekable :class:`Source`.

:func:`open_source` opens a name as a :class:`Source` (random access to the
plain FITS bytes through a file descriptor).  Standard input, FIFOs and gzip
files are read once into an anonymous in-memory file (``memfd``), watched by
:class:`_StreamGuard` so that an endless stream after the last HDU is an error
at once.  :func:`stat_input` says in one line why there is nothing to read at
a path, and :func:`split_selector` takes CFITSIO-style HDU selectors and image
sections off a name.

Part of the FITS layer whose writer is :mod:`perscli.io.fitsfile`.
"""

from __future__ import annotations

import errno
import gzip
import math
import os
import re
import select
import stat
import sys
import tempfile
import threading
import time
import zlib

from .. import PerscliError
from .cards import BLOCK, CARD, _parse_value, padded


#: seconds to wait for a FIFO's writer (or its first bytes) before giving up
FIFO_TIMEOUT = float(os.environ.get("PERSCLI_FIFO_TIMEOUT", "10"))

_GZIP_MAGIC = b"\x1f\x8b"
_CHUNK = 1 << 22


# -- sources -------------------------------------------------------------------------------------

def _anonymous_file(label: str) -> int:
    """A file descriptor of an anonymous in-memory file (nothing on disk to clean up)."""
    if hasattr(os, "memfd_create"):
        return os.memfd_create("perscli-input", os.MFD_CLOEXEC)

    fh = tempfile.TemporaryFile()
    return os.dup(fh.fileno())


#: per-thread read buffers of Source.pread(scratch=True)
_SCRATCH = threading.local()


def _write_all(fd: int, data) -> None:
    view = memoryview(data)
    while len(view):
        n = os.write(fd, view)
        view = view[n:]


class Source:
    """Random access to the bytes of one input, through a file descriptor.

    Attributes
    ----------
    label : str
        The name used in messages ('stdin' for '-').
    fd : int
        Open, seekable file descriptor of plain (decompressed) FITS bytes.
    size : int
        Bytes in the file.
    cfitsio_name : str
        How CFITSIO opens the same bytes.
    """

    def __init__(self, label: str, fd: int, *, path: str | None = None):
        self.label = label
        self.fd = fd
        self.size = os.fstat(fd).st_size
        proc = f"/proc/self/fd/{fd}"
        # CFITSIO opens the descriptor through /proc, so file names with brackets or
        # other extended-syntax characters are never reinterpreted
        self.cfitsio_name = proc if os.path.exists(proc) else (path or proc)

    @classmethod
    def from_bytes(cls, label: str, data) -> "Source":
        """A source holding ``data`` (e.g. a FITS file received on a pipe)."""
        fd = _anonymous_file(label)
        _write_all(fd, data)
        return cls(label, fd)

    def pread(self, offset: int, length: int, *, scratch: bool = False):
        """``length`` bytes from ``offset``.

        With ``scratch`` the bytes land in a buffer of the calling thread that
        the next scratch read overwrites (no new, zero-filled buffer per call
        on the hot path): use them before reading again.
        """
        if length <= 0:
            return bytearray(0)
        if scratch:
            local = _SCRATCH.__dict__
            buf = local.get("buf")
            if buf is None or len(buf) < length:
                buf = local["buf"] = bytearray(length)
            view = memoryview(buf)[:length]
        else:
            buf = bytearray(length)
            view = memoryview(buf)
        got = 0
        while got < length:
            n = os.preadv(self.fd, [view[got:]], offset + got)
            if n == 0:
                raise PerscliError(f"{self.label}: the file is truncated (ends at byte {offset + got}); "
                                   "re-copy or regenerate it")
            got += n
        return view if scratch else buf

    def close(self):
        if self.fd is not None:
            os.close(self.fd)
            self.fd = None


def _check_start(label: str, head: bytes) -> None:
    if head[:len(_GZIP_MAGIC)] == _GZIP_MAGIC:
        return
    if not head:
        raise PerscliError(f"{label}: the file is empty; check that it was written completely")
    if head[:10] != b"SIMPLE  = ":
        raise PerscliError(f"{label}: not a FITS file (it does not start with a SIMPLE card); "
                           "check that it is complete and really FITS")


class _StreamGuard:
    """Follows the HDU structure of a FITS stream as it arrives, so that reading stops one block after
    the end of the last HDU: a valid file followed by an endless stream (``cat f.fits /dev/zero``)
    is an error at once instead of filling the memory."""

    def __init__(self, label: str):
        self.label = label
        self.buf = bytearray()     # bytes from ``self.at`` on that are not yet understood
        self.at = 0                # offset of ``self.buf[0]`` in the stream
        self.next_hdu = 0          # where the next header starts
        self.in_header = True
        self.cards = {}

    def feed(self, chunk) -> None:
        self.buf += chunk
        while True:
            if self.in_header:
                if len(self.buf) < BLOCK:
                    return
                block = bytes(self.buf[:BLOCK])
                if not self.cards and self.at > 0 and block[:9] != b"XTENSION=":
                    if block.strip(b"\0 "):
                        raise PerscliError(f"{self.label}: data after the end of the last HDU (byte {self.at}) that "
                                           "are not a FITS extension: trailing garbage or a second file; re-send "
                                           "one FITS file")
                    raise PerscliError(f"{self.label}: the stream goes on after the end of the last HDU "
                                       f"(byte {self.at}) with blank bytes; send exactly one FITS file")
                done = False
                for i in range(0, BLOCK, CARD):
                    key = block[i:i + 8].rstrip()
                    if key == b"END":
                        done = True
                        break
                    if block[i + 8:i + 10] == b"= " and key in (b"BITPIX", b"NAXIS", b"PCOUNT", b"GCOUNT") or \
                            (key.startswith(b"NAXIS") and key[5:].isdigit()):
                        value, _ = _parse_value(block[i + 10:i + CARD].decode("ascii", "replace"))
                        self.cards.setdefault(key.decode(), value)
                del self.buf[:BLOCK]
                self.at += BLOCK
                if done:
                    self.in_header = False
                    self.next_hdu = self.at + padded(self._size())
                    self.cards = {}
            else:
                skip = min(len(self.buf), self.next_hdu - self.at)
                del self.buf[:skip]
                self.at += skip
                if self.at < self.next_hdu:
                    return
                self.in_header = True

    def _size(self) -> int:
        try:
            naxis = int(self.cards.get("NAXIS", 0))
            dims = [int(self.cards.get(f"NAXIS{k}", 0)) for k in range(1, naxis + 1)]
            n = math.prod(dims) if dims else 0
            return abs(int(self.cards.get("BITPIX", 8))) // 8 * int(self.cards.get("GCOUNT", 1)) * (
                int(self.cards.get("PCOUNT", 0)) + n)
        except (TypeError, ValueError):
            return 0   # CFITSIO will say what is wrong with this header


def _read_stream(label: str, read) -> Source:
    """Read a stream to its end into an anonymous file (checking its first bytes early)."""
    fd = _anonymous_file(label)
    try:
        head = b""
        guard = None
        while True:
            chunk = read(_CHUNK)
            if not chunk:
                break
            if len(head) < BLOCK:
                head += bytes(chunk[:BLOCK - len(head)])
                if len(head) >= 10:
                    _check_start(label, head)  # fail fast on /dev/zero and other non-FITS streams
                    if guard is None and head[:2] != _GZIP_MAGIC:
                        guard = _StreamGuard(label)
            if guard is not None:
                guard.feed(chunk)
            _write_all(fd, chunk)
        if not head:
            raise PerscliError(f"{label}: the input is empty; pipe or write a FITS file into it")
        _check_start(label, head)
        return _maybe_gunzip(Source(label, fd))
    except BaseException:
        os.close(fd)
        raise


def _maybe_gunzip(source: Source) -> Source:
    """The decompressed bytes of a gzip source, in an anonymous file (the source itself if not gzip)."""
    if bytes(source.pread(0, min(2, source.size))) != _GZIP_MAGIC:
        return source

    out = _anonymous_file(source.label)
    try:
        with os.fdopen(os.dup(source.fd), "rb") as raw, gzip.GzipFile(fileobj=raw) as gz:
            raw.seek(0)
            first = True
            while True:
                chunk = gz.read(_CHUNK)
                if not chunk:
                    break
                if first:
                    _check_start(source.label + " (decompressed)", chunk[:BLOCK])
                    guard = _StreamGuard(source.label)
                    first = False
                guard.feed(chunk)
                _write_all(out, chunk)
        if first:
            raise PerscliError(f"{source.label}: the gzip file holds nothing")
    except (OSError, EOFError, zlib.error) as exc:
        os.close(out)
        source.close()
        what = "truncated" if isinstance(exc, EOFError) else "not a valid gzip file"
        raise PerscliError(f"{source.label}: {what} ({exc}); re-copy it") from None
    except BaseException:
        os.close(out)
        source.close()
        raise
    source.close()
    return Source(source.label, out)


def _read_fifo(name: str) -> Source:
    """Read a named pipe without blocking forever on a missing writer."""
    fd = os.open(name, os.O_RDONLY | os.O_NONBLOCK)
    deadline = time.monotonic() + FIFO_TIMEOUT
    got_any = [False]

    def read(n):
        while True:
            try:
                data = os.read(fd, n)
            except BlockingIOError:
                data = None
            if data:
                got_any[0] = True
                return data
            if data == b"" and got_any[0]:
                return b""  # the writer closed its end: the stream is complete
            remaining = deadline - time.monotonic()
            if not got_any[0] and remaining <= 0:
                raise PerscliError(f"{name}: a named pipe (FIFO) with no writer or no data after "
                                   f"{FIFO_TIMEOUT:g} s; start the program that writes it first "
                                   "(PERSCLI_FIFO_TIMEOUT sets the wait)")
            if got_any[0]:
                select.select([fd], [], [], 1.0)
            else:
                time.sleep(0.02)

    try:
        return _read_stream(name, read)
    finally:
        os.close(fd)


_SELECTOR = re.compile(r"^(?P<path>.*?)(?P<ext>\[[^\]]*\])(?P<sec>\[[^\]]*\])?$")


def split_selector(name: str):
    """``path``, HDU selector and image section of a CFITSIO-style name.

    ``file.fits[SCI]``, ``file.fits[SCI,2]``, ``file.fits[1]`` select an HDU
    (by EXTNAME[,EXTVER] or number, 0 = primary); a second bracket
    ``[x1:x2,y1:y2]`` (1-indexed, inclusive, ``*`` for a whole axis) selects an
    image section.  A file whose real name contains brackets is taken as it is.

    Returns
    -------
    (str, str or None, str or None)
    """
    if os.path.exists(name) or "[" not in name:
        return name, None, None
    m = _SELECTOR.match(name)
    if not m or not m.group("path"):
        return name, None, None
    ext = m.group("ext")[1:-1].strip()
    sec = m.group("sec")[1:-1].strip() if m.group("sec") else None
    if sec is None and re.fullmatch(r"[\d*\s:,-]+", ext) and ":" in ext:
        ext, sec = None, ext  # file.fits[1:10,1:10]: a section of the first image
    return m.group("path"), ext, sec


def stat_input(name: str, *, kind: str = "a FITS file", hint: str = "") -> os.stat_result:
    """``os.stat`` of an input, or one line saying why there is nothing to read at ``name``.

    Parameters
    ----------
    name : str
        The path given.
    kind : str
        What a link should point at ("a FITS file", "a file of patch centres").
    hint : str
        Appended to the missing and unreadable messages (e.g. "; give a FITS file").

    Raises
    ------
    PerscliError
        Missing, a broken symbolic link or a loop of them, unreadable.
    """
    try:
        return os.stat(name)
    except FileNotFoundError:
        if os.path.islink(name):
            raise PerscliError(f"{name}: a broken symbolic link; point it at {kind}") from None
        raise PerscliError(f"{name}: no such file{hint}") from None
    except OSError as exc:
        if exc.errno == errno.ELOOP:
            raise PerscliError(f"{name}: a loop of symbolic links; point it at {kind}") from None
        raise PerscliError(f"{name}: cannot be read ({exc.strerror}){hint}") from None


def open_source(name: str, stdin=None) -> Source:
    """Open ``name`` (a path or '-') as a :class:`Source` of plain FITS bytes.

    Raises
    ------
    PerscliError
        Missing, unreadable, a directory, a device or socket, an empty file,
        a FIFO without a writer, a corrupt or truncated gzip file.
    """
    if name == "-":
        stream = stdin if stdin is not None else sys.stdin.buffer
        return _read_stream("stdin", stream.read)
    st = stat_input(name)
    if stat.S_ISDIR(st.st_mode):
        raise PerscliError(f"{name}: is a directory, not a FITS file; give the path of a file inside it")
    if stat.S_ISFIFO(st.st_mode):
        return _read_fifo(name)
    if not stat.S_ISREG(st.st_mode):
        raise PerscliError(f"{name}: is not a regular file (a device or socket); give a FITS file, "
                           "or '-' to read standard input")
    try:
        fd = os.open(name, os.O_RDONLY | getattr(os, "O_CLOEXEC", 0))
    except OSError as exc:
        raise PerscliError(f"{name}: cannot be read ({exc.strerror})") from None
    source = Source(name, fd, path=name)
    try:
        _check_start(name, bytes(source.pread(0, min(10, source.size))))
        return _maybe_gunzip(source)
    except BaseException:
        source.close()
        raise
