"""Fit the unified body (LBS) to sparse constraints: PanoMan's initialisation and baseline.

Constraints are the ones PanoMan's benchmark uses (paper 004 §5.2): surface vertex handles and
points given by a linear regressor of the mesh (joint positions: the rig's RBF joint regressor
applied to the posed mesh). The unknowns are the PCA shape coefficients, the 77 joint
rotations (T-pose-relative axis-angle) and the Hips position of each item of a batch.

Stages, batched (the objective is a sum over items, so each item's minimiser is its own; L-BFGS
shares its line searches across the batch, so results move slightly with the batch's make-up):
0. initialisation: shape from the bone lengths (pose-invariant), then analytic IK: each
   joint's rotation aligns its rest child offsets with the target ones (Kabsch / shortest arc);
1. joints only: L-BFGS on the FK joint positions against the joint targets (no skinning,
   cheap), shape, pose and translation together;
2. all constraints on the skinned mesh: L-BFGS on the regressed joints and the vertex handles,
   with a small pose prior (|pose|^2) that settles what the constraints leave free.

    fit = fit_body(layer, vertex_ids, vertex_targets, regressor, joint_targets)
    fit.vertices   # (B, V, 3)
"""

from __future__ import annotations

from dataclasses import dataclass

import torch

from .._checks import check_finite, check_grad_mode, check_like, check_shape
from ..body import BodyLayer
from ..geometry.procrustes import kabsch
from ..geometry.rotations import matrix_to_axis_angle, shortest_arc

__all__ = ["BodyFit", "fit_body", "regressor_matrix", "sparse_joint_regressor"]


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


def regressor_matrix(ids: torch.Tensor, weights: torch.Tensor, num_vertices: int) -> torch.Tensor:
    """Sparse (R, V) float64 tensor of a regressor given as rows of vertex ids (R, k) and weights (R, k)."""
    r, k = ids.shape
    idx = torch.stack([torch.arange(r, device=ids.device).repeat_interleave(k), ids.reshape(-1)])
    # Checked (an id outside [0, V) raises here, not a crash later); 77 rows cost nothing to check.
    coo = torch.sparse_coo_tensor(idx, weights.reshape(-1).double(), (r, num_vertices), check_invariants=True)
    return coo.coalesce()


def sparse_joint_regressor(
    meshes: torch.Tensor, *, vertices_per_joint: int = 32, ridge: float = 0.01
) -> tuple[torch.Tensor, torch.Tensor]:
    """A sparse stand-in for the RBF joint regressor, for solvers that need narrow rows.

    The RBF regressor spreads a joint over hundreds to thousands of vertices (median 466, at
    most 5,353), which makes ``C^T C`` of a Gauss–Newton system dense. Here each joint (Root
    excluded: it is the origin) reads only the ``vertices_per_joint`` vertices with the largest
    RBF weights; their weights (summing to 1, so the map commutes with translations) are fitted
    by least squares to reproduce the RBF regressor on ``meshes`` (B, V, 3), e.g. posed training
    bodies (paper 004 §5.2: joints become vertex constraints by linear regression).

    Returns:
        (rows (77, k) vertex ids, weights (77, k)) for joints 1..77, on the device of ``meshes``.
    """
    from ..rig import Rig

    rig = Rig.canonical()
    m = meshes.double()
    dev = m.device
    dense = torch.zeros(rig.num_joints, rig.num_vertices, dtype=torch.float64, device=dev)
    dense[rig.rbf_joint.long().to(dev), rig.rbf_vertex.long().to(dev)] = rig.rbf_weight.to(dev, torch.float64)
    target = torch.einsum("jv,bvc->bjc", dense, m)  # (B, J, 3)
    k = vertices_per_joint
    ids = dense[1:].abs().topk(k, dim=1).indices  # (77, k)
    weights = []
    for j in range(1, rig.num_joints):
        w0 = dense[j, ids[j - 1]]
        w0 = w0 / w0.sum()
        a = m[:, ids[j - 1]].permute(0, 2, 1).reshape(-1, k)  # (3B, k)
        a = a - a.mean(0)  # centred: with sum(w) = 1 fixed below, translations drop out
        y = target[:, j].reshape(-1)
        y = y - y.mean()
        # ridge towards the renormalised RBF weights, then the affine constraint sum(w) = 1
        lhs = a.T @ a + ridge * len(y) * 1e-4 * torch.eye(k, dtype=a.dtype, device=dev)
        rhs = a.T @ y + ridge * len(y) * 1e-4 * w0
        kkt = a.new_zeros(k + 1, k + 1)
        kkt[:k, :k], kkt[:k, k], kkt[k, :k] = lhs, 1.0, 1.0
        sol = torch.linalg.solve(kkt, torch.cat([rhs, a.new_ones(1)]))
        weights.append(sol[:k])
    return ids, torch.stack(weights)


