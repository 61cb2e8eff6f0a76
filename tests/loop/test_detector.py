"""LoopDetector: true loops with ground-truth poses, exclusions, degenerate inputs,
modes, batch = per-pair verification, and no false loop on a repetitive texture."""

from __future__ import annotations

import math
from dataclasses import replace

import pytest
import torch

from tactile_slam.config import Config
from tactile_slam.geometry.frame import Frame
from tactile_slam.loop.detector import Loop, LoopDetector, LoopError
from tactile_slam.loop.retrieval import footprints
from tactile_slam.posegraph import se3
from tactile_slam.registration.normalflow import register
from tactile_slam.registration.result import pose_error
from tactile_slam.tracking.keyframe import Keyframe
from tests.registration.surfaces import Surface, frames, rigid, textured

EYE = torch.eye(4, dtype=torch.float64)
T_LOOP = rigid(rz_deg=25, tx_mm=1.0, ty_mm=-0.6)


def _kf(i, frame, session=None, image=None):
    return Keyframe(i, i if session is None else session, frame, True, EYE.clone(), image)


@pytest.fixture(scope="module")
def scene():
    """Keyframes 0 (reference pose) and 2 (moved by T_LOOP) of one textured surface,
    a third touch 1 elsewhere in the same session, and a flat keyframe 3."""
    fr = frames(textured(0), [EYE, rigid(tx_mm=0.4, rz_deg=3), T_LOOP])
    flat = frames(Surface(flat=True, depth=0.5e-3), [EYE])
    return {0: _kf(0, fr[0], 0), 1: _kf(1, fr[1], 0), 2: _kf(2, fr[2], 1), 3: _kf(3, flat[0], 2)}


def _detector(scene, config=None, mode=None, ids=(0, 1, 2, 3)):
    det = LoopDetector(config or Config(), mode=mode)
    for i in ids:
        det.add(scene[i])
    return det


def _loop_error(loop: Loop, tar_T_ref: torch.Tensor):
    rot, trans = pose_error(loop.ref_T_tar[None], se3.inverse(tar_T_ref)[None])
    return float(rot), float(trans)


@pytest.mark.parametrize("feature_map", ["laplacian", "gaussian"])
def test_finds_true_loop_with_ground_truth_pose(scene, feature_map):
    config = Config()
    config.loop.feature_map = feature_map
    det = _detector(scene, config)
    loops = det.detect(scene[2], [0, 1, 3], {}, {}, scene)
    by_ref = {lp.ref_id: lp for lp in loops}
    assert 0 in by_ref and 3 not in by_ref
    lp = by_ref[0]
    assert lp.tar_id == 2 and lp.inliers >= 8 and lp.ccs >= 0.7 and lp.scr >= 0.3
    assert lp.ref_T_tar.dtype == torch.float64 and lp.ref_T_tar.shape == (4, 4)
    rot, trans = _loop_error(lp, T_LOOP)
    assert rot < 1.0 and trans < 0.3
    assert det.stats.candidates >= 1 and det.stats.loops == len(loops)
    d = lp.to_dict()
    assert d["ref_id"] == 0 and len(d["ref_T_tar"]) == 4
    # the loop carries its verification's conditioning (loops.json too)
    res = det.verify(scene[2], [scene[0]], lp.init_tar_T_ref[None])
    assert 0.0 < lp.conditioning <= 1.0 and d["conditioning"] == lp.conditioning
    assert lp.conditioning == pytest.approx(float(res.conditioning[0]), rel=1e-6)


def test_detection_on_device(scene, device):
    """Keyframes living on ``device``: features come from the CPU, verification runs
    on the device, and the loop is the same."""
    moved = {i: replace(k, maps=k.frame.to(device)) for i, k in scene.items()}
    det = _detector(moved)
    loops = [lp for lp in det.detect(moved[2], [0, 1, 3], {}, {}, moved) if lp.ref_id == 0]
    assert len(loops) == 1 and loops[0].ref_T_tar.device.type == "cpu"
    rot, trans = _loop_error(loops[0], T_LOOP)
    assert rot < 1.0 and trans < 0.3


