"""Reading frames: image data, units, gain and timing from FITS headers.

A *frame* is one exposure: a 2-D image, a WFC3-IR MULTIACCUM file (one SCI
extension per read) or a 3-D cube of reads with a read-time table.  This
module turns the many ways a header can say the same thing into one
:class:`Frame`:

==========  ==============================================================
data        the SCI extension if there is one, else the primary HDU
units       BUNIT: electron, electron/s, DN, DN/s and the HST spellings
            ELECTRONS, ELECTRONS/S, COUNTS, COUNTS/S (case-insensitive)
gain        GAIN, else CCDGAIN (e-/DN), unless ``gain=`` is given
exptime     EXPTIME, else XPOSURE (s), else ``exptime=``, else end - start
timing      EXPSTART/EXPEND (MJD, as HST writes them), else MJD-BEG/MJD-END,
            else DATE-OBS (+ TIME-OBS) plus the exposure time
fluence     of an earlier exposure: a FLUENCE extension (electrons, as
            ``perscli render`` writes) if there is one, else the data
ramps       WFC3-IR raw/ima: SCI,1 is the last read, SCI,NSAMP the zeroth;
            SAMPTIME (s since the start) per read.  Cubes: (read, y, x) in
            time order with a READTIMES table (column TIME, s since start).
==========  ==============================================================

Keywords are looked up in the science extension's header first, then in the
primary header.  Opening a frame reads only its headers; pixels are read
when asked for, row block by row block (:meth:`Frame.rows`), so that many
frames can be streamed side by side.  ``-`` reads a FITS stream from
standard input into memory (a pipe cannot seek).
"""

from __future__ import annotations

import datetime as _dt
import sys
from dataclasses import dataclass, field

import numpy as np

from .. import PerscliError
from .fitsfile import HDU, Source, scan

#: canonical unit -> (is DN, is a rate)
UNITS = {
    "electron": (False, False),
    "electron/s": (False, True),
    "DN": (True, False),
    "DN/s": (True, True),
}

_UNIT_ALIASES = {
    "electron": "electron", "electrons": "electron", "e-": "electron", "e": "electron",
    "electron/s": "electron/s", "electrons/s": "electron/s", "e-/s": "electron/s",
    "e/s": "electron/s", "electron s-1": "electron/s", "electron.s-1": "electron/s",
    "electron / s": "electron/s",
    "dn": "DN", "count": "DN", "counts": "DN", "adu": "DN",
    "dn/s": "DN/s", "counts/s": "DN/s", "count/s": "DN/s", "adu/s": "DN/s", "dn s-1": "DN/s",
    "dn / s": "DN/s",
}

MJD_EPOCH = _dt.datetime(1858, 11, 17)
SECONDS_PER_DAY = 86400.0

TIMING_HINT = ("add EXPSTART/EXPEND (MJD), MJD-BEG/MJD-END, or DATE-OBS with EXPTIME to the header, "
               "or give --gap SECONDS (and --exptime SECONDS) to treat the inputs as a regular sequence "
               "in command-line order")


def normalize_unit(text: str, source: str = "BUNIT") -> str:
    """Map a BUNIT spelling to one of :data:`UNITS`.

    Parameters
    ----------
    text : str
        The unit as written ('ELECTRONS/S', 'e-', 'DN', ...).
    source : str
        Where it came from, for the error message.
    """
    key = " ".join(str(text).strip().lower().split())
    if key not in _UNIT_ALIASES:
        raise PerscliError(
            f"{source}={text!r} is not a unit perscli understands: use electron, electron/s, DN or DN/s "
            "(or the HST spellings ELECTRONS, ELECTRONS/S, COUNTS, COUNTS/S)")
    return _UNIT_ALIASES[key]


