"""Render one Roman SCA exposure of a truth catalog.

The optics (:class:`perscli.optics.Optics`, which measure shares) come from
GalSim's Roman module: the WCS of the SCA for the pointing
(``galsim.roman.getWCS``, with the observatory position angle), the PSF of
that SCA and filter (``galsim.roman.getPSF`` at the SCA centre and the
filter's effective wavelength: it varies from SCA to SCA and filter to
filter, not across one SCA), the filter's AB zeropoint and the zodiacal sky
of ``galsim.roman.getSkyLevel`` (at the exposure's date: the zodiacal light
depends on where the Sun is) plus the thermal background.  Every error of
the exposure's geometry (a coordinate out of range, a position Roman cannot
observe on that date, an object GalSim's WCS cannot place) is a one-line
:class:`~perscli.PerscliError` naming the fix.  Objects are drawn by
:class:`perscli.optics.StampDrawer`; the detector chain of
:mod:`perscli.detector.effects` turns the expected electrons into a frame.
"""

from __future__ import annotations

import contextlib
import datetime as _dt
import logging
import math
from dataclasses import dataclass
from typing import NamedTuple

import galsim.roman as roman
import numpy as np

from .. import PerscliError, _kernels
from ..executor import imap
from ..instrument import ROMAN_EXPTIME, ROMAN_FILTERS, ROMAN_N_SCA, ROMAN_SCA_SIZE
from ..io.tables import read_table
from ..optics import (Optics, StampDrawer, exponential_forms, galaxy_stamp_size, local_jacobians, stamp_drawer,
                      star_stamp_size)
from ..scene import check_catalog, check_filter, check_mjd, check_pa, check_position

log = logging.getLogger(__name__)

FILTERS = ROMAN_FILTERS
SCA_SIZE = ROMAN_SCA_SIZE


@dataclass
class Exposure:
    """What is observed: a pointing, an SCA, a filter and a time.

    Attributes
    ----------
    ra, dec : float
        Pointing centre of the focal plane, degrees.
    pa : float
        Position angle of the observatory, degrees (GalSim's convention).
    sca : int
        1-18.
    filter : str
        A Roman filter name (J129, H158, ...).
    mjd : float
        Start of the exposure (MJD).
    exptime : float
        Seconds.
    bounds : tuple of int, optional
        (xmin, xmax, ymin, ymax), 1-indexed inclusive pixels of a cutout;
        None for the full 4088 x 4088 SCA.
    expid : int
        Identifier written to the header (a schedule row, say).
    """

    ra: float
    dec: float
    pa: float
    sca: int
    filter: str
    mjd: float
    exptime: float = ROMAN_EXPTIME
    bounds: tuple | None = None
    expid: int = -1

    def __post_init__(self):
        if self.filter not in FILTERS:
            raise PerscliError(f"unknown filter {self.filter!r}: use one of {', '.join(FILTERS)}")
        if not 1 <= int(self.sca) <= ROMAN_N_SCA:
            raise PerscliError(f"--sca {self.sca} is not a Roman SCA: use 1 to {ROMAN_N_SCA}")
        what = "pointing" if self.expid < 0 else f"pointing of exposure {self.expid}"
        self.ra, self.dec = check_position(self.ra, self.dec, what)
        self.pa = check_pa(self.pa, f"{what}: position angle")
        self.mjd = check_mjd(self.mjd, f"{what}: start")
        if not (math.isfinite(self.exptime) and self.exptime > 0):
            raise PerscliError(f"exposure time {self.exptime} s must be positive")
        if self.bounds is not None:
            xmin, xmax, ymin, ymax = (int(v) for v in self.bounds)
            if not (1 <= xmin <= xmax <= SCA_SIZE and 1 <= ymin <= ymax <= SCA_SIZE):
                raise PerscliError(f"--bounds {self.bounds} must lie within 1..{SCA_SIZE} with min <= max")
            self.bounds = (xmin, xmax, ymin, ymax)

    @classmethod
    def from_pointing(cls, pointing, *, sca: int | None = None, bounds=None) -> "Exposure":
        """The exposure of one SCA for a pointing (a schedule row or a pointings-table row).

        Parameters
        ----------
        pointing : perscli.scene.schedule.Pointing
            E.g. ``schedule_pointing(schedule, row)``, a row of
            ``read_pointings(...)``, ``select_covering(...)`` or
            ``previous_exposures(...)``: ra, dec, pa, filter, mjd, exptime and
            expid are taken from it.
        sca : int, optional
            1-18; default the pointing's ``sca``.
        bounds : (xmin, xmax, ymin, ymax), optional
            A cutout, as :attr:`bounds`.
        """
        sca = sca or pointing.sca
        if not sca:
            raise PerscliError("the pointing names no SCA: give sca (1-18)")
        return cls(ra=float(pointing.ra), dec=float(pointing.dec), pa=float(pointing.pa), sca=int(sca),
                   filter=check_filter(pointing.filter), mjd=float(pointing.mjd), exptime=float(pointing.exptime),
                   bounds=None if bounds is None else tuple(bounds), expid=int(pointing.expid))

    @property
    def full_bounds(self) -> tuple:
        return self.bounds or (1, SCA_SIZE, 1, SCA_SIZE)

    @property
    def date(self) -> _dt.datetime:
        return _dt.datetime(1858, 11, 17) + _dt.timedelta(days=self.mjd)

    @property
    def end(self) -> float:
        return self.mjd + self.exptime / 86400.0


