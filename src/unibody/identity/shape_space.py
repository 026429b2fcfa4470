"""Build a PCA shape space on the canonical topology from several identity backends.

Each source is a :class:`~unibody.body.BodyLayer` (Anny, or a user's SMPL-family / MHR /
GarmentMeasurements model, moved to the canonical topology by its topology transfer) with
a sampler of its own shape distribution and a weight. :func:`build_shape_space` draws
identities from every source, runs each through the layer (backend -> transfer -> skeleton
fit), reposes it to the rig's bind A-pose and places its Hips at :data:`HIPS_M`
(:func:`to_bind_pose`), mirror-augments it, and folds it into one incremental PCA
(:func:`~unibody.identity.pca.ipca_update`). The result is a PCA asset
(:func:`~unibody.identity.pca.write_asset`) that ``BodyLayer.from_pca(path)`` loads.

    sources = [ShapeSource("anny", anny_layer(), anny_sampler(AnnyRecipe()), 1.0),
               ShapeSource("smpl", BodyLayer.from_identity(smpl), backend_sampler(smpl), 1.0)]
    build_shape_space(sources, "my_space.npz", identities=4000)

Placement: a body's shape does not say where it stands, and sources disagree on it (Anny's
origin lies near the pelvis, SMPL's at its own pelvis joint, a registered scan's feet on the
floor). Every mesh is therefore translated so that its fitted Hips joint lies at
:data:`HIPS_M` before the PCA; meshes projected onto such a space must be placed the same way
(:func:`to_bind_pose` does it). Without it a 1 m offset between sources becomes the leading
"shape" direction (``benchmarks/shape_spaces.py``).

Weights: a source of weight w gives ``round(identities * w / sum(weights))`` identities (each
also mirrored), spread evenly over the chunks. Sampling is seeded per (seed, source, chunk),
so a resumed build draws exactly the identities an uninterrupted one would.
"""

from __future__ import annotations

import json
import math
import time
from collections.abc import Callable, Sequence
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Protocol

import numpy as np
import torch

from ..io.atomic import atomic_write
from .pca import IPCAState, ipca_finalize, ipca_init, ipca_update, write_asset

__all__ = [
    "HIPS_M",
    "AnnyRecipe",
    "ShapeSource",
    "anny_sampler",
    "backend_sampler",
    "build_shape_space",
    "PosingLayer",
    "parse_weights",
    "to_bind_pose",
]

HIPS_M: tuple[float, float, float] = (0.0, 0.035, 0.027)
"""Where every mesh's Hips joint is placed before the PCA, m: the Hips of the v1 space's mean body
(0.00019, 0.03504, 0.02731), rounded to the millimetre (Anny's own placement of an average body)."""

Sampler = Callable[[np.random.Generator, int], torch.Tensor]


class Prepared(Protocol):
    """What :func:`to_bind_pose` reads of a :class:`~unibody.body.PreparedIdentity`."""

    rest_joints: torch.Tensor


class PosingLayer(Protocol):
    """The part of :class:`~unibody.body.BodyLayer` the builder uses (this floor cannot import body)."""

    num_vertices: int
    tpose_orient: torch.Tensor

    def prepare_rest(self, rest_vertices: torch.Tensor) -> Prepared: ...

    def prepare_identity(self, params: torch.Tensor) -> Prepared: ...

    def repose_to_bind(self, prepared: Prepared) -> torch.Tensor: ...


@dataclass(frozen=True)
class AnnyRecipe:
    """The distribution of Anny identities (all values are Anny parameters).

    Attributes:
        phenotypes: "default" (6) or "all" (11: adds cupsize, firmness and the
            african/asian/caucasian blend).
        phenotype_range: each of gender, age, muscle, weight, height, proportions, cupsize
            and firmness is uniform in this range (age 0 is a newborn, 1 an elder).
        ethnicity: "dirichlet": the three ethnicity weights are a uniform point of the simplex
            (Dirichlet(1, 1, 1); pure and mixed ancestries alike); "default": 1/3 each.
        local_change_probability: each local change is active with this probability.
        local_change_amplitude: an active change is uniform in [-a, a] (Anny's range is [-1, 1]).
        mirror_augmented: each mesh also enters mirrored (:func:`unibody.symmetry.mirror`).
    """

    phenotypes: str = "all"
    phenotype_range: tuple[float, float] = (0.0, 1.0)
    ethnicity: str = "dirichlet"
    local_change_probability: float = 0.125
    local_change_amplitude: float = 1.0
    mirror_augmented: bool = True

    def __post_init__(self) -> None:
        if self.phenotypes not in ("default", "all"):
            raise ValueError(f"phenotypes: expected 'default' or 'all', got {self.phenotypes!r}")
        if self.ethnicity not in ("dirichlet", "default"):
            raise ValueError(f"ethnicity: expected 'dirichlet' or 'default', got {self.ethnicity!r}")
        lo, hi = self.phenotype_range
        if not 0.0 <= lo <= hi <= 1.0:
            raise ValueError(f"phenotype_range: expected 0 <= lo <= hi <= 1, got {self.phenotype_range}")
        if not 0.0 <= self.local_change_probability <= 1.0 or not 0.0 <= self.local_change_amplitude <= 1.0:
            raise ValueError(
                "local_change_probability, local_change_amplitude: expected values in [0, 1], got "
                f"{self.local_change_probability}, {self.local_change_amplitude}"
            )

    @classmethod
    def from_dict(cls, d: dict) -> AnnyRecipe:
        d = dict(d)
        d["phenotype_range"] = tuple(d["phenotype_range"])
        return cls(**d)


