"""``g``: a mesh from its edge lengths and signed bending angles (paper 004 App. A, after Wang et al. 2017).

Face frames are solved from per-edge connection maps (one sparse least-squares problem, face 0
fixed), then vertices from the framed edge vectors (a cached graph Laplacian, ``anchor_vertex``
fixed); computed in float64, the input dtype and device come back. Steps: ``docs/panoman.md``.

Gauge: ``reconstruct`` without ``reference`` returns face 0's frame equal to the identity and the
anchor vertex at the origin; with ``reference`` the result is rigidly aligned to it (Kabsch over
all vertices). ``reconstruct_rla`` without ``reference`` takes face 0's frame and the anchor's
position from the rest mesh. Inconsistent input (e.g. blended RLA vectors) gives the
least-squares mesh.
"""

from __future__ import annotations

import weakref
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp
import scipy.sparse.csgraph as csgraph
import scipy.sparse.linalg as spla
import torch

from .._checks import check_finite, check_shape, check_tensor
from ..geometry.procrustes import kabsch, polar
from ._cholesky import cholesky
from .mesh import EdgeTopology
from .rla import dihedral_angles, edge_lengths, face_frames, rla_to_lengths_angles

__all__ = ["connection_maps", "reconstruct", "reconstruct_rla"]

# Corner indices into the edge-local points (x_i, x_j, x_k, x_h) of each face's first edge
# (v0, v1), by the slot of the edge in that face: ζ holds i -> j, so its vertices roll to
# (i, j, k), (k, i, j) or (j, k, i); τ holds j -> i and rolls to (j, i, h), (h, j, i) or (i, h, j).
_ZETA_FIRST = ((0, 1), (2, 0), (1, 2))
_TAU_FIRST = ((1, 0), (3, 1), (0, 3))


