"""MHR identity backend: 45 identity coefficients + bone scales -> rest mesh (native topology).

MHR (Meta's Momentum Human Rig, Apache-2.0) shapes a body in two ways: 45 PCA identity
blendshapes (20 body, 20 head, 5 hands) move the rest vertices, and the *scale* model
parameters grow or shrink bones; the skinning then carries the shaped rest mesh along the
scaled skeleton. This module evaluates exactly that identity + bone-scale path with zero
pose, zero facial expression and no pose correctives, in torch, without pymomentum.

Parameters, in order (``param_names``):
    * 45 identity coefficients ``body_00..body_19, head_00..head_19, hands_0..hands_4``,
      zero-mean, unit-variance (typical range -3..3, MHR README);
    * the S bone-scale model parameters flagged in ``scaling_parameters`` (68 in MHR),
      in the file's model-parameter order, named after ``parameter_names``; a value ``x``
      sets joint scales ``2 ** (PT x)``, 0 is the template skeleton. Their limits in the
      file are returned by :meth:`MHRIdentity.param_limits`.

Assets (MHR's own portable format, schema version 1) in one folder: ``rig.npz`` (shared
by all LODs) and ``lod{N}.npz``. They are what ``scripts/convert_assets.py`` of MHR's main
branch (after 1.0.1) writes from the release files (``lod{N}.fbx`` + ``compact_v6_1.model``,
which only pymomentum's C++ reads) and what ``python -m mhr.download_assets --lod N`` of
that branch fetches. MHR is centimetres, Y up, facing +Z; this module converts to metres
once, at load (the axes already match unibody's). Pose correctives and expressions stored
in the same files are never read.

Facts relied on (no code copied):
    * mhr 1.0.1 wheel, ``mhr/mhr.py`` ``MHR.from_files``: ``lod{lod}.fbx`` and
      ``compact_v6_1.model`` go through ``pymomentum.geometry.Character.load_fbx(...,
      load_blendshapes=True)``; 45 identity + 72 expression blendshapes; the blend-shape
      coefficients are appended as the *last* 117 model parameters. ``MHR.forward``:
      rest = base_shape + sum_k c_k shape_vectors[k]; joint parameters = PT @ [model
      parameters (204), zeros (117)]; skeleton state by FK; vertices = skin_points(state, rest).
    * mhr 1.0.1 METADATA (README): identity = 20 body, 20 head, 5 hands, typical range -3..3.
    * facebookresearch/momentum ``pymomentum/torch/character.py``: 7 joint parameters per
      joint, [0:3] translation added to ``joint_translation_offsets``, [3:6] XYZ Euler
      angles turned into a quaternion then pre-multiplied by ``joint_prerotations``, [6]
      log2 scale (scale = exp(ln 2 * p)); FK composes skeleton states (t, q xyzw, s) parent
      after child; LBS skins with ``global_state * inverse_bind_pose`` per joint.
    * MHR main branch ``mhr/_torch_rig.py`` (torch runtime for the converted assets): the
      ``rig.npz`` / ``lod{N}.npz`` keys and shapes checked below, ``RIG_SCHEMA_VERSION = 1``,
      ``inverse_bind_pose`` stored as (J, 8) skeleton states (t, q xyzw, s); the Euler
      quaternion is q_z q_y q_x, i.e. R = Rz(rz) Ry(ry) Rx(rx) (``batch6DFromXYZ`` in the
      1.0.1 ``mhr/utils.py`` builds the same matrix); a point transforms as t + R (s p).
    * MHR ``tools/mhr_smpl_conversion/conversion.py``: "MHR uses centimeters while SMPL uses
      meters", converted by a factor 100 only (same axes as SMPL: Y up, facing +Z);
      py-soma-x ``MHRIdentityModel``: native unit centimetres, up +Y, forward +Z, rest
      shapes from 45 identity coefficients and 68 scales with zero pose.
"""

from __future__ import annotations

import math
import zipfile
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
from torch import nn

