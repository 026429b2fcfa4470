"""Pose correctives (issue 40): plain LBS, LBS + procedural twist, the teacher and the correctives
MLP (alone, and on the twist rig with the weights trained for it) on seeded stress poses x
held-out identities.

Measures (:mod:`unibody.correctives.metrics`): edge strain and dihedral change in the joint
regions (mean, P95), limb-segment volume / rest, the smallest forearm cross-section / rest at a
150 deg hand twist, self-intersecting triangle pairs (trunk and limbs; the first
``--intersect-identities`` identities), the MLP against the teacher (mm, both rigs), the change
the MLP makes at small poses (every joint within 0.2 rad of the rest pose, and of the T-pose;
both rigs), the
cost of posing with correctives at batch 1 and 32 on both rigs (float32, one thread, median of 15
interleaved rounds of 10 calls) and its split over the correctives' stages (plain rig, batch 32),
and what pose inversion leaves on meshes made with correctives, modelling plain LBS
(``corrective_rounds=0``) and knowing the correctives (``corrective_rounds=2``, the default);
how far the teacher and the MLP move flesh that one bone carries off that bone (stress poses, and
the arms of Anny bodies at the T-pose).

    OMP_NUM_THREADS=1 python benchmarks/correctives.py [--identities 10] [--png docs/correctives.png]
        [--section-png docs/correctives_section.png]

The "MLP + twist" row poses with ``BodyLayer.from_pca(procedural=True)`` and the twist-rig
weights (``--weights-twist``, default the shipped ``correctives_twist.pt``); the teacher row is
the teacher the plain weights were trained with (their meta: ARAP iterations, volume, contact),
unless ``--teacher-iterations`` says otherwise.
"""

from __future__ import annotations

import argparse
import functools
import time

import numpy as np
import torch
from PIL import Image, ImageDraw

from unibody import BodyLayer
from unibody.correctives.metrics import SEGMENTS, SurfaceMeasures, limb_profile, one_bone
from unibody.correctives.model import Correctives
from unibody.correctives.stress import forearm_twist_pose, stress_poses
from unibody.correctives.training import TeacherSetup, draw_identities, teacher_targets
from unibody.geometry.rotations import axis_angle_to_matrix
from unibody.symmetry import mirror
from unibody.synth.poses import keyed_generator
from unibody.viz.render import Camera, MeshSpec, render_image

METHODS = ("LBS", "LBS + twist", "teacher", "MLP", "MLP + twist")


def forearm_min_section(measures: SurfaceMeasures, rest, rest_joints, posed, joints) -> float:
    """Smallest cross-section ratio posed / rest over 21 planes across the wrist half of the left forearm."""
    names = measures.joint_names
    a, b = names.index("LeftForeArm"), names.index("LeftHand")
    sub = [a, b] + [i for i, n in enumerate(names) if n.startswith("LeftHand")]
    w = measures.weights[:, sorted(set(sub))].sum(1) >= 0.5
    faces = measures.faces[w[measures.faces].all(1)]
    ts = np.linspace(0.5, 1.0, 21)
    a0 = limb_profile(rest, faces, rest_joints[a], rest_joints[b], ts)
    a1 = limb_profile(posed, faces, joints[a], joints[b], ts)
    return float((a1 / a0).min())


def small_poses(layer: BodyLayer, prepared, n: int, gen: torch.Generator, around_rest: bool) -> torch.Tensor:
    """(n, 77, 3, 3) T-pose-relative poses with every joint within 0.2 rad of the rest pose (or of the T-pose)."""
    delta = torch.randn(n, 77, 3, generator=gen)
    delta = delta / delta.norm(dim=-1, keepdim=True) * 0.2 * torch.rand(n, 77, 1, generator=gen)
    r = axis_angle_to_matrix(delta)
    if not around_rest:
        return r
    rot = prepared.rest_rotations[0]
    rest_local = rot[layer.parents[1:]].transpose(-1, -2) @ rot[1:]
    return layer.to_relative(rest_local[None] @ r)


