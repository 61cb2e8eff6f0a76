"""Reconstruction: keyframe surface fusion and watertight meshing."""
