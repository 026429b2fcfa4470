"""Shape-space reconstruction error on held-out identities (paper 000 §4.4, Table 5 protocol).

Held-out set: ``--identities`` Anny identities drawn with ``--seed`` (default 1; the shipped
PCA was built with seed 0) from the same distribution as the PCA's training set (the recipe
is read from the asset's metadata) and reposed the same way, to the bind A-pose (see
``scripts/build_pca.py``). The script checks that no held-out identity coincides with a
training identity (it regenerates the training parameters from the asset's seed).

Each held-out mesh is projected (least squares over all 18,056 canonical vertices) onto
the first k directions of each basis; reported: the per-vertex distance between the mesh
and its projection, mean / median / P95 over all vertices of all meshes, in mm. No vertex is
excluded (inner mouth and eye vertices included).

A basis is any linear shape space on the canonical topology (:class:`Basis`: a mean and
directions, not necessarily orthonormal), so other backends (SMPL / SMPL-X / MHR shape
directions transferred to the canonical topology) can be added as rows with
:func:`evaluate`. Rows here: the shipped PCA and, with ``--checkpoint``, the float64
directions of the build checkpoint. Storage: the same coefficients through the stored
directions (shipped; float16 only; int8 with one scale per component) against the float64
ones, i.e. what each storage costs a user of ``forward``.
Also printed: forward timing of the PCA backend against Anny + topology transfer.

    python benchmarks/shape_spaces.py [--identities 200] [--seed 1] [--threads 1]
"""

from __future__ import annotations

import argparse
import sys
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "scripts"))
import build_pca  # noqa: E402  (the training recipe, sampler and reposing, shared on purpose)

from unibody.identity.pca import IPCAState, PCAIdentity, default_asset_path, ipca_finalize  # noqa: E402

KS = (10, 32, 64, 128)


@dataclass(frozen=True)
class Basis:
    """A linear shape space on the canonical topology.

    Attributes:
        name: row label.
        mean: (V, 3) m.
        directions: (K, V, 3) shape directions in order of importance (need not be orthonormal).
    """

    name: str
    mean: torch.Tensor
    directions: torch.Tensor


@dataclass(frozen=True)
class Row:
    """Per-vertex reconstruction error (mm) of one basis truncated to k directions."""

    name: str
    k: int
    mean: float
    median: float
    p95: float


def evaluate(basis: Basis, meshes: torch.Tensor, ks: tuple[int, ...] = KS) -> list[Row]:
    """Project meshes (N, V, 3) onto the first k directions of ``basis`` for each k (float64).

    Least squares through a QR of the directions: the first k columns of Q span exactly the
    first k directions, so one factorisation serves every k.
    """
    d = basis.directions.to(torch.float64).reshape(basis.directions.shape[0], -1)
    q, _ = torch.linalg.qr(d.T)  # (3V, K)
    resid = (meshes.to(torch.float64) - basis.mean.to(torch.float64)).reshape(meshes.shape[0], -1)
    coef = resid @ q
    rows = []
    for k in ks:
        if k > d.shape[0]:
            continue
        err = resid - coef[:, :k] @ q[:, :k].T
        per_vertex = 1e3 * err.reshape(meshes.shape).norm(dim=-1).flatten().numpy()
        rows.append(Row(basis.name, k, *(float(x) for x in (per_vertex.mean(), *np.percentile(per_vertex, [50, 95])))))
    return rows


def storage_error(reference: torch.Tensor, stored: torch.Tensor, std: torch.Tensor, coeffs: torch.Tensor) -> str:
    """Per-vertex distance (mm) between meshes made with reference and stored directions.

    Args:
        reference, stored: (K, V, 3) directions; std: (K,) m; coeffs: (N, K) in stds.
    """
    diff = (coeffs * std) @ (stored - reference).reshape(reference.shape[0], -1).to(coeffs.dtype)
    d = 1e3 * diff.reshape(coeffs.shape[0], -1, 3).norm(dim=-1)
    p95 = float(np.percentile(d.flatten().numpy(), 95))
    return f"mean {float(d.mean()):.4f} mm, P95 {p95:.4f} mm, max {float(d.max()):.4f} mm"


def int8_directions(directions: torch.Tensor) -> torch.Tensor:
    """The directions rounded to int8 with one scale per direction (max |entry| -> 127)."""
    flat = directions.reshape(directions.shape[0], -1).to(torch.float64)
    scale = flat.abs().amax(dim=1, keepdim=True) / 127.0
    return (torch.round(flat / scale) * scale).reshape(directions.shape)


