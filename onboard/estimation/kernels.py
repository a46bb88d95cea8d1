r"""Compiled inner loops of the window problem (numba), beside the numpy formulations they replace.

Why compiled: the model selection evaluates a window problem's residuals, Jacobian, ``J^T J`` and ``J^T r`` a few
hundred times on arrays of a few hundred numbers, and in numpy each of those took 15-45 calls whose fixed cost
was most of their time.  One loop over the observations does the arithmetic without the calls.

The measurement rows' kernels have numpy references here with the same signature (``*_reference``: the
formulation :class:`~onboard.estimation.window_problem.WindowProblem` used before, or the dense product); the turn
prior's and the scaling's are checked against the dense products and numpy's expressions
(``tests/onboard/test_estimator_kernels.py``, over random windows).  The elementwise arithmetic is the same
operations in the same order; the sums that numpy handed to BLAS (the spline's basis product, the rotation by the
attitude bias, the knot intervals' sums of ``J^T J``, ``J^T r``'s basis product) run here in plain index order,
and BLAS's order (blocked, with fused multiply-adds on CPUs that have them) differs by the machine, so those agree
to rounding (~1e-15 of the values), not to the bit.  No ``fastmath``: no reassociation, no fused multiply-add of
our own; numpy's error model (a division by zero gives inf or NaN as in the references, not an exception).

The kernels compile on first use, or load from numba's cache (``cache=True``: in ``NUMBA_CACHE_DIR`` when it is
set, else beside this module); :func:`warm` does that once per process at the estimator's construction, so that no
estimator step pays it (seconds to compile, a fraction of a second to load from the cache: docs/performance.md).
numba is a declared dependency of the onboard service: without it this module raises ImportError naming it, rather
than falling back to the numpy formulation at several times the CPU.
"""

from __future__ import annotations

import numpy as np

from onboard.core.jit import njit

__all__ = [
    "linearise_measurements",
    "linearise_measurements_reference",
    "measurement_gram",
    "measurement_gram_reference",
    "measurement_gradient",
    "measurement_gradient_reference",
    "add_turn_prior_transpose",
    "add_turn_prior_gram",
    "turn_prior_rows",
    "scale_normal_equations",
    "warm",
]


