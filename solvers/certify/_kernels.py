"""Numba kernel of the rotation dual search: the closed-form affine projection.

Compiled once and cached on disk.

Array-to-array slice assignments are written as loops: for those numba compiles a
shape-mismatch error path that formats strings, seconds of a first run's compilation.
"""

from __future__ import annotations

import numpy as np
from numba import njit
from numba import types as nt

from solvers.jit import kernel

# Argument types of the declared signatures: C-contiguous, writable arrays.
F1, F2, U2 = nt.float64[::1], nt.float64[:, ::1], nt.uint8[:, ::1]
I1 = nt.int64[::1]
f8, i8 = nt.float64, nt.int64


@kernel(F2, F2, F1, f8)
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


@njit(cache=True)
def _horn_lambda_max(H, upper):  # pragma: no cover - compiled
    """An upper bound on ``max_{R in SO(3)} tr(R H)`` (tight to about 1e-12 relative).

    The maximum is the largest eigenvalue of Horn's 4 x 4 matrix ``N(H)``. Its characteristic
    polynomial ``x^4 + c2 x^2 + c1 x + c0`` is convex beyond the largest root, so Newton's
    method started above it (at ``upper``, e.g. ``(G_a + G_b) / 2``) decreases monotonically to
    it: every iterate is an upper bound (Theobald's QCP), at a fraction of an SVD's cost. A
    Near double roots (rank-one ``H``) rounding limits Newton's accuracy, so the result is
    verified: ``x I - N`` must pass a Cholesky test, else ``x`` is raised.
    """
    hm = max(np.abs(H).max(), 1e-300)
    Hn = H / hm  # the quartic's powers would under/overflow at extreme scales
    # tr(R H) <= ||H||_* <= 3 sqrt(3) max|H_ij|: a start that cannot overflow.
    un = min(upper / hm, 5.2)
    sxx, sxy, sxz = Hn[0, 0], Hn[0, 1], Hn[0, 2]
    syx, syy, syz = Hn[1, 0], Hn[1, 1], Hn[1, 2]
    szx, szy, szz = Hn[2, 0], Hn[2, 1], Hn[2, 2]
    N = np.empty((4, 4))
    N[0, 0] = sxx + syy + szz
    N[0, 1] = syz - szy
    N[0, 2] = szx - sxz
    N[0, 3] = sxy - syx
    N[1, 1] = sxx - syy - szz
    N[1, 2] = sxy + syx
    N[1, 3] = szx + sxz
    N[2, 2] = -sxx + syy - szz
    N[2, 3] = syz + szy
    N[3, 3] = -sxx - syy + szz
    for i in range(4):
        for j in range(i):
            N[i, j] = N[j, i]
    c2 = -2.0 * (Hn * Hn).sum()
    c1 = -8.0 * (sxx * (syy * szz - syz * szy) - sxy * (syx * szz - syz * szx)
                 + sxz * (syx * szy - syy * szx))
    # det(N) by cofactors along the first row.
    c0 = 0.0
    for j in range(4):
        m = np.empty((3, 3))
        for r in range(3):
            cc = 0
            for c in range(4):
                if c != j:
                    m[r, cc] = N[r + 1, c]
                    cc += 1
        minor = (m[0, 0] * (m[1, 1] * m[2, 2] - m[1, 2] * m[2, 1])
                 - m[0, 1] * (m[1, 0] * m[2, 2] - m[1, 2] * m[2, 0])
                 + m[0, 2] * (m[1, 0] * m[2, 1] - m[1, 1] * m[2, 0]))
        c0 += (-1.0) ** j * N[0, j] * minor
    x = un
    iters = 0
    for _ in range(60):
        iters += 1
        x2 = x * x
        p = x2 * x2 + c2 * x2 + c1 * x + c0
        dp = 4.0 * x2 * x + 2.0 * c2 * x + c1
        if dp <= 0.0:
            break  # not above the largest root any more (rounding): keep the last upper bound
        step = p / dp
        if step <= 1e-13 * abs(x):
            break
        x -= step
    # Near a double root (clustered singular values) rounding limits the root's accuracy:
    # the result is verified (x I - N positive definite by Cholesky) and raised until it is.
    margin = 1e-9 * un
    for _ in range(12):
        xt = min(x + margin, un)
        if xt >= un or _pd_shift(N, xt):
            break
        margin *= 10.0
    else:
        return un * hm
    if iters > 20:
        # Newton converges linearly to a multiple root and the quartic's rounding leaves it up
        # to ~1e-5 relative above (H = -19 I: a triple root); descend while the shift stays
        # positive definite, which keeps every value an upper bound.
        step = 1e-4 * max(abs(xt), 1e-300)
        for _ in range(80):
            if step <= 1e-14 * max(abs(xt), 1e-300):
                break
            if _pd_shift(N, xt - step):
                xt -= step
                step *= 2.0
            else:
                step *= 0.5
    return xt * hm


