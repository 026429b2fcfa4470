"""Retarget any skeleton's motion onto the canonical body by joint positions (and orientations).

Given world positions of M source joints (T, M, 3) in metres (Y up), the canonical joint each
one maps to and, optionally, the source joints' world orientations, :func:`retarget`

1. fits an identity of the layer's backend (the native PCA) so that the canonical rest
   distances between mapped joints match the source's (median over frames), within the
   backend's limits (:func:`~unibody.fitting.shape_fit.param_limits`, capped at
   :attr:`RetargetConfig.max_coeff`);
2. calibrates, per mapped joint, a constant rotation ``A_m`` from the source joint's frame to
   the canonical joint's: the two rest poses are taken as the same pose up to each bone's
   direction (``A_m = Rs0_m^T S_m O_m``, ``Rs0`` the source rest orientation, ``O`` the
   canonical T-pose one, ``S_m`` the shortest arc between the two rest bone directions after
   a global Kabsch alignment of the torsos, so the source may face any way);
3. solves every frame (batches of frames in parallel) by Levenberg–Marquardt on the Hips
   translation and world rotation increments of the solved joints (the ancestors of mapped
   joints), the increments applied as in :func:`~unibody.fitting._gauss_newton.rotate_joints`.
   Residuals: mapped joint positions (m); ``orientation_weight`` x the world rotation error of
   mapped joints against ``R_s(t) A_m`` (twist about bone axes, hands, feet, head); and
   ``prior_weight`` x each solved joint's local rotation away from its start. The start of
   every frame is the source's own rotations transferred through ``A_m`` (so the solve is
   temporally consistent by construction: no frame depends on a cold guess), or the T-pose with
   the torso aligned by Kabsch when no orientations are given, then warm-started frame to
   frame. Unmapped joints between two mapped ones on the spine and neck follow their mapped
   parent (the same increment, so the bend is split evenly); any other unmapped joint stays at
   zero (T-pose-relative).

Units: metres; axes: Y up, the canonical body faces +Z (the source may face anywhere).
"""

from __future__ import annotations

import contextlib
from collections.abc import Iterator, Sequence
from dataclasses import dataclass

import torch

from .._checks import check_count, check_finite, check_grad_mode, check_number, check_shape
from ..body import BodyLayer, PreparedIdentity
from ..geometry.procrustes import kabsch, polar_svd
from ..geometry.rotations import matrix_to_axis_angle, shortest_arc, skew
from ._gauss_newton import rotate_joints
from .shape_fit import param_limits

__all__ = ["RetargetConfig", "RetargetResult", "bone_pairs", "fit_bone_lengths", "fit_tpose_offsets", "retarget"]

# Canonical joints that follow their parent when unmapped (spine and neck chains).
_FOLLOW_PARENT = frozenset({"Spine1", "Spine2", "Chest", "Neck1", "Neck2"})
_TORSO = ("Hips", "Spine1", "Spine2", "Chest", "Neck1", "LeftLeg", "RightLeg", "LeftArm", "RightArm")


@dataclass(frozen=True, slots=True)
class RetargetConfig:
    """Settings of :func:`retarget`.

    Attributes:
        iterations: LM iterations per frame (first frames of a no-orientation solve get 4x).
        orientation_weight: m per radian of world orientation error of a mapped joint.
        prior_weight: m per radian of a solved joint's local rotation away from its start.
        batch: frames solved in parallel.
        num_components: identity coefficients fitted (the first ones of the layer's backend).
        max_coeff: bound on each fitted coefficient (standard deviations for the PCA).
        identity_steps: L-BFGS iterations of the bone-length fit.
        offset_rounds: re-solves with per-joint offsets fitted (when offset frames are given).
    """

    iterations: int = 6
    orientation_weight: float = 0.03
    prior_weight: float = 0.003
    batch: int = 256
    num_components: int = 16
    max_coeff: float = 4.0
    identity_steps: int = 60
    offset_rounds: int = 1

    def __post_init__(self) -> None:
        for name, low in (("iterations", 1), ("batch", 1), ("num_components", 1), ("identity_steps", 0)):
            check_count(getattr(self, name), name, low)
        check_count(self.offset_rounds, "offset_rounds")
        for name in ("orientation_weight", "prior_weight"):
            check_number(getattr(self, name), name)
        check_number(self.max_coeff, "max_coeff", positive=True)


