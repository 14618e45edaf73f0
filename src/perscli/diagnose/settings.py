"""The settings of ``perscli diagnose``, with their defaults written once.

:class:`DiagnoseOptions` is the one home of how diagnose reads measured frames
and how much of them its fits use: the library
(:func:`perscli.diagnose.report.diagnose`) takes one, the command's options
show and use its defaults, and the likelihoods
(:class:`perscli.diagnose.likelihood.Problem`,
:class:`perscli.diagnose.ramp.RampProblem`) take their default from it.  This
module imports nothing heavy, so that ``--help`` stays fast.
"""

from __future__ import annotations

import dataclasses

from ..settings import setting

#: about this many pixels, over all exposures, in the fits: a stripe of rows in each eighth of the frame
#: where the simulation is brightest (the gaps use every pixel)
DEFAULT_FIT_PIXELS = 1_000_000


@dataclasses.dataclass(frozen=True)
class DiagnoseOptions:
    """How ``perscli diagnose`` reads the measured frames and fits them.

    Attributes
    ----------
    fit_pixels : int
        About this many pixels, over all exposures, are used in the fits (at
        least 1000); the gaps before and after use every pixel.
    gain : float or None
        e-/DN of measured DN frames whose header has no GAIN or CCDGAIN.
    exptime : float or None
        Seconds, for measured frames whose header has no exposure time.
    workers : int
        Threads over the exposures of each likelihood evaluation (the result
        does not depend on it).
    """

    fit_pixels: int = setting(DEFAULT_FIT_PIXELS, "int", "About this many pixels, over all exposures, are used in "
                              "the fits (a stripe of rows in each eighth of the frame, where the simulation is "
                              "brightest); the gaps use every pixel.", lo=1000, metavar="N")
    gain: float | None = None
    exptime: float | None = None
    workers: int = 1
