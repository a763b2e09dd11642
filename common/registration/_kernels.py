"""Numba kernels behind the pseudo-distance: exact field sums, the split (far/near) kernel, the
cloud-in-cell deposit, trilinear interpolation and the near-field correction.

The *field* of a population B at a point q is S_B(q) = Σⱼ w_j / (ε + |q − b_j|).  The fast evaluator
splits the kernel K(r) = 1/(ε + r) into a smooth far part K_far (equal to K beyond a cut-off radius
r_c, a quadratic in r² inside it, matching value and slope at r_c) and a compact near part
K − K_far (zero beyond r_c).  The far part is convolved on a grid by FFT; the near part is summed
exactly over B's neighbours found through a cell list of cell size r_c.
"""
from __future__ import annotations

import numpy as np
from numba import njit, prange


# ---------------------------------------------------------------------------------------- kernels
@njit(cache=True, inline="always")
def k_exact(r, eps):
    return 1.0 / (eps + r)


@njit(cache=True, inline="always")
def dk_exact(r, eps):
    d = eps + r
    return -1.0 / (d * d)


@njit(cache=True, inline="always")
def k_far(r, eps, rc):
    if r >= rc:
        return 1.0 / (eps + r)
    d = eps + rc
    return 1.0 / d - (r * r - rc * rc) / (2.0 * rc * d * d)


@njit(cache=True, inline="always")
def dk_far(r, eps, rc):
    if r >= rc:
        d = eps + r
        return -1.0 / (d * d)
    d = eps + rc
    return -r / (rc * d * d)


@njit(cache=True)
def far_kernel_grid(shape0, shape1, shape2, h, eps, rc):
    """K_far sampled on the circular offset layout of an FFT of the given shape."""
    out = np.empty((shape0, shape1, shape2))
    for i in range(shape0):
        oi = i if i <= shape0 // 2 else i - shape0
        for j in range(shape1):
            oj = j if j <= shape1 // 2 else j - shape1
            for k in range(shape2):
                ok = k if k <= shape2 // 2 else k - shape2
                r = h * np.sqrt(oi * oi + oj * oj + ok * ok)
                out[i, j, k] = k_far(r, eps, rc)
    return out


# ------------------------------------------------------------------------------------- exact sums
@njit(cache=True, parallel=True)
def exact_field(Q, B, wb, eps):
    """S_B and ∇S_B at every row of Q, summed over all of B (float64, parallel over Q)."""
    n = Q.shape[0]
    S = np.zeros(n)
    G = np.zeros((n, 3))
    for i in prange(n):
        s = 0.0
        gx = 0.0
        gy = 0.0
        gz = 0.0
        qx, qy, qz = Q[i, 0], Q[i, 1], Q[i, 2]
        for j in range(B.shape[0]):
            dx = qx - B[j, 0]
            dy = qy - B[j, 1]
            dz = qz - B[j, 2]
            r = np.sqrt(dx * dx + dy * dy + dz * dz)
            d = eps + r
            s += wb[j] / d
            if r > 1e-300:
                f = -wb[j] / (d * d * r)
                gx += f * dx
                gy += f * dy
                gz += f * dz
        S[i] = s
        G[i, 0] = gx
        G[i, 1] = gy
        G[i, 2] = gz
    return S, G


@njit(cache=True, parallel=True)
def exact_field_value(Q, B, wb, eps):
    """S_B at every row of Q (value only, parallel over Q)."""
    n = Q.shape[0]
    S = np.zeros(n)
    for i in prange(n):
        s = 0.0
        qx, qy, qz = Q[i, 0], Q[i, 1], Q[i, 2]
        for j in range(B.shape[0]):
            dx = qx - B[j, 0]
            dy = qy - B[j, 1]
            dz = qz - B[j, 2]
            s += wb[j] / (eps + np.sqrt(dx * dx + dy * dy + dz * dz))
        S[i] = s
    return S


