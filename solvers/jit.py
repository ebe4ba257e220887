"""Compiled kernels: one declared signature each, compiled once, cached, warmed in parallel.

Every numba kernel of :mod:`solvers` (and of :mod:`certpose.model`) is declared with
:func:`kernel`, which is ``numba.njit(cache=True)`` plus the one signature its callers use.
numba compiles a kernel on its first call and keeps the machine code on disk
(``NUMBA_CACHE_DIR``, or ``__pycache__`` beside the source), so only the first run of a fresh
install pays the compilation: several seconds, nearly all of it Python work inside numba
(typing and lowering), on one core.

:func:`warm_up` shortens that first run. It looks up which of the kernels a command will call
are not yet in the cache, and a helper process compiles them, in the order the command will need
them, while the command goes on with its other work. Code that calls kernels loads their module
through :func:`compiled`: if a warm-up holds kernels of that module, this process compiles those
the helper has not reached (from the back of its list) and waits only for the ones it took. Two
cores compile at once and nothing is compiled twice. With a warm cache no helper is started; a
thread of this process loads the cached kernels instead (``preload=True``): numba's first load in a
process sets up its code generator, about 0.4 s, mostly outside the GIL, which then overlaps the
command's other work (a YCB-Video frame's scene) instead of delaying its first kernel call.

Declaring the signature also documents what each kernel takes, and lets the tests check that
the callers use only that one (a second signature would be a second compilation).
"""

from __future__ import annotations

import atexit
import gc
import importlib
import logging
import os
import shutil
import subprocess
import sys
import tempfile
import threading
import time
from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass
from typing import Any

log = logging.getLogger(__name__)

__all__ = ["KernelSpec", "compiled", "declared", "is_cached", "kernel", "pending", "preloading",
           "wait", "warm_up"]


@dataclass(frozen=True)
class KernelSpec:
    """A declared kernel: its module, name and numba argument types; ``deferred``: its callers
    do without it while a warm-up compiles it (see :func:`kernel`)."""

    module: str
    name: str
    signature: tuple[Any, ...]
    deferred: bool = False

    def dispatcher(self) -> Any:
        return getattr(importlib.import_module(self.module), self.name)


_REGISTRY: dict[str, list[KernelSpec]] = {}


def kernel(*signature: Any, deferred: bool = False,
           **options: Any) -> Callable[[Callable[..., Any]], Any]:
    """``numba.njit(cache=True, **options)`` with its one signature declared.

    Parameters
    ----------
    *signature : numba types
        The argument types the callers pass (e.g. ``numba.types.float64[:, ::1]`` for a
        C-contiguous, writable (N, 3) array).
    deferred : bool
        Its callers have another way to the same result while it is not compiled (they check
        :func:`pending` for its module): a warm-up's helper compiles it after the others, a
        command waiting for the others never compiles it meanwhile, and at exit the command
        waits for a helper left with deferred kernels only (instead of stopping it), so the
        first run pays only what is left of their compilation when its own work is done.
    **options
        Further ``njit`` options (``fastmath``, ``nogil``, ...).
    """
    from numba import njit

    def wrap(fn: Callable[..., Any]) -> Any:
        dispatcher = njit(cache=True, **options)(fn)
        _REGISTRY.setdefault(fn.__module__, []).append(
            KernelSpec(fn.__module__, fn.__name__, tuple(signature), bool(deferred)))
        return dispatcher

    return wrap


def declared(modules: Iterable[str] | None = None) -> list[KernelSpec]:
    """The declared kernels of ``modules`` (imported here), or of every module imported so far."""
    names = list(_REGISTRY) if modules is None else list(modules)
    for name in names:
        importlib.import_module(name)
    return [spec for name in names for spec in _REGISTRY.get(name, [])]


def is_cached(spec: KernelSpec) -> bool:
    """Whether ``spec``'s machine code is loaded or in numba's disk cache for this source.

    Reads only the cache's index (numba's own key: signature, CPU and bytecode hash). When the
    index cannot be read the kernel counts as cached: nothing is warmed, and numba compiles it
    on first use as usual.
    """
    disp = spec.dispatcher()
    try:
        if tuple(spec.signature) in disp.overloads:
            return True
        cache = disp._cache  # numba's Cache: no public query for "is this signature on disk"
        key = cache._index_key(tuple(spec.signature), disp.targetctx.codegen())
        return key in cache._cache_file._load_index()
    except Exception:  # an unknown numba layout: do not guess
        log.debug("cannot read numba's cache index for %s.%s", spec.module, spec.name,
                  exc_info=True)
        return True


