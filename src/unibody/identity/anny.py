"""Anny identity backend: phenotypes (and optional local changes) -> rest mesh.

Anny (NAVER, Apache-2.0) maps anthropometric phenotypes in [0, 1] and optional
local-change coefficients in [-1, 1] to a rest mesh on its native 13,718-vertex topology
through multi-linear blendshapes. Its native frame is Z up, -Y forward; this module returns
unibody's frame (Y up, +Z forward): (x, y, z) -> (x, z, -y), metres.

Phenotypes: the six of :data:`PHENOTYPES` (gender, age, muscle, weight, height, proportions;
age 0 is a newborn, 1 an elder), or all eleven of :data:`ALL_PHENOTYPES` (adding cupsize,
firmness and the african/asian/caucasian mix) with ``AnnyIdentity.create(phenotypes="all")``,
as py-soma-x builds Anny. A phenotype not given takes Anny's default 0.5 (the race mix then
is 1/3 each); Anny's 6-phenotype model *is* the 11-phenotype one at those defaults (1.5e-10 m
apart in float64, anny 0.6.2), so either backend accepts 6 or 11 phenotypes and gives
py-soma-x's rest mesh for the same numbers. The 6-phenotype model refuses 11 numbers whose
extra five differ from 0.5 (it cannot represent them) rather than drop them; it is the
default because its blendshape basis is 2.3x smaller (136 vs 310 shapes: 98 vs 181 ms per 32
rest meshes on 2 CPU cores).

Anny caches its built model under its own cache folder (``~/.cache/anny``, or
``$ANNY_CACHE_DIR``). :meth:`AnnyIdentity.create` says on stderr when it builds that model
(the first run: about a minute), holds a lock so that concurrent processes build it once,
removes a cache file that Anny cannot load (with a warning, touching no other file) and
rebuilds it, and builds in memory when Anny's cache folder cannot be written. Warp's
start-up banner, which would go to stdout, is silenced (its warnings still show).
"""

from __future__ import annotations

import contextlib
import hashlib
import json
import sys
import time
import warnings
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Literal

import torch
from torch import nn

from .._checks import check_finite, check_like, check_shape

__all__ = ["ALL_PHENOTYPES", "AnnyIdentity", "PHENOTYPES"]

PHENOTYPES: tuple[str, ...] = ("gender", "age", "muscle", "weight", "height", "proportions")
ALL_PHENOTYPES: tuple[str, ...] = PHENOTYPES + ("cupsize", "firmness", "african", "asian", "caucasian")
PHENOTYPE_DEFAULT = 0.5  # Anny's (and py-soma-x's) value for a phenotype not given


