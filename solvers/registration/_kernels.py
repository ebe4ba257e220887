"""Numba kernels for the hot loops of GNC and pruning (consistency graph, greedy clique, voting).

Kept free of Python objects so each call costs microseconds; compiled once and cached. Callers
pass C-contiguous, writable float64 arrays (:func:`as_kernel_array`): numba compiles a separate
specialisation for read-only arrays, which would double the first run's compile time. Sorting
is done by the callers in numpy (numba would compile its own mergesort).

Array-to-array slice assignments are written as loops: for those numba compiles a
shape-mismatch error path that formats strings, seconds of a first run's compilation.
"""

from __future__ import annotations

import numpy as np
from numba import njit
from numba import types as nt

from solvers._linalg_kernels import procrustes, sym_eig
from solvers.jit import kernel

# Argument types of the declared signatures: C-contiguous, writable arrays.
F1, F2 = nt.float64[::1], nt.float64[:, ::1]
I1, I2 = nt.int64[::1], nt.int64[:, ::1]
U2 = nt.uint8[:, ::1]
f8, i8 = nt.float64, nt.int64


def as_kernel_array(value, dtype=np.float64):
    """``value`` as a C-contiguous, writable array of ``dtype`` (copied only when needed)."""
    if type(value) is np.ndarray and value.dtype == dtype:
        f = value.flags
        if f.c_contiguous and f.writeable:
            return value
        return value.copy(order="C")  # cheaper than np.require on small arrays
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


@kernel(F2, F2, F1, F1, f8, i8, f8, f8)
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


@njit(cache=True)
def _consistent(at, bt, beta, i, j, cbar, rel_slack, abs_slack):  # pragma: no cover - compiled
    """``| ||a_j - a_i|| - ||b_j - b_i|| | <= cbar (beta_i + beta_j) (1 + rel_slack)
    + abs_slack (||a_j - a_i|| + ||b_j - b_i||)``: the one pairwise-consistency test."""
    x0 = at[0, j] - at[0, i]
    x1 = at[1, j] - at[1, i]
    x2 = at[2, j] - at[2, i]
    y0 = bt[0, j] - bt[0, i]
    y1 = bt[1, j] - bt[1, i]
    y2 = bt[2, j] - bt[2, i]
    la = np.sqrt(x0 * x0 + x1 * x1 + x2 * x2)
    lb = np.sqrt(y0 * y0 + y1 * y1 + y2 * y2)
    return abs(la - lb) <= cbar * (beta[i] + beta[j]) * (1.0 + rel_slack) + abs_slack * (la + lb)


@kernel(F2, F2, F1, f8, f8, f8)
def consistency_matrix(at, bt, beta, cbar, rel_slack, abs_slack):  # pragma: no cover - compiled
    """Dense symmetric adjacency (uint8) of the pairwise-consistency graph (:func:`_consistent`);
    ``at``/``bt`` are the points transposed, (3, N) contiguous. The diagonal is 0."""
    n = at.shape[1]
    adj = np.empty((n, n), dtype=np.uint8)
    for i in range(n):
        row = adj[i]
        # Whole rows (each pair tested twice, symmetric by construction): the loop vectorises.
        for j in range(n):
            row[j] = _consistent(at, bt, beta, i, j, cbar, rel_slack, abs_slack)
        row[i] = 0
    return adj


@kernel(F2, F2, F1, f8, f8, f8)
def consistency_edge_list(at, bt, beta, cbar, rel_slack, abs_slack):  # pragma: no cover
    """Edges ``(i, j)``, ``i < j``, (E, 2) int64, of the graph of :func:`consistency_matrix`,
    without its N^2 bytes (two passes: count, then fill)."""
    n = at.shape[1]
    count = 0
    for i in range(n):
        for j in range(i + 1, n):
            if _consistent(at, bt, beta, i, j, cbar, rel_slack, abs_slack):
                count += 1
    out = np.empty((count, 2), dtype=np.int64)
    k = 0
    for i in range(n):
        for j in range(i + 1, n):
            if _consistent(at, bt, beta, i, j, cbar, rel_slack, abs_slack):
                out[k, 0] = i
                out[k, 1] = j
                k += 1
    return out


