"""Object points spread evenly over the surface, with the area each stands for (issue 10 item 5)."""

from __future__ import annotations

import math

import numpy as np
import pytest

from certpose.geometry.features import FPFHBackbone
from certpose.geometry.objects import (
    MIN_SURFACE_POINTS,
    ObjectModel,
    object_from_points,
    sample_surface,
)
from tests.conftest import mug_body, mug_on_0000, refined_turn

VS = 0.005
# A mug without handle: 4-mm wall (outer radius 40 mm, inner 36 mm), 80 mm tall, closed 4-mm
# bottom, open top with a flat rim.
R_OUT, R_IN, H, BOTTOM = 0.040, 0.036, 0.080, 0.004
AREA = {
    "outer": 2 * math.pi * R_OUT * H,
    "inner": 2 * math.pi * R_IN * (H - BOTTOM),
    "bottom_out": math.pi * R_OUT**2,
    "bottom_in": math.pi * R_IN**2,
    "rim": math.pi * (R_OUT**2 - R_IN**2),
}


def _azimuth(rng: np.random.Generator, m: int, uneven: bool) -> np.ndarray:
    """``m`` azimuths, uniform or with density proportional to 2 + cos(theta) (three times
    denser at 0 than at pi, as uneven as YCB-Video's ``points.xyz`` around the mug)."""
    th = rng.uniform(-np.pi, np.pi, 4 * m)
    if uneven:
        th = th[rng.uniform(0, 3, th.size) < 2 + np.cos(th)]
    return th[:m]


def _cup_points(rng: np.random.Generator, n: int, *, parts: tuple[str, ...] = tuple(AREA),
                uneven: bool = False) -> np.ndarray:
    """``n`` random points on the given parts of the cup, in proportion to their areas."""
    total = sum(AREA[k] for k in parts)
    out = []
    for name in parts:
        th = _azimuth(rng, int(round(n * AREA[name] / total)), uneven)
        if name in ("outer", "inner"):
            r = R_OUT if name == "outer" else R_IN
            z = rng.uniform(0.0 if name == "outer" else BOTTOM, H, th.size)
            out.append(np.c_[r * np.cos(th), r * np.sin(th), z])
        else:
            lo, hi, z = {"bottom_out": (0, R_OUT, 0.0), "bottom_in": (0, R_IN, BOTTOM),
                         "rim": (R_IN, R_OUT, H)}[name]
            r = np.sqrt(rng.uniform(lo**2, hi**2, th.size))
            out.append(np.c_[r * np.cos(th), r * np.sin(th), np.full(th.size, z)])
    return np.concatenate(out)


def _wall(p: np.ndarray, r: float) -> np.ndarray:
    """The mid-height band of the cylinder of radius ``r`` (within 1.5 mm of it)."""
    rr = np.hypot(p[:, 0], p[:, 1])
    return (p[:, 2] > 0.015) & (p[:, 2] < H - 0.015) & (np.abs(rr - r) < 0.0015)


def _sector_density(p: np.ndarray, areas: np.ndarray, r: float) -> np.ndarray:
    """Sampled area per unit of true area in 12 sectors of a wall's mid-height band."""
    band = _wall(p, r)
    th = np.arctan2(p[band, 1], p[band, 0])
    true = 2 * math.pi * r * (H - 0.03) / 12
    return np.histogram(th, bins=12, range=(-np.pi, np.pi), weights=areas[band])[0] / true


@pytest.mark.slow
def test_a_thin_wall_keeps_both_sides_evenly():
    # Both sides of the 4-mm wall sampled about 1.5 mm apart (denser than the wall is thick).
    pts = _cup_points(np.random.default_rng(0), 20_000)
    p, n, areas = sample_surface(pts, voxel_size=VS, density=2.0, rng=0)
    assert areas.sum() == pytest.approx(sum(AREA.values()), rel=0.03)
    for r in (R_OUT, R_IN):
        density = _sector_density(p, areas, r)
        assert density.min() > 0.85 and density.max() < 1.15, (r, density)
    # Unit normals, outwards on the outer side and towards the axis on the inner side.
    np.testing.assert_allclose(np.linalg.norm(n, axis=1), 1.0, atol=1e-9)
    radial = np.c_[p[:, 0], p[:, 1], np.zeros(len(p))]
    radial /= np.linalg.norm(radial, axis=1, keepdims=True)
    outer, inner = _wall(p, R_OUT), _wall(p, R_IN)
    assert np.mean(np.einsum("ij,ij->i", n[outer], radial[outer]) > 0.8) > 0.9
    assert np.mean(np.einsum("ij,ij->i", n[inner], radial[inner]) < -0.8) > 0.9
    # The voxel average (5-mm voxels) merges the sides in places: points between them.
    from certpose.geometry.rgbd import StructuredPointCloud

    vox = StructuredPointCloud(pts, np.zeros((len(pts), 0))).voxel_downsample(VS).points
    rr = np.hypot(vox[:, 0], vox[:, 1])
    assert np.mean((rr > R_IN + 0.001) & (rr < R_OUT - 0.001)) > 0.1
    rr = np.hypot(p[:, 0], p[:, 1])
    assert np.mean((rr > R_IN + 0.001) & (rr < R_OUT - 0.001)) < 0.03


