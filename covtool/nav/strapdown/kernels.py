"""Compiled numba kernels of the strapdown (issue 13).

The arithmetic of :func:`covtool.nav.strapdown.mechanization._nav_core`
written for scalars (seed 001, eq (1)–(4) for the coning and sculling) and
compiled with ``numba.njit(cache=True)``, so a navigation step costs tens of
nanoseconds per run; used by :func:`covtool.nav.strapdown.run` over whole
records.
"""
from __future__ import annotations

import math

import numba

from covtool.nav import earth


#: compiled kernels: cached on disk so the compile cost is paid once per installation
_njit = numba.njit(cache=True, nogil=True)
_OMEGA_IE, _E2, _A, _GAMMA_E = earth.OMEGA_IE, earth.E2, earth.A, earth.GAMMA_E
_K_SOM, _F, _M_RATIO = earth.K_SOMIGLIANA, earth.F, earth.M_RATIO


# --------------------------------------------------------------------------
# compiled kernel (issue 13): the navigation-frame update of many steps and runs
# --------------------------------------------------------------------------
# The same arithmetic as _nav_core, written for scalars and compiled with numba, so a
# navigation step costs tens of nanoseconds per run instead of one Python call of ~270 µs
# for the whole ensemble.  _nav_core stays the reference (tests compare the two).


@_njit
def _store_state(dst, lat, lon, h, vn, ve, vd, q0, q1, q2, q3):
    """Write one navigation state (lat, lon, h, v_NED, q_nb) into ``dst``, shape (10,)."""
    dst[0], dst[1], dst[2] = lat, lon, h
    dst[3], dst[4], dst[5] = vn, ve, vd
    dst[6], dst[7], dst[8], dst[9] = q0, q1, q2, q3


@_njit
def _nav_core_scalar(lat, lon, h, vn, ve, vd, q0, q1, q2, q3, b0, b1, b2, b3, ux, uy, uz, rx, ry, rz, T):
    W = _OMEGA_IE
    # C(q) u = u + q0 t + qv × t, t = 2 qv × u
    tx = 2.0 * (q2 * uz - q3 * uy)
    ty = 2.0 * (q3 * ux - q1 * uz)
    tz = 2.0 * (q1 * uy - q2 * ux)
    nx = ux + q0 * tx + (q2 * tz - q3 * ty)
    ny = uy + q0 * ty + (q3 * tx - q1 * tz)
    nz = uz + q0 * tz + (q1 * ty - q2 * tx)
    # predictor with the start-of-interval rates
    la, hh = lat, h
    wn_, we_, wd_ = vn, ve, vd
    for it in range(2):
        sl = math.sin(la)
        cl = math.cos(la)
        s2 = sl * sl
        w = 1.0 - _E2 * s2
        sw = math.sqrt(w)
        rnh = _A / sw + hh
        rmh = _A * (1.0 - _E2) / (w * sw) + hh
        g0 = _GAMMA_E * (1.0 + _K_SOM * s2) / sw
        g = g0 * (1.0 - 2.0 * hh / _A * (1.0 + _F + _M_RATIO - 2.0 * _F * s2) + 3.0 * hh * hh / (_A * _A))
        t_ = sl / cl
        zn = (W * cl + we_ / rnh) * T
        ze = (-wn_ / rmh) * T
        zd = (-W * sl - we_ * t_ / rnh) * T
        cn = zn + W * cl * T
        ce = ze
        cd = zd - W * sl * T
        gc0 = -(ce * wd_ - cd * we_)
        gc1 = -(cd * wn_ - cn * wd_)
        gc2 = -(cn * we_ - ce * wn_) + g * T
        v1n = vn + nx - 0.5 * (ze * nz - zd * ny) + gc0
        v1e = ve + ny - 0.5 * (zd * nx - zn * nz) + gc1
        v1d = vd + nz - 0.5 * (zn * ny - ze * nx) + gc2
        if it == 0:
            la = lat + 0.25 * T * (vn + v1n) / rmh
            hh = h - 0.25 * T * (vd + v1d)
            wn_ = 0.5 * (vn + v1n)
            we_ = 0.5 * (ve + v1e)
            wd_ = 0.5 * (vd + v1d)
    tx = 2.0 * (q2 * rz - q3 * ry)
    ty = 2.0 * (q3 * rx - q1 * rz)
    tz = 2.0 * (q1 * ry - q2 * rx)
    rn_ = rx + q0 * tx + (q2 * tz - q3 * ty)
    re_ = ry + q0 * ty + (q3 * tx - q1 * tz)
    rd_ = rz + q0 * tz + (q1 * ty - q2 * tx)
    rn_ = rn_ - (ze * nz - zd * ny) / 6.0
    re_ = re_ - (zd * nx - zn * nz) / 6.0
    rd_ = rd_ - (zn * ny - ze * nx) / 6.0
    dN = T * (vn + rn_ + 0.5 * gc0)
    dE = T * (ve + re_ + 0.5 * gc1)
    dD = T * (vd + rd_ + 0.5 * gc2)
    lat1 = lat + dN / rmh
    lon1 = lon + dE / (rnh * cl)
    h1 = h - dD
    p0 = q0 * b0 - q1 * b1 - q2 * b2 - q3 * b3
    p1 = q0 * b1 + q1 * b0 + q2 * b3 - q3 * b2
    p2 = q0 * b2 - q1 * b3 + q2 * b0 + q3 * b1
    p3 = q0 * b3 + q1 * b2 - q2 * b1 + q3 * b0
    r0 = 1.0 - (zn * zn + ze * ze + zd * zd) / 8.0
    an, ae, ad = -0.5 * zn, -0.5 * ze, -0.5 * zd
    s0 = r0 * p0 - an * p1 - ae * p2 - ad * p3
    s1 = r0 * p1 + an * p0 + ae * p3 - ad * p2
    s2_ = r0 * p2 - an * p3 + ae * p0 + ad * p1
    s3 = r0 * p3 + an * p2 - ae * p1 + ad * p0
    k = 1.0 / math.sqrt(s0 * s0 + s1 * s1 + s2_ * s2_ + s3 * s3)
    return lat1, lon1, h1, v1n, v1e, v1d, s0 * k, s1 * k, s2_ * k, s3 * k


