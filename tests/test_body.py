"""BodyLayer on the real rig and the Anny backend: conventions, gradients, errors."""

from __future__ import annotations

import pytest
import torch

from unibody import BodyLayer, joint_index
from unibody.geometry.kinematics import relative_to_parent
from unibody.geometry.rotations import axis_angle_to_matrix, matrix_to_rot6d


@pytest.fixture(scope="module")
def layer(rig):
    return BodyLayer(rig)


@pytest.fixture(scope="module")
def bind(layer, rig):
    return layer.prepare_rest(rig.bind_vertices[None])


def _tpose_positions():
    import os

    import anny

    raw = torch.load(os.path.join(os.path.dirname(anny.__file__), "data/soma/soma_rig.pt"), weights_only=True)
    return raw["t_pose_world"][:, :3, 3].double() / 100


def test_zero_pose_is_tpose(layer, bind, rig):
    out = layer.pose(bind, torch.zeros(1, 77, 3, dtype=torch.float64))
    tpose = _tpose_positions()
    hips = joint_index("Hips")
    rel, ref = out.joints[0] - out.joints[0, hips], tpose - tpose[hips]
    assert (rel[1:] - ref[1:]).abs().max() < 1e-6
    assert (out.transforms[0, :, :3, :3] - rig.tpose_orient).abs().max() < 1e-9
    assert out.joints[0, hips].abs().max() == 0  # transl None puts the Hips at the origin


def test_absolute_bind_pose_reproduces_rest(layer, bind, rig):
    local_r, _ = relative_to_parent(rig.tree, bind.rest_rotations, bind.rest_joints)
    out = layer.pose(bind, local_r[:, 1:], transl=bind.rest_joints[:, 1], absolute=True)
    assert (out.vertices - rig.bind_vertices).abs().max() < 1e-9
    assert (out.transforms[..., :3, :3] - rig.bind_transforms[:, :3, :3]).abs().max() < 1e-9


def test_pose_formats_agree_and_identity_broadcasts(layer, bind):
    gen = torch.Generator().manual_seed(7)
    aa = 0.4 * torch.randn(3, 77, 3, generator=gen, dtype=torch.float64)
    mat = axis_angle_to_matrix(aa)
    transl = torch.randn(3, 3, generator=gen, dtype=torch.float64)
    a = layer.pose(bind, aa, transl=transl)
    b = layer.pose(bind, mat, transl=transl)
    c = layer.pose(bind, matrix_to_rot6d(mat), transl=transl)
    expanded = type(bind)(
        *(x.expand(3, *x.shape[1:]) for x in (bind.rest_vertices, bind.rest_rotations, bind.rest_joints, bind.offsets))
    )
    d = layer.pose(expanded, aa, transl=transl)
    for other in (b, c, d):
        assert (a.vertices - other.vertices).abs().max() < 1e-10
    assert (a.joints[:, joint_index("Hips")] - transl).abs().max() < 1e-12


def test_float32_matches_float64(rig):
    l64, l32 = BodyLayer(rig), BodyLayer(rig).float()
    gen = torch.Generator().manual_seed(8)
    pose = 0.3 * torch.randn(2, 77, 3, generator=gen, dtype=torch.float64)
    a = l64.pose(l64.prepare_rest(rig.bind_vertices[None]), pose)
    b = l32.pose(l32.prepare_rest(rig.bind_vertices[None].float()), pose.float())
    assert b.vertices.dtype == torch.float32
    assert (a.vertices - b.vertices.double()).abs().max() < 1e-4


def _project(x, seed=0):
    """A few random projections of an output: gradcheck stays cheap on 54k outputs."""
    gen = torch.Generator().manual_seed(seed)
    return x.flatten(1) @ torch.randn(x[0].numel(), 4, generator=gen, dtype=x.dtype)


def test_gradcheck_pose_and_transl(layer, bind):
    gen = torch.Generator().manual_seed(9)
    pose = (0.3 * torch.randn(1, 77, 3, generator=gen, dtype=torch.float64)).requires_grad_(True)
    transl = torch.randn(1, 3, generator=gen, dtype=torch.float64).requires_grad_(True)
    assert torch.autograd.gradcheck(
        lambda p, t: _project(layer.pose(bind, p, transl=t).vertices), (pose, transl), fast_mode=True
    )


