"""A conversion run: inputs to tasks, one task per file, on this process, a local pool or Ray.

:func:`plan` turns input files and folders into :class:`Task` s (formats detected from content,
outputs under ``--out`` mirroring the inputs' relative paths, finished work from an earlier run
verified and left out); :func:`convert_file` is the per-file task (read, then every writer) that
every executor runs unchanged; :func:`run` does both and writes the report
(:mod:`unibody.convert.report`). Executors: this process (``jobs=1``), a
``concurrent.futures.ProcessPoolExecutor`` of spawned workers (``jobs>1``), or Ray
(``executor="ray"``: the cluster at ``$RAY_ADDRESS``, else a local Ray with ``jobs`` CPUs).
A cluster array job runs one ``shard=(i, N)`` per node: shard ``i`` takes every N-th file of
the sorted inputs, starting at the i-th.
"""

from __future__ import annotations

import os
import sys
import time
import warnings as _warnings
from collections.abc import Callable, Iterable, Iterator
from dataclasses import dataclass, field
from pathlib import Path

from ..io.atomic import OutputError, file_sha256, output_lock
from ._types import ConvertOptions
from .formats import FORMATS, WRITERS, NotAMotion, detect, output_name, reader, writer
from .report import Journal, all_records, load_records, report_paths, write_report

__all__ = ["RunSummary", "Task", "convert_file", "plan", "run"]


@dataclass(frozen=True, slots=True)
class Task:
    """One input file and what to write from it.

    Attributes:
        input: the input file (absolute path).
        format: its format (detected or ``--from``); None when it could not be read.
        outputs: ``(format, absolute output path)`` per writer.
        error: why the file cannot be converted (it is reported as failed), else None.
    """

    input: str
    format: str | None
    outputs: tuple[tuple[str, str], ...]
    error: str | None = None


@dataclass(frozen=True, slots=True)
class RunSummary:
    """What a run did: counts of files and frames, seconds, and where the report is."""

    converted: int
    failed: int
    done_before: int
    skipped: int
    frames: int
    seconds: float
    report: Path
    errors: tuple[str, ...] = field(default=())

    def line(self) -> str:
        rate = self.frames / self.seconds if self.seconds > 0 else 0.0
        return (
            f"converted {self.converted} file(s), {self.frames} frames in {self.seconds:.1f} s ({rate:,.0f} frames/s); "
            f"{self.done_before} done before, {self.failed} failed, {self.skipped} not motion files; "
            f"report {self.report}"
        )


# --------------------------------------------------------------------------- planning


def _walk(folder: Path, out: Path) -> Iterator[Path]:
    """Files under ``folder`` (links to folders not followed), minus hidden files and ``out``'s content."""
    out_real = os.path.realpath(out)
    inside = os.path.realpath(folder) != out_real
    for root, dirs, files in os.walk(folder):
        dirs[:] = sorted(d for d in dirs if not d.startswith(".") and not (inside and _same(Path(root, d), out_real)))
        for name in sorted(files):
            if not name.startswith(".") and not name.startswith("convert_report"):
                yield Path(root, name)


def _same(path: Path, real: str) -> bool:
    return os.path.realpath(path) == real


def _candidates(inputs: Iterable[Path], out: Path) -> Iterator[tuple[Path, Path, bool]]:
    """``(file, path relative to its input, given explicitly)`` for every input file."""
    for given in inputs:
        if given.is_dir():
            for f in _walk(given, out):
                yield f, f.relative_to(given), False
        elif given.exists():
            yield given, Path(given.name), True
        else:
            raise FileNotFoundError(f"{given}: no such file or folder")


def _classify(path: Path, explicit: bool, source: str | None) -> tuple[str | None, str | None, str | None]:
    """``(format, error, skip reason)`` of one candidate file."""
    if path.is_symlink() and not path.exists():
        return None, f"{path}: a broken link (to {os.readlink(path)})", None
    if source is not None and explicit:
        return source, None, None
    try:
        fmt = detect(path)
    except NotAMotion as exc:
        if source is not None and path.suffix.lower() in FORMATS[source].inputs:
            return source, None, None
        return (None, str(exc), None) if explicit else (None, None, str(exc))
    except (OSError, ValueError) as exc:
        return None, _line(exc, path), None
    if source is not None and fmt != source:
        msg = f"{path}: detected as {fmt}, not --from {source}"
        return (source, None, None) if explicit else (None, None, msg)
    return fmt, None, None


