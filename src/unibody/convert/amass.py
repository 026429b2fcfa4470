"""AMASS motion files (SMPL-H and SMPL-X) to the canonical motion.

Layouts read (``.npz``, plain arrays, never a pickle):

=========== ======================================================================================
SMPL-H      ``poses (T, 156)`` (root, 21 body, 2 x 15 hand joints), ``trans (T, 3)``, ``betas (K,)``
            (16 in AMASS), ``gender``, ``mocap_framerate``; ``dmpls (T, 8)`` is ignored with a
            warning (there is no DMPL model: the soft-tissue motion is lost)
SMPL-X      ``poses (T, 165)`` (root, 21 body, jaw, 2 eyes, 2 x 15 hand joints) or the split keys
            ``root_orient (T, 3)``, ``pose_body (T, 63)``, ``pose_hand (T, 90)``, ``pose_jaw (T, 3)``,
            ``pose_eye (T, 6)``; ``trans``, ``betas``, ``gender``, ``mocap_frame_rate``,
            ``surface_model_type``
=========== ======================================================================================

The model file: ``options.models`` is a file, or a folder searched recursively for ``.npz`` /
``.pkl`` model files. The family (from the layout, checked against ``surface_model_type``)
and the take's ``gender`` pick the file; the family is read from the path (``smplx``,
``smplh``, ``smpl`` in a folder or file name, as in ``SMPLX_FEMALE.npz`` or
``smplh/female/model.npz``; files that name none are opened to count their vertices and joints)
and the gender with :func:`unibody.identity.smpl.gender_from_path`. A neutral model is never
substituted for a missing gendered one: bodies and joint centres differ by centimetres, and
the motion would silently change. A missing file is an error naming the gender, the folder
and the files found.

Axes: AMASS worlds are Z up; unibody is Y up. Posed vertices (and with them the translation)
are mapped at the boundary by ``(x, y, z) -> (x, z, -y)``, a rotation by -90 degrees about X:
an upright AMASS body stands along +Y afterwards, and its heading is kept. The rest shape
(zero pose) is the model's own Y-up frame and is not converted.

Pipeline per file: the take's rest shape (betas) -> :class:`SMPLModel` posed in batches of
``options.batch`` frames -> the model template's topology transfer (automatic registration,
cached on disk; a new template costs ~40 s once) -> :class:`PoseInverter` at
``options.preset`` with ``layer.prepare_rest`` of the transferred rest shape. The motion keeps
the file's frame rate; its identity is the native PCA projection of the transferred rest
shape reposed to the bind pose (least squares, one product per file; the pose was solved on
the transferred rest shape itself, so playing it on the PCA identity adds that projection's
residual, reported as ``identity_mean_mm``).
"""

from __future__ import annotations

import re
import time
from dataclasses import dataclass
from functools import lru_cache
from pathlib import Path

import numpy as np
import torch

from ..body import BodyLayer
from ..fitting.inversion import PRESETS, PoseInverter
from ..identity.smpl import FAMILIES, gender_from_path
from ..identity.smpl_model import SMPLModel
from ..io.npz import read_npz
from ..motion import Motion, check_fps
from ..registration import topology_transfer
from ..topology import TopologyTransfer
from ._body import _layer
from ._types import Converted, ConvertOptions

__all__ = ["AmassTake", "find_model", "read_amass", "read_take", "solve_meshes", "to_y_up"]

_JOINTS = {"smplh": 52, "smplx": 55}
_SPLIT = (("root_orient", 3), ("pose_body", 63), ("pose_hand", 90), ("pose_jaw", 3), ("pose_eye", 6))
_LAYOUTS = (
    "SMPL-H poses (T, 156) or SMPL-X poses (T, 165) or the split keys root_orient/pose_body/pose_hand"
    "[/pose_jaw/pose_eye], with trans (T, 3), betas, gender and mocap_framerate/mocap_frame_rate"
)
_PCA_COMPONENTS = 128
# Posing and transfer run in chunks whose intermediates stay in cache (one SMPL-X frame's
# blended transforms are 0.5 MB): on 1 thread, 2026-11-26, forward 0.86 vs 1.33 ms/frame
# (64 vs 256 frames), transfer 1.05 vs 2.0 ms/frame (16 vs 256); the inverter takes the batch.
_FORWARD_CHUNK = 64
_TRANSFER_CHUNK = 16


