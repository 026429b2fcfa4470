"""Linear blend skinning, v'_i = sum_k w_ik (R_k v_i + t_k) (paper 000 eq. 6).

``(R_k, t_k)`` is the skinning transform G_k T_k^-1 of joint k. The canonical mesh has at
most 14 and on average 3.4 influences per vertex, so the fast path never forms a dense
(V, J) product. It writes the skinning of one rest mesh as one sparse matrix
``X (V, 4J)`` with ``X[i, 4k + c] = w_ik [v_i; 1]_c``; posing B meshes of that identity is
then a single sparse-dense product ``X @ A`` with ``A (4J, 3B)`` the stacked transforms:
~nnz x 12 multiply-adds per mesh and no (V, B, 3, 4) intermediate. Gradients with respect
to both the rest vertices and the transforms come from an explicit backward.
``lbs_dense`` is the plain reference the tests compare against.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import nn

from .sparse import crow_indices as _crow
from .sparse import csr

__all__ = [
    "Skinning",
    "SkinLayout",
    "skin_layout",
    "register_skin_layout",
    "registered_skin_layout",
    "lbs_joint_major",
    "lbs_sparse",
    "skin_values",
    "lbs_dense",
]

# Sparse products run over chunks of 8 poses: the CPU product (MKL, torch 2.13) is fastest per
# column at 24 columns and 1.5x, then 6x slower per column past 26 and 32 (single thread:
# 28 us per column at 24, 36 at 30, 115 at 36).
_POSE_CHUNK = 8


@dataclass(frozen=True, slots=True, eq=False)
class Skinning:
    """Sparse skinning weights of a body, read-only: the public view solvers use.

    Influence e of N moves vertex ``vertex[e]`` with joint ``joint[e]`` by ``weight[e]``.
    Influences are sorted by vertex: those of vertex i are ``crow[i]:crow[i + 1]``.

    Attributes:
        vertex: (N,) int64 vertex ids, non-decreasing.
        joint: (N,) int64 joint ids (Root = 0 included in the numbering).
        weight: (N,) weights, the body's dtype; each vertex's weights sum to 1.
        crow: (V + 1,) int64 CSR row pointers of the (V, J) weight matrix.
        num_vertices: V.
        num_joints: J.
    """

    vertex: torch.Tensor
    joint: torch.Tensor
    weight: torch.Tensor
    crow: torch.Tensor
    num_vertices: int
    num_joints: int

    def matrix(self) -> torch.Tensor:
        """The (V, J) weights as a sparse CSR tensor."""
        return csr(self.crow, self.joint, self.weight, (self.num_vertices, self.num_joints))

    def dense(self) -> torch.Tensor:
        """The (V, J) weights as a dense tensor (zeros where a joint does not skin a vertex)."""
        out = self.weight.new_zeros(self.num_vertices, self.num_joints)
        return out.index_put_((self.vertex, self.joint), self.weight)


@dataclass(frozen=True, eq=False)
class SkinLayout:
    """Index structure of the skinning matrices, built once per rig (int64 tensors).

    Attributes:
        vertex, joint: (nnz,) vertex-sorted influences.
        x_crow, x_col: CSR structure of X (V, 4J).
        xt_crow, xt_col, xt_perm: CSR structure of X^T and the permutation of X's values.
        w_crow: CSR row pointers of the weights (V, J) (columns are ``joint``).
        num_vertices, num_joints: V, J.
    """

    vertex: torch.Tensor
    joint: torch.Tensor
    x_crow: torch.Tensor
    x_col: torch.Tensor
    xt_crow: torch.Tensor
    xt_col: torch.Tensor
    xt_perm: torch.Tensor
    w_crow: torch.Tensor
    num_vertices: int
    num_joints: int

    def to(self, device: torch.device) -> SkinLayout:
        fields = {k: getattr(self, k) for k in self.__dataclass_fields__}
        return SkinLayout(**{k: v.to(device) if isinstance(v, torch.Tensor) else v for k, v in fields.items()})


def skin_layout(vertex: torch.Tensor, joint: torch.Tensor, num_vertices: int, num_joints: int) -> SkinLayout:
    """Precompute the sparse structure for (vertex, joint) influences sorted by vertex."""
    if vertex.numel() and bool((vertex[1:] < vertex[:-1]).any()):
        raise ValueError("skin_vertex: expected influences sorted by vertex")
    four = torch.arange(4, device=vertex.device)
    x_row = vertex.repeat_interleave(4)
    x_col = (4 * joint[:, None] + four).reshape(-1)
    perm = torch.argsort(x_col * num_vertices + x_row)
    # X's indices in int32: the CPU sparse product (MKL) converts int64 ones on every call
    # (0.07 ms of a 0.3 ms batch-1 product); X has ~4 * 61k entries, far below 2^31.
    i32 = torch.int32
    return SkinLayout(
        vertex=vertex,
        joint=joint,
        x_crow=_crow(x_row, num_vertices).to(i32),
        x_col=x_col.to(i32),
        xt_crow=_crow(x_col, 4 * num_joints).to(i32),
        xt_col=x_row[perm].to(i32),
        xt_perm=perm,
        w_crow=_crow(vertex, num_vertices),
        num_vertices=num_vertices,
        num_joints=num_joints,
    )


_INDEX_FIELDS = ("vertex", "joint", "x_crow", "x_col", "xt_crow", "xt_col", "xt_perm", "w_crow")


def register_skin_layout(module: nn.Module, layout: SkinLayout) -> None:
    """Keep a layout on ``module`` as non-persistent buffers ``_skin_<field>`` (they follow ``.to()``)."""
    for k in _INDEX_FIELDS:
        module.register_buffer(f"_skin_{k}", getattr(layout, k), persistent=False)


def registered_skin_layout(module: nn.Module) -> SkinLayout:
    """The layout stored by :func:`register_skin_layout`, on the module's current device."""
    fields = {k: getattr(module, f"_skin_{k}") for k in _INDEX_FIELDS}
    # V and J from the row-pointer lengths: w_crow has V + 1 entries, xt_crow 4 J + 1.
    v, j = fields["w_crow"].numel() - 1, (fields["xt_crow"].numel() - 1) // 4
    return SkinLayout(**fields, num_vertices=v, num_joints=j)


