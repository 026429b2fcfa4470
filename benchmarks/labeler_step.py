"""Where one training step of the two-stage mocap labeler goes (issue 38 item 4): ms per part.

One batch of synthetic frames (the shipped recipe's lab variation, no motions) on ``--device``; the
paper-size second stage (width 147, 8 layers, 7 heads) behind cmu41's frozen first stage, as
``scripts/train_labeler.py --orient-with cmu41`` trains it. Each part is timed over ``--reps``
calls after one warm-up, with ``torch.cuda.synchronize()`` on CUDA:

- the whole step (first stage, second stage, loss, backward, Adam step, the loss read back);
- the first stage's orientation alone (no gradient);
- the second stage's scores, forward and backward;
- ``log_sinkhorn`` (35 iterations) forward and backward, eager and, with ``--compile``, through
  ``torch.compile`` (its compile time printed).

    python benchmarks/labeler_step.py --device cuda --compile
    python benchmarks/labeler_step.py --device cpu --batch 64 --reps 2     # a CPU smoke run
"""

from __future__ import annotations

import argparse
import time

import torch

from unibody.mocap.labeler import Labeler, labeling_loss
from unibody.mocap.layout import MarkerLayout
from unibody.mocap.orient import torso_template
from unibody.mocap.pipeline import load_labeler
from unibody.mocap.sinkhorn import log_sinkhorn
from unibody.mocap.synthetic import LAB_VARIATION, SyntheticConfig, SyntheticMocap


def main(argv: list[str] | None = None) -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--device", default="cuda")
    p.add_argument("--batch", type=int, default=1024)
    p.add_argument("--reps", type=int, default=10)
    p.add_argument("--width", type=int, default=147)
    p.add_argument("--layers", type=int, default=8)
    p.add_argument("--heads", type=int, default=7)
    p.add_argument("--compile", action="store_true", help="also time log_sinkhorn through torch.compile")
    args = p.parse_args(argv)
    dev = args.device
    if dev.startswith("cuda") and not torch.cuda.is_available():
        raise SystemExit("--device: CUDA is not available on this machine")
    torch.manual_seed(0)
    layout = MarkerLayout.load("cmu41")
    syn = SyntheticMocap(layout, SyntheticConfig(stature_prob=0.75, stick_prob=0.9, **LAB_VARIATION))
    b = syn.sample(args.batch, torch.Generator().manual_seed(0)).to(dev)
    orienter = load_labeler("cmu41").orienter.with_config(refine=1)
    template, torso = torso_template(layout.subset(orienter.label_names))
    model = Labeler(
        len(layout), label_names=layout.labels, width=args.width, layers=args.layers, heads=args.heads,
        refine=0, retry=0.0, orienter=orienter, template=template, torso=torso,
    ).to(dev)  # fmt: skip
    opt = torch.optim.Adam([x for x in model.parameters() if x.requires_grad], lr=1e-4)
    sync = torch.cuda.synchronize if dev.startswith("cuda") else (lambda: None)

    def timed(name: str, fn) -> None:  # noqa: ANN001
        fn()
        sync()
        t = time.perf_counter()
        for _ in range(args.reps):
            fn()
        sync()
        print(f"| {name} | {1e3 * (time.perf_counter() - t) / args.reps:.1f} |", flush=True)

    def step() -> None:
        loss = labeling_loss(model(b.points, b.mask, refine=0, retry=0.0), b)
        opt.zero_grad(set_to_none=True)
        loss.backward()
        opt.step()
        float(loss.detach())

    with torch.no_grad():
        rot, centre = model.orient(b.points, b.mask)
    q = b.points @ rot.transpose(1, 2)

    def scores() -> None:
        model.scores(q, b.mask, centre).sum().backward()

    def sinkhorn(fn) -> None:  # noqa: ANN001
        s = model.scores(q, b.mask, centre).detach().requires_grad_(True)
        fn(s, model.bin_score, b.mask).sum().backward()

    eager = lambda s, bs, m: log_sinkhorn(s, bs, m, 35)  # noqa: E731
    print(f"device {dev}, batch {args.batch}, {b.points.shape[1]} point slots, {len(layout)} labels, "
          f"second stage {sum(x.numel() for x in model.parameters() if x.requires_grad):,} parameters\n")  # fmt: skip
    print("| part | ms |\n|---|---|")
    timed("whole training step", step)
    timed("first stage: orient (refine 1, no gradient)", lambda: torch.no_grad()(model.orient)(b.points, b.mask))
    timed("second stage: scores, forward + backward", scores)
    timed("log_sinkhorn 35 iterations, forward + backward", lambda: sinkhorn(eager))
    if args.compile:
        compiled = torch.compile(eager)
        t = time.perf_counter()
        sinkhorn(compiled)
        sync()
        print(f"\ntorch.compile of log_sinkhorn: {time.perf_counter() - t:.0f} s to compile\n")
        print("| part | ms |\n|---|---|")
        timed("log_sinkhorn compiled, forward + backward", lambda: sinkhorn(compiled))


if __name__ == "__main__":
    main()
