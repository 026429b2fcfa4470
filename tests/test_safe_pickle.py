"""The restricted unpickler: hostile pickles never run code; chumpy/scipy-era pickles load as arrays."""

from __future__ import annotations

import io
import os
import pickle
import subprocess
import sys

import numpy as np
import pytest

from smpl_format import chumpy_ch, chumpy_node, chumpy_select, dumps, sparse_matrix
from unibody.io import safe_pickle


def _load(data: bytes) -> object:
    return safe_pickle.load(io.BytesIO(data))


def _hostile(target):
    """Protocol-0 text pickles that would create ``target`` if any global were resolved."""
    t = str(target)
    return {
        "os.system": f"cos\nsystem\n(S'touch {t}'\ntR.",
        "posix.system": f"cposix\nsystem\n(S'touch {t}'\ntR.",
        "builtins.eval": f"cbuiltins\neval\n(S'open({t!r}, \"w\").close()'\ntR.",
        "__builtin__.eval": f"c__builtin__\neval\n(S'open({t!r}, \"w\").close()'\ntR.",
        "subprocess.Popen": f"csubprocess\nPopen\n((lp0\nS'touch'\naS'{t}'\natR.",
        "builtins.open": f"cbuiltins\nopen\n(S'{t}'\nS'w'\ntR.",  # a REDUCE that creates a file
        "__builtin__.getattr": "c__builtin__\ngetattr\n(cnumpy\nndarray\nS'tofile'\ntR.",
        "numpy.load": f"cnumpy\nload\n(S'{t}'\ntR.",
    }


@pytest.mark.parametrize(
    "name",
    [
        "os.system",
        "posix.system",
        "builtins.eval",
        "__builtin__.eval",
        "subprocess.Popen",
        "builtins.open",
        "__builtin__.getattr",
        "numpy.load",
    ],
)
def test_hostile_globals_are_refused_without_side_effect(tmp_path, name):
    target = tmp_path / "pwned"
    payload = _hostile(target)[name].encode()
    with pytest.raises(pickle.UnpicklingError, match=rf"refusing global {name}\b"):
        _load(payload)
    assert not target.exists()
    if name == "builtins.open":  # the test can fail: the stock unpickler does create the file
        pickle.loads(payload).close()
        assert target.exists()


class _Evil:
    def __init__(self, func, args):
        self.func, self.args = func, args

    def __reduce__(self):
        return self.func, self.args


@pytest.mark.parametrize("protocol", range(pickle.HIGHEST_PROTOCOL + 1))
@pytest.mark.parametrize("how", ["system", "popen", "eval"])
def test_reduce_payloads_of_every_protocol_are_refused(tmp_path, protocol, how):
    target = tmp_path / "pwned"
    func, args = {
        "system": (os.system, (f"touch {target}",)),
        "popen": (subprocess.Popen, (["touch", str(target)],)),
        "eval": (eval, (f"open({str(target)!r}, 'w').close()",)),
    }[how]
    data = pickle.dumps({"v_template": np.zeros(3), "evil": _Evil(func, args)}, protocol=protocol)
    with pytest.raises(pickle.UnpicklingError, match="refusing global"):
        _load(data)
    assert not target.exists()


@pytest.mark.parametrize(
    ("payload", "match"),
    [
        # copy_reg._reconstructor is allowed for stand-ins only, not to build arbitrary classes
        (b"ccopy_reg\n_reconstructor\n(c__builtin__\nset\nc__builtin__\nobject\nNtR.", "only the chumpy/scipy"),
        (b"ccopy_reg\n_reconstructor\n(cchumpy.ch\nCh\nc__builtin__\nset\nNtR.", "only the chumpy/scipy"),
        # _codecs.encode is allowed with latin-1 only
        (b"c_codecs\nencode\n(S'abc'\nS'rot13'\ntR.", "only \\(str, 'latin1'\\)"),
        (b"cnumpy.testing._private.utils\nrunstring\n(S'1'\n(dtR.", "refusing global numpy.testing"),
        (b"cchumpy.ch_ops\nadd\n)\x81.", "refusing global chumpy.ch_ops.add"),
        (b"cscipy.sparse.linalg\neigs\n.", "refusing global scipy.sparse.linalg.eigs"),
        (b"(S'true'\nios\nsystem\n.", "refusing global os.system"),  # the INST opcode
    ],
)
def test_misuse_of_allowed_names_is_refused(payload, match):
    with pytest.raises(pickle.UnpicklingError, match=match):
        _load(payload)


def test_persistent_ids_are_refused():
    with pytest.raises(pickle.UnpicklingError, match="persistent ids"):
        _load(b"P1\n.")


def _reference_payload(legacy):
    rng = np.random.default_rng(3)
    full = rng.normal(size=(5, 3, 4))
    dense = np.zeros((4, 7))
    dense[[0, 1, 1, 3], [2, 0, 6, 6]] = [1.5, -2.0, 0.25, 3.0]
    payload = {
        "x": chumpy_ch(full[..., 0]),
        "select": chumpy_select(full, 2),
        "transpose": chumpy_node("transpose", a=chumpy_ch(full[:, :, 0]), axes=None),
        "reshape": chumpy_node("Reshape", a=chumpy_ch(full), newshape=(15, 4)),
        "csc": sparse_matrix(dense, "csc", legacy=legacy),
        "csr": sparse_matrix(dense, "csr", legacy=legacy),
        "coo": sparse_matrix(dense, "coo", legacy=legacy, coords=not legacy),
        "plain": [np.arange(3, dtype=np.int32), ("lbs", 2.5, None)],
    }
    expected = {
        "x": full[..., 0],
        "select": full[..., :2],
        "transpose": full[:, :, 0].T,
        "reshape": full.reshape(15, 4),
        "csc": dense,
        "csr": dense,
        "coo": dense,
    }
    return payload, expected


