"""The canonical asset cache: verified on load, rebuilt when unusable, built once across processes.

A real build (~5 s) runs once per module into a temporary ``UNIBODY_CACHE_DIR``; the corruption
tests then replace ``assets._build`` by a counter returning that build's arrays, so each one
checks the cache machinery (warning, rebuild, atomic rewrite) without rebuilding for real.
"""

from __future__ import annotations

import os
import re
import subprocess
import sys
import threading
import time
import zipfile
from pathlib import Path

import numpy as np
import pytest

from unibody import assets
from unibody.assets import AssetWarning
from unibody.io.atomic import waiting_lock

RNG = np.random.default_rng(0)


def _equal(a: dict[str, np.ndarray], b: dict[str, np.ndarray]) -> bool:
    return a.keys() == b.keys() and all(np.array_equal(a[k], b[k]) for k in a)


@pytest.fixture(scope="module")
def first_run(tmp_path_factory):
    """A first run in a fresh process and UNIBODY_CACHE_DIR: (cache folder, stdout, stderr)."""
    folder = tmp_path_factory.mktemp("first-run")
    code = "from unibody.assets import canonical_assets; canonical_assets(); print('RESULT')"
    env = {**os.environ, "UNIBODY_CACHE_DIR": str(folder)}
    run = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True, timeout=300)
    assert run.returncode == 0, run.stderr
    return folder / f"v{assets.DATA_VERSION}", run.stdout, run.stderr


@pytest.fixture(scope="module")
def reference(first_run):
    """(arrays, file bytes) of a fresh build of the canonical assets (the first run's)."""
    (path,) = first_run[0].iterdir()
    arrays, problem = assets.read_cache(path, assets._check_canonical)
    assert problem is None
    return arrays, path.read_bytes()


@pytest.fixture
def cache(monkeypatch, tmp_path, reference):
    """The cache file path in a fresh UNIBODY_CACHE_DIR, holding the reference build; ``_build`` counted."""
    arrays, data = reference
    monkeypatch.setenv("UNIBODY_CACHE_DIR", str(tmp_path / "cache"))
    path = assets.canonical_cache_path()
    path.parent.mkdir(parents=True)
    path.write_bytes(data)
    builds = []

    def build(folder):
        builds.append(folder)
        return {k: v.copy() for k, v in arrays.items()}

    monkeypatch.setattr(assets, "_build", build)
    assets.canonical_assets.cache_clear()
    yield path, builds
    assets.canonical_assets.cache_clear()


def _save(path: Path, arrays: dict[str, np.ndarray], *, sign: bool) -> None:
    """Write ``arrays`` as a valid npz, with their true checksum when ``sign`` (a structurally bad file)."""
    extra = {"_sha256": np.str_(assets.array_checksum(arrays))} if sign else {}
    with open(path, "wb") as f:
        np.savez(f, **arrays, **extra)


def _altered(reference, key: str, change) -> dict[str, np.ndarray]:
    arrays = {k: v.copy() for k, v in reference[0].items()}
    arrays[key] = change(arrays[key])
    return arrays


def _set(i, value):
    def change(a):
        a.flat[i] = value
        return a

    return change


