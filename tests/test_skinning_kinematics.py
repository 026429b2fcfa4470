"""LBS and FK invariants on the synthetic chain rig (fast, exhaustive) and the real rig."""

from __future__ import annotations

import torch

from conftest import TOL, fk_loop
from unibody.geometry.kinematics import forward_kinematics, relative_to_parent
from unibody.geometry.rotations import axis_angle_to_matrix
from unibody.geometry.skinning import lbs_dense, lbs_sparse, skin_layout


def _random_mats(b, j, gen, dtype):
    rot = axis_angle_to_matrix(torch.randn(b, j, 3, generator=gen, dtype=torch.float64)).to(dtype)
    t = torch.randn(b, j, 3, 1, generator=gen, dtype=torch.float64).to(dtype)
    return torch.cat([rot, t], -1)


def _layout(rig):
    return skin_layout(rig.skin_vertex, rig.skin_joint, rig.num_vertices, rig.num_joints)


def test_weights_partition_of_unity(rig):
    sums = torch.zeros(rig.num_vertices, dtype=torch.float64).index_add_(0, rig.skin_vertex, rig.skin_weight)
    assert torch.allclose(sums, torch.ones_like(sums), atol=1e-12)
    counts = torch.bincount(rig.skin_vertex)
    assert int(counts.max()) == 14 and abs(float(counts.double().mean()) - 3.36) < 0.05


def test_identity_transforms_give_rest(rig, dtype):
    rest = rig.bind_vertices.to(dtype)[None]
    eye = torch.eye(3, 4, dtype=dtype).expand(3, rig.num_joints, 3, 4)
    out = lbs_sparse(rest, eye, rig.skin_weight.to(dtype), _layout(rig))
    assert out.shape == (3, rig.num_vertices, 3)
    assert (out - rest).abs().max() < 10 * TOL[dtype]


def test_sparse_equals_dense(rig, dtype):
    gen = torch.Generator().manual_seed(1)
    rest = rig.bind_vertices.to(dtype)
    mats = _random_mats(4, rig.num_joints, gen, dtype)
    dense = lbs_dense(rest[None].expand(4, -1, -1), mats, rig.dense_skinning_weights().to(dtype))
    shared = lbs_sparse(rest[None], mats, rig.skin_weight.to(dtype), _layout(rig))
    per_item = lbs_sparse(rest[None].expand(4, -1, -1) * 1.0, mats, rig.skin_weight.to(dtype), _layout(rig))
    assert (shared - dense).abs().max() < 100 * TOL[dtype]
    assert (per_item - dense).abs().max() < 100 * TOL[dtype]


def test_lbs_commutes_with_rigid_motion(small_rig):
    gen = torch.Generator().manual_seed(2)
    rest = small_rig.bind_vertices[None]
    mats = _random_mats(2, small_rig.num_joints, gen, torch.float64)
    q = axis_angle_to_matrix(torch.tensor([0.4, -1.1, 0.7], dtype=torch.float64))
    t = torch.tensor([0.3, -0.2, 1.5], dtype=torch.float64)
    moved = torch.cat([q @ mats[..., :3], (q @ mats[..., 3:]) + t[:, None]], -1)
    layout = _layout(small_rig)
    a = lbs_sparse(rest, moved, small_rig.skin_weight, layout)
    b = lbs_sparse(rest, mats, small_rig.skin_weight, layout) @ q.T + t
    assert (a - b).abs().max() < 1e-12


def test_lbs_gradcheck(small_rig):
    gen = torch.Generator().manual_seed(3)
    layout = _layout(small_rig)
    for n_rest in (1, 2):
        rest = small_rig.bind_vertices[None].repeat(n_rest, 1, 1) + 0.01 * torch.randn(
            n_rest, small_rig.num_vertices, 3, generator=gen, dtype=torch.float64
        )
        mats = _random_mats(2, small_rig.num_joints, gen, torch.float64)
        rest.requires_grad_(True)
        mats.requires_grad_(True)
        assert torch.autograd.gradcheck(
            lambda r, m: lbs_sparse(r, m, small_rig.skin_weight, layout), (rest, mats), fast_mode=True
        )


def test_fk_matches_joint_loop_and_inverts(rig):
    gen = torch.Generator().manual_seed(4)
    rot = axis_angle_to_matrix(0.5 * torch.randn(2, rig.num_joints, 3, generator=gen, dtype=torch.float64))
    trans = torch.randn(2, rig.num_joints, 3, generator=gen, dtype=torch.float64)
    wr, wt = forward_kinematics(rig.tree, rot, trans)
    ref = fk_loop(rig.tree.parents, rot, trans)
    assert (wr - ref[..., :3, :3]).abs().max() < 1e-12
    assert (wt - ref[..., :3, 3]).abs().max() < 1e-12
    lr, lt = relative_to_parent(rig.tree, wr, wt)
    assert (lr - rot).abs().max() < 1e-12 and (lt - trans).abs().max() < 1e-12


def test_kinematic_tree_lives_in_geometry_and_geometry_imports_no_rig():
    import ast
    import inspect

    import unibody
    from unibody import rig
    from unibody.geometry import kinematics

    assert rig.KinematicTree is kinematics.KinematicTree is unibody.KinematicTree
    tree = kinematics.KinematicTree((-1, 0, 1, 1, 3))
    assert tree.levels == ((0,), (1,), (2, 3), (4,)) and tree.children == ((1,), (2, 3), (), (4,), ())
    # geometry is pure math: no import reaches back up into the package (rig, body, ...).
    imported = {n.module for n in ast.walk(ast.parse(inspect.getsource(kinematics))) if isinstance(n, ast.ImportFrom)}
    assert imported <= {"__future__", "dataclasses", "functools"}, imported
