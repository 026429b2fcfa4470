"""Anny identity backend: phenotypes (and optional local changes) -> rest mesh.

Anny (NAVER, Apache-2.0) maps six anthropometric phenotypes in [0, 1] (gender, age,
muscle, weight, height, proportions; age 0 is a newborn, 1 an elder) and optional
local-change coefficients in [-1, 1] to a rest mesh on its native 13,718-vertex topology
through multi-linear blendshapes. Its native frame is Z up, -Y forward; this module returns
unibody's frame (Y up, +Z forward): (x, y, z) -> (x, z, -y), metres.
"""

from __future__ import annotations

import torch
from torch import nn

from .._checks import check_finite, check_like, check_shape

__all__ = ["AnnyIdentity", "PHENOTYPES"]

PHENOTYPES: tuple[str, ...] = ("gender", "age", "muscle", "weight", "height", "proportions")


class AnnyIdentity(nn.Module):
    """Rest meshes of Anny identities on Anny's native topology.

    Args:
        model: an ``anny.Anny`` model built with ``rig="anny", topology="anny"`` and the
            default phenotypes (see :meth:`create`).
    """

    name = "anny"

    def __init__(self, model: nn.Module) -> None:
        super().__init__()
        labels = tuple(model.phenotype_labels)
        if labels != PHENOTYPES:
            raise ValueError(f"model: expected Anny phenotypes {PHENOTYPES}, got {labels}")
        self.model = model
        self.local_changes: tuple[str, ...] = tuple(model.local_change_labels)
        self.param_names: tuple[str, ...] = PHENOTYPES + self.local_changes
        self.num_vertices = int(model.template_vertices.shape[0])

    @classmethod
    def create(cls, *, local_changes: str | tuple[str, ...] = "none") -> AnnyIdentity:
        """Build the Anny backend (``local_changes``: "none", "default", "all" or names)."""
        import anny

        local = list(local_changes) if isinstance(local_changes, tuple) else local_changes
        return cls(anny.Anny(rig="anny", topology="anny", local_changes=local))

    @property
    def num_params(self) -> int:
        """K: 6 phenotypes followed by the local changes."""
        return len(self.param_names)

    def default_params(self, batch: int = 1) -> torch.Tensor:
        """(B, K) the average identity: phenotypes 0.5, local changes 0."""
        ref = self.model.template_vertices
        params = ref.new_zeros(batch, self.num_params)
        params[:, : len(PHENOTYPES)] = 0.5
        return params

    def faces(self) -> torch.Tensor:
        """(F, 3) triangles of the native mesh."""
        return self.model.get_triangular_faces()

    def forward(self, params: torch.Tensor) -> torch.Tensor:
        """Rest meshes.

        Args:
            params: (B, K) phenotypes in [0, 1] then local changes in [-1, 1], in the order
                of ``param_names``.

        Returns:
            (B, 13718, 3) rest vertices, metres, Y up, facing +Z.
        """
        ref = self.model.template_vertices
        check_shape(params, f"B {self.num_params}", name="identity params")
        check_like(params, ref, name="identity params", owner="the Anny backend")
        check_finite(params, "identity params")
        n = len(PHENOTYPES)
        phen, local = params[:, :n], params[:, n:]
        for name, x, lo in (("phenotype", phen, 0.0), ("local change", local, -1.0)):
            bad = (x < lo) | (x > 1.0)
            if bool(bad.any()):
                b, k = (int(i) for i in torch.nonzero(bad)[0])
                label = self.param_names[k + (0 if name == "phenotype" else n)]
                raise ValueError(
                    f"identity params: {name} {label!r} must lie in [{lo:g}, 1], got {float(x[b, k]):.4g} at batch {b}"
                )
        coeffs = self.model._get_phenotype_blendshape_coefficients(phen, local, params.new_zeros(params.shape[0], 0))
        v = self.model.get_rest_vertices(coeffs)
        return torch.stack([v[..., 0], v[..., 2], -v[..., 1]], dim=-1)
