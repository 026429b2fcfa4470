"""SMPL-family identity backend: shape coefficients (betas) -> rest mesh, from official model files.

SMPL (6,890 vertices, 24 joints), SMPL-H (6,890 v, 52 j) and SMPL-X (10,475 v, 55 j) share
one linear shape model, ``v = v_template + shapedirs @ betas`` (paper 000 §3.2). The family
is recognised from the vertex and joint counts. SMPL-X files append expression columns to
``shapedirs``: 300 shape + 100 expression when there are at least 400 columns, otherwise
10 + 10 (the v1.0 files), as the ``smplx`` package reads them. Only shape columns are used
here; expressions are not identity.

Frame: the SMPL family is already in metres, with Y up, facing +Z (the body's left on +X).
That is unibody's frame, so no conversion is applied. The native origin is kept: it sits
near the pelvis, not at the feet.

Licensed files come from the user; nothing is shipped. ``.npz`` files are read with
``allow_pickle=False``. Only the keys needed are read, so object-array extras such as
SMPL-X ``part2num`` are never touched. A needed key that is nevertheless stored as a
pickled object array (e.g. a sparse ``J_regressor`` saved with ``np.savez``) goes
through :mod:`unibody.io.safe_pickle`, and so does every ``.pkl`` file (chumpy and scipy
objects included).
"""

from __future__ import annotations

import re
import zipfile
from pathlib import Path

import numpy as np
import torch
from torch import nn
from torch.nn import functional as F

from .._checks import check_finite, check_like, check_shape
from ..io import safe_pickle
from ..io.npz import check_npz_members

__all__ = [
    "FAMILIES",
    "GENDERS",
    "MODEL_KEYS",
    "POSE_KEYS",
    "SMPLIdentity",
    "gender_from_path",
    "read_model_file",
    "shape_columns",
]

FAMILIES: dict[tuple[int, int], str] = {(6890, 24): "smpl", (6890, 52): "smplh", (10475, 55): "smplx"}
"""(vertices, joints) -> family name."""

GENDERS: tuple[str, ...] = ("neutral", "male", "female", "unknown")

MODEL_KEYS: tuple[str, ...] = ("v_template", "shapedirs", "f", "J_regressor", "kintree_table")
"""The keys read from a model file (official names); every other key is ignored."""

POSE_KEYS: tuple[str, ...] = ("weights", "posedirs")
"""The further keys a posable model reads (:class:`unibody.identity.smpl_model.SMPLModel`)."""

_SMPLX_SHAPE, _SMPLX_EXPRESSION = 300, 100
_GENDER_TOKENS = {"neutral": "neutral", "male": "male", "female": "female"}
_SMPL10_TOKENS = {"m": "male", "f": "female"}  # SMPL 1.0 names: basicModel_f_lbs_10_207_0_v1.0.0.pkl


def shape_columns(family: str, num_columns: int) -> int:
    """How many of the ``num_columns`` shapedirs columns are identity (shape) columns.

    All of them for SMPL and SMPL-H. SMPL-X files append expressions: 300 shape columns
    when there are at least 400 columns, else 10 (the 10 + 10 v1.0 files).
    """
    if family != "smplx":
        return num_columns
    return _SMPLX_SHAPE if num_columns >= _SMPLX_SHAPE + _SMPLX_EXPRESSION else min(10, num_columns)


def gender_from_path(path: str | Path) -> str:
    """Parse the gender from a model file name, e.g. ``SMPLX_FEMALE.npz`` -> "female".

    The file stem is tried first, then the parent folder (AMASS layout ``male/model.npz``).
    SMPL 1.0 names (``basicModel_f_lbs_...``) use ``f`` / ``m``. Returns "neutral", "male",
    "female", or "unknown" when no single gender is named.
    """
    path = Path(path)
    for part, short in ((path.stem, path.stem.lower().startswith("basicmodel")), (path.parent.name, False)):
        tokens = re.split(r"[^a-z]+", part.lower())
        aliases = {**_GENDER_TOKENS, **(_SMPL10_TOKENS if short else {})}
        found = {aliases[t] for t in tokens if t in aliases}
        if len(found) == 1:
            return found.pop()
    return "unknown"


