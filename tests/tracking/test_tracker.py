"""Keyframe and session logic on crafted sequences with a scripted registrar.

Frame i has a known sensor pose X_i (object frame); the fake registrar returns the
exact tar_T_ref = inv(X_tar) X_ref unless a scripted rule says the pair fails. The
tracker's composed poses must then equal the truth, and its keyframes and sessions
must follow method.md section 5.
"""

from __future__ import annotations

import math
from dataclasses import replace

import pytest
import torch

from tactile_slam.config import TrackingConfig
from tactile_slam.geometry.frame import CroppedFrame, Frame
from tactile_slam.posegraph import se3
from tactile_slam.registration.result import RegistrationError, RegistrationResult, pose_error
from tactile_slam.tracking.frame_to_frame import FrameToFrameTracker
from tactile_slam.tracking.tracker import Tracker


def pose(i: int) -> torch.Tensor:
    """Sensor pose of frame i: a constant body-frame step (2 degrees about z, 0.5 mm in x,
    0.25 mm in y: within the default speed limits at 25 fps) applied i times."""
    a = math.radians(2.0)
    step = torch.eye(4, dtype=torch.float64)
    step[:2, :2] = torch.tensor([[math.cos(a), -math.sin(a)], [math.sin(a), math.cos(a)]])
    step[:2, 3] = torch.tensor([5e-4, 2.5e-4])
    return torch.linalg.matrix_power(step, i)


def frame(i: int, contact: bool | int = True, fps: float = 25.0) -> Frame:
    """``contact``: in contact (True), not (False), or a number of contact pixels below
    the in-contact minimum (a weak frame)."""
    z = torch.zeros(1, 4, 4)
    mask = torch.zeros(1, 16, dtype=torch.bool)
    mask[:, :int(contact)] = True
    return Frame(
        gradients=torch.zeros(1, 4, 4, 2), height=z, contact=mask.view(1, 4, 4),
        normals=torch.zeros(1, 4, 4, 3), curvature=z, in_contact=torch.tensor([contact is True]),
        depth_known=torch.tensor([True]), index=torch.tensor([i]),
        timestamp=torch.tensor([i / fps], dtype=torch.float64), mm_per_px=0.0634,
    )


class ScriptedRegistrar:
    def __init__(self, fails, slip=None, coarse_fails=None, conditioning=0.1):
        self.fails = fails  # (ref_index, tar_index) -> bool
        self.conditioning = conditioning  # of every answer
        self.slip = slip  # (ref_index, tar_index) -> (4, 4) error applied to the answer, or None
        # the coarse solve: (ref_index, tar_index) -> bool; by default it fails where the fine one does
        self.coarse_fails = coarse_fails or fails
        self.calls: list[tuple[int, int, torch.Tensor]] = []
        self.coarse_calls: list[tuple[int, int, tuple[int, ...]]] = []

    def prepare(self, ref: Frame):
        return int(ref.index[0])

    def register(self, ref_index, tar: Frame, init):
        """Every target is the same frame here; a batch (the keyframe-edge check) gets the
        same answer for each start and is not logged in ``calls``."""
        tar_index, b = int(tar.index[0]), len(tar)
        if b == 1:
            self.calls.append((ref_index, tar_index, init[0].clone()))
        return self._answer(ref_index, tar_index, b, not self.fails(ref_index, tar_index))

    def register_coarse(self, ref_index, tar: Frame, init, factors):
        tar_index = int(tar.index[0])
        self.coarse_calls.append((ref_index, tar_index, factors))
        return self._answer(ref_index, tar_index, len(tar), not self.coarse_fails(ref_index, tar_index))

    def _answer(self, ref_index, tar_index, b, ok):
        t = torch.linalg.inv(pose(tar_index)) @ pose(ref_index)
        if self.slip is not None and self.slip(ref_index, tar_index) is not None:
            t = self.slip(ref_index, tar_index) @ t
        full = lambda v, dt=torch.float64: torch.full((b,), v, dtype=dt)  # noqa: E731
        return RegistrationResult(t.expand(b, 4, 4).clone(), full(0.9 if ok else 0.1), full(0.9),
                                  full(100, torch.int64),
                                  full(7, torch.int64), full(True, torch.bool), full(ok, torch.bool),
                                  full(self.conditioning))


def run(contacts, fails=lambda r, t: False, slip=None, fps=25.0, coarse_fails=None, conditioning=0.1, **cfg):
    reg = ScriptedRegistrar(fails, slip, coarse_fails, conditioning)
    tr = Tracker(TrackingConfig(**cfg), reg)
    steps = [tr.step(frame(i, c, fps)) for i, c in enumerate(contacts)]
    tail = tr.finish()
    kfs = [k for s in steps for k in s.keyframes] + tail
    reg.tracker = tr
    return steps, kfs, reg


def check_poses(steps, kfs):
    """kf_T_frame composed with the keyframe chain reproduces the true relative poses."""
    by_id = {k.id: k for k in kfs}
    head_pose = {}
    kf_pose = {}
    for k in sorted(kfs, key=lambda k: k.id):
        if k.new_session:
            kf_pose[k.id] = torch.eye(4, dtype=torch.float64)
            head_pose[k.session] = k.video_index
        else:
            prev = max(j for j in kf_pose if by_id[j].session == k.session)
            kf_pose[k.id] = kf_pose[prev] @ k.prev_T_kf
    for s in steps:
        if not s.in_contact:
            continue
        est = kf_pose[s.keyframe_id] @ s.kf_T_frame
        true = torch.linalg.inv(pose(head_pose[s.session])) @ pose(s.index)
        torch.testing.assert_close(est, true)


