"""Pose runs over a BOP dataset's targets, in this process or on Dask, streamed and resumable.

One task is one image (:func:`certpose.bop.pose.pose_image`): a worker receives the dataset's
path and the image's ids and targets, reads the image once, poses its targets and returns their
rows. The driver appends each image's rows to the results file and its side file as the image
finishes (:mod:`certpose.bop.results`), keeps at most two tasks per worker slot in flight, and
on ``resume`` runs only the images whose rows are not complete on disk. The embedded cluster is
the one ``certpose bench`` starts (one single-thread worker process per slot,
:func:`certpose.bench.runner._local_cluster`); every worker keeps its object models for the
tasks it runs next. A finished run's files are sorted by ``(scene_id, im_id, obj_id)``, so that
they do not depend on the order in which the images finished.
"""

from __future__ import annotations

import logging
import os
import time
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

__all__ = ["BOPRunInterrupted", "BOPRunSummary", "run_bop_poses"]

log = logging.getLogger(__name__)


CLUSTER_CONFIG: dict[str, Any] = {
    "distributed.admin.tick.interval": "1s",
    "distributed.worker.memory.monitor-interval": "1s",
    "distributed.scheduler.work-stealing-interval": "1s",
    "distributed.admin.system-monitor.interval": "2s",
}
"""Dask's periodic checks, slowed for the embedded cluster of a pose run: its tasks last
seconds, and at the defaults (every 20-500 ms in the scheduler, two workers and their nannies)
an idle two-worker cluster costs about 0.1 s of CPU a second, 40% more than at these values."""


class BOPRunInterrupted(Exception):
    """Ctrl-C during a run: the finished images' rows are on disk; the message says where."""


@dataclass(frozen=True)
class BOPRunSummary:
    """What a run did.

    Attributes
    ----------
    results, side : str
        The two files.
    images, targets : int
        Of the run (``targets`` counts instances: ``inst_count`` summed).
    skipped_images : int
        Already complete on disk (``resume``).
    posed, failed : int
        Instances posed in this run, and those of them that failed.
    wall_seconds : float
    workers : int or str
        ``0`` in process, the embedded cluster's size, or ``"scheduler"``.
    success : bool
        No instance failed.
    status, message : str
    """

    results: str
    side: str
    images: int
    targets: int
    skipped_images: int
    posed: int
    failed: int
    wall_seconds: float
    workers: int | str
    success: bool
    status: str
    message: str
    extra: dict[str, Any] = field(default_factory=dict)

    def to_dict(self) -> dict[str, Any]:
        return {k: getattr(self, k) for k in self.__dataclass_fields__}


def _tasks(targets: Sequence[Any]) -> list[tuple[int, int, list[tuple[int, int]]]]:
    from certpose.io.bop import group_targets

    return [(s, i, [(t.obj_id, t.inst_count) for t in ts])
            for (s, i), ts in sorted(group_targets(targets).items())]


