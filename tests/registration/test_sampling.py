import numpy as np
import pytest
import torch

from tactile_slam.geometry.curvature import normals_from_gradients
from tactile_slam.registration.sampling import (_spread_batch, flat_nonzero, mask_to_indices, nonzero_2d,
                                                select_samples, spread_top_k, top_k_mask, within_slope)


def _random_maps(b=2, h=30, w=40, seed=0, dtype=torch.float32):
    g = torch.Generator().manual_seed(seed)
    contact = torch.rand((b, h, w), generator=g) > 0.4
    lap = (torch.randn((b, h, w), generator=g) * 0.2).clamp(-0.7, 0.7).to(dtype) * contact
    return lap, contact


@pytest.mark.parametrize("shape", [(1, 0), (1, 7), (3, 50), (2, 30, 40)])
@pytest.mark.parametrize("density", [0.0, 0.3, 1.0])
def test_nonzero_matches_torch(device, shape, density):
    mask = (torch.rand(shape, generator=torch.Generator().manual_seed(1)) < density).to(device)
    flat = flat_nonzero(mask)
    assert flat.dtype == torch.int64 and flat.device == mask.device
    assert torch.equal(flat, mask.reshape(-1).nonzero()[:, 0])
    if mask.dim() == 2:
        rows, cols = nonzero_2d(mask)
        ref_rows, ref_cols = mask.nonzero(as_tuple=True)
        assert torch.equal(rows, ref_rows) and torch.equal(cols, ref_cols)


class TestMaskToIndices:
    def test_row_major_and_padding(self, device):
        mask = torch.tensor([[0, 1, 0, 1, 1], [1, 0, 0, 0, 0]], dtype=torch.bool, device=device)
        idx, valid = mask_to_indices(mask)
        assert idx.tolist() == [[1, 3, 4], [0, 0, 0]]
        assert valid.tolist() == [[True, True, True], [True, False, False]]

    def test_truncates_to_k(self, device):
        mask = torch.ones((1, 6), dtype=torch.bool, device=device)
        idx, valid = mask_to_indices(mask, 4)
        assert idx.tolist() == [[0, 1, 2, 3]] and bool(valid.all())

    def test_empty_rows_give_one_invalid_column(self, device):
        idx, valid = mask_to_indices(torch.zeros((3, 5), dtype=torch.bool, device=device))
        assert idx.shape == (3, 1) and not bool(valid.any())


class TestTopK:
    @pytest.mark.parametrize("ties", [False, True])
    def test_matches_stable_sort(self, device, dtype, ties):
        lap, contact = _random_maps(dtype=dtype)
        if ties:  # heavy ties: quantise, so that the tie rule decides
            lap = (lap * 20).round() / 20
        idx, valid = select_samples(lap.to(device), contact.to(device), 300, "topk")
        for i in range(lap.shape[0]):
            a = np.where(contact[i].numpy().ravel(), np.abs(lap[i].numpy().ravel()), -1.0)
            order = np.argsort(-a, kind="stable")[:300]  # |L| descending, ties by index
            expected = np.sort(order[a[order] >= 0])
            assert idx[i][valid[i]].cpu().numpy().tolist() == expected.tolist()

    def test_fewer_contact_pixels_than_k_takes_all(self, device):
        lap, contact = _random_maps()
        idx, valid = select_samples(lap.to(device), contact.to(device), 10**6, "topk")
        assert valid.sum(1).tolist() == contact.reshape(2, -1).sum(1).tolist()

    def test_all_at_clip_still_selects_k(self, device):
        contact = torch.ones((1, 60, 80), dtype=torch.bool, device=device)
        lap = torch.full((1, 60, 80), 0.7, device=device)
        idx, valid = select_samples(lap, contact, 3000, "topk")
        assert int(valid.sum()) == 3000 and idx[0, :3000].tolist() == list(range(3000))

    def test_never_selects_outside_contact(self, device):
        score = torch.tensor([[0.5, -1.0, 0.1, -1.0]], device=device)
        assert top_k_mask(score, 3).tolist() == [[True, False, True, False]]


