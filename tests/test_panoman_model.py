"""PanoMan model, discrete-shell fit and body fit: invariants that can fail."""

from __future__ import annotations

import numpy as np
import pytest
import scipy.sparse as sp
import torch

from unibody import BodyLayer
from unibody.panoman.body_fit import _pose_from_joints, sparse_joint_regressor
from unibody.panoman.model import Decomposition, PanoMan, default_model_path
from unibody.panoman.nets import MLP, CorrectionNet
from unibody.panoman.rla import rla
from unibody.panoman.shell import Handles, ShellConfig, fit_shell

F64 = torch.float64


@pytest.fixture(scope="module")
def layer():
    return BodyLayer.from_pca(num_components=10, dtype=F64)


@pytest.fixture(scope="module")
def bodies(layer):
    """Rest mesh of a shape and two posed meshes of it (float64)."""
    gen = torch.Generator().manual_seed(3)
    alpha = 0.5 * torch.randn(1, 10, generator=gen, dtype=F64)
    prep = layer.prepare_identity(alpha)
    pose = 0.25 * torch.randn(2, 77, 3, generator=gen, dtype=F64)
    posed = layer.pose(prep, pose).vertices
    return alpha, prep, pose, posed


def _toy_model(posed, rest, with_nets=False):
    """Two body components: the exact RL/RA vectors of two posed meshes (dense 'components')."""
    from unibody.panoman.mesh import EdgeTopology
    from unibody.rig import Rig

    rig = Rig.canonical()
    topo = EdgeTopology.from_faces(rig.faces.long(), rig.num_vertices)
    rl, ra = rla(rest, posed, topo)
    e = topo.num_edges
    decs = [
        Decomposition.from_dense("rl", "body", torch.zeros(e), rl.float()),
        Decomposition.from_dense("ra", "body", torch.zeros(e), ra.float()),
    ]
    kw = {}
    if with_nets:
        torch.manual_seed(0)
        kw["beta_net"] = MLP((77 * 9, 8, 3), torch.tensor([0, 1, 3]), 4).eval()
        kw["correction"] = CorrectionNet((4, 5, 2), 1e-3 * torch.randn(2, 2 * e)).eval()
    return PanoMan(decs, **kw), rl, ra


def test_subspace_mesh_is_reconstructed_by_g(bodies):
    alpha, prep, _, posed = bodies
    model, _, _ = _toy_model(posed, prep.rest_vertices)
    # with the shape space's own rest for alpha, beta = e_1 means "the first posed mesh's RLA"
    assert torch.allclose(model.rest(alpha), prep.rest_vertices, atol=1e-9)
    beta = torch.tensor([[1.0, 0.0, 1.0, 0.0]], dtype=F64)
    out = model(alpha, beta, reference=posed[:1])
    assert (out - posed[:1]).norm(dim=-1).max() < 2e-4  # float32-stored components


def test_shell_fit_removes_noise_toward_the_subspace(bodies):
    alpha, prep, _, posed = bodies
    model, _, _ = _toy_model(posed, prep.rest_vertices)
    target = posed[0].numpy()
    # a smooth perturbation (what an imperfect initial fit looks like), 2 mm at most
    noisy = target + 2e-3 * np.sin(7.0 * target[:, [1, 2, 0]] + np.array([0.3, 1.1, 2.0]))
    ids = np.arange(0, target.shape[0], 600)
    res = fit_shell(
        model.topology,
        model.subspace(alpha[0]),
        noisy,
        Handles(ids, target[ids]),
        config=ShellConfig(iterations=6, refactor_every=1),
    )
    before = np.linalg.norm(noisy - target, axis=1).mean()
    after = np.linalg.norm(res.vertices - target, axis=1).mean()
    assert after < 0.15 * before, (before, after)
    assert res.energy[-1] < res.energy[0]
    assert abs(res.beta[0] - 1.0) < 0.05 and abs(res.beta[2] - 1.0) < 0.05


