"""The pose distribution: samplers of p(O_R,t) seeded by eq. (2) solutions, their baselines and
initialisers for other samplers.

May import :mod:`certpose.model`, :mod:`certpose.estimation` and :mod:`solvers`' public names;
never the CLI or the bench.
"""

from certpose.sampling.baselines import DEParams, MCMCParams, SamplerResult, de_sample, mcmc_sample
from certpose.sampling.calibration import (
    CalibratedDistribution,
    CalibrationFit,
    CalibrationParams,
    calibrated_distribution,
    fit_calibration,
)
from certpose.sampling.distribution import PoseDistribution, PoseMode
from certpose.sampling.reference import AxisMarginal, axis_marginal
from certpose.sampling.sampler import (
    ISParams,
    ISResult,
    TangentMixture,
    importance_sample,
    sample_pose_distribution,
)
from certpose.sampling.target import PoseTarget, demo_object_model, pose_target

__all__ = ["AxisMarginal", "CalibratedDistribution", "CalibrationFit", "CalibrationParams", "DEParams", "ISParams", "ISResult", "MCMCParams", "PoseDistribution", "PoseMode", "PoseTarget",
           "SamplerResult", "TangentMixture", "axis_marginal", "calibrated_distribution", "de_sample", "demo_object_model", "fit_calibration", "importance_sample",
           "mcmc_sample", "pose_target", "sample_pose_distribution"]