def interleaved(calls: dict, rounds: int = 15) -> dict:
    """ms per call of each of ``calls``: median of ``rounds`` rounds of 10 calls each, the calls
    interleaved round by round (the machine's load moves them alike), after 3 warm-up calls."""
    for f in calls.values():
        for _ in range(3):
            f()
    times = {k: [] for k in calls}
    for _ in range(rounds):
        for k, f in calls.items():
            t = time.perf_counter()
            for _ in range(10):
                f()
            times[k].append((time.perf_counter() - t) / 10 * 1e3)
    return {k: float(np.median(v)) for k, v in times.items()}


def timing(layer: BodyLayer, prepared, pose: torch.Tensor, rounds: int = 15) -> tuple[float, float]:
    """ms per call of ``pose()`` without and with correctives (:func:`interleaved`)."""
    m = interleaved({c: functools.partial(layer.pose, prepared, pose, correctives=c) for c in (False, True)}, rounds)
    return m[False], m[True]


def stage_split(layer: BodyLayer, prepared, pose: torch.Tensor, rounds: int = 15) -> dict[str, float]:
    """ms per call of ``pose()`` without and with correctives and of the correctives' stages (the
    rotations they read, the MLP, the decode; skinning the displacements: the rest of the
    difference), :func:`interleaved`."""
    corr = layer.correctives
    world = layer.pose(prepared, pose, correctives=False).transforms
    rel = corr.world_relative(world, prepared.rest_rotations, layer.parents)
    shape = corr.shape_inputs(prepared.rest_vertices, prepared.rest_joints)
    x6 = corr.features(rel)
    scale = corr.size_of(prepared.rest_joints) / corr.size_ref
    m = interleaved(
        {
            "without": lambda: layer.pose(prepared, pose, correctives=False),
            "with": lambda: layer.pose(prepared, pose, correctives=True),
            "rotations": lambda: corr.features(corr.world_relative(world, prepared.rest_rotations, layer.parents)),
            "MLP": lambda: corr.activations(x6, shape),
            "MLP + decode": lambda: corr.slot_displacements(x6, scale, shape),
        },
        rounds,
    )
    m["decode"] = m.pop("MLP + decode") - m["MLP"]
    m["skinning the displacements (the rest)"] = m["with"] - m["without"] - m["rotations"] - m["MLP"] - m["decode"]
    return m


def panel(verts, faces, centre, view, label, size=360) -> np.ndarray:
    cam = Camera(tuple(centre + 0.9 * view), tuple(centre), fov_y=34.0)
    img = render_image([MeshSpec(verts, faces, (0.80, 0.66, 0.58))], width=size, height=size, camera=cam, ground_y=None)
    im = Image.fromarray(img)
    ImageDraw.Draw(im).text((8, 6), label, fill=(20, 20, 20))
    return np.asarray(im)


