"""Build unibody's broader native shape space (``src/unibody/identity/data/pca_v2.npz``).

    OMP_NUM_THREADS=1 python scripts/build_shape_space.py --identities 8000 --seed 0 --chunk 200 --rank 256 \\
        --components 128 --phenotypes all --local-probability 0.125 --local-amplitude 1.0 \\
        --registered 8 --registered-copies 40

What it does (the recipe, command and seed are also written into the asset's metadata):

1. Samples ``--identities`` Anny identities (Apache-2.0; ``BodyLayer.from_anny(local_changes="all",
   phenotypes="all")``: 11 phenotypes + 256 local changes) with
   :func:`unibody.identity.shape_space.anny_params`: gender, age (newborn to elder), muscle,
   weight, height, proportions, cupsize and firmness uniform in [0, 1]; the
   african/asian/caucasian blend uniform on the simplex; each local change active with
   probability ``--local-probability`` and then uniform in [-``--local-amplitude``,
   ``--local-amplitude``] (Anny's full range is [-1, 1]).
2. Runs each through Anny -> topology transfer -> skeleton fit, reposes it to the bind A-pose
   and places its Hips at :data:`unibody.identity.shape_space.HIPS_M`
   (:func:`~unibody.identity.shape_space.to_bind_pose`).
3. Mirror-augments every mesh and folds chunks into an incremental PCA keeping ``--rank``
   directions (float64); writes the first ``--components`` as float16 (the first
   ``--split-leading`` with their float16 remainder).

4. Stage 2 (``--registered N``): N more Anny identities of the same recipe (their own stream,
   ``default_rng([seed, 1000])``) are registered onto the canonical mesh *automatically* from
   Anny's native mesh (:func:`unibody.registration.register`, as any foreign template is), placed
   the same way, mirrored, and folded ``--registered-copies`` times into the finished stage-1
   state. The automatic correspondence slides vertices along the surface by several mm against
   the hand-made wrap the other meshes use; these samples let the space hold that sliding, which
   every registered foreign body carries. The copies are the largest count that keeps held-out
   Anny identities (v1 recipe, seed 1) at <= 0.5 mm at 128 components (40 of 10, 20, 40, 80
   with 8 bodies). Registrations are cached in ``--registered-cache`` (1-3 min each).

Other sources (a user's SMPL / MHR / GarmentMeasurements files) go through the same library
function with ``unibody shape-space build``. Nothing here is trained on the evaluation meshes.
Progress goes to stdout; the state is checkpointed after every chunk (``--checkpoint``) and
the same command resumes from it. One thread by default.
"""

from __future__ import annotations

import argparse
import json
import platform
import sys
from pathlib import Path

import torch

ROOT = Path(__file__).resolve().parents[1]
DEFAULT_OUT = ROOT / "src/unibody/identity/data/pca_v2.npz"
DEFAULT_CHECKPOINT = ROOT / "build/shape_space_checkpoint.npz"


def recipe_from_args(args: argparse.Namespace):
    from unibody.identity.shape_space import AnnyRecipe

    return AnnyRecipe(
        phenotypes=args.phenotypes,
        ethnicity="dirichlet" if args.phenotypes == "all" else "default",
        local_change_probability=args.local_probability,
        local_change_amplitude=args.local_amplitude,
        mirror_augmented=True,
    )


def anny_source(recipe, dtype: torch.dtype = torch.float32):
    """The Anny :class:`~unibody.identity.shape_space.ShapeSource` of ``recipe``."""
    from dataclasses import asdict

    from unibody import BodyLayer
    from unibody.assets import ANNY_VERSION
    from unibody.identity.shape_space import ShapeSource, anny_sampler

    layer = BodyLayer.from_anny(local_changes="all", phenotypes=recipe.phenotypes, dtype=dtype)
    num_local = layer.identity.num_params - len(layer.identity.phenotypes)
    description = {"backend": f"anny=={ANNY_VERSION} (Apache-2.0)", "recipe": asdict(recipe)}
    return ShapeSource("anny", layer, anny_sampler(recipe, num_local), 1.0, description)


