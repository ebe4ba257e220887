"""One BLAS thread for loops of many mid-sized dense linear-algebra calls."""

from __future__ import annotations

import contextlib
from collections.abc import Iterator
from typing import Any

_controller: Any = None


@contextlib.contextmanager
def single_thread_blas() -> Iterator[None]:
    """Limit BLAS/LAPACK to one thread inside the block.

    Many eigendecompositions of a few hundred rows run faster on one thread (no
    oversubscription; measured 10-100x slower multi-threaded on a loaded 2-core machine). The
    threadpoolctl controller is built once: building it scans the loaded libraries (about 2 ms,
    as long as a whole K = 20 certificate).
    """
    global _controller
    try:
        from threadpoolctl import ThreadpoolController
    except ImportError:  # optional dependency
        yield
        return
    if _controller is None:
        _controller = ThreadpoolController()
    with _controller.limit(limits=1, user_api="blas"):
        yield
