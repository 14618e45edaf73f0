"""FITS checksums (FITS Standard, Appendix J): CHECKSUM and DATASUM, and the switch that turns their check off.

- :func:`read_options` (``--no-checksum``), :func:`checksums_enabled`,
  :class:`carrying_read_options` (how the options reach worker threads,
  processes and Dask tasks), and :data:`CHECKSUM_HINT`, what a mismatch means
  and what to do.
- :func:`ones_complement_add`: how the DATASUMs of pieces combine.
- :func:`_stored_cards`, :func:`_verify_header_bytes`: the check of a stored
  header against its CHECKSUM, without reading the data.
- :func:`_ascii_checksum`: the 16-character encoding the writer stores.

The sums of data are computed by the compiled :mod:`perscli._kernels`;
:class:`perscli.io.fitsreader.HDU` verifies data as it reads them and the
writer (:mod:`perscli.io.fitsfile`) signs
its outputs.
"""

from __future__ import annotations

import contextlib
import contextvars

from .. import PerscliError, _kernels
from .cards import CARD, _parse_value


#: what a checksum mismatch means and what to do: most often a file edited by a tool that kept the
#: old CHECKSUM/DATASUM cards (astropy does, unless told checksum=True), less often a damaged copy
CHECKSUM_HINT = ("the checksums are stale (the file changed after they were written, e.g. edited with a tool "
                 "that kept the old cards) or the file is corrupt: if it was edited on purpose, update them "
                 "with astropy's `fitscheck --force FILE` or give --no-checksum; otherwise re-copy it")


#: whether the CHECKSUM/DATASUM of inputs are verified, in the current context (thread, task)
_VERIFY = contextvars.ContextVar("perscli_verify_checksums", default=True)


def checksums_enabled() -> bool:
    """Whether CHECKSUM/DATASUM of inputs are verified here (:func:`read_options` turns it off)."""
    return _VERIFY.get()


@contextlib.contextmanager
def read_options(*, verify_checksums: bool = True):
    """The options of the FITS reads made inside the block, as ``rasterio.Env`` holds GDAL's.

    Passed down, not global: they hold in this thread's context (a ``contextvars`` variable) until
    the block ends, so one command's ``--no-checksum`` never reaches the next call in the same
    process; :class:`carrying_read_options` takes them to the executor's threads, processes and
    Dask tasks.

    Parameters
    ----------
    verify_checksums : bool
        Verify the CHECKSUM and DATASUM of every HDU read (False: ``--no-checksum``, for files
        edited on purpose).
    """
    token = _VERIFY.set(bool(verify_checksums))
    try:
        yield
    finally:
        _VERIFY.reset(token)


def current_read_options() -> dict:
    """The read options in force here, as keyword arguments of :func:`read_options`."""
    return {"verify_checksums": _VERIFY.get()}


class carrying_read_options:
    """``func`` with the read options in force where this was made, wherever it is called.

    A worker thread starts from an empty context and a worker process or a Dask worker on
    another machine knows nothing of the command line: the executor and the study's runner wrap
    each function they hand out.  Picklable when ``func`` is.
    """

    def __init__(self, func, options: dict | None = None):
        self.func = func
        self.options = current_read_options() if options is None else dict(options)

    def __call__(self, *args, **kwargs):
        with read_options(**self.options):
            return self.func(*args, **kwargs)


def ones_complement_add(a: int, b: int) -> int:
    """Add two 32-bit ones'-complement sums (how FITS DATASUMs of pieces combine)."""
    s = a + b
    while s >> 32:
        s = (s & 0xFFFFFFFF) + (s >> 32)
    return s


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


def _verify_header_bytes(raw: bytes, where: str) -> None:
    """Check a header's bytes against its CHECKSUM, with the DATASUM it states (no data read)."""
    if not checksums_enabled():
        return

    stored = _stored_cards(raw)
    stated = str(stored.get("DATASUM", "")).strip()
    if "CHECKSUM" not in stored or not stated.isdigit() or int(stated) > 0xFFFFFFFF:
        return
    if ones_complement_add(_kernels.datasum(raw), int(stated)) != 0xFFFFFFFF:
        raise PerscliError(f"{where}: the header does not match its CHECKSUM: {CHECKSUM_HINT}")


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
