"""A joint convex lower bound of the weighted TLS cost over one cell of poses (numba).

A cell of :func:`solvers.certify._pose_kernels.pose_bnb` holds the rotations
``R = exp([w]x) R_c`` with ``|w| <= theta`` (rotation vectors within ``theta`` of the cube's
centre give rotations within angle ``theta`` of ``R_c``) and the translations ``t_c + dt`` with
``|dt|_inf <= ts``. With ``q_i = R_c a_i`` and ``e_i = q_i + t_c - b_i``, the residual is
``e_i + w x q_i + dt + r_i`` where ``r_i = (exp([w]x) - I - [w]x) q_i``; for ``|w| = theta``
and a unit vector ``x`` perpendicular to ``w``, ``|(exp([w]x) - I - [w]x) x| = |exp(i theta) -
1 - i theta| = |int_0^theta i (exp(i s) - 1) ds| <= theta^2 / 2`` (the component along ``w``
is fixed), so ``|r_i| <= err_i = theta^2 |a_i| / 2``: second order in the cell's size. Each
term's cost ``min(v_i |res|^2, wout_i)`` is nondecreasing in ``|res|``, so it is at least
``phi_i(d_i) = min(v_i (d_i - err_i)_+^2, wout_i)`` with ``d_i(w, dt) = |e_i + w x q_i + dt|``,
a convex function of ``z = (w, dt)``. ``phi_i`` is not convex; its convex envelope on the range
``[lo_i, hi_i]`` of ``d_i`` over the cell is: the quadratic up to the point where its tangent
passes through ``(hi_i, wout_i)``, then that tangent (the chord from ``lo_i`` when the tangent
point is left of ``lo_i``). The envelope is convex and nondecreasing, so ``F(z) = sum_i
env_i(d_i(z))`` is convex and below the cost on the cell; unlike a bound per term, every term
sees the same pose. A few damped Newton steps approach ``F``'s minimum ``z*`` over the ball
times the box, and ``F(z*) + min_z g . (z - z*)`` (``g`` the gradient at ``z*``; closed form
over the ball and the box) is a lower bound whatever ``z*`` is.
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

# Columns of a term's envelope: err (the residual's shift), knot p, value below the knot's
# constant b0, value at the knot, slope beyond it, the quadratic's weight (0: a chord).
_C, _P, _B0, _BASE, _S, _VQ = 0, 1, 2, 3, 4, 5
ENV_COLS = 6
NEWTON_STEPS = 4
"""Damped Newton steps towards the minimum of the convex relaxation."""


@njit(cache=True)
def _envelope(v, w, c, lo, hi, env):  # pragma: no cover - compiled
    """The convex envelope of ``min(v (d - c)_+^2, w)`` on ``[lo, hi]`` into ``env``
    (``ENV_COLS``); returns False when the term costs ``w`` throughout."""
    m = max(lo - c, 0.0)
    phil = v * m * m
    if phil >= w:
        return False
    W = w / v
    H = hi - c
    env[_C] = c
    if H <= math.sqrt(W):  # never an outlier on the range (H < 0 too): the quadratic itself
        env[_P], env[_B0], env[_BASE], env[_S], env[_VQ] = np.inf, 0.0, 0.0, 0.0, v
        return True
    u = H - math.sqrt(H * H - W)  # the tangent from (hi, w) touches at c + u
    if c + u >= lo:
        env[_P], env[_B0], env[_BASE], env[_S], env[_VQ] = c + u, 0.0, v * u * u, 2.0 * v * u, v
    else:  # the chord from (lo, phi(lo)) to (hi, w)
        env[_P], env[_B0], env[_BASE], env[_VQ] = lo, phil, phil, 0.0
        env[_S] = (w - phil) / max(hi - lo, 1e-300)
    return True


@njit(cache=True)
def _term(env, d):  # pragma: no cover - compiled
    """The envelope's value, slope and curvature at ``d``."""
    if d <= env[_P]:
        x = d - env[_C]
        if x <= 0.0:
            return env[_B0], 0.0, 0.0
        vq = env[_VQ]
        return env[_B0] + vq * x * x, 2.0 * vq * x, 2.0 * vq
    return env[_BASE] + env[_S] * (d - env[_P]), env[_S], 0.0


