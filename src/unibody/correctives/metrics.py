"""Surface measures that tell a better deformation from plain LBS (issue 40).

All compare a posed mesh with its own rest mesh, on the canonical topology:

* **edge strain** ``|l / l_rest - 1|`` and **dihedral change** ``|wrap(a - a_rest)|`` (PanoMan's
  RL and RA, paper 004 eq. 1: ``a`` the signed bending angle of an edge), over the edges of the
  *joint regions*: vertices skinned both by a stressed joint (shoulders, elbows, wrists, hips,
  knees, ankles) and by its parent, grown by two rings;
* **segment volume**: the volume of the cone from the segment's bone midpoint (carried by the
  segment's joint) to the faces of the segment (every vertex mostly skinned by that joint),
  posed / rest, for the upper arms, forearms, thighs and shins;
* **cross-section** of a limb: the area of the cut of the mesh by a plane normal to the bone
  (oriented cut segments, shoelace), the smallest ratio posed / rest over 21 planes;
* **self-intersections**: triangle pairs that intersect (exact test,
  :func:`unibody.geometry.intersect.intersecting_pairs`), over the faces of the trunk and limbs.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from ..geometry.intersect import intersecting_pairs
from .teacher import STRESSED_JOINTS, teacher_region

__all__ = [
    "STRESSED_JOINTS",
    "SEGMENTS",
    "SurfaceMeasures",
    "cone_volume",
    "cross_section_area",
    "limb_profile",
    "one_bone",
]

SEGMENTS: tuple[tuple[str, str], ...] = tuple(
    (s + a, s + b)
    for s in ("Left", "Right")
    for a, b in (("Arm", "ForeArm"), ("ForeArm", "Hand"), ("Leg", "Shin"), ("Shin", "Foot"))
)
"""(segment joint, its child) of each limb segment whose volume is measured."""


def _edge_tables(faces: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Interior edges (E, 2) of a closed mesh and the opposite vertex of each side (E, 2)."""
    a = faces.reshape(-1)
    b = np.roll(faces, -1, axis=1).reshape(-1)
    c = np.roll(faces, -2, axis=1).reshape(-1)
    key = np.minimum(a, b) * (faces.max() + 1) + np.maximum(a, b)
    order = np.argsort(key, kind="stable")
    key, a, b, c = key[order], a[order], b[order], c[order]
    first = np.flatnonzero(np.r_[True, key[1:] != key[:-1]])
    pair = first[np.diff(np.r_[first, len(key)]) == 2]
    fwd = a[pair] < b[pair]  # the side holding the half-edge i -> j (i < j) is zeta
    i, j = np.minimum(a[pair], b[pair]), np.maximum(a[pair], b[pair])
    zeta = np.where(fwd, c[pair], c[pair + 1])
    tau = np.where(fwd, c[pair + 1], c[pair])
    return np.stack([i, j], 1), np.stack([zeta, tau], 1)


def cross_section_area(verts: np.ndarray, faces: np.ndarray, origin: np.ndarray, normal: np.ndarray) -> float:
    """Area (m^2) of the cut of a closed triangle mesh by the plane (origin, unit normal)."""
    d = (verts - origin) @ normal
    fd = d[faces]
    cut = (fd.min(1) < 0) & (fd.max(1) > 0)
    f, fd = faces[cut], fd[cut]
    pts = []
    for a, b in ((0, 1), (1, 2), (2, 0)):
        da, db = fd[:, a], fd[:, b]
        s = np.where((da < 0) != (db < 0), da / np.where(da == db, 1, da - db), np.nan)
        pts.append(verts[f[:, a]] + s[:, None] * (verts[f[:, b]] - verts[f[:, a]]))
    pts = np.stack(pts, 1)  # (F, 3 edges, 3): exactly two edges of a cut face cross
    p = pts[~np.isnan(pts[..., 0])].reshape(-1, 2, 3)
    p, q = p[:, 0] - origin, p[:, 1] - origin
    tri = verts[f]
    n_face = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    flip = (np.cross(normal, q - p) * n_face).sum(1) > 0  # the solid on the segment's left seen from +normal
    p, q = np.where(flip[:, None], q, p), np.where(flip[:, None], p, q)
    return 0.5 * float((np.cross(p, q) @ normal).sum())