def picture(layer: BodyLayer, path: str) -> None:
    """Four stress poses of the mean body: LBS (top) vs correctives (bottom), close on the joint."""
    prepared = layer.prepare_identity(torch.zeros(1, layer.identity.num_params))
    poses, labels = stress_poses(torch.Generator().manual_seed(0), seeded=0)
    # views picked by eye; the elbow from below and in front, where the fold is seen
    picks = [("elbow 150 (left)", "LeftForeArm", (0.2, -0.8, 0.6)), ("knee 150 (left)", "LeftShin", (1.0, 0.0, 0.2)),
             ("shoulder abduction 150 (left)", "LeftArm", (0.3, 0.2, 1.0)),
             ("squat: hip 120 + knee 150 (left)", "LeftLeg", (1.0, 0.1, 0.3))]  # fmt: skip
    faces = layer.faces.numpy()
    rows = [[], []]
    for label, joint, view in picks:
        i = labels.index(label)
        view = np.array(view) / np.linalg.norm(view)
        for r, corr in enumerate((False, True)):
            out = layer.pose(prepared, poses[i : i + 1], correctives=corr)
            centre = out.joints[0, layer.joint_names.index(joint)].numpy()
            tag = f"{label}: {'correctives' if corr else 'LBS'}"
            rows[r].append(panel(out.vertices[0].numpy(), faces, centre, view, tag))
    grid = np.concatenate([np.concatenate(row, 1) for row in rows], 0)
    Image.fromarray(grid).save(path)
    print(f"wrote {path}")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--weights", default=None, help="correctives weights (default: the shipped ones)")
    parser.add_argument(
        "--weights-twist", default=None, help="the twist rig's correctives (default: the shipped correctives_twist.pt)"
    )
    parser.add_argument("--teacher-iterations", type=int, default=None, help="default: the plain weights' meta, or 6")
    parser.add_argument("--identities", type=int, default=10)
    parser.add_argument("--intersect-identities", type=int, default=3)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--threads", type=int, default=1)
    parser.add_argument("--device", default="cpu")
    parser.add_argument("--png", default=None)
    parser.add_argument("--section-png", default=None, help="the arm cross-sections of the default Anny body")
    parser.add_argument(
        "--sections",
        default="quality small mirror backends speed inversion",
        help="any of: quality small mirror backends speed inversion",
    )
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    model = Correctives.load(args.weights)
    model_twist = Correctives.load(args.weights_twist, procedural=True)
    if args.teacher_iterations is None:
        args.teacher_iterations = int(model.meta.get("teacher_iterations", 6))
    layer = BodyLayer.from_pca(correctives=model).to(args.device)
    twist = BodyLayer.from_pca(procedural=True, correctives=model_twist).to(args.device)
    for tag, m in (("plain rig", model), ("twist rig", model_twist)):
        print(f"correctives ({tag}): {len(m.union)} vertices, {m.num_active} active joints; "
              f"{m.meta.get('command', '')}")  # fmt: skip
    if "quality" in args.sections:
        quality(layer, twist, args)
    if "small" in args.sections:
        for tag, lay in (("plain rig", layer), ("twist rig", twist)):
            small(lay, tag, args)
    if "mirror" in args.sections:
        for tag, lay in (("plain rig", layer), ("twist rig", twist)):
            mirrored(lay, tag)
    if "backends" in args.sections:
        backends(model, args)
        backends(model_twist, args, procedural=True)
    if "speed" in args.sections:
        prepared = layer.prepare_identity(torch.zeros(1, layer.identity.num_params))
        poses, _ = stress_poses(keyed_generator("correctives-stress", args.seed))
        for tag, lay in (("plain rig", layer), ("twist rig", twist)):
            for b in (1, 32):
                off, on = timing(lay, prepared, poses[:b])
                print(f"pose(), {tag}, float32, batch {b:2d}, {torch.get_num_threads()} thread(s): without "
                      f"{off:6.2f} ms, with correctives {on:6.2f} ms (+{on / off - 1:.0%})")  # fmt: skip
        split = stage_split(layer, prepared, poses[:32])
        parts = [f"{k} {v:.2f} ms ({v / split['without']:.0%})" for k, v in split.items() if k != "without"]
        print("  plain rig, batch 32, the correctives' stages against pose() without them: " + ", ".join(parts))
    if "inversion" in args.sections:
        inversion(layer, args)
    if args.png:
        picture(layer, args.png)
    if args.section_png:
        section_png(model, args.section_png)


def small(layer: BodyLayer, tag: str, args: argparse.Namespace) -> None:
    """The change the correctives make at small poses (16 per identity), around the rest pose and the T-pose."""
    gen = keyed_generator("correctives-small", args.seed)
    coeffs = draw_identities(layer, args.identities, keyed_generator("correctives-benchmark", args.seed))
    for around_rest in (True, False):
        change = []
        for c in coeffs:
            prepared = layer.prepare_identity(c[None])
            pose = small_poses(layer, prepared, 16, gen, around_rest)
            a = layer.pose(prepared, pose, correctives=False).vertices
            b = layer.pose(prepared, pose).vertices
            change.append((a - b).norm(dim=-1))
        change = torch.stack(change) * 1e3
        where = "rest pose" if around_rest else "T-pose"
        print(f"small poses, {tag} (every joint within 0.2 rad of the {where}): change mean {change.mean():.3f} mm "
              f"(per mesh max {change.mean(-1).max():.3f} mm), largest vertex {change.max():.2f} mm")  # fmt: skip
    # How the limbs' volumes at the T-pose vary with the body (the teacher keeps each at 100 %)
    vols = tpose_volumes(layer, [layer.prepare_identity(c[None]) for c in coeffs])
    for on, v in vols.items():  # (identities, segments): left Arm, ForeArm, Leg, Shin, then right
        kinds = ("upper arm", "forearm", "thigh", "shin")
        text = ", ".join(f"{k} {float(v[:, [i, i + 4]].min()):.0%}-{float(v[:, [i, i + 4]].max()):.0%}"
                         for i, k in enumerate(kinds))  # fmt: skip
        print(f"T-pose segment volumes / rest over {len(v)} identities, {tag}, {'with' if on else 'without'} "
              f"correctives: {text}")  # fmt: skip


