"""Memory settings of the process against the default: glibc's malloc thresholds, huge pages.

Each large temporary of a batch (a 28 MB blend buffer at batch 32) is, by default, mapped afresh
from the system and page-faulted in on every call: glibc hands blocks past its mmap threshold
back when freed and trims its heap. Compared here: the default; PyTorch's
``THP_MEM_ALLOC_ENABLE=1`` (large tensors on transparent huge pages); and glibc's
``MALLOC_MMAP_THRESHOLD_`` at its 32 MB cap with ``MALLOC_TRIM_THRESHOLD_`` at 1 GB (freed memory
kept by the process; peak memory unchanged). These are read once per process, so each round
starts one child process per setting, in turn (the order alternates), and each child times the
workloads (median of ``--reps`` calls). Printed: the median over rounds, and default / setting
(> 1: the setting is faster). unibody sets none of them: they are the user's process-wide choice
(docs/body.md, "Speed").

    python benchmarks/allocator.py [--rounds 5] [--reps 9] [--threads 2]
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import time

# glibc's malloc: no fresh mmap (and page faults) for blocks up to its 32 MB cap; freed memory kept
MALLOC = {"MALLOC_MMAP_THRESHOLD_": str(32 << 20), "MALLOC_TRIM_THRESHOLD_": str(1 << 30)}
SETTINGS = {"default": {}, "huge pages": {"THP_MEM_ALLOC_ENABLE": "1"}, "malloc": MALLOC}
WORKLOADS = ("full forward, batch 32", "full forward, batch 128", "pose, batch 32", "invert analytic, batch 32")


def child(reps: int, threads: int) -> dict[str, float]:
    """ms per call of each workload in this process."""
    import torch

    from unibody import PRESETS, BodyLayer, PoseInverter

    torch.set_num_threads(threads)
    layer = BodyLayer.from_anny()
    gen = torch.Generator().manual_seed(0)

    def timed(call) -> float:
        call()
        times = []
        for _ in range(reps):
            t0 = time.perf_counter()
            call()
            times.append(time.perf_counter() - t0)
        return 1e3 * statistics.median(times)

    out = {}
    with torch.no_grad():
        for b in (32, 128):
            params, pose = torch.rand(b, 6, generator=gen), 0.3 * torch.randn(b, 77, 3, generator=gen)
            out[f"full forward, batch {b}"] = timed(lambda p=params, q=pose: layer(p, q))
        prepared = layer.prepare_identity(torch.rand(1, 6, generator=gen))
        pose = 0.3 * torch.randn(32, 77, 3, generator=gen)
        out["pose, batch 32"] = timed(lambda: layer.pose(prepared, pose))
        target = layer.pose(prepared, pose).vertices.contiguous()
        inverter = PoseInverter(layer, PRESETS["analytic"])
        out["invert analytic, batch 32"] = timed(lambda: inverter.invert(target, prepared))
    return out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--rounds", type=int, default=3)
    parser.add_argument("--reps", type=int, default=9)
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument("--child", action="store_true", help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.child:
        print(json.dumps(child(args.reps, args.threads)))
        return
    runs: dict[str, list[dict[str, float]]] = {name: [] for name in SETTINGS}
    for r in range(args.rounds):
        order = list(SETTINGS) if r % 2 == 0 else list(reversed(SETTINGS))
        for setting in order:
            env = {k: v for k, v in os.environ.items() if k not in ("THP_MEM_ALLOC_ENABLE", *MALLOC)}
            env.update(SETTINGS[setting])
            cmd = [sys.executable, __file__, "--child", "--reps", str(args.reps), "--threads", str(args.threads)]
            done = subprocess.run(cmd, env=env, capture_output=True, text=True, check=True)
            runs[setting].append(json.loads(done.stdout.strip().splitlines()[-1]))
    thp = (
        open("/sys/kernel/mm/transparent_hugepage/enabled").read().strip()
        if os.path.exists("/sys/kernel/mm/transparent_hugepage/enabled")
        else "n/a"
    )
    print(f"{args.rounds} rounds x {args.reps} calls, {args.threads} threads, float32; kernel THP mode: {thp}\n")
    names = list(SETTINGS)
    head = " | ".join(f"{n} ms" for n in names) + " | " + " | ".join(f"default / {n}" for n in names[1:])
    print(f"| workload | {head} |\n|---|" + "---:|" * (2 * len(names) - 1))
    for w in WORKLOADS:
        ms = [statistics.median(r[w] for r in runs[n]) for n in names]
        cells = " | ".join(f"{m:.1f}" for m in ms) + " | " + " | ".join(f"{ms[0] / m:.2f}x" for m in ms[1:])
        print(f"| {w} | {cells} |")


if __name__ == "__main__":
    main()
