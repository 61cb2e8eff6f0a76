"""Loop-candidate retrieval that does not grow as brute force over the map.

Two filters narrow the eligible keyframes (the active coverage keyframes) before the
per-pair matching and RANSAC of :mod:`tactile_slam.loop.matching`:

* a **pose gate** for keyframes of the query's own connected group: each keyframe's
  contact footprint is summarised by its centroid and radius (metres, keyframe frame);
  a candidate whose footprint sphere, moved by the current pose estimates, lies farther
  than ``margin`` from the query's, or whose sensor z axis opposes the query's (the
  coverage set's overlap is zero then, method.md 6.1), cannot overlap it and is
  skipped. Keyframes of other groups have no relative pose estimate and are not gated.
* a **descriptor index** over the keyframes' SIFT descriptors: each query descriptor
  takes its ``k`` nearest indexed descriptors; each distinct keyframe among them gets
  one vote; the keyframes with the most votes (at least ``min_votes``) are the
  candidates. The newest descriptors (up to ``exact_max``) are searched exactly; older
  ones sit in OpenCV FLANN kd-tree forests of sizes at least doubling (the logarithmic
  method, :class:`DescriptorIndex`), so no part of the search grows linearly with the map
  and each descriptor is rebuilt into a forest ``O(log N)`` times.

Per-query cost is ``O(Q log^2 N)`` for the kd-tree levels plus ``O(Q exact_max)`` for the
exact tail, instead of a match and a RANSAC per keyframe.
"""

from __future__ import annotations

from collections.abc import Collection
from dataclasses import dataclass

import cv2
import numpy as np
import torch


class RetrievalError(ValueError):
    """Invalid input to retrieval (bad descriptors, unknown or duplicate id, bad pose)."""


# --------------------------------------------------------------------------- pose gate


@dataclass
class Footprint:
    """Contact footprint of a keyframe in its own sensor frame.

    Attributes:
        centre: ``(3,)`` float64 metres, mean of the contact points.
        radius: metres, largest distance of a contact point from ``centre``.
    """

    centre: torch.Tensor
    radius: float


def footprints(height: torch.Tensor, contact: torch.Tensor, m_per_px: float) -> list[Footprint | None]:
    """Footprints of ``B`` keyframes (``None`` where the contact is empty).

    Args:
        height: ``(B, H, W)`` px.
        contact: ``(B, H, W)`` bool.
        m_per_px: metres per pixel.

    Returns:
        ``B`` footprints; points follow method.md 1.2.
    """
    if height.ndim != 3 or tuple(contact.shape) != tuple(height.shape):
        raise RetrievalError(f"height and contact must be matching (B, H, W), got {tuple(height.shape)} "
                             f"and {tuple(contact.shape)}")
    _, h, w = height.shape
    out: list[Footprint | None] = []
    for hk, ck in zip(height, contact):  # contact pixels only: ~10x less work than full maps
        rows, cols = torch.nonzero(ck, as_tuple=True)
        if rows.numel() == 0:
            out.append(None)
            continue
        pts = torch.stack([cols.double() - (w - 1) / 2.0, rows.double() - (h - 1) / 2.0, hk[rows, cols].double()],
                          1) * m_per_px
        centre = pts.mean(0)
        out.append(Footprint(centre.cpu(), float(torch.linalg.vector_norm(pts - centre, dim=1).max())))
    return out


