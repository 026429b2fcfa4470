"""Mesh sequences of any registered topology to the canonical motion.

Input: an ``.npz`` with ``vertices (T, N, 3)`` (metres, unibody axes: Y up), ``topology`` (a
name, used in messages and the motion's ``source``), optionally ``fps`` (default 30, with a
warning) and ``faces (F, 3)`` (checked, not used). The topology is told by the vertex count:

- 18,056: the canonical mesh, inverted directly;
- 13,718: Anny's mesh, through the bundled wrap (:meth:`TopologyTransfer.from_anny`);
- anything else (SMPL 6,890, SMPL-X 10,475, MHR lod1 18,439, ...): ``options.template`` names
  its rest mesh, an ``.obj`` with faces, an SMPL-family model file (``.npz`` / ``.pkl``, its
  ``v_template`` and ``f``) or an MHR asset folder (``rig.npz`` + ``lod{N}.npz``, the LOD
  whose vertex count matches the sequence; its mean rest mesh in metres), in the same units
  and axes as the sequence. It is registered onto
  the canonical mesh automatically (:func:`unibody.registration.topology_transfer`, cached on
  disk; a new template costs ~40 s once). A template also overrides the two counts above.

The rest shape is unknown in a mesh sequence: it is estimated from frame 0
(:meth:`PoseInverter.estimate_identity`, as ``unibody invert`` does), then every frame is
inverted at ``options.preset`` in batches of ``options.batch``. The motion keeps the frame
rate; its identity is the native PCA projection of that rest shape (see
:func:`unibody.convert.amass.pca_identity`).
"""

from __future__ import annotations

import time
from functools import lru_cache
from pathlib import Path

import numpy as np
import torch

from ..io.npz import read_npz
from ..io.obj import read_obj
from ..motion import Motion, check_fps
from ..registration import topology_transfer
from ..topology import CANONICAL_VERTICES, TopologyTransfer
from ._types import Converted, ConvertOptions
from .amass import _TRANSFER_CHUNK, _member, _string, inverter, pca_identity, solve_meshes

__all__ = ["read_meshes", "template_transfer"]

ANNY_VERTICES = 13718
DEFAULT_FPS = 30.0
_TEMPLATE_HELP = (
    "--template takes the topology's rest mesh: an .obj with faces, an SMPL-family .npz/.pkl model file, "
    "or an MHR asset folder"
)


def _read(path: Path) -> tuple[np.ndarray, str, float | None]:
    """vertices (T, N, 3) float64, topology, fps (None when absent); every field checked."""
    with read_npz(path) as data:
        missing = {"vertices", "topology"} - set(data.files)
        if missing:
            raise ValueError(
                f"{path}: missing field(s) {', '.join(sorted(missing))}; expected vertices (T, N, 3) and topology "
                f"(fields: {', '.join(sorted(data.files)) or 'none'})"
            )
        v, topo = _member(data, "vertices", path), _member(data, "topology", path)
        fps = _member(data, "fps", path) if "fps" in data.files else None
        faces = _member(data, "faces", path) if "faces" in data.files else None
    if v.ndim != 3 or v.shape[2] != 3 or v.shape[0] == 0 or v.dtype.kind != "f":
        raise ValueError(f"{path}: vertices: expected floats of shape (T, N, 3) with T >= 1, got {v.dtype} {v.shape}")
    bad = np.flatnonzero(~np.isfinite(v).all(axis=(1, 2)))
    if bad.size:
        shown = ", ".join(str(i) for i in bad[:10]) + (", ..." if bad.size > 10 else "")
        raise ValueError(f"{path}: vertices: NaN/inf at frames {shown} ({bad.size} of {len(v)} frames)")
    if fps is not None:
        if fps.size != 1 or fps.dtype.kind not in "fiu":
            raise ValueError(f"{path}: fps: expected a number, got {fps.dtype} {fps.shape}")
        fps = check_fps(float(fps.reshape(())), f"{path}: fps")
    if faces is not None:
        n = v.shape[1]
        ok = faces.ndim == 2 and faces.shape[1] == 3 and faces.dtype.kind in "iu"
        if not ok or (faces.size and (faces.min() < 0 or faces.max() >= n)):
            raise ValueError(
                f"{path}: faces: expected integer triangles (F, 3) with ids in [0, {n}), got {faces.shape}"
            )
    return v, _string(topo, path, "topology"), fps


def _template(path: Path, n: int) -> tuple[np.ndarray, object]:
    """(vertices (V, 3), faces) of a template: an OBJ, an SMPL-family model file, or an MHR folder."""
    if path.is_dir():
        return _mhr_template(path, n)
    suffix = path.suffix.lower()
    if suffix == ".obj":
        v, faces = read_obj(path)
        if not faces:
            raise ValueError(f"--template: {path} has no faces; {_TEMPLATE_HELP}")
        return v, faces
    if suffix in (".npz", ".pkl"):
        from ..identity.smpl import read_model_file

        a = read_model_file(path)
        return a["v_template"].astype(np.float64), a["f"].astype(np.int64)
    raise ValueError(f"--template: expected an .obj, .npz or .pkl file, got {path.name!r}; {_TEMPLATE_HELP}")


