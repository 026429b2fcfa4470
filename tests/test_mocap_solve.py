"""MoSh-like marker solve: recovery of a known synthetic body, replay, layouts from one frame.

Ground truth: a PCA body (coefficients ~ N(0, 1), seeded), a smooth 20-frame motion (sinusoids
on arms, legs, spine and head, a turning or tumbling Hips) and markers placed with
``place_markers`` from the shipped ``cmu41`` layout on the posed meshes, i.e. on the posed
vertex normals, not by the solver's own skinned latent markers.
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest
import torch

from unibody.body import BodyLayer
from unibody.geometry.rotations import axis_angle_to_matrix
from unibody.mocap._marker_body import BODY_JOINTS, MarkerBody, _row_weights
from unibody.mocap.layout import MarkerLayout, place_markers
from unibody.mocap.solve import (
    SolveConfig,
    derive_layout,
    lab_to_unibody,
    pick_frames,
    solve_markers,
    unibody_to_lab,
)
from unibody.motion import load_motion, save_motion
from unibody.rig import joint_index
from unibody.synth.poses import sample_poses

EVALDATA = Path("/work/shared/evaldata")
K = 16
FPS = 10.0  # the test motion: one full swing per 20 frames (2 s)
BODY = [joint_index(n) for n in BODY_JOINTS]


@pytest.fixture(scope="module")
def layer() -> BodyLayer:
    return BodyLayer.from_pca(num_components=K, dtype=torch.float64)


@pytest.fixture(scope="module")
def layout() -> MarkerLayout:
    return MarkerLayout.load("cmu41")


def _motion(seed: int, tumble: bool, frames: int = 20):
    g = torch.Generator().manual_seed(seed)
    beta = torch.randn(1, K, generator=g, dtype=torch.float64)
    phase = 2 * math.pi * torch.linspace(0, 1, frames, dtype=torch.float64)
    pose = torch.zeros(frames, 77, 3, dtype=torch.float64)
    # (joint, axis, offset, amplitude, phase shift): T-pose-relative, see unibody.synth.poses.
    for name, axis, off, amp, shift in (
        ("LeftArm", 2, -1.0, 0.6, 0.0),
        ("LeftArm", 1, 0.0, -0.3, 0.0),
        ("RightArm", 2, 1.0, -0.5, 1.0),
        ("LeftForeArm", 1, -0.8, -0.6, 0.0),
        ("RightForeArm", 1, 0.5, 0.4, 0.0),
        ("LeftLeg", 0, 0.0, -0.6, 0.0),
        ("LeftShin", 0, 0.5, 0.5, 0.0),
        ("RightLeg", 0, 0.0, 0.4, 0.0),
        ("RightShin", 0, 0.3, 0.3, 0.5 * math.pi),
        ("Spine2", 0, 0.0, 0.2, 0.0),
        ("Head", 1, 0.0, 0.3, 0.0),
    ):
        pose[:, joint_index(name) - 1, axis] += off + amp * torch.sin(phase + shift)
    t = phase / (2 * math.pi)
    if tumble:  # a full turn about the left-right axis: handstand half-way
        pose[:, 0, 0] = 6.0 * t
    else:
        pose[:, 0, 1] = 2.0 * t
    transl = torch.stack([0.5 * t, 0.9 + 0.05 * torch.sin(4 * t), 0.3 * t], -1)
    return beta, pose, transl


def _synthetic(layer, layout, seed: int, tumble: bool = False, frames: int = 20):
    beta, pose, transl = _motion(seed, tumble, frames)
    out = layer.pose(layer.prepare_identity(beta), pose, transl=transl)
    points = place_markers(out.vertices, layer.faces, layout.vertices, layout.distance)
    return points, out.joints, out.rest_vertices[0]


def _joint_error(layer, result, joints) -> torch.Tensor:
    """(T, 23) m, body-joint error of the result replayed in the layer."""
    prep = layer.prepare_identity(result.identity[None].double())
    out = layer.pose(prep, result.pose.double(), transl=result.transl.double())
    return (out.joints[:, BODY] - joints[:, BODY]).norm(dim=-1)


@pytest.fixture(scope="module")
def clean(layer, layout):
    points, joints, _ = _synthetic(layer, layout, seed=1)
    return points.float(), joints, solve_markers(points.float(), layout, fps=FPS)


def test_solve_recovers_a_known_body(layer, layout, clean):
    points, joints, res = clean
    t, m = points.shape[:2]
    assert res.pose.shape == (t, 77, 3) and res.transl.shape == (t, 3) and res.identity.shape == (K,)
    assert res.latent.shape == (m, 3) and res.residual.shape == (t, m) and res.anchors.shape == (m,)
    assert res.pose.dtype == res.transl.dtype == res.residual.dtype == torch.float32
    assert bool(res.solved.all())
    assert float(res.residual.mean()) <= 0.005
    err = _joint_error(layer, res, joints)
    assert float(err.mean()) <= 0.010, f"mean body-joint error {1000 * float(err.mean()):.1f} mm"
    # Unsolved joints keep the fixed relaxed pose in every frame.
    eyes = [joint_index("LeftEye") - 1, joint_index("Jaw") - 1]
    assert float(res.pose[:, eyes].abs().max()) == 0.0


def test_missing_markers_and_a_tumble(layer, layout):
    points, joints, _ = _synthetic(layer, layout, seed=2, tumble=True)
    g = torch.Generator().manual_seed(2)
    missing = torch.rand(points.shape[:2], generator=g, dtype=torch.float64) < 0.1
    points = points.masked_fill(missing[..., None], float("nan"))
    res = solve_markers(points, layout, fps=FPS)
    assert res.pose.dtype == torch.float64
    assert bool(torch.equal(torch.isnan(res.residual), missing))
    assert float(res.residual.nanmean()) <= 0.005
    err = _joint_error(layer, res, joints)
    assert float(err.mean()) <= 0.015, f"mean body-joint error {1000 * float(err.mean()):.1f} mm"


def test_residual_is_the_replayed_latent_markers(layer, clean):
    """Skin the latent markers with the public layer: the distances are the reported residuals."""
    points, _, res = clean
    prep = layer.prepare_identity(res.identity[None].double())
    out = layer.pose(prep, res.pose.double(), transl=res.transl.double())
    rest = torch.eye(4, dtype=torch.float64).repeat(1, layer.num_joints, 1, 1)
    rest[..., :3, :3], rest[..., :3, 3] = prep.rest_rotations, prep.rest_joints
    skin = out.transforms @ torch.linalg.inv(rest)  # G_k T_k^-1
    weights = torch.zeros(layer.num_vertices, layer.num_joints, dtype=torch.float64)
    weights[layer.skinning.vertex, layer.skinning.joint] = layer.skinning.weight
    blend = torch.einsum("mk,tkij->tmij", weights[res.anchors], skin)
    model = (blend[..., :3, :3] @ res.latent.double()[:, :, None]).squeeze(-1) + blend[..., :3, 3]
    dist = (model - points.double()).norm(dim=-1)
    torch.testing.assert_close(dist, res.residual.double(), atol=2e-5, rtol=0)
    torch.testing.assert_close(res.markers.double(), model, atol=2e-5, rtol=0)


def test_to_motion_replays(tmp_path, layout, clean):
    points, joints, res = clean
    motion = res.to_motion(fps=FPS)
    assert motion.identity_backend == "pca" and motion.fps == FPS
    path = tmp_path / "solved.npz"
    save_motion(path, motion)
    back = load_motion(path)
    replay = BodyLayer.from_pca(num_components=back.identity.shape[0])  # float32, as a user would
    prep = replay.prepare_identity(torch.from_numpy(back.identity)[None])
    out = replay.pose(prep, torch.from_numpy(back.pose), transl=torch.from_numpy(back.transl))
    err = (out.joints[:, BODY].double() - joints[:, BODY]).norm(dim=-1)
    assert float(err.mean()) <= 0.010
    # The replayed skin carries the markers: every observed marker is near its anchor vertex.
    skin = (out.vertices[:, res.anchors] - points).norm(dim=-1)
    assert float(skin.max()) <= 0.06


def test_robust_solve_is_not_dragged_by_mislabelled_points(layer, layout, clean):
    """8 % of the labels moved to another marker's point: the Cauchy term keeps the body, squares do not."""
    points, joints, _ = clean
    g = torch.Generator().manual_seed(5)
    t, m = points.shape[:2]
    wrong = torch.rand(t, m, generator=g) < 0.08
    other = (torch.arange(m) + torch.randint(1, m, (t, m), generator=g)) % m  # never the marker itself
    bad = torch.where(wrong[..., None], points.gather(1, other[..., None].expand(-1, -1, 3)), points)
    errs = {}
    for robust in (0.0, 0.015):
        res = solve_markers(bad, layout, config=SolveConfig(robust=robust), fps=FPS)
        errs[robust] = float(_joint_error(layer, res, joints).mean())
        if robust:
            # the true points fit as in the clean solve; the moved ones stand out by far
            assert float(res.residual[~wrong].mean()) <= 0.003  # measured 0.9 mm (clean: 0.13 mm)
            assert float(res.residual[wrong].min()) > 0.03  # measured 131 mm
    # measured: 4.1 mm robust, 116 mm least squares (clean data: 2.6 mm either way)
    assert errs[0.015] <= 0.008, errs
    assert errs[0.0] > 0.05, errs


