"""The ``unibody`` command: thin wrappers that parse, call the library and print.

Results go to stdout, progress and errors to stderr. An error is one line naming the argument
or file, what was expected and what was given; the traceback only with ``--debug``. Outputs
are checked before any work (never an input, never an existing file without ``--force``),
locked against a second writer and written atomically. Exit codes: see :data:`EXIT_CODES`.
"""

from __future__ import annotations

import argparse
import pickle
import sys
import traceback
import warnings
from pathlib import Path

import torch

from ._common import EXIT_CODES, InputError, UsageError, _progress
from .body_commands import _assets_info, run_demo, run_invert, run_pose
from .convert_commands import add_convert_parser, run_convert
from .mocap_commands import run_mocap_label, run_mocap_layout, run_mocap_solve
from .shape_commands import add_shape_space_parser, run_shape_space
from .view_commands import add_view_parser, run_view

__all__ = ["EXIT_CODES", "InputError", "UsageError", "main"]


def _parser() -> argparse.ArgumentParser:
    common = argparse.ArgumentParser(add_help=False)
    common.add_argument("--debug", action="store_true", default=argparse.SUPPRESS, help="print tracebacks")
    writes = argparse.ArgumentParser(add_help=False, parents=[common])
    writes.add_argument("--force", action="store_true", help="replace an existing output file")
    codes = "\n".join(f"  {code:>3}  {what}" for code, what in EXIT_CODES.items())
    parser = argparse.ArgumentParser(
        prog="unibody",
        description=__doc__.split("\n\n")[0],
        epilog=f"exit codes:\n{codes}",
        formatter_class=argparse.RawDescriptionHelpFormatter,
        parents=[common],
    )
    sub = parser.add_subparsers(dest="command", required=True)
    demo = sub.add_parser("demo", parents=[common], help="pose identities of several backends; write demo.glb/png")
    demo.add_argument("--out", type=Path, default=Path("unibody_demo"), help="output folder")
    demo.add_argument(
        "--backends", nargs="+", default=["anny"], help="anny | pca | smpl=FILE | mhr=DIR | garment=DIR (default anny)"
    )
    sub.add_parser("assets", parents=[common], help="build (once) and describe the canonical asset cache")
    inv = sub.add_parser("invert", parents=[writes], help="mesh sequence (npz: vertices (T, N, 3), topology) -> motion")
    inv.add_argument("sequence", type=Path)
    inv.add_argument("--out", type=Path, required=True, help="motion file to write (.npz)")
    inv.add_argument("--preset", default="analytic", help="fast | analytic | svd | accurate")
    inv.add_argument("--batch", type=int, default=64)
    pose = sub.add_parser("pose", parents=[writes], help="motion npz -> canonical meshes npz (vertices (T, V, 3))")
    pose.add_argument("motion", type=Path)
    pose.add_argument("--out", type=Path, required=True, help="meshes file to write (.npz)")
    pose.add_argument("--procedural", action="store_true", help="with the shipped procedural twist joints")
    add_convert_parser(sub, [writes])
    mocap = sub.add_parser("mocap", parents=[common], help="optical mocap: label raw C3D point clouds, solve the body")
    msub = mocap.add_subparsers(dest="mocap_command", required=True)
    lab = msub.add_parser(
        "label", parents=[writes], help="raw markers (.c3d/.trc/.npz) -> labelled markers (.c3d/.trc/.npz)"
    )
    lab.add_argument("markers", type=Path)
    lab.add_argument("--out", type=Path, required=True, help="labelled markers to write (.c3d, .trc or .npz)")
    lab.add_argument("--model", default="cmu41", help="shipped labeler (cmu41 | cmu41_large | pig39) or a weights file")
    lab.add_argument("--up", default="z", choices=("z", "y"), help="vertical axis of the file")
    lab.add_argument(
        "--per-frame", action="store_true", help="label each frame on its own (no tracklets settled over the take)"
    )
    lab.add_argument(
        "--retry", type=float, metavar="CONF",
        help="two-stage labelers: orient again the frames labelled less surely than CONF (default: the model's, "
        "0.9 for the shipped ones; 0: never, about twice as fast)",
    )  # fmt: skip
    lab.add_argument(
        "--bf16", action="store_true",
        help="run the networks in bfloat16 (9-17 %% faster on CPUs with AMX; labels move a little)",
    )  # fmt: skip
    lab.add_argument("--device", default="cpu", help="where the labeler runs: cpu, cuda or cuda:N")
    lab.add_argument(
        "--body", nargs="?", const="", metavar="LAYOUT",
        help="then check the labels against a body solved from them: each point takes the solved marker it sits "
        "on, where that is clear (the model's layout: the one it was trained on by default, or a JSON file)",
    )  # fmt: skip
    sol = msub.add_parser("solve", parents=[writes], help="labelled markers (.c3d/.trc/.npz) -> unibody motion (.npz)")
    sol.add_argument("markers", type=Path)
    sol.add_argument("--out", type=Path, required=True, help="motion file to write (.npz)")
    sol.add_argument("--layout", default="cmu41", help="shipped layout (pig35 | pig39 | cmu41 | superset) or JSON")
    sol.add_argument("--up", default="z", choices=("z", "y"))
    sol.add_argument("--png", type=Path, help="also render the middle frame with its markers (.png)")
    lay = msub.add_parser(
        "layout", parents=[writes], help="one labelled frame (.c3d/.trc/.npz) -> the session's layout"
    )
    lay.add_argument("markers", type=Path)
    lay.add_argument("--out", type=Path, required=True, help="layout to write (.json)")
    lay.add_argument("--base", default="pig39", help="layout whose labels the file uses (shipped name or JSON)")
    lay.add_argument("--frame", type=int, default=0)
    lay.add_argument("--up", default="z", choices=("z", "y"))
    lay.add_argument("--prefix", default="X", help="name prefix of the file's other markers")
    add_view_parser(sub, [writes])
    add_shape_space_parser(sub, common, writes)
    return parser


