"""ASF/AMC reading (unibody.io.asfamc): hand-computed answers, real CMU files, one-line errors."""

from __future__ import annotations

import time
from pathlib import Path

import numpy as np
import pytest

import unibody.io.asfamc as asfamc
from unibody.io.asfamc import read_asf, read_asf_amc

CMU = Path(__file__).resolve().parents[2] / "shared" / "motions" / "cmu" / "asfamc"

# root -> upper (axis rotated 90 deg about z, dof rx) -> lower
#      -> side  (axis zero, dof rx)                  -> lower2
#      -> twist (dof rz rx: the order of the dof line is not the order of rotation)
ASF = """# a hand-made skeleton
:version 1.10
:name test
:units
  mass 1.0
  length 0.45
  angle deg
:documentation
  free text: with a colon
:root
   order TX TY TZ RX RY RZ
   axis XYZ
   position 0 0 0
   orientation 0 0 0
:bonedata
  begin
     id 1
     name upper
     direction 0 1 0
     length 2
     axis 0 0 90 XYZ
    dof rx
    limits (-180.0 180.0)
  end
  begin
     id 2
     name lower
     direction 1 0 0
     length 1
     axis 0 0 0 XYZ
  end
  begin
     id 3
     name side
     direction 0 1 0
     length 2
     axis 0 0 0 XYZ
    dof rx
    limits (-inf inf)
  end
  begin
     id 4
     name lower2
     direction 1 0 0
     length 1
     axis 0 0 0 XYZ
  end
  begin
     id 5
     name twist
     direction 0 1 0
     length 1
     axis 0 0 0 XYZ
    dof rz rx
    limits (-180.0 180.0)
           (-180.0 180.0)
  end
:hierarchy
  begin
    root upper side twist
    upper lower
    side lower2
  end
"""

FRAME1 = "1\nroot 1 2 3 0 0 0\nupper 90\nside 90\ntwist 90 90\n"
FRAME2 = "2\nroot 1 2 3 0 90 0\nupper 0\nside 0\ntwist 0 0\n"
AMC = ":FULLY-SPECIFIED\n:DEGREES\n" + FRAME1 + FRAME2


def _files(tmp_path: Path, asf: str = ASF, amc: str = AMC) -> tuple[Path, Path]:
    (tmp_path / "s.asf").write_text(asf)
    (tmp_path / "s.amc").write_text(amc)
    return tmp_path / "s.asf", tmp_path / "s.amc"


@pytest.mark.parametrize("regular", [True, False])
def test_hand_made_skeleton_known_positions(tmp_path, monkeypatch, regular):
    if not regular:  # the line-by-line reader must give the same answers as the one-pass one
        monkeypatch.setattr(asfamc, "_amc_fast", lambda *args: None)
    m = read_asf_amc(*_files(tmp_path), fps=60)
    assert m.fps == 60.0 and m.source == "asf/amc" and m.num_frames == 2
    assert m.meters_per_unit == pytest.approx(0.0254 / 0.45)
    assert m.names == ("root", "upper", "lower", "side", "lower2", "twist", "lower_End", "lower2_End", "twist_End")
    pos, _ = m.world()
    at = {n: pos[:, k] for k, n in enumerate(m.names)}
    root = np.array([1.0, 2.0, 3.0])
    # frame 0: upper's axis frame is Rz(90), so rx 90 turns it about world +y: (0,2,0) stays, (1,0,0) -> (0,0,-1)
    np.testing.assert_allclose(at["upper"][0], root, atol=1e-12)
    np.testing.assert_allclose(at["lower"][0], root + [0, 2, 0], atol=1e-12)
    np.testing.assert_allclose(at["lower_End"][0], root + [0, 2, -1], atol=1e-12)
    # side's axis frame is the world: rx 90 turns (0,2,0) -> (0,0,2) and (1,0,0) stays
    np.testing.assert_allclose(at["lower2"][0], root + [0, 0, 2], atol=1e-12)
    np.testing.assert_allclose(at["lower2_End"][0], root + [1, 0, 2], atol=1e-12)
    # twist: "dof rz rx" with axis order XYZ is Rz @ Rx: y -> z under Rx(90), z stays under Rz(90)
    np.testing.assert_allclose(at["twist_End"][0], root + [0, 0, 1], atol=1e-12)
    # frame 1: bones at rest, the root turned 90 deg about y: x -> -z
    np.testing.assert_allclose(at["lower_End"][1], root + [0, 2, -1], atol=1e-12)
    np.testing.assert_allclose(at["lower2_End"][1], root + [0, 2, -1], atol=1e-12)
    np.testing.assert_array_equal(m.rotations[1, 1:], np.broadcast_to(np.eye(3), (8, 3, 3)))