def parse_date_obs(date: str, time: str | None = None, label: str = "") -> float:
    """ISO-8601 DATE-OBS (with TIME-OBS when DATE-OBS has no time) to MJD.

    A time-zone offset, if present, is honoured (the result is in UTC).
    """
    text = str(date).strip()
    if "T" not in text and time:
        text = f"{text}T{str(time).strip()}"
    where = f"{label}: " if label else ""
    try:
        moment = _dt.datetime.fromisoformat(text[:-1] + "+00:00" if text.endswith("Z") else text)
    except ValueError:
        raise PerscliError(f"{where}DATE-OBS={date!r} is not an ISO-8601 date (YYYY-MM-DDThh:mm:ss); "
                           "fix the header or give EXPSTART/EXPEND") from None
    if moment.tzinfo is not None:
        moment = moment.astimezone(_dt.timezone.utc).replace(tzinfo=None)
    return (moment - MJD_EPOCH).total_seconds() / SECONDS_PER_DAY


@dataclass
class Frame:
    """One exposure read from a FITS file.

    Attributes
    ----------
    name : str
        The path, or '-' for standard input.
    hdus : list of perscli.io.fitsfile.HDU
        Every HDU of the file (headers parsed, data not read).
    sci : list of int
        HDU indices of the science arrays in time order (one for an image or
        a cube; the reads of a WFC3 ramp, zeroth read first).
    layout : {'image', 'wfc3-ramp', 'cube'}
    unit : str
        One of :data:`UNITS`.
    gain : float or None
        e-/DN.
    exptime : float or None
        Seconds.
    start, end : float or None
        MJD of the start and end of the exposure.
    read_times : ndarray or None
        Seconds since the start of the exposure, one per read (ramps only).
    timing_source : str
        Which keywords (or option) gave the timing.
    """

    name: str
    hdus: list
    sci: list
    layout: str
    unit: str
    gain: float | None
    exptime: float | None
    start: float | None
    end: float | None
    read_times: np.ndarray | None = None
    timing_source: str = ""
    source: Source | None = field(default=None, repr=False)
    fluence_hdu: int | None = None
    image_shape: tuple | None = None

    @classmethod
    def planned(cls, name: str, shape: tuple, start: float, end: float, exptime: float, offsets=None,
                sca: int | None = None):
        """An exposure that is being made (no file yet): timing and shape only.

        Used as the 'current' frame when rendering with persistence from
        earlier exposures; ``offsets`` are its (LTV1, LTV2) for a cutout and
        ``sca`` its detector.
        """
        from .fitsfile import Header, format_card

        cards = [format_card("LTV1", float(offsets[0])), format_card("LTV2", float(offsets[1]))] if offsets else []
        if sca is not None:
            cards.append(format_card("SCA", int(sca)))
        frame = cls(name=name, hdus=[], sci=[], layout="image", unit="electron", gain=None, exptime=exptime,
                    start=start, end=end, image_shape=tuple(shape))
        frame._planned_header = Header(cards)
        return frame

    @property
    def label(self) -> str:
        return "stdin" if self.name == "-" else self.name

    # -- headers ---------------------------------------------------------
    @property
    def header(self):
        """Header of the (first) science HDU."""
        if not self.sci:
            return self._planned_header
        return self.hdus[self.sci[0]].header

    def keyword(self, key, default=None):
        """A keyword from the science header, else from the primary header."""
        for hdr in (self.header, self.hdus[0].header if self.hdus else self.header):
            if key in hdr and hdr[key] not in (None, ""):
                return hdr[key]
        return default

    @property
    def is_ramp(self) -> bool:
        return self.layout in ("wfc3-ramp", "cube")

    @property
    def nreads(self) -> int:
        return len(self.read_times) if self.is_ramp else 1

    @property
    def shape(self) -> tuple:
        """Shape of one image (one read)."""
        if self.image_shape is not None:
            return self.image_shape
        return tuple(self.hdus[self.sci[0]].shape[-2:])

    # -- pixels ----------------------------------------------------------
    def _plane(self, k: int):
        """(HDU, plane index within it) of read ``k`` in time order."""
        if self.layout == "cube":
            return self.hdus[self.sci[0]], k
        return self.hdus[self.sci[k]], 0

    def rows(self, k: int, r0: int, r1: int) -> np.ndarray:
        """Rows ``r0:r1`` of plane ``k`` (time order) in the file's units.

        Float data are returned as stored (big-endian, no copy); integer data
        are scaled to float64.
        """
        hdu, plane = self._plane(k)
        return hdu.read_rows(r0, r1, plane)

    def planes(self) -> list:
        """The science arrays in time order, in the file's units (native byte order)."""
        ny = self.shape[0]
        return [_native(self.rows(k, 0, ny)) for k in range(self.nreads)]

    def electrons_per_unit(self, seconds: float | None = None) -> float:
        """Factor that turns a value in this frame's unit into electrons.

        Parameters
        ----------
        seconds : float, optional
            Integration time the value refers to (default: the exposure time).
        """
        is_dn, is_rate = UNITS[self.unit]
        factor = 1.0
        if is_dn:
            if self.gain is None:
                raise PerscliError(
                    f"{self.label}: BUNIT is {self.unit} but the header has neither GAIN nor CCDGAIN; "
                    "give --gain E_PER_DN")
            factor *= self.gain
        if is_rate:
            if seconds is None:
                seconds = self.exptime
            if seconds is None:
                raise PerscliError(
                    f"{self.label}: BUNIT is {self.unit} (a rate) but the header has no EXPTIME or XPOSURE; "
                    "give --exptime SECONDS")
            factor *= seconds
        return factor

    def fluence_rows(self, r0: int, r1: int):
        """The accumulated charge of rows ``r0:r1``, as ``(array, scale)``.

        ``array * scale`` is the fluence in electrons.  For a float image the
        array is the file's bytes as stored (no conversion: the compiled
        kernel swaps bytes itself); for a ramp it is the last read minus the
        zeroth read.
        """
        if self.fluence_hdu is not None:
            # a frame perscli rendered: its FLUENCE extension holds the collected charge in electrons
            return self.hdus[self.fluence_hdu].read_rows(r0, r1), 1.0
        if not self.is_ramp:
            return self.rows(0, r0, r1), self.electrons_per_unit()
        last = np.asarray(self.rows(self.nreads - 1, r0, r1), dtype=np.float64)
        first = np.asarray(self.rows(0, r0, r1), dtype=np.float64)
        if UNITS[self.unit][1]:
            # a rate ramp (WFC3 ima) stores each read's charge divided by its SAMPTIME
            charge = last * self.read_times[-1] - first * self.read_times[0]
        else:
            charge = last - first
        return charge, self.electrons_per_unit(seconds=1.0)

    def fluence(self):
        """The accumulated charge of the whole exposure, as ``(array, scale)`` (see :meth:`fluence_rows`)."""
        array, scale = self.fluence_rows(0, self.shape[0])
        return _native(array), scale

    @property
    def fluence_is_raw(self) -> bool:
        """True when :meth:`fluence_rows` hands out the stored bytes (their DATASUM can be folded in)."""
        if self.fluence_hdu is not None:
            return self.hdus[self.fluence_hdu].is_plain_float
        return not self.is_ramp and self.hdus[self.sci[0]].is_plain_float

    @property
    def provenance_hdu(self) -> int:
        """The HDU whose DATASUM stands for this frame in provenance (FLUENCE if used, the last read
        of a ramp, else the science HDU)."""
        if self.fluence_hdu is not None:
            return self.fluence_hdu
        return self.sci[-1] if self.layout == "wfc3-ramp" else self.sci[0]

    def check_datasum(self, index: int, value: int) -> int:
        """Compare a computed DATASUM with the header's, if it states one."""
        hdu = self.hdus[index]
        stated = str(hdu.header.get("DATASUM", "")).strip()
        if stated.isdigit() and int(stated) != value:
            raise PerscliError(
                f"{self.label}: HDU {index} ({hdu.name or 'PRIMARY'}) data do not match its DATASUM "
                f"({stated}, computed {value}): the file is corrupt; re-copy it "
                "(or delete DATASUM if the data were edited on purpose)")
        return value

    def datasum(self, index: int) -> int:
        """FITS DATASUM of HDU ``index`` computed from its bytes as stored.

        Raises
        ------
        PerscliError
            If the header carries a DATASUM that the data do not match.
        """
        return self.check_datasum(index, self.hdus[index].datasum())

    def close(self):
        """Release the file."""
        if self.source is not None:
            self.source.close()