def _shape_from_bones(layer: BodyLayer, joint_targets: torch.Tensor, steps: int) -> torch.Tensor:
    """Shape coefficients (B, K) whose rest bone lengths match the targets' (pose-invariant)."""
    parents = layer.parents[2:]  # bones of joints 2..77 (the Hips' parent is the virtual Root)
    target = (joint_targets[:, 1:] - joint_targets[:, parents - 1]).norm(dim=-1)
    shape = joint_targets.new_zeros(joint_targets.shape[0], layer.identity.num_params, requires_grad=True)
    opt = torch.optim.LBFGS([shape], lr=1.0, max_iter=steps, line_search_fn="strong_wolfe")

    def closure():
        opt.zero_grad()
        rest = layer.prepare_identity(shape).rest_joints
        length = (rest[:, 2:] - rest[:, parents]).norm(dim=-1)
        loss = ((length - target) ** 2).sum() + 1e-6 * (shape**2).sum()
        loss.backward()
        return loss

    opt.step(closure)
    return shape.detach()


def _pose_from_joints(layer: BodyLayer, prepared, joint_targets: torch.Tensor) -> torch.Tensor:
    """Analytic IK: (B, 77, 3) T-pose-relative axis-angle that carries the rest joints onto the targets.

    Top-down over the tree, each joint's world rotation change D_j aligns its rest child offsets,
    turned by the parent's D_p, with the target offsets: Kabsch for several children, the
    shortest arc for one (least twist), D_p for none. Absolute local rotations follow from the
    world frames W_j = D_j R0_j as W_p^T W_j.
    """
    b = joint_targets.shape[0]
    dtype = joint_targets.dtype
    r0, p0 = prepared.rest_rotations.expand(b, -1, -1, -1), prepared.rest_joints.expand(b, -1, -1)
    target = torch.cat([p0[:, :1], joint_targets], dim=1)  # Root row: unused
    children = layer.rig_tree.children
    delta = torch.eye(3, dtype=dtype, device=joint_targets.device).repeat(b, len(children), 1, 1)
    for level in layer.rig_tree.levels[1:]:
        for j in level:
            p = layer.rig_tree.parents[j]  # a Python int: no device sync per joint
            kids = children[j]
            if not kids:
                delta[:, j] = delta[:, p]
                continue
            a = (p0[:, list(kids)] - p0[:, j : j + 1]) @ delta[:, p].transpose(-1, -2)
            t = target[:, list(kids)] - target[:, j : j + 1]
            if len(kids) == 1:
                delta[:, j] = shortest_arc(a[:, 0], t[:, 0]) @ delta[:, p]
            else:
                delta[:, j] = kabsch(a, t) @ delta[:, p]
    world = delta @ r0
    local = world[:, layer.parents[1:]].transpose(-1, -2) @ world[:, 1:]
    local[:, 0] = world[:, 1]  # the Hips' parent is the (identity) Root
    return matrix_to_axis_angle(layer.to_relative(local))


def _regress(regressor: torch.Tensor, vertices: torch.Tensor) -> torch.Tensor:
    """(B, V, 3) -> (B, R, 3) through a sparse (R, V) regressor."""
    b, v, _ = vertices.shape
    flat = vertices.permute(1, 0, 2).reshape(v, b * 3)
    return torch.sparse.mm(regressor, flat).reshape(-1, b, 3).permute(1, 0, 2)


