"""BodyLayer entry points under arbitrary input (issue 35: items 10, 11, 12, 18).

Property, for ``pose`` (axis-angle, matrices, 6D), ``transl``, identity parameters (PCA and
Anny), ``prepare_rest``: either a documented exception (``ValueError``/``TypeError``) whose
message starts with the argument's name, or a result of the right shape with only finite
values. Never NaN/inf, never another exception type. Batches of 0, 1 and 2.
Default run: seeded, ~30 examples per property; ``--hypothesis-profile=long`` for more.
"""

from __future__ import annotations

import numpy as np
import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from unibody import BodyLayer
from unibody.geometry.rotations import axis_angle_to_matrix, matrix_to_rot6d

V, J = 18056, 78
SPECIAL = [0.0, -0.0, 1.0, -1.0, 1e-30, -1e-30, 1e-6, 1e3, 1e20, -1e20, 3e38, -3e38, np.inf, -np.inf, np.nan]
VALUES = st.sampled_from(SPECIAL) | st.floats(width=32, allow_nan=True, allow_infinity=True)
BATCH = st.sampled_from([0, 1, 2])
_PROFILE_EXAMPLES = settings().max_examples  # 30 by default, 1000 with --hypothesis-profile=long


def examples(n: int) -> settings:
    """``n`` examples in the default run; the long profile's count otherwise."""
    return settings(max_examples=n if _PROFILE_EXAMPLES <= 30 else _PROFILE_EXAMPLES)


@pytest.fixture(scope="module")
def pca():
    layer = BodyLayer.from_pca(num_components=10)
    return layer, layer.prepare_identity(torch.zeros(1, 10))


@pytest.fixture(scope="module")
def pca_twist():
    layer = BodyLayer.from_pca(num_components=10, procedural=True)
    return layer, layer.prepare_identity(torch.zeros(1, 10))


@pytest.fixture(scope="module")
def anny():
    return BodyLayer.from_anny()


def _outcome(fn, names: tuple[str, ...]):
    """Run ``fn``: a documented error naming one of ``names`` (returns None), or its result."""
    try:
        return fn()
    except (ValueError, TypeError) as err:
        msg = str(err)
        assert msg.startswith(tuple(f"{n}:" for n in names)), msg
        return None


def _assert_body(out, b: int) -> None:
    assert out.vertices.shape == (b, V, 3) and out.joints.shape == (b, J, 3)
    assert out.transforms.shape == (b, J, 4, 4) and out.rest_vertices.shape == (b, V, 3)
    for x in (out.vertices, out.joints, out.transforms):
        assert torch.isfinite(x).all()


@st.composite
def poses(draw):
    """A pose batch: valid rotations of a drawn scale, then some entries poisoned."""
    b = draw(BATCH)
    kind = draw(st.sampled_from(["aa", "mat", "6d"]))
    seed = draw(st.integers(0, 2**16))
    scale = draw(st.sampled_from([0.0, 0.3, 3.0, 1e3, 1e20, 1e30]))
    aa = scale * torch.randn(b, 77, 3, generator=torch.Generator().manual_seed(seed))
    x = {"aa": aa, "mat": axis_angle_to_matrix(aa), "6d": matrix_to_rot6d(axis_angle_to_matrix(aa))}[kind]
    flat = x.reshape(-1).clone()
    how = draw(st.sampled_from(["keep", "poison", "fill", "scale", "transpose_half", "swap_halves"]))
    if how == "poison" and flat.numel():
        for _ in range(draw(st.integers(1, 4))):
            flat[draw(st.integers(0, flat.numel() - 1))] = draw(VALUES)
    elif how == "fill":
        flat[:] = draw(VALUES)
    elif how == "scale":
        flat = flat * draw(VALUES)
    x = flat.view_as(x)
    if how == "transpose_half" and kind == "mat":  # rows of a rotation times -1: a reflection
        x = x.clone()
        x[..., 0, :] = -x[..., 0, :]
    if how == "swap_halves" and kind == "6d":  # second half parallel to the first
        x = torch.cat([x[..., :3], -2 * x[..., :3]], -1)
    return x


@examples(60)
@given(poses())
def test_pose_entry_point(pca, pose):
    layer, prepared = pca
    out = _outcome(lambda: layer.pose(prepared, pose), ("pose",))
    if out is not None:
        _assert_body(out, pose.shape[0])
        if pose.dim() == 4 and pose.shape[0]:  # accepted matrices are rotations: no scaled or collapsed mesh
            diag = (out.vertices.amax(1) - out.vertices.amin(1)).norm(dim=-1)
            assert bool(((diag > 0.3) & (diag < 4.0)).all()), diag


