"""Reconstruction metrics against a ground-truth mesh (method.md section 9.3).

Both meshes are sampled area-uniformly (the same seed for both, so identical meshes give
identical samples); the distance of a sample to the other mesh is its exact distance to
the nearest point of that surface (open3d ``RaycastingScene``), which unlike a
sample-to-sample distance carries no bias from the sampling density.

* Chamfer distance (mm): ``(mean d(A -> B) + mean d(B -> A)) / 2``.
* F-score at each threshold tau: ``2 P R / (P + R)`` with precision ``P`` = fraction of
  reconstruction samples within tau of the ground truth and recall ``R`` = fraction of
  ground-truth samples within tau of the reconstruction.
* Normal consistency: mean ``|n_a . n_b|`` between a sample's triangle normal and the
  normal of the nearest triangle of the other mesh, symmetrised (orientation-free).
* NCD (the paper's "normal cosine distance", a similarity: 1.0 is perfect): touches at
  ``n_touches`` farthest-point (Poisson-disk-like) points of the ground truth, pressed
  ``depth_mm`` along the smoothed surface normal with the same sensor pose for both
  meshes, rendered with :class:`tactile_slam.sim.renderer.GelRenderer`; per touch the
  mean cosine between the gel normals of the two renders over pixels in contact in
  both; NCD is the mean over touches that share at least ``min_pixels`` such pixels.

A reconstruction lives in its first sensor frame ``start``; :func:`recon_report` moves it
into the object frame with the ground-truth ``object_T_start`` and reports the metrics
both for that placement and after a point-to-plane ICP refinement.
"""

from __future__ import annotations

import numpy as np
import open3d as o3d
import torch

from tactile_slam.config import Config
from tactile_slam.geometry.curvature import normals_from_gradients
from tactile_slam.sim.motions import pressed_poses
from tactile_slam.sim.renderer import GelRenderer, RenderConfig
from tactile_slam.sim.surface import SurfaceGuide, farthest_points, sample_surface

THRESHOLDS_MM = (0.1, 0.25, 0.5, 1.0)


class ReconMetricError(ValueError):
    """A mesh given to a reconstruction metric is unusable."""


def _check_mesh(mesh: o3d.geometry.TriangleMesh, name: str) -> None:
    if len(mesh.triangles) == 0:
        raise ReconMetricError(f"{name} mesh has no triangles")
    if not np.isfinite(np.asarray(mesh.vertices)).all():
        raise ReconMetricError(f"{name} mesh has non-finite vertices")


def _scene(mesh: o3d.geometry.TriangleMesh) -> o3d.t.geometry.RaycastingScene:
    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(o3d.t.geometry.TriangleMesh.from_legacy(mesh))
    return scene


def _to_surface(points: np.ndarray, normals: np.ndarray, scene) -> tuple[np.ndarray, np.ndarray]:
    """Distances (m) of ``points`` to the scene's surface and ``|cos|`` to its normals."""
    res = scene.compute_closest_points(o3d.core.Tensor(points.astype(np.float32)))
    closest = res["points"].numpy().astype(np.float64)
    n = res["primitive_normals"].numpy().astype(np.float64)
    return np.linalg.norm(points - closest, axis=1), np.abs(np.sum(normals * n, axis=1))


def surface_metrics(recon: o3d.geometry.TriangleMesh, gt: o3d.geometry.TriangleMesh, n_samples: int = 100_000,
                    seed: int = 0, thresholds_mm: tuple[float, ...] = THRESHOLDS_MM) -> dict:
    """Chamfer distance, F-scores and normal consistency of two meshes in metres.

    Returns:
        ``{"chamfer_mm", "recon_to_gt_mm", "gt_to_recon_mm", "fscore": {tau: {"f",
        "precision", "recall"}}, "normal_consistency"}``.
    """
    _check_mesh(recon, "reconstruction")
    _check_mesh(gt, "ground-truth")
    pa, na = sample_surface(recon, n_samples, np.random.default_rng(seed))
    pb, nb = sample_surface(gt, n_samples, np.random.default_rng(seed))
    d_ab, c_ab = _to_surface(pa, na, _scene(gt))
    d_ba, c_ba = _to_surface(pb, nb, _scene(recon))
    d_ab, d_ba = d_ab * 1000.0, d_ba * 1000.0
    fs = {}
    for tau in thresholds_mm:
        p, r = float((d_ab <= tau).mean()), float((d_ba <= tau).mean())
        fs[f"{tau:g}"] = {"f": 2 * p * r / (p + r) if p + r > 0 else 0.0, "precision": p, "recall": r}
    return {
        "chamfer_mm": float(0.5 * (d_ab.mean() + d_ba.mean())),
        "recon_to_gt_mm": float(d_ab.mean()),
        "gt_to_recon_mm": float(d_ba.mean()),
        "fscore": fs,
        "normal_consistency": float(min(0.5 * (c_ab.mean() + c_ba.mean()), 1.0)),
    }


