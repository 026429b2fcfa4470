"""The correctives' cached rest-pose MLP value follows the parameters, the dtype and autograd."""

from __future__ import annotations

import torch

from conftest import chain_rig
from unibody.correctives.model import Correctives


def _model() -> Correctives:
    rig = chain_rig()
    w = rig.dense_skinning_weights()
    inputs = torch.tensor([[2, 3, -1], [3, 2, 4], [4, 3, -1]])
    verts = [torch.nonzero(w[:, k] > 0.05).flatten() for k in (2, 3, 4)]
    model = Correctives(inputs, verts, rig.num_vertices, hidden=8, channels=4, bones=((1, 2), (2, 3)))
    gen = torch.Generator().manual_seed(3)
    with torch.no_grad():
        for p in model.parameters():
            p.copy_(0.3 * torch.randn(p.shape, generator=gen))
    return model.requires_grad_(False)


def _uncached(model: Correctives, x6: torch.Tensor) -> torch.Tensor:
    return model._mlp(x6) - model._mlp(x6.new_zeros(1, *x6.shape[1:]))


def test_cache_follows_parameters_and_dtype():
    model = _model()
    x6 = 0.4 * torch.randn(5, len(model.needed), 6, generator=torch.Generator().manual_seed(1))
    assert torch.equal(model.activations(x6), _uncached(model, x6))
    assert model.activations(torch.zeros_like(x6)).abs().max() == 0
    with torch.no_grad():  # an in-place update (an optimiser step) must not leave a stale offset
        model.b2.add_(0.5)
        model.b1.sub_(0.2)
    assert torch.equal(model.activations(x6), _uncached(model, x6))
    assert model.activations(torch.zeros_like(x6)).abs().max() == 0
    model.freeze(model.needed[:1], torch.full((1, 6), 0.3))  # frozen inputs enter the offset too
    assert torch.equal(model.activations(x6), _uncached(model, x6))
    assert model.activations(torch.zeros_like(x6)).abs().max() == 0
    d = model.double()
    x64 = x6.double()
    assert d.activations(x64).dtype == torch.float64
    assert torch.equal(d.activations(x64), _uncached(d, x64))


def test_no_cache_while_training():
    """With trainable parameters the offset is computed live, so gradients reach them through it."""
    model = _model().requires_grad_(True)
    x6 = 0.4 * torch.randn(4, len(model.needed), 6, generator=torch.Generator().manual_seed(2))
    model.activations(x6).sum().backward()
    live = model.b2.grad.clone()
    model.zero_grad()
    _uncached(model, x6).sum().backward()
    assert torch.allclose(live, model.b2.grad)
    assert live.abs().sum() > 0


def test_shape_inputs_are_kept_for_the_same_rest_tensors_only():
    """Posing one prepared identity again reuses its shape inputs; another identity (even at a
    freed one's address), an in-place edit or a rest mesh needing gradients gets its own."""
    rig = chain_rig()
    w = rig.dense_skinning_weights().argmax(1)
    spec = {
        "joints": [(2, 3)],
        "vertices": [torch.nonzero(w == 2).flatten()],
        "mean": torch.zeros(2),
        "std": torch.ones(2),
    }
    verts = [torch.nonzero(rig.dense_skinning_weights()[:, k] > 0.05).flatten() for k in (2, 3, 4)]
    model = Correctives(_model().inputs, verts, rig.num_vertices, hidden=8, channels=4, bones=((1, 2),), shape=spec)
    v, j = rig.bind_vertices[None].float(), rig.bind_transforms[None, :, :3, 3].float()
    first = model.shape_inputs(v, j)
    assert model.shape_inputs(v, j) is first and torch.equal(first, model.shape_features(v, j))
    v2 = v.clone()
    v2.mul_(1.5)  # another identity
    assert torch.equal(model.shape_inputs(v2, j), model.shape_features(v2, j))
    v2.mul_(2.0)  # edited in place
    assert torch.equal(model.shape_inputs(v2, j), model.shape_features(v2, j))
    del v2
    v3 = v * 3.0  # may land at the freed tensor's address
    assert torch.equal(model.shape_inputs(v3, j), model.shape_features(v3, j))
    r = v.clone().requires_grad_(True)
    model.shape_inputs(r, j).sum().backward()
    assert r.grad is not None and r.grad.abs().sum() > 0


