"""How each lab difference moves the labeler (issue 38): synthetic frames, one change per row.

    OMP_NUM_THREADS=1 python benchmarks/mocap_variation.py [--models cmu41 build/new/labeler.pt]
        [--motions build/cmu_motions --holdout 93 105] [--frames 2048] [--seed 0] [--takes] [--no-frames]

Each row draws the same seeded frames (a body pool no training run used, ``pool_seed`` 7777)
with the shipped training recipe's placement (``SyntheticConfig()`` with the model's layout
rules) plus **one** of the knobs of :data:`unibody.mocap.synthetic.LAB_VARIATION` at its
stated range (the last rows: all of them; real CMU motion frames of held-out subjects,
plain and with all knobs), then corrupts them per frame (0-5 occlusions, 0-3 ghosts,
permuted), and scores each model's per-frame labels (accuracy over real points, %). A row
where the shipped model drops and a retrained one holds is a difference the retraining
taught; it is not a retraining per row (the CPU does not allow it), it is the sensitivity of
each model to each change on its own.

``--takes`` (with ``--motions`` and ``--holdout``) adds whole takes in a simulated lab: each
held-out motion becomes one take (:meth:`~unibody.mocap.synthetic.SyntheticMocap.take`: one
actor, one placement and one lab draw for all its frames, at the motion's own rate), corrupted
as ``benchmarks/mocap.py``'s tracklet rows are (0-5 occlusions and 0-3 ghosts per frame in
columns, 50 broken trajectories; then 10 wrongly joined trajectory pairs), and labelled as
``unibody mocap label`` labels (``sequence_probabilities``, ``settle_tracklets``). Labs: the
recipe's placement; a lab as issue 38 describes its held-out one (T10 high on the back, 4-8 cm
below C7 on the mean body, back-waist markers 17-18 cm apart on an adult, the asymmetric back
marker on the left for one actor in two; see HELD_OUT_LAB); every lab knob at its range; that
lab with T10 past the training range, up to C7's own height on the mean body. Per-frame and
tracklet accuracy (%) pooled over the takes, and the worst take's tracklet accuracy.
"""

from __future__ import annotations

import argparse
import sys
import time
from dataclasses import replace
from pathlib import Path

import numpy as np
import torch

from unibody.mocap.labeler import predict
from unibody.mocap.layout import MarkerLayout
from unibody.mocap.pipeline import load_labeler
from unibody.mocap.synthetic import LAB_VARIATION, SyntheticConfig, SyntheticMocap
from unibody.motion import load_motion

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "scripts"))
from mocap import tracklet  # noqa: E402  (benchmarks/mocap.py: the real files' tracklet protocol)
from train_labeler import motion_files, read_motions  # noqa: E402

# the issue's held-out lab, on the mean body (1.51 m; an adult's distances are ~1.16x): T10 "16-22 cm
# higher than on CMU", whose own T10 sits 23 and 33 cm below C7 in its files (subjects 85 and 135,
# medians; the one figure taken from the evaluation files, to place the description on our body,
# whose T10 is 18 cm below C7): 4-8 cm below C7 here, the top of the training range.
HELD_OUT_LAB = {
    "midline": (("T10", 0.10, 0.14),),
    "lateral": (("BWT", 0.073, 0.078), ("PSI", 0.073, 0.078)),
    "mirror_labels": LAB_VARIATION["mirror_labels"],
    "mirror_prob": 0.5,
}
LABS = (
    ("the recipe's placement", {}),
    ("the held-out lab of issue 38 (T10 high, back waist wide, back marker left in half)", HELD_OUT_LAB),
    ("every lab knob at its range", {k: v for k, v in LAB_VARIATION.items() if not k.startswith("motion")}),
    ("T10 past the training range, up to C7's height (the lab above, T10 0.14-0.19)",
     {**HELD_OUT_LAB, "midline": (("T10", 0.14, 0.19),)}),
)  # fmt: skip

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


