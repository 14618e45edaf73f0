"""Fuzz suite for every FITS input of perscli: corrupt, truncated, hostile and special inputs.

Every case is a small, deterministic file (tests/fuzz_corpus.py: seeds built from fixed random
seeds, all with CHECKSUM/DATASUM) and one command run on it as a process would run it:

    cur        perscli apply-persistence CASE earlier.fits --mode add -o OUT      (CASE is current)
    prev       perscli apply-persistence later.fits CASE --mode predict -o OUT    (CASE is earlier)
    measure    perscli measure CASE --catalog truth.fits --psf psf.fits -o OUT
    catalog    perscli measure frame.fits --catalog CASE --psf psf.fits -o OUT   (a truth catalogue)
    render     perscli render CASE ... --bounds (16 x 16 pixels) -o OUT          (a truth catalogue)
    correlate  perscli correlate CASE --frames 0 1 ... -o OUT                     (a SHAPES table)

Each case ends in one of two ways, and nothing else:

- exit status 1, stderr exactly one non-empty line naming the input, no output and no
  temporary file in the output folder; or
- exit status 0 and a correct result: the output equals the output of the uncorrupted input
  (``SAME``), or, with the checksum check off (NO_CHECKSUM), the outcome of the same bytes
  re-signed with valid checksums and checked (``CONSISTENT``).

Always: no traceback, no hang (a generous deadline per case, :data:`TIMEOUT`), no crash, no memory blow (RLIMIT_AS 3 GiB),
inputs byte-for-byte unchanged.  Which of the two endings a case may have (``expect``):

ERROR          must fail: truncations, bit flips under CHECKSUM/DATASUM in what the command reads,
               invalid structure or scaling, garbage, non-FITS and special files.
SAME           must work and give the uncorrupted result (.gz, tile-compressed, [EXT], FIFO).
ERROR_OR_SAME  either (a flip or a cut in an HDU the command need not read, a CONTINUE flood, a
               duplicated keyword, BLANK on float data).
CONSISTENT     with NO_CHECKSUM: the same exit status and output as the re-signed file.

"What the command reads" (:func:`needed`): every HDU of CURRENT (apply-persistence copies them all
into its output), of a measured frame and of a table; of an earlier exposure, the primary header
plus, for a rendered frame, SCI's header and FLUENCE, for a WFC3 ramp, the SCI headers and the data
of SCI,1 and SCI,NSAMP (fluence = last minus zeroth read).  Issue 8 asks to verify "every HDU that is
read"; a fault in an HDU that is not read may pass only when the output is unchanged.

Structural and scaling edits are re-signed (fuzz_corpus.resign) so that they must be caught by the
structure checks, not by a checksum mismatch.  Outputs of exit 0 must open in astropy with valid
checksums.  Peak memory of a run must stay under MAX_RSS_MB; runs in the fork server also have
RLIMIT_FSIZE 256 MB, which caps an in-memory copy (memfd) of an endless stream.

Cases marked ``fits_layer`` (``pytest -m fits_layer``) need behaviour of the new FITS layer (issue
8: CHECKSUM/DATASUM of every HDU read, structure and scaling checks, trailing garbage, linear
CONTINUE parsing, FIFOs and devices, gzip, tile compression, [EXT]); they are NOT xfailed: they
fail until the FITS layer does it.  A failure message starts with its kind: [hang], [crash],
[traceback], [memory], [slow] (CPU time of a flood), [exit N], [accepted] (exit 0 where an error was due), [wrong result],
[refused] (exit 1 on a valid input), [inconsistent] (NO_CHECKSUM changes more than the check),
[message] (not exactly one line naming the file), [partial output] (output or temporary file left,
in the output folder or next to the input), [input modified], [bad output].

Set PERSCLI_FUZZ_LOG=file.jsonl to append one JSON line per case (id, kind, exit status, time).

Runs: cases go through fuzz_corpus.ForkServer (a fresh interpreter that imports perscli once and
forks a child per case: ~20 ms a case); the standard-input and broken-pipe cases run the
``perscli`` console script in real subprocesses.
"""

from __future__ import annotations

import hashlib
import json
import os
import shutil
import subprocess
import sys
import threading
import time
import warnings
from dataclasses import dataclass
from functools import lru_cache
from pathlib import Path
from typing import Callable

import numpy as np
import pytest
from astropy.io import fits

import fuzz_corpus as fc
from fuzz_corpus import card, quoted

#: the option that turns the CHECKSUM/DATASUM check of inputs off; a group option, so that it
#: reaches every command (measure and correlate have no option of their own)
NO_CHECKSUM = "--no-checksum"

#: seconds after which a run is killed and reported as a hang: a deadline for a hung run, not a measure of
#: speed (a case takes ~0.02 s, a render ~1 s, a FIFO without a writer perscli's own 10 s wait), so generous
#: that a loaded machine never reaches it
TIMEOUT = 300.0
#: CPU seconds a 100,000-card header may take: linear parsing takes ~1 s, quadratic parsing minutes.  CPU time,
#: not wall-clock time: what a loaded machine's other processes take does not count
FLOOD_CPU = 60.0
MEMORY = 3 * fc.GiB     # RLIMIT_AS of every run
MAX_RSS_MB = 1500       # peak resident memory of a run (perscli and its imports take ~100-300 MB)

ERROR, SAME, ERROR_OR_SAME, CONSISTENT = "error", "same", "error-or-same", "consistent"

with warnings.catch_warnings():            # an unregistered marker warns once, here
    warnings.simplefilter("ignore")
    FITS_LAYER = pytest.mark.fits_layer

PERSCLI = shutil.which("perscli", path=os.path.dirname(sys.executable)) or shutil.which("perscli")
IS_ROOT = hasattr(os, "geteuid") and os.geteuid() == 0

CORRELATE_ARGS = ["--frames", "0", "1", "--npatch", "2", "--nbins", "2", "--nboot", "2", "--min-sep", "1",
                  "--max-sep", "20", "--seed", "3"]


def command_args(command: str, case: str, out: str, inputs: dict) -> list:
    """The perscli arguments of ``command`` on ``case`` (``inputs``: the valid partner files)."""
    return {
        "cur": ["apply-persistence", case, inputs["earlier"], "--mode", "add"],
        "prev": ["apply-persistence", inputs["later"], case, "--mode", "predict"],
        "measure": ["measure", case, "--catalog", inputs["truth"], "--psf", inputs["psf"], "--stamp", "16"],
        "catalog": ["measure", inputs["frame"], "--catalog", case, "--psf", inputs["psf"], "--stamp", "16"],
        "render": ["render", case, *fc.RENDER_ARGS],
        "correlate": ["correlate", case, *CORRELATE_ARGS],
    }[command] + ["-o", out]


# =================================================================================================
# The cases
# =================================================================================================

@dataclass(frozen=True)
class Case:
    seed: str                          # the valid file the case derives from
    command: str                       # a key of command_args
    name: str                          # what was done to it
    make: Callable | None              # () -> bytes of the case file (None: a special file)
    expect: str
    checksum: bool = True              # False: run with NO_CHECKSUM
    special: str | None = None         # dir, devnull, devzero, fifo, fifo-writer, noperm, loop, ext:<selector>
    new: bool = False                  # needs the new FITS layer (marked fits_layer)
    timeout: float = TIMEOUT
    max_cpu: float | None = None       # CPU seconds the run may take (complexity, not speed: the floods)
    suffix: str = ".fits"
    compare: str = "all"               # all HDUs, or 'sci' (the SCI image only)
    base: Callable | None = None       # () -> the unmutated bytes (default: the seed), for CONSISTENT

    @property
    def id(self) -> str:
        return f"{self.seed}-{self.command}-{self.name}" + ("" if self.checksum else "-nochecksum")


def seed_bytes(name: str) -> bytes:
    return fc.seeds()[name]


@lru_cache(maxsize=None)
def hdus_of(name: str):
    """The HDUs of a seed (shared: never modify them)."""
    return tuple(fc.split(seed_bytes(name)))


