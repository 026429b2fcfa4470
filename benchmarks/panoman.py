"""PanoMan benchmark (paper 004 §6): fitting to sparse constraints, large twist, timing.

Sections:
- ``fit``: held-out full-motion meshes (new identities of PCA pool seed 1, new body poses with
  procedural twist, finger poses and facial expressions, all from seed 1 streams; the model was
  built from seed 0) are fitted from sparse constraints: the 78 joint positions (the rig's RBF
  regressor applied to the mesh, hand joints included) and 20 surface points (vertices of the
  CMU marker layout). Reported: mean and max per-vertex error against the true mesh for the best
  LBS fit of ``BodyLayer`` (PCA shape, 77 joint rotations, translation; plain LBS) and for
  PanoMan (initialised from that fit, then the discrete-shell fit in its subspace), and the
  seconds per frame of each.
- ``twist``: the mean body with the left hand turned 150 degrees about the forearm: plain LBS
  versus PanoMan fitted to the same hand and body (all vertices except the forearm are
  handles); minimum cross-section and volume of the forearm relative to rest, and a PNG.

    OMP_NUM_THREADS=2 python benchmarks/panoman.py [--sections fit twist] [--frames 50] [--png docs/panoman_twist.png]
"""

from __future__ import annotations

import argparse
import math
import time

import numpy as np
import torch

from unibody import BodyLayer
from unibody.mocap.layout import MarkerLayout
from unibody.panoman import dataset
from unibody.panoman.body_fit import fit_body, joint_regressor
from unibody.panoman.model import PanoMan
from unibody.panoman.shell import Handles, ShellConfig, fit_shell
from unibody.rig import Rig

POINTS = "LFHD RFHD C7 CLAV STRN T10 LSHO RSHO LELB RELB LWRA RWRA LFWT RFWT LKNE RKNE LANK RANK LTOE RTOE".split()


def surface_points() -> torch.Tensor:
    """(20,) canonical vertex ids: the CMU layout's markers listed in POINTS."""
    layout = MarkerLayout.load("cmu41")
    return torch.tensor([int(layout.vertices[layout.index(x)]) for x in POINTS])


def held_out(n: int, seed: int = 1) -> dataset.PanoSamples:
    """Full-motion meshes (body + hands + face) of held-out identities and motions."""
    return dataset.full_samples(n, seed=seed)


def errors(v: np.ndarray, gt: np.ndarray) -> tuple[float, float]:
    d = np.linalg.norm(v - gt, axis=-1)
    return float(d.mean()), float(d.max())


def section_fit(model: PanoMan, frames: int, config: ShellConfig) -> None:
    samples = held_out(frames)
    gt = samples.posed.double()
    ids = surface_points()
    layer = BodyLayer.from_pca(num_components=10, dtype=torch.float64)
    reg = joint_regressor(layer)
    regn = reg.to_dense().numpy()
    joints = torch.einsum("jv,bvc->bjc", reg.to_dense(), gt)
    t0 = time.perf_counter()
    fit = fit_body(layer, ids, gt[:, ids], reg, joints)
    t_lbs = (time.perf_counter() - t0) / frames
    import scipy.sparse as sp

    regs = sp.csr_matrix(regn)
    rows = []
    for i in range(frames):
        sub = model.subspace(fit.shape[i])
        handles = Handles(ids.numpy(), gt[i, ids].numpy(), regs, joints[i].numpy())
        res = fit_shell(model.topology, sub, fit.vertices[i].numpy(), handles, config=config)
        rows.append((*errors(fit.vertices[i].numpy(), gt[i].numpy()), *errors(res.vertices, gt[i].numpy()), res.seconds))
        print(f"frame {i:3d}: LBS {rows[-1][0] * 1e3:6.2f} / {rows[-1][1] * 1e3:6.1f} mm   "
              f"PanoMan {rows[-1][2] * 1e3:6.2f} / {rows[-1][3] * 1e3:6.1f} mm   {res.seconds:.2f} s", flush=True)
    r = np.array(rows)
    print(f"\n| method | mean per-vertex error (mm) | max, mean over frames (mm) | max over all (mm) | s / frame |")
    print("|---|---|---|---|---|")
    print(f"| BodyLayer LBS fit | {r[:, 0].mean() * 1e3:.2f} | {r[:, 1].mean() * 1e3:.1f} | {r[:, 1].max() * 1e3:.1f} "
          f"| {t_lbs:.2f} |")
    print(f"| PanoMan (from the LBS fit) | {r[:, 2].mean() * 1e3:.2f} | {r[:, 3].mean() * 1e3:.1f} | "
          f"{r[:, 3].max() * 1e3:.1f} | {r[:, 4].mean() + t_lbs:.2f} |")


