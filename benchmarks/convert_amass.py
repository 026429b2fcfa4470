"""AMASS-format conversion throughput: generated SMPL-X takes -> unibody motion files (issue 34).

What it measures, on 2 threads (``torch.set_num_threads(2)``; ``--threads``), float32, CPU:
  - a generated SMPL-X-format model file (10,475 v, 55 joints, 10 shape + 10 expression
    columns) skinned exactly like the canonical body (``tests/smpl_format.canonical_model``:
    a seeded subset of the canonical bind mesh, merged canonical weights, exact joint
    regressor; its ``posedirs`` are zeros, but the pose-blendshape product runs all the same);
  - ``--takes`` AMASS SMPL-X files of ``--frames`` frames each (120 fps): smooth poses (per
    joint a sum of three sinusoids, 0.35 rad, fingers 0.2), a slow heading turn and a walk,
    Z up as in AMASS;
  - each file read, posed by :class:`SMPLModel`, mapped to the canonical topology, inverted
    (``--presets``, default analytic and fast) and written as a unibody motion file, with the
    time split (SMPL-X forward, transfer, inversion, I/O = read + write) and frames/s end to end;
  - the inversion error: per-vertex distance between the generating SMPL-X meshes on the
    canonical topology and the canonical body posed with the recovered motion (mean / max).

The registration of the template is replaced by the model's exact transfer (what a
registration gives; a real one costs ~40 s once per template, then comes from the disk
cache); the per-frame transfer is the same gather either way. One-time setup (model load,
inverter construction) is reported apart from the per-file rate.

    python benchmarks/convert_amass.py [--takes 20] [--frames 500] [--presets analytic fast] [--seed 0]
"""

from __future__ import annotations

import argparse
import copy
import math
import platform
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))
from smpl_format import canonical_model, write_npz  # noqa: E402  (the generated model file, shared on purpose)
from unibody.convert import ConvertOptions, amass  # noqa: E402
from unibody.motion import save_motion  # noqa: E402


def smooth_take(frames: int, rng: np.random.Generator, fps: float = 120.0) -> tuple[np.ndarray, np.ndarray]:
    """(T, 165) SMPL-X poses and (T, 3) Z-up translations of a smooth, seeded motion."""
    t = np.arange(frames)[:, None, None] / fps
    freq = 0.1 + 0.4 * rng.random((1, 55 * 3, 3))
    phase = 2 * math.pi * rng.random((1, 55 * 3, 3))
    amp = np.full((1, 55 * 3, 1), 0.35 / math.sqrt(3))
    amp[:, 25 * 3 :] = 0.2 / math.sqrt(3)  # the 30 hand joints
    poses = (amp * np.sin(2 * math.pi * freq * t + phase)).sum(-1)
    heading = 0.3 * t[:, 0, 0]
    # global orientation: SMPL's Y up turned to AMASS's Z up, then a slow turn about Z
    rx = np.array([[1, 0, 0], [0, 0, -1], [0, 1, 0]], dtype=np.float64)
    c, s = np.cos(heading), np.sin(heading)
    rz = np.stack(
        [np.stack([c, -s, 0 * c], -1), np.stack([s, c, 0 * c], -1), np.stack([0 * c, 0 * c, 1 + 0 * c], -1)], -2
    )
    poses[:, :3] = _matrix_to_axis_angle(rz @ rx)
    trans = np.stack([0.5 * np.sin(0.2 * t[:, 0, 0]), 0.8 * t[:, 0, 0] % 4.0, 0.9 + 0.02 * np.sin(5 * t[:, 0, 0])], 1)
    return poses, trans


def write_takes(folder: Path, takes: int, frames: int, rng: np.random.Generator) -> list[Path]:
    """``takes`` AMASS SMPL-X files (female, 120 fps) of :func:`smooth_take` motions in ``folder``."""
    paths = []
    for i in range(takes):
        poses, trans = smooth_take(frames, rng)
        path = folder / f"take_{i:03d}.npz"
        np.savez(
            path,
            poses=poses,
            trans=trans,
            betas=rng.normal(size=16),
            gender=np.array("female"),
            mocap_frame_rate=np.array(120.0),
            surface_model_type=np.array("smplx"),
        )
        paths.append(path)
    return paths


