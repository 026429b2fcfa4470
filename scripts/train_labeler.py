"""Train a mocap labeler for one marker layout on synthetic mocap (paper 003 §4.4-4.5).

    OMP_NUM_THREADS=1 python scripts/train_labeler.py --layout cmu41 --out build/labeler_cmu41 --threads 1
    OMP_NUM_THREADS=1 python scripts/train_labeler.py --layout pig39 --subsets pig35 --extras 40 \
        --out build/labeler_pig39 --threads 1
    OMP_NUM_THREADS=2 python scripts/train_labeler.py --layout cmu41 --orient-with cmu41 --init cmu41 \
        --out build/oriented_cmu41 --threads 2

The third trains the second stage of a two-stage labeler: frames are first labelled by the
``--orient-with`` labeler (frozen, saved inside the new weights; of a two-stage labeler, its
first stage) and rotated into the rest frame by its torso labels (:mod:`unibody.mocap.orient`);
``--init`` starts the new network from a labeler's weights (of a two-stage one, its second
stage). Both may know fewer labels than ``--layout``: a session layout from
``unibody mocap layout`` (the shipped layout and the session's other markers, paper §4.5)
trains from the shipped weights, its new labels' score rows starting fresh; ``--fitted`` then
keeps every marker near its fitted place instead of the placement guides' slides, and
``--neck-roll`` lets the head tilt further sideways than the recipe's poses (a session whose
subject looks up and aside: the tennis serve in benchmarks/README.md).

The shipped weights are two-stage labelers trained in several runs (first stage: cmu41 eleven,
pig39 eight; second stage: cmu41 two, pig39 three), each starting from the last (``--init``) as
the synthetic data improved; the exact commands, with the revision of each run, are in each
weights file's ``meta["recipe"]`` and in benchmarks/README.md:

    python -c "from unibody.mocap.pipeline import load_labeler; print(*load_labeler('cmu41').meta['recipe'], sep='\\n')"

Two runs side by side with ``--threads 1`` each use a 2-core machine best (one-stage runs
about 2 steps/s each; second stages, their frozen first stage included, about 0.8 (cmu41)
and 0.55 (pig39)); one run alone goes about 1.7x faster with ``--threads 2``.

``--device cuda`` trains the networks on a GPU; the synthetic data is still drawn on the CPU by
the same generator, so the batches are the same on any device (the weights are not
bit-identical across devices). There one process cannot draw batches fast enough:
``--workers N`` draws them in N processes, each batch from a generator seeded by its step (the
same batches for any N, and on resume; a different stream from ``--workers 0``), and
``--time-limit S`` sets ``--steps`` from the speed of the warm-up so that the run ends within S
seconds (rerun with the ``--steps`` it printed to reproduce it). ``cmu41_large`` was trained
that way on one H200 (its recipe: ``load_labeler('cmu41_large').meta['recipe']``).
``--layers`` above the ``--init`` labeler's grows it deeper: the
new blocks come last and start as the identity, so training starts from the labels it gave.
``--motions`` poses a fraction ``--motion-prob`` of the samples from the frames of unibody
motion files (the paper trains on AMASS: its sequences, turned into canonical rotations by
``unibody invert``, fit here; or CMU's BVH and ASF/AMC through ``unibody convert``), each
turned to a random heading (``--lab-variation`` also mirrors half of them and jitters every
joint). Folders are walked for ``*.motion.npz``; ``--motion-holdout`` keeps subjects out (their
frames pose the validation set instead). ``--lab-variation`` switches on
:data:`unibody.mocap.synthetic.LAB_VARIATION` (how labs differ: midline and waist markers,
the asymmetric back marker, suits, soft tissue, calibration scale, wider bodies).

Data is drawn on the fly from :class:`unibody.mocap.synthetic.SyntheticMocap` (a pool of
PCA bodies from ``--pool-seed``, seeded poses, jitter, noise, occlusions, ghosts). Validation
uses a fixed set from a disjoint body pool and random stream. Resumable: a checkpoint is
written every ``--checkpoint-every`` seconds and on Ctrl-C; rerunning the same command
continues from it (model, optimiser, schedule and random state). The final weights go to
``<out>/labeler.pt`` with the command, seed, steps and validation metrics in their metadata.
No real mocap is used, and no evaluation file: the script refuses motion files of the
evaluation subjects (``../shared/motions/cmu/manifest.json``'s ``excluded_subjects``).
"""

