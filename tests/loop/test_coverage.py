"""Boundary weights and the coverage set (method.md 6.1) on crafted overlaps."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from scipy.ndimage import distance_transform_edt

from tactile_slam.config import Config, digit
from tactile_slam.geometry.frame import FrameBuilder
from tactile_slam.loop.coverage import (
    CoverageError,
    CoverageSet,
    boundary_weights,
    distance_to_background,
    point_map,
)
from tactile_slam.tracking.keyframe import Keyframe

CFG = Config()
S = CFG.sensor.m_per_px
H, W = CFG.sensor.shape


def rect(r0, r1, c0, c1) -> torch.Tensor:
    m = torch.zeros(H, W, dtype=torch.bool)
    m[r0:r1, c0:c1] = True
    return m


def keyframe(kf_id: int, contact: torch.Tensor, device="cpu") -> Keyframe:
    frame = FrameBuilder(CFG).from_gradients(torch.zeros(1, H, W, 2), contact=contact[None])
    return Keyframe(id=kf_id, session=0, maps=frame.to(device), new_session=kf_id == 0,
                    prev_T_kf=torch.eye(4, dtype=torch.float64))


def pose(dx_px=0.0, dy_px=0.0, dz_m=0.0, flip=False) -> torch.Tensor:
    T = torch.eye(4, dtype=torch.float64)
    if flip:  # 180 degrees about x: z axes oppose
        T[1, 1] = T[2, 2] = -1.0
    T[:3, 3] = torch.tensor([dx_px * S, dy_px * S, dz_m], dtype=torch.float64)
    return T


# ------------------------------------------------------------------ weights


@pytest.mark.parametrize("backend", ["auto", "torch", "cv2"])
def test_distance_matches_scipy_with_border_as_background(device, backend):
    """Both backends (OpenCV's EDT, the separable one in torch) against scipy: random
    holes, a contact against two borders, the clamp, and a frame without contact."""
    g = torch.Generator().manual_seed(1)
    mask = torch.rand(3, 40, 50, generator=g) > 0.05
    mask[1] = False
    mask[1, 5:40, 0:30] = True  # touches the bottom and left borders
    mask[2] = False
    d = distance_to_background(mask.to(device), 1000.0, backend)
    assert d.shape == (3, 40, 50) and d.dtype == torch.float32 and d.device == mask.to(device).device
    d = d.cpu().numpy()
    for i in range(3):
        ref = distance_transform_edt(np.pad(mask[i].numpy(), 1))[1:-1, 1:-1]
        np.testing.assert_allclose(d[i], ref, atol=1e-5)
    clamped = distance_to_background(mask.to(device), 3.0, backend).cpu().numpy()
    ref = np.minimum(distance_transform_edt(np.pad(mask[1].numpy(), 1))[1:-1, 1:-1], 3.0)
    np.testing.assert_allclose(clamped[1], ref, atol=1e-5)
    with pytest.raises(ValueError, match="backend"):
        distance_to_background(mask.to(device), 3.0, "scipy")


def test_distance_backends_agree_to_the_last_bit_and_repeat():
    """OpenCV's square roots can be 1 ulp off and change from call to call (its threads
    split the image differently); the squared distances are integers, so both backends
    return the correctly rounded root: bit-identical, and identical on every call (fusion
    of cropped keyframes must equal that of full ones)."""
    g = torch.Generator().manual_seed(4)
    mask = torch.rand(2, 90, 120, generator=g) > 0.02
    mask[1] = False
    mask[1, 10:80, 20:110] = True
    ref = distance_to_background(mask, 40.0, "torch")
    for _ in range(20):
        assert torch.equal(distance_to_background(mask, 40.0, "cv2"), ref)


def test_boundary_weights_values_and_shapes(device):
    mask = rect(20, 220, 20, 300).to(device)
    w = boundary_weights(torch.stack([mask, ~mask]))
    assert w.shape == (2, H, W) and w.dtype == torch.float32
    scale = H / 60
    d = torch.from_numpy(distance_transform_edt(np.pad(mask.cpu().numpy(), 1))[1:-1, 1:-1]).float()
    ref = 0.5 * (torch.tanh(d / scale - 3) + 1) * mask.cpu()
    torch.testing.assert_close(w[0].cpu(), ref, atol=1e-6, rtol=0)
    # Sample values of method.md 6.1: W(12 px) = 0.5 at 12 px inside the edge.
    assert w[0, 20 + 11, 160].item() == pytest.approx(0.5, abs=1e-6)
    assert w[0, 20, 160].item() == pytest.approx(0.5 * (math.tanh(1 / scale - 3) + 1), abs=1e-6)
    assert float(w[1][mask].abs().max()) == 0.0  # zero outside contact


def test_boundary_weights_bad_length():
    with pytest.raises(CoverageError):
        boundary_weights(rect(0, 10, 0, 10)[None], length=0.0)


def test_point_map_convention(dtype):
    h = torch.zeros(1, H, W, dtype=dtype)
    h[0, 0, 0] = -3.0
    p = point_map(h, S)
    assert p.shape == (1, H, W, 3)
    torch.testing.assert_close(p[0, 0, 0], torch.tensor([-(W - 1) / 2 * S, -(H - 1) / 2 * S, -3 * S]))
    # x grows with columns, y with rows, centre between pixels 159/160 and 119/120
    assert p[0, 0, 160, 0] == pytest.approx(0.5 * S) and p[0, 120, 0, 1] == pytest.approx(0.5 * S)


def test_point_map_of_a_window_is_the_full_maps_window(dtype):
    """A window with its origin and the full image's shape gives exactly the full map's
    points there (the same pixel centres, not the window's own)."""
    h = torch.randn(1, H, W, dtype=dtype)
    full = point_map(h, S)
    win = point_map(h[:, 37:90, 201:260], S, origin=(37, 201), full_shape=(H, W))
    assert torch.equal(win, full[:, 37:90, 201:260])


# ------------------------------------------------------------------ coverage set


def test_threshold_follows_sensor_scale():
    assert CoverageSet(CFG).threshold == pytest.approx(50.0)
    assert CoverageSet(digit()).threshold == pytest.approx(50 * 0.0634**2 / 0.0405**2)


def test_identical_second_keyframe_is_pruned(device):
    cs = CoverageSet(CFG)
    m = rect(40, 200, 60, 260)
    assert cs.add(keyframe(0, m, device), pose())
    assert not cs.add(keyframe(1, m, device), pose())
    assert cs.active == [0] and cs.neighbours(0) == [] and cs.neighbours(1) == []


def test_overlap_value_matches_independent_sum(device):
    cs = CoverageSet(CFG)
    m = rect(40, 200, 60, 260)
    cs.add(keyframe(0, m, device), pose())
    cs.add(keyframe(1, m, device), pose(dx_px=30))
    n0, n1 = cs._nodes[0], cs._nodes[1]
    ov = cs.overlaps(n1, [n0])  # overlap(1 <- 0): 0's points land 30 px left in 1's image
    w = boundary_weights(m[None])[0]
    expected = w[:, 30:][m[:, :-30]].sum()
    assert float(ov[0]) == pytest.approx(float(expected), rel=1e-5)
    assert cs.neighbours(0) == [1] and cs.active == [0, 1]


def test_disjoint_keyframes_are_both_kept(device):
    cs = CoverageSet(CFG)
    m = rect(40, 200, 60, 260)
    cs.add(keyframe(0, m, device), pose())
    cs.add(keyframe(1, m, device), pose(dx_px=400))
    assert cs.active == [0, 1] and cs.neighbours(0) == []


def test_opposed_z_axes_do_not_overlap(device):
    cs = CoverageSet(CFG)
    m = rect(40, 200, 60, 260)
    cs.add(keyframe(0, m, device), pose())
    cs.add(keyframe(1, m, device), pose(flip=True))
    assert cs.active == [0, 1] and cs.neighbours(1) == []
    assert float(cs.overlaps(cs._nodes[1], [cs._nodes[0]])[0]) == 0.0


def test_pruning_does_not_skip_neighbours(device):
    """The public code removes a pruned neighbour from the list it iterates, so the
    next neighbour escapes pruning; here a large keyframe covers two small ones and
    both must go."""
    cs = CoverageSet(CFG)
    cs.add(keyframe(0, rect(80, 160, 40, 120), device), pose())
    cs.add(keyframe(1, rect(80, 160, 200, 280), device), pose())
    assert cs.active == [0, 1]
    assert cs.add(keyframe(2, rect(20, 220, 10, 310), device), pose())
    assert cs.active == [2]
    assert cs.neighbours(2) == []


def test_merge_compares_absorbed_members_with_each_other(device):
    cs = CoverageSet(CFG)
    m = rect(40, 200, 60, 260)
    cs.add(keyframe(0, m, device), pose(dx_px=500), group=0)
    cs.add(keyframe(1, m, device), pose(), group=1)
    cs.add(keyframe(2, m, device), pose(), group=2)  # same place, another group
    assert cs.active == [0, 1, 2]
    cs.merge(0, [1, 2])
    assert cs.active == [0, 1]
    assert {cs.group(i) for i in range(3)} == {0}


def test_update_poses_changes_links(device):
    cs = CoverageSet(CFG)
    m = rect(40, 200, 60, 260)
    cs.add(keyframe(0, m, device), pose(dx_px=400))
    cs.update_poses({0: pose()})
    assert not cs.add(keyframe(1, m, device), pose())  # now on top of keyframe 0


def test_revealed_matches_independent_sum_as_links_change(device):
    """revealed(k) keeps its max over neighbours between calls; after insertions,
    pruning and a pose update it still equals sum_p max(W_k(p) - max_n W_n(p shifted), 0)
    computed here from shifted weight maps (translations by whole pixels)."""
    m = rect(40, 200, 60, 260)
    w = boundary_weights(m[None])[0]
    shifts = {}
    cs = CoverageSet(CFG)

    def expected(k: int) -> float:
        cover = torch.zeros(H, W)
        for n in cs.neighbours(k):
            d = shifts[k] - shifts[n]  # k's pixel column c lands on n's column c + d
            moved = torch.zeros(H, W)
            if d >= 0:
                moved[:, :W - d] = w[:, d:]
            else:
                moved[:, -d:] = w[:, :W + d]
            cover = torch.maximum(cover, moved)
        return float((w - cover).clamp(min=0)[m].sum())

    def check():
        for k in cs.active:
            assert cs.revealed(cs._nodes[k]) == pytest.approx(expected(k), rel=1e-5)

    for k, dx in enumerate([0, 90, 45, 150, 20]):
        shifts[k] = dx
        cs.add(keyframe(k, m, device), pose(dx_px=dx))
        check()
    assert len(cs.active) < 5  # something was pruned on the way
    moved_id = cs.active[-1]
    shifts[moved_id] += 7
    cs.update_poses({moved_id: pose(dx_px=shifts[moved_id])})  # links kept, geometry changed
    check()


def test_capacity_allocated_up_front_gives_the_same_set(device):
    """Maps allocated up front (fewer than needed, so the storage still grows) give the
    same links, active keyframes and weights as growing from nothing."""
    masks = [rect(40, 200, 60, 260), rect(60, 220, 30, 200), rect(40, 200, 60, 260), rect(10, 120, 100, 300)]
    shifts = [0, 40, 300, 150]
    sets = [CoverageSet(CFG, capacity=c) for c in (0, 2)]
    for cs in sets:
        for k, (m, dx) in enumerate(zip(masks, shifts)):
            cs.add(keyframe(k, m, device), pose(dx_px=dx))
    a, b = sets
    assert a.active == b.active and len(a.active) >= 2
    for k in a.active:
        assert a.neighbours(k) == b.neighbours(k)
        assert torch.equal(a.weights(k), b.weights(k))
    with pytest.raises(CoverageError, match="capacity"):
        CoverageSet(CFG, capacity=-1)


def test_depth_gate_and_symmetric_options(device):
    m = rect(40, 200, 60, 260)
    cfg = Config()
    cfg.loop.coverage_depth_gate_mm = 1.0
    gated = CoverageSet(cfg)
    gated.add(keyframe(0, m, device), pose())
    assert gated.add(keyframe(1, m, device), pose(dz_m=5e-3))  # 5 mm deeper: another surface
    assert gated.active == [0, 1] and gated.neighbours(0) == []
    plain = CoverageSet(CFG)
    plain.add(keyframe(0, m, device), pose())
    assert not plain.add(keyframe(1, m, device), pose(dz_m=5e-3))
    # A small patch inside a large one: overlap(large <- small) sums the large patch's
    # near-1 weights over the small patch; the reverse sums the small patch's own
    # weights, and the symmetric option takes the smaller.
    cfg = Config()
    cfg.loop.coverage_symmetric = True
    sym = CoverageSet(cfg)
    small_mask = rect(100, 140, 140, 180)
    sym.add(keyframe(0, rect(20, 220, 10, 310), device), pose())
    sym.add(keyframe(1, small_mask, device), pose(dx_px=400))
    sym.update_poses({1: pose()})
    big, small = sym._nodes[0], sym._nodes[1]
    own = float(boundary_weights(small_mask[None]).sum())
    assert float(sym.overlaps(big, [small])[0]) == pytest.approx(own, rel=1e-5)
    asym = CoverageSet(CFG)
    asym.add(keyframe(0, rect(20, 220, 10, 310), device), pose())
    asym.add(keyframe(1, small_mask, device), pose(dx_px=400))
    asym.update_poses({1: pose()})
    assert float(asym.overlaps(asym._nodes[0], [asym._nodes[1]])[0]) == pytest.approx(40 * 40, rel=1e-4)


def test_errors():
    cs = CoverageSet(CFG)
    with pytest.raises(CoverageError, match="no contact"):
        cs.add(keyframe(0, torch.zeros(H, W, dtype=torch.bool)), pose())
    cs.add(keyframe(0, rect(40, 200, 60, 260)), pose())
    with pytest.raises(CoverageError, match="already added"):
        cs.add(keyframe(0, rect(40, 200, 60, 260)), pose())
    with pytest.raises(CoverageError, match="not in the coverage set"):
        cs.neighbours(7)
    with pytest.raises(CoverageError, match=r"\(4, 4\)"):
        cs.add(keyframe(1, rect(40, 200, 60, 260)), torch.eye(3))
    bad = pose()
    bad[0, 3] = float("nan")
    with pytest.raises(CoverageError, match="NaN"):
        cs.update_poses({0: bad})
    assert issubclass(CoverageError, ValueError)
