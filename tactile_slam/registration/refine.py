"""Re-measuring loop factors with every contact pixel.

Loop verification runs NormalFlow on the reference's ``n_samples`` (3000) selected
contact pixels (the highest curvature of each cell of the contact): fast, and enough to
accept or refuse a pair. The few loops the back end accepts are worth more work:
NormalFlow from that first measurement over *every* contact pixel
(``PoseGraphConfig.refine_n_samples``) adds the low-curvature pixels, whose normals
carry the contact's overall shape (its tilt) that the texture pixels constrain poorly.
On the loops of the simulated tracking episodes this cut the rotation error of a loop
from 0.38 to 0.14 deg (seed) and from 1.02 to 0.62 deg (shell). Odometry edges are not
re-measured: on the knurled and dice episodes that made the trajectories worse
(docs/posegraph.md has the measurements).

A loop is also measurable the other way round: the target as reference, over *its*
pixels (:func:`refine_both_ways`). The two measurements share no samples, so where they
disagree at least one is off by half of that; where both pass, their midpoint is the
loop's value. At large tilts between the touches (40-53 deg on the long seed scan) one
direction alone was up to 1.75 deg off while the two disagreed by as much
(docs/loops.md, "Loops measured both ways").
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, replace

import torch

from tactile_slam.config import NormalFlowConfig
from tactile_slam.geometry.contact import contact_mask
from tactile_slam.geometry.frame import Frame
from tactile_slam.posegraph import se3
from tactile_slam.registration.normalflow import register
from tactile_slam.registration.result import RegistrationError, pose_error


def pressed_core(frame: Frame, depth_test: tuple[float, float | None, float], percentile_q: float) -> Frame:
    """The frames with their contact narrowed to the pixels that pass the contact depth
    test (:func:`~tactile_slam.geometry.contact.contact_mask` with the contact as its
    region, no further erosion): where the gel follows the object. A contact mask made by
    that test (image input) comes back unchanged; a looser given mask loses its shallow
    rim and the texture valleys the gel does not reach, whose normals do not turn with the
    object (docs/registration.md, "Tilt bias at a loose mask's rim").

    Args:
        frame: ``B`` frames.
        depth_test: ``(threshold_px, fraction, floor_px)`` (:attr:`Config.depth_test`).
        percentile_q: the height percentile of the gel level (``contact.height_percentile``).

    Returns:
        a :class:`Frame` sharing every map but ``contact`` (``(B, H, W)`` bool) and
        ``in_contact``, which is kept.
    """
    threshold, fraction, floor = depth_test
    core, _ = contact_mask(frame.height, frame.contact, threshold, percentile_q, 1, fraction, floor)
    return replace(frame, contact=core)


def _check_edges(refs: Sequence[Frame], tars: Sequence[Frame], ref_T_tar: torch.Tensor,
                 n_samples: int | None) -> None:
    """Raise :class:`RegistrationError` unless there are ``B`` frames of each and
    ``(B, 4, 4)`` poses, and ``n_samples`` is ``None`` or positive."""
    b = len(refs)
    if b != len(tars) or ref_T_tar.shape != (b, 4, 4):
        raise RegistrationError(f"need B reference and target frames and (B, 4, 4) poses, got {len(refs)}, "
                                f"{len(tars)} and {tuple(ref_T_tar.shape)}")
    if n_samples is not None and n_samples < 1:
        raise RegistrationError(f"refine n_samples must be >= 1 or None, got {n_samples}")


def _measure(refs: Sequence[Frame], tars: Sequence[Frame], ref_T_tar: torch.Tensor, config: NormalFlowConfig,
             n_samples: int | None) -> tuple[torch.Tensor, torch.Tensor]:
    """NormalFlow's ``(B, 4, 4)`` float64 ``ref_T_tar`` from ``ref_T_tar`` over
    ``n_samples`` reference pixels, whether or not it passed, and ``ok (B,)`` bool: passed
    its checks and finite."""
    cfg = replace(config, n_samples=n_samples)
    res = register(Frame.cat(list(refs)), Frame.cat(list(tars)), se3.inverse(ref_T_tar), cfg)
    measured = se3.inverse(res.tar_T_ref.double().cpu())
    return measured, res.ok.cpu() & torch.isfinite(measured).all(dim=(1, 2))


def refine_edges(refs: Sequence[Frame], tars: Sequence[Frame], ref_T_tar: torch.Tensor,
                 config: NormalFlowConfig, n_samples: int | None = None) -> tuple[torch.Tensor, torch.Tensor]:
    """Re-measure ``B`` relative poses with NormalFlow from their current values.

    Args:
        refs, tars: ``B`` single frames each (``B = 1`` frames; contact sizes may differ).
        ref_T_tar: ``(B, 4, 4)`` float64 measured poses of ``tar`` in ``ref`` (metres).
        config: NormalFlow settings with the thresholds that accepted the edges.
        n_samples: reference samples (``None``: every contact pixel).

    Returns:
        ``(refined (B, 4, 4) float64, ok (B,) bool)``: where the refinement fails its
        checks (or is not finite) the input pose is returned and ``ok`` is False.
    """
    _check_edges(refs, tars, ref_T_tar, n_samples)
    if len(refs) == 0:
        return ref_T_tar.clone(), torch.zeros(0, dtype=torch.bool)
    ref_T_tar = ref_T_tar.double()
    measured, ok = _measure(refs, tars, ref_T_tar, config, n_samples)
    return torch.where(ok[:, None, None], measured, ref_T_tar), ok


@dataclass
class BothWays:
    """A loop re-measured in both directions (:func:`refine_both_ways`); every field is
    ``(B, ...)``.

    Attributes:
        ref_T_tar: ``(B, 4, 4)`` float64 the loops' values: the SE(3) midpoint of the two
            measurements where both pass their checks, the passing one where one does, the
            input where neither does.
        forward: ``(B, 4, 4)`` NormalFlow over the reference's pixels, whether or not it
            passed (:func:`refine_edges` returns the input where it did not).
        reverse: ``(B, 4, 4)`` NormalFlow over the target's pixels, as ``ref_T_tar``.
        forward_ok, reverse_ok: ``(B,)`` bool, which passed their checks.
    """

    ref_T_tar: torch.Tensor
    forward: torch.Tensor
    reverse: torch.Tensor
    forward_ok: torch.Tensor
    reverse_ok: torch.Tensor

    def asymmetry(self) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
        """How far the two measurements disagree, each ``(B,)`` float64: the geodesic angle
        between their rotations and its split into tilt (the angle the sensor axis turns
        by) and twist (about the axis), in degrees, and the distance between their
        translations in mm (as a loop is scored against the truth)."""
        rot, trans = pose_error(self.forward, self.reverse)
        d = se3.inverse(self.forward) @ self.reverse
        return rot, se3.tilt_deg(d), se3.twist_deg(d), trans


def midpoint(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """SE(3) geodesic midpoints ``a Exp(Log(a^-1 b) / 2)`` of ``(B, 4, 4)`` float64 poses."""
    return a @ se3.exp(0.5 * se3.log(se3.inverse(a) @ b))


def refine_both_ways(refs: Sequence[Frame], tars: Sequence[Frame], ref_T_tar: torch.Tensor,
                     config: NormalFlowConfig, n_samples: int | None = None) -> BothWays:
    """Re-measure ``B`` relative poses from their current values in both directions, in one
    NormalFlow batch of ``2B`` pairs: ``tar`` in ``ref`` over the reference's pixels, and
    ``ref`` in ``tar`` over the target's (its inverse compared with the first).

    Args: as :func:`refine_edges`.

    Returns:
        :class:`BothWays`.
    """
    _check_edges(refs, tars, ref_T_tar, n_samples)
    b = len(refs)
    ref_T_tar = ref_T_tar.double()
    if b == 0:
        none = torch.zeros(0, dtype=torch.bool)
        return BothWays(ref_T_tar.clone(), ref_T_tar.clone(), ref_T_tar.clone(), none, none.clone())
    both, ok = _measure([*refs, *tars], [*tars, *refs], torch.cat([ref_T_tar, se3.inverse(ref_T_tar)]), config,
                        n_samples)
    forward, reverse = both[:b], se3.inverse(both[b:])
    f_ok, r_ok = ok[:b], ok[b:]
    one = torch.where(f_ok[:, None, None], forward, torch.where(r_ok[:, None, None], reverse, ref_T_tar))
    value = torch.where((f_ok & r_ok)[:, None, None], midpoint(forward, reverse), one)
    return BothWays(value, forward, reverse, f_ok, r_ok)