def registered_anny(count: int, seed: int, cache: Path, progress=print) -> list[tuple[torch.Tensor, torch.Tensor]]:
    """``[(automatic, hand-made)]`` canonical rest meshes (V, 3) float64 of Anny identities.

    Identities of the v2 recipe from ``default_rng([seed, 1000])`` (a stream the Anny source and
    the benchmark's held-out sets never use); each native Anny mesh is registered onto the
    canonical mesh automatically (:func:`unibody.registration.register`, default preset), as a
    user's foreign template would be, next to the same identity through the hand-made wrap. Both
    in the registration's normalised frame. Cached per identity in ``cache`` (a few minutes each).
    """
    import hashlib

    import numpy as np

    from unibody import BodyLayer
    from unibody.identity.shape_space import AnnyRecipe, anny_params
    from unibody.io.atomic import atomic_write
    from unibody.registration import REGISTRATION_VERSION, register

    layer = BodyLayer.from_anny(local_changes="all", phenotypes="all", dtype=torch.float64)
    num_local = layer.identity.num_params - 11
    params = anny_params(AnnyRecipe(), np.random.default_rng([seed, 1000]), count, num_local)
    out = []
    for i, row in enumerate(params):
        key = f"registration v{REGISTRATION_VERSION}, {hashlib.sha256(row.tobytes()).hexdigest()}"
        path = cache / f"registered_{i:03d}.npz"
        if path.is_file():
            with np.load(path, allow_pickle=False) as data:
                if str(data["key"]) == key:
                    out.append((torch.from_numpy(data["automatic"]), torch.from_numpy(data["hand_made"])))
                    continue
        progress(f"registering Anny identity {i + 1}/{count} from its own mesh (a few minutes)")
        with torch.no_grad():
            native = layer.identity(torch.from_numpy(row)[None])[0]
            truth = layer.topology(native[None])[0]
        reg = register(native, layer.identity.faces())
        n = reg.normalization
        auto, truth = n.apply(reg.correspondence.apply(native)), n.apply(truth)
        cache.mkdir(parents=True, exist_ok=True)
        with atomic_write(path) as f:
            np.savez(f, automatic=auto.numpy(), hand_made=truth.numpy(), key=np.asarray(key))
        out.append((auto, truth))
    return out


def command_line(args: argparse.Namespace) -> str:
    return (
        f"OMP_NUM_THREADS=1 python scripts/build_shape_space.py --identities {args.identities} --seed {args.seed} "
        f"--chunk {args.chunk} --rank {args.rank} --components {args.components} --split-leading "
        f"{args.split_leading} --phenotypes {args.phenotypes} --local-probability {args.local_probability} "
        f"--local-amplitude {args.local_amplitude} --registered {args.registered} "
        f"--registered-copies {args.registered_copies}"
    )


def fold_registered(args: argparse.Namespace, meta: dict) -> dict:
    """Stage 2: fold the automatically registered Anny bodies into the finished stage-1 state; write the asset."""
    import numpy as np

    from unibody import BodyLayer
    from unibody.identity.pca import IPCAState, ipca_finalize, ipca_update, write_asset
    from unibody.identity.shape_space import to_bind_pose
    from unibody.rig import Rig
    from unibody.symmetry import mirror

    layer = BodyLayer(Rig.canonical(), None, None).double()
    pairs = registered_anny(args.registered, args.seed, Path(args.registered_cache), lambda m: print(m, flush=True))
    with torch.no_grad():
        autos = to_bind_pose(layer, torch.stack([a for a, _ in pairs]))
        hand = to_bind_pose(layer, torch.stack([t for _, t in pairs]))
    sliding = 1e3 * (autos - hand).norm(dim=-1)
    samples = torch.cat([autos, mirror(autos)]).reshape(2 * len(pairs), -1)
    with np.load(args.checkpoint, allow_pickle=False) as data:
        state = IPCAState.from_numpy({k: data[k] for k in data.files})
    if int(np.load(args.checkpoint)["next_chunk"]) * args.chunk < args.identities:
        raise SystemExit(f"checkpoint {args.checkpoint} is not a finished stage 1; run the command again")
    for _ in range(args.registered_copies):
        state = ipca_update(state, samples, args.rank)
    mean, comps, std = ipca_finalize(state, args.components)
    total_var = state.sum_sq / (state.count - 1)
    meta = dict(meta)
    meta.pop("asset_bytes", None)
    meta["sources"] = [
        *meta["sources"],
        {
            "name": "anny, automatic registration",
            "identities": len(pairs),
            "copies": args.registered_copies,
            "recipe": "the anny recipe, default_rng([seed, 1000]); native Anny mesh registered with "
            "unibody.registration.register (default preset), bind pose, Hips placed, mirrored",
            "sliding_vs_hand_made_wrap_mm": {"mean": float(sliding.mean()), "max": float(sliding.max())},
        },
    ]
    meta.update(
        samples=state.count,
        explained_variance_fraction=float((std**2).sum()) / total_var,
        total_variance_m2=total_var,
    )
    v = layer.num_vertices
    meta["asset_bytes"] = write_asset(
        args.out,
        mean=mean.reshape(v, 3).numpy(),
        components=comps.reshape(-1, v, 3).numpy(),
        std=std.numpy(),
        metadata=meta,
        split_leading=args.split_leading,
    )
    return meta


