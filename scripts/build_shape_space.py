"""Build unibody's broader native shape space (``src/unibody/identity/data/pca_v2.npz``).

    OMP_NUM_THREADS=1 python scripts/build_shape_space.py --identities 8000 --seed 0 --chunk 200 --rank 256 \\
        --components 128 --phenotypes all --local-probability 0.125 --local-amplitude 1.0

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


def command_line(args: argparse.Namespace) -> str:
    return (
        f"OMP_NUM_THREADS=1 python scripts/build_shape_space.py --identities {args.identities} --seed {args.seed} "
        f"--chunk {args.chunk} --rank {args.rank} --components {args.components} --split-leading "
        f"{args.split_leading} --phenotypes {args.phenotypes} --local-probability {args.local_probability} "
        f"--local-amplitude {args.local_amplitude}"
    )


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
