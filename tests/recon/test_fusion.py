"""Fusion of coverage keyframes and grid triangulation (method.md 8.1-8.2)."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest
import torch
from scipy.ndimage import distance_transform_edt
from scipy.spatial.transform import Rotation

from tests.recon.recon_oracle import sphere_keyframes
from tactile_slam.config import Config
from tactile_slam.geometry.frame import FrameBuilder, crop_to_contact
from tactile_slam.recon import ReconError, fuse, merge_surfaces
from tactile_slam.loop.coverage import lookup_bilinear, lookup_nearest, transform_points
from tactile_slam.recon.fusion import (
    contact_box,
    grid_normals,
    keyframe_contact_box,
    project_into_box,
    rows_reaching_box,
)
from tactile_slam.recon.mesh import grid_faces
from tactile_slam.tracking.keyframe import Keyframe

CFG = Config()
S = CFG.sensor.m_per_px
H, W = CFG.sensor.shape


def flat_keyframe(kf_id: int, r0, r1, c0, c1, device="cpu") -> Keyframe:
    contact = torch.zeros(1, H, W, dtype=torch.bool)
    contact[0, r0:r1, c0:c1] = True
    frame = FrameBuilder(CFG).from_gradients(torch.zeros(1, H, W, 2), contact=contact)
    return Keyframe(id=kf_id, session=0, maps=frame.to(device), new_session=False,
                    prev_T_kf=torch.eye(4, dtype=torch.float64))


def shifted(dx_px=0.0, dz_m=0.0) -> torch.Tensor:
    T = torch.eye(4, dtype=torch.float64)
    T[0, 3] = dx_px * S
    T[2, 3] = dz_m
    return T


def weights_np(r0, r1, c0, c1) -> np.ndarray:
    m = np.zeros((H, W), bool)
    m[r0:r1, c0:c1] = True
    d = distance_transform_edt(np.pad(m, 1))[1:-1, 1:-1]
    return 0.5 * (np.tanh(d / (H / 60) - 3) + 1) * m


def test_grid_faces_winding_and_count(device):
    mask = torch.zeros(4, 5, dtype=torch.bool, device=device)
    mask[1:3, 1:4] = True  # 2 x 3 block -> 2 x (1 x 2) quads -> 4 triangles
    f = grid_faces(mask)
    assert f.shape == (4, 3) and f.dtype == torch.int64
    # vertices of the masked pixels, row-major, flat
    rr, cc = torch.nonzero(mask, as_tuple=True)
    v = torch.stack([cc.double(), rr.double(), torch.zeros_like(rr, dtype=torch.float64)], 1)
    n = torch.linalg.cross(v[f[:, 1]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 0]], dim=1)
    torch.testing.assert_close(n, torch.tensor([0.0, 0.0, -1.0], dtype=torch.float64, device=device).expand_as(n))
    assert grid_faces(torch.zeros(3, 3, dtype=torch.bool)).shape == (0, 3)


def test_grid_faces_of_a_stack_match_each_mask_with_offsets():
    """A stack of masks triangulates as each mask alone, indices shifted by the pixel
    counts of the masks before it; no triangle joins two masks (full masks touch the
    border rows and columns, where a flat index would wrap into the next mask)."""
    gen = torch.Generator().manual_seed(0)
    masks = torch.rand(3, 6, 7, generator=gen) > 0.3
    masks[1] = True
    stacked = grid_faces(masks)
    offsets = [0, int(masks[0].sum()), int(masks[:2].sum())]
    each = torch.cat([grid_faces(m) + o for m, o in zip(masks, offsets)])
    assert sorted(map(tuple, stacked.tolist())) == sorted(map(tuple, each.tolist()))
    owner = torch.repeat_interleave(torch.arange(3), masks.reshape(3, -1).sum(1))
    assert (owner[stacked] == owner[stacked[:, :1]]).all()


def test_grid_normals_face_outward(dtype):
    ys, xs = torch.meshgrid(torch.arange(8, dtype=dtype), torch.arange(9, dtype=dtype), indexing="ij")
    pts = torch.stack([xs, ys, 0.5 * xs], -1)  # plane z = x / 2
    n = grid_normals(pts)
    expected = torch.tensor([0.5, 0.0, -1.0], dtype=dtype) / (1.25**0.5)
    torch.testing.assert_close(n, expected.expand_as(n))
    assert n.shape == (8, 9, 3)
    at = torch.tensor([0, 8, 40, 71])  # corners, an inner pixel, the last pixel
    curved = pts.clone()
    curved[..., 2] = 0.1 * xs**2 - 0.05 * ys * xs
    torch.testing.assert_close(grid_normals(curved, at), grid_normals(curved).reshape(-1, 3)[at], atol=0, rtol=0)


def test_fused_point_is_weighted_mean_of_surfaces(device):
    """Two flat keyframes 0.1 mm apart in depth, side by side: each fused point is
    ((W_a + 1e-8) z_a + W_b z_b) / (W_a + 1e-8 + W_b), computed here independently."""
    box = (60, 180, 60, 260)
    kfs = [flat_keyframe(0, *box, device=device), flat_keyframe(1, *box, device=device)]
    poses = torch.stack([shifted(), shifted(dx_px=100, dz_m=1e-4)])
    fused = fuse(kfs, poses, CFG)
    assert [f.id for f in fused] == [0, 1]
    wa = weights_np(*box)
    wb = np.zeros_like(wa)
    wb[:, 100:] = wa[:, :-100]  # b's weights seen at a's pixels (b is 100 px to the right)
    m = wa > 0
    expected = (wb[m] * 1e-4) / (wa[m] + 1e-8 + wb[m])
    got = fused[0].points[:, 2].cpu().numpy()
    np.testing.assert_allclose(got, expected, atol=2e-7)
    assert torch.isfinite(fused[0].points).all() and torch.isfinite(fused[0].normals).all()


def test_gate_blocks_distant_surfaces(device):
    box = (60, 180, 60, 260)
    kfs = [flat_keyframe(0, *box, device=device), flat_keyframe(1, *box, device=device)]
    poses = torch.stack([shifted(), shifted(dx_px=100, dz_m=2e-3)])  # 2 mm deeper
    cfg = Config()
    cfg.recon.fusion_gate_mm = 1.0
    fused = fuse(kfs, poses, cfg)
    assert float(fused[0].points[:, 2].abs().max()) == 0.0
    cfg.recon.fusion_gate_mm = 3.0
    assert float(fuse(kfs, poses, cfg)[0].points[:, 2].abs().max()) > 1e-3
    cfg.recon.fusion_gate_mm = 0.0
    with pytest.raises(ReconError, match="fusion_gate_mm"):
        fuse(kfs, poses, cfg)


def test_merged_mesh_has_no_stacked_sheets(device):
    """Overlapping keyframes contribute each surface point once."""
    box = (40, 200, 40, 280)
    kfs = [flat_keyframe(0, *box, device=device), flat_keyframe(1, *box, device=device)]
    poses = torch.stack([shifted(), shifted(dx_px=120)])
    fused = fuse(kfs, poses, CFG)
    mesh = merge_surfaces(fused)
    union = 160 * (240 + 120)
    assert mesh.n_vertices <= union
    assert mesh.n_vertices >= 0.97 * union
    # no two vertices closer than a fraction of a pixel
    v = mesh.vertices.numpy()
    from scipy.spatial import cKDTree

    d, _ = cKDTree(v).query(v, k=2)
    assert d[:, 1].min() > 0.5 * S
    assert torch.allclose(mesh.normals[:, 2], torch.tensor(-1.0, dtype=torch.float64))


def test_fused_sphere_points_lie_on_sphere():
    cfg = Config()
    kfs, poses = sphere_keyframes(cfg, radius_mm=3.0, depth_mm=0.8, n=12)
    fused = fuse(kfs, poses, cfg)
    pts = torch.cat([f.points for f in fused]).numpy() * 1000
    err = np.abs(np.linalg.norm(pts, axis=1) - 3.0)
    assert err.mean() < 0.01 and err.max() < 0.05
    nrm = torch.cat([f.normals for f in fused]).numpy()
    inner = (nrm * pts / np.linalg.norm(pts, axis=1, keepdims=True)).sum(1)
    assert np.median(inner) > 0.99  # outward normals


def test_cropped_keyframes_fuse_exactly_as_full_ones():
    """The pipeline keeps keyframes cropped to their contact (``Keyframe.compact``) by the
    time it meshes: fusion of the crops equals fusion of the full frames, and their
    contact boxes are read without expanding them."""
    cfg = Config()
    kfs, poses = sphere_keyframes(cfg, radius_mm=3.0, depth_mm=0.8, n=12)
    full = fuse(kfs, poses, cfg)
    cropped = [Keyframe(k.id, k.session, crop_to_contact(k.frame), k.new_session, k.prev_T_kf) for k in kfs]
    assert all(k.maps.box.height.numel() < H * W for k in cropped)  # the crops do drop pixels
    for k, c in zip(kfs, cropped):
        assert torch.equal(keyframe_contact_box(c), contact_box(k.frame.contact[0]))
        assert torch.equal(keyframe_contact_box(k), contact_box(k.frame.contact[0]))
    out = fuse(cropped, poses, cfg)
    assert [f.id for f in out] == [f.id for f in full]
    for a, b in zip(full, out):
        for name in ("mask", "points", "normals", "weights", "owned"):
            assert torch.equal(getattr(a, name), getattr(b, name)), name


def _read(maps: torch.Tensor, cr: torch.Tensor, bilinear: bool) -> torch.Tensor:
    """The coverage map reads on one ``(H, W)`` map at ``(N, 2)`` positions -> ``(N,)``."""
    buf, slots = maps.reshape(1, -1), torch.zeros(1, dtype=torch.int64)
    if bilinear:
        return lookup_bilinear([buf], slots, cr[None], tuple(maps.shape))[0][0]
    return lookup_nearest(buf, slots, cr[None, :, 0], cr[None, :, 1], tuple(maps.shape))[0]


def test_map_reads_match_scipy_interpolation():
    """The reads fusion uses (``coverage.lookup_bilinear`` / ``lookup_nearest``): bilinear with zeros outside the image
    (scipy's grid-constant mode) and the nearest pixel's weight, at positions inside, on
    and beyond the border."""
    from scipy.ndimage import map_coordinates

    rng = np.random.default_rng(1)
    height, weight = rng.normal(size=(2, 7, 9))
    cr = np.concatenate([rng.uniform(-2, 10, size=(300, 2)), [[0, 0], [8, 6], [8.4, 6.4], [-0.6, 3.2]]])
    h_bil = _read(torch.from_numpy(height), torch.from_numpy(cr), True)
    w_bil = _read(torch.from_numpy(weight), torch.from_numpy(cr), True)
    w_near = _read(torch.from_numpy(weight), torch.from_numpy(cr), False)
    coords = cr[:, ::-1].T  # (row, col)
    np.testing.assert_allclose(h_bil, map_coordinates(height, coords, order=1, mode="grid-constant"), atol=1e-12)
    np.testing.assert_allclose(w_bil, map_coordinates(weight, coords, order=1, mode="grid-constant"), atol=1e-12)
    r, c = np.round(cr[:, 1]).astype(int), np.round(cr[:, 0]).astype(int)
    inside = (r >= 0) & (r < 7) & (c >= 0) & (c < 9)
    expected = np.where(inside, weight[r.clip(0, 6), c.clip(0, 8)], 0.0)
    np.testing.assert_array_equal(w_near, expected)


def test_bilinear_reads_inside_the_image_equal_the_general_path():
    """Positions whose four corners are all in the image take a path without clamps or
    in-image tests; it gives the same bits as the general path, which a single
    position beyond the border selects for the same batch."""
    rng = np.random.default_rng(4)
    buf = torch.from_numpy(rng.normal(size=(3, 7 * 9))).float()
    slots = torch.tensor([2, 0])
    cr = torch.from_numpy(np.stack([rng.uniform(0, 7.999, (2, 400)), rng.uniform(0, 5.999, (2, 400))], -1)).float()
    fast = lookup_bilinear([buf, 2 * buf], slots, cr, (7, 9))
    outside = torch.tensor([-0.5, 3.0]).expand(2, 1, 2)
    general = lookup_bilinear([buf, 2 * buf], slots, torch.cat([cr, outside], 1), (7, 9))
    for a, b in zip(fast, general):
        assert torch.equal(a, b[:, :-1])
    from scipy.ndimage import map_coordinates
    expected = map_coordinates(buf[2].double().view(7, 9).numpy(), cr[0].double().numpy()[:, ::-1].T, order=1)
    np.testing.assert_allclose(fast[0][0].double().numpy(), expected, atol=1e-5)


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_surface_reads_of_a_coverage_keyframe_match_scipy(dtype):
    """``CoverageSet.surface_at`` (one pass over the corners for both maps) reads the
    keyframe's stored height and weight maps as scipy interpolates them: bilinear
    height and weight, zeros outside the image, and the weight at the nearest pixel.
    The height is kept within 1 px of the contact box, all that a read with a non-zero
    bilinear weight reaches."""
    from scipy.ndimage import map_coordinates

    from tactile_slam.loop.coverage import CoverageSet

    kf = flat_keyframe(0, 40, 200, 60, 300)
    rng = np.random.default_rng(3)
    kf.maps.height[0] = torch.from_numpy(rng.uniform(-3.0, 0.0, size=(H, W))).float()
    cs = CoverageSet(CFG)
    cs.add(kf, torch.eye(4, dtype=torch.float64))
    height, weight = kf.maps.height[0].double().numpy(), cs.weights(0).double().numpy()
    kept = np.zeros_like(height, dtype=bool)
    kept[39:201, 59:301] = True  # heights are kept within 1 px of the contact box
    height = np.where(kept, height, 0.0)
    assert (weight[~kept] == 0).all()
    cr = np.concatenate([rng.uniform(-3, W + 2, size=(500, 1)), rng.uniform(-3, H + 2, size=(500, 1))], 1)
    cr_t = torch.from_numpy(cr).to(dtype)
    h_bil, w_bil, w_near = cs.surface_at(0, cr_t)
    cr = cr_t.double().numpy()  # the positions as read
    coords = cr[:, ::-1].T  # (row, col)
    tol = 1e-5 if dtype == torch.float32 else 1e-12
    np.testing.assert_allclose(h_bil, map_coordinates(height, coords, order=1, mode="grid-constant"), atol=3 * tol)
    np.testing.assert_allclose(w_bil, map_coordinates(weight, coords, order=1, mode="grid-constant"), atol=tol)
    r, c = np.round(cr[:, 1]).astype(int), np.round(cr[:, 0]).astype(int)
    inside = (r >= 0) & (r < H) & (c >= 0) & (c < W)
    np.testing.assert_array_equal(w_near, np.where(inside, weight[r.clip(0, H - 1), c.clip(0, W - 1)], 0.0))
    assert (w_bil[~inside] == 0).sum() > 0 and (w_near > 0).sum() > 100


def test_box_projection_keeps_every_point_that_can_read_the_box():
    """Points dropped by the box test read 0 from any map that is 0 outside the box."""
    rng = np.random.default_rng(2)
    mask = torch.zeros(H, W, dtype=torch.bool)
    mask[50:90, 100:180] = True
    box = contact_box(mask)
    assert box.tolist() == [100, 179, 50, 89]
    weight = torch.from_numpy(rng.uniform(0.1, 1.0, size=(H, W))) * mask
    pts = torch.from_numpy(np.stack([rng.uniform(-12, 12, 5000) * 1e-3, rng.uniform(-9, 9, 5000) * 1e-3,
                                     rng.uniform(-1, 0, 5000) * 1e-3], 1))
    n_T_t = shifted(dx_px=13.3)
    n_T_t[:3, :3] = torch.from_numpy(Rotation.from_rotvec([0.05, -0.1, 0.6]).as_matrix())
    i, cr = project_into_box(transform_points(n_T_t[None], pts.T.contiguous())[0], box, S, (H, W))
    moved = pts @ n_T_t[:3, :3].T + n_T_t[:3, 3]
    all_cr = torch.stack([moved[:, 0] / S + (W - 1) / 2, moved[:, 1] / S + (H - 1) / 2], 1)
    torch.testing.assert_close(cr, all_cr[i])
    w_bil, w_near = _read(weight, all_cr, True), _read(weight, all_cr, False)
    dropped = torch.ones(len(pts), dtype=torch.bool)
    dropped[i] = False
    assert 0 < len(i) < len(pts)
    assert (w_bil[dropped] == 0).all() and (w_near[dropped] == 0).all()
    assert (w_bil[i] > 0).float().mean() > 0.5


def test_fused_normals_are_central_differences_of_the_fused_grid():
    """Normals computed on the contact box equal those of the whole fused image grid,
    also for a contact that touches the image border."""
    from tactile_slam.loop.coverage import point_map

    box = (0, 120, 0, 200)
    kfs = [flat_keyframe(0, *box), flat_keyframe(1, *box)]
    fused = fuse(kfs, torch.stack([shifted(), shifted(dx_px=100, dz_m=1e-4)]), CFG)
    fk = fused[0]  # keyframe 0 sits at the start frame: its points are in its own frame
    grid = point_map(kfs[0].frame.height, S)[0]
    grid[fk.mask] = fk.points
    expected = grid_normals(grid)[fk.mask]
    assert float(expected[:, 0].abs().max()) > 1e-3  # the fused surface is tilted where the sheets blend
    torch.testing.assert_close(fk.normals, expected, atol=1e-6, rtol=0)


def test_keyframe_contact_box_without_contact_is_an_error():
    cfg = Config()
    k = sphere_keyframes(cfg, radius_mm=3.0, depth_mm=0.8, n=1)[0][0]
    flat = replace(k.frame, contact=torch.zeros_like(k.frame.contact))
    for maps in (flat, crop_to_contact(flat)):
        with pytest.raises(ReconError, match=f"keyframe {k.id} has no contact"):
            keyframe_contact_box(Keyframe(k.id, k.session, maps, k.new_session, k.prev_T_kf))


def test_rows_reaching_box_hold_every_point_the_box_keeps():
    """Over random poses (tilts up to 35 deg, in-plane turns, shifts) and boxes, every
    point of a grid-like cloud that the box projection keeps lies in the returned rows;
    and the bound is useful: far from the box, rows are excluded."""
    rng = np.random.default_rng(5)
    excluded = 0
    for trial in range(60):
        rows_px = rng.integers(0, H, 4000).astype(np.float64)  # pixel centres, as a keyframe's points
        cols_px = rng.integers(0, W, 4000).astype(np.float64)
        flat = trial % 2 == 0  # half the trials: a flat patch and an in-plane move (a tight bound)
        depth = np.zeros(4000) if flat else rng.uniform(-1.5e-3, 0.2e-3, 4000)
        pts = torch.from_numpy(np.stack([(cols_px - (W - 1) / 2) * S, (rows_px - (H - 1) / 2) * S, depth],
                                        0)).float()  # (3, N)
        n_T_t = torch.eye(4, dtype=torch.float64)
        tilt = rng.normal(size=3) * (np.array([0.0, 0.0, 1.5]) if flat else np.array([0.3, 0.3, 1.5]))
        n_T_t[:3, :3] = torch.from_numpy(Rotation.from_rotvec(tilt).as_matrix())
        n_T_t[:3, 3] = torch.from_numpy(rng.uniform(-6e-3, 6e-3, 3) * np.array([1, 1, 0.0 if flat else 0.2]))
        c0, r0 = int(rng.integers(0, W - 40)), int(rng.integers(0, H - 40))
        box = torch.tensor([c0, c0 + int(rng.integers(5, 40)), r0, r0 + int(rng.integers(5, 40))])
        lo, hi = pts.double().min(dim=1).values.tolist(), pts.double().max(dim=1).values.tolist()
        r_lo, r_hi = rows_reaching_box(n_T_t, lo, hi, box.tolist(), S, (H, W))
        i, _ = project_into_box(transform_points(n_T_t[None], pts)[0], box, S, (H, W))
        row_of = rows_px[i.numpy()]
        assert ((row_of >= r_lo) & (row_of <= r_hi)).all(), trial
        excluded += int(((rows_px < r_lo) | (rows_px > r_hi)).sum())
    assert excluded > 0