@kernel(U2, I1, I1, i8)
def multistart_greedy_clique(adj, deg, order, max_starts):  # pragma: no cover - compiled
    """Best of the greedy cliques grown inside each vertex's neighbourhood (by degree order).

    ``order`` lists the vertices by decreasing degree; at most ``max_starts`` of them start a
    clique. A cheap, strong lower bound on the maximum clique: O(starts * d * c) for degree d
    and clique size c.
    """
    n = adj.shape[0]
    best = np.empty(n, dtype=np.int64)
    best_size = 0
    in_best = np.zeros(n, dtype=np.bool_)
    members = np.empty(n, dtype=np.int64)
    starts = 0
    for v in order:
        if deg[v] + 1 <= best_size or starts >= max_starts:
            break  # later starts have lower degree: none can beat the best clique
        if in_best[v]:
            continue  # its neighbourhood was just explored from inside the best clique
        starts += 1
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
        if m > best_size:
            best_size = m
            for k in range(n):
                in_best[k] = False
            for k in range(m):
                best[k] = members[k]
                in_best[members[k]] = True
    return best[:best_size].copy()


@kernel(F2, F1, F1, f8, I2, I2)
def scalar_tls_rows(vals, beta, w, cbar2, order_lo, order_hi):  # pragma: no cover - compiled
    """:func:`scalar_tls` of each row of ``vals`` (d, N); returns ``(x (d,), found (d,))``: one
    call for the three axes of a translation vote.

    ``order_lo[r]`` sorts the lower ends ``vals[r] - beta cbar`` and ``order_hi[r]`` the upper
    ends ``vals[r] + beta cbar`` (both ``argsort(vals[r])`` when ``beta`` is uniform); the two
    sorted lists are merged here (sorting N values twice, or once, costs less than 2N).
    """
    d, n = vals.shape
    cbar = np.sqrt(cbar2)
    x = np.empty(d)
    found = np.zeros(d, dtype=np.bool_)
    ids = np.empty(2 * n, dtype=np.int64)
    ends = np.empty(2 * n)
    for r in range(d):
        v = vals[r]
        lo = order_lo[r]
        hi = order_hi[r]
        i = 0
        j = 0
        for m in range(2 * n):
            if j >= n:
                take_lo = True
            elif i >= n:
                take_lo = False
            else:
                take_lo = v[lo[i]] - beta[lo[i]] * cbar <= v[hi[j]] + beta[hi[j]] * cbar
            if take_lo:
                k = lo[i]
                ids[m] = k
                ends[m] = v[k] - beta[k] * cbar
                i += 1
            else:
                k = hi[j]
                ids[m] = k + n
                ends[m] = v[k] + beta[k] * cbar
                j += 1
        x[r], _, found[r] = _sweep(v, beta, w, cbar2, ids, ends)
    return x, found


@kernel(F1, F1, F1, f8, F1, I1)
def scalar_tls(v, beta, w, cbar2, ends, order):  # pragma: no cover - compiled
    """Exact scalar TLS by sweeping sorted interval endpoints; returns (x, cost, found).

    ``ends`` (2N,) holds ``v - beta cbar`` then ``v + beta cbar``; ``order`` sorts it (ties in
    any order: the cost is continuous at every endpoint, so either side of a tie is exact).
    ``found`` is False when no piece beats "all outliers" (then any x is optimal).
    """
    m = order.shape[0]
    sorted_ends = np.empty(m)
    for i in range(m):
        sorted_ends[i] = ends[order[i]]
    return _sweep(v, beta, w, cbar2, order, sorted_ends)


@njit(cache=True)
def _sweep(v, beta, w, cbar2, ids, ends):  # pragma: no cover - compiled
    """The sweep of :func:`scalar_tls` over the endpoints in sorted order: ``ends`` (2N,) their
    values, ``ids`` which they are (``k``: the lower end of ``v[k]``, ``k + N``: its upper end)."""
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
        e = ids[m]
        k = e if e < n else e - n
        sign = 1.0 if e < n else -1.0
        p = w[k] / (beta[k] * beta[k])
        s0 += sign * p
        s1 += sign * p * v[k]
        s2 += sign * p * v[k] * v[k]
        aw += sign * w[k]
        lo = ends[m]
        hi = ends[m + 1]
        if s0 <= 1e-300 or hi < lo:
            continue
        x = min(max(s1 / s0, lo), hi)
        cost = s0 * x * x - 2.0 * s1 * x + s2 + (total_w - aw) * cbar2
        if cost < best_cost:
            best_cost = cost
            best_x = x
            found = True
    return best_x, best_cost, found



