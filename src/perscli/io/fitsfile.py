"""FITS input and output: fitsio (CFITSIO) underneath, perscli's checks on top.

One FITS stack for every command.  CFITSIO, through fitsio, parses headers,
reads images (plain, scaled and tile-compressed) and tables, and writes every
output.  On top of it this module adds what a careful reader needs and
CFITSIO leaves to its caller:

- :func:`open_fits` accepts a path, ``-`` (standard input), a FIFO, a gzip
  file (``.fits.gz``) and CFITSIO-style HDU selectors and image sections
  (``file.fits[SCI,2]``, ``file.fits[1][1:100,1:100]``).  Standard input,
  FIFOs and gzip files are read once into an anonymous in-memory file
  (``memfd``), so that every source is a seekable file descriptor and no
  temporary file is ever left on disk.  A FIFO without a writer, a device or a
  directory gives one clear error instead of a hang.
- Structure is checked before any data are used: data running past the end
  of the file (truncation or a huge declared size), bytes after the last HDU
  (trailing garbage, a second file appended, or a corrupt extension header),
  and invalid scaling keywords (BSCALE = 0, non-finite BZERO).
- CHECKSUM and DATASUM (FITS Standard, Appendix J) of every HDU whose data
  are read are verified when present, on the bytes as stored (for a
  tile-compressed image, its binary table).  The check can be switched off
  (``--no-checksum``, which sets ``PERSCLI_NO_CHECKSUM=1`` so that worker
  processes inherit it) for files edited on purpose.
- The one hand-written fast path: rows of a plain, uncompressed image are read
  with ``os.pread`` as stored (big-endian), so that apply-persistence's
  compiled kernel converts, models and checksums them in one pass
  (benchmarks/bench_apply_persistence.py measures what it saves).

Outputs (:func:`write_hdus`) are written by fitsio, optionally tile-compressed
(lossless GZIP_2) or gzip-compressed as a whole (``-o x.fits.gz``), with
CHECKSUM/DATASUM computed here so that the same content always gives the same
bytes (CFITSIO's own cards carry the time of writing in their comments).
"""

from __future__ import annotations

import errno
import math
import os
import re
import select
import stat
import sys
import threading
import time
from dataclasses import dataclass, field

import numpy as np

from .. import PerscliError

BLOCK = 2880
CARD = 80

#: seconds to wait for a FIFO's writer (or its first bytes) before giving up
FIFO_TIMEOUT = float(os.environ.get("PERSCLI_FIFO_TIMEOUT", "10"))

_BITPIX_DTYPES = {8: ">u1", 16: ">i2", 32: ">i4", 64: ">i8", -32: ">f4", -64: ">f8"}
_GZIP_MAGIC = b"\x1f\x8b"
_CHUNK = 1 << 22

#: what a checksum mismatch means and what to do: most often a file edited by a tool that kept the
#: old CHECKSUM/DATASUM cards (astropy does, unless told checksum=True), less often a damaged copy
CHECKSUM_HINT = ("the checksums are stale (the file changed after they were written, e.g. edited with a tool "
                 "that kept the old cards) or the file is corrupt: if it was edited on purpose, update them "
                 "with astropy's `fitscheck --force FILE` or give --no-checksum; otherwise re-copy it")


def checksums_enabled() -> bool:
    """Whether CHECKSUM/DATASUM of inputs are verified (``--no-checksum`` turns it off)."""
    return os.environ.get("PERSCLI_NO_CHECKSUM", "") in ("", "0")


def set_checksum_verification(enabled: bool) -> None:
    """Switch verification on or off for this process and the processes it starts."""
    if enabled:
        os.environ.pop("PERSCLI_NO_CHECKSUM", None)
    else:
        os.environ["PERSCLI_NO_CHECKSUM"] = "1"


# -- header values ------------------------------------------------------------------------------

def _parse_value(text: str):
    """Value of a fixed- or free-format card field (after '= ')."""
    s = text.lstrip()
    if not s:
        return None, ""
    if s[0] == "'":
        out = []
        i = 1
        n = len(s)
        while i < n:
            j = s.find("'", i)
            if j < 0:
                out.append(s[i:])
                i = n
                break
            out.append(s[i:j])
            if j + 1 < n and s[j + 1] == "'":
                out.append("'")
                i = j + 2
                continue
            i = j
            break
        rest = s[i + 1:]
        comment = rest.split("/", 1)[1].strip() if "/" in rest else ""
        return "".join(out).rstrip(), comment
    token, _, comment = s.partition("/")
    token = token.strip()
    comment = comment.strip()
    if token == "T":
        return True, comment
    if token == "F":
        return False, comment
    if token == "":
        return None, comment
    try:
        return int(token), comment
    except ValueError:
        pass
    try:
        return float(token.replace("D", "E").replace("d", "e")), comment
    except ValueError:
        return token, comment  # complex or non-standard: kept as text


class Header:
    """Parsed cards of one HDU: a read-only mapping plus the card images.

    Long strings (the CONTINUE convention) are joined in linear time, so a
    header of 100,000 CONTINUE cards is parsed in a fraction of a second.

    Attributes
    ----------
    cards : list of str
        The 80-character card images as found (END excluded).
    """

    def __init__(self, cards):
        self.cards = [c.ljust(CARD)[:CARD] for c in cards]
        self._values = {}
        self._history = []
        pending, pieces = None, []

        def flush():
            if pending is not None and len(pieces) > 1:
                self._values[pending] = "".join(pieces)

        for card in self.cards:
            key = card[:8].rstrip()
            if key == "CONTINUE" and pending is not None:
                more, _ = _parse_value(card[8:])
                if isinstance(more, str):
                    if pieces[-1].endswith("&"):
                        pieces[-1] = pieces[-1][:-1]
                    pieces.append(more)
                    if not more.endswith("&"):
                        flush()
                        pending, pieces = None, []
                    continue
            flush()
            pending, pieces = None, []
            if key in ("HISTORY", "COMMENT", ""):
                if key == "HISTORY":
                    self._history.append(card[8:].rstrip())
                continue
            if key == "HIERARCH" and "=" in card:
                name, _, rest = card[9:].partition("=")
                key = name.strip()
                value, _ = _parse_value(rest)
            elif card[8:10] == "= ":
                value, _ = _parse_value(card[10:])
            else:
                continue
            if key not in self._values:  # the first occurrence wins, as in astropy
                self._values[key] = value
                if isinstance(value, str) and value.endswith("&"):
                    pending, pieces = key, [value]
        flush()

    def __contains__(self, key):
        return key in self._values

    def __getitem__(self, key):
        return self._values[key]

    def get(self, key, default=None):
        return self._values.get(key, default)

    def keys(self):
        return self._values.keys()

    @property
    def history(self) -> list:
        return list(self._history)


# -- sources -------------------------------------------------------------------------------------

def _anonymous_file(label: str) -> int:
    """A file descriptor of an anonymous in-memory file (nothing on disk to clean up)."""
    if hasattr(os, "memfd_create"):
        return os.memfd_create("perscli-input", os.MFD_CLOEXEC)
    import tempfile

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
    import gzip
    import zlib

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
    try:
        st = os.stat(name)
    except FileNotFoundError:
        if os.path.islink(name):
            raise PerscliError(f"{name}: a broken symbolic link; point it at a FITS file") from None
        raise PerscliError(f"{name}: no such file") from None
    except OSError as exc:
        if exc.errno == errno.ELOOP:
            raise PerscliError(f"{name}: a loop of symbolic links; point it at a FITS file") from None
        raise PerscliError(f"{name}: cannot be read ({exc.strerror})") from None
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


# -- HDUs ----------------------------------------------------------------------------------------

def padded(n: int) -> int:
    return (n + BLOCK - 1) // BLOCK * BLOCK


