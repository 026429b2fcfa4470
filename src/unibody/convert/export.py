"""Writers of rigged, animated exports (glTF 2.0 binary, USD) and of canonical mesh sequences.

Each follows the convert writer contract ``write_<format>(motion, path, options) -> None``:
it poses the motion's body (:func:`~unibody.convert._body.body_for`) with
:meth:`~unibody.body.BodyLayer.pose` in batches of ``options.batch`` frames and writes exactly
``path``, atomically. The source frame rate is kept: frame i is at ``i / motion.fps`` seconds.

Rigged exports (:func:`write_glb`, :func:`write_usd`) hold the identity's canonical rest mesh,
bound to the 78 joints at their rest transforms (the inverse bind matrices), and per frame
each joint's local rotation and translation ``G_parent^-1 G_k`` from the posed world
transforms. They keep only the (T, 78) transforms in memory, never the posed meshes.

glTF keeps 8 influences per vertex (``JOINTS_0/1``, ``WEIGHTS_0/1``), what common engines
read; the canonical mesh has up to 14 (1,940 of its 18,056 vertices have more than 8). Keeping
the top 8, renormalised, moves vertices by at most 0.021 mm (mean 1e-5 mm) over 64 sampled
poses (``synth.sample_poses``, seed 0, bend 0.3, fold 0.2; top 4 would move them up to 6.3 mm).
USD keeps every influence.
"""

from __future__ import annotations

import zipfile
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import torch

from ..body import BodyLayer, PreparedIdentity
from ..geometry.rotations import matrix_to_quat_xyzw
from ..io.atomic import atomic_write
from ..io.glb import SkinnedAnimation, write_skinned_glb
from ..motion import Motion, check_fps, check_motion
from ._body import body_for
from ._types import ConvertOptions

__all__ = ["GLB_INFLUENCES", "write_glb", "write_meshes", "write_usd"]

GLB_INFLUENCES = 8
"""Influences per vertex in glTF exports (two JOINTS/WEIGHTS sets); see the module docstring."""

_DTYPES = {"float32": torch.float32, "float64": torch.float64}


def _check(motion: Motion, path: object, options: ConvertOptions, suffixes: tuple[str, ...]) -> Path:
    """ValueError (one line, naming the argument) unless the writer's arguments are usable."""
    if not isinstance(motion, Motion):
        raise ValueError(f"motion: expected a unibody.motion.Motion, got {type(motion).__name__}")
    if not isinstance(options, ConvertOptions):
        raise ValueError(f"options: expected a ConvertOptions, got {type(options).__name__}")
    if not isinstance(path, str | Path):
        raise ValueError(f"path: expected a file path, got {type(path).__name__}")
    path = Path(path)
    if path.suffix.lower() not in suffixes:
        raise ValueError(f"path: expected a {' or '.join(suffixes)} file, got {str(path)!r}")
    pose, transl = np.asarray(motion.pose), np.asarray(motion.transl)
    if pose.ndim != 3 or pose.shape[0] == 0 or pose.shape[1:] != (77, 3) or pose.dtype.kind != "f":
        raise ValueError(f"motion.pose: expected (T, 77, 3) floats with T >= 1, got {pose.shape} {pose.dtype}")
    if transl.shape != (pose.shape[0], 3) or transl.dtype.kind != "f":
        raise ValueError(f"motion.transl: expected ({pose.shape[0]}, 3) floats, got {transl.shape} {transl.dtype}")
    for name, x in (("pose", pose), ("transl", transl)):
        bad = ~np.isfinite(x).reshape(len(x), -1).all(axis=1)
        if bad.any():
            raise ValueError(
                f"motion.{name}: expected finite values, got NaN/inf at frame(s) {np.flatnonzero(bad)[:5].tolist()}"
            )
    check_motion(motion)  # float32's range, the root's distance, the identity, the rate
    return path  # options: ConvertOptions checked its batch and dtype when made