def _spread_reference(lap: np.ndarray, contact: np.ndarray, k: int, cell: int) -> list[int]:
    """An independent reading of the spread rule, one frame ``(H, W)``: per cell, the
    contact pixels by |L| in 65,536 levels of the frame's largest, descending (ties by
    index); the ``k`` smallest ``(rank + 0.5) / count`` win, ties by the higher |L|, then
    the lower index."""
    h, w = lap.shape
    top = np.abs(lap[contact]).max()
    level = np.floor(np.abs(lap).astype(np.float32) / np.float32(top) * np.float32(65535))
    cand = []
    for r0 in range(0, h, cell):
        for c0 in range(0, w, cell):
            px = [r * w + c for r in range(r0, min(r0 + cell, h)) for c in range(c0, min(c0 + cell, w))
                  if contact[r, c]]
            px.sort(key=lambda p: (-level.flat[p], p))
            cand += [((rank + 0.5) / len(px), -abs(lap.flat[p]), p) for rank, p in enumerate(px)]
    return sorted(p for _, _, p in sorted(cand)[:k])


class TestSpreadRule:
    @pytest.mark.parametrize("ties", [False, True])
    def test_matches_reference(self, device, dtype, ties):
        lap, contact = _random_maps(h=37, w=45, dtype=dtype)
        if ties:
            lap = (lap * 20).round() / 20
        for k in (1, 97, 300, 10**5):
            idx, valid = select_samples(lap.to(device), contact.to(device), k, "spread", cell_px=8)
            for i in range(lap.shape[0]):
                expected = _spread_reference(lap[i].double().numpy(), contact[i].numpy(), k, 8)
                assert idx[i][valid[i]].cpu().numpy().tolist() == expected

    def test_each_cell_gets_its_share(self, device):
        """A contact of two 16x16 cells, one of them with all the strong curvature: top-k
        takes every sample there, spread takes half from each cell, each its strongest."""
        lap = torch.zeros(1, 16, 32)
        contact = torch.ones(1, 16, 32, dtype=torch.bool)
        lap[0, :, :16] = torch.linspace(0.3, 0.6, 256).reshape(16, 16)
        lap[0, :, 16:] = torch.linspace(0.001, 0.01, 256).reshape(16, 16)
        top, _ = select_samples(lap.to(device), contact.to(device), 100, "topk")
        assert bool((top.cpu() % 32 < 16).all())
        idx, valid = select_samples(lap.to(device), contact.to(device), 100, "spread")
        left = idx.cpu()[valid.cpu()] % 32 < 16
        assert int(left.sum()) == 50 and int((~left).sum()) == 50
        flat = lap.reshape(-1)
        chosen = flat[idx.cpu()[valid.cpu()]]
        assert float(chosen[~left].min()) >= float(torch.sort(flat.reshape(16, 32)[:, 16:].reshape(-1))[0][-50])

    def test_one_cell_is_top_k_and_small_contact_is_all(self, device):
        lap, contact = _random_maps()
        a = select_samples(lap.to(device), contact.to(device), 300, "spread", cell_px=64)
        b = select_samples(lap.to(device), contact.to(device), 300, "topk")
        assert torch.equal(a[0][a[1]], b[0][b[1]])
        idx, valid = select_samples(lap.to(device), contact.to(device), 10**6, "spread")
        assert valid.sum(1).tolist() == contact.reshape(2, -1).sum(1).tolist()

    @pytest.mark.parametrize("cell_px", [1, 8, 16])
    def test_numpy_rows_equal_batched_torch(self, cell_px):
        """The CPU's per-frame numpy ranking and the batched torch ops (the accelerator
        path, run here on the CPU) pick the same samples: frames of different contact
        sizes (padding), scores with many ties (the position decides), fewer candidates
        than k in one frame, and one-pixel cells (more than int16 cells)."""
        g = torch.Generator().manual_seed(5)
        contact = torch.rand((3, 200, 200), generator=g) > 0.5
        contact[1, 50:] = False
        contact[2] = False
        contact[2, :10, :20] = True  # 200 candidates, fewer than k
        pixel, inside = mask_to_indices(contact.reshape(3, -1))
        score = torch.where(inside, torch.randint(0, 6, pixel.shape, generator=g).float() / 5, 0.0)
        for k in (1, 700, 5000):
            pos, valid = spread_top_k(score, pixel, inside, 200, cell_px, k)
            want_pos, want_valid = _spread_batch(score, pixel, inside, 200, cell_px, k)
            assert torch.equal(valid, want_valid) and torch.equal(pos[valid], want_pos[want_valid]), k
            assert valid.sum(1).tolist() == [k, k, min(k, 200)]

    def test_many_cells_matches_reference(self):
        """One-pixel cells on a 200 x 200 image (40,000 cells: the torch path): every
        contact pixel is its own cell, so the rule keeps the k first by |L| then index."""
        lap, contact = _random_maps(b=1, h=200, w=200)
        idx, valid = select_samples(lap, contact, 700, "spread", cell_px=1)
        expected = _spread_reference(lap[0].double().numpy(), contact[0].numpy(), 700, 1)
        assert idx[0][valid[0]].tolist() == expected

    def test_no_contact_selects_nothing(self, device):
        """A frame without contact, alone or beside one with contact: no valid sample, no
        error (the registration then reports too few shared samples)."""
        lap, contact = _random_maps(b=2, h=60, w=80)
        contact[0] = False
        idx, valid = select_samples(lap[:1].to(device), contact[:1].to(device), 300, "spread")
        assert not bool(valid.any())
        idx, valid = select_samples(lap.to(device), contact.to(device), 300, "spread")
        assert not bool(valid[0].any()) and int(valid[1].sum()) == 300

    def test_batch_equals_single_frames(self, device):
        lap, contact = _random_maps(b=3, h=60, w=80)
        contact[1] = False
        contact[1, 10:20, 10:30] = True  # a much smaller contact: padding in the batch
        idx, valid = select_samples(lap.to(device), contact.to(device), 500, "spread")
        for i in range(3):
            one, ok = select_samples(lap[i:i + 1].to(device), contact[i:i + 1].to(device), 500, "spread")
            assert idx[i][valid[i]].tolist() == one[0][ok[0]].tolist()


