"""``unibody convert``: motion files and folders in, other motion formats out, at dataset scale."""

from __future__ import annotations

import argparse
import importlib.util
from pathlib import Path

from ._common import InputError, UsageError

UNITS = ("m", "cm", "mm", "in", "ft")


def add_convert_parser(sub, parents: list[argparse.ArgumentParser]) -> None:
    """The ``convert`` subcommand's arguments."""
    from ..convert.formats import READERS, WRITERS

    conv = sub.add_parser(
        "convert",
        parents=parents,
        help="motion files and folders (AMASS, BVH, ASF/AMC, SOMA, mesh sequences, motion) -> other formats",
        description="Convert motion files (formats detected from content) into one or more formats under --out, "
        "mirroring the inputs' relative paths. Finished outputs are verified and skipped when rerun; a failing "
        "file is reported and the others go on (exit 3); convert_report.json/.csv in --out lists every file.",
    )
    conv.add_argument("inputs", nargs="+", type=Path, metavar="INPUT", help="files and folders (recursive)")
    conv.add_argument("--to", required=True, metavar="FORMAT[,FORMAT...]", help=f"one or more of {', '.join(WRITERS)}")
    conv.add_argument("--out", required=True, type=Path, metavar="DIR", help="output folder (created if missing)")
    conv.add_argument(
        "--from", dest="source", metavar="FORMAT", help=f"input format, not detected ({', '.join(READERS)})"
    )
    conv.add_argument("--jobs", default="1", metavar="N", help="local worker processes (default 1)")
    conv.add_argument("--shard", metavar="i/N", help="convert only shard i of N of the sorted inputs (array jobs)")
    conv.add_argument("--executor", default="local", metavar="{local,ray}", help="ray: $RAY_ADDRESS or a local Ray")
    conv.add_argument("--preset", default="analytic", help="inversion preset for mesh inputs")
    conv.add_argument("--models", type=Path, metavar="DIR", help="SMPL-family model files for AMASS inputs")
    conv.add_argument("--template", type=Path, metavar="FILE", help="rest mesh of a mesh sequence's topology")
    conv.add_argument("--units", help=f"length unit of skeletal inputs ({', '.join(UNITS)}; default: detected)")
    conv.add_argument("--mapping", type=Path, metavar="JSON", help="joint-name correspondence of skeletal inputs")
    conv.add_argument("--batch", default="256", metavar="N", help="frames per batch (default 256)")


def _positive(value: str, name: str, what: str) -> int:
    try:
        n = int(value)
    except ValueError:
        n = 0
    if n < 1 or str(value).strip() != str(n):
        raise UsageError(f"{name}: expected a positive number of {what}, got {value!r}")
    return n


def _shard(value: str | None) -> tuple[int, int] | None:
    if value is None:
        return None
    i, sep, n = value.partition("/")
    if sep and i.isdigit() and n.isdigit() and 0 <= int(i) < int(n):
        return int(i), int(n)
    raise UsageError(f"--shard: expected i/N with 0 <= i < N (e.g. 0/4), got {value!r}")


def _formats(value: str) -> tuple[str, ...]:
    from ..convert.formats import WRITERS

    names = tuple(dict.fromkeys(v.strip().lower() for v in value.split(",") if v.strip()))
    bad = [n for n in names if n not in WRITERS]
    if not names or bad:
        raise UsageError(f"--to: expected one or more of {', '.join(WRITERS)} (comma-separated), got {value!r}")
    return names


def _path(value: Path | None, name: str, kind: str) -> Path | None:
    if value is not None and not value.exists():
        raise UsageError(f"--{name}: expected an existing {kind}, got {str(value)!r} (no such file or folder)")
    return value


def _options(args: argparse.Namespace):
    from ..convert import ConvertOptions
    from ..fitting.inversion import PRESETS

    if args.preset not in PRESETS:
        raise UsageError(f"--preset: expected one of {', '.join(PRESETS)}, got {args.preset!r}")
    if args.units is not None and args.units not in UNITS:
        raise UsageError(f"--units: expected one of {', '.join(UNITS)}, got {args.units!r}")
    return ConvertOptions(
        preset=args.preset,
        models=_path(args.models, "models", "folder or model file"),
        template=_path(args.template, "template", "mesh or identity file"),
        units=args.units,
        mapping=_path(args.mapping, "mapping", "JSON file"),
        batch=_positive(args.batch, "--batch", "frames"),
    )


def run_convert(args: argparse.Namespace, force: bool = False) -> None:
    """Check the arguments (one line each, exit 2), run the conversion, print the summary."""
    from ..convert.formats import READERS
    from ..convert.run import run

    to = _formats(args.to)
    if args.source is not None and args.source not in READERS:
        raise UsageError(f"--from: expected one of {', '.join(READERS)}, got {args.source!r}")
    jobs = _positive(args.jobs, "--jobs", "worker processes")
    shard = _shard(args.shard)
    if args.executor not in ("local", "ray"):
        raise UsageError(f"--executor: expected local or ray, got {args.executor!r}")
    if args.executor == "ray" and importlib.util.find_spec("ray") is None:
        raise UsageError("--executor ray needs Ray: pip install 'unibody[ray]'")
    options = _options(args)
    missing = [str(p) for p in args.inputs if not p.exists()]
    if missing:
        raise InputError(f"{missing[0]}: no such file or folder")
    summary = run(
        args.inputs, to, args.out, options=options, source=args.source, jobs=jobs, shard=shard,
        executor=args.executor, force=force,
    )  # fmt: skip
    print(summary.line())
    if summary.failed:
        total = summary.failed + summary.converted
        raise InputError(f"{summary.failed} of {total} file(s) failed; see {summary.report}")
