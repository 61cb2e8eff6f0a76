import math
from dataclasses import replace

import pytest
import torch

from tactile_slam.config import Config, NormalFlowConfig
from tactile_slam.geometry.frame import Frame, FrameBuilder, WindowBatch, crop_to_contact, full_batch, window_batch
from tactile_slam.registration.normalflow import (
    normalflow,
    prepare_reference,
    reference_settings,
    register,
    register_pair,
    register_prepared,
    window_multiple,
)
from tactile_slam.registration.result import RegistrationError, RegistrationResult, TrackingLost, pose_error
from tactile_slam.registration.sampling import select_samples

from .surfaces import Surface, as_dtype, bumpy, frames, rigid

EYE = torch.eye(4, dtype=torch.float64)
PX_MM = 0.0634

# name: (true tar_T_ref, initial tar_T_ref)
MOTIONS = {
    "subpixel": (rigid(tx_mm=0.3 * PX_MM, ty_mm=-0.2 * PX_MM), EYE),
    "t0.5mm": (rigid(tx_mm=0.5, ty_mm=-0.3), EYE),
    "t1mm": (rigid(tx_mm=-1.0, ty_mm=0.6), EYE),
    "rz0.5": (rigid(rz_deg=0.5), EYE),
    "rz-10": (rigid(rz_deg=-10), EYE),
    "rz40": (rigid(rz_deg=40), EYE),
    "rz-40": (rigid(rz_deg=-40), EYE),
    "rz90_close_init": (rigid(rz_deg=90, tx_mm=0.3), rigid(rz_deg=80)),
    "rx10": (rigid(rx_deg=10, tx_mm=0.2), EYE),
    "ry-15": (rigid(ry_deg=-15), EYE),
    "tilt15_combo": (rigid(rx_deg=-9, ry_deg=12, rz_deg=5, tx_mm=0.3, ty_mm=-0.2, tz_mm=-0.1), EYE),
}
NAMES = list(MOTIONS)


@pytest.fixture(scope="module")
def scene():
    """Reference (B = 1), targets (B = len(MOTIONS)), truths and inits."""
    truth = torch.stack([MOTIONS[n][0] for n in NAMES])
    init = torch.stack([MOTIONS[n][1] for n in NAMES])
    f = frames(bumpy(1), [EYE] + list(truth))
    return f[0], f[1:], truth, init


@pytest.fixture(scope="module")
def batched(scene):
    ref, tars, _, init = scene
    return register(ref, tars, init)


def _close(a: RegistrationResult, b: RegistrationResult, rot_deg=1e-3, trans_mm=1e-4):
    rot, trans = pose_error(a.tar_T_ref, b.tar_T_ref)
    assert (rot < rot_deg).all() and (trans < trans_mm).all(), (rot, trans)
    assert torch.equal(a.ok.cpu(), b.ok.cpu())


class TestSmoke:
    def test_result_types_and_shapes(self, scene, batched):
        b = len(NAMES)
        assert isinstance(batched, RegistrationResult) and len(batched) == b
        assert batched.tar_T_ref.shape == (b, 4, 4) and batched.tar_T_ref.dtype == torch.float64
        for name in ("ccs", "scr", "n_shared", "iterations", "converged", "ok", "conditioning"):
            assert getattr(batched, name).shape == (b,)
        assert batched.conditioning.dtype == torch.float64
        assert bool(((batched.conditioning > 0) & (batched.conditioning <= 1)).all())
        assert batched.ok.dtype == torch.bool and batched.n_shared.dtype == torch.int64
        assert torch.equal(batched.tar_T_ref[:, 3], EYE[3].expand(b, 4))
        pairs = list(batched)  # one result per pair, each with its batch axis; the loop ends
        assert len(pairs) == b and all(len(p) == 1 for p in pairs)
        assert torch.equal(pairs[-1].tar_T_ref, batched[-1].tar_T_ref) and torch.equal(
            batched[-1].tar_T_ref, batched.tar_T_ref[b - 1:])
        with pytest.raises(IndexError, match=f"out of range for a batch of {b}"):
            batched[b]

    def test_iterations_respect_min_and_cap(self, scene, batched):
        assert (batched.iterations <= 50).all()
        ref, tars, _, init = scene
        public = register(ref, tars, init, NormalFlowConfig(min_iters=7))  # the reference code's rule
        assert (public.iterations[public.converged] >= 7).all()
        # the default stops at the first step below tolerance: some pair finishes sooner,
        # at (almost) the same pose
        assert bool((batched.iterations < public.iterations).any())
        _close(batched, public, rot_deg=5e-3, trans_mm=1e-3)

    def test_iteration_cap(self, scene):
        ref, tars, _, init = scene
        res = register(ref, tars[:2], init[:2], NormalFlowConfig(max_iters=3, min_iters=3, rot_tol=0, trans_tol_m=0))
        assert res.iterations.tolist() == [3, 3] and not bool(res.converged.any())


@pytest.mark.parametrize("name", NAMES)
def test_accuracy(scene, batched, name):
    """Translations, sub-pixel motions, in-plane rotations up to 40 deg from identity and
    90 deg from a close start, tilts up to 15 deg: recovered to 0.1 deg and 0.01 mm."""
    i = NAMES.index(name)
    rot, trans = pose_error(batched.tar_T_ref[i:i + 1], scene[2][i:i + 1])
    assert float(rot) < 0.1 and float(trans) < 0.01, (float(rot), float(trans))
    assert bool(batched.ok[i]) and bool(batched.converged[i])
    assert float(batched.ccs[i]) > 0.95 and float(batched.scr[i]) > 0.5


