"""What limits per-frame labelling: the first stage (orientation, centre) or the second (issue 38).

On the labelled CMU evaluation files (every 4th frame; labels used only here, for scoring and
for the oracles), per-frame C+G as ``benchmarks/mocap.py`` corrupts them (seed 0), the shipped
two-stage labeler's second stage is given:

- ``pipeline``: its own first stage's orientation and centre, retries at the model's ``retry``;
- ``no retry``: the same without retries;
- ``oracle orientation``: the rotation fitted to the true torso labels (the same weighted
  Kabsch as the first stage's, with weight 1 on every true torso marker), the centre of the
  true markers, no retry;
- ``oracle centre``: its own first stage's orientation, the centre of the true markers, no retry.

If the oracles barely beat the pipeline, the first stage is not what limits the accuracy.

    OMP_NUM_THREADS=2 python benchmarks/mocap_oracle.py [--model cmu41] [--stride 4] [--evaldata ../shared/evaldata]
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).parent))
import mocap as bench  # noqa: E402  (benchmarks/mocap.py: the files, the corruption, the posture bins)

from unibody.mocap.labeler import predict  # noqa: E402
from unibody.mocap.orient import fit_rotation  # noqa: E402

ROWS = ("pipeline", "no retry", "oracle orientation", "oracle centre")


def main(argv: list[str] | None = None) -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--model", default="cmu41", help="a shipped two-stage cmu41-layout labeler (name or path)")
    p.add_argument("--stride", type=int, default=4, help="every k-th frame of each file")
    p.add_argument("--evaldata", type=Path, default=Path(__file__).resolve().parents[2] / "shared/evaldata")
    args = p.parse_args(argv)
    if not args.evaldata.is_dir():
        raise SystemExit(f"--evaldata: {args.evaldata} is not a folder")
    try:
        model = bench.load_labeler(args.model).eval()
    except (OSError, ValueError) as err:
        raise SystemExit(f"--model: {err}") from None
    if "LFWT" not in model.label_names or len(model.label_names) != 41:
        raise SystemExit(f"--model: {args.model} labels {len(model.label_names)} markers, not the cmu41 layout")
    if model.orienter is None:
        raise SystemExit(f"--model: {args.model} has no first stage (orienter)")
    null = model.num_labels
    bins = len(bench.UPRIGHT_BINS)
    hits = torch.zeros(len(ROWS), bins + 1, 2, dtype=torch.long)  # row, posture (last: all), (right, total)
    for name in bench.FILES["cmu41"]:
        seq = bench.read(args.evaldata / name)
        marked, ghosts = bench.split(seq, model.label_names)
        marked, ghosts = marked[:: args.stride], ghosts[:: args.stride]
        posture = torch.as_tensor(bench.posture_bin(bench.trunk_up(marked, model.label_names)))
        gen = torch.Generator().manual_seed(0)
        for s, b in bench.corrupted(marked, ghosts, gen, null):
            with torch.no_grad():
                pts = torch.where(b.mask[..., None], b.points, 0.0)
                true_marker = b.labels != null
                known = b.labels.clamp_max(null - 1)
                rot_true = fit_rotation(pts, (b.mask & true_marker & model.torso[known]).float(), model.template[known])
                rot_own, _ = model.orient(b.points, b.mask)
                plans = [model(b.points, b.mask), model(b.points, b.mask, retry=0.0)]
                for rot in (rot_true, rot_own):
                    q = pts @ rot.transpose(1, 2)
                    plans.append(model._label(q, b.mask, model._marker_centres(q, b.mask, true_marker), 0))
            frame_bin = posture[s : s + len(b.points)]
            for r, plan in enumerate(plans):
                right = (predict(plan, b.mask)[0] == b.labels) & b.mask
                for k in range(bins):
                    sel = frame_bin == k
                    hits[r, k] += torch.stack([right[sel].sum(), b.mask[sel].sum()])
                hits[r, bins] += torch.stack([right.sum(), b.mask.sum()])
        print(f"_{name}: done_", file=sys.stderr, flush=True)
    total = hits[0, :, 1]
    heads = [f"{label} ({100 * int(total[k]) / int(total[bins]):.0f} % of points)" for k, (_, label) in
             enumerate(bench.UPRIGHT_BINS)]  # fmt: skip
    print(f"Per-frame C+G accuracy (%), {args.model}, CMU files, every {args.stride}th frame, seed 0\n")
    print("| second stage given | " + " | ".join(heads) + " | all |")
    print("|---" * (bins + 2) + "|")
    for r, row in enumerate(ROWS):
        cells = [f"{100 * int(a) / max(1, int(n)):.2f}" for a, n in hits[r]]
        print(f"| {row} | " + " | ".join(cells) + " |")


if __name__ == "__main__":
    main()
