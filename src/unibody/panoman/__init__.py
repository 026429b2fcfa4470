"""PanoMan (Wang et al., ACM TOG 2021) on the canonical topology.

Sparse localized components over relative edge lengths and dihedral angles (RLA) of the
canonical mesh, a correction MLP and a beta(theta) MLP, and a discrete-shell fit to sparse
constraints:

    from unibody.panoman import PanoMan, Handles, fit, fit_body
    model = PanoMan.load()                                   # shipped, built by scripts/build_panoman.py
    lbs = fit_body(layer, vertex_ids, points, regressor, joints)   # BodyLayer fit: init + baseline
    result = fit(model, lbs.shape[0], Handles(vertex_ids, points[0]), reference=lbs.vertices[0])

Modules: ``mesh`` (edge topology), ``rla`` (RLA vectors, shell Jacobian), ``reconstruct``
(``g``, Appendix A), ``splocs`` (sparse localized decomposition), ``dataset`` (H_B, H_F, H_H),
``model``, ``nets``, ``build``, ``shell`` (discrete-shell energy and solver), ``body_fit``, ``fit``.
"""

from .body_fit import BodyFit, fit_body, regressor_matrix, sparse_joint_regressor
from .fit import fit
from .mesh import EdgeTopology
from .model import Decomposition, PanoMan
from .reconstruct import reconstruct_rla
from .rla import dihedral_angles, edge_lengths, rla
from .shell import Handles, ShellConfig, ShellResult, fit_shell
from .splocs import SplocsConfig, SplocsResult, sparse_localized_components

__all__ = [
    "BodyFit",
    "Decomposition",
    "EdgeTopology",
    "Handles",
    "PanoMan",
    "ShellConfig",
    "ShellResult",
    "SplocsConfig",
    "SplocsResult",
    "dihedral_angles",
    "edge_lengths",
    "fit",
    "fit_body",
    "fit_shell",
    "reconstruct_rla",
    "regressor_matrix",
    "rla",
    "sparse_joint_regressor",
    "sparse_localized_components",
]
