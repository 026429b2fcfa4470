"""PanoMan's two small networks (paper 004 Figs. 4 and 9), with plain state dicts.

- :class:`MLP` for beta(theta): joint rotations -> component weights. The pose is fed as the
  entries of (R - I) of each joint (continuous, zero at the T-pose); inputs and outputs are
  standardised with stored statistics. Paper: two hidden layers of 400 and 600 units.
- :class:`CorrectionNet` for R(beta_B): body weights -> RL/RA corrections. The paper's output
  layer spans all 2|E| entries (1,500 x 65k weights for its mesh); ours spans the leading
  principal directions of the training residuals instead (``basis``, (R, 2E)), which keeps
  the shipped file small and the correction smooth.
"""

from __future__ import annotations

import torch
from torch import nn

from ..geometry.rotations import axis_angle_to_matrix

__all__ = ["CorrectionNet", "MLP", "pose_features"]


def pose_features(pose: torch.Tensor) -> torch.Tensor:
    """(B, 77, 3) axis-angle -> (B, 77 * 9) entries of R - I."""
    r = axis_angle_to_matrix(pose)
    return (r - torch.eye(3, dtype=r.dtype)).flatten(1)


class _Standardised(nn.Module):
    def __init__(self, sizes: tuple[int, ...]) -> None:
        super().__init__()
        layers: list[nn.Module] = []
        for a, b in zip(sizes[:-2], sizes[1:-1], strict=False):
            layers += [nn.Linear(a, b), nn.ReLU()]
        layers.append(nn.Linear(sizes[-2], sizes[-1]))
        self.net = nn.Sequential(*layers)
        self.sizes = tuple(int(s) for s in sizes)
        for name, n in (("in_mean", sizes[0]), ("in_std", sizes[0]), ("out_mean", sizes[-1]), ("out_std", sizes[-1])):
            self.register_buffer(name, torch.zeros(n) if "mean" in name else torch.ones(n))

    def set_statistics(self, x: torch.Tensor, y: torch.Tensor) -> None:
        self.in_mean.copy_(x.mean(0))
        self.in_std.copy_(x.std(0).clamp_min(1e-6))
        self.out_mean.copy_(y.mean(0))
        self.out_std.copy_(y.std(0).clamp_min(1e-6))

    def raw(self, x: torch.Tensor) -> torch.Tensor:
        """Standardised output of standardised input (what training fits)."""
        return self.net((x - self.in_mean) / self.in_std)

    def state(self) -> dict:
        return {"sizes": list(self.sizes), "tensors": {k: v.detach().clone() for k, v in self.state_dict().items()}}


class MLP(_Standardised):
    """beta(theta): (B, 77, 3) axis-angle -> (B, K).

    ``sizes`` = (77 * 9, hidden..., K'): the network predicts K' of the K weights, those at
    ``out_index`` (K',) (the body and hand weights; the face weights are not a function of the
    joint rotations) and leaves the others 0.
    """

    def __init__(self, sizes: tuple[int, ...], out_index: torch.Tensor, out_size: int) -> None:
        super().__init__(sizes)
        self.register_buffer("out_index", out_index.long())
        self.out_size = int(out_size)

    def forward(self, pose: torch.Tensor) -> torch.Tensor:
        y = self.raw(pose_features(pose)) * self.out_std + self.out_mean
        return y.new_zeros(y.shape[0], self.out_size).index_copy(1, self.out_index, y)

    def state(self) -> dict:
        return {**super().state(), "out_size": self.out_size}

    @classmethod
    def from_state(cls, state: dict) -> MLP:
        m = cls(tuple(state["sizes"]), state["tensors"]["out_index"], state["out_size"])
        m.load_state_dict(state["tensors"])
        return m.eval()


class CorrectionNet(_Standardised):
    """R(beta_B): (B, K_B) -> ((B, E) RL correction, (B, E) RA correction) through ``basis`` (R, 2E)."""

    def __init__(self, sizes: tuple[int, ...], basis: torch.Tensor) -> None:
        super().__init__(sizes)
        self.register_buffer("basis", basis.float())

    def coefficients(self, beta_body: torch.Tensor) -> torch.Tensor:
        return self.raw(beta_body) * self.out_std + self.out_mean

    def forward(self, beta_body: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        flat = self.coefficients(beta_body) @ self.basis.to(beta_body.dtype)
        e = flat.shape[1] // 2
        return flat[:, :e], flat[:, e:]

    def state(self) -> dict:
        s = super().state()
        s["tensors"]["basis"] = self.basis.half()
        return s

    @classmethod
    def from_state(cls, state: dict) -> CorrectionNet:
        t = dict(state["tensors"])
        m = cls(tuple(state["sizes"]), t["basis"].float())
        t["basis"] = t["basis"].float()
        m.load_state_dict(t)
        return m.eval()
