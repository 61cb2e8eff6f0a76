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

import math
from collections.abc import Sequence
from dataclasses import dataclass

import torch
import torch.nn.functional as F

from tactile_slam.config import Config
from tactile_slam.geometry.frame import contact_bounds, height_and_contact_in
from tactile_slam.geometry.morphology import mask_bounds, window_around
from tactile_slam.loop.coverage import CoverageSet, pixel_coords, point_map, transform_points
from tactile_slam.recon.mesh import TriMesh, grid_faces
from tactile_slam.tracking.keyframe import Keyframe


class ReconError(ValueError):
    """Reconstruction input that cannot give a surface (empty, no contact, bad poses)."""


@dataclass
class FusedKeyframe:
    """The fused surface of one coverage keyframe.

    Attributes:
        id: keyframe id.
        mask: ``(H, W)`` bool eroded contact; the rows below list its pixels row-major.
        points: ``(N, 3)`` float32 fused points in the group's start frame, metres
            (rotated and moved in float64; float32 keeps 10 nm over 0.1 m and halves
            the memory of large scans).
        normals: ``(N, 3)`` float32 outward unit normals in the start frame.
        weights: ``(N,)`` float32 the keyframe's own boundary weights.
        owned: ``(N,)`` bool, the points this keyframe contributes to the merged mesh.
        outward: ``(3,)`` float32 the keyframe's -z axis in the start frame.
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
    cs = CoverageSet(config, device=keyframes[0].maps.device, capacity=len(keyframes))
    for kf, pose in zip(keyframes, start_T_kf):
        cs.add(kf, pose)
    return cs


def grid_normals(points: torch.Tensor, at: torch.Tensor | None = None) -> torch.Tensor:
    """Outward (-z facing) unit normals of a ``(H, W, 3)`` point grid by central
    differences (:func:`torch.gradient`): ``normalize(dP/drow x dP/dcol)``.

    Args:
        points: ``(H, W, 3)``.
        at: ``(N,)`` int64 row-major flat pixel indices where the normals are wanted
            (``None``: every pixel); the cross products and norms run only there.

    Returns:
        ``(N, 3)`` at ``at``, else ``(H, W, 3)``.
    """
    d_row, d_col = torch.gradient(points, dim=(0, 1))
    if at is not None:
        d_row, d_col = d_row.reshape(-1, 3).index_select(0, at), d_col.reshape(-1, 3).index_select(0, at)
    return F.normalize(torch.linalg.cross(d_row, d_col, dim=-1), dim=-1)


def contact_box(contact: torch.Tensor) -> torch.Tensor:
    """Bounding box of a non-empty ``(H, W)`` bool mask: ``(4,)`` int64
    ``(col_min, col_max, row_min, row_max)``, inclusive."""
    r0, r1, c0, c1 = mask_bounds(contact)
    return torch.tensor([c0, c1 - 1, r0, r1 - 1], device=contact.device)


def keyframe_contact_box(keyframe: Keyframe) -> torch.Tensor:
    """:func:`contact_box` of a keyframe's contact in full-image pixels, read from its
    stored maps (a cropped keyframe is not expanded for it)."""
    bounds = contact_bounds(keyframe.maps)
    if bounds is None:
        raise ReconError(f"keyframe {keyframe.id} has no contact")
    r0, r1, c0, c1 = bounds
    return torch.tensor([c0, c1, r0, r1], device=keyframe.maps.device)


def project_into_box(moved: torch.Tensor, box: torch.Tensor, m_per_px: float, shape: tuple[int, int]
                     ) -> tuple[torch.Tensor, torch.Tensor]:
    """Keep keyframe t's points, moved into keyframe n's frame, that have a pixel of n's
    box among their bilinear corners or as their nearest pixel (maps that are 0 outside
    the box read 0 for all others).

    Args:
        moved: ``(R, N)`` with ``R >= 2``: t's points in n's frame, channel-first
            (:func:`~tactile_slam.loop.coverage.transform_points`), metres; rows ``x, y, ...``.
        box: ``(4,)`` from :func:`contact_box`.

    Returns:
        ``(M,)`` int64 indices of the kept points and their ``(M, 2)`` ``(col, row)`` in n.
    """
    col, row = pixel_coords(moved[0], moved[1], m_per_px, shape)
    b = box.tolist()
    i = ((col > b[0] - 1) & (col < b[1] + 1) & (row > b[2] - 1) & (row < b[3] + 1)).nonzero()[:, 0]
    return i, torch.stack([col.index_select(0, i), row.index_select(0, i)], dim=1)


def _interval_dot(coeffs: Sequence[float], lo: Sequence[float], hi: Sequence[float]) -> tuple[float, float]:
    """Range of ``sum_k c_k x_k`` over the box ``lo <= x <= hi``."""
    a = sum(min(c * l, c * h) for c, l, h in zip(coeffs, lo, hi))
    b = sum(max(c * l, c * h) for c, l, h in zip(coeffs, lo, hi))
    return a, b


def rows_reaching_box(n_T_t: torch.Tensor, lo: Sequence[float], hi: Sequence[float], box: Sequence[int],
                      m_per_px: float, shape: tuple[int, int]) -> tuple[int, int]:
    """Pixel rows of keyframe t (full image, inclusive; may lie outside it) that hold
    every point :func:`project_into_box` can keep: a conservative bound by interval
    arithmetic, one pixel wider on every side.

    Args:
        n_T_t: ``(4, 4)`` t -> n, metres.
        lo, hi: bounds of t's points in t's frame (3 floats each, metres).
        box: n's ``(col_min, col_max, row_min, row_max)`` (:func:`contact_box`).
        m_per_px, shape: sensor scale and ``(H, W)``.
    """
    h, w = shape
    T = n_T_t.tolist()
    rot, trans = [row[:3] for row in T[:3]], [row[3] for row in T[:3]]
    z_lo, z_hi = _interval_dot(rot[2], lo, hi)  # n's z of t's points, less n_T_t's z translation
    # where a kept point lies in n's frame, less n_T_t's translation
    n_lo = [(box[0] - 2 - (w - 1) / 2.0) * m_per_px - trans[0], (box[2] - 2 - (h - 1) / 2.0) * m_per_px - trans[1],
            z_lo - m_per_px]
    n_hi = [(box[1] + 2 - (w - 1) / 2.0) * m_per_px - trans[0], (box[3] + 2 - (h - 1) / 2.0) * m_per_px - trans[1],
            z_hi + m_per_px]
    y_lo, y_hi = _interval_dot([rot[0][1], rot[1][1], rot[2][1]], n_lo, n_hi)  # t's y = R^T (p_n - trans)
    return math.floor(y_lo / m_per_px + (h - 1) / 2.0) - 1, math.ceil(y_hi / m_per_px + (h - 1) / 2.0) + 1


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
    boxes = {t: keyframe_contact_box(by_id[t]).to(coverage.device) for t in coverage.active}
    out = []
    for t in coverage.active:
        # t's contact box plus a 1 px margin (the central differences of its normals)
        c0, c1, r0, r1 = boxes[t].tolist()
        rows, cols = window_around((r0, r1, c0, c1), 1, coverage.shape)
        height, sub_mask = (x.to(coverage.device) for x in height_and_contact_in(by_id[t].maps, rows, cols))
        grid = point_map(height.to(torch.float32)[None], s, (rows.start, cols.start), coverage.shape)[0]
        # the contact's pixels in the window, flat and row-major (as over the full image)
        pix = sub_mask.reshape(-1).nonzero()[:, 0]
        p = grid.reshape(-1, 3).index_select(0, pix)  # (N, 3)
        w_t = coverage.weights(t)[rows, cols].reshape(-1).index_select(0, pix)
        pose_t = coverage.pose(t)
        p_t = p.T.contiguous()  # channel-first for the projections
        lo, hi = p.min(dim=0).values.tolist(), p.max(dim=0).values.tolist()
        # the points of window row r are p[starts[r]:starts[r + 1]]
        starts = [0] + torch.cumsum(sub_mask.sum(dim=1), 0).tolist()
        owned = torch.ones(p.shape[0], dtype=torch.bool, device=p.device)
        shift = torch.zeros_like(p)
        total = w_t + 1e-8
        for n in coverage.neighbours(t):
            n_T_t = torch.linalg.solve(coverage.pose(n), pose_t)
            # only t's points that reach n's contact can read a non-zero weight: first
            # the rows that can, then the points whose projection does
            r_lo, r_hi = rows_reaching_box(n_T_t, lo, hi, boxes[n].tolist(), s, coverage.shape)
            a = starts[min(max(r_lo - rows.start, 0), len(starts) - 1)]
            b = starts[min(max(r_hi + 1 - rows.start, 0), len(starts) - 1)]
            if a == b:
                continue
            moved = transform_points(n_T_t[None], p_t[:, a:b])[0]  # (3, b - a) in n's frame
            i, cr = project_into_box(moved, boxes[n], s, coverage.shape)
            h_n, w_n, w_own = coverage.surface_at(n, cr)
            slide = h_n * s - moved[2].index_select(0, i)  # along n's z axis
            i += a
            near = slide.abs() <= gate
            w_n = w_n * near
            shift.index_add_(0, i, (w_n * slide).unsqueeze(1) * n_T_t[2, :3].to(p.dtype))
            total.index_add_(0, i, w_n)
            # Ownership: the keyframe with the larger weight (deeper inside its contact,
            # at its nearest pixel) keeps a shared point; the later keyframe on ties.
            beats = w_own >= w_t[i] if n > t else w_own > w_t[i]
            owned[i[(w_own > 0) & near & beats]] = False
        p = p + shift / total.unsqueeze(1)
        grid.reshape(-1, 3).index_copy_(0, pix, p)
        normals = (grid_normals(grid, pix).double() @ pose_t[:3, :3].T).float()
        points = (p.double() @ pose_t[:3, :3].T + pose_t[:3, 3]).float()
        mask = torch.zeros(coverage.shape, dtype=torch.bool, device=coverage.device)
        mask[rows, cols] = sub_mask
        out.append(FusedKeyframe(id=t, mask=mask, points=points, normals=normals, weights=w_t, owned=owned,
                                 outward=-pose_t[:3, 2].float()))
    return out


def merge_surfaces(fused: Sequence[FusedKeyframe]) -> TriMesh:
    """One mesh from the owned parts of fused keyframes: grid triangles over each
    keyframe's owned pixels (triangulated over its contact box), concatenated in
    keyframe order. Vertex normals are the fused grids' outward normals (central
    differences, the ones Poisson meshing uses). Ownership leaves one sheet per surface
    region (no stacked copies); seams between keyframes are not stitched. Vertices in
    no triangle (isolated owned pixels) are dropped."""
    if not fused:
        raise ReconError("fusion produced no keyframes to merge")
    faces, verts, norms, offset = [], [], [], 0
    for fk in fused:
        r0, r1, c0, c1 = mask_bounds(fk.mask)
        # row-major order within the box is the order of the pixels in the full mask
        keep = torch.zeros((r1 - r0, c1 - c0), dtype=torch.bool, device=fk.mask.device)
        keep[fk.mask[r0:r1, c0:c1]] = fk.owned
        f = grid_faces(keep)  # into this keyframe's owned points
        used = torch.zeros(int(fk.owned.sum()), dtype=torch.bool, device=f.device)
        used[f.reshape(-1)] = True
        faces.append((torch.cumsum(used, 0) - 1 + offset)[f])
        rows = fk.owned.nonzero()[:, 0][used]
        verts.append(fk.points.index_select(0, rows))
        norms.append(fk.normals.index_select(0, rows))
        offset += verts[-1].shape[0]
    f = torch.cat(faces)
    if f.numel() == 0:
        raise ReconError("fusion produced no triangles (contacts too small or fully overlapped)")
    return TriMesh(vertices=torch.cat(verts).cpu().double(), faces=f.cpu(), normals=torch.cat(norms).cpu().double())
