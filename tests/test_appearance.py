"""Object models with appearance from posed RGB-D views, on the real YCB-Video frames."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from certpose.cli import main
from certpose.estimation.pipeline import build_ycbv_object_model
from certpose.geometry.appearance import (
    AppearanceBackbone,
    BuiltObjectModel,
    PosedView,
    color_histograms,
    object_from_posed_views,
    project_model_colors,
)
from certpose.io.ycbv import load_model_points, load_ycbv_frame
from tests.conftest import require_data

OBJ = "009_gelatin_box"



def _model_from_scene(root, scene: str, obj: str):
    """``obj``'s appearance model from every frame of ``scene`` (to be tested on another scene)."""
    views = [f"{scene}/{m.name[:6]}" for m in sorted((root / scene).glob("*-meta.mat"))]
    return build_ycbv_object_model(root, views, obj)

@pytest.fixture(scope="module")
def root() -> Path:
    require_data("ycbv", "0000", "000001-meta.mat")
    return require_data("ycbv")


@pytest.fixture(scope="module")
def gelatin(root) -> BuiltObjectModel:
    """The gelatin box coloured from frames 1 and 2 of scene 0000."""
    return build_ycbv_object_model(root, ["0000/000001", "0000/000002"], OBJ)


def test_colours_land_on_the_right_points(root, gelatin):
    # Project the coloured model points into frame 3 (not used to build the model) with its
    # ground-truth pose: their colours must be the image's colours there.
    yf = load_ycbv_frame(root, "0000/000003")
    view = yf.posed_view(OBJ)
    m = gelatin.model
    vis, image_colors, _ = project_model_colors(m.points, m.normals, view)
    both = vis & gelatin.observed
    assert both.sum() > 100
    err = np.abs(m.colors[both] - image_colors[both]).mean(axis=1)
    assert np.median(err) < 0.08  # sensor noise between frames and voxel averaging
    # The same pixels assigned to the wrong points disagree far more.
    idx = np.flatnonzero(both)
    shuffled = np.abs(m.colors[idx] - image_colors[np.random.default_rng(0).permutation(idx)])
    assert np.median(err) < 0.3 * np.median(shuffled.mean(axis=1))
    # So do the points under the box's 180-degree turn about its axis: they land on other print.
    S = np.diag([-1.0, -1.0, 1.0, 1.0])
    turned = PosedView(yf.frame, view.mask, view.T_camera_object @ S, "turned")
    vis_t, colors_t, _ = project_model_colors(m.points, m.normals, turned)
    both_t = vis_t & gelatin.observed
    assert both_t.sum() > 50
    err_t = np.abs(m.colors[both_t] - colors_t[both_t]).mean(axis=1)
    assert np.median(err_t) > 2 * np.median(err)


def test_unseen_points_carry_no_appearance(gelatin):
    m, seen = gelatin.model, gelatin.observed
    assert 0 < seen.sum() < len(m)  # one camera sees one side of the box
    colour_block = m.descriptors[:, -(gelatin.backbone.hue_bins + 2):]
    # Their colour block is zero: no guessed colour, so no colour similarity either way.
    assert np.all(colour_block[~seen] == 0.0)
    assert np.all(m.colors[~seen] == 0.0)
    # The model says how much of its surface was seen (by area: it is sampled over its surface).
    assert gelatin.seen_fraction == pytest.approx(m.areas[seen].sum() / m.areas.sum())
    assert 0.0 < gelatin.seen_fraction < 1.0
    assert np.all(np.linalg.norm(colour_block[seen], axis=1) > 0)
    # Their shape part is kept: it is known from the model points.
    assert np.all(np.linalg.norm(m.descriptors[~seen], axis=1) > 0)


def test_zero_descriptors_for_unseen_points_on_request(root):
    built = build_ycbv_object_model(root, ["0000/000001"], OBJ, unseen="zero")
    assert np.all(built.model.descriptors[~built.observed] == 0.0)
    assert np.all(np.linalg.norm(built.model.descriptors[built.observed], axis=1) > 0.99)


def test_save_load_round_trip(gelatin, tmp_path):
    path = tmp_path / "gelatin.npz"
    gelatin.save(path)
    back = BuiltObjectModel.load(path)
    for name in ("points", "descriptors", "colors", "normals"):
        np.testing.assert_array_equal(getattr(back.model, name), getattr(gelatin.model, name))
    np.testing.assert_array_equal(back.observed, gelatin.observed)
    assert back.backbone == gelatin.backbone
    assert back.views == ("0000/000001", "0000/000002") and back.scenes == ("0000",)
    assert back.model.name == OBJ and back.voxel_size == gelatin.voxel_size
    np.testing.assert_array_equal(back.model.areas, gelatin.model.areas)


