"""Compiled kernels: declared signatures, the cache check and the parallel first-run warm-up."""

from __future__ import annotations

import json
import os
import subprocess
import sys
import textwrap
from pathlib import Path

import numpy as np
import pytest

from solvers import jit

ROOT = Path(__file__).resolve().parents[1]
MODULES = ["solvers._linalg_kernels", "solvers.registration._kernels",
           "solvers.registration._clique_kernels", "solvers.certify._kernels",
           "solvers.certify._mode_kernels", "solvers.certify._pose_kernels",
           "solvers.certify._convex_cell",
           "certpose.model._kernels", "certpose.sampling._kernels",
           "certpose.geometry._fpfh_kernels"]


def _run(code: str, cache_dir: Path) -> dict:
    """Run ``code`` in a fresh interpreter on the numba cache ``cache_dir``; its last stdout line
    is JSON."""
    env = dict(os.environ, NUMBA_CACHE_DIR=str(cache_dir))
    env["PYTHONPATH"] = os.pathsep.join(filter(None, [str(ROOT), env.get("PYTHONPATH")]))
    proc = subprocess.run([sys.executable, "-c", textwrap.dedent(code)], env=env,
                          capture_output=True, text=True, timeout=600)
    assert proc.returncode == 0, proc.stderr
    return json.loads(proc.stdout.strip().splitlines()[-1])


def test_every_kernel_module_declares_its_entry_points():
    specs = jit.declared(MODULES)
    names = {(s.module, s.name) for s in specs}
    for required in [("solvers.registration._kernels", "gnc_tls"),
                     ("solvers._linalg_kernels", "procrustes"),
                     ("solvers.certify._kernels", "heavy_maximal_cliques"),
                     ("certpose.model._kernels", "eq1_batch")]:
        assert required in names
    for spec in specs:
        assert len(spec.signature) == spec.dispatcher().py_func.__code__.co_argcount


def test_callers_use_only_the_declared_signature():
    """A second signature would be a second compilation on a first run."""
    from certpose.api import register
    from certpose.data.instances import make_instance
    from certpose.io.points import synthetic_shape

    for outliers, certify in ((0.5, False), (0.95, True)):
        inst = make_instance(synthetic_shape(), 60, outliers, noise=0.01, rng=3)
        src = inst.source.copy()
        src.setflags(write=False)  # read-only input must not make a read-only specialisation
        register(src, inst.target.astype(np.float32), noise_bound=inst.noise_bound,
                 certify=certify)
        # Weights with zeros: the pruning selects the active columns (a copy in C order).
        w = np.ones(inst.source.shape[0])
        w[::7] = 0.0
        register(src, inst.target, noise_bound=inst.noise_bound, weights=w, certify=certify)
    used = 0
    for spec in jit.declared(MODULES):
        sigs = spec.dispatcher().signatures
        used += bool(sigs)
        assert all(tuple(s) == spec.signature for s in sigs), (spec.name, sigs)
    assert used >= 8


def test_unknown_kernel_is_a_clear_error():
    with pytest.raises(ValueError, match="no declared kernel"):
        jit.warm_up(["solvers.registration._kernels:no_such_kernel"])
    proc = subprocess.run([sys.executable, "-m", "solvers.jit", "solvers.jit:nothing"],
                          capture_output=True, text=True, cwd=ROOT)
    assert proc.returncode == 2 and "no declared kernel" in proc.stderr


