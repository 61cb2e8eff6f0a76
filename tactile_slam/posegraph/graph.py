"""The pose graph: keyframe poses, prior and between factors, g2o I/O (method.md section 7.1).

Nodes are keyframe ids mapped to ``start_T_kf`` (``(4, 4)`` float64, metres): the keyframe's
pose in its group's "start" frame. Factors:

* **prior** on node ``k``: ``start_T_k`` should equal ``Z``;
* **between** ``(i, j)``: ``i_T_j`` should equal ``Z``; the error is
  ``Log(Z^-1 . start_T_i^-1 . start_T_j)``.

Every factor carries a diagonal noise ``sigma`` ``(6,)`` in the tangent order of
:mod:`tactile_slam.posegraph.se3`, **[translation (m) x3, rotation (rad) x3]**. Edge data live in
growable float64/int64 tensors so that the solver linearises every factor in one batch.
"""

from __future__ import annotations

from collections.abc import Iterable, Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from tactile_slam.config import PoseGraphConfig
from tactile_slam.posegraph import se3

EDGE_KINDS = ("odometry", "loop")
_LOOP_MARKER = "# tactile-slam: EDGE_SE3:QUAT lines below are loop closures"
_PRIOR_PARAM = 0  # the id of the identity PARAMS_SE3OFFSET that the written priors refer to
_SIGMA_MIN = float(torch.finfo(torch.float64).max) ** -0.5  # smallest sigma whose sigma^-2 is finite
_SIGMA_MAX = float(torch.finfo(torch.float64).tiny) ** -0.5  # largest whose sigma^-2 is a normal float


class GraphError(ValueError):
    """The pose graph is inconsistent (unknown node, duplicate node, bad sigma, bad file)."""


@dataclass
class EdgeArrays:
    """Between factors as batched tensors (views, do not modify).

    Attributes:
        i, j: ``(E,)`` int64 node *rows* (not ids) of the two ends.
        Z: ``(E, 4, 4)`` float64, measured ``i_T_j``.
        sigma: ``(E, 6)`` float64 noise, [translation m x3, rotation rad x3].
        loop: ``(E,)`` bool, True for loop closures, False for odometry.
    """

    i: torch.Tensor
    j: torch.Tensor
    Z: torch.Tensor
    sigma: torch.Tensor
    loop: torch.Tensor


@dataclass
class PriorArrays:
    """Prior factors as batched tensors: rows ``(P,)``, ``Z`` ``(P, 4, 4)``, ``sigma`` ``(P, 6)``."""

    rows: torch.Tensor
    Z: torch.Tensor
    sigma: torch.Tensor


class _Rows:
    """A growable tensor with amortised O(1) appends along dim 0."""

    def __init__(self, width: int | None, dtype: torch.dtype) -> None:
        shape = (16,) if width is None else (16, width)
        self.data = torch.zeros(shape, dtype=dtype)
        self.n = 0

    def extend(self, rows: torch.Tensor) -> None:
        k = rows.shape[0]
        if self.n + k > self.data.shape[0]:
            cap = max(2 * self.data.shape[0], self.n + k)
            grown = torch.zeros((cap,) + self.data.shape[1:], dtype=self.data.dtype)
            grown[: self.n] = self.data[: self.n]
            self.data = grown
        self.data[self.n: self.n + k] = rows
        self.n += k

    def view(self) -> torch.Tensor:
        return self.data[: self.n]


