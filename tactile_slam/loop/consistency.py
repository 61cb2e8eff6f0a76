"""Back-end loop acceptance: a verified loop must agree with the map (docs/loops.md).

A loop that NormalFlow verifies is a true match of the *surface*; on a symmetric or
periodic object it can still be a false loop of the *object* (the two touches are a half
turn or a whole period apart on identical texture). No test on the two keyframes alone can
tell; the map can:

* **within a connected group** the current pose estimates predict the loop's relative pose.
  :func:`consistent` compares the measurement with that prediction under a tolerance that
  grows with the *drift path* between the two keyframes: the shortest path between them in
  the graph of accepted factors, each factor weighted by the motion it measures
  (:func:`motion_mm`). Chains of relative measurements drift in proportion to the motion they
  chain; a recent loop near both keyframes makes the path (and the tolerance) short again.
  Far beyond the tolerance a loop is rejected; a little beyond it (a tracker that slipped,
  or a false match one period away) it needs corroboration, as below.
* **across groups** no prediction exists; :class:`LoopGate` holds such loops until enough
  of them, found by distinct query keyframes, agree on the transform between the two
  groups (:func:`implied_transform`, each checked through another like a loop within one
  group), or until single loops between three groups close a cycle (:func:`closing_prediction`):
  the transforms they imply compose to the identity within the drift tolerance.

:class:`MotionGraph` keeps the weighted adjacency incrementally (one entry per factor) and
answers bounded shortest-path queries, so a check costs the size of the neighbourhood it
explores, not of the map.
"""

from __future__ import annotations

import heapq
import math
from collections.abc import Iterable
from dataclasses import dataclass

import torch

from tactile_slam.config import MERGE_DISTINCT
from tactile_slam.posegraph import se3
from tactile_slam.registration.result import pose_error


@dataclass(frozen=True)
class DriftModel:
    """Tolerance of a loop against the pose estimate: ``base + rate * path``.

    Attributes:
        base_rot_deg, base_trans_mm: tolerance at zero path (loop measurement error).
        rot_deg_per_mm, trans_mm_per_mm: growth per mm of drift path (odometry drift).
        lever_mm: a rotation of ``a`` rad counts as ``a * lever_mm`` mm of motion.
    """

    base_rot_deg: float
    base_trans_mm: float
    rot_deg_per_mm: float
    trans_mm_per_mm: float
    lever_mm: float

    def __post_init__(self) -> None:
        values = (self.base_rot_deg, self.base_trans_mm, self.rot_deg_per_mm, self.trans_mm_per_mm, self.lever_mm)
        if not all(math.isfinite(v) and v >= 0 for v in values):
            raise ValueError(f"drift tolerances and the lever must be finite and >= 0, got {values}")

    def tolerance(self, path_mm: float | torch.Tensor) -> tuple:
        """``(rotation deg, translation mm)`` tolerance after ``path_mm`` of drift path."""
        return self.base_rot_deg + self.rot_deg_per_mm * path_mm, self.base_trans_mm + self.trans_mm_per_mm * path_mm

    def half_turn_path_mm(self) -> float:
        """The drift path beyond which the rotation tolerance exceeds 180 degrees (nothing
        can be told from the estimate any more); ``inf`` without rotation drift."""
        if self.rot_deg_per_mm <= 0:
            return math.inf
        return max(180.0 - self.base_rot_deg, 0.0) / self.rot_deg_per_mm

    def scaled(self, factor: float) -> DriftModel:
        """The same model with every tolerance ``factor`` times larger."""
        return DriftModel(self.base_rot_deg * factor, self.base_trans_mm * factor, self.rot_deg_per_mm * factor,
                          self.trans_mm_per_mm * factor, self.lever_mm)


