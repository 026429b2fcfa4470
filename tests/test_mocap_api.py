"""unibody.mocap's public names: a contract (changing them is a deliberate edit of this file)."""

from __future__ import annotations

import subprocess
import sys

import unibody.mocap as mocap


def test_mocap_all_snapshot_and_every_name_resolves():
    assert sorted(mocap.__all__) == [
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
    from unibody.mocap import relabel, solve

    assert mocap.solve_markers is solve.solve_markers and mocap.RelabelConfig is relabel.RelabelConfig
    assert mocap.SolveConfig is solve.SolveConfig and mocap.SolveResult is solve.SolveResult
    assert set(mocap.__all__) <= set(dir(mocap))


def test_importing_mocap_loads_no_weights_and_no_solver():
    code = """
import sys
import torch
loads = []
real = torch.load
torch.load = lambda *a, **k: loads.append(a) or real(*a, **k)
import unibody.mocap
solver = ("solve", "derive", "_stage1", "_stage2", "_marker_body", "relabel")
print(loads, sorted(m for m in sys.modules if m.removeprefix("unibody.mocap.") in solver))
"""
    run = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert run.stdout.strip() == "[] []", run.stdout
