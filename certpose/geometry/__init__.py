"""Geometry of observations and objects: RGB-D frames, structured point clouds, feature
descriptors and object models.

Owns cameras, back-projection, descriptor backbones (FPFH, DINO, given arrays),
:class:`~certpose.geometry.objects.ObjectModel` and the plausibility checks of cameras and
observed sizes (:mod:`~certpose.geometry.plausibility`). May import :mod:`solvers`' public names; never
the probabilistic model, estimation or the CLI.
"""