class SMPLIdentity(nn.Module):
    """Rest meshes of the SMPL family (SMPL, SMPL-H, SMPL-X) on their native topology.

    Args:
        v_template: (V, 3) m, the mean shape.
        shapedirs: (V, 3, S) m per unit coefficient; for SMPL-X the expression columns
            after the shape columns are dropped (see :func:`shape_columns`).
        faces: (F, 3) vertex ids (file key ``f``).
        joint_regressor: (J, V) rest-joint regressor (file key ``J_regressor``).
        parents: (J,) parent of each joint, -1 for the root (``kintree_table[0]``).
        num_betas: K, the shape coefficients to use (the first K); all shape columns when None.
        gender: "neutral", "male", "female" or "unknown" (one file per gender).
        dtype: floating dtype of the buffers (float32 by default; ``.to()`` works afterwards).

    Raises:
        ValueError: shapes, counts or values that no SMPL-family model has.
        TypeError: an argument that is not an array, or non-integer ids.
    """

    def __init__(
        self,
        v_template: np.ndarray | torch.Tensor,
        shapedirs: np.ndarray | torch.Tensor,
        faces: np.ndarray | torch.Tensor,
        joint_regressor: np.ndarray | torch.Tensor,
        parents: np.ndarray | torch.Tensor,
        *,
        num_betas: int | None = None,
        gender: str = "unknown",
        dtype: torch.dtype = torch.float32,
    ) -> None:
        super().__init__()
        arrays = _validated(v_template, shapedirs, faces, joint_regressor, parents)
        self.num_vertices, self.num_joints = arrays["v_template"].shape[0], arrays["joint_regressor"].shape[0]
        self.name: str = FAMILIES[(self.num_vertices, self.num_joints)]
        self.topology = "smplx" if self.name == "smplx" else "smpl"  # SMPL-H shares SMPL's mesh
        self.num_shape_columns = shape_columns(self.name, arrays["shapedirs"].shape[2])
        k = _num_betas(num_betas, self.num_shape_columns, self.name)
        if gender not in GENDERS:
            raise ValueError(f"gender: expected one of {', '.join(GENDERS)}, got {gender!r}")
        if not dtype.is_floating_point:
            raise TypeError(f"dtype: expected a floating dtype, got {dtype}")
        self.gender = gender
        self.param_names: tuple[str, ...] = tuple(f"beta{i}" for i in range(k))
        self.parents: tuple[int, ...] = tuple(int(p) for p in arrays["parents"])
        # Copies (never views of the caller's arrays). Non-persistent: the module is rebuilt from
        # the user's files, and licensed data must not leak into checkpoints through state_dict().
        for name, value in (
            ("v_template", arrays["v_template"]),
            ("shapedirs", arrays["shapedirs"][:, :, :k]),
            ("joint_regressor", arrays["joint_regressor"]),
        ):
            self.register_buffer(name, torch.tensor(np.asarray(value, dtype=np.float64), dtype=dtype), persistent=False)
        faces = torch.tensor(arrays["faces"].astype(np.int64))
        self.register_buffer("triangles", faces, persistent=False)

    @classmethod
    def from_file(
        cls,
        path: str | Path,
        *,
        num_betas: int | None = None,
        gender: str | None = None,
        dtype: torch.dtype = torch.float32,
    ) -> SMPLIdentity:
        """Load an official SMPL / SMPL-H / SMPL-X model file (``.npz`` or ``.pkl``).

        Args:
            path: the model file, e.g. ``SMPL_NEUTRAL.pkl`` or ``SMPLX_FEMALE.npz``.
            num_betas: K, the shape coefficients to use; all shape columns when None.
            gender: overrides the gender parsed from the file name (:func:`gender_from_path`).
            dtype: floating dtype of the buffers.

        Raises:
            FileNotFoundError: no such file.
            ValueError: an unknown suffix, a missing key, or arrays no SMPL-family model
                has (messages start with the file name).
            pickle.UnpicklingError: a ``.pkl`` that :mod:`unibody.io.safe_pickle` refuses.
        """
        path = Path(path)
        arrays = read_model_file(path)
        parents = arrays["parents"]
        try:
            return cls(
                arrays["v_template"],
                arrays["shapedirs"],
                arrays["f"],
                arrays["J_regressor"],
                parents,
                num_betas=num_betas,
                gender=gender_from_path(path) if gender is None else gender,
                dtype=dtype,
            )
        except (ValueError, TypeError) as e:
            raise type(e)(f"{path}: {e}") from None

    @property
    def num_params(self) -> int:
        """K: the number of shape coefficients (betas) taken by :meth:`forward`."""
        return len(self.param_names)

    @property
    def param_bounds(self) -> None:
        """None: betas are unbounded (any finite value is a shape of the linear model)."""
        return None

    def default_params(self, batch: int = 1) -> torch.Tensor:
        """(B, K) zeros: the mean shape ``v_template``."""
        if isinstance(batch, bool) or not isinstance(batch, int) or batch < 1:
            raise ValueError(f"batch: expected a positive int, got {batch!r}")
        return self.v_template.new_zeros(batch, self.num_params)

    def faces(self) -> torch.Tensor:
        """(F, 3) int64 triangles of the native mesh."""
        return self.triangles

    def template(self) -> torch.Tensor:
        """(V, 3) m, the mean shape in unibody axes (the buffer itself: do not modify)."""
        return self.v_template

    def forward(self, betas: torch.Tensor) -> torch.Tensor:
        """Rest meshes.

        Args:
            betas: (B, K) shape coefficients in the order of ``param_names``, same dtype
                and device as the module.

        Returns:
            (B, V, 3) rest vertices, metres, Y up, facing +Z.
        """
        check_shape(betas, f"B {self.num_params}", name="betas")
        check_like(betas, self.v_template, name="betas", owner="the SMPL backend")
        check_finite(betas, "betas")
        offsets = F.linear(betas, self.shapedirs.view(-1, self.num_params))  # (B, 3V)
        return self.v_template + offsets.view(betas.shape[0], self.num_vertices, 3)

    def rest_joints(self, vertices: torch.Tensor) -> torch.Tensor:
        """(B, J, 3) m, the model's own joints regressed from rest meshes (B, V, 3)."""
        check_shape(vertices, f"B {self.num_vertices} 3", name="vertices")
        check_like(vertices, self.v_template, name="vertices", owner="the SMPL backend")
        return self.joint_regressor @ vertices

    def extra_repr(self) -> str:
        return (
            f"name={self.name}, gender={self.gender}, vertices={self.num_vertices}, "
            f"joints={self.num_joints}, betas={self.num_params}/{self.num_shape_columns}"
        )


