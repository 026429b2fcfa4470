"""The procedural twist sidecar (``unibody.procedural/1``): parse and validate, nothing else.

The sidecar (paper 001, ``docs/procedural.md``) declares generated twist joints, how their
angles are extracted from the public pose and how the expanded rig collapses back to the 78
public joints. :func:`parse` checks every rule of the spec before building anything and
raises :class:`ProceduralFormatError` naming the JSON path of the offending entry, e.g.
``segments[2].sign: expected 1 or -1, got 0``. Names are not resolved against the canonical
rig here; that happens when the definition is compiled.

Pure Python on purpose: no torch, so tools and tests can read sidecars cheaply.
"""

from __future__ import annotations

import json
import math
import os
import re
import reprlib
from dataclasses import dataclass
from importlib import resources
from typing import Any

__all__ = [
    "AXES",
    "AXIS_CONVENTIONS",
    "CONVENTIONS",
    "MATRIX_META",
    "POLICIES",
    "EVALUATION_ORDER",
    "SOURCE_ROTATION",
    "SUPPORTED_MODES",
    "ChannelExtractor",
    "Conventions",
    "ParameterMatrix",
    "ProceduralDefinition",
    "ProceduralFormatError",
    "PublicRigDerivation",
    "RotationExtraction",
    "Segment",
    "TemplateAsset",
    "load",
    "parse",
    "schema",
]

SUPPORTED_MODES = ("local_x_euler", "local_x_swing_twist", "aligned_x_swing_twist")
EVALUATION_ORDER = (
    "extract_channels",
    "twist_angles",
    "twist_rotations",
    "twist_translations",
    "forward_kinematics",
    "skinning",
)
AXES = ("x", "y", "z")
SOURCE_ROTATION = {
    "local_x_euler": "absolute_local",
    "local_x_swing_twist": "absolute_local",
    "aligned_x_swing_twist": "world",
}
"""The rotation each extraction mode reads: ``local_*`` the absolute local one, ``aligned_*`` world."""
CHANNEL_AXIS = "x"
CHANNEL_REFERENCE = "bind"
SUPPORTED_MAJOR = 1
MATRIX_NAMES = ("rotation", "translation")
TRANSLATION_TOLERANCE = 1e-5
ROTATION_VALUE_LIMIT = 10.0
"""Bound on ``|value|`` of a rotation-matrix entry: the share of its driver's twist a twist joint
takes (the shipped sidecar uses 1/3 to 1). Ten times the driver's twist is no twist distribution;
the bound also keeps every value finite in float32 (the format's dtype: 1e40 would be inf) and
every twist angle below 10 pi, so posing stays finite in either dtype."""

CONVENTIONS = {
    "units": "meters",
    "angle_units": "radians",
    "dtype": "float32",
    "matrix_layout": "row_major",
    "rotation_handedness": "right",
    "euler_order": "XYZ",
    "quaternion_order": "xyzw",
}
AXIS_CONVENTIONS = {"up": "+Y", "forward": "+Z", "bone": "+X"}
POLICIES = {
    "removed_joint_parent_policy": "nearest_kept_ancestor",
    "skin_weight_aggregation_policy": "add_to_nearest_kept_ancestor",
}
MATRIX_META = {"format": "coo", "dtype": "float32", "row_space": "procedural_joints", "column_space": "public_joints"}
_TOP_KEYS = (
    "schema_version",
    "modes",
    "template_asset",
    "conventions",
    "public_rig_derivation",
    "channel_extractors",
    "rotation_extraction",
    "segments",
    "parameter_matrices",
    "evaluation_order",
)
_SEMVER = re.compile(r"(0|[1-9][0-9]*)\.(0|[1-9][0-9]*)\.(0|[1-9][0-9]*)(-[0-9A-Za-z.-]+)?(\+[0-9A-Za-z.-]+)?")
_NAME = re.compile(r"\S+")


class _Repr(reprlib.Repr):
    """A bounded repr for error messages, safe for any decoded JSON value."""

    def repr_int(self, x: int, level: int) -> str:
        # builtin repr refuses integers above 4300 digits (and would be useless in a message)
        return f"<{x.bit_length()}-bit integer>" if x.bit_length() > 256 else super().repr_int(x, level)