def test_batch_equals_single(scene, batched):
    ref, tars, _, init = scene
    for i in (0, 5, 9):
        _close(register_pair(ref, tars[i], init[i:i + 1]), batched[i])


@pytest.mark.parametrize("own_references", [False, True])
def test_pairs_finishing_at_different_iterations(scene, own_references):
    """Pairs that stop early leave the working batch; the ones still iterating, and the
    bookkeeping (iterations, convergence), must match one-pair runs. With one reference
    per pair the normal equations come from the subtraction path."""
    ref, tars, _, init = scene
    pick = [0, 5, 7, 9, 10]
    far = init[pick].clone()
    far[1] = rigid(rz_deg=120)  # starts far away: runs to the cap or gets lost
    refs = Frame.cat([ref] * len(pick)) if own_references else ref
    res = register(refs, tars[pick], far)
    assert len(set(res.iterations.tolist())) > 1
    for j, i in enumerate(pick):
        one = register_pair(ref, tars[i], far[j:j + 1])
        _close(one, res[j])
        assert int(one.iterations[0]) == int(res.iterations[j]) and bool(one.converged[0]) == bool(res.converged[j])


class TestCpuChunks:
    """On the CPU, pairs with their own references are prepared and solved
    ``cpu_chunk_samples // n_samples`` at a time; the result is the whole batch's."""

    @pytest.mark.parametrize("fallback", [(), (16, 4)])
    def test_chunks_give_the_whole_batch_result(self, scene, fallback):
        ref, tars, _, init = scene
        init = init.clone()
        init[[2, 6]] = rigid(rz_deg=120)  # far starts: failures, pairs at the cap, the fallback's retries
        refs = Frame.cat([ref] * len(tars))
        whole_cfg = NormalFlowConfig(n_samples=1000, cpu_chunk_samples=0, fallback_factors=fallback)
        chunk_cfg = replace(whole_cfg, cpu_chunk_samples=3000)  # 3 pairs a chunk: 4 chunks of 11 pairs
        whole = register(refs, tars, init, whole_cfg)
        assert not bool(whole.ok.all())  # failures too (the fallback's path)
        for chunked in (register(refs, tars, init, chunk_cfg),
                        register_prepared(prepare_reference(refs, chunk_cfg), tars, init, chunk_cfg)):
            _close(chunked, whole, rot_deg=1e-5, trans_mm=1e-6)
            for name in ("iterations", "converged", "n_shared"):
                assert torch.equal(getattr(chunked, name), getattr(whole, name)), name
            assert torch.allclose(chunked.ccs, whole.ccs, atol=1e-6, equal_nan=True)

    def test_chunk_size(self, scene, monkeypatch):
        import importlib

        nf = importlib.import_module("tactile_slam.registration.normalflow")
        sizes = []
        solve = nf._register_with_fallback
        monkeypatch.setattr(nf, "_register_with_fallback", lambda p, t, i, c: sizes.append(len(t)) or solve(p, t, i, c))
        ref, tars, _, init = scene
        cfg = NormalFlowConfig(n_samples=1000, cpu_chunk_samples=3500)
        register(Frame.cat([ref] * len(tars)), tars, init, cfg)
        assert sizes == [3, 3, 3, 2]
        sizes.clear()
        register(ref, tars, init, cfg)  # one reference for all: never split
        assert sizes == [len(tars)]
        assert nf._chunk_pairs(cfg, 1000, torch.device("cuda")) >= 2 ** 62  # other devices: whole batch
        assert nf._chunk_pairs(replace(cfg, cpu_chunk_samples=0), 1000, torch.device("cpu")) >= 2 ** 62
        assert nf._chunk_pairs(cfg, 5000, torch.device("cpu")) == 1

    def test_bad_setting(self, scene):
        ref, tars, _, _ = scene
        with pytest.raises(RegistrationError, match="cpu_chunk_samples"):
            register(ref, tars[:1], None, NormalFlowConfig(cpu_chunk_samples=-1))

    def test_mismatched_batch(self, scene):
        ref, tars, _, _ = scene
        with pytest.raises(RegistrationError, match="cannot be paired"):
            register(Frame.cat([ref] * 4), tars[:3], None, NormalFlowConfig(n_samples=1000, cpu_chunk_samples=1000))


def _beyond_margin(frames: Frame, margin: int, seed: int) -> Frame:
    """``frames`` with random height, normals and curvature more than ``margin`` pixels
    outside each frame's contact box, where a :class:`CroppedFrame` keeps nothing."""
    g = torch.Generator().manual_seed(seed)
    far = torch.ones_like(frames.contact)
    for i in range(len(frames)):
        crop = crop_to_contact(frames[i], margin)
        h, w = crop.box.shape
        far[i, crop.top:crop.top + h, crop.left:crop.left + w] = False
    noise = {name: torch.randn(getattr(frames, name).shape, generator=g, dtype=getattr(frames, name).dtype)
             for name in ("height", "normals", "curvature")}
    return replace(frames, height=torch.where(far, noise["height"], frames.height),
                   normals=torch.where(far[..., None], noise["normals"], frames.normals),
                   curvature=torch.where(far, noise["curvature"], frames.curvature))


