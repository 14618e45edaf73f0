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
ramps       WFC3-IR raw/ima: SCI,1 is the last read, SCI,NSAMP the zeroth;
            SAMPTIME (s since the start) per read.  Cubes: (read, y, x) in
            time order with a READTIMES table (column TIME, s since start).
==========  ==============================================================

Keywords are looked up in the science extension's header first, then in the
primary header.  Files are memory-mapped, so a frame costs no memory until its
pixels are used; ``-`` reads a FITS stream from standard input into memory
(astropy cannot seek on a pipe).
"""

from __future__ import annotations

import datetime as _dt
import io
import os
import sys
import warnings
from dataclasses import dataclass, field

import numpy as np
from astropy.io import fits

from .. import PerscliError

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


def parse_date_obs(date: str, time: str | None = None) -> float:
    """ISO-8601 DATE-OBS (with TIME-OBS when DATE-OBS has no time) to MJD."""
    text = str(date).strip()
    if "T" not in text and time:
        text = f"{text}T{str(time).strip()}"
    try:
        moment = _dt.datetime.fromisoformat(text.rstrip("Z"))
    except ValueError:
        raise PerscliError(f"DATE-OBS={date!r} is not an ISO-8601 date (YYYY-MM-DDThh:mm:ss)") from None
    return (moment - MJD_EPOCH).total_seconds() / SECONDS_PER_DAY


@dataclass
class Frame:
    """One exposure read from a FITS file.

    Attributes
    ----------
    name : str
        The path, or '-' for standard input.
    hdul : astropy.io.fits.HDUList
        The open file (memory-mapped).
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
    raw : bytes or None
        The whole file, when it came from standard input.
    """

    name: str
    hdul: fits.HDUList
    sci: list
    layout: str
    unit: str
    gain: float | None
    exptime: float | None
    start: float | None
    end: float | None
    read_times: np.ndarray | None = None
    raw: bytes | None = field(default=None, repr=False)
    timing_source: str = ""

    # -- headers ---------------------------------------------------------
    @property
    def header(self) -> fits.Header:
        """Header of the (first) science HDU."""
        return self.hdul[self.sci[0]].header

    def keyword(self, key, default=None):
        """A keyword from the science header, else from the primary header."""
        for hdr in (self.header, self.hdul[0].header):
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
        shape = self.hdul[self.sci[0]].shape
        return tuple(shape[-2:])

    # -- pixels ----------------------------------------------------------
    def planes(self) -> list:
        """The science arrays in time order, in the file's units (memmaps where possible)."""
        if self.layout == "cube":
            data = self.hdul[self.sci[0]].data
            return [data[k] for k in range(data.shape[0])]
        return [self.hdul[i].data for i in self.sci]

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
                    f"{self.name}: BUNIT is {self.unit} but the header has neither GAIN nor CCDGAIN; "
                    "give --gain E_PER_DN")
            factor *= self.gain
        if is_rate:
            if seconds is None:
                seconds = self.exptime
            if seconds is None:
                raise PerscliError(
                    f"{self.name}: BUNIT is {self.unit} (a rate) but the header has no EXPTIME or XPOSURE; "
                    "give --exptime SECONDS")
            factor *= seconds
        return factor

    def fluence(self):
        """The accumulated charge of this exposure, as ``(array, scale)``.

        ``array * scale`` is the fluence in electrons.  For a plain float
        image the array is the file's own memory map (no copy); for a ramp
        it is the last read minus the zeroth read.
        """
        if not self.is_ramp:
            data = self.hdul[self.sci[0]].data
            if data.dtype.kind != "f":
                data = np.asarray(data, dtype=np.float64)
            return data, self.electrons_per_unit()
        planes = self.planes()
        is_dn, is_rate = UNITS[self.unit]
        last = np.asarray(planes[-1], dtype=np.float64)
        first = np.asarray(planes[0], dtype=np.float64)
        if is_rate:
            # a rate ramp (WFC3 ima) stores each read's charge divided by its SAMPTIME
            charge = (last * self.read_times[-1] - first * self.read_times[0])
        else:
            charge = last - first
        return charge, self.electrons_per_unit(seconds=1.0)

    def datasum(self, index: int) -> int:
        """FITS DATASUM of HDU ``index``, computed from its bytes as stored.

        Raises
        ------
        PerscliError
            If the header carries a DATASUM that the data do not match (the
            data were corrupted after the file was written).
        """
        from .. import _kernels

        hdu = self.hdul[index]
        info = hdu.fileinfo()
        if info is None or info["datSpan"] == 0:
            return 0
        loc, span = info["datLoc"], info["datSpan"]
        if self.raw is not None:
            value = _kernels.datasum(memoryview(self.raw)[loc:loc + span])
        else:
            mm = np.memmap(self.name, dtype=np.uint8, mode="r", offset=loc, shape=(span,))
            try:
                value = _kernels.datasum(mm)
            finally:
                del mm
        stated = str(hdu.header.get("DATASUM", "")).strip()
        if stated.isdigit() and int(stated) != value:
            label = "stdin" if self.name == "-" else self.name
            raise PerscliError(
                f"{label}: HDU {index} ({hdu.name}) data do not match its DATASUM ({stated}, computed {value}): "
                "the file is corrupt; re-copy it (or delete DATASUM if the data were edited on purpose)")
        return value

    def close(self):
        """Release the memory map (pages of earlier frames are not kept)."""
        self.hdul.close()