@pytest.mark.parametrize("check, below, conditioning, fires", [
    (None, None, 1e-3, False),  # off
    (1.0, None, 0.1, True),  # every frame
    (1.0, 1e-2, 1e-3, True),  # a weakly constrained keyframe registration is checked
    (1.0, 1e-2, 0.1, False),  # a well constrained one is not
    (1.0, 1e-2, math.nan, True),  # nor known to be: checked
])
def test_frame_to_frame_cross_check(check, below, conditioning, fires):
    """Registrations against keyframe 0 drift by 2 deg from frame 3 on, while every
    frame-to-frame registration is right (a keyframe held while the sensor rolls around
    a cylinder). Unchecked, the drifted poses are kept; with the 1 deg check, frame 3's
    keyframe registration disagrees with frame 2 -> 3 chained onto frame 2's pose, so
    frame 2 becomes a keyframe and every pose is right."""
    c, s = math.cos(math.radians(2.0)), math.sin(math.radians(2.0))
    turn = torch.eye(4, dtype=torch.float64)
    turn[:2, :2] = torch.tensor([[c, -s], [s, c]], dtype=torch.float64)
    steps, kfs, reg = run([True] * 6, slip=lambda r, t: turn if r == 0 and t >= 3 else None, f2f_check_deg=check,
                          f2f_below_conditioning=below, conditioning=conditioning)
    if not fires:
        assert [k.video_index for k in kfs] == [0, 5] and reg.tracker.f2f_refusals == 0
        assert reg.tracker.f2f_checks == 0
        with pytest.raises(AssertionError):
            check_poses(steps, kfs)
    else:
        assert [k.video_index for k in kfs] == [0, 2, 5] and reg.tracker.f2f_refusals == 1
        # frames 2 and 3 against keyframe 0 (frame 1 follows it; frame 3's retry against the
        # new keyframe 2 does too), 4 and 5 against keyframe 2
        assert reg.tracker.f2f_checks == 4
        check_poses(steps, kfs)


class PairConditioningRegistrar(ScriptedRegistrar):
    """Answers with a conditioning that names the pair: ``ref + tar / 100``."""

    def _answer(self, ref_index, tar_index, b, ok):
        res = super()._answer(ref_index, tar_index, b, ok)
        res.conditioning = torch.full((b,), ref_index + tar_index / 100, dtype=torch.float64)
        return res


def test_steps_report_the_accepted_registrations_conditioning():
    """Each tracked frame carries the conditioning of the registration it was accepted on:
    its keyframe's, or after the lazy rule the retry's against the new keyframe; session
    heads and frames without contact carry NaN."""
    reg = PairConditioningRegistrar(lambda r, t: (r, t) == (0, 3))
    tr = Tracker(TrackingConfig(), reg)
    steps = [tr.step(frame(i, c)) for i, c in enumerate([True] * 5 + [False])]
    got = [s.conditioning for s in steps]
    assert math.isnan(got[0]) and math.isnan(got[5])  # session head, contact loss
    # frames 1, 2 against keyframe 0; frame 3 fails there and is accepted against frame 2
    assert got[1:5] == [0 + 1 / 100, 0 + 2 / 100, 2 + 3 / 100, 2 + 4 / 100]


def test_single_session_no_failures():
    steps, kfs, _ = run([True] * 6)
    assert [k.id for k in kfs] == [0, 1]
    assert kfs[0].new_session and kfs[0].video_index == 0
    assert not kfs[1].new_session and kfs[1].video_index == 5  # flushed tail at end of stream
    check_poses(steps, kfs)


def test_contact_loss_starts_new_session_and_flushes_tail():
    contacts = [True] * 4 + [False] * 2 + [True] * 3
    steps, kfs, _ = run(contacts)
    assert [(k.video_index, k.session, k.new_session) for k in kfs] == [
        (0, 0, True), (3, 0, False), (6, 1, True), (8, 1, False)]
    assert steps[4].keyframes and steps[4].keyframes[0].video_index == 3
    assert steps[5].keyframes == [] and steps[5].kf_T_frame is None
    check_poses(steps, kfs)


def test_no_tail_flush_when_disabled():
    _, kfs, _ = run([True] * 4 + [False] + [True] * 2, flush_session_tail=False)
    assert [k.video_index for k in kfs] == [0, 5]


def test_lazy_keyframe_then_retry_succeeds():
    # a pair fails when the frames are more than 2 apart
    steps, kfs, reg = run([True] * 8, fails=lambda r, t: t - r > 2)
    assert [k.video_index for k in kfs if not k.new_session][:2] == [2, 4]
    assert all(k.session == 0 for k in kfs)
    s3 = steps[3]
    assert [k.video_index for k in s3.keyframes] == [2] and not s3.is_keyframe
    # the retry against the new keyframe starts from the (constant-position) identity
    assert (reg.calls[3][0], reg.calls[3][1]) == (2, 3)
    torch.testing.assert_close(reg.calls[3][2], torch.eye(4, dtype=torch.float64))
    check_poses(steps, kfs)


