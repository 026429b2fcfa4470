"""What the marker solve returns (:class:`SolveResult`) and its conversion to a :class:`~unibody.motion.Motion`."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from ..motion import Motion
from .frames import check_fps

__all__ = ["SolveResult"]


@dataclass(frozen=True, slots=True)
class SolveResult:
    """A solved marker sequence.

    Attributes:
        identity: (K,) PCA coefficients (``BodyLayer.from_pca(num_components=K)``).
        latent: (M, 3) m, latent marker positions on the fitted rest body (bind A-pose, the
            identity's rest mesh frame).
        anchors: (M,) int64, the canonical vertex each latent marker is skinned with.
        pose: (T, 77, 3) axis-angle, T-pose-relative local rotations of joints 1..77.
        transl: (T, 3) m, Hips world position, unibody frame (Y up).
        markers: (T, M, 3) m, the model markers of every frame (unibody frame), missing or not.
        residual: (T, M) m, distance of each observed marker to its model marker after the
            fit; NaN where the marker is missing.
        solved: (T,) bool, False for frames interpolated for lack of visible markers.
        stage1_frames: (F,) int64, the frames stage 1 fitted the shape on.
    """

    identity: torch.Tensor
    latent: torch.Tensor
    anchors: torch.Tensor
    pose: torch.Tensor
    transl: torch.Tensor
    markers: torch.Tensor
    residual: torch.Tensor
    solved: torch.Tensor
    stage1_frames: torch.Tensor

    def to_motion(self, fps: float) -> Motion:
        """The motion (``identity_backend="pca"``); it replays in ``BodyLayer.from_pca(num_components=K)``."""
        check_fps(fps)
        return Motion(
            self.pose.detach().cpu().numpy().astype(np.float32),
            self.transl.detach().cpu().numpy().astype(np.float32),
            float(fps),
            self.identity.detach().cpu().numpy().astype(np.float32),
            "pca",
        )