def test_handles_at_every_vertex_reproduce_the_target(bodies):
    alpha, prep, _, posed = bodies
    model, _, _ = _toy_model(posed, prep.rest_vertices)
    target = posed[1].numpy()  # not in the span of... anything but the second component
    init = prep.rest_vertices[0].numpy()
    ids = np.arange(target.shape[0])
    res = fit_shell(
        model.topology,
        model.subspace(alpha[0]),
        init,
        Handles(ids, target),
        config=ShellConfig(handles=1e6, iterations=4, refactor_every=1),
    )
    assert np.linalg.norm(res.vertices - target, axis=1).max() < 1e-4
    assert res.handle_error.max() < 1e-4


def test_save_load_round_trip(tmp_path, bodies):
    alpha, prep, pose, posed = bodies
    model, _, _ = _toy_model(posed, prep.rest_vertices, with_nets=True)
    path = tmp_path / "m.pt"
    model.save(path)
    again = PanoMan.load(path)
    beta = torch.tensor([[0.3, -0.2, 0.5, 0.1]], dtype=F64)
    for a, b in zip(model.rla(beta), again.rla(beta), strict=False):
        assert torch.allclose(a, b, atol=1e-3 * float(a.abs().max()))  # components stored as float16
    assert torch.allclose(model.beta_from_pose(pose), again.beta_from_pose(pose))
    assert again.beta_from_pose(pose)[:, 2].abs().max() == 0  # not predicted: stays 0


def test_load_rejects_other_files(tmp_path):
    p = tmp_path / "x.pt"
    torch.save({"format": "something"}, p)
    with pytest.raises(ValueError, match=r"x.pt: not a unibody.panoman/1 file .*\(format 'something', expected"):
        PanoMan.load(p)
    with pytest.raises(FileNotFoundError, match="path"):
        PanoMan.load(tmp_path / "missing.pt")


def test_analytic_ik_reproduces_joint_positions(layer, bodies):
    alpha, prep, pose, _ = bodies
    local = layer.local_rotations(pose, absolute=False)
    _, joints, _ = layer.skin_transforms(prep, local, torch.zeros(2, 3, dtype=F64))
    recovered = _pose_from_joints(layer, prep, joints[:, 1:])
    _, again, _ = layer.skin_transforms(
        prep, layer.local_rotations(recovered, absolute=False), torch.zeros(2, 3, dtype=F64)
    )
    assert (again - joints).norm(dim=-1).max() < 1e-8


def test_sparse_joint_regressor_is_affine_and_close():
    from unibody.panoman import dataset
    from unibody.rig import Rig

    train = torch.cat(
        [dataset.body_samples(24, seed=0, dtype=F64).posed, dataset.hand_samples(24, seed=0, dtype=F64).posed]
    )
    test = dataset.full_samples(4, seed=1, dtype=F64).posed
    ids, w = sparse_joint_regressor(train, vertices_per_joint=32)
    assert ids.shape == (77, 32) and torch.allclose(w.sum(1), torch.ones(77, dtype=F64))
    rig = Rig.canonical()
    dense = torch.zeros(78, rig.num_vertices, dtype=F64)
    dense[rig.rbf_joint.long(), rig.rbf_vertex.long()] = rig.rbf_weight.double()
    full = torch.einsum("jv,bvc->bjc", dense, test)[:, 1:]
    sparse = (test[:, ids] * w[None, ..., None]).sum(2)
    assert (full - sparse).norm(dim=-1).mean() < 3e-3  # held out: new identities and motions


@pytest.mark.skipif(not default_model_path().is_file(), reason="no shipped PanoMan model")
def test_shipped_model_components_are_sparse_and_local():
    model = PanoMan.load()
    e = model.topology.num_edges
    for d in model.decompositions:
        sizes = d.support_sizes()
        assert int(sizes.max()) < 0.5 * e, (d.quantity, d.subset, int(sizes.max()))
    assert model.beta_net is not None and model.joint_regressor is not None


