"""``perscli render`` as a function: catalogue + exposure + detector model -> FITS frame.

What a frame holds (:data:`HDU_NAMES`, chosen with ``hdus``): SCI (the frame,
DN after gain), IDEAL (noise-free electrons of sky and sources), FLUENCE (the
charge collected, after saturation: at most the full well), DRAWN (the
noise-free electrons of every object, galaxies and stars, no sky, not
clipped), STARFLU (the same of the stars alone), PERSIST (the persistence
charge from earlier exposures) and MODEL (the detector model).

What persists of an earlier exposure (the persistence effect's ``source``
and ``fluence_cap``, :meth:`perscli.detector.effects.Persistence.fluence_input`):
its DRAWN ('drawn': the light drawn on it, what the paper's pipeline
persisted), its STARFLU ('stars'), its FLUENCE ('all'), or its FLUENCE where
it exceeds a number of electrons (a threshold); the fluence x fed to the law
is then min(x, cap) when a cap is set.  A frame rendered once with DRAWN,
STARFLU and FLUENCE is therefore the history of later frames for every
source, and the persistence is applied when the later frame is rendered
(:func:`persisting_fluence`).

Where the frame lands (:func:`footprint_report`, ``perscli render
--dry-run``): its corners on the sky, its size, and which objects of the
catalogue it covers, without drawing anything.  A frame on which no object
of the catalogue lands is almost always a mistake (the wrong SCA or row, or
a catalogue drawn elsewhere): :func:`render_file` warns, naming where the
frame and the catalogue are, and refuses it with ``strict``.

The frame's FITS layout (its HDUs and their cards) is :mod:`perscli.render.cards`.
"""

from __future__ import annotations

import copy
import dataclasses
import logging
import os

import galsim
import numpy as np

from .. import PerscliError
from ..detector.blocks import NOISE_BLOCK
from ..detector.chain import run_chain
from ..detector.earlier import check_earlier
from ..detector.effects import Persistence
from ..detector.model import DetectorModel
from ..detector.persistence import order_earlier, persistence_charge
from ..io.fitsreader import open_fits
from ..io.frames import SECONDS_PER_DAY, normalize_unit, open_frame
from ..io.output import atomic_output, atomic_path, check_output, write_hdus
from ..io.sources import split_selector
from ..optics import Optics
from ..scene import separation, sky_extent
from ..scene.footprints import objects_on_sca
from .cards import _frame_hdus, _provenance, _source_params
from .exposure import SCA_SIZE, Exposure, draw_sources, plan_objects, read_truth
from .plots import frame_figure
from .settings import DEFAULT_HDUS, HDU_NAMES, LIGHT_HDUS, SOURCE_HDU, RenderOptions

log = logging.getLogger(__name__)


def check_hdus(hdus) -> tuple:
    """The HDUs to write, checked and in :data:`HDU_NAMES` order.

    Parameters
    ----------
    hdus : str or sequence of str or None
        Names (any case), or one comma-separated string ('SCI,FLUENCE');
        None: :data:`DEFAULT_HDUS`.

    Raises
    ------
    PerscliError
        An unknown name, or none at all.
    """
    if hdus is None:
        return DEFAULT_HDUS
    if isinstance(hdus, str):
        hdus = hdus.split(",")
    names = [str(h).strip().upper() for h in hdus if str(h).strip()]
    unknown = [h for h in names if h not in HDU_NAMES]
    if unknown:
        raise PerscliError(f"--hdus: unknown HDU(s) {', '.join(unknown)}; choose from {','.join(HDU_NAMES)}")
    if not names:
        raise PerscliError(f"--hdus: give at least one HDU of {','.join(HDU_NAMES)}")
    return tuple(h for h in HDU_NAMES if h in names)


def with_persistence_source(model: DetectorModel, source) -> DetectorModel:
    """A copy of ``model`` whose persistence effect takes its fluence from ``source``.

    Parameters
    ----------
    model : DetectorModel
        Not changed.
    source : {'drawn', 'stars', 'all'} or float or str
        'drawn', 'stars', 'all', or electrons (a number, or text such as '5e4'):
        the ``source`` parameter of the persistence effect
        (:class:`perscli.detector.effects.Persistence`).  None: ``model`` itself.

    Raises
    ------
    PerscliError
        Not one of those (one line naming persistence.source).
    """
    if source is None:
        return model
    if isinstance(source, str):
        source = source.strip()
        if source.lower() in ("drawn", "all", "stars"):
            source = source.lower()
    value = Persistence.validate({"source": source}, "--persistence-source")["source"]
    model = copy.deepcopy(model)
    eff = model.get("persistence")
    if eff is not None:
        eff.params = {**eff.params, "source": value}
    return model


