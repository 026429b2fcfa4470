"""The PanoMan model on the canonical topology (paper 004 §4.2).

    rest   B_S(alpha) = mean + S alpha                      native PCA, first 10 components
    RL     X_L(alpha, beta) = sum_Z mean_LZ + M_L beta_L (+ R_L(beta_B))   eq. 3 (+ §4.2 correction)
    RA     X_A(alpha, beta) = sum_Z mean_AZ + M_A beta_A (+ R_A(beta_B))
    mesh   B_P(alpha, beta) = g(X_L, X_A, B_S(alpha))       eq. 5, g = :func:`reconstruct_rla`

``M_L = [M_LB, M_LF, M_LH]`` and ``M_A`` stack six sparse localized decompositions (RL and RA of
body poses, facial expressions and hand gestures). ``beta = (beta_L, beta_A)`` with the
subsets in the order body, face, hands inside each half. Two small MLPs complete it: the
correction ``R(beta_B)`` and ``beta(theta)`` from joint rotations (Fig. 9).

The model is data: :meth:`PanoMan.save` / :meth:`PanoMan.load` write and read one
``torch.save`` file (``weights_only`` safe) that also carries the recipe that built it.
"""

from __future__ import annotations

from dataclasses import dataclass
from importlib import resources
from pathlib import Path

import numpy as np
import scipy.sparse as sp
import torch
from torch import nn

from .._checks import check_finite, check_shape
from ..identity.pca import PCAIdentity
from ..io.atomic import atomic_path
from ..io.weights import read_weights, rebuilding
from ..rig import Rig
from .mesh import EdgeTopology
from .nets import MLP, CorrectionNet
from .reconstruct import reconstruct_rla
from .rla import dihedral_angles, edge_lengths
from .shell import ShellSubspace

__all__ = ["Decomposition", "PanoMan", "SUBSETS", "default_model_path"]

SUBSETS = ("body", "face", "hands")
FORMAT = "unibody.panoman/1"


def default_model_path() -> Path:
    return Path(str(resources.files("unibody.panoman"))) / "data" / "panoman_v1.pt"


@dataclass(frozen=True)
class Decomposition:
    """Sparse localized components of one quantity over one subset.

    Attributes:
        quantity: "rl" or "ra".
        subset: "body", "face" or "hands".
        mean: (E,) mean vector of the subset's training samples.
        index: (2, nnz) int64 (component, edge) of the nonzeros; value (nnz,).
        num_components: K.
    """

    quantity: str
    subset: str
    mean: torch.Tensor
    index: torch.Tensor
    value: torch.Tensor
    num_components: int

    @classmethod
    def from_dense(cls, quantity: str, subset: str, mean: torch.Tensor, components: torch.Tensor) -> Decomposition:
        nz = components.nonzero().T
        return cls(quantity, subset, mean.float(), nz, components[nz[0], nz[1]].float(), components.shape[0])

    def matrix(self, num_edges: int) -> sp.csc_matrix:
        """(E, K) scipy sparse, components as columns (float64)."""
        i = self.index.numpy()
        return sp.csc_matrix((self.value.double().numpy(), (i[1], i[0])), shape=(num_edges, self.num_components))

    def support_sizes(self) -> torch.Tensor:
        """(K,) number of edges each component touches."""
        return torch.bincount(self.index[0], minlength=self.num_components)