_REPR = _Repr()
_KINDS = {
    type(None): "null",
    bool: "boolean",
    int: "integer",
    float: "number",
    str: "string",
    list: "array",
    dict: "object",
}
_REPR.maxstring = _REPR.maxother = 60
_REPR.maxlist = _REPR.maxdict = 4
_REPR.maxlevel = 2


class ProceduralFormatError(ValueError):
    """A sidecar that breaks the format; ``path`` is the JSON path of the offending entry.

    Attributes:
        path: where the problem is, e.g. ``segments[2].sign`` or ``$`` for the whole document.
    """

    def __init__(self, path: str, message: str) -> None:
        super().__init__(f"{path}: {message}")
        self.path = path
        self.detail = message

    def __reduce__(self) -> tuple[Any, ...]:
        return (type(self), (self.path, self.detail))


# --------------------------------------------------------------------------- the definition


@dataclass(frozen=True, slots=True)
class TemplateAsset:
    """Identity of the template rig the sidecar targets; ``joint_count`` counts public + twist joints."""

    name: str
    version: str
    source: str
    joint_count: int


@dataclass(frozen=True, slots=True)
class Conventions:
    """Units, dtype and axis conventions; version 1 admits exactly one value for each."""

    units: str
    angle_units: str
    dtype: str
    matrix_layout: str
    rotation_handedness: str
    euler_order: str
    quaternion_order: str
    up_axis: str
    forward_axis: str
    bone_axis: str


@dataclass(frozen=True, slots=True)
class PublicRigDerivation:
    """How the expanded rig collapses to the public joints (named here, in canonical order)."""

    main_joint_names: tuple[str, ...]
    removed_joint_parent_policy: str
    skin_weight_aggregation_policy: str


@dataclass(frozen=True, slots=True)
class ChannelExtractor:
    """What extraction ``mode`` reads: ``source_rotation`` about ``axis``, relative to ``reference``."""

    mode: str
    source_rotation: str
    axis: str
    reference: str
    description: str = ""


@dataclass(frozen=True, slots=True)
class RotationExtraction:
    """The extraction mode per twist joint: ``default`` unless overridden in ``per_procedural_joint``.

    Attributes:
        default: mode used by every twist joint without an override.
        per_procedural_joint: ``(twist_joint, mode)`` overrides.
        as_string: the sidecar gave the policy as a plain mode string (kept for :meth:`to_dict`).
    """

    default: str
    per_procedural_joint: tuple[tuple[str, str], ...] = ()
    as_string: bool = False

    def mode_of(self, joint: str) -> str:
        """Return the extraction mode of twist joint ``joint``."""
        return dict(self.per_procedural_joint).get(joint, self.default)

    def to_dict(self) -> str | dict[str, Any]:
        """Return the JSON form: the plain string when given so, else the object form."""
        if self.as_string and not self.per_procedural_joint:
            return self.default
        return {"default": self.default, "per_procedural_joint": dict(self.per_procedural_joint)}


@dataclass(frozen=True, slots=True)
class Segment:
    """A bone ``start -> end`` with generated twist joints, all parented to ``start``.

    Attributes:
        reverse_compensation: the segment is driven by ``start`` (its inherited twist is
            compensated) instead of ``end``.
        source_axis: local axis of the twist rotation, one of :data:`AXES`.
        sign: 1 or -1, applied to the twist angle.
    """

    name: str
    start: str
    end: str
    twist_joints: tuple[str, ...]
    reverse_compensation: bool
    source_axis: str
    sign: int

    @property
    def driver(self) -> str:
        """The public joint whose channel drives the segment (its rotation-matrix column)."""
        return self.start if self.reverse_compensation else self.end

    def to_dict(self) -> dict[str, Any]:
        """Return the JSON form."""
        return {
            "name": self.name,
            "start": self.start,
            "end": self.end,
            "twist_joints": list(self.twist_joints),
            "reverse_compensation": self.reverse_compensation,
            "source_axis": self.source_axis,
            "sign": self.sign,
        }


@dataclass(frozen=True, slots=True)
class ParameterMatrix:
    """A sparse COO matrix over twist joints (rows) and public joints (columns)."""

    name: str
    format: str
    dtype: str
    row_space: str
    column_space: str
    rows: tuple[str, ...]
    columns: tuple[str, ...]
    values: tuple[float, ...]

    def to_dict(self) -> dict[str, Any]:
        """Return the JSON form (without the name, which is its key in ``parameter_matrices``)."""
        return {
            "format": self.format,
            "dtype": self.dtype,
            "row_space": self.row_space,
            "column_space": self.column_space,
            "rows": list(self.rows),
            "columns": list(self.columns),
            "values": list(self.values),
        }


