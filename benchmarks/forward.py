"""Forward throughput of BodyLayer with the Anny backend.

Measures meshes/s and ms/call at several batch sizes for
  (a) posing a prepared identity (FK + LBS; one identity broadcast over the batch), and
  (b) the full forward with a distinct Anny identity per mesh (Anny blendshapes ->
      topology transfer -> skeleton transfer -> FK + LBS).
Inputs are seeded random poses (0.3 rad std axis-angle) and uniform phenotypes in [0, 1].

    python benchmarks/forward.py [--device cpu] [--dtype float32] [--threads 2] [--seed 0]
"""

from __future__ import annotations

import argparse
import platform
import time

import torch

from unibody import BodyLayer


def _time(fn, device: str, min_time: float = 1.0) -> float:
    """Median seconds per call over repeats filling ``min_time`` (after a warm-up)."""
    for _ in range(3):
        fn()
    sync = torch.cuda.synchronize if device.startswith("cuda") else (lambda: None)
    sync()
    times: list[float] = []
    start = time.perf_counter()
    while time.perf_counter() - start < min_time or len(times) < 5:
        t = time.perf_counter()
        fn()
        sync()
        times.append(time.perf_counter() - t)
    return sorted(times)[len(times) // 2]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--device", default="cpu")
    parser.add_argument("--dtype", default="float32", choices=["float32", "float64"])
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--batches", type=int, nargs="+", default=[1, 8, 32, 128])
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    dtype = getattr(torch, args.dtype)
    layer = BodyLayer.from_anny(dtype=dtype).to(args.device)
    gen = torch.Generator().manual_seed(args.seed)
    print(
        f"# {platform.processor() or platform.machine()}, torch {torch.__version__}, "
        f"{args.threads} threads, {args.device}, {args.dtype}"
    )
    print("| batch | (a) pose prepared: ms/call | meshes/s | (b) full forward: ms/call | meshes/s |")
    print("|---:|---:|---:|---:|---:|")
    with torch.inference_mode():
        prepared = layer.prepare_identity(torch.full((1, 6), 0.5, dtype=dtype, device=args.device))
        for b in args.batches:
            pose = (0.3 * torch.randn(b, 77, 3, generator=gen)).to(args.device, dtype)
            params = torch.rand(b, 6, generator=gen).to(args.device, dtype)
            ta = _time(lambda pose=pose: layer.pose(prepared, pose), args.device)
            tb = _time(lambda params=params, pose=pose: layer(params, pose), args.device)
            print(f"| {b} | {1e3 * ta:.2f} | {b / ta:,.0f} | {1e3 * tb:.2f} | {b / tb:,.0f} |")


if __name__ == "__main__":
    main()
