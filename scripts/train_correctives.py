"""Train the pose correctives (issue 40, paper 000 §3.5.2) from the as-rigid-as-possible teacher.

Two resumable stages, both on one thread by default:

1. ``generate``: draws identities of the native PCA (children to adults) and poses (the seeded
   generator with deep bends plus randomised stress families), poses each identity with LBS,
   relaxes it with the teacher and stores the rest-space targets in chunk files under
   ``--data`` (one per identity; existing chunks are kept, so a rerun resumes).
2. ``train``: fits :class:`unibody.correctives.model.Correctives` (77 rest-relative joint
   rotations -> J x 24 activations -> sparse rest-space displacements) with Adam, checkpointing
   to ``--data/checkpoint.pt`` (``--resume`` continues), and writes the shipped weights with the
   command, seed and data recipe (``--out``).

    OMP_NUM_THREADS=1 python scripts/train_correctives.py generate --identities 160 --poses 16
    OMP_NUM_THREADS=1 python scripts/train_correctives.py train --minutes 25 --resume
"""

from __future__ import annotations

import argparse
import math
import sys
import time
from pathlib import Path

import torch
from tqdm import tqdm

from unibody import BodyLayer
from unibody.correctives.model import Correctives
from unibody.correctives.stress import FAMILIES
from unibody.correctives.training import TeacherSetup, draw_identities, size_of, teacher_targets
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


def generate(args: argparse.Namespace) -> None:
    data = Path(args.data)
    data.mkdir(parents=True, exist_ok=True)
    layer = BodyLayer.from_pca()
    setup = TeacherSetup(layer)
    coeffs = draw_identities(layer, args.identities, keyed_generator("correctives-identities", args.seed))
    todo = [i for i in range(args.identities) if not (data / f"chunk_{i:05d}.pt").exists()]
    print(f"teacher region: {len(setup.union)} vertices; {len(todo)} of {args.identities} identities to do")
    for i in tqdm(todo, desc="teacher", unit="identity", smoothing=0.1):
        prepared = layer.prepare_identity(coeffs[i : i + 1])
        pose = draw_poses(args.poses, keyed_generator("correctives-poses", args.seed, i))
        _, _, d = teacher_targets(layer, prepared, pose, setup)
        rel = Correctives.rest_relative(layer.local_rotations(pose), prepared.rest_rotations, layer.parents)
        chunk = {"rel": rel.float(), "d": d.float(), "size": size_of(prepared.rest_joints).float(), "coeffs": coeffs[i]}
        tmp = data / f"chunk_{i:05d}.tmp"
        torch.save(chunk, tmp)
        tmp.rename(data / f"chunk_{i:05d}.pt")


def build_model(layer: BodyLayer, setup: TeacherSetup, size_ref: float, meta: dict, hidden: int) -> Correctives:
    """Active joints: the stressed ones; inputs: the joint, its parent, its children (not Hips/Root)."""
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
    return Correctives(
        inputs, verts, layer.num_vertices, hidden=hidden, size_ref=size_ref, joint_names=tuple(setup.masks), meta=meta
    )


def _validate(model: Correctives, rel: torch.Tensor, size: torch.Tensor, d: torch.Tensor, best: dict) -> dict:
    """Mean rest-space error (mm) on the held-out identities; the best state so far."""
    with torch.no_grad():
        mm = float((model.union_displacements(rel, size) - d).norm(dim=-1).mean()) * 1e3
    if mm < best["mm"]:
        best = {"mm": mm, "state": {k: v.clone() for k, v in model.state_dict().items()}}
    return {**best, "last": mm}


