"""Sparse block Cholesky for pose-graph normal equations: nested dissection + multifrontal.

The normal matrix of a pose graph is symmetric positive definite with dense ``b x b`` blocks
(``b = 6``) on a node graph. SciPy has no sparse Cholesky and its SuperLU runs on a reference
BLAS, so a 5,000-keyframe scan takes seconds per factorisation. Here instead:

* **ordering** (symbolic, once per sparsity pattern): geometric nested dissection. Nodes are
  split at the median of their coordinates (the pose translations) along the widest axis; the
  nodes of one side that touch the other form the separator, eliminated after both halves.
  Any split gives a valid ordering; geometry only makes separators small. Parts of at most
  ``leaf_size`` nodes become dense leaves.
* **numeric factorisation**: one dense *front* per dissection node, holding its pivots and
  their boundary (the later nodes its subtree touches). Each front is assembled from the
  original blocks plus its children's Schur complements (extend-add), factorised with LAPACK
  (``L11 = chol(F11)``, ``L21 = F21 L11^-T``), and passes ``F22 - L21 L21^T`` to its parent.

Fronts are float64 torch tensors (torch's LAPACK follows ``torch.set_num_threads``, which the
solver pins to one thread); all heavy work is BLAS-3.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch


class FactorError(ValueError):
    """The matrix is not positive definite (e.g. a group of poses without an anchor)."""


@dataclass
class _Front:
    piv: np.ndarray          # pivot nodes, in elimination order
    bnd: np.ndarray          # boundary nodes (later in the order), sorted by position
    children: list[int]
    flat_pos: torch.Tensor   # positions in the flattened front of the assembled block entries
    flat_src: torch.Tensor   # matching positions in the flattened (S, b, b) block array
    child_maps: list[torch.Tensor]  # per child: scalar rows of its boundary inside this front


def _vertex_cover(ea: np.ndarray, eb: np.ndarray, n: int) -> np.ndarray:
    """A small vertex cover of the edges ``(ea, eb)``: greedily take the node of highest degree."""
    alive = np.ones(ea.size, dtype=bool)
    cover = []
    while alive.any():
        deg = np.bincount(ea[alive], minlength=n) + np.bincount(eb[alive], minlength=n)
        v = int(np.argmax(deg))
        cover.append(v)
        alive &= (ea != v) & (eb != v)
    return np.array(cover, dtype=np.int64)


def _dissect(nodes: np.ndarray, ea: np.ndarray, eb: np.ndarray, coords: np.ndarray, leaf_size: int,
             out: list[tuple[np.ndarray, list[int]]]) -> int | None:
    """Append dissection nodes (pivots, children) in postorder; returns this subtree's front index.

    ``ea``, ``eb`` are the edges inside ``nodes``. Returns None for an empty subtree.
    """
    if nodes.size == 0:
        return None
    if nodes.size <= leaf_size:
        out.append((nodes, []))
        return len(out) - 1
    c = coords[nodes]
    axis = int(np.argmax(c.max(0) - c.min(0)))
    order = np.argsort(c[:, axis], kind="stable")
    side = np.zeros(coords.shape[0], dtype=np.int8)
    side[nodes[order[: nodes.size // 2]]] = 1
    side[nodes[order[nodes.size // 2:]]] = 2
    cross = side[ea] != side[eb]
    sep = _vertex_cover(ea[cross], eb[cross], coords.shape[0])
    side[sep] = 3
    children = []
    for s in (1, 2):
        inner = (side[ea] == s) & (side[eb] == s)
        sub = nodes[side[nodes] == s]
        child = _dissect(sub, ea[inner], eb[inner], coords, leaf_size, out)
        if child is not None:
            children.append(child)
    out.append((sep, children))  # an empty separator (disconnected halves) just groups children
    return len(out) - 1


def _lower_schur_update(F22: torch.Tensor, L21: torch.Tensor, panels: int = 4) -> torch.Tensor:
    """``F22 - L21 L21^T`` in place, on and below the diagonal only: nothing reads a front's
    upper triangle (Cholesky and the triangular solve read the lower one, and extend-add
    maps a child's lower triangle into its parent's, the boundary being sorted). Row panels
    stop at their diagonal block, so four panels do 10/16 of a full product's work.
    ``(m, m)``, ``(m, k)`` -> ``F22``."""
    m = F22.shape[0]
    if m < 64 * panels:  # small fronts: one product
        return F22.addmm_(L21, L21.mT, alpha=-1.0)
    cuts = [m * i // panels for i in range(panels + 1)]
    for a, b in zip(cuts[:-1], cuts[1:]):
        F22[a:b, :b].addmm_(L21[a:b], L21[:b].mT, alpha=-1.0)
    return F22


class BlockCholesky:
    """Symbolic analysis of an SPD block matrix; :meth:`factor` then :meth:`solve`.

    Args:
        n: number of nodes (block rows).
        slot_row, slot_col: ``(S,)`` block coordinates of the stored blocks; the pattern must be
            symmetric and contain every diagonal block ``(k, k)``.
        coords: ``(n, d)`` node coordinates for the dissection (pose translations).
        block: block size ``b``.
        leaf_size: largest dense leaf, in nodes.
    """

    def __init__(self, n: int, slot_row: np.ndarray, slot_col: np.ndarray, coords: np.ndarray,
                 block: int = 6, leaf_size: int = 32) -> None:
        self.n, self.b = n, block
        off = slot_row != slot_col
        ea, eb = slot_row[off], slot_col[off]
        keep = ea < eb
        ea, eb = ea[keep], eb[keep]
        nd: list[tuple[np.ndarray, list[int]]] = []
        _dissect(np.arange(n), ea, eb, np.asarray(coords, dtype=np.float64), leaf_size, nd)
        self.perm = np.concatenate([p for p, _ in nd]) if nd else np.zeros(0, dtype=np.int64)
        pos = np.empty(n, dtype=np.int64)
        pos[self.perm] = np.arange(n)
        self.pos = pos

        # adjacency (both directions) as CSR for boundary computation
        a = np.concatenate([ea, eb])
        bb = np.concatenate([eb, ea])
        order = np.argsort(a, kind="stable")
        a, bb = a[order], bb[order]
        ptr = np.zeros(n + 1, dtype=np.int64)
        np.cumsum(np.bincount(a, minlength=n), out=ptr[1:])

        # subtree end position of each dissection node (postorder => contiguous ranges)
        end = np.zeros(len(nd), dtype=np.int64)
        cursor = 0
        for f, (piv, _) in enumerate(nd):
            cursor += piv.size
            end[f] = cursor - 1
        self.fronts: list[_Front] = []
        bnds: list[np.ndarray] = []
        for f, (piv, children) in enumerate(nd):
            nb = bb[np.concatenate([np.arange(ptr[v], ptr[v + 1]) for v in piv])] if piv.size else \
                np.zeros(0, dtype=np.int64)
            cand = np.concatenate([nb] + [bnds[c] for c in children])
            cand = np.unique(cand)
            cand = cand[pos[cand] > end[f]]
            bnd = cand[np.argsort(pos[cand])]
            bnds.append(bnd)
            self.fronts.append(_Front(piv, bnd, children, np.zeros(0, np.int64), np.zeros(0, np.int64), []))

        # numeric assembly maps: block (r, c) with pos[c] <= pos[r] goes to the front pivoting c
        front_of = np.empty(n, dtype=np.int64)
        for f, fr in enumerate(self.fronts):
            front_of[fr.piv] = f
        lower = pos[slot_col] <= pos[slot_row]
        slots = np.nonzero(lower)[0]
        owner = front_of[slot_col[slots]]
        by_front = np.argsort(owner, kind="stable")
        slots, owner = slots[by_front], owner[by_front]
        starts = np.searchsorted(owner, np.arange(len(self.fronts) + 1))
        loc = np.full(n, -1, dtype=np.int64)
        e = np.arange(block)
        for f, fr in enumerate(self.fronts):
            idx = np.concatenate([fr.piv, fr.bnd])
            loc[idx] = np.arange(idx.size)
            m = block * idx.size
            s = slots[starts[f]: starts[f + 1]]
            r, c = loc[slot_row[s]], loc[slot_col[s]]
            rows = (block * r)[:, None, None] + e[None, :, None]
            cols = (block * c)[:, None, None] + e[None, None, :]
            fr.flat_pos = torch.from_numpy((rows * m + cols).reshape(-1))
            fr.flat_src = torch.from_numpy((s[:, None] * block * block + np.arange(block * block)[None, :]).reshape(-1))
            for ch in fr.children:
                cb = self.fronts[ch].bnd
                fr.child_maps.append(torch.from_numpy(((block * loc[cb])[:, None] + e[None, :]).reshape(-1)))
            loc[idx] = -1
        self._L11: list[torch.Tensor] = []
        self._L21: list[torch.Tensor] = []

    def factor(self, blocks: np.ndarray) -> None:
        """Factorise the matrix whose stored blocks are ``blocks`` ``(S, b, b)`` (slot order).

        Raises :class:`FactorError` if a pivot block is not positive definite.
        """
        flat = torch.from_numpy(np.ascontiguousarray(blocks, dtype=np.float64).reshape(-1))
        b = self.b
        updates: list[torch.Tensor | None] = [None] * len(self.fronts)
        self._L11, self._L21 = [], []
        for f, fr in enumerate(self.fronts):
            k = b * fr.piv.size
            m = k + b * fr.bnd.size
            F = torch.zeros(m * m, dtype=torch.float64)
            F[fr.flat_pos] = flat[fr.flat_src]
            F = F.reshape(m, m)
            for ch, cmap in zip(fr.children, fr.child_maps):
                U = updates[ch]
                if U is not None and U.numel():  # extend-add: one scatter-add at flat positions
                    F.view(-1).index_add_(0, (cmap[:, None] * m + cmap[None, :]).reshape(-1), U.reshape(-1))
                updates[ch] = None
            if k == 0:
                self._L11.append(torch.zeros(0, 0, dtype=torch.float64))
                self._L21.append(torch.zeros(m, 0, dtype=torch.float64))
                updates[f] = F
                continue
            L11, info = torch.linalg.cholesky_ex(F[:k, :k])
            if int(info) != 0:
                raise FactorError("normal matrix is not positive definite (unanchored poses?)")
            L21 = torch.linalg.solve_triangular(L11.mT, F[k:, :k], upper=True, left=False)
            self._L11.append(L11)
            self._L21.append(L21)
            updates[f] = _lower_schur_update(F[k:, k:], L21) if m > k else None

    def solve(self, rhs: np.ndarray) -> np.ndarray:
        """Solve ``A x = rhs`` with the last factorisation; ``rhs`` ``(n * b,)``."""
        b = self.b
        y = torch.tensor(np.asarray(rhs, dtype=np.float64)).reshape(self.n, b)
        for fr, L11, L21 in zip(self.fronts, self._L11, self._L21):
            if fr.piv.size == 0:
                continue
            yp = torch.linalg.solve_triangular(L11, y[fr.piv].reshape(-1, 1), upper=False)
            y[fr.piv] = yp.reshape(-1, b)
            if fr.bnd.size:
                y[fr.bnd] -= (L21 @ yp).reshape(-1, b)
        for fr, L11, L21 in zip(reversed(self.fronts), reversed(self._L11), reversed(self._L21)):
            if fr.piv.size == 0:
                continue
            rhs_p = y[fr.piv].reshape(-1, 1)
            if fr.bnd.size:
                rhs_p = rhs_p - L21.mT @ y[fr.bnd].reshape(-1, 1)
            y[fr.piv] = torch.linalg.solve_triangular(L11.mT, rhs_p, upper=True).reshape(-1, b)
        return y.reshape(-1).numpy()