@lru_cache(maxsize=None)
def spans_of(name: str):
    return tuple(fc.layout(hdus_of(name)))


#: HDUs (and parts) that a command reads; a fault elsewhere may pass when the result is unchanged
def needed(seed: str, command: str, hdu: int, part: str) -> bool:
    if command == "prev" and seed == "rendered":          # timing from SCI's header, fluence from FLUENCE
        return hdu == 0 or (hdu == 1 and part == "header") or hdu == 3
    if command == "prev" and seed == "ramp":              # last minus zeroth read: SCI,1 and SCI,NSAMP
        name = hdus_of("ramp")[hdu].name()
        return hdu == 0 or (name == "SCI" and (part == "header" or hdu in (1, 1 + 3 * (fc.NSAMP - 1))))
    return True


def needed_end(seed: str, command: str) -> int:
    """Offset after the last byte the command needs."""
    end = 0
    for sp in spans_of(seed):
        if needed(seed, command, sp.hdu, "header"):
            end = max(end, sp.header[1])
        if needed(seed, command, sp.hdu, "data") and sp.padded_stop > sp.data[0]:
            end = max(end, sp.padded_stop)
    return end


def _mutation(seed: str, fn):
    return lambda: fn(seed_bytes(seed))


def _flip_at(seed: str, offset: int, mask: int):
    return lambda: fc.flip(seed_bytes(seed), offset, mask)


def _hdu_label(seed: str, i: int) -> str:
    h = hdus_of(seed)[i]
    ver = h.int_value("EXTVER")
    return f"h{i}:{h.name()}" + (f",{ver}" if ver and seed == "ramp" else "")


# -- truncation -------------------------------------------------------------------------------------