@dataclass(frozen=True, slots=True)
class RetargetResult:
    """A retargeted motion.

    Attributes:
        pose: (T, 77, 3) axis-angle, T-pose-relative local rotations of joints 1..77.
        transl: (T, 3) m, Hips world position.
        identity: (K,) identity parameters of the layer's backend (zeros past ``num_components``).
        joint_error: (T, M) m, distance of each mapped canonical joint to its target (the
            source joint moved by its fitted offset; the source joint itself without offsets).
        raw_error: (T, M) m, distance of each mapped canonical joint to its source joint.
        offsets: (M, 3) m, fitted offset of each joint in its source frame (zeros without).
        bone_error: (N,) m, rest bone-length residual of the identity fit (canonical - source).
    """

    pose: torch.Tensor
    transl: torch.Tensor
    identity: torch.Tensor
    joint_error: torch.Tensor
    raw_error: torch.Tensor
    offsets: torch.Tensor
    bone_error: torch.Tensor


def _mapped_index(layer: BodyLayer, joints: Sequence[str]) -> list[int]:
    index = {n: i for i, n in enumerate(layer.joint_names)}
    bad = [n for n in joints if n not in index or n == "Root"]
    if bad:
        raise ValueError(f"joints: expected canonical joint names (unibody.JOINT_NAMES[1:]), got {bad}")
    dup = sorted({n for n in joints if list(joints).count(n) > 1})
    if dup:
        raise ValueError(f"joints: each canonical joint may be mapped once, got {dup} more than once")
    return [index[n] for n in joints]


def bone_pairs(parents: list[int], mapped: list[int]) -> list[tuple[int, int]]:
    """(a, b) column pairs: mapped joint b and its nearest mapped canonical ancestor a.

    Args:
        parents: the canonical parent of every joint (``layer.rig_tree.parents``).
        mapped: the canonical joint of each column.
    """
    col = {c: i for i, c in enumerate(mapped)}
    out = []
    for i, c in enumerate(mapped):
        a = parents[c]
        while a > 0 and a not in col:
            a = parents[a]
        if a in col:
            out.append((col[a], i))
    return out


def _tpose_joints(layer: BodyLayer, prepared: PreparedIdentity) -> tuple[torch.Tensor, torch.Tensor]:
    """World joints (Bi, J, 3) and rotations (Bi, J, 3, 3) of prepared identities in the T-pose, Hips at 0."""
    b = prepared.rest_joints.shape[0]
    ref = prepared.rest_joints
    local = layer.local_rotations(ref.new_zeros(b, layer.num_joints - 1, 3))
    g_rot, g_pos, _ = layer.skin_transforms(prepared, local, ref.new_zeros(b, 3))
    return g_pos, g_rot