# ----------------------------------------------------------------------------------- grid building
@njit(cache=True, error_model="numpy")
def cic_deposit(P, w, lo, h, shape):
    """Cloud-in-cell (trilinear) deposit of weights w at points P onto a grid starting at lo."""
    rho = np.zeros((shape[0], shape[1], shape[2]))
    for j in range(P.shape[0]):
        fx = (P[j, 0] - lo[0]) / h
        fy = (P[j, 1] - lo[1]) / h
        fz = (P[j, 2] - lo[2]) / h
        ix = min(max(int(np.floor(fx)), 0), shape[0] - 2)
        iy = min(max(int(np.floor(fy)), 0), shape[1] - 2)
        iz = min(max(int(np.floor(fz)), 0), shape[2] - 2)
        tx = fx - ix
        ty = fy - iy
        tz = fz - iz
        for a in range(2):
            wx = tx if a else 1.0 - tx
            for b in range(2):
                wy = ty if b else 1.0 - ty
                for c in range(2):
                    wz = tz if c else 1.0 - tz
                    rho[ix + a, iy + b, iz + c] += w[j] * wx * wy * wz
    return rho


@njit(cache=True, error_model="numpy")
def build_cells(B, wb, lo, cell, dims):
    """3-D cell list of B: flies sorted by cell (x-major, then y, then z), as float32 SoA.

    Returns (Bs (3, p) float32 coordinates relative to `lo`, their weights (p,) float32, start
    (n_cells + 1,) int32 offsets).  Cells of one x-y column are consecutive, so the flies of a z-range
    of cells in a column are one contiguous run: a query reads 2 offsets per column and scans a
    contiguous, vectorisable run (the earlier x-y column list binary-searched z in every column, and
    that search cost more than the distances it saved).
    """
    p = B.shape[0]
    ncell = dims[0] * dims[1] * dims[2]
    cid = np.empty(p, dtype=np.int64)
    for j in range(p):
        cx = min(max(int(np.floor((B[j, 0] - lo[0]) / cell)), 0), dims[0] - 1)
        cy = min(max(int(np.floor((B[j, 1] - lo[1]) / cell)), 0), dims[1] - 1)
        cz = min(max(int(np.floor((B[j, 2] - lo[2]) / cell)), 0), dims[2] - 1)
        cid[j] = (cx * dims[1] + cy) * dims[2] + cz
    start = np.zeros(ncell + 1, dtype=np.int32)
    for j in range(p):
        start[cid[j] + 1] += 1
    for c in range(ncell):
        start[c + 1] += start[c]
    fill = start[:-1].copy()
    Bs = np.empty((3, p), dtype=np.float32)
    ws = np.empty(p, dtype=np.float32)
    for j in range(p):
        k = fill[cid[j]]
        fill[cid[j]] += 1
        Bs[0, k] = B[j, 0] - lo[0]
        Bs[1, k] = B[j, 1] - lo[1]
        Bs[2, k] = B[j, 2] - lo[2]
        ws[k] = wb[j]
    return Bs, ws, start


# ------------------------------------------------------------------------------------- evaluation
@njit(cache=True, error_model="numpy")
def _cr_weights(t):
    """Catmull-Rom weights of nodes -1, 0, 1, 2 at fraction t, and their derivatives."""
    t2 = t * t
    t3 = t2 * t
    w0 = 0.5 * (-t3 + 2.0 * t2 - t)
    w1 = 0.5 * (3.0 * t3 - 5.0 * t2 + 2.0)
    w2 = 0.5 * (-3.0 * t3 + 4.0 * t2 + t)
    w3 = 0.5 * (t3 - t2)
    d0 = 0.5 * (-3.0 * t2 + 4.0 * t - 1.0)
    d1 = 0.5 * (9.0 * t2 - 10.0 * t)
    d2 = 0.5 * (-9.0 * t2 + 8.0 * t + 1.0)
    d3 = 0.5 * (3.0 * t2 - 2.0 * t)
    return (w0, w1, w2, w3), (d0, d1, d2, d3)