def test_surface_sampled_appearance_model(root, tmp_path):
    # Points spread evenly over the reconstructed surface, coloured by the views, with their
    # areas (saved and loaded with the model).
    built = build_ycbv_object_model(root, ["0000/000001"], OBJ, sampling="surface")
    m = built.model
    assert m.areas is not None and m.areas.shape == (len(m),)
    assert 0.01 < m.area < 0.03  # the gelatin box: 8.9 x 7.3 x 2.9 cm, 0.022 m^2 in all
    assert 0 < built.observed.sum() < len(m)
    path = tmp_path / "gelatin_surface.npz"
    built.save(path)
    np.testing.assert_array_equal(BuiltObjectModel.load(path).model.areas, m.areas)
    # The default; voxel averages on request carry no areas.
    assert np.array_equal(build_ycbv_object_model(root, ["0000/000001"], OBJ).model.areas, m.areas)
    assert build_ycbv_object_model(root, ["0000/000001"], OBJ, sampling="voxel").model.areas is None
    with pytest.raises(ValueError, match="sampling"):
        build_ycbv_object_model(root, ["0000/000001"], OBJ, sampling="mesh")


def test_load_refuses_other_files(tmp_path):
    with pytest.raises(FileNotFoundError, match="does not exist"):
        BuiltObjectModel.load(tmp_path / "missing.npz")
    other = tmp_path / "other.npz"
    np.savez(other, points=np.zeros((5, 3)))
    with pytest.raises(ValueError, match="not a certpose object model"):
        BuiltObjectModel.load(other)
    garbage = tmp_path / "garbage.npz"
    garbage.write_text("not a zip file")
    with pytest.raises(ValueError, match="Cannot read"):
        BuiltObjectModel.load(garbage)
    # A .npy file and a cut archive are not object models either (np.load returned a bare
    # array for the first: "does not support the context manager protocol").
    np.save(tmp_path / "points.npy", np.zeros((5, 3)))
    cut = tmp_path / "cut.npz"
    cut.write_bytes(other.read_bytes()[:100])
    for bad in (tmp_path / "points.npy", cut):
        with pytest.raises(ValueError, match=f"Cannot read .*{bad.name} as an object model: not a .npz"):
            BuiltObjectModel.load(bad)


def test_bad_views_give_clear_errors(root):
    yf = load_ycbv_frame(root, "0000/000001")
    mask = yf.object_mask(OBJ)
    with pytest.raises(ValueError, match="without a pose"):
        PosedView(yf.frame, mask, None, "0000/000001")
    with pytest.raises(ValueError, match=r"mask.*\(480, 640\).*0000/000001"):
        PosedView(yf.frame, mask[:-10], yf.poses[OBJ], "0000/000001")
    with pytest.raises(ValueError, match="views` is empty"):
        object_from_posed_views(load_model_points(root / "models" / OBJ / "points.xyz"), [])
    # The mustard bottle is not in scene 0000: no frame has its pose.
    with pytest.raises(ValueError, match="006_mustard_bottle.*no pose"):
        build_ycbv_object_model(root, ["0000/000001", "0000/000002"], "006_mustard_bottle")
    # A pose that puts the object behind the camera: no view sees any point.
    T = yf.poses[OBJ].copy()
    T[2, 3] = -1.0
    view = PosedView(yf.frame, mask, T, "0000/000001")
    with pytest.raises(ValueError, match="No view sees any point"):
        object_from_posed_views(load_model_points(root / "models" / OBJ / "points.xyz"), [view])


def test_color_histograms_compare_colours():
    rng = np.random.default_rng(0)
    pts = rng.uniform(-0.05, 0.05, size=(400, 3))
    red = np.tile([0.9, 0.1, 0.1], (400, 1))
    blue = np.tile([0.1, 0.1, 0.9], (400, 1))
    h_red = color_histograms(pts, red, radius=0.02)
    h_blue = color_histograms(pts, blue, radius=0.02)
    np.testing.assert_allclose(np.einsum("ij,ij->i", h_red, h_red), 1.0)
    assert np.all(np.einsum("ij,ij->i", h_red, h_blue) < 0.0)
    # Brightness alone does not change a chromatic colour's histogram.
    np.testing.assert_allclose(color_histograms(pts, 0.6 * red, radius=0.02), h_red, atol=1e-12)
    unknown = np.full((400, 3), np.nan)
    assert np.all(color_histograms(pts, unknown, radius=0.02) == 0.0)
    with pytest.raises(ValueError, match="colors"):
        color_histograms(pts, red[:10], radius=0.02)


