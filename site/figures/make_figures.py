"""Draw the documentation's figures into docs/figures/ (the README's and the manual's).

Usage::

    python docs/figures/make_figures.py [--only demo tls bench] [--out docs/figures]

* ``demo_distribution.png``: the demo's pose distribution (``certpose pose --demo --samples
  10000 --plot``): marginals of roll, pitch, yaw and x, y, z, and the turn about the mug's axis,
  with the exact arc on which the handle is hidden shaded.
* ``tls_cost.png``: the truncated least-squares cost and the graduated non-convexity surrogates
  that GNC minimises on the way to it.
* ``bench.png``: success rate and median time against the outlier ratio of certpose and its
  peers on the bunny protocol (``certpose bench --n 100 --trials 10 --plot``; synthetic shape
  when the bunny is not in ``../shared/data``).
"""

from __future__ import annotations

import argparse
import shutil
import tempfile
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
DPI = 60  # small files: the PNGs live in the repository


def demo(out: Path) -> Path:
    """The demo's pose distribution, as ``certpose pose --demo --samples 10000 --plot``."""
    from certpose.data.synthetic import make_mug_scene
    from certpose.estimation.pipeline import PoseParams, run_demo
    from certpose.sampling import ISParams
    from certpose.sampling.plots import plot_marginals

    res = run_demo(params=PoseParams(sampler=ISParams(resample=10_000)), rng=0)
    arcs = make_mug_scene(rng=0).hidden_handle_arc(step=1.0).arcs
    info = res.sampling
    return plot_marginals(res.distribution, out / "demo_distribution.png", axis=(0.0, 0.0, 1.0),
                          T_gt=res.T_camera_object_gt, T_ref=res.T_camera_object_gt, arcs=arcs,
                          arcs_label="handle hidden", dpi=DPI,
                          title="demo mug: importance sampler, 10000 particles, ground truth in red",
                          notes=[f"ESS: {info['ess']:.0f}", f"temperature: {info['temperature']:.3g}",
                                 f"time: {info['seconds']:.2f} s"])


def tls(out: Path) -> Path:
    """rho(r) = min(r^2, 1) and GNC's surrogates for a few mu (residuals in noise bounds)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    r = np.linspace(0.0, 3.0, 400)
    fig, ax = plt.subplots(figsize=(6, 3.2))
    for mu in (0.05, 0.3, 2.0, 20.0):
        # GNC-TLS surrogate (Yang et al. 2020), cbar = 1.
        lo, hi = mu / (mu + 1.0), (mu + 1.0) / mu
        s = np.where(r**2 <= lo, r**2, np.where(r**2 >= hi, 1.0,
                     2.0 * np.sqrt(mu * (mu + 1.0)) * r - mu * (r**2 + 1.0)))
        ax.plot(r, s, lw=1, alpha=0.7, label=f"GNC, mu = {mu:g}")
    ax.plot(r, np.minimum(r**2, 1.0), "k", lw=2, label="TLS: min(r^2, 1)")
    ax.set_xlabel("residual / noise bound")
    ax.set_ylabel("cost")
    ax.legend(fontsize=8)
    fig.tight_layout()
    path = out / "tls_cost.png"
    fig.savefig(path, dpi=DPI + 20)
    plt.close(fig)
    return path


def bench(out: Path) -> Path:
    """certpose and its peers on the bunny protocol, N = 100."""
    from certpose.bench.report import plot_report
    from certpose.bench.runner import BenchConfig, run_benchmark
    from certpose.io.points import load_bunny

    bunny = HERE.parents[2] / "shared" / "data" / "bunny" / "bun_zipper_res3.ply"
    shape = load_bunny(bunny) if bunny.is_file() else None
    cfg = BenchConfig(trials=10, solvers=("gnc", "gnc+certify", "gtsam-gnc", "o3d-ransac", "o3d-fgr"))
    report = run_benchmark(cfg, shape=shape, shape_name=str(bunny) if shape is not None else "synthetic",
                           progress=False)
    with tempfile.TemporaryDirectory() as tmp:
        paths = plot_report(report.summary, report.scopes, tmp, title="bunny protocol, N = 100")
        shutil.copy(paths[0], out / "bench.png")
    return out / "bench.png"


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--only", nargs="+", choices=("demo", "tls", "bench"), default=("demo", "tls", "bench"))
    ap.add_argument("--out", type=Path, default=HERE, help="folder of the PNGs (default docs/figures)")
    args = ap.parse_args()
    for name in args.only:
        path = {"demo": demo, "tls": tls, "bench": bench}[name](args.out)
        print(f"wrote {path} ({path.stat().st_size // 1024} KiB)")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
