"""The probabilistic model of the paper: the scene grid, the fused scene field, the object
classifier p_O, eq. (1) (the pose log-likelihood) and eq. (2) (its weighted TLS approximation).

May import :mod:`certpose.geometry` and :mod:`solvers`' public names. The grid (voxel states and
geometry) lives in :mod:`certpose.model.grid`, which every other module here imports; none of the
others imports another at module level except through it.
"""
