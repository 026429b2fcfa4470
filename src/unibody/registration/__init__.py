"""Automatic registration of new body templates onto the canonical topology (the "wrap").

See :func:`register` for the algorithm and :func:`topology_transfer` for the cached
transfer built from it.
"""

from ._articulated import Phase
from ._cache import REGISTRATION_VERSION, topology_transfer
from ._nonrigid import IcpSettings
from ._normalize import Normalization
from ._register import MAX_FIT_P95, PRESETS, Registration, RegistrationConfig, RegistrationStats, normalize, register

__all__ = [
    "IcpSettings",
    "MAX_FIT_P95",
    "Normalization",
    "PRESETS",
    "REGISTRATION_VERSION",
    "Phase",
    "Registration",
    "RegistrationConfig",
    "RegistrationStats",
    "normalize",
    "register",
    "topology_transfer",
]
