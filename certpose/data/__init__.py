"""Data the project makes itself: synthetic RGB-D scenes (the embedded default of ``certpose pose
--demo``) and synthetic shapes.

May import :mod:`certpose.geometry` and :mod:`solvers`' public names.
"""
