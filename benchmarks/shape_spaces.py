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
directions of the build checkpoint; with ``--fit-identities`` below ``--identities`` they are
repeated on that subset, so that they compare like for like with the fitted rows.

Fitted rows (backends whose shape space is not a linear basis on the canonical mesh): the
first ``--fit-identities`` held-out meshes (default 50, to keep the default run under ~10
minutes on one thread; the table's "held-out" column says how many) are fitted with
:func:`unibody.fitting.shape_fit.fit_identity`, which minimises the mean squared per-vertex distance
to ``layer.repose_to_bind(layer.prepare_identity(params))`` through the whole differentiable
pipeline (identity -> topology transfer -> skeleton fit -> repose), parameters kept in their
ranges, from the backend's default parameters, float32, ``--fit-adam`` Adam steps (default 0)
then up to ``--fit-lbfgs`` L-BFGS iterations (default 400), in batches of ``--fit-batch``:
- "Anny, 6 phenotypes" (``BodyLayer.from_anny()``): what 6 phenotypes explain of identities
  made with local changes (the analogue of a low-dimensional model such as SMPL-10 in Table 5);
  the phenotype model is multilinear, so a fit can end in a local minimum.
- "Anny, phenotypes + 256 local changes" (``BodyLayer.from_anny(local_changes="all")``): the
  generating model itself, a sanity row: its residual is what the fitter leaves, not a
  property of the shape space (it tends to 0 with more iterations).
- SMPL / MHR / GarmentMeasurements: only when the user's files are given (``UNIBODY_SMPL_FILE``,
  ``UNIBODY_MHR_DIR``, ``UNIBODY_GARMENT_DIR``; ``unibody.identity.create`` then
  ``BodyLayer.from_identity``, which registers the template the first time); otherwise one
  line says why the row is skipped. Note the held-out set is Anny-generated: a low residual
  says how much of Anny's space a model covers, not how well it fits real bodies.
"fit (s)" is the wall time of the whole row's fit.

Storage: the same coefficients through the stored directions (shipped; float16 only; int8
with one scale per component) against the float64 ones, i.e. what each storage costs a user
of ``forward``. Also printed: forward timing of the PCA backend against Anny + topology
transfer.

    python benchmarks/shape_spaces.py [--identities 200] [--seed 1] [--threads 1] [--fit-identities 50]
        [--fit-lbfgs 400] [--fit-adam 0] [--fit-batch 50]
"""

from __future__ import annotations

import argparse
import os
import sys
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "scripts"))
import build_pca  # noqa: E402  (the training recipe, sampler and reposing, shared on purpose)

from unibody import BodyLayer  # noqa: E402
from unibody.fitting.shape_fit import fit_identity  # noqa: E402
from unibody.identity import ENV_VARS, create  # noqa: E402
from unibody.identity.pca import IPCAState, PCAIdentity, default_asset_path, ipca_finalize  # noqa: E402

KS = (10, 32, 64, 128)
USER_BACKENDS = ("smpl", "mhr", "garment")
FIT_ADAM, FIT_LBFGS = 0, 400
LABELS = {"smpl": "SMPL", "smplh": "SMPL-H", "smplx": "SMPL-X", "mhr": "MHR", "garment": "GarmentMeasurements"}


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
    """Per-vertex reconstruction error (mm) of one shape space with k parameters.

    ``held_out``: meshes evaluated; ``fit_s``: seconds the fit took (None for a projection).
    """

    name: str
    k: int
    mean: float
    median: float
    p95: float
    held_out: int = 0
    fit_s: float | None = None


def error_row(name: str, k: int, per_vertex_mm: np.ndarray, held_out: int, fit_s: float | None = None) -> Row:
    """A row from per-vertex distances (any shape), mm."""
    d = per_vertex_mm.ravel()
    return Row(name, k, float(d.mean()), *(float(x) for x in np.percentile(d, [50, 95])), held_out, fit_s)


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
        per_vertex = 1e3 * err.reshape(meshes.shape).norm(dim=-1).numpy()
        rows.append(error_row(basis.name, k, per_vertex, meshes.shape[0]))
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


@dataclass(frozen=True)
class FitSettings:
    """How the fitted rows run :func:`unibody.fitting.shape_fit.fit_identity` (``batch``: identities per call)."""

    adam: int
    lbfgs: int
    lr: float
    batch: int


def fitted_row(label: str, layer: BodyLayer, targets: torch.Tensor, settings: FitSettings) -> Row:
    """Fit the layer's identity parameters to ``targets`` (N, V, 3), bind A-pose; one row."""
    n, k = targets.shape[0], layer.identity.num_params
    dtype = layer.skeleton.bind_rot.dtype
    errors, t0 = [], time.perf_counter()
    for s in range(0, n, settings.batch):
        e = min(n, s + settings.batch)
        print(f"{label} ({k} parameters): fitting identities {s}..{e - 1} of {n}", flush=True)
        fit = fit_identity(
            layer,
            targets[s:e].to(dtype),
            steps=settings.adam,
            lr=settings.lr,
            lbfgs_steps=settings.lbfgs,
            progress=lambda line: print(line, flush=True),
        )
        errors.append(1e3 * fit.per_vertex_error.double().numpy())
    seconds = time.perf_counter() - t0
    per_identity = np.concatenate(errors).mean(axis=1)
    worst = int(per_identity.argmax())
    print(
        f"{label}: mean per-vertex error per identity: median {np.median(per_identity):.3f} mm, "
        f"max {per_identity[worst]:.3f} mm (held-out identity {worst}); under 1 mm: "
        f"{int((per_identity < 1.0).sum())} of {n}; {seconds:.0f} s"
    )
    return error_row(f"{label} (fitted)", k, np.concatenate(errors), n, seconds)