def _native(array: np.ndarray) -> np.ndarray:
    return np.asarray(array, dtype=array.dtype.newbyteorder("="))


def _read_stdin(stdin) -> bytes:
    stream = stdin if stdin is not None else sys.stdin.buffer
    data = stream.read()
    if not data:
        raise PerscliError("stdin: standard input is empty; pipe a FITS file into it")
    return data


def _open_source(name: str, stdin=None) -> Source:
    import os

    if name == "-":
        return Source("stdin", data=_read_stdin(stdin))
    if not os.path.exists(name):
        raise PerscliError(f"{name}: no such file")
    if os.path.isdir(name):
        raise PerscliError(f"{name}: is a directory, not a FITS file; give the path of a file inside it")
    try:
        return Source(name, path=name)
    except OSError as exc:
        raise PerscliError(f"{name}: cannot be read ({exc.strerror})") from None


def _science_hdus(name, hdus):
    """Find the science arrays and the layout of a file."""
    sci = [h.index for h in hdus if h.name == "SCI" and h.is_image]
    if len(sci) > 1:
        by_ver = sorted(sci, key=lambda i: hdus[i].ver)
        if all("SAMPTIME" in hdus[i].header for i in by_ver):
            # WFC3 MULTIACCUM: SCI,1 is the last read, so time order is descending EXTVER
            return by_ver[::-1], "wfc3-ramp"
        raise PerscliError(
            f"{name}: {len(sci)} SCI extensions but no SAMPTIME keywords: not a MULTIACCUM ramp; "
            "extract one SCI extension (e.g. fitscopy 'file[SCI,1]')")
    if sci:
        index = sci[0]
    elif int(hdus[0].header.get("NAXIS", 0)) > 0:
        index = 0
    else:
        raise PerscliError(f"{name}: no image data: expected a SCI extension or an image in the primary HDU")
    hdu = hdus[index]
    if hdu.data_size == 0:
        raise PerscliError(f"{name}: the {'SCI' if sci else 'primary'} HDU holds no data")
    ndim = len(hdu.shape)
    if ndim == 2:
        return [index], "image"
    if ndim == 3:
        return [index], "cube"
    raise PerscliError(f"{name}: the image has {ndim} axes; expected 2 (an image) or 3 (reads, y, x)")


