"""Left/right mirror symmetry of the pose correctives (unibody.correctives.mirror)."""

from __future__ import annotations

import pytest
import torch

from unibody import BodyLayer
from unibody.correctives.mirror import asymmetry, mirror_maps, symmetrize
from unibody.correctives.model import Correctives
from unibody.geometry.rotations import axis_angle_to_matrix
from unibody.mocap.synthetic import mirror_pose


@pytest.fixture(scope="module")
def pca():
    layer = BodyLayer.from_pca()
    return layer, layer.prepare_identity(torch.zeros(1, layer.identity.num_params))


def _random(seed: int) -> Correctives:
    """The shipped model's structure with random parameters and identity statistics."""
    model = Correctives.load()
    gen = torch.Generator().manual_seed(seed)
    with torch.no_grad():
        for p in model.parameters():
            p.copy_(0.2 * torch.randn(p.shape, generator=gen))
        model.shape_mean.copy_(torch.randn(model.num_shape, generator=gen))
        model.shape_std.copy_(0.5 + torch.rand(model.num_shape, generator=gen))
    return model


def _inputs(model: Correctives, n: int = 16, seed: int = 1):
    gen = torch.Generator().manual_seed(seed)
    rel = axis_angle_to_matrix(0.5 * torch.randn(n, 77, 3, generator=gen))
    return rel, torch.full((1,), float(model.size_ref)), torch.randn(n, model.num_shape, generator=gen)


def test_maps_are_involutions(pca):
    layer, _ = pca
    model = Correctives.load()
    m = mirror_maps(model, layer.joint_names)
    for idx in (m.joints, m.active, m.needed, m.union, m.rows, m.shape):
        assert torch.equal(idx[idx], torch.arange(len(idx)))
    assert not torch.equal(m.union, torch.arange(len(m.union)))  # a real map: left and right swap
    d = torch.randn(3, len(model.union), 3)
    assert torch.equal(m.output(m.output(d)), d)


@pytest.mark.parametrize("keep", ["Left", "Right"])
def test_symmetrize_makes_the_model_equivariant_and_keeps_its_side(pca, keep):
    """After symmetrize, f(mirror x) = mirror f(x) exactly; the kept side's displacements are the
    same function as before (the identity statistics' change folded into the first layer)."""
    layer, _ = pca
    model = _random(0)
    m = mirror_maps(model, layer.joint_names)
    rel, size, shape = _inputs(model)
    assert asymmetry(model, m, rel, size, shape) > 1e-2  # random: far from symmetric
    with torch.no_grad():
        before = model.union_displacements(rel, size, shape)
    # the shape inputs are standardised with the model's statistics: give it the same raw build
    raw = shape * model.shape_std + model.shape_mean
    symmetrize(model, m, keep)
    shape = (raw - model.shape_mean) / model.shape_std
    assert torch.allclose(model.shape_mean, model.shape_mean[m.shape])
    scale = float(before.abs().max())  # float32 rounding of the folded statistics, relative to the output
    assert asymmetry(model, m, rel, size, shape) < 1e-6 * scale
    with torch.no_grad():
        after = model.union_displacements(rel, size, shape)
    kept = [k for k, n in enumerate(model.joint_names) if n.startswith(keep)]
    ids = torch.cat([model.vertex_ids.split(model.sizes.tolist())[k] for k in kept])
    other = torch.cat([model.vertex_ids.split(model.sizes.tolist())[k] for k in range(12) if k not in kept])
    only = torch.isin(model.union, ids) & ~torch.isin(model.union, other)
    assert only.sum() > 1000
    assert (after[:, only] - before[:, only]).abs().max() < 1e-6 * scale
    assert (after[:, ~only] - before[:, ~only]).abs().max() > 1e-2 * scale


def test_right_joints_read_their_partners_rotation_in_the_mirrored_pose(pca):
    """What the maps assume of the rig: on a symmetric body, the mirrored pose gives each needed
    joint its partner's rest-relative rotation (a permutation, not a reflection of it)."""
    layer, prepared = pca
    model = Correctives.load()
    m = mirror_maps(model, layer.joint_names)
    pose = 0.4 * torch.randn(4, 77, 3, generator=torch.Generator().manual_seed(2))
    rel = [
        model.world_relative(layer.pose(prepared, p).transforms, prepared.rest_rotations, layer.parents)
        for p in (pose, mirror_pose(pose, layer.joint_names))
    ]
    assert (rel[1] - rel[0][:, m.needed]).abs().max() < 0.02  # the rig's own asymmetry (< 1 mm)
    s = torch.diag(torch.tensor([-1.0, 1.0, 1.0]))
    assert (rel[1] - s @ rel[0][:, m.needed] @ s).abs().max() > 0.5


