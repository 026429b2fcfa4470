"""``unibody shape-space build``: a PCA shape space from Anny and the user's own body models."""

from __future__ import annotations

import argparse
import json
from pathlib import Path
from typing import TYPE_CHECKING

from ._common import InputError, UsageError, _progress

if TYPE_CHECKING:
    import torch

    from ..identity.shape_space import ShapeSource

__all__ = ["SOURCE_KINDS", "add_shape_space_parser", "run_shape_space", "source_from_spec"]


def add_shape_space_parser(
    sub: argparse._SubParsersAction, common: argparse.ArgumentParser, writes: argparse.ArgumentParser
) -> None:
    """Register ``shape-space build`` on the ``unibody`` subcommands (``common``: --debug; ``writes``: --force)."""
    shape = sub.add_parser("shape-space", parents=[common], help="build a PCA shape space from body models")
    ssub = shape.add_subparsers(dest="shape_command", required=True)
    b = ssub.add_parser(
        "build",
        parents=[writes],
        help="sample Anny and user models, move them to the bind pose, fit one PCA (.npz for BodyLayer.from_pca)",
    )
    b.add_argument(
        "--from", dest="sources", nargs="+", required=True, metavar="SOURCE",
        help="anny | smpl=FILE | smplh=FILE | smplx=FILE | mhr=DIR | garment=DIR (one or more)",
    )  # fmt: skip
    b.add_argument("--out", type=Path, required=True, help="shape space to write (.npz)")
    b.add_argument("--weight", nargs="+", default=[], metavar="NAME=W", help="share of a source (default 1 each)")
    b.add_argument("--identities", type=int, default=4000, help="identities in all (each also mirrored)")
    b.add_argument("--components", type=int, default=128, help="components written")
    b.add_argument("--rank", type=int, default=256, help="components kept while streaming (>= --components)")
    b.add_argument("--chunk", type=int, default=200, help="identities per incremental update")
    b.add_argument("--seed", type=int, default=0)
    b.add_argument("--no-mirror", dest="mirror", action="store_false", help="no mirror augmentation")
    b.add_argument(
        "--checkpoint", type=Path, default=None,
        help="running state, saved after every chunk; the same command resumes from it (default OUT.partial.npz)",
    )  # fmt: skip


def run_shape_space(args: argparse.Namespace, force: bool) -> None:
    """Parse the sources, build the space (resumable), print a summary on stdout."""
    import torch

    from ..identity.shape_space import build_shape_space, parse_weights
    from ..io.atomic import check_output, output_lock

    for name, value, lo in (("--identities", args.identities, 1), ("--components", args.components, 1),
                            ("--chunk", args.chunk, 1), ("--seed", args.seed, 0)):  # fmt: skip
        if value < lo:
            raise UsageError(f"{name}: expected an integer >= {lo}, got {value}")
    if args.rank < args.components:
        raise UsageError(f"--rank: expected >= --components ({args.components}), got {args.rank}")
    try:
        weights = parse_weights(args.weight)
    except ValueError as exc:
        raise UsageError(str(exc)) from None
    kinds = [s.partition("=")[0] for s in args.sources]
    unknown = sorted(set(weights) - set(kinds))
    if unknown:
        raise UsageError(f"--weight: {', '.join(unknown)} is not among the --from sources ({', '.join(kinds)})")
    if len(set(kinds)) != len(kinds):
        raise UsageError(f"--from: each kind at most once, got {', '.join(kinds)}")
    out = check_output(args.out, suffixes=[".npz"], force=force)
    checkpoint = args.checkpoint or out.with_name(out.stem + ".partial.npz")
    sources = []
    for spec in args.sources:
        try:
            sources.append(source_from_spec(spec, weights.get(spec.partition("=")[0], 1.0)))
        except FileNotFoundError as exc:
            raise InputError(str(exc)) from None
        except ValueError as exc:
            if str(exc).startswith("--from"):
                raise UsageError(str(exc)) from None
            raise InputError(f"{spec}: {exc}") from exc
    command = "unibody shape-space build --from " + " ".join(args.sources)
    with output_lock(out):
        meta = build_shape_space(
            sources,
            out,
            identities=args.identities,
            seed=args.seed,
            chunk=args.chunk,
            rank=args.rank,
            components=args.components,
            mirror=args.mirror,
            checkpoint=checkpoint,
            metadata={"command": command, "name": out.stem, "torch": torch.__version__},
            progress=_progress,
        )
    checkpoint.unlink(missing_ok=True)
    summary = {
        "out": str(out),
        "bytes": meta["asset_bytes"],
        "components": meta["num_components"],
        "samples": meta["samples"],
        "sources": meta["sources"],
        "explained_variance_fraction": meta["explained_variance_fraction"],
    }
    print(json.dumps(summary, indent=2))
    print(f"load it with BodyLayer.from_pca({str(out)!r})")