def fit_bone_lengths(
    layer: BodyLayer, mapped: list[int], lengths: torch.Tensor, config: RetargetConfig
) -> tuple[torch.Tensor, torch.Tensor]:
    """Identity parameters (K,) whose T-pose distances between mapped joints match ``lengths``.

    The T-pose joints are linear in the PCA coefficients up to the skeleton fit's rotations, so
    the fit linearises them (one batched forward of K + 1 identities, finite differences of
    1 standard deviation), solves the small bounded least-squares problem by L-BFGS, and
    relinearises once at the result (backpropagating through the skeleton fit instead cost
    ~0.4 s per evaluation, 39 s per file).

    Args:
        mapped: canonical joint of each source column; lengths: (N,) m, per :func:`_bones` pair.

    Returns:
        ``(params (K,), residual (N,) m)``.
    """
    bones = bone_pairs([int(p) for p in layer.rig_tree.parents], mapped)
    ref = layer.tpose_orient
    k_all = layer.identity.num_params
    k = min(config.num_components, k_all)
    lim = param_limits(layer.identity)[:k].to(ref).clamp(-config.max_coeff, config.max_coeff)
    lo, hi = lim[:, 0].double(), lim[:, 1].double()
    a = torch.tensor([mapped[i] for i, _ in bones], dtype=torch.long, device=ref.device)
    b = torch.tensor([mapped[j] for _, j in bones], dtype=torch.long, device=ref.device)
    target = lengths.double()

    def full(c: torch.Tensor) -> torch.Tensor:
        return torch.cat([c.to(ref), ref.new_zeros(k_all - k)])

    def joints_at(c: torch.Tensor) -> torch.Tensor:
        with torch.no_grad():
            probe = full(c)[None].repeat(k + 1, 1)
            step = torch.where(c > 0, -1.0, 1.0).to(ref)  # stay within the limits
            probe[1:, :k] += torch.diag(step)
            pos, _ = _tpose_joints(layer, layer.prepare_identity(probe))
        pos = pos.double()
        return pos[0], (pos[1:] - pos[0]) / step.double()[:, None, None]

    c = lo.new_zeros(k)
    for _ in range(2 if bones else 0):
        base, jac = joints_at(c)
        c = _fit_linear(base, jac, c, lo, hi, a, b, target, config)
    params = full(c)
    with torch.no_grad():
        pos, _ = _tpose_joints(layer, layer.prepare_identity(params[None]))
        return params, torch.linalg.vector_norm(pos[0, a] - pos[0, b], dim=-1) - target.to(ref)


def fit_tpose_offsets(
    layer: BodyLayer, offsets: torch.Tensor, ridge: float = 1e-12
) -> tuple[torch.Tensor, torch.Tensor]:
    """Identity parameters (K,) of every component whose T-pose joint offsets match ``offsets``.

    For a skeleton that *is* the canonical one (a canonical BVH): each joint's T-pose offset
    from its parent, in world axes, is known as a vector, so the fit is a linear least-squares
    problem in all K coefficients (joints linearised by finite differences, as in
    :func:`fit_bone_lengths`, relinearised twice), with a tiny ridge for the directions that do
    not move any joint. Coefficients are kept within the backend's limits.

    Args:
        offsets: (77, 3) m, joint k+1's T-pose position minus its parent's (row 0, the Hips, unused).

    Returns:
        ``(params (K,), residual (76,) m)``: the distance between fitted and given offsets of joints 2..77.
    """
    check_shape(offsets, f"{layer.num_joints - 1} 3", name="offsets")
    check_finite(offsets, "offsets")
    ref = layer.tpose_orient
    parents = torch.as_tensor([int(p) for p in layer.rig_tree.parents], device=ref.device)
    child = torch.arange(2, layer.num_joints, device=ref.device)
    k = layer.identity.num_params
    lim = param_limits(layer.identity).to(ref).double()
    target = offsets[1:].double().reshape(-1)
    c = target.new_zeros(k)

    def offsets_at(params: torch.Tensor) -> torch.Tensor:
        with torch.no_grad():
            pos, _ = _tpose_joints(layer, layer.prepare_identity(params.to(ref)))
        pos = pos.double()
        return (pos[:, child] - pos[:, parents[child]]).reshape(len(params), -1)

    for _ in range(3):
        step = torch.where(c > 0, -1.0, 1.0).double()
        probe = c[None].repeat(k + 1, 1)
        probe[1:] += torch.diag(step)
        d = offsets_at(probe)
        jac = (d[1:] - d[0]) / step[:, None]  # (K, 3N)
        lhs = jac @ jac.T + ridge * torch.eye(k, dtype=jac.dtype, device=jac.device)
        c = torch.minimum(torch.maximum(c + torch.linalg.solve(lhs, jac @ (target - d[0])), lim[:, 0]), lim[:, 1])
    residual = torch.linalg.vector_norm((offsets_at(c[None])[0] - target).reshape(-1, 3), dim=-1)
    return c.to(ref), residual.to(ref)


