"""The corpus and the runner of tests/test_fuzz.py.

Corpus
    Small valid files as perscli's users have them (:func:`seeds`), each with
    CHECKSUM/DATASUM, built from fixed random seeds so that every run of the
    suite sees the same bytes, and the primitives that corrupt them
    (truncation, bit flips, card edits, garbage).  FITS structure is handled
    here by a small independent implementation (blocks, cards, sizes, and the
    checksum of the FITS Standard, Appendix J): :func:`resign` re-signs an
    edited file so that a reader must find the structural fault itself, not
    only a checksum mismatch.  ``test_fuzz.py`` checks it against astropy and
    CFITSIO.

Runner
    :class:`ForkServer` starts one fresh Python process that imports perscli
    once and forks a child per case.  The child runs ``perscli``'s console
    entry point as a process would (argv, real file descriptors 0/1/2), with a
    memory limit (RLIMIT_AS), a file-size limit and its own process group; the
    server kills the group at the deadline.  A case costs ~40 ms instead of a
    ~0.5 s interpreter start, and a hang, a crash (SIGBUS on a truncated
    memory map) or a memory blow stays in the child.  The server is started
    fresh, not forked from pytest, because a process that has run OpenMP
    code (perscli's kernels, TreeCorr) cannot fork safely.
"""

from __future__ import annotations

import gzip
import io
import os
import pickle
import select
import signal
import struct
import subprocess
import sys
import time
from dataclasses import dataclass, field
from functools import lru_cache

import numpy as np

BLOCK = 2880
CARD = 80
DAY = 86400.0
T0 = 60000.0                      # MJD of the earliest exposure
SHAPE = (32, 32)
GiB = 1 << 30


# =================================================================================================
# FITS structure, independent of perscli (and of astropy's reader)
# =================================================================================================

def card(key: str, value: str | None = None, comment: str = "") -> bytes:
    """An 80-byte card image.  ``value`` is the raw value token: numbers are right-justified to
    column 30, strings (starting with a quote) left-justified from column 11; None: a commentary card."""
    if value is None:
        text = f"{key:<8}{comment}"
    else:
        field_ = f"{value:<20}" if value.startswith("'") else f"{value:>20}"
        text = f"{key:<8}= {field_}" + (f" / {comment}" if comment else "")
    raw = text.encode("latin-1")
    if len(raw) > CARD:
        raise ValueError(f"card too long: {text!r}")
    return raw.ljust(CARD, b" ")


def quoted(text: str) -> str:
    """A FITS string token: quotes doubled, padded to at least 8 characters."""
    return "'" + text.replace("'", "''").ljust(8) + "'"


END_CARD = card("END", None)
BLANK_CARD = b" " * CARD