@dataclass(frozen=True, slots=True)
class ProceduralDefinition:
    """A validated sidecar. Build it with :func:`parse` or :func:`load`, write it with :meth:`to_dict`."""

    schema_version: str
    modes: tuple[str, ...]
    template_asset: TemplateAsset
    conventions: Conventions
    public_rig_derivation: PublicRigDerivation
    channel_extractors: tuple[ChannelExtractor, ...]
    rotation_extraction: RotationExtraction
    segments: tuple[Segment, ...]
    rotation: ParameterMatrix
    translation: ParameterMatrix
    evaluation_order: tuple[str, ...]

    @property
    def main_joint_names(self) -> tuple[str, ...]:
        """The public joints, canonical order."""
        return self.public_rig_derivation.main_joint_names

    @property
    def twist_joints(self) -> tuple[str, ...]:
        """All generated twist joints, in segment order (their order in the expanded rig)."""
        return tuple(joint for segment in self.segments for joint in segment.twist_joints)

    def segment_of(self, twist_joint: str) -> Segment:
        """Return the segment that generates ``twist_joint``; ValueError if there is none."""
        for segment in self.segments:
            if twist_joint in segment.twist_joints:
                return segment
        raise ValueError(f"twist_joint: unknown twist joint {twist_joint!r}")

    def to_dict(self) -> dict[str, Any]:
        """Return the JSON form; ``parse(d.to_dict()) == d``."""
        c = self.conventions
        derivation = self.public_rig_derivation
        extractors: dict[str, Any] = {}
        for e in self.channel_extractors:
            extractors[e.mode] = {"source_rotation": e.source_rotation, "axis": e.axis, "reference": e.reference}
            if e.description:
                extractors[e.mode]["description"] = e.description
        return {
            "schema_version": self.schema_version,
            "modes": list(self.modes),
            "template_asset": {
                "name": self.template_asset.name,
                "version": self.template_asset.version,
                "source": self.template_asset.source,
                "joint_count": self.template_asset.joint_count,
            },
            "conventions": {
                "units": c.units,
                "angle_units": c.angle_units,
                "dtype": c.dtype,
                "matrix_layout": c.matrix_layout,
                "rotation_handedness": c.rotation_handedness,
                "euler_order": c.euler_order,
                "quaternion_order": c.quaternion_order,
                "axes": {"up": c.up_axis, "forward": c.forward_axis, "bone": c.bone_axis},
            },
            "public_rig_derivation": {
                "main_joint_names": list(derivation.main_joint_names),
                "removed_joint_parent_policy": derivation.removed_joint_parent_policy,
                "skin_weight_aggregation_policy": derivation.skin_weight_aggregation_policy,
            },
            "channel_extractors": extractors,
            "rotation_extraction": self.rotation_extraction.to_dict(),
            "segments": [s.to_dict() for s in self.segments],
            "parameter_matrices": {"rotation": self.rotation.to_dict(), "translation": self.translation.to_dict()},
            "evaluation_order": list(self.evaluation_order),
        }


# --------------------------------------------------------------------------- entry points


def parse(obj: object) -> ProceduralDefinition:
    """Validate a decoded sidecar (``json.load`` output) and return its definition.

    Raises:
        ProceduralFormatError: for any violation of the format, whatever ``obj`` is.
    """
    top = _object(obj, "$", _TOP_KEYS)
    version = _schema_version(top["schema_version"])
    modes = _modes(top["modes"])
    template = _template_asset(top["template_asset"])
    conventions = _conventions(top["conventions"])
    derivation = _derivation(top["public_rig_derivation"])
    extractors = _extractors(top["channel_extractors"], modes)
    segments = _segments(top["segments"], set(derivation.main_joint_names))
    owner = {joint: seg for seg in segments for joint in seg.twist_joints}
    policy = _rotation_extraction(top["rotation_extraction"], modes, owner)
    rotation, translation = _matrices(top["parameter_matrices"], owner, set(derivation.main_joint_names))
    order = _evaluation_order(top["evaluation_order"])
    expected = len(derivation.main_joint_names) + len(owner)
    if template.joint_count != expected:
        raise ProceduralFormatError(
            "template_asset.joint_count",
            f"expected {expected} ({len(derivation.main_joint_names)} main joints + {len(owner)} twist joints), "
            f"got {_REPR.repr(template.joint_count)}",
        )
    return ProceduralDefinition(
        version, modes, template, conventions, derivation, extractors, policy, segments, rotation, translation, order
    )


