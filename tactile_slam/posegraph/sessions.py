"""Sessions and groups: union-find over tracking sessions (method.md section 7.1).

A *session* is a contiguous contact period tracked without an unrecoverable failure; its
first keyframe (the head) is anchored by an identity prior, so every new session starts its own
*group* with its own "start" frame. Loops join groups. :meth:`SessionGroups.merge` applies the
section 7.1 rules (the group with the most keyframes becomes the root, ties going to the new
keyframe's group; absorbed groups lose their priors) and the section 7.2 [Rec] fix: each
absorbed group is moved rigidly through a loop measurement into the root's frame, so the
solver starts from consistent values instead of identity-anchored ones.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field

import torch

from tactile_slam.posegraph import se3
from tactile_slam.posegraph.graph import PoseGraph


class SessionError(ValueError):
    """Unknown keyframe or session, or a keyframe added twice."""


@dataclass
class MergeResult:
    """What :meth:`SessionGroups.merge` did.

    Attributes:
        root: root session of the merged group.
        absorbed: root sessions of the groups absorbed into it, in merge order.
        moved: keyframe ids whose initial values were re-initialised.
        removed_priors: keyframe ids whose priors were removed from the graph.
    """

    root: int
    absorbed: list[int] = field(default_factory=list)
    moved: list[int] = field(default_factory=list)
    removed_priors: list[int] = field(default_factory=list)


class SessionGroups:
    """Union-find of sessions; a group's size is its number of keyframes."""

    def __init__(self) -> None:
        self._parent: dict[int, int] = {}
        self._size: dict[int, int] = {}
        self._members: dict[int, list[int]] = {}
        self._anchor: dict[int, int] = {}
        self._session_of: dict[int, int] = {}

    # ------------------------------------------------------------------ queries
    def find(self, session: int) -> int:
        """Root session of ``session``'s group (with path halving)."""
        if session not in self._parent:
            raise SessionError(f"unknown session {session}")
        p = self._parent
        while p[session] != session:
            p[session] = p[p[session]]
            session = p[session]
        return session

    def group_of(self, kf_id: int) -> int:
        """Root session of the group that keyframe ``kf_id`` belongs to."""
        if kf_id not in self._session_of:
            raise SessionError(f"unknown keyframe {kf_id}")
        return self.find(self._session_of[kf_id])

    def size(self, root: int) -> int:
        return self._size[self.find(root)]

    def members(self, root: int) -> list[int]:
        """Keyframe ids of the group of ``root``, in insertion order within each session."""
        return list(self._members[self.find(root)])

    def anchor(self, root: int) -> int:
        """The keyframe whose prior defines the group's "start" frame."""
        return self._anchor[self.find(root)]

    @property
    def groups(self) -> list[int]:
        """Root sessions of all groups."""
        return [s for s, p in self._parent.items() if s == p]

    @property
    def num_sessions(self) -> int:
        return len(self._parent)

    # ------------------------------------------------------------------ updates
    def add_keyframe(self, kf_id: int, session: int) -> bool:
        """Register a keyframe; returns True when it is the head of a new session.

        A new session becomes its own group anchored at this keyframe: the caller adds the
        identity prior on it to the pose graph.
        """
        if kf_id in self._session_of:
            raise SessionError(f"keyframe {kf_id} was already added")
        self._session_of[kf_id] = session
        head = session not in self._parent
        if head:
            self._parent[session] = session
            self._size[session] = 0
            self._members[session] = []
            self._anchor[session] = kf_id
        root = self.find(session)
        self._size[root] += 1
        self._members[root].append(kf_id)
        return head

    def merge(self, graph: PoseGraph, t: int, loops: Sequence[tuple[int, torch.Tensor]],
              reinit: bool = True) -> MergeResult:
        """Merge the groups joined by accepted loops ``(r, r_T_t)`` of new keyframe ``t``.

        The loop factors themselves are the caller's to add. Groups take part in the order
        group(t), then the groups of the refs in ``loops`` order; the largest becomes the root
        (ties: the earliest, so group(t) wins a tie). For each absorbed group its prior is
        removed from ``graph`` and, when ``reinit``, every pose ``start_T_k`` of it becomes
        ``C . start_T_k``, with ``C`` taken through its first loop so that the loop holds exactly:
        ``C = start_T_r . Z . start_T_t^-1`` when t's group moves, and
        ``C = start_T_t . Z^-1 . start_T_r^-1`` when r's group moves.
        """
        gt = self.group_of(t)
        order = [gt]
        first_loop: dict[int, tuple[int, torch.Tensor]] = {}
        for r, Z in loops:
            gr = self.group_of(r)
            if gr not in first_loop:
                first_loop[gr] = (r, torch.as_tensor(Z, dtype=torch.float64))
            if gr not in order:
                order.append(gr)
        root = order[0]
        for g in order[1:]:
            if self._size[g] > self._size[root]:
                root = g
        result = MergeResult(root=root)
        if len(order) == 1:
            return result
        absorbed = [g for g in order if g != root]
        if reinit:
            if gt != root:
                r, Z = first_loop[root]
                C = graph.pose(r) @ Z @ se3.inverse(graph.pose(t))
                result.moved += self._move(graph, gt, C)
            for g in absorbed:
                if g == gt:
                    continue
                r, Z = first_loop[g]
                C = graph.pose(t) @ se3.inverse(Z) @ se3.inverse(graph.pose(r))
                result.moved += self._move(graph, g, C)
        for g in absorbed:
            a = self._anchor.pop(g)
            if a in graph and graph.has_prior(a):
                graph.remove_prior(a)
                result.removed_priors.append(a)
            self._parent[g] = root
            self._size[root] += self._size.pop(g)
            self._members[root] += self._members.pop(g)
            result.absorbed.append(g)
        return result

    def _move(self, graph: PoseGraph, group: int, C: torch.Tensor) -> list[int]:
        ids = [k for k in self._members[group] if k in graph]
        rows = graph.rows(ids)
        graph.set_poses(rows, C @ graph.poses(ids))
        return ids