def mirrored(layer: BodyLayer, tag: str) -> None:
    """Left/right: on the mean body (mirror-symmetric), each stress family's left pose against the
    mirror image of its right pose; LBS leaves only the rig's own asymmetry."""
    prepared = layer.prepare_identity(torch.zeros(1, layer.identity.num_params))
    poses, labels = stress_poses(keyed_generator("correctives-stress", 0), seeded=0)
    left = [i for i, n in enumerate(labels) if n.endswith("(left)")]
    right = [labels.index(labels[i].replace("(left)", "(right)")) for i in left]
    for on in (False, True):
        a = layer.pose(prepared, poses[left], correctives=on).vertices
        b = layer.pose(prepared, poses[right], correctives=on).vertices
        gap = (a - mirror(b)).norm(dim=-1) * 1e3
        what = "with" if on else "without"
        print(f"left vs mirrored right, {tag}, mean body, {len(left)} stress families, {what} correctives: "
              f"mean {gap.mean():.3f} mm, largest {gap.max():.2f} mm")  # fmt: skip


def tpose_volumes(layer: BodyLayer, prepared: list) -> dict[bool, torch.Tensor]:
    """{with correctives: (identities, segments) volume / rest of :data:`SEGMENTS` at the T-pose}."""
    measures = SurfaceMeasures.from_layer(layer)
    vols = {False: [], True: []}
    for p in prepared:
        for on in vols:
            out = layer.pose(p, torch.zeros(1, 77, 3), correctives=on)
            vols[on].append(measures.segment_volumes(p.rest_vertices, p.rest_rotations, p.rest_joints, out.vertices,
                                                     out.transforms)[0])  # fmt: skip
    return {on: torch.stack(rows) for on, rows in vols.items()}


def backends(model: Correctives, args: argparse.Namespace, n: int = 8, procedural: bool = False) -> None:
    """Limb volumes at the T-pose on bodies of another backend (Anny: seeded phenotypes, uniform in
    [0, 1]), whose rest poses the native-PCA training identities do not share; left and right apart."""
    layer = BodyLayer.from_anny(procedural=procedural, correctives=model)
    phen = torch.rand(n, layer.identity.num_params, generator=keyed_generator("correctives-anny", args.seed))
    for on, v in tpose_volumes(layer, [layer.prepare_identity(c[None]) for c in phen]).items():
        text = ", ".join(
            f"{name} {float(v[:, k].min()):.0%}-{float(v[:, k].max()):.0%}" for k, (name, _) in enumerate(SEGMENTS)
        )
        print(
            f"Anny T-pose segment volumes / rest over {n} phenotypes, {'twist' if procedural else 'plain'} rig, "
            f"{'with' if on else 'without'} correctives: {text}"
        )
    # How far the correctives move the arms' one-bone flesh (skinning weight >= 0.99) off its bone there
    w = layer.skinning.dense().detach().double().numpy()
    arms = ("LeftArm", "RightArm", "LeftForeArm", "RightForeArm")
    carried = {j: torch.from_numpy(one_bone(w, layer.joint_names.index(j))) for j in arms}
    moved = {j: [] for j in arms}
    for c in phen:
        p = layer.prepare_identity(c[None])
        on, off = (layer.pose(p, torch.zeros(1, 77, 3), correctives=k).vertices[0] for k in (True, False))
        for j, vals in moved.items():
            vals.append(float((on - off)[carried[j]].norm(dim=-1).mean()) * 1e3)
    text = ", ".join(f"{j} {min(v):.1f}-{max(v):.1f}" for j, v in moved.items())
    print(f"Anny T-pose, one-bone flesh of the arms moved off LBS by the correctives (mean per segment, mm): {text}")


def _pixel(q: np.ndarray, frame: tuple) -> tuple[float, float]:
    """Image position of point q in a section's ``frame`` (origin, x axis, y axis; pixels per metre)."""
    o, x, y = frame
    return (210 + float((q - o) @ x), 220 + float((q - o) @ y))


