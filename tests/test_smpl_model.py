"""The SMPL-family posed forward against the ``smplx`` package (test-only oracle) on generated model files."""

from __future__ import annotations

import pytest
import torch

from smpl_format import make_model, write_npz, write_pkl
from unibody.identity.smpl_model import SMPLModel

smplx = pytest.importorskip("smplx")


@pytest.fixture(scope="module")
def files(tmp_path_factory):
    root = tmp_path_factory.mktemp("smpl_model")
    return {
        "smplh": write_npz(root / "smplh_male.npz", make_model("smplh", seed=3, oracle=True)),
        "smplx": write_npz(root / "SMPLX_FEMALE.npz", make_model("smplx", seed=4, oracle=True)),
    }


def _random(family: str, b: int, seed: int) -> dict[str, torch.Tensor]:
    g = torch.Generator().manual_seed(seed)
    j = {"smplh": 52, "smplx": 55}[family]
    return {
        "pose": 0.6 * torch.randn(b, j, 3, generator=g, dtype=torch.float64),
        "betas": 1.5 * torch.randn(b, 10, generator=g, dtype=torch.float64),
        "expression": torch.randn(b, 10, generator=g, dtype=torch.float64),
        "transl": torch.randn(b, 3, generator=g, dtype=torch.float64),
    }


def _oracle(family: str, path, x: dict[str, torch.Tensor]):
    kw = {"model_path": str(path), "ext": "npz", "use_pca": False, "flat_hand_mean": True, "dtype": torch.float64}
    p, b = x["pose"], x["pose"].shape[0]
    args = {
        "global_orient": p[:, 0],
        "body_pose": p[:, 1:22].reshape(b, -1),
        "betas": x["betas"],
        "transl": x["transl"],
    }
    if family == "smplh":
        model = smplx.SMPLH(num_betas=10, batch_size=b, **kw)
        args.update(left_hand_pose=p[:, 22:37].reshape(b, -1), right_hand_pose=p[:, 37:52].reshape(b, -1))
    else:
        model = smplx.SMPLX(num_betas=10, num_expression_coeffs=10, batch_size=b, **kw)
        args.update(
            jaw_pose=p[:, 22],
            leye_pose=p[:, 23],
            reye_pose=p[:, 24],
            left_hand_pose=p[:, 25:40].reshape(b, -1),
            right_hand_pose=p[:, 40:55].reshape(b, -1),
            expression=x["expression"],
        )
    with torch.no_grad():
        return model(**args)


@pytest.mark.parametrize("family", ["smplh", "smplx"])
def test_the_forward_agrees_with_smplx_to_1e_5_m(files, family):
    """Random body, hand, jaw and eye poses, betas, expressions and translations, float64."""
    x = _random(family, 4, seed=7)
    model = SMPLModel.from_file(files[family], num_betas=10, dtype=torch.float64)
    kw = {"expression": x["expression"]} if family == "smplx" else {}
    ours = model(x["pose"], x["betas"], transl=x["transl"], **kw)
    ref = _oracle(family, files[family], x)
    j = model.num_joints
    assert ours.vertices.shape == ref.vertices.shape
    assert (ours.vertices - ref.vertices).abs().max() < 1e-5
    assert (ours.joints - ref.joints[:, :j]).abs().max() < 1e-5
    # the pose blendshapes and the pose matter: the comparison can fail
    assert (ours.vertices - model(torch.zeros_like(x["pose"]), x["betas"], **kw).vertices).abs().max() > 0.1