def _stored_cards(raw: bytes) -> dict:
    """CHECKSUM and DATASUM as they stand in the stored header bytes."""
    out = {}
    for i in range(0, len(raw), CARD):
        key = raw[i:i + 8]
        if key in (b"CHECKSUM", b"DATASUM "):
            value, _ = _parse_value(raw[i + 10:i + CARD].decode("ascii", "replace"))
            out.setdefault(key.decode().strip(), value)
        elif key == b"END     ":
            break
    return out


@dataclass
class HDU:
    """One HDU of an opened file: what its header says and how to read its data.

    Attributes
    ----------
    index : int
        0 for the primary HDU.
    header : Header
        The header as a reader sees it (for a tile-compressed image, the
        image's header).
    header_offset, data_offset, data_end : int
        Where the stored header and data are (bytes; ``data_end`` without padding).
    compressed : bool
        A tile-compressed image (stored as a binary table).
    kind : {'image', 'table'}
    """

    index: int
    header: Header
    header_offset: int
    data_offset: int
    data_end: int
    compressed: bool
    kind: str
    file: "FitsFile" = field(repr=False)
    verified: bool = field(default=False, repr=False)

    @property
    def source(self) -> Source:
        return self.file.source

    @property
    def data_size(self) -> int:
        if self.compressed:
            return int(np.prod(self.shape)) * self.dtype.itemsize if self.shape else 0
        return self.data_end - self.data_offset

    @property
    def name(self) -> str:
        default = "PRIMARY" if self.index == 0 else ""
        return str(self.header.get("EXTNAME", default)).strip().upper()

    @property
    def ver(self) -> int:
        try:
            return int(self.header.get("EXTVER", 1))
        except (TypeError, ValueError):
            return 1

    @property
    def label(self) -> str:
        return f"HDU {self.index}" + (f" ({self.name})" if self.name else "")

    @property
    def is_image(self) -> bool:
        return self.kind == "image"

    @property
    def shape(self) -> tuple:
        """numpy-order shape of the (uncompressed) data, slowest axis first."""
        if self.kind != "image":
            return ()
        naxis = int(self.header.get("NAXIS", 0))
        return tuple(int(self.header[f"NAXIS{k}"]) for k in range(naxis, 0, -1))

    @property
    def dtype(self) -> np.dtype:
        bitpix = int(self.header["BITPIX"])
        return np.dtype(_BITPIX_DTYPES[bitpix])

    @property
    def scaling(self) -> tuple:
        """(BSCALE, BZERO), (1, 0) when absent."""
        return float(self.header.get("BSCALE", 1.0)), float(self.header.get("BZERO", 0.0))

    @property
    def is_plain(self) -> bool:
        """An uncompressed image: its stored bytes can be read directly."""
        return self.kind == "image" and not self.compressed

    @property
    def is_plain_float(self) -> bool:
        """Uncompressed float data without scaling: the stored bytes are the values."""
        return self.is_plain and self.dtype.kind == "f" and self.scaling == (1.0, 0.0)

    # -- checks ----------------------------------------------------------------------------------
    def datasum(self) -> int:
        """FITS DATASUM of the data as stored (with their padding), computed in chunks."""
        from .. import _kernels

        total, offset, end = 0, self.data_offset, padded(self.data_end - self.data_offset) + self.data_offset
        while offset < end:
            n = min(_CHUNK, end - offset)
            total = ones_complement_add(total, _kernels.datasum(self.source.pread(offset, n)))
            offset += n
        return total

    def verify(self, datasum: int | None = None) -> int:
        """Check CHECKSUM and DATASUM, when the header has them, and return the data's DATASUM.

        Parameters
        ----------
        datasum : int, optional
            The DATASUM of the stored data when the caller has already
            computed it while reading (the fast path); else computed here.

        Raises
        ------
        PerscliError
            Naming the file and the HDU, with the fix.
        """
        if self.verified and datasum is None:
            return self._datasum
        if datasum is None:
            datasum = self.datasum()
        else:
            # the caller summed the data as it used them; the block padding after them counts too
            size = self.data_end - self.data_offset
            pad = padded(size) - size
            if pad:
                from .. import _kernels

                tail = bytes(self.source.pread(self.data_end, pad))
                if size % 4:
                    tail = bytes(size % 4) + tail  # keep the 32-bit words aligned to the data's start
                datasum = ones_complement_add(datasum, _kernels.datasum(tail))
        self._datasum = datasum
        if not checksums_enabled():
            self.verified = True
            return datasum
        from .. import _kernels

        raw = bytes(self.source.pread(self.header_offset, self.data_offset - self.header_offset))
        stored = _stored_cards(raw)
        where = f"{self.file.label}: {self.label}"
        stated = str(stored.get("DATASUM", "")).strip()
        if stated:
            if not stated.isdigit():
                raise PerscliError(f"{where}: DATASUM = {stated!r} is not a checksum; {CHECKSUM_HINT}")
            if int(stated) != datasum:
                raise PerscliError(f"{where}: the data do not match their DATASUM ({stated}, computed "
                                   f"{datasum}): {CHECKSUM_HINT}")
        if "CHECKSUM" in stored:
            total = ones_complement_add(_kernels.datasum(raw), datasum)
            if total != 0xFFFFFFFF:
                raise PerscliError(f"{where}: the header and data do not match their CHECKSUM: {CHECKSUM_HINT}")
        self.verified = True
        return datasum

    def verify_header(self) -> None:
        """Check the header against CHECKSUM with the DATASUM it states, without reading the data.

        Cheap (the header's own bytes), so it is done for every HDU when a file
        is opened: a corrupted keyword (EXPEND read as EZPEND) is caught even in
        an HDU whose data are never read.  :meth:`verify` checks the data too.
        """
        raw = bytes(self.source.pread(self.header_offset, self.data_offset - self.header_offset))
        _verify_header_bytes(raw, f"{self.file.label}: {self.label}")

    # -- reading images ----------------------------------------------------------------------------
    def stream_rows(self, r0: int, r1: int, plane: int = 0, *, scratch: bool = False) -> np.ndarray:
        """Rows of a plain image as stored (big-endian, unscaled), WITHOUT verifying checksums.

        The fast path: the caller folds the DATASUM of what it reads and calls
        :meth:`verify` with it at the end.  With ``scratch`` the rows live in
        the thread's read buffer until its next scratch read.
        """
        shape = self.shape
        ny, nx = shape[-2], shape[-1]
        item = self.dtype.itemsize
        start = (plane * ny + r0) * nx * item
        buf = self.source.pread(self.data_offset + start, (r1 - r0) * nx * item, scratch=scratch)
        return np.frombuffer(buf, dtype=self.dtype).reshape(r1 - r0, nx)

    def read_rows(self, r0: int, r1: int, plane: int = 0, *, native: bool = False) -> np.ndarray:
        """Rows ``r0:r1`` of a 2-D image, or of plane ``plane`` of a 3-D cube (checksums verified).

        Float data come back as stored (big-endian for a plain file) unless
        ``native``; integer data are scaled with BSCALE/BZERO to float64.
        """
        self.verify()
        if self.compressed:
            fits_hdu = self.file.fitsio[self.index]
            try:
                arr = fits_hdu[r0:r1, :] if len(self.shape) == 2 else fits_hdu[plane:plane + 1, r0:r1, :][0]
            except Exception as exc:  # CFITSIO: tiles that do not decompress
                raise self._unreadable(exc) from None
            return self._finish(np.asarray(arr))
        arr = self.stream_rows(r0, r1, plane)
        if self.dtype.kind != "f" or self.scaling != (1.0, 0.0):
            return self._scaled(arr)
        return arr.astype(arr.dtype.newbyteorder("=")) if native else arr

    def _unreadable(self, exc) -> PerscliError:
        return PerscliError(f"{self.file.label}: {self.label}: the data cannot be read ({_cfitsio_reason(exc)}); "
                            "the file is corrupt: re-copy it")

    def _finish(self, arr):
        """Data read through CFITSIO (which applies BSCALE/BZERO itself) as floats."""
        if arr.dtype.kind != "f":
            arr = arr.astype(np.float64)
        return arr

    def _scaled(self, arr: np.ndarray) -> np.ndarray:
        """Physical values of stored numbers: BSCALE * stored + BZERO, BLANK as NaN."""
        bscale, bzero = self.scaling
        out = arr.astype(np.float64)
        if bscale != 1.0:
            out *= bscale
        if bzero != 0.0:
            out += bzero
        blank = self.header.get("BLANK")
        if self.dtype.kind != "f" and isinstance(blank, int):
            out[arr == blank] = np.nan
        return out

    def read(self, *, native: bool = True) -> np.ndarray | None:
        """All the data of an image, scaled, as an array of the HDU's shape (checksums verified)."""
        shape = self.shape
        if not shape or 0 in shape:
            return None
        self.verify()
        if self.compressed:
            try:
                return self._finish(np.asarray(self.file.fitsio[self.index].read()))
            except Exception as exc:  # CFITSIO: tiles that do not decompress
                raise self._unreadable(exc) from None
        buf = self.source.pread(self.data_offset, self.data_end - self.data_offset)
        arr = np.frombuffer(buf, dtype=self.dtype).reshape(shape)
        if self.dtype.kind != "f" or self.scaling != (1.0, 0.0):
            return self._scaled(arr)
        return arr.astype(arr.dtype.newbyteorder("=")) if native else arr

    def raw_bytes(self, start: int = 0, length: int | None = None):
        """Stored bytes of the data unit (unverified; used to copy an HDU unchanged)."""
        if length is None:
            length = self.data_end - self.data_offset - start
        return self.source.pread(self.data_offset + start, length)

    def read_copy(self):
        """The data as CFITSIO presents them, to be written again unchanged: ``(array or None, units)``.

        Integer images keep their type (unsigned 16-bit data stored with
        BZERO = 32768 come back as uint16); tables come back as structured
        arrays with their TUNITn.
        """
        self.verify()
        if self.kind == "image" and (not self.shape or 0 in self.shape):
            return None, None
        try:
            data = self.file.fitsio[self.index].read()
        except Exception as exc:  # CFITSIO on corrupt data
            raise self._unreadable(exc) from None
        if data is None:
            return None, None
        data = np.asarray(data)
        units = None
        if self.kind == "table":
            units = [str(self.header.get(f"TUNIT{k}", "") or "") for k in range(1, len(data.dtype.names) + 1)]
        return data, units

    # -- reading tables ----------------------------------------------------------------------------
    @property
    def colnames(self) -> list:
        return list(self.file.fitsio[self.index].get_colnames()) if self.kind == "table" else []

    @property
    def nrows(self) -> int:
        return int(self.header.get("NAXIS2", 0)) if self.kind == "table" else 0

    def read_column(self, name: str) -> np.ndarray:
        """One column of a binary table, in native byte order (checksums verified)."""
        self.verify()
        try:
            values = self.file.fitsio[self.index].read_column(name)
        except Exception as exc:  # CFITSIO on a corrupt table
            raise PerscliError(f"{self.file.label}: {self.label}: column {name!r} cannot be read "
                               f"({_cfitsio_reason(exc)}); the table is corrupt") from None
        values = np.asarray(values)
        if values.dtype.byteorder not in ("=", "|"):
            values = values.astype(values.dtype.newbyteorder("="))
        return values


