"""Reading data from disk: point and weight files, YCB-Video frames with ground truth,
manifests of posed RGB-D views (any camera), and datasets in the BOP layout
(:mod:`certpose.io.bop`).

Owns file formats and their strict checks (a malformed file is an error naming the file, never a
silently wrong array). May import :mod:`certpose.geometry` (frames) and :mod:`solvers`' public
names; nothing in here builds a model or estimates a pose.
"""

from certpose.io.output import check_output_path, to_json, write_json
from certpose.io.points import (
    POINT_SUFFIXES,
    WEIGHT_SUFFIXES,
    load_bunny,
    read_correspondences,
    read_points,
    read_weights,
    scale_to_unit_cube,
    synthetic_shape,
)
from certpose.io.problems import ProblemFile, load_problem, save_problem
from certpose.io.ycbv import YCBVFrame, load_class_names, load_model_points, load_ycbv_frame

__all__ = [
    "POINT_SUFFIXES",
    "ProblemFile",
    "WEIGHT_SUFFIXES",
    "YCBVFrame",
    "check_output_path",
    "load_bunny",
    "load_class_names",
    "load_model_points",
    "load_problem",
    "load_ycbv_frame",
    "read_correspondences",
    "read_points",
    "read_weights",
    "save_problem",
    "scale_to_unit_cube",
    "synthetic_shape",
    "to_json",
    "write_json",
]
