"""The body a motion is played on: its identity backend and parameters, built once per process."""

from __future__ import annotations

from functools import lru_cache

import torch

from ..body import BodyLayer, PreparedIdentity
from ..motion import Motion

__all__ = ["BACKENDS", "body_for"]

BACKENDS = ("pca", "anny")
"""Identity backends a motion file may name; a motion without an identity plays on the PCA mean."""


@lru_cache(maxsize=4)
def _layer(backend: str, num_params: int, dtype: torch.dtype) -> BodyLayer:
    if backend == "anny":
        return BodyLayer.from_anny(dtype=dtype)
    return BodyLayer.from_pca(num_components=num_params, dtype=dtype)


def body_for(motion: Motion, dtype: torch.dtype = torch.float32) -> tuple[BodyLayer, PreparedIdentity]:
    """The layer and prepared identity of ``motion`` (``identity_backend`` "pca" or "anny").

    Raises:
        ValueError: the motion names another backend, or its identity has the wrong length.
    """
    backend = motion.identity_backend or "pca"
    if backend not in BACKENDS:
        raise ValueError(f"identity_backend: expected one of {', '.join(BACKENDS)}, got {backend!r}")
    params = None if motion.identity is None else torch.as_tensor(motion.identity, dtype=dtype)[None]
    k = 128 if params is None or backend == "anny" else params.shape[1]
    layer = _layer(backend, k, dtype)
    with torch.no_grad():
        if params is None:
            params = torch.zeros(1, layer.identity.num_params, dtype=dtype)
        prepared = layer.prepare_identity(params)
    return layer, prepared