@pytest.mark.slow
def test_warm_up_compiles_each_kernel_once_across_two_processes(tmp_path):
    """On an empty cache the helper and this process share the kernels; afterwards the calls
    compile nothing, and a second run starts no helper."""
    code = """
        import json, time
        from numba.core import event
        compiles = []
        class Count(event.Listener):
            def on_start(self, e): compiles.append(e.data["dispatcher"].py_func.__name__)
            def on_end(self, e): pass
        event.register("numba:compile", Count())
        import numpy as np
        from solvers import jit
        names = ["row_degrees", "k_core", "scalar_tls_rows"]
        kernels = [f"solvers.registration._kernels:{n}" for n in names]
        specs = [s for s in jit.declared(["solvers.registration._kernels"]) if s.name in names]
        cold_before = [not jit.is_cached(s) for s in specs]
        started = jit.warm_up(kernels)
        pending = jit.pending()
        k = jit.compiled("solvers.registration._kernels")  # compiles the rest, waits
        here = list(compiles)
        adj = np.ones((5, 5), dtype=np.uint8); np.fill_diagonal(adj, 0)
        deg = k.row_degrees(adj)
        core = k.k_core(adj, deg, 4)
        order = np.zeros((3, 4), dtype=np.int64)
        x, found = k.scalar_tls_rows(np.zeros((3, 4)), np.ones(4), np.ones(4), 1.0, order, order)
        print(json.dumps({"cold_before": cold_before, "started": started, "pending": pending,
                          "here": here, "after": compiles[len(here):],
                          "cached": [jit.is_cached(s) for s in specs],
                          "core": core.tolist(), "left": jit.pending()}))
    """
    first = _run(code, tmp_path)
    assert first["cold_before"] == [True, True, True]
    assert first["started"] == 3 and first["pending"] == ["solvers.registration._kernels"]
    assert first["after"] == []  # nothing compiled at the calls: all done before
    assert first["cached"] == [True, True, True] and first["left"] == []
    assert first["core"] == [0, 1, 2, 3, 4]
    # Kernels compiled here are the ones the helper had not claimed: never all three twice.
    assert len([n for n in first["here"] if n in ("row_degrees", "k_core", "scalar_tls_rows")]) < 3
    second = _run(code, tmp_path)
    assert second["cold_before"] == [False, False, False]
    assert second["started"] == 0 and second["pending"] == [] and second["here"] == []
    assert second["after"] == []  # loaded from the cache the first run filled


@pytest.mark.slow
def test_cli_warms_kernels_on_a_cold_cache(tmp_path):
    env = dict(os.environ, NUMBA_CACHE_DIR=str(tmp_path))
    env["PYTHONPATH"] = os.pathsep.join(filter(None, [str(ROOT), env.get("PYTHONPATH")]))
    args = [sys.executable, "-m", "certpose", "-v", "register", "--demo", "--demo-n", "40"]
    first = subprocess.run(args, env=env, capture_output=True, text=True, timeout=600)
    assert first.returncode == 0, first.stderr
    assert "7 kernels being compiled in the background" in first.stderr
    second = subprocess.run(args, env=env, capture_output=True, text=True, timeout=600)
    assert second.returncode == 0 and "in the background" not in second.stderr
    assert first.stdout.splitlines()[2:6] == second.stdout.splitlines()[2:6]  # same pose


def test_unneeded_warm_up_is_stopped_at_exit(tmp_path):
    """A command that ends before calling its kernels leaves no helper and no lock folder."""
    out = _run("""
        import json
        from solvers import jit
        jit.warm_up(["solvers.registration._kernels:gnc_tls"])
        item = jit._PENDING[0]
        print(json.dumps({"pid": item.proc.pid, "dir": item.lock_dir}))
    """, tmp_path)
    assert not Path(out["dir"]).exists()
    with pytest.raises(ProcessLookupError):
        os.kill(out["pid"], 0)


_DEFERRED_RUN = """
    import json
    import logging
    from solvers import jit
    logs = []
    handler = logging.Handler()
    handler.emit = lambda record: logs.append(record.getMessage())
    logging.getLogger("solvers.jit").addHandler(handler)
    logging.getLogger("solvers.jit").setLevel(logging.INFO)
    names = ["certpose.geometry._fpfh_kernels:fpfh"]
    specs = [s for s in jit.declared(["certpose.geometry._fpfh_kernels"]) if s.name == "fpfh"]
    started = jit.warm_up(names)
    item = jit._PENDING[0] if jit._PENDING else None
    out = {"started": started, "deferred": specs[0].deferred, "pending": jit.pending(),
           "pid": item and item.proc and item.proc.pid, "dir": item and item.lock_dir,
           "lock": jit.deferred_lock_path("certpose.geometry._fpfh_kernels"),
           "logs": [m for m in logs if "in the background" in m]}
    print(json.dumps(out))
"""


def _alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    return True


def _wait_gone(pid: int, timeout: float = 600.0) -> None:
    import time

    end = time.monotonic() + timeout
    while _alive(pid):
        assert time.monotonic() < end, f"process {pid} still running"
        time.sleep(0.05)