def pose_gate(query: Footprint, start_T_query: torch.Tensor, refs: list[Footprint],
              start_T_refs: torch.Tensor, margin_m: float) -> torch.Tensor:
    """Which reference footprints may overlap the query's under the pose estimates.

    Args:
        query: the query keyframe's footprint.
        start_T_query: ``(4, 4)`` float64 pose of the query keyframe in the group start.
        refs: ``R`` footprints of keyframes in the same group.
        start_T_refs: ``(R, 4, 4)`` their poses in the same start frame.
        margin_m: slack added to the sum of radii (pose drift, gel deformation).

    Returns:
        ``(R,)`` bool, True where the reference may overlap the query.
    """
    if len(refs) == 0:
        return torch.zeros(0, dtype=torch.bool)
    tq = torch.as_tensor(start_T_query, dtype=torch.float64).cpu()
    tr = torch.as_tensor(start_T_refs, dtype=torch.float64).cpu()
    if tq.shape != (4, 4) or tr.shape != (len(refs), 4, 4):
        raise RetrievalError(f"poses must be (4, 4) and ({len(refs)}, 4, 4), got {tuple(tq.shape)} "
                             f"and {tuple(tr.shape)}")
    if not (bool(torch.isfinite(tq).all()) and bool(torch.isfinite(tr).all())):
        raise RetrievalError("pose estimates contain NaN or Inf")
    cq = tq[:3, :3] @ query.centre + tq[:3, 3]
    centres = torch.stack([f.centre for f in refs])
    radii = torch.tensor([f.radius for f in refs], dtype=torch.float64)
    cr = torch.einsum("rij,rj->ri", tr[:, :3, :3], centres) + tr[:, :3, 3]
    near = torch.linalg.vector_norm(cr - cq, dim=1) <= radii + query.radius + margin_m
    facing = tr[:, :3, 2] @ tq[:3, 2] > 0.0
    return near & facing


# --------------------------------------------------------------------------- descriptor index


@dataclass(frozen=True)
class IndexSettings:
    """Descriptor-index settings.

    Attributes:
        neighbours: nearest descriptors per query descriptor (``k``).
        min_votes: least votes for a keyframe to be returned.
        exact_max: the newest descriptors, up to this many, are searched exactly (a
            map that small is searched exactly as a whole).
        rebuild_fraction: rebuild a kd-tree level when the descriptors of keyframes
            removed from it exceed this fraction of it.
        trees: kd-trees in the FLANN forest.
        checks: leaves FLANN visits per query (accuracy vs time).
        seed: seed of the forest's random splits. FLANN draws them from OpenCV's RNG of
            the calling thread, whose state depends on everything the process did
            before; seeded at each build, a level depends only on its descriptors, so
            the same scan gives the same loops whether it runs alone or after others.
    """

    neighbours: int = 5
    min_votes: int = 3
    exact_max: int = 4096
    rebuild_fraction: float = 0.25
    trees: int = 4
    checks: int = 64
    seed: int = 0


def _exact_knn(query: np.ndarray, pool: np.ndarray, k: int) -> tuple[np.ndarray, np.ndarray]:
    """``k`` nearest rows of ``pool`` ``(P, D)`` for each row of ``query`` ``(Q, D)`` by
    squared L2. Returns ``(idx (Q, k') int64, d2 (Q, k') float32)``, ``k' = min(k, P)``."""
    q, p = torch.from_numpy(query), torch.from_numpy(pool)
    d2 = (q.square().sum(1, keepdim=True) - 2.0 * q @ p.T + p.square().sum(1)[None]).clamp_min(0.0)
    vals, idx = d2.topk(min(k, p.shape[0]), dim=1, largest=False)
    return idx.numpy().astype(np.int64), vals.numpy()


@dataclass
class _Level:
    """A kd-tree forest over the descriptors of some keyframes (``ids``); ``dead`` counts
    the descriptors of those removed since it was built, still in its trees."""

    ids: set[int]
    owner: np.ndarray
    flann: cv2.flann_Index
    dead: int = 0


