"""Build the shipped marker layouts (src/unibody/mocap/data/layouts/*.json) from anatomical rules.

    python scripts/make_marker_layouts.py [--png build/layouts.png]

Each marker is found on the mean body of the native PCA in the T-pose (arms along +-X, palms
down, X to the body's left, Y up, Z forward): from an anchor inside the body (a blend of two
joints plus an offset, metres) a ray leaves in an anatomical direction, and the marker's
vertex is the farthest surface vertex within 1.5 cm of that ray. Right-side markers mirror
the left rule (x -> -x). Rules follow the Plug-in Gait and CMU placement guides (bony
landmarks: acromion, epicondyles, styloids, malleoli, ASIS/PSIS, C7, T10, jugular notch,
xiphoid). The result is deterministic; no mocap data is used.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import torch

from unibody.body import BodyLayer
from unibody.mocap.layout import MarkerLayout

OUT = Path(__file__).resolve().parents[1] / "src/unibody/mocap/data/layouts"
SKIN = 0.0095  # m, a 14 mm marker on its base (paper 003 / MoSh++ default)

# label: (joint a, joint b, t, offset (x, y, z), direction (x, y, z)); anchor = lerp(a, b, t) + offset.
# Left-side rules; a label starting with "L" gets an "R" mirror. Central markers have no mirror.
RULES: dict[str, tuple] = {
    # head and trunk
    "LFHD": ("Head", "HeadEnd", 0.55, (0.0, 0.0, 0.0), (1.2, 0.15, 1.0)),  # the temple (PiG, CGM2)
    "LBHD": ("Head", "HeadEnd", 0.3, (0.0, 0.0, 0.0), (0.5, -0.1, -1.0)),  # above the occiput: bands tilt up
    "C7": ("Neck1", "Neck1", 0.0, (0.0, -0.01, 0.0), (0.0, 0.25, -1.0)),
    "T10": ("Spine2", "Chest", 1.0, (0.0, 0.03, 0.0), (0.0, 0.0, -1.0)),
    "CLAV": ("Neck1", "Neck1", 0.0, (0.0, -0.035, 0.0), (0.0, 0.0, 1.0)),
    "STRN": ("Spine2", "Chest", 1.0, (0.0, 0.02, 0.0), (0.0, 0.0, 1.0)),
    "RBAK": ("Chest", "Neck1", 0.45, (-0.075, 0.0, 0.0), (-0.2, 0.0, -1.0)),
    # arms (T-pose, palms down: lateral of the upper arm is +Y, the thumb side of the wrist +Z)
    "LSHO": ("LeftShoulder", "LeftArm", 0.85, (0.0, 0.0, 0.0), (0.15, 1.0, 0.0)),
    "LUPA": ("LeftArm", "LeftForeArm", 0.55, (0.0, 0.0, 0.0), (0.0, 0.8, -0.6)),
    "LELB": ("LeftForeArm", "LeftForeArm", 0.0, (0.0, 0.0, 0.0), (0.0, 0.85, -0.5)),
    "LFRM": ("LeftForeArm", "LeftHand", 0.5, (0.0, 0.0, 0.0), (0.0, 0.7, -0.7)),
    "LWRA": ("LeftForeArm", "LeftHand", 0.96, (0.0, 0.0, 0.0), (0.0, 0.15, 1.0)),
    "LWRB": ("LeftForeArm", "LeftHand", 0.96, (0.0, 0.0, 0.0), (0.0, 0.15, -1.0)),
    "LFIN": ("LeftHand", "LeftHandIndex1", 0.9, (0.0, 0.0, 0.0), (0.0, 1.0, 0.0)),
    # pelvis (PiG ASIS/PSIS; CMU front/back waist a little higher and more lateral)
    "LASI": ("Hips", "LeftLeg", 0.9, (0.0, 0.09, 0.0), (0.25, 0.0, 1.0)),
    "LPSI": ("Hips", "LeftLeg", 0.45, (0.0, 0.09, 0.0), (0.0, 0.0, -1.0)),
    "LFWT": ("Hips", "LeftLeg", 1.0, (0.0, 0.12, 0.0), (0.35, 0.0, 1.0)),
    "LBWT": ("Hips", "LeftLeg", 0.5, (0.0, 0.12, 0.0), (0.1, 0.0, -1.0)),  # over the PSIS, ~10 cm apart
    # legs
    "LTHI": ("LeftLeg", "LeftShin", 0.6, (0.0, 0.0, 0.0), (1.0, 0.0, 0.25)),
    "LKNE": ("LeftShin", "LeftShin", 0.0, (0.0, 0.0, 0.0), (1.0, 0.0, 0.0)),
    "LTIB": ("LeftShin", "LeftFoot", 0.6, (0.0, 0.0, 0.0), (1.0, 0.0, 0.25)),
    "LSHN": ("LeftShin", "LeftFoot", 0.45, (0.0, 0.0, 0.0), (0.3, 0.0, 1.0)),
    "LANK": ("LeftFoot", "LeftFoot", 0.0, (0.0, 0.0, 0.0), (1.0, 0.0, -0.1)),
    "LHEE": ("LeftFoot", "LeftFoot", 0.0, (0.0, -0.035, 0.0), (0.0, -0.1, -1.0)),
    "LTOE": ("LeftFoot", "LeftToeBase", 0.95, (-0.01, 0.0, 0.0), (0.0, 1.0, 0.1)),
    "LMT5": ("LeftFoot", "LeftToeBase", 0.75, (0.0, -0.015, 0.0), (1.0, 0.0, 0.0)),
}

PIG35 = (
    "LFHD RFHD LBHD RBHD C7 T10 CLAV STRN RBAK LSHO LELB LWRA LWRB LFIN RSHO RELB RWRA RWRB RFIN "
    "LASI RASI LPSI RPSI LTHI LKNE LTIB LANK LHEE LTOE RTHI RKNE RTIB RANK RHEE RTOE"
).split()
PIG39 = (
    "LFHD RFHD LBHD RBHD C7 T10 CLAV STRN RBAK LSHO LUPA LELB LFRM LWRA LWRB LFIN RSHO RUPA RELB RFRM RWRA RWRB RFIN "
    "LASI RASI LPSI RPSI LTHI LKNE LTIB LANK LHEE LTOE RTHI RKNE RTIB RANK RHEE RTOE"
).split()
CMU41 = (
    "LFHD RFHD LBHD RBHD C7 T10 CLAV STRN RBAC LSHO LUPA LELB LFRM LWRA LWRB LFIN RSHO RUPA RELB RFRM RWRA RWRB "
    "RFIN LFWT RFWT LBWT RBWT LTHI LKNE LSHN LANK LHEE LTOE LMT5 RTHI RKNE RSHN RANK RHEE RTOE RMT5"
).split()
ALIASES = {"RBAC": "RBAK"}  # the CMU name of the same landmark


def expand_rules() -> dict[str, tuple]:
    rules = {}
    for label, (a, b, t, off, d) in RULES.items():
        rules[label] = (a, b, t, off, d)
        if label[0] == "L":
            mirror = lambda n: n.replace("Left", "Right")  # noqa: E731
            rules["R" + label[1:]] = (mirror(a), mirror(b), t, (-off[0], *off[1:]), (-d[0], *d[1:]))
    return rules


def find_vertex(v: torch.Tensor, anchor: torch.Tensor, direction: torch.Tensor, radius: float = 0.015) -> int:
    """The farthest vertex along the ray anchor + s * direction within ``radius`` of it."""
    d = direction / direction.norm()
    w = v - anchor
    s = w @ d
    perp = (w - s[:, None] * d).norm(dim=-1)
    score = torch.where((perp < radius) & (s > 0), s, torch.full_like(s, -1.0))
    if float(score.max()) <= 0:
        raise RuntimeError(f"no surface vertex along the ray from {anchor.tolist()} towards {d.tolist()}")
    return int(score.argmax())


def build() -> tuple[dict[str, int], torch.Tensor, BodyLayer]:
    layer = BodyLayer.from_pca(num_components=1, dtype=torch.float64)
    prepared = layer.prepare_identity(torch.zeros(1, 1, dtype=torch.float64))
    out = layer.pose(prepared, torch.zeros(1, 77, 3, dtype=torch.float64))
    v, j = out.vertices[0], out.joints[0]
    name = {n: i for i, n in enumerate(layer.joint_names)}
    found = {}
    for label, (a, b, t, off, d) in expand_rules().items():
        anchor = (1 - t) * j[name[a]] + t * j[name[b]] + torch.tensor(off, dtype=v.dtype)
        found[label] = find_vertex(v, anchor, torch.tensor(d, dtype=v.dtype))
    return found, v, layer


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--png", type=Path, help="render the superset on the mean body")
    args = parser.parse_args()
    found, v, layer = build()
    OUT.mkdir(parents=True, exist_ok=True)
    layouts = {"pig35": PIG35, "pig39": PIG39, "cmu41": CMU41}
    union = list(dict.fromkeys([*PIG39, *[x for x in CMU41 if x not in ALIASES]]))
    layouts["superset"] = union
    for name, labels in layouts.items():
        ids = torch.tensor([found[ALIASES.get(x, x)] for x in labels])
        MarkerLayout(name, tuple(labels), ids, torch.full((len(labels),), SKIN)).save(OUT / f"{name}.json")
        print(f"{name}: {len(labels)} markers -> {OUT / f'{name}.json'}")
    if args.png:
        from unibody.mocap.render import render_markers

        ids = torch.tensor([found[x] for x in union])
        render_markers(args.png, v, layer.faces, v[ids], labels=union)


if __name__ == "__main__":
    main()