@pytest.mark.slow
def test_samples_are_even_where_the_input_is_not():
    # A single-sheet mug (as YCB-Video's points.xyz is): side wall and bottom, the input three
    # times denser on one side of the axis than on the other.
    pts = _cup_points(np.random.default_rng(0), 5000, parts=("outer", "bottom_out"), uneven=True)
    band = _wall(pts, R_OUT)
    raw = np.histogram(np.arctan2(pts[band, 1], pts[band, 0]), bins=12, range=(-np.pi, np.pi))[0]
    assert raw.max() / raw.min() > 2.0  # the input is uneven
    p, n, areas = sample_surface(pts, voxel_size=VS, density=2.0, rng=0, area_weights="equal")
    density = _sector_density(p, areas, R_OUT)
    assert density.min() > 0.85 and density.max() < 1.15, density
    # The area each sample stands for: equal, summing to the surface's area.
    assert areas.shape == (len(p),) and np.all(areas > 0)
    np.testing.assert_allclose(areas, areas[0])
    assert areas.sum() == pytest.approx(AREA["outer"] + AREA["bottom_out"], rel=0.05)
    # Spacing: about 0.7 voxel at density 2 (samples per voxel_size**2).
    from scipy.spatial import cKDTree

    assert 0.4 * VS < np.median(cKDTree(p).query(p, k=2)[0][:, 1]) < 0.9 * VS
    # Denser sampling: twice the points, the same area.
    p4, _, a4 = sample_surface(pts, voxel_size=VS, density=4.0, rng=0, area_weights="equal")
    assert len(p4) == pytest.approx(2 * len(p), rel=0.05)
    assert a4.sum() == pytest.approx(areas.sum(), rel=0.02)


def _half_band_spread(p: np.ndarray, areas: np.ndarray) -> float:
    """Range of the sampled area of the outer wall's mid-height band over its halves (72
    turns), relative to a half's true area: what a view of one side of a turning cylinder
    counts."""
    band = _wall(p, R_OUT)
    th = np.arctan2(p[band, 1], p[band, 0])
    half = [areas[band][np.mod(th - t0, 2 * np.pi) < np.pi].sum()
            for t0 in np.linspace(0, 2 * np.pi, 72, endpoint=False)]
    return (max(half) - min(half)) / (math.pi * R_OUT * (H - 0.03))


@pytest.mark.slow
@pytest.mark.parametrize("seed", [0, 1])
def test_voronoi_areas_weigh_each_region_by_its_area(seed):
    # The uneven single-sheet mug: Poisson-disk samples are even on average only (the halves of
    # the band hold 3.4% / 5.4% more or less sample area than their true area with equal areas,
    # seeds 0 / 1); each sample's Voronoi cell on the mesh evens them out (2.0% / 2.1%: what
    # is left is the reconstructed surface's own).
    pts = _cup_points(np.random.default_rng(seed), 5000, parts=("outer", "bottom_out"), uneven=True)
    p, _, equal = sample_surface(pts, voxel_size=VS, density=2.0, rng=seed, area_weights="equal")
    q, _, cells = sample_surface(pts, voxel_size=VS, density=2.0, rng=seed)  # the default
    np.testing.assert_array_equal(p, q)  # the same samples, other weights
    assert np.all(cells > 0) and 0.1 < cells.std() / cells.mean() < 0.3
    assert cells.sum() == pytest.approx(equal.sum(), rel=0.01)
    assert _half_band_spread(p, cells) < 0.03 < _half_band_spread(p, equal)
    density = _sector_density(p, cells, R_OUT)
    assert density.min() > 0.93 and density.max() < 1.07, density


@pytest.mark.slow
def test_sampling_is_reproducible():
    # Coarse (1-cm voxels, 600 points): quick.
    pts = _cup_points(np.random.default_rng(1), 600, parts=("outer", "bottom_out"))
    a, _, _ = sample_surface(pts, voxel_size=0.01, rng=3)
    b, _, _ = sample_surface(pts, voxel_size=0.01, rng=3)
    c, _, _ = sample_surface(pts, voxel_size=0.01, rng=4)
    np.testing.assert_array_equal(a, b)
    assert a.shape != c.shape or not np.array_equal(a, c)


