"""SkeletonTransfer (paper 000 §3.4) on the real rig."""

from __future__ import annotations

import torch

from unibody import SkeletonTransfer
from unibody.geometry.rotations import axis_angle_to_matrix


def test_rbf_reproduces_bind_joints(rig):
    st = SkeletonTransfer(rig)
    joints = st.joint_positions(rig.bind_vertices[None])[0]
    assert (joints - rig.bind_transforms[:, :3, 3]).abs().max() < 1e-9


def test_bind_shape_returns_bind_transforms(rig):
    rot, pos = SkeletonTransfer(rig)(rig.bind_vertices[None])
    assert (rot[0] - rig.bind_transforms[:, :3, :3]).abs().max() < 1e-6
    assert (pos[0] - rig.bind_transforms[:, :3, 3]).abs().max() < 1e-6


def test_rigid_motion_equivariance(rig):
    st = SkeletonTransfer(rig)
    q = axis_angle_to_matrix(torch.tensor([0.3, -2.0, 0.5], dtype=torch.float64))
    t = torch.tensor([0.4, 1.0, -0.3], dtype=torch.float64)
    rot, pos = st(rig.bind_vertices[None])
    rot2, pos2 = st(rig.bind_vertices[None] @ q.T + t)
    assert (pos2[0, 1:] - (pos[0, 1:] @ q.T + t)).abs().max() < 1e-9
    assert (rot2[0, 1:] - q @ rot[0, 1:]).abs().max() < 1e-9


def test_recovers_posed_skeleton(rig):
    """Fig. 5: fitted on a posed mesh, the transfer returns the posed skeleton."""
    from unibody import BodyLayer

    layer = BodyLayer(rig)
    prepared = layer.prepare_rest(rig.bind_vertices[None])
    gen = torch.Generator().manual_seed(5)
    pose = 0.25 * torch.randn(3, 77, 3, generator=gen, dtype=torch.float64)
    out = layer.pose(prepared, pose)
    _, pos = layer.skeleton(out.vertices)
    err = (pos[:, 1:] - out.joints[:, 1:]).norm(dim=-1)
    assert float(err.median()) < 0.005 and float(err.max()) < 0.05
