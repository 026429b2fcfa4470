"""Training loop of the occupancy network (paper 002 §4 "Training"), resumable.

A step draws ``bodies`` posed bodies and ``per_part`` queries per part (half uniform in the
part's padded box, half within ~1 cm of its surface), labels them with winding numbers and
minimises the binary cross-entropy of the max-composed logit on the points inside at least one
box (the reference minimises the MSE of the sigmoid; the cross-entropy trains faster). Batch
``i`` is a function of ``(seed, i)`` only, so a resumed run sees exactly the data it would have
seen; batches are drawn by one background worker while the main process trains.
"""

from __future__ import annotations

import math
import pickle
import time
from collections.abc import Iterator
from dataclasses import asdict, dataclass
from pathlib import Path

import torch
from torch.nn.functional import binary_cross_entropy_with_logits

from ..io.atomic import atomic_path
from ..rig import Rig
from . import data
from .model import OUTSIDE, OccupancyNet
from .parts import BodyParts

__all__ = ["TrainConfig", "make_net", "iou", "evaluate", "read_checkpoint", "train"]


@dataclass(frozen=True)
class TrainConfig:
    steps: int = 5000
    bodies: int = 8
    per_part: int = 256
    lr: float = 1e-3
    min_lr: float = 1e-5
    identities: int = 1000
    seed: int = 0
    eval_every: int = 250
    eval_bodies: int = 16
    save_every: int = 100


def make_net(**config) -> OccupancyNet:
    """An untrained network on the canonical parts (``config``: :class:`OccupancyNet` options)."""
    rig = Rig.canonical()
    return OccupancyNet(BodyParts.canonical(), rig.faces, rig.bind_vertices, **config)


def _batch(parts: BodyParts, cfg: TrainConfig, step: int) -> dict[str, torch.Tensor]:
    out, faces = data.pose_bodies(cfg.bodies, seed=cfg.seed, index=step, identities=cfg.identities)
    points = data.training_queries(parts, out, faces, cfg.per_part, data.generator("queries", cfg.seed, step))
    return {
        "vertices": out.vertices,
        "transforms": out.transforms,
        "points": points,
        "inside": data.inside_mesh(out.vertices, faces, points),
    }


class _Batches(torch.utils.data.IterableDataset):
    def __init__(self, parts: BodyParts, cfg: TrainConfig, start: int) -> None:
        self.parts, self.cfg, self.start = parts, cfg, start

    def __iter__(self) -> Iterator[dict[str, torch.Tensor]]:
        torch.set_num_threads(1)
        for step in range(self.start, self.cfg.steps):
            yield _batch(self.parts, self.cfg, step)


def iou(pred: torch.Tensor, truth: torch.Tensor) -> torch.Tensor:
    """(B,) intersection over union of boolean occupancies (B, T)."""
    inter = (pred & truth).sum(-1).double()
    union = (pred | truth).sum(-1).double()
    return torch.where(union > 0, inter / union.clamp_min(1), torch.ones_like(inter))


@torch.no_grad()
def evaluate(net: OccupancyNet, bodies: int = 16, points: int = 20000, *, seed: int = 1) -> dict[str, float]:
    """Mean IoU (%) on ``bodies`` held-out bodies (identity pool and pose stream ``seed``):
    ``points`` uniform in each body's bounding box and as many near its surface."""
    out, faces = data.pose_bodies(bodies, seed=seed, index=0)
    uniform, near = data.evaluation_points(out.vertices, faces, points, data.generator("eval", seed))
    enc = net.encode(out.vertices, out.transforms)
    res = {}
    for name, q in (("uniform", uniform), ("surface", near)):
        pred = torch.cat([net(q[i : i + 1], _index(enc, i)) for i in range(bodies)]) > 0.5
        res[name] = 100 * float(iou(pred, data.inside_mesh(out.vertices, faces, q)).mean())
    return res


def _index(enc, i: int):
    return type(enc)(*(getattr(enc, f)[i : i + 1] for f in enc.__slots__))


_CHECKPOINT_KEYS = {"model": dict, "optimizer": dict, "step": int, "history": list, "train": dict, "net": dict}