@njit(cache=True)
def _pd_shift(N, x):  # pragma: no cover - compiled
    """Whether ``x I - N`` (4 x 4) is positive definite, by Cholesky with a rounding margin."""
    A = -N.copy()
    for i in range(4):
        A[i, i] += x
    tiny = 64.0 * 2.220446049250313e-16 * (abs(x) + np.abs(N).max())
    for j in range(4):
        d = A[j, j]
        for k in range(j):
            d -= A[j, k] * A[j, k]
        if not d > tiny:
            return False
        d = np.sqrt(d)
        A[j, j] = d
        for i in range(j + 1, 4):
            v = A[i, j]
            for k in range(j):
                v -= A[i, k] * A[j, k]
            A[i, j] = v / d
    return True


@njit(cache=True)
def _centred(s):  # pragma: no cover - compiled
    """Centroids, centred cross-covariance and spreads from running sums ``s`` (``sw > 0``)."""
    sw = s[0]
    ca = s[1:4] / sw
    cb = s[4:7] / sw
    H = np.empty((3, 3))
    for i in range(3):
        for j in range(3):
            H[i, j] = s[7 + 3 * i + j] - sw * ca[i] * cb[j]
    return ca, cb, H, s[16] - sw * (ca @ ca), s[17] - sw * (cb @ cb)


@njit(cache=True)
def _ls_bound(s):  # pragma: no cover - compiled
    """A lower bound (tight to rounding) on the least-squares optimum from running sums ``s``."""
    if s[0] <= 0.0:
        return 0.0
    _, _, H, ga, gb = _centred(s)
    lam = _horn_lambda_max(H, 0.5 * (abs(ga) + abs(gb)) * (1.0 + 1e-9) + 1e-300)
    return max(ga + gb - 2.0 * lam, 0.0)


@njit(cache=True)
def _ls_value(s):  # pragma: no cover - compiled
    """Least-squares optimum and pose (centred frame) from running sums ``s``, by SVD."""
    if s[0] <= 0.0:
        return 0.0, np.eye(3), np.zeros(3)
    ca, cb, H, ga, gb = _centred(s)
    U, sv, Vt = np.linalg.svd(H)
    d = 1.0 if np.linalg.det(U @ Vt) > 0 else -1.0
    D = np.eye(3)
    D[2, 2] = d
    R = Vt.T @ D @ U.T
    return max(ga + gb - 2.0 * (sv[0] + sv[1] + d * sv[2]), 0.0), R, cb - R @ ca


