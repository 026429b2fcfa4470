"""Articulated occupancy (paper 002): parts, the network's invariants, the shipped weights, losses."""

from __future__ import annotations

import math

import pytest
import torch

from unibody.body import BodyOutput
from unibody.geometry.rotations import axis_angle_to_matrix
from unibody.occupancy import BodyOccupancy, BodyParts, resolve_self_intersections
from unibody.occupancy import data as occ_data
from unibody.occupancy.metrics import part_intersections
from unibody.occupancy.model import OUTSIDE, default_weights_path, local_features
from unibody.occupancy.parts import PART_JOINTS
from unibody.occupancy.train import TrainConfig, evaluate, iou, make_net, train
from unibody.rig import Rig

pytestmark = pytest.mark.filterwarnings("ignore::UserWarning")


@pytest.fixture(scope="module")
def shipped() -> BodyOccupancy:
    return BodyOccupancy.pretrained()


@pytest.fixture(scope="module")
def bodies() -> tuple[BodyOutput, torch.Tensor]:
    return occ_data.pose_bodies(3, seed=1, index=7)


def test_parts_cover_every_vertex_and_merge_by_name():
    rig = Rig.canonical()
    parts = BodyParts.canonical()
    assert parts.num_parts == len(PART_JOINTS) == 17
    assert parts.vertex_part.shape == (rig.num_vertices,)
    assert int(parts.vertex_part.min()) >= 0 and int(parts.vertex_part.max()) < parts.num_parts
    assert torch.bincount(parts.vertex_part, minlength=17).min() > 100
    assert parts.face_part.shape == (rig.faces.shape[0],)
    w = rig.dense_skinning_weights()
    name = dict(enumerate(rig.joint_names))
    owner = w.argmax(1)
    for joint, part in (("LeftHandIndex3", "LeftHand"), ("Jaw", "Head"), ("RightToeBase", "RightFoot"),
                        ("LeftShoulder", "Chest"), ("Spine1", "Hips"), ("LeftForeArm", "LeftForeArm")):  # fmt: skip
        v = owner == rig.joint_names.index(joint)
        assert v.any(), name
        assert (parts.vertex_part[v] == PART_JOINTS.index(part)).all(), joint
    k = PART_JOINTS.index
    assert parts.parents[k("LeftArm")] == k("Chest") and parts.parents[k("Head")] == k("Neck1")
    assert torch.equal(parts.allowed, parts.allowed.T) and not parts.allowed.diagonal().any()
    assert not parts.allowed[k("LeftArm"), k("LeftForeArm")]  # parent and child
    assert not parts.allowed[k("LeftLeg"), k("RightLeg")]  # a named exclusion
    assert parts.allowed[k("LeftHand"), k("Chest")] and parts.allowed[k("LeftHand"), k("RightHand")]


def test_sparse_decoding_equals_dense_box_masked_decoding(bodies):
    torch.manual_seed(0)
    net = make_net(width=32, depth=2, samples=16, encoder_width=16, code=16)
    out, _ = bodies
    enc = net.encode(out.vertices, out.transforms)
    points = out.vertices[:, ::97] + 0.01 * torch.randn(3, 187, 3)
    u, inside = enc.to_boxes(points)
    b, t, k = u.shape[:3]
    bb, tt, kk = (i.flatten() for i in torch.meshgrid(torch.arange(b), torch.arange(t), torch.arange(k), indexing="ij"))
    uu = u[bb, tt, kk]
    dense = net.decode(uu, local_features(uu, bb, kk, enc), enc.bias[bb, kk]).view(b, t, k)
    expected = torch.where(inside, dense, torch.full_like(dense, OUTSIDE))
    assert inside.any(-1).float().mean() > 0.8
    torch.testing.assert_close(net.part_logits(points, enc), expected, rtol=1e-5, atol=1e-5)


def test_local_features_match_a_brute_force_nearest_sample(bodies):
    torch.manual_seed(0)
    net = make_net(width=32, depth=2, samples=16, encoder_width=16, code=16).double()
    out, _ = bodies
    enc = net.encode(out.vertices.double(), out.transforms.double())
    n = 500
    b, k = torch.randint(3, (n,)), torch.randint(17, (n,))
    u = 2 * torch.rand(n, 3, dtype=torch.float64) - 1
    feat = local_features(u, b, k, enc)
    x = u * enc.half[b, k] + enc.center[b, k]
    samples = enc.samples[b, k]  # (n, S, 3)
    j = (samples - x[:, None]).norm(dim=-1).argmin(1)
    p, normal = samples[torch.arange(n), j], enc.normals[b, k][torch.arange(n), j]
    torch.testing.assert_close(feat[:, :3], (x - p) / enc.half[b, k])
    torch.testing.assert_close(feat[:, 4:], normal)
    torch.testing.assert_close(normal.norm(dim=-1), torch.ones(n, dtype=torch.float64))
    assert (feat[:, 3].sign() == ((x - p) * normal).sum(-1).sign()).all()