class TestThresholdRule:
    def test_at_most_n_minus_one_and_empty_at_clip(self, device):
        lap, contact = _random_maps()
        idx, valid = select_samples(lap.to(device), contact.to(device), 100, "threshold")
        assert (valid.sum(1) <= 99).all()
        sel = lap.reshape(2, -1).abs().gather(1, idx.cpu())[valid.cpu()]
        assert float(sel.min()) > 0
        clip = torch.full((1, 60, 80), 0.7, device=device)
        _, valid = select_samples(clip, torch.ones_like(clip, dtype=torch.bool), 3000, "threshold")
        assert int(valid.sum()) == 0


class TestRandomRule:
    def test_seeded_and_inside_contact(self, device):
        lap, contact = _random_maps()
        a = select_samples(lap.to(device), contact.to(device), 50, "random", torch.Generator().manual_seed(3))
        b = select_samples(lap.to(device), contact.to(device), 50, "random", torch.Generator().manual_seed(3))
        c = select_samples(lap.to(device), contact.to(device), 50, "random", torch.Generator().manual_seed(4))
        assert torch.equal(a[0], b[0]) and not torch.equal(a[0], c[0])
        assert bool(contact.reshape(2, -1).gather(1, a[0].cpu()).all())
        assert a[1].sum(1).tolist() == [50, 50]

    def test_uniform_over_the_contact(self):
        """Every contact pixel is drawn with probability n / |contact|: over 2000 seeds each
        of 200 contact pixels comes out 500 times in expectation (binomial sd 19.4); none
        outside it; fewer contact pixels than n gives all of them."""
        lap = torch.randn(1, 30, 40, generator=torch.Generator().manual_seed(0))
        contact = torch.zeros(1, 30, 40, dtype=torch.bool)
        contact[0, 5:15, 10:30] = True
        counts = torch.zeros(30 * 40)
        for seed in range(2000):
            idx, valid = select_samples(lap, contact, 50, "random", torch.Generator().manual_seed(seed))
            assert int(valid.sum()) == 50
            counts.index_add_(0, idx[valid], torch.ones(50))
        inside = contact.reshape(-1)
        assert float(counts[~inside].sum()) == 0.0
        assert float((counts[inside] - 500.0).abs().max()) < 5 * 19.4
        idx, valid = select_samples(lap, contact, 500, "random", torch.Generator().manual_seed(1))
        assert int(valid.sum()) == 200 and torch.equal(idx[valid], torch.nonzero(inside).flatten())


