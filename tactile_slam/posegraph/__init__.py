"""Pose graph on SE(3): factors, sparse Levenberg-Marquardt, g2o export."""