def _posed(
    motion: Motion, options: ConvertOptions, meshes: bool = True
) -> tuple[BodyLayer, PreparedIdentity, Iterator[tuple[torch.Tensor, torch.Tensor | None]]]:
    """The motion's body and an iterator over its posed frames, ``options.batch`` at a time.

    Each item is ``(transforms (B, J, 4, 4), vertices (B, V, 3) or None)``. Without ``meshes``
    the skinning is skipped (FK only, :meth:`BodyLayer.skin_transforms`): the rigged exports
    need only the transforms, and 2,000 frames then take 1.0 s instead of 9.1 s (batch 256,
    min of 3 interleaved runs, 2 shared CPU cores). A layer with procedural twist joints always goes
    through :meth:`BodyLayer.pose` (its twist joints move the mesh, not the 78 public joints).
    """
    dtype = _DTYPES[options.dtype]
    layer, prepared = body_for(motion, dtype)
    bottom = torch.tensor([0.0, 0.0, 0.0, 1.0], dtype=dtype)

    def batches() -> Iterator[tuple[torch.Tensor, torch.Tensor | None]]:
        with torch.no_grad():
            for s in range(0, len(motion.pose), options.batch):
                pose = torch.as_tensor(np.asarray(motion.pose[s : s + options.batch]), dtype=dtype)
                transl = torch.as_tensor(np.asarray(motion.transl[s : s + options.batch]), dtype=dtype)
                if meshes or layer.twist is not None:
                    out = layer.pose(prepared, pose, transl=transl)
                    yield out.transforms, out.vertices
                    continue
                rot, pos, _ = layer.skin_transforms(prepared, layer.local_rotations(pose), transl)
                top = torch.cat([rot, pos[..., None]], dim=-1)
                yield torch.cat([top, bottom.expand(*top.shape[:2], 1, 4)], dim=-2), None

    return layer, prepared, batches()


def _local(transforms: torch.Tensor, parents: torch.Tensor, is_root: torch.Tensor) -> tuple[np.ndarray, np.ndarray]:
    """Posed world transforms (B, J, 4, 4) -> local quaternions (B, J, 4) xyzw and translations (B, J, 3).

    Local = G_parent^-1 G_k; a root keeps its world transform.
    """
    g = transforms.double()
    rot, pos = g[..., :3, :3], g[..., :3, 3]
    rp_t = rot[:, parents].transpose(-1, -2)
    local_r = torch.where(is_root[:, None, None], rot, rp_t @ rot)
    local_t = torch.where(is_root[:, None], pos, (rp_t @ (pos - pos[:, parents])[..., None]).squeeze(-1))
    return matrix_to_quat_xyzw(local_r).numpy(), local_t.numpy()


def _skinned(motion: Motion, options: ConvertOptions, influences: int | None) -> SkinnedAnimation:
    """The motion as a :class:`SkinnedAnimation` of its canonical rest mesh (top ``influences``, or all)."""
    layer, prepared, frames = _posed(motion, options, meshes=False)
    parents_list = [int(p) for p in layer.rig_tree.parents]
    parents = torch.tensor([max(p, 0) for p in parents_list])
    is_root = torch.tensor([p < 0 for p in parents_list])
    t, j = len(motion.pose), layer.num_joints
    rotations, translations = np.empty((t, j, 4)), np.empty((t, j, 3))
    s = 0
    for transforms, _ in frames:
        b = transforms.shape[0]
        rotations[s : s + b], translations[s : s + b] = _local(transforms, parents, is_root)
        s += b

    bind = np.zeros((j, 4, 4))
    bind[:, :3, :3] = prepared.rest_rotations[0].double().numpy()
    bind[:, :3, 3] = prepared.rest_joints[0].double().numpy()
    bind[:, 3, 3] = 1.0
    weights = layer.skinning.dense().double().numpy()  # (V, J): 18,056 x 78, 11 MB
    k = int((weights > 0).sum(axis=1).max()) if influences is None else influences
    top = np.argsort(-weights, axis=1, kind="stable")[:, :k]
    top_w = np.take_along_axis(weights, top, axis=1)
    return SkinnedAnimation(
        vertices=prepared.rest_vertices[0].double().numpy(),
        faces=layer.faces.numpy(),
        joint_names=tuple(layer.joint_names),
        parents=np.asarray(parents_list),
        bind_matrices=bind,
        joint_indices=top,
        joint_weights=top_w / top_w.sum(axis=1, keepdims=True),
        rotations=rotations,
        translations=translations,
        fps=check_fps(motion.fps, "motion.fps"),
    )