def ones_complement_add(a: int, b: int) -> int:
    """Add two 32-bit ones'-complement sums (how FITS DATASUMs of pieces combine)."""
    s = a + b
    while s >> 32:
        s = (s & 0xFFFFFFFF) + (s >> 32)
    return s


def _cfitsio_reason(exc: Exception) -> str:
    text = str(exc).strip().splitlines()
    return text[0].strip() if text else type(exc).__name__


_STATUS = re.compile(r"status\s*=\s*(\d+)")


def _describe_cfitsio(label: str, exc: Exception) -> PerscliError:
    if isinstance(exc, UnicodeDecodeError):
        return PerscliError(f"{label}: a header holds bytes that are not ASCII text: the file is corrupt; re-copy it")
    reason = _cfitsio_reason(exc)
    m = _STATUS.search(str(exc))
    code = int(m.group(1)) if m else None
    if code in (107, 108):
        return PerscliError(f"{label}: the file is truncated ({reason}); re-copy or regenerate it")
    if code == 225:
        return PerscliError(f"{label}: an extension header does not start with XTENSION: a corrupt header, or a "
                            "second FITS file appended after the first; re-copy the file (one file per input)")
    return PerscliError(f"{label}: not a valid FITS file ({reason}); the file is corrupt: re-copy it "
                        "or check that it really is FITS")


def _image_view(cards, where: str = "") -> list:
    """The header of a tile-compressed image as its reader sees it: ZBITPIX, ZNAXISn become BITPIX,
    NAXISn (the stored table's own structure is dropped), the other cards as they are."""
    stored = Header(cards)
    try:
        bitpix = _whole(stored.get("ZBITPIX", -32), "ZBITPIX", where)
        naxis = _whole(stored.get("ZNAXIS", 0), "ZNAXIS", where)
        dims = [_whole(stored.get(f"ZNAXIS{k}", 0), f"ZNAXIS{k}", where) for k in range(1, min(naxis, 999) + 1)]
    except PerscliError as exc:
        raise PerscliError(f"{exc} (a tile-compressed image)") from None
    out = [format_card("XTENSION", "IMAGE"), format_card("BITPIX", bitpix), format_card("NAXIS", naxis)]
    out += [format_card(f"NAXIS{k}", n) for k, n in enumerate(dims, 1)]
    return out + [c for c in cards if not _is_structural(c[:8].rstrip()) or c[:8].rstrip() in ("EXTNAME",)]


def _whole(value, key: str, where: str) -> int:
    """A structural keyword's value, which must be a whole number (not text, a float or a logical)."""
    if isinstance(value, bool) or not isinstance(value, int):
        shown = "missing" if value is None else f"= {value!r}, not a whole number"
        raise PerscliError(f"{where}: {key} {shown}: the header is corrupt; re-copy the file")
    return value


def _stored_size(label: str, index: int, header: Header, fallback: int) -> int:
    """Bytes of an HDU's data without padding (FITS Standard 4.4.1), from its header."""
    try:
        naxis = int(header.get("NAXIS", 0))
        if naxis == 0:
            return 0
        dims = [int(header[f"NAXIS{k}"]) for k in range(1, naxis + 1)]
        if header.get("GROUPS") is True and dims[0] == 0:
            dims = dims[1:]
        bits = abs(int(header["BITPIX"]))
        return bits // 8 * int(header.get("GCOUNT", 1)) * (int(header.get("PCOUNT", 0)) + math.prod(dims))
    except (KeyError, TypeError, ValueError):
        return fallback


_EXTENSIONS = ("IMAGE", "BINTABLE", "TABLE", "A3DTABLE", "IUEIMAGE")


def _check_axes(hdr, where: str, index: int) -> None:
    """Refuse a header whose BITPIX, NAXIS, NAXISn, PCOUNT or GCOUNT is missing or not a whole number.

    Every size and shape is computed from them: a flipped bit can turn
    'NAXIS1  =' into 'NAXIS1  <' (NAXIS1 missing) or '32' into '0 32' (text)
    when no CHECKSUM says so.
    """
    _whole(hdr.get("BITPIX"), "BITPIX", where)
    naxis = _whole(hdr.get("NAXIS"), "NAXIS", where)
    if not 0 <= naxis <= 999:
        raise PerscliError(f"{where}: NAXIS = {naxis} is not 0 to 999; the header is corrupt")
    for k in range(1, naxis + 1):
        _whole(hdr.get(f"NAXIS{k}"), f"NAXIS{k}", where)
    for key in ("PCOUNT", "GCOUNT"):
        if key in hdr or index > 0:
            _whole(hdr.get(key, 0 if key == "PCOUNT" else 1), key, where)


