"""Writing results: strict JSON, and output paths checked before any work starts."""

from __future__ import annotations

import json
import math
import os
from enum import Enum
from os import PathLike
from pathlib import Path
from typing import Any

import numpy as np

__all__ = ["check_output_dir", "check_output_path", "jsonable", "to_json", "write_json"]


def check_output_path(path: str | PathLike[str], *, what: str = "output") -> Path:
    """Check that ``path`` can be written, before the work that produces it starts.

    The parent folder must exist and be writable, and ``path`` must not be a folder (an
    existing file is overwritten).

    Raises
    ------
    OSError
        With a one-line message naming the path.
    """
    p = Path(path)
    if p.is_dir():
        raise OSError(f"{what} path '{p}' is a directory; give a file name.")
    parent = p.parent if str(p.parent) else Path(".")
    if not parent.is_dir():
        raise OSError(f"cannot write {what} '{p}': folder '{parent}' does not exist.")
    if p.exists() and not os.access(p, os.W_OK):
        raise OSError(f"cannot write {what} '{p}': the file is not writable.")
    if not p.exists() and not os.access(parent, os.W_OK | os.X_OK):
        raise OSError(f"cannot write {what} '{p}': folder '{parent}' is not writable.")
    return p


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
    """Write ``payload`` as strict JSON to ``path``; returns the path.

    Raises
    ------
    OSError
        The file cannot be written (one-line message naming it).
    """
    p = Path(path)
    text = to_json(payload) + "\n"
    try:
        p.write_text(text, encoding="utf-8")
    except OSError as exc:
        raise OSError(f"cannot write JSON file '{p}': {exc.strerror or exc}.") from None
    return p
