"""Retargeting real CMU motions (BVH and ASF/AMC) onto the canonical body: errors, flips, speed.

For every motion in ``../shared/motions/cmu/`` (68 BVH of cgspeed's 43-joint DAZ skeleton, 115
AMC with their subject's ASF; training data, free for development) it runs the reader of
``unibody convert`` (:mod:`unibody.convert.skeletal`) and prints, per format: files, frames, the
mapped-joint position error after retargeting (mean / P95 / max over all frames and mapped
joints, mm; against the source joints moved by their fitted constant offsets, and "raw"
against the source joints themselves), the worst excess of the largest recovered joint change
per frame over the source's (deg), and frames/s (reading included, one process).
Targets (issue 34): mean <= 20 mm, P95 <= 40 mm, excess <= 5 deg.

It then renders one motion, five frames side by side, the converted body with the source
skeleton overlaid (red), to ``docs/convert_cmu.png``.

    python benchmarks/convert_skeletal.py [--limit N] [--threads 1] [--data ../shared/motions/cmu]
        [--picture bvh/002/02_01.bvh] [--no-picture]
"""

from __future__ import annotations

import argparse
import platform
import time
from pathlib import Path

import numpy as np
import torch
from PIL import Image, ImageDraw

from unibody.convert import ConvertOptions
from unibody.convert._body import body_for
from unibody.convert.skeletal import find_asf, metres_per_unit, read_amc, read_bvh
from unibody.io.asfamc import read_asf_amc
from unibody.io.bvh import read_bvh as read_bvh_file
from unibody.viz.render import MeshSpec, frame_camera, project, render_image

ROOT = Path(__file__).resolve().parents[1]


def _files(data: Path, limit: int | None) -> dict[str, list[Path]]:
    out = {"bvh": sorted((data / "bvh").rglob("*.bvh")), "amc": sorted((data / "asfamc").rglob("*.amc"))}
    if limit is not None:  # spread over subjects: every k-th file
        out = {k: v[:: max(1, len(v) // limit)][:limit] for k, v in out.items()}
    return out


def _table(data: Path, limit: int | None) -> None:
    opts = ConvertOptions()
    cols = "format | files | frames | mean mm | P95 mm | max mm | raw mean mm | raw P95 mm | worst excess deg"
    cols += " | frames/s"
    print(f"| {cols} |")
    print("|---|---|---|---|---|---|---|---|---|---|")
    worst_files = []
    for fmt, files in _files(data, limit).items():
        read = read_bvh if fmt == "bvh" else read_amc
        n_frames, sums, seconds = 0, np.zeros(2), 0.0
        p95s, maxs, raw95, excess = [], [], [], []
        for f in files:
            t = time.perf_counter()
            s = read(f, opts).stats
            seconds += time.perf_counter() - t
            n = s["frames"]
            n_frames += n
            sums += n * np.array([s["retarget_mean_mm"], s["retarget_raw_mean_mm"]])
            p95s.append((s["retarget_p95_mm"], n))
            raw95.append((s["retarget_raw_p95_mm"], n))
            maxs.append(s["retarget_max_mm"])
            excess.append(s["max_joint_change_deg"] - s["source_max_joint_change_deg"])
            worst_files.append((s["retarget_p95_mm"], s["retarget_mean_mm"], excess[-1], f.name))
        # P95 over all samples is approximated by the frame-weighted mean of the per-file P95s.
        w95 = sum(p * n for p, n in p95s) / n_frames
        r95 = sum(p * n for p, n in raw95) / n_frames
        mean, raw_mean = sums / n_frames
        print(
            f"| {fmt} | {len(files)} | {n_frames} | {mean:.1f} | {w95:.1f} | {max(maxs):.1f} | {raw_mean:.1f} | "
            f"{r95:.1f} | {max(excess):+.1f} | {n_frames / seconds:.0f} |"
        )
    worst_files.sort(reverse=True)
    print("\nworst files by P95 (P95 mm, mean mm, excess deg, file):")
    for p95, mean, exc, name in worst_files[:5]:
        print(f"  {p95:6.1f} {mean:6.1f} {exc:+6.1f}  {name}")


def _source_skeleton(path: Path) -> tuple[np.ndarray, np.ndarray]:
    """World joint positions (T, J, 3) m of a file's own skeleton, and its parents."""
    sk = read_bvh_file(path) if path.suffix == ".bvh" else read_asf_amc(find_asf(path), path)
    pos, _ = sk.world()
    return pos * metres_per_unit(sk, None, ""), sk.parents


def _picture(path: Path, out: Path, frames: int = 5) -> None:
    conv = (read_bvh if path.suffix == ".bvh" else read_amc)(path, ConvertOptions())
    motion = conv.motion
    layer, prepared = body_for(motion)
    t = motion.pose.shape[0]
    idx = np.linspace(0, t - 1, frames + 2)[1:-1].round().astype(int)
    with torch.no_grad():
        o = layer.pose(prepared, torch.as_tensor(motion.pose[idx]), transl=torch.as_tensor(motion.transl[idx]))
    verts = o.vertices.numpy().astype(np.float64)
    src, parents = _source_skeleton(path)
    src = src[idx]
    faces = layer.faces.numpy()
    meshes, skel = [], []
    for i in range(frames):  # side by side along X, each frame centred on its Hips
        shift = np.array([0.9 * i - motion.transl[idx[i], 0], 0.0, -motion.transl[idx[i], 2]])
        meshes.append(MeshSpec(verts[i] + shift, faces, (0.72, 0.76, 0.82), f"frame {idx[i]}"))
        skel.append(src[i] + shift)
    ground = float(min(v[:, 1].min() for v in verts))
    w, h = 2000, 640
    cam = frame_camera(meshes, "front", w, h)
    img = Image.fromarray(render_image(meshes, width=w, height=h, view="front", ground_y=ground, camera=cam))
    draw = ImageDraw.Draw(img)
    for pts in skel:
        px = project(cam, pts, w, h)
        for j, p in enumerate(parents):
            if p >= 0:
                draw.line([tuple(px[p, :2]), tuple(px[j, :2])], fill=(220, 30, 30), width=3)
        for x, y, _ in px:
            draw.ellipse([x - 4, y - 4, x + 4, y + 4], fill=(150, 0, 0))
    out.parent.mkdir(parents=True, exist_ok=True)
    img.save(out)
    s = conv.stats
    print(
        f"\npicture: {out} ({path.name}, frames {idx.tolist()}; mean {s['retarget_mean_mm']:.1f} mm, "
        f"raw mean {s['retarget_raw_mean_mm']:.1f} mm)"
    )


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--data", type=Path, default=ROOT.parent / "shared" / "motions" / "cmu")
    ap.add_argument("--limit", type=int, default=None, help="files per format (spread over subjects)")
    ap.add_argument("--threads", type=int, default=1, help="torch threads (the solver itself runs on one)")
    ap.add_argument("--picture", default="bvh/002/02_01.bvh", help="motion to render, relative to --data")
    ap.add_argument("--out", type=Path, default=ROOT / "docs" / "convert_cmu.png")
    ap.add_argument("--no-picture", action="store_true")
    ap.add_argument("--no-table", action="store_true")
    args = ap.parse_args()
    torch.set_num_threads(args.threads)
    print(f"# convert_skeletal: {platform.processor() or platform.machine()}, torch {torch.__version__}, "
          f"{args.threads} threads")  # fmt: skip
    if not args.no_table:
        _table(args.data, args.limit)
    if not args.no_picture:
        _picture(args.data / args.picture, args.out)


if __name__ == "__main__":
    main()