def test_nothing_beyond_the_crop_margin_is_read(scene):
    """Keyframes are stored cropped to their contact plus a margin (``crop_to_contact``,
    8 px): references and targets rebuilt from crops register exactly as the full frames,
    even when the full frames hold arbitrary values beyond the margin."""
    ref, tars, _, init = scene
    ref_n, tars_n = _beyond_margin(ref, 8, 0), _beyond_margin(tars, 8, 1)
    assert not torch.equal(tars_n.normals, tars.normals)  # the noise is where the crops keep nothing

    def rebuilt(frames: Frame) -> Frame:
        return Frame.cat([crop_to_contact(frames[i]).expand() for i in range(len(frames))])

    full, cropped = register(ref_n, tars_n, init), register(rebuilt(ref_n), rebuilt(tars_n), init)
    for name in ("tar_T_ref", "ccs", "scr", "n_shared", "iterations", "ok"):
        assert torch.equal(getattr(full, name), getattr(cropped, name)), name
    # a compacted keyframe's maps (CroppedFrame) register as they are, reference or target
    one = register(ref_n, tars_n[2:3], init[2])
    direct = register(crop_to_contact(ref_n), crop_to_contact(tars_n[2]), init[2])
    prepared = register_prepared(prepare_reference(crop_to_contact(ref_n)), crop_to_contact(tars_n[2]), init[2])
    for res in (direct, prepared):
        for name in ("tar_T_ref", "ccs", "n_shared", "iterations", "ok"):
            assert torch.equal(getattr(res, name), getattr(one, name)), name


WINDOW_CONFIGS = {"default": NormalFlowConfig(), "coarse": NormalFlowConfig(coarse_factors=(4,)),
                  "fallback": NormalFlowConfig(fallback_factors=(16, 4))}


@pytest.mark.parametrize("name", list(WINDOW_CONFIGS))
def test_targets_in_windows_register_as_full_frames(scene, name):
    """Targets read from windows around their crops (``window_batch``) give the full
    frames' results up to the rounding of grid coordinates in float32: the same accepted
    pairs and iterations, converged poses within 1e-3 deg and 1e-4 mm. With the fallback, a pair
    1.5 mm off (coarse levels) and one started off the contact (the shift search, which
    reads the expanded targets) are recovered in both."""
    ref, tars, truth, init = scene
    config = WINDOW_CONFIGS[name]
    far, turn = rigid(tx_mm=1.5, ty_mm=-0.75), rigid(rz_deg=-10)
    tars = Frame.cat([tars, frames(bumpy(1), [far, turn])])
    init = torch.cat([init, torch.stack([EYE, rigid(tx_mm=9.0)])])  # the last starts off the contact
    truth = torch.cat([truth, torch.stack([far, turn])])
    crops = [crop_to_contact(tars[i]) for i in range(len(tars))]
    windows = window_batch(crops, window_multiple(config))
    assert windows.maps.shape[0] * windows.maps.shape[1] < 0.8 * 240 * 320  # less than the image
    prep = prepare_reference(ref, config)
    full, win = register_prepared(prep, full_batch(crops), init, config), register_prepared(prep, windows, init, config)
    # a pair that never converged (a wrong basin, stopped by the stall check) carries the
    # rounding through its iterations: its pose agrees to 0.1 deg / 0.01 mm and its CCS to
    # 1e-3 (0.026 deg and 3e-5 seen on one thread), every converged pair's to 1e-3 deg /
    # 1e-4 mm and 1e-6
    conv = full.converged
    assert torch.equal(win.converged, conv)
    _close(win[conv], full[conv], rot_deg=1e-3, trans_mm=1e-4)
    _close(win[~conv], full[~conv], rot_deg=0.1, trans_mm=1e-2)
    assert torch.equal(win.iterations, full.iterations)
    torch.testing.assert_close(win.ccs[conv], full.ccs[conv], rtol=0, atol=1e-6, equal_nan=True)
    torch.testing.assert_close(win.ccs[~conv], full.ccs[~conv], rtol=0, atol=1e-3, equal_nan=True)
    assert full.ok[-2:].tolist() == [name == "fallback"] * 2
    ok = full.ok.clone()
    rot, trans = pose_error(win.tar_T_ref[ok], truth[ok])
    assert (rot < 0.1).all() and (trans < 0.01).all()


def test_a_window_without_contact_is_a_failure_without_nan(scene):
    ref, tars, _, _ = scene
    flat = replace(tars[:1], contact=torch.zeros_like(tars.contact[:1]))
    res = register_prepared(prepare_reference(ref), window_batch([crop_to_contact(flat)]))
    assert not bool(res.ok[0]) and bool(torch.isfinite(res.tar_T_ref).all())


def test_nan_in_a_window_is_an_error(scene):
    ref, tars, _, init = scene
    windows = window_batch([crop_to_contact(tars[i]) for i in range(2)])
    windows.maps.normals[1][windows.maps.contact[1]] = float("nan")
    with pytest.raises(RegistrationError, match="NaN"):
        register_prepared(prepare_reference(ref), windows, init[:2])


def test_windows_must_be_aligned_to_the_levels(scene):
    ref, tars, _, init = scene
    windows = window_batch([crop_to_contact(tars[i]) for i in range(2)], 4)
    config = NormalFlowConfig(coarse_factors=(8,))
    assert window_multiple(config) == 8 and window_multiple(NormalFlowConfig(coarse_factors=(4,),
                                                                            fallback_factors=(6,))) == 12
    if not (windows.origins % 8).any():
        windows = WindowBatch(windows.maps, windows.origins + 4, windows.shape)
    with pytest.raises(RegistrationError, match="aligned"):
        register_prepared(prepare_reference(ref, config), windows, init[:2], config)


def test_prepared_reference_is_reused(scene, batched):
    ref, tars, _, init = scene
    prep = prepare_reference(ref)
    _close(register_prepared(prep, tars[:3], init[:3]), batched[:3])
    _close(register_prepared(prep, tars[8:], init[8:]), batched[8:])


