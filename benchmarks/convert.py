"""`unibody convert` figures (issue 34): AMASS throughput, scaling, BVH/ASF-AMC retargeting, round trips.

Sections (``--sections``, default all):
  amass      AMASS-format throughput and its time split: ``benchmarks/convert_amass.py``
  scaling    the same kind of generated SMPL-X takes through the real command line
             (``unibody convert --to motion``) with ``--jobs 1``, ``--jobs 2`` and a local Ray on
             2 CPUs; the hours AMASS (~17 M frames) would take on 1, 10 and 100 nodes
  skeletal   every CMU motion of ../shared/motions/cmu (BVH and ASF/AMC) retargeted, and the
             picture docs/convert_cmu.png: ``benchmarks/convert_skeletal.py``
  roundtrip  motion -> BVH -> motion, motion -> GLB -> independent reader (pygltflib + numpy
             skinning) -> mesh, motion -> SOMA npz -> motion, motion -> USD -> UsdSkel -> mesh

    python benchmarks/convert.py [--sections amass scaling skeletal roundtrip] [--quick]
"""

from __future__ import annotations

import argparse
import math
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import torch

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "tests"))
sys.path.insert(0, str(ROOT / "benchmarks"))

AMASS_FRAMES = 17e6  # AMASS, all subsets, native rates (about 17 M frames)


def _subprocess(script: str, *args: str) -> None:
    print(f"$ python benchmarks/{script} {' '.join(args)}", flush=True)
    subprocess.run([sys.executable, str(ROOT / "benchmarks" / script), *args], check=True)


def _cpu() -> str:
    for line in Path("/proc/cpuinfo").read_text().splitlines():
        if line.startswith("model name"):
            return line.split(":", 1)[1].strip()
    return "unknown CPU"


def scaling(takes: int, frames: int) -> None:
    """Files -> motion files through the command line: --jobs 1, --jobs 2, Ray (2 CPUs)."""
    from convert_amass import write_takes

    from smpl_format import canonical_model, write_npz
    from unibody.registration import topology_transfer

    rng = np.random.default_rng(0)
    with tempfile.TemporaryDirectory() as tmp:
        root = Path(tmp)
        model, _ = canonical_model("smplx", seed=0, num_shape=10)
        models = root / "models"
        models.mkdir()
        write_npz(models / "SMPLX_FEMALE.npz", model)
        t0 = time.perf_counter()
        # The real registration of this template, once: later runs read it from the disk cache.
        topology_transfer(
            torch.as_tensor(model["v_template"]).double(), torch.as_tensor(model["f"].astype(np.int64)), "smplx"
        )
        print(f"registration of the generated SMPL-X template (once, then cached): {time.perf_counter() - t0:.0f} s")
        inputs = root / "takes"
        inputs.mkdir()
        write_takes(inputs, takes, frames, rng)
        total = takes * frames
        rows = []
        runs = [
            ("--jobs 1", ["--jobs", "1"]),
            ("--jobs 2", ["--jobs", "2"]),
            ("Ray, 2 CPUs", ["--jobs", "2", "--executor", "ray"]),
        ]
        for label, extra in runs:
            out = root / f"out_{len(rows)}"
            cmd = [
                "unibody",
                "convert",
                str(inputs),
                "--to",
                "motion",
                "--out",
                str(out),
                "--models",
                str(models),
                *extra,
            ]
            t0 = time.perf_counter()
            subprocess.run(cmd, check=True, stderr=subprocess.DEVNULL, env={**os.environ, "RAY_ADDRESS": ""})
            seconds = time.perf_counter() - t0
            rows.append((label, seconds, total / seconds))
            print(f"{label}: {total} frames in {seconds:.1f} s", flush=True)
    print()
    ncores = len(os.sched_getaffinity(0))
    print(f"{takes} takes x {frames} frames = {total} frames, analytic preset, float32; {_cpu()}, {ncores} cores")
    print(
        "(wall time of the whole command: start-up, model loading, worker start, reading, posing, inversion, writing)"
    )
    print()
    print("| run | seconds | frames/s | speed-up |")
    print("|---|---:|---:|---:|")
    for label, seconds, rate in rows:
        print(f"| {label} | {seconds:.1f} | {rate:,.0f} | {rate / rows[0][2]:.2f}x |")
    cores = len(os.sched_getaffinity(0))
    per_core = max(rate for _, _, rate in rows) / cores  # every run used all the cores
    print()
    print(
        f"AMASS (~{AMASS_FRAMES / 1e6:.0f} M frames) at the best measured rate / {cores} cores = {per_core:,.0f} "
        "frames/s per core, scaling linearly (shards share nothing):"
    )
    print()
    print("| nodes | 2 cores each | 32 cores each |")
    print("|---:|---:|---:|")
    for nodes in (1, 10, 100):
        h2 = AMASS_FRAMES / (per_core * 2 * nodes) / 3600
        h32 = AMASS_FRAMES / (per_core * 32 * nodes) / 3600
        print(f"| {nodes} | {h2:.1f} h | {h32:.2f} h |")


def _random_motion(frames: int, seed: int = 0):
    from unibody.motion import Motion

    rng = np.random.default_rng(seed)
    t = np.arange(frames)[:, None, None] / 30.0
    pose = (0.3 * np.sin(2 * math.pi * (0.2 + rng.random((1, 77, 3))) * t + 6.3 * rng.random((1, 77, 3)))).astype(
        np.float32
    )
    transl = np.stack([0.3 * np.sin(t[:, 0, 0]), 0.9 + 0.02 * t[:, 0, 0], 0.5 * t[:, 0, 0]], -1).astype(np.float32)
    identity = (0.8 * rng.standard_normal(128)).astype(np.float32)
    return Motion(pose, transl, 30.0, identity, "pca", "benchmark")


