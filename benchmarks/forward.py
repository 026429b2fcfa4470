"""Forward throughput of BodyLayer with the Anny backend, and where the time of one pose goes.

Measures meshes/s and ms/call at several batch sizes for
  (a) posing a prepared identity (FK + LBS, with ``transl``; one identity broadcast over the batch), and
  (b) the full forward with a distinct Anny identity per mesh (Anny blendshapes ->
      topology transfer -> skeleton transfer -> FK + LBS).
Inputs are seeded random poses (0.3 rad std axis-angle), translations (0.1 m std) and uniform
phenotypes in [0, 1]. Times are medians of wall-clock calls (CUDA-synchronised on a GPU).
The side-by-side comparison with py-soma-x is ``benchmarks/peer.py``.

  --compile   also time (a) with ``layer.compile_posing()`` and print the first call (compile) time
  --profile   torch.profiler summary of (a) at batch 1: milliseconds per pose by operator

    python benchmarks/forward.py [--device cpu] [--dtype float32] [--threads 2] [--seed 0] [--compile] [--profile]
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


def profile_batch1(layer: BodyLayer, prepared, pose: torch.Tensor, transl: torch.Tensor, rows: int = 12) -> None:
    """Print the operators that take the time of a batch-1 pose (self CPU time, ms per pose)."""
    from torch.profiler import ProfilerActivity, profile

    n = 200
    for _ in range(20):
        layer.pose(prepared, pose, transl=transl)
    with profile(activities=[ProfilerActivity.CPU]) as prof:
        for _ in range(n):
            layer.pose(prepared, pose, transl=transl)
    events = sorted(prof.key_averages(), key=lambda e: -e.self_cpu_time_total)
    total = sum(e.self_cpu_time_total for e in events) / n / 1e3
    print(f"\nbatch-1 pose under the profiler: {total:.3f} ms of operator time per pose (profiler overhead included)")
    print("| operator | calls/pose | ms/pose | share |")
    print("|---|---:|---:|---:|")
    for e in events[:rows]:
        ms = e.self_cpu_time_total / n / 1e3
        print(f"| {e.key} | {e.count / n:g} | {ms:.3f} | {100 * ms / total:.0f} % |")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--device", default="cpu")
    parser.add_argument("--dtype", default="float32", choices=["float32", "float64"])
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--batches", type=int, nargs="+", default=[1, 8, 32, 128])
    parser.add_argument("--compile", action="store_true", help="also time layer.compile_posing()")
    parser.add_argument("--profile", action="store_true", help="profile a batch-1 pose")
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    dtype = getattr(torch, args.dtype)
    layer = BodyLayer.from_anny(dtype=dtype).to(args.device)
    gen = torch.Generator().manual_seed(args.seed)
    print(
        f"# {platform.processor() or platform.machine()}, torch {torch.__version__}, "
        f"{args.threads} threads, {args.device}, {args.dtype}"
    )
    inputs = {
        b: (
            (0.3 * torch.randn(b, 77, 3, generator=gen)).to(args.device, dtype),
            (0.1 * torch.randn(b, 3, generator=gen)).to(args.device, dtype),
            torch.rand(b, 6, generator=gen).to(args.device, dtype),
        )
        for b in args.batches
    }
    with torch.inference_mode():
        prepared = layer.prepare_identity(torch.full((1, 6), 0.5, dtype=dtype, device=args.device))
        print("| batch | (a) pose prepared: ms/call | meshes/s | (b) full forward: ms/call | meshes/s |")
        print("|---:|---:|---:|---:|---:|")
        for b, (pose, transl, params) in inputs.items():
            ta = _time(lambda pose=pose, transl=transl: layer.pose(prepared, pose, transl=transl), args.device)
            tb = _time(lambda p=params, pose=pose, transl=transl: layer(p, pose, transl=transl), args.device)
            print(f"| {b} | {1e3 * ta:.2f} | {b / ta:,.0f} | {1e3 * tb:.2f} | {b / tb:,.0f} |")
        if args.compile:
            layer.compile_posing()
            print(
                "\n| batch | (a) compiled: first call s | ms/call | meshes/s | eager ms/call | compiled / eager speed |"
            )
            print("|---:|---:|---:|---:|---:|---:|")
            for b, (pose, transl, _) in inputs.items():
                t0 = time.perf_counter()
                layer.pose(prepared, pose, transl=transl)
                first = time.perf_counter() - t0
                tc = _time(lambda pose=pose, transl=transl: layer.pose(prepared, pose, transl=transl), args.device)
                layer.compile_posing(False)
                te = _time(lambda pose=pose, transl=transl: layer.pose(prepared, pose, transl=transl), args.device)
                layer.compile_posing()
                print(f"| {b} | {first:.1f} | {1e3 * tc:.2f} | {b / tc:,.0f} | {1e3 * te:.2f} | {te / tc:.2f}x |")
            layer.compile_posing(False)
        if args.profile:
            pose, transl, _ = inputs.get(1) or (inputs[args.batches[0]][0][:1], inputs[args.batches[0]][1][:1], None)
            profile_batch1(layer, prepared, pose, transl)


if __name__ == "__main__":
    main()