SOURCE_KINDS: tuple[str, ...] = ("anny", "smpl", "smplh", "smplx", "mhr", "garment")
"""What ``unibody shape-space build --from`` accepts: ``anny`` alone, the others as ``KIND=PATH``
(an SMPL-family model file, an MHR assets folder, a GarmentMeasurements folder)."""


def source_from_spec(spec: str, weight: float = 1.0, *, dtype: torch.dtype | None = None) -> ShapeSource:
    """One :class:`ShapeSource` from a command-line item: ``anny`` or ``KIND=PATH`` (:data:`SOURCE_KINDS`).

    A foreign backend is registered onto the canonical mesh the first time (cached; about a
    minute) and sampled by :func:`backend_sampler`.

    Raises:
        ValueError: an unknown kind or a missing ``=PATH`` (the message lists the choices).
        FileNotFoundError: the path does not exist.
    """
    from dataclasses import asdict

    import torch

    from ..body import BodyLayer
    from ..identity.shape_space import AnnyRecipe, ShapeSource, anny_sampler, backend_sampler
    from ..io.atomic import file_sha256

    dtype = torch.float32 if dtype is None else dtype
    kind, sep, path = spec.partition("=")
    if kind not in SOURCE_KINDS or (kind == "anny") == bool(sep):
        raise ValueError(
            f"--from: expected 'anny' or KIND=PATH with KIND one of {', '.join(SOURCE_KINDS[1:])} "
            f"(e.g. smpl=SMPL_NEUTRAL.npz, mhr=assets/), got {spec!r}"
        )
    if kind == "anny":
        recipe = AnnyRecipe()
        layer = BodyLayer.from_anny(local_changes="all", phenotypes=recipe.phenotypes, dtype=dtype)
        num_local = layer.identity.num_params - len(layer.identity.phenotypes)
        return ShapeSource("anny", layer, anny_sampler(recipe, num_local), weight, {"recipe": asdict(recipe)})
    p = Path(path)
    if not p.exists():
        raise FileNotFoundError(f"--from {kind}: no such {'file' if kind.startswith('smpl') else 'folder'}: {p}")
    if kind.startswith("smpl"):
        from ..identity.smpl import SMPLIdentity

        identity = SMPLIdentity.from_file(p)
        described = {"file": p.name, "sha256": file_sha256(p)}
    else:
        from ..identity.garment import GarmentIdentity
        from ..identity.mhr import MHRIdentity

        identity = (MHRIdentity if kind == "mhr" else GarmentIdentity).from_files(p)
        described = {"folder": p.name}
    layer = BodyLayer.from_identity(identity, dtype=dtype)
    sampler = backend_sampler(identity)
    described["sampler"] = "backend_sampler: N(default, 1) unbounded, N(default, range/4) clipped bounded"
    return ShapeSource(kind, layer, sampler, weight, {"backend": identity.name, **described})
