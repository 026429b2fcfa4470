"""Articulated occupancy benchmark (paper 002 §5): accuracy, speed, self-intersection, scene collision.

Sections:
- ``iou``: held-out bodies (identity pool 1 and pose stream 1; training used pool 0 and its own
  poses): mean IoU of the occupancy at 1/2 against winding numbers of the posed mesh, for points
  uniform in each body's bounding box and near its surface (N(0, 1 cm) about area-weighted
  surface samples), as in paper Table 2. Then the same for real poses: frames of three CMU
  mocap files in ``../shared/evaldata`` solved by ``unibody.mocap`` (never used in training),
  and for Anny identities (uniform phenotypes), a body model the network never saw.
- ``speed``: one body: encoding time, and the time to query 10,000 points (uniform in the
  bounding box, and near the surface) after encoding; median of repeats, CPU.
- ``self``: seeded extreme poses (sample_poses with amplitude >= 0.8) of held-out identities,
  kept when their meshes intersect between parts that may not touch (exact triangle test,
  ``occupancy.metrics``); mean intersecting pairs over ``resolve_self_intersections`` (200
  steps), the change of the joint rotations, and the convergence curve as a PNG.
- ``variants``: on the first 20 of those poses, the stopping rule and the rigid parts of
  ``resolve_self_intersections`` against the alternatives.
- ``figure``: a PNG of a held-out body, its marching-cubes occupancy surface, and the most
  intersecting of four seeded poses before and after ``resolve_self_intersections``.
- ``scene``: a body standing 6 cm into a floor with a box through its thigh, as point clouds:
  scene points inside the body mesh (winding numbers) before and after optimising translation
  and pose with the collision term.

    OMP_NUM_THREADS=1 python benchmarks/occupancy.py [--sections iou speed self scene] [--bodies 50]
"""

from __future__ import annotations

import argparse
import dataclasses
import time
from pathlib import Path

import numpy as np
import torch
from PIL import Image, ImageDraw

from unibody.geometry.rotations import axis_angle_to_matrix, rotation_angle
from unibody.occupancy import BodyOccupancy, resolve_self_intersections
from unibody.occupancy import data as occ_data
from unibody.occupancy.metrics import part_intersecting_pairs, part_intersections
from unibody.occupancy.train import iou
from unibody.synth.poses import sample_poses

CURVE_STEPS = (0, 5, 10, 20, 30, 50, 75, 100, 150, 200)


REAL = (("cmu_85_02", 4), ("cmu_135_02", 10), ("cmu_85_12", 40))  # evaldata C3D files, frame step


def real_poses(count: int, evaldata: Path) -> torch.Tensor:
    """(count, 77, 3) poses solved from real CMU mocap (jumps, flips, breakdance, kata, floor work) with
    unibody's own labeler-free solve of the labelled markers; frames with a median marker residual
    above 1.5 cm are dropped, then ``count`` are taken evenly."""
    from unibody.mocap.c3d import read_markers
    from unibody.mocap.layout import MarkerLayout
    from unibody.mocap.pipeline import solve_sequence

    poses = []
    for name, step in REAL:
        seq = read_markers(evaldata / "c3d" / f"{name}.c3d")
        seq = dataclasses.replace(seq, points=seq.points[::step], rate=seq.rate / step)
        res = solve_sequence(seq, MarkerLayout.load("cmu41"))
        good = np.nanmedian(np.asarray(res.residual), axis=1) < 0.015
        poses.append(torch.as_tensor(np.asarray(res.pose)[good], dtype=torch.float32))
    pose = torch.cat(poses)
    return pose[torch.linspace(0, len(pose) - 1, count).round().long()]


