"""Command-line interface: a thin layer over the library (owns argument parsing, printing, exit codes).

Each sub-command lives in its own module exposing ``add_parser(subparsers)``; heavy imports
happen inside the command functions so ``certpose --help`` stays fast.

Conventions shared by every command (:func:`add_common`): ``--json OUT`` (``-`` for standard
output, which then carries only the JSON), ``--seed``, ``-q/--quiet``, ``-v/--verbose``, a
progress bar on stderr for long work, one-line errors (the traceback only with ``--verbose``)
and the exit codes :data:`EXIT_OK` (0), :data:`EXIT_FAILED` (1: a solve failed, or
``--require-certificate`` was not met) and :data:`EXIT_USAGE` (2: bad input).
"""

from __future__ import annotations

import argparse
import contextlib
import gc
import importlib
import importlib.abc
import importlib.util
import logging
import os
import sys
import threading
import traceback
import types
from collections.abc import Iterator, Sequence
from typing import Any

from certpose._version import __version__

_COMMANDS = ("certpose.cli.register", "certpose.cli.bench", "certpose.cli.pose", "certpose.cli.object",
             "certpose.cli.bop", "certpose.cli.score")

EXIT_OK = 0
EXIT_FAILED = 1
EXIT_USAGE = 2
EXIT_INTERRUPTED = 130


class CLIError(Exception):
    """Bad input reported to the user as one line (exit code 2)."""


class CLIFailure(Exception):
    """A failure that is not the input's fault, reported as one line (exit code 1)."""


def add_common(p: argparse.ArgumentParser, *, seed_help: str | None = None,
               json_help: str = "also write the result as JSON to OUT ('-': standard output)",
               force: bool = True) -> None:
    """The options every command takes: --json, --seed, --quiet, --verbose and --force (one
    overwrite policy for every output file; ``force=False`` for a command that defines its
    own --force)."""
    g = p.add_argument_group("common options")
    g.add_argument("--json", metavar="OUT", default=None, help=json_help)
    if force:
        g.add_argument("--force", action="store_true",
                       help="overwrite output files that exist (refused otherwise)")
    if seed_help is not None:
        g.add_argument("--seed", type=_seed, default=0, help=seed_help)
    g.add_argument("-q", "--quiet", action="store_true",
                   help="print nothing but errors (and the JSON of --json -); no progress bar")
    g.add_argument("-v", "--verbose", action="count", default=0, dest="sub_verbose",
                   help="more logging (-vv: debug); tracebacks on errors")


def _seed(text: str) -> int:
    """--seed's type: NumPy refuses negative seeds ("expected non-negative integer")."""
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"invalid int value: {text!r}") from None
    if value < 0:
        raise argparse.ArgumentTypeError(f"must be a non-negative integer, got {value}")
    return value


def say(args: argparse.Namespace, text: str) -> None:
    """Print a line of the human-readable output unless --quiet or --json -."""
    if not (getattr(args, "quiet", False) or getattr(args, "json", None) == "-"):
        print(text)


def show_progress(args: argparse.Namespace) -> bool:
    return not (getattr(args, "quiet", False) or getattr(args, "no_progress", False))


def check_json_output(args: argparse.Namespace) -> None:
    """Check --json OUT before any work."""
    if getattr(args, "json", None) not in (None, "-"):
        from certpose.io.output import check_output_path

        check_output_path(args.json, what="--json output", force=getattr(args, "force", False))


def emit_json(args: argparse.Namespace, payload: Any) -> None:
    """Write ``payload`` to --json OUT, or print it with --json -."""
    from certpose.io.output import to_json, write_json

    if args.json == "-":
        print(to_json(payload))
    elif args.json is not None:
        say(args, f"wrote {write_json(args.json, payload)}")


