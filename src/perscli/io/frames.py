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
placement   where the pixels lie on the detector (:meth:`Frame.placement`):
            detector pixel = image pixel - LTV (LTV1 for x, LTV2 for y, FITS
            1-indexed; IRAF's convention, which HST, JWST and CFITSIO image
            sections follow); WFC3-IR raw/ima frames have a border of 5
            reference pixels that sees no light (calwf3 trims it from flt)
==========  ==============================================================

Fluence of the HST products (what an earlier exposure leaves behind):

- flt (2-D, BUNIT ELECTRONS/S): rate x EXPTIME;
- raw (MULTIACCUM, COUNTS): (last read - zeroth read) x CCDGAIN;
- ima (MULTIACCUM, calibrated): the last read's accumulated signal: its rate
  x its SAMPTIME when in ELECTRONS/S; in ELECTRONS or COUNTS the last read
  itself when calwf3 has subtracted the zeroth read (ZOFFCORR = 'COMPLETE'),
  else last minus zeroth read.

Keywords are looked up in the science extension's header first, then in the
primary header.  Opening a frame reads only its headers; pixels are read
when asked for, row block by row block (:meth:`Frame.rows`), so that many
frames can be streamed side by side, and the CHECKSUM/DATASUM of every HDU
read are verified.  Files are opened by :func:`perscli.io.fitsreader.open_fits`:
``-`` (standard input), FIFOs, ``.fits.gz``, tile-compressed images,
``file.fits[SCI,2]`` (that HDU is the science image) and image sections
``file.fits[1][x1:x2,y1:y2]`` (LTV1/LTV2 shifted as CFITSIO does).
"""

from __future__ import annotations

import datetime as _dt
from dataclasses import dataclass, field

import numpy as np

from .. import PerscliError
from .fitsreader import HDU, FitsFile, open_fits

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

#: WFC3-IR raw and ima frames keep the detector's reference pixels, the outermost 5 rows and columns,
#: which are not sensitive to light; subarrays carry 5 of them on each side too, and calwf3 trims them
#: from flt files (WFC3 Instrument and Data Handbooks).
WFC3_IR_BORDER = 5
#: Image sizes of WFC3-IR raw/ima frames: the full frame and the 512, 256, 128 and 64 pixel subarrays,
#: each with its reference-pixel border (the flt sizes are 10 less: 1014, 512, 256, 128, 64).
WFC3_IR_RAW_SIZES = (1024, 522, 266, 138, 74)
#: LTV1/LTV2 of a WFC3-IR full frame whose header lacks them.  Detector pixels are those of a
#: full-frame flt (1014x1014, whose archive headers say LTV = 0); calwf3 trims the 5 reference pixels
#: from raw/ima to flt and moves LTV by 5, so a raw/ima full frame (1024x1024) has LTV = 5.  (These
#: values centre the subarrays of the shared files on the detector: SQ128SUB's science pixels at
#: 444-571, SQ256SUB's at 380-635.)
WFC3_IR_FULL_FRAME_LTV = {1024: 5.0, 1014: 0.0}

MJD_EPOCH = _dt.datetime(1858, 11, 17)
SECONDS_PER_DAY = 86400.0

#: MJD of any exposure perscli takes: 1858-11-17 to 2132-09-01 (perscli.scene.MJD_RANGE, written here
#: again so that reading a frame does not import the scene package).  A timing keyword outside it is
#: corrupt (EXPSTART = 1E300) or not an MJD (a Julian Date), and would silently put an exposure
#: centuries from the others: no persistence at all.
MJD_RANGE = (0.0, 100000.0)
#: gains perscli takes, in e-/DN: every infrared array and CCD is within it (HST, JWST, Roman: 1-3);
#: GAIN = 1E308 would turn any persistence into 0 DN, GAIN = 1E-300 into infinity
GAIN_RANGE = (1e-3, 1e3)
#: the longest exposure time perscli takes for a rate frame (s): 10^7 s, 116 days, above any single
#: exposure or stack; a larger EXPTIME is corrupt and overflows the charge (rate x EXPTIME)
MAX_EXPTIME = 1e7

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
    hdus : list of perscli.io.fitsreader.HDU
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
    source: FitsFile | None = field(default=None, repr=False)
    fluence_hdu: int | None = None
    image_shape: tuple | None = None
    section: tuple | None = None
    overrides: dict = field(default_factory=dict)

    @property
    def label(self) -> str:
        return "stdin" if self.name == "-" else self.name

    # -- headers ---------------------------------------------------------
    @property
    def header(self):
        """Header of the (first) science HDU."""
        return self.hdus[self.sci[0]].header

    def keyword(self, key, default=None):
        """A keyword from the science header, else from the primary header."""
        if key in self.overrides:
            return self.overrides[key]
        for hdr in (self.header, self.hdus[0].header if self.hdus else self.header):
            if key in hdr and hdr[key] not in (None, ""):
                return hdr[key]
        return default

    @property
    def is_wfc3_ir(self) -> bool:
        """An HST WFC3 infrared frame (INSTRUME = 'WFC3', DETECTOR = 'IR')."""
        return (str(self.keyword("INSTRUME", "")).strip().upper() == "WFC3"
                and str(self.keyword("DETECTOR", "")).strip().upper() == "IR")

    @property
    def stored_shape(self) -> tuple:
        """Shape of one image as stored, before any image section."""
        return tuple(self.hdus[self.sci[0]].shape[-2:])

    @property
    def reference_border(self) -> int:
        """Width of the border of reference pixels around the stored image (WFC3-IR raw/ima: 5; else 0)."""
        ny, nx = self.stored_shape
        if self.is_wfc3_ir and ny in WFC3_IR_RAW_SIZES and nx in WFC3_IR_RAW_SIZES:
            return WFC3_IR_BORDER
        return 0

    def _default_ltv(self, key: str):
        """LTV1/LTV2 of a WFC3-IR full frame whose header has none (see :data:`WFC3_IR_FULL_FRAME_LTV`)."""
        if not self.is_wfc3_ir:
            return None
        ny, nx = self.stored_shape
        if ny == nx and ny in WFC3_IR_FULL_FRAME_LTV:
            return WFC3_IR_FULL_FRAME_LTV[ny]
        return None

    def placement(self) -> Placement:
        """Where this frame's pixels lie on the detector (see :class:`Placement`).

        The offset comes from LTV1/LTV2 (detector pixel = image pixel - LTV,
        as HST and CFITSIO write them; a section ``file[x1:x2,y1:y2]`` moves
        them as CFITSIO does); a WFC3-IR full frame without them gets
        calwf3's values.  WFC3-IR raw/ima frames lose their 5-pixel border
        of reference pixels from the science area.
        """
        values, source = [], "LTV1/LTV2"
        for key in ("LTV2", "LTV1"):
            value = self.keyword(key)
            if value is None:
                value = self._default_ltv(key)
                source = "the WFC3-IR full-frame default" if value is not None else source
            if value is None:
                values = None
                break
            try:
                values.append(float(value))
            except (TypeError, ValueError):
                raise PerscliError(f"{self.label}: {key}={value!r} is not a number of pixels") from None
        offset = None if values is None else (-values[0], -values[1])
        scale = []
        for key in ("LTM2_2", "LTM1_1"):
            value = self.keyword(key, 1.0)
            try:
                scale.append(float(value))
            except (TypeError, ValueError):
                raise PerscliError(f"{self.label}: {key}={value!r} is not a number") from None
        ny, nx = self.shape
        box = [0, ny, 0, nx]
        border = self.reference_border
        if border:
            sny, snx = self.stored_shape
            rows, cols = self.section if self.section is not None else (slice(None), slice(None))
            for axis, (n_stored, sl) in enumerate(((sny, rows), (snx, cols))):
                first, _, step = sl.indices(n_stored)
                if step != 1:
                    raise PerscliError(f"{self.label}: a section with a step cannot be placed on the detector; "
                                       "take every pixel (file[x1:x2,y1:y2])")
                n = (ny, nx)[axis]
                box[2 * axis] = min(n, max(0, border - first))
                box[2 * axis + 1] = max(box[2 * axis], min(n, n_stored - border - first))
        if offset is None:
            source = "no LTV1/LTV2"
        return Placement(offset=offset, science=tuple(box), scale=tuple(scale), source=source)

    @property
    def zero_read_subtracted(self) -> bool:
        """True for a calwf3 ima whose reads already count from the zeroth read (ZOFFCORR = 'COMPLETE')."""
        return str(self.keyword("ZOFFCORR", "")).strip().upper() == "COMPLETE"

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
        ny, nx = self.hdus[self.sci[0]].shape[-2:]
        if self.section is not None:
            rows, cols = self.section
            return (len(range(*rows.indices(ny))), len(range(*cols.indices(nx))))
        return (ny, nx)

    # -- pixels ----------------------------------------------------------
    def _plane(self, k: int):
        """(HDU, plane index within it) of read ``k`` in time order."""
        if self.layout == "cube":
            return self.hdus[self.sci[0]], k
        return self.hdus[self.sci[k]], 0

    def _rows_of(self, hdu: HDU, plane: int, r0: int, r1: int, *, stream: bool = False,
                 scratch: bool = False) -> np.ndarray:
        """Rows of a plane through the image section, if any (``stream``: the unverified fast path)."""
        if self.section is not None:
            rows, cols = self.section
            start = rows.start or 0
            arr = hdu.read_rows(start + r0, start + r1, plane)
            return arr[:, cols]
        if stream:
            return hdu.stream_rows(r0, r1, plane, scratch=scratch)
        return hdu.read_rows(r0, r1, plane)

    def rows(self, k: int, r0: int, r1: int) -> np.ndarray:
        """Rows ``r0:r1`` of plane ``k`` (time order) in the file's units (checksums verified).

        Float data of a plain file are returned as stored (big-endian); other
        data are scaled to float64.
        """
        hdu, plane = self._plane(k)
        return self._rows_of(hdu, plane, r0, r1)

    @property
    def rows_are_raw(self) -> bool:
        """True when the science image of an image frame can be streamed as stored (see :meth:`raw_rows`)."""
        return self.layout == "image" and self.section is None and self.hdus[self.sci[0]].is_plain_float

    def raw_rows(self, r0: int, r1: int, *, scratch: bool = False) -> np.ndarray:
        """The fast path: rows of the science image as stored, NOT verified.

        The caller folds their DATASUM and hands it to :meth:`verify` at the end.
        With ``scratch`` they live in the thread's read buffer until its next read.
        """
        return self.hdus[self.sci[0]].stream_rows(r0, r1, scratch=scratch)

    def planes(self) -> list:
        """The science arrays in time order, in the file's units (native byte order)."""
        if self.layout == "stamps":
            raise PerscliError(f"{self.label}: its SCI holds only a frame's header: the pixels are kept around some "
                               "objects only (a study's final; perscli.study.differential.read_stamps reads them)")
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
            # checked where it is used: a gain outside any detector's would make the charge 0 or infinite
            # (GAIN = 1E308: no persistence at all), and a frame in electrons does not use it
            if not GAIN_RANGE[0] <= self.gain <= GAIN_RANGE[1]:
                raise PerscliError(
                    f"{self.label}: gain {self.gain:g} e-/DN is outside {GAIN_RANGE[0]:g} to {GAIN_RANGE[1]:g}, "
                    "the range of real detectors: the header's GAIN/CCDGAIN is corrupt; fix it or give --gain "
                    "E_PER_DN")
            factor *= self.gain
        if is_rate:
            if seconds is None:
                seconds = self.exptime
            if seconds is None:
                raise PerscliError(
                    f"{self.label}: BUNIT is {self.unit} (a rate) but the header has no EXPTIME or XPOSURE; "
                    "give --exptime SECONDS")
            # a rate frame's charge is rate x time: with 0 s it is 0 whatever the data (the frame would
            # silently receive or give no persistence)
            if not 0 < seconds <= MAX_EXPTIME:
                raise PerscliError(
                    f"{self.label}: BUNIT is {self.unit} (a rate) but the exposure time is {seconds:g} s: the "
                    f"charge is the rate times a time between 0 and {MAX_EXPTIME:g} s; fix EXPTIME (or "
                    "XPOSURE, EXPSTART/EXPEND) in the header")
            factor *= seconds
        return factor

    def fluence_rows(self, r0: int, r1: int, *, scratch: bool = False):
        """The accumulated charge of rows ``r0:r1``, as ``(array, scale)``.

        ``array * scale`` is the fluence in electrons.  For a float image the
        array is the file's bytes as stored (no conversion: the compiled
        kernel swaps bytes itself); for a ramp it is the last read minus the
        zeroth read (the last read alone in a calwf3 ima whose reads count
        from the zeroth read already: ZOFFCORR = 'COMPLETE'; in a rate ramp
        the last read times its SAMPTIME).
        """
        if self.fluence_hdu is not None:
            # a frame perscli rendered: its FLUENCE extension holds the collected charge in electrons
            hdu = self.hdus[self.fluence_hdu]
            return self._rows_of(hdu, 0, r0, r1, stream=self.fluence_is_raw, scratch=scratch), 1.0
        if not self.is_ramp:
            hdu = self.hdus[self.sci[0]]
            return self._rows_of(hdu, 0, r0, r1, stream=self.fluence_is_raw, scratch=scratch), self.electrons_per_unit()
        last = np.asarray(self.rows(self.nreads - 1, r0, r1), dtype=np.float64)
        if self.zero_read_subtracted:
            # calwf3's ZOFFCORR has taken the zeroth read off every read: the last one is the signal
            charge = last * self.read_times[-1] if UNITS[self.unit][1] else last
            return charge, self.electrons_per_unit(seconds=1.0)
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
        """True when :meth:`fluence_rows` hands out the stored bytes unverified: the caller folds their
        DATASUM and passes it to :meth:`verify` for :attr:`fluence_source`."""
        if self.section is not None:
            return False
        if self.fluence_hdu is not None:
            return self.hdus[self.fluence_hdu].is_plain_float
        return not self.is_ramp and self.hdus[self.sci[0]].is_plain_float

    @property
    def fluence_source(self) -> int:
        """The HDU that :meth:`fluence_rows` reads (FLUENCE if present, else the science image)."""
        return self.fluence_hdu if self.fluence_hdu is not None else self.sci[0]

    @property
    def provenance_hdu(self) -> int:
        """The HDU whose DATASUM stands for this frame in provenance (FLUENCE if used, the last read
        of a ramp, else the science HDU)."""
        if self.fluence_hdu is not None:
            return self.fluence_hdu
        return self.sci[-1] if self.layout == "wfc3-ramp" else self.sci[0]

    def verify(self, index: int, datasum: int | None = None) -> int:
        """Verify CHECKSUM/DATASUM of HDU ``index`` and return its DATASUM.

        Parameters
        ----------
        datasum : int, optional
            What the caller computed while streaming the HDU's stored bytes.
        """
        return self.hdus[index].verify(datasum)

    def datasum(self, index: int) -> int:
        """FITS DATASUM of HDU ``index`` as stored (verified against its header)."""
        return self.hdus[index].verify()

    def close(self):
        """Release the file."""
        if self.source is not None:
            self.source.close()

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()