def section_png(model: Correctives, path: str) -> None:
    """Cross-sections of the default Anny body's left upper arm and forearm (half-way along each bone)
    at the T-pose, in the bone's frame (the bone at the dot; 1 cm grid): LBS, the teacher without
    and with anchors, and the correctives ``model``."""
    layer = BodyLayer.from_anny(correctives=model).double()
    p = layer.prepare_identity(torch.full((1, layer.identity.num_params), 0.5, dtype=torch.float64))
    pose = torch.zeros(1, 77, 3, dtype=torch.float64)
    out = layer.pose(p, pose, correctives=False)
    meshes = {"LBS": out.vertices[0].numpy()}
    for anchor in (0.0, float(model.meta.get("teacher_anchor", 0.0)) or 0.01):
        setup = TeacherSetup(layer, anchor=anchor)
        label = f"teacher, anchor {anchor:g}" + (" (before 2026-11-28)" if anchor == 0 else "")
        meshes[label] = teacher_targets(layer, p, pose, setup, iterations=12)[1][0].numpy()
    meshes["correctives MLP (these weights)"] = layer.pose(p, pose).vertices[0].numpy()
    faces, joints, names = layer.faces.numpy(), out.joints[0].numpy(), list(layer.joint_names)
    colours = [(0, 0, 0), (40, 90, 200), (20, 150, 60), (200, 30, 30)]
    panels = []
    for a, b, title in (("LeftArm", "LeftForeArm", "upper arm"), ("LeftForeArm", "LeftHand", "forearm")):
        ja, jb = joints[names.index(a)], joints[names.index(b)]
        o, n = 0.5 * (ja + jb), (jb - ja) / np.linalg.norm(jb - ja)
        up = np.array([0.0, 1.0, 0.0]) - n * n[1]
        up /= np.linalg.norm(up)
        side = np.cross(n, up)
        im = Image.new("RGB", (420, 560), "white")
        draw = ImageDraw.Draw(im)
        scale = 420 / 0.16  # 16 cm across
        frame = (o, side * scale, -up * scale)  # pixel = (210, 220) + ((q - o) . side, -(q - o) . up) * scale

        for g in range(-8, 12):
            draw.line([(210 + g * scale / 100, 20), (210 + g * scale / 100, 480)], fill=(235, 235, 235))
            draw.line([(0, 220 + g * scale / 100), (420, 220 + g * scale / 100)], fill=(235, 235, 235))
        draw.ellipse([206, 216, 214, 224], fill=(0, 0, 0))
        for k, (label, v) in enumerate(meshes.items()):
            d = (v - o) @ n
            for f in faces[(d[faces].min(1) < 0) & (d[faces].max(1) > 0)]:
                cut = [v[f[i]] + d[f[i]] / (d[f[i]] - d[f[(i + 1) % 3]]) * (v[f[(i + 1) % 3]] - v[f[i]])
                       for i in range(3) if (d[f[i]] < 0) != (d[f[(i + 1) % 3]] < 0)]  # fmt: skip
                draw.line([_pixel(cut[0], frame), _pixel(cut[1], frame)], fill=colours[k], width=2)
            draw.text((8, 492 + 15 * k), label, fill=colours[k])
        draw.text((8, 6), f"Anny (default), T-pose: left {title}, half-way along the bone", fill=(0, 0, 0))
        panels.append(np.asarray(im))
    Image.fromarray(np.concatenate(panels, 1)).save(path)
    print(f"wrote {path}")


