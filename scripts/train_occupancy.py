"""Train the shipped occupancy network (src/unibody/occupancy/weights/occupancy_v1.pt).

    OMP_NUM_THREADS=1 python scripts/train_occupancy.py [--checkpoint build/occupancy/train.pt] [--out PATH]

The defaults are the shipped recipe; the shipped file was written by
``OMP_NUM_THREADS=1 python scripts/train_occupancy.py --steps 5000 --eval-every 250`` (the same
run: seed 0, 5,000 Adam steps, lr 1e-3 cosine to 1e-5; ~70 min on one core of a 2-vCPU AMD EPYC).
Data recipe (``unibody.occupancy.data``): each step 8 posed bodies, PCA identities of pool 0
(1,000 identities, 10 components, newborns to adults) in poses of ``unibody.synth.poses.sample_poses``
with procedural twist, and 256 queries per part (half uniform in the padded part box, half within
N(0, 1 cm) of the part's surface) labelled by libigl's fast winding numbers.

Resumable: the checkpoint is written every 100 steps and a rerun with the same options goes on
from it. Progress and held-out IoU go to stdout. Everything is a function of ``--seed``
(training bodies use identity pool 0; the held-out evaluation uses pool 1 and its own poses).
"""

from __future__ import annotations

import argparse
import dataclasses
import shlex
import sys
import time
from pathlib import Path

import torch

from unibody.io.atomic import atomic_path
from unibody.occupancy.model import default_weights_path
from unibody.occupancy.train import TrainConfig, read_checkpoint, train


def main(argv=None) -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--checkpoint", type=Path, default=Path("build/occupancy/train.pt"))
    p.add_argument("--out", type=Path, default=default_weights_path())
    for field in dataclasses.fields(TrainConfig):
        p.add_argument(f"--{field.name.replace('_', '-')}", type=type(field.default), default=field.default)
    p.add_argument("--width", type=int, default=128, help="decoder width")
    p.add_argument("--depth", type=int, default=4, help="decoder hidden layers")
    args = p.parse_args(argv)
    cli = sys.argv[1:] if argv is None else list(argv)
    torch.set_num_threads(1)
    cfg = TrainConfig(**{f.name: getattr(args, f.name) for f in dataclasses.fields(TrainConfig)})
    net_config = {"width": args.width, "depth": args.depth}
    args.checkpoint.parent.mkdir(parents=True, exist_ok=True)

    def log(msg: str) -> None:
        print(f"[{time.strftime('%H:%M:%S')}] {msg}", flush=True)

    net = train(args.checkpoint, cfg, net_config, log=log)
    history = read_checkpoint(args.checkpoint)["history"]  # torch.load(weights_only=True)
    args.out.parent.mkdir(parents=True, exist_ok=True)
    state = {
        "config": net.config,
        "model": net.state_dict(),
        "command": "OMP_NUM_THREADS=1 python scripts/train_occupancy.py " + shlex.join(cli),
        "train": dataclasses.asdict(cfg),
        "history": history,
    }
    with atomic_path(args.out) as tmp:  # unique exclusive temporary file, fsync, rename
        torch.save(state, tmp)
    log(f"wrote {args.out}")


if __name__ == "__main__":
    main()
