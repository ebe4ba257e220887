"""Eq. (1)'s colour for model points no view saw (``LikelihoodParams.unseen_color``)."""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
import pytest
from scipy.special import logsumexp

from certpose.geometry.appearance import AppearanceBackbone
from certpose.geometry.objects import ObjectModel
from certpose.model.classifier import ClassifierStatus, ObjectClassification
from certpose.model.grid import EMPTY, OCCUPIED, UNOBSERVED
from certpose.model.likelihood import LikelihoodParams, PoseLikelihood, palette_similarity
from certpose.model.scene import SceneField
from solvers.lie import make_transform

BB = AppearanceBackbone()
COLS = BB.color_columns


def _rows(rng: np.random.Generator, n: int) -> np.ndarray:
    """Descriptors as the backbone makes them: a unit shape block times sqrt(1 - w), a unit
    colour block times sqrt(w)."""
    shape = rng.normal(size=(n, COLS.start))
    colour = rng.normal(size=(n, COLS.stop - COLS.start))
    shape /= np.linalg.norm(shape, axis=1, keepdims=True)
    colour /= np.linalg.norm(colour, axis=1, keepdims=True)
    w = BB.color_weight
    return np.hstack([math.sqrt(1 - w) * shape, math.sqrt(w) * colour])


def _world(seed: int = 0, backbone=BB):
    """A dense random scene described by ``backbone`` and an object of which a third of the
    points carry no colour (their colour block is zero: unseen)."""
    rng = np.random.default_rng(seed)
    shape = (10, 10, 10)
    state = rng.choice([UNOBSERVED, EMPTY, OCCUPIED], size=shape, p=[0.1, 0.1, 0.8]).astype(np.int8)
    desc = np.zeros((*shape, BB.dim))
    occ = state == OCCUPIED
    desc[occ] = _rows(rng, int(occ.sum()))
    scene = SceneField(0.01, np.array([-0.05, -0.05, -0.05]), shape, desc, state, backbone=backbone)
    log_p = np.where(rng.random(shape) < 0.5, math.log(0.9), -5.0)
    cls = ObjectClassification(log_p, occ & (log_p > -1), -5.0, "test", ClassifierStatus.OK, "")
    n = 60
    z = _rows(rng, n)
    unseen = np.arange(n) % 3 == 0
    z[unseen, COLS] = 0.0
    obj = ObjectModel(rng.uniform(-0.02, 0.02, size=(n, 3)), z)
    return scene, cls, obj, unseen


def _pose(seed: int) -> np.ndarray:
    from scipy.spatial.transform import Rotation

    rng = np.random.default_rng(seed)
    return make_transform(Rotation.random(random_state=rng).as_matrix(), rng.uniform(-0.01, 0.01, 3))


def test_palette_similarity_is_the_log_mean_exp_or_the_best():
    rng = np.random.default_rng(1)
    desc = _rows(rng, 7)
    pal = _rows(rng, 5)[:, COLS]
    s = desc[:, COLS] @ pal.T
    beta = 3.6
    expect = (logsumexp(beta * s, axis=1) - math.log(5)) / beta
    np.testing.assert_allclose(palette_similarity(desc, pal, COLS, beta=beta), expect, rtol=1e-5)
    np.testing.assert_allclose(palette_similarity(desc, pal, COLS), s.max(axis=1), rtol=1e-5)
    np.testing.assert_allclose(palette_similarity(desc, pal, COLS, beta=0.0), s.mean(axis=1),
                               rtol=1e-5)
    # Between the mean and the largest.
    m = palette_similarity(desc, pal, COLS, beta=beta)
    assert np.all(m >= s.mean(axis=1) - 1e-6) and np.all(m <= s.max(axis=1) + 1e-6)
    np.testing.assert_allclose(palette_similarity(desc, pal, COLS, beta=beta, chunk=2), m)
    # A scene row without colour has similarity 0 with every colour.
    blank = desc.copy()
    blank[2, COLS] = 0.0
    got = palette_similarity(blank, pal, COLS, beta=beta)
    assert got[2] == 0.0
    np.testing.assert_allclose(np.delete(got, 2), np.delete(m, 2))
    with pytest.raises(ValueError, match="palette"):
        palette_similarity(desc, pal[:0], COLS)
    with pytest.raises(ValueError, match="beta"):
        palette_similarity(desc, pal, COLS, beta=-1.0)


