"""Optimisers descend a gradient whatever their caller's grad mode.

Under ``torch.no_grad()`` (every ``unibody`` command runs under it) they enable gradients
themselves: the registration of a new template failed there with "element 0 of tensors does not
require grad" (see test_registration.py -k inside_out, test_occupancy.py -k stops_items). Under
``torch.inference_mode()`` gradients cannot be had; each says so in one line instead of failing
deep inside autograd (retargeting did).
"""

from __future__ import annotations

from pathlib import Path

import pytest
import torch

from unibody.fitting.retarget import retarget
from unibody.fitting.shape_fit import fit_identity
from unibody.occupancy import resolve_self_intersections
from unibody.panoman.body_fit import fit_body
from unibody.registration import normalize, register

CLIP = Path(__file__).resolve().parents[2] / "shared" / "motions" / "cmu" / "bvh" / "002" / "02_01.bvh"


@pytest.mark.parametrize(
    "call, name",
    [
        (lambda: register(None, None), "register"),
        (lambda: normalize(None, None), "normalize"),
        (lambda: retarget(None, None, ()), "retarget"),
        (lambda: fit_identity(None, None), "fit_identity"),
        (lambda: fit_body(None, None, None, None, None), "fit_body"),
        (lambda: resolve_self_intersections(None, None, None, None), "resolve_self_intersections"),
    ],
)
def test_inference_mode_is_refused_in_one_line(call, name):
    with torch.inference_mode(), pytest.raises(RuntimeError, match=rf"^{name} descends a gradient: call it outside"):
        call()


@pytest.mark.skipif(not CLIP.is_file(), reason="../shared/motions/cmu is not here")
def test_a_bvh_converted_under_inference_mode_says_why(tmp_path):
    from unibody.convert import ConvertOptions
    from unibody.convert.skeletal import read_bvh

    lines = CLIP.read_text().splitlines()
    at = next(i for i, s in enumerate(lines) if s.startswith("Frames:"))
    clip = tmp_path / "clip.bvh"
    clip.write_text("\n".join(lines[:at] + ["Frames: 2"] + lines[at + 1 : at + 4]) + "\n")
    with torch.inference_mode(), pytest.raises(RuntimeError, match="^retarget descends a gradient"):
        read_bvh(clip, ConvertOptions())  # was: "element 0 of tensors does not require grad" from L-BFGS
    with torch.no_grad():
        assert read_bvh(clip, ConvertOptions()).motion.pose.shape == (2, 77, 3)
