"""perscli: image persistence in near-infrared detectors.

The science lives in the subpackages, which follow the data flow:

- :mod:`perscli.io`: reading frames (units, timing, ramps) and writing FITS
  outputs with provenance;
- :mod:`perscli.detector`: detector effects, persistence first.

The command-line interface (:mod:`perscli.cli`) is a thin layer over them.
"""

__version__ = "0.1.0"


class PerscliError(Exception):
    """An error in the user's data or request, reported as one line.

    The message names the file, keyword or value at fault and what would fix
    it; the command line prints it and exits with status 1.
    """
