"""Body regions of the canonical mesh (body, hands, feet, head), from the skinning weights.

Each vertex takes the region of its most influential joint; regions are defined by joint
names. Used for per-region error reports (paper 000 Table 3) and per-vertex loss weights.
"""

from __future__ import annotations

import torch

from .rig import Rig

__all__ = ["REGIONS", "dominant_joints", "joint_regions", "vertex_regions"]

REGIONS: tuple[str, ...] = ("body", "hands", "feet", "head")


def _region_of(name: str) -> int:
    if "Hand" in name:
        return REGIONS.index("hands")
    if any(part in name for part in ("Foot", "Toe")):
        return REGIONS.index("feet")
    if name in ("Neck2", "Head", "HeadEnd", "Jaw", "LeftEye", "RightEye"):
        return REGIONS.index("head")
    return REGIONS.index("body")


def joint_regions(joint_names: tuple[str, ...]) -> torch.Tensor:
    """(J,) region index of each joint (see ``REGIONS``)."""
    return torch.tensor([_region_of(n) for n in joint_names])


def dominant_joints(
    skin_vertex: torch.Tensor, skin_joint: torch.Tensor, skin_weight: torch.Tensor, num_vertices: int, num_joints: int
) -> torch.Tensor:
    """(V,) the joint with the largest skinning weight of each vertex (CPU)."""
    dense = skin_weight.new_zeros(num_vertices, num_joints)
    dense[skin_vertex, skin_joint] = skin_weight
    return dense.argmax(1).cpu()


def vertex_regions(rig: Rig) -> torch.Tensor:
    """(V,) region index of each vertex: the region of its largest skinning weight."""
    dominant = dominant_joints(rig.skin_vertex, rig.skin_joint, rig.skin_weight, rig.num_vertices, rig.num_joints)
    return joint_regions(rig.joint_names)[dominant]