def test_retry_fails_new_session_two_keyframes_in_one_step():
    steps, kfs, _ = run([True] * 6, fails=lambda r, t: t == 3)
    s = steps[3]
    assert [(k.video_index, k.new_session) for k in s.keyframes] == [(2, False), (3, True)]
    assert s.is_keyframe and s.session == 1
    check_poses(steps, kfs)


def test_failure_right_after_keyframe_starts_new_session():
    steps, kfs, _ = run([True] * 4, fails=lambda r, t: (r, t) == (0, 1))
    assert steps[1].is_keyframe and steps[1].keyframes[0].new_session and steps[1].session == 1
    check_poses(steps, kfs)


def test_stream_ending_mid_contact_keeps_tail():
    steps, kfs, _ = run([False, True, True, True])
    assert kfs[-1].video_index == 3 and not kfs[-1].new_session


KEEP = 8 * 0.0634 ** 2  # mm^2: 8 of the test frames' 16 pixels


def test_weak_frames_continue_a_session():
    """Frames below the in-contact minimum but above keep_contact_mm2 are tracked like
    any frame inside a session; with None (the reference rule) each dip starts anew."""
    contacts = [True] * 3 + [10, 8] + [True] * 2
    steps, kfs, _ = run(contacts, keep_contact_mm2=KEEP)
    assert [(k.video_index, k.session, k.new_session) for k in kfs] == [(0, 0, True), (6, 0, False)]
    assert all(s.in_contact and s.session == 0 for s in steps) and steps[4].keyframe_id == 0
    check_poses(steps, kfs)
    steps, kfs, _ = run(contacts, keep_contact_mm2=None)
    assert [(k.video_index, k.new_session) for k in kfs] == [(0, True), (2, False), (5, True), (6, False)]
    assert not steps[3].in_contact and not steps[4].in_contact


def test_weak_frames_never_start_a_session_and_too_little_contact_ends_one():
    steps, kfs, _ = run([False, 12, 12, True, True, 7, True], keep_contact_mm2=KEEP)
    assert [s.in_contact for s in steps] == [False, False, False, True, True, False, True]
    assert [(k.video_index, k.session, k.new_session) for k in kfs] == [
        (3, 0, True), (4, 0, False), (6, 1, True)]
    assert steps[5].keyframes == kfs[1:2]  # the first session's tail, flushed by the loss
    check_poses(steps, kfs)


@pytest.mark.parametrize("fails_at, emitted", [(3, [(2, False)]), (1, [])])
def test_weak_frame_that_does_not_register_ends_the_session(fails_at, emitted):
    """Failure after the lazy retry (or right after a keyframe): contact loss, never a
    new session from the weak frame; the next strong frame starts one."""
    contacts = [True] * fails_at + [10, True, True]
    steps, kfs, _ = run(contacts, fails=lambda r, t: t == fails_at, keep_contact_mm2=KEEP)
    s = steps[fails_at]
    assert not s.in_contact and s.kf_T_frame is None
    assert [(k.video_index, k.new_session) for k in s.keyframes] == emitted
    nxt = steps[fails_at + 1]
    assert nxt.is_keyframe and nxt.keyframes[0].new_session and nxt.session == 1
    assert [k.video_index for k in kfs].count(fails_at - 1) <= 1  # no tail made twice
    check_poses(steps, kfs)


def test_frame_to_frame_baseline_keeps_contact_the_same_way():
    reg = ScriptedRegistrar(lambda r, t: False)
    tr = FrameToFrameTracker(reg, KEEP)
    steps = [tr.step(frame(i, c)) for i, c in enumerate([12, True, True, 10, 5, True])]
    assert [s.in_contact for s in steps] == [False, True, True, True, False, True]
    assert [s.session for s in steps if s.in_contact] == [0, 0, 0, 1]
    torch.testing.assert_close(steps[3].kf_T_frame, torch.linalg.inv(pose(1)) @ pose(3))
    with pytest.raises(ValueError, match="keep_contact_mm2"):
        FrameToFrameTracker(reg, -1.0)


def _owns_storage(fr: Frame) -> bool:
    grads = getattr(fr, "gradients", None)
    maps = (fr.height, fr.contact, fr.normals, fr.curvature) + (() if grads is None else (grads,))
    return all(m.untyped_storage().nbytes() == m.numel() * m.element_size() for m in maps)


def test_keyframes_do_not_keep_their_geometry_batch_alive():
    """The pipeline hands the trackers ``batch[i]``, a view of a geometry batch. A
    keyframe holding that view kept all of the batch's maps alive: a 6000-frame scan
    grew to 10 GB. Keyframes own copies of their own frame's maps, without the gradients
    (nothing reads a keyframe's slopes), and keep the contact's surroundings only once
    compacted (:class:`CroppedFrame`)."""
    batch = Frame.cat([frame(i, c) for i, c in enumerate([True, True, False, True, True, True])])
    assert not _owns_storage(batch[0])  # the view the trackers are given
    tr = Tracker(TrackingConfig(), ScriptedRegistrar(lambda r, t: t == 4))
    kfs = [k for i in range(len(batch)) for k in tr.step(batch[i]).keyframes] + tr.finish()
    f2f = FrameToFrameTracker(ScriptedRegistrar(lambda r, t: False), KEEP)
    kfs += [k for i in range(len(batch)) for k in f2f.step(batch[i]).keyframes]
    assert len(kfs) >= 4 and all(_owns_storage(k.maps) and k.maps.gradients is None for k in kfs)
    torch.testing.assert_close(kfs[0].frame.normals, batch[0].normals)
    kfs[0].compact()  # what the pipeline does once the back end has the keyframe
    assert isinstance(kfs[0].maps, CroppedFrame) and _owns_storage(kfs[0].maps.box)
    torch.testing.assert_close(kfs[0].frame.normals, batch[0].normals)


