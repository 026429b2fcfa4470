"""unibody: one canonical mesh and 78-joint skeleton for any parametric human body model.

Units are metres, Y is up and bodies face +Z. Poses are (B, 77, 3) axis-angle local
rotations of joints 1..77, T-pose-relative by default (paper 001).
"""

from .body import BodyLayer, BodyOutput, PreparedIdentity
from .fitting.inversion import PRESETS, InversionConfig, InversionResult, PoseInverter
from .identity import AnnyIdentity, GarmentIdentity, MHRIdentity, PCAIdentity, SMPLIdentity
from .rig import JOINT_NAMES, NUM_JOINTS, NUM_POSED, KinematicTree, Rig, joint_index
from .skeleton import SkeletonTransfer
from .topology import TopologyTransfer

__all__ = [
    "AnnyIdentity",
    "BodyLayer",
    "BodyOutput",
    "GarmentIdentity",
    "InversionConfig",
    "InversionResult",
    "JOINT_NAMES",
    "KinematicTree",
    "MHRIdentity",
    "NUM_JOINTS",
    "NUM_POSED",
    "PCAIdentity",
    "PRESETS",
    "PoseInverter",
    "PreparedIdentity",
    "Rig",
    "SMPLIdentity",
    "SkeletonTransfer",
    "TopologyTransfer",
    "joint_index",
]
__version__ = "0.1.0"
