"""Mesh sequences (canonical, and a foreign topology through a template) to canonical motions."""

from __future__ import annotations

import copy
import os
from pathlib import Path

import numpy as np
import pytest
import torch

from smpl_format import canonical_model, write_npz
from unibody.convert import ConvertOptions, amass, meshes
from unibody.identity.smpl_model import SMPLModel


def _write_obj(path, v, f):
    lines = [f"v {x:.9f} {y:.9f} {z:.9f}" for x, y, z in v] + [f"f {a + 1} {b + 1} {c + 1}" for a, b, c in f]
    path.write_text("\n".join(lines) + "\n")
    return path


@pytest.fixture(scope="module")
def smplh(tmp_path_factory):
    """A canonical-skinned SMPL-H-format model (6,890 v), its files, its exact transfer and 10 posed meshes."""
    root = tmp_path_factory.mktemp("meshes")
    model, transfer = canonical_model("smplh", seed=2)
    npz = write_npz(root / "smplh_model.npz", model)
    obj = _write_obj(root / "smpl_rest.obj", model["v_template"], model["f"])
    body = SMPLModel.from_file(npz, dtype=torch.float64)
    g = torch.Generator().manual_seed(3)
    pose = 0.25 * torch.randn(10, 52, 3, generator=g, dtype=torch.float64)
    with torch.no_grad():
        verts = body(pose, transl=torch.tensor([[0.0, 1.0, 0.0]], dtype=torch.float64).expand(10, 3)).vertices
    return {"npz": npz, "obj": obj, "transfer": transfer, "vertices": verts.numpy(), "root": root}


@pytest.fixture(autouse=True)
def exact_transfer(smplh, monkeypatch):
    calls = []

    def fake(vertices, faces, name, **kw):
        calls.append((np.asarray(vertices).shape, name))
        return copy.deepcopy(smplh["transfer"])

    monkeypatch.setattr(meshes, "topology_transfer", fake)
    meshes._cached_transfer.cache_clear()
    return calls


def test_a_canonical_sequence_keeps_its_fps_and_is_reproduced(tmp_path):
    layer, _, _ = amass.inverter(ConvertOptions())
    g = torch.Generator().manual_seed(0)
    with torch.no_grad():
        prepared = layer.prepare_identity(0.5 * torch.randn(1, 128, generator=g))
        pose = 0.3 * torch.randn(8, 77, 3, generator=g)
        posed = layer.pose(prepared, pose, transl=torch.randn(8, 3, generator=g)).vertices
    np.savez(tmp_path / "c.npz", vertices=posed.numpy(), topology=np.array("canonical"), fps=np.array(50.0))
    out = meshes.read_meshes(tmp_path / "c.npz", ConvertOptions())
    m = out.motion
    assert m.fps == 50.0 and m.pose.shape == (8, 77, 3) and out.warnings == ()
    assert m.source == "meshes canonical: c.npz" and out.stats["topology"] == "canonical"
    assert out.stats["inversion_mean_mm"] < 4.0, out.stats  # the rest shape is estimated from posed frame 0

    # the identity was estimated from the meshes: its PCA projection is near the generating body (bind pose, centred)
    def bind(p):
        x = layer.repose_to_bind(p)
        return x - x.mean(1, keepdim=True)

    with torch.no_grad():
        fit = bind(layer.prepare_identity(torch.from_numpy(m.identity)[None]))
        gen, mean = bind(prepared), bind(layer.prepare_identity(torch.zeros(1, 128)))
    err = float(torch.linalg.vector_norm(fit - gen, dim=-1).mean())
    assert err < 0.008 and err < 0.2 * float(torch.linalg.vector_norm(mean - gen, dim=-1).mean()), err


