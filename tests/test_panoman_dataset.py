"""PanoMan training set (H_B, H_F, H_H) and Anny's facial actions on the canonical topology."""

from __future__ import annotations

import pytest
import torch

from unibody import BodyLayer
from unibody.geometry.rotations import axis_angle_to_matrix, swing_twist
from unibody.panoman.dataset import (
    FINGER_JOINTS,
    body_samples,
    face_samples,
    hand_samples,
    identity_pool,
    iter_batches,
    sample_expressions,
)
from unibody.rig import JOINT_NAMES, Rig, joint_index
from unibody.synth.expressions import FACIAL_ACTIONS, expression_basis, expression_reference

V = 18056


@pytest.fixture(scope="module")
def layer() -> BodyLayer:
    """An independent float64 PCA layer (no twist) for reference rest meshes and joints."""
    return BodyLayer.from_pca(num_components=10, dtype=torch.float64)


@pytest.fixture(scope="module")
def basis() -> torch.Tensor:
    return expression_basis(torch.float64)[1]


@pytest.fixture(scope="module")
def edges() -> torch.Tensor:
    f = Rig.canonical().faces.long()
    e = torch.cat([f[:, [0, 1]], f[:, [1, 2]], f[:, [2, 0]]]).sort(dim=1).values
    return torch.unique(e, dim=0)


def _reference(layer: BodyLayer, s) -> tuple[torch.Tensor, torch.Tensor]:
    """(rest (N, V, 3), joints (N, J, 3)) of the samples' identities, recomputed independently."""
    with torch.no_grad():
        prep = layer.prepare_identity(s.shape.double())
    return prep.rest_vertices, prep.rest_joints


def test_identity_pool_prefix_truncation_and_disjoint_seeds():
    a = identity_pool(300, seed=0, dtype=torch.float64)
    assert a.shape == (300, 10) and a.dtype == torch.float64
    assert torch.equal(identity_pool(50, seed=0, dtype=torch.float64), a[:50])
    assert float(a.abs().max()) <= 2.0 and 0.75 < float(a.std()) < 1.0  # N(0, 1) truncated to [-2, 2]
    b = identity_pool(300, seed=1, dtype=torch.float64)
    assert float(torch.cdist(a, b).min()) > 0.1  # held-out identities are new


def test_body_samples(layer, edges):
    s = body_samples(6, seed=0, identities=3, batch_size=4)
    assert s.subset == "body" and len(s) == 6
    for name, shape in (("rest", (6, V, 3)), ("posed", (6, V, 3)), ("shape", (6, 10)), ("pose", (6, 77, 3)),
                        ("expression", (6, 52))):  # fmt: skip
        t = getattr(s, name)
        assert t.shape == shape and t.dtype == torch.float32, name
    assert torch.equal(s.identity, torch.tensor([0, 1, 2, 0, 1, 2]))
    assert torch.equal(s.shape, identity_pool(3, seed=0)[s.identity])
    rest, _ = _reference(layer, s)
    assert float((s.rest.double() - rest).abs().max()) < 1e-6  # each sample's rest is its bind-pose mesh
    assert torch.equal(s.pose[:, joint_index("Hips") - 1], torch.zeros(6, 3))  # upright, zero heading
    kept = torch.tensor([joint_index(n) - 1 for n in (*FINGER_JOINTS, "Jaw", "LeftEye", "HeadEnd")])
    assert torch.equal(s.pose[0, kept], s.pose[3, kept])  # the identity's rest rotations: no hand motion
    assert not torch.equal(s.pose[0], s.pose[3])
    assert not s.expression.any()
    assert float((s.posed - s.rest).norm(dim=-1).amax(1).min()) > 0.05
    length = (s.posed[:, edges[:, 0]] - s.posed[:, edges[:, 1]]).norm(dim=-1)
    rest_length = (s.rest[:, edges[:, 0]] - s.rest[:, edges[:, 1]]).norm(dim=-1)
    strain = (length / rest_length - 1).abs()
    assert float(strain.median()) < 0.05 and float(strain.quantile(0.99)) < 0.5
    # determinism, prefix stability across batch sizes, exact float64 -> float32 rounding
    again = body_samples(4, seed=0, identities=3, batch_size=64)
    assert torch.equal(again.posed, s.posed[:4]) and torch.equal(again.pose, s.pose[:4])
    wide = body_samples(2, seed=0, identities=3, dtype=torch.float64)
    assert torch.equal(wide.posed.float(), s.posed[:2])
    other = body_samples(2, seed=1, identities=3)
    assert not torch.allclose(other.pose, s.pose[:2]) and not torch.allclose(other.shape, s.shape[:2])


def test_body_twists():
    s = body_samples(3, seed=0, identities=1, twist_fraction=1.0, dtype=torch.float64)
    x = torch.tensor([1.0, 0.0, 0.0], dtype=torch.float64)
    for name, largest in (("Arm", 1.3), ("ForeArm", 1.5)):
        for side in ("Left", "Right"):
            _, angle = swing_twist(axis_angle_to_matrix(s.pose[:, joint_index(side + name) - 1]), x)
            assert bool((angle.abs() >= 0.5 * largest - 1e-9).all() and (angle.abs() <= largest + 1e-9).all())