from .._checks import check_finite, check_like, check_shape
from ..geometry.kinematics import forward_kinematics
from ..geometry.rotations import euler_xyz_to_matrix, quat_xyzw_to_matrix
from ..geometry.skinning import lbs_sparse, register_skin_layout, registered_skin_layout, skin_layout
from ..io.npz import check_npz_members
from ..rig import KinematicTree

__all__ = ["MHRAssets", "MHRIdentity", "load_mhr_assets", "MHR_SCHEMA_VERSION", "NUM_MHR_IDENTITY"]

MHR_SCHEMA_VERSION = 1
NUM_MHR_IDENTITY = 45
_IDENTITY_NAMES: tuple[str, ...] = (
    tuple(f"body_{i:02d}" for i in range(20))
    + tuple(f"head_{i:02d}" for i in range(20))
    + tuple(f"hands_{i}" for i in range(5))
)
_CM_TO_M = 0.01
_PARAMS_PER_JOINT = 7
_RIG_KEYS = (
    "schema_version", "parameter_transform", "scaling_parameters", "parameter_names", "joint_offsets",
    "joint_prerotations", "joint_parents", "joint_names", "inverse_bind_pose",
)  # fmt: skip
_LIMIT_KEYS = ("limit_min", "limit_max", "limit_parameter_index")
_LOD_KEYS = ("schema_version", "lod", "base_shape", "shape_vectors", "faces", "skin_indices", "skin_weights")


@dataclass(frozen=True, eq=False)
class MHRAssets:
    """The identity + bone-scale part of an MHR model, float64 numpy, metres, unibody axes.

    Attributes:
        lod: level of detail of the mesh.
        base_shape: (V, 3) m, the template rest mesh.
        identity_dirs: (45, V, 3) m per unit coefficient.
        faces: (F, 3) int64 triangles.
        joint_names: J names; parents: (J,) int64, -1 for roots.
        offsets: (J, 3) m joint translation offsets; prerotations: (J, 4) xyzw.
        inverse_bind: (J, 8) skeleton states (t m, q xyzw, s).
        scale_transform: (7J, S) columns of the parameter transform for the scale
            parameters (translation rows in m).
        scale_names: S model-parameter names; scale_limits: (S, 2) [min, max] (+-inf: none).
        skin_vertex, skin_joint, skin_weight: (N,) nonzero influences sorted by vertex.
    """

    lod: int
    base_shape: np.ndarray
    identity_dirs: np.ndarray
    faces: np.ndarray
    joint_names: tuple[str, ...]
    parents: np.ndarray
    offsets: np.ndarray
    prerotations: np.ndarray
    inverse_bind: np.ndarray
    scale_transform: np.ndarray
    scale_names: tuple[str, ...]
    scale_limits: np.ndarray
    skin_vertex: np.ndarray
    skin_joint: np.ndarray
    skin_weight: np.ndarray


def _open_npz(path: Path, keys: Sequence[str]) -> dict[str, np.ndarray]:
    """Read ``keys`` (and the optional limits) from an npz; other members (correctives) stay unread."""
    try:
        check_npz_members(path)
        data = np.load(path, allow_pickle=False)
    except (OSError, ValueError, EOFError, zipfile.BadZipFile) as exc:
        raise ValueError(f"MHR asset {path}: not a readable .npz file ({exc})") from exc
    if not isinstance(data, np.lib.npyio.NpzFile):
        raise ValueError(f"MHR asset {path}: expected an .npz archive, got a single array")
    with data:
        missing = [k for k in keys if k not in data.files]
        if missing:
            raise ValueError(
                f"MHR asset {path}: missing array(s) {', '.join(map(repr, missing))}; "
                f"expected MHR converted assets, schema version {MHR_SCHEMA_VERSION}"
            )
        arrays = {k: data[k] for k in (*keys, *_LIMIT_KEYS) if k in data.files}
    version = np.asarray(arrays["schema_version"]).reshape(-1)
    if version.size != 1 or int(version[0]) != MHR_SCHEMA_VERSION:
        raise ValueError(
            f"MHR asset {path}: schema_version {version.tolist()} is not supported; expected {MHR_SCHEMA_VERSION}"
        )
    return arrays


