"""GPU figures of issue 37 in one short run: posing, full forward, inversion presets, mocap labelling, the peer.

Sections (each prints a Markdown table; every timing is the median over repeats after a warm-up,
with ``torch.cuda.synchronize()`` around each call on CUDA):

- **pose**: posing one prepared Anny identity (FK + LBS, with ``transl``), float32, batch
  1 / 32 / 128 / 1024: meshes/s and ms/call.
- **forward**: the full forward with a distinct Anny identity per mesh (Anny -> topology transfer ->
  skeleton fit -> FK + LBS), batch 1 / 32 / 128.
- **inversion**: presets ``fast``, ``analytic``, ``refined`` on 64 meshes of one Anny identity posed
  by seeded 0.3 rad poses: frames/s and the mean per-vertex error (mm) of the re-posed result.
- **mocap**: the shipped two-stage ``cmu41`` labeler (orienter + retry) on a synthetic session
  (``SyntheticMocap``, held-out pool seed), ``label_frames`` at batch 256: frames/s and accuracy.
- **correctives**: posing a prepared identity with the shipped pose correctives (issue 40) and
  without, plain rig and twist rig, float32, the two calls interleaved: ms/call and the extra time.
- **peer**: py-soma-x (``peer.peer_layer``: ``soma.SOMALayer(identity_model_type="anny",
  enable_procedural_transforms=False, mode="warp")`` on the asset folder built offline by
  ``_peer_assets.py``) on the same device in the same process, timed by ``peer.bench_speed`` (calls
  interleaved with unibody's), posing and full forward at the same batches; only when ``import soma``
  works (``pip install '.[peer]'``) and ``benchmarks/peer.py`` exists. Skipped otherwise, with the reason.

``--budget`` seconds (default 400) bounds the whole run: a section that would start after it is
skipped and says so (``benchmarks/gpu.sh`` also kills the run at 420 s).

    python benchmarks/gpu.py [--device cuda] [--batches 1 32 128 1024] [--budget 400]
    python benchmarks/gpu.py --device cpu --small      # the CPU smoke run (small batches, short timings)
    python benchmarks/gpu.py --identity pca            # the PCA identity instead of Anny (no Anny model data needed)
"""

from __future__ import annotations

import argparse
import datetime
import importlib.util
import platform
import sys
import time
from pathlib import Path

import torch

HERE = Path(__file__).resolve().parent
T0 = time.perf_counter()


def _sync(device: str) -> None:
    if device.startswith("cuda"):
        torch.cuda.synchronize()


