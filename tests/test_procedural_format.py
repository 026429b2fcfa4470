"""The procedural twist sidecar format: a valid file parses and round-trips; every rule of
docs/procedural.md "Validation" raises ProceduralFormatError naming the offending entry;
no input whatsoever makes the parser raise anything else."""

from __future__ import annotations

import copy
import json
import math
import pickle
import re
from collections.abc import Callable
from typing import Any

import jsonschema
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from unibody.procedural import (
    EVALUATION_ORDER,
    SUPPORTED_MODES,
    ProceduralDefinition,
    ProceduralFormatError,
    RotationExtraction,
    load,
    parse,
    schema,
)
from unibody.rig import JOINT_NAMES

FOREARM = [f"LeftForeArmTwist{i}" for i in (1, 2, 3)]
UPPER_ARM = [f"LeftArmTwist{i}" for i in (1, 2, 3)]


def valid_sidecar(per_joint: bool = False) -> dict[str, Any]:
    """A small valid sidecar over the canonical joints: a forward forearm and a reverse upper-arm segment.

    Args:
        per_joint: give ``rotation_extraction`` in the object form with one override, else as a string.
    """
    rotation: dict[str, list[Any]] = {"rows": [], "columns": [], "values": []}
    translation: dict[str, list[Any]] = {"rows": [], "columns": [], "values": []}

    def add(m: dict[str, list[Any]], row: str, column: str, value: float) -> None:
        if value != 0.0:
            m["rows"].append(row)
            m["columns"].append(column)
            m["values"].append(value)

    segments = [
        ("LeftForeArm", "LeftForeArm", "LeftHand", FOREARM, False, 1, (1 / 3, 2 / 3, 1.0)),
        ("LeftArm", "LeftArm", "LeftForeArm", UPPER_ARM, True, -1, (0.0, 1 / 3, 2 / 3)),
    ]
    for _, start, end, twists, reverse, _, ts in segments:
        for joint, t in zip(twists, ts, strict=True):
            add(rotation, joint, start if reverse else end, 1.0 - t if reverse else t)
            add(translation, joint, start, 1.0 - t)
            add(translation, joint, end, t)
    meta = {"format": "coo", "dtype": "float32", "row_space": "procedural_joints", "column_space": "public_joints"}
    extractors = {
        "local_x_euler": {"source_rotation": "absolute_local", "axis": "x", "reference": "bind"},
        "local_x_swing_twist": {"source_rotation": "absolute_local", "axis": "x", "reference": "bind"},
        "aligned_x_swing_twist": {
            "source_rotation": "world",
            "axis": "x",
            "reference": "bind",
            "description": "twist about the bone of the segment-aligned virtual orientation",
        },
    }
    policy: Any = "aligned_x_swing_twist"
    if per_joint:
        policy = {"default": "local_x_euler", "per_procedural_joint": {FOREARM[1]: "local_x_swing_twist"}}
    return {
        "schema_version": "1.0.0",
        "modes": list(SUPPORTED_MODES),
        "template_asset": {"name": "test", "version": "0", "source": "tests", "joint_count": len(JOINT_NAMES) + 6},
        "conventions": {
            "units": "meters",
            "angle_units": "radians",
            "dtype": "float32",
            "matrix_layout": "row_major",
            "rotation_handedness": "right",
            "euler_order": "XYZ",
            "quaternion_order": "xyzw",
            "axes": {"up": "+Y", "forward": "+Z", "bone": "+X"},
        },
        "public_rig_derivation": {
            "main_joint_names": list(JOINT_NAMES),
            "removed_joint_parent_policy": "nearest_kept_ancestor",
            "skin_weight_aggregation_policy": "add_to_nearest_kept_ancestor",
        },
        "channel_extractors": extractors,
        "rotation_extraction": policy,
        "segments": [
            {
                "name": name,
                "start": start,
                "end": end,
                "twist_joints": list(twists),
                "reverse_compensation": reverse,
                "source_axis": "x",
                "sign": sign,
            }
            for name, start, end, twists, reverse, sign, _ in segments
        ],
        "parameter_matrices": {"rotation": {**meta, **rotation}, "translation": {**meta, **translation}},
        "evaluation_order": list(EVALUATION_ORDER),
    }


