"""Frame orientation from torso labels, and the two-stage labeler built on it."""

from __future__ import annotations

import importlib.util
import math
from pathlib import Path

import pytest
import torch

from unibody.geometry.rotations import axis_angle_to_matrix, rotation_angle
from unibody.mocap.labeler import Labeler, _distinct, _surety, predict
from unibody.mocap.layout import MarkerLayout
from unibody.mocap.orient import NUDGES, TILTS, fit_rotation, torso_template
from unibody.mocap.synthetic import POSE

SCRIPT = Path(__file__).resolve().parents[1] / "scripts" / "train_labeler.py"


def _rotations(n: int, seed: int, dtype=torch.float64) -> torch.Tensor:
    g = torch.Generator().manual_seed(seed)
    return axis_angle_to_matrix(torch.randn(n, 3, generator=g, dtype=dtype) * 1.5)


@pytest.mark.parametrize("name", ["cmu41", "pig39"])
def test_torso_template_is_upright_facing_forward(name):
    layout = MarkerLayout.load(name)
    template, torso = torso_template(layout)
    at = dict(zip(layout.labels, template, strict=True))
    pelvis = ("LFWT", "RFWT", "LBWT", "RBWT", "RBAC") if name == "cmu41" else ("LASI", "RASI", "LPSI", "RPSI", "RBAK")
    assert {x for x, t in zip(layout.labels, torso, strict=True) if t} == {"C7", "T10", "CLAV", "STRN", *pelvis}
    front, back = pelvis[0], pelvis[2]
    assert at["CLAV"][2] > at["C7"][2] + 0.1 and at[front][2] > at[back][2] + 0.1  # +Z forward
    assert at[front][0] > 0.05 > -0.05 > at[pelvis[1]][0]  # +X to the body's left
    assert at["C7"][1] > at[front][1] + 0.3  # Y up


def test_fit_rotation_recovers_a_rotation_despite_wrong_labels():
    """CMU's nine torso markers, rotated, moved and jittered by 5 mm, with STRN's label given to a
    point 15 cm off: the reweighted fit recovers the rotation within 2.5 deg (median; 6 at most),
    one plain weighted Kabsch only within 6.6 deg (median). With the front waist labels swapped
    as well (3 of 9 wrong) the median error stays under 10 deg."""
    layout = MarkerLayout.load("cmu41")
    template, torso = torso_template(layout)
    names = [x for x, t in zip(layout.labels, torso, strict=True) if t]
    g = torch.Generator().manual_seed(0)
    b = 64
    targets = template[torso].double().expand(b, -1, -1)
    rot = _rotations(b, 1)
    points = targets @ rot + torch.randn(b, 1, 3, generator=g, dtype=torch.float64)  # p = R^T q + t
    points = points + 0.005 * torch.randn(b, len(names), 3, generator=g, dtype=torch.float64)
    lf, rf, st = names.index("LFWT"), names.index("RFWT"), names.index("STRN")
    points[:, st] += 0.15 * torch.nn.functional.normalize(torch.randn(b, 3, generator=g, dtype=torch.float64), dim=1)
    weights = torch.ones(b, len(names), dtype=torch.float64)
    robust = rotation_angle(fit_rotation(points, weights, targets) @ rot.transpose(1, 2)).rad2deg()
    plain = rotation_angle(fit_rotation(points, weights, targets, iters=1) @ rot.transpose(1, 2)).rad2deg()
    assert float(robust.median()) < 2.5 and float(robust.max()) < 6.0, robust
    assert float(plain.median()) > 5.0, plain
    swapped = targets.clone()
    swapped[:, [lf, rf]] = targets[:, [rf, lf]]
    both = rotation_angle(fit_rotation(points, weights, swapped) @ rot.transpose(1, 2)).rad2deg()
    assert float(both.median()) < 10.0, both


def test_fit_rotation_is_equivariant_and_needs_four_points():
    """Rotating the frame by Q turns the fit R into R Q^T: the oriented frame R p does not change."""
    g = torch.Generator().manual_seed(2)
    points = torch.randn(8, 12, 3, generator=g, dtype=torch.float64)
    targets = torch.randn(8, 12, 3, generator=g, dtype=torch.float64)
    weights = torch.rand(8, 12, generator=g, dtype=torch.float64)
    q = _rotations(8, 3)
    r = fit_rotation(points, weights, targets)
    rq = fit_rotation(points @ q.transpose(1, 2), weights, targets)
    torch.testing.assert_close(rq, r @ q.transpose(1, 2))
    few = weights.clone()
    few[:, 3:] = 0.0
    assert torch.equal(fit_rotation(points, few, targets), torch.eye(3, dtype=torch.float64).expand(8, 3, 3))
    with pytest.raises(ValueError, match="weights: expected shape"):
        fit_rotation(points, weights[:, :5], targets)


