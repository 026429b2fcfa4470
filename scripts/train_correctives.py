"""Train the pose correctives (issue 40, paper 000 §3.5.2) from the as-rigid-as-possible teacher.

Two resumable stages, both on one thread by default:

1. ``generate``: draws identities of the native PCA (children to adults) and poses (the seeded
   generator with deep bends plus randomised stress families and, with ``--motions DIR``, frames
   of real motions: the ``unibody.motion/1`` files under DIR, e.g. the CMU database converted by
   ``unibody convert ... --to motion``), poses each identity with LBS, relaxes it with the
   teacher and stores both rest-space targets in chunk files under ``--data`` (one per identity;
   existing chunks are kept, so a rerun resumes): ``d`` for the plain rig and ``d_twist`` for
   the procedural-twist rig (:func:`~unibody.correctives.training.twist_targets`).
2. ``train``: fits :class:`unibody.correctives.model.Correctives` (77 rest-relative joint
   rotations -> J x 24 activations -> sparse rest-space displacements) with AdamW on the
   ``--target`` (``plain``: ``correctives.pt``, ``twist``: ``correctives_twist.pt``),
   checkpointing to ``--data/checkpoint_<target>.pt`` (``--resume`` continues), and writes the
   shipped weights with the command, seed and data recipe (``--out``).

    OMP_NUM_THREADS=1 python scripts/train_correctives.py generate --identities 280 --poses 12 \
        --motions build/cmu_motions --data build/correctives-data
    OMP_NUM_THREADS=1 python scripts/train_correctives.py train --target plain --data build/correctives-data
    OMP_NUM_THREADS=1 python scripts/train_correctives.py train --target twist --data build/correctives-data
"""

from __future__ import annotations

import argparse
import functools
import math
import shlex
import sys
import time
from pathlib import Path

import numpy as np
import torch
from tqdm import tqdm

from unibody import BodyLayer
from unibody.correctives.metrics import SEGMENTS, SurfaceMeasures, cone_volume
from unibody.correctives.mirror import CorrectivesMirror, asymmetry, mirror_maps, symmetrize
from unibody.correctives.model import Correctives, default_weights_path
from unibody.correctives.stress import FAMILIES
from unibody.correctives.teacher import RELEASE
from unibody.correctives.training import (
    ANCHOR,
    TeacherSetup,
    blended_rotations,
    draw_identities,
    size_of,
    teacher_targets,
    twist_targets,
)
from unibody.geometry.rotations import axis_angle_to_matrix, matrix_to_axis_angle
from unibody.motion import load_motion
from unibody.rig import JOINT_NAMES
from unibody.synth.poses import keyed_generator, mirror_rotation, sample_poses


