"""The SLAM back end: keyframes -> loop closure -> session merging -> pose graph
(method.md sections 6-7).

:class:`BackEnd` is a pure algorithm object: :meth:`BackEnd.add` takes each keyframe
the tracker emits, in order, and keeps ``start_T_kf`` (every keyframe's pose in its
connected group's start frame, metres) and ``group`` (keyframe id -> group id, the id of
the group's root session) up to date. Per keyframe (offline step order of method 7.2):

1. insert the node with its chained initial value, and its prior (session head) or
   odometry factor;
2. detect loops against the *active coverage* keyframes, as the coverage set was before
   this keyframe; settle them from other starts (:mod:`tactile_slam.loop.ambiguity`: loops
   between groups that verify elsewhere are marked ambiguous, and loops that stray from the
   estimate or join groups move to the best-scoring alignment nearby, ``loop.best_nearby``);
   for loops between two groups that still lack a second query keyframe, probe a predicted
   pair (``loop.probes``, :mod:`tactile_slam.loop.probe`); re-measure them over every contact
   pixel of both keyframes (``posegraph.refine_loops``, ``refine_both_ways``,
   :mod:`tactile_slam.registration.refine`; not in the ``only_sift`` ablation, whose point
   is the SIFT measurement) and hold those whose two directions disagree;
3. decide which verified loops enter the graph (:class:`~tactile_slam.loop.consistency.LoopGate`,
   ``loop.consistency``): a loop within the keyframe's group that agrees with the current
   estimate within the drift tolerance is accepted, one far beyond it rejected; the others,
   and loops into another group, wait until enough of them agree with each other (a
   symmetric or periodic object verifies false loops that no two-keyframe test can reject;
   docs/loops.md);
4. add every accepted loop as a between factor; merge the groups they connect (the root
   is the group with most keyframes, ties to the new keyframe's group), moving each
   absorbed group rigidly through a loop measurement before solving (the public code
   leaves absorbed poses at their identity-anchored values) and removing its prior;
5. solve incrementally (only what the new factors disturb);
6. insert the keyframe into the coverage set with its solved pose, refresh the poses of
   the keyframes the solve moved, and merge the coverage graphs of merged groups;
   keyframes the coverage set deactivates leave the loop detector.
"""

from __future__ import annotations

import json
import math
import time
from collections.abc import Callable, Iterator, Mapping, Sequence
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path

import numpy as np
import torch

from tactile_slam.config import Config
from tactile_slam.eval.loop_metrics import within_tolerance
from tactile_slam.loop.ambiguity import best, elsewhere, starts
from tactile_slam.loop.consistency import DriftModel, LoopGate
from tactile_slam.loop.coverage import CoverageSet
from tactile_slam.loop.detector import Loop, LoopDetector
from tactile_slam.loop.probe import best_pair
from tactile_slam.loop.retrieval import Footprint
from tactile_slam.posegraph import se3
from tactile_slam.posegraph.graph import PoseGraph
from tactile_slam.posegraph.incremental import IncrementalSolver
from tactile_slam.posegraph.sessions import SessionGroups
from tactile_slam.registration.refine import BothWays, pressed_core, refine_both_ways, refine_edges
from tactile_slam.registration.result import pose_error
from tactile_slam.tracking.keyframe import Keyframe


@dataclass
class BackEndStats:
    """Counters (the paper's Table II/V statistics) and cumulative times in seconds."""

    keyframes: int = 0
    loops: int = 0
    merges: int = 0
    refined: int = 0  # loops re-measured (refinements that failed their checks keep the first value)
    refine_failed: int = 0
    ambiguous_loops: int = 0  # loops between groups whose pair also verified elsewhere (held as repetitive)
    moved_loops: int = 0  # loops moved to a better-scoring alignment nearby (loop.best_nearby, or probes)
    probes: int = 0  # predicted pairs verified for loops waiting between groups
    probe_loops: int = 0  # of them, verified (they still pass the loop gate like any loop)
    probes_ambiguous: int = 0  # verified, but an alternative start verified elsewhere too
    time_refine: list[float] = field(default_factory=list)
    time_loop_detection: list[float] = field(default_factory=list)
    time_pose_graph: list[float] = field(default_factory=list)
    time_coverage: list[float] = field(default_factory=list)