def anny_params(recipe: AnnyRecipe, rng: np.random.Generator, count: int, num_local: int) -> np.ndarray:
    """(count, 6 or 11 phenotypes + num_local) Anny parameters of ``recipe``, float64."""
    lo, hi = recipe.phenotype_range
    six = lo + (hi - lo) * rng.random((count, 6))
    cols = [six]
    if recipe.phenotypes == "all":
        cols.append(lo + (hi - lo) * rng.random((count, 2)))  # cupsize, firmness
        if recipe.ethnicity == "dirichlet":
            cols.append(rng.dirichlet(np.ones(3), size=count))
        else:
            cols.append(np.full((count, 3), 0.5))  # Anny normalises the blend: 1/3 each
    active = rng.random((count, num_local)) < recipe.local_change_probability
    value = recipe.local_change_amplitude * (2.0 * rng.random((count, num_local)) - 1.0)
    cols.append(np.where(active, value, 0.0))
    return np.concatenate(cols, axis=1)


def anny_sampler(recipe: AnnyRecipe, num_local: int) -> Sampler:
    """A sampler of Anny parameters (``num_local``: the layer's local changes)."""

    def sample(rng: np.random.Generator, count: int) -> torch.Tensor:
        return torch.from_numpy(anny_params(recipe, rng, count, num_local))

    return sample


def backend_sampler(identity: torch.nn.Module, *, spread: float = 1.0) -> Sampler:
    """A sampler of a backend's own shape distribution, from its default parameters and bounds.

    Parameters unbounded on both sides (SMPL betas, GarmentMeasurements and MHR identity
    coefficients, all in standard deviations of their model) are normal with standard deviation
    ``spread`` around the default; bounded ones (MHR bone scales) are normal around the default
    with a quarter of their range as standard deviation, clipped to the bounds.
    """
    default = identity.default_params(1)[0].detach().double().cpu()
    bounds = identity.param_bounds
    k = default.shape[0]
    if bounds is None:
        lo, hi = torch.full((k,), -math.inf, dtype=torch.float64), torch.full((k,), math.inf, dtype=torch.float64)
    else:
        lo, hi = (b.detach().double().cpu() for b in bounds)
    finite = torch.isfinite(lo) & torch.isfinite(hi)
    sd = torch.where(finite, (hi - lo).nan_to_num(0.0, 0.0, 0.0) / 4.0, torch.full_like(default, spread))

    def sample(rng: np.random.Generator, count: int) -> torch.Tensor:
        z = torch.from_numpy(rng.standard_normal((count, k)))
        return torch.minimum(torch.maximum(default + sd * z, lo), hi)

    return sample


@dataclass(frozen=True)
class ShapeSource:
    """One source of bodies for :func:`build_shape_space`.

    Attributes:
        name: a label (metadata and progress lines).
        layer: the backend on the canonical rig (``BodyLayer.from_anny``, ``BodyLayer.from_identity``, ...).
        sampler: ``(rng, count) -> (count, K)`` parameters of the layer's identity backend.
        weight: the source's share of the identities (relative to the other weights), > 0.
        description: how the source was made (metadata; e.g. the model file's name and recipe).
    """

    name: str
    layer: PosingLayer
    sampler: Sampler
    weight: float = 1.0
    description: dict = field(default_factory=dict)