@dataclass(frozen=True, slots=True)
class AmassTake:
    """One AMASS file, checked.

    Attributes:
        family: "smplh" or "smplx".
        gender: "neutral", "male" or "female".
        poses: (T, J, 3) float64 axis-angle, the model's full pose (J = 52 or 55).
        trans: (T, 3) float64 m, Z-up AMASS world.
        betas: (K,) float64 shape coefficients.
        fps: frames per second.
        warnings: one-line notes about the file (ignored keys, ...).
    """

    family: str
    gender: str
    poses: np.ndarray
    trans: np.ndarray
    betas: np.ndarray
    fps: float
    warnings: tuple[str, ...] = ()


def read_take(path: str | Path) -> AmassTake:
    """Read and check an AMASS ``.npz``.

    Raises:
        ValueError: not an AMASS layout (the message lists the keys found and the layouts
            expected), a malformed field, or NaN/inf frames (named by index).
    """
    path = Path(path)
    with read_npz(path) as data:
        keys = set(data.files)
        fields = {k: _member(data, k, path) for k in keys & {"poses", "trans", "betas", "gender", *dict(_SPLIT)}}
        fields.update({k: _member(data, k, path) for k in keys & {"surface_model_type", "mocap_framerate"}})
        if "mocap_frame_rate" in keys:
            fields["mocap_framerate"] = _member(data, "mocap_frame_rate", path)
    notes = []
    family, poses = _poses(fields, keys, path, notes)
    if "dmpls" in keys:
        notes.append("dmpls ignored: there is no DMPL model (the soft-tissue motion is lost)")
    missing = [k for k in ("trans", "betas", "gender", "mocap_framerate") if k not in fields]
    if missing:
        raise ValueError(f"{path}: AMASS {family} layout without {', '.join(missing)} (keys: {_keys(keys)})")
    t = poses.shape[0]
    if t == 0:
        raise ValueError(f"{path}: poses: expected at least one frame, got shape {poses.shape}")
    trans = _real(fields["trans"], (t, 3), f"{path}: trans", f"({t}, 3)")
    betas = _real(fields["betas"].reshape(-1), None, f"{path}: betas", "(K,)")
    _finite_frames(poses.reshape(t, -1), trans, path)
    if not np.isfinite(betas).all():
        raise ValueError(f"{path}: betas: expected finite values, got {int((~np.isfinite(betas)).sum())} NaN/inf")
    gender = _gender(fields["gender"], path)
    fps_field = fields["mocap_framerate"]
    if fps_field.size != 1 or fps_field.dtype.kind not in "fiu":
        raise ValueError(f"{path}: mocap_framerate: expected a number, got {fps_field.dtype} {fps_field.shape}")
    fps = check_fps(float(fps_field.reshape(())), f"{path}: mocap_framerate")
    return AmassTake(family, gender, poses, trans, betas, fps, tuple(notes))


def _member(data: np.lib.npyio.NpzFile, key: str, path: Path) -> np.ndarray:
    try:
        return data[key]
    except (OSError, ValueError, EOFError) as e:
        raise ValueError(f"{path}: field {key!r} is unreadable ({e})") from None


def _keys(keys: set[str]) -> str:
    return ", ".join(sorted(keys)) or "none"


def _real(x: np.ndarray, shape: tuple[int, ...] | None, where: str, want: str) -> np.ndarray:
    if x.dtype.kind not in "fiu" or (shape is not None and x.shape != shape):
        raise ValueError(f"{where}: expected real numbers of shape {want}, got {x.dtype} {x.shape}")
    return x.astype(np.float64)