def _expect(path: Path, key: str, array: np.ndarray, shape: tuple[int | None, ...]) -> np.ndarray:
    """Check an array's shape (None: any size) and finiteness; name the file and key on failure."""
    ok = array.ndim == len(shape) and all(s is None or s == n for s, n in zip(shape, array.shape, strict=False))
    if not ok:
        want = "(" + ", ".join("*" if s is None else str(s) for s in shape) + ")"
        raise ValueError(f"MHR asset {path}: '{key}' expected shape {want}, got {array.shape}")
    if array.dtype.kind == "f" and not np.isfinite(array).all():
        raise ValueError(f"MHR asset {path}: '{key}' holds NaN/inf values")
    return array


def _missing_hint(folder: Path, lod: int) -> str:
    if (folder / f"lod{lod}.fbx").is_file():
        return (
            f"; {folder} holds the FBX release (lod{lod}.fbx + compact_v6_1.model), which needs pymomentum: "
            "convert it once with MHR's scripts/convert_assets.py, or fetch the converted assets with "
            f"`python -m mhr.download_assets --lod {lod}`"
        )
    return f"; expected MHR converted assets rig.npz and lod{lod}.npz (`python -m mhr.download_assets --lod {lod}`)"


def _scale_limits(rig: dict[str, np.ndarray], columns: np.ndarray) -> np.ndarray:
    """(S, 2) min/max limits of the scale columns from the rig's min-max limits (inf: none)."""
    limits = np.tile(np.array([-np.inf, np.inf]), (len(columns), 1))
    if all(k in rig for k in _LIMIT_KEYS):
        where = {int(c): i for i, c in enumerate(columns)}
        for lo, hi, p in zip(rig["limit_min"], rig["limit_max"], rig["limit_parameter_index"], strict=True):
            if int(p) in where:
                limits[where[int(p)]] = (float(lo), float(hi))
    return limits


def _mesh_arrays(path: Path, mesh: dict[str, np.ndarray], num_joints: int) -> dict[str, np.ndarray]:
    """Template, identity blendshapes (first 45 shapes), faces and nonzero skin influences, metres."""
    base = _expect(path, "base_shape", mesh["base_shape"], (None, 3))
    v = base.shape[0]
    dirs = _expect(path, "shape_vectors", mesh["shape_vectors"], (None, v, 3))
    if dirs.shape[0] < NUM_MHR_IDENTITY:
        raise ValueError(f"MHR asset {path}: 'shape_vectors' has {dirs.shape[0]} shapes, expected >= 45")
    faces = _expect(path, "faces", mesh["faces"], (None, 3)).astype(np.int64)
    if faces.size and (faces.min() < 0 or faces.max() >= v):
        raise ValueError(f"MHR asset {path}: 'faces' index out of range [0, {v})")
    idx = _expect(path, "skin_indices", mesh["skin_indices"], (v, None)).astype(np.int64)
    w = _expect(path, "skin_weights", mesh["skin_weights"], idx.shape).astype(np.float64)
    if idx.size and (idx.min() < 0 or idx.max() >= num_joints):
        raise ValueError(f"MHR asset {path}: 'skin_indices' index out of range [0, {num_joints})")
    sv, sk = np.nonzero(w)  # row-major, so sorted by vertex; zero weights are padding
    return {
        "base_shape": base.astype(np.float64) * _CM_TO_M,
        "identity_dirs": dirs[:NUM_MHR_IDENTITY].astype(np.float64) * _CM_TO_M,
        "faces": faces,
        "skin_vertex": sv,
        "skin_joint": idx[sv, sk],
        "skin_weight": w[sv, sk],
    }


