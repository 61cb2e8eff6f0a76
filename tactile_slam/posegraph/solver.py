"""Sparse Levenberg-Marquardt on SE(3) for pose graphs (method.md section 7).

Every factor is linearised in one batch (:mod:`tactile_slam.posegraph.se3`), the whitened
6x6 blocks are summed into block-sparse normal equations ``(J^T W J + lambda I) delta = -J^T W e``
whose nested-dissection ordering is computed once per sparsity pattern, and the system is
solved by the multifrontal block Cholesky of :mod:`tactile_slam.posegraph.cholesky` (SciPy's
SuperLU was 10-30x slower on 5,000-keyframe graphs: it runs on a reference BLAS).

The cost is GTSAM's: ``0.5 sum rho(|e / sigma|^2)``; the LM schedule follows GTSAM's defaults
(at most 100 iterations, relative and absolute decrease tolerances 1e-5, initial lambda 1e-5,
factor 10, upper bound 1e5). Poses move by right perturbation ``T <- T . Exp(delta)``.

Loop factors can be robustified (``config.robust``): ``"huber"`` or ``"cauchy"`` kernels by
iteratively reweighted least squares, or ``"gnc"``, graduated non-convexity with a truncated
least-squares cost that ends with each loop accepted or rejected. Odometry factors and
priors are always plain least squares (known inliers).
"""

from __future__ import annotations

import time
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass, field

import numpy as np
import scipy.sparse as sp
import scipy.sparse.csgraph as csgraph
import torch

from tactile_slam.config import ROBUST_MODES, PoseGraphConfig
from tactile_slam.posegraph import robust, se3
from tactile_slam.posegraph.cholesky import BlockCholesky, FactorError
from tactile_slam.posegraph.graph import GraphError, PoseGraph


class SolverError(ValueError):
    """The problem is ill-posed (a connected group of variables without a prior)."""


@dataclass
class SolveReport:
    """What one solve did.

    Attributes:
        iterations: accepted LM steps (summed over GNC stages).
        cost_initial / cost_final: ``0.5 sum rho(|e/sigma|^2)`` before and after.
        converged: a tolerance was met: an accepted step lowered the cost by at most
            ``abs_tol`` / ``rel_tol``, or, at a minimum, a rejected step raised it by at most
            that and was predicted to lower it by at most that (False when stopped by the
            iteration cap or the lambda bound).
        n_variables / n_factors: poses optimised, factors touching them.
        time_s: wall-clock seconds.
        loop_weights: ``(E,)`` float64 final weight of every edge of the graph (1 for odometry
            and for edges outside the solved set; 0..1 for loops under a robust mode).
        rejected_loops: edge indices of loops whose final weight is below 0.5.
    """

    iterations: int = 0
    cost_initial: float = 0.0
    cost_final: float = 0.0
    converged: bool = True
    n_variables: int = 0
    n_factors: int = 0
    time_s: float = 0.0
    loop_weights: torch.Tensor = field(default_factory=lambda: torch.zeros(0, dtype=torch.float64))
    rejected_loops: list[int] = field(default_factory=list)


