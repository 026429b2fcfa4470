"""Write seeded MHR assets in MHR's converted format (schema version 1), for tests.

The files hold exactly the members MHR's ``scripts/convert_assets.py`` writes (and its
``mhr/_torch_rig.py`` requires): ``rig.npz`` with the parameter transform, parameter sets,
skeleton, inverse bind pose, min-max limits and the pose-corrective activation members;
``lod{N}.npz`` with the blendshapes (45 identity + E expression), mesh, UVs, skinning and the
corrective blendshapes. Values are synthetic (a small random skeleton and a point cloud
around it, centimetres, Y up); nothing licensed is read or reproduced.

``python tests/mhr_format.py OUT_DIR [--full]`` writes a set (``--full``: MHR LOD1 sizes,
127 joints, 18,439 vertices, 204 rig parameters of which 68 scales).
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

SCHEMA_VERSION = 1
NUM_IDENTITY = 45
PARAMS_PER_JOINT = 7


def _quat_xyzw(rng: np.random.Generator, n: int, spread: float) -> np.ndarray:
    """Random unit quaternions within ``spread`` radians of the identity, xyzw, w >= 0."""
    axis = rng.normal(size=(n, 3))
    axis /= np.linalg.norm(axis, axis=1, keepdims=True)
    half = 0.5 * rng.uniform(0.0, spread, size=(n, 1))
    return np.concatenate([np.sin(half) * axis, np.cos(half)], axis=1)


def _qmul(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    av, aw, bv, bw = a[..., :3], a[..., 3:], b[..., :3], b[..., 3:]
    return np.concatenate([aw * bv + bw * av + np.cross(av, bv), aw * bw - (av * bv).sum(-1, keepdims=True)], -1)


def _qrot(q: np.ndarray, v: np.ndarray) -> np.ndarray:
    """Rotate v by unit q: the vector part of q (v, 0) q*."""
    qc = q * np.array([-1.0, -1.0, -1.0, 1.0])
    return _qmul(_qmul(q, np.concatenate([v, np.zeros_like(v[..., :1])], -1)), qc)[..., :3]


def _bind_states(parents: np.ndarray, offsets: np.ndarray, prerot: np.ndarray) -> np.ndarray:
    """(J, 8) world skeleton states (t, q, s) of the zero-parameter skeleton (parents first)."""
    states = np.zeros((len(parents), 8))
    for j, p in enumerate(parents):
        if p < 0:
            states[j] = np.concatenate([offsets[j], prerot[j], [1.0]])
        else:
            tp, qp, sp = states[p, :3], states[p, 3:7], states[p, 7]
            states[j] = np.concatenate([tp + sp * _qrot(qp, offsets[j]), _qmul(qp, prerot[j]), [sp]])
    return states


def _invert_states(states: np.ndarray) -> np.ndarray:
    """Inverse skeleton states: s' = 1/s, q' = q*, t' = -(1/s) q* t."""
    qc = states[:, 3:7] * np.array([-1.0, -1.0, -1.0, 1.0])
    s_inv = 1.0 / states[:, 7:]
    return np.concatenate([-s_inv * _qrot(qc, states[:, :3]), qc, s_inv], axis=1)