def test_keyframes_carry_the_trackers_preparation_until_compacted():
    """Every keyframe (session heads, lazy-rule keyframes, flushed tails) carries what the
    registrar prepared for it as the tracking reference, so that loop verification need
    not prepare it again; compacting drops it."""
    batch = Frame.cat([frame(i, c) for i, c in enumerate([True, True, True, True, False, True, True])])
    tr = Tracker(TrackingConfig(), ScriptedRegistrar(lambda r, t: t == 3))
    kfs = [k for i in range(len(batch)) for k in tr.step(batch[i]).keyframes] + tr.finish()
    assert len(kfs) >= 4 and any(not k.new_session for k in kfs)
    assert [k.prepared for k in kfs] == [k.video_index for k in kfs]  # ScriptedRegistrar prepares to the index
    kfs[0].compact()
    assert kfs[0].prepared is None and kfs[1].prepared == kfs[1].video_index


@pytest.mark.parametrize("fails, emitted", [
    (lambda r, t: (r, t) == (0, 1), []),  # right after the session's keyframe
    (lambda r, t: t == 3, [2]),  # against the keyframe and, after the lazy rule, the previous frame
])
def test_coarse_fallback_keeps_the_session(fails, emitted):
    """A frame about to start a new session is registered once more against the previous
    frame through coarse levels; if that verifies, the session goes on."""
    bad = 1 if not emitted else 3
    steps, kfs, reg = run([True] * 6, fails=fails, coarse_fails=lambda r, t: False)
    s = steps[bad]
    assert not s.is_keyframe and s.session == 0 and [k.video_index for k in s.keyframes] == emitted
    assert all(k.session == 0 for k in kfs) and reg.tracker.coarse_rescues == 1
    assert reg.coarse_calls == [(bad - 1, bad, (4,))]
    check_poses(steps, kfs)
    assert reg.tracker.registration_breaks == 0
    steps, kfs, reg = run([True] * 6, fails=fails, fallback_factors=())  # off: a new session
    assert steps[bad].is_keyframe and steps[bad].session == 1 and reg.coarse_calls == []
    assert reg.tracker.registration_breaks == 1  # inside the contact, not at a new touch


def test_registration_breaks_count_only_sessions_begun_inside_a_contact():
    """A new touch after contact loss starts a session without counting; failing against
    the keyframe and, after the lazy rule, the previous frame counts once per session."""
    steps, _, reg = run([True, True, False, True, True])
    assert steps[3].session == 1 and reg.tracker.registration_breaks == 0
    steps, _, reg = run([True] * 6, fails=lambda r, t: t in (2, 4), fallback_factors=())
    assert [s.session for s in steps] == [0, 0, 1, 1, 2, 2] and reg.tracker.registration_breaks == 2


def test_coarse_fallback_that_fails_or_jumps_starts_a_new_session():
    steps, _, reg = run([True] * 5, fails=lambda r, t: (r, t) == (0, 1))  # the coarse solve fails too
    assert steps[1].is_keyframe and steps[1].session == 1 and len(reg.coarse_calls) == 1
    jump = _rz(20.0)  # a verified coarse result 20 deg away: beyond the speed limits
    steps, _, reg = run([True] * 5, fails=lambda r, t: (r, t) == (0, 1), coarse_fails=lambda r, t: False,
                        slip=lambda r, t: jump if (r, t) == (0, 1) else None)
    assert steps[1].is_keyframe and steps[1].session == 1 and reg.tracker.coarse_rescues == 0
    assert reg.tracker.implausible == 1


def test_coarse_fallback_with_normalflow():
    """The real registrar: a 1.3 mm step between frames is beyond the full-resolution
    basin of top-k samples from the identity; the 4x coarse level recovers it. (Samples
    spread over the contact, the default, recover it at full resolution.)"""
    from tactile_slam.config import NormalFlowConfig
    from tactile_slam.tracking.tracker import NormalFlowRegistrar

    from ..registration.surfaces import bumpy, frames, rigid

    truth = rigid(tx_mm=1.3)
    f = frames(bumpy(1), [torch.eye(4, dtype=torch.float64), truth])
    eye = torch.eye(4, dtype=torch.float64)[None]
    spread = NormalFlowRegistrar(NormalFlowConfig(), TrackingConfig())
    direct = spread.register(spread.prepare(f[0:1]), f[1:2], eye)
    rot, trans = pose_error(direct.tar_T_ref, truth[None])
    assert bool(direct.ok[0]) and float(rot) < 0.1 and float(trans) < 0.01, (float(rot), float(trans))
    reg = NormalFlowRegistrar(NormalFlowConfig(selection="topk"), TrackingConfig())
    prep = reg.prepare(f[0:1])
    assert not bool(reg.register(prep, f[1:2], eye).ok[0])
    res = reg.register_coarse(prep, f[1:2], eye, (4,))
    rot, trans = pose_error(res.tar_T_ref, truth[None])
    assert bool(res.ok[0]) and float(rot) < 0.1 and float(trans) < 0.01, (float(rot), float(trans))
    with pytest.raises(RegistrationError, match="divide the image size"):
        reg.register_coarse(prep, f[1:2], eye, (7,))