@_njit
def _nav_loop(x, qb, ub, rb, T, every, offset, out):
    """Advance ``x`` (10, R) in place over S steps, keeping every ``every``-th.

    ``qb`` (4, Rb, S), ``ub`` and ``rb`` (3, Rb, S) with Rb = R or 1 (shared by
    the runs).  Step j is global step ``offset + j + 1``; when that is a
    multiple of ``every`` the state after it goes to ``out[:, :, i]``, i
    counting the kept steps of this call from 0.
    """
    R = x.shape[1]
    S = qb.shape[2]
    shared = qb.shape[1] == 1
    for m in range(R):
        mb = 0 if shared else m
        lat, lon, h = x[0, m], x[1, m], x[2, m]
        vn, ve, vd = x[3, m], x[4, m], x[5, m]
        q0, q1, q2, q3 = x[6, m], x[7, m], x[8, m], x[9, m]
        for j in range(S):
            lat, lon, h, vn, ve, vd, q0, q1, q2, q3 = _nav_core_scalar(
                lat, lon, h, vn, ve, vd, q0, q1, q2, q3,
                qb[0, mb, j], qb[1, mb, j], qb[2, mb, j], qb[3, mb, j],
                ub[0, mb, j], ub[1, mb, j], ub[2, mb, j], rb[0, mb, j], rb[1, mb, j], rb[2, mb, j], T)
            if (offset + j + 1) % every == 0:
                o = (offset + j + 1) // every - offset // every - 1
                _store_state(out[:, m, o], lat, lon, h, vn, ve, vd, q0, q1, q2, q3)
        _store_state(x[:, m], lat, lon, h, vn, ve, vd, q0, q1, q2, q3)


_F8 = numba.float64
_IN3 = numba.types.Array(_F8, 3, "A", readonly=True)       # increments: any strides, views, read-only
_IN1 = numba.types.Array(_F8, 1, "A", readonly=True)
_ROWS = numba.types.Array(numba.int64, 1, "A", readonly=True)
#: the one compiled signature of _strapdown_loop: strided and read-only increments are taken as they are
#: (no contiguous copy of a record or of each epoch's slice of it), and one specialisation is compiled
_STRAPDOWN_SIG = numba.void(_F8[:, :], _IN3, _IN3, _ROWS, _F8[:, :], _F8[:, :], numba.int64, _IN1, _F8,
                            numba.int64, numba.int64, _F8[:, :, :])


