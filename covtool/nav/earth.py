"""WGS-84 Earth model and the NED navigation frame.

This module owns every Earth constant and Earth-related formula in covtool.
All inputs and outputs are SI: latitude and longitude in [rad], height in [m],
velocities in [m/s], rates in [rad/s].  Every function broadcasts over arrays.

The navigation frame is local-level North-East-Down (NED).  Positions are
geodetic latitude ``L``, longitude ``l`` and height ``h`` above the ellipsoid.

References
----------
NIMA TR8350.2, "Department of Defense World Geodetic System 1984", 3rd ed.
D. H. Titterton and J. L. Weston, *Strapdown Inertial Navigation Technology*,
2nd ed., IEE, 2004, §3.7 (navigation equations) and §3.7.2 (gravity).
"""

from __future__ import annotations

import numpy as np

#: semi-major axis [m]
A = 6378137.0
#: flattening [-]
F = 1.0 / 298.257223563
#: first eccentricity squared [-]
E2 = F * (2.0 - F)
#: semi-minor axis [m]
B = A * (1.0 - F)
#: Earth rotation rate [rad/s]
OMEGA_IE = 7.292115e-5
#: Earth gravitational constant [m^3/s^2]
GM = 3.986004418e14
#: normal gravity at the equator [m/s^2]
GAMMA_E = 9.7803253359
#: Somigliana constant k = (b*gamma_p)/(a*gamma_e) - 1 [-]
K_SOMIGLIANA = 0.00193185265241
#: m = omega^2 a^2 b / GM [-]
M_RATIO = OMEGA_IE**2 * A**2 * B / GM


def _arr(x):
    """Array of float or complex (complex-step differentiation passes through)."""
    a = np.asarray(x)
    return a if np.iscomplexobj(a) else a.astype(float)


def radii(lat):
    """Meridian and transverse radii of curvature.

    Parameters
    ----------
    lat : array_like
        Geodetic latitude. [rad]

    Returns
    -------
    R_M, R_N : ndarray
        Meridian (north-south) and transverse (prime vertical) radii. [m]

    Notes
    -----
    ``R_M = a(1-e^2)/(1-e^2 sin^2 L)^{3/2}``, ``R_N = a/(1-e^2 sin^2 L)^{1/2}``.
    """
    s2 = np.sin(lat) ** 2
    w = 1.0 - E2 * s2
    return A * (1.0 - E2) / w**1.5, A / np.sqrt(w)


def radii_derivatives(lat):
    """Derivatives of the radii with respect to latitude [m/rad].

    Returns
    -------
    dR_M, dR_N : ndarray
        ``dR_M/dL`` and ``dR_N/dL``.
    """
    s, c = np.sin(lat), np.cos(lat)
    w = 1.0 - E2 * s * s
    return 3.0 * A * (1.0 - E2) * E2 * s * c / w**2.5, A * E2 * s * c / w**1.5


def gravity(lat, h):
    """Normal gravity magnitude, positive down, with altitude dependence.

    Parameters
    ----------
    lat : array_like
        Geodetic latitude. [rad]
    h : array_like
        Height above the ellipsoid. [m]

    Returns
    -------
    ndarray
        Normal gravity. [m/s^2]

    Notes
    -----
    Somigliana's closed form on the ellipsoid and the second-order free-air
    expansion of TR8350.2 eq (4-3)::

        g0(L) = g_e (1 + k sin^2 L) / sqrt(1 - e^2 sin^2 L)
        g(L,h) = g0(L) [1 - 2h/a (1 + f + m - 2 f sin^2 L) + 3 h^2/a^2]
    """
    s2 = np.sin(lat) ** 2
    g0 = GAMMA_E * (1.0 + K_SOMIGLIANA * s2) / np.sqrt(1.0 - E2 * s2)
    return g0 * (1.0 - 2.0 * h / A * (1.0 + F + M_RATIO - 2.0 * F * s2) + 3.0 * h * h / A**2)