def _two_stage(num_labels=8, seed=0):
    torch.manual_seed(seed)
    first = Labeler(num_labels, width=16, layers=1, heads=2, refine=1)
    template = torch.randn(num_labels, 3)
    torso = torch.arange(num_labels) < 5
    return Labeler(num_labels, width=16, layers=1, heads=2, orienter=first, template=template, torso=torso)


def test_two_stage_labeler_saves_loads_and_keeps_its_first_stage_frozen(tmp_path):
    model = _two_stage().eval()
    assert all(not p.requires_grad for p in model.orienter.parameters())
    assert model.orienter.config.refine == 1
    pts = torch.randn(3, 10, 3)
    mask = torch.ones(3, 10, dtype=torch.bool)
    mask[0, 7:] = False
    model.save(tmp_path / "two.pt")
    loaded = Labeler.load(tmp_path / "two.pt").eval()
    assert loaded.config == model.config and torch.equal(loaded.template, model.template)
    assert loaded.orienter.config == model.orienter.config
    assert all(not p.requires_grad for p in loaded.orienter.parameters())
    with torch.no_grad():
        out = model(pts, mask)
        torch.testing.assert_close(loaded(pts, mask), out)
        padded = pts.clone()
        padded[0, 7:] = torch.nan  # padding may hold anything
        torch.testing.assert_close(model(padded, mask), out)
    loss = model(pts, mask).logsumexp(dim=(1, 2)).sum()
    loss.backward()
    assert model.orienter.bin_score.grad is None and model.bin_score.grad is not None
    double = _two_stage().double()
    assert double(pts.double(), mask).dtype == torch.float64


def test_second_stage_may_name_more_labels_than_its_orienter(tmp_path):
    """A session layout's labeler (general labels + extra markers) oriented by the general first stage."""
    torch.manual_seed(1)
    names = ("A", "B", "C", "D", "E", "F")
    first = Labeler(6, label_names=names, width=16, layers=1, heads=2)
    template, torso = torch.randn(6, 3), torch.arange(6) < 4
    session = ("X01", *names[:3], "X02", *names[3:])  # any order
    model = Labeler(8, label_names=session, width=16, layers=1, heads=2, orienter=first, template=template,
                    torso=torso).eval()  # fmt: skip
    pts, mask = torch.randn(2, 9, 3), torch.ones(2, 9, dtype=torch.bool)
    rot, centre = model.orient(pts, mask)
    assert rot.shape == (2, 3, 3) and centre.shape == (2, 3)
    assert model(pts, mask).shape == (2, 10, 9)
    model.save(tmp_path / "session.pt")
    loaded = Labeler.load(tmp_path / "session.pt").eval()
    assert loaded.label_names == session and loaded.orienter.label_names == names
    assert loaded.config == model.config
    with torch.no_grad():
        torch.testing.assert_close(loaded(pts, mask), model(pts, mask))


def test_two_stage_labeler_errors():
    first = Labeler(8, width=16, layers=1, heads=2)
    with pytest.raises(ValueError, match="template, torso"):
        Labeler(8, orienter=first)
    with pytest.raises(ValueError, match="orienter: expected a labeler of these labels"):
        Labeler(8, label_names="abcdefgh", orienter=first, template=torch.zeros(8, 3), torso=torch.ones(8, dtype=bool))
    with pytest.raises(ValueError, match="template: expected shape"):  # the orienter's 8 labels, not these 9
        Labeler(9, orienter=first, template=torch.zeros(9, 3), torso=torch.ones(9, dtype=torch.bool))
    with pytest.raises(ValueError, match="torso: expected a bool mask of at least 4"):
        Labeler(8, orienter=first, template=torch.zeros(8, 3), torso=torch.arange(8) < 2)
    with pytest.raises(ValueError, match="template: expected shape"):
        Labeler(8, orienter=first, template=torch.zeros(8, 2), torso=torch.ones(8, dtype=torch.bool))
    with pytest.raises(ValueError, match="no orienter"):
        first.orient(torch.zeros(1, 8, 3), torch.ones(1, 8, dtype=torch.bool))


