"""Lab variation of the synthetic mocap (issue 38): each knob does what it says, nothing else
moves, and the training script never takes an evaluation subject's motion."""

from __future__ import annotations

import importlib.util
import json
from dataclasses import replace
from pathlib import Path

import pytest
import torch

from unibody.mocap.layout import MarkerLayout
from unibody.mocap.pipeline import available_labelers, load_labeler
from unibody.mocap.synthetic import LAB_VARIATION, SyntheticConfig, SyntheticMocap, mirror_pose

ROOT = Path(__file__).resolve().parents[1]
EVALDATA = ROOT.parent / "shared" / "evaldata"


def _exact(**kw) -> SyntheticConfig:
    """No jitter, noise, spread, wrist bars or skin distance: each marker on its drawn vertex."""
    return SyntheticConfig(
        identities=8, jitter_radius=0.0, loose=(), segments=(), distance=(0.0, 0.0), noise=(0.0, 0.0),
        spread=0.0, stick_prob=0.0, **kw,
    )  # fmt: skip


@pytest.fixture(scope="module")
def layout():
    return MarkerLayout.load("cmu41")


@pytest.fixture(scope="module")
def mean_rest(layout):
    syn = SyntheticMocap(layout, _exact())
    p = syn.layer.prepare_identity(torch.zeros(1, syn.config.shape_components))
    return p.rest_vertices[0]


def _drawn(syn: SyntheticMocap, label: str, mirrored: bool = False) -> torch.Tensor:
    """The vertex ids a marker may be drawn on (its mirror images with ``mirrored``)."""
    i = syn.layout.labels.index(label)
    c = syn.candidates[i, : syn.num_candidates[i]]
    return syn.used[syn.mirror_used[c] if mirrored else c]


def test_midline_and_lateral_rules_span_their_ranges(layout, mean_rest):
    """T10 slides up the back midline by its stated range; the back-waist markers sit 6-20 cm apart."""
    syn = SyntheticMocap(layout, _exact(midline=LAB_VARIATION["midline"], lateral=LAB_VARIATION["lateral"]))
    v, base = mean_rest, layout.vertices
    t10 = v[_drawn(syn, "T10")]
    y0 = v[base[layout.labels.index("T10")], 1]
    assert t10[:, 0].abs().max() <= 0.02 + 1e-6  # on the midline
    assert (t10[:, 2] < 0).all()  # on the back
    assert float(t10[:, 1].min() - y0) < -0.03 and float(t10[:, 1].max() - y0) > 0.12  # the range is used
    c7 = v[base[layout.labels.index("C7")], 1]
    assert float(t10[:, 1].max()) < float(c7) - 0.03  # never up to C7
    lb, rb = v[_drawn(syn, "LBWT")], v[_drawn(syn, "RBWT")]
    assert (lb[:, 0] >= 0.03 - 1e-6).all() and (lb[:, 0] <= 0.10 + 1e-6).all()
    assert (rb[:, 0] <= -0.03 + 1e-6).all() and (rb[:, 0] >= -0.10 - 1e-6).all()
    assert float(lb[:, 0].max() - rb[:, 0].min()) > 0.18  # far apart, as in a lab unlike CMU
    # off by default: the layout vertex only
    plain = SyntheticMocap(layout, _exact())
    assert _drawn(plain, "T10").tolist() == [int(base[layout.labels.index("T10")])]


def test_asymmetric_marker_moves_to_the_other_side_in_the_stated_fraction(layout):
    cfg = _exact(mirror_labels=("RBAC",), mirror_prob=0.2)
    syn = SyntheticMocap(layout, cfg)
    i = layout.labels.index("RBAC")
    m = syn.markers(4000, torch.Generator().manual_seed(0))
    at = lambda x: m[:, layout.labels.index(x)]  # noqa: E731
    left = (((m[:, i] - at("C7")) * (at("LSHO") - at("RSHO"))).sum(-1) > 0).float().mean()  # body's left
    assert 0.17 < float(left) < 0.23
    assert (_drawn(syn, "RBAC", mirrored=True) != _drawn(syn, "RBAC")).all()
    others = [j for j in range(len(layout)) if j != i]
    ref = SyntheticMocap(layout, replace(cfg, mirror_prob=0.0)).markers(4000, torch.Generator().manual_seed(0))
    assert not torch.equal(ref[:, i], m[:, i])
    assert torch.isfinite(m[:, others]).all()


