"""The fast posing path (issue 37): joint-major FK by pointer jumping, cached skinning values,
vertex-major LBS output, the unchecked and compiled variants, each against an independent
reference or the checked eager path."""

from __future__ import annotations

import dataclasses

import pytest
import torch

from conftest import chain_rig, fk_loop
from unibody import BodyLayer
from unibody.geometry.kinematics import KinematicTree, chain, compose, forward_kinematics, joint_major
from unibody.geometry.rotations import axis_angle_to_matrix, matrix_to_rot6d
from unibody.geometry.skinning import lbs_dense


@pytest.mark.parametrize(
    "parents",
    [
        (-1,),  # a lone root
        (-1, 0, 1, 2, 3, 4, 5, 6, 7, 8, 9, 10, 11, 12, 13, 14, 15, 16),  # a deep chain: 5 jumps
        (-1, 0, 0, 0, 0, 0),  # a star
        (-1, 0, 0, 1, 1, 2, 5, 5, 3, 8, 9, 9),  # branching
    ],
    ids=["root", "chain", "star", "tree"],
)
def test_pointer_jumping_equals_joint_loop(parents):
    gen = torch.Generator().manual_seed(len(parents))
    b, j = 3, len(parents)
    rot = axis_angle_to_matrix(torch.randn(b, j, 3, generator=gen, dtype=torch.float64))
    trans = torch.randn(b, j, 3, generator=gen, dtype=torch.float64)
    wr, wt = forward_kinematics(KinematicTree(parents), rot, trans)
    ref = fk_loop(parents, rot, trans)
    assert (wr - ref[..., :3, :3]).abs().max() < 1e-12
    assert (wt - ref[..., :3, 3]).abs().max() < 1e-12


def test_compose_is_the_matrix_product_and_broadcasts():
    gen = torch.Generator().manual_seed(0)
    p = torch.randn(2, 5, 3, 4, generator=gen, dtype=torch.float64)
    a = torch.randn(1, 5, 3, 4, generator=gen, dtype=torch.float64)  # one right factor for the whole batch
    hom = torch.tensor([0.0, 0.0, 0.0, 1.0], dtype=torch.float64).expand(2, 5, 1, 4)
    ref = (torch.cat([p, hom], -2) @ torch.cat([a.expand(2, -1, -1, -1), hom], -2))[..., :3, :]
    jm = compose(joint_major(p[..., :3], p[..., 3]), joint_major(a[..., :3], a[..., 3]))
    assert jm.shape == (5, 4, 3, 2)
    assert (jm.permute(3, 0, 2, 1) - ref).abs().max() < 1e-14
    rot_only = compose(joint_major(p[..., :3]), joint_major(a[..., :3]))  # 3x3 products
    assert (rot_only.permute(3, 0, 2, 1) - p[..., :3] @ a[..., :3]).abs().max() < 1e-14


def test_chain_gradients_float64():
    tree = KinematicTree((-1, 0, 1, 1, 3, 4))
    gen = torch.Generator().manual_seed(1)
    rot = axis_angle_to_matrix(torch.randn(2, 6, 3, generator=gen, dtype=torch.float64))
    trans = torch.randn(2, 6, 3, generator=gen, dtype=torch.float64).requires_grad_(True)
    rot.requires_grad_(True)
    assert torch.autograd.gradcheck(lambda r, t: chain(tree, joint_major(r, t)), (rot, trans), fast_mode=True)


def _reference_pose(layer: BodyLayer, prepared, pose: torch.Tensor, transl: torch.Tensor) -> tuple:
    """Posing written out independently: T-pose-relative -> absolute, joint loop FK, dense LBS."""
    o = layer.tpose_orient
    parents = layer.rig_tree.parents
    rel = axis_angle_to_matrix(pose)
    absolute = o[[max(p, 0) for p in parents[1:]]].transpose(-1, -2) @ rel @ o[1:]
    b = pose.shape[0]
    rot = torch.cat([torch.eye(3, dtype=pose.dtype).expand(b, 1, 3, 3), absolute], 1)
    trans = prepared.offsets.expand(b, -1, -1).clone()
    trans[:, 1] = transl
    world = fk_loop(parents, rot, trans)
    rest_inv = torch.linalg.inv(
        torch.cat(
            [
                torch.cat([prepared.rest_rotations, prepared.rest_joints[..., None]], -1),
                torch.tensor([0.0, 0.0, 0.0, 1.0], dtype=pose.dtype).expand(
                    prepared.batch_size, layer.num_joints, 1, 4
                ),
            ],
            -2,
        )
    )
    mats = (world @ rest_inv)[..., :3, :]
    weights = layer.skinning.dense()
    vertices = lbs_dense(prepared.rest_vertices.expand(b, -1, -1), mats, weights)
    return world, vertices


