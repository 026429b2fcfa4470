"""Pose inversion: posed meshes -> 77 joint rotations and root translation (paper 000 §3.6).

Three solvers, chosen explicitly by :class:`InversionConfig` (never inferred):

``"skeleton"``  SkeletonTransfer on the posed mesh: the fitted world frames are the posed
                joint frames, so local rotations are R_abs,k = F_p^T F_k. One pass, no iteration.
``"analytic"``  hierarchical inverse LBS from that start, parent to child, one tree level at a
                time. For joint k, every other joint's contribution is held at the current
                estimate and subtracted, which leaves w_ik R_k a_ik + (residual) with
                a_ik = R_rest,k^T (v_i - j_rest,k); R_k is the Procrustes polar factor of
                H_k = sum_i w_ik e_i a_ik^T + R_k,cur sum_i w_ik^2 a_ik a_ik^T (e: residual),
                orthogonalised by Newton-Schulz (eq. 8) or, for the ablation, SVD.
                Schedule: ``body_passes`` over body joints, then ``full_passes`` over all.
``"autograd"``  continuous 6D rotations and the translation optimised with Adam through
                FK + LBS with per-region vertex weights, started from ``init``.

Input meshes may be on the canonical topology or on the layer's identity topology (Anny's
native mesh), which is transferred first. Joints that skin no vertex (end joints, eyes) are
unobservable and returned with zero (T-pose-relative) rotation.

Input checks (units, mirroring, foreign or random meshes, absurd coordinates; each refusal a
ValueError naming ``vertices`` and the mesh) and the trimming of outlier vertices for the solve:
docs/body.md ("Input checks"), figures in benchmarks/README.md (``inversion_robust.py``).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Literal, NamedTuple, get_args

import torch
from torch import nn

from .._checks import check_count, check_finite, check_like, check_number, check_shape
from ..body import REST_EXTENT_M, BodyLayer, PreparedIdentity, outside_rest_extent
from ..geometry.kinematics import forward_kinematics
from ..geometry.procrustes import polar_svd
from ..geometry.rotations import matrix_to_axis_angle, matrix_to_rot6d, rot6d_to_matrix
from ..geometry.skinning import lbs_sparse, skin_layout
from ..geometry.sparse import crow_indices, csr
from ..motion import MAX_DISTANCE
from ..regions import REGIONS, dominant_joints, joint_regions
from ._gauss_newton import gauss_newton, gauss_newton_data

__all__ = ["InversionConfig", "InversionResult", "PoseInverter", "PRESETS", "MAX_COORDINATE", "SIZE_BAND", "EDGE_BAND"]

MAX_COORDINATE = MAX_DISTANCE  # m: a coordinate beyond 1e5 is refused (its square stays finite in float32)
SIZE_BAND = (0.2, 5.0)  # accepted size ratio to the identity's rest mesh (random poses, 1 rad std: 0.31-1.44)
EDGE_BAND = (0.5, 2.0)  # accepted median edge-length ratio to the rest mesh (the same poses: 0.97-1.22)
_ABS_SIZE = (0.02, 3.0)  # m, median distance from the centre, without an identity (rest: baby 0.14, large adult 0.70)
_ABS_EDGE = (5e-4, 3e-2)  # m, median edge length, without an identity (baby 1.9 mm, large adult 7.0 mm)
_ABS_RADIUS = 3.0  # m, outlier radius without an identity
_MAX_OUTLIERS = 0.01  # fraction of a mesh's vertices that may be trimmed as outliers
_NUM_SAMPLE, _NUM_EDGES, _NUM_FACES = 257, 512, 512
# Size ratios that name a unit in the message (matched within a factor 1.6).
_UNIT_HINTS = (
    (1000.0, " (millimetres? divide by 1000)"),
    (100.0, " (centimetres? divide by 100)"),
    (1 / 0.0254, " (inches? multiply by 0.0254)"),
    (1 / 0.3048, " (feet? multiply by 0.3048)"),
    (1e-3, " (kilometres? multiply by 1000)"),
)

Method = Literal["skeleton", "analytic", "autograd"]
Init = Literal["analytic", "skeleton", "none"]
Orthogonalization = Literal["newton_schulz", "svd"]


class _Level(NamedTuple):
    """One tree level of the analytic solve (:meth:`PoseInverter._level_data`)."""

    joints: torch.Tensor  # (n,) the solved joints
    verts: torch.Tensor  # (m,) the vertices their subtrees move, joint by joint (slot-major)
    slot: torch.Tensor  # (m,) each vertex's solved joint, 0..n-1
    omega: torch.Tensor  # (m,) each vertex's skinning weight inside that subtree
    all: tuple  # (weights, layout) for lbs_sparse over the vertices' influences
    sub: tuple  # the same, only the influences inside the vertex's subtree
    moved: torch.Tensor  # (k,) the joints inside a solved joint's subtree
    carried: torch.Tensor  # (k,) the slot of that solved joint
    block: int  # vertices per solved joint when every joint has as many, else 0


@dataclass(frozen=True)
class InversionConfig:
    """How to invert. See the module docstring for the methods.

    Attributes:
        method: "skeleton", "analytic" or "autograd".
        orthogonalization: polar factor by "newton_schulz" (default) or "svd" (ablation).
        body_passes, full_passes: analytic schedule (paper default 2 and 1).
        ns_iters: scaled Newton-Schulz iterations per solve (:func:`_newton_schulz_scaled`; 9
            reach the accuracy that 16 plain steps had at the default damping).
        vertices_per_joint: analytic solver: at most this many (seeded sample) vertices per
            joint's subtree enter its Procrustes fit.
        gauss_newton_steps: Gauss-Newton steps over all joints after the analytic solve
            (0: none), on ``gauss_newton_samples`` seeded sample vertices.
        damping: weight of "stay at the current rotation" relative to the data term; keeps
            near-coplanar vertex sets (clavicles) well posed.
        init: start of the autograd solver: "analytic", "skeleton" or "none" (T-pose).
        steps, lr: Adam iterations and learning rate of the autograd solver.
        region_weights: per-vertex loss weights of the autograd solver for the regions
            ``body, hands, feet, head``.
        residuals: whether the result carries the re-posed mesh and the per-vertex error
            (one more FK + LBS over the batch); False leaves them None, for callers that
            want the pose only (motion conversion at full speed).
        corrective_rounds: with a layer that applies pose correctives
            (:mod:`unibody.correctives`), the analytic solve is repeated this many times against
            the meshes less the correctives' displacement at the pose found so far (a fixed
            point: the meshes are LBS plus correctives of their own pose); 0 models plain LBS.
            Layers without correctives ignore it.
    """

    method: Method = "analytic"
    orthogonalization: Orthogonalization = "newton_schulz"
    body_passes: int = 2
    full_passes: int = 1
    ns_iters: int = 9
    vertices_per_joint: int = 128
    gauss_newton_steps: int = 0
    gauss_newton_samples: int = 1500
    damping: float = 3e-3
    init: Init = "analytic"
    steps: int = 100
    lr: float = 1e-3
    region_weights: tuple[float, float, float, float] = (1.0, 1.0, 1.0, 1.0)
    residuals: bool = True
    corrective_rounds: int = 2

    def __post_init__(self) -> None:
        for name, alias in (("method", Method), ("orthogonalization", Orthogonalization), ("init", Init)):
            value, choices = getattr(self, name), get_args(alias)
            if value not in choices:
                raise ValueError(f"{name}: expected one of {', '.join(choices)}, got {value!r}")
        counts = {"body_passes": 0, "full_passes": 0, "ns_iters": 0, "steps": 0, "corrective_rounds": 0}
        counts |= {"gauss_newton_steps": 0, "vertices_per_joint": 1, "gauss_newton_samples": 1}
        for name, low in counts.items():
            check_count(getattr(self, name), name, low)
        check_number(self.damping, "damping")
        check_number(self.lr, "lr", positive=True)
        weights = self.region_weights
        finite = all(isinstance(w, (int, float)) and not isinstance(w, bool) and math.isfinite(w) for w in weights)
        if len(weights) != len(REGIONS) or not finite or min(weights) < 0 or max(weights) == 0:
            raise ValueError(
                f"region_weights: expected {len(REGIONS)} finite non-negative weights, not all 0 "
                f"({', '.join(REGIONS)}), got {weights}"
            )
        if not isinstance(self.residuals, bool):
            raise ValueError(f"residuals: expected True or False, got {self.residuals!r}")


PRESETS: dict[str, InversionConfig] = {
    "fast": InversionConfig(method="skeleton"),
    "analytic": InversionConfig(),
    "refined": InversionConfig(body_passes=1, full_passes=0, gauss_newton_steps=3, gauss_newton_samples=600),
    "svd": InversionConfig(orthogonalization="svd"),
    "accurate": InversionConfig(method="autograd", init="analytic", steps=100, region_weights=(1.0, 4.0, 2.0, 2.0)),
}


@dataclass(frozen=True, slots=True)
class InversionResult:
    """Recovered pose.

    Attributes:
        pose: (B, 77, 3) axis-angle, T-pose-relative local rotations of joints 1..77.
        rotations: (B, 77, 3, 3) the same as matrices.
        transl: (B, 3) m, Hips world position.
        vertices: (B, V, 3) m, the canonical mesh posed with the result; None when the
            config's ``residuals`` is False.
        per_vertex_error: (B, V) m, distance to the target on the canonical topology; None
            when ``residuals`` is False.
        iterations: level solves (analytic) or optimiser steps (autograd) performed.
    """

    pose: torch.Tensor
    rotations: torch.Tensor
    transl: torch.Tensor
    vertices: torch.Tensor | None
    per_vertex_error: torch.Tensor | None
    iterations: int


class PoseInverter(nn.Module):
    """Invert posed meshes of a :class:`BodyLayer`.

    Args:
        layer: the body layer whose rig (and identity topology) the meshes use.
        config: the solver; see :data:`PRESETS`.
    """

    def __init__(self, layer: BodyLayer, config: InversionConfig | None = None) -> None:
        super().__init__()
        if not isinstance(layer, BodyLayer):
            raise TypeError(f"layer: expected a BodyLayer, got {type(layer).__name__}")
        if not isinstance(config, InversionConfig | None):
            hint = f" (PRESETS[{config!r}]?)" if isinstance(config, str) and config in PRESETS else ""
            raise TypeError(f"config: expected an InversionConfig{hint}, got {type(config).__name__}")
        self.layer = layer
        self.config = InversionConfig() if config is None else config
        skin = layer.skinning
        skinned = torch.bincount(skin.joint, minlength=layer.num_joints) > 0
        self.register_buffer("observable", skinned[1:].clone(), persistent=False)
        names = layer.joint_names
        finger = ["Hand" in n and not n.endswith("Hand") for n in names]
        dominant = dominant_joints(skin.vertex, skin.joint, skin.weight, layer.num_vertices, layer.num_joints)
        cap = self.config.vertices_per_joint
        levels = {s: self._level_data(layer, dominant, skinned, finger, s, cap) for s in ("body", "full")}
        # Every level's vertices index one compact set, gathered from the target once per call:
        # the levels' own gathers from the whole mesh each missed the cache (6.6 of ~110 ms at
        # batch 32 on two cores).
        self._solve_verts = torch.cat([lv.verts for scope in levels.values() for lv in scope]).unique()
        compact = torch.full((layer.num_vertices,), -1, dtype=torch.long)
        compact[self._solve_verts] = torch.arange(len(self._solve_verts))
        self._levels = {s: [lv._replace(verts=compact[lv.verts]) for lv in scope] for s, scope in levels.items()}
        self._gn = (
            gauss_newton_data(layer, self.config.gauss_newton_samples) if self.config.gauss_newton_steps else None
        )
        regions = joint_regions(names)[dominant.cpu()]  # a CPU table; the buffer follows the layer
        weights = torch.tensor(self.config.region_weights, dtype=layer.skin_weight.dtype)[regions]
        self.register_buffer("vertex_weight", (weights / weights.mean()).to(layer.skin_weight.device), persistent=False)
        self._init_checks(layer)

    def _init_checks(self, layer: BodyLayer) -> None:
        """Fixed seeded samples for the input checks, and the canonical mesh's vertex adjacency.

        CPU index tensors (moved per call, as the level data): vertex samples of each accepted
        topology, sampled canonical edges and faces, and the CSR adjacency used to trim outliers.
        """
        gen = torch.Generator().manual_seed(0)
        sizes = [layer.num_vertices] + ([layer.topology.num_source_vertices] if layer.topology is not None else [])
        self._sample = {n: torch.randperm(n, generator=gen)[: min(n, _NUM_SAMPLE)].sort().values for n in sizes}
        faces = layer.faces.cpu()
        edges = torch.cat([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]]).sort(dim=1).values.unique(dim=0)
        self._edges = edges[torch.randperm(len(edges), generator=gen)[:_NUM_EDGES].sort().values]
        sample = faces[torch.randperm(len(faces), generator=gen)[:_NUM_FACES]]
        self._faces = sample[torch.argsort(sample.min(1).values)]  # in vertex order: cache-friendly gathers
        both = torch.cat([edges, edges.flip(1)])
        both = both[torch.argsort(both[:, 0] * layer.num_vertices + both[:, 1])]
        self._adj_crow = crow_indices(both[:, 0], layer.num_vertices)
        self._adj_col = both[:, 1].contiguous()

    @staticmethod
    def _level_data(layer: BodyLayer, dominant, skinned, finger, scope: str, cap: int) -> list[_Level]:
        """Per tree level: the solved joints and, for each, vertices its subtree moves.

        A vertex belongs to the subtree of the level-l ancestor of its dominant joint and
        counts with weight omega = its skinning weight inside that subtree. At most ``cap``
        vertices per joint are kept (a fixed seeded sample): a rigid fit needs no more, and
        the solver then never touches the whole mesh inside a level.
        Returns one :class:`_Level` per level, its vertices joint by joint (a block each).
        """
        parents = layer.rig_tree.parents
        depth = {j: d for d, level in enumerate(layer.rig_tree.levels) for j in level}  # the tree's own depths

        def ancestor(j: int, d: int) -> int:
            while depth[j] > d:
                j = parents[j]
            return j if depth[j] == d else -1

        skin = layer.skinning
        sv, sj, sw = (x.cpu() for x in (skin.vertex, skin.joint, skin.weight))
        order = torch.randperm(layer.num_vertices, generator=torch.Generator().manual_seed(0))
        out = []
        for d, level in enumerate(layer.rig_tree.levels[1:], start=1):
            joints = [j for j in level if skinned[j] and (scope == "full" or not finger[j])]
            if not joints:
                continue
            slot_of = {j: i for i, j in enumerate(joints)}
            anc = torch.tensor([slot_of.get(ancestor(j, d), -1) for j in range(len(parents))])
            vert_slot = anc[dominant]
            same = anc[sj] == vert_slot[sv]
            omega = torch.zeros(layer.num_vertices, dtype=sw.dtype).index_add_(0, sv[same], sw[same])
            shuffled = vert_slot[order]
            rank = torch.zeros_like(shuffled)
            for k in range(len(joints)):  # position of each vertex within its joint's shuffled set
                mask = shuffled == k
                rank[mask] = torch.arange(int(mask.sum()))
            verts = order[(shuffled >= 0) & (rank < cap)].sort().values
            verts = verts[torch.sort(vert_slot[verts], stable=True).indices]  # joint by joint
            counts = torch.bincount(vert_slot[verts], minlength=len(joints))
            pos = torch.full((layer.num_vertices,), -1, dtype=torch.long)
            pos[verts] = torch.arange(verts.numel())
            infl = torch.nonzero(pos[sv] >= 0).flatten()
            infl = infl[torch.sort(pos[sv[infl]], stable=True).indices]  # by row, as skin_layout wants
            sub = infl[same[infl]]
            all_layout = skin_layout(pos[sv[infl]], sj[infl], verts.numel(), layer.num_joints)
            sub_layout = skin_layout(pos[sv[sub]], sj[sub], verts.numel(), layer.num_joints)
            out.append(
                _Level(
                    torch.tensor(joints),
                    verts,
                    vert_slot[verts],
                    omega[verts],
                    (sw[infl], all_layout),
                    (sw[sub], sub_layout),
                    torch.nonzero(anc >= 0).flatten(),
                    anc[anc >= 0],
                    int(counts[0]) if bool((counts == counts[0]).all()) else 0,
                )
            )
        return out

    # -- inputs -------------------------------------------------------------------------
    def _canonical(self, vertices: torch.Tensor, rest: torch.Tensor | None) -> tuple[torch.Tensor, torch.Tensor]:
        """Checked canonical-topology meshes (B, V, 3): outliers trimmed (module docstring), and as given.

        ``rest`` is the identity's canonical rest mesh (Bi, V, 3), the reference for the size,
        edge, volume and outlier checks; None uses absolute bounds.
        """
        layer = self.layer
        check_shape(vertices, "B N 3", name="vertices")
        check_like(vertices, layer.tpose_orient, name="vertices", owner="the inverter")
        check_finite(vertices, "vertices")
        n = vertices.shape[1]
        accepted = {layer.num_vertices: "canonical"}
        if layer.topology is not None:
            accepted[layer.topology.num_source_vertices] = layer.topology.name
        if n not in accepted:
            raise ValueError(
                f"vertices: expected {' or '.join(f'{k} ({v})' for k, v in accepted.items())} "
                f"vertices per mesh, got {n}"
            )
        if vertices.shape[0] == 0:
            empty = vertices.new_zeros(0, layer.num_vertices, 3)
            return empty, empty
        # Every gather below (checks, solver samples) would copy a strided mesh again (input
        # checks 65 -> ~15 ms at batch 32, one thread), so copy once, into vertex-major order
        # (V, B, 3), seen as (B, V, 3): the layout of BodyLayer's output, of the skeleton fit's
        # operand (it then makes no copy of its own) and of the posed mesh the residuals compare.
        # Skeleton transfer 1.2-1.4x faster than with a batch-major copy (inversion_speed.py).
        b = vertices.shape[0]
        rows = vertices.transpose(0, 1).contiguous()  # (V, B, 3)
        vertices = rows.transpose(0, 1)
        hi = rows.view(n, 3 * b).amax(0).view(b, 3).amax(1)  # a reduction down rows of poses
        lo = rows.view(n, 3 * b).amin(0).view(b, 3).amin(1)
        reach = torch.maximum(hi, -lo)
        if bool((reach > MAX_COORDINATE).any()):
            b = int(torch.nonzero(reach > MAX_COORDINATE)[0])
            i = int(vertices[b].abs().amax(-1).argmax())
            raise ValueError(
                f"vertices: mesh {b}, vertex {i} is at ({', '.join(f'{float(x):.3g}' for x in vertices[b, i])}), "
                f"beyond +-{MAX_COORDINATE:.0e} m: vertices must be in metres"
            )
        centre, size = self._size(vertices)
        flat = size <= torch.finfo(size.dtype).tiny
        if bool(flat.any()):
            raise _degenerate(int(torch.nonzero(flat)[0]))
        if n != layer.num_vertices:
            vertices = layer.topology(vertices)
            centre = self._size(vertices)[0]
        edge = self._edge(vertices)
        if rest is None:
            ref = None
        else:
            rest_centre, rest_size = self._size(rest)
            ref = (rest_size, self._edge(rest))
        self._check_scale(size, edge, ref, vertices)
        target = self._trim(vertices, centre, rest, lo, hi)
        self._check_flat(_gather(target, self._sample[layer.num_vertices].to(target.device)))
        self._check_mirrored(target, centre, None if rest is None else (rest, rest_centre))
        return target, vertices

    def _size(self, vertices: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Robust centre (B, 3) and size (B,) of meshes: per-axis median of a fixed vertex sample,
        and the median distance of that sample from it (one far vertex moves neither)."""
        pts = _gather(vertices, self._sample[vertices.shape[1]].to(vertices.device))
        centre = pts.median(dim=1).values
        return centre, _distances(pts, centre[:, None]).median(dim=1).values

    @staticmethod
    def _check_scale(size, edge, ref, vertices) -> None:
        """Refuse meshes of the wrong size (units) or whose edges are far too long or short.

        Two ratios to the identity's rest mesh (absolute bands without one): the size (median
        distance from the centre; depends a little on the pose) and the median sampled edge length
        (nearly pose-invariant). A mesh in other units scales both alike; random or reordered
        points keep the size and lengthen the edges.
        """
        if ref is None:
            size_ratio, edge_ratio = size / 0.5, edge / 5e-3  # an adult's, for the message only
            bad_size = (size < _ABS_SIZE[0]) | (size > _ABS_SIZE[1])
            bad_edge = (edge < _ABS_EDGE[0]) | (edge > _ABS_EDGE[1])
        else:
            size_ratio, edge_ratio = size / ref[0], edge / ref[1]
            bad_size = (size_ratio < SIZE_BAND[0]) | (size_ratio > SIZE_BAND[1])
            bad_edge = (edge_ratio < EDGE_BAND[0]) | (edge_ratio > EDGE_BAND[1])
        bad = bad_size | bad_edge
        if not bool(bad.any()):
            return
        b = int(torch.nonzero(bad)[0])
        rs, re = float(size_ratio[b]), float(edge_ratio[b])
        if abs(math.log(re / rs)) < math.log(3.0):  # both scaled alike: other units (the edges know best)
            hint = next((h for f, h in _UNIT_HINTS if abs(math.log(re / f)) < math.log(1.6)), "")
            what = "an adult body" if ref is None else "the identity's rest mesh"
            expected = f"{_ABS_EDGE[0]}-{_ABS_EDGE[1]} m" if ref is None else f"{float(ref[1][b % len(ref[1])]):.3g} m"
            diag = float((vertices[b].amax(0) - vertices[b].amin(0)).norm())
            raise ValueError(
                f"vertices: mesh {b} is about {re:.3g}x the size of {what} (median sampled edge "
                f"{float(edge[b]):.3g}, expected {expected}; bounding-box diagonal {diag:.4g}): vertices "
                f"must be in metres{hint or '; or is it the wrong identity, or not a body?'}"
            )
        expected = f"{_ABS_EDGE[0]}-{_ABS_EDGE[1]} m" if ref is None else f"{float(ref[1][b % len(ref[1])]):.3g} m"
        raise ValueError(
            f"vertices: mesh {b} is not a body mesh in this vertex order: the median of {_NUM_EDGES} "
            f"sampled edges is {float(edge[b]):.3g} m long, expected {expected} (a posed body's stays "
            f"near its rest length) while its size is {rs:.3g}x the expected: random, reordered or very "
            "noisy points, or the wrong identity?"
        )

    def _trim(self, target, centre, rest, lo, hi) -> torch.Tensor:
        """Replace vertices farther than the outlier radius r from ``centre`` by the mean of their
        inlier neighbours (outward, ring by ring); refuse a mesh with more than 1 % of them.

        ``lo``, ``hi`` (B,): the smallest and largest coordinate of each mesh (any axis; the
        transfer to the canonical mesh interpolates, so they bound it too). A mesh whose every
        coordinate lies within [min_k c_k - r / sqrt(3), max_k c_k + r / sqrt(3)] (c the centre)
        is skipped: two flat reductions instead of a pass over every vertex. Such a mesh has no
        vertex farther than r + sqrt(3) (max_k c_k - min_k c_k) from the centre: the test is exact
        for outliers beyond that (a body near the origin: r + 1.6 m), and a closer outlier is
        trimmed whenever any vertex of its mesh leaves that box.
        """
        if rest is None:
            radius = target.new_full((1,), _ABS_RADIUS)
        else:
            radius = (rest.amax(1) - rest.amin(1)).norm(dim=-1)  # the rest bounding-box diagonal, (Bi,)
        # A vertex farther than r from the centre has a coordinate more than r / sqrt(3) from the
        # centre's (the converse bound is in the docstring).
        box = radius / math.sqrt(3.0)
        maybe = (hi > centre.amax(-1) + box) | (lo < centre.amin(-1) - box)
        frames = torch.nonzero(maybe).flatten()
        if frames.numel() == 0:
            return target
        radius = radius.expand(target.shape[0])[frames]
        sub = target[frames]
        far = _distances(sub, centre[frames, None]) > radius[:, None]
        count = far.sum(1)
        limit = int(_MAX_OUTLIERS * target.shape[1])
        if bool((count > limit).any()):
            k = int(torch.nonzero(count > limit)[0])
            raise ValueError(
                f"vertices: mesh {int(frames[k])} has {int(count[k])} of {target.shape[1]} vertices more than "
                f"{float(radius[k]):.2f} m from the body's centre (at most {limit} are trimmed as outliers): "
                "not one body in metres?"
            )
        if not bool(far.any()):
            return target
        return target.index_copy(0, frames, self._fill(sub, far, centre[frames]))

    def _fill(self, pts: torch.Tensor, far: torch.Tensor, centre: torch.Tensor) -> torch.Tensor:
        """``pts`` (b, V, 3) with the ``far`` (b, V) vertices set to their inlier neighbours' mean."""
        b, v, _ = pts.shape
        dev, dtype = pts.device, pts.dtype
        col = self._adj_col.to(dev)
        adj = csr(self._adj_crow.to(dev), col, torch.ones(col.numel(), dtype=dtype, device=dev), (v, v))
        good = ~far
        x = torch.where(good[..., None], pts, 0.0)
        for _ in range(32):  # a ring per pass; 1 % of the vertices is never more than a few rings deep
            if bool(good.all()):
                break
            stacked = torch.cat([x.permute(1, 0, 2).reshape(v, 3 * b), good.T.to(dtype)], dim=1)
            agg = adj @ stacked
            sums = agg[:, : 3 * b].reshape(v, b, 3).transpose(0, 1)
            cnt = agg[:, 3 * b :].T
            new = ~good & (cnt > 0)
            x = torch.where(new[..., None], sums / cnt.clamp_min(1.0)[..., None], x)
            good = good | new
        return torch.where(good[..., None], x, centre[:, None])  # unreachable vertices: the centre

    @staticmethod
    def _check_flat(pts: torch.Tensor) -> None:
        """Refuse meshes whose (sampled, outlier-free) points are coincident, collinear or coplanar."""
        x = pts - pts.mean(1, keepdim=True)
        cov = x.transpose(1, 2) @ x / x.shape[1]
        try:
            ev = torch.linalg.eigvalsh(cov)
        except torch.linalg.LinAlgError as e:  # finite, bounded input: should not happen
            raise ValueError(f"vertices: the meshes' spread could not be measured ({e})") from None
        # Centred moments round at ~eps relative to the spread: a body's thinnest axis is
        # ~1e-2 of the trace, a plane's is 0, so 100 eps separates them in float32 and float64.
        flat = ev[:, 0] <= 100 * torch.finfo(ev.dtype).eps * ev.sum(-1).clamp_min(torch.finfo(ev.dtype).tiny)
        if bool(flat.any()):
            raise _degenerate(int(torch.nonzero(flat)[0]))

    def _edge(self, mesh: torch.Tensor) -> torch.Tensor:
        """(B,) median length of the sampled canonical edges."""
        e = self._edges.to(mesh.device)
        return _distances(_gather(mesh, e[:, 0]), _gather(mesh, e[:, 1])).median(dim=1).values

    def _volume(self, mesh: torch.Tensor, centre: torch.Tensor) -> torch.Tensor:
        """(B,) signed volume of the sampled faces' tetrahedra about ``centre`` (sign: orientation)."""
        f = self._faces.to(mesh.device)
        (ax, ay, az), (bx, by, bz), (cx, cy, cz) = (
            (_gather(mesh, f[:, k]) - centre[:, None]).unbind(-1) for k in range(3)
        )
        det = ax * (by * cz - bz * cy) + ay * (bz * cx - bx * cz) + az * (bx * cy - by * cx)
        return det.sum(1) / 6

    def _check_mirrored(self, target, centre, rest) -> None:
        volume = self._volume(target, centre)
        ref = volume.new_ones(1) if rest is None else self._volume(*rest)
        mirrored = volume * ref.sign() <= 0
        if bool(mirrored.any()):
            b = int(torch.nonzero(mirrored)[0])
            raise ValueError(
                f"vertices: mesh {b} is mirrored (left and right swapped): its signed volume is "
                f"{float(volume[b] / ref[b % len(ref)]):.2f}x the identity's rest mesh's, a body's is "
                "positive; negate one axis to undo the mirroring"
            )

    # -- solvers ------------------------------------------------------------------------
    def _skeleton_init(self, target: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Absolute local rotations (B, J, 3, 3) and Hips position (B, 3) from SkeletonTransfer."""
        frames, joints = self.layer.skeleton.fit(target)
        parents = self.layer.parents
        local = frames[:, parents].transpose(-1, -2) @ frames
        local = torch.cat([frames[:, :1], local[:, 1:]], dim=1)
        return self._zero_unobservable(local), joints[:, 1]

    def _zero_unobservable(self, local: torch.Tensor, keep: torch.Tensor | None = None) -> torch.Tensor:
        """Set unobservable joints (or all but ``keep``) to the zero T-pose-relative rotation."""
        o, parents = self.layer.tpose_orient, self.layer.parents
        tpose = (o[parents[1:]].transpose(-1, -2) @ o[1:]).expand_as(local[:, 1:])
        keep = (self.observable if keep is None else keep)[None, :, None, None]
        return torch.cat([local[:, :1], torch.where(keep, local[:, 1:], tpose)], dim=1)

    def _local_coords(self, prepared: PreparedIdentity) -> tuple[torch.Tensor, torch.Tensor]:
        """Per influence w_ik a_ik (Bi, nnz, 3) and per joint sum_i w_ik^2 a a^T (Bi, J, 3, 3)."""
        layer = self.layer
        skin = layer.skinning
        v, j, w = skin.vertex, skin.joint, skin.weight
        a = (
            prepared.rest_rotations[:, j].transpose(-1, -2)
            @ (prepared.rest_vertices[:, v] - prepared.rest_joints[:, j])[..., None]
        ).squeeze(-1)
        wa = w[:, None] * a
        s = a.new_zeros(a.shape[0], layer.num_joints, 3, 3).index_add_(1, j, wa[..., :, None] * wa[..., None, :])
        return wa, s

    def _polar(self, h: torch.Tensor) -> torch.Tensor:
        if self.config.orthogonalization == "svd":
            return polar_svd(h)
        # The damping bounds sigma_min(h) / sigma_max(h) below by ~lambda / (1 + lambda);
        # /sqrt(3) for the Frobenius normalisation; floored so lambda = 0 still iterates.
        lam = self.config.damping
        return _newton_schulz_scaled(h, self.config.ns_iters, max(lam / (math.sqrt(3.0) * (1 + lam)), 1e-4))

    def _analytic(self, prepared, target, local, transl) -> tuple[torch.Tensor, torch.Tensor, int]:
        """Parent-to-child subtree Procrustes (see the module docstring).

        FK runs once: solving level l rotates each solved joint's subtree rigidly (by delta
        about the joint; the Hips also translate), so the world frames and skinning transforms
        of every joint are updated by that rigid motion instead of a new FK pass per level.
        """
        layer, cfg = self.layer, self.config
        dev = target.device
        eye = torch.eye(3, dtype=target.dtype, device=dev)
        schedule = [self._levels["body"]] * cfg.body_passes + [self._levels["full"]] * cfg.full_passes
        solves = 0
        solved = self._solve_verts.to(dev)
        rest = prepared.rest_vertices.index_select(1, solved)
        target = _gather(target, solved).contiguous()
        g_rot, g_pos, mats = layer.skin_transforms(prepared, local, transl)
        # [world frame | skinning transform] per joint, (B, J, 3, 8): one rigid update per level.
        frames = torch.cat([g_rot, g_pos[..., None], mats], dim=-1)
        for levels in schedule:
            for level in levels:
                (w_all, all_layout), (w_sub, sub_layout) = level.all, level.sub
                joints, verts, slot, omega, moved, carried = (
                    x.to(dev) for x in (level.joints, level.verts, level.slot, level.omega, level.moved, level.carried)
                )
                mats = frames[..., 4:]
                rest_s = rest.index_select(1, verts)
                p = lbs_sparse(rest_s, mats, w_all.to(dev, rest.dtype), all_layout.to(dev))
                t = target.index_select(1, verts)
                g_at = frames[..., 3].index_select(1, joints)
                root = bool(joints[0] == 1)
                if root:  # the Hips move every vertex: a rigid fit with translation about centroids
                    ct = t.mean(1, keepdim=True)
                    cp = p.mean(1, keepdim=True)
                    tq, pq = t - ct, p - cp
                else:
                    # Rotating joint k by delta about its position g moves the subtree part s_i of
                    # a vertex (weight omega_i) and nothing else: p_i = n_i + delta (s_i - omega_i g)
                    # + omega_i g. The exact fit of delta is the polar factor of sum r q^T.
                    s_part = lbs_sparse(rest_s, mats, w_sub.to(dev, rest.dtype), sub_layout.to(dev))
                    pq = s_part - omega[:, None] * g_at.index_select(1, slot)
                    tq = t - p + pq
                b, n, c = tq.shape[0], joints.numel(), level.block
                if c:  # each joint's vertices are one block: sum q r^T per block as a batched product
                    h = tq.view(b, n, c, 3).transpose(-1, -2) @ pq.view(b, n, c, 3)
                    spread = pq.square().sum(-1).view(b, n, c).sum(-1)
                else:  # joints with unequal vertex counts (a large vertices_per_joint)
                    h = tq.new_zeros(b, n, 3, 3).index_add_(1, slot, tq[..., :, None] * pq[..., None, :])
                    spread = tq.new_zeros(b, n).index_add_(1, slot, pq.square().sum(-1))
                # Damping towards the current rotation, lambda * sum |q|^2 * I: keeps
                # collinear subtrees (finger chains) and empty ones (delta = I) well posed.
                h = h + cfg.damping * spread[..., None, None] * eye
                # Two plain Newton-Schulz steps after the solve make delta a rotation to rounding
                # (the scaled run stops at ~1e-4), so the composed frames do not drift.
                delta = _newton_schulz_scaled(self._polar(torch.where((spread > 0)[..., None, None], h, eye)), 2)
                # The rigid motion x -> delta x + e of each solved subtree: about the joint, or
                # for the Hips onto the fitted translation.
                if root:
                    transl = (ct - (delta @ (cp - g_at)[..., None]).squeeze(-1))[:, 0]
                    e = transl[:, None] - (delta @ g_at[..., None]).squeeze(-1)
                else:
                    e = g_at - (delta @ g_at[..., None]).squeeze(-1)
                # Only the solved subtrees' frames move (the Hips': every joint's).
                moved_frames = delta.index_select(1, carried) @ frames.index_select(1, moved)
                shift = e.index_select(1, carried)
                moved_frames[..., 3] += shift  # the bmm's own output: no copy, no autograd conflict
                moved_frames[..., 7] += shift
                frames = frames.index_copy(1, moved, moved_frames)
                solves += 1
        g_rot = frames[..., :3]
        parents = layer.parents
        local = torch.cat([g_rot[:, :1], g_rot[:, parents[1:]].transpose(-1, -2) @ g_rot[:, 1:]], dim=1)
        # Each level's delta is orthogonal only to the Newton-Schulz tolerance (~1e-6) and the
        # products compound it; project once so the returned pose reproduces the returned mesh.
        # Two plain Newton-Schulz steps from that near-rotation reach rounding, as the SVD polar
        # does, at a fraction of its time (3.2 ms for 32 x 78 matrices on two cores).
        return self._zero_unobservable(_newton_schulz_scaled(local, 2)), transl, solves

    def _autograd(self, prepared, target, local, transl) -> tuple[torch.Tensor, torch.Tensor, int]:
        if torch.is_inference_mode_enabled():
            raise RuntimeError("method 'autograd' needs gradients: call invert() outside torch.inference_mode()")
        cfg = self.config
        prepared = prepared.detach()
        target = target.detach()
        r6 = matrix_to_rot6d(local[:, 1:].detach()).requires_grad_(True)
        t = transl.detach().clone().requires_grad_(True)
        opt = torch.optim.Adam([r6, t], lr=cfg.lr)
        sched = torch.optim.lr_scheduler.CosineAnnealingLR(opt, max(cfg.steps, 1))
        root = local[:, :1].detach()
        best_r6, best_t = r6.detach().clone(), t.detach().clone()
        best = torch.full((r6.shape[0],), float("inf"), dtype=r6.dtype, device=r6.device)
        with torch.enable_grad():
            for _ in range(cfg.steps + 1):
                opt.zero_grad(set_to_none=True)
                rot = torch.cat([root, rot6d_to_matrix(r6)], dim=1)
                _, _, pred = self.layer.skin_local(prepared, rot, t)
                per_frame = (self.vertex_weight * (pred - target).square().sum(-1)).mean(1)
                # Keep each frame's best iterate: Adam's steps need not decrease the loss.
                better = per_frame.detach() < best
                best = torch.where(better, per_frame.detach(), best)
                best_r6 = torch.where(better[:, None, None], r6.detach(), best_r6)
                best_t = torch.where(better[:, None], t.detach(), best_t)
                per_frame.sum().backward()
                opt.step()
                sched.step()
        rot = torch.cat([root, rot6d_to_matrix(best_r6)], dim=1)
        return self._zero_unobservable(rot), best_t, cfg.steps

    def estimate_identity(self, vertices: torch.Tensor) -> PreparedIdentity:
        """Rest shapes of unknown identities from posed meshes (the "identity unknown" path).

        SkeletonTransfer on the posed mesh gives the posed skeleton; its bones are re-posed
        into the T-pose, and the mesh is un-posed by inverting each vertex's blended skinning
        transform. The result is a T-pose rest shape on which the skeleton is fitted again.

        Args:
            vertices: (B, V, 3) canonical or (B, Vs, 3) identity-topology posed meshes.

        Returns:
            PreparedIdentity of batch B.
        """
        layer = self.layer
        target, _ = self._canonical(vertices, None)
        b = target.shape[0]
        if b == 0:
            z = layer.tpose_orient.new_zeros
            j = layer.num_joints
            return PreparedIdentity(z(0, layer.num_vertices, 3), z(0, j, 3, 3), z(0, j, 3), z(0, j, 3))
        frames, joints = layer.skeleton.fit(target)
        parents = layer.parents
        offsets = (frames[:, parents].transpose(-1, -2) @ (joints - joints[:, parents])[..., None]).squeeze(-1)
        offsets = torch.cat([offsets[:, :1], joints[:, 1:2], offsets[:, 2:]], dim=1)
        o = layer.tpose_orient
        local = torch.cat([o[:1], o[parents[1:]].transpose(-1, -2) @ o[1:]]).expand(b, -1, -1, -1)
        rest_rot, rest_pos = forward_kinematics(layer.rig_tree, local, offsets)
        skin_rot = frames @ rest_rot.transpose(-1, -2)
        skin_t = joints - (skin_rot @ rest_pos[..., None]).squeeze(-1)
        mats = torch.cat([skin_rot, skin_t[..., None]], dim=-1)  # (B, J, 3, 4)
        w = layer.skinning.matrix()
        blended = (w @ mats.permute(1, 0, 2, 3).reshape(layer.num_joints, -1)).view(-1, b, 3, 4).transpose(0, 1)
        rest, info = torch.linalg.solve_ex(blended[..., :3], target - blended[..., 3])
        bad = (info != 0).any(-1) | ~torch.isfinite(rest).all(-1).all(-1)
        if bool(bad.any()):
            raise ValueError(
                f"vertices: mesh {int(torch.nonzero(bad)[0])} cannot be un-posed (a blended skinning "
                "transform is singular): not a body mesh?"
            )
        # Each vertex is un-posed on its own, so vertices far off the body stay far off it; name the
        # input, not the rest mesh prepare_rest would blame for it (as "not in metres").
        far = outside_rest_extent(rest)
        if far is not None:
            lo, hi = REST_EXTENT_M
            raise ValueError(
                f"vertices: mesh {far[0]} un-poses to a rest shape {far[1]:.3g} m across, outside the "
                f"[{lo:g}, {hi:g}] m of a body: vertices far off the body (outliers), or not a body mesh in metres?"
            )
        return layer.prepare_rest(rest)

    # -- entry point --------------------------------------------------------------------
    def invert(self, vertices: torch.Tensor, prepared: PreparedIdentity) -> InversionResult:
        """Recover the pose of posed meshes of a known identity.

        Args:
            vertices: (B, V, 3) canonical or (B, Vs, 3) identity-topology meshes, metres.
            prepared: the identity (batch 1 or B), from ``layer.prepare_identity``.

        Returns:
            InversionResult.
        """
        if not isinstance(prepared, PreparedIdentity):
            raise TypeError(f"prepared: expected a PreparedIdentity, got {type(prepared).__name__}")
        check_shape(vertices, "B N 3", name="vertices")
        b = vertices.shape[0]
        if prepared.batch_size not in (1, b):
            raise ValueError(f"prepared: identity batch {prepared.batch_size} must be 1 or the mesh batch {b}")
        target, given = self._canonical(vertices, prepared.rest_vertices)
        if b == 0:
            return self._empty(target)
        try:
            result = self._solve(target, prepared, given)
        except torch.linalg.LinAlgError as e:  # never a raw linear-algebra error for the caller
            raise ValueError(f"vertices: the pose solve failed numerically ({e}); are these body meshes?") from None
        bad = ~(torch.isfinite(result.rotations).all((-1, -2, -3)) & torch.isfinite(result.transl).all(-1))
        if bool(bad.any()):
            raise ValueError(
                f"vertices: the pose solve of mesh {int(torch.nonzero(bad)[0])} gave non-finite values; "
                "are these body meshes?"
            )
        return result

    def _empty(self, target: torch.Tensor) -> InversionResult:
        """The result of a batch of 0 meshes, shaped as any other."""
        z, j, v = target.new_zeros, self.layer.num_joints - 1, self.layer.num_vertices
        res = self.config.residuals
        return InversionResult(
            z(0, j, 3), z(0, j, 3, 3), z(0, 3), z(0, v, 3) if res else None, z(0, v) if res else None, 0
        )

    def _solve(self, target: torch.Tensor, prepared: PreparedIdentity, given: torch.Tensor) -> InversionResult:
        cfg = self.config
        local, transl = self._skeleton_init(target)
        iterations = 0
        rounds = cfg.corrective_rounds if self.layer.correctives is not None else 0
        offset = None
        if cfg.method == "analytic" or (cfg.method == "autograd" and cfg.init == "analytic"):
            for r in range(rounds + 1):
                if r:  # the meshes less the correctives of the pose found so far
                    offset = self._corrective_offset(prepared, local, transl)
                local, transl, n = self._analytic(
                    prepared, target if offset is None else target - offset, local, transl
                )
                iterations += n
                if self._gn is not None:
                    local, transl = gauss_newton(
                        self.layer,
                        self._gn,
                        prepared,
                        target if offset is None else target - offset,
                        local,
                        transl,
                        cfg.gauss_newton_steps,
                    )
                    local = self._zero_unobservable(polar_svd(local))
        if cfg.method == "autograd":
            if cfg.init == "none":
                local = self._zero_unobservable(local, keep=torch.zeros_like(self.observable))
                transl = target.mean(1)
            local, transl, iterations = self._autograd(prepared, target, local, transl)
        rel = self.layer.to_relative(local[:, 1:])
        pred = error = None
        if cfg.residuals:
            _, _, pred = self.layer.skin_local(prepared, local, transl)
            if offset is not None:  # re-posed as the layer poses: with its correctives
                pred = pred + self._corrective_offset(prepared, local, transl)
            error = _distances(pred, given)
        return InversionResult(matrix_to_axis_angle(rel), rel, transl, pred, error, iterations)

    def _corrective_offset(self, prepared: PreparedIdentity, local: torch.Tensor, transl: torch.Tensor) -> torch.Tensor:
        """(B, V, 3) what the layer's correctives add to LBS at absolute local rotations ``local`` (B, J, 3, 3)."""
        with torch.no_grad():
            args = (prepared, local[:, 1:].contiguous())
            on = self.layer.pose(*args, transl=transl, absolute=True, check=False, correctives=True).vertices
            off = self.layer.pose(*args, transl=transl, absolute=True, check=False, correctives=False).vertices
            return on - off