def test_previous_keyframe_of_same_session_is_excluded(scene):
    det = _detector(scene)
    assert det.detect(scene[1], [0], {}, {}, scene) == []  # 0 = 1 - 1, same session
    assert det.stats.pairs == 0
    other = replace(scene[1], session=7)
    loops = det.detect(other, [0], {}, {}, scene)  # a new session: 0 is a candidate
    assert [lp.ref_id for lp in loops] == [0]
    rot, trans = _loop_error(loops[0], rigid(tx_mm=0.4, rz_deg=3))
    assert rot < 1.0 and trans < 0.3


def test_degenerate_inputs_return_no_loops(scene):
    det = _detector(scene)
    assert det.detect(scene[3], [0, 1, 2], {}, {}, scene) == []  # query without keypoints
    assert det.detect(scene[0], [0], {}, {}, scene) == []  # only itself
    assert det.detect(scene[2], [], {}, {}, scene) == []  # nothing eligible
    single = _detector(scene, ids=(0,))
    assert single.detect(scene[0], [0], {0: 0}, {0: EYE}, scene) == []


def test_removed_keyframe_is_skipped(scene):
    det = _detector(scene)
    det.remove(0)
    assert 0 not in det
    assert all(lp.ref_id != 0 for lp in det.detect(scene[2], [0, 1], {}, {}, scene))
    with pytest.raises(LoopError):
        det.remove(0)
    with pytest.raises(LoopError):
        det.add(scene[0])


def test_footprint_is_computed_once_and_kept_after_remove(scene, monkeypatch):
    det = _detector(scene, ids=(0, 1))
    expected = footprints(scene[0].frame.height, scene[0].frame.contact, scene[0].frame.mm_per_px / 1000.0)[0]
    det.remove(0)
    calls = []
    monkeypatch.setattr("tactile_slam.loop.detector.footprints", lambda *a: calls.append(1) or [None])
    fp = det.footprint(scene[0])  # stored when added, still there after removal
    torch.testing.assert_close(fp.centre, expected.centre)
    assert fp.radius == pytest.approx(expected.radius) and calls == []
    assert det.footprint(scene[3]) is None and det.footprint(scene[3]) is None and calls == [1]  # once per id


def test_batch_verification_equals_per_pair(scene):
    det = _detector(scene)
    refs = [scene[0], scene[1], scene[0]]
    init = torch.stack([T_LOOP, EYE, rigid(rz_deg=20, tx_mm=0.8)])
    batch = det.verify(scene[2], refs, init)
    for i, ref in enumerate(refs):
        one = det.verify(scene[2], [ref], init[i:i + 1])
        # batched float32 reductions differ from single ones in the last bits only
        torch.testing.assert_close(batch.tar_T_ref[i], one.tar_T_ref[0], atol=1e-7, rtol=0)
        torch.testing.assert_close(batch.ccs[i], one.ccs[0], atol=1e-6, rtol=0, equal_nan=True)
        torch.testing.assert_close(batch.scr[i], one.scr[0], atol=1e-6, rtol=0, equal_nan=True)
        assert bool(batch.ok[i]) == bool(one.ok[0])
    small = replace(Config(), loop=replace(Config().loop, verify_batch=2))
    chunked = LoopDetector(small).verify(scene[2], refs, init)
    torch.testing.assert_close(chunked.tar_T_ref, batch.tar_T_ref, atol=1e-7, rtol=0)


def test_exhaustive_verification_runs_without_the_stall_check(scene):
    """``exhaustive=True`` (the ambiguity check, probes) verifies with
    ``stall_check_iters=0``: a start in a wrong basin that the default verification stops
    at a check runs on to the cap, and every pair matches a direct registration without
    the check."""
    det = _detector(scene)
    refs = [scene[0]] * 3
    init = torch.stack([T_LOOP @ rigid(rz_deg=a) for a in (0, 90, 180)])  # the truth, a quarter and a half turn off
    quick = det.verify(scene[2], refs, init)
    full = det.verify(scene[2], refs, init, exhaustive=True)
    direct = register(scene[2].frame, Frame.cat([r.frame for r in refs]), se3.inverse(init),
                      replace(det.nf_config, stall_check_iters=0))
    torch.testing.assert_close(full.tar_T_ref, se3.inverse(direct.tar_T_ref.double()), atol=1e-9, rtol=0)
    assert full.iterations.tolist() == direct.iterations.tolist()
    assert bool(quick.ok[0]) and bool(full.ok[0])  # the truth verifies either way
    stopped = ~quick.ok & (quick.iterations < full.iterations)
    assert bool(stopped.any())  # some wrong start was stopped early by default, not exhaustively


