"""Fit the unified body (LBS) to sparse constraints: PanoMan's initialisation and baseline.

Constraints are the ones PanoMan's benchmark uses (paper 004 §5.2): surface vertex handles and
points given by a linear regressor of the mesh (joint positions: the rig's RBF joint regressor
applied to the posed mesh). The unknowns are the PCA shape coefficients, the 77 joint
rotations (T-pose-relative axis-angle) and the Hips position of each item of a batch.

Two stages, batched and independent per item:
1. joints only: Adam on the FK joint positions against the joint targets (no skinning, cheap),
   shape, pose and translation together — this gets the articulation right from the T-pose;
2. all constraints on the skinned mesh: L-BFGS on the regressed joints and the vertex handles,
   with a small pose prior (|pose|^2) that settles what the constraints leave free.

    fit = fit_body(layer, vertex_ids, vertex_targets, regressor, joint_targets)
    fit.vertices   # (B, V, 3)
"""

from __future__ import annotations

from dataclasses import dataclass

import torch

from ..body import BodyLayer

__all__ = ["BodyFit", "fit_body", "joint_regressor"]


@dataclass(frozen=True, slots=True)
class BodyFit:
    """A fitted batch.

    Attributes:
        shape: (B, K) PCA coefficients.
        pose: (B, 77, 3) T-pose-relative axis-angle.
        transl: (B, 3) m, Hips world position.
        vertices: (B, V, 3) m, the fitted mesh.
    """

    shape: torch.Tensor
    pose: torch.Tensor
    transl: torch.Tensor
    vertices: torch.Tensor


def joint_regressor(layer: BodyLayer) -> torch.Tensor:
    """The rig's RBF joint regressor as a sparse (J, V) tensor in the layer's dtype."""
    from ..rig import Rig

    rig = Rig.canonical()
    idx = torch.stack([rig.rbf_joint.long(), rig.rbf_vertex.long()])
    dtype = layer.tpose_orient.dtype
    return torch.sparse_coo_tensor(idx, rig.rbf_weight.to(dtype), (rig.num_joints, rig.num_vertices)).coalesce()


def _regress(regressor: torch.Tensor, vertices: torch.Tensor) -> torch.Tensor:
    """(B, V, 3) -> (B, R, 3) through a sparse (R, V) regressor."""
    b, v, _ = vertices.shape
    flat = vertices.permute(1, 0, 2).reshape(v, b * 3)
    return torch.sparse.mm(regressor, flat).reshape(-1, b, 3).permute(1, 0, 2)


def fit_body(
    layer: BodyLayer,
    vertex_ids: torch.Tensor,
    vertex_targets: torch.Tensor,
    regressor: torch.Tensor,
    joint_targets: torch.Tensor,
    *,
    joint_steps: int = 300,
    mesh_steps: int = 60,
    pose_prior: float = 1e-4,
) -> BodyFit:
    """Fit shape, pose and translation of ``layer`` (a PCA-identity layer) to the constraints.

    Args:
        layer: a :class:`BodyLayer` whose identity backend takes (B, K) coefficients.
        vertex_ids: (H,) canonical vertex indices of the surface handles.
        vertex_targets: (B, H, 3) m.
        regressor: (R, V) sparse regressor (e.g. :func:`joint_regressor`); the first R joints
            of the rig are assumed to be what it regresses (R = 78 for the joint regressor).
        joint_targets: (B, R, 3) m, the regressed points of the target meshes.
        joint_steps, mesh_steps: iterations of the two stages.
        pose_prior: weight of |pose|^2 in stage 2 (per joint, radians^2, against m^2 residuals).
    """
    b = vertex_targets.shape[0]
    dtype = layer.tpose_orient.dtype
    k = layer.identity.num_params
    shape = torch.zeros(b, k, dtype=dtype, requires_grad=True)
    pose = torch.zeros(b, 77, 3, dtype=dtype, requires_grad=True)
    transl = joint_targets[:, 1].detach().clone().requires_grad_(True)

    def fk_joints():
        prepared = layer.prepare_identity(shape)
        local = layer._local_rotations(pose, absolute=False)
        _, g_pos, _ = layer.skin_transforms(prepared, local, transl)
        return g_pos

    opt = torch.optim.Adam([shape, pose, transl], lr=0.03)
    for i in range(joint_steps):
        opt.zero_grad()
        loss = ((fk_joints() - joint_targets) ** 2).sum() + 1e-5 * (shape**2).sum()
        loss.backward()
        opt.step()
        if i == joint_steps // 2:
            for g in opt.param_groups:
                g["lr"] = 0.01

    def mesh_loss():
        out = layer(shape, pose, transl=transl)
        r_j = _regress(regressor, out.vertices) - joint_targets
        r_v = out.vertices[:, vertex_ids] - vertex_targets
        return (r_j**2).sum() + (r_v**2).sum() + pose_prior * (pose**2).sum() + 1e-5 * (shape**2).sum()

    lbfgs = torch.optim.LBFGS([shape, pose, transl], lr=1.0, max_iter=mesh_steps, line_search_fn="strong_wolfe")

    def closure():
        lbfgs.zero_grad()
        loss = mesh_loss()
        loss.backward()
        return loss

    lbfgs.step(closure)
    with torch.no_grad():
        out = layer(shape, pose, transl=transl)
    return BodyFit(shape.detach(), pose.detach(), transl.detach(), out.vertices)