@numba.njit([_STRAPDOWN_SIG], cache=True, nogil=True)
def _strapdown_loop(x, dth, dv, rows, prev_th, prev_dv, n, wc, T, every, offset, out):
    """The whole strapdown step (:func:`step`) over a record, compiled.

    ``x`` (10, R) advanced in place; ``dth``, ``dv`` (Rb, K, 3) with K = S·n,
    run m driven by row ``rows[m]`` (e.g. one row shared by every run, or
    several runs on one row); ``prev_th``, ``prev_dv`` (R, 3) the
    sample before the record, overwritten with the last sample; ``wc`` the
    coning weights of :func:`covtool.nav.coning._weights`.  Body increments as
    :func:`covtool.nav.coning.body_increments` and
    :func:`~covtool.nav.coning.body_position_increment` (seed 001 eq (1)–(4)),
    rotation-vector quaternion as :func:`_rotvec_quat`, navigation update as
    :func:`_nav_core`; kept states as in :func:`_nav_loop`.
    """
    R = x.shape[1]
    S = dth.shape[1] // n
    for m in range(R):
        mb = rows[m]
        lat, lon, h = x[0, m], x[1, m], x[2, m]
        vn, ve, vd = x[3, m], x[4, m], x[5, m]
        q0, q1, q2, q3 = x[6, m], x[7, m], x[8, m], x[9, m]
        p0x, p0y, p0z = prev_th[m, 0], prev_th[m, 1], prev_th[m, 2]
        v0x, v0y, v0z = prev_dv[m, 0], prev_dv[m, 1], prev_dv[m, 2]
        for j in range(S):
            # coning and sculling, seed 001 eq (2), (4): A, B the weighted earlier samples
            Ax, Ay, Az = wc[0] * p0x, wc[0] * p0y, wc[0] * p0z
            Bx, By, Bz = wc[0] * v0x, wc[0] * v0y, wc[0] * v0z
            al0 = al1 = al2 = 0.0
            up0 = up1 = up2 = 0.0
            r0 = r1 = r2 = 0.0
            for i in range(n):
                a0, a1, a2 = dth[mb, j * n + i, 0], dth[mb, j * n + i, 1], dth[mb, j * n + i, 2]
                u0, u1, u2 = dv[mb, j * n + i, 0], dv[mb, j * n + i, 1], dv[mb, j * n + i, 2]
                if i < n - 1:
                    Ax += wc[i + 1] * a0
                    Ay += wc[i + 1] * a1
                    Az += wc[i + 1] * a2
                    Bx += wc[i + 1] * u0
                    By += wc[i + 1] * u1
                    Bz += wc[i + 1] * u2
                al0 += a0
                al1 += a1
                al2 += a2
                up0 += u0
                up1 += u1
                up2 += u2
                wr = (n - i - 0.5) / n
                r0 += wr * u0
                r1 += wr * u1
                r2 += wr * u2
            lx, ly, lz = a0, a1, a2          # last sample of the interval
            mx, my, mz = u0, u1, u2
            phx = al0 + (Ay * lz - Az * ly)
            phy = al1 + (Az * lx - Ax * lz)
            phz = al2 + (Ax * ly - Ay * lx)
            a2s = al0 * al0 + al1 * al1 + al2 * al2
            if a2s < 1e-6:
                c1 = 0.5 - a2s / 24.0 + a2s * a2s / 720.0
                c2 = 1.0 / 6.0 - a2s / 120.0 + a2s * a2s / 5040.0
            else:
                aa = math.sqrt(a2s)
                c1 = (1.0 - math.cos(aa)) / aa ** 2
                c2 = (aa - math.sin(aa)) / aa ** 3
            xu0 = al1 * up2 - al2 * up1
            xu1 = al2 * up0 - al0 * up2
            xu2 = al0 * up1 - al1 * up0
            xx0 = al1 * xu2 - al2 * xu1
            xx1 = al2 * xu0 - al0 * xu2
            xx2 = al0 * xu1 - al1 * xu0
            ux = up0 + c1 * xu0 + c2 * xx0 + (Ay * mz - Az * my) + (By * lz - Bz * ly)
            uy = up1 + c1 * xu1 + c2 * xx1 + (Az * mx - Ax * mz) + (Bz * lx - Bx * lz)
            uz = up2 + c1 * xu2 + c2 * xx2 + (Ax * my - Ay * mx) + (Bx * ly - By * lx)
            rx = r0 + xu0 / 6.0
            ry = r1 + xu1 / 6.0
            rz = r2 + xu2 / 6.0
            # exp(φ/2)
            f2 = phx * phx + phy * phy + phz * phz
            fa = math.sqrt(f2)
            b0 = math.cos(0.5 * fa)
            sf = 0.5 - f2 / 48.0 if f2 < 1e-8 else math.sin(0.5 * fa) / fa
            lat, lon, h, vn, ve, vd, q0, q1, q2, q3 = _nav_core_scalar(
                lat, lon, h, vn, ve, vd, q0, q1, q2, q3, b0, sf * phx, sf * phy, sf * phz,
                ux, uy, uz, rx, ry, rz, T)
            p0x, p0y, p0z = lx, ly, lz
            v0x, v0y, v0z = mx, my, mz
            if (offset + j + 1) % every == 0:
                o = (offset + j + 1) // every - offset // every - 1
                _store_state(out[:, m, o], lat, lon, h, vn, ve, vd, q0, q1, q2, q3)
        _store_state(x[:, m], lat, lon, h, vn, ve, vd, q0, q1, q2, q3)
        prev_th[m, 0], prev_th[m, 1], prev_th[m, 2] = p0x, p0y, p0z
        prev_dv[m, 0], prev_dv[m, 1], prev_dv[m, 2] = v0x, v0y, v0z