def _read_times(name, hdus, sci, layout, nplanes):
    if layout == "wfc3-ramp":
        times = np.array([float(hdus[i].header["SAMPTIME"]) for i in sci])
    else:
        tables = [h for h in hdus if h.name in ("READTIMES", "READ_TIMES", "TIMES")
                  and str(h.header.get("XTENSION", "")).strip() == "BINTABLE"]
        if not tables:
            raise PerscliError(
                f"{name}: a 3-D cube needs a READTIMES table (column TIME, seconds since the exposure start, "
                "one row per read)")
        times = _table_column(name, tables[0], "TIME")
        if len(times) != nplanes:
            raise PerscliError(f"{name}: READTIMES has {len(times)} rows but the cube has {nplanes} reads")
    if not np.all(np.isfinite(times)) or np.any(np.diff(times) < 0) or times[0] < 0:
        raise PerscliError(f"{name}: read times must be finite, non-negative and increasing; got {times.tolist()}")
    return times


def _table_column(name, hdu: HDU, column: str) -> np.ndarray:
    """A numeric column of a binary table, read with numpy from the raw rows."""
    hdr = hdu.header
    nfields = int(hdr.get("TFIELDS", 0))
    formats = {"D": ">f8", "E": ">f4", "J": ">i4", "K": ">i8", "I": ">i2", "B": "u1"}
    fields = []
    for i in range(1, nfields + 1):
        tform = str(hdr.get(f"TFORM{i}", "")).strip()
        repeat = "".join(ch for ch in tform if ch.isdigit()) or "1"
        code = tform.lstrip("0123456789")[:1]
        ttype = str(hdr.get(f"TTYPE{i}", f"col{i}")).strip()
        width = {"D": 8, "E": 4, "J": 4, "K": 8, "I": 2, "B": 1, "L": 1, "A": 1, "X": 0}.get(code)
        if width is None:
            raise PerscliError(f"{name}: READTIMES column {ttype} has unsupported format {tform}")
        dtype = formats.get(code, f"V{width}")
        fields.append((ttype, dtype, int(repeat)))
    names = [f[0] for f in fields]
    match = [n for n in names if n.upper() == column]
    if not match:
        raise PerscliError(f"{name}: the READTIMES table has no {column} column (seconds since the exposure start)")
    dtype = np.dtype([(n, d) if r == 1 else (n, d, (r,)) for n, d, r in fields])
    nrows = int(hdr.get("NAXIS2", 0))
    if dtype.itemsize != int(hdr.get("NAXIS1", 0)):
        raise PerscliError(f"{name}: the READTIMES table's row length does not match its columns")
    rows = np.frombuffer(hdu.raw_bytes(0, nrows * dtype.itemsize), dtype=dtype)
    return np.asarray(rows[match[0]], dtype=np.float64)


