"""Correctives of any mask layout (the slot order of ``correctives/model.py``).

Property: for masks drawn at random over a chain rig's vertices (overlapping or not, windows or
scattered sets), the displacements equal the sum over masks of each joint's activations times its
decoder, put on its mask's vertices, whether the masks form runs of slots (each run then holds
exactly its mask's vertices) or not (the scatter path); and posing with them equals LBS of the
displaced rest mesh. Default run: seeded, bounded; ``--hypothesis-profile=long``.
"""

from __future__ import annotations

import functools

import torch
from hypothesis import event, given, settings
from hypothesis import strategies as st

from conftest import chain_rig
from unibody import BodyLayer
from unibody.body import PreparedIdentity
from unibody.correctives.model import Correctives

_PROFILE_EXAMPLES = settings().max_examples  # 30 by default, 1000 with --hypothesis-profile=long


@functools.cache
def _chain():
    rig = chain_rig()
    layer = BodyLayer(rig).double()
    return rig, layer, layer.prepare_rest(rig.bind_vertices[None].double())


def _window(v: int) -> st.SearchStrategy:
    return st.tuples(st.integers(0, v - 1), st.integers(1, 12)).map(lambda t: list(range(t[0], min(t[0] + t[1], v))))


def _scattered(pool: int) -> st.SearchStrategy:
    return st.lists(st.integers(0, pool - 1), min_size=1, max_size=10, unique=True)


@settings(max_examples=40 if _PROFILE_EXAMPLES <= 30 else _PROFILE_EXAMPLES)
@given(data=st.data(), seed=st.integers(0, 2**31 - 1))
def test_any_masks_decode_and_pose_exactly(data, seed):
    rig, plain, prepared = _chain()
    v = rig.num_vertices
    a = data.draw(st.integers(1, 5), label="masks")
    masks = [torch.tensor(data.draw(st.one_of(_window(v), _scattered(16)), label=f"mask {k}")) for k in range(a)]
    inputs = torch.tensor([[2 + k % 3, 1 + (k + 1) % 4] for k in range(a)])
    model = Correctives(inputs, masks, v, hidden=6, channels=3, bones=((1, 2), (2, 3))).double()
    gen = torch.Generator().manual_seed(seed)
    with torch.no_grad():
        for p in model.parameters():
            p.copy_(0.3 * torch.randn(p.shape, generator=gen, dtype=torch.float64))
    model.requires_grad_(False)
    event("runs of slots" if model._runs is not None else "scatter")
    if model._runs is not None:
        for (s, e), (r0, r1) in zip(model._blocks, model._runs, strict=True):
            assert sorted(model._slot_vertex[r0:r1].tolist()) == sorted(model.vertex_ids[s:e].tolist())
    pose = 0.8 * torch.randn(3, rig.num_joints - 1, 3, generator=gen, dtype=torch.float64)
    rel = model.rest_relative(plain.local_rotations(pose), prepared.rest_rotations, plain.parents)
    size = model.size_of(prepared.rest_joints)
    d = model(rel, size)
    act = model.activations(model.features(rel[:, model.needed - 1])) * size / model.size_ref
    by_hand = torch.zeros_like(d)
    for k, (s, e) in enumerate(model._blocks):
        by_hand[:, model.vertex_ids[s:e]] += (act[:, k] @ model.decode[3 * s : 3 * e].T).view(3, -1, 3)
    assert (d - by_hand).abs().max() < 1e-12
    on = BodyLayer(rig, correctives=model).double()
    p = prepared
    shifted = PreparedIdentity(
        p.rest_vertices + d, *(t.expand(3, *t.shape[1:]) for t in (p.rest_rotations, p.rest_joints, p.offsets))
    )
    assert (on.pose(prepared, pose).vertices - plain.pose(shifted, pose).vertices).abs().max() < 1e-10
