"""Fit PanoMan to sparse constraints (paper 004 §5): the discrete-shell fit from an initial mesh.

    result = fit(model, alpha, handles, reference=lbs_vertices, pose=theta)

The initial mesh is ``reference``: the LBS fit of ``BodyLayer`` to the same constraints
(:func:`unibody.panoman.body_fit.fit_body`), which also gives the identity ``alpha`` (§5.3 uses
an SMPL fit the same way). With joint rotations ``pose`` the weights beta(theta) of the Fig. 9
network enter the energy as parameter targets (eq. 10, "motion data") with weight
``config.parameters``.

What we measured and did not keep: starting from ``g(X(alpha, beta(theta)))`` (the paper's
initialisation) is worse here. ``g`` integrates frames over the whole surface, so the RLA error
of a blended vector (a few percent per edge) becomes centimetres of drift at the extremities,
and the shell fit then starts far from the handles (figures in benchmarks/README.md).
"""

from __future__ import annotations

import numpy as np
import torch

from .._checks import check_finite, check_shape, check_tensor
from .model import PanoMan
from .shell import Handles, ShellConfig, ShellResult, fit_shell

__all__ = ["fit"]


def fit(
    model: PanoMan,
    alpha: torch.Tensor,
    handles: Handles,
    *,
    reference: torch.Tensor,
    pose: torch.Tensor | None = None,
    config: ShellConfig | None = None,
) -> ShellResult:
    """Fit one mesh.

    Args:
        model: the PanoMan model.
        alpha: (10,) shape coefficients of the identity.
        handles: the constraints (vertex handles and regressed joints).
        reference: (V, 3) m, the initial mesh, in the target's place.
        pose: optional (77, 3) T-pose-relative axis-angle joint rotations (motion-data prior).
        config: weights and schedule of the shell fit (None: the defaults).

    ``alpha``, ``reference`` and ``pose`` may be on any device; the fit runs on the CPU (scipy)
    and returns numpy arrays.
    """
    config = ShellConfig() if config is None else config
    for name, x in (("alpha", alpha), ("reference", reference), ("pose", pose)):
        if x is not None:
            check_tensor(x, name)
            check_finite(x, name)
    check_shape(alpha.reshape(-1), str(model.shape_space.num_params), name="alpha")
    check_shape(reference, f"{model.topology.vertex_count} 3", name="reference")
    if pose is not None:
        check_shape(pose, "77 3", "1 77 3", name="pose")
    # The shell fit is numpy/scipy and the model lives on the CPU: inputs may come from any
    # device (e.g. a fit_body on CUDA) and with gradients; they are copied to the CPU here.
    alpha = alpha.detach().reshape(-1).to("cpu", torch.float64)
    init = reference.detach().reshape(-1, 3).to("cpu", torch.float64).numpy()
    targets = None
    if pose is not None:
        beta0 = model.beta_from_pose(pose.detach().reshape(1, 77, 3).to("cpu", torch.float64))[0].numpy()
        mask = np.zeros(model.num_beta)
        mask[model.beta_net.out_index.numpy()] = 1.0
        targets = (mask, beta0)
    return fit_shell(model.topology, model.subspace(alpha, beta_targets=targets), init, handles, config=config)
