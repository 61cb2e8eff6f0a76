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
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import replace

import torch

from tactile_slam.config import NormalFlowConfig
from tactile_slam.geometry.contact import contact_mask
from tactile_slam.geometry.frame import Frame
from tactile_slam.posegraph import se3
from tactile_slam.registration.normalflow import register
from tactile_slam.registration.result import RegistrationError


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
    b = len(refs)
    if b != len(tars) or ref_T_tar.shape != (b, 4, 4):
        raise RegistrationError(f"need B reference and target frames and (B, 4, 4) poses, got {len(refs)}, "
                                f"{len(tars)} and {tuple(ref_T_tar.shape)}")
    if n_samples is not None and n_samples < 1:
        raise RegistrationError(f"refine n_samples must be >= 1 or None, got {n_samples}")
    if b == 0:
        return ref_T_tar.clone(), torch.zeros(0, dtype=torch.bool)
    ref_T_tar = ref_T_tar.double()
    cfg = replace(config, n_samples=n_samples)
    res = register(Frame.cat(list(refs)), Frame.cat(list(tars)), se3.inverse(ref_T_tar), cfg)
    refined = se3.inverse(res.tar_T_ref.double().cpu())
    ok = res.ok.cpu() & torch.isfinite(refined).all(dim=(1, 2))
    return torch.where(ok[:, None, None], refined, ref_T_tar), ok
