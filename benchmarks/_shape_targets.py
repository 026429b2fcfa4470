"""Bodies from outside a shape space's training set, moved onto the canonical topology (for shape_spaces.py).

- The three template meshes of the evaluation data (``mesh/human_{man,woman,neutral}.obj``:
  SMPL man and woman, SMPL-X neutral, CC BY 4.0; evaluation only, never trained on), registered
  with :func:`unibody.registration.register` (default preset) and mapped to the canonical
  topology in the normalised frame (metres, Y up, feet on y = 0), in their own T-pose.
- Controls: held-out Anny identities whose native mesh goes through the same automatic
  registration, next to the same identity transferred by the hand-made wrap (the mesh the
  native PCA is trained on). Their gap is what the pipeline alone costs a body that is in the span.

Registrations take ~1 min each; the results are cached under ``build/shape_targets/`` keyed by
the registration version and the source's sha256.
"""

from __future__ import annotations

import hashlib
import os
from pathlib import Path

import numpy as np
import torch

from unibody import BodyLayer
from unibody.io.atomic import atomic_write, file_sha256
from unibody.io.obj import read_obj
from unibody.registration import REGISTRATION_VERSION, register

ROOT = Path(__file__).resolve().parents[1]
CACHE = ROOT / "build" / "shape_targets"
TEMPLATES = {"SMPL man": "human_man.obj", "SMPL woman": "human_woman.obj", "SMPL-X neutral": "human_neutral.obj"}


def evaldata_dir() -> Path:
    return Path(os.environ.get("UNIBODY_EVALDATA", "/work/shared/evaldata"))


def _registered(vertices: np.ndarray | torch.Tensor, faces) -> np.ndarray:
    """(V, 3) float64 canonical mesh of a source mesh, in the normalised frame (metres, Y up)."""
    v = torch.as_tensor(np.asarray(vertices), dtype=torch.float64)
    reg = register(v, faces)
    return reg.normalization.apply(reg.correspondence.apply(v)).numpy()


def _cached(path: Path, key: str, make) -> np.ndarray:
    if path.is_file():
        with np.load(path, allow_pickle=False) as data:
            if str(data["key"]) == key:
                return data["vertices"]
    vertices = make()
    path.parent.mkdir(parents=True, exist_ok=True)
    with atomic_write(path) as f:
        np.savez(f, vertices=vertices, key=np.asarray(key))
    return vertices


def template_meshes(progress=print) -> dict[str, torch.Tensor]:
    """``{name: (V, 3) float64}`` the registered template meshes (T-pose, normalised frame); {} if absent."""
    out = {}
    for name, file in TEMPLATES.items():
        path = evaldata_dir() / "mesh" / file
        if not path.is_file():
            progress(f"{name}: {path} not found; row skipped")
            continue
        key = f"registration v{REGISTRATION_VERSION}, {file_sha256(path)}"
        cache = CACHE / f"{path.stem}.npz"
        if not cache.is_file():
            progress(f"{name}: registering {path.name} (about a minute)")
        out[name] = torch.from_numpy(_cached(cache, key, lambda p=path: _registered(*read_obj(p))))
    return out


def anny_controls(params: np.ndarray, progress=print) -> list[tuple[torch.Tensor, torch.Tensor]]:
    """``[(automatic (V, 3), hand-made (V, 3))]`` of Anny identities (rows of ``params``), float64.

    Both in the registration's normalised frame: the identity's native Anny mesh registered
    automatically, and the same identity through the hand-made wrap's transfer.
    """
    layer = BodyLayer.from_anny(local_changes="all", dtype=torch.float64)
    out = []
    for i, row in enumerate(np.asarray(params, dtype=np.float64)):
        with torch.no_grad():
            native = layer.identity(torch.from_numpy(row)[None])[0]
            truth = layer.topology(native[None])[0]
        key = f"registration v{REGISTRATION_VERSION}, anny params {hashlib.sha256(row.tobytes()).hexdigest()}"
        cache = CACHE / f"anny_control_{i}.npz"
        if not cache.is_file():
            progress(f"Anny control {i}: registering its native mesh (a few minutes)")

        def make(native=native, truth=truth) -> np.ndarray:
            reg = register(native, layer.identity.faces())
            n = reg.normalization
            return np.stack([n.apply(reg.correspondence.apply(native)).numpy(), n.apply(truth).numpy()])

        pair = torch.from_numpy(_cached(cache, key, make))
        out.append((pair[0], pair[1]))
    return out
