"""Pose inversion on bad input: outlier vertices and the cost of the input checks.

Two tables, from seeded random poses (0.25 rad std on every joint, 0.1 m translation std) of
one Anny identity:

  outliers  mean per-vertex error over the inlier vertices (mm) with 0, 1 or 10 vertices moved
            1 km (or 0.5 m) away in every frame, per preset;
  speed     frames/s of each preset on clean meshes, batch 64, best of --repeats runs.

    python benchmarks/inversion_robust.py [--dtype float32] [--threads 2] [--frames 64] [--repeats 5]
"""

from __future__ import annotations

import argparse
import time

import torch

from unibody import BodyLayer
from unibody.fitting.inversion import PRESETS, PoseInverter


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--dtype", choices=["float32", "float64"], default="float32")
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument("--frames", type=int, default=64)
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--presets", nargs="+", default=["fast", "analytic", "svd"])
    parser.add_argument("--sections", nargs="+", default=["outliers", "speed"])
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    dtype = getattr(torch, args.dtype)
    layer = BodyLayer.from_anny(dtype=dtype)
    gen = torch.Generator().manual_seed(0)
    prepared = layer.prepare_identity(torch.full((1, 6), 0.5, dtype=dtype))
    pose = (0.25 * torch.randn(args.frames, 77, 3, generator=gen, dtype=torch.float64)).to(dtype)
    transl = (0.1 * torch.randn(args.frames, 3, generator=gen, dtype=torch.float64)).to(dtype)
    with torch.no_grad():
        target = layer.pose(prepared, pose, transl=transl).vertices
    inverters = {p: PoseInverter(layer, PRESETS[p]) for p in args.presets}
    if "outliers" in args.sections:
        print(f"mean inlier per-vertex error, mm ({args.frames} frames, {args.dtype})")
        cases = [("clean", 0, 0.0), ("1 vertex 1 km away", 1, 1000.0), ("10 vertices 1 km away", 10, 1000.0),
                 ("10 vertices 0.5 m away", 10, 0.5)]  # fmt: skip
        print(f"{'case':<26}" + "".join(f"{p:>12}" for p in args.presets))
        for name, count, dist in cases:
            bad = torch.randperm(layer.num_vertices, generator=gen)[:count]
            direction = torch.nn.functional.normalize(torch.randn(args.frames, count, 3, generator=gen), dim=-1)
            moved = target.clone()
            moved[:, bad] += dist * direction.to(dtype)
            row = f"{name:<26}"
            for inv in inverters.values():
                with torch.no_grad():
                    r = inv.invert(moved, prepared)
                keep = torch.ones(layer.num_vertices, dtype=torch.bool)
                keep[bad] = False
                err = (r.vertices - target)[:, keep].norm(dim=-1)
                row += f"{1e3 * float(err.mean()):12.2f}"
            print(row)
    if "speed" in args.sections:
        print(f"\nframes/s at batch {args.frames}, {args.threads} threads, {args.dtype}, best of {args.repeats}")
        for p, inv in inverters.items():
            with torch.no_grad():
                inv.invert(target, prepared)
                best = float("inf")
                for _ in range(args.repeats):
                    t0 = time.perf_counter()
                    inv.invert(target, prepared)
                    best = min(best, time.perf_counter() - t0)
            print(f"{p:<12}{args.frames / best:10.1f}")


if __name__ == "__main__":
    main()