# -- the catalogue --------------------------------------------------------------------------------

REQUIRED = ("id", "ra", "dec", "kind", "hlr", "e1", "e2")
#: what read_truth may read (for --columns)
TRUTH_READS = REQUIRED + ("mag_*",)


def read_truth(path: str, filter_name: str, *, columns=None):
    """The columns of a truth catalogue needed to draw ``filter_name``, as numpy arrays.

    Parameters
    ----------
    path : str
        The catalogue (``perscli catalog``'s columns, or others mapped by ``columns``).
    filter_name : str
        Roman filter: the magnitude column is ``mag_<filter_name>``.
    columns : dict, optional
        Column mapping {perscli name: file column} (``--columns``).

    Raises
    ------
    PerscliError
        Not a readable FITS table, a missing column, non-finite values, an
        unknown kind, or values no object can have
        (:func:`perscli.scene.check_catalog`).
    """
    table = read_table(path, what="truth catalogue (perscli catalog)", columns=columns or {}, known=TRUTH_READS)
    mag = f"mag_{filter_name}"
    needed = REQUIRED + (mag,)
    kinds = {"id": "integer", "kind": "text"}
    cols = {c: table.column(c, kind=kinds.get(c, "number"), needed=needed) for c in REQUIRED}
    cols["mag"] = table.column(mag, needed=needed).astype(np.float64)
    cols["kind"] = np.char.lower(cols["kind"])
    label = table.label
    for c in ("ra", "dec", "hlr", "e1", "e2", "mag"):
        cols[c] = np.asarray(cols[c], dtype=np.float64)
        bad = ~np.isfinite(cols[c])
        if c in ("hlr", "e1", "e2"):
            bad &= cols["kind"] == "galaxy"
        if np.any(bad):
            raise PerscliError(f"{label}: column {mag if c == 'mag' else c} has {int(bad.sum())} non-finite "
                               f"value(s) (first at id {cols['id'][bad][0]}); fix or drop those rows")
    unknown = set(np.unique(cols["kind"]).tolist()) - {"star", "galaxy"}
    if unknown:
        raise PerscliError(f"{label}: column kind has {sorted(unknown)}; expected 'star' or 'galaxy'")

    # the catalogue check measure makes too: ids, positions, sizes and ellipticities that GalSim can draw
    # (hlr = 0 divided by zero, |e| >= 1 raised GalSim's range error)
    check_catalog(label, cols, header=table.header, names={"mag": mag})
    cols["datasum"] = table.datasum
    return cols


# -- drawing ------------------------------------------------------------------------------------

def plan_objects(cols, optics: Optics, bounds, known: dict | None = None):
    """Which objects touch the image, with their positions, fluxes and stamp sizes.

    Parameters
    ----------
    cols : dict
        The catalogue's columns (:func:`read_truth`).
    optics : Optics
    bounds : (xmin, xmax, ymin, ymax)
        The image, 1-indexed inclusive SCA pixels.
    known : dict, optional
        Kept between calls on the same ``cols`` and ``optics`` with other
        bounds (a study's frame and the area its galaxies need): the
        positions, fluxes and stamp sizes already worked out are not worked
        out again.  The plans are the same as without it.

    Returns
    -------
    todo, x, y, flux, sizes
        Indices of the objects to draw, and per object its position, flux
        (electrons) and stamp side (0 where not needed).
    """
    if known is not None and "x" in known:
        x, y, flux = known["x"], known["y"], known["flux"]
        sizes = known["sizes"]
    else:
        x, y = optics.positions(cols["ra"], cols["dec"])
        flux = optics.electrons(cols["mag"])
        sizes = np.full(len(x), -1, dtype=np.int64)         # -1: not worked out yet
        if known is not None:
            known.update(x=x, y=y, flux=flux, sizes=sizes)
    is_star = cols["kind"] == "star"
    hlr_pix = cols["hlr"] / roman.pixel_scale
    xmin, xmax, ymin, ymax = bounds
    # no stamp is larger than 2048 pixels: only objects within that margin need a size
    near = np.flatnonzero((x + 1025 >= xmin) & (x - 1025 <= xmax) & (y + 1025 >= ymin) & (y - 1025 <= ymax))
    for i in near[sizes[near] < 0]:
        sizes[i] = star_stamp_size(flux[i]) if is_star[i] else galaxy_stamp_size(hlr_pix[i])
    # the sizes of these bounds: those near them (other objects' sizes, worked out for other bounds, are 0 here)
    here = np.zeros(len(x), dtype=np.int64)
    here[near] = sizes[near]
    half = here / 2 + 1
    keep = (here > 0) & (x + half >= xmin) & (x - half <= xmax) & (y + half >= ymin) & (y - half <= ymax)
    keep &= flux > 0
    return np.flatnonzero(keep), x, y, flux, here