def test_one_reference_taken_from_a_batch_solves_like_its_own(scene):
    """A reference prepared alone keeps its per-sample products sample-last (a transposed
    view), one taken out of a batch of references keeps the batch's sample-first rows: both
    give the same normal matrices, so the same solves of several targets and of one."""
    ref, tars, _, init = scene
    alone = prepare_reference(ref)
    from_batch = prepare_reference(Frame.cat([tars[1], ref]))[1:2]
    assert not alone.levels[-1].jtj.is_contiguous() and from_batch.levels[-1].jtj.is_contiguous()
    torch.testing.assert_close(alone.levels[-1].jtj, from_batch.levels[-1].jtj, rtol=0, atol=0)
    for t in (slice(0, 4), slice(5, 6)):
        a, b = register_prepared(alone, tars[t], init[t]), register_prepared(from_batch, tars[t], init[t])
        torch.testing.assert_close(a.tar_T_ref, b.tar_T_ref, rtol=0, atol=1e-12)
        assert a.ok.tolist() == b.ok.tolist() and a.iterations.tolist() == b.iterations.tolist()


def test_results_are_ordinary_tensors_under_any_grad_mode(scene):
    """The solve runs under inference mode, but what it returns can be changed in place and
    enter autograd; the result is the same whether the caller has grad enabled, disabled
    or is in inference mode itself."""
    ref, tars, _, init = scene
    res = register(ref, tars[:2], init[:2])
    for name in ("tar_T_ref", "ccs", "ok", "iterations"):
        assert not getattr(res, name).is_inference(), name
    before = res.tar_T_ref.clone()
    res.tar_T_ref[:, :3, 3] *= 1000.0  # e.g. to millimetres, in place
    assert torch.equal(res.tar_T_ref[:, :3, 3], before[:, :3, 3] * 1000.0)
    (res.ccs.clone().requires_grad_() * 2).sum().backward()  # usable in a graph
    T = normalflow(ref, tars[0], init[0])
    T[0, 3] = 0.0
    for mode in (torch.no_grad, torch.inference_mode):
        with mode():
            assert torch.equal(register(ref, tars[:2], init[:2]).tar_T_ref, before)
    assert prepare_reference(ref).points_t.is_inference()  # read-only input of later solves


def test_different_contact_sizes_in_one_batch():
    """References with different contact areas (padding) give their single results."""
    truth = rigid(rz_deg=6, tx_mm=0.4)
    a = frames(replace(bumpy(1), depth=0.3e-3), [EYE, truth])
    b = frames(replace(bumpy(1), depth=0.7e-3), [EYE, truth])
    assert abs(int(a.contact[0].sum()) - int(b.contact[0].sum())) > 3000
    cfg = NormalFlowConfig(n_samples=None)  # every contact pixel: very different counts
    both = register(Frame.cat([a[0], b[0]]), Frame.cat([a[1], b[1]]), None, cfg)
    _close(both[0], register(a[0], a[1], None, cfg))
    _close(both[1], register(b[0], b[1], None, cfg))
    rot, trans = pose_error(both.tar_T_ref, truth.expand(2, 4, 4))
    assert (rot < 0.1).all() and (trans < 0.01).all()


def test_float32_matches_float64(scene, batched):
    ref, tars, _, init = scene
    pick = [NAMES.index(n) for n in ("subpixel", "rz-40", "rz90_close_init", "tilt15_combo")]
    res64 = register(as_dtype(ref, torch.float64), as_dtype(tars[pick], torch.float64), init[pick], dtype=torch.float64)
    _close(res64, batched[pick], rot_deg=0.01, trans_mm=2e-3)


def test_device(scene, batched, device):
    ref, tars, _, init = scene
    res = register(ref.to(device), tars[:3].to(device), init[:3].to(device))
    assert res.tar_T_ref.device.type == device.type
    _close(res, batched[:3], rot_deg=0.01, trans_mm=1e-3)


def test_autograd_jacobian_path_gives_same_result(scene, batched):
    ref, tars, _, init = scene
    res = register(ref, tars[:2], init[:2], NormalFlowConfig(jacobian="autograd", n_samples=3000))
    _close(res, batched[:2])


def test_lm_damping_converges_to_same_pose(scene, batched):
    ref, tars, _, init = scene
    res = register(ref, tars[:5], init[:5], NormalFlowConfig(lm_damping=1e-3))
    _close(res, batched[:5], rot_deg=0.01, trans_mm=1e-3)


def test_old_normalflow_mode(scene):
    """Random 5000 samples, no score checks: seeded, still accurate on small motions."""
    ref, tars, truth, init = scene
    cfg = NormalFlowConfig(selection="random", n_samples=5000, check_scores=False)
    a, b = register(ref, tars[:3], init[:3], cfg), register(ref, tars[:3], init[:3], cfg)
    assert torch.equal(a.tar_T_ref, b.tar_T_ref)
    rot, trans = pose_error(a.tar_T_ref, truth[:3])
    assert (rot < 0.1).all() and (trans < 0.01).all()


STALL_WRONG = [rigid(rz_deg=60), rigid(rz_deg=75), rigid(rz_deg=30, tx_mm=1.0)]  # fail from the identity
STALL_RIGHT = [rigid(rz_deg=40), rigid(rz_deg=-40), rigid(tx_mm=-1.0, ty_mm=0.6)]  # converge from it


@pytest.fixture(scope="module")
def stall_pairs():
    f = frames(bumpy(1), [EYE, *STALL_WRONG, *STALL_RIGHT])
    return f[0], f[1:]


