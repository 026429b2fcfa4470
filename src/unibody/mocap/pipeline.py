"""Raw marker file -> labelled markers -> solved body: the steps behind ``unibody mocap``.

    seq = read_markers("session.c3d")                       # any labels, or none ('*12')
    model = load_labeler("cmu41")                           # shipped weights, or a path
    labelled = label_sequence(seq, model)                   # MarkerSequence with the model's labels
    checked = label_sequence(seq, model, layout=MarkerLayout.load("cmu41"))  # checked by a body solve
    result = solve_sequence(labelled, MarkerLayout.load("cmu41"))
    session = frame_layout(seq, MarkerLayout.load("pig39"), frame=0, name="session")  # + its extra markers

Labelled output: one column per model label (NaN where the label is absent in a frame),
then the points left unlabelled as ``*0``, ``*1``, ... columns (one per input column that
kept any). With ``tracklets`` each input column (a hardware tracklet) is labelled from the
evidence of its frames, one label per span of it (:func:`~unibody.mocap.tracklets.settle_tracklets`,
paper 003 §4.5), else every frame is labelled on its own. With ``layout`` the labels are then
checked against a body solved from them (:func:`~unibody.mocap.relabel.relabel_tracklets` with
tracklets: the body's labels are more evidence for the spans; :func:`~unibody.mocap.relabel.relabel`
without: each point takes the solved marker it sits on, where that is clear). Copies of a
point within 1 mm (:mod:`unibody.mocap.coincident`) are labelled as their original.

A session whose markers go beyond a shipped layout (tracking clusters, foot sets) gets its own
layout from one labelled frame (:func:`frame_layout`, paper §4.5: one labelled frame per layout
variation); a labeler trained on it (``scripts/train_labeler.py --layout session.json --init
pig39 --orient-with pig39``) names those markers instead of confusing them with the layout's.
"""

from __future__ import annotations

import warnings
from collections.abc import Callable
from dataclasses import dataclass
from importlib import resources
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np
import torch

from .._checks import check_count
from .c3d import MarkerSequence
from .coincident import COINCIDENT_TOL, find_coincident
from .frames import check_marker_units, lab_to_unibody
from .labeler import Labeler, label_frames, sequence_probabilities
from .layout import MarkerLayout
from .tracklets import labelled_markers, settle_tracklets

# Labelling never loads the solver: its modules are imported where a body is solved (the
# functions below that solve, and label_sequence's body check).
if TYPE_CHECKING:
    from .relabel import RelabelConfig
    from .solve import SolveConfig, SolveResult

__all__ = [
    "FAR_RADIUS",
    "MIN_LABELLED",
    "LabelReport",
    "LabelledSequence",
    "available_labelers",
    "frame_layout",
    "label_sequence",
    "load_labeler",
    "main_cluster",
    "render_solution",
    "solve_sequence",
]

FAR_RADIUS = (
    2.0  # m: farther from the frame's main cluster's centre, a point is not labelled (synthetic markers: <= 1.61)
)
MIN_LABELLED = 3  # a frame with fewer labelled points "could not be labelled"


