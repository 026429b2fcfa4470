"""Write SMPL-family model files in the official formats, for tests (seeded; no licensed data).

Templates are the real SMPL-topology meshes of the evaluation data when present:
``mesh/human_man.obj`` (6,890 v, SMPL and SMPL-H topology) and ``mesh/human_neutral.obj``
(10,475 v, SMPL-X topology), CC BY 4.0. They are looked up under ``$UNIBODY_EVALDATA``,
else ``/work/shared/evaldata``. Without them a synthetic tube with the same vertex count
stands in. Family detection only needs the counts. Shape directions, regressors and weights
are random: these files test formats and bookkeeping, not anatomy.

Formats (key names and shapes as the ``smplx`` package reads them):

- ``.npz``: plain arrays ``v_template (V, 3)``, ``shapedirs (V, 3, S)``, ``J_regressor (J, V)``,
  ``weights (V, J)``, ``kintree_table (2, J)`` (root parent stored as 4294967295), ``f (F, 3)``
  uint32, optionally ``posedirs (V, 3, 9 (J - 1))``.
- ``.pkl``: the same dict pickled the Python-2 way (SMPL's own ``save_model`` calls
  ``pickle.dump(d, f, -1)``: protocol 2 in Python 2). ``J_regressor`` is a
  ``scipy.sparse.csc_matrix``. The SMPL 1.0 ("chumpy") variant also wraps ``v_template``,
  ``shapedirs``, ``posedirs`` and ``weights`` in ``chumpy.ch.Ch``. The MANO / SMPL-H
  variant stores ``shapedirs`` as a ``chumpy.reordering.Select`` over a wider ``Ch``.

chumpy and scipy are never imported. Throw-away classes carry their module and qualified
names, and a pickler subclass writes those names as globals, exactly as the real files
record them. ``legacy=True`` also uses the Python-2 era numpy/scipy module names
(``numpy.core.multiarray``, ``scipy.sparse.csc``) and stores raw array bytes as latin-1
text, as Python 2 ``str`` data reads back.
"""

from __future__ import annotations

import io
import os
import pickle
import zipfile
from pathlib import Path

import numpy as np
from scipy.spatial import cKDTree

from unibody.io.obj import read_obj

SIZES: dict[str, tuple[int, int, int]] = {"smpl": (6890, 24, 10), "smplh": (6890, 52, 16), "smplx": (10475, 55, 20)}
"""family -> (vertices, joints, default shapedirs columns; SMPL-X v1.0 layout: 10 shape + 10 expression)."""

SMPL_PARENTS = (-1, 0, 0, 0, 1, 2, 3, 4, 5, 6, 7, 8, 9, 9, 9, 12, 13, 14, 16, 17, 18, 19, 20, 21)
ROOT_PARENT = 4294967295  # uint32 -1, how the official kintree tables store the root's parent
_MESHES = {6890: "human_man.obj", 10475: "human_neutral.obj"}


def _fake_class(module: str, name: str) -> type:
    return type(name, (), {"__module__": module, "__qualname__": name})


FAKE_CH = _fake_class("chumpy.ch", "Ch")
FAKE_CHUMPY = {
    "Ch": FAKE_CH,
    "Select": _fake_class("chumpy.reordering", "Select"),
    "transpose": _fake_class("chumpy.reordering", "transpose"),
    "Reshape": _fake_class("chumpy.reordering", "Reshape"),
    "add": _fake_class("chumpy.ch_ops", "add"),  # not on the loader's allow-list
}
FAKE_SPARSE = {
    (fmt, legacy): _fake_class(f"scipy.sparse.{'' if legacy else '_'}{fmt}", f"{fmt}_matrix")
    for fmt in ("csc", "csr", "coo")
    for legacy in (True, False)
}
_FAKES = [*FAKE_CHUMPY.values(), *FAKE_SPARSE.values()]
_LEGACY_NUMPY = {
    id(np.zeros(1).__reduce__()[0]): ("numpy.core.multiarray", "_reconstruct"),
    id(np.float64(0).__reduce__()[0]): ("numpy.core.multiarray", "scalar"),
}


def evaldata_dir() -> Path:
    return Path(os.environ.get("UNIBODY_EVALDATA", "/work/shared/evaldata"))


def real_template(num_vertices: int) -> tuple[np.ndarray, np.ndarray] | None:
    """The real CC BY 4.0 template with this vertex count, or None when absent."""
    path = evaldata_dir() / "mesh" / _MESHES[num_vertices]
    if not path.is_file():
        return None
    v, faces = read_obj(path)
    return v, np.asarray(faces, dtype=np.int64)