class TestStallCheck:
    """``stall_check_iters``: a pair in a wrong basin stops early with the failure it would
    report at the iteration cap; pairs that converge, slowly or not, are untouched."""

    def test_wrong_basins_stop_early_and_fail_as_at_the_cap(self, stall_pairs):
        ref, tars = stall_pairs
        n = len(STALL_WRONG)
        off = register(ref, tars[:n], None, NormalFlowConfig(stall_check_iters=0))
        on = register(ref, tars[:n], None, NormalFlowConfig(stall_check_iters=10))
        assert not off.ok.any() and not on.ok.any()
        assert (on.iterations < off.iterations).all() and (on.iterations % 10 == 0).all()
        assert not on.converged.any()
        # the reported scores are those of the pose it stopped at, and they fail there too
        assert ((on.ccs < 0.85) | (on.scr < 0.3)).all()

    def test_converging_pairs_are_untouched(self, stall_pairs):
        """rz40 needs over 40 iterations from the identity: its CCS climbs, so it goes on."""
        ref, tars = stall_pairs
        right = tars[len(STALL_WRONG):]
        off = register(ref, right, None, NormalFlowConfig(stall_check_iters=0))
        on = register(ref, right, None, NormalFlowConfig(stall_check_iters=10))
        assert off.ok.all() and int(off.iterations.max()) > 30
        assert torch.equal(on.tar_T_ref, off.tar_T_ref) and torch.equal(on.iterations, off.iterations)

    def test_off_without_score_checks(self, stall_pairs):
        ref, tars = stall_pairs
        cfg = NormalFlowConfig(check_scores=False)
        a = register(ref, tars[:len(STALL_WRONG)], None, cfg)
        b = register(ref, tars[:len(STALL_WRONG)], None, replace(cfg, stall_check_iters=0))
        assert torch.equal(a.iterations, b.iterations) and torch.equal(a.tar_T_ref, b.tar_T_ref)

    def test_negative_interval_is_an_error(self, stall_pairs):
        ref, tars = stall_pairs
        with pytest.raises(RegistrationError, match="stall_check_iters"):
            register(ref, tars[:1], None, NormalFlowConfig(stall_check_iters=-1))


class TestFallback:
    """Pairs that fail are solved again through coarse levels (``fallback_factors``)."""

    def test_recovers_a_translation_beyond_the_fine_basin(self):
        truth = rigid(tx_mm=1.5, ty_mm=-0.75)
        f = frames(bumpy(1), [EYE, truth])
        off = register(f[0], f[1], None, NormalFlowConfig(fallback_factors=()))
        assert not bool(off.ok[0])  # the full-resolution solve alone fails (and says so)
        on = register(f[0], f[1], None, NormalFlowConfig(fallback_factors=(16, 4)))
        rot, trans = pose_error(on.tar_T_ref, truth[None])
        assert bool(on.ok[0]) and float(rot) < 0.1 and float(trans) < 0.01, (float(rot), float(trans))

    @pytest.mark.parametrize("own_references", [False, True])
    def test_only_failures_are_retried(self, own_references):
        """One batch: a passing pair keeps its exact result, a failure the retry fixes takes
        the retry's, and a pair that fails both ways keeps its first result. With the shift
        search, the pair started off the contact is retried from the searched shift and
        recovered; the others keep their results."""
        big = rigid(tx_mm=1.5, ty_mm=-0.75)
        f = frames(bumpy(1), [EYE, rigid(rz_deg=-10), big])
        refs = Frame.cat([f[0]] * 3) if own_references else f[0]
        tars = Frame.cat([f[1], f[2], f[1]])
        init = torch.stack([EYE, EYE, rigid(tx_mm=9.0)])  # the last starts off the contact
        off = register(refs, tars, init, NormalFlowConfig(fallback_factors=()))
        on = register(refs, tars, init, NormalFlowConfig(fallback_factors=(16, 4), fallback_shift_search=False))
        assert off.ok.tolist() == [True, False, False] and on.ok.tolist() == [True, True, False]
        for name in ("tar_T_ref", "ccs", "scr", "n_shared", "iterations", "converged"):
            a, b = getattr(on, name)[[0, 2]], getattr(off, name)[[0, 2]]
            assert torch.equal(a, b) or torch.allclose(a, b, rtol=0, atol=0, equal_nan=True), name
        rot, trans = pose_error(on.tar_T_ref[1:2], big[None])
        assert float(rot) < 0.1 and float(trans) < 0.01
        searched = register(refs, tars, init, NormalFlowConfig(fallback_factors=(16, 4)))
        assert searched.ok.tolist() == [True, True, True]
        assert torch.equal(searched.tar_T_ref[:2], on.tar_T_ref[:2])
        rot, trans = pose_error(searched.tar_T_ref[2:], rigid(rz_deg=-10)[None])
        assert float(rot) < 0.1 and float(trans) < 0.01

    def test_bad_factor(self, scene):
        ref, tars, _, _ = scene
        with pytest.raises(RegistrationError, match="fallback_factors"):
            register(ref, tars[:1], None, NormalFlowConfig(fallback_factors=(7,)))


