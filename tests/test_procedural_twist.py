"""Procedural twist: expanded rig, channel extractors, evaluation and the body layer with it."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from unibody import BodyLayer, joint_index
from unibody.geometry.rotations import axis_angle_to_matrix
from unibody.procedural import ProceduralTwist, canonical_definition, collapse_rig, expand_rig, twist_channel
from unibody.procedural.format import parse

DRIVERS = ("LeftArm", "LeftHand", "LeftLeg", "LeftFoot", "RightArm", "RightHand", "RightLeg", "RightFoot")


@pytest.fixture(scope="module")
def definition():
    return canonical_definition()


@pytest.fixture(scope="module")
def expanded(rig, definition):
    return expand_rig(rig, definition)


@pytest.fixture(scope="module")
def layers(rig):
    plain, twisted = BodyLayer(rig), BodyLayer(rig, procedural=True)
    return plain, twisted, plain.prepare_rest(rig.bind_vertices[None])


def _bind_local(prepared, rig):
    """Absolute local rotations of the rest (bind) pose."""
    r = prepared.rest_rotations
    parents = torch.tensor([max(p, 0) for p in rig.tree.parents])
    return r[:, parents].transpose(-1, -2) @ r


def _random_rotations(n, scale, gen, dtype=torch.float64):
    return axis_angle_to_matrix(scale * torch.randn(n, 3, generator=gen, dtype=dtype))


# --- the shipped sidecar and the expanded rig ------------------------------------------------


def test_shipped_sidecar_round_trips_and_matches_its_script(definition, rig):
    import importlib.util
    from pathlib import Path

    assert parse(definition.to_dict()) == definition
    assert definition.template_asset.joint_count == 78 + 24 == len(definition.main_joint_names) + 24
    path = Path(__file__).resolve().parents[1] / "scripts/make_twist_sidecar.py"
    spec = importlib.util.spec_from_file_location("make_twist_sidecar", path)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    assert parse(module.build(rig)) == definition  # the shipped file is what the script makes


def test_collapse_reproduces_public_rig_exactly(rig, definition, expanded):
    assert expanded.num_joints == 102
    back = collapse_rig(expanded, definition.main_joint_names)
    assert back.joint_names == rig.joint_names
    assert back.tree.parents == rig.tree.parents
    torch.testing.assert_close(back.dense_skinning_weights(), rig.dense_skinning_weights(), rtol=0, atol=2e-16)
    assert torch.equal(back.bind_transforms, rig.bind_transforms)
    assert torch.equal(back.tpose_orient, rig.tpose_orient)


def test_expanded_weights_split_along_the_bone(rig, definition, expanded):
    w = expanded.dense_skinning_weights()
    assert (w >= 0).all()
    torch.testing.assert_close(w.sum(1), torch.ones(rig.num_vertices, dtype=w.dtype), rtol=0, atol=1e-12)
    assert (w[:, 78:].sum(0) > 1.0).all()  # every twist joint skins a real region
    # Twist joints are leaf children of their segment's start joint, on the bone.
    pos = expanded.bind_transforms[:, :3, 3]
    for seg in definition.segments:
        a, b = rig.joint_names.index(seg.start), rig.joint_names.index(seg.end)
        bone = pos[b] - pos[a]
        for name in seg.twist_joints:
            k = expanded.joint_names.index(name)
            assert expanded.tree.parents[k] == a and not expanded.tree.children[k]
            off = pos[k] - pos[a]
            assert torch.linalg.cross(off, bone).norm() < 1e-9 * bone.norm()
    # Along the forearm each vertex's twist share is its clamped position on the bone.
    seg = next(s for s in definition.segments if s.name == "LeftForeArm")
    a, b = (rig.joint_names.index(n) for n in (seg.start, seg.end))
    cols = [a] + [expanded.joint_names.index(n) for n in seg.twist_joints]
    ts = torch.tensor([0.0, 1 / 3, 2 / 3, 1.0], dtype=w.dtype)
    on = w[:, cols].sum(1) > 0
    share = (w[on][:, cols] * ts).sum(1) / w[on][:, cols].sum(1)
    t_v = ((rig.bind_vertices[on] - pos[a]) @ (pos[b] - pos[a])) / (pos[b] - pos[a]).square().sum()
    torch.testing.assert_close(share, t_v.clamp(0, 1), rtol=0, atol=1e-6)
    assert share.min() < 0.05 and share.max() > 0.95


# --- channel extractors against slow references ----------------------------------------------


def _slow_euler_x(m):
    """The a with Rx(a)^T M = Ry(b) Rz(c), cos b >= 0: that product has a zero at (1, 2), by search."""

    def residual(a):
        rx = np.array([[1, 0, 0], [0, math.cos(a), -math.sin(a)], [0, math.sin(a), math.cos(a)]])
        r = rx.T @ m
        return abs(r[1, 2]) + (0 if r[2, 2] >= 0 else 10)

    grid = np.linspace(-math.pi, math.pi, 1441)
    a = grid[np.argmin([residual(x) for x in grid])]
    lo, hi = a - 0.005, a + 0.005
    for _ in range(60):
        x, y = hi - 0.618 * (hi - lo), lo + 0.618 * (hi - lo)
        lo, hi = (lo, y) if residual(x) < residual(y) else (x, hi)
    return (lo + hi) / 2


def _slow_twist(m, axis):
    """argmax_phi trace(M Rot_axis(phi)^T): the twist that leaves the smallest swing."""
    n = np.asarray(axis) / np.linalg.norm(axis)
    k = np.array([[0, -n[2], n[1]], [n[2], 0, -n[0]], [-n[1], n[0], 0]])

    def score(phi):
        r = np.eye(3) + math.sin(phi) * k + (1 - math.cos(phi)) * k @ k
        return np.trace(m @ r.T)

    grid = np.linspace(-math.pi, math.pi, 721)
    phi = grid[np.argmax([score(p) for p in grid])]
    lo, hi = phi - 0.01, phi + 0.01
    for _ in range(60):  # golden-section refinement
        a, b = hi - 0.618 * (hi - lo), lo + 0.618 * (hi - lo)
        lo, hi = (a, hi) if score(a) < score(b) else (lo, b)
    return (lo + hi) / 2


def _wrap(a):
    return (a + math.pi) % (2 * math.pi) - math.pi


@pytest.mark.parametrize("mode", ["local_x_euler", "local_x_swing_twist", "aligned_x_swing_twist"])
def test_extractors_match_slow_references(mode):
    gen = torch.Generator().manual_seed(3)
    d = _random_rotations(200, 1.2, gen)
    bone = torch.randn(200, 3, generator=gen, dtype=torch.float64)
    got = twist_channel(mode, d, bone)
    for i in range(d.shape[0]):
        m = d[i].numpy()
        if mode == "local_x_euler":
            ref = _slow_euler_x(m)
        else:
            ref = _slow_twist(m, [1.0, 0.0, 0.0] if mode == "local_x_swing_twist" else bone[i].numpy())
        assert abs(_wrap(float(got[i]) - ref)) < 1e-5, (i, float(got[i]), ref)  # search precision


def test_swing_twist_half_angle_is_stable_near_identity_and_has_finite_gradients():
    d = torch.eye(3, dtype=torch.float64).repeat(4, 1, 1).requires_grad_()
    for mode in ("local_x_euler", "local_x_swing_twist", "aligned_x_swing_twist"):
        ang = twist_channel(mode, d, torch.tensor([0.0, 1.0, 0.0], dtype=torch.float64).expand(4, 3))
        (g,) = torch.autograd.grad(ang.sum(), d)
        assert ang.abs().max() == 0 and torch.isfinite(g).all()


# --- evaluation ------------------------------------------------------------------------------


def _mixed_modes(definition):
    """The shipped sidecar with some twist joints read by the two local extractors."""
    d = definition.to_dict()
    d["modes"] = ["local_x_euler", "local_x_swing_twist", "aligned_x_swing_twist"]
    extractor = {"axis": "x", "reference": "bind", "source_rotation": "absolute_local"}
    d["channel_extractors"] |= {m: extractor for m in d["modes"][:2]}
    d["rotation_extraction"] = {
        "default": "aligned_x_swing_twist",
        "per_procedural_joint": {
            "LeftForeArmTwist1": "local_x_euler",
            "LeftForeArmTwist3": "local_x_swing_twist",
            "RightArmTwist2": "local_x_euler",
            "LeftShinTwist1": "local_x_swing_twist",
        },
    }
    return parse(d)


def test_angles_match_a_per_joint_loop(layers, definition, rig):
    _, _, prepared = layers
    definition = _mixed_modes(definition)
    twist = ProceduralTwist(definition, rig)
    assert twist.modes == ("aligned_x_swing_twist", "local_x_euler", "local_x_swing_twist")
    gen = torch.Generator().manual_seed(1)
    eye = torch.eye(3, dtype=torch.float64).expand(3, 1, 3, 3)
    local = torch.cat([eye, _random_rotations(3 * 77, 0.8, gen).view(3, 77, 3, 3)], 1)
    got = twist.angles(local, prepared.rest_rotations, prepared.rest_joints)
    names = rig.joint_names
    bind_local = _bind_local(prepared, rig)[0]
    rest_r, rest_p = prepared.rest_rotations[0], prepared.rest_joints[0]
    m = definition.rotation
    for b in range(3):
        for k, name in enumerate(definition.twist_joints):  # the slow way: one joint at a time
            seg = definition.segment_of(name)
            mode = definition.rotation_extraction.mode_of(name)
            total = 0.0
            for r, c, v in zip(m.rows, m.columns, m.values, strict=True):
                if r != name:
                    continue
                j = names.index(c)
                d = (bind_local[j].T @ local[b, j]).numpy()
                bone = (rest_r[j].T @ (rest_p[names.index(seg.end)] - rest_p[names.index(seg.start)])).numpy()
                if mode == "local_x_euler":
                    channel = _slow_euler_x(d)
                else:
                    channel = _slow_twist(d, bone if mode.startswith("aligned") else [1.0, 0.0, 0.0])
                total += v * channel
            assert abs(float(got[b, k]) - total) < 1e-5


def test_bind_pose_and_pure_bending_match_plain_lbs(layers, rig):
    plain, twisted, prepared = layers
    gen = torch.Generator().manual_seed(2)
    bind_local = _bind_local(prepared, rig).expand(4, -1, -1, -1).clone()
    transl = torch.randn(4, 3, generator=gen, dtype=torch.float64) * 0.1
    out_p = plain.pose(prepared, bind_local[:, 1:], transl=transl, absolute=True)
    out_t = twisted.pose(prepared, bind_local[:, 1:], transl=transl, absolute=True)
    assert (out_t.vertices - out_p.vertices).abs().max() < 1e-10
    assert (
        out_t.vertices - (prepared.rest_vertices + (transl - prepared.rest_joints[:, 1])[:, None])
    ).abs().max() < 1e-9
    # Bend everything: non-drivers freely, drivers only by swings (axes normal to their bone).
    local = bind_local @ _random_rotations(4 * 78, 0.7, gen).view(4, 78, 3, 3)
    names = rig.joint_names
    rest_r, rest_p = prepared.rest_rotations[0], prepared.rest_joints[0]
    ends = {s.driver: s for s in canonical_definition().segments}
    for name in DRIVERS:
        j, seg = names.index(name), ends[name]
        bone = rest_r[j].T @ (rest_p[names.index(seg.end)] - rest_p[names.index(seg.start)])
        axis = torch.linalg.cross(bone.expand(4, 3), torch.randn(4, 3, generator=gen, dtype=torch.float64))
        swing = axis_angle_to_matrix(0.9 * torch.nn.functional.normalize(axis, dim=-1))
        local[:, j] = bind_local[:, j] @ swing
    out_p = plain.pose(prepared, local[:, 1:], transl=transl, absolute=True)
    out_t = twisted.pose(prepared, local[:, 1:], transl=transl, absolute=True)
    assert (out_t.vertices - out_p.vertices).abs().max() < 1e-10
    # Twisting a hand changes the forearm, never the public joints.
    local[:, names.index("LeftHand")] = local[:, names.index("LeftHand")] @ axis_angle_to_matrix(
        torch.tensor([2.0, 0.0, 0.0], dtype=torch.float64)
    )
    out_p = plain.pose(prepared, local[:, 1:], transl=transl, absolute=True)
    out_t = twisted.pose(prepared, local[:, 1:], transl=transl, absolute=True)
    assert torch.equal(out_t.joints, out_p.joints) and torch.equal(out_t.transforms, out_p.transforms)
    assert (out_t.vertices - out_p.vertices).abs().max() > 0.01


def _radius(vertices, joints, names, seg_start, seg_end, select):
    a, b = joints[:, names.index(seg_start)], joints[:, names.index(seg_end)]
    u = torch.nn.functional.normalize(b - a, dim=-1)
    rel = vertices[:, select] - a[:, None]
    return (rel - (rel * u[:, None]).sum(-1, keepdim=True) * u[:, None]).norm(dim=-1)


def test_twist_keeps_the_forearm_round(layers, rig):
    plain, twisted, prepared = layers
    names = rig.joint_names
    local = _bind_local(prepared, rig).clone()
    j = names.index("LeftHand")
    bone = prepared.rest_rotations[0, j].T @ (prepared.rest_joints[0, j] - prepared.rest_joints[0, j - 1])
    local[:, j] = local[:, j] @ axis_angle_to_matrix(math.radians(150) * bone / bone.norm())
    w = rig.dense_skinning_weights()
    select = w[:, names.index("LeftForeArm")] > 0.3
    rest = _radius(prepared.rest_vertices, prepared.rest_joints, names, "LeftForeArm", "LeftHand", select)
    radius = {}
    for key, layer in (("plain", plain), ("twist", twisted)):
        out = layer.pose(prepared, local[:, 1:], absolute=True)
        radius[key] = (_radius(out.vertices, out.joints, names, "LeftForeArm", "LeftHand", select) / rest).min()
    assert radius["plain"] < 0.5 < 0.8 < radius["twist"], radius


def test_gradients_flow_through_twist(rig):
    layer = BodyLayer(rig, procedural=True)
    prepared = layer.prepare_rest(rig.bind_vertices[None])
    names = rig.joint_names
    idx = [names.index(n) - 1 for n in ("LeftHand", "RightArm", "LeftFoot")]
    verts = torch.randperm(rig.num_vertices, generator=torch.Generator().manual_seed(0))[:40]

    def f(aa):
        pose = torch.zeros(1, 77, 3, dtype=torch.float64).index_put((torch.tensor(0), torch.tensor(idx)), aa)
        return layer.pose(prepared, pose).vertices[0, verts]

    aa = (0.3 * torch.randn(3, 3, dtype=torch.float64, generator=torch.Generator().manual_seed(1))).requires_grad_()
    assert torch.autograd.gradcheck(f, (aa,), eps=1e-6, atol=1e-6)


def test_procedural_layer_keeps_the_public_interface(rig):
    layer = BodyLayer(rig, procedural=True).float()
    prepared = layer.prepare_rest(rig.bind_vertices[None].float())
    out = layer.pose(prepared, 0.2 * torch.randn(2, 77, 3))
    assert out.vertices.shape == (2, rig.num_vertices, 3) and out.vertices.dtype == torch.float32
    assert out.joints.shape == (2, 78, 3) and out.transforms.shape == (2, 78, 4, 4)
    assert joint_index("LeftHand") < 78
    with pytest.raises(TypeError, match="procedural"):
        BodyLayer(rig, procedural="yes")


def test_compile_rejects_a_definition_that_does_not_fit_the_rig(rig, definition, small_rig):
    from unibody.procedural import ProceduralFormatError

    with pytest.raises(ProceduralFormatError, match="main_joint_names"):
        ProceduralTwist(definition, small_rig)
    d = definition.to_dict()
    seg = d["segments"][1]
    seg["end"] = "RightHand"  # not below LeftForeArm
    for m in d["parameter_matrices"].values():
        m["columns"] = ["RightHand" if c == "LeftHand" else c for c in m["columns"]]
    with pytest.raises(ProceduralFormatError, match=r"segments\[1\]\.end"):
        ProceduralTwist(parse(d), rig)