def load(path: str | os.PathLike[str]) -> ProceduralDefinition:
    """Read and validate a sidecar file (UTF-8 JSON; ``NaN``/``Infinity`` literals are rejected).

    Raises:
        ProceduralFormatError: with path ``$`` when the file is not valid JSON, else as :func:`parse`.
        OSError: when the file cannot be read.
    """
    try:
        with open(path, encoding="utf-8") as f:
            obj = json.load(f, parse_constant=_reject_constant)
    except (ValueError, RecursionError) as e:  # JSONDecodeError and UnicodeDecodeError are ValueErrors
        raise ProceduralFormatError("$", f"invalid JSON in {os.fspath(path)!r}: {e}") from None
    return parse(obj)


def schema() -> dict[str, Any]:
    """Return the JSON Schema (draft 2020-12) of the structure; cross-references are :func:`parse`'s job."""
    return json.loads(resources.files("unibody.procedural").joinpath("schema.json").read_text(encoding="utf-8"))


def _reject_constant(name: str) -> float:
    raise ValueError(f"non-finite number {name} is not allowed")


# --------------------------------------------------------------------------- generic checks


def _key(path: str, key: object) -> str:
    name = key if isinstance(key, str) else _REPR.repr(key)
    return name if path == "$" else f"{path}.{name}"


def _got(value: object) -> str:
    """The JSON kind and a bounded repr of ``value``, e.g. ``integer 7`` or ``array ['meters']``."""
    return f"{_KINDS.get(type(value), type(value).__name__)} {_REPR.repr(value)}"


def _object(value: object, path: str, required: tuple[str, ...], optional: tuple[str, ...] = ()) -> dict[str, Any]:
    """An object with exactly the ``required`` keys plus any of the ``optional`` ones."""
    _mapping(value, path)
    for key in required:
        if key not in value:
            raise ProceduralFormatError(_key(path, key), f"missing required key {key!r}")
    for key in value:
        if key not in required and key not in optional:
            allowed = ", ".join(required + optional)
            raise ProceduralFormatError(_key(path, key), f"unknown key {_REPR.repr(key)}; expected {allowed}")
    return value


def _mapping(value: object, path: str) -> dict[Any, Any]:
    if not isinstance(value, dict):
        raise ProceduralFormatError(path, f"expected an object, got {_got(value)}")
    return value


def _list(value: object, path: str, *, nonempty: bool = False) -> list[Any]:
    if not isinstance(value, list):
        raise ProceduralFormatError(path, f"expected an array, got {_got(value)}")
    if nonempty and not value:
        raise ProceduralFormatError(path, "expected a non-empty array, got []")
    return value


def _text(value: object, path: str) -> str:
    if not isinstance(value, str) or not value:
        raise ProceduralFormatError(path, f"expected a non-empty string, got {_got(value)}")
    return value


def _name(value: object, path: str) -> str:
    if not isinstance(value, str) or not _NAME.fullmatch(value):
        raise ProceduralFormatError(path, f"expected a name (non-empty, no whitespace), got {_got(value)}")
    return value


def _const(value: object, path: str, expected: str) -> str:
    if not isinstance(value, str) or value != expected:
        raise ProceduralFormatError(path, f"expected {expected!r}, got {_got(value)}")
    return value


def _choice(value: object, path: str, options: tuple[str, ...], what: str) -> str:
    if not isinstance(value, str) or value not in options:
        raise ProceduralFormatError(path, f"invalid {what} {_REPR.repr(value)}; expected one of {', '.join(options)}")
    return value


def _number(value: object, path: str) -> float:
    if isinstance(value, (int, float)) and not isinstance(value, bool):
        try:
            x = float(value)
        except OverflowError:
            x = math.inf
        if math.isfinite(x):
            return x
    raise ProceduralFormatError(path, f"expected a finite number, got {_got(value)}")


