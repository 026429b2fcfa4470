"""Articulated occupancy of the unified body (COAP, paper 002): part-wise neural occupancy of
posed bodies, self-intersection and scene-collision terms, marching-cubes surfaces.

    from unibody.occupancy import BodyOccupancy, resolve_self_intersections
    occ = BodyOccupancy.pretrained()
"""

from .field import BodyOccupancy
from .model import OccupancyNet, PartEncoding
from .parts import BodyParts
from .resolve import Resolved, resolve_self_intersections

__all__ = ["BodyOccupancy", "BodyParts", "OccupancyNet", "PartEncoding", "Resolved", "resolve_self_intersections"]