def _read_bytes(name: str, stdin) -> bytes:
    stream = stdin if stdin is not None else sys.stdin.buffer
    data = stream.read()
    if not data:
        raise PerscliError(f"{name}: standard input is empty; pipe a FITS file into it")
    return data


def _open_hdul(name: str, stdin=None):
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        try:
            if name == "-":
                raw = _read_bytes("stdin", stdin)
                hdul = fits.open(io.BytesIO(raw), memmap=False, lazy_load_hdus=False)
            else:
                raw = None
                if not os.path.exists(name):
                    raise PerscliError(f"{name}: no such file")
                if os.path.isdir(name):
                    raise PerscliError(f"{name}: is a directory, not a FITS file")
                hdul = fits.open(name, mode="readonly", lazy_load_hdus=False)
        except PerscliError:
            raise
        except (OSError, ValueError, TypeError, IndexError, KeyError) as exc:
            what = str(exc).splitlines()[0] if str(exc) else type(exc).__name__
            raise PerscliError(f"{'stdin' if name == '-' else name}: not a readable FITS file ({what}); "
                               "check that it is complete and really FITS") from None
    for w in caught:
        if "truncated" in str(w.message):
            raise PerscliError(f"{'stdin' if name == '-' else name}: the file is truncated: "
                               f"{str(w.message).split(';')[0]}; re-copy or regenerate it")
    return hdul, raw


def _data_bytes(header) -> int:
    """Size of an HDU's data in bytes from its header (FITS Standard 4.4.1.1)."""
    naxis = int(header.get("NAXIS", 0))
    if naxis == 0:
        return 0
    n = 1
    for k in range(1, naxis + 1):
        n *= int(header.get(f"NAXIS{k}", 0))
    return abs(int(header["BITPIX"])) // 8 * int(header.get("GCOUNT", 1)) * (int(header.get("PCOUNT", 0)) + n)


def _check_complete(name, hdul, raw):
    size = len(raw) if raw is not None else os.path.getsize(name)
    for i, hdu in enumerate(hdul):
        info = hdu.fileinfo()
        if info is None:
            continue
        need = info["datLoc"] + _data_bytes(hdu.header)
        if need > size:
            raise PerscliError(
                f"{name}: the file is truncated: HDU {i} needs {need} bytes but the file has {size}; "
                "re-copy or regenerate it")


def _science_hdus(name, hdul):
    """Find the science arrays and the layout of a file."""
    sci = [i for i, h in enumerate(hdul) if h.name == "SCI" and getattr(h, "is_image", False)]
    if len(sci) > 1:
        by_ver = sorted(sci, key=lambda i: hdul[i].ver)
        if all("SAMPTIME" in hdul[i].header for i in by_ver):
            # WFC3 MULTIACCUM: SCI,1 is the last read, so time order is descending EXTVER
            return by_ver[::-1], "wfc3-ramp"
        raise PerscliError(
            f"{name}: {len(sci)} SCI extensions but no SAMPTIME keywords: not a MULTIACCUM ramp; "
            "extract one SCI extension (e.g. fitscopy 'file[SCI,1]')")
    if sci:
        index = sci[0]
    elif hdul[0].header.get("NAXIS", 0) > 0:
        index = 0
    else:
        raise PerscliError(f"{name}: no image data: expected a SCI extension or an image in the primary HDU")
    hdu = hdul[index]
    if hdu.data is None or hdu.header.get("NAXIS", 0) == 0:
        raise PerscliError(f"{name}: the {'SCI' if sci else 'primary'} HDU holds no data")
    ndim = hdu.header["NAXIS"]
    if ndim == 2:
        return [index], "image"
    if ndim == 3:
        return [index], "cube"
    raise PerscliError(f"{name}: the image has {ndim} axes; expected 2 (an image) or 3 (reads, y, x)")


