"""PanoMan RLA representation: edge topology, lengths and signed bending angles, RLA vectors,
the analytic shell Jacobian, connection maps and the reconstruction ``g`` (paper 004 §4.1, App. A)."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest
import scipy.sparse as sp
import torch

from conftest import icosphere
from unibody.panoman import reconstruct as recon_module
from unibody.panoman.mesh import EdgeTopology
from unibody.panoman.reconstruct import connection_maps, reconstruct, reconstruct_rla
from unibody.panoman.rla import (
    dihedral_angles,
    edge_lengths,
    face_frames,
    rla,
    rla_to_lengths_angles,
    shell_jacobian,
    wrap_angle,
)

# ----------------------------------------------------------------------------- meshes


def cube() -> tuple[np.ndarray, np.ndarray]:
    """Unit cube split into 12 outward-facing triangles."""
    v = np.array([[x, y, z] for x in (0, 1) for y in (0, 1) for z in (0, 1)], dtype=np.float64)
    quads = [[0, 1, 3, 2], [4, 6, 7, 5], [0, 4, 5, 1], [2, 3, 7, 6], [0, 2, 6, 4], [1, 5, 7, 3]]
    f = np.array([t for a, b, c, d in quads for t in ([a, b, c], [a, c, d])])
    return v, f


def hinge_tetrahedron(phi: float) -> tuple[np.ndarray, np.ndarray]:
    """Tetrahedron whose edge (0, 1) has faces ζ = (0, 1, 2) in z = 0 and τ = (1, 0, 3) hinged by ``phi``."""
    v = np.array([[0, 0, 0], [1, 0, 0], [0.5, 1, 0], [0.4, -math.cos(phi), -math.sin(phi)]])
    return v, np.array([[0, 1, 2], [1, 0, 3], [0, 2, 3], [1, 3, 2]])


def topo_of(faces: np.ndarray, num_vertices: int) -> EdgeTopology:
    return EdgeTopology.from_faces(torch.as_tensor(faces), num_vertices)


def random_rotation(gen: torch.Generator) -> torch.Tensor:
    q, r = torch.linalg.qr(torch.randn(3, 3, generator=gen, dtype=torch.float64))
    q = q * torch.sign(torch.diagonal(r))
    return q if torch.det(q) > 0 else -q


def kabsch_error(x: torch.Tensor, y: torch.Tensor) -> float:
    """Largest per-vertex distance between (V, 3) meshes after the best rigid fit of x onto y."""
    x, y = x.double(), y.double()
    cx, cy = x.mean(0), y.mean(0)
    u, _, vt = torch.linalg.svd((x - cx).T @ (y - cy))
    d = torch.sign(torch.det(u @ vt))
    rot = u @ torch.diag(torch.stack([d.new_ones(()), d.new_ones(()), d])) @ vt
    return float(((x - cx) @ rot + cy - y).norm(dim=-1).max())


@pytest.fixture(scope="module")
def canonical(rig) -> tuple[EdgeTopology, torch.Tensor]:
    return EdgeTopology.from_faces(rig.faces, rig.bind_vertices.shape[0]), rig.bind_vertices


@pytest.fixture(scope="module")
def posed() -> tuple[torch.Tensor, torch.Tensor]:
    """(rest (1, V, 3), posed (2, V, 3)) float64: the zero identity in two random poses (seeds 0 and 1)."""
    from unibody import BodyLayer

    layer = BodyLayer.from_pca(num_components=10, dtype=torch.float64)
    prep = layer.prepare_identity(torch.zeros(1, 10, dtype=torch.float64))
    poses = [
        0.4 * torch.randn(1, 77, 3, generator=torch.Generator().manual_seed(s), dtype=torch.float64) for s in (0, 1)
    ]
    return prep.rest_vertices, torch.cat([layer.pose(prep, p).vertices for p in poses])


# ----------------------------------------------------------------------------- topology


def test_topology_of_canonical_mesh(canonical):
    topo, verts = canonical
    assert (topo.num_vertices, topo.num_faces, topo.num_edges) == (18056, 36108, 54162)
    assert topo.num_vertices - topo.num_edges + topo.num_faces == 2  # genus 0
    faces, edges = topo.faces, topo.edges
    for t in (faces, edges, topo.edge_faces, topo.opposite, topo.face_edges, topo.edge_slots):
        assert t.dtype == torch.int64
    assert bool((edges[:, 0] < edges[:, 1]).all())
    key = edges[:, 0] * topo.num_vertices + edges[:, 1]
    assert bool((key[1:] > key[:-1]).all())  # sorted and unique
    # Face ζ (side 0) holds i -> j and τ (side 1) holds j -> i at the recorded slot, and the
    # opposite vertex is the face's third one.
    for side, (a, b) in enumerate(((0, 1), (1, 0))):
        f = faces[topo.edge_faces[:, side]]
        slot = topo.edge_slots[:, side]
        rows = torch.arange(topo.num_edges)
        assert torch.equal(f[rows, slot], edges[:, a])
        assert torch.equal(f[rows, (slot + 1) % 3], edges[:, b])
        assert torch.equal(f[rows, (slot + 2) % 3], topo.opposite[:, side])
        assert torch.equal(topo.face_edges[topo.edge_faces[:, side], slot], rows)
    assert bool((topo.edge_faces[:, 0] != topo.edge_faces[:, 1]).all())
    # Every face's three edges are its (v0 v1, v1 v2, v2 v0) pairs.
    ends = edges[topo.face_edges]  # (F, 3, 2)
    lo = torch.minimum(faces, faces.roll(-1, 1))
    hi = torch.maximum(faces, faces.roll(-1, 1))
    assert torch.equal(ends[..., 0], lo) and torch.equal(ends[..., 1], hi)
    # Outward orientation: positive enclosed volume and convex edges dominate on average.
    v = verts
    volume = float((torch.linalg.cross(v[faces[:, 0]], v[faces[:, 1]]) * v[faces[:, 2]]).sum() / 6)
    assert 0.03 < volume < 0.15  # cubic metres, a human body
    assert float(dihedral_angles(verts[None], topo).mean()) > 0


def test_topology_errors():
    v, f = cube()
    with pytest.raises(ValueError, match=r"faces: expected a closed manifold .* 3 boundary edges"):
        topo_of(f[1:], 8)
    flipped = f.copy()
    flipped[0] = flipped[0, ::-1]
    with pytest.raises(
        ValueError, match=r"faces: expected a consistently oriented mesh .* found 3 edges traversed twice"
    ):
        topo_of(flipped, 8)
    fin = np.array([[0, 1, 2], [1, 0, 3], [0, 1, 4], [1, 0, 2]])
    with pytest.raises(ValueError, match=r"non-manifold edges in more than two faces"):
        topo_of(fin, 5)
    with pytest.raises(ValueError, match=r"faces: expected shape \(F, 3\), got \(12, 4\)"):
        topo_of(np.zeros((12, 4), dtype=np.int64), 8)
    with pytest.raises(ValueError, match=r"faces: expected vertex ids in \[0, 7\), got range \[0, 7\]"):
        topo_of(f, 7)
    with pytest.raises(ValueError, match=r"faces: expected three distinct vertices .* 1 degenerate"):
        topo_of(np.vstack([f, [[0, 0, 1]]]), 8)
    with pytest.raises(TypeError, match=r"faces: expected an integer tensor, got float32"):
        EdgeTopology.from_faces(torch.as_tensor(f, dtype=torch.float32), 8)
    with pytest.raises(ValueError, match=r"num_vertices: expected a positive int"):
        topo_of(f, 0)


def test_topology_to_device_is_a_copy():
    v, f = cube()
    topo = topo_of(f, 8)
    assert topo.to("cpu") is topo
    meta = topo.to("meta")
    assert meta.edges.device.type == "meta" and meta.num_vertices == 8 and meta.num_edges == 18


# ----------------------------------------------------------------------------- lengths and angles


@pytest.mark.parametrize("phi", [-1.0, 0.3, 1.2, 2.5, math.pi - 1e-3])
def test_hinge_angle_and_sign(phi):
    v, f = hinge_tetrahedron(phi)
    topo = topo_of(f, 4)
    e = int(((topo.edges[:, 0] == 0) & (topo.edges[:, 1] == 1)).nonzero())
    assert topo.edge_faces[e].tolist() == [0, 1]
    a = dihedral_angles(torch.as_tensor(v)[None], topo)[0, e]
    assert float(a) == pytest.approx(phi, abs=1e-12)


def test_known_solids_angles_and_lengths(dtype):
    v, f = cube()
    topo = topo_of(f, 8)
    x = torch.as_tensor(v, dtype=dtype)[None]
    lengths, angles = edge_lengths(x, topo)[0], dihedral_angles(x, topo)[0]
    assert lengths.dtype == dtype and angles.dtype == dtype
    diagonal = (lengths - math.sqrt(2)).abs() < 1e-4
    assert int(diagonal.sum()) == 6
    torch.testing.assert_close(lengths[~diagonal], torch.ones(12, dtype=dtype))
    torch.testing.assert_close(angles[diagonal], torch.zeros(6, dtype=dtype), atol=1e-6, rtol=0)
    torch.testing.assert_close(angles[~diagonal], torch.full((12,), math.pi / 2, dtype=dtype))
    # Inward-facing cube: every edge is concave.
    inward = topo_of(f[:, ::-1].copy(), 8)
    torch.testing.assert_close(dihedral_angles(x, inward)[0][~diagonal], torch.full((12,), -math.pi / 2, dtype=dtype))
    # Regular tetrahedron: inner angle arccos(1/3), bending angle pi - arccos(1/3).
    tv = torch.tensor([[1, 1, 1], [1, -1, -1], [-1, 1, -1], [-1, -1, 1]], dtype=dtype)[None]
    tet = topo_of(np.array([[0, 1, 2], [0, 3, 1], [0, 2, 3], [1, 3, 2]]), 4)
    expected = math.pi - math.acos(1 / 3)
    torch.testing.assert_close(dihedral_angles(tv, tet), torch.full((1, 6), expected, dtype=dtype))


def test_flat_and_folded_pair():
    # A closed two-triangle "pillow": the two faces coincide, every edge folds by pi (not -pi).
    topo = topo_of(np.array([[0, 1, 2], [0, 2, 1]]), 3)
    x = torch.tensor([[[0.0, 0, 0], [1, 0, 0], [0, 1, 0]]], dtype=torch.float64)
    assert dihedral_angles(x, topo).tolist() == [[math.pi] * 3]


def test_wrap_angle():
    x = torch.tensor([-math.pi, math.pi, 3 * math.pi, -3 * math.pi + 0.1, 0.5, 7.0], dtype=torch.float64)
    expected = torch.tensor([math.pi, math.pi, math.pi, -math.pi + 0.1, 0.5, 7.0 - 2 * math.pi], dtype=torch.float64)
    torch.testing.assert_close(wrap_angle(x), expected)


def test_rigid_motion_invariance(canonical, posed):
    topo, _ = canonical
    x = posed[1][:1]
    gen = torch.Generator().manual_seed(3)
    moved = x @ random_rotation(gen).T + torch.randn(3, generator=gen, dtype=torch.float64)
    torch.testing.assert_close(edge_lengths(moved, topo), edge_lengths(x, topo), atol=1e-12, rtol=0)
    torch.testing.assert_close(dihedral_angles(moved, topo), dihedral_angles(x, topo), atol=1e-8, rtol=0)
    rl, ra = rla(x, moved, topo)
    # Relative length error ~ eps * (coordinates ~1.5 m) / (shortest edges ~0.3 mm) ~ 1e-12.
    assert float(rl.abs().max()) < 1e-11 and float(ra.abs().max()) < 1e-8
    rl, ra = rla(x, x, topo)
    assert float(rl.abs().max()) == 0 and float(ra.abs().max()) == 0


def test_rla_broadcasts_and_inverts(canonical, posed):
    topo, _ = canonical
    rest, x = posed
    rl, ra = rla(rest, x, topo)
    assert rl.shape == ra.shape == (2, topo.num_edges)
    assert float(ra.abs().max()) <= math.pi
    rl2, ra2 = rla(rest.expand(2, -1, -1), x, topo)
    torch.testing.assert_close(rl, rl2)
    torch.testing.assert_close(ra, ra2)
    lengths, angles = rla_to_lengths_angles(rl, ra, edge_lengths(rest, topo), dihedral_angles(rest, topo))
    torch.testing.assert_close(lengths, edge_lengths(x, topo), atol=1e-12, rtol=0)
    torch.testing.assert_close(angles, dihedral_angles(x, topo), atol=1e-9, rtol=0)


def test_rla_gradcheck():
    v, f = icosphere(1)
    topo = topo_of(f, len(v))
    gen = torch.Generator().manual_seed(0)
    rest = torch.as_tensor(v)[None] + 0.02 * torch.randn(1, len(v), 3, generator=gen, dtype=torch.float64)
    x = rest * torch.tensor([1.2, 0.8, 1.0], dtype=torch.float64) + 0.03 * torch.randn(
        1, len(v), 3, generator=gen, dtype=torch.float64
    )
    assert torch.autograd.gradcheck(
        lambda r, p: rla(r, p, topo), (rest.requires_grad_(), x.requires_grad_()), eps=1e-6, atol=1e-6
    )


# ----------------------------------------------------------------------------- shell Jacobian


def stacked(x: torch.Tensor, topo: EdgeTopology) -> torch.Tensor:
    return torch.cat([edge_lengths(x[None], topo)[0], dihedral_angles(x[None], topo)[0]])


def test_shell_jacobian_matches_autograd():
    v, f = icosphere(1)
    topo = topo_of(f, len(v))
    gen = torch.Generator().manual_seed(1)
    x = torch.as_tensor(v) * torch.tensor([1.0, 1.5, 0.7], dtype=torch.float64)
    x = x + 0.05 * torch.randn(x.shape, generator=gen, dtype=torch.float64)
    rows, cols, vals = shell_jacobian(x, topo)
    n_e = topo.num_edges
    assert rows.dtype == cols.dtype == np.int64 and vals.dtype == np.float64 and len(vals) == 18 * n_e
    jac = sp.coo_matrix((vals, (rows, cols)), shape=(2 * n_e, 3 * len(v))).toarray()
    assert np.count_nonzero(jac[:n_e], axis=1).max() == 6 and np.count_nonzero(jac[n_e:], axis=1).max() == 12
    ref = torch.autograd.functional.jacobian(lambda y: stacked(y.reshape(-1, 3), topo), x.reshape(-1))
    np.testing.assert_allclose(jac, ref.numpy(), atol=1e-10, rtol=0)
    # A NumPy array gives the same.
    np.testing.assert_array_equal(shell_jacobian(x.numpy(), topo)[2], vals)


def test_shell_jacobian_finite_differences_on_canonical(canonical, posed):
    topo, _ = canonical
    x = posed[1][0]
    rows, cols, vals = shell_jacobian(x, topo)
    jac = sp.csr_matrix((vals, (rows, cols)), shape=(2 * topo.num_edges, 3 * topo.num_vertices))
    n_e = topo.num_edges

    def central(step: torch.Tensor) -> torch.Tensor:
        diff = stacked(x + step, topo) - stacked(x - step, topo)
        return torch.cat([diff[:n_e], wrap_angle(diff[n_e:])]) / 2  # angles near pi may cross the cut

    # Every row at once along a random direction ... (the mesh has 0.1 mm edges, so derivatives reach
    # 1e4 rad/m and the step must be tiny; the FD error was checked to fall as h^2 down to h = 1e-8)
    gen = torch.Generator().manual_seed(2)
    d = torch.randn(x.shape, generator=gen, dtype=torch.float64)
    h = 1e-8
    analytic = jac @ d.reshape(-1).numpy()
    assert (np.abs(analytic - central(h * d).numpy() / h) <= 1e-4 * np.maximum(np.abs(analytic), 1)).all()
    # ... and a few rows entry by entry, on a topology restricted to their edges (same vertices).
    picked = torch.tensor([0, 1234, 7, 40000])
    sub = dataclasses.replace(topo, edges=topo.edges[picked], opposite=topo.opposite[picked])
    for k, row in enumerate([0, 1234, n_e + 7, n_e + 40000]):
        dense = jac[row].toarray()[0]
        for col in np.flatnonzero(dense):
            step = torch.zeros(3 * topo.num_vertices, dtype=torch.float64)
            step[col] = h
            plus, minus = stacked(x + step.reshape(-1, 3), sub), stacked(x - step.reshape(-1, 3), sub)
            diff = plus[k] - minus[k] if row < n_e else wrap_angle(plus[4 + k] - minus[4 + k])
            assert float(diff) / (2 * h) == pytest.approx(dense[col], rel=1e-4, abs=1e-4)


# ----------------------------------------------------------------------------- connection maps and g


def test_connection_maps_equal_actual_frames(canonical, posed):
    topo, _ = canonical
    x = posed[1]
    frames = face_frames(x, topo)
    eye = torch.eye(3, dtype=torch.float64)
    torch.testing.assert_close(frames.transpose(-1, -2) @ frames, eye.expand_as(frames), atol=1e-12, rtol=0)
    q = connection_maps(edge_lengths(x, topo), dihedral_angles(x, topo), topo)
    actual = frames[:, topo.edge_faces[:, 0]].transpose(-1, -2) @ frames[:, topo.edge_faces[:, 1]]
    assert float((q - actual).abs().max()) < 1e-10


def test_round_trip_float64(canonical, posed):
    topo, _ = canonical
    rest, x = posed
    rl, ra = rla(rest, x, topo)
    aligned = reconstruct_rla(rl, ra, rest, topo, reference=x)
    assert aligned.dtype == torch.float64 and aligned.shape == x.shape
    err = float((aligned - x).norm(dim=-1).max())
    print(f"g round trip, float64, B=2: max per-vertex error {err:.2e} m")
    assert err < 1e-8
    # Default gauge of reconstruct_rla: face 0's frame and the anchor vertex come from the rest mesh.
    free = reconstruct_rla(rl[:1], ra[:1], rest, topo)
    torch.testing.assert_close(face_frames(free, topo)[0, 0], face_frames(rest, topo)[0, 0], atol=1e-10, rtol=0)
    torch.testing.assert_close(free[0, 0], rest[0, 0], atol=1e-12, rtol=0)
    assert kabsch_error(free[0], x[0]) < 1e-8
    # Default gauge of reconstruct: face 0's frame is the identity, the anchor at the origin.
    lengths, angles = edge_lengths(x[:1], topo), dihedral_angles(x[:1], topo)
    own = reconstruct(lengths, angles, topo, anchor_vertex=5)
    torch.testing.assert_close(face_frames(own, topo)[0, 0], torch.eye(3, dtype=torch.float64), atol=1e-10, rtol=0)
    assert float(own[0, 5].abs().max()) == 0
    assert kabsch_error(own[0], x[0]) < 1e-8


def test_round_trip_float32_batched(canonical, posed):
    topo, _ = canonical
    rest, x = posed[0].float(), posed[1].float()
    rl, ra = rla(rest, x, topo)
    out = reconstruct_rla(rl, ra, rest, topo, reference=x)
    assert out.dtype == torch.float32 and out.shape == x.shape
    err = float((out.double() - posed[1]).norm(dim=-1).max())
    print(f"g round trip, float32, B=2: max per-vertex error {err:.2e} m")
    assert err < 1e-4


def test_inconsistent_input_cg_and_direct_agree(monkeypatch):
    """Slightly inconsistent input takes the CG path; forcing the direct path gives the same frames."""
    v, f = icosphere(2)
    topo = topo_of(f, len(v))
    x = torch.as_tensor(v)[None] * torch.tensor([1.0, 2.0, 0.5], dtype=torch.float64)
    gen = torch.Generator().manual_seed(4)
    lengths = edge_lengths(x, topo) * (1 + 1e-5 * torch.randn(1, topo.num_edges, generator=gen, dtype=torch.float64))
    angles = dihedral_angles(x, topo) + 1e-5 * torch.randn(1, topo.num_edges, generator=gen, dtype=torch.float64)
    q = connection_maps(lengths, angles, topo)[0].numpy()
    solver = recon_module._frame_solver(topo)
    calls = []
    real_pcg = recon_module._block_pcg
    monkeypatch.setattr(recon_module, "_block_pcg", lambda *a: calls.append(1) or real_pcg(*a))
    by_cg = solver.solve(q)
    assert calls == [1]
    monkeypatch.setattr(recon_module, "_CG_MAX_DEVIATION", 0.0)
    direct = solver.solve(q)
    assert calls == [1]
    np.testing.assert_allclose(by_cg, direct, atol=1e-10, rtol=0)
    # Strongly inconsistent input still gives a sane least-squares mesh (direct path).
    noisy = angles + 0.05 * torch.randn(angles.shape, generator=gen, dtype=torch.float64)
    out = reconstruct(lengths, noisy, topo, reference=x)
    assert 1e-4 < kabsch_error(out[0], x[0]) < 0.5


def test_closest_rotations_match_svd():
    gen = np.random.default_rng(0)
    m = gen.normal(size=(200, 3, 3))
    m[:5] = np.eye(3) + 1e-3 * gen.normal(size=(5, 3, 3))
    out = recon_module._closest_rotations(m)
    u, _, vt = np.linalg.svd(m)
    u[:, :, 2] *= np.sign(np.linalg.det(u @ vt))[:, None]
    np.testing.assert_allclose(out, u @ vt, atol=1e-10)
    assert bool((np.linalg.det(m) < 0).any())  # reflections were exercised


# ----------------------------------------------------------------------------- bad input


def test_bad_inputs():
    v, f = cube()
    topo = topo_of(f, 8)
    x = torch.as_tensor(v)[None]
    with pytest.raises(ValueError, match=r"vertices: expected shape \(B, 8, 3\), got \(1, 7, 3\)"):
        edge_lengths(x[:, :7], topo)
    with pytest.raises(ValueError, match=r"vertices: expected finite values, got 3 NaN"):
        dihedral_angles(torch.where(torch.arange(8)[None, :, None] == 3, float("nan"), x), topo)
    with pytest.raises(ValueError, match=r"rest: expected shape \(1, 8, 3\) or \(2, 8, 3\)"):
        rla(x.expand(3, -1, -1), x.expand(2, -1, -1), topo)
    with pytest.raises(TypeError, match=r"rest: is float32 on cpu but posed is float64"):
        rla(x.float(), x, topo)
    with pytest.raises(ValueError, match=r"vertices: expected shape \(8, 3\), got \(3, 8\)"):
        shell_jacobian(x[0].numpy().T, topo)
    with pytest.raises(ValueError, match=r"vertices: expected shape \(8, 3\), got \(1, 8, 3\)"):
        shell_jacobian(x, topo)
    bad = x[0].clone()
    bad[2, 1] = float("nan")
    with pytest.raises(ValueError, match=r"vertices: expected finite values, got 1 NaN"):
        shell_jacobian(bad, topo)
    lengths, angles = edge_lengths(x, topo), dihedral_angles(x, topo)
    with pytest.raises(ValueError, match=r"rest_lengths: expected shape \(1, E\) or \(B, E\) with B=1, E=18"):
        rla_to_lengths_angles(lengths, angles, lengths[:, :5], angles)
    with pytest.raises(ValueError, match=r"lengths: expected shape \(B, E\) with E=18, got \(1, 17\)"):
        reconstruct(lengths[:, 1:], angles[:, 1:], topo)
    with pytest.raises(TypeError, match=r"angles: is float32 on cpu but lengths is float64"):
        reconstruct(lengths, angles.float(), topo)
    with pytest.raises(ValueError, match=r"angles: expected finite values"):
        reconstruct(lengths, angles * float("nan"), topo)
    with pytest.raises(ValueError, match=r"lengths: expected positive values, got 1 entries"):
        reconstruct(torch.where(torch.arange(18) == 0, -1.0, lengths), angles, topo)
    with pytest.raises(ValueError, match=r"anchor_vertex: expected an int in \[0, 8\), got 8"):
        reconstruct(lengths, angles, topo, anchor_vertex=8)
    with pytest.raises(ValueError, match=r"reference: expected shape \(1, 8, 3\), got \(8, 3\)"):
        reconstruct(lengths, angles, topo, reference=x[0])
    with pytest.raises(ValueError, match=r"ra: expected shape \(B, E\) with .*got \(2, 18\)"):
        reconstruct_rla(lengths * 0, angles.expand(2, -1), x, topo)
    # Two separate tetrahedra: a valid topology that g cannot place as one mesh.
    tet = np.array([[0, 1, 2], [0, 3, 1], [0, 2, 3], [1, 3, 2]])
    two = topo_of(np.vstack([tet, tet + 4]), 8)
    with pytest.raises(ValueError, match=r"topo: expected one connected mesh .* found 2"):
        reconstruct(edge_lengths(x, two), dihedral_angles(x, two), two)
