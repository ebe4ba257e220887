"""From certpose's pose distribution to other samplers: emcee, PyMC, Nevergrad and a gtsam graph.

Usage::

    python examples/distribution_to_samplers.py [--samples 2000] [--walkers 32] [--steps 40]

1. The demo (a mug whose handle is hidden): its MLE and pose distribution (``certpose pose
   --demo --samples N`` in Python), and the distribution's target ``exp(eq. (1) / T)`` as a
   callable (:func:`certpose.sampling.target.pose_target`).
2. emcee: walkers drawn from the distribution in the chart around its heaviest mode
   (``xi = (log(R_ref^T R), t - t_ref)``), run on ``PoseTarget.chart_log_prob``.
3. PyMC: the same density as a black-box PyTensor ``Op`` (no gradient: a gradient-free step),
   chains started from the distribution (``pymc_initvals``).
4. gtsam: per mode a ``PriorFactorPose3`` (mean + 6x6 covariance in gtsam's body-frame
   tangent), in a graph with a second pose 2 cm away (e.g. the object pushed by a gripper).
5. Nevergrad: TwoPointsDE on the target, its first population suggested from the distribution.
"""

from __future__ import annotations

import argparse

import numpy as np


def chart_op(target, T_ref):  # noqa: ANN001, ANN201
    """A PyTensor ``Op``: the vector ``xi`` (6,) -> ``target.chart_log_prob(xi, T_ref)``."""
    import pytensor.tensor as pt
    from pytensor.graph.basic import Apply
    from pytensor.graph.op import Op

    class ChartLogProb(Op):
        def make_node(self, xi):  # noqa: ANN001, ANN202
            return Apply(self, [pt.as_tensor_variable(xi)], [pt.dscalar()])

        def perform(self, node, inputs, outputs):  # noqa: ANN001, ANN202
            outputs[0][0] = np.asarray(target.chart_log_prob(inputs[0], T_ref), dtype=np.float64)

    return ChartLogProb()


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--samples", type=int, default=2000, help="particles of the distribution")
    ap.add_argument("--walkers", type=int, default=32, help="emcee walkers")
    ap.add_argument("--steps", type=int, default=40, help="emcee steps and PyMC draws per chain")
    ap.add_argument("--de-budget", type=int, default=2000, help="Nevergrad evaluations")
    args = ap.parse_args()

    import emcee
    import gtsam
    import pymc as pm

    from certpose.estimation.pipeline import PoseParams, run_demo
    from certpose.sampling import ISParams
    from certpose.sampling.baselines import DEParams, de_sample
    from certpose.sampling.chart import from_chart
    from certpose.sampling.initialisers import (
        emcee_walkers,
        gtsam_priors,
        nevergrad_population,
        pymc_initvals,
    )
    from certpose.sampling.target import demo_object_model, pose_target

    res = run_demo(params=PoseParams(sampler=ISParams(draws=max(10_000, args.samples),
                                                      resample=args.samples)))
    dist, T_gt = res.distribution, res.T_camera_object_gt
    target = pose_target(res, demo_object_model())
    modes = dist.modes()
    T_ref = modes[0].T
    print(f"distribution: {len(dist)} particles, {len(modes)} mode(s), heaviest mass "
          f"{modes[0].mass:.2f}; temperature {target.temperature:.3g}")

    def cm_from_truth(T: np.ndarray) -> float:
        return 100.0 * float(np.median(np.linalg.norm(T[:, :3, 3] - T_gt[:3, 3], axis=1)))

    # --- emcee in the chart around the heaviest mode -----------------------------------------
    p0 = emcee_walkers(dist, args.walkers, T_ref=T_ref, rng=0)
    sampler = emcee.EnsembleSampler(args.walkers, 6, target.chart_log_prob, args=(T_ref,))
    state = sampler.run_mcmc(p0, args.steps)  # emcee checks the walkers are independent
    print(f"emcee: {args.walkers} walkers x {args.steps} steps, acceptance "
          f"{sampler.acceptance_fraction.mean():.2f}, chain shape {sampler.get_chain().shape}; "
          f"final walkers {cm_from_truth(from_chart(state.coords, T_ref)):.2f} cm from the truth (median)")

    # --- PyMC: the target as a black-box Op --------------------------------------------------
    with pm.Model():
        xi = pm.Flat("xi", shape=6)
        pm.Potential("pose", chart_op(target, T_ref)(xi))
        idata = pm.sample(draws=args.steps, tune=args.steps, chains=2, cores=1,
                          step=pm.DEMetropolisZ(), initvals=pymc_initvals(dist, 2, T_ref=T_ref, rng=0),
                          progressbar=False, compute_convergence_checks=False, random_seed=0)
    draws = from_chart(idata.posterior["xi"].values.reshape(-1, 6), T_ref)
    print(f"pymc: 2 chains x {args.steps} draws (DEMetropolisZ); draws "
          f"{cm_from_truth(draws):.2f} cm from the truth (median)")

    # --- gtsam: a prior per mode, and a second pose 2 cm away ---------------------------------
    x0, x1 = gtsam.symbol("x", 0), gtsam.symbol("x", 1)
    graph = gtsam.NonlinearFactorGraph()
    (prior, mass), *_ = gtsam_priors(dist, x0)
    graph.add(prior)
    push = gtsam.Pose3(gtsam.Rot3(), gtsam.Point3(0.02, 0.0, 0.0))  # in the object frame
    graph.add(gtsam.BetweenFactorPose3(x0, x1, push, gtsam.noiseModel.Isotropic.Sigma(6, 1e-3)))
    init = gtsam.Values()
    init.insert(x0, gtsam.Pose3(res.T_camera_object))
    init.insert(x1, gtsam.Pose3(res.T_camera_object))
    result = gtsam.LevenbergMarquardtOptimizer(graph, init).optimize()
    P0, P1 = result.atPose3(x0).matrix(), result.atPose3(x1).matrix()
    cov1 = gtsam.Marginals(graph, result).marginalCovariance(x1)
    print(f"gtsam: prior on the heaviest mode (mass {mass:.2f}); x1 "
          f"{100 * np.linalg.norm(P1[:3, 3] - P0[:3, 3]):.2f} cm away; x1's standard deviations: "
          f"rotation {np.degrees(np.sqrt(np.diag(cov1)[:3])).round(1).tolist()} deg, translation "
          f"{(1000 * np.sqrt(np.diag(cov1)[3:])).round(2).tolist()} mm")

    # --- Nevergrad: DE started from the distribution (camera frame) ---------------------------
    T_mle = res.T_camera_object
    de = de_sample(target.log_likelihood, T_mle, init=nevergrad_population(dist, 32, T_ref=T_mle, rng=0),
                   rng=0, params=DEParams(max_evaluations=args.de_budget,
                                          temperature=target.temperature, batch=32))
    best = de.weighted.poses[int(np.argmax(de.weighted.weights))]
    print(f"nevergrad: TwoPointsDE, {de.num_evaluations} evaluations from 32 suggested poses; "
          f"best pose {cm_from_truth(best[None]):.2f} cm from the truth, population ESS {de.ess:.0f}")


if __name__ == "__main__":
    main()
