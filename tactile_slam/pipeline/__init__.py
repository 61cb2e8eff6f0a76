"""Pipelines: own the data loop, progress, timing and the output folder."""
