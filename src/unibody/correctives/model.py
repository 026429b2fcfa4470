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
length) over the training mean: one set of displacements serves children and adults. A model
built with ``shape`` also feeds every activation the identity's build (:meth:`Correctives.shape_features`:
each limb segment's girth over its length, and the size), so the displacements follow the
body, not only the pose (as STAR's shape-dependent pose correctives do); the rest-pass
``relu(W2_k relu(W1_k [0, shape] + b1_k) + b2_k)`` is then per identity, and ``f`` is still 0 at rest. The masks
are the teacher's joint regions (:func:`~.teacher.teacher_region`); the active joints are
the shoulders, elbows, wrists, hips, knees and ankles.
"""

from __future__ import annotations

import weakref
from importlib import resources
from pathlib import Path

import torch
from torch import nn

from ..geometry.rotations import matrix_to_rot6d
from ..geometry.sparse import csr
from ..io.weights import read_weights, rebuilding

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


def _slot_order(
    inverse: torch.Tensor, blocks: list[tuple[int, int]], u: int
) -> tuple[torch.Tensor, list[tuple[int, int]] | None]:
    """An order of the union (U,) in which every mask is one run, and each mask's run (start, end).

    ``inverse``: the union position of each mask row; ``blocks``: each mask's rows. Masks that
    share vertices form groups (a limb's shoulder, elbow and wrist masks; the two hips'); inside
    a group, vertices are ordered by the first and then the last mask they belong to, which
    makes every mask a run when the masks of a group overlap like links of a chain (each vertex
    in consecutive masks), as the teacher's joint regions do. Otherwise runs is None and the
    order is the sorted union.
    """
    from scipy.sparse import csr_matrix
    from scipy.sparse.csgraph import connected_components

    a = len(blocks)
    member = torch.zeros(u, a, dtype=torch.bool)
    for k, (s, e) in enumerate(blocks):
        member[inverse[s:e], k] = True
    shared = (member.T.float() @ member.float()).numpy() > 0  # (A, A): masks sharing a vertex
    group = torch.from_numpy(connected_components(csr_matrix(shared), directed=False)[1]).long()
    ids = torch.arange(a)
    first = torch.where(member, ids, a).amin(1)
    last = torch.where(member, ids, -1).amax(1)
    order = torch.argsort((group[first] * a + first) * a + last, stable=True)
    slot = torch.empty_like(order)
    slot[order] = torch.arange(u)
    runs = []
    for s, e in blocks:
        if e == s:
            runs.append((0, 0))
            continue
        where = slot[inverse[s:e]]
        lo, hi = int(where.min()), int(where.max())
        if hi - lo + 1 != e - s:  # not one run (or a vertex twice in a mask)
            return torch.arange(u), None
        runs.append((lo, hi + 1))
    return order, runs


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
        shape: the identity inputs (see :meth:`shape_features`), or None for a pose-only model:
            ``{"joints": (S, 2) (joint, child) ids of the limb segments, "vertices": per segment
            its (n_s,) vertex ids, "mean", "std": (S + 1,) the training identities' feature
            statistics}``.
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
        shape: dict | None = None,
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
        self.num_shape = 0  # identity inputs per activation (0: a pose-only model)
        if shape is not None:
            segs = [torch.as_tensor(v, dtype=torch.int64) for v in shape["vertices"]]
            counts = torch.tensor([len(v) for v in segs])
            self.register_buffer("_shape_joints", torch.as_tensor(shape["joints"], dtype=torch.int64).view(-1, 2))
            self.register_buffer("_shape_vertex", torch.cat(segs))
            self.register_buffer("_shape_segment", torch.repeat_interleave(torch.arange(len(segs)), counts))
            self.register_buffer("_shape_count", counts.float())
            self.register_buffer("shape_mean", torch.as_tensor(shape["mean"], dtype=torch.float32).flatten())
            self.register_buffer("shape_std", torch.as_tensor(shape["std"], dtype=torch.float32).flatten())
            self.num_shape = len(segs) + 1
            if self.shape_mean.shape != (self.num_shape,) or self.shape_std.shape != (self.num_shape,):
                raise ValueError(f"shape: mean and std must have {self.num_shape} entries (segments + size)")
        f = self.num_shape
        gen = torch.Generator().manual_seed(0)
        self.w1 = nn.Parameter(torch.randn(a, hidden, i * 6 + f, generator=gen) / (i * 6 + f) ** 0.5)
        self.b1 = nn.Parameter(torch.zeros(a, hidden))
        self.w2 = nn.Parameter(torch.randn(a, channels, hidden, generator=gen) / hidden**0.5)
        self.b2 = nn.Parameter(torch.zeros(a, channels))
        # [(mask vertex, xyz), c], the active joints' masks stacked: joint k's rows 3 start_k .. 3 end_k.
        self.decode = nn.Parameter(torch.zeros(int(sizes.sum()) * 3, channels))
        # The union of the masks, sorted: where f may be non-zero.
        union, inverse = torch.unique(self.vertex_ids, return_inverse=True)
        self.register_buffer("union", union)
        # Posing decodes into "slots", the union in an order where each mask is one run of slots
        # (when the masks allow it: the shipped ones do), vertex-major with xyz inside: each
        # active joint's product then adds straight into its run, with no gather of the masks'
        # rows nor scatter of the vertices in two or three masks: the correctives' own time fell
        # to 0.78-0.87 of the gather's (benchmarks/correctives_ab.py, one core). Each mask's rows
        # are reordered by slot.
        order, self._runs = _slot_order(inverse, self._blocks, len(union))
        slot = torch.empty_like(order)
        slot[order] = torch.arange(len(order))
        self.register_buffer("_slot", slot, persistent=False)  # union position -> slot
        self.register_buffer("_slot_vertex", union[order], persistent=False)  # slot -> vertex
        v_slot = slot[inverse]
        perm = torch.cat([s + torch.argsort(v_slot[s:e]) for s, e in self._blocks])
        xyz = torch.arange(3)
        self.register_buffer("_decode_rows", (3 * perm[:, None] + xyz).flatten(), persistent=False)
        self.register_buffer("_decode_place", (3 * v_slot[perm][:, None] + xyz).flatten(), persistent=False)

    def size_of(self, rest_joints: torch.Tensor) -> torch.Tensor:
        """(Bi,) the identities' sizes (m): mean length of :attr:`bones` in rest joints (Bi, J, 3)."""
        return size_of(rest_joints, self.bones)

    @property
    def num_active(self) -> int:
        return self.inputs.shape[0]

    def shape_features(self, rest_vertices: torch.Tensor, rest_joints: torch.Tensor) -> torch.Tensor | None:
        """(Bi, S + 1) the identity inputs of a model built with ``shape``; None for a pose-only model.

        Per limb segment, the log of its girth over its length: the mean distance of its vertices
        to the bone's line through the rest joints, over the bone's length (the same for a body
        scaled as a whole); then the log of the size over :attr:`size_ref`. Each is standardised
        with the training identities' mean and std. Differentiable in both arguments.

        Args:
            rest_vertices: (Bi, V, 3) m; rest_joints: (Bi, J, 3) m (a prepared identity's).
        """
        if not self.num_shape:
            return None
        pairs, seg = self._shape_joints, self._shape_segment
        # index_select, not advanced indexing: 0.15 vs 0.68 ms per call at Bi = 1 (one core)
        ends = rest_joints.index_select(1, pairs.flatten()).view(-1, len(pairs), 2, 3)
        start, axis = ends[:, :, 0], ends[:, :, 1] - ends[:, :, 0]  # (Bi, S, 3)
        rel = rest_vertices.index_select(1, self._shape_vertex) - start.index_select(1, seg)
        ax = axis.index_select(1, seg)
        along = (rel * ax).sum(-1, keepdim=True) / ax.square().sum(-1, keepdim=True)
        dist = (rel - along * ax).norm(dim=-1)  # (Bi, n) to the bone's line
        girth = dist.new_zeros(dist.shape[0], len(pairs)).index_add_(1, seg, dist) / self._shape_count.to(dist)
        size = self.size_of(rest_joints) / self.size_ref.to(dist)
        feats = torch.cat([torch.log(girth / axis.norm(dim=-1)), torch.log(size)[:, None]], 1)
        return (feats - self.shape_mean.to(feats)) / self.shape_std.to(feats)

    def shape_inputs(self, rest_vertices: torch.Tensor, rest_joints: torch.Tensor) -> torch.Tensor | None:
        """:meth:`shape_features`, kept for the next call with the same rest tensors (the same
        objects, unchanged since, needing no gradient): posing one prepared identity again skips
        them (0.35 of a 2.7 ms batch-1 pose on one core). A weak reference: never another tensor's."""
        if not self.num_shape:
            return None
        live = (rest_vertices, rest_joints, self.shape_mean, self.shape_std)
        if torch.is_grad_enabled() and (rest_vertices.requires_grad or rest_joints.requires_grad):
            return self._finite(self.shape_features(rest_vertices, rest_joints))
        versions = tuple(t._version for t in live)
        cached = getattr(self, "_shape_cache", None)
        if cached is not None and cached[0]() is rest_vertices and cached[1]() is rest_joints and cached[2] == versions:
            return cached[3]
        with torch.no_grad():
            feats = self._finite(self.shape_features(rest_vertices, rest_joints))
        self._shape_cache = (weakref.ref(rest_vertices), weakref.ref(rest_joints), versions, feats)
        return feats

    @staticmethod
    def _finite(feats: torch.Tensor) -> torch.Tensor:
        """``feats``, or ValueError where a degenerate rest mesh made them non-finite (the posed
        displacements would be NaN, which the layer's output bound does not see)."""
        if not bool(torch.isfinite(feats.detach()).all()):
            bad = int(torch.nonzero(~torch.isfinite(feats.detach()).all(1))[0])
            raise ValueError(
                f"prepared: identity {bad} gives non-finite correctives shape inputs (a limb bone of zero "
                "length, or a limb segment with no girth); expected a rest mesh with real limbs"
            )
        return feats

    def _shape_of(self, shape: torch.Tensor | None) -> torch.Tensor | None:
        if self.num_shape and shape is None:
            raise ValueError(
                "shape: this correctives model reads the identity's build; pass "
                "shape=model.shape_features(rest_vertices, rest_joints)"
            )
        if self.num_shape and (shape.ndim != 2 or shape.shape[1] != self.num_shape):
            raise ValueError(f"shape: expected (B or 1, {self.num_shape}) shape features, got {tuple(shape.shape)}")
        return shape if self.num_shape else None

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

    def _mlp(self, x6: torch.Tensor, shape: torch.Tensor | None = None) -> torch.Tensor:
        x6 = torch.where(self._frozen[:, None], self._frozen_value.to(x6.dtype), x6)
        x6 = torch.cat([x6, x6.new_zeros(x6.shape[0], 1, 6)], 1)  # + the padding's zero row
        x = x6[:, self._input_slot].flatten(-2)  # (B, A, I*6)
        if shape is not None:  # every activation also reads the identity's build (B or 1 rows)
            x = torch.cat([x, shape.to(x.dtype)[:, None].expand(x.shape[0], x.shape[1], -1)], -1)
        x = x.transpose(0, 1)  # (A, B, I*6 [+ S + 1])
        w1, b1, w2, b2 = (p.to(x6.dtype) for p in (self.w1, self.b1, self.w2, self.b2))
        h = torch.baddbmm(b1[:, None], x, w1.transpose(1, 2)).relu()
        return torch.baddbmm(b2[:, None], h, w2.transpose(1, 2)).relu().transpose(0, 1)  # (B, A, C)

    def activations(self, x6: torch.Tensor, shape: torch.Tensor | None = None) -> torch.Tensor:
        """(B, A, C) activations of :meth:`features` (B, N, 6); exactly 0 where they are 0 (the rest pose).

        Args:
            shape: (B or 1, S + 1) :meth:`shape_features`, for a model built with ``shape``.
        """
        shape = self._shape_of(shape)
        if shape is not None:  # the rest pass is per identity (1 or B rows), in the same products
            b, bi = x6.shape[0], shape.shape[0]
            rows = torch.cat([x6, x6.new_zeros(bi, *x6.shape[1:])])
            both = self._mlp(rows, torch.cat([shape.expand(b, -1), shape]))
            return both[:b] - both[b:]
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

    def _slot_decode(self, dtype: torch.dtype) -> torch.Tensor:
        """:attr:`decode` with each mask's rows in slot order; kept between calls while it needs
        no gradient and has not changed."""
        if torch.is_grad_enabled() and self.decode.requires_grad:
            return self.decode.to(dtype)[self._decode_rows]
        key = (dtype, self.decode.device, self.decode.data_ptr(), self.decode._version)
        cached = getattr(self, "_decode_cache", None)
        if cached is None or cached[0] != key:
            with torch.no_grad():
                cached = self._decode_cache = (key, self.decode.to(dtype)[self._decode_rows])
        return cached[1]

    def slot_displacements(
        self, x6: torch.Tensor, scale: torch.Tensor, shape: torch.Tensor | None = None
    ) -> torch.Tensor:
        """(U, 3, B) rest-space displacements (m) of the union's vertices in slot order
        (``union[order]``, see :meth:`union_displacements` for the sorted order), from :meth:`features`.

        Args:
            x6: (B, N, 6) features; scale: (B,) or (1,) identity size / :attr:`size_ref`;
            shape: (B or 1, S + 1) :meth:`shape_features` (a model built with ``shape``).
        """
        act = self.activations(x6, shape) * scale.to(x6.dtype).view(-1, 1, 1)  # (B, A, C)
        b, u = act.shape[0], len(self.union)
        at = act.permute(1, 2, 0)  # (A, C, B)
        dec = self._slot_decode(x6.dtype)
        # One small product per active joint, over its own mask: (3 V_k, 24) @ (24, B).
        if self._runs is None or (torch.is_grad_enabled() and (act.requires_grad or dec.requires_grad)):
            per_mask = torch.cat([dec[3 * s : 3 * e] @ at[k] for k, (s, e) in enumerate(self._blocks)])
            return per_mask.new_zeros(3 * u, b).index_add(0, self._decode_place, per_mask).view(u, 3, b)
        d = dec.new_zeros(3 * u, b)
        for k, ((s, e), (r, _)) in enumerate(zip(self._blocks, self._runs, strict=True)):
            d[3 * r : 3 * (r + e - s)].addmm_(dec[3 * s : 3 * e], at[k])
        return d.view(u, 3, b)

    def union_displacements(
        self, rel: torch.Tensor, size: torch.Tensor, shape: torch.Tensor | None = None
    ) -> torch.Tensor:
        """(B, U, 3) rest-space displacements (m) on :attr:`union` vertices.

        Args:
            rel: (B, 77, 3, 3) local rotations (joints 1..77) relative to the identity's rest pose.
            size: (B,) or (1,) the identities' mean limb bone lengths (m).
            shape: (B or 1, S + 1) :meth:`shape_features` (a model built with ``shape``).
        """
        x6 = self.features(rel[:, self.needed - 1])
        return self.slot_displacements(x6, size / self.size_ref, shape).index_select(0, self._slot).permute(2, 0, 1)

    def forward(self, rel: torch.Tensor, size: torch.Tensor, shape: torch.Tensor | None = None) -> torch.Tensor:
        """(B, V, 3) rest-space displacements on the whole topology (zero off :attr:`union`).

        Args:
            rel: (B, 77, 3, 3) local rotations (joints 1..77) relative to the identity's rest pose.
            size: (B,) or (1,) the identities' mean limb bone lengths (m).
            shape: (B or 1, S + 1) :meth:`shape_features` (a model built with ``shape``).
        """
        d = self.union_displacements(rel, size, shape)
        return d.new_zeros(d.shape[0], self.num_vertices, 3).index_copy(1, self.union, d)

    def world_relative(self, world: torch.Tensor, rest_rotations: torch.Tensor, parents: torch.Tensor) -> torch.Tensor:
        """(B, N, 3, 3) the :attr:`needed` joints' rest-relative local rotations, from posed world transforms.

        Args:
            world: (B, J, 4, 4) posed world transforms; rest_rotations: (Bi, J, 3, 3); parents: (J,).
        """
        n = self.needed
        rr = rest_rotations[..., :3, :3]
        left = rr[:, n].transpose(-1, -2) @ rr[:, parents[n]]  # rest local^T, (Bi, N, 3, 3)
        both = world[..., :3, :3].index_select(1, torch.cat([parents[n], n]))
        return left @ (both[:, : len(n)].transpose(-1, -2) @ both[:, len(n) :])

    def posed(
        self,
        vertices: torch.Tensor,
        rel: torch.Tensor,
        mats: torch.Tensor,
        size: torch.Tensor,
        binding: dict,
        shape: torch.Tensor | None = None,
    ) -> torch.Tensor:
        """LBS vertices (B, V, 3) plus the skinned correctives of the pose that gave them.

        Args:
            vertices: (B, V, 3) LBS of the rest meshes, a view of vertex-major (V, B, 3) storage
                (a fresh tensor: updated in place when no gradient is needed).
            rel: (B, N, 3, 3) the :attr:`needed` joints' rest-relative local rotations
                (:meth:`world_relative`, or :meth:`rest_relative` of them).
            mats: (J, 4, 3, B) joint-major skinning transforms of the rig that skinned
                ``vertices`` (``geometry.kinematics``); size: (Bi,) identity sizes (:func:`size_of`);
            binding: :meth:`skin_binding` of that rig's skinning;
            shape: (Bi, S + 1) :meth:`shape_features` (a model built with ``shape``).
        """
        d = self.slot_displacements(self.features(rel), size / self.size_ref, shape)
        return self.apply(vertices, mats, d, binding)

    def skin_binding(self, skinning) -> dict[str, torch.Tensor]:  # noqa: ANN001 (a geometry.skinning.Skinning)
        """The skinning weights of the :attr:`union` rows in slot order, to skin displacements by :meth:`apply`.

        Only the joints that skin those rows are kept (Jd of the rig's), as a CSR (U, Jd) matrix:
        ``{"crow", "col", "val", "joints"}``. The layer keeps it (one model may serve a plain and
        a procedural-twist layer, whose skinning differs).
        """
        dense = skinning.dense()[self._slot_vertex.to(skinning.weight.device)]
        joints = torch.nonzero(dense.abs().amax(0) > 0).flatten()
        w = dense[:, joints].to_sparse_csr()
        return {"crow": w.crow_indices().int(), "col": w.col_indices().int(), "val": w.values(), "joints": joints}

    @staticmethod
    def rest_relative(
        local: torch.Tensor, rest_rotations: torch.Tensor, parents: torch.Tensor, joints: torch.Tensor | None = None
    ) -> torch.Tensor:
        """(B, N, 3, 3) local rotations relative to the rest pose, ``R_rest,loc^T R_loc``.

        Args:
            local: (B, J, 3, 3) absolute local rotations, Root first (row 0 is not used).
            rest_rotations: (Bi, J, 3, 3) fitted rest world rotations; parents: (J,) (Root's 0).
            joints: (N,) the joints wanted (default 1..77, N = 77), e.g. :attr:`needed`.
        """
        joints = torch.arange(1, local.shape[1], device=local.device) if joints is None else joints
        rest_local = rest_rotations[:, parents[joints]].transpose(-1, -2) @ rest_rotations[:, joints]
        return rest_local.transpose(-1, -2) @ local.index_select(1, joints)

    def apply(self, vertices: torch.Tensor, mats: torch.Tensor, d: torch.Tensor, binding: dict) -> torch.Tensor:
        """LBS of the rest mesh plus the skinned displacements: ``LBS(v + d) = LBS(v) + (sum_k w_k R_k) d``.

        Args:
            vertices: (B, V, 3) LBS of the rest meshes (a fresh tensor: updated in place when no
                gradient is needed).
            mats: (J, 4, 3, B) joint-major skinning transforms (``geometry.kinematics``).
            d: (U, 3, B) rest-space displacements of the union in slot order (:meth:`slot_displacements`).
            binding: :meth:`skin_binding` of the skinning ``mats`` belong to.
        """
        u, b = len(self.union), mats.shape[3]
        joints = binding["joints"]
        jd = len(joints)
        rot = mats.index_select(0, joints)[:, :3].reshape(jd, 9, b)  # [joint, (column, row), pose]
        w = csr(binding["crow"], binding["col"], binding["val"].to(mats.dtype), (u, jd))
        if torch.is_grad_enabled() and (rot.requires_grad or w.requires_grad):
            bl = (w @ rot.view(jd, 9 * b)).view(u, 3, 3, b).permute(1, 2, 0, 3)
        elif b == 1:  # one product: 0.25 vs 0.5 ms for the planes below (one core)
            blend = torch.addmm(self._empty(rot, u, 9), w, rot.view(jd, 9), beta=0)
            bl = blend.view(u, 3, 3, 1).permute(1, 2, 0, 3)
        else:
            # One plane per rotation entry: the blended rotations come out as (9, U, B), and every
            # product below runs over U B contiguous values (the vertex-major (U, 3, 3, B) blend
            # took 2.4 vs 1.7 ms for this function at B = 32 on one core, 0.8 vs 0.6 ms at B = 2).
            rot = rot.transpose(0, 1).contiguous()
            blend = self._empty(rot, 9, u, b)
            step = 32 if rot.device.type == "cpu" else b  # no such cliff on a GPU (geometry.skinning)
            for i in range(9):
                for s in range(0, b, step):
                    out = blend[i, :, s : s + step]
                    torch.addmm(out, w, rot[i, :, s : s + step], beta=0, out=out)
            bl = blend.view(3, 3, u, b)  # [column, row, vertex, pose]
        vm = vertices.transpose(0, 1)  # (V, B, 3): the sparse product's own vertex-major storage
        dx, dy, dz = d.unbind(1)  # (U, B) each
        if torch.is_grad_enabled() and (vertices.requires_grad or bl.requires_grad or d.requires_grad):
            moved = torch.addcmul(bl[0] * dx, bl[1], dy).addcmul(bl[2], dz)  # (row, U, B)
            return vm.index_add(0, self._slot_vertex, moved.permute(1, 2, 0)).transpose(0, 1)
        moved = (bl[0] * dx).addcmul_(bl[1], dy).addcmul_(bl[2], dz)  # in place: no temporaries
        return vm.index_add_(0, self._slot_vertex, moved.permute(1, 2, 0).contiguous()).transpose(0, 1)

    @staticmethod
    def _empty(like: torch.Tensor, *shape: int) -> torch.Tensor:
        """An output buffer for ``addmm(..., beta=0)``: left empty on the CPU, where MKL never reads
        it; zeroed elsewhere, where that is not promised (as ``geometry.skinning`` does)."""
        return like.new_empty(shape) if like.device.type == "cpu" else like.new_zeros(shape)

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
            "shape": None
            if not self.num_shape
            else {
                "joints": self._shape_joints.cpu(),
                "vertices": [t.cpu() for t in self._shape_vertex.split(self._shape_count.long().tolist())],
                "mean": self.shape_mean.cpu(),
                "std": self.shape_std.cpu(),
            },
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
            shape=state.get("shape"),
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
            ValueError: ``path`` is no such file (other bytes, missing or malformed entries,
                NaN/inf weights); the message names it.
        """
        path = default_weights_path(procedural) if path is None else Path(path)
        if not path.is_file():
            raise FileNotFoundError(
                f"correctives: weights file {str(path)!r} not found (expected a file written by "
                "scripts/train_correctives.py train)"
            )
        what = "correctives weights written by scripts/train_correctives.py"
        state = read_weights(path, what)
        with rebuilding(path, what):
            model = cls.from_state(state)
        # Frozen: posing with them builds no autograd graph unless the pose or the identity needs one.
        return model.requires_grad_(False)