@dataclass
class DrawContext:
    """What every stamp needs: the exposure's optics and a drawer holding its PSF (see :func:`draw_context`)."""

    optics: Optics
    drawer: StampDrawer


def draw_context(exposure: Exposure, optics: Optics | None = None) -> DrawContext:
    """The :class:`DrawContext` of an exposure (a picklable factory: ``executor.Lazy(draw_context, exposure)``)."""
    optics = optics if optics is not None else Optics(exposure)
    return DrawContext(optics, stamp_drawer(exposure.sca, exposure.filter))


#: objects per batch of :func:`draw_batch`: at most this many stamp pixels (a few tens of MB of spectra)
BATCH_PIXELS = 2 ** 22


class StampRun(NamedTuple):
    """The stamps of a run of objects (:func:`draw_batch`), in the run's order, for :func:`add_stamp_run`."""

    index: np.ndarray       # catalogue row of each object
    x0: np.ndarray          # its stamp's first column (detector pixels, int64)
    y0: np.ndarray          # its stamp's first row
    flux: np.ndarray        # its electrons
    group: np.ndarray       # which of ``stamps`` holds its stamp
    slot: np.ndarray        # its place there
    stamps: tuple           # per stamp side: (B, n, n) unit-flux stamps, centre at [0, 0] (not rolled)


def draw_batch(context: DrawContext, job) -> StampRun:
    """The stamps of a run of objects, in the job's order.

    ``job`` is (indices, x, y, flux, sizes, forms): arrays of one run of
    consecutive objects of :func:`draw_sources`; ``forms`` the exponential
    covariance forms of the galaxies (NaN rows for stars,
    :func:`perscli.optics.exponential_forms`).  Objects of one stamp size are
    drawn together (:meth:`perscli.optics.StampDrawer.batch`).
    """
    index, x, y, flux, sizes, forms = job
    ix, iy = np.floor(x + 0.5).astype(np.int64), np.floor(y + 0.5).astype(np.int64)
    sizes = np.asarray(sizes, dtype=np.int64)
    group, slot = np.zeros(len(index), dtype=np.int64), np.zeros(len(index), dtype=np.int64)
    stamps = []
    for g, n in enumerate(np.unique(sizes)):
        pick = np.flatnonzero(sizes == n)
        stamps.append(context.drawer.batch(int(n), x[pick] - ix[pick], y[pick] - iy[pick], forms[pick], roll=False))
        group[pick], slot[pick] = g, np.arange(len(pick))
    return StampRun(np.asarray(index, dtype=np.int64), ix - sizes // 2, iy - sizes // 2,
                    np.asarray(flux, dtype=np.float64), group, slot, tuple(stamps))


def add_stamp_run(run: StampRun, image, bounds, star_image=None, is_star=None) -> None:
    """Add a run's stamps times their fluxes into ``image`` (over ``bounds``), one after the other in its order.

    The stars' stamps are also added into ``star_image`` (``is_star``: per
    catalogue row).  Each pixel is the sum of the same products in the same
    order as adding each stamp's slice in numpy: the same bits, without a
    Python step per object (:func:`perscli._kernels.add_stamps`).
    """
    xmin, xmax, ymin, ymax = bounds
    target = image if image is not None else star_image
    stars = np.zeros(len(run.index), dtype=np.uint8)
    if is_star is not None and star_image is not None:
        stars[:] = np.asarray(is_star, dtype=bool)[run.index]
    if image is None:
        # only the stars' image: the other objects add nothing to it
        keep = stars.astype(bool)
        run = StampRun(*(a[keep] for a in run[:6]), run.stamps)
        stars = np.ones(len(run.index), dtype=np.uint8)
        _kernels.add_stamps(target, None, (ymax - ymin + 1, xmax - xmin + 1, xmin, ymin), run.stamps, run.group,
                            run.slot, run.x0, run.y0, run.flux, stars)
        return
    _kernels.add_stamps(target, star_image if stars.any() else None, (ymax - ymin + 1, xmax - xmin + 1, xmin, ymin),
                        run.stamps, run.group, run.slot, run.x0, run.y0, run.flux, stars)


