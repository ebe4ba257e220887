"""Certify a registration: is the returned pose globally optimal, and for which problem?

Usage::

    python examples/certify_pose.py [--n 60] [--outliers 0.5] [--seed 0]

Builds a bunny-protocol instance (the TEASER++/QUASAR protocol; a synthetic shape when the bunny is not in
``../shared/data``), registers it with ``certify=True``, and then certifies the same pose, and a
pose rotated 5 degrees away from it, with :func:`solvers.certify.certify_pose`. A certificate
vouches only for the pose it is attached to, on the problem it names.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation

import certpose
from solvers import WeightedTLSProblem
from solvers.certify import certify_pose

BUNNY = Path(__file__).resolve().parents[2] / "shared" / "data" / "bunny" / "bun_zipper_res3.ply"


def make_problem(n: int, outliers: float, rng: np.random.Generator) -> WeightedTLSProblem:
    from certpose.data.instances import make_instance
    from certpose.io import load_bunny, synthetic_shape

    cloud = load_bunny(BUNNY) if BUNNY.exists() else synthetic_shape(2000)
    inst = make_instance(cloud, n, outliers, noise=0.01, rng=rng)
    return WeightedTLSProblem(inst.source, inst.target, noise_bound=inst.noise_bound)


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--n", type=int, default=60, help="correspondences (default 60)")
    parser.add_argument("--outliers", type=float, default=0.5, help="outlier ratio (default 0.5)")
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args()
    problem = make_problem(args.n, args.outliers, np.random.default_rng(args.seed))

    result = certpose.register(problem.source, problem.target, noise_bound=problem.noise_bound,
                               certify=True)
    print(f"registration: {result.status.value}, cost {result.cost:.6g}")
    cert = result.certificate
    if cert is None:
        print(f"no certificate: {result.info.get('certificate_message', result.message)}")
        return 1
    print(f"certificate of the returned pose: {cert.summary()}")

    wrong = Rotation.from_rotvec(np.radians(5.0) * np.array([0.0, 0.0, 1.0])).as_matrix()
    R_wrong = wrong @ result.rotation
    for scope in ("rotation", "full"):
        c = certify_pose(problem, R_wrong, result.translation, scope=scope, time_limit=20.0)
        print(f"pose rotated by 5 deg, scope={scope}: {c.summary()}")
        if c.certified:
            print("error: a wrong pose was certified", file=sys.stderr)
            return 1
    return 0 if cert.certified else 1


if __name__ == "__main__":
    sys.exit(main())