def open_history(name: str, source: str):
    """Open an earlier exposure (``--previous``) for the persistence it leaves: a frame perscli rendered.

    Parameters
    ----------
    name : str
        The frame: a path (plain, ``.fits.gz`` or tile-compressed, optionally
        with an image section ``[x1:x2,y1:y2]``), '-' for standard input, or
        ``path[EXT]`` naming the image to use, which must then be that HDU.
    source : {'drawn', 'stars', 'all', 'threshold'}
        Which image of it persists (:data:`perscli.render.settings.SOURCE_HDU`):
        DRAWN, STARFLU, or FLUENCE for the others.

    Returns
    -------
    perscli.io.frames.Frame
        Opened on that one image (its science image), with the timing, SCA
        and cutout offsets of its header.

    Raises
    ------
    PerscliError
        The frame has no such extension (one line saying how to render it
        with one), or cannot be read.
    """
    want = SOURCE_HDU[source]
    why = {"DRAWN": "the persistence source is the light drawn on it (the default; --persistence-source drawn): "
                    "render it with DRAWN in --hdus (the default), or choose another --persistence-source",
           "STARFLU": "the persistence source is the stars' light (--persistence-source stars), which needs "
                      "the stars' fluence of every earlier exposure: render it with STARFLU in --hdus, or use "
                      "--persistence-source drawn",
           "FLUENCE": "an earlier exposure leaves persistence through the charge it collected: render it with "
                      "FLUENCE in --hdus (the default)"}[want]

    def missing(label, hdus) -> PerscliError:
        # a table and no image: a catalogue (most likely the truth catalogue) given where a frame belongs
        if not any(h.is_image and h.shape for h in hdus) and any(h.kind == "table" for h in hdus):
            names = ", ".join(h.name or f"HDU {h.index}" for h in hdus if h.kind == "table")
            return PerscliError(f"{label}: is a table ({names}), a catalogue, not a frame: --previous takes an "
                                f"earlier exposure perscli rendered (with {want})")
        return PerscliError(f"{label}: no {want} extension: {why}")

    if name == "-":
        # standard input is read once: the whole frame, then its extension by name
        frame = open_frame(name)
        found = [h.index for h in frame.hdus if h.name == want and h.is_image and h.shape]
        if not found:
            frame.close()
            raise missing("stdin", frame.hdus)

        frame.sci, frame.fluence_hdu = found[:1], None
        frame.unit = normalize_unit(frame.hdus[found[0]].header.get("BUNIT", "electron"), f"stdin: {want} BUNIT")
        return frame
    path, ext, sec = split_selector(name)
    target = name if ext is not None else (f"{path}[{want}]" + (f"[{sec}]" if sec else ""))
    try:
        frame = open_frame(target)
    except PerscliError:
        if ext is not None:
            raise
        with open_fits(path) as probe:          # why it failed: most often, no such extension
            if not any(h.name == want for h in probe.hdus):
                raise missing(path, probe.hdus) from None
        raise
    used = frame.hdus[frame.sci[0]].name
    if used != want:
        frame.close()
        raise PerscliError(f"{name}: names the {used or 'primary'} HDU, but the persistence of an earlier exposure "
                           f"comes from its {want} ({why.split(':')[0]})")
    frame.name = path if ext is None and sec is None else name
    return frame