def sigma_vector(sigma: Sequence[float] | torch.Tensor | None, default: torch.Tensor) -> torch.Tensor:
    """Noise ``(6,)`` float64 from ``None`` (the default), 2 values (rot rad, trans m) or 6 values.

    Six values are [translation m x3, rotation rad x3]; two values are (rotation, translation)
    as in :class:`PoseGraphConfig`. Raises :class:`GraphError` unless all are finite and > 0
    and their information ``sigma^-2`` is a finite, normal float64 (sigma within about
    7.5e-155 .. 6.7e153), so that the solver's cost and the g2o export stay finite.
    """
    if sigma is None:
        return default.clone()
    s = torch.as_tensor(sigma, dtype=torch.float64).flatten()
    if s.numel() == 2:
        s = torch.cat([s[1].repeat(3), s[0].repeat(3)])
    if s.numel() != 6:
        raise GraphError(f"sigma must have 2 or 6 values, got {s.numel()}")
    if not (torch.isfinite(s).all() and (s > 0).all()):
        raise GraphError(f"sigma must be finite and > 0, got {s.tolist()}")
    info = s ** -2
    if not (torch.isfinite(info).all() and (info >= torch.finfo(torch.float64).tiny).all()):
        raise GraphError(f"sigma must lie within about {_SIGMA_MIN:.1e} .. {_SIGMA_MAX:.1e}, so that its "
                         f"information sigma^-2 is a finite, normal float64; got {s.tolist()}")
    return s


