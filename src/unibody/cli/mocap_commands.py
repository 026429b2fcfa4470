"""``unibody mocap label``, ``solve`` and ``layout``: optical motion capture files."""

from __future__ import annotations

import time
from pathlib import Path

import torch

from ._common import InputError, UsageError, _about, _progress, _read_take


def run_mocap_label(
    src: Path,
    out: Path,
    model: str,
    up: str,
    tracklets: bool,
    retry: float | None = None,
    bf16: bool = False,
    body: str | None = None,
    device: str = "cpu",
    force: bool = False,
) -> None:
    from .._checks import check_device
    from ..io.atomic import check_output, output_lock
    from ..mocap.c3d import write_c3d, write_npz
    from ..mocap.layout import MarkerLayout, available_layouts
    from ..mocap.pipeline import label_sequence, load_labeler
    from ..mocap.trc import write_trc

    try:
        dev = check_device(device, "--device")
    except ValueError as err:
        raise UsageError(str(err)) from None
    out = check_output(out, inputs=[src], suffixes=[".c3d", ".npz", ".trc"], force=force)
    seq = _read_take(src, up)
    labeler = load_labeler(model).to(dev).set_autocast(torch.bfloat16 if bf16 else None)
    layout = None
    if body is not None:
        name = body or str(labeler.meta.get("layout") or model)  # by default the layout the weights were trained on
        if not body and name not in available_layouts():
            raise UsageError(f"--body: {name!r} is not a shipped layout; name the model's layout (--body FILE.json)")
        layout = MarkerLayout.load(name)
    if retry is not None:
        try:
            labeler = labeler.with_config(retry=retry)
        except ValueError as err:
            raise UsageError(f"--{err}") from None
    with output_lock(out):
        t = time.perf_counter()
        try:
            labelled = label_sequence(
                seq, labeler, up=up, tracklets=tracklets, layout=layout, progress=lambda line: _progress("  " + line)
            )
        except ValueError as err:  # about an option (--body, --up) or about the file's data
            name, _, rest = str(err).partition(":")
            if name in ("layout", "up"):
                raise UsageError(f"--{'body' if name == 'layout' else name}:{rest}") from None
            raise InputError(f"{src}: {str(err).removeprefix('seq: ')}") from None
        dt = time.perf_counter() - t
        report = labelled.report
        if report.frames and len(report.unlabelled) == report.frames:
            raise InputError(f"{src}: no frame could be labelled: {report.summary()}")
        {".c3d": write_c3d, ".trc": write_trc}.get(out.suffix.lower(), write_npz)(out, labelled)
    found = int((seq.visible & (labelled.point_labels < labeler.num_labels)).sum())  # copies: their original's label
    total = int(seq.visible.sum())
    merged = ""
    if report.copies:
        merged = f" ({len(report.copies)} copy columns merged: {', '.join(f'{c}={o}' for c, o in report.copies)})"
    print(
        f"labelled {seq.num_frames} frames in {dt:.1f} s ({seq.num_frames / dt:,.0f} frames/s): "
        f"{found} of {total} points got a marker label{merged}; wrote {out}"
    )


def run_mocap_solve(src: Path, out: Path, layout_name: str, up: str, png: Path | None, force: bool = False) -> None:
    from ..io.atomic import atomic_path, check_output, output_lock
    from ..mocap.layout import MarkerLayout
    from ..mocap.pipeline import render_solution, solve_sequence
    from ..motion import save_motion

    out = check_output(out, inputs=[src], suffixes=[".npz"], force=force)
    if png is not None:
        png = check_output(png, inputs=[src, out], suffixes=[".png"], force=force, name="--png")
    seq = _read_take(src, up)
    layout = MarkerLayout.load(layout_name)
    with output_lock(out):
        t = time.perf_counter()
        with _about(src):
            result = solve_sequence(seq, layout, up=up, progress=lambda line: _progress("  " + line))
        dt = time.perf_counter() - t
        save_motion(out, result.to_motion(seq.rate))
    r = result.residual[torch.isfinite(result.residual)] * 1000
    print(
        f"solved {int(result.solved.sum())}/{seq.num_frames} frames in {dt:.1f} s "
        f"({seq.num_frames / dt:,.0f} frames/s), "
        f"marker residual mean {float(r.mean()):.1f} mm; wrote {out} (replay: unibody pose {out} --out meshes.npz)"
    )
    if png is not None:
        f = seq.num_frames // 2
        with atomic_path(png) as tmp:
            render_solution(tmp, seq, layout, result, f, up=up)
        print(f"wrote {png} (frame {f})")


def run_mocap_layout(src: Path, out: Path, base: str, frame: int, up: str, prefix: str, force: bool = False) -> None:
    from ..io.atomic import atomic_path, check_output
    from ..mocap.layout import MarkerLayout
    from ..mocap.pipeline import frame_layout

    if prefix.startswith("*"):
        raise UsageError(
            f"--prefix: expected a name prefix not starting with '*' (the mark of unlabelled points), got {prefix!r}"
        )
    out = check_output(out, inputs=[src], suffixes=[".json"], force=force)
    seq = _read_take(src, up)
    if not 0 <= frame < seq.num_frames:
        raise UsageError(f"--frame: expected a frame in 0..{seq.num_frames - 1} of {src}, got {frame}")
    layout = MarkerLayout.load(base)
    t = time.perf_counter()
    with _about(src):
        session = frame_layout(
            seq, layout, frame=frame, name=out.stem, up=up, prefix=prefix, progress=lambda line: _progress("  " + line)
        )
    with atomic_path(out) as tmp:
        session.save(tmp)
    print(
        f"fitted frame {frame} in {time.perf_counter() - t:.1f} s: {len(layout)} {layout.name} markers and "
        f"{len(session) - len(layout)} more ({prefix}01...); wrote {out}"
    )
