"""Data the project makes itself: synthetic RGB-D scenes (the embedded default of ``certpose pose
--demo``), synthetic shapes, and registration instances with ground truth (the
benchmark's protocol, also ``certpose register --demo``'s problem and the tests').

May import :mod:`certpose.geometry` and :mod:`solvers`' public names.
"""
