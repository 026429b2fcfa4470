"""Candy-wrapper check: limb cross-sections and volume under large twists, with and without
procedural twist joints (paper 001; paper 004 Figs. 1 and 13 show the LBS collapse).

The canonical rest mesh is held in its bind pose; one driver joint is turned about its own
bone by 90 and 150 degrees (hand -> forearm, foot -> shin; the upper arm and thigh turn
themselves, which the reverse-compensated twist joints absorb near the shoulder and hip).
The limb (vertices skinned mostly to the segment joint's subtree) is cut by 21 planes normal
to the bone across the half of the segment next to the twisted joint; each cut's area comes
from the oriented cut segments (shoelace over all loops). Reported: the smallest area ratio
posed/rest over the planes and the volume ratio (areas integrated along the bone). A PNG
shows plain LBS and procedural twist side by side at 150 degrees.

    python benchmarks/twist.py [--png docs/twist.png]
"""

from __future__ import annotations

import argparse
import math
import time

import numpy as np
import torch
from PIL import Image

from unibody import BodyLayer
from unibody.correctives.metrics import limb_profile
from unibody.geometry.rotations import axis_angle_to_matrix
from unibody.rig import Rig
from unibody.viz.render import Camera, MeshSpec, render_image

# (label, segment start, segment end, twisted joint, plane range along the segment)
CASES = (
    ("forearm (hand twist)", "LeftForeArm", "LeftHand", "LeftHand", (0.5, 1.0)),
    ("shin (foot twist)", "LeftShin", "LeftFoot", "LeftFoot", (0.5, 1.0)),
    ("upper arm (own twist)", "LeftArm", "LeftForeArm", "LeftArm", (0.15, 0.5)),
    ("thigh (own twist)", "LeftLeg", "LeftShin", "LeftLeg", (0.15, 0.5)),
)
ANGLES = (90.0, 150.0)
PLANES = 21


def twisted_pose(prepared, rig: Rig, joint: str, start: str, end: str, degrees: float) -> torch.Tensor:
    """Absolute local rotations: bind pose with ``joint`` turned about the start->end bone."""
    names = rig.joint_names
    r = prepared.rest_rotations[0]
    parents = torch.tensor([max(p, 0) for p in rig.tree.parents])
    local = r[parents].transpose(-1, -2) @ r
    j = names.index(joint)
    bone = r[j].T @ (prepared.rest_joints[0, names.index(end)] - prepared.rest_joints[0, names.index(start)])
    local[j] = local[j] @ axis_angle_to_matrix(math.radians(degrees) * bone / bone.norm())
    return local[None, 1:]


def limb_faces(rig: Rig, start: str) -> np.ndarray:
    """Faces whose three vertices are skinned at least half to ``start``'s subtree."""
    names, children = rig.joint_names, rig.tree.children
    sub, stack = [], [names.index(start)]
    while stack:
        j = stack.pop()
        sub.append(j)
        stack += children[j]
    w = rig.dense_skinning_weights()[:, sub].sum(1).numpy() >= 0.5
    f = rig.faces.numpy()
    return f[w[f].all(1)]


def panel(verts, faces, a, b, label, size=(520, 520)) -> np.ndarray:
    mid = a + 0.85 * (b - a)
    axis = (b - a) / np.linalg.norm(b - a)
    view = np.array([0.0, 0.0, 1.0]) - axis[2] * axis
    view /= np.linalg.norm(view)
    cam = Camera(tuple(mid + 0.7 * view), tuple(mid), fov_y=32.0)
    img = render_image([MeshSpec(verts, faces, (0.80, 0.66, 0.58))], width=size[0], height=size[1], camera=cam,
                       ground_y=None)  # fmt: skip
    from PIL import ImageDraw

    im = Image.fromarray(img)
    ImageDraw.Draw(im).text((12, 10), label, fill=(20, 20, 20))
    return np.asarray(im)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--png", default="docs/twist.png")
    parser.add_argument("--threads", type=int, default=2)
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    rig = Rig.canonical()
    plain, twisted = BodyLayer(rig), BodyLayer(rig, procedural=True)
    prepared = plain.prepare_rest(rig.bind_vertices[None])
    names, all_faces = rig.joint_names, rig.faces.numpy()
    rest = prepared.rest_vertices[0].numpy()
    print(f"{'case':24s} {'deg':>4s} | {'min area ratio':>15s} {'volume ratio':>13s} | plain LBS -> procedural twist")
    panels = []
    for label, start, end, joint, (t0, t1) in CASES:
        faces = limb_faces(rig, start)
        ts = np.linspace(t0, t1, PLANES)
        ja, jb = names.index(start), names.index(end)
        rest_j = prepared.rest_joints[0].numpy()
        area0 = limb_profile(rest, faces, rest_j[ja], rest_j[jb], ts)
        for deg in ANGLES:
            row = []
            local = twisted_pose(prepared, rig, joint, start, end, deg)
            for layer in (plain, twisted):
                out = layer.pose(prepared, local, absolute=True)
                v, j = out.vertices[0].numpy(), out.joints[0].numpy()
                area = limb_profile(v, faces, j[ja], j[jb], ts)
                row.append(((area / area0).min(), np.trapezoid(area, ts) / np.trapezoid(area0, ts)))
                if deg == ANGLES[-1] and label.startswith(("forearm", "shin")):
                    tag = "plain LBS" if layer is plain else "procedural twist"
                    panels.append(panel(v, all_faces, j[ja], j[jb], f"{label}, {deg:.0f} deg: {tag}"))
            (pa, pv), (ta, tv) = row
            print(f"{label:24s} {deg:4.0f} | {pa:6.1%} -> {ta:6.1%}  {pv:6.1%} -> {tv:6.1%}")
    grid = np.concatenate([np.concatenate(panels[i : i + 2], 1) for i in range(0, len(panels), 2)], 0)
    Image.fromarray(grid).save(args.png)
    print(f"wrote {args.png}")
    # Cost of the twist joints (24 extra joints, 102 in all) at batch 64, float32: the two layers
    # interleaved round by round (the machine's load moves both alike), median of 15 rounds of 10 calls.
    gen = torch.Generator().manual_seed(0)
    pose = 0.3 * torch.randn(64, 77, 3, generator=gen)
    layers = {"plain LBS": plain.float(), "procedural twist": twisted.float()}
    prepared = {k: lay.prepare_rest(rig.bind_vertices[None].float()) for k, lay in layers.items()}
    times = {k: [] for k in layers}
    for k, lay in layers.items():
        for _ in range(3):
            lay.pose(prepared[k], pose)
    for _ in range(15):
        for k, lay in layers.items():
            t = time.perf_counter()
            for _ in range(10):
                lay.pose(prepared[k], pose)
            times[k].append((time.perf_counter() - t) / 10 * 1e3)
    ms = {k: float(np.median(v)) for k, v in times.items()}
    for k, v in ms.items():
        print(f"pose(), batch 64, float32, {torch.get_num_threads()} threads: {k:16s} {v:6.1f} ms")
    print(f"procedural twist / plain LBS: {ms['procedural twist'] / ms['plain LBS']:.2f}x")


if __name__ == "__main__":
    main()