@contextlib.contextmanager
def busy(args: argparse.Namespace, desc: str, *, delay: float = 1.0) -> Iterator[None]:
    """A progress bar (elapsed seconds) on stderr around work that reports no steps; shown
    after ``delay`` seconds on a terminal, never with --quiet."""
    if not (show_progress(args) and sys.stderr.isatty()):  # before importing tqdm (~10 ms)
        yield
        return
    try:
        from tqdm import tqdm
    except ImportError:  # the bench extra is not installed: no bar
        yield
        return
    stop = threading.Event()

    def tick() -> None:
        if stop.wait(delay):
            return
        with tqdm(desc=desc, bar_format="{desc}: {elapsed}", leave=False,
                  file=sys.stderr) as bar:
            while not stop.wait(0.5):
                bar.refresh()

    thread = threading.Thread(target=tick, daemon=True)
    thread.start()
    try:
        yield
    finally:
        stop.set()
        thread.join()


_WARM_COMMANDS = {"register": "certpose.cli.register", "pose": "certpose.cli.pose"}


def warm_kernels(argv: Sequence[str]) -> int:
    """On a first run after installing, start compiling the kernels the command in ``argv`` will
    call, in a helper process (:func:`solvers.jit.warm_up`), before anything else: building the
    parser imports every command. With a warm cache a thread loads them instead, while the command
    reads its input. Only a speed-up: never fails a command."""
    command = _command_word(argv)
    if command not in _WARM_COMMANDS or "-h" in argv or "--help" in argv:
        return 0
    try:
        from solvers.jit import warm_up

        module = importlib.import_module(_WARM_COMMANDS[command])
        return warm_up(module.kernels(list(argv)), preload=True)
    except Exception as exc:  # the kernels then compile on first use, as without it
        logging.getLogger(__name__).debug("kernel warm-up not started: %s", exc)
        return 0


def _command_word(argv: Sequence[str]) -> str | None:
    words = [a for a in argv if not a.startswith("-")]
    return words[0] if words else None


def build_parser(command: str | None = None) -> argparse.ArgumentParser:
    """The program's parser; with ``command`` (a known command's name) only that command's
    subparser: the others' modules are not imported (``bench`` alone costs about 0.2 s)."""
    modules = [m for m in _COMMANDS if m.rsplit(".", 1)[1] == command] or list(_COMMANDS)
    parser = argparse.ArgumentParser(
        prog="certpose",
        description="Certifiable robust registration and probabilistic object pose estimation.",
        epilog="exit codes: 0 success; 1 a solve failed or --require-certificate was not met; "
               "2 bad input; 130 interrupted. `python -m certpose` is the same program.",
    )
    parser.add_argument("--version", action="version", version=f"certpose {__version__}")
    parser.add_argument("-v", "--verbose", action="count", default=0, help="more logging")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    for name in modules:
        try:
            module = importlib.import_module(name)
        except ModuleNotFoundError as exc:
            if exc.name != name:
                raise
            continue
        module.add_parser(sub)
    return parser


_EXTRAS = {"open3d": "pose", "imageio": "pose", "PIL": "pose", "cv2": "pose", "gtsam": "bench",
           "tqdm": "bench", "matplotlib": "bench", "distributed": "bench", "dask": "bench",
           "arviz": "samplers", "nevergrad": "samplers", "emcee": "samplers", "pymc": "samplers"}
"""The optional extra that brings each optional module (pyproject.toml)."""


def _message(exc: BaseException) -> str:
    text = " ".join(str(exc).split()) or type(exc).__name__
    if isinstance(exc, KeyError) and exc.args:
        text = str(exc.args[0])
    name = getattr(exc, "name", None)
    if isinstance(exc, ModuleNotFoundError) and name and name.split(".")[0] in _EXTRAS:
        top = name.split(".")[0]
        text = (f"this needs {top}, which is not installed: pip install "
                f"'certpose[{_EXTRAS[top]}]'")
    return text