from __future__ import annotations

import argparse
import itertools
import math
import shlex
import signal
import subprocess
import sys
import time
from collections.abc import Iterator
from pathlib import Path

import torch

from unibody._checks import check_device
from unibody.io.atomic import atomic_path
from unibody.mocap.corrupt import MocapBatch
from unibody.mocap.labeler import Labeler, labeling_loss, predict
from unibody.mocap.layout import MarkerLayout
from unibody.mocap.orient import torso_template
from unibody.mocap.pipeline import load_labeler
from unibody.mocap.synthetic import LAB_VARIATION, POSE, SyntheticConfig, SyntheticMocap
from unibody.motion import load_motion

HEAD_BANDS = (("FHD", 10.0, 100.0), ("BHD", 110.0, 170.0))  # --head-bands: azimuths from the front, degrees
# The CMU subjects of the evaluation files (../shared/evaldata: cmu_85_*, cmu_131_*, cmu_135_*):
# never trained on (the motions folder leaves them out; this refuses them if given by hand).
EVALUATION_SUBJECTS = (85, 131, 135)


def synthetic(
    args: argparse.Namespace, layout: MarkerLayout, pool_seed: int, identities: int, motions: torch.Tensor | None = None
) -> SyntheticMocap:
    subs = tuple(MarkerLayout.load(s).labels for s in args.subsets)
    ranges = dict(POSE["ranges"])
    if args.neck_roll is not None:  # sideways tilt (about Z) of each of Neck1, Neck2 and Head
        for joint in ("Neck1", "Neck2", "Head"):
            lo, hi, relaxed = ranges[joint]
            ranges[joint] = ((*lo[:2], -args.neck_roll), (*hi[:2], args.neck_roll), relaxed)
    slides = {}  # --slide SUFFIX LO HI: that segment rule's range along its bone
    for suffix, *span in args.slide:
        try:
            lo, hi = map(float, span)
        except ValueError:
            lo = hi = math.nan
        if not 0 <= lo <= hi:
            raise SystemExit(f"--slide {suffix}: expected numbers 0 <= LO <= HI, got {' '.join(span)}")
        slides[suffix] = (lo, hi)
    segments = tuple((*r[:3], *slides.pop(r[0])) if r[0] in slides else r for r in SyntheticConfig.segments)
    if slides:
        raise SystemExit(f"--slide: expected one of {[r[0] for r in segments]}, got {sorted(slides)}")
    cfg = SyntheticConfig(
        identities=identities, pool_seed=pool_seed, subsets=subs, extras=args.extras,
        extra_distance=(args.extra_distance[0], args.extra_distance[1]), stick_prob=args.stick_prob,
        extra_prob=args.extra_prob, extra_clusters=args.extra_clusters, cluster_size=args.cluster_size,
        cluster_radius=args.cluster_radius,
        stature_prob=args.stature_prob, bands=HEAD_BANDS if args.head_bands else (),
        pose={**POSE, "ranges": ranges, **({} if args.fold is None else {"fold": args.fold})}, segments=segments,
        motion_prob=args.motion_prob,
        **(LAB_VARIATION if args.lab_variation else {}),
        **({} if args.fitted is None else {"fitted": True, "jitter_radius": args.fitted}),
    )  # fmt: skip
    return SyntheticMocap(layout, cfg, motions=motions)


def motion_subject(path: Path) -> int | None:
    """The CMU subject of a motion file named like CMU's takes (``02_01.motion.npz`` -> 2), else None."""
    head = path.name.split("_")[0]
    return int(head) if head.isdigit() and "_" in path.name else None


