"""Reading FITS inputs: :func:`open_fits` and :class:`FitsFile`, its :class:`HDU` s, and their checks.

CFITSIO (through fitsio) parses the file; this module checks what CFITSIO
lets through before any data are used (structure, scaling keywords, every
card, CHECKSUM of every header), explains what CFITSIO cannot read
(:func:`_header_fault`, :func:`_describe_cfitsio`), and reads data: plain
images straight from the :class:`~perscli.io.sources.Source` with
``os.pread`` (the fast path), the rest through CFITSIO, CHECKSUM/DATASUM
verified on the way.

Part of the FITS layer whose writer is :mod:`perscli.io.fitsfile`.
"""

from __future__ import annotations

import math
import re
from dataclasses import dataclass, field

import fitsio
import numpy as np

from .. import PerscliError, _kernels
from .cards import BLOCK, CARD, Header, _check_cards, _is_structural, format_card, padded
from .checksum import CHECKSUM_HINT, _stored_cards, _verify_header_bytes, checksums_enabled, ones_complement_add
from .sources import _CHUNK, Source, open_source, split_selector

_BITPIX_DTYPES = {8: ">u1", 16: ">i2", 32: ">i4", 64: ">i8", -32: ">f4", -64: ">f8"}


# -- HDUs ----------------------------------------------------------------------------------------

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
                tail = bytes(self.source.pread(self.data_end, pad))
                if size % 4:
                    tail = bytes(size % 4) + tail  # keep the 32-bit words aligned to the data's start
                datasum = ones_complement_add(datasum, _kernels.datasum(tail))
        self._datasum = datasum
        if not checksums_enabled():
            self.verified = True
            return datasum

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