def test_robust_costs_and_row_weights_agree():
    """The IRLS row weights are the Cauchy cost's gradient over 2 r, and it is squares at small d."""
    g = torch.Generator().manual_seed(0)
    r = (0.05 * torch.randn(2, 7, 3, generator=g, dtype=torch.float64)).requires_grad_()
    data = 200 * torch.rand(2, 7, generator=g, dtype=torch.float64)
    cost, w2 = _row_weights(r, data, 0.01)
    (grad,) = torch.autograd.grad(cost.sum(), r)
    torch.testing.assert_close(grad, 2 * w2[..., None] * r.detach())
    tiny = 1e-5 * r.detach()
    squares, _ = _row_weights(tiny, data, 0.0)
    torch.testing.assert_close(_row_weights(tiny, data, 0.01)[0], squares, rtol=1e-6, atol=0)
    assert bool((w2 < data.square()).all())


def test_unsolved_frames_are_interpolated(layer, layout):
    points, joints, _ = _synthetic(layer, layout, seed=3)
    points = points.clone()
    points[9, 4:] = float("nan")  # 4 of 41 markers left: below min_visible
    res = solve_markers(points, layout, fps=FPS)
    assert res.solved.tolist() == [i != 9 for i in range(points.shape[0])]
    assert bool(torch.isfinite(res.pose).all())
    err = _joint_error(layer, res, joints)
    assert float(err[9].mean()) <= 0.03  # slerp between the neighbours of a smooth motion
    assert float(err[8].mean()) <= 0.010