def to_bind_pose(layer: PosingLayer, rest_vertices: torch.Tensor) -> torch.Tensor:
    """Canonical rest meshes (B, V, 3) -> the bind A-pose with the Hips at :data:`HIPS_M`, m.

    The skeleton is fitted to each mesh (:meth:`BodyLayer.prepare_rest`), every joint gets its
    bind local rotation (:meth:`BodyLayer.repose_to_bind`), then the mesh is translated so that
    its Hips lie at :data:`HIPS_M`. Meshes of a space built by :func:`build_shape_space` are
    placed this way; place a mesh the same way before projecting it onto one.
    """
    with torch.no_grad():
        return _placed(layer, layer.prepare_rest(rest_vertices))


def _placed(layer: PosingLayer, prepared: Prepared) -> torch.Tensor:
    posed = layer.repose_to_bind(prepared)
    hips = prepared.rest_joints[:, 1]  # repose_to_bind keeps the Hips at their rest position
    return posed - (hips - hips.new_tensor(HIPS_M))[:, None]


def _counts(sources: Sequence[ShapeSource], identities: int) -> list[int]:
    total = sum(s.weight for s in sources)
    return [max(1, round(identities * s.weight / total)) for s in sources]


def _check_sources(sources: Sequence[ShapeSource]) -> None:
    if not sources:
        raise ValueError("sources: expected at least one ShapeSource, got none")
    names = [s.name for s in sources]
    if len(set(names)) != len(names):
        raise ValueError(f"sources: names must be unique, got {names}")
    for s in sources:
        if not (isinstance(s.weight, (int, float)) and math.isfinite(s.weight) and s.weight > 0):
            raise ValueError(f"source {s.name!r}: weight must be a finite number > 0, got {s.weight!r}")
    v = {s.layer.num_vertices for s in sources}
    if len(v) != 1:
        raise ValueError(f"sources: every layer must be on the canonical mesh, got vertex counts {sorted(v)}")


def _chunk_samples(source: ShapeSource, index: int, seed: int, chunk: int, rows: int, mirror_: bool) -> torch.Tensor:
    """(rows or 2 rows, 3V) float64 bind-pose meshes of one source for one chunk."""
    from ..symmetry import mirror

    if rows == 0:
        return torch.zeros(0, 3 * source.layer.num_vertices, dtype=torch.float64)
    rng = np.random.default_rng([seed, index, chunk])
    dtype = source.layer.tpose_orient.dtype  # the layer's dtype
    params = source.sampler(rng, rows).to(dtype)
    with torch.no_grad():
        meshes = _placed(source.layer, source.layer.prepare_identity(params))
        if mirror_:
            meshes = torch.cat([meshes, mirror(meshes)])
    return meshes.reshape(meshes.shape[0], -1).double()


def _save_checkpoint(path: Path, state: IPCAState, next_chunk: int, config: dict, elapsed: float) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    with atomic_write(path) as f:
        np.savez(
            f,
            **state.to_numpy(),
            next_chunk=np.asarray(next_chunk),
            config=np.asarray(json.dumps(config, sort_keys=True)),
            elapsed=np.asarray(elapsed),
        )


def _load_checkpoint(path: Path, config: dict) -> tuple[IPCAState, int, float]:
    with np.load(path, allow_pickle=False) as data:
        saved = json.loads(str(data["config"]))
        if saved != json.loads(json.dumps(config, sort_keys=True)):
            raise ValueError(
                f"checkpoint {path}: made with other settings ({saved}), not {config}; delete it to start over"
            )
        arrays = {k: data[k] for k in data.files}
    return IPCAState.from_numpy(arrays), int(arrays["next_chunk"]), float(arrays["elapsed"])


