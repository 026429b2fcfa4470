"""`unibody mocap label` end to end, on an idle machine and beside a job that keeps one core busy.

The command runs torch with one thread per core. With OpenMP's default waiting, a thread that
reaches a barrier spins; when another job holds one of the cores, the spinning thread burns the
time slice the descheduled one needs, and every small parallel region waits for the scheduler.
The ``unibody`` command therefore starts with ``OMP_WAIT_POLICY=PASSIVE`` unless the user set it
(``unibody/__init__.py``); ``OMP_WAIT_POLICY=""`` (empty) gives libgomp's default, the path before.

    python benchmarks/cli_contention.py [--evaldata ../shared/evaldata] [--files cmu_85_12 cmu_135_02]

Prints the wall time of each run (start-up, reading and writing included) and frames/s.
"""

from __future__ import annotations

import argparse
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path


def run(c3d: Path, policy: str | None, out: Path) -> float:
    env = dict(os.environ)
    env.pop("OMP_NUM_THREADS", None)
    if policy is None:
        env.pop("OMP_WAIT_POLICY", None)
    else:
        env["OMP_WAIT_POLICY"] = policy
    out.unlink(missing_ok=True)
    t = time.perf_counter()
    subprocess.run(["unibody", "mocap", "label", str(c3d), "--model", "cmu41", "--out", str(out)], env=env,
                   check=True, capture_output=True)  # fmt: skip
    return time.perf_counter() - t


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--evaldata", type=Path, default=Path(__file__).resolve().parents[2] / "shared/evaldata")
    p.add_argument("--files", nargs="+", default=["cmu_85_12", "cmu_135_02"])
    args = p.parse_args()
    from unibody.mocap.c3d import read_markers

    print(f"{os.cpu_count()} cores; torch threads = cores (the command's default)\n")
    print("| file | frames | machine | libgomp default (before) | PASSIVE (the command now) |")
    print("|---|---:|---|---|---|")
    with tempfile.TemporaryDirectory() as tmp:
        out = Path(tmp) / "labelled.c3d"
        for name in args.files:
            c3d = args.evaldata / "c3d" / f"{name}.c3d"
            frames = read_markers(c3d).num_frames
            for busy in (False, True):
                hog = subprocess.Popen([sys.executable, "-c", "while True: pass"]) if busy else None
                try:
                    cells = []
                    for policy in ("", None):
                        s = run(c3d, policy, out)
                        cells.append(f"{s:.1f} s ({frames / s:.0f} frames/s)")
                finally:
                    if hog is not None:
                        hog.kill()
                        hog.wait()
                where = "one core busy with another job" if busy else "idle"
                print(f"| {name} | {frames:,} | {where} | {cells[0]} | {cells[1]} |", flush=True)


if __name__ == "__main__":
    main()
