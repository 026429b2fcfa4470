"""Shape-space reconstruction error (paper 000 §4.4, Table 5 protocol; issue 41).

Spaces (``--spaces``, default the shipped ``v1`` and ``v2``; any asset path works, e.g. one written
by ``unibody shape-space build``) are judged on bodies they were not trained on:

1. Held-out Anny identities (``--identities`` per recipe, ``--seed`` 1; v1 and v2 were built
   with seed 0): the v1 recipe (6 phenotypes, local changes active with probability 1/8 in
   [-0.5, 0.5]) and the v2 recipe (11 phenotypes with the ethnicity blend, local changes
   active with probability 1/8 in [-1, 1]), each reposed to the bind A-pose with its Hips at
   ``HIPS_M`` (:func:`unibody.identity.shape_space.to_bind_pose`), projected with the global
   translation free.
2. The three template meshes of the evaluation data (SMPL man and woman, SMPL-X neutral, CC BY
   4.0, never trained on), registered onto the canonical topology (:mod:`_shape_targets`,
   cached), under four protocols: "issue" (skeleton fit, repose to the bind pose, projection:
   the measurement of issue 41, where the registered body stands on the floor while Anny's
   bodies have their origin near the pelvis), "Hips placed" (the Hips moved to ``HIPS_M``),
   "translation-free" (and the global translation free) and "+ inversion" (then
   ``--inversion-rounds`` rounds of un-posing the registered mesh by pose inversion against
   the current projection, as paper 000 reposes its scans). ``--controls`` held-out Anny
   identities go through the same automatic registration, next to the same identities
   through the hand-made wrap: their gap is what the pipeline costs a body that is in the span.
3. ``--table5``: every space against every set of bodies, with two spaces made by the user
   builder from a generated SMPL-format model (alone, and with Anny).

Reported: per-vertex distance between a body and its projection, over all 18,056 canonical
vertices, in mm. Also: what float16/int8 storage costs, and ``forward`` timing of each space
against Anny + topology transfer. ``--fit-identities N`` adds the fitted rows of backends that
are not linear spaces (Anny's 6 phenotypes; the user's SMPL / MHR / GarmentMeasurements files
when ``UNIBODY_SMPL_FILE`` / ``UNIBODY_MHR_DIR`` / ``UNIBODY_GARMENT_DIR`` are set), fitted with
:func:`unibody.fitting.shape_fit.fit_identity` through the whole pipeline.

    OMP_NUM_THREADS=1 python benchmarks/shape_spaces.py [--spaces v1 v2 PATH ...] [--identities 200]
        [--seed 1] [--controls 3] [--inversion-rounds 3] [--no-templates] [--table5] [--fit-identities 0]
"""

from __future__ import annotations

import argparse
import os
import sys
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "scripts"))
sys.path.insert(0, str(Path(__file__).resolve().parent))
import _shape_targets as targets_  # noqa: E402
import build_pca  # noqa: E402  (the training recipe, sampler and reposing, shared on purpose)

from unibody import BodyLayer  # noqa: E402
from unibody.fitting.inversion import PRESETS as INVERSION_PRESETS  # noqa: E402
from unibody.fitting.inversion import PoseInverter  # noqa: E402
from unibody.fitting.shape_fit import fit_identity  # noqa: E402
from unibody.geometry.mesh import vertex_normals  # noqa: E402
from unibody.identity import ENV_VARS, create  # noqa: E402
from unibody.identity.pca import IPCAState, PCAIdentity, asset_path, ipca_finalize  # noqa: E402
from unibody.identity.shape_space import AnnyRecipe, anny_params, to_bind_pose  # noqa: E402
from unibody.rig import Rig  # noqa: E402

KS = (10, 32, 64, 128)
USER_BACKENDS = ("smpl", "mhr", "garment")
FIT_ADAM, FIT_LBFGS = 0, 400
LABELS = {"smpl": "SMPL", "smplh": "SMPL-H", "smplx": "SMPL-X", "mhr": "MHR", "garment": "GarmentMeasurements"}


@dataclass(frozen=True)
class Basis:
    """A linear shape space on the canonical topology.

    Attributes:
        name: row label.
        mean: (V, 3) m.
        directions: (K, V, 3) shape directions in order of importance (need not be orthonormal).
    """

    name: str
    mean: torch.Tensor
    directions: torch.Tensor


