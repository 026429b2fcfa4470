"""Topology-transfer fidelity for Anny (paper 000 Table 1).

For seeded random Anny identities (phenotypes uniform in [0, 1]), transfer the native rest
mesh to the canonical topology and measure, for every canonical vertex, the exact
closest-point distance to the native Anny surface. Reports mean / std / P95 / max in mm,
and the same for the wrap itself (SOMA_wrap.obj against base_body.obj), the baseline.

Excluded vertices: canonical vertices whose tetrahedron base triangle lies in Anny's
inner eye and mouth geometry (segmentation labels eye_cavity.*, eye_back.*, mouth_cavity,
tongue): these inner surfaces have no counterpart the paper compares (its Table 1
excludes eye and mouth bags). Figures over all vertices are printed too.

    python benchmarks/topology.py [--identities 100] [--seed 0] [--threads 2]
"""

from __future__ import annotations

import argparse
import time

import numpy as np
import torch

from unibody import assets
from unibody.geometry.tetra import closest_triangles, quads_to_triangles
from unibody.identity.anny import AnnyIdentity
from unibody.io.obj import read_obj
from unibody.topology import TopologyTransfer

INNER = ["eye_cavity.L", "eye_cavity.R", "eye_back.L", "eye_back.R", "mouth_cavity", "tongue"]


def inner_vertex_mask(identity: AnnyIdentity, transfer: TopologyTransfer) -> torch.Tensor:
    """(V,) canonical vertices whose base triangle touches Anny's inner eye/mouth faces."""
    from anny.face_segmentation import get_face_segmentation_mask

    model = identity.model
    face_mask = get_face_segmentation_mask(model, INNER)
    inner = torch.zeros(identity.num_vertices, dtype=torch.bool)
    inner[model.faces[face_mask].flatten()] = True
    return inner[transfer.face_vertices].any(1)


def _stats(d_mm: np.ndarray) -> str:
    return f"mean {d_mm.mean():.4f}  std {d_mm.std():.4f}  P95 {np.percentile(d_mm, 95):.4f}  max {d_mm.max():.4f}"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--identities", type=int, default=100)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--threads", type=int, default=2)
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    identity = AnnyIdentity.create()
    # The wrap is registered on base_body.obj's quads split as (a, b, c), (a, c, d): that
    # surface is the reference. Anny renders its quads with its own diagonals, which differ on
    # about half of them; distances to that surface are printed too (quad non-planarity).
    base, base_quads = read_obj(assets.source_dir() / "base_body.obj")
    faces = quads_to_triangles(base_quads)
    anny_faces = identity.faces()
    transfer = TopologyTransfer.from_anny().double()
    inner = inner_vertex_mask(identity, transfer)
    print(f"excluded {int(inner.sum())} of {inner.numel()} canonical vertices (inner eyes/mouth)")

    wrap, _ = read_obj(assets.source_dir() / "SOMA_wrap.obj")
    _, _, d = closest_triangles(torch.from_numpy(wrap), torch.from_numpy(base), faces)
    d_wrap = 1e3 * d.numpy()

    gen = torch.Generator().manual_seed(args.seed)
    params = torch.rand(args.identities, 6, generator=gen, dtype=torch.float64)
    all_d, all_d_anny = [], []
    t0 = time.perf_counter()
    with torch.no_grad():
        for i in range(args.identities):
            native = identity(params[i : i + 1])
            canonical = transfer(native)[0]
            _, _, d = closest_triangles(canonical, native[0], faces)
            all_d.append(1e3 * d.numpy())
            _, _, d = closest_triangles(canonical, native[0], anny_faces)
            all_d_anny.append(1e3 * d.numpy())
            if (i + 1) % 10 == 0:
                print(f"  {i + 1}/{args.identities} identities  ({time.perf_counter() - t0:.0f} s)", flush=True)
    d_all, d_anny = np.stack(all_d), np.stack(all_d_anny)
    keep = ~inner.numpy()
    print(f"Anny, {args.identities} identities (seed {args.seed}), closest-point distance in mm:")
    print(f"  transfer, kept vertices : {_stats(d_all[:, keep])}")
    print(f"  transfer, all vertices  : {_stats(d_all)}")
    print(f"  wrap baseline, kept     : {_stats(d_wrap[keep])}")
    print(f"  wrap baseline, all      : {_stats(d_wrap)}")
    print("against Anny's own render triangulation (other quad diagonals):")
    print(f"  transfer, kept vertices : {_stats(d_anny[:, keep])}")


if __name__ == "__main__":
    main()