def _batches(todo, sizes):
    """Runs of consecutive objects whose stamps hold at most :data:`BATCH_PIXELS` pixels (one at least)."""
    start, total = 0, 0
    for k, i in enumerate(todo):
        px = int(sizes[i]) ** 2
        if k > start and total + px > BATCH_PIXELS:
            yield start, k
            start, total = k, 0
        total += px
    if start < len(todo):
        yield start, len(todo)


def draw_sources(cols, exposure: Exposure, *, workers: int = 1, progress=None, stars: bool = False,
                 optics: Optics | None = None, plan=None, bounds=None, only=None, image: bool = True):
    """Expected electrons from the catalogue's objects on the exposure's pixels.

    Stamps are drawn in runs of consecutive objects by :func:`draw_batch`
    through :func:`perscli.executor.imap` (``workers`` processes, each handed
    the optics once) and added in catalogue order whatever the number of
    workers, so the result is the same bytes for any ``workers``.

    Parameters
    ----------
    cols : dict
        The catalogue's columns (:func:`read_truth`).
    exposure : Exposure
    workers : int
        Processes drawing stamps.
    progress : callable, optional
        Called as ``progress(done, total)`` after each stamp.
    stars : bool
        Also return the image of the stars alone (the same stamps, added to
        a second image in the same order).
    optics : Optics, optional
        The exposure's optics, when already made.
    plan : tuple, optional
        :func:`plan_objects` of these columns and optics over ``bounds``, when already made.
    bounds : (xmin, xmax, ymin, ymax), optional
        The detector pixels to draw (default the exposure's frame).
    only : ndarray of bool, optional
        Per catalogue row: draw only these of the objects that reach ``bounds``
        (the stars alone, say, or those reaching some noise blocks).  Each
        pixel is the sum of the same stamps in the same order either way, so
        the pixels that only the objects drawn reach are the same bits.
    image : bool
        False: no image of all the objects (with ``stars``, only the stars' image).

    Returns
    -------
    (ndarray, int, Optics) or (ndarray, int, Optics, ndarray)
        The image (float64, shape of the bounds; None without ``image``), the
        number of objects drawn, the optics (WCS, PSF, zeropoint, sky) used,
        and with ``stars`` the stars' image.
    """
    optics = optics if optics is not None else Optics(exposure)
    xmin, xmax, ymin, ymax = bounds if bounds is not None else exposure.full_bounds
    shape = (ymax - ymin + 1, xmax - xmin + 1)
    star_image = np.zeros(shape) if stars else None
    todo, x, y, flux, sizes = plan if plan is not None else plan_objects(cols, optics, (xmin, xmax, ymin, ymax))
    if only is not None:
        todo = todo[np.asarray(only, dtype=bool)[todo]]
    image = np.zeros(shape) if image else None
    ndrawn = len(todo)
    if ndrawn:
        forms = np.full((len(x), 3), np.nan)
        gal = todo[cols["kind"][todo] == "galaxy"]
        if len(gal):
            jac = local_jacobians(optics.wcs, x[gal], y[gal])
            forms[gal] = exponential_forms(jac, np.asarray(cols["hlr"], dtype=np.float64)[gal],
                                           np.asarray(cols["e1"], dtype=np.float64)[gal],
                                           np.asarray(cols["e2"], dtype=np.float64)[gal])
        jobs = [(todo[a:b], x[todo[a:b]], y[todo[a:b]], flux[todo[a:b]], sizes[todo[a:b]], forms[todo[a:b]])
                for a, b in _batches(todo, sizes)]
        context = draw_context(exposure, optics)
        # the PSF table of each stamp size (the costly part of a large stamp) is made once, here, and
        # handed to every worker with the context, rather than remade in each of them
        for n in sorted(set(sizes[todo].tolist())):
            context.drawer._split(int(n))
        batches = imap(draw_batch, jobs, context=context, workers=workers, chunksize=1)
        is_star = cols["kind"] == "star"
        done = 0
        with contextlib.closing(batches):
            for run in batches:
                add_stamp_run(run, image, (xmin, xmax, ymin, ymax), star_image, is_star)
                done += len(run.index)
                if progress is not None:
                    progress(done, ndrawn)
    if stars:
        return image, ndrawn, optics, star_image
    return image, ndrawn, optics
