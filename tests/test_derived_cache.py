"""The on-disk cache of data derived from object models (visibility tables, axes of revolution)."""

from __future__ import annotations

import numpy as np
import pytest

from certpose.io.derived import cached_arrays, derived_cache_dir, use_derived_cache


@pytest.fixture
def cache(tmp_path):
    before = derived_cache_dir()
    use_derived_cache(tmp_path)
    yield tmp_path
    use_derived_cache(before)


def test_arrays_are_computed_once_and_read_back(cache):
    calls = []

    def compute():
        calls.append(1)
        return {"a": np.arange(5.0), "b": np.array(3)}

    first = cached_arrays("thing", b"inputs", ("certpose.io.derived",), compute)
    again = cached_arrays("thing", b"inputs", ("certpose.io.derived",), compute)
    other = cached_arrays("thing", b"other inputs", ("certpose.io.derived",), compute)
    assert len(calls) == 2  # the second call read the file
    np.testing.assert_array_equal(first["a"], again["a"])
    assert int(again["b"]) == 3 and other["a"].shape == (5,)
    files = sorted((cache / "derived").glob("thing-*.npz"))
    assert len(files) == 2 and not list((cache / "derived").glob("*.tmp"))


def test_an_unreadable_entry_is_recomputed_and_replaced(cache):
    cached_arrays("thing", b"x", ("certpose.io.derived",), lambda: {"a": np.ones(3)})
    (path,) = (cache / "derived").glob("thing-*.npz")
    path.write_bytes(b"not an npz")
    out = cached_arrays("thing", b"x", ("certpose.io.derived",), lambda: {"a": np.zeros(3)})
    np.testing.assert_array_equal(out["a"], np.zeros(3))
    out = cached_arrays("thing", b"x", ("certpose.io.derived",), lambda: {"a": np.full(3, 7.0)})
    np.testing.assert_array_equal(out["a"], np.zeros(3))  # the replaced file was read


def test_off_by_default_and_when_turned_off(tmp_path):
    before = derived_cache_dir()
    try:
        use_derived_cache(None)
        calls = []
        for _ in range(2):
            cached_arrays("thing", b"x", ("certpose.io.derived",), lambda: calls.append(1) or {"a": np.ones(1)})
        assert len(calls) == 2 and not any(tmp_path.iterdir())
    finally:
        use_derived_cache(before)


def test_the_visibility_table_from_the_cache_equals_a_fresh_one(cache):
    from certpose.model import visibility as vis

    rng = np.random.default_rng(0)
    # An L-shaped (non-convex) cloud of two slabs with normals: its table is not None.
    a = rng.uniform([0, 0, 0], [0.1, 0.02, 0.05], (600, 3))
    b = rng.uniform([0, 0, 0], [0.02, 0.1, 0.05], (600, 3))
    p = np.vstack([a, b])
    n = rng.normal(size=p.shape)
    n /= np.linalg.norm(n, axis=1, keepdims=True)
    fresh = vis.visibility_table(p, n)
    vis._TABLES.clear()
    first = vis.cached_visibility_table(p, n)
    vis._TABLES.clear()  # the next one must come from the disk
    second = vis.cached_visibility_table(p, n)
    assert list((cache / "derived").glob("visibility-*.npz"))
    for t in (first, second):
        assert (t.table is None) == (fresh.table is None)
        if fresh.table is not None:
            np.testing.assert_array_equal(t.table, fresh.table)
        np.testing.assert_array_equal(t.normals, fresh.normals)
        assert t.faces == fresh.faces and t.grazing == fresh.grazing


def test_an_axis_cached_at_another_tolerance_is_not_read(cache, monkeypatch):
    """The cached axis of revolution is keyed by the tolerance too: an axis found at 2.5 sample
    gaps (a box's faces pass then) is not read back once the tolerance is one gap."""
    from scipy.spatial import cKDTree

    from certpose.estimation import modes

    # A 16 x 8 x 4 cm box's faces on a 3 mm grid.
    g = np.arange(-0.08, 0.0801, 0.003)
    faces = []
    half = np.array([0.08, 0.04, 0.02])
    for k in range(3):
        a, b = [i for i in range(3) if i != k]
        u, v = np.meshgrid(g[np.abs(g) <= half[a]], g[np.abs(g) <= half[b]], indexing="ij")
        for s in (-1.0, 1.0):
            f = np.zeros((u.size, 3))
            f[:, a], f[:, b], f[:, k] = u.ravel(), v.ravel(), s * half[k]
            faces.append(f)
    box = np.vstack(faces)
    gap = float(np.median(cKDTree(box).query(box, k=2)[0][:, 1]))
    wide = 8.0  # gaps: wide enough for the box's faces to pass as a surface of revolution
    monkeypatch.setattr(modes, "AXIS_TOLERANCE_GAPS", wide)
    monkeypatch.setattr(modes, "_AXES", {})
    assert modes.revolution_axis(box) is not None, gap
    monkeypatch.setattr(modes, "AXIS_TOLERANCE_GAPS", 1.0)
    monkeypatch.setattr(modes, "_AXES", {})
    assert modes.revolution_axis(box) is None
    assert len(list((cache / "derived").glob("revolution-axis-*.npz"))) == 2