@kernel(F2, F2, F1, F1, f8, i8, i8, F2, F1, I1, I1, F1)
def clique_bnb(a, b, v, wout, allowance, stop_nodes, max_nodes, state, out, phase, ints,
               best):  # pragma: no cover - compiled
    """Depth-first branch and bound of ``min_S [LS_S^* + sum_{k not in S} wout_k]``, resumable.

    ``a``, ``b`` (K, 3) centred points in branching order, ``v`` (K,) least-squares weights
    ``w / beta^2``, ``wout`` (K,) outlier costs ``cbar2 w``. A node's state is the running sums
    of its forced-in set ``[sw, sum v a (3), sum v b (3), sum v a b^T (9), sum v|a|^2,
    sum v|b|^2]`` and its forced-out cost; its bound is ``LS_I^* + out`` (Horn's eigenvalue by
    QCP Newton from above, :func:`_horn_lambda_max`).

    The search's whole state lives in the arrays the caller passes (and keeps between calls):
    ``state`` (K + 1, 18), ``out`` (K + 1,), ``phase`` (K + 1,), ``ints = [depth, nodes,
    found]`` and ``best = [value, R (9, row-major), t (3)]`` (the best leaf value, initially the
    known upper bound, and its least-squares pose in the centred frame). A fresh search starts
    from zeros with ``ints = [0, 0, 0]``. The call returns 0 when the search is complete, 1 when
    ``stop_nodes`` nodes have been visited (call again to go on: the caller can look at signals
    in between), 2 when ``max_nodes`` is exceeded (the search is not complete).
    """
    K = a.shape[0]
    depth, nodes = ints[0], ints[1]
    while depth >= 0:
        if phase[depth] == 0:
            if nodes >= stop_nodes and nodes < max_nodes:
                ints[0], ints[1] = depth, nodes
                return 1
            nodes += 1
            if nodes > max_nodes:
                ints[0], ints[1] = depth, nodes
                return 2
            bound = _ls_bound(state[depth])
            if not bound >= 0.0:  # NaN: least squares is non-negative, nothing more is known
                bound = 0.0
            bound += out[depth]
            if bound - allowance >= best[0]:
                depth -= 1
                continue
            if depth == K:
                val, R, tp = _ls_value(state[depth])
                val += out[depth]
                if val < best[0]:
                    best[0] = val
                    for i in range(3):
                        for j in range(3):
                            best[1 + 3 * i + j] = R[i, j]
                        best[10 + i] = tp[i]
                    ints[2] = 1
                depth -= 1
                continue
            phase[depth] = 1
        if phase[depth] == 1:
            phase[depth] = 2
            k = depth
            s = state[depth + 1]
            for q in range(s.shape[0]):
                s[q] = state[depth, q]
            vk = v[k]
            s[0] += vk
            for i in range(3):
                s[1 + i] += vk * a[k, i]
                s[4 + i] += vk * b[k, i]
                for j in range(3):
                    s[7 + 3 * i + j] += vk * a[k, i] * b[k, j]
                s[16] += vk * a[k, i] * a[k, i]
                s[17] += vk * b[k, i] * b[k, i]
            out[depth + 1] = out[depth]
            phase[depth + 1] = 0
            depth += 1
            continue
        if phase[depth] == 2:
            phase[depth] = 3
            for q in range(state.shape[1]):
                state[depth + 1, q] = state[depth, q]
            out[depth + 1] = out[depth] + wout[depth]
            phase[depth + 1] = 0
            depth += 1
            continue
        phase[depth] = 0
        depth -= 1
    ints[0], ints[1] = depth, nodes
    return 0


@njit(cache=True)
def _grow(buf, need):  # pragma: no cover - compiled
    if need <= buf.shape[0]:
        return buf
    out = np.empty(max(need, 2 * buf.shape[0]), dtype=buf.dtype)
    for q in range(buf.shape[0]):
        out[q] = buf[q]
    return out