def test_constant_velocity_init_extrapolates():
    _, _, reg = run([True] * 4, init="constant_velocity")
    ref, tar, init = reg.calls[-1]  # frame 3 against keyframe 0
    expected = torch.linalg.inv(torch.linalg.inv(pose(0)) @ pose(2) @ torch.linalg.inv(pose(1)) @ pose(2))
    torch.testing.assert_close(init, expected)
    true = torch.linalg.inv(pose(3)) @ pose(0)
    torch.testing.assert_close(init, true)  # exact for a constant-velocity motion


def _rz(deg: float) -> torch.Tensor:
    a = math.radians(deg)
    T = torch.eye(4, dtype=torch.float64)
    T[:2, :2] = torch.tensor([[math.cos(a), -math.sin(a)], [math.sin(a), math.cos(a)]])
    return T


def _slip_at_4(r, t):
    """Against an older keyframe, frame 4 converges 12 degrees off (CCS/SCR still pass)."""
    return _rz(12.0) if (t == 4 and r < 3) else None


def test_implausible_jump_is_a_failure_and_the_retry_recovers():
    steps, kfs, reg = run([True] * 7, slip=_slip_at_4)
    assert reg.tracker.implausible == 1
    s4 = steps[4]
    assert [k.video_index for k in s4.keyframes] == [3] and not s4.is_keyframe and s4.session == 0
    assert [c[:2] for c in reg.calls[-3:]] == [(3, 4), (3, 5), (3, 6)]  # retry, then onwards from frame 3
    check_poses(steps, kfs)  # the slip never entered a pose


def test_speed_limits_scale_with_the_frame_interval_and_can_be_disabled():
    # at 2 fps the same 12-degree slip is below 125 deg/s * 0.5 s: accepted, pose wrong
    steps, kfs, reg = run([True] * 7, slip=_slip_at_4, fps=2.0)
    assert reg.tracker.implausible == 0 and [k.video_index for k in kfs] == [0, 6]
    with pytest.raises(AssertionError):
        check_poses(steps, kfs)
    _, kfs, reg = run([True] * 7, slip=_slip_at_4, max_deg_per_s=None)
    assert reg.tracker.implausible == 0 and [k.video_index for k in kfs] == [0, 6]
    # a translation slip is caught by the translation limit alone
    shift = torch.eye(4, dtype=torch.float64)
    shift[0, 3] = 2e-3
    _, kfs, reg = run([True] * 7, slip=lambda r, t: shift if (t == 4 and r < 3) else None, max_deg_per_s=None)
    assert reg.tracker.implausible == 1 and 3 in [k.video_index for k in kfs]


@pytest.mark.parametrize("mode, error_deg", [("forward", 1.0), ("reverse", 0.0), ("midpoint", 0.5)])
def test_keyframe_edge_direction(mode, error_deg):
    # tracking frame 3 from keyframe 0 converges 1 deg off; frame 4 fails against keyframe 0,
    # so frame 3 becomes the keyframe; registering keyframe 0 against frame 3 is exact
    steps, kfs, reg = run([True] * 6, fails=lambda r, t: (r, t) == (0, 4),
                          slip=lambda r, t: _rz(1.0) if (r, t) == (0, 3) else None, keyframe_edge=mode)
    assert [k.video_index for k in kfs] == [0, 3, 5]
    true = torch.linalg.inv(pose(0)) @ pose(3)
    assert float(pose_error(kfs[1].prev_T_kf[None], true[None])[0]) == pytest.approx(error_deg, abs=1e-6)
    # the frames tracked from keyframe 3 are exact, so their error is the edge's alone
    est = kfs[1].prev_T_kf @ steps[4].kf_T_frame
    true4 = torch.linalg.inv(pose(0)) @ pose(4)
    assert float(pose_error(est[None], true4[None])[0]) == pytest.approx(error_deg, abs=1e-6)


def test_failed_reverse_edge_keeps_the_tracked_edge():
    _, kfs, _ = run([True] * 6, fails=lambda r, t: (r, t) in ((0, 4), (3, 0)),
                    slip=lambda r, t: _rz(1.0) if (r, t) == (0, 3) else None, keyframe_edge="reverse")
    true = torch.linalg.inv(pose(0)) @ pose(3)
    assert float(pose_error(kfs[1].prev_T_kf[None], true[None])[0]) == pytest.approx(1.0, abs=1e-6)


@pytest.mark.parametrize("fps", [float("inf"), float("nan")])  # timestamps all 0 / all NaN (unknown)
def test_frames_without_timestamps_are_not_speed_checked(fps):
    _, kfs, reg = run([True] * 7, slip=_slip_at_4, fps=fps)
    assert reg.tracker.implausible == 0 and [k.video_index for k in kfs] == [0, 6]