def test_occupancy_gradients_pass_gradcheck(bodies):
    torch.manual_seed(0)
    net = make_net(width=16, depth=2, samples=8, encoder_width=8, code=8).double()
    out, _ = bodies
    v0, g = out.vertices[:1].double(), out.transforms[:1].double()
    points = (v0[:, ::1500] + 0.004 * torch.randn(1, 13, 3, dtype=torch.float64)).requires_grad_(True)
    moved = torch.zeros(1, 40, 3, dtype=torch.float64, requires_grad=True)
    picked = torch.arange(0, 18056, 452)[:40]

    def occupancy(p, dv):
        v = v0.index_add(1, picked, dv)
        return net(p, net.encode(v, g))

    assert (occupancy(points, moved) > 0).any()
    assert torch.autograd.gradcheck(occupancy, (points, moved), eps=1e-7, atol=1e-6)


def test_occupancy_follows_rigid_motion_of_the_body(bodies):
    torch.manual_seed(0)
    net = make_net(width=32, depth=2, samples=16, encoder_width=16, code=16).double()
    out, _ = bodies
    r = axis_angle_to_matrix(torch.tensor([0.3, -1.2, 0.7], dtype=torch.float64))
    t = torch.tensor([0.4, -0.2, 1.5], dtype=torch.float64)
    v, g = out.vertices.double(), out.transforms.double()
    moved_g = g.clone()
    moved_g[..., :3, :3] = r @ g[..., :3, :3]
    moved_g[..., :3, 3] = g[..., :3, 3] @ r.T + t
    points = v[:, ::50] + 0.03 * torch.randn(3, 362, 3, dtype=torch.float64)
    before = net(points, net.encode(v, g))
    after = net(points @ r.T + t, net.encode(v @ r.T + t, moved_g))
    torch.testing.assert_close(after, before, rtol=1e-7, atol=1e-7)


def test_shipped_weights_are_full_inside_and_empty_far_outside(shipped, bodies):
    out, faces = bodies
    joints = out.joints[:, [Rig.canonical().joint_names.index(n) for n in ("Spine2", "Chest", "LeftArm", "RightShin")]]
    assert occ_data.inside_mesh(out.vertices, faces, joints).all()
    assert (shipped.query(joints, out) > 0.9).all()
    lo, hi = out.vertices.amin(1, keepdim=True), out.vertices.amax(1, keepdim=True)
    far = torch.cat([lo - 0.3, hi + 0.3, (lo + hi) / 2 + torch.tensor([0.0, 0.0, 1.0])], 1)
    assert (shipped.query(far, out) < 0.01).all()


def test_shipped_weights_iou_on_held_out_bodies(shipped):
    res = evaluate(shipped.net, bodies=4, points=5000, seed=2)
    assert res["uniform"] > 95.0 and res["surface"] > 89.0, res  # shipped: 96.7 and 92.2


def test_iou():
    a = torch.tensor([[1, 1, 0, 0], [0, 0, 0, 0]], dtype=torch.bool)
    b = torch.tensor([[1, 0, 1, 0], [0, 0, 0, 0]], dtype=torch.bool)
    torch.testing.assert_close(iou(a, b), torch.tensor([1 / 3, 1.0], dtype=torch.float64))


def test_winding_numbers_label_a_posed_body(bodies):
    out, faces = bodies
    centre = out.joints[:, 1:2]  # the Hips are inside
    far = out.vertices.amax(1, keepdim=True) + 1.0
    inside = occ_data.inside_mesh(out.vertices, faces, torch.cat([centre, far], 1))
    assert inside[:, 0].all() and not inside[:, 1].any()


def _intersecting_body():
    """A body whose left hand sinks into the chest (a forearm folded across the torso)."""
    from unibody.body import BodyLayer

    layer = BodyLayer.from_pca(num_components=10)
    names = Rig.canonical().joint_names
    pose = torch.zeros(1, 77, 3)
    pose[0, names.index("LeftArm") - 1] = torch.tensor([0.0, -1.3, -0.3])
    pose[0, names.index("LeftForeArm") - 1] = torch.tensor([0.0, -2.3, 0.0])
    return layer, torch.zeros(1, 10), pose


