"""Tracking: lazy keyframes and sessions on top of NormalFlow."""