VALIDATOR = jsonschema.Draft202012Validator(schema())


# --------------------------------------------------------------------------- valid input


@pytest.mark.parametrize("per_joint", [False, True])
def test_valid_sidecar_parses_round_trips_and_matches_schema(per_joint):
    raw = valid_sidecar(per_joint)
    jsonschema.Draft202012Validator.check_schema(schema())
    jsonschema.validate(raw, schema())
    d = parse(raw)
    assert isinstance(d, ProceduralDefinition)
    assert hash(d) == hash(parse(valid_sidecar(per_joint)))
    assert parse(d.to_dict()) == d
    assert json.loads(json.dumps(d.to_dict())) == d.to_dict()
    assert d.to_dict()["rotation_extraction"] == raw["rotation_extraction"]
    jsonschema.validate(d.to_dict(), schema())


def test_definition_accessors():
    d = parse(valid_sidecar(per_joint=True))
    assert d.main_joint_names == JOINT_NAMES
    assert d.twist_joints == (*FOREARM, *UPPER_ARM)
    assert d.template_asset.joint_count == len(JOINT_NAMES) + len(d.twist_joints)
    assert d.segment_of("LeftArmTwist2").name == "LeftArm"
    assert [s.driver for s in d.segments] == ["LeftHand", "LeftArm"]
    assert [s.sign for s in d.segments] == [1, -1]
    assert d.rotation_extraction.mode_of(FOREARM[1]) == "local_x_swing_twist"
    assert d.rotation_extraction.mode_of(FOREARM[0]) == "local_x_euler"
    assert [e.mode for e in d.channel_extractors] == list(SUPPORTED_MODES)
    assert d.conventions.bone_axis == "+X" and d.rotation.name == "rotation" and d.translation.name == "translation"
    with pytest.raises(ValueError, match="Hips"):
        d.segment_of("Hips")
    assert parse(valid_sidecar()).rotation_extraction == RotationExtraction("aligned_x_swing_twist", as_string=True)


def test_load(tmp_path):
    path = tmp_path / "twist.json"
    path.write_text(json.dumps(valid_sidecar()), encoding="utf-8")
    assert load(path) == parse(valid_sidecar()) == load(str(path))


def test_error_is_a_value_error_and_pickles():
    with pytest.raises(ValueError) as info:
        parse(None)
    err = info.value
    assert isinstance(err, ProceduralFormatError) and err.path == "$"
    again = pickle.loads(pickle.dumps(err))
    assert again.path == err.path and str(again) == str(err)


# --------------------------------------------------------------------------- one case per rule

_STEP = re.compile(r"\.?([^.\[\]]+)|\[(-?\d+)\]")


def _steps(path: str) -> list[str | int]:
    return [key if key else int(index) for key, index in _STEP.findall(path)]


def _parent(d: Any, path: str) -> tuple[Any, str | int]:
    *head, last = _steps(path)
    for step in head:
        d = d[step]
    return d, last


def put(path: str, value: Any) -> Callable[[dict], None]:
    def mutate(d: dict) -> None:
        parent, last = _parent(d, path)
        parent[last] = value

    return mutate


def drop(path: str) -> Callable[[dict], None]:
    def mutate(d: dict) -> None:
        parent, last = _parent(d, path)
        del parent[last]

    return mutate


def drop_entries(matrix: str, keep: Callable[[str, str, float], bool]) -> Callable[[dict], None]:
    def mutate(d: dict) -> None:
        m = d["parameter_matrices"][matrix]
        kept = [e for e in zip(m["rows"], m["columns"], m["values"], strict=True) if keep(*e)]
        m["rows"], m["columns"], m["values"] = (list(x) for x in zip(*kept, strict=True))

    return mutate


def append_entry(matrix: str, row: str, column: str, value: float) -> Callable[[dict], None]:
    def mutate(d: dict) -> None:
        m = d["parameter_matrices"][matrix]
        m["rows"].append(row)
        m["columns"].append(column)
        m["values"].append(value)

    return mutate