def test_radians_and_length_units(tmp_path):
    asf = ASF.replace("angle deg", "angle rad").replace("axis 0 0 90 XYZ", f"axis 0 0 {np.pi / 2!r} XYZ")
    asf = asf.replace("length 0.45", "length 1.0")
    amc = ":FULLY-SPECIFIED\n" + FRAME1.replace(" 90", f" {np.pi / 2!r}")  # no :DEGREES: the ASF's unit
    m = read_asf_amc(*_files(tmp_path, asf, amc))
    pos, _ = m.world()
    np.testing.assert_allclose(pos[0, m.names.index("lower_End")], [1, 4, 2], atol=1e-12)
    assert m.meters_per_unit == pytest.approx(0.0254)
    amc = ":FULLY-SPECIFIED\n:DEGREES\n" + FRAME1
    pos, _ = read_asf_amc(*_files(tmp_path, asf, amc)).world()
    np.testing.assert_allclose(pos[0, m.names.index("lower_End")], [1, 4, 2], atol=1e-12)


def test_translation_and_length_dofs(tmp_path):
    asf = ASF.replace("axis 0 0 0 XYZ\n    dof rx\n", "axis 0 0 90 XYZ\n    dof tx l\n")  # on side
    amc = ":DEGREES\n1\nroot 0 0 0 0 0 0\nupper 0\nside 0.5 1.5\ntwist 0 0\n"
    m = read_asf_amc(*_files(tmp_path, asf, amc))
    pos, _ = m.world()
    # tx moves side's start along its axis frame's x = world +y; l lengthens it along its direction (+y)
    np.testing.assert_allclose(pos[0, m.names.index("side")], [0, 0.5, 0], atol=1e-12)
    np.testing.assert_allclose(pos[0, m.names.index("lower2")], [0, 0.5 + 2 + 1.5, 0], atol=1e-12)


def _cmu(subject: str, clip: str):
    asf, amc = CMU / subject / f"{subject[1:]}.asf", CMU / subject / f"{clip}.amc"
    if not amc.exists():
        pytest.skip("CMU motions not present")
    return read_asf(asf), read_asf_amc(asf, amc)


def test_real_cmu_walk_bones_keep_their_lengths_and_the_body_is_upright():
    skel, m = _cmu("016", "16_31")  # a walk, 424 frames
    assert m.num_frames == 424 and m.meters_per_unit == pytest.approx(0.0254 / 0.45)
    pos, rot = m.world()
    # every bone keeps its ASF length in every frame (joint -> child joint)
    for k in range(1, len(skel.names)):
        ends = [c for c in range(len(m.names)) if m.parents[c] == k]
        for c in ends:
            length = np.linalg.norm(pos[:, c] - pos[:, k], axis=-1)
            np.testing.assert_allclose(length, skel.lengths[k], rtol=1e-9, atol=1e-9)
    metres = pos * m.meters_per_unit
    y = {n: metres[:, m.names.index(n), 1] for n in ("head", "root", "ltibia", "rtibia", "lfoot", "ltoes_End")}
    assert np.all(y["head"] > y["root"] + 0.3) and np.all(y["root"] > y["ltibia"] + 0.2)
    assert np.all(y["ltibia"] > y["lfoot"] + 0.2) and -0.05 < y["ltoes_End"].min() < 0.1
    # the feet point where the body walks, and the left hip is on the walker's left (Y up)
    ix = m.names.index
    step = metres[30:, 0] - metres[:-30, 0]
    step[:, 1] = 0
    moving = np.linalg.norm(step, axis=1) > 0.1
    travel = step[moving] / np.linalg.norm(step[moving], axis=1, keepdims=True)
    foot = (metres[:-30, ix("ltoes")] - metres[:-30, ix("lfoot")])[moving]
    foot[:, 1] = 0
    foot /= np.linalg.norm(foot, axis=1, keepdims=True)
    assert np.mean(np.sum(foot * travel, axis=1)) > 0.8
    hips = (metres[:-30, ix("lfemur")] - metres[:-30, ix("rfemur")])[moving]
    assert np.all(np.sum(hips * np.cross([0.0, 1.0, 0.0], travel), axis=1) > 0)
    # the ASF puts each 1-dof knee's hinge (axis-frame x) across the shin: the knee bends in a plane
    k = ix("ltibia")
    hinge = rot[:, k] @ skel.axes[k][:, 0]
    shin = pos[:, ix("lfoot")] - pos[:, k]
    assert np.abs(np.sum(hinge * shin, axis=1)).max() < 1e-5 * skel.lengths[k]  # the ASF has 6 digits
    thigh = pos[:, k] - pos[:, ix("lfemur")]
    cos = np.sum(thigh * shin, axis=1) / np.linalg.norm(thigh, axis=1) / np.linalg.norm(shin, axis=1)
    assert np.ptp(np.arccos(cos)) > 0.5  # and the knee does bend while walking (radians)