def write_glb(motion: Motion, path: Path, options: ConvertOptions) -> None:
    """Write ``motion`` as a skinned, animated glTF 2.0 binary (``.glb``) at exactly ``path``.

    One mesh (the identity's canonical rest mesh), a skin over the 78 joints (a node per joint,
    named as :data:`unibody.JOINT_NAMES`, Root the scene root), :data:`GLB_INFLUENCES` influences
    per vertex, one animation with a rotation and a translation channel per joint (LINEAR, at
    ``i / fps`` s). Metres, Y up, the body faces +Z (glTF's own axes).

    Raises:
        ValueError: a bad ``motion``, ``options`` or ``path`` (not ``.glb``): one line naming it.
    """
    path = _check(motion, path, options, (".glb",))
    write_skinned_glb(path, _skinned(motion, options, GLB_INFLUENCES))


def write_usd(motion: Motion, path: Path, options: ConvertOptions) -> None:
    """Write ``motion`` as a UsdSkel stage (``.usda`` text, ``.usdc`` or ``.usd`` crate) at exactly ``path``.

    A SkelRoot ``/Body`` (the default prim) holding the Skeleton, its SkelAnimation (time code
    i = frame i, ``timeCodesPerSecond`` = fps) and the skinned Mesh with every influence
    (:func:`unibody.io.usd.write_skinned_usd`). Needs the optional ``usd-core`` package.

    Raises:
        ValueError: a bad ``motion``, ``options`` or ``path`` (not ``.usda``/``.usdc``/``.usd``).
        ImportError: ``usd-core`` is not installed (the message says ``pip install 'unibody[usd]'``).
    """
    from ..io.usd import USD_SUFFIXES, write_skinned_usd

    path = _check(motion, path, options, USD_SUFFIXES)
    write_skinned_usd(path, _skinned(motion, options, None))


def write_meshes(motion: Motion, path: Path, options: ConvertOptions) -> None:
    """Write the posed canonical meshes of ``motion`` as a mesh-sequence ``.npz`` at exactly ``path``.

    Fields: ``vertices`` (T, V, 3) float32 m, ``faces`` (F, 3) int64, ``topology`` "canonical",
    ``fps`` () float32, and ``identity`` (K,) / ``identity_backend`` when the motion has an
    identity (:func:`unibody.motion.load_mesh_sequence` reads it). Streamed: ``vertices`` is
    written batch by batch into the archive (uncompressed, ZIP64), so memory holds one batch of
    meshes (``options.batch`` x 18,056 x 3 floats), not T of them (T x 217 KB).

    Raises:
        ValueError: a bad ``motion``, ``options`` or ``path`` (not ``.npz``): one line naming it.
    """
    path = _check(motion, path, options, (".npz",))
    layer, _, frames = _posed(motion, options)
    shape = (len(motion.pose), layer.num_vertices, 3)
    small = {
        "faces": layer.faces.numpy().astype(np.int64),
        "topology": np.asarray("canonical"),
        "fps": np.asarray(check_fps(motion.fps, "motion.fps"), np.float32),
    }
    if motion.identity is not None:
        small["identity"] = np.asarray(motion.identity, np.float32)
        small["identity_backend"] = np.asarray(motion.identity_backend or "")
    with atomic_write(path) as fh, zipfile.ZipFile(fh, "w", zipfile.ZIP_STORED, allowZip64=True) as zf:
        with zf.open("vertices.npy", "w", force_zip64=True) as member:
            header = {"descr": np.lib.format.dtype_to_descr(np.dtype("<f4")), "fortran_order": False, "shape": shape}
            np.lib.format.write_array_header_2_0(member, header)
            for _, vertices in frames:
                member.write(np.ascontiguousarray(vertices.numpy(), dtype="<f4").tobytes())
        for name, array in small.items():
            with zf.open(f"{name}.npy", "w") as member:
                np.lib.format.write_array(member, array, allow_pickle=False)