@njit(cache=True, nogil=True, error_model="numpy")
def linearise_measurements(c, index, w0, p_cam_T, beta, gamma, dt, Rphi, R_T, xy_T, sT, jacobian, X, los, r, U):
    """The measurement rows of the window problem at control points ``c`` (count, 3), in place; returns validity.

    ``index``/``w0`` (F, 4) the basis rows (controls and weights of p(t_i)); ``p_cam_T`` (3, F) the camera
    centres; ``beta`` (3,) and ``gamma`` (3,) the camera-position offset and drift, ``Rphi`` (3, 3) Exp(phi) of
    the attitude bias, each of size 0 when the problem has none; ``dt`` (F,) times from the reference; ``R_T``
    (3, 3, F) ``R_cn`` observation-last; ``xy_T`` (2, F) the measurements; ``sT`` (2, F) the rows' weights.
    Writes ``X`` (3, F) the positions, ``los`` (3, F) their lines of sight from the cameras, ``r`` (2F,) the
    residuals (row 2f + a), and with ``jacobian`` ``U`` (2, 3 + nuisances, F): d r / d w (w the line of sight
    with the offsets), then the attitude bias's, offset's and drift's local columns, those present, in that order.
    Valid when every predicted direction is in front of its camera (:func:`linearise_measurements_reference`).
    """
    F = w0.shape[0]
    has_beta = beta.size == 3
    has_gamma = gamma.size == 3
    has_phi = Rphi.size == 9
    k_beta = 6 if has_phi else 3
    k_gamma = k_beta + 3 if has_beta else k_beta
    valid = True
    for f in range(F):
        # p(t_f): the basis row against its four controls, summed in the basis order
        x0 = w0[f, 0] * c[index[f, 0], 0]
        x1 = w0[f, 0] * c[index[f, 0], 1]
        x2 = w0[f, 0] * c[index[f, 0], 2]
        for m in range(1, 4):
            x0 += w0[f, m] * c[index[f, m], 0]
            x1 += w0[f, m] * c[index[f, m], 1]
            x2 += w0[f, m] * c[index[f, m], 2]
        X[0, f] = x0
        X[1, f] = x1
        X[2, f] = x2
        l0 = x0 - p_cam_T[0, f]
        l1 = x1 - p_cam_T[1, f]
        l2 = x2 - p_cam_T[2, f]
        los[0, f] = l0
        los[1, f] = l1
        los[2, f] = l2
        if has_beta:
            l0 = l0 + beta[0]
            l1 = l1 + beta[1]
            l2 = l2 + beta[2]
        if has_gamma:
            l0 = l0 + gamma[0] * dt[f]
            l1 = l1 + gamma[1] * dt[f]
            l2 = l2 + gamma[2] * dt[f]
        if has_phi:
            v0 = Rphi[0, 0] * l0 + Rphi[0, 1] * l1 + Rphi[0, 2] * l2
            v1 = Rphi[1, 0] * l0 + Rphi[1, 1] * l1 + Rphi[1, 2] * l2
            v2 = Rphi[2, 0] * l0 + Rphi[2, 1] * l1 + Rphi[2, 2] * l2
        else:
            v0, v1, v2 = l0, l1, l2
        y0 = R_T[0, 0, f] * v0 + R_T[0, 1, f] * v1 + R_T[0, 2, f] * v2
        y1 = R_T[1, 0, f] * v0 + R_T[1, 1, f] * v1 + R_T[1, 2, f] * v2
        z = R_T[2, 0, f] * v0 + R_T[2, 1, f] * v1 + R_T[2, 2, f] * v2
        # (a NaN fails both tests, as in numpy)
        if not (z * z > 1e-12 * (v0 * v0 + v1 * v1 + v2 * v2) and z > 0):
            valid = False
        zs = z if z > 1e-9 else 1e-9  # np.fmax(z, 1e-9): a NaN depth becomes 1e-9
        px = y0 / zs
        py = y1 / zs
        r[2 * f] = (px - xy_T[0, f]) * sT[0, f]
        r[2 * f + 1] = (py - xy_T[1, f]) * sT[1, f]
        if not jacobian:
            continue
        kz = 1.0 / zs
        for a in range(2):
            pa = px if a == 0 else py
            ka = kz * sT[a, f]
            # d r_a / d w_rot = (R[a] - pred_a R[2]) / z * s_a
            m0 = (R_T[a, 0, f] - pa * R_T[2, 0, f]) * ka
            m1 = (R_T[a, 1, f] - pa * R_T[2, 1, f]) * ka
            m2 = (R_T[a, 2, f] - pa * R_T[2, 2, f]) * ka
            if has_phi:
                # d r / d w = (d r / d w_rot) Rphi; d r / d phi = -m [w_rot]x, component i: w[i+1] m[i+2] - w[i+2] m[i+1]
                u0 = Rphi[0, 0] * m0 + Rphi[1, 0] * m1 + Rphi[2, 0] * m2
                u1 = Rphi[0, 1] * m0 + Rphi[1, 1] * m1 + Rphi[2, 1] * m2
                u2 = Rphi[0, 2] * m0 + Rphi[1, 2] * m1 + Rphi[2, 2] * m2
                U[a, 3, f] = v1 * m2 - v2 * m1
                U[a, 4, f] = v2 * m0 - v0 * m2
                U[a, 5, f] = v0 * m1 - v1 * m0
            else:
                u0, u1, u2 = m0, m1, m2
            U[a, 0, f] = u0
            U[a, 1, f] = u1
            U[a, 2, f] = u2
            if has_beta:
                U[a, k_beta, f] = u0
                U[a, k_beta + 1, f] = u1
                U[a, k_beta + 2, f] = u2
            if has_gamma:
                U[a, k_gamma, f] = u0 * dt[f]
                U[a, k_gamma + 1, f] = u1 * dt[f]
                U[a, k_gamma + 2, f] = u2 * dt[f]
    return valid