def takes(models: dict, layout, base: SyntheticConfig, files: list[Path], seed: int) -> None:
    """Whole takes of the held-out motions in each simulated lab (see the module)."""
    clips = [load_motion(f) for f in files]
    frames_in = sum(len(c.pose) for c in clips)
    print(f"\n{len(clips)} takes ({frames_in} frames at the motions' own rate), seed {seed}, layout {layout.name}: "
          "per-frame C+G / tracklet / joined: tracklet, accuracy (%) pooled; the worst take's tracklet")  # fmt: skip
    print("| lab | model | per-frame C+G | tracklet | joined: tracklet | worst take: tracklet "
          "| tracklet >= per-frame |")  # fmt: skip
    print("|---|---|---|---|---|---|---|")
    for name, kw in LABS:
        t0 = time.time()
        syn = SyntheticMocap(layout, replace(base, **kw))
        gen = torch.Generator().manual_seed(seed)
        marked = [
            syn.take(torch.as_tensor(c.pose), gen, torch.as_tensor(c.transl)).numpy().astype(np.float64) for c in clips
        ]
        for mname, model in models.items():
            rng, mgen = np.random.default_rng(seed), torch.Generator().manual_seed(seed)
            hits = {k: [0, 0] for k in ("frame", "tracklet", "joined_tracklet")}
            worst, every = 100.0, True
            for x in marked:
                rows = tracklet(model, x, np.zeros((len(x), 0, 3)), mgen, rng)
                acc = {}
                for k in hits:
                    p, t = rows[k]
                    hits[k][0] += int((p == t).sum())
                    hits[k][1] += len(t)
                    acc[k] = 100.0 * float((p == t).double().mean())
                worst, every = min(worst, acc["tracklet"]), every and acc["tracklet"] >= acc["frame"]
            cells = " | ".join(f"{100.0 * a / max(n, 1):.2f}" for a, n in hits.values())
            print(f"| {name} | {mname} | {cells} | {worst:.2f} | {'yes' if every else 'no'} |  "
                  f"<!-- {time.time() - t0:.0f} s -->", flush=True)  # fmt: skip


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--models", nargs="+", default=["cmu41"], help="labeler names or weights paths")
    p.add_argument("--layout", default="cmu41")
    p.add_argument("--motions", nargs="*", default=[], help="motion files/folders; only --holdout subjects are used")
    p.add_argument("--holdout", nargs="*", type=int, default=[], help="held-out CMU subjects whose frames pose rows")
    p.add_argument("--frames", type=int, default=2048)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--takes", action="store_true", help="also whole takes of the held-out motions in simulated labs")
    p.add_argument("--no-frames", action="store_true", help="skip the per-frame table")
    args = p.parse_args()
    if args.takes and not (args.motions and args.holdout):
        p.error("--takes: needs --motions and --holdout (the held-out motions become the takes)")
    layout = MarkerLayout.load(args.layout)
    models = {m: load_labeler(m) for m in args.models}
    base = SyntheticConfig(identities=256, pool_seed=7777)
    rows = [(name, replace(base, **kw), None) for name, kw in ROWS]
    held = motion_files(args.motions, args.holdout)[1] if args.motions and args.holdout else []
    if held and not args.no_frames:
        motions = read_motions(held)
        subjects = " ".join(map(str, args.holdout))
        rows.append((f"held-out CMU motions (subjects {subjects})", replace(base, motion_prob=1.0), motions))
        rows.append(
            ("held-out CMU motions + all of the above", replace(base, motion_prob=1.0, **LAB_VARIATION), motions)
        )
    if not args.no_frames:
        print(f"{args.frames} frames per row, seed {args.seed}, layout {layout.name}; per-frame accuracy (%)")
        print("| change | " + " | ".join(models) + " |")
        print("|---|" + "---|" * len(models))
        for name, cfg, motions in rows:
            t = time.time()
            batches = frames(layout, cfg, motions, args.frames, args.seed)
            cells = [f"{score(m, batches):.2f}" for m in models.values()]
            print(f"| {name} | " + " | ".join(cells) + f" |  <!-- {time.time() - t:.0f} s -->", flush=True)
    if args.takes:
        takes(models, layout, base, held, args.seed)


if __name__ == "__main__":
    main()