def test_bad_input_gives_a_clear_error():
    good = _cup_points(np.random.default_rng(2), 500)
    with pytest.raises(ValueError, match=rf"at least {MIN_SURFACE_POINTS} points, got 0"):
        sample_surface(np.zeros((0, 3)), voxel_size=VS)
    with pytest.raises(ValueError, match=rf"at least {MIN_SURFACE_POINTS} points, got 10"):
        sample_surface(good[:10], voxel_size=VS)
    bad = good.copy()
    bad[3, 1] = np.nan
    with pytest.raises(ValueError, match="NaN or inf"):
        sample_surface(bad, voxel_size=VS)
    with pytest.raises(ValueError, match=r"shape \(N, 3\)"):
        sample_surface(good[:, :2], voxel_size=VS)
    with pytest.raises(ValueError, match="degenerate"):
        sample_surface(np.outer(np.linspace(0, 0.1, 50), [1.0, 2.0, 3.0]), voxel_size=VS)
    with pytest.raises(ValueError, match="density"):
        sample_surface(good, voxel_size=VS, density=0.0)
    with pytest.raises(ValueError, match="voxel_size"):
        sample_surface(good, voxel_size=-1.0)
    with pytest.raises(ValueError, match="sampling"):
        object_from_points(good, FPFHBackbone(), voxel_size=VS, sampling="mesh")
    with pytest.raises(ValueError, match="area_weights"):
        sample_surface(good, voxel_size=VS, area_weights="delaunay")
    with pytest.raises(ValueError, match="area_weights"):
        object_from_points(good, FPFHBackbone(), voxel_size=VS, area_weights="delaunay")
    with pytest.raises(ValueError, match="area_weights.*surface"):
        object_from_points(good, FPFHBackbone(), voxel_size=VS, sampling="voxel", area_weights="voronoi")
    with pytest.raises(ValueError, match="area_weights.*surface"):
        object_from_points(good, FPFHBackbone(), voxel_size=VS, sampling="voxel", area_weights="equal")


def test_model_points_in_millimetres_are_refused_before_the_work(tmp_path, capsys):
    # YCB/BOP meshes come in millimetres: the mug's points x 1000 made open3d allocate 4e9
    # surface samples (`certpose pose: error: std::bad_alloc`, exit 1, after the scene was
    # built), and `object build`'s voxel model blamed the views' poses.
    from certpose.cli import main
    from certpose.geometry.objects import MAX_SURFACE_SAMPLES
    from certpose.io.ycbv import load_model_points
    from tests.conftest import require_data

    root = require_data("ycbv", "0000").parent
    mug = load_model_points(root / "models" / "025_mug" / "points.xyz")
    for sampling in ("surface", "voxel"):
        with pytest.raises(ValueError, match=r"span 116 m, 23194 voxels .* must be in metres"):
            object_from_points(mug * 1000.0, FPFHBackbone(), voxel_size=0.005, sampling=sampling)
    # Within the span limit, a surface that would take too many samples (refused before
    # open3d allocates them; here by the density, 1.2 million samples).
    with pytest.raises(ValueError, match=rf"more than {MAX_SURFACE_SAMPLES}: are the points in metres"):
        sample_surface(mug, voxel_size=0.005, density=1000.0)
    mm = tmp_path / "mug_mm.xyz"
    np.savetxt(mm, mug * 1000.0)
    for argv in (["pose", "--ycbv", str(root), "--model", str(mm)],
                 ["object", "build", "--ycbv", str(root), "--object", "025_mug", "--views",
                  "0000/000001", "--model", str(mm), "-o", str(tmp_path / "m.npz")]):
        assert main(argv) == 2
        err = capsys.readouterr().err
        assert err.count("\n") == 1 and "must be in metres" in err, err
    # The metre model still builds.
    assert len(object_from_points(mug, FPFHBackbone(), voxel_size=0.005, sampling="voxel")) > 0


def test_object_model_areas_are_validated_and_kept_by_subsample():
    rng = np.random.default_rng(0)
    pts = rng.normal(scale=0.02, size=(200, 3))
    desc = np.tile(np.eye(4)[0], (200, 1))
    areas = rng.uniform(1e-6, 3e-5, 200)
    obj = ObjectModel(pts, desc, areas=areas)
    assert obj.area == pytest.approx(areas.sum())
    sub = obj.subsample(20, rng=0)
    assert len(sub) == 20 and sub.area == pytest.approx(obj.area)  # every area handed to a kept point
    assert obj.select(np.arange(50)).area == pytest.approx(areas[:50].sum())
    assert ObjectModel(pts, desc).area is None
    with pytest.raises(ValueError, match=r"`areas` to have shape \(200,\)"):
        ObjectModel(pts, desc, areas=areas[:5])
    with pytest.raises(ValueError, match="strictly positive"):
        ObjectModel(pts, desc, areas=-areas)
    with pytest.raises(ValueError, match="NaN or inf"):
        ObjectModel(pts, desc, areas=np.full(200, np.nan))