def _rig_arrays(path: Path, rig: dict[str, np.ndarray]) -> dict:
    """Skeleton, inverse bind pose and the scale columns of the parameter transform, metres."""
    parents = _expect(path, "joint_parents", rig["joint_parents"], (None,)).astype(np.int64)
    _topological_order(parents, f"MHR asset {path}: 'joint_parents'")
    j = len(parents)
    pt = _expect(path, "parameter_transform", rig["parameter_transform"], (_PARAMS_PER_JOINT * j, None))
    num_model = pt.shape[1]
    columns = np.flatnonzero(_expect(path, "scaling_parameters", rig["scaling_parameters"], (num_model,)))
    names = [str(n) for n in _expect(path, "parameter_names", rig["parameter_names"], (num_model,))]
    scale_pt = pt[:, columns].astype(np.float64).reshape(j, _PARAMS_PER_JOINT, -1)
    scale_pt[:, :3] *= _CM_TO_M  # translation rows: cm per unit parameter -> m
    ibp = _expect(path, "inverse_bind_pose", rig["inverse_bind_pose"], (j, 8)).astype(np.float64)
    ibp[:, :3] *= _CM_TO_M
    return {
        "joint_names": tuple(str(n) for n in _expect(path, "joint_names", rig["joint_names"], (j,))),
        "parents": parents,
        "offsets": _expect(path, "joint_offsets", rig["joint_offsets"], (j, 3)).astype(np.float64) * _CM_TO_M,
        "prerotations": _expect(path, "joint_prerotations", rig["joint_prerotations"], (j, 4)).astype(np.float64),
        "inverse_bind": ibp,
        "scale_transform": scale_pt.reshape(_PARAMS_PER_JOINT * j, -1),
        "scale_names": tuple(names[c] for c in columns),
        "scale_limits": _scale_limits(rig, columns),
    }


def load_mhr_assets(folder: str | Path, *, lod: int = 1) -> MHRAssets:
    """Read MHR converted assets (``rig.npz`` + ``lod{lod}.npz``) and convert them to metres.

    Args:
        folder: the folder holding the two files.
        lod: level of detail, 0..6 (MHR's default is 1).

    Raises:
        FileNotFoundError: a file is missing (the message says how to get it).
        ValueError: a key is missing, a shape is inconsistent or values are not finite.
    """
    folder = Path(folder)
    if lod not in range(7):
        raise ValueError(f"lod: expected an integer in 0..6, got {lod!r}")
    rig_path, lod_path = folder / "rig.npz", folder / f"lod{lod}.npz"
    for path in (rig_path, lod_path):
        if not path.is_file():
            raise FileNotFoundError(f"MHR asset {path} is missing{_missing_hint(folder, lod)}")
    rig, mesh = _open_npz(rig_path, _RIG_KEYS), _open_npz(lod_path, _LOD_KEYS)
    if int(np.asarray(mesh["lod"]).reshape(-1)[0]) != lod:
        raise ValueError(f"MHR asset {lod_path}: holds LOD {int(mesh['lod'])}, expected {lod}")
    skeleton = _rig_arrays(rig_path, rig)
    return MHRAssets(lod=lod, **skeleton, **_mesh_arrays(lod_path, mesh, len(skeleton["parents"])))


def _topological_order(parents: np.ndarray, source: str = "joint_parents") -> list[int]:
    """Joints ordered so that every parent precedes its children (stable, by depth)."""
    j = len(parents)
    if ((parents < -1) | (parents >= j) | (parents == np.arange(j))).any():
        raise ValueError(f"{source}: expected values in [-1, {j}) and no self-parent, got {parents.tolist()}")
    depth = np.full(j, -1)
    for start in range(j):
        chain, k = [], start
        while k >= 0 and depth[k] < 0:
            if k in chain:
                raise ValueError(f"{source}: the hierarchy has a cycle through joint {k}")
            chain.append(k)
            k = int(parents[k])
        base = -1 if k < 0 else depth[k]
        for n, c in enumerate(reversed(chain), start=1):
            depth[c] = base + n
    return [int(i) for i in np.argsort(depth, kind="stable")]


