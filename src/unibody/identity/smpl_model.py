"""The posed SMPL-family forward (SMPL, SMPL-H, SMPL-X) from the user's model files.

The SMPL equations (Loper et al. 2015; SMPL-X: Pavlakos et al. 2019), batched, float32 or
float64, differentiable, on the module's device::

    v_shaped = v_template + shapedirs @ [betas, expression]           (B, V, 3)
    J        = J_regressor @ v_shaped                                 (B, J, 3)
    v_posed  = v_shaped + posedirs @ vec(R_1..R_{J-1} - I)            pose blendshapes
    G_j      = G_parent(j) [R_j | J_j - J_parent(j)]                  FK, one step per tree level
    v        = sum_j w_ij (G_j (v_posed - J_j)) + transl               LBS

Poses are the model's full axis-angle pose ``(B, J, 3)`` in the file's joint order: SMPL
24 (root + 23), SMPL-H 52 (root, 21 body, 15 left-hand, 15 right-hand joints), SMPL-X 55
(root, 21 body, jaw, left eye, right eye, 15 left-hand, 15 right-hand joints). Hand poses
are full rotations (no PCA); the hand means are not added (``flat_hand_mean``).

Frame: the model's own (metres, Y up, facing +Z; no conversion). The ``smplx`` package's
forward on the same file agrees to 1e-5 m in float64 (tests/test_smpl_model.py).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
from torch import nn

from .._checks import check_finite, check_like, check_shape, check_tensor
from ..geometry.kinematics import KinematicTree, forward_kinematics
from ..geometry.rotations import axis_angle_to_matrix
from .smpl import FAMILIES, GENDERS, POSE_KEYS, gender_from_path, read_model_file, shape_columns

__all__ = ["SMPLModel", "SMPLOutput"]


@dataclass(frozen=True, slots=True)
class SMPLOutput:
    """Posed SMPL-family meshes.

    Attributes:
        vertices: (B, V, 3) m, posed vertices in the model's frame, ``transl`` added (for B > 1 a
            view of vertex-major storage, as ``BodyLayer``'s; ``.contiguous()`` packs it).
        joints: (B, J, 3) m, posed joints of the model's kinematic tree, ``transl`` added.
    """

    vertices: torch.Tensor
    joints: torch.Tensor


class SMPLModel(nn.Module):
    """A posable SMPL-family model.

    Args:
        arrays: the model file's arrays as :func:`unibody.identity.smpl.read_model_file`
            returns them with ``keys=POSE_KEYS``: ``v_template (V, 3)``, ``shapedirs (V, 3, S)``,
            ``posedirs (V, 3, 9 (J - 1))``, ``weights (V, J)``, ``f (F, 3)``,
            ``J_regressor (J, V)``, ``parents (J,)``.
        num_betas: K, shape coefficients to use (the first K shape columns); all when None.
        gender: "neutral", "male", "female" or "unknown".
        dtype: floating dtype of the buffers.

    SMPL-X files append expression columns to ``shapedirs`` (:func:`shape_columns`); they
    are kept as ``num_expression`` expression coefficients. Buffers are non-persistent: the
    module is rebuilt from the user's (licensed) file, never saved in a checkpoint.

    Raises:
        ValueError: shapes or values that no SMPL-family model has.
    """

    def __init__(
        self,
        arrays: dict[str, np.ndarray],
        *,
        num_betas: int | None = None,
        gender: str = "unknown",
        dtype: torch.dtype = torch.float32,
    ) -> None:
        super().__init__()
        a = _validated(arrays)
        v, j = a["v_template"].shape[0], a["J_regressor"].shape[0]
        self.name: str = FAMILIES[(v, j)]
        self.num_vertices, self.num_joints = v, j
        num_shape = shape_columns(self.name, a["shapedirs"].shape[2])
        if num_betas is None:
            num_betas = num_shape
        if isinstance(num_betas, bool) or not isinstance(num_betas, int) or not 1 <= num_betas <= num_shape:
            raise ValueError(
                f"num_betas: expected an int in [1, {num_shape}] for this {self.name} model, got {num_betas!r}"
            )
        if gender not in GENDERS:
            raise ValueError(f"gender: expected one of {', '.join(GENDERS)}, got {gender!r}")
        if not dtype.is_floating_point:
            raise TypeError(f"dtype: expected a floating dtype, got {dtype}")
        self.gender = gender
        self.num_betas = num_betas
        expression = a["shapedirs"][:, :, num_shape:] if self.name == "smplx" else a["shapedirs"][:, :, :0]
        self.num_expression = expression.shape[2]
        self.tree = KinematicTree(tuple(int(p) for p in a["parents"]))
        dirs = np.concatenate([a["shapedirs"][:, :, :num_betas], expression], axis=2)
        buffers = {
            "v_template": a["v_template"],
            "shapedirs": dirs.reshape(3 * v, -1).T,  # (K + E, 3V)
            "posedirs": a["posedirs"].reshape(3 * v, -1).T,  # (9 (J - 1), 3V), rows joint-major
            "weights": a["weights"],
            "joint_regressor": a["J_regressor"],
        }
        for name, value in buffers.items():
            self.register_buffer(name, torch.tensor(np.asarray(value, np.float64), dtype=dtype), persistent=False)
        self.register_buffer("triangles", torch.tensor(a["f"].astype(np.int64)), persistent=False)
        self.register_buffer("parents", torch.tensor(a["parents"]), persistent=False)

    @classmethod
    def from_file(
        cls,
        path: str | Path,
        *,
        num_betas: int | None = None,
        gender: str | None = None,
        dtype: torch.dtype = torch.float32,
    ) -> SMPLModel:
        """Load an official SMPL / SMPL-H / SMPL-X model file (``.npz`` or ``.pkl``, read safely).

        Args:
            path: the model file, e.g. ``SMPLX_FEMALE.npz`` or ``smplh/male/model.npz``.
            num_betas: K, the shape coefficients to use; all shape columns when None.
            gender: overrides the gender parsed from the path (:func:`gender_from_path`).
            dtype: floating dtype of the buffers.

        Raises:
            FileNotFoundError: no such file.
            ValueError: an unknown suffix, a missing key (``posedirs`` and ``weights``
                included), or arrays no SMPL-family model has; the message starts with the file.
        """
        path = Path(path)
        arrays = read_model_file(path, POSE_KEYS)
        try:
            return cls(
                arrays,
                num_betas=num_betas,
                gender=gender_from_path(path) if gender is None else gender,
                dtype=dtype,
            )
        except (ValueError, TypeError) as e:
            raise type(e)(f"{path}: {e}") from None

    def faces(self) -> torch.Tensor:
        """(F, 3) int64 triangles of the native mesh."""
        return self.triangles

    def template(self) -> torch.Tensor:
        """(V, 3) m, the mean shape (the buffer itself: do not modify)."""
        return self.v_template

    def shaped(self, betas: torch.Tensor | None = None, expression: torch.Tensor | None = None) -> torch.Tensor:
        """Rest meshes ``v_template + shapedirs @ [betas, expression]`` (B, V, 3), m (zero pose).

        Args:
            betas: (B, K) shape coefficients; None: zeros. B may be 1.
            expression: (B, E) SMPL-X expression coefficients; None: zeros.
        """
        coeffs = self._coefficients(betas, expression)
        if coeffs is None:
            return self.v_template[None]
        offsets = coeffs @ self.shapedirs
        return self.v_template + offsets.view(coeffs.shape[0], self.num_vertices, 3)

    def forward(
        self,
        pose: torch.Tensor,
        betas: torch.Tensor | None = None,
        *,
        expression: torch.Tensor | None = None,
        transl: torch.Tensor | None = None,
    ) -> SMPLOutput:
        """Pose the model.

        Args:
            pose: (B, J, 3) axis-angle (radians), the full pose in the file's joint order
                (joint 0 is the global orientation).
            betas: (B, K) or (1, K) shape coefficients; None: the mean shape.
            expression: (B, E) or (1, E) SMPL-X expression coefficients; None: zeros.
            transl: (B, 3) m, added to every vertex and joint; None: zeros.

        Returns:
            :class:`SMPLOutput` with B posed meshes and joints.

        Raises:
            TypeError: an argument that is not a tensor of the module's dtype and device.
            ValueError: a wrong shape or NaN/inf values (the message names the argument).
        """
        check_shape(pose, f"B {self.num_joints} 3", name="pose")
        check_like(pose, self.v_template, name="pose", owner=f"the {self.name} model")
        check_finite(pose, "pose")
        b = pose.shape[0]
        if transl is not None:
            check_shape(transl, "B 3", name="transl", sizes={"B": b})
            check_like(transl, self.v_template, name="transl", owner=f"the {self.name} model")
            check_finite(transl, "transl")
        rest = self.shaped(betas, expression)
        if rest.shape[0] not in (1, b):
            raise ValueError(f"betas: expected a batch of 1 or {b} (the pose batch), got {rest.shape[0]}")
        joints = self.joint_regressor @ rest  # (1 or B, J, 3)
        rot = axis_angle_to_matrix(pose)  # (B, J, 3, 3)
        eye = torch.eye(3, dtype=rot.dtype, device=rot.device)
        v, j = self.num_vertices, self.num_joints
        feature = (rot[:, 1:] - eye).reshape(b, 9 * (j - 1))  # sized, not -1: a batch of 0 has no size to infer
        # Vertex-major (V, 3, B) throughout, each stage one product over every pose: the
        # blended transforms as (V, J) @ (J, 12 B), not B broadcast (V, J) @ (J, 12) products,
        # and applied by multiply-adds, not (3 x 3) @ (3 x 1) ones: 64 SMPL-X poses 1.4x faster
        # in float32 on two cores. The blendshapes' product is taken as P^T F^T in float32; in
        # float64 that product ran 1.7x slower than F P, whose transposed copy costs less.
        if feature.dtype == torch.float32:
            shapes = self.posedirs.t() @ feature.t()
        else:
            shapes = (feature @ self.posedirs).t().contiguous()
        posed = rest.permute(1, 2, 0) + shapes.view(v, 3, b)
        local_t = torch.cat([joints[:, :1], joints[:, 1:] - joints[:, self.parents[1:]]], dim=1)
        g_rot, g_pos = forward_kinematics(self.tree, rot, local_t.expand(b, -1, -1))
        skin_t = g_pos - (g_rot @ joints[..., None]).squeeze(-1)
        mats = torch.cat([g_rot, skin_t[..., None]], dim=-1)  # (B, J, 3, 4)
        blended = (self.weights @ mats.permute(1, 2, 3, 0).reshape(j, 12 * b)).view(v, 3, 4, b)
        out = torch.addcmul(blended[:, :, 3], blended[:, :, 0], posed[:, None, 0])
        out = out.addcmul_(blended[:, :, 1], posed[:, None, 1]).addcmul_(blended[:, :, 2], posed[:, None, 2])
        if transl is not None:
            out = out.add_(transl.t())
            g_pos = g_pos + transl[:, None]
        return SMPLOutput(out.permute(2, 0, 1), g_pos)  # (B, V, 3), a view of vertex-major storage

    def _coefficients(self, betas: torch.Tensor | None, expression: torch.Tensor | None) -> torch.Tensor | None:
        """[betas, expression] (B, K + E) with zeros for a missing part; None when both are None."""
        if betas is None and expression is None:
            return None
        parts = []
        for x, n, name in ((betas, self.num_betas, "betas"), (expression, self.num_expression, "expression")):
            if x is None:
                continue
            check_tensor(x, name)
            check_shape(x, f"B {n}", name=name)
            check_like(x, self.v_template, name=name, owner=f"the {self.name} model")
            check_finite(x, name)
            parts.append((x, name))
        batches = {x.shape[0] for x, _ in parts}
        if len(batches) > 1 and 1 not in batches:
            raise ValueError(f"betas / expression: batches {sorted(batches)} differ; expected equal batches or 1")
        b = max(batches)
        full = []
        for x, n in ((betas, self.num_betas), (expression, self.num_expression)):
            full.append(self.v_template.new_zeros(b, n) if x is None else x.expand(b, -1))
        return torch.cat(full, dim=1)

    def extra_repr(self) -> str:
        return (
            f"name={self.name}, gender={self.gender}, vertices={self.num_vertices}, joints={self.num_joints}, "
            f"betas={self.num_betas}, expression={self.num_expression}"
        )


def _validated(arrays: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
    """Check the arrays against each other (shapes, finite values, ids); one-line ValueErrors."""
    keys = ("v_template", "shapedirs", "posedirs", "weights", "f", "J_regressor", "parents")
    missing = [k for k in keys if k not in arrays]
    if missing:
        raise ValueError(f"arrays: missing {', '.join(missing)}; expected {', '.join(keys)}")
    a = {k: np.asarray(arrays[k]) for k in keys}
    v = a["v_template"].shape[0] if a["v_template"].ndim == 2 else -1
    j = a["J_regressor"].shape[0] if a["J_regressor"].ndim == 2 else -1
    expected = {
        "v_template": (v, 3),
        "J_regressor": (j, v),
        "weights": (v, j),
        "posedirs": (v, 3, 9 * (j - 1)),
        "parents": (j,),
    }
    for key, shape in expected.items():
        if a[key].shape != shape or v < 1 or j < 1:
            want = "(V, 3, 9 (J - 1))" if key == "posedirs" else str(shape).replace("-1", "?")
            raise ValueError(f"{key}: expected shape {want}, got {a[key].shape}")
    if a["shapedirs"].ndim != 3 or a["shapedirs"].shape[:2] != (v, 3) or a["shapedirs"].shape[2] == 0:
        raise ValueError(f"shapedirs: expected shape ({v}, 3, S) with S >= 1, got {a['shapedirs'].shape}")
    if (v, j) not in FAMILIES:
        known = ", ".join(f"{n} {nv} v / {nj} joints" for (nv, nj), n in FAMILIES.items())
        raise ValueError(f"v_template / J_regressor: {v} vertices and {j} joints match no SMPL-family model ({known})")
    for key in ("v_template", "shapedirs", "posedirs", "weights", "J_regressor"):
        if a[key].dtype.kind not in "biuf" or not np.isfinite(a[key]).all():
            raise ValueError(f"{key}: expected finite real values, got dtype {a[key].dtype} with NaN/inf or no numbers")
    f = a["f"]
    if f.ndim != 2 or f.shape[1] != 3 or f.dtype.kind not in "iu" or (f.size and (f.min() < 0 or f.max() >= v)):
        raise ValueError(f"f: expected integer triangles (F, 3) with ids in [0, {v}), got {f.dtype} {f.shape}")
    p = a["parents"].astype(np.int64)
    if p[0] != -1 or (p[1:] < 0).any() or (p[1:] >= np.arange(1, j)).any():
        raise ValueError(f"parents: expected -1 for the root and each parent before its child, got {p.tolist()[:8]}...")
    return {**a, "parents": p}