def truncations(seed: str, commands, hdus=None) -> list:
    raw_len = len(seed_bytes(seed))
    spans = spans_of(seed)
    points = [("primary-only", fc.BLOCK)] if len(spans) > 1 else []
    for sp in spans:
        if hdus is not None and sp.hdu not in hdus:
            continue
        label = _hdu_label(seed, sp.hdu)
        ncards = hdus_of(seed)[sp.hdu].end_index() + 1
        points.append((f"{label}-mid-header", sp.header[0] + (ncards // 2) * fc.CARD + 37))
        if sp.data[1] > sp.data[0]:
            points.append((f"{label}-no-data", sp.header[1]))                  # at a block boundary
            points.append((f"{label}-mid-data", (sp.data[0] + sp.data[1]) // 2 + 3))
    last = spans[-1]
    if last.padded_stop > last.data[1]:
        points.append(("no-final-padding", last.data[1]))
    points.append(("last-byte", raw_len - 1))
    cases = []
    for name, cut in points:
        for command in commands:
            expect = ERROR if cut < needed_end(seed, command) else ERROR_OR_SAME
            cases.append(Case(seed, command, f"trunc-{name}@{cut}", _mutation(seed, lambda r, c=cut: r[:c]), expect))
    return cases


# -- bit flips ----------------------------------------------------------------------------------------

def header_flips(seed: str, targets: dict, rng_seed: int, randoms: int = 1) -> list:
    """[(label, hdu, part, offset, mask)] for cards named in ``targets`` {hdu: [(KEY, where)]}, the header
    padding after END, and ``randoms`` seeded random flips in each listed HDU's header."""
    hdus, spans = hdus_of(seed), spans_of(seed)
    rng = np.random.default_rng(rng_seed)
    out = []
    for i, items in targets.items():
        label = _hdu_label(seed, i)
        for key, where in items:
            if key == "padding":
                end = hdus[i].end_index()
                off = spans[i].header[0] + (end + 1) * fc.CARD + 5
                assert off < spans[i].header[1], (seed, i)
                out.append((f"{label}-padding-after-END", i, "header", off, 0x01))
                continue
            off, mask = fc.flip_in_card(hdus, i, key, where)
            what = {"name": "name", "value": "value"}.get(where, f"col{where}")
            out.append((f"{label}-{key}-{what}", i, "header", off, mask))
        for off, mask in fc.random_offsets(rng, spans[i].header[0], spans[i].header[1], randoms):
            out.append((f"{label}-random@{off}^{mask:#04x}", i, "header", off, mask))
    return out


def data_flips(seed: str, targets: dict, rng_seed: int, randoms: int = 0) -> list:
    """[(label, hdu, part, offset, mask)]: ``targets`` {hdu: [where]} with where 'first', 'middle', 'last',
    'padding', ('row', n, column) or ('offset', n); plus ``randoms`` seeded flips in each HDU's data."""
    hdus, spans = hdus_of(seed), spans_of(seed)
    rng = np.random.default_rng(rng_seed)
    out = []
    for i, items in targets.items():
        sp, h = spans[i], hdus[i]
        label = _hdu_label(seed, i)
        item = abs(h.int_value("BITPIX")) // 8
        for where in items:
            if where == "first":
                off, mask = sp.data[0], 0x40
            elif where == "middle":
                n = (sp.data[1] - sp.data[0]) // item
                off, mask = sp.data[0] + (n // 2) * item, 0x10
            elif where == "last":
                off, mask = sp.data[1] - 1, 0x01
            elif where == "padding":
                off, mask = sp.data[1] + 1, 0x01
                assert off < sp.padded_stop
            elif where[0] == "row":
                _, row, column = where
                off, mask = sp.data[0] + row * h.int_value("NAXIS1") + column_offset(h, column), 0x01
                where = f"row{row}.{column}"
            else:
                raise ValueError(where)
            out.append((f"{label}-data-{where}", i, "data", off, mask))
        for off, mask in fc.random_offsets(rng, sp.data[0], sp.data[1], randoms):
            out.append((f"{label}-data-random@{off}^{mask:#04x}", i, "data", off, mask))
    return out


_TFORM_SIZE = {"L": 1, "X": 1, "B": 1, "I": 2, "J": 4, "K": 8, "A": 1, "E": 4, "D": 8, "C": 8, "M": 16,
               "P": 8, "Q": 16}


def column_offset(h: fc.Hdu, column: str) -> int:
    """Byte offset of ``column`` in a row of binary table ``h``."""
    off = 0
    for k in range(1, h.int_value("TFIELDS") + 1):
        form = h.value_text(f"TFORM{k}")
        digits = "".join(ch for ch in form if ch.isdigit())
        code = form.lstrip("0123456789")[0]
        if h.value_text(f"TTYPE{k}").lower() == column.lower():
            return off
        off += (int(digits) if digits else 1) * _TFORM_SIZE[code]
    raise KeyError(column)


def flip_cases(seed: str, flips, commands, nochecksum_commands=(), nochecksum_labels=None) -> list:
    """A checksummed case per flip and command (ERROR where the command reads the flipped part), and a
    NO_CHECKSUM case (CONSISTENT) per flip whose label is in ``nochecksum_labels`` (None: all)."""
    missing = set(nochecksum_labels or ()) - {f[0] for f in flips}
    assert not missing, f"no such flips: {missing}"
    cases = []
    for label, hdu, part, off, mask in flips:
        make = _flip_at(seed, off, mask)
        for command in commands:
            expect = ERROR if needed(seed, command, hdu, part) else ERROR_OR_SAME
            cases.append(Case(seed, command, f"flip-{label}", make, expect, new=True))
        if nochecksum_labels is None or label in nochecksum_labels:
            for command in nochecksum_commands:
                cases.append(Case(seed, command, f"flip-{label}", make, CONSISTENT, checksum=False, new=True))
    return cases


# -- edited cards (re-signed: the reader must see the fault itself) --------------------------------------

def c(key, value, comment=""):
    return card(key, value, comment)


IMAGE_STRUCTURE = [
    ("BITPIX=7", dict(replace={"BITPIX": c("BITPIX", "7")})),
    ("BITPIX=-16", dict(replace={"BITPIX": c("BITPIX", "-16")})),
    ("BITPIX='abc'", dict(replace={"BITPIX": c("BITPIX", quoted("abc"))})),
    ("NAXIS=-1", dict(replace={"NAXIS": c("NAXIS", "-1")})),
    ("NAXIS=1000", dict(replace={"NAXIS": c("NAXIS", "1000")})),
    ("NAXIS1=-32", dict(replace={"NAXIS1": c("NAXIS1", "-32")})),
    ("NAXIS1=10**12", dict(replace={"NAXIS1": c("NAXIS1", str(10 ** 12))})),
    ("NAXIS2=10**12", dict(replace={"NAXIS2": c("NAXIS2", str(10 ** 12))})),
    ("NAXIS1=NAXIS2=40000", dict(replace={"NAXIS1": c("NAXIS1", "40000"), "NAXIS2": c("NAXIS2", "40000")})),
    ("NAXIS1=NAXIS2=3037000500", dict(replace={"NAXIS1": c("NAXIS1", "3037000500"),
                                               "NAXIS2": c("NAXIS2", "3037000500")})),   # product > 2**63 bytes
    ("NAXIS1='abc'", dict(replace={"NAXIS1": c("NAXIS1", quoted("abc"))})),
    ("NAXIS2-missing", dict(delete=["NAXIS2"])),
    ("no-END", dict(no_end=True)),
    ("PCOUNT=-1", dict(replace={"PCOUNT": c("PCOUNT", "-1")})),
    ("PCOUNT=10**15", dict(replace={"PCOUNT": c("PCOUNT", str(10 ** 15))})),
    ("GCOUNT=0", dict(replace={"GCOUNT": c("GCOUNT", "0")})),
    ("GCOUNT=2", dict(replace={"GCOUNT": c("GCOUNT", "2")})),
    ("XTENSION='FOOBAR'", dict(replace={"XTENSION": c("XTENSION", quoted("FOOBAR"))})),
    ("XTENSION='BINTABLE'", dict(replace={"XTENSION": c("XTENSION", quoted("BINTABLE"))})),
]
#: legal or tolerable oddities: a reader may refuse them or read the file as it was
IMAGE_ODDITIES = [
    ("NAXIS2-duplicated=16", dict(insert=[c("NAXIS2", "16")])),
    ("BITPIX-NAXIS-swapped", dict(swap=("BITPIX", "NAXIS"))),
]
PRIMARY_STRUCTURE = [
    ("SIMPLE=F", dict(replace={"SIMPLE": c("SIMPLE", "F")})),
    ("SIMPLE-missing", dict(replace={"SIMPLE": c("XIMPLE", "T")})),
    ("BITPIX=7", dict(replace={"BITPIX": c("BITPIX", "7")})),
    ("NAXIS=1000", dict(replace={"NAXIS": c("NAXIS", "1000")})),
]
SCALING = [
    ("BSCALE=0", dict(set={"BSCALE": "0"})),
    ("BSCALE=NaN", dict(set={"BSCALE": "NaN"})),
    ("BSCALE='abc'", dict(set={"BSCALE": quoted("abc")})),
    ("BZERO=NaN", dict(set={"BZERO": "NaN"})),
    ("BZERO=1E999", dict(set={"BZERO": "1E999"})),
]
TABLE_STRUCTURE = [
    ("NAXIS1=row-1", lambda h: dict(replace={"NAXIS1": c("NAXIS1", str(h.int_value("NAXIS1") - 1))})),
    ("NAXIS2=10**12", lambda h: dict(replace={"NAXIS2": c("NAXIS2", str(10 ** 12))})),
    ("NAXIS2=-1", lambda h: dict(replace={"NAXIS2": c("NAXIS2", "-1")})),
    ("TFIELDS=1000", lambda h: dict(replace={"TFIELDS": c("TFIELDS", "1000")})),
    ("TFIELDS=-1", lambda h: dict(replace={"TFIELDS": c("TFIELDS", "-1")})),
    ("TFORM2='Q9Z'", lambda h: dict(replace={"TFORM2": c("TFORM2", quoted("Q9Z"))})),
    ("TFORM2='1000000000D'", lambda h: dict(replace={"TFORM2": c("TFORM2", quoted("1000000000D"))})),
    ("PCOUNT=10**12", lambda h: dict(replace={"PCOUNT": c("PCOUNT", str(10 ** 12))})),
    ("GCOUNT=2", lambda h: dict(replace={"GCOUNT": c("GCOUNT", "2")})),
    ("XTENSION='IMAGE'", lambda h: dict(replace={"XTENSION": c("XTENSION", quoted("IMAGE"))})),
    ("no-END", lambda h: dict(no_end=True)),
]


def edited(seed: str, hdu: int, spec: dict):
    """A make() for ``seed`` with HDU ``hdu`` edited by ``spec`` (fc.edit's keywords; 'set' replaces a card
    when present, else inserts it) and re-signed."""
    spec = dict(spec)
    setting = spec.pop("set", None)

    def make():
        raw = seed_bytes(seed)
        if setting:
            h = fc.split(raw)[hdu]
            replace, insert = dict(spec.get("replace", {})), list(spec.get("insert", []))
            for key, token in setting.items():
                try:
                    h.index(key)
                    replace[key] = c(key, token)
                except KeyError:
                    insert.append(c(key, token))
            return fc.edit(raw, hdu, **{**spec, "replace": replace, "insert": insert})
        return fc.edit(raw, hdu, **spec)

    return make


def edit_cases(seed: str, hdu: int, specs, commands, expect=ERROR, prefix="struct", new=True) -> list:
    label = _hdu_label(seed, hdu)
    return [Case(seed, command, f"{prefix}-{label}-{name}", edited(seed, hdu, spec), expect, new=new)
            for name, spec in specs for command in commands]


def table_structure_cases(seed: str, commands) -> list:
    h = hdus_of(seed)[1]
    return edit_cases(seed, 1, [(name, fn(h)) for name, fn in TABLE_STRUCTURE], commands)


# -- floods, garbage, foreign files -----------------------------------------------------------------------

def flood_cases(seed: str, hdu: int, commands) -> list:
    label = _hdu_label(seed, hdu)
    out = []
    for name, cards in (("CONTINUE-flood-100000", lambda: fc.continue_flood(100_000)),
                        ("COMMENT-flood-100000", lambda: fc.comment_flood(100_000))):
        make = (lambda cards=cards: fc.edit(seed_bytes(seed), hdu, insert=cards()))
        for command in commands:
            out.append(Case(seed, command, f"{name}-{label}", make, ERROR_OR_SAME, max_cpu=FLOOD_CPU, new=True))
    return out


def garbage_cases(seed: str, commands) -> list:
    rng = np.random.default_rng(1701)
    block = rng.integers(0, 256, fc.BLOCK, dtype=np.uint8).tobytes()
    tails = [("trailing-text", lambda r: r + b"garbage after the last HDU\n" * 4),
             ("trailing-random-block", lambda r: r + block),
             ("concatenated-twice", lambda r: r + r)]
    return [Case(seed, command, name, _mutation(seed, fn), ERROR, new=True) for name, fn in tails
            for command in commands]


def foreign_cases(seed: str, commands) -> list:
    rng = np.random.default_rng(1801)
    noise = rng.integers(0, 256, 2 * fc.BLOCK, dtype=np.uint8).tobytes()
    gz = fc.gzipped(seed_bytes(seed))
    items = [
        ("empty", lambda: b"", ".fits", False),
        ("text", lambda: b"This is not a FITS file.\n" * 40, ".fits", False),
        ("png-header", lambda: fc.PNG_HEADER + noise[:500], ".fits", False),
        ("random-bytes", lambda: noise, ".fits", False),
        ("SIMPLE-then-random", lambda: fc.card("SIMPLE", "T") + noise, ".fits", False),
        ("gzip-of-garbage", lambda: fc.gzipped(noise), ".fits.gz", True),
        ("gz-truncated", lambda: gz[: len(gz) // 2], ".fits.gz", True),
        ("gz-flipped", lambda: fc.flip(gz, len(gz) // 2, 0x10), ".fits.gz", True),
    ]
    return [Case(seed, command, name, make, ERROR, suffix=suffix, new=new) for name, make, suffix, new in items
            for command in commands]


def compressed_cases(seed: str, commands, *, fpack=True) -> list:
    """Valid .fits.gz and tile-compressed inputs give the uncompressed result; corrupt ones an error."""
    out = []
    for command in commands:
        out.append(Case(seed, command, "gz-valid", lambda: fc.gzipped(seed_bytes(seed)), SAME, suffix=".fits.gz",
                        new=True))
    if not fpack:
        return out
    tiled = lambda: fc.tile_compressed(seed_bytes(seed))  # noqa: E731

    def heap_flip():
        raw = tiled()
        sp = fc.layout(fc.split(raw))[1]
        return fc.flip(raw, (sp.data[0] + sp.data[1]) // 2, 0x08)

    def cut():
        raw = tiled()
        sp = fc.layout(fc.split(raw))[1]
        return raw[:(sp.data[0] + sp.data[1]) // 2]

    for command in commands:
        out.append(Case(seed, command, "fpack-valid", tiled, SAME, new=True))
        out.append(Case(seed, command, "fpack-heap-flipped", heap_flip, ERROR, new=True))
        out.append(Case(seed, command, "fpack-truncated", cut, ERROR, new=True))
        out.append(Case(seed, command, "fpack-heap-flipped", heap_flip, CONSISTENT, checksum=False, new=True,
                        base=tiled))
    return out


def special_cases() -> list:
    frame = lambda: seed_bytes("frame")  # noqa: E731
    out = [Case("frame", "cur", "ext-[SCI]", frame, SAME, special="ext:[SCI]", compare="sci", new=True),
           Case("frame", "cur", "ext-[1]", frame, SAME, special="ext:[1]", compare="sci", new=True),
           Case("frame", "cur", "ext-[NOPE]", frame, ERROR, special="ext:[NOPE]", new=True),
           Case("frame", "prev", "ext-[7]", frame, ERROR, special="ext:[7]", new=True),
           Case("frame", "cur", "ext-[SCI]-of-a-flipped-file", lambda: fc.flip(seed_bytes("frame"),
                spans_of("frame")[1].data[0] + 8, 0x20), ERROR, special="ext:[SCI]", new=True),
           Case("frame", "cur", "fifo-with-writer", frame, SAME, special="fifo-writer", new=True),
           Case("frame", "cur", "fifo-without-writer", None, ERROR, special="fifo", new=True),
           Case("frame", "cur", "fifo-valid-then-endless-zeros", frame, ERROR, special="fifo-endless", new=True)]
    for command in ("cur", "prev"):
        for kind in ("dir", "devnull", "devzero", "loop", "noperm"):
            out.append(Case("frame", command, kind, frame if kind == "noperm" else None, ERROR, special=kind,
                            new=kind == "devzero"))
    out.append(Case("truth", "catalog", "devzero", None, ERROR, special="devzero", new=True))
    out.append(Case("shapes", "correlate", "devzero", None, ERROR, special="devzero", new=True))
    return out


# -- the corpus ----------------------------------------------------------------------------------------

def valid_cases() -> list:
    pairs = [("frame", "cur"), ("frame", "prev"), ("frame", "measure"), ("rendered", "cur"), ("rendered", "prev"),
             ("ramp", "cur"), ("ramp", "prev"), ("truth", "catalog"), ("truth", "render"),
             ("shapes", "correlate")]
    out = [Case(seed, command, "valid", _mutation(seed, bytes), SAME) for seed, command in pairs]
    out += [Case(seed, command, "valid", _mutation(seed, bytes), SAME, checksum=False) for seed, command in pairs
            if command != "render"]
    return out


def frame_cases() -> list:
    cmds = ("cur", "prev", "measure")
    out = truncations("frame", cmds)
    flips = header_flips("frame", {
        0: [("EXTEND", "name"), ("OBJECT", "value"), ("COMMENT", 20), ("END", "name"), ("padding", None),
            ("CHECKSUM", "value")],
        1: [("EXPEND", "name"), ("EXPSTART", "value"), ("EXPTIME", "value"), ("NAXIS1", "value"),
            ("BUNIT", "value"), ("EXTNAME", "value"), ("XTENSION", "value"), ("COMMENT", 20), ("END", "name"),
            ("padding", None), ("CHECKSUM", "value"), ("DATASUM", "value")],
    }, rng_seed=2101, randoms=1)
    flips += data_flips("frame", {1: ["first", "middle", "last", "padding"]}, rng_seed=2102, randoms=1)
    out += flip_cases("frame", flips, cmds, nochecksum_commands=("cur", "prev"))
    out += edit_cases("frame", 1, IMAGE_STRUCTURE, ("cur", "prev"))
    out += edit_cases("frame", 1, [s for s in IMAGE_STRUCTURE if s[0] in ("BITPIX=7", "NAXIS1=10**12", "no-END")],
                      ("measure",))
    out += edit_cases("frame", 1, IMAGE_ODDITIES, ("cur", "prev"), expect=ERROR_OR_SAME)
    out += edit_cases("frame", 0, PRIMARY_STRUCTURE, ("cur", "prev"))
    out += edit_cases("frame", 0, [("EXTEND=F", dict(replace={"EXTEND": c("EXTEND", "F")}))], ("cur",),
                      expect=ERROR_OR_SAME)
    out += edit_cases("frame", 1, SCALING, ("cur", "prev", "measure"), prefix="scaling")
    out += edit_cases("frame", 1, [("BLANK=-999-on-float", dict(insert=[c("BLANK", "-999")]))], ("cur", "prev"),
                      expect=ERROR_OR_SAME, prefix="scaling")
    out += flood_cases("frame", 1, ("cur",))
    out += garbage_cases("frame", cmds)
    out += foreign_cases("frame", ("cur", "prev"))
    out += foreign_cases("frame", ("measure",))[:2]
    out += compressed_cases("frame", ("cur", "prev"))
    return out


def rendered_cases() -> list:
    cmds = ("cur", "prev")
    out = truncations("rendered", cmds)
    flips = header_flips("rendered", {
        0: [("CREATOR", "value"), ("HISTORY", 20), ("END", "name")],
        1: [("EXPEND", "name"), ("GAIN", "value"), ("BUNIT", "value"), ("NAXIS2", "value")],
        2: [("EXTNAME", "value"), ("NAXIS1", "value")],
        3: [("EXTNAME", "value"), ("BUNIT", "value"), ("EXPEND", "name")],
        4: [("TFORM4", "value"), ("NAXIS2", "value"), ("TTYPE1", "value"), ("COMMENT", 20)],
    }, rng_seed=2201, randoms=1)
    flips += data_flips("rendered", {1: ["first"], 2: ["middle"], 3: ["first", "middle"],
                                     4: [("row", 2, "EFFECT"), ("row", 3, "VALUE")]}, rng_seed=2202)
    out += flip_cases("rendered", flips, cmds, nochecksum_commands=cmds, nochecksum_labels={
        "h1:SCI-BUNIT-value", "h3:FLUENCE-BUNIT-value", "h2:IDEAL-data-middle", "h3:FLUENCE-data-middle",
        "h4:MODEL-TFORM4-value", "h4:MODEL-data-row3.VALUE"})
    out += edit_cases("rendered", 3, [s for s in IMAGE_STRUCTURE if s[0] in ("NAXIS1=10**12", "BITPIX=7")], cmds)
    out += edit_cases("rendered", 2, [s for s in IMAGE_STRUCTURE if s[0] in ("NAXIS2=10**12", "GCOUNT=2")], cmds)
    out += edit_cases("rendered", 4, [("NAXIS2=10**12", dict(replace={"NAXIS2": c("NAXIS2", str(10 ** 12))}))],
                      cmds)
    out += garbage_cases("rendered", cmds)
    return out


def ramp_cases() -> list:
    cmds = ("cur", "prev")
    sci = lambda ver: 1 + 3 * (ver - 1)  # noqa: E731
    out = truncations("ramp", cmds, hdus={0, sci(1), sci(1) + 1, sci(2), sci(3) + 2, sci(4), sci(4) + 2})
    flips = header_flips("ramp", {
        0: [("NSAMP", "value"), ("CCDGAIN", "value"), ("EXPEND", "name")],
        sci(1): [("SAMPTIME", "value"), ("BZERO", "value"), ("EXTVER", "value"), ("NAXIS1", "value")],
        sci(1) + 1: [("EXTNAME", "value")],
        sci(1) + 2: [("BITPIX", "value")],
        sci(2): [("SAMPTIME", "value")],
        sci(4): [("EXTVER", "value"), ("BZERO", "value")],
        **{i: [] for i in range(1 + 3 * fc.NSAMP) if i not in (0, sci(1), sci(1) + 1, sci(1) + 2, sci(2), sci(4))},
    }, rng_seed=2301, randoms=1)               # a random flip in the header of every HDU
    data = {i: ["middle"] for i in range(1, 1 + 3 * fc.NSAMP)}    # the data of every HDU
    data[sci(1)] += ["first", "last"]
    data[sci(4)] += ["first"]
    flips += data_flips("ramp", data, rng_seed=2302)
    out += flip_cases("ramp", flips, cmds, nochecksum_commands=cmds, nochecksum_labels={
        "h0:PRIMARY-CCDGAIN-value", "h1:SCI,1-SAMPTIME-value", "h4:SCI,2-data-middle", "h10:SCI,4-data-first",
        "h2:ERR,1-data-middle"})
    out += edit_cases("ramp", sci(2), [s for s in IMAGE_STRUCTURE if s[0] == "NAXIS1=10**12"], cmds)
    out += edit_cases("ramp", sci(4) + 2, [s for s in IMAGE_STRUCTURE if s[0] == "BITPIX=7"], cmds)
    out += edit_cases("ramp", sci(2) + 1, [s for s in IMAGE_STRUCTURE if s[0] == "GCOUNT=2"], cmds)
    out += edit_cases("ramp", sci(1), [s for s in SCALING if s[0] in ("BSCALE=0", "BZERO=NaN")], cmds,
                      prefix="scaling")
    out += edit_cases("ramp", sci(4), [("BZERO='abc'", dict(set={"BZERO": quoted("abc")}))], cmds, prefix="scaling")
    out += garbage_cases("ramp", ("cur",))
    return out


def truth_cases() -> list:
    out = truncations("truth", ("catalog",))
    flips = header_flips("truth", {0: [("SEED", "value")],
                                   1: [("TTYPE2", "value"), ("TFORM2", "value"), ("TUNIT2", "value"),
                                       ("NAXIS2", "value"), ("EXTNAME", "value")]}, rng_seed=2401, randoms=1)
    flips += data_flips("truth", {1: [("row", 0, "ra"), ("row", 1, "mag_J129"), ("row", 2, "kind"),
                                      ("row", 3, "hlr")]}, rng_seed=2402, randoms=1)
    out += flip_cases("truth", flips, ("catalog",), nochecksum_commands=("catalog",), nochecksum_labels={
        "h1:TRUTH-TTYPE2-value", "h1:TRUTH-TUNIT2-value", "h1:TRUTH-data-row1.mag_J129", "h1:TRUTH-data-row2.kind"})
    out += table_structure_cases("truth", ("catalog",))
    out += garbage_cases("truth", ("catalog",))
    out += foreign_cases("truth", ("catalog",))[:2]
    out += compressed_cases("truth", ("catalog",), fpack=False)
    # render reads the same catalogue; ~1 s a run, so a few cases only
    sp = spans_of("truth")[1]
    render = [Case("truth", "render", "trunc-mid-data", _mutation("truth", lambda r: r[:(sp.data[0] + sp.data[1]) // 2]),
                   ERROR),
              Case("truth", "render", "flip-TTYPE2-value", _flip_at("truth", *fc.flip_in_card(hdus_of("truth"), 1,
                                                                                             "TTYPE2", "value")),
                   ERROR, new=True)]
    row1 = [f for f in flips if f[0] == "h1:TRUTH-data-row1.mag_J129"][0]
    render.append(Case("truth", "render", "flip-data-row1.mag_J129", _flip_at("truth", row1[3], row1[4]), ERROR,
                       new=True))
    render.append(Case("truth", "render", "flip-data-row1.mag_J129", _flip_at("truth", row1[3], row1[4]), CONSISTENT,
                       checksum=False, new=True))
    render += edit_cases("truth", 1, [("NAXIS2=10**12", dict(replace={"NAXIS2": c("NAXIS2", str(10 ** 12))}))],
                         ("render",))
    render += garbage_cases("truth", ("render",))[:1]
    return out + render


def shapes_cases() -> list:
    out = truncations("shapes", ("correlate",))
    flips = header_flips("shapes", {0: [("NFRAMES", "value")],
                                    1: [("TTYPE7", "value"), ("TFORM2", "value"), ("NAXIS2", "value"),
                                        ("TFIELDS", "value"), ("EXTNAME", "value")]}, rng_seed=2501, randoms=2)
    flips += data_flips("shapes", {1: [("row", 5, "g1"), ("row", 30, "frame"), ("row", 3, "flags"),
                                       ("row", 10, "id")]}, rng_seed=2502, randoms=1)
    out += flip_cases("shapes", flips, ("correlate",), nochecksum_commands=("correlate",), nochecksum_labels={
        "h1:SHAPES-TTYPE7-value", "h1:SHAPES-data-row5.g1", "h1:SHAPES-data-row3.flags"})
    out += table_structure_cases("shapes", ("correlate",))
    out += flood_cases("shapes", 1, ("correlate",))
    out += garbage_cases("shapes", ("correlate",))
    out += foreign_cases("shapes", ("correlate",))[:2]
    out += compressed_cases("shapes", ("correlate",), fpack=False)
    return out


def all_cases() -> list:
    cases = (valid_cases() + frame_cases() + rendered_cases() + ramp_cases() + truth_cases() + shapes_cases()
             + special_cases())
    ids = [case.id for case in cases]
    dupes = {i for i in ids if ids.count(i) > 1}
    assert not dupes, dupes
    return cases


CASES = all_cases()


# =================================================================================================
# Running and judging
# =================================================================================================

@pytest.fixture(scope="module")
def server():
    srv = fc.ForkServer(memory=MEMORY).start()
    yield srv
    srv.stop()


@pytest.fixture(scope="module")
def inputs(tmp_path_factory):
    """The valid partner files (earlier.fits, later.fits, truth.fits, frame.fits, psf.fits), read-only."""
    folder = tmp_path_factory.mktemp("fuzz_inputs")
    out = {}
    for name in ("earlier", "later", "truth", "frame", "psf"):
        path = folder / f"{name}.fits"
        path.write_bytes(fc.seeds()[name])
        out[name] = str(path)
    return out


_REFERENCES: dict = {}


def _digest(data: bytes) -> str:
    return hashlib.sha256(data).hexdigest()


def snapshot(paths) -> dict:
    """sha256 and mtime of every regular file among ``paths`` (FIFOs and devices are not read)."""
    out = {}
    for p in paths:
        try:
            if os.path.isfile(p) and not os.path.islink(p):
                out[p] = (_digest(Path(p).read_bytes()), os.stat(p).st_mtime_ns)
        except OSError:
            pass
    return out


class Failure(AssertionError):
    def __init__(self, kind: str, text: str):
        super().__init__(f"[{kind}] {text}")
        self.kind = kind


def run_case(server, inputs, folder: Path, case_bytes, command: str, *, name: str, timeout: float,
             checksum: bool, special=None):
    """Write the case file (or make the special file), run ``command`` on it; returns the run with the name
    the error line must show (``shown``), the output folder and snapshots of the inputs."""
    folder.mkdir(parents=True, exist_ok=True)
    out_dir = folder / "out"
    out_dir.mkdir()
    case_path = folder / name
    writer = None
    if case_bytes is not None and special not in ("fifo-writer", "fifo-endless"):
        case_path.write_bytes(case_bytes)
    arg = str(case_path)
    if special == "dir":
        case_path.mkdir()
    elif special == "devnull":
        arg = os.devnull
    elif special == "devzero":
        arg = "/dev/zero"
    elif special == "loop":
        os.symlink(folder / "loop2.fits", case_path)
        os.symlink(case_path, folder / "loop2.fits")
    elif special == "noperm":
        os.chmod(case_path, 0)
    elif special in ("fifo", "fifo-writer", "fifo-endless"):
        os.mkfifo(case_path)
        if special != "fifo":
            writer = threading.Thread(target=_feed_fifo, args=(case_path, case_bytes, time.monotonic() + timeout,
                                                               special == "fifo-endless"), daemon=True)
            writer.start()
    elif special and special.startswith("ext:"):
        arg = str(case_path) + special[4:]
    watched = [str(case_path), *inputs.values()]
    before = snapshot(watched)
    present = sorted(os.listdir(folder))
    args = command_args(command, arg, str(out_dir / "out.fits"), inputs)
    if not checksum:
        args = [NO_CHECKSUM, *args]
    run = server.run(args, cwd=str(folder), timeout=timeout)
    if writer is not None:
        writer.join(timeout=5)
    run.update(after=snapshot(watched), before=before, args=args, folder=str(folder), present=present,
               shown=arg if special in ("devnull", "devzero") else os.path.basename(arg.split("[")[0]))
    return run, out_dir


def _feed_fifo(path, data, deadline, endless=False):
    """Write ``data`` into FIFO ``path`` once a reader has opened it (give up at ``deadline``); ``endless``:
    then zeros until the reader goes away or the deadline passes."""
    while time.monotonic() < deadline:
        try:
            fd = os.open(path, os.O_WRONLY | os.O_NONBLOCK)
        except OSError:
            time.sleep(0.01)
            continue
        os.set_blocking(fd, True)
        try:
            _write_stream(lambda b: os.write(fd, b), data, endless, deadline)
        finally:
            os.close(fd)
        return


def _write_stream(write, data, endless, deadline):
    """Write ``data`` (then zeros while ``endless`` and before ``deadline``); stop quietly when the reader
    has gone."""
    zeros = bytes(1 << 16)
    try:
        view = memoryview(data)
        while view:
            view = view[write(view[:1 << 16]):]
        while endless and time.monotonic() < deadline:
            write(zeros)
    except (BrokenPipeError, OSError, ValueError):
        pass


def contents(path: Path):
    """[(name, ver, data)] of an output, read by astropy with its checksums verified."""
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        with fits.open(path, checksum=True) as hdul:
            out = []
            for h in hdul:
                if h.data is None:
                    data = None
                elif isinstance(h, (fits.BinTableHDU, fits.TableHDU)):
                    data = {n: np.array(h.data[n]) for n in h.columns.names}
                else:
                    data = np.array(h.data)
                out.append((h.name, h.ver, data))
            return out


def _equal(a, b, approx: bool) -> bool:
    if a is None or b is None:
        return a is None and b is None
    if isinstance(a, dict):
        return a.keys() == b.keys() and all(_equal(a[k], b[k], approx) for k in a)
    if a.shape != b.shape:
        return False
    if a.dtype.kind in "fc" and b.dtype.kind in "fc":
        if approx:
            return bool(np.allclose(a, b, rtol=1e-10, atol=0, equal_nan=True))
        return bool(np.array_equal(a, b, equal_nan=True))
    return bool(np.array_equal(a, b))


def same_result(got, ref, compare: str, approx: bool) -> str | None:
    """None when the outputs agree, else what differs."""
    if compare == "sci":
        pick = lambda hdus: next((h for h in hdus if h[0] == "SCI"), next(h for h in hdus if h[2] is not None))  # noqa
        got, ref = [pick(got)], [pick(ref)]
    if [(n, v) for n, v, _ in got] != [(n, v) for n, v, _ in ref]:
        return f"HDUs {[(n, v) for n, v, _ in got]} != {[(n, v) for n, v, _ in ref]}"
    for (n, v, a), (_, _, b) in zip(got, ref):
        if not _equal(a, b, approx):
            return f"data of HDU {n},{v} differ from the reference"
    return None


def _excerpt(lines, head=3, tail=12):
    return lines if len(lines) <= head + tail + 1 else [*lines[:head], "...", *lines[-tail:]]


def judge(run, out_dir: Path, *, expect_error_only: bool, label: str, max_cpu: float | None = None):
    """The checks every run must pass; returns the output's contents (exit 0) or None (exit 1).

    ``max_cpu``: CPU seconds the run may take (user + system, the child's own: not the machine's load)."""
    stderr = run["stderr"]
    where = f"{label}\n  $ perscli {' '.join(run['args'])}\n  exit {run['code']} in {run['elapsed']:.2f}s; " \
            "stderr:\n" + "".join(f"    | {line}\n" for line in _excerpt(stderr.splitlines()))
    if run["timed_out"]:
        raise Failure("hang", f"no answer within the deadline: {where}")
    if max_cpu is not None and run["cpu"] > max_cpu:
        raise Failure("slow", f"{run['cpu']:.1f} CPU seconds, more than {max_cpu:g} (quadratic work?): {where}")
    if run["code"] < 0:
        raise Failure("crash", f"killed by signal {-run['code']}: {where}")
    if "Traceback" in stderr or "Exception ignored" in stderr:
        if "MemoryError" in stderr or "File too large" in stderr:    # RLIMIT_AS, or RLIMIT_FSIZE on a memfd
            raise Failure("memory", f"a memory limit was hit (traceback): {where}")
        raise Failure("traceback", where)
    if run["code"] not in (0, 1):
        raise Failure(f"exit {run['code']}", where)
    if run.get("maxrss_mb", 0) > MAX_RSS_MB or "out of memory" in stderr:
        raise Failure("memory", f"peak memory {run.get('maxrss_mb', 0):.0f} MB: {where}")
    if run["after"] != run["before"]:
        changed = [p for p in run["before"] if run["after"].get(p) != run["before"][p]]
        raise Failure("input modified", f"{changed}: {where}")
    left = sorted(os.listdir(out_dir))
    if "present" in run and sorted(os.listdir(run["folder"])) != run["present"]:
        raise Failure("partial output", f"files appeared next to the input: "
                                        f"{sorted(set(os.listdir(run['folder'])) - set(run['present']))}: {where}")
    if run["code"] == 1:
        lines = stderr.splitlines()
        if len(lines) != 1 or not lines[0].strip():
            raise Failure("message", f"not exactly one line on stderr: {where}")
        if run["shown"] not in lines[0]:
            raise Failure("message", f"the error line does not name {run['shown']}: {where}")
        if left:
            raise Failure("partial output", f"{left} left in the output folder: {where}")
        return None
    if expect_error_only:
        raise Failure("accepted", f"exit 0 on an input that must be refused: {where}")
    if left != ["out.fits"]:
        raise Failure("partial output", f"output folder holds {left}: {where}")
    try:
        return contents(out_dir / "out.fits")
    except Exception as exc:  # noqa: BLE001
        raise Failure("bad output", f"output unreadable or bad checksum ({exc}): {where}") from None


def reference(server, inputs, tmp_root: Path, seed: str, command: str, data: bytes | None = None):
    """(exit status, contents, stderr) of ``command`` on ``data`` (default: the valid seed) with the checksum
    check on; cached by content.  The run itself must pass :func:`judge`."""
    data = seed_bytes(seed) if data is None else data
    key = (_digest(data), command)
    if key not in _REFERENCES:
        folder = tmp_root / f"ref-{len(_REFERENCES)}"
        run, out_dir = run_case(server, inputs, folder, data, command, name="case.fits", timeout=TIMEOUT,
                                checksum=True)
        got = judge(run, out_dir, expect_error_only=False, label=f"reference run ({seed}, {command})")
        _REFERENCES[key] = (run["code"], got, run["stderr"].strip())
    return _REFERENCES[key]


def _log(case_id: str, kind: str, run=None):
    path = os.environ.get("PERSCLI_FUZZ_LOG")
    if not path:
        return
    rec = {"id": case_id, "kind": kind}
    if run is not None:
        rec.update(code=run["code"], elapsed=round(run["elapsed"], 3),
                   stderr=run["stderr"].strip().splitlines()[:1])
    with open(path, "a") as fh:
        fh.write(json.dumps(rec) + "\n")


def _params():
    for case in CASES:
        marks = [FITS_LAYER] if case.new else []
        if case.special == "noperm":
            marks.append(pytest.mark.skipif(IS_ROOT, reason="root reads any file: no permission case is moot"))
        yield pytest.param(case, id=case.id, marks=marks)


@pytest.mark.parametrize("case", list(_params()))
def test_fuzz_case(case: Case, server, inputs, tmp_path):
    approx = case.command == "correlate"       # TreeCorr's sums: equal to rounding
    data = case.make() if case.make is not None else None
    run = None
    try:
        run, out_dir = run_case(server, inputs, tmp_path / "case", data, case.command, name="case" + case.suffix,
                                timeout=case.timeout, checksum=case.checksum, special=case.special)
        got = judge(run, out_dir, expect_error_only=case.expect == ERROR, label=f"{case.id} (expect {case.expect})",
                    max_cpu=case.max_cpu)
        if case.name == "valid" and case.checksum and case.special is None:
            _REFERENCES.setdefault((_digest(data), case.command), (run["code"], got, run["stderr"].strip()))
        if case.expect == CONSISTENT:
            base = case.base() if case.base else seed_bytes(case.seed)
            ref_code, ref, ref_err = reference(server, inputs, tmp_path, case.seed, case.command,
                                               fc.resigned_like(data, base))
            if run["code"] != ref_code:
                raise Failure("inconsistent", f"{case.id}: exit {run['code']} with {NO_CHECKSUM} "
                                              f"({run['stderr'].strip()!r}), exit {ref_code} on the same bytes "
                                              f"re-signed ({ref_err!r})")
            if got is not None:
                diff = same_result(got, ref, case.compare, approx)
                if diff:
                    raise Failure("wrong result", f"{case.id}: {diff} (reference: the same bytes re-signed)")
        elif got is not None:
            ref_code, ref, ref_err = reference(server, inputs, tmp_path, case.seed, case.command)
            if ref_code != 0:
                raise Failure("refused", f"{case.id}: the valid {case.seed} itself is refused: {ref_err}")
            diff = same_result(got, ref, case.compare, approx)
            if diff:
                raise Failure("wrong result", f"{case.id}: {diff} (reference: the valid {case.seed})")
        elif case.expect == SAME:
            raise Failure("refused", f"{case.id}: a valid input was refused: {run['stderr'].strip()}")
    except Failure as exc:
        _log(case.id, exc.kind, run)
        raise
    _log(case.id, "pass", run)


# =================================================================================================
# The corpus itself: deterministic, valid, and the checksum code right
# =================================================================================================

def test_corpus_seeds_are_valid_and_signed(tmp_path):
    """Every seed opens in astropy and CFITSIO with valid CHECKSUM/DATASUM in every HDU, and re-signing
    it (this file's own checksum code, used for the edited cases) changes no byte."""
    import fitsio

    seeds = dict(fc.seeds(), fpack=fc.tile_compressed(fc.seeds()["frame"]))
    for name, raw in seeds.items():
        assert len(raw) % fc.BLOCK == 0, name
        for h in fc.split(raw):
            h.index("CHECKSUM"), h.index("DATASUM")    # raise KeyError when absent
        assert fc.join(fc.resign(fc.split(raw))) == raw, name
        path = tmp_path / f"{name}.fits"
        path.write_bytes(raw)
        with warnings.catch_warnings():
            warnings.simplefilter("error")
            with fits.open(path, checksum=True) as hdul:
                assert len(hdul) == len(fc.split(raw)), name
                [h.data for h in hdul]
        with fitsio.FITS(str(path)) as f:
            for hdu in f:
                hdu.verify_checksum()          # raises on a mismatch


def test_corpus_mutations_are_detected_by_astropy(tmp_path):
    """The checksum code is not vacuous: a flipped bit breaks astropy's check, re-signing repairs it."""
    raw = fc.seeds()["frame"]
    sp = fc.layout(fc.split(raw))[1]
    bad = fc.flip(raw, sp.data[0] + 100, 0x04)
    path = tmp_path / "bad.fits"
    path.write_bytes(bad)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        with fits.open(path, checksum=True) as hdul:
            hdul[1].data
    messages = " ".join(str(w.message) for w in caught)
    assert "Checksum verification failed" in messages and "Datasum verification failed" in messages, messages
    path.write_bytes(fc.resigned_like(bad, raw))
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        with fits.open(path, checksum=True) as hdul:
            assert hdul[1].data.shape == fc.SHAPE


def test_corpus_is_deterministic():
    """A fresh interpreter builds the same bytes: no time, no global random state in the corpus."""
    code = ("import hashlib, fuzz_corpus as f; s = f.seeds(); "
            "print({k: hashlib.sha256(v).hexdigest() for k, v in sorted(s.items())}); "
            "print(hashlib.sha256(f.tile_compressed(s['frame'])).hexdigest())")
    env = dict(os.environ, PYTHONPATH=os.path.dirname(os.path.abspath(__file__)))
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=env, timeout=120)
    assert out.returncode == 0, out.stderr
    here = ({k: _digest(v) for k, v in sorted(fc.seeds().items())},
            _digest(fc.tile_compressed(fc.seeds()["frame"])))
    assert out.stdout.splitlines() == [str(here[0]), here[1]]
    again = [(case.id, _digest(case.make())) for case in all_cases()[:200] if case.make is not None]
    assert again == [(case.id, _digest(case.make())) for case in CASES[:200] if case.make is not None]


def test_judge_catches_every_kind_of_failure(tmp_path):
    """Each check of :func:`judge` fires on a run that breaks it (so that no case passes vacuously)."""
    out_dir = tmp_path / "out"
    out_dir.mkdir()
    good_error = dict(code=1, stderr="Error: case.fits: truncated\n", timed_out=False, elapsed=0.1, args=["x"],
                      shown="case.fits", before={"a": 1}, after={"a": 1}, maxrss_mb=100.0,
                      folder=str(tmp_path), present=sorted(os.listdir(tmp_path)))
    assert judge(good_error, out_dir, expect_error_only=True, label="ok") is None
    broken = {
        "hang": dict(timed_out=True),
        "crash": dict(code=-7),
        "traceback": dict(stderr="Traceback (most recent call last):\nValueError: x\n"),
        "memory": dict(maxrss_mb=MAX_RSS_MB + 1.0),
        "exit 2": dict(code=2),
        "input modified": dict(after={"a": 2}),
        "message": dict(stderr="Error: case.fits: one\nand two\n"),
    }
    for kind, change in broken.items():
        with pytest.raises(Failure) as err:
            judge({**good_error, **change}, out_dir, expect_error_only=True, label=kind)
        assert err.value.kind == kind, (kind, str(err.value))
    with pytest.raises(Failure, match="does not name"):
        judge({**good_error, "stderr": "Error: something failed\n"}, out_dir, expect_error_only=True, label="name")
    (out_dir / ".out.fits.part").write_bytes(b"x")
    with pytest.raises(Failure, match=r"\[partial output\]"):
        judge(good_error, out_dir, expect_error_only=True, label="part")
    (out_dir / ".out.fits.part").unlink()
    (tmp_path / "case.fits.tmp").write_bytes(b"x")
    with pytest.raises(Failure, match="next to the input"):
        judge(good_error, out_dir, expect_error_only=True, label="next")
    (tmp_path / "case.fits.tmp").unlink()
    success = {**good_error, "code": 0, "stderr": ""}
    with pytest.raises(Failure, match=r"\[accepted\]"):
        judge(success, out_dir, expect_error_only=True, label="accepted")
    (out_dir / "out.fits").write_bytes(b"SIMPLE  =   garbage")
    with pytest.raises(Failure, match=r"\[bad output\]"):
        judge(success, out_dir, expect_error_only=False, label="bad output")
    # and the comparison sees a one-bit change of one pixel
    (out_dir / "out.fits").write_bytes(seed_bytes("frame"))
    ref = judge(success, out_dir, expect_error_only=False, label="good")
    sp = spans_of("frame")[1]
    (out_dir / "out.fits").write_bytes(fc.resigned_like(fc.flip(seed_bytes("frame"), sp.data[1] - 1, 1),
                                                        seed_bytes("frame")))
    got = judge(success, out_dir, expect_error_only=False, label="changed")
    assert same_result(ref, ref, "all", False) is None and same_result(got, ref, "all", False) is not None


def test_server_kills_a_run_at_its_deadline(server, inputs, tmp_path):
    """A FIFO that nobody writes, with a deadline shorter than perscli's wait: the run is reported as a hang."""
    run, out_dir = run_case(server, inputs, tmp_path / "case", None, "cur", name="case.fits", timeout=1.0,
                            checksum=True, special="fifo")
    # the kill itself is what is checked (the harness's deadline works), not how fast a loaded machine does it
    assert run["timed_out"] and run["code"] == -9 and 0.9 < run["elapsed"] < 60
    with pytest.raises(Failure, match=r"\[hang\]"):
        judge(run, out_dir, expect_error_only=True, label="hang")


# =================================================================================================
# Standard input and a broken standard output: real processes and real pipes
# =================================================================================================

def _clean_env():
    env = dict(os.environ)
    return env


def run_process(args, *, stdin, feed=None, endless=False, cwd, timeout=TIMEOUT) -> dict:
    """Run the perscli console script; ``stdin`` is a file object or PIPE (then ``feed`` bytes are written
    into it by a thread, followed by zeros for ever when ``endless``).  Returns a run like ForkServer.run."""
    start = time.monotonic()
    with open(Path(cwd) / ".stderr", "w+b") as err:
        proc = subprocess.Popen([PERSCLI, *args], stdin=stdin, stdout=subprocess.DEVNULL, stderr=err, cwd=cwd,
                                env=_clean_env(), preexec_fn=fc.limit_memory(MEMORY))
        writer = None
        if stdin is subprocess.PIPE:
            def feed_and_close():
                _write_stream(proc.stdin.write, feed, endless, start + timeout)
                try:
                    proc.stdin.close()                 # end of input
                except OSError:
                    pass

            writer = threading.Thread(target=feed_and_close, daemon=True)
            writer.start()
        timed_out = False
        deadline = start + timeout
        while True:
            pid, status, usage = os.wait4(proc.pid, os.WNOHANG)
            if pid:
                break
            if time.monotonic() > deadline:
                timed_out = True
                proc.kill()
                _, status, usage = os.wait4(proc.pid, 0)
                break
            time.sleep(0.01)
        proc.returncode = os.waitstatus_to_exitcode(status)
        if writer is not None:
            writer.join(timeout=5)
            try:
                proc.stdin.close()
            except OSError:
                pass
        err.seek(0)
        stderr = err.read().decode("utf-8", "backslashreplace")
    os.remove(Path(cwd) / ".stderr")
    return dict(code=proc.returncode if not timed_out else -9, stderr=stderr, timed_out=timed_out,
                elapsed=time.monotonic() - start, maxrss_mb=usage.ru_maxrss / 1024.0)


STDIN_CASES = [
    ("valid", lambda: seed_bytes("frame"), SAME, False),
    ("gz-valid", lambda: fc.gzipped(seed_bytes("frame")), SAME, True),
    ("empty", lambda: b"", ERROR, False),
    ("text", lambda: b"not FITS\n" * 100, ERROR, False),
    ("truncated-mid-data", lambda: seed_bytes("frame")[:7000], ERROR, False),
    ("flip-EXPEND-name", lambda: fc.flip(seed_bytes("frame"), *fc.flip_in_card(hdus_of("frame"), 1, "EXPEND",
                                                                                "name")), ERROR, True),
    ("trailing-garbage", lambda: seed_bytes("frame") + b"garbage\n" * 10, ERROR, True),
    ("devzero", None, ERROR, True),                                       # perscli ... - < /dev/zero
    ("valid-then-endless-zeros", lambda: seed_bytes("frame"), ERROR, True),  # cat frame.fits /dev/zero | perscli
]


@pytest.mark.skipif(PERSCLI is None, reason="perscli console script not installed")
@pytest.mark.parametrize("name, make, expect, new",
                         [pytest.param(*c, id=f"stdin-{c[0]}", marks=[FITS_LAYER] if c[3] else []) for c in STDIN_CASES])
def test_stdin(name, make, expect, new, inputs, server, tmp_path):
    """``cat CASE | perscli apply-persistence - earlier.fits -o OUT``: a real process, a real pipe on stdin."""
    out_dir = tmp_path / "out"
    out_dir.mkdir()
    before = snapshot(inputs.values())
    args = ["apply-persistence", "-", inputs["earlier"], "--mode", "add", "-o", str(out_dir / "out.fits")]
    if make is None:
        with open("/dev/zero", "rb") as zero:
            run = run_process(args, stdin=zero, cwd=tmp_path)
    else:
        run = run_process(args, stdin=subprocess.PIPE, feed=make(), endless="endless" in name, cwd=tmp_path)
    run.update(before=before, after=snapshot(inputs.values()), shown="stdin",
               args=["apply-persistence", "-", "earlier.fits", "-o", "out/out.fits"])
    try:
        got = judge(run, out_dir, expect_error_only=expect == ERROR, label=f"stdin-{name}")
        if got is None and expect == SAME:
            raise Failure("refused", f"stdin-{name}: a valid input was refused: {run['stderr'].strip()}")
        if got is not None:
            _, ref, _ = reference(server, inputs, tmp_path, "frame", "cur")
            diff = same_result(got, ref, "all", False)
            if diff:
                raise Failure("wrong result", f"stdin-{name}: {diff}")
    except Failure as exc:
        _log(f"stdin-{name}", exc.kind, run)
        raise
    _log(f"stdin-{name}", "pass", run)


@pytest.mark.skipif(PERSCLI is None, reason="perscli console script not installed")
def test_broken_stdout_pipe_exits_quietly(tmp_path):
    """``perscli apply-persistence BIG PREV -o - | head -c 10``: the reader goes away after 10 bytes of a
    ~0.5 MB output; perscli must end quietly (no traceback, nothing on stderr) and leave no file."""
    cur, prev = tmp_path / "big_current.fits", tmp_path / "big_previous.fits"
    cur.write_bytes(fc.seeds()["big_current"])
    prev.write_bytes(fc.seeds()["big_previous"])
    work = tmp_path / "work"
    work.mkdir()
    before = snapshot([str(cur), str(prev)])
    with open(tmp_path / "stderr.txt", "wb") as err:
        proc = subprocess.Popen([PERSCLI, "apply-persistence", str(cur), str(prev), "-o", "-"], stdout=subprocess.PIPE,
                                stderr=err, cwd=work, env=_clean_env(), preexec_fn=fc.limit_memory(MEMORY))
        head = proc.stdout.read(10)
        proc.stdout.close()
        try:
            code = proc.wait(timeout=TIMEOUT)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait()
            _log("broken-stdout-pipe", "hang")
            raise Failure("hang", "perscli did not end after its reader closed the pipe") from None
    stderr = (tmp_path / "stderr.txt").read_text(errors="backslashreplace")
    kind = None
    if head != b"SIMPLE  = ":
        kind, text = "bad output", f"first bytes {head!r}"
    elif "Traceback" in stderr or "Exception ignored" in stderr:
        kind, text = "traceback", stderr
    elif stderr.strip():
        kind, text = "message", f"not quiet (exit {code}): {stderr.strip()}"
    elif os.listdir(work):
        kind, text = "partial output", str(os.listdir(work))
    elif snapshot([str(cur), str(prev)]) != before:
        kind, text = "input modified", ""
    _log("broken-stdout-pipe", kind or "pass")
    if kind:
        raise Failure(kind, f"broken stdout pipe: {text}")