def _fit_linear(
    base: torch.Tensor,
    jac: torch.Tensor,
    c0: torch.Tensor,
    lo: torch.Tensor,
    hi: torch.Tensor,
    a: torch.Tensor,
    b: torch.Tensor,
    target: torch.Tensor,
    config: RetargetConfig,
) -> torch.Tensor:
    """Coefficients (k,) in [lo, hi] fitting the distances |pos_a - pos_b| to ``target`` with the
    joints linearised at ``c0`` (pos = base + (c - c0) jac); L-BFGS on logits, a weak prior."""
    scale = target.clamp_min(0.02)
    z = torch.logit(((c0 - lo) / (hi - lo)).clamp(1e-4, 1 - 1e-4)).requires_grad_(True)
    opt = torch.optim.LBFGS([z], lr=1, max_iter=config.identity_steps, line_search_fn="strong_wolfe")

    def closure() -> torch.Tensor:
        opt.zero_grad()
        c = lo + (hi - lo) * torch.sigmoid(z)
        pos = base + torch.einsum("k,kjd->jd", c - c0, jac)
        length = torch.linalg.vector_norm(pos[a] - pos[b], dim=-1)
        loss = ((length - target) / scale).square().mean() + 1e-4 * (c / config.max_coeff).square().mean()
        loss.backward()
        return loss

    opt.step(closure)
    return (lo + (hi - lo) * torch.sigmoid(z)).detach()


def _solve_structure(layer: BodyLayer, mapped: list[int], has_rot: bool):
    """Solved joints, their groups (increment shared within a group) and constant Jacobian blocks."""
    parents = [int(p) for p in layer.rig_tree.parents]
    names = layer.joint_names
    mapped_set = set(mapped)
    solved = set()
    for c in mapped:
        a = parents[c] if not has_rot else c
        while a > 0:
            solved.add(a)
            a = parents[a]
    solved.add(1)
    solved = sorted(solved)
    group: dict[int, int] = {}
    roots: list[int] = []
    for k in solved:  # parents before children (the rig is ordered so)
        p = parents[k]
        if k not in mapped_set and names[k] in _FOLLOW_PARENT and p in group:
            group[k] = group[p]
        else:
            group[k] = len(roots)
            roots.append(k)
    return solved, group, len(roots), parents


def retarget(
    layer: BodyLayer,
    positions: torch.Tensor,
    joints: Sequence[str],
    *,
    orientations: torch.Tensor | None = None,
    rest_positions: torch.Tensor | None = None,
    rest_orientations: torch.Tensor | None = None,
    offset_frames: torch.Tensor | None = None,
    config: RetargetConfig | None = None,
) -> RetargetResult:
    """Retarget mapped source joints onto the canonical body (see the module docstring).

    Args:
        layer: a layer with an identity backend (the native PCA: ``BodyLayer.from_pca``).
        positions: (T, M, 3) m, world positions of the mapped source joints, Y up.
        joints: M canonical joint names, the joint each source column maps to.
        orientations: (T, M, 3, 3) world orientations of the source joints, or None.
        rest_positions: (M, 3) m, the source joints in the skeleton's rest pose (needed with
            ``orientations``); rest_orientations: (M, 3, 3) their rest world orientations.
        offset_frames: (T, M, 3, 3) world orientations of the source bones that carry each mapped
            joint (its parent's), or None. When given, a constant offset per joint in that frame
            is fitted (``offset_rounds`` times: the mean residual of the previous solve) and the
            canonical joints track the offset source joints: source and canonical joints do not
            sit at the same anatomical spots (CMU's hip joint is the pelvis centre, ours is higher).
        config: solver settings (:class:`RetargetConfig`).

    Returns:
        :class:`RetargetResult`.

    Raises:
        ValueError: unknown or repeated joint names, fewer than 3 mapped joints, wrong shapes,
            no frames, NaN/inf (the message lists the bad frames).

    Inputs are cast to the layer's dtype (the solve runs in it; float64 is the safer choice
    for long position-only motions).
    """
    check_grad_mode("retarget")
    cfg = config or RetargetConfig()
    if not isinstance(layer, BodyLayer) or layer.identity is None:
        raise ValueError("layer: expected a BodyLayer with an identity backend (e.g. BodyLayer.from_pca())")
    ref = layer.tpose_orient
    mapped = _mapped_index(layer, joints)
    m = len(mapped)
    if m < 3:
        raise ValueError(f"joints: expected at least 3 mapped joints, got {m}")
    check_shape(positions, f"T {m} 3", name="positions")
    _check_frames(positions, "positions")
    positions = positions.to(ref)
    t = positions.shape[0]
    if t == 0:
        raise ValueError(f"positions: expected at least one frame, got shape {tuple(positions.shape)}")
    has_rot = orientations is not None
    if has_rot:
        check_shape(orientations, f"T {m} 3 3", name="orientations", sizes={"T": t})
        _check_frames(orientations, "orientations")
        if rest_positions is None or rest_orientations is None:
            raise ValueError("rest_positions, rest_orientations: required with orientations, got None")
        check_shape(rest_positions, f"{m} 3", name="rest_positions")
        check_shape(rest_orientations, f"{m} 3 3", name="rest_orientations")
        check_finite(rest_positions, "rest_positions")
        check_finite(rest_orientations, "rest_orientations")
        orientations = orientations.to(ref)
    if offset_frames is not None:
        check_shape(offset_frames, f"T {m} 3 3", name="offset_frames", sizes={"T": t})
        _check_frames(offset_frames, "offset_frames")
        offset_frames = offset_frames.to(ref)
    with _one_thread():
        return _rounds(layer, positions, mapped, orientations, rest_positions, rest_orientations, offset_frames, cfg)


