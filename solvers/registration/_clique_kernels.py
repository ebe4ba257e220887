"""Bitset maximum-clique search for large, dense graphs, compiled on first use.

San Segundo's BBMC (candidate sets and adjacency rows as 64-bit words; greedy colouring one
colour class at a time) with Tomita's re-colouring and San Segundo's infra-chromatic bound,
started from the largest of the cliques grown greedily from the highest-degree vertices, after
a peel to the core that clique allows. Kept apart from
:mod:`solvers.registration._kernels`: it compiles only when a consistency graph's core is large
and not already a clique (dense graphs of real features), never on the small problems of a
first ``certpose`` run. One declared signature (:func:`solvers.jit.kernel`); its helpers are
inlined into it (``inline="always"``: no compilation of their own); array copies are loops
(numba compiles a string-formatting error path for slice assignments).
"""

from __future__ import annotations

import numpy as np
from llvmlite import ir
from numba import njit, types
from numba.extending import intrinsic

from solvers.jit import kernel

U2, I1, i8 = types.uint8[:, ::1], types.int64[::1], types.int64


@intrinsic
def _ctz(typingctx, x):  # pragma: no cover - compiled
    """Index of the lowest set bit of a non-zero uint64 (LLVM ``cttz``)."""

    def codegen(context, builder, signature, args):
        return builder.cttz(args[0], ir.Constant(ir.IntType(1), 1))

    return types.int64(types.uint64), codegen


@intrinsic
def _popcount(typingctx, x):  # pragma: no cover - compiled
    """Number of set bits of a uint64 (LLVM ``ctpop``)."""

    def codegen(context, builder, signature, args):
        return builder.ctpop(args[0])

    return types.int64(types.uint64), codegen


@njit(inline="always")
def _bitset_rows(adj, order):  # pragma: no cover - compiled
    """Adjacency as bitset rows in the numbering of ``order`` (position p is vertex order[p])."""
    n = adj.shape[0]
    nw = (n + 63) >> 6
    bits = np.empty((n, nw), dtype=np.uint64)
    row = np.empty(nw << 6, dtype=np.int64)
    for q in range(n, nw << 6):
        row[q] = 0
    for p in range(n):
        r = order[p]
        for q in range(n):
            row[q] = adj[r, order[q]]
        for w in range(nw):
            x = np.uint64(0)
            for b in range(64):  # branch-free: adjacency bits are unpredictable
                x |= np.uint64(row[(w << 6) + b] != 0) << np.uint64(b)
            bits[p, w] = x
    return bits


GREEDY_STARTS = 256
GREEDY_MAX_WORK = 4_000_000
"""Vertices (the first of the order) that grow a greedy clique: on dense graphs of 1,000
vertices, 256 starts found the maximum clique or one vertex less in 14 of 15 cases."""


@njit(inline="always")
def _greedy_cliques(bits, n, out, starts):  # pragma: no cover - compiled
    """Largest of the cliques grown from every vertex, each step adding the candidate with the
    most neighbours among the candidates; writes it to ``out`` and returns ``(size, work)``.

    A run stops once it cannot beat the best clique: that takes ``k`` more vertices, each with
    ``k - 1`` neighbours among the candidates.
    """
    nw = bits.shape[1]
    cand = np.empty(nw, dtype=np.uint64)
    members = np.empty(n, dtype=np.int64)
    one = np.uint64(1)
    best = 0
    work = 0
    for v in range(starts):
        if work > GREEDY_MAX_WORK:
            break
        deg = 0
        for w in range(nw):
            cand[w] = bits[v, w]
            deg += _popcount(cand[w])
        if deg + 1 <= best:
            continue
        members[0] = v
        size = 1
        while True:
            pick = -1
            top = -1
            need = best - size  # beating `best` takes need + 1 more vertices, each with
            enough = 0  # at least `need` neighbours among the candidates
            for w in range(nw):
                x = cand[w]
                while x != 0:
                    u = (w << 6) + _ctz(x)
                    x &= x - one
                    d = 0
                    for w2 in range(nw):
                        d += _popcount(bits[u, w2] & cand[w2])
                    if d > top:
                        top = d
                        pick = u
                    if d >= need:
                        enough += 1
                    work += nw
            if pick < 0 or enough <= need:
                break
            members[size] = pick
            size += 1
            for w in range(nw):
                cand[w] &= bits[pick, w]
        if pick < 0 and size > best:
            best = size
            for q in range(size):
                out[q] = members[q]
    return best, work


RECOLOUR_TRIES = 3


