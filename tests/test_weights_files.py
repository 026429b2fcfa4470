"""Weights files in place of the shipped ones: one ValueError naming the file, no torch traceback, no NaN results.

Before (unibody.io.weights): ``unibody mocap label --model FILE`` on junk bytes ended in
"internal error (KeyError: 101)", on a truncated file in a torch RuntimeError, on another
model's file in a KeyError or a state-dict size mismatch, and on weights holding a NaN it
labelled and then blamed the marker file ("x.c3d: matrix contains invalid numeric entries").
The same held for the correctives, occupancy and PanoMan loaders.
"""

from __future__ import annotations

from pathlib import Path

import pytest
import torch

from test_cli import _markers, _one_line_error, _run
from test_mocap_pipeline import smooth_sequence
from unibody.correctives.model import Correctives
from unibody.correctives.model import default_weights_path as correctives_path
from unibody.mocap.labeler import Labeler
from unibody.mocap.layout import MarkerLayout
from unibody.mocap.pipeline import _weights_dir
from unibody.mocap.solve import unibody_to_lab
from unibody.occupancy.field import BodyOccupancy
from unibody.occupancy.model import default_weights_path as occupancy_path
from unibody.panoman.model import PanoMan, default_model_path

LOADERS = {
    "labeler": (Labeler.load, lambda: Path(str(_weights_dir() / "labeler_cmu41.pt")), "not a labeler"),
    "correctives": (Correctives.load, correctives_path, "not correctives weights"),
    "occupancy": (BodyOccupancy.pretrained, occupancy_path, "not occupancy weights"),
    "panoman": (PanoMan.load, default_model_path, "not a unibody.panoman/1 file"),
}


def _nan_copy(src: Path, dst: Path) -> Path:
    """The file with its first floating-point tensor (found anywhere in the saved dict) set to NaN."""
    state = torch.load(src, weights_only=True)

    def poison(x):  # noqa: ANN001, ANN202
        if isinstance(x, torch.Tensor) and x.is_floating_point() and x.numel():
            x.view(-1)[0] = float("nan")
            return True
        items = x.values() if isinstance(x, dict) else x if isinstance(x, list | tuple) else ()
        return any(poison(v) for v in items)

    assert poison(state)
    torch.save(state, dst)
    return dst


@pytest.mark.parametrize("kind", sorted(LOADERS))
def test_a_file_that_is_not_these_weights_is_one_error_naming_it(tmp_path, kind):
    load, shipped, what = LOADERS[kind]
    raw = shipped().read_bytes()
    load(shipped())  # the shipped file loads
    other = LOADERS["labeler" if kind != "labeler" else "correctives"][1]()
    cases = {
        "junk.pt": b"not a weights file" * 8,
        "half.pt": raw[: len(raw) // 2],
        "other.pt": other.read_bytes(),
    }
    for name, data in cases.items():
        (tmp_path / name).write_bytes(data)
        with pytest.raises(ValueError, match=rf"^{tmp_path / name}: ") as info:
            load(tmp_path / name)
        assert what in str(info.value), info.value
        assert "\n" not in str(info.value)
    bad = _nan_copy(shipped(), tmp_path / "nan.pt")
    with pytest.raises(ValueError, match=rf"^{bad}: \S+ holds NaN/inf: corrupted weights$"):
        load(bad)


def test_cli_label_with_a_broken_model_file(tmp_path, capsys):
    """`unibody mocap label --model FILE`: exit 3, one line naming the model file, nothing written."""
    points, _ = smooth_sequence(MarkerLayout.load("cmu41"), frames=3)
    markers = _markers(tmp_path / "m.npz", unibody_to_lab(points.numpy(), up="z"))
    (tmp_path / "junk.pt").write_bytes(b"junk" * 10)
    _nan_copy(Path(str(_weights_dir() / "labeler_cmu41.pt")), tmp_path / "nan.pt")
    for model, needle in (
        ("junk.pt", "junk.pt: not a labeler"),
        ("nan.pt", "nan.pt: state_dict.bin_score holds NaN/inf"),
    ):
        code, out, err = _run(
            capsys, "mocap", "label", markers, "--model", tmp_path / model, "--out", tmp_path / "o.c3d"
        )
        assert code == 3 and out == "" and not (tmp_path / "o.c3d").exists()
        _one_line_error(err, needle)