@pytest.mark.slow
def test_training_script_trains_the_second_stage_only(tmp_path, monkeypatch):
    spec = importlib.util.spec_from_file_location("train_labeler", SCRIPT)
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    configs, make = [], mod.SyntheticMocap
    monkeypatch.setattr(mod, "SyntheticMocap", lambda layout, cfg, **kw: configs.append(cfg) or make(layout, cfg, **kw))
    tiny = ["--layout", "cmu41", "--batch", "8", "--threads", "1", "--width", "16", "--layers", "1", "--heads", "2",
            "--val-frames", "16", "--identities", "8", "--log-every", "1000"]  # fmt: skip
    mod.main([*tiny, "--steps", "3", "--out", str(tmp_path / "first")])
    first = Labeler.load(tmp_path / "first" / "labeler.pt")
    weights = str(tmp_path / "first" / "labeler.pt")
    mod.main([*tiny, "--steps", "4", "--out", str(tmp_path / "two"), "--orient-with", weights, "--init", weights])
    two = Labeler.load(tmp_path / "two" / "labeler.pt")
    for k, v in first.state_dict().items():
        assert torch.equal(two.orienter.state_dict()[k], v), k  # the first stage is never trained
    assert not torch.equal(two.embed[0].weight, first.embed[0].weight)  # the second is
    assert two.meta["orient_with"].endswith("labeler.pt") and two.orienter.config.refine == 1
    template, torso = torso_template(MarkerLayout.load("cmu41"))
    assert torch.equal(two.template, template) and torch.equal(two.torso, torso)
    # a session layout: cmu41 and two more markers; shared labels keep their score rows
    cmu = MarkerLayout.load("cmu41")
    session = MarkerLayout("session", (*cmu.labels, "X01", "X02"), torch.cat([cmu.vertices, torch.tensor([100, 200])]),
                           torch.cat([cmu.distance, torch.tensor([0.01, 0.01])]))  # fmt: skip
    session.save(tmp_path / "session.json")
    args = ["--layout", str(tmp_path / "session.json"), "--orient-with", weights, "--init", weights]
    assert all(c.pose == POSE and not c.fitted for c in configs)  # the recipe's poses and slides
    configs.clear()
    extra = ["--fitted", "0.02", "--neck-roll", "0.3", "--steps", "0"]
    mod.main([*tiny[2:], *args, *extra, "--out", str(tmp_path / "session")])
    three = Labeler.load(tmp_path / "session" / "labeler.pt")
    assert "--fitted 0.02 --neck-roll 0.3" in three.meta["command"]
    ranges = configs[0].pose["ranges"]
    for joint in ("Neck1", "Neck2", "Head"):  # only the sideways tilt (about Z) widens
        (lo, hi, relaxed), ref = ranges[joint], POSE["ranges"][joint]
        assert lo == (*ref[0][:2], -0.3) and hi == (*ref[1][:2], 0.3) and relaxed == ref[2]
    assert configs[0].fitted and configs[0].jitter_radius == 0.02
    assert POSE["ranges"]["Head"][1][2] == 0.15  # the recipe's own ranges are untouched
    assert three.label_names == session.labels and three.orienter.label_names == cmu.labels
    assert torch.equal(three.head[-1].weight[: len(cmu)], first.head[-1].weight)
    assert torch.equal(three.blocks[0].qkv.weight, first.blocks[0].qkv.weight)
    assert torch.equal(three.template, template)


def test_tilts_are_distinct_turns_that_tip_the_vertical_over_and_nudges_are_small():
    eye = torch.eye(3, dtype=torch.float64)
    torch.testing.assert_close(TILTS @ TILTS.transpose(1, 2), eye.expand(13, 3, 3))
    torch.testing.assert_close(torch.linalg.det(TILTS), torch.ones(13, dtype=torch.float64))
    up = TILTS[:, :, 1]  # where each tilt takes the vertical
    assert bool((up[:, 1] < math.cos(math.radians(44))).all())  # every one tips it 45 deg or more
    cos = ((TILTS[:, None] * TILTS[None]).sum(dim=(2, 3)) - 1) / 2  # cosine of the angle between two tilts
    assert bool((cos - 2 * torch.eye(13, dtype=torch.float64) < math.cos(math.radians(40))).all())
    assert torch.equal(NUDGES[0], eye) and len(NUDGES) == 7
    torch.testing.assert_close(rotation_angle(NUDGES[1:]), torch.full((6,), 0.35, dtype=torch.float64))