def _skeleton(rng: np.random.Generator, num_joints: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Parents (root 0, each parent before its child), offsets (cm) and prerotations."""
    parents = np.array([-1] + [int(rng.integers(0, max(1, j - 1) + 1)) if j > 1 else 0 for j in range(1, num_joints)])
    offsets = rng.normal(scale=12.0, size=(num_joints, 3))
    offsets[0] = (0.0, 0.0, 0.0)
    if num_joints > 1:
        offsets[1] = (0.0, 95.0, 0.0)  # pelvis height: the body stands on y = 0, Y up
    return parents, offsets, _quat_xyzw(rng, num_joints, 1.2)


def _parameter_transform(
    rng: np.random.Generator, num_joints: int, num_pose: int, num_scales: int, num_shapes: int
) -> dict:
    """Rigid (6), pose (Euler angles of joints 1, 2, ...), scales, then the blend-shape columns (zero rows)."""
    j = num_joints
    num_rig = 6 + num_pose + num_scales
    num_model = num_rig + num_shapes
    pt = np.zeros((PARAMS_PER_JOINT * j, num_model), dtype=np.float32)
    for c in range(6):
        pt[c, c] = 1.0  # root tx ty tz rx ry rz
    for k in range(num_pose):
        pt[PARAMS_PER_JOINT * (1 + (k // 3) % (j - 1)) + 3 + k % 3, 6 + k] = 1.0
    scale_cols = np.arange(6 + num_pose, num_rig)
    for i, c in enumerate(scale_cols):
        if i == 0:
            pt[PARAMS_PER_JOINT * 0 + 6, c] = 1.0  # a global scale on the root
            continue
        joints = rng.choice(np.arange(1, j), size=min(2, j - 1), replace=False)
        pt[PARAMS_PER_JOINT * joints + 6, c] = rng.uniform(0.5, 1.0, size=len(joints))
        if i % 3 == 2:  # some scale parameters also lengthen a bone (a translation row, cm per unit)
            pt[PARAMS_PER_JOINT * int(joints[0]) + int(rng.integers(0, 3)), c] = rng.uniform(-4.0, 4.0)
    names = (
        ["root_tx", "root_ty", "root_tz", "root_rx", "root_ry", "root_rz"]
        + [f"joint{1 + (k // 3) % (j - 1)}_r{'xyz'[k % 3]}" for k in range(num_pose)]
        + [f"scale_{i}" for i in range(num_scales)]
        + [f"blend_{i}" for i in range(num_shapes)]
    )
    flags = np.zeros((3, num_model), dtype=bool)
    flags[0, : 6 + num_pose] = True  # pose (rigid included, as in MHR)
    flags[1, :6] = True  # rigid
    flags[2, scale_cols] = True  # scaling
    return {"pt": pt, "names": np.asarray(names), "flags": flags, "scale_cols": scale_cols}


def _mesh(rng: np.random.Generator, joints: np.ndarray, num_vertices: int, influences: int) -> dict:
    """Vertices near random joints (cm), 2-3 nonzero skin weights each, zero-padded slots."""
    j = len(joints)
    home = rng.integers(1 if j > 1 else 0, j, size=num_vertices)
    base = joints[home] + rng.normal(scale=6.0, size=(num_vertices, 3))
    idx = np.zeros((num_vertices, influences), dtype=np.int32)
    w = np.zeros((num_vertices, influences), dtype=np.float32)
    for v in range(num_vertices):
        n = int(rng.integers(1, min(3, j) + 1))
        near = np.argsort(np.linalg.norm(joints - base[v], axis=1))[:n]
        idx[v, :n] = near
        raw = rng.uniform(0.2, 1.0, size=n)
        w[v, :n] = raw / raw.sum()
    faces = np.stack([rng.choice(num_vertices, size=3, replace=False) for _ in range(2 * num_vertices)])
    return {"base": base, "idx": idx, "w": w, "faces": faces.astype(np.int32)}


def make_mhr_arrays(
    *,
    num_joints: int = 8,
    num_vertices: int = 40,
    num_pose: int | None = None,
    num_scales: int = 6,
    num_expression: int = 72,
    influences: int = 8,
    lod: int = 1,
    seed: int = 0,
) -> tuple[dict[str, np.ndarray], dict[str, np.ndarray]]:
    """The members of ``rig.npz`` and ``lod{lod}.npz`` (MHR converted schema version 1)."""
    rng = np.random.default_rng(seed)
    parents, offsets, prerot = _skeleton(rng, num_joints)
    bind = _bind_states(parents, offsets, prerot)
    num_shapes = NUM_IDENTITY + num_expression
    num_pose = 3 * (num_joints - 1) if num_pose is None else num_pose
    pt = _parameter_transform(rng, num_joints, num_pose, num_scales, num_shapes)
    mesh = _mesh(rng, bind[:, :3], num_vertices, influences)
    scale_cols = pt["scale_cols"]
    levels = np.zeros(num_joints, dtype=np.int64)
    for j in range(1, num_joints):
        levels[j] = levels[parents[j]] + 1
    pairs = [np.stack([np.flatnonzero(levels == d), parents[levels == d]]) for d in range(1, levels.max() + 1)]
    mask = np.zeros((4 * num_joints, 2 * num_joints), dtype=bool)  # (3000, 750) in MHR
    mask[np.arange(mask.shape[0]), np.arange(mask.shape[0]) % mask.shape[1]] = True
    rig = {
        "schema_version": np.array(SCHEMA_VERSION, dtype=np.int64),
        "source_momentum_version": np.array("synthetic"),
        "parameter_transform": pt["pt"],
        "pose_parameters": pt["flags"][0],
        "rigid_parameters": pt["flags"][1],
        "scaling_parameters": pt["flags"][2],
        "active_joints": np.ones(num_joints, dtype=bool),
        "parameter_names": pt["names"],
        "joint_offsets": offsets.astype(np.float32),
        "joint_prerotations": prerot.astype(np.float32),
        "joint_parents": parents.astype(np.int32),
        "joint_names": np.asarray(["root"] + [f"joint{j}" for j in range(1, num_joints)]),
        "fk_indices": np.concatenate(pairs, axis=1).astype(np.int64) if pairs else np.zeros((2, 0), np.int64),
        "fk_sizes": np.asarray([p.shape[1] for p in pairs], dtype=np.int64),
        "inverse_bind_pose": _invert_states(bind).astype(np.float32),
        "limit_min": np.full(len(scale_cols), -1.0, dtype=np.float32),
        "limit_max": np.full(len(scale_cols), 1.5, dtype=np.float32),
        "limit_weight": np.ones(len(scale_cols), dtype=np.float32),
        "limit_parameter_index": scale_cols.astype(np.int32),
        "0.sparse_indices": np.stack(np.nonzero(mask)).astype(np.int64),
        "0.sparse_weight": rng.normal(size=int(mask.sum())).astype(np.float32),
        "posedirs_sparse_mask": mask,
    }
    shape_vectors = rng.normal(scale=1.5, size=(num_shapes, num_vertices, 3)).astype(np.float32)
    lod_arrays = {
        "schema_version": np.array(SCHEMA_VERSION, dtype=np.int64),
        "lod": np.array(lod, dtype=np.int64),
        "base_shape": mesh["base"].astype(np.float32),
        "shape_vectors": shape_vectors,
        "faces": mesh["faces"],
        "texcoords": rng.uniform(size=(num_vertices, 2)).astype(np.float32),
        "texcoord_faces": mesh["faces"].copy(),
        "skin_indices": mesh["idx"],
        "skin_weights": mesh["w"],
        "corrective_blendshapes": rng.normal(scale=0.1, size=(4, num_vertices, 3)).astype(np.float32),
    }
    return rig, lod_arrays


def write_mhr_assets(
    folder: str | Path,
    rig: dict[str, np.ndarray] | None = None,
    lod_arrays: dict[str, np.ndarray] | None = None,
    *,
    file_lod: int | None = None,
    **sizes: int,
) -> tuple[dict[str, np.ndarray], dict[str, np.ndarray]]:
    """Write ``rig.npz`` and ``lod{N}.npz`` (compressed npz, as MHR's converter) into ``folder``.

    ``N`` is the ``lod`` member unless ``file_lod`` names another file (to test mismatches).
    """
    if rig is None or lod_arrays is None:
        rig, lod_arrays = make_mhr_arrays(**sizes)
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    np.savez_compressed(folder / "rig.npz", **rig)
    n = int(lod_arrays["lod"]) if file_lod is None else file_lod
    np.savez_compressed(folder / f"lod{n}.npz", **lod_arrays)
    return rig, lod_arrays


FULL_SIZES = {"num_joints": 127, "num_vertices": 18439, "num_pose": 130, "num_scales": 68}

if __name__ == "__main__":
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("out", type=Path)
    parser.add_argument("--full", action="store_true", help="MHR LOD1 sizes")
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args()
    write_mhr_assets(args.out, seed=args.seed, **(FULL_SIZES if args.full else {}))
    print(f"wrote {args.out / 'rig.npz'} and {args.out / 'lod1.npz'}")
