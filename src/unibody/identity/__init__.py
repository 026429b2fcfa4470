"""Identity backends: each maps its own shape parameters to a rest mesh on its native topology."""

from __future__ import annotations

from torch import nn

from .anny import PHENOTYPES, AnnyIdentity

__all__ = ["AnnyIdentity", "PHENOTYPES", "BACKENDS", "create"]

BACKENDS: tuple[str, ...] = ("anny",)


def create(name: str) -> nn.Module:
    """Build an identity backend by name (for the CLI); see ``BACKENDS``."""
    if name == "anny":
        return AnnyIdentity.create()
    raise ValueError(f"identity backend: unknown name {name!r}; choose one of {', '.join(BACKENDS)}")