@njit(cache=True)
def _colour_sort(adj, cand, m, out_v, out_c, rest, klass):  # pragma: no cover - compiled
    """Greedy colouring of ``cand[:m]``, one colour class at a time; writes the vertices sorted
    by colour to ``out_v[:m]`` and their colours (1-based, non-decreasing) to ``out_c[:m]``.

    The colour of the ``k``-th output vertex bounds the largest clique among ``out_v[:k+1]``
    (Tomita's MCQ). ``rest`` and ``klass`` (>= m) are scratch.
    """
    left = m
    for i in range(m):
        rest[i] = cand[i]
    pos = 0
    colour = 0
    while left > 0:
        colour += 1
        size = 0
        kept = 0
        for i in range(left):
            v = rest[i]
            clash = False
            for q in range(size):
                if adj[v, klass[q]] != 0:
                    clash = True
                    break
            if clash:
                rest[kept] = v
                kept += 1
            else:
                klass[size] = v
                size += 1
                out_v[pos] = v
                out_c[pos] = colour
                pos += 1
        left = kept
    return colour


@kernel(U2, I1, i8, i8, i8, i8)
def max_clique_bnb(adj, order, lower, target, limit, max_work):  # pragma: no cover - compiled
    """Branch and bound for maximum cliques with greedy-colouring bounds (Tomita's MCQ).

    ``order`` lists the vertices (by decreasing degree). With ``target <= 0`` it looks for one
    clique larger than ``lower`` (a known clique's size): branches whose colour bound cannot
    beat the best size are cut. With ``target > 0`` it lists up to ``limit`` cliques of exactly
    ``target`` vertices (``target`` the proven maximum: branches that cannot reach it are cut).

    Returns ``(cliques (limit, size) int64, count, size, complete, nodes)``: ``count`` rows of
    ``cliques[:, :size]`` are the cliques found (``count = 0`` when nothing beat ``lower``);
    ``complete`` is False when ``max_work`` ran out (or, listing ties, ``limit`` was reached).
    Work is counted in adjacency look-ups (candidates scanned plus candidates times colours
    in each colouring), so the budget bounds time on large dense cores as on small ones.
    """
    n = adj.shape[0]
    out = np.empty((max(limit, 1), n), dtype=np.int64)
    rest = np.empty(n, dtype=np.int64)
    klass = np.empty(n, dtype=np.int64)
    # Candidate lists of all open levels, stacked in one buffer (grown on demand): level d
    # holds buf_v/buf_c[start[d]:start[d] + ptr[d]], each level a subset of the one below.
    cap = 4 * n + 16
    buf_v = np.empty(cap, dtype=np.int64)
    buf_c = np.empty(cap, dtype=np.int64)
    start = np.zeros(n + 2, dtype=np.int64)
    ptr = np.zeros(n + 2, dtype=np.int64)
    clique = np.empty(n + 1, dtype=np.int64)
    tmp = np.empty(n, dtype=np.int64)
    if n == 0:
        return out[:, :0], 0, 0, True, 0
    _colour_sort(adj, order, n, buf_v, buf_c, rest, klass)
    ptr[0] = n
    ties = target > 0
    best = target if ties else lower
    count = 0
    nodes = 0
    work = 0
    depth = 0
    complete = True
    while depth >= 0:
        i = ptr[depth] - 1
        s0 = start[depth]
        # Colours are non-decreasing along a level: once the bound fails here, it fails for
        # every vertex left at this level.
        if i < 0:
            depth -= 1
            continue
        bound = depth + buf_c[s0 + i]
        if bound < best or (bound == best and not ties):
            depth -= 1
            continue
        ptr[depth] = i
        v = buf_v[s0 + i]
        clique[depth] = v
        nodes += 1
        work += i
        if work > max_work:
            complete = False
            break
        m = 0
        for q in range(i):
            u = buf_v[s0 + q]
            if adj[v, u] != 0:
                tmp[m] = u
                m += 1
        if m == 0:
            size = depth + 1
            if ties:
                if size == target:
                    for q in range(size):
                        out[count, q] = clique[q]
                    count += 1
                    if count >= limit:
                        complete = False
                        break
            elif size > best:
                best = size
                for q in range(size):
                    out[0, q] = clique[q]
                count = 1
            continue
        s1 = s0 + i  # level depth + 1 starts after the live part of this level
        if s1 + m > cap:
            cap = 2 * (s1 + m)
            nv = np.empty(cap, dtype=np.int64)
            nc = np.empty(cap, dtype=np.int64)
            for q in range(s1):
                nv[q] = buf_v[q]
                nc[q] = buf_c[q]
            buf_v, buf_c = nv, nc
        work += m * _colour_sort(adj, tmp, m, buf_v[s1:], buf_c[s1:], rest, klass)
        depth += 1
        start[depth] = s1
        ptr[depth] = m
    size = target if ties else (best if count > 0 else 0)
    return out[:, :size], count, size, complete, nodes