def test_bad_config_and_batch():
    with pytest.raises(ValueError, match="tracking.init"):
        Tracker(TrackingConfig(init="magic"), ScriptedRegistrar(lambda r, t: False))
    with pytest.raises(ValueError, match="tracking.keyframe_edge"):
        Tracker(TrackingConfig(keyframe_edge="both"), ScriptedRegistrar(lambda r, t: False))
    for bad in (0.0, -5.0, float("nan"), float("inf")):
        with pytest.raises(ValueError, match="max_deg_per_s"):
            Tracker(TrackingConfig(max_deg_per_s=bad), ScriptedRegistrar(lambda r, t: False))
        with pytest.raises(ValueError, match="max_mm_per_s"):
            Tracker(TrackingConfig(max_mm_per_s=bad), ScriptedRegistrar(lambda r, t: False))
        with pytest.raises(ValueError, match="decoded_max_tilt_deg"):
            Tracker(TrackingConfig(decoded_max_tilt_deg=bad), ScriptedRegistrar(lambda r, t: False))
        with pytest.raises(ValueError, match="tracking.max_tilt_deg"):
            Tracker(TrackingConfig(max_tilt_deg=bad), ScriptedRegistrar(lambda r, t: False))
        with pytest.raises(ValueError, match="f2f_check_deg"):
            Tracker(TrackingConfig(f2f_check_deg=bad), ScriptedRegistrar(lambda r, t: False))
        with pytest.raises(ValueError, match="f2f_below_conditioning"):
            Tracker(TrackingConfig(f2f_below_conditioning=bad), ScriptedRegistrar(lambda r, t: False))
    for bad in ((1,), (2.5,), (True,)):
        with pytest.raises(ValueError, match="fallback_factors"):
            Tracker(TrackingConfig(fallback_factors=bad), ScriptedRegistrar(lambda r, t: False))
    for bad in (-1.0, float("nan"), float("inf"), True):
        with pytest.raises(ValueError, match="keep_contact_mm2"):
            Tracker(TrackingConfig(keep_contact_mm2=bad), ScriptedRegistrar(lambda r, t: False))
    tr = Tracker(TrackingConfig(), ScriptedRegistrar(lambda r, t: False))
    with pytest.raises(ValueError, match="one frame"):
        tr.step(Frame.cat([frame(0), frame(1)]))


class RibRegistrar(ScriptedRegistrar):
    """Every registration slips by ``slip`` (a rib over) with CCS 0.9, except the
    keyframe-edge batch's start ``right``, which finds the truth (moved by ``off``) with CCS
    ``right_ccs``."""

    def __init__(self, slip: torch.Tensor, right: int, right_ccs: float, off: torch.Tensor | None = None):
        super().__init__(lambda r, t: False, lambda r, t: slip)
        self.right, self.right_ccs = right, right_ccs
        self.off = torch.eye(4, dtype=torch.float64) if off is None else off

    def register(self, ref_index, tar: Frame, init):
        res = super().register(ref_index, tar, init)
        if len(tar) == 5:
            truth = torch.linalg.inv(pose(int(tar.index[0]))) @ pose(ref_index)
            res.tar_T_ref[self.right] = self.off @ truth
            res.ccs[self.right] = self.right_ccs
        return res


def _rib(mm: float = 0.45) -> torch.Tensor:
    slip = torch.eye(4, dtype=torch.float64)
    slip[0, 3] = mm * 1e-3
    return slip


@pytest.mark.parametrize("off_mm, right_ccs, moved", [(0.0, 0.95, True), (0.0, 0.905, False), (-2.0, 0.95, False)])
def test_keyframe_edge_takes_a_nearby_start_that_scores_higher(off_mm, right_ccs, moved):
    """Frame 3 fails against keyframe 0, so frame 2 becomes a keyframe; its tracked pose
    slipped a rib. A shifted start that verifies with a CCS higher by more than the margin
    (0.01) gives the keyframe edge; within the margin, or beyond one frame's motion (1 mm)
    from the tracked pose (2.45 mm here), the tracked pose stays."""
    reg = RibRegistrar(_rib(), right=3, right_ccs=right_ccs, off=_rib(off_mm))
    reg.fails = lambda r, t: (r, t) == (0, 3)
    tr = Tracker(TrackingConfig(), reg)
    kfs = [k for i in range(5) for k in tr.step(frame(i)).keyframes]
    edge = kfs[1].prev_T_kf
    truth = torch.linalg.inv(pose(0)) @ pose(2)
    slipped = torch.linalg.inv(_rib() @ torch.linalg.inv(pose(2)) @ pose(0))
    torch.testing.assert_close(edge, truth if moved else slipped)
    assert tr.moved_edges == int(moved)


def test_keyframe_edge_check_off_and_bad_settings():
    reg = RibRegistrar(_rib(), right=1, right_ccs=0.99)
    reg.fails = lambda r, t: (r, t) == (0, 3)
    tr = Tracker(TrackingConfig(keyframe_near_mm=None), reg)
    kfs = [k for i in range(5) for k in tr.step(frame(i)).keyframes]
    torch.testing.assert_close(kfs[1].prev_T_kf, torch.linalg.inv(_rib() @ torch.linalg.inv(pose(2)) @ pose(0)))
    assert tr.moved_edges == 0
    for bad in ({"keyframe_near_mm": 0.0}, {"keyframe_near_mm": math.nan}, {"keyframe_near_margin": -0.1},
                {"keyframe_near_margin": math.inf}, {"keyframe_near_max_deg": math.nan},
                {"keyframe_near_max_mm": -1.0}, {"keyframe_near_rounds": 0}, {"keyframe_near_rounds": 1.5},
                {"keyframe_near_rounds": True}):
        with pytest.raises(ValueError, match="keyframe_near"):
            Tracker(TrackingConfig(**bad), reg)


