"""The correctives model (paper 000 §3.5.2, eq. 7; the two-stage structure of MHR).

``V_corr(beta, theta) = V(beta) + s(beta) f(theta)``: the 77 local joint rotations relative to the
identity's rest pose, as 6D vectors minus the identity's (so the rest pose is 0), go to a bank
of ``K = A x C`` corrective activations (``C = 24`` per active joint), which map to rest-space
displacements of the vertices near that joint only. Activation ``a`` of joint ``k`` sees the
rotations of k, its parent and its children (Hips and Root excluded: the global orientation
must not deform the body):

    h_k = relu(W1_k x_k + b1_k),  a_k = relu(W2_k h_k + b2_k) - relu(W2_k relu(b1_k) + b2_k)
    f(theta)[mask_k] += a_k D_k         (D_k: (C, |mask_k| x 3))

so ``f`` is exactly 0 at the rest pose. ``s(beta)`` is the identity's size (mean limb bone
length) over the training mean: one set of displacements serves children and adults. The masks
are the teacher's joint regions (:func:`~.teacher.teacher_region`); the active joints are
the shoulders, elbows, wrists, hips, knees and ankles.
"""

from __future__ import annotations

from importlib import resources
from pathlib import Path

import torch
from torch import nn

from ..geometry.rotations import matrix_to_rot6d
from ..geometry.sparse import csr

__all__ = ["Correctives", "default_weights_path", "size_of", "LIMB_BONES"]

LIMB_BONES: tuple[tuple[int, int], ...] = (
    (13, 14),
    (14, 15),
    (68, 69),
    (69, 70),
    (41, 42),
    (42, 43),
    (73, 74),
    (74, 75),
)
"""(joint, child) ids of the eight limb bones (upper arms, forearms, thighs, shins) on the canonical rig."""


def size_of(rest_joints: torch.Tensor, bones: torch.Tensor | None = None) -> torch.Tensor:
    """(Bi,) mean length (m) of the limb bones (default :data:`LIMB_BONES`) of fitted rest joints (Bi, J, 3).

    Args:
        rest_joints: (Bi, J, 3) m; bones: (L, 2) (joint, child) ids.
    """
    bones = torch.tensor(LIMB_BONES) if bones is None else bones
    return (rest_joints[:, bones[:, 1]] - rest_joints[:, bones[:, 0]]).norm(dim=-1).mean(-1)


def default_weights_path(procedural: bool = False) -> Path:
    """The shipped weights: ``correctives.pt`` for the plain rig, ``correctives_twist.pt`` for the
    procedural-twist rig (trained against LBS + twist joints, so the twist is not corrected twice)."""
    name = "correctives_twist.pt" if procedural else "correctives.pt"
    return Path(str(resources.files("unibody.correctives") / "data" / name))