def test_verification_uses_the_query_as_reference(scene):
    """Verification registers the query (reference, prepared once) to the candidates
    (targets) and returns the candidates' ``query_T_candidate``: the same as registering
    the pairs that way directly, and close to the method's direction (candidate as
    reference) on these noise-free frames."""
    det = _detector(scene)
    refs = [scene[0], scene[1]]
    init = torch.stack([T_LOOP, EYE])
    got = det.verify(scene[2], refs, init)
    direct = register(scene[2].frame, Frame.cat([scene[0].frame, scene[1].frame]), se3.inverse(init),
                      det.nf_config)
    torch.testing.assert_close(got.tar_T_ref, se3.inverse(direct.tar_T_ref.double()), atol=1e-9, rtol=0)
    torch.testing.assert_close(got.ccs, direct.ccs, equal_nan=True)
    assert got.ok.tolist() == direct.ok.tolist()
    method = register(Frame.cat([scene[0].frame, scene[1].frame]), Frame.cat([scene[2].frame] * 2), init,
                      det.nf_config)
    both = got.ok & method.ok
    assert bool(both.any())
    rot, trans = pose_error(got.tar_T_ref[both], method.tar_T_ref.double()[both])
    assert float(rot.max()) < 0.05 and float(trans.max()) < 0.005


def test_verification_reuses_the_trackers_preparation(scene, monkeypatch):
    """A query keyframe that still carries the tracker's preparation (same sample settings,
    other thresholds) is not prepared again, and verifies exactly as a freshly prepared
    one; a preparation with other settings (fewer samples) is not reused."""
    import tactile_slam.loop.detector as detector_module
    from tactile_slam.registration.normalflow import prepare_reference

    det = _detector(scene)
    refs, init = [scene[0], scene[1]], torch.stack([T_LOOP, EYE])
    fresh = det.verify(scene[2], refs, init)
    calls = []
    monkeypatch.setattr(detector_module, "prepare_reference",
                        lambda *a, **k: calls.append(1) or prepare_reference(*a, **k))
    tracking = replace(det.nf_config, ccs_threshold=0.5, scr_threshold=0.1)  # the tracker's thresholds
    query = replace(scene[2], prepared=prepare_reference(scene[2].frame, tracking))
    reused = det.verify(query, refs, init)
    assert calls == []
    for name in ("tar_T_ref", "ccs", "scr", "ok", "iterations"):
        assert torch.equal(getattr(reused, name), getattr(fresh, name)), name
    other = replace(scene[2], prepared=prepare_reference(scene[2].frame, replace(det.nf_config, n_samples=500)))
    det.verify(other, refs, init)
    assert calls == [1]
    query.compact()
    assert query.prepared is None


def test_only_sift_mode_uses_lifted_estimate(scene):
    det = _detector(scene, mode="only_sift")
    loops = [lp for lp in det.detect(scene[2], [0, 1, 3], {}, {}, scene) if lp.ref_id == 0]
    assert len(loops) == 1 and math.isnan(loops[0].ccs) and det.stats.verified == 0
    assert math.isnan(loops[0].conditioning)  # nothing verified
    torch.testing.assert_close(loops[0].ref_T_tar, se3.inverse(loops[0].init_tar_T_ref))
    rot, trans = _loop_error(loops[0], T_LOOP)
    assert rot < 1.5 and trans < 0.5 + abs(float(T_LOOP[2, 3])) * 1e3


