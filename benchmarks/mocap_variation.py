"""How each lab difference moves the labeler (issue 38): synthetic frames, one change per row.

    OMP_NUM_THREADS=1 python benchmarks/mocap_variation.py [--models cmu41 build/new/labeler.pt]
        [--motions build/cmu_motions --holdout 93 105] [--frames 2048] [--seed 0]

Each row draws the same seeded frames (a body pool no training run used, ``pool_seed`` 7777)
with the shipped training recipe's placement (``SyntheticConfig()`` with the model's layout
rules) plus **one** of the knobs of :data:`unibody.mocap.synthetic.LAB_VARIATION` at its
stated range (the last rows: all of them; real CMU motion frames of held-out subjects,
plain and with all knobs), then corrupts them per frame (0-5 occlusions, 0-3 ghosts,
permuted), and scores each model's per-frame labels (accuracy over real points, %). A row
where the shipped model drops and a retrained one holds is a difference the retraining
taught; it is not a retraining per row (the CPU does not allow it), it is the sensitivity of
each model to each change on its own.
"""

from __future__ import annotations

import argparse
import sys
import time
from dataclasses import replace
from pathlib import Path

import torch

from unibody.mocap.labeler import predict
from unibody.mocap.layout import MarkerLayout
from unibody.mocap.pipeline import load_labeler
from unibody.mocap.synthetic import LAB_VARIATION, SyntheticConfig, SyntheticMocap

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "scripts"))
from train_labeler import motion_files, read_motions  # noqa: E402

ROWS = (
    ("shipped recipe's placement", {}),
    ("T10 / STRN up and down the midline", {"midline": LAB_VARIATION["midline"]}),
    ("waist markers nearer / farther apart", {"lateral": LAB_VARIATION["lateral"]}),
    ("RBAC/RBAK on the left (every frame)", {"mirror_labels": LAB_VARIATION["mirror_labels"], "mirror_prob": 1.0}),
    ("suit: +0-1 cm under every marker", {"suit": LAB_VARIATION["suit"]}),
    ("soft tissue 0-8 mm", {"soft_tissue": LAB_VARIATION["soft_tissue"]}),
    ("calibration scale +-2 %", {"scale": LAB_VARIATION["scale"]}),
    ("bodies 1.6x wider (every body)", {"shape_tail_prob": 1.0, "shape_tail_scale": LAB_VARIATION["shape_tail_scale"]}),
    ("all of the above (recipe's fractions)", {k: v for k, v in LAB_VARIATION.items() if not k.startswith("motion")}),
)


def score(model, batches) -> float:
    right = total = 0
    with torch.no_grad():
        for b in batches:
            pred, _ = predict(model(b.points, b.mask), b.mask)
            right += int(((pred == b.labels) & b.mask).sum())
            total += int(b.mask.sum())
    return 100.0 * right / max(total, 1)


def frames(layout, cfg: SyntheticConfig, motions, n: int, seed: int):
    syn = SyntheticMocap(layout, cfg, motions=motions)
    gen = torch.Generator().manual_seed(seed)
    return [syn.sample(256, gen) for _ in range(max(1, n // 256))]


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--models", nargs="+", default=["cmu41"], help="labeler names or weights paths")
    p.add_argument("--layout", default="cmu41")
    p.add_argument("--motions", nargs="*", default=[], help="motion files/folders; only --holdout subjects are used")
    p.add_argument("--holdout", nargs="*", type=int, default=[], help="held-out CMU subjects whose frames pose rows")
    p.add_argument("--frames", type=int, default=2048)
    p.add_argument("--seed", type=int, default=0)
    args = p.parse_args()
    layout = MarkerLayout.load(args.layout)
    models = {m: load_labeler(m) for m in args.models}
    base = SyntheticConfig(identities=256, pool_seed=7777)
    rows = [(name, replace(base, **kw), None) for name, kw in ROWS]
    if args.motions and args.holdout:
        _, held = motion_files(args.motions, args.holdout)
        motions = read_motions(held)
        subjects = " ".join(map(str, args.holdout))
        rows.append((f"held-out CMU motions (subjects {subjects})", replace(base, motion_prob=1.0), motions))
        rows.append(
            ("held-out CMU motions + all of the above", replace(base, motion_prob=1.0, **LAB_VARIATION), motions)
        )
    print(f"{args.frames} frames per row, seed {args.seed}, layout {layout.name}; per-frame accuracy (%)")
    print("| change | " + " | ".join(models) + " |")
    print("|---|" + "---|" * len(models))
    for name, cfg, motions in rows:
        t = time.time()
        batches = frames(layout, cfg, motions, args.frames, args.seed)
        cells = [f"{score(m, batches):.2f}" for m in models.values()]
        print(f"| {name} | " + " | ".join(cells) + f" |  <!-- {time.time() - t:.0f} s -->", flush=True)


if __name__ == "__main__":
    main()
