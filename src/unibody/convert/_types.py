"""The options every reader and writer takes, and what a reader returns."""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

from .._checks import check_count
from ..motion import Motion

__all__ = ["ConvertOptions", "Converted"]


@dataclass(frozen=True, slots=True)
class ConvertOptions:
    """Options of one conversion (the same for every file of a run).

    Attributes:
        preset: inversion preset for mesh inputs (:data:`unibody.fitting.inversion.PRESETS`).
        models: folder (or file) of the user's SMPL-family model files, for AMASS inputs.
        template: rest mesh (OBJ / model file / identity file) of a mesh sequence's topology.
        units: length unit of skeletal inputs ("m", "cm", "mm", "in", "ft"), None to detect.
        mapping: JSON file overriding the joint-name correspondence of skeletal inputs.
        batch: frames per batch for posing and inversion.
        dtype: "float32" or "float64" for the solvers.
    """

    preset: str = "analytic"
    models: Path | None = None
    template: Path | None = None
    units: str | None = None
    mapping: Path | None = None
    batch: int = 256
    dtype: str = "float32"

    def __post_init__(self) -> None:
        # Checked when made, so every reader and writer meets them valid (a batch of 0, a preset
        # "best" or a dtype "half" ran, or failed far from here, before).
        from ..fitting.inversion import PRESETS
        from .skeletal import UNITS

        if self.preset not in PRESETS:
            raise ValueError(f"preset: expected one of {', '.join(PRESETS)}, got {self.preset!r}")
        check_count(self.batch, "batch", 1)
        if self.dtype not in ("float32", "float64"):
            raise ValueError(f"dtype: expected float32 or float64, got {self.dtype!r}")
        if self.units is not None and self.units not in UNITS:
            raise ValueError(f"units: expected one of {', '.join(UNITS)} or None (detected), got {self.units!r}")
        for name in ("models", "template", "mapping"):
            value = getattr(self, name)
            if value is not None and not isinstance(value, str | Path):
                raise TypeError(f"{name}: expected a path or None, got {type(value).__name__}")


@dataclass(frozen=True, slots=True)
class Converted:
    """A reader's result: the canonical motion and what the per-file report shows.

    ``stats`` holds plain JSON values, e.g. ``frames``, ``fps``, ``inversion_mean_mm``,
    ``inversion_max_mm``, ``retarget_mean_mm``, timings in seconds (``time_<stage>_s``).
    ``warnings`` are one-line messages about the file.
    """

    motion: Motion
    stats: dict = field(default_factory=dict)
    warnings: tuple[str, ...] = ()