def test_derive_layout_from_one_frame(layer, layout):
    points, _, rest = _synthetic(layer, layout, seed=1)
    g = torch.Generator().manual_seed(0)
    dist = torch.cdist(rest[layout.vertices], rest)
    guess = []
    for i in range(len(layout)):  # each marker moved 18-30 mm on the body
        ring = torch.nonzero((dist[i] > 0.018) & (dist[i] < 0.03)).flatten()
        guess.append(int(ring[torch.randint(ring.numel(), (1,), generator=g)]))
    initial = MarkerLayout("guess", layout.labels, torch.tensor(guess), layout.distance.clone())
    before = (rest[initial.vertices] - rest[layout.vertices]).norm(dim=-1).mean()
    derived = derive_layout(points[5], layout.labels, name="derived", initial=initial)
    assert derived.name == "derived" and derived.labels == layout.labels
    after = (rest[derived.vertices] - rest[layout.vertices]).norm(dim=-1).mean()
    assert float(after) <= 0.02 and float(after) <= 0.8 * float(before), (float(before), float(after))
    assert float(derived.distance.min()) > -0.005 and float(derived.distance.max()) < 0.03


def test_derive_layout_names_the_frames_unlabelled_points(layer, layout):
    """Markers of another protocol in the frame become new markers where they sit on the body."""
    points, _, rest = _synthetic(layer, layout, seed=2)
    hidden = list(range(1, 41, 5))  # RFHD, CLAV, LELB, RSHO, RWRB, RBWT, LHEE, RSHN: beside labelled ones
    shown = [i for i in range(len(layout)) if i not in hidden]
    known, extra = layout.subset([layout.labels[i] for i in shown]), layout.subset([layout.labels[i] for i in hidden])
    frame = points[7]
    unlabelled = torch.cat([frame[hidden], torch.full((1, 3), float("nan"))])  # a missing row is skipped
    derived = derive_layout(frame[shown], known.labels, name="session", initial=known, unlabelled=unlabelled)
    n = len(shown)
    assert derived.labels == (*known.labels, *(f"X{k:02d}" for k in range(1, len(hidden) + 1)))
    err = (rest[derived.vertices[n:]] - rest[extra.vertices]).norm(dim=-1)
    assert float(err.mean()) <= 0.012 and float(err.max()) <= 0.03, err  # measured: 0.9 cm mean, 2.4 cm max
    assert float((derived.distance[n:] - extra.distance).abs().max()) < 0.008  # measured: 6.2 mm
    clash = MarkerLayout("clash", ("X02", *known.labels[1:]), known.vertices, known.distance)
    with pytest.raises(ValueError, match="prefix: 'X' gives names"):
        derive_layout(frame[shown], clash.labels, name="x", initial=clash, unlabelled=frame[hidden])
    with pytest.raises(ValueError, match="unlabelled: expected shape"):
        derive_layout(frame[shown], known.labels, name="x", initial=known, unlabelled=frame[hidden, :2])