def _check_structure(label: str, hdu: HDU) -> None:
    """Structural and scaling keywords that CFITSIO lets through but make the file or its data meaningless."""
    hdr = hdu.header
    where = f"{label}: {hdu.label}"
    if not hdu.compressed:
        _check_axes(hdr, where, hdu.index)
    if hdu.index == 0 and hdr.get("SIMPLE") is not True:
        raise PerscliError(f"{where}: SIMPLE = {hdr.get('SIMPLE')!r}: the file says it does not conform to FITS; "
                           "it is corrupt or not FITS")
    if hdu.index > 0 and not hdu.compressed and str(hdr.get("XTENSION", "")).strip().upper() not in _EXTENSIONS:
        raise PerscliError(f"{where}: XTENSION = {hdr.get('XTENSION')!r} is not a FITS extension type "
                           f"({', '.join(_EXTENSIONS)}); the file is corrupt")
    for key in ("BSCALE", "BZERO"):
        if key in hdr:
            value = hdr[key]
            if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
                raise PerscliError(f"{where}: {key} = {value!r} is not a finite number; the file is corrupt")
    if "BSCALE" in hdr and hdr["BSCALE"] == 0:
        raise PerscliError(f"{where}: BSCALE = 0 would make every pixel equal to BZERO; the file is corrupt")
    if hdu.kind == "image" and ("BSCALE" in hdr or "BZERO" in hdr) and int(hdr.get("BITPIX", 0)) in _BITPIX_DTYPES:
        _check_scaled_range(hdr, where)
    if hdu.kind == "image":
        if int(hdr.get("BITPIX", 0)) not in _BITPIX_DTYPES:
            raise PerscliError(f"{where}: BITPIX = {hdr.get('BITPIX')!r} is not a FITS value; the file is corrupt")
        for n in hdu.shape:
            if n < 0:
                raise PerscliError(f"{where}: a negative NAXISn; the file is corrupt")


def _check_scaled_range(hdr, where: str) -> None:
    """Refuse BSCALE/BZERO that take the stored numbers beyond the floats they are read as.

    Readers turn scaled 8- and 16-bit integers into 32-bit floats (astropy
    does; perscli's outputs of such frames are 32-bit), anything else into
    64-bit floats: ``BZERO = 1E300`` on 16-bit data makes every pixel
    infinite, which no reader would call data.
    """
    bscale, bzero = float(hdr.get("BSCALE", 1.0)), float(hdr.get("BZERO", 0.0))
    dtype = np.dtype(_BITPIX_DTYPES[int(hdr["BITPIX"])])
    target = np.float32 if dtype.kind != "f" and dtype.itemsize <= 2 or dtype == np.dtype(">f4") else np.float64
    limit = float(np.finfo(target).max)
    # the stored extremes: the integer type's range, or (floats) the value 1 as a scale of BSCALE
    lo, hi = (float(np.iinfo(dtype).min), float(np.iinfo(dtype).max)) if dtype.kind != "f" else (-1.0, 1.0)
    with np.errstate(over="ignore", invalid="ignore"):
        ends = [bzero + bscale * lo, bzero + bscale * hi]
    if not all(math.isfinite(v) and abs(v) <= limit for v in ends):
        bits = 8 * np.dtype(target).itemsize
        raise PerscliError(f"{where}: BZERO = {bzero:g} and BSCALE = {bscale:g} take the stored "
                           f"{'integers' if dtype.kind != 'f' else 'values'} beyond the range of the {bits}-bit "
                           "floats they are read as; the scaling keywords are corrupt")


# -- header cards as FITS allows them ---------------------------------------------------------------

_KEYWORD = re.compile(rb"[A-Z0-9_-]* *")
_NUMBER = rb"[+-]?(?:\d+\.?\d*|\.\d+)(?:[EeDd][+-]?\d+)?"
#: a fixed- or free-format value (FITS Standard 4.2): string, logical, number, complex, or none; then a comment
_VALUE = re.compile(rb" *(?:'(?:[^']|'')*'|[TF]|" + _NUMBER + rb"|\( *" + _NUMBER + rb" *, *" + _NUMBER
                    + rb" *\))? *(?:/.*)?")
_STRING = re.compile(rb" *(?:'(?:[^']|'')*')? *(?:/.*)?")
_PRINTABLE = bytes(range(0x20, 0x7F))


def _card_problem(card: bytes) -> str | None:
    """What makes one 80-byte card invalid FITS (None when it is valid)."""
    if card.translate(None, _PRINTABLE):
        bad = next(b for b in card if b < 0x20 or b > 0x7E)
        return f"holds the byte {bad:#04x}, which is not printable ASCII text"
    key = card[:8]
    if key == b"HIERARCH":
        if b"=" in card[8:] and not _VALUE.fullmatch(card[8:].split(b"=", 1)[1]):
            return "has a value that is not a FITS value (an unterminated string, or text that is no number)"
        return None
    if not _KEYWORD.fullmatch(key):
        return "has a keyword name with characters FITS does not allow (A-Z, 0-9, - and _)"
    if key == b"CONTINUE":
        return None if _STRING.fullmatch(card[8:]) else "continues a string without a valid string value"
    if card[8:10] == b"= " and key.rstrip() not in (b"COMMENT", b"HISTORY", b""):
        if not _VALUE.fullmatch(card[10:]):
            return "has a value that is not a FITS value (an unterminated string, or text that is no number)"
    return None


def _check_cards(raw: bytes, where: str) -> None:
    """Refuse a header (its stored bytes, END included) holding a card that is not valid FITS.

    Such cards would be copied into outputs that other readers refuse
    (astropy: 'Card is not FITS standard'), and text with control
    characters breaks the libraries a header is given to (WCS).
    """
    for i in range(0, len(raw) - CARD + 1, CARD):
        card = raw[i:i + CARD]
        if card[:8] == b"END     ":
            return
        problem = _card_problem(card)
        if problem is not None:
            # control characters shown escaped: a BEL or an ESC in the message would ring or redraw the terminal
            text = "".join(ch if " " <= ch <= "~" else f"\\x{ord(ch):02x}" for ch in card.decode("latin-1")).rstrip()
            shown = text if len(text) <= 40 else text[:40] + "..."
            raise PerscliError(f"{where}: card {i // CARD + 1} ({shown}) {problem}: the header is corrupt; "
                               "re-copy the file or fix the card")


def _verify_header_bytes(raw: bytes, where: str) -> None:
    """Check a header's bytes against its CHECKSUM, with the DATASUM it states (no data read)."""
    if not checksums_enabled():
        return
    from .. import _kernels

    stored = _stored_cards(raw)
    stated = str(stored.get("DATASUM", "")).strip()
    if "CHECKSUM" not in stored or not stated.isdigit() or int(stated) > 0xFFFFFFFF:
        return
    if ones_complement_add(_kernels.datasum(raw), int(stated)) != 0xFFFFFFFF:
        raise PerscliError(f"{where}: the header does not match its CHECKSUM: {CHECKSUM_HINT}")


def _header_fault(source: Source, label: str, max_hdus: int = 10000):
    """Walk the headers with perscli's own reader: the first that fails its CHECKSUM or holds an invalid card.

    For files CFITSIO cannot read (or reads only part of): a flipped bit in
    a signed header is reported as what it is, a checksum mismatch, rather
    than as the truncation or garbage CFITSIO then sees.  None when every
    header it can reach is sound (CFITSIO's own message then stands).
    """
    try:
        offset = 0
        for index in range(max_hdus):
            if offset + BLOCK > source.size:
                return None
            pos, found = offset, False
            while not found and pos + BLOCK <= source.size:
                block = bytes(source.pread(pos, BLOCK))
                pos += BLOCK
                found = any(block[i:i + 8] == b"END     " for i in range(0, BLOCK, CARD))
            if not found:
                return None
            raw = bytes(source.pread(offset, pos - offset))
            where = f"{label}: HDU {index}"
            try:
                _verify_header_bytes(raw, where)
                _check_cards(raw, where)
            except PerscliError as exc:
                return exc
            cards = []
            for i in range(0, len(raw), CARD):
                if raw[i:i + 8] == b"END     ":
                    break
                cards.append(raw[i:i + CARD].decode("ascii", "replace"))
            header = Header(cards)
            try:
                # a missing or garbled NAXISn makes CFITSIO read the data as the next header
                _check_axes(header, where, index)
            except PerscliError as exc:
                return exc
            size = _stored_size(label, index, header, None)
            if size is None or size < 0:
                return None
            offset = pos + padded(size)
    except Exception:  # noqa: BLE001 - a diagnosis only: CFITSIO's message stands
        return None
    return None