@examples(25)
@given(poses())
def test_pose_with_procedural_twist(pca_twist, pose):
    layer, prepared = pca_twist
    out = _outcome(lambda: layer.pose(prepared, pose), ("pose",))
    if out is not None:
        _assert_body(out, pose.shape[0])


@examples(30)
@given(BATCH, VALUES, st.sampled_from(["shape", "dtype", "value", "list"]))
def test_transl(pca, b, value, how):
    layer, prepared = pca
    transl = torch.full((b, 3), value)
    if how == "shape":
        transl = torch.zeros(b + 1, 3)
    elif how == "dtype":
        transl = transl.double()
    elif how == "list":
        transl = transl.tolist()
    out = _outcome(lambda: layer.pose(prepared, torch.zeros(b, 77, 3), transl=transl), ("transl", "pose"))
    if out is not None:
        _assert_body(out, b)


@examples(40)
@given(BATCH, st.data(), st.sampled_from(["values", "scale", "shape", "dtype", "numpy"]))
def test_pca_identity_params(pca, b, data, how):
    layer, _ = pca
    k = 10
    params = torch.tensor(data.draw(st.lists(VALUES, min_size=b * k, max_size=b * k)), dtype=torch.float32)
    params = params.view(b, k)
    if how == "scale":
        params = data.draw(st.sampled_from([0.5, 3.0, 9.9, 10.1, 1e30])) * torch.randn(b, k).clamp(-1, 1)
    elif how == "shape":
        params = torch.zeros(b, data.draw(st.sampled_from([0, 9, 11])))
    elif how == "dtype":
        params = torch.zeros(b, k, dtype=torch.float64)
    elif how == "numpy":
        params = np.zeros((b, k), np.float32)
    out = _outcome(lambda: layer(params, torch.zeros(b, 77, 3)), ("identity params",))
    if out is not None:
        _assert_body(out, b)
        lo, hi = layer.identity.param_bounds
        assert bool(((params >= lo) & (params <= hi)).all())  # nothing out of bounds got through


@examples(20)
@given(st.sampled_from([1, 2]), st.data())
def test_anny_phenotypes(anny, b, data):
    """Anny phenotypes: in-range ones give sane bodies, anything else a clear error."""
    k = anny.identity.num_params
    edge = st.sampled_from([0.0, 1.0, 0.5, -1e-6, 1.000001, -1.0, 2.0, 1e30, np.nan, np.inf])
    values = data.draw(st.lists(edge | st.floats(-0.5, 1.5, width=32), min_size=b * k, max_size=b * k))
    params = torch.tensor(values, dtype=torch.float32).view(b, k)
    out = _outcome(lambda: anny(params, torch.zeros(b, 77, 3)), ("identity params",))
    if out is not None:
        _assert_body(out, b)
        diag = (out.rest_vertices.amax(1) - out.rest_vertices.amin(1)).norm(dim=-1)
        assert bool(((diag > 0.3) & (diag < 4.0)).all()), diag  # a human, not garbage


def test_anny_empty_batch(anny):
    out = anny(torch.zeros(0, anny.identity.num_params), torch.zeros(0, 77, 3))
    _assert_body(out, 0)


@examples(40)
@given(BATCH, st.data(), st.sampled_from(["scale", "poison", "offset", "dtype", "shape"]))
def test_prepare_rest(pca, b, data, how):
    layer, prepared = pca
    rest = prepared.rest_vertices.expand(b, -1, -1).clone()
    if how == "scale":
        rest = rest * data.draw(VALUES)
    elif how == "poison" and b:
        rest[data.draw(st.integers(0, b - 1)), data.draw(st.integers(0, V - 1)), 1] = data.draw(VALUES)
    elif how == "offset":
        rest = rest + data.draw(st.sampled_from([1.0, 1e3, 1e6, 1e30, -3e38]))
    elif how == "dtype":
        rest = rest.double()
    elif how == "shape":
        rest = rest[:, : data.draw(st.sampled_from([0, 100, V - 1]))]
    prep = _outcome(lambda: layer.prepare_rest(rest), ("rest_vertices",))
    if prep is None:
        return
    for x in (prep.rest_rotations, prep.rest_joints, prep.offsets):
        assert x.shape[0] == b and torch.isfinite(x).all()
    out = _outcome(lambda: layer.pose(prep, 0.3 * torch.ones(b, 77, 3)), ("pose",))
    if out is not None:
        _assert_body(out, b)