def test_jacobians_match_finite_differences(layout):
    """Marker and pose-prior Jacobians of the LM against central differences of the update."""
    body = MarkerBody(K, torch.device("cpu"))
    g = torch.Generator().manual_seed(4)
    ident = body.identity(torch.randn(1, K, generator=g, dtype=torch.float64))
    p, _ = body.latent(ident, layout.vertices, layout.distance.double(), 0.0)
    pose = sample_poses(2, g, dtype=torch.float64)
    local = body._absolute(axis_angle_to_matrix(pose))
    transl = torch.randn(2, 3, generator=g, dtype=torch.float64)
    x, g_rot, jac, _ = body.markers(ident, layout.vertices, p, local, transl, jacobian=True)
    r, jp = body.prior(local, g_rot)
    cols = [0, 4, 3 + 3 * BODY_JOINTS.index("LeftForeArm") + 2, 3 + 3 * BODY_JOINTS.index("RightShin")]
    eps = 1e-6
    for c in cols:
        step = torch.zeros(2, body.num_params, dtype=torch.float64)
        step[:, c] = eps
        out = []
        for sign in (1, -1):
            lo, tr = body.apply(local, transl, g_rot, sign * step)
            out.append((body.markers(ident, layout.vertices, p, lo, tr, jacobian=False)[0], body.prior(lo, None)[0]))
        torch.testing.assert_close((out[0][0] - out[1][0]) / (2 * eps), jac[..., c], atol=1e-6, rtol=1e-5)
        if c >= 6:  # joint slot s has prior row s - 1 (no prior on the Hips)
            s, k = divmod(c - 3, 3)
            fd = (out[0][1] - out[1][1]) / (2 * eps)
            torch.testing.assert_close(fd[:, s - 1], jp[:, s - 1, :, k], atol=1e-6, rtol=1e-5)
            assert float(fd.abs().sum()) == pytest.approx(float(fd[:, s - 1].abs().sum()), rel=1e-6)


def test_lab_frames_round_trip():
    p = torch.tensor([[1.0, 2.0, 3.0], [0.0, 0.0, 1.0]])
    y_up = lab_to_unibody(p)
    torch.testing.assert_close(y_up[1], torch.tensor([0.0, 1.0, 0.0]))  # lab up -> Y
    torch.testing.assert_close(unibody_to_lab(y_up), p)
    a = np.arange(12.0).reshape(2, 2, 3)
    np.testing.assert_array_equal(unibody_to_lab(lab_to_unibody(a)), a)
    assert lab_to_unibody(p, up="y") is p
    with pytest.raises(ValueError, match="up: expected 'y' or 'z'"):
        lab_to_unibody(p, up="x")


def test_pick_frames_is_tolerant():
    vis = torch.ones(30, 5, dtype=torch.bool)
    vis[:, 0] = False  # no complete frame anywhere
    vis[3, 1:] = False  # a frame with one visible marker: never picked
    vis[12, :] = True
    picked = pick_frames(vis, 3)
    assert picked.tolist()[1] == 12 and len(picked) == 3
    assert 3 not in pick_frames(vis[:5], 5).tolist()


