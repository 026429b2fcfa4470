"""How much of the teacher a decoder of C modes per active joint can hold (issue 40's distortion target).

The correctives map each active joint's C = 24 activations linearly to displacements of its mask
(paper 000 §3.5.2). Whatever the MLP does, the displacements lie in the span of the decoders; this
asks how much of the teacher's strain relief that span can carry. On held-out identities x the
stress poses of ``benchmarks/correctives.py``, the teacher's rest-space targets are projected, per
pose, on

- the shipped decoders' span (the activations that fit best: an oracle no MLP beats with them);
- per-joint PCA bases of the training targets (``--data``: the chunks the weights were trained on,
  ``scripts/train_correctives.py generate``) with C modes each, for each C in ``--modes``: the
  best C-mode decoders of that data (up to the overlap of the masks);

in L2 and in edge differences (what edge strain sees; plus 0.1 of the L2 term), then skinned by
the rig and measured as ``benchmarks/correctives.py`` measures. ``--rig twist``: the procedural-twist
rig's weights, targets (``d_twist``) and skinning. The reduction is against plain LBS.

    OMP_NUM_THREADS=2 python benchmarks/correctives_span.py --data build/correctives-data-anchor-mix [--rig twist]
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import numpy as np
import torch

from unibody import BodyLayer
from unibody.body import PreparedIdentity
from unibody.correctives.metrics import SurfaceMeasures
from unibody.correctives.model import Correctives
from unibody.correctives.stress import stress_poses
from unibody.correctives.training import TeacherSetup, draw_identities, teacher_targets, twist_targets
from unibody.synth.poses import keyed_generator


def mask_basis(model: Correctives, decoders: list[torch.Tensor]) -> torch.Tensor:
    """(U, 3, sum C_k) every active joint's modes (3 V_k, C_k) placed on its mask's union rows."""
    at = torch.searchsorted(model.union, model.vertex_ids)
    out = torch.zeros(len(model.union), 3, sum(d.shape[1] for d in decoders), dtype=torch.float64)
    col = 0
    for (s, e), d in zip(model._blocks, decoders, strict=True):
        out[at[s:e], :, col : col + d.shape[1]] = d.view(e - s, 3, -1)
        col += d.shape[1]
    return out


class Projector:
    """Least-squares fits of targets (B, U, 3) in a basis (U, 3, K): in L2, and in edge differences."""

    def __init__(self, model: Correctives, faces: np.ndarray) -> None:
        u = len(model.union)
        e = np.unique(np.sort(np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]]), 1), axis=0)
        slot = np.full(model.num_vertices, u)  # off the union: a zero row
        slot[model.union.numpy()] = np.arange(u)
        e = e[(slot[e] < u).any(1)]
        self.ends = torch.from_numpy(slot[e[:, 0]]), torch.from_numpy(slot[e[:, 1]])

    def _diff(self, x: torch.Tensor) -> torch.Tensor:
        z = torch.cat([x, torch.zeros_like(x[:1])])
        return z[self.ends[0]] - z[self.ends[1]]

    def __call__(self, basis: torch.Tensor, d: torch.Tensor, edges: bool) -> torch.Tensor:
        u, b = basis.shape[0], d.shape[0]
        flat, target = basis.reshape(3 * u, -1), d.permute(1, 2, 0).reshape(3 * u, b)
        if edges:
            lhs = torch.cat([self._diff(basis).reshape(-1, flat.shape[1]), 0.1 * flat])
            rhs = torch.cat([self._diff(d.permute(1, 2, 0)).reshape(-1, b), 0.1 * target])
        else:
            lhs, rhs = flat, target
        return (flat @ torch.linalg.lstsq(lhs, rhs).solution).T.reshape(b, u, 3)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--data", required=True, help="folder of training chunks (chunk_*.pt with 'd')")
    ap.add_argument("--modes", type=int, nargs="+", default=[24, 48, 96])
    ap.add_argument("--identities", type=int, default=3, help="the first of the correctives benchmark's (default 3)")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--rig", choices=("plain", "twist"), default="plain")
    args = ap.parse_args()
    torch.set_num_threads(args.threads)
    chunks = sorted(Path(args.data).glob("chunk_*.pt"))
    if not chunks:
        raise SystemExit(f"--data: no chunk_*.pt files in {args.data!r}")
    twist = args.rig == "twist"
    model = Correctives.load(procedural=twist)
    layer = BodyLayer.from_pca(correctives=Correctives.load())  # the plain rig: LBS, the teacher, the measures
    rig = BodyLayer.from_pca(procedural=twist, correctives=model)
    measures = SurfaceMeasures.from_layer(layer)
    meta = model.meta
    setup = TeacherSetup(
        layer,
        volume=bool(meta["teacher_volume"]),
        contact=bool(meta["teacher_contact"]),
        anchor=float(meta["teacher_anchor"]),
    )
    if not torch.equal(setup.union, model.union):
        raise SystemExit("the teacher's region is not the shipped model's union")
    t0 = time.perf_counter()
    key = "d_twist" if twist else "d"
    data = torch.cat([torch.load(c, map_location="cpu", weights_only=True)[key] for c in chunks])  # (N, U, 3)
    at = torch.searchsorted(model.union, model.vertex_ids)
    right = []  # per mask: right singular vectors of its training targets, (3 V_k, r)
    for s, e in model._blocks:
        x = data[:, at[s:e]].reshape(len(data), -1).double()
        right.append(torch.linalg.svd(x, full_matrices=False)[2].T)
    del data
    print(f"{len(chunks)} chunks, per-mask PCA: {time.perf_counter() - t0:.0f} s", flush=True)
    bases = {
        "shipped decoders": mask_basis(
            model, [d.double() for d in model.decode.detach().split((3 * model.sizes).tolist())]
        )
    }
    for c in args.modes:
        bases[f"PCA, {c} modes per joint"] = mask_basis(model, [r[:, :c] for r in right])
    project = Projector(model, layer.faces.numpy().astype(np.int64))
    skin = BodyLayer.from_pca(procedural=twist).double()
    poses, _ = stress_poses(keyed_generator("correctives-stress", args.seed))
    coeffs = draw_identities(layer, args.identities, keyed_generator("correctives-benchmark", args.seed))
    rows: dict[str, list] = {}

    def add(name: str, prepared, verts: torch.Tensor) -> None:  # noqa: ANN001
        s, a = measures.distortion(prepared.rest_vertices, verts)
        rows.setdefault(name, []).append((s.flatten(), a.flatten()))

    for n, c in enumerate(coeffs):
        prepared = layer.prepare_identity(c[None])
        lbs, teacher, d = teacher_targets(layer, prepared, poses, setup, iterations=int(meta["teacher_iterations"]))
        add("LBS", prepared, lbs)
        add("teacher", prepared, teacher)
        if twist:
            add("LBS + twist", prepared, rig.pose(prepared, poses, correctives=False).vertices)
            d = twist_targets(prepared, poses, teacher, setup)
        add("correctives MLP (shipped)", prepared, rig.pose(prepared, poses).vertices)
        p64 = [
            t.double().expand(len(poses), *t.shape[1:])
            for t in (prepared.rest_rotations, prepared.rest_joints, prepared.offsets)
        ]
        for name, basis in bases.items():
            for edges in (False, True):
                full = torch.zeros(len(poses), model.num_vertices, 3, dtype=torch.float64)
                full[:, model.union] = project(basis, d.double(), edges)
                shifted = PreparedIdentity(prepared.rest_vertices.double() + full, *p64)
                add(f"{name}, {'edge' if edges else 'L2'} fit", prepared, skin.pose(shifted, poses.double()).vertices)
        print(f"  identity {n + 1}/{len(coeffs)} ({time.perf_counter() - t0:.0f} s)", flush=True)
    print(f"\n{len(poses)} stress poses x {len(coeffs)} held-out identities; best activations per pose (oracle)")
    base = None
    for name, got in rows.items():
        s, a = torch.cat([g[0] for g in got]), torch.cat([g[1] for g in got])
        base = base or (float(s.mean()), float(a.mean()))
        print(f"{name:42s} strain {float(s.mean()):.4f} ({1 - float(s.mean()) / base[0]:.0%} less than LBS)  "
              f"dihedral {np.degrees(float(a.mean())):.2f} deg ({1 - float(a.mean()) / base[1]:.0%} less)")  # fmt: skip


if __name__ == "__main__":
    main()