def run_bop_poses(
    root: str | Path,
    results: str | Path,
    *,
    split: str = "test",
    targets: str | Path | None = None,
    params: Any = None,
    seed: int = 0,
    workers: int | None = 0,
    scheduler: str | None = None,
    resume: bool = False,
    force: bool = False,
    cache_dir: str | Path | None = None,
    particles_dir: str | Path | None = None,
    progress: Callable[[int], None] | None = None,
) -> BOPRunSummary:
    """Pose every target of a BOP dataset and write the BOP results file (see the module
    docstring).

    Parameters
    ----------
    root : path
        The BOP dataset folder.
    results : path
        The results CSV (its side file beside it, :func:`certpose.bop.results.side_path`).
    split : str
    targets : path, optional
        The targets file (default ``<root>/test_targets_bop19.json``).
    params : PoseParams, optional
    seed : int
        Every instance's seed.
    workers : int or None
        ``0``: in this process; ``N``: an embedded Dask cluster of ``N`` workers; ``None``:
        one per CPU core.
    scheduler : str, optional
        A running Dask scheduler's address (instead of ``workers``).
    resume, force : bool
        See :func:`certpose.bop.results.open_results`.
    cache_dir : path, optional
        The object-model cache (workers share it).
    particles_dir : path, optional
        Per-instance particles (with ``params.sampler``).
    progress : callable, optional
        Called with the number of instances of each finished image.

    Raises
    ------
    BOPRunInterrupted
        On Ctrl-C, after closing the files.
    """
    from certpose.bop.results import open_results, sort_results
    from certpose.estimation.pipeline import PoseParams
    from certpose.io.bop import BOPDataset

    params = params or PoseParams()
    root = Path(root).resolve()
    ds = BOPDataset(root, split)
    tasks = _tasks(ds.targets(targets))
    expected = {(s, i): sum(c for _, c in ts) for s, i, ts in tasks}
    bop_w, side_w, done = open_results(results, expected, resume=resume, force=force)
    todo = [t for t in tasks if (t[0], t[1]) not in done]
    n_targets = sum(expected.values())
    if progress is not None and done:
        progress(sum(expected[k] for k in done if k in expected))
    kwargs = {"params": params, "seed": int(seed),
              "cache_dir": None if cache_dir is None else str(cache_dir),
              "particles_dir": None if particles_dir is None else str(particles_dir)}
    counts = {"posed": 0, "failed": 0}

    def emit(rows: tuple[list[dict[str, Any]], list[dict[str, Any]]]) -> None:
        bop_rows, side_rows = rows
        side_w.write_many(side_rows)  # the ledger first: resume checks the results against it
        bop_w.write_many(bop_rows)
        counts["posed"] += len(side_rows)
        counts["failed"] += sum(not r.get("success") for r in side_rows)
        if progress is not None:
            progress(len(side_rows))

    t0 = time.perf_counter()
    finished = False
    try:
        if scheduler is None and workers == 0:
            for s, i, ts in todo:
                emit(_pose_task(str(root), split, s, i, ts, kwargs))
        else:
            _run_dask(todo, str(root), split, kwargs, workers=workers, scheduler=scheduler,
                      emit=emit)
        finished = True
    except KeyboardInterrupt:
        raise BOPRunInterrupted(
            f"interrupted: {counts['posed']} new instance row(s) written to {results}; run "
            "again with --resume to finish.") from None
    finally:
        bop_w.close()
        side_w.close()
    if finished:
        sort_results(results)
    wall = time.perf_counter() - t0
    failed = counts["failed"]
    return BOPRunSummary(
        str(results), str(side_w.path), len(tasks), n_targets, len(done), counts["posed"],
        failed, wall, "scheduler" if scheduler is not None else (
            os.cpu_count() or 1 if workers is None else workers),
        failed == 0, "ok" if failed == 0 else "failures",
        f"{counts['posed']} instance(s) of {len(todo)} image(s) posed, {failed} failed; "
        f"{len(done)} image(s) already complete")


def _pose_task(root: str, split: str, scene_id: int, im_id: int,
               targets: list[tuple[int, int]], kwargs: dict[str, Any]
               ) -> tuple[list[dict[str, Any]], list[dict[str, Any]]]:
    from certpose.bop.pose import pose_image

    return pose_image(root, split, scene_id, im_id, targets, **kwargs)


def _one_thread_open3d() -> None:
    """Open3D's parallel loops on one thread in an embedded worker (its TBB pool takes every
    core by default and ignores the worker's thread variables): the worker is one of one
    single-thread worker per core. The poses do not depend on it (the benchmark and the tests
    compare the rows with those of an in-process run)."""
    try:
        import open3d as o3d
    except ImportError:
        return
    o3d.utility.set_max_threads(1)


def _run_dask(todo: Sequence[tuple[int, int, list[tuple[int, int]]]], root: str, split: str,
              kwargs: dict[str, Any], *, workers: int | None, scheduler: str | None,
              emit: Callable[[Any], None]) -> None:
    """Images on Dask, at most two per worker slot in flight, rows emitted as each finishes."""
    from certpose.bench.rows import bench_extra
    from certpose.bench.runner import _ignore_sigint, _local_cluster

    distributed = bench_extra("distributed", "certpose pose --bop on Dask")
    if not log.isEnabledFor(logging.DEBUG):
        logging.getLogger("distributed").setLevel(logging.WARNING)
    if scheduler is not None:
        cluster, client = None, distributed.Client(scheduler)
    else:
        import dask

        with dask.config.set(CLUSTER_CONFIG):
            cluster = _local_cluster(workers or os.cpu_count() or 1)
            client = distributed.Client(cluster)
        client.run(_ignore_sigint)
        client.run(_one_thread_open3d)
    try:
        slots = max(sum(client.nthreads().values()), 1)
        # Images with the most targets first: the last tasks are short, the workers end together.
        items: Iterator[Any] = iter(sorted(todo, key=lambda t: -sum(c for _, c in t[2])))

        def submit(task: Any) -> Any:
            s, i, ts = task
            return client.submit(_pose_task, root, split, s, i, ts, kwargs, pure=False,
                                 retries=1, key=f"bop-pose-{s}-{i}-{time.monotonic_ns()}")

        pending = distributed.as_completed([submit(t) for _, t in zip(range(2 * slots), items,
                                                                         strict=False)])
        for fut in pending:
            rows = fut.result()
            fut.release()
            emit(rows)
            nxt = next(items, None)
            if nxt is not None:
                pending.add(submit(nxt))
    except KeyboardInterrupt:
        logging.getLogger("distributed").setLevel(logging.CRITICAL)
        raise
    finally:
        client.close()
        if cluster is not None:
            cluster.close()