def _rounds(layer, positions, mapped, orientations, rest_positions, rest_orientations, offset_frames, cfg):
    """Identity fit, calibration and solve; again with per-joint offsets (``offset_rounds``)."""
    ref = layer.tpose_orient
    m = len(mapped)
    has_rot = orientations is not None
    bones = bone_pairs([int(p) for p in layer.rig_tree.parents], mapped)
    offsets = positions.new_zeros(m, 3)
    targets = reached = positions
    rounds = 1 + (cfg.offset_rounds if offset_frames is not None else 0)
    for r in range(rounds):
        if r:  # the mean residual of each joint in its source frame: a fixed offset between definitions
            local_err = (offset_frames.transpose(-1, -2) @ (reached - positions)[..., None]).squeeze(-1)
            offsets = local_err.mean(0)
            targets = positions + (offset_frames @ offsets[..., None]).squeeze(-1)
        if bones:
            ia = torch.tensor([i for i, _ in bones], device=targets.device)
            ib = torch.tensor([j for _, j in bones], device=targets.device)
            lengths = torch.linalg.vector_norm(targets[:, ia] - targets[:, ib], dim=-1).median(0).values
        else:
            lengths = positions.new_zeros(0)
        params, bone_error = fit_bone_lengths(layer, mapped, lengths, cfg)
        with torch.no_grad():
            prepared = layer.prepare_identity(params[None])
            tpos, trot = _tpose_joints(layer, prepared)
            tpos, trot = tpos[0], trot[0]
            targets_rot = None
            if has_rot:
                align = _calibrate(layer, mapped, tpos, trot, rest_positions.to(ref), rest_orientations.to(ref))
                targets_rot = orientations @ align
            pose, transl, err, reached = _solve_all(layer, prepared, mapped, targets, targets_rot, tpos, cfg)
    raw = torch.linalg.vector_norm(reached - positions, dim=-1)
    return RetargetResult(pose, transl, params, err, raw, offsets, bone_error)


@contextlib.contextmanager
def _one_thread() -> Iterator[None]:
    """Run torch on one intra-op thread, then restore the setting.

    The solver's tensors are small (a batch of frames x 78 joints x 3 x 3) and its FK walks ~15
    tree levels: intra-op threads only add synchronisation, and on a loaded machine their spin
    waits dominate. Measured (2-core machine, load average 5): FK of 60 frames 2.1 ms on one
    thread vs 140 ms on two. Parallelism comes from converting files in separate processes.
    """
    before = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        yield
    finally:
        torch.set_num_threads(before)


def _check_frames(x: torch.Tensor, name: str) -> None:
    bad = ~torch.isfinite(x).flatten(1).all(1)
    if bool(bad.any()):
        idx = torch.nonzero(bad).flatten().tolist()
        shown = ", ".join(map(str, idx[:10])) + (" ..." if len(idx) > 10 else "")
        raise ValueError(f"{name}: expected finite values, got NaN/inf in {len(idx)} frame(s): {shown}")