def motion_files(paths: list[str], holdout: list[int]) -> tuple[list[Path], list[Path]]:
    """The motion files given (folders walked for ``*.motion.npz``), split into (training, held out)."""
    files = []
    for x in map(Path, paths):
        if x.is_dir():
            files += sorted(x.rglob("*.motion.npz"))
        elif x.is_file():
            files.append(x)
        else:
            raise SystemExit(f"--motions: {x}: no such file or folder")
    if not files and paths:
        raise SystemExit(f"--motions: no *.motion.npz under {' '.join(paths)}")
    if bad := [f.name for f in files if motion_subject(f) in EVALUATION_SUBJECTS]:
        raise SystemExit(
            f"--motions: {bad[0]} is a take of an evaluation subject {EVALUATION_SUBJECTS}; never train on it"
        )
    kept = [f for f in files if motion_subject(f) not in holdout]
    return kept, [f for f in files if motion_subject(f) in holdout]


def read_motions(paths: list[Path], stride: int = 1) -> torch.Tensor | None:
    """The pose frames (F, 77, 3) of unibody motion files, every ``stride``-th of each, stacked (None without files)."""
    if not paths:
        return None
    try:
        return torch.cat([torch.as_tensor(load_motion(x).pose[::stride], dtype=torch.float32) for x in paths])
    except (OSError, ValueError, KeyError) as err:
        raise SystemExit(f"--motions: {err}") from None


class _StepBatches(torch.utils.data.Dataset):
    """Training batch ``step`` of a run, drawn from its own generator seeded by (seed, step).

    With ``--workers`` the batches come from worker processes in any number; seeding each batch
    by its step keeps the data the same for any number of workers and on resume.
    """

    def __init__(self, data: SyntheticMocap, batch: int, seed: int) -> None:
        self.data, self.batch, self.seed = data, batch, seed

    def __getitem__(self, step: int) -> MocapBatch:
        gen = torch.Generator().manual_seed(self.seed * 1_000_003 + step)
        return self.data.sample(self.batch, gen)


def batches_from(
    data: SyntheticMocap, args: argparse.Namespace, gen: torch.Generator, step: int
) -> Iterator[MocapBatch]:
    """The training batches from ``step`` on: one generator in this process, or ``--workers`` processes."""
    if args.workers == 0:
        while True:
            yield data.sample(args.batch, gen)
    loader = torch.utils.data.DataLoader(
        _StepBatches(data, args.batch, args.seed), batch_size=None, sampler=itertools.count(step),
        num_workers=args.workers, prefetch_factor=4, collate_fn=lambda b: b,
    )  # fmt: skip
    yield from loader


def accuracy(model: Labeler, batches: list[MocapBatch]) -> tuple[float, float]:
    """Per-point accuracy over real points, and over marker points only."""
    right = total = right_m = total_m = 0
    model.eval()
    with torch.no_grad():
        for b in batches:
            pred, _ = predict(model(b.points, b.mask), b.mask)
            ok = (pred == b.labels) & b.mask
            marker = b.mask & (b.labels < model.num_labels)
            right, total = right + int(ok.sum()), total + int(b.mask.sum())
            right_m, total_m = right_m + int((ok & marker).sum()), total_m + int(marker.sum())
    model.train()
    return right / max(total, 1), right_m / max(total_m, 1)