def _poses(fields: dict, keys: set[str], path: Path, notes: list[str]) -> tuple[str, np.ndarray]:
    """The family and the full pose (T, J, 3) of either layout."""
    stated = None
    if "surface_model_type" in fields:
        stated = _string(fields["surface_model_type"], path, "surface_model_type")
        stated = {"smpl+h": "smplh", "smplx_locked_head": "smplx"}.get(stated, stated)
    if "poses" in fields and fields["poses"].ndim == 2 and fields["poses"].shape[1] in (156, 165):
        poses = fields["poses"]
        family = "smplh" if poses.shape[1] == 156 else "smplx"
    elif {"root_orient", "pose_body", "pose_hand"} <= keys:
        family = "smplx" if ({"pose_jaw", "pose_eye"} & keys or stated == "smplx") else "smplh"
        t = fields["root_orient"].shape[0] if fields["root_orient"].ndim == 2 else -1
        parts = []
        for key, width in _SPLIT[: 3 if family == "smplh" else 5]:
            if key not in fields:
                notes.append(f"{key} missing: zeros used")
                parts.append(np.zeros((max(t, 0), width)))
                continue
            x = fields[key]
            if x.ndim != 2 or x.shape != (t, width) or x.dtype.kind not in "fiu":
                raise ValueError(
                    f"{path}: {key}: expected real numbers of shape ({t}, {width}), got {x.dtype} {x.shape}"
                )
            parts.append(x)
        body, hand = parts[:2], parts[2]
        poses = np.concatenate(body + ([*parts[3:5], hand] if family == "smplx" else [hand]), axis=1)
    else:
        shape = f" (poses {fields['poses'].shape})" if "poses" in fields else ""
        raise ValueError(f"{path}: unknown AMASS layout{shape}; keys: {_keys(keys)}; expected {_LAYOUTS}")
    if stated is not None and stated != family:
        raise ValueError(
            f"{path}: surface_model_type {stated!r} does not match the pose layout ({family}, poses {poses.shape})"
        )
    if poses.dtype.kind not in "fiu":
        raise ValueError(f"{path}: poses: expected real numbers, got dtype {poses.dtype}")
    return family, poses.astype(np.float64).reshape(poses.shape[0], _JOINTS[family], 3)


def _finite_frames(poses: np.ndarray, trans: np.ndarray, path: Path) -> None:
    bad = np.flatnonzero(~(np.isfinite(poses).all(1) & np.isfinite(trans).all(1)))
    if bad.size:
        shown = ", ".join(str(i) for i in bad[:10]) + (", ..." if bad.size > 10 else "")
        raise ValueError(f"{path}: NaN/inf in poses or trans at frames {shown} ({bad.size} of {len(poses)} frames)")


def _string(x: np.ndarray, path: Path, key: str) -> str:
    """A 0-d or one-element string array (str or bytes), stripped and lower-cased."""
    if x.dtype.kind not in "US" or x.size != 1:
        raise ValueError(f"{path}: {key}: expected a string, got {x.dtype} {x.shape}")
    value = x.reshape(())[()]
    return (value.decode("latin1") if isinstance(value, bytes) else str(value)).strip().lower()


def _gender(x: np.ndarray, path: Path) -> str:
    g = _string(x, path, "gender")
    if g not in ("neutral", "male", "female"):
        raise ValueError(f"{path}: gender: expected neutral, male or female, got {g!r}")
    return g


# --- model files --------------------------------------------------------------------------------------------


def _family_from_path(path: Path, root: Path) -> str | None:
    try:
        rel = path.relative_to(root)
    except ValueError:
        rel = Path(path.name)
    text = re.sub(r"[^a-z]", "", f"{root.name}/{rel}".lower())
    for family in ("smplx", "smplh", "mano", "smpl"):
        if family in text:
            return family
    return None


def find_model(models: str | Path | None, family: str, gender: str, *, source: str | Path = "") -> Path:
    """The user's model file of ``family`` and ``gender`` in ``models`` (a file or a folder, recursive).

    Raises:
        ValueError: ``models`` is None or missing, or holds no such file (the message names
            the gender, the folder and the files found).
    """
    where = f"{source}: " if source else ""
    if models is None:
        raise ValueError(f"{where}an AMASS {family} take needs the user's model files: pass --models FOLDER")
    models = Path(models)
    if models.is_file():
        return models
    if not models.is_dir():
        raise ValueError(f"{where}--models: {models} is neither a model file nor a folder")
    files = sorted(p for p in models.rglob("*") if p.suffix.lower() in (".npz", ".pkl") and p.is_file())
    found = [(p, _family_from_path(p, models), gender_from_path(p)) for p in files]
    named = [p for p, f, g in found if f == family and g == gender]
    unnamed = [p for p, f, g in found if f is None and g == gender and _counted_family(p) == family]
    match = sorted(named + unnamed, key=lambda p: (p.suffix.lower() != ".npz", len(p.parts), str(p)))
    if match:
        return match[0]
    listing = "; ".join(f"{p.relative_to(models)} ({f or '?'} {g})" for p, f, g in found[:12]) or "none"
    raise ValueError(
        f"{where}no {family} model file for gender {gender!r} in {models} (found: {listing}); "
        f"add one (e.g. {family.upper()}_{gender.upper()}.npz); a neutral model is not substituted"
    )