@njit(cache=True)
def _value(E, Q, env, n, z, grad, hess, want):  # pragma: no cover - compiled
    """``F(z)``; with ``want`` 1 its gradient into ``grad``, with 2 also its Hessian.

    With ``y = e + w x q + dt``, ``d = |y|``, ``u = y / d``: ``dF/dw = F' q x u``, ``dF/dt =
    F' u``; the Hessian is ``alpha g g^T + beta J^T J`` with ``g = (q x u, u)``, ``beta = F' /
    d``, ``alpha = F'' - beta`` and ``J^T J = [[|q|^2 I - q q^T, [q]x], [-[q]x, I]]``, whose
    sums over the terms are gathered first.
    """
    f = 0.0
    for x in range(6):
        grad[x] = 0.0
    acc = np.zeros(11)  # sum beta, beta q (3), beta |q|^2, beta q q^T (6: xx yy zz xy xz yz)
    if want >= 2:
        for x in range(6):
            for y in range(6):
                hess[x, y] = 0.0
    w0, w1, w2, t0, t1, t2 = z[0], z[1], z[2], z[3], z[4], z[5]
    for k in range(n):
        q0, q1, q2 = Q[k, 0], Q[k, 1], Q[k, 2]
        y0 = E[k, 0] + w1 * q2 - w2 * q1 + t0
        y1 = E[k, 1] + w2 * q0 - w0 * q2 + t1
        y2 = E[k, 2] + w0 * q1 - w1 * q0 + t2
        d = math.sqrt(y0 * y0 + y1 * y1 + y2 * y2)
        val, slope, curv = _term(env[k], d)
        f += val
        if want == 0 or slope == 0.0:
            continue
        dd = max(d, 1e-300)
        u0, u1, u2 = y0 / dd, y1 / dd, y2 / dd
        g0 = q1 * u2 - q2 * u1
        g1 = q2 * u0 - q0 * u2
        g2 = q0 * u1 - q1 * u0
        grad[0] += slope * g0
        grad[1] += slope * g1
        grad[2] += slope * g2
        grad[3] += slope * u0
        grad[4] += slope * u1
        grad[5] += slope * u2
        if want >= 2:
            beta = slope / dd
            alpha = curv - beta
            gg = (g0, g1, g2, u0, u1, u2)
            for c1 in range(6):
                ac = alpha * gg[c1]
                for c2 in range(c1, 6):
                    hess[c1, c2] += ac * gg[c2]
            acc[0] += beta
            acc[1] += beta * q0
            acc[2] += beta * q1
            acc[3] += beta * q2
            acc[4] += beta * (q0 * q0 + q1 * q1 + q2 * q2)
            acc[5] += beta * q0 * q0
            acc[6] += beta * q1 * q1
            acc[7] += beta * q2 * q2
            acc[8] += beta * q0 * q1
            acc[9] += beta * q0 * q2
            acc[10] += beta * q1 * q2
    if want >= 2:
        # beta J^T J: rotation block |q|^2 I - q q^T, cross block [q]x, translation block I
        hess[0, 0] += acc[4] - acc[5]
        hess[1, 1] += acc[4] - acc[6]
        hess[2, 2] += acc[4] - acc[7]
        hess[0, 1] -= acc[8]
        hess[0, 2] -= acc[9]
        hess[1, 2] -= acc[10]
        hess[0, 4] -= acc[3]
        hess[0, 5] += acc[2]
        hess[1, 3] += acc[3]
        hess[1, 5] -= acc[1]
        hess[2, 3] -= acc[2]
        hess[2, 4] += acc[1]
        for x in range(3, 6):
            hess[x, x] += acc[0]
        for c1 in range(6):
            for c2 in range(c1):
                hess[c1, c2] = hess[c2, c1]
    return f


@njit(cache=True)
def _project(z, theta, ts):  # pragma: no cover - compiled
    nw = math.sqrt(z[0] * z[0] + z[1] * z[1] + z[2] * z[2])
    if nw > theta:
        f = theta / nw
        z[0], z[1], z[2] = z[0] * f, z[1] * f, z[2] * f
    for x in range(3, 6):
        z[x] = min(max(z[x], -ts), ts)


@njit(cache=True)
def _linear_floor(z, g, theta, ts):  # pragma: no cover - compiled
    """``min g . (z' - z)`` over ``|w'| <= theta``, ``|dt'|_inf <= ts``."""
    gw = math.sqrt(g[0] * g[0] + g[1] * g[1] + g[2] * g[2])
    out = -theta * gw - (g[0] * z[0] + g[1] * z[1] + g[2] * z[2])
    for x in range(3, 6):
        out += -ts * abs(g[x]) - g[x] * z[x]
    return out