def _run(args: argparse.Namespace) -> None:
    force = getattr(args, "force", False)
    if args.command == "demo":
        run_demo(args.out, args.backends)
    elif args.command == "assets":
        _assets_info()
    elif args.command == "invert":
        run_invert(args.sequence, args.out, args.preset, args.batch, force)
    elif args.command == "pose":
        run_pose(args.motion, args.out, args.procedural, force)
    elif args.command == "convert":
        run_convert(args, force)
    elif args.command == "view":
        run_view(args, force)
    elif args.command == "shape-space":
        run_shape_space(args, force)
    elif args.mocap_command == "label":
        run_mocap_label(
            args.markers, args.out, args.model, args.up, not args.per_frame, args.retry, args.bf16, args.body,
            args.device, force,
        )  # fmt: skip
    elif args.mocap_command == "solve":
        run_mocap_solve(args.markers, args.out, args.layout, args.up, args.png, force)
    else:
        run_mocap_layout(args.markers, args.out, args.base, args.frame, args.up, args.prefix, force)


def _warning_line(message, category, filename, lineno, file=None, line=None) -> None:
    """Warnings as one line on stderr, without the source line Python prints under them."""
    _progress(f"unibody: warning: {message}")


def _exit_code(exc: BaseException) -> tuple[int, str]:
    """The exit code of an error (:data:`EXIT_CODES`) and its one-line message."""
    from ..assets import AssetError
    from ..io.atomic import OutputError

    msg = str(exc) or type(exc).__name__
    if isinstance(exc, UsageError):
        return 2, msg
    if isinstance(exc, OutputError):
        return 4, msg
    if isinstance(exc, AssetError):
        return 5, msg
    if isinstance(exc, (InputError, ValueError, TypeError, pickle.UnpicklingError)):
        return 3, msg
    if isinstance(exc, OSError):  # inputs are read through _read, so this is a write (disk full, read-only, ...)
        where = f"{exc.filename}: " if exc.filename else ""
        return 4, f"cannot write: {where}{exc.strerror or msg}"
    if isinstance(exc, MemoryError):
        return 1, "out of memory; try a smaller --batch or fewer frames per file"
    return 1, f"internal error ({type(exc).__name__}: {msg}); rerun with --debug and report the traceback"


def main(argv: list[str] | None = None) -> int:
    """Run the ``unibody`` command; return its exit code (:data:`EXIT_CODES`)."""
    args = _parser().parse_args(argv)
    debug = getattr(args, "debug", False)
    try:
        with torch.no_grad(), warnings.catch_warnings():  # contexts, not global switches: callers keep their state
            if not debug:
                warnings.showwarning = _warning_line
            _run(args)
    except KeyboardInterrupt:
        if debug:
            traceback.print_exc()
        _progress("unibody: interrupted")
        return 130
    except Exception as exc:  # noqa: BLE001 - the one place every error becomes a line and an exit code
        if debug:
            traceback.print_exc()
        code, msg = _exit_code(exc)
        _progress(f"unibody: error: {msg}")
        return code
    return 0


if __name__ == "__main__":
    sys.exit(main())