def user_layer(name: str) -> tuple[str, BodyLayer | None, str]:
    """``(label, layer, "")`` for a backend whose user files are present, else ``(label, None, why)``."""
    label, env = LABELS[name], ENV_VARS[name]
    if not os.environ.get(env):
        return label, None, f"{env} is not set (the user's {label} model files; none ship with unibody)"
    try:
        from unibody.registration import topology_transfer  # noqa: F401  (BodyLayer.from_identity needs it)
    except ImportError:
        return label, None, "unibody.registration.topology_transfer is not available (BodyLayer.from_identity needs it)"
    try:
        identity = create(name)
        label = LABELS.get(identity.name, label)
        return label, BodyLayer.from_identity(identity), ""
    except (OSError, ValueError, TypeError, KeyError) as exc:
        return label, None, f"could not build it from ${env}: {exc}"


def fitted_rows(anny_all: BodyLayer, targets: torch.Tensor, settings: FitSettings) -> list[Row]:
    """Rows of the backends fitted through the pipeline (Anny twice, then user backends if present)."""
    rows = [
        fitted_row("Anny, 6 phenotypes", BodyLayer.from_anny(), targets, settings),
        fitted_row("Anny, phenotypes + 256 local changes", anny_all, targets, settings),
    ]
    for name in USER_BACKENDS:
        label, layer, why = user_layer(name)
        if layer is None:
            print(f"{label} row skipped: {why}")
        else:
            rows.append(fitted_row(label, layer, targets, settings))
    return rows


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
    parser.add_argument(
        "--fit-identities", type=int, default=50, help="held-out identities for the fitted rows (0: no fitted rows)"
    )
    parser.add_argument("--fit-batch", type=int, default=50, help="identities per fit_identity call")
    parser.add_argument("--fit-adam", type=int, default=FIT_ADAM, help="Adam steps per fit")
    parser.add_argument("--fit-lr", type=float, default=0.05, help="Adam learning rate")
    parser.add_argument("--fit-lbfgs", type=int, default=FIT_LBFGS, help="L-BFGS iterations per fit, after Adam")
    args = parser.parse_args()
    if args.device != "cpu":
        parser.error("--device: only cpu is supported")
    if not 0 <= args.fit_identities <= args.identities:
        parser.error(f"--fit-identities: expected 0..{args.identities} (--identities), got {args.fit_identities}")
    if args.fit_batch < 1:
        parser.error(f"--fit-batch: expected >= 1, got {args.fit_batch}")
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
    n_fit = args.fit_identities
    if n_fit:
        if n_fit < args.identities:  # the linear bases on the fitted subset too, for a like-for-like comparison
            rows += [row for basis in bases for row in evaluate(basis, meshes[:n_fit])]
        settings = FitSettings(args.fit_adam, args.fit_lbfgs, args.fit_lr, args.fit_batch)
        print(
            f"\nfitted rows: the first {n_fit} held-out identities, fit_identity with {settings.adam} Adam steps "
            f"(lr {settings.lr}) then up to {settings.lbfgs} L-BFGS iterations, float32, batches of {settings.batch}"
        )
        rows += fitted_rows(layer, meshes[:n_fit], settings)
    print(
        "\n| shape space | k | held-out | mean (mm) | median (mm) | P95 (mm) | fit (s) |"
        "\n|---|---:|---:|---:|---:|---:|---:|"
    )
    for r in rows:
        fit_s = "—" if r.fit_s is None else f"{r.fit_s:.0f}"
        print(f"| {r.name} | {r.k} | {r.held_out} | {r.mean:.3f} | {r.median:.3f} | {r.p95:.3f} | {fit_s} |")
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
