"""Reference solve with ``pypose.optim.LM`` (dense Jacobian; for small graphs and cross-checks).

pypose builds the dense ``(6 F) x (6 N)`` Jacobian by autograd through its LieTensor ``Log``
and solves the dense normal equations, so its cost grows quickly with the graph (about 0.4 s
per iteration at 50 keyframes and 13 s at 500 on a 2-core machine). It serves as the
independent implementation that :func:`tactile_slam.posegraph.solver.solve` is tested against.
"""

from __future__ import annotations

import time

import pypose as pp
import torch

from tactile_slam.posegraph import se3
from tactile_slam.posegraph.graph import PoseGraph


class _Residuals(torch.nn.Module):
    """Whitened residuals of every factor: ``(6 (E + P),)``, pypose's own SE(3) maths."""

    def __init__(self, graph: PoseGraph) -> None:
        super().__init__()
        e, p = graph.edges, graph.priors
        self.nodes = pp.Parameter(se3.to_pypose(graph.poses()))
        self.i, self.j, self.Zinv = e.i, e.j, se3.to_pypose(e.Z).Inv()
        self.w = 1.0 / e.sigma
        self.prow, self.PZinv, self.pw = p.rows, se3.to_pypose(p.Z).Inv(), 1.0 / p.sigma

    def forward(self, _input: torch.Tensor | None = None) -> torch.Tensor:
        X = self.nodes
        e = (self.Zinv * X[self.i].Inv() * X[self.j]).Log().tensor() * self.w
        p = (self.PZinv * X[self.prow]).Log().tensor() * self.pw
        return torch.cat([e.reshape(-1), p.reshape(-1)])


def solve_pypose(graph: PoseGraph, max_iters: int = 100, tol: float = 1e-5,
                 time_limit_s: float | None = None) -> dict[str, float]:
    """Optimise ``graph`` in place with ``pypose.optim.LM``; returns iterations, costs, time.

    Stops when the relative cost decrease falls below ``tol``, after ``max_iters`` steps, or
    once ``time_limit_s`` has passed. Cost is ``0.5 sum |e / sigma|^2`` as in the sparse solver.
    """
    model = _Residuals(graph).double()
    opt = pp.optim.LM(model, strategy=pp.optim.strategy.Constant(damping=1e-6), vectorize=True)
    t0 = time.perf_counter()
    with torch.no_grad():
        cost0 = 0.5 * float((model() ** 2).sum())
    cost, its, step_times = cost0, 0, []
    while its < max_iters:
        ts = time.perf_counter()
        new = 0.5 * float(opt.step(input=None))
        step_times.append(time.perf_counter() - ts)
        its += 1
        done = cost - new <= tol * max(cost, 1e-300)
        cost = min(cost, new)
        if done or (time_limit_s is not None and time.perf_counter() - t0 > time_limit_s):
            break
    with torch.no_grad():
        graph.set_poses(torch.arange(graph.num_nodes), se3.from_pypose(model.nodes.detach()))
        cost = 0.5 * float((model() ** 2).sum())
    return {"iterations": its, "cost_initial": cost0, "cost_final": cost,
            "time_s": time.perf_counter() - t0, "step_s": step_times}
