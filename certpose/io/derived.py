"""An on-disk cache of what is derived from an object model's points: its self-occlusion table
(:func:`~certpose.model.visibility.cached_visibility_table`) and its axis of revolution
(:func:`~certpose.estimation.modes.revolution_turns`).

Both are deterministic for given points and code, and both were rebuilt by every ``certpose
pose`` call: the mustard bottle's visibility table took 1.15 s of a 3.5 s MLE and its search for
an axis of revolution 0.40 s (2 cores, shared). The program turns this cache on with
:func:`use_derived_cache` (in :func:`~certpose.io.cache.default_cache_dir`); the library caches
only when told to, and then keeps each entry in a file named by a hash of its inputs and of the
source of the modules that compute it (and the open3d version), so that editing that code
computes afresh instead of reading a stale entry. Entries are written beside their final name
and renamed: a concurrent reader (another Dask worker) sees a whole file or none.
"""

from __future__ import annotations

import hashlib
import logging
import os
import tempfile
from collections.abc import Callable, Sequence
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

__all__ = ["cached_arrays", "derived_cache_dir", "source_digest", "use_derived_cache",
           "use_derived_cache_unless_set"]

log = logging.getLogger(__name__)

#: Bumped when the file layout changes.
_FORMAT = "certpose-derived-1"

_DIR: list[Path | None] = [None]


def use_derived_cache(directory: str | os.PathLike[str] | None) -> None:
    """Keep derived data in ``directory`` (its ``derived/`` folder) from now on in this process;
    ``None`` turns the cache off (the default)."""
    _DIR[0] = None if directory is None else Path(directory)


def use_derived_cache_unless_set(directory: str | os.PathLike[str]) -> None:
    """:func:`use_derived_cache` with ``directory`` when no directory is set yet: the model
    cache's folder keeps the models' derived data too, unless the program chose another."""
    if _DIR[0] is None:
        use_derived_cache(directory)


def derived_cache_dir() -> Path | None:
    """The directory :func:`use_derived_cache` set (``None``: off)."""
    return _DIR[0]


def source_digest(modules: Sequence[str]) -> bytes:
    """SHA-256 of the modules' source files and the open3d version: what a cached result was
    computed with (:mod:`certpose.io.cache` keys object models by it too).

    Raises
    ------
    OSError
        When a module has no source file (e.g. an installed wheel without sources).
    """
    import importlib.util

    h = hashlib.sha256()
    for name in modules:
        spec = importlib.util.find_spec(name)
        origin = None if spec is None else spec.origin
        if origin is None or not os.path.isfile(origin):
            raise OSError(f"no source for {name}")
        h.update(Path(origin).read_bytes())
    try:
        from importlib.metadata import version

        h.update(version("open3d").encode())
    except Exception:  # open3d absent or without metadata: the key just lacks it
        h.update(b"open3d?")
    return h.digest()


def _digest(modules: Sequence[str]) -> bytes:
    return hashlib.sha256(_FORMAT.encode() + source_digest(modules)).digest()


def _read(path: Path) -> dict[str, NDArray[np.generic]] | None:
    try:
        with np.load(path, allow_pickle=False) as d:
            if str(d["format"]) != _FORMAT:
                return None
            return {k: d[k] for k in d.files if k != "format"}
    except Exception as exc:  # unreadable or partial: compute afresh
        log.debug("derived cache %s not used: %s", path, exc)
        return None


def _write(path: Path, arrays: dict[str, NDArray[np.generic]]) -> None:
    tmp = None
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        fd, tmp = tempfile.mkstemp(dir=path.parent, suffix=".tmp")
        with os.fdopen(fd, "wb") as f:
            np.savez(f, format=np.array(_FORMAT), **arrays)
        os.replace(tmp, path)
    except OSError as exc:  # a read-only or full disk costs the next call a recomputation
        log.debug("derived cache %s not written: %s", path, exc)
        if tmp is not None and os.path.exists(tmp):
            os.unlink(tmp)


def cached_arrays(kind: str, inputs: bytes, modules: Sequence[str],
                  compute: Callable[[], dict[str, NDArray[np.generic]]]) -> dict[str, NDArray[np.generic]]:
    """``compute()`` (named arrays), read from the cache when computed there before.

    Parameters
    ----------
    kind : str
        What is cached (a file-name prefix), e.g. ``"visibility"``.
    inputs : bytes
        Everything the result depends on besides code (the points' bytes, the options' repr).
    modules : sequence of str
        Modules whose source decides the result (part of the key).
    compute : callable
        Returns the arrays (no object arrays) when the cache has no entry or is off.
    """
    directory = derived_cache_dir()
    path = None
    if directory is not None:
        try:
            key = hashlib.sha256(_digest(modules) + kind.encode() + b"|" + inputs).hexdigest()[:32]
            path = directory / "derived" / f"{kind}-{key}.npz"
        except OSError as exc:
            log.debug("derived cache off: %s", exc)
    if path is not None and path.is_file():
        arrays = _read(path)
        if arrays is not None:
            return arrays
    arrays = compute()
    if path is not None:
        _write(path, arrays)
    return arrays
