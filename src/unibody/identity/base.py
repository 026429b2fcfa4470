"""The identity-backend contract: what :class:`~unibody.body.BodyLayer` needs from a shape model.

A backend is an ``nn.Module`` that maps K shape parameters to rest meshes on its own (native)
topology, in metres, Y up, facing +Z. Anny, PCA, SMPL, MHR and GarmentMeasurements implement
it; so can any user model, without subclassing (a structural ``typing.Protocol``).
"""

from __future__ import annotations

from typing import Protocol, runtime_checkable

import torch
from torch import nn

__all__ = ["IdentityBackend", "MEMBERS", "missing_members", "check_identity_backend"]


@runtime_checkable
class IdentityBackend(Protocol):
    """Structural type of an identity backend.

    Attributes:
        name: short name of the model (``"anny"``, ``"pca"``, ``"smplx"``, ...); names the
            registration cache of a foreign topology.
        param_names: (K,) names of the parameters, in order.
        num_params: K.
        param_bounds: ``(lower (K,), upper (K,))`` inclusive bounds in the backend's dtype,
            ``-inf`` / ``inf`` where a parameter is unbounded on that side; None when every
            parameter is unbounded. ``forward`` accepts any parameters within them, and
            fitters (:func:`unibody.fitting.shape_fit.fit_identity`) keep to them.
    """

    name: str
    param_names: tuple[str, ...]

    @property
    def num_params(self) -> int: ...

    @property
    def param_bounds(self) -> tuple[torch.Tensor, torch.Tensor] | None: ...

    def default_params(self, batch: int = 1) -> torch.Tensor:
        """(B, K) the backend's reference identity (its mean or average body)."""
        ...

    def forward(self, params: torch.Tensor) -> torch.Tensor:
        """(B, K) parameters -> (B, V, 3) m, rest meshes on the native topology."""
        ...

    def template(self) -> torch.Tensor:
        """(V, 3) m, the native rest mesh of ``default_params()``."""
        ...

    def faces(self) -> torch.Tensor:
        """(F, 3) int64 triangles of the native mesh."""
        ...


MEMBERS: tuple[str, ...] = (
    "name",
    "param_names",
    "num_params",
    "param_bounds",
    "default_params",
    "forward",
    "template",
    "faces",
)
"""The members of :class:`IdentityBackend`, in the order error messages list them."""


def missing_members(obj: object) -> list[str]:
    """The :data:`MEMBERS` that ``obj`` lacks (empty for a backend)."""
    return [m for m in MEMBERS if not hasattr(obj, m)]


def check_identity_backend(identity: object, name: str = "identity") -> None:
    """TypeError unless ``identity`` is an ``nn.Module`` implementing :class:`IdentityBackend`."""
    missing = missing_members(identity)
    if isinstance(identity, nn.Module) and not missing:
        return
    what = type(identity).__name__
    why = []
    if not isinstance(identity, nn.Module):
        why.append("is not a torch.nn.Module")
    if missing:
        why.append(f"lacks {', '.join(missing)}")
    raise TypeError(
        f"{name}: expected an identity backend (an nn.Module implementing unibody.identity.IdentityBackend: "
        f"{', '.join(MEMBERS)}), got {what}, which {' and '.join(why)}"
    )