class PanoMan(nn.Module):
    """Shape PCA + sparse localized RL/RA components + correction MLP + beta(theta) MLP.

    Args:
        decompositions: the six :class:`Decomposition` (any subset may be missing).
        shape_components: number of PCA components used for the rest shape (paper: 10).
        beta_net: optional module, (B, 77, 3) axis-angle pose -> (B, K_L + K_A) weights.
        correction: optional module, (B, K_LB + K_AB) body weights -> ((B, E), (B, E)) RL/RA corrections.
        joint_regressor: optional (vertex ids (77, k), weights (77, k)): joints 1..77 as narrow linear
            functions of the vertices (:func:`~unibody.panoman.body_fit.sparse_joint_regressor`), the
            joint-position constraints of the fit (§5.2).
        metadata: recipe and figures (informative).
    """

    def __init__(
        self,
        decompositions: list[Decomposition],
        *,
        shape_components: int = 10,
        beta_net: nn.Module | None = None,
        correction: nn.Module | None = None,
        joint_regressor: tuple[torch.Tensor, torch.Tensor] | None = None,
        metadata: dict | None = None,
    ) -> None:
        super().__init__()

        rig = Rig.canonical()
        self.topology = EdgeTopology.from_faces(rig.faces.long(), rig.num_vertices)
        self.shape_space = PCAIdentity.from_asset(num_components=shape_components, dtype=torch.float64)
        order = {(q, s): i for i, (q, s) in enumerate((q, s) for q in ("rl", "ra") for s in SUBSETS)}
        self.decompositions = sorted(decompositions, key=lambda d: order[(d.quantity, d.subset)])
        self.beta_net, self.correction = beta_net, correction
        self.joint_regressor = joint_regressor
        self.metadata = dict(metadata or {})
        e = self.topology.num_edges
        self._mats = {
            q: sp.hstack([d.matrix(e) for d in self.decompositions if d.quantity == q]).tocsc() for q in ("rl", "ra")
        }
        self._means = {q: sum(d.mean.double() for d in self.decompositions if d.quantity == q) for q in ("rl", "ra")}

    # ----------------------------------------------------------------- layout of beta
    @property
    def num_beta(self) -> int:
        return sum(d.num_components for d in self.decompositions)

    def beta_slices(self) -> dict[tuple[str, str], slice]:
        """Where each decomposition's weights sit in beta."""
        out, start = {}, 0
        for d in self.decompositions:
            out[(d.quantity, d.subset)] = slice(start, start + d.num_components)
            start += d.num_components
        return out

    def body_beta(self, beta: torch.Tensor) -> torch.Tensor:
        """(B, K_LB + K_AB) the body weights the correction MLP reads."""
        s = self.beta_slices()
        return torch.cat([beta[:, s[("rl", "body")]], beta[:, s[("ra", "body")]]], dim=1)

    # ----------------------------------------------------------------- model
    def rest(self, alpha: torch.Tensor) -> torch.Tensor:
        """B_S(alpha): (B, V, 3) m rest meshes (bind A-pose) of (B, 10) shape coefficients."""
        return self.shape_space(alpha.double())

    def rla(self, beta: torch.Tensor, *, corrected: bool = True) -> tuple[torch.Tensor, torch.Tensor]:
        """(rl, ra) (B, E) of weights beta (B, K), eq. 3 plus the correction."""
        check_shape(beta, f"B {self.num_beta}", name="beta")
        check_finite(beta, "beta")
        b = beta.double().numpy()
        k_l = self._mats["rl"].shape[1]
        rl = torch.from_numpy((self._mats["rl"] @ b[:, :k_l].T).T) + self._means["rl"]
        ra = torch.from_numpy((self._mats["ra"] @ b[:, k_l:].T).T) + self._means["ra"]
        if corrected and self.correction is not None:
            with torch.no_grad():
                dl, da = self.correction(self.body_beta(beta.float()))
            rl, ra = rl + dl.double(), ra + da.double()
        # weights far outside the training range (e.g. extrapolated by beta(theta)) could ask
        # for non-positive edge lengths: keep every edge at least 5 % of its rest length
        return rl.clamp_min(-0.95), ra

    def forward(
        self, alpha: torch.Tensor, beta: torch.Tensor, *, reference: torch.Tensor | None = None
    ) -> torch.Tensor:
        """B_P(alpha, beta): (B, V, 3) m posed meshes through g (eq. 5), float64.

        Args:
            alpha: (B, 10) shape coefficients.
            beta: (B, K) motion weights.
            reference: optional (B, V, 3) meshes to align the result to rigidly (g is defined
                up to a rigid motion).
        """

        rl, ra = self.rla(beta)
        return reconstruct_rla(rl, ra, self.rest(alpha), self.topology, reference=reference)

    def beta_from_pose(self, pose: torch.Tensor) -> torch.Tensor:
        """beta(theta): (B, 77, 3) T-pose-relative axis-angle -> (B, K) weights (Fig. 9)."""
        if self.beta_net is None:
            raise ValueError("pose: this model has no beta(theta) network")
        check_shape(pose, "B 77 3", name="pose")
        check_finite(pose, "pose")
        with torch.no_grad():
            return self.beta_net(pose.float()).double()

    def project(self, rl: torch.Tensor, ra: torch.Tensor) -> torch.Tensor:
        """Least-squares weights (B, K) of RL/RA vectors (B, E) on the components (no correction)."""
        out = []
        for q, x in (("rl", rl), ("ra", ra)):
            m = self._mats[q]
            y = (x.double() - self._means[q]).numpy().T
            lhs = (m.T @ m).toarray() + 1e-8 * np.eye(m.shape[1])
            out.append(torch.from_numpy(np.linalg.solve(lhs, m.T @ y).T))
        return torch.cat(out, dim=1)

    def subspace(self, alpha: torch.Tensor, *, beta_targets=None):
        """The :class:`~unibody.panoman.shell.ShellSubspace` of one identity (alpha (10,)), for fitting."""

        rest = self.rest(alpha.reshape(1, -1))
        topo = self.topology
        l0 = edge_lengths(rest, topo)[0].numpy()
        a0 = dihedral_angles(rest, topo)[0].numpy()
        v = rest[0].numpy()
        f = topo.faces.numpy()
        area = 0.5 * np.linalg.norm(np.cross(v[f[:, 1]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 0]]), axis=1)
        s0 = area[topo.edge_faces.numpy()].sum(1)
        residual = None
        if self.correction is not None:

            def residual(beta: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
                with torch.no_grad():
                    b = self.body_beta(torch.from_numpy(beta)[None].float())
                    dl, da = self.correction(b)
                return dl[0].double().numpy(), da[0].double().numpy()

        return ShellSubspace(
            l0,
            a0,
            s0,
            self._means["rl"].numpy(),
            self._means["ra"].numpy(),
            self._mats["rl"],
            self._mats["ra"],
            residual,
            beta_targets,
        )

    # ----------------------------------------------------------------- files
    def state(self) -> dict:
        return {
            "format": FORMAT,
            "shape_components": self.shape_space.num_params,
            "decompositions": [
                {
                    "quantity": d.quantity,
                    "subset": d.subset,
                    "mean": d.mean,
                    "index": d.index.int(),
                    "value": d.value.half(),
                    "num_components": d.num_components,
                }
                for d in self.decompositions
            ],
            "beta_net": None if self.beta_net is None else self.beta_net.state(),
            "correction": None if self.correction is None else self.correction.state(),
            "joint_regressor": None if self.joint_regressor is None else list(self.joint_regressor),
            "metadata": self.metadata,
        }

    def save(self, path: str | Path) -> None:
        with atomic_path(path) as tmp:
            torch.save(self.state(), tmp)

    @classmethod
    def load(cls, path: str | Path | None = None) -> PanoMan:
        """The shipped model (None) or a file written by :meth:`save`."""

        p = default_model_path() if path is None else Path(path)
        if not p.is_file():
            raise FileNotFoundError(f"path: no PanoMan model at {p}; build one with scripts/build_panoman.py")
        what = f"a {FORMAT} file written by PanoMan.save"
        s = read_weights(p, what)
        if s.get("format") != FORMAT:
            raise ValueError(f"{p}: not {what} (format {s.get('format')!r}, expected {FORMAT!r})")
        with rebuilding(p, what):
            decs = [
                Decomposition(**{**d, "index": d["index"].long(), "value": d["value"].float()})
                for d in s["decompositions"]
            ]
            beta_net = None if s["beta_net"] is None else MLP.from_state(s["beta_net"])
            correction = None if s["correction"] is None else CorrectionNet.from_state(s["correction"])
            reg = s.get("joint_regressor")
            model = cls(
                decs,
                shape_components=s["shape_components"],
                beta_net=beta_net,
                correction=correction,
                joint_regressor=None if reg is None else tuple(reg),
                metadata=s["metadata"],
            )
        return model