class TestFailures:
    def test_flat_contact_is_a_failure_without_nan(self):
        f = frames(Surface(flat=True), [EYE, rigid(tx_mm=0.2)])
        res = register(f[0], f[1])
        assert not bool(res.ok[0]) and bool(torch.isfinite(res.tar_T_ref).all())
        with pytest.raises(TrackingLost, match="registration failed"):
            normalflow(f[0], f[1])

    def test_textureless_sphere_is_degenerate(self):
        f = frames(Surface(), [EYE, rigid(rz_deg=3, tx_mm=0.2)])
        res = register(f[0], f[1])
        assert not bool(res.ok[0]) and bool(torch.isfinite(res.tar_T_ref).all())
        # the same sphere passes once the degeneracy test is disabled: the scores alone cannot tell
        assert bool(register(f[0], f[1], None, NormalFlowConfig(degenerate_eig=0.0)).ok[0])

    @pytest.mark.parametrize("damping", [1e-3, 1.0])
    def test_lm_damping_holds_an_unobservable_direction(self, damping):
        """A textureless sphere cannot see a turn about its vertical axis. The damped solve
        leaves that direction where it started (identity), and the pair stays a finite
        failure. Marquardt's diag(A) alone is 0 there, so the step along it was rounding
        noise over the 1e-12 ridge: 5.9 degrees of turn at damping 1e-3, 78 at 1."""
        f = frames(Surface(), [EYE, rigid(rz_deg=3, tx_mm=0.2)])
        res = register(f[0], f[1], None, NormalFlowConfig(lm_damping=damping))
        rot = res.tar_T_ref[0, :3, :3]
        turn_z = math.degrees(math.atan2(float(rot[1, 0]), float(rot[0, 0])))
        assert not bool(res.ok[0]) and bool(torch.isfinite(res.tar_T_ref).all())
        assert abs(turn_z) < 0.2

    @pytest.mark.parametrize("damping", [0.0, 1e-3, 1.0])
    def test_lm_damping_does_not_hold_back_a_weak_direction(self, damping):
        """Straight grooves on a dome: the slide along the grooves is seen only through the
        dome, a weak but real constraint. Damping still recovers the motion."""
        truth = rigid(rz_deg=3, tx_mm=0.2)
        f = frames(Surface(waves=[(60e-6, 1e-3, 0.0, 0.0)]), [EYE, truth])
        res = register(f[0], f[1], None, NormalFlowConfig(lm_damping=damping))
        rot, trans = pose_error(res.tar_T_ref, truth[None])
        assert bool(res.ok[0]) and float(rot) < 0.05 and float(trans) < 0.005

    def test_conditioning_orders_the_constraints_and_decides_degeneracy(self):
        """A flat contact constrains nothing (0), a textureless sphere hides its turns
        (~1e-10), straight grooves leave the slide along them to the dome, a bumpy
        texture pins every direction. ``degenerate_eig`` is a threshold on exactly this
        number: just above a pair's value it fails, just below it passes."""
        truth = rigid(rz_deg=3, tx_mm=0.2)
        surfaces = [Surface(flat=True), Surface(), Surface(waves=[(60e-6, 1e-3, 0.0, 0.0)]), bumpy(1)]
        pairs = [frames(surf, [EYE, truth]) for surf in surfaces]
        cond = [float(register(f[0], f[1]).conditioning[0]) for f in pairs]
        assert cond[0] == 0.0 and cond[1] < 1e-6 < cond[2] < 1e-3 < cond[3] <= 1.0, cond
        f, c = pairs[2], cond[2]
        assert bool(register(f[0], f[1], None, NormalFlowConfig(degenerate_eig=0.9 * c)).ok[0])
        assert not bool(register(f[0], f[1], None, NormalFlowConfig(degenerate_eig=1.1 * c)).ok[0])

    def test_too_few_shared_samples(self, scene):
        ref, tars, _, _ = scene
        res = register(ref, tars[:1], rigid(tx_mm=9.0))
        assert not bool(res.ok[0]) and int(res.n_shared[0]) < 10
        assert int(res.iterations[0]) == 0 and bool(torch.isfinite(res.tar_T_ref).all())

    def test_no_valid_height_sample_gives_failure_not_nan(self, scene):
        ref, tars, _, _ = scene
        tar = replace(tars[:1], contact=torch.zeros_like(tars[:1].contact))
        res = register(ref, tar, None, NormalFlowConfig(min_shared=1))
        assert not bool(res.ok[0])
        assert float(res.tar_T_ref[0, 2, 3]) == 0.0 and bool(torch.isfinite(res.tar_T_ref).all())

    def test_many_pixels_at_the_curvature_clip(self):
        spiky = Surface(waves=[(150e-6, 0.45e-3, 0.3, 0.0), (150e-6, 0.55e-3, 1.9, 1.0)])
        truth = rigid(rz_deg=2, tx_mm=0.1)
        f = frames(spiky, [EYE, truth])
        at_clip = (f[0].curvature.abs() >= 0.7 - 1e-6) & f[0].contact
        assert int(at_clip.sum()) >= 3000
        res = register(f[0], f[1])  # exact top-k still selects 3000 samples
        rot, trans = pose_error(res.tar_T_ref, truth[None])
        assert bool(res.ok[0]) and float(rot) < 0.1 and float(trans) < 0.01
        legacy = register(f[0], f[1], None, NormalFlowConfig(selection="threshold"))
        assert not bool(legacy.ok[0]) and bool(torch.isfinite(legacy.tar_T_ref).all())

    def test_single_pair_success_returns_pose(self, scene):
        ref, tars, truth, _ = scene
        T = normalflow(ref, tars[1])
        assert T.shape == (4, 4) and float(pose_error(T[None], truth[1:2])[1]) < 0.01


def _sampled_pixel(frame) -> tuple[int, int]:
    """The NormalFlow sample (default top-k) nearest the contact's centre of mass."""
    idx, _ = select_samples(frame.curvature, frame.contact, NormalFlowConfig().n_samples)
    r, c = idx[0] // frame.shape[1], idx[0] % frame.shape[1]
    i = int(((r - r.float().mean()) ** 2 + (c - c.float().mean()) ** 2).argmin())
    return int(r[i]), int(c[i])


