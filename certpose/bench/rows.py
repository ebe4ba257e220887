"""The benchmark's row file: one CSV line per (instance, solver), appended as each row finishes.

Every row is flushed to the operating system before the next one is written, so a run killed
at any moment (even with SIGKILL) leaves complete rows plus at most one truncated last line;
:func:`open_rows` drops that line when a run is resumed. The file is also ``fsync``-ed at most
once a second and on close, against a crash of the machine itself (an ``fsync`` per row cost
2-4 ms here: 10-20 s of a 5,000-row run in one process). A row is keyed by ``(suite, instance,
solver)``. Nothing here holds the rows in memory: they are read one at a time (:func:`iter_rows`).

The file opens with :func:`pandas.read_csv` (``certified`` is empty when the solver gives no
certificate).
"""

from __future__ import annotations

import csv
import json
import logging
import math
import os
import time
from collections.abc import Iterable, Iterator, Sequence
from pathlib import Path
from typing import Any

__all__ = ["TRIAL_COLUMNS", "bench_extra", "ROWS_FILE", "MANIFEST_FILE", "RowWriter", "read_rows", "iter_rows", "open_rows",
           "row_key", "count_rows"]

log = logging.getLogger(__name__)

TRIAL_COLUMNS = (
    "suite",
    "instance",
    "instance_seed",
    "solver",
    "n",
    "outlier_ratio",
    "trial",
    "success",
    "rotation_error_deg",
    "translation_error",
    "time_ms",
    "reported_time_ms",
    "cost",
    "status",
    "certified",
    "cert_problem",
    "lower_bound",
    "upper_bound",
    "relative_gap",
    "error",
)
"""Columns of the row file, one row per (instance, solver)."""

ROWS_FILE = "trials.csv"
"""Name of the streamed row file inside the output folder."""
MANIFEST_FILE = "run.json"
"""What the rows were drawn with (shape, noise): a resumed run must match it."""
RESULT_FILES = (ROWS_FILE, MANIFEST_FILE, "summary.csv", "bench.json", "bench.png",
                "certificates.png", "report.md")
"""Files of a result set; any of them present means the folder holds a previous run."""

_INT = ("instance_seed", "n", "trial")
_FLOAT = ("outlier_ratio", "rotation_error_deg", "translation_error", "time_ms",
          "reported_time_ms", "cost", "lower_bound", "upper_bound", "relative_gap")


def bench_extra(module: str, what: str) -> Any:
    """Import ``module`` of the ``bench`` extra, or say how to install it."""
    import importlib

    try:
        return importlib.import_module(module)
    except ImportError as exc:
        raise ImportError(f"{what} needs {module.split('.')[0]}, part of the bench extra: "
                          f"pip install 'certpose[bench]'") from exc


def row_key(row: dict[str, Any]) -> tuple[str, str, str]:
    """``(suite, instance, solver)``: what identifies a row across runs."""
    return (str(row["suite"]), str(row["instance"]), str(row["solver"]))


def _parse(row: dict[str, str]) -> dict[str, Any]:
    out: dict[str, Any] = dict(row)
    for k in _INT:
        out[k] = int(row[k])
    for k in _FLOAT:
        out[k] = float(row[k])
    out["success"] = row["success"] == "True"
    out["certified"] = None if row["certified"] == "" else row["certified"] == "True"
    return out


def read_rows(path: str | os.PathLike[str], columns: Sequence[str]) -> list[dict[str, Any]]:
    """Rows of a row file with their types, ignoring a truncated last line.

    Raises
    ------
    ValueError
        One line naming the file when it is not a row file with ``columns``.
    """
    return list(iter_rows(path, columns))


def iter_rows(path: str | os.PathLike[str], columns: Sequence[str]) -> Iterator[dict[str, Any]]:
    """Rows of a row file, one at a time, with their types; a truncated last line (no newline)
    is ignored.

    Raises
    ------
    FileNotFoundError
        No such file.
    ValueError
        One line naming the file (and line) when it is not a row file with ``columns``.
    """
    p = Path(path)
    if not p.is_file():
        raise FileNotFoundError(f"row file '{p}' does not exist.")
    with p.open(newline="", encoding="utf-8") as fh:
        lines = _complete_lines(fh)
        try:
            reader = csv.DictReader(lines)
            fields = reader.fieldnames
        except (UnicodeDecodeError, csv.Error) as exc:
            raise ValueError(f"'{p}' is not a certpose bench row file ({exc}).") from None
        if tuple(fields or ()) != tuple(columns):
            raise ValueError(
                f"'{p}' is not a certpose bench row file: expected the columns "
                f"{', '.join(columns)}, got {', '.join(fields or ['nothing'])}."
            )
        lineno = 1
        try:
            for row in reader:
                lineno += 1
                if None in row or any(v is None for v in row.values()):
                    raise ValueError(f"{len(row)} fields instead of {len(columns)}")
                yield _parse(row)
        except (KeyError, TypeError, ValueError, UnicodeDecodeError, csv.Error) as exc:
            raise ValueError(f"'{p}' line {lineno} is not a valid row: {exc}") from None


def _complete_lines(fh: Any) -> Iterator[str]:
    for line in fh:
        if line.endswith("\n"):  # a killed run may leave half a line
            yield line


def count_rows(path: str | os.PathLike[str]) -> int:
    """Number of complete rows of a row file (header excluded)."""
    with Path(path).open(newline="", encoding="utf-8") as fh:
        return max(sum(1 for _ in _complete_lines(fh)) - 1, 0)


