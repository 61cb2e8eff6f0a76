"""Incremental, cheap preview of the fused surface (for live display).

Each keyframe's contact points (subsampled on a pixel stride) are accumulated into a
sparse voxel grid as boundary-weighted sums of position and outward normal, so the
preview is a weighted average per voxel: adding a keyframe costs one sort of the
occupied voxels. Points are kept in keyframe coordinates, so a pose-graph update is
absorbed by :meth:`PreviewSurface.update_poses`, which re-accumulates with the new
poses. Poses are ``start_T_kf`` (keyframe -> start frame), float64 metres.
"""

from __future__ import annotations

from collections.abc import Mapping
from pathlib import Path

import numpy as np
import open3d as o3d
import torch

from tactile_slam.config import Config
from tactile_slam.loop.coverage import boundary_weights, point_map
from tactile_slam.recon.fusion import ReconError
from tactile_slam.recon.meshing import voxel_keys
from tactile_slam.tracking.keyframe import Keyframe


class PreviewSurface:
    """Sparse weighted voxel accumulation of keyframe surfaces.

    Args:
        config: sensor scale.
        voxel_mm: voxel side.
        stride: pixel subsampling of each keyframe (2 keeps a quarter of the points).
        min_weight: voxels with less accumulated boundary weight are not reported.
    """

    def __init__(self, config: Config, voxel_mm: float = 0.1, stride: int = 2, min_weight: float = 0.05):
        if not voxel_mm > 0 or stride < 1:
            raise ReconError(f"preview needs voxel_mm > 0 and stride >= 1, got {voxel_mm}, {stride}")
        self.m_per_px = config.sensor.m_per_px
        self.voxel = voxel_mm / 1000.0
        self.stride = int(stride)
        self.min_weight = float(min_weight)
        self._local: dict[int, tuple[torch.Tensor, torch.Tensor, torch.Tensor]] = {}
        self._poses: dict[int, torch.Tensor] = {}
        self._clear()

    def _clear(self) -> None:
        self._keys = torch.zeros(0, dtype=torch.int64)
        self._psum = torch.zeros(0, 3, dtype=torch.float64)
        self._nsum = torch.zeros(0, 3, dtype=torch.float64)
        self._wsum = torch.zeros(0, dtype=torch.float64)

    def __len__(self) -> int:
        return len(self._local)

    def add(self, keyframe: Keyframe, start_T_kf: torch.Tensor) -> None:
        """Accumulate one keyframe at its pose (a keyframe without contact is ignored)."""
        frame = keyframe.frame
        contact = frame.contact[0].cpu()
        if not bool(contact.any()):
            return
        pose = torch.as_tensor(start_T_kf, dtype=torch.float64).cpu()
        if pose.shape != (4, 4) or not torch.isfinite(pose).all():
            raise ReconError(f"keyframe {keyframe.id}: pose must be a finite (4, 4) matrix")
        sel = torch.zeros_like(contact)
        sel[:: self.stride, :: self.stride] = True
        sel &= contact
        w = boundary_weights(contact[None])[0][sel]
        pts = point_map(frame.height.cpu().float(), self.m_per_px)[0][sel].double()
        nrm = -frame.normals[0].cpu()[sel].double()  # object outward = minus the gel normal
        keep = w > 0
        self._local[keyframe.id] = (pts[keep], nrm[keep], w[keep].double())
        self._poses[keyframe.id] = pose
        self._accumulate(keyframe.id)

    def update_poses(self, poses: Mapping[int, torch.Tensor]) -> None:
        """Replace poses of known keyframes and re-accumulate everything."""
        for kf_id, pose in poses.items():
            if kf_id in self._poses:
                self._poses[kf_id] = torch.as_tensor(pose, dtype=torch.float64).cpu()
        self._clear()
        for kf_id in self._local:
            self._accumulate(kf_id)

    def _accumulate(self, kf_id: int) -> None:
        pts, nrm, w = self._local[kf_id]
        pose = self._poses[kf_id]
        p = pts @ pose[:3, :3].T + pose[:3, 3]
        n = nrm @ pose[:3, :3].T
        keys = voxel_keys(p, self.voxel)
        all_keys = torch.cat([self._keys, keys])
        uniq, inv = torch.unique(all_keys, return_inverse=True)
        m = uniq.shape[0]
        old, new = inv[: self._keys.shape[0]], inv[self._keys.shape[0]:]
        psum = torch.zeros(m, 3, dtype=torch.float64).index_add_(0, old, self._psum).index_add_(0, new, p * w[:, None])
        nsum = torch.zeros(m, 3, dtype=torch.float64).index_add_(0, old, self._nsum).index_add_(0, new, n * w[:, None])
        wsum = torch.zeros(m, dtype=torch.float64).index_add_(0, old, self._wsum).index_add_(0, new, w)
        self._keys, self._psum, self._nsum, self._wsum = uniq, psum, nsum, wsum

    def points(self) -> tuple[torch.Tensor, torch.Tensor]:
        """``(M, 3)`` float64 weighted-mean points (metres, start frame) and ``(M, 3)``
        unit outward normals of voxels with enough weight."""
        ok = self._wsum >= self.min_weight
        p = self._psum[ok] / self._wsum[ok, None]
        n = torch.nn.functional.normalize(self._nsum[ok], dim=1)
        return p, n

    def save_ply(self, path: str | Path) -> Path:
        """Write the preview as an oriented point cloud (binary PLY, metres)."""
        p, n = self.points()
        if p.shape[0] == 0:
            raise ReconError("the preview is empty: no keyframe with contact was added")
        pcd = o3d.geometry.PointCloud()
        pcd.points = o3d.utility.Vector3dVector(p.numpy())
        pcd.normals = o3d.utility.Vector3dVector(n.numpy())
        path = Path(path)
        path.parent.mkdir(parents=True, exist_ok=True)
        if not o3d.io.write_point_cloud(str(path), pcd):
            raise ReconError(f"could not write {path}")
        return path

    def save_png(self, path: str | Path) -> Path:
        """Render the preview points (shaded by normal) from several views."""
        from tactile_slam.recon.render import render_points

        p, n = self.points()
        if p.shape[0] == 0:
            raise ReconError("the preview is empty: no keyframe with contact was added")
        return render_points(np.asarray(p), np.asarray(n), path)
