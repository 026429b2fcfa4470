"""Playback speed of ``unibody view``: frames/s the server shows for one and for five bodies.

A websocket client on the loopback port receives everything the server sends, as a browser
would (it counts the bytes and draws nothing). Printed, for a 120 fps motion:

  pose only         frames/s of posing alone (the bodies' ``frames``: ``BodyLayer``, 16 frames a batch)
  show, flat out    frames/s of ``Viewer.show`` called back to back: pose, assign each body's vertex
                    array to its existing mesh node, queue the update (the server-side update rate)
  playing at 1x     the viewer's own playback (wall clock, 120 fps) over the whole motion: frames
                    shown per second, mesh updates per second per body that reached the client
                    (bytes received / 18,056 x 12 B), and this process's CPU use

viser sends each node's newest state at most every 1/60 s (a browser draws at 60 Hz), so the
client gets up to 60 updates/s per body while the server shows all 120 frames/s. Rates are
given with wall and process (CPU) time: other load on the machine slows wall time only.

Motion: ``--motion FILE`` (a unibody motion, e.g. ``unibody convert 02_01.bvh --to motion``), or
a seeded synthetic 120 fps motion (smooth random joint rotations) of ``--frames`` frames.
Bodies: the motion's identity, and for five bodies four more seeded PCA identities, side by side.

    python benchmarks/viewer.py [--motion FILE] [--frames 360] [--bodies 1 5] [--seed 0] [--device cpu]
"""

from __future__ import annotations

import argparse
import platform
import threading
import time
from pathlib import Path

import numpy as np
import torch


def _synthetic(frames: int, seed: int):
    from unibody.motion import Motion

    rng = np.random.default_rng(seed)
    t = np.arange(frames) / 120.0
    freq = rng.uniform(0.3, 1.5, (1, 77, 3))
    phase = rng.uniform(0, 2 * np.pi, (1, 77, 3))
    pose = (0.25 * np.sin(2 * np.pi * freq * t[:, None, None] + phase)).astype(np.float32)
    transl = np.stack([0.5 * t, np.full_like(t, 0.95), np.zeros_like(t)], 1).astype(np.float32)
    return Motion(pose, transl, 120.0, np.zeros(16, np.float32), "pca", f"synthetic seed {seed}")


def _bodies(motion, n: int, seed: int):
    from unibody.cli.view_sources import body_from_motion
    from unibody.motion import Motion

    layers: dict = {}
    gen = np.random.default_rng(seed)
    out = [body_from_motion("motion", motion, layers)]
    for i in range(1, n):
        ident = motion.identity if motion.identity is not None else np.zeros(16, np.float32)
        ident = (np.asarray(ident) + gen.normal(0, 1, len(ident))).clip(-3, 3).astype(np.float32)
        other = Motion(motion.pose, motion.transl, motion.fps, ident, motion.identity_backend or "pca")
        out.append(body_from_motion(f"body {i}", other, layers))
    return out


class _Client:
    """A websocket client that receives and counts what the viewer sends."""

    def __init__(self, port: int) -> None:
        import viser
        from websockets.sync.client import connect

        self.ws = connect(f"ws://127.0.0.1:{port}", subprotocols=[f"viser-v{viser.__version__}"], max_size=None)
        self.bytes, self.last = 0, time.perf_counter()
        self.thread = threading.Thread(target=self._run, daemon=True)
        self.thread.start()

    def _run(self) -> None:
        try:
            while True:
                msg = self.ws.recv()
                self.bytes += len(msg)
                self.last = time.perf_counter()
        except Exception:  # noqa: BLE001 - the connection closes at the end
            return

    def idle(self, quiet: float = 0.5, limit: float = 30.0) -> float:
        """Wait until nothing arrived for ``quiet`` seconds; return when the last byte came."""
        start = time.perf_counter()
        while time.perf_counter() - self.last < quiet and time.perf_counter() - start < limit:
            time.sleep(0.05)
        return self.last

    def close(self) -> None:
        self.ws.close()
        self.thread.join(timeout=5)


def _rate(n: int, wall: float, cpu: float) -> str:
    return f"{n / wall:7.1f} frames/s wall, {n / cpu:7.1f} frames/s per CPU-second"


def run(motion, n_bodies: int, seed: int) -> None:
    from unibody.viz.viewer.app import Viewer
    from unibody.viz.viewer.tracks import SceneItem

    class Counting(Viewer):
        shown = 0

        def show(self, frame: int, *, force: bool = False) -> None:
            self.shown += 1
            super().show(frame, force=force)

    bodies = _bodies(motion, n_bodies, seed)
    n = len(motion.pose)
    mesh_bytes = bodies[0].layer.num_vertices * 12
    for b in bodies:  # warm up (first posing loads kernels)
        b.frames(np.array([n - 1]))
    w, c = time.perf_counter(), time.process_time()
    for k in range(n):
        for b in bodies:
            b.frames(np.array([k]))
    w, c = time.perf_counter() - w, time.process_time() - c
    print(f"  {n_bodies} bod{'y' if n_bodies == 1 else 'ies'}, {n} frames at {motion.fps:g} fps")
    print(f"    pose only        {_rate(n, w, c)}")
    items = [SceneItem(b.name, bodies=(b,)) for b in bodies]
    viewer = Counting(items, port=0)
    client = _Client(viewer.port)
    try:
        client.idle()
        for b in bodies:
            b._chunk = None  # pose afresh
        w, c = time.perf_counter(), time.process_time()
        for g in range(1, n):
            viewer.show(g)
        w, c = time.perf_counter() - w, time.process_time() - c
        print(f"    show, flat out   {_rate(n - 1, w, c)}")
        client.idle()
        viewer.show(0)
        client.idle()
        sent0, shown0 = client.bytes, viewer.shown
        viewer.loop = False
        w, c = time.perf_counter(), time.process_time()
        viewer.play()
        while viewer.playing and time.perf_counter() - w < 3 * n / motion.fps:
            time.sleep(0.01)
        w, c = time.perf_counter() - w, time.process_time() - c
        shown, got = viewer.shown - shown0, (client.bytes - sent0) / mesh_bytes / n_bodies
        print(
            f"    playing at 1x    {n / motion.fps:.2f} s of motion in {w:.2f} s: {shown / w:.0f} frames/s shown "
            f"(of {motion.fps:g}), {got / w:.0f} mesh updates/s per body reached the client, "
            f"CPU {100 * c / w:.0f} % of one core"
        )
    finally:
        client.close()
        viewer.stop()


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--motion", type=Path, help="a unibody motion file (default: synthetic, 120 fps)")
    ap.add_argument("--frames", type=int, default=360, help="frames of the synthetic motion")
    ap.add_argument("--bodies", type=int, nargs="+", default=[1, 5])
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--device", default="cpu", help="only cpu: the viewer poses on the CPU")
    ap.add_argument("--threads", type=int, default=None, help="torch threads (default: torch's)")
    args = ap.parse_args()
    if args.device != "cpu":
        ap.error("--device: the viewer poses on the CPU; expected cpu")
    if args.threads:
        torch.set_num_threads(args.threads)
    from unibody.motion import load_motion

    motion = load_motion(args.motion) if args.motion else _synthetic(args.frames, args.seed)
    print(f"viewer playback: {platform.processor() or platform.machine()}, {torch.get_num_threads()} torch threads, "
          f"motion {args.motion or motion.source}")  # fmt: skip
    with torch.no_grad():
        for n in args.bodies:
            run(motion, n, args.seed)


if __name__ == "__main__":
    main()
