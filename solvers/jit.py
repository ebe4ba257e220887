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

Kernels declared ``deferred`` (their callers have another way to the same result meanwhile) are
compiled by the helper last. A run that ends while its helper compiles only those leaves it
running, detached (its own session, no terminal, none of the caller's pipes), so that they end up
in the cache without the run waiting for them; ``SOLVERS_JIT_DETACH=0`` makes the run wait
instead. A lock file in numba's cache folder (``<module>.deferred.lock``, held with ``flock``
while a process compiles that module's deferred kernels) keeps concurrent runs from compiling
them twice: a second run started meanwhile does without them, as the first did.

Declaring the signature also documents what each kernel takes, and lets the tests check that
the callers use only that one (a second signature would be a second compilation).
"""

from __future__ import annotations

import atexit
import contextlib
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

__all__ = ["DETACH_ENV", "KernelSpec", "compiled", "declared", "deferred_lock_path", "is_cached",
           "kernel", "pending", "preloading", "wait", "warm_up"]

#: Environment variable: ``0`` makes a run wait at exit for its helper's deferred kernels
#: instead of leaving it to compile them detached.
DETACH_ENV = "SOLVERS_JIT_DETACH"


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
        command waiting for the others never compiles it meanwhile, and at exit a helper left
        with deferred kernels only goes on compiling them, detached (see the module's
        docstring), so the first run does not wait for them.
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

    Reads only the cache's index (numba's own key: signature, CPU and bytecode hash) and checks
    that its data file exists (numba writes the index first, then the data file, each
    atomically). When the index cannot be read the kernel counts as cached: nothing is warmed,
    and numba compiles it on first use as usual.
    """
    disp = spec.dispatcher()
    try:
        if tuple(spec.signature) in disp.overloads:
            return True
        cache = disp._cache  # numba's Cache: no public query for "is this signature on disk"
        key = cache._index_key(tuple(spec.signature), disp.targetctx.codegen())
        files = cache._cache_file
        name = files._load_index().get(key)
        return name is not None and os.path.exists(files._data_path(name))
    except Exception:  # an unknown numba layout: do not guess
        log.debug("cannot read numba's cache index for %s.%s", spec.module, spec.name,
                  exc_info=True)
        return True


def _claim(lock_dir: str, spec: KernelSpec) -> bool:
    """Whether this process takes ``spec`` (the first to create its lock file does; with the
    folder gone, its helper has ended: compiling here at worst loads what it cached)."""
    try:
        os.close(os.open(os.path.join(lock_dir, f"{spec.module}.{spec.name}"),
                         os.O_CREAT | os.O_EXCL | os.O_WRONLY))
    except FileExistsError:
        return False
    except FileNotFoundError:
        return True
    return True


def deferred_lock_path(module: str) -> str:
    """The lock file held (``flock``) by a process compiling ``module``'s deferred kernels: in
    numba's cache folder for ``module`` (the folder is created), else in the temporary folder.
    The file holds the process id of the last holder."""
    try:
        spec = next(s for s in declared([module]) if s.deferred)
        folder = spec.dispatcher()._cache._cache_path  # numba's: no public name
        os.makedirs(folder, exist_ok=True)
    except Exception:  # an unknown numba layout, or no deferred kernel
        log.debug("no numba cache folder for %s", module, exc_info=True)
        folder = tempfile.gettempdir()
    return os.path.join(folder, f"{module}.deferred.lock")


def _deferred_busy(module: str) -> bool:
    """Whether another process holds ``module``'s deferred-kernels lock (it compiles them)."""
    with _deferred_lock(module, block=False, mark=False) as mine:
        return not mine


@contextlib.contextmanager
def _deferred_lock(module: str, *, block: bool, mark: bool = True) -> Any:
    """Hold ``module``'s deferred-kernels lock (``mark``: writing this process's id into it);
    yields False (without waiting, when ``block`` is False) if another process holds it.
    Without ``fcntl`` (not POSIX) or a lock file it can create, it always yields True."""
    try:
        import fcntl
    except ImportError:
        yield True
        return
    try:
        fd = os.open(deferred_lock_path(module), os.O_RDWR | os.O_CREAT, 0o644)
    except OSError as exc:  # no lock file: go on unguarded (at worst compiled twice)
        log.debug("no lock file for %s's deferred kernels: %s", module, exc)
        yield True
        return
    try:
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | (0 if block else fcntl.LOCK_NB))
        except BlockingIOError:
            yield False
            return
        if mark:
            os.ftruncate(fd, 0)
            os.write(fd, str(os.getpid()).encode())
        yield True  # released when the file is closed (or the process ends)
    finally:
        os.close(fd)


