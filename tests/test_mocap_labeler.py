"""Labeler network, loss, decoding, label_frames, save/load, and the training script (toy data)."""

from __future__ import annotations

import argparse
import dataclasses
import importlib.util
import math
import time
from pathlib import Path

import numpy as np
import pytest
import torch

from unibody.mocap import labeler
from unibody.mocap.corrupt import MocapBatch
from unibody.mocap.labeler import Labeler, LabelerConfig, label_frames, labeling_loss, predict
from unibody.mocap.layout import MarkerLayout
from unibody.mocap.metrics import labeling_scores
from unibody.mocap.synthetic import SyntheticConfig, SyntheticMocap
from unibody.motion import Motion, save_motion
from unibody.synth.poses import sample_poses

SCRIPT = Path(__file__).resolve().parents[1] / "scripts" / "train_labeler.py"


def _toy_batch(frames=8, num_labels=12, ghosts=(1, 2), occluded=(0, 1), seed=0, dtype=torch.float32):
    """Random "bodies": one template of labelled points, per-frame jitter, a heading about Y,
    ghosts near the frame, occlusions, and a random order of the real points (padding last)."""
    g = torch.Generator().manual_seed(seed)
    template = 0.4 * torch.randn(num_labels, 3, generator=g, dtype=dtype)
    n = num_labels + ghosts[1]
    points = torch.zeros(frames, n, 3, dtype=dtype)
    labels = torch.full((frames, n), num_labels, dtype=torch.long)
    mask = torch.zeros(frames, n, dtype=torch.bool)
    available = torch.zeros(frames, num_labels, dtype=torch.bool)
    for f in range(frames):
        a = float(torch.rand((), generator=g)) * 2 * math.pi
        rot = torch.tensor([[math.cos(a), 0, math.sin(a)], [0, 1, 0], [-math.sin(a), 0, math.cos(a)]], dtype=dtype)
        body = (template + 0.03 * torch.randn(num_labels, 3, generator=g, dtype=dtype)) @ rot.T
        body = body + torch.tensor([0.0, 1.0, 0.0], dtype=dtype)
        n_occ = int(torch.randint(occluded[0], occluded[1] + 1, (), generator=g))
        keep = torch.randperm(num_labels, generator=g)[: num_labels - n_occ].sort().values
        n_gh = int(torch.randint(ghosts[0], ghosts[1] + 1, (), generator=g))
        gh = body[keep].median(0).values + 0.3 * torch.randn(n_gh, 3, generator=g, dtype=dtype)
        pts = torch.cat([body[keep], gh])
        lab = torch.cat([keep, torch.full((n_gh,), num_labels)])
        perm = torch.randperm(len(pts), generator=g)
        points[f, : len(pts)] = pts[perm]
        labels[f, : len(pts)] = lab[perm]
        mask[f, : len(pts)] = True
        available[f, keep] = True
    return MocapBatch(points, mask, labels, available)


def _small(num_labels=12, **kw):
    torch.manual_seed(0)
    return Labeler(num_labels, width=32, layers=2, heads=2, **kw)


def test_overfit_tiny_set():
    torch.manual_seed(0)
    batch = _toy_batch()
    model = _small()
    opt = torch.optim.Adam(model.parameters(), lr=3e-3)
    for _ in range(400):
        loss = labeling_loss(model(batch.points, batch.mask), batch)
        opt.zero_grad()
        loss.backward()
        opt.step()
    model.eval()
    with torch.no_grad():
        labels, conf = predict(model(batch.points, batch.mask), batch.mask)
    assert torch.equal(labels[batch.mask], batch.labels[batch.mask]), float(loss)
    assert float(conf[batch.mask].min()) > 0.5
    scores = labeling_scores(labels[batch.mask], batch.labels[batch.mask], null=12)
    assert scores["accuracy"] == 1.0 and scores["f1"] == 1.0