@pytest.mark.slow
def test_object_from_points_surface_model():
    pts = _cup_points(np.random.default_rng(0), 5000, parts=("outer", "bottom_out"))
    obj = object_from_points(pts, FPFHBackbone(), voxel_size=VS, colors=np.full(pts.shape, 0.5),
                             sampling="surface", name="cup")
    assert obj.areas is not None
    assert obj.area == pytest.approx(AREA["outer"] + AREA["bottom_out"], rel=0.05)
    assert obj.descriptors.shape == (len(obj), 33) and obj.colors.shape == (len(obj), 3)
    vox = object_from_points(pts, FPFHBackbone(), voxel_size=VS, sampling="voxel")
    assert vox.areas is None


@pytest.mark.slow
def test_even_sampling_smooths_eq1_along_the_mugs_hidden_handle_arc():
    # YCB-Video 0000/000002: turning the mug about its body's axis inside the arc where its
    # handle is hidden, the body's share of eq. (1) should barely change. With the voxel
    # average of points.xyz it jumps by about 3.5 nats per 2-deg step (uneven azimuthal density,
    # walls merged in some voxels), with the even surface samples by about half that per unit
    # of eq. (1)'s weight (measured 3.5 and 2.0 nats, total weights 1139 and 1269: the surface
    # holds the inner wall near the rim that the voxel average merges with the outer one).
    from scipy.spatial.transform import Rotation

    from certpose.model.likelihood import LikelihoodParams, PoseLikelihood

    s, G, C, _ = mug_on_0000("000002")
    steps, weights = {}, {}
    for sampling in ("voxel", "surface"):
        obj = object_from_points(s.model_points, FPFHBackbone(), voxel_size=VS, sampling=sampling)
        # Measured on the voxel free space of the paper's eq. (1), where every point counts.
        lik = PoseLikelihood(s.scene, s.classification, obj, params=LikelihoodParams(free_space="voxels"))
        body = obj.points[:, 0] < 0.045
        vals = []
        for a in np.radians(np.arange(-10.0, 61.0, 2.0)):
            Rz = Rotation.from_rotvec([0.0, 0.0, a]).as_matrix()
            T = G.copy()
            T[:3, :3] = G[:3, :3] @ Rz
            T[:3, 3] = G[:3, 3] + G[:3, :3] @ (C - Rz @ C)
            vals.append(lik.point_terms(T)[body].sum())
        steps[sampling] = float(np.abs(np.diff(vals)).mean())
        weights[sampling] = lik.total_weight
    assert 1.0 < weights["surface"] / weights["voxel"] < 1.2, weights
    assert steps["surface"] < 2.5, steps
    assert steps["surface"] / weights["surface"] < 0.6 * steps["voxel"] / weights["voxel"], (steps, weights)


@pytest.mark.slow
def test_voronoi_areas_flatten_the_mug_body_along_its_hidden_handle_arc():
    # YCB-Video 0000/000001: the mug's body (handle dropped) turned about its axis inside the
    # arc where the handle is hidden, the other five degrees of freedom refined on eq. (1)
    # without the similarity (beta = 0: the classifier's term and free space; the classifier's
    # term blurred by 7.5 mm, free space charged at the point from 3.5 mm). With equal areas
    # the body's value drifts along the arc by 7.1 nats (the samples' count per region varies by
    # a few percent), with the samples' Voronoi cells by 2.6 (every 5 deg over -20..70 deg;
    # examples/benchmarks/bench_arc.py has the whole arc).
    from certpose.model.likelihood import LikelihoodParams, PoseLikelihood

    s, G, C, turned_pose = mug_on_0000("000001")
    params = LikelihoodParams(beta=0.0, field_blur=0.0075, free_space_at="point",
                              free_space_tolerance=0.0035, free_space_ramp=0.0025)
    ranges = {}
    for weights in ("equal", "voronoi"):
        obj = object_from_points(s.model_points, FPFHBackbone(), voxel_size=s.scene.voxel_size,
                                 area_weights=weights)
        lik = PoseLikelihood(s.scene, s.classification, mug_body(obj), params=params)
        best = [float(lik(refined_turn(lik, G, C, turned_pose, a))) for a in np.arange(-20.0, 71.0, 5.0)]
        ranges[weights] = float(np.ptp(best))
    assert ranges["voronoi"] < 4.5 < ranges["equal"], ranges