class RowWriter:
    """Append rows to a CSV file, each flushed as it is written; ``fsync``-ed every
    ``sync_seconds`` at most and on close."""

    def __init__(self, path: Path, columns: Sequence[str], *, append: bool,
                 sync_seconds: float = 1.0) -> None:
        self.path = path
        self.sync_seconds = sync_seconds
        self._synced = -math.inf
        self.columns = tuple(columns)
        self.count = 0
        self.initial = 0  # rows already in the file when it was opened
        self._fh = path.open("a" if append else "w", newline="", encoding="utf-8")
        self._csv = csv.DictWriter(self._fh, fieldnames=list(columns), extrasaction="ignore",
                                   lineterminator="\n")
        if not append:
            self._csv.writeheader()
            self._sync()

    def write(self, row: dict[str, Any]) -> None:
        self._csv.writerow({k: _cell(row.get(k)) for k in self.columns})
        self._sync()
        self.count += 1

    def write_many(self, rows: Iterable[dict[str, Any]]) -> None:
        """Write rows that finished together (a Dask batch) with one flush."""
        for row in rows:
            self._csv.writerow({k: _cell(row.get(k)) for k in self.columns})
            self.count += 1
        self._sync()

    def _sync(self, *, force: bool = False) -> None:
        self._fh.flush()  # in the OS's hands: survives the death of this process
        now = time.monotonic()
        if force or now - self._synced >= self.sync_seconds:
            os.fsync(self._fh.fileno())
            self._synced = now

    def close(self) -> None:
        if not self._fh.closed:
            self._sync(force=True)
            self._fh.close()

    def __enter__(self) -> RowWriter:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def _cell(value: Any) -> Any:
    if value is None:
        return ""
    if isinstance(value, str):
        # One row per line, always: a truncated last line is then the only partial record.
        return " ".join(value.splitlines())
    if isinstance(value, float) and math.isnan(value):
        return "nan"
    return value


def _end_of_last_line(path: Path) -> int:
    """Byte offset just past the file's last newline (0 if it has none), reading its tail."""
    with path.open("rb") as fh:
        end = fh.seek(0, os.SEEK_END)
        pos = end
        while pos > 0:
            step = min(pos, 1 << 16)
            fh.seek(pos - step)
            chunk = fh.read(step)
            k = chunk.rfind(b"\n")
            if k >= 0:
                return pos - step + k + 1
            pos -= step
    return 0


def open_rows(
    out_dir: str | os.PathLike[str],
    columns: Sequence[str],
    manifest: dict[str, Any],
    *,
    resume: bool = False,
    force: bool = False,
) -> tuple[RowWriter, set[tuple[str, str, str]]]:
    """Open the row file of ``out_dir`` for a new or a resumed run, before any work.

    Parameters
    ----------
    out_dir : path
        Output folder; created if missing.
    columns : sequence of str
        The row file's columns.
    manifest : dict
        What the rows are drawn with; stored as ``run.json``, and compared on ``resume``.
    resume : bool
        Keep the rows already present (a truncated last line is dropped).
    force : bool
        Delete a previous result set in ``out_dir``.

    Returns
    -------
    writer : RowWriter
    done : set of (suite, instance, solver)
        Keys of the rows already present (empty unless ``resume``); the rows are checked one
        at a time, not kept.

    Raises
    ------
    FileExistsError
        ``out_dir`` holds a result set and neither ``resume`` nor ``force`` is given.
    ValueError
        ``resume`` and ``force`` together; a resumed folder drawn with another manifest.
    """
    if resume and force:
        raise ValueError("--resume and --force exclude each other (keep the rows, or delete them).")
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    rows_path, manifest_path = out / ROWS_FILE, out / MANIFEST_FILE
    existing = [name for name in RESULT_FILES if (out / name).exists()]
    if existing and not (resume or force):
        raise FileExistsError(
            f"'{out}' already holds bench results ({', '.join(existing)}); pass --resume to "
            "continue that run or --force to overwrite it."
        )
    if force:
        for name in existing:
            (out / name).unlink()
        existing = []
    manifest = json.loads(json.dumps(manifest))  # the form it is stored in
    done: set[tuple[str, str, str]] = set()
    if resume and rows_path.exists():
        if manifest_path.exists():
            try:
                old = json.loads(manifest_path.read_text(encoding="utf-8"))
            except (json.JSONDecodeError, UnicodeDecodeError) as exc:
                raise ValueError(f"cannot resume '{out}': {manifest_path.name} is not valid "
                                 f"JSON ({exc}).") from None
            if not isinstance(old, dict):
                raise ValueError(f"cannot resume '{out}': {manifest_path.name} is not a "
                                 "certpose bench manifest.")
            if old != manifest:
                diff = sorted(k for k in set(old) | set(manifest) if old.get(k) != manifest.get(k))
                raise ValueError(
                    f"cannot resume '{out}': it was run with other {', '.join(diff)} "
                    f"({', '.join(f'{k}={old.get(k)!r}' for k in diff)})."
                )
        cut = _end_of_last_line(rows_path)
        if cut > 0:
            done = {row_key(r) for r in iter_rows(rows_path, columns)}
            if cut < rows_path.stat().st_size:
                log.info("dropping a truncated last line of %s", rows_path)
                with rows_path.open("r+b") as fh:
                    fh.truncate(cut)
            writer = RowWriter(rows_path, columns, append=True)
            writer.initial = count_rows(rows_path)
        else:  # killed before the header was complete
            writer = RowWriter(rows_path, columns, append=False)
    else:
        writer = RowWriter(rows_path, columns, append=False)
    from certpose.io.output import write_text_atomic

    write_text_atomic(manifest_path, json.dumps(manifest, indent=2) + "\n")
    return writer, done
