"""A marker layout from one labelled frame (paper 003 §4.5 / App. G): stage 1 of the solve on one frame."""

from __future__ import annotations

from collections.abc import Sequence

import torch

from ._marker_body import MarkerBody
from ._stage1 import Stage1Result, stage1
from .frames import check_points
from .layout import MarkerLayout
from .solve_config import SolveConfig

__all__ = ["derive_layout"]


def derive_layout(
    points: torch.Tensor,
    labels: Sequence[str],
    *,
    name: str,
    config: SolveConfig | None = None,
    initial: MarkerLayout | None = None,
    unlabelled: torch.Tensor | None = None,
    prefix: str = "X",
) -> MarkerLayout:
    """A marker layout from one labelled frame (paper 003 §4.5 / App. G: MoSh on one frame).

    Fits a PCA body, its pose and the latent markers to the frame (stage 1 with one frame and
    the wider ``derive_slide_std``), then takes for each latent marker the nearest canonical
    vertex of the fitted rest body and its signed distance along that vertex's normal.

    With ``unlabelled`` points (a session's markers of another protocol: tracking clusters,
    foot sets), each becomes a new marker ``{prefix}01``, ``{prefix}02``, ...: a first fit to
    the labelled markers places it on the nearest vertex of the posed body, then all markers
    are fitted together. A labeler trained on the result names them instead of confusing
    them with the layout's markers (the paper's one labelled frame per layout variation).

    Args:
        points: (M, 3) m, one frame in unibody's frame (Y up), NaN where missing.
        labels: the M marker labels.
        name: the new layout's name.
        config: weights; default :class:`SolveConfig`.
        initial: the starting placement, a layout holding every label (extra ones are
            ignored); default the shipped ``superset`` layout.
        unlabelled: (K, 3) m, other markers of the same frame (NaN rows are skipped).
        prefix: name prefix of the markers made from ``unlabelled``.

    Returns:
        :class:`MarkerLayout` with the M labels (missing markers keep their initial placement),
        then the new markers.

    Raises:
        TypeError / ValueError: bad points, or labels neither in ``initial`` nor the superset.
    """
    config = SolveConfig() if config is None else config
    labels = tuple(labels)
    check_points(points, "M 3", len(labels))
    if initial is None:
        superset = MarkerLayout.load("superset")
        unknown = [x for x in labels if x not in superset.labels]
        if unknown:
            raise ValueError(f"labels: {unknown} are not in the superset layout; pass initial=MarkerLayout(...)")
        initial = superset.subset(labels)
    elif not isinstance(initial, MarkerLayout):
        raise TypeError(f"initial: expected a MarkerLayout, got {type(initial).__name__}")
    else:
        initial = initial.subset(labels)
    obs = points.detach().to(torch.float64)[None]
    vis = torch.isfinite(obs).all(-1)
    if int(vis.sum()) < 3:
        raise ValueError("points: fewer than 3 visible markers")
    body = MarkerBody(config.shape_components, obs.device)
    anchors = initial.vertices.to(obs.device)
    distance = initial.distance.to(obs)
    slide, surface = config.derive_slide_std, config.derive_surface_std
    s1 = stage1(body, obs, vis, anchors, distance, config, slide_std=slide, surface_std=surface)
    if unlabelled is not None:
        check_points(unlabelled, "K 3", None, name="unlabelled")
        extra = unlabelled.detach().to(obs)
        extra = extra[torch.isfinite(extra).all(-1)]
        if len(extra):
            labels = labels + tuple(f"{prefix}{k + 1:02d}" for k in range(len(extra)))
            if len(set(labels)) != len(labels):
                raise ValueError(f"prefix: {prefix!r} gives names that are already labels")
            anchors, distance = _extend(body, s1, extra, anchors, distance)
            obs = torch.cat([obs, extra[None]], 1)
            vis = torch.isfinite(obs).all(-1)
            s1 = stage1(body, obs, vis, anchors, distance, config, slide_std=slide, surface_std=surface)
    rest = s1.ident.rest
    vertex = torch.cdist(s1.latent, rest[0]).argmin(1)
    signed = ((s1.latent - rest[0, vertex]) * body.normals(rest, vertex)[0]).sum(-1)
    seen = vis[0]
    vertex = torch.where(seen, vertex, anchors)
    signed = torch.where(seen, signed, distance)
    return MarkerLayout(name, labels, vertex.cpu(), signed.float().cpu())


def _extend(body: MarkerBody, s1: Stage1Result, extra, anchors, distance) -> tuple[torch.Tensor, torch.Tensor]:
    """Anchors and distances with those of ``extra`` (K, 3) appended: nearest posed vertex of the stage-1 fit."""
    rest = s1.ident.rest
    every = torch.arange(rest.shape[1], device=rest.device)
    posed, *_ = body.markers(s1.ident, every, rest, s1.local[:1], s1.transl[:1], False)
    vertex = torch.cdist(extra, posed[0]).argmin(1)
    signed = ((extra - posed[0, vertex]) * body.normals(posed, vertex)[0]).sum(-1).clamp(0.0, 0.05)
    return torch.cat([anchors, vertex]), torch.cat([distance, signed])
