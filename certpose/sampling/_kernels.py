"""Numba kernel of the importance sampler's proposal density; imported lazily by
:mod:`certpose.sampling.sampler` (:meth:`TangentMixture.component_log_densities`).

The same arithmetic as the NumPy path it replaces, draw by draw: the rotation vector of
``R_k^T R`` (:func:`solvers.lie.so3_log`'s formulas: ``arccos`` of the trace with the small-angle
series, Shepperd's quaternion within 0.1 rad of a half turn), its three wraps ``theta + 2 pi m``
(``m = -1, 0, 1``), the whitened chart vector of each, the Student t (or Gaussian) log density
plus the exponential map's log Jacobian ``log(s^2 / (2 (1 - cos s)))``, and their log-sum-exp.
It was a third of a YCB-Video sampling run's time in NumPy (many temporaries per component).
"""

from __future__ import annotations

import math

import numpy as np
from numba import types as nt

from solvers.jit import kernel

F1, F2, F3 = nt.float64[::1], nt.float64[:, ::1], nt.float64[:, :, ::1]


@kernel(F3, F2, F3, F2, F3, F1, F1, nt.float64, F2, nogil=True)
def mixture_log_densities(R, t, Rk, tk, Li, log_norm, log_w, dof, out):  # noqa: ANN001, ANN201
    """``out[k, i] = log(w_k q_k(R_i, t_i))`` for a mixture of chart t (``dof`` finite) or
    Gaussian (``dof`` inf) components with centres ``Rk``, ``tk``, inverse Cholesky factors
    ``Li`` and log normalisers ``log_norm`` (the chart's, without the Jacobian)."""
    n, K = R.shape[0], Rk.shape[0]
    gauss = not math.isfinite(dof)
    two_pi = 2.0 * math.pi
    Q = np.empty((3, 3))
    v = np.empty(3)
    qv = np.empty(3)
    vals = np.empty(3)
    for k in range(K):
        for i in range(n):
            for a in range(3):
                for b in range(3):
                    Q[a, b] = Rk[k, 0, a] * R[i, 0, b] + Rk[k, 1, a] * R[i, 1, b] + Rk[k, 2, a] * R[i, 2, b]
            # so3_log
            cos = (Q[0, 0] + Q[1, 1] + Q[2, 2] - 1.0) / 2.0
            cos = min(1.0, max(-1.0, cos))
            th = math.acos(cos)
            if th > math.pi - 0.1:
                d0, d1, d2 = Q[0, 0], Q[1, 1], Q[2, 2]
                ii = 0
                if d1 > d0 and d1 >= d2:
                    ii = 1
                elif d2 > d0 and d2 > d1:
                    ii = 2
                jj, kk = (ii + 1) % 3, (ii + 2) % 3
                big = math.sqrt(max(1.0 + Q[ii, ii] - Q[jj, jj] - Q[kk, kk], 1e-300)) / 2.0
                qv[ii] = big
                qv[jj] = (Q[jj, ii] + Q[ii, jj]) / (4.0 * big)
                qv[kk] = (Q[kk, ii] + Q[ii, kk]) / (4.0 * big)
                qw = (Q[kk, jj] - Q[jj, kk]) / (4.0 * big)
                if qw < 0:
                    qv[0], qv[1], qv[2], qw = -qv[0], -qv[1], -qv[2], -qw
                vn = math.sqrt(qv[0] * qv[0] + qv[1] * qv[1] + qv[2] * qv[2])
                f = 2.0 * math.atan2(vn, qw) / vn
                v[0], v[1], v[2] = qv[0] * f, qv[1] * f, qv[2] * f
            else:
                if th < 1e-4:
                    f = 0.5 + th * th / 12.0
                else:
                    f = th / (2.0 * math.sin(th))
                v[0] = (Q[2, 1] - Q[1, 2]) * f
                v[1] = (Q[0, 2] - Q[2, 0]) * f
                v[2] = (Q[1, 0] - Q[0, 1]) * f
            theta = math.sqrt(v[0] * v[0] + v[1] * v[1] + v[2] * v[2])
            if theta > 1e-12:
                u0, u1, u2 = v[0] / theta, v[1] / theta, v[2] / theta
            else:
                u0, u1, u2 = 1.0, 0.0, 0.0
            sh = math.sin(theta / 2.0)
            two_one_minus_cos = max(4.0 * sh * sh, 1e-300)
            AA = 0.0
            AB = 0.0
            BB = 0.0
            d0 = t[i, 0] - tk[k, 0]
            d1 = t[i, 1] - tk[k, 1]
            d2 = t[i, 2] - tk[k, 2]
            for r in range(6):
                A = u0 * Li[k, r, 0] + u1 * Li[k, r, 1] + u2 * Li[k, r, 2]
                B = d0 * Li[k, r, 3] + d1 * Li[k, r, 4] + d2 * Li[k, r, 5]
                AA += A * A
                AB += A * B
                BB += B * B
            top = -np.inf
            for m in range(3):
                s = theta + two_pi * (m - 1)
                m2 = s * s * AA + 2.0 * s * AB + BB
                if gauss:
                    lg = log_norm[k] - 0.5 * m2
                else:
                    lg = log_norm[k] - 0.5 * (dof + 6.0) * math.log1p(m2 / dof)
                if s == 0.0:
                    lj = 0.0
                else:
                    lj = math.log(max(s * s, 1e-300)) - math.log(two_one_minus_cos)
                vals[m] = lg + lj
                top = max(top, vals[m])
            acc = 0.0
            for m in range(3):
                acc += math.exp(vals[m] - top)
            out[k, i] = log_w[k] + top + math.log(acc)
