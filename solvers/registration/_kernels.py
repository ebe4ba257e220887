"""Numba kernels for the hot loops of GNC and pruning (consistency graph, greedy clique, voting).

Kept free of Python objects so each call costs microseconds; compiled once and cached. Callers
pass C-contiguous, writable float64 arrays (:func:`as_kernel_array`): numba compiles a separate
specialisation for read-only arrays, which would double the first run's compile time. Sorting
is done by the callers in numpy (numba would compile its own mergesort).
"""

from __future__ import annotations

import numpy as np
from numba import njit

from solvers.procrustes import procrustes_kernel

procrustes = procrustes_kernel()  # the one weighted Procrustes, compiled


def as_kernel_array(value, dtype=np.float64):
    """``value`` as a C-contiguous, writable array of ``dtype`` (copied only when needed)."""
    return np.require(value, dtype=dtype, requirements=["C", "W"])


@njit(cache=True)
def residuals_sq(a, b, R, t, inv_beta2):  # pragma: no cover - compiled
    n = a.shape[0]
    r2 = np.empty(n)
    for k in range(n):
        s = 0.0
        for i in range(3):
            d = b[k, i] - t[i] - (R[i, 0] * a[k, 0] + R[i, 1] * a[k, 1] + R[i, 2] * a[k, 2])
            s += d * d
        r2[k] = s * inv_beta2[k]
    return r2


@njit(cache=True)
def gnc_tls(a, b, prior_w, inv_beta2, cbar2, max_iter, mu_factor, cost_tol):  # pragma: no cover
    """GNC-TLS (Yang et al. 2020) with per-correspondence prior weights.

    Returns (R, t, gnc_weights, iterations, converged, ok).
    """
    n = a.shape[0]
    w = np.empty(n)
    for k in range(n):
        w[k] = prior_w[k]
    R, t, ok = procrustes(a, b, w)
    if not ok:
        return R, t, w, 0, False, False
    r2 = residuals_sq(a, b, R, t, inv_beta2)
    r2max = 0.0
    for k in range(n):
        if prior_w[k] > 0.0 and r2[k] > r2max:
            r2max = r2[k]
    gw = np.empty(n)
    for k in range(n):
        gw[k] = 1.0
    if 2.0 * r2max <= cbar2:
        # Every residual is already inside the truncation: least squares is the TLS optimum.
        return R, t, gw, 1, True, True
    mu = cbar2 / (2.0 * r2max - cbar2)
    prev_cost = np.inf
    it = 0
    converged = False
    cbar = np.sqrt(cbar2)
    while it < max_iter:
        it += 1
        lo = mu / (mu + 1.0) * cbar2
        hi = (mu + 1.0) / mu * cbar2
        for k in range(n):
            if r2[k] <= lo:
                gw[k] = 1.0
            elif r2[k] >= hi:
                gw[k] = 0.0
            else:
                gw[k] = cbar / np.sqrt(r2[k]) * np.sqrt(mu * (mu + 1.0)) - mu
            w[k] = gw[k] * prior_w[k]
        R, t, ok = procrustes(a, b, w)
        if not ok:
            return R, t, gw, it, False, False
        r2 = residuals_sq(a, b, R, t, inv_beta2)
        cost = 0.0
        for k in range(n):
            cost += w[k] * r2[k]
        if abs(cost - prev_cost) <= cost_tol * max(1.0, abs(cost)):
            converged = True
            break
        # Binary weights mean the surrogate equals TLS: further mu increases change nothing.
        binary = True
        for k in range(n):
            if gw[k] != 0.0 and gw[k] != 1.0:
                binary = False
                break
        if binary and it > 1 and abs(cost - prev_cost) <= 1e-9 * max(1.0, abs(cost)):
            converged = True
            break
        prev_cost = cost
        mu *= mu_factor
    return R, t, gw, it, converged, True


@njit(cache=True, fastmath=True)
def consistency_matrix(at, bt, beta, cbar):  # pragma: no cover - compiled
    """Dense symmetric adjacency (uint8) of the pairwise-consistency graph.

    ``at``/``bt`` are the points transposed, (3, N) contiguous, so the inner loop vectorises.
    ``i ~ j`` when |‖a_j - a_i‖ - ‖b_j - b_i‖| <= cbar (β_i + β_j); the diagonal is 0.
    """
    n = at.shape[1]
    ax, ay, az = at[0], at[1], at[2]
    bx, by, bz = bt[0], bt[1], bt[2]
    adj = np.zeros((n, n), dtype=np.uint8)
    for i in range(n):
        row = adj[i]
        for j in range(n):
            x0 = ax[j] - ax[i]
            x1 = ay[j] - ay[i]
            x2 = az[j] - az[i]
            y0 = bx[j] - bx[i]
            y1 = by[j] - by[i]
            y2 = bz[j] - bz[i]
            d = np.sqrt(x0 * x0 + x1 * x1 + x2 * x2) - np.sqrt(y0 * y0 + y1 * y1 + y2 * y2)
            row[j] = abs(d) <= cbar * (beta[i] + beta[j])
        row[i] = 0
    return adj


@njit(cache=True)
def multistart_greedy_clique(adj, deg, order):  # pragma: no cover - compiled
    """Best of the greedy cliques grown inside each vertex's neighbourhood (by degree order).

    ``order`` lists the vertices by decreasing degree. A cheap, strong lower bound on the
    maximum clique: O(N * d * c) for degree d and clique size c.
    """
    n = adj.shape[0]
    best = np.empty(0, dtype=np.int64)
    in_best = np.zeros(n, dtype=np.bool_)
    members = np.empty(n, dtype=np.int64)
    for v in order:
        if deg[v] + 1 <= best.shape[0]:
            break  # later starts have lower degree: none can beat the best clique
        if in_best[v]:
            continue  # its neighbourhood was just explored from inside the best clique
        members[0] = v
        m = 1
        for u in order:
            if u == v or adj[v, u] == 0:
                continue
            ok = True
            for k in range(1, m):
                if adj[u, members[k]] == 0:
                    ok = False
                    break
            if ok:
                members[m] = u
                m += 1
        if m > best.shape[0]:
            best = members[:m].copy()
            in_best[:] = False
            in_best[best] = True
    return best


@njit(cache=True)
def scalar_tls(v, beta, w, cbar2, ends, order):  # pragma: no cover - compiled
    """Exact scalar TLS by sweeping sorted interval endpoints; returns (x, cost, found).

    ``ends`` (2N,) holds ``v - beta cbar`` then ``v + beta cbar``; ``order`` sorts it (stable).
    ``found`` is False when no piece beats "all outliers" (then any x is optimal).
    """
    n = v.shape[0]
    total_w = 0.0
    for k in range(n):
        total_w += w[k]
    s0 = 0.0
    s1 = 0.0
    s2 = 0.0
    aw = 0.0
    best_x = 0.0
    best_cost = total_w * cbar2
    found = False
    for m in range(2 * n - 1):
        e = order[m]
        k = e if e < n else e - n
        sign = 1.0 if e < n else -1.0
        p = w[k] / (beta[k] * beta[k])
        s0 += sign * p
        s1 += sign * p * v[k]
        s2 += sign * p * v[k] * v[k]
        aw += sign * w[k]
        lo = ends[e]
        hi = ends[order[m + 1]]
        if s0 <= 1e-300 or hi < lo:
            continue
        x = min(max(s1 / s0, lo), hi)
        cost = s0 * x * x - 2.0 * s1 * x + s2 + (total_w - aw) * cbar2
        if cost < best_cost:
            best_cost = cost
            best_x = x
            found = True
    return best_x, best_cost, found