@njit(cache=True)
def convex_bound(E, Q, env, n, theta, ts, z, useless, enough):  # pragma: no cover - compiled
    """A lower bound of ``sum_k env_k(|E_k + w x Q_k + dt|)`` over ``|w| <= theta``,
    ``|dt|_inf <= ts`` (rows ``:n`` of ``E``, ``Q``, ``env``); ``z`` (6,) holds the
    starting point and receives the last iterate. It stops once the bound reaches ``enough``,
    or once an iterate's value is at most ``useless`` (no bound can exceed it then; ``-inf``
    when the starting point's is)."""
    grad = np.empty(6)
    hess = np.empty((6, 6))
    trial = np.empty(6)
    g2 = np.empty(6)
    _project(z, theta, ts)
    f = _value(E, Q, env, n, z, grad, hess, 0)
    if f <= useless:
        return -np.inf
    f = _value(E, Q, env, n, z, grad, hess, 2)
    best = f + _linear_floor(z, grad, theta, ts)
    for _ in range(NEWTON_STEPS):
        if best >= enough or f <= useless:
            break
        tr = 0.0
        for x in range(6):
            tr += hess[x, x]
        lam = 1e-9 * tr + 1e-300
        for x in range(6):
            hess[x, x] += lam
        try:
            step = np.linalg.solve(hess, -grad)
        except Exception:  # singular: no curvature left to follow
            break
        moved = False
        tstep = 1.0
        for _ls in range(6):
            for x in range(6):
                trial[x] = z[x] + tstep * step[x]
            _project(trial, theta, ts)
            ft = _value(E, Q, env, n, trial, g2, hess, 0)
            if ft < f:
                moved = True
                break
            tstep *= 0.25
        if not moved:
            break
        for x in range(6):
            z[x] = trial[x]
        f = _value(E, Q, env, n, z, grad, hess, 2)
        lb = f + _linear_floor(z, grad, theta, ts)
        if lb > best:
            best = lb
        if f - best <= 1e-9 * (1.0 + abs(f)):
            break
    return best


@njit(cache=True)
def cell_terms(a, b, v, wout, anorm, slack, idx, R, tc0, tc1, tc2, theta, ts, E, Q,
               env):  # pragma: no cover - compiled
    """Fill ``E``, ``Q``, ``env`` for the terms ``idx`` of the cell (rotation ``R`` at its
    centre, angle radius ``theta``; translation centre ``tc``, half-side ``ts``); returns the
    number of rows filled and the outlier cost of the terms costing ``wout`` throughout."""
    rem = 0.5 * theta * theta * (1.0 + 1e-12)
    tr = math.sqrt(3.0) * ts * (1.0 + 1e-12)
    n = 0
    const = 0.0
    for k in range(idx.size):
        i = idx[k]
        q0 = R[0, 0] * a[i, 0] + R[0, 1] * a[i, 1] + R[0, 2] * a[i, 2]
        q1 = R[1, 0] * a[i, 0] + R[1, 1] * a[i, 1] + R[1, 2] * a[i, 2]
        q2 = R[2, 0] * a[i, 0] + R[2, 1] * a[i, 1] + R[2, 2] * a[i, 2]
        e0, e1, e2 = q0 + tc0 - b[i, 0], q1 + tc1 - b[i, 1], q2 + tc2 - b[i, 2]
        en = math.sqrt(e0 * e0 + e1 * e1 + e2 * e2)
        reach = theta * anorm[i] * (1.0 + 1e-12) + tr
        lo = max(en - reach, 0.0)
        hi = en + reach
        c = rem * anorm[i] + slack[i]
        if not _envelope(v[i], wout[i], c, lo, hi, env[n]):
            const += wout[i]
            continue
        E[n, 0], E[n, 1], E[n, 2] = e0, e1, e2
        Q[n, 0], Q[n, 1], Q[n, 2] = q0, q1, q2
        n += 1
    return n, const


@kernel(F2, F2, F1, F1, F1, F1, I1, F2, f8, F1, f8)
def cell_bound(a, b, v, wout, anorm, slack, idx, R, theta, tc, ts):  # pragma: no cover - compiled
    """The convex bound of ``sum_{i in idx} min(v_i |R' a_i + t - b_i|^2, wout_i)`` over the
    rotations ``R'`` within angle ``theta`` (radians) of ``R`` (3, 3) and the translations
    within ``ts`` (per axis) of ``tc`` (3,); ``slack`` (N,) is added to each residual's
    remainder (a rounding allowance); other arrays as :func:`pose_bnb`'s."""
    m = idx.size
    E = np.empty((m, 3))
    Q = np.empty((m, 3))
    env = np.empty((m, ENV_COLS))
    ts = ts * (1.0 + 1e-12)
    n, const = cell_terms(a, b, v, wout, anorm, slack, idx, R, tc[0], tc[1], tc[2], theta, ts,
                          E, Q, env)
    return const + convex_bound(E, Q, env, n, theta, ts, np.zeros(6), -np.inf, np.inf)