def _torso_rotation(
    mapped: list[int], names: tuple[str, ...], canon: torch.Tensor, source: torch.Tensor
) -> torch.Tensor:
    """Rotation (..., 3, 3) taking the canonical torso (M, 3) onto the source's (..., M, 3), Kabsch."""
    cols = [i for i, c in enumerate(mapped) if names[c] in _TORSO]
    if len(cols) < 3:
        cols = list(range(len(mapped)))
    a = canon[cols] - canon[cols].mean(0)
    b = source[..., cols, :] - source[..., cols, :].mean(-2, keepdim=True)
    return kabsch(a.expand_as(b), b)


def _calibrate(
    layer: BodyLayer, mapped: list[int], tpos: torch.Tensor, trot: torch.Tensor, rpos: torch.Tensor, rrot: torch.Tensor
) -> torch.Tensor:
    """A_m (M, 3, 3): source world orientation @ A_m = canonical world orientation, from the rest poses."""
    names = layer.joint_names
    canon = tpos[mapped]
    q = _torso_rotation(mapped, names, canon, rpos)
    children: dict[int, list[int]] = {}
    for a, b in bone_pairs([int(p) for p in layer.rig_tree.parents], mapped):
        children.setdefault(a, []).append(b)
    s = q.expand(len(mapped), 3, 3).clone()
    for i, kids in children.items():
        if len(kids) == 1:  # one mapped child: the bone direction is well defined
            dc = q @ (canon[kids[0]] - canon[i])
            ds = rpos[kids[0]] - rpos[i]
            if float(dc.norm()) > 1e-6 and float(ds.norm()) > 1e-6:
                s[i] = shortest_arc(dc, ds) @ q
    return rrot.transpose(-1, -2) @ s @ trot[mapped]


