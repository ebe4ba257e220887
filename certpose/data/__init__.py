"""Data the project makes itself: synthetic RGB-D scenes (the embedded default of ``certpose pose
--demo``), synthetic shapes, and registration instances with ground truth (the
benchmark's protocol, also ``certpose register --demo``'s problem and the tests), and putative
FPFH correspondences on the real 3DMatch scan pair (:mod:`certpose.data.threedmatch`).

May import :mod:`certpose.geometry`, :mod:`certpose.io` (file readers) and :mod:`solvers`' public
names.
"""