def test_hostile_arguments_are_named_before_any_work(layer):
    # Each used to fail deep inside scipy or torch (an index error, a broadcast, a reshape), to
    # blame "vertices" or "identity params", or to run: ids 1.5 truncated, iterations -1.
    from unibody.panoman import fit, fit_body, regressor_matrix

    model = PanoMan.load()
    v = model.topology.vertex_count
    ref, alpha = torch.zeros(v, 3, dtype=F64), torch.zeros(10, dtype=F64)
    ids, pts = np.arange(0, v, 900), np.zeros((21, 3))
    cases = [
        (lambda: fit(model, alpha[:5], Handles(ids, pts), reference=ref), "alpha: expected shape (10), got (5,)"),
        (lambda: fit(model, alpha, Handles(ids, pts), reference=ref[:100]), "reference: expected shape (18056, 3)"),
        (lambda: fit(model, alpha * np.nan, Handles(ids, pts), reference=ref), "alpha: expected finite values"),
        (lambda: fit(model, alpha, Handles(ids, pts), reference=ref, pose=torch.zeros(10, 3)), "pose: expected shape"),
        (lambda: fit(model, alpha, Handles(np.array([v]), pts[:1]), reference=ref), f"got {v}"),
        (lambda: fit(model, alpha, Handles(np.array([-1]), pts[:1]), reference=ref), "in [0, 18056), got -1"),
        (lambda: Handles(np.array([1.5]), pts[:1]), "handles.vertex_ids: expected (H,) integer vertex ids"),
        (lambda: Handles(ids, pts[:3]), "handles.vertex_targets: expected (21, 3) numbers, got (3, 3)"),
        (lambda: Handles(ids, pts * np.nan), "handles.vertex_targets: expected finite values, got 63 NaN/inf"),
        (lambda: Handles(ids, None), "handles: give vertex_ids and vertex_targets together"),
        (lambda: ShellConfig(iterations=0), "config.iterations: expected an int >= 1, got 0"),
        (lambda: ShellConfig(handles=float("nan")), "config.handles: expected a finite number >= 0, got nan"),
        (lambda: ShellConfig(damping=-1.0), "config.damping: expected a finite number >= 0, got -1.0"),
    ]
    for call, message in cases:
        with pytest.raises(ValueError) as err:
            call()
        assert message in str(err.value), (message, str(err.value))
    assert ShellConfig(iterations=np.int64(3), bending=np.float32(2)).iterations == 3  # numpy numbers are numbers
    regs = sp.random(3, 100, density=0.1, format="csr")
    with pytest.raises(ValueError, match="handles.regressor: expected 18056 columns, got 100"):
        Handles(regressor=regs, regressor_targets=np.zeros((3, 3))).matrix(v)
    reg = regressor_matrix(*model.joint_regressor, v)
    joints, t_ids = torch.zeros(1, 77, 3, dtype=F64), torch.tensor([0, 900])
    body = [
        (
            lambda: fit_body(layer, t_ids, torch.zeros(1, 3, 3, dtype=F64), reg, joints),
            "vertex_targets: expected shape",
        ),
        (
            lambda: fit_body(layer, t_ids + v, torch.zeros(1, 2, 3, dtype=F64), reg, joints),
            "vertex_ids: expected canonical",
        ),
        (
            lambda: fit_body(layer, t_ids, torch.zeros(1, 2, 3, dtype=F64), reg, joints * np.nan),
            "joint_targets: expected finite",
        ),
        (
            lambda: fit_body(layer, t_ids, torch.zeros(1, 2, 3, dtype=F64), reg, joints[:, :10]),
            "joint_targets: expected shape",
        ),
        (
            lambda: fit_body(layer, t_ids * 1.0, torch.zeros(1, 2, 3, dtype=F64), reg, joints),
            "vertex_ids: expected integer",
        ),
        (
            lambda: fit_body(layer, t_ids, torch.zeros(1, 2, 3), reg, joints),
            "vertex_targets: is float32 on cpu but the layer",
        ),
    ]
    for call, message in body:
        with pytest.raises((ValueError, TypeError)) as err:
            call()
        assert message in str(err.value), (message, str(err.value))
