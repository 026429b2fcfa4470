"""Labelling in a lab the labeler was not built for (issue 38): each shipped labeler on the other lab's files.

The CMU files (CMU-41 names) and the Plug-in Gait files (BTKData, pyCGM, KTK: PiG-39 names) come
from labs with different placement habits. The two marker sets name the same places
differently; :data:`SAME_PLACE` maps one onto the other (front and back waist vs ASIS and PSIS,
shank vs tibia, the asymmetric back marker). Each labeler then labels the other lab's files,
scored on the labels the two sets share (the CMU forefoot markers MT5 have no PiG twin: in the
CMU files they are extra points the PiG labeler must call null), with ``benchmarks/mocap.py``'s
protocol and seed: no noise, per-frame C+G, tracklets, joined tracklets. Its own lab's files
(with the renaming applied both ways, so the scoring is the same) are the baseline.

Nothing here is trained: the shipped weights, the evaluation files (labels used only for scoring).

    OMP_NUM_THREADS=2 python benchmarks/mocap_crosslab.py [--evaldata ../shared/evaldata] [--seed 0]
"""

from __future__ import annotations

import argparse
import sys
from dataclasses import replace
from pathlib import Path

sys.path.insert(0, str(Path(__file__).parent))
import mocap as bench  # noqa: E402  (benchmarks/mocap.py: files, protocol, rows)

# PiG-39 name -> CMU-41 name of the same place.
SAME_PLACE = {
    "LASI": "LFWT", "RASI": "RFWT", "LPSI": "LBWT", "RPSI": "RBWT",
    "LTIB": "LSHN", "RTIB": "RSHN", "RBAK": "RBAC",
}  # fmt: skip


def renamed(seq, names: dict[str, str]):  # noqa: ANN001, ANN201 (MarkerSequence -> MarkerSequence)
    """The sequence with its labels renamed (others kept)."""
    return replace(seq, labels=tuple(names.get(x, x) for x in seq.labels))


def main(argv: list[str] | None = None) -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--evaldata", type=Path, default=Path(__file__).resolve().parents[2] / "shared/evaldata")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--models", nargs="+", default=["cmu41", "pig39"], help="labelers (names or weights paths)")
    args = p.parse_args(argv)
    if not args.evaldata.is_dir():
        raise SystemExit(f"--evaldata: {args.evaldata} is not a folder")
    to_cmu = SAME_PLACE
    to_pig = {v: k for k, v in SAME_PLACE.items()}
    try:
        models = {name: bench.load_labeler(name) for name in args.models}
    except (OSError, ValueError) as err:
        raise SystemExit(f"--models: {err}") from None
    print("| files | model | frames | " + bench.HEADER.split("| frames | ", 1)[1])
    for name, model in models.items():
        cmu_names = "LFWT" in model.label_names
        names = to_cmu if cmu_names else to_pig
        for lab, files in bench.FILES.items():
            rows, frames = [], 0
            for rel in files:
                seq = renamed(bench.read(args.evaldata / rel), names)
                frames += len(seq.points)
                rows.append(bench.score_file(model, seq, args.seed, model.num_labels))
                print(f"_{name} on {Path(rel).stem}: done_", file=sys.stderr, flush=True)
            own = (lab == "cmu41") == cmu_names
            tag = f"**{lab} files** ({'its own lab' if own else 'another lab'})"
            print(bench.row(tag, name, frames, bench.pool(rows, model.num_labels)))


if __name__ == "__main__":
    main()
