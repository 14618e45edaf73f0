"""Rendering exposures: sources drawn through the optics, then the detector chain."""
