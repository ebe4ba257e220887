"""Numba kernel of the branch and bound over poses (:mod:`solvers.certify.pose_bnb`).

Compiled once and cached on disk.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit
from numba import types as nt

from solvers.certify._convex_cell import ENV_COLS, cell_terms, convex_bound
from solvers.certify._kernels import _ls_bound, clique_bnb
from solvers.jit import kernel

F1, F2 = nt.float64[::1], nt.float64[:, ::1]
U2 = nt.uint64[:, ::1]
I1, I2 = nt.int64[::1], nt.int64[:, ::1]
f8, i8 = nt.float64, nt.int64

# Columns of a recorded cell: rotation-vector centre, half-side, translation centre,
# half-side, lower bound, where its parent's terms start in the pool, how many, their
# parent's outlier cost, the parent's colouring's ``cinfo`` (classes, rotation half-side,
# terms).
_BOUND, _POFF, _PLEN, _POUT, _PCOL = 8, 9, 10, 11, 12
REC_COLS = 15

CONVEX_THETA = 0.05
"""Largest rotation radius (rad) of a cell given the joint convex bound. In larger cells its
second-order remainder leaves it below the other bounds, and the cells it is tried on are not
recoloured: on the 3DMatch pair 0.05 took the fewest CPU seconds to gap 1e-3 of 0.025, 0.05,
0.1 and 0.2."""

# Columns of a frame (one cell per depth): rotation-vector centre, half-side, translation
# centre, half-side, which half is split, the next child to visit.
_RC, _RS, _TC, _TS, _KIND, _NEXT = 0, 3, 4, 7, 8, 9
FRAME_COLS = 10


@njit(cache=True)
def _rotvec_matrix(r0, r1, r2):  # pragma: no cover - compiled
    angle = math.sqrt(r0 * r0 + r1 * r1 + r2 * r2)
    R = np.empty((3, 3))
    if angle < 1e-300:
        for i in range(3):
            for j in range(3):
                R[i, j] = 1.0 if i == j else 0.0
        return R
    x, y, z = r0 / angle, r1 / angle, r2 / angle
    c, s = math.cos(angle), math.sin(angle)
    C = 1.0 - c
    R[0, 0] = c + x * x * C
    R[0, 1] = x * y * C - z * s
    R[0, 2] = x * z * C + y * s
    R[1, 0] = y * x * C + z * s
    R[1, 1] = c + y * y * C
    R[1, 2] = y * z * C - x * s
    R[2, 0] = z * x * C - y * s
    R[2, 1] = z * y * C + x * s
    R[2, 2] = c + z * z * C
    return R



@njit(cache=True)
def _record(rec, nrec, pool, poolid, depth, act, cnt, outc, ccol, cinfo, rc0, rc1, rc2, rs, tc0,
            tc1, tc2, ts, bound, floor):  # pragma: no cover - compiled
    """Append a cell (a child of the frame at ``depth``) to ``rec``, its parent's terms and
    their colour classes to ``pool`` (columns 0 and 1) once per parent; its bound is at least
    ``floor`` (a bound of a cell holding it)."""
    if poolid[depth] < 0:
        off = nrec[1]
        for q in range(cnt[depth]):
            i = act[depth, q]
            pool[off + q, 0] = i
            pool[off + q, 1] = ccol[depth, i]
        nrec[1] = off + cnt[depth]
        poolid[depth] = off
    j = nrec[0]
    rec[j, 0], rec[j, 1], rec[j, 2], rec[j, 3] = rc0, rc1, rc2, rs
    rec[j, 4], rec[j, 5], rec[j, 6], rec[j, 7] = tc0, tc1, tc2, ts
    rec[j, _BOUND], rec[j, _POFF], rec[j, _PLEN] = max(bound, floor), poolid[depth], cnt[depth]
    rec[j, _POUT] = outc[depth]
    rec[j, _PCOL], rec[j, _PCOL + 1], rec[j, _PCOL + 2] = cinfo[depth, 0], cinfo[depth, 1], \
        cinfo[depth, 2]
    nrec[0] = j + 1


@njit(cache=True)
def _recolour(P, lo, wout, adjbits, members, size, dvec, a, pair_tol, srot, slack,
              cls):  # pragma: no cover - compiled
    """A greedy colouring (heaviest gain ``wout - lo`` first) of the terms ``P``: writes each
    term's class to ``cls`` and returns the sum over classes of their largest gain and the
    number of classes.

    Two terms conflict (may share a pose's inlier set) when the consistency graph joins them
    and the cell's rotations can map ``a_j - a_i`` onto ``b_j - b_i`` within their noise
    bounds: ``|d_i - d_j| - srot |a_i - a_j| <= pair_tol_i + pair_tol_j`` with ``d = R0 a - b``
    (translation-free, so a wide translation cube does not loosen it).
    """
    n = P.size
    g = np.empty(n)
    for q in range(n):
        g[q] = wout[P[q]] - lo[P[q]]
    order = np.argsort(-g)
    ncls = 0
    total = 0.0
    for q in range(n):
        i = P[order[q]]
        placed = False
        for c in range(ncls):
            ok = True
            for m in range(size[c]):
                j = members[c, m]
                if adjbits[i, j >> 6] & (np.uint64(1) << np.uint64(j & 63)):
                    x0 = dvec[i, 0] - dvec[j, 0]
                    x1 = dvec[i, 1] - dvec[j, 1]
                    x2 = dvec[i, 2] - dvec[j, 2]
                    y0 = a[i, 0] - a[j, 0]
                    y1 = a[i, 1] - a[j, 1]
                    y2 = a[i, 2] - a[j, 2]
                    dist = math.sqrt(x0 * x0 + x1 * x1 + x2 * x2)
                    rad = srot * math.sqrt(y0 * y0 + y1 * y1 + y2 * y2) + slack[i] + slack[j]
                    if dist - rad <= pair_tol[i] + pair_tol[j]:
                        ok = False
                        break
            if ok:
                members[c, size[c]] = i
                size[c] += 1
                cls[i] = c
                placed = True
                break
        if not placed:
            members[ncls, 0] = i
            size[ncls] = 1
            cls[i] = ncls
            ncls += 1
            total += g[order[q]]
    return total, ncls


@kernel(F2, F2, F1, F1, F1, F1, F1, I2, F2, U2, i8, f8, f8, i8, i8, i8, i8, F2, I2, I1, F1, I1,
        F1, I2)
def pose_bnb(a, b, v, wout, anorm, slack, pair_tol, ccol, cinfo, adjbits, recolour_max, thr,
             allowance, kleaf, leaf_nodes, stop_nodes, max_nodes, frames, act, cnt, outc, ints,
             best, hist):  # pragma: no cover - compiled
    """Depth-first branch and bound of ``min_{R, t} sum_i min(v_i |R a_i + t - b_i|^2, wout_i)``
    over cells (rotation-vector cube x translation cube), pruned against ``thr``; resumable.

    ``a``, ``b`` (N, 3) points, ``v`` (N,) least-squares weights, ``wout`` (N,) outlier costs,
    ``anorm`` (N,) ``|a_i|``, ``slack`` (N,) a rounding allowance per term's residual (added to
    every cell's uncertainty radius). A cell with rotation vectors within ``sr`` (half-side) of
    ``rc`` and translations within ``st`` of ``tc`` (a box) moves ``R a_i`` by at most
    ``rho_i = 2 sin(min(sqrt(3) sr, pi) / 2) |a_i|`` from ``R(rc) a_i`` (Hartley and Kahl:
    rotation vectors ``d`` apart give rotations at most ``d`` apart in angle), so each term's
    residual lies between the distances from ``b_i - R(rc) a_i`` to the nearest and the
    farthest point of the translation box (per axis), less and plus ``rho_i``. Terms whose
    lower residual cannot be an inlier's are outliers throughout the cell ("impossible"); terms
    whose upper residual is an inlier's are inliers throughout ("sure"); the rest are
    "uncertain". A cell's bound is the larger of ``out + sum_uncertain v lo^2 + max(LS_sure,
    sum_sure v lo^2)`` (``LS``: the least-squares optimum over every pose, closed form) and
    the colouring bound ``out_0 + sum wout - sum_classes max_class (wout - v lo^2)``: a pose's
    inliers are pairwise consistent, so at most one per class of a colouring of the terms'
    conflict graph. A cell of rotation radius ``sqrt(3) sr`` at most :data:`CONVEX_THETA` that
    these leave below ``thr`` (or, recording, below ``cap``) is given the joint convex bound
    (:mod:`solvers.certify._convex_cell`: every possible term at one pose, the rotation's
    remainder second order in the cell's size, the Newton steps started from the parent's last
    iterate). ``ccol[0]`` (a colouring of the consistency graph ``adjbits``) serves the
    root; a cell of at most ``recolour_max`` possible terms whose rotation cube or terms shrank
    since its ancestors' colouring, and that the convex bound was not tried on, is recoloured
    greedily, two terms conflicting when
    ``adjbits`` joins them and the cell's rotations can align their difference vectors within
    ``pair_tol_i + pair_tol_j`` (translation-free, so wide translation cubes do not loosen it).
    A colouring stays valid in every sub-cell (their poses are among the cell's), so sub-cells
    inherit it (``ccol[d]``, ``cinfo[d] = [classes, rotation half-side, terms]`` when it was
    made). A cell
    with at most ``kleaf`` uncertain terms is solved exactly over its inlier sets (every pose
    of the cell keeps the sure terms and none of the impossible ones) by :func:`clique_bnb`
    from the sure terms' sums.

    ``frames`` (D, FRAME_COLS), ``act`` (D, N) and ``cnt`` (D,) hold the depth-first search
    (frame 0: the root cell, its active list every term; ``ints = [depth, nodes, code]``).
    ``best = [lowest pruned bound, found value, R (9), t (3)]``: a leaf whose optimum is below
    ``thr`` stores its value and least-squares pose and stops the search with code 3 (the
    caller lowers ``thr`` and resumes). Returns 0 complete, 1 paused at ``stop_nodes``, 2 out
    of ``max_nodes``, 3 a better pose found.
    """
    return _search(a, b, v, wout, anorm, slack, pair_tol, ccol, cinfo, adjbits, recolour_max,
                   thr, allowance, kleaf, leaf_nodes, stop_nodes, max_nodes, frames, act, cnt,
                   outc, ints, best, hist, outc[0], np.zeros((0, REC_COLS)),
                   np.zeros(2, dtype=np.int64), np.zeros((0, 2), dtype=np.int64),
                   np.zeros(frames.shape[0], dtype=np.int64), -np.inf, frames.shape[0] + 1,
                   -np.inf, _scratch(a.shape[0], recolour_max, frames.shape[0]))


@njit(cache=True)
def _scratch(N, recolour_max, D):  # pragma: no cover - compiled
    """Work arrays of :func:`_search` (allocated once per call of a kernel: the recolouring's
    class table is ``recolour_max`` squared; per depth, the convex bound's last iterate in the
    cell split there and whether there is one)."""
    rmax = min(max(recolour_max, 1), N)
    return (np.empty(N), np.zeros(N, dtype=np.bool_), np.zeros(18), np.zeros(N),
            np.zeros((rmax, rmax), dtype=np.int64), np.zeros(rmax, dtype=np.int64),
            np.empty((N, 3)), np.empty((N, 3)), np.empty((N, 3)), np.empty((N, ENV_COLS)),
            np.zeros(6), np.zeros((D, 7)))


@njit(cache=True)
def _search(a, b, v, wout, anorm, slack, pair_tol, ccol, cinfo, adjbits, recolour_max, thr,
            allowance, kleaf, leaf_nodes, stop_nodes, max_nodes, frames, act, cnt, outc, ints,
            best, hist, base0, rec, nrec, pool, poolid, cap, split_depth, floor,
            scratch):  # pragma: no cover - compiled
    """:func:`pose_bnb`'s search (``scratch``: :func:`_scratch`'s arrays); ``base0`` is the
    outlier cost of the terms outside the core
    (the colouring bound's constant). With ``rec`` of at least one row, every cell left with
    a bound below ``cap`` (pruned, or solved exactly against ``thr``) is recorded there for a
    later search (:func:`pose_frontier`): its cube, bound, and its parent's terms (stored once
    per parent in ``pool``; ``poolid[d]``: where the list of the frame at depth ``d`` is, -1 when
    not yet stored; ``nrec = [records, pool entries]``); returns 4 (resumable) when they might
    not fit.
    """
    N = a.shape[0]
    D = frames.shape[0]
    depth, nodes = ints[0], ints[1]
    lo, hi_in, s, cmax, members, size, dvec, cE, cQ, cenv, cz, zpar = scratch
    rmax = size.size
    wtot = 0.0
    for i in range(N):
        wtot += wout[i]
    recording = rec.shape[0] > 0
    # A cell to record is bounded on until its bound reaches ``cap`` (a cell at or above it is
    # not recorded), so that the next, higher thresholds may leave it alone.
    early = max(cap - thr, 0.0) if recording else 0.0
    while depth >= 0:
        fr = frames[depth]
        k = int(fr[_NEXT])
        if k >= 8:
            depth -= 1
            continue
        if depth + 1 >= D:  # out of frames: the search cannot be completed
            ints[0], ints[1] = depth, nodes
            return 2
        if recording and (nrec[0] >= rec.shape[0] or (
                poolid[depth] < 0 and nrec[1] + cnt[depth] > pool.shape[0])):
            ints[0], ints[1] = depth, nodes
            return 4
        fr[_NEXT] = k + 1
        if nodes >= stop_nodes and nodes < max_nodes:
            fr[_NEXT] = k
            ints[0], ints[1] = depth, nodes
            return 1
        nodes += 1
        if nodes > max_nodes:
            fr[_NEXT] = k
            ints[0], ints[1] = depth, nodes
            return 2
        hist[depth, 0] += 1
        # The child cell: halve the rotation or the translation cube.
        rc0, rc1, rc2, rs = fr[_RC], fr[_RC + 1], fr[_RC + 2], fr[_RS]
        tc0, tc1, tc2, ts = fr[_TC], fr[_TC + 1], fr[_TC + 2], fr[_TS]
        o0 = 1.0 if (k & 1) else -1.0
        o1 = 1.0 if (k & 2) else -1.0
        o2 = 1.0 if (k & 4) else -1.0
        if fr[_KIND] == 0.0:
            rs = 0.5 * rs
            rc0, rc1, rc2 = rc0 + o0 * rs, rc1 + o1 * rs, rc2 + o2 * rs
            # Cubes wholly outside the ball of radius pi hold no rotation the ball lacks.
            dx = max(abs(rc0) - rs, 0.0)
            dy = max(abs(rc1) - rs, 0.0)
            dz = max(abs(rc2) - rs, 0.0)
            if dx * dx + dy * dy + dz * dz > math.pi * math.pi * (1.0 + 1e-9):
                continue
        elif fr[_KIND] == 2.0:
            pass  # a recorded cell searched again: its one child is itself
        else:
            ts = 0.5 * ts
            tc0, tc1, tc2 = tc0 + o0 * ts, tc1 + o1 * ts, tc2 + o2 * ts
        R = _rotvec_matrix(rc0, rc1, rc2)
        theta = min(math.sqrt(3.0) * rs * (1.0 + 1e-12) + 1e-13, math.pi)
        srot = 2.0 * math.sin(0.5 * theta) * (1.0 + 1e-12)
        strans = math.sqrt(3.0) * ts * (1.0 + 1e-12)
        tbox = ts * (1.0 + 1e-12)
        # Terms: the parent's active (possible) ones; the others are outliers here too.
        n_par = cnt[depth]
        out = outc[depth]
        bound = out
        n_new = 0
        n_unc = 0
        asum = 0.0
        inherited = np.inf
        for x in range(18):
            s[x] = 0.0
        sure_lo = 0.0
        pruned = False
        ncol = int(cinfo[depth, 0])
        for x in range(ncol):
            cmax[x] = 0.0
        for q in range(n_par):
            i = act[depth, q]
            e0 = R[0, 0] * a[i, 0] + R[0, 1] * a[i, 1] + R[0, 2] * a[i, 2] + tc0 - b[i, 0]
            e1 = R[1, 0] * a[i, 0] + R[1, 1] * a[i, 1] + R[1, 2] * a[i, 2] + tc1 - b[i, 1]
            e2 = R[2, 0] * a[i, 0] + R[2, 1] * a[i, 1] + R[2, 2] * a[i, 2] + tc2 - b[i, 2]
            dvec[i, 0], dvec[i, 1], dvec[i, 2] = e0 - tc0, e1 - tc1, e2 - tc2
            # The translations are a box: the nearest and farthest of its points, per axis,
            # then the rotations' ball.
            n0 = max(abs(e0) - tbox, 0.0)
            n1 = max(abs(e1) - tbox, 0.0)
            n2 = max(abs(e2) - tbox, 0.0)
            rho = srot * anorm[i] + slack[i]
            low = max(math.sqrt(n0 * n0 + n1 * n1 + n2 * n2) - rho, 0.0)
            c_low = v[i] * low * low
            if c_low >= wout[i]:
                out += wout[i]
                bound += wout[i]
            else:
                f0, f1, f2 = abs(e0) + tbox, abs(e1) + tbox, abs(e2) + tbox
                high = math.sqrt(f0 * f0 + f1 * f1 + f2 * f2) + rho
                act[depth + 1, n_new] = i
                n_new += 1
                lo[i] = c_low
                g = wout[i] - c_low
                cl = ccol[depth, i]
                if g > cmax[cl]:
                    cmax[cl] = g
                if v[i] * high * high < wout[i]:
                    hi_in[i] = True
                    sure_lo += c_low
                    vi = v[i]
                    s[0] += vi
                    for x in range(3):
                        s[1 + x] += vi * a[i, x]
                        s[4 + x] += vi * b[i, x]
                        for y in range(3):
                            s[7 + 3 * x + y] += vi * a[i, x] * b[i, y]
                        s[16] += vi * a[i, x] * a[i, x]
                        s[17] += vi * b[i, x] * b[i, x]
                    bound += c_low
                else:
                    hi_in[i] = False
                    n_unc += 1
                    bound += c_low
                asum += anorm[i]
            if bound - allowance >= thr + early:
                pruned = True
                break
        if bound - allowance >= thr:
            pruned = True
        if (not pruned or (recording and bound - allowance < cap)) and s[0] > 0.0 and \
                n_new - n_unc >= 3:
            ls = _ls_bound(s)
            if ls > sure_lo:
                bound += ls - sure_lo
                if bound - allowance >= thr:
                    pruned = True
        if not pruned or (recording and bound - allowance < cap):
            # A pose's inliers form a clique: at most one per colour class of the
            # consistency graph, so its gain over all-outliers is at most the classes' best.
            gain = 0.0
            for x in range(ncol):
                gain += cmax[x]
            inherited = gain
            if base0 + wtot - gain > bound:
                bound = base0 + wtot - gain
                if bound - allowance >= thr:
                    pruned = True
        recoloured = False
        tried = False
        convexed = False
        if (not pruned or (recording and bound - allowance < cap)) and theta <= CONVEX_THETA:
            # The joint convex bound (every term at one pose, second order in the rotation).
            ncv, ccon = cell_terms(a, b, v, wout, anorm, slack, act[depth + 1, :n_new], R, tc0,
                                   tc1, tc2, theta, tbox, cE, cQ, cenv)
            # From the parent's last iterate, moved to this cell's centre (a start only).
            zp = zpar[depth]
            for x in range(3):
                cz[x] = zp[x] - (rc0, rc1, rc2)[x] + fr[_RC + x] if zp[6] > 0.0 else 0.0
                cz[3 + x] = zp[3 + x] - (tc0, tc1, tc2)[x] + fr[_TC + x] if zp[6] > 0.0 else 0.0
            convexed = True
            # Of use only above the cell's bound and the threshold; enough at the cap.
            useless = max(bound, thr + allowance) - out - ccon
            enough = (max(cap, thr) if recording else thr) + allowance - out - ccon
            cvx = out + ccon + convex_bound(cE, cQ, cenv, ncv, theta, tbox, cz, useless, enough)
            hist[depth, 4] += 1
            if cvx > bound:
                bound = cvx
                if bound - allowance >= thr and not pruned:
                    pruned = True
                    hist[depth, 5] += 1
        ncls_new = 0
        if not pruned and not convexed and n_new <= recolour_max and (
                rs < cinfo[depth, 1] or n_new < 0.7 * cinfo[depth, 2]):
            # The same bound from a greedy colouring of this cell's possible terms alone,
            # kept for its sub-cells (a colouring stays valid in any sub-cell).
            for x in range(rmax):
                size[x] = 0
            gain, ncls_new = _recolour(act[depth + 1, :n_new], lo, wout, adjbits, members, size,
                                       dvec, a, pair_tol, srot, slack, ccol[depth + 1])
            tried = True
            recoloured = gain < inherited  # else the sub-cells keep the inherited classes
            if base0 + wtot - gain > bound:
                bound = base0 + wtot - gain
                if bound - allowance >= thr:
                    pruned = True
                    hist[depth, 2] += 1
        if pruned:
            hist[depth, 1] += 1
            if bound - allowance < best[0]:
                best[0] = bound - allowance
            if recording and bound - allowance < cap:
                _record(rec, nrec, pool, poolid, depth, act, cnt, outc, ccol, cinfo, rc0, rc1, rc2,
                        rs, tc0, tc1, tc2, ts, bound - allowance, floor)
            continue
        if n_unc <= kleaf:
            # Exact over the cell's inlier sets: sure terms in, impossible ones out.
            K = n_unc
            au = np.empty((K, 3))
            bu = np.empty((K, 3))
            vu = np.empty(K)
            wu = np.empty(K)
            m = 0
            for q in range(n_new):
                i = act[depth + 1, q]
                if not hi_in[i]:
                    for x in range(3):
                        au[m, x] = a[i, x]
                        bu[m, x] = b[i, x]
                    vu[m] = v[i]
                    wu[m] = wout[i]
                    m += 1
            state = np.zeros((K + 1, 18))
            for x in range(18):
                state[0, x] = s[x]
            outs = np.zeros(K + 1)
            outs[0] = out
            phase = np.zeros(K + 1, dtype=np.int64)
            li = np.zeros(3, dtype=np.int64)
            bp = np.zeros(13)
            bp[0] = thr
            code = clique_bnb(au, bu, vu, wu, allowance, leaf_nodes, leaf_nodes, state, outs,
                              phase, li, bp)
            nodes += li[1]
            if li[2] == 1:
                # A set whose least-squares pose costs less than ``thr``: a better pose.
                best[1] = bp[0]
                for x in range(12):
                    best[2 + x] = bp[1 + x]
                if code == 0:
                    if bp[0] - allowance < best[0]:
                        best[0] = bp[0] - allowance
                    if recording and bp[0] - allowance < cap:
                        _record(rec, nrec, pool, poolid, depth, act, cnt, outc, ccol, cinfo, rc0,
                                rc1, rc2, rs, tc0, tc1, tc2, ts, bp[0] - allowance, floor)
                else:
                    fr[_NEXT] = k  # not finished: visit the cell again
                ints[0], ints[1], ints[2] = depth, nodes, code
                return 3
            if code == 0:
                hist[depth, 3] += 1
                if thr - allowance < best[0]:
                    best[0] = thr - allowance
                if recording and thr - allowance < cap:
                    _record(rec, nrec, pool, poolid, depth, act, cnt, outc, ccol, cinfo, rc0, rc1,
                            rc2, rs, tc0, tc1, tc2, ts, thr - allowance, floor)
                continue
        if depth + 1 >= split_depth:
            # Deep enough below the search's root: left for a later pass (the frontier's
            # cells are searched lowest bound first, in blocks shared by the workers).
            if bound - allowance < cap:
                _record(rec, nrec, pool, poolid, depth, act, cnt, outc, ccol, cinfo, rc0, rc1, rc2,
                        rs, tc0, tc1, tc2, ts, bound - allowance, floor)
            continue
        # Split the child: the half with the larger uncertainty radius.
        nf = frames[depth + 1]
        nf[_RC], nf[_RC + 1], nf[_RC + 2], nf[_RS] = rc0, rc1, rc2, rs
        nf[_TC], nf[_TC + 1], nf[_TC + 2], nf[_TS] = tc0, tc1, tc2, ts
        nf[_KIND] = 0.0 if srot * asum / max(n_new, 1) > strans else 1.0
        nf[_NEXT] = 0.0
        cnt[depth + 1] = n_new
        outc[depth + 1] = out
        for x in range(6):
            zpar[depth + 1, x] = cz[x]
        zpar[depth + 1, 6] = 1.0 if convexed else 0.0
        poolid[depth + 1] = -1
        if recoloured:
            cinfo[depth + 1, 0], cinfo[depth + 1, 1], cinfo[depth + 1, 2] = ncls_new, rs, n_new
        else:
            for q in range(n_new):
                i = act[depth + 1, q]
                ccol[depth + 1, i] = ccol[depth, i]
            for x in range(3):
                cinfo[depth + 1, x] = cinfo[depth, x]
            if tried:  # not again until the rotation cell or the terms shrink further
                cinfo[depth + 1, 1], cinfo[depth + 1, 2] = rs, n_new
        depth += 1
    ints[0], ints[1] = depth, nodes
    return 0


@kernel(F2, F2, F1, F1, F1, F1, F1, I2, F2, U2, i8, f8, f8, i8, i8, i8, F2, I2, f8, F2, I2,
        I1, F1, I1, F1, I2, F2, I1, I2, I1, f8, i8, nogil=True)
def pose_frontier(a, b, v, wout, anorm, slack, pair_tol, ccol, cinfo, adjbits, recolour_max, thr,
                  allowance, kleaf, leaf_nodes, stop_nodes, roots, rpool, base0, frames,
                  act, cnt, outc, ints, best, hist, rec, nrec, pool, poolid, cap,
                  split_depth):  # pragma: no cover - compiled
    """:func:`pose_bnb`'s search below each of the cells ``roots`` (rows as ``rec``'s, sorted
    by bound; their parents' terms in ``rpool``) in turn, recording every cell it leaves with a
    bound below ``cap`` in ``rec`` (see :func:`_search`), and every cell ``split_depth`` levels
    below its root unsplit, with its bound (for a later pass); resumable.

    Each root is bounded again (its one child is itself: frame kind 2) from its parent's terms
    (``outc``: their parent's outlier cost) and their colouring (``rpool`` columns 0 and 1), as
    the depth-first search bounds a child, and split while its bound is below ``thr``
    (``base0``: the outlier cost of the terms outside the core). ``ints =
    [depth, nodes, code, next root, searching a root]``. Returns 0 when every root is done
    or the next root's bound is at least ``thr`` (it and the later ones stay as they are),
    else :func:`_search`'s code (1 paused at ``stop_nodes``, 2 out of frames, 3 a better
    pose, 4 records full).
    """
    max_nodes = np.iinfo(np.int64).max // 2
    scratch = _scratch(a.shape[0], recolour_max, frames.shape[0])
    while True:
        if ints[4] == 0:
            r = ints[3]
            if r >= roots.shape[0] or roots[r, _BOUND] >= thr:
                return 0
            fr = frames[0]
            for x in range(8):
                fr[x] = roots[r, x]
            off, n = int(roots[r, _POFF]), int(roots[r, _PLEN])
            for q in range(n):
                i = rpool[off + q, 0]
                act[0, q] = i
                ccol[0, i] = rpool[off + q, 1]
            cnt[0] = n
            outc[0] = roots[r, _POUT]
            for x in range(3):
                cinfo[0, x] = roots[r, _PCOL + x]
            fr[_KIND] = 2.0
            fr[_NEXT] = 7.0
            scratch[-1][0, 6] = 0.0  # no convex iterate at this root yet
            poolid[0] = -1
            ints[0] = 0
            ints[4] = 1
        code = _search(a, b, v, wout, anorm, slack, pair_tol, ccol, cinfo, adjbits,
                       recolour_max, thr, allowance, kleaf, leaf_nodes, stop_nodes, max_nodes,
                       frames, act, cnt, outc, ints, best, hist, base0, rec, nrec, pool, poolid,
                       cap, split_depth, roots[ints[3], _BOUND], scratch)
        if code != 0:
            return code
        ints[4] = 0
        ints[3] += 1