def _read_times(name, hdul, sci, layout, nplanes):
    if layout == "wfc3-ramp":
        times = np.array([float(hdul[i].header["SAMPTIME"]) for i in sci])
    else:
        tables = [h for h in hdul if h.name in ("READTIMES", "READ_TIMES", "TIMES") and isinstance(h, fits.BinTableHDU)]
        if not tables:
            raise PerscliError(
                f"{name}: a 3-D cube needs a READTIMES table (column TIME, seconds since the exposure start, "
                "one row per read)")
        cols = {c.lower(): c for c in tables[0].columns.names}
        if "time" not in cols:
            raise PerscliError(f"{name}: the READTIMES table has no TIME column (seconds since the exposure start)")
        times = np.asarray(tables[0].data[cols["time"]], dtype=np.float64)
        if len(times) != nplanes:
            raise PerscliError(f"{name}: READTIMES has {len(times)} rows but the cube has {nplanes} reads")
    if not np.all(np.isfinite(times)) or np.any(np.diff(times) < 0) or times[0] < 0:
        raise PerscliError(f"{name}: read times must be finite, non-negative and increasing; got {times.tolist()}")
    return times


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
    label = "stdin" if name == "-" else name
    hdul, raw = _open_hdul(name, stdin)
    try:
        _check_complete(label, hdul, raw)
        sci, layout = _science_hdus(label, hdul)
        hdrs = (hdul[sci[0]].header, hdul[0].header)
        nplanes = hdul[sci[0]].shape[0] if layout == "cube" else len(sci)
        read_times = _read_times(label, hdul, sci, layout, nplanes) if layout != "image" else None

        if units is not None:
            unit = normalize_unit(units, "--units")
        else:
            bunit = next((h["BUNIT"] for h in hdrs if h.get("BUNIT") not in (None, "")), None)
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
        source = "EXPSTART/EXPEND"
        if start is None or end is None:
            start = _float_keyword(hdrs, "MJD-BEG", label)
            end = _float_keyword(hdrs, "MJD-END", label)
            source = "MJD-BEG/MJD-END"
        hdr_exptime = _float_keyword(hdrs, "EXPTIME", label)
        if hdr_exptime is None:
            hdr_exptime = _float_keyword(hdrs, "XPOSURE", label)
        if hdr_exptime is None:
            hdr_exptime = exptime
        if start is None or end is None:
            start = end = None
            date = next((h["DATE-OBS"] for h in hdrs if h.get("DATE-OBS") not in (None, "")), None)
            if date is not None and hdr_exptime is not None:
                time_obs = next((h["TIME-OBS"] for h in hdrs if h.get("TIME-OBS") not in (None, "")), None)
                start = parse_date_obs(date, time_obs)
                end = start + hdr_exptime / SECONDS_PER_DAY
                source = "DATE-OBS+EXPTIME"
            else:
                source = ""
        if start is not None and end < start:
            raise PerscliError(f"{label}: the exposure ends ({end}) before it starts ({start}) ({source})")
        if hdr_exptime is None and start is not None:
            hdr_exptime = (end - start) * SECONDS_PER_DAY
        if hdr_exptime is not None and hdr_exptime < 0:
            raise PerscliError(f"{label}: exposure time {hdr_exptime} s is negative")
        return Frame(name=name, hdul=hdul, sci=sci, layout=layout, unit=unit, gain=gain,
                     exptime=hdr_exptime, start=start, end=end, read_times=read_times, raw=raw,
                     timing_source=source)
    except BaseException:
        hdul.close()
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
            raise PerscliError(f"{frame.name}: --gap needs an exposure time: the header has no EXPTIME; "
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
        label = "stdin" if frame.name == "-" else frame.name
        raise PerscliError(f"{label}: no exposure timing; {TIMING_HINT}")
