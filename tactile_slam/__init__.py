"""tactile-slam: tactile SLAM for GelSight-type sensors in PyTorch."""

__version__ = "0.1.0"