def section_iou(occ: BodyOccupancy, bodies: int, points: int, evaldata: Path | None) -> None:
    def held_out(start: int, n: int):
        return occ_data.pose_bodies(n, seed=1, index=1000 + start)

    _iou_set(occ, bodies, points, held_out, "PCA identities of held-out pool 1, seeded held-out poses")
    if evaldata is not None and (evaldata / "c3d").is_dir():
        pose = real_poses(bodies, evaldata)
        layer = occ_data._layer()

        def real(start: int, n: int):
            with torch.no_grad():
                return layer(occ_data._pool(1, 1000)[start : start + n], pose[start : start + n]), layer.faces

        _iou_set(occ, bodies, points, real, "held-out PCA identities, real poses solved from evaldata CMU mocap")
    from unibody import BodyLayer

    anny = BodyLayer.from_anny(procedural=True)

    def anny_bodies(start: int, n: int):
        gen = occ_data.generator("benchmark-anny", start)
        with torch.no_grad():
            return anny(torch.rand(n, 6, generator=gen), sample_poses(n, gen)), anny.faces

    _iou_set(occ, bodies, points, anny_bodies, "Anny identities (uniform phenotypes; never trained on), seeded poses")


def _iou_set(occ: BodyOccupancy, bodies: int, points: int, make, title: str) -> None:
    res = {"uniform": [], "surface": []}
    heights = []
    for start in range(0, bodies, 10):
        n = min(10, bodies - start)
        out, faces = make(start, n)
        gen = occ_data.generator("benchmark-iou", start)
        uniform, near = occ_data.evaluation_points(out.vertices, faces, points, gen)
        with torch.no_grad():
            enc = occ.encode(out)
            for name, q in (("uniform", uniform), ("surface", near)):
                pred = torch.stack([occ.query(q[i : i + 1], _item(enc, i))[0] for i in range(n)]) > 0.5
                res[name].append(iou(pred, occ_data.inside_mesh(out.vertices, faces, q)))
        rest = out.rest_vertices
        heights.append(rest[..., 1].amax(1) - rest[..., 1].amin(1))
    h = torch.cat(heights)
    print(f"IoU, {title}: {bodies} bodies, {points} points each per set, %:")
    for name in res:
        v = torch.cat(res[name]) * 100
        child = v[h < 1.3]
        print(f"  {name:8s} mean {v.mean():.2f}  min {v.min():.2f}  children (<1.3 m, n={len(child)}) "
              f"{child.mean() if len(child) else float('nan'):.2f}")  # fmt: skip


def _item(enc, i):
    return type(enc)(*(getattr(enc, f)[i : i + 1] for f in enc.__slots__))


def _median_ms(fn, repeats: int) -> float:
    fn()
    times = []
    for _ in range(repeats):
        t = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t)
    return 1000 * float(np.median(times))


def section_speed(occ: BodyOccupancy, repeats: int) -> None:
    out, faces = occ_data.pose_bodies(1, seed=1, index=2000)
    uniform, near = occ_data.evaluation_points(out.vertices, faces, 10_000, occ_data.generator("speed"))
    with torch.inference_mode():
        enc_ms = _median_ms(lambda: occ.encode(out), repeats)
        enc = occ.encode(out)
        print(f"threads {torch.get_num_threads()}: encode one body {enc_ms:.1f} ms")
        for name, q in (("uniform in box", uniform), ("near surface", near)):
            ms = _median_ms(lambda q=q: occ.query(q, enc), repeats)
            boxes = enc.to_boxes(q)[1].sum(-1).double().mean()
            print(f"  query 10,000 points {name:15s} {ms:6.1f} ms  ({boxes:.2f} part boxes per point)")


def self_intersecting_poses(count: int, parts, batch: int = 40):
    """(params, pose) of the first ``count`` seeded extreme poses that intersect between parts,
    and how many poses were drawn."""
    layer, pool = occ_data._layer(), occ_data._pool(1, 1000)
    params, poses = [], []
    index = 0
    while sum(len(p) for p in poses) < count:
        gen = occ_data.generator("self-intersection", index)
        pose = sample_poses(batch, gen, min_amplitude=0.8, tumble=0.0)
        ids = torch.randint(1000, (batch,), generator=gen)
        with torch.no_grad():
            out = layer(pool[ids], pose)
        keep = part_intersections(out.vertices, layer.faces.long(), parts) > 0
        params.append(pool[ids][keep])
        poses.append(pose[keep])
        index += 1
    return torch.cat(params)[:count], torch.cat(poses)[:count], index * batch


