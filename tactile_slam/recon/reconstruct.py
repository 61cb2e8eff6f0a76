"""End-to-end reconstruction: keyframes + solved poses -> fused mesh + watertight mesh."""

from __future__ import annotations

import time
from collections import Counter
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path

import torch

from tactile_slam.config import Config
from tactile_slam.recon.fusion import ReconError, build_coverage, fuse, merge_surfaces
from tactile_slam.recon.mesh import TriMesh
from tactile_slam.recon.meshing import oriented_points, poisson_mesh
from tactile_slam.tracking.keyframe import Keyframe


@dataclass
class ReconResult:
    """Reconstruction of one connected group, in that group's start frame (metres).

    Attributes:
        fused_mesh: the merged grid mesh of the fused coverage keyframes.
        mesh: the Poisson re-mesh, or ``None`` when ``config.recon.poisson`` is off.
        group: the group label.
        stats: counts and timings (seconds).
    """

    fused_mesh: TriMesh
    mesh: TriMesh | None
    group: int = 0
    stats: dict = field(default_factory=dict)

    def save(self, out_dir: str | Path, render: bool = True) -> dict[str, Path]:
        """Write ``mesh_fused.ply``, ``mesh.ply`` (if any) and ``mesh.png`` (views of the
        final mesh) into ``out_dir``; returns the paths written."""
        from tactile_slam.recon.render import render_views

        out_dir = Path(out_dir)
        paths = {"mesh_fused": self.fused_mesh.save_ply(out_dir / "mesh_fused.ply")}
        if self.mesh is not None:
            paths["mesh"] = self.mesh.save_ply(out_dir / "mesh.ply")
        if render:
            paths["png"] = render_views(self.mesh if self.mesh is not None else self.fused_mesh, out_dir / "mesh.png")
        return paths


def _pose_tensor(keyframes: Sequence[Keyframe], start_T_kf) -> torch.Tensor:
    if isinstance(start_T_kf, Mapping):
        missing = [kf.id for kf in keyframes if kf.id not in start_T_kf]
        if missing:
            raise ReconError(f"no pose for keyframe(s) {missing[:10]}")
        poses = torch.stack([torch.as_tensor(start_T_kf[kf.id], dtype=torch.float64) for kf in keyframes])
    else:
        poses = torch.as_tensor(start_T_kf, dtype=torch.float64)
    if poses.shape != (len(keyframes), 4, 4):
        raise ReconError(f"expected poses of shape ({len(keyframes)}, 4, 4), got {tuple(poses.shape)}")
    if not torch.isfinite(poses).all():
        raise ReconError("poses contain NaN or Inf")
    return poses


def split_groups(
    keyframes: Sequence[Keyframe], groups: Mapping[int, int] | None
) -> dict[int, list[int]]:
    """Keyframe positions per group label, largest group first (ties: first seen)."""
    labels = [0 if groups is None else int(groups[kf.id]) for kf in keyframes]
    order = [g for g, _ in Counter(labels).most_common()]
    return {g: [i for i, lab in enumerate(labels) if lab == g] for g in order}


def reconstruct(
    keyframes: Sequence[Keyframe],
    start_T_kf: Mapping[int, torch.Tensor] | torch.Tensor,
    config: Config,
    groups: Mapping[int, int] | None = None,
    group: int | None = None,
) -> ReconResult:
    """Reconstruct one connected group (the largest by default).

    Args:
        keyframes: keyframes in insertion order.
        start_T_kf: ``(K, 4, 4)`` float64 or ``{id: (4, 4)}``: each keyframe's pose in
            its group's start frame (maps keyframe-sensor coordinates into it), metres.
        config: sensor, coverage and ``recon`` settings.
        groups: keyframe id -> group label (``None``: all one group).
        group: which group to reconstruct (``None``: the one with most keyframes).

    Raises:
        ReconError: no keyframes, fewer than two in contact, bad poses, or an
            unknown group.
    """
    if len(keyframes) == 0:
        raise ReconError("no keyframes to reconstruct: the run produced no contact keyframes")
    poses = _pose_tensor(keyframes, start_T_kf)
    parts = split_groups(keyframes, groups)
    label = next(iter(parts)) if group is None else group
    if label not in parts:
        raise ReconError(f"unknown group {label}; groups are {sorted(parts)}")
    idx = [i for i in parts[label] if keyframes[i].has_contact]
    if len(idx) < 2:
        raise ReconError(
            f"reconstruction needs at least 2 keyframes with contact in group {label}, got {len(idx)}"
        )
    kfs = [keyframes[i] for i in idx]
    grp_poses = poses[idx].to(kfs[0].maps.device)
    stats: dict = {"group": label, "keyframes": len(kfs), "groups": len(parts)}
    t0 = time.perf_counter()
    coverage = build_coverage(kfs, grp_poses, config)
    if not coverage.active:
        raise ReconError(
            f"group {label} has no coverage keyframe: each of its {len(kfs)} contacts has a boundary-weighted "
            f"area below loop.coverage_overlap_mm2 ({config.loop.coverage_overlap_mm2:.3g} mm^2), too small to fuse"
        )
    t1 = time.perf_counter()
    fused = fuse(kfs, grp_poses, config, coverage)
    fused_mesh = merge_surfaces(fused)
    t2 = time.perf_counter()
    stats.update(coverage_keyframes=len(fused), coverage_s=t1 - t0, fusion_s=t2 - t1,
                 fused_vertices=fused_mesh.n_vertices, fused_faces=fused_mesh.n_faces)
    mesh = None
    if config.recon.poisson:
        pts, nrm = oriented_points(fused, config.recon.min_weight)
        del fused  # large scans: release the fused grids before Poisson
        mesh, mstats = poisson_mesh(pts, nrm, config.recon)
        stats.update({f"mesh_{k}": v for k, v in mstats.items()})
        stats["meshing_s"] = time.perf_counter() - t2
    return ReconResult(fused_mesh=fused_mesh, mesh=mesh, group=label, stats=stats)


def reconstruct_groups(
    keyframes: Sequence[Keyframe],
    start_T_kf: Mapping[int, torch.Tensor] | torch.Tensor,
    config: Config,
    groups: Mapping[int, int],
) -> dict[int, ReconResult]:
    """Every group with at least two contact keyframes, each in its own start frame."""
    if len(keyframes) == 0:
        raise ReconError("no keyframes to reconstruct: the run produced no contact keyframes")
    out = {}
    for label, idx in split_groups(keyframes, groups).items():
        if sum(keyframes[i].has_contact for i in idx) >= 2:
            out[label] = reconstruct(keyframes, start_T_kf, config, groups, group=label)
    if not out:
        raise ReconError("no group has at least 2 keyframes with contact")
    return out
