"""The per-file report of a conversion run: ``convert_report.json`` and ``.csv`` in ``--out``.

One record per input file: ``input``, ``format`` (detected), ``status`` ("ok", "failed",
"skipped": not a motion file, "running": started by a run that did not finish), ``outputs``
(format, path, bytes, sha256), ``frames``, ``fps``, ``seconds``, ``stats`` (the reader's
``Converted.stats``), ``warnings``, ``error``, and the input's size and modification time (a
changed input is converted again). While a run works, each record is also appended to a journal
(``convert_report.journal``, JSON lines), so a killed run loses nothing of what it finished; the
next run merges the journal and the previous report, and the final report replaces both. Shards
of an array job keep their own files (``convert_report.<i>of<N>.json``, ...).
"""

from __future__ import annotations

import csv
import io
import json
import os
import re
from pathlib import Path

from ..io.atomic import atomic_write

__all__ = ["REPORT_FORMAT", "Journal", "all_records", "load_records", "report_paths", "write_report"]

REPORT_FORMAT = "unibody.convert_report/1"
_BASE = ("input", "format", "status", "outputs", "frames", "fps", "seconds", "warnings", "error")


def report_paths(out: Path, shard: tuple[int, int] | None = None) -> tuple[Path, Path, Path]:
    """The JSON report, the CSV report and the journal of a run (of one shard) writing to ``out``."""
    stem = "convert_report" if shard is None else f"convert_report.{shard[0]}of{shard[1]}"
    return out / f"{stem}.json", out / f"{stem}.csv", out / f"{stem}.journal"


def load_records(out: Path, shard: tuple[int, int] | None = None) -> tuple[dict[str, dict], list[str]]:
    """Records of earlier runs by input (the report, then the journal; later wins), and warnings.

    A damaged report or journal line is not an error: its records are simply redone.
    """
    json_path, _, journal = report_paths(out, shard)
    records: dict[str, dict] = {}
    notes = []
    if json_path.exists():
        try:
            data = json.loads(json_path.read_text())
            if data.get("format") != REPORT_FORMAT:
                raise ValueError(f"format {data.get('format')!r}")
            records.update({r["input"]: r for r in data["files"]})
        except (OSError, ValueError, KeyError, TypeError) as exc:
            notes.append(f"{json_path} is not used ({type(exc).__name__}: {exc}); its files are converted again")
    if journal.exists():
        try:
            lines = journal.read_text().splitlines()
        except (OSError, UnicodeDecodeError) as exc:
            notes.append(f"{journal} is not used ({exc})")
            lines = []
        for line in lines:
            try:
                record = json.loads(line)
                records[record["input"]] = record
            except (ValueError, KeyError, TypeError):
                continue  # the line a kill cut short
    return records, notes


class Journal:
    """Append-only JSON lines, flushed to disk per call: what a killed run had finished."""

    def __init__(self, path: Path) -> None:
        self.path = path

    def append(self, *records: dict) -> None:
        if not records:
            return
        text = "".join(json.dumps(r, sort_keys=True) + "\n" for r in records)
        with open(self.path, "a", encoding="utf-8") as f:
            f.write(text)
            f.flush()
            os.fsync(f.fileno())

    def remove(self) -> None:
        self.path.unlink(missing_ok=True)


def _csv(records: list[dict]) -> str:
    stats = sorted({k for r in records for k in (r.get("stats") or {})} - set(_BASE))
    buf = io.StringIO()
    w = csv.writer(buf)
    w.writerow([*_BASE, *stats])
    for r in records:
        row = [r.get(k) for k in _BASE]
        row[3] = ";".join(o["path"] for o in r.get("outputs") or [])
        row[7] = " | ".join(r.get("warnings") or [])
        row = ["" if v is None else v for v in row]
        w.writerow([*row, *("" if (v := (r.get("stats") or {}).get(k)) is None else v for k in stats)])
    return buf.getvalue()


def write_report(out: Path, records: dict[str, dict], summary: dict, shard: tuple[int, int] | None = None) -> Path:
    """Write the JSON and CSV reports atomically (records sorted by input); return the JSON path."""
    json_path, csv_path, _ = report_paths(out, shard)
    rows = [records[k] for k in sorted(records)]
    body = {"format": REPORT_FORMAT, "summary": summary, "files": rows}
    with atomic_write(json_path, "w") as f:
        json.dump(body, f, indent=1, sort_keys=True, default=str)
    with atomic_write(csv_path, "w") as f:
        f.write(_csv(rows))
    return json_path


def all_records(out: Path, shard: tuple[int, int] | None = None) -> dict[str, dict]:
    """Records of every report in ``out`` (the whole run's and each shard's), ``shard``'s own last.

    What any earlier run of this folder finished or wrote, whatever its sharding: finished files
    are not redone and the files it wrote are known as outputs, not inputs.
    """
    found = set()
    for name in sorted(os.listdir(out)) if out.is_dir() else []:
        m = re.fullmatch(r"convert_report(?:\.(\d+)of(\d+))?\.(?:json|journal)", name)
        if m:
            found.add(None if m.group(1) is None else (int(m.group(1)), int(m.group(2))))
    records: dict[str, dict] = {}
    for key in sorted(found - {shard}, key=str):
        records.update(load_records(out, key)[0])
    records.update(load_records(out, shard)[0])
    return records
