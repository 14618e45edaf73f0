"""A small, fast FITS reader and writer for image files.

Why not astropy here: importing ``astropy.io.fits`` costs ~0.3 s per process,
more than the whole persistence computation of ten full Roman frames, and
astropy offers no way to stream the pixels of many files side by side.  FITS
(Standard 4.0) is simple enough for what perscli's frame layer needs:

- :func:`scan` walks the HDUs of a file or a byte string and parses their
  headers (fixed-format cards, long strings with CONTINUE, HIERARCH);
- :meth:`HDU.read_rows` reads rows of an image straight from the file
  (``os.pread``), so frames are streamed and never mapped whole;
- :class:`Writer` writes HDUs with DATASUM and CHECKSUM (Appendix J of the
  Standard) computed by the compiled kernel, copying the cards of the input
  verbatim so that nothing in a header is lost or reformatted.

Tables and everything else are passed through as bytes; astropy remains the
tool for building tables (commands that need it import it themselves).
"""

from __future__ import annotations

import math
import os
from dataclasses import dataclass, field

import numpy as np

from .. import PerscliError

BLOCK = 2880
CARD = 80

_BITPIX_DTYPES = {8: ">u1", 16: ">i2", 32: ">i4", 64: ">i8", -32: ">f4", -64: ">f8"}


def _parse_value(text: str):
    """Value of a fixed- or free-format card field (after '= ')."""
    s = text.lstrip()
    if not s:
        return None, ""
    if s[0] == "'":
        out = []
        i = 1
        while i < len(s):
            if s[i] == "'":
                if i + 1 < len(s) and s[i + 1] == "'":
                    out.append("'")
                    i += 2
                    continue
                break
            out.append(s[i])
            i += 1
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

    Attributes
    ----------
    cards : list of str
        The 80-character card images as found (END excluded).
    """

    def __init__(self, cards):
        self.cards = list(cards)
        self._values = {}
        self._history = []
        pending = None
        for card in self.cards:
            key = card[:8].rstrip()
            if key == "CONTINUE" and pending is not None:
                more, _ = _parse_value(card[8:])
                if isinstance(more, str):
                    prev = self._values[pending]
                    self._values[pending] = prev[:-1] + more if prev.endswith("&") else prev + more
                    continue
            pending = None
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
                pending = key

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


@dataclass
class HDU:
    """One HDU of a scanned file: where it is and what its header says."""

    index: int
    header: Header
    header_offset: int
    data_offset: int
    data_size: int          # bytes of data, without the block padding
    source: "Source" = field(repr=False)

    @property
    def name(self) -> str:
        if self.index == 0:
            return str(self.header.get("EXTNAME", "PRIMARY")).strip().upper()
        return str(self.header.get("EXTNAME", "")).strip().upper()

    @property
    def ver(self) -> int:
        return int(self.header.get("EXTVER", 1))

    @property
    def is_image(self) -> bool:
        return self.index == 0 or str(self.header.get("XTENSION", "")).strip() == "IMAGE"

    @property
    def shape(self) -> tuple:
        """numpy-order shape of the data (slowest axis first)."""
        naxis = int(self.header.get("NAXIS", 0))
        return tuple(int(self.header[f"NAXIS{k}"]) for k in range(naxis, 0, -1))

    @property
    def dtype(self) -> np.dtype:
        bitpix = int(self.header["BITPIX"])
        if bitpix not in _BITPIX_DTYPES:
            raise PerscliError(f"{self.source.label}: HDU {self.index} has BITPIX={bitpix}, not a FITS value")
        return np.dtype(_BITPIX_DTYPES[bitpix])

    @property
    def scaling(self) -> tuple:
        """(BSCALE, BZERO), (1, 0) when absent."""
        return float(self.header.get("BSCALE", 1.0)), float(self.header.get("BZERO", 0.0))

    @property
    def is_plain_float(self) -> bool:
        """Float data with no scaling: the on-disk bytes can be used as they are."""
        return self.dtype.kind == "f" and self.scaling == (1.0, 0.0)

    def raw_bytes(self, start: int = 0, length: int | None = None):
        """Bytes of the data unit (as stored, big-endian), from ``start``."""
        if length is None:
            length = self.data_size - start
        return self.source.pread(self.data_offset + start, length)

    def header_bytes(self) -> bytes:
        return bytes(self.source.pread(self.header_offset, self.data_offset - self.header_offset))

    def read_rows(self, r0: int, r1: int, plane: int = 0, *, native: bool = False) -> np.ndarray:
        """Rows ``r0:r1`` of a 2-D image, or of plane ``plane`` of a 3-D cube.

        Float data come back as they are stored (big-endian) unless
        ``native``; integer data are scaled with BSCALE/BZERO to float64.
        """
        shape = self.shape
        ny, nx = shape[-2], shape[-1]
        item = self.dtype.itemsize
        start = (plane * ny + r0) * nx * item
        buf = self.raw_bytes(start, (r1 - r0) * nx * item)
        arr = np.frombuffer(buf, dtype=self.dtype).reshape(r1 - r0, nx)
        if self.dtype.kind != "f" or self.scaling != (1.0, 0.0):
            return self._scaled(arr)
        return arr.astype(arr.dtype.newbyteorder("=")) if native else arr

    def _scaled(self, arr: np.ndarray) -> np.ndarray:
        """Physical values of stored integers: BSCALE * stored + BZERO, BLANK as NaN."""
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

    def read(self, *, native: bool = True) -> np.ndarray:
        """All the data, scaled, as an array of the HDU's shape."""
        shape = self.shape
        if not shape:
            return None
        if len(shape) == 2:
            return self.read_rows(0, shape[0], native=native)
        buf = self.raw_bytes(0, self.data_size)
        arr = np.frombuffer(buf, dtype=self.dtype).reshape(shape)
        if self.dtype.kind != "f" or self.scaling != (1.0, 0.0):
            return self._scaled(arr)
        return arr.astype(arr.dtype.newbyteorder("=")) if native else arr

    def datasum(self) -> int:
        """FITS DATASUM of the data as stored."""
        from .. import _kernels

        if self.data_size == 0:
            return 0
        return _kernels.datasum(self.raw_bytes(0, self.data_size))