@pytest.mark.parametrize("protocol", [0, 2, 4, 5])
@pytest.mark.parametrize("legacy", [True, False], ids=["py2-names", "modern-names"])
def test_chumpy_and_scipy_era_pickles_load_as_arrays(protocol, legacy):
    payload, expected = _reference_payload(legacy)
    before = set(sys.modules)
    out = _load(dumps(payload, protocol=protocol, legacy=legacy))
    assert isinstance(out, dict) and set(out) == set(payload)
    for key, want in expected.items():
        assert type(out[key]) is np.ndarray, key
        assert out[key].shape == want.shape and np.array_equal(out[key], want), key
    assert np.array_equal(out["plain"][0], np.arange(3)) and out["plain"][0].dtype == np.int32
    assert out["plain"][1] == ("lbs", 2.5, None)
    added = {m.split(".")[0] for m in set(sys.modules) - before}
    assert not added & {"chumpy", "scipy"}


def test_sparse_duplicates_are_summed_like_scipy():
    coo = sparse_matrix(np.zeros((2, 3)), "coo")
    coo.data, coo.row, coo.col = np.array([1.0, 2.0, 4.0]), np.array([1, 1, 0]), np.array([2, 2, 0])
    out = _load(dumps({"m": coo}))
    assert np.array_equal(out["m"], [[4.0, 0.0, 0.0], [0.0, 0.0, 3.0]])


def test_old_scipy_shape_attribute_and_object_arrays():
    m = sparse_matrix(np.eye(3), "csr")
    m.shape = m.__dict__.pop("_shape")  # SciPy before 0.14 kept a plain ``shape`` attribute
    holder = np.empty(2, dtype=object)
    holder[0], holder[1] = m, "tag"
    out = _load(dumps({"holder": holder}, protocol=4, legacy=False))
    assert out["holder"].dtype == object and out["holder"].shape == (2,)
    assert np.array_equal(out["holder"][0], np.eye(3)) and out["holder"][1] == "tag"


def test_file_paths_are_named_in_errors(tmp_path):
    path = tmp_path / "SMPL_NEUTRAL.pkl"
    path.write_bytes(b"cos\nsystem\n(S'true'\ntR.")
    with pytest.raises(pickle.UnpicklingError, match=r"SMPL_NEUTRAL\.pkl: refusing global os\.system"):
        safe_pickle.load(path)
    path.write_bytes(dumps({"a": np.ones(2)})[:-20])
    with pytest.raises(pickle.UnpicklingError, match=r"SMPL_NEUTRAL\.pkl: (pickle data was truncated|not a loadable)"):
        safe_pickle.load(str(path))
    with pytest.raises(FileNotFoundError):
        safe_pickle.load(tmp_path / "missing.pkl")
    path.write_bytes(dumps({"a": chumpy_ch(np.ones(2))}))
    with path.open("rb") as f:
        assert np.array_equal(safe_pickle.load(f)["a"], np.ones(2))


def _bad_states():
    sel = chumpy_select(np.ones((2, 3, 2)), 1)
    sel.idxs = sel.idxs.astype(np.float64)
    out_of_range = chumpy_select(np.ones((2, 3, 2)), 1)
    out_of_range.idxs = out_of_range.idxs + 100
    no_x = chumpy_ch(np.ones(2))
    del no_x.x
    indptr = sparse_matrix(np.eye(3), "csc")
    indptr.indptr = indptr.indptr[:-1]
    rows = sparse_matrix(np.eye(3), "coo")
    rows.row = rows.row + 5
    no_shape = sparse_matrix(np.eye(3), "csr")
    del no_shape._shape
    huge = sparse_matrix(np.eye(3), "csr")
    huge._shape = (10**6, 10**6)
    return {
        "float idxs": (sel, r"\['m'\]: cannot evaluate chumpy.reordering.Select: idxs must be integers"),
        "idxs out of range": (out_of_range, "cannot evaluate chumpy.reordering.Select"),
        "Ch without x": (no_x, r"chumpy.ch.Ch state lacks 'x'"),
        "bad indptr": (indptr, "invalid indptr"),
        "row out of range": (rows, "invalid row indices"),
        "no shape": (no_shape, "has no valid '_shape'"),
        "huge": (huge, "unsupported shape"),
    }


@pytest.mark.parametrize("case", list(_bad_states()))
def test_malformed_states_raise(case):
    obj, match = _bad_states()[case]
    with pytest.raises(pickle.UnpicklingError, match=match):
        _load(dumps({"m": obj}))


def test_cycles_and_deep_nesting_raise():
    cyclic: list = []
    cyclic.append(cyclic)
    with pytest.raises(pickle.UnpicklingError, match="cyclic reference"):
        _load(pickle.dumps(cyclic))
    node = chumpy_ch(np.ones(1))
    for _ in range(80):
        node = chumpy_node("Reshape", a=node, newshape=(1,))
    with pytest.raises(pickle.UnpicklingError, match="nested deeper than 64"):
        _load(dumps(node))


def test_standins_refuse_construction_with_arguments():
    # REDUCE on an allowed stand-in class with arguments (no class of the real files is called so)
    with pytest.raises(pickle.UnpicklingError, match="not a loadable pickle"):
        _load(b"cchumpy.ch\nCh\n(S'x'\ntR.")
