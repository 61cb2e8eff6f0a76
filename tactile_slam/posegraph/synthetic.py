"""Synthetic tactile scans with ground truth, for pose-graph tests and benchmarks.

The sensor slides over a sphere (the object) in a smooth random walk, its z-axis pointing
into the surface as in method.md section 1.2; every step makes a keyframe. Loop closures
join keyframes whose sensing centres lie within ``loop_radius_m`` of each other, which gives
the spatially local, surface-like loop structure of a real scan (and of Table V's graphs).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch
from scipy.spatial import cKDTree

from tactile_slam.config import PoseGraphConfig
from tactile_slam.posegraph import se3
from tactile_slam.posegraph.graph import PoseGraph


@dataclass
class SyntheticScan:
    """A pose graph with its ground truth.

    Attributes:
        graph: priors on session heads (identity), odometry within sessions, the loops whose
            ends share a session; initial values chained from the noisy odometry, each session
            starting at identity.
        gt: ``(N, 4, 4)`` float64 true ``start_T_kf`` with start = keyframe 0.
        session: ``(N,)`` int64 session of each keyframe (ids are ``0..N-1``).
        loops: ``(L, 2)`` int64 ``(r, t)`` keyframe pairs of all loops, ``r < t``.
        loop_Z: ``(L, 4, 4)`` float64 measured ``r_T_t`` of all loops; those between sessions
            are not in ``graph`` (merging sessions is the caller's job).
    """

    graph: PoseGraph
    gt: torch.Tensor
    session: torch.Tensor
    loops: torch.Tensor
    loop_Z: torch.Tensor


def _cross(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    return np.array([a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0]])


def sphere_walk(n: int, radius_m: float = 0.02, step_m: float = 1e-3, turn_rad: float = 0.3,
                spin_rad: float = 0.05, seed: int = 0) -> torch.Tensor:
    """``object_T_sensor`` ``(n, 4, 4)`` float64 of a random walk on a sphere, z into the surface.

    ``turn_rad`` is the heading change per step (std) and ``spin_rad`` the in-plane rotation
    per step (std). Positions are the sensing centres on the sphere of ``radius_m``.
    """
    rng = np.random.default_rng(seed)
    p = np.array([0.0, 0.0, -radius_m])
    heading = np.array([1.0, 0.0, 0.0])
    psi = 0.0
    out = np.zeros((n, 4, 4))
    for k in range(n):
        z = -p / np.linalg.norm(p)
        a = np.array([1.0, 0.0, 0.0]) if abs(z[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
        x0 = _cross(a, z)
        x0 /= np.linalg.norm(x0)
        y0 = _cross(z, x0)
        x = np.cos(psi) * x0 + np.sin(psi) * y0
        y = _cross(z, x)
        out[k, :3, :3] = np.stack([x, y, z], axis=1)
        out[k, :3, 3] = p
        out[k, 3, 3] = 1.0
        heading = heading - heading.dot(z) * z
        heading /= np.linalg.norm(heading)
        ang = rng.normal(0.0, turn_rad)
        heading = np.cos(ang) * heading + np.sin(ang) * _cross(z, heading)
        p = p + step_m * heading
        p *= radius_m / np.linalg.norm(p)
        psi += rng.normal(0.0, spin_rad)
    return torch.from_numpy(out)


def _greedy_coverage(centres: np.ndarray, spacing: float) -> np.ndarray:
    """``(N,)`` bool: keyframes farther than ``spacing`` from every earlier coverage keyframe."""
    keep = np.zeros(len(centres), dtype=bool)
    chosen: list[np.ndarray] = []
    for k, c in enumerate(centres):
        if not chosen or np.min(np.linalg.norm(np.asarray(chosen) - c, axis=1)) >= spacing:
            keep[k] = True
            chosen.append(c)
    return keep


def _noisy(T: torch.Tensor, sigma: torch.Tensor, gen: torch.Generator) -> torch.Tensor:
    """``T . Exp(n)``, ``n ~ N(0, diag(sigma^2))`` [translation, rotation]; T ``(K, 4, 4)``."""
    n = torch.randn(T.shape[0], 6, dtype=torch.float64, generator=gen) * sigma
    return T @ se3.exp(n)


def synthetic_scan(n_keyframes: int, n_loops: int, n_sessions: int = 1, seed: int = 0,
                   odometry_sigma: tuple[float, float] = (0.003, 3e-5),
                   loop_sigma: tuple[float, float] = (0.003, 3e-5),
                   loop_radius_m: float = 3e-3, coverage_spacing_m: float = 2e-3, config: PoseGraphConfig | None = None,
                   **walk) -> SyntheticScan:
    """Build a scan of ``n_keyframes`` with ``n_loops`` loops in ``n_sessions`` equal sessions.

    As in GelSLAM, loops run from a keyframe ``t`` to an earlier *coverage* keyframe ``r``
    (``r < t - 1``) within ``loop_radius_m``; coverage keyframes are picked greedily in
    scan order, each at least ``coverage_spacing_m`` from the earlier ones (0 makes every
    keyframe a coverage keyframe). Noise sigmas are (rotation rad, translation m) for the
    simulated measurements; the factors carry the graph's default sigma from ``config``.
    ``walk`` goes to :func:`sphere_walk`. Raises ``ValueError`` if the walk has fewer candidate pairs than ``n_loops``.
    """
    if n_keyframes < 1 or n_sessions < 1 or n_sessions > n_keyframes or n_loops < 0:
        raise ValueError("need n_keyframes >= n_sessions >= 1 and n_loops >= 0")
    obj_T = sphere_walk(n_keyframes, seed=seed, **walk)
    gt = torch.linalg.inv(obj_T[0]) @ obj_T
    gen = torch.Generator().manual_seed(seed + 1)
    odo_s = torch.tensor([odometry_sigma[1]] * 3 + [odometry_sigma[0]] * 3, dtype=torch.float64)
    loop_s = torch.tensor([loop_sigma[1]] * 3 + [loop_sigma[0]] * 3, dtype=torch.float64)

    session = torch.div(torch.arange(n_keyframes) * n_sessions, n_keyframes, rounding_mode="floor")
    heads = torch.ones(n_keyframes, dtype=torch.bool)
    heads[1:] = session[1:] != session[:-1]

    rel = torch.linalg.inv(gt[:-1]) @ gt[1:]
    odo = _noisy(rel, odo_s, gen)

    centres = obj_T[:, :3, 3].numpy()
    coverage = _greedy_coverage(centres, coverage_spacing_m)
    tree = cKDTree(centres)
    pairs = np.sort(tree.query_pairs(loop_radius_m, output_type="ndarray"), axis=1)
    pairs = pairs[(pairs[:, 1] - pairs[:, 0] > 1) & coverage[pairs[:, 0]]]
    if len(pairs) < n_loops:
        raise ValueError(f"the walk has only {len(pairs)} loop candidates, {n_loops} requested")
    rng = np.random.default_rng(seed + 2)
    pick = np.sort(rng.choice(len(pairs), size=n_loops, replace=False))
    loops = torch.from_numpy(pairs[pick]).long()
    loop_Z = _noisy(torch.linalg.inv(gt[loops[:, 0]]) @ gt[loops[:, 1]], loop_s, gen)

    init = torch.empty(n_keyframes, 4, 4, dtype=torch.float64)
    for k in range(n_keyframes):
        init[k] = torch.eye(4, dtype=torch.float64) if heads[k] else init[k - 1] @ odo[k - 1]
    g = PoseGraph(config)
    g.add_nodes(range(n_keyframes), init)
    for k in torch.nonzero(heads).flatten().tolist():
        g.add_prior(k)
    inner = torch.nonzero(~heads[1:]).flatten()
    g.add_betweens(inner.tolist(), (inner + 1).tolist(), odo[inner])
    same = session[loops[:, 0]] == session[loops[:, 1]]
    g.add_betweens(loops[same, 0].tolist(), loops[same, 1].tolist(), loop_Z[same], kind="loop")
    return SyntheticScan(g, gt, session, loops, loop_Z)


@dataclass
class KeyframeStep:
    """What arrives with keyframe ``t`` when a scan is replayed in order.

    Attributes:
        t: keyframe id.
        odometry: ``(4, 4)`` ``(t-1)_T_t``, or None for a session head (which gets a prior).
        loops: ``[(r, r_T_t)]`` loop measurements ending at ``t`` that are in the scan's graph.
    """

    t: int
    odometry: torch.Tensor | None
    loops: list[tuple[int, torch.Tensor]]


def replay_steps(scan: SyntheticScan) -> list[KeyframeStep]:
    """The scan's factors grouped by the keyframe at which they become available."""
    e = scan.graph.edges
    steps = [KeyframeStep(t, None, []) for t in range(scan.graph.num_nodes)]
    for k in range(e.i.numel()):
        i, j = int(e.i[k]), int(e.j[k])
        if bool(e.loop[k]):
            steps[j].loops.append((i, e.Z[k]))
        else:
            steps[j].odometry = e.Z[k]
    return steps


def add_step(graph: PoseGraph, step: KeyframeStep) -> None:
    """Insert one replayed keyframe into ``graph``: a node with its chained initial value
    and its prior (session head) or odometry factor, then the loops ending at it."""
    if step.odometry is None:
        graph.add_node(step.t)
        graph.add_prior(step.t)
    else:
        graph.add_node(step.t, graph.pose(step.t - 1) @ step.odometry)
        graph.add_between(step.t - 1, step.t, step.odometry)
    for r, Z in step.loops:
        graph.add_between(r, step.t, Z, kind="loop")