@njit(inline="always")
def _colour(bits, cand, kmin, lv, lc, s, u, qq, cls, used):  # pragma: no cover - compiled
    """Greedy colouring of the bitset ``cand`` one class at a time, in index order.

    Vertices of colour ``>= kmin`` are appended to ``lv[s:]`` with their colours in ``lc``
    (non-decreasing); the classes below ``kmin`` are kept in ``cls`` so that such a vertex can
    be moved into one of them (re-colouring: no neighbour there, or one neighbour that fits in
    another class) or shown not to need a branch (infra-chromatic: its one neighbour ``w`` in
    class ``a`` and class ``b`` hold no common neighbour, so no clique takes a vertex from each
    of ``{v}``, class ``a`` and class ``b``; classes so used are frozen). Either way the
    vertices left unlisted hold no clique of more than ``kmin - 1``. Returns ``(m, work)``.
    """
    nw = cand.shape[0]
    one = np.uint64(1)
    zero = np.uint64(0)
    left = 0
    for w in range(nw):
        u[w] = cand[w]
        left += _popcount(cand[w])
    m = 0
    k = 0
    work = 0
    while left > 0:
        if k + left < kmin:
            break  # the vertices left get colours below kmin whatever happens
        k += 1
        for w in range(nw):
            qq[w] = u[w]
        if k < kmin:
            for w in range(nw):
                cls[k, w] = zero
            used[k] = 0
        work += nw
        for w in range(nw):
            while qq[w] != zero:
                b = _ctz(qq[w])
                bit = one << np.uint64(b)
                v = (w << 6) + b
                qq[w] &= ~bit
                u[w] &= ~bit
                left -= 1
                for w2 in range(w + 1, nw):
                    qq[w2] &= ~bits[v, w2]
                qq[w] &= ~bits[v, w]
                work += nw - w
                if k < kmin:
                    cls[k, w] |= bit
                    continue
                # Re-colour into a class below kmin, or find an infra-chromatic pair. The
                # classes with one neighbour of v are tried a few times only: each try scans
                # every class, which costs most where cliques (and kmin) are large.
                placed = False
                ia = -1
                ib = -1
                tries = 0
                for k1 in range(1, kmin):
                    if used[k1] != 0:
                        continue
                    hit = -1
                    many = False
                    for w3 in range(nw):
                        x = bits[v, w3] & cls[k1, w3]
                        if x != zero:
                            if hit >= 0 or (x & (x - one)) != zero:
                                many = True
                                work += w3 + 1
                                break
                            hit = (w3 << 6) + _ctz(x)
                    if many:
                        continue
                    work += nw
                    if hit < 0:
                        cls[k1, w] |= bit
                        placed = True
                        break
                    if tries >= RECOLOUR_TRIES:
                        continue
                    tries += 1
                    for k2 in range(1, kmin):
                        if k2 == k1 or used[k2] != 0:
                            continue
                        free = True
                        for w3 in range(nw):
                            if bits[hit, w3] & cls[k2, w3] != zero:
                                free = False
                                work += w3 + 1
                                break
                        if free:
                            work += nw
                            hb = one << np.uint64(hit & 63)
                            cls[k1, hit >> 6] &= ~hb
                            cls[k2, hit >> 6] |= hb
                            cls[k1, w] |= bit
                            placed = True
                            break
                        if ia < 0:
                            common = False
                            for w3 in range(nw):
                                if bits[hit, w3] & bits[v, w3] & cls[k2, w3] != zero:
                                    common = True
                                    work += w3 + 1
                                    break
                            if not common:
                                work += nw
                                ia = k1
                                ib = k2
                    if placed:
                        break
                if placed:
                    continue
                if ia >= 0:
                    used[ia] = 1
                    used[ib] = 1
                    continue
                lv[s + m] = v
                lc[s + m] = k
                m += 1
    return m, work