@dataclass(frozen=True)
class Row:
    """Per-vertex reconstruction error (mm) of one shape space with k parameters.

    ``held_out``: meshes evaluated; ``fit_s``: seconds the fit took (None for a projection).
    """

    name: str
    k: int
    mean: float
    median: float
    p95: float
    held_out: int = 0
    fit_s: float | None = None


def error_row(name: str, k: int, per_vertex_mm: np.ndarray, held_out: int, fit_s: float | None = None) -> Row:
    """A row from per-vertex distances (any shape), mm."""
    d = per_vertex_mm.ravel()
    return Row(name, k, float(d.mean()), *(float(x) for x in np.percentile(d, [50, 95])), held_out, fit_s)


def translations(num_vertices: int) -> torch.Tensor:
    """(3, 3V) float64: the three global translations as flattened mesh directions."""
    t = torch.zeros(3, num_vertices, 3, dtype=torch.float64)
    for i in range(3):
        t[i, :, i] = 1.0
    return t.reshape(3, -1)


def residuals(
    basis: Basis, meshes: torch.Tensor, ks: tuple[int, ...] = KS, *, translation: bool = False
) -> dict[int, torch.Tensor]:
    """``{k: (N, V, 3) mesh - projection}`` onto the first k directions of ``basis`` (float64).

    Least squares through one QR of the directions: the first columns of Q span exactly the
    first k directions, so one factorisation serves every k. ``translation``: the three global
    translations come first and are always free (the projection "up to where the body stands").
    """
    d = basis.directions.to(torch.float64).reshape(basis.directions.shape[0], -1)
    t = translations(meshes.shape[1]) if translation else d.new_zeros(0, d.shape[1])
    q, _ = torch.linalg.qr(torch.cat([t, d]).T)  # (3V, T + K)
    resid = (meshes.to(torch.float64) - basis.mean.to(torch.float64)).reshape(meshes.shape[0], -1)
    coef = resid @ q
    out = {}
    for k in ks:
        if k > d.shape[0]:
            continue
        n = t.shape[0] + k
        out[k] = (resid - coef[:, :n] @ q[:, :n].T).reshape(meshes.shape)
    return out


def evaluate(
    basis: Basis, meshes: torch.Tensor, ks: tuple[int, ...] = KS, *, translation: bool = False, name: str | None = None
) -> list[Row]:
    """Rows of the per-vertex error of the projections of meshes (N, V, 3) (see :func:`residuals`)."""
    return [
        error_row(name or basis.name, k, 1e3 * err.norm(dim=-1).numpy(), meshes.shape[0])
        for k, err in residuals(basis, meshes, ks, translation=translation).items()
    ]


def storage_error(reference: torch.Tensor, stored: torch.Tensor, std: torch.Tensor, coeffs: torch.Tensor) -> str:
    """Per-vertex distance (mm) between meshes made with reference and stored directions.

    Args:
        reference, stored: (K, V, 3) directions; std: (K,) m; coeffs: (N, K) in stds.
    """
    diff = (coeffs * std) @ (stored - reference).reshape(reference.shape[0], -1).to(coeffs.dtype)
    d = 1e3 * diff.reshape(coeffs.shape[0], -1, 3).norm(dim=-1)
    p95 = float(np.percentile(d.flatten().numpy(), 95))
    return f"mean {float(d.mean()):.4f} mm, P95 {p95:.4f} mm, max {float(d.max()):.4f} mm"


def int8_directions(directions: torch.Tensor) -> torch.Tensor:
    """The directions rounded to int8 with one scale per direction (max |entry| -> 127)."""
    flat = directions.reshape(directions.shape[0], -1).to(torch.float64)
    scale = flat.abs().amax(dim=1, keepdim=True) / 127.0
    return (torch.round(flat / scale) * scale).reshape(directions.shape)


@dataclass(frozen=True)
class FitSettings:
    """How the fitted rows run :func:`unibody.fitting.shape_fit.fit_identity` (``batch``: identities per call)."""

    adam: int
    lbfgs: int
    lr: float
    batch: int


