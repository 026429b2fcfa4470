"""Training and evaluation samples for the occupancy network (paper 002 §4, "Training").

Bodies are PCA identities (newborns to adults; :func:`unibody.synth.identities.identity_pool`,
pool 0 trains and pool 1 is held out) in poses from :func:`unibody.synth.poses.sample_poses`, posed
by the float32 PCA layer with procedural twist. Ground truth is the generalized winding number
of the posed mesh (libigl's fast winding numbers), which stays robust where LBS makes the mesh
self-intersect. Every draw is a function of ``(seed, index)`` so that training can resume.
"""

from __future__ import annotations

import functools

import numpy as np
import torch

from ..body import BodyLayer, BodyOutput
from ..synth.identities import NUM_SHAPE, identity_pool
from ..synth.poses import keyed_generator, sample_poses
from .model import part_boxes
from .parts import BodyParts

__all__ = ["generator", "pose_bodies", "inside_mesh", "surface_points", "training_queries", "evaluation_points"]


def generator(*key: object) -> torch.Generator:
    """The random stream of ``key`` within the occupancy data (:func:`unibody.synth.poses.keyed_generator`)."""
    return keyed_generator("occupancy", *key)


@functools.cache
def _layer() -> BodyLayer:
    return BodyLayer.from_pca(num_components=NUM_SHAPE, procedural=True)


@functools.cache
def _pool(seed: int, size: int) -> torch.Tensor:
    return identity_pool(size, seed=seed)


def pose_bodies(n: int, *, seed: int, index: int, identities: int = 1000) -> tuple[BodyOutput, torch.Tensor]:
    """``n`` posed bodies of draw ``index`` of set ``seed`` (0 trains, 1 held out) and the mesh faces.

    Identities come from pool ``seed`` (``identities`` of them), poses from a stream keyed by
    ``(seed, index)``.
    """
    gen = generator("bodies", seed, index)
    layer = _layer()
    pick = torch.randint(identities, (n,), generator=gen)
    pose = sample_poses(n, gen)
    with torch.no_grad():
        out = layer(_pool(seed, identities)[pick], pose)
    return out, layer.faces


def inside_mesh(vertices: torch.Tensor, faces: torch.Tensor, points: torch.Tensor) -> torch.Tensor:
    """(B, T) bool: generalized winding number > 1/2 of ``points`` (B, T, 3) w.r.t. meshes (B, V, 3)."""
    import igl

    f = np.ascontiguousarray(faces.cpu().numpy().astype(np.int64))
    out = []
    for v, p in zip(vertices.detach().cpu().double().numpy(), points.detach().cpu().double().numpy(), strict=True):
        out.append(torch.from_numpy(igl.fast_winding_number(np.ascontiguousarray(v), f, np.ascontiguousarray(p))))
    return (torch.stack(out) > 0.5).to(points.device)


def surface_points(
    vertices: torch.Tensor, faces: torch.Tensor, n: int, gen: torch.Generator, face_weight: torch.Tensor | None = None
) -> tuple[torch.Tensor, torch.Tensor]:
    """``n`` area-weighted surface samples (B, n, 3) of meshes (B, V, 3) and their face ids (B, n).

    ``face_weight`` (F,) or (B, F) multiplies the areas.
    """
    tri = vertices[:, faces.long()]
    area = torch.linalg.cross(tri[:, :, 1] - tri[:, :, 0], tri[:, :, 2] - tri[:, :, 0]).norm(dim=-1)
    if face_weight is not None:
        area = area * face_weight
    ids = torch.multinomial(area.double().cpu(), n, replacement=True, generator=gen).to(vertices.device)
    r = torch.rand(*ids.shape, 2, generator=gen).to(vertices)
    s = r[..., 0].sqrt()
    bary = torch.stack([1 - s, s * (1 - r[..., 1]), s * r[..., 1]], -1)
    picked = torch.gather(tri, 1, ids[..., None, None].expand(-1, -1, 3, 3))
    return (bary[..., None] * picked).sum(-2), ids


def training_queries(
    parts: BodyParts,
    out: BodyOutput,
    faces: torch.Tensor,
    per_part: int,
    gen: torch.Generator,
    *,
    sigma: float = 0.01,
    padding: float = 1.125,
) -> torch.Tensor:
    """(B, K * per_part, 3) queries: per part, half uniform in its padded box, half near its surface.

    Near-surface points are area-weighted surface samples plus N(0, sigma^2) noise (m); every
    part gets the same share in expectation.
    """
    g = out.transforms[:, parts.joints]
    rotation, origin = g[..., :3, :3], g[..., :3, 3]
    center, half = part_boxes(parts, out.vertices, rotation, origin, padding)
    b, k, half_n = out.vertices.shape[0], parts.num_parts, per_part // 2
    u = 2 * torch.rand(b, k, half_n, 3, generator=gen).to(center) - 1
    local = center[:, :, None] + u * half[:, :, None]
    uniform = torch.einsum("bknd,bkcd->bknc", local, rotation) + origin[:, :, None]
    # One draw for all parts: weighting each face by 1 / (its part's area) gives every part the same share.
    tri = out.vertices[:, faces.long()]
    area = torch.linalg.cross(tri[:, :, 1] - tri[:, :, 0], tri[:, :, 2] - tri[:, :, 0]).norm(dim=-1)
    label = parts.face_part.to(area.device)
    part_area = area.new_zeros(b, k).index_add_(1, label, area)
    p, _ = surface_points(out.vertices, faces, k * (per_part - half_n), gen, 1.0 / part_area[:, label])
    near = p + sigma * torch.randn(p.shape, generator=gen).to(p)
    return torch.cat([uniform.reshape(b, -1, 3), near], 1)


def evaluation_points(
    vertices: torch.Tensor, faces: torch.Tensor, n: int, gen: torch.Generator, *, sigma: float = 0.01
) -> tuple[torch.Tensor, torch.Tensor]:
    """Evaluation queries of paper 002 §5: ``n`` uniform in each mesh's bounding box (padded by
    5 % of its size on every side) and ``n`` near its surface (area-weighted, N(0, sigma^2) noise)."""
    lo, hi = vertices.amin(1, keepdim=True), vertices.amax(1, keepdim=True)
    pad = 0.05 * (hi - lo)
    u = torch.rand(vertices.shape[0], n, 3, generator=gen).to(vertices)
    uniform = lo - pad + u * (hi - lo + 2 * pad)
    p, _ = surface_points(vertices, faces, n, gen)
    return uniform, p + sigma * torch.randn(p.shape, generator=gen).to(p)
