"""Benchmark of the noise-injected importance sampler on the demo mug.

Target: 10,000 resampled particles with ESS >= 1,000 in <= 2 s of sampling.

    PYTHONPATH=. python examples/benchmarks/bench_sampler.py [--draws 10000] [--rounds 6] [--repeats 3]
"""

from __future__ import annotations

import argparse
import os
import time
from dataclasses import replace

import numpy as np


def build_demo(seed: int = 0, likelihood_params=None, revolution: str | None = "auto", *,  # noqa: ANN001, ANN201
               mle: bool = True, elevation_deg=None, ring_modes: bool = True):
    """The `certpose pose --demo` scene, its likelihood, MLE and ground truth (``likelihood_params``:
    other eq. (1) constants than the defaults, for the MLE and the likelihood; ``revolution``:
    the object model's, as :func:`certpose.estimation.pipeline.run_demo`'s; ``mle=False``: no
    MLE, None in its place, about 2 s less; ``elevation_deg``: the model views' elevations,
    :meth:`~certpose.data.synthetic.SyntheticScene.render_object_views`'s default when None;
    ``ring_modes``: the MLE's, :class:`~certpose.estimation.mle.MLEParams`)."""
    from certpose.data.synthetic import make_mug_scene
    from certpose.estimation.mle import estimate_mle
    from certpose.estimation.pipeline import PoseParams, _scene_for
    from certpose.geometry.features import FPFHBackbone
    from certpose.geometry.objects import object_from_views
    from certpose.model.classifier import classify_from_mask
    from certpose.model.likelihood import PoseLikelihood

    params, backbone, gen = PoseParams(), FPFHBackbone(), np.random.default_rng(seed)
    if likelihood_params is not None:
        params = replace(params, likelihood=likelihood_params)
    params = replace(params, mle=replace(params.mle, ring_modes=ring_modes))
    sc = make_mug_scene(rng=gen)
    views = (sc.render_object_views(4) if elevation_deg is None else
             sc.render_object_views(4, elevation_deg=elevation_deg))
    scene = _scene_for(sc.frame, sc.object_mask, params, backbone)
    obj = object_from_views(views, backbone, voxel_size=params.voxel_size, name="mug", revolution=revolution)
    cls = classify_from_mask(scene, sc.frame.with_mask(sc.object_mask), params=params.classifier)
    result = None
    if mle:
        result = estimate_mle(scene, cls, obj, params=params.mle, likelihood_params=params.likelihood,
                              viewpoint=np.zeros(3), rng=gen)
    lik = PoseLikelihood(scene, cls, obj, params=params.likelihood)
    return lik, result, sc.T_camera_object


def main() -> None:
    from certpose.sampling.sampler import ISParams, sample_pose_distribution, seeds_from_mle

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--draws", type=int, default=10_000)
    ap.add_argument("--rounds", type=int, default=ISParams.rounds)
    ap.add_argument("--repeats", type=int, default=3)
    args = ap.parse_args()
    lik, mle, gt = build_demo()
    seeds = seeds_from_mle(mle)
    params = ISParams(draws=args.draws, rounds=args.rounds, resample=10_000)
    sample_pose_distribution(lik, seeds, params=ISParams(draws=500, rounds=1), rng=0)  # JIT warm-up
    print(f"load average {os.getloadavg()}, {len(seeds)} seeds, {lik.num_points} model points")
    for r in range(args.repeats):
        t = time.perf_counter()
        res = sample_pose_distribution(lik, seeds, params=params, rng=r)
        dt = time.perf_counter() - t
        d = res.weighted
        x = res.distribution.tangent(gt[:3, :3], gt[:3, 3])
        axis = res.distribution.rotations[:, :, 2] @ gt[:3, 2]
        tilt = np.degrees(np.arccos(np.clip(axis, -1, 1)))
        print(f"run {r}: {dt:.2f} s wall ({res.seconds:.2f} s sampling), T = {res.temperature:.1f}, "
              f"ESS {d.ess:.0f} of {len(d)} (per round {', '.join(f'{e:.0f}' for e in res.ess_per_round)}), "
              f"Pareto-k {d.pareto_k():.2f}, {res.num_evaluations} evaluations; resampled 10,000: "
              f"axis tilt q95 {np.quantile(tilt, 0.95):.2f} deg, "
              f"translation error q95 {1e3 * np.quantile(np.linalg.norm(x[:, 3:], axis=1), 0.95):.2f} mm")
        modes = d.modes()
        print("  modes (mass, particles): " + ", ".join(f"{m.mass:.3f} ({m.num_particles})" for m in modes))


if __name__ == "__main__":
    main()