def test_face_samples(layer, basis):
    s = face_samples(8, seed=0, identities=4)
    assert s.subset == "face" and s.posed.shape == (8, V, 3) and s.expression.shape == (8, 52)
    w = s.expression.double()
    assert bool(((w >= 0) & (w <= 1)).all()) and bool((w > 0).any(1).all())
    assert not w[:, FACIAL_ACTIONS.index("tongueOut")].any()
    rest, joints = _reference(layer, s)
    assert float((s.rest.double() - rest).abs().max()) < 1e-6
    offset = s.posed.double() - s.rest.double()
    below = rest[..., 1] < joints[:, joint_index("Neck1"), 1, None]
    assert float(offset.norm(dim=-1)[below].max()) < 1e-6  # confined to the head
    # posed - rest = s_i * sum_k w_k delta_k with one head-size scale per identity
    combo = torch.einsum("bk,kvc->bvc", w, basis)
    scale = (offset * combo).sum((1, 2)) / combo.pow(2).sum((1, 2))
    assert float((offset - scale[:, None, None] * combo).abs().max()) < 2e-7
    assert bool(((scale > 0.6) & (scale < 1.35)).all())
    height = rest[..., 1].amax(1) - rest[..., 1].amin(1)
    order = height.argsort()
    assert bool((scale[order].diff() >= -0.05).all())  # bigger bodies, bigger heads
    neutral = face_samples(2, seed=0, identities=2, max_active=0)
    assert not neutral.expression.any() and torch.equal(neutral.posed, neutral.rest)
    other = face_samples(8, seed=1, identities=4)
    assert not torch.equal(other.expression, s.expression)


def test_expression_sampler_structure():
    w = sample_expressions(4000, torch.Generator().manual_seed(0), max_active=3)
    units = w.gt(0).sum(1)
    assert int(units.min()) >= 1 and float(w.max()) <= 1.0
    jaw = w[:, FACIAL_ACTIONS.index("jawOpen")] > 0
    assert 0.25 < float(jaw.float().mean()) < 0.5
    close = w[:, FACIAL_ACTIONS.index("mouthClose")]
    assert bool((close <= w[:, FACIAL_ACTIONS.index("jawOpen")] + 1e-12).all())
    left, right = w[:, FACIAL_ACTIONS.index("mouthSmileLeft")] > 0, w[:, FACIAL_ACTIONS.index("mouthSmileRight")] > 0
    assert float((left & right).float().sum() / (left | right).float().sum()) > 0.6  # pairs mostly together
    side = w[:, [FACIAL_ACTIONS.index("jawLeft"), FACIAL_ACTIONS.index("jawRight")]] > 0
    assert not bool(side.all(1).any())  # opposite actions never together


def test_expression_basis(basis):
    labels, deltas32 = expression_basis(torch.float32)
    assert labels == FACIAL_ACTIONS and len(labels) == 52
    assert deltas32.shape == (52, V, 3) and deltas32.dtype == torch.float32
    assert torch.equal(deltas32, basis.float())
    from anny.models.facial_actions import FACIAL_ACTION_LABELS

    assert labels == tuple(FACIAL_ACTION_LABELS)
    reach = basis.norm(dim=-1).amax(1)
    assert float(reach[labels.index("tongueOut")]) == 0.0  # the canonical mesh has no tongue
    assert bool((reach[[i for i, n in enumerate(labels) if n != "tongueOut"]] > 1e-3).all())
    # jawOpen drops the chin: the lowest point of the front of the jaw on the midline
    ref = expression_reference(torch.float64)
    mid = (ref[:, 0].abs() < 1e-3) & (Rig.canonical().dense_skinning_weights()[:, joint_index("Jaw")] > 0.5)
    front = mid & (ref[:, 2] > ref[mid, 2].max() - 0.015)
    chin = torch.nonzero(front).squeeze(1)[ref[front, 1].argmin()]
    drop = float(basis[labels.index("jawOpen"), chin, 1])
    assert -0.035 < drop < -0.01, drop  # 2.4 cm at weight 1 on Anny's average head
    with pytest.raises(ValueError, match="dtype"):
        expression_basis(torch.float16)


def test_hand_samples(layer):
    s = hand_samples(4, seed=0, identities=2)
    assert s.subset == "hands" and s.posed.shape == (4, V, 3) and not s.expression.any()
    rest, _ = _reference(layer, s)
    assert float((s.rest.double() - rest).abs().max()) < 1e-6
    w = Rig.canonical().dense_skinning_weights()
    hand = [i for i, name in enumerate(JOINT_NAMES) if "Hand" in name]
    still = w[:, hand].sum(1) == 0
    moved = (s.posed - s.rest).norm(dim=-1)
    assert float(moved[:, still].max()) < 1e-6 and float(moved.amax(1).min()) > 0.02
    rows = torch.tensor([joint_index(n) - 1 for n in FINGER_JOINTS])
    other = torch.ones(77, dtype=torch.bool)
    other[rows] = False
    assert torch.equal(s.pose[0, other], s.pose[2, other])  # same identity, same rest pose elsewhere
    assert not torch.equal(s.pose[0, rows], s.pose[2, rows])
    assert float(s.pose[:, rows].norm(dim=-1).max()) < 1.8


def test_errors():
    with pytest.raises(ValueError, match="subset"):
        iter_batches("feet", 4, seed=0)
    with pytest.raises(ValueError, match="n: expected"):
        body_samples(0, seed=0)
    with pytest.raises(ValueError, match="seed"):
        body_samples(2, seed=-1)
    with pytest.raises(ValueError, match="twist_fraction"):
        body_samples(2, seed=0, twist_fraction=1.5)
    with pytest.raises(ValueError, match="identities"):
        hand_samples(2, seed=0, identities=0)
    with pytest.raises(ValueError, match="dtype"):
        face_samples(2, seed=0, dtype=torch.float16)
    with pytest.raises(ValueError, match="p_jaw"):
        sample_expressions(2, torch.Generator(), p_jaw=2.0)