def test_backbone_validation():
    with pytest.raises(ValueError, match="color_weight"):
        AppearanceBackbone(color_weight=1.5)
    with pytest.raises(ValueError, match="color_radius"):
        AppearanceBackbone(color_radius=0.0)


@pytest.mark.slow
def test_cli_object_build_then_pose(root, tmp_path, capsys):
    out = tmp_path / "gelatin.npz"
    assert main(["object", "build", "--ycbv", str(root), "--object", OBJ,
                 "--views", "0000/000001", "0000/000002", "-o", str(out)]) == 0
    text = capsys.readouterr().out
    assert "do not evaluate it on them" in text and out.is_file()
    assert BuiltObjectModel.load(out).scenes == ("0000",)
    # A model of another object is refused.
    assert main(["pose", "--ycbv", str(root), "--frame", "0000/000003", "--object", "025_mug",
                 "--object-model", str(out), "--no-certify"]) == 2
    assert "not of --object 025_mug" in capsys.readouterr().err
    # Errors are one line.
    assert main(["object", "build", "--ycbv", str(root), "--object", "006_mustard_bottle",
                 "--views", "0000/000001", "-o", str(tmp_path / "m.npz")]) == 2
    err = capsys.readouterr().err
    assert "no pose" in err and err.count("\n") == 1
    js = tmp_path / "pose.json"
    # (Evaluated on the scene that built it only to exercise the command, not to judge it.)
    assert main(["pose", "--ycbv", str(root), "--frame", "0000/000003", "--object", OBJ,
                 "--object-model", str(out), "--no-certify", "--json", str(js)]) == 0
    data = json.loads(js.read_text())
    assert data["input"]["object_model"] == str(out)
    assert np.asarray(data["T_camera_object"]).shape == (4, 4)


@pytest.mark.slow
def test_cross_scene_appearance_model_tells_the_flip(root):
    """The potted-meat can, model from scene 0002, evaluated on scene 0049 (never on 0002).

    Without appearance eq. (1) prefers the can turned by about 180 degrees (by about 17 nats
    in 0049/000010; the search and its turns find that mode); the printed label tells them
    apart. (On 0049/000001, the frame used before the models' Voronoi areas of 2026-11-26, the
    geometry-only model now gets the can right: 4.7 deg.)
    """
    from certpose.estimation.pipeline import run_ycbv

    obj = "010_potted_meat_can"
    built = build_ycbv_object_model(root, ["0002/000001", "0002/000010", "0002/000020"], obj)
    assert "0049" not in built.scenes
    geo = run_ycbv(root, "0049/000010", obj, rng=0)
    app = run_ycbv(root, "0049/000010", obj, object_model=built, rng=0)
    assert geo.errors.add_s < 0.01 and geo.errors.rotation_deg > 150.0  # flipped
    assert app.errors.add_s < 0.01 and app.errors.rotation_deg < 10.0
    diameter = 0.144  # of the box around the model points
    assert app.errors.add < 0.1 * diameter < geo.errors.add


@pytest.mark.slow
def test_the_turn_of_an_appearance_model_is_refined_when_it_is_the_truth(root):
    """The potted-meat can in 0002/000020, model from scene 0049's views, mask classifier: the
    search ends on the can turned by 180 degrees, 90 nats below the refined truth; the truth is
    that pose's near-symmetric turn, ranked below the 6 turns refined before (depending on the
    coarse subsample), so it was never refined and the turned can was returned."""
    from certpose.estimation.pipeline import run_ycbv

    obj = "010_potted_meat_can"
    built = _model_from_scene(root, "0049", obj)
    assert "0002" not in built.scenes
    res = run_ycbv(root, "0002/000020", obj, object_model=built, rng=0, classifier="mask")
    assert res.errors.add_s < 0.01 and res.errors.rotation_deg < 10.0

