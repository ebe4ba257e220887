"""Ctrl-C that a compiled kernel turned into another exception.

A ``KeyboardInterrupt`` raised while a numba kernel (or another C extension) is running can come
back as a ``SystemError`` ("returned a result with an exception set") whose cause or context is
the interrupt. Code that catches ``Exception`` to keep going (one failed solve must not stop a
benchmark) would then swallow the user's Ctrl-C: it calls :func:`reraise_interrupt` first.
"""

from __future__ import annotations

import threading

__all__ = ["interrupt_in", "reraise_interrupt"]


def interrupt_in(exc: BaseException) -> KeyboardInterrupt | None:
    """The ``KeyboardInterrupt`` in ``exc``'s chain of causes and contexts, if any."""
    seen: set[int] = set()
    stack: list[BaseException | None] = [exc]
    while stack:
        e = stack.pop()
        if e is None or id(e) in seen:
            continue
        seen.add(id(e))
        if isinstance(e, KeyboardInterrupt):
            return e
        stack.extend((e.__cause__, e.__context__))
    return None


def reraise_interrupt(exc: BaseException) -> None:
    """Raise ``KeyboardInterrupt`` if ``exc`` carries one; otherwise return."""
    found = interrupt_in(exc)
    if found is not None:
        raise KeyboardInterrupt() from exc


#: Set by the command line's SIGINT handler: a Ctrl-C that Python swallowed (raised inside a
#: weakref callback of the import machinery, "Exception ignored") still counts, and outputs are
#: not committed after it (:func:`certpose.io.output.atomic_path`).
INTERRUPTED = threading.Event()


def raise_if_interrupted() -> None:
    """Raise ``KeyboardInterrupt`` if a Ctrl-C was received (:data:`INTERRUPTED`)."""
    if INTERRUPTED.is_set():
        raise KeyboardInterrupt()
