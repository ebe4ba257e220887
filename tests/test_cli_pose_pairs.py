"""`certpose pose` on several (frame, object) pairs in one call (real YCB-Video frames)."""

from __future__ import annotations

import numpy as np
import pytest

from certpose.cli import main
from tests.conftest import require_data, strict_json

MUG_FRAMES = ["0000/000001", "0000/000002"]


@pytest.mark.slow  # three poses, ~4 s
def test_pairs_in_one_call_equal_single_calls(tmp_path, capsys):
    """Two frames x (the mug, an object absent from scene 0000): the list holds the two mug
    payloads, equal to those of two single calls with the same seed, the absent object skipped."""
    root = require_data("ycbv")
    common = ["--ycbv", str(root), "--no-certify", "--seed", "3"]
    out = tmp_path / "pairs.json"
    code = main(["pose", *common, "--frame", *MUG_FRAMES, "--object", "025_mug",
                 "002_master_chef_can", "--json", str(out)])
    captured = capsys.readouterr()
    assert code == 0, captured.err
    assert captured.out.count("== pair ") == 4 and captured.out.count("pose of YCB-Video") == 2
    assert captured.err.count("skipped") == 2 and "002_master_chef_can" in captured.err
    pairs = strict_json(out.read_text())
    assert isinstance(pairs, list) and len(pairs) == 2
    for frame, multi in zip(MUG_FRAMES, pairs, strict=True):
        single_out = tmp_path / f"{frame.replace('/', '_')}.json"
        assert main(["pose", *common, "--frame", frame, "--object", "025_mug", "--json",
                     str(single_out)]) == 0
        text = capsys.readouterr().out
        assert "== pair" not in text and "pairs successfully" not in text
        single = strict_json(single_out.read_text())
        assert isinstance(single, dict)  # one pair: one payload, as before
        assert set(multi) == set(single) and multi["input"] == single["input"]
        assert multi["input"]["frame"] == frame and multi["input"]["object"] == "025_mug"
        np.testing.assert_array_equal(multi["T_camera_object"], single["T_camera_object"])
        assert multi["log_likelihood"] == single["log_likelihood"]
        assert multi["errors"] == single["errors"]


@pytest.mark.parametrize("extra", [["--model", "points.xyz"], ["--object-model", "m.npz"],
                                   ["--save-problem", "p.npz"], ["--box", "0", "0", "9", "9"],
                                   ["--samples", "10", "--plot", "p.png"],
                                   ["--samples", "10", "--particles", "p.npz"]])
def test_one_pair_options_refuse_several_pairs(tmp_path, capsys, extra):
    root = require_data("ycbv")
    extra = [str(tmp_path / e) if e.endswith((".xyz", ".npz", ".png")) else e for e in extra]
    assert main(["pose", "--ycbv", str(root), "--frame", *MUG_FRAMES, *extra]) == 2
    err = capsys.readouterr().err
    option = next(e for e in extra if e.startswith("--") and e != "--samples")
    assert err.count("\n") == 1 and f"{option} concerns one pair" in err
    assert main(["pose", "--demo", "--object", "025_mug", "040_large_marker"]) == 2
    assert "--ycbv" in capsys.readouterr().err


@pytest.mark.parametrize("extra", [["--frame", "0000/000002"], ["--object", "061_foam_brick"],
                                   ["--model", "m.xyz"], ["--object-model", "m.npz"]])
def test_demo_refuses_the_options_of_a_ycbv_frame(capsys, extra):
    # --demo poses its own mug: a frame, object or model given with it was silently ignored.
    assert main(["pose", "--demo", *extra]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and f"{extra[0]} needs --ycbv" in err, err


def test_pairs_all_absent_fail_and_bad_frame_is_bad_input(tmp_path, capsys):
    root = require_data("ycbv")
    out = tmp_path / "none.json"
    code = main(["pose", "--ycbv", str(root), "--frame", *MUG_FRAMES, "--object",
                 "002_master_chef_can", "--json", str(out)])
    captured = capsys.readouterr()
    assert code == 1  # no pair succeeded
    assert captured.err.count("skipped") == 2 and "is not annotated in frame" in captured.err
    assert strict_json(out.read_text()) == []
    assert "posed 0 of 2 pairs successfully (2 skipped)" in captured.out
    assert main(["pose", "--ycbv", str(root), "--frame", "0000/000001", "0000/999999"]) == 2
    assert "--frame 0000/999999" in capsys.readouterr().err