@pytest.mark.slow
def test_the_refined_eq2_minimiser_lands_in_the_winners_basin(root):
    """Issue 10 item 2 on a real frame: the potted-meat can in 0002/000001, model from scene
    0049's views, mask classifier. Eq. (2)'s minimiser of the highest support is the can turned
    by about 180 degrees (eq. (2) has no free-space term); refined on eq. (1) it ended 260 nats
    below the winner, which came from the coarse search, and it was the one certified. Every
    seed's eq. (2) minimiser is now refined, the one about the right seed wins or lands next to
    the winner, and that one is certified."""
    from certpose.estimation.pipeline import pose_errors, run_ycbv
    from solvers.lie import rotation_error_deg

    obj = "010_potted_meat_can"
    built = _model_from_scene(root, "0049", obj)
    assert "0002" not in built.scenes
    res = run_ycbv(root, "0002/000001", obj, object_model=built, rng=0, classifier="mask")
    mle = res.mle
    assert res.errors.add_s < 0.01 and res.errors.rotation_deg < 10.0
    refined = [h for h in mle.hypotheses if h.source.split(":")[0] == "eq2"]
    assert refined
    W = mle.T_scene_object
    near = [h for h in refined if np.linalg.norm(h.pose[:3, 3] - W[:3, 3]) <= 0.005
            and rotation_error_deg(h.pose[:3, :3], W[:3, :3]) <= 2.0]
    assert mle.hypothesis.split(":")[0] == "eq2" or near, (mle.hypothesis, [
        (h.source, h.score) for h in refined], mle.log_likelihood)
    assert mle.eq2_refined_log_likelihood >= mle.log_likelihood - 5.0
    # The raw minimiser (the certified one) is the one in the winner's basin, not its turn.
    raw = np.linalg.inv(res.T_world_camera) @ mle.eq2_result.T_target_source
    points = load_model_points(root / "models" / obj / "points.xyz")
    assert pose_errors(raw, res.T_camera_object_gt, points).add_s < 0.01
    assert rotation_error_deg(mle.eq2_result.rotation, W[:3, :3]) < 30.0


@pytest.mark.slow
def test_box_only_search_keeps_the_translations_not_slid_onto_the_positives(root):
    """Mustard bottle in 0002/000010, model from scene 0050's views, box only (best buddies, half
    of the positives off the bottle): sliding the coarse translations onto the positives alone
    dragged them off; the search returned the bottle 7 cm off, 991 nats below the refined
    truth."""
    from certpose.estimation.pipeline import run_ycbv

    obj = "006_mustard_bottle"
    built = _model_from_scene(root, "0050", obj)
    assert "0002" not in built.scenes
    res = run_ycbv(root, "0002/000010", obj, object_model=built, rng=0, classifier="best_buddies")
    assert res.errors.add_s < 0.01

@pytest.mark.slow
def test_a_search_that_ends_hidden_in_unobserved_space_searches_again(root):
    """Mustard bottle, model from 0002, in 0050/000020 (seed 0): the first coarse search ends
    with the whole object in unobserved space (eq. (1) = N log p_unobserved; returned with
    ADD-S 9 cm before the search was repeated in that case)."""
    from certpose.estimation.pipeline import run_ycbv

    obj = "006_mustard_bottle"
    built = build_ycbv_object_model(root, ["0002/000001", "0002/000010", "0002/000020"], obj)
    res = run_ycbv(root, "0050/000020", obj, object_model=built, rng=0)
    assert res.log_likelihood > len(built.model) * np.log(0.1) + 1.0
    assert res.errors.add_s < 0.01


def test_similarity_scale_multiplies_beta_for_appearance_descriptors_only():
    from certpose.estimation.pipeline import likelihood_params_for
    from certpose.geometry.features import FPFHBackbone
    from certpose.model.likelihood import LikelihoodParams

    base = LikelihoodParams(beta=2.0, c_empty=-20.0)
    assert likelihood_params_for(base, FPFHBackbone()) is base
    assert likelihood_params_for(base, None) is base
    scaled = likelihood_params_for(base, AppearanceBackbone(similarity_scale=3.0))
    assert scaled.beta == 6.0 and scaled.c_empty == -20.0
    assert likelihood_params_for(None, AppearanceBackbone(similarity_scale=2.5)).beta == 2.5
    with pytest.raises(ValueError, match="similarity_scale"):
        AppearanceBackbone(similarity_scale=0.0)


def test_backbone_json_keeps_the_scale_and_old_models_load_with_scale_one():
    from certpose.geometry.appearance import backbone_from_json, backbone_to_json

    bb = AppearanceBackbone(color_weight=0.7, similarity_scale=2.0)
    assert backbone_from_json(backbone_to_json(bb)) == bb
    spec = json.loads(backbone_to_json(bb))
    del spec["params"]["similarity_scale"]  # a model saved before the scale existed
    old = backbone_from_json(json.dumps(spec))
    assert old.similarity_scale == 1.0 and old.color_weight == 0.7


