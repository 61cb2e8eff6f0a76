"""Registration results, errors and pose-error metrics shared by NormalFlow and the baselines."""

from __future__ import annotations

from dataclasses import dataclass, fields

import torch

from tactile_slam.geometry.frame import item_slice


class RegistrationError(ValueError):
    """Registration inputs are unusable (NaN/Inf, mismatched sizes or batches, bad init)."""


@dataclass
class RegistrationResult:
    """Per-pair outcome of registering ``B`` reference frames to ``B`` target frames.

    Attributes:
        tar_T_ref: ``(B, 4, 4)`` float64, metres; maps reference-sensor coordinates of a
            static object point into target-sensor coordinates. Always finite: a failed
            pair keeps its last finite estimate (``tz = 0`` when it could not be solved).
        ccs: ``(B,)`` float64 curvature cosine similarity over the shared samples
            (NaN when undefined, or not computed by a baseline).
        scr: ``(B,)`` float64 shared curvature ratio (NaN when undefined or not computed).
        n_shared: ``(B,)`` int64 samples shared by the two contacts at the final pose
            (baselines: inlier correspondences).
        iterations: ``(B,)`` int64 solver iterations taken.
        converged: ``(B,)`` bool, the step fell below the convergence tolerances.
        ok: ``(B,)`` bool, the registration passed every check; failed pairs are reported
            here, never raised.
        conditioning: ``(B,)`` float64 smallest over largest eigenvalue of the final
            normal equations, translations scaled by the samples' RMS spread (0 when
            they are not finite; NaN for the baselines). Below ``degenerate_eig`` a
            pair fails; above it, a small value still marks a weakly constrained
            direction (a flat valley of the cost): see docs/registration.md.
    """

    tar_T_ref: torch.Tensor
    ccs: torch.Tensor
    scr: torch.Tensor
    n_shared: torch.Tensor
    iterations: torch.Tensor
    converged: torch.Tensor
    ok: torch.Tensor
    conditioning: torch.Tensor

    def __len__(self) -> int:
        return self.tar_T_ref.shape[0]

    def __getitem__(self, i: int | slice | torch.Tensor) -> "RegistrationResult":
        if isinstance(i, int):
            i = item_slice(i, len(self))
        return RegistrationResult(**{f.name: getattr(self, f.name)[i] for f in fields(self)})

    def clone(self) -> "RegistrationResult":
        """A copy as ordinary tensors (also of a result computed under
        ``torch.inference_mode``, whose tensors cannot be changed in place)."""
        return RegistrationResult(**{f.name: getattr(self, f.name).clone() for f in fields(self)})

    @staticmethod
    def cat(results: list["RegistrationResult"]) -> "RegistrationResult":
        if not results:
            raise RegistrationError("cannot concatenate an empty list of results")
        return RegistrationResult(
            **{f.name: torch.cat([getattr(r, f.name) for r in results]) for f in fields(RegistrationResult)}
        )


class TrackingLost(RuntimeError):
    """A single-pair registration failed its checks; ``result`` holds the details."""

    def __init__(self, result: RegistrationResult):
        self.result = result
        super().__init__(
            "registration failed: "
            f"CCS {float(result.ccs[0]):.3f}, SCR {float(result.scr[0]):.3f}, "
            f"{int(result.n_shared[0])} shared samples, {int(result.iterations[0])} iterations"
        )


def pose_error(est_T: torch.Tensor, true_T: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Geodesic rotation error (degrees) and translation error (mm) between poses.

    Args:
        est_T: ``(B, 4, 4)`` estimated ``a_T_b`` in metres.
        true_T: ``(B, 4, 4)`` true ``a_T_b`` in metres.

    Returns:
        ``(rot_deg (B,), trans_mm (B,))`` float64.
    """
    est_T = est_T.double()
    true_T = true_T.double().to(est_T.device)
    r = est_T[:, :3, :3].transpose(1, 2) @ true_T[:, :3, :3]
    # atan2(sin, cos) of the relative rotation: accurate near 0 and 180 deg
    skew = r - r.transpose(1, 2)
    sin = torch.stack([skew[:, 2, 1], skew[:, 0, 2], skew[:, 1, 0]], -1).norm(dim=-1) / 2.0
    cos = (r.diagonal(dim1=1, dim2=2).sum(-1) - 1.0) / 2.0
    rot = torch.rad2deg(torch.atan2(sin, cos))
    trans = torch.linalg.vector_norm(est_T[:, :3, 3] - true_T[:, :3, 3], dim=-1) * 1000.0
    return rot, trans