def test_equivariance_translation_and_padding():
    batch = _toy_batch(frames=3, seed=1)
    model = _small().eval()
    with torch.no_grad():
        ref = model(batch.points, batch.mask)
        # permuting the points permutes the plan rows
        perm = torch.randperm(batch.points.shape[1], generator=torch.Generator().manual_seed(2))
        out = model(batch.points[:, perm], batch.mask[:, perm])
        torch.testing.assert_close(out[:, :-1], ref[:, :-1][:, perm], atol=1e-4, rtol=1e-4)
        # a shift of the whole frame is removed by the median centring
        out = model(batch.points + torch.tensor([3.0, -1.0, 2.0]), batch.mask)
        m = torch.cat([batch.mask, torch.ones(3, 1, dtype=torch.bool)], 1)
        torch.testing.assert_close(out[m], ref[m], atol=1e-4, rtol=1e-4)
        # extra padding slots (holding garbage) change nothing for the real rows
        pad_pts = torch.cat([batch.points, 5 * torch.ones(3, 4, 3)], 1)
        pad_mask = torch.cat([batch.mask, torch.zeros(3, 4, dtype=torch.bool)], 1)
        out = model(pad_pts, pad_mask)
        n = batch.points.shape[1]
        torch.testing.assert_close(out[:, :n][batch.mask], ref[:, :n][batch.mask], atol=1e-4, rtol=1e-4)
        torch.testing.assert_close(out[:, -1], ref[:, -1], atol=1e-4, rtol=1e-4)


def test_frames_are_independent_and_long_batches_run_in_chunks(monkeypatch):
    batch = _toy_batch(frames=7, seed=4)
    model = _small().eval()
    with torch.no_grad():
        alone = torch.cat([model(batch.points[i : i + 1], batch.mask[i : i + 1]) for i in range(7)])
        monkeypatch.setattr(labeler, "_CHUNK", 3)  # passes of 3, 3 and 1 frames
        torch.testing.assert_close(model(batch.points, batch.mask), alone, atol=1e-5, rtol=1e-5)
        torch.testing.assert_close(
            model(batch.points, batch.mask, refine=2),
            torch.cat([model(batch.points[i : i + 1], batch.mask[i : i + 1], refine=2) for i in range(7)]),
            atol=1e-5,
            rtol=1e-5,
        )


def test_loss_matches_hand_computation():
    # one frame, 3 slots (marker 1, a ghost, padding), L = 2 labels: label 0 unmatched
    logp = torch.log(torch.rand(1, 4, 3, generator=torch.Generator().manual_seed(0)))
    batch = MocapBatch(
        torch.zeros(1, 3, 3),
        torch.tensor([[True, True, False]]),
        torch.tensor([[1, 2, 2]]),
        torch.tensor([[False, True]]),
    )
    # rows: point 0 -> label 1 (w 1), ghost -> null column (w 1/1); dustbin row: label 0 (w 1/1)
    expected = -(logp[0, 0, 1] + logp[0, 1, 2] + logp[0, 3, 0]) / 3
    torch.testing.assert_close(labeling_loss(logp, batch), expected)
    # two ghosts: their rows and the dustbin row weigh 1/2
    batch2 = MocapBatch(batch.points, torch.tensor([[True, True, True]]), torch.tensor([[1, 2, 2]]), batch.available)
    expected2 = -(logp[0, 0, 1] + 0.5 * (logp[0, 1, 2] + logp[0, 2, 2] + logp[0, 3, 0])) / 4
    torch.testing.assert_close(labeling_loss(logp, batch2), expected2)


def test_loss_finite_all_null_and_empty_frames():
    model = _small(num_labels=4)
    pts = torch.randn(3, 5, 3)
    mask = torch.tensor([[True] * 5, [False] * 5, [True, True, False, False, False]])
    labels = torch.full((3, 5), 4)  # every point is a ghost; frame 1 has no points at all
    batch = MocapBatch(pts, mask, labels, torch.zeros(3, 4, dtype=torch.bool))
    loss = labeling_loss(model(pts, mask), batch)
    assert torch.isfinite(loss)
    loss.backward()
    assert all(torch.isfinite(p.grad).all() for p in model.parameters() if p.grad is not None)
    labels, conf = predict(model(pts, mask).detach(), mask)
    assert (labels[~mask] == 4).all() and (conf[~mask] == 0).all()


def test_predict_never_duplicates():
    g = torch.Generator().manual_seed(0)
    for _ in range(20):
        logp = torch.randn(16, 9, 5, generator=g) * 3  # random "plans": many argmax collisions
        mask = torch.rand(16, 8, generator=g) > 0.2
        labels, conf = predict(logp, mask)
        for b in range(16):
            real = labels[b][labels[b] != 4]
            assert len(real) == len(real.unique())
        assert (labels[~mask] == 4).all()