def section_twist(model: PanoMan, config: ShellConfig, png: str | None) -> None:
    import twist as tw  # benchmarks/twist.py: cross-sections, limb faces, twisted pose, picture panel

    rig = Rig.canonical()
    layer = BodyLayer.from_pca(num_components=10, dtype=torch.float64)
    alpha = torch.zeros(1, 10, dtype=torch.float64)
    prepared = layer.prepare_identity(alpha)
    rest = prepared.rest_vertices[0].numpy()
    names = rig.joint_names
    label, start, end, joint, (t0, t1) = tw.CASES[0]
    faces = tw.limb_faces(rig, start)
    ts = np.linspace(t0, t1, tw.PLANES)
    ja, jb = names.index(start), names.index(end)
    rj = prepared.rest_joints[0].numpy()
    area0 = tw.limb_profile(rest, faces, rj[ja], rj[jb], ts)
    local = tw.twisted_pose(prepared, rig, joint, start, end, 150.0)
    out = layer.pose(prepared, local, absolute=True)
    lbs, pj = out.vertices[0].numpy(), out.joints[0].numpy()
    # handles: every vertex not skinned mostly to the forearm
    w = rig.dense_skinning_weights().numpy()
    free = w[:, ja] >= 0.5
    ids = np.nonzero(~free)[0]
    sub = model.subspace(alpha[0])
    t = time.perf_counter()
    res = fit_shell(model.topology, sub, lbs, Handles(ids, lbs[ids]), config=config)
    dt = time.perf_counter() - t
    results = {}
    for tag, v in (("plain LBS", lbs), ("PanoMan", res.vertices)):
        area = tw.limb_profile(v, faces, pj[ja], pj[jb], ts)
        results[tag] = ((area / area0).min(), np.trapezoid(area, ts) / np.trapezoid(area0, ts), v)
    print(f"\nforearm, hand turned 150 deg ({res.seconds:.1f} s fit, {len(res.energy) - 1} iterations):")
    print("| mesh | min cross-section / rest | volume / rest |")
    print("|---|---|---|")
    for tag, (a, vol, _) in results.items():
        print(f"| {tag} | {a * 100:.1f} % | {vol * 100:.1f} % |")
    if png:
        from PIL import Image

        all_faces = rig.faces.numpy()
        panels = [tw.panel(v, all_faces, pj[ja], pj[jb], f"forearm, 150 deg: {tag}") for tag, (_, _, v) in results.items()]
        Image.fromarray(np.concatenate(panels, axis=1)).save(png)
        print(f"wrote {png}")
    _ = dt, math


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--sections", nargs="+", default=["fit", "twist"], choices=["fit", "twist"])
    p.add_argument("--frames", type=int, default=50)
    p.add_argument("--model", default=None, help="a PanoMan file (default: the shipped one)")
    p.add_argument("--png", default="docs/panoman_twist.png")
    p.add_argument("--threads", type=int, default=2)
    args = p.parse_args()
    torch.set_num_threads(args.threads)
    model = PanoMan.load(args.model)
    config = ShellConfig()
    if "fit" in args.sections:
        section_fit(model, args.frames, config)
    if "twist" in args.sections:
        section_twist(model, config, args.png)


if __name__ == "__main__":
    main()