class DescriptorIndex:
    """Approximate nearest-neighbour index of keyframe descriptors with per-keyframe voting.

    The descriptors of the newest keyframes (at most ``exact_max``) are searched exactly;
    when they exceed it they become a kd-tree *level*, and a level at least half the size
    of the one before it is merged into it (the logarithmic method: levels at least
    doubling in size, each descriptor rebuilt ``O(log N)`` times). A query searches every
    level and the exact tail, so it costs ``O(Q log^2 N)`` plus ``O(Q exact_max)``, at any
    map size. A level loses the keyframes removed from it and is rebuilt once more than
    ``rebuild_fraction`` of it is dead.

    Args:
        settings: index settings.
    """

    def __init__(self, settings: IndexSettings | None = None):
        self.settings = settings or IndexSettings()
        if self.settings.neighbours < 1 or self.settings.min_votes < 1:
            raise RetrievalError("index neighbours and min_votes must be >= 1")
        self._blocks: dict[int, np.ndarray] = {}  # live descriptors per keyframe id
        self._levels: list[_Level] = []  # kd-tree levels, largest first
        self._tail: list[int] = []  # ids searched exactly, in order
        self._tail_cache: tuple[np.ndarray, np.ndarray] | None = None

    def __len__(self) -> int:
        return len(self._blocks)

    def __contains__(self, kf_id: int) -> bool:
        return kf_id in self._blocks

    @property
    def n_descriptors(self) -> int:
        return sum(len(d) for d in self._blocks.values())

    @property
    def level_sizes(self) -> list[int]:
        """Descriptors in each kd-tree level (dead ones included), largest first; then the
        exact tail's count last."""
        return [len(lv.owner) for lv in self._levels] + [self._count(self._tail)]

    def add(self, kf_id: int, descriptors: torch.Tensor | np.ndarray) -> None:
        """Index a keyframe's ``(N, D)`` descriptors (``N`` may be 0)."""
        if kf_id in self._blocks:
            raise RetrievalError(f"keyframe {kf_id} is already indexed")
        d = np.ascontiguousarray(descriptors.cpu().numpy() if isinstance(descriptors, torch.Tensor) else descriptors,
                                 dtype=np.float32)
        if d.ndim != 2 or (len(d) and d.shape[1] != 128):
            raise RetrievalError(f"descriptors must be (N, 128), got {d.shape}")
        if not np.isfinite(d).all():
            raise RetrievalError(f"descriptors of keyframe {kf_id} contain NaN or Inf")
        self._blocks[kf_id] = d
        self._tail.append(kf_id)
        self._tail_cache = None
        if self._count(self._tail) > self.settings.exact_max:
            self._levels.append(self._build(self._tail))
            self._tail = []
            while len(self._levels) >= 2 and 2 * self._live(self._levels[-1]) >= self._live(self._levels[-2]):
                last = self._levels.pop()
                self._levels[-1] = self._build(self._levels[-1].ids | last.ids)

    def remove(self, kf_id: int) -> None:
        """Drop a keyframe (e.g. deactivated by the coverage set); unknown ids are an error."""
        d = self._blocks.pop(kf_id, None)
        if d is None:
            raise RetrievalError(f"keyframe {kf_id} is not indexed")
        if kf_id in self._tail:
            self._tail.remove(kf_id)
            self._tail_cache = None
        else:
            i = next(i for i, lv in enumerate(self._levels) if kf_id in lv.ids)
            lv = self._levels[i]
            lv.ids.discard(kf_id)
            lv.dead += len(d)
            if self._live(lv) == 0:  # keyframes without descriptors may remain: to the tail
                del self._levels[i]
                self._tail += sorted(lv.ids)
                self._tail_cache = None
            elif lv.dead > self.settings.rebuild_fraction * len(lv.owner):
                self._levels[i] = self._build(lv.ids)
        if self._levels and self.n_descriptors <= self.settings.exact_max:  # shrank back: all exact
            self._tail = list(self._blocks)
            self._levels = []
            self._tail_cache = None

    def _count(self, ids) -> int:
        return sum(len(self._blocks[i]) for i in ids)

    def _live(self, level: _Level) -> int:
        return len(level.owner) - level.dead

    def _stack(self, ids: list[int]) -> tuple[np.ndarray, np.ndarray]:
        """The descriptors of ``ids`` in one array and the id owning each row:
        ``((n, 128) float32, (n,) int64)``."""
        blocks = [self._blocks[i] for i in ids]
        desc = np.concatenate(blocks) if blocks else np.zeros((0, 128), np.float32)
        return desc, np.repeat(np.asarray(ids, np.int64), [len(b) for b in blocks])

    def _build(self, ids) -> _Level:
        ids = sorted(ids)
        desc, owner = self._stack(ids)
        cv2.setRNGSeed(self.settings.seed)  # the kd-trees' splits (see IndexSettings.seed)
        return _Level(set(ids), owner, cv2.flann_Index(desc, dict(algorithm=1, trees=self.settings.trees)))

    def _tail_pool(self) -> tuple[np.ndarray, np.ndarray]:
        if self._tail_cache is None:
            self._tail_cache = self._stack(self._tail)
        return self._tail_cache

    def neighbours(self, query: torch.Tensor | np.ndarray) -> np.ndarray:
        """Keyframe ids of the ``k`` nearest live descriptors of each query descriptor.

        Args:
            query: ``(Q, D)`` descriptors.

        Returns:
            ``(Q, k')`` int64 keyframe ids (``-1`` where fewer than ``k`` exist).
        """
        q = np.ascontiguousarray(query.cpu().numpy() if isinstance(query, torch.Tensor) else query, np.float32)
        k = self.settings.neighbours
        out_ids, out_d = [], []
        for lv in self._levels if len(q) else []:
            kk = min(k + (k if lv.dead else 0), len(lv.owner))
            idx, d2 = lv.flann.knnSearch(q, kk, params=dict(checks=self.settings.checks))
            idx = idx.astype(np.int64).reshape(len(q), kk)
            owner = lv.owner[np.clip(idx, 0, None)]
            dead = idx < 0
            if lv.dead:
                dead |= ~np.isin(owner, np.fromiter(lv.ids, np.int64, len(lv.ids)))
            out_ids.append(np.where(dead, -1, owner))
            out_d.append(np.where(dead, np.inf, d2.reshape(len(q), kk)))
        desc, owner = self._tail_pool()
        if len(desc) and len(q):
            idx, d2 = _exact_knn(q, desc, k)
            out_ids.append(owner[idx])
            out_d.append(d2)
        if not out_ids:
            return np.full((len(q), 0), -1, np.int64)
        ids, d = np.concatenate(out_ids, 1), np.concatenate(out_d, 1)
        order = np.argsort(d, axis=1, kind="stable")[:, :k]
        return np.take_along_axis(ids, order, 1)

    def vote(self, query: torch.Tensor | np.ndarray, allowed: Collection[int] | None = None) -> dict[int, int]:
        """Votes per keyframe: the number of query descriptors with that keyframe among
        their ``k`` nearest descriptors. Only ``allowed`` ids count (all if ``None``).

        Returns:
            ``{kf_id: votes}`` for ids with at least one vote.
        """
        ids = self.neighbours(query)
        if ids.size == 0:
            return {}
        # one vote per (query descriptor, keyframe)
        ids = np.sort(ids, axis=1)
        first = np.ones_like(ids, dtype=bool)
        first[:, 1:] = ids[:, 1:] != ids[:, :-1]
        flat = ids[first & (ids >= 0)]
        if allowed is not None:
            flat = flat[np.isin(flat, np.fromiter(allowed, np.int64, len(allowed)))]
        uniq, counts = np.unique(flat, return_counts=True)
        return dict(zip(uniq.tolist(), counts.tolist()))

    def query(self, query: torch.Tensor | np.ndarray, allowed: Collection[int] | None, top: int) -> list[int]:
        """The ``top`` keyframes with the most votes (at least ``min_votes``), best first
        (ties: lower id first)."""
        votes = self.vote(query, allowed)
        ranked = sorted((kf for kf, v in votes.items() if v >= self.settings.min_votes), key=lambda i: (-votes[i], i))
        return ranked[:top]