def linearise_measurements_reference(
    c, index, w0, p_cam_T, beta, gamma, dt, Rphi, R_T, xy_T, sT, jacobian, X, los, r, U
):
    """:func:`linearise_measurements` in numpy: the formulation ``WindowProblem.linearise`` used before the kernel
    (observation-last arrays, the dense basis product through BLAS), arguments and outputs the same."""
    F = w0.shape[0]
    B0T = np.zeros((c.shape[0], F))
    np.put_along_axis(B0T.T, index, w0, axis=1)
    X[...] = c.T @ B0T
    w = X - p_cam_T
    los[...] = w
    if beta.size:
        w = w + beta[:, None]
    if gamma.size:
        w = w + gamma[:, None] * dt
    w_rot = Rphi @ w if Rphi.size else w
    y = np.einsum("ijf,jf->if", R_T, w_rot)
    z = y[2]
    valid = bool((z * z > 1e-12 * np.einsum("if,if->f", w_rot, w_rot)).all() and (z > 0).all())
    zs = np.fmax(z, 1e-9)
    pred = y[:2] / zs
    r.reshape(F, 2).T[...] = (pred - xy_T) * sT
    if not jacobian:
        return valid
    M = (R_T[:2] - pred[:, None, :] * R_T[2]) * ((1.0 / zs) * sT)[:, None, :]  # (2, 3, F): d r / d w_rot
    k = 3
    if Rphi.size:
        U[:, :3] = np.matmul(Rphi.T, M)
        U[:, 3:6] = np.cross(w_rot.T[None], M.transpose(0, 2, 1)).transpose(0, 2, 1)
        k = 6
    else:
        U[:, :3] = M
    if beta.size:
        U[:, k : k + 3] = U[:, :3]
        k += 3
    if gamma.size:
        U[:, k : k + 3] = U[:, :3] * dt
    return valid


#: the control pairs m <= n of a knot interval's 4 x 4 blocks, and the axis pairs i <= j of a 3 x 3 one
_PAIRS4 = np.array([(m, n) for m in range(4) for n in range(m, 4)], dtype=np.int64)
_PAIRS3 = np.array([(i, j) for i in range(3) for j in range(i, 3)], dtype=np.int64)


