"""Evaluation metrics: tracking errors, loop precision/recall, reconstruction."""
