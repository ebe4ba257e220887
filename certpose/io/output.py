"""Writing results: strict JSON, output paths checked before any work starts, every file
written atomically (a temporary file in the same folder, then a rename), and folders locked
against a second writer."""

from __future__ import annotations

import contextlib
import errno
import json
import math
import os
import secrets
import threading
from collections.abc import Iterator
from enum import Enum
from os import PathLike
from pathlib import Path
from typing import Any

import numpy as np

from solvers.interrupt import raise_if_interrupted

__all__ = [
    "FolderBusyError",
    "atomic_path",
    "check_output_dir",
    "check_output_path",
    "folder_lock",
    "jsonable",
    "to_json",
    "write_json",
    "write_text_atomic",
]


def _temp_name(p: Path) -> Path:
    """A fresh hidden name beside ``p`` with the same suffix (writers infer formats from it)."""
    return p.with_name(f".{p.name}.{os.getpid()}.{secrets.token_hex(4)}.tmp{p.suffix}")


def _probe(parent: Path) -> None:
    """Create and remove a file in ``parent``: the only test that holds for root too
    (``os.access`` says yes to root everywhere, /proc and read-only mounts included)."""
    probe = _temp_name(parent / "probe")
    fd = os.open(probe, os.O_CREAT | os.O_EXCL | os.O_WRONLY, 0o600)
    os.close(fd)
    os.unlink(probe)


def check_output_path(path: str | PathLike[str], *, what: str = "output",
                      force: bool = True) -> Path:
    """Check that ``path`` can be written, before the work that produces it starts.

    The parent folder must exist and a file must be creatable in it (tried, not guessed),
    and ``path`` must not be a folder. An existing file is refused unless ``force``.

    Raises
    ------
    FileExistsError
        ``path`` exists and ``force`` is False.
    OSError
        With a one-line message naming the path.
    """
    p = Path(path)
    if p.is_dir():
        raise OSError(f"{what} path '{p}' is a directory; give a file name.")
    parent = p.parent if str(p.parent) else Path(".")
    if not parent.is_dir():
        raise OSError(f"cannot write {what} '{p}': folder '{parent}' does not exist.")
    if p.exists() and not force:
        raise FileExistsError(f"{what} '{p}' already exists; pass --force to overwrite it.")
    if p.exists() and not os.access(p, os.W_OK):
        raise OSError(f"cannot write {what} '{p}': the file is not writable.")
    try:
        _probe(parent)
    except OSError as exc:
        raise OSError(f"cannot write {what} '{p}': cannot create a file in folder '{parent}' "
                      f"({exc.strerror or exc}).") from None
    return p


@contextlib.contextmanager
def atomic_path(path: str | PathLike[str]) -> Iterator[Path]:
    """A temporary path beside ``path`` to write; renamed onto ``path`` when the block ends
    without an exception, removed otherwise.

    Readers (and a second writer) see either the old file or the complete new one, never a
    partial file; of two writers the last to finish wins. The temporary name keeps the suffix,
    so writers that infer the format from it (``np.savez``, ``savefig``) write the right one.
    """
    p = Path(path)
    tmp = _temp_name(p)
    try:
        yield tmp
        if tmp.exists():
            with open(tmp, "rb+") as fh:  # on disk before the rename makes it visible
                os.fsync(fh.fileno())
            if not tmp.stat().st_mode & 0o044:  # a 0600 file from a library: the umask's mode
                umask = os.umask(0)
                os.umask(umask)
                os.chmod(tmp, 0o666 & ~umask)
        raise_if_interrupted()  # a Ctrl-C Python swallowed commits nothing
        os.replace(tmp, p)
    except BaseException:
        with contextlib.suppress(OSError):
            tmp.unlink()
        raise


def write_text_atomic(path: str | PathLike[str], text: str) -> Path:
    """Write ``text`` (UTF-8) to ``path`` atomically (see :func:`atomic_path`)."""
    p = Path(path)
    with atomic_path(p) as tmp:
        tmp.write_text(text, encoding="utf-8")
    return p


class FolderBusyError(OSError):
    """Another process holds the folder's lock."""


_LOCK_NAME = ".certpose.lock"
_held: dict[str, tuple[int, int]] = {}  # folder -> (file descriptor, depth): re-entrant
_held_guard = threading.Lock()