def _counted_family(path: Path) -> str | None:
    """The family of a file that names none, from its vertex and joint counts (None if unreadable)."""
    from ..identity.smpl import read_model_file

    try:
        a = read_model_file(path)
    except (ValueError, OSError):
        return None
    return FAMILIES.get((a["v_template"].shape[0], a["J_regressor"].shape[0]))


@lru_cache(maxsize=4)
def _model(path: str, stamp: int, dtype: torch.dtype) -> SMPLModel:
    return SMPLModel.from_file(path, dtype=dtype)


@lru_cache(maxsize=4)
def _transfer(path: str, stamp: int, dtype: torch.dtype) -> TopologyTransfer:
    model = _model(path, stamp, dtype)
    with torch.no_grad():
        t = topology_transfer(model.template().double(), model.faces(), f"{model.name} {Path(path).name}")
    return t.to(dtype)


@lru_cache(maxsize=8)
def _inverter(preset: str, dtype: torch.dtype) -> tuple[BodyLayer, PoseInverter]:
    layer = _layer("pca", _PCA_COMPONENTS, dtype)
    return layer, PoseInverter(layer, PRESETS[preset])


def inverter(options: ConvertOptions) -> tuple[BodyLayer, PoseInverter, torch.dtype]:
    """The canonical layer and the inverter of ``options`` (built once per process), and the dtype."""
    dtype = {"float32": torch.float32, "float64": torch.float64}[options.dtype]  # ConvertOptions checked it
    return (*_inverter(options.preset, dtype), dtype)


def to_y_up(x: torch.Tensor) -> torch.Tensor:
    """AMASS Z-up to unibody Y-up: ``(x, y, z) -> (x, z, -y)`` on the last axis."""
    a, b, c = x.unbind(-1)
    return torch.stack([a, c, -b], dim=-1)


# --- the conversion -----------------------------------------------------------------------------------------


def solve_meshes(
    meshes, prepared, inv: PoseInverter, batch: int, times: dict[str, float]
) -> tuple[np.ndarray, np.ndarray, float, float]:
    """Invert posed meshes batch by batch.

    Args:
        meshes: a callable ``meshes(start, stop) -> (B, V, 3)`` canonical-topology tensor
            (it may add to ``times``).
        prepared: the identity (batch 1).
        inv: the inverter.
        batch: frames per batch.
        times: ``time_inversion_s`` is added to it.

    Returns:
        ``(pose (T, 77, 3) float32, transl (T, 3) float32, mean error mm, max error mm)``.
    """
    poses, transl, total, count, worst = [], [], 0.0, 0, 0.0
    start, frames = 0, meshes.frames
    while start < frames:
        stop = min(start + batch, frames)
        target = meshes(start, stop)
        t0 = time.perf_counter()
        with torch.enable_grad() if inv.config.method == "autograd" else torch.no_grad():
            result = inv.invert(target, prepared)
        times["time_inversion_s"] = times.get("time_inversion_s", 0.0) + time.perf_counter() - t0
        poses.append(result.pose.detach().cpu().numpy().astype(np.float32))
        transl.append(result.transl.detach().cpu().numpy().astype(np.float32))
        if result.per_vertex_error is not None:
            err = result.per_vertex_error.detach()
            total += float(err.double().sum())
            count += err.numel()
            worst = max(worst, float(err.max()))
        start = stop
    mean = 1000 * total / count if count else float("nan")
    return np.concatenate(poses), np.concatenate(transl), mean, 1000 * worst