def init_from(model: Labeler, start: dict, start_names: tuple[str, ...], source: str) -> None:
    """Copy a labeler's weights (not its first stage) into ``model``, whose labels include ``start_names``.

    The score head's output rows follow the labels: rows of shared labels are copied, those
    of new labels (a session layout's extra markers) keep their fresh initialisation. A model
    with more blocks than ``start`` (``--layers``) grows deeper: its extra blocks come last and
    start as the identity (their attention and feed-forward outputs zero), so it labels as
    ``start`` does until it trains.
    """
    own = model.state_dict()
    keys = [k for k in own if not k.startswith("orienter.") and k not in ("template", "torso")]
    depth = len({k.split(".")[1] for k in start if k.startswith("blocks.")})
    if depth > len(model.blocks):
        raise SystemExit(f"--init: {source} has {depth} blocks, more than --layers {len(model.blocks)}")
    grown = [k for k in keys if k.startswith("blocks.") and int(k.split(".")[1]) >= depth]
    if missing := [k for k in keys if k not in start and k not in grown]:
        raise SystemExit(f"--init: {source} lacks {missing[:3]}")
    keys = [k for k in keys if k not in grown]
    for block in list(model.blocks)[depth:]:
        for layer in (block.proj, block.ffn[-1]):
            torch.nn.init.zeros_(layer.weight)
            torch.nn.init.zeros_(layer.bias)
    out, name = model.head[-1], f"head.{len(model.head) - 1}"
    rows = torch.tensor([model.label_names.index(x) for x in start_names])
    weight, bias = out.weight.detach().clone(), out.bias.detach().clone()
    weight[rows], bias[rows] = start[f"{name}.weight"], start[f"{name}.bias"]
    state = {k: start[k] for k in keys} | {f"{name}.weight": weight, f"{name}.bias": bias}
    model.load_state_dict(state, strict=False)


def git_rev() -> str:
    try:
        return subprocess.run(["git", "rev-parse", "HEAD"], capture_output=True, text=True, check=True).stdout.strip()
    except (OSError, subprocess.CalledProcessError):
        return "unknown"