def test_losses_have_finite_gradients(shipped):
    layer, params, pose = _intersecting_body()
    pose = pose.clone().requires_grad_(True)
    transl = torch.zeros(1, 3, requires_grad=True)
    out = layer(params, pose, transl=transl)
    loss = shipped.self_intersection_loss(out, generator=torch.Generator().manual_seed(0))
    assert float(loss) > 0
    (grad,) = torch.autograd.grad(loss.sum(), pose)
    assert torch.isfinite(grad).all() and grad.abs().sum() > 0
    grid = torch.linspace(-0.5, 0.5, 101)
    floor = torch.stack(torch.meshgrid(grid, torch.tensor([-0.6]), grid, indexing="ij"), -1).reshape(-1, 3)
    coll = shipped.collision_loss(floor, layer(params, pose.detach(), transl=transl))
    assert float(coll) > 0
    (g_t,) = torch.autograd.grad(coll.sum(), transl)
    assert torch.isfinite(g_t).all() and g_t[0, 1] < 0  # lifting the body reduces the penetration


def test_resolve_reduces_the_self_intersection(shipped):
    layer, params, pose = _intersecting_body()
    before = pose.clone()
    res = resolve_self_intersections(shipped, layer, params, pose, steps=40)
    assert torch.equal(pose, before)
    assert res.loss.shape == (41, 1)
    assert float(res.loss[-1, 0]) < 0.25 * float(res.loss[0, 0])
    faces = layer.faces.long()
    with torch.no_grad():
        exact = [int(part_intersections(layer(params, p).vertices, faces, shipped.parts)[0]) for p in (pose, res.pose)]
    assert exact[0] > 100 and exact[1] < 0.2 * exact[0], exact
    assert torch.equal(res.pose[:, 0], pose[:, 0])  # the Hips stay
    names = Rig.canonical().joint_names
    for name in ("LeftEye", "LeftHandIndex2", "RightToeBase"):  # they move no part frame
        assert torch.equal(res.pose[:, names.index(name) - 1], pose[:, names.index(name) - 1]), name
    change = (res.pose - pose).norm(dim=-1).max()
    assert 0 < float(change) < math.radians(60)


def test_resolve_stops_items_separately_with_one_shared_identity(shipped):
    layer, params, pose = _intersecting_body()
    pose = torch.cat([torch.zeros_like(pose), pose])  # the T-pose has nothing to resolve
    with torch.no_grad():  # a caller's no_grad (the viewer's command) is no matter: it enables its own
        res = resolve_self_intersections(shipped, layer, params, pose, steps=30)
    assert int(res.steps[0]) == 9 and torch.equal(res.pose[0], pose[0])  # ten zero terms, never moved
    assert float(res.loss[-1, 1]) < 0.25 * float(res.loss[0, 1])


def test_extract_mesh_is_a_closed_outward_surface_of_the_right_volume(shipped, bodies):
    out, faces = bodies
    one = BodyOutput(*(x[:1] for x in (out.vertices, out.joints, out.transforms, out.rest_vertices)))
    (verts, tris) = shipped.extract_mesh(one, resolution=64)[0]

    def volume(v, f):
        a, b, c = v[f[:, 0]], v[f[:, 1]], v[f[:, 2]]
        return float((a * torch.linalg.cross(b, c)).sum() / 6)

    truth = volume(out.vertices[0].double(), faces.long())
    assert truth > 0
    assert abs(volume(verts.double(), tris) / truth - 1) < 0.1


def test_bad_input_is_named(shipped, bodies):
    out, _ = bodies
    with pytest.raises(ValueError, match="points"):
        shipped.query(torch.zeros(3, 5, 2), out)
    with pytest.raises(ValueError, match="points"):
        shipped.query(torch.full((5, 3), float("nan")), out)
    with pytest.raises(TypeError, match="points"):
        shipped.query(torch.zeros(5, 3, dtype=torch.float64), out)
    with pytest.raises(ValueError, match="body.vertices"):
        shipped.query(torch.zeros(5, 3), BodyOutput(out.vertices[:, :100], out.joints, out.transforms, out.vertices))
    with pytest.raises(TypeError, match="body"):
        shipped.query(torch.zeros(5, 3), out.vertices)
    with pytest.raises(FileNotFoundError, match="path"):
        BodyOccupancy.pretrained("/nonexistent/weights.pt")
    layer, params, pose = _intersecting_body()
    with pytest.raises(ValueError, match="patience"):
        resolve_self_intersections(shipped, layer, params, pose, patience=0)
    # Each was accepted or failed elsewhere: a NaN prior weight as "pose: expected finite values",
    # samples -3 inside torch, 3 identities for 1 pose silently cut to 1, a string as rigid_parts.
    for kw, error, match in (
        ({"prior_weight": float("nan")}, ValueError, r"prior_weight: expected a finite number >= 0, got nan"),
        ({"prior_weight": -5.0}, ValueError, r"prior_weight: expected a finite number >= 0"),
        ({"lr": float("nan")}, ValueError, r"lr: expected a finite number > 0, got nan"),
        ({"samples": -3}, ValueError, r"samples: expected an integer >= 1, got -3"),
        ({"rigid_parts": "no"}, TypeError, r"rigid_parts: expected True or False, got 'no'"),
        ({"params": params.expand(3, -1)}, ValueError, r"params: expected \(1, K\) for 1 pose\(s\), got \(3, 10\)"),
    ):
        args = {"params": params, **kw}
        with pytest.raises(error, match=match):
            resolve_self_intersections(shipped, layer, args.pop("params"), pose, steps=1, **args)
    with pytest.raises(TypeError, match=r"occupancy: expected a BodyOccupancy"):
        resolve_self_intersections("shipped", layer, params, pose)