def persisting_fluence(fluence: np.ndarray, scale: float = 1.0, *, threshold: float | None = None,
                       cap: float | None = None, floor: float = 0.0, out: np.ndarray | None = None) -> np.ndarray:
    """What of an earlier exposure's fluence enters the persistence law.

    Parameters
    ----------
    fluence : ndarray
        The earlier exposure's FLUENCE or STARFLU (times ``scale``: electrons).
    scale : float
    threshold : float, optional
        Electrons: pixels at or below it leave nothing (the 'threshold' source).
    cap : float, optional
        Electrons: larger values count as this (the fluence cap, e.g. the full well).
    floor : float
        Electrons: pixels at or below it leave nothing (the persistence effect's
        ``floor``: how far faint light persists); 0 (the default) changes nothing.
    out : ndarray, optional
        Scratch of ``fluence``'s shape and type to write into when anything
        changes (a whole frame freshly allocated costs as much as the rest).

    Returns
    -------
    ndarray
        Same dtype and scale as ``fluence``; ``fluence`` itself when nothing changes
        (so that the default path is the bytes it always was).
    """
    result = fluence
    zero = fluence.dtype.type(0)
    with np.errstate(invalid="ignore"):
        for level in (floor or None, threshold):
            if level is not None:
                keep = result * scale > level
                if out is None:
                    result = np.where(keep, result, zero)
                else:
                    np.copyto(out, result)
                    np.putmask(out, ~keep, zero)
                    result = out
        if cap is not None and np.nanmax(result) * scale > cap:
            # in the image's own type: a float64 copy of a whole frame costs more than the rest together
            result = np.minimum(result, fluence.dtype.type(cap / scale), out=out)
    return result


# -- where the frame lands ------------------------------------------------------------------------

def footprint_report(truth: str, exposure: Exposure, *, cols=None, optics: Optics | None = None,
                     columns=None) -> dict:
    """Where an exposure's frame lands on the sky and which catalogue objects it covers; nothing is drawn.

    Parameters
    ----------
    truth : str
        The truth catalogue (``perscli catalog``), read and checked as
        :func:`render_file` reads it.
    exposure : Exposure
        With its ``bounds`` (the frame: a cutout or the whole SCA).
    cols, optics : optional
        :func:`read_truth` of ``truth`` and the exposure's :class:`Optics`, when already made.

    Returns
    -------
    dict
        ``bounds``; ``corners``: [(x, y, ra, dec)] of the frame's outer pixel
        edges (xmin-0.5, ymin-0.5), (xmax+0.5, ymin-0.5), (xmax+0.5, ymax+0.5),
        (xmin-0.5, ymax+0.5) through GalSim's WCS; ``centre``: (x, y, ra, dec)
        of the frame's centre; ``size_arcsec``: its width and height along x
        and y; ``catalog``: the catalogue's (ra, dec, radius) extent, its
        number of objects and of stars and galaxies; ``on_frame``: indices
        (into the catalogue) of the objects whose centre lands on the frame,
        with ``x``, ``y`` their pixel positions; ``drawn``: indices of the
        objects whose stamps reach the frame (what render draws, NOBJ);
        ``separation``: degrees from the frame's centre to the catalogue's.
    """
    cols = cols if cols is not None else read_truth(truth, exposure.filter, columns=columns)
    optics = optics if optics is not None else Optics(exposure)
    xmin, xmax, ymin, ymax = exposure.full_bounds
    xs = [xmin - 0.5, xmax + 0.5, xmax + 0.5, xmin - 0.5]
    ys = [ymin - 0.5, ymin - 0.5, ymax + 0.5, ymax + 0.5]
    cra, cdec = optics.wcs.xyToradec(np.array(xs), np.array(ys), units="deg")
    xc, yc = (xmin + xmax) / 2.0, (ymin + ymax) / 2.0
    centre = optics.wcs.toWorld(galsim.PositionD(xc, yc))
    centre = (xc, yc, centre.ra / galsim.degrees % 360.0, centre.dec / galsim.degrees)
    x, y = optics.positions(cols["ra"], cols["dec"])
    on = np.flatnonzero(objects_on_sca(x, y, exposure.full_bounds))
    drawn = plan_objects(cols, optics, exposure.full_bounds)[0]
    extent = sky_extent(cols["ra"], cols["dec"])
    width = float(separation(cra[0], cdec[0], cra[1], cdec[1])) * 3600.0
    height = float(separation(cra[1], cdec[1], cra[2], cdec[2])) * 3600.0
    is_star = cols["kind"] == "star"
    return {
        "truth": truth, "exposure": exposure, "bounds": (xmin, xmax, ymin, ymax),
        "corners": [(xs[i], ys[i], float(cra[i]) % 360.0, float(cdec[i])) for i in range(4)],
        "centre": centre, "size_arcsec": (width, height),
        "catalog": {"ra": extent[0], "dec": extent[1], "radius": extent[2], "n": len(cols["ra"]),
                    "stars": int(np.count_nonzero(is_star)), "galaxies": int(np.count_nonzero(~is_star))},
        "on_frame": on, "x": x, "y": y, "drawn": drawn,
        "on_stars": int(np.count_nonzero(is_star[on])), "on_galaxies": int(np.count_nonzero(~is_star[on])),
        "separation": float(separation(centre[2], centre[3], extent[0], extent[1])) if len(cols["ra"]) else np.nan,
        "cols": cols,
    }