def median_time(fn, device: str, min_time: float, warmup: int = 2, min_reps: int = 3) -> float:
    """Median seconds per call of ``fn`` over repeats filling ``min_time`` (after ``warmup`` calls)."""
    for _ in range(warmup):
        fn()
    _sync(device)
    times: list[float] = []
    start = time.perf_counter()
    while time.perf_counter() - start < min_time or len(times) < min_reps:
        t = time.perf_counter()
        fn()
        _sync(device)
        times.append(time.perf_counter() - t)
    return sorted(times)[len(times) // 2]


class Budget:
    def __init__(self, seconds: float) -> None:
        self.seconds = seconds

    def left(self) -> float:
        return self.seconds - (time.perf_counter() - T0)

    def allows(self, name: str, need: float) -> bool:
        if self.left() >= need:
            return True
        print(f"\n_{name}: skipped, {self.left():.0f} s of the {self.seconds:.0f} s budget left (needs ~{need:.0f} s)_")
        return False


def _poses(b: int, gen: torch.Generator, std: float = 0.3) -> torch.Tensor:
    return std * torch.randn(b, 77, 3, generator=gen)


def _params(layer, b: int, gen: torch.Generator) -> torch.Tensor:
    """(b, P) identity parameters of the layer's backend: Anny phenotypes in [0, 1], PCA coefficients ~ N(0, 0.5)."""
    n = layer.identity.num_params
    if type(layer.identity).__name__ == "AnnyIdentity":
        return torch.rand(b, n, generator=gen)
    return 0.5 * torch.randn(b, n, generator=gen)


def section_pose(layer, device: str, batches: list[int], min_time: float) -> None:
    gen = torch.Generator().manual_seed(0)
    with torch.no_grad():
        prepared = layer.prepare_identity(_params(layer, 1, gen).to(device))
    print(f"\n### Posing a prepared identity ({type(layer.identity).__name__}, float32, with transl)\n")
    print("| batch | meshes/s | ms/call |\n|---|---|---|")
    for b in batches:
        pose, transl = _poses(b, gen).to(device), (0.1 * torch.randn(b, 3, generator=gen)).to(device)
        with torch.no_grad():
            t = median_time(lambda p=pose, tr=transl: layer.pose(prepared, p, transl=tr), device, min_time)
        print(f"| {b} | {b / t:,.0f} | {1e3 * t:.3f} |", flush=True)


def section_forward(layer, device: str, batches: list[int], min_time: float) -> None:
    gen = torch.Generator().manual_seed(1)
    print(f"\n### Full forward, a distinct identity per mesh ({type(layer.identity).__name__}, float32, with transl)\n")
    print("| batch | meshes/s | ms/call |\n|---|---|---|")
    for b in batches:
        params = _params(layer, b, gen).to(device)
        pose, transl = _poses(b, gen).to(device), (0.1 * torch.randn(b, 3, generator=gen)).to(device)
        with torch.no_grad():
            t = median_time(lambda c=params, p=pose, tr=transl: layer(c, p, transl=tr), device, min_time)
        print(f"| {b} | {b / t:,.0f} | {1e3 * t:.3f} |", flush=True)


def section_inversion(layer, device: str, batch: int, min_time: float) -> None:
    from unibody.fitting.inversion import PRESETS, PoseInverter

    gen = torch.Generator().manual_seed(2)
    with torch.no_grad():
        prepared = layer.prepare_identity(_params(layer, 1, gen).to(device))
        meshes = layer.pose(prepared, _poses(batch, gen).to(device), transl=torch.zeros(batch, 3, device=device))
    print(f"\n### Inversion presets, {batch} meshes of one {type(layer.identity).__name__} identity (float32)\n")
    print("| preset | frames/s | ms/call | mean error (mm) |\n|---|---|---|---|")
    for name in ("fast", "analytic", "refined"):
        inv = PoseInverter(layer, PRESETS[name])
        with torch.no_grad():
            res = inv.invert(meshes.vertices, prepared)
            t = median_time(lambda inv=inv: inv.invert(meshes.vertices, prepared), device, min_time, warmup=1)
        err = 1e3 * float(res.per_vertex_error.mean())
        print(f"| {name} | {batch / t:,.0f} | {1e3 * t:.2f} | {err:.2f} |", flush=True)


def section_correctives(identity: str, device: str, batches: list[int], min_time: float) -> None:
    """Posing with and without the shipped correctives, interleaved rounds: the extra time per call."""
    from unibody import BodyLayer

    build = BodyLayer.from_anny if identity == "anny" else BodyLayer.from_pca
    print("\n### Pose correctives (issue 40): posing a prepared identity with and without (float32, with transl)\n")
    print("| rig | batch | ms/call without | ms/call with | extra |\n|---|---|---|---|---|")
    for procedural in (False, True):
        layer = build(dtype=torch.float32, procedural=procedural, correctives=True).to(device)
        gen = torch.Generator().manual_seed(3)
        with torch.no_grad():
            prepared = layer.prepare_identity(_params(layer, 1, gen).to(device))
        for b in batches:
            pose, transl = _poses(b, gen, 0.6).to(device), (0.1 * torch.randn(b, 3, generator=gen)).to(device)
            times = {False: [], True: []}
            with torch.no_grad():
                for _ in range(3):  # rounds interleaved: a slow spell of the machine hits both
                    for on in (False, True):
                        times[on].append(
                            median_time(
                                lambda p=pose, tr=transl, on=on, lay=layer, pr=prepared: lay.pose(
                                    pr, p, transl=tr, correctives=on
                                ),
                                device,
                                min_time / 3,
                            )
                        )
            off, on = sorted(times[False])[1], sorted(times[True])[1]
            rig = "twist" if procedural else "plain"
            print(f"| {rig} | {b} | {1e3 * off:.3f} | {1e3 * on:.3f} | {100 * (on / off - 1):+.0f} % |", flush=True)


def section_mocap(device: str, frames: int, min_time: float) -> None:
    from unibody.mocap.labeler import label_frames
    from unibody.mocap.layout import MarkerLayout
    from unibody.mocap.pipeline import load_labeler
    from unibody.mocap.synthetic import SyntheticConfig, SyntheticMocap

    layout = MarkerLayout.load("cmu41")
    batch = SyntheticMocap(layout, SyntheticConfig(identities=16, pool_seed=777)).sample(
        frames, torch.Generator().manual_seed(4242)
    )
    seq = torch.where(batch.mask[..., None], batch.points, torch.nan).to(device)  # (T, N, 3), NaN = missing
    model = load_labeler("cmu41").to(device).eval()
    print(f"\n### Mocap labelling, shipped cmu41 two-stage labeler, {frames} synthetic frames (float32)\n")
    print("| batch | frames/s | accuracy |\n|---|---|---|")
    for b in sorted({1, min(256, frames)}):
        if b == 1:  # batch 1 is slow: 32 frames of it
            part = seq[:32]
            t = median_time(lambda part=part: label_frames(model, part, batch=1), device, min_time, warmup=1)
            print(f"| 1 | {part.shape[0] / t:,.0f} | |", flush=True)
            continue
        labels = label_frames(model, seq, batch=b)
        acc = float((labels.cpu() == batch.labels)[batch.mask].float().mean())
        t = median_time(lambda b=b: label_frames(model, seq, batch=b), device, min_time, warmup=1)
        print(f"| {b} | {frames / t:,.0f} | {acc:.4f} |", flush=True)


def _peer_reason() -> str | None:
    """Why the peer section cannot run (None when it can)."""
    if importlib.util.find_spec("soma") is None:
        return "py-soma-x is not installed (`import soma` fails)"
    if not (HERE / "peer.py").is_file():
        return "benchmarks/peer.py does not exist"
    return None


def section_peer(layer, device: str, batches: list[int], fwd_batches: list[int], reps: int) -> None:
    """py-soma-x beside unibody through benchmarks/peer.py (its layer, its interleaved timing)."""
    import argparse as _argparse

    sys.path.insert(0, str(HERE))
    import peer  # benchmarks/peer.py (imports benchmarks/_peer_assets.py)

    t = time.perf_counter()
    other = peer.peer_layer(device)
    print(f"\n### Peer: py-soma-x on {device}, beside unibody (built in {time.perf_counter() - t:.0f} s)")
    print("\nbenchmarks/peer.py's bench_speed: the two libraries' calls interleaved, the median per call.")
    for section, sizes in (("pose", batches), ("forward", fwd_batches)):
        ns = _argparse.Namespace(sections=(section,), batches=sizes, seed=0, reps=reps, device=device)
        with torch.no_grad():
            peer.bench_speed(layer, other, ns)


def describe(device: str) -> str:
    if device.startswith("cuda"):
        p = torch.cuda.get_device_properties(torch.device(device))
        card = f"{p.name}, {p.total_memory / 2**30:.0f} GiB, CUDA {torch.version.cuda}"
    else:
        card = f"CPU {platform.processor() or platform.machine()}, {torch.get_num_threads()} threads"
    return f"{card}; torch {torch.__version__}; Python {platform.python_version()}"


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--device", default="cuda")
    parser.add_argument("--batches", type=int, nargs="+", default=[1, 32, 128, 1024], help="posing batches")
    parser.add_argument("--forward-batches", type=int, nargs="+", default=[1, 32, 128])
    parser.add_argument("--inversion-batch", type=int, default=64)
    parser.add_argument("--mocap-frames", type=int, default=1024)
    parser.add_argument("--min-time", type=float, default=1.0, help="seconds of repeats per timing")
    parser.add_argument("--budget", type=float, default=400.0, help="seconds for the whole run")
    parser.add_argument("--small", action="store_true", help="smoke run: small batches, short timings")
    parser.add_argument("--no-peer", action="store_true")
    parser.add_argument("--identity", choices=("anny", "pca"), default="anny", help="the identity backend timed")
    args = parser.parse_args(argv)
    if args.small:
        args.batches, args.forward_batches = [1, 8], [1, 4]
        args.inversion_batch, args.mocap_frames, args.min_time = 4, 64, 0.2
    device = args.device
    if device.startswith("cuda") and not torch.cuda.is_available():
        raise SystemExit("--device: CUDA is not available on this machine")
    budget = Budget(args.budget)
    print(f"## unibody GPU benchmark ({datetime.date.today().isoformat()})\n")
    print(f"Device: {describe(device)}. Command: `python benchmarks/gpu.py {' '.join(argv or sys.argv[1:])}`")
    from unibody import BodyLayer

    t = time.perf_counter()
    build = BodyLayer.from_anny if args.identity == "anny" else BodyLayer.from_pca
    layer = build(dtype=torch.float32).to(device)
    print(f"\nBodyLayer.from_{args.identity} on {device}: {time.perf_counter() - t:.1f} s")
    sections = [
        ("pose", 20, lambda: section_pose(layer, device, args.batches, args.min_time)),
        ("forward", 20, lambda: section_forward(layer, device, args.forward_batches, args.min_time)),
        ("inversion", 30, lambda: section_inversion(layer, device, args.inversion_batch, args.min_time)),
        ("correctives", 40, lambda: section_correctives(args.identity, device, args.batches, args.min_time)),
        ("mocap", 30, lambda: section_mocap(device, args.mocap_frames, args.min_time)),
    ]
    for name, need, run in sections:
        if budget.allows(name, need):
            run()
    reason = "--no-peer" if args.no_peer else _peer_reason()
    if reason is None and args.identity != "anny":
        reason = "the peer is timed with the Anny identity only"
    if reason is not None:
        print(f"\n_peer: skipped ({reason})_")
    elif budget.allows("peer", 120):
        section_peer(layer, device, args.batches, args.forward_batches, reps=5 if args.small else 21)
    print(f"\nTotal: {time.perf_counter() - T0:.0f} s")


if __name__ == "__main__":
    main()