class AnnyIdentity(nn.Module):
    """Rest meshes of Anny identities on Anny's native topology.

    Args:
        model: an ``anny.Anny`` model built with ``rig="anny", topology="anny"`` and the
            default (6) or all (11) phenotypes (see :meth:`create`).
    """

    name = "anny"

    def __init__(self, model: nn.Module) -> None:
        super().__init__()
        labels = tuple(model.phenotype_labels)
        if labels not in (PHENOTYPES, ALL_PHENOTYPES):
            raise ValueError(f"model: expected Anny phenotypes {PHENOTYPES} or {ALL_PHENOTYPES}, got {labels}")
        self.model = model
        self.phenotypes: tuple[str, ...] = labels
        self.local_changes: tuple[str, ...] = tuple(model.local_change_labels)
        self.param_names: tuple[str, ...] = labels + self.local_changes
        self.num_vertices = int(model.template_vertices.shape[0])

    @classmethod
    def create(
        cls, *, local_changes: str | tuple[str, ...] = "none", phenotypes: Literal["default", "all"] = "default"
    ) -> AnnyIdentity:
        """Build the Anny backend.

        Args:
            local_changes: "none", "default", "all" or a tuple of Anny's local-change names.
            phenotypes: "default", the six of :data:`PHENOTYPES`, or "all", the eleven of
                :data:`ALL_PHENOTYPES` (py-soma-x's set; a second Anny model, built once).

        Raises:
            ValueError: ``phenotypes`` is neither "default" nor "all".
        """
        if phenotypes not in ("default", "all"):
            raise ValueError(f"phenotypes: expected 'default' or 'all', got {phenotypes!r}")
        import anny

        local = list(local_changes) if isinstance(local_changes, tuple) else local_changes
        model = _build_anny(
            lambda: anny.Anny(rig="anny", topology="anny", local_changes=local, phenotypes=phenotypes),
            _anny_model_path(local, phenotypes),
        )
        return cls(model)

    @property
    def num_params(self) -> int:
        """K: the phenotypes (6 or 11) followed by the local changes."""
        return len(self.param_names)

    def default_params(self, batch: int = 1) -> torch.Tensor:
        """(B, K) the average identity: phenotypes 0.5, local changes 0."""
        ref = self.model.template_vertices
        params = ref.new_zeros(batch, self.num_params)
        params[:, : len(self.phenotypes)] = PHENOTYPE_DEFAULT
        return params

    @property
    def param_bounds(self) -> tuple[torch.Tensor, torch.Tensor]:
        """``(lower, upper)``, each (K,): phenotypes in [0, 1], local changes in [-1, 1]."""
        ref = self.model.template_vertices
        lower = ref.new_full((self.num_params,), -1.0)
        lower[: len(self.phenotypes)] = 0.0
        return lower, ref.new_ones(self.num_params)

    def faces(self) -> torch.Tensor:
        """(F, 3) triangles of the native mesh."""
        return self.model.get_triangular_faces()

    def template(self) -> torch.Tensor:
        """(V, 3) m, the average identity's rest mesh, ``forward(default_params())[0]``."""
        return self.forward(self.default_params())[0]

    def forward(self, params: torch.Tensor) -> torch.Tensor:
        """Rest meshes.

        Args:
            params: (B, K) phenotypes in [0, 1] then local changes in [-1, 1], in the order
                of ``param_names``. The phenotypes may also be the other set: six
                (:data:`PHENOTYPES`, the other five then take 0.5) on an all-phenotype
                backend, or eleven (:data:`ALL_PHENOTYPES`) on the default one, whose extra
                five must then be 0.5.

        Returns:
            (B, 13718, 3) rest vertices, metres, Y up, facing +Z.

        Raises:
            ValueError: wrong shape, non-finite or out-of-range values, or eleven phenotypes
                whose extra five this backend's 6-phenotype model cannot represent.
        """
        ref = self.model.template_vertices
        n_local = len(self.local_changes)
        n = len(self.phenotypes)
        other = len(ALL_PHENOTYPES) if n == len(PHENOTYPES) else len(PHENOTYPES)
        check_shape(params, f"B {n + n_local}", f"B {other + n_local}", name="identity params")
        check_like(params, ref, name="identity params", owner="the Anny backend")
        check_finite(params, "identity params")
        given = params.shape[1] - n_local
        labels = (PHENOTYPES if given == len(PHENOTYPES) else ALL_PHENOTYPES) + self.local_changes
        phen, local = params[:, :given], params[:, given:]
        for kind, x, lo, offset in (("phenotype", phen, 0.0, 0), ("local change", local, -1.0, given)):
            bad = (x < lo) | (x > 1.0)
            if bool(bad.any()):
                b, k = (int(i) for i in torch.nonzero(bad)[0])
                raise ValueError(
                    f"identity params: {kind} {labels[k + offset]!r} must lie in [{lo:g}, 1], "
                    f"got {float(x[b, k]):.4g} at batch {b}"
                )
        coeffs = self.model._get_phenotype_blendshape_coefficients(
            self._phenotypes_for_model(phen), local, params.new_zeros(params.shape[0], 0)
        )
        v = self.model.get_rest_vertices(coeffs)
        return torch.stack([v[..., 0], v[..., 2], -v[..., 1]], dim=-1)

    def _phenotypes_for_model(self, phen: torch.Tensor) -> torch.Tensor:
        """(B, 6 or 11) given phenotypes -> (B, n) in the model's phenotype order (defaults filled)."""
        n, given = len(self.phenotypes), phen.shape[1]
        if given == n:
            return phen
        if given < n:  # six given to the 11-phenotype model: Anny's defaults for the rest
            return torch.cat([phen, phen.new_full((phen.shape[0], n - given), PHENOTYPE_DEFAULT)], dim=1)
        extra = phen[:, n:]
        off = extra != PHENOTYPE_DEFAULT
        if bool(off.any()):
            b, k = (int(i) for i in torch.nonzero(off)[0])
            raise ValueError(
                f"identity params: phenotype {ALL_PHENOTYPES[n + k]!r} is {float(extra[b, k]):.4g} at batch {b}, "
                f"but this Anny backend has the 6 phenotypes {PHENOTYPES} (the other five fixed at "
                f"{PHENOTYPE_DEFAULT}); for all 11 use AnnyIdentity.create(phenotypes='all'), e.g. "
                "BodyLayer(Rig.canonical(), AnnyIdentity.create(phenotypes='all'), TopologyTransfer.from_anny())"
            )
        return phen[:, :n]


def _quiet_warp() -> None:
    """Keep Warp's start-up banner and notes off stdout (Anny initialises Warp on import)."""
    try:
        import warp
    except ImportError:
        return
    if hasattr(warp.config, "quiet"):  # Warp < 1.10
        warp.config.quiet = True
    level = getattr(warp, "LOG_WARNING", None)
    if level is not None and getattr(warp.config, "log_level", level) < level:
        warp.config.log_level = level