def _count(n: int, one: str, many: str) -> str:
    return f"{n} {one if n == 1 else many}"


def format_footprint(report: dict, *, source: str = "") -> str:
    """The text of a :func:`footprint_report`, as ``perscli render --dry-run`` prints it (lines of 'key value').

    ``source`` says where the exposure came from (e.g. 'plan.fits row 0').
    """
    e = report["exposure"]
    xmin, xmax, ymin, ymax = report["bounds"]
    cat = report["catalog"]
    xc, yc, rc, dc = report["centre"]
    when = e.date.strftime("%Y-%m-%d %H:%M:%S")
    lines = [
        f"exposure    {source + ', ' if source else ''}expid {e.expid}: MJD {e.mjd:.6f} ({when} UTC), "
        f"{e.filter}, {e.exptime:g} s",
        f"pointing    ra {e.ra:.6f} dec {e.dec:+.6f} pa {e.pa:.3f} (centre of the focal plane; degrees)",
        f"SCA {e.sca:<7d} frame x {xmin}..{xmax}, y {ymin}..{ymax}: {xmax - xmin + 1} x {ymax - ymin + 1} pixels "
        f"({report['size_arcsec'][0]:.1f}\" x {report['size_arcsec'][1]:.1f}\")",
        f"centre      {f'({xc:g}, {yc:g})':<16s} ra {rc:.6f} dec {dc:+.6f}",
    ]
    for k, (x, y, ra, dec) in enumerate(report["corners"]):
        label = "corners" if k == 0 else ""
        lines.append(f"{label:<11s} {f'({x:g}, {y:g})':<16s} ra {ra:.6f} dec {dec:+.6f}")
    name = os.path.basename(str(report["truth"])) if report["truth"] != "-" else "stdin"
    if cat["n"]:
        kinds = f"{_count(cat['stars'], 'star', 'stars')}, {_count(cat['galaxies'], 'galaxy', 'galaxies')}"
        lines.append(f"catalogue   {name}: {_count(cat['n'], 'object', 'objects')} ({kinds}) within "
                     f"{cat['radius']:.4f} deg of ra {cat['ra']:.6f} dec {cat['dec']:+.6f}; the frame's centre is "
                     f"{report['separation']:.4f} deg from it")
    else:
        lines.append(f"catalogue   {name}: no objects")
    on, drawn = report["on_frame"], report["drawn"]
    lines.append(f"on frame    {_count(len(on), 'object', 'objects')} centred on the frame ("
                 f"{_count(report['on_stars'], 'star', 'stars')}, "
                 f"{_count(report['on_galaxies'], 'galaxy', 'galaxies')}); {len(drawn)} drawn (their stamps "
                 "reach the frame)")
    return "\n".join(lines) + "\n"


def write_regions(report: dict, dest: str, *, overwrite: bool = False, stdout=None) -> int:
    """A ds9 region file (fk5, degrees) of the frame's outline and the objects drawn on it.

    The outline is a polygon through the frame's corners; each object whose
    stamp reaches the frame is a circle of its half-light radius (galaxies)
    or a cross (stars), tagged with its kind.  Returns the number of objects.
    """
    e, cols = report["exposure"], report["cols"]
    xmin, xmax, ymin, ymax = report["bounds"]
    corners = ",".join(f"{ra:.8f},{dec:+.8f}" for _, _, ra, dec in report["corners"])
    lines = ["# Region file format: DS9 version 4.1",
             f"# perscli render --dry-run: SCA {e.sca} frame x {xmin}..{xmax} y {ymin}..{ymax}, expid {e.expid}, "
             f"MJD {e.mjd:.6f}, {e.filter}; objects of {report['truth']} drawn on it",
             'global color=green font="helvetica 10 normal roman"',
             "fk5",
             f"polygon({corners}) # color=cyan text={{SCA {e.sca}}}"]
    for i in report["drawn"]:
        ra, dec = float(cols["ra"][i]), float(cols["dec"][i])
        if cols["kind"][i] == "star":
            lines.append(f"point({ra:.8f},{dec:+.8f}) # point=cross color=yellow tag={{star}} text={{{cols['id'][i]}}}")
        else:
            radius = max(float(cols["hlr"][i]), 0.1)
            lines.append(f'circle({ra:.8f},{dec:+.8f},{radius:.3f}") # tag={{galaxy}}')
    with atomic_output(dest, overwrite=overwrite, stdout=stdout) as fh:
        fh.write(("\n".join(lines) + "\n").encode())
    return len(report["drawn"])


