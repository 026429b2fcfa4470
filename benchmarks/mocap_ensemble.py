"""Per-frame labels of two labelers and of their mean plan (issue 38's per-frame target).

    OMP_NUM_THREADS=2 python benchmarks/mocap_ensemble.py [--models cmu41 cmu41_large] [--evaldata ../shared/evaldata]

The CMU evaluation files, per-frame C+G with the draws of ``benchmarks/mocap.py``'s label section
(seed 0: the same frames, occlusions and ghosts for every model), accuracy / macro F1 (%) per file
and pooled, for each model alone and for the mean of their plans (probabilities averaged, then the
same decode). Not shipped: a measure of what averaging the two shipped CMU labelers would give.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import torch
from torch import nn

from unibody.mocap.metrics import labeling_scores
from unibody.mocap.pipeline import load_labeler

sys.path.insert(0, str(Path(__file__).parent))
from mocap import FILES, per_frame, read, split  # noqa: E402  (benchmarks/mocap.py: files and protocol)


class PlanMean(nn.Module):
    """The mean of labelers' plans (same labels): ``log mean exp`` of their log plans."""

    def __init__(self, models: list) -> None:
        super().__init__()
        self.models = models
        self.num_labels, self.label_names = models[0].num_labels, models[0].label_names

    def forward(self, points: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
        plans = torch.stack([m(points, mask) for m in self.models])
        return torch.logsumexp(plans, 0) - torch.log(torch.tensor(float(len(self.models))))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--models", nargs=2, default=["cmu41", "cmu41_large"], help="two labelers with the same labels")
    ap.add_argument("--evaldata", type=Path, default=Path(__file__).resolve().parents[2] / "shared/evaldata")
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args()
    if not args.evaldata.is_dir():
        raise SystemExit(f"--evaldata: {args.evaldata} is not a folder")
    models = {name: load_labeler(name) for name in args.models}
    a, b = models.values()
    if a.label_names != b.label_names:
        raise SystemExit(f"--models: {args.models[0]} and {args.models[1]} label different markers")
    models["mean plan"] = PlanMean([a, b])
    pooled: dict[str, list] = {k: [] for k in models}
    for rel in FILES["cmu41"]:
        seq = read(args.evaldata / rel)
        for name, model in models.items():
            marked, ghosts = split(seq, model.label_names)
            gen = torch.Generator().manual_seed(args.seed)
            per_frame(model, marked, ghosts, gen, occlusions=(0, 0), ghosts=(0, 0))  # the no-noise row's draws
            pred, true = per_frame(model, marked, ghosts, gen)
            pooled[name].append((pred, true))
            s = labeling_scores(pred, true, null=a.num_labels)
            print(f"{Path(rel).stem:12s} {name:12s} {100 * s['accuracy']:6.2f} {100 * s['f1']:6.2f}", flush=True)
    for name, got in pooled.items():
        s = labeling_scores(torch.cat([g[0] for g in got]), torch.cat([g[1] for g in got]), null=a.num_labels)
        print(f"{'pooled':12s} {name:12s} {100 * s['accuracy']:6.2f} {100 * s['f1']:6.2f}")


if __name__ == "__main__":
    main()
