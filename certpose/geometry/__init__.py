"""Geometry of observations and objects: RGB-D frames, structured point clouds, feature
descriptors and object models.

Owns cameras, back-projection, descriptor backbones (FPFH, DINO, given arrays) and
:class:`~certpose.geometry.objects.ObjectModel`. May import :mod:`solvers`' public names; never
the probabilistic model, estimation or the CLI.
"""
