"""Simulator: procedural objects, gel renderer, motions and episodes with ground truth."""