@njit(cache=True, error_model="numpy")
def _interp(grid, lo, h, qx, qy, qz, want_grad):
    """Tricubic (Catmull-Rom) value of `grid` at q and its analytic gradient; inside flag.

    Catmull-Rom interpolates the nodes and reproduces quadratics, so unlike trilinear interpolation
    it adds no smoothing bias, and its gradient is continuous (good for the optimiser).
    """
    n0, n1, n2 = grid.shape
    fx = (qx - lo[0]) / h
    fy = (qy - lo[1]) / h
    fz = (qz - lo[2]) / h
    if not (fx >= 1.0 and fy >= 1.0 and fz >= 1.0 and fx <= n0 - 2 and fy <= n1 - 2 and fz <= n2 - 2):
        return False, 0.0, 0.0, 0.0, 0.0
    ix = min(int(fx), n0 - 3)
    iy = min(int(fy), n1 - 3)
    iz = min(int(fz), n2 - 3)
    wx, dwx = _cr_weights(fx - ix)
    wy, dwy = _cr_weights(fy - iy)
    wz, dwz = _cr_weights(fz - iz)
    s = 0.0
    gx = 0.0
    gy = 0.0
    gz = 0.0
    for a in range(4):
        sa = 0.0
        ga_y = 0.0
        ga_z = 0.0
        for b in range(4):
            sb = 0.0
            gb_z = 0.0
            for c in range(4):
                v = grid[ix - 1 + a, iy - 1 + b, iz - 1 + c]
                sb += wz[c] * v
                if want_grad:
                    gb_z += dwz[c] * v
            sa += wy[b] * sb
            if want_grad:
                ga_y += dwy[b] * sb
                ga_z += wy[b] * gb_z
        s += wx[a] * sa
        if want_grad:
            gx += dwx[a] * sa
            gy += wx[a] * ga_y
            gz += wx[a] * ga_z
    return True, s, gx / h, gy / h, gz / h


@njit(cache=True, fastmath=True, error_model="numpy")
def _near_at(qx, qy, qz, Bs, wbs, start, clo, cell, dims, eps, rc, want_grad):
    """Σ_j w_j (K − K_far)(|q − b_j|) over B's flies within r_c of q, and its gradient.

    K − K_far is a compact bump (1/ε − K_far(0) at 0, zero with zero slope at r_c): the near-field
    correction of the fast δ, and on its own the kernel of the local correlation objective.
    Float32 inside (coordinates relative to the cell list's corner: ≈1e-6 relative error per term),
    accumulated per run into float64.
    """
    s = 0.0
    dx = 0.0
    dy = 0.0
    dz = 0.0
    px = qx - clo[0]
    py = qy - clo[1]
    pz = qz - clo[2]
    rc2 = rc * rc
    x0 = max(int(np.floor((px - rc) / cell)), 0)
    x1 = min(int(np.floor((px + rc) / cell)), dims[0] - 1)
    y0 = max(int(np.floor((py - rc) / cell)), 0)
    y1 = min(int(np.floor((py + rc) / cell)), dims[1] - 1)
    if x0 > x1 or y0 > y1 or pz + rc < 0.0 or pz - rc > dims[2] * cell:
        return s, dx, dy, dz
    dc = eps + rc
    kc = np.float32(1.0 / dc)                    # K(r_c)
    c1 = np.float32(1.0 / (2.0 * rc * dc * dc))  # K_far(r) = kc − (r² − r_c²)·c1 inside r_c
    c2 = np.float32(1.0 / (rc * dc * dc))        # −K_far'(r)/r inside r_c
    e32 = np.float32(eps)
    r32 = np.float32(rc2)
    fx = np.float32(px)
    fy = np.float32(py)
    fz = np.float32(pz)
    nz = dims[2]
    bx = Bs[0]
    by = Bs[1]
    bz = Bs[2]
    for ax in range(x0, x1 + 1):
        ddx = max(ax * cell - px, px - (ax + 1) * cell, 0.0)
        for ay in range(y0, y1 + 1):
            ddy = max(ay * cell - py, py - (ay + 1) * cell, 0.0)
            d2 = ddx * ddx + ddy * ddy
            if d2 >= rc2:
                continue
            rz = np.sqrt(rc2 - d2)
            z0 = max(int(np.floor((pz - rz) / cell)), 0)
            z1 = min(int(np.floor((pz + rz) / cell)), nz - 1)
            if z0 > z1:
                continue
            base = (ax * dims[1] + ay) * nz
            ja = np.uint64(start[base + z0])
            jb = np.uint64(start[base + z1 + 1])
            # Branch-free body over a contiguous SoA run: LLVM vectorises it.  Inside r_c, K_far is
            # a polynomial in r², so only K itself needs the square root.
            ss = np.float32(0.0)
            sx = np.float32(0.0)
            sy = np.float32(0.0)
            sz = np.float32(0.0)
            for j in range(ja, jb):
                ex = fx - bx[j]
                ey = fy - by[j]
                ez = fz - bz[j]
                r2 = ex * ex + ey * ey + ez * ez
                w = wbs[j] if r2 < r32 else np.float32(0.0)
                r = np.sqrt(r2)
                inv = np.float32(1.0) / (e32 + r)
                ss += w * (inv - (kc - (r2 - r32) * c1))
                if want_grad:
                    f = w * (c2 - inv * inv / max(r, np.float32(1e-12)))
                    sx += f * ex
                    sy += f * ey
                    sz += f * ez
            s += ss
            if want_grad:
                dx += sx
                dy += sy
                dz += sz
    return s, dx, dy, dz