@dataclass(frozen=True)
class LabelReport:
    """What :func:`label_sequence` could not label.

    Attributes:
        frames: T.
        empty: frames without a visible point.
        scattered: frames with points but fewer than ``MIN_LABELLED`` within ``FAR_RADIUS`` of
            the frame's main cluster (nothing to label: points far apart).
        rejected: frames whose ``MIN_LABELLED`` or more near points got fewer than ``MIN_LABELLED``
            marker labels (the labeler took them for ghosts: another marker set, units or body?).
        far_points: points left unlabelled because they lie farther than ``FAR_RADIUS`` from their
            frame's main cluster (reflections, other subjects, absurd values).
        copies: (copy, original) input column names: columns that copy another within
            ``COINCIDENT_TOL`` (:mod:`unibody.mocap.coincident`), merged into their original.
        coincident_points: other points merged into a point of their frame within ``COINCIDENT_TOL``.
    """

    frames: int
    empty: np.ndarray
    scattered: np.ndarray
    rejected: np.ndarray
    far_points: int
    copies: tuple[tuple[str, str], ...] = ()
    coincident_points: int = 0

    @property
    def unlabelled(self) -> np.ndarray:
        """Sorted frames that could not be labelled (any reason)."""
        return np.sort(np.concatenate([self.empty, self.scattered, self.rejected]))

    def summary(self) -> str:
        """One line for the user; empty when every frame got labels and no point was dropped."""
        parts = []
        for frames, why in (
            (self.empty, "without points"),
            (self.scattered, f"with fewer than {MIN_LABELLED} points within {FAR_RADIUS:g} m of each other"),
            (self.rejected, f"where the labeler named fewer than {MIN_LABELLED} points (another marker set?)"),
        ):
            if len(frames):
                first = ", ".join(str(int(f)) for f in frames[:5]) + (", ..." if len(frames) > 5 else "")
                parts.append(f"{len(frames)} {why} (frames {first})")
        line = ""
        if parts:
            line = f"{len(self.unlabelled)} of {self.frames} frames could not be labelled: " + "; ".join(parts)
        if self.far_points:
            far = (
                f"{self.far_points} points farther than {FAR_RADIUS:g} m from their frame's main cluster "
                "were left unlabelled"
            )
            line = f"{line}; {far}" if line else far
        merged = []
        tol = f"{1000 * COINCIDENT_TOL:g} mm"
        if self.copies:
            pairs = ", ".join(f"{c}={o}" for c, o in self.copies)
            merged.append(f"merged {len(self.copies)} columns that copy others within {tol} ({pairs})")
        if self.coincident_points:
            merged.append(f"merged {self.coincident_points} more points that coincide with another within {tol}")
        if merged:
            line = "; ".join([line, *merged]) if line else "; ".join(merged)
        return line


@dataclass(frozen=True)
class LabelledSequence(MarkerSequence):
    """A :class:`MarkerSequence` from :func:`label_sequence`, with its :class:`LabelReport`.

    ``point_labels``: (T, N) int64, each input point's label in [0, L] (the model's label
    order; L = null, also for absent points); a copy (:mod:`unibody.mocap.coincident`) has its
    original's label.
    """

    report: LabelReport | None = None
    point_labels: np.ndarray | None = None


def main_cluster(points: np.ndarray, radius: float = FAR_RADIUS) -> np.ndarray:
    """(T, N) bool: the visible points within ``radius`` of their frame's main cluster's centre.

    The centre is the per-axis median of the frame's visible points, then the median of the
    points within ``radius`` of it. Where that keeps less than half of the frame's points (the
    median fell between groups), the main cluster is the largest group within ``radius`` of one
    point, and the centre its median. Non-finite, absurd (1e27 m) and far points are never kept.

    Args:
        points: (T, N, 3) m, NaN for missing points.
        radius: m.
    """
    pts = np.asarray(points, dtype=np.float64)
    vis = np.isfinite(pts).all(-1)
    keep = np.zeros(vis.shape, dtype=bool)
    any_vis = vis.any(1)
    with np.errstate(over="ignore", invalid="ignore"), warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)  # all-NaN frames' medians
        centre = np.nanmedian(np.where(vis[..., None], pts, np.nan), axis=1)  # (T, 3), NaN for empty frames
        for _ in range(2):
            dist = np.linalg.norm(pts - centre[:, None], axis=-1)
            keep = vis & (dist <= radius)
            ok = keep.any(1)
            centre = np.where(ok[:, None], np.nanmedian(np.where(keep[..., None], pts, np.nan), axis=1), centre)
        keep = vis & (np.linalg.norm(pts - centre[:, None], axis=-1) <= radius)
        for t in np.flatnonzero(any_vis & (2 * keep.sum(1) < vis.sum(1))):
            idx = np.flatnonzero(vis[t])
            p = pts[t, idx]
            d = np.linalg.norm(p[:, None] - p[None], axis=-1)
            seed = int(np.argmax((d <= radius).sum(1)))
            c = np.median(p[d[seed] <= radius], axis=0)
            keep[t] = False
            keep[t, idx] = np.linalg.norm(p - c, axis=-1) <= radius
    return keep