def main(argv: list[str] | None = None) -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--layout", required=True, help="shipped layout name or layout JSON")
    p.add_argument("--subsets", nargs="*", default=[], help="smaller layouts also drawn (their labels only)")
    p.add_argument("--out", type=Path, required=True)
    p.add_argument("--steps", type=int, default=6000)
    p.add_argument("--batch", type=int, default=256)
    p.add_argument("--lr", type=float, default=1e-3)
    p.add_argument("--weight-decay", type=float, default=5e-5)
    p.add_argument("--warmup", type=int, default=200)
    p.add_argument("--width", type=int, default=96)
    p.add_argument("--layers", type=int, default=4)
    p.add_argument("--heads", type=int, default=4)
    p.add_argument("--centre", choices=("median", "midrange"), default="median")
    p.add_argument("--stature-prob", type=float, default=0.75, help="fraction of bodies with an adult stature")
    p.add_argument("--refine", type=int, default=2, help="re-centring passes when labelling (not in training)")
    p.add_argument("--identities", type=int, default=1024)
    p.add_argument("--extras", type=int, default=0, help="up to this many markers of another protocol per frame")
    p.add_argument("--extra-prob", type=float, default=0.3, help="fraction of batches with --extras")
    p.add_argument("--extra-clusters", type=float, default=0.0, help="of those, fraction in tracking clusters")
    p.add_argument("--cluster-size", type=int, default=3, help="extra markers per tracking cluster")
    p.add_argument("--cluster-radius", type=float, default=0.08, help="m, a cluster's radius on the rest mesh")
    p.add_argument("--stick-prob", type=float, default=0.5, help="fraction of samples with wrist bars")
    p.add_argument("--head-bands", action="store_true", help="head markers anywhere around the head (HEAD_BANDS)")
    p.add_argument("--neck-roll", type=float, metavar="RAD", help="rad, each neck joint and the head tilt sideways")
    p.add_argument("--fold", type=float, metavar="FRACTION", help="fraction of poses folded at the hips")
    p.add_argument(
        "--slide", nargs=3, action="append", default=[], metavar=("SUFFIX", "LO", "HI"),
        help="a segment rule's range along its bone (SyntheticConfig.segments), e.g. --slide FIN 0.1 1.0",
    )  # fmt: skip
    p.add_argument(
        "--fitted", type=float, metavar="RADIUS",
        help="m: a session layout is fitted, so markers stay within RADIUS of their vertex, at their distance",
    )  # fmt: skip
    p.add_argument(
        "--extra-distance", type=float, nargs=2, default=(0.03, float("inf")), metavar=("LO", "HI"),
        help="m, range of an extra marker's distance to the nearest layout vertex",
    )  # fmt: skip
    p.add_argument(
        "--motions", nargs="+", default=[], metavar="PATH",
        help="unibody motion files (.npz) or folders of *.motion.npz whose frames pose --motion-prob of the samples",
    )  # fmt: skip
    p.add_argument(
        "--motion-holdout", nargs="+", type=int, default=[], metavar="SUBJECT",
        help="CMU subjects (by file name, 02_01.motion.npz -> 2) kept out of training; they pose the validation set",
    )  # fmt: skip
    p.add_argument("--lab-variation", action="store_true", help="draw lab differences (synthetic.LAB_VARIATION)")
    p.add_argument("--motion-prob", type=float, default=0.5, help="fraction of samples posed from --motions")
    p.add_argument(
        "--motion-stride", type=int, default=1, metavar="K",
        help="every K-th frame of each motion file (120 Hz CMU: 4 -> 30 Hz)",
    )  # fmt: skip
    p.add_argument("--pool-seed", type=int, default=0)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--val-frames", type=int, default=2048)
    p.add_argument("--threads", type=int, default=2)
    p.add_argument(
        "--device", default="cpu",
        help="cpu, cuda or cuda:N: where the networks train (data is drawn on the CPU, the same on any device)",
    )  # fmt: skip
    p.add_argument(
        "--workers", type=int, default=0,
        help="processes drawing the training batches (each batch then seeded by its step; 0: one stream here)",
    )  # fmt: skip
    p.add_argument(
        "--time-limit", type=float, metavar="SECONDS",
        help="set --steps from the speed of the warm-up steps so that the run ends within SECONDS (at most --steps)",
    )  # fmt: skip
    p.add_argument("--checkpoint-every", type=float, default=120.0, help="seconds")
    p.add_argument("--log-every", type=float, default=20.0, help="seconds")
    p.add_argument("--stop-at", type=int, help="checkpoint and stop after this step (resume later)")
    p.add_argument("--init", help="start from labeler weights (name or path) or another run's checkpoint.pt")
    p.add_argument("--orient-with", help="labeler (name or path) whose torso labels orient every frame first")
    p.add_argument("--orienter-refine", type=int, default=1, help="the orienter's re-centring passes")
    p.add_argument(
        "--retry", type=float, default=0.9,
        help="with --orient-with: frames labelled less surely than this are oriented again (not in training)",
    )  # fmt: skip
    args = p.parse_args(argv)
    try:
        device = check_device(args.device, "--device")
    except ValueError as err:
        raise SystemExit(str(err)) from None
    torch.set_num_threads(args.threads)
    t_start = time.time()
    rev = git_rev()  # the code the run started from
    args.out.mkdir(parents=True, exist_ok=True)
    ckpt_path = args.out / "checkpoint.pt"

    layout = MarkerLayout.load(args.layout)
    if not 0.0 <= args.motion_prob <= 1.0:
        raise SystemExit(f"--motion-prob: expected a probability in [0, 1], got {args.motion_prob}")
    for name, value, low in (("--motion-stride", args.motion_stride, 1), ("--workers", args.workers, 0)):
        if value < low:
            raise SystemExit(f"{name}: expected an integer >= {low}, got {value}")
    if args.time_limit is not None and not (args.time_limit > 0 and args.warmup >= 20):
        raise SystemExit(f"--time-limit: expected seconds > 0 and --warmup >= 20, got {args.time_limit}, {args.warmup}")
    train_files, held_files = motion_files(args.motions, args.motion_holdout)
    motions = read_motions(train_files, args.motion_stride)
    held = read_motions(held_files, args.motion_stride)
    train_data = synthetic(args, layout, args.pool_seed, args.identities, motions)
    val_data = synthetic(args, layout, args.pool_seed + 1000, 256, motions if held is None else held)  # disjoint bodies
    val_gen = torch.Generator().manual_seed(10_000 + args.seed)
    size, count = min(256, args.val_frames), max(1, args.val_frames // 256)
    val = [val_data.sample(size, val_gen).to(device) for _ in range(count)]

    torch.manual_seed(args.seed)
    orient = {}
    if args.orient_with:
        orienter = load_labeler(args.orient_with)
        orienter = orienter.orienter or orienter  # a two-stage labeler lends its first stage
        if not set(orienter.label_names) <= set(layout.labels):
            raise SystemExit(f"--orient-with: {args.orient_with} labels {orienter.label_names}, not in {layout.name}")
        orienter = orienter.with_config(refine=args.orienter_refine)
        template, torso = torso_template(layout.subset(orienter.label_names))
        orient = {"orienter": orienter, "template": template, "torso": torso}
    model = Labeler(
        len(layout),
        label_names=layout.labels,
        width=args.width,
        layers=args.layers,
        heads=args.heads,
        centre=args.centre,
        refine=args.refine,
        retry=args.retry if orient else 0.0,
        **orient,
    )
    if args.init:
        if args.init.endswith("checkpoint.pt"):  # another run's training checkpoint
            start, start_names = torch.load(args.init, weights_only=True, map_location="cpu")["model"], layout.labels
        else:
            start_model = load_labeler(args.init)
            start, start_names = start_model.state_dict(), start_model.label_names
        if not set(start_names) <= set(layout.labels):
            raise SystemExit(f"--init: {args.init} labels {start_names} are not all in {layout.name}")
        init_from(model, start, start_names, args.init)
    model.to(device)
    trainable = [x for x in model.parameters() if x.requires_grad]
    opt = torch.optim.Adam(trainable, lr=args.lr, weight_decay=args.weight_decay)

    def lr_at(step: int) -> float:  # linear warm-up, then cosine to 2 % of the base rate
        if step < args.warmup:
            return args.lr * (step + 1) / args.warmup
        t = (step - args.warmup) / max(1, args.steps - args.warmup)
        return args.lr * (0.02 + 0.98 * 0.5 * (1 + math.cos(math.pi * min(t, 1.0))))

    gen = torch.Generator().manual_seed(args.seed)
    step = 0
    if ckpt_path.exists():
        state = torch.load(ckpt_path, weights_only=True, map_location="cpu")  # the generator stays on the CPU
        model.load_state_dict(state["model"])
        opt.load_state_dict(state["opt"])
        gen.set_state(state["gen"])
        step = int(state["step"])
        rev = state.get("git_rev", rev)
        print(f"resumed from {ckpt_path} at step {step}", flush=True)

    def save_checkpoint() -> None:
        state = {"model": model.state_dict(), "opt": opt.state_dict(), "gen": gen.get_state(), "step": step}
        with atomic_path(ckpt_path) as tmp:
            torch.save({**state, "git_rev": rev}, tmp)

    stop = {"now": False}
    previous = {sig: signal.signal(sig, lambda *_: stop.update(now=True)) for sig in (signal.SIGINT, signal.SIGTERM)}
    t0 = t_log = t_ckpt = t_start
    step0, loss_avg = step, None
    end = args.steps if args.stop_at is None else min(args.steps, args.stop_at)
    batches = batches_from(train_data, args, gen, step)
    calibrate = (step0 + 10, step0 + args.warmup) if args.time_limit is not None and step0 < args.warmup else None
    while step < end and not stop["now"]:
        if calibrate and step in calibrate:  # the warm-up's speed sets the length of the schedule
            if step == calibrate[0]:
                t_cal = time.time()
            else:
                rate = (calibrate[1] - calibrate[0]) / (time.time() - t_cal)
                left = args.time_limit - (time.time() - t_start) - 30.0  # the final validation and saving
                args.steps = min(args.steps, step + max(0, int(0.97 * rate * left)))
                end = args.steps if args.stop_at is None else min(args.steps, args.stop_at)
                print(f"--time-limit {args.time_limit:g}: {rate:.1f} steps/s, --steps {args.steps}", flush=True)
        if args.time_limit is not None and time.time() - t_start > args.time_limit - 20.0:
            print(f"--time-limit {args.time_limit:g}: stopped early at step {step} of {args.steps}", flush=True)
            args.steps = end = step  # ends here: the weights are written as at the end of a schedule
            break
        for group in opt.param_groups:
            group["lr"] = lr_at(step)
        batch = next(batches).to(device)
        loss = labeling_loss(model(batch.points, batch.mask, refine=0, retry=0.0), batch)
        if not torch.isfinite(loss):
            raise FloatingPointError(f"non-finite loss at step {step}")
        opt.zero_grad(set_to_none=True)
        loss.backward()
        torch.nn.utils.clip_grad_norm_(trainable, 5.0)
        opt.step()
        step += 1
        loss_avg = float(loss.detach()) if loss_avg is None else 0.98 * loss_avg + 0.02 * float(loss.detach())
        now = time.time()
        if now - t_log >= args.log_every or step == args.steps:
            rate = (step - step0) / (now - t0)
            acc, acc_m = accuracy(model, val[:2])
            eta = (args.steps - step) / max(rate, 1e-9)
            print(
                f"step {step}/{args.steps} loss {loss_avg:.4f} val acc {acc:.4f} (markers {acc_m:.4f}) "
                f"lr {lr_at(step):.2e} {rate:.2f} steps/s ETA {eta / 60:.1f} min",
                flush=True,
            )
            t_log = now
        if now - t_ckpt >= args.checkpoint_every:
            save_checkpoint()
            t_ckpt = now
    for sig, handler in previous.items():
        signal.signal(sig, handler)
    save_checkpoint()
    if step < args.steps:
        print(f"stopped at step {step}; rerun the same command to resume", flush=True)
        if stop["now"]:
            sys.exit(130)
        return
    acc, acc_m = accuracy(model, val)
    given = sys.argv[1:] if argv is None else argv
    command = "python scripts/train_labeler.py " + " ".join(shlex.quote(a) for a in given)
    meta = {
        "command": command,
        "seed": args.seed,
        "init": args.init,
        "steps": step,
        "layout": layout.name,
        "subsets": args.subsets,
        "extras": args.extras,
        "extra_distance": list(args.extra_distance),
        "extra_prob": args.extra_prob,
        "extra_clusters": args.extra_clusters,
        "cluster_size": args.cluster_size,
        "cluster_radius": args.cluster_radius,
        "stick_prob": args.stick_prob,
        "head_bands": args.head_bands,
        "motions": [x.name for x in train_files],
        "motion_subjects": sorted({motion_subject(x) for x in train_files} - {None}),
        "motion_holdout": [x.name for x in held_files],
        "motion_frames": 0 if motions is None else len(motions),
        "motion_stride": args.motion_stride,
        "workers": args.workers,
        "batch": args.batch,
        "architecture": {"width": args.width, "layers": args.layers, "heads": args.heads},
        "lab_variation": LAB_VARIATION if args.lab_variation else None,
        "motion_prob": args.motion_prob if args.motions else None,
        "orient_with": args.orient_with,
        "orienter_refine": args.orienter_refine if args.orient_with else None,
        "retry": args.retry if args.orient_with else None,
        "orienter": orient["orienter"].meta if orient else None,
        "synthetic_val_accuracy": round(acc, 5),
        "synthetic_val_marker_accuracy": round(acc_m, 5),
        "val_frames": sum(len(b.points) for b in val),
        "git_rev": rev,
        "torch": str(torch.__version__),
        "device": str(device),
    }
    model.save(args.out / "labeler.pt", meta)
    print(f"wrote {args.out / 'labeler.pt'}: synthetic val accuracy {acc:.4f} (markers {acc_m:.4f})", flush=True)


if __name__ == "__main__":
    main()
