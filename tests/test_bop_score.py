"""BOP metrics against hand-computed cases, and `certpose score` on ground-truth results."""

from __future__ import annotations

import csv
import json

import numpy as np
import pytest

from certpose.bop.metrics import adi, distance_image, mspd, mssd, vsd
from certpose.bop.results import BOP_COLUMNS, bop_row_cells
from certpose.bop.score import match_and_recall, score_bop
from tests.conftest import require_data

K = np.array([[1000.0, 0, 50], [0, 1000.0, 50], [0, 0, 1]])


def _square(r0, c0, n=10, z=1.0, shape=(100, 100)):
    d = np.zeros(shape)
    d[r0:r0 + n, c0:c0 + n] = z
    return d


def test_vsd_hand_computed():
    gt = _square(45, 40)
    test = np.zeros_like(gt)  # no measurement: every rendered pixel counts as visible
    # Shifted by 5 columns: 50 common pixels of a union of 150 -> 100 / 150 for every tau.
    est = _square(45, 45)
    np.testing.assert_allclose(vsd(est, gt, test, K, delta=0.015, taus=[0.1, 0.5],
                                   diameter=0.1), [2 / 3, 2 / 3])
    # Same pixels 5 cm further: the distances differ by 5 cm * sqrt(1 + x^2 + y^2) (< 1.0001),
    # half the diameter: costly at tau 0.3, not at 0.6.
    far = _square(45, 40, z=1.05)
    np.testing.assert_allclose(vsd(far, gt, test, K, delta=0.1, taus=[0.3, 0.6], diameter=0.1),
                               [1.0, 0.0])
    # The test depth 2 cm in front of the estimate (beyond delta = 1.5 cm) hides it, but not
    # where the ground truth is visible (the estimate's mask includes those pixels).
    test = _square(45, 40, z=0.98)
    e = vsd(_square(45, 45, z=1.0), gt, test, K, delta=0.015, taus=[0.05], diameter=0.1)
    # visib_gt: none (the test is 2 cm in front everywhere on the ground truth's square).
    # visib_est: its 50 pixels outside the test square (test depth 0 there) -> 50 / 50.
    np.testing.assert_allclose(e, [1.0])
    # Nothing rendered anywhere: error 1.
    z = np.zeros_like(gt)
    np.testing.assert_allclose(vsd(z, z, z, K, delta=0.015, taus=[0.2], diameter=0.1), [1.0])


def test_distance_image_is_the_range():
    d = np.full((3, 4), 2.0)
    Kd = np.array([[2.0, 0, 1], [0, 4.0, 1], [0, 0, 1]])
    r = distance_image(d, Kd)
    x = (np.arange(4) - 1) / 2.0
    y = (np.arange(3) - 1) / 4.0
    np.testing.assert_allclose(r, 2.0 * np.sqrt(1 + x[None] ** 2 + y[:, None] ** 2))


def test_mssd_mspd_with_symmetries():
    pts = np.array([[0.05, 0, 0], [-0.05, 0, 0], [0, 0.02, 0], [0, -0.02, 0.01]])
    R = np.eye(3)
    t = np.array([0.0, 0.0, 1.0])
    I4 = np.eye(4)[None]
    assert mssd(R, t + [0.003, 0, 0], R, t, pts, I4) == pytest.approx(0.003)
    flip = np.diag([-1.0, -1.0, 1.0])  # half turn about z
    S = np.stack([np.eye(4), np.diag([-1.0, -1.0, 1.0, 1.0])])
    far = mssd(flip, t, R, t, pts, I4)
    assert far == pytest.approx(0.1)  # the end points swap
    assert mssd(flip, t, R, t, pts, S) == pytest.approx(0.0, abs=1e-15)
    # MSPD: a 1 mm shift along x at 1 m is 1 pixel with f = 1000.
    assert mspd(R, t + [0.001, 0, 0], R, t, K, pts, I4) == pytest.approx(1.0)
    assert mspd(flip, t, R, t, K, pts, S) == pytest.approx(0.0, abs=1e-9)
    # ADD-S of the flipped pose: each true point has a partner.
    assert adi(flip, t, R, t, pts[:2]) == pytest.approx(0.0, abs=1e-15)