def _newton_schulz_scaled(h: torch.Tensor, iters: int, lower: float | None = None) -> torch.Tensor:
    """Polar factor of ``h`` (..., 3, 3) by Newton-Schulz with a scaling per step (paper 000 eq. 8).

    X <- 3/2 a X - 1/2 a^3 X X^T X from X = h / |h|_F, so the singular values start in
    [``lower``, 1]. With a = sqrt(3 / (1 + l + l^2)) every singular value in [l, 1] maps into
    [l', 1], l' = 3/2 a l - 1/2 a^3 l^3 (the scaled cubic equioscillates on the interval; Chen &
    Chow 2014): the smallest grow ~2.6x per step instead of 1.5x, so from l = 1.7e-3 (the
    default damping) 9 steps reach 1 - l = 2e-4 where the plain iteration needs 17. A singular
    value below ``lower`` still converges, at up to 1.5x per step. ``lower=None``: ``h`` is
    already near-orthogonal; plain steps (a = 1), no normalisation. One batched matmul and one
    ``baddbmm`` per step (the 3x3 products are dispatch-bound on CPU).
    """
    shape = h.shape
    x = h.reshape(-1, 3, 3)
    if lower is not None:
        norm = x.square().sum((-1, -2)).sqrt().clamp_min(torch.finfo(h.dtype).tiny)
        x = x / norm[:, None, None]
    low = 1.0 if lower is None else lower
    for _ in range(iters):
        a = math.sqrt(3.0 / (1.0 + low + low * low))
        x = torch.baddbmm(x, x @ x.transpose(-1, -2), x, beta=1.5 * a, alpha=-0.5 * a**3)
        low = min(1.5 * a * low - 0.5 * a**3 * low**3, 1.0)
    return x.reshape(shape)