def _compile(specs: Sequence[KernelSpec], lock_dir: str | None = None, *,
             block: bool = True) -> int:
    """Compile ``specs`` in order, skipping those another process has claimed in ``lock_dir``.
    Deferred ones are compiled under their module's lock (:func:`deferred_lock_path`), once no
    other process holds it (``block``), or skipped if one does (``block=False``: the helper's
    way; the process holding it compiles them)."""
    done = 0
    enabled = gc.isenabled()
    gc.disable()  # numba's compiler makes ~10^5 short-lived objects: collections cost ~8%
    try:
        with contextlib.ExitStack() as held:
            locked: dict[str, bool] = {}
            for spec in specs:
                if spec.deferred and spec.module not in locked:
                    locked[spec.module] = held.enter_context(
                        _deferred_lock(spec.module, block=block))
                if spec.deferred and not locked[spec.module]:
                    continue  # another process compiles it
                if lock_dir is None or _claim(lock_dir, spec):
                    spec.dispatcher().compile(tuple(spec.signature))  # a cached one just loads
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
    for token in _TOKENS:  # which of the two is still there (see _leave)
        open(os.path.join(lock_dir, token), "wb").close()
    # Deferred kernels another process compiles (an earlier run's detached helper): not for our
    # helper; they stay pending, so their callers do without them here too.
    busy = sorted({s.module for s in cold if s.deferred and _deferred_busy(s.module)})
    if busy:
        log.info("deferred kernels of %s: another process is compiling them", busy)
    args = [f"{s.module}:{s.name}" for s in cold if not (s.deferred and s.module in busy)]
    proc: subprocess.Popen[bytes] | None = None
    try:
        if args:
            with open(os.path.join(lock_dir, "stderr"), "wb") as err:  # a file: no pipe to fill
                # Its own session and none of our pipes: it may outlive this process (deferred
                # kernels, see _abandon) without holding a caller's pipe or terminal.
                proc = subprocess.Popen(
                    [sys.executable, "-m", "solvers.jit", "--locks", lock_dir, *args],
                    stdin=subprocess.DEVNULL, stdout=subprocess.DEVNULL, stderr=err,
                    start_new_session=True)
    except OSError as exc:  # no helper: this process compiles them when it needs them
        log.info("kernel warm-up helper not started (%s)", exc)
    if not _PENDING:
        atexit.register(_abandon)
    _PENDING.append(_Warming(proc, cold, lock_dir))
    log.info("first run: %d kernels being compiled in the background (%d by another process)",
             len(cold), len(cold) - len(args))
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
        # The helper's: is_cached sees both of numba's files (index, then data, each atomic).
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


_TOKENS = (".command", ".helper")


def _leave(lock_dir: str, token: str) -> None:
    """``token``'s process is done with ``lock_dir``: the second of the two to leave removes it
    (each removes its token, then looks for the other's)."""
    with contextlib.suppress(FileNotFoundError):
        os.unlink(os.path.join(lock_dir, token))
    other = next(t for t in _TOKENS if t != token)
    if not os.path.exists(os.path.join(lock_dir, other)):
        shutil.rmtree(lock_dir, ignore_errors=True)


def _detach_enabled() -> bool:
    return os.environ.get(DETACH_ENV, "1").strip() != "0"


def _abandon() -> None:
    """At exit: stop helpers whose kernels were never needed (numba writes its cache files
    atomically, so a stopped helper leaves no partial entry) and remove their lock folders.
    A helper left with deferred kernels only (the others cached) goes on compiling them,
    detached (it removes its lock folder when done): no caller ever compiles those, and stopped
    at the end of every (short) run they never would be. With ``SOLVERS_JIT_DETACH=0`` it is
    waited for instead."""
    while _PENDING:
        item = _PENDING.pop()
        if item.proc is not None and item.proc.poll() is None:
            if all(s.deferred or is_cached(s) for s in item.specs):
                if _detach_enabled():
                    log.info("deferred kernels of %s: compiling on in a detached process "
                             "(pid %d)", sorted(item.modules), item.proc.pid)
                    _leave(item.lock_dir, ".command")
                    continue
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
    first = [s for s in specs if not s.deferred]
    _compile(first, lock_dir)
    later = [s for s in specs if s.deferred]
    if later:
        with contextlib.suppress(OSError, AttributeError):  # AttributeError: not POSIX
            os.nice(10)  # no caller waits for these: a command running meanwhile goes first
        _compile(later, lock_dir, block=False)
    if lock_dir is not None:  # not on failure: the folder keeps this process's stderr
        _leave(lock_dir, ".helper")
    gc.freeze()  # exiting: skip the last collection over the compiler's objects
    return 0


if __name__ == "__main__":
    gc.disable()  # a short-lived compiler process: no collections at all
    # Run as a script this file is ``__main__``; the kernels register with ``solvers.jit``.
    from solvers.jit import _main as _registered_main

    sys.exit(_registered_main(sys.argv[1:]))
