"""Topology abstraction: carry a mesh from a source topology onto the canonical one.

Paper 000 §3.3: each canonical vertex stores the three source vertices of its closest
source triangle (on the artist's wrap) and four barycentric coordinates in the
tetrahedron lifted from that triangle. At run time each canonical vertex is a weighted sum
of four points of the deformed source mesh (eq. 1): a gather whose cost depends on the
canonical vertex count only.
"""

from __future__ import annotations

import torch
from torch import nn

from ._checks import check_finite, check_like, check_shape
from .geometry.tetra import apply_correspondence

__all__ = ["CANONICAL_VERTICES", "TopologyTransfer"]

CANONICAL_VERTICES = 18056
"""Vertices of the canonical mesh (the SOMA topology): every canonical vertex id is below it."""


class TopologyTransfer(nn.Module):
    """Map meshes of one source topology to the canonical topology.

    Args:
        name: the source topology's name (used in messages).
        num_source_vertices: Vs, the source vertex count.
        face_vertices: (V, 3) source vertex ids of each canonical vertex's tetrahedron base.
        weights: (V, 4) tetrahedral barycentric coordinates.
    """

    def __init__(self, name: str, num_source_vertices: int, face_vertices: torch.Tensor, weights: torch.Tensor) -> None:
        super().__init__()
        self.name = name
        self.num_source_vertices = num_source_vertices
        if int(face_vertices.max()) >= num_source_vertices or int(face_vertices.min()) < 0:
            raise ValueError(
                f"face_vertices: expected ids in [0, {num_source_vertices}), "
                f"got range [{int(face_vertices.min())}, {int(face_vertices.max())}]"
            )
        self.register_buffer("face_vertices", face_vertices.long(), persistent=False)
        self.register_buffer("weights", weights, persistent=False)

    @property
    def num_vertices(self) -> int:
        """V, the canonical vertex count."""
        return self.face_vertices.shape[0]

    @classmethod
    def from_anny(cls) -> TopologyTransfer:
        """The transfer from Anny's native 13,718-vertex mesh, built from the bundled wrap."""
        from .assets import canonical_assets

        a = canonical_assets()
        return cls("anny", 13718, torch.from_numpy(a["anny_face_vertices"]), torch.from_numpy(a["anny_weights"]))

    def forward(self, source: torch.Tensor) -> torch.Tensor:
        """Transfer meshes.

        Args:
            source: (B, Vs, 3) vertices on the source topology, metres, unibody axes.

        Returns:
            (B, V, 3) vertices on the canonical topology.
        """
        check_shape(source, f"B {self.num_source_vertices} 3", name=f"{self.name} vertices")
        check_like(source, self.weights, name=f"{self.name} vertices", owner="the topology transfer")
        check_finite(source, f"{self.name} vertices")
        return apply_correspondence(source, self.face_vertices, self.weights)