@pytest.mark.slow
def test_deferred_kernels_compile_detached_after_a_run(tmp_path):
    """A run that ends while its helper compiles deferred kernels only returns at once, its pipes
    closed (subprocess.run with captured output), and leaves the helper compiling them in its own
    session; a second run meanwhile does without them and starts no helper for them (the first
    one holds their lock); once it is done they are cached."""
    first = _run(_DEFERRED_RUN, tmp_path)  # returns when the run's pipes close
    assert first["started"] == 1 and first["deferred"]
    assert first["logs"] == ["first run: 1 kernels being compiled in the background (0 by another process)"]
    assert first["pending"] == ["certpose.geometry._fpfh_kernels"]
    pid = first["pid"]
    assert _alive(pid)  # still compiling (seconds), detached
    assert os.getsid(pid) == pid and os.getsid(pid) != os.getsid(0)
    second = _run(_DEFERRED_RUN, tmp_path)
    assert second["started"] == 1 and second["pid"] is None  # no helper for them: one compiles
    assert second["logs"] == ["first run: 1 kernels being compiled in the background (1 by another process)"]
    assert second["pending"] == ["certpose.geometry._fpfh_kernels"]  # open3d's FPFH meanwhile
    assert not Path(second["dir"]).exists()
    assert _alive(pid)
    assert Path(first["lock"]).read_text() == str(pid)  # held by the first's helper throughout
    _wait_gone(pid)
    assert not Path(first["dir"]).exists()  # the helper removed its lock folder
    third = _run(_DEFERRED_RUN, tmp_path)
    assert third["started"] == 0 and third["pending"] == []


@pytest.mark.slow
def test_a_shell_pipe_returns_while_the_detached_helper_compiles(tmp_path):
    env = dict(os.environ, NUMBA_CACHE_DIR=str(tmp_path))
    env["PYTHONPATH"] = os.pathsep.join(filter(None, [str(ROOT), env.get("PYTHONPATH")]))
    script = tmp_path / "run.py"
    script.write_text(textwrap.dedent(_DEFERRED_RUN))
    proc = subprocess.run(["sh", "-c", f'"{sys.executable}" "{script}" 2>&1 | cat'], env=env,
                          capture_output=True, text=True, timeout=600)
    assert proc.returncode == 0, proc.stdout
    out = json.loads(proc.stdout.strip().splitlines()[-1])
    assert out["started"] == 1 and _alive(out["pid"])
    _wait_gone(out["pid"])


@pytest.mark.slow
def test_deferred_kernels_are_waited_for_when_detaching_is_off(tmp_path, monkeypatch):
    """SOLVERS_JIT_DETACH=0: the run waits at exit for its helper's deferred kernels."""
    monkeypatch.setenv(jit.DETACH_ENV, "0")
    first = _run(_DEFERRED_RUN, tmp_path)
    monkeypatch.delenv(jit.DETACH_ENV)
    assert first["started"] == 1 and not _alive(first["pid"])
    assert not Path(first["dir"]).exists()
    second = _run(_DEFERRED_RUN, tmp_path)
    assert second["started"] == 0 and second["pending"] == []


def test_commands_warm_what_they_will_call():
    from certpose.cli import pose, register
    from solvers.certify import CERTIFY_KERNELS
    from solvers.registration import PRUNED_SOLVE_KERNELS

    assert register.kernels(["register", "--demo"]) == PRUNED_SOLVE_KERNELS
    for extra in (["--certify"], ["--require-certificate"], ["--solver", "sdp"], ["--solver=sdp"]):
        assert register.kernels(["register", "a.xyz", "b.xyz", *extra])[-len(CERTIFY_KERNELS):] \
            == CERTIFY_KERNELS
    full = pose.kernels(["pose", "--demo"])
    assert set(PRUNED_SOLVE_KERNELS) | set(CERTIFY_KERNELS) < set(full)
    assert full[0] == PRUNED_SOLVE_KERNELS[0] and len(set(full)) == len(full)
    # The FPFH's last (preloaded first), deferred: the scene uses open3d's while they compile.
    fpfh = [s for s in jit.declared(["certpose.geometry._fpfh_kernels"])]
    assert {k.split(":")[0] for k in full[-2:]} == {"certpose.geometry._fpfh_kernels"}
    assert fpfh and all(s.deferred for s in fpfh)
    assert not any(s.deferred for s in jit.declared(MODULES[:-1]))
    assert not set(CERTIFY_KERNELS) & set(pose.kernels(["pose", "--demo", "--no-certify"]))
    # every name is a declared kernel
    assert jit.warm_up([]) == 0
    names = {f"{s.module}:{s.name}" for s in jit.declared(MODULES)}
    assert set(full) <= names