def train(args: argparse.Namespace, command: str) -> None:
    data = Path(args.data)
    files = sorted(data.glob("chunk_*.pt"))
    if not files:
        raise SystemExit(f"--data: no chunk_*.pt files in {data}; run the generate stage first")
    chunks = [torch.load(f, weights_only=True) for f in files]
    held = max(1, len(chunks) // 20)  # the last 5 % of the identities: validation only
    rel = torch.cat([c["rel"] for c in chunks[:-held]])
    size = torch.cat([c["size"].expand(len(c["rel"])) for c in chunks[:-held]])
    d = torch.cat([c["d"] for c in chunks[:-held]])
    v_rel = torch.cat([c["rel"] for c in chunks[-held:]])
    v_size = torch.cat([c["size"].expand(len(c["rel"])) for c in chunks[-held:]])
    v_d = torch.cat([c["d"] for c in chunks[-held:]])
    size_ref = float(size.mean())
    layer = BodyLayer.from_pca()
    setup = TeacherSetup(layer)
    meta = {
        "command": command,
        "seed": args.seed,
        "data": (
            f"{len(chunks)} native-PCA identities (16 components N(0,1), stature U(1.0, 1.95) m, "
            f"keyed_generator('correctives-identities', {args.seed})) x {len(chunks[0]['rel'])} poses each "
            f"(draw_poses: sample_poses with bend 0.3, chamber 0.1, fold 0.15 + randomised stress families; "
            f"keyed_generator('correctives-poses', {args.seed}, i)); teacher: spokes-and-rims ARAP, 6 "
            f"iterations from LBS + procedural twist, joint regions grown 5 rings (wrists and ankles: the "
            f"whole forearm or shin), LBS boundary; last {held} identities held out for validation"
        ),
        "generate": f"python scripts/train_correctives.py generate --identities {len(chunks)} --seed {args.seed}",
    }
    model = build_model(layer, setup, size_ref, meta, args.hidden)
    if not torch.equal(model.union, setup.union):
        raise SystemExit("internal: the model's vertex union differs from the teacher's")
    opt = torch.optim.AdamW(model.parameters(), lr=args.lr, weight_decay=args.weight_decay)
    ckpt = data / "checkpoint.pt"
    step, elapsed, best = 0, 0.0, {"mm": float("inf"), "last": float("inf"), "state": None}
    if args.resume and ckpt.exists():
        state = torch.load(ckpt, weights_only=True)
        model.load_state_dict(state["model"])
        opt.load_state_dict(state["opt"])
        step, elapsed, best = state["step"], state["elapsed"], state["best"]
        print(f"resumed at step {step}, {elapsed / 60:.1f} min")
    budget = args.minutes * 60
    gen = torch.Generator().manual_seed(args.seed + step)
    n = len(rel)
    target = d / (size / size_ref)[:, None, None]
    bar = tqdm(total=int(budget), initial=int(elapsed), desc="train", unit="s")
    t0, last = time.perf_counter() - elapsed, time.perf_counter()
    while elapsed < budget:
        for g in opt.param_groups:  # cosine decay over the time budget
            g["lr"] = args.lr * 0.5 * (1 + math.cos(math.pi * min(elapsed / budget, 1.0)))
        idx = torch.randint(n, (args.batch,), generator=gen)
        pred = model.union_displacements(rel[idx], size_ref * torch.ones(1))
        loss = (pred - target[idx]).square().sum(-1).mean()
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
            best = _validate(model, v_rel, v_size, v_d, best)
            torch.save(
                {"model": model.state_dict(), "opt": opt.state_dict(), "step": step, "elapsed": elapsed, "best": best},
                ckpt,
            )
            bar.write(f"step {step}: held-out mean {best['last']:.3f} mm (best {best['mm']:.3f} mm)")
            last = time.perf_counter()
    bar.close()
    best = _validate(model, v_rel, v_size, v_d, best)
    torch.save(
        {"model": model.state_dict(), "opt": opt.state_dict(), "step": step, "elapsed": elapsed, "best": best}, ckpt
    )
    model.load_state_dict(best["state"])
    with torch.no_grad():
        err = (model.union_displacements(v_rel, v_size) - v_d).norm(dim=-1)
    model.meta.update(
        {
            "steps": step,
            "minutes": elapsed / 60,
            "validation_rest_mm": [float(err.mean()) * 1e3, float(err.max()) * 1e3],
            "training": (
                f"AdamW lr {args.lr} wd {args.weight_decay}, hidden {args.hidden}, cosine over "
                f"{args.minutes} min, batch {args.batch}; best held-out state"
            ),
        }
    )
    print(f"{step} steps; held-out rest-space error mean {err.mean() * 1e3:.2f} mm, max {err.max() * 1e3:.2f} mm")
    state = model.state()
    state["params"] = {k: v.half() if k == "decode" else v for k, v in state["params"].items()}
    Path(args.out).parent.mkdir(parents=True, exist_ok=True)
    torch.save(state, args.out)
    print(f"wrote {args.out} ({Path(args.out).stat().st_size / 1e6:.2f} MB)")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("stage", choices=("generate", "train"))
    parser.add_argument("--data", default=str(Path.home() / ".cache" / "unibody" / "correctives-teacher"))
    parser.add_argument("--seed", type=int, default=40)
    parser.add_argument("--identities", type=int, default=160)
    parser.add_argument("--poses", type=int, default=16)
    parser.add_argument("--minutes", type=float, default=25.0)
    parser.add_argument("--resume", action="store_true")
    parser.add_argument("--out", default="src/unibody/correctives/data/correctives.pt")
    parser.add_argument("--threads", type=int, default=1)
    parser.add_argument("--lr", type=float, default=3e-3)
    parser.add_argument("--batch", type=int, default=32)
    parser.add_argument("--weight-decay", type=float, default=0.01)
    parser.add_argument("--hidden", type=int, default=64)
    parser.add_argument("--validate-every", type=float, default=120.0, help="seconds between checkpoints")
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    torch.manual_seed(args.seed)
    if args.stage == "generate":
        generate(args)
    else:
        train(args, " ".join(["python", *sys.argv]))


if __name__ == "__main__":
    main()