def test_unseen_points_take_the_seen_palette(root):
    # unseen="palette": the colour block of every unseen point is the colour descriptor of the
    # whole seen palette (a unit vector times sqrt(w)), the same for all of them, and it is
    # what color_histograms gives a point whose neighbourhood holds every seen point.
    built = build_ycbv_object_model(root, ["0000/000001"], OBJ, unseen="palette")
    m, seen, bb = built.model, built.observed, built.backbone
    nc = bb.hue_bins + 2
    block = m.descriptors[~seen, -nc:]
    assert (~seen).sum() > 10
    np.testing.assert_allclose(block, block[:1].repeat(len(block), axis=0), atol=1e-12)
    np.testing.assert_allclose(np.linalg.norm(block[0]), np.sqrt(bb.color_weight), atol=1e-9)
    far = color_histograms(m.points[seen], m.colors[seen], radius=10.0, hue_bins=bb.hue_bins)
    np.testing.assert_allclose(block[0], np.sqrt(bb.color_weight) * far[0], atol=1e-9)
    # The seen points keep their own local colour statistics (they differ from the palette).
    assert np.median(np.abs(m.descriptors[seen, -nc:] - block[0]).sum(axis=1)) > 0.1
    with pytest.raises(ValueError, match="unseen"):
        build_ycbv_object_model(root, ["0000/000001"], OBJ, unseen="mean")


def test_cli_object_build_defaults_are_the_backbones(tmp_path, capsys):
    bb = AppearanceBackbone()
    with pytest.raises(SystemExit):
        main(["object", "build", "--help"])
    text = " ".join(capsys.readouterr().out.split())
    assert f"(default: {bb.color_weight:g})" in text and f"(default: {bb.similarity_scale:g})" in text
    out = str(tmp_path / "m.npz")
    for opt, bad in (("--similarity-scale", "0"), ("--color-weight", "1.5")):
        assert main(["object", "build", "--ycbv", str(tmp_path), "--object", OBJ, "--views",
                     "0000/000001", opt, bad, "-o", out]) == 2
        assert opt in capsys.readouterr().err


def _mustard_box_only(root, model_scene: str, frame: str):
    """The mustard bottle posed box only (best buddies) in ``frame`` with a model built from
    ``model_scene``'s views (never the frame's own scene): its name and the pipeline's result."""
    from certpose.estimation.pipeline import run_ycbv

    obj = "006_mustard_bottle"
    built = _model_from_scene(root, model_scene, obj)
    assert frame.split("/")[0] not in built.scenes
    return obj, run_ycbv(root, frame, obj, object_model=built, rng=0, classifier="best_buddies")


@pytest.mark.slow
@pytest.mark.xfail(strict=True, reason=(
    "with the visibility-aware eq. (1) the best refined eq. (2) hypothesis is the bottle turned "
    "174 deg from the raw minimiser (with the marginal colour of unseen points; 29 deg while they "
    "scored none); the returned pose, the turn step's, is within 1 cm ADD-S and 10 deg"))
def test_the_certified_eq2_minimiser_box_only_is_in_the_refined_minimisers_basin(root):
    """Issue 10 item 2, box only (best buddies, no mask): the mustard bottle in 0050/000020,
    model from scene 0002's views. The local rounds of the eq. (2) minimiser that is certified
    began at its raw minimiser and stayed in that basin, 1.06 cm ADD-S from the truth and 20
    degrees from the minimiser as eq. (1) refined it; begun at the refined pose they end next to
    it (measured 0.36 cm). Every hypothesis the MLE refines is now an eq. (2) minimiser's."""
    from certpose.estimation.pipeline import pose_errors
    from solvers.lie import rotation_error_deg

    obj, res = _mustard_box_only(root, "0002", "0050/000020")
    mle = res.mle
    assert res.errors.add_s < 0.01
    assert all(h.source.split(":")[0] == "eq2" for h in mle.hypotheses), [
        h.source for h in mle.hypotheses]
    raw = mle.eq2_result
    points = load_model_points(root / "models" / obj / "points.xyz")
    T_wc = res.T_world_camera
    assert pose_errors(np.linalg.inv(T_wc) @ raw.T_target_source, res.T_camera_object_gt,
                       points).add_s < 0.01
    # Next to the best refined eq. (2) hypothesis (the refinement's, before the hops).
    best = max((h for h in mle.hypotheses if h.source.startswith("eq2:")), key=lambda h: h.score)
    assert rotation_error_deg(raw.rotation, best.pose[:3, :3]) < 5.0
    assert np.linalg.norm(raw.translation - best.pose[:3, 3]) < 0.005