@njit(cache=True, error_model="numpy")
def _field_at(qx, qy, qz, grid, lo, h, B, wb, eps, rc, Bs, wbs, start, clo, cell,
              dims, near, want_grad):
    """Fast S_B(q) and ∇S_B(q): far field from the grid + exact near correction.

    Points outside the grid fall back to the exact sum over all of B (correct, slower).
    """
    inside, s, dx, dy, dz = _interp(grid, lo, h, qx, qy, qz, want_grad)
    if not inside:
        s = 0.0
        dx = 0.0
        dy = 0.0
        dz = 0.0
        for j in range(B.shape[0]):
            ex = qx - B[j, 0]
            ey = qy - B[j, 1]
            ez = qz - B[j, 2]
            r = np.sqrt(ex * ex + ey * ey + ez * ez)
            d = eps + r
            s += wb[j] / d
            if want_grad and r > 1e-300:
                f = -wb[j] / (d * d * r)
                dx += f * ex
                dy += f * ey
                dz += f * ez
        return s, dx, dy, dz, True
    if near:
        ns, nx, ny, nz = _near_at(qx, qy, qz, Bs, wbs, start, clo, cell, dims, eps, rc, want_grad)
        s += ns
        dx += nx
        dy += ny
        dz += nz
    return s, dx, dy, dz, False


@njit(cache=True, parallel=True, error_model="numpy")
def fast_field(Q, grid, lo, h, B, wb, eps, rc, Bs, wbs, start, clo, cell, dims, near, want_grad):
    """S_B and ∇S_B at every row of Q (parallel over Q); also how many rows fell outside the grid."""
    n = Q.shape[0]
    S = np.empty(n)
    G = np.zeros((n, 3))
    outside = np.zeros(n, dtype=np.bool_)
    for i in prange(n):
        s, dx, dy, dz, out = _field_at(Q[i, 0], Q[i, 1], Q[i, 2], grid, lo, h, B, wb,
                                       eps, rc, Bs, wbs, start, clo, cell, dims, near, want_grad)
        S[i] = s
        G[i, 0] = dx
        G[i, 1] = dy
        G[i, 2] = dz
        outside[i] = out
    return S, G, outside.sum()