def _solve_all(
    layer: BodyLayer,
    prepared: PreparedIdentity,
    mapped: list[int],
    positions: torch.Tensor,
    targets_rot: torch.Tensor | None,
    tpos: torch.Tensor,
    cfg: RetargetConfig,
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
    has_rot = targets_rot is not None
    solver = _Solver(layer, prepared, mapped, has_rot, cfg)
    t = positions.shape[0]
    zero_local = layer.local_rotations(positions.new_zeros(1, layer.num_joints - 1, 3))
    names = layer.joint_names
    poses, transls, errs = [], [], []
    if has_rot:
        for s in range(0, t, cfg.batch):
            sl = slice(s, s + cfg.batch)
            local, transl = solver.init_from_rotations(zero_local, positions[sl], targets_rot[sl])
            local, transl, err = solver.solve(local, transl, positions[sl], targets_rot[sl], cfg.iterations)
            poses.append(local)
            transls.append(transl)
            errs.append(err)
    else:
        # No orientations: the T-pose with the torso aligned by Kabsch starts the first frame, then
        # each frame starts from the previous one (warm start; the prior pulls towards it).
        canon = tpos[mapped]
        rot0 = _torso_rotation(mapped, names, canon, positions[:1])
        local = zero_local.clone()
        local[:, 1] = rot0 @ zero_local[:, 1]
        transl = _hips_guess(mapped, canon, positions[:1], rot0)
        iters = 4 * cfg.iterations
        for f in range(t):
            local, transl, err = solver.solve(local, transl, positions[f : f + 1], None, iters)
            # Frame after frame the float32 updates would leave SO(3) and stall the steps.
            local = polar_svd(local)
            iters = cfg.iterations
            poses.append(local)
            transls.append(transl)
            errs.append(err)
    local = torch.cat(poses)
    pose = matrix_to_axis_angle(layer.to_relative(local[:, 1:]))
    transl = torch.cat(transls)
    _, g_pos, _ = layer.skin_transforms(prepared, local, transl)
    return pose, transl, torch.cat(errs), g_pos[:, mapped]


def _hips_guess(mapped: list[int], canon: torch.Tensor, pos: torch.Tensor, rot: torch.Tensor) -> torch.Tensor:
    """Hips position (B, 3) given the torso rotation: centroid match of all mapped joints."""
    return pos.mean(-2) - (rot @ canon.mean(0)[:, None]).squeeze(-1)


class _Solver:
    """Batched Levenberg–Marquardt over frames; see the module docstring for the residuals."""

    def __init__(self, layer: BodyLayer, prepared: PreparedIdentity, mapped: list[int], has_rot: bool, cfg) -> None:
        self.layer, self.prepared, self.mapped, self.cfg = layer, prepared, mapped, cfg
        ref = layer.tpose_orient
        solved, group, n_groups, parents = _solve_structure(layer, mapped, has_rot)
        dev = ref.device  # index tensors used with index_add_/index_copy must share the device
        self.solved = torch.tensor(solved, device=dev)
        self.group = torch.tensor([group[k] for k in solved], device=dev)
        self.n_groups, self.parents_list = n_groups, parents
        m = len(mapped)
        # (mapped column, solved joint) pairs where the joint moves the column's position.
        pair_col, pair_joint, pair_group = [], [], []
        chain_count = torch.zeros(m, n_groups, dtype=ref.dtype)
        pos_in_solved = {k: i for i, k in enumerate(solved)}
        for i, c in enumerate(mapped):
            a = c
            while a > 0:
                if a in pos_in_solved:
                    chain_count[i, group[a]] += 1  # world rotation of c turns with every ancestor-or-self
                    if a != c:
                        pair_col.append(i)
                        pair_joint.append(a)
                        pair_group.append(group[a])
                a = parents[a]
        self.pair_col = torch.tensor(pair_col, dtype=torch.long, device=dev)
        self.pair_joint = torch.tensor(pair_joint, dtype=torch.long, device=dev)
        self.pair_group = torch.tensor(pair_group, dtype=torch.long, device=dev)
        n = 3 + 3 * n_groups
        self.n = n
        eye = torch.eye(3, dtype=ref.dtype)
        # Constant blocks: orientation rows (M*3, n) and prior rows (S*3, n).
        rot_j = torch.zeros(m, 3, n_groups, 3, dtype=ref.dtype)
        rot_j += chain_count[:, None, :, None] * eye[:, None, :]
        self.rot_jac = torch.cat([torch.zeros(m, 3, 3, dtype=ref.dtype), rot_j.reshape(m, 3, 3 * n_groups)], -1)
        self.rot_jac = (cfg.orientation_weight * self.rot_jac.reshape(3 * m, n)).to(ref)
        s = len(solved)
        prior_j = torch.zeros(s, 3, n_groups, 3, dtype=ref.dtype)
        prior_j[torch.arange(s), :, self.group.cpu(), :] = eye
        self.prior_jac = torch.cat([torch.zeros(s, 3, 3, dtype=ref.dtype), prior_j.reshape(s, 3, 3 * n_groups)], -1)
        self.prior_jac = (cfg.prior_weight * self.prior_jac.reshape(3 * s, n)).to(ref)
        self.has_rot = has_rot
        self.const_jtj = self.prior_jac.T @ self.prior_jac
        if has_rot:
            self.const_jtj = self.const_jtj + self.rot_jac.T @ self.rot_jac
        self.eye = torch.eye(n, dtype=ref.dtype, device=ref.device)
        self.mapped_t = torch.tensor(mapped, device=dev)
        self.parents_t = layer.parents

    def init_from_rotations(self, zero_local: torch.Tensor, pos: torch.Tensor, rot: torch.Tensor):
        """Local rotations from the target world orientations (top-down), unmapped joints at zero."""
        b = pos.shape[0]
        world: dict[int, torch.Tensor] = {}
        local = zero_local.expand(b, -1, -1, -1).clone()
        col = {c: i for i, c in enumerate(self.mapped)}
        eye = torch.eye(3, dtype=pos.dtype, device=pos.device).expand(b, 3, 3)
        for k in range(1, self.layer.num_joints):
            p = self.parents_list[k]
            gp = world.get(p, eye) if p > 0 else eye
            if k in col:
                local[:, k] = gp.transpose(-1, -2) @ rot[:, col[k]]
            world[k] = gp @ local[:, k]
        if 1 in col:
            transl = pos[:, col[1]]
        else:
            canon = self._tpose_mapped()
            transl = _hips_guess(self.mapped, canon, pos, world[1] @ zero_local[0, 1].transpose(-1, -2))
        return local, transl

    def _tpose_mapped(self) -> torch.Tensor:
        tpos, _ = _tpose_joints(self.layer, self.prepared)
        return tpos[0, self.mapped]

    def _residuals(self, local, transl, pos, rot, ref_local):
        g_rot, g_pos, _ = self.layer.skin_transforms(self.prepared, local, transl)
        r_pos = pos - g_pos[:, self.mapped_t]
        parts = [r_pos.flatten(1)]
        if self.has_rot:
            r_rot = matrix_to_axis_angle(rot @ g_rot[:, self.mapped_t].transpose(-1, -2))
            parts.append(self.cfg.orientation_weight * r_rot.flatten(1))
        gp = g_rot[:, self.parents_t[self.solved]]
        e = matrix_to_axis_angle(local[:, self.solved] @ ref_local[:, self.solved].transpose(-1, -2))
        parts.append(-self.cfg.prior_weight * (gp @ e[..., None]).squeeze(-1).flatten(1))
        r = torch.cat(parts, 1)
        return g_rot, g_pos, r, r_pos

    def solve(self, local, transl, pos, rot, iters):
        b = pos.shape[0]
        ref_local = local
        lam = pos.new_full((b,), 1e-3)
        g_rot, g_pos, r, r_pos = self._residuals(local, transl, pos, rot, ref_local)
        cost = r.square().sum(1)
        m = len(self.mapped)
        for _ in range(iters):
            q = g_pos[:, self.mapped_t[self.pair_col]] - g_pos[:, self.pair_joint]  # (B, P, 3)
            # d p_c / d w_g = -[p_c - g_k]_x summed over the group's joints k (tied joints add up).
            blocks = q.new_zeros(b, m * (1 + self.n_groups), 3, 3)
            blocks.index_add_(1, self.pair_col * (1 + self.n_groups) + 1 + self.pair_group, -skew(q))
            jp = blocks.view(b, m, 1 + self.n_groups, 3, 3).transpose(2, 3).reshape(b, 3 * m, self.n)
            jp[:, :, :3] = torch.eye(3, dtype=pos.dtype, device=pos.device).repeat(m, 1)
            jtj = jp.transpose(1, 2) @ jp + self.const_jtj
            rhs = jp.transpose(1, 2) @ r_pos.reshape(b, 3 * m, 1)
            rest = r[:, 3 * m :]
            const_j = torch.cat([self.rot_jac, self.prior_jac]) if self.has_rot else self.prior_jac
            rhs = rhs + (const_j.T @ rest.T).T[..., None]
            scale = jtj.diagonal(dim1=1, dim2=2).mean(-1)
            chol, info = torch.linalg.cholesky_ex(jtj + (lam * scale)[:, None, None] * self.eye)
            step = torch.cholesky_solve(rhs, chol).squeeze(-1)
            step = torch.where((info == 0)[:, None] & torch.isfinite(step), step, torch.zeros_like(step))
            incr = step[:, 3:].view(b, self.n_groups, 3)[:, self.group]
            new = rotate_joints(local, g_rot, self.solved, self.parents_t, incr)
            cand_local = local.index_copy(1, self.solved, new)
            cand_transl = transl + step[:, :3]
            cg_rot, cg_pos, cr, cr_pos = self._residuals(cand_local, cand_transl, pos, rot, ref_local)
            c_cost = cr.square().sum(1)
            ok = c_cost < cost
            local = torch.where(ok[:, None, None, None], cand_local, local)
            transl = torch.where(ok[:, None], cand_transl, transl)
            g_rot = torch.where(ok[:, None, None, None], cg_rot, g_rot)
            g_pos = torch.where(ok[:, None, None], cg_pos, g_pos)
            r = torch.where(ok[:, None], cr, r)
            r_pos = torch.where(ok[:, None, None], cr_pos, r_pos)
            cost = torch.where(ok, c_cost, cost)
            lam = torch.where(ok, lam / 3, lam * 10)
        return local, transl, torch.linalg.vector_norm(r_pos, dim=-1)