def test_retry_never_leaves_a_frame_less_sure_and_keeps_the_sure_ones(tmp_path):
    model = _two_stage(seed=1).eval()
    g = torch.Generator().manual_seed(2)
    pts, mask = torch.randn(16, 10, 3, generator=g), torch.ones(16, 10, dtype=torch.bool)
    mask[3, 6:] = False
    with torch.no_grad():
        plain = model(pts, mask)
        sure = predict(plain, mask)[1].sum(dim=1) / mask.sum(dim=1)
        cut = float(sure.median())
        for retry in (cut, 1.0):
            out = model(pts, mask, retry=retry)
            again = predict(out, mask)[1].sum(dim=1) / mask.sum(dim=1)
            assert bool((again >= sure - 1e-6).all())
            kept = sure >= retry
            torch.testing.assert_close(out[kept], plain[kept])
        assert bool((again > sure + 1e-4).any())  # some frame of an untrained model is surer turned
    retrying = Labeler(8, width=16, layers=1, heads=2, orienter=model.orienter, template=model.template,
                       torso=model.torso, retry=1.0)  # fmt: skip
    retrying.load_state_dict(model.state_dict())
    retrying.save(tmp_path / "r.pt")
    loaded = Labeler.load(tmp_path / "r.pt").eval()
    assert loaded.config.retry == 1.0
    with torch.no_grad():
        torch.testing.assert_close(loaded(pts, mask), model(pts, mask, retry=1.0))
    model(pts, mask, retry=cut).logsumexp(dim=(1, 2)).sum().backward()  # the frames kept carry gradients
    assert model.bin_score.grad is not None and model.bin_score.grad.isfinite()
    with pytest.raises(ValueError, match="retry: expected 0, or a confidence in"):
        Labeler(8, retry=0.5)  # no orienter
    with pytest.raises(ValueError, match="retry: expected 0, or a confidence in"):
        model(pts, mask, retry=1.5)


def test_distinct_drops_turns_within_two_degrees_of_an_earlier_one_of_the_same_frame():
    def turn(deg):
        return axis_angle_to_matrix(torch.tensor([0.0, 0.0, math.radians(deg)], dtype=torch.float64))

    r = _rotations(1, seed=5)[0]
    frame0 = [r, r @ turn(1.0), r @ turn(5.0), r, TILTS[0] @ r]
    frame1 = [r @ turn(3.0), r, r @ turn(1.5), r @ turn(90.0), r]
    rots = torch.stack([torch.stack(pair) for pair in zip(frame0, frame1, strict=True)])  # (K=5, F=2, 3, 3)
    assert _distinct(rots).tolist() == [[True, True], [False, True], [True, False], [False, True], [True, False]]


def test_surest_labels_the_kept_candidates_and_returns_the_surest_of_them():
    model = _two_stage(seed=3).eval()
    g = torch.Generator().manual_seed(4)
    pts, mask = torch.randn(5, 10, 3, generator=g), torch.ones(5, 10, dtype=torch.bool)
    mask[2, 7:] = False
    rots = _rotations(20, seed=6, dtype=torch.float32).view(4, 5, 3, 3)
    marker = torch.rand(4, 5, 10, generator=g) < 0.8
    keep = torch.rand(4, 5, generator=g) < 0.6
    keep[0] = True
    with torch.no_grad():
        best = model(pts, mask, retry=0.0)
        sure = torch.zeros(5)  # every frame takes its surest kept candidate
        got, got_sure = model._surest(pts, mask, rots, marker, best, sure, 0, keep)
        for f in range(5):
            alone = []
            for k in keep[:, f].nonzero()[:, 0].tolist():
                p = pts[f : f + 1] @ rots[k, f].T
                c = model._marker_centres(p, mask[f : f + 1], marker[k, f][None])
                plan = model._label(p, mask[f : f + 1], c, 0)
                alone.append((float(_surety(plan, mask[f : f + 1])), plan[0]))
            top, plan = max(alone, key=lambda x: x[0])
            assert got_sure[f].item() == pytest.approx(top, abs=1e-5)
            torch.testing.assert_close(got[f], plan, atol=1e-4, rtol=1e-4)