@kernel(U2, I1, I1, i8, i8)
def max_clique_bitset(adj, order, seed, limit, max_work):  # pragma: no cover - compiled
    """Maximum clique of ``adj`` and up to ``limit`` cliques tied with it, in one search.

    ``order`` is the vertex order of the colourings (by decreasing degree). The search starts
    from the largest greedy clique (:func:`_greedy_cliques`); while fewer than ``limit`` ties
    are known it lists the cliques of the best size (branches whose bound reaches it are
    searched), then it only looks for larger ones. Work is counted in 64-bit word operations;
    when ``max_work`` runs out the best cliques found so far are returned.

    Returns ``(cliques (limit, n) int64, count, size, exact, nodes)``: the first ``count`` rows
    of ``cliques[:, :size]`` are the cliques, in the vertex numbering of ``adj``; ``exact`` is
    False when the budget ran out before the proof.
    """
    n = adj.shape[0]
    out = np.empty((max(limit, 1), max(n, 1)), dtype=np.int64)
    if n == 0:
        return out[:, :0], 0, 0, True, 0, 0
    bits = _bitset_rows(adj, order)
    nw = bits.shape[1]
    one = np.uint64(1)
    zero = np.uint64(0)
    greedy = np.empty(n, dtype=np.int64)
    best, work = _greedy_cliques(bits, n, greedy, min(n, GREEDY_STARTS))
    if seed.shape[0] > best:  # the caller's clique is larger: start from it
        pos = np.empty(n, dtype=np.int64)
        for p in range(n):
            pos[order[p]] = p
        best = seed.shape[0]
        for q in range(best):
            greedy[q] = pos[seed[q]]
    # Peel to the (best - 1)-core: every clique of `best` vertices (ties included) lies in it,
    # and the greedy clique may be larger than the one the caller peeled with.
    deg = np.empty(n, dtype=np.int64)
    stack = np.empty(n, dtype=np.int64)
    alive = np.empty(nw, dtype=np.uint64)
    for w in range(nw):
        alive[w] = zero
    top = 0
    dmax = 0
    for p in range(n):
        d = 0
        for w in range(nw):
            d += _popcount(bits[p, w])
        deg[p] = d
        dmax = max(dmax, d)
        alive[p >> 6] |= one << np.uint64(p & 63)
        if d < best - 1:
            stack[top] = p
            top += 1
            alive[p >> 6] &= ~(one << np.uint64(p & 63))
    work += n * nw
    while top > 0:
        top -= 1
        p = stack[top]
        for w in range(nw):
            x = bits[p, w] & alive[w]
            while x != zero:
                q = (w << 6) + _ctz(x)
                x &= x - one
                deg[q] -= 1
                if deg[q] < best - 1:
                    alive[q >> 6] &= ~(one << np.uint64(q & 63))
                    stack[top] = q
                    top += 1
        work += nw
    maxd = max(dmax, best) + 3  # deeper than any clique; more colour classes than kmin
    cand = np.empty((maxd, nw), dtype=np.uint64)
    u = np.empty(nw, dtype=np.uint64)
    qq = np.empty(nw, dtype=np.uint64)
    cls = np.empty((maxd, nw), dtype=np.uint64)
    used = np.empty(maxd, dtype=np.int64)
    cap = 4 * n + 64
    lv = np.empty(cap, dtype=np.int64)
    lc = np.empty(cap, dtype=np.int64)
    start = np.empty(maxd, dtype=np.int64)
    ptr = np.empty(maxd, dtype=np.int64)
    start[0] = 0
    clique = np.empty(maxd, dtype=np.int64)
    for w in range(nw):
        cand[0, w] = alive[w]
    count = 0  # cliques of size `best` listed (the greedy one is found again by the search)
    nodes = 0
    exact = True
    depth = 0
    colour = True
    while True:
        if colour:
            s = start[depth]
            size = 0
            for w in range(nw):
                size += _popcount(cand[depth, w])
            if s + size > cap:
                ncap = 2 * (s + size)
                nv = np.empty(ncap, dtype=np.int64)
                nc = np.empty(ncap, dtype=np.int64)
                for q in range(s):
                    nv[q] = lv[q]
                    nc[q] = lc[q]
                lv, lc, cap = nv, nc, ncap
            ties = count < limit
            kmin = best - depth if ties else best - depth + 1
            m, wk = _colour(bits, cand[depth], max(kmin, 1), lv, lc, s, u, qq, cls, used)
            work += wk
            ptr[depth] = m
            colour = False
        i = ptr[depth] - 1
        s0 = start[depth]
        ties = count < limit
        if i < 0 or depth + lc[s0 + i] < best or (depth + lc[s0 + i] == best and not ties):
            depth -= 1
            if depth < 0:
                break
            continue
        ptr[depth] = i
        v = lv[s0 + i]
        clique[depth] = v
        nodes += 1
        cand[depth, v >> 6] &= ~(one << np.uint64(v & 63))
        empty = True
        for w in range(nw):
            x = cand[depth, w] & bits[v, w]
            cand[depth + 1, w] = x
            if x != zero:
                empty = False
        work += nw
        if work > max_work:
            exact = False
            break
        if empty:
            size = depth + 1
            if size > best:
                best = size
                count = 0
            if size == best and count < limit:
                for q in range(size):
                    out[count, q] = order[clique[q]]
                count += 1
            continue
        depth += 1
        start[depth] = s0 + i
        colour = True
    if count == 0:  # nothing found beyond the greedy clique (or the budget ran out first)
        for q in range(best):
            out[0, q] = order[greedy[q]]
        count = 1
    return out[:, :best], count, best, exact, nodes, work
