"""Numba kernel of the rotation dual search: the closed-form affine projection.

Compiled once and cached on disk.
"""

from __future__ import annotations

import numpy as np
from numba import njit


@njit(cache=True)
def identity_frame_projection(M, S0, th, c):  # pragma: no cover - compiled
    """Projection of ``M`` onto the rotation dual's affine set (identity frame), see
    :class:`solvers.certify.sdp_dual._IdentityFrameProjector`; ``c = 4 / (K + 3)``."""
    nb = th.size
    out = S0.copy()
    V = np.zeros((nb, nb, 3))
    u = np.zeros((nb, 3))
    for i in range(nb):
        for j in range(nb):
            oi, oj = 4 * i, 4 * j
            if i != j:
                for a in range(3):
                    for b in range(3):
                        out[oi + a, oj + b] += 0.5 * ((M[oi + a, oj + b] - S0[oi + a, oj + b])
                                                      - (M[oi + b, oj + a] - S0[oi + b, oj + a]))
                    V[i, j, a] = 0.5 * ((M[oi + a, oj + 3] - S0[oi + a, oj + 3])
                                        - (M[oi + 3, oj + a] - S0[oi + 3, oj + a]))
            else:
                for a in range(3):
                    u[i, a] = 0.5 * ((M[oi + a, oi + 3] - S0[oi + a, oi + 3])
                                     + (M[oi + 3, oi + a] - S0[oi + 3, oi + a]))
    rho = u.copy()
    for i in range(nb):
        for j in range(nb):
            t = th[i] * th[j]
            for a in range(3):
                rho[i, a] += t * V[i, j, a]
    tot = np.zeros(3)
    for i in range(nb):
        for a in range(3):
            tot[a] += rho[i, a]
    lam = np.empty((nb, 3))
    for i in range(nb):
        for a in range(3):
            lam[i, a] = c * (rho[i, a] + 0.5 * tot[a])
    E = np.zeros((nb, 3, 3))
    Em = np.zeros((3, 3))
    for i in range(nb):
        oi = 4 * i
        for a in range(3):
            for b in range(3):
                e = 0.5 * ((M[oi + a, oi + b] - S0[oi + a, oi + b])
                           + (M[oi + b, oi + a] - S0[oi + b, oi + a]))
                E[i, a, b] = e
                Em[a, b] += e / nb
    for i in range(nb):
        oi = 4 * i
        for j in range(nb):
            oj = 4 * j
            if i != j:
                t = 0.25 * th[i] * th[j]
                for a in range(3):
                    v = V[i, j, a] - t * (lam[i, a] - lam[j, a])
                    out[oi + a, oj + 3] += v
                    out[oi + 3, oj + a] -= v
            else:
                for a in range(3):
                    for b in range(3):
                        out[oi + a, oi + b] += E[i, a, b] - Em[a, b]
                    ua = u[i, a] - 0.5 * lam[i, a]
                    out[oi + a, oi + 3] += ua
                    out[oi + 3, oi + a] += ua
    return out
