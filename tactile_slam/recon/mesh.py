"""Triangle-mesh container, grid triangulation, topology checks and PLY output (method.md 8.2)."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
import open3d as o3d
import torch
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components


class MeshError(ValueError):
    """An empty or malformed mesh, or an unwritable output."""


@dataclass
class TriMesh:
    """A triangle mesh in metres.

    Attributes:
        vertices: ``(V, 3)`` float64 metres, in the frame named by whoever made it.
        faces: ``(F, 3)`` int64 vertex indices, counter-clockwise seen from outside.
        normals: ``(V, 3)`` float64 unit outward vertex normals.
    """

    vertices: torch.Tensor
    faces: torch.Tensor
    normals: torch.Tensor

    @property
    def n_vertices(self) -> int:
        return int(self.vertices.shape[0])

    @property
    def n_faces(self) -> int:
        return int(self.faces.shape[0])

    def to_open3d(self) -> o3d.geometry.TriangleMesh:
        m = o3d.geometry.TriangleMesh()
        m.vertices = o3d.utility.Vector3dVector(self.vertices.detach().cpu().double().numpy())
        m.triangles = o3d.utility.Vector3iVector(self.faces.detach().cpu().numpy().astype(np.int32))
        m.vertex_normals = o3d.utility.Vector3dVector(self.normals.detach().cpu().double().numpy())
        return m

    @staticmethod
    def from_open3d(mesh: o3d.geometry.TriangleMesh) -> "TriMesh":
        if not mesh.has_vertex_normals():
            mesh.compute_vertex_normals()
        return TriMesh(
            vertices=torch.from_numpy(np.asarray(mesh.vertices, dtype=np.float64).copy()),
            faces=torch.from_numpy(np.asarray(mesh.triangles, dtype=np.int64).copy()),
            normals=torch.from_numpy(np.asarray(mesh.vertex_normals, dtype=np.float64).copy()),
        )

    def save_ply(self, path: str | Path) -> Path:
        """Binary little-endian PLY with double xyz and normals, in metres."""
        if self.n_vertices == 0:
            raise MeshError(f"refusing to write an empty mesh to {path}")
        path = Path(path)
        path.parent.mkdir(parents=True, exist_ok=True)
        if not o3d.io.write_triangle_mesh(str(path), self.to_open3d(), write_ascii=False, compressed=False,
                                          write_vertex_normals=True, write_vertex_colors=False):
            raise MeshError(f"could not write mesh to {path}")
        return path


def grid_faces(mask: torch.Tensor) -> torch.Tensor:
    """Triangulate the pixels of one mask or a stack of masks (method.md 8.2).

    For each masked pixel (r, c): triangle (r,c)-(r+1,c)-(r,c+1) when both others are
    masked, and (r+1,c)-(r+1,c+1)-(r,c+1) when (r+1,c+1) is masked too. With x right,
    y down and z out of the gel, face normals point to -z, the object's outside.
    Triangles never join pixels of different masks in a stack.

    Args:
        mask: ``(H, W)`` or ``(K, H, W)`` bool.

    Returns:
        ``(F, 3)`` int64 indices into the row-major list of masked pixels (over the
        whole stack: mask 0's pixels first, then mask 1's, ...).
    """
    m = mask if mask.dim() == 3 else mask.unsqueeze(0)
    k, h, w = m.shape
    padded = torch.zeros((k, h + 1, w + 1), dtype=torch.bool, device=mask.device)
    padded[:, :h, :w] = m
    pos = padded.reshape(-1).nonzero()[:, 0]  # masked pixels, row-major over the stack
    index = torch.full((k * (h + 1) * (w + 1),), -1, dtype=torch.int64, device=mask.device)
    index[pos] = torch.arange(pos.shape[0], device=mask.device)
    # a pixel's right, lower and diagonal neighbours are 1, w + 1 and w + 2 further on;
    # the padding row and column read -1
    right = index[pos + 1]
    down = index[pos + w + 1]
    diag = index[pos + w + 2]
    upper = (down >= 0) & (right >= 0)
    iu = upper.nonzero()[:, 0]
    il = (upper & (diag >= 0)).nonzero()[:, 0]
    f1 = torch.stack([iu, down.index_select(0, iu), right.index_select(0, iu)], dim=1)
    f2 = torch.stack([down.index_select(0, il), diag.index_select(0, il), right.index_select(0, il)], dim=1)
    return torch.cat([f1, f2])


def _shared_edges(faces: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """The faces' undirected edges sorted by their vertex pair: ``(3F,)`` face of each,
    ``(3F,)`` lower and ``(3F,)`` higher vertex, and ``(3F - 1,)`` bool "same edge as
    the next one" (faces sharing an edge are consecutive)."""
    a, b = faces.reshape(-1).astype(np.int64), faces[:, [1, 2, 0]].reshape(-1).astype(np.int64)
    lo, hi = np.minimum(a, b), np.maximum(a, b)
    key = lo * (int(hi.max()) + 1) + hi
    order = np.argsort(key)
    key = key[order]
    return order // 3, lo[order], hi[order], key[1:] == key[:-1]


def face_components(faces: np.ndarray) -> np.ndarray:
    """Labels of the edge-connected components of ``(F, 3)`` triangles (faces that
    share an edge are connected; a shared vertex alone does not connect): ``(F,)``,
    numbered in order of each component's first face."""
    if len(faces) == 0:
        return np.zeros(0, dtype=np.int64)
    face, _, _, same = _shared_edges(faces)
    graph = coo_matrix((np.ones(int(same.sum()), dtype=np.int8), (face[:-1][same], face[1:][same])),
                       shape=(len(faces), len(faces)))
    return connected_components(graph, directed=False)[1]


def is_closed_manifold(faces: np.ndarray) -> bool:
    """Whether ``(F, 3)`` triangles are closed and manifold: every edge in exactly two
    faces (no boundary, no fins), and the faces around every vertex form one fan
    (edge-connected through edges at that vertex; two cones touching at their tips fail).
    No faces is not closed."""
    if len(faces) == 0:
        return False
    face, lo, hi, same = _shared_edges(faces)
    starts = np.flatnonzero(np.r_[True, ~same])
    if not (np.diff(np.r_[starts, len(face)]) == 2).all():
        return False
    # corners (face, vertex), numbered 3 f + position; two faces sharing edge (u, v)
    # join their corners at u and at v
    i = np.flatnonzero(same)
    f1, f2 = face[i], face[i + 1]
    ends = np.r_[lo[i], hi[i]]
    f1, f2 = np.r_[f1, f1], np.r_[f2, f2]
    c1 = 3 * f1 + np.argmax(faces[f1] == ends[:, None], axis=1)
    c2 = 3 * f2 + np.argmax(faces[f2] == ends[:, None], axis=1)
    graph = coo_matrix((np.ones(len(c1), dtype=np.int8), (c1, c2)), shape=(3 * len(faces), 3 * len(faces)))
    n_fans = connected_components(graph, directed=False)[0]
    return n_fans == int(np.count_nonzero(np.bincount(faces.reshape(-1))))