def test_training_runs_and_resumes(tmp_path):
    cfg = TrainConfig(steps=2, bodies=1, per_part=16, identities=4, eval_every=1000, eval_bodies=1, save_every=1)
    net_config = {"width": 16, "depth": 2, "samples": 8, "encoder_width": 8, "code": 8}
    path = tmp_path / "ckpt.pt"
    train(path, cfg, net_config, log=lambda _: None)
    first = torch.load(path, weights_only=True)  # checkpoints are plain data
    assert first["step"] == 2 and len(first["history"]) >= 1
    train(path, cfg, net_config, log=lambda _: None)  # nothing left to do: resumes at the end
    with pytest.raises(ValueError, match="configuration"):
        train(path, TrainConfig(steps=3, bodies=1, per_part=16, identities=4), net_config, log=lambda _: None)


def test_shipped_file_records_its_command():
    state = torch.load(default_weights_path(), weights_only=True)
    assert state["command"].startswith("OMP_NUM_THREADS=1 python scripts/train_occupancy.py")
    assert state["train"]["seed"] == 0


class _RunsCode:
    """Pickles as a call of ``os.system``: a checkpoint that runs a command when unpickled unsafely."""

    def __init__(self, command: str) -> None:
        self.command = command

    def __reduce__(self):
        import os

        return os.system, (self.command,)


def test_resume_refuses_a_checkpoint_that_would_run_code(tmp_path):
    marker = tmp_path / "pwned"
    path = tmp_path / "ckpt.pt"
    cfg = TrainConfig(steps=2, bodies=1, per_part=16, identities=4)
    torch.save({"model": _RunsCode(f"touch {marker}"), "optimizer": {}, "step": 0, "history": [],
                "train": {}, "net": {}}, path)  # fmt: skip
    with pytest.raises(ValueError, match=r"ckpt\.pt: not a training checkpoint that loads as plain data.*system"):
        train(path, cfg, {}, log=lambda _: None)
    assert not marker.exists()
    path.write_bytes(path.read_bytes()[:100])  # a truncated checkpoint: the same clear error
    with pytest.raises(ValueError, match=r"ckpt\.pt: not a training checkpoint"):
        train(path, cfg, {}, log=lambda _: None)
    torch.save({"model": {}, "step": "2"}, path)
    with pytest.raises(ValueError, match=r"ckpt\.pt: checkpoint entry 'optimizer': expected dict, got nothing"):
        train(path, cfg, {}, log=lambda _: None)


def test_checkpoint_saves_never_follow_a_planted_link(tmp_path):
    victim = tmp_path / "victim.txt"
    victim.write_text("precious")
    path = tmp_path / "ckpt.pt"
    (tmp_path / "ckpt.tmp").symlink_to(victim)  # the temporary name the trainer used to write through
    cfg = TrainConfig(steps=1, bodies=1, per_part=16, identities=4, eval_every=1000, eval_bodies=1, save_every=1)
    train(path, cfg, {"width": 16, "depth": 2, "samples": 8, "encoder_width": 8, "code": 8}, log=lambda _: None)
    assert victim.read_text() == "precious"
    assert (tmp_path / "ckpt.tmp").is_symlink() and not path.is_symlink()
    ckpt = torch.load(path, weights_only=True)  # the checkpoint is plain data
    assert ckpt["step"] == 1 and isinstance(ckpt["history"], list)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["ckpt.pt", "ckpt.tmp", "victim.txt"]  # no temporary left