def _claim(lock_dir: str, spec: KernelSpec) -> bool:
    """Whether this process takes ``spec`` (the first to create its lock file does)."""
    try:
        os.close(os.open(os.path.join(lock_dir, f"{spec.module}.{spec.name}"),
                         os.O_CREAT | os.O_EXCL | os.O_WRONLY))
    except FileExistsError:
        return False
    return True


def _compile(specs: Sequence[KernelSpec], lock_dir: str | None = None) -> int:
    """Compile ``specs`` in order, skipping those another process has claimed in ``lock_dir``."""
    done = 0
    enabled = gc.isenabled()
    gc.disable()  # numba's compiler makes ~10^5 short-lived objects: collections cost ~8%
    try:
        for spec in specs:
            if lock_dir is None or _claim(lock_dir, spec):
                spec.dispatcher().compile(tuple(spec.signature))
                done += 1
    finally:
        if enabled:
            gc.enable()
    return done


@dataclass
class _Warming:
    """A helper process compiling ``specs`` front to back; this process takes them from the back
    when it needs them (lock files in ``lock_dir`` say who compiles what)."""

    proc: subprocess.Popen[bytes] | None
    specs: list[KernelSpec]
    lock_dir: str

    @property
    def modules(self) -> frozenset[str]:
        return frozenset(s.module for s in self.specs)


_PENDING: list[_Warming] = []


def warm_up(kernels: Sequence[str], *, preload: bool = False) -> int:
    """Start compiling the kernels a command will call that are not cached yet.

    A helper process (this Python, ``python -m solvers.jit``, same environment and so the same
    numba cache) compiles them in the order given, while the caller goes on with other work.
    When the caller needs a module's kernels (:func:`compiled`), it compiles those the helper
    has not started itself, from the back, and waits only for the ones the helper took: two
    cores share the work and nothing is compiled twice. Returns at once when every kernel is
    cached.

    Parameters
    ----------
    kernels : sequence of str
        ``"module"`` (all its declared kernels) or ``"module:name"`` (one of them), in the order
        the command will need them (the helper takes the ``deferred`` ones last).
    preload : bool
        Also load the cached ones from numba's disk cache, in a thread of this process, in the
        order the command will need them (the back of ``kernels`` first, as :func:`wait` takes
        them). A kernel called meanwhile waits for its own load (numba's compiler lock), never
        loads twice.

    Returns
    -------
    int
        Number of kernels that were not cached (0: nothing was started).
    """
    specs = []
    for item in kernels:
        module, _, name = item.partition(":")
        found = [s for s in declared([module]) if not name or s.name == name]
        if not found:
            raise ValueError(f"no declared kernel {item!r}")
        specs.extend(found)
    cold = [s for s in specs if not is_cached(s)]
    cold = [s for s in cold if not s.deferred] + [s for s in cold if s.deferred]
    if preload:
        _preload([s for s in specs[::-1] if s not in cold])
    if not cold:
        return 0
    lock_dir = tempfile.mkdtemp(prefix="solvers-jit-")
    args = [f"{s.module}:{s.name}" for s in cold]
    try:
        with open(os.path.join(lock_dir, "stderr"), "wb") as err:  # a file: no pipe to fill
            proc: subprocess.Popen[bytes] | None = subprocess.Popen(
                [sys.executable, "-m", "solvers.jit", "--locks", lock_dir, *args],
                stdin=subprocess.DEVNULL, stdout=subprocess.DEVNULL, stderr=err)
    except OSError as exc:  # no helper: this process compiles them when it needs them
        log.info("kernel warm-up helper not started (%s)", exc)
        proc = None
    if not _PENDING:
        atexit.register(_abandon)
    _PENDING.append(_Warming(proc, cold, lock_dir))
    log.info("first run: compiling %d kernels in the background", len(cold))
    return len(cold)


_PRELOADS: list[threading.Thread] = []


def _preload(specs: Sequence[KernelSpec]) -> None:
    if not specs:
        return

    def load() -> None:
        t0 = time.perf_counter()
        for spec in specs:
            try:
                spec.dispatcher().compile(tuple(spec.signature))
            except Exception:  # only a head start: the caller's first call loads or fails as usual
                log.debug("preloading %s.%s failed", spec.module, spec.name, exc_info=True)
                return
        log.debug("preloaded %d cached kernels in %.2f s", len(specs), time.perf_counter() - t0)

    thread = threading.Thread(target=load, name="solvers-jit-preload", daemon=True)
    if not _PRELOADS:
        atexit.register(_join_preloads)  # no daemon thread left inside numba at shutdown
    _PRELOADS.append(thread)
    thread.start()