@njit(cache=True, nogil=True, error_model="numpy")
def measurement_gram(U, index, w0, nuis_cols, H_fixed, H):
    """``J^T J`` of the measurement rows plus ``H_fixed``, into ``H`` (n, n), from their local Jacobian ``U`` (2, 3 +
    nuisances, F) of :func:`linearise_measurements`: row (f, a) is ``w0[f, m] U[a, :3, f]`` in the columns of control
    ``index[f, m]`` and ``U[a, 3:, f]`` in the nuisances' columns ``nuis_cols`` (increasing, after the controls').

    Per observation ``P = u^T U`` (the two rows' outer products); per knot interval (the observations sharing
    ``index[f, 0]``) the sums ``sum_f w0[m] w0[n] P[:, :3]`` for the control pairs m <= n and axis pairs i <= j (the
    rest is their mirror: ``P[:, :3]`` is symmetric) and ``sum_f w0[m] P[:, 3:]``, added to the upper triangle of H
    when the interval ends; ``n^T n`` over every observation into the nuisances' block; the lower triangle the
    upper's mirror (:func:`measurement_gram_reference`).
    """
    F = w0.shape[0]
    u = U.shape[1]
    nm = u - 3
    pairs4, pairs3 = _PAIRS4, _PAIRS3
    H[:, :] = 0.0
    S = np.zeros((10, 6))  # the interval's control-control sums, (m, n) pair by (i, j) pair
    Sn = np.zeros((4, 3 * nm))  # its control-nuisance sums, (control, axis x nuisance)
    N = np.zeros((nm, nm))
    Q = np.empty(3 * nm)
    seg = -1
    for f in range(F + 1):
        if f == F or index[f, 0] != seg:
            if seg >= 0:  # the interval ends: its sums into H
                for p in range(10):
                    r0 = 3 * (seg + pairs4[p, 0])
                    c0 = 3 * (seg + pairs4[p, 1])
                    for q in range(6):
                        i, j = pairs3[q, 0], pairs3[q, 1]
                        H[r0 + i, c0 + j] += S[p, q]
                        if i != j and r0 != c0:
                            H[r0 + j, c0 + i] += S[p, q]
                for m in range(4):
                    for i in range(3):
                        for j in range(nm):
                            H[3 * (seg + m) + i, nuis_cols[j]] += Sn[m, i * nm + j]
            if f == F:
                break
            seg = index[f, 0]
            S[:, :] = 0.0
            Sn[:, :] = 0.0
        a0, a1, a2 = U[0, 0, f], U[0, 1, f], U[0, 2, f]
        b0, b1, b2 = U[1, 0, f], U[1, 1, f], U[1, 2, f]
        # P[q] for the axis pairs (0, 0), (0, 1), (0, 2), (1, 1), (1, 2), (2, 2)
        p0 = a0 * a0 + b0 * b0
        p1 = a0 * a1 + b0 * b1
        p2 = a0 * a2 + b0 * b2
        p3 = a1 * a1 + b1 * b1
        p4 = a1 * a2 + b1 * b2
        p5 = a2 * a2 + b2 * b2
        for j in range(nm):
            c0 = U[0, 3 + j, f]
            c1 = U[1, 3 + j, f]
            Q[j] = a0 * c0 + b0 * c1
            Q[nm + j] = a1 * c0 + b1 * c1
            Q[2 * nm + j] = a2 * c0 + b2 * c1
        for p in range(10):
            w = w0[f, pairs4[p, 0]] * w0[f, pairs4[p, 1]]
            S[p, 0] += w * p0
            S[p, 1] += w * p1
            S[p, 2] += w * p2
            S[p, 3] += w * p3
            S[p, 4] += w * p4
            S[p, 5] += w * p5
        for m in range(4):
            w = w0[f, m]
            for k in range(3 * nm):
                Sn[m, k] += w * Q[k]
        for i in range(nm):
            for j in range(i, nm):
                N[i, j] += U[0, 3 + i, f] * U[0, 3 + j, f] + U[1, 3 + i, f] * U[1, 3 + j, f]
    for i in range(nm):
        for j in range(i, nm):
            H[nuis_cols[i], nuis_cols[j]] += N[i, j]
    n_all = H.shape[0]
    for i in range(n_all):
        for j in range(i + 1, n_all):
            H[j, i] = H[i, j]
    for i in range(n_all):
        for j in range(n_all):
            H[i, j] += H_fixed[i, j]


@njit(cache=True, nogil=True, error_model="numpy")
def add_turn_prior_transpose(Bq1, Bq2, sq_h, sq_v, x, om, out):
    """Adds ``J_p^T x`` to ``out`` (3 count,), J_p the coordinated-turn motion prior's rows (3G) at turn rate ``om``
    without the turn rate's column, x (3G,): ``d rp / d c`` is ``sq Bq2`` on each axis (``sq_h`` north and east,
    ``sq_v`` down), plus ``om sq_h Bq1`` from the east control to the north row and minus it from north to east.
    Per control and axis ``sum_g Bq2[g, c] sq[g] x[g] + om sum_g Bq1[g, c] sq_h[g] t[g]`` (t = (-x_e, x_n, 0)),
    the bases' zeros skipped (they add nothing); ``WindowProblem`` used the two dense products in numpy."""
    G, count = Bq2.shape
    a2 = np.zeros((count, 3))
    a1 = np.zeros((count, 2))
    for g in range(G):
        e0 = sq_h[g] * x[3 * g]
        e1 = sq_h[g] * x[3 * g + 1]
        e2 = sq_v[g] * x[3 * g + 2]
        t0 = sq_h[g] * -x[3 * g + 1]
        t1 = sq_h[g] * x[3 * g]
        for c in range(count):
            b2 = Bq2[g, c]
            if b2 != 0.0:
                a2[c, 0] += b2 * e0
                a2[c, 1] += b2 * e1
                a2[c, 2] += b2 * e2
            b1 = Bq1[g, c]
            if b1 != 0.0:
                a1[c, 0] += b1 * t0
                a1[c, 1] += b1 * t1
    for c in range(count):
        out[3 * c] += a2[c, 0] + om * a1[c, 0]
        out[3 * c + 1] += a2[c, 1] + om * a1[c, 1]
        out[3 * c + 2] += a2[c, 2]


