"""AMASS files (SMPL-H, SMPL-X, both pose layouts) to canonical motions, on generated model files.

The model files are skinned exactly like the canonical body (``smpl_format.canonical_model``)
and the registration is replaced by that model's exact transfer (the monkeypatch pattern of
tests/test_registration.py), so a correct conversion reproduces the posed meshes to the
inverter's accuracy and nothing is registered in the default suite.
"""

from __future__ import annotations

import copy
from pathlib import Path

import numpy as np
import pytest
import torch

from smpl_format import canonical_model, write_npz
from unibody.convert import ConvertOptions, amass
from unibody.identity.smpl_model import SMPLModel


@pytest.fixture(scope="module")
def models(tmp_path_factory):
    root = tmp_path_factory.mktemp("models")
    transfers = {}
    paths = {}
    for family, rel in (("smplx", "smplx/SMPLX_FEMALE.npz"), ("smplh", "smplh/male/model.npz")):
        model, transfer = canonical_model(family, seed=1, num_shape=10 if family == "smplx" else 16)
        (root / rel).parent.mkdir(parents=True, exist_ok=True)
        paths[family] = write_npz(root / rel, model)
        transfers[model["v_template"].shape[0], len(model["J_regressor"])] = transfer
    return root, paths, transfers


@pytest.fixture(autouse=True)
def exact_transfer(models, monkeypatch):
    transfers = models[2]

    def fake(vertices, faces, name, **kw):
        family = "smplx" if vertices.shape[0] == 10475 else "smplh"
        return copy.deepcopy(transfers[vertices.shape[0], {"smplx": 55, "smplh": 52}[family]])

    monkeypatch.setattr(amass, "topology_transfer", fake)


def smooth_poses(t: int, joints: int, seed: int) -> np.ndarray:
    """(T, J*3) poses interpolated between random keys (0.3 rad), upright in a Z-up world."""
    rng = np.random.default_rng(seed)
    keys = rng.normal(scale=0.3, size=(4, joints * 3))
    s = np.linspace(0, 3, t)
    poses = np.stack([np.interp(s, np.arange(4), keys[:, i]) for i in range(joints * 3)], 1)
    poses[:, :3] = [np.pi / 2, 0.0, 0.4]  # SMPL's Y up turned to AMASS's Z up
    return poses


def write_take(path: Path, family: str, t: int = 24, seed: int = 0, split: bool = False, **extra) -> dict:
    rng = np.random.default_rng(seed + 100)
    poses = smooth_poses(t, 55 if family == "smplx" else 52, seed)
    fields = {
        "trans": np.cumsum(rng.normal(scale=0.01, size=(t, 3)), 0) + [0, 0, 0.9],
        "betas": rng.normal(size=16 if family == "smplh" else 10),
    }
    if family == "smplx":
        fields.update(gender=np.array("female"), mocap_frame_rate=np.array(120.0), surface_model_type=np.array("smplx"))
    else:
        fields.update(gender=np.array("male"), mocap_framerate=np.array(60.0))
    if split:
        fields.update(
            root_orient=poses[:, :3],
            pose_body=poses[:, 3:66],
            pose_jaw=poses[:, 66:69],
            pose_eye=poses[:, 69:75],
            pose_hand=poses[:, 75:],
        )
    else:
        fields["poses"] = poses
    fields.update(extra)
    np.savez(path, **fields)
    return {**fields, "poses": poses}