def motion_mm(a_T_b: torch.Tensor, lever_mm: float) -> torch.Tensor:
    """Motion measured by relative poses ``(..., 4, 4)`` (metres): translation in mm plus
    rotation angle (rad) times ``lever_mm``. Returns ``(...)`` float64."""
    xi = se3.log(a_T_b.double())
    return torch.linalg.vector_norm(a_T_b[..., :3, 3].double(), dim=-1) * 1e3 + \
        torch.linalg.vector_norm(xi[..., 3:], dim=-1) * lever_mm


def consistent(predicted: torch.Tensor, measured: torch.Tensor, path_mm: torch.Tensor,
               model: DriftModel) -> torch.Tensor:
    """Whether measured relative poses agree with predicted ones within the drift tolerance
    (rotation angle of ``predicted^-1 measured`` and distance between the translations,
    :func:`~tactile_slam.registration.result.pose_error`).

    Args:
        predicted, measured: ``(B, 4, 4)`` float64 ``r_T_t`` (metres).
        path_mm: ``(B,)`` drift path between the two keyframes (``inf``: unknown, fails).
        model: the tolerance.

    Returns:
        ``(B,)`` bool.
    """
    rot, trans = pose_error(predicted, measured)
    path = path_mm.double()
    rot_tol, trans_tol = model.tolerance(path)
    return torch.isfinite(path) & (rot <= rot_tol) & (trans <= trans_tol)


def implied_transform(start_T_a: torch.Tensor, a_T_b: torch.Tensor, start_T_b: torch.Tensor) -> torch.Tensor:
    """``A_T_B`` ``(4, 4)``: the map from group B's start frame into group A's implied by a
    loop ``a_T_b`` between keyframe ``a`` of A and ``b`` of B at poses ``start_T_a``,
    ``start_T_b`` in their own groups."""
    return start_T_a @ a_T_b @ se3.inverse(start_T_b)


def closing_prediction(A_T_B: torch.Tensor, B_T_C: torch.Tensor, start_T_x: torch.Tensor,
                       start_T_y: torch.Tensor) -> torch.Tensor:
    """The loops that would close cycles of three groups A, B, C, as the other two predict them.

    Args:
        A_T_B: ``(n0, 4, 4)`` float64 transforms from group B's start frame into A's implied by
            loops between A and B (:func:`implied_transform`).
        B_T_C: ``(n1, 4, 4)`` the same for loops between B and C.
        start_T_x, start_T_y: ``(n2, 4, 4)`` the ends of loops between C and A: keyframe
            ``x`` in C and ``y`` in A, at their poses in their own groups.

    Returns:
        ``(n0, n1, n2, 4, 4)`` predicted ``x_T_y`` for every combination (equal to the
        measurements when the cycles close).
    """
    C_T_A = se3.inverse(A_T_B[:, None] @ B_T_C[None])
    return se3.inverse(start_T_x) @ C_T_A[:, :, None] @ start_T_y


class MotionGraph:
    """Undirected keyframe graph, each edge weighted by the motion it measures (mm)."""

    def __init__(self, lever_mm: float) -> None:
        self.lever_mm = lever_mm
        self._adj: dict[int, list[tuple[int, float]]] = {}

    def add_node(self, node: int) -> None:
        self._adj.setdefault(node, [])

    def add_edge(self, i: int, j: int, i_T_j: torch.Tensor) -> None:
        """An edge for the factor ``(i, j, i_T_j)`` (metres); adds unknown nodes."""
        w = float(motion_mm(i_T_j, self.lever_mm))
        self._adj.setdefault(i, []).append((j, w))
        self._adj.setdefault(j, []).append((i, w))

    def paths(self, source: int, targets: Iterable[int], limit: float = math.inf) -> dict[int, float]:
        """Shortest weighted path (mm) from ``source`` to each of ``targets``; ``inf`` for
        targets farther than ``limit`` or unreachable. Stops once every target is settled."""
        left = set(targets)
        out = {t: math.inf for t in left}
        if source not in self._adj:
            return out
        dist = {source: 0.0}
        heap = [(0.0, source)]
        done: set[int] = set()
        while heap and left:
            d, u = heapq.heappop(heap)
            if u in done:
                continue
            done.add(u)
            if u in left:
                out[u] = d
                left.discard(u)
            for v, w in self._adj[u]:
                nd = d + w
                if nd <= limit and nd < dist.get(v, math.inf):
                    dist[v] = nd
                    heapq.heappush(heap, (nd, v))
        return out


