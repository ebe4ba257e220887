"""Pose estimation on the model: coarse search, local refinement, the maximum-likelihood pose,
the RGB-D pipeline and pose-error metrics.

May import :mod:`certpose.model`, :mod:`certpose.geometry`, :mod:`certpose.io`,
:mod:`certpose.data` and :mod:`solvers`' public names; never the CLI or the bench.
"""
