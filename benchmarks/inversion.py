"""Pose-inversion accuracy, speed and temporal stability (paper 000 §4.2, Tables 2-3, Fig. 10).

Protocols (all data generated from seeds; nothing here is used for training):
  random   the py-soma-x protocol: random poses, 0.3 rad std axis-angle on every joint,
           0.1 m translation std; one Anny identity per batch of 64.
  smooth   a seeded smooth motion generator: per joint a sum of three sinusoids
           (0.1-0.5 Hz, 30 fps) with amplitude 0.35 rad (fingers 0.2), over --identities
           Anny identities x --frames frames each.
For each method: mean / median / max per-vertex error (mm) against the BodyLayer mesh that
produced the target, per region (body, hands, feet, head), and frames/s at batch 64.
Cross-model (Table 2/3 analogue): Anny posed by its own 104-bone rig and skinning on its
native 13,718-vertex mesh (smooth random local rotations about Anny's reference pose,
0.25 rad amplitude, 0.1 for fingers, toes, face), given to the inverter on Anny's topology:
it is transferred to the canonical mesh and inverted; errors are against that transfer.
Two bone sets (--cross-bones): "all" moves every Anny bone, including ones the canonical rig
lacks; "mapped" moves only the Anny bones with a canonical counterpart (head within
--cross-max-dist of a fitted canonical joint and the same skinned subtree, one-to-one; see
counterpart_map, printed with the table), the rest keep Anny's reference pose.
Temporal: on one smooth sequence of --stability-frames frames, the mean frame-to-frame
change of the shoulder-region error (SVD vs Newton-Schulz) and the largest frame-to-frame
rotation change of any observable joint, against that of the ground-truth motion.

    python benchmarks/inversion.py [--identities 20] [--frames 100] [--stability-frames 2000]
    python benchmarks/inversion.py --sections cross [--cross-bones all mapped] [--cross-max-dist 0.04]
"""

from __future__ import annotations

import argparse
import math
import textwrap
import time

import torch

from unibody import BodyLayer, Rig
from unibody.fitting.inversion import InversionConfig, PoseInverter
from unibody.geometry.rotations import axis_angle_to_matrix, rotation_angle
from unibody.regions import REGIONS, dominant_joints, vertex_regions

METHODS = {
    "skeleton transfer": InversionConfig(method="skeleton"),
    "skeleton transfer, pose only": InversionConfig(method="skeleton", residuals=False),
    "analytic (Newton-Schulz)": InversionConfig(),
    "analytic (SVD)": InversionConfig(orthogonalization="svd"),
    "analytic + Gauss-Newton (3)": InversionConfig(gauss_newton_steps=3),
    "analytic + autograd (30)": InversionConfig(method="autograd", init="analytic", steps=30),
    "autograd, no init (30)": InversionConfig(method="autograd", init="none", steps=30),
}