def _matrix_to_axis_angle(r: np.ndarray) -> np.ndarray:
    from unibody.geometry.rotations import matrix_to_axis_angle

    return matrix_to_axis_angle(torch.from_numpy(r)).numpy()


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--takes", type=int, default=20)
    parser.add_argument("--frames", type=int, default=500, help="frames per take")
    parser.add_argument("--presets", nargs="+", default=["analytic", "fast"])
    parser.add_argument("--batch", type=int, default=256)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--device", default="cpu", choices=["cpu"], help="the converter runs on the CPU")
    parser.add_argument(
        "--threads", type=int, default=2, help="torch threads (1 on a shared machine: 2 threads thrash under load)"
    )
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    rng = np.random.default_rng(args.seed)
    with tempfile.TemporaryDirectory() as tmp:
        root = Path(tmp)
        t0 = time.perf_counter()
        model, transfer = canonical_model("smplx", seed=args.seed, num_shape=10)
        write_npz(root / "SMPLX_FEMALE.npz", model)
        amass.topology_transfer = lambda *a, **k: copy.deepcopy(transfer)
        print(f"model file generated in {time.perf_counter() - t0:.1f} s")
        takes = write_takes(root, args.takes, args.frames, rng)
        rows = [run(preset, takes, root, args.batch) for preset in args.presets]
    frames = args.takes * args.frames
    print()
    print(
        f"{args.takes} takes x {args.frames} frames = {frames} frames, batch {args.batch}, float32, "
        f"{args.threads} thread(s); "
        f"{platform.processor() or platform.machine()}, {_cpu_name()}, load average {_load()}"
    )
    print()
    print(
        "| preset | setup s | forward s | transfer s | inversion s | I/O s | total s | frames/s end to end "
        "| inverter alone, frames/s | error mean mm | error max mm |"
    )
    print("|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|")
    for r in rows:
        print(
            f"| {r['preset']} | {r['setup']:.1f} | {r['forward']:.1f} | {r['transfer']:.1f} | {r['inversion']:.1f} "
            f"| {r['io']:.1f} | {r['total']:.1f} | **{frames / r['total']:,.0f}** | {r['alone']:,.0f} "
            f"| {r['mean']:.2f} | {r['max']:.1f} |"
        )


def run(preset: str, takes: list[Path], root: Path, batch: int) -> dict:
    options = ConvertOptions(models=root, preset=preset, batch=batch)
    t0 = time.perf_counter()
    amass.inverter(options)  # one-time: the canonical layer and the inverter
    amass._model(str(root / "SMPLX_FEMALE.npz"), (root / "SMPLX_FEMALE.npz").stat().st_mtime_ns, torch.float32)
    setup = time.perf_counter() - t0
    sums = {"forward": 0.0, "transfer": 0.0, "inversion": 0.0, "io": 0.0}
    err_sum, frames, worst = 0.0, 0, 0.0
    out = root / preset
    out.mkdir()
    alone = inverter_alone(takes[0], options)
    t0 = time.perf_counter()
    for path in takes:
        converted = amass.read_amass(path, options)
        t1 = time.perf_counter()
        save_motion(out / path.name, converted.motion)
        s = converted.stats
        sums["io"] += s["time_io_s"] + time.perf_counter() - t1
        sums["forward"] += s["time_forward_s"]
        sums["transfer"] += s["time_transfer_s"]
        sums["inversion"] += s["time_inversion_s"]
        err_sum += s["inversion_mean_mm"] * s["frames"]
        frames += s["frames"]
        worst = max(worst, s["inversion_max_mm"])
    total = time.perf_counter() - t0
    print(f"{preset}: {frames} frames in {total:.1f} s ({frames / total:.0f} frames/s)", flush=True)
    return {
        "preset": preset,
        "setup": setup,
        "total": total,
        "mean": err_sum / frames,
        "max": worst,
        "alone": alone,
        **sums,
    }


def inverter_alone(path: Path, options: ConvertOptions) -> float:
    """Frames/s of the inverter by itself on one take's canonical meshes (same batches): the
    reference the end-to-end rate is compared with, measured in the same process (the machine
    is shared; only ratios travel)."""
    layer, inv, dtype = amass.inverter(options)
    take = amass.read_take(path)
    model_path = root_model(path)
    model = amass._model(str(model_path), model_path.stat().st_mtime_ns, dtype)
    transfer = amass._transfer(str(model_path), model_path.stat().st_mtime_ns, dtype)
    betas = torch.zeros(1, model.num_betas)
    betas[0] = torch.as_tensor(take.betas[: model.num_betas], dtype=dtype)
    with torch.no_grad():
        prepared = layer.prepare_rest(transfer(model.shaped(betas)))
        pose = torch.as_tensor(take.poses, dtype=dtype)
        trans = torch.as_tensor(take.trans, dtype=dtype)
        target = transfer(amass.to_y_up(model(pose, betas, transl=trans).vertices))
        t0 = time.perf_counter()
        for start in range(0, len(target), options.batch):
            inv.invert(target[start : start + options.batch], prepared)
    return len(target) / (time.perf_counter() - t0)


def root_model(path: Path) -> Path:
    return path.parent / "SMPLX_FEMALE.npz"


def _load() -> str:
    try:
        return " ".join(Path("/proc/loadavg").read_text().split()[:3])
    except OSError:
        return "unknown"


def _cpu_name() -> str:
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return "unknown CPU"


if __name__ == "__main__":
    main()