def _degenerate(b: int) -> ValueError:
    return ValueError(
        f"vertices: mesh {b} is degenerate (its points are coincident, collinear or coplanar); "
        "a posed body spans three dimensions"
    )


def _gather(mesh: torch.Tensor, index: torch.Tensor) -> torch.Tensor:
    """Vertices ``index`` (n,) of meshes (B, V, 3) as (B, n, 3), in either storage layout: a
    vertex-major mesh is gathered row by row (``index_select`` over its second axis would copy
    the whole mesh into batch-major order first)."""
    if mesh.stride(0) < mesh.stride(1):
        return mesh.transpose(0, 1).index_select(0, index).transpose(0, 1)
    return mesh.index_select(1, index)


def _distances(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """|a - b| over the last axis of size 3 (~2x faster than ``norm(dim=-1)`` on CPU).

    Operands of different layouts (a vertex-major posed mesh against a batch-major input) are
    made contiguous first: a subtraction across the two layouts took ~3.5 ms at 32 x 18,056 x 3
    on two cores, the copy and a contiguous one ~1 ms.
    """
    if a.stride() != b.stride():
        a, b = a.contiguous(), b.contiguous()
    d = a - b
    x, y, z = d.unbind(-1)
    return (x * x).addcmul_(y, y).addcmul_(z, z).sqrt_()
