"""PanoMan benchmark (paper 004 §6): fitting to sparse constraints, large twist, timing.

Sections:
- ``model``: the shipped components (support sizes, variance explained on held-out seed-1 samples
  of each subset) and how well ``g`` (eq. 5) gives back held-out body meshes from their exact,
  projected and beta(theta)-predicted RLA vectors.
- ``fit``: held-out full-motion meshes (new identities of PCA pool seed 1, new body poses with
  procedural twist, finger poses and facial expressions, all from seed 1 streams; the model was
  built from seed 0) are fitted from sparse constraints: the 78 joint positions (the rig's RBF
  regressor applied to the mesh, hand joints included) and 20 surface points (vertices of the
  CMU marker layout). Reported: mean and max per-vertex error against the true mesh for the best
  LBS fit of ``BodyLayer`` (PCA shape, 77 joint rotations, translation; plain LBS) and for
  PanoMan (initialised from that fit, then the discrete-shell fit in its subspace), and the
  seconds per frame of each.
- ``twist``: the mean body with the left hand turned 150 degrees about the forearm: plain LBS
  versus PanoMan fitted to the same hand and body (every vertex the forearm joint does not
  influence is a handle), started from the rest pose and from the LBS mesh; minimum
  cross-section and volume of the forearm relative to rest, and a PNG.

    OMP_NUM_THREADS=2 python benchmarks/panoman.py [--sections fit twist] [--frames 50] [--png docs/panoman_twist.png]
"""

from __future__ import annotations

import argparse
import time

import numpy as np
import torch

from unibody import BodyLayer
from unibody.mocap.layout import MarkerLayout
from unibody.panoman import dataset
from unibody.panoman.body_fit import fit_body, regressor_matrix
from unibody.panoman.fit import fit as pano_fit
from unibody.panoman.model import PanoMan
from unibody.panoman.shell import Handles, ShellConfig
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


def section_fit(model: PanoMan, frames: int, config: ShellConfig, joint_steps: int, mesh_steps: int) -> None:
    samples = held_out(frames)
    gt = samples.posed.double()
    ids = surface_points()
    layer = BodyLayer.from_pca(num_components=10, dtype=torch.float64)
    jids, jw = model.joint_regressor
    reg = regressor_matrix(jids, jw, gt.shape[1])
    joints = (gt[:, jids] * jw[None, ..., None].double()).sum(2)  # (B, 77, 3)
    t0 = time.perf_counter()
    fit = fit_body(layer, ids, gt[:, ids], reg, joints, joint_steps=joint_steps, mesh_steps=mesh_steps)
    t_lbs = (time.perf_counter() - t0) / frames
    import scipy.sparse as sp

    i = reg.indices().numpy()
    regs = sp.csr_matrix((reg.values().numpy(), (i[0], i[1])), shape=tuple(reg.shape))
    rows = []
    for i in range(frames):
        handles = Handles(ids.numpy(), gt[i, ids].numpy(), regs, joints[i].numpy())
        truth = gt[i].numpy()
        row = [*errors(fit.vertices[i].numpy(), truth)]
        res = pano_fit(model, fit.shape[i], handles, reference=fit.vertices[i], config=config)
        row += [*errors(res.vertices, truth), res.seconds]
        rows.append(row)
        print(
            f"frame {i:3d}: LBS {row[0] * 1e3:6.2f} / {row[1] * 1e3:6.1f} mm   PanoMan {row[2] * 1e3:6.2f} / "
            f"{row[3] * 1e3:6.1f} mm {row[4]:.1f} s",
            flush=True,
        )
    r = np.array(rows)
    print(
        f"\n{frames} held-out full-motion meshes; constraints: 77 joints (sparse regressor) + {len(ids)} surface points"
    )
    print("| method | mean per-vertex error (mm) | max per frame, mean (mm) | max over all (mm) | s / frame |")
    print("|---|---|---|---|---|")
    print(
        f"| BodyLayer LBS fit | {r[:, 0].mean() * 1e3:.2f} | {r[:, 1].mean() * 1e3:.1f} | {r[:, 1].max() * 1e3:.1f} "
        f"| {t_lbs:.2f} |"
    )
    for label, c in (("PanoMan (shell fit from the LBS fit)", 2),):
        print(
            f"| {label} | {r[:, c].mean() * 1e3:.2f} | {r[:, c + 1].mean() * 1e3:.1f} | {r[:, c + 1].max() * 1e3:.1f} "
            f"| {t_lbs:.2f} + {r[:, c + 2].mean():.2f} |"
        )