class PoseGraph:
    """Keyframe poses and their factors.

    Args:
        config: default noise (``sigma_rot_rad``, ``sigma_trans_m``) for factors added
            without an explicit ``sigma``.
    """

    def __init__(self, config: PoseGraphConfig | None = None) -> None:
        config = config or PoseGraphConfig()
        self.default_sigma = sigma_vector((config.sigma_rot_rad, config.sigma_trans_m), torch.ones(6))
        self._row: dict[int, int] = {}
        self._ids = _Rows(None, torch.int64)
        self._poses = _Rows(16, torch.float64)
        self._ei = _Rows(None, torch.int64)
        self._ej = _Rows(None, torch.int64)
        self._eZ = _Rows(16, torch.float64)
        self._esigma = _Rows(6, torch.float64)
        self._eloop = _Rows(None, torch.bool)
        self._priors: dict[int, tuple[torch.Tensor, torch.Tensor]] = {}

    # ------------------------------------------------------------------ nodes
    @property
    def num_nodes(self) -> int:
        return self._ids.n

    @property
    def num_edges(self) -> int:
        return self._ei.n

    @property
    def ids(self) -> torch.Tensor:
        """``(N,)`` int64 node ids in row order."""
        return self._ids.view()

    def __contains__(self, node_id: int) -> bool:
        return int(node_id) in self._row

    def rows(self, node_ids: Iterable[int] | int) -> torch.Tensor:
        """Rows ``(K,)`` int64 of node ids; :class:`GraphError` names any unknown id."""
        ids = [node_ids] if isinstance(node_ids, (int, np.integer)) else list(node_ids)
        try:
            return torch.tensor([self._row[int(k)] for k in ids], dtype=torch.int64)
        except KeyError as exc:
            raise GraphError(f"node {exc.args[0]} is not in the pose graph") from None

    def add_node(self, node_id: int, start_T_kf: torch.Tensor | None = None) -> None:
        """Add keyframe ``node_id`` with initial value ``start_T_kf`` ``(4, 4)`` (identity if None)."""
        T = torch.eye(4, dtype=torch.float64) if start_T_kf is None else torch.as_tensor(start_T_kf)
        if T.shape != (4, 4):
            raise GraphError(f"start_T_kf must be (4, 4), got {tuple(T.shape)}")
        self.add_nodes([node_id], T[None])

    def add_nodes(self, node_ids: Sequence[int], start_T_kf: torch.Tensor) -> None:
        """Add keyframes ``node_ids`` ``(K,)`` with initial values ``start_T_kf`` ``(K, 4, 4)``."""
        node_ids = [int(k) for k in node_ids]
        X = se3.check_pose(start_T_kf)
        if X.shape != (len(node_ids), 4, 4):
            raise GraphError(f"start_T_kf must be ({len(node_ids)}, 4, 4), got {tuple(start_T_kf.shape)}")
        if len(set(node_ids)) != len(node_ids) or any(k in self._row for k in node_ids):
            dup = next(k for n, k in enumerate(node_ids) if k in self._row or k in node_ids[:n])
            raise GraphError(f"node {dup} is already in the pose graph")
        for k in node_ids:
            self._row[k] = len(self._row)
        self._ids.extend(torch.tensor(node_ids, dtype=torch.int64))
        self._poses.extend(X.reshape(-1, 16))

    def pose(self, node_id: int) -> torch.Tensor:
        """Current ``start_T_kf`` ``(4, 4)`` float64 of one node."""
        return self._poses.data[self.rows(node_id)[0]].reshape(4, 4).clone()

    def poses(self, node_ids: Iterable[int] | None = None) -> torch.Tensor:
        """Current ``start_T_kf`` ``(K, 4, 4)`` float64 of ``node_ids`` (all nodes if None)."""
        P = self._poses.view() if node_ids is None else self._poses.view()[self.rows(node_ids)]
        return P.reshape(-1, 4, 4).clone()

    def check_rows(self, rows: Sequence[int] | torch.Tensor) -> torch.Tensor:
        """Graph rows ``(K,)`` as int64; :class:`GraphError` unless they are integers in ``0..N-1``.

        Rows are positions in :attr:`ids`, not node ids; a negative row is refused rather than
        read from the end.
        """
        r = torch.as_tensor(rows)
        if r.ndim != 1 or (r.numel() and (r.dtype == torch.bool or r.is_floating_point() or r.is_complex())):
            raise GraphError(f"rows must be a 1-D sequence of integers, got {r.dtype} of shape {tuple(r.shape)}")
        r = r.to(torch.int64)
        bad = r[(r < 0) | (r >= self.num_nodes)]
        if bad.numel():
            raise GraphError(f"rows {bad[:5].tolist()} are outside the graph's rows 0..{self.num_nodes - 1}")
        return r

    def set_poses(self, rows: Sequence[int] | torch.Tensor, start_T_kf: torch.Tensor) -> None:
        """Overwrite the poses at ``rows`` ``(K,)`` (graph rows, not ids) with ``(K, 4, 4)``.

        The rows go through :meth:`check_rows` and the poses through :func:`se3.check_pose`
        (finite, rigid), as for :meth:`add_nodes`.
        """
        r = self.check_rows(rows)
        X = se3.check_pose(start_T_kf)
        if X.shape != (r.numel(), 4, 4):
            raise GraphError(f"start_T_kf must be ({r.numel()}, 4, 4), got {tuple(X.shape)}")
        self._poses.data[r] = X.reshape(-1, 16)

    # ------------------------------------------------------------------ factors
    def add_prior(self, node_id: int, start_T_kf: torch.Tensor | None = None,
                  sigma: Sequence[float] | torch.Tensor | None = None) -> None:
        """Anchor ``node_id`` at ``start_T_kf`` ``(4, 4)`` (identity if None); replaces an old prior."""
        row = int(self.rows(node_id)[0])
        T = torch.eye(4, dtype=torch.float64) if start_T_kf is None else start_T_kf
        self._priors[row] = (se3.check_pose(T).reshape(4, 4), sigma_vector(sigma, self.default_sigma))

    def remove_prior(self, node_id: int) -> None:
        """Drop the prior on ``node_id``; :class:`GraphError` if it has none."""
        row = int(self.rows(node_id)[0])
        if row not in self._priors:
            raise GraphError(f"node {node_id} has no prior to remove")
        del self._priors[row]

    def has_prior(self, node_id: int) -> bool:
        return int(self.rows(node_id)[0]) in self._priors

    def add_between(self, i: int, j: int, i_T_j: torch.Tensor,
                    sigma: Sequence[float] | torch.Tensor | None = None, kind: str = "odometry") -> int:
        """Add the factor ``start_T_i^-1 . start_T_j = i_T_j`` ``(4, 4)``; returns the edge index.

        ``kind`` is ``"odometry"`` (a known inlier) or ``"loop"`` (may be down-weighted by the
        robust modes of the solver).
        """
        Z = torch.as_tensor(i_T_j)
        if Z.shape != (4, 4):
            raise GraphError(f"i_T_j must be (4, 4), got {tuple(Z.shape)}")
        return self.add_betweens([i], [j], Z[None], sigma, kind)[0]

    def add_betweens(self, i: Sequence[int], j: Sequence[int], i_T_j: torch.Tensor,
                     sigma: Sequence[float] | torch.Tensor | None = None, kind: str = "odometry") -> list[int]:
        """Batched :meth:`add_between`: ids ``(E,)``, ``i_T_j`` ``(E, 4, 4)``, one sigma and kind."""
        if kind not in EDGE_KINDS:
            raise GraphError(f"edge kind must be one of {EDGE_KINDS}, got {kind!r}")
        ri, rj = self.rows(i), self.rows(j)
        if ri.shape != rj.shape:
            raise GraphError(f"got {ri.numel()} start nodes and {rj.numel()} end nodes")
        if (ri == rj).any():
            raise GraphError(f"between factor from node {int(self.ids[ri[ri == rj][0]])} to itself")
        Z = se3.check_pose(i_T_j)
        if Z.shape != (ri.numel(), 4, 4):
            raise GraphError(f"i_T_j must be ({ri.numel()}, 4, 4), got {tuple(torch.as_tensor(i_T_j).shape)}")
        first = self._ei.n
        self._ei.extend(ri)
        self._ej.extend(rj)
        self._eZ.extend(Z.reshape(-1, 16))
        self._esigma.extend(sigma_vector(sigma, self.default_sigma).expand(ri.numel(), 6))
        self._eloop.extend(torch.full((ri.numel(),), kind == "loop"))
        return list(range(first, self._ei.n))

    @property
    def edges(self) -> EdgeArrays:
        return EdgeArrays(self._ei.view(), self._ej.view(), self._eZ.view().reshape(-1, 4, 4),
                          self._esigma.view(), self._eloop.view())

    @property
    def priors(self) -> PriorArrays:
        rows = sorted(self._priors)
        if not rows:
            return PriorArrays(torch.zeros(0, dtype=torch.int64), torch.zeros(0, 4, 4, dtype=torch.float64),
                               torch.zeros(0, 6, dtype=torch.float64))
        Z = torch.stack([self._priors[r][0] for r in rows])
        sigma = torch.stack([self._priors[r][1] for r in rows])
        return PriorArrays(torch.tensor(rows, dtype=torch.int64), Z, sigma)

    # ------------------------------------------------------------------ g2o
    def to_g2o(self, path: str | Path) -> Path:
        """Write the graph as a g2o file (metres) that g2o itself loads.

        Lines: ``PARAMS_SE3OFFSET 0 0 0 0 0 0 0 1`` (the identity sensor offset that g2o's
        prior refers to), ``VERTEX_SE3:QUAT id x y z qx qy qz qw``,
        ``EDGE_SE3_PRIOR id 0 x y z qx qy qz qw info(21)`` and
        ``EDGE_SE3:QUAT i j x y z qx qy qz qw info(21)``. Information matrices are
        ``diag(sigma^-2)`` over the [translation, rotation] tangent, written as the 21
        upper-triangular entries row by row (GTSAM's reading of g2o); they are finite, since
        :func:`sigma_vector` bounds every sigma. Loop closures follow a marker comment so that
        :meth:`from_g2o` restores their kind.
        """
        path = Path(path)
        lines = ["PARAMS_SE3OFFSET %d %s" % (_PRIOR_PARAM, _fmt([0.0] * 6 + [1.0]))]
        ids = self.ids.tolist()
        for k, x in zip(ids, _quat_rows(self.poses())):
            lines.append("VERTEX_SE3:QUAT %d %s" % (k, _fmt(x)))
        pr = self.priors
        for r, z, s in zip(pr.rows.tolist(), _quat_rows(pr.Z), pr.sigma):
            lines.append("EDGE_SE3_PRIOR %d %d %s %s" % (ids[r], _PRIOR_PARAM, _fmt(z), _fmt(_info_upper(s))))
        e = self.edges
        for want_loop in (False, True):
            if want_loop and bool(e.loop.any()):
                lines.append(_LOOP_MARKER)
            sel = torch.nonzero(e.loop == want_loop).flatten()
            for n, z in zip(sel.tolist(), _quat_rows(e.Z[sel])):
                lines.append("EDGE_SE3:QUAT %d %d %s %s" % (
                    ids[int(e.i[n])], ids[int(e.j[n])], _fmt(z), _fmt(_info_upper(e.sigma[n]))))
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text("\n".join(lines) + "\n")
        return path

    @classmethod
    def from_g2o(cls, path: str | Path, config: PoseGraphConfig | None = None) -> "PoseGraph":
        """Read a g2o SE3:QUAT file: one written by :meth:`to_g2o` (also by its earlier versions,
        whose ``EDGE_SE3_PRIOR`` has no parameter id) or by g2o.

        Records (``#`` lines are comments):

        * ``VERTEX_SE3:QUAT id x y z qx qy qz qw`` (the quaternion is normalised);
        * ``EDGE_SE3:QUAT i j x y z qx qy qz qw info(21)``;
        * ``EDGE_SE3_PRIOR id param x y z qx qy qz qw info(21)``, ``param`` defined by an
          earlier ``PARAMS_SE3OFFSET``, or ``EDGE_SE3_PRIOR id x y z qx qy qz qw info(21)``;
        * ``PARAMS_SE3OFFSET param x y z qx qy qz qw``: only the identity offset (a prior
          through another offset would need a full information matrix);
        * ``FIX id ...``: each node named (already read) gets a prior at its value with the
          default sigma, which replaces any ``EDGE_SE3_PRIOR`` of its own.

        An information matrix must be finite and positive definite; its off-diagonal entries are
        then dropped (noise is diagonal here: ``sigma = diag(info)^-1/2``). Without the loop
        marker, an edge is odometry when its ids are consecutive and a loop otherwise.
        :class:`GraphError` names the file and line of any bad record.
        """
        path = Path(path)
        if not path.is_file():
            raise GraphError(f"g2o file not found: {path}")
        g = cls(config)
        lines = [raw.strip() for raw in path.read_text().splitlines()]
        any_marker = _LOOP_MARKER in lines
        after_marker = False
        params: set[int] = set()
        fixed: set[int] = set()
        for n, line in enumerate(lines, 1):
            after_marker |= line == _LOOP_MARKER
            if not line or line.startswith("#"):
                continue
            try:
                g._read_g2o_record(line.split(), params, fixed, after_marker if any_marker else None)
            except (ValueError, IndexError) as exc:
                raise GraphError(f"{path}:{n}: {exc}") from None
        for k in fixed:
            g.add_prior(k, g.pose(k))
        return g

    def _read_g2o_record(self, tok: list[str], params: set[int], fixed: set[int], loop: bool | None) -> None:
        """Apply one g2o record (its tokens) to the graph (:meth:`from_g2o`).

        ``params``: the ids of the identity offsets read so far (grows); ``fixed``: the node ids
        of ``FIX`` records (grows); ``loop``: whether an edge here is a loop closure (None:
        decided by consecutive ids). Raises ``ValueError`` (often :class:`GraphError`).
        """
        kind, n = tok[0], len(tok)
        if kind == "VERTEX_SE3:QUAT" and n == 9:
            self.add_node(int(tok[1]), _matrix(tok[2:9]))
        elif kind == "EDGE_SE3:QUAT" and n == 31:
            i, j = int(tok[1]), int(tok[2])
            is_loop = abs(j - i) != 1 if loop is None else loop
            self.add_between(i, j, _matrix(tok[3:10]), _sigma_from_info(tok[10:31]),
                             kind="loop" if is_loop else "odometry")
        elif kind == "EDGE_SE3_PRIOR" and n in (30, 31):
            if n == 31 and int(tok[2]) not in params:
                raise GraphError(f"EDGE_SE3_PRIOR refers to parameter {tok[2]}, which no earlier "
                                 "PARAMS_SE3OFFSET defines")
            first = n - 28  # the pose: after the node id and, in g2o's form, the parameter id
            self.add_prior(int(tok[1]), _matrix(tok[first:first + 7]), _sigma_from_info(tok[first + 7:]))
        elif kind == "PARAMS_SE3OFFSET" and n == 9:
            pid = int(tok[1])
            if pid in params:
                raise GraphError(f"parameter {pid} is already defined")
            if not torch.allclose(_matrix(tok[2:9]), torch.eye(4, dtype=torch.float64), rtol=0.0, atol=1e-12):
                raise GraphError(f"PARAMS_SE3OFFSET {pid} is not the identity; only identity offsets are "
                                 "supported (a prior through another offset needs a full information matrix)")
            params.add(pid)
        elif kind == "FIX" and n >= 2:
            ids = [int(t) for t in tok[1:]]
            self.rows(ids)  # each must already be a node, as in g2o
            fixed.update(ids)
        else:
            raise GraphError(f"unsupported or malformed record {kind!r} ({n} tokens)")