@dataclass(frozen=True)
class Placement:
    """Where a frame's pixels lie on its detector.

    Attributes
    ----------
    offset : (float, float) or None
        ``(dy, dx)``: detector pixel = image pixel + offset (any indexing, as
        both are shifted alike), i.e. ``(-LTV2, -LTV1)``; None when the
        header does not say.
    science : (int, int, int, int)
        ``(y0, y1, x0, x1)``: the light-sensitive pixels in image
        coordinates (0-indexed, half-open), the whole image unless the frame
        has a reference-pixel border.
    scale : (float, float)
        LTM2_2, LTM1_1 (1: one image pixel per detector pixel).
    source : str
        Where the offset came from, for messages.
    """

    offset: tuple | None
    science: tuple
    scale: tuple = (1.0, 1.0)
    source: str = ""


def _native(array: np.ndarray) -> np.ndarray:
    return np.asarray(array, dtype=array.dtype.newbyteorder("="))


#: keywords of a header-only SCI HDU that declare the shape of the frame it describes (layout 'stamps')
STAMPS_SHAPE_KEYWORDS = ("FRAMENX", "FRAMENY")


def _science_hdus(name, hdus, selected=None):
    """Find the science arrays and the layout of a file (``selected``: the HDU of ``file[EXT]``)."""
    if selected is not None:
        hdu = hdus[selected]
        if hdu.is_image and not hdu.shape and all(k in hdu.header for k in STAMPS_SHAPE_KEYWORDS):
            return [selected], "stamps"
        if not hdu.is_image or not hdu.shape:
            raise PerscliError(f"{name}: the selected {hdu.label} holds no image")
        sci = [selected]
    else:
        sci = [h.index for h in hdus if h.name == "SCI" and h.is_image]
    if len(sci) > 1:
        by_ver = sorted(sci, key=lambda i: hdus[i].ver)
        if all("SAMPTIME" in hdus[i].header for i in by_ver):
            # WFC3 MULTIACCUM: SCI,1 is the last read, so time order is descending EXTVER
            return by_ver[::-1], "wfc3-ramp"
        raise PerscliError(
            f"{name}: {len(sci)} SCI extensions but no SAMPTIME keywords: not a MULTIACCUM ramp; "
            f"select one, e.g. '{name}[SCI,1]'")
    if sci and not hdus[sci[0]].shape and all(k in hdus[sci[0]].header for k in STAMPS_SHAPE_KEYWORDS):
        # the header of a frame whose pixels are kept only around some objects (a study's final): its shape
        # is declared, its pixels are in other HDUs
        return sci[:1], "stamps"
    if sci:
        index = sci[0]
    elif hdus[0].is_image and int(hdus[0].header.get("NAXIS", 0)) > 0:
        index = 0
    else:
        images = [h for h in hdus if h.is_image and h.shape and 0 not in h.shape]
        if len(images) == 1:
            # e.g. an fpacked file: the image is the first extension, whatever its name
            index = images[0].index
        else:
            raise PerscliError(f"{name}: no image data: expected a SCI extension or an image in the primary "
                               "HDU (select one with file.fits[EXT])")
    hdu = hdus[index]
    if not hdu.shape or 0 in hdu.shape:
        raise PerscliError(f"{name}: the {hdu.label} holds no data")
    ndim = len(hdu.shape)
    if ndim == 2:
        return [index], "image"
    if ndim == 3:
        return [index], "cube"
    raise PerscliError(f"{name}: the image has {ndim} axes; expected 2 (an image) or 3 (reads, y, x)")