class _KeyframeView(Mapping):
    """Keyframe id -> ``lookup(id)`` for the back end's keyframes, read on access (no copy)."""

    def __init__(self, keyframes: Mapping, lookup: Callable) -> None:
        self._keyframes, self._lookup = keyframes, lookup

    def __getitem__(self, kf_id: int):
        if kf_id not in self._keyframes:
            raise KeyError(kf_id)
        return self._lookup(kf_id)

    def __iter__(self) -> Iterator[int]:
        return iter(self._keyframes)

    def __len__(self) -> int:
        return len(self._keyframes)


def asymmetric(both: BothWays, tilt_sigma_deg: Sequence[float | None], max_deg: float | None,
               max_mm: float | None) -> torch.Tensor:
    """Which loops measured both ways disagree with themselves: the two measurements differ
    by more than a loop may differ from the truth under the evaluation's rule
    (:func:`~tactile_slam.eval.loop_metrics.within_tolerance` with ``max_deg`` and
    ``max_mm``: geodesic rotation, or on a loop that declares a tilt sigma, twist and tilt
    within ``max(max_deg, sigma)``); ``None`` limits nothing. Non-finite measurements count
    as disagreeing. ``B`` loops -> ``(B,)`` bool."""
    rot, tilt, twist, trans = (x.numpy() for x in both.asymmetry())
    sigma = np.array([math.nan if s is None else s for s in tilt_sigma_deg], dtype=np.float64)
    agree = within_tolerance(rot, tilt, twist, trans, sigma, math.inf if max_deg is None else max_deg,
                             math.inf if max_mm is None else max_mm)
    return torch.from_numpy(~agree)


def drift_model(config: Config) -> DriftModel:
    """The loop tolerance of ``config.loop``; rotations count as motion of the gel's corner
    (half the sensor diagonal)."""
    lc, sc = config.loop, config.sensor
    return DriftModel(lc.drift_base_rot_deg, lc.drift_base_trans_mm, lc.drift_rot_deg_per_mm,
                      lc.drift_trans_mm_per_mm, 0.5 * math.hypot(sc.width, sc.height) * sc.mm_per_px)