def test_bad_rule_and_count():
    lap, contact = _random_maps()
    with pytest.raises(ValueError, match="selection"):
        select_samples(lap, contact, 10, "best")
    with pytest.raises(ValueError, match="n_samples"):
        select_samples(lap, contact, 0, "topk")


def test_all_pixels_when_n_is_none():
    lap, contact = _random_maps()
    idx, valid = select_samples(lap, contact, None)
    assert valid.sum(1).tolist() == contact.reshape(2, -1).sum(1).tolist()


@pytest.mark.parametrize("rule", ["spread", "topk", "threshold"])
@pytest.mark.parametrize("value", [float("nan"), float("inf")])
def test_non_finite_curvature_in_the_contact_is_an_error(device, rule, value):
    from tactile_slam.registration.result import RegistrationError

    lap, contact = _random_maps()
    r, c = contact[0].nonzero()[0]
    lap[0, r, c] = value
    with pytest.raises(RegistrationError, match="NaN or Inf"):
        select_samples(lap.to(device), contact.to(device), 100, rule)


def _cap(b: int, h: int = 40, w: int = 50, radius_px: float = 30.0, dtype=torch.float32, device="cpu"):
    """Slopes of spheres of radius ``radius_px`` (shifted per frame) and their contact
    (a disc of slopes up to about 0.9): ``(B, H, W, 2)``, ``(B, H, W)``."""
    yy, xx = torch.meshgrid(torch.arange(h, dtype=torch.float64), torch.arange(w, dtype=torch.float64), indexing="ij")
    grads, contact = [], []
    for i in range(b):
        dx, dy = xx - w / 2 - i, yy - h / 2
        r2 = dx**2 + dy**2
        inside = r2 < (0.67 * radius_px) ** 2
        dz = (radius_px**2 - r2.clamp(max=radius_px**2 - 1)).sqrt()
        grads.append(torch.stack([dx / dz, dy / dz], -1) * inside[..., None])
        contact.append(inside)
    return torch.stack(grads).to(device, dtype), torch.stack(contact).to(device)


def test_within_slope_keeps_the_flatter_contact_pixels(device, dtype):
    g, contact = _cap(3, dtype=dtype, device=device)
    normals = normals_from_gradients(g)
    kept = within_slope(normals, contact, 0.5)
    assert kept.shape == contact.shape and kept.dtype == torch.bool and kept.device == contact.device
    slope = torch.linalg.vector_norm(g.double(), dim=-1)  # independent: the slopes themselves
    want = contact & (slope <= 0.5)
    differ = kept ^ want  # at most rounding at the limit itself
    if differ.any():
        assert int(differ.sum()) <= 2 and float((slope[differ] - 0.5).abs().max()) < 1e-4
    assert not (kept & ~contact).any()
    assert 0.2 < float(kept.sum() / contact.sum()) < 0.5  # the cap's rim is steeper than 0.5
    # a frame flatter than the limit nowhere keeps its whole contact; the others do not change
    few = within_slope(normals, contact, 0.15)
    share = few.reshape(3, -1).sum(1) / contact.reshape(3, -1).sum(1)
    assert bool((share == 1.0).all())  # under a quarter of each cap is that flat: all kept
    assert torch.equal(within_slope(normals, contact, 0.15, min_fraction=0.0),
                       contact & (torch.linalg.vector_norm(normals[..., :2], dim=-1)
                                  <= 0.15 * normals[..., 2].abs()))
    assert torch.equal(within_slope(normals[:1], contact[:1], 0.5), kept[:1])  # per frame
    empty = torch.zeros_like(contact)
    assert not within_slope(normals, empty, 0.5).any()
    # a NaN normal counts as steep: dropped, the rest of its frame as before
    r, c = (kept[1].nonzero()[0]).tolist()
    bad = normals.clone()
    bad[1, r, c] = float("nan")
    dropped = within_slope(bad, contact, 0.5)
    assert not dropped[1, r, c] and int((dropped ^ kept).sum()) == 1