@pytest.mark.slow
def test_threads_share_a_warm_up(tmp_path):
    """The MLE certifies in a thread: two threads reaching warmed modules at once."""
    out = _run("""
        import json, threading
        from solvers import jit
        jit.warm_up(["solvers.registration._kernels:row_degrees",
                     "solvers.registration._kernels:k_core"])
        errors = []
        def load():
            try:
                jit.compiled("solvers.registration._kernels")
            except Exception as exc:
                errors.append(repr(exc))
        threads = [threading.Thread(target=load) for _ in range(4)]
        [t.start() for t in threads]
        [t.join() for t in threads]
        specs = jit.declared(["solvers.registration._kernels"])
        print(json.dumps({"errors": errors, "left": jit.pending(),
                          "cached": [jit.is_cached(s) for s in specs
                                     if s.name in ("row_degrees", "k_core")]}))
    """, tmp_path)
    assert out == {"errors": [], "left": [], "cached": [True, True]}


def test_compiling_pauses_the_garbage_collector_and_restores_it():
    import gc

    spec = next(s for s in jit.declared(["solvers.registration._kernels"])
                if s.name == "row_degrees")
    assert gc.isenabled()
    assert jit._compile([spec]) == 1
    assert gc.isenabled()
    gc.disable()
    try:
        jit._compile([spec])
        assert not gc.isenabled()  # a caller's choice is kept
    finally:
        gc.enable()
    broken = jit.KernelSpec(spec.module, spec.name, ("not a numba type",))
    with pytest.raises(TypeError):
        jit._compile([broken])
    assert gc.isenabled()  # restored on failure too


@pytest.mark.slow
def test_warm_up_preloads_cached_kernels_in_a_thread(tmp_path):
    """With a warm cache, preload=True starts no helper process but loads the kernels from the cache
    in a thread; a call meanwhile waits for its load (numba's lock) and gives the right answer."""
    kernels = ["solvers.registration._kernels:row_degrees", "solvers.registration._kernels:k_core"]
    _run(f"""
        import json
        from solvers import jit
        jit._compile([s for s in jit.declared(["solvers.registration._kernels"])
                      if f"{{s.module}}:{{s.name}}" in {kernels!r}])
        print("{{}}")
    """, tmp_path)
    out = _run(f"""
        import json, time
        import numpy as np
        from solvers import jit
        specs = [s for s in jit.declared(["solvers.registration._kernels"])
                 if f"{{s.module}}:{{s.name}}" in {kernels!r}]
        before = [len(s.dispatcher().overloads) for s in specs]
        started = jit.warm_up({kernels!r}, preload=True)
        threads = [t.name for t in jit._PRELOADS]
        k = jit.compiled("solvers.registration._kernels")
        jit._join_preloads()
        print(json.dumps({{"started": started, "pending": jit.pending(), "threads": threads,
                          "before": before, "after": [len(s.dispatcher().overloads) for s in specs],
                          "preloading": jit.preloading()}}))
    """, tmp_path)
    assert out == {"started": 0, "pending": [], "threads": ["solvers-jit-preload"],
                   "before": [0, 0], "after": [1, 1], "preloading": False}



def test_deferred_lock_without_a_lock_file_goes_on_unguarded(tmp_path, monkeypatch):
    """A lock file that cannot be created (a missing or read-only folder) never stops a run."""
    module = "certpose.geometry._fpfh_kernels"
    monkeypatch.setattr(jit, "deferred_lock_path", lambda m: str(tmp_path / "missing" / "x.lock"))
    assert jit._deferred_busy(module) is False
    with jit._deferred_lock(module, block=True) as mine:
        assert mine is True
