"""Build unibody's native PCA shape space (``src/unibody/identity/data/pca_v1.npz``).

    python scripts/build_pca.py --identities 10000 --seed 0 --chunk 256 --rank 256 --components 128 --split-leading 1

What it does (the recipe is also written into the asset's metadata):

1. Samples ``--identities`` Anny identities (``BodyLayer.from_anny(local_changes="all")``:
   6 phenotypes + 256 local changes) from ``numpy.random.default_rng(seed)``, one row of
   6 + 2 x 256 uniforms per identity (row i does not depend on how many are drawn):
   - phenotypes (gender, age, muscle, weight, height, proportions) uniform in [0, 1]: the
     whole box, newborns (age 0) to elders (age 1) included;
   - local changes: each one active with probability 1/8 (about 32 of 256 per identity),
     an active one uniform in [-0.5, 0.5], the others 0 (sparse, moderate amplitude: Anny's
     changes at +-1 move vertices by up to 10 cm, e.g. a leg length or a pregnant belly).
2. Runs each identity through Anny -> topology transfer -> skeleton transfer and reposes it
   to the rig's bind A-pose: absolute local rotations equal to the bind pose's own
   (R_bind,parent^T R_bind,k) and transl = the identity's rest Hips position, so every
   sample's skeleton has exactly the bind orientations (Anny's rest pose differs from the
   bind pose by ~4-37 degrees at the hands, forearms, fingers and feet). Measured over the
   10,000 training identities, reposing moves vertices by 43.0 mm on average (median 23.1,
   P95 138.5, max 245.6 mm; ``repose_displacement`` in the metadata).
3. Mirror-augments every sample (:func:`unibody.symmetry.mirror`).
4. Folds each chunk of ``--chunk`` identities (2 x chunk samples) into an incremental PCA
   (Ross et al. 2008, :func:`unibody.identity.pca.ipca_update`) keeping ``--rank``
   directions, in float64; ships the first ``--components`` as float16, the first
   ``--split-leading`` with their float16 remainder too (the first holds 99.7 % of the
   variance: float16 alone would cost 0.05 mm mean, 0.4 mm max on held-out meshes).

Progress goes to stdout. The running state is checkpointed after every chunk
(``--checkpoint``, default ``build/pca_checkpoint.npz``); running the same command again
continues from it (a checkpoint made with other settings is refused). One thread by default
(``--threads``): 10,000 identities took 119 s of chunk time (plus ~10 s setup) on one core
of the CI-class machine.
"""

from __future__ import annotations

import argparse
import json
import platform
import sys
import time
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np
import torch

ROOT = Path(__file__).resolve().parents[1]
DEFAULT_OUT = ROOT / "src/unibody/identity/data/pca_v1.npz"
DEFAULT_CHECKPOINT = ROOT / "build/pca_checkpoint.npz"
REPOSE_BIN_MM = 0.05  # histogram of the reposing displacement, for its percentiles
REPOSE_BINS = 20000


@dataclass(frozen=True)
class Recipe:
    """The identity distribution of the training (and held-out) meshes."""

    phenotype_range: tuple[float, float] = (0.0, 1.0)
    local_change_probability: float = 0.125
    local_change_amplitude: float = 0.5
    pose: str = "bind A-pose (absolute bind local rotations, transl = rest Hips)"
    mirror_augmented: bool = True

    @classmethod
    def from_dict(cls, d: dict) -> Recipe:
        d = dict(d)
        d["phenotype_range"] = tuple(d["phenotype_range"])
        return cls(**d)


def sample_params(recipe: Recipe, count: int, seed: int, num_local: int, start: int = 0) -> np.ndarray:
    """Identity parameters ``(count, 6 + num_local)`` float64, rows ``start .. start + count``.

    One row of ``6 + 2 num_local`` uniforms per identity from ``default_rng(seed)``: the
    phenotypes, then the activation draws, then the values of the local changes.
    """
    rng = np.random.default_rng(seed)
    u = rng.random((start + count, 6 + 2 * num_local))[start:]
    lo, hi = recipe.phenotype_range
    phen = lo + (hi - lo) * u[:, :6]
    active = u[:, 6 : 6 + num_local] < recipe.local_change_probability
    value = recipe.local_change_amplitude * (2.0 * u[:, 6 + num_local :] - 1.0)
    return np.concatenate([phen, np.where(active, value, 0.0)], axis=1)


