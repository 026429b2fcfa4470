"""The expanded rig of a procedural definition, and its collapse back to the public rig.

Expansion (paper 001): the public joints keep their indices; the twist joints follow in
segment order, each a leaf child of its segment's ``start`` joint. A twist joint sits on the
bone at the position its ``translation`` row gives, ``p_k = sum_j T[k, j] p_j``, and its bind
frame is the start joint's turned by the shortest arc ``A_k`` that lays its source axis
exactly along the bone (a no-op when the start joint's axis already follows the bone).

Skinning weights are split here, not stored in the sidecar: the start joint's weight column
is divided along the bone by linear hat functions over the nodes {start joint, twist
joints}. A twist joint's node is its bone parameter ``t_k`` (its translation weight on the
end joint); the start joint's node is where its twist value vanishes, ``t = 0`` for a forward
segment and ``t = 1`` for a reverse-compensation one. A vertex's bone parameter is the
projection of its bind position on the bone, clamped to the nodes' range. Each piece of a
weight is split in two that sum to it, so the partition of unity holds and the collapse
(removed joints' columns added to their nearest kept ancestor) gives the public weights back.
"""

from __future__ import annotations

import torch

from ..geometry.rotations import shortest_arc
from ..rig import KinematicTree, Rig
from .format import AXES, ProceduralDefinition, ProceduralFormatError

__all__ = ["expand_rig", "collapse_rig", "segment_alignment", "translation_matrix"]


def translation_matrix(definition: ProceduralDefinition, dtype: torch.dtype = torch.float64) -> torch.Tensor:
    """(K, J) dense ``T``: twist joint rest position = ``T @ public rest joint positions``."""
    names = definition.main_joint_names
    col = {n: i for i, n in enumerate(names)}
    row = {n: i for i, n in enumerate(definition.twist_joints)}
    m = definition.translation
    t = torch.zeros(len(row), len(col), dtype=dtype)
    t[[row[r] for r in m.rows], [col[c] for c in m.columns]] = torch.tensor(m.values, dtype=dtype)
    return t


def segment_alignment(rest_rot: torch.Tensor, rest_pos: torch.Tensor, start, end, axis) -> torch.Tensor:
    """Shortest arcs ``A_k`` (..., K, 3, 3) carrying each source axis onto ``+-`` the bone (start frame).

    Args:
        rest_rot: (..., J, 3, 3) rest world rotations; rest_pos: (..., J, 3) rest positions.
        start, end, axis: (K,) long tensors, the segment joints and source axis of each twist joint.
    """
    bone = rest_rot[..., start, :, :].transpose(-1, -2) @ (rest_pos[..., end, :] - rest_pos[..., start, :])[..., None]
    bone = bone.squeeze(-1)
    e = torch.nn.functional.one_hot(axis, 3).to(bone.dtype)
    side = torch.where((bone * e).sum(-1, keepdim=True) < 0, -1.0, 1.0).to(bone.dtype)
    return shortest_arc(e.expand_as(bone), side * bone)


def _segment_tables(definition: ProceduralDefinition, rig: Rig):
    """Per twist joint: (start, end, axis) index lists and bone parameter; validated against the rig."""
    names = rig.joint_names
    if tuple(definition.main_joint_names) != tuple(names):
        raise ProceduralFormatError(
            "public_rig_derivation.main_joint_names",
            f"expected the {len(names)} joint names of the rig in its order, got {len(definition.main_joint_names)}"
            " names that differ",
        )
    idx = {n: i for i, n in enumerate(names)}
    pos = rig.bind_transforms[:, :3, 3]
    trans = translation_matrix(definition)
    starts: dict[int, str] = {}
    start, end, axis, t_of = [], [], [], []
    for s, seg in enumerate(definition.segments):
        a, b = idx[seg.start], idx[seg.end]
        path = f"segments[{s}]"
        if a in starts:
            raise ProceduralFormatError(f"{path}.start", f"joint {seg.start!r} already starts segment {starts[a]!r}")
        starts[a] = seg.name
        j = b
        while j > a:
            j = rig.tree.parents[j]
        if j != a:
            raise ProceduralFormatError(f"{path}.end", f"{seg.end!r} is not a descendant of start {seg.start!r}")
        if float((pos[b] - pos[a]).norm()) < 1e-6:
            raise ProceduralFormatError(
                path, f"degenerate segment: {seg.start!r} and {seg.end!r} coincide in the bind pose"
            )
        k0 = len(start)
        for _ in seg.twist_joints:
            start.append(a), end.append(b), axis.append(AXES.index(seg.source_axis))
        t_seg = trans[k0 : len(start), b].tolist()
        nodes = [*t_seg, 1.0 if seg.reverse_compensation else 0.0]
        if len(set(nodes)) != len(nodes):
            raise ProceduralFormatError(
                f"{path}.twist_joints",
                f"degenerate segment: twist joints of {seg.name!r} share a bone position (t = {t_seg})",
            )
        t_of.extend(t_seg)
    return [torch.tensor(x) for x in (start, end, axis)], torch.tensor(t_of, dtype=torch.float64)


