"""An on-disk cache of object models built from model points (``certpose pose --model``).

Building an object model from ``points.xyz`` (:func:`~certpose.geometry.objects.object_from_points`:
a Poisson surface reconstruction, its sampling and the samples' descriptors) is deterministic
for a given input and seed, and took about 1 s of every ``certpose pose`` call (2 cores,
shared). :func:`object_from_points_cached` builds it once and reads it back afterwards. The key
is a hash of everything the result depends on: the points, the backbone, the voxel size, the
name, the seed, and the source of the modules that build the model (and the open3d version),
so that editing that code or upgrading open3d builds afresh instead of reading a stale model.

:func:`visibility_table_cached` keeps an object model's visibility table the same way (under
``visibility/``, keyed by the points, the normals, the grazing option and the source of
:mod:`certpose.model.visibility`), so that the processes of a dataset run read it instead of
each casting its rays.

The program uses :func:`default_cache_dir` (``$CERTPOSE_CACHE_DIR``, else
``$XDG_CACHE_HOME/certpose``, else ``~/.cache/certpose``; ``CERTPOSE_CACHE_DIR=""`` turns the
cache off); the library caches only when given a directory.
"""

from __future__ import annotations

import hashlib
import logging
import os
import tempfile
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import ArrayLike

from certpose.geometry.objects import ObjectModel

__all__ = ["default_cache_dir", "object_from_points_cached", "visibility_table_cached"]

log = logging.getLogger(__name__)

#: Bumped when the file layout changes.
_FORMAT = "certpose-object-cache-1"
# Modules whose code decides the built model.
_SOURCES = ("certpose.geometry.objects", "certpose.geometry.features", "certpose.geometry.rgbd",
            "certpose.geometry.revolution", "certpose.geometry._fpfh_kernels")


def default_cache_dir() -> Path | None:
    """The program's cache directory (see the module docstring); ``None`` when turned off."""
    env = os.environ.get("CERTPOSE_CACHE_DIR")
    if env is not None:
        return Path(env).expanduser() if env.strip() else None
    base = os.environ.get("XDG_CACHE_HOME") or os.path.join(os.path.expanduser("~"), ".cache")
    return Path(base) / "certpose"


def _source_digest(sources: tuple[str, ...] = _SOURCES) -> bytes:
    from certpose.io.derived import source_digest

    return source_digest(sources)


def _key(points: np.ndarray, backbone: Any, voxel_size: float, name: str, rng: int,
         revolution: str | None = None, colors: np.ndarray | None = None,
         mesh: tuple[Any, Any] | None = None) -> str:
    h = hashlib.sha256()
    h.update(_FORMAT.encode())
    h.update(_source_digest())
    h.update(repr(points.shape).encode())
    h.update(np.ascontiguousarray(points, dtype=np.float64).tobytes())
    # Frozen dataclasses: the repr holds every parameter.
    h.update(f"{type(backbone).__module__}.{type(backbone).__qualname__}|{backbone!r}".encode())
    h.update(f"|{float(voxel_size)!r}|{name}|{int(rng)}".encode())
    if revolution is not None:  # absent from the keys of the models built before the option
        h.update(f"|revolution={revolution}".encode())
    if colors is not None:  # likewise
        h.update(b"|colors")
        h.update(np.ascontiguousarray(colors, dtype=np.float64).tobytes())
    if mesh is not None:
        h.update(b"|mesh")
        h.update(np.ascontiguousarray(mesh[0], dtype=np.float64).tobytes())
        h.update(np.ascontiguousarray(mesh[1], dtype=np.int64).tobytes())
    return h.hexdigest()[:32]


def _read(path: Path) -> ObjectModel | None:
    try:
        with np.load(path, allow_pickle=False) as d:
            if str(d["format"]) != _FORMAT:
                return None
            opt = {k: (d[k] if k in d.files else None) for k in ("colors", "normals", "areas")}
            return ObjectModel(d["points"], d["descriptors"], opt["colors"], opt["normals"],
                               str(d["name"]), opt["areas"])
    except Exception as exc:  # unreadable or partial: build afresh
        log.debug("object cache %s not used: %s", path, exc)
        return None


def _write(path: Path, model: ObjectModel) -> None:
    arrays = {"format": np.array(_FORMAT), "points": model.points,
              "descriptors": model.descriptors, "name": np.array(model.name)}
    for k in ("colors", "normals", "areas"):
        if getattr(model, k) is not None:
            arrays[k] = getattr(model, k)
    _save_npz(path, arrays, "object")


def _save_npz(path: Path, arrays: dict[str, Any], what: str) -> None:
    tmp = None
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        # Written beside, then renamed: a concurrent reader sees the whole file or none.
        fd, tmp = tempfile.mkstemp(dir=path.parent, suffix=".tmp")
        with os.fdopen(fd, "wb") as f:
            np.savez(f, **arrays)
        os.replace(tmp, path)
    except OSError as exc:  # a read-only or full disk costs the next call a rebuild, no more
        log.debug("%s cache %s not written: %s", what, path, exc)
        if tmp is not None and os.path.exists(tmp):  # no half-written file left behind
            os.unlink(tmp)