def no_objects_message(report: dict, *, dry_run: bool = False) -> str:
    """One short line: no object of the catalogue lands on the frame, where the frame and the catalogue are.

    What to do about it is :func:`no_objects_fix` (the warning's further lines).
    """
    e, cat = report["exposure"], report["catalog"]
    _, _, rc, dc = report["centre"]
    name = "stdin" if report["truth"] == "-" else report["truth"]
    frame = f"this cutout of SCA {e.sca}" if e.bounds else f"SCA {e.sca}"
    where = f"ra {rc:.4f}, dec {dc:+.4f}"
    if cat["n"]:
        return (f"no object of {name} lands on {frame} ({where}), {report['separation']:.3f} deg from the "
                f"catalogue (ra {cat['ra']:.4f}, dec {cat['dec']:+.4f})")
    return f"{name} holds no object: {frame} ({where}) draws nothing"


def no_objects_fix(*, dry_run: bool = False) -> str:
    """The indented lines after :func:`no_objects_message` in its warning: how to find a frame that covers the
    catalogue, or draw a catalogue that covers the frame."""
    return ("\n  to find rows and SCAs that cover it: perscli pointings ... --sca N --footprints --catalog CAT"
            "\n  to draw a catalogue where the SCA lands: perscli catalog --pointings POINTINGS --sca N"
            + ("" if dry_run else "\n  (render --dry-run shows where a frame lands; --strict makes this an error)"))