def build(args: argparse.Namespace) -> dict:
    from unibody import __version__
    from unibody.identity.shape_space import build_shape_space

    torch.set_num_threads(args.threads)
    recipe = recipe_from_args(args)
    metadata = {
        "command": command_line(args),
        "name": Path(args.out).stem,
        "identities": args.identities,
        "unibody_version": __version__,
        "machine": f"{platform.machine()} {platform.processor() or ''} torch {torch.__version__}, "
        f"{args.threads} thread(s)",
    }
    meta = build_shape_space(
        [anny_source(recipe)],
        args.out,
        identities=args.identities,
        seed=args.seed,
        chunk=args.chunk,
        rank=args.rank,
        components=args.components,
        split_leading=args.split_leading,
        checkpoint=args.checkpoint,
        metadata=metadata,
        progress=lambda line: print(line, flush=True),
    )
    if args.registered:
        meta = fold_registered(args, meta)
    out = Path(args.out)
    if args.write_json:
        out.with_suffix(".json").write_text(json.dumps(meta, indent=2, sort_keys=True) + "\n")
    explained = 100 * meta["explained_variance_fraction"]
    print(f"wrote {out} ({meta['asset_bytes']:,} bytes); explained variance {explained:.5f} %")
    print(f"chunks took {meta['build_seconds']:.0f} s")
    return meta


def parse_args(argv: list[str] | None = None) -> argparse.Namespace:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--identities", type=int, default=8000, help="Anny identities (twice as many samples)")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--chunk", type=int, default=200, help="identities per incremental update")
    p.add_argument("--rank", type=int, default=256, help="directions kept while streaming")
    p.add_argument("--components", type=int, default=128, help="directions shipped")
    p.add_argument("--split-leading", type=int, default=1, help="leading components stored as float16 hi + lo")
    p.add_argument("--phenotypes", choices=("default", "all"), default="all")
    p.add_argument("--local-probability", type=float, default=0.125, help="chance that a local change is active")
    p.add_argument("--local-amplitude", type=float, default=1.0, help="active changes uniform in [-a, a]")
    p.add_argument("--registered", type=int, default=0, help="Anny bodies through the automatic registration")
    p.add_argument("--registered-copies", type=int, default=0, help="how many times each enters (its weight)")
    p.add_argument("--registered-cache", default=str(ROOT / "build/shape_space_registered"))
    p.add_argument("--out", default=str(DEFAULT_OUT))
    p.add_argument("--checkpoint", default=str(DEFAULT_CHECKPOINT))
    p.add_argument("--no-json", dest="write_json", action="store_false", help="no .json sidecar next to --out")
    p.add_argument("--threads", type=int, default=1)
    p.add_argument("--device", default="cpu", help="only cpu is supported (the build is CPU-bound)")
    args = p.parse_args(argv)
    if args.device != "cpu":
        p.error("--device: only cpu is supported")
    if args.components > args.rank:
        p.error(f"--components {args.components} exceeds --rank {args.rank}")
    return args


def main(argv: list[str] | None = None) -> None:
    build(parse_args(argv))


if __name__ == "__main__":
    main(sys.argv[1:])