class PreviousFrameRegistrar(RibRegistrar):
    """:class:`RibRegistrar` (the edge search finds the truth) with every registration's
    conditioning ``conditioning``; the previous-frame batch (``B = 2``: the tracked, then
    the moved start) converges to its starts with CCS ``prev_ccs``. Counts those batches."""

    def __init__(self, conditioning: float, prev_ccs: tuple[float, float], fails):
        super().__init__(_rib(), right=3, right_ccs=0.95)
        self.fails, self.conditioning, self.prev_ccs, self.pairs = fails, conditioning, prev_ccs, 0

    def register(self, ref_index, tar: Frame, init):
        res = super().register(ref_index, tar, init)
        if len(tar) == 2:
            self.pairs += 1
            res.tar_T_ref[:] = init.to(res.tar_T_ref.dtype)
            res.ccs[:] = torch.tensor(self.prev_ccs, dtype=res.ccs.dtype)
        return res


@pytest.mark.parametrize("conditioning, prev_ccs, fails_at, moved, asked", [
    (1e-3, (0.9, 0.95), 3, True, True),  # weak: the frame before the new keyframe prefers the move
    (1e-3, (0.95, 0.9), 3, False, True),  # weak: it prefers the tracked edge, which stays
    (1e-3, (0.9, 0.905), 3, False, True),  # weak: the move wins by less than the margin
    (0.1, (0.95, 0.9), 3, True, False),  # well constrained: the search alone decides
    (1e-3, (0.95, 0.9), 2, True, False),  # the frame before the new keyframe is the keyframe
])
def test_weak_keyframe_edge_moves_only_where_the_previous_frame_agrees(conditioning, prev_ccs, fails_at, moved,
                                                                        asked):
    """On a lattice a shift of one period can score higher against an older keyframe than
    the truth (the unseen knurl s2). Where the tracked edge is weakly constrained (below
    ``f2f_below_conditioning``), the frame before the new keyframe is registered against it
    from both poses, and the move stands only if that scores it higher by the margin."""
    reg = PreviousFrameRegistrar(conditioning, prev_ccs, lambda r, t: (r, t) == (0, fails_at))
    tr = Tracker(TrackingConfig(), reg)
    kfs = [k for i in range(5) for k in tr.step(frame(i)).keyframes]
    b = fails_at - 1  # the new keyframe
    truth = torch.linalg.inv(pose(0)) @ pose(b)
    slipped = torch.linalg.inv(_rib() @ torch.linalg.inv(pose(b)) @ pose(0))
    torch.testing.assert_close(kfs[1].prev_T_kf, truth if moved else slipped)
    assert (tr.moved_edges, tr.kept_edges) == (int(moved), int(asked and not moved))
    assert reg.pairs == int(asked)


def test_weak_keyframe_edge_check_follows_the_cross_check_switch():
    """With the frame-to-frame cross-check off, no edge is weak: the search alone decides."""
    reg = PreviousFrameRegistrar(1e-3, (0.95, 0.9), lambda r, t: (r, t) == (0, 3))
    tr = Tracker(TrackingConfig(f2f_check_deg=None), reg)
    kfs = [k for i in range(5) for k in tr.step(frame(i)).keyframes]
    torch.testing.assert_close(kfs[1].prev_T_kf, torch.linalg.inv(pose(0)) @ pose(2))
    assert (tr.moved_edges, tr.kept_edges, reg.pairs) == (1, 0, 0)


class LatticeRegistrar(ScriptedRegistrar):
    """Ribs 0.45 mm apart along x: tracking (``B = 1``) slips ``ribs`` ribs; a start of the
    keyframe-edge batch converges to the rib nearest to it, with CCS 0.99 at the truth and
    0.04 less per rib away. Counts the batches."""

    def __init__(self, ribs: int):
        super().__init__(lambda r, t: (r, t) == (0, 3), lambda r, t: _rib(0.45 * ribs))
        self.batches = 0

    def register(self, ref_index, tar: Frame, init):
        res = super().register(ref_index, tar, init)
        if len(tar) == 5:
            self.batches += 1
            truth = torch.linalg.inv(pose(int(tar.index[0]))) @ pose(ref_index)
            k = torch.round((init.double() @ torch.linalg.inv(truth))[:, 0, 3] / 0.45e-3)
            for b in range(5):
                res.tar_T_ref[b] = _rib(0.45 * float(k[b])) @ truth
            res.ccs[:] = (0.99 - 0.04 * k.abs()).to(res.ccs.dtype)
        return res