def fitted_row(label: str, layer: BodyLayer, targets: torch.Tensor, settings: FitSettings) -> Row:
    """Fit the layer's identity parameters to ``targets`` (N, V, 3), bind A-pose; one row."""
    n, k = targets.shape[0], layer.identity.num_params
    dtype = layer.skeleton.bind_rot.dtype
    errors, t0 = [], time.perf_counter()
    for s in range(0, n, settings.batch):
        e = min(n, s + settings.batch)
        print(f"{label} ({k} parameters): fitting identities {s}..{e - 1} of {n}", flush=True)
        fit = fit_identity(
            layer,
            targets[s:e].to(dtype),
            steps=settings.adam,
            lr=settings.lr,
            lbfgs_steps=settings.lbfgs,
            progress=lambda line: print(line, flush=True),
        )
        errors.append(1e3 * fit.per_vertex_error.double().numpy())
    seconds = time.perf_counter() - t0
    per_identity = np.concatenate(errors).mean(axis=1)
    worst = int(per_identity.argmax())
    print(
        f"{label}: mean per-vertex error per identity: median {np.median(per_identity):.3f} mm, "
        f"max {per_identity[worst]:.3f} mm (held-out identity {worst}); under 1 mm: "
        f"{int((per_identity < 1.0).sum())} of {n}; {seconds:.0f} s"
    )
    return error_row(f"{label} (fitted)", k, np.concatenate(errors), n, seconds)


def user_layer(name: str) -> tuple[str, BodyLayer | None, str]:
    """``(label, layer, "")`` for a backend whose user files are present, else ``(label, None, why)``."""
    label, env = LABELS[name], ENV_VARS[name]
    if not os.environ.get(env):
        return label, None, f"{env} is not set (the user's {label} model files; none ship with unibody)"
    try:
        from unibody.registration import topology_transfer  # noqa: F401  (BodyLayer.from_identity needs it)
    except ImportError:
        return label, None, "unibody.registration.topology_transfer is not available (BodyLayer.from_identity needs it)"
    try:
        identity = create(name)
        label = LABELS.get(identity.name, label)
        return label, BodyLayer.from_identity(identity), ""
    except (OSError, ValueError, TypeError, KeyError) as exc:
        return label, None, f"could not build it from ${env}: {exc}"


def fitted_rows(anny_all: BodyLayer, targets: torch.Tensor, settings: FitSettings) -> list[Row]:
    """Rows of the backends fitted through the pipeline (Anny twice, then user backends if present)."""
    rows = [
        fitted_row("Anny, 6 phenotypes", BodyLayer.from_anny(), targets, settings),
        fitted_row("Anny, phenotypes + 256 local changes", anny_all, targets, settings),
    ]
    for name in USER_BACKENDS:
        label, layer, why = user_layer(name)
        if layer is None:
            print(f"{label} row skipped: {why}")
        else:
            rows.append(fitted_row(label, layer, targets, settings))
    return rows


def _time(fn, reps: int) -> float:
    fn()
    t0 = time.perf_counter()
    for _ in range(reps):
        fn()
    return 1e3 * (time.perf_counter() - t0) / reps


def timing(pca: PCAIdentity, layer) -> list[str]:
    """ms per call: PCA forward vs Anny (local changes all) + topology transfer, float32."""
    lines = []
    with torch.no_grad():
        for b in (1, 32):
            c = torch.randn(b, pca.num_params, generator=torch.Generator().manual_seed(0))
            p = layer.identity.default_params(b)
            t_pca = _time(lambda c=c: pca(c), 20)
            t_anny = _time(lambda p=p: layer.topology(layer.identity(p)), 5)
            lines.append(f"| {b} | {t_pca:.3f} | {t_anny:.2f} | {t_anny / t_pca:.0f}x |")
    return lines


# --------------------------------------------------------------------------- spaces and bodies


def load_space(spec: str) -> tuple[str, PCAIdentity]:
    """``(label, float64 PCAIdentity)`` of "v1", "v2" (shipped) or a path to an asset."""
    path = asset_path(spec)
    label = spec if spec in ("v1", "v2") else Path(spec).stem
    return label, PCAIdentity.from_asset(path, dtype=torch.float64)


def space_basis(label: str, pca: PCAIdentity) -> Basis:
    return Basis(label, pca.mean, pca.basis.reshape(pca.num_params, -1, 3))


