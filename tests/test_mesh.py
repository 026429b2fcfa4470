"""unibody.geometry.mesh: normals, areas and edges against closed-form values."""

from __future__ import annotations

import pytest
import torch

from conftest import icosahedron
from unibody.geometry import mesh


def ico(dtype=torch.float64) -> tuple[torch.Tensor, torch.Tensor]:
    v, f = icosahedron()
    return torch.from_numpy(v).to(dtype), torch.from_numpy(f)


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_vertex_normals_are_radial_on_the_icosahedron(dtype):
    v, f = ico(dtype)
    n = mesh.vertex_normals(v, f)
    assert n.dtype == dtype
    torch.testing.assert_close(n, v)  # unit sphere: the radial direction is the vertex itself
    # Face normals point along the face centroids.
    c = v[f].mean(1)
    torch.testing.assert_close(mesh.face_normals(v, f), c / c.norm(dim=-1, keepdim=True))


def test_vertex_normals_weight_faces_by_area_and_leave_isolated_vertices_zero():
    v = torch.tensor([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 3], [5, 5, 5]], dtype=torch.float64)
    f = torch.tensor([[0, 1, 2], [0, 3, 1]])  # areas 0.5 (normal +z) and 1.5 (normal +y)
    n = mesh.vertex_normals(v, f)
    expected = torch.tensor([0, 1.5, 0.5], dtype=torch.float64)
    torch.testing.assert_close(n[0], expected / expected.norm(), atol=1e-15, rtol=0)
    assert torch.equal(n[4], torch.zeros(3, dtype=torch.float64))
    torch.testing.assert_close(mesh.face_areas(v, f), torch.tensor([0.5, 1.5], dtype=torch.float64))
    # Barycentric cells: a third of each incident face; they add up to the total area.
    cells = mesh.vertex_areas(v, f)
    torch.testing.assert_close(cells[0], torch.tensor(2.0 / 3.0, dtype=torch.float64))
    torch.testing.assert_close(cells.sum(), torch.tensor(2.0, dtype=torch.float64))


def test_batched_equals_one_by_one():
    v, f = ico()
    g = torch.Generator().manual_seed(0)
    vb = v * (1 + 0.3 * torch.rand(2, 3, *v.shape[:1], 1, generator=g, dtype=v.dtype))
    for fn in (mesh.vertex_normals, mesh.face_normals, mesh.face_areas, mesh.vertex_areas):
        out = fn(vb, f)
        for i in range(2):
            for j in range(3):
                assert torch.equal(out[i, j], fn(vb[i, j], f)), fn.__name__


def test_unique_edges_of_the_icosahedron():
    _, f = ico()
    e = mesh.unique_edges(f)
    assert e.shape == (30, 2)  # Euler: V - E + F = 2 with V = 12, F = 20
    assert bool((e[:, 0] < e[:, 1]).all())


def test_vertex_normals_gradcheck():
    v, f = ico()
    v = (v * 1.1).requires_grad_(True)
    assert torch.autograd.gradcheck(lambda x: mesh.vertex_normals(x, f), (v,))