def section_model(model: PanoMan, n: int = 10) -> None:
    """Components (support sizes), held-out RLA fit, the mesh g gives back, beta(theta) error."""
    from unibody.panoman.reconstruct import reconstruct_rla
    from unibody.panoman.rla import rla

    e = model.topology.num_edges
    print("| decomposition | components | support median / max (edges) | held-out variance explained |")
    print("|---|---|---|---|")
    held = {
        sub: getattr(dataset, f"{name}_samples")(n, seed=1, dtype=torch.float64)
        for sub, name in (("body", "body"), ("face", "face"), ("hands", "hand"))
    }
    vectors = {sub: rla(h.rest, h.posed, model.topology) for sub, h in held.items()}
    for d in model.decompositions:
        x = vectors[d.subset][0 if d.quantity == "rl" else 1] - d.mean.double()
        m = torch.from_numpy(d.matrix(e).toarray())
        w = torch.linalg.lstsq(m, x.T).solution
        explained = 1 - float((x - (m @ w).T).pow(2).sum() / x.pow(2).sum())
        sizes = d.support_sizes().float()
        print(
            f"| {d.quantity.upper()} {d.subset} | {d.num_components} | {sizes.median():.0f} / {sizes.max():.0f} "
            f"| {explained * 100:.1f} % |"
        )
    h = held["body"]
    rl, ra = vectors["body"]
    beta = model.project(rl, ra)
    print(f"\n{n} held-out body meshes (seed 1), per-vertex error of g (eq. 5), rigidly aligned:")
    print("| RLA vector | RL rms | RA rms (rad) | mean error (mm) | max (mm) |")
    print("|---|---|---|---|---|")
    rows = (
        ("exact (the mesh's own)", rl, ra),
        ("projected on the components", *model.rla(beta, corrected=False)),
        ("projected + correction MLP", *model.rla(beta)),
        ("beta(theta) from the true pose", *model.rla(model.beta_from_pose(h.pose.double()))),
    )
    for label, a, b in rows:
        v = reconstruct_rla(a, b, h.rest, model.topology, reference=h.posed)
        d = (v - h.posed).norm(dim=-1)
        print(
            f"| {label} | {(a - rl).pow(2).mean().sqrt():.4f} | {(b - ra).pow(2).mean().sqrt():.4f} | "
            f"{d.mean() * 1e3:.2f} | {d.max() * 1e3:.1f} |"
        )


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
    # handles: every vertex the forearm joint does not influence (the hand and fingers, turned
    # rigidly, and the rest of the body); the forearm and both its blend zones are free
    w = rig.dense_skinning_weights().numpy()
    ids = np.nonzero(w[:, ja] <= 1e-3)[0]
    handles = Handles(ids, lbs[ids])
    twisted = BodyLayer.from_pca(num_components=10, procedural=True, dtype=torch.float64)
    results = {
        "plain LBS": lbs,
        "LBS + procedural twist joints": twisted.pose(prepared, local, absolute=True).vertices[0].numpy(),
    }
    fits = {}
    for tag, init in (
        ("PanoMan, from the rest pose", prepared.rest_vertices[0]),
        ("PanoMan, from the LBS mesh", out.vertices[0]),
    ):
        fits[tag] = pano_fit(model, alpha[0], handles, reference=init, config=config)
        results[tag] = fits[tag].vertices
    print(f"\nforearm, hand turned 150 deg; {len(ids)} handles, {rig.num_vertices - len(ids)} free vertices")
    print("| mesh | min cross-section / rest | volume / rest | fit s | iterations | largest handle error (mm) |")
    print("|---|---|---|---|---|---|")
    for tag, v in results.items():
        area = tw.limb_profile(v, faces, pj[ja], pj[jb], ts)
        f = fits.get(tag)
        extra = (
            "| | | |" if f is None else f"| {f.seconds:.1f} | {len(f.energy) - 1} | {f.handle_error.max() * 1e3:.2f} |"
        )
        volume = np.trapezoid(area, ts) / np.trapezoid(area0, ts)
        print(f"| {tag} | {(area / area0).min() * 100:.1f} % | {volume * 100:.1f} % {extra}")
    if png:
        from PIL import Image

        all_faces = rig.faces.numpy()
        panels = [tw.panel(v, all_faces, pj[ja], pj[jb], f"forearm, 150 deg: {tag}") for tag, v in results.items()]
        Image.fromarray(np.concatenate(panels, axis=1)).save(png)
        print(f"wrote {png}")


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--sections", nargs="+", default=["model", "fit", "twist"], choices=["model", "fit", "twist"])
    p.add_argument("--frames", type=int, default=50)
    p.add_argument("--model", default=None, help="a PanoMan file (default: the shipped one)")
    p.add_argument("--png", default="docs/panoman_twist.png")
    p.add_argument("--threads", type=int, default=1, help="torch threads (1 is fastest on a shared 2-core machine)")
    p.add_argument("--iterations", type=int, default=ShellConfig.iterations)
    p.add_argument("--joint-steps", type=int, default=100, help="L-BFGS iterations of the LBS fit, joints stage")
    p.add_argument("--mesh-steps", type=int, default=60, help="L-BFGS iterations of the LBS fit, mesh stage")
    p.add_argument("--refactor-every", type=int, default=ShellConfig.refactor_every)
    args = p.parse_args()
    torch.set_num_threads(args.threads)
    model = PanoMan.load(args.model)
    config = ShellConfig(iterations=args.iterations, refactor_every=args.refactor_every)
    if "model" in args.sections:
        section_model(model)
    if "fit" in args.sections:
        section_fit(model, args.frames, config, args.joint_steps, args.mesh_steps)
    if "twist" in args.sections:
        section_twist(model, config, args.png)


if __name__ == "__main__":
    main()