def test_float32_follows_float64_and_one_betas_row_broadcasts(files):
    x = _random("smplx", 3, seed=2)
    m64 = SMPLModel.from_file(files["smplx"], dtype=torch.float64)
    m32 = SMPLModel.from_file(files["smplx"])
    assert m32.num_betas == 10 and m32.num_expression == 10  # the 10 + 10 v1.0 layout
    out64 = m64(x["pose"], x["betas"][:1])
    out32 = m32(x["pose"].float(), x["betas"][:1].float())
    assert out32.vertices.dtype == torch.float32
    assert (out32.vertices.double() - out64.vertices).abs().max() < 1e-4
    each = m64(x["pose"][1:2], x["betas"][:1])
    assert torch.allclose(each.vertices[0], out64.vertices[1], atol=1e-12)
    assert torch.allclose(m64.to(torch.float32).v_template, m32.v_template)


def test_gradients_match_finite_differences(files):
    model = SMPLModel.from_file(files["smplh"], dtype=torch.float64)
    x = _random("smplh", 2, seed=5)
    weights = torch.randn(2, model.num_vertices, 3, dtype=torch.float64, generator=torch.Generator().manual_seed(1))
    pose, betas = x["pose"].requires_grad_(), x["betas"][:, :10].clone()
    betas = torch.cat([betas, torch.zeros(2, 6, dtype=torch.float64)], 1).requires_grad_()
    loss = (model(pose, betas).vertices * weights).sum()
    gp, gb = torch.autograd.grad(loss, (pose, betas))
    for value, grad in ((pose, gp), (betas, gb)):
        d = torch.randn_like(value)
        with torch.no_grad():
            value += 1e-6 * d
            up = (model(pose, betas).vertices * weights).sum()
            value -= 2e-6 * d
            down = (model(pose, betas).vertices * weights).sum()
            value += 1e-6 * d
        assert float((up - down) / 2e-6) == pytest.approx(float((grad * d).sum()), rel=1e-5)


def test_a_pickled_model_file_reads_like_the_npz(tmp_path):
    model = make_model("smplh", seed=3, posedirs=True)
    a = SMPLModel.from_file(write_npz(tmp_path / "m.npz", model), dtype=torch.float64)
    b = SMPLModel.from_file(write_pkl(tmp_path / "m.pkl", model, chumpy=True), dtype=torch.float64)
    pose = 0.5 * torch.randn(2, 52, 3, dtype=torch.float64)
    assert torch.equal(a(pose).vertices, b(pose).vertices)
    assert b.name == "smplh" and a.faces().shape == (len(model["f"]), 3)


def test_bad_arguments_get_one_line_errors(files, tmp_path):
    model = SMPLModel.from_file(files["smplx"])
    pose = torch.zeros(2, 55, 3)
    with pytest.raises(ValueError, match=r"pose: expected shape \(B, 55, 3\), got \(2, 52, 3\)"):
        model(torch.zeros(2, 52, 3))
    with pytest.raises(ValueError, match="pose: expected finite values, got 1 NaN"):
        model(pose.index_put((torch.tensor([1]), torch.tensor([3]), torch.tensor([0])), torch.tensor(float("nan"))))
    with pytest.raises(ValueError, match=r"betas: expected shape \(B, 10\)"):
        model(pose, torch.zeros(2, 16))
    with pytest.raises(ValueError, match="betas: expected a batch of 1 or 2"):
        model(pose, torch.zeros(3, 10))
    with pytest.raises(TypeError, match="pose: is float64 on cpu but the smplx model is float32"):
        model(pose.double())
    with pytest.raises(ValueError, match=r"transl: expected shape \(B, 3\) with B=2"):
        model(pose, transl=torch.zeros(3, 3))
    no_pose = {k: v for k, v in make_model("smpl").items() if k != "weights"}
    with pytest.raises(ValueError, match="SMPL_MALE.npz: missing key 'weights'"):
        SMPLModel.from_file(write_npz(tmp_path / "SMPL_MALE.npz", no_pose))
    bad = make_model("smpl", posedirs=True)
    bad["weights"] = bad["weights"][:, :20]
    with pytest.raises(ValueError, match=r"SMPL_F.npz: weights: expected shape \(6890, 24\), got \(6890, 20\)"):
        SMPLModel.from_file(write_npz(tmp_path / "SMPL_F.npz", bad))