def inversion(layer: BodyLayer, args: argparse.Namespace) -> None:
    """Pose inversion of meshes made with and without correctives, each re-posed the same way: the
    error it leaves, modelling plain LBS (``corrective_rounds=0``) and knowing the correctives (2)."""
    from dataclasses import replace

    from unibody import PRESETS, PoseInverter
    from unibody.synth.poses import sample_poses

    coeffs = draw_identities(layer, 4, keyed_generator("correctives-benchmark", args.seed))
    gen = keyed_generator("correctives-inversion", args.seed)
    stress, _ = stress_poses(keyed_generator("correctives-stress", args.seed))
    sets = {"generator poses": sample_poses(8, gen, fingers=False), "stress poses": stress[:8]}
    cases = ((False, 0), (True, 0), (True, 2))  # (meshes made with correctives, corrective rounds)
    for preset in ("analytic", "refined"):
        for name, poses in sets.items():
            for corr, rounds in cases:
                inverter = PoseInverter(layer, replace(PRESETS[preset], corrective_rounds=rounds))
                errs, t = [], time.perf_counter()
                for c in coeffs:
                    prepared = layer.prepare_identity(c[None])
                    target = layer.pose(prepared, poses, correctives=corr).vertices
                    res = inverter.invert(target.contiguous(), prepared)
                    again = layer.pose(prepared, res.rotations, transl=res.transl, correctives=corr).vertices
                    errs.append((again - target).norm(dim=-1) * 1e3)
                rate = len(coeffs) * len(poses) / (time.perf_counter() - t)
                e = torch.stack(errs)
                tag = "with" if corr else "without"
                print(f"inversion {preset:8s} {name:15s} meshes {tag:7s} correctives, corrective_rounds {rounds}, "
                      f"re-posed {tag} them: mean {e.mean():.2f} mm, P95 {e.quantile(0.95):.2f} mm, "
                      f"max {e.max():.1f} mm; {rate:.0f} meshes/s")  # fmt: skip


