"""The compositional occupancy network (paper 002 §4): local part frames and boxes, a shared
PointNet encoder over each part's surface samples, a shared decoder, max composition.

Differs from the reference implementation for speed and determinism (fixed encoder samples,
box-normalised coordinates, decoding only inside part boxes, a local-geometry input): see
``docs/occupancy.md``.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import nn

from .parts import BodyParts

__all__ = ["PartEncoding", "OccupancyNet", "OUTSIDE"]

OUTSIDE = -1.0e4  # logit of a part at a point outside its box (sigmoid gives exactly 0)


@dataclass(frozen=True, slots=True)
class PartEncoding:
    """A posed batch as the decoder sees it.

    Attributes:
        rotation: (B, K, 3, 3) world rotation of each part's frame.
        origin: (B, K, 3) m, world origin of each part's frame (its joint).
        center: (B, K, 3) m, box centre in the part frame.
        half: (B, K, 3) m, padded box half-size in the part frame.
        bias: (B, K, W) the decoder's first-layer bias of each part (code, part id, box size).
        samples: (B, K, S, 3) m, the part's encoder samples in its frame.
        normals: (B, K, S, 3) their unit normals in the part frame.
    """

    rotation: torch.Tensor
    origin: torch.Tensor
    center: torch.Tensor
    half: torch.Tensor
    bias: torch.Tensor
    samples: torch.Tensor
    normals: torch.Tensor

    def to_boxes(self, points: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Box coordinates (B, T, K, 3) of world ``points`` (B, T, 3) and the inside mask (B, T, K)."""
        local = torch.einsum("btc,bkcd->btkd", points, self.rotation)
        local = local - torch.einsum("bkc,bkcd->bkd", self.origin, self.rotation)[:, None]
        u = (local - self.center[:, None]) / self.half[:, None]
        return u, (u.abs() <= 1.0).all(-1)

    def detach(self) -> PartEncoding:
        return PartEncoding(*(getattr(self, f).detach() for f in self.__slots__))


def part_boxes(
    parts: BodyParts, vertices: torch.Tensor, rotation: torch.Tensor, origin: torch.Tensor, padding: float
) -> tuple[torch.Tensor, torch.Tensor]:
    """Centres and padded half-sizes (B, K, 3) of the parts' vertices in their own frames."""
    label = parts.vertex_part.to(vertices.device)
    local = torch.einsum("bvc,bvcd->bvd", vertices - origin[:, label], rotation[:, label])
    b, k = vertices.shape[0], parts.num_parts
    index = label[None, :, None].expand_as(local)
    hi = local.new_full((b, k, 3), -torch.inf).scatter_reduce(1, index, local, "amax")
    lo = local.new_full((b, k, 3), torch.inf).scatter_reduce(1, index, local, "amin")
    return 0.5 * (hi + lo), 0.5 * padding * (hi - lo)


def _surface_samples(parts: BodyParts, faces: torch.Tensor, vertices: torch.Tensor, count: int, seed: int):
    """(K, 2*count) face ids and (K, 2*count, 3) barycentric weights: ``count`` area-weighted
    samples on each part's tight faces, then ``count`` on its extended faces (template areas)."""
    gen = torch.Generator().manual_seed(seed)
    tri = vertices[faces]
    area = torch.linalg.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]).norm(dim=-1)
    ids, bary = [], []
    for k in range(parts.num_parts):
        rows = []
        for mask in (parts.face_part == k, parts.extended[k][parts.face_part]):
            w = torch.where(mask, area, torch.zeros_like(area))
            rows.append(torch.multinomial(w, count, replacement=True, generator=gen))
        ids.append(torch.cat(rows))
        r = torch.rand(2 * count, 2, generator=gen, dtype=torch.float64)
        s = r[:, 0].sqrt()
        bary.append(torch.stack([1 - s, s * (1 - r[:, 1]), s * r[:, 1]], -1))
    return torch.stack(ids), torch.stack(bary)