def test_pose_matches_an_independent_reference(anny_layer64):
    layer = anny_layer64
    gen = torch.Generator().manual_seed(5)
    prepared = layer.prepare_identity(torch.rand(1, 6, generator=gen, dtype=torch.float64))
    pose = 0.4 * torch.randn(11, 77, 3, generator=gen, dtype=torch.float64)  # 11: chunks of 8 and 3
    transl = torch.randn(11, 3, generator=gen, dtype=torch.float64)
    out = layer.pose(prepared, pose, transl=transl)
    world, vertices = _reference_pose(layer, prepared, pose, transl)
    assert (out.transforms - world).abs().max() < 1e-12
    assert (out.vertices - vertices).abs().max() < 1e-12
    assert out.transforms.is_contiguous()


def test_unchecked_path_is_bit_identical(anny_layer64):
    layer = anny_layer64
    gen = torch.Generator().manual_seed(6)
    prepared = layer.prepare_identity(torch.rand(1, 6, generator=gen, dtype=torch.float64))
    aa = 0.5 * torch.randn(5, 77, 3, generator=gen, dtype=torch.float64)
    transl = torch.randn(5, 3, generator=gen, dtype=torch.float64)
    for pose in (aa, axis_angle_to_matrix(aa), matrix_to_rot6d(axis_angle_to_matrix(aa))):
        for absolute in (False, True):
            a = layer.pose(prepared, pose, transl=transl, absolute=absolute)
            b = layer.pose(prepared, pose, transl=transl, absolute=absolute, check=False)
            for field in ("vertices", "joints", "transforms"):
                assert torch.equal(getattr(a, field), getattr(b, field))


def test_unchecked_path_still_checks_shapes_and_dtypes(anny_layer64):
    layer = anny_layer64
    prepared = layer.prepare_identity(torch.full((1, 6), 0.5, dtype=torch.float64))
    with pytest.raises(ValueError, match=r"pose: expected shape \(B, 77, 3\)"):
        layer.pose(prepared, torch.zeros(2, 76, 3, dtype=torch.float64), check=False)
    with pytest.raises(TypeError, match="pose: is float32"):
        layer.pose(prepared, torch.zeros(2, 77, 3), check=False)
    with pytest.raises(ValueError, match="transl: expected shape"):
        layer.pose(prepared, torch.zeros(2, 77, 3, dtype=torch.float64), transl=torch.zeros(3, 3), check=False)


def test_skin_values_are_a_cache_of_the_own_rest_mesh(anny_layer64):
    layer = anny_layer64
    gen = torch.Generator().manual_seed(7)
    assert layer.prepare_identity(torch.rand(2, 6, generator=gen, dtype=torch.float64)).skin_values is None
    prepared = layer.prepare_identity(torch.rand(1, 6, generator=gen, dtype=torch.float64))
    assert prepared.skin_values is not None
    pose = 0.3 * torch.randn(2, 77, 3, generator=gen, dtype=torch.float64)
    cached = layer.pose(prepared, pose).vertices
    # Built by hand or replaced: no cache, so the values come from the mesh it holds.
    by_hand = dataclasses.replace(prepared, rest_vertices=prepared.rest_vertices + 0.01)
    assert by_hand.skin_values is None
    transl = torch.zeros(2, 3, dtype=torch.float64)
    _, reference = _reference_pose(layer, by_hand, pose, transl)
    assert (layer.pose(by_hand, pose, transl=transl).vertices - reference).abs().max() < 1e-12
    assert (layer.pose(prepared.detach(), pose).vertices - cached).abs().max() == 0