class _Problem:
    """The factors touching a set of variable rows, with a fixed block-sparse pattern.

    ``var_rows`` ``(n,)`` are graph rows being optimised; all other poses stay fixed. The
    normal matrix is ``6n x 6n`` with one 6x6 block per slot; the slots and the Cholesky
    ordering (on the poses' translations at construction) are built once here.
    ``check_anchored`` False skips the gauge check, for a problem that is only linearised.
    """

    def __init__(self, graph: PoseGraph, var_rows: torch.Tensor, check_anchored: bool = True) -> None:
        n_all = graph.num_nodes
        self.var_rows = var_rows
        self.n = n = var_rows.numel()
        local = torch.full((n_all,), -1, dtype=torch.int64)
        local[var_rows] = torch.arange(n)
        e = graph.edges
        li, lj = local[e.i], local[e.j]
        keep = (li >= 0) | (lj >= 0)
        self.edge_idx = torch.nonzero(keep).flatten()
        self.ei, self.ej = e.i[keep], e.j[keep]
        self.li, self.lj = li[keep], lj[keep]
        self.Z = e.Z[keep]
        self.sigma = e.sigma[keep]
        self.loop = e.loop[keep]
        pr = graph.priors
        pkeep = local[pr.rows] >= 0
        self.prow, self.plocal = pr.rows[pkeep], local[pr.rows[pkeep]]
        self.pZ, self.psigma = pr.Z[pkeep], pr.sigma[pkeep]
        if check_anchored:
            self._check_anchored()
        self._build_pattern(graph.poses()[var_rows, :3, 3].numpy())

    def _check_anchored(self) -> None:
        """Every connected group of variables must contain a prior or touch a fixed pose."""
        n = self.n
        both = (self.li >= 0) & (self.lj >= 0)
        a, b = self.li[both].numpy(), self.lj[both].numpy()
        adj = sp.coo_matrix((np.ones(a.size), (a, b)), shape=(n, n))
        ncomp, label = csgraph.connected_components(adj, directed=False)
        anchored = np.zeros(ncomp, dtype=bool)
        anchored[label[self.plocal.numpy()]] = True
        one_fixed = ~both
        ends = torch.where(self.li[one_fixed] >= 0, self.li[one_fixed], self.lj[one_fixed]).numpy()
        anchored[label[ends]] = True
        if not anchored.all():
            k = int(np.nonzero(~anchored)[0][0])
            members = self.var_rows[torch.from_numpy(np.nonzero(label == k)[0][:5])]
            raise SolverError(f"a connected group of {int((label == k).sum())} poses has no prior "
                              f"(gauge undefined); it contains rows {members.tolist()}")

    def _build_pattern(self, coords: np.ndarray) -> None:
        n = self.n
        both = (self.li >= 0) & (self.lj >= 0)
        diag_keys = torch.arange(n) * (n + 1)
        off = torch.cat([self.li[both] * n + self.lj[both], self.lj[both] * n + self.li[both]])
        keys, inv = torch.unique(torch.cat([diag_keys, off]), return_inverse=True)
        self.n_blocks = keys.numel()
        self.slot_diag = inv[:n]
        m = int(both.sum())
        # where each edge's four 6x6 blocks (ii, ij, ji, jj) and two gradient rows (i, j) go in
        # every linearisation; a block or row with a fixed end goes to a spare slot / row
        E = self.li.numel()
        spare = torch.full((E,), self.n_blocks, dtype=torch.int64)
        ij, ji = spare.clone(), spare.clone()
        ij[both], ji[both] = inv[n:n + m], inv[n + m:]
        ii = torch.where(self.li >= 0, self.slot_diag[self.li.clamp(min=0)], spare)
        jj = torch.where(self.lj >= 0, self.slot_diag[self.lj.clamp(min=0)], spare)
        self.edge_slots = torch.stack([ii, ij, ji, jj], 1).reshape(-1)
        self.edge_rows = torch.stack([torch.where(self.li >= 0, self.li, n), torch.where(self.lj >= 0, self.lj, n)],
                                     1).reshape(-1)
        self.slot_p = self.slot_diag[self.plocal]
        self._keys, self._coords = keys, coords
        self._chol: BlockCholesky | None = None

    @property
    def chol(self) -> BlockCholesky:
        """The symbolic factorisation, built on first use."""
        if self._chol is None:
            n = self.n
            self._chol = BlockCholesky(n, (self._keys // n).numpy(), (self._keys % n).numpy(), self._coords)
        return self._chol

    # -------------------------------------------------------------- evaluation
    def residuals(self, X: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """Squared whitened norms of the edges ``(E',)`` and priors ``(P',)`` at poses ``X``
        ``(N, 4, 4)``, and the edges' errors ``(E', 6)`` (for :meth:`linearize` at the same ``X``)."""
        err = se3.between_error(self.Z, X[self.ei], X[self.ej])
        e = err / self.sigma
        if not self.prow.numel():
            return (e * e).sum(-1), e.new_zeros(0), err
        p = se3.log(se3.inverse(self.pZ) @ X[self.prow]) / self.psigma
        return (e * e).sum(-1), (p * p).sum(-1), err

    def linearize(self, X: torch.Tensor, w: torch.Tensor, err: torch.Tensor | None = None
                  ) -> tuple[np.ndarray, np.ndarray]:
        """Blocks ``(S, 6, 6)`` of ``J^T W J`` and the gradient ``J^T W e`` ``(6n,)`` at ``X``.

        ``w`` ``(E',)`` are per-edge weights (IRLS or GNC); priors have weight 1. ``err``: the
        edges' errors at ``X`` if already known (:meth:`residuals`).
        """
        e, Ji, Jj = se3.between_jacobians(self.Z, X[self.ei], X[self.ej], err)
        f = w.sqrt()[:, None] / self.sigma  # (E', 6): whitening and weight of each error row
        e = e * f
        J = torch.cat([Ji, Jj], dim=2) * f[:, :, None]  # (E', 6, 12)
        JT = J.transpose(1, 2)
        m = e.shape[0]
        H = (JT @ J).reshape(m, 2, 6, 2, 6).transpose(2, 3).reshape(4 * m, 6, 6)  # ii, ij, ji, jj
        blocks = torch.zeros(self.n_blocks + 1, 6, 6, dtype=torch.float64)  # + the spare slot
        blocks.index_add_(0, self.edge_slots, H)
        g = torch.zeros(self.n + 1, 6, dtype=torch.float64)  # + the spare row
        g.index_add_(0, self.edge_rows, (JT @ e[:, :, None]).reshape(2 * m, 6))
        if self.prow.numel():
            ep, Jp = se3.prior_jacobian(self.pZ, X[self.prow])
            ep, Jp = ep / self.psigma, Jp / self.psigma[:, :, None]
            JpT = Jp.transpose(1, 2)
            blocks.index_add_(0, self.slot_p, JpT @ Jp)
            g.index_add_(0, self.plocal, (JpT @ ep[:, :, None]).squeeze(-1))
        return blocks[:-1].numpy(), g[:-1].numpy().reshape(-1)

    def step(self, blocks: np.ndarray, g: np.ndarray, lam: float) -> torch.Tensor | None:
        """Solve ``(H + lam I) delta = -g``; ``delta`` ``(n, 6)``, or None if not positive definite."""
        damped = blocks.copy()
        damped[self.slot_diag.numpy()] += lam * np.eye(6)
        try:
            self.chol.factor(damped)
        except FactorError:
            return None
        return torch.from_numpy(self.chol.solve(-g)).reshape(self.n, 6)

    def retract(self, X: torch.Tensor, delta: torch.Tensor) -> torch.Tensor:
        Y = X.clone()
        Y[self.var_rows] = se3.retract(X[self.var_rows], delta)
        return Y


def _weights_and_cost(prob: _Problem, X: torch.Tensor, kernel: str, k2: float,
                      fixed_w: torch.Tensor | None) -> tuple[torch.Tensor, float, torch.Tensor]:
    """Per-edge weights ``(E',)`` for linearisation, the total cost at ``X`` and the edges'
    errors ``(E', 6)`` there."""
    s_e, s_p, err = prob.residuals(X)
    if fixed_w is not None:
        return fixed_w, 0.5 * float((fixed_w * s_e).sum() + s_p.sum()), err
    rho = torch.where(prob.loop, robust.kernel_cost(kernel, s_e, k2), s_e)
    w = torch.where(prob.loop, robust.kernel_weight(kernel, s_e, k2), torch.ones_like(s_e))
    return w, 0.5 * float(rho.sum() + s_p.sum()), err


def _levenberg_marquardt(prob: _Problem, X: torch.Tensor, config: PoseGraphConfig, kernel: str,
                         fixed_w: torch.Tensor | None, max_iters: int
                         ) -> tuple[torch.Tensor, int, float, float, bool]:
    """GTSAM-style LM; returns (poses, accepted steps, initial cost, final cost, converged).

    Converged: an accepted step lowered the cost by no more than the tolerances, or a rejected
    step raised it by no more than them while the quadratic model predicted no larger decrease
    (a minimum: nothing lowers the cost measurably). Not converged: lambda passed its bound.
    """
    k2 = config.robust_chi2
    w, cost, err = _weights_and_cost(prob, X, kernel, k2, fixed_w)
    cost0 = cost
    lam = config.lambda_init
    it = 0
    converged = cost <= 0.0
    while it < max_iters and not converged:
        data, g = prob.linearize(X, w, err)
        while True:
            delta = prob.step(data, g, lam)
            if delta is not None:
                X_new = prob.retract(X, delta)
                w_new, cost_new, err_new = _weights_and_cost(prob, X_new, kernel, k2, fixed_w)
                if np.isfinite(cost_new) and cost_new <= cost:
                    break
                if (np.isfinite(cost_new) and _negligible(cost_new - cost, cost, config)
                        and _negligible(_predicted_decrease(g, delta, lam), cost, config)):
                    return X, it, cost0, cost, True  # at a minimum: no step lowers the cost measurably
            lam *= config.lambda_factor
            if lam > config.lambda_max:
                return X, it, cost0, cost, False
        it += 1
        decrease = cost - cost_new
        X, w, cost, err = X_new, w_new, cost_new, err_new
        lam = max(lam / config.lambda_factor, 1e-300)
        converged = _negligible(decrease, cost + decrease, config) or cost <= 0
    return X, it, cost0, cost, converged


def _negligible(change: float, cost: float, config: PoseGraphConfig) -> bool:
    """Whether a cost change is within LM's tolerances: at most ``abs_tol`` or ``rel_tol * cost``."""
    return change <= config.abs_tol or change <= config.rel_tol * cost


def _predicted_decrease(g: np.ndarray, delta: torch.Tensor, lam: float) -> float:
    """The cost decrease ``-(g.d + 0.5 d^T H d)`` that the quadratic model promises for the step
    ``d`` ``(n, 6)`` solving ``(H + lam I) d = -g`` (``g`` ``(6n,)``): ``0.5 (-g.d + lam |d|^2)``."""
    d = delta.numpy().reshape(-1)
    return 0.5 * (-float(g @ d) + lam * float(d @ d))


@contextmanager
def solver_context() -> Iterator[None]:
    """Run torch on one intra-op thread and under ``torch.inference_mode`` inside the block,
    then restore the thread setting.

    The solver's tensors are small (6x6 blocks, thousands of edges): OpenMP parallel regions
    only add synchronisation, and on a busy machine a descheduled worker stalls each one (a
    60-keyframe incremental replay took 108 s with 2 threads and 3 s with 1 under load); and
    autograd's bookkeeping on each of its many small operations is pure overhead (the solve
    is not differentiated). Poses written into the graph stay ordinary tensors.
    """
    n = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        with torch.inference_mode():
            yield
    finally:
        torch.set_num_threads(n)


def solve(graph: PoseGraph, config: PoseGraphConfig | None = None,
          rows: torch.Tensor | None = None, max_iters: int | None = None) -> SolveReport:
    """Optimise the poses of ``graph`` in place and report what happened.

    Args:
        graph: the pose graph; its current poses are the initial values (warm start).
        config: solver settings and robust mode; defaults to :class:`PoseGraphConfig`.
        rows: ``(n,)`` graph rows to optimise (e.g. one connected group), integers in
            ``0..N-1`` (:meth:`PoseGraph.check_rows`); all other poses are held fixed. ``None``
            optimises every node.
        max_iters: cap on accepted LM steps per stage (``config.max_iters`` if None).

    Raises :class:`SolverError` when a connected group of variables has no prior and no fixed
    neighbour, and :class:`GraphError` for an unknown robust mode or a row outside the graph.
    """
    with solver_context():
        report = _solve(graph, config, rows, max_iters)
    report.loop_weights = report.loop_weights.clone()  # an ordinary tensor, like every pose of the graph
    return report


def _solve(graph: PoseGraph, config: PoseGraphConfig | None, rows: torch.Tensor | None,
           max_iters: int | None) -> SolveReport:
    t0 = time.perf_counter()
    config = config or PoseGraphConfig()
    if config.robust not in ROBUST_MODES:
        raise GraphError(f"robust mode must be one of {ROBUST_MODES}, got {config.robust!r}")
    max_iters = config.max_iters if max_iters is None else max_iters
    report = SolveReport(loop_weights=torch.ones(graph.num_edges, dtype=torch.float64))
    if graph.num_nodes == 0:
        return report
    rows = torch.arange(graph.num_nodes) if rows is None else graph.check_rows(rows)
    if rows.numel() == 0:
        return report
    prob = _Problem(graph, torch.unique(rows))
    report.n_variables, report.n_factors = prob.n, prob.edge_idx.numel() + prob.prow.numel()
    X = graph.poses()

    if config.robust == "gnc":
        X, w, its, c0, c1, conv = _gnc(prob, X, config, max_iters)
    else:
        X, its, c0, c1, conv = _levenberg_marquardt(prob, X, config, config.robust, None, max_iters)
        w, _, _ = _weights_and_cost(prob, X, config.robust, config.robust_chi2, None)
    graph.set_poses(prob.var_rows, X[prob.var_rows])
    report.iterations, report.cost_initial, report.cost_final, report.converged = its, c0, c1, conv
    report.loop_weights[prob.edge_idx] = w
    report.rejected_loops = prob.edge_idx[prob.loop & (w < 0.5)].tolist()
    report.time_s = time.perf_counter() - t0
    return report


def _gnc(prob: _Problem, X: torch.Tensor, config: PoseGraphConfig, max_iters: int
         ) -> tuple[torch.Tensor, torch.Tensor, int, float, float, bool]:
    """Graduated non-convexity with TLS on loop factors (odometry and priors are inliers).

    Starts from the least-squares solution, then alternates closed-form weight updates with
    weighted LM, growing ``mu`` by ``config.gnc_mu_step`` until the weights are binary.
    """
    c2 = config.robust_chi2
    X, its, c0, _, conv = _levenberg_marquardt(prob, X, config, "none", None, max_iters)
    s_e, _, _ = prob.residuals(X)
    mu = robust.gnc_initial_mu(s_e[prob.loop], c2)
    w = torch.ones_like(s_e)
    for _ in range(config.gnc_max_iters):
        w = torch.where(prob.loop, robust.gnc_tls_weights(s_e, mu, c2), torch.ones_like(s_e))
        X, k, _, _, conv = _levenberg_marquardt(prob, X, config, "none", w, max_iters)
        its += k
        s_e, _, _ = prob.residuals(X)
        lw = w[prob.loop]
        if mu == float("inf") or bool(((lw < 1e-3) | (lw > 1 - 1e-3)).all()):
            break
        mu *= config.gnc_mu_step
    w = torch.where(prob.loop, (w >= 0.5).to(w.dtype), w)
    X, k, _, cost, conv = _levenberg_marquardt(prob, X, config, "none", w, max_iters)
    return X, w, its + k, c0, cost, conv