def _names(value: object, path: str, what: str) -> tuple[str, ...]:
    """A non-empty array of distinct names."""
    items = _list(value, path, nonempty=True)
    seen: set[str] = set()
    for i, item in enumerate(items):
        _name(item, f"{path}[{i}]")
        if item in seen:
            raise ProceduralFormatError(f"{path}[{i}]", f"duplicate {what} {item!r}")
        seen.add(item)
    return tuple(items)


# --------------------------------------------------------------------------- sections


def _schema_version(value: object) -> str:
    if not isinstance(value, str) or not _SEMVER.fullmatch(value):
        raise ProceduralFormatError(
            "schema_version", f"expected a semantic version MAJOR.MINOR.PATCH, got {_got(value)}"
        )
    major = int(value.split(".", 1)[0])
    if major != SUPPORTED_MAJOR:
        raise ProceduralFormatError(
            "schema_version", f"unsupported major version {major} in {value!r}; supported: {SUPPORTED_MAJOR}"
        )
    return value


def _modes(value: object) -> tuple[str, ...]:
    items = _list(value, "modes", nonempty=True)
    for i, mode in enumerate(items):
        _choice(mode, f"modes[{i}]", SUPPORTED_MODES, "mode")
        if mode in items[:i]:
            raise ProceduralFormatError(f"modes[{i}]", f"duplicate mode {mode!r}")
    return tuple(items)


def _template_asset(value: object) -> TemplateAsset:
    d = _object(value, "template_asset", ("name", "version", "source", "joint_count"))
    count = d["joint_count"]
    if not isinstance(count, int) or isinstance(count, bool) or count < 1:
        raise ProceduralFormatError("template_asset.joint_count", f"expected a positive integer, got {_got(count)}")
    fields = [_text(d[k], f"template_asset.{k}") for k in ("name", "version", "source")]
    return TemplateAsset(*fields, joint_count=count)


def _conventions(value: object) -> Conventions:
    d = _object(value, "conventions", (*CONVENTIONS, "axes"))
    for key, expected in CONVENTIONS.items():
        _const(d[key], f"conventions.{key}", expected)
    axes = _object(d["axes"], "conventions.axes", tuple(AXIS_CONVENTIONS))
    for key, expected in AXIS_CONVENTIONS.items():
        _const(axes[key], f"conventions.axes.{key}", expected)
    return Conventions(*(d[k] for k in CONVENTIONS), axes["up"], axes["forward"], axes["bone"])


def _derivation(value: object) -> PublicRigDerivation:
    path = "public_rig_derivation"
    d = _object(value, path, ("main_joint_names", *POLICIES))
    names = _names(d["main_joint_names"], f"{path}.main_joint_names", "main joint name")
    for key, expected in POLICIES.items():
        _const(d[key], f"{path}.{key}", expected)
    return PublicRigDerivation(names, *(d[k] for k in POLICIES))


def _extractors(value: object, modes: tuple[str, ...]) -> tuple[ChannelExtractor, ...]:
    d = _mapping(value, "channel_extractors")
    for mode in d:
        if mode not in modes:
            declared = ", ".join(modes)
            raise ProceduralFormatError(
                _key("channel_extractors", mode),
                f"extractor for undeclared mode {_REPR.repr(mode)}; declared: {declared}",
            )
    extractors = []
    for mode in modes:
        path = f"channel_extractors.{mode}"
        if mode not in d:
            raise ProceduralFormatError(path, f"missing extractor for declared mode {mode!r}")
        e = _object(d[mode], path, ("source_rotation", "axis", "reference"), ("description",))
        source = e["source_rotation"]
        if not isinstance(source, str) or source != SOURCE_ROTATION[mode]:
            raise ProceduralFormatError(
                f"{path}.source_rotation", f"expected {SOURCE_ROTATION[mode]!r} for mode {mode!r}, got {_got(source)}"
            )
        _const(e["axis"], f"{path}.axis", CHANNEL_AXIS)
        _const(e["reference"], f"{path}.reference", CHANNEL_REFERENCE)
        description = e.get("description", "")
        if not isinstance(description, str):
            raise ProceduralFormatError(f"{path}.description", f"expected a string, got {_got(description)}")
        extractors.append(ChannelExtractor(mode, source, e["axis"], e["reference"], description))
    return tuple(extractors)


