"""The public surface is a contract: changing it must be a deliberate edit of this file."""

from __future__ import annotations

import dataclasses

import unibody


def test_all_snapshot():
    assert sorted(unibody.__all__) == [
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


def test_output_fields():
    assert [f.name for f in dataclasses.fields(unibody.BodyOutput)] == [
        "vertices",
        "joints",
        "transforms",
        "rest_vertices",
    ]
    assert [f.name for f in dataclasses.fields(unibody.PreparedIdentity)] == [
        "rest_vertices",
        "rest_rotations",
        "rest_joints",
        "offsets",
        "skin_values",  # derived by prepare_rest, not a constructor argument
    ]
    assert [f.name for f in dataclasses.fields(unibody.PreparedIdentity) if f.init][-1] == "offsets"
    assert [f.name for f in dataclasses.fields(unibody.InversionResult)] == [
        "pose",
        "rotations",
        "transl",
        "vertices",
        "per_vertex_error",
        "iterations",
    ]


def test_joint_contract():
    names = unibody.JOINT_NAMES
    assert len(names) == unibody.NUM_JOINTS == 78 and unibody.NUM_POSED == 77
    assert names[:12] == (
        "Root",
        "Hips",
        "Spine1",
        "Spine2",
        "Chest",
        "Neck1",
        "Neck2",
        "Head",
        "HeadEnd",
        "Jaw",
        "LeftEye",
        "RightEye",
    )
    assert names[12:16] == ("LeftShoulder", "LeftArm", "LeftForeArm", "LeftHand")
    assert names[68:73] == ("LeftLeg", "LeftShin", "LeftFoot", "LeftToeBase", "LeftToeEnd")
    assert unibody.joint_index("RightToeEnd") == 77


def test_canonical_rig_parents(rig):
    p = rig.tree.parents
    idx = unibody.joint_index
    assert p[idx("Hips")] == idx("Root") and p[idx("LeftLeg")] == idx("Hips")
    assert p[idx("LeftShoulder")] == idx("Chest") and p[idx("Jaw")] == idx("Head")
    assert rig.num_vertices == 18056 and rig.faces.shape == (36108, 3)
