"""Earlier exposures on the current frame's detector: checked, and placed on its pixels.

Persistence stays on the detector that saw the light: an earlier exposure
of another instrument or detector (INSTRUME, SCA/DETECTOR) is refused, and
so is one that does not end before the current exposure starts.

- :func:`check_earlier`: the strict check of callers that need the same
  pixels (render, diagnose): same image shape and subarray offsets;
- :func:`overlap`: where an earlier frame's light-sensitive pixels fall on
  the current frame, through their LTV1/LTV2 (detector pixel = image
  pixel - LTV, FITS 1-indexed), as an :class:`Overlap`, for
  :func:`perscli.detector.apply.plan`.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass

from .. import PerscliError
from ..io.frames import Frame, require_timing


@dataclass(frozen=True)
class Overlap:
    """Where an earlier frame's light-sensitive pixels fall on the current frame.

    Attributes
    ----------
    shift : (int, int)
        ``(dy, dx)``: current pixel ``(y, x)`` is the earlier frame's image
        pixel ``(y + dy, x + dx)`` (0-indexed, both).
    box : (int, int, int, int)
        ``(y0, y1, x0, x1)``: the current frame's pixels (0-indexed,
        half-open) that both frames saw with light-sensitive pixels.
    same_pixels : bool
        Both frames have the same shape, placement and science area: the
        earlier one is streamed row block for row block as it is stored.
    """

    shift: tuple
    box: tuple
    same_pixels: bool


def _detector(frame: Frame):
    return frame.keyword("SCA", frame.keyword("DETECTOR"))


def _check_detector(prev: Frame, label: str, detector, instrument=None) -> None:
    """Refuse an earlier exposure of another instrument or detector."""
    theirs = prev.keyword("INSTRUME")
    if None not in (theirs, instrument) and str(theirs).strip().upper() != str(instrument).strip().upper():
        raise PerscliError(f"{prev.label}: instrument INSTRUME={str(theirs).strip()} differs from {label}'s "
                           f"{str(instrument).strip()}: persistence stays on the detector that saw the light; "
                           "give earlier exposures of the same detector")
    theirs = _detector(prev)
    if None not in (theirs, detector) and str(theirs).strip() != str(detector).strip():
        raise PerscliError(f"{prev.label}: detector SCA/DETECTOR={theirs} differs from "
                           f"{label}'s {detector}: persistence stays on the detector that saw "
                           "the light; give earlier exposures of the same detector")


def check_earlier(prev: Frame, *, label: str, shape: tuple, detector=None, offsets=(None, None),
                  start: float | None = None) -> None:
    """Refuse an earlier exposure that does not cover exactly the pixels of the current one.

    The strict check of callers that need the same pixels (render, diagnose);
    apply-persistence places frames of different areas with :func:`overlap`.

    Parameters
    ----------
    prev : Frame
        The earlier exposure.
    label : str
        The current exposure, for messages.
    shape : tuple
        The current exposure's image shape.
    detector : optional
        Its SCA/DETECTOR keyword, when known.
    offsets : (LTV1, LTV2)
        Its subarray offsets, when known.
    start : float, optional
        Its start (MJD).
    """
    require_timing(prev)
    if prev.shape != tuple(shape):
        raise PerscliError(f"{prev.label}: image shape {prev.shape} differs from {label}'s "
                           f"{tuple(shape)}; earlier exposures must be of the same detector area")
    _check_detector(prev, label, detector)
    mine = (prev.keyword("LTV1"), prev.keyword("LTV2"))
    if None not in mine + tuple(offsets) and tuple(float(v) for v in mine) != tuple(float(v) for v in offsets):
        raise PerscliError(f"{prev.label}: subarray offset LTV1/LTV2={mine} differs from "
                           f"{label}'s {tuple(offsets)}: not the same pixels of the detector")
    _check_start(prev, label, start)


def _check_start(prev: Frame, label: str, start) -> None:
    if start is not None and prev.end > start:
        raise PerscliError(
            f"{prev.label} ends at MJD {prev.end:.8f}, after {label} starts "
            f"(MJD {start:.8f}): it is not an earlier exposure; check the order or the timestamps")


def _footprint(placement) -> str:
    """The detector pixels of a science box, FITS 1-indexed and inclusive, for messages."""
    y0, y1, x0, x1 = placement.science
    dy, dx = placement.offset
    return f"x {x0 + 1 + dx:g}-{x1 + dx:g}, y {y0 + 1 + dy:g}-{y1 + dy:g}"


def overlap(prev: Frame, current: Frame) -> Overlap:
    """Place an earlier frame on the current one through their LTV1/LTV2.

    Parameters
    ----------
    prev, current : Frame

    Returns
    -------
    Overlap

    Raises
    ------
    PerscliError
        Frames of different shapes neither of which has LTV1/LTV2 (where they
        lie cannot be told; when one has them, the other's are taken as 0, the
        FITS default), offsets that are not whole pixels, binned or
        flipped pixels (LTM1_1/LTM2_2 not 1) where the frames differ, and
        frames with no light-sensitive detector pixel in common.
    """
    here, there = current.placement(), prev.placement()
    same_shape = prev.shape == current.shape
    if here.offset is None and there.offset is None:
        if not same_shape:
            raise PerscliError(f"{prev.label}: image shape {prev.shape} differs from {current.label}'s "
                               f"{current.shape} and neither has LTV1/LTV2 to place it on the detector; give "
                               "earlier exposures of the same detector area, or add LTV1/LTV2 (detector pixel = "
                               "image pixel - LTV)")
        # frames of one detector area, as a simulation writes them
        return Overlap((0, 0), here.science, True)
    # one side says where it lies: the other, silent, lies where LTV = 0 puts it (the IRAF/FITS default,
    # which a CFITSIO image section of it also assumes)
    here = here if here.offset is not None else dataclasses.replace(here, offset=(0.0, 0.0), source="no LTV: 0")
    there = there if there.offset is not None else dataclasses.replace(there, offset=(0.0, 0.0), source="no LTV: 0")
    if here.offset == there.offset and same_shape and here.scale == there.scale and here.science == there.science:
        return Overlap((0, 0), here.science, True)
    for frame, placement in ((prev, there), (current, here)):
        if placement.scale != (1.0, 1.0):
            raise PerscliError(f"{frame.label}: LTM1_1/LTM2_2 = {placement.scale[1]:g}/{placement.scale[0]:g}: "
                               "binned or flipped pixels cannot be placed on another frame's; give frames with "
                               "one image pixel per detector pixel")
    shift = tuple(a - b for a, b in zip(here.offset, there.offset))
    if not all(float(v).is_integer() for v in shift):
        raise PerscliError(f"{prev.label}: LTV1/LTV2 put it {shift[1]:g}, {shift[0]:g} pixels from "
                           f"{current.label}: not whole pixels, so no pixel of one is a pixel of the other")
    dy, dx = (int(v) for v in shift)
    cy0, cy1, cx0, cx1 = here.science
    py0, py1, px0, px1 = there.science
    box = (max(cy0, py0 - dy), min(cy1, py1 - dy), max(cx0, px0 - dx), min(cx1, px1 - dx))
    if box[0] >= box[1] or box[2] >= box[3]:
        raise PerscliError(f"{prev.label} covers detector pixels {_footprint(there)} ({there.source}) and "
                           f"{current.label} {_footprint(here)} ({here.source}): no pixel in common, so no "
                           "persistence can flow; give earlier exposures that overlap CURRENT")
    return Overlap((dy, dx), box, False)