def simulation_area(bounds) -> tuple:
    """The detector pixels simulated for a frame of ``bounds``: what makes its pixels those of the whole SCA.

    The frame grown by one pixel (interpixel capacitance brings in each
    neighbour's signal) and then out to whole noise blocks
    (:data:`perscli.detector.blocks.NOISE_BLOCK`: Poisson noise is only
    reproducible for a whole block), within the detector.  A cutout is then
    exactly that part of the whole detector's frame (but for the persistence
    of pixels outside it, which its earlier frames do not hold).
    """
    b = NOISE_BLOCK
    xmin, xmax, ymin, ymax = (int(v) for v in bounds)

    def grow(lo, hi):
        lo, hi = max(1, lo - 1), min(SCA_SIZE, hi + 1)
        return max(1, (lo - 1) // b * b + 1), min(SCA_SIZE, (hi - 1) // b * b + b)

    (x0, x1), (y0, y1) = grow(xmin, xmax), grow(ymin, ymax)
    return x0, x1, y0, y1


def crop(image: np.ndarray, area, bounds) -> np.ndarray:
    """The part of ``image`` (covering ``area``) that covers ``bounds``, both (xmin, xmax, ymin, ymax)."""
    return image[bounds[2] - area[2]:bounds[3] - area[2] + 1, bounds[0] - area[0]:bounds[1] - area[0] + 1]


def pad_to(image: np.ndarray | None, bounds, area) -> np.ndarray | None:
    """``image`` (covering ``bounds``) placed in zeros covering ``area``."""
    if image is None or tuple(bounds) == tuple(area):
        return image
    out = np.zeros((area[3] - area[2] + 1, area[1] - area[0] + 1), dtype=image.dtype)
    crop(out, area, bounds)[...] = image
    return out


def crop_result(result, area, bounds):
    """A :class:`~perscli.detector.chain.ChainResult` over ``area`` cut to ``bounds``."""
    if tuple(area) == tuple(bounds):
        return result
    cut = {f: crop(getattr(result, f), area, bounds) for f in ("sci", "ideal", "fluence")}
    if result.persistence is not None:
        cut["persistence"] = crop(result.persistence, area, bounds)
    return dataclasses.replace(result, **cut)


def reaching(plan, bounds) -> np.ndarray:
    """Per catalogue row: whether its stamp (``plan``: :func:`plan_objects`) reaches ``bounds``."""
    todo, x, y, _, sizes = plan
    xmin, xmax, ymin, ymax = bounds
    out = np.zeros(len(x), dtype=bool)
    half = sizes[todo] / 2 + 1
    xt, yt = x[todo], y[todo]
    out[todo] = (xt + half >= xmin) & (xt - half <= xmax) & (yt + half >= ymin) & (yt - half <= ymax)
    return out


def history_persistence(opened, exposure: Exposure, pmodel, *, threshold=None, cap=None, floor=0.0):
    """The persistence charge that earlier frames leave in ``exposure``, on its frame's pixels.

    Parameters
    ----------
    opened : list of perscli.io.frames.Frame
        Earlier frames of the same detector area (:func:`open_history`), checked here.
    exposure : Exposure
    pmodel : perscli.detector.persistence.PersistenceModel
    threshold, cap : float, optional
        See :func:`persisting_fluence`.
    floor : float
        Electrons: pixels of an earlier frame at or below it leave nothing (0: every positive pixel).

    Returns
    -------
    (ndarray, list of float)
        Electrons per pixel, and the delays (s) after the earlier exposures used.
    """
    charges, gaps = history_persistences(opened, exposure, {"": (pmodel, threshold, cap, floor)})
    return charges[""], gaps


#: earlier frames' fluence kept by :func:`history_persistences` for the next exposure (a study's worker
#: renders the finals of one detector one after the other: each shares all but one earlier exposure
#: with the one before): (path, size, mtime) -> (array, scale)
_FLUENCE_CACHE: dict = {}
_FLUENCE_CACHE_SIZE = 12


def _fluence_of(frame):
    """An earlier frame's fluence and scale, read and its checksum verified once per process and file."""
    key = None
    name = getattr(frame, "name", None)
    if name and name != "-" and os.path.isfile(name):
        st = os.stat(name)
        key = (os.path.realpath(name), frame.fluence_source, st.st_size, st.st_mtime_ns)
        if key in _FLUENCE_CACHE:
            _FLUENCE_CACHE[key] = _FLUENCE_CACHE.pop(key)       # most recently used last
            return _FLUENCE_CACHE[key]
    value = frame.fluence()
    frame.verify(frame.fluence_source)
    if key is not None:
        _FLUENCE_CACHE[key] = value
        while len(_FLUENCE_CACHE) > _FLUENCE_CACHE_SIZE:
            _FLUENCE_CACHE.pop(next(iter(_FLUENCE_CACHE)))
    return value


def history_persistences(opened, exposure: Exposure, laws: dict):
    """:func:`history_persistence` for several laws, each earlier frame read once.

    Parameters
    ----------
    laws : dict
        Name -> (PersistenceModel, threshold, cap, floor).

    Returns
    -------
    (dict, list of float)
        Name -> electrons per pixel, and the delays (s) after the earlier
        exposures the first law uses.
    """
    xmin, xmax, ymin, ymax = exposure.full_bounds
    shape = (ymax - ymin + 1, xmax - xmin + 1)
    for frame in opened:
        check_earlier(frame, label="the exposure being rendered", shape=shape, detector=exposure.sca,
                      offsets=(1 - xmin, 1 - ymin), start=exposure.mjd)
    # seconds from the start of this exposure (negative: before it), differenced in MJD first as
    # apply-persistence does, so that both give the same bits
    start = 0.0
    ends = [(frame.end - exposure.mjd) * SECONDS_PER_DAY for frame in opened]
    gaps = None
    for pmodel, *_ in laws.values():
        keep, _ = order_earlier(ends, start, pmodel, [f.label for f in opened])
        gaps = [start - ends[i] for i in keep] if gaps is None else gaps
    read = [_fluence_of(frame) for frame in opened]
    # the window from the header times, as for any frame read from a file
    window = (exposure.end - exposure.mjd) * SECONDS_PER_DAY
    charges = {}
    for name, (pmodel, threshold, cap, floor) in laws.items():
        fluences = [(persisting_fluence(f, scale, threshold=threshold, cap=cap, floor=floor), scale)
                    for f, scale in read]
        charges[name] = persistence_charge([f for f, _ in fluences], ends, start, window, pmodel,
                                           scales=[scale for _, scale in fluences])[0]
    return charges, gaps or []


def render_file(truth: str, exposure: Exposure, dest: str, options: RenderOptions | None = None, *,
                model: DetectorModel, seed: int, previous=(), overwrite: bool = False, workers: int = 1,
                progress=None, plot: str | None = None) -> dict:
    """Render ``exposure`` of the truth catalogue ``truth`` and write ``dest``.

    Parameters
    ----------
    truth : str
        FITS truth catalogue (``perscli catalog``).
    exposure : Exposure
        E.g. ``Exposure.from_pointing(schedule_pointing(schedule, row), sca=7)``.
    dest : str
        Output path or '-'.
    options : RenderOptions, optional
        What to write (the HDUs, their compression), what of the earlier
        exposures persists, ``strict`` and the catalogue's column mapping
        (:class:`~perscli.render.settings.RenderOptions`, where their
        defaults are written; None: those defaults).
    model : DetectorModel
        Not changed (``persistence_source`` acts on a copy).
    seed : int
        Seed of every random stream; the same seed gives the same bytes
        (apart from DATE and CHECKSUM), and frames of one exposure rendered
        with and without persistence, whatever its source, share their noise.
    previous : sequence of str
        Earlier exposures of the same SCA area: frames perscli rendered, with
        FLUENCE (or STARFLU for the 'stars' source), see :func:`open_history`.
    overwrite, workers, progress
        As for every command.
    plot : str, optional
        Also write a PNG of the frame and its persistence.

    Returns
    -------
    dict
        Summary: objects drawn, sky rate, units, persistence maximum, the HDUs
        written and the persistence source.

    Raises
    ------
    PerscliError
        Bad inputs, an exposure GalSim cannot make (one line naming the fix),
        or with ``strict`` a frame without objects.  Nothing is written.
    """
    o = options if options is not None else RenderOptions()
    hdus = _checked_outputs(truth, dest, previous, o.hdus, plot=plot, overwrite=overwrite)
    model = with_persistence_source(model, o.persistence_source)
    source, threshold, cap = Persistence.fluence_input(model)
    cols = read_truth(truth, exposure.filter, columns=o.columns)
    optics = Optics(exposure)
    # what only the drawn light needs (the history of later frames): the objects drawn on the frame, no sky,
    # no detector
    light_only = set(hdus) <= {*LIGHT_HDUS, "MODEL"}
    area = exposure.full_bounds if light_only else simulation_area(exposure.full_bounds)
    plan = plan_objects(cols, optics, area)
    on_frame = _objects_on_frame(truth, exposure, cols, optics, plan, strict=o.strict)
    opened = _open_previous(previous, model, source, light_only=light_only, hdus=hdus)
    try:
        drawn = _render_frame(cols, exposure, model, optics, plan, area, on_frame, opened, hdus=hdus,
                              light_only=light_only, seed=seed, threshold=threshold, cap=cap, workers=workers,
                              progress=progress)
        source_params = _source_params(source, threshold, cap)
        out = _frame_hdus(drawn, exposure, model, seed, hdus, source_params)
        _provenance(out[0], truth, cols["datasum"], exposure, model, seed, opened, drawn.gaps,
                    source_params if opened else {}, drawn.sky_rate, drawn.nobj, hdus)
        write_hdus(out, dest, overwrite=overwrite, compress=o.compress)
        if plot:
            with atomic_path(plot, overwrite=overwrite, suffix=".part.png") as tmp:
                frame_figure(drawn.result.sci, tmp, persist=drawn.result.persistence, unit=drawn.result.unit,
                             title=f"SCA {exposure.sca} {exposure.filter} MJD {exposure.mjd:.5f} seed {seed}")
        persist = drawn.result.persistence if drawn.result is not None else None
        return {"objects": drawn.nobj, "sky_rate": drawn.sky_rate, "unit": drawn.unit,
                "persistence_max": float(np.nanmax(persist)) if persist is not None else 0.0,
                "hdus": tuple(h.extname for h in out[1:]),
                "persistence_source": "threshold" if source == "threshold" else source,
                "persistence_threshold": threshold, "fluence_cap": cap}
    finally:
        for frame in opened:
            frame.close()


def _checked_outputs(truth: str, dest: str, previous, hdus, *, plot, overwrite: bool) -> tuple:
    """Check :func:`render_file`'s outputs (the frame, the figure) and the HDUs asked for (:func:`check_hdus`)."""
    check_output(dest, overwrite=overwrite, inputs=[truth, *previous])
    if plot:
        check_output(plot, overwrite=overwrite, inputs=[truth, *previous])
        if dest != "-" and os.path.abspath(plot) == os.path.abspath(dest):
            raise PerscliError(f"{plot}: --plot and -o name the same file: choose another name for the figure")
    return check_hdus(hdus)


def _objects_on_frame(truth: str, exposure: Exposure, cols, optics, plan, *, strict: bool) -> np.ndarray:
    """Per catalogue row: whether its stamp reaches the frame (:func:`reaching`).

    A frame that no object reaches is warned of (where the frame and the
    catalogue are, and how to fix it), or refused with ``strict``.
    """
    on_frame = reaching(plan, exposure.full_bounds)
    if not on_frame.any():
        message = no_objects_message(footprint_report(truth, exposure, cols=cols, optics=optics))
        if strict:
            raise PerscliError("--strict: " + message)
        # short lines rather than one of 600 characters: what, then how to fix it
        log.warning("%s%s", message, no_objects_fix())
    return on_frame


def _open_previous(previous, model: DetectorModel, source: str, *, light_only: bool, hdus) -> list:
    """The earlier frames whose persistence falls on the frame (:func:`open_history`), open.

    None when the persistence effect is off or only the drawn light is
    written (with a note); the frames opened are closed again if one fails.
    """
    previous = list(previous)
    if previous and not model.enabled("persistence"):
        log.warning("--previous given but the persistence effect is off in the detector model: ignored")
    if previous and light_only:
        log.info("--previous not needed: only the drawn light (%s) is written", ",".join(h for h in hdus if h != "MODEL"))
    opened = []
    try:
        for name in previous if model.enabled("persistence") and not light_only else []:
            opened.append(open_history(name, source))
    except BaseException:
        for frame in opened:
            frame.close()
        raise
    return opened


@dataclasses.dataclass
class _Drawn:
    """A frame as :func:`_render_frame` made it, on the frame's pixels."""

    result: object                  # ChainResult of the detector chain; None when only the drawn light is written
    drawn_light: np.ndarray | None  # DRAWN: every object's light, float32 (when asked for)
    star_light: np.ndarray | None   # STARFLU: the stars' light (when asked for)
    optics: Optics                  # as draw_sources returned it
    nobj: int                       # objects drawn on the frame
    gaps: list                      # [s] delays after the earlier exposures used

    @property
    def sky_rate(self):
        return self.result.sky_rate if self.result is not None else None

    @property
    def unit(self) -> str:
        return self.result.unit if self.result is not None else "electron"


def _render_frame(cols, exposure: Exposure, model: DetectorModel, optics, plan, area, on_frame, opened, *, hdus,
                  light_only: bool, seed: int, threshold, cap, workers: int = 1, progress=None) -> _Drawn:
    """Draw the objects over ``area`` and run the detector chain (persistence of ``opened`` included).

    Parameters
    ----------
    cols, plan, area, on_frame
        The catalogue, its stamps (:func:`plan_objects`), the pixels
        simulated (:func:`simulation_area`) and the rows on the frame.
    opened : list of Frame
        Earlier frames (:func:`_open_previous`).
    hdus, light_only
        The HDUs asked for; whether they are only drawn light (no chain).
    threshold, cap
        What of the earlier frames persists (:func:`persisting_fluence`).

    Returns
    -------
    _Drawn
    """
    stars_only = set(hdus) <= {"STARFLU", "MODEL"}
    is_star = cols["kind"] == "star"
    drawn = draw_sources(cols, exposure, workers=workers, progress=progress, stars="STARFLU" in hdus,
                         optics=optics, plan=plan, bounds=area, only=is_star if stars_only else None,
                         image=not stars_only)
    sources, _, optics = drawn[:3]
    star_light = drawn[3] if len(drawn) > 3 else None
    # the light of every object drawn, as the frame's float32: what persists for source drawn
    drawn_light = crop(sources, area, exposure.full_bounds).astype(np.float32) if "DRAWN" in hdus else None
    nobj = int(np.count_nonzero(on_frame & is_star)) if stars_only else int(np.count_nonzero(on_frame))
    gaps = []

    def persistence():
        charge, used = history_persistence(opened, exposure, model.persistence_model(), threshold=threshold,
                                           cap=cap, floor=Persistence.floor(model))
        gaps.extend(used)
        return pad_to(charge, exposure.full_bounds, area)

    if light_only:
        result = None
    else:
        result = crop_result(run_chain(sources, model, exptime=exposure.exptime, seed=seed,
                                       sky_rate=optics.sky_rate, persistence=persistence if opened else None,
                                       origin=(area[0], area[2])), area, exposure.full_bounds)
    star_light = None if star_light is None else crop(star_light, area, exposure.full_bounds)
    return _Drawn(result=result, drawn_light=drawn_light, star_light=star_light, optics=optics, nobj=nobj,
                  gaps=gaps)