def _weights_dir():
    return resources.files("unibody.mocap") / "data"


def available_labelers() -> tuple[str, ...]:
    """Layouts with shipped labeler weights."""
    names = [p.name for p in _weights_dir().iterdir()]
    return tuple(sorted(n[len("labeler_") : -len(".pt")] for n in names if n.startswith("labeler_")))


def load_labeler(name_or_path: str | Path) -> Labeler:
    """Shipped labeler weights by layout name (``"pig39"``, ``"cmu41"``) or a weights file."""
    p = Path(name_or_path)
    if p.suffix == ".pt" or p.exists():
        return Labeler.load(p)
    res = _weights_dir() / f"labeler_{name_or_path}.pt"
    if not res.is_file():
        raise ValueError(f"labeler: no shipped weights for {str(name_or_path)!r}; shipped: {available_labelers()}")
    with resources.as_file(res) as f:
        return Labeler.load(f)


def _check_inputs(seq: object, model: object = None, layout: object = None) -> None:
    """TypeError naming the argument that is not a MarkerSequence, Labeler or MarkerLayout."""
    if not isinstance(seq, MarkerSequence):
        raise TypeError(f"seq: expected a MarkerSequence (read_markers(path)), got {type(seq).__name__}")
    if model is not None and not isinstance(model, Labeler):
        raise TypeError(f"model: expected a Labeler (load_labeler(name or path)), got {type(model).__name__}")
    if layout is not None and not isinstance(layout, MarkerLayout):
        raise TypeError(f"layout: expected a MarkerLayout (MarkerLayout.load(name)), got {type(layout).__name__}")


