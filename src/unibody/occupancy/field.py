"""Occupancy of posed unified bodies: queries, self-intersection and collision terms (paper 002 §4-5).

    occ = BodyOccupancy.pretrained()
    out = layer(params, pose)                       # any BodyLayer output on the canonical mesh
    inside = occ.query(points, out)                 # (B, T) in [0, 1]
    loss = occ.self_intersection_loss(out)          # (B,), differentiable w.r.t. the pose
    loss = occ.collision_loss(scene_points, out)    # (B,)

Every call accepts a :class:`~unibody.body.BodyOutput` or the :class:`PartEncoding` of one
(``occ.encode(out)``); encode once when querying the same bodies many times.
"""

from __future__ import annotations

from pathlib import Path

import torch
from torch import nn

from .._checks import check_finite, check_like, check_tensor
from ..body import BodyOutput
from .model import OccupancyNet, PartEncoding, default_weights_path
from .parts import BodyParts

__all__ = ["BodyOccupancy"]

Body = BodyOutput | PartEncoding


class BodyOccupancy(nn.Module):
    """Articulated occupancy of the canonical body (any identity, any pose).

    Args:
        net: the occupancy network (see :meth:`pretrained`).
    """

    def __init__(self, net: OccupancyNet) -> None:
        super().__init__()
        self.net = net
        self.register_buffer("allowed", net.parts.allowed.clone(), persistent=False)

    @classmethod
    def pretrained(cls, path: str | Path | None = None) -> BodyOccupancy:
        """The weights shipped with unibody (or a file written by ``scripts/train_occupancy.py``)."""
        path = Path(path) if path is not None else default_weights_path()
        if not path.exists():
            raise FileNotFoundError(f"path: no occupancy weights at {path}")
        from ..io.weights import read_weights, rebuilding
        from ..rig import Rig

        what = "occupancy weights written by scripts/train_occupancy.py"
        state = read_weights(path, what)
        rig = Rig.canonical()
        with rebuilding(path, what):
            net = OccupancyNet(BodyParts.canonical(), rig.faces, rig.bind_vertices, **state["config"])
            net.load_state_dict(state["model"])
        return cls(net.eval()).requires_grad_(False)

    @property
    def parts(self) -> BodyParts:
        return self.net.parts

    def encode(self, body: BodyOutput) -> PartEncoding:
        """Part frames, boxes and codes of a posed batch (differentiable w.r.t. its vertices)."""
        if isinstance(body, PartEncoding):
            return body
        if not isinstance(body, BodyOutput):
            raise TypeError(f"body: expected a BodyOutput or a PartEncoding, got {type(body).__name__}")
        v = body.vertices
        if v.ndim != 3 or v.shape[1:] != (self.net.num_vertices, 3):
            raise ValueError(
                f"body.vertices: expected (B, {self.net.num_vertices}, 3) on the canonical mesh, got {tuple(v.shape)}"
            )
        check_like(v, self.net.out.weight, "body.vertices", owner="the occupancy model")
        check_finite(v, "body.vertices")
        return self.net.encode(v, body.transforms)

    def _points(self, points: torch.Tensor, enc: PartEncoding, name: str = "points") -> torch.Tensor:
        points = check_tensor(points, name)
        if points.ndim == 2:
            points = points.expand(enc.bias.shape[0], *points.shape)
        b = enc.bias.shape[0]
        if points.ndim != 3 or points.shape[-1] != 3 or points.shape[0] != b:
            raise ValueError(f"{name}: expected (T, 3) or ({b}, T, 3), got {tuple(points.shape)}")
        check_like(points, enc.bias, name, owner="the occupancy model")
        check_finite(points, name)
        return points

    def query(self, points: torch.Tensor, body: Body, *, parts: bool = False) -> torch.Tensor:
        """Occupancy in [0, 1] of world ``points`` (T, 3) or (B, T, 3): (B, T), or per part (B, T, K)."""
        enc = self.encode(body)
        logits = self.net.part_logits(self._points(points, enc), enc)
        return torch.sigmoid(logits if parts else logits.amax(-1))

    def collision_loss(self, points: torch.Tensor, body: Body) -> torch.Tensor:
        """(B,) sum over scene ``points`` (T, 3) or (B, T, 3) of relu(occupancy - 1/2) (paper 002 eq. 10)."""
        return torch.relu(self.query(points, body) - 0.5).sum(-1)

    def self_intersection_loss(
        self,
        body: Body,
        *,
        samples: int = 256,
        vertices: torch.Tensor | None = None,
        threshold: float = 0.5,
        generator: torch.Generator | None = None,
    ) -> torch.Tensor:
        """(B,) volume-aware self-intersection penalty (paper 002 eq. 9).

        Candidates are ``samples`` uniform points in every part's box plus the mesh vertices
        (detached; pass ``vertices`` (B, V, 3) when ``body`` is an encoding), kept where the
        boxes of two parts that may not overlap meet (``parts.allowed``: parent, child and the
        named neighbours excluded). At a candidate where two such parts i and j are both
        occupied (> ``threshold``), the penalty is occ_i + occ_j - 2 ``threshold``, summed over
        pairs and points. A threshold below 1/2 asks for a margin between the parts.
        """
        if not 0.0 < threshold < 1.0:
            raise ValueError(f"threshold: expected a value in (0, 1), got {threshold}")
        enc = self.encode(body)
        if isinstance(body, BodyOutput):
            vertices = body.vertices
        b, k = enc.bias.shape[:2]
        # Drawn where the generator lives (the CPU when there is none: the same samples on any
        # device for a CPU generator), then moved; a CUDA generator draws on its device.
        where = generator.device if generator is not None else torch.device("cpu")
        u = 2 * torch.rand(b, k, samples, 3, generator=generator, dtype=enc.bias.dtype, device=where) - 1
        u = u.to(enc.bias.device)
        local = enc.center[:, :, None] + u * enc.half[:, :, None]
        pts = torch.einsum("bknd,bkcd->bknc", local, enc.rotation) + enc.origin[:, :, None]
        pts = pts.reshape(b, -1, 3)
        if vertices is not None:
            pts = torch.cat([pts, vertices.to(pts)], 1)
        pts = pts.detach()
        allowed = self.allowed.to(pts.dtype)
        with torch.no_grad():
            inside = enc.to_boxes(pts)[1]
            keep = (inside & (inside.to(pts.dtype) @ allowed > 0)).any(-1)
            count = keep.sum(1)
            order = torch.argsort((~keep).to(torch.int8), dim=1, stable=True)[:, : int(count.max())]
            valid = torch.arange(order.shape[1], device=pts.device) < count[:, None]
        pts = torch.gather(pts, 1, order[..., None].expand(-1, -1, 3))
        occ = torch.sigmoid(self.net.part_logits(pts, enc)) * valid[..., None]
        hit = (occ > threshold).to(occ.dtype)
        partners = hit @ allowed  # occupied parts at each point that this part may not overlap
        return (hit * partners * (occ - threshold)).sum((1, 2))

    def extract_mesh(self, body: Body, *, resolution: int = 128, chunk: int = 200_000):
        """Marching-cubes surfaces (scikit-image) of the occupancy at 1/2, one per batch item.

        The grid spans each body's vertex bounding box padded by 5 % per side (needs a
        BodyOutput), or each body's union of part boxes when given an encoding.

        Returns:
            a list of (vertices (n, 3), faces (m, 3) int64) tensors, world frame, on the body's device.
        """
        from skimage.measure import marching_cubes

        if not isinstance(resolution, int) or resolution < 8:
            raise ValueError(f"resolution: expected an int >= 8, got {resolution!r}")
        enc = self.encode(body)
        if isinstance(body, BodyOutput):
            lo, hi = body.vertices.amin(1), body.vertices.amax(1)
        else:
            corners = torch.tensor([[x, y, z] for x in (-1, 1) for y in (-1, 1) for z in (-1, 1)]).to(enc.half)
            local = enc.center[:, :, None] + corners * enc.half[:, :, None]
            world = torch.einsum("bknd,bkcd->bknc", local, enc.rotation) + enc.origin[:, :, None]
            lo, hi = world.flatten(1, 2).amin(1), world.flatten(1, 2).amax(1)
        pad = 0.05 * (hi - lo)
        lo, hi = (lo - pad).detach(), (hi + pad).detach()
        meshes = []
        with torch.no_grad():
            for i in range(enc.bias.shape[0]):
                axes = [torch.linspace(float(lo[i, d]), float(hi[i, d]), resolution) for d in range(3)]
                grid = torch.stack(torch.meshgrid(*axes, indexing="ij"), -1).reshape(-1, 3).to(enc.bias)
                item = PartEncoding(*(getattr(enc, f)[i : i + 1] for f in PartEncoding.__slots__))
                logit = torch.cat([self.net.part_logits(g[None], item).amax(-1)[0] for g in grid.split(chunk)])
                field = logit.clamp(-10.0, 10.0).view(resolution, resolution, resolution).cpu().double().numpy()
                if field.max() <= 0 or field.min() >= 0:
                    meshes.append((grid.new_zeros(0, 3), torch.zeros(0, 3, dtype=torch.long, device=grid.device)))
                    continue
                step = ((hi[i] - lo[i]) / (resolution - 1)).cpu().double().numpy()
                verts, faces, _, _ = marching_cubes(field, level=0.0, spacing=tuple(step))
                verts = torch.from_numpy(verts.copy()).to(grid) + lo[i].to(grid)
                # scikit-image orients faces toward increasing values (inside); flip them to face outward
                faces = torch.from_numpy(faces[:, ::-1].copy()).long().to(grid.device)
                meshes.append((verts, faces))
        return meshes
