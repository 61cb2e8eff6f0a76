"""The tracker: NormalFlow from the current keyframe to each frame, lazy keyframes,
sessions (method.md section 5).

Beyond the method's CCS/SCR failure test, a registration against an older keyframe that
implies a sensor motion since the previous frame faster than ``tracking.max_deg_per_s`` /
``max_mm_per_s`` counts as a failure (motion continuity): on a line contact or a periodic
texture NormalFlow can converge to a wrong alignment that the scores cannot tell apart,
and the lazy rule's retry from the previous frame recovers; a legitimately fast motion is
accepted by that retry and only costs a keyframe (docs/benchmarks.md).

The same holds for a registration more than ``tracking.max_tilt_deg`` out of plane from
its keyframe: NormalFlow's error grows with the tilt, and on a roll it can stall with
high scores (docs/benchmarks.md, "Keyframe tilt limit"). For frames decoded from images the
limit is ``tracking.decoded_max_tilt_deg`` where smaller: the decoder flattens steep
slopes, so a long out-of-plane baseline is measured short ("Keyframes from video").

A new keyframe's pose in the previous keyframe (the odometry edge of the pose graph) is
registered again, in one batch, from starts shifted by ``tracking.keyframe_near_mm`` along
+-x and +-y; a verified result whose CCS beats the tracked one by more than
``tracking.keyframe_near_margin``, within one frame's motion limit of it
(``keyframe_near_max_deg``, ``keyframe_near_max_mm``), replaces it, and the search repeats
from there (``keyframe_near_rounds`` batches at most). On ribs about as far apart as a
frame's step, tracking slips to the neighbouring rib (or the next) and verifies there,
with a lower CCS than at the truth (docs/benchmarks.md, "Keyframe edges").
Where the tracked edge is weakly constrained (the frame-to-frame cross-check's
conditioning boundary below), a moved edge must also win from the frame before the new
keyframe: that frame is registered against the new keyframe from the tracked and from the
moved pose, and the move stands only where the moved start verifies with a CCS higher by
the same margin. On a lattice (the knurl) a shift of one period can score higher against
an older keyframe than the truth does, on a small contact ("Keyframe edges on a lattice").
With ``tracking.keyframe_edge`` ``"reverse"`` or ``"midpoint"`` the edge is then measured
the other way round too, the previous keyframe against the new one, and that result or
the midpoint of the two directions replaces it ("Keyframe edge direction").

Sessions: a frame whose registration fails against both the keyframe and the previous
frame is tried once more against the previous frame through ``tracking.fallback_factors``
coarse levels before it starts a new session ("Coarse fallback"); a running session goes
on through frames whose contact area is below the in-contact minimum but at least
``tracking.keep_contact_mm2`` ("Contact hysteresis").

A pure algorithm object: state plus :meth:`Tracker.step`. It never reads files or
times itself; the pipeline does that.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, replace
from typing import Any, Protocol

import torch

from tactile_slam.config import KEYFRAME_EDGES, TRACKING_INITS, NormalFlowConfig, TrackingConfig, lower_limit
from tactile_slam.geometry.frame import Frame, own_maps
from tactile_slam.posegraph import se3
from tactile_slam.registration.normalflow import prepare_reference, register_prepared
from tactile_slam.registration.result import RegistrationResult, pose_error
from tactile_slam.tracking.keyframe import Keyframe


class Registrar(Protocol):
    """Registers frames against a prepared reference (NormalFlow, or a test double)."""

    def prepare(self, ref: Frame) -> Any: ...

    def register(self, prepared: Any, tar: Frame, init_tar_T_ref: torch.Tensor) -> RegistrationResult: ...

    def register_coarse(self, prepared: Any, tar: Frame, init_tar_T_ref: torch.Tensor,
                        factors: tuple[int, ...]) -> RegistrationResult: ...


class NormalFlowRegistrar:
    """:class:`Registrar` backed by NormalFlow with the tracking thresholds.

    Args:
        normalflow: solver settings; its CCS/SCR thresholds are replaced by ``tracking``'s.
        tracking: CCS/SCR thresholds for tracking.
    """

    def __init__(self, normalflow: NormalFlowConfig, tracking: TrackingConfig):
        self.config = replace(
            normalflow, ccs_threshold=tracking.ccs_threshold, scr_threshold=tracking.scr_threshold
        )

    def prepare(self, ref: Frame):
        return prepare_reference(ref, self.config)

    def register(self, prepared, tar: Frame, init_tar_T_ref: torch.Tensor) -> RegistrationResult:
        return register_prepared(prepared, tar, init_tar_T_ref, self.config)

    def register_coarse(self, prepared, tar: Frame, init_tar_T_ref: torch.Tensor,
                        factors: tuple[int, ...]) -> RegistrationResult:
        """As :meth:`register`, through levels of block-averaged maps (``factors``, coarse
        to fine) before the full-resolution one: a wider basin."""
        wide = prepared.retry_levels(None, factors, self.config.jacobian)
        return register_prepared(wide, tar, init_tar_T_ref, replace(self.config, coarse_factors=factors,
                                                                    fallback_factors=()))


@dataclass
class TrackStep:
    """What :meth:`Tracker.step` reports for one frame.

    Attributes:
        index: the frame's video index.
        in_contact: whether the frame was tracked at all.
        kf_T_frame: ``(4, 4)`` float64 metres, the frame's sensor pose in its keyframe
            (``None`` without contact).
        keyframe_id / session: ids of the frame's keyframe and tracking session.
        ccs / scr: quality scores of the accepted registration (NaN for keyframes
            that start a session).
        keyframes: keyframes emitted by this step, in id order (0, 1 or 2; a flushed
            session tail is emitted by the first non-contact step).
        is_keyframe: this frame itself became a keyframe.
        conditioning: the accepted registration's conditioning (smallest over largest
            eigenvalue of its normal equations, :class:`RegistrationResult`): small where
            the contact leaves a motion weakly constrained (an edge, a groove, a lattice);
            NaN where ``ccs`` is.
    """

    index: int
    in_contact: bool
    kf_T_frame: torch.Tensor | None = None
    keyframe_id: int | None = None
    session: int | None = None
    ccs: float = float("nan")
    scr: float = float("nan")
    keyframes: list[Keyframe] = field(default_factory=list)
    is_keyframe: bool = False
    conditioning: float = float("nan")


def _eye() -> torch.Tensor:
    return torch.eye(4, dtype=torch.float64)


def check_keep_contact(keep_contact_mm2: float | None) -> None:
    """``tracking.keep_contact_mm2`` is ``None`` or a finite number >= 0."""
    if keep_contact_mm2 is not None and (isinstance(keep_contact_mm2, bool)
                                         or not (math.isfinite(keep_contact_mm2) and keep_contact_mm2 >= 0)):
        raise ValueError(f"tracking.keep_contact_mm2 must be a finite number >= 0 or None, got {keep_contact_mm2!r}")


def holds_contact(frame: Frame, running: bool, keep_contact_mm2: float | None) -> bool:
    """Whether a ``B = 1`` frame is tracked: it is in contact, or a session is
    ``running`` and its eroded contact area is at least ``keep_contact_mm2`` (mm^2;
    ``None``: never)."""
    if bool(frame.in_contact[0]):
        return True
    return running and keep_contact_mm2 is not None and \
        float(frame.contact.sum()) * frame.mm_per_px ** 2 >= keep_contact_mm2


def _kf_T_frame(res: RegistrationResult) -> torch.Tensor:
    """``(4, 4)`` float64 pose of the target frame in the keyframe from a ``B = 1`` result."""
    return torch.linalg.inv(res.tar_T_ref[0].to(torch.float64).cpu())


class Tracker:
    """Lazy-keyframe tracker.

    Args:
        config: tracking settings (thresholds are applied by the registrar; here
            ``flush_session_tail`` and ``init``).
        registrar: registration backend.
    """

    def __init__(self, config: TrackingConfig, registrar: Registrar):
        if config.init not in TRACKING_INITS:
            raise ValueError(f"tracking.init must be one of {TRACKING_INITS}, got {config.init!r}")
        if config.keyframe_edge not in KEYFRAME_EDGES:
            raise ValueError(f"tracking.keyframe_edge must be one of {KEYFRAME_EDGES}, got {config.keyframe_edge!r}")
        for name in ("max_deg_per_s", "max_mm_per_s", "keyframe_near_mm", "decoded_max_tilt_deg", "max_tilt_deg",
                     "f2f_check_deg", "f2f_below_conditioning"):
            v = getattr(config, name)
            if v is not None and not (math.isfinite(v) and v > 0):
                raise ValueError(f"tracking.{name} must be a positive number or None, got {v!r}")
        for name in ("keyframe_near_margin", "keyframe_near_max_deg", "keyframe_near_max_mm"):
            v = getattr(config, name)
            if not (math.isfinite(v) and v >= 0):
                raise ValueError(f"tracking.{name} must be a finite number >= 0, got {v!r}")
        if isinstance(config.keyframe_near_rounds, bool) or not isinstance(config.keyframe_near_rounds, int) \
                or config.keyframe_near_rounds < 1:
            raise ValueError(
                f"tracking.keyframe_near_rounds must be an integer >= 1, got {config.keyframe_near_rounds!r}")
        check_keep_contact(config.keep_contact_mm2)
        if any(isinstance(f, bool) or not isinstance(f, int) or f < 2 for f in config.fallback_factors):
            raise ValueError(f"tracking.fallback_factors must be integers >= 2, got {config.fallback_factors!r}")
        self.config = config
        self.registrar = registrar
        self.next_keyframe_id = 0
        self.next_session = 0
        self.kf: Keyframe | None = None
        self.kf_prepared: Any = None
        self.prev: Frame | None = None
        self.prevprev: Frame | None = None  # the frame before prev, at kf_T_prevprev; None if it is the keyframe
        self._recent: list[tuple[Frame, Any]] = []  # (frame, prepared) of prev / prevprev, at most 2
        self.kf_T_prev = _eye()
        self.kf_T_prevprev: torch.Tensor | None = None
        self.prev_is_keyframe = False
        self.prev_in_contact = False
        self.implausible = 0  # registrations refused by the motion-continuity check
        self.moved_edges = 0  # keyframe edges replaced by a better-scoring nearby alignment
        self.kept_edges = 0  # nearby alignments the frame before the new keyframe refused
        self.coarse_rescues = 0  # frames kept in their session by the coarse fallback
        self.registration_breaks = 0  # sessions started inside a contact: registration failed
        self.tilted = 0  # registrations refused for their tilt from the keyframe
        self.f2f_checks = 0  # frames registered against the previous frame by the cross-check
        self.f2f_refusals = 0  # keyframe registrations refused by the frame-to-frame cross-check

    # ----------------------------------------------------------------- helpers
    def _make_keyframe(self, frame: Frame, new_session: bool, prev_T_kf: torch.Tensor) -> Keyframe:
        if not new_session and self.config.keyframe_near_mm is not None:
            prev_T_kf = self._best_nearby(frame, prev_T_kf)
        prepared = self._prepare(frame)
        if not new_session and self.config.keyframe_edge != "forward":
            prev_T_kf = self._reverse_edge(prepared, prev_T_kf)
        if new_session:
            self.next_session += 1
        session = self.next_session - 1
        # a copy without gradients: the frame is usually a view of its geometry batch, which
        # it would keep alive; the pipeline crops it to the contact once the back end has it
        kf = Keyframe(self.next_keyframe_id, session, own_maps(frame), new_session, prev_T_kf.clone(),
                      prepared=prepared)
        self.next_keyframe_id += 1
        self.kf = kf
        self.kf_prepared = prepared  # kept here too: the pipeline's Keyframe.compact() drops kf.prepared
        return kf

    def _prepare(self, frame: Frame) -> Any:
        """``registrar.prepare(frame)``, reused while ``frame`` (the same object) is the
        previous frame or the one before it: the cross-check prepares the previous frame,
        which the lazy rule may make the keyframe next, and the keyframe-edge check reads
        the frame before that."""
        for f, prepared in self._recent:
            if f is frame:
                return prepared
        prepared = self.registrar.prepare(frame)
        self._recent = [(f, p) for f, p in self._recent if f is self.prev or f is self.prevprev][-1:]
        self._recent.append((frame, prepared))
        return prepared

    def _reverse_edge(self, prepared: Any, prev_T_kf: torch.Tensor) -> torch.Tensor:
        """The edge ``prev_T_kf`` (new keyframe in the current one) measured the other way
        round: the current keyframe registered against the new one (``prepared``), started
        from the tracked edge. ``"reverse"`` returns that result, ``"midpoint"`` the
        geodesic midpoint of the two; a failed registration returns ``prev_T_kf``."""
        res = self.registrar.register(prepared, self.kf.frame, prev_T_kf[None])[0]
        if not bool(res.ok):
            return prev_T_kf
        back = res.tar_T_ref[0].to(torch.float64).cpu()
        if self.config.keyframe_edge == "reverse":
            return back
        return prev_T_kf @ se3.exp(0.5 * se3.log(torch.linalg.inv(prev_T_kf) @ back))

    def _best_nearby(self, frame: Frame, prev_T_kf: torch.Tensor) -> torch.Tensor:
        """``frame``'s pose in the current keyframe, registered again from ``prev_T_kf`` and
        from it shifted by ``keyframe_near_mm`` along +-x and +-y (one batch against the
        prepared keyframe): the verified result with the highest CCS within
        ``keyframe_near_max_deg`` / ``_mm`` of the first start's, where it beats that one by
        more than ``keyframe_near_margin``. While that moves the pose, the search repeats
        from the new best (up to ``keyframe_near_rounds`` batches), each round's best having
        to beat the last by the margin, the limit still counted from the first start's
        result: a slip of two ribs needs two steps. Where the first start's result is weakly
        constrained (:meth:`_weak`), the frame before ``frame`` must prefer the move too
        (:meth:`_previous_prefers_move`). Returns ``prev_T_kf`` if nothing beat it."""
        c = self.config
        moves = torch.cat([_eye()[None], se3.shifts_xy(c.keyframe_near_mm / 1000.0)])
        tracked = torch.linalg.inv(prev_T_kf)
        start, first, first_cond, best_ccs = tracked, None, None, None
        for _ in range(c.keyframe_near_rounds):
            res = self.registrar.register(self.kf_prepared, Frame.cat([frame] * 5), moves @ start)
            T = res.tar_T_ref.to(torch.float64).cpu()
            if first is None:
                first, first_cond = T[:1], res.conditioning[0]
            rot, trans = pose_error(T, first.expand(5, 4, 4))
            near = (rot <= c.keyframe_near_max_deg) & (trans <= c.keyframe_near_max_mm)
            score = torch.where(res.ok.cpu() & near, res.ccs.double().cpu().nan_to_num(-math.inf), -math.inf)
            if best_ccs is None:  # first round: the re-registered tracked pose is the one to beat
                best_ccs = float(score[0])
            score[0] = best_ccs + c.keyframe_near_margin
            k = int(score.argmax())
            if k == 0 or not math.isfinite(float(score[k])):
                break
            start, best_ccs = T[k], float(score[k])
        if start is tracked:
            return prev_T_kf
        moved = torch.linalg.inv(start)
        if self._weak(float(first_cond)) and not self._previous_prefers_move(frame, prev_T_kf, moved):
            self.kept_edges += 1
            return prev_T_kf
        self.moved_edges += 1
        return moved

    def _weak(self, conditioning: float) -> bool:
        """Whether a registration of this ``conditioning`` gets the frame-to-frame
        cross-check (``tracking.f2f_check_deg`` on, conditioning below
        ``tracking.f2f_below_conditioning`` or NaN; ``None``: every one)."""
        below = self.config.f2f_below_conditioning
        return self.config.f2f_check_deg is not None and (below is None or not conditioning >= below)

    def _previous_prefers_move(self, frame: Frame, tracked: torch.Tensor, moved: torch.Tensor) -> bool:
        """Whether the frame before ``frame`` (the new keyframe) agrees with moving its edge
        from ``tracked`` to ``moved`` (both ``(4, 4)`` poses of ``frame`` in the current
        keyframe): registered against ``frame`` from both poses in one batch, the moved start
        must verify with a CCS higher than the tracked start's by more than
        ``tracking.keyframe_near_margin`` (a failed tracked start counts as lowest). True
        when that frame is the keyframe itself (:attr:`prevprev` ``None``): then the search's
        own comparison was already the previous frame's."""
        if self.prevprev is None:
            return True
        starts = torch.stack([torch.linalg.inv(edge) @ self.kf_T_prevprev for edge in (tracked, moved)])  # frame_T_pp
        res = self.registrar.register(self._prepare(self.prevprev), Frame.cat([frame] * 2), starts)
        ccs = torch.where(res.ok.cpu(), res.ccs.double().cpu().nan_to_num(-math.inf), -math.inf)
        return bool(res.ok[1]) and float(ccs[1]) > float(ccs[0]) + self.config.keyframe_near_margin

    def _init_guess(self) -> torch.Tensor:
        """Initial tar_T_ref = inv(predicted kf_T_frame)."""
        pred = self.kf_T_prev
        if self.config.init == "constant_velocity" and self.kf_T_prevprev is not None:
            pred = self.kf_T_prev @ torch.linalg.inv(self.kf_T_prevprev) @ self.kf_T_prev
        return torch.linalg.inv(pred)

    def _register(self, frame: Frame, init: torch.Tensor) -> RegistrationResult:
        return self.registrar.register(self.kf_prepared, frame, init[None])[0]

    def _flush_tail(self) -> list[Keyframe]:
        if not self.config.flush_session_tail or self.prev is None or self.prev_is_keyframe or not self.prev_in_contact:
            return []
        kf = self._make_keyframe(self.prev, False, self.kf_T_prev)
        self.kf_T_prev, self.kf_T_prevprev, self.prevprev, self.prev_is_keyframe = _eye(), None, None, True
        return [kf]

    # ----------------------------------------------------------------- API
    def step(self, frame: Frame) -> TrackStep:
        """Track one frame (``Frame`` with ``B = 1``)."""
        if len(frame) != 1:
            raise ValueError(f"Tracker.step takes one frame, got a batch of {len(frame)}")
        index = int(frame.index[0])
        if not holds_contact(frame, self.prev_in_contact, self.config.keep_contact_mm2):
            return self._lost(index, self._flush_tail())
        weak = not bool(frame.in_contact[0])  # below the minimum: continues a session, never starts one

        if not self.prev_in_contact:
            kf = self._new_session(frame)
            return self._done(frame, TrackStep(index, True, _eye(), kf.id, kf.session, keyframes=[kf],
                                               is_keyframe=True))

        res = self._register(frame, self._init_guess())
        if bool(res.ok):
            kf_T_frame = _kf_T_frame(res)
            if self.prev_is_keyframe or (self._continuous(frame, kf_T_frame)
                                         and self._within_tilt(frame, kf_T_frame)
                                         and self._agrees_with_previous(frame, res)):
                return self._tracked(frame, res, kf_T_frame, [])
        if self.prev_is_keyframe:
            res = self._coarse(frame)
            if res is not None:
                return self._tracked(frame, res, _kf_T_frame(res), [])
            if weak:
                return self._lost(index, [])
            kf = self._new_session(frame, broke=True)
            return self._done(frame, TrackStep(index, True, _eye(), kf.id, kf.session, keyframes=[kf],
                                               is_keyframe=True))
        # lazy keyframe rule: the previous frame becomes a keyframe, then retry
        prev_kf = self._make_keyframe(self.prev, False, self.kf_T_prev)
        old_kf_T_prev = prev_kf.prev_T_kf
        self.kf_T_prevprev = (
            torch.linalg.inv(old_kf_T_prev) @ self.kf_T_prevprev if self.kf_T_prevprev is not None else None
        )
        self.kf_T_prev, self.prev_is_keyframe = _eye(), True
        res = self._register(frame, self._init_guess())
        if bool(res.ok):
            return self._tracked(frame, res, _kf_T_frame(res), [prev_kf])
        res = self._coarse(frame)
        if res is not None:
            return self._tracked(frame, res, _kf_T_frame(res), [prev_kf])
        if weak:  # the session's tail is the keyframe just made
            return self._lost(index, [prev_kf])
        kf = self._new_session(frame, broke=True)
        return self._done(
            frame, TrackStep(index, True, _eye(), kf.id, kf.session, keyframes=[prev_kf, kf], is_keyframe=True)
        )

    def finish(self) -> list[Keyframe]:
        """End of stream: flush the last session's tail; returns the emitted keyframes."""
        emitted = self._flush_tail()
        self.prev, self.prevprev, self.prev_in_contact = None, None, False
        return emitted

    # ----------------------------------------------------------------- internals
    def _lost(self, index: int, emitted: list[Keyframe]) -> TrackStep:
        """Contact loss: the session ends; ``emitted``: its flushed tail, if any."""
        self.prev_in_contact = False
        self.prev, self.prevprev = None, None
        return TrackStep(index=index, in_contact=False, keyframes=emitted)

    def _coarse(self, frame: Frame) -> RegistrationResult | None:
        """The last chance before a new session: ``frame`` against the current keyframe
        (the previous frame) through ``tracking.fallback_factors``; the result if it
        verifies and stays within the speed limits, else ``None``."""
        if not self.config.fallback_factors:
            return None
        init = self._init_guess()[None]
        res = self.registrar.register_coarse(self.kf_prepared, frame, init, self.config.fallback_factors)[0]
        if not bool(res.ok) or not self._continuous(frame, _kf_T_frame(res)):
            return None
        self.coarse_rescues += 1
        return res

    def _continuous(self, frame: Frame, kf_T_frame: torch.Tensor) -> bool:
        """Whether the motion since the previous frame implied by ``kf_T_frame`` (from a
        registration against an older keyframe) stays within the speed limits; frames without
        timestamps are not checked. A refusal makes the previous frame the keyframe
        (the lazy rule), whose retry starts from the identity and is not checked."""
        c = self.config
        dt = float(frame.timestamp[0]) - float(self.prev.timestamp[0])
        if not (math.isfinite(dt) and dt > 0) or (c.max_deg_per_s is None and c.max_mm_per_s is None):
            return True
        rot, trans = pose_error(self.kf_T_prev[None], kf_T_frame[None])
        ok = (c.max_deg_per_s is None or float(rot) <= c.max_deg_per_s * dt) and \
            (c.max_mm_per_s is None or float(trans) <= c.max_mm_per_s * dt)
        self.implausible += not ok
        return ok

    def _agrees_with_previous(self, frame: Frame, res: RegistrationResult) -> bool:
        """Whether the frame's registration ``res`` against an older keyframe lies within
        ``tracking.f2f_check_deg`` in rotation of the frame registered against the previous
        frame and chained onto its pose; always, when the check is off, when ``res`` is
        well conditioned (``tracking.f2f_below_conditioning``) or when that registration
        fails. A refusal makes the previous frame the keyframe (the lazy rule)."""
        if not self._weak(float(res.conditioning[0])):
            return True
        self.f2f_checks += 1
        kf_T_frame = _kf_T_frame(res)
        start = torch.linalg.inv(torch.linalg.inv(self.kf_T_prev) @ kf_T_frame)  # prev_T_frame, inverted
        f2f = self.registrar.register(self._prepare(self.prev), frame, start[None])[0]
        if not bool(f2f.ok):
            return True
        chained = self.kf_T_prev @ _kf_T_frame(f2f)
        ok = float(pose_error(chained[None], kf_T_frame[None])[0]) <= self.config.f2f_check_deg
        self.f2f_refusals += not ok
        return ok

    def _within_tilt(self, frame: Frame, kf_T_frame: torch.Tensor) -> bool:
        """Whether a frame lies within ``tracking.max_tilt_deg`` of its (older) keyframe out
        of plane, and within ``tracking.decoded_max_tilt_deg`` if decoded from an image. A
        refusal makes the previous frame the keyframe (the lazy rule): the registration's
        error grows with the tilt, and the decoder under-reads tilts in proportion to them."""
        c = self.config
        limit = lower_limit(c.max_tilt_deg, c.decoded_max_tilt_deg, frame.decoded)
        ok = limit is None or float(se3.tilt_deg(kf_T_frame)) <= limit
        self.tilted += not ok
        return ok

    def _new_session(self, frame: Frame, broke: bool = False) -> Keyframe:
        """A session head; ``broke``: started inside a contact because registration failed."""
        self.registration_breaks += broke
        return self._make_keyframe(frame, True, _eye())

    def _tracked(self, frame: Frame, res: RegistrationResult, kf_T_frame: torch.Tensor,
                 emitted: list[Keyframe]) -> TrackStep:
        self.kf_T_prevprev, self.prevprev = self.kf_T_prev, None if self.prev_is_keyframe else self.prev
        self.kf_T_prev = kf_T_frame
        self.prev_is_keyframe = False
        self.prev, self.prev_in_contact = frame, True
        return TrackStep(
            int(frame.index[0]), True, kf_T_frame, self.kf.id, self.kf.session,
            float(res.ccs[0]), float(res.scr[0]), emitted, False, float(res.conditioning[0]),
        )

    def _done(self, frame: Frame, step: TrackStep) -> TrackStep:
        """Bookkeeping after the frame itself became a (session-head) keyframe."""
        self.kf_T_prev, self.kf_T_prevprev, self.prevprev = _eye(), None, None
        self.prev_is_keyframe = True
        self.prev, self.prev_in_contact = frame, True
        return step
