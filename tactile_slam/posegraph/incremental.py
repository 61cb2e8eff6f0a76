"""Incremental pose-graph updates after each keyframe (method.md section 7.2, [Rec]).

GelSLAM re-solves the whole graph from scratch after every keyframe. Here, after new nodes
and factors are added to a :class:`PoseGraph`, :meth:`IncrementalSolver.update`:

1. **skips** the solve when the new factors' whitened cost at the current estimate is at most
   ``tol`` and no prior was removed (a solve could then lower the cost by at most that much;
   a keyframe whose only factor is its odometry, initialised by chaining it, adds exactly 0);
2. otherwise solves a **local region** first: the ``window`` poses nearest (in graph hops) to
   the new factors' ends, warm-started, with every other pose held fixed;
3. **checks the boundary**: the cost decrease that moving the fixed poses next to the region
   would still bring, predicted from their gradient and block-diagonal Hessian. If it
   exceeds ``tol`` the region grows fourfold and is re-solved, up to the whole connected group.

:meth:`IncrementalSolver.finalize` runs a full warm-started solve (e.g. at the end of a scan).
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field

import torch

from tactile_slam.config import PoseGraphConfig
from tactile_slam.posegraph import se3
from tactile_slam.posegraph.graph import PoseGraph
from tactile_slam.posegraph.solver import SolveReport, _Problem, solve, solver_context


@dataclass
class UpdateReport:
    """What one :meth:`IncrementalSolver.update` did.

    Attributes:
        skipped: the new factors were already satisfied; nothing was solved.
        new_cost: whitened cost ``0.5 sum |e/sigma|^2`` of the new factors before the update.
        regions: number of poses in each region solved, in order (the last one sufficed).
        iterations: accepted LM steps over all regions.
        time_s: wall-clock seconds.
    """

    skipped: bool = True
    new_cost: float = 0.0
    regions: list[int] = field(default_factory=list)
    iterations: int = 0
    time_s: float = 0.0


class IncrementalSolver:
    """Keeps ``graph`` near its least-squares optimum as keyframes arrive.

    Args:
        graph: the pose graph; nodes and factors are added to it by the caller between calls
            to :meth:`update`. Its poses are updated in place.
        config: solver settings; ``incremental_window`` (poses in the first region),
            ``incremental_tol`` (boundary test, whitened cost units) and
            ``incremental_max_iters`` (LM steps per region) drive the local solves.
    """

    def __init__(self, graph: PoseGraph, config: PoseGraphConfig | None = None) -> None:
        self.graph = graph
        self.config = config or PoseGraphConfig()
        self._nodes_seen = 0
        self._edges_seen = 0
        self._priors_seen: set[int] = set()
        self._adjacency: list[list[int]] = []  # neighbours of each graph row, extended as edges arrive

    def update(self) -> UpdateReport:
        """Bring the estimate up to date with the factors added since the last call."""
        with solver_context():
            return self._update()

    def _update(self) -> UpdateReport:
        t0 = time.perf_counter()
        g, cfg = self.graph, self.config
        report = UpdateReport()
        e = g.edges
        new_edges = torch.arange(self._edges_seen, g.num_edges)
        priors = g.priors
        prior_rows = set(priors.rows.tolist())
        added_priors = sorted(prior_rows - self._priors_seen)
        removed_priors = sorted(self._priors_seen - prior_rows)
        seeds = torch.cat([e.i[new_edges], e.j[new_edges], torch.arange(self._nodes_seen, g.num_nodes),
                           torch.tensor(added_priors + removed_priors, dtype=torch.int64)]).unique()
        self._adjacency.extend([] for _ in range(g.num_nodes - len(self._adjacency)))
        for i, j in zip(e.i[new_edges].tolist(), e.j[new_edges].tolist()):
            self._adjacency[i].append(j)
            self._adjacency[j].append(i)
        self._nodes_seen, self._edges_seen, self._priors_seen = g.num_nodes, g.num_edges, prior_rows
        if seeds.numel() == 0:
            report.time_s = time.perf_counter() - t0
            return report

        report.new_cost = _new_factor_cost(g, new_edges, torch.tensor(added_priors, dtype=torch.int64))
        if report.new_cost <= cfg.incremental_tol and not removed_priors:
            report.time_s = time.perf_counter() - t0
            return report
        report.skipped = False

        levels = _HopLevels(self._adjacency, seeds.tolist())
        size = cfg.incremental_window
        while True:
            rows, boundary = levels.region(size)
            rep = solve(g, cfg, rows=rows, max_iters=cfg.incremental_max_iters)
            report.regions.append(rows.numel())
            report.iterations += rep.iterations
            if boundary.numel() == 0 or _boundary_decrease(g, boundary) <= cfg.incremental_tol:
                break  # no pose left outside the region, or none that would still move
            size = 4 * rows.numel()
        report.time_s = time.perf_counter() - t0
        return report

    def finalize(self) -> SolveReport:
        """Full warm-started solve of every pose (e.g. at the end of a scan)."""
        self.update()
        return solve(self.graph, self.config)


def _new_factor_cost(g: PoseGraph, new_edges: torch.Tensor, new_prior_rows: torch.Tensor) -> float:
    """Whitened cost ``0.5 sum |e/sigma|^2`` of the given edges and of the priors on the given rows."""
    X = g.poses()
    e = g.edges
    r = se3.between_error(e.Z[new_edges], X[e.i[new_edges]], X[e.j[new_edges]]) / e.sigma[new_edges]
    cost = 0.5 * float((r * r).sum())
    pr = g.priors
    sel = torch.isin(pr.rows, new_prior_rows)
    if sel.any():
        p = se3.log(se3.inverse(pr.Z[sel]) @ X[pr.rows[sel]]) / pr.sigma[sel]
        cost += 0.5 * float((p * p).sum())
    return cost


class _HopLevels:
    """Graph rows by hop distance from seed rows (breadth-first), expanded only as far as asked.

    ``adjacency[r]`` lists the neighbours of row ``r``. A region of the default window reads
    a hundred-odd rows, so this beats a shortest-path pass over the whole graph per update.
    """

    def __init__(self, adjacency: list[list[int]], seeds: list[int]) -> None:
        self.adjacency = adjacency
        self.levels = [sorted(set(seeds))]
        self.seen = set(self.levels[0])

    def _grow(self) -> bool:
        """Add the next level; False when nothing is left to reach."""
        nxt = {v for u in self.levels[-1] for v in self.adjacency[u]} - self.seen
        if not nxt:
            return False
        self.seen |= nxt
        self.levels.append(sorted(nxt))
        return True

    def region(self, size: int) -> tuple[torch.Tensor, torch.Tensor]:
        """Rows within the smallest radius that holds at least ``size`` rows (every reachable
        row if fewer), and the rows one hop beyond it (empty when there are none); both
        sorted ``(n,)`` int64."""
        r, count = 0, len(self.levels[0])
        while count < size and (r + 1 < len(self.levels) or self._grow()):
            r += 1
            count += len(self.levels[r])
        if r + 1 == len(self.levels):
            self._grow()
        rows = sorted(v for level in self.levels[:r + 1] for v in level)
        boundary = self.levels[r + 1] if r + 1 < len(self.levels) else []
        return torch.tensor(rows, dtype=torch.int64), torch.tensor(boundary, dtype=torch.int64)


def _boundary_decrease(g: PoseGraph, boundary: torch.Tensor) -> float:
    """Predicted cost decrease from moving each ``boundary`` pose alone: ``0.5 g^T D^-1 g``."""
    prob = _Problem(g, boundary, check_anchored=False)  # linearised only, never solved
    w = torch.ones(prob.edge_idx.numel(), dtype=torch.float64)
    blocks, grad = prob.linearize(g.poses(), w)
    D = torch.from_numpy(blocks[prob.slot_diag.numpy()])
    gr = torch.from_numpy(grad).reshape(-1, 6, 1)
    return 0.5 * float((gr * torch.linalg.solve(D, gr)).sum())
