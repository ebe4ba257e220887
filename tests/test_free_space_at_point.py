"""``LikelihoodParams.free_space_at="point"`` on a real frame: eq. (1) charges free space where
the point itself passes the tolerance, the measure of :func:`certpose.model.arc.free_space_arc`.
(The kernel against the plain-Python reference: tests/test_likelihood.py.)"""

from __future__ import annotations

import numpy as np
import pytest

from certpose.model.likelihood import LikelihoodParams, PoseLikelihood
from tests.conftest import mug_on_0000


@pytest.mark.slow
def test_no_free_space_charge_inside_the_mugs_hidden_handle_arc():
    # YCB-Video 0000/000001: the mug turned about its body axis (no refinement). On the arc
    # where none of the model's points stands deeper than 5 mm in free space (free_space_arc
    # with the same points), the point-relative ramp charges nothing: eq. (1) equals eq. (1)
    # without any free-space charge. The voxel-centre default charges the handle's tip from
    # about 2.5 mm (measured every 5 deg over the arc, -26.5..82.5 deg: 0.6-2.9 nats in the body
    # of the arc, 15.4 and 5.8 at its ends); 10 deg beyond the ends both charge (point
    # 23.9 / 5.1 nats, voxel 63.9 / 32.9).
    from certpose.model.arc import free_space_arc

    s, G, C, turned_pose = mug_on_0000("000001")
    obj = s.object_model
    arc = free_space_arc(s.scene, obj.points, G, centre=C, tolerance=0.005, free_space="voxels")
    assert arc.success
    lo, hi = arc.arc
    assert hi - lo > 60  # the handle hides over a wide arc
    inside = np.r_[np.arange(lo, hi, 5.0), hi]
    beyond = np.array([lo - 10.0, hi + 10.0])
    poses = np.stack([turned_pose(G, C, a, np.zeros(5)) for a in np.r_[inside, beyond]])

    voxel = PoseLikelihood(s.scene, s.classification, obj)
    point = voxel.with_object(obj, params=LikelihoodParams(free_space_at="point"))
    free = voxel.with_object(obj, params=LikelihoodParams(free_space_at="point", free_space_tolerance=1.0))
    charge_point = free(poses) - point(poses)
    charge_voxel = free(poses) - voxel(poses)
    n = len(inside)
    np.testing.assert_allclose(charge_point[:n], 0.0, atol=1e-3)
    assert charge_voxel[:n].max() > 3.0  # the voxel-centre blend charges inside the arc
    assert np.all(charge_point[n:] > 1.0) and np.all(charge_voxel[n:] > 1.0)