def _tensor(array: np.ndarray, dtype: torch.dtype) -> torch.Tensor:
    return torch.as_tensor(np.ascontiguousarray(array), dtype=dtype)


def momentum_euler_xyz_to_matrix(angles: torch.Tensor) -> torch.Tensor:
    """Momentum's "XYZ Euler" rotation ``Rz(z) @ Ry(y) @ Rx(x)``; ``(..., 3) -> (..., 3, 3)``.

    ``Rz(z) Ry(y) Rx(x) = (Rx(-x) Ry(-y) Rz(-z))^T``, the transpose of the intrinsic X-Y-Z
    matrix of the negated angles, so the one rotations module provides it.
    """
    return euler_xyz_to_matrix(-angles).transpose(-1, -2)


class MHRIdentity(nn.Module):
    """Rest meshes of MHR identities (identity blendshapes + bone scales) on MHR's topology.

    Args:
        assets: the model data, from :func:`load_mhr_assets`.
        dtype: dtype of the buffers (float32 or float64); ``.to()`` changes it later.
    """

    name = "mhr"

    def __init__(self, assets: MHRAssets, *, dtype: torch.dtype = torch.float32) -> None:
        super().__init__()
        order = _topological_order(assets.parents)
        slot = {j: i + 1 for i, j in enumerate(order)}  # internal joint index; 0 is a virtual root
        self.tree = KinematicTree((-1,) + tuple(slot.get(int(assets.parents[j]), 0) for j in order))
        self.joint_names = assets.joint_names
        self.param_names: tuple[str, ...] = _IDENTITY_NAMES + assets.scale_names
        self.num_vertices = int(assets.base_shape.shape[0])
        self.lod = assets.lod
        self._register_shape(assets, dtype)
        self._register_skeleton(assets, order, dtype)
        joint = torch.as_tensor([slot[int(k)] - 1 for k in assets.skin_joint], dtype=torch.long)
        vertex = torch.as_tensor(assets.skin_vertex, dtype=torch.long)
        register_skin_layout(self, skin_layout(vertex, joint, self.num_vertices, len(order)))

    def _register_shape(self, assets: MHRAssets, dtype: torch.dtype) -> None:
        self.register_buffer("base_shape", _tensor(assets.base_shape, dtype))
        self.register_buffer("identity_dirs", _tensor(assets.identity_dirs.reshape(NUM_MHR_IDENTITY, -1), dtype))
        self.register_buffer("skin_weight", _tensor(assets.skin_weight, dtype))
        self.register_buffer("face_indices", torch.as_tensor(assets.faces, dtype=torch.long), persistent=False)

    def _register_skeleton(self, assets: MHRAssets, order: list[int], dtype: torch.dtype) -> None:
        """Joint data in internal (parents-first) order; inverse binds as (J, 3, 4) [sR | t]."""
        j = len(order)
        st = assets.scale_transform.reshape(j, _PARAMS_PER_JOINT, -1)[order]
        self.register_buffer("scale_transform", _tensor(st.reshape(_PARAMS_PER_JOINT * j, -1), dtype))
        self.register_buffer("scale_limits", _tensor(assets.scale_limits, dtype))
        self.register_buffer("offsets", _tensor(assets.offsets[order], dtype))
        self.register_buffer("prerotations", quat_xyzw_to_matrix(_tensor(assets.prerotations[order], dtype)))
        ibp = _tensor(assets.inverse_bind[order], dtype)
        ibp_rot = quat_xyzw_to_matrix(ibp[:, 3:7]) * ibp[:, 7:, None]
        self.register_buffer("inverse_bind", torch.cat([ibp_rot, ibp[:, :3, None]], dim=-1))

    @classmethod
    def from_files(cls, folder: str | Path, *, lod: int = 1, dtype: torch.dtype = torch.float32) -> MHRIdentity:
        """Load MHR converted assets (``rig.npz`` + ``lod{lod}.npz``) from ``folder``."""
        return cls(load_mhr_assets(folder, lod=lod), dtype=dtype)

    @property
    def num_params(self) -> int:
        """K: 45 identity coefficients followed by the S bone-scale parameters."""
        return len(self.param_names)

    @property
    def num_scales(self) -> int:
        """S: number of bone-scale parameters."""
        return self.num_params - NUM_MHR_IDENTITY

    def default_params(self, batch: int = 1) -> torch.Tensor:
        """(B, K) the template identity: every coefficient and scale 0."""
        return self.base_shape.new_zeros(batch, self.num_params)

    def param_limits(self) -> torch.Tensor:
        """(K, 2) [min, max] per parameter: the file's limits for scales, +-inf otherwise."""
        inf = self.base_shape.new_full((NUM_MHR_IDENTITY, 2), math.inf)
        inf[:, 0] = -math.inf
        return torch.cat([inf, self.scale_limits], dim=0)

    @property
    def param_bounds(self) -> tuple[torch.Tensor, torch.Tensor]:
        """``(lower, upper)``, each (K,): identity coefficients unbounded (+-inf), bone scales
        within the file's limits (:meth:`param_limits` as two vectors)."""
        limits = self.param_limits()
        return limits[:, 0], limits[:, 1]

    def faces(self) -> torch.Tensor:
        """(F, 3) triangles of the native mesh (long)."""
        return self.face_indices

    def template(self) -> torch.Tensor:
        """(V, 3) m, the rest mesh at zero parameters."""
        return self.forward(self.default_params())[0]

    def _skinning_transforms(self, scales: torch.Tensor) -> torch.Tensor:
        """(B, J, 3, 4) ``global_state * inverse_bind_pose`` of the scaled rest skeleton."""
        b, j = scales.shape[0], self.offsets.shape[0]
        jp = (scales @ self.scale_transform.T).view(b, j, _PARAMS_PER_JOINT)
        scale = torch.exp(math.log(2.0) * jp[..., 6:])[..., None]
        rot = self.prerotations @ momentum_euler_xyz_to_matrix(jp[..., 3:6]) * scale
        trans = jp[..., :3] + self.offsets
        eye = torch.eye(3, dtype=rot.dtype, device=rot.device).expand(b, 1, 3, 3)
        g_rot, g_t = forward_kinematics(
            self.tree, torch.cat([eye, rot], dim=1), torch.cat([trans.new_zeros(b, 1, 3), trans], dim=1)
        )
        g_rot, g_t = g_rot[:, 1:], g_t[:, 1:]
        skin_rot = g_rot @ self.inverse_bind[..., :3]
        skin_t = (g_rot @ self.inverse_bind[..., 3:]).squeeze(-1) + g_t
        return torch.cat([skin_rot, skin_t[..., None]], dim=-1)

    def extra_repr(self) -> str:
        return f"lod={self.lod}, vertices={self.num_vertices}, identity={NUM_MHR_IDENTITY}, scales={self.num_scales}"

    def forward(self, params: torch.Tensor) -> torch.Tensor:
        """Rest meshes.

        Args:
            params: (B, K) 45 identity coefficients then S bone-scale parameters, in the
                order of ``param_names``.

        Returns:
            (B, V, 3) rest vertices, metres, Y up, facing +Z.
        """
        check_shape(params, f"B {self.num_params}", name="identity params")
        check_like(params, self.base_shape, name="identity params", owner="the MHR backend")
        check_finite(params, "identity params")
        coeffs, scales = params[:, :NUM_MHR_IDENTITY], params[:, NUM_MHR_IDENTITY:]
        rest = self.base_shape + (coeffs @ self.identity_dirs).view(-1, self.num_vertices, 3)
        mats = self._skinning_transforms(scales)
        return lbs_sparse(rest, mats, self.skin_weight, registered_skin_layout(self))