def label_sequence(
    seq: MarkerSequence,
    model: Labeler,
    *,
    up: str = "z",
    tracklets: bool = True,
    batch: int = 256,
    layout: MarkerLayout | None = None,
    body_config: RelabelConfig | None = None,
    progress: Callable[[str], None] | None = None,
    body: MarkerLayout | None = None,
) -> LabelledSequence:
    """Label every point of a marker sequence (labels already in the file are ignored).

    Args:
        seq: the input, in its lab frame (``up`` names its vertical axis).
        model: a trained labeler, on any device and in any dtype (the labels come back on the CPU).
        up: "z" or "y", the vertical axis of ``seq``.
        tracklets: whether each input column's spans are labelled from their frames' evidence
            (:func:`~unibody.mocap.tracklets.settle_tracklets`).
        batch: frames per forward pass.
        layout: the layout of the model's markers (the same labels, in order): check the labels
            against a body solved from them (:func:`~unibody.mocap.relabel.relabel`).
        body_config: that check's thresholds.
        progress: called with one-line reports of the check, and with the
            :meth:`LabelReport.summary` when some frame or point could not be labelled.
        body: deprecated name of ``layout`` (it is a marker layout, not a body); warns.

    Returns:
        The labelled sequence; its ``report`` (:class:`LabelReport`) counts the frames that
        could not be labelled and why, and the far points left unlabelled.

    Raises:
        ValueError: ``seq`` is not in metres (:func:`~unibody.mocap.frames.check_marker_units`),
            or ``layout`` does not match the model.
        TypeError: both ``layout`` and ``body`` given.

    Points farther than ``FAR_RADIUS`` (2 m) from their frame's main cluster
    (:func:`main_cluster`) are not given to the labeler and stay unlabelled.
    """
    _check_inputs(seq, model=model)
    check_count(batch, "batch", 1)
    if not isinstance(tracklets, bool):  # a truthy string would pass as True
        raise TypeError(f"tracklets: expected True or False, got {tracklets!r}")
    arg = "layout"
    if body is not None:
        warnings.warn(
            "label_sequence(body=...) is deprecated: it is a marker layout; pass layout=...",
            DeprecationWarning,
            stacklevel=2,
        )
        if layout is not None:
            raise TypeError("label_sequence: got layout= and its deprecated name body=; pass layout= only")
        layout, arg = body, "body"
    if layout is not None and layout.labels != model.label_names:
        raise ValueError(
            f"{arg}: the layout {layout.name!r} must name the model's {model.num_labels} labels in order "
            f"({', '.join(model.label_names[:4])}, ...), got {len(layout)} ({', '.join(layout.labels[:4])}, ...)"
        )
    check_marker_units(seq.points, "seq")
    # Copies of a point (within 1 mm) are hidden from every step and take their original's label.
    co = find_coincident(seq.points)
    copy = co.copy
    raw = np.where(copy[..., None], np.nan, seq.points)
    visible = np.isfinite(raw).all(-1)
    near = main_cluster(raw)
    far = visible & ~near
    # Far points (reflections, other subjects, absurd values) never reach the labeler or the body check.
    pts = torch.as_tensor(lab_to_unibody(np.where(near[..., None], raw, np.nan), up=up))  # float64
    null = model.num_labels
    if not near.any():  # nothing to label (no column, or no point near a cluster): the report says why
        frame = torch.full(near.shape, null, dtype=torch.int64)
    elif not tracklets:
        frame = label_frames(model, pts.to(model.bin_score), batch=batch).cpu()  # (T, N), L = null
        if layout is not None:
            from .relabel import relabel

            frame, _ = relabel(pts, frame, layout, fps=seq.rate, config=body_config, progress=progress)
    else:  # the columns' evidence over the sequence (far points: gaps)
        prob = sequence_probabilities(model, pts.to(model.bin_score), batch=batch).prob.cpu()
        if layout is None:
            frame = settle_tracklets(prob, torch.from_numpy(near))
        else:
            from .relabel import relabel_tracklets

            frame, _ = relabel_tracklets(pts, prob, layout, fps=seq.rate, config=body_config, progress=progress)
    out = labelled_markers(torch.from_numpy(raw), frame, null).numpy()
    left = visible & (frame == null).numpy()
    keep = np.nonzero(left.any(axis=0))[0]
    rest = np.where(left[:, keep, None], raw[:, keep], np.nan)
    labels = (*model.label_names, *(f"*{i}" for i in range(len(keep))))
    points = np.concatenate([out, rest], axis=1)
    named = (visible & (frame != null).numpy()).sum(1)
    n_vis, n_near = visible.sum(1), near.sum(1)
    point_labels = np.where(seq.visible, co.spread(np.where(visible, frame.numpy(), null)), null)
    report = LabelReport(
        frames=seq.num_frames,
        empty=np.flatnonzero(n_vis == 0),
        scattered=np.flatnonzero((n_vis > 0) & (n_near < MIN_LABELLED) & (named < MIN_LABELLED)),
        rejected=np.flatnonzero((n_near >= MIN_LABELLED) & (named < MIN_LABELLED)),
        far_points=int(far.sum()),
        copies=tuple((seq.labels[c], seq.labels[o]) for c, o in co.columns),
        coincident_points=co.frame_copies,
    )
    if progress is not None and (line := report.summary()):
        progress(line)
    return LabelledSequence(points, labels, ("",) * len(labels), seq.rate, report, point_labels.astype(np.int64))


def solve_sequence(
    seq: MarkerSequence,
    layout: MarkerLayout,
    *,
    up: str = "z",
    config: SolveConfig | None = None,
    progress: Callable[[str], None] | None = None,
) -> SolveResult:
    """Solve the body from the layout's labelled markers of ``seq`` (other columns are ignored).

    Layout labels missing from ``seq`` are treated as never visible; at least a few must exist.
    """
    _check_inputs(seq, layout=layout)
    present = [x for x in layout.labels if x in seq.labels]
    if len(present) < 6:
        raise ValueError(
            f"seq: only {len(present)} of the layout's {len(layout)} labels are in the file "
            f"(have {', '.join(seq.labels[:12])}...); label it first (unibody mocap label)"
        )
    from .solve import solve_markers

    lay = layout.subset(present)
    pts = torch.as_tensor(lab_to_unibody(seq.select(present).points, up=up), dtype=torch.float64)
    return solve_markers(pts, lay, config=config, fps=seq.rate, progress=progress)


