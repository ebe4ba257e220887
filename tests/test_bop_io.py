"""The BOP layout: the YCB-Video converter and the BOP reader (units, masks, models, symmetries)."""

from __future__ import annotations

import json

import numpy as np
import pytest
from scipy.spatial.distance import pdist

from certpose.bop.convert import convert_ycbv, find_symmetries
from certpose.io.bop import BOPDataset, load_bop_targets, symmetry_transforms
from certpose.io.ycbv import load_model_points, load_ycbv_frame
from tests.conftest import require_data

FRAMES = ["0000/000001", "0049/000010"]


@pytest.fixture(scope="module")
def converted(tmp_path_factory):
    root = require_data("ycbv")
    out = tmp_path_factory.mktemp("bop") / "ycbv"
    summary = convert_ycbv(root, out, frames=FRAMES)
    return root, out, summary


def test_layout_and_targets(converted):
    _, out, summary = converted
    assert summary["images"] == 2 and summary["instances"] == 7
    for scene, im in ((0, 1), (49, 10)):
        sdir = out / "test" / f"{scene:06d}"
        for name in ("scene_camera.json", "scene_gt.json", "scene_gt_info.json"):
            assert (sdir / name).is_file()
        assert (sdir / "rgb" / f"{im:06d}.png").is_file()
        assert (sdir / "depth" / f"{im:06d}.png").is_file()
    targets = load_bop_targets(out / "test_targets_bop19.json")
    assert {(t.scene_id, t.im_id, t.obj_id) for t in targets} == {
        (0, 1, 8), (0, 1, 14), (0, 1, 21), (49, 10, 3), (49, 10, 6), (49, 10, 9), (49, 10, 13)}
    cam = json.loads((out / "test" / "000049" / "scene_camera.json").read_text())["10"]
    assert cam["depth_scale"] == pytest.approx(0.1)  # BOP's YCB-V: 0.1 mm per unit


def test_frames_read_back_as_the_ycbv_frames(converted):
    root, out, _ = converted
    ds = BOPDataset(out, "test")
    for name in FRAMES:
        scene, frame = (int(x) for x in name.split("/"))
        yf = load_ycbv_frame(root, name)
        f = ds.frame(scene, frame)
        assert np.array_equal(f.depth, yf.frame.depth)  # metres, bit for bit
        assert np.array_equal(f.color, yf.frame.color)
        assert f.intrinsics == yf.frame.intrinsics
        insts = ds.instances(scene, frame)
        assert [i.obj_id for i in insts] == yf.class_indexes
        for inst, obj in zip(insts, yf.class_names, strict=True):
            assert np.array_equal(ds.mask_visib(scene, frame, inst.gt_id),
                                  yf.label == inst.obj_id)
            np.testing.assert_allclose(inst.T_camera_object, yf.poses[obj], rtol=0, atol=1e-15)
            assert 0.1 <= inst.visib_fract <= 1.0


def test_models_in_metres_with_their_info(converted):
    root, out, _ = converted
    ds = BOPDataset(out)
    names = {13: "024_bowl", 14: "025_mug", 3: "004_sugar_box"}
    for obj_id, name in names.items():
        P = load_model_points(root / "models" / name / "points.xyz")
        obj = ds.object(obj_id)
        assert obj.points.shape == P.shape and obj.faces is not None and obj.faces.shape[1] == 3
        np.testing.assert_array_equal(obj.points, P)  # the same floats: the same object model
        assert obj.diameter == pytest.approx(pdist(P).max(), rel=1e-12)
        info = ds.models_info[obj_id]
        assert info["min_x"] == pytest.approx(1000 * P[:, 0].min())
        assert info["size_z"] == pytest.approx(1000 * np.ptp(P[:, 2]))
    assert ds.object(13) is ds.object(13)  # read once
    # The bowl turns about its z axis; the mug's handle breaks its symmetry; the sugar box is
    # not among BOP's symmetric YCB-V objects (its print tells its sides apart).
    bowl = ds.models_info[13]["symmetries_continuous"]
    assert len(bowl) == 1 and np.allclose(np.abs(bowl[0]["axis"]), [0, 0, 1])
    assert "symmetries_continuous" not in ds.models_info[14]
    assert "symmetries_discrete" not in ds.models_info[14]
    assert ds.object(13).symmetries.shape == (315, 4, 4)  # ceil(pi / 0.01) steps
    assert ds.object(3).symmetries.shape == (1, 4, 4)


def _box_points(sides, n=4000, seed=0):
    rng = np.random.default_rng(seed)
    p = rng.uniform(-0.5, 0.5, (n, 3))
    k = rng.integers(0, 3, n)
    p[np.arange(n), k] = np.sign(p[np.arange(n), k]) * 0.5
    return p * np.asarray(sides) + [0.01, -0.02, 0.03]