def test_predict_keeps_most_confident():
    p = torch.tensor([[0.6, 0.3, 0.1], [0.9, 0.05, 0.05], [0.6, 0.1, 0.3], [0.2, 0.7, 0.1]])
    logp = torch.cat([p, torch.ones(1, 3)]).log()[None]  # last row: the (unused) dustbin row
    labels, conf = predict(logp, torch.ones(1, 4, dtype=torch.bool))
    # points 0, 1, 2 all want label 0: point 1 (0.9) keeps it, 0 and 2 become null (label 2)
    assert labels.tolist() == [[2, 0, 2, 1]]
    torch.testing.assert_close(conf, torch.tensor([[0.1, 0.9, 0.3, 0.7]]))


def test_label_frames_nan_and_batches():
    model = _small()  # in training mode: label_frames runs it in eval mode and restores the mode
    batch = _toy_batch(frames=5, seed=3)
    pts = torch.where(batch.mask[..., None], batch.points, torch.nan)
    pts[2, 0] = torch.nan  # hide one more point
    visible = torch.isfinite(pts).all(2)
    out = label_frames(model, pts, batch=2)
    assert model.training
    assert out.shape == visible.shape and (out[~visible] == 12).all()
    with torch.no_grad():
        ref, _ = predict(model.eval()(torch.nan_to_num(pts), visible), visible)
    assert torch.equal(out, ref)


def test_float64_and_save_load(tmp_path):
    model = _small(label_names=[f"M{i}" for i in range(12)]).double().eval()
    batch = _toy_batch(frames=2, seed=4, dtype=torch.float64)
    path = tmp_path / "labeler.pt"
    model.save(path, {"seed": 7, "val": {"accuracy": 0.5}, "command": "x y"})
    loaded = Labeler.load(path).double().eval()
    assert loaded.label_names == model.label_names and loaded.meta["val"]["accuracy"] == 0.5
    assert loaded.config == model.config
    with torch.no_grad():
        torch.testing.assert_close(loaded(batch.points, batch.mask), model(batch.points, batch.mask))
    with pytest.raises(TypeError, match=r"meta\['when'\]: expected str"):
        model.save(path, {"when": torch.__version__})  # a str subclass that weights_only cannot load
    torch.save({"format": "something else"}, tmp_path / "bad.pt")
    with pytest.raises(
        ValueError, match=r"bad.pt: not a labeler .*\(format 'something else', expected 'unibody.labeler/1'\)"
    ):
        Labeler.load(tmp_path / "bad.pt")


def test_errors():
    model = _small()
    pts, mask = torch.zeros(2, 5, 3), torch.ones(2, 5, dtype=torch.bool)
    with pytest.raises(ValueError, match="mask: expected shape"):
        model(pts, mask[:, :4])
    with pytest.raises(TypeError, match="mask: expected a bool"):
        model(pts, mask.float())
    with pytest.raises(TypeError, match="points: is float64"):
        model(pts.double(), mask)
    with pytest.raises(ValueError, match="points: expected finite"):
        model(torch.full((2, 5, 3), torch.nan), mask)
    with pytest.raises(ValueError, match="width/heads"):
        Labeler(12, width=30, heads=4)
    with pytest.raises(ValueError, match="label_names: expected 12"):
        Labeler(12, label_names=["a"])
    bad = MocapBatch(pts, mask, torch.full((2, 5), 13), torch.zeros(2, 12, dtype=torch.bool))
    with pytest.raises(ValueError, match="batch.labels: real points need labels"):
        labeling_loss(model(pts, mask), bad)


def _script():
    spec = importlib.util.spec_from_file_location("train_labeler", SCRIPT)
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def _args(out, seed=3, *extra):
    return ["--layout", "cmu41", "--steps", "12", "--batch", "16", "--seed", str(seed), "--threads", "1",
            "--width", "16", "--layers", "1", "--heads", "2", "--val-frames", "32", "--identities", "8",
            "--log-every", "1000", "--out", str(out), *extra]  # fmt: skip


@pytest.mark.slow
def test_training_script_resumes_bit_identically(tmp_path):
    mod = _script()
    mod.main(_args(tmp_path / "a"))
    mod.main(_args(tmp_path / "b", 3, "--stop-at", "7"))
    assert (tmp_path / "b" / "checkpoint.pt").exists() and not (tmp_path / "b" / "labeler.pt").exists()
    mod.main(_args(tmp_path / "b"))
    a, b = Labeler.load(tmp_path / "a" / "labeler.pt"), Labeler.load(tmp_path / "b" / "labeler.pt")
    for (k, x), y in zip(a.state_dict().items(), b.state_dict().values(), strict=True):
        assert torch.equal(x, y), k
    assert a.meta["steps"] == 12 and a.meta["seed"] == 3 and "--layout cmu41" in a.meta["command"]
    assert a.meta["synthetic_val_accuracy"] == b.meta["synthetic_val_accuracy"]
    # a different seed trains a different model (so the comparison above can fail)
    mod.main(_args(tmp_path / "c", 4))
    c = Labeler.load(tmp_path / "c" / "labeler.pt")
    assert not torch.equal(c.bin_score, a.bin_score)