class FitsFile:
    """An opened FITS input: its HDUs, checked, ready to read.

    Parameters
    ----------
    name : str
        A path (optionally with ``[EXT]`` and ``[x1:x2,y1:y2]``), or '-'.
    stdin : binary file, optional
        Stream to read for '-' (default ``sys.stdin.buffer``).

    Attributes
    ----------
    label : str
        The name used in messages.
    hdus : list of HDU
    selected : int or None
        The HDU chosen with ``[EXT]``, if any.
    section : tuple of slice or None
        ``(rows, columns)`` chosen with an image section, as numpy slices.
    """

    def __init__(self, name: str, *, stdin=None):
        import fitsio

        path, ext, sec = split_selector(name) if name != "-" else (name, None, None)
        self.name = name
        self.label = "stdin" if name == "-" else name
        self.source = open_source(path, stdin)
        self.source.label = self.label
        self.fitsio = None
        try:
            try:
                self.fitsio = fitsio.FITS(self.source.cfitsio_name)
                infos = []
                for i, h in enumerate(self.fitsio):
                    cards = [rec.get("card_string", "") for rec in self.fitsio._FITS.read_header(i + 1)]
                    infos.append((h.get_offsets(), h.get_exttype(), getattr(h, "is_compressed", lambda: False)(), cards))
            except PerscliError:
                raise
            except Exception as exc:  # CFITSIO's errors (fitsio raises several types) on a corrupt file
                # a flipped bit in a signed header is said as such, not as what CFITSIO made of it
                raise _header_fault(self.source, self.label) or _describe_cfitsio(self.label, exc) from None
            self.hdus = []
            for i, (offsets, exttype, compressed, cards) in enumerate(infos):
                kind = "image" if exttype == "IMAGE_HDU" else "table"
                start = int(offsets["data_start"])
                header_start = int(offsets["header_start"])
                # first what the header's own bytes say: its CHECKSUM (a flipped bit in NAXIS1 is a
                # checksum mismatch, not a truncation or a missing keyword), then cards FITS allows
                raw = bytes(self.source.pread(header_start, start - header_start))
                extname = str(Header(cards).get("EXTNAME", "PRIMARY" if i == 0 else "")).strip().upper()
                where = f"{self.label}: HDU {i}" + (f" ({extname})" if extname else "")
                _verify_header_bytes(raw, where)
                _check_cards(raw, where)
                if compressed:
                    cards = _image_view(cards, where)
                header = Header(cards)
                # CFITSIO's data_end includes the block padding; the data's own size is the header's
                size = int(offsets["data_end"]) - start
                if not compressed:
                    size = _stored_size(self.label, i, header, size)
                hdu = HDU(i, header, header_start, start, start + size, bool(compressed), kind, self)
                _check_structure(self.label, hdu)
                if hdu.data_end > self.source.size:
                    raise PerscliError(
                        f"{self.label}: the file is truncated: {hdu.label} needs {padded(hdu.data_end)} bytes "
                        f"but the file has {self.source.size}; re-copy or regenerate it")
                self.hdus.append(hdu)
            if not self.hdus:
                raise PerscliError(f"{self.label}: no HDU could be read; the file is corrupt")
            end = padded(self.hdus[-1].data_end)
            if end > self.source.size:
                raise PerscliError(f"{self.label}: the file is truncated (the last HDU's padding is missing); "
                                   "re-copy or regenerate it")
            if self.source.size > end:
                self._explain_extra(end)
            self.selected = self._select(ext) if ext is not None else None
            self.section = self._section(sec) if sec is not None else None
        except BaseException:
            self.close()
            raise

    def _explain_extra(self, end: int) -> None:
        """Bytes after the last HDU CFITSIO could read: say what they most likely are."""
        extra = self.source.size - end
        fault = _header_fault(self.source, self.label)
        if fault is not None:
            raise fault
        head = bytes(self.source.pread(end, min(extra, BLOCK)))
        n = len(self.hdus)
        if head.startswith(b"XTENSION="):
            if extra < BLOCK or b"END     " not in bytes(self.source.pread(end, extra)):
                raise PerscliError(f"{self.label}: the file is truncated inside the header of HDU {n}; "
                                   "re-copy or regenerate it")
            raise PerscliError(f"{self.label}: the header of HDU {n} (at byte {end}) is corrupt: CFITSIO cannot "
                               "read it; re-copy the file")
        if head.startswith(b"SIMPLE  ="):
            raise PerscliError(f"{self.label}: a second FITS file is appended after byte {end}: one file per "
                               "input; split them")
        raise PerscliError(f"{self.label}: {extra} bytes after the end of {self.hdus[-1].label} (byte {end}) "
                           "that are not a FITS extension: trailing garbage or a corrupt extension header; "
                           "re-copy the file")

    def _select(self, ext: str) -> int:
        text = ext.strip()
        if re.fullmatch(r"\+?\d+", text):
            index = int(text)
            if index >= len(self.hdus):
                raise PerscliError(f"{self.label}: [{ext}]: the file has only {len(self.hdus)} HDUs (0-"
                                   f"{len(self.hdus) - 1})")
            return index
        name, _, ver = text.partition(",")
        name = name.strip().upper()
        for hdu in self.hdus:
            if hdu.name == name and (not ver.strip() or hdu.ver == _int(ver, self.label, ext)):
                return hdu.index
        names = ", ".join(f"{h.name or h.index}" + (f",{h.ver}" if h.ver != 1 else "") for h in self.hdus)
        raise PerscliError(f"{self.label}: no HDU [{ext}]; the file has {names}")

    def _section(self, sec: str):
        parts = [p.strip() for p in sec.split(",")]
        if len(parts) != 2:
            raise PerscliError(f"{self.label}: image section [{sec}] must be [x1:x2,y1:y2] (1-indexed, inclusive; "
                               "* for a whole axis)")
        out = []
        for text in parts[::-1]:  # FITS order is x, y; numpy's is rows, columns
            if text == "*":
                out.append(slice(None))
                continue
            lo, sep, hi = text.partition(":")
            if not sep:
                raise PerscliError(f"{self.label}: image section [{sec}]: {text!r} is not first:last")
            a, b = _int(lo, self.label, sec), _int(hi, self.label, sec)
            if a < 1 or b < a:
                raise PerscliError(f"{self.label}: image section [{sec}]: {text!r} must have 1 <= first <= last")
            out.append(slice(a - 1, b))
        return tuple(out)

    def close(self):
        if self.fitsio is not None:
            try:
                self.fitsio.close()
            except Exception:  # closing a read-only file cannot lose data
                pass
            self.fitsio = None
        self.source.close()

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()


def _int(text, label, what) -> int:
    try:
        return int(str(text).strip())
    except ValueError:
        raise PerscliError(f"{label}: [{what}]: {text!r} is not a whole number") from None


def open_fits(name: str, *, stdin=None) -> FitsFile:
    """Open and check a FITS input (see :class:`FitsFile`)."""
    return FitsFile(name, stdin=stdin)


# -- writing -------------------------------------------------------------------------------------