def skin_values(rest: torch.Tensor, weight: torch.Tensor, layout: SkinLayout) -> torch.Tensor:
    """Values (..., 4 nnz) of X for rest meshes (..., V, 3): ``w_e [v_i; 1]`` per influence e.

    They depend on the rest mesh only, so a prepared identity keeps them and posing it again
    skips this gather (0.3-0.8 ms of a 2 ms batch-1 pose; ``benchmarks/forward.py --profile``).
    """
    w = weight[:, None].expand(*rest.shape[:-2], -1, 1)
    return torch.cat([rest.index_select(-2, layout.vertex) * w, w], dim=-1).flatten(-2)


def _chunk(device: torch.device) -> int:
    """Poses per sparse product: :data:`_POSE_CHUNK` on the CPU; all of them on a GPU (no such cliff there)."""
    return _POSE_CHUNK if device.type == "cpu" else 1 << 30


def _groups(n_rest: int, n_pose: int, chunk: int = _POSE_CHUNK) -> list[tuple[int, slice]]:
    """(rest index, pose slice) pairs: one rest shared by chunks, or one rest per pose."""
    if n_rest == 1:
        return [(0, slice(s, min(s + chunk, n_pose))) for s in range(0, n_pose, chunk)]
    return [(b, slice(b, b + 1)) for b in range(n_pose)]


def _blend_apply(rest: torch.Tensor, mats: torch.Tensor, weight: torch.Tensor, layout: SkinLayout) -> torch.Tensor:
    """LBS of one rest mesh per pose (B, V, 3) as blended transforms: (V, 3, B), batch innermost.

    ``W @ M`` (the (V, J) weights times the (J, 12 B) transforms, in 24-column products) gives
    every vertex its blended [R | t]; three fused multiply-adds apply it. No per-identity
    skinning matrix is built: 1.8x faster than one sparse product per identity at B = 32 on one
    core (22 vs 39 ms), their values alone being a gather of 4 x 61k entries per mesh. It is
    memory-bound: the blended transforms are 12 floats per vertex and pose.
    """
    v, j = layout.num_vertices, layout.num_joints
    b = mats.shape[3]
    w = csr(layout.w_crow.int(), layout.joint.int(), weight, (v, j))
    m = mats.reshape(j, 12 * b)
    blend = rest.new_empty(v, 12 * b) if rest.device.type == "cpu" else rest.new_zeros(v, 12 * b)
    step = 3 * _chunk(rest.device)
    for s in range(0, 12 * b, step):
        cols = blend[:, s : s + step]
        torch.addmm(cols, w, m[:, s : s + step], beta=0, out=cols)
    blend = blend.view(v, 4, 3, b)  # [vertex, column, row, pose]
    rt = rest.permute(1, 2, 0).contiguous()[:, :, None]  # (V, 3, 1, B)
    out = torch.addcmul(blend[:, 3], blend[:, 0], rt[:, 0])
    out = torch.addcmul(out, blend[:, 1], rt[:, 1])
    return torch.addcmul(out, blend[:, 2], rt[:, 2])