def test_training_script_device():
    """``--device`` is checked before any work; the weights record the device they trained on."""
    mod = _script()
    with pytest.raises(SystemExit, match="--device: expected cpu, cuda or cuda:N, got 'gpu'"):
        mod.main(_args("unused", 3, "--device", "gpu"))
    if not torch.cuda.is_available():
        with pytest.raises(SystemExit, match="--device: 'cuda' is not on this machine"):
            mod.main(_args("unused", 3, "--device", "cuda"))


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA")
def test_training_script_on_cuda_resumes_and_loads_on_the_cpu(tmp_path):
    """A run on the GPU stops, resumes from its checkpoint and writes weights that load on the CPU
    and label the validation frames as well as a CPU run of the same command (same batches)."""
    mod = _script()
    mod.main(_args(tmp_path / "cpu"))
    mod.main(_args(tmp_path / "gpu", 3, "--device", "cuda", "--stop-at", "7"))
    mod.main(_args(tmp_path / "gpu", 3, "--device", "cuda"))
    a, b = Labeler.load(tmp_path / "cpu" / "labeler.pt"), Labeler.load(tmp_path / "gpu" / "labeler.pt")
    assert b.bin_score.device.type == "cpu" and b.meta["device"] == "cuda" and b.meta["steps"] == 12
    assert abs(a.meta["synthetic_val_accuracy"] - b.meta["synthetic_val_accuracy"]) < 0.05


@pytest.mark.slow
def test_training_script_grows_a_labeler_deeper(tmp_path):
    """``--init`` a labeler of fewer blocks than ``--layers``: the extra blocks start as the identity,
    so before training it labels exactly as the labeler it grew from; fewer blocks are refused."""
    mod = _script()
    mod.main(_args(tmp_path / "a"))
    grown = [*_args(tmp_path / "b"), "--layers", "3", "--steps", "0", "--init", str(tmp_path / "a" / "labeler.pt")]
    mod.main(grown)
    a, b = Labeler.load(tmp_path / "a" / "labeler.pt"), Labeler.load(tmp_path / "b" / "labeler.pt")
    assert len(a.blocks) == 1 and len(b.blocks) == 3
    batch = SyntheticMocap(MarkerLayout.load("cmu41"), SyntheticConfig(identities=4)).sample(
        8, torch.Generator().manual_seed(0)
    )
    with torch.no_grad():
        assert torch.equal(a(batch.points, batch.mask), b(batch.points, batch.mask))
    assert not torch.equal(b.blocks[1].qkv.weight, b.blocks[2].qkv.weight)  # fresh, trainable inner layers
    with pytest.raises(SystemExit, match="--init: .* has 3 blocks, more than --layers 1"):
        mod.main([*_args(tmp_path / "c"), "--init", str(tmp_path / "b" / "labeler.pt")])


@pytest.mark.slow
def test_training_script_motions(tmp_path):
    """``--motions`` trains on the frames of motion files; the weights name them. A file that is not
    a motion, or a probability outside [0, 1], is refused before any work."""
    poses = sample_poses(30, torch.Generator().manual_seed(8), bend=1.0)
    save_motion(tmp_path / "m.npz", Motion(poses.numpy(), np.zeros((30, 3), np.float32), 30.0))
    mod = _script()
    mod.main(_args(tmp_path / "a", 3, "--motions", str(tmp_path / "m.npz"), "--motion-prob", "0.7"))
    meta = Labeler.load(tmp_path / "a" / "labeler.pt").meta
    assert meta["motions"] == ["m.npz"] and meta["motion_frames"] == 30 and meta["motion_prob"] == 0.7
    np.savez(tmp_path / "bad.npz", pose=np.zeros((3, 76, 3)))
    with pytest.raises(SystemExit, match="--motions: "):
        mod.main(_args(tmp_path / "b", 3, "--motions", str(tmp_path / "bad.npz")))
    with pytest.raises(SystemExit, match=r"--motion-prob: expected a probability in \[0, 1\], got 1.5"):
        mod.main(_args(tmp_path / "b", 3, "--motions", str(tmp_path / "m.npz"), "--motion-prob", "1.5"))


