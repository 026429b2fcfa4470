"""Log-domain Sinkhorn normalisation with dustbins (paper 003 §4.2, after SuperGlue).

Notation, for one frame b with N point slots of which n_b are real, and L labels:

- ``S`` (N, L) scores; the augmented score matrix ``Z`` (N+1, L+1) appends a dustbin row
  (row N, "label unmatched") and a dustbin column (column L, "point is null") that all
  hold one learnable scalar ``bin_score``.
- Row marginals ``mu``: 1 for each real point, 0 for each padding slot, L for the dustbin row.
- Column marginals ``nu``: 1 for each label, n_b for the dustbin column.
  Both sum to n_b + L.
- Sinkhorn runs on the marginals divided by n_b + L (so the plan is a probability
  distribution, which keeps the iterations well scaled) and the result is multiplied back,
  so the returned plan has the marginals above: rows of real points and label columns
  sum to 1.

Padding slots get a very negative (finite) log-marginal instead of -inf: their plan rows
underflow to exactly 0 mass, and neither the forward values nor the gradients hold NaN.

Without gradients (labelling), the same iterations run on scalings instead of
log-scalings: u = mu / (K v), v = nu / (K^T u) with K = exp(Z - row max), batched
mat-vec products instead of log-sum-exps, several times faster on CPU. The iterates are the
same up to rounding. Frames whose rows span more than 0.7 of the float exponent range
(62 in float32) or whose scalings leave it are computed in the log domain.
"""

from __future__ import annotations

import math

import torch

from .._checks import check_shape, check_tensor

__all__ = ["log_sinkhorn"]

# log-mass of a padding slot; exp() of it is exactly 0 in float32 and float64.
_NEG = -1.0e4


def log_sinkhorn(
    scores: torch.Tensor, bin_score: torch.Tensor, row_mask: torch.Tensor, iters: int = 35
) -> torch.Tensor:
    """Normalise scores into a log transport plan with dustbins.

    Args:
        scores: (B, N, L) point-to-label scores (log-potentials), float32 or float64.
        bin_score: scalar tensor, score of every dustbin entry (learnable in the labeler).
        row_mask: (B, N) bool, True for real points, False for padding slots.
        iters: number of Sinkhorn iterations (the paper uses 35).

    Returns:
        (B, N+1, L+1) log plan ``log P``: for real rows sum_j P[i, j] = 1, for each label
        column sum_i P[i, j] = 1, the dustbin row sums to L and the dustbin column to n_b
        (up to convergence). Padding rows are very negative (about -1e4), never NaN.

    Raises:
        TypeError: non-tensor inputs or a non-bool mask.
        ValueError: bad shapes or ``iters < 1``.
    """
    sizes: dict[str, int] = {}
    check_shape(scores, "B N L", name="scores", sizes=sizes)
    check_shape(row_mask, "B N", name="row_mask", sizes=sizes)
    check_tensor(bin_score, "bin_score")
    if bin_score.numel() != 1:
        raise ValueError(f"bin_score: expected a scalar tensor, got shape {tuple(bin_score.shape)}")
    if row_mask.dtype != torch.bool:
        raise TypeError(f"row_mask: expected a bool tensor, got {row_mask.dtype}")
    if iters < 1:
        raise ValueError(f"iters: expected >= 1, got {iters}")
    b, n, num_labels = scores.shape

    bins = bin_score.reshape(()).to(scores).expand(b, 1, 1)
    z = torch.cat(
        [
            torch.cat([scores, bins.expand(b, n, 1)], dim=2),
            bins.expand(b, 1, num_labels + 1),
        ],
        dim=1,
    )

    n_valid = row_mask.sum(dim=1).to(scores.dtype)  # (B,)
    log_norm = -torch.log(n_valid + num_labels)  # (B,)
    neg = scores.new_tensor(_NEG)
    log_mu = torch.cat(
        [
            torch.where(row_mask, log_norm[:, None], neg),
            (math.log(num_labels) + log_norm)[:, None],
        ],
        dim=1,
    )  # (B, N+1)
    # An empty frame has a dustbin column of mass 0: all label mass goes to the dustbin row.
    log_bin_col = torch.where(n_valid > 0, torch.log(n_valid.clamp(min=1)) + log_norm, neg)
    log_nu = torch.cat([log_norm[:, None].expand(b, num_labels), log_bin_col[:, None]], dim=1)  # (B, L+1)

    if torch.is_grad_enabled() and (scores.requires_grad or bin_score.requires_grad):
        u, v = _log_iterations(z, log_mu, log_nu, iters)
    else:
        u, v = _scaling_iterations(z, log_mu, log_nu, iters)
    return z + u[:, :, None] + v[:, None, :] - log_norm[:, None, None]


def _log_iterations(z, log_mu, log_nu, iters: int) -> tuple[torch.Tensor, torch.Tensor]:
    """Log-scalings u (B, N+1), v (B, L+1) of the plan z + u + v, by log-sum-exps (differentiable, stable)."""
    u = torch.zeros_like(log_mu)
    v = torch.zeros_like(log_nu)
    for _ in range(iters):
        u = log_mu - torch.logsumexp(z + v[:, None, :], dim=2)
        v = log_nu - torch.logsumexp(z + u[:, :, None], dim=1)
    return u, v


def _scaling_iterations(z, log_mu, log_nu, iters: int) -> tuple[torch.Tensor, torch.Tensor]:
    """:func:`_log_iterations` by multiplicative updates; frames that leave the float range are redone."""
    top = z.amax(dim=2, keepdim=True)
    k = torch.exp(z - top)  # each row's largest entry is 1; the dustbin row is all ones
    mu, nu = log_mu.exp(), log_nu.exp()  # padding rows and the empty frame's dustbin column: exactly 0
    a = torch.ones_like(mu)
    c = torch.ones_like(nu)
    for _ in range(iters):
        a = mu / (k @ c[..., None])[..., 0]
        c = nu / (k.transpose(1, 2) @ a[..., None])[..., 0]
    u = (torch.log(a) - top[..., 0]).clamp_min(_NEG)
    v = torch.log(c).clamp_min(_NEG)
    # Entries more than 0.7 of the exponent range below their row's top could underflow, and
    # the scalings that balance them could overflow: such frames (none in our labelers' output,
    # whose rows span < 60) and any frame whose scalings did leave the range take the log domain.
    narrow = ((top - z.amin(dim=2, keepdim=True))[..., 0] <= 0.7 * math.log(torch.finfo(z.dtype).max)) | (mu == 0)
    ok = narrow.all(dim=1) & (torch.isfinite(a) & ((a > 0) | (mu == 0))).all(dim=1)
    ok &= (torch.isfinite(c) & ((c > 0) | (nu == 0))).all(dim=1)
    if not bool(ok.all()):
        bad = (~ok).nonzero()[:, 0]
        u[bad], v[bad] = _log_iterations(z[bad], log_mu[bad], log_nu[bad], iters)
    return u, v