class BackEnd:
    """Loop closure and pose-graph optimisation over keyframes.

    Args:
        config: settings (``loop``, ``posegraph``, ``normalflow``, ...).
        loop_mode: loop-detection mode (``full``, ``only_sift``, ``only_nf``,
            ``image_sift``) or ``None`` for no loop closure (sessions stay separate
            groups, each keyframe is still in the coverage set).
    """

    def __init__(self, config: Config, loop_mode: str | None = "full"):
        n = config.posegraph.refine_n_samples
        if n is not None and n < 1:
            raise ValueError(f"posegraph.refine_n_samples must be >= 1 or None, got {n}")
        if config.loop.probes < 0:
            raise ValueError(f"loop.probes must be >= 0, got {config.loop.probes}")
        if config.loop.decoded_max_tilt_deg is not None and not config.loop.decoded_max_tilt_deg >= 0.0:
            raise ValueError(f"loop.decoded_max_tilt_deg must be >= 0 or None, got {config.loop.decoded_max_tilt_deg}")
        sigma = config.loop.decoded_tilt_sigma_deg
        if sigma is not None and not (math.isfinite(sigma) and sigma > 0.0):
            raise ValueError(f"loop.decoded_tilt_sigma_deg must be finite and > 0 or None, got {sigma}")
        for name in ("max_asymmetry_deg", "max_asymmetry_mm"):
            v = getattr(config.loop, name)
            if v is not None and not v >= 0.0:
                raise ValueError(f"loop.{name} must be >= 0 or None, got {v}")
        if not (config.loop.best_nearby_rot_deg >= 0.0 and config.loop.best_nearby_trans_mm >= 0.0):
            raise ValueError(f"loop.best_nearby_rot_deg and best_nearby_trans_mm must be >= 0, got "
                             f"{config.loop.best_nearby_rot_deg} and {config.loop.best_nearby_trans_mm}")
        self.config = config
        self.graph = PoseGraph(config.posegraph)
        self.solver = IncrementalSolver(self.graph, config.posegraph)
        self.coverage = CoverageSet(config)
        self.detector = LoopDetector(config, loop_mode) if loop_mode is not None else None
        self.keyframes: dict[int, Keyframe] = {}
        self.loops: list[Loop] = []
        self.stats = BackEndStats()
        self.sessions = SessionGroups()
        self.gate = (LoopGate(drift_model(config), config.loop.merge_min_pairs, config.loop.doubt_factor,
                               config.loop.merge_distinct, config.loop.merge_cycles, config.loop.trust_repetitive)
                     if config.loop.consistency else None)
        self._tilted: list[Loop] = []  # verified loops held by the decoded tilt limit
        self._asymmetric: list[Loop] = []  # verified loops whose two re-measurements disagree
        self._last_in_session: dict[int, int] = {}
        self._probed: set[tuple[int, int]] = set()
        self._group_view = _KeyframeView(self.keyframes, self.sessions.group_of)  # -> group id
        self._pose_view = _KeyframeView(self.keyframes, self.graph.pose)  # -> (4, 4) start_T_kf

    @property
    def group(self) -> Mapping[int, int]:
        """Keyframe id -> group id (its root session), for every keyframe; a live view
        (``dict(backend.group)`` for a snapshot)."""
        return self._group_view

    @property
    def start_T_kf(self) -> Mapping[int, torch.Tensor]:
        """Keyframe id -> ``(4, 4)`` float64 pose in its group's start frame, metres; a live
        view (``dict(backend.start_T_kf)`` for a snapshot)."""
        return self._pose_view

    # ------------------------------------------------------------------ step
    def add(self, kf: Keyframe, detect: bool = True) -> list[Loop]:
        """Process one keyframe; returns the loops that entered the graph with it (its own,
        and earlier pending loops accepted now).

        ``detect=False`` skips loop detection *for* this keyframe (online skipping,
        method.md 6.4): it still gets its odometry factor, joins the coverage set and
        stays a candidate for later keyframes."""
        self.keyframes[kf.id] = kf
        self.stats.keyframes += 1
        prev = self._last_in_session.get(kf.session)
        if self.sessions.add_keyframe(kf.id, kf.session):
            self.graph.add_node(kf.id)
            self.graph.add_prior(kf.id)
            if self.gate is not None:
                self.gate.add_node(kf.id)
        else:
            self.graph.add_node(kf.id, self.graph.pose(prev) @ kf.prev_T_kf)
            self.graph.add_between(prev, kf.id, kf.prev_T_kf, kind="odometry")
            if self.gate is not None:
                self.gate.add_factor(prev, kf.id, kf.prev_T_kf)
        self._last_in_session[kf.session] = kf.id

        t0 = time.perf_counter()
        loops: list[Loop] = []
        if self.detector is not None:
            if detect:
                eligible = [k for k in self.coverage.active if k in self.detector]
                loops = self._within_tilt(
                    self.detector.detect(kf, eligible, self._group_view, self._pose_view, self.keyframes))
            self.detector.add(kf)
            loops = self._settle(kf, loops)
            loops = loops + self._within_tilt(self._probe(loops))
            loops = [lp if self._depth_known(lp.ref_id, lp.tar_id) else replace(lp, depth_known=False) for lp in loops]
            loops = [self._declare_tilt(lp) for lp in loops]
        t_refine = time.perf_counter()
        loops = self._within_tilt(self._remeasure(loops))
        t1 = time.perf_counter()
        self.stats.time_refine.append(t1 - t_refine)
        self.stats.time_loop_detection.append(t_refine - t0)

        if self.gate is not None:
            sel = self.gate.select(loops, self.sessions.group_of, self.graph.pose)
            loops, joins = sel.accepted, sel.merges
        else:
            joins = [(kf.id, lp.ref_id, lp.ref_T_tar) for lp in loops]
        for loop in loops:
            self.graph.add_between(loop.ref_id, loop.tar_id, loop.ref_T_tar, self._loop_sigma(loop), kind="loop")
            if self.gate is not None:
                self.gate.add_factor(loop.ref_id, loop.tar_id, loop.ref_T_tar)
        merges = [self.sessions.merge(self.graph, t, [(r, Z)], self.config.posegraph.reinit_merged)
                  for t, r, Z in joins]
        self.stats.merges += sum(len(m.absorbed) for m in merges)
        self.loops += loops
        self.stats.loops += len(loops)
        self.solver.update()
        t2 = time.perf_counter()
        self.stats.time_pose_graph.append(t2 - t1)

        root = self.sessions.group_of(kf.id)
        changed = {root} | {self.sessions.find(m.root) for m in merges}
        active = [k for k in self.coverage.active if self.sessions.group_of(k) in changed]
        if active:  # only active coverage keyframes take part in overlap tests
            self.coverage.update_poses(dict(zip(active, self.graph.poses(active))))
        for m in merges:
            if m.absorbed:
                self.coverage.merge(self.sessions.find(m.root), m.absorbed)
        before = set(self.coverage.active)
        self.coverage.add(kf, self.graph.pose(kf.id), root)
        if self.detector is not None:
            for gone in before - set(self.coverage.active):
                if gone in self.detector:
                    self.detector.remove(gone)
            if not self.coverage.is_active(kf.id) and kf.id in self.detector:
                self.detector.remove(kf.id)
        self.stats.time_coverage.append(time.perf_counter() - t2)
        return loops

    def _within_tilt(self, loops: list[Loop]) -> list[Loop]:
        """``loops`` without those between keyframes decoded from images (either one) whose
        measured out-of-plane rotation exceeds ``loop.decoded_max_tilt_deg``, the tilt
        NormalFlow's verification is specified for (docs/loops.md, "Tilted loops from
        video"). They are kept for :meth:`held_loops` (reason ``tilted``). Checked on the
        verification's value and again on the re-measured one, which is what the graph
        and ``loops.json`` get."""
        limit = self.config.loop.decoded_max_tilt_deg
        if limit is None or not loops:
            return loops
        keep = []
        for lp in loops:
            (keep if not self._decoded(lp) or float(se3.tilt_deg(lp.ref_T_tar)) <= limit else self._tilted).append(lp)
        return keep

    def _declare_tilt(self, loop: Loop) -> Loop:
        """``loop`` with ``tilt_sigma_deg`` set to ``loop.decoded_tilt_sigma_deg`` when either
        keyframe was decoded from an image (the decoder under-reads tilts); unchanged
        otherwise."""
        sigma = self.config.loop.decoded_tilt_sigma_deg
        return loop if sigma is None or not self._decoded(loop) else replace(loop, tilt_sigma_deg=sigma)

    def _decoded(self, loop: Loop) -> bool:
        """Whether either keyframe of ``loop`` was decoded from an image (:attr:`Keyframe.decoded`)."""
        return self.keyframes[loop.ref_id].decoded or self.keyframes[loop.tar_id].decoded

    def _loop_sigma(self, loop: Loop) -> list[float] | None:
        """The between factor's noise ``[translation m x3, rotation rad x3]`` (in the query
        keyframe's frame, :func:`~tactile_slam.posegraph.se3.between_error`): the graph's
        default, with ``tilt_sigma_deg`` on the rotations about x and y when the loop
        declares one; ``None`` (the default) otherwise."""
        if loop.tilt_sigma_deg is None:
            return None
        pg = self.config.posegraph
        tilt = math.radians(loop.tilt_sigma_deg)
        return [pg.sigma_trans_m] * 3 + [tilt, tilt, pg.sigma_rot_rad]

    def _depth_known(self, i: int, j: int) -> bool:
        """Whether both keyframes' heights have a known zero (:attr:`Keyframe.depth_known`)."""
        return self.keyframes[i].depth_known and self.keyframes[j].depth_known

    def _settle(self, kf: Keyframe, loops: list[Loop]) -> list[Loop]:
        """``loops`` of query ``kf`` settled by NormalFlow from other starts
        (:mod:`tactile_slam.loop.ambiguity`), in batches with the query as the shared reference.

        * Within the query's group (``loop.best_nearby``): a loop that differs from the
          estimate's prediction by more than ``loop.best_nearby_rot_deg`` or
          ``best_nearby_trans_mm`` moves to the verified alignment with the highest CCS among
          its pose and its shifts by the gate's base translation tolerance
          (the near starts of :func:`~tactile_slam.loop.ambiguity.starts`). On ribs a
          fraction of a millimetre apart, a loop one period off verifies and passes the gate
          (its error is inside the drift tolerance); the near start one period over reaches
          the truth, which scores higher. It is marked ``ambiguous`` when one of the other
          starts verifies elsewhere: on a lattice coarser than the near shifts (a knurl) a
          loop a period off stays there, and the gate then takes it only where it agrees with
          the estimate at zero drift. A loop closer to the prediction cannot be false where
          the estimate is right, so it is taken as measured.
        * Between two groups (``loop.check_ambiguity``): marked ``ambiguous`` when the pair
          also verifies from an alternative start at another pose. With
          ``loop.best_nearby`` (or probes) such loops first move to the best nearby
          alignment (:func:`~tactile_slam.loop.ambiguity.best`): a loop one period off on
          ribs predicts probes one period off, which verify there."""
        fp = self.detector.footprint(kf)
        if self.gate is None or self.detector.mode == "only_sift" or fp is None or fp.radius <= 0.0:
            return loops
        lc, group_of = self.config.loop, self.sessions.group_of
        near = self._near_m() if lc.best_nearby or lc.probes else None
        out = list(loops)
        across = [i for i, lp in enumerate(loops) if group_of(lp.ref_id) != group_of(kf.id)]
        check = [i for i in across if not loops[i].repetitive] if lc.check_ambiguity else []
        within = [i for i, lp in enumerate(loops) if group_of(lp.ref_id) == group_of(kf.id)] if lc.best_nearby else []
        if within:
            pred = torch.stack([se3.inverse(self.graph.pose(loops[i].ref_id)) @ self.graph.pose(kf.id) for i in within])
            rot, trans = pose_error(torch.stack([loops[i].ref_T_tar.double() for i in within]), pred)
            within = [i for i, r, t in zip(within, rot.tolist(), trans.tolist())
                      if r > lc.best_nearby_rot_deg or t > lc.best_nearby_trans_mm]
        if check:
            inits = torch.cat([starts(se3.inverse(loops[i].ref_T_tar.double()), fp.centre, fp.radius, near)
                               for i in check])
            q_T_c, ok, ccs, scr = self._verify_starts(kf, [loops[i].ref_id for i in check], inits, exhaustive=True)
            at = best(ok, ccs) if near is not None else torch.zeros(len(check), dtype=torch.long)
            flag = elsewhere(q_T_c, ok, self.gate.model, at, near=False).tolist()
            for j, (i, amb) in enumerate(zip(check, flag)):
                out[i] = self._moved(out[i], q_T_c[j], ccs[j], scr[j], int(at[j]))
                if amb:
                    out[i] = replace(out[i], ambiguous=True)
            self.stats.ambiguous_loops += sum(flag)
        if within:  # the loop's own pose competes with its near starts; the other starts must not verify
            own = torch.stack([se3.inverse(loops[i].ref_T_tar.double()) for i in within])
            q_T_c, ok, ccs, scr = self._verify_starts(kf, [loops[i].ref_id for i in within],
                                                      torch.cat([starts(T, fp.centre, fp.radius, near) for T in own]),
                                                      exhaustive=True)
            at = best(ok, ccs)
            flag = elsewhere(q_T_c, ok, self.gate.model, at, near=False).tolist()
            for j, (i, amb) in enumerate(zip(within, flag)):
                out[i] = self._moved(out[i], q_T_c[j], ccs[j], scr[j], int(at[j]))
                if amb:
                    out[i] = replace(out[i], ambiguous=True)
            self.stats.ambiguous_loops += sum(flag)
        return out

    def _verify_starts(self, kf: Keyframe, ref_ids: list[int], inits: torch.Tensor, exhaustive: bool):
        """NormalFlow of query ``kf`` against each keyframe of ``ref_ids`` from its ``S``
        starts (``inits``: ``(B * S, 4, 4)``, ``S`` consecutive per keyframe): ``(B, S, 4, 4)``
        ``query_T_candidate`` and ``(B, S)`` ok, CCS and SCR, on the CPU."""
        S = len(inits) // len(ref_ids)
        res = self.detector.verify(kf, [self.keyframes[r] for r in ref_ids for _ in range(S)], inits,
                                   exhaustive=exhaustive)
        return (res.tar_T_ref.double().cpu().reshape(len(ref_ids), S, 4, 4),
                *(x.cpu().reshape(len(ref_ids), S) for x in (res.ok, res.ccs, res.scr)))

    def _moved(self, loop: Loop, q_T_c: torch.Tensor, ccs: torch.Tensor, scr: torch.Tensor, b: int) -> Loop:
        """``loop`` at the result of start ``b`` (``q_T_c``: ``(S, 4, 4)``; ``ccs``, ``scr``:
        ``(S,)``); unchanged for the first start."""
        if not b:
            return loop
        self.stats.moved_loops += 1
        return replace(loop, ref_T_tar=se3.inverse(q_T_c[b]), ccs=float(ccs[b]), scr=float(scr[b]))

    def _near_m(self) -> float:
        """The near shift of :func:`~tactile_slam.loop.ambiguity.starts`: the gate's base
        translation tolerance (metres)."""
        return self.gate.model.base_trans_mm / 1000.0

    def _probe(self, loops: list[Loop]) -> list[Loop]:
        """Verified probes (``Loop.probe``) for the group pairs whose waiting loops (the
        gate's, and ``loops`` of the new keyframe) come from fewer than
        ``loop.merge_min_pairs`` query keyframes; at most ``loop.probes``, the pairs with the
        newest loops first (:mod:`tactile_slam.loop.probe`)."""
        budget = self.config.loop.probes
        if budget == 0 or self.gate is None or self.detector.mode in ("only_sift", "only_nf"):
            return []
        group_of, trust = self.sessions.group_of, self.config.loop.trust_repetitive
        waiting: dict[frozenset, list[tuple[int, int, torch.Tensor]]] = {}
        held = [(p.a_id, p.b_id, p.a_T_b, p.repetitive) for p in self.gate.pending]
        new = [(lp.ref_id, lp.tar_id, lp.ref_T_tar, not (lp.says_where or trust)) for lp in loops]
        for a, b, a_T_b, rep in held + new:
            key = frozenset((group_of(a), group_of(b)))
            if len(key) == 2 and not rep:
                waiting.setdefault(key, []).append((a, b, a_T_b))
        keys = sorted((k for k, v in waiting.items() if len({b for _, b, _ in v}) < self.config.loop.merge_min_pairs),
                      key=lambda k: -max(b for _, b, _ in waiting[k]))
        probes = []
        for key in keys[:budget]:
            a, b, a_T_b = max(waiting[key], key=lambda e: e[1])
            ends = {e for x, y, _ in waiting[key] for e in (x, y)}
            xs = [k for k in self.sessions.members(group_of(a)) if self._probe_ok(k, trust)]
            ys = [k for k in self.sessions.members(group_of(b)) if k not in ends and self._probe_ok(k, trust)]
            if not xs or not ys:
                continue
            H_T_G = self.graph.pose(a) @ a_T_b.double() @ se3.inverse(self.graph.pose(b))
            fx, fy = [self._footprint(k) for k in xs], [self._footprint(k) for k in ys]
            allowed = torch.ones(len(xs), len(ys), dtype=torch.bool)
            row, col = {k: i for i, k in enumerate(xs)}, {k: j for j, k in enumerate(ys)}
            for x, y in self._probed:
                if x in row and y in col:
                    allowed[row[x], col[y]] = False
            pair = best_pair(H_T_G, self.graph.poses(xs), torch.stack([f.centre for f in fx]),
                             torch.tensor([f.radius for f in fx], dtype=torch.float64), self.graph.poses(ys),
                             torch.stack([f.centre for f in fy]),
                             torch.tensor([f.radius for f in fy], dtype=torch.float64), allowed)
            if pair is None:
                continue
            x, y = xs[pair[0]], ys[pair[1]]
            self._probed.add((x, y))
            self.stats.probes += 1
            loop = self._probe_pair(x, y, H_T_G)
            if loop is not None:
                probes.append(loop)
        self.stats.probe_loops += len(probes)
        return probes

    def _probe_pair(self, x: int, y: int, H_T_G: torch.Tensor) -> Loop | None:
        """NormalFlow on ``(x, y)`` from the pose ``H_T_G`` predicts and from the alternatives
        of :func:`~tactile_slam.loop.ambiguity.starts`: a loop at the best nearby alignment
        when one verifies and no alternative verifies somewhere else (beyond the gate's base
        tolerance)."""
        x_T_y = se3.inverse(self.graph.pose(x)) @ H_T_G @ self.graph.pose(y)
        # NormalFlow's reference is the smaller contact: SCR is the share of its samples
        # the other contact holds, which a smaller patch inside a larger one passes
        y_ref = self._footprint(y).radius <= self._footprint(x).radius
        q, c = (y, x) if y_ref else (x, y)
        fq = self._footprint(q)
        inits = starts(se3.inverse(x_T_y) if y_ref else x_T_y, fq.centre, fq.radius, self._near_m())
        res = self.detector.verify(self.keyframes[q], [self.keyframes[c]] * len(inits), inits, exhaustive=True)
        q_T_c, ok, ccs = res.tar_T_ref.double().cpu(), res.ok.cpu(), res.ccs.cpu()
        at = best(ok[None], ccs[None])
        b = int(at[0])
        if not bool(ok[b]):
            return None
        if bool(elsewhere(q_T_c[None], ok[None], self.gate.model, at)):
            self.stats.probes_ambiguous += 1
            return None
        x_T_y_meas = se3.inverse(q_T_c[b]) if y_ref else q_T_c[b]
        return Loop(x, y, x_T_y_meas, float(ccs[b]), float(res.scr[b]), 0, se3.inverse(x_T_y), False, probe=True,
                    conditioning=float(res.conditioning[b]))

    def _footprint(self, kf_id: int) -> Footprint | None:
        return self.detector.footprint(self.keyframes[kf_id])

    def _probe_ok(self, kf_id: int, trust_repetitive: bool) -> bool:
        """A keyframe may take part in a probe: it has contact, and its texture does not
        match itself elsewhere (unless such loops are trusted)."""
        fp = self._footprint(kf_id)
        return (fp is not None and fp.radius > 0.0
                and (trust_repetitive or not self.detector.is_repetitive(self.keyframes[kf_id])))

    def _remeasure(self, loops: list[Loop]) -> list[Loop]:
        """Verified ``loops`` re-measured over ``posegraph.refine_n_samples`` pixels (every
        contact pixel by default; with ``posegraph.refine_core``, of the pressed core,
        :func:`~tactile_slam.registration.refine.pressed_core`), before the loop gate sees
        them; not in the ``only_sift`` ablation, whose point is the SIFT measurement. With
        ``posegraph.refine_both_ways`` each is measured over both keyframes' pixels
        (:func:`~tactile_slam.registration.refine.refine_both_ways`) and a loop whose two
        measurements disagree beyond ``loop.max_asymmetry_deg`` / ``max_asymmetry_mm`` is
        held (:meth:`held_loops`, reason ``asymmetric``). A loop no measurement of which
        passes its checks keeps its verified value. Each keyframe's maps are expanded (and
        narrowed) once, however many of the loops it ends."""
        cfg = self.config
        if not loops or not cfg.posegraph.refine_loops or self.detector.mode == "only_sift":
            return loops
        frame = {i: self.keyframes[i].frame for i in {e for lp in loops for e in (lp.ref_id, lp.tar_id)}}
        if cfg.posegraph.refine_core:
            frame = {i: pressed_core(f, cfg.depth_test, cfg.contact.height_percentile) for i, f in frame.items()}
        args = ([frame[lp.ref_id] for lp in loops], [frame[lp.tar_id] for lp in loops],
                torch.stack([lp.ref_T_tar for lp in loops]), self.detector.nf_config, cfg.posegraph.refine_n_samples)
        if cfg.posegraph.refine_both_ways:
            both = refine_both_ways(*args)
            Zs, ok = both.ref_T_tar, both.forward_ok | both.reverse_ok
            held = asymmetric(both, [lp.tilt_sigma_deg for lp in loops], cfg.loop.max_asymmetry_deg,
                              cfg.loop.max_asymmetry_mm).tolist()
        else:
            Zs, ok = refine_edges(*args)
            held = [False] * len(loops)
        self.stats.refined += int(ok.sum())
        self.stats.refine_failed += int((~ok).sum())
        out = [replace(lp, ref_T_tar=Z) for lp, Z in zip(loops, Zs)]
        self._asymmetric += [lp for lp, h in zip(out, held) if h]
        return [lp for lp, h in zip(out, held) if not h]

    def summary(self) -> dict:
        """The paper's statistics (Table II/V) and median times per keyframe in ms."""
        med = lambda xs: float(np.median(xs) * 1000) if xs else float("nan")  # noqa: E731
        st = self.stats
        return {
            "coverage_keyframes": len(self.coverage.active),
            "loop_candidates": self.detector.stats.candidates if self.detector is not None else 0,
            "loops": st.loops,
            "group_merges": st.merges,
            "keyframes_depth_unknown": sum(not k.depth_known for k in self.keyframes.values()),
            "loop_gate": asdict(self.gate.stats) if self.gate is not None else None,
            "refined_loops": st.refined,
            "refine_failed": st.refine_failed,
            "ambiguous_loops": st.ambiguous_loops,
            "moved_loops": st.moved_loops,
            "probes": st.probes,
            "probe_loops": st.probe_loops,
            "probes_ambiguous": st.probes_ambiguous,
            "tilted_loops": len(self._tilted),
            "asymmetric_loops": len(self._asymmetric),
            "timing_ms_per_keyframe": {"loop_detection": med(st.time_loop_detection),
                                       "pose_graph": med(st.time_pose_graph),
                                       "coverage": med(st.time_coverage),
                                       "refine": med(st.time_refine)},
        }

    def held_loops(self) -> list[dict]:
        """Every verified loop that is not in the graph, JSON-ready (:meth:`Loop.to_dict`)
        with its ``reason``: ``tilted`` (:meth:`_within_tilt`), then the gate's
        (:meth:`~tactile_slam.loop.consistency.LoopGate.held`; without the gate,
        ``loop.consistency: false``, every other verified loop is accepted)."""
        held = ([(loop, "tilted") for loop in self._tilted] + [(loop, "asymmetric") for loop in self._asymmetric]
                + (self.gate.held() if self.gate is not None else []))
        return [loop.to_dict() | {"reason": reason} for loop, reason in held]

    def write(self, out_dir: Path) -> None:
        """``loops.json`` (accepted loops), ``loops_held.json`` (verified loops not in the
        graph, :meth:`held_loops`) and ``pose_graph.g2o`` into ``out_dir``."""
        out_dir.mkdir(parents=True, exist_ok=True)
        (out_dir / "loops.json").write_text(json.dumps([loop.to_dict() for loop in self.loops], indent=2))
        (out_dir / "loops_held.json").write_text(json.dumps(self.held_loops(), indent=2))
        if self.graph.num_nodes:
            self.graph.to_g2o(out_dir / "pose_graph.g2o")

    def finish(self) -> None:
        """Final full warm-started solve (end of the scan)."""
        if self.keyframes:
            self.solver.finalize()