def _split_weights(rig: Rig, definition: ProceduralDefinition, start, t_of) -> tuple[torch.Tensor, ...]:
    """Skinning triplets of the expanded rig, vertex-sorted."""
    num = rig.num_joints
    sv, sj, sw = rig.skin_vertex, rig.skin_joint, rig.skin_weight
    pos = rig.bind_transforms[:, :3, 3]
    keep = torch.ones_like(sv, dtype=torch.bool)
    parts_v, parts_j, parts_w = [sv], [sj], [sw]
    k0 = 0
    for seg in definition.segments:
        k = len(seg.twist_joints)
        a = int(start[k0])
        nodes_t = torch.cat([t_of[k0 : k0 + k], t_of.new_tensor([1.0 if seg.reverse_compensation else 0.0])])
        nodes_j = torch.cat([torch.arange(num + k0, num + k0 + k), torch.tensor([a])])
        nodes_t, order = nodes_t.sort()
        nodes_j = nodes_j[order]
        sel = sj == a
        keep &= ~sel
        bone = pos[rig.joint_names.index(seg.end)] - pos[a]
        t = ((rig.bind_vertices[sv[sel]] - pos[a]) @ bone) / (bone @ bone)
        t = t.clamp(float(nodes_t[0]), float(nodes_t[-1]))
        i = (torch.bucketize(t, nodes_t, right=True) - 1).clamp(0, len(nodes_t) - 2)
        lam = (t - nodes_t[i]) / (nodes_t[i + 1] - nodes_t[i])
        w = sw[sel]
        lo = w * (1 - lam)
        parts_v += [sv[sel], sv[sel]]
        parts_j += [nodes_j[i], nodes_j[i + 1]]
        parts_w += [lo, w - lo]
        k0 += k
    parts_w[0] = torch.where(keep, sw, 0.0)
    v, j, w = torch.cat(parts_v), torch.cat(parts_j), torch.cat(parts_w)
    nz = w > 0
    v, j, w = v[nz], j[nz], w[nz]
    order = torch.argsort(v * (num + k0) + j)
    return v[order], j[order], w[order]


def expand_rig(rig: Rig, definition: ProceduralDefinition) -> Rig:
    """The rig with the definition's twist joints appended (see the module docstring).

    Raises:
        ProceduralFormatError: the definition does not fit the rig (other main joints, a joint
            starting two segments, an end joint outside the start joint's subtree, a bone of
            zero length, twist joints sharing a bone position).
    """
    (start, end, axis), t_of = _segment_tables(definition, rig)
    num, k = rig.num_joints, len(start)
    bind_r, bind_p = rig.bind_transforms[:, :3, :3], rig.bind_transforms[:, :3, 3]
    align = segment_alignment(bind_r, bind_p, start, end, axis)
    trans = translation_matrix(definition)
    tw = torch.eye(4, dtype=bind_r.dtype).repeat(k, 1, 1)
    tw[:, :3, :3] = bind_r[start] @ align
    tw[:, :3, 3] = trans @ bind_p
    # RBF rows of a twist joint: the same combination of its start and end rows.
    rj, rv, rw = rig.rbf_joint, rig.rbf_vertex, rig.rbf_weight
    tk, tj = trans.nonzero(as_tuple=True)
    hit = rj[None, :] == tj[:, None]
    pair, entry = hit.nonzero(as_tuple=True)
    new_j = torch.cat([rj, num + tk[pair]])
    new_v = torch.cat([rv, rv[entry]])
    new_w = torch.cat([rw, trans[tk[pair], tj[pair]] * rw[entry]])
    order = torch.argsort(new_j * rig.num_vertices + new_v, stable=True)
    sv, sj, sw = _split_weights(rig, definition, start, t_of)
    return Rig(
        joint_names=(*rig.joint_names, *definition.twist_joints),
        tree=KinematicTree((*rig.tree.parents, *start.tolist())),
        bind_vertices=rig.bind_vertices,
        faces=rig.faces,
        skin_vertex=sv,
        skin_joint=sj,
        skin_weight=sw,
        rbf_joint=new_j[order],
        rbf_vertex=new_v[order],
        rbf_weight=new_w[order],
        bind_transforms=torch.cat([rig.bind_transforms, tw]),
        tpose_orient=torch.cat([rig.tpose_orient, rig.tpose_orient[start] @ align]),
    )


def collapse_rig(expanded: Rig, main_joint_names: tuple[str, ...]) -> Rig:
    """Public rig derivation: keep ``main_joint_names``; parents of kept joints are remapped to
    their nearest kept ancestor and removed joints' weight columns are added to it.
    """
    names = expanded.joint_names
    kept = [names.index(n) for n in main_joint_names]
    new_index = {old: new for new, old in enumerate(kept)}
    parents = expanded.tree.parents

    def nearest_kept(j: int) -> int:
        while j not in new_index:
            j = parents[j]
        return new_index[j]

    to_kept = torch.tensor([nearest_kept(j) for j in range(len(names))])
    new_parents = tuple(-1 if parents[j] < 0 else nearest_kept(parents[j]) for j in kept)
    n = len(kept)
    key = expanded.skin_vertex * n + to_kept[expanded.skin_joint]
    uniq, inverse = torch.unique(key, return_inverse=True)
    weight = expanded.skin_weight.new_zeros(uniq.shape).index_add_(0, inverse, expanded.skin_weight)
    rbf = torch.isin(expanded.rbf_joint, torch.tensor(kept))
    kept_t = torch.tensor(kept)
    return Rig(
        joint_names=tuple(main_joint_names),
        tree=KinematicTree(new_parents),
        bind_vertices=expanded.bind_vertices,
        faces=expanded.faces,
        skin_vertex=uniq // n,
        skin_joint=uniq % n,
        skin_weight=weight,
        rbf_joint=to_kept[expanded.rbf_joint[rbf]],
        rbf_vertex=expanded.rbf_vertex[rbf],
        rbf_weight=expanded.rbf_weight[rbf],
        bind_transforms=expanded.bind_transforms[kept_t],
        tpose_orient=expanded.tpose_orient[kept_t],
    )