@njit(cache=True, error_model="numpy")
def fast_field_serial(Q, grid, lo, h, B, wb, eps, rc, Bs, wbs, start, clo, cell, dims, near, want_grad):
    """S_B and ∇S_B at every row of Q (serial: predictable on a busy machine); also how many rows fell outside the grid."""
    n = Q.shape[0]
    S = np.empty(n)
    G = np.zeros((n, 3))
    outside = np.zeros(n, dtype=np.bool_)
    for i in range(n):
        s, dx, dy, dz, out = _field_at(Q[i, 0], Q[i, 1], Q[i, 2], grid, lo, h, B, wb,
                                       eps, rc, Bs, wbs, start, clo, cell, dims, near, want_grad)
        S[i] = s
        G[i, 0] = dx
        G[i, 1] = dy
        G[i, 2] = dz
        outside[i] = out
    return S, G, outside.sum()


@njit(cache=True, error_model="numpy")
def batch_delta(A, wa, Rs, ts, grid, lo, h, B, wb, eps, rc, Bs, wbs, start, clo, cell, dims,
                near):
    """Σᵢ wa_i / S_B(Rᵀ(a_i − t)) for every candidate (R, t): the un-normalised δ(A, f(B)).

    Serial: on the shared 2-core machine parallel threads stall whenever another process holds a
    core (measured 10× slower), and the lattice is small.  Used by the coarse global search.
    """
    m = Rs.shape[0]
    out = np.empty(m)
    for k in prange(m):
        R = Rs[k]
        t = ts[k]
        acc = 0.0
        for i in range(A.shape[0]):
            ex = A[i, 0] - t[0]
            ey = A[i, 1] - t[1]
            ez = A[i, 2] - t[2]
            qx = R[0, 0] * ex + R[1, 0] * ey + R[2, 0] * ez
            qy = R[0, 1] * ex + R[1, 1] * ey + R[2, 1] * ez
            qz = R[0, 2] * ex + R[1, 2] * ey + R[2, 2] * ez
            s, dx, dy, dz, o = _field_at(qx, qy, qz, grid, lo, h, B, wb, eps, rc,
                                         Bs, wbs, start, clo, cell, dims, near, False)
            acc += wa[i] / s
        out[k] = acc
    return out


@njit(cache=True, error_model="numpy")
def near_field(Q, Bs, wbs, start, clo, cell, dims, eps, rc, want_grad):
    """The near sum of `_near_at` at every row of Q (serial), with gradients (n, 3)."""
    n = Q.shape[0]
    S = np.empty(n)
    G = np.zeros((n, 3))
    for i in range(n):
        s, dx, dy, dz = _near_at(Q[i, 0], Q[i, 1], Q[i, 2], Bs, wbs, start, clo, cell, dims, eps, rc,
                                 want_grad)
        S[i] = s
        G[i, 0] = dx
        G[i, 1] = dy
        G[i, 2] = dz
    return S, G


@njit(cache=True, error_model="numpy")
def batch_near(A, wa, Rs, ts, Bs, wbs, start, clo, cell, dims, eps, rc):
    """Σᵢ wa_i · near-sum(Rᵀ(a_i − t)) for every candidate (R, t) (serial, see batch_delta)."""
    m = Rs.shape[0]
    out = np.empty(m)
    for k in prange(m):
        R = Rs[k]
        t = ts[k]
        acc = 0.0
        for i in range(A.shape[0]):
            ex = A[i, 0] - t[0]
            ey = A[i, 1] - t[1]
            ez = A[i, 2] - t[2]
            qx = R[0, 0] * ex + R[1, 0] * ey + R[2, 0] * ez
            qy = R[0, 1] * ex + R[1, 1] * ey + R[2, 1] * ez
            qz = R[0, 2] * ex + R[1, 2] * ey + R[2, 2] * ez
            s, dx, dy, dz = _near_at(qx, qy, qz, Bs, wbs, start, clo, cell, dims, eps, rc, False)
            acc += wa[i] * s
        out[k] = acc
    return out