def test_gradcheck_rest_shape(small_rig):
    """Gradients through skeleton transfer + FK + LBS with respect to the rest mesh."""
    layer = BodyLayer(small_rig)
    gen = torch.Generator().manual_seed(10)
    rest = (
        small_rig.bind_vertices + 0.005 * torch.randn(small_rig.num_vertices, 3, generator=gen, dtype=torch.float64)
    )[None].requires_grad_(True)
    pose = 0.3 * torch.randn(2, small_rig.num_joints - 1, 3, generator=gen, dtype=torch.float64)
    assert torch.autograd.gradcheck(lambda r: layer.pose(layer.prepare_rest(r), pose).vertices, (rest,), fast_mode=True)


def test_gradcheck_identity_params(anny_layer64):
    gen = torch.Generator().manual_seed(11)
    params = (0.2 + 0.6 * torch.rand(1, 6, generator=gen, dtype=torch.float64)).requires_grad_(True)
    pose = 0.3 * torch.randn(1, 77, 3, generator=gen, dtype=torch.float64)
    assert torch.autograd.gradcheck(
        lambda p: _project(anny_layer64(p, pose).vertices), (params,), atol=1e-5, fast_mode=True
    )


@pytest.mark.parametrize(
    ("make", "error", "match"),
    [
        (
            lambda: torch.zeros(2, 76, 3, dtype=torch.float64),
            ValueError,
            r"pose: expected shape \(B, 77, 3\).*got \(2, 76, 3\)",
        ),
        (lambda: torch.zeros(2, 77, 4, dtype=torch.float64), ValueError, r"pose: expected shape"),
        (
            lambda: torch.full((1, 77, 3), float("nan"), dtype=torch.float64),
            ValueError,
            r"pose: expected finite values",
        ),
        (
            lambda: torch.zeros(1, 77, 3, dtype=torch.float32),
            TypeError,
            r"pose: is float32 on cpu but the layer is float64",
        ),
        (lambda: [[0.0] * 3] * 77, TypeError, r"pose: expected a torch.Tensor, got list"),
    ],
)
def test_bad_pose(layer, bind, make, error, match):
    with pytest.raises(error, match=match):
        layer.pose(bind, make())


def test_bad_transl_and_prepared(layer, bind, rig):
    pose = torch.zeros(2, 77, 3, dtype=torch.float64)
    with pytest.raises(ValueError, match=r"transl: expected shape \(B, 3\) with B=2, got \(3, 3\)"):
        layer.pose(bind, pose, transl=torch.zeros(3, 3, dtype=torch.float64))
    two = layer.prepare_rest(rig.bind_vertices[None].expand(2, -1, -1))
    with pytest.raises(ValueError, match="prepared: identity batch 2 must be 1 or the pose batch 3"):
        layer.pose(two, torch.zeros(3, 77, 3, dtype=torch.float64))
    with pytest.raises(TypeError, match="prepared: expected a PreparedIdentity"):
        layer.pose(rig.bind_vertices, pose)
    with pytest.raises(ValueError, match=r"vertices: expected shape \(B, 18056, 3\), got \(1, 100, 3\)"):
        layer.prepare_rest(torch.zeros(1, 100, 3, dtype=torch.float64))
    with pytest.raises(ValueError, match="params: this layer has no identity backend"):
        layer.prepare_identity(torch.zeros(1, 6, dtype=torch.float64))


def test_unknown_names():
    from unibody import identity

    with pytest.raises(ValueError, match=r"joint name: unknown joint 'LeftForearm'; did you mean 'LeftForeArm'"):
        joint_index("LeftForearm")
    with pytest.raises(ValueError, match=r"identity backend: unknown name 'smplz'; choose one of anny, pca, smpl"):
        identity.create("smplz")


def test_backend_needs_user_files(monkeypatch):
    from unibody import identity

    monkeypatch.delenv("UNIBODY_MHR_DIR", raising=False)
    with pytest.raises(ValueError, match=r"identity backend 'mhr': needs the user's model files; .*UNIBODY_MHR_DIR"):
        identity.create("mhr")


def test_anny_param_errors(anny_layer64):
    ok = torch.full((1, 6), 0.5, dtype=torch.float64)
    with pytest.raises(ValueError, match=r"identity params: phenotype 'age' must lie in \[0, 1\], got 1.5 at batch 0"):
        anny_layer64.prepare_identity(ok.clone().index_fill_(1, torch.tensor([1]), 1.5))
    with pytest.raises(ValueError, match=r"identity params: expected shape \(B, 6\), got \(1, 5\)"):
        anny_layer64.prepare_identity(ok[:, :5])
    with pytest.raises(ValueError, match="identity params: expected finite values"):
        anny_layer64.prepare_identity(ok * float("nan"))