class Source:
    """Random access to the bytes of a FITS file (a path) or of a byte string."""

    def __init__(self, label: str, path: str | None = None, data: bytes | None = None):
        self.label = label
        self.path = path
        self.data = data
        self.fd = None
        if path is not None:
            self.fd = os.open(path, os.O_RDONLY)
            self.size = os.fstat(self.fd).st_size
        else:
            self.size = len(data)

    def pread(self, offset: int, length: int):
        if self.data is not None:
            return memoryview(self.data)[offset:offset + length]
        buf = bytearray(length)
        view = memoryview(buf)
        got = 0
        while got < length:
            n = os.preadv(self.fd, [view[got:]], offset + got)
            if n == 0:
                raise PerscliError(f"{self.label}: the file is truncated (ends at byte {offset + got})")
            got += n
        return buf

    def close(self):
        if self.fd is not None:
            os.close(self.fd)
            self.fd = None


def data_size(header: Header) -> int:
    """Bytes of an HDU's data from its header (FITS Standard 4.4.1), without padding."""
    naxis = int(header.get("NAXIS", 0))
    if naxis == 0:
        return 0
    dims = [int(header.get(f"NAXIS{k}", 0)) for k in range(1, naxis + 1)]
    if header.get("GROUPS") is True and dims[0] == 0:
        dims = dims[1:]
    n = math.prod(dims)
    return abs(int(header["BITPIX"])) // 8 * int(header.get("GCOUNT", 1)) * (int(header.get("PCOUNT", 0)) + n)


def padded(n: int) -> int:
    return (n + BLOCK - 1) // BLOCK * BLOCK


def scan(source: Source) -> list:
    """Walk the HDUs of ``source`` and parse their headers.

    Raises
    ------
    PerscliError
        Not FITS, a header without END, or data running past the end of the file.
    """
    hdus = []
    offset = 0
    label = source.label
    if source.size == 0:
        raise PerscliError(f"{label}: the file is empty; check that it was written completely")
    while offset < source.size:
        cards = []
        pos = offset
        while True:
            if pos + BLOCK > source.size:
                if not hdus and not cards:
                    raise PerscliError(f"{label}: not a FITS file (shorter than one 2880-byte block); "
                                       "check that it is complete and really FITS")
                if cards or bytes(source.pread(pos, source.size - pos)).strip(b"\0 "):
                    raise PerscliError(f"{label}: the file is truncated inside the header of HDU {len(hdus)}; "
                                       "re-copy or regenerate it")
                return hdus
            block = bytes(source.pread(pos, BLOCK))
            pos += BLOCK
            if not cards:
                first = block[:10]
                if not hdus and first != b"SIMPLE  = ":
                    raise PerscliError(f"{label}: not a FITS file (no SIMPLE card at the start); "
                                       "check that it is complete and really FITS")
                if hdus and first != b"XTENSION= ":
                    if block.strip(b"\0 "):
                        # bytes after the last HDU that are not an extension: ignored, as astropy does
                        pass
                    return hdus
            try:
                text = block.decode("ascii")
            except UnicodeDecodeError:
                raise PerscliError(f"{label}: HDU {len(hdus)} has non-ASCII bytes in its header: "
                                   "the file is corrupt") from None
            done = False
            for i in range(0, BLOCK, CARD):
                card = text[i:i + CARD]
                if card[:8] == "END     " or card.rstrip() == "END":
                    done = True
                    break
                cards.append(card)
            if done:
                break
        header = Header(cards)
        try:
            size = data_size(header)
        except (KeyError, ValueError, TypeError):
            raise PerscliError(f"{label}: HDU {len(hdus)} has a malformed BITPIX/NAXIS header; "
                               "the file is corrupt") from None
        if pos + size > source.size:
            raise PerscliError(f"{label}: the file is truncated: HDU {len(hdus)} needs {pos + size} bytes "
                               f"but the file has {source.size}; re-copy or regenerate it")
        hdus.append(HDU(len(hdus), header, offset, pos, size, source))
        offset = pos + padded(size)
    return hdus


