"""Marker layouts: named optical markers on the canonical mesh (paper 003 §4.4, eq. 5).

A marker sits ``distance`` metres from the skin along the vertex normal of its canonical
vertex: ``X = v[vertex] + n[vertex] * distance``. Layouts are JSON files::

    {"format": "unibody.marker_layout/1", "name": "pig39", "topology": "canonical",
     "markers": {"LFHD": {"vertex": 1234, "distance": 0.0095}, ...}}

Shipped layouts (``mocap/data/layouts``): ``pig35`` and ``pig39`` (Vicon Plug-in Gait full
body, without / with the upper-arm and forearm markers), ``cmu41`` (the CMU mocap set) and
``superset`` (their union, for label priming). They are built from anatomical rules by
``scripts/make_marker_layouts.py``; :func:`unibody.mocap.solve.derive_layout` builds one
from a single labelled frame of a new dataset instead.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from importlib import resources
from pathlib import Path

import torch

from .._checks import check_shape
from ..geometry import mesh
from ..io.atomic import atomic_write
from ..topology import CANONICAL_VERTICES

__all__ = [
    "LAYOUT_FORMAT",
    "MAX_MARKER_DISTANCE",
    "MarkerLayout",
    "available_layouts",
    "place_markers",
    "vertex_normals",
]

LAYOUT_FORMAT = "unibody.marker_layout/1"
MAX_MARKER_DISTANCE = 0.2
"""Metres: the farthest a layout's marker may sit from the skin (shipped markers: 9.5 mm; cluster
plates and derived session markers: a few cm). Farther, it is not a marker on this body."""


def _layout_dir():
    return resources.files("unibody.mocap") / "data" / "layouts"


def available_layouts() -> tuple[str, ...]:
    """Names of the shipped layouts."""
    return tuple(sorted(p.name[: -len(".json")] for p in _layout_dir().iterdir() if p.name.endswith(".json")))


@dataclass(frozen=True)
class MarkerLayout:
    """M named markers on the canonical mesh.

    Attributes:
        name: the layout's name.
        labels: M marker labels.
        vertices: (M,) int64 canonical vertex ids.
        distance: (M,) float32 m, marker centre to skin along the vertex normal.
    """

    name: str
    labels: tuple[str, ...]
    vertices: torch.Tensor
    distance: torch.Tensor

    def __post_init__(self) -> None:
        m = len(self.labels)
        bad = [x for x in self.labels if not isinstance(x, str) or not x or x.startswith("*")]
        if bad:
            raise ValueError(f"labels: expected names that are not empty and do not start with '*', got {bad[0]!r}")
        if len(set(self.labels)) != m:
            dup = sorted({x for x in self.labels if self.labels.count(x) > 1})
            raise ValueError(f"labels: duplicate marker labels {dup}")
        check_shape(self.vertices, "M", name="vertices", sizes={"M": m})
        check_shape(self.distance, "M", name="distance", sizes={"M": m})

    def __len__(self) -> int:
        return len(self.labels)

    def index(self, label: str) -> int:
        """Position of ``label`` in :attr:`labels`."""
        try:
            return self.labels.index(label)
        except ValueError:
            raise ValueError(f"label: {label!r} is not in layout {self.name!r} ({', '.join(self.labels)})") from None

    def subset(self, labels, name: str | None = None) -> MarkerLayout:
        """The layout restricted to ``labels``, in that order."""
        idx = torch.tensor([self.index(x) for x in labels], dtype=torch.long)
        return MarkerLayout(name or self.name, tuple(labels), self.vertices[idx], self.distance[idx])

    @classmethod
    def load(cls, name_or_path: str | Path) -> MarkerLayout:
        """A shipped layout by name (:func:`available_layouts`) or a layout JSON file.

        Raises:
            ValueError: an unknown name, or a file that is not a layout (one line naming the
                file and the field: unreadable, not JSON, another format, no markers, a vertex
                that is not a canonical vertex id, a distance that is not finite or farther
                than :data:`MAX_MARKER_DISTANCE` from the skin, a label that is empty or
                starts with ``*`` (the mark of unlabelled points)).
        """
        p = Path(name_or_path)
        if not (p.suffix == ".json" or p.exists()):
            res = _layout_dir() / f"{name_or_path}.json"
            if not res.is_file():
                raise ValueError(
                    f"layout: unknown layout {str(name_or_path)!r}; shipped: {', '.join(available_layouts())}"
                )
            return cls._parse(res.read_text(), str(name_or_path))
        try:
            text = p.read_bytes().decode("utf-8")
        except OSError as exc:
            raise ValueError(f"{p}: cannot read the layout ({exc.strerror or exc})") from None
        except UnicodeDecodeError:
            raise ValueError(f"{p}: not a layout JSON file (not UTF-8 text)") from None
        return cls._parse(text, str(p))

    @classmethod
    def _parse(cls, text: str, where: str) -> MarkerLayout:
        try:
            data = json.loads(text)
        except json.JSONDecodeError as exc:
            raise ValueError(
                f"{where}: not a layout JSON file ({exc.msg} at line {exc.lineno} column {exc.colno})"
            ) from None
        if not isinstance(data, dict) or data.get("format") != LAYOUT_FORMAT:
            got = data.get("format") if isinstance(data, dict) else f"a JSON {type(data).__name__}"
            raise ValueError(f"{where}: expected a layout (format {LAYOUT_FORMAT!r}), got {got!r}")
        if data.get("topology", "canonical") != "canonical":
            raise ValueError(f"{where}: topology: expected 'canonical', got {data['topology']!r}")
        name, markers = data.get("name"), data.get("markers")
        if not isinstance(name, str) or not name:
            raise ValueError(f"{where}: name: expected a non-empty string, got {name!r}")
        if not isinstance(markers, dict) or not markers:
            raise ValueError(f"{where}: markers: expected an object of one or more markers, got {markers!r:.80}")
        vertices, distance = [], []
        for label, m in markers.items():
            at = f"{where}: markers.{label}"
            if not isinstance(m, dict):
                raise ValueError(f"{at}: expected an object with vertex and distance, got {m!r:.80}")
            v, d = m.get("vertex"), m.get("distance")
            if isinstance(v, bool) or not isinstance(v, int) or not 0 <= v < CANONICAL_VERTICES:
                raise ValueError(
                    f"{at}.vertex: expected a canonical vertex id in 0..{CANONICAL_VERTICES - 1}, got {v!r}"
                )
            if isinstance(d, bool) or not isinstance(d, int | float) or not abs(d) <= MAX_MARKER_DISTANCE:
                raise ValueError(
                    f"{at}.distance: expected metres from the skin within +-{MAX_MARKER_DISTANCE:g}, got {d!r}"
                )
            vertices.append(v)
            distance.append(float(d))
        try:
            return cls(name, tuple(markers), torch.tensor(vertices), torch.tensor(distance, dtype=torch.float32))
        except ValueError as exc:
            raise ValueError(f"{where}: {exc}") from None

    def to_json(self) -> dict:
        markers = {
            x: {"vertex": int(v), "distance": round(float(d), 5)}
            for x, v, d in zip(self.labels, self.vertices, self.distance, strict=True)
        }
        return {"format": LAYOUT_FORMAT, "name": self.name, "topology": "canonical", "markers": markers}

    def save(self, path: str | Path) -> None:
        """Write the layout as JSON."""
        with atomic_write(path, "w") as f:
            f.write(json.dumps(self.to_json(), indent=1) + "\n")


def vertex_normals(vertices: torch.Tensor, faces: torch.Tensor) -> torch.Tensor:
    """Area-weighted unit vertex normals (B, V, 3) of meshes (B, V, 3) with triangles (F, 3).

    :func:`unibody.geometry.mesh.vertex_normals` with the batch checked.
    """
    check_shape(vertices, "B V 3", name="vertices")
    return mesh.vertex_normals(vertices, faces)


def place_markers(
    vertices: torch.Tensor,
    faces: torch.Tensor,
    vertex_ids: torch.Tensor,
    distance: torch.Tensor,
    normals: torch.Tensor | None = None,
) -> torch.Tensor:
    """Markers (B, M, 3) = v[ids] + n[ids] * distance (paper 003 eq. 5).

    Args:
        vertices: (B, V, 3) m, posed meshes.
        faces: (F, 3) triangles.
        vertex_ids: (M,) or (B, M) canonical vertex ids.
        distance: (M,) or (B, M) m, marker-to-skin distance.
        normals: (B, V, 3) precomputed unit normals, optional.
    """
    b = vertices.shape[0]
    n = vertex_normals(vertices, faces) if normals is None else normals
    ids = vertex_ids.to(vertices.device)  # a layout's tensors live on the CPU
    ids = ids.expand(b, -1) if ids.dim() == 1 else ids
    d = distance.to(vertices)
    d = d.expand(b, -1) if d.dim() == 1 else d
    gather = ids[..., None].expand(-1, -1, 3)
    return vertices.gather(1, gather) + n.gather(1, gather) * d[..., None]