def _format_value(value) -> str:
    if isinstance(value, (bool, np.bool_)):
        return f"{'T' if value else 'F':>20}"
    if isinstance(value, (int, np.integer)):
        return f"{int(value):>20}"
    if isinstance(value, (float, np.floating)):
        value = float(value)
        if not math.isfinite(value):
            raise ValueError(f"FITS cannot store the non-finite value {value}")
        text = repr(value).upper()
        if "." not in text and "E" not in text:
            text += ".0"
        elif "E" in text and "." not in text.split("E")[0]:
            mant, exp = text.split("E")
            text = f"{mant}.0E{exp}"
        return f"{text:>20}"
    text = _ascii_text(str(value)).replace("'", "''")
    # fixed format: the closing quote at column 20 or later, as astropy and cfitsio write it
    quoted = f"'{text:<8}'"
    return f"{quoted:<20}"


def _ascii_text(text: str) -> str:
    """``text`` as printable ASCII, the only characters a FITS header holds: others are escaped
    (``é`` becomes ``\\xe9``, a tab ``\\t``), so that a file name or a message of any script can
    be recorded without making the header invalid."""
    if text.isascii() and text.isprintable():
        return text
    return "".join(ch if " " <= ch <= "~" else ch.encode("unicode_escape").decode("ascii") for ch in text)


def format_card(key: str, value=None, comment: str | None = None) -> str:
    """``KEY = value / comment`` as one 80-character card image.

    A string too long for one card continues on CONTINUE cards (the FITS
    long-string convention): the result is then several cards' worth of
    characters, a multiple of 80.
    """
    key = key.upper()
    if len(key) > 8:
        raise ValueError(f"keyword {key!r} is longer than 8 characters")
    if key in ("HISTORY", "COMMENT", ""):
        return f"{key:<8}{_ascii_text(str(value or ''))}"[:CARD].ljust(CARD)
    text = _format_value(value)
    if isinstance(value, str) and len(text.rstrip()) > 70:
        return _long_string_cards(key, _ascii_text(value), comment)
    card = f"{key:<8}= {text}"
    if comment:
        card += f" / {_ascii_text(comment)}"
    return card[:CARD].ljust(CARD)


def _long_string_cards(key: str, value: str, comment: str | None) -> str:
    escaped = value.replace("'", "''")
    pieces = []
    while escaped:
        cut = 67
        if len(escaped) > cut and escaped[cut - 1] == "'" and escaped[cut - 2:cut] != "''":
            cut -= 1  # never split an escaped quote pair
        pieces.append(escaped[:cut])
        escaped = escaped[cut:]
    cards = []
    for i, piece in enumerate(pieces):
        last = i == len(pieces) - 1
        body = f"'{piece}{'' if last else '&'}'"
        head = f"{key:<8}= " if i == 0 else "CONTINUE  "
        cards.append(f"{head}{body}".ljust(CARD)[:CARD])
    if comment:
        cards[-1] = (cards[-1].rstrip() + f" / {_ascii_text(comment)}")[:CARD].ljust(CARD)
    return "".join(cards)


def history_cards(text: str) -> list:
    """HISTORY cards carrying ``text``, wrapped at 72 characters."""
    return [format_card("HISTORY", text[i:i + 72]) for i in range(0, max(len(text), 1), 72)]


def _ascii_checksum(value: int) -> str:
    """The 16-character ASCII encoding of a 32-bit checksum (FITS Standard, Appendix J)."""
    value = (~value) & 0xFFFFFFFF  # encode the complement so the HDU sums to -0
    excluded = set(range(0x3A, 0x41)) | set(range(0x5B, 0x61))
    chars = [0] * 16
    for i in range(4):
        byte = (value >> (24 - 8 * i)) & 0xFF
        quotient, remainder = byte // 4 + 0x30, byte % 4
        ch = [quotient + remainder, quotient, quotient, quotient]
        changed = True
        while changed:
            changed = False
            for j in (0, 2):
                while ch[j] in excluded or ch[j + 1] in excluded:
                    ch[j] += 1
                    ch[j + 1] -= 1
                    changed = True
        for j in range(4):
            chars[4 * j + i] = ch[j]
    text = bytes(chars).decode("ascii")
    return text[-1] + text[:-1]  # rotate right by one character


#: structural and checksum keywords: written by fitsio or by the checksum pass, never copied
_STRUCTURAL = {"SIMPLE", "XTENSION", "BITPIX", "NAXIS", "EXTEND", "PCOUNT", "GCOUNT", "BZERO", "BSCALE",
               "BLANK", "CHECKSUM", "DATASUM", "EXTNAME", "TFIELDS", "THEAP", "ZIMAGE", "ZBITPIX", "ZNAXIS",
               "ZTILE1", "ZTILE2", "ZTILE3", "ZCMPTYPE", "ZQUANTIZ", "ZDITHER0", "ZHECKSUM", "ZDATASUM",
               "ZSIMPLE", "ZEXTEND", "ZTENSION", "ZPCOUNT", "ZGCOUNT", "ZBLANK"}
_STRUCTURAL_PATTERN = re.compile(r"^(NAXIS\d+|ZNAXIS\d+|ZTILE\d+|ZNAME\d+|ZVAL\d+|T(TYPE|FORM|UNIT|DIM|NULL|SCAL|ZERO|DISP)\d+)$")


def _is_structural(key: str) -> bool:
    return key in _STRUCTURAL or _STRUCTURAL_PATTERN.match(key) is not None


@dataclass
class OutHDU:
    """An HDU to write: card images (no structural keywords needed) and its data.

    Attributes
    ----------
    cards : list of str
        80-character card images; structural, scaling and checksum keywords
        among them are ignored (they are written for ``data``).
    data : ndarray, bytes-like or None
        An image (any byte order), a structured array for a binary table, or
        the stored bytes of an HDU copied unchanged (then ``cards`` must be
        its complete header).
    extname : str, optional
    units : sequence of str, optional
        TUNITn of a table's columns.
    datasum : int, optional
        The FITS DATASUM of ``data`` as stored, when whoever made ``data``
        (big-endian, C-contiguous) summed it already, block by block in its
        own threads; the plain-image writer then writes the bytes in one
        call instead of summing them again in one thread.
    """

    cards: list
    data: object = None
    extname: str | None = None
    units: list | None = None
    datasum: int | None = None

    def set(self, key: str, value, comment: str | None = None):
        """Replace ``key``'s card (and its CONTINUE cards), or append it."""
        text = format_card(key, value, comment)
        new = [text[i:i + CARD] for i in range(0, len(text), CARD)]
        for i, old in enumerate(self.cards):
            if old[:8].rstrip() == key.upper() and old[8:10] == "= ":
                j = i + 1
                while j < len(self.cards) and self.cards[j][:8] == "CONTINUE":
                    j += 1
                self.cards[i:j] = new
                return
        self.cards.extend(new)

    def __setitem__(self, key, value):
        """``hdu[key] = value`` or ``(value, comment)``, like an astropy Header."""
        if isinstance(value, tuple):
            self.set(key, *value)
        else:
            self.set(key, value)

    def get(self, key, default=None):
        return Header(self.cards).get(key, default)

    def add_history(self, text: str):
        self.cards.extend(history_cards(text))

    def add_comment(self, text: str):
        self.cards.append(format_card("COMMENT", text))

    @property
    def header(self) -> "OutHDU":
        """The HDU itself: ``hdu.header[key] = value`` reads as with astropy."""
        return self

    def remove(self, *keys, matching=None):
        """Drop the cards of ``keys`` (and of keywords for which ``matching(key)`` is true)."""
        keys = {k.upper() for k in keys}
        kept, dropping = [], False
        for card in self.cards:
            key = card[:8].rstrip()
            if key == "CONTINUE" and dropping:
                continue
            dropping = card[8:10] == "= " and (key in keys or (matching is not None and matching(key)))
            if not dropping:
                kept.append(card)
        self.cards = kept


