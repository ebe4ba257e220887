"""From a pose distribution to other samplers: emcee walkers, a gtsam factor graph, Nevergrad.

Usage::

    python examples/distribution_to_samplers.py [--samples 2000] [--walkers 32] [--steps 40]

1. The demo scene (a mug, handle hidden), its eq. (1) likelihood, the MLE and the pose
   distribution of the importance sampler (``certpose pose --demo --samples N`` in Python).
2. emcee: walkers drawn from the distribution in the chart around its heaviest mode
   (``xi = (log(R_ref^T R), t - t_ref)``), run on the same target written in the chart (with
   the exponential map's Haar Jacobian, so that the density is per unit of ``xi``).
3. gtsam: per mode a ``PriorFactorPose3`` (mean + 6x6 covariance in gtsam's body-frame
   tangent), in a graph with a second pose 2 cm away (a ``BetweenFactorPose3``, e.g. the object
   pushed by a gripper), optimised, with the marginal covariance of the second pose.
4. Nevergrad: TwoPointsDE on the same target, its first population suggested from the
   distribution (``certpose.sampling.baselines.de_sample(init=...)``).
"""

from __future__ import annotations

import argparse
import math

import numpy as np


def demo_distribution(samples: int, seed: int = 0):  # noqa: ANN201
    """The demo's likelihood, temperature, ground truth and pose distribution (camera frame)."""
    from certpose.data.synthetic import make_mug_scene
    from certpose.estimation.mle import estimate_mle
    from certpose.geometry.features import FPFHBackbone
    from certpose.geometry.objects import object_from_views
    from certpose.model.classifier import classify_from_mask
    from certpose.model.likelihood import PoseLikelihood
    from certpose.model.scene import build_scene_field
    from certpose.sampling import ISParams, sample_pose_distribution
    from certpose.sampling.sampler import seeds_from_mle

    gen = np.random.default_rng(seed)
    backbone = FPFHBackbone()
    sc = make_mug_scene(rng=gen)
    # The scene field in the camera frame, cropped to the mug's mask + 10 cm (as the pipeline).
    scene = build_scene_field(sc.frame, backbone, voxel_size=0.005, roi_mask=sc.object_mask,
                              margin=0.1)
    obj = object_from_views(sc.render_object_views(4), backbone, voxel_size=0.005, name="mug")
    cls = classify_from_mask(scene, sc.frame.with_mask(sc.object_mask))
    mle = estimate_mle(scene, cls, obj, viewpoint=np.zeros(3), rng=gen)
    lik = PoseLikelihood(scene, cls, obj)
    res = sample_pose_distribution(lik, seeds_from_mle(mle),
                                   params=ISParams(draws=max(10_000, samples), resample=samples),
                                   rng=gen)
    return lik, res.temperature, sc.T_camera_object, res.distribution, mle.T_scene_object


def main() -> None:
    import emcee
    import gtsam

    from certpose.sampling.baselines import DEParams, de_sample
    from certpose.sampling.chart import from_chart, to_chart
    from certpose.sampling.initialisers import emcee_walkers, gtsam_priors, nevergrad_population

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--samples", type=int, default=2000)
    ap.add_argument("--walkers", type=int, default=32)
    ap.add_argument("--steps", type=int, default=40)
    ap.add_argument("--de-budget", type=int, default=2000)
    args = ap.parse_args()

    lik, temp, T_gt, dist, T_mle = demo_distribution(args.samples)
    modes = dist.modes()
    T_ref = modes[0].T
    print(f"distribution: {len(dist)} particles, {len(modes)} mode(s), heaviest mass "
          f"{modes[0].mass:.2f}; temperature {temp:.3g}")

    # --- emcee in the chart around the heaviest mode -----------------------------------------
    def log_prob(xi: np.ndarray) -> float:
        theta = float(np.linalg.norm(xi[:3]))
        if theta >= math.pi:
            return -np.inf  # one chart: rotation vectors inside the ball of radius pi
        jac = 1.0 if theta < 1e-8 else 2.0 * (1.0 - math.cos(theta)) / theta**2
        return float(lik(from_chart(xi, T_ref))[0]) / temp + math.log(jac)

    p0 = emcee_walkers(dist, args.walkers, T_ref=T_ref, rng=0)
    sampler = emcee.EnsembleSampler(args.walkers, 6, log_prob)
    state = sampler.run_mcmc(p0, args.steps)  # emcee checks the walkers are independent
    chain = sampler.get_chain()
    T_last = from_chart(state.coords, T_ref)
    off = np.linalg.norm(T_last[:, :3, 3] - T_gt[:3, 3], axis=1)
    print(f"emcee: {args.walkers} walkers x {args.steps} steps, acceptance "
          f"{sampler.acceptance_fraction.mean():.2f}, chain shape {chain.shape}; final walkers "
          f"{100 * np.median(off):.2f} cm from the truth (median)")

    # --- gtsam: a prior per mode, and a second pose 2 cm away ---------------------------------
    x0, x1 = gtsam.symbol("x", 0), gtsam.symbol("x", 1)
    graph = gtsam.NonlinearFactorGraph()
    (prior, mass), *_ = gtsam_priors(dist, x0)
    graph.add(prior)
    push = gtsam.Pose3(gtsam.Rot3(), gtsam.Point3(0.02, 0.0, 0.0))  # in the object frame
    graph.add(gtsam.BetweenFactorPose3(x0, x1, push, gtsam.noiseModel.Isotropic.Sigma(6, 1e-3)))
    init = gtsam.Values()
    init.insert(x0, gtsam.Pose3(T_mle))
    init.insert(x1, gtsam.Pose3(T_mle))
    result = gtsam.LevenbergMarquardtOptimizer(graph, init).optimize()
    P0, P1 = result.atPose3(x0).matrix(), result.atPose3(x1).matrix()
    cov1 = gtsam.Marginals(graph, result).marginalCovariance(x1)
    print(f"gtsam: prior on the heaviest mode (mass {mass:.2f}); x0 at the mode mean "
          f"(|dt| {np.linalg.norm(P0[:3, 3] - T_ref[:3, 3]):.1e} m), x1 "
          f"{100 * np.linalg.norm(P1[:3, 3] - P0[:3, 3]):.2f} cm away; x1's standard deviations: "
          f"rotation {np.degrees(np.sqrt(np.diag(cov1)[:3])).round(1).tolist()} deg, translation "
          f"{(1000 * np.sqrt(np.diag(cov1)[3:])).round(2).tolist()} mm")

    # --- Nevergrad: DE started from the distribution ------------------------------------------
    init_pop = nevergrad_population(dist, 32, T_ref=T_mle, rng=0)
    de = de_sample(lik, T_mle, init=init_pop, rng=0,
                   params=DEParams(max_evaluations=args.de_budget, temperature=temp, batch=32))
    best = de.weighted.poses[int(np.argmax(de.weighted.weights))]
    x_best = to_chart(best[:3, :3][None], best[:3, 3][None], T_gt)[0]
    print(f"nevergrad: TwoPointsDE, {de.num_evaluations} evaluations from 32 suggested poses; "
          f"best pose {100 * np.linalg.norm(x_best[3:]):.2f} cm from the truth, population ESS "
          f"{de.ess:.0f}")


if __name__ == "__main__":
    main()
