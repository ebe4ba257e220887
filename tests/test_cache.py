"""The object-model cache of ``certpose pose``: the model read back is the one built."""

from __future__ import annotations

import numpy as np
import pytest

from certpose.geometry.features import FPFHBackbone
from certpose.geometry.objects import object_from_points
from certpose.io.cache import (
    _key,
    default_cache_dir,
    object_from_points_cached,
    visibility_table_cached,
)
from tests.conftest import box_surface


def _same(a, b) -> None:
    assert a.name == b.name
    for k in ("points", "descriptors", "normals", "areas"):
        np.testing.assert_array_equal(getattr(a, k), getattr(b, k))


def test_cached_object_model_is_the_built_one(tmp_path) -> None:
    pts = box_surface(np.random.default_rng(1), np.array([0.06, 0.04, 0.03]), 400)
    fresh = object_from_points(pts, FPFHBackbone(), voxel_size=0.005, name="box")
    first = object_from_points_cached(pts, FPFHBackbone(), voxel_size=0.005, name="box",
                                      cache_dir=tmp_path)
    files = sorted((tmp_path / "objects").glob("*.npz"))
    assert len(files) == 1
    second = object_from_points_cached(pts, FPFHBackbone(), voxel_size=0.005, name="box",
                                       cache_dir=tmp_path)
    _same(first, fresh)
    _same(second, fresh)
    # Another backbone, voxel size or point set is another key.
    key = _key(pts, FPFHBackbone(), 0.005, "box", 0)
    assert files[0].stem == key
    assert len({key, _key(pts, FPFHBackbone(radius=0.02), 0.005, "box", 0),
                _key(pts, FPFHBackbone(), 0.006, "box", 0), _key(pts[:-1], FPFHBackbone(), 0.005, "box", 0),
                _key(pts, FPFHBackbone(), 0.005, "box", 1)}) == 5
    # A damaged file is rebuilt, not read.
    files[0].write_bytes(b"not an npz")
    _same(object_from_points_cached(pts, FPFHBackbone(), voxel_size=0.005, name="box",
                                    cache_dir=tmp_path), fresh)
    # A cache file that cannot be written (here a directory stands in its place) costs a
    # rebuild, and leaves no half-written file behind.
    files[0].unlink()
    files[0].mkdir()
    _same(object_from_points_cached(pts, FPFHBackbone(), voxel_size=0.005, name="box",
                                    cache_dir=tmp_path), fresh)
    assert sorted(p.name for p in (tmp_path / "objects").iterdir()) == [files[0].name]
    with pytest.raises(TypeError, match="rng"):
        object_from_points_cached(pts, FPFHBackbone(), voxel_size=0.005,
                                  rng=np.random.default_rng(0))


def test_default_cache_dir(monkeypatch, tmp_path) -> None:
    monkeypatch.setenv("CERTPOSE_CACHE_DIR", str(tmp_path))
    assert default_cache_dir() == tmp_path
    monkeypatch.setenv("CERTPOSE_CACHE_DIR", "")
    assert default_cache_dir() is None
    monkeypatch.delenv("CERTPOSE_CACHE_DIR")
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path))
    assert default_cache_dir() == tmp_path / "certpose"


def test_cached_revolution_model_has_its_own_key(tmp_path) -> None:
    from tests.test_revolution import _cup

    pts, _ = _cup(4000, np.random.default_rng(2))
    plain = object_from_points_cached(pts, FPFHBackbone(), voxel_size=0.005, cache_dir=tmp_path)
    sym = object_from_points_cached(pts, FPFHBackbone(), voxel_size=0.005, cache_dir=tmp_path,
                                    revolution="auto")
    assert len(list((tmp_path / "objects").glob("*.npz"))) == 2
    _same(sym, object_from_points(pts, FPFHBackbone(), voxel_size=0.005, revolution="auto"))
    _same(object_from_points_cached(pts, FPFHBackbone(), voxel_size=0.005, cache_dir=tmp_path,
                                    revolution="auto"), sym)
    assert not np.array_equal(plain.points, sym.points)
    assert _key(pts, FPFHBackbone(), 0.005, "", 0) != _key(pts, FPFHBackbone(), 0.005, "", 0, "auto")


def _same_table(a, b) -> None:
    assert (a.faces, a.grazing) == (b.faces, b.grazing)
    np.testing.assert_array_equal(a.normals, b.normals)
    assert (a.table is None) == (b.table is None)
    if a.table is not None:
        np.testing.assert_array_equal(a.table, b.table)


def test_cached_visibility_table_is_the_built_one(tmp_path, monkeypatch) -> None:
    from certpose.model import visibility as vis

    # Two balls 3 cm apart: not convex (each hides part of the other), so a table is not None.
    rng = np.random.default_rng(2)
    normals = rng.normal(size=(800, 3))
    normals /= np.linalg.norm(normals, axis=1, keepdims=True)
    points = 0.01 * normals + np.where(np.arange(800)[:, None] < 400, 0.0, 1.0) * [0.03, 0, 0]
    model = type("Model", (), {"points": points, "normals": normals})
    build = vis.visibility_table
    fresh = build(model.points, model.normals)
    assert fresh.table is not None
    monkeypatch.setattr(vis, "_TABLES", {})
    first = visibility_table_cached(model.points, model.normals, cache_dir=tmp_path)
    files = list((tmp_path / "derived").glob("visibility-*.npz"))
    assert len(files) == 1
    _same_table(first, fresh)
    # Another process (an empty table memory) reads it back instead of casting rays, and
    # keeps it where the likelihood looks for it.
    monkeypatch.setattr(vis, "_TABLES", {})

    def no_build(*args, **kwargs):
        raise AssertionError("rebuilt")

    monkeypatch.setattr(vis, "visibility_table", no_build)
    second = visibility_table_cached(model.points, model.normals, cache_dir=tmp_path)
    _same_table(second, fresh)
    assert vis.cached_visibility_table(model.points, model.normals) is second
    # A damaged file is rebuilt, not read.
    monkeypatch.setattr(vis, "visibility_table", build)
    monkeypatch.setattr(vis, "_TABLES", {})
    files[0].write_bytes(b"not an npz")
    _same_table(visibility_table_cached(model.points, model.normals, cache_dir=tmp_path), fresh)
    # A table this process holds already is written for the other processes too.
    files[0].unlink()
    _same_table(visibility_table_cached(model.points, model.normals, cache_dir=tmp_path), fresh)
    assert files[0].is_file()
    # Without a cache folder: the process's memory only.
    monkeypatch.setattr(vis, "_TABLES", {})
    _same_table(visibility_table_cached(model.points, model.normals), fresh)
    assert len(list((tmp_path / "derived").glob("visibility-*.npz"))) == 1