def canonical_samples(layer, params: np.ndarray) -> tuple[torch.Tensor, torch.Tensor]:
    """``(rest (B, V, 3), reposed (B, V, 3))`` canonical meshes of Anny identities, m."""
    dtype = layer.skeleton.bind_rot.dtype
    with torch.no_grad():
        prepared = layer.prepare_identity(torch.as_tensor(params, dtype=dtype))
        return prepared.rest_vertices, layer.repose_to_bind(prepared)


def anny_layer(dtype: torch.dtype = torch.float32):
    from unibody import BodyLayer

    return BodyLayer.from_anny(local_changes="all", dtype=dtype)


def _config(args: argparse.Namespace, recipe: Recipe) -> dict:
    return {
        "identities": args.identities,
        "seed": args.seed,
        "chunk": args.chunk,
        "rank": args.rank,
        "recipe": asdict(recipe),
    }


def _save_checkpoint(path: Path, state, chunk: int, hist: np.ndarray, config: dict, elapsed: float) -> None:
    from unibody.io.atomic import atomic_write

    path.parent.mkdir(parents=True, exist_ok=True)
    with atomic_write(path) as f:  # an interrupted write never leaves a broken checkpoint
        np.savez(
            f,
            **state.to_numpy(),
            next_chunk=np.asarray(chunk),
            repose_hist=hist,
            config=np.asarray(json.dumps(config, sort_keys=True)),
            elapsed=np.asarray(elapsed),
        )


def _load_checkpoint(path: Path, config: dict):
    from unibody.identity.pca import IPCAState

    with np.load(path, allow_pickle=False) as data:
        saved = json.loads(str(data["config"]))
        if saved != json.loads(json.dumps(config, sort_keys=True)):
            raise SystemExit(
                f"checkpoint {path} was made with other settings:\n  {saved}\nnot\n  {config}\n"
                "delete it (or pass --restart) to start over"
            )
        arrays = {k: data[k] for k in data.files}
    state = IPCAState.from_numpy(arrays)
    return state, int(arrays["next_chunk"]), arrays["repose_hist"].astype(np.int64), float(arrays["elapsed"])


def _hist_stats(hist: np.ndarray, total_mm: float, max_mm: float) -> dict:
    count = int(hist.sum())
    cdf = np.cumsum(hist) / count
    edge = lambda q: float((np.searchsorted(cdf, q) + 1) * REPOSE_BIN_MM)  # noqa: E731  (upper bin edge)
    return {"mean_mm": total_mm / count, "median_mm": edge(0.5), "p95_mm": edge(0.95), "max_mm": max_mm}