def only_modes(*modes: str) -> Callable[[dict], None]:
    def mutate(d: dict) -> None:
        d["modes"] = list(modes)
        d["channel_extractors"] = {m: d["channel_extractors"][m] for m in modes}

    return mutate


def chain(*mutations: Callable[[dict], None]) -> Callable[[dict], None]:
    def mutate(d: dict) -> None:
        for m in mutations:
            m(d)

    return mutate


ROT = "parameter_matrices.rotation"
TRANS = "parameter_matrices.translation"
PER_JOINT = "rotation_extraction.per_procedural_joint"

# (id, mutation, expected .path, fragment the message must contain)
CASES = [
    ("missing_top_level_field", drop("modes"), "modes", "missing required key 'modes'"),
    ("wrong_type", put("segments", {}), "segments", "expected an array, got object"),
    ("wrong_type_nested", put("template_asset.name", 7), "template_asset.name", "got integer 7"),
    ("list_instead_of_object", put("conventions", ["meters"]), "conventions", "expected an object"),
    ("schema_version_major", put("schema_version", "2.0.0"), "schema_version", "unsupported major version 2"),
    ("schema_version_not_semver", put("schema_version", "1.0"), "schema_version", "'1.0'"),
    ("unsupported_mode", put("modes[0]", "local_z_euler"), "modes[0]", "'local_z_euler'"),
    ("duplicate_mode", lambda d: d["modes"].append("local_x_euler"), "modes[3]", "duplicate mode 'local_x_euler'"),
    ("empty_modes", put("modes", []), "modes", "non-empty"),
    (
        "extractor_missing",
        drop("channel_extractors.local_x_euler"),
        "channel_extractors.local_x_euler",
        "missing extractor for declared mode 'local_x_euler'",
    ),
    (
        "extractor_undeclared",
        put("modes", ["aligned_x_swing_twist"]),
        "channel_extractors.local_x_euler",
        "undeclared mode 'local_x_euler'",
    ),
    (
        "source_rotation_for_mode",
        put("channel_extractors.aligned_x_swing_twist.source_rotation", "absolute_local"),
        "channel_extractors.aligned_x_swing_twist.source_rotation",
        "expected 'world' for mode 'aligned_x_swing_twist', got string 'absolute_local'",
    ),
    (
        "extractor_axis",
        put("channel_extractors.local_x_euler.axis", "y"),
        "channel_extractors.local_x_euler.axis",
        "'y'",
    ),
    ("conventions_value", put("conventions.units", "centimeters"), "conventions.units", "'centimeters'"),
    ("conventions_axes", put("conventions.axes.up", "+Z"), "conventions.axes.up", "expected '+Y', got string '+Z'"),
    (
        "derivation_policy",
        put("public_rig_derivation.removed_joint_parent_policy", "drop"),
        "public_rig_derivation.removed_joint_parent_policy",
        "'drop'",
    ),
    ("segment_start_unknown", put("segments[0].start", "LeftForeArmX"), "segments[0].start", "'LeftForeArmX'"),
    ("segment_end_unknown", put("segments[1].end", "Elbow"), "segments[1].end", "unknown joint 'Elbow'"),
    ("matrix_column_unknown", put(f"{ROT}.columns[0]", "Nope"), f"{ROT}.columns[0]", "unknown public joint 'Nope'"),
    (
        "matrix_row_unknown",
        put(f"{TRANS}.rows[2]", "LeftForeArmTwist9"),
        f"{TRANS}.rows[2]",
        "unknown twist joint 'LeftForeArmTwist9'",
    ),
    ("matrix_row_main_joint", put(f"{ROT}.rows[0]", "Hips"), f"{ROT}.rows[0]", "unknown twist joint 'Hips'"),
    (
        "twist_joint_without_rotation_row",
        drop_entries("rotation", lambda r, c, v: r != FOREARM[0]),
        f"{ROT}.rows",
        f"twist joint '{FOREARM[0]}' has no entry",
    ),
    (
        "twist_joint_without_translation_row",
        drop_entries("translation", lambda r, c, v: r != UPPER_ARM[2]),
        f"{TRANS}.rows",
        f"twist joint '{UPPER_ARM[2]}' has no entry",
    ),
    (
        "duplicate_twist_joint",
        put("segments[1].twist_joints[0]", FOREARM[0]),
        "segments[1].twist_joints[0]",
        f"duplicate twist joint '{FOREARM[0]}'",
    ),
    (
        "twist_joint_named_like_main",
        put("segments[0].twist_joints[2]", "LeftHand"),
        "segments[0].twist_joints[2]",
        "'LeftHand' is named like a main joint",
    ),
    (
        "duplicate_main_joint",
        put("public_rig_derivation.main_joint_names[5]", JOINT_NAMES[4]),
        "public_rig_derivation.main_joint_names[5]",
        f"duplicate main joint name '{JOINT_NAMES[4]}'",
    ),
    ("duplicate_segment_name", put("segments[1].name", "LeftForeArm"), "segments[1].name", "duplicate segment name"),
    (
        "duplicate_matrix_entry",
        append_entry("rotation", FOREARM[0], "LeftHand", 0.5),
        f"{ROT}.rows[6]",
        f"duplicate entry ('{FOREARM[0]}', 'LeftHand'), first given at index 0",
    ),
    (
        "unknown_matrix_name",
        lambda d: d["parameter_matrices"].update(scale=d["parameter_matrices"]["rotation"]),
        "parameter_matrices.scale",
        "unknown matrix name 'scale'",
    ),
    ("missing_matrix", drop(TRANS), TRANS, "missing required key 'translation'"),
    ("matrix_format", put(f"{ROT}.format", "csr"), f"{ROT}.format", "'csr'"),
    ("invalid_source_axis", put("segments[0].source_axis", "w"), "segments[0].source_axis", "invalid axis 'w'"),
    ("invalid_sign_0", put("segments[0].sign", 0), "segments[0].sign", "expected 1 or -1, got 0"),
    ("invalid_sign_2", put("segments[1].sign", 2), "segments[1].sign", "expected 1 or -1, got 2"),
    ("invalid_sign_float", put("segments[0].sign", 1.0), "segments[0].sign", "expected 1 or -1, got 1.0"),
    ("invalid_sign_bool", put("segments[0].sign", True), "segments[0].sign", "expected 1 or -1, got True"),
    ("invalid_sign_huge", put("segments[0].sign", 10**5000), "segments[0].sign", "got <16610-bit integer>"),
    (
        "reverse_compensation_not_bool",
        put("segments[0].reverse_compensation", 0),
        "segments[0].reverse_compensation",
        "got integer 0",
    ),
    ("missing_rotation_extraction", drop("rotation_extraction"), "rotation_extraction", "missing required key"),
    (
        "rotation_extraction_undeclared",
        chain(only_modes("aligned_x_swing_twist"), put("rotation_extraction", "local_x_euler")),
        "rotation_extraction",
        "'local_x_euler' is not declared",
    ),
    (
        "rotation_extraction_unsupported",
        put("rotation_extraction", {"default": "global_twist"}),
        "rotation_extraction.default",
        "'global_twist'",
    ),
    ("rotation_extraction_wrong_type", put("rotation_extraction", 3), "rotation_extraction", "got integer 3"),
    (
        "per_joint_mode_undeclared",
        chain(
            only_modes("aligned_x_swing_twist"),
            put("rotation_extraction", {"default": "aligned_x_swing_twist", "per_procedural_joint": {}}),
            put(f"{PER_JOINT}.{FOREARM[1]}", "local_x_euler"),
        ),
        f"{PER_JOINT}.{FOREARM[1]}",
        "'local_x_euler' is not declared",
    ),
    (
        "per_joint_key_not_twist_joint",
        put("rotation_extraction", {"default": "local_x_euler", "per_procedural_joint": {"LeftHand": "local_x_euler"}}),
        f"{PER_JOINT}.LeftHand",
        "unknown twist joint 'LeftHand'",
    ),
    (
        "rotation_extraction_missing_default",
        put("rotation_extraction", {"per_procedural_joint": {}}),
        "rotation_extraction.default",
        "missing required key 'default'",
    ),
    ("degenerate_start_equals_end", put("segments[0].end", "LeftForeArm"), "segments[0].end", "degenerate segment"),
    ("degenerate_no_twist_joints", put("segments[1].twist_joints", []), "segments[1].twist_joints", "degenerate"),
    ("no_segments", put("segments", []), "segments", "non-empty"),
    (
        "rotation_entry_outside_driver",
        put(f"{ROT}.columns[0]", "LeftForeArm"),
        f"{ROT}.columns[0]",
        "outside the driver column 'LeftHand' of segment 'LeftForeArm'",
    ),
    (
        "reverse_rotation_entry_in_end_column",
        put(f"{ROT}.columns[3]", "LeftForeArm"),
        f"{ROT}.columns[3]",
        "outside the driver column 'LeftArm'",
    ),
    (
        "translation_not_summing_to_one",
        put(f"{TRANS}.values[0]", 0.5),
        f"{TRANS}.rows[0]",
        f"weights of twist joint '{FOREARM[0]}' sum to",
    ),
    (
        "translation_foreign_column",
        put(f"{TRANS}.columns[0]", "Hips"),
        f"{TRANS}.columns[0]",
        "references neither start 'LeftForeArm' nor end 'LeftHand'",
    ),
    (
        "translation_weight_out_of_range",
        chain(put(f"{TRANS}.values[0]", 1.5), put(f"{TRANS}.values[1]", -0.5)),
        f"{TRANS}.values[0]",
        "expected a weight in [0, 1], got 1.5",
    ),
    ("non_finite_nan", put(f"{ROT}.values[0]", float("nan")), f"{ROT}.values[0]", "got number nan"),
    ("non_finite_inf", put(f"{TRANS}.values[1]", -math.inf), f"{TRANS}.values[1]", "got number -inf"),
    ("non_finite_huge_int", put(f"{ROT}.values[2]", 10**400), f"{ROT}.values[2]", "finite number"),
    # 1e40 is finite in float64 but inf in float32 (the format's dtype): NaN twists when posed.
    ("rotation_value_overflows_float32", put(f"{ROT}.values[3]", 1e40), f"{ROT}.values[3]", "in [-10, 10], got 1e+40"),
    ("rotation_value_out_of_range", put(f"{ROT}.values[0]", -10.5), f"{ROT}.values[0]", "twist share in [-10, 10]"),
    ("value_bool", put(f"{ROT}.values[1]", True), f"{ROT}.values[1]", "got boolean True"),
    ("value_string", put(f"{ROT}.values[1]", "0.5"), f"{ROT}.values[1]", "got string '0.5'"),
    (
        "wrong_evaluation_order",
        lambda d: d["evaluation_order"].reverse(),
        "evaluation_order",
        "got array ['skinning'",
    ),
    (
        "joint_count_mismatch",
        put("template_asset.joint_count", 102),
        "template_asset.joint_count",
        "expected 84 (78 main joints + 6 twist joints), got 102",
    ),
    ("joint_count_bool", put("template_asset.joint_count", True), "template_asset.joint_count", "got boolean True"),
    ("lengths_values", lambda d: d["parameter_matrices"]["rotation"]["values"].pop(), f"{ROT}.values", "got 5"),
    ("lengths_columns", lambda d: d["parameter_matrices"]["translation"]["columns"].pop(), f"{TRANS}.columns", "got"),
    ("unknown_top_level_key", put("comment", "hi"), "comment", "unknown key 'comment'"),
    ("unknown_nested_key", put("segments[0].color", "red"), "segments[0].color", "unknown key 'color'"),
    (
        "unknown_extractor_key",
        put("channel_extractors.local_x_euler.gain", 2),
        "channel_extractors.local_x_euler.gain",
        "gain",
    ),
    ("name_with_space", put("segments[0].name", "Left ForeArm"), "segments[0].name", "'Left ForeArm'"),
]


