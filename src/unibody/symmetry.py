"""Sagittal (left/right) mirror symmetry of the canonical mesh.

The mirror is the reflection x -> -x about the plane x = 0 (the body's left is +X, so the
plane splits left from right). Each canonical vertex i has a partner ``index[i]``: the bind
(A-pose) vertex nearest to the reflection of vertex i. On the canonical SOMA mesh this map is
a bijective involution (``index[index[i]] == i``; 194 vertices on the midplane are their own
partner) and the reflected vertices lie within 0.16 um of their partners (float32 rounding of
the source file), so mirroring a mesh is a gather plus a sign flip:
``mirror(v)[i] = S v[index[i]]`` with S = diag(-1, 1, 1).

The map depends on the bind mesh only: it is computed on first use and cached
(:func:`functools.cache`), so no asset can drift out of step with the rig.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import cache

import torch

from ._checks import check_finite, check_shape, check_tensor

__all__ = ["MirrorMap", "canonical_mirror_map", "mirror", "mirror_correspondence", "partner_joints"]

_QUERY_BLOCK = 1024
_START_RADIUS = 0.005  # m; the search window grows by 4x until every query found a partner inside it


@dataclass(frozen=True, slots=True)
class MirrorMap:
    """A left/right vertex correspondence.

    Attributes:
        index: (V,) long, the partner of each vertex (its mirror image's nearest vertex).
        distance: (V,) m, float64, distance between each reflected vertex and its partner.
    """

    index: torch.Tensor
    distance: torch.Tensor

    @property
    def is_bijection(self) -> bool:
        """Whether every vertex is the partner of exactly one vertex."""
        return int(torch.unique(self.index).numel()) == int(self.index.numel())

    @property
    def is_involution(self) -> bool:
        """Whether the partner of each vertex's partner is the vertex itself."""
        return bool((self.index[self.index] == torch.arange(self.index.numel())).all())

    @property
    def num_midplane(self) -> int:
        """How many vertices are their own partner (they lie on the plane x = 0)."""
        return int((self.index == torch.arange(self.index.numel())).sum())

    @property
    def max_distance(self) -> float:
        """m, the largest reflected-vertex-to-partner distance."""
        return float(self.distance.max())


def mirror_correspondence(vertices: torch.Tensor) -> MirrorMap:
    """Match each vertex's reflection (x -> -x) to its nearest vertex, exactly.

    The search sorts the vertices by y and compares each block of reflected queries with the
    vertices in a y-window around it; the window grows until every query's nearest candidate
    lies within the window's margin, which proves no vertex outside it is nearer. The result
    equals a brute-force nearest-neighbour search (ties aside).

    Args:
        vertices: (V, 3) m, a mesh in unibody axes (the body's left on +X).

    Returns:
        The correspondence; check :attr:`MirrorMap.is_involution` before using it as a mirror.
    """
    check_shape(vertices, "V 3", name="vertices")
    check_finite(vertices, "vertices")
    v = vertices.detach().to(torch.float64)
    order = torch.argsort(v[:, 1])
    sorted_v = v[order]
    y = sorted_v[:, 1].contiguous()
    queries = sorted_v * sorted_v.new_tensor([-1.0, 1.0, 1.0])
    index = torch.empty(len(v), dtype=torch.long, device=v.device)
    distance = torch.empty(len(v), dtype=torch.float64, device=v.device)
    for start in range(0, len(v), _QUERY_BLOCK):
        q = queries[start : start + _QUERY_BLOCK]
        lo_y, hi_y, radius = q[:, 1].min(), q[:, 1].max(), _START_RADIUS
        while True:
            lo = int(torch.searchsorted(y, lo_y - radius))
            hi = int(torch.searchsorted(y, hi_y + radius, right=True))
            d, i = torch.cdist(q, sorted_v[lo:hi]).min(dim=1)
            if hi - lo == len(v) or bool((d <= radius).all()):
                break
            radius *= 4.0
        index[order[start : start + len(q)]] = order[lo + i]
        distance[order[start : start + len(q)]] = d
    return MirrorMap(index.cpu(), distance.cpu())


@cache
def canonical_mirror_map() -> MirrorMap:
    """The mirror map of the canonical mesh, from its bind (A-pose) vertices (computed once).

    Raises:
        AssetError: the bind mesh is not left/right symmetric (the map is no involution).
    """
    from .assets import AssetError, canonical_assets

    m = mirror_correspondence(torch.from_numpy(canonical_assets()["bind_vertices"]))
    if not (m.is_involution and m.is_bijection):
        raise AssetError(
            "canonical mesh: the left/right nearest-vertex map is not a bijective involution "
            f"(largest mismatch {1e3 * m.max_distance:.3g} mm); the bind mesh is not symmetric"
        )
    return m


@cache
def _index_on(device: torch.device) -> torch.Tensor:
    return canonical_mirror_map().index.to(device)


def mirror(vertices: torch.Tensor) -> torch.Tensor:
    """Reflect meshes on the canonical topology about the sagittal plane x = 0.

    Vertex i of the result is the reflection of the input's vertex ``index[i]``, so the result
    is again a valid mesh on the canonical topology (left and right swap). Linear, so
    gradients flow; ``mirror(mirror(v)) == v`` exactly.

    Args:
        vertices: (B, V, 3) m, meshes on the canonical topology (V = 18,056).

    Returns:
        (B, V, 3) m, the mirrored meshes.
    """
    check_tensor(vertices, "vertices")
    index = _index_on(vertices.device)
    check_shape(vertices, f"B {index.numel()} 3", name="vertices")
    check_finite(vertices, "vertices")
    return vertices[:, index] * vertices.new_tensor([-1.0, 1.0, 1.0])


@cache
def partner_joints(joint_names: tuple[str, ...]) -> torch.Tensor:
    """(J,) int64 each joint's left/right partner by name ("Left..." <-> "Right..."; a midline
    joint is its own), e.g. for ``BodyLayer.joint_names``.

    Raises:
        ValueError: a "Left..." or "Right..." joint without its partner among ``joint_names``.
    """
    names = list(joint_names)
    swap = {"Left": "Right", "Right": "Left"}
    partner = [next((swap[k] + n[len(k) :] for k in swap if n.startswith(k)), n) for n in names]
    missing = [n for n, q in zip(names, partner, strict=True) if q not in names]
    if missing:
        raise ValueError(f"joint_names: {missing[0]!r} has no left/right partner {partner[names.index(missing[0])]!r}")
    return torch.tensor([names.index(q) for q in partner])
