"""Left/right mirror map of the canonical mesh: exact search, involution, mirror of meshes."""

from __future__ import annotations

import pytest
import torch

from unibody.symmetry import canonical_mirror_map, mirror, mirror_correspondence


def _brute_force(v: torch.Tensor) -> torch.Tensor:
    return torch.cdist(v * v.new_tensor([-1.0, 1.0, 1.0]), v).argmin(dim=1)


def test_windowed_search_equals_brute_force():
    # An asymmetric cloud stretched along y (like a body), so that the y-window has to grow.
    gen = torch.Generator().manual_seed(3)
    v = torch.rand(3000, 3, generator=gen, dtype=torch.float64) * torch.tensor([0.5, 1.8, 0.3], dtype=torch.float64)
    m = mirror_correspondence(v)
    assert torch.equal(m.index, _brute_force(v))
    assert torch.allclose(m.distance, (v[m.index] - v * v.new_tensor([-1.0, 1.0, 1.0])).norm(dim=1))
    assert not m.is_involution  # random points have no mirror partners


def test_symmetric_cloud_gives_its_permutation():
    gen = torch.Generator().manual_seed(4)
    half = torch.rand(500, 3, generator=gen, dtype=torch.float64) + torch.tensor([0.01, 0.0, 0.0], dtype=torch.float64)
    mid = torch.rand(20, 3, generator=gen, dtype=torch.float64) * torch.tensor([0.0, 1.0, 1.0], dtype=torch.float64)
    v = torch.cat([half, half * half.new_tensor([-1.0, 1.0, 1.0]), mid])
    perm = torch.randperm(len(v), generator=gen)
    m = mirror_correspondence(v[perm])
    expected = torch.cat([torch.arange(500) + 500, torch.arange(500), torch.arange(20) + 1000])
    inverse = torch.argsort(perm)
    assert torch.equal(m.index, inverse[expected[perm]])
    assert m.is_involution and m.is_bijection and m.num_midplane == 20
    assert m.max_distance < 1e-7  # cdist rounding


def test_canonical_map_is_a_bijective_involution(rig):
    m = canonical_mirror_map()
    assert m.index.shape == (rig.num_vertices,)
    assert m.is_involution and m.is_bijection
    assert m.max_distance < 1e-6  # measured 0.16 um: float32 rounding of the source mesh
    assert 0 < m.num_midplane < 1000  # measured 194
    mid = m.index == torch.arange(rig.num_vertices)
    assert rig.bind_vertices[mid, 0].abs().max() < 1e-6
    # Partners are on opposite sides.
    side = torch.sign(rig.bind_vertices[:, 0])
    assert bool((side[~mid] == -side[m.index][~mid]).all())


def test_mirror_of_bind_mesh_is_itself_and_involution(rig):
    bind = rig.bind_vertices[None]
    assert (mirror(bind) - bind).abs().max() < 1e-6
    gen = torch.Generator().manual_seed(5)
    x = torch.randn(2, rig.num_vertices, 3, generator=gen)
    assert torch.equal(mirror(mirror(x)), x)


def test_mirror_reflects_a_shift_and_swaps_sides(rig):
    bind = rig.bind_vertices[None]
    shift = torch.tensor([0.3, -0.2, 0.1], dtype=torch.float64)
    out = mirror(bind + shift)
    assert (out - (bind + shift * shift.new_tensor([-1.0, 1.0, 1.0]))).abs().max() < 1e-6
    # Moving only the left half (+X) moves only the right half of the mirror, the other way.
    left = (rig.bind_vertices[:, 0] > 1e-6)[None, :, None]
    moved = mirror(bind + left * shift)
    right = (rig.bind_vertices[:, 0] < -1e-6)[None, :, None]
    assert (moved - (bind + right * shift * shift.new_tensor([-1.0, 1.0, 1.0]))).abs().max() < 1e-6


def test_mirror_gradcheck(rig):
    x = torch.randn(1, rig.num_vertices, 3, dtype=torch.float64, requires_grad=True)
    assert torch.autograd.gradcheck(mirror, (x,), fast_mode=True)


def test_mirror_errors(rig):
    with pytest.raises(TypeError, match="vertices: expected a torch.Tensor"):
        mirror(rig.bind_vertices.numpy())
    with pytest.raises(ValueError, match=r"vertices: expected shape \(B, 18056, 3\), got \(18056, 3\)"):
        mirror(rig.bind_vertices)
    with pytest.raises(ValueError, match=r"vertices: expected shape \(B, 18056, 3\)"):
        mirror(torch.zeros(1, 100, 3))
    bad = rig.bind_vertices[None].clone()
    bad[0, 7, 1] = float("nan")
    with pytest.raises(ValueError, match="vertices: expected finite values"):
        mirror(bad)
    with pytest.raises(ValueError, match=r"vertices: expected shape \(V, 3\)"):
        mirror_correspondence(torch.zeros(10, 2))


def test_partner_joints_swap_left_and_right():
    from unibody.rig import JOINT_NAMES
    from unibody.symmetry import partner_joints

    names = tuple(JOINT_NAMES)
    p = partner_joints(names)
    assert torch.equal(p[p], torch.arange(len(names)))
    assert names[int(p[names.index("LeftForeArm")])] == "RightForeArm" and int(p[names.index("Hips")]) == 1
    with pytest.raises(ValueError, match="joint_names: 'LeftArm' has no left/right partner 'RightArm'"):
        partner_joints(("Root", "LeftArm"))