@pytest.mark.parametrize(("mutate", "path", "fragment"), [c[1:] for c in CASES], ids=[c[0] for c in CASES])
def test_each_rule_raises_with_path(mutate, path, fragment):
    d = valid_sidecar()
    mutate(d)
    with pytest.raises(ProceduralFormatError) as info:
        parse(d)
    err = info.value
    assert err.path == path
    assert str(err).startswith(f"{path}: ")
    assert fragment in str(err)


@pytest.mark.parametrize("obj", [None, [], "sidecar", 3, True], ids=repr)
def test_document_of_wrong_type(obj):
    with pytest.raises(ProceduralFormatError, match=r"^\$: expected an object") as info:
        parse(obj)
    assert info.value.path == "$"


@pytest.mark.parametrize(
    ("text", "fragment"),
    [
        ('{"schema_version": "1.0.0",', "invalid JSON"),
        ("", "invalid JSON"),
        ("[" * 100_000, "invalid JSON"),
        (json.dumps(valid_sidecar()).replace("0.3333333333333333", "NaN", 1), "NaN"),
        (json.dumps(valid_sidecar()).replace("0.3333333333333333", "-Infinity", 1), "Infinity"),
    ],
    ids=["truncated", "empty", "too_deep", "nan_literal", "infinity_literal"],
)
def test_load_rejects_invalid_json(tmp_path, text, fragment):
    path = tmp_path / "bad.json"
    path.write_text(text, encoding="utf-8")
    with pytest.raises(ProceduralFormatError) as info:
        load(path)
    assert info.value.path == "$" and fragment in str(info.value)