_UPPER = torch.triu_indices(6, 6)  # (2, 21): g2o's upper triangle, row by row


def _quat_rows(T: torch.Tensor) -> list[list[float]]:
    """``[x, y, z, qx, qy, qz, qw]`` rows of poses ``(K, 4, 4)``."""
    return torch.cat([T[:, :3, 3], se3.rotmat_to_quat(T[:, :3, :3])], dim=1).tolist()


def _fmt(values: Iterable[float]) -> str:
    return " ".join(repr(float(v)) for v in values)


def _info_upper(sigma: torch.Tensor) -> list[float]:
    """The 21 upper-triangular entries (row by row) of the information ``diag(sigma^-2)``, sigma ``(6,)``."""
    return torch.diag(sigma.double() ** -2)[_UPPER[0], _UPPER[1]].tolist()


def _sigma_from_info(tokens: Sequence[str]) -> torch.Tensor:
    """Noise ``(6,)`` ``diag(info)^-1/2`` of a g2o information matrix given as its 21
    upper-triangular entries row by row; the off-diagonal entries are dropped.

    Raises :class:`GraphError` unless the matrix is finite and positive definite (a matrix
    with a positive diagonal can still be indefinite).
    """
    upper = torch.tensor([float(t) for t in tokens], dtype=torch.float64)
    if not torch.isfinite(upper).all():
        raise GraphError("information matrix has non-finite entries")
    info = torch.zeros(6, 6, dtype=torch.float64)
    info[_UPPER[0], _UPPER[1]] = upper
    info = info + info.triu(1).T
    if torch.linalg.cholesky_ex(info).info != 0:
        raise GraphError("information matrix is not positive definite")
    return info.diagonal().rsqrt()


def _matrix(tokens: Sequence[str]) -> torch.Tensor:
    x = torch.tensor([float(t) for t in tokens], dtype=torch.float64)
    q = x[3:]
    if not torch.isfinite(x).all() or q.norm() < 1e-12:
        raise GraphError("pose must be finite with a non-zero quaternion")
    T = torch.eye(4, dtype=torch.float64)
    T[:3, :3] = se3.quat_to_rotmat(q / q.norm())
    T[:3, 3] = x[:3]
    return T