@kernel(F2, F1)
def weighted_spread(points, weights):  # pragma: no cover - compiled
    """``(count, scale, ev)`` of the points of positive weight: their number, the largest
    absolute coordinate, and the square roots of the eigenvalues (descending, (3,)) of their
    weighted covariance, computed on the points divided by ``scale`` (any finite scale)."""
    n = points.shape[0]
    count = 0
    wmax = 0.0
    scale = 0.0
    for k in range(n):
        if weights[k] > 0.0:
            count += 1
            wmax = max(wmax, weights[k])
            for i in range(3):
                scale = max(scale, abs(points[k, i]))
    ev = np.zeros(3)
    if count == 0 or not scale > 0.0:
        return count, scale, ev
    wsum = 0.0
    mean = np.zeros(3)
    for k in range(n):
        if weights[k] > 0.0:
            wk = weights[k] / wmax
            wsum += wk
            for i in range(3):
                mean[i] += wk * points[k, i] / scale
    mean /= wsum
    cov = np.zeros((3, 3))
    for k in range(n):
        if weights[k] > 0.0:
            wk = weights[k] / wmax
            for i in range(3):
                di = points[k, i] / scale - mean[i]
                for j in range(3):
                    cov[i, j] += wk * di * (points[k, j] / scale - mean[j])
    cov /= wsum
    V = np.empty((3, 3))
    sym_eig(cov, V)  # the Jacobi of the Procrustes kernel: compiled once, no LAPACK
    # Sorted descending by swaps (no sum-based middle: it would cancel).
    l0, l1, l2 = cov[0, 0], cov[1, 1], cov[2, 2]
    if l0 < l1:
        l0, l1 = l1, l0
    if l1 < l2:
        l1, l2 = l2, l1
    if l0 < l1:
        l0, l1 = l1, l0
    ev[0] = scale * np.sqrt(max(l0, 0.0))
    ev[1] = scale * np.sqrt(max(l1, 0.0))
    ev[2] = scale * np.sqrt(max(l2, 0.0))
    return count, scale, ev


@kernel(U2)
def row_degrees(adj):  # pragma: no cover - compiled
    """Row sums of a 0/1 uint8 matrix as int64 (numpy's widening sum costs more at small N)."""
    n = adj.shape[0]
    deg = np.zeros(n, dtype=np.int64)
    for i in range(n):
        s = 0
        for j in range(adj.shape[1]):
            s += adj[i, j]
        deg[i] = s
    return deg


@kernel(U2, I1, i8)
def k_core(adj, deg, k):  # pragma: no cover - compiled
    """Vertices of the ``k``-core: drop every vertex of degree < ``k`` until none is left."""
    n = adj.shape[0]
    d = deg.copy()
    alive = np.ones(n, dtype=np.bool_)
    queued = np.zeros(n, dtype=np.bool_)
    stack = np.empty(n, dtype=np.int64)
    top = 0
    for v in range(n):
        if d[v] < k:
            stack[top] = v
            top += 1
            queued[v] = True
    while top > 0:
        top -= 1
        v = stack[top]
        alive[v] = False
        for u in range(n):
            if adj[v, u] != 0 and alive[u]:
                d[u] -= 1
                if d[u] < k and not queued[u]:
                    queued[u] = True
                    stack[top] = u
                    top += 1
    m = 0
    for v in range(n):
        if alive[v]:
            stack[m] = v  # the stack is empty now: reused for the survivors
            m += 1
    return stack[:m].copy()
