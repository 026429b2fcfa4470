"""Build the shipped PanoMan model (src/unibody/panoman/data/panoman_v1.pt) from synthetic data.

    OMP_NUM_THREADS=1 python scripts/build_panoman.py --work build/panoman [--out PATH]

Resumable: every stage writes its result under ``--work`` and is skipped when that file exists
(delete it to redo a stage). Progress goes to stdout. Everything is a function of ``--seed``;
the held-out sets of benchmarks/panoman.py use other seeds (dataset seed 1 and up).
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import pickle
import sys
import time
from pathlib import Path

import torch

from unibody.identity.pca import PCAIdentity
from unibody.io.atomic import atomic_path
from unibody.panoman import dataset
from unibody.panoman.body_fit import sparse_joint_regressor
from unibody.panoman.build import decompose, edge_graph, rla_matrix, train_beta_net, train_correction
from unibody.panoman.mesh import EdgeTopology
from unibody.panoman.model import SUBSETS, Decomposition, PanoMan, default_model_path
from unibody.panoman.nets import MLP, CorrectionNet
from unibody.panoman.splocs import SplocsConfig
from unibody.rig import Rig


def log(msg: str) -> None:
    print(f"[{time.strftime('%H:%M:%S')}] {msg}", flush=True)


def cached(path: Path, make):
    """``make()``, or the value a previous run saved at ``path``.

    Values are tensors and plain data, read back with ``torch.load(weights_only=True)``; a file
    that does not load so (an older cache holding objects, a truncated file) is rebuilt. The
    file is written atomically (unique exclusive temporary file, fsync, rename).
    """
    if path.exists():
        try:
            value = torch.load(path, map_location="cpu", weights_only=True)
        except (pickle.UnpicklingError, RuntimeError, EOFError) as e:
            log(f"rebuild: {path} does not load as plain data ({type(e).__name__})")
        else:
            log(f"resume: {path}")
            return value
    value = make()
    with atomic_path(path) as tmp:
        torch.save(value, tmp)
    return value


def _fields(dec: Decomposition) -> dict:
    return {f.name: getattr(dec, f.name) for f in dataclasses.fields(dec)}


def main(argv=None) -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--work", type=Path, default=Path("build/panoman"))
    p.add_argument("--out", type=Path, default=default_model_path())
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--samples", type=int, nargs=3, default=(4000, 600, 1500), metavar=("BODY", "FACE", "HANDS"))
    p.add_argument("--components", type=int, nargs=3, default=(128, 32, 32), metavar=("BODY", "FACE", "HANDS"))
    p.add_argument("--sparsity", type=float, default=None, help="SplocsConfig.sparsity (default: its own)")
    p.add_argument("--iterations", type=int, default=10)
    p.add_argument("--net-steps", type=int, default=6000)
    p.add_argument("--correction-rank", type=int, default=16, help="0 disables the correction MLP")
    args = p.parse_args(argv)
    args.work.mkdir(parents=True, exist_ok=True)
    torch.manual_seed(args.seed)
    rig = Rig.canonical()
    topo = EdgeTopology.from_faces(rig.faces.long(), rig.num_vertices)
    makers = {"body": dataset.body_samples, "face": dataset.face_samples, "hands": dataset.hand_samples}
    n_samples = dict(zip(SUBSETS, args.samples, strict=False))
    n_comp = dict(zip(SUBSETS, args.components, strict=False))

    data = {}
    for subset in SUBSETS:

        def make(subset=subset):
            log(f"{subset}: {n_samples[subset]} samples")
            s = makers[subset](n_samples[subset], seed=args.seed)
            rl, ra = rla_matrix(s, topo)
            return {"rl": rl, "ra": ra, "pose": s.pose.float(), "shape": s.shape.float()}

        data[subset] = cached(args.work / f"rla_{subset}.pt", make)

    mean_rest = PCAIdentity.from_asset(num_components=1, dtype=torch.float64).mean
    graph, _ = edge_graph(topo, mean_rest)
    decs = []
    for subset in SUBSETS:
        for q in ("rl", "ra"):
            kw = {} if args.sparsity is None else {"sparsity": args.sparsity}
            cfg = SplocsConfig(num_components=n_comp[subset], iterations=args.iterations, seed=args.seed, **kw)

            def make(q=q, subset=subset, cfg=cfg):
                def progress(stage, i, n):
                    if i == n or i % 10 == 0:
                        log(f"{q}/{subset} {stage} {i}/{n}")

                dec, res = decompose(data[subset][q], graph, q, subset, cfg, progress=progress)
                sizes = dec.support_sizes().float()
                log(
                    f"{q}/{subset}: {dec.num_components} components, support median {sizes.median():.0f} "
                    f"max {sizes.max():.0f} edges of {topo.num_edges}"
                )
                return _fields(dec)  # plain data, loadable with weights_only=True

            decs.append(Decomposition(**cached(args.work / f"dec_{q}_{subset}.pt", make)))

    model = PanoMan(decs)
    sl = model.beta_slices()
    beta = {s: model.project(data[s]["rl"], data[s]["ra"]).float() for s in SUBSETS}

    # beta(theta): body and hand samples; targets = their weights with the face weights left out
    keep = torch.ones(model.num_beta, dtype=torch.bool)
    for q in ("rl", "ra"):
        keep[sl[(q, "face")]] = False

    def make_beta_net():
        pose = torch.cat([data["body"]["pose"], data["hands"]["pose"]])
        tgt = torch.cat([beta["body"], beta["hands"]])
        # each subset's own weights only: the other subset's weights are ~0 on its samples anyway
        log(f"beta(theta): {pose.shape[0]} poses -> {int(keep.sum())} weights")
        net = train_beta_net(pose, tgt, keep, steps=args.net_steps, seed=args.seed, log=log)
        return net.state()

    beta_net = MLP.from_state(cached(args.work / "beta_net.pt", make_beta_net))

    correction = None
    if args.correction_rank > 0:

        def make_correction():
            b = beta["body"].double()
            rl_hat, ra_hat = model.rla(b, corrected=False)
            resid = torch.cat([data["body"]["rl"].double() - rl_hat, data["body"]["ra"].double() - ra_hat], dim=1)
            log(
                f"correction: residual rms rl {resid[:, : topo.num_edges].pow(2).mean().sqrt():.2e} "
                f"ra {resid[:, topo.num_edges :].pow(2).mean().sqrt():.2e}"
            )
            net = train_correction(
                model.body_beta(b).float(),
                resid.float(),
                rank=args.correction_rank,
                steps=args.net_steps,
                seed=args.seed,
                log=log,
            )
            return net.state()

        correction = CorrectionNet.from_state(cached(args.work / "correction.pt", make_correction))

    def make_regressor():
        meshes = torch.cat(
            [
                dataset.body_samples(64, seed=args.seed, dtype=torch.float64).posed,
                dataset.hand_samples(64, seed=args.seed, dtype=torch.float64).posed,
            ]
        )
        return list(sparse_joint_regressor(meshes))

    joint_regressor = tuple(cached(args.work / "joint_regressor.pt", make_regressor))

    recipe = {
        "command": f"OMP_NUM_THREADS={os.environ.get('OMP_NUM_THREADS', '')} python scripts/build_panoman.py "
        + " ".join(sys.argv[1:] if argv is None else argv),
        "seed": args.seed,
        "samples": n_samples,
        "components": n_comp,
        "iterations": args.iterations,
        "net_steps": args.net_steps,
        "correction_rank": args.correction_rank,
    }
    final = PanoMan(
        decs, beta_net=beta_net, correction=correction, joint_regressor=joint_regressor, metadata={"recipe": recipe}
    )
    args.out.parent.mkdir(parents=True, exist_ok=True)
    with atomic_path(args.out) as tmp:
        final.save(tmp)
    log(f"wrote {args.out} ({args.out.stat().st_size / 1e6:.1f} MB): {json.dumps(recipe)}")


if __name__ == "__main__":
    main()