def _segments(value: object, main: set[str]) -> tuple[Segment, ...]:
    keys = ("name", "start", "end", "twist_joints", "reverse_compensation", "source_axis", "sign")
    segments: list[Segment] = []
    where: dict[str, str] = {}  # twist joint -> path of its declaration
    for i, item in enumerate(_list(value, "segments", nonempty=True)):
        path = f"segments[{i}]"
        d = _object(item, path, keys)
        name = _name(d["name"], f"{path}.name")
        if any(s.name == name for s in segments):
            raise ProceduralFormatError(f"{path}.name", f"duplicate segment name {name!r}")
        for key in ("start", "end"):
            joint = _name(d[key], f"{path}.{key}")
            if joint not in main:
                raise ProceduralFormatError(
                    f"{path}.{key}", f"unknown joint {joint!r}; not in public_rig_derivation.main_joint_names"
                )
        if d["start"] == d["end"]:
            raise ProceduralFormatError(f"{path}.end", f"degenerate segment: end equals start {d['end']!r}")
        twists = _list(d["twist_joints"], f"{path}.twist_joints")
        if not twists:
            raise ProceduralFormatError(f"{path}.twist_joints", "degenerate segment: expected at least one twist joint")
        for k, joint in enumerate(twists):
            at = f"{path}.twist_joints[{k}]"
            _name(joint, at)
            if joint in main:
                raise ProceduralFormatError(at, f"twist joint {joint!r} is named like a main joint")
            if joint in where:
                raise ProceduralFormatError(at, f"duplicate twist joint {joint!r}, already declared at {where[joint]}")
            where[joint] = at
        reverse = d["reverse_compensation"]
        if not isinstance(reverse, bool):
            raise ProceduralFormatError(f"{path}.reverse_compensation", f"expected true or false, got {_got(reverse)}")
        axis = _choice(d["source_axis"], f"{path}.source_axis", AXES, "axis")
        sign = d["sign"]
        if type(sign) is not int or sign not in (1, -1):
            raise ProceduralFormatError(f"{path}.sign", f"expected 1 or -1, got {_REPR.repr(sign)}")
        segments.append(Segment(name, d["start"], d["end"], tuple(twists), reverse, axis, sign))
    return tuple(segments)


def _declared_mode(value: object, path: str, modes: tuple[str, ...]) -> str:
    if isinstance(value, str) and value in SUPPORTED_MODES and value not in modes:
        raise ProceduralFormatError(path, f"mode {value!r} is not declared in modes ({', '.join(modes)})")
    return _choice(value, path, modes, "extraction mode")


def _rotation_extraction(value: object, modes: tuple[str, ...], owner: dict[str, Segment]) -> RotationExtraction:
    path = "rotation_extraction"
    if isinstance(value, str):
        return RotationExtraction(_declared_mode(value, path, modes), as_string=True)
    if not isinstance(value, dict):
        raise ProceduralFormatError(path, f"expected a mode string or an object, got {_got(value)}")
    d = _object(value, path, ("default",), ("per_procedural_joint",))
    default = _declared_mode(d["default"], f"{path}.default", modes)
    overrides = _mapping(d.get("per_procedural_joint", {}), f"{path}.per_procedural_joint")
    for joint, mode in overrides.items():
        at = _key(f"{path}.per_procedural_joint", joint)
        if joint not in owner:
            raise ProceduralFormatError(at, f"unknown twist joint {_REPR.repr(joint)}")
        _declared_mode(mode, at, modes)
    ordered = tuple((joint, overrides[joint]) for joint in owner if joint in overrides)  # segment order
    return RotationExtraction(default, ordered)


def _matrices(value: object, owner: dict[str, Segment], main: set[str]) -> tuple[ParameterMatrix, ParameterMatrix]:
    d = _mapping(value, "parameter_matrices")
    for name in d:
        if name not in MATRIX_NAMES:
            raise ProceduralFormatError(
                _key("parameter_matrices", name),
                f"unknown matrix name {_REPR.repr(name)}; expected rotation, translation",
            )
    _object(d, "parameter_matrices", MATRIX_NAMES)
    return _rotation(_matrix(d, "rotation", owner, main), owner), _translation(
        _matrix(d, "translation", owner, main), owner
    )