def test_only_nf_mode_verifies_every_candidate_from_identity(scene):
    det = _detector(scene, mode="only_nf")
    loops = det.detect(replace(scene[1], session=7), [0, 2, 3], {}, {}, scene)
    assert det.stats.verified == 3 and det.stats.matched == 0
    assert all(lp.inliers == 0 and torch.equal(lp.init_tar_T_ref, EYE) for lp in loops)
    assert 0 in [lp.ref_id for lp in loops]  # a small motion: NF from identity converges


def test_image_sift_needs_images(scene):
    det = LoopDetector(Config(), mode="image_sift")
    with pytest.raises(LoopError, match="image"):
        det.add(scene[0])
    img = torch.zeros(240, 320, 3, dtype=torch.uint8)
    assert len(det.add(replace(scene[3], image=img))) == 0


def test_bad_configuration_and_input(scene):
    with pytest.raises(LoopError, match="mode"):
        LoopDetector(Config(), mode="fast")
    config = Config()
    config.loop.feature_map = "hessian"
    with pytest.raises(LoopError, match="loop.feature_map must be one of"):
        LoopDetector(config)
    det = _detector(scene, ids=(0,))
    with pytest.raises(LoopError, match="keyframe 1 was never added"):
        det.detect(scene[2], [1, 0], {}, {}, scene)
    with pytest.raises(LoopError, match="keyframe 0 is missing from the keyframe map"):
        det.detect(scene[2], [0], {}, {}, {2: scene[2]})
    with pytest.raises(LoopError, match="single frame"):
        det.add(Keyframe(9, 0, scene[0].frame.cat([scene[0].frame, scene[1].frame]), True, EYE))


def test_repetitive_texture_no_false_loop():
    """Two touches 12 mm apart on a periodic texture (period 1 mm) look identical. In
    the same group, with pose estimates near the truth, the pose gate must reject the
    pair; without poses the ambiguity is real (the pair verifies), which shows the scene
    would produce a false loop."""
    period = 1.0e-3
    waves = [(25e-6, period, 0.0, 0.3), (25e-6, period, math.pi / 2, 1.1)]
    surf = Surface(depth=0.6e-3, waves=waves)
    fr = frames(surf, [EYE])
    kfs = {0: _kf(0, fr[0], 0), 5: _kf(5, fr[0], 0)}
    start_T = {0: EYE, 5: rigid(tx_mm=12.0)}  # the true poses: 12 periods apart
    det = LoopDetector(Config())
    for k in kfs.values():
        det.add(k)
    assert det.detect(kfs[5], [0], {0: 0, 5: 0}, start_T, kfs) == []
    assert det.stats.gated == 1
    ambiguous = det.detect(kfs[5], [0], {0: 0, 5: 1}, start_T, kfs)  # other group: no gate
    assert len(ambiguous) == 1


def test_a_query_is_extracted_once_between_detect_and_add(scene, monkeypatch):
    """The back end detects with a new keyframe, then adds it: its SIFT features are
    computed once and reused (the same values), and a different keyframe is not confused
    with it."""
    det = _detector(scene, ids=(0, 1, 3))
    calls = []
    real = det.extract
    monkeypatch.setattr(det, "extract", lambda kf: calls.append(kf.id) or real(kf))
    loops = det.detect(scene[2], [0, 1, 3], {}, {}, scene)
    assert loops and calls == [2]
    assert [lp.repetitive for lp in loops] == [det.is_repetitive(scene[2]) or det.is_repetitive(scene[lp.ref_id])
                                              for lp in loops]
    feats = det.add(scene[2])
    assert calls == [2]
    fresh = real(scene[2])
    assert torch.equal(feats.keypoints, fresh.keypoints) and torch.equal(feats.descriptors, fresh.descriptors)
    other = _kf(7, scene[0].frame)
    det.detect(other, [0], {}, {}, {**scene, 7: other})
    det.add(_kf(8, scene[1].frame))  # not the last query: extracted afresh
    assert calls == [2, 7, 8]


def test_edge_threshold_must_be_positive():
    cfg = Config()
    cfg.loop.sift_edge_threshold = 0.0
    with pytest.raises(LoopError, match="sift_edge_threshold"):
        LoopDetector(cfg)