def test_find_symmetries_on_hand_made_shapes():
    # A box with three different sides: the three half turns about its axes, through its centre.
    box = _box_points([0.10, 0.06, 0.03])
    disc, cont = find_symmetries(box)
    assert cont == [] and len(disc) == 3
    for S in disc:
        assert np.allclose(S[:3, 3], [0.01, -0.02, 0.03] - S[:3, :3] @ [0.01, -0.02, 0.03],
                           atol=1e-3)
        assert np.isclose(np.trace(S[:3, :3]), -1.0)  # a half turn
    # A square cross-section adds the quarter turns about its axis.
    prism = _box_points([0.05, 0.05, 0.12])
    disc, _ = find_symmetries(prism)
    quarter = np.array([[0, -1, 0], [1, 0, 0], [0, 0, 1]])
    assert any(np.allclose(S[:3, :3], quarter, atol=1e-9) for S in disc)
    assert 5 <= len(disc) <= 7  # at most the square prism's group D4 without the identity
    from scipy.spatial import cKDTree

    tree = cKDTree(prism)
    for S in disc:  # each one maps the prism onto itself
        assert np.quantile(tree.query(prism @ S[:3, :3].T + S[:3, 3])[0], 0.9) < 0.004
    # A cylinder: continuous about its axis (z), plus a half turn that flips it end for end.
    rng = np.random.default_rng(1)
    a, z = rng.uniform(0, 2 * np.pi, 4000), rng.uniform(-0.05, 0.05, 4000)
    cyl = np.stack([0.03 * np.cos(a), 0.03 * np.sin(a), z], 1)
    disc, cont = find_symmetries(cyl)
    assert len(cont) == 1 and np.allclose(np.abs(cont[0]["axis"]), [0, 0, 1])
    assert len(disc) == 1
    # A bottom on one end only (a can without lid): no half turn any more, still continuous.
    r, b = 0.03 * np.sqrt(rng.uniform(0, 1, 1500)), rng.uniform(0, 2 * np.pi, 1500)
    can = np.vstack([cyl, np.stack([r * np.cos(b), r * np.sin(b), np.full(1500, -0.05)], 1)])
    disc, cont = find_symmetries(can)
    assert len(cont) == 1 and disc == []
    # A box with a bump on one face: none.
    lump = np.vstack([box, rng.normal([0.06, 0.0, 0.04], 0.004, (300, 3))])
    assert find_symmetries(lump) == ([], [])


def test_symmetry_transforms_compose_as_the_toolkit():
    info = {"symmetries_discrete": [[-1, 0, 0, 20, 0, -1, 0, 0, 0, 0, 1, 0, 0, 0, 0, 1]],
            "symmetries_continuous": [{"axis": [0, 0, 1], "offset": [10, 0, 0]}]}
    S = symmetry_transforms(info)
    assert S.shape == (2 * 315, 4, 4)
    assert np.allclose(S[0], np.eye(4))
    # Every transform fixes the axis' offset point (10 mm = 0.01 m) or maps it by the flip.
    c = np.array([0.01, 0, 0, 1.0])
    moved = np.einsum("kij,j->ki", S, c)[:, :3]
    assert np.allclose(moved[:315], c[:3]) and np.allclose(moved[315:], [0.01, 0, 0])
    assert np.allclose(S[315][:3, :3], np.diag([-1, -1, 1]))


def test_reader_errors(tmp_path, converted):
    _, out, _ = converted
    with pytest.raises(FileNotFoundError, match="models_info.json"):
        BOPDataset(tmp_path)
    bad = tmp_path / "targets.json"
    bad.write_text(json.dumps([{"scene_id": 0, "im_id": 1, "obj_id": 14},
                               {"scene_id": 0, "im_id": 1, "obj_id": 14}]))
    with pytest.raises(ValueError, match="listed twice"):
        load_bop_targets(bad)
    bad.write_text(json.dumps([{"scene_id": 0, "obj_id": 14}]))
    with pytest.raises(ValueError, match="target 0"):
        load_bop_targets(bad)
    ds = BOPDataset(out)
    with pytest.raises(KeyError, match="Image 7 of scene 0"):
        ds.instances(0, 7)
    with pytest.raises(KeyError, match="Object 99"):
        ds.object(99)


def test_cli_convert_demo_reads_back(tmp_path):
    from certpose.cli import main
    from certpose.data.synthetic import make_mug_scene

    out = tmp_path / "demo"
    assert main(["bop", "convert-demo", str(out), "-q"]) == 0
    ds = BOPDataset(out)
    sc = make_mug_scene(rng=0)
    f = ds.frame(0, 0)
    valid = sc.frame.depth > 0
    assert np.abs(f.depth[valid] - sc.frame.depth[valid]).max() <= 0.0005  # millimetre PNG
    (inst,) = ds.instances(0, 0)
    np.testing.assert_allclose(inst.T_camera_object, sc.T_camera_object, atol=1e-12)
    assert np.array_equal(ds.mask_visib(0, 0, 0), sc.object_mask)
    assert main(["bop", "convert-ycbv", str(tmp_path / "nowhere"), str(out), "-q"]) == 2