def test_unseen_points_score_the_palette_marginal_at_each_corner():
    """Each unseen point's term equals the term of the same point carrying, at every occupied
    corner, the log-mean-exp of the seen colour blocks' similarities there (computed here with
    scipy on the scene's own descriptors); the seen points' terms do not change."""
    scene, cls, obj, unseen = _world()
    params = LikelihoodParams(beta=4.0)
    lik = PoseLikelihood(scene, cls, obj, params=params)
    plain = PoseLikelihood(scene, cls, obj, params=replace(params, unseen_color="none"))
    # The reference: the scene's descriptors with one more column holding the marginal / 0.9,
    # the unseen points' descriptors with 0.9 there (rows of norm <= 1); "none" eq. (1) on those.
    occ = scene.state == OCCUPIED
    f = scene.descriptors[occ]
    pal = obj.descriptors[~unseen][:, COLS]
    marg = (logsumexp(params.beta * f[:, COLS] @ pal.T, axis=1) - math.log(len(pal))) / params.beta
    desc2 = np.zeros((*scene.shape, BB.dim + 1))
    desc2[occ] = np.hstack([f, marg[:, None] / 0.9])
    scene2 = SceneField(scene.voxel_size, scene.origin, scene.shape, desc2, scene.state)
    obj2 = ObjectModel(obj.points, np.hstack([obj.descriptors, 0.9 * unseen[:, None]]))
    ref = PoseLikelihood(scene2, cls, obj2, params=replace(params, unseen_color="none"))
    moved = 0
    for seed in range(5):
        T = _pose(seed)
        got, want, before = lik.point_terms(T), ref.point_terms(T), plain.point_terms(T)
        np.testing.assert_allclose(got, want, rtol=1e-5, atol=1e-5)
        np.testing.assert_allclose(got[~unseen], before[~unseen], rtol=1e-6, atol=1e-6)
        moved += int(np.sum(np.abs(got[unseen] - before[unseen]) > 1e-3))
        np.testing.assert_allclose(lik.log_likelihood(T), got.sum(), rtol=1e-6)
    assert moved > 20  # the unseen points did change


def test_nothing_is_credited_without_colour_information():
    scene, cls, obj, unseen = _world()
    T = _pose(0)
    base = PoseLikelihood(scene, cls, obj, params=LikelihoodParams(unseen_color="none"))(T)
    # A scene described by a backbone without a colour block (geometry only) ...
    geo = SceneField(scene.voxel_size, scene.origin, scene.shape, scene.descriptors, scene.state)
    assert PoseLikelihood(geo, cls, obj)(T) == pytest.approx(base, rel=1e-9)
    # ... and a model that saw every point or none of its colours: no change.
    z = obj.descriptors.copy()
    z[:, COLS] = 0.0
    blank = ObjectModel(obj.points, z)
    assert PoseLikelihood(scene, cls, blank)(T) == pytest.approx(
        PoseLikelihood(scene, cls, blank, params=LikelihoodParams(unseen_color="none"))(T), rel=1e-9)
    full = ObjectModel(obj.points, _rows(np.random.default_rng(5), len(obj)))
    assert PoseLikelihood(scene, cls, full)(T) == pytest.approx(
        PoseLikelihood(scene, cls, full, params=LikelihoodParams(unseen_color="none"))(T), rel=1e-9)
    with pytest.raises(ValueError, match="unseen_color"):
        LikelihoodParams(unseen_color="mean")


def test_a_subsample_keeps_the_full_models_palette():
    """``with_object`` (the MLE's subsamples) scores the points with the palette of the model
    the likelihood was built with: a point's term does not depend on which others were kept."""
    scene, cls, obj, unseen = _world()
    lik = PoseLikelihood(scene, cls, obj)
    keep = np.arange(len(obj)) < 40
    sub = ObjectModel(obj.points[keep], obj.descriptors[keep])
    T = _pose(3)
    np.testing.assert_allclose(lik.with_object(sub).point_terms(T), lik.point_terms(T)[keep],
                               rtol=1e-6, atol=1e-9)
    # New params recompute the column (beta changes the marginal).
    hot = lik.with_object(obj, params=replace(lik.params, beta=8.0))
    np.testing.assert_allclose(hot.point_terms(T),
                               PoseLikelihood(scene, cls, obj, params=replace(lik.params, beta=8.0))
                               .point_terms(T), rtol=1e-6, atol=1e-9)