@pytest.mark.slow
def test_read_every_cmu_asf_amc():
    files = sorted(CMU.glob("*/*.amc"))
    if len(files) < 115:
        pytest.skip("CMU motions not present")
    t = time.perf_counter()
    frames = 0
    for amc in files:
        (asf,) = amc.parent.glob("*.asf")
        m = read_asf_amc(asf, amc)
        frames += m.num_frames
        assert np.isfinite(m.rotations).all() and np.isfinite(m.translations).all()
    print(f"{len(files)} AMC files, {frames} frames in {time.perf_counter() - t:.1f} s")


def _err(tmp_path: Path, asf: str = ASF, amc: str = AMC, fps: float = 120.0) -> str:
    a, b = _files(tmp_path, asf, amc)
    with pytest.raises(ValueError) as err:
        read_asf_amc(a, b, fps=fps)
    msg = str(err.value)
    assert "\n" not in msg, msg
    return msg


@pytest.mark.parametrize(
    ("asf", "message"),
    [
        ("", "s.asf: expected an ASF/AMC text file, got an empty file"),
        (ASF.split(":bonedata")[0], "s.asf: expected an ASF file with a :bonedata section"),
        (ASF.replace("  end\n  begin\n     id 2", "  begin\n     id 2", 1), "expected 'end' before the next 'begin'"),
        (ASF.replace("    side lower2\n", "    side lower2 ghost\n"), "in :hierarchy, got 'ghost'"),
        (ASF.replace("    side lower2\n", ""), "1 unattached ('lower2')"),
        (ASF.replace("    upper lower\n", "    upper lower\n    lower upper\n"), "twice (a cycle?)"),
        (ASF.replace("length 2\n", "length two\n", 1), "line 20: expected a number for length, got 'two'"),
        (ASF.replace("direction 1 0 0", "direction nan 0 0", 1), "finite number for direction"),
        (ASF.replace("dof rz rx", "dof rz rq"), "expected dofs among rx ry rz tx ty tz l"),
        (ASF.replace("angle deg", "angle grad"), "expected 'angle deg' or 'angle rad'"),
        (ASF.replace("axis 0 0 90 XYZ", "axis 0 0 90 XYY"), "expected a rotation order such as XYZ"),
        ("hello\n", "expected a ':keyword' section"),
    ],
)
def test_asf_errors(tmp_path, asf, message):
    msg = _err(tmp_path, asf=asf)
    assert message in msg and "s.asf" in msg, msg


@pytest.mark.parametrize(
    ("amc", "message"),
    [
        (":DEGREES\n", "s.amc: expected AMC frames"),
        (AMC.replace("upper 90\n", "upper 90 1\n"), "s.amc: line 5 (frame 0): expected 1 values for upper (rx), got 2"),
        (AMC.replace("upper 90\n", "elbow 90\n"), "line 5: expected a bone of the ASF skeleton, got 'elbow'"),
        (AMC.replace("side 90\n", ""), "s.amc: frame 0: expected one line for bone side, got 0"),
        (AMC.replace("side 0\n", "side 0\nside 1\n"), "frame 1: expected one line for bone side, got 2"),
        (AMC.replace("2\nroot", "3\nroot"), "expected frame number 2, got 3"),
        (AMC.replace("side 0\n", "side nan\n"), "got NaN/inf for bone side in frames 1"),
        (AMC.replace("side 0\n", "side x\n"), "expected numbers on the lines of bone side"),
        (AMC + ":DEGREES\n", "expected frame data, got the header line"),
    ],
)
def test_amc_errors(tmp_path, amc, message):
    msg = _err(tmp_path, amc=amc)
    assert message in msg, msg


def test_bad_fps(tmp_path):
    assert "fps: expected a positive number" in _err(tmp_path, fps=0.0)
    assert "fps: expected a positive number" in _err(tmp_path, fps=float("nan"))