@pytest.mark.parametrize("template", ["obj", "npz"])
def test_a_foreign_topology_goes_through_its_template(smplh, tmp_path, template, exact_transfer):
    np.savez(tmp_path / "s.npz", vertices=smplh["vertices"].astype(np.float32), topology=np.array("smpl"))
    out = meshes.read_meshes(tmp_path / "s.npz", ConvertOptions(template=smplh[template]))
    assert out.motion.fps == 30.0 and out.warnings == ("fps missing: 30 assumed",)
    assert out.stats["frames"] == 10 and out.stats["inversion_mean_mm"] < 3.0, out.stats
    assert exact_transfer[0][0] == (6890, 3)
    # the motion on the canonical body reproduces the SMPL-H meshes (their vertices are canonical ones)
    layer, _, _ = amass.inverter(ConvertOptions())
    t = copy.deepcopy(smplh["transfer"]).to(torch.float32)
    with torch.no_grad():
        src = torch.from_numpy(smplh["vertices"]).float()
        prepared = layer.prepare_rest(_rest(out, layer, t, src))
        posed = layer.pose(prepared, torch.from_numpy(out.motion.pose), transl=torch.from_numpy(out.motion.transl))
    target = t(src)
    err = 1000 * torch.linalg.vector_norm(posed.vertices - target, dim=-1).mean(1)
    assert float(err.mean()) < 3.0, err


def _rest(out, layer, transfer, src):
    from unibody.fitting.inversion import PRESETS, PoseInverter

    return PoseInverter(layer, PRESETS["analytic"]).estimate_identity(transfer(src[:1])).rest_vertices


def test_float64_converts_like_float32(smplh, tmp_path):
    np.savez(tmp_path / "s.npz", vertices=smplh["vertices"][:3], topology=np.array("smpl"), fps=np.array(24))
    a = meshes.read_meshes(tmp_path / "s.npz", ConvertOptions(template=smplh["obj"], dtype="float64"))
    b = meshes.read_meshes(tmp_path / "s.npz", ConvertOptions(template=smplh["obj"]))
    assert a.motion.fps == 24.0 and a.stats["inversion_mean_mm"] < 3.0
    assert abs(a.stats["inversion_mean_mm"] - b.stats["inversion_mean_mm"]) < 0.2
    assert np.abs(a.motion.transl - b.motion.transl).max() < 1e-3


def test_a_foreign_topology_without_a_template_says_what_template_takes(tmp_path):
    np.savez(tmp_path / "x.npz", vertices=np.zeros((2, 10475, 3), np.float32), topology=np.array("smplx"))
    with pytest.raises(
        ValueError,
        match=r"x.npz: vertices have 10475 per frame \(topology 'smplx'\), not the canonical 18056 or Anny's 13718: "
        r"pass --template; --template takes the topology.s rest mesh: an .obj with faces, an SMPL-family "
        r".npz/.pkl model file, or an MHR asset folder",
    ):
        meshes.read_meshes(tmp_path / "x.npz", ConvertOptions())


def test_a_template_of_another_count_and_bad_fields_are_refused(smplh, tmp_path):
    np.savez(tmp_path / "y.npz", vertices=np.zeros((2, 100, 3), np.float32), topology=np.array("smpl"))
    with pytest.raises(ValueError, match="y.npz: vertices have 100 per frame but the template smpl_rest.obj has 6890"):
        meshes.read_meshes(tmp_path / "y.npz", ConvertOptions(template=smplh["obj"]))
    v = np.zeros((5, 100, 3), np.float32)
    v[[1, 3], 7, 2] = np.nan
    np.savez(tmp_path / "n.npz", vertices=v, topology=np.array("smpl"))
    with pytest.raises(ValueError, match=r"n.npz: vertices: NaN/inf at frames 1, 3 \(2 of 5 frames\)"):
        meshes.read_meshes(tmp_path / "n.npz", ConvertOptions())
    np.savez(tmp_path / "t.npz", vertices=np.zeros((5, 100, 2), np.float32), topology=np.array("smpl"))
    with pytest.raises(ValueError, match=r"t.npz: vertices: expected floats of shape \(T, N, 3\)"):
        meshes.read_meshes(tmp_path / "t.npz", ConvertOptions())
    np.savez(tmp_path / "m.npz", vertices=np.zeros((5, 100, 3), np.float32))
    with pytest.raises(ValueError, match="m.npz: missing field.s. topology"):
        meshes.read_meshes(tmp_path / "m.npz", ConvertOptions())
    with pytest.raises(ValueError, match="--template: expected an .obj, .npz or .pkl file, got 'a.ply'"):
        (tmp_path / "a.ply").write_text("ply")
        meshes.read_meshes(tmp_path / "y.npz", ConvertOptions(template=tmp_path / "a.ply"))