def _as_numpy(x: object, name: str) -> np.ndarray:
    if isinstance(x, torch.Tensor):
        return x.detach().cpu().numpy()
    if isinstance(x, np.ndarray):
        return x
    raise TypeError(f"{name}: expected a numpy array or torch.Tensor, got {type(x).__name__}")


def _check(x: np.ndarray, name: str, ndim: int, tail: tuple[int | None, ...], kind: str) -> None:
    """Check rank, trailing sizes (None = any), dtype kind ("f": real numbers, "i": integers)."""
    dims = ["?"] * (ndim - len(tail)) + ["?" if t is None else str(t) for t in tail]
    want = f"({dims[0]},)" if ndim == 1 else "(" + ", ".join(dims) + ")"
    if x.ndim != ndim or any(t is not None and s != t for s, t in zip(x.shape[ndim - len(tail) :], tail, strict=True)):
        raise ValueError(f"{name}: expected shape {want}, got {x.shape}")
    kinds = "iu" if kind == "i" else "biuf"
    if x.dtype.kind not in kinds:
        raise TypeError(f"{name}: expected {'integer' if kind == 'i' else 'real'} values, got dtype {x.dtype}")
    if kind == "f" and not np.isfinite(x).all():
        raise ValueError(f"{name}: expected finite values, got {int((~np.isfinite(x)).sum())} NaN/inf entries")


def _validated(*args: object) -> dict[str, np.ndarray]:
    """Validate the constructor arrays against each other; return them as numpy arrays."""
    names = ("v_template", "shapedirs", "faces", "joint_regressor", "parents")
    a = {n: _as_numpy(x, n) for n, x in zip(names, args, strict=True)}
    _check(a["v_template"], "v_template", 2, (3,), "f")
    v = a["v_template"].shape[0]
    _check(a["shapedirs"], "shapedirs", 3, (v, 3, None), "f")
    if a["shapedirs"].shape[2] == 0:
        raise ValueError("shapedirs: expected at least one shape column, got shape " + str(a["shapedirs"].shape))
    _check(a["faces"], "faces (key 'f')", 2, (3,), "i")
    if a["faces"].size and (a["faces"].min() < 0 or a["faces"].max() >= v):
        raise ValueError(
            f"faces (key 'f'): expected vertex ids in [0, {v}), got [{a['faces'].min()}, {a['faces'].max()}]"
        )
    _check(a["joint_regressor"], "joint_regressor (key 'J_regressor')", 2, (None, v), "f")
    j = a["joint_regressor"].shape[0]
    _check(a["parents"], "parents", 1, (j,), "i")
    p = a["parents"].astype(np.int64)
    if j and (p[0] != -1 or (p[1:] < 0).any() or (p[1:] >= j).any()):
        raise ValueError(
            f"parents: expected -1 for the root and joint ids in [0, {j}) after it, got {p.tolist()[:8]}..."
        )
    if (v, j) not in FAMILIES:
        known = ", ".join(f"{n} {nv} v / {nj} joints" for (nv, nj), n in FAMILIES.items())
        raise ValueError(
            f"v_template / joint_regressor: {v} vertices and {j} joints match no SMPL-family model ({known})"
        )
    return a


def _num_betas(num_betas: int | None, available: int, family: str) -> int:
    if num_betas is None:
        return available
    if isinstance(num_betas, bool) or not isinstance(num_betas, int) or not 1 <= num_betas <= available:
        raise ValueError(f"num_betas: expected an int in [1, {available}] for this {family} model, got {num_betas!r}")
    return num_betas