@pytest.mark.parametrize("procedural", [False, True])
def test_shipped_weights_are_mirror_symmetric(pca, procedural):
    layer, _ = pca
    model = Correctives.load(procedural=procedural)
    m = mirror_maps(model, layer.joint_names)
    assert asymmetry(model, m, *_inputs(model)) < 1e-5


def test_not_mirror_closed_or_bad_side(pca):
    layer, _ = pca
    model = Correctives.load()
    m = mirror_maps(model, layer.joint_names)
    with pytest.raises(ValueError, match="keep: expected 'Left' or 'Right', got 'Up'"):
        symmetrize(model, m, "Up")
    masks = list(model.vertex_ids.split(model.sizes.tolist()))
    masks[0] = masks[0][1:]  # LeftArm's mask loses a vertex its partner keeps
    lopsided = Correctives(model.inputs, masks, model.num_vertices, joint_names=model.joint_names)
    with pytest.raises(ValueError, match="mask is not the mirror of its partner's"):
        mirror_maps(lopsided, layer.joint_names)


def test_paired_batches_keep_a_symmetric_model_symmetric(pca):
    """train --mirror: each sample and its mirror image in the batch, the latter scored back in the
    sample's frame; the gradients are then mirror images, and AdamW steps keep the symmetry."""
    layer, _ = pca
    model = _random(3).double().requires_grad_(True)  # float64: Adam would magnify float32 rounding
    m = mirror_maps(model, layer.joint_names)
    symmetrize(model, m)
    start = model.decode.detach().clone()
    rel, size, shape = (t.double() for t in _inputs(model, 8, seed=4))
    target = 0.01 * torch.randn(8, len(model.union), 3, generator=torch.Generator().manual_seed(5)).double()
    opt = torch.optim.AdamW(model.parameters(), lr=1e-3, weight_decay=0.05)
    for _ in range(3):
        m_rel, m_shape = m.inputs(rel, shape)
        both = model.union_displacements(torch.cat([rel, m_rel]), size, torch.cat([shape, m_shape]))
        pred = torch.cat([both[:8], m.output(both[8:])])
        loss = (pred - target.repeat(2, 1, 1)).square().sum(-1).mean()
        opt.zero_grad()
        loss.backward()
        opt.step()
    assert float((model.decode.detach() - start).abs().max()) > 1e-3  # it trained
    assert asymmetry(model, m, rel, size, shape) < 1e-9
    # one-sided batches (no mirror images) do not keep it
    loss = (model.union_displacements(rel, size, shape) - target).square().sum(-1).mean()
    opt.zero_grad()
    loss.backward()
    opt.step()
    assert asymmetry(model, m, rel, size, shape) > 1e-3


@pytest.mark.parametrize("procedural", [False, True])
def test_a_symmetric_body_in_mirrored_poses_gets_mirrored_meshes(procedural):
    """The shipped weights on the mean body (mirror-symmetric): each stress family's left pose
    against the mirror image of its right pose differs by the rig's own asymmetry only (LBS:
    0.9 mm at most; the weights of 1799a86: 32 mm, 46 mm on the twist rig)."""
    from unibody.correctives.stress import stress_poses
    from unibody.symmetry import mirror

    layer = BodyLayer.from_pca(procedural=procedural, correctives=True)
    prepared = layer.prepare_identity(torch.zeros(1, layer.identity.num_params))
    poses, labels = stress_poses(torch.Generator().manual_seed(0), seeded=0)
    left = [i for i, n in enumerate(labels) if n.endswith("(left)")]
    right = [labels.index(labels[i].replace("(left)", "(right)")) for i in left]
    a = layer.pose(prepared, poses[left]).vertices
    assert (a - mirror(layer.pose(prepared, poses[right]).vertices)).norm(dim=-1).max() < 2e-3