def synthetic_template(num_vertices: int) -> tuple[np.ndarray, np.ndarray]:
    """A closed-ish tube of ``num_vertices`` points (rings of 10), 1.7 m tall, Y up."""
    per_ring = 10
    rings = num_vertices // per_ring
    t = np.arange(num_vertices)
    ring, k = np.minimum(t // per_ring, rings - 1), t % per_ring
    angle = 2 * np.pi * k / per_ring + 0.1 * (t >= rings * per_ring)
    v = np.stack([0.15 * np.cos(angle), 1.7 * ring / rings, 0.1 * np.sin(angle)], 1)
    a = (np.arange(rings - 1)[:, None] * per_ring + np.arange(per_ring)[None]).reshape(-1)
    b = (a // per_ring) * per_ring + (a + 1) % per_ring
    faces = np.concatenate([np.stack([a, b, b + per_ring], 1), np.stack([a, b + per_ring, a + per_ring], 1)])
    return v, faces


def template(num_vertices: int) -> tuple[np.ndarray, np.ndarray]:
    return real_template(num_vertices) or synthetic_template(num_vertices)


def make_model(
    family: str, *, seed: int = 0, num_shape: int | None = None, posedirs: bool = False, oracle: bool = False
) -> dict[str, np.ndarray]:
    """A random model of ``family`` in the official key layout (float64, like the files).

    ``oracle`` adds the keys the ``smplx`` package needs to load the file (see :func:`oracle_keys`).
    """
    num_vertices, num_joints, default_shape = SIZES[family]
    rng = np.random.default_rng(seed)
    v, faces = template(num_vertices)
    if family == "smpl":
        parents = np.array(SMPL_PARENTS)
    else:  # any tree with parents before children
        parents = np.array([-1, *(rng.integers(0, j) for j in range(1, num_joints))])
    regressor = np.zeros((num_joints, num_vertices))
    for j in range(num_joints):  # each joint averages a few vertices, rows sum to 1 (as in the files)
        ids = rng.choice(num_vertices, size=8, replace=False)
        regressor[j, ids] = rng.dirichlet(np.ones(8))
    weights = np.zeros((num_vertices, num_joints))
    for i in range(4):
        weights[np.arange(num_vertices), rng.integers(0, num_joints, num_vertices)] += rng.random(num_vertices) + i
    weights /= weights.sum(1, keepdims=True)
    model = {
        "v_template": v,
        "shapedirs": rng.normal(scale=0.01, size=(num_vertices, 3, num_shape or default_shape)),
        "J_regressor": regressor,
        "weights": weights,
        "kintree_table": np.stack([np.where(parents < 0, ROOT_PARENT, parents), np.arange(num_joints)]).astype(
            np.int64
        ),
        "f": faces.astype(np.uint32),
    }
    if posedirs or oracle:
        model["posedirs"] = rng.normal(scale=0.001, size=(num_vertices, 3, 9 * (num_joints - 1)))
    if oracle:
        model.update(oracle_keys(family, len(faces), seed))
    return model


def oracle_keys(family: str, num_faces: int, seed: int = 0) -> dict[str, np.ndarray]:
    """The keys besides the model that ``smplx`` reads: hand PCA (SMPL-H, SMPL-X), face landmarks (SMPL-X).

    Random but well-formed: the forward compared in the tests uses full hand poses
    (``use_pca=False``, ``flat_hand_mean=True``), so none of them changes the posed mesh.
    """
    rng = np.random.default_rng(seed + 1)
    out: dict[str, np.ndarray] = {}
    if family in ("smplh", "smplx"):
        for side in "lr":
            out[f"hands_components{side}"] = np.linalg.qr(rng.normal(size=(45, 45)))[0]
            out[f"hands_mean{side}"] = rng.normal(scale=0.1, size=45)
    if family == "smplx":
        out["lmk_faces_idx"] = rng.integers(0, num_faces, 51).astype(np.int64)
        out["lmk_bary_coords"] = rng.dirichlet(np.ones(3), 51)
        out["dynamic_lmk_faces_idx"] = rng.integers(0, num_faces, (79, 17)).astype(np.int64)
        out["dynamic_lmk_bary_coords"] = rng.dirichlet(np.ones(3), (79, 17))
    return out


# --- a model file of the canonical body itself (the AMASS and mesh-sequence tests) -------------------------------

_DROPPED = ("End", "Index4", "Middle4", "Ring4", "Pinky4", "Neck2")


def canonical_joints(family: str) -> tuple[str, ...]:
    """The canonical joints a :func:`canonical_model` of ``family`` keeps, in index order (Hips first).

    Ends, fourth finger segments and Neck2 are dropped (55 joints: the SMPL-X count); SMPL-H
    (52) also drops the jaw and the eyes. Parents precede children, as the files require.
    """
    from unibody import JOINT_NAMES

    keep = [n for n in JOINT_NAMES[1:] if not any(n.endswith(d) for d in _DROPPED)]
    if family == "smplh":
        keep = [n for n in keep if n not in ("Jaw", "LeftEye", "RightEye")]
    if len(keep) != SIZES[family][1]:
        raise ValueError(f"family: expected smplh or smplx, got {family!r}")
    return tuple(keep)


def canonical_model(family: str, *, seed: int = 0, num_shape: int = 16) -> tuple[dict[str, np.ndarray], object]:
    """A ``family``-format model file skinned exactly like the canonical body, and its topology transfer.

    The template is a seeded subset of the canonical PCA mean mesh in the bind A-pose
    (10,475 or 6,890 of its 18,056 vertices), the joints are the bind joints of
    :func:`canonical_joints` (each regressed exactly as an affine combination of four
    vertices), the weights are the canonical ones with every dropped joint merged into its
    kept ancestor, and the shape directions are smooth (affine fields of the template).
    Posed by the SMPL equations (zero pose = the bind A-pose), it gives meshes the
    canonical rig reproduces, up to the transfer. The transfer maps each canonical vertex
    through the tetrahedron of its three nearest template vertices (exact at rest): what a
    registration would give, without its 40 s. ``posedirs`` are zero and ``num_shape``
    shape columns are followed, for SMPL-X, by 10 expression columns when ``num_shape`` is 10.
    """
    import torch

    from unibody import JOINT_NAMES
    from unibody.geometry.tetra import lift_tetrahedra, tet_barycentric
    from unibody.topology import TopologyTransfer

    num_vertices, num_joints, _ = SIZES[family]
    rng = np.random.default_rng(seed)
    layer = _pca_layer()
    with torch.no_grad():
        prepared = layer.prepare_identity(torch.zeros(1, layer.identity.num_params, dtype=torch.float64))
    bind = prepared.rest_vertices[0].numpy()
    joints_all = prepared.rest_joints[0].numpy()
    subset = np.sort(rng.permutation(bind.shape[0])[:num_vertices])
    v = bind[subset]
    keep = canonical_joints(family)
    index = {n: i for i, n in enumerate(JOINT_NAMES)}
    kept = [index[n] for n in keep]
    slot = {c: i for i, c in enumerate(kept)}
    parents_all = layer.parents.tolist()

    def ancestor(c: int) -> int:
        while c not in slot:
            c = parents_all[c]
        return slot[c]

    parents = np.array([-1] + [ancestor(parents_all[c]) for c in kept[1:]])
    skin = layer.skinning
    dense = np.zeros((bind.shape[0], num_joints))
    owner = np.array([ancestor(j) if j > 0 else 0 for j in range(len(JOINT_NAMES))])
    np.add.at(dense, (skin.vertex.numpy(), owner[skin.joint.numpy()]), skin.weight.double().numpy())
    weights = dense[subset]
    tree = cKDTree(v)
    regressor = np.zeros((num_joints, num_vertices))
    _, near_joint = tree.query(joints_all[kept], k=24)
    for j, c in enumerate(kept):  # the minimum-norm affine weights of 24 near vertices: exact, well spread
        ids = near_joint[j]
        a = np.concatenate([v[ids].T, np.ones((1, len(ids)))])
        regressor[j, ids] = np.linalg.lstsq(a, np.append(joints_all[c], 1.0), rcond=None)[0]
    centre = v.mean(0)
    dirs = np.stack([(v - centre) @ (0.03 * rng.normal(size=(3, 3))) for _ in range(num_shape)], axis=2)
    if family == "smplx" and num_shape == 10:
        dirs = np.concatenate([dirs, rng.normal(scale=1e-4, size=dirs.shape)], axis=2)
    # transfer: the tetrahedron of the three nearest template vertices of every canonical vertex
    near = _nearest(bind, v, tree, subset, layer.faces.numpy())
    fv = torch.from_numpy(near)
    vt = torch.from_numpy(v)
    w = tet_barycentric(torch.from_numpy(bind), lift_tetrahedra(vt, fv))
    transfer = TopologyTransfer(family, num_vertices, fv, w)
    model = {
        "v_template": v,
        "shapedirs": dirs,
        "posedirs": np.zeros((num_vertices, 3, 9 * (num_joints - 1))),
        "J_regressor": regressor,
        "weights": weights,
        "kintree_table": np.stack([np.where(parents < 0, ROOT_PARENT, parents), np.arange(num_joints)]).astype(
            np.int64
        ),
        "f": np.unique(np.sort(near, axis=1), axis=0).astype(np.uint32),
    }
    return model, transfer


_LAYER: list = []


def _pca_layer():
    """The float64 PCA layer, built once per test session."""
    import torch

    from unibody import BodyLayer

    if not _LAYER:
        _LAYER.append(BodyLayer.from_pca(num_components=16, dtype=torch.float64))
    return _LAYER[0]


def _nearest(points: np.ndarray, candidates: np.ndarray, tree: cKDTree, subset: np.ndarray, faces: np.ndarray):
    """(N, 3) a well-shaped triangle of near candidates per point, within three rings of it on the
    canonical mesh (never across a gap, e.g. onto the next finger): the nearest, and the pair of
    the next ones that spans the largest triangle with it."""
    from scipy import sparse

    n = len(points)
    rows = np.concatenate([faces[:, 0], faces[:, 1], faces[:, 2], np.arange(n)])
    cols = np.concatenate([faces[:, 1], faces[:, 2], faces[:, 0], np.arange(n)])
    a = sparse.csr_matrix((np.ones(len(rows)), (rows, cols)), shape=(n, n))
    a = ((a + a.T) > 0).astype(np.float64)
    ring = ((a @ a @ a) > 0).tocsr()
    _, ids = tree.query(points, k=12)
    near = np.asarray(ring[np.repeat(np.arange(n), 12), subset[ids].reshape(-1)]).reshape(n, 12) > 0
    near[:, :3] |= near.sum(1, keepdims=True) < 3  # isolated points keep their plain nearest ones
    order = np.argsort(~near, axis=1, kind="stable")[:, :8]  # valid candidates first, by distance
    ids = np.take_along_axis(ids, order, 1)
    p = candidates[ids]  # (N, 8, 3)
    e = p[:, 1:] - p[:, :1]
    area = np.linalg.norm(np.cross(e[:, :, None], e[:, None, :]), axis=-1)  # (N, 7, 7)
    valid = np.take_along_axis(near, order, 1)[:, 1:]
    area *= valid[:, :, None] & valid[:, None, :]
    best = area.reshape(n, -1).argmax(1)
    i, j = np.unravel_index(best, (7, 7))
    return np.stack([ids[:, 0], ids[np.arange(n), i + 1], ids[np.arange(n), j + 1]], 1)


# --- stand-ins for chumpy and scipy objects ------------------------------------------------------------------


def fake_object(cls: type, state: dict[str, object]) -> object:
    obj = cls.__new__(cls)
    obj.__dict__.update(state)
    return obj


def chumpy_node(kind: str, **terms: object) -> object:
    """A chumpy node as ``Ch.__getstate__`` leaves it: its terms plus bookkeeping entries."""
    state = {"_dirty_vars": set(terms), "_itr": None, "_depends_on_deps": {}, "_make_dense": False}
    return fake_object(FAKE_CHUMPY[kind], {**state, "_make_sparse": False, **terms})


def chumpy_ch(x: np.ndarray) -> object:
    return chumpy_node("Ch", x=np.asarray(x, dtype=np.float64))


def chumpy_select(full: np.ndarray, keep: int) -> object:
    """MANO-style ``Select``: the first ``keep`` columns of a wider (V, 3, S) ``Ch``."""
    idxs = np.arange(full.size).reshape(full.shape)[..., :keep].reshape(-1)
    return chumpy_node("Select", a=chumpy_ch(full), idxs=idxs, preferred_shape=(*full.shape[:-1], keep))


def sparse_matrix(dense: np.ndarray, fmt: str = "csc", *, legacy: bool = True, coords: bool = False) -> object:
    """A scipy csc/csr/coo matrix as it pickles (``coords`` for SciPy >= 1.13 coo)."""
    rows, cols = np.nonzero(dense)
    order = np.lexsort((rows, cols)) if fmt == "csc" else np.lexsort((cols, rows))
    rows, cols = rows[order], cols[order]
    state: dict[str, object] = {"_shape": dense.shape, "maxprint": 50, "data": dense[rows, cols]}
    if legacy:
        state["format"] = fmt  # old SciPy kept the format name in the instance dict
    if fmt == "coo":
        state.update(
            {"coords": (rows, cols)} if coords else {"row": rows.astype(np.int32), "col": cols.astype(np.int32)}
        )
    else:
        major, minor, n = (cols, rows, dense.shape[1]) if fmt == "csc" else (rows, cols, dense.shape[0])
        indptr = np.concatenate([[0], np.cumsum(np.bincount(major, minlength=n))]).astype(np.int32)
        state.update(indices=minor.astype(np.int32), indptr=indptr)
    return fake_object(FAKE_SPARSE[(fmt, legacy)], state)


class _Pickler(pickle._Pickler):
    """Pure-Python pickler that records the stand-ins under their fake module names."""

    def __init__(self, file: io.BufferedIOBase, protocol: int, legacy: bool) -> None:
        super().__init__(file, protocol=protocol)
        self.legacy = legacy
        self.names = {id(c): (c.__module__, c.__qualname__) for c in _FAKES}
        if legacy:
            self.names.update(_LEGACY_NUMPY)

    def reducer_override(self, obj: object) -> object:
        if self.legacy and type(obj) is np.ndarray and not obj.dtype.hasobject:
            func, args, (version, shape, dtype, fortran, raw) = obj.__reduce__()
            return func, (args[0], args[1], "b"), (version, shape, dtype, fortran, raw.decode("latin1"))
        return NotImplemented

    def save_global(self, obj: object, name: str | None = None) -> None:
        target = self.names.get(id(obj))
        if target is None:
            return super().save_global(obj, name)
        module, qualname = target
        if self.proto >= 4:
            self.save(module)
            self.save(qualname)
            self.write(pickle.STACK_GLOBAL)
        else:
            self.write(pickle.GLOBAL + f"{module}\n{qualname}\n".encode())
        self.memoize(obj)


def dumps(obj: object, *, protocol: int = 2, legacy: bool = True) -> bytes:
    buf = io.BytesIO()
    _Pickler(buf, protocol, legacy).dump(obj)
    return buf.getvalue()


# --- writers ----------------------------------------------------------------------------------------------------


def pkl_payload(
    model: dict[str, np.ndarray], *, chumpy: bool = False, select_shapedirs: bool = False, legacy: bool = True
) -> dict[str, object]:
    """The dict an official pickle holds: sparse J_regressor, optional chumpy wrappers, extra entries."""
    out: dict[str, object] = {"bs_style": "lbs", "bs_type": "lrotmin", **model}
    out["J_regressor"] = sparse_matrix(model["J_regressor"], "csc", legacy=legacy)
    if chumpy:
        for key in ("v_template", "shapedirs", "posedirs", "weights"):
            if key in model:
                out[key] = chumpy_ch(model[key])
    if select_shapedirs:
        sd = model["shapedirs"]
        extra = np.random.default_rng(1).normal(size=sd.shape)
        out["shapedirs"] = chumpy_select(np.concatenate([sd, extra], axis=2), sd.shape[2])
    return out


def write_pkl(
    path: Path,
    model: dict[str, np.ndarray],
    *,
    protocol: int = 2,
    chumpy: bool = False,
    select_shapedirs: bool = False,
    legacy: bool = True,
) -> Path:
    payload = pkl_payload(model, chumpy=chumpy, select_shapedirs=select_shapedirs, legacy=legacy)
    path.write_bytes(dumps(payload, protocol=protocol, legacy=legacy))
    return path


def write_npz(path: Path, model: dict[str, object], *, object_keys: tuple[str, ...] = ()) -> Path:
    """Write an npz; ``object_keys`` become pickled 0-d object arrays (``J_regressor`` as a csc matrix)."""
    with zipfile.ZipFile(path, "w") as zf:
        for key, value in model.items():
            with zf.open(f"{key}.npy", "w") as fp:
                if key not in object_keys:
                    np.lib.format.write_array(fp, np.asarray(value), allow_pickle=False)
                    continue
                holder = np.empty(1, dtype=object)
                holder[0] = sparse_matrix(value) if key == "J_regressor" else value
                holder = holder.reshape(())
                np.lib.format.write_array_header_1_0(fp, {"descr": "|O", "fortran_order": False, "shape": ()})
                fp.write(dumps(holder, protocol=3, legacy=False))
    return path