@dataclass
class PendingLoop:
    """A verified loop between two groups, waiting for agreement.

    ``a_id`` / ``b_id`` are its ends (``a`` = reference, ``b`` = query keyframe);
    ``a_T_b`` the measurement; ``loop`` the caller's object (added once accepted);
    ``groups`` the group(s) of its ends when last evaluated; ``recheck``: other loops were
    accepted for the same groups, so it is checked against the estimate at the next step."""

    a_id: int
    b_id: int
    a_T_b: torch.Tensor
    loop: object
    groups: frozenset = frozenset()
    recheck: bool = False
    repetitive: bool = False

    def oriented(self, group_of, g: int) -> tuple[int, int, torch.Tensor]:
        """``(x, y, x_T_y)``: this loop with ``x`` in group ``g``."""
        if group_of(self.a_id) == g:
            return self.a_id, self.b_id, self.a_T_b
        return self.b_id, self.a_id, se3.inverse(self.a_T_b)


@dataclass
class GateStats:
    """Counters of :class:`LoopGate`.

    ``rejected_consistency``: loops within a group beyond ``doubt_factor`` times the drift
    tolerance (the others left out of an accepted set meet the corrected estimate the same
    way); ``doubtful``: loops within a group beyond the tolerance but within that, held
    pending (cumulative); ``deferred``: loops between groups held pending (cumulative);
    ``ambiguous``: evaluations where two disagreeing sets of loops both had enough support,
    or a closed cycle that another loop between its groups contradicts (no merge);
    ``cycles``: cycles of three groups closed by single loops (each merges three groups);
    ``repetitive``: loops on a texture that matches itself elsewhere (``Loop.repetitive``)
    or whose pair also verifies elsewhere (``Loop.ambiguous``), dropped: between groups all
    of them, within a group those beyond the tolerance at zero drift path;
    ``pending``: loops waiting now.
    """

    rejected_consistency: int = 0
    doubtful: int = 0
    deferred: int = 0
    ambiguous: int = 0
    cycles: int = 0
    repetitive: int = 0
    pending: int = 0


@dataclass
class Selection:
    """What :meth:`LoopGate.select` decided for one keyframe.

    ``accepted``: loops to add as factors (the query's loops within its group, the loops of
    each merge, and pending loops whose groups were joined meanwhile that pass the check);
    ``merges``: ``(t, r, r_T_t)``, one accepted loop per pair of groups to join, for
    :meth:`tactile_slam.posegraph.sessions.SessionGroups.merge` (in order).
    """

    accepted: list
    merges: list[tuple[int, int, torch.Tensor]]