@njit(cache=True, nogil=True, error_model="numpy")
def add_turn_prior_gram(H, A, B, C, om, Bq1, Bq2, sq_h, sq_v, j_om, i_omega):
    """Adds the coordinated-turn motion prior's rows' ``J^T J`` at turn rate ``om`` to ``H``: ``A + om B + om^2 C``
    on the controls (the span's polynomial, ``_SpanPrior.grams``), ``J_p^T j_om`` (:func:`add_turn_prior_transpose`)
    between the controls and the turn rate's column ``i_omega`` (``j_om`` that column, 3G), ``j_om . j_om`` on
    its diagonal."""
    nc = A.shape[0]
    om2 = om * om
    for i in range(nc):
        for j in range(nc):
            H[i, j] += (A[i, j] + om * B[i, j]) + om2 * C[i, j]
    h = np.zeros(nc)
    add_turn_prior_transpose(Bq1, Bq2, sq_h, sq_v, j_om, om, h)
    for i in range(nc):
        H[i, i_omega] += h[i]
        H[i_omega, i] += h[i]
    d = 0.0
    for g in range(j_om.size):
        d += j_om[g] * j_om[g]
    H[i_omega, i_omega] += d


@njit(cache=True, nogil=True, error_model="numpy")
def turn_prior_rows(Bq1, Bq2, sq_h, sq_v, c, om, rp, j_omega, jacobian):
    """The coordinated-turn motion prior's residuals at controls ``c`` (count, 3) and turn rate ``om``, into ``rp``
    (3G,): ``sq_h (a_n + om v_e)``, ``sq_h (a_e - om v_n)``, ``sq_v a_d`` with ``v = Bq1 c``, ``a = Bq2 c`` (the
    bases' zeros skipped); with ``jacobian`` the turn rate's column ``j_omega`` (3G,): ``sq_h v_e``, ``-sq_h v_n``, 0
    (its third entries are not written: they stay zero)."""
    G, count = Bq2.shape
    for g in range(G):
        v0 = 0.0
        v1 = 0.0
        a0 = 0.0
        a1 = 0.0
        a2 = 0.0
        for k in range(count):
            b1 = Bq1[g, k]
            if b1 != 0.0:
                v0 += b1 * c[k, 0]
                v1 += b1 * c[k, 1]
            b2 = Bq2[g, k]
            if b2 != 0.0:
                a0 += b2 * c[k, 0]
                a1 += b2 * c[k, 1]
                a2 += b2 * c[k, 2]
        rp[3 * g] = sq_h[g] * (a0 + om * v1)
        rp[3 * g + 1] = sq_h[g] * (a1 - om * v0)
        rp[3 * g + 2] = sq_v[g] * a2
        if jacobian:
            j_omega[3 * g] = sq_h[g] * v1
            j_omega[3 * g + 1] = -sq_h[g] * v0


@njit(cache=True, nogil=True, error_model="numpy")
def scale_normal_equations(H, g):
    """More's column scaling of the normal equations, in place: ``d = sqrt(diag H)`` (1 where 0), ``H / (d d^T)``,
    ``g / d``; returns d.  Elementwise as the numpy it replaces (``H /= np.multiply.outer(d, d)``), bit for bit."""
    n = H.shape[0]
    d = np.empty(n)
    for i in range(n):
        d[i] = np.sqrt(H[i, i])
        if d[i] == 0.0:
            d[i] = 1.0
    for i in range(n):
        for j in range(n):
            H[i, j] /= d[i] * d[j]
    for i in range(g.size):
        g[i] /= d[i]
    return d


def measurement_gram_reference(U, index, w0, nuis_cols, H_fixed, H):
    """:func:`measurement_gram` as the dense product of the measurement rows' Jacobian, in numpy."""
    F = w0.shape[0]
    n = H.shape[0]
    J = np.zeros((2 * F, n))
    rows = J.reshape(F, 2, n)
    for m in range(4):  # the four controls of a row are distinct columns
        for k in range(3):
            rows[np.arange(F), :, 3 * index[:, m] + k] = (w0[:, m] * U[:, k]).T
    for j, col in enumerate(nuis_cols):
        rows[:, :, col] += U[:, 3 + j].T
    H[...] = J.T @ J + H_fixed