def test_one_model_serves_a_plain_and_a_twist_layer():
    """Each layer keeps its own skinning binding: building the twist layer leaves the plain one right."""
    import numpy as np

    from unibody import BodyLayer
    from unibody.body import PreparedIdentity
    from unibody.correctives.training import TeacherSetup

    plain0 = BodyLayer.from_pca().double()
    setup = TeacherSetup(plain0, twist_start=False)
    names = plain0.joint_names
    inputs = torch.tensor([[names.index(n), int(plain0.parents[names.index(n)])] for n in setup.masks])
    verts = [torch.from_numpy(np.flatnonzero(m)) for m in setup.masks.values()]
    model = Correctives(inputs, verts, plain0.num_vertices, hidden=8, channels=4, size_ref=0.3)
    with torch.no_grad():
        for p in model.parameters():
            p.copy_(0.1 * torch.randn(p.shape, generator=torch.Generator().manual_seed(7)))
    model.requires_grad_(False)
    plain = BodyLayer.from_pca(correctives=model).double()
    twist = BodyLayer.from_pca(procedural=True, correctives=model).double()
    prepared = plain.prepare_identity(torch.zeros(1, plain.identity.num_params, dtype=torch.float64))
    pose = 0.7 * torch.randn(3, 77, 3, generator=torch.Generator().manual_seed(8), dtype=torch.float64)
    local = plain.local_rotations(pose)
    p = prepared
    d = model.double()(model.rest_relative(local, p.rest_rotations, plain.parents), model.size_of(p.rest_joints))
    rest = (p.rest_rotations, p.rest_joints, p.offsets)
    shifted = PreparedIdentity(p.rest_vertices + d, *(t.expand(3, *t.shape[1:]) for t in rest))
    # The displaced rest mesh, skinned by each rig. The plain rig reads the rotations back from
    # the world transforms (R_p^T R_k), whose fitted rest rotations are orthonormal to ~1e-9 only.
    for layer, tol in ((plain, 1e-8), (twist, 1e-12)):
        ref = layer.pose(shifted, pose, correctives=False).vertices
        assert (layer.pose(prepared, pose).vertices - ref).abs().max() < tol
    assert (plain.pose(prepared, pose).vertices - twist.pose(prepared, pose).vertices).abs().max() > 1e-3
    x = pose[:1].clone().requires_grad_(True)  # gradients through the twist rig's skinned displacements
    assert torch.autograd.gradcheck(lambda q: twist.pose(prepared, q).vertices[:, ::997], (x,), fast_mode=True)


def test_inversion_knows_the_correctives():
    """A layer with correctives inverts meshes made with them (the fixed point), and rounds = 0 is plain LBS."""
    from dataclasses import replace

    import pytest

    from unibody import PRESETS, BodyLayer, InversionConfig, PoseInverter
    from unibody.correctives.stress import stress_poses

    layer = BodyLayer.from_pca(correctives=True)
    prepared = layer.prepare_identity(torch.zeros(1, layer.identity.num_params))
    poses, _ = stress_poses(torch.Generator().manual_seed(0), seeded=0)
    poses = poses[[0, 2, 4, 10]]  # elbow, knee, shoulder, squat
    target = layer.pose(prepared, poses).vertices.contiguous()
    err = {}
    for rounds in (0, 2):
        res = PoseInverter(layer, replace(PRESETS["refined"], corrective_rounds=rounds)).invert(target, prepared)
        again = layer.pose(prepared, res.rotations, transl=res.transl).vertices
        err[rounds] = float((again - target).norm(dim=-1).mean())
        if rounds:  # the residuals re-pose as the layer does, with its correctives (rounds 0: plain LBS)
            torch.testing.assert_close(res.vertices, again, atol=1e-5, rtol=0)
    assert err[2] < 0.6 * err[0]
    with pytest.raises(ValueError, match="corrective_rounds: expected an integer >= 0"):
        InversionConfig(corrective_rounds=-1)
