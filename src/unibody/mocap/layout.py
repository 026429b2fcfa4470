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

__all__ = ["LAYOUT_FORMAT", "MarkerLayout", "available_layouts", "place_markers", "vertex_normals"]

LAYOUT_FORMAT = "unibody.marker_layout/1"


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
        """A shipped layout by name (:func:`available_layouts`) or a layout JSON file."""
        p = Path(name_or_path)
        if p.suffix == ".json" or p.exists():
            text = p.read_text()
        else:
            res = _layout_dir() / f"{name_or_path}.json"
            if not res.is_file():
                raise ValueError(
                    f"layout: unknown layout {str(name_or_path)!r}; shipped: {', '.join(available_layouts())}"
                )
            text = res.read_text()
        data = json.loads(text)
        if data.get("format") != LAYOUT_FORMAT:
            raise ValueError(f"layout {name_or_path}: expected format {LAYOUT_FORMAT!r}, got {data.get('format')!r}")
        markers = data["markers"]
        labels = tuple(markers)
        vertices = torch.tensor([int(markers[x]["vertex"]) for x in labels], dtype=torch.long)
        distance = torch.tensor([float(markers[x]["distance"]) for x in labels], dtype=torch.float32)
        return cls(str(data["name"]), labels, vertices, distance)

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
