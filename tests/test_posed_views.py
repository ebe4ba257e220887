"""Posed views from a JSON manifest (certpose.io.views) and `certpose object build --posed-views`."""

from __future__ import annotations

import json
import os
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from certpose.cli import main
from certpose.io.views import load_posed_views

DATA = Path(__file__).resolve().parents[1].parent / "shared" / "data" / "ycbv"
needs_ycbv = pytest.mark.skipif(not DATA.is_dir() and not os.environ.get("CI"),
                                reason="YCB-Video data not found")
OBJECT = "006_mustard_bottle"
VIEWS = ("0002/000001", "0002/000010", "0002/000020")


def _ycbv_manifest(tmp_path: Path) -> Path:
    """YCB-Video views written as a user would: image paths, a mask PNG per view, each view's
    ground-truth T_camera_object and the camera's intrinsics, as JSON."""
    from certpose.io.ycbv import load_ycbv_frame

    views, k = [], None
    for name in VIEWS:
        yf = load_ycbv_frame(DATA, name)
        mask = tmp_path / f"{name.replace('/', '_')}-mask.png"
        Image.fromarray(yf.object_mask(OBJECT).astype(np.uint8) * 255).save(mask)
        views.append({"name": name, "color": str(DATA / f"{name}-color.png"),
                      "depth": str(DATA / f"{name}-depth.png"), "mask": mask.name,  # relative
                      "T_camera_object": yf.poses[OBJECT].tolist()})
        c = yf.frame.intrinsics
        k = [c.fx, c.fy, c.cx, c.cy]
    path = tmp_path / "views.json"
    path.write_text(json.dumps({"intrinsics": k, "depth_scale": 10000, "views": views}))
    return path


@pytest.mark.slow
@needs_ycbv
def test_a_manifest_of_ycbv_views_builds_the_ycbv_model(tmp_path: Path) -> None:
    """The same views given as a manifest build the model `--ycbv --views` builds: the same
    points, descriptors and observed points, and the same provenance."""
    from certpose.geometry.appearance import BuiltObjectModel

    manifest = _ycbv_manifest(tmp_path)
    model = str(DATA / "models" / OBJECT / "points.xyz")
    own, ref = tmp_path / "own.npz", tmp_path / "ref.npz"
    assert main(["object", "build", "-q", "--posed-views", str(manifest), "--model", model,
                 "--object", OBJECT, "-o", str(own)]) == 0
    assert main(["object", "build", "-q", "--ycbv", str(DATA), "--views", *VIEWS,
                 "--object", OBJECT, "-o", str(ref)]) == 0
    a, b = BuiltObjectModel.load(own), BuiltObjectModel.load(ref)
    # The poses are snapped onto SO(3) once more when read back: equal to rounding.
    np.testing.assert_array_equal(a.model.points, b.model.points)
    np.testing.assert_allclose(a.model.descriptors, b.model.descriptors, rtol=1e-9, atol=1e-12)
    np.testing.assert_array_equal(a.observed, b.observed)
    assert a.views == b.views and a.scenes == ("0002",) and a.model.name == OBJECT


def _tiny_view(tmp_path: Path, *, mask_size=(40, 30), mask_value=1) -> dict:  # noqa: ANN001
    w, h = 40, 30
    Image.fromarray(np.full((h, w, 3), 128, np.uint8)).save(tmp_path / "c.png")
    Image.fromarray(np.full((h, w), 600, np.uint16)).save(tmp_path / "d.png")
    Image.fromarray(np.full(mask_size[::-1], mask_value, np.uint8)).save(tmp_path / "m.png")
    T = np.eye(4)
    T[2, 3] = 0.6
    return {"color": "c.png", "depth": "d.png", "mask": "m.png", "T_camera_object": T.tolist()}


def _write(tmp_path: Path, doc: object) -> Path:
    path = tmp_path / "views.json"
    path.write_text(json.dumps(doc))
    return path