def _check_args(layer, vertex_ids, vertex_targets, regressor, joint_targets) -> None:  # noqa: ANN001
    """TypeError / ValueError naming the argument (:func:`fit_body`'s)."""
    if not isinstance(layer, BodyLayer) or layer.identity is None:
        raise ValueError("layer: expected a BodyLayer with an identity backend (e.g. BodyLayer.from_pca())")
    sizes = {"V": layer.num_vertices, "J": layer.num_joints - 1}
    check_shape(vertex_ids, "H", name="vertex_ids", sizes=sizes)
    if vertex_ids.is_floating_point() or vertex_ids.is_complex() or vertex_ids.dtype == torch.bool:
        raise TypeError(f"vertex_ids: expected integer vertex ids, got {str(vertex_ids.dtype).removeprefix('torch.')}")
    if len(vertex_ids) and not (0 <= int(vertex_ids.min()) and int(vertex_ids.max()) < sizes["V"]):
        bad = vertex_ids[(vertex_ids < 0) | (vertex_ids >= sizes["V"])][0]
        raise ValueError(f"vertex_ids: expected canonical vertex ids in [0, {sizes['V']}), got {int(bad)}")
    check_shape(regressor, "J V", name="regressor", sizes=sizes)
    for name, x, spec in (("vertex_targets", vertex_targets, "B H 3"), ("joint_targets", joint_targets, "B J 3")):
        check_shape(x, spec, name=name, sizes=sizes)
        check_like(x, layer.tpose_orient, name=name)
        check_finite(x, name)


@torch.enable_grad()  # it descends a gradient whatever its caller (commands run under no_grad)
def fit_body(
    layer: BodyLayer,
    vertex_ids: torch.Tensor,
    vertex_targets: torch.Tensor,
    regressor: torch.Tensor,
    joint_targets: torch.Tensor,
    *,
    shape_steps: int = 30,
    joint_steps: int = 100,
    mesh_steps: int = 60,
    pose_prior: float = 1e-4,
) -> BodyFit:
    """Fit shape, pose and translation of ``layer`` (a PCA-identity layer) to the constraints.

    Args:
        layer: a :class:`BodyLayer` whose identity backend takes (B, K) coefficients.
        vertex_ids: (H,) canonical vertex indices of the surface handles.
        vertex_targets: (B, H, 3) m.
        regressor: (77, V) sparse regressor of joints 1..77 (:func:`regressor_matrix` of
            :func:`sparse_joint_regressor`).
        joint_targets: (B, 77, 3) m, the regressed joints of the target meshes.
        joint_steps, mesh_steps: iterations of the two stages.
        pose_prior: weight of |pose|^2 in stage 2 (per joint, radians^2, against m^2 residuals).
    """
    check_grad_mode("fit_body")
    _check_args(layer, vertex_ids, vertex_targets, regressor, joint_targets)
    joint_targets = joint_targets.detach()
    # The constraint indices and the regressor are constants: take them to the targets' device.
    dev = joint_targets.device
    vertex_ids, regressor = vertex_ids.to(dev), regressor.to(dev)
    shape0 = _shape_from_bones(layer, joint_targets, shape_steps)
    with torch.no_grad():
        pose0 = _pose_from_joints(layer, layer.prepare_identity(shape0), joint_targets)
    shape = shape0.clone().requires_grad_(True)
    pose = pose0.clone().requires_grad_(True)
    transl = joint_targets[:, 0].clone().requires_grad_(True)

    def fk_joints():
        prepared = layer.prepare_identity(shape)
        local = layer.local_rotations(pose)
        _, g_pos, _ = layer.skin_transforms(prepared, local, transl)
        return g_pos[:, 1:]

    def lbfgs(loss_fn, steps):
        opt = torch.optim.LBFGS(
            [shape, pose, transl],
            lr=1.0,
            max_iter=steps,
            history_size=50,
            line_search_fn="strong_wolfe",
            tolerance_grad=1e-12,
            tolerance_change=1e-14,
        )

        def closure():
            opt.zero_grad()
            loss = loss_fn()
            loss.backward()
            return loss

        opt.step(closure)

    lbfgs(
        lambda: ((fk_joints() - joint_targets) ** 2).sum() + 1e-6 * (shape**2).sum() + 1e-6 * (pose**2).sum(),
        joint_steps,
    )

    def mesh_loss():
        out = layer(shape, pose, transl=transl)
        r_j = _regress(regressor, out.vertices) - joint_targets
        r_v = out.vertices[:, vertex_ids] - vertex_targets
        return (r_j**2).sum() + (r_v**2).sum() + pose_prior * (pose**2).sum() + 1e-5 * (shape**2).sum()

    lbfgs(mesh_loss, mesh_steps)
    with torch.no_grad():
        out = layer(shape, pose, transl=transl)
    return BodyFit(shape.detach(), pose.detach(), transl.detach(), out.vertices)