def test_load_rejects_non_utf8(tmp_path):
    path = tmp_path / "bad.json"
    path.write_bytes(b'{"schema_version": "\xff"}')
    with pytest.raises(ProceduralFormatError, match=r"^\$: invalid JSON"):
        load(path)


# --------------------------------------------------------------------------- properties

_KEYS = sorted({k for k in json.dumps(valid_sidecar(True)).split('"') if k.isidentifier()})
json_values = st.recursive(
    st.none() | st.booleans() | st.integers() | st.floats() | st.text(max_size=12),
    lambda children: (
        st.lists(children, max_size=4)
        | st.dictionaries(st.sampled_from(_KEYS) | st.text(max_size=8), children, max_size=4)
    ),
    max_leaves=20,
)


def _expect_format_error_or_valid(obj: object) -> None:
    """Parse ``obj``: either a ProceduralFormatError, or a definition that round-trips and fits the schema."""
    try:
        d = parse(obj)
    except ProceduralFormatError as err:
        assert str(err).startswith(f"{err.path}: ")
        return
    assert parse(d.to_dict()) == d
    VALIDATOR.validate(obj)


@settings(max_examples=200, deadline=None)
@given(json_values)
def test_arbitrary_json_raises_only_format_errors(obj):
    _expect_format_error_or_valid(obj)