def main(argv: Sequence[str] | None = None, *, _startup_gc_paused: bool = False) -> int:
    words = sys.argv[1:] if argv is None else argv
    warming = warm_kernels(words)
    parser = build_parser(_command_word(words))
    args = parser.parse_args(argv)  # exits 2 on unknown options
    if _startup_gc_paused:  # (run) the imports are done: they are never collected again
        gc.freeze()
        gc.enable()
    verbose = args.verbose + getattr(args, "sub_verbose", 0)
    quiet = getattr(args, "quiet", False)
    logging.basicConfig(
        level=logging.ERROR if quiet and not verbose else logging.WARNING - 10 * min(verbose, 2),
        format="%(levelname)s %(name)s: %(message)s",
    )
    if warming:
        logging.getLogger("solvers.jit").info(
            "first run: %d kernels being compiled in the background", warming)
    if not getattr(args, "func", None):
        parser.print_help()
        return EXIT_USAGE
    prefix = f"certpose {args.command}: error:"
    try:
        try:
            return int(args.func(args) or 0)
        except Exception as exc:
            # Ctrl-C inside a compiled kernel can surface as another error (SystemError).
            from solvers.interrupt import reraise_interrupt

            reraise_interrupt(exc)
            raise
    except KeyboardInterrupt:
        print(f"certpose {args.command}: interrupted", file=sys.stderr)
        return EXIT_INTERRUPTED
    except (CLIError, ValueError, TypeError, OSError, KeyError) as exc:
        if verbose:
            traceback.print_exc()
        print(f"{prefix} {_message(exc)}", file=sys.stderr)
        return EXIT_USAGE
    except (CLIFailure, ImportError, MemoryError) as exc:
        if verbose:
            traceback.print_exc()
        print(f"{prefix} {_message(exc)}", file=sys.stderr)
        return EXIT_FAILED
    except Exception as exc:  # a bug or a backend failure: one line unless --verbose
        if verbose:
            traceback.print_exc()
        print(f"{prefix} {type(exc).__name__}: {_message(exc)} (run with --verbose for the "
              "traceback)", file=sys.stderr)
        return EXIT_FAILED


class _DeferredOpen3dPlotly(importlib.abc.MetaPathFinder, importlib.abc.Loader):
    """Stands in for ``open3d.visualization.draw_plotly`` until one of its functions is called.

    ``import open3d`` imports that module, which imports Dash, Plotly and IPython: about 1.3 s of
    every ``certpose pose`` run on this project's machine (open3d itself takes 0.9 s), for
    functions the program never calls. The stand-in's functions import the real module on first
    use, so nothing is lost. Installed by :func:`run` only (the program, not the library)."""

    NAME = "open3d.visualization.draw_plotly"
    FUNCTIONS = ("get_plotly_fig", "draw_plotly", "draw_plotly_server")

    def find_spec(self, name: str, path: Any = None, target: Any = None) -> Any:
        if name != self.NAME:
            return None
        return importlib.util.spec_from_loader(name, self)

    def create_module(self, spec: Any) -> None:
        return None  # the default module object

    def exec_module(self, module: Any) -> None:
        for name in self.FUNCTIONS:
            def proxy(*args: Any, _name: str = name, **kwargs: Any) -> Any:
                return getattr(self.real(), _name)(*args, **kwargs)

            proxy.__name__ = name
            setattr(module, name, proxy)

    def real(self) -> Any:
        """The real module, imported now (the stand-in is retired)."""
        if self in sys.meta_path:
            sys.meta_path.remove(self)
            sys.modules.pop(self.NAME, None)
        return importlib.import_module(self.NAME)


def defer_open3d_plotly() -> None:
    """Install :class:`_DeferredOpen3dPlotly` unless open3d or its Plotly module is loaded."""
    if "open3d" in sys.modules or any(isinstance(f, _DeferredOpen3dPlotly) for f in sys.meta_path):
        return
    sys.meta_path.insert(0, _DeferredOpen3dPlotly())


_LAZY_LOCK = threading.RLock()
_LAZY_LOADING: set[int] = set()


class _LazyModule(types.ModuleType):
    """A module whose code runs on the first access to one of its attributes. Thread-safe
    (unlike ``importlib.util.LazyLoader`` before Python 3.12.3): other threads wait for the
    code to finish; the loading thread's own accesses (the code reading its module) go through."""

    def __getattribute__(self, attr: str) -> Any:
        if type(self) is _LazyModule:
            with _LAZY_LOCK:
                if type(self) is _LazyModule and id(self) not in _LAZY_LOADING:
                    _LAZY_LOADING.add(id(self))
                    try:
                        types.ModuleType.__getattribute__(self, "__spec__").loader.exec_module(self)
                        self.__class__ = types.ModuleType
                    finally:
                        _LAZY_LOADING.discard(id(self))
        return types.ModuleType.__getattribute__(self, attr)