def quality(layer: BodyLayer, twist: BodyLayer, args: argparse.Namespace) -> None:
    """The stress-pose table: ``layer`` (plain rig) and ``twist`` (procedural twist), both with correctives."""
    measures = SurfaceMeasures.from_layer(layer)
    meta = layer.correctives.meta
    volume, contact = bool(meta.get("teacher_volume", False)), bool(meta.get("teacher_contact", False))
    anchor = float(meta.get("teacher_anchor", 0.0))  # weights before 2026-11-28's anchored teacher: none
    setup = TeacherSetup(layer, volume=volume, contact=contact, anchor=anchor)
    # Flesh one bone carries (weight >= 0.99) inside the relaxed region: how far each method moves it off
    # where its rig's skinning puts it (LBS: 0 by construction; "MLP + twist" against "LBS + twist").
    carried = torch.from_numpy(one_bone(measures.weights) & setup.free)
    drift, skinned = {m: [] for m in METHODS[2:]}, {}
    coeffs = draw_identities(layer, args.identities, keyed_generator("correctives-benchmark", args.seed))
    poses, labels = stress_poses(keyed_generator("correctives-stress", args.seed))
    acc = {m: {"strain": [], "dihedral": [], "volume": [], "isect": [], "section": []} for m in METHODS}
    fit = {"MLP": [], "MLP + twist": []}
    t0 = time.perf_counter()
    for n, c in enumerate(coeffs):
        prepared = layer.prepare_identity(c[None])
        _, teacher, _ = teacher_targets(layer, prepared, poses, setup, iterations=args.teacher_iterations)
        tw_pose = forearm_twist_pose(150.0)
        _, tw_teacher, _ = teacher_targets(layer, prepared, tw_pose, setup, iterations=args.teacher_iterations)
        for m in METHODS:
            lay = twist if "twist" in m else layer
            corr = m.startswith("MLP")
            out = lay.pose(prepared, poses, correctives=corr)
            verts = teacher.float() if m == "teacher" else out.vertices
            if m.startswith("LBS"):  # METHODS lists both skinnings first
                skinned[m] = out.vertices
            else:
                lbs = skinned["LBS + twist" if "twist" in m else "LBS"]
                drift[m].append((verts - lbs)[:, carried].norm(dim=-1).mean(-1) * 1e3)
            s, a = measures.distortion(prepared.rest_vertices, verts)
            acc[m]["strain"].append(s.flatten())
            acc[m]["dihedral"].append(a.flatten())
            vol = measures.segment_volumes(
                prepared.rest_vertices, prepared.rest_rotations, prepared.rest_joints, verts, out.transforms
            )
            acc[m]["volume"].append(vol)
            if n < args.intersect_identities:
                acc[m]["isect"].append(measures.self_intersections(verts))
            tw = lay.pose(prepared, tw_pose, correctives=corr)
            tv = tw_teacher[0].numpy() if m == "teacher" else tw.vertices[0].double().numpy()
            acc[m]["section"].append(forearm_min_section(
                measures, prepared.rest_vertices[0].double().numpy(), prepared.rest_joints[0].double().numpy(), tv,
                tw.joints[0].double().numpy()))  # fmt: skip
            if m.startswith("MLP"):
                fit[m].append((out.vertices.double() - teacher).norm(dim=-1))
        done = time.perf_counter() - t0
        print(
            f"  identity {n + 1}/{len(coeffs)} ({done:.0f} s, ETA {done / (n + 1) * (len(coeffs) - n - 1):.0f} s)",
            flush=True,
        )
    print(f"\n{len(poses)} stress poses x {len(coeffs)} held-out identities (native PCA, stature 1.0-1.95 m); "
          f"self-intersections over the first {min(args.intersect_identities, len(coeffs))} identities")  # fmt: skip
    head = f"{'method':12s} | {'strain mean':>11s} {'P95':>6s} | {'dihedral mean':>13s} {'P95':>6s} | "
    head += f"{'volume mean':>11s} {'min':>6s} | {'isect pairs/mesh':>16s} | {'forearm 150 min section':>23s}"
    print(head)
    base = {}
    for m in METHODS:
        s, a = torch.cat(acc[m]["strain"]), torch.cat(acc[m]["dihedral"])
        vol = torch.cat(acc[m]["volume"])
        isect = np.concatenate(acc[m]["isect"]) if acc[m]["isect"] else np.zeros(1)
        sec = np.array(acc[m]["section"])
        row = (float(s.mean()), float(s.quantile(0.95)), float(a.mean()), float(a.quantile(0.95)), float(vol.mean()),
               float(vol.min()), float(isect.mean()), float(sec.min()))  # fmt: skip
        base.setdefault("LBS", row)
        print(f"{m:12s} | {row[0]:11.4f} {row[1]:6.4f} | {np.degrees(row[2]):11.2f} ° {np.degrees(row[3]):5.1f}° | "
              f"{row[4]:11.1%} {row[5]:6.1%} | {row[6]:16.1f} | {row[7]:23.1%}")  # fmt: skip
    print("\nreduction vs LBS (1 - method / LBS): strain mean, dihedral mean, intersections")
    lbs = base["LBS"]
    for m in METHODS[1:]:
        s, a = torch.cat(acc[m]["strain"]), torch.cat(acc[m]["dihedral"])
        isect = np.concatenate(acc[m]["isect"]) if acc[m]["isect"] else np.zeros(1)
        print(f"  {m:12s} strain {1 - float(s.mean()) / lbs[0]:+.0%}, dihedral {1 - float(a.mean()) / lbs[2]:+.0%}, "
              f"intersections {1 - float(isect.mean()) / max(lbs[6], 1e-9):+.0%}")  # fmt: skip
    print("\nsegment volumes under 90 % of rest (share of segment instances; the smallest: segment, pose, identity)")
    for m in METHODS:
        vol = torch.stack(acc[m]["volume"])  # (identities, poses, segments)
        i, p, k = np.unravel_index(int(vol.argmin()), tuple(vol.shape))
        print(f"  {m:12s} {float((vol < 0.9).float().mean()):6.2%}; {float(vol.min()):.1%} {SEGMENTS[k][0]}, "
              f"{labels[p]}, identity {i}")  # fmt: skip
    print(
        f"\none-bone flesh moved off its bone ({int(carried.sum())} vertices of the relaxed region with a "
        "skinning weight >= 0.99; mean |x - the rig's LBS| per mesh), mm: mean / P95 / max over meshes"
    )
    for m, d in drift.items():
        d = torch.cat(d)
        print(f"  {m:12s} {float(d.mean()):.1f} / {float(d.quantile(0.95)):.1f} / {float(d.max()):.1f}")
    print(f"\nteacher: {args.teacher_iterations} ARAP iterations, volume {'on' if volume else 'off'}, "
          f"contact {'on' if contact else 'off'}, anchor {anchor:g}")  # fmt: skip
    for m, errs in fit.items():
        err = torch.stack(errs) * 1e3  # (identities, poses, V)
        print(f"{m} vs teacher on the stress poses: mean {err.mean():.2f} mm, per-mesh max mean "
              f"{err.amax(-1).mean():.1f} mm, max {err.max():.1f} mm")  # fmt: skip


if __name__ == "__main__":
    main()