def draw_poses(n: int, generator: torch.Generator) -> torch.Tensor:
    """(n, 77, 3) training poses: half from the generator (deep bends and folds included), half
    stress families (:data:`~.stress.FAMILIES`, random side, amplitude U(0.2, 1.1)) on milder generator poses."""
    base = sample_poses(n, generator, bend=0.3, chamber=0.1, fold=0.15, together=0.1, arms_alike=0.1, fingers=False)
    mild = sample_poses(n, generator, min_amplitude=0.0, fingers=False)
    index = {name: i - 1 for i, name in enumerate(JOINT_NAMES)}
    fam = list(FAMILIES.values())
    for b in range(n // 2, n):
        base[b] = mild[b] * 0.5
        for _ in range(1 + int(torch.randint(3, (1,), generator=generator))):
            joints = fam[int(torch.randint(len(fam), (1,), generator=generator))]
            amp = 0.2 + 0.9 * float(torch.rand(1, generator=generator))
            right = bool(torch.rand(1, generator=generator) < 0.5)
            for name, v in joints.items():
                vec = amp * torch.tensor(v)
                if right:
                    name, vec = "Right" + name.removeprefix("Left"), mirror_rotation(vec)
                base[b, index[name]] = vec + 0.1 * torch.randn(3, generator=generator)
    return base


FINGERS = [i - 1 for i, n in enumerate(JOINT_NAMES) if "Hand" in n and not n.endswith("Hand")]
"""Pose rows (joints 1..77) of the finger joints: straight (0, as in the T-pose) in every training pose."""


def rest_pose(layer: BodyLayer, prepared) -> torch.Tensor:  # noqa: ANN001 (a PreparedIdentity)
    """(77, 3) the rest pose of a prepared identity (its first), T-pose-relative axis-angle: posed
    with it, the identity gives its rest mesh back."""
    rot = prepared.rest_rotations[0]
    return matrix_to_axis_angle(layer.to_relative(rot[layer.parents[1:]].transpose(-1, -2) @ rot[1:]))


def calm_poses(rest: torch.Tensor, n: int, generator: torch.Generator) -> torch.Tensor:
    """(n, 77, 3) display poses between the T-pose and the identity's own rest pose: each joint at
    t times its rest-pose rotation (t ~ U(0, 1) per pose, one t for the whole body), then turned
    U(0, 0.2) rad about a uniform axis; fingers straight.

    Why: the T-pose (arms out, elbows straight) and the poses on the way to the rest A-pose are
    where users look at bodies, and where an Anny body, whose rest elbows are bent 34 degrees (the
    native-PCA bodies' 25), sits outside what the generator and the motions reach. The correctives
    trained without them shrank Anny's forearms to 83-96 % of their rest volume at the T-pose,
    where LBS keeps 99-101 %.

    Args:
        rest: (77, 3) the identity's rest pose, T-pose-relative axis-angle (joints 1..77).
    """
    t = torch.rand(n, 1, 1, generator=generator, dtype=rest.dtype)
    axis = torch.nn.functional.normalize(torch.randn(n, 77, 3, generator=generator, dtype=rest.dtype), dim=-1)
    angle = 0.2 * torch.rand(n, 77, 1, generator=generator, dtype=rest.dtype)
    rot = axis_angle_to_matrix(axis * angle) @ axis_angle_to_matrix(t * rest)
    out = matrix_to_axis_angle(rot)
    out[:, FINGERS] = 0.0
    return out


def load_motions(root: Path) -> list[tuple[str, torch.Tensor]]:
    """Every ``*.motion.npz`` under ``root`` (sorted), read by :func:`unibody.motion.load_motion`:
    (path relative to root, (T, 77, 3) T-pose-relative axis-angle poses)."""
    files = sorted(Path(root).rglob("*.motion.npz"))
    if not files:
        raise SystemExit(f"--motions: no *.motion.npz files under {root} (unibody convert ... --to motion)")
    return [(str(f.relative_to(root)), torch.from_numpy(load_motion(f).pose)) for f in files]


def motion_frames(
    n: int, generator: torch.Generator, motions: list[tuple[str, torch.Tensor]]
) -> tuple[torch.Tensor, list[str]]:
    """(n, 77, 3) frames of uniformly drawn motions (a uniform frame of each), fingers straight,
    and their sources ``"file:frame"``. The Hips rotation is kept (the teacher and the targets
    do not depend on it); the root translation is not used."""
    poses, sources = [], []
    for _ in range(n):
        name, pose = motions[int(torch.randint(len(motions), (1,), generator=generator))]
        f = int(torch.randint(len(pose), (1,), generator=generator))
        poses.append(pose[f].clone())
        sources.append(f"{name}:{f}")
    out = torch.stack(poses) if poses else torch.zeros(0, 77, 3)
    out[:, FINGERS] = 0.0
    return out, sources


def generate(args: argparse.Namespace) -> None:
    data = Path(args.data)
    data.mkdir(parents=True, exist_ok=True)
    layer = _backend_layer(args.backend, torch.float32)
    setup = TeacherSetup(layer, volume=args.volume, contact=args.contact, anchor=args.anchor)
    if args.backend == "anny":  # phenotypes uniform in [0, 1]: babies to the elderly, every build
        gen = keyed_generator("correctives-identities-anny", args.seed)
        coeffs = torch.rand(args.identities, layer.identity.num_params, generator=gen)
    else:
        coeffs = draw_identities(layer, args.identities, keyed_generator("correctives-identities", args.seed))
    name = "chunk_anny_{:05d}" if args.backend == "anny" else "chunk_{:05d}"
    calm = round(args.poses * args.calm_share)
    if calm:  # their own family: its chunks are named apart and hold out their own 5 %
        name = name.replace("chunk_", "chunk_calm_")
    motions = load_motions(Path(args.motions)) if args.motions else []
    k = min(round(args.poses * args.motion_share), args.poses - calm) if motions else 0
    part, parts = args.shard
    todo = [i for i in range(part, args.identities, parts) if not (data / f"{name.format(i)}.pt").exists()]
    print(f"teacher region: {len(setup.union)} vertices; {len(todo)} of {args.identities} identities to do; "
          f"{k} of {args.poses} poses from {len(motions)} motions, {calm} calm")  # fmt: skip
    for i in tqdm(todo, desc="teacher", unit="identity", smoothing=0.1):
        prepared = layer.prepare_identity(coeffs[i : i + 1])
        pose = draw_poses(args.poses - k - calm, keyed_generator("correctives-poses", args.seed, i))
        frames, sources = motion_frames(k, keyed_generator("correctives-motion-frames", args.seed, i), motions)
        if calm:
            gen = keyed_generator("correctives-calm-poses", args.seed, i)
            still = calm_poses(rest_pose(layer, prepared), calm, gen)
            pose = torch.cat([pose, frames, still])
        else:
            pose = torch.cat([pose, frames])
        _, teacher, d = teacher_targets(layer, prepared, pose, setup, iterations=args.iterations)
        d_twist = twist_targets(prepared, pose, teacher, setup)
        rel = Correctives.rest_relative(layer.local_rotations(pose), prepared.rest_rotations, layer.parents)
        chunk = {
            "rel": rel.float(),
            "d": d.float(),
            "d_twist": d_twist.float(),
            "size": size_of(prepared.rest_joints).float(),
            "coeffs": coeffs[i],
            "backend": args.backend,
            "sources": ["draw_poses"] * (args.poses - k - calm) + sources + ["calm_poses"] * calm,
            "family": "calm" if calm else "",
            "recipe": {
                "seed": args.seed,
                "iterations": args.iterations,
                "volume": args.volume,
                "contact": args.contact,
                "anchor": args.anchor,
                "motions": str(args.motions or ""),
                "motion_files": len(motions),
                "motion_frames": sum(len(p) for _, p in motions),
                "calm_share": args.calm_share,
            },
        }
        tmp = data / f"{name.format(i)}.tmp"
        torch.save(chunk, tmp)
        tmp.rename(data / f"{name.format(i)}.pt")


def build_model(
    layer: BodyLayer, setup: TeacherSetup, size_ref: float, meta: dict, hidden: int, shape: bool = False
) -> Correctives:
    """Active joints: the stressed ones; inputs: the joint, its parent, its children (not Hips/Root);
    with ``shape``, the identity's build too (the limb segments of :data:`SEGMENTS`, each its
    vertices of dominant weight; feature statistics 0 / 1 until :func:`_shape_inputs` sets them)."""
    names, parents = layer.joint_names, setup.parents.tolist()
    rows, verts = [], []
    for name, mask in setup.masks.items():
        k = names.index(name)
        group = [k, parents[k]] + [c for c in range(len(names)) if parents[c] == k and c != k]
        group = [j for j in group if j > 1]
        rows.append(group)
        verts.append(torch.from_numpy(mask.nonzero()[0]))
    width = max(len(r) for r in rows)
    inputs = torch.tensor([r + [-1] * (width - len(r)) for r in rows])
    spec = None
    if shape:  # the measures' limb segments, each the vertices its joint dominates
        measures = SurfaceMeasures.from_layer(layer)
        dominant = torch.from_numpy(measures.weights.argmax(1))
        pairs = list(measures.segment_joints)
        n = len(pairs) + 1
        spec = {
            "joints": pairs,
            "vertices": [torch.nonzero(dominant == a).flatten() for a, _ in pairs],
            "mean": torch.zeros(n),
            "std": torch.ones(n),
        }
    return Correctives(
        inputs,
        verts,
        layer.num_vertices,
        hidden=hidden,
        size_ref=size_ref,
        joint_names=tuple(setup.masks),
        meta=meta,
        shape=spec,
    )


def _load_init(model: Correctives, path: str) -> Correctives:
    """Copy the parameters of the weights at ``path`` into ``model`` (same structure); a pose-only
    start of a model with identity inputs gives those inputs zero weights, so the model starts as
    the same function. Returns the loaded weights."""
    init = Correctives.load(path)
    with torch.no_grad():
        for name, param in model.named_parameters():
            src = getattr(init, name)
            pose_only = name == "w1" and src.shape[:2] == param.shape[:2]
            if pose_only and model.num_shape and src.shape[2] + model.num_shape == param.shape[2]:
                param.zero_()[..., : src.shape[2]] = src
            elif src.shape != param.shape:
                raise SystemExit(
                    f"--init: {path} has {name} of shape {tuple(src.shape)}, expected {tuple(param.shape)}"
                )
            else:
                param.copy_(src)
    return init


def _shape_inputs(
    model: Correctives, layer: BodyLayer, chunks: list[dict], held: int, stats: tuple | None = None
) -> torch.Tensor:
    """(N samples, S + 1) the raw identity features of every sample of the chunks (standardise them
    with the model's statistics); first sets those statistics: ``stats`` = (mean, std), those of
    the weights a fine-tune starts from (so it starts as their function, whatever its data), or
    else from the training chunks (all but the last ``held``)."""
    with torch.no_grad():
        raw = []
        for c in chunks:
            p = _prepare(c, layer.tpose_orient.dtype)
            raw.append(model.shape_features(p.rest_vertices, p.rest_joints))
        raw = torch.cat(raw)  # statistics 0 / 1: the raw features
        mean, std = (raw[:-held].mean(0), raw[:-held].std(0)) if stats is None else stats
        model.shape_mean.copy_(mean)
        model.shape_std.copy_(std)
    return torch.repeat_interleave(raw, torch.tensor([len(c["rel"]) for c in chunks]), 0)


def _mirror_side(model: Correctives, maps: CorrectivesMirror, val: tuple, raw: torch.Tensor | None) -> str:
    """Symmetrize ``model`` in place from the side whose mirror image scores better on the held-out
    samples ``val`` = (rel, size, d) (rest-space error; ``raw``: every sample's raw identity
    features, the held-out ones last, or None); returns that side ("Left" or "Right")."""
    v_rel, v_size, v_d = val
    state = {k: v.clone() for k, v in model.state_dict().items()}
    scores = {}
    for keep in ("Left", "Right"):
        model.load_state_dict(state)
        symmetrize(model, maps, keep)
        v_shp = None if raw is None else ((raw - model.shape_mean) / model.shape_std)[-len(v_rel) :]
        with torch.no_grad():
            err = (model.union_displacements(v_rel, v_size, v_shp) - v_d).norm(dim=-1)
        scores[keep] = float(err.mean()) * 1e3
    keep = min(scores, key=scores.get)
    left, right = scores["Left"], scores["Right"]
    print(f"mirror: held-out rest-space error {left:.2f} mm from the left, {right:.2f} mm from the right")
    model.load_state_dict(state)
    symmetrize(model, maps, keep)
    return keep


def _validate(
    model: Correctives,
    rel: torch.Tensor,
    size: torch.Tensor,
    d: torch.Tensor,
    best: dict,
    edges: torch.Tensor,
    ew: float,
    blend: torch.Tensor | None = None,
    posed: float = 0.0,
    volume: tuple[float, dict, torch.Tensor] | None = None,
    shape: torch.Tensor | None = None,
) -> dict:
    """Held-out score (mm): mean error, plus ``sqrt(ew)`` x the mean error of the edge differences
    when the edge loss is on (the training objective's terms), rest-space and posed (``blend``
    (N, U, 3, 3) applied) mixed by ``posed`` as the loss mixes them, plus ``1e3 sqrt(vw x the
    volume loss)`` with ``volume = (vw, segment data, the held-out samples' ids in it)``; ``shape``:
    the samples' identity inputs (a model built with them); the best state so far."""

    def score(err: torch.Tensor) -> float:
        mm = float(err.norm(dim=-1).mean()) * 1e3
        if ew:
            mm += ew**0.5 * float((err[:, edges[:, 0]] - err[:, edges[:, 1]]).norm(dim=-1).mean()) * 1e3
        return mm

    with torch.no_grad():
        pred = model.union_displacements(rel, size, shape)
        err = pred - d
        mm = (1 - posed) * score(err) if posed < 1 else 0.0
        if posed:
            mm += posed * score((blend @ err[..., None]).squeeze(-1))
        if volume is not None:
            vw, seg, ids = volume
            mm += 1e3 * (vw * float(_volume_loss(seg, ids, (blend @ pred[..., None]).squeeze(-1)))) ** 0.5
    if mm < best["mm"]:
        best = {"mm": mm, "state": {k: v.clone() for k, v in model.state_dict().items()}}
    return {**best, "last": mm}


def _recipe(chunks: list[dict], held: int, seed: int, target: str) -> str:
    """The data recipe of the chunks, for the weights' meta."""
    recipe = chunks[0].get("recipe", {"iterations": 6, "motions": "", "motion_files": 0, "motion_frames": 0})
    seed = recipe.get("seed", seed)  # the data's own seed (generate's), not the training run's
    sources = [s for c in chunks for s in c.get("sources", ["draw_poses"] * len(c["rel"]))]
    calm = sum(s == "calm_poses" for s in sources)
    sources = [s for s in sources if s != "calm_poses"]
    used = [s for s in sources if s != "draw_poses"]
    motions = ""
    if used:
        motions = (
            f" + {len(used)} frames ({len(set(used))} distinct) of {len({s.rsplit(':', 1)[0] for s in used})} of the "
            f"{recipe['motion_files']} motions ({recipe['motion_frames']} frames) under {recipe['motions']} "
            "(uniform motion, uniform frame, fingers straight; "
            f"keyed_generator('correctives-motion-frames', {seed}, i))"
        )
    volume = (
        ", each limb segment (upper arms, forearms, thighs, shins) held at its rest volume (cone from its bone "
        "midpoint; the constraint linearised in every global step)"
        if recipe.get("volume")
        else ""
    )
    if recipe.get("contact"):
        volume += (
            ", then self-contact resolved (free vertices inside another part pulled back along their normals, "
            "3 rounds x 4 iterations; teacher.Contact)"
        )
    if recipe.get("anchor"):
        volume += (
            f", flesh one bone carries tied to it (teacher.bone_anchors, strength {recipe['anchor']:g}; dropped "
            f"within {RELEASE} rings of vertices in contact)"
        )
    rig = "the procedural-twist rig (LBS + twist joints)" if target == "twist" else "plain LBS"
    main = [c for c in chunks if not c.get("family")] or chunks  # calm chunks alone: described as both
    anny = [c for c in main if c.get("backend") == "anny"]
    who = f"{len(main) - len(anny)} native-PCA identities (16 components N(0,1), stature U(1.0, 1.95) m, "
    who += f"keyed_generator('correctives-identities', {seed}))"
    if anny:
        aseed = anny[0].get("recipe", {}).get("seed", seed)
        who += (
            f" + {len(anny)} Anny identities (phenotypes U(0, 1), keyed_generator('correctives-identities-anny', "
            f"{aseed}); their poses keyed by that seed)"
        )
    who += f" x {len(main[0]['rel'])} poses each"
    if calm:  # the calm family: identities and poses of their own seeds
        parts = []
        for backend in ("pca", "anny"):
            cs = [c for c in chunks if c.get("family") == "calm" and c.get("backend", "pca") == backend]
            if cs:
                r = cs[0]["recipe"]
                key = "correctives-identities-anny" if backend == "anny" else "correctives-identities"
                parts.append(f"{len(cs)} {'Anny' if backend == 'anny' else 'native-PCA'} identities "
                             f"(keyed_generator('{key}', {r['seed']})) x {len(cs[0]['rel'])}")  # fmt: skip
        who += (
            f", then {calm} calm poses on " + " + ".join(parts) + " (calm_poses: every joint at t x its rest-pose "
            "rotation, t ~ U(0, 1), turned U(0, 0.2) rad; keyed_generator('correctives-calm-poses', seed, i))"
        )
    return (
        f"{who}, in all "
        f"{len(sources) - len(used)} from draw_poses (sample_poses with bend 0.3, chamber 0.1, fold 0.15 + "
        f"randomised stress families; keyed_generator('correctives-poses', {seed}, i)){motions}; teacher: "
        f"spokes-and-rims ARAP, {recipe['iterations']} iterations from LBS + procedural twist{volume}, joint "
        f"regions grown 5 rings (wrists and ankles: the whole forearm or shin), LBS boundary; targets: rest-space "
        f"displacements that {rig} maps onto the teacher; last {held} identities held out for validation"
    )


def _union_edges(setup: TeacherSetup) -> torch.Tensor:
    """(E, 2) the mesh edges with both ends among the masked vertices, as slots of ``setup.union``."""
    f = torch.from_numpy(setup.faces)
    e = torch.cat([f[:, [0, 1]], f[:, [1, 2]], f[:, [2, 0]]]).sort(1).values.unique(dim=0)
    slot = torch.full((int(f.max()) + 1,), -1, dtype=torch.int64)
    slot[setup.union] = torch.arange(len(setup.union))
    e = slot[e]
    return e[(e >= 0).all(1)]


def _chunks_key(chunks: list[dict]) -> list[float]:
    """A fingerprint of the chunks (their rotations and identities), for the caches below."""
    return [float(c["rel"].double().sum()) for c in chunks] + [float(c["coeffs"].double().sum()) for c in chunks]


@functools.cache
def _backend_layer(backend: str, dtype: torch.dtype) -> BodyLayer:
    """The identity backend whose coefficients a chunk holds (``pca`` or ``anny``), in ``dtype``.
    Every backend prepares identities on the canonical topology and rig, so any layer poses them."""
    layer = BodyLayer.from_anny() if backend == "anny" else BodyLayer.from_pca()
    return layer.to(dtype)


def _prepare(chunk: dict, dtype: torch.dtype):  # noqa: ANN202 (a PreparedIdentity)
    """A chunk's identity, prepared by its own backend (``chunk["backend"]``, native PCA by default)."""
    return _backend_layer(chunk.get("backend", "pca"), dtype).prepare_identity(chunk["coeffs"][None].to(dtype))


def _chunk_pose(layer: BodyLayer, chunk: dict) -> tuple:
    """A chunk's identity, prepared by its backend (float64), and its absolute local rotations
    (B, 77, 3, 3) on ``layer``'s rig."""
    p = _prepare(chunk, torch.float64)
    rr = p.rest_rotations[0]
    rest_local = rr[layer.parents[1:]].transpose(-1, -2) @ rr[1:]
    return p, rest_local @ chunk["rel"].double()  # rel = rest_local^T local


def _cached(path: Path, key: list[float]) -> dict | None:
    """The cache at ``path`` when it was made from the same chunks, else None."""
    if path.exists():
        cached = torch.load(path, weights_only=True)
        if isinstance(cached, dict) and cached.get("key") == key:
            return cached
    return None


def _save(path: Path, value: dict) -> None:
    """Write a file atomically (a cache, or the trained weights)."""
    tmp = path.with_suffix(".tmp")
    torch.save(value, tmp)
    tmp.replace(path)


def _blends(chunks: list[dict], union: torch.Tensor, data: Path, target: str) -> torch.Tensor:
    """(N, U, 3, 3) float32 blended rotations ``M`` of every sample of the chunks on the rig of
    ``target`` (``LBS(v + d) = LBS(v) + M d`` on the union), from the chunks' identities and
    rest-relative rotations; cached in ``data/blend_<target>.pt``."""
    path, key = data / f"blend_{target}.pt", _chunks_key(chunks)
    cached = _cached(path, key)
    if cached is not None:
        return cached["blend"]
    layer = BodyLayer.from_pca(procedural=target == "twist").double()
    out = []
    for c in tqdm(chunks, desc="blended rotations", unit="identity"):
        p, local = _chunk_pose(layer, c)
        out.append(blended_rotations(layer, p, local, union, absolute=True)[1].float())
    out = torch.cat(out)
    _save(path, {"blend": out, "key": key})
    return out


def _segment_data(chunks: list[dict], union: torch.Tensor, data: Path, target: str) -> dict:
    """What the volume loss needs: the limb segments' faces (:class:`SurfaceMeasures`) over their
    vertices ``S``, and per sample the rig's LBS of ``S``, the posed cone apexes and the rest
    volumes; cached in ``data/segments_<target>.pt``."""
    layer = BodyLayer.from_pca(procedural=target == "twist").double()
    measures = SurfaceMeasures.from_layer(BodyLayer.from_pca())
    verts = torch.from_numpy(np.unique(np.concatenate(measures.segment_faces)))
    where = torch.full((layer.num_vertices,), -1, dtype=torch.int64)
    where[verts] = torch.arange(len(verts))
    faces = [where[torch.from_numpy(f)] for f in measures.segment_faces]
    inside = where[union] >= 0
    out = {"faces": faces, "slot": torch.nonzero(inside).flatten(), "at": where[union][inside]}
    path, key = data / f"segments_{target}.pt", _chunks_key(chunks)
    cached = _cached(path, key)
    if cached is not None and torch.equal(cached["vertices"], verts):
        return {**out, **cached}
    lbs, apex, rest = [], [], []
    for c in tqdm(chunks, desc="segment volumes", unit="identity"):
        p, local = _chunk_pose(layer, c)
        posed = layer.pose(p, local, absolute=True, correctives=False)
        apex0, apex1 = measures.segment_apexes(p.rest_rotations, p.rest_joints, posed.transforms)
        x = p.rest_vertices[:, verts]
        rest.append(
            torch.stack([cone_volume(x, f, apex0[:, k]) for k, f in enumerate(faces)], -1).expand(len(local), -1)
        )
        lbs.append(posed.vertices[:, verts])
        apex.append(apex1)
    cached = {
        "key": key,
        "vertices": verts,
        "lbs": torch.cat(lbs).float(),
        "apex": torch.cat(apex).float(),
        "rest": torch.cat(rest).float(),
    }
    _save(path, cached)
    return {**out, **cached}


def _only_segments(seg: dict, names: list[str]) -> dict:
    """:func:`_segment_data` restricted to the segments ``names`` (joint names of :data:`SEGMENTS`)."""
    keep = [k for k, (joint, _) in enumerate(SEGMENTS) if joint in names]
    return {**seg, "faces": [seg["faces"][k] for k in keep], "apex": seg["apex"][:, keep], "rest": seg["rest"][:, keep]}


def _volume_loss(seg: dict, idx: torch.Tensor, moved: torch.Tensor) -> torch.Tensor:
    """Mean squared relative change of the segments' volumes of samples ``idx`` when the union
    vertices move by ``moved`` (B, U, 3) on the posed mesh."""
    x = seg["lbs"][idx].index_add(1, seg["at"], moved[:, seg["slot"]])
    vol = torch.stack([cone_volume(x, f, seg["apex"][idx, k]) for k, f in enumerate(seg["faces"])], -1)
    return (vol / seg["rest"][idx] - 1).square().mean()


def _freeze_fingers(model: Correctives, rel: torch.Tensor) -> None:
    """Hold the finger inputs (straight in every training pose) at their training mean."""
    fingers = torch.tensor([j + 1 for j in FINGERS])
    ids = model.needed[torch.isin(model.needed, fingers)]
    if len(ids):
        x6 = model.features(rel[:, ids - 1])
        model.freeze(ids, x6.mean(0))


def train(args: argparse.Namespace, command: str) -> None:
    data = Path(args.data)
    files = sorted(data.glob("chunk_*.pt"))
    if not files:
        raise SystemExit(f"--data: no chunk_*.pt files in {data}; run the generate stage first")
    key = "d_twist" if args.target == "twist" else "d"
    chunks = [torch.load(f, weights_only=True) for f in files]
    if key not in chunks[0]:
        raise SystemExit(f"--target {args.target}: the chunks in {data} have no {key!r} (made by an older generate)")
    # The last 5 % of each backend's identities (and of each pose family's: calm poses have their
    # own identities): validation only (ordered train, then held out)
    groups: dict[tuple[str, str], list[dict]] = {}
    for c in chunks:
        groups.setdefault((c.get("backend", "pca"), c.get("family", "")), []).append(c)
    cut = {b: max(1, len(cs) // 20) for b, cs in groups.items()}
    chunks = [c for b, cs in groups.items() for c in cs[: -cut[b]]] + [
        c for b, cs in groups.items() for c in cs[-cut[b] :]
    ]
    held = sum(cut.values())
    rel = torch.cat([c["rel"] for c in chunks[:-held]])
    size = torch.cat([c["size"].expand(len(c["rel"])) for c in chunks[:-held]])
    d = torch.cat([c[key] for c in chunks[:-held]])
    v_rel = torch.cat([c["rel"] for c in chunks[-held:]])
    v_size = torch.cat([c["size"].expand(len(c["rel"])) for c in chunks[-held:]])
    v_d = torch.cat([c[key] for c in chunks[-held:]])
    size_ref = float(size.mean())
    init_state = torch.load(args.init, map_location="cpu", weights_only=True) if args.init else None
    if init_state is not None:  # a fine-tune keeps its start's normalisation: it starts as the same function
        size_ref = float(init_state["size_ref"])
    layer = BodyLayer.from_pca()
    setup = TeacherSetup(layer, twist_start=False, volume=False, contact=False)  # its masks only
    meta = {
        "command": command,
        "seed": args.seed,
        "target": args.target,
        "data": _recipe(chunks, held, args.seed, args.target),
        "teacher_iterations": int(chunks[0].get("recipe", {}).get("iterations", 6)),
        "teacher_volume": bool(chunks[0].get("recipe", {}).get("volume", False)),
        "teacher_contact": bool(chunks[0].get("recipe", {}).get("contact", False)),
        "teacher_anchor": float(chunks[0].get("recipe", {}).get("anchor", 0.0)),
        "generate": args.generate_command
        or f"python scripts/train_correctives.py generate --identities {len(chunks)} --seed {args.seed}",
    }
    motions = chunks[0].get("recipe", {}).get("motions", "")
    if motions:  # how the motion folder was made (the CMU training motions, never evaluation data)
        meta["motions"] = (
            f"{motions}: unibody convert ../shared/motions/cmu/bvh ../shared/motions/cmu/asfamc --to motion "
            f"--out {motions} (the 183 CMU training motions; no evaluation data)"
        )
    model = build_model(layer, setup, size_ref, meta, args.hidden, shape=args.shape)
    if not torch.equal(model.union, setup.union):
        raise SystemExit("internal: the model's vertex union differs from the teacher's")
    _freeze_fingers(model, rel)
    shp = v_shp = None
    if args.shape:
        stats = (init_state or {}).get("shape")
        raw = _shape_inputs(model, layer, chunks, held, None if stats is None else (stats["mean"], stats["std"]))
        model.meta["shape_inputs"] = (
            "every activation also reads the identity's build: per limb segment log(mean distance of its "
            "vertices to the bone line / bone length), and log(size / size_ref), standardised over the "
            "training identities"
        )
    if args.init:
        init = _load_init(model, args.init)
        model.meta["init"] = f"{args.init} ({init.meta.get('command', '')})"
    maps = mirror_maps(model, layer.joint_names) if args.mirror else None
    if maps is not None:  # left and right mirror images of each other from the start (its statistics too)
        keep = _mirror_side(model, maps, (v_rel, v_size, v_d), raw if args.shape else None)
        model.meta["mirror"] = (
            f"left/right symmetric: the {keep} joints' activations and decoders mirrored onto their partners "
            "(unibody.correctives.mirror.symmetrize) at the start and the end; every batch holds each sample and "
            "its mirror image, so the gradients are mirror images up to float32 rounding (which AdamW's "
            "normalisation magnifies over thousands of steps: hence the last symmetrize)"
        )
    if args.shape:
        shp = (raw - model.shape_mean) / model.shape_std
        shp, v_shp = shp[: len(rel)], shp[len(rel) :]
    if args.small_weight:
        model.meta["small_pose_loss"] = (
            f"{args.small_weight} x mean squared displacement on {args.batch} random poses per step with "
            "every joint turned U(0, 0.2) rad about a uniform axis from the rest pose"
        )
    if args.edge_weight:
        model.meta["edge_loss"] = (
            f"{args.edge_weight} x mean squared error of the displacement differences along the mesh edges "
            "inside the masked vertices"
        )
    edges = _union_edges(setup)
    blend = v_blend = seg = None
    pw, vw = args.posed_weight, args.volume_weight
    if pw or vw:
        blend = _blends(chunks, setup.union, data, args.target)
        ntrain = len(rel)
        blend, v_blend = blend[:ntrain], blend[ntrain:]
    v_volume = None
    if vw:
        seg = _only_segments(_segment_data(chunks, setup.union, data, args.target), args.volume_segments)
        v_volume = (vw, seg, torch.arange(ntrain, ntrain + len(v_rel)))
        model.meta["volume_loss"] = (
            f"{vw:g} x the mean squared relative change of the limb segments' volumes (the benchmark's cone "
            f"volumes) on the posed training meshes; segments: {', '.join(args.volume_segments)}"
        )
    if pw:
        model.meta["posed_loss"] = (
            f"the loss (point and edge terms) is {1 - pw:g} x its rest-space form + {pw:g} x its posed form: "
            "the errors M (pred - target), M each sample's blended rotations of the rig "
            "(LBS(v + d) = LBS(v) + M d)"
        )
    opt = torch.optim.AdamW(model.parameters(), lr=args.lr, weight_decay=args.weight_decay)
    ckpt = data / f"checkpoint_{args.target}.pt"
    step, elapsed, best = 0, 0.0, {"mm": float("inf"), "last": float("inf"), "state": None}
    if args.resume and ckpt.exists():
        state = torch.load(ckpt, weights_only=True)
        model.load_state_dict(state["model"])
        opt.load_state_dict(state["opt"])
        step, elapsed, best = state["step"], state["elapsed"], state["best"]
        print(f"resumed at step {step}, {elapsed / 60:.1f} min")
    budget = args.minutes * 60
    if best["state"] is None:  # the starting point (an --init) competes too
        best = _validate(model, v_rel, v_size, v_d, best, edges, args.edge_weight, v_blend, pw, v_volume, v_shp)
    gen = torch.Generator().manual_seed(args.seed + step)
    n = len(rel)
    target = d / (size / size_ref)[:, None, None]

    def fit(err: torch.Tensor) -> torch.Tensor:
        loss = err.square().sum(-1).mean()
        if args.edge_weight:  # the error of the edges' displacement differences too: what edge strain sees
            loss = loss + args.edge_weight * (err[:, edges[:, 0]] - err[:, edges[:, 1]]).square().sum(-1).mean()
        return loss

    bar = tqdm(total=int(budget), initial=int(elapsed), desc="train", unit="s")
    t0, last = time.perf_counter() - elapsed, time.perf_counter()
    while elapsed < budget:
        for g in opt.param_groups:  # cosine decay over the time budget
            g["lr"] = args.lr * 0.5 * (1 + math.cos(math.pi * min(elapsed / budget, 1.0)))
        if maps is None:
            idx = torch.randint(n, (args.batch,), generator=gen)
            pred = model.union_displacements(rel[idx], size_ref * torch.ones(1), None if shp is None else shp[idx])
        else:  # each sample and its mirror image (scored back in the sample's own frame)
            half = torch.randint(n, (args.batch // 2,), generator=gen)
            m_rel, m_shp = maps.inputs(rel[half], None if shp is None else shp[half])
            both = model.union_displacements(
                torch.cat([rel[half], m_rel]),
                size_ref * torch.ones(1),
                None if shp is None else torch.cat([shp[half], m_shp]),
            )
            idx = torch.cat([half, half])
            pred = torch.cat([both[: len(half)], maps.output(both[len(half) :])])
        err = pred - target[idx]
        loss = (1 - pw) * fit(err) if pw < 1 else 0.0
        if pw or vw:  # on the posed mesh, at the samples' real size
            m, scale = blend[idx], (size[idx] / size_ref)[:, None, None]
        if pw:  # posed: what the surface shows (M is far from a rotation where bones blend)
            loss = loss + pw * fit((m @ err[..., None]).squeeze(-1) * scale)
        if vw:  # the limbs' volumes, which the teacher holds
            loss = loss + vw * _volume_loss(seg, idx, (m @ pred[..., None]).squeeze(-1) * scale)
        if args.small_weight:  # small poses: no displacement (LBS is fine there)
            axis = torch.nn.functional.normalize(torch.randn(args.batch, 77, 3, generator=gen), dim=-1)
            small = axis_angle_to_matrix(axis * 0.2 * torch.rand(args.batch, 77, 1, generator=gen))
            s_shp = None if shp is None else shp[idx]
            if maps is not None:  # mirrored in pairs too
                m_small, m_shp = maps.inputs(small[: len(half)], None if shp is None else shp[half])
                small = torch.cat([small[: len(half)], m_small])
                s_shp = None if shp is None else torch.cat([shp[half], m_shp])
            still = model.union_displacements(small, size_ref * torch.ones(1), s_shp)
            loss = loss + args.small_weight * still.square().sum(-1).mean()
        opt.zero_grad()
        loss.backward()
        opt.step()
        step += 1
        elapsed = time.perf_counter() - t0
        if step % 50 == 0:
            bar.update(int(elapsed) - bar.n)
            bar.set_postfix(loss_mm=f"{loss.sqrt().item() * 1e3:.2f}", step=step)
        if (
            time.perf_counter() - last > args.validate_every
        ):  # checkpoint, and keep the best model on the held-out identities
            best = _validate(model, v_rel, v_size, v_d, best, edges, args.edge_weight, v_blend, pw, v_volume, v_shp)
            torch.save(
                {"model": model.state_dict(), "opt": opt.state_dict(), "step": step, "elapsed": elapsed, "best": best},
                ckpt,
            )
            bar.write(f"step {step}: held-out score {best['last']:.3f} mm (best {best['mm']:.3f} mm)")
            last = time.perf_counter()
    bar.close()
    best = _validate(model, v_rel, v_size, v_d, best, edges, args.edge_weight, v_blend, pw, v_volume, v_shp)
    torch.save(
        {"model": model.state_dict(), "opt": opt.state_dict(), "step": step, "elapsed": elapsed, "best": best}, ckpt
    )
    model.load_state_dict(best["state"])
    if maps is not None:  # the symmetry the paired batches kept, up to rounding: made exact again
        drift = asymmetry(model, maps, v_rel, v_size, v_shp)
        symmetrize(model, maps, keep)
        print(f"mirror: largest asymmetry on the held-out samples before the last symmetrize {drift * 1e3:.4f} mm")
    with torch.no_grad():
        err = (model.union_displacements(v_rel, v_size, v_shp) - v_d).norm(dim=-1)
    model.meta.update(
        {
            "steps": step,
            "minutes": elapsed / 60,
            "validation_rest_mm": [float(err.mean()) * 1e3, float(err.max()) * 1e3],
            "training": (
                f"AdamW lr {args.lr} wd {args.weight_decay}, hidden {args.hidden}, cosine over "
                f"{args.minutes} min, batch {args.batch}; best held-out state"
            ),
            "frozen": "finger inputs of the wrist activations held at their training mean (straight fingers in every "
            "training pose)",
        }
    )
    print(f"{step} steps; held-out rest-space error mean {err.mean() * 1e3:.2f} mm, max {err.max() * 1e3:.2f} mm")
    state = model.state()
    state["params"] = {k: v.half() if k == "decode" else v for k, v in state["params"].items()}
    Path(args.out).parent.mkdir(parents=True, exist_ok=True)
    _save(Path(args.out), state)  # atomically: an interrupted write leaves the old file
    print(f"wrote {args.out} ({Path(args.out).stat().st_size / 1e6:.2f} MB)")


def _shard(text: str) -> tuple[int, int]:
    """``K/N`` -> (K, N) with 0 <= K < N."""
    try:
        k, n = (int(t) for t in text.split("/"))
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected K/N (e.g. 0/2), got {text!r}") from None
    if not 0 <= k < n:
        raise argparse.ArgumentTypeError(f"expected 0 <= K < N, got {text!r}")
    return k, n


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("stage", choices=("generate", "train"))
    parser.add_argument("--data", default=str(Path.home() / ".cache" / "unibody" / "correctives-teacher"))
    parser.add_argument("--seed", type=int, default=40)
    parser.add_argument("--identities", type=int, default=160)
    parser.add_argument(
        "--backend",
        choices=("pca", "anny"),
        default="pca",
        help="generate: the identities' backend (native PCA, or Anny phenotypes: another rest pose)",
    )
    parser.add_argument("--poses", type=int, default=16)
    parser.add_argument("--minutes", type=float, default=25.0)
    parser.add_argument("--resume", action="store_true")
    parser.add_argument("--out", default=None, help="default: the shipped weights file of --target")
    parser.add_argument("--target", choices=("plain", "twist"), default="plain", help="the rig the correctives serve")
    parser.add_argument("--motions", default=None, help="directory of unibody.motion/1 files (generate)")
    parser.add_argument("--motion-share", type=float, default=0.5, help="share of each identity's poses from --motions")
    parser.add_argument(
        "--calm-share",
        type=float,
        default=0.0,
        help="generate: share of each identity's poses between the T-pose and its rest pose (calm_poses); "
        "chunks with any are named chunk_calm_*",
    )
    parser.add_argument("--iterations", type=int, default=6, help="ARAP iterations of the teacher (generate)")
    parser.add_argument(
        "--volume",
        action=argparse.BooleanOptionalAction,
        default=True,
        help="the teacher keeps each limb segment's rest volume (generate; --no-volume: ARAP alone)",
    )
    parser.add_argument(
        "--contact",
        action=argparse.BooleanOptionalAction,
        default=True,
        help="the teacher pulls penetrating vertices out of the body (generate; --no-contact: no self-contact)",
    )
    parser.add_argument(
        "--anchor",
        type=float,
        default=ANCHOR,
        help="the teacher's tie of flesh one bone carries to that bone, in units of the mean Laplacian diagonal "
        f"(generate; 0: none; default {ANCHOR})",
    )
    parser.add_argument(
        "--shard",
        type=_shard,
        default=(0, 1),
        metavar="K/N",
        help="generate only identities i with i %% N == K (run N processes side by side; default 0/1)",
    )
    parser.add_argument("--generate-command", default="", help="the generate command(s) that made --data, for the meta")
    parser.add_argument("--threads", type=int, default=1)
    parser.add_argument("--lr", type=float, default=3e-3)
    parser.add_argument("--batch", type=int, default=32)
    parser.add_argument("--weight-decay", type=float, default=0.01)
    parser.add_argument("--hidden", type=int, default=64)
    parser.add_argument(
        "--shape",
        action="store_true",
        help="train: every activation also reads the identity's build (limb girths over lengths, size)",
    )
    parser.add_argument("--validate-every", type=float, default=120.0, help="seconds between checkpoints")
    parser.add_argument(
        "--edge-weight",
        type=float,
        default=0.0,
        help="weight of a loss on the displacement differences along mesh edges (what edge strain sees)",
    )
    parser.add_argument(
        "--posed-weight",
        type=float,
        default=0.0,
        help="share W in [0, 1] of the loss measured on the posed mesh (each sample's blended rotations "
        "applied; computed once and cached under --data): (1 - W) rest-space + W posed",
    )
    parser.add_argument(
        "--volume-weight",
        type=float,
        default=0.0,
        help="weight of a loss on the limb segments' volume change on the posed training meshes (the teacher "
        "keeps them at rest volume; segment data computed once and cached under --data)",
    )
    parser.add_argument(
        "--volume-segments",
        default=",".join(joint for joint, _ in SEGMENTS),
        help="comma-separated limb segments (their joints' names) the volume loss sees (default: all eight)",
    )
    parser.add_argument(
        "--init",
        default=None,
        help="start from these weights (a fine-tune; same structure, or a pose-only model under --shape)",
    )
    parser.add_argument(
        "--mirror",
        action="store_true",
        help="train: left and right mirror images of each other (symmetrized at the start, each sample and its "
        "mirror image in every batch)",
    )
    parser.add_argument(
        "--small-weight",
        type=float,
        default=0.0,
        help="weight of a zero-displacement loss on random small poses (every joint within 0.2 rad of "
        "the rest pose): where LBS was fine, keep it",
    )
    args = parser.parse_args()
    if args.mirror and args.batch < 2:
        parser.error(f"--mirror: a batch holds samples and their mirrors; expected --batch >= 2, got {args.batch}")
    if args.small_weight < 0:
        parser.error(f"--small-weight: expected >= 0, got {args.small_weight}")
    if not 0 <= args.posed_weight <= 1:
        parser.error(f"--posed-weight: expected a number in [0, 1], got {args.posed_weight}")
    if not 0 <= args.calm_share <= 1:
        parser.error(f"--calm-share: expected a number in [0, 1], got {args.calm_share}")
    if not args.anchor >= 0:  # NaN fails too
        parser.error(f"--anchor: expected a number >= 0, got {args.anchor}")
    if args.volume_weight < 0:
        parser.error(f"--volume-weight: expected >= 0, got {args.volume_weight}")
    args.volume_segments = [n for n in args.volume_segments.split(",") if n]
    known = [joint for joint, _ in SEGMENTS]
    if not args.volume_segments or any(n not in known for n in args.volume_segments):
        parser.error(f"--volume-segments: expected a comma-separated subset of {','.join(known)}, got "
                     f"{','.join(args.volume_segments) or 'nothing'}")  # fmt: skip
    if args.edge_weight < 0:
        parser.error(f"--edge-weight: expected >= 0, got {args.edge_weight}")
    if args.init and not Path(args.init).is_file():
        parser.error(f"--init: {args.init} is not a file (expected weights written by the train stage)")
    torch.set_num_threads(args.threads)
    torch.manual_seed(args.seed)
    if args.out is None:
        args.out = str(Path("src/unibody/correctives/data") / default_weights_path(args.target == "twist").name)
    if args.init and Path(args.out).resolve() == Path(args.init).resolve():
        parser.error(f"--out: {args.out} is the --init weights; expected another file (the input is kept)")
    if args.stage == "generate":
        generate(args)
    else:
        train(args, shlex.join(["python", *sys.argv]))


if __name__ == "__main__":
    main()