def test_a_manifest_is_read_relative_to_its_folder(tmp_path: Path) -> None:
    view = _tiny_view(tmp_path)
    R = np.array([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])
    view["T_camera_object"] = [[*R[0], 0.01], [*R[1], 0.0], [*(R[2] + [0, 0, 2e-4]), 0.6],
                               [0, 0, 0, 1]]  # orthonormal to 1e-4 only, as text gives
    views = load_posed_views(_write(tmp_path, {"intrinsics": [40, 40, 20, 15], "views": [view]}))
    (v,) = views
    assert v.name == "c" and v.mask.all() and v.frame.depth.shape == (30, 40)
    assert np.allclose(v.frame.depth, 0.6)  # default depth scale 1000 (millimetres)
    R_read = v.T_camera_object[:3, :3]
    assert np.allclose(R_read.T @ R_read, np.eye(3), atol=1e-12) and np.allclose(R_read, R, atol=1e-3)


@pytest.mark.parametrize("change, message", [
    (lambda doc: doc.update(views=[]), 'non-empty "views"'),
    (lambda doc: doc["views"][0].pop("mask"), "missing mask"),
    (lambda doc: doc.update(intrinsics=[500, 500, 20]), r"`intrinsics` must be \[fx, fy, cx, cy\]"),
    (lambda doc: doc.update(depth_scale=0), "`depth_scale` must be a positive number"),
    (lambda doc: doc["views"][0].update(T_camera_object=np.diag([2.0, 1, 1, 1]).tolist()),
     "T_camera_object"),
    (lambda doc: doc["views"][0].update(depth="none.png"), "does not exist"),
])
def test_bad_manifests_name_the_problem(tmp_path: Path, change, message: str) -> None:  # noqa: ANN001
    doc = {"intrinsics": [40, 40, 20, 15], "views": [_tiny_view(tmp_path)]}
    change(doc)
    with pytest.raises((ValueError, FileNotFoundError), match=message):
        load_posed_views(_write(tmp_path, doc))


def test_bad_masks_and_files(tmp_path: Path) -> None:
    with pytest.raises(FileNotFoundError, match="manifest"):
        load_posed_views(tmp_path / "none.json")
    (tmp_path / "bad.json").write_text("{not json")
    with pytest.raises(ValueError, match="not JSON"):
        load_posed_views(tmp_path / "bad.json")
    doc = {"intrinsics": [40, 40, 20, 15], "views": [_tiny_view(tmp_path, mask_size=(20, 10))]}
    with pytest.raises(ValueError, match=r"mask .* is 20x10 pixels, the depth image 40x30"):
        load_posed_views(_write(tmp_path, doc))
    doc = {"intrinsics": [40, 40, 20, 15], "views": [_tiny_view(tmp_path, mask_value=0)]}
    with pytest.raises(ValueError, match="no object pixel"):
        load_posed_views(_write(tmp_path, doc))


def test_object_build_refuses_mixed_sources(tmp_path: Path, capsys) -> None:  # noqa: ANN001
    path = _write(tmp_path, {"views": [_tiny_view(tmp_path)]})
    out = str(tmp_path / "m.npz")
    cases = [
        (["--posed-views", str(path), "--object", "x", "-o", out], "--posed-views needs --model"),
        (["--posed-views", str(path), "--model", "x.xyz", "--views", "0002/000001", "-o", out],
         "--views needs --ycbv"),
        (["--posed-views", str(tmp_path / "none.json"), "--model", str(path), "-o", out],
         "does not exist"),
    ]
    for argv, message in cases:
        assert main(["object", "build", *argv]) == 2, argv
        assert message in capsys.readouterr().err, argv
    assert not Path(out).exists()


def test_the_docs_manifest_example_loads(tmp_path: Path) -> None:
    """The manifest shown in the object-models how-to is one the loader reads."""
    import re

    readme = (Path(__file__).resolve().parents[1] / "docs" / "how-to" / "object-models.md").read_text()
    doc = json.loads(re.search(r"```json\n(.*?)```", readme, re.S).group(1))
    for view in doc["views"]:  # tiny images under the names it gives
        k = doc["intrinsics"]
        h, w = int(2 * k[3]), int(2 * k[2])
        Image.fromarray(np.full((h, w, 3), 90, np.uint8)).save(tmp_path / view["color"])
        Image.fromarray(np.full((h, w), 600, np.uint16)).save(tmp_path / view["depth"])
        Image.fromarray(np.full((h, w), 255, np.uint8)).save(tmp_path / view["mask"])
    (v,) = load_posed_views(_write(tmp_path, doc))
    assert v.name == "turntable/0001" and np.allclose(v.frame.depth, 0.6)
    assert np.allclose(v.T_camera_object[:3, 3], [0, 0, 0.6])