def limb_profile(verts: np.ndarray, faces: np.ndarray, a: np.ndarray, b: np.ndarray, ts: np.ndarray) -> np.ndarray:
    """Cross-section areas (m^2) at bone parameters ``ts`` between joint positions a and b."""
    axis = (b - a) / np.linalg.norm(b - a)
    return np.array([cross_section_area(verts, faces, a + t * (b - a), axis) for t in ts])


def one_bone(weights: np.ndarray, joint: int | None = None, *, threshold: float = 0.99) -> np.ndarray:
    """(V,) bool: the vertices one bone carries (a skinning weight >= ``threshold``), or only those
    ``joint`` carries: where correctives should leave the flesh where its bone puts it.

    Args:
        weights: (V, J) dense skinning weights (numpy).
    """
    out = weights.max(1) >= threshold
    return out if joint is None else out & (weights.argmax(1) == joint)


def cone_volume(x: torch.Tensor, faces: torch.Tensor, apex: torch.Tensor) -> torch.Tensor:
    """(B,) signed volume of the cone from ``apex`` (B, 3) to ``faces`` (F, 3) of meshes x (B, V, 3)."""
    a, b, c = (x[:, faces[:, i]] - apex[:, None] for i in range(3))
    return (a * torch.linalg.cross(b, c, dim=-1)).sum((-1, -2)) / 6