def _triangle_apex(base: torch.Tensor, left: torch.Tensor, right: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """In-plane coordinates ``(x, y >= 0)`` of a triangle's apex over a base on the x axis.

    ``left`` and ``right`` are the apex's distances to the base's start and end; a triangle
    inequality violation clamps ``y`` to 0.
    """
    x = (base * base + left * left - right * right) / (2 * base)
    return x, torch.sqrt(torch.clamp(left * left - x * x, min=0))


def _frame_from_first_edge(u: torch.Tensor, n: torch.Tensor) -> torch.Tensor:
    u = torch.nn.functional.normalize(u, dim=-1)
    return torch.stack([u, torch.linalg.cross(n, u), n], dim=-1)


def connection_maps(lengths: torch.Tensor, angles: torch.Tensor, topo: EdgeTopology) -> torch.Tensor:
    """Connection map ``Q_e = R_ζ^T R_τ`` of every edge from lengths and bending angles only.

    Both faces are laid out in a frame at the edge (origin ``x_i``, x along ``i -> j``, z along
    ``n_ζ``): ``ζ`` flat in z = 0 with its apex at ``y > 0``, ``τ`` unfolded to ``y < 0`` and then
    hinged about the x axis by the bending angle. Each face's frame follows from its first edge
    in that layout, and ``Q_e`` is their relative rotation.

    Args:
        lengths: (B, E) edge lengths, metres.
        angles: (B, E) signed bending angles, radians (convention of :mod:`unibody.panoman.rla`).
        topo: the mesh's edge tables.

    Returns:
        (B, E, 3, 3) rotations, equal to ``face_frames(x)[ζ]^T face_frames(x)[τ]`` for a mesh ``x``
        with these lengths and angles.

    Raises:
        ValueError: wrong shapes, non-finite values or non-positive lengths.
    """
    _check_lengths_angles(lengths, angles, topo)
    dev = lengths.device
    edge_faces, slots = topo.edge_faces.to(dev), topo.edge_slots.to(dev)
    face_lengths = lengths[:, topo.face_edges.to(dev)]  # (B, F, 3)
    zeta = face_lengths[:, edge_faces[:, 0]]  # (B, E, 3), slot s holds i -> j
    tau = face_lengths[:, edge_faces[:, 1]]  # slot s holds j -> i

    def at(x: torch.Tensor, shift: int, slot: torch.Tensor) -> torch.Tensor:
        return torch.gather(x, 2, ((slot + shift) % 3).expand(x.shape[0], -1)[..., None])[..., 0]

    s_zeta, s_tau = slots[:, 0], slots[:, 1]
    xk, yk = _triangle_apex(lengths, at(zeta, 2, s_zeta), at(zeta, 1, s_zeta))  # |k - i|, |k - j|
    xh, yh = _triangle_apex(lengths, at(tau, 1, s_tau), at(tau, 2, s_tau))  # |h - i|, |h - j|
    zero = torch.zeros_like(lengths)
    cos, sin = torch.cos(angles), torch.sin(angles)
    points = torch.stack(
        [
            torch.stack([zero, zero, zero], -1),
            torch.stack([lengths, zero, zero], -1),
            torch.stack([xk, yk, zero], -1),
            torch.stack([xh, -yh * cos, -yh * sin], -1),
        ],
        dim=2,
    )  # (B, E, 4, 3): x_i, x_j, x_k, x_h

    rows = torch.arange(topo.num_edges, device=dev)

    def first_edge(table: tuple[tuple[int, int], ...], slot: torch.Tensor) -> torch.Tensor:
        corners = torch.tensor(table, device=dev)[slot]  # (E, 2)
        return points[:, rows, corners[:, 1]] - points[:, rows, corners[:, 0]]

    one = torch.ones_like(lengths)
    r_zeta = _frame_from_first_edge(first_edge(_ZETA_FIRST, s_zeta), torch.stack([zero, zero, one], -1))
    r_tau = _frame_from_first_edge(first_edge(_TAU_FIRST, s_tau), torch.stack([zero, -sin, cos], -1))
    return r_zeta.transpose(-1, -2) @ r_tau


def _check_lengths_angles(lengths: torch.Tensor, angles: torch.Tensor, topo: EdgeTopology) -> None:
    for x, name in ((lengths, "lengths"), (angles, "angles")):
        check_tensor(x, name)
        if not x.is_floating_point():
            raise TypeError(f"{name}: expected a floating tensor, got {str(x.dtype).removeprefix('torch.')}")
    sizes = {"E": topo.num_edges}
    check_shape(lengths, "B E", name="lengths", sizes=sizes)
    check_shape(angles, "B E", name="angles", sizes=sizes)
    if angles.dtype != lengths.dtype or angles.device != lengths.device:
        raise TypeError(
            f"angles: is {str(angles.dtype).removeprefix('torch.')} on {angles.device} but lengths is "
            f"{str(lengths.dtype).removeprefix('torch.')} on {lengths.device}; convert one of them"
        )
    check_finite(lengths, "lengths")
    check_finite(angles, "angles")
    if bool((lengths <= 0).any()):
        raise ValueError(f"lengths: expected positive values, got {int((lengths <= 0).sum())} entries <= 0")


_CG_MAX_DEVIATION = 1e-3  # largest |C_e - I| entry for which the CG path is tried
_CG_TOL = 1e-12  # largest preconditioned-residual entry (~ frame error) at which CG stops
_CG_MAX_ITER = 30


def _splu(matrix: sp.spmatrix) -> spla.SuperLU:
    """SuperLU of a symmetric positive definite matrix (minimum degree on A + A^T, diagonal pivots)."""
    # SuperLU's relax/panel_size knobs are left at their defaults: relax > panel_size corrupts the heap.
    return spla.splu(
        sp.csc_matrix(matrix), permc_spec="MMD_AT_PLUS_A", options={"SymmetricMode": True, "DiagPivotThresh": 0.0}
    )


@dataclass(frozen=True)
class _FrameSolver:
    """Per-topology data of the frame solve: edge faces, a BFS spanning tree of the face graph
    from face 0, its factorised Laplacian (face 0 removed) and the fixed sparsity pattern of the
    (3F x 3F) normal matrix."""

    zeta: np.ndarray  # (E,) face ζ of every edge
    tau: np.ndarray  # (E,) face τ of every edge
    parent: np.ndarray  # (F,) BFS parent (face 0 is its own)
    parent_edge: np.ndarray  # (F,) the edge shared with the parent (unused for face 0)
    is_tau: np.ndarray  # (F,) whether the face is τ of that edge
    face_laplacian: spla.SuperLU  # (F-1, F-1), the CG preconditioner
    free_mask: np.ndarray  # (36 E,) COO entries of the normal matrix outside face 0's rows and columns
    free_slot: np.ndarray  # their position in the CSR data of the free block (duplicates add up)
    free_indices: np.ndarray
    free_indptr: np.ndarray
    rhs_mask: np.ndarray  # COO entries in face 0's columns and free rows
    rhs_slot: np.ndarray  # their flat position in the (3F-3, 3) right-hand side

    @property
    def num_faces(self) -> int:
        return self.parent.shape[0]

    def tree_frames(self, q: np.ndarray) -> np.ndarray:
        """Frames (F, 3, 3) chained from face 0 = I along the tree, by pointer jumping.

        Invariant: ``R_t = R_{up[t]} @ acc[t]``; each step composes with the ancestor's
        transform and doubles the distance jumped, so log2(depth) steps reach face 0.
        """
        edge_q = q[self.parent_edge]
        acc = np.where(self.is_tau[:, None, None], edge_q, edge_q.transpose(0, 2, 1))
        acc[0] = np.eye(3)
        up = self.parent.copy()
        while (up != 0).any():
            acc = acc[up] @ acc
            up = up[up]
        return acc

    def system(self, c: np.ndarray) -> tuple[sp.csr_matrix, np.ndarray]:
        """Free block and right-hand side of the normal equations of ``sum_e |x_τ - C_e^T x_ζ|^2``.

        The unknown ``x`` is one row of every frame (3F entries); the normal matrix has blocks
        ``I`` at (τ,τ), ``C C^T`` at (ζ,ζ), ``-C^T`` at (τ,ζ) and ``-C`` at (ζ,τ). Face 0's rows
        are fixed to ``e_0, e_1, e_2``, which moves its columns to the right-hand side.
        """
        ct = c.transpose(0, 2, 1)
        vals = np.concatenate([np.broadcast_to(np.eye(3), c.shape).ravel(), (c @ ct).ravel(), -ct.ravel(), -c.ravel()])
        n = 3 * self.num_faces - 3
        data = np.bincount(self.free_slot, weights=vals[self.free_mask], minlength=len(self.free_indices))
        matrix = sp.csr_matrix((data, self.free_indices, self.free_indptr), shape=(n, n))
        rhs = -np.bincount(self.rhs_slot, weights=vals[self.rhs_mask], minlength=3 * n).reshape(n, 3)
        return matrix, rhs

    def solve(self, q: np.ndarray) -> np.ndarray:
        """Frames (F, 3, 3) minimising ``sum_e ||R_τ - R_ζ Q_e||^2`` with ``R_0 = I``, projected to rotations.

        Row ``r`` of the frames, ``x_t = e_r^T R_t``, minimises ``sum_e |x_τ - x_ζ Q_e|^2``: three
        right-hand sides of one linear system. We change variables to ``y_t = x_t T_t^T`` with ``T``
        the frames chained along the tree (orthogonal, so the same least squares); the system keeps
        its form with ``C_e = T_ζ Q_e T_τ^T``, which is ``I`` on tree edges, and on every edge when
        the input is consistent. Nearly consistent input (``|C_e - I| < 1e-3``: exact or float32
        RLA vectors) is then solved by conjugate gradients from ``y_t = e_r`` preconditioned by
        the face-graph Laplacian (x) I3 (factorised once per topology), which converges in a few
        steps. Inconsistent input (blended RLA vectors) has a frustrated connection that no flat
        preconditioner matches, so it goes to a direct sparse Cholesky factorisation of the
        (3F - 3) system instead (sparse Cholesky), as does CG that has not converged in 30 steps.
        Measured on the canonical mesh, one CPU thread: ~0.09 s on the CG path, ~0.6 s direct.
        """
        n_faces = self.num_faces
        tree = self.tree_frames(q)
        c = tree[self.zeta] @ q @ tree[self.tau].transpose(0, 2, 1)
        matrix, rhs = self.system(c)
        rows = None
        if np.abs(c - np.eye(3)).max() < _CG_MAX_DEVIATION:

            def precondition(r: np.ndarray) -> np.ndarray:
                return self.face_laplacian.solve(r.reshape(n_faces - 1, 9)).reshape(-1, 3)

            rows = _block_pcg(matrix, rhs, np.tile(np.eye(3), (n_faces - 1, 1)), precondition)
        if rows is None:
            rows = cholesky(matrix)(rhs)
        frames = np.empty((n_faces, 3, 3))
        frames[0] = np.eye(3)
        frames[1:] = _closest_rotations(rows.reshape(n_faces - 1, 3, 3).transpose(0, 2, 1) @ tree[1:])
        return frames


@dataclass(frozen=True)
class _VertexSolver:
    """Per-(topology, anchor) data of the vertex solve: the half-edge incidence and its
    factorised Laplacian without the anchor's row and column."""

    incidence_t: sp.csr_matrix  # (V, 3F): transpose of the half-edge incidence (head +1, tail -1)
    laplacian: spla.SuperLU
    anchor: int

    def solve(self, face_edges: np.ndarray) -> np.ndarray:
        """Least-squares vertices (V, 3) from world edge vectors (3F, 3), anchor at the origin."""
        rhs = self.incidence_t @ face_edges
        keep = np.arange(rhs.shape[0]) != self.anchor
        out = np.zeros_like(rhs)
        out[keep] = self.laplacian.solve(np.ascontiguousarray(rhs[keep]))
        return out


# Solvers per topology (weak keys: an entry lives as long as its topology object).
_FRAME_SOLVERS: weakref.WeakKeyDictionary[EdgeTopology, _FrameSolver] = weakref.WeakKeyDictionary()
_VERTEX_SOLVERS: weakref.WeakKeyDictionary[EdgeTopology, dict[int, _VertexSolver]] = weakref.WeakKeyDictionary()


def _vertex_solver(topo: EdgeTopology, anchor: int) -> _VertexSolver:
    per_anchor = _VERTEX_SOLVERS.setdefault(topo, {})
    if anchor not in per_anchor:
        faces = topo.faces.cpu().numpy()
        n_half = 3 * faces.shape[0]
        heads_tails = np.stack([np.roll(faces, -1, 1), faces], -1).ravel()
        incidence = sp.csr_matrix(
            (np.tile([1.0, -1.0], n_half), (np.repeat(np.arange(n_half), 2), heads_tails)),
            shape=(n_half, topo.num_vertices),
        )
        lap = (incidence.T @ incidence).tocsr()
        n_parts, _ = csgraph.connected_components(lap, directed=False)
        if n_parts != 1:
            raise ValueError(
                f"topo: expected one connected mesh using every vertex, found {n_parts} vertex components "
                f"(an unused vertex is a component of its own)"
            )
        keep = np.arange(topo.num_vertices) != anchor
        per_anchor[anchor] = _VertexSolver(incidence.T.tocsr(), _splu(lap[keep][:, keep]), anchor)
    return per_anchor[anchor]


def _frame_solver(topo: EdgeTopology) -> _FrameSolver:
    if topo not in _FRAME_SOLVERS:
        _FRAME_SOLVERS[topo] = _build_frame_solver(topo)
    return _FRAME_SOLVERS[topo]


def _build_frame_solver(topo: EdgeTopology) -> _FrameSolver:
    ef = topo.edge_faces.cpu().numpy()
    n_faces = topo.num_faces
    adjacency = sp.coo_matrix((np.ones(len(ef)), (ef[:, 0], ef[:, 1])), shape=(n_faces, n_faces))
    adjacency = (adjacency + adjacency.T).tocsr()
    order, parent = csgraph.breadth_first_order(adjacency, 0, directed=False, return_predecessors=True)
    if len(order) != n_faces:
        raise ValueError(
            f"topo: expected faces connected through edges, found {n_faces - len(order)} faces unreachable "
            f"from face 0 (surfaces that touch only at vertices)"
        )
    parent[0] = 0
    face_edges = topo.face_edges.cpu().numpy()
    faces_of = ef[face_edges]  # (F, 3, 2): ζ and τ of each of the face's edges
    own = np.arange(n_faces)[:, None]
    other = np.where(faces_of[..., 0] == own, faces_of[..., 1], faces_of[..., 0])
    parent_edge = face_edges[np.arange(n_faces), np.argmax(other == parent[:, None], axis=1)]
    laplacian = sp.diags(np.asarray(adjacency.sum(1)).ravel()) - adjacency
    return _FrameSolver(
        ef[:, 0].copy(),
        ef[:, 1].copy(),
        parent,
        parent_edge,
        ef[parent_edge, 1] == np.arange(n_faces),
        _splu(laplacian[1:][:, 1:]),
        *_frame_pattern(ef[:, 0], ef[:, 1], n_faces),
    )


def _frame_pattern(zeta: np.ndarray, tau: np.ndarray, n_faces: int) -> tuple[np.ndarray, ...]:
    """Sparsity pattern of the normal matrix: COO entries of blocks (τ,τ), (ζ,ζ), (τ,ζ), (ζ,τ) per
    edge (the order of :meth:`_FrameSolver.system`), mapped to CSR slots of the free block and to
    right-hand-side slots."""
    shape = (len(zeta), 3, 3)
    blocks = [(tau, tau), (zeta, zeta), (tau, zeta), (zeta, tau)]
    rows = np.concatenate(
        [np.broadcast_to(3 * r[:, None, None] + np.arange(3)[:, None], shape).ravel() for r, _ in blocks]
    )
    cols = np.concatenate([np.broadcast_to(3 * c[:, None, None] + np.arange(3), shape).ravel() for _, c in blocks])
    n = 3 * n_faces - 3
    free_mask = (rows >= 3) & (cols >= 3)
    keys, free_slot = np.unique((rows[free_mask] - 3) * n + (cols[free_mask] - 3), return_inverse=True)
    indptr = np.concatenate([[0], np.cumsum(np.bincount(keys // n, minlength=n))])
    rhs_mask = (rows >= 3) & (cols < 3)
    rhs_slot = (rows[rhs_mask] - 3) * 3 + cols[rhs_mask]
    return free_mask, free_slot.ravel(), (keys % n).astype(np.int32), indptr.astype(np.int32), rhs_mask, rhs_slot


def _closest_rotations(m: np.ndarray) -> np.ndarray:
    """Closest rotation (det +1) of each (N, 3, 3) matrix: :func:`unibody.geometry.procrustes.polar`."""
    return polar(torch.from_numpy(m)).numpy()


def _block_pcg(
    matrix: sp.csr_matrix, rhs: np.ndarray, guess: np.ndarray, precondition: Callable[[np.ndarray], np.ndarray]
) -> np.ndarray | None:
    """Preconditioned CG on the columns of ``rhs`` in lockstep; ``None`` if not converged.

    Stops when the preconditioned residual (an estimate of the error, the preconditioner being
    close to the inverse) is below ``_CG_TOL`` in every entry.
    """
    tol = _CG_TOL
    x = guess.copy()
    r = rhs - matrix @ x
    z = precondition(r)
    p = z.copy()
    rz = np.einsum("ij,ij->j", r, z)
    for _ in range(_CG_MAX_ITER):
        if np.abs(z).max() < tol:
            return x
        mp = matrix @ p
        curvature = np.einsum("ij,ij->j", p, mp)
        alpha = np.divide(rz, curvature, out=np.zeros_like(rz), where=curvature > 0)
        x += alpha * p
        r -= alpha * mp
        z = precondition(r)
        rz_new = np.einsum("ij,ij->j", r, z)
        beta = np.divide(rz_new, rz, out=np.zeros_like(rz), where=rz > 0)
        rz = rz_new
        p = z + beta * p
    return x if np.abs(z).max() < tol else None


def _local_face_edges(face_lengths: np.ndarray) -> np.ndarray:
    """In-plane coordinates (F, 3, 2) of each face's edges (v0v1, v1v2, v2v0) in its own frame."""
    l01, l12, l20 = face_lengths[:, 0], face_lengths[:, 1], face_lengths[:, 2]
    x = (l01 * l01 + l20 * l20 - l12 * l12) / (2 * l01)
    y = np.sqrt(np.clip(l20 * l20 - x * x, 0, None))
    zero = np.zeros_like(x)
    return np.stack([np.stack([l01, zero], -1), np.stack([x - l01, y], -1), np.stack([-x, -y], -1)], 1)


def _align(x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """``x`` (V, 3) moved by the rotation and translation that best fit it to ``y``."""
    cx, cy = x.mean(0), y.mean(0)
    rot = kabsch(torch.from_numpy(x - cx), torch.from_numpy(y - cy)).numpy()
    return (x - cx) @ rot.T + cy


def _reconstruct_identity_gauge(
    lengths: torch.Tensor, angles: torch.Tensor, topo: EdgeTopology, anchor_vertex: int
) -> np.ndarray:
    """(B, V, 3) float64 meshes with face 0's frame = I and the anchor at the origin."""
    vertex_solver, frame_solver = _vertex_solver(topo, anchor_vertex), _frame_solver(topo)
    lengths64 = lengths.detach().to("cpu", torch.float64)
    q = connection_maps(lengths64, angles.detach().to("cpu", torch.float64), topo).numpy()
    face_lengths = lengths64[:, topo.face_edges.cpu()].numpy().reshape(-1, 3)
    local = _local_face_edges(face_lengths).reshape(lengths.shape[0], topo.num_faces, 3, 2)
    out = np.empty((lengths.shape[0], topo.num_vertices, 3))
    for b in range(lengths.shape[0]):
        frames = frame_solver.solve(q[b])
        world = np.einsum("fcp,fkp->fkc", frames[:, :, :2], local[b])  # u, v columns times (x, y)
        out[b] = vertex_solver.solve(world.reshape(-1, 3))
    return out


def _check_anchor(anchor_vertex: int, topo: EdgeTopology) -> None:
    if not isinstance(anchor_vertex, int) or not 0 <= anchor_vertex < topo.num_vertices:
        raise ValueError(f"anchor_vertex: expected an int in [0, {topo.num_vertices}), got {anchor_vertex!r}")


def _check_reference(reference: torch.Tensor, batch: int, topo: EdgeTopology) -> np.ndarray:
    check_tensor(reference, "reference")
    specs = dict.fromkeys([f"1 {topo.num_vertices} 3", f"{batch} {topo.num_vertices} 3"])
    check_shape(reference, *specs, name="reference")
    check_finite(reference, "reference")
    return np.broadcast_to(reference.detach().to("cpu", torch.float64).numpy(), (batch, topo.num_vertices, 3))


def reconstruct(
    lengths: torch.Tensor,
    angles: torch.Tensor,
    topo: EdgeTopology,
    *,
    anchor_vertex: int = 0,
    reference: torch.Tensor | None = None,
) -> torch.Tensor:
    """Meshes from edge lengths and signed bending angles (``g`` of paper 004, App. A).

    Args:
        lengths: (B, E) edge lengths, metres.
        angles: (B, E) signed bending angles, radians (convention of :mod:`unibody.panoman.rla`).
        topo: the mesh's edge tables (one connected, closed, oriented mesh using every vertex).
        anchor_vertex: the vertex held fixed in the vertex solve.
        reference: optional (B, V, 3) or (1, V, 3) meshes, metres, to align the result to rigidly.

    Returns:
        (B, V, 3) vertices, metres, dtype and device of ``lengths``. Without ``reference`` face 0's
        frame is the identity (its first edge along +x, its normal along +z) and the anchor
        vertex is at the origin; with it, the Kabsch fit over all vertices places the result.
        Not differentiable (SciPy solve).

    Raises:
        ValueError: wrong shapes, non-finite values, non-positive lengths, a bad anchor or a
            topology that is not one connected component.
        TypeError: non-floating inputs or a dtype/device mismatch between lengths and angles.
    """
    _check_lengths_angles(lengths, angles, topo)
    _check_anchor(anchor_vertex, topo)
    ref = None if reference is None else _check_reference(reference, lengths.shape[0], topo)
    out = _reconstruct_identity_gauge(lengths, angles, topo, anchor_vertex)
    if ref is not None:
        out = np.stack([_align(o, r) for o, r in zip(out, ref, strict=True)])
    return torch.from_numpy(out).to(device=lengths.device, dtype=lengths.dtype)


def reconstruct_rla(
    rl: torch.Tensor,
    ra: torch.Tensor,
    rest: torch.Tensor,
    topo: EdgeTopology,
    *,
    anchor_vertex: int = 0,
    reference: torch.Tensor | None = None,
) -> torch.Tensor:
    """Meshes from RL/RA vectors and their rest meshes: eq. 1 inverted, then :func:`reconstruct`.

    Args:
        rl: (B, E) relative edge lengths.
        ra: (B, E) relative signed bending angles, radians.
        rest: (B, V, 3) or (1, V, 3) rest meshes, metres, whose own lengths and angles are used.
        topo: the mesh's edge tables.
        anchor_vertex: the vertex held fixed in the vertex solve.
        reference: optional (B, V, 3) or (1, V, 3) meshes to align the result to rigidly.

    Returns:
        (B, V, 3) vertices, metres, dtype and device of ``rl``. Without ``reference``, face 0's
        frame and the anchor vertex's position are those of ``rest``.

    Raises:
        ValueError: wrong shapes or non-finite values (see :func:`reconstruct`).
        TypeError: dtype or device mismatches.
    """
    sizes = {"E": topo.num_edges, "V": topo.num_vertices}
    check_shape(rl, "B E", name="rl", sizes=sizes)
    check_shape(ra, "B E", name="ra", sizes=sizes)
    check_shape(rest, "1 V 3", "B V 3", name="rest", sizes=sizes)
    for x, name in ((rl, "rl"), (ra, "ra")):
        if x.dtype != rest.dtype or x.device != rest.device:
            raise TypeError(
                f"{name}: is {str(x.dtype).removeprefix('torch.')} on {x.device} but rest is "
                f"{str(rest.dtype).removeprefix('torch.')} on {rest.device}; convert one of them"
            )
    _check_anchor(anchor_vertex, topo)
    lengths, angles = rla_to_lengths_angles(rl, ra, edge_lengths(rest, topo), dihedral_angles(rest, topo))
    if reference is not None:
        return reconstruct(lengths, angles, topo, anchor_vertex=anchor_vertex, reference=reference)
    _check_lengths_angles(lengths, angles, topo)
    out = torch.from_numpy(_reconstruct_identity_gauge(lengths, angles, topo, anchor_vertex))
    rest64 = rest.detach().to("cpu", torch.float64)
    frame0 = face_frames(rest64, topo)[:, 0]  # (1 or B, 3, 3): face 0's rest frame
    out = out @ frame0.transpose(-1, -2) + rest64[:, anchor_vertex, None]
    return out.to(device=rl.device, dtype=rl.dtype)