@pytest.mark.parametrize("ribs, rounds, left, batches", [(2, 3, 0, 3), (2, 1, 1, 1), (3, 3, 1, 3), (1, 3, 0, 2)])
def test_keyframe_edge_search_repeats_from_the_new_best(ribs, rounds, left, batches):
    """A slip of two ribs needs two rounds (each start is 0.5 mm away, and converges to the
    nearest rib); a third round stops when nothing beats the truth. The motion limit (1 mm)
    counts from the tracked pose's result, so a slip of three ribs (1.35 mm) ends one rib
    short. Within ``keyframe_near_rounds`` batches."""
    reg = LatticeRegistrar(ribs)
    tr = Tracker(TrackingConfig(keyframe_near_rounds=rounds), reg)
    kfs = [k for i in range(5) for k in tr.step(frame(i)).keyframes]
    truth = torch.linalg.inv(pose(2)) @ pose(0)  # tar_T_ref of the edge
    torch.testing.assert_close(kfs[1].prev_T_kf, torch.linalg.inv(_rib(0.45 * left) @ truth))
    assert tr.moved_edges == 1
    assert reg.batches == batches


def _tilt_pose(i: int) -> torch.Tensor:
    """Frame i tilted 2 degrees per frame about x from frame 0, shifted 0.1 mm per frame."""
    a = math.radians(2.0 * i)
    T = torch.eye(4, dtype=torch.float64)
    T[1:3, 1:3] = torch.tensor([[math.cos(a), -math.sin(a)], [math.sin(a), math.cos(a)]])
    T[0, 3] = 1e-4 * i
    return T


class TiltRegistrar(ScriptedRegistrar):
    def _answer(self, ref_index, tar_index, b, ok):
        t = torch.linalg.inv(_tilt_pose(tar_index)) @ _tilt_pose(ref_index)
        full = lambda v, dt=torch.float64: torch.full((b,), v, dtype=dt)  # noqa: E731
        return RegistrationResult(t.expand(b, 4, 4).clone(), full(0.9), full(0.9), full(100, torch.int64),
                                  full(7, torch.int64), full(True, torch.bool), full(ok, torch.bool), full(0.1))


@pytest.mark.parametrize("decoded, limit, all_limit, keyframes, tilted", [
    (False, 5.5, None, [0, 9], 0),  # gradients given as input: one keyframe for 18 deg
    (True, None, None, [0, 9], 0),  # no limit
    (True, 5.5, None, [0, 2, 4, 6, 8, 9], 4),  # a third frame would be 6 deg from its keyframe
    (True, 9.0, None, [0, 4, 8, 9], 2),
    (False, 5.5, 9.0, [0, 4, 8, 9], 2),  # the limit for every frame
    (True, 5.5, 9.0, [0, 2, 4, 6, 8, 9], 4),  # decoded: the smaller of the two
    (True, 9.0, 5.5, [0, 2, 4, 6, 8, 9], 4),
    (True, None, 9.0, [0, 4, 8, 9], 2),
])
def test_frames_keep_their_keyframe_within_the_tilt_limits(decoded, limit, all_limit, keyframes, tilted):
    reg = TiltRegistrar(lambda r, t: False)
    tr = Tracker(TrackingConfig(decoded_max_tilt_deg=limit, max_tilt_deg=all_limit), reg)
    steps = [tr.step(replace(frame(i), decoded=decoded)) for i in range(10)]
    kfs = [k for s in steps for k in s.keyframes] + tr.finish()
    assert [k.video_index for k in kfs] == keyframes and tr.tilted == tilted
    assert all(s.in_contact and s.session == 0 for s in steps)
    kf_pose = {}
    for k in kfs:  # the chain of keyframe edges and each frame's pose in its keyframe give the truth
        kf_pose[k.id] = torch.eye(4, dtype=torch.float64) if k.new_session else kf_pose[k.id - 1] @ k.prev_T_kf
    for s in steps:
        torch.testing.assert_close(kf_pose[s.keyframe_id] @ s.kf_T_frame, _tilt_pose(s.index))
        assert decoded is False or limit is None or float(se3.tilt_deg(s.kf_T_frame)) <= limit + 1e-9


class CountingRegistrar(ScriptedRegistrar):
    def __init__(self, *args, **kwargs):
        super().__init__(*args, **kwargs)
        self.prepared: list[int] = []

    def prepare(self, ref: Frame):
        self.prepared.append(int(ref.index[0]))
        return super().prepare(ref)


def test_a_frame_the_cross_check_prepared_is_not_prepared_again_as_keyframe():
    """Frame 3's registration against keyframe 0 is 2 deg off; the cross-check prepares
    frame 2 to register frame 3 against it, refuses, and the lazy rule makes frame 2 the
    keyframe from that same preparation. Poses stay exact."""
    turn = torch.eye(4, dtype=torch.float64)
    turn[:2, :2] = torch.tensor([[math.cos(0.035), -math.sin(0.035)], [math.sin(0.035), math.cos(0.035)]])
    reg = CountingRegistrar(lambda r, t: False, lambda r, t: turn if (r, t) == (0, 3) else None, conditioning=1e-3)
    tr = Tracker(TrackingConfig(keyframe_near_mm=None), reg)
    steps = [tr.step(frame(i)) for i in range(5)]
    kfs = [k for s in steps for k in s.keyframes] + tr.finish()
    assert tr.f2f_refusals == 1 and [k.video_index for k in kfs] == [0, 2, 4]
    assert sorted(reg.prepared) == [0, 1, 2, 3, 4]  # each frame once: checks 1-3, keyframes 0, 2 and the tail 4
    check_poses(steps, kfs)