def _matrix(d: dict[str, Any], name: str, owner: dict[str, Segment], main: set[str]) -> ParameterMatrix:
    """Types, metadata, lengths, known rows and columns, no duplicate entries."""
    path = f"parameter_matrices.{name}"
    m = _object(d[name], path, (*MATRIX_META, "rows", "columns", "values"))
    for key, expected in MATRIX_META.items():
        _const(m[key], f"{path}.{key}", expected)
    rows = _list(m["rows"], f"{path}.rows")
    columns = _list(m["columns"], f"{path}.columns")
    values = _list(m["values"], f"{path}.values")
    for key, items in (("columns", columns), ("values", values)):
        if len(items) != len(rows):
            raise ProceduralFormatError(
                f"{path}.{key}", f"expected {len(rows)} entries (one per entry of rows), got {len(items)}"
            )
    first: dict[tuple[str, str], int] = {}
    for i, (row, column) in enumerate(zip(rows, columns, strict=True)):
        if _name(row, f"{path}.rows[{i}]") not in owner:
            raise ProceduralFormatError(f"{path}.rows[{i}]", f"unknown twist joint {row!r}")
        if _name(column, f"{path}.columns[{i}]") not in main:
            raise ProceduralFormatError(f"{path}.columns[{i}]", f"unknown public joint {column!r}")
        if (row, column) in first:
            raise ProceduralFormatError(
                f"{path}.rows[{i}]", f"duplicate entry ({row!r}, {column!r}), first given at index {first[row, column]}"
            )
        first[row, column] = i
    numbers = tuple(_number(v, f"{path}.values[{i}]") for i, v in enumerate(values))
    return ParameterMatrix(name, *(m[k] for k in MATRIX_META), tuple(rows), tuple(columns), numbers)


def _missing_rows(m: ParameterMatrix, owner: dict[str, Segment]) -> None:
    present = set(m.rows)
    for joint in owner:
        if joint not in present:
            raise ProceduralFormatError(f"parameter_matrices.{m.name}.rows", f"twist joint {joint!r} has no entry")


def _rotation(m: ParameterMatrix, owner: dict[str, Segment]) -> ParameterMatrix:
    """Every twist joint has entries, all in its segment's driver column, within the value limit."""
    for i, (row, column, value) in enumerate(zip(m.rows, m.columns, m.values, strict=True)):
        if not abs(value) <= ROTATION_VALUE_LIMIT:
            raise ProceduralFormatError(
                f"parameter_matrices.rotation.values[{i}]",
                f"expected a twist share in [-{ROTATION_VALUE_LIMIT:g}, {ROTATION_VALUE_LIMIT:g}], got {value!r}",
            )
        segment = owner[row]
        if column != segment.driver:
            raise ProceduralFormatError(
                f"parameter_matrices.rotation.columns[{i}]",
                f"entry ({row!r}, {column!r}) lies outside the driver column {segment.driver!r} "
                f"of segment {segment.name!r}",
            )
    _missing_rows(m, owner)
    return m


def _translation(m: ParameterMatrix, owner: dict[str, Segment]) -> ParameterMatrix:
    """Every twist joint has weights in [0, 1] on its segment's start and end only, summing to 1."""
    path = "parameter_matrices.translation"
    totals: dict[str, float] = {}
    first: dict[str, int] = {}
    for i, (row, column, value) in enumerate(zip(m.rows, m.columns, m.values, strict=True)):
        segment = owner[row]
        if column not in (segment.start, segment.end):
            raise ProceduralFormatError(
                f"{path}.columns[{i}]",
                f"entry ({row!r}, {column!r}) references neither start {segment.start!r} nor end {segment.end!r} "
                f"of segment {segment.name!r}",
            )
        if not 0.0 <= value <= 1.0:
            raise ProceduralFormatError(f"{path}.values[{i}]", f"expected a weight in [0, 1], got {value!r}")
        totals[row] = totals.get(row, 0.0) + value
        first.setdefault(row, i)
    _missing_rows(m, owner)
    for row, total in totals.items():
        if abs(total - 1.0) > TRANSLATION_TOLERANCE:
            raise ProceduralFormatError(
                f"{path}.rows[{first[row]}]", f"weights of twist joint {row!r} sum to {total!r}, expected 1"
            )
    return m


def _evaluation_order(value: object) -> tuple[str, ...]:
    if not isinstance(value, list) or tuple(value) != EVALUATION_ORDER:
        raise ProceduralFormatError("evaluation_order", f"expected {list(EVALUATION_ORDER)}, got {_got(value)}")
    return EVALUATION_ORDER