def touch_poses(gt: o3d.geometry.TriangleMesh, n_touches: int = 100, depth_mm: float = 1.0, seed: int = 0,
                config: Config | None = None, renderer: GelRenderer | None = None) -> np.ndarray:
    """Sensor poses ``object_T_sensor`` ``(n, 4, 4)`` of the NCD touches: farthest-point
    surface points, the gel tangent to the smoothed surface, pressed ``depth_mm``, with
    the sensor x axis along the object's x (or y) axis projected on the gel."""
    rng = np.random.default_rng(seed)
    cand, _ = sample_surface(gt, max(50 * n_touches, 5000), rng)
    pts = cand[farthest_points(cand, n_touches, start=int(rng.integers(len(cand))))]
    points, normals = SurfaceGuide(gt).project(pts)
    renderer = renderer or GelRenderer(gt, config)
    hint = np.broadcast_to([1.0, 0.0, 0.0], points.shape).copy()
    zeros = np.zeros(len(points))
    return pressed_poses(renderer, points, normals, hint, zeros, zeros, zeros, np.full(len(points), depth_mm * 1e-3))


def ncd(recon: o3d.geometry.TriangleMesh, gt: o3d.geometry.TriangleMesh, n_touches: int = 100,
        depth_mm: float = 1.0, seed: int = 0, min_pixels: int = 100, config: Config | None = None,
        render_config: RenderConfig | None = None) -> dict:
    """The paper's NCD between two meshes in the same (object) frame, metres.

    Returns:
        ``{"ncd", "touches", "touches_used", "per_touch" (list, NaN for unused)}``.
    """
    _check_mesh(recon, "reconstruction")
    _check_mesh(gt, "ground-truth")
    config = config or Config()
    r_gt = GelRenderer(gt, config, render_config)
    r_rec = GelRenderer(recon, config, render_config)
    poses = touch_poses(gt, n_touches, depth_mm, seed, config, r_gt)
    per = np.full(len(poses), np.nan)
    for a in range(0, len(poses), 16):
        m_gt, m_rec = r_gt.render(poses[a:a + 16]), r_rec.render(poses[a:a + 16])
        cos = (normals_from_gradients(m_gt.gradients) * normals_from_gradients(m_rec.gradients)).sum(-1)
        both = m_gt.contact & m_rec.contact
        cnt = both.sum(dim=(1, 2))
        mean = (cos * both).sum(dim=(1, 2)) / cnt.clamp_min(1)
        per[a:a + len(cnt)] = torch.where(cnt >= min_pixels, mean, torch.nan).double().numpy()
    used = np.isfinite(per)
    return {"ncd": float(per[used].mean()) if used.any() else float("nan"), "touches": int(len(per)),
            "touches_used": int(used.sum()), "per_touch": per.tolist()}


def icp_refine(recon: o3d.geometry.TriangleMesh, gt: o3d.geometry.TriangleMesh, max_distance_mm: float = 1.0,
               n_samples: int = 50_000, seed: int = 0) -> np.ndarray:
    """Point-to-plane ICP of the reconstruction onto the ground truth (no scale).

    Returns:
        ``(4, 4)`` correction ``gt_T_recon`` (apply it to the reconstruction).
    """
    pa, na = sample_surface(recon, n_samples, np.random.default_rng(seed))
    pb, nb = sample_surface(gt, n_samples, np.random.default_rng(seed + 1))
    src = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(pa))
    src.normals = o3d.utility.Vector3dVector(na)
    dst = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(pb))
    dst.normals = o3d.utility.Vector3dVector(nb)
    res = o3d.pipelines.registration.registration_icp(
        src, dst, max_distance_mm * 1e-3, np.eye(4),
        o3d.pipelines.registration.TransformationEstimationPointToPlane(),
        o3d.pipelines.registration.ICPConvergenceCriteria(max_iteration=50))
    return np.asarray(res.transformation)


def recon_report(recon_in_start: o3d.geometry.TriangleMesh, gt: o3d.geometry.TriangleMesh,
                 object_T_start: np.ndarray, icp: bool = True, n_samples: int = 100_000,
                 n_touches: int = 100, seed: int = 0, config: Config | None = None) -> dict:
    """Metrics of a reconstruction given in its start sensor frame.

    Args:
        recon_in_start: reconstruction in the start frame, metres.
        gt: ground-truth mesh in the object frame, metres.
        object_T_start: ``(4, 4)`` ground-truth pose of the start frame.
        icp: also report the metrics after ICP refinement.

    Returns:
        ``{"gt_pose": {...}, "icp": {..., "correction": 4x4 list}}`` each holding
        :func:`surface_metrics` plus ``"ncd"``.
    """
    placed = o3d.geometry.TriangleMesh(recon_in_start).transform(np.asarray(object_T_start, dtype=np.float64))
    placed.compute_triangle_normals()

    def block(mesh):
        out = surface_metrics(mesh, gt, n_samples, seed)
        out["ncd"] = ncd(mesh, gt, n_touches, seed=seed, config=config)["ncd"]
        return out

    report = {"gt_pose": block(placed)}
    if icp:
        corr = icp_refine(placed, gt, seed=seed)
        refined = o3d.geometry.TriangleMesh(placed).transform(corr)
        report["icp"] = block(refined)
        report["icp"]["correction"] = corr.tolist()
    return report