def _mhr_template(folder: Path, n: int) -> tuple[np.ndarray, np.ndarray]:
    """The mean rest mesh (m) and faces of the MHR LOD with ``n`` vertices in an asset folder."""
    from ..identity.mhr import MHRIdentity

    lods = sorted(int(p.stem[3:]) for p in folder.glob("lod*.npz") if p.stem[3:].isdigit())
    if not lods:
        raise ValueError(f"--template: folder {folder} holds no MHR lod*.npz; {_TEMPLATE_HELP}")
    counts = {}
    for lod in lods:
        with read_npz(folder / f"lod{lod}.npz") as data:
            counts[lod] = data["base_shape"].shape[0] if "base_shape" in data.files else -1
    match = [lod for lod, count in counts.items() if count == n]
    if not match:
        raise ValueError(f"--template: no MHR LOD in {folder} has {n} vertices (LOD: vertices {counts})")
    identity = MHRIdentity.from_files(folder, lod=match[0], dtype=torch.float64)
    with torch.no_grad():
        return identity.template().numpy(), identity.faces().numpy()


@lru_cache(maxsize=4)
def _cached_transfer(path: str, stamp: int, n: int) -> TopologyTransfer:
    v, faces = _template(Path(path), n)
    with torch.no_grad():
        try:
            return topology_transfer(v, faces, Path(path).stem)
        except ValueError as exc:  # the template, not the input file, is what the user must change
            raise ValueError(f"--template {Path(path).name}: {exc}") from exc


def template_transfer(template: str | Path, num_vertices: int) -> TopologyTransfer:
    """The float64 transfer of a template's topology (registered once, cached on disk and in the process).

    ``num_vertices`` picks the LOD of an MHR folder (files carry one topology each).
    """
    path = Path(template)
    if not path.exists():
        raise ValueError(f"--template: nothing at {path}; {_TEMPLATE_HELP}")
    return _cached_transfer(str(path), path.stat().st_mtime_ns, num_vertices)


def _transfer_for(path: Path, n: int, topology: str, options: ConvertOptions) -> TopologyTransfer | None:
    if options.template is not None:
        transfer = template_transfer(options.template, n)
        if transfer.num_source_vertices != n:
            raise ValueError(
                f"{path}: vertices have {n} per frame but the template {Path(options.template).name} has "
                f"{transfer.num_source_vertices}; {_TEMPLATE_HELP} of this sequence's topology"
            )
        return transfer
    if n == CANONICAL_VERTICES:
        return None
    if n == ANNY_VERTICES:
        return TopologyTransfer.from_anny()
    raise ValueError(
        f"{path}: vertices have {n} per frame (topology {topology!r}), not the canonical {CANONICAL_VERTICES} or "
        f"Anny's {ANNY_VERTICES}: pass --template; {_TEMPLATE_HELP}"
    )


class _Sequence:
    """Canonical-topology meshes of a sequence by frame range (times the transfer)."""

    def __init__(self, vertices: np.ndarray, transfer: TopologyTransfer | None, dtype: torch.dtype, times: dict):
        self.vertices, self.transfer, self.dtype, self.times = vertices, transfer, dtype, times
        self.frames = len(vertices)

    def __call__(self, start: int, stop: int) -> torch.Tensor:
        t0 = time.perf_counter()
        v = torch.as_tensor(self.vertices[start:stop], dtype=self.dtype)
        if self.transfer is not None:
            with torch.no_grad():  # in chunks that stay in cache (see unibody.convert.amass)
                v = torch.cat([self.transfer(v[k : k + _TRANSFER_CHUNK]) for k in range(0, len(v), _TRANSFER_CHUNK)])
        self.times["time_transfer_s"] = self.times.get("time_transfer_s", 0.0) + time.perf_counter() - t0
        return v


def read_meshes(path: Path, options: ConvertOptions) -> Converted:
    """Convert a mesh sequence (see the module docstring) to the canonical motion.

    Raises:
        ValueError: a missing or malformed field, NaN/inf frames (named by index), a foreign
            vertex count without ``--template`` (or one that differs from the template's), or
            meshes the inverter refuses (one line, naming the file).
    """
    path = Path(path)
    layer, inv, dtype = inverter(options)
    t0 = time.perf_counter()
    vertices, topology, fps = _read(path)
    times = {"time_io_s": time.perf_counter() - t0}
    notes = []
    if fps is None:
        fps = DEFAULT_FPS
        notes.append(f"fps missing: {DEFAULT_FPS:g} assumed")
    t1 = time.perf_counter()
    transfer = _transfer_for(path, vertices.shape[1], topology, options)
    if transfer is not None:
        transfer = _as(transfer, dtype)
    times["time_transfer_s"] = time.perf_counter() - t1
    seq = _Sequence(vertices, transfer, dtype, times)
    try:
        with torch.no_grad():
            prepared = inv.estimate_identity(seq(0, 1))
        pose, transl, mean_mm, max_mm = solve_meshes(seq, prepared, inv, options.batch, times)
    except ValueError as e:
        raise ValueError(f"{path}: {e}") from None
    identity, identity_mm = pca_identity(layer, prepared)
    motion = Motion(pose, transl, fps, identity, "pca", f"meshes {topology}: {path.name}")
    stats = {
        "frames": int(pose.shape[0]),
        "fps": fps,
        "topology": topology,
        "inversion_mean_mm": mean_mm,
        "inversion_max_mm": max_mm,
        "identity_mean_mm": identity_mm,
        **{k: round(v, 4) for k, v in times.items()},
    }
    return Converted(motion, stats, tuple(notes))


def _as(transfer: TopologyTransfer, dtype: torch.dtype) -> TopologyTransfer:
    """The transfer in ``dtype`` (a copy: ``Module.to`` would change the cached one in place)."""
    if transfer.weights.dtype == dtype:
        return transfer
    return TopologyTransfer(
        transfer.name, transfer.num_source_vertices, transfer.face_vertices, transfer.weights.to(dtype)
    )