def build_shape_space(
    sources: Sequence[ShapeSource],
    out: str | Path,
    *,
    identities: int = 4000,
    seed: int = 0,
    chunk: int = 256,
    rank: int = 256,
    components: int = 128,
    split_leading: int = 1,
    mirror: bool = True,
    checkpoint: str | Path | None = None,
    metadata: dict | None = None,
    progress: Callable[[str], None] | None = None,
) -> dict:
    """Sample every source, move the bodies to the bind pose, fit one PCA and write the asset.

    Args:
        sources: the bodies' sources (unique names, weights > 0).
        out: the ``.npz`` asset to write (atomically).
        identities: identities in all (each source's share follows its weight; each is also
            mirrored when ``mirror``).
        seed: sampling seed (per source and chunk: ``default_rng([seed, source, chunk])``).
        chunk: identities per incremental PCA update.
        rank: directions kept while streaming (more than ``components``).
        components: K, directions written.
        split_leading: leading components that also store their float16 remainder.
        mirror: mirror-augment every mesh.
        checkpoint: a ``.npz`` to save the running state to after every chunk and resume from.
        metadata: extra metadata (the command, the sources' recipes) written into the asset.
        progress: called with one line per chunk.

    Returns:
        The metadata written into the asset (with ``asset_bytes``).

    Raises:
        ValueError: bad sources or sizes, fewer samples than ``components``, or a checkpoint
            made with other settings.
    """
    _check_sources(sources)
    sizes = (("identities", identities, 1), ("chunk", chunk, 1), ("components", components, 1), ("seed", seed, 0))
    for label, x, lo in sizes:  # a negative seed failed in numpy as "expected non-negative integer"
        if isinstance(x, bool) or not isinstance(x, int) or x < lo:
            raise ValueError(f"{label}: expected an int >= {lo}, got {x!r}")
    if not components <= rank:
        raise ValueError(f"components: {components} exceeds rank {rank}")
    counts = _counts(sources, identities)
    samples = sum(counts) * (2 if mirror else 1)
    if samples <= components:
        raise ValueError(f"identities: {samples} samples cannot give {components} components; draw more")
    n_chunks = -(-max(counts) // chunk)
    config = {
        "seed": seed,
        "chunk": chunk,
        "rank": rank,
        "mirror": mirror,
        "sources": [{"name": s.name, "identities": n, **s.description} for s, n in zip(sources, counts, strict=True)],
    }
    say = progress or (lambda line: None)
    ckpt = Path(checkpoint) if checkpoint is not None else None
    v = sources[0].layer.num_vertices
    if ckpt is not None and ckpt.is_file():
        state, first, elapsed = _load_checkpoint(ckpt, config)
        say(f"resuming from {ckpt}: chunk {first}/{n_chunks}, {state.count} samples")
    else:
        state, first, elapsed = ipca_init(3 * v), 0, 0.0
    for c in range(first, n_chunks):
        t0 = time.perf_counter()
        rows = [
            _chunk_samples(s, i, seed, c, n * (c + 1) // n_chunks - n * c // n_chunks, mirror)
            for i, (s, n) in enumerate(zip(sources, counts, strict=True))
        ]
        state = ipca_update(state, torch.cat(rows), rank)
        elapsed += time.perf_counter() - t0
        if ckpt is not None:
            _save_checkpoint(ckpt, state, c + 1, config, elapsed)
        kept = float((state.singular**2).sum()) / max(state.sum_sq, 1e-300)
        eta = elapsed / (c + 1) * (n_chunks - c - 1)  # the chunks are alike: the mean so far
        say(
            f"chunk {c + 1}/{n_chunks}: {state.count} samples, {time.perf_counter() - t0:.1f} s, "
            f"variance in rank {state.basis.shape[0]}: {100 * kept:.4f} %, about {_duration(eta)} left"
        )
    k = min(components, state.basis.shape[0])
    mean, comps, std = ipca_finalize(state, k)
    total_var = state.sum_sq / (state.count - 1)
    meta = {
        "format_version": 1,
        **config,
        "samples": state.count,
        "num_components": k,
        "placement": f"bind A-pose (absolute bind local rotations), Hips at {list(HIPS_M)} m",
        "std_unit": "m (norm of a whole (V, 3) mesh); coefficients are in standard deviations",
        "components_storage": f"float16; the first {split_leading} also store their float16 remainder",
        "total_variance_m2": total_var,
        "explained_variance_fraction": float((std**2).sum()) / total_var,
        "build_seconds": elapsed,
        **(metadata or {}),
    }
    size = write_asset(
        out,
        mean=mean.reshape(v, 3).numpy(),
        components=comps.reshape(k, v, 3).numpy(),
        std=std.numpy(),
        metadata=meta,
        split_leading=split_leading,
    )
    meta["asset_bytes"] = size
    return meta


def _duration(seconds: float) -> str:
    """``seconds`` for a person: 42 s, 75 min, 3.2 h, 12 days."""
    if seconds < 120:
        return f"{seconds:.0f} s"
    if seconds < 7200:
        return f"{seconds / 60:.0f} min"
    return f"{seconds / 3600:.1f} h" if seconds < 172800 else f"{seconds / 86400:.0f} days"


def recipe_dict(recipe: AnnyRecipe) -> dict:
    """The recipe as metadata."""
    return asdict(recipe)


def parse_weights(specs: Sequence[str]) -> dict[str, float]:
    """``["smpl=2", ...]`` -> ``{"smpl": 2.0}``; ValueError naming the bad item."""
    out = {}
    for spec in specs:
        name, sep, value = spec.partition("=")
        try:
            w = float(value) if sep else math.nan
        except ValueError:
            w = math.nan
        if not name or not (math.isfinite(w) and w > 0):
            raise ValueError(f"--weight: expected NAME=W with W a number > 0 (e.g. smpl=2), got {spec!r}")
        out[name] = w
    return out
