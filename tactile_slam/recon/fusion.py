"""Boundary-weighted fusion of coverage keyframes and the merged grid mesh (method.md 8.1-8.2).

Each coverage keyframe t keeps its own contact points P (metres, keyframe frame) and
moves each one toward its coverage neighbours' surfaces: P is projected into
neighbour n, n's height is read there (bilinearly) and the point slides along n's z
axis onto it (Q). The fused point is the weighted mean

    ((W_t + 1e-8) P + sum_n w_n Q_n) / (W_t + 1e-8 + sum_n w_n),

with w_n = W_n at the projection, and 0 where |Q_n - P| exceeds the fusion gate
(computed directly as the sliding distance, so it cannot be NaN). Near t's own
boundary W_t is about 0 and the neighbours decide the surface, which removes the
border artefacts of naive pasting.

Overlapping sheets are not stacked: every surface point belongs to the keyframe in
which it lies deepest inside the contact (largest boundary weight, later keyframe on
ties); other keyframes drop their copy of it before triangulation.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import torch
import torch.nn.functional as F

from tactile_slam.config import Config
from tactile_slam.loop.coverage import CoverageSet, pixel_coords, point_map, transform_points
from tactile_slam.recon.mesh import TriMesh, grid_faces, vertex_normals
from tactile_slam.tracking.keyframe import Keyframe


class ReconError(ValueError):
    """Reconstruction input that cannot give a surface (empty, no contact, bad poses)."""


@dataclass
class FusedKeyframe:
    """The fused surface of one coverage keyframe.

    Attributes:
        id: keyframe id.
        mask: ``(H, W)`` bool eroded contact; the rows below list its pixels row-major.
        points: ``(N, 3)`` float64 fused points in the group's start frame, metres.
        normals: ``(N, 3)`` float64 outward unit normals in the start frame.
        weights: ``(N,)`` float32 the keyframe's own boundary weights.
        owned: ``(N,)`` bool, the points this keyframe contributes to the merged mesh.
        outward: ``(3,)`` float64 the keyframe's -z axis in the start frame.
    """

    id: int
    mask: torch.Tensor
    points: torch.Tensor
    normals: torch.Tensor
    weights: torch.Tensor
    owned: torch.Tensor
    outward: torch.Tensor


def build_coverage(keyframes: Sequence[Keyframe], start_T_kf: torch.Tensor, config: Config) -> CoverageSet:
    """A fresh coverage set over one group, in insertion order, with the final poses.

    Args:
        keyframes: the group's keyframes in insertion order.
        start_T_kf: ``(K, 4, 4)`` float64 poses (keyframe -> group start frame), metres.
    """
    cs = CoverageSet(config, device=keyframes[0].frame.device)
    for kf, pose in zip(keyframes, start_T_kf):
        cs.add(kf, pose)
    return cs


def grid_normals(points: torch.Tensor) -> torch.Tensor:
    """Outward (-z facing) unit normals of a ``(H, W, 3)`` point grid by central
    differences: ``normalize(dP/drow x dP/dcol)``."""
    d_row, d_col = torch.gradient(points, dim=(0, 1))
    return F.normalize(torch.linalg.cross(d_row, d_col, dim=-1), dim=-1)


def fuse(
    keyframes: Sequence[Keyframe],
    start_T_kf: torch.Tensor,
    config: Config,
    coverage: CoverageSet | None = None,
) -> list[FusedKeyframe]:
    """Fuse every active coverage keyframe of one group with its coverage neighbours.

    Args:
        keyframes: the group's keyframes in insertion order, each with contact.
        start_T_kf: ``(K, 4, 4)`` float64 poses (keyframe -> start frame), metres.
        config: sensor scale, coverage thresholds and ``recon.fusion_gate_mm``.
        coverage: a coverage set over exactly these keyframes and poses; ``None``
            builds a fresh one (method.md 8.1).

    Returns:
        one :class:`FusedKeyframe` per active coverage keyframe, in insertion order.
    """
    if coverage is None:
        coverage = build_coverage(keyframes, start_T_kf, config)
    by_id = {kf.id: kf for kf in keyframes}
    s = config.sensor.m_per_px
    gate = config.recon.fusion_gate_mm / 1000.0
    if not gate > 0:
        raise ReconError(f"recon.fusion_gate_mm must be > 0, got {config.recon.fusion_gate_mm}")
    out = []
    for t in coverage.active:
        mask = by_id[t].frame.contact[0].to(coverage.device)
        grid = point_map(by_id[t].frame.height.to(coverage.device, torch.float32), s)[0]  # (H, W, 3)
        p = grid[mask]  # (N, 3)
        w_t = coverage.weights(t)[mask]
        pose_t = coverage.pose(t)
        owned = torch.ones(p.shape[0], dtype=torch.bool, device=p.device)
        nbs = coverage.neighbours(t)
        if nbs:
            poses = torch.stack([coverage.pose(n) for n in nbs])
            n_T_t = torch.linalg.solve(poses, pose_t.expand(len(nbs), 4, 4))
            moved = transform_points(n_T_t, p.expand(len(nbs), -1, -1))  # (K, N, 3)
            cr = pixel_coords(moved, s, coverage.shape)
            h_n = coverage.lookup(nbs, cr, heights=True, bilinear=True)
            slide = h_n * s - moved[..., 2]  # (K, N) signed distance along n's z axis
            near = slide.abs() <= gate
            w_n = coverage.lookup(nbs, cr, bilinear=True) * near
            z_n = n_T_t[:, 2, :3].to(p.dtype)  # n's z axis in t's frame, (K, 3)
            shift = torch.einsum("kn,kc->nc", w_n * slide, z_n)
            p = p + shift / (w_t + 1e-8 + w_n.sum(dim=0)).unsqueeze(1)
            # Ownership: the keyframe with the larger weight (deeper inside its contact)
            # keeps a shared point; the later keyframe on ties.
            w_own = coverage.lookup(nbs, cr)
            ids = torch.tensor(nbs, device=p.device).unsqueeze(1)
            beats = (w_own > w_t) | ((w_own == w_t) & (ids > t))
            owned = ~((w_own > 0) & near & beats).any(dim=0)
        grid = grid.clone()
        grid[mask] = p
        normals = grid_normals(grid)[mask].double() @ pose_t[:3, :3].T
        points = p.double() @ pose_t[:3, :3].T + pose_t[:3, 3]
        out.append(FusedKeyframe(id=t, mask=mask, points=points, normals=normals, weights=w_t, owned=owned,
                                 outward=-pose_t[:3, 2]))
    return out


def merge_surfaces(fused: Sequence[FusedKeyframe]) -> TriMesh:
    """One mesh from the owned parts of fused keyframes: grid triangles over each
    keyframe's owned pixels, concatenated, with area-weighted outward vertex normals.
    Ownership leaves one sheet per surface region (no stacked copies); seams between
    keyframes are not stitched."""
    verts, faces = [], []
    offset = 0
    for fk in fused:
        keep = torch.zeros_like(fk.mask)
        keep[fk.mask] = fk.owned
        f = grid_faces(keep)
        if f.numel() == 0:
            continue
        verts.append(fk.points[fk.owned])
        faces.append(f + offset)
        offset += verts[-1].shape[0]
    if not faces:
        raise ReconError("fusion produced no triangles (contacts too small or fully overlapped)")
    v = torch.cat(verts)
    f = torch.cat(faces)
    used = torch.zeros(v.shape[0], dtype=torch.bool, device=v.device)
    used[f.reshape(-1)] = True
    remap = torch.cumsum(used, 0) - 1
    v = v[used]
    f = remap[f]
    return TriMesh(vertices=v.cpu(), faces=f.cpu(), normals=vertex_normals(v, f).cpu())