def table_hdu(columns: dict, extname: str, *, units: dict | None = None, descriptions: dict | None = None,
              cards=()) -> OutHDU:
    """A binary-table HDU from named columns (1-D, or 2-D for a vector per row).

    Parameters
    ----------
    columns : dict of str -> array_like
        In order; text becomes fixed-width ASCII, booleans FITS logicals.
    extname : str
    units : dict, optional
        TUNITn by column name.
    descriptions : dict, optional
        Written as the comments of the TTYPEn cards.
    cards : sequence of str
        More header cards.
    """
    arrays = {}
    for name, values in columns.items():
        values = np.asarray(values)
        if values.dtype.kind == "U":
            values = np.char.encode(values, "ascii", errors="replace")
        if values.dtype.kind == "S" and values.dtype.itemsize == 0:
            values = values.astype("S1")
        arrays[name] = values
    n = len(next(iter(arrays.values()))) if arrays else 0
    dtype = [(name, v.dtype.newbyteorder("=") if v.dtype.kind not in "SUb" else v.dtype, v.shape[1:])
             for name, v in arrays.items()]
    table = np.empty(n, dtype=dtype)
    for name, v in arrays.items():
        table[name] = v
    out = list(cards)
    for k, name in enumerate(arrays, 1):
        if descriptions and name in descriptions:
            out.append(format_card(f"TTYPE{k}", name, descriptions[name]))
    return OutHDU(out, table, extname=extname, units=[str((units or {}).get(name) or "") for name in arrays])


#: lossless tile compression of images: GZIP_2 (byte-shuffled gzip) keeps every float bit
COMPRESSIONS = ("none", "gzip", "rice")


def _native(arr: np.ndarray) -> np.ndarray:
    # fitsio 1.4 silently corrupts big-endian arrays written to a compressed HDU: always native order
    if arr.dtype.byteorder not in ("=", "|"):
        arr = arr.astype(arr.dtype.newbyteorder("="))
    return np.ascontiguousarray(arr)


def _header_cards(cards) -> list:
    """The cards to copy into an output HDU: everything but structure and checksums, then placeholders.

    Raises
    ------
    PerscliError
        A card that is not valid FITS (inputs are checked as they are
        opened, so this guards perscli's own cards): an output that other
        readers refuse is never written.
    """
    out = [c.ljust(CARD)[:CARD] for c in cards
           if not _is_structural(c[:8].rstrip()) and c.strip() != "" and c[:8] != "END     "]
    for card in out:
        try:
            problem = _card_problem(card.encode("ascii"))
        except UnicodeEncodeError:
            problem = "holds characters that are not ASCII text"
        if problem is not None:
            raise PerscliError(f"cannot write the header card {card.rstrip()!r}: it {problem}")
    return out + _PLACEHOLDERS


def _write_one(fits, hdu: OutHDU, *, first: bool, compress: str) -> None:
    """Append one HDU to an open fitsio file: structure from the data, then the cards verbatim.

    Cards are written as they are (CFITSIO's ``fits_write_record``), so values
    keep every digit they had: an MJD copied from an input is not rounded.
    """
    data = hdu.data
    extname = hdu.extname
    if extname is None:
        extname = Header(hdu.cards).get("EXTNAME")
        extname = str(extname).strip() if extname is not None else None
    if data is not None and not isinstance(data, np.ndarray):
        raise TypeError("OutHDU.data must be a numpy array or None")
    if data is not None and data.dtype.names:
        if first:
            fits.write(None)
        fits.write_table(_native(data), extname=extname, units=hdu.units)
        # column descriptions given as comments of TTYPEn cards are kept (fitsio writes bare TTYPEn)
        for card in hdu.cards:
            key = card[:8].rstrip()
            if re.fullmatch(r"TTYPE\d+", key) and card[8:10] == "= ":
                value, comment = _parse_value(card[10:])
                if comment:
                    fits[-1].write_key(key, value, comment=comment)
    else:
        kwargs = {}
        if compress != "none" and data is not None and data.size and not first:
            if compress == "rice" and data.dtype.kind == "f":
                raise PerscliError("--compress rice is lossless only for integer data; use --compress gzip")
            # qlevel 0: no quantisation, every bit of a float image is kept; one tile per row
            kwargs = dict(compress="GZIP_2" if compress == "gzip" else "RICE", qlevel=0.0)
            if data.ndim == 2:
                kwargs["tile_dims"] = [1, data.shape[1]]
        if data is None or not data.size:
            fits.write(None, extname=extname)
            _write_cards(fits, hdu.cards)
        else:
            # the header first, then the data: cards written after the data would make CFITSIO move
            # the whole data unit each time the header grows by a block
            data = _native(data)
            if kwargs:
                fits.create_image_hdu(dims=data.shape, dtype=data.dtype, extname=extname, **kwargs)
                _write_cards(fits, hdu.cards)
            else:
                # one pixel while the header is written, then the real size: the data unit is never moved
                fits.create_image_hdu(dims=[1] * data.ndim, dtype=data.dtype, extname=extname)
                _write_cards(fits, hdu.cards)
                fits[-1].reshape(data.shape)
            fits[-1].write(data)
        return
    _write_cards(fits, hdu.cards)


def _write_cards(fits, cards) -> None:
    ext = len(fits)
    for card in _header_cards(cards):
        try:
            fits._FITS.write_record(ext, card)
        except (OSError, ValueError) as exc:
            # a fault of the file (a full disk, a file-size limit: CFITSIO's status 104 to 113) is the
            # writer's to report (write_fits_path names the system's reason), not the card's
            status = re.search(r"FITSIO status = (\d+)", str(exc))
            if isinstance(exc, OSError) and status and int(status.group(1)) in _CFITSIO_FILE_FAULTS:
                raise
            raise PerscliError(f"cannot write the header card {card.rstrip()!r}: {_cfitsio_reason(exc)}") from None
    fits.update_hdu_list()


#: CFITSIO status codes of a file that cannot be written or read back (FILE_NOT_OPENED to
#: MEMORY_ALLOCATION: 106 WRITE_ERROR, 107 END_OF_FILE after a short write, 112 READONLY_FILE)
_CFITSIO_FILE_FAULTS = frozenset(range(104, 114))


def _finish_checksums(path: str) -> None:
    """Write DATASUM and CHECKSUM into every HDU of a written file, in place.

    CFITSIO's own checksum cards carry the time of writing in their comments;
    these carry fixed comments, so the same content gives the same bytes.
    """
    import fitsio

    from .. import _kernels

    with fitsio.FITS(path) as f:
        offsets = [h.get_offsets() for h in f]
    fd = os.open(path, os.O_RDWR)
    try:
        for off in offsets:
            h0, d0, d1 = int(off["header_start"]), int(off["data_start"]), int(off["data_end"])
            datasum = 0
            pos, end = d0, d0 + padded(d1 - d0)
            while pos < end:
                n = min(_CHUNK, end - pos)
                datasum = ones_complement_add(datasum, _kernels.datasum(os.pread(fd, n, pos)))
                pos += n
            header = bytearray(os.pread(fd, d0 - h0, h0))
            where = {}
            for i in range(0, len(header), CARD):
                key = bytes(header[i:i + 8])
                if key in (b"CHECKSU_", b"DATASUM_"):
                    where.setdefault({b"CHECKSU_": "CHECKSUM", b"DATASUM_": "DATASUM"}[key], i)
                elif key == b"END     ":
                    break
            if "CHECKSUM" not in where or "DATASUM" not in where:
                raise RuntimeError(f"{path}: CHECKSUM/DATASUM placeholders missing in an HDU")
            c, d = where["CHECKSUM"], where["DATASUM"]
            header[d:d + CARD] = format_card("DATASUM", str(datasum), "data unit checksum").encode("ascii")
            header[c:c + CARD] = format_card("CHECKSUM", "0" * 16, "HDU checksum").encode("ascii")
            total = ones_complement_add(_kernels.datasum(bytes(header)), datasum)
            header[c:c + CARD] = format_card("CHECKSUM", _ascii_checksum(total), "HDU checksum").encode("ascii")
            os.pwrite(fd, bytes(header), h0)
    finally:
        os.close(fd)