def _angle(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Angle (rad) between rotations given as axis-angle arrays (..., 3)."""
    from unibody.geometry.rotations import axis_angle_to_matrix

    ra = axis_angle_to_matrix(torch.as_tensor(a, dtype=torch.float64))
    rb = axis_angle_to_matrix(torch.as_tensor(b, dtype=torch.float64))
    cos = ((ra.transpose(-1, -2) @ rb).diagonal(dim1=-2, dim2=-1).sum(-1) - 1) / 2
    return torch.arccos(cos.clamp(-1, 1)).numpy()


def roundtrip(frames: int) -> None:
    """Errors of each round trip on one random 30 fps motion of a non-mean PCA identity."""
    import test_convert_export
    from test_convert_export import _gltf_skin_at
    from unibody.convert import ConvertOptions
    from unibody.convert._body import body_for
    from unibody.convert.export import write_glb, write_usd
    from unibody.convert.formats import read_motion, reader, write_motion, writer

    motion = _random_motion(frames)
    test_convert_export.FPS = motion.fps  # the reader checks the key times against it
    options = ConvertOptions()
    layer, prepared = body_for(motion)
    with torch.no_grad():
        ref = layer.pose(prepared, torch.as_tensor(motion.pose), transl=torch.as_tensor(motion.transl))
    ref_v, ref_j = ref.vertices.numpy(), ref.joints.numpy()
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        root = Path(tmp)
        for fmt, suffix in (("bvh", ".bvh"), ("soma", ".soma.npz"), ("motion", ".motion.npz")):
            path = root / f"m{suffix}"
            t0 = time.perf_counter()
            (write_motion if fmt == "motion" else writer(fmt))(motion, path, options)
            back = (read_motion if fmt == "motion" else reader(fmt))(path, options).motion
            seconds = time.perf_counter() - t0
            rot = _angle(motion.pose, back.pose)
            lb, pb = body_for(back)
            with torch.no_grad():
                joints = lb.pose(pb, torch.as_tensor(back.pose), transl=torch.as_tensor(back.transl)).joints.numpy()
            jerr = np.linalg.norm(joints - ref_j, axis=-1) * 1000
            rows.append(
                (f"motion -> {fmt} -> motion", f"{rot.max():.1e} rad", f"{jerr.max():.3f} mm (joints)", seconds)
            )
        import pygltflib

        path = root / "m.glb"
        t0 = time.perf_counter()
        write_glb(motion, path, options)
        gltf = pygltflib.GLTF2().load(str(path))
        blob = gltf.binary_blob()
        errs = [np.linalg.norm(_gltf_skin_at(gltf, blob, k) - ref_v[k], axis=-1).max() * 1000 for k in range(frames)]
        rows.append(
            (
                "motion -> GLB -> pygltflib + numpy skinning",
                "",
                f"{max(errs):.3f} mm (vertices)",
                time.perf_counter() - t0,
            )
        )
        try:
            from pxr import Usd, UsdSkel
        except ImportError:
            print("usd-core missing: USD round trip skipped (pip install 'unibody[usd]')")
        else:
            path = root / "m.usdc"
            t0 = time.perf_counter()
            write_usd(motion, path, options)
            stage = Usd.Stage.Open(str(path))
            cache = UsdSkel.Cache()
            root_prim = UsdSkel.Root(stage.GetDefaultPrim())
            cache.Populate(root_prim, Usd.PrimDefaultPredicate)
            skel = cache.GetSkelQuery(UsdSkel.Skeleton(stage.GetPrimAtPath("/Body/Skeleton")))
            query = cache.GetSkinningQuery(stage.GetPrimAtPath("/Body/Mesh"))
            from pxr import UsdGeom, Vt

            points = UsdGeom.Mesh(stage.GetPrimAtPath("/Body/Mesh")).GetPointsAttr().Get()
            errs = []
            for k in range(frames):
                xf = skel.ComputeSkinningTransforms(k)
                p = Vt.Vec3fArray(points)
                query.ComputeSkinnedPoints(xf, p, k)
                errs.append(np.linalg.norm(np.asarray(p) - ref_v[k], axis=-1).max() * 1000)
            rows.append(
                ("motion -> USD -> UsdSkel skinning", "", f"{max(errs):.4f} mm (vertices)", time.perf_counter() - t0)
            )
    print()
    print(f"{frames} frames, 30 fps, a non-mean PCA identity; {_cpu()}")
    print()
    print("| round trip | largest rotation error | largest position error | seconds |")
    print("|---|---:|---:|---:|")
    for name, rot, pos, seconds in rows:
        print(f"| {name} | {rot} | {pos} | {seconds:.2f} |")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--sections", nargs="+", default=["amass", "scaling", "skeletal", "roundtrip"])
    ap.add_argument("--quick", action="store_true", help="small sizes, a smoke run")
    args = ap.parse_args()
    quick = args.quick
    if "amass" in args.sections:
        _subprocess("convert_amass.py", *(["--takes", "2", "--frames", "100"] if quick else []))
    if "scaling" in args.sections:
        scaling(4 if quick else 20, 100 if quick else 500)
    if "skeletal" in args.sections:
        _subprocess("convert_skeletal.py", *(["--limit", "2", "--no-picture"] if quick else []))
    if "roundtrip" in args.sections:
        roundtrip(10 if quick else 120)


if __name__ == "__main__":
    main()
