"""``unibody view``: look at motions, mesh sequences, mocap takes and GLB files in a browser.

The viewer is a viser server on this machine (``unibody[viewer]``); ``--record`` writes a
video or PNG frames instead, without a server or a browser.
"""

from __future__ import annotations

import argparse
import math
import time
from pathlib import Path

from ._common import UsageError, _progress

__all__ = ["add_view_parser", "run_view"]


MAX_RECORD_IMAGES = 100_000
"""The most images ``--record`` makes: 55 minutes of video at 30 fps."""


def add_view_parser(sub, parents: list[argparse.ArgumentParser]) -> None:
    """The ``view`` subcommand's arguments."""
    view = sub.add_parser(
        "view",
        parents=parents,
        help="interactive viewer (browser) for motions, meshes, C3D takes, GLB; or --record a video",
        description="Serve the files in a browser viewer (viser): a timeline with play/pause, frame slider, "
        "speed and loop; bodies as meshes with skeleton and joint names on demand; C3D points coloured by "
        "label (grey: unlabelled, magenta: ghosts away from the subject); identity and pose panels. "
        "Several files are shown side by side (--overlay: in one place). With --record, write a video or "
        "PNG frames instead (no browser). Without files: one Anny body (--body pca: the native PCA body).",
    )
    view.add_argument("files", nargs="*", type=Path, metavar="FILE",
                      help="motion (.npz, .bvh, .amc, SOMA/AMASS npz), mesh sequence (.npz), .c3d, .trc, "
                           ".glb")  # fmt: skip
    view.add_argument("--body", choices=("anny", "pca"), help="also show one body of this backend in the T-pose")
    view.add_argument("--port", default="8080", help="port to serve on (the next free one if taken; 0: any)")
    view.add_argument("--host", default="127.0.0.1", help="address to listen on (default: this machine only)")
    view.add_argument("--overlay", action="store_true", help="draw the files in one place, not side by side")
    view.add_argument("--spacing", default="1.5", help="metres between files side by side (default 1.5, at most 100)")
    view.add_argument("--solve", metavar="LAYOUT", help="C3D: solve the body from the labels (pig39, cmu41, ...)")
    view.add_argument(
        "--up", default="z", choices=("z", "y"), help="C3D, TRC: the lab's vertical axis (default z; OpenSim: y)"
    )
    view.add_argument(
        "--resolve", action="store_true", help="also show each motion moved out of self-intersection (~1 s a frame)"
    )
    view.add_argument(
        "--panoman", metavar="FRAME", help="also show a PanoMan fit of each motion's FRAME with its handles (~20 s)"
    )
    view.add_argument("--record", type=Path, metavar="OUT", help="write OUT.mp4 or OUT.png frames; no server")
    view.add_argument("--turntable", metavar="SECONDS", help="--record: one turn of the camera around frame 0")
    view.add_argument("--fps", default="30", help="--record: frames per second (default 30)")
    view.add_argument("--size", default="960x540", metavar="WxH", help="--record: image size (default 960x540)")
    view.add_argument("--seconds", metavar="S", help="serve for S seconds, then stop (default: until Ctrl-C)")


def _number(value: str, name: str, what: str, low: float = 0.0, integer: bool = False, high: float = math.inf) -> float:
    try:
        x = float(value)
    except ValueError:
        x = math.nan
    if not (math.isfinite(x) and low < x <= high) or (integer and x != int(x)):
        raise UsageError(f"{name}: expected {what}, got {value!r}")
    return int(x) if integer else x


def _size(value: str) -> tuple[int, int]:
    w, sep, h = value.lower().partition("x")
    if sep and w.isdigit() and h.isdigit() and 16 <= int(w) <= 8192 and 16 <= int(h) <= 8192:
        return int(w), int(h)
    raise UsageError(f"--size: expected WIDTHxHEIGHT in pixels (16..8192), e.g. 960x540, got {value!r}")


def _port(value: str) -> int:
    if value.isdigit() and 0 <= int(value) <= 65535:
        return int(value)
    raise UsageError(f"--port: expected a port number 0..65535, got {value!r}")