@njit(cache=True, nogil=True, error_model="numpy")
def measurement_gradient(U, r, index, w0, nuis_cols, g):
    """``J^T r`` of the measurement rows (their residuals ``r``, 2F of them first), into ``g`` (n,): per observation
    ``U[0] r[2f] + U[1] r[2f + 1]``, its first three times ``w0[f, m]`` into control ``index[f, m]``'s columns, the
    rest into the nuisances' (:func:`measurement_gradient_reference`)."""
    F = w0.shape[0]
    u = U.shape[1]
    g[:] = 0.0
    for f in range(F):
        ra = r[2 * f]
        rb = r[2 * f + 1]
        for j in range(3):
            t = U[0, j, f] * ra
            t += U[1, j, f] * rb
            for m in range(4):
                g[3 * index[f, m] + j] += w0[f, m] * t
        for j in range(3, u):
            t = U[0, j, f] * ra
            t += U[1, j, f] * rb
            g[nuis_cols[j - 3]] += t


def measurement_gradient_reference(U, r, index, w0, nuis_cols, g):
    """:func:`measurement_gradient` in numpy: the dense basis product, the formulation ``WindowProblem.gradient``
    used before the kernel."""
    F = w0.shape[0]
    B0 = np.zeros((F, int(index.max()) + 1))
    np.put_along_axis(B0, index, w0, axis=1)
    Ur = U[0] * r[0 : 2 * F : 2]
    Ur += U[1] * r[1 : 2 * F : 2]
    g[:] = 0.0
    ctrl = (Ur[:3] @ B0).T.reshape(-1)
    g[: ctrl.size] = ctrl
    if U.shape[1] > 3:
        g[nuis_cols] += Ur[3:].sum(axis=1)


_WARM = False


def warm() -> None:
    """Compile (or load from the cache) every kernel for the argument types the window problem passes: once per
    process, at the estimator's construction; later calls return at once."""
    global _WARM
    if _WARM:
        return
    F, count = 6, 5
    index = np.minimum(np.arange(F)[:, None] // 3 + np.arange(4)[None, :], count - 1).astype(np.intp)
    w0 = np.full((F, 4), 0.25)
    c = np.ones((count, 3))
    p_cam_T = np.zeros((3, F))
    R_T = np.zeros((3, 3, F))
    R_T[0, 0] = R_T[1, 1] = R_T[2, 2] = 1.0
    xy_T, sT, dt = np.zeros((2, F)), np.ones((2, F)), np.zeros(F)
    nuis = np.arange(3 * count, 3 * count + 9, dtype=np.intp)
    U = np.zeros((2, 12, F))
    X, los, r = np.empty((3, F)), np.empty((3, F)), np.empty(2 * F)
    for jacobian in (True, False):
        linearise_measurements(
            c, index, w0, p_cam_T, np.zeros(3), np.zeros(3), dt, np.eye(3), R_T, xy_T, sT, jacobian, X, los, r, U
        )
    n = 3 * count + 9
    measurement_gram(U, index, w0, nuis, np.zeros((n, n)), np.empty((n, n)))
    measurement_gradient(U, r, index, w0, nuis, np.empty(n))
    G = 3 * (count - 3)
    Bq = np.ones((G, count))
    A = np.ones((9, 9))
    add_turn_prior_gram(np.zeros((n, n)), A, A, A, 0.1, Bq, Bq, np.ones(G), np.ones(G), np.ones(3 * G), 3 * count)
    add_turn_prior_transpose(Bq, Bq, np.ones(G), np.ones(G), np.ones(3 * G), 0.1, np.zeros(3 * count))
    for jacobian in (True, False):
        turn_prior_rows(Bq, Bq, np.ones(G), np.ones(G), c, 0.1, np.empty(3 * G), np.zeros(3 * G), jacobian)
    for size in (n, 0):  # the solver's scaling (a gradient), the factor's (none)
        scale_normal_equations(np.eye(n), np.ones(size))
    _WARM = True