class TestBadInput:
    @pytest.mark.parametrize("field", ["normals", "height", "curvature"])
    @pytest.mark.parametrize("value", [float("nan"), float("inf")])
    def test_nan_and_inf_in_the_reference(self, scene, field, value):
        ref, tars, _, _ = scene
        bad = getattr(ref, field).clone()
        bad[(0, *_sampled_pixel(ref))] = value
        with pytest.raises(RegistrationError, match="reference.*NaN or Inf"):
            register(replace(ref, **{field: bad}), tars[:1])

    @pytest.mark.parametrize("field", ["normals", "height", "curvature"])
    def test_nan_in_a_target(self, scene, field):
        """A batch with one bad target raises (an input error, not a failed pair). The
        targets are the reference itself, so the samples land on their own pixels."""
        ref = scene[0]
        bad = getattr(ref, field).clone()
        bad[(0, *_sampled_pixel(ref))] = float("nan")
        with pytest.raises(RegistrationError, match="target.*NaN or Inf"):
            register(ref, Frame.cat([ref, replace(ref, **{field: bad})]))

    def test_unread_pixels_are_not_checked(self, scene):
        """Only the values NormalFlow reads must be finite: a NaN in an image corner far from
        every sample leaves the result unchanged."""
        ref, tars, _, _ = scene
        bad_ref, bad_tar = ref.height.clone(), tars[:1].normals.clone()
        bad_ref[0, 0, 0], bad_tar[0, 0, 0, 0] = float("inf"), float("nan")
        a = register(ref, tars[:1])
        b = register(replace(ref, height=bad_ref), replace(tars[:1], normals=bad_tar))
        assert torch.equal(a.tar_T_ref, b.tar_T_ref) and torch.equal(a.ok, b.ok)

    def test_nan_reference_normals_under_the_fallback_levels(self):
        """The fallback's coarse levels average the normal map in blocks around the samples."""
        f = frames(bumpy(1), [EYE, rigid(tx_mm=1.5, ty_mm=-0.75)])
        r, c = _sampled_pixel(f[0])
        bad = f[0].normals.clone()
        bad[0, r - r % 16 + 15, c - c % 16, 2] = float("nan")  # same 16x16 block as the sample
        ref = replace(f[0], normals=bad)
        with pytest.raises(RegistrationError, match="reference.*NaN or Inf"):
            register(ref, f[1], None, NormalFlowConfig(fallback_factors=(16, 4)))

    def test_bad_init(self, scene):
        ref, tars, _, _ = scene
        with pytest.raises(RegistrationError, match="NaN"):
            register(ref, tars[:1], torch.full((4, 4), float("nan"), dtype=torch.float64))
        with pytest.raises(RegistrationError, match="init_tar_T_ref must be"):
            register(ref, tars[:2], torch.eye(3, dtype=torch.float64))
        with pytest.raises(RegistrationError, match="init_tar_T_ref must be"):
            register(ref, tars[:2], EYE.expand(3, 4, 4))

    def test_mismatched_batches_sizes_and_scales(self, scene):
        ref, tars, _, _ = scene
        with pytest.raises(RegistrationError, match="cannot be paired"):
            register(tars[:2], tars[:3])
        with pytest.raises(RegistrationError, match="single frames"):
            register_pair(ref, tars[:2])
        with pytest.raises(RegistrationError, match="scale"):
            register(ref, replace(tars[:1], mm_per_px=0.05))
        small = Frame(**{k: (v[:, :200] if torch.is_tensor(v) and v.ndim >= 3 else v)
                         for k, v in vars(tars[:1]).items()})
        with pytest.raises(RegistrationError, match="size"):
            register(ref, small)

    @pytest.mark.parametrize("dtype", [torch.float16, torch.bfloat16, torch.int32])
    def test_unsupported_working_dtype(self, scene, dtype):
        ref, tars, _, _ = scene
        with pytest.raises(RegistrationError, match="float32 or float64"):
            register(ref, tars[:1], None, None, dtype)
        half = replace(ref, normals=ref.normals.to(torch.float16))  # the frame's own dtype
        with pytest.raises(RegistrationError, match="float32 or float64"):
            prepare_reference(half)

    def test_not_a_frame(self, scene):
        ref, tars, _, _ = scene
        with pytest.raises(RegistrationError, match="target must be a Frame"):
            register(ref, tars[:1].normals)
        with pytest.raises(RegistrationError, match="reference must be a Frame"):
            prepare_reference(window_batch(tars[:1], window_multiple(NormalFlowConfig())))

    def test_preparation_of_other_settings_is_refused(self, scene):
        """A reference prepared with other samples or levels than the solve's config would
        silently ignore what the config asks for."""
        ref, tars, _, _ = scene
        prep = prepare_reference(ref)
        for other in (NormalFlowConfig(coarse_factors=(8, 2)), NormalFlowConfig(jacobian="autograd"),
                      NormalFlowConfig(n_samples=500)):
            with pytest.raises(RegistrationError, match="prepare it with this config"):
                register_prepared(prep, tars[:1], None, other)
        register_prepared(prep, tars[:1], None, NormalFlowConfig(ccs_threshold=0.5))  # thresholds act later

    def test_bad_config(self, scene):
        ref, tars, _, _ = scene
        with pytest.raises(RegistrationError, match="jacobian"):
            register(ref, tars[:1], None, NormalFlowConfig(jacobian="numeric"))
        with pytest.raises(ValueError, match="selection"):
            register(ref, tars[:1], None, NormalFlowConfig(selection="best"))
        with pytest.raises(RegistrationError, match=r"expected a NormalFlowConfig \(e.g. config.normalflow\), got Config"):
            register(ref, tars[:1], None, Config())
        with pytest.raises(RegistrationError, match="normalflow.ccs_threshold must be in"):
            register(ref, tars[:1], None, NormalFlowConfig(ccs_threshold=float("nan")))


