"""The teacher of the pose correctives: an elastic (as-rigid-as-possible) relaxation of the LBS
mesh around the joints, volume kept, self-contact resolved.

Plain LBS shears and collapses the surface where the skinning weights blend two bones (the
inside of a bent elbow or knee, a raised shoulder, a twisted forearm), and lets a bent limb sink
into itself. The teacher keeps LBS where one bone dominates and relaxes the joint regions
(:func:`teacher_region`) toward the rest shape's local geometry: the spokes-and-rims
as-rigid-as-possible energy (:class:`Arap`) with the LBS result as start and as boundary, flesh
that one bone carries tied to that bone (:func:`bone_anchors`) except where it is pressed into
another part, each limb segment held at its rest volume (a linearised constraint in every global
step), then the free vertices found inside the body pulled back out (:class:`Contact`). It is measured against
LBS by :mod:`.metrics` (``benchmarks/correctives.py``).
"""

from __future__ import annotations

import numpy as np
import torch

__all__ = ["Arap", "Contact", "bone_anchors", "teacher_region"]


def _memberships(rest: np.ndarray, faces: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Spokes-and-rims cells: (M, 2) edges, (M,) cell vertex, (M,) weights.

    Every half of a face's edge (opposite corner o) carries the cotangent weight ``cot(o) / 2``
    into three cells: those of its two ends (spokes) and that of o (a rim, which resists bending).
    """
    edges, cells, vals = [], [], []
    for k in range(3):
        i, j, o = faces[:, k], faces[:, (k + 1) % 3], faces[:, (k + 2) % 3]
        u, v = rest[i] - rest[o], rest[j] - rest[o]
        cot = (u * v).sum(1) / np.maximum(np.linalg.norm(np.cross(u, v), axis=1), 1e-12)
        for c in (i, j, o):
            edges.append(np.stack([i, j], 1))
            cells.append(c)
            vals.append(0.5 * cot)
    w = np.concatenate(vals)
    # Obtuse corners give negative weights, which break the energy's convexity; a floor keeps the
    # Laplacian positive definite at a negligible bias (the canonical mesh is near-Delaunay).
    return np.concatenate(edges), np.concatenate(cells), np.maximum(w, 0.05 * np.median(w))


class Arap:
    """As-rigid-as-possible relaxation of a region of a posed mesh.

    The energy ``sum_c sum_(a,b) in cell c  w_ab |(x_a - x_b) - R_c (x0_a - x0_b)|^2`` over the
    spokes-and-rims cells of Chao et al. 2010 ("A simple geometric model for elastic
    deformations": vertex c's cell holds its spokes and the rims of its faces, so bending costs
    energy too; Sorkine & Alexa 2007 use the spokes only) with cotangent weights of the rest mesh
    x0 and one rotation per cell, is minimised over the ``free`` vertices with the others held
    where they are, by alternating its two exact block minimisations: per-cell rotations (polar
    factor of the cell's edge covariance) and one sparse Cholesky solve of the Laplacian system.

    Args:
        rest: (V, 3) the identity's rest mesh (float64 numpy).
        faces: (F, 3) int faces.
        free: (V,) bool, the vertices to relax (the joint regions).
        iterations: local/global rounds.
        volumes: per limb segment, (Fs, 3) faces whose cone volume each global step keeps.
        anchor: (V,) >= 0, each vertex's tie to where it starts (its skinned position), in units
            of the mean Laplacian diagonal: flesh held by one bone stays on that bone.
    """

    def __init__(
        self,
        rest: np.ndarray,
        faces: np.ndarray,
        free: np.ndarray,
        *,
        iterations: int = 8,
        volumes: tuple[np.ndarray, ...] = (),
        anchor: np.ndarray | None = None,
    ) -> None:
        import scipy.sparse as sp

        v = len(rest)
        e, c, w = _memberships(rest, faces)
        touch = free[e].any(1)
        cells = np.unique(c[touch])
        keep = np.isin(c, cells)  # every membership of a cell the free vertices depend on
        self.edges, self.w = e[keep], w[keep]
        self.cells, self.cell = cells, np.searchsorted(cells, c[keep])
        i, j = self.edges.T
        lap = sp.coo_matrix((np.r_[-self.w, -self.w], (np.r_[i, j], np.r_[j, i])), shape=(v, v)).tocsr()
        lap = lap - sp.diags(np.asarray(lap.sum(1)).ravel())
        self.free, self.fixed = np.flatnonzero(free), np.flatnonzero(~free)
        self._lap = a = lap[self.free][:, self.free].tocsr()
        self._scale = float(np.abs(a.diagonal()).mean())  # the unit of the anchors' and contacts' pulls
        self._anchor = None
        if anchor is not None and np.any(anchor[self.free] > 0):
            self._anchor = np.asarray(anchor, dtype=np.float64)[self.free] * self._scale
            a = (a + sp.diags(self._anchor)).tocsr()
        self._a = a
        self.l_fh = lap[self.free][:, self.fixed].tocsr()
        self._solver = _factor(a)
        self.e0 = rest[i] - rest[j]  # (M, 3)
        self.iterations, self.num_vertices = iterations, v
        self.volumes = tuple(np.asarray(f, dtype=np.int64) for f in volumes)
        self._slot = np.full(v, -1)
        self._slot[self.free] = np.arange(len(self.free))
        if self.volumes:  # all segments' faces at once; where each corner's gradient lands in (S nf)
            self._vol_faces = torch.from_numpy(np.concatenate(self.volumes))
            self._vol_seg = torch.from_numpy(np.repeat(np.arange(len(self.volumes)), [len(f) for f in self.volumes]))
            slots = torch.from_numpy(self._slot)[self._vol_faces]
            self._vol_scatter = [
                (slots[:, i] >= 0, (self._vol_seg * len(self.free) + slots[:, i])[slots[:, i] >= 0]) for i in range(3)
            ]

    def _volume_step(
        self,
        x: torch.Tensor,
        y: np.ndarray,
        apex: torch.Tensor,
        target: torch.Tensor,
        *,
        solver,  # noqa: ANN001
    ) -> np.ndarray:
        """The global step's solution ``y`` (nf, 3B) moved to meet every volume constraint, linearised at x.

        Volume ``V_s(x) = sum_f (a - c).((b - c) x (d - c)) / 6`` (c the apex) has gradient
        ``g_s`` on the free vertices; the solution of the constrained quadratic is
        ``y + A^-1 G mu`` with ``(G^T A^-1 G) mu = target - V(x) - G^T (y - x)`` (one small
        S x S system per pose, 3 S extra right-hand sides of the factored Laplacian).
        """
        b, nf, s = x.shape[0], len(self.free), len(self.volumes)
        f, seg = self._vol_faces, self._vol_seg
        p = [x[:, f[:, i]] - apex[:, seg] for i in range(3)]  # (B, F, 3) each, every segment's faces
        vol = x.new_zeros(b, s).index_add_(1, seg, (p[0] * torch.linalg.cross(p[1], p[2], dim=-1)).sum(-1) / 6)
        g = x.new_zeros(b, s * nf, 3)
        for i, (keep, at) in enumerate(self._vol_scatter):  # dV/dx of corner i: (next - c) x (last - c) / 6
            g.index_add_(1, at, torch.linalg.cross(p[(i + 1) % 3][:, keep], p[(i + 2) % 3][:, keep], dim=-1) / 6)
        g = g.view(b, s, nf, 3)
        rhs = np.ascontiguousarray(g.permute(2, 0, 1, 3).reshape(nf, 3 * b * s).numpy())
        z = np.zeros_like(rhs)
        solver.solve(rhs, z)
        z = torch.from_numpy(z).reshape(nf, b, s, 3).permute(1, 2, 0, 3)  # (B, S, nf, 3) = A^-1 g
        yb = torch.from_numpy(y).reshape(nf, b, 3).permute(1, 0, 2)  # (B, nf, 3)
        xf = x[:, self.free]
        k_mat = torch.einsum("bsvc,btvc->bst", g, z)
        r = target - vol - torch.einsum("bsvc,bvc->bs", g, yb - xf)
        ridge = 1e-9 * k_mat.diagonal(dim1=-2, dim2=-1).abs().amax(-1, keepdim=True).clamp_min(1e-30)
        mu = torch.linalg.solve(k_mat + torch.diag_embed(ridge.expand(-1, s)), r)
        yb = yb + torch.einsum("bs,bsvc->bvc", mu, z)
        return yb.permute(1, 0, 2).reshape(nf, 3 * b).numpy()

    def __call__(
        self,
        posed: np.ndarray,
        apex: np.ndarray | None = None,
        target: np.ndarray | None = None,
        contact: Contact | None = None,
    ) -> np.ndarray:
        """Relax (B, V, 3) posed meshes (float64 numpy); the fixed vertices are returned unchanged.

        With ``volumes`` (the constructor's), ``apex`` (B, S, 3) and ``target`` (S,) or (B, S):
        every global step also keeps each volume at its target (the cone volume from the apex
        to the faces), linearised at the current mesh. With ``contact``, each mesh is then
        relaxed again with its penetrating free vertices pulled out (:class:`Contact`).
        """
        x = torch.from_numpy(np.array(posed, dtype=np.float64, copy=True))
        vol = None
        if self.volumes and apex is not None:
            apex_t = torch.as_tensor(apex, dtype=torch.float64)
            vol = (apex_t, torch.as_tensor(target, dtype=torch.float64).expand(x.shape[0], len(self.volumes)))
        if self._anchor is not None and contact is not None:  # each mesh its own anchors: one at a time
            for b in range(x.shape[0]):
                self._relax_one(x[b : b + 1], None if vol is None else (vol[0][b : b + 1], vol[1][b : b + 1]), contact)
            return x.numpy()
        tie = None if self._anchor is None else self._anchor[:, None] * self._columns(x)
        for _ in range(self.iterations):
            self._round(x, self._solver, vol, tie=tie)
        if contact is not None:
            for b in range(x.shape[0]):
                one = None if vol is None else (vol[0][b : b + 1], vol[1][b : b + 1])
                self._resolve_contacts(x[b : b + 1], one, contact)
        return x.numpy()

    def _columns(self, x: torch.Tensor) -> np.ndarray:
        """(nf, 3B) the free vertices of meshes x (B, V, 3), the layout of the global step."""
        return x[:, self.free].permute(1, 0, 2).reshape(len(self.free), 3 * x.shape[0]).numpy()

    def _released(self, ids: np.ndarray, contact: Contact) -> np.ndarray:
        """(nf,) the anchors with those within ``contact.release`` rings of vertices ``ids`` dropped."""
        near = np.zeros(self.num_vertices, bool)
        near[ids] = True
        return self._anchor * ~_grow(near, self.edges, contact.release)[self.free]

    def _relax_one(self, x: torch.Tensor, vol, contact: Contact) -> None:  # noqa: ANN001
        """Relax one mesh (1, V, 3) in place, anchored, where flesh pressed into another part at the
        start (and around it) is free to leave its bone; then its contacts resolved."""
        import scipy.sparse as sp

        start = self._columns(x)
        inside = np.fromiter(contact.targets(x[0].numpy(), self.free), dtype=np.int64)
        anchor = self._released(inside, contact) if len(inside) else self._anchor
        solver = _factor((self._lap + sp.diags(anchor)).tocsr()) if len(inside) else self._solver
        for _ in range(self.iterations):
            self._round(x, solver, vol, tie=anchor[:, None] * start)
        self._resolve_contacts(x, vol, contact, (start, inside))

    def _round(self, x: torch.Tensor, solver, vol, pull=None, tie=None) -> None:  # noqa: ANN001
        """One local/global round on (B, V, 3) meshes x, in place; ``pull``: (slots, (n, 3) targets,
        weight) of free vertices drawn to targets (B = 1; ``solver`` factors the pulled system);
        ``tie``: (nf, 3B) the anchors' pull toward the start (the factored matrix holds the anchors)."""
        b, v = x.shape[:2]
        i, j = (torch.from_numpy(t) for t in self.edges.T)
        cell = torch.from_numpy(self.cell)
        w, e0 = torch.from_numpy(self.w), torch.from_numpy(self.e0)
        nf, nc = len(self.free), len(self.cells)
        e = x[:, i] - x[:, j]  # (B, M, 3)
        cov = (w[:, None, None] * e0[:, :, None]) * e[:, :, None, :]
        s = x.new_zeros(b, nc, 3, 3).index_add_(1, cell, cov)
        u, _, vh = torch.linalg.svd(s)
        d = torch.sign(torch.linalg.det(vh.transpose(-1, -2) @ u.transpose(-1, -2)))
        vh = torch.cat([vh[..., :2, :], vh[..., 2:, :] * d[..., None, None]], -2)
        rot = vh.transpose(-1, -2) @ u.transpose(-1, -2)  # R_c maps rest edges to posed ones
        rhs_e = w[:, None] * (rot[:, cell] @ e0[..., None]).squeeze(-1)  # (B, M, 3)
        rhs = x.new_zeros(b, v, 3).index_add_(1, i, rhs_e).index_add_(1, j, -rhs_e)
        rhs_f = rhs[:, self.free].permute(1, 0, 2).reshape(nf, 3 * b).numpy()
        fixed = x[:, self.fixed].permute(1, 0, 2).reshape(len(self.fixed), 3 * b).numpy()
        rhs_f = np.ascontiguousarray(rhs_f - self.l_fh @ fixed)
        if tie is not None:
            rhs_f += tie
        if pull is not None:
            rhs_f[pull[0]] += pull[2] * pull[1]
        out = np.zeros_like(rhs_f)
        solver.solve(rhs_f, out)
        if vol is not None:
            out = self._volume_step(x, out, *vol, solver=solver)
        x[:, self.free] = torch.from_numpy(out).reshape(nf, b, 3).permute(1, 0, 2)

    def _resolve_contacts(self, x: torch.Tensor, vol, contact: Contact, anchored=None) -> None:  # noqa: ANN001
        """Relax one mesh (1, V, 3) again, in place, with its penetrating free vertices pulled out
        (each round adds the newly found ones; every pull stays to the end). ``anchored``: (the
        start's :meth:`_columns`, ids of the vertices found inside at the start) when anchored."""
        import scipy.sparse as sp

        pulls: dict[int, np.ndarray] = {}
        weight = contact.weight * self._scale
        for _ in range(contact.rounds):
            found = contact.targets(x[0].numpy(), self.free)
            if not found:
                break
            pulls.update(found)
            ids = np.fromiter(pulls, dtype=np.int64)
            slots = self._slot[ids]
            targets = np.stack(list(pulls.values()))
            a, tie = self._a, None
            if anchored is not None:  # every vertex found inside so far, and the rings around it, leaves its bone
                anchor = self._released(np.r_[anchored[1], ids], contact)
                a, tie = self._lap + sp.diags(anchor), anchor[:, None] * anchored[0]
            solver = _factor((a + sp.diags(np.bincount(slots, minlength=len(self.free)) * weight)).tocsr())
            for _ in range(contact.iterations):
                self._round(x, solver, vol, (slots, targets, weight), tie)


def _factor(a):  # noqa: ANN001, ANN202 (a scipy CSR matrix -> a cholespy solver)
    """A sparse Cholesky factorisation of a symmetric positive definite CSR matrix."""
    from cholespy import CholeskySolverD, MatrixType

    return CholeskySolverD(a.shape[0], a.indptr.astype(np.int32), a.indices.astype(np.int32), a.data, MatrixType.CSR)


RELEASE = 8
"""Rings around the vertices in contact whose tie to their bone (:func:`bone_anchors`) the contact rounds drop."""


class Contact:
    """Self-contact of the teacher: free vertices inside the body are pulled back out.

    A vertex is inside the body when a point ``offset`` outside it along its normal has a
    winding number >= 1/2 (libigl's fast winding number of the whole posed mesh): outside its
    own surface, yet inside another part. Its depth is its distance to the closest surface of
    the parts other than its own (``labels``: each vertex's dominant joint); its target lies
    back along its own normal by half the depth when that surface can move too (both sides of
    a contact meet in the middle), by all of it when it is held (a fixed vertex of the trunk,
    say), plus ``margin``. The pull is soft: the elastic energy and the volumes still hold.

    Args:
        faces: (F, 3) int64; labels: (V,) int part of each vertex (its dominant joint);
        rounds: detect-and-relax rounds; iterations: local/global rounds after each;
        weight: the pull, in units of the mean Laplacian diagonal; offset, margin: m;
        release: rings around the vertices found inside whose anchors (:class:`Arap`'s ``anchor``)
            the contact rounds drop: soft tissue pressed together leaves its bone, the rest of the
            limb stays on it.
    """

    def __init__(
        self,
        faces: np.ndarray,
        labels: np.ndarray,
        *,
        rounds: int = 3,
        iterations: int = 4,
        weight: float = 1.0,
        offset: float = 1e-3,
        margin: float = 2e-3,
        release: int = RELEASE,
    ) -> None:
        self.faces, self.labels = np.ascontiguousarray(faces, dtype=np.int64), labels
        self.rounds, self.iterations, self.weight, self.offset, self.margin = rounds, iterations, weight, offset, margin
        self.release = release
        self._face_labels = labels[self.faces]

    def targets(self, x: np.ndarray, free: np.ndarray) -> dict[int, np.ndarray]:
        """{vertex id: (3,) target} of the free vertices of mesh x (V, 3) that are inside the body."""
        import igl

        from ..geometry.mesh import vertex_normals

        f = self.faces
        vn = vertex_normals(torch.from_numpy(x), torch.from_numpy(f)).numpy()
        probe = x[free] + self.offset * vn[free]
        inside = free[igl.fast_winding_number(x, f, probe) >= 0.5]
        out: dict[int, np.ndarray] = {}
        is_free = np.zeros(len(x), bool)
        is_free[free] = True
        for part in np.unique(self.labels[inside]):
            ids = inside[self.labels[inside] == part]
            other = f[(self._face_labels != part).all(1)]
            _, fid, c = igl.point_mesh_squared_distance(x[ids], x, other)
            held = ~is_free[other[fid]].any(1)
            depth = np.linalg.norm(c - x[ids], axis=1, keepdims=True)
            step = np.where(held[:, None], 1.0, 0.5)
            # Back along its own normal (not toward the closest point, whose direction jumps from
            # one vertex to the next and crumpled the contact: 2-3x the intersections).
            t = x[ids] - vn[ids] * (step * depth + self.margin)
            out.update(zip(ids.tolist(), t, strict=True))
        return out


STRESSED_JOINTS: tuple[str, ...] = tuple(
    s + j for s in ("Left", "Right") for j in ("Arm", "ForeArm", "Hand", "Leg", "Shin", "Foot")
)
"""Joints whose neighbourhood (with their parents) the teacher relaxes and the metrics measure."""


def bone_anchors(weights: np.ndarray, strength: float, *, onset: float = 0.5) -> np.ndarray:
    """(V,) each vertex's tie to its skinned position: ``strength * r^2``, ``r`` the share of its
    dominant bone's weight above ``onset``, rescaled to [0, 1].

    Flesh that one bone carries stays on that bone; where bones blend (``r`` near 0) the surface
    is free to relax. Without it the relaxation may slide a whole free limb off its bones: held
    only at the trunk and the hand, the upper arm's flesh of an Anny body at the T-pose sagged
    47 mm below its humerus (ARAP pulling the shoulder toward its rest, arms-down shape).

    Args:
        weights: (V, J) dense skinning weights; strength: the tie of a one-bone vertex, in units
            of the mean Laplacian diagonal (:class:`Arap`'s ``anchor``).
    """
    r = np.clip((weights.max(1) - onset) / (1.0 - onset), 0.0, 1.0)
    return strength * r**2


def _grow(mask: np.ndarray, edges: np.ndarray, rings: int) -> np.ndarray:
    for _ in range(rings):
        grow = mask.copy()
        grow[edges[mask[edges[:, 0]], 1]] = True
        grow[edges[mask[edges[:, 1]], 0]] = True
        mask = grow
    return mask


def teacher_region(
    weights: np.ndarray,
    parents: np.ndarray,
    joint_names: tuple[str, ...],
    faces: np.ndarray,
    *,
    rings: int = 2,
    whole_segments: bool = True,
) -> dict[str, np.ndarray]:
    """Per stressed joint: (V,) bool, the vertices skinned by it and its parent (>= 0.05), grown by ``rings``.

    With ``whole_segments``, the wrists and ankles also take the whole forearm or shin (the vertices it dominates): a
    twisted hand or foot turns the segment along its length, which a band at the joint cannot
    relax (LBS's candy wrapper).

    Args:
        weights: (V, J) dense skinning weights; parents: (J,) parent ids; faces: (F, 3).
    """
    e = np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]])
    dominant = weights.argmax(1)
    out = {}
    for name in STRESSED_JOINTS:
        k = joint_names.index(name)
        band = (weights[:, k] >= 0.05) & (weights[:, parents[k]] >= 0.05)
        if whole_segments and name.endswith(("Hand", "Foot")):
            band |= dominant == parents[k]
        out[name] = _grow(band, e, rings)
    return out