def test_suit_scale_and_soft_tissue(layout):
    """A suit moves every marker off the skin by its draw; a scale keeps the Hips and scales the rest;
    soft tissue moves only the soft-tissue markers."""
    g = lambda: torch.Generator().manual_seed(3)  # noqa: E731
    base = SyntheticMocap(layout, _exact()).markers(64, g())
    suit = SyntheticMocap(layout, _exact(suit=(0.01, 0.01))).markers(64, g())
    assert torch.allclose((suit - base).norm(dim=-1), torch.full(base.shape[:2], 0.01), atol=1e-5)
    scaled = SyntheticMocap(layout, _exact(scale=(1.02, 1.02))).markers(64, g())
    ratio = scaled.norm(dim=-1) / base.norm(dim=-1)  # spread 0: the Hips are at the origin
    assert torch.allclose(ratio, torch.full_like(ratio, 1.02), atol=1e-4)
    soft = SyntheticMocap(layout, _exact(soft_tissue=0.008)).markers(64, g())
    moved = (soft - base).norm(dim=-1).amax(0) > 1e-6
    names = [x for x, k in zip(layout.labels, moved.tolist(), strict=True) if k]
    assert "LTHI" in names and "T10" in names and "LKNE" not in names and "C7" not in names


def test_shape_tails_widen_only_the_drawn_fraction(layout):
    a = SyntheticMocap(layout, replace(_exact(), identities=400)).coefficients
    b = SyntheticMocap(layout, replace(_exact(), identities=400, shape_tail_prob=0.25, shape_tail_scale=1.6))
    b = b.coefficients
    assert torch.equal(a[:, 0], b[:, 0])  # statures unchanged
    wide = (b[:, 1:] != a[:, 1:]).any(1)
    assert 0.15 < float(wide.float().mean()) < 0.35
    assert torch.allclose(b[wide, 1:], 1.6 * a[wide, 1:])


def test_mirror_pose_mirrors_the_skeleton(layout):
    """Posing the mirrored pose gives the mirror image of the skeleton (x -> -x, left <-> right)."""
    syn = SyntheticMocap(layout, _exact())
    layer = syn.layer
    p = layer.prepare_identity(torch.zeros(1, syn.config.shape_components))
    pose = 0.5 * torch.randn(6, 77, 3, generator=torch.Generator().manual_seed(1))
    a = layer.pose(p, pose).joints
    b = layer.pose(p, mirror_pose(pose, layer.joint_names)).joints
    names = list(layer.joint_names)
    swap = {n: n.replace("Left", "@").replace("Right", "Left").replace("@", "Right") for n in names}
    back = b[:, [names.index(swap[n]) for n in names]] * torch.tensor([-1.0, 1.0, 1.0])
    assert float((a - back).abs().max()) < 2e-3  # the PCA mean skeleton is symmetric to ~1 mm
    assert float((a - b).abs().max()) > 0.1
    assert torch.equal(mirror_pose(mirror_pose(pose, layer.joint_names), layer.joint_names), pose)


def _train_script():
    spec = importlib.util.spec_from_file_location("train_labeler", ROOT / "scripts" / "train_labeler.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def test_training_refuses_evaluation_subjects_and_holds_out_by_subject(tmp_path):
    mod = _train_script()
    for name in ("02_01.motion.npz", "05_03.motion.npz", "85_02.motion.npz"):
        (tmp_path / name).write_bytes(b"")
    with pytest.raises(SystemExit, match="85_02.motion.npz is a take of an evaluation subject"):
        mod.motion_files([str(tmp_path)], [])
    (tmp_path / "85_02.motion.npz").unlink()
    kept, held = mod.motion_files([str(tmp_path)], [5])
    assert [x.name for x in kept] == ["02_01.motion.npz"] and [x.name for x in held] == ["05_03.motion.npz"]
    with pytest.raises(SystemExit, match="no such file"):
        mod.motion_files([str(tmp_path / "missing")], [])


def _evaluation_names() -> tuple[set[str], set[int]]:
    manifest = json.loads((EVALDATA / "manifest.json").read_text()) if (EVALDATA / "manifest.json").exists() else {}
    text = json.dumps(manifest)
    files = {p.name for p in EVALDATA.rglob("*") if p.is_file()} if EVALDATA.exists() else set()
    subjects = {85, 131, 135}
    subjects |= {int(x.split("_")[1]) for x in files if x.startswith("cmu_") and x.split("_")[1].isdigit()}
    assert subjects and (files or not text)
    return {Path(x).stem.split(".")[0] for x in files}, subjects


@pytest.mark.parametrize("name", available_labelers())
def test_shipped_weights_name_no_evaluation_file_or_subject(name):
    """The training manifest stored in the weights names no evaluation file or CMU subject."""
    if not EVALDATA.exists():
        pytest.skip(f"no evaluation data at {EVALDATA}")
    stems, subjects = _evaluation_names()
    meta = load_labeler(name).meta
    recipe = json.dumps(meta)
    for motion in meta.get("motions") or []:
        assert int(motion.split("_")[0]) not in subjects, motion
        assert motion.split(".")[0] not in stems, motion
    assert not [s for s in stems if len(s) > 6 and s in recipe], "an evaluation file is named in the recipe"
    for subject in meta.get("motion_subjects") or []:
        assert subject not in subjects