def object_from_points_cached(
    points: ArrayLike,
    backbone: Any,
    *,
    voxel_size: float,
    name: str = "",
    rng: int = 0,
    cache_dir: str | os.PathLike[str] | None = None,
    revolution: str | None = None,
    colors: ArrayLike | None = None,
    mesh: tuple[ArrayLike, ArrayLike] | None = None,
) -> ObjectModel:
    """:func:`~certpose.geometry.objects.object_from_points` (surface sampling), read from
    ``cache_dir`` when built there before with the same inputs and code.

    Parameters
    ----------
    points : (N, 3) array_like
        Model points in the object frame, metres.
    backbone : FeatureBackbone
        A frozen dataclass (its ``repr`` is part of the key), e.g.
        :class:`~certpose.geometry.features.FPFHBackbone`.
    voxel_size : float
        Metres.
    name : str, optional
    rng : int, optional
        Seed of the surface sampling (an int: a generator would make the build irreproducible).
    cache_dir : path, optional
        Where models are kept; ``None`` builds without caching. Given one, this process also
        keeps the data derived from models there (:func:`~certpose.io.derived.use_derived_cache`,
        unless it was set already): their visibility tables and axes of revolution.
    revolution : {"auto"} or None, optional
        :func:`~certpose.geometry.objects.object_from_points`' option (part of the key).
    colors : (N, 3) array_like, optional
        RGB in ``[0, 1]`` (part of the key).
    mesh : tuple of (V, 3) and (F, 3) array_like, optional
        The object's mesh, sampled instead of a surface reconstructed from ``points`` (part of
        the key).

    Returns
    -------
    ObjectModel
        The same arrays as a fresh build.
    """
    from certpose.geometry.objects import object_from_points

    if isinstance(rng, (bool, np.bool_)) or not isinstance(rng, (int, np.integer)):
        raise TypeError(f"`rng` must be an int seed, got {type(rng).__name__}.")
    from certpose.geometry.plausibility import check_model_points

    pts = np.asarray(points, dtype=np.float64)
    check_model_points(pts, name=f"points of model {name!r}" if name else "model points")
    cols = None if colors is None else np.asarray(colors, dtype=np.float64)
    path = None
    if cache_dir is not None:
        from certpose.io.derived import use_derived_cache_unless_set

        use_derived_cache_unless_set(cache_dir)
        try:
            key = _key(pts, backbone, voxel_size, name, int(rng), revolution, cols, mesh)
            path = Path(cache_dir) / "objects" / f"{key}.npz"
        except OSError as exc:
            log.debug("object cache off: %s", exc)
    if path is not None and path.is_file():
        model = _read(path)
        if model is not None:
            log.info("object model %r read from the cache (%s)", name, path)
            return model
    model = object_from_points(pts, backbone, voxel_size=voxel_size, name=name, rng=int(rng),
                               revolution=revolution, colors=cols, mesh=mesh)
    if path is not None:
        _write(path, model)
    return model


def visibility_table_cached(points: ArrayLike, normals: ArrayLike, *, grazing: float = 0.25,
                            cache_dir: str | os.PathLike[str] | None = None) -> Any:
    """:func:`~certpose.model.visibility.cached_visibility_table` (default options), read from
    ``cache_dir`` when built there before from the same points, normals and code.

    A table takes about 0.5 s of ray casting per YCB-Video model; every process that builds a
    likelihood of the model needs it (each Dask worker of a dataset run, each
    ``certpose pose`` call). The table is kept in the derived-data cache of ``cache_dir``
    (:mod:`certpose.io.derived`; a table this process holds already is written there too) and
    in the process's own table memory, where :class:`~certpose.model.likelihood.PoseLikelihood`
    finds it.

    Parameters
    ----------
    points, normals : (N, 3) array_like
        The model's points (metres, object frame) and outward unit normals.
    grazing : float
        See :func:`~certpose.model.visibility.visibility_table`.
    cache_dir : path, optional
        Where tables are kept; ``None``: the table of the process's memory (and of the derived
        cache, when the program turned it on), built if needed.

    Returns
    -------
    VisibilityTable
        The same arrays as a fresh build.
    """
    from certpose.io.derived import derived_cache_dir, use_derived_cache
    from certpose.model import visibility as vis

    p = np.ascontiguousarray(points, dtype=np.float64)
    n = np.ascontiguousarray(normals, dtype=np.float64)
    if cache_dir is None:
        return vis.cached_visibility_table(p, n, grazing=grazing)
    before = derived_cache_dir()
    use_derived_cache(cache_dir)
    try:
        held = vis.cached_visibility_table(p, n, grazing=grazing) if vis.table_in_memory(
            p, n, grazing=grazing) else None
        table = vis._from_disk(p, n, float(grazing), built=held)
    finally:
        use_derived_cache(before)
    vis.remember_table(p, n, held if held is not None else table, grazing=grazing)
    return held if held is not None else table