def _items(args: argparse.Namespace) -> list:
    from .view_sources import default_body, load_item, panoman_item, resolved_item

    layers: dict = {}
    items = [load_item(path, layers, solve=args.solve, up=args.up) for path in args.files]
    if args.body or not items:
        items.append(default_body(args.body or "anny", layers))
    frame = None if args.panoman is None else _number(args.panoman, "--panoman", "a frame number", -1, True)
    out = []
    for item in items:  # each file, then what is derived from it
        out.append(item)
        if args.resolve:
            out.append(resolved_item(item, lambda line: _progress("  " + line)))
        if frame is not None:
            out.append(panoman_item(item, int(frame), lambda line: _progress("  " + line)))
    return [x for x in out if x is not None]


def run_view(args: argparse.Namespace, force: bool = False) -> None:
    """Serve or record the files of ``args`` (see :func:`add_view_parser`)."""
    from ..viz.viewer.tracks import MAX_SPACING

    spacing = _number(args.spacing, "--spacing", f"metres in (0, {MAX_SPACING:g}]", high=MAX_SPACING)
    port = _port(args.port)
    seconds = None if args.seconds is None else _number(args.seconds, "--seconds", "a positive number of seconds")
    if args.record is not None:
        _record(args, spacing, force)
        return
    if args.turntable is not None:
        raise UsageError("--turntable: only with --record OUT")
    from ..viz.viewer import viser_missing

    if (why := viser_missing()) is not None:
        raise UsageError(why)
    items = _items(args)
    from ..viz.viewer.app import Viewer

    viewer = Viewer(items, host=args.host, port=port, layout="overlay" if args.overlay else "side", spacing=spacing)
    try:
        if viewer.port_note:
            _progress(f"unibody: {viewer.port_note}")
        frames = f"{viewer.num_frames} frames at {viewer.fps:g} fps" if viewer.num_frames > 1 else "one frame"
        print(f"viewing {len(items)} item(s), {frames}: open {viewer.url} (Ctrl-C stops)", flush=True)
        end = math.inf if seconds is None else time.monotonic() + seconds
        while time.monotonic() < end:
            time.sleep(min(0.2, max(0.0, end - time.monotonic())))
    finally:
        viewer.stop()


def _longest(items: list) -> str:
    item = max(items, key=lambda x: x.duration)
    return f"{item.name} lasts {item.duration:.3g} s ({item.fps:g} fps)"


def _record(args: argparse.Namespace, spacing: float, force: bool) -> None:
    from ..io.atomic import check_output
    from ..viz.viewer.record import frame_count, png_paths, record, render_frames

    out = check_output(args.record, inputs=args.files, suffixes=[".mp4", ".png"], force=force, name="--record")
    fps = _number(args.fps, "--fps", "a positive frame rate")
    turntable = (
        None if args.turntable is None else _number(args.turntable, "--turntable", "a positive number of seconds")
    )
    width, height = _size(args.size)
    if out.suffix.lower() == ".mp4":
        import importlib.util

        if importlib.util.find_spec("imageio_ffmpeg") is None:
            raise UsageError("--record: .mp4 needs imageio-ffmpeg: pip install 'unibody[viewer]' (or write .png)")
    items = _items(args)
    count = frame_count(items, fps=fps, turntable=turntable)
    if count > MAX_RECORD_IMAGES:  # a file at 1e-5 fps lasts a day a frame: refuse, do not render for days
        what = f"--turntable {turntable:g}" if turntable is not None else _longest(items)
        raise UsageError(
            f"--record: {what} makes {count} images at --fps {fps:g}; expected at most {MAX_RECORD_IMAGES} "
            "(lower --fps or shorten it)"
        )
    if out.suffix.lower() == ".png" and count > 1:
        for path in png_paths(out, count):
            check_output(path, inputs=args.files, suffixes=[".png"], force=force, name="--record")
    t = time.perf_counter()
    images = render_frames(items, fps=fps, turntable=turntable, width=width, height=height, spacing=spacing,
                           overlay=args.overlay)  # fmt: skip

    def progress(images):
        for i, image in enumerate(images):
            if i % 10 == 0:
                _progress(f"  rendering frame {i + 1}/{count}")
            yield image

    written = record(progress(images), out, fps=fps, count=count)
    dt = time.perf_counter() - t
    where = str(out) if len(written) == 1 else f"{written[0]} .. {written[-1].name}"
    print(f"wrote {where}: {count} frame(s) {width}x{height} in {dt:.1f} s ({count / dt:.1f} frames/s)")
