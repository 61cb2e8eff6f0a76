"""Pairwise registration: NormalFlow and the ICP / FPFH baselines (``registration.baselines``)."""

from tactile_slam.registration.normalflow import (
    PreparedReference,
    normalflow,
    prepare_reference,
    register,
    register_pair,
    register_prepared,
)
from tactile_slam.registration.result import RegistrationError, RegistrationResult, TrackingLost, pose_error

__all__ = [
    "PreparedReference", "RegistrationError", "RegistrationResult", "TrackingLost", "normalflow", "pose_error",
    "prepare_reference", "register", "register_pair", "register_prepared",
]