def plan(
    inputs: Iterable[str | os.PathLike[str]],
    to: Iterable[str],
    out: str | os.PathLike[str],
    *,
    source: str | None = None,
    shard: tuple[int, int] | None = None,
    written: frozenset[str] | set[str] = frozenset(),
) -> tuple[list[Task], list[dict]]:
    """The tasks of a run (this shard's) and the files left out as not motion files.

    Args:
        inputs: files and folders (folders are walked recursively; hidden files, the reports
            and the content of ``out`` are left out).
        to: output formats (:data:`unibody.convert.formats.WRITERS`).
        out: the output folder; an input's outputs mirror its path relative to its folder.
        source: the input format for every file (``--from``), else detected per file.
        shard: ``(i, N)``: only every N-th task of the sorted list, from the i-th.
        written: outputs earlier runs wrote (real paths, from the reports in ``out``): a file
            found in a folder that is one of them is not an input. Any other file found there
            stays an input, and an input whose output it would be fails instead.

    Raises:
        FileNotFoundError: an input does not exist.
    """
    to, out = tuple(to), Path(out)
    found: dict[str, tuple[Path, Path, bool]] = {}
    for path, rel, explicit in _candidates([Path(p) for p in inputs], out):
        # one task per real file; a broken link is its own (named by itself, not by where it points)
        found.setdefault(os.path.realpath(path) if path.exists() else os.path.abspath(path), (path, rel, explicit))
    tasks, skipped = [], []
    classified = {}
    out_real = os.path.realpath(out)
    for key in sorted(found):
        path, rel, explicit = found[key]
        if key in written and not explicit:
            skipped.append({"input": key, "status": "skipped", "error": f"{key}: an earlier run's output"})
            continue
        fmt, error, skip = _classify(path, explicit, source)
        if skip is not None:
            skipped.append({"input": key, "status": "skipped", "error": skip})
        else:
            classified[key] = (rel, fmt, error)
    # Inputs that would write the same output keep their own suffix in the output's name.
    names: dict[str, list[str]] = {}
    for key, (rel, _, _) in classified.items():
        names.setdefault(str(output_name(rel, to[0]) if to else rel), []).append(key)
    clash = {k for keys in names.values() if len(keys) > 1 for k in keys}
    planned = {
        key: tuple((fmt, os.path.join(out_real, output_name(rel, fmt, key in clash))) for fmt in to)
        for key, (rel, _, _) in classified.items()
    }
    all_outputs: dict[str, str] = {}
    for key, outs in planned.items():
        for _, p in outs:
            all_outputs.setdefault(p, key)
    explicit = {key for key, (_, _, given) in found.items() if given}
    for key, (_, fmt, error) in classified.items():
        hit = next(
            (p for _, p in planned[key] if p == key or (p in classified and (p not in written or p in explicit))), None
        )
        if error is None and hit is not None:
            error = f"--out: {hit} is an input file; name another --out"
        twin = next((all_outputs[p] for _, p in planned[key] if all_outputs[p] != key), None)
        if error is None and twin is not None:  # e.g. a/walk.npz and b/walk.npz given as files
            error = f"--out: {key} and {twin} would write the same outputs; convert them into separate --out folders"
        tasks.append(Task(key, fmt, planned[key], error))
    if shard is not None:
        tasks = tasks[shard[0] :: shard[1]]
    return tasks, skipped


# --------------------------------------------------------------------------- the per-file task


def _line(exc: BaseException, path: str | Path) -> str:
    """One line naming ``path``: the exception's message (first line), or an internal error's type."""
    msg = (str(exc).strip().splitlines() or [""])[0] or type(exc).__name__
    if not isinstance(exc, (ValueError, TypeError, OSError, KeyError, EOFError)):
        msg = f"internal error ({type(exc).__name__}: {msg})"
    elif isinstance(exc, OSError) and exc.strerror:
        msg = f"{exc.filename + ': ' if exc.filename else ''}{exc.strerror}"
    return msg if str(path) in msg or Path(path).name in msg else f"{path}: {msg}"