class _LazyLoader(importlib.abc.Loader):
    def __init__(self, loader: Any) -> None:
        self.loader = loader

    def create_module(self, spec: Any) -> Any:
        return self.loader.create_module(spec)

    def exec_module(self, module: Any) -> None:
        module.__spec__.loader = module.__loader__ = self.loader
        module.__class__ = _LazyModule


class _DeferredNumpyExtras(importlib.abc.MetaPathFinder):
    """Imports NumPy's tool sub-packages lazily: their module objects exist, their code runs on
    first use.

    SciPy's vendored ``array_api_compat`` copies every public name of ``numpy`` on the first
    import of any ``scipy`` sub-package (``scipy._lib._array_api``), which imports ``numpy.f2py``
    (with ``charset_normalizer``) and ``numpy.testing`` (with ``unittest``): about 0.09 s of
    every ``certpose pose`` run on this project's machine, for modules the program never uses
    (``numpy.ma`` too, but numba reads it on every kernel call).
    Installed by :func:`run` only (the program, not the library)."""

    NAMES = frozenset({"numpy.f2py", "numpy.testing"})

    def find_spec(self, name: str, path: Any = None, target: Any = None) -> Any:
        if name not in self.NAMES:
            return None
        for finder in sys.meta_path:
            if finder is self or not hasattr(finder, "find_spec"):
                continue
            spec = finder.find_spec(name, path, target)
            if spec is not None:
                if hasattr(spec.loader, "exec_module"):
                    spec.loader = _LazyLoader(spec.loader)
                return spec
        return None


def defer_numpy_extras() -> None:
    """Install :class:`_DeferredNumpyExtras` unless one of its modules is loaded."""
    names = _DeferredNumpyExtras.NAMES
    if any(n in sys.modules for n in names) or any(isinstance(f, _DeferredNumpyExtras)
                                                   for f in sys.meta_path):
        return
    sys.meta_path.insert(0, _DeferredNumpyExtras())


def run() -> None:
    """The ``certpose`` program (console script and ``python -m certpose``): :func:`main`, then
    exit without the interpreter's last garbage collection."""
    import signal

    from solvers.interrupt import INTERRUPTED

    def on_sigint(signum: int, frame: Any) -> None:
        INTERRUPTED.set()
        raise KeyboardInterrupt

    if signal.getsignal(signal.SIGINT) is signal.default_int_handler:
        signal.signal(signal.SIGINT, on_sigint)
    defer_open3d_plotly()
    defer_numpy_extras()
    # No collections while the start-up imports build their ~10^6 objects (none of them garbage).
    gc.disable()
    try:
        code = main(_startup_gc_paused=True)
    except KeyboardInterrupt:  # during the start-up imports or the parsing
        print("certpose: interrupted", file=sys.stderr)
        code = EXIT_INTERRUPTED
    finally:
        gc.enable()
    if INTERRUPTED.is_set() and code != EXIT_INTERRUPTED:
        # A Ctrl-C that Python swallowed (inside a weakref callback of the imports) still ends
        # the command as interrupted; no output was committed after it.
        print("certpose: interrupted", file=sys.stderr)
        code = EXIT_INTERRUPTED
    if code == EXIT_INTERRUPTED:
        # No interpreter shutdown after Ctrl-C: the interrupted work's objects are still
        # referenced, and libraries' exit-time destructors would report them (Open3D prints
        # its memory statistics on stdout) or fail the exit code. Files are complete or gone
        # already (written through temporary files).
        for stream in (sys.stdout, sys.stderr):
            with contextlib.suppress(Exception):
                stream.flush()
        os._exit(code)
    # The process ends here: the last collection would walk every object numba and scipy
    # created (about 0.5 s per run); frozen objects are skipped, the OS frees the memory.
    gc.freeze()
    sys.exit(code)


if __name__ == "__main__":
    run()
