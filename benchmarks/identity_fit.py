"""Identity fitting on the native PCA (128 components): how the parameters' step sizes decide
whether ``fit_identity`` finds the body.

``fit_identity`` descends in unconstrained variables z; each bounded parameter is a sigmoid of
z whose slope grows as ``span ** SPAN_EXPONENT`` (``unibody.fitting.shape_fit._Bounded``). For
each exponent, fit (L-BFGS from the mean body, ``--iterations``) three kinds of bodies, reposed
to the bind pose:

- native-PCA bodies with coefficients ``0.8 N(0, 1)`` and ``1.5 N(0, 1)`` (in the space: the
  fit can reach 0 mm);
- Anny bodies with uniform phenotypes (outside the space: the floor is the space's own error);

and print, per kind, the iterations run, the mean per-vertex error and the worst body's largest
vertex error (mm). The shipped exponent runs in float64 and float32; ``--exponents`` adds
float64 rows of others (the comparison in CHANGELOG: ``--exponents 0 0.75 0.85 1``).

    OMP_NUM_THREADS=1 python benchmarks/identity_fit.py [--bodies 8] [--seeds 5 7] [--iterations 200]
                                                        [--exponents 0 0.75 0.85 1]
"""

from __future__ import annotations

import argparse
import time

import torch

from unibody import BodyLayer
from unibody.fitting import shape_fit


def targets(pca: BodyLayer, anny: BodyLayer, bodies: int, seed: int) -> dict[str, torch.Tensor]:
    """Bind-pose meshes of each kind (float64)."""
    g = torch.Generator().manual_seed(seed)
    out = {}
    with torch.no_grad():
        for scale in (0.8, 1.5):
            coeffs = scale * torch.randn(bodies, pca.identity.num_params, generator=g, dtype=torch.float64)
            out[f"native PCA, {scale} sigma"] = pca.repose_to_bind(pca.prepare_identity(coeffs))
        phenotypes = torch.rand(bodies, 6, generator=g, dtype=torch.float64)
        out["Anny (outside the space)"] = anny.repose_to_bind(anny.prepare_identity(phenotypes))
    return out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--bodies", type=int, default=8, help="bodies per kind and seed")
    parser.add_argument("--seeds", type=int, nargs="+", default=[5, 7])
    parser.add_argument("--iterations", type=int, default=200, help="L-BFGS iterations at most")
    parser.add_argument(
        "--exponents", type=float, nargs="+", default=[], help="float64 rows for these too (default: the shipped one)"
    )
    args = parser.parse_args()
    torch.set_num_threads(1)
    pca64, anny64 = BodyLayer.from_pca().double(), BodyLayer.from_anny().double()
    sets = [targets(pca64, anny64, args.bodies, s) for s in args.seeds]
    kinds = list(sets[0])
    shipped = shape_fit.SPAN_EXPONENT
    runs = [(e, torch.float64) for e in sorted({shipped, *args.exponents})] + [(shipped, torch.float32)]
    layers = {torch.float64: pca64, torch.float32: BodyLayer.from_pca()}
    print(f"{len(args.seeds)} seeds x {args.bodies} bodies per kind; L-BFGS at most {args.iterations} iterations")
    print("| exponent | dtype | " + " | ".join(f"{k}: iterations, mean / worst max mm" for k in kinds) + " | s |")
    print("|---|---|" + "---|" * len(kinds) + "---|")
    try:
        for exponent, dtype in runs:
            shape_fit.SPAN_EXPONENT = exponent
            cells, t0 = [], time.perf_counter()
            for kind in kinds:
                its, errors = [], []
                for s in sets:
                    fit = shape_fit.fit_identity(layers[dtype], s[kind].to(dtype), lbfgs_steps=args.iterations)
                    its.append(fit.lbfgs_steps)
                    errors.append(fit.per_vertex_error.double())
                e = 1e3 * torch.cat(errors)
                cells.append(f"{'/'.join(map(str, its))}, {float(e.mean()):.3f} / {float(e.amax(1).max()):.3f}")
            name = f"**{exponent:g}** (shipped)" if exponent == shipped else f"{exponent:g}"
            dt = str(dtype).removeprefix("torch.")
            print(f"| {name} | {dt} | " + " | ".join(cells) + f" | {time.perf_counter() - t0:.0f} |", flush=True)
    finally:
        shape_fit.SPAN_EXPONENT = shipped


if __name__ == "__main__":
    main()
