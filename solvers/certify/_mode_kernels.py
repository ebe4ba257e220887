"""Numba kernel of the mode-set branch and bound: the bounds of a batch of pose boxes.

Compiled once and cached on disk. It releases the GIL, so :mod:`solvers.certify.mode_set` runs
large batches as chunks on a thread pool.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit
from numba import types as nt

from solvers.jit import kernel

F1, F2 = nt.float64[::1], nt.float64[:, ::1]
I1 = nt.int64[::1]
f8 = nt.float64

_FISTA_ITERATIONS = 60


@njit(cache=True)
def _set_distance(e0, e1, e2, h, r):  # pragma: no cover - compiled
    """Distance from the origin to ``e + C_h + B_r`` (a cube of half-width ``h`` plus a ball of
    radius ``r``, both centred at ``e``), 0 inside."""
    x = max(abs(e0) - h, 0.0)
    y = max(abs(e1) - h, 0.0)
    z = max(abs(e2) - h, 0.0)
    return max(math.sqrt(x * x + y * y + z * z) - r, 0.0)


@njit(cache=True)
def _project(x, theta, h):  # pragma: no cover - compiled
    """Project ``x = (omega, du)`` onto ``||omega|| <= theta`` times ``|du_i| <= h``, in place."""
    n = math.sqrt(x[0] * x[0] + x[1] * x[1] + x[2] * x[2])
    if n > theta:
        f = theta / n
        x[0] *= f
        x[1] *= f
        x[2] *= f
    for i in range(3, 6):
        x[i] = min(h, max(-h, x[i]))


@njit(cache=True)
def _feasible(x, theta, h):  # pragma: no cover - compiled
    if x[0] * x[0] + x[1] * x[1] + x[2] * x[2] > theta * theta:
        return False
    return abs(x[3]) <= h and abs(x[4]) <= h and abs(x[5]) <= h


@njit(cache=True)
def _cholesky_solve(H, g, x):  # pragma: no cover - compiled
    """``x = -H^-1 g`` for a 6x6 symmetric ``H`` (regularised); False when not positive."""
    L = np.zeros((6, 6))
    tr = 0.0
    for i in range(6):
        tr += H[i, i]
    reg = 1e-12 * tr + 1e-300
    for i in range(6):
        for j in range(i + 1):
            s = H[i, j] + (reg if i == j else 0.0)
            for k in range(j):
                s -= L[i, k] * L[j, k]
            if i == j:
                if s <= 0.0:
                    return False
                L[i, i] = math.sqrt(s)
            else:
                L[i, j] = s / L[j, j]
    y = np.empty(6)
    for i in range(6):
        s = -g[i]
        for k in range(i):
            s -= L[i, k] * y[k]
        y[i] = s / L[i, i]
    for i in range(5, -1, -1):
        s = y[i]
        for k in range(i + 1, 6):
            s -= L[k, i] * x[k]
        x[i] = s / L[i, i]
    return True


@njit(cache=True)
def _qp_lower(H, g, q0, theta, h):  # pragma: no cover - compiled
    """A lower bound on ``min q0 + 2 g.x + x.H x`` over ``||x[:3]|| <= theta``, ``|x[3:]| <= h``
    (``H`` positive semidefinite): at any ``x``, convexity gives ``Q(y) >= Q(x) +
    grad.(y - x)``, whose least value over the set is closed form; ``x`` is the Newton point
    when feasible, else accelerated projected gradient steps from its projection."""
    x = np.zeros(6)
    if _cholesky_solve(H, g, x):
        if not _feasible(x, theta, h):
            _project(x, theta, h)
            L = 0.0  # Gershgorin: an upper bound on H's largest eigenvalue
            for i in range(6):
                s = 0.0
                for j in range(6):
                    s += abs(H[i, j])
                L = max(L, s)
            if L > 0.0:
                y = x.copy()
                xo = x.copy()
                tk = 1.0
                for _ in range(_FISTA_ITERATIONS):
                    for i in range(6):
                        gi = g[i]
                        for j in range(6):
                            gi += H[i, j] * y[j]
                        xo[i] = y[i] - gi / L
                    _project(xo, theta, h)
                    tn = 0.5 * (1.0 + math.sqrt(1.0 + 4.0 * tk * tk))
                    for i in range(6):
                        y[i] = xo[i] + (tk - 1.0) / tn * (xo[i] - x[i])
                        x[i] = xo[i]
                    tk = tn
    val = q0
    gr = np.empty(6)
    for i in range(6):
        hx = 0.0
        for j in range(6):
            hx += H[i, j] * x[j]
        val += 2.0 * g[i] * x[i] + x[i] * hx
        gr[i] = 2.0 * (hx + g[i])
    lin = val
    for i in range(6):
        lin -= gr[i] * x[i]
    lin -= theta * math.sqrt(gr[0] * gr[0] + gr[1] * gr[1] + gr[2] * gr[2])
    lin -= h * (abs(gr[3]) + abs(gr[4]) + abs(gr[5]))
    return lin


@njit(cache=True)
def _coupled_bound(R, u0, u1, u2, theta, h, src, dst, a, wc, tau):  # pragma: no cover - compiled
    """A lower bound of the cost over a box that keeps the points' motion rigid (see
    :mod:`solvers.certify.mode_set`): each term's minorant over its ball, a constant or a
    quadratic, and the quadratics' sum minimised over the box's linearised motions."""
    chord = 2.0 * math.sin(0.5 * theta)
    rt = math.sqrt(3.0) * h
    rem = 0.5 * theta * theta + theta * theta * theta / 6.0
    H = np.zeros((6, 6))
    g = np.zeros(6)
    q0 = 0.0
    const = 0.0
    J = np.zeros((3, 6))
    J[0, 3] = J[1, 4] = J[2, 5] = 1.0
    for k in range(src.shape[0]):
        s0, s1, s2 = src[k, 0], src[k, 1], src[k, 2]
        p0 = R[0, 0] * s0 + R[0, 1] * s1 + R[0, 2] * s2
        p1 = R[1, 0] * s0 + R[1, 1] * s1 + R[1, 2] * s2
        p2 = R[2, 0] * s0 + R[2, 1] * s1 + R[2, 2] * s2
        r0, r1, r2 = p0 + u0 - dst[k, 0], p1 + u1 - dst[k, 1], p2 + u2 - dst[k, 2]
        dist = math.sqrt(r0 * r0 + r1 * r1 + r2 * r2)
        pn = math.sqrt(s0 * s0 + s1 * s1 + s2 * s2)
        rho = chord * pn + rt
        near = _set_distance(r0, r1, r2, h, chord * pn)  # least distance over the box
        if near >= tau[k]:
            const += wc[k]  # an outlier over the whole box
            continue
        # Linearised motion: exp(w) p = p + w x p + e, |e| <= |p| (theta^2/2 + theta^3/6).
        eps = pn * rem
        J[0, 0] = 0.0; J[0, 1] = p2; J[0, 2] = -p1  # noqa: E702  (J xi = w x p + du)
        J[1, 0] = -p2; J[1, 1] = 0.0; J[1, 2] = p0  # noqa: E702
        J[2, 0] = p1; J[2, 1] = -p0; J[2, 2] = 0.0  # noqa: E702
        if dist + rho > tau[k]:
            # Undecided over its box: along the radius x = |q - b| in [lo, hi] the term is
            # min(a x^2, wc) >= phi(lo) + s (x - lo) with s = min(2 a lo, (wc - phi(lo)) /
            # (hi - lo)) (below the quadratic's tangent, below wc at hi), and x >= n.(q - b)
            # with n the unit direction at the centre: an affine minorant of the motion.
            lo = near
            flo = a[k] * lo * lo
            sl = min(2.0 * a[k] * lo, (wc[k] - flo) / max(dist + rho - lo, 1e-300))
            if sl <= 0.0 or dist <= 0.0:
                const += flo
                continue
            n0, n1, n2 = r0 / dist, r1 / dist, r2 / dist
            const += flo + sl * (dist - lo) - sl * eps
            for i in range(6):
                g[i] += 0.5 * sl * (J[0, i] * n0 + J[1, i] * n1 + J[2, i] * n2)
            continue
        # An inlier over its ball: a |x + e|^2 >= a |x|^2 - 2 a |x| |e| with the linearised
        # residual |x| <= dist + theta |p| + sqrt(3) h.
        const -= 2.0 * a[k] * eps * (dist + theta * pn + rt)
        ak = a[k]
        for i in range(6):
            g[i] += ak * (J[0, i] * r0 + J[1, i] * r1 + J[2, i] * r2)
            for j in range(i, 6):
                H[i, j] += ak * (J[0, i] * J[0, j] + J[1, i] * J[1, j] + J[2, i] * J[2, j])
        q0 += ak * (r0 * r0 + r1 * r1 + r2 * r2)
    for i in range(6):
        for j in range(i):
            H[i, j] = H[j, i]
    return const + _qp_lower(H, g, q0, theta, h)


@kernel(F2, F2, I1, F2, F1, F1, I1, F1, I1, F2, F1, F2, F2, F1, F1, F1, f8, f8, F1, F1,
        nogil=True)
def box_bounds(boxes, group_src, sub_start, sub_centre, sub_weight, sub_const, sub_mask, cap,
               term_start, term_dst, term_tau, src, dst, a, wc, tau, threshold, couple_rho,
               lower, upper):  # pragma: no cover - compiled
    """Lower and upper bounds of the weighted TLS cost over each pose box.

    A box row starts ``(v0, v1, v2, sigma, u0, u1, u2, h)``: rotation vectors in the cube of
    half-side ``sigma`` about ``v``, translations in the cube of half-width ``h`` about ``u``.
    ``lower[b]``: the sum over groups of each group's exact minimum over the ball that holds its
    source point's image (subsets sorted by ``sub_const`` within a group, ``cap`` the group's
    all-outlier cost). Only subsets of the group's terms that the ball can bring within their
    truncation radius (``term_tau``) are tried: adding a term that is truncated over the whole
    ball never lowers a subset's cost there (``sub_mask``: the subset's terms, bit ``i`` for the
    group's ``i``-th term from ``term_start``). ``upper[b]``: the cost at the box's centre (terms ``min(a ||R s + u -
    d||^2, wc)``). Boxes whose group bound is at most ``threshold`` and over which no point
    moves more than ``couple_rho`` also get the rigid (coupled) bound; the larger counts. A box's
    sum stops once it exceeds ``threshold`` (the partial sum is its lower bound; the groups come
    with the largest all-outlier costs first), and its ``upper`` is then ``inf`` (no use).
    """
    B = boxes.shape[0]
    G = group_src.shape[0]
    K = src.shape[0]
    R = np.empty((3, 3))
    rmax = 0.0
    for k in range(K):
        rmax = max(rmax, math.sqrt(src[k, 0] ** 2 + src[k, 1] ** 2 + src[k, 2] ** 2))
    for b in range(B):
        v0, v1, v2 = boxes[b, 0], boxes[b, 1], boxes[b, 2]
        th = math.sqrt(v0 * v0 + v1 * v1 + v2 * v2)
        if th < 1e-12:
            R[0, 0] = 1.0; R[0, 1] = -v2; R[0, 2] = v1  # noqa: E702
            R[1, 0] = v2; R[1, 1] = 1.0; R[1, 2] = -v0  # noqa: E702
            R[2, 0] = -v1; R[2, 1] = v0; R[2, 2] = 1.0  # noqa: E702
        else:
            x, y, z = v0 / th, v1 / th, v2 / th
            c, s = math.cos(th), math.sin(th)
            C = 1.0 - c
            R[0, 0] = c + x * x * C; R[0, 1] = x * y * C - z * s; R[0, 2] = x * z * C + y * s  # noqa: E702
            R[1, 0] = y * x * C + z * s; R[1, 1] = c + y * y * C; R[1, 2] = y * z * C - x * s  # noqa: E702
            R[2, 0] = z * x * C - y * s; R[2, 1] = z * y * C + x * s; R[2, 2] = c + z * z * C  # noqa: E702
        u0, u1, u2 = boxes[b, 4], boxes[b, 5], boxes[b, 6]
        # Any rotation vector of the cube is within sqrt(3) sigma of the centre's, and the angle
        # between two rotations is at most the distance of their rotation vectors.
        ang = min(math.sqrt(3.0) * boxes[b, 3], math.pi)
        chord = 2.0 * math.sin(0.5 * ang)
        hb = boxes[b, 7]
        rt = math.sqrt(3.0) * hb
        lb = 0.0
        for g in range(G):
            p0, p1, p2 = group_src[g, 0], group_src[g, 1], group_src[g, 2]
            q0 = R[0, 0] * p0 + R[0, 1] * p1 + R[0, 2] * p2 + u0
            q1 = R[1, 0] * p0 + R[1, 1] * p1 + R[1, 2] * p2 + u1
            q2 = R[2, 0] * p0 + R[2, 1] * p1 + R[2, 2] * p2 + u2
            # The image lies in (ball of the rotation's chord) + (translation cube).
            rr = chord * math.sqrt(p0 * p0 + p1 * p1 + p2 * p2)
            best = cap[g]
            reach = 0
            for i in range(term_start[g], term_start[g + 1]):
                # Within reach: the distance from the cube's points to the target is below
                # the truncation radius plus the ball's (squares: no root).
                x = max(abs(term_dst[i, 0] - q0) - hb, 0.0)
                y = max(abs(term_dst[i, 1] - q1) - hb, 0.0)
                z = max(abs(term_dst[i, 2] - q2) - hb, 0.0)
                if x * x + y * y + z * z < (term_tau[i] + rr) * (term_tau[i] + rr):
                    reach |= 1 << (i - term_start[g])
            if reach == 0:
                lb += best
                if lb > threshold:
                    break  # pruned already: the partial sum is a lower bound too
                continue
            for j in range(sub_start[g], sub_start[g + 1]):
                k = sub_const[j]
                if k >= best:
                    break  # sorted: no later subset can do better
                if sub_mask[j] & ~reach:
                    continue
                d = _set_distance(sub_centre[j, 0] - q0, sub_centre[j, 1] - q1,
                                  sub_centre[j, 2] - q2, hb, rr)
                if d <= 0.0:
                    best = k
                    break
                val = k + sub_weight[j] * d * d
                if val < best:
                    best = val
            lb += best
            if lb > threshold:
                break  # pruned already: the partial sum is a lower bound too
        if lb <= threshold and chord * rmax + rt <= couple_rho:
            lb = max(lb, _coupled_bound(R, u0, u1, u2, ang, boxes[b, 7], src, dst, a, wc, tau))
        lower[b] = lb
        if lb > threshold:
            upper[b] = np.inf  # pruned: its centre cannot beat the best (cost >= lb)
            continue
        ub = 0.0
        for i in range(K):
            s0, s1, s2 = src[i, 0], src[i, 1], src[i, 2]
            r0 = R[0, 0] * s0 + R[0, 1] * s1 + R[0, 2] * s2 + u0 - dst[i, 0]
            r1 = R[1, 0] * s0 + R[1, 1] * s1 + R[1, 2] * s2 + u1 - dst[i, 1]
            r2 = R[2, 0] * s0 + R[2, 1] * s1 + R[2, 2] * s2 + u2 - dst[i, 2]
            val = a[i] * (r0 * r0 + r1 * r1 + r2 * r2)
            ub += val if val < wc[i] else wc[i]
        upper[b] = ub