def test_cached_values_keep_gradients_to_the_identity(anny_layer64):
    layer = anny_layer64
    params = torch.full((1, 6), 0.5, dtype=torch.float64, requires_grad=True)
    pose = 0.3 * torch.randn(3, 77, 3, generator=torch.Generator().manual_seed(8), dtype=torch.float64)
    prepared = layer.prepare_identity(params)
    direction = torch.randn(3, layer.num_vertices, 3, generator=torch.Generator().manual_seed(9), dtype=torch.float64)
    (g,) = torch.autograd.grad((layer.pose(prepared, pose).vertices * direction).sum(), params)
    uncached = dataclasses.replace(layer.prepare_identity(params))  # same identity, no cached values
    (g_ref,) = torch.autograd.grad((layer.pose(uncached, pose).vertices * direction).sum(), params)
    assert g.abs().max() > 0 and (g - g_ref).abs().max() < 1e-9 * g_ref.abs().max()


def test_overflow_guard_takes_the_exact_check_past_its_bound():
    """A translation near the float64 limit fails the cheap bound; the exact scan then passes it."""
    layer = BodyLayer(chain_rig()).double()
    prepared = layer.prepare_rest(chain_rig().bind_vertices[None].double())
    pose = 0.3 * torch.randn(
        2, layer.num_joints - 1, 3, generator=torch.Generator().manual_seed(11), dtype=torch.float64
    )
    near = layer.pose(prepared, pose).vertices
    far = layer.pose(prepared, pose, transl=torch.full((2, 3), 1e308, dtype=torch.float64)).vertices
    assert torch.isfinite(far).all()
    assert ((far - 1e308) - (near - near[:, :1] + far[:, :1] - 1e308)).abs().max() <= 1e293


@pytest.mark.slow
def test_compiled_posing_agrees_with_eager():
    """torch.compile of the dense part (tens of seconds to compile, so slow)."""
    layer = BodyLayer(chain_rig())
    rest = chain_rig().bind_vertices[None].float()
    prepared = layer.prepare_rest(rest)
    gen = torch.Generator().manual_seed(10)
    for b in (1, 5):
        pose = 0.5 * torch.randn(b, layer.num_joints - 1, 3, generator=gen)
        transl = torch.randn(b, 3, generator=gen)
        eager = layer.pose(prepared, pose, transl=transl)
        compiled = layer.compile_posing().pose(prepared, pose, transl=transl)
        layer.compile_posing(False)
        assert (compiled.vertices - eager.vertices).abs().max() < 1e-5
        assert (compiled.transforms - eager.transforms).abs().max() < 1e-5


@pytest.fixture(scope="module")
def anny_layer32():
    return BodyLayer.from_anny()


def test_warp_kernel_agrees_with_the_torch_path(anny_layer32):
    """float32 without gradients takes the Warp kernel; with a gradient the torch path: the same body."""
    from unibody.geometry._warp import posing

    layer = anny_layer32
    assert posing.available()
    gen = torch.Generator().manual_seed(12)
    for b, bi in ((1, 1), (3, 1), (3, 3), (0, 1)):
        prepared = layer.prepare_identity(torch.rand(bi, 6, generator=gen))
        aa = 0.6 * torch.randn(b, 77, 3, generator=gen)
        transl = torch.randn(b, 3, generator=gen)
        for pose in (aa, axis_angle_to_matrix(aa), matrix_to_rot6d(axis_angle_to_matrix(aa))):
            for absolute in (False, True):
                with torch.no_grad():
                    fast = layer.pose(prepared, pose, transl=transl, absolute=absolute)
                ref = layer.pose(prepared, pose.clone().requires_grad_(True), transl=transl, absolute=absolute)
                assert fast.vertices.shape == (b, layer.num_vertices, 3)
                if b:
                    assert (fast.transforms - ref.transforms.detach()).abs().max() < 5e-6
                    assert (fast.vertices - ref.vertices.detach()).abs().max() < 5e-6


def test_warp_path_leaves_huge_angles_to_torch(anny_layer32):
    """Past MAX_ANGLE the kernel is not trusted: the result is exactly the torch path's."""
    from unibody.geometry._warp.posing import MAX_ANGLE

    layer = anny_layer32
    prepared = layer.prepare_identity(torch.full((1, 6), 0.5))
    pose = 0.3 * torch.randn(2, 77, 3, generator=torch.Generator().manual_seed(13))
    pose[1, 5] = torch.tensor([2 * MAX_ANGLE, 0.0, 0.0])
    with torch.no_grad():
        fast = layer.pose(prepared, pose).vertices
    assert torch.equal(fast, layer.pose(prepared, pose.clone().requires_grad_(True)).vertices.detach())