def test_training_script_slide_sets_one_segment_range():
    """``--slide FIN 0.1 1.0`` changes that rule's range along its bone and no other rule; an unknown
    suffix or a range with LO > HI is refused."""
    mod = _script()
    base = dict(subsets=[], neck_roll=None, extras=0, extra_distance=(0.03, float("inf")), stick_prob=0.9,
                extra_prob=0.3, extra_clusters=0.0, cluster_size=3, cluster_radius=0.08, stature_prob=0.75,
                head_bands=False, fitted=None, fold=None, motion_prob=0.5, lab_variation=False)  # fmt: skip
    layout = MarkerLayout.load("cmu41")
    syn = mod.synthetic(argparse.Namespace(**base, slide=[["FIN", "0.1", "1.0"]]), layout, 0, 4)
    assert "fold" not in syn.config.pose  # --fold FRACTION: sample_poses(fold=FRACTION)
    assert mod.synthetic(argparse.Namespace(**{**base, "fold": 0.2}, slide=[]), layout, 0, 4).config.pose["fold"] == 0.2
    default = SyntheticConfig.segments
    assert [r for r in syn.config.segments if r[0] == "FIN"] == [("FIN", "Hand", "HandMiddle2", 0.1, 1.0)]
    assert [r for r in syn.config.segments if r[0] != "FIN"] == [r for r in default if r[0] != "FIN"]
    assert [r for r in default if r[0] == "FIN"] != [("FIN", "Hand", "HandMiddle2", 0.1, 1.0)]
    for bad in (["FINGER", "0.1", "1.0"], ["FIN", "0.9", "0.1"]):
        with pytest.raises(SystemExit, match="--slide"):
            mod.synthetic(argparse.Namespace(**base, slide=[bad]), layout, 0, 4)


def test_midrange_centre_ignores_a_crowd_of_extra_points(tmp_path):
    """The median follows a crowd of extra points (pyCGM's foot markers); the middle of the 5-95 % range
    stays with the body; the choice is saved with the weights."""
    torch.manual_seed(0)
    body = torch.rand(1, 40, 3) * torch.tensor([0.5, 1.7, 0.3])  # 40 points spread over a body's box
    crowd = torch.rand(1, 30, 3) * torch.tensor([0.5, 0.1, 0.3])  # 30 more near the floor
    pts, mask = torch.cat([body, crowd], dim=1), torch.ones(1, 70, dtype=torch.bool)
    median, midrange = Labeler(5), Labeler(5, centre="midrange")
    assert abs(float(median.centres(body, mask[:, :40])[0, 1] - median.centres(pts, mask)[0, 1])) > 0.3
    assert abs(float(midrange.centres(body, mask[:, :40])[0, 1] - midrange.centres(pts, mask)[0, 1])) < 0.1
    padded = torch.cat([pts, torch.full((1, 5, 3), 99.0)], dim=1)  # padding never counts
    assert torch.equal(midrange.centres(padded, torch.cat([mask, torch.zeros(1, 5, dtype=torch.bool)], 1)),
                       midrange.centres(pts, mask))  # fmt: skip
    midrange.save(tmp_path / "m.pt")
    assert Labeler.load(tmp_path / "m.pt").config.centre == "midrange"
    with pytest.raises(ValueError, match="centre"):
        Labeler(5, centre="mean")
    Labeler(5, refine=2).save(tmp_path / "r.pt")
    assert Labeler.load(tmp_path / "r.pt").config.refine == 2
    with pytest.raises(ValueError, match="refine"):
        Labeler(5, refine=-1)
    with pytest.raises(ValueError, match="refine"):
        midrange(pts, mask, refine=-1)