class LoopGate:
    """Decides which verified loops enter the pose graph (see the module docstring).

    Args:
        model: drift tolerance: a loop within a group that agrees with the estimate within it
            is accepted at once.
        min_pairs: loops that need corroboration (between two groups; within a group, beyond
            the tolerance) are accepted only when at least this many of them, from distinct
            keyframes on both sides, agree on the same transform and no disagreeing set of
            loops has that support too; two groups then merge.
        doubt_factor: a loop within a group farther from the estimate than this many times
            the tolerance is rejected outright (a half turn of a symmetric object, a teleport).
        distinct: what counts as independent support: ``"queries"``, agreeing loops found by
            ``min_pairs`` distinct query keyframes (separate detections; their candidates
            may be one keyframe, which is all the coverage set keeps of a small region);
            ``"both"``, distinct keyframes on both sides.
        cycles: also accept three loops between three groups (A-B, B-C, C-A), found by at
            least ``min_pairs`` (and two) distinct query keyframes, whose implied transforms
            compose to the identity within the drift tolerance of the paths between their
            ends, when no other waiting loop
            between those groups contradicts them by more than ``doubt_factor`` times it:
            short sessions after contact loss seldom give two loops to the same group, but a
            later session often touches two earlier ones, and a false loop rarely closes a
            cycle. The three groups merge.
        trust_repetitive: let loops whose keyframes' texture matches another part of itself
            (``Loop.repetitive``, e.g. a knurl's lattice) join two groups like any other. By
            default such a loop is used only within a group, and only where the estimate
            predicts it within the tolerance at zero drift path (the loop's own error): once
            the estimate has drifted, a match one period off agrees with it as well as the
            true one (the knurl, 2026-11-29). Between groups it is dropped: two keyframes on
            one periodic texture match the same wrong period alike, and nothing else can
            tell. Loops marked ``ambiguous`` (the pair also verifies elsewhere,
            :mod:`tactile_slam.loop.ambiguity`) are treated the same.

    The caller reports every factor it adds (:meth:`add_factor`) and calls :meth:`select`
    once per keyframe with its verified loops, after the keyframe's node and odometry are in.
    """

    def __init__(self, model: DriftModel, min_pairs: int = 2, doubt_factor: float = 5.0,
                 distinct: str = "queries", cycles: bool = True, trust_repetitive: bool = False) -> None:
        if min_pairs < 1 or doubt_factor < 1.0:
            raise ValueError(f"need min_pairs >= 1 and doubt_factor >= 1, got {min_pairs}, {doubt_factor}")
        if distinct not in MERGE_DISTINCT:
            raise ValueError(f"distinct must be one of {MERGE_DISTINCT}, got {distinct!r}")
        self.model = model
        self.min_pairs = min_pairs
        self.distinct = distinct
        self.doubt_factor = doubt_factor
        self.cycles = cycles
        self.trust_repetitive = trust_repetitive
        self._limit = model.scaled(doubt_factor).half_turn_path_mm()  # drift paths searched up to this
        self.motion = MotionGraph(model.lever_mm)
        self.pending: list[PendingLoop] = []
        self.dropped: list[tuple[object, str]] = []  # verified loops let go, with the reason (see held)
        self.stats = GateStats()

    def add_node(self, node: int) -> None:
        self.motion.add_node(node)

    def add_factor(self, i: int, j: int, i_T_j: torch.Tensor) -> None:
        """A between factor the caller added to the pose graph (odometry or loop)."""
        self.motion.add_edge(i, j, i_T_j)

    def select(self, loops: list, group_of, pose) -> Selection:
        """Accept, defer or reject the verified loops of the keyframe just added.

        Args:
            loops: its verified loops, and probes (their ``tar_id`` another keyframe of a
                group; objects with ``ref_id``, ``tar_id`` and ``ref_T_tar`` ``(4, 4)`` metres).
            group_of: keyframe id -> group id (current).
            pose: keyframe id -> ``(4, 4)`` float64 ``start_T_kf`` (current estimate).
        """
        # loops within one group now: the query's own, and pending ones whose groups were joined
        joined = [p for p in self.pending
                  if p.recheck or (len(p.groups) == 2 and group_of(p.a_id) == group_of(p.b_id))]
        self.pending = [p for p in self.pending if not any(p is q for q in joined)]
        mine = [PendingLoop(lp.ref_id, lp.tar_id, lp.ref_T_tar, lp,
                            repetitive=not (lp.says_where or self.trust_repetitive)) for lp in loops]
        accepted = self._check_within(joined + [p for p in mine if group_of(p.a_id) == group_of(p.b_id)], pose)
        new = self._drop_repetitive([p for p in mine if group_of(p.a_id) != group_of(p.b_id)])
        self.pending += new
        self.stats.deferred += len(new)
        dirty: dict[frozenset, list[PendingLoop]] = {}
        for p in self.pending:
            now = frozenset((group_of(p.a_id), group_of(p.b_id)))
            if now != p.groups:
                dirty.setdefault(now, [])
            p.groups = now
        for p in self.pending:
            if p.groups in dirty:
                dirty[p.groups].append(p)
        merges, merged, open_keys = [], set(), []
        for key, members in dirty.items():
            chosen = self._evaluate(members, group_of, pose)
            if chosen is None:
                open_keys += [key] if len(key) == 2 else []
                continue
            accepted += [p.loop for p in chosen]
            if len(key) == 2:
                merges.append((chosen[0].b_id, chosen[0].a_id, chosen[0].a_T_b))
                merged |= key
            self._take(chosen, members)
        for key in open_keys if self.cycles else []:
            if key & merged:
                continue  # its groups change now; re-evaluated as a new pair at the next keyframe
            cycle = self._close_cycle(key, group_of, pose, merged)
            if cycle is not None:
                chosen, members = cycle
                accepted += [p.loop for p in chosen]
                merges += [(p.b_id, p.a_id, p.a_T_b) for p in chosen[:2]]
                merged |= {group_of(p.a_id) for p in chosen} | {group_of(p.b_id) for p in chosen}
                self._take(chosen, members)
                self.stats.cycles += 1
        self.stats.pending = len(self.pending)
        return Selection(accepted, merges)

    def held(self) -> list[tuple[object, str]]:
        """Every verified loop the gate has not let into the graph, with the reason:
        ``repetitive`` / ``ambiguous`` (dropped: ``Loop.repetitive``, or its pair also
        verified elsewhere; between groups, or within one beyond the tolerance at zero drift
        path), ``inconsistent`` (within a group, beyond
        ``doubt_factor`` times the drift tolerance: rejected), ``waiting`` (between groups,
        pending: too little agreeing support yet, or a disagreeing set as strong) and
        ``doubtful`` (within a group, between the tolerance and ``doubt_factor`` times it:
        pending). Pending loops carry their state at the gate's last evaluation."""
        return self.dropped + [(p.loop, "waiting" if len(p.groups) == 2 else "doubtful") for p in self.pending]

    def _drop_repetitive(self, loops: list[PendingLoop]) -> list[PendingLoop]:
        """The loops that may wait for corroboration: those on a repeating texture are
        dropped (counted in ``stats.repetitive``)."""
        keep = [p for p in loops if not p.repetitive]
        self.dropped += [(p.loop, "repetitive" if p.loop.repetitive else "ambiguous")
                         for p in loops if p.repetitive]
        self.stats.repetitive += len(loops) - len(keep)
        return keep

    def _take(self, chosen: list[PendingLoop], members: list[PendingLoop]) -> None:
        """Remove accepted loops from the pending ones; the other ``members`` (loops between
        the same groups) meet the corrected estimate at the next keyframe."""
        self.pending = [p for p in self.pending if not any(p is q for q in chosen)]
        for p in members:
            p.recheck = True

    # ------------------------------------------------------------------ within a group
    def _check_within(self, loops: list[PendingLoop], pose) -> list:
        """Loops within one group: accepted within the drift tolerance, rejected beyond
        ``doubt_factor`` times it, held pending (like loops between groups) in between."""
        if not loops:
            return []
        paths = torch.tensor([self.motion.paths(p.b_id, [p.a_id], self._limit)[p.a_id] for p in loops],
                             dtype=torch.float64)
        Ta = torch.stack([pose(p.a_id) for p in loops])
        Tb = torch.stack([pose(p.b_id) for p in loops])
        pred, meas = se3.inverse(Ta) @ Tb, torch.stack([p.a_T_b.double() for p in loops])
        ok = consistent(pred, meas, paths, self.model).tolist()
        # beyond the search limit the doubt band exceeds a half turn: nothing can be rejected
        plausible = (consistent(pred, meas, paths, self.model.scaled(self.doubt_factor))
                     | ~torch.isfinite(paths)).tolist()
        # a repetitive loop: its aliases agree with the estimate as well once it has drifted,
        # so it counts only where it agrees within the loop's own error (no drift allowance)
        if any(p.repetitive for p in loops):
            tight = consistent(pred, meas, torch.zeros_like(paths), self.model).tolist()
            keep = [not p.repetitive or t for p, t in zip(loops, tight)]
            self._drop_repetitive([p for p, k in zip(loops, keep) if not k])
            loops, ok, plausible = ([x for x, k in zip(v, keep) if k] for v in (loops, ok, plausible))
        doubtful = [p for p, k, m in zip(loops, ok, plausible) if m and not k]
        for p in doubtful:
            p.groups, p.recheck = frozenset(), False  # evaluated with its group below
        self.pending += doubtful
        self.dropped += [(p.loop, "inconsistent") for p, m in zip(loops, plausible) if not m]
        self.stats.doubtful += len(doubtful)
        self.stats.rejected_consistency += len(loops) - sum(plausible)
        return [p.loop for p, k in zip(loops, ok) if k]

    # ------------------------------------------------------------------ across groups
    def _support(self, agree: set[int], ends: list, members: list[PendingLoop]) -> int:
        """Independent support of an agreeing set of loops (see ``distinct``)."""
        if self.distinct == "queries":
            return len({members[q].b_id for q in agree})
        return min(len({ends[q][0] for q in agree}), len({ends[q][1] for q in agree}))

    def _evaluate(self, members: list[PendingLoop], group_of, pose) -> list[PendingLoop] | None:
        """Loops between one pair of groups: the largest set agreeing on the transform between
        them, when it has enough support and no disagreeing set has too (else None)."""
        if len(members) < self.min_pairs:
            return None
        g_a = group_of(members[0].a_id)
        # oriented as (a in group g_a, b in the other group, a_T_b)
        ends = [p.oriented(group_of, g_a) for p in members]
        a_ids = sorted({a for a, _, _ in ends})
        b_ids = sorted({b for _, b, _ in ends})
        from_a = {a: self.motion.paths(a, a_ids, self._limit) for a in a_ids}
        from_b = {b: self.motion.paths(b, b_ids, self._limit) for b in b_ids}
        A_T_B = torch.stack([implied_transform(pose(a), T, pose(b)) for a, b, T in ends])
        meas = torch.stack([T.double() for _, _, T in ends])
        Ta_inv = se3.inverse(torch.stack([pose(a) for a, _, _ in ends]))
        Tb = torch.stack([pose(b) for _, b, _ in ends])
        n = len(ends)
        qualified: list[set[int]] = []
        for k in range(n):  # pivot k: does loop q agree with the transform loop k implies?
            pred = Ta_inv @ A_T_B[k] @ Tb
            paths = torch.tensor([from_a[ends[k][0]][a] + from_b[ends[k][1]][b] for a, b, _ in ends],
                                 dtype=torch.float64)
            agree = {q for q, ok in enumerate(consistent(pred, meas, paths, self.model).tolist()) if ok} | {k}
            if self._support(agree, ends, members) >= self.min_pairs:
                qualified.append(agree)
        if not qualified:
            return None
        best = max(qualified, key=len)
        if any(not (s & best) for s in qualified):  # disjoint (disagreeing) sets both supported
            self.stats.ambiguous += 1
            return None
        return [members[q] for q in sorted(best)]

    # ------------------------------------------------------------------ cycles of groups
    def _close_cycle(self, key: frozenset, group_of, pose,
                     skip: set) -> tuple[list[PendingLoop], list[PendingLoop]] | None:
        """Three pending loops A-B (the pair ``key``), B-C, C-A that close a cycle (see
        ``cycles``), C not in ``skip``; returns ``(loops in that order, every pending loop
        between the three groups)`` or None. The loops must come from at least ``min_pairs``
        (and two) distinct query keyframes, the support :meth:`_evaluate` asks of two groups.
        Every combination of one loop per leg is checked in one batch."""
        between: dict[frozenset, list[PendingLoop]] = {}
        for p in self.pending:
            if len(p.groups) == 2:
                between.setdefault(p.groups, []).append(p)
        g_a, g_b = sorted(key)
        third = sorted({g for k in between if g_a in k for g in k} & {g for k in between if g_b in k for g in k}
                       - {g_a, g_b} - skip)
        paths: dict[tuple[int, int], float] = {}

        def path(i: int, j: int) -> float:
            if (i, j) not in paths:
                paths[(i, j)] = self.motion.paths(i, [j], self._limit)[j]
            return paths[(i, j)]

        contradicted = False
        for g_c in third:
            legs = [between[key], between[frozenset((g_b, g_c))], between[frozenset((g_c, g_a))]]
            ends = [[p.oriented(group_of, g) for p in leg] for leg, g in zip(legs, (g_a, g_b, g_c))]
            # G_i_T_G_i+1 implied by each loop of the first two legs; the last leg is predicted
            A_T_B, B_T_C = (torch.stack([implied_transform(pose(x), T.double(), pose(y)) for x, y, T in leg])
                            for leg in ends[:2])
            pred = closing_prediction(A_T_B, B_T_C, torch.stack([pose(x) for x, _, _ in ends[2]]),
                                      torch.stack([pose(y) for _, y, _ in ends[2]]))  # (n0, n1, n2, 4, 4)
            meas = torch.stack([T.double() for _, _, T in ends[2]]).expand_as(pred)
            drift = torch.tensor([[[path(e3[1], e1[0]) + path(e1[1], e2[0]) + path(e2[1], e3[0]) for e3 in ends[2]]
                                   for e2 in ends[1]] for e1 in ends[0]], dtype=torch.float64)
            ok = consistent(pred.reshape(-1, 4, 4), meas.reshape(-1, 4, 4), drift.reshape(-1), self.model)
            for flat in torch.nonzero(ok).flatten().tolist():
                i, rest = divmod(flat, len(legs[1]) * len(legs[2]))
                chosen = (legs[0][i], legs[1][rest // len(legs[2])], legs[2][rest % len(legs[2])])
                if len({p.b_id for p in chosen}) < max(self.min_pairs, 2):
                    continue
                members = legs[0] + legs[1] + legs[2]
                if self._contradicted(chosen, members, group_of, pose):
                    contradicted = True
                    continue
                return list(chosen), members
        self.stats.ambiguous += contradicted
        return None

    def _contradicted(self, chosen: tuple, members: list[PendingLoop], group_of, pose) -> bool:
        """Whether a pending loop among ``members`` disagrees with the transform between its
        groups that ``chosen`` (loops between the same three groups) implies by more than
        ``doubt_factor`` times the drift tolerance."""
        model = self.model.scaled(self.doubt_factor)
        for q in members:
            if any(q is p for p in chosen):
                continue
            p = next(p for p in chosen if p.groups == q.groups)
            x, y, T = p.oriented(group_of, group_of(q.a_id))
            G_T_H = implied_transform(pose(x), T, pose(y))
            pred = se3.inverse(pose(q.a_id)) @ G_T_H @ pose(q.b_id)
            drift = torch.tensor([self.motion.paths(x, [q.a_id], self._limit)[q.a_id]
                                  + self.motion.paths(y, [q.b_id], self._limit)[q.b_id]], dtype=torch.float64)
            if not bool(consistent(pred[None], q.a_T_b.double()[None], drift, model)):
                return True
        return False
