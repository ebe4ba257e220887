"""Numba kernels for the hot loops of GNC and pruning.

Kept free of Python objects so each call costs microseconds; compiled once and cached.
"""

from __future__ import annotations

import numpy as np
from numba import njit


@njit(cache=True)
def procrustes(a, b, w):  # pragma: no cover - compiled
    """Weighted Horn/Umeyama; returns (R, t, ok). ``ok`` is False for a zero weight sum."""
    n = a.shape[0]
    sw = 0.0
    ca = np.zeros(3)
    cb = np.zeros(3)
    for k in range(n):
        sw += w[k]
        for d in range(3):
            ca[d] += w[k] * a[k, d]
            cb[d] += w[k] * b[k, d]
    R = np.eye(3)
    if sw <= 0.0:
        return R, np.zeros(3), False
    ca /= sw
    cb /= sw
    H = np.zeros((3, 3))
    for k in range(n):
        if w[k] == 0.0:
            continue
        for i in range(3):
            bi = w[k] * (b[k, i] - cb[i])
            for j in range(3):
                H[i, j] += bi * (a[k, j] - ca[j])
    U, _, Vt = np.linalg.svd(H)
    if np.linalg.det(U) * np.linalg.det(Vt) < 0.0:
        for i in range(3):
            U[i, 2] = -U[i, 2]
    R = U @ Vt
    t = cb - R @ ca
    return R, t, True


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
    w = prior_w.copy()
    R, t, ok = procrustes(a, b, w)
    if not ok:
        return R, t, w, 0, False, False
    r2 = residuals_sq(a, b, R, t, inv_beta2)
    r2max = 0.0
    for k in range(n):
        if prior_w[k] > 0.0 and r2[k] > r2max:
            r2max = r2[k]
    gw = np.ones(n)
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


@njit(cache=True)
def consistency_edges(a, b, beta, cbar):  # pragma: no cover - compiled
    """Pairs (i < j) whose translation-invariant lengths agree: |‖a_ij‖ - ‖b_ij‖| <= c(β_i + β_j).

    Returns a (E, 2) int array of edges.
    """
    n = a.shape[0]
    cap = 1024
    edges = np.empty((cap, 2), dtype=np.int64)
    m = 0
    for i in range(n):
        for j in range(i + 1, n):
            da = 0.0
            db = 0.0
            for d in range(3):
                x = a[j, d] - a[i, d]
                y = b[j, d] - b[i, d]
                da += x * x
                db += y * y
            bound = cbar * (beta[i] + beta[j])
            if abs(np.sqrt(da) - np.sqrt(db)) <= bound:
                if m == cap:
                    cap *= 2
                    grown = np.empty((cap, 2), dtype=np.int64)
                    grown[:m] = edges[:m]
                    edges = grown
                edges[m, 0] = i
                edges[m, 1] = j
                m += 1
    return edges[:m]
