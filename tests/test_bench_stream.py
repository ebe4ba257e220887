"""``certpose bench`` at scale: rows streamed to disk, resume after a kill, overwrite refusal,
and the Dask path (a real ``distributed.LocalCluster``) giving the in-process rows."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from certpose.bench.rows import open_rows, read_rows
from certpose.bench.runner import TRIAL_COLUMNS, BenchConfig, instance_seed, run_benchmark
from certpose.cli import main

ROOT = Path(__file__).resolve().parents[1]
# Wall-clock times differ from run to run; every other column is a function of the seeds.
TIMES = ["time_ms", "reported_time_ms"]
TINY = ["bench", "--n", "15", "--outlier-ratios", "0", "0.5", "--trials", "2", "--seed", "4",
        "--solvers", "gnc", "gnc-only", "--no-progress"]


def _rows(path: Path) -> pd.DataFrame:
    """The row file without the timing columns, in a canonical order."""
    df = pd.read_csv(path, keep_default_na=False, dtype=str).drop(columns=TIMES)
    return df.sort_values(["suite", "instance", "solver"]).reset_index(drop=True)


def test_rows_stream_and_overwrite_needs_force(tmp_path, capsys):
    out = tmp_path / "res"
    assert main([*TINY, "--out", str(out), "--workers", "0"]) == 0
    first = (out / "trials.csv").read_text()
    df = pd.read_csv(out / "trials.csv")
    assert list(df.columns) == list(TRIAL_COLUMNS)
    assert len(df) == 2 * 2 * 2 and df.groupby(["suite", "instance", "solver"]).ngroups == 8
    capsys.readouterr()

    # Another run into the same folder is refused, and the rows are untouched.
    assert main([*TINY, "--seed", "5", "--out", str(out), "--workers", "0"]) == 2
    err = capsys.readouterr().err.strip()
    assert "already holds bench results" in err and "--force" in err and "\n" not in err
    assert (out / "trials.csv").read_text() == first

    assert main([*TINY, "--seed", "5", "--out", str(out), "--workers", "0", "--force"]) == 0
    df5 = pd.read_csv(out / "trials.csv")
    assert len(df5) == 8
    assert set(df5["instance_seed"]).isdisjoint(set(df["instance_seed"]))
    assert main([*TINY, "--out", str(out), "--force", "--resume"]) == 2
    assert "exclude each other" in capsys.readouterr().err


def test_output_folder_checked_before_any_work(tmp_path, capsys):
    # Nothing listens on port 1: had the run started (Dask client, warm-up), the error would be
    # about the connection, not about the folder.
    nowhere = ["--scheduler", "tcp://127.0.0.1:1"]
    a_file = tmp_path / "file.txt"
    a_file.write_text("not a folder")
    assert main([*TINY, "--out", str(a_file), *nowhere]) == 2
    assert "is not a directory" in capsys.readouterr().err

    out = tmp_path / "res"
    assert main([*TINY, "--out", str(out), "--workers", "0"]) == 0
    capsys.readouterr()
    assert main([*TINY, "--out", str(out), *nowhere]) == 2
    assert "already holds bench results" in capsys.readouterr().err


def test_resume_drops_a_truncated_last_line_and_refuses_other_noise(tmp_path):
    config = BenchConfig(n_values=(12,), outlier_ratios=(0.25,), trials=3, seed=2,
                         solvers=("gnc-only",))
    out = tmp_path / "res"
    full = run_benchmark(config, progress=False, out_dir=out)
    path = out / "trials.csv"
    lines = path.read_text().splitlines(keepends=True)
    assert len(lines) == 4
    # As if killed while writing the third row.
    path.write_text("".join(lines[:3]) + lines[3][:25])
    assert len(read_rows(path, TRIAL_COLUMNS)) == 2
    resumed = run_benchmark(config, progress=False, out_dir=out, resume=True)
    assert _rows(path).equals(_rows_of(full.trials, tmp_path))
    assert len(resumed.trials) == 3 and path.read_text().count("\n") == 4

    other = BenchConfig(n_values=(12,), outlier_ratios=(0.25,), trials=3, seed=2, noise=0.02,
                        solvers=("gnc-only",))
    with pytest.raises(ValueError, match="cannot resume .* noise"):
        run_benchmark(other, progress=False, out_dir=out, resume=True)


def test_each_row_is_in_the_file_as_soon_as_it_is_written(tmp_path):
    from certpose.bench.rows import RowWriter, count_rows

    path = tmp_path / "trials.csv"
    row = dict.fromkeys(TRIAL_COLUMNS, 1)
    with RowWriter(path, TRIAL_COLUMNS, append=False, sync_seconds=3600) as w:
        for k in range(3):
            w.write(row)
            assert count_rows(path) == k + 1  # another process (a resume) sees it now
        w.write_many([row, row])
        assert count_rows(path) == 5


def test_open_rows_rejects_a_foreign_file(tmp_path):
    (tmp_path / "trials.csv").write_text("a,b\n1,2\n")
    with pytest.raises(ValueError, match="not a certpose bench row file"):
        open_rows(tmp_path, TRIAL_COLUMNS, {}, resume=True)


def test_instance_seed_is_a_pure_function_of_the_grid_place():
    assert instance_seed(0, 100, 0.5, 3) == instance_seed(0, 100, 0.5, 3)
    seeds = {instance_seed(s, n, r, t) for s in (0, 1) for n in (100, 1000)
             for r in (0.0, 0.5, 0.95) for t in range(50)}
    assert len(seeds) == 2 * 2 * 3 * 50
    assert all(0 <= x < 2**63 for x in seeds)


def _rows_of(records, tmp_path) -> pd.DataFrame:
    from certpose.bench.rows import RowWriter

    path = tmp_path / "expected.csv"
    with RowWriter(path, TRIAL_COLUMNS, append=False) as w:
        w.write_many(records)
    return _rows(path)


def _cli(*args: str) -> list[str]:
    return [sys.executable, "-m", "certpose", *args]


def _env() -> dict[str, str]:
    return {**os.environ, "PYTHONPATH": str(ROOT)}


def _wait_for_rows(path: Path, count: int, proc: subprocess.Popen, timeout: float = 120) -> None:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if path.exists() and path.read_text().count("\n") > count:
            return
        assert proc.poll() is None, "the run ended before it could be interrupted"
        time.sleep(0.05)
    raise AssertionError(f"fewer than {count} rows after {timeout} s")


GRID = ["bench", "--n", "40", "--outlier-ratios", "0", "0.6", "0.9", "--trials", "400",
        "--seed", "11", "--solvers", "gnc", "gnc-only", "--no-progress"]
GRID_ROWS = 3 * 400 * 2


def _with_trials(grid: list[str], trials: int) -> list[str]:
    k = grid.index("--trials") + 1
    return [*grid[:k], str(trials), *grid[k + 1:]]


@pytest.mark.slow  # two runs of 2,400 solves in subprocesses (a few seconds each)
def test_sigkill_then_resume_gives_the_rows_of_an_uninterrupted_run(tmp_path):
    whole, cut = tmp_path / "whole", tmp_path / "cut"
    subprocess.run(_cli(*GRID, "--workers", "0", "--out", str(whole)), env=_env(), check=True,
                   capture_output=True)

    proc = subprocess.Popen(_cli(*GRID, "--workers", "0", "--out", str(cut)), env=_env(),
                            stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    _wait_for_rows(cut / "trials.csv", 50, proc)
    proc.send_signal(signal.SIGKILL)
    proc.wait()
    n_cut = len(read_rows(cut / "trials.csv", TRIAL_COLUMNS))
    assert 50 <= n_cut < GRID_ROWS

    done = subprocess.run(_cli(*GRID, "--workers", "0", "--out", str(cut), "--resume"),
                          env=_env(), capture_output=True, text=True)
    assert done.returncode == 0, done.stderr
    a, b = _rows(whole / "trials.csv"), _rows(cut / "trials.csv")
    assert len(a) == GRID_ROWS and a.equals(b)


@pytest.mark.slow  # a subprocess run interrupted with Ctrl-C
def test_ctrl_c_keeps_the_finished_rows_and_says_so_in_one_line(tmp_path):
    out = tmp_path / "res"
    # A grid far too long (120,000 solves, minutes) to finish before the signal lands, even if
    # this process is descheduled for seconds on a loaded machine (12,000 solves once did).
    grid = _with_trials(GRID, 20000)
    # SIGINT back to its default in the child: a test run started in the background (SIGINT
    # ignored) would otherwise pass the ignore on, and Python would never see the Ctrl-C.
    proc = subprocess.Popen(_cli(*grid, "--workers", "0", "--out", str(out)), env=_env(),
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                            preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL))
    _wait_for_rows(out / "trials.csv", 20, proc)
    proc.send_signal(signal.SIGINT)
    _, err = proc.communicate(timeout=60)
    assert proc.returncode == 130
    lines = err.strip().splitlines()
    assert len(lines) == 1 and "interrupted" in lines[0] and "--resume" in lines[0], err
    written = read_rows(out / "trials.csv", TRIAL_COLUMNS)
    assert f"{len(written)} new row(s)" in lines[0]


@pytest.fixture(scope="module")
def cluster():
    """The cluster `certpose bench --workers 2` starts (the same configuration)."""
    pytest.importorskip("distributed")
    from certpose.bench.runner import _local_cluster

    # A cluster started before with Dask's defaults (another test) wrote Dask's malloc setting
    # into this process's environment, which every later worker would inherit.
    saved = os.environ.pop("MALLOC_TRIM_THRESHOLD_", None)
    try:
        with _local_cluster(2) as cl:
            yield cl
    finally:
        if saved is not None:
            os.environ["MALLOC_TRIM_THRESHOLD_"] = saved


@pytest.mark.slow  # starts a 2-process LocalCluster
def test_embedded_workers_run_one_thread_each(cluster):
    pytest.importorskip("threadpoolctl")
    from distributed import Client

    from certpose.bench.runner import WORKER_ENV

    names = ["OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS", "NUMBA_NUM_THREADS"]
    assert set(names) <= set(WORKER_ENV)
    with Client(cluster.scheduler_address) as client:
        assert set(client.nthreads().values()) == {1}
        envs = client.run(lambda: {k: os.environ.get(k) for k in names})
        # The BLAS libraries as loaded in the workers, not only the variables.
        pools = client.run(lambda: {p["num_threads"] for p in _threadpools()})
    assert len(envs) == 2 and all(e == dict.fromkeys(names, "1") for e in envs.values())
    assert all(p == {1} for p in pools.values()), pools


@pytest.mark.slow  # starts a 2-process LocalCluster
def test_embedded_workers_run_without_the_profiler(cluster):
    from distributed import Client

    def profiler(dask_worker) -> tuple[bool, bool]:  # client.run passes the worker by name
        import dask

        # The configuration as the worker read it, and its sampling callback not running.
        callbacks = dask_worker.periodic_callbacks
        running = "profile" in callbacks and callbacks["profile"].is_running()
        return dask.config.get("distributed.worker.profile.enabled"), running

    with Client(cluster.scheduler_address) as client:
        states = client.run(profiler)
    assert len(states) == 2 and all(s == (False, False) for s in states.values()), states


@pytest.mark.slow  # starts a 2-process LocalCluster
def test_embedded_workers_split_no_eq1_batch_among_threads(cluster):
    # One single-thread worker per core: a worker that split its eq. (1) batches between
    # threads would compete with the other workers for the cores.
    from distributed import Client

    def pool_threads() -> int:
        from certpose.model.likelihood import _pool

        return _pool()[1]

    with Client(cluster.scheduler_address) as client:
        sizes = client.run(pool_threads)
    assert len(sizes) == 2 and set(sizes.values()) == {1}, sizes


def _faults_of_reallocations() -> int:
    """Page faults of 50 allocations of a freed 2 MB array (glibc serves them from the heap
    once its dynamic mmap threshold has seen one freed: about one allocation's 512 pages)."""
    import resource

    a = np.ones(1 << 18)
    del a
    before = resource.getrusage(resource.RUSAGE_SELF).ru_minflt
    for _ in range(50):
        a = np.ones(1 << 18)
        del a
    return resource.getrusage(resource.RUSAGE_SELF).ru_minflt - before


@pytest.mark.slow  # starts a 2-process LocalCluster
def test_embedded_workers_reuse_freed_memory(cluster):
    # Dask's default MALLOC_TRIM_THRESHOLD_ turns off glibc's dynamic mmap threshold: every
    # large array is mapped and faulted in afresh (50 x 512 pages here; in a pose run, 20 s of
    # system time over the 60 YCB-Video targets).
    from distributed import Client

    with Client(cluster.scheduler_address) as client:
        faults = client.run(_faults_of_reallocations)
        env = client.run(lambda: os.environ.get("MALLOC_TRIM_THRESHOLD_"))
    assert len(faults) == 2 and all(f < 50 * 512 / 4 for f in faults.values()), faults
    assert set(env.values()) == {None}, env


def _threadpools() -> list[dict]:
    import numpy  # noqa: F401  (loads OpenBLAS)
    from threadpoolctl import threadpool_info

    return threadpool_info()


def test_open3d_rows_do_not_depend_on_its_thread_count(tmp_path):
    # o3d-ransac's result depends on how many threads Open3D runs (on this grid: 1 vs 2); the
    # bench runs it on one, so rows do not depend on the machine or on Dask vs in-process.
    o3d = pytest.importorskip("open3d")
    config = BenchConfig(n_values=(100,), outlier_ratios=(0.9,), trials=4, seed=0,
                         solvers=("o3d-ransac",))
    before = o3d.utility.get_max_threads()
    if before < 2:
        pytest.skip("Open3D runs one thread here (one core) whatever the limit")
    frames = []
    try:
        for n in (1, 2):
            o3d.utility.set_max_threads(n)
            run_benchmark(config, progress=False, out_dir=tmp_path / str(n), workers=0)
            assert o3d.utility.get_max_threads() == n  # the caller's setting is restored
            frames.append(_rows(tmp_path / str(n) / "trials.csv"))
    finally:
        o3d.utility.set_max_threads(before)
    assert len(frames[0]) == 4 and frames[0].equals(frames[1])


def test_dask_chunks_shrink_towards_the_end():
    from certpose.bench.runner import _batches, _Task
    from certpose.bench.suites import InstanceSpec, protocol_specs

    specs = list(protocol_specs("s", (100,), (0.0, 0.5, 0.9), 200, 0))
    extra = InstanceSpec("3dmatch", "pair", 0, 0, "3dmatch", ("x",))
    tasks = [_Task(s, ("gnc",)) for s in specs[:300]] + [_Task(extra, ("gnc",))] + [
        _Task(s, ("gnc",)) for s in specs[300:]]
    chunks = list(_batches(iter(tasks), 50, n_protocol=len(specs), slots=2))
    assert [t for c in chunks for t in c] == tasks  # each task once, in order
    assert [c for c in chunks if c[0].spec.kind != "protocol"] == [[tasks[300]]]
    sizes = [len(c) for c in chunks if c[0].spec.kind == "protocol"]
    assert max(sizes) == 50 and sizes == sorted(sizes, reverse=True)
    assert sizes[-1] == 1 and sum(sizes[-5:]) < 10  # no full chunk left for one worker alone
    # A size the user gives is kept (the last chunk holds the rest).
    fixed = [len(c) for c in _batches(iter(tasks[:300]), 40)]
    assert fixed == [40] * 7 + [20]


@pytest.mark.slow  # starts a 2-process LocalCluster
def test_dask_gives_the_rows_of_the_in_process_run(tmp_path, cluster):
    config = BenchConfig(n_values=(20, 30), outlier_ratios=(0.0, 0.7), trials=3, seed=7,
                         solvers=("gnc", "gnc-only"))
    local = run_benchmark(config, progress=False, out_dir=tmp_path / "local", workers=0)
    dask = run_benchmark(config, progress=False, out_dir=tmp_path / "dask",
                         scheduler=cluster.scheduler_address, batch_size=2)
    a, b = _rows(tmp_path / "local" / "trials.csv"), _rows(tmp_path / "dask" / "trials.csv")
    assert len(a) == 2 * 2 * 3 * 2 and a.equals(b)
    assert local.summary and len(dask.trials) == len(local.trials)

    # Resuming on Dask after losing rows fills in exactly the missing ones.
    path = tmp_path / "dask" / "trials.csv"
    lines = path.read_text().splitlines(keepends=True)
    path.write_text("".join(lines[:7]))
    run_benchmark(config, progress=False, out_dir=tmp_path / "dask", resume=True,
                  scheduler=cluster.scheduler_address, batch_size=2)
    assert _rows(path).equals(a)


@pytest.mark.slow  # starts a 2-process LocalCluster
def test_dask_runs_suites_without_protocol_shapes(tmp_path, cluster):
    # A run of problem files only has no shapes to send to the workers; Dask cannot scatter an
    # empty dict, and `certpose bench --problems DIR` (also --suite 3dmatch, eq2) failed on it.
    from certpose.data.instances import make_instance
    from certpose.io.points import synthetic_shape
    from certpose.io.problems import save_problem

    folder = tmp_path / "probs"
    folder.mkdir()
    for k in range(3):
        inst = make_instance(synthetic_shape(), 40, 0.5, noise=0.01, rng=k)
        T = np.eye(4)
        T[:3, :3], T[:3, 3] = inst.rotation, inst.translation
        save_problem(folder / f"p{k}.npz", inst.source, inst.target,
                     noise_bound=inst.noise_bound, T_target_source=T)
    config = BenchConfig(problems=(str(folder),), solvers=("gnc", "gnc-only"))
    run_benchmark(config, progress=False, out_dir=tmp_path / "local", workers=0)
    run_benchmark(config, progress=False, out_dir=tmp_path / "dask",
                  scheduler=cluster.scheduler_address)
    a, b = _rows(tmp_path / "local" / "trials.csv"), _rows(tmp_path / "dask" / "trials.csv")
    assert len(a) == 3 * 2 and a.equals(b)
    assert set(a["success"]) == {"True"}


@pytest.mark.slow  # a LocalCluster run with one worker killed in the middle
def test_a_killed_worker_loses_no_row(tmp_path, cluster):
    import threading

    from distributed import Client

    # Long enough (3,000 solves) that the kill lands mid-run; the pids are known beforehand so
    # that it follows the 60th row at once.
    config = BenchConfig(n_values=(40,), outlier_ratios=(0.0, 0.6, 0.9), trials=1000, seed=3,
                         solvers=("gnc-only",))
    out = tmp_path / "res"
    errors: list[BaseException] = []

    def bench() -> None:
        try:
            run_benchmark(config, progress=False, out_dir=out,
                          scheduler=cluster.scheduler_address, batch_size=5)
        except BaseException as exc:  # re-raised in the test's thread
            errors.append(exc)

    with Client(cluster.scheduler_address) as client:
        pids = client.run(os.getpid)
    victim = sorted(pids.values())[0]
    thread = threading.Thread(target=bench)
    thread.start()
    path = out / "trials.csv"
    deadline = time.monotonic() + 120
    while not (path.exists() and path.read_text().count("\n") > 60):
        assert thread.is_alive() and time.monotonic() < deadline, errors
        time.sleep(0.02)
    os.kill(victim, signal.SIGKILL)
    at_kill = path.read_text().count("\n") - 1
    thread.join(timeout=180)
    assert not thread.is_alive() and not errors, errors
    assert at_kill < 3000  # the kill did land mid-run
    with Client(cluster.scheduler_address) as client:
        assert victim not in client.run(os.getpid).values()  # it did die (and was replaced)

    expected = run_benchmark(config, progress=False, workers=0)
    rows = _rows(path)
    assert len(rows) == 3000 and rows.equals(_rows_of(expected.trials, tmp_path))


def _interrupted_in_a_kernel(inst):
    """What a numba kernel returns when Ctrl-C lands inside it: a SystemError whose cause is
    the KeyboardInterrupt."""
    try:
        raise KeyboardInterrupt
    except KeyboardInterrupt as ki:
        raise SystemError("CPUDispatcher(gnc_tls) returned a result with an exception set") from ki


def test_ctrl_c_inside_a_kernel_stops_the_run_and_writes_no_failed_row(tmp_path, monkeypatch,
                                                                       capsys):
    from certpose.bench import runner

    out = tmp_path / "res"
    calls = {"n": 0}
    real = runner.SOLVERS["gnc-only"]

    def solver(inst):
        calls["n"] += 1
        if calls["n"] == 3:  # the first two solves finish, the third is interrupted
            _interrupted_in_a_kernel(inst)
        return real(inst)

    args = ["bench", "--n", "15", "--outlier-ratios", "0", "0.5", "--trials", "3", "--seed", "4",
            "--solvers", "gnc-only", "--no-progress", "--workers", "0", "--out", str(out)]
    runner._ensure_warm(["gnc-only"])  # the warm-up solve would count as a call
    monkeypatch.setitem(runner.SOLVERS, "gnc-only", solver)
    assert main(args) == 130
    err = capsys.readouterr().err.strip()
    assert "interrupted: 2 new row(s)" in err and "\n" not in err
    rows = read_rows(out / "trials.csv", TRIAL_COLUMNS)
    assert len(rows) == 2 and all(r["status"] != "exception" for r in rows)


def test_interrupt_found_through_causes_and_contexts():
    from solvers.interrupt import interrupt_in, reraise_interrupt

    reraise_interrupt(ValueError("plain"))  # nothing to find: returns
    assert interrupt_in(RuntimeError("x")) is None
    with pytest.raises(KeyboardInterrupt):
        try:
            _interrupted_in_a_kernel(None)
        except SystemError as exc:
            reraise_interrupt(exc)
    # Through __context__ (raised while handling), and a cycle does not loop.
    try:
        try:
            raise KeyboardInterrupt
        except KeyboardInterrupt:
            raise ValueError("during handling")  # noqa: B904 - the implicit context is the case
    except ValueError as exc:
        assert isinstance(interrupt_in(exc), KeyboardInterrupt)
        a, b = RuntimeError("a"), RuntimeError("b")
        a.__context__, b.__context__ = b, a
        assert interrupt_in(a) is None
