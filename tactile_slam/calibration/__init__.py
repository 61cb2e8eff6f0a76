"""Calibration: press labelling, dataset, MLP training and evaluation, model files."""