def padded(n: int) -> int:
    return -(-n // BLOCK) * BLOCK


@dataclass
class Hdu:
    """One HDU as stored: ``header`` (whole blocks, END and padding included) and ``data`` (whole blocks)."""

    header: bytearray
    data: bytes = b""

    # -- cards ---------------------------------------------------------------------------------
    def cards(self) -> list:
        return [bytes(self.header[i:i + CARD]) for i in range(0, len(self.header), CARD)]

    def set_cards(self, cards) -> None:
        body = b"".join(cards)
        self.header = bytearray(body.ljust(padded(max(len(body), 1)), b" "))

    def end_index(self) -> int:
        for i, c in enumerate(self.cards()):
            if c[:8] == b"END     ":
                return i
        raise ValueError("no END card")

    def index(self, key: str, nth: int = 0) -> int:
        k = key.encode().ljust(8)[:8]
        found = [i for i, c in enumerate(self.cards()) if c[:8] == k]
        if len(found) <= nth:
            raise KeyError(key)
        return found[nth]

    def value_text(self, key: str) -> str:
        c = self.cards()[self.index(key)].decode("latin-1")
        token = c[10:]
        if token.lstrip().startswith("'"):
            return token.strip().split("' ")[0].strip("'").strip() if "' " in token else token.strip().strip("'")
        return token.split("/")[0].strip()

    def int_value(self, key: str, default=None):
        try:
            return int(self.value_text(key))
        except KeyError:
            return default

    def replace(self, key: str, new: bytes, nth: int = 0) -> None:
        cards = self.cards()
        cards[self.index(key, nth)] = new
        self.set_cards(cards)

    def delete(self, key: str) -> None:
        cards = self.cards()
        del cards[self.index(key)]
        self.set_cards(cards)

    def insert(self, new_cards, before: str = "END") -> None:
        """Insert card images before ``before`` (default: before END), growing the header by blocks."""
        cards = self.cards()
        end = self.end_index()
        at = self.index(before) if before != "END" else end
        used = cards[:end + 1]
        used[at:at] = list(new_cards)
        self.set_cards(used)

    # -- sizes ---------------------------------------------------------------------------------
    def data_bytes(self) -> int:
        """Size of the data as declared (unpadded), for a valid header."""
        naxis = self.int_value("NAXIS")
        if not naxis:
            return 0
        n = 1
        for i in range(1, naxis + 1):
            n *= self.int_value(f"NAXIS{i}")
        bitpix = self.int_value("BITPIX")
        return abs(bitpix) // 8 * self.int_value("GCOUNT", 1) * (self.int_value("PCOUNT", 0) + n)

    def name(self) -> str:
        try:
            return self.value_text("EXTNAME")
        except KeyError:
            return "PRIMARY"


def split(raw: bytes) -> list:
    """The HDUs of a valid file."""
    hdus, pos = [], 0
    while pos < len(raw):
        end = pos
        while raw[end:end + 8] != b"END     ":
            end += CARD
            if end >= len(raw):
                raise ValueError("no END card")
        hstop = padded(end + CARD - pos) + pos
        hdu = Hdu(bytearray(raw[pos:hstop]))
        dstop = hstop + padded(hdu.data_bytes())
        hdu.data = bytes(raw[hstop:dstop])
        hdus.append(hdu)
        pos = dstop
    return hdus


def split_like(raw: bytes, like: list) -> list:
    """Cut ``raw`` (a same-length mutation of ``like``'s bytes) at ``like``'s HDU boundaries."""
    hdus, pos = [], 0
    for h in like:
        a, b = pos + len(h.header), pos + len(h.header) + len(h.data)
        hdus.append(Hdu(bytearray(raw[pos:a]), bytes(raw[a:b])))
        pos = b
    assert pos == len(raw), "split_like: not a same-length mutation"
    return hdus


def join(hdus, trailing: bytes = b"") -> bytes:
    return b"".join(bytes(h.header) + h.data for h in hdus) + trailing


@dataclass
class Span:
    hdu: int
    name: str
    header: tuple      # (start, stop) of the header blocks
    data: tuple        # (start, stop) of the data as declared (unpadded)
    padded_stop: int   # end of the data blocks


def layout(hdus) -> list:
    out, pos = [], 0
    for i, h in enumerate(hdus):
        hstart, dstart = pos, pos + len(h.header)
        n = h.data_bytes()
        out.append(Span(i, h.name() if i else "PRIMARY", (hstart, dstart), (dstart, dstart + n),
                        dstart + len(h.data)))
        pos = dstart + len(h.data)
    return out


# -- checksums (FITS Standard, Appendix J) ---------------------------------------------------------

def checksum32(data: bytes) -> int:
    """32-bit ones' complement sum of the big-endian words of ``data`` (a multiple of 4 bytes)."""
    if not data:
        return 0
    s = int(np.frombuffer(data, dtype=">u4").astype(np.uint64).sum(dtype=np.uint64))
    while s >> 32:
        s = (s & 0xFFFFFFFF) + (s >> 32)
    return s


def add32(a: int, b: int) -> int:
    s = a + b
    while s >> 32:
        s = (s & 0xFFFFFFFF) + (s >> 32)
    return s


_EXCLUDE = set(b":;<=>?@[\\]^_`")


def encode_checksum(value: int) -> str:
    """The 16-character ASCII encoding of a 32-bit value (Seaman, Pence & Rots)."""
    out = [0] * 16
    for i, byte in enumerate(value.to_bytes(4, "big")):
        q, r = divmod(byte, 4)
        ch = [q + r + 0x30, q + 0x30, q + 0x30, q + 0x30]
        changed = True
        while changed:
            changed = False
            for j in (0, 2):
                if ch[j] in _EXCLUDE or ch[j + 1] in _EXCLUDE:
                    ch[j] += 1
                    ch[j + 1] -= 1
                    changed = True
        for j in range(4):
            out[4 * j + i] = ch[j]
    text = bytes(out).decode("ascii")
    return text[-1] + text[:-1]


def resign_hdu(hdu: Hdu, checksum_at: int | None = None, datasum_at: int | None = None) -> None:
    """Recompute DATASUM and CHECKSUM of ``hdu`` in place (cards found by name unless indices are given)."""
    ck = checksum_at if checksum_at is not None else hdu.index("CHECKSUM")
    ds = datasum_at if datasum_at is not None else hdu.index("DATASUM")
    datasum = checksum32(hdu.data)
    cards = hdu.cards()
    cards[ds] = card("DATASUM", quoted(str(datasum)), "data unit checksum")
    cards[ck] = card("CHECKSUM", quoted("0" * 16), "HDU checksum")
    hdu.header = bytearray(b"".join(cards))
    total = add32(checksum32(bytes(hdu.header)), datasum)
    cards[ck] = card("CHECKSUM", quoted(encode_checksum(~total & 0xFFFFFFFF)), "HDU checksum")
    hdu.header = bytearray(b"".join(cards))


def resign(hdus, like=None) -> list:
    """Re-sign every HDU that has CHECKSUM/DATASUM cards; with ``like`` (the unmutated HDUs), the
    cards are rewritten where they are in ``like`` (so that a bit flip in them is undone too)."""
    for i, h in enumerate(hdus):
        if like is not None:
            try:
                resign_hdu(h, like[i].index("CHECKSUM"), like[i].index("DATASUM"))
            except KeyError:
                pass
            continue
        try:
            h.index("CHECKSUM"), h.index("DATASUM")
        except KeyError:
            continue
        resign_hdu(h)
    return hdus


# =================================================================================================
# Seeds: valid files as perscli's users have them
# =================================================================================================

def _astropy_bytes(hdul) -> bytes:
    buf = io.BytesIO()
    hdul.writeto(buf, checksum=True)
    return buf.getvalue()


def _normalized(raw: bytes) -> bytes:
    """Astropy's CHECKSUM/DATASUM cards carry the time of writing in their comments: rewrite them with
    fixed comments and re-sign, so that the same seed always gives the same bytes."""
    return join(resign(split(raw)))


def _frame_wcs_header():
    from astropy.io import fits

    h = fits.Header()
    h["CTYPE1"], h["CTYPE2"] = "RA---TAN", "DEC--TAN"
    h["CRVAL1"], h["CRVAL2"] = 10.0, -44.0
    h["CRPIX1"], h["CRPIX2"] = 16.5, 16.5
    c, s = np.cos(0.5), np.sin(0.5)
    scale = 0.11 / 3600.0
    h["CD1_1"], h["CD1_2"], h["CD2_1"], h["CD2_2"] = -c * scale, s * scale, s * scale, c * scale
    return h


#: (x, y) FITS pixels of the two objects on the frame seed
FRAME_OBJECTS = [(10.3, 11.2, 20.4, 0.35, 0.15, -0.1), (22.1, 20.6, 19.8, 0.30, -0.2, 0.05)]
#: ra/dec of two objects inside the render cutout RENDER_BOUNDS (Roman SCA 7 at ra 10, dec -44, pa 30,
#: pixels (1005.3, 2006.1) and (1011.7, 2010.4), from perscli.optics.Optics' WCS)
RENDER_OBJECTS = [(9.539532272511588, -44.04113205864226, "galaxy", 19.0, 0.4, 0.2, -0.1),
                  (9.53938852738555, -44.04133748678204, "star", 17.0, 0.0, 0.0, 0.0)]
RENDER_ARGS = ["--ra", "10", "--dec", "-44", "--pa", "30", "--mjd", "61541.97", "--filter", "J129", "--sca", "7",
               "--bounds", "1001", "1016", "2001", "2016", "--seed", "1"]
SKY = 200.0


def _timing(hdr, start, exptime):
    hdr["EXPTIME"] = (exptime, "[s] exposure time")
    hdr["EXPSTART"] = (start, "[MJD] exposure start")
    hdr["EXPEND"] = (start + exptime / DAY, "[MJD] exposure end")


def frame_seed() -> bytes:
    """A 2-D frame in electrons in a SCI extension: two objects on a sky, timing, WCS, a COMMENT."""
    from astropy.io import fits

    rng = np.random.default_rng(1101)
    yy, xx = np.mgrid[1:SHAPE[0] + 1, 1:SHAPE[1] + 1]
    img = np.full(SHAPE, SKY)
    for x, y, _mag, _hlr, _e1, _e2 in FRAME_OBJECTS:
        img += 6000.0 / (2 * np.pi * 2.2 ** 2) * np.exp(-((xx - x) ** 2 + (yy - y) ** 2) / (2 * 2.2 ** 2))
    img += rng.normal(0.0, 15.0, SHAPE)
    primary = fits.Header()
    primary["OBJECT"] = "fuzz frame"
    primary["COMMENT"] = "perscli fuzz corpus: a 2-D frame with a SCI extension"
    hdr = _frame_wcs_header()
    hdr["BUNIT"] = ("electron", "units of the data")
    hdr["GAIN"] = (1.0, "[e-/DN]")
    _timing(hdr, T0 + 1000.0 / DAY, 100.0)
    hdr["SKYRATE"] = (SKY / 100.0 - 0.015, "[e-/pixel/s] sky")
    hdr["SCA"], hdr["FILTER"], hdr["ZPT_AB"] = 7, "J129", 26.0
    hdr["COMMENT"] = "this card means nothing: a bit flipped in it changes no value"
    return _normalized(_astropy_bytes(fits.HDUList([fits.PrimaryHDU(header=primary),
                                                     fits.ImageHDU(img.astype(np.float32), hdr, name="SCI")])))


def partner_frame(start: float, fluence: bool) -> bytes:
    """A valid frame that pairs with the cases: the earlier exposure (bright) or the later one."""
    from astropy.io import fits

    rng = np.random.default_rng(1201 if fluence else 1202)
    data = 10 ** rng.uniform(0, 5.2, SHAPE) if fluence else np.full(SHAPE, 100.0)
    hdr = fits.Header()
    hdr["BUNIT"] = "electron"
    _timing(hdr, start, 100.0)
    return _normalized(_astropy_bytes(fits.HDUList([fits.PrimaryHDU(),
                                                     fits.ImageHDU(data.astype(np.float32), hdr, name="SCI")])))


def rendered_seed() -> bytes:
    """A frame like perscli render writes: SCI (DN), IDEAL and FLUENCE (electrons), MODEL table."""
    from astropy.io import fits

    rng = np.random.default_rng(1301)
    ideal = SKY + 10 ** rng.uniform(0, 4.5, SHAPE)
    fluence = ideal.copy()
    fluence.reshape(-1)[:6] = [0.0, 1.0, 4.99e4, 5.0e4, 5.01e4, 1.2e5]
    sci = np.round(fluence + rng.normal(0, 8.5, SHAPE))
    primary = fits.Header()
    primary["CREATOR"] = ("perscli 0.1.0", "software that made this file")
    primary["DETMODEL"] = ("roman", "detector model given; as resolved: MODEL table")
    primary["FILTER"], primary["SCA"] = "J129", 7
    primary["SEED"] = (1, "random seed")
    primary["HISTORY"] = "perscli 0.1.0: render sca=7 filter=J129 mjd=60000.0115740741 model=roman"
    hdus = [fits.PrimaryHDU(header=primary)]
    for name, data, unit in (("SCI", sci, "DN"), ("IDEAL", ideal, "electron"), ("FLUENCE", fluence, "electron")):
        hdr = _frame_wcs_header()
        hdr["BUNIT"] = (unit, "units of the data")
        hdr["GAIN"] = (1.0, "[e-/DN]")
        _timing(hdr, T0 + 1000.0 / DAY, 139.8)
        hdr["SCA"], hdr["FILTER"] = 7, "J129"
        hdr["ZPT_AB"] = (15.03962528980125, "AB mag of 1 photon/cm^2/s")
        hdr["SEED"] = 1
        if name == "SCI":
            hdr["SKYRATE"] = (1.43, "[e-/pixel/s] sky background used")
        hdus.append(fits.ImageHDU(data.astype(np.float32), hdr, name=name))
    rows = [("sky", True, "level", '"auto"', "e-/pixel/s"), ("poisson", True, "", "", ""),
            ("dark", True, "current", "0.015", "e-/pixel/s"), ("read_noise", True, "sigma", "8.5", "e-"),
            ("gain", True, "value", "1.0", "e-/DN")]
    cols = [fits.Column("EFFECT", "12A", array=[r[0] for r in rows]),
            fits.Column("ENABLED", "L", array=[r[1] for r in rows]),
            fits.Column("PARAM", "12A", array=[r[2] for r in rows]),
            fits.Column("VALUE", "113A", array=[r[3] for r in rows]),
            fits.Column("UNIT", "10A", array=[r[4] for r in rows])]
    model = fits.BinTableHDU.from_columns(cols, name="MODEL")
    model.header["COMMENT"] = "the detector model that made this frame, one row per parameter"
    hdus.append(model)
    return _normalized(_astropy_bytes(fits.HDUList(hdus)))


NSAMP = 4
SAMPTIMES = [0.0, 10.0, 20.0, 30.0]


def ramp_seed() -> bytes:
    """A WFC3-IR MULTIACCUM raw file: NSAMP reads as SCI (uint16 DN, BZERO 32768), ERR, DQ; SCI,1 is the
    last read and SCI,NSAMP the zeroth read; timing and CCDGAIN in the primary header."""
    from astropy.io import fits

    rng = np.random.default_rng(1401)
    rate = 10 ** rng.uniform(0, 2.8, SHAPE)                 # DN/s
    zeroth = rng.integers(9000, 11000, SHAPE).astype(np.float64)
    reads = [np.round(zeroth + rate * t) for t in SAMPTIMES]  # up to ~30000 DN
    primary = fits.Header()
    primary["TELESCOP"], primary["INSTRUME"], primary["DETECTOR"] = "HST", "WFC3", "IR"
    primary["NSAMP"] = (NSAMP, "number of MULTIACCUM samples")
    primary["SAMP_SEQ"] = "SPARS10"
    primary["CCDGAIN"] = (2.5, "[e-/DN]")
    _timing(primary, T0 + 1000.0 / DAY, SAMPTIMES[-1])
    hdus = [fits.PrimaryHDU(header=primary)]
    for ver in range(1, NSAMP + 1):
        k = NSAMP - ver
        hdr = fits.Header()
        hdr["BUNIT"] = "COUNTS"
        hdr["SAMPTIME"] = (SAMPTIMES[k], "[s] time of this read")
        hdus.append(fits.ImageHDU(reads[k].astype(np.uint16), hdr, name="SCI", ver=ver))
        hdus.append(fits.ImageHDU(np.full(SHAPE, 5.0 + ver, dtype=np.float32), name="ERR", ver=ver))
        hdus.append(fits.ImageHDU((rng.random(SHAPE) < 0.02).astype(np.int16) * 4, name="DQ", ver=ver))
    return _normalized(_astropy_bytes(fits.HDUList(hdus)))


def truth_seed() -> bytes:
    """A truth catalogue as perscli catalog writes it (TRUTH table): two objects on the frame seed (for
    measure), two inside the render cutout."""
    from astropy.io import fits
    from astropy.wcs import WCS

    wcs = WCS(_frame_wcs_header())
    rows = []
    for i, (x, y, mag, hlr, e1, e2) in enumerate(FRAME_OBJECTS, 1):
        ra, dec = wcs.all_pix2world([[x, y]], 1)[0]
        rows.append((i, float(ra), float(dec), "galaxy", mag, hlr, e1, e2))
    for i, (ra, dec, kind, mag, hlr, e1, e2) in enumerate(RENDER_OBJECTS, len(rows) + 1):
        rows.append((i, ra, dec, kind, mag, hlr, e1, e2))
    col = lambda k: [r[k] for r in rows]  # noqa: E731
    mags = np.array(col(4))
    cols = [fits.Column("id", "K", array=np.array(col(0), dtype=np.int64)),
            fits.Column("ra", "D", array=col(1), unit="deg"), fits.Column("dec", "D", array=col(2), unit="deg"),
            fits.Column("kind", "6A", array=col(3))]
    for name, offset in (("R062", 0.3), ("Z087", 0.2), ("Y106", 0.1), ("J129", 0.0), ("H158", -0.3),
                         ("F184", -0.4), ("K213", -0.5), ("W146", -0.15)):
        cols.append(fits.Column(f"mag_{name}", "D", array=mags + offset, unit="mag"))
    cols += [fits.Column("hlr", "D", array=col(5), unit="arcsec"), fits.Column("e1", "D", array=col(6)),
             fits.Column("e2", "D", array=col(7)), fits.Column("gaia_id", "K", array=np.full(len(rows), -1))]
    table = fits.BinTableHDU.from_columns(cols, name="TRUTH")
    primary = fits.Header()
    primary["CREATOR"] = "perscli 0.1.0"
    primary["RA"], primary["DEC"], primary["SIZE"], primary["SEED"] = 10.0, -44.0, 1.0, 7
    return _normalized(_astropy_bytes(fits.HDUList([fits.PrimaryHDU(header=primary), table])))


NSHAPES = 24


def shapes_seed() -> bytes:
    """A SHAPES table as perscli measure writes it: frames 0 and 1 of NSHAPES objects (frame 0 = 1 + De)."""
    from astropy.io import fits

    rng = np.random.default_rng(1501)
    n = NSHAPES
    ra, dec = 10.0 + rng.uniform(-0.2, 0.2, n), -44.0 + rng.uniform(-0.2, 0.2, n)
    g1, g2 = rng.normal(0, 0.27, n), rng.normal(0, 0.27, n)
    de1, de2 = rng.normal(0, 1e-4, n), rng.normal(0, 1e-4, n)
    x, y = rng.uniform(1, 4088, n), rng.uniform(1, 4088, n)
    both = lambda a, b: np.concatenate([a, b])  # noqa: E731
    cols = [fits.Column("id", "K", array=both(np.arange(1, n + 1), np.arange(1, n + 1))),
            fits.Column("frame", "I", array=both(np.zeros(n), np.ones(n)).astype(np.int16)),
            fits.Column("x", "D", array=both(x, x), unit="pix"), fits.Column("y", "D", array=both(y, y), unit="pix"),
            fits.Column("ra", "D", array=both(ra, ra), unit="deg"),
            fits.Column("dec", "D", array=both(dec, dec), unit="deg"),
            fits.Column("g1", "D", array=both(g1 + de1, g1)), fits.Column("g2", "D", array=both(g2 + de2, g2)),
            fits.Column("g1_err", "D", array=np.full(2 * n, 0.01)),
            fits.Column("g2_err", "D", array=np.full(2 * n, 0.01)),
            fits.Column("flags", "J", array=np.zeros(2 * n, dtype=np.int32))]
    table = fits.BinTableHDU.from_columns(cols, name="SHAPES")
    primary = fits.Header()
    primary["CREATOR"] = "perscli 0.1.0"
    primary["METHOD"], primary["NFRAMES"] = "exp", 2
    return _normalized(_astropy_bytes(fits.HDUList([fits.PrimaryHDU(header=primary), table])))


def psf_image() -> bytes:
    """The optical PSF for measure --psf: a Gaussian sampled 2x finer than the frame (PIXSCALE 0.055")."""
    from astropy.io import fits

    yy, xx = np.mgrid[-16:16, -16:16] + 0.5
    psf = np.exp(-(xx ** 2 + yy ** 2) / (2 * 2.6 ** 2))
    hdr = fits.Header()
    hdr["PIXSCALE"] = (0.055, "[arcsec] pixel scale")
    hdr["PSFPIXEL"] = (False, "the optical PSF: no pixel response")
    return _normalized(_astropy_bytes(fits.HDUList([fits.PrimaryHDU(psf / psf.sum(), hdr)])))


def big_pair() -> tuple:
    """(current, previous) frames of 256 x 256 pixels: an output (~512 kB) larger than a pipe's buffer."""
    from astropy.io import fits

    rng = np.random.default_rng(1601)
    out = []
    for start, data in ((T0 + 1000.0 / DAY, np.full((256, 256), 100.0)), (T0, 10 ** rng.uniform(0, 5, (256, 256)))):
        hdr = fits.Header()
        hdr["BUNIT"] = "electron"
        _timing(hdr, start, 100.0)
        out.append(_normalized(_astropy_bytes(fits.HDUList([fits.PrimaryHDU(),
                                                             fits.ImageHDU(data.astype(np.float32), hdr, "SCI")]))))
    return tuple(out)


def tile_compressed(seed: bytes) -> bytes:
    """``seed`` (a frame) with its SCI image tile-compressed losslessly (GZIP_2, no quantisation), as
    fpack would, signed like the other seeds."""
    from astropy.io import fits

    with fits.open(io.BytesIO(seed)) as hdul:
        primary = fits.PrimaryHDU(header=hdul[0].header.copy())
        for key in ("CHECKSUM", "DATASUM"):
            primary.header.remove(key, ignore_missing=True)
        hdr = hdul["SCI"].header.copy()
        for key in ("CHECKSUM", "DATASUM"):
            hdr.remove(key, ignore_missing=True)
        comp = fits.CompImageHDU(hdul["SCI"].data, hdr, name="SCI", compression_type="GZIP_2",
                                 quantize_level=0.0)
        raw = _astropy_bytes(fits.HDUList([primary, comp]))
    hdus = split(raw)
    for h in hdus:        # astropy also writes ZHECKSUM/ZDSUM with the time in their comments: drop them
        for key in ("ZHECKSUM", "ZDATASUM"):
            try:
                h.delete(key)
            except KeyError:
                pass
    # each tile is a gzip stream whose header holds the time of compression (MTIME): zero it
    comp = hdus[1]
    width, rows = comp.int_value("NAXIS1"), comp.int_value("NAXIS2")
    heap = comp.int_value("THEAP", width * rows)
    data = bytearray(comp.data)
    for row in range(rows):
        _count, offset = struct.unpack(">ii", bytes(data[row * width:row * width + 8]))
        at = heap + offset
        if data[at:at + 2] == b"\x1f\x8b":
            data[at + 4:at + 8] = bytes(4)
    comp.data = bytes(data)
    return join(resign(hdus))


def gzipped(data: bytes) -> bytes:
    return gzip.compress(data, compresslevel=6, mtime=0)


@lru_cache(maxsize=None)
def seeds() -> dict:
    """{name: bytes} of every valid file of the corpus (built once per process)."""
    current, previous = big_pair()
    return {
        "frame": frame_seed(),
        "rendered": rendered_seed(),
        "ramp": ramp_seed(),
        "truth": truth_seed(),
        "shapes": shapes_seed(),
        "earlier": partner_frame(T0, fluence=True),
        "later": partner_frame(T0 + 3000.0 / DAY, fluence=False),
        "psf": psf_image(),
        "big_current": current,
        "big_previous": previous,
    }


# =================================================================================================
# Mutations (pure functions: bytes -> bytes)
# =================================================================================================

def flip(raw: bytes, offset: int, mask: int) -> bytes:
    b = bytearray(raw)
    b[offset] ^= mask
    return bytes(b)


def flip_in_card(hdus, hdu: int, key: str, where: str, *, mask: int | None = None, nth: int = 0):
    """(offset in the file, mask) of a bit flip in card ``key`` of HDU ``hdu``: ``where`` is 'name'
    (the keyword's second letter: EXPEND -> EZPEND), 'value' (the first character of the value) or an
    int (a column of the card)."""
    spans = layout(hdus)
    idx = hdus[hdu].index(key, nth)
    text = hdus[hdu].cards()[idx]
    if where == "name":
        col, default = 1, 0x02
    elif where == "value":
        col = 10
        while text[col:col + 1] in (b" ", b"'"):
            col += 1
        default = 0x01
    else:
        col, default = int(where), 0x01
    return spans[hdu].header[0] + idx * CARD + col, (mask or default)


def edit(seed: bytes, hdu: int, *, replace=None, insert=None, delete=None, no_end=False, sign=True,
         swap=None) -> bytes:
    """``seed`` with cards of HDU ``hdu`` edited, then re-signed (``sign=False``: checksums left stale).

    replace: {KEY: card image}; insert: [card images] before END; delete: [KEY]; swap: (KEY1, KEY2)
    exchanges two cards; no_end: the END card is blanked (the header then runs into the data).
    """
    hdus = split(seed)
    h = hdus[hdu]
    for key, image in (replace or {}).items():
        h.replace(key, image)
    for key in (delete or []):
        h.delete(key)
    if insert:
        h.insert(insert)
    if swap:
        cards = h.cards()
        i, j = h.index(swap[0]), h.index(swap[1])
        cards[i], cards[j] = cards[j], cards[i]
        h.set_cards(cards)
    if sign:
        resign(hdus)
    if no_end:
        cards = h.cards()
        cards[h.end_index()] = BLANK_CARD
        h.set_cards(cards)
        # the header must still cover whole blocks: the reader now runs on into the data
    return join(hdus)


def continue_flood(n: int, chunk: str = "x" * 66) -> list:
    """A long-string keyword (NOTE) continued over ``n`` CONTINUE cards (valid FITS, ~80 n bytes)."""
    cards = [card("NOTE", "'" + chunk + "&'")]
    cards += [card("CONTINUE", None, "  '" + chunk + "&'")] * (n - 1)
    cards.append(card("CONTINUE", None, "  'end'"))
    return cards


def comment_flood(n: int) -> list:
    return [card("COMMENT", None, f"comment card number {i:06d} of a flood") for i in range(n)]


def resigned_like(mutated: bytes, seed: bytes) -> bytes:
    """A same-length mutation of ``seed`` with CHECKSUM/DATASUM recomputed (the file as it would be if it
    had been edited on purpose and re-signed): the reference for runs with the checksum check off."""
    like = split(seed)
    return join(resign(split_like(mutated, like), like=like))


def random_offsets(rng, start: int, stop: int, count: int) -> list:
    """``count`` (offset, mask) pairs drawn from ``rng`` within [start, stop)."""
    return [(int(rng.integers(start, stop)), 1 << int(rng.integers(0, 8))) for _ in range(count)]


PNG_HEADER = (b"\x89PNG\r\n\x1a\n" + struct.pack(">I", 13) + b"IHDR" + struct.pack(">IIBBBBB", 32, 32, 8, 0, 0, 0, 0)
              + b"\x00\x00\x00\x00")


# =================================================================================================
# Runner: a fork server that runs perscli as a process would
# =================================================================================================

#: modules the server imports before it forks (best effort: a missing one is only slower)
PRELOAD = ("perscli.cli.main", "perscli.io.fitsfile", "perscli.io.frames", "perscli.io.tables",
           "perscli.io.output", "perscli.detector.apply", "perscli.measure.shapes", "perscli.stats.correlate",
           "perscli.render.run", "perscli.render.exposure", "astropy.io.fits", "astropy.wcs", "fitsio", "galsim",
           "galsim.roman", "treecorr", "scipy.spatial")


def _send(fd: int, obj) -> None:
    data = pickle.dumps(obj)
    data = struct.pack(">Q", len(data)) + data
    while data:
        n = os.write(fd, data)
        data = data[n:]


def _recv(fd: int, deadline: float | None = None):
    def read(n):
        out = b""
        while len(out) < n:
            if deadline is not None:
                left = deadline - time.monotonic()
                if left <= 0 or not select.select([fd], [], [], left)[0]:
                    raise TimeoutError("no answer from the fuzz server")
            chunk = os.read(fd, n - len(out))
            if not chunk:
                raise EOFError
            out += chunk
        return out

    (n,) = struct.unpack(">Q", read(8))
    return pickle.loads(read(n))


def _child(req: dict, out_fd: int, err_fd: int, closing: list) -> None:
    """In the forked child: become a perscli process and exit with its status (never returns)."""
    code = 70
    try:
        for fd in closing:
            os.close(fd)
        os.setpgid(0, 0)
        os.chdir(req["cwd"])
        stdin_fd = os.open(req.get("stdin") or os.devnull, os.O_RDONLY)
        os.dup2(stdin_fd, 0)
        os.dup2(out_fd, 1)
        os.dup2(err_fd, 2)
        import resource

        resource.setrlimit(resource.RLIMIT_AS, (req["memory"], req["memory"]))
        resource.setrlimit(resource.RLIMIT_FSIZE, (req["fsize"], req["fsize"]))   # also caps a memfd
        signal.signal(signal.SIGXFSZ, signal.SIG_IGN)
        signal.signal(signal.SIGPIPE, signal.SIG_IGN)        # as the Python interpreter sets it
        sys.stdin = io.TextIOWrapper(io.BufferedReader(io.FileIO(0, "rb", closefd=False)), encoding="utf-8")
        sys.stdout = io.TextIOWrapper(io.BufferedWriter(io.FileIO(1, "wb", closefd=False)), encoding="utf-8")
        sys.stderr = io.TextIOWrapper(io.BufferedWriter(io.FileIO(2, "wb", closefd=False)), encoding="utf-8",
                                      errors="backslashreplace", line_buffering=True)
        sys.argv = ["perscli", *req["args"]]
        os.environ.update(req.get("env") or {})
        import traceback
        import warnings

        warnings.resetwarnings()               # the filters of a fresh interpreter
        for action, category in (("ignore", DeprecationWarning), ("ignore", PendingDeprecationWarning),
                                 ("ignore", ImportWarning), ("ignore", ResourceWarning)):
            warnings.simplefilter(action, category)
        try:
            from perscli.cli.main import main

            main()
            code = 0
        except SystemExit as exc:
            if exc.code is None:
                code = 0
            elif isinstance(exc.code, int):
                code = exc.code
            else:
                print(exc.code, file=sys.stderr)
                code = 1
        except BaseException:                  # what the interpreter does with an uncaught exception
            traceback.print_exc()
            code = 1
        for stream in (sys.stdout, sys.stderr):
            try:
                stream.flush()
            except Exception:
                pass
    except BaseException:
        try:
            import traceback

            os.write(2, ("fuzz server child failed:\n" + traceback.format_exc()).encode())
        except Exception:
            pass
    os._exit(code)


def _wait(pid: int, deadline: float):
    """(status, rusage, timed_out) of child ``pid``.  At ``deadline`` its process group is killed; after a
    normal exit too (anything it left running), while the unreaped child still reserves the group's id."""
    pidfd = os.pidfd_open(pid) if hasattr(os, "pidfd_open") else None
    timed_out = False
    try:
        while os.waitid(os.P_PID, pid, os.WEXITED | os.WNOHANG | os.WNOWAIT) is None:
            left = deadline - time.monotonic()
            if left <= 0:
                timed_out = True
                break
            if pidfd is not None:
                select.select([pidfd], [], [], min(left, 1.0))
            else:
                time.sleep(min(left, 0.005))
    finally:
        if pidfd is not None:
            os.close(pidfd)
    try:
        os.killpg(pid, signal.SIGKILL)
    except (ProcessLookupError, PermissionError):
        pass
    _, status, usage = os.wait4(pid, 0)
    return status, usage, timed_out


def _run_forked(req: dict, closing: list) -> dict:
    import tempfile

    with tempfile.TemporaryFile() as out, tempfile.TemporaryFile() as err:
        start = time.monotonic()
        pid = os.fork()
        if pid == 0:
            _child(req, out.fileno(), err.fileno(), closing)
        status, usage, timed_out = _wait(pid, start + req["timeout"])
        elapsed = time.monotonic() - start
        out.seek(0)
        err.seek(0)
        stdout = out.read(req.get("max_stdout", 1 << 20))
        stderr = err.read(1 << 16).decode("utf-8", "backslashreplace")
    if os.WIFSIGNALED(status):
        code = -os.WTERMSIG(status)
    else:
        code = os.WEXITSTATUS(status)
    return dict(code=code, stdout=stdout, stderr=stderr, elapsed=elapsed, timed_out=timed_out,
                maxrss_mb=usage.ru_maxrss / 1024.0, cpu=usage.ru_utime + usage.ru_stime)


def serve() -> None:
    """The server's main loop: requests on fd 0, answers on fd 1 (both moved off 0/1 first)."""
    rfd, wfd = os.dup(0), os.dup(1)
    null = os.open(os.devnull, os.O_RDWR)
    os.dup2(null, 0)
    os.dup2(null, 1)
    for name in PRELOAD:
        try:
            __import__(name)
        except Exception:
            pass
    _send(wfd, {"ready": os.getpid()})
    while True:
        try:
            req = _recv(rfd)
        except EOFError:
            return
        try:
            _send(wfd, _run_forked(req, [rfd, wfd]))
        except Exception as exc:  # noqa: BLE001 - report to the client
            _send(wfd, {"error": repr(exc)})


@dataclass
class ForkServer:
    """Client side of :func:`serve`."""

    memory: int = 3 * GiB
    fsize: int = 256 << 20
    proc: subprocess.Popen = field(default=None, init=False)

    def start(self) -> "ForkServer":
        env = dict(os.environ)
        here = os.path.dirname(os.path.abspath(__file__))
        env["PYTHONPATH"] = here + (os.pathsep + env["PYTHONPATH"] if env.get("PYTHONPATH") else "")
        env.setdefault("OMP_NUM_THREADS", "1")
        self.proc = subprocess.Popen([sys.executable, "-c", "import fuzz_corpus; fuzz_corpus.serve()"],
                                     stdin=subprocess.PIPE, stdout=subprocess.PIPE, env=env, cwd=here)
        hello = _recv(self.proc.stdout.fileno(), time.monotonic() + 120)
        assert "ready" in hello, hello
        return self

    def run(self, args, *, cwd: str, timeout: float, stdin: str | None = None, env=None) -> dict:
        _send(self.proc.stdin.fileno(), dict(args=[str(a) for a in args], cwd=str(cwd), timeout=timeout,
                                             stdin=stdin, env=env or {}, memory=self.memory, fsize=self.fsize))
        self.proc.stdin.flush()
        answer = _recv(self.proc.stdout.fileno(), time.monotonic() + timeout + 60)
        if "error" in answer:
            raise RuntimeError(f"fuzz server: {answer['error']}")
        return answer

    def stop(self) -> None:
        if self.proc is None:
            return
        try:
            self.proc.stdin.close()
            self.proc.wait(timeout=10)
        except Exception:
            self.proc.kill()
            self.proc.wait()
        self.proc.stdout.close()
        self.proc = None


def limit_memory(nbytes: int = 3 * GiB, fsize: int = 256 << 20):
    """A preexec_fn for subprocess: RLIMIT_AS, and RLIMIT_FSIZE with SIGXFSZ ignored (a write past it fails
    with EFBIG; the limit also caps an in-memory file such as a memfd that an endless input would grow)."""

    def apply():
        import resource

        resource.setrlimit(resource.RLIMIT_AS, (nbytes, nbytes))
        resource.setrlimit(resource.RLIMIT_FSIZE, (fsize, fsize))
        signal.signal(signal.SIGXFSZ, signal.SIG_IGN)

    return apply
