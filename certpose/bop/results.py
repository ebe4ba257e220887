"""BOP results files: the challenge's CSV and certpose's side file, streamed and resumable.

The results file has BOP 2019's columns ``scene_id,im_id,obj_id,score,R,t,time``: ``R`` the
nine entries of ``R_camera_object`` row-major and ``t`` the translation in millimetres, each
space-separated, ``time`` the seconds the whole image took (the same on every row of an
image). The side file (``<results>.certpose.csv``) has one row per target instance, including
those that failed: the certificate, its gap, the number of eq. (1) modes, the sampler's ESS,
the errors against the ground truth. Rows go to disk image by image (each image's rows with
one flush, :class:`certpose.bench.rows.RowWriter`); a resumed run keeps the images whose rows
are complete in both files and drops the others (a run killed mid-image).
"""

from __future__ import annotations

import csv
import logging
import math
import os
import tempfile
from collections.abc import Iterable
from pathlib import Path
from typing import Any

import numpy as np

from certpose.io.bop import MM

__all__ = ["BOP_COLUMNS", "SIDE_COLUMNS", "side_path", "bop_row_cells", "read_bop_results",
           "open_results"]

log = logging.getLogger(__name__)

BOP_COLUMNS = ("scene_id", "im_id", "obj_id", "score", "R", "t", "time")
"""The BOP 2019 results file's columns."""

SIDE_COLUMNS = ("scene_id", "im_id", "obj_id", "gt_id", "success", "status", "score",
                "log_likelihood", "certified", "relative_gap", "lower_bound", "upper_bound",
                "modes", "ess", "pareto_k", "add_s_mm", "add_mm", "rotation_error_deg",
                "seconds", "particles", "error")
"""certpose's own columns, one row per target instance (``score`` = eq. (1) at the pose)."""


def side_path(results: str | os.PathLike[str]) -> Path:
    """The side file of a results file: ``results.csv`` -> ``results.certpose.csv``."""
    p = Path(results)
    return p.with_name(p.stem + ".certpose" + (p.suffix or ".csv"))


def bop_row_cells(T_camera_object: np.ndarray) -> tuple[str, str]:
    """``R`` (row-major) and ``t`` (millimetres) cells of a pose in metres, full precision."""
    T = np.asarray(T_camera_object, dtype=np.float64)
    return (" ".join(repr(float(v)) for v in T[:3, :3].ravel()),
            " ".join(repr(float(v) * MM) for v in T[:3, 3]))


def _complete_rows(path: Path) -> tuple[list[str], list[dict[str, str]]]:
    """Header and the rows of complete lines (a killed writer's half line is ignored)."""
    from certpose.bench.rows import _complete_lines

    with path.open(newline="", encoding="utf-8") as fh:
        lines = list(_complete_lines(fh))
    if not lines:
        return [], []
    reader = csv.DictReader(lines)
    return list(reader.fieldnames or []), list(reader)


def read_bop_results(path: str | os.PathLike[str]) -> list[dict[str, Any]]:
    """Read a BOP 2019 results CSV: ``scene_id, im_id, obj_id`` (int), ``score``, ``time``
    (float), ``R`` (3, 3), ``t`` (3,) in metres (converted from the file's millimetres).

    Raises
    ------
    FileNotFoundError
    ValueError
        Other columns, or a malformed row (naming the line).
    """
    p = Path(path)
    if not p.is_file():
        raise FileNotFoundError(f"The results file {p} does not exist.")
    header, rows = _complete_rows(p)
    if tuple(header) != BOP_COLUMNS:
        raise ValueError(f"{p} is not a BOP results file: expected the columns "
                         f"{','.join(BOP_COLUMNS)}, got {','.join(header) or 'nothing'}.")
    out = []
    for k, r in enumerate(rows, start=2):
        try:
            R = np.array([float(v) for v in r["R"].split()]).reshape(3, 3)
            t = np.array([float(v) for v in r["t"].split()]).reshape(3) / MM
            out.append({"scene_id": int(r["scene_id"]), "im_id": int(r["im_id"]),
                        "obj_id": int(r["obj_id"]), "score": float(r["score"]),
                        "time": float(r["time"]), "R": R, "t": t})
        except (ValueError, TypeError, AttributeError) as exc:
            raise ValueError(f"{p}, line {k}: not a valid BOP row ({exc}).") from None
    return out


def _rewrite(path: Path, columns: tuple[str, ...], rows: Iterable[dict[str, str]]) -> None:
    fd, tmp = tempfile.mkstemp(dir=path.parent, suffix=".tmp")
    with os.fdopen(fd, "w", newline="", encoding="utf-8") as fh:
        w = csv.DictWriter(fh, fieldnames=list(columns), lineterminator="\n")
        w.writeheader()
        w.writerows(rows)
        fh.flush()
        os.fsync(fh.fileno())
    os.replace(tmp, path)


