"""unibody: one canonical mesh and 78-joint skeleton for any parametric human body model.

Units are metres, Y is up and bodies face +Z. Poses are (B, 77, 3) axis-angle local
rotations of joints 1..77, T-pose-relative by default (paper 001).
"""

import os as _os
import sys as _sys

# The ``unibody`` command on a machine other jobs share: with OpenMP's default waiting, a torch
# thread spins at each barrier while the one the scheduler put aside waits for a core. On 2 cores
# with one busy, ``unibody mocap label`` took 23-27 s spinning and 14-16 s waiting passively
# (benchmarks/cli_contention.py; 4-9x in runs beside heavier jobs); idle, passive cost ~6 %.
# Only for the command, only before torch loads OpenMP, never over the user's own setting (an
# empty value gives libgomp's default).
if _sys.argv and _os.path.basename(_sys.argv[0]) == "unibody" and "torch" not in _sys.modules:
    _os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")

from .body import BodyLayer, BodyOutput, PreparedIdentity  # noqa: E402
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