def anny_heldout(count: int, seed: int) -> dict[str, torch.Tensor]:
    """Held-out Anny bodies (bind pose, Hips at HIPS_M, float64) of the v1 and v2 recipes.

    v1: ``build_pca.sample_params`` of the v1 recipe with ``seed`` (the v1 space was built with
    seed 0); v2: :func:`anny_params` of the default :class:`AnnyRecipe` from
    ``default_rng(seed)`` (the v2 build draws from ``default_rng([0, 0, chunk])``).
    """
    layer = BodyLayer.from_anny(local_changes="all", phenotypes="all", dtype=torch.float64)
    num_local = layer.identity.num_params - 11
    sets = {
        "Anny, v1 recipe": build_pca.sample_params(build_pca.Recipe(), count, seed, num_local),
        "Anny, v2 recipe": anny_params(AnnyRecipe(), np.random.default_rng(seed), count, num_local),
    }
    out = {}
    for name, params in sets.items():
        parts = []
        for s in range(0, count, 50):
            with torch.no_grad():
                rest = layer.topology(layer.identity(torch.from_numpy(params[s : s + 50])))
            parts.append(to_bind_pose(layer, rest))
        out[name] = torch.cat(parts)
    return out


def rig_layer() -> BodyLayer:
    """The canonical rig without identity backend, float64 (skeleton fit, reposing, inversion)."""
    return BodyLayer(Rig.canonical(), None, None).double()


def issue_placement(layer: BodyLayer, meshes: torch.Tensor) -> torch.Tensor:
    """The issue's protocol: skeleton fit, repose to the bind pose, Hips left where they are."""
    with torch.no_grad():
        return layer.repose_to_bind(layer.prepare_rest(meshes))


