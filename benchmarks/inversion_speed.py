"""Pose-inversion speed and error per preset, optionally A/B against another copy of the inverter.

Measures frames/s (median per call over interleaved calls) and the mean / max per-vertex
error (mm) of the presets ``fast``, ``analytic`` and ``refined`` on meshes posed by unibody
itself: benchmarks/inversion.py's ``random`` protocol (one Anny identity, 0.3 rad std
axis-angle on every joint, 0.1 m translation std). With ``--baseline PATH`` (a copy of an
older ``inversion.py`` kept outside the repository, with ``_gauss_newton.py`` beside it) every
preset is also run through that copy in the same process, calls interleaved, and the ratio
new/old of frames/s is printed. ``--profile`` prints a torch.profiler table per preset.

    python benchmarks/inversion_speed.py [--batch 32 64] [--reps 15] [--threads 2]
    python benchmarks/inversion_speed.py --baseline /tmp/inv_old/inversion.py
    python benchmarks/inversion_speed.py --profile --presets refined --batch 32
"""

from __future__ import annotations

import argparse
import importlib.util
import statistics
import sys
import time
from pathlib import Path

import torch

from unibody import BodyLayer
from unibody.fitting.inversion import PRESETS, PoseInverter


def load_baseline(path: Path):
    """Import an inversion.py copy (and the _gauss_newton.py beside it) inside unibody.fitting."""
    gn_path = path.parent / "_gauss_newton.py"
    gn_name = "unibody.fitting._gauss_newton_baseline"
    spec = importlib.util.spec_from_file_location(gn_name, gn_path)
    gn = importlib.util.module_from_spec(spec)
    sys.modules[gn_name] = gn
    spec.loader.exec_module(gn)
    source = path.read_text().replace("from ._gauss_newton import", "from ._gauss_newton_baseline import")
    name = "unibody.fitting._inversion_baseline"
    module = importlib.util.module_from_spec(importlib.util.spec_from_loader(name, loader=None))
    module.__package__ = "unibody.fitting"
    sys.modules[name] = module
    exec(compile(source, str(path), "exec"), module.__dict__)
    return module


def data(layer, batch: int, seed: int, dtype: torch.dtype, device: str):
    gen = torch.Generator().manual_seed(seed)
    prepared = layer.prepare_identity(torch.rand(1, 6, generator=gen).to(device, dtype))
    pose = (0.3 * torch.randn(batch, 77, 3, generator=gen)).to(device, dtype)
    transl = (0.1 * torch.randn(batch, 3, generator=gen)).to(device, dtype)
    with torch.no_grad():
        target = layer.pose(prepared, pose, transl=transl).vertices
    return prepared, target


def error_mm(layer, prepared, target, result) -> tuple[float, float]:
    with torch.no_grad():
        posed = layer.pose(prepared, result.pose, transl=result.transl).vertices
    e = 1e3 * (posed - target).norm(dim=-1)
    return float(e.mean()), float(e.max())


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--batch", type=int, nargs="+", default=[32, 64])
    parser.add_argument("--presets", nargs="+", default=["fast", "analytic", "refined"])
    parser.add_argument("--reps", type=int, default=15)
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--device", default="cpu")
    parser.add_argument("--dtype", choices=["float32", "float64"], default="float32")
    parser.add_argument(
        "--clock",
        choices=["wall", "cpu"],
        default="wall",
        help="cpu: process CPU time (with --threads 1, a load-independent proxy on a shared machine)",
    )
    parser.add_argument("--baseline", type=Path, help="path of an older inversion.py to compare with")
    parser.add_argument("--profile", action="store_true", help="torch.profiler table per preset (new code)")
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    dtype = getattr(torch, args.dtype)
    layer = BodyLayer.from_anny().to(args.device, dtype)
    old = load_baseline(args.baseline) if args.baseline else None
    clock = time.perf_counter if args.clock == "wall" else time.process_time
    setup = f"threads {args.threads}, {args.device}, {args.dtype}, {args.clock} clock"
    print(f"{setup}, median of {args.reps} interleaved calls")
    print("| batch | preset | new frames/s | new mean / max mm | old frames/s | old mean / max mm | new/old |")
    print("|---:|---|---:|---|---:|---|---:|")
    for batch in args.batch:
        prepared, target = data(layer, batch, args.seed, dtype, args.device)
        for name in args.presets:
            runs = {"new": PoseInverter(layer, PRESETS[name])}
            if old is not None:
                runs["old"] = old.PoseInverter(layer, old.PRESETS[name])
            times = {k: [] for k in runs}
            results = {}
            with torch.no_grad():
                for k, inv in runs.items():  # warm-up
                    results[k] = inv.invert(target, prepared)
                for _ in range(args.reps):
                    for k, inv in runs.items():
                        if args.device != "cpu":
                            torch.cuda.synchronize()
                        t0 = clock()
                        inv.invert(target, prepared)
                        if args.device != "cpu":
                            torch.cuda.synchronize()
                        times[k].append(clock() - t0)
            fps = {k: batch / statistics.median(v) for k, v in times.items()}
            err = {k: error_mm(layer, prepared, target, r) for k, r in results.items()}
            cells = [f"{fps['new']:,.0f}", f"{err['new'][0]:.3f} / {err['new'][1]:.2f}"]
            if old is not None:
                cells += [f"{fps['old']:,.0f}", f"{err['old'][0]:.3f} / {err['old'][1]:.2f}"]
                cells.append(f"{fps['new'] / fps['old']:.2f}x")
            else:
                cells += ["", "", ""]
            print(f"| {batch} | {name} | " + " | ".join(cells) + " |", flush=True)
            if args.profile:
                profile(runs["new"], target, prepared)


def profile(inverter, target, prepared) -> None:
    from torch.profiler import ProfilerActivity, record_function
    from torch.profiler import profile as torch_profile

    with torch.no_grad(), torch_profile(activities=[ProfilerActivity.CPU]) as prof:
        for _ in range(5):
            with record_function("invert"):
                inverter.invert(target, prepared)
    print(prof.key_averages().table(sort_by="self_cpu_time_total", row_limit=25))


if __name__ == "__main__":
    main()