def heldout_params(metadata: dict, count: int, seed: int, num_local: int) -> tuple[np.ndarray, float]:
    """Held-out parameters and their smallest L-inf distance to any training identity."""
    if seed == metadata["seed"]:
        raise SystemExit(f"--seed {seed} is the training seed; choose another for a held-out set")
    recipe = build_pca.Recipe.from_dict(metadata["recipe"])
    held = build_pca.sample_params(recipe, count, seed, num_local)
    train = build_pca.sample_params(recipe, metadata["identities"], metadata["seed"], num_local)
    closest = min(float(np.abs(train - h).max(axis=1).min()) for h in held)
    if closest == 0.0:
        raise SystemExit("a held-out identity coincides with a training identity")
    return held, closest


def _time(fn, reps: int) -> float:
    fn()
    t0 = time.perf_counter()
    for _ in range(reps):
        fn()
    return 1e3 * (time.perf_counter() - t0) / reps


def timing(pca: PCAIdentity, layer) -> list[str]:
    """ms per call: PCA forward vs Anny (local changes all) + topology transfer, float32."""
    lines = []
    with torch.no_grad():
        for b in (1, 32):
            c = torch.randn(b, pca.num_params, generator=torch.Generator().manual_seed(0))
            p = layer.identity.default_params(b)
            t_pca = _time(lambda c=c: pca(c), 20)
            t_anny = _time(lambda p=p: layer.topology(layer.identity(p)), 5)
            lines.append(f"| {b} | {t_pca:.3f} | {t_anny:.2f} | {t_anny / t_pca:.0f}x |")
    return lines


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--identities", type=int, default=200)
    parser.add_argument("--seed", type=int, default=1)
    parser.add_argument("--threads", type=int, default=1)
    parser.add_argument("--asset", default=None, help="a PCA asset (default: the shipped one)")
    parser.add_argument("--checkpoint", default=None, help="a build checkpoint: adds its float64 basis as a row")
    parser.add_argument("--device", default="cpu", help="only cpu")
    args = parser.parse_args()
    if args.device != "cpu":
        parser.error("--device: only cpu is supported")
    torch.set_num_threads(args.threads)
    t0 = time.perf_counter()
    pca = PCAIdentity.from_asset(args.asset, dtype=torch.float64)
    meta = pca.metadata
    layer = build_pca.anny_layer()
    num_local = layer.identity.num_params - 6
    params, closest = heldout_params(meta, args.identities, args.seed, num_local)
    print(
        f"held-out: {args.identities} identities, seed {args.seed}; training: {meta['identities']} identities "
        f"(seed {meta['seed']}, {meta['samples']} samples with mirrors); closest held-out/training "
        f"parameter distance (L-inf) {closest:.3f}"
    )
    rest, meshes = [], []
    for s in range(0, args.identities, 64):
        r, m = build_pca.canonical_samples(layer, params[s : s + 64])
        rest.append(r)
        meshes.append(m)
    rest, meshes = torch.cat(rest).double(), torch.cat(meshes).double()
    d = 1e3 * (meshes - rest).norm(dim=-1)
    print(
        f"reposing to the bind pose moved held-out vertices by mean {d.mean():.2f} mm, "
        f"median {d.median():.2f} mm, max {d.max():.2f} mm"
    )
    directions = pca.basis.reshape(pca.num_params, -1, 3)
    bases = [Basis("native PCA (shipped)", pca.mean, directions)]
    reference, ref_name = directions, "shipped"
    if args.checkpoint:
        with np.load(args.checkpoint, allow_pickle=False) as data:
            state = IPCAState.from_numpy({k: data[k] for k in data.files})
        mean, comps, _ = ipca_finalize(state, pca.num_params)
        reference, ref_name = comps.reshape(pca.num_params, -1, 3), "float64 (checkpoint)"
        bases.append(Basis("native PCA (float64, checkpoint)", mean.reshape(-1, 3), reference))
    rows = [row for basis in bases for row in evaluate(basis, meshes)]
    print("\n| basis | k | mean (mm) | median (mm) | P95 (mm) |\n|---|---:|---:|---:|---:|")
    for r in rows:
        print(f"| {r.name} | {r.k} | {r.mean:.3f} | {r.median:.3f} | {r.p95:.3f} |")
    coeffs = pca.project(meshes)
    with np.load(args.asset or default_asset_path(), allow_pickle=False) as data:
        hi = torch.from_numpy(data["components"].astype(np.float64))
    print(f"\nstorage: per-vertex distance to the {ref_name} directions, same coefficients (held-out projections)")
    variants = [
        ("shipped (float16, leading hi + lo, re-orthonormalised)", directions),
        ("float16 only", hi),
        ("int8 + per-component scale", int8_directions(reference)),
    ]
    for name, stored in variants:
        if stored is not reference:
            print(f"  {name}: {storage_error(reference, stored, pca.std, coeffs)}")
    print("\nforward, float32, one thread per --threads:\n")
    print("| batch | PCA ms/call | Anny + transfer ms/call | ratio |\n|---:|---:|---:|---:|")
    for line in timing(PCAIdentity.from_asset(args.asset), layer):
        print(line)
    print(f"\ntotal {time.perf_counter() - t0:.0f} s")


if __name__ == "__main__":
    main()