@kernel(U2, F1, i8, f8, i8, i8)
def heavy_maximal_cliques(adj, w, s_min, thr, limit, max_nodes):  # pragma: no cover - compiled
    """The maximal cliques of ``adj`` with at least ``s_min`` vertices and weight ``> thr``.

    Bron-Kerbosch with Tomita's pivot (a vertex of ``P u X`` with the most neighbours in
    ``P``), iterative, cutting every branch whose clique plus candidates has fewer than
    ``s_min`` vertices or weight ``<= thr`` (no clique below it qualifies). Unlike a library
    listing, it stops: after ``max_nodes`` branches or at ``limit + 1`` cliques.

    Returns ``(flat, offsets, count, complete, nodes)``: clique ``k`` is
    ``flat[offsets[k]:offsets[k + 1]]``; ``complete`` is False when either limit stopped it.
    """
    n = adj.shape[0]
    flat = np.empty(16 * n + 16, dtype=np.int64)
    offsets = np.zeros(min(limit, 1024) + 2, dtype=np.int64)
    count = 0
    nodes = 0
    # Per level d: P at bufP[sp[d]:sp[d] + nP[d]], X at bufX[sx[d]:sx[d] + nX[d]] (room for
    # every P vertex to move to X), the branch vertices at bufB[sb[d]:sb[d] + nB[d]] (next at
    # bi[d]); the clique R = rr[:d] of weight wr[d].
    cap = 4 * n + 16
    bufP = np.empty(cap, dtype=np.int64)
    bufX = np.empty(2 * cap, dtype=np.int64)
    bufB = np.empty(cap, dtype=np.int64)
    sp = np.zeros(n + 2, dtype=np.int64)
    nP = np.zeros(n + 2, dtype=np.int64)
    sx = np.zeros(n + 2, dtype=np.int64)
    nX = np.zeros(n + 2, dtype=np.int64)
    sb = np.zeros(n + 2, dtype=np.int64)
    nB = np.zeros(n + 2, dtype=np.int64)
    bi = np.zeros(n + 2, dtype=np.int64)
    rr = np.empty(n + 1, dtype=np.int64)
    wr = np.zeros(n + 2)
    tP = np.empty(n, dtype=np.int64)
    tX = np.empty(n, dtype=np.int64)
    complete = True
    total = 0.0
    for v in range(n):
        bufP[v] = v
        total += w[v]
    if n < s_min or total <= thr:
        return flat[:0], offsets[:1], 0, True, 0
    nP[0] = n
    sx[0] = n
    nX[0] = 0
    # Level 0's pivot and branch list.
    depth = 0
    ready = False  # level `depth` needs its pivot and branch list
    while depth >= 0:
        if not ready:
            p0, x0 = sp[depth], sx[depth]
            best_u, best_k = -1, -1
            for q in range(nP[depth] + nX[depth]):
                u = bufP[p0 + q] if q < nP[depth] else bufX[x0 + q - nP[depth]]
                k = 0
                for r in range(nP[depth]):
                    k += adj[u, bufP[p0 + r]]
                if k > best_k:
                    best_k, best_u = k, u
            b0 = sb[depth]
            m = 0
            for r in range(nP[depth]):
                u = bufP[p0 + r]
                if u == best_u or adj[best_u, u] == 0:
                    bufB[b0 + m] = u
                    m += 1
            nB[depth] = m
            bi[depth] = 0
            ready = True
        if bi[depth] >= nB[depth]:
            depth -= 1
            continue
        v = bufB[sb[depth] + bi[depth]]
        bi[depth] += 1
        nodes += 1
        if nodes > max_nodes:
            complete = False
            break
        p0, x0 = sp[depth], sx[depth]
        mp = 0
        wp = 0.0
        for r in range(nP[depth]):
            u = bufP[p0 + r]
            if adj[v, u] != 0:
                tP[mp] = u
                mp += 1
                wp += w[u]
        mx = 0
        for r in range(nX[depth]):
            u = bufX[x0 + r]
            if adj[v, u] != 0:
                tX[mx] = u
                mx += 1
        # v leaves P for X at this level (its branch is explored now).
        for r in range(nP[depth]):
            if bufP[p0 + r] == v:
                bufP[p0 + r] = bufP[p0 + nP[depth] - 1]
                nP[depth] -= 1
                break
        bufX[x0 + nX[depth]] = v
        nX[depth] += 1
        rr[depth] = v
        wv = wr[depth] + w[v]
        size = depth + 1
        if size + mp < s_min or wv + wp <= thr:
            continue  # no clique of this branch qualifies
        if mp == 0:
            if mx == 0 and wv > thr:  # maximal, large and heavy enough
                if count >= limit:
                    complete = False
                    count += 1
                    break
                flat = _grow(flat, offsets[count] + size)
                offsets = _grow(offsets, count + 2)
                for q in range(size):
                    flat[offsets[count] + q] = rr[q]
                offsets[count + 1] = offsets[count] + size
                count += 1
            continue
        # Descend: level depth + 1 stacked after this level's regions.
        d1 = depth + 1
        sp[d1] = sp[depth] + nP[depth] + 1
        sx[d1] = sx[depth] + nX[depth] + nP[depth] + 1
        sb[d1] = sb[depth] + nB[depth]
        bufP = _grow(bufP, sp[d1] + mp)
        bufX = _grow(bufX, sx[d1] + mp + mx)
        bufB = _grow(bufB, sb[d1] + mp)
        for q in range(mp):
            bufP[sp[d1] + q] = tP[q]
        for q in range(mx):
            bufX[sx[d1] + q] = tX[q]
        nP[d1] = mp
        nX[d1] = mx
        wr[d1] = wv
        depth = d1
        ready = False
    return flat[: offsets[min(count, limit)]], offsets[: min(count, limit) + 1], count, complete, nodes