def _float_keyword(frame_hdrs, key, name):
    for hdr in frame_hdrs:
        if key in hdr and hdr[key] not in (None, ""):
            try:
                value = float(hdr[key])
            except (TypeError, ValueError):
                raise PerscliError(f"{name}: keyword {key}={hdr[key]!r} is not a number") from None
            if not np.isfinite(value):
                raise PerscliError(f"{name}: keyword {key}={hdr[key]!r} is not finite")
            return value
    return None


def _first(hdrs, key):
    return next((h[key] for h in hdrs if h.get(key) not in (None, "")), None)


def open_frame(name: str, *, units: str | None = None, gain: float | None = None,
               exptime: float | None = None, stdin=None) -> Frame:
    """Open a FITS frame and read its units, gain, exposure time and timing.

    Parameters
    ----------
    name : str
        Path, or '-' for standard input.
    units : str, optional
        Overrides BUNIT (any spelling :func:`normalize_unit` accepts).
    gain : float, optional
        Overrides GAIN/CCDGAIN, in e-/DN.
    exptime : float, optional
        Exposure time in seconds for frames whose header has none.
    stdin : binary file, optional
        Stream to read for '-' (default ``sys.stdin.buffer``).

    Returns
    -------
    Frame
        Timing may be missing (``start is None``): :func:`require_timing`
        says what is needed.

    Raises
    ------
    PerscliError
        Unreadable, truncated or corrupt file; no image; unknown units.
    """
    source = _open_source(name, stdin)
    label = source.label
    try:
        hdus = scan(source)
        sci, layout = _science_hdus(label, hdus)
        hdrs = (hdus[sci[0]].header, hdus[0].header)
        nplanes = hdus[sci[0]].shape[0] if layout == "cube" else len(sci)
        read_times = _read_times(label, hdus, sci, layout, nplanes) if layout != "image" else None
        for i in sci:
            if hdus[i].shape[-2:] != hdus[sci[0]].shape[-2:]:
                raise PerscliError(f"{label}: the reads of the ramp differ in shape")

        if units is not None:
            unit = normalize_unit(units, "--units")
        else:
            bunit = _first(hdrs, "BUNIT")
            if bunit is None:
                raise PerscliError(f"{label}: no BUNIT keyword; give --units electron|electron/s|DN|DN/s")
            unit = normalize_unit(bunit, f"{label}: BUNIT")

        if gain is None:
            gain = _float_keyword(hdrs, "GAIN", label)
            if gain is None:
                gain = _float_keyword(hdrs, "CCDGAIN", label)
        if gain is not None and gain <= 0:
            raise PerscliError(f"{label}: gain {gain} e-/DN must be positive; give --gain E_PER_DN")

        start = _float_keyword(hdrs, "EXPSTART", label)
        end = _float_keyword(hdrs, "EXPEND", label)
        source_kw = "EXPSTART/EXPEND"
        if start is None or end is None:
            start = _float_keyword(hdrs, "MJD-BEG", label)
            end = _float_keyword(hdrs, "MJD-END", label)
            source_kw = "MJD-BEG/MJD-END"
        hdr_exptime = _float_keyword(hdrs, "EXPTIME", label)
        if hdr_exptime is None:
            hdr_exptime = _float_keyword(hdrs, "XPOSURE", label)
        if hdr_exptime is None:
            hdr_exptime = exptime
        if start is None or end is None:
            start = end = None
            date = _first(hdrs, "DATE-OBS")
            if date is not None and hdr_exptime is not None:
                start = parse_date_obs(date, _first(hdrs, "TIME-OBS"), label)
                end = start + hdr_exptime / SECONDS_PER_DAY
                source_kw = "DATE-OBS+EXPTIME"
            else:
                source_kw = ""
        if start is not None and end < start:
            raise PerscliError(f"{label}: the exposure ends ({end}) before it starts ({start}) ({source_kw})")
        if hdr_exptime is None and start is not None:
            hdr_exptime = (end - start) * SECONDS_PER_DAY
        if hdr_exptime is not None and hdr_exptime < 0:
            raise PerscliError(f"{label}: exposure time {hdr_exptime} s is negative")
        fluence = [h.index for h in hdus if h.name == "FLUENCE" and h.is_image and h.data_size]
        if fluence and hdus[fluence[0]].shape[-2:] != hdus[sci[0]].shape[-2:]:
            raise PerscliError(f"{label}: the FLUENCE extension's shape differs from the science image's")
        return Frame(name=name, hdus=hdus, sci=sci, layout=layout, unit=unit, gain=gain,
                     exptime=hdr_exptime, start=start, end=end, read_times=read_times,
                     timing_source=source_kw, source=source, fluence_hdu=fluence[0] if fluence else None)
    except BaseException:
        source.close()
        raise


def assign_sequence_timing(frames, gap: float, exptime: float | None = None):
    """Give frames the timing of a regular sequence, in the order given.

    Each frame lasts its own exposure time (or ``exptime``) and starts
    ``gap`` seconds after the previous one ends; the first starts at MJD 0.
    Used when headers carry no timestamps (``--gap``).
    """
    t = 0.0
    for frame in frames:
        seconds = frame.exptime if frame.exptime is not None else exptime
        if seconds is None:
            raise PerscliError(f"{frame.label}: --gap needs an exposure time: the header has no EXPTIME; "
                               "give --exptime SECONDS")
        frame.exptime = seconds
        frame.start = t / SECONDS_PER_DAY
        t += seconds
        frame.end = t / SECONDS_PER_DAY
        frame.timing_source = f"--gap {gap:g}"
        t += gap


def require_timing(frame: Frame):
    """Raise a clear error if ``frame`` has no start/end time."""
    if frame.start is None or frame.end is None:
        raise PerscliError(f"{frame.label}: no exposure timing; {TIMING_HINT}")
