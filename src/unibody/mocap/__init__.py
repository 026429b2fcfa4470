"""Optical motion capture (paper 003): read marker files, label raw point clouds, solve the body.

    from unibody.mocap import MarkerLayout, label_sequence, load_labeler, read_markers, solve_sequence

    seq = read_markers("session.c3d")                         # metres, NaN = missing
    labelled = label_sequence(seq, load_labeler("cmu41"))     # LabelledSequence (+ .report)
    result = solve_sequence(labelled, MarkerLayout.load("cmu41"))  # SolveResult; .to_motion(fps)

Modules: ``c3d`` (C3D / npz marker files), ``layout`` (named markers on the canonical mesh),
``frames`` (lab axes and units), ``labeler`` (self-attention + Sinkhorn), ``tracklets``,
``pipeline`` (file-level label / solve / layout steps), ``solve`` (MoSh-like body solve:
``solve_config``, ``_stage1``, ``_stage2``, ``solve_result``, ``derive``), ``relabel``
(body-checked labels), ``synthetic`` and ``corrupt`` (training data), ``metrics``.

Importing this package loads no weights and no solver: ``solve_markers``, ``derive_layout``
and ``RelabelConfig`` are imported from their modules on first use (the body check itself is
:func:`unibody.mocap.relabel.relabel`, not re-exported: the name is its module's).
"""

from __future__ import annotations

import importlib

from .c3d import MarkerSequence, read_markers, write_c3d, write_npz
from .frames import check_marker_units, lab_to_unibody, unibody_to_lab
from .labeler import Labeler, LabelerConfig, label_frames
from .layout import MarkerLayout, available_layouts
from .pipeline import (
    LabelledSequence,
    LabelReport,
    available_labelers,
    frame_layout,
    label_sequence,
    load_labeler,
    render_solution,
    solve_sequence,
)
from .solve_config import SolveConfig
from .solve_result import SolveResult

__all__ = [
    "LabelReport",
    "Labeler",
    "LabelerConfig",
    "LabelledSequence",
    "MarkerLayout",
    "MarkerSequence",
    "RelabelConfig",
    "SolveConfig",
    "SolveResult",
    "available_labelers",
    "available_layouts",
    "check_marker_units",
    "derive_layout",
    "frame_layout",
    "lab_to_unibody",
    "label_frames",
    "label_sequence",
    "load_labeler",
    "read_markers",
    "render_solution",
    "solve_markers",
    "solve_sequence",
    "unibody_to_lab",
    "write_c3d",
    "write_npz",
]

# Public names whose modules import the body solver: loaded on first access (PEP 562).
_ON_USE = {
    "RelabelConfig": ".relabel",
    "derive_layout": ".derive",
    "solve_markers": ".solve",
}


def __getattr__(name: str):
    if name in _ON_USE:
        value = getattr(importlib.import_module(_ON_USE[name], __name__), name)
        globals()[name] = value
        return value
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


def __dir__() -> list[str]:
    return sorted(set(globals()) | set(__all__))
