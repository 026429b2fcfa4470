"""Edge topology of a closed, consistently oriented triangle mesh (the index tables RLA needs).

Conventions: faces wind counter-clockwise seen from outside, so ``(v1 - v0) x (v2 - v0)`` is
the outward normal. An edge ``e = (i, j)`` has ``i < j``; ``ζ`` (zeta) is the face whose
winding holds the directed half-edge ``i -> j`` and ``τ`` (tau) the face holding ``j -> i``.
All index tensors are int64.
"""

from __future__ import annotations

from dataclasses import dataclass, fields

import numpy as np
import torch

__all__ = ["EdgeTopology"]


def _examples(pairs: np.ndarray, limit: int = 3) -> str:
    return ", ".join(f"({int(i)}, {int(j)})" for i, j in pairs[:limit])


def _validate_faces(faces: object, num_vertices: int) -> np.ndarray:
    if not isinstance(faces, torch.Tensor):
        raise TypeError(f"faces: expected a torch.Tensor, got {type(faces).__name__}")
    if faces.dim() != 2 or faces.shape[1] != 3:
        raise ValueError(f"faces: expected shape (F, 3), got {tuple(faces.shape)}")
    if faces.is_floating_point() or faces.is_complex() or faces.dtype == torch.bool:
        raise TypeError(f"faces: expected an integer tensor, got {str(faces.dtype).removeprefix('torch.')}")
    if faces.shape[0] == 0:
        raise ValueError("faces: expected at least one face, got (0, 3)")
    if not isinstance(num_vertices, int) or num_vertices <= 0:
        raise ValueError(f"num_vertices: expected a positive int, got {num_vertices!r}")
    f = faces.detach().cpu().numpy().astype(np.int64)
    if f.min() < 0 or f.max() >= num_vertices:
        raise ValueError(f"faces: expected vertex ids in [0, {num_vertices}), got range [{f.min()}, {f.max()}]")
    bad = (f[:, 0] == f[:, 1]) | (f[:, 1] == f[:, 2]) | (f[:, 2] == f[:, 0])
    if bad.any():
        raise ValueError(
            f"faces: expected three distinct vertices per face, found {int(bad.sum())} degenerate faces "
            f"(first: face {int(np.flatnonzero(bad)[0])})"
        )
    return f