def read_checkpoint(path: Path) -> dict:
    """Load a training checkpoint with ``torch.load(weights_only=True)``: tensors and plain data only.

    Raises:
        ValueError: ``path`` is not such a checkpoint (a pickle that names other globals, as a
            crafted file that would run code does, a truncated file, or missing entries).
    """
    try:
        ckpt = torch.load(path, map_location="cpu", weights_only=True)
    except (pickle.UnpicklingError, RuntimeError, EOFError, ValueError, TypeError, AttributeError) as e:
        lines = [line.strip() for line in str(e).splitlines() if line.strip()] or [type(e).__name__]
        boilerplate = ("Weights only load failed", "Check the documentation", "Please file an issue")
        reason = next((line for line in lines if not line.startswith(boilerplate)), lines[0])[:200]
        raise ValueError(
            f"{path}: not a training checkpoint that loads as plain data (tensors, numbers, strings, "
            f"lists and dicts): {reason}"
        ) from None
    if not isinstance(ckpt, dict):
        raise ValueError(f"{path}: expected a checkpoint dict, got {type(ckpt).__name__}")
    for key, kind in _CHECKPOINT_KEYS.items():
        if not isinstance(ckpt.get(key), kind) or isinstance(ckpt.get(key), bool):
            got = type(ckpt[key]).__name__ if key in ckpt else "nothing"
            raise ValueError(f"{path}: checkpoint entry {key!r}: expected {kind.__name__}, got {got}")
    return ckpt


def train(path: Path, cfg: TrainConfig, net_config: dict | None = None, log=print) -> OccupancyNet:
    """Train (or resume from ``path``) and save a checkpoint every ``cfg.save_every`` steps.

    The checkpoint holds tensors and plain data only (it is read back with
    ``torch.load(weights_only=True)``) and is replaced atomically: written to a fresh,
    exclusively created temporary file beside it, synced, then renamed over it.

    Raises:
        ValueError: ``path`` exists but is not a checkpoint of this run's configuration, or
            cannot be loaded as plain data (see :func:`read_checkpoint`).
    """
    path = Path(path)
    net_config = dict(net_config or {})
    start, history = 0, []
    if path.exists():
        ckpt = read_checkpoint(path)
        saved = {**asdict(TrainConfig()), **ckpt["train"]}  # options added since the file was written: defaults
        if saved != asdict(cfg) or ckpt["net"] != net_config:
            raise ValueError(f"{path}: its configuration differs from this run's; use another path")
        net = make_net(**net_config)
        net.load_state_dict(ckpt["model"])
        opt = torch.optim.Adam(net.parameters(), lr=cfg.lr)
        opt.load_state_dict(ckpt["optimizer"])
        start, history = ckpt["step"], ckpt["history"]
        log(f"resumed at step {start}")
    else:
        torch.manual_seed(cfg.seed)
        net = make_net(**net_config)
        opt = torch.optim.Adam(net.parameters(), lr=cfg.lr)

    def save(step: int) -> None:
        state = {"model": net.state_dict(), "optimizer": opt.state_dict(), "step": step, "history": history,
                 "train": asdict(cfg), "net": net_config}  # fmt: skip
        with atomic_path(path) as tmp:  # a unique temporary file: a link planted beside path is never followed
            torch.save(state, tmp)

    loader = torch.utils.data.DataLoader(
        _Batches(net.parts, cfg, start), batch_size=None, num_workers=1, prefetch_factor=4
    )
    t0, running = time.time(), []
    for step, batch in enumerate(loader, start=start):
        lr = cfg.min_lr + 0.5 * (cfg.lr - cfg.min_lr) * (1 + math.cos(math.pi * step / cfg.steps))
        for group in opt.param_groups:
            group["lr"] = lr
        enc = net.encode(batch["vertices"], batch["transforms"])
        logit = net.part_logits(batch["points"], enc).amax(-1)
        boxed = logit > OUTSIDE
        loss = binary_cross_entropy_with_logits(logit[boxed], batch["inside"][boxed].float())
        opt.zero_grad(set_to_none=True)
        loss.backward()
        opt.step()
        running.append(float(loss.detach()))
        done = step + 1
        if done % 50 == 0:
            rate = (done - start) / (time.time() - t0)
            log(f"step {done}/{cfg.steps} loss {sum(running) / len(running):.4f} lr {lr:.2e} "
                f"{rate:.2f} steps/s, eta {(cfg.steps - done) / rate / 60:.0f} min")  # fmt: skip
            history.append((done, sum(running) / len(running)))
            running = []
        if done % cfg.eval_every == 0 or done == cfg.steps:
            net.eval()
            res = evaluate(net, bodies=cfg.eval_bodies)
            net.train()
            history.append((done, res))
            log(f"step {done}: held-out IoU uniform {res['uniform']:.2f} surface {res['surface']:.2f}")
        if done % cfg.save_every == 0 or done == cfg.steps:
            save(done)
    return net