def _shape_keyword(header, key: str, label: str) -> int:
    value = header[key]
    if isinstance(value, bool) or not isinstance(value, int) or value < 1:
        raise PerscliError(f"{label}: {key}={value!r} is not a number of pixels; the header is corrupt")
    return int(value)


def _read_times(name, hdus, sci, layout, nplanes):
    if layout == "wfc3-ramp":
        times = []
        for i in sci:
            value = hdus[i].header["SAMPTIME"]
            if isinstance(value, bool) or not isinstance(value, (int, float)):
                raise PerscliError(f"{name}: {hdus[i].label}: SAMPTIME={value!r} is not a number of seconds; "
                                   "the header is corrupt: fix it or re-copy the file")
            times.append(float(value))
        times = np.array(times)
    else:
        tables = [h for h in hdus if h.name in ("READTIMES", "READ_TIMES", "TIMES")
                  and h.kind == "table"]
        if not tables:
            raise PerscliError(
                f"{name}: a 3-D cube needs a READTIMES table (column TIME, seconds since the exposure start, "
                "one row per read)")
        match = [c for c in tables[0].colnames if c.upper() == "TIME"]
        if not match:
            raise PerscliError(f"{name}: the READTIMES table has no TIME column (seconds since the exposure start)")
        times = np.asarray(tables[0].read_column(match[0]), dtype=np.float64).reshape(-1)
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
    source = open_fits(name, stdin=stdin)
    label = source.label
    try:
        hdus = source.hdus
        sci, layout = _science_hdus(label, hdus, source.selected)
        hdrs = (hdus[sci[0]].header, hdus[0].header)
        nplanes = hdus[sci[0]].shape[0] if layout == "cube" else len(sci)
        read_times = _read_times(label, hdus, sci, layout, nplanes) if layout not in ("image", "stamps") else None
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
        fluence = [h.index for h in hdus if h.name == "FLUENCE" and h.is_image and h.shape]
        if source.selected is not None:
            fluence = []  # file[EXT] names the one image to use
        if fluence and hdus[fluence[0]].shape[-2:] != hdus[sci[0]].shape[-2:]:
            raise PerscliError(f"{label}: the FLUENCE extension's shape differs from the science image's")
        declared = None
        if layout == "stamps":
            h = hdus[sci[0]].header
            declared = (_shape_keyword(h, "FRAMENY", label), _shape_keyword(h, "FRAMENX", label))
        frame = Frame(name=name, hdus=hdus, sci=sci, layout=layout, unit=unit, gain=gain,
                      exptime=hdr_exptime, start=start, end=end, read_times=read_times,
                      timing_source=source_kw, source=source, fluence_hdu=fluence[0] if fluence else None,
                      section=source.section, image_shape=declared)
        if source.section is not None:
            # a cutout of the detector: its offset moves as CFITSIO moves LTV1/LTV2 for a section
            rows, cols = source.section
            for key, sl in (("LTV1", cols), ("LTV2", rows)):
                base = frame.keyword(key)
                if base is None:
                    base = frame._default_ltv(key)
                if base is None:
                    base = 0.0
                try:
                    frame.overrides[key] = float(base) - float(sl.start or 0)
                except (TypeError, ValueError):
                    raise PerscliError(f"{label}: {key}={base!r} is not a number") from None
        return frame
    except BaseException:
        source.close()
        raise


