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
  (``--no-checksum``: :func:`perscli.io.checksum.read_options`, carried to
  worker threads, processes and Dask tasks) for files edited on purpose.
- The one hand-written fast path: rows of a plain, uncompressed image are read
  with ``os.pread`` as stored (big-endian), so that apply-persistence's
  compiled kernel converts, models and checksums them in one pass
  (benchmarks/bench_apply_persistence.py measures what it saves).

Outputs (:func:`write_hdus`) are written by fitsio, optionally tile-compressed
(lossless GZIP_2) or gzip-compressed as a whole (``-o x.fits.gz``), with
CHECKSUM/DATASUM computed here so that the same content always gives the same
bytes (CFITSIO's own cards carry the time of writing in their comments).

Layout: this module is the writer (:class:`OutHDU`, :func:`table_hdu`,
:func:`write_fits_path`, :func:`gzip_file`) and the layer's entry point; the
rest is in :mod:`perscli.io.sources` (paths, stdin, FIFOs, gzip),
:mod:`perscli.io.cards` (header cards: parsing, checks, formatting),
:mod:`perscli.io.checksum` (CHECKSUM/DATASUM, ``--no-checksum``) and
:mod:`perscli.io.fitsreader` (:class:`FitsFile`, :class:`HDU`).
"""

from __future__ import annotations

import errno
import gzip
import os
import re
from dataclasses import dataclass

import fitsio
import numpy as np

from .. import PerscliError, _kernels

# tests monkeypatch ``fitsfile._ascii_checksum``, which the writer below looks up here, as it does
# ``_header_cards`` and ``_plain_image``, defined here
from .cards import BLOCK, CARD, Header, _card_problem, _is_structural, _parse_value, format_card, history_cards, padded
from .checksum import _ascii_checksum, ones_complement_add
from .fitsreader import _cfitsio_reason
from .sources import _CHUNK

# -- writing -------------------------------------------------------------------------------------

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
    with open(src, "rb") as fin, os.fdopen(os.dup(dest_fd), "wb") as raw, \
            gzip.GzipFile(filename="", mode="wb", fileobj=raw, mtime=0, compresslevel=6) as gz:
        while True:
            chunk = fin.read(_CHUNK)
            if not chunk:
                break
            gz.write(chunk)