def test_a_template_the_registration_refuses_is_named(smplh, tmp_path, monkeypatch):
    def refuse(vertices, faces, name, **kw):
        raise ValueError("vertices: not a body the canonical mesh can wrap: ...")

    monkeypatch.setattr(meshes, "topology_transfer", refuse)
    np.savez(tmp_path / "y.npz", vertices=np.zeros((2, 6890, 3), np.float32), topology=np.array("smpl"))
    with pytest.raises(ValueError, match=r"^--template smpl_rest.obj: vertices: not a body the canonical mesh"):
        meshes.read_meshes(tmp_path / "y.npz", ConvertOptions(template=smplh["obj"]))


def test_an_mhr_asset_folder_is_a_template_and_its_lod_is_picked_by_vertex_count(tmp_path, monkeypatch):
    from mhr_format import write_mhr_assets
    from unibody.identity.mhr import MHRIdentity

    write_mhr_assets(tmp_path / "mhr", seed=0, num_vertices=40)
    seen = []

    class Stop(Exception):
        pass

    def record(vertices, faces, name, **kw):
        seen.append((np.asarray(vertices), np.asarray(faces)))
        raise Stop

    monkeypatch.setattr(meshes, "topology_transfer", record)
    np.savez(tmp_path / "p.npz", vertices=np.ones((1, 40, 3), np.float32), topology=np.array("mhr"))
    with pytest.raises(Stop):
        meshes.read_meshes(tmp_path / "p.npz", ConvertOptions(template=tmp_path / "mhr"))
    rest = MHRIdentity.from_files(tmp_path / "mhr", lod=1, dtype=torch.float64).template().numpy()
    assert np.allclose(seen[0][0], rest) and seen[0][1].shape[1] == 3  # the mean rest mesh, in metres
    np.savez(tmp_path / "q.npz", vertices=np.ones((1, 41, 3), np.float32), topology=np.array("mhr"))
    with pytest.raises(
        ValueError, match=r"--template: no MHR LOD in .*mhr has 41 vertices \(LOD: vertices \{1: 40\}\)"
    ):
        meshes.read_meshes(tmp_path / "q.npz", ConvertOptions(template=tmp_path / "mhr"))


@pytest.mark.slow
@pytest.mark.licensed
@pytest.mark.skipif(not os.environ.get("UNIBODY_MHR_DIR"), reason="set UNIBODY_MHR_DIR to MHR converted assets")
def test_sam_3d_body_outputs_invert_through_the_mhr_lod1_topology(tmp_path, monkeypatch):
    """Real SAM 3D Body predictions (../shared/evaldata/mhr, Apache-2.0) on MHR lod1, registered for real."""
    monkeypatch.undo()  # the real registration (~40 s once per template, then cached)
    from smpl_format import evaldata_dir

    files = sorted((evaldata_dir() / "mhr").glob("*.npz"))
    if not files:
        pytest.skip("no SAM 3D Body outputs under the evaluation data")
    for path in files:
        with np.load(path) as data:
            v = data["pred_vertices"][None].astype(np.float32)  # camera frame, metres: a rotation of any world
        np.savez(tmp_path / path.name, vertices=v, topology=np.array("mhr lod1"))
        out = meshes.read_meshes(tmp_path / path.name, ConvertOptions(template=Path(os.environ["UNIBODY_MHR_DIR"])))
        print(path.name, out.stats)
        assert out.stats["inversion_mean_mm"] < 15.0, (path.name, out.stats)
