"""Build a PanoMan model from synthetic data (paper 004 §4.3–4.4); driven by scripts/build_panoman.py.

Steps, each a function of its inputs and a seed:
1. :func:`rla_matrix`: RL / RA vectors (N, E) of a training subset (body poses with procedural
   twist, facial expressions, hand gestures; :mod:`unibody.panoman.dataset`).
2. :func:`decompose`: sparse localized components of each (quantity, subset), six in all.
3. :func:`train_beta_net`: beta(theta) from joint rotations to the body + hand weights
   (targets: least-squares weights of each training sample, :meth:`PanoMan.project`).
4. :func:`train_correction`: R(beta_B), the residual of the body samples after the components,
   on the leading principal directions of those residuals.
"""

from __future__ import annotations

import time

import numpy as np
import scipy.sparse as sp
import torch

from .mesh import EdgeTopology
from .model import Decomposition
from .nets import MLP, CorrectionNet, pose_features
from .rla import rla

__all__ = ["decompose", "edge_graph", "rla_matrix", "train_beta_net", "train_correction"]


def rla_matrix(samples, topo: EdgeTopology, *, chunk: int = 64) -> tuple[torch.Tensor, torch.Tensor]:
    """(RL (N, E), RA (N, E)) float32 of a :class:`~unibody.panoman.dataset.PanoSamples`."""
    rls, ras = [], []
    for i in range(0, samples.posed.shape[0], chunk):
        rest = samples.rest[i : i + chunk].double()
        rl, ra = rla(rest, samples.posed[i : i + chunk].double(), topo)
        rls.append(rl.float())
        ras.append(ra.float())
    return torch.cat(rls), torch.cat(ras)


def edge_graph(topo: EdgeTopology, rest: torch.Tensor) -> tuple[sp.csr_matrix, np.ndarray]:
    """Edge adjacency (edges sharing a face) weighted by midpoint distance, and midpoints (E, 3)."""
    e = topo.edges.numpy()
    v = rest.double().numpy().reshape(-1, 3)
    mid = 0.5 * (v[e[:, 0]] + v[e[:, 1]])
    fe = topo.face_edges.numpy()
    a = np.concatenate([fe[:, [0, 1]], fe[:, [1, 2]], fe[:, [2, 0]]])
    w = np.linalg.norm(mid[a[:, 0]] - mid[a[:, 1]], axis=1)
    n = len(e)
    g = sp.coo_matrix(
        (np.concatenate([w, w]), (np.concatenate([a[:, 0], a[:, 1]]), np.concatenate([a[:, 1], a[:, 0]]))), shape=(n, n)
    ).tocsr()
    return g, mid


def decompose(x: torch.Tensor, graph: sp.csr_matrix, quantity: str, subset: str, config, *, progress=None):
    """Sparse localized components of data (N, E) -> (Decomposition, SplocsResult)."""
    from .splocs import sparse_localized_components

    t0 = time.perf_counter()
    res = sparse_localized_components(x.double(), graph, config, progress=progress)
    dec = Decomposition.from_dense(quantity, subset, res.mean, res.components)
    if progress is not None:
        progress(f"{quantity}/{subset} done in {time.perf_counter() - t0:.1f} s", 1, 1)
    return dec, res


def _train(net, x: torch.Tensor, y: torch.Tensor, *, steps: int, lr: float, seed: int, log=None) -> float:
    """Adam on standardised MSE with a cosine schedule; returns the final training loss."""
    gen = torch.Generator().manual_seed(seed)
    net.set_statistics(x, y)
    target = (y - net.out_mean) / net.out_std
    opt = torch.optim.Adam(net.parameters(), lr=lr, weight_decay=1e-6)
    sched = torch.optim.lr_scheduler.CosineAnnealingLR(opt, steps)
    batch = min(256, x.shape[0])
    loss = torch.tensor(0.0)
    for step in range(steps):
        idx = torch.randint(x.shape[0], (batch,), generator=gen)
        loss = ((net.raw(x[idx]) - target[idx]) ** 2).mean()
        opt.zero_grad()
        loss.backward()
        opt.step()
        sched.step()
        if log is not None and (step % 500 == 0 or step == steps - 1):
            log(f"step {step + 1}/{steps} loss {float(loss.detach()):.4f}")
    return float(loss.detach())


def train_beta_net(
    pose: torch.Tensor,
    beta: torch.Tensor,
    keep: torch.Tensor,
    *,
    hidden=(400, 600),
    steps=3000,
    lr=1e-3,
    seed=0,
    log=None,
):
    """beta(theta) (paper Fig. 9) on poses (N, 77, 3) and their weights (N, K); predicts beta[:, keep]."""
    torch.manual_seed(seed)
    index = keep.nonzero().squeeze(1)
    net = MLP((77 * 9, *hidden, len(index)), index, beta.shape[1])
    _train(net, pose_features(pose.float()), beta[:, index].float(), steps=steps, lr=lr, seed=seed, log=log)
    return net.eval()


def train_correction(
    beta_body: torch.Tensor, residual: torch.Tensor, *, rank=16, hidden=(256,), steps=3000, lr=1e-3, seed=0, log=None
):
    """R(beta_B) on body weights (N, K_B) and residuals (N, 2E): PCA to ``rank``, then an MLP.

    The principal directions come from the eigenvectors of the (N, N) Gram matrix of the centred
    residuals (float64), which needs N^2 memory instead of a full SVD's workspace.
    """
    torch.manual_seed(seed)
    mean = residual.double().mean(0)
    r = residual.double() - mean  # a new tensor: the caller's residuals stay as they are
    evals, evecs = torch.linalg.eigh(r @ r.T)
    top = evecs[:, -rank:].flip(1) / evals[-rank:].flip(0).clamp_min(1e-30).sqrt()  # (N, rank)
    directions = top.T @ r  # (rank, 2E), orthonormal rows
    coeff = torch.cat([r @ directions.T, torch.ones(r.shape[0], 1, dtype=r.dtype)], dim=1)
    # The mean residual is folded in as an extra direction with coefficient 1.
    basis = torch.cat([directions, mean[None]], dim=0)
    net = CorrectionNet((beta_body.shape[1], *hidden, rank + 1), basis.float())
    _train(net, beta_body.float(), coeff.float(), steps=steps, lr=lr, seed=seed, log=log)
    return net.eval()