@dataclass(frozen=True, eq=False)
class EdgeTopology:
    """Edge tables of a closed, consistently oriented manifold triangle mesh.

    Build it with :meth:`from_faces`. Equality and hashing are by identity, so an instance can
    key a cache (``reconstruct`` caches its factorised Laplacian per topology this way).

    Attributes:
        faces: (F, 3) vertex ids, counter-clockwise seen from outside.
        edges: (E, 2) vertex ids ``(i, j)`` with ``i < j``, sorted lexicographically.
        edge_faces: (E, 2) ``(ζ, τ)``: the face holding half-edge ``i -> j`` and the one holding ``j -> i``.
        opposite: (E, 2) the vertex of ``ζ`` and of ``τ`` that is not on the edge (``k`` and ``h``).
        face_edges: (F, 3) edge ids of each face's edges ``(v0 v1, v1 v2, v2 v0)``.
        edge_slots: (E, 2) position of the edge inside ``face_edges`` of ``ζ`` and of ``τ``, so
            ``face_edges[edge_faces[e, s], edge_slots[e, s]] == e``; the half-edge at slot ``k`` of
            face ``t`` runs from ``faces[t, k]`` to ``faces[t, (k + 1) % 3]``.
        vertex_count: V, the number of vertices (some may be unused by ``faces``).
    """

    faces: torch.Tensor
    edges: torch.Tensor
    edge_faces: torch.Tensor
    opposite: torch.Tensor
    face_edges: torch.Tensor
    edge_slots: torch.Tensor
    vertex_count: int

    @classmethod
    def from_faces(cls, faces: torch.Tensor, num_vertices: int) -> EdgeTopology:
        """Build the edge tables of a closed, consistently oriented manifold mesh.

        Args:
            faces: (F, 3) integer vertex ids.
            num_vertices: V; every id must lie in ``[0, V)``.

        Returns:
            The topology, its tensors int64 on the CPU.

        Raises:
            TypeError: ``faces`` is not an integer tensor.
            ValueError: wrong shape, ids out of range, degenerate faces, boundary edges (an edge in
                one face), non-manifold edges (in more than two faces), or an inconsistent orientation
                (an edge whose two faces traverse it in the same direction).
        """
        f = _validate_faces(faces, num_vertices)
        n_faces = f.shape[0]
        tail = f.reshape(-1)  # half-edge 3t + k runs tail -> head
        head = np.roll(f, -1, axis=1).reshape(-1)
        lo, hi = np.minimum(tail, head), np.maximum(tail, head)
        keys, inverse, counts = np.unique(lo * num_vertices + hi, return_inverse=True, return_counts=True)
        inverse = inverse.reshape(-1)
        pairs = np.stack([keys // num_vertices, keys % num_vertices], axis=1)
        if (counts != 2).any():
            boundary, nonmanifold = counts == 1, counts > 2
            parts = []
            if boundary.any():
                parts.append(f"{int(boundary.sum())} boundary edges in one face (e.g. {_examples(pairs[boundary])})")
            if nonmanifold.any():
                parts.append(
                    f"{int(nonmanifold.sum())} non-manifold edges in more than two faces "
                    f"(e.g. {_examples(pairs[nonmanifold])})"
                )
            raise ValueError(
                "faces: expected a closed manifold mesh with every edge in exactly 2 faces, found "
                + " and ".join(parts)
            )
        forward = tail < head
        n_forward = np.bincount(inverse, weights=forward, minlength=len(keys))
        if (n_forward != 1).any():
            flipped = n_forward != 1
            raise ValueError(
                f"faces: expected a consistently oriented mesh (each edge traversed once in each direction), "
                f"found {int(flipped.sum())} edges traversed twice in the same direction "
                f"(e.g. {_examples(pairs[flipped])}); flip the offending faces"
            )
        half = np.arange(3 * n_faces)
        side = np.where(forward, 0, 1)
        edge_faces = np.empty((len(keys), 2), dtype=np.int64)
        opposite = np.empty_like(edge_faces)
        slots = np.empty_like(edge_faces)
        edge_faces[inverse, side] = half // 3
        slots[inverse, side] = half % 3
        opposite[inverse, side] = np.roll(f, -2, axis=1).reshape(-1)
        return cls(
            faces=torch.from_numpy(f),
            edges=torch.from_numpy(pairs),
            edge_faces=torch.from_numpy(edge_faces),
            opposite=torch.from_numpy(opposite),
            face_edges=torch.from_numpy(inverse.reshape(n_faces, 3).astype(np.int64)),
            edge_slots=torch.from_numpy(slots),
            vertex_count=int(num_vertices),
        )

    @property
    def num_vertices(self) -> int:
        """V, the vertex count."""
        return self.vertex_count

    @property
    def num_edges(self) -> int:
        """E, the edge count."""
        return self.edges.shape[0]

    @property
    def num_faces(self) -> int:
        """F, the face count."""
        return self.faces.shape[0]

    @property
    def device(self) -> torch.device:
        """The device of the index tensors."""
        return self.edges.device

    def to(self, device: torch.device | str) -> EdgeTopology:
        """A copy with every index tensor on ``device`` (``self`` when already there)."""
        device = torch.device(device)
        if self.edges.device == device:
            return self
        moved = {
            fld.name: getattr(self, fld.name).to(device)
            if isinstance(getattr(self, fld.name), torch.Tensor)
            else getattr(self, fld.name)
            for fld in fields(self)
        }
        return EdgeTopology(**moved)