def test_a_glitch_frame_neither_is_held_back_nor_drags_its_neighbours(layout, clean):
    """Frame 10 with the whole subject displaced 20 m (a broken export). Before, the quadratic
    temporal prior dragged the frames after it towards it (here at 60 Hz: 2 m off in the next
    frame, 0.1 m in the one after; a 40 m glitch in another take held its own frame 8 m back and
    the next five 30 m to 80 mm off); the prior is now Cauchy past 1000 m/s^2
    (``acceleration_robust``): every frame fits its own markers as in the clean solve."""
    points, fps = clean[0], 60.0  # a prior strong enough to hold a frame back
    ref = solve_markers(points, layout, fps=fps)
    glitch = points.clone()
    glitch[10] += 20.0
    res = solve_markers(glitch, layout, fps=fps)
    assert float(res.residual.median(1).values.max()) < 0.002
    assert float(res.residual.mean()) < 1.5 * float(ref.residual.mean())
    assert abs(float(res.transl[10, 0] - ref.transl[10, 0]) - 20.0) < 0.01
    squares = solve_markers(glitch, layout, fps=fps, config=SolveConfig(acceleration_robust=0.0))
    assert float(squares.residual.median(1).values[11]) > 0.5  # the old prior (kept on request): 2 m


def test_a_long_walk_is_metres_not_millimetres(layout, clean):
    """The subject travels 60 m over the take: the solve used to refuse it ("coordinates span 60
    units; millimetres?"); units are now judged as the labeler judges them, by the distances
    between a frame's markers."""
    points, _, ref = clean
    walk = points + torch.linspace(0, 60, len(points))[:, None, None] * torch.tensor([1.0, 0.0, 0.0])
    res = solve_markers(walk, layout, fps=FPS)
    assert float(res.residual.mean()) < 1.5 * float(ref.residual.mean())


def test_input_errors(layout):
    good = torch.zeros(4, len(layout), 3)
    with pytest.raises(ValueError, match=r"points: expected shape \(T, M, 3\)"):
        solve_markers(torch.zeros(4, 41), layout)
    with pytest.raises(ValueError, match="layout: 40 markers but points have 41"):
        solve_markers(good, layout.subset(layout.labels[:40]))
    with pytest.raises(ValueError, match="millimetres"):
        solve_markers(good + torch.linspace(0, 2000, 41)[None, :, None], layout)
    with pytest.raises(ValueError, match="all NaN"):
        solve_markers(torch.full_like(good, float("nan")), layout)
    few = torch.randn(4, len(layout), 3).index_fill(1, torch.arange(5, len(layout)), float("nan"))
    with pytest.raises(ValueError, match=r"points: no frame has the 13 visible markers a solve needs .* one frame: 5"):
        solve_markers(few, layout)  # before: every frame interpolated from none, markers 1.1 m off
    with pytest.raises(ValueError, match="got inf"):
        solve_markers(good.index_fill(0, torch.tensor([0]), float("inf")), layout)
    with pytest.raises(TypeError, match="float32 or float64"):
        solve_markers(good.long(), layout)
    with pytest.raises(ValueError, match="fps"):
        solve_markers(good, layout, fps=0.0)
    with pytest.raises(TypeError, match="MarkerLayout"):
        solve_markers(good, "cmu41")
    with pytest.raises(ValueError, match="not in the superset"):
        derive_layout(good[0, :2], ("LFHD", "NOSUCH"), name="x")


@pytest.mark.parametrize(
    ("field", "value", "message"),
    [
        ("marker_std", 0.0, "marker_std: expected a value > 0"),
        ("window", 2.5, "window: expected an int"),
        ("stage1_anneal", (), "stage1_anneal"),
        ("min_visible", 1.5, "min_visible"),
        ("shape_components", 200, "shape_components"),
        ("pose_prior_weight", float("nan"), "pose_prior_weight"),
        ("robust", -0.01, "robust: expected a value >= 0"),
        ("acceleration_robust", -1.0, "acceleration_robust: expected a value >= 0"),
    ],
)
def test_config_errors(field, value, message):
    with pytest.raises(ValueError, match=message):
        SolveConfig(**{field: value})


def test_real_cmu_sequence(layout):
    """CMU 85_02 (jumps and flips), first 120 frames, with the shipped cmu41 layout."""
    path = EVALDATA / "c3d" / "cmu_85_02.c3d"
    if not path.is_file():
        pytest.skip("evaldata not available")
    pytest.importorskip("ezc3d")
    from unibody.mocap.c3d import read_markers

    seq = read_markers(path)
    idx = [seq.labels.index(x) for x in layout.labels]
    points = lab_to_unibody(torch.from_numpy(seq.points[:120, idx]))
    res = solve_markers(points, layout, fps=seq.rate)
    assert bool(res.solved.all())
    # Measured 2.1 mm mean / 1.8 mm median; a failed solve (a limb or the body turned the wrong
    # way) is off by centimetres.
    assert float(res.residual.mean()) <= 0.006
    assert float(res.residual.median()) <= 0.004