def build(args: argparse.Namespace) -> dict:
    """Run (or resume) the build; returns the metadata written into the asset."""
    from unibody import __version__
    from unibody.assets import ANNY_VERSION
    from unibody.identity.pca import ipca_finalize, ipca_init, ipca_update, write_asset
    from unibody.symmetry import canonical_mirror_map, mirror

    torch.set_num_threads(args.threads)
    recipe = Recipe()
    config = _config(args, recipe)
    ckpt = Path(args.checkpoint)
    layer = anny_layer()
    num_local = layer.identity.num_params - 6
    dim = 3 * layer.num_vertices
    n_chunks = -(-args.identities // args.chunk)
    if ckpt.is_file() and not args.restart:
        state, first, hist, elapsed = _load_checkpoint(ckpt, config)
        print(f"resuming from {ckpt}: chunk {first}/{n_chunks}, {state.count} samples, {elapsed:.0f} s so far")
    else:
        state, first, hist, elapsed = ipca_init(dim), 0, np.zeros(REPOSE_BINS + 2, dtype=np.int64), 0.0
    # hist[:-2] counts per-vertex repose displacements in REPOSE_BIN_MM bins; hist[-2] holds their
    # sum and hist[-1] their max, both in nm (integers, so the whole tally is one checkpoint array).
    print(f"{args.identities} identities, {n_chunks} chunks of {args.chunk}, rank {args.rank}, seed {args.seed}")
    t_loop = time.perf_counter()
    for c in range(first, n_chunks):
        t0 = time.perf_counter()
        start = c * args.chunk
        count = min(args.chunk, args.identities - start)
        params = sample_params(recipe, count, args.seed, num_local, start=start)
        rest, reposed = canonical_samples(layer, params)
        d_mm = (1e3 * (reposed - rest).norm(dim=-1)).double().flatten().numpy()
        hist[:-2] += np.bincount(
            np.minimum((d_mm / REPOSE_BIN_MM).astype(np.int64), REPOSE_BINS - 1), minlength=REPOSE_BINS
        )
        hist[-2] += int(round(1e6 * d_mm.sum()))
        hist[-1] = max(int(hist[-1]), int(round(1e6 * d_mm.max())))
        samples = torch.cat([reposed, mirror(reposed)]) if recipe.mirror_augmented else reposed
        t1 = time.perf_counter()
        state = ipca_update(state, samples.reshape(samples.shape[0], -1), args.rank)
        t2 = time.perf_counter()
        elapsed += t2 - t0
        _save_checkpoint(ckpt, state, c + 1, hist, config, elapsed)
        kept = float((state.singular**2).sum()) / state.sum_sq
        run_time = time.perf_counter() - t_loop
        eta = run_time / (c + 1 - first) * (n_chunks - c - 1)
        print(
            f"chunk {c + 1:3d}/{n_chunks}  samples {state.count:6d}  meshes {t1 - t0:5.1f} s  pca {t2 - t1:5.1f} s"
            f"  std[0] {float(state.singular[0]) / max(state.count - 1, 1) ** 0.5:.4f} m"
            f"  variance in rank {args.rank}: {100 * kept:.5f} %  ETA {eta:.0f} s",
            flush=True,
        )
        if args.stop_after is not None and c + 1 - first >= args.stop_after:
            print(f"stopped after {args.stop_after} chunk(s); run the same command again to continue")
            return {}
    mean, comps, std = ipca_finalize(state, args.components)
    variance = std**2
    total_var = state.sum_sq / (state.count - 1)
    sym = canonical_mirror_map()
    repose = _hist_stats(hist[:-2], hist[-2] * 1e-6, hist[-1] * 1e-6)
    command = (
        f"python scripts/build_pca.py --identities {args.identities} --seed {args.seed} --chunk {args.chunk} "
        f"--rank {args.rank} --components {args.components} --split-leading {args.split_leading}"
    )
    metadata = {
        "format_version": 1,
        "command": command,
        "seed": args.seed,
        "identities": args.identities,
        "samples": state.count,
        "chunk": args.chunk,
        "rank_kept_while_streaming": args.rank,
        "num_components": args.components,
        "components_storage": f"float16; the first {args.split_leading} also store their float16 remainder",
        "recipe": asdict(recipe),
        "source": f"anny=={ANNY_VERSION}, BodyLayer.from_anny(local_changes='all'), float32",
        "unibody_version": __version__,
        "std_unit": "m (norm of a whole (V, 3) mesh); coefficients are in standard deviations",
        "total_variance_m2": total_var,
        "explained_variance_fraction": float(variance.sum()) / total_var,
        "variance_kept_while_streaming_fraction": float((state.singular**2).sum()) / state.sum_sq,
        "repose_displacement": repose,
        "mirror_map": {"max_distance_um": 1e6 * sym.max_distance, "midplane_vertices": sym.num_midplane},
        "build_seconds": elapsed,
        "machine": f"{platform.machine()} {platform.processor() or ''} torch {torch.__version__}, "
        f"{args.threads} thread(s)",
    }
    v = layer.num_vertices
    out = Path(args.out)
    size = write_asset(
        out,
        mean=mean.reshape(v, 3).numpy(),
        components=comps.reshape(-1, v, 3).numpy(),
        std=std.numpy(),
        metadata=metadata,
        split_leading=args.split_leading,
    )
    metadata["asset_bytes"] = size
    out.with_suffix(".json").write_text(json.dumps(metadata, indent=2, sort_keys=True) + "\n")
    print(f"wrote {out} ({size:,} bytes) and {out.with_suffix('.json').name}")
    print(f"explained variance at K={args.components}: {100 * metadata['explained_variance_fraction']:.4f} %")
    print(
        f"reposing moved vertices by mean {repose['mean_mm']:.2f} mm, P95 {repose['p95_mm']:.2f} mm, "
        f"max {repose['max_mm']:.2f} mm; chunks took {elapsed:.0f} s in all"
    )
    return metadata


def parse_args(argv: list[str] | None = None) -> argparse.Namespace:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--identities", type=int, default=10000, help="Anny identities (twice as many samples)")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--chunk", type=int, default=256, help="identities per incremental update")
    p.add_argument("--rank", type=int, default=256, help="directions kept while streaming")
    p.add_argument("--components", type=int, default=128, help="directions shipped")
    p.add_argument("--split-leading", type=int, default=1, help="leading components stored as float16 hi + lo")
    p.add_argument("--out", default=str(DEFAULT_OUT))
    p.add_argument("--checkpoint", default=str(DEFAULT_CHECKPOINT))
    p.add_argument("--restart", action="store_true", help="ignore an existing checkpoint")
    p.add_argument("--stop-after", type=int, default=None, help="stop after this many chunks (testing resume)")
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