@njit(inline="always")
def _pair_value(ci, wi, ki, cj, wj, kj, d, i, j):  # pragma: no cover - compiled
    """Subsets ``i`` and ``j`` of two groups with their images ``d`` apart: their costs plus
    ``A_i A_j / (A_i + A_j) (||m_i - m_j|| - d)^2`` (:mod:`solvers.certify.groups`), in numpy's
    order of operations (the distance's squares summed left to right)."""
    Ai = wi[i]
    Aj = wj[j]
    mu = Ai * Aj / max(Ai + Aj, 1e-300) if (Ai > 0.0 and Aj > 0.0) else 0.0
    x = ci[i, 0] - cj[j, 0]
    y = ci[i, 1] - cj[j, 1]
    z = ci[i, 2] - cj[j, 2]
    e = np.sqrt(x * x + y * y + z * z) - d
    return (ki[i] + kj[j]) + mu * (e * e)


@kernel(F2, F1, F1, F2, F1, F1, f8, i8, nogil=True)
def pair_minimum(ci, wi, ki, cj, wj, kj, d, few):  # pragma: no cover - compiled
    """Exact minimum over all subset pairs of two groups' :func:`_pair_value` (centres (S, 3),
    weights (S,) and costs (S,) of each group's subsets). The ``few`` cheapest subsets of each
    are paired first; a pair is then skipped when its two costs alone reach the least value so
    far (the distance term is >= 0 and the rounded sum does not fall below its first part), so
    the result is the minimum over every pair."""
    fi = np.argsort(ki)[:few]
    fj = np.argsort(kj)[:few]
    best = np.inf
    for a in fi:
        for b in fj:
            v = _pair_value(ci, wi, ki, cj, wj, kj, d, a, b)
            if v < best:
                best = v
    kbi = ki.min()
    kbj = kj.min()
    for i in range(ki.shape[0]):
        if not ki[i] + kbj < best:
            continue
        for j in range(kj.shape[0]):
            if not (kj[j] + kbi < best and ki[i] + kj[j] < best):
                continue
            v = _pair_value(ci, wi, ki, cj, wj, kj, d, i, j)
            if v < best:
                best = v
    return best
