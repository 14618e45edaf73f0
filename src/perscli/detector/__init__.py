"""Detector effects, one home for each (persistence first)."""