def test_labeler_config_is_frozen_checked_and_saved_as_a_plain_dict(tmp_path):
    """LabelerConfig: frozen; changing a setting gives a checked copy; the weights file keeps a plain dict."""
    model = Labeler(5, width=8, layers=1, heads=2, refine=1)
    assert model.config == LabelerConfig(5, width=8, layers=1, heads=2, refine=1)
    with pytest.raises(dataclasses.FrozenInstanceError):
        model.config.refine = 2
    other = model.with_config(refine=3, centre="midrange")
    assert (other.config.refine, other.config.centre, model.config.refine) == (3, "midrange", 1)
    assert torch.equal(other.bin_score, model.bin_score) and other.bin_score is not model.bin_score
    model.config = dataclasses.replace(model.config, sinkhorn_iters=20)
    assert model.config.sinkhorn_iters == 20
    with pytest.raises(ValueError, match="width are fixed by the weights"):
        model.config = dataclasses.replace(model.config, width=16)
    with pytest.raises(ValueError, match="retry: expected 0, or a confidence in"):
        model.with_config(retry=0.5)  # no orienter
    with pytest.raises(TypeError, match="config: expected a LabelerConfig"):
        model.config = {"refine": 1}
    with pytest.raises(ValueError, match="centre"):
        LabelerConfig(5, centre="mean")
    model.save(tmp_path / "c.pt")
    payload = torch.load(tmp_path / "c.pt", weights_only=True)
    assert payload["config"] == dict(num_labels=5, width=8, layers=1, heads=2, sinkhorn_iters=20, centre="median",
                                     refine=1, retry=0.0)  # fmt: skip
    assert Labeler.load(tmp_path / "c.pt").config == model.config
    old = dict(payload, config={k: v for k, v in payload["config"].items() if k != "retry"})  # a file before retry
    torch.save(old, tmp_path / "old.pt")
    assert Labeler.load(tmp_path / "old.pt").config.retry == 0.0


@pytest.mark.parametrize("name", ["cmu41", "cmu41_large", "pig39"])
def test_shipped_weights_load_and_save_the_same_config_dict(tmp_path, name):
    from importlib import resources

    with resources.as_file(resources.files("unibody.mocap") / "data" / f"labeler_{name}.pt") as f:
        stored = torch.load(f, weights_only=True)["config"]
        model = Labeler.load(f)
    assert model.config.to_dict() == {k: v for k, v in stored.items() if k != "orienter"}
    assert model.orienter.config.to_dict() == stored["orienter"]
    model.save(tmp_path / "again.pt")
    assert torch.load(tmp_path / "again.pt", weights_only=True)["config"] == stored


def test_training_script_workers_draw_each_batch_from_its_step(tmp_path):
    """With ``--workers`` each batch is seeded by its step: one worker or two, straight or resumed,
    train the same weights; another seed trains other weights (so the comparison can fail)."""
    mod = _script()
    mod.main(_args(tmp_path / "a", 3, "--workers", "1"))
    mod.main(_args(tmp_path / "b", 3, "--workers", "2", "--stop-at", "7"))
    mod.main(_args(tmp_path / "b", 3, "--workers", "2"))
    mod.main(_args(tmp_path / "c", 4, "--workers", "2"))
    a, b, c = (Labeler.load(tmp_path / x / "labeler.pt") for x in "abc")
    for (k, x), y in zip(a.state_dict().items(), b.state_dict().values(), strict=True):
        assert torch.equal(x, y), k
    assert a.meta["workers"] == 1 and b.meta["workers"] == 2 and a.meta["batch"] == 16
    assert not torch.equal(c.bin_score, a.bin_score)


def test_training_script_motion_stride_and_time_limit(tmp_path):
    """``--motion-stride K`` keeps every K-th frame of each file; ``--time-limit`` sets the steps from
    the warm-up's speed and never runs past the limit; bad values are refused before any work."""
    poses = sample_poses(30, torch.Generator().manual_seed(8), bend=1.0)
    save_motion(tmp_path / "m.npz", Motion(poses.numpy(), np.zeros((30, 3), np.float32), 30.0))
    mod = _script()
    given = ["--motions", str(tmp_path / "m.npz"), "--motion-stride", "3", "--warmup", "20", "--time-limit", "1000"]
    mod.main(_args(tmp_path / "a", 3, *given))
    meta = Labeler.load(tmp_path / "a" / "labeler.pt").meta
    assert meta["motion_frames"] == 10 and meta["motion_stride"] == 3
    assert meta["steps"] == 12  # the limit leaves room for more: --steps caps the run
    start = time.time()
    mod.main(_args(tmp_path / "b", 3, "--steps", "100000", "--warmup", "20", "--time-limit", "32"))
    assert 1 <= Labeler.load(tmp_path / "b" / "labeler.pt").meta["steps"] < 100000
    assert time.time() - start < 32
    for bad, match in (
        (["--motion-stride", "0"], "--motion-stride: expected an integer >= 1, got 0"),
        (["--workers", "-1"], "--workers: expected an integer >= 0, got -1"),
        (["--time-limit", "10", "--warmup", "5"], "--time-limit: expected seconds > 0 and --warmup >= 20"),
    ):
        with pytest.raises(SystemExit, match=match):
            mod.main(_args(tmp_path / "c", 3, *bad))