def _frames(path: Path, fmt: str) -> int | None:
    """Frames of an output file, read back (None for formats without a cheap reader here)."""
    import numpy as np

    from ..io.npz import read_npz

    if fmt in ("motion", "soma", "meshes"):
        key = {"motion": "pose", "soma": "poses", "meshes": "vertices"}[fmt]
        with read_npz(path) as data:
            return int(np.shape(data[key])[0])
    if fmt == "bvh":
        with open(path, encoding="latin-1") as f:
            for line in f:
                if line.strip().lower().startswith("frames:"):
                    return int(line.split(":", 1)[1])
    return None


def convert_file(task: Task, options: ConvertOptions, threads: int | None = None) -> dict:
    """Convert one file: read it, then write every output; never raises, returns its report record.

    Args:
        task: the file and its outputs.
        options: the run's options.
        threads: torch threads for this worker (None: leave as is).
    """
    import torch

    if threads:
        torch.set_num_threads(threads)
    t0 = time.perf_counter()
    record = _record(task, "failed")
    try:
        if task.error:
            raise ValueError(task.error)
        with _warnings.catch_warnings(record=True) as caught:
            _warnings.simplefilter("always")  # every file's own warnings, also ones seen before in this process
            _warnings.filterwarnings("ignore", category=DeprecationWarning)
            _warnings.filterwarnings("ignore", message="Sparse CSR tensor support is in beta")  # torch's notice
            converted = reader(task.format)(Path(task.input), options)
            motion = converted.motion
            record.update(frames=int(len(motion.pose)), fps=float(motion.fps), stats=dict(converted.stats))
            outputs = []
            for fmt, out in task.outputs:
                Path(out).parent.mkdir(parents=True, exist_ok=True)
                writer(fmt)(motion, Path(out), options)
                sha = file_sha256(out)
                outputs.append({"format": fmt, "path": out, "bytes": os.path.getsize(out), "sha256": sha})
        seen = [*converted.warnings, *(str(w.message).splitlines()[0] for w in caught)]
        record.update(status="ok", outputs=outputs, warnings=list(dict.fromkeys(seen)))
    except Exception as exc:  # noqa: BLE001 - a failing file is reported and the others go on
        record["error"] = _line(exc, task.input)
    record["seconds"] = round(time.perf_counter() - t0, 4)
    return record


def _record(task: Task, status: str) -> dict:
    try:
        st = os.stat(task.input)
        size, mtime = st.st_size, st.st_mtime_ns
    except OSError:
        size = mtime = None
    return {
        "input": task.input, "format": task.format, "status": status,
        "outputs": [{"format": f, "path": p} for f, p in task.outputs],
        "frames": None, "fps": None, "seconds": None, "stats": {}, "warnings": [], "error": None,
        "input_bytes": size, "input_mtime_ns": mtime,
    }  # fmt: skip


# --------------------------------------------------------------------------- resume


def _verified(task: Task, record: dict | None) -> bool:
    """Whether ``record`` (an earlier run's) finished ``task`` and its outputs are still those files."""
    if not record or record.get("status") != "ok" or task.error:
        return False
    now = _record(task, "ok")
    if (now["input_bytes"], now["input_mtime_ns"]) != (record.get("input_bytes"), record.get("input_mtime_ns")):
        return False
    outs = {(o.get("format"), o.get("path")): o for o in record.get("outputs") or []}
    if set(outs) != set(task.outputs):
        return False
    for (fmt, path), o in outs.items():
        try:
            if os.path.getsize(path) != o.get("bytes") or file_sha256(path) != o.get("sha256"):
                return False
            frames = _frames(Path(path), fmt)
        except (OSError, ValueError, KeyError):
            return False
        if frames is not None and frames != record.get("frames"):
            return False
    return True