def _check_mjd(label: str, source: str, start: float, end: float) -> None:
    """Refuse timing keywords outside :data:`MJD_RANGE` (a corrupt value, or a Julian Date)."""
    for what, value in (("start", start), ("end", end)):
        if not MJD_RANGE[0] <= value <= MJD_RANGE[1]:
            # a Julian Date is the one common mistake worth naming; anything else is only corrupt
            jd = 2400000.5 + MJD_RANGE[0] <= value <= 2400000.5 + MJD_RANGE[1]
            hint = f" (a Julian Date? MJD = JD - 2400000.5 = {value - 2400000.5:.5f})" if jd else ""
            raise PerscliError(f"{label}: the exposure {what} MJD {value:g} ({source}) is not in "
                               f"[{MJD_RANGE[0]:g}, {MJD_RANGE[1]:g}] (1858 to 2132){hint}: the timing keywords "
                               "are corrupt; fix them")


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
    """Raise a clear error if ``frame`` has no start/end time, or one outside :data:`MJD_RANGE`.

    Raises
    ------
    PerscliError
        No timing keywords, or timing that cannot be an exposure's.
    """
    if frame.start is None or frame.end is None:
        raise PerscliError(f"{frame.label}: no exposure timing; {TIMING_HINT}")
    # checked here, where the timing is used, not when the frame is opened: --gap replaces it
    _check_mjd(frame.label, frame.timing_source, frame.start, frame.end)
