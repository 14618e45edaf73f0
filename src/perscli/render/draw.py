"""Moved to :mod:`perscli.optics`, the one home of the stamp drawing that render and measure share.

The names stay importable from here for outside callers.
"""

from __future__ import annotations

from ..optics import StampDrawer, _centred_freqs, galaxy_stamp_size, star_stamp_size  # noqa: F401