#: fitsio drops CHECKSUM/DATASUM cards it is given: these stand in for them until _finish_checksums
_PLACEHOLDERS = [format_card("CHECKSU_", "0" * 16, "HDU checksum"), format_card("DATASUM_", "0", "data unit checksum")]


def write_fits_path(hdus, path: str, *, compress: str = "none") -> None:
    """Write :class:`OutHDU` s to ``path`` (created or replaced) with CHECKSUM/DATASUM in every HDU.

    Parameters
    ----------
    hdus : sequence of OutHDU
        The first is the primary HDU.
    path : str
        A plain file name (no CFITSIO syntax), e.g. a temporary file.
    compress : {'none', 'gzip', 'rice'}
        Tile-compress the image extensions: 'gzip' is GZIP_2 without
        quantisation (lossless for every data type); 'rice' is lossless for
        integer images only.
    """
    import fitsio

    if compress not in COMPRESSIONS:
        raise PerscliError(f"--compress must be one of {', '.join(COMPRESSIONS)}, not {compress!r}")
    if compress == "none" and all(_plain_image(h.data) for h in hdus):
        _write_plain(hdus, path)
        return
    try:
        with fitsio.FITS(path, "rw", clobber=True, ignore_empty=True) as out:
            for i, hdu in enumerate(hdus):
                _write_one(out, hdu, first=i == 0, compress=compress)
    except OSError as exc:
        if exc.errno is not None or "FITSIO status" not in str(exc):
            raise
        # CFITSIO says 'error writing to FITS file' (or 'tried to move past end of file' after one):
        # the system's reason is found again, so that the message names it
        _raise_write_fault(path, _cfitsio_reason(exc))
    _check_complete(path, len(hdus))
    _finish_checksums(path)


def _check_complete(path: str, nhdus: int) -> None:
    """Raise the OSError of a write CFITSIO lost: fitsio may close a file cut short by a full disk or
    a file-size limit (ENOSPC, EFBIG) without an error, leaving fewer bytes than its headers declare."""
    import fitsio

    size = os.path.getsize(path)
    try:
        with fitsio.FITS(path) as f:
            offsets = [h.get_offsets() for h in f]
        complete = len(offsets) == nhdus and padded(int(offsets[-1]["data_end"])) == size and size % BLOCK == 0
    except Exception:  # noqa: BLE001 - CFITSIO cannot read back what it wrote: incomplete
        complete = False
    if not complete:
        _raise_write_fault(path, f"the file is incomplete ({size} bytes)")


def _raise_write_fault(path: str, what: str):
    """Raise the OSError behind a write that CFITSIO reported without the system's reason.

    One block is written past the end of ``path``: a full disk, a quota or
    a file-size limit fails it again with its own errno (ENOSPC, EDQUOT,
    EFBIG), which the message the user reads then names.  When it does not
    fail, an OSError (EIO) with ``what``.
    """
    size = os.path.getsize(path)
    fd = os.open(path, os.O_WRONLY)
    try:
        offset, end = size, size + BLOCK
        while offset < end:     # a write that partly fits returns short; the next one fails
            written = os.pwrite(fd, bytes(end - offset), offset)
            if written <= 0:
                break
            offset += written
    finally:
        os.close(fd)
    raise OSError(errno.EIO, f"the FITS writer (CFITSIO) failed: {what}", path)


_PLAIN_BITPIX = {"f4": -32, "f8": -64, "i2": 16, "i4": 32, "i8": 64, "u1": 8}


def _plain_image(data) -> bool:
    """Data the fast writer stores as they are: no table, no scaling needed (no unsigned 16/32/64-bit)."""
    return data is None or (isinstance(data, np.ndarray) and not data.dtype.names
                            and data.dtype.str[1:] in _PLAIN_BITPIX)


def _write_plain(hdus, path: str) -> None:
    """The fast path for plain images: cards and big-endian bytes streamed, checksums computed on the way.

    benchmarks/bench_apply_persistence.py shows why it exists: CFITSIO sizes
    a new image by writing zeros over its data unit before the data are
    written, and writing a 67 MB frame that way costs three times as long
    (0.17 s against 0.055 s, a third of the whole apply-persistence run).
    The bytes are what the fitsio path writes, apart from CFITSIO's own
    comment cards (tests/test_fits_io.py compares the two).
    """
    from .. import _kernels

    with open(path, "wb") as fh:
        for i, hdu in enumerate(hdus):
            data = hdu.data
            if data is not None and data.size == 0:
                data = None
            extname = hdu.extname
            if extname is None:
                extname = Header(hdu.cards).get("EXTNAME")
            bitpix = 16 if data is None else _PLAIN_BITPIX[data.dtype.str[1:]]  # 16 for no data, as CFITSIO
            naxis = () if data is None else data.shape[::-1]
            head = [format_card("SIMPLE", True, "conforms to FITS standard") if i == 0
                    else format_card("XTENSION", "IMAGE", "image extension"),
                    format_card("BITPIX", bitpix, "array data type"),
                    format_card("NAXIS", len(naxis), "number of array dimensions")]
            head += [format_card(f"NAXIS{k}", int(n)) for k, n in enumerate(naxis, 1)]
            head += ([format_card("EXTEND", True)] if i == 0
                     else [format_card("PCOUNT", 0, "number of parameters"), format_card("GCOUNT", 1, "number of groups")])
            if extname:
                head.append(format_card("EXTNAME", str(extname).strip(), "extension name"))
            cards = head + [c for c in _header_cards(hdu.cards) if c[:8] not in ("CHECKSU_", "DATASUM_")]
            cards.append(format_card("CHECKSUM", "0" * 16, "HDU checksum"))
            cards.append(format_card("DATASUM", "0", "data unit checksum"))
            start = fh.tell()
            fh.write(_header_bytes(cards))  # its size does not depend on the checksum values
            datasum, nbytes = 0, 0
            if data is not None and hdu.datasum is not None and data.dtype.byteorder == ">" \
                    and data.flags.c_contiguous:
                # stored bytes already, summed by their producer
                datasum, nbytes = int(hdu.datasum), data.nbytes
                fh.write(memoryview(data.reshape(-1)).cast("B"))
                fh.write(b"\0" * (padded(nbytes) - nbytes))
            elif data is not None:
                # big-endian a slab at a time: no second copy of the whole image in memory
                be = data.dtype.newbyteorder(">")
                flat = data.reshape(-1) if data.flags.c_contiguous else np.ascontiguousarray(data).reshape(-1)
                step = max(1, (1 << 22) // data.dtype.itemsize)
                for a in range(0, flat.size, step):
                    chunk = memoryview(np.ascontiguousarray(flat[a:a + step], dtype=be)).cast("B")
                    datasum = ones_complement_add(datasum, _kernels.datasum(chunk))
                    fh.write(chunk)
                    nbytes += len(chunk)
                fh.write(b"\0" * (padded(nbytes) - nbytes))
            end = fh.tell()
            cards[-1] = format_card("DATASUM", str(datasum), "data unit checksum")
            total = ones_complement_add(_kernels.datasum(_header_bytes(cards)), datasum)
            cards[-2] = format_card("CHECKSUM", _ascii_checksum(total), "HDU checksum")
            fh.seek(start)
            fh.write(_header_bytes(cards))
            fh.seek(end)


def _header_bytes(cards) -> bytes:
    text = "".join(c.ljust(CARD)[:CARD] for c in cards) + "END".ljust(CARD)
    text += " " * (padded(len(text)) - len(text))
    return text.encode("ascii")


def gzip_file(src: str, dest_fd: int) -> None:
    """gzip ``src`` into ``dest_fd`` with no name or time stamp, so that equal content gives equal bytes."""
    import gzip

    with open(src, "rb") as fin, os.fdopen(os.dup(dest_fd), "wb") as raw, \
            gzip.GzipFile(filename="", mode="wb", fileobj=raw, mtime=0, compresslevel=6) as gz:
        while True:
            chunk = fin.read(_CHUNK)
            if not chunk:
                break
            gz.write(chunk)