def test_matching_is_greedy_by_score():
    # Two estimates of one object, two valid instances: the better-scored estimate takes the
    # instance it fits best; the other one gets the remaining instance if it fits it.
    items = [{"key": 1, "score": 0.9, "errors": {"a": {"v": 0.1}, "b": {"v": 0.2}}},
             {"key": 1, "score": 0.5, "errors": {"a": {"v": 0.05}, "b": {"v": 0.6}}}]
    err = lambda e: e["v"]  # noqa: E731
    assert match_and_recall(items, 2, err, 0.3) == pytest.approx(0.5)  # b left at 0.6
    assert match_and_recall(items, 2, err, 0.7) == pytest.approx(1.0)
    assert match_and_recall(items, 4, err, 0.7) == pytest.approx(0.5)  # two instances missed


@pytest.fixture(scope="module")
def small_bop(tmp_path_factory):
    from certpose.bop.convert import convert_ycbv

    out = tmp_path_factory.mktemp("bop") / "ycbv"
    convert_ycbv(require_data("ycbv"), out, frames=["0000/000001", "0049/000010"])
    return out


def _results(path, rows):
    with path.open("w", newline="") as fh:
        w = csv.DictWriter(fh, fieldnames=list(BOP_COLUMNS), lineterminator="\n")
        w.writeheader()
        for scene, im, obj, T, score in rows:
            R, t = bop_row_cells(T)
            w.writerow({"scene_id": scene, "im_id": im, "obj_id": obj, "score": score, "R": R,
                        "t": t, "time": 1.0})


def test_score_of_ground_truth_and_of_shifted_poses(small_bop, tmp_path):
    from certpose.io.bop import BOPDataset

    ds = BOPDataset(small_bop)
    targets = ds.targets()
    gt = {}
    for t in targets:
        inst = next(i for i in ds.instances(t.scene_id, t.im_id) if i.obj_id == t.obj_id)
        gt[(t.scene_id, t.im_id, t.obj_id)] = inst.T_camera_object
    res = tmp_path / "gt.csv"
    _results(res, [(*k, T, 1.0) for k, T in gt.items()])
    s = score_bop(small_bop, res)
    assert s.targets == s.estimates == 7
    assert s.ar == {"vsd": 1.0, "mssd": 1.0, "mspd": 1.0, "ar": 1.0}
    assert s.add_s["recall_0.1d"] == 1.0 and s.rotation_error_deg["median"] < 1e-4  # arccos near 1
    # The sugar box (object 3, no symmetry) moved by 0.32 of its diameter along the camera's
    # z axis: MSSD 0.32 d exactly, correct for the thresholds 0.35-0.5 (4 of 10); one missing
    # target (the bowl, 13): no match at all. A worse-scored second estimate of the sugar box
    # at the truth is not evaluated (one instance: the best-scored estimate only).
    d3 = ds.object(3).diameter
    rows = []
    for (scene, im, obj), T in gt.items():
        if obj == 13:
            continue
        if obj == 3:
            T2 = T.copy()
            T2[2, 3] += 0.32 * d3
            rows += [(scene, im, obj, T2, 2.0), (scene, im, obj, T, 1.0)]
        else:
            rows.append((scene, im, obj, T, 1.0))
    _results(res, rows)
    s = score_bop(small_bop, res)
    assert s.estimates == 6
    assert s.recalls["mssd"] == pytest.approx([5 / 7] * 6 + [6 / 7] * 4)
    box = next(r for r in s.per_target if r["obj_id"] == 3)
    assert box["mssd"] == pytest.approx(0.32 * d3)
    assert not next(r for r in s.per_target if r["obj_id"] == 13)["estimated"]


def test_cli_score(small_bop, tmp_path):
    from certpose.cli import main

    res = tmp_path / "empty.csv"
    res.write_text(",".join(BOP_COLUMNS) + "\n")
    out = tmp_path / "s.json"
    assert main(["score", "--bop", str(small_bop), str(res), "--json", str(out), "-q"]) == 0
    data = json.loads(out.read_text())
    assert data["ar"]["ar"] == 0.0 and data["targets"] == 7 and data["estimates"] == 0
    assert main(["score", "--bop", str(small_bop), str(tmp_path / "none.csv"), "-q"]) == 2
