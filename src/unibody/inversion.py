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
"""

from __future__ import annotations

from dataclasses import dataclass, fields
from typing import Literal, get_args

import torch
from torch import nn

from ._checks import check_finite, check_like, check_shape
from ._gauss_newton import gauss_newton, gauss_newton_data
from .body import BodyLayer, PreparedIdentity
from .geometry.kinematics import forward_kinematics
from .geometry.procrustes import newton_schulz, polar_svd
from .geometry.rotations import matrix_to_axis_angle, matrix_to_rot6d, rot6d_to_matrix
from .geometry.skinning import lbs_sparse, skin_layout
from .geometry.sparse import csr
from .regions import REGIONS, dominant_joints, joint_regions

__all__ = ["InversionConfig", "InversionResult", "PoseInverter", "PRESETS"]

Method = Literal["skeleton", "analytic", "autograd"]
Init = Literal["analytic", "skeleton", "none"]
Orthogonalization = Literal["newton_schulz", "svd"]


@dataclass(frozen=True)
class InversionConfig:
    """How to invert. See the module docstring for the methods.

    Attributes:
        method: "skeleton", "analytic" or "autograd".
        orthogonalization: polar factor by "newton_schulz" (default) or "svd" (ablation).
        body_passes, full_passes: analytic schedule (paper default 2 and 1).
        ns_iters: Newton-Schulz iterations per solve.
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
    """

    method: Method = "analytic"
    orthogonalization: Orthogonalization = "newton_schulz"
    body_passes: int = 2
    full_passes: int = 1
    ns_iters: int = 16
    vertices_per_joint: int = 128
    gauss_newton_steps: int = 0
    gauss_newton_samples: int = 1500
    damping: float = 3e-3
    init: Init = "analytic"
    steps: int = 100
    lr: float = 1e-3
    region_weights: tuple[float, float, float, float] = (1.0, 1.0, 1.0, 1.0)
    residuals: bool = True

    def __post_init__(self) -> None:
        for name, alias in (("method", Method), ("orthogonalization", Orthogonalization), ("init", Init)):
            value, choices = getattr(self, name), get_args(alias)
            if value not in choices:
                raise ValueError(f"{name}: expected one of {', '.join(choices)}, got {value!r}")
        for name in ("body_passes", "full_passes", "ns_iters", "steps"):
            if getattr(self, name) < 0:
                raise ValueError(f"{name}: expected >= 0, got {getattr(self, name)}")
        if len(self.region_weights) != len(REGIONS) or min(self.region_weights) < 0:
            raise ValueError(
                f"region_weights: expected {len(REGIONS)} non-negative weights "
                f"({', '.join(REGIONS)}), got {self.region_weights}"
            )


PRESETS: dict[str, InversionConfig] = {
    "fast": InversionConfig(method="skeleton"),
    "analytic": InversionConfig(),
    "refined": InversionConfig(gauss_newton_steps=3),
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
        self.layer = layer
        self.config = InversionConfig() if config is None else config
        joint_of = layer._skin_joint
        skinned = torch.bincount(joint_of, minlength=layer.num_joints) > 0
        self.register_buffer("observable", skinned[1:].clone(), persistent=False)
        names = layer.joint_names
        finger = ["Hand" in n and not n.endswith("Hand") for n in names]
        dominant = dominant_joints(
            layer._skin_vertex, layer._skin_joint, layer.skin_weight, layer.num_vertices, layer.num_joints
        )
        cap = self.config.vertices_per_joint
        self._levels = {s: self._level_data(layer, dominant, skinned, finger, s, cap) for s in ("body", "full")}
        self._gn = (
            gauss_newton_data(layer, self.config.gauss_newton_samples) if self.config.gauss_newton_steps else None
        )
        regions = joint_regions(names)[dominant]
        weights = torch.tensor(self.config.region_weights, dtype=layer.skin_weight.dtype)[regions]
        self.register_buffer("vertex_weight", weights / weights.mean(), persistent=False)

    @staticmethod
    def _level_data(
        layer: BodyLayer, dominant, skinned, finger, scope: str, cap: int
    ) -> list[tuple[torch.Tensor, ...]]:
        """Per tree level: the solved joints and, for each, vertices its subtree moves.

        A vertex belongs to the subtree of the level-l ancestor of its dominant joint and
        counts with weight omega = its skinning weight inside that subtree. At most ``cap``
        vertices per joint are kept (a fixed seeded sample): a rigid fit needs no more, and
        the solver then never touches the whole mesh inside a level.
        Returns ``[(joints (n,), verts (m,), slot (m,), omega (m,), all, sub), ...]`` where
        ``all`` and ``sub`` are (weights, layout) pairs for :func:`lbs_sparse` over the sampled
        vertices' influences: all of them, and only those inside the vertex's subtree.
        """
        parents = layer.rig_tree.parents
        depth = [0] * len(parents)
        for j in range(1, len(parents)):
            depth[j] = depth[parents[j]] + 1

        def ancestor(j: int, d: int) -> int:
            while depth[j] > d:
                j = parents[j]
            return j if depth[j] == d else -1

        sv, sj, sw = (x.cpu() for x in (layer._skin_vertex, layer._skin_joint, layer.skin_weight))
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
            pos = torch.full((layer.num_vertices,), -1, dtype=torch.long)
            pos[verts] = torch.arange(verts.numel())
            infl = torch.nonzero(pos[sv] >= 0).flatten()
            sub = torch.nonzero((pos[sv] >= 0) & same).flatten()
            all_layout = skin_layout(pos[sv[infl]], sj[infl], verts.numel(), layer.num_joints)
            sub_layout = skin_layout(pos[sv[sub]], sj[sub], verts.numel(), layer.num_joints)
            out.append(
                (
                    torch.tensor(joints),
                    verts,
                    vert_slot[verts],
                    omega[verts],
                    (sw[infl], all_layout),
                    (sw[sub], sub_layout),
                )
            )
        return out

    # -- inputs -------------------------------------------------------------------------
    def _canonical(self, vertices: torch.Tensor) -> torch.Tensor:
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
        mean = vertices.mean(1)
        cov = vertices.transpose(1, 2) @ vertices / n - mean[:, :, None] * mean[:, None, :]
        ev = torch.linalg.eigvalsh(cov)
        # Uncentred moments round at ~eps relative to the spread: a body's thinnest axis is
        # ~1e-2 of the trace, a plane's is 0, so 100 eps separates them in float32 and float64.
        flat = ev[:, 0] <= 100 * torch.finfo(ev.dtype).eps * ev.sum(-1).clamp_min(torch.finfo(ev.dtype).tiny)
        if bool(flat.any()):
            b = int(torch.nonzero(flat)[0])
            raise ValueError(
                f"vertices: mesh {b} is degenerate (its points are coincident, collinear or "
                "coplanar); a posed body spans three dimensions"
            )
        if n != layer.num_vertices:
            vertices = layer.topology(vertices)
        return vertices

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
        v, j, w = layer._skin_vertex, layer._skin_joint, layer.skin_weight
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
        return newton_schulz(h, iters=self.config.ns_iters)

    def _analytic(self, prepared, target, local, transl) -> tuple[torch.Tensor, torch.Tensor, int]:
        """Parent-to-child subtree Procrustes (see the module docstring)."""
        layer, cfg = self.layer, self.config
        dev = target.device
        eye = torch.eye(3, dtype=target.dtype, device=dev)
        schedule = [self._levels["body"]] * cfg.body_passes + [self._levels["full"]] * cfg.full_passes
        solves = 0
        rest = prepared.rest_vertices
        for levels in schedule:
            for joints, verts, slot, omega, (w_all, all_layout), (w_sub, sub_layout) in levels:
                joints, verts, slot, omega = (x.to(dev) for x in (joints, verts, slot, omega))
                g_rot, g_pos, mats = layer.skin_transforms(prepared, local, transl)
                rest_s = rest[:, verts]
                p = lbs_sparse(rest_s, mats, w_all.to(dev, rest.dtype), all_layout.to(dev))
                t = target[:, verts]
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
                    g = omega[:, None] * g_pos[:, joints][:, slot]
                    pq = s_part - g
                    tq = t - p + pq
                n = joints.numel()
                h = tq.new_zeros(tq.shape[0], n, 3, 3).index_add_(1, slot, tq[..., :, None] * pq[..., None, :])
                # Damping towards the current rotation, lambda * sum |q|^2 * I: keeps
                # collinear subtrees (finger chains) and empty ones (delta = I) well posed.
                spread = tq.new_zeros(tq.shape[0], n).index_add_(1, slot, pq.square().sum(-1))
                h = h + cfg.damping * spread[..., None, None] * eye
                # Newton-Schulz from h / ||h||_inf (eq. 8); the damping bounds the condition
                # number of h by ~1/lambda, so ns_iters ~ log_1.5(1/lambda) + 3 steps converge.
                delta = self._polar(torch.where((spread > 0)[..., None, None], h, eye))
                g_new = delta @ g_rot[:, joints]
                if root:
                    transl = (ct - (delta @ (cp - g_pos[:, 1:2])[..., None]).squeeze(-1))[:, 0]
                parent = g_rot[:, layer.parents[joints]]
                # R_p^T R_p is I only to rounding; without a polish the deviation compounds
                # down the chain (x3 per level in float32). Two Newton-Schulz steps restore it.
                new = parent.transpose(-1, -2) @ g_new
                local = local.index_copy(1, joints, newton_schulz(new, iters=2, init=new))
                solves += 1
        # A truncated Newton-Schulz run leaves rotations orthogonal to ~1e-4: project once so
        # the returned pose reproduces the returned mesh exactly.
        return self._zero_unobservable(polar_svd(local)), transl, solves

    def _autograd(self, prepared, target, local, transl) -> tuple[torch.Tensor, torch.Tensor, int]:
        if torch.is_inference_mode_enabled():
            raise RuntimeError("method 'autograd' needs gradients: call invert() outside torch.inference_mode()")
        cfg = self.config
        prepared = PreparedIdentity(*(getattr(prepared, f.name).detach() for f in fields(PreparedIdentity)))
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
        target = self._canonical(vertices)
        b = target.shape[0]
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
        w = csr(layer._skin_w_crow, layer._skin_joint, layer.skin_weight, (layer.num_vertices, layer.num_joints))
        blended = (w @ mats.permute(1, 0, 2, 3).reshape(layer.num_joints, -1)).view(-1, b, 3, 4).transpose(0, 1)
        rest = torch.linalg.solve(blended[..., :3], target - blended[..., 3])
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
        target = self._canonical(vertices)
        if prepared.batch_size not in (1, target.shape[0]):
            raise ValueError(
                f"prepared: identity batch {prepared.batch_size} must be 1 or the mesh batch {target.shape[0]}"
            )
        cfg = self.config
        local, transl = self._skeleton_init(target)
        iterations = 0
        if cfg.method == "analytic" or (cfg.method == "autograd" and cfg.init == "analytic"):
            local, transl, iterations = self._analytic(prepared, target, local, transl)
            if self._gn is not None:
                local, transl = gauss_newton(
                    self.layer, self._gn, prepared, target, local, transl, cfg.gauss_newton_steps
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
            error = _distances(pred, target)
        return InversionResult(matrix_to_axis_angle(rel), rel, transl, pred, error, iterations)


def _distances(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """|a - b| over the last axis of size 3 (~2x faster than ``norm(dim=-1)`` on CPU)."""
    d = a - b
    x, y, z = d.unbind(-1)
    return (x * x).addcmul_(y, y).addcmul_(z, z).sqrt_()