def open_results(results: str | os.PathLike[str], expected: dict[tuple[int, int], int], *,
                 resume: bool = False, force: bool = False) -> tuple[Any, Any, set[tuple[int, int]]]:
    """Open the results file and its side file for a new or a resumed run, before any work.

    Parameters
    ----------
    results : path
        The BOP results CSV; its side file is :func:`side_path`.
    expected : dict of (scene_id, im_id) to int
        The number of target instances (side rows) of each image of the run.
    resume : bool
        Keep the images whose rows are complete in both files; drop the others.
    force : bool
        Overwrite existing files.

    Returns
    -------
    bop_writer, side_writer : RowWriter
    done : set of (scene_id, im_id)
        Images already complete.

    Raises
    ------
    FileExistsError
        The results file exists and neither ``resume`` nor ``force`` is given.
    ValueError
        ``resume`` with ``force``; files of another format; a resumed side file with an image
        of the run holding more rows than its targets (another run's file).
    """
    from certpose.bench.rows import RowWriter

    if resume and force:
        raise ValueError("--resume and --force exclude each other (keep the rows, or delete them).")
    res, side = Path(results), side_path(results)
    existing = [p for p in (res, side) if p.exists()]
    if existing and not (resume or force):
        raise FileExistsError(f"{existing[0]} already exists; pass --resume to continue that run "
                              "or --force to overwrite it.")
    if not (resume and existing):
        return (RowWriter(res, BOP_COLUMNS, append=False),
                RowWriter(side, SIDE_COLUMNS, append=False), set())
    bop_rows, side_rows = [], []
    headed = 0  # files with their header line
    for p, cols, store in ((res, BOP_COLUMNS, bop_rows), (side, SIDE_COLUMNS, side_rows)):
        if not p.exists():
            continue
        header, rows = _complete_rows(p)
        headed += bool(header)
        if header and tuple(header) != cols:
            raise ValueError(f"cannot resume: {p} has the columns {','.join(header)}, not "
                             f"{','.join(cols)}.")
        store.extend(r for r in rows if None not in r.values())

    def key(r: dict[str, str]) -> tuple[int, int]:
        return int(r["scene_id"]), int(r["im_id"])

    n_side: dict[tuple[int, int], int] = {}
    n_ok: dict[tuple[int, int], int] = {}
    for r in side_rows:
        n_side[key(r)] = n_side.get(key(r), 0) + 1
        n_ok[key(r)] = n_ok.get(key(r), 0) + (r["success"] == "True")
    n_bop: dict[tuple[int, int], int] = {}
    for r in bop_rows:
        n_bop[key(r)] = n_bop.get(key(r), 0) + 1
    for k, n in n_side.items():
        if k in expected and n > expected[k]:
            raise ValueError(f"cannot resume: {side} holds {n} rows for scene {k[0]}, image "
                             f"{k[1]}, which has {expected[k]} target instance(s).")
    done = {k for k, n in n_side.items()
            if n == expected.get(k, -1) and n_bop.get(k, 0) == n_ok.get(k, 0)}
    dropped = len(side_rows) - sum(n_side[k] for k in done)
    if dropped or len(bop_rows) != sum(n_bop.get(k, 0) for k in done) or headed < 2:
        log.info("resume: dropping the rows of %d unfinished image(s)",
                 len(set(n_side) | set(n_bop) - done))
        _rewrite(res, BOP_COLUMNS, (r for r in bop_rows if key(r) in done))
        _rewrite(side, SIDE_COLUMNS, (r for r in side_rows if key(r) in done))
    bop_w = RowWriter(res, BOP_COLUMNS, append=True)
    side_w = RowWriter(side, SIDE_COLUMNS, append=True)
    bop_w.initial = sum(n_bop.get(k, 0) for k in done)
    side_w.initial = sum(n_side[k] for k in done)
    return bop_w, side_w, done


def sort_results(results: str | os.PathLike[str]) -> None:
    """Rewrite a finished run's two files sorted by ``(scene_id, im_id, obj_id)`` (the order
    of a run on Dask is the order its images finished)."""
    for p, cols in ((Path(results), BOP_COLUMNS), (side_path(results), SIDE_COLUMNS)):
        _, rows = _complete_rows(p)
        rows.sort(key=lambda r: (int(r["scene_id"]), int(r["im_id"]), int(r["obj_id"]),
                                 -_float(r.get("score", "")), r.get("gt_id", "")))
        _rewrite(p, cols, rows)


def _float(text: str) -> float:
    try:
        v = float(text)
    except ValueError:
        return -math.inf
    return v if math.isfinite(v) else -math.inf