@dataclass(frozen=True)
class SurfaceMeasures:
    """The measures' index tables for one rig (build with :meth:`from_layer`).

    Attributes:
        faces: (F, 3) int64 canonical faces.
        edges, opposite: (E, 2) interior edges and their opposite vertices.
        region_edges: (Er,) ids of the edges inside the joint regions.
        region_vertices: (V,) bool, the joint regions.
        segment_faces: per :data:`SEGMENTS` entry, (Fs, 3) faces of the segment.
        segment_joints: per entry, (segment joint id, child joint id).
        body_faces: (Fb,) ids of the faces tested for self-intersection (trunk and limbs).
        weights: (V, J) dense skinning weights (float64).
        joint_names: the rig's joint names.
    """

    faces: np.ndarray
    edges: np.ndarray
    opposite: np.ndarray
    region_edges: np.ndarray
    region_vertices: np.ndarray
    segment_faces: tuple[np.ndarray, ...]
    segment_joints: tuple[tuple[int, int], ...]
    body_faces: np.ndarray
    weights: np.ndarray
    joint_names: tuple[str, ...]

    @classmethod
    def from_layer(cls, layer) -> SurfaceMeasures:  # noqa: ANN001 (a BodyLayer; no import cycle)
        """Tables from a :class:`~unibody.body.BodyLayer`'s faces, skinning and joint names."""
        faces = layer.faces.cpu().numpy().astype(np.int64)
        names = tuple(layer.joint_names)
        w = layer.skinning.dense().detach().cpu().double().numpy()
        parents = layer.parents.cpu().numpy()
        edges, opposite = _edge_tables(faces)
        region = np.any(list(teacher_region(w, parents, names, faces, rings=2, whole_segments=False).values()), axis=0)
        region_edges = np.flatnonzero(region[edges].all(1))
        dominant = w.argmax(1)
        seg_faces, seg_joints = [], []
        for joint, child in SEGMENTS:
            k = names.index(joint)
            seg_faces.append(faces[(dominant[faces] == k).all(1)])
            seg_joints.append((k, names.index(child)))
        excluded = [
            i for i, n in enumerate(names) if any(p in n for p in ("Hand", "Foot", "Toe", "Head", "Neck", "Eye", "Jaw"))
        ]
        body_faces = np.flatnonzero(~np.isin(dominant[faces], excluded).any(1))
        return cls(
            faces, edges, opposite, region_edges, region, tuple(seg_faces), tuple(seg_joints), body_faces, w, names
        )

    def _bending(self, v: torch.Tensor) -> torch.Tensor:
        e, o = torch.from_numpy(self.edges), torch.from_numpy(self.opposite)
        xi, xj = v[:, e[:, 0]], v[:, e[:, 1]]
        d = xj - xi
        n1 = torch.linalg.cross(d, v[:, o[:, 0]] - xi, dim=-1)
        n2 = torch.linalg.cross(-d, v[:, o[:, 1]] - xj, dim=-1)
        sin = (torch.linalg.cross(n1, n2, dim=-1) * d).sum(-1)
        cos = (n1 * n2).sum(-1) * d.norm(dim=-1)
        return torch.atan2(sin, cos)

    def distortion(self, rest: torch.Tensor, posed: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Edge strain and dihedral change (rad) of the joint-region edges: two (B, Er) tensors.

        Args:
            rest: (B or 1, V, 3) rest meshes; posed: (B, V, 3).
        """
        rest, posed = rest.detach().cpu().double(), posed.detach().cpu().double()
        e = torch.from_numpy(self.edges[self.region_edges])
        length = lambda x: (x[:, e[:, 1]] - x[:, e[:, 0]]).norm(dim=-1)  # noqa: E731
        strain = (length(posed) / length(rest) - 1).abs()
        da = self._bending(posed)[:, self.region_edges] - self._bending(rest)[:, self.region_edges]
        da = torch.remainder(da + torch.pi, 2 * torch.pi) - torch.pi
        return strain, da.abs()

    def segment_volumes(
        self,
        rest: torch.Tensor,
        rest_rotations: torch.Tensor,
        rest_joints: torch.Tensor,
        posed: torch.Tensor,
        world: torch.Tensor,
    ) -> torch.Tensor:
        """(B, S) volume ratios posed / rest of the :data:`SEGMENTS`.

        Args:
            rest: (B or 1, V, 3) m; rest_rotations: (B or 1, J, 3, 3); rest_joints: (B or 1, J, 3) m
                (a :class:`~unibody.body.PreparedIdentity`'s fields); posed: (B, V, 3) m;
            world: (B, J, 4, 4) posed world transforms (``BodyOutput.transforms``).
        """
        rest, posed = rest.detach().cpu().double(), posed.detach().cpu().double()
        apex0, apex = self.segment_apexes(rest_rotations, rest_joints, world)
        out = [
            cone_volume(posed, torch.from_numpy(f), apex[:, k]) / cone_volume(rest, torch.from_numpy(f), apex0[:, k])
            for k, f in enumerate(self.segment_faces)
        ]
        return torch.stack(out, -1)

    def segment_apexes(
        self, rest_rotations: torch.Tensor, rest_joints: torch.Tensor, world: torch.Tensor
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """The segments' cone apexes, float64: ((Bi, S, 3) at rest, (B, S, 3) posed).

        The apex is the bone midpoint at rest, carried rigidly by the segment's joint.
        """
        rr, rj, g = (t.detach().cpu().double() for t in (rest_rotations, rest_joints, world))
        rest_apex, posed_apex = [], []
        for k, c in self.segment_joints:
            apex0 = 0.5 * (rj[:, k] + rj[:, c])  # (Bi, 3)
            local = (rr[:, k].transpose(-1, -2) @ (apex0 - rj[:, k])[..., None]).squeeze(-1)
            rest_apex.append(apex0)
            posed_apex.append((g[:, k, :3, :3] @ local[..., None]).squeeze(-1) + g[:, k, :3, 3])
        return torch.stack(rest_apex, 1), torch.stack(posed_apex, 1)

    def self_intersections(self, posed: torch.Tensor) -> np.ndarray:
        """(B,) number of intersecting triangle pairs among the trunk-and-limb faces."""
        faces = torch.from_numpy(self.faces[self.body_faces])
        return np.array([len(intersecting_pairs(v.detach().cpu().double(), faces)) for v in posed])