class Correctives(nn.Module):
    """Pose correctives on the canonical topology.

    Args:
        inputs: (A, I) int64 joint ids (1..77) feeding each active joint, padded with -1.
        vertices: per active joint, (V_k,) int64 vertex ids of its mask.
        num_vertices: V of the topology.
        hidden, channels: widths of the two layers (``C`` = channels, 24 in the paper).
        size_ref: m, the training identities' mean limb bone length.
        joint_names: the active joints (for reports).
        bones: (joint, child) ids whose mean rest length is the identity's size (:func:`size_of`).
        meta: recipe and provenance kept with the weights.
    """

    def __init__(
        self,
        inputs: torch.Tensor,
        vertices: list[torch.Tensor],
        num_vertices: int,
        *,
        hidden: int = 64,
        channels: int = 24,
        size_ref: float = 1.0,
        joint_names: tuple[str, ...] = (),
        bones: tuple[tuple[int, int], ...] = LIMB_BONES,
        meta: dict | None = None,
    ) -> None:
        super().__init__()
        a, i = inputs.shape
        self.num_vertices, self.hidden, self.channels = num_vertices, hidden, channels
        self.joint_names, self.meta = joint_names, dict(meta or {})
        self.register_buffer("inputs", inputs)
        # The joints any activation reads (sorted ids 2..77) and each input's slot among them
        # (slot len(needed) is a zero row for the padding).
        needed = torch.unique(inputs[inputs >= 0])
        self.register_buffer("needed", needed)
        self.register_buffer("_input_slot", torch.where(inputs >= 0, torch.searchsorted(needed, inputs), len(needed)))
        # Inputs held at a constant (see :meth:`freeze`): (N,) mask and (N, 6) values.
        self.register_buffer("_frozen", torch.zeros(len(needed), dtype=torch.bool))
        self.register_buffer("_frozen_value", torch.zeros(len(needed), 6))
        sizes = torch.tensor([len(v) for v in vertices])
        self.register_buffer("sizes", sizes)
        ends = torch.cumsum(sizes, 0).tolist()
        self._blocks = list(zip([0, *ends[:-1]], ends, strict=True))
        self.register_buffer("vertex_ids", torch.cat(vertices))
        self.register_buffer("size_ref", torch.tensor(float(size_ref)))
        self.register_buffer("bones", torch.tensor(bones, dtype=torch.int64).view(-1, 2))
        gen = torch.Generator().manual_seed(0)
        self.w1 = nn.Parameter(torch.randn(a, hidden, i * 6, generator=gen) / (i * 6) ** 0.5)
        self.b1 = nn.Parameter(torch.zeros(a, hidden))
        self.w2 = nn.Parameter(torch.randn(a, channels, hidden, generator=gen) / hidden**0.5)
        self.b2 = nn.Parameter(torch.zeros(a, channels))
        # [(mask vertex, xyz), c], the active joints' masks stacked: joint k's rows 3 start_k .. 3 end_k.
        self.decode = nn.Parameter(torch.zeros(int(sizes.sum()) * 3, channels))
        # The union of the masks, sorted: where f may be non-zero.
        union, inverse = torch.unique(self.vertex_ids, return_inverse=True)
        self.register_buffer("union", union)
        self.register_buffer("_slot", inverse)

    def size_of(self, rest_joints: torch.Tensor) -> torch.Tensor:
        """(Bi,) the identities' sizes (m): mean length of :attr:`bones` in rest joints (Bi, J, 3)."""
        return size_of(rest_joints, self.bones)

    @property
    def num_active(self) -> int:
        return self.inputs.shape[0]

    def features(self, rel: torch.Tensor) -> torch.Tensor:
        """(B, N, 6) inputs of the :attr:`needed` joints: 6D of their rest-relative rotations minus the identity's.

        Args:
            rel: (B, N, 3, 3) rest-relative local rotations of the :attr:`needed` joints.
        """
        return matrix_to_rot6d(rel) - rel.new_tensor([1.0, 0.0, 0.0, 0.0, 1.0, 0.0])

    def freeze(self, joints: torch.Tensor, values: torch.Tensor) -> Correctives:
        """Hold the inputs of ``joints`` (ids among :attr:`needed`) at ``values`` (n, 6) features.

        For inputs that did not vary in training (the fingers, straight in every training
        pose, feed the wrists' activations): any other value would be an extrapolation.
        """
        slot = torch.searchsorted(self.needed, joints.to(self.needed.device))
        self._frozen[slot] = True
        self._frozen_value[slot] = values.to(self._frozen_value)
        return self

    def _mlp(self, x6: torch.Tensor) -> torch.Tensor:
        x6 = torch.where(self._frozen[:, None], self._frozen_value.to(x6.dtype), x6)
        x6 = torch.cat([x6, x6.new_zeros(x6.shape[0], 1, 6)], 1)  # + the padding's zero row
        x = x6[:, self._input_slot].flatten(-2)  # (B, A, I*6)
        w1, b1, w2, b2 = (p.to(x6.dtype) for p in (self.w1, self.b1, self.w2, self.b2))
        h = torch.relu(torch.einsum("ahi,bai->bah", w1, x) + b1)
        return torch.relu(torch.einsum("ach,bah->bac", w2, h) + b2)

    def activations(self, x6: torch.Tensor) -> torch.Tensor:
        """(B, A, C) activations of :meth:`features` (B, N, 6); exactly 0 where they are 0 (the rest pose)."""
        return self._mlp(x6) - self._rest_mlp(x6)

    def _rest_mlp(self, x6: torch.Tensor) -> torch.Tensor:
        """(1, A, C) the MLP at the rest pose: a constant of the parameters, kept between calls
        while they need no gradient and have not changed (it was a second MLP pass per pose)."""
        params = (self.w1, self.b1, self.w2, self.b2, self._frozen, self._frozen_value)
        zero = x6.new_zeros(1, *x6.shape[1:])
        if torch.is_grad_enabled() and any(p.requires_grad for p in params):
            return self._mlp(zero)
        key = (x6.dtype, x6.device, tuple((p.data_ptr(), p._version) for p in params))
        cached = getattr(self, "_rest_cache", None)
        if cached is None or cached[0] != key:
            with torch.no_grad():
                cached = self._rest_cache = (key, self._mlp(zero))
        return cached[1]

    def displacements_vm(self, x6: torch.Tensor, scale: torch.Tensor) -> torch.Tensor:
        """(U, 3, B) rest-space displacements (m) on :attr:`union`, vertex-major, from :meth:`features`.

        Args:
            x6: (B, N, 6) features; scale: (B,) or (1,) identity size / :attr:`size_ref`.
        """
        act = self.activations(x6) * scale.to(x6.dtype).view(-1, 1, 1)  # (B, A, C)
        b = act.shape[0]
        dec = self.decode.to(x6.dtype)
        # One small product per active joint, over its own mask: (3 V_k, 24) @ (24, B).
        if torch.is_grad_enabled() and (act.requires_grad or dec.requires_grad):
            per_mask = torch.cat([dec[3 * s : 3 * e] @ act[:, k].t() for k, (s, e) in enumerate(self._blocks)])
        else:  # the same products straight into one buffer (no concatenating copy)
            per_mask, at = dec.new_empty(dec.shape[0], b), act.permute(1, 2, 0)
            for k, (s, e) in enumerate(self._blocks):
                torch.mm(dec[3 * s : 3 * e], at[k], out=per_mask[3 * s : 3 * e])
        out = per_mask.new_zeros(len(self.union), 3, b)
        return out.index_add_(0, self._slot, per_mask.view(-1, 3, b))

    def union_displacements(self, rel: torch.Tensor, size: torch.Tensor) -> torch.Tensor:
        """(B, U, 3) rest-space displacements (m) on :attr:`union` vertices.

        Args:
            rel: (B, 77, 3, 3) local rotations (joints 1..77) relative to the identity's rest pose.
            size: (B,) or (1,) the identities' mean limb bone lengths (m).
        """
        x6 = self.features(rel[:, self.needed - 1])
        return self.displacements_vm(x6, size / self.size_ref).permute(2, 0, 1)

    def forward(self, rel: torch.Tensor, size: torch.Tensor) -> torch.Tensor:
        """(B, V, 3) rest-space displacements on the whole topology (zero off :attr:`union`).

        Args:
            rel: (B, 77, 3, 3) local rotations (joints 1..77) relative to the identity's rest pose.
            size: (B,) or (1,) the identities' mean limb bone lengths (m).
        """
        d = self.union_displacements(rel, size)
        return d.new_zeros(d.shape[0], self.num_vertices, 3).index_copy(1, self.union, d)

    def world_relative(self, world: torch.Tensor, rest_rotations: torch.Tensor, parents: torch.Tensor) -> torch.Tensor:
        """(B, N, 3, 3) the :attr:`needed` joints' rest-relative local rotations, from posed world transforms.

        Args:
            world: (B, J, 4, 4) posed world transforms; rest_rotations: (Bi, J, 3, 3); parents: (J,).
        """
        n = self.needed
        wr = world[:, :, :3, :3]
        wp, wk = wr[:, parents[n]], wr[:, n]
        local = (wp[..., :, :, None] * wk[..., :, None, :]).sum(-3)  # R_p^T R_k, (B, N, 3, 3)
        rr = rest_rotations[:, :, :3, :3]
        rest_local = (rr[:, parents[n], :, :, None] * rr[:, n, :, None, :]).sum(-3)
        return (rest_local[..., :, :, None] * local[..., :, None, :]).sum(-3)

    def posed(
        self, vertices: torch.Tensor, rel: torch.Tensor, mats: torch.Tensor, size: torch.Tensor, binding: dict
    ) -> torch.Tensor:
        """LBS vertices (B, V, 3) plus the skinned correctives of the pose that gave them.

        Args:
            vertices: (B, V, 3) LBS of the rest meshes, a view of vertex-major (V, B, 3) storage
                (a fresh tensor: updated in place when no gradient is needed).
            rel: (B, N, 3, 3) the :attr:`needed` joints' rest-relative local rotations
                (:meth:`world_relative`, or :meth:`rest_relative` rows ``needed - 1``).
            mats: (J, 4, 3, B) joint-major skinning transforms of the rig that skinned
                ``vertices`` (``geometry.kinematics``); size: (Bi,) identity sizes (:func:`size_of`);
            binding: :meth:`skin_binding` of that rig's skinning.
        """
        d = self.displacements_vm(self.features(rel), size / self.size_ref)
        return self.apply(vertices, mats, d, binding)

    def skin_binding(self, skinning) -> dict[str, torch.Tensor]:  # noqa: ANN001 (a geometry.skinning.Skinning)
        """The skinning weights of the :attr:`union` rows, to skin displacements by :meth:`apply`.

        Only the joints that skin those rows are kept (Jd of the rig's), as a CSR (U, Jd) matrix:
        ``{"crow", "col", "val", "joints"}``. The layer keeps it (one model may serve a plain and
        a procedural-twist layer, whose skinning differs).
        """
        dense = skinning.dense()[self.union.to(skinning.weight.device)]
        joints = torch.nonzero(dense.abs().amax(0) > 0).flatten()
        w = dense[:, joints].to_sparse_csr()
        return {"crow": w.crow_indices().int(), "col": w.col_indices().int(), "val": w.values(), "joints": joints}

    @staticmethod
    def rest_relative(local: torch.Tensor, rest_rotations: torch.Tensor, parents: torch.Tensor) -> torch.Tensor:
        """(B, 77, 3, 3) local rotations relative to the rest pose, ``R_rest,loc^T R_loc``.

        Args:
            local: (B, J, 3, 3) absolute local rotations, Root first (row 0 is not used).
            rest_rotations: (Bi, J, 3, 3) fitted rest world rotations; parents: (J,) (Root's 0).
        """
        rest_local = rest_rotations[:, parents[1:]].transpose(-1, -2) @ rest_rotations[:, 1:]
        # A^T B as broadcast products: cheaper than a batched matmul of 3x3 matrices.
        return (rest_local[..., :, :, None] * local[:, 1:, :, None, :]).sum(-3)

    def apply(self, vertices: torch.Tensor, mats: torch.Tensor, d: torch.Tensor, binding: dict) -> torch.Tensor:
        """LBS of the rest mesh plus the skinned displacements: ``LBS(v + d) = LBS(v) + (sum_k w_k R_k) d``.

        Args:
            vertices: (B, V, 3) LBS of the rest meshes (a fresh tensor: updated in place when no
                gradient is needed).
            mats: (J, 4, 3, B) joint-major skinning transforms (``geometry.kinematics``).
            d: (U, 3, B) vertex-major rest-space displacements on :attr:`union`.
            binding: :meth:`skin_binding` of the skinning ``mats`` belong to.
        """
        u, b = len(self.union), mats.shape[3]
        joints = binding["joints"]
        jd = len(joints)
        # Rotations as (Jd, [column, row, pose]), mats' own layout: the blended rotations then
        # come out as (U, column, row, B), and d (U, column, B) multiplies them along the poses.
        rot = mats.index_select(0, joints)[:, :3].reshape(jd, 9 * b)
        w = csr(binding["crow"], binding["col"], binding["val"].to(mats.dtype), (u, jd))
        if torch.is_grad_enabled() and (rot.requires_grad or w.requires_grad):
            blend = w @ rot
        else:  # MKL's sparse product is fastest per column at 24 columns (geometry.skinning)
            blend = rot.new_empty(u, 9 * b)
            for s in range(0, 9 * b, 24):
                torch.addmm(blend[:, s : s + 24], w, rot[:, s : s + 24], beta=0, out=blend[:, s : s + 24])
        # Three multiply-adds over (U, 3, B), then one copy into the output's (U, B, 3) layout:
        # measured 1.2x faster at B = 32 than a product over (U, 3, B, 3) broadcasting d along
        # the rows and a sum over the columns.
        bl = blend.view(u, 3, 3, b)
        moved = torch.addcmul(bl[:, 0] * d[:, 0, None], bl[:, 1], d[:, 1, None]).addcmul(bl[:, 2], d[:, 2, None])
        moved = moved.transpose(1, 2).contiguous()  # (U, B, 3)
        vm = vertices.transpose(0, 1)  # (V, B, 3): the sparse product's own vertex-major storage
        if torch.is_grad_enabled() and (vertices.requires_grad or moved.requires_grad):
            return vm.index_add(0, self.union, moved).transpose(0, 1)
        return vm.index_add_(0, self.union, moved).transpose(0, 1)

    def state(self) -> dict:
        """Everything :meth:`from_state` needs (tensors and plain data)."""
        return {
            "inputs": self.inputs.cpu(),
            "vertices": [t.cpu() for t in self.vertex_ids.split(self.sizes.tolist())],
            "num_vertices": self.num_vertices,
            "hidden": self.hidden,
            "channels": self.channels,
            "size_ref": float(self.size_ref),
            "joint_names": list(self.joint_names),
            "bones": self.bones.tolist(),
            "params": {k: v.detach().cpu() for k, v in self.named_parameters()},
            "frozen": [self.needed[self._frozen].cpu(), self._frozen_value[self._frozen].cpu()],
            "meta": self.meta,
        }

    @classmethod
    def from_state(cls, state: dict) -> Correctives:
        """Rebuild from :meth:`state`."""
        model = cls(
            state["inputs"],
            list(state["vertices"]),
            int(state["num_vertices"]),
            hidden=int(state["hidden"]),
            channels=int(state["channels"]),
            size_ref=float(state["size_ref"]),
            joint_names=tuple(state["joint_names"]),
            bones=tuple(tuple(b) for b in state.get("bones", LIMB_BONES)),
            meta=state["meta"],
        )
        with torch.no_grad():
            for k, v in state["params"].items():
                getattr(model, k).copy_(v.float())
        if "frozen" in state:
            model.freeze(*state["frozen"])
        return model

    @classmethod
    def load(cls, path: str | Path | None = None, *, procedural: bool = False) -> Correctives:
        """Load weights (default: the shipped ones for the plain rig, or for the twist rig with ``procedural``).

        Raises:
            FileNotFoundError: ``path`` does not exist (the message names it).
        """
        path = default_weights_path(procedural) if path is None else Path(path)
        if not path.is_file():
            raise FileNotFoundError(
                f"correctives: weights file {str(path)!r} not found (expected a file written by "
                "scripts/train_correctives.py train)"
            )
        # Frozen: posing with them builds no autograd graph unless the pose or the identity needs one.
        return cls.from_state(torch.load(path, map_location="cpu", weights_only=True)).requires_grad_(False)