def joint_change(before: torch.Tensor, after: torch.Tensor) -> torch.Tensor:
    """(B, 76) degrees between the local rotations of the joints below the Hips of two poses."""
    rel = axis_angle_to_matrix(before[:, 1:]).transpose(-1, -2) @ axis_angle_to_matrix(after[:, 1:])
    return torch.rad2deg(rotation_angle(rel))


def curve_png(path: str, steps, mean_pairs, title: str) -> None:
    w, h, m = 640, 400, 60
    img = Image.new("RGB", (w, h), (255, 255, 255))
    d = ImageDraw.Draw(img)
    top = max(mean_pairs) * 1.05
    x = lambda s: m + (w - 2 * m) * s / steps[-1]  # noqa: E731
    y = lambda v: h - m - (h - 2 * m) * v / top  # noqa: E731
    d.line([(m, m), (m, h - m), (w - m, h - m)], fill=(0, 0, 0))
    for s in (0, 50, 100, 150, 200):
        d.text((x(s) - 8, h - m + 6), str(s), fill=(0, 0, 0))
    for frac in (0, 0.25, 0.5, 0.75, 1.0):
        d.text((6, y(frac * top) - 6), f"{frac * top:.0f}", fill=(0, 0, 0))
        d.line([(m - 4, y(frac * top)), (m, y(frac * top))], fill=(0, 0, 0))
    d.line([(x(s), y(v)) for s, v in zip(steps, mean_pairs, strict=True)], fill=(200, 40, 40), width=3)
    for s, v in zip(steps, mean_pairs, strict=True):
        d.ellipse([x(s) - 3, y(v) - 3, x(s) + 3, y(v) + 3], fill=(200, 40, 40))
    d.text((m, 20), title, fill=(0, 0, 0))
    d.text((w // 2 - 60, h - 24), "optimisation step", fill=(0, 0, 0))
    img.save(path)


def section_self(occ: BodyOccupancy, count: int, steps: int, png: str | None, batch: int, **kw) -> None:
    t0 = time.time()
    params, pose, drawn = self_intersecting_poses(count, occ.parts)
    print(f"{count} self-intersecting poses among the first {drawn} drawn ({time.time() - t0:.0f} s)")
    layer = occ_data._layer()
    faces, parts = layer.faces.long(), occ.parts
    curve = {s: [] for s in CURVE_STEPS if s <= steps}
    results, counting, t1 = [], [], time.time()
    for start in range(0, count, batch):
        sl = slice(start, start + batch)

        def record(step, current, sl=sl):
            if step in curve:
                t = time.time()
                with torch.no_grad():
                    curve[step].append(part_intersections(layer(params[sl], current).vertices, faces, parts))
                counting.append(time.time() - t)

        res = resolve_self_intersections(occ, layer, params[sl], pose[sl], steps=steps, callback=record, **kw)
        n_done = len(curve[0])
        for s in curve:  # items that finished early keep their last count
            while len(curve[s]) < n_done:
                curve[s].append(curve[max(t for t in curve if len(curve[t]) == n_done and t < s)][-1])
        results.append(res)
    elapsed = time.time() - t1 - sum(counting)  # the resolve alone, without the exact counts of the curve
    pairs = {s: torch.cat(v).double() for s, v in curve.items()}
    first, last = pairs[0].mean(), pairs[max(pairs)].mean()
    new_pose = torch.cat([r.pose for r in results])
    change = joint_change(pose, new_pose)
    moved = change > 1.0
    print(f"resolve_self_intersections, {steps} steps, {elapsed / count:.2f} s per pose (batches of {batch}):")
    print(f"  mean intersecting triangle pairs (between parts that may not touch): {first:.1f} -> {last:.1f} "
          f"({100 * (1 - last / first):.1f} % fewer); "
          f"poses fully resolved {(pairs[max(pairs)] == 0).double().mean():.0%}")  # fmt: skip
    print("  curve: " + ", ".join(f"{s}: {v.mean():.1f}" for s, v in pairs.items()))
    print(f"  joint rotation change: mean over the 76 joints below the Hips {change.mean():.2f} deg; "
          f"over joints that moved > 1 deg {change[moved].mean():.1f} deg ({moved.double().mean():.0%} of joints); "
          f"max {change.max():.1f} deg")  # fmt: skip
    if png:
        curve_png(png, list(pairs), [float(v.mean()) for v in pairs.values()],
                  f"mean intersecting triangle pairs, {count} poses (COAP-style resolve)")  # fmt: skip
        print(f"  wrote {png}")


VARIANTS = (
    ("stop an item at its first zero term", dict(patience=1, rigid_parts=False)),
    ("never stop early (the paper's fixed budget)", dict(patience=None, rigid_parts=False)),
    ("10 consecutive zeros, gradients through the part codes", dict(patience=10, rigid_parts=False)),
    ("10 consecutive zeros, rigid parts (the defaults)", dict(patience=10, rigid_parts=True)),
)


def section_variants(occ: BodyOccupancy, count: int, steps: int) -> None:
    """The stopping rule and rigid parts of resolve_self_intersections against the alternatives."""
    params, pose, _ = self_intersecting_poses(count, occ.parts)
    layer = occ_data._layer()
    faces, parts = layer.faces.long(), occ.parts
    with torch.no_grad():
        before = part_intersections(layer(params, pose).vertices, faces, parts).double()
    print(f"resolve variants on the first {count} self-intersecting poses, {steps} steps at most:")
    for name, kw in VARIANTS:
        t = time.time()
        res = resolve_self_intersections(occ, layer, params, pose, steps=steps, **kw)
        elapsed = time.time() - t
        with torch.no_grad():
            after = part_intersections(layer(params, res.pose).vertices, faces, parts).double()
        change = joint_change(pose, res.pose)
        resolved = (after == 0).double().mean()
        print(f"  {name:56s} pairs {before.mean():.1f} -> {after.mean():.1f}, resolved {resolved:.0%}, "
              f"mean joint change {change.mean():.2f} deg, {elapsed / count:.2f} s per pose")  # fmt: skip


def scene_points(floor_y: float, box_lo, box_hi, spacing: float = 0.01, seed: int = 0) -> torch.Tensor:
    """A floor square (2 x 2 m at height ``floor_y``) and a box's surface, sampled every ``spacing`` m,
    each point with two copies moved inward (against its normal) by |N(5 cm, 5 cm)|, as in the
    reference's scene tutorial: a surface alone gives the term no sense of which side is solid."""
    g = torch.arange(-1.0, 1.0, spacing)
    fx, fz = torch.meshgrid(g, g, indexing="ij")
    points = [torch.stack([fx, torch.full_like(fx, floor_y), fz], -1).reshape(-1, 3)]
    normals = [torch.tensor([0.0, 1.0, 0.0]).expand_as(points[0])]
    lo, hi = torch.tensor(box_lo), torch.tensor(box_hi)
    for axis in range(3):
        a, b = [i for i in range(3) if i != axis]
        ga = torch.arange(float(lo[a]), float(hi[a]) + 1e-9, spacing)
        gb = torch.arange(float(lo[b]), float(hi[b]) + 1e-9, spacing)
        ma, mb = torch.meshgrid(ga, gb, indexing="ij")
        for side, sign in ((lo[axis], -1.0), (hi[axis], 1.0)):
            p = torch.zeros(ma.numel(), 3)
            p[:, a], p[:, b], p[:, axis] = ma.flatten(), mb.flatten(), float(side)
            n = torch.zeros_like(p)
            n[:, axis] = sign
            points.append(p)
            normals.append(n)
    p, n = torch.cat(points), torch.cat(normals)
    gen = torch.Generator().manual_seed(seed)
    depth = (0.05 + 0.05 * torch.randn(2, len(p), 1, generator=gen)).abs()
    return torch.cat([p, p - depth[0] * n, p - depth[1] * n])


def section_scene(occ: BodyOccupancy, steps: int) -> None:
    layer = occ_data._layer()
    params = occ_data._pool(1, 10)[3:4]
    pose = torch.zeros(1, 77, 3)
    names = occ_data._layer().joint_names
    pose[0, names.index("LeftArm") - 1, 2] = -1.2
    pose[0, names.index("RightArm") - 1, 2] = 1.2
    with torch.no_grad():
        out = layer(params, pose)
    v = out.vertices[0]
    floor_y = float(v[:, 1].min()) + 0.06
    knee = out.joints[0, names.index("LeftShin")]
    box_lo = (float(knee[0]) - 0.05, float(knee[1]) + 0.05, float(v[:, 2].min()) - 0.2)
    box_hi = (float(knee[0]) + 0.35, float(knee[1]) + 0.45, float(v[:, 2].min()) + 0.12)
    scene = scene_points(floor_y, box_lo, box_hi)
    faces = layer.faces

    def penetrating(o) -> int:
        return int(occ_data.inside_mesh(o.vertices, faces, scene[None]).sum())

    transl = torch.zeros(1, 3, requires_grad=True)
    delta = torch.zeros(1, 76, 3, requires_grad=True)
    opt = torch.optim.Adam([transl, delta], lr=5e-3)
    before = penetrating(out)
    t0 = time.time()
    for step in range(steps):
        cur = torch.cat([pose[:, :1], pose[:, 1:] + delta], 1)
        o = layer(params, cur, transl=transl)
        term = occ.collision_loss(scene, o)
        if float(term.detach()) == 0.0:  # nothing penetrates any more
            break
        loss = term + 100.0 * delta.pow(2).sum()
        opt.zero_grad()
        loss.sum().backward()
        opt.step()
        if step == 0:
            first = float(term.detach())
    with torch.no_grad():
        o = layer(params, torch.cat([pose[:, :1], pose[:, 1:] + delta], 1), transl=transl)
    after = penetrating(o)
    change = torch.rad2deg(delta.detach().norm(dim=-1))
    print(f"scene: floor 6 cm above the soles + a box through the left thigh ({len(scene)} points, with "
          f"inward copies); lowest vertex {float(out.vertices[0, :, 1].min()) - floor_y:+.3f} m -> "
          f"{float(o.vertices[0, :, 1].min()) - floor_y:+.3f} m from the floor")  # fmt: skip
    print(f"  scene points inside the body mesh: {before} -> {after}; collision term {first:.1f} -> "
          f"{float(occ.collision_loss(scene, o)):.1f}; translation {transl.detach()[0].numpy().round(3)} m; "
          f"joint change mean {change.mean():.2f} deg, max {change.max():.1f} deg; "
          f"{step} steps, {time.time() - t0:.1f} s")  # fmt: skip


def _panel(meshes, label: str, size: int = 420) -> np.ndarray:
    from unibody.viz.render import render_image

    img = Image.fromarray(render_image(meshes, width=size, height=size, view="front", ground_y=None))
    ImageDraw.Draw(img).text((10, 8), label, fill=(20, 20, 20))
    return np.asarray(img)


def _split(vertices: torch.Tensor, faces: torch.Tensor, red: torch.Tensor):
    from unibody.viz.render import MeshSpec

    v = vertices.detach().cpu().numpy()
    return [MeshSpec(v, faces[~red].numpy(), (0.80, 0.66, 0.58)), MeshSpec(v, faces[red].numpy(), (0.85, 0.1, 0.1))]


def section_figure(occ: BodyOccupancy, path: str, steps: int) -> None:
    """Held-out body, its marching-cubes occupancy surface, a self-intersecting pose before/after."""
    from unibody.viz.render import MeshSpec

    out, faces = occ_data.pose_bodies(1, seed=1, index=3000)
    verts, tris = occ.extract_mesh(out, resolution=128)[0]
    layer, f = occ_data._layer(), occ_data._layer().faces.long()
    params, pose, _ = self_intersecting_poses(4, occ.parts)
    with torch.no_grad():
        counts = part_intersections(layer(params, pose).vertices, f, occ.parts)
    i = int(counts.argmax())
    res = resolve_self_intersections(occ, layer, params[i : i + 1], pose[i : i + 1], steps=steps)
    panels = [
        _panel([MeshSpec(out.vertices[0].numpy(), faces.numpy(), (0.80, 0.66, 0.58))], "held-out body (mesh)"),
        _panel([MeshSpec(verts.numpy(), tris.numpy(), (0.55, 0.68, 0.85))], "occupancy, marching cubes 128^3"),
    ]
    for label, p in (
        ("self-intersecting (red)", pose[i : i + 1]),
        (f"resolved (stopped at step {int(res.steps[0])})", res.pose),
    ):
        with torch.no_grad():
            v = layer(params[i : i + 1], p).vertices[0]
        pairs = part_intersecting_pairs(v, f, occ.parts)
        red = torch.zeros(len(f), dtype=torch.bool)
        red[pairs.flatten()] = True
        panels.append(_panel(_split(v, f, red), f"{label}: {len(pairs)} pairs"))
    Image.fromarray(np.concatenate(panels, 1)).save(path)
    change = joint_change(pose[i : i + 1], res.pose)[0]
    top = int(change.argmax())
    print(f"figure pose: {int(counts[i])} pairs, stopped at step {int(res.steps[0])}; "
          f"{int((change > 1).sum())} joints moved > 1 deg, the most {change[top]:.1f} deg "
          f"({occ_data._layer().joint_names[top + 2]})")  # fmt: skip
    print(f"wrote {path}")


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--sections", nargs="+", default=["iou", "speed", "self", "variants", "scene", "figure"],
                   choices=["iou", "speed", "self", "variants", "scene", "figure"])  # fmt: skip
    p.add_argument("--weights", default=None, help="an occupancy file (default: the shipped one)")
    p.add_argument("--bodies", type=int, default=50)
    p.add_argument("--points", type=int, default=100_000)
    p.add_argument("--poses", type=int, default=100)
    p.add_argument("--steps", type=int, default=200)
    p.add_argument("--batch", type=int, default=50)
    p.add_argument("--lr", type=float, default=0.01)
    p.add_argument("--prior-weight", type=float, default=100.0)
    p.add_argument("--png", default="docs/occupancy_self_intersection.png")
    p.add_argument("--figure", default="docs/occupancy.png")
    p.add_argument("--threads", type=int, default=1)
    p.add_argument("--evaldata", type=Path, default=Path(__file__).resolve().parents[2] / "shared" / "evaldata",
                   help="the evaldata folder (real poses for the IoU section); skipped when absent")  # fmt: skip
    args = p.parse_args()
    torch.set_num_threads(args.threads)
    occ = BodyOccupancy.pretrained(args.weights)
    if "iou" in args.sections:
        section_iou(occ, args.bodies, args.points, args.evaldata)
    if "speed" in args.sections:
        for threads in sorted({1, args.threads, 2}):
            torch.set_num_threads(threads)
            section_speed(occ, 30)
        torch.set_num_threads(args.threads)
    if "self" in args.sections:
        section_self(occ, args.poses, args.steps, args.png, args.batch, lr=args.lr, prior_weight=args.prior_weight)
    if "variants" in args.sections:
        section_variants(occ, 20, args.steps)
    if "scene" in args.sections:
        section_scene(occ, args.steps)
    if "figure" in args.sections:
        section_figure(occ, args.figure, args.steps)


if __name__ == "__main__":
    main()