def local_features(u: torch.Tensor, b: torch.Tensor, k: torch.Tensor, enc: PartEncoding) -> torch.Tensor:
    """(N, 7) local geometry of box coordinates ``u`` (N, 3) of parts ``k`` of bodies ``b``: the
    offset to the part's nearest encoder sample in box units, the signed distance to that sample's
    tangent plane in units of the mean box half-size, and the sample's normal (part frame)."""
    half, center = enc.half[b, k], enc.center[b, k]
    x = u * half + center  # the part frame, metres
    num_parts = enc.half.shape[1]
    key = b * num_parts + k
    order = torch.argsort(key, stable=True)
    counts = torch.bincount(key, minlength=enc.half.shape[0] * num_parts).tolist()
    nearest = torch.empty_like(key)
    start = 0
    with torch.no_grad():
        for group, n in enumerate(counts):
            if n:
                rows = order[start : start + n]
                s = enc.samples[group // num_parts, group % num_parts]
                # |x - s|^2 up to the per-row constant |x|^2: one matmul, no square roots
                nearest[rows] = torch.addmm(s.pow(2).sum(-1), x[rows], s.T, alpha=-2.0).argmin(1)
                start += n
    p, n = enc.samples[b, k, nearest], enc.normals[b, k, nearest]
    off = x - p
    signed = (off * n).sum(-1, keepdim=True) / half.mean(-1, keepdim=True)
    return torch.cat([off / half, signed, n], -1)


class _ResBlock(nn.Module):
    def __init__(self, d_in: int, d_out: int) -> None:
        super().__init__()
        self.fc0, self.fc1 = nn.Linear(d_in, d_out), nn.Linear(d_out, d_out)
        self.skip = nn.Linear(d_in, d_out, bias=False)
        nn.init.zeros_(self.fc1.weight)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.skip(x) + self.fc1(torch.relu(self.fc0(torch.relu(x))))


class PointEncoder(nn.Module):
    """ResNet PointNet (ONet/LEAP style): per-point blocks with max-pooled context, one code per set."""

    def __init__(self, d_in: int, width: int, code: int, blocks: int = 3) -> None:
        super().__init__()
        self.fc_in = nn.Linear(d_in, 2 * width)
        self.blocks = nn.ModuleList(_ResBlock(2 * width, width) for _ in range(blocks))
        self.fc_out = nn.Linear(width, code)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        """(N, S, d_in) point sets -> (N, code)."""
        h = self.fc_in(x)
        for i, block in enumerate(self.blocks):
            h = block(h)
            if i + 1 < len(self.blocks):
                h = torch.cat([h, h.amax(1, keepdim=True).expand_as(h)], -1)
        return self.fc_out(torch.relu(h.amax(1)))


class OccupancyNet(nn.Module):
    """Shared encoder and decoder for all parts.

    Args:
        parts: the part decomposition.
        faces: (F, 3) mesh faces; template: (V, 3) template vertices (for the sample layout).
        samples: encoder samples per part from its tight faces (as many again from the extended ones).
        encoder_width: the encoder's block width; width: the decoder's; code: part code size.
        depth: decoder hidden layers; octaves: Fourier octaves of the box coordinates.
        padding: box padding factor (the reference's 1.125).
        seed: seed of the encoder's sample layout.
    """

    def __init__(
        self,
        parts: BodyParts,
        faces: torch.Tensor,
        template: torch.Tensor,
        *,
        samples: int = 128,
        encoder_width: int = 64,
        width: int = 128,
        code: int = 128,
        depth: int = 4,
        octaves: int = 3,
        padding: float = 1.125,
        seed: int = 0,
    ) -> None:
        super().__init__()
        self.parts, self.padding, self.octaves = parts, padding, octaves
        self.num_vertices = template.shape[0]
        self.config = dict(samples=samples, encoder_width=encoder_width, width=width, code=code, depth=depth,
                           octaves=octaves, padding=padding, seed=seed)  # fmt: skip
        k = parts.num_parts
        ids, bary = _surface_samples(parts, faces.long(), template.double(), samples, seed)
        self.register_buffer("sample_vertices", faces.long()[ids], persistent=False)  # (K, S, 3)
        self.register_buffer("sample_bary", bary.float(), persistent=False)
        tight = torch.cat([torch.ones(samples), torch.zeros(samples)])
        self.register_buffer("sample_tight", tight, persistent=False)
        self.register_buffer("part_joints", parts.joints.clone(), persistent=False)
        self.encoder = PointEncoder(4, encoder_width, code)
        self.bias = nn.Linear(code + k + 3, width)
        self.inp = nn.Linear(3 + 6 * octaves + 7, width, bias=False)
        self.hidden = nn.ModuleList(nn.Linear(width, width) for _ in range(depth - 1))
        self.out = nn.Linear(width, 1)
        self.act = nn.SiLU()
        self.register_buffer("freq", torch.pi * 2.0 ** torch.arange(octaves, dtype=torch.float32), persistent=False)

    def encode(self, vertices: torch.Tensor, transforms: torch.Tensor) -> PartEncoding:
        """Encode posed meshes (B, V, 3) with their posed joint transforms (B, J, 4, 4)."""
        g = transforms[:, self.part_joints]
        rotation, origin = g[..., :3, :3], g[..., :3, 3]
        center, half = part_boxes(self.parts, vertices, rotation, origin, self.padding)
        tri = vertices[:, self.sample_vertices]  # (B, K, S, 3, 3)
        p = torch.einsum("bksic,ksi->bksc", tri, self.sample_bary.to(vertices.dtype))
        local = torch.einsum("bksc,bkcd->bksd", p - origin[:, :, None], rotation)
        u = (local - center[:, :, None]) / half[:, :, None]
        n = torch.linalg.cross(tri[..., 1, :] - tri[..., 0, :], tri[..., 2, :] - tri[..., 0, :])
        n = torch.einsum("bksc,bkcd->bksd", n, rotation)
        n = n / n.norm(dim=-1, keepdim=True).clamp_min(1e-12)
        b, k, s, _ = u.shape
        x = torch.cat([u, self.sample_tight.to(u.dtype).expand(b, k, s)[..., None]], -1)
        z = self.encoder(x.reshape(b * k, s, 4)).view(b, k, -1)
        onehot = torch.eye(k, dtype=z.dtype, device=z.device).expand(b, k, k)
        bias = self.bias(torch.cat([z, onehot, half.log()], -1))
        return PartEncoding(rotation, origin, center, half, bias, local, n)

    def decode(self, u: torch.Tensor, local: torch.Tensor, bias: torch.Tensor) -> torch.Tensor:
        """Logits (N,) of box coordinates ``u`` (N, 3) with local features (N, 7) and first-layer biases (N, W)."""
        a = u[..., None] * self.freq
        h = self.act(self.inp(torch.cat([u, a.sin().flatten(-2), a.cos().flatten(-2), local], -1)) + bias)
        for layer in self.hidden:
            h = h + self.act(layer(h))
        return self.out(h).squeeze(-1)

    def part_logits(self, points: torch.Tensor, enc: PartEncoding) -> torch.Tensor:
        """(B, T, K) logits of every part at world ``points`` (B, T, 3); OUTSIDE where out of its box."""
        u, inside = enc.to_boxes(points)
        b, t, k = inside.nonzero(as_tuple=True)
        u = u[b, t, k]
        logit = self.decode(u, local_features(u, b, k, enc), enc.bias[b, k])
        full = u.new_full(inside.shape, OUTSIDE)
        return full.index_put((b, t, k), logit)

    def forward(self, points: torch.Tensor, enc: PartEncoding) -> torch.Tensor:
        """(B, T) occupancy in [0, 1] of world ``points`` (B, T, 3): the max over parts."""
        return torch.sigmoid(self.part_logits(points, enc).amax(-1))


def default_weights_path():
    """The shipped weights, ``unibody/occupancy/weights/occupancy_v1.pt``."""
    from pathlib import Path

    return Path(__file__).parent / "weights" / "occupancy_v1.pt"