def test_coarse_level(scene):
    """A 4x4 block-averaged level first: same accuracy; factors must divide the image."""
    ref, tars, truth, init = scene
    pick = [NAMES.index("t1mm"), NAMES.index("rz-10"), NAMES.index("tilt15_combo")]
    res = register(ref, tars[pick], init[pick], NormalFlowConfig(coarse_factors=(4,)))
    rot, trans = pose_error(res.tar_T_ref, truth[pick])
    assert (rot < 0.1).all() and (trans < 0.01).all() and bool(res.ok.all()), (rot, trans)
    with pytest.raises(RegistrationError, match="coarse_factors"):
        register(ref, tars[:1], None, NormalFlowConfig(coarse_factors=(7,)))


def _ball_reference():
    """A reference whose contact is a ball cap with slopes up to 1.33, and its slopes
    ``(H, W)`` (float64)."""
    h, w = 240, 320
    yy, xx = torch.meshgrid(torch.arange(h, dtype=torch.float64), torch.arange(w, dtype=torch.float64), indexing="ij")
    dx, dy = xx - (w - 1) / 2, yy - (h - 1) / 2
    inside = dx**2 + dy**2 < 80.0**2
    dz = (100.0**2 - (dx**2 + dy**2).clamp(max=100.0**2 - 1)).sqrt()
    g = (torch.stack([dx / dz, dy / dz], -1) * inside[..., None])[None].float()  # a ball, slopes up to 1.33
    ref = FrameBuilder(Config()).from_gradients(g, inside[None])
    return ref, torch.linalg.vector_norm(g[0].double(), dim=-1)


def _sampled_slopes(frame, slope, config):
    """The slopes at a prepared reference's samples, and the preparation."""
    prep = prepare_reference(frame, config)
    h, w = frame.shape
    p = prep.points_t[0, :2].T[prep.valid[0]].double() / prep.m_per_px
    col, row = (p[:, 0] + (w - 1) / 2).round().long(), (p[:, 1] + (h - 1) / 2).round().long()
    return slope[row, col], prep


def test_decoded_reference_samples_only_its_flatter_pixels():
    """A reference decoded from an image takes no sample steeper than
    ``decoded_max_slope``; without the general limit the same maps given as gradients
    sample the steep rim too."""
    ref, slope = _ball_reference()
    cfg = NormalFlowConfig(max_slope=None)
    plain, _ = _sampled_slopes(ref, slope, cfg)
    dec, prep = _sampled_slopes(replace(ref, decoded=True), slope, cfg)
    assert cfg.decoded_max_slope == 0.5 and len(dec) == len(plain) == cfg.n_samples
    assert float(plain.max()) > 0.9 and float(dec.max()) <= 0.5 + 1e-3
    assert torch.equal(prep.contact, ref.contact)  # the scores still see the whole contact
    off, _ = _sampled_slopes(replace(ref, decoded=True), slope, replace(cfg, decoded_max_slope=None))
    torch.testing.assert_close(off, plain)
    assert reference_settings(replace(cfg, decoded_max_slope=None)) != reference_settings(cfg)
    for name in ("decoded_max_slope", "max_slope"):
        for bad in (0.0, -0.5, float("nan")):
            with pytest.raises(RegistrationError, match=name):
                prepare_reference(ref, replace(cfg, **{name: bad}))


@pytest.mark.parametrize("decoded", [False, True])
def test_every_reference_samples_no_pixel_steeper_than_the_limit(decoded):
    """``max_slope`` holds for gradients given as input and for decoded frames; where
    both limits apply the lower one does; a contact mostly steeper keeps its steep pixels."""
    ref, slope = _ball_reference()
    ref = replace(ref, decoded=decoded)
    for limit, dec_limit, expect in ((0.5, None, 0.5), (0.7, 0.5, 0.5 if decoded else 0.7), (0.6, 0.8, 0.6)):
        got, _ = _sampled_slopes(ref, slope, NormalFlowConfig(max_slope=limit, decoded_max_slope=dec_limit))
        assert len(got) == NormalFlowConfig().n_samples and float(got.max()) <= expect + 1e-3
        assert float(got.max()) > expect - 0.05  # the limit, not something stricter
    steep, _ = _sampled_slopes(ref, slope, NormalFlowConfig(max_slope=0.05, decoded_max_slope=None))
    assert float(steep.max()) > 0.9  # under a quarter of the contact is that flat: all of it is used
    assert reference_settings(NormalFlowConfig(max_slope=None)) != reference_settings(NormalFlowConfig())


def test_reference_settings_say_when_a_preparation_can_be_reused():
    """A preparation records what it took from its configuration: thresholds and iteration
    limits do not change it, the samples, the Jacobian and the coarse levels do; the
    fallback pyramid records its own levels."""
    base = NormalFlowConfig()
    same = replace(base, ccs_threshold=0.5, scr_threshold=0.1, max_iters=7, fallback_factors=(4,))
    assert reference_settings(same) == reference_settings(base)
    for other in (replace(base, n_samples=500), replace(base, selection="threshold"),
                  replace(base, jacobian="autograd"), replace(base, coarse_factors=(4,)),
                  replace(base, selection="random"), replace(base, selection="random", seed=1)):
        assert reference_settings(other) != reference_settings(base)
    assert reference_settings(replace(base, seed=5)) == reference_settings(base)  # seed only for "random"
    ref = frames(bumpy(0), [torch.eye(4, dtype=torch.float64)])
    prep = prepare_reference(ref, same)
    assert prep.settings == reference_settings(base) and prep[0:1].settings == prep.settings
    assert prep.retry_levels(None, (16, 4), base.jacobian).settings == \
        reference_settings(replace(base, coarse_factors=(4, 16)))