def reproduction_mm(model_path: Path, take: dict, motion, transfers, dtype=torch.float32) -> np.ndarray:
    """Per-frame mean distance (mm) between the SMPL-family meshes and the recovered motion on the canonical body.

    The generated model's vertices are a subset of the canonical mesh: compared vertex by vertex.
    """
    model = SMPLModel.from_file(model_path, dtype=dtype)
    layer, _, _ = amass.inverter(ConvertOptions(dtype=str(dtype).removeprefix("torch.")))
    betas = torch.as_tensor(take["betas"][: model.num_betas], dtype=dtype)[None]
    transfer = copy.deepcopy(transfers[model.num_vertices, model.num_joints]).to(dtype)
    t = len(take["poses"])
    with torch.no_grad():
        prepared = layer.prepare_rest(transfer(model.shaped(betas)))
        pose = torch.as_tensor(take["poses"], dtype=dtype).view(t, -1, 3)
        src = amass.to_y_up(model(pose, betas, transl=torch.as_tensor(take["trans"], dtype=dtype)).vertices)
        out = layer.pose(
            prepared, torch.as_tensor(motion.pose, dtype=dtype), transl=torch.as_tensor(motion.transl, dtype=dtype)
        )
    subset = transfer.face_vertices[:, 0]  # the canonical vertices that are template vertices map to themselves
    own = (transfer.weights[:, 0] - 1).abs() < 1e-9
    ids = torch.full((model.num_vertices,), -1, dtype=torch.long)
    ids[subset[own]] = torch.nonzero(own).squeeze(1)
    assert (ids >= 0).all()
    return 1000 * torch.linalg.vector_norm(out.vertices[:, ids] - src, dim=-1).mean(1).numpy()


def test_an_smplx_take_converts_and_reproduces_its_meshes(models, tmp_path):
    root, paths, transfers = models
    take = write_take(tmp_path / "walk_poses.npz", "smplx", t=16)
    out = amass.read_amass(tmp_path / "walk_poses.npz", ConvertOptions(models=root))
    m = out.motion
    assert m.pose.shape == (16, 77, 3) and m.transl.shape == (16, 3) and m.fps == 120.0
    assert m.source == "amass smplx female: walk_poses.npz"
    assert m.identity_backend == "pca" and m.identity.shape == (128,)
    assert out.stats["frames"] == 16 and out.stats["fps"] == 120.0 and out.stats["model"] == "SMPLX_FEMALE.npz"
    assert out.stats["inversion_mean_mm"] < 3.0
    for key in ("time_forward_s", "time_transfer_s", "time_inversion_s", "time_io_s", "inversion_max_mm"):
        assert out.stats[key] >= 0
    err = reproduction_mm(paths["smplx"], take, m, transfers)
    assert err.mean() < 3.0 and err.max() < 6.0, err
    # Y up: the body stands along +Y (AMASS Z up mapped by (x, y, z) -> (x, z, -y))
    assert np.allclose(m.transl[:, 1], take["trans"][:, 2], atol=0.1)


def test_the_split_smplx_keys_give_the_same_motion(models, tmp_path):
    root = models[0]
    write_take(tmp_path / "a.npz", "smplx", t=6, seed=4)
    write_take(tmp_path / "b.npz", "smplx", t=6, seed=4, split=True)
    a = amass.read_amass(tmp_path / "a.npz", ConvertOptions(models=root)).motion
    b = amass.read_amass(tmp_path / "b.npz", ConvertOptions(models=root)).motion
    assert np.array_equal(a.pose, b.pose) and np.array_equal(a.transl, b.transl)


def test_an_smplh_take_with_dmpls_converts_with_a_warning(models, tmp_path):
    root, paths, transfers = models
    take = write_take(tmp_path / "jump.npz", "smplh", t=8, seed=2, dmpls=np.zeros((8, 8)))
    out = amass.read_amass(tmp_path / "jump.npz", ConvertOptions(models=root))
    assert out.motion.fps == 60.0 and out.motion.source == "amass smplh male: jump.npz"
    assert any(w.startswith("dmpls ignored") for w in out.warnings)
    assert out.stats["model"] == "model.npz"
    err = reproduction_mm(paths["smplh"], take, out.motion, transfers)
    assert err.mean() < 3.0, err


def test_float64_matches_float32(models, tmp_path):
    root = models[0]
    write_take(tmp_path / "t.npz", "smplx", t=4, seed=5)
    a = amass.read_amass(tmp_path / "t.npz", ConvertOptions(models=root, dtype="float64"))
    b = amass.read_amass(tmp_path / "t.npz", ConvertOptions(models=root))
    assert a.stats["inversion_mean_mm"] < 3.0
    assert abs(a.stats["inversion_mean_mm"] - b.stats["inversion_mean_mm"]) < 0.2
    assert np.abs(a.motion.transl - b.motion.transl).max() < 1e-3


