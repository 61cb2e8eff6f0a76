"""Point-cloud registration baselines behind NormalFlow's interface (method.md 9.5).

Both run Open3D on clouds built from the contact-masked heights (metres, every contact
pixel) with the gel normals N as point normals; source = reference, target = target,
so the estimated transform is tar_T_ref. They loop over pairs (they are yardsticks,
not the production path).

The result fields NormalFlow computes from curvature do not exist here: ``ccs`` and
``scr`` are NaN, ``iterations`` is -1 (Open3D does not report it), ``converged`` is
True, ``n_shared`` is the final ICP inlier count and ``ok`` means "at least
``min_inliers`` inliers" (the baselines have no failure test of their own).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import open3d as o3d
import torch

from tactile_slam.geometry.frame import Frame
from tactile_slam.registration.result import RegistrationError, RegistrationResult

_reg = o3d.pipelines.registration


@dataclass
class BaselineConfig:
    """Parameters of the public NormalFlow experiment scripts (method.md 9.5)."""

    icp_max_corr_m: float = 0.1  # effectively unbounded
    icp_max_iters: int = 30
    icp_rel_fitness: float = 1e-6
    icp_rel_rmse: float = 1e-6
    fpfh_radius_m: float = 1e-3
    fpfh_max_nn: int = 100
    ransac_corr_m: float = 1e-3
    ransac_n: int = 4
    ransac_edge_ratio: float = 0.9
    ransac_iters: int = 10000
    ransac_confidence: float = 0.99
    min_inliers: int = 10
    seed: int = 0


def contact_cloud(frame: Frame, i: int = 0) -> o3d.geometry.PointCloud:
    """Open3D cloud (metres, float64) of frame ``i``'s contact pixels, normals N.

    Raises :class:`RegistrationError` when the frame has no contact or non-finite maps."""
    h, w = frame.shape
    s = frame.mm_per_px / 1000.0
    mask = frame.contact[i].cpu()
    if not bool(mask.any()):
        raise RegistrationError(f"frame {i} has no contact pixels to build a cloud from")
    r, c = torch.nonzero(mask, as_tuple=True)
    z = frame.height[i].cpu()[r, c].double()
    pts = torch.stack([(c - (w - 1) / 2.0) * s, (r - (h - 1) / 2.0) * s, z * s], dim=1)
    nrm = frame.normals[i].cpu()[r, c].double()
    if not (bool(torch.isfinite(pts).all()) and bool(torch.isfinite(nrm).all())):
        raise RegistrationError(f"frame {i} contains NaN or Inf in its height or normals")
    cloud = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(pts.numpy()))
    cloud.normals = o3d.utility.Vector3dVector(nrm.numpy())
    return cloud


def _icp(src, dst, init: np.ndarray, cfg: BaselineConfig):
    criteria = _reg.ICPConvergenceCriteria(cfg.icp_rel_fitness, cfg.icp_rel_rmse, cfg.icp_max_iters)
    return _reg.registration_icp(src, dst, cfg.icp_max_corr_m, init, _reg.TransformationEstimationPointToPlane(),
                                 criteria)


def _fpfh(cloud, cfg: BaselineConfig):
    param = o3d.geometry.KDTreeSearchParamHybrid(radius=cfg.fpfh_radius_m, max_nn=cfg.fpfh_max_nn)
    return _reg.compute_fpfh_feature(cloud, param)


def _fpfh_ransac_icp(src, dst, init: np.ndarray, cfg: BaselineConfig):
    """Pre-align the target by inv(init), FPFH + feature RANSAC, compose with init, ICP."""
    moved = o3d.geometry.PointCloud(dst).transform(np.linalg.inv(init))
    checkers = [_reg.CorrespondenceCheckerBasedOnEdgeLength(cfg.ransac_edge_ratio),
                _reg.CorrespondenceCheckerBasedOnDistance(cfg.ransac_corr_m)]
    ransac = _reg.registration_ransac_based_on_feature_matching(
        src, moved, _fpfh(src, cfg), _fpfh(moved, cfg), True, cfg.ransac_corr_m,
        _reg.TransformationEstimationPointToPoint(False), cfg.ransac_n, checkers,
        _reg.RANSACConvergenceCriteria(cfg.ransac_iters, cfg.ransac_confidence))
    return _icp(src, dst, init @ ransac.transformation, cfg)


def _run(method, ref: Frame, tar: Frame, init_tar_T_ref: torch.Tensor | None, cfg: BaselineConfig
         ) -> RegistrationResult:
    b = len(tar)
    if len(ref) not in (1, b) or b == 0:
        raise RegistrationError(f"{len(ref)} references cannot be paired with {b} targets")
    init = torch.eye(4, dtype=torch.float64) if init_tar_T_ref is None else init_tar_T_ref.detach().double().cpu()
    init = init.expand(b, 4, 4) if init.ndim == 2 else init
    if init.shape != (b, 4, 4) or not bool(torch.isfinite(init).all()):
        raise RegistrationError(f"init_tar_T_ref must be finite (B, 4, 4) or (4, 4), got {tuple(init.shape)}")
    o3d.utility.random.seed(cfg.seed)
    poses, inliers = [], []
    with o3d.utility.VerbosityContextManager(o3d.utility.VerbosityLevel.Error):
        for i in range(b):
            res = method(contact_cloud(ref, i if len(ref) == b else 0), contact_cloud(tar, i), init[i].numpy(), cfg)
            poses.append(torch.from_numpy(np.array(res.transformation)))
            inliers.append(len(res.correspondence_set))
    n = torch.tensor(inliers, dtype=torch.int64)
    nan = torch.full((b,), float("nan"), dtype=torch.float64)
    dev = tar.device
    return RegistrationResult(
        tar_T_ref=torch.stack(poses).to(dev), ccs=nan.to(dev), scr=nan.clone().to(dev), n_shared=n.to(dev),
        iterations=torch.full((b,), -1, dtype=torch.int64, device=dev),
        converged=torch.ones(b, dtype=torch.bool, device=dev), ok=(n >= cfg.min_inliers).to(dev),
        conditioning=nan.clone().to(dev),
    )


def register_icp(ref: Frame, tar: Frame, init_tar_T_ref: torch.Tensor | None = None,
                 config: BaselineConfig | None = None) -> RegistrationResult:
    """Open3D point-to-plane ICP, ``B`` pairs (or one reference to ``B`` targets).

    Args:
        ref, tar: frames; ``init_tar_T_ref`` ``(B, 4, 4)``/``(4, 4)`` float64 metres.

    Returns:
        tar_T_ref per pair (see the module notes for the other fields).
    """
    return _run(_icp, ref, tar, init_tar_T_ref, config or BaselineConfig())


def register_fpfh(ref: Frame, tar: Frame, init_tar_T_ref: torch.Tensor | None = None,
                  config: BaselineConfig | None = None) -> RegistrationResult:
    """FPFH + RANSAC + point-to-plane ICP (the "FPFH+RI" baseline), same interface."""
    return _run(_fpfh_ransac_icp, ref, tar, init_tar_T_ref, config or BaselineConfig())
