"""The canonical rig's bind mesh as a posable, rescalable template (registration stage 2).

Notation (column vectors, metres): bind world transforms ``(R_b,k, p_b,k)``, bind local
rotations ``L_k = R_b,p^T R_b,k`` and offsets ``o_k = R_b,p^T (p_b,k - p_b,p)`` (p the parent).
Parameters: a local rotation delta ``exp(theta_k)`` per joint (zero = the bind A-pose), a
bone-length scale ``exp(lambda_k)`` on each offset, a size scale ``exp(mu_k)`` of the
geometry each joint carries, and a global similarity ``(s, R_g, t)``. Forward kinematics
gives world transforms ``(G_R,k, G_p,k)``; vertices are skinned with the canonical weights
``w_ik`` (scaled LBS):

    v'_i = sum_k w_ik (G_R,k exp(mu_k) R_b,k^T (v_i - p_b,k) + G_p,k),    x_i = s R_g v'_i + t.

Left/right joints share their scale parameters (bodies are close to symmetric), except the
hands, which are fitted independently.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import cached_property

import torch

from ..geometry.kinematics import forward_kinematics
from ..geometry.rotations import axis_angle_to_matrix
from ..rig import Rig

__all__ = ["Template", "TemplateParams"]


@dataclass(frozen=True, slots=True)
class TemplateParams:
    """Template parameters (float64 tensors; any may require grad).

    Attributes:
        theta: (J, 3) axis-angle local rotation deltas from the bind pose.
        bone: (G,) log bone-length scales per symmetry group.
        size: (G,) log geometry scales per symmetry group.
        log_scale: () log global scale.
        rot: (3,) axis-angle global rotation.
        transl: (3,) m, global translation.
    """

    theta: torch.Tensor
    bone: torch.Tensor
    size: torch.Tensor
    log_scale: torch.Tensor
    rot: torch.Tensor
    transl: torch.Tensor

    def detached(self) -> TemplateParams:
        return TemplateParams(*(getattr(self, k).detach().clone() for k in self.__slots__))


class Template:
    """The canonical bind mesh with its skeleton, ready to be posed and scaled (float64, CPU)."""

    def __init__(self, rig: Rig) -> None:
        self.rig = rig
        self.tree = rig.tree
        self.vertices = rig.bind_vertices.to(torch.float64)
        self.faces = rig.faces.long()
        self.weights = rig.dense_skinning_weights().to(torch.float64)
        bind = rig.bind_transforms.to(torch.float64)
        self.bind_rot, self.bind_pos = bind[:, :3, :3], bind[:, :3, 3]
        parents = torch.tensor([max(p, 0) for p in rig.tree.parents])
        self.parents = parents
        rp_t = self.bind_rot[parents].transpose(-1, -2)
        self.local_rot = rp_t @ self.bind_rot
        self.offsets = (rp_t @ (self.bind_pos - self.bind_pos[parents])[..., None]).squeeze(-1)
        self.local_rot[0], self.offsets[0] = torch.eye(3, dtype=torch.float64), self.bind_pos[0]
        # T-pose: absolute local rotation O_p^T O_j, i.e. delta L^T O_p^T O_j (paper 001).
        o = rig.tpose_orient.to(torch.float64)
        tpose_local = o[parents].transpose(-1, -2) @ o
        self.tpose_delta = self.local_rot.transpose(-1, -2) @ tpose_local
        self.tpose_delta[0] = torch.eye(3, dtype=torch.float64)
        self.skinned = self.weights.sum(0) > 0
        names = rig.joint_names
        groups: dict[str, int] = {}
        # Hands keep their own scales per side, so the two hands are independent problems.
        key = [n if "Hand" in n else n.replace("Left", "").replace("Right", "") for n in names]
        self.group = torch.tensor([groups.setdefault(k, len(groups)) for k in key])
        self.num_groups = len(groups)
        self.num_joints = len(names)

    def params(self, theta: torch.Tensor | None = None) -> TemplateParams:
        """Neutral parameters (bind pose, unit scales) or the given pose deltas."""
        z = self.vertices.new_zeros
        th = z(self.num_joints, 3) if theta is None else theta.clone()
        return TemplateParams(th, z(self.num_groups), z(self.num_groups), z(()), z(3), z(3))

    def joints(self, p: TemplateParams, delta_rot: torch.Tensor | None = None):
        """World transforms ``(G_R (J, 3, 3), G_p (J, 3))`` before the global similarity."""
        rot = axis_angle_to_matrix(p.theta) if delta_rot is None else delta_rot
        local_r = self.local_rot @ rot
        local_t = self.offsets * torch.exp(p.bone)[self.group, None]
        local_t = torch.cat([self.offsets[:2], local_t[2:]])  # Root and Hips keep their places
        g_r, g_p = forward_kinematics(self.tree, local_r[None], local_t[None])
        return g_r[0], g_p[0]

    def pose(self, p: TemplateParams, index: torch.Tensor | None = None, delta_rot: torch.Tensor | None = None):
        """Posed template vertices ``(N, 3)`` (all vertices, or those in ``index``) and joints ``(J, 3)``."""
        g_r, g_p = self.joints(p, delta_rot)
        sr = g_r * torch.exp(p.size)[self.group, None, None] @ self.bind_rot.transpose(-1, -2)
        st = g_p - (sr @ self.bind_pos[..., None]).squeeze(-1)
        mats = torch.cat([sr, st[..., None]], dim=-1).reshape(-1, 12)  # (J, 12)
        v = self.vertices if index is None else self.vertices[index]
        w = self.weights if index is None else self.weights[index]
        m = (w @ mats).view(-1, 3, 4)
        x = (m[..., :3] @ v[..., None]).squeeze(-1) + m[..., 3]
        return self.similarity(p, x), self.similarity(p, g_p)

    @staticmethod
    def similarity(p: TemplateParams, x: torch.Tensor) -> torch.Tensor:
        """``s R_g x + t`` for points ``(..., 3)``."""
        r = axis_angle_to_matrix(p.rot)
        return torch.exp(p.log_scale) * x @ r.transpose(-1, -2) + p.transl

    @cached_property
    def finger_pairs(self) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
        """Neighbouring fingers' joints at the same level and the knuckles that span each palm.

        Returns ``(pairs (P, 2), bind distances (P,), side of each pair (P,), knuckles (2, 2))``:
        index-middle, middle-ring and ring-pinky at levels 2, 3, 4 and the tip, left hand then
        right (side 0, 1); ``knuckles`` holds the index and pinky knuckle (level 2) per side.
        """
        names = self.rig.joint_names
        pairs, side_of, knuckles = [], [], []
        for s, side in enumerate(("Left", "Right")):
            knuckles.append((names.index(f"{side}HandIndex2"), names.index(f"{side}HandPinky2")))
            for a, b in (("Index", "Middle"), ("Middle", "Ring"), ("Ring", "Pinky")):
                for level in ("2", "3", "4", "End"):
                    pairs.append((names.index(f"{side}Hand{a}{level}"), names.index(f"{side}Hand{b}{level}")))
                    side_of.append(s)
        idx = torch.tensor(pairs)
        bind = (self.bind_pos[idx[:, 0]] - self.bind_pos[idx[:, 1]]).norm(dim=-1)
        return idx, bind, torch.tensor(side_of), torch.tensor(knuckles)

    @cached_property
    def finger_axes(self) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
        """Anatomical axes of the four fingers' joints, in each joint's bind frame.

        Returns ``(hinge joints (H,), flexion axes (H, 3), knuckle joints (K,), bone axes (K, 3),
        knuckle flexion axes (K, 3))``:
        the middle and end finger joints (levels 3, 4) bend about one axis, the flexion axis
        (the palm's width direction made orthogonal to the bone); the knuckles (level 2) also
        spread, but do not twist about their bone.
        """
        names, pos, rot = self.rig.joint_names, self.bind_pos, self.bind_rot
        hinge, flex, knuckle, bone, knuckle_flex = [], [], [], [], []
        for side in ("Left", "Right"):
            width = pos[names.index(f"{side}HandPinky2")] - pos[names.index(f"{side}HandIndex2")]
            for finger in ("Index", "Middle", "Ring", "Pinky"):
                for level in ("2", "3", "4"):
                    k = names.index(f"{side}Hand{finger}{level}")
                    child = names.index(f"{side}Hand{finger}{int(level) + 1 if level != '4' else 'End'}")
                    b = pos[child] - pos[k]
                    b = b / b.norm()
                    a = width - (width @ b) * b
                    a = a / a.norm()
                    if level == "2":
                        knuckle.append(k)
                        bone.append(rot[k].T @ b)
                        knuckle_flex.append(rot[k].T @ a)
                    else:
                        hinge.append(k)
                        flex.append(rot[k].T @ a)
        return (
            torch.tensor(hinge),
            torch.stack(flex),
            torch.tensor(knuckle),
            torch.stack(bone),
            torch.stack(knuckle_flex),
        )