class _AmassMeshes:
    """Posed, Y-up, transferred meshes of a take, by frame range (times the stages)."""

    def __init__(self, take: AmassTake, model: SMPLModel, transfer: TopologyTransfer, betas: torch.Tensor, times):
        self.take, self.model, self.transfer, self.betas, self.times = take, model, transfer, betas, times
        self.frames = take.poses.shape[0]

    def __call__(self, start: int, stop: int) -> torch.Tensor:
        dtype = self.betas.dtype
        out, forward, transfer = [], 0.0, 0.0
        with torch.no_grad():
            for s in range(start, stop, _FORWARD_CHUNK):
                t0 = time.perf_counter()
                e = min(s + _FORWARD_CHUNK, stop)
                pose = torch.as_tensor(self.take.poses[s:e], dtype=dtype)
                trans = torch.as_tensor(self.take.trans[s:e], dtype=dtype)
                verts = to_y_up(self.model(pose, self.betas, transl=trans).vertices)
                t1 = time.perf_counter()
                out.extend(self.transfer(verts[k : k + _TRANSFER_CHUNK]) for k in range(0, e - s, _TRANSFER_CHUNK))
                forward, transfer = forward + t1 - t0, transfer + time.perf_counter() - t1
        self.times["time_forward_s"] = self.times.get("time_forward_s", 0.0) + forward
        self.times["time_transfer_s"] = self.times.get("time_transfer_s", 0.0) + transfer
        return torch.cat(out)


def read_amass(path: Path, options: ConvertOptions) -> Converted:
    """Convert an AMASS file (SMPL-H or SMPL-X) to the canonical motion (see the module docstring).

    Raises:
        ValueError: an unknown layout, a malformed field, NaN/inf frames, no model file for the
            take's family and gender, or a model file of another family (one line, naming the file).
    """
    path = Path(path)
    layer, inv, dtype = inverter(options)
    t0 = time.perf_counter()
    take = read_take(path)
    times = {"time_io_s": time.perf_counter() - t0}
    model_path = find_model(options.models, take.family, take.gender, source=path)
    stamp = model_path.stat().st_mtime_ns
    model = _model(str(model_path), stamp, dtype)
    if model.name != take.family:
        raise ValueError(
            f"{path}: the {take.family} take needs a {take.family} model file; {model_path} is {model.name}"
        )
    notes = list(take.warnings)
    betas = np.zeros(model.num_betas)
    k = min(len(take.betas), model.num_betas)
    betas[:k] = take.betas[:k]
    if len(take.betas) > k and np.any(take.betas[k:] != 0):
        notes.append(f"betas {k + 1}..{len(take.betas)} dropped: {model_path.name} has {model.num_betas} shape columns")
    betas_t = torch.as_tensor(betas, dtype=dtype)[None]
    t1 = time.perf_counter()
    transfer = _transfer(str(model_path), stamp, dtype)
    with torch.no_grad():
        rest = transfer(model.shaped(betas_t))
        prepared = layer.prepare_rest(rest)
    times["time_transfer_s"] = time.perf_counter() - t1
    meshes = _AmassMeshes(take, model, transfer, betas_t, times)
    pose, transl, mean_mm, max_mm = solve_meshes(meshes, prepared, inv, options.batch, times)
    identity, identity_mm = pca_identity(layer, prepared)
    motion = Motion(pose, transl, take.fps, identity, "pca", f"amass {take.family} {take.gender}: {path.name}")
    stats = {
        "frames": int(pose.shape[0]),
        "fps": take.fps,
        "model": model_path.name,
        "inversion_mean_mm": mean_mm,
        "inversion_max_mm": max_mm,
        "identity_mean_mm": identity_mm,
        **{k: round(v, 4) for k, v in times.items()},
    }
    return Converted(motion, stats, tuple(notes))


def pca_identity(layer: BodyLayer, prepared) -> tuple[np.ndarray, float]:
    """Native PCA coefficients of a prepared rest shape, and the fit's mean error in mm.

    The rest shape is reposed to the bind pose, its centroid moved onto the PCA mean's, and
    projected by least squares (a rest shape may sit anywhere: SMPL's origin is near the
    pelvis, an estimated one at the posed Hips; the motion's ``transl`` places the body).
    """
    with torch.no_grad():
        bind = layer.repose_to_bind(prepared)
        mean = layer.identity(layer.identity.default_params(1).to(bind))
        bind = bind - bind.mean(1, keepdim=True) + mean.mean(1, keepdim=True)
        coeffs = layer.identity.project(bind)
        err = float(torch.linalg.vector_norm(layer.identity(coeffs) - bind, dim=-1).mean()) * 1000
    return coeffs[0].cpu().numpy().astype(np.float32), err