def _flip_byte(data: bytes) -> bytes:
    b = bytearray(data)
    b[len(b) // 2] ^= 0x40  # inside bind_vertices or faces: the zip's CRC no longer matches
    return bytes(b)


# name -> (how to corrupt the file at path, what the warning says)
CORRUPTIONS = {
    "truncated": (lambda p, ref: p.write_bytes(ref[1][: len(ref[1]) // 2]), "unreadable"),
    "empty": (lambda p, ref: p.write_bytes(b""), "unreadable"),
    "random bytes": (lambda p, ref: p.write_bytes(RNG.bytes(4096)), "unreadable"),
    "flipped byte (bad CRC)": (lambda p, ref: p.write_bytes(_flip_byte(ref[1])), "unreadable: BadZipFile.*CRC"),
    "wrong keys": (lambda p, ref: _save(p, {"vertices": np.zeros((3, 3))}, sign=True), r"keys: missing \["),
    "no checksum (older file)": (lambda p, ref: _save(p, ref[0], sign=False), "no checksum"),
    "doubled bind vertices": (
        lambda p, ref: _save(p, {**_altered(ref, "bind_vertices", lambda a: 2 * a), "_sha256": _sha(ref)}, sign=False),
        "checksum mismatch",
    ),
    "NaN weight": (lambda p, ref: _save(p, _altered(ref, "skin_weight", _set(7, np.nan)), sign=True), "non-finite"),
    "face index 1e9": (
        lambda p, ref: _save(p, _altered(ref, "faces", _set(5, 10**9)), sign=True),
        "faces: index out of range",
    ),
    "skin weights not summing to 1": (
        lambda p, ref: _save(p, _altered(ref, "skin_weight", lambda a: 0.5 * a), sign=True),
        "do not sum to 1",
    ),
    "float32 vertices": (
        lambda p, ref: _save(p, _altered(ref, "bind_vertices", lambda a: a.astype(np.float32)), sign=True),
        "bind_vertices: dtype float32",
    ),
    "compressed members": (lambda p, ref: _save_compressed(p, ref), "compressed members"),
    "empty folder in its place": (lambda p, ref: (p.unlink(), p.mkdir()), "a folder is in its place"),
}


def _sha(ref) -> np.str_:
    return np.str_(assets.array_checksum(ref[0]))


def _save_compressed(path: Path, ref) -> None:
    with open(path, "wb") as f:
        np.savez_compressed(f, **ref[0], _sha256=_sha(ref))


@pytest.mark.parametrize("name", list(CORRUPTIONS))
def test_a_corrupt_cache_is_rebuilt_with_a_warning(cache, reference, name):
    path, builds = cache
    corrupt, message = CORRUPTIONS[name]
    corrupt(path, reference)
    with pytest.warns(AssetWarning, match=f"cache file .* is unusable \\(.*{message}"):
        arrays = assets.canonical_assets()
    assert _equal(arrays, reference[0]) and len(builds) == 1
    # Rewritten atomically: intact, no temporary or lock file left, and read back without a rebuild.
    again, problem = assets.read_cache(path, assets._check_canonical)
    assert problem is None and _equal(again, reference[0])
    assert sorted(p.name for p in path.parent.iterdir()) == [path.name]
    assets.canonical_assets.cache_clear()
    assert _equal(assets.canonical_assets(), reference[0]) and len(builds) == 1


def test_an_intact_cache_is_used_without_a_build(cache, reference, recwarn):
    path, builds = cache
    assert _equal(assets.canonical_assets(), reference[0]) and not builds
    assert not [w for w in recwarn if issubclass(w.category, AssetWarning)]


def test_a_full_folder_in_its_place_is_left_alone_and_the_assets_built_in_memory(cache, reference):
    path, builds = cache
    path.unlink()
    path.mkdir()
    (path / "keep.txt").write_text("not ours")
    with pytest.warns(AssetWarning) as record:
        arrays = assets.canonical_assets()
    messages = " ".join(str(w.message) for w in record)
    assert "a folder is in its place" in messages and "cannot write the cache" in messages
    assert _equal(arrays, reference[0]) and (path / "keep.txt").read_text() == "not ours"


def test_an_unwritable_cache_folder_means_in_memory_with_one_warning(monkeypatch, tmp_path, reference):
    """A cache folder under a regular file cannot be created, even by root."""
    (tmp_path / "a-file").write_text("")
    monkeypatch.setenv("UNIBODY_CACHE_DIR", str(tmp_path / "a-file" / "cache"))
    monkeypatch.setattr(assets, "_build", lambda folder: {k: v.copy() for k, v in reference[0].items()})
    assets.canonical_assets.cache_clear()
    with pytest.warns(AssetWarning, match="cannot write the cache in .*a-file.*building in memory"):
        arrays = assets.canonical_assets()
    assert _equal(arrays, reference[0])
    assets.canonical_assets.cache_clear()
    with pytest.warns() as record:  # the same folder again: no second warning
        assert _equal(assets.canonical_assets(), reference[0])
        import warnings

        warnings.warn("sentinel", UserWarning, stacklevel=1)
    assert [str(w.message) for w in record] == ["sentinel"]
    assets.canonical_assets.cache_clear()


@pytest.mark.skipif(os.geteuid() == 0, reason="root writes into a read-only folder; see the under-a-file test")
def test_a_read_only_cache_folder_means_in_memory(monkeypatch, tmp_path, reference):
    folder = tmp_path / "ro"
    folder.mkdir()
    folder.chmod(0o500)
    monkeypatch.setenv("UNIBODY_CACHE_DIR", str(folder))
    monkeypatch.setattr(assets, "_build", lambda f: {k: v.copy() for k, v in reference[0].items()})
    assets.canonical_assets.cache_clear()
    try:
        with pytest.warns(AssetWarning, match="cannot write the cache"):
            assert _equal(assets.canonical_assets(), reference[0])
    finally:
        folder.chmod(0o700)
        assets.canonical_assets.cache_clear()


@pytest.mark.parametrize("value", ["", "   "])
def test_an_empty_cache_dir_variable_means_the_default_folder(monkeypatch, tmp_path, value):
    import platformdirs

    monkeypatch.chdir(tmp_path)
    monkeypatch.setenv("UNIBODY_CACHE_DIR", value)
    folder = assets.cache_dir()
    assert folder == Path(platformdirs.user_cache_dir("unibody")) / f"v{assets.DATA_VERSION}"
    assert folder.is_absolute()


def test_a_fresh_build_that_fails_its_checks_is_an_error(monkeypatch, tmp_path, reference):
    monkeypatch.setenv("UNIBODY_CACHE_DIR", str(tmp_path))
    bad = _altered(reference, "faces", _set(0, -1))
    monkeypatch.setattr(assets, "_build", lambda folder: bad)
    assets.canonical_assets.cache_clear()
    with pytest.raises(assets.AssetError, match="fresh build fails its checks .*faces: index out of range"):
        assets.canonical_assets()
    assets.canonical_assets.cache_clear()
    assert not list(tmp_path.rglob("*.npz"))


def test_waiting_lock_waits_for_the_holder_then_times_out(tmp_path):
    target = tmp_path / "file"
    order = []
    entered = threading.Event()

    def holder():
        with waiting_lock(target):
            entered.set()
            time.sleep(0.3)
            order.append("first")

    t = threading.Thread(target=holder)
    t.start()
    entered.wait()
    with pytest.raises(TimeoutError, match="another process held .*file.lock"):
        with waiting_lock(target, timeout=0.05):
            pass
    with waiting_lock(target):
        order.append("second")
    t.join()
    assert order == ["first", "second"] and not (tmp_path / "file.lock").exists()


_CHILD = """
import sys, time
from pathlib import Path
import numpy as np
from unibody import assets

ref = dict(np.load(sys.argv[1]))
ref.pop("_sha256")

def build(folder):
    print("BUILD", file=sys.stderr, flush=True)
    time.sleep(1.5)
    return ref

assets._build = build
ready = Path(sys.argv[2])
(ready / sys.argv[3]).touch()
while len(list(ready.iterdir())) < 2:  # start together
    time.sleep(0.01)
arrays = assets.canonical_assets()
print(assets.array_checksum(arrays))
"""


def test_two_processes_build_once_and_read_the_same_arrays(tmp_path, reference):
    ref_file = tmp_path / "ref.npz"
    ref_file.write_bytes(reference[1])
    ready = tmp_path / "ready"
    ready.mkdir()
    env = {**os.environ, "UNIBODY_CACHE_DIR": str(tmp_path / "cache")}
    procs = [
        subprocess.Popen(
            [sys.executable, "-c", _CHILD, str(ref_file), str(ready), name],
            env=env,
            stdout=subprocess.PIPE,
            stderr=subprocess.PIPE,
            text=True,
        )
        for name in ("a", "b")
    ]
    outs = [p.communicate(timeout=120) for p in procs]
    assert [p.returncode for p in procs] == [0, 0], outs
    sums = {out.strip() for out, _ in outs}
    assert sums == {assets.array_checksum(reference[0])}
    assert sum(err.count("BUILD") for _, err in outs) == 1, outs  # one built, the other waited and read
    cache = tmp_path / "cache" / f"v{assets.DATA_VERSION}"
    assert [p.suffix for p in cache.iterdir()] == [".npz"]  # no temporary or lock file left
    arrays, problem = assets.read_cache(next(cache.iterdir()), assets._check_canonical)
    assert problem is None and _equal(arrays, reference[0])


def test_first_run_says_what_it_builds_on_stderr(first_run):
    folder, out, err = first_run
    (path,) = folder.iterdir()
    assert path == folder / assets.canonical_cache_path().name
    assert f"unibody: building the canonical assets once (~5-20 s) into {path}..." in err
    assert re.search(r"unibody: built the canonical assets in \d+\.\d s", err)
    assert out == "RESULT\n"


def test_warp_prints_no_banner_on_stdout():
    """Anny initialises Warp on import of its skinning module; the banner would go to stdout."""
    pytest.importorskip("warp")
    code = "from unibody.identity.anny import _quiet_warp; _quiet_warp(); import anny.skinning.warp_skinning"
    run = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=300)
    assert run.returncode == 0, run.stderr
    assert run.stdout == ""  # without _quiet_warp: "Warp 1.19.0 initialized: ..."


@pytest.mark.slow
def test_anny_first_load_keeps_stdout_clean(tmp_path):
    """``AnnyIdentity.create`` end to end with a copy of the installed Anny cache (never writing ~/.cache/anny)."""
    real = Path.home() / ".cache" / "anny"
    env = {**os.environ, "UNIBODY_CACHE_DIR": str(tmp_path / "unibody"), "ANNY_CACHE_DIR": str(real)}
    probe = "from unibody.identity.anny import _anny_model_path; print(_anny_model_path('none'))"
    source = Path(subprocess.run([sys.executable, "-c", probe], env=env, capture_output=True, text=True).stdout.strip())
    if not source.is_file():
        pytest.skip("no cached Anny model to copy: the first run would build it for a minute")
    target = tmp_path / "anny" / source.parent.name / source.name
    target.parent.mkdir(parents=True)
    target.write_bytes(source.read_bytes())
    env["ANNY_CACHE_DIR"] = str(tmp_path / "anny")
    code = "from unibody.identity.anny import AnnyIdentity; AnnyIdentity.create(); print('RESULT')"
    run = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True, timeout=300)
    assert run.returncode == 0, run.stderr
    assert run.stdout == "RESULT\n"  # no Warp banner
    assert "Anny's model" not in run.stderr  # cached: loaded without a message
    assert list((tmp_path / "anny").rglob("*.safetensors")) == [target]


def test_npz_members_are_stored_not_compressed(reference):
    """read_cache refuses compressed members (a zip bomb could inflate); our writer stores them."""
    import io

    with zipfile.ZipFile(io.BytesIO(reference[1])) as z:
        assert {i.compress_type for i in z.infolist()} == {zipfile.ZIP_STORED}