def _anny_model_path(local_changes: str | list[str], phenotypes: str = "default") -> Path | None:
    """Where Anny caches the model data that ``Anny(rig="anny", topology="anny")`` loads, or None if unknown.

    This mirrors ``anny.models.model_data.cache_builder`` (anny 0.6.2); it only decides which
    progress message to print, so any mismatch costs a message, never a result.
    """
    try:
        from anny.models import build_compact_model_data
        from anny.models.model_data import CURRENT_DATA_VERSION, RigConfig, TopologyConfig, _get_builder_metadata
        from anny.paths import get_anny_cache_path

        root = get_anny_cache_path()
        if root is None:
            return None
        meta = _get_builder_metadata(
            build_compact_model_data.__wrapped__,
            rig=RigConfig.from_string("anny"),
            topology=TopologyConfig.from_string("anny"),
            local_changes=local_changes,
            facial_actions="none",
            phenotypes=phenotypes,
            rank=None,
        )
        key = hashlib.sha256(json.dumps(meta, sort_keys=True).encode()).hexdigest()[:32]
        return Path(root) / f"v{CURRENT_DATA_VERSION}" / f"build_compact_model_data_{key}.safetensors"
    except Exception:  # another anny version: no prediction, a plainer message
        return None


@contextlib.contextmanager
def _watch_anny_cache() -> Iterator[list[tuple[Path, Exception]]]:
    """Record (path, error) for each Anny cache file that fails to load during the block."""
    from anny.models.model_data import ModelData

    original = ModelData.__dict__["load_safetensors"]
    failures: list[tuple[Path, Exception]] = []

    def load(model_cls, path):
        try:
            return original.__func__(model_cls, path)
        except Exception as exc:
            failures.append((Path(path), exc))
            raise

    ModelData.load_safetensors = classmethod(load)
    try:
        yield failures
    finally:
        ModelData.load_safetensors = original


@contextlib.contextmanager
def _anny_cache_off() -> Iterator[None]:
    """Make Anny build without reading or writing its cache during the block."""
    import anny.paths

    saved = anny.paths._ANNY_CACHE_DIR[0]
    anny.paths._ANNY_CACHE_DIR[0] = None  # cache_builder's "no cache" case; the setter refuses None
    try:
        yield
    finally:
        anny.paths._ANNY_CACHE_DIR[0] = saved


def _say(message: str) -> None:
    print(f"unibody: {message}", file=sys.stderr, flush=True)


def _build_anny(make: Callable[[], nn.Module], predicted: Path | None) -> nn.Module:
    """``make()`` with progress messages, a build lock, and repair of Anny's unloadable cache files."""
    from anny.paths import get_anny_cache_path

    from ..assets import AssetWarning, cache_dir
    from ..io.atomic import waiting_lock

    _quiet_warp()
    root = get_anny_cache_path()
    with contextlib.ExitStack() as stack:
        locked = False

        def lock() -> None:
            nonlocal locked
            if locked or predicted is None:
                return
            locked = True
            try:
                folder = cache_dir()
                folder.mkdir(parents=True, exist_ok=True)
                stack.enter_context(waiting_lock(folder / f"anny-{predicted.name}", timeout=900.0))
            except OSError:  # no writable unibody cache (or a stuck holder): build without the lock
                pass

        in_memory = False
        for _ in range(8):  # each round removes one bad file or turns the cache off
            if predicted is not None and not predicted.is_file():
                lock()  # one process builds; the others wait, then load its file
            building = in_memory or predicted is None or not predicted.is_file()
            if building:
                where = "in memory" if in_memory else f"into {root}"
                known = "" if predicted is not None or in_memory else " (or loading it, if cached)"
                _say(f"building Anny's model once (about a minute){known} {where}...")
            t0 = time.perf_counter()
            with _watch_anny_cache() as failures:
                try:
                    model = make()
                except Exception as exc:
                    error = exc
                else:
                    if building:
                        _say(f"built Anny's model in {time.perf_counter() - t0:.1f} s")
                    return model
            if failures and not in_memory:
                bad, why = failures[-1]
                warnings.warn(
                    f"Anny's cache file {bad} cannot be loaded ({type(why).__name__}: {why}); "
                    "removing it and rebuilding",
                    AssetWarning,
                    stacklevel=3,
                )
                lock()
                try:
                    bad.unlink(missing_ok=True)
                except OSError as exc:
                    warnings.warn(f"cannot remove {bad} ({exc}); building Anny's model in memory", AssetWarning, 3)
                    in_memory = True
                    stack.enter_context(_anny_cache_off())
            elif isinstance(error, OSError) and not in_memory:
                warnings.warn(
                    f"cannot write Anny's cache in {root} ({error}); building Anny's model in memory, every run "
                    "(set ANNY_CACHE_DIR)",
                    AssetWarning,
                    stacklevel=3,
                )
                in_memory = True
                stack.enter_context(_anny_cache_off())
            else:
                raise error
        raise error
