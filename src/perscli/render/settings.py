"""The settings of ``perscli render``, with their defaults written once.

:class:`RenderOptions` is the one home of render's output settings, as
:class:`perscli.stats.settings.CorrelateOptions` is of correlate's: the
library (:func:`perscli.render.run.render_file`) takes one, the command's
options show and use its defaults, and a study's render tasks make one.
What a call renders (the catalogue, the exposure, the detector model, the
seed, the earlier frames) and how it runs (workers, overwriting, a figure)
stay arguments of the call.  This module imports nothing heavy, so that
``perscli render --help`` stays fast.
"""

from __future__ import annotations

import dataclasses

from ..settings import setting

#: the HDUs a rendered frame can hold, in the order they are written
HDU_NAMES = ("SCI", "IDEAL", "FLUENCE", "DRAWN", "STARFLU", "PERSIST", "MODEL")

#: what ``perscli render`` writes unless told otherwise (PERSIST only with earlier exposures).
#: DRAWN among them: a frame rendered with the defaults is the history of later ones under the default
#: persistence source (drawn); STARFLU (the stars' light alone) only when asked
DEFAULT_HDUS = ("SCI", "IDEAL", "FLUENCE", "DRAWN", "PERSIST", "MODEL")

#: the image of an earlier frame that each persistence source reads
#: (:meth:`perscli.detector.effects.Persistence.fluence_input`)
SOURCE_HDU = {"drawn": "DRAWN", "stars": "STARFLU", "all": "FLUENCE", "threshold": "FLUENCE"}

#: the images that need only the objects drawn (no sky, no detector): a frame holding only these is drawn and
#: written without running the detector chain
LIGHT_HDUS = ("DRAWN", "STARFLU")


@dataclasses.dataclass(frozen=True)
class RenderOptions:
    """What ``perscli render`` writes, and from which catalogue columns and earlier light.

    Attributes
    ----------
    hdus : sequence of str or str
        The HDUs to write, among :data:`HDU_NAMES` (a comma-separated string
        too); written in that order, PERSIST only when earlier exposures are
        given.  A frame that is to be the history of later ones needs
        the image its persistence source reads (:data:`SOURCE_HDU`): DRAWN
        for 'drawn', STARFLU for 'stars', FLUENCE for the others.
    compress : {'none', 'gzip', 'rice'}
        Lossless tile compression of the images (a full SCA: ~40% of the
        plain size with gzip).
    persistence_source : {'drawn', 'stars', 'all'} or float or None
        What of the earlier exposures persists (the persistence effect's
        ``source``; None: the detector model's, 'drawn' by default): 'drawn'
        their DRAWN (the light of every object, no sky), 'stars' their
        STARFLU, 'all' their FLUENCE, a number of electrons: only pixels
        whose FLUENCE exceeds it.  The fluence is then capped at the
        effect's ``fluence_cap`` (default: none).
    strict : bool
        No object of the catalogue drawn on the frame is an error (before
        anything is drawn or written) rather than a warning.
    columns : dict or None
        Column mapping {perscli name: file column} of the truth catalogue
        (``--columns``; :func:`perscli.render.exposure.read_truth`).
    """

    hdus: tuple | str = DEFAULT_HDUS
    compress: str = "none"
    persistence_source: str | float | None = None
    strict: bool = setting(False, "flag", "No object of TRUTH.fits on the frame is an error (exit 1, nothing "
                           "written), not a warning.")
    columns: dict | None = None