def _join_preloads() -> None:
    while _PRELOADS:
        _PRELOADS.pop().join()


def preloading() -> bool:
    """Whether a :func:`warm_up` thread is still loading cached kernels."""
    return any(t.is_alive() for t in _PRELOADS)


def pending() -> list[str]:
    """Modules whose kernels a warm-up is still compiling."""
    return sorted({m for w in _PENDING for m in w.modules})


_POLL_SECONDS = 0.01


def wait(modules: Iterable[str] | None = None) -> None:
    """Make the warmed kernels of ``modules`` (default: all) ready: compile here those the helper
    has not started (from the back of its list), then wait until the helper has cached the ones
    it took, meanwhile compiling here the warm-up's other kernels the helper has not reached.
    The helper goes on with the rest."""
    with _WAIT_LOCK:  # threads (e.g. a certifier thread) share the warm-ups
        _wait(None if modules is None else set(modules))


_WAIT_LOCK = threading.RLock()


def _wait(wanted: set[str] | None) -> None:
    for item in list(_PENDING):
        specs = [s for s in item.specs if wanted is None or s.module in wanted]
        if not specs:
            continue
        t0 = time.perf_counter()
        mine = _compile(specs[::-1], item.lock_dir)
        later = [s for s in item.specs[::-1] if s not in specs and not s.deferred]
        # The helper's: numba writes the data file, then the index (each atomically).
        while not all(is_cached(s) for s in specs):
            if item.proc is None or item.proc.poll() is not None:
                break  # it ended without them: they compile here, on first use
            if later:  # rather than wait idle, compile one the command needs later
                mine += _compile([later.pop(0)], item.lock_dir)
                continue
            time.sleep(_POLL_SECONDS)
        log.debug("warm-up of %s: %d of %d kernels compiled here, %.2f s", sorted(
            {s.module for s in specs}), mine, len(specs), time.perf_counter() - t0)
        remaining = [s for s in item.specs if s not in specs]
        if remaining and (item.proc is not None and item.proc.poll() is None):
            item.specs = remaining
            continue
        _PENDING.remove(item)
        _finish(item)


def _finish(item: _Warming) -> None:
    if item.proc is not None and item.proc.wait() != 0:
        with open(os.path.join(item.lock_dir, "stderr"), "rb") as f:
            last = f.read().decode(errors="replace").strip().splitlines()[-1:]
        log.warning("kernel warm-up helper failed (exit %s): %s", item.proc.returncode,
                    last[0] if last else "")
    shutil.rmtree(item.lock_dir, ignore_errors=True)


def _abandon() -> None:
    """At exit: stop helpers whose kernels were never needed (numba writes its cache files
    atomically, so a stopped helper leaves no partial entry) and remove their lock folders.
    A helper left with deferred kernels only (the others cached) is waited for instead: no
    caller ever compiles those, and stopped at the end of every (short) run they never would be."""
    while _PENDING:
        item = _PENDING.pop()
        if item.proc is not None and item.proc.poll() is None:
            if all(s.deferred or is_cached(s) for s in item.specs):
                item.proc.wait()
            else:
                item.proc.terminate()
                item.proc.wait()
        shutil.rmtree(item.lock_dir, ignore_errors=True)


def compiled(module: str) -> Any:
    """The kernel module ``module``, once no warm-up is compiling it."""
    if _PENDING:
        wait([module])
    loaded = sys.modules.get(module)  # per solve: importlib's own lookup costs microseconds
    return loaded if loaded is not None else importlib.import_module(module)


def _main(argv: Sequence[str]) -> int:
    lock_dir = None
    if argv[:1] == ["--locks"]:
        lock_dir, argv = argv[1], argv[2:]
    specs = []
    for item in argv:
        module, _, name = item.partition(":")
        found = [s for s in declared([module]) if s.name == name]
        if not found:
            print(f"solvers.jit: no declared kernel {item!r}", file=sys.stderr)
            return 2
        specs.extend(found)
    _compile(specs, lock_dir)
    gc.freeze()  # exiting: skip the last collection over the compiler's objects
    return 0


if __name__ == "__main__":
    gc.disable()  # a short-lived compiler process: no collections at all
    # Run as a script this file is ``__main__``; the kernels register with ``solvers.jit``.
    from solvers.jit import _main as _registered_main

    sys.exit(_registered_main(sys.argv[1:]))