def test_an_unknown_layout_names_the_keys_and_the_layouts(models, tmp_path):
    np.savez(tmp_path / "x.npz", poses=np.zeros((5, 72)), trans=np.zeros((5, 3)))
    with pytest.raises(
        ValueError,
        match=r"x.npz: unknown AMASS layout \(poses \(5, 72\)\); keys: poses, trans; "
        r"expected SMPL-H poses \(T, 156\) or SMPL-X poses \(T, 165\)",
    ):
        amass.read_amass(tmp_path / "x.npz", ConvertOptions(models=models[0]))


def test_a_missing_gender_names_the_gender_the_folder_and_the_files(models, tmp_path):
    write_take(tmp_path / "m.npz", "smplx", t=3, gender=np.array("male"))
    with pytest.raises(
        ValueError,
        match=r"m.npz: no smplx model file for gender 'male' in .*models.* \(found: "
        r"smplh/male/model.npz \(smplh male\); smplx/SMPLX_FEMALE.npz \(smplx female\)\)",
    ):
        amass.read_amass(tmp_path / "m.npz", ConvertOptions(models=models[0]))
    with pytest.raises(ValueError, match="m.npz: an AMASS smplx take needs the user's model files: pass --models"):
        amass.read_amass(tmp_path / "m.npz", ConvertOptions())


def test_nan_frames_are_named_by_index(models, tmp_path):
    poses = smooth_poses(8, 55, 0)
    poses[[2, 5], 7] = np.nan
    write_take(tmp_path / "n.npz", "smplx", t=8, poses=poses)
    with pytest.raises(ValueError, match=r"n.npz: NaN/inf in poses or trans at frames 2, 5 \(2 of 8 frames\)"):
        amass.read_amass(tmp_path / "n.npz", ConvertOptions(models=models[0]))


def test_a_layout_against_its_surface_model_type_and_bad_fields_are_refused(models, tmp_path):
    root = models[0]
    write_take(tmp_path / "s.npz", "smplh", t=3, surface_model_type=np.array("smplx"))
    with pytest.raises(ValueError, match=r"s.npz: surface_model_type 'smplx' does not match the pose layout \(smplh"):
        amass.read_amass(tmp_path / "s.npz", ConvertOptions(models=root))
    write_take(tmp_path / "g.npz", "smplx", t=3, gender=np.array("robot"))
    with pytest.raises(ValueError, match="g.npz: gender: expected neutral, male or female, got 'robot'"):
        amass.read_amass(tmp_path / "g.npz", ConvertOptions(models=root))
    write_take(tmp_path / "f.npz", "smplx", t=3, mocap_frame_rate=np.array(-1.0))
    with pytest.raises(ValueError, match="f.npz: mocap_framerate: expected a positive number"):
        amass.read_amass(tmp_path / "f.npz", ConvertOptions(models=root))
    write_take(tmp_path / "h.npz", "smplh", t=3)
    with pytest.raises(ValueError, match="h.npz: the smplh take needs a smplh model file; .*SMPLX_FEMALE.npz is smplx"):
        amass.read_amass(tmp_path / "h.npz", ConvertOptions(models=models[1]["smplx"]))


def test_read_take_accepts_byte_strings_and_refuses_empty_takes(tmp_path):
    write_take(tmp_path / "b.npz", "smplh", t=3, gender=np.array(b"female"), surface_model_type=np.array(b"smplh"))
    take = amass.read_take(tmp_path / "b.npz")
    assert take.gender == "female" and take.family == "smplh" and take.poses.shape == (3, 52, 3)
    write_take(tmp_path / "e.npz", "smplx", t=0)
    with pytest.raises(ValueError, match=r"e.npz: poses: expected at least one frame, got shape \(0, 55, 3\)"):
        amass.read_take(tmp_path / "e.npz")