def gravity_derivatives(lat, h):
    """Partial derivatives of :func:`gravity`.

    Returns
    -------
    dg_dlat : ndarray
        ``dg/dL`` [m/s^2/rad]
    dg_dh : ndarray
        ``dg/dh`` [1/s^2]; about ``-2 g / R``, the source of the vertical
        channel instability (seed 002, eq (4), term ``δg``).
    """
    s, c = np.sin(lat), np.cos(lat)
    s2 = s * s
    w = 1.0 - E2 * s2
    g0 = GAMMA_E * (1.0 + K_SOMIGLIANA * s2) / np.sqrt(w)
    dg0 = GAMMA_E * (2.0 * K_SOMIGLIANA * s * c / np.sqrt(w) + (1.0 + K_SOMIGLIANA * s2) * E2 * s * c / w**1.5)
    fac = 1.0 - 2.0 * h / A * (1.0 + F + M_RATIO - 2.0 * F * s2) + 3.0 * h * h / A**2
    dfac_dlat = 8.0 * F * s * c * h / A
    dfac_dh = -2.0 / A * (1.0 + F + M_RATIO - 2.0 * F * s2) + 6.0 * h / A**2
    return dg0 * fac + g0 * dfac_dlat, g0 * dfac_dh


def gravity_n(lat, h):
    """Normal gravity vector in NED, shape ``(..., 3)`` [m/s^2]."""
    g = _arr(gravity(lat, h))
    z = np.zeros_like(g)
    return np.stack([z, z, g], axis=-1)


def earth_rate_n(lat):
    """Earth rate ω_ie^n in NED, shape ``(..., 3)`` [rad/s]."""
    lat = _arr(lat)
    return np.stack([OMEGA_IE * np.cos(lat), np.zeros_like(lat), -OMEGA_IE * np.sin(lat)], axis=-1)


def transport_rate_n(lat, h, v_n):
    """Transport rate ω_en^n in NED, shape ``(..., 3)`` [rad/s].

    ``ω_en^n = [v_E/(R_N+h), -v_N/(R_M+h), -v_E tan L/(R_N+h)]``.
    """
    v_n = _arr(v_n)
    rm, rn = radii(lat)
    vn, ve = v_n[..., 0], v_n[..., 1]
    return np.stack([ve / (rn + h), -vn / (rm + h), -ve * np.tan(lat) / (rn + h)], axis=-1)


def position_rates(lat, h, v_n):
    """Rates of geodetic position (L̇, l̇, ḣ), shape ``(..., 3)``.

    ``L̇ = v_N/(R_M+h)``, ``l̇ = v_E/((R_N+h) cos L)``, ``ḣ = -v_D``.
    """
    v_n = _arr(v_n)
    rm, rn = radii(lat)
    return np.stack([v_n[..., 0] / (rm + h), v_n[..., 1] / ((rn + h) * np.cos(lat)), -v_n[..., 2]], axis=-1)


def velocity_rate(lat, h, v_n, f_n):
    """Navigation-frame velocity rate (the velocity equation, seed 002 eq (4) unperturbed).

    ``v̇^n = f^n - (2 ω_ie^n + ω_en^n) × v^n + g^n``.
    """
    w = 2.0 * earth_rate_n(lat) + transport_rate_n(lat, h, v_n)
    return f_n - np.cross(w, v_n) + gravity_n(lat, h)


def schuler_frequency(lat=np.pi / 4, h=0.0):
    """Schuler frequency sqrt(g/R) with R the geometric-mean radius [rad/s]."""
    rm, rn = radii(lat)
    return np.sqrt(gravity(lat, h) / np.sqrt((rm + h) * (rn + h)))


def llh_to_ecef(lat, lon, h):
    """Geodetic position to ECEF, shape ``(..., 3)`` [m]."""
    _, rn = radii(lat)
    cl = np.cos(lat)
    return np.stack([(rn + h) * cl * np.cos(lon), (rn + h) * cl * np.sin(lon), (rn * (1.0 - E2) + h) * np.sin(lat)], axis=-1)


def dcm_ecef_to_ned(lat, lon):
    """Direction cosine matrix C_e^n, shape ``(..., 3, 3)``."""
    sl, cl, so, co = np.sin(lat), np.cos(lat), np.sin(lon), np.cos(lon)
    return np.stack([
        np.stack([-sl * co, -sl * so, cl], axis=-1),
        np.stack([-so, co, np.zeros_like(so)], axis=-1),
        np.stack([-cl * co, -cl * so, -sl], axis=-1),
    ], axis=-2)
