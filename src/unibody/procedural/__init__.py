"""Procedural twist joints (paper 001): the sidecar format and, built on it, the twist evaluator."""

from .expand import collapse_rig, expand_rig
from .extract import EXTRACTORS, twist_channel
from .format import (
    AXES,
    EVALUATION_ORDER,
    SOURCE_ROTATION,
    SUPPORTED_MODES,
    ChannelExtractor,
    Conventions,
    ParameterMatrix,
    ProceduralDefinition,
    ProceduralFormatError,
    PublicRigDerivation,
    RotationExtraction,
    Segment,
    TemplateAsset,
    load,
    parse,
    schema,
)
from .twist import ProceduralTwist, canonical_definition

__all__ = [
    "AXES",
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
    "EXTRACTORS",
    "ProceduralTwist",
    "canonical_definition",
    "collapse_rig",
    "expand_rig",
    "twist_channel",
]