class _SparseSkin(torch.autograd.Function):
    """X @ A per pose chunk, A (4J, 3B) from joint-major ``mats`` (J, 4, 3, B)."""

    @staticmethod
    def forward(ctx, rest, mats, weight, layout, values):  # noqa: D102
        v, j = layout.num_vertices, layout.num_joints
        b = mats.shape[3]
        a = mats.transpose(2, 3).reshape(4 * j, 3 * b)
        # The products land in a vertex-major (V, B, 3) buffer; the result is its (B, V, 3)
        # view. Writing them pose-major instead costs a strided copy as long as the product
        # itself (0.39 vs 0.55 ms per chunk of 8). beta = 0 never reads the buffer (MKL), so
        # it starts empty on the CPU; zeroed elsewhere, where that is not promised.
        out = rest.new_empty(v, 3 * b) if rest.device.type == "cpu" else rest.new_zeros(v, 3 * b)
        ctx.save_for_backward(rest, mats, weight)
        ctx.layout = layout
        # Blend when no values are at hand and building them would not pay: one identity per
        # pose, or a single identity posed once or twice (0.56 vs 1.6 ms at B = 1, one core).
        if values is None and (rest.shape[0] > 1 or b <= 2):
            out.view(v, b, 3).copy_(_blend_apply(rest, mats, weight, layout).transpose(1, 2))
            return out.view(v, b, 3).transpose(0, 1)
        x = None
        for r, sl in _groups(rest.shape[0], b, _chunk(rest.device)):
            if x is None or rest.shape[0] > 1:
                vals = skin_values(rest[r], weight, layout) if values is None else values[r]
                x = csr(layout.x_crow, layout.x_col, vals, (v, 4 * j))
            cols = out[:, 3 * sl.start : 3 * sl.stop]
            torch.addmm(cols, x, a[:, 3 * sl.start : 3 * sl.stop], beta=0, out=cols)
        return out.view(v, b, 3).transpose(0, 1)

    @staticmethod
    def backward(ctx, grad):  # noqa: D102
        rest, mats, weight = ctx.saved_tensors
        layout: SkinLayout = ctx.layout
        v, j = layout.num_vertices, layout.num_joints
        b = mats.shape[3]
        grad_rest = grad_mats = None
        if ctx.needs_input_grad[1]:
            grad_vm = grad.transpose(0, 1).reshape(v, 3 * b)  # vertex-major, as the forward's buffer
            grad_a = grad.new_empty(4 * j, 3 * b)
            for r, sl in _groups(rest.shape[0], b, _chunk(rest.device)):
                vals = skin_values(rest[r], weight, layout)[layout.xt_perm]
                xt = csr(layout.xt_crow, layout.xt_col, vals, (4 * j, v))
                grad_a[:, 3 * sl.start : 3 * sl.stop] = xt @ grad_vm[:, 3 * sl.start : 3 * sl.stop]
            grad_mats = grad_a.view(j, 4, b, 3).transpose(2, 3)
        if ctx.needs_input_grad[0]:
            # d v'_i / d v_i = sum_k w_ik R_k: blend the rotations with the sparse weights.
            w = csr(layout.w_crow, layout.joint, weight, (v, j))
            rot = mats[:, :3].transpose(2, 3).reshape(j, 9 * b)
            blended = (w @ rot).view(v, 3, b, 3)  # [v, col, b, row]
            per_pose = torch.einsum("vcbr,bvr->bvc", blended, grad)
            grad_rest = per_pose.sum(0, keepdim=True) if rest.shape[0] == 1 else per_pose
        return grad_rest, grad_mats, None, None, None


def lbs_joint_major(
    rest: torch.Tensor,
    mats: torch.Tensor,
    weight: torch.Tensor,
    layout: SkinLayout,
    values: torch.Tensor | None = None,
) -> torch.Tensor:
    """:func:`lbs_sparse` with joint-major transforms (J, 4, 3, B) (``geometry.kinematics``)."""
    return _SparseSkin.apply(rest, mats, weight, layout, values)


def lbs_sparse(
    rest: torch.Tensor,
    mats: torch.Tensor,
    weight: torch.Tensor,
    layout: SkinLayout,
    values: torch.Tensor | None = None,
) -> torch.Tensor:
    """Skin rest meshes with sparse weights.

    Args:
        rest: (1, V, 3) or (B, V, 3) rest vertices (one identity broadcasts over B poses).
        mats: (B, J, 3, 4) skinning transforms [R_k | t_k] = G_k T_k^-1.
        weight: (nnz,) influence weights in ``layout`` order, same dtype as ``rest``.
        layout: the sparse structure from :func:`skin_layout`.
        values: ``skin_values(rest, weight, layout)`` computed earlier, or None to compute
            them here. Gradients reach ``rest`` either way (through the explicit backward),
            so they must be exactly those values.

    Returns:
        (B, V, 3) skinned vertices.
    """
    return lbs_joint_major(rest, mats.permute(1, 3, 2, 0), weight, layout, values)


def lbs_dense(rest: torch.Tensor, mats: torch.Tensor, weights: torch.Tensor) -> torch.Tensor:
    """Reference LBS with dense weights (V, J): blend the transforms, then apply them."""
    blended = torch.einsum("vk,bkij->bvij", weights, mats)
    return (blended[..., :3] @ rest[..., None]).squeeze(-1) + blended[..., 3]
