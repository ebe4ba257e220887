"""The public pose target (certpose.sampling.target): the run's own eq. (1) and temperature."""

from __future__ import annotations

import math

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from certpose.sampling.target import PoseTarget, demo_object_model, pose_target


def test_pose_target_refuses_bad_temperature_and_shapes() -> None:
    with pytest.raises(ValueError, match="`temperature` must be positive"):
        PoseTarget(None, 0.0, np.eye(4))
    with pytest.raises(ValueError, match="`temperature` must be positive"):
        PoseTarget(None, float("nan"), np.eye(4))
    target = PoseTarget(None, 1.0, np.eye(4))
    with pytest.raises(ValueError, match=r"Expected `T_camera_object` to have shape \(4, 4\) or"):
        target.log_likelihood(np.eye(3))
    with pytest.raises(ValueError, match=r"Expected `xi` to have shape \(6,\) or \(n, 6\)"):
        target.chart_log_prob(np.zeros(5), np.eye(4))


def test_pose_target_refuses_a_result_without_a_scene() -> None:
    from certpose.estimation.pipeline import PoseResult

    res = PoseResult(np.eye(4), -np.inf, None, "", "", math.nan, math.nan, {}, None, False,
                     "failed", "no scene")
    with pytest.raises(ValueError, match="no scene field or classifier"):
        pose_target(res, None)


@pytest.mark.slow
def test_pose_target_is_the_demo_runs_target() -> None:
    from certpose.estimation.pipeline import PoseParams, run_demo
    from certpose.sampling import ISParams
    from certpose.sampling.chart import from_chart, to_chart

    res = run_demo(params=PoseParams(sampler=ISParams(draws=2000, resample=300)))
    target = pose_target(res, demo_object_model())
    # The same eq. (1) as the run's MLE and the run's temperature.
    assert target.log_likelihood(res.T_camera_object) == pytest.approx(res.log_likelihood, abs=1e-6)
    assert target.temperature == res.sampling["temperature"]
    assert target(res.T_camera_object) == pytest.approx(res.log_likelihood / target.temperature)
    # Batches: one value per pose, the same as one at a time.
    d = res.distribution
    T = np.concatenate([d.rotations[:4], d.translations[:4, :, None]], axis=2)
    T = np.concatenate([T, np.tile([[[0.0, 0.0, 0.0, 1.0]]], (4, 1, 1))], axis=1)
    batch = target.log_prob(T)
    assert batch.shape == (4,)
    np.testing.assert_allclose(batch, [target.log_prob(t) for t in T], rtol=1e-12)
    # The MLE beats its particles (it maximises eq. (1)).
    assert np.all(batch <= target.log_prob(res.T_camera_object) + 1e-9)
    # The chart: xi = 0 is T_ref itself (Jacobian 1); a turn adds log(2 (1 - cos a) / a^2).
    T_ref = res.T_camera_object
    assert target.chart_log_prob(np.zeros(6), T_ref) == pytest.approx(target.log_prob(T_ref))
    xi = np.r_[0.0, 0.0, 0.3, 0.001, 0.0, 0.0]
    jac = 2.0 * (1.0 - math.cos(0.3)) / 0.3**2
    assert target.chart_log_prob(xi, T_ref) == pytest.approx(
        target.log_prob(from_chart(xi, T_ref)[0]) + math.log(jac))
    assert to_chart(from_chart(xi, T_ref)[:, :3, :3], from_chart(xi, T_ref)[:, :3, 3], T_ref)[0] \
        == pytest.approx(xi)
    # Outside the one chart (|w| >= pi): -inf, not an aliased pose.
    w = Rotation.random(random_state=0).as_rotvec()
    far = np.r_[w / np.linalg.norm(w) * 3.5, 0.0, 0.0, 0.0]
    assert target.chart_log_prob(far, T_ref) == -np.inf