def unpose(layer: BodyLayer, inverter: PoseInverter, body: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
    """Un-pose ``target`` (V, 3) with the pose that maps the rest ``body`` (V, 3) onto it.

    The pose comes from :class:`PoseInverter` (analytic); each target vertex is mapped back by
    the inverse of its blended skinning transform of ``body``'s skeleton, so the result lies in
    ``body``'s rest frame (bind pose, its Hips). Paper 000 §4.4 reposes scans this way.
    """
    with torch.no_grad():
        prepared = layer.prepare_rest(body[None])
        res = inverter.invert(target[None], prepared)
        mats = layer.skin_transforms(prepared, layer.local_rotations(res.pose), res.transl)[2][0]  # (J, 3, 4)
        blended = (layer.skinning.matrix() @ mats.reshape(layer.num_joints, -1)).view(-1, 3, 4)
        return torch.linalg.solve(blended[..., :3], (target - blended[..., 3])[..., None])[..., 0]


def inverted_errors(
    basis: Basis, layer: BodyLayer, inverter: PoseInverter, target: torch.Tensor, rounds: int
) -> dict[int, np.ndarray]:
    """``{k: per-vertex error (V,) mm}``: projection (translation free) alternated with un-posing.

    Start: the skeleton-fit repose (Hips placed); then ``rounds`` times: un-pose the target with
    the pose that maps the current projection onto it (:func:`unpose`), project again.
    """
    out = {}
    start = to_bind_pose(layer, target[None])
    for k, err in residuals(basis, start, translation=True).items():
        x = start[0]
        for _ in range(rounds):
            x = unpose(layer, inverter, x - err[0], target)
            err = residuals(basis, x[None], (k,), translation=True)[k]
        out[k] = 1e3 * err[0].norm(dim=-1).numpy()
    return out


def _fmt_row(cells: list[str]) -> str:
    return "| " + " | ".join(cells) + " |"


def template_section(spaces: dict[str, Basis], rounds: int, controls: int) -> None:
    """The issue's table (and what it is made of) for each space."""
    layer = rig_layer()
    layer_faces = Rig.canonical().faces
    inverter = PoseInverter(layer, INVERSION_PRESETS["analytic"])
    bodies = targets_.template_meshes()
    if controls:
        pairs = targets_.anny_controls(build_pca.sample_params(build_pca.Recipe(), controls, 1, 256))
        for i, (auto, truth) in enumerate(pairs):
            bodies[f"Anny control {i}, automatic registration"] = auto
            bodies[f"Anny control {i}, hand-made wrap"] = truth
    if not bodies:
        print("no template meshes: section skipped")
        return
    ks = " | ".join(str(k) for k in KS)
    print(
        "\n### Bodies from outside the training set: mean per-vertex error (mm) at k components\n"
        "\nprotocols: issue = registration, skeleton fit, repose to the bind pose, projection (as in issue 41); "
        "Hips placed = the same with the Hips moved to HIPS_M (to_bind_pose, how v2 was trained); "
        "translation-free = Hips placed and the global translation free (normal part: the mean of |n . error| "
        "along the body's vertex normals, what is left when sliding along the surface is not counted); "
        f"+ inversion = then {rounds} rounds of un-posing by pose inversion and projection\n"
    )
    print(f"| space | body | protocol | {ks} |\n|---|---|---|" + "---:|" * len(KS))
    for label, basis in spaces.items():
        for name, mesh in bodies.items():
            m = mesh[None].double()
            raw = [float(1e3 * e.norm(dim=-1).mean()) for e in residuals(basis, issue_placement(layer, m)).values()]
            placed_mesh = to_bind_pose(layer, m)
            placed = [float(1e3 * e.norm(dim=-1).mean()) for e in residuals(basis, placed_mesh).values()]
            free_err = residuals(basis, placed_mesh, translation=True)
            free = [float(1e3 * e.norm(dim=-1).mean()) for e in free_err.values()]
            normals = vertex_normals(placed_mesh[0], layer_faces)
            normal = [float(1e3 * (e[0] * normals).sum(-1).abs().mean()) for e in free_err.values()]
            inv = [float(e.mean()) for e in inverted_errors(basis, layer, inverter, mesh.double(), rounds).values()]
            protocols = (("issue", raw), ("Hips placed", placed), ("translation-free", free),
                         ("translation-free, normal part", normal), (f"+ inversion ({rounds})", inv))  # fmt: skip
            for proto, vals in protocols:
                print(_fmt_row([label, name, proto, *(f"{v:.2f}" for v in vals)]), flush=True)
    if controls:
        print("\nAnny controls: per-vertex distance between the automatic and the hand-made correspondence (mm)")
        for i, (auto, truth) in enumerate(pairs):
            rest = 1e3 * (auto - truth).norm(dim=-1)
            bind = 1e3 * (to_bind_pose(layer, auto[None]) - to_bind_pose(layer, truth[None])).norm(dim=-1)
            print(
                f"  control {i}: T-pose {rest.mean():.2f} mean / {rest.max():.1f} max; bind pose {bind.mean():.2f} mean"
            )


def heldout_section(spaces: dict[str, Basis], heldout: dict[str, torch.Tensor]) -> None:
    print(
        "\n### Held-out Anny identities (bind pose, Hips placed, translation-free projection), per-vertex error (mm)\n"
    )
    print("| space | bodies | k | held-out | mean | median | P95 |\n|---|---|---:|---:|---:|---:|---:|")
    for label, basis in spaces.items():
        for name, meshes in heldout.items():
            for r in evaluate(basis, meshes, translation=True):
                print(f"| {label} | {name} | {r.k} | {r.held_out} | {r.mean:.3f} | {r.median:.3f} | {r.p95:.3f} |")


def storage_section(label: str, pca: PCAIdentity, spec: str, meshes: torch.Tensor) -> None:
    directions = pca.basis.reshape(pca.num_params, -1, 3)
    coeffs = pca.project(meshes)
    with np.load(asset_path(spec), allow_pickle=False) as data:
        hi = torch.from_numpy(data["components"].astype(np.float64))
    print(f"\nstorage ({label}): per-vertex distance to the shipped re-orthonormalised directions, same coefficients")
    print(f"  float16 only: {storage_error(directions, hi, pca.std, coeffs)}")
    print(f"  int8 + per-component scale: {storage_error(directions, int8_directions(directions), pca.std, coeffs)}")


TABLE5_DIR = targets_.ROOT / "build" / "shape_space_table5"


def generated_smpl_file(folder: Path) -> Path:
    """A generated SMPL-format model file (tests/smpl_format.py): the SMPL man template (CC BY 4.0),
    random regressor and weights, and 10 smooth shape directions (affine fields of the template,
    0.03 per unit): a file in SMPL's format, not SMPL's shape space."""
    sys.path.insert(0, str(targets_.ROOT / "tests"))
    from smpl_format import make_model, write_npz

    path = folder / "SMPL_GENERATED.npz"
    if not path.is_file():
        model = make_model("smpl", seed=7)
        v = model["v_template"]
        rng = np.random.default_rng(7)
        model["shapedirs"] = np.stack([(v - v.mean(0)) @ (0.03 * rng.normal(size=(3, 3))) for _ in range(10)], axis=2)
        folder.mkdir(parents=True, exist_ok=True)
        write_npz(path, model)
    return path


def builder_spaces(identities: int) -> dict[str, tuple[Path, object]]:
    """Spaces made by the user builder (cached): the generated SMPL-format model alone, and with Anny.

    Returns ``{label: (asset, ShapeSource of the generated model)}``.
    """
    from unibody.cli.shape_commands import source_from_spec
    from unibody.identity.shape_space import build_shape_space

    smpl = source_from_spec(f"smpl={generated_smpl_file(TABLE5_DIR)}", dtype=torch.float64)
    out = {}
    for label, specs in (("builder: generated SMPL", []), ("builder: Anny + generated SMPL", ["anny"])):
        sources = [source_from_spec(sp) for sp in specs] + [smpl]
        n = identities if specs else max(identities // 8, 200)
        path = TABLE5_DIR / (f"anny_smpl_{n}.npz" if specs else f"smpl_only_{n}.npz")
        if not path.is_file():
            print(f"building {label} ({n} identities; cached in {path})", flush=True)
            command = f"unibody shape-space build --from {' '.join([*specs, 'smpl=GENERATED'])}"
            build_shape_space(sources, path, identities=n, chunk=200, components=128 if specs else 20,
                              checkpoint=path.with_suffix(".partial.npz"), metadata={"command": command},
                              progress=lambda line: print("  " + line, flush=True))  # fmt: skip
        out[label] = (path, smpl)
    return out


def table5_section(spaces: dict[str, Basis], heldout: dict[str, torch.Tensor], identities: int) -> None:
    """Each space representing the others' bodies (paper 000 Table 5, side by side)."""
    built = builder_spaces(identities)
    spaces = dict(spaces)
    smpl = None
    for label, (path, source) in built.items():
        pca = PCAIdentity.from_asset(path, num_components=None, dtype=torch.float64)
        spaces[label] = space_basis(label, pca)
        smpl = source
    params = smpl.sampler(np.random.default_rng(4321), 50).double()
    with torch.no_grad():
        gen = to_bind_pose(smpl.layer, smpl.layer.prepare_identity(params).rest_vertices)
    layer = rig_layer()
    bodies = {**heldout, "generated SMPL-format bodies (held out)": gen}
    for name, mesh in targets_.template_meshes().items():
        bodies[f"{name} (translation-free)"] = to_bind_pose(layer, mesh[None].double())
    ks = " | ".join(str(k) for k in KS)
    print("\n### Table 5 side by side: mean per-vertex error (mm) of each space on each set of bodies\n")
    print("All bodies in the bind pose with the Hips placed; projection with the global translation free.\n")
    for name, meshes in bodies.items():
        print(f"\n{name} ({meshes.shape[0]} bodies)\n\n| space | {ks} |\n|---|" + "---:|" * len(KS))
        for label, basis in spaces.items():
            errs = residuals(basis, meshes, translation=True)
            cells = [f"{float(1e3 * errs[k].norm(dim=-1).mean()):.2f}" if k in errs else "—" for k in KS]
            print(_fmt_row([label, *cells]), flush=True)
    print(
        "\nThe generated SMPL-format model's template is the SMPL man mesh itself (tests/smpl_format.py), so the "
        "builder spaces that include it hold that body by construction; they show the mechanism, not SMPL's space."
    )


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--spaces", nargs="+", default=None, help="v1, v2 or asset paths (default: v1 and v2)")
    parser.add_argument("--identities", type=int, default=200, help="held-out Anny identities per recipe")
    parser.add_argument("--seed", type=int, default=1)
    parser.add_argument("--threads", type=int, default=1)
    parser.add_argument("--templates", action=argparse.BooleanOptionalAction, default=True,
                        help="the three template meshes (registered once, cached in build/shape_targets)")  # fmt: skip
    parser.add_argument("--controls", type=int, default=3, help="Anny identities through the automatic registration")
    parser.add_argument("--inversion-rounds", type=int, default=3)
    parser.add_argument("--table5", action="store_true",
                        help="Table 5 side by side, with spaces made by the user builder")  # fmt: skip
    parser.add_argument("--table5-identities", type=int, default=2000, help="identities of the Anny + SMPL space")
    parser.add_argument("--checkpoint", default=None, help="a v1 build checkpoint: adds its float64 basis as a space")
    parser.add_argument("--device", default="cpu", help="only cpu")
    parser.add_argument("--fit-identities", type=int, default=0, help="held-out identities for the fitted rows")
    parser.add_argument("--fit-batch", type=int, default=50, help="identities per fit_identity call")
    parser.add_argument("--fit-adam", type=int, default=FIT_ADAM, help="Adam steps per fit")
    parser.add_argument("--fit-lr", type=float, default=0.05, help="Adam learning rate")
    parser.add_argument("--fit-lbfgs", type=int, default=FIT_LBFGS, help="L-BFGS iterations per fit, after Adam")
    args = parser.parse_args()
    if args.device != "cpu":
        parser.error("--device: only cpu is supported")
    if not 0 <= args.fit_identities <= args.identities:
        parser.error(f"--fit-identities: expected 0..{args.identities} (--identities), got {args.fit_identities}")
    if args.seed == 0:
        parser.error("--seed: 0 is the training seed of v1; choose another for a held-out set")
    torch.set_num_threads(args.threads)
    t0 = time.perf_counter()
    specs = args.spaces or ["v1", *(["v2"] if asset_path("v2").is_file() else [])]
    loaded = {spec: load_space(spec) for spec in specs}
    spaces = {label: space_basis(label, pca) for label, pca in loaded.values()}
    if args.checkpoint:
        with np.load(args.checkpoint, allow_pickle=False) as data:
            state = IPCAState.from_numpy({k: data[k] for k in data.files})
        mean, comps, _ = ipca_finalize(state, 128)
        spaces["v1 float64 (checkpoint)"] = Basis(
            "v1 float64 (checkpoint)", mean.reshape(-1, 3), comps.reshape(128, -1, 3)
        )
    for label, pca in loaded.values():
        print(f"{label}: K = {pca.num_params}, {pca.metadata.get('command', '')}")
    heldout = anny_heldout(args.identities, args.seed)
    heldout_section(spaces, heldout)
    if args.templates:
        template_section(spaces, args.inversion_rounds, args.controls)
    if args.table5:
        table5_section(spaces, heldout, args.table5_identities)
    for spec, (label, pca) in loaded.items():
        storage_section(label, pca, spec, heldout["Anny, v1 recipe"])
    print("\nforward, float32, one thread per --threads:\n")
    print("| space | batch | PCA ms/call | Anny + transfer ms/call | ratio |\n|---|---:|---:|---:|---:|")
    anny = build_pca.anny_layer()
    for spec, (label, _) in loaded.items():
        for line in timing(PCAIdentity.from_asset(asset_path(spec)), anny):
            print(f"| {label} " + line)
    if args.fit_identities:
        settings = FitSettings(args.fit_adam, args.fit_lbfgs, args.fit_lr, args.fit_batch)
        params = build_pca.sample_params(build_pca.Recipe(), args.fit_identities, args.seed, 256)
        targets = build_pca.canonical_samples(anny, params)[1].double()  # fit_identity compares unplaced meshes
        rows = [r for basis in spaces.values() for r in evaluate(basis, targets, translation=True)]
        rows += fitted_rows(anny, targets, settings)
        print(
            "\n| shape space | k | held-out | mean (mm) | median (mm) | P95 (mm) | fit (s) |"
            "\n|---|---:|---:|---:|---:|---:|---:|"
        )
        for r in rows:
            fit_s = "—" if r.fit_s is None else f"{r.fit_s:.0f}"
            print(f"| {r.name} | {r.k} | {r.held_out} | {r.mean:.3f} | {r.median:.3f} | {r.p95:.3f} | {fit_s} |")
    print(f"\ntotal {time.perf_counter() - t0:.0f} s")


if __name__ == "__main__":
    main()