@pytest.mark.slow
def test_the_certified_eq2_minimiser_follows_a_winning_turn(root):
    """Issue 10 item 2, box only: the mustard bottle in 0002/000010, model from scene 0050's
    views. Every refined eq. (2) minimiser is the bottle turned by 180 degrees; the winner is
    that pose's near-symmetric turn (the MLE's mode step), and the minimiser certified was the
    turned one (raw ADD-S 1.12 cm). Eq. (2) is now solved again about the winner. (The model
    saw the bottle's back, the frame shows its front: while its unseen points scored no colour
    the pose came back turned 163 deg; they now score the seen palette's marginal.)"""
    from certpose.estimation.pipeline import pose_errors
    from solvers.lie import rotation_error_deg

    obj, res = _mustard_box_only(root, "0050", "0002/000010")
    mle = res.mle
    assert res.errors.add_s < 0.01 and res.errors.rotation_deg < 10.0
    raw = mle.eq2_result
    points = load_model_points(root / "models" / obj / "points.xyz")
    assert pose_errors(np.linalg.inv(res.T_world_camera) @ raw.T_target_source,
                       res.T_camera_object_gt, points).add_s < 0.01
    W = mle.T_scene_object
    assert rotation_error_deg(raw.rotation, W[:3, :3]) < 5.0
    assert np.linalg.norm(raw.translation - W[:3, 3]) < 0.005


def _seen_share(res, built) -> float:
    """Share of what the frame shows of the model at the true pose that the model's views saw
    (points weighted by their visibility, as eq. (1) weighs them)."""
    from certpose.estimation.pipeline import likelihood_params_for
    from certpose.model.likelihood import PoseLikelihood

    lik = PoseLikelihood(res.scene, res.classification, built.model,
                         params=likelihood_params_for(None, built.backbone))
    w = lik.point_weights * lik.visibility(res.T_world_camera @ res.T_camera_object_gt)
    return float(w[built.observed].sum() / w.sum())


def _mustard_with_samples(root, model_scene: str, frame: str):
    """The mustard bottle in ``frame``, mask classifier, model from ``model_scene``'s views,
    with its pose distribution as ``certpose pose --samples 2000`` samples it; the result, the
    seen share and the truth's credible level."""
    from dataclasses import replace

    from certpose.estimation.pipeline import PoseParams, run_ycbv
    from certpose.sampling.sampler import ISParams

    obj = "006_mustard_bottle"
    built = _model_from_scene(root, model_scene, obj)
    assert frame.split("/")[0] not in built.scenes
    params = replace(PoseParams(), sampler=ISParams(draws=10_000, resample=2000))
    res = run_ycbv(root, frame, obj, object_model=built, rng=0, classifier="mask", params=params)
    G = res.T_camera_object_gt
    return res, _seen_share(res, built), res.distribution.credible_level(G[:3, :3], G[:3, 3])


@pytest.mark.slow
def test_a_model_that_saw_the_other_side_is_not_confidently_turned(root):
    """The mustard bottle in 0002/000010, model from scene 0050's views, which saw under 5% of
    what this frame shows. Its unseen points scored no colour while the seen ones, turned by 180
    degrees to face the camera, matched the bottle's yellow: eq. (1) preferred the turn by about
    430-520 nats and the distribution held the truth at level 1.00 (outside every credible
    region). Unseen points now score the marginal of the seen palette: the truth wins and lies
    inside the 90% region."""
    res, share, level = _mustard_with_samples(root, "0050", "0002/000010")
    assert share < 1 / 3
    assert res.errors.add_s < 0.01 and res.errors.rotation_deg < 10.0
    assert level <= 0.9


@pytest.mark.slow
def test_where_the_views_saw_little_the_truth_stays_in_the_90_region(root):
    """The mustard bottle in 0050/000001, model from scene 0002's views (under 5% of what the
    frame shows seen). The returned pose is still the turn (the turned seen side matches the
    front's layout a little better than the palette does), but by tens of nats rather than 520:
    the distribution keeps the truth inside its 90% credible region (was level 1.00)."""
    res, share, level = _mustard_with_samples(root, "0002", "0050/000001")
    assert share < 1 / 3
    assert res.errors.add_s < 0.01
    assert level <= 0.9
