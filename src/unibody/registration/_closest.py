"""Exact closest points on a triangle surface that registration queries again and again.

:class:`SurfaceIndex` keeps libigl's AABB tree of one mesh (CPU, float64) and answers
closest-triangle queries against it; :meth:`SurfaceIndex.refit` rebuilds the tree when the
mesh moves (same topology), as the template does inside the ICP loop. Registration needs
neither gradients nor CUDA here, so the torch search of
:func:`unibody.geometry.tetra.closest_triangles` is not used.
"""

from __future__ import annotations

import numpy as np
import torch

__all__ = ["SurfaceIndex"]


class SurfaceIndex:
    """Closest-triangle queries against one triangle mesh.

    Args:
        vertices: (V, 3) mesh vertices (computed in float64).
        faces: (F, 3) long triangles; zero-area triangles take part like any other (as the
            segment or point they are).
    """

    def __init__(self, vertices: torch.Tensor, faces: torch.Tensor) -> None:
        self.faces = faces
        self._faces = np.ascontiguousarray(faces.detach().cpu().numpy().astype(np.int64, copy=False))
        self.refit(vertices)

    def refit(self, vertices: torch.Tensor) -> None:
        """Rebuild the tree for moved ``vertices`` (same topology)."""
        import igl  # a compiled extension: loaded on first use only

        self.vertices = vertices
        self._vertices = np.ascontiguousarray(vertices.detach().to(device="cpu", dtype=torch.float64).numpy())
        self._tree = igl.AABB()
        self._tree.init(self._vertices, self._faces)

    def area(self) -> float:
        """Total surface area of the mesh."""
        t = self.vertices.detach()[self.faces]
        return float(0.5 * torch.linalg.cross(t[:, 1] - t[:, 0], t[:, 2] - t[:, 0], dim=-1).norm(dim=-1).sum())

    def query(self, points: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """Exact closest triangle for each of ``points (N, 3)``; equally close triangles: either.

        Returns ``(face index (N,) long, closest point (N, 3), distance (N,))`` in the dtype of
        ``points``.
        """
        p = np.ascontiguousarray(points.detach().to(device="cpu", dtype=torch.float64).numpy())
        sq, face, q = self._tree.squared_distance(self._vertices, self._faces, p)
        return (
            torch.from_numpy(face),
            torch.from_numpy(q).to(points.dtype),
            torch.from_numpy(sq).sqrt().to(points.dtype),
        )