@settings(max_examples=200, deadline=None)
@given(st.dictionaries(st.sampled_from(list(valid_sidecar())), json_values, max_size=10))
def test_arbitrary_top_level_values_raise_only_format_errors(obj):
    _expect_format_error_or_valid(obj)


def _paths(node: Any, prefix: tuple[Any, ...] = ()) -> list[tuple[Any, ...]]:
    items = node.items() if isinstance(node, dict) else enumerate(node) if isinstance(node, list) else ()
    out = []
    for key, child in items:
        out.append((*prefix, key))
        out.extend(_paths(child, (*prefix, key)))
    return out


_VALID = {False: valid_sidecar(), True: valid_sidecar(per_joint=True)}
_PATHS = {k: _paths(v) for k, v in _VALID.items()}


@settings(max_examples=200, deadline=None)
@given(st.booleans(), st.data(), st.sampled_from(["delete", "replace", "duplicate"]), json_values)
def test_mutated_sidecar_parses_or_raises_format_error(per_joint, data, op, value):
    d = copy.deepcopy(_VALID[per_joint])
    path = data.draw(st.sampled_from(_PATHS[per_joint]))
    parent = d
    for step in path[:-1]:
        parent = parent[step]
    key = path[-1]
    if op == "delete":
        del parent[key]
    elif op == "duplicate" and isinstance(parent, list):
        parent.insert(key, copy.deepcopy(parent[key]))
    else:
        parent[key] = value
    _expect_format_error_or_valid(d)