def read_model_file(path: str | Path, keys: tuple[str, ...] = ()) -> dict[str, np.ndarray]:
    """Read the arrays of an official SMPL-family model file (``.npz`` or ``.pkl``), safely.

    Args:
        path: the model file.
        keys: further official keys to read (e.g. :data:`POSE_KEYS`), all required.

    Returns:
        The :data:`MODEL_KEYS` and ``keys`` as numeric numpy arrays (chumpy and sparse values
        made dense), plus ``parents (J,)`` int64 from ``kintree_table[0]`` with -1 for the root.

    Raises:
        FileNotFoundError: no such file.
        ValueError: an unknown suffix, a missing key or a non-numeric value (the message
            starts with the file name).
        pickle.UnpicklingError: a ``.pkl`` that :mod:`unibody.io.safe_pickle` refuses.
    """
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"path: no SMPL-family model file at {path}")
    suffix = path.suffix.lower()
    if suffix not in (".npz", ".pkl"):
        raise ValueError(f"path: expected a .npz or .pkl SMPL-family model file, got {path.name!r}")
    wanted = MODEL_KEYS + tuple(k for k in keys if k not in MODEL_KEYS)
    arrays = _read_npz(path, wanted) if suffix == ".npz" else _read_pkl(path, wanted)
    kintree = arrays["kintree_table"]
    if kintree.ndim != 2 or kintree.shape[0] != 2 or kintree.dtype.kind not in "iu":
        raise ValueError(f"{path}: kintree_table: expected integer shape (2, J), got {kintree.dtype} {kintree.shape}")
    parents = kintree[0].astype(np.int64)
    parents[0] = -1  # the root's parent is stored as 4294967295 (uint32 -1)
    return {**arrays, "parents": parents}


def _missing(path: Path, key: str, keys: tuple[str, ...] = MODEL_KEYS) -> ValueError:
    return ValueError(f"{path}: missing key {key!r}; an SMPL-family model file holds {', '.join(keys)}")


def _numeric(value: object, path: Path, key: str) -> np.ndarray:
    if isinstance(value, np.ndarray) and value.dtype.hasobject and value.ndim == 0:
        value = value.item()  # a 0-d object array: np.savez of a non-array value
    arr = np.asarray(value)
    if arr.dtype.kind not in "biuf":
        raise ValueError(f"{path}: {key}: expected a numeric array, got {type(value).__name__} of dtype {arr.dtype}")
    return arr


def _read_pkl(path: Path, keys: tuple[str, ...] = MODEL_KEYS) -> dict[str, np.ndarray]:
    data = safe_pickle.load(path)
    if not isinstance(data, dict):
        raise ValueError(f"{path}: expected a pickled dict of model arrays, got {type(data).__name__}")
    for key in keys:
        if key not in data:
            raise _missing(path, key, keys)
    return {key: _numeric(data[key], path, key) for key in keys}


def _read_npz(path: Path, keys: tuple[str, ...] = MODEL_KEYS) -> dict[str, np.ndarray]:
    try:
        check_npz_members(path)
        npz = np.load(path, allow_pickle=False)
    except (OSError, ValueError, EOFError, zipfile.BadZipFile) as e:
        raise ValueError(f"{path}: not a readable .npz archive ({e})") from None
    if not isinstance(npz, np.lib.npyio.NpzFile):
        raise ValueError(f"{path}: not an .npz archive (it holds a single array)")
    with npz:
        for key in keys:
            if key not in npz.files:
                raise _missing(path, key, keys)
        return {key: _numeric(_npz_member(npz, path, key), path, key) for key in keys}


def _npz_member(npz: np.lib.npyio.NpzFile, path: Path, key: str) -> object:
    try:
        return npz[key]
    except ValueError as e:  # "Object arrays cannot be loaded when allow_pickle=False"
        if "allow_pickle" not in str(e):
            raise ValueError(f"{path}: {key}: unreadable array ({e})") from None
        return _object_member(path, key)
    except (OSError, EOFError, zipfile.BadZipFile) as e:
        raise ValueError(f"{path}: {key}: unreadable array ({e})") from None


def _object_member(path: Path, key: str) -> object:
    """Read a pickled object-array member of an npz through the restricted unpickler."""
    with zipfile.ZipFile(path) as zf, zf.open(f"{key}.npy") as fp:
        version = np.lib.format.read_magic(fp)
        if version == (1, 0):
            np.lib.format.read_array_header_1_0(fp)
        elif version == (2, 0):
            np.lib.format.read_array_header_2_0(fp)
        else:
            raise ValueError(f"{path}: {key}: unsupported .npy format version {version}")
        return safe_pickle.load(fp)  # numpy pickles the whole object array after the header