# -- writing ----------------------------------------------------------------

def _format_value(value) -> str:
    if isinstance(value, bool):
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
    text = str(value).replace("'", "''")
    # fixed format: the closing quote at column 20 or later, as astropy and cfitsio write it
    quoted = f"'{text:<8}'"
    return f"{quoted:<20}"


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
        return f"{key:<8}{str(value or '')}"[:CARD].ljust(CARD)
    text = _format_value(value)
    if isinstance(value, str) and len(text.rstrip()) > 70:
        return _long_string_cards(key, value, comment)
    card = f"{key:<8}= {text}"
    if comment:
        card += f" / {comment}"
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
        cards[-1] = (cards[-1].rstrip() + f" / {comment}")[:CARD].ljust(CARD)
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


def _add32(a: int, b: int) -> int:
    s = a + b
    return (s & 0xFFFFFFFF) + (s >> 32)


@dataclass
class OutHDU:
    """An HDU to write: card images (no END) and big-endian data bytes."""

    cards: list
    data: object = b""     # bytes-like, the data unit without padding

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

    def add_history(self, text: str):
        self.cards.extend(history_cards(text))

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


def image_cards(data: np.ndarray, cards, *, primary: bool, extname: str | None = None) -> list:
    """Cards of an image HDU holding ``data``: structural keywords first, then ``cards``.

    Structural and scaling keywords in ``cards`` (SIMPLE/XTENSION, BITPIX,
    NAXISn, EXTEND, PCOUNT, GCOUNT, BZERO, BSCALE, BLANK, CHECKSUM, DATASUM)
    are dropped and rewritten for ``data``.
    """
    bitpix = {np.dtype(v).str[1:]: k for k, v in _BITPIX_DTYPES.items()}[data.dtype.str[1:]]
    head = [format_card("SIMPLE", True, "conforms to FITS standard") if primary
            else format_card("XTENSION", "IMAGE", "image extension"),
            format_card("BITPIX", bitpix, "array data type"),
            format_card("NAXIS", data.ndim, "number of array dimensions")]
    for k, n in enumerate(data.shape[::-1], 1):
        head.append(format_card(f"NAXIS{k}", int(n)))
    if primary:
        head.append(format_card("EXTEND", True))
    else:
        head += [format_card("PCOUNT", 0, "number of parameters"), format_card("GCOUNT", 1, "number of groups")]
    structural = {"SIMPLE", "XTENSION", "BITPIX", "NAXIS", "EXTEND", "PCOUNT", "GCOUNT", "BZERO", "BSCALE",
                  "BLANK", "CHECKSUM", "DATASUM", "EXTNAME"}
    rest = []
    for card in cards:
        key = card[:8].rstrip()
        if key in structural or (key.startswith("NAXIS") and key[5:].isdigit()):
            continue
        rest.append(card)
    if extname:
        head.append(format_card("EXTNAME", extname, "extension name"))
    return head + rest


def to_bytes(data: np.ndarray):
    """Big-endian bytes of an array (no copy when it already is)."""
    be = data.dtype.newbyteorder(">")
    if data.dtype != be or not data.flags.c_contiguous:
        data = np.ascontiguousarray(data, dtype=be)
    return memoryview(data).cast("B")


class Writer:
    """Serialise HDUs with DATASUM and CHECKSUM, into a file object."""

    def __init__(self, stream):
        self.stream = stream

    def write(self, hdu: OutHDU):
        from .. import _kernels

        data = hdu.data if hdu.data is not None else b""
        datasum = _kernels.datasum(data) if len(data) else 0
        hdu.set("CHECKSUM", "0" * 16, "HDU checksum")
        hdu.set("DATASUM", str(datasum), "data unit checksum")
        header = self._header_bytes(hdu.cards)
        total = _add32(_kernels.datasum(header), datasum)
        while total >> 32:
            total = (total & 0xFFFFFFFF) + (total >> 32)
        hdu.set("CHECKSUM", _ascii_checksum(total), "HDU checksum")
        self.stream.write(self._header_bytes(hdu.cards))
        if len(data):
            self.stream.write(data)
            pad = padded(len(data)) - len(data)
            if pad:
                self.stream.write(b"\0" * pad)

    @staticmethod
    def _header_bytes(cards) -> bytes:
        text = "".join(c.ljust(CARD)[:CARD] for c in cards) + "END".ljust(CARD)
        text += " " * (padded(len(text)) - len(text))
        return text.encode("ascii")