def _refuse_unknown_outputs(task: Task, written: set[str], force: bool) -> Task:
    """``task`` with an error if it would replace a file that no earlier run in ``--out`` wrote."""
    if force or task.error:
        return task
    for _, path in task.outputs:
        if os.path.lexists(path) and path not in written:
            return Task(task.input, task.format, task.outputs, f"--out: {path} exists; pass --force to replace it")
    return task


# --------------------------------------------------------------------------- executors


def _threads(jobs: int) -> int:
    try:
        cores = len(os.sched_getaffinity(0))
    except AttributeError:  # not Linux
        cores = os.cpu_count() or 1
    return max(1, cores // jobs)


def _local(tasks: list[Task], options: ConvertOptions, jobs: int) -> Iterator[dict]:
    if jobs == 1 or len(tasks) <= 1:
        for task in tasks:
            yield convert_file(task, options)
        return
    import multiprocessing
    from concurrent.futures import ProcessPoolExecutor, as_completed

    threads = _threads(jobs)
    pool = ProcessPoolExecutor(max_workers=min(jobs, len(tasks)), mp_context=multiprocessing.get_context("spawn"))
    try:
        futures = {pool.submit(convert_file, t, options, threads): t for t in tasks}
        for fut in as_completed(futures):
            try:
                yield fut.result()
            except Exception as exc:  # noqa: BLE001 - a worker that died (killed, out of memory): that file failed
                yield _died(futures[fut], exc)
    finally:
        pool.shutdown(wait=True, cancel_futures=True)


def _died(task: Task, exc: BaseException) -> dict:
    record = _record(task, "failed")
    record["error"] = f"{task.input}: the worker running it died ({type(exc).__name__}: {str(exc)[:200]})"
    return record


RAY_MISSING = "--executor ray needs Ray: pip install 'unibody[ray]'"


def _ray(tasks: list[Task], options: ConvertOptions, jobs: int) -> Iterator[dict]:
    try:
        import ray
    except ImportError:
        raise ImportError(RAY_MISSING) from None
    started = not ray.is_initialized()
    if started:
        address = os.environ.get("RAY_ADDRESS")
        if address:
            ray.init(address=address, log_to_driver=False)
        else:
            ray.init(num_cpus=jobs, include_dashboard=False, log_to_driver=False)
    try:
        remote = ray.remote(num_cpus=1, max_retries=1)(convert_file)
        refs = {remote.remote(t, options, 1): t for t in tasks}
        pending = list(refs)
        while pending:
            done, pending = ray.wait(pending, num_returns=1)
            try:
                yield ray.get(done[0])
            except Exception as exc:  # noqa: BLE001 - a worker or node lost: that file failed
                yield _died(refs[done[0]], exc)
    finally:
        if started:
            ray.shutdown()


# --------------------------------------------------------------------------- the run


def run(
    inputs: Iterable[str | os.PathLike[str]],
    to: Iterable[str],
    out: str | os.PathLike[str],
    *,
    options: ConvertOptions | None = None,
    source: str | None = None,
    jobs: int = 1,
    shard: tuple[int, int] | None = None,
    executor: str = "local",
    force: bool = False,
    progress: bool = True,
    on_error: Callable[[str], None] | None = None,
) -> RunSummary:
    """Convert every motion file of ``inputs`` into each format of ``to`` under ``out``.

    Finished outputs of an earlier run (recorded in its report, still the same files) are
    skipped unless ``force``; a failing file is reported (``on_error``, one line) and the
    others go on; the JSON/CSV report is merged with the earlier one and written atomically,
    also when the run is interrupted.

    Raises:
        FileNotFoundError: an input does not exist.
        OutputError: ``out`` is not a folder, or another run writes the same report.
        ImportError: ``executor="ray"`` without Ray installed.
        ValueError: an unknown format, ``jobs < 1`` or a bad ``shard``.
    """
    options = options or ConvertOptions()
    to = tuple(to)
    bad = [f for f in to if f not in WRITERS]
    if not to or bad:
        raise ValueError(f"to: expected formats among {', '.join(WRITERS)}, got {', '.join(bad) or 'none'}")
    if jobs < 1 or executor not in ("local", "ray"):
        raise ValueError(f"expected jobs >= 1 and executor 'local' or 'ray', got {jobs} and {executor!r}")
    if shard is not None and not (0 <= shard[0] < shard[1]):
        raise ValueError(f"shard: expected i/N with 0 <= i < N, got {shard[0]}/{shard[1]}")
    out = Path(out)
    if out.exists() and not out.is_dir():
        raise OutputError(f"--out: {out} is a file; name a folder")
    t0 = time.perf_counter()
    inputs = [Path(p) for p in inputs]
    missing = next((p for p in inputs if not p.exists()), None)
    if missing is not None:
        raise FileNotFoundError(f"{missing}: no such file or folder")
    out.mkdir(parents=True, exist_ok=True)
    json_path, _, journal_path = report_paths(out, shard)
    with output_lock(json_path):
        records, notes = load_records(out, shard)
        for note in notes:
            _warnings.warn(note, stacklevel=2)
        known = all_records(out, shard)  # any earlier run's, whatever its sharding
        written = {o["path"] for r in known.values() for o in r.get("outputs") or [] if o.get("path")}
        tasks, skipped = plan(inputs, to, out, source=source, shard=shard, written=written)
        todo, done_before = [], 0
        for task in tasks:
            if not force and _verified(task, known.get(task.input)):
                done_before += 1
            else:
                todo.append(_refuse_unknown_outputs(task, written, force))
        for s in skipped:
            records[s["input"]] = s
        journal = Journal(journal_path)
        started = [_record(t, "running") for t in todo if not t.error]
        records.update((r["input"], r) for r in started)
        journal.append(*started)
        results: list[dict] = []
        try:
            _execute(todo, options, jobs, executor, progress, journal, records, results, on_error)
        finally:  # also on Ctrl-C: the report says what was done, the rerun does the rest
            summary = _finish(results, done_before, len(skipped), time.perf_counter() - t0, json_path)
            write_report(out, records, _summary_dict(summary, to, jobs, executor, shard), shard)
            journal.remove()
    return summary


def _execute(todo, options, jobs, executor, progress, journal, records, results, on_error) -> None:
    """Run the tasks; each record goes to ``records``, ``results`` and the journal as it comes."""
    from tqdm import tqdm

    bar = tqdm(total=len(todo), unit="file", desc="convert", file=sys.stderr, disable=not progress or not todo,
               dynamic_ncols=True, mininterval=0.5)  # fmt: skip
    t0 = time.perf_counter()
    frames = 0
    say = on_error or (lambda line: bar.write(f"unibody: error: {line}", file=sys.stderr))
    try:
        stream = (_ray if executor == "ray" else _local)(todo, options, jobs)
        for record in stream:
            results.append(record)
            records[record["input"]] = record
            journal.append(record)
            if record["status"] == "failed":
                say(record["error"])
            for w in record["warnings"]:
                bar.write(f"unibody: warning: {w}", file=sys.stderr)
            frames += record["frames"] or 0
            bar.set_postfix_str(f"{frames / max(time.perf_counter() - t0, 1e-9):,.0f} frames/s", refresh=False)
            bar.update(1)
    finally:
        bar.close()


def _finish(results: list[dict], done_before: int, skipped: int, seconds: float, report: Path) -> RunSummary:
    ok = [r for r in results if r["status"] == "ok"]
    failed = [r for r in results if r["status"] != "ok"]
    return RunSummary(
        converted=len(ok), failed=len(failed), done_before=done_before, skipped=skipped,
        frames=sum(r["frames"] or 0 for r in ok), seconds=seconds, report=report,
        errors=tuple(r["error"] or "" for r in failed),
    )  # fmt: skip


def _summary_dict(s: RunSummary, to, jobs, executor, shard) -> dict:
    return {
        "converted": s.converted, "failed": s.failed, "done_before": s.done_before, "skipped": s.skipped,
        "frames": s.frames, "seconds": round(s.seconds, 3), "to": list(to), "jobs": jobs, "executor": executor,
        "shard": None if shard is None else f"{shard[0]}/{shard[1]}",
    }  # fmt: skip
