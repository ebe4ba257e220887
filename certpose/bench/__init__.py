"""Solver benchmarking: the runner (certpose and its peers on the same instances, drawn by
:mod:`certpose.data.instances`) and reports (tables, JSON, plots).

May import every other part of certpose and :mod:`solvers`' public names; only the CLI imports it.
"""