def frame_layout(
    seq: MarkerSequence,
    base: MarkerLayout,
    *,
    frame: int,
    name: str,
    up: str = "z",
    prefix: str = "X",
    config: SolveConfig | None = None,
    progress: Callable[[str], None] | None = None,
) -> MarkerLayout:
    """A session's layout from one frame: ``base``'s markers fitted, and every other point of it.

    The file's points labelled with ``base`` labels are fitted (:func:`derive_layout`, starting
    from ``base``'s placement; labels absent or missing in that frame keep it); each other
    point visible in that frame (unlabelled ``*`` points, other protocols' markers) becomes a
    new marker ``{prefix}01``, ... in the order of the file's columns, except points that are no
    marker of this body: farther than ``FAR_RADIUS`` from the median of the labelled markers
    (reflections, other subjects) or within ``COINCIDENT_TOL`` of a labelled marker or an earlier
    point (copies); ``progress`` is told how many were left out. Labels: ``base``'s, then the new
    ones.

    Raises:
        ValueError: ``frame`` out of range, or ``seq`` not in metres, with fewer than 6 of
            ``base``'s labels in that frame, with two labels on one point (within 1 mm), or with a
            label outside the labelled markers' main cluster (:func:`main_cluster`).
    """
    if not 0 <= frame < seq.num_frames:
        raise ValueError(f"frame: expected 0 <= frame < {seq.num_frames}, got {frame}")
    check_marker_units(seq.points[frame : frame + 1], "seq")
    pts = lab_to_unibody(seq.points[frame], up=up)
    idx = {x: i for i, x in enumerate(seq.labels)}
    known = np.stack([pts[idx[x]] if x in idx else np.full(3, np.nan) for x in base.labels])
    if (seen := int(np.isfinite(known).all(-1).sum())) < 6:
        raise ValueError(f"seq: frame {frame} has {seen} of {base.name}'s labels; need 6 or more")
    others = np.array([pts[i] for i, x in enumerate(seq.labels) if x not in base.labels]).reshape(-1, 3)
    others = others[np.isfinite(others).all(-1)]
    k = len(known)
    original = find_coincident(np.concatenate([known, others])[None]).original[0]  # labelled points first
    copy = original != np.arange(k + len(others))
    if (twice := np.flatnonzero(copy[:k])).size:
        a, b = base.labels[original[twice[0]]], base.labels[twice[0]]
        raise ValueError(f"seq: frame {frame} has {a} and {b} on one point (within 1 mm): a point labelled twice?")
    near = main_cluster(known[None])[0]
    if (off := np.flatnonzero(np.isfinite(known).all(-1) & ~near)).size:
        raise ValueError(
            f"seq: frame {frame}'s {base.labels[off[0]]} lies farther than {FAR_RADIUS:g} m from the other "
            f"labelled markers ({off.size} such): mislabelled?"
        )
    far = np.linalg.norm(others - np.median(known[near], axis=0), axis=-1) > FAR_RADIUS
    copy = copy[k:]
    if progress is not None and (far | copy).any():
        progress(
            f"left out {int((far | copy).sum())} of frame {frame}'s {len(others)} other points: "
            f"{int(far.sum())} farther than {FAR_RADIUS:g} m from the body, "
            f"{int((copy & ~far).sum())} within {1000 * COINCIDENT_TOL:g} mm of another point"
        )
    others = others[~(far | copy)]
    extra = torch.as_tensor(others) if len(others) else None
    from .solve import derive_layout

    return derive_layout(torch.as_tensor(known), base.labels, name=name, config=config, initial=base,
                         unlabelled=extra, prefix=prefix)  # fmt: skip


def render_solution(
    path, seq: MarkerSequence, layout: MarkerLayout, result: SolveResult, frame: int, *, up: str = "z"
) -> None:
    """PNG of the solved body at ``frame`` with the file's markers of ``layout`` (red), front | back."""
    from ..body import BodyLayer
    from .render import render_markers

    layer = BodyLayer.from_pca(num_components=result.identity.shape[0], dtype=torch.float64)
    f = slice(frame, frame + 1)
    body = layer(result.identity[None].double(), result.pose[f].double(), transl=result.transl[f].double())
    present = [x for x in layout.labels if x in seq.labels]
    render_markers(path, body.vertices[0], layer.faces, lab_to_unibody(seq.select(present).points[frame], up=up))
