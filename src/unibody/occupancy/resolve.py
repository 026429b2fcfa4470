"""Resolve self-intersections by optimising the pose against the occupancy (paper 002 §5.2).

The pose moves by gradient steps (Adam) on the self-intersection term plus a quadratic pull
toward the input pose; the Hips (global orientation) and the translation stay fixed. The term is
a Monte-Carlo estimate (fresh candidate points every step), so one zero proves little: an item
stops moving only once its term has been zero at ``patience`` consecutive steps. Unlike the
reference, a batch is optimised at once (its items do not interact: the loss is a sum of
per-item terms).
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable
from dataclasses import dataclass

import torch

from .._checks import check_count, check_finite, check_grad_mode, check_number, check_shape, check_tensor
from ..body import BodyLayer
from .data import generator
from .field import BodyOccupancy

__all__ = ["Resolved", "resolve_self_intersections"]


@dataclass(frozen=True, slots=True)
class Resolved:
    """Result of :func:`resolve_self_intersections`.

    Attributes:
        pose: (B, 77, 3) the resolved T-pose-relative axis-angle pose (the input is untouched).
        loss: (steps + 1, B) the self-intersection term before every step and after the last.
        steps: (B,) the step at which each item stopped, its term zero at ``patience`` consecutive
            steps (``steps`` if it never did).
    """

    pose: torch.Tensor
    loss: torch.Tensor
    steps: torch.Tensor


@torch.enable_grad()  # it descends a gradient whatever its caller (commands run under no_grad)
def resolve_self_intersections(
    occupancy: BodyOccupancy,
    layer: BodyLayer,
    params: torch.Tensor,
    pose: torch.Tensor,
    *,
    transl: torch.Tensor | None = None,
    steps: int = 200,
    lr: float = 0.01,
    prior_weight: float = 100.0,
    samples: int = 256,
    threshold: float = 0.3,
    patience: int | None = 10,
    rigid_parts: bool = True,
    seed: int = 0,
    callback: Callable[[int, torch.Tensor], None] | None = None,
) -> Resolved:
    """Move ``pose`` (B, 77, 3) of ``layer(params, pose, transl=transl)`` out of self-intersection.

    Minimises ``self_intersection_loss + prior_weight * |pose - pose_in|^2`` per item over the
    joints below the Hips. The loss uses ``threshold`` 0.3 rather than 1/2: parts are pushed a
    little past the network's estimate of contact, which is off by about a millimetre, so the
    meshes come apart instead of stopping where they still graze. With ``rigid_parts`` the pose
    acts on the term through the part frames alone (part codes and boxes held fixed at each
    step): joints that only reshape a part (eyes, fingers, toes) are left alone, where Adam's
    per-joint normalisation would otherwise move them as far as the joints in contact, and the
    backward pass skips the encoder. Items that have stopped are
    no longer posed or queried. ``patience=None`` never stops an item early (the paper's fixed
    step budget).

    ``callback(step, pose)`` sees the current (B, 77, 3) pose before every step and after the
    last (e.g. to count intersecting triangles).
    """
    check_grad_mode("resolve_self_intersections")
    if not isinstance(occupancy, BodyOccupancy):
        raise TypeError(
            f"occupancy: expected a BodyOccupancy (BodyOccupancy.pretrained()), got {type(occupancy).__name__}"
        )
    if not isinstance(layer, BodyLayer):
        raise TypeError(f"layer: expected a BodyLayer, got {type(layer).__name__}")
    check_shape(pose, "B 77 3", name="pose")
    check_finite(pose, "pose")
    check_tensor(params, "params")
    b = pose.shape[0]
    if params.ndim != 2 or params.shape[0] not in (1, b):  # else rows were silently dropped
        want = "(1, K)" if b == 1 else f"(1, K) or ({b}, K)"
        raise ValueError(f"params: expected {want} for {b} pose(s), got {tuple(params.shape)}")
    check_count(steps, "steps")
    if patience is not None:
        check_count(patience, "patience", 1)
    check_count(samples, "samples", 1)
    check_number(lr, "lr", positive=True)
    check_number(prior_weight, "prior_weight")
    if not isinstance(rigid_parts, bool):
        raise TypeError(f"rigid_parts: expected True or False, got {rigid_parts!r}")
    start = pose.detach()
    delta = torch.zeros_like(start[:, 1:], requires_grad=True)
    opt = torch.optim.Adam([delta], lr=lr)
    done = torch.zeros(b, dtype=torch.bool, device=start.device)
    zeros = torch.zeros(b, dtype=torch.long, device=start.device)  # consecutive zero terms
    finished = torch.full((b,), steps, dtype=torch.long)
    history = []
    for step in range(steps + 1):
        current = torch.cat([start[:, :1], start[:, 1:] + delta], 1)
        if callback is not None:
            callback(step, current.detach())
        active = (~done).nonzero().squeeze(1)
        ident = params if params.shape[0] == 1 else params[active]  # one identity may serve every pose
        out = layer(ident, current[active], transl=None if transl is None else transl[active])
        gen = generator("resolve", seed, step)
        enc = occupancy.encode(out)
        if rigid_parts:  # the pose acts through the part frames alone
            enc = dataclasses.replace(enc.detach(), rotation=enc.rotation, origin=enc.origin)
        term = occupancy.self_intersection_loss(
            enc, vertices=out.vertices, samples=samples, threshold=threshold, generator=gen
        )
        loss = term.new_zeros(b).index_copy(0, active, term.detach())  # stopped items: their last value, 0
        history.append(loss.cpu())
        zeros = torch.where(loss <= 0, zeros + 1, torch.zeros_like(zeros))
        newly = (zeros >= (patience or steps + 2)) & ~done
        finished[newly.cpu()] = step
        done |= newly
        if step == steps or bool(done.all()):
            break
        opt.zero_grad(set_to_none=True)
        keep = ~newly[active]  # items stopping now take no further step
        (term[keep].sum() + prior_weight * delta[active[keep]].pow(2).sum()).backward()
        frozen = delta.detach()[done].clone()
        opt.step()
        with torch.no_grad():
            delta[done] = frozen  # Adam's momentum would move stopped items on
    loss = torch.stack(history)
    if loss.shape[0] < steps + 1:  # every item finished early: the rest of the curve is flat
        loss = torch.cat([loss, loss[-1:].expand(steps + 1 - loss.shape[0], -1)])
    return Resolved(current.detach(), loss, finished)