def smooth_motion(frames: int, gen: torch.Generator, finger: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """(T, 77, 3) smooth poses and (T, 3) translations at 30 fps."""
    t = torch.arange(frames, dtype=torch.float64)[:, None, None, None] / 30.0
    freq = 0.1 + 0.4 * torch.rand(1, 77, 3, 3, generator=gen, dtype=torch.float64)
    phase = 2 * math.pi * torch.rand(1, 77, 3, 3, generator=gen, dtype=torch.float64)
    amp = torch.where(finger[None, :, None, None], 0.2, 0.35) / math.sqrt(3)
    pose = (amp * torch.sin(2 * math.pi * freq * t + phase)).sum(-1)
    transl = 0.1 * torch.sin(2 * math.pi * 0.3 * t[:, 0, 0] + torch.tensor([0.0, 1.0, 2.0], dtype=torch.float64))
    return pose, transl


def run(layer, inverter, prepared, target, batch: int = 64):
    """Invert in batches; returns (errors (T, V) m, result poses (T, 77, 3, 3), seconds)."""
    errs, rots, seconds = [], [], 0.0
    grad = inverter.config.method == "autograd"
    for s in range(0, len(target), batch):
        t0 = time.perf_counter()
        with torch.set_grad_enabled(grad):
            r = inverter.invert(target[s : s + batch], prepared)
        seconds += time.perf_counter() - t0
        if r.per_vertex_error is None:  # pose only: the error is measured outside the timing
            with torch.no_grad():
                posed = layer.pose(prepared, r.pose.detach(), transl=r.transl.detach()).vertices
            errs.append((posed - target[s : s + batch]).norm(dim=-1))
        else:
            errs.append(r.per_vertex_error.detach())
        rots.append(r.rotations.detach())
    return torch.cat(errs), torch.cat(rots), seconds


def evaluate(layer, data, regions) -> None:
    """Report every method over ``data``: a list of (prepared identity, target meshes)."""
    for name, cfg in METHODS.items():
        inverter = PoseInverter(layer, cfg)
        errs, sec = [], 0.0
        for prepared, target in data:
            err, _, s = run(layer, inverter, prepared, target)
            errs.append(err)
            sec += s
        report(name, torch.cat(errs), sec, regions)


def report(name: str, err: torch.Tensor, seconds: float, regions: torch.Tensor) -> None:
    e = 1e3 * err
    per_region = "  ".join(f"{REGIONS[k]} {e[:, regions == k].mean():.2f}" for k in range(len(REGIONS)))
    print(f"| {name} | {e.mean():.2f} | {e.median():.2f} | {e.max():.1f} | {len(e) / seconds:,.0f} | {per_region} |")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--identities", type=int, default=20)
    parser.add_argument("--frames", type=int, default=100)
    parser.add_argument("--random-frames", type=int, default=512)
    parser.add_argument("--stability-frames", type=int, default=2000)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument("--cross-frames", type=int, default=100)
    parser.add_argument("--cross-bones", nargs="+", choices=["all", "mapped"], default=["all", "mapped"])
    parser.add_argument("--cross-max-dist", type=float, default=0.04, help="mapped: head distance limit, m")
    parser.add_argument("--cross-min-overlap", type=float, default=0.5, help="mapped: subtree skin overlap")
    parser.add_argument("--sections", nargs="+", default=["random", "smooth", "cross", "stability"])
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    layer = BodyLayer.from_anny()
    regions = vertex_regions(Rig.canonical())
    finger = torch.tensor(["Hand" in n and not n.endswith("Hand") for n in layer.joint_names[1:]])
    gen = torch.Generator().manual_seed(args.seed)
    header = "| method | mean mm | median mm | max mm | frames/s | per region mean mm |\n|---|---:|---:|---:|---:|---|"

    if "random" in args.sections:
        random_protocol(layer, regions, gen, args, header)
    if "smooth" in args.sections:
        smooth_protocol(layer, regions, finger, gen, args, header)
    if "cross" in args.sections:
        cross_model(layer, regions, gen, args, header)
    if "stability" in args.sections:
        stability(layer, finger, gen, args)


def random_protocol(layer, regions, gen, args, header) -> None:
    """py-soma-x's protocol: random poses, 0.3 rad std, 0.1 m translation std."""
    params = torch.rand(1, 6, generator=gen)
    prepared = layer.prepare_identity(params)
    pose = 0.3 * torch.randn(args.random_frames, 77, 3, generator=gen)
    transl = 0.1 * torch.randn(args.random_frames, 3, generator=gen)
    with torch.no_grad():
        target = layer.pose(prepared, pose, transl=transl).vertices
    print(f"## random protocol: {args.random_frames} frames, 0.3 rad std, one identity, batch 64\n{header}")
    for name, cfg in METHODS.items():
        err, _, sec = run(layer, PoseInverter(layer, cfg), prepared, target)
        report(name, err, sec, regions)


def smooth_protocol(layer, regions, finger, gen, args, header) -> None:
    """Smooth seeded motions over many identities."""
    print(f"\n## smooth motions: {args.identities} identities x {args.frames} frames, batch 64\n{header}")
    data = []
    for _ in range(args.identities):
        prepared = layer.prepare_identity(torch.rand(1, 6, generator=gen))
        pose, transl = smooth_motion(args.frames, gen, finger)
        with torch.no_grad():
            data.append((prepared, layer.pose(prepared, pose.float(), transl=transl.float()).vertices))
    evaluate(layer, data, regions)


def subtree_sums(weights: torch.Tensor, parents: list[int]) -> torch.Tensor:
    """(V, B) skinning weights -> each bone's weight plus its descendants' (parents precede children)."""
    out = weights.clone()
    for b in range(len(parents) - 1, 0, -1):
        if parents[b] >= 0:
            out[:, parents[b]] += out[:, b]
    return out


def counterpart_map(layer, params: torch.Tensor, max_dist: float, min_overlap: float) -> dict[int, tuple]:
    """Anny bone -> (canonical joint, head distance m, subtree skin overlap), decided from data.

    For one identity: Anny's rest bone heads (unibody axes) against the canonical joints the
    layer fits to the same mesh, and the weighted Jaccard overlap of the vertices each one
    moves (skinning weights summed over its subtree; Anny's carried to the canonical mesh).
    A pair qualifies when the heads lie within ``max_dist`` and the overlap is at least
    ``min_overlap``; only canonical joints that skin vertices (observable) are candidates. A
    pair that moves every vertex (Anny's root and the Hips) is a rigid motion, representable
    about any pivot (the translation absorbs the offset), so it is exempt from the distance
    test. Pairs are then taken one-to-one, the rigid pair first and the rest in order of head
    distance, so an Anny chain facing one canonical joint keeps only its closest bone.
    """
    model = layer.identity.model
    n = len(model.bone_labels)
    with torch.no_grad():
        out = model(pose_parameters=torch.eye(4).repeat(1, n, 1, 1), phenotype_kwargs=params)
        h = out["rest_bone_heads"][0].double()
        heads = torch.stack([h[:, 0], h[:, 2], -h[:, 1]], -1)
        dist = torch.cdist(heads, layer.prepare_identity(params).rest_joints[0].double())
    idx, w = model.vertex_bone_indices, model.vertex_bone_weights.double()
    anny = subtree_sums(torch.zeros(idx.shape[0], n, dtype=torch.float64).scatter_add_(1, idx, w), model.bone_parents)
    topo = layer.topology
    bary = topo.weights[:, :3].double().clamp(min=0)
    anny = (anny[topo.face_vertices] * (bary / bary.sum(1, keepdim=True))[..., None]).sum(1)
    rig = Rig.canonical()
    canon = subtree_sums(rig.dense_skinning_weights().double(), list(rig.tree.parents))
    jaccard = [torch.minimum(a[:, None], canon).sum(0) / torch.maximum(a[:, None], canon).sum(0) for a in anny.T]
    overlap = torch.stack(jaccard)  # (bones, joints) weighted Jaccard
    rigid = (anny.min(0).values > 0.999)[:, None] & (canon.min(0).values > 0.999)[None, :]
    observable = torch.cat([torch.zeros(1, dtype=torch.bool), PoseInverter(layer).observable.cpu()])
    ok = ((dist <= max_dist) | rigid) & (overlap >= min_overlap) & observable[None, :]
    pairs: dict[int, tuple] = {}
    taken: set[int] = set()
    for a, c in sorted(ok.nonzero().tolist(), key=lambda ac: (not rigid[ac[0], ac[1]], float(dist[ac[0], ac[1]]))):
        if a not in pairs and c not in taken:
            pairs[a] = (c, float(dist[a, c]), float(overlap[a, c]))
            taken.add(c)
    return pairs


def print_map(labels: list[str], names: tuple[str, ...], pairs: dict[int, tuple], max_dist: float) -> None:
    rows = [f"{labels[a]}->{names[c]} {100 * d:.1f} cm {o:.2f}" for a, (c, d, o) in sorted(pairs.items())]
    near = max((d for c, d, o in pairs.values() if d <= max_dist), default=0.0)
    print(
        f"counterpart map ({len(pairs)} of {len(labels)} Anny bones animated; Anny bone -> canonical joint, "
        f"head distance, subtree skin overlap; max distance {100 * near:.2f} cm, rigid root pair exempt):"
    )
    print(textwrap.fill(", ".join(rows), 110, initial_indent="  ", subsequent_indent="  "))
    frozen = [n for i, n in enumerate(labels) if i not in pairs]
    print(textwrap.fill("frozen: " + ", ".join(frozen), 110, initial_indent="  ", subsequent_indent="  "))


def cross_model(layer, regions, gen, args, header) -> None:
    """Anny's native rig and skinning -> Anny topology -> canonical -> inversion.

    ``--cross-bones all``: every Anny bone moves. ``mapped``: only the bones of
    :func:`counterpart_map` (for the mid identity) move, the rest keep Anny's reference pose.
    Both draw the same identities and sinusoids (the generator is rewound), so they pair up.
    """
    model = layer.identity.model
    labels = list(model.bone_labels)
    small = ("finger", "toe", "thumb", "eye", "tongue", "jaw", "metacarpal", "special", "breast")
    amp = torch.tensor([0.1 if any(k in n.lower() for k in small) else 0.25 for n in labels], dtype=torch.float64)
    frames = args.cross_frames
    n_id = max(1, args.identities // 4)
    start = gen.get_state()
    for bones in args.cross_bones:
        gen.set_state(start)
        scale = amp
        if bones == "mapped":
            pairs = counterpart_map(layer, torch.full((1, 6), 0.5), args.cross_max_dist, args.cross_min_overlap)
            scale = amp * torch.isin(torch.arange(len(labels)), torch.tensor(list(pairs)))
        print(f"\n## cross-model ({bones} bones): Anny native rig, {n_id} identities x {frames} frames, batch 64")
        if bones == "mapped":
            print_map(labels, layer.joint_names, pairs, args.cross_max_dist)
        print(header)
        data = []
        for _ in range(n_id):
            params = torch.rand(1, 6, generator=gen)
            t = torch.arange(frames, dtype=torch.float64)[:, None, None, None] / 30.0
            freq = 0.1 + 0.4 * torch.rand(1, len(labels), 3, 3, generator=gen, dtype=torch.float64)
            phase = 2 * math.pi * torch.rand(1, len(labels), 3, 3, generator=gen, dtype=torch.float64)
            aa = (scale[None, :, None, None] / math.sqrt(3) * torch.sin(2 * math.pi * freq * t + phase)).sum(-1)
            delta = torch.eye(4, dtype=torch.float64).repeat(frames, len(labels), 1, 1)
            delta[..., :3, :3] = axis_angle_to_matrix(aa)
            with torch.no_grad():
                native = model.double()(pose_parameters=delta, phenotype_kwargs=params.double())["vertices"]
                model.float()
                native = torch.stack([native[..., 0], native[..., 2], -native[..., 1]], -1).float()
                data.append((layer.prepare_identity(params), native))
        evaluate(layer, data, regions)


def stability(layer, finger, gen, args) -> None:
    """Frame-to-frame behaviour on one long smooth sequence."""
    prepared = layer.prepare_identity(torch.rand(1, 6, generator=gen))
    pose, transl = smooth_motion(args.stability_frames, gen, finger)
    with torch.no_grad():
        target = layer.pose(prepared, pose.float(), transl=transl.float()).vertices
    truth = axis_angle_to_matrix(pose.float())
    step_truth = rotation_angle(truth[1:].transpose(-1, -2) @ truth[:-1])
    shoulder = torch.tensor([layer.joint_names.index(n) for n in ("LeftShoulder", "RightShoulder")])
    dominant = dominant_joints(
        layer.skinning.vertex, layer.skinning.joint, layer.skinning.weight, layer.num_vertices, layer.num_joints
    )
    shoulder_v = torch.isin(dominant, shoulder)
    observable = PoseInverter(layer).observable
    print(f"\n## temporal stability: {args.stability_frames} smooth frames, one identity")
    print("| method | shoulder error change mm/frame | max joint jump deg/frame (truth) |\n|---|---:|---:|")
    variants = {
        "analytic (SVD), no damping": InversionConfig(orthogonalization="svd", damping=0.0),
        "analytic (Newton-Schulz), no damping": InversionConfig(damping=0.0, ns_iters=30),
        "analytic (SVD)": METHODS["analytic (SVD)"],
        "analytic (Newton-Schulz)": METHODS["analytic (Newton-Schulz)"],
    }
    for name, cfg in variants.items():
        err, rots, _ = run(layer, PoseInverter(layer, cfg), prepared, target)
        e = 1e3 * err[:, shoulder_v].mean(1)
        jump = rotation_angle(rots[1:].transpose(-1, -2) @ rots[:-1])[:, observable]
        deg = 180 / math.pi
        print(
            f"| {name} | {(e[1:] - e[:-1]).abs().mean():.3f} | {deg * jump.max():.2f} "
            f"({deg * step_truth[:, observable].max():.2f}) |"
        )


if __name__ == "__main__":
    main()