@contextlib.contextmanager
def folder_lock(folder: str | PathLike[str], *, what: str = "folder") -> Iterator[None]:
    """Hold an exclusive lock on ``folder`` (created if missing) for the block.

    A second process that asks for it is refused at once with :class:`FolderBusyError`
    naming the holder's process id; the same process may nest the lock. The lock is the
    kernel's (``flock`` on ``folder/.certpose.lock``): it is released when the process ends,
    killed or not, so a crash never leaves a folder locked.
    """
    import fcntl

    d = Path(folder)
    d.mkdir(parents=True, exist_ok=True)
    key = os.path.realpath(d)
    with _held_guard:
        if key in _held:
            fd, depth = _held[key]
            _held[key] = (fd, depth + 1)
            nested = True
        else:
            nested = False
    if not nested:
        fd = os.open(d / _LOCK_NAME, os.O_RDWR | os.O_CREAT, 0o644)
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except OSError as exc:
            holder = os.pread(fd, 32, 0).decode(errors="replace").strip() or "unknown"
            os.close(fd)
            if exc.errno in (errno.EAGAIN, errno.EACCES, errno.EWOULDBLOCK):
                raise FolderBusyError(
                    f"{what} '{d}' is in use by another certpose run (process {holder}); wait "
                    "for it to finish or choose another folder.") from None
            raise
        os.ftruncate(fd, 0)
        os.pwrite(fd, f"{os.getpid()}\n".encode(), 0)
        with _held_guard:
            _held[key] = (fd, 1)
    try:
        yield
    finally:
        with _held_guard:
            fd, depth = _held[key]
            if depth > 1:
                _held[key] = (fd, depth - 1)
            else:
                del _held[key]
                os.close(fd)  # releases the flock


def check_output_dir(path: str | PathLike[str], *, what: str = "output") -> Path:
    """Check that folder ``path`` exists and is writable, or can be created, before the work.

    Raises
    ------
    OSError
        With a one-line message naming the path.
    """
    p = Path(path)
    if p.exists():
        if not p.is_dir():
            raise OSError(f"{what} '{p}' is not a directory.")
        if not os.access(p, os.W_OK | os.X_OK):
            raise OSError(f"cannot write into {what} '{p}': the folder is not writable.")
        try:
            _probe(p)
        except OSError as exc:
            raise OSError(f"cannot write into {what} '{p}': {exc.strerror or exc}.") from None
        return p
    ancestor = p.parent
    while not ancestor.exists() and ancestor != ancestor.parent:
        ancestor = ancestor.parent
    if not ancestor.is_dir():
        raise OSError(f"cannot create {what} '{p}': '{ancestor}' is not a directory.")
    if not os.access(ancestor, os.W_OK | os.X_OK):
        raise OSError(f"cannot create {what} '{p}': folder '{ancestor}' is not writable.")
    return p


def jsonable(value: Any) -> Any:
    """``value`` with numpy types, enums, tuples and paths made JSON types; NaN/inf become None.

    JSON has no NaN or infinity; ``null`` is what strict parsers (and other languages) accept.
    """
    if isinstance(value, dict) or hasattr(value, "items") and callable(value.items):
        return {str(k): jsonable(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [jsonable(v) for v in value]
    if isinstance(value, np.ndarray):
        return jsonable(value.tolist())
    if isinstance(value, Enum):
        return jsonable(value.value)
    if isinstance(value, (np.bool_, np.integer, np.floating)):
        value = value.item()
    if isinstance(value, float) and not math.isfinite(value):
        return None
    if isinstance(value, PathLike):
        return os.fspath(value)
    return value


def to_json(payload: Any, *, indent: int | None = 2) -> str:
    """Strict JSON text of ``payload`` (see :func:`jsonable`); never writes ``NaN``."""
    return json.dumps(jsonable(payload), indent=indent, allow_nan=False)


def write_json(path: str | PathLike[str], payload: Any) -> Path:
    """Write ``payload`` as strict JSON to ``path`` atomically; returns the path.

    Raises
    ------
    OSError
        The file cannot be written (one-line message naming it).
    """
    p = Path(path)
    text = to_json(payload) + "\n"
    try:
        write_text_atomic(p, text)
    except OSError as exc:
        raise OSError(f"cannot write JSON file '{p}': {exc.strerror or exc}.") from None
    return p
