"""WGS-84 against its published values (NIMA TR8350.2, 3rd ed., Tables 3.1–3.5).

Every expected number here is a literal from the standard, never a value
computed by covtool: a 0.01 m/s² error in equatorial gravity, a wrong
Somigliana constant or a spherical radius fails these tests.
"""

import numpy as np
import pytest

from covtool.nav import earth

# TR8350.2 Table 3.1 (defining) and Table 3.3/3.4 (derived) parameters
A = 6378137.0                        # semi-major axis [m]
B = 6356752.3142                     # semi-minor axis [m]
E2 = 6.69437999014e-3                # first eccentricity squared
OMEGA = 7292115.0e-11                # Earth rotation rate [rad/s]
GAMMA_E = 9.7803253359               # normal gravity at the equator [m/s²]
GAMMA_P = 9.8321849378               # normal gravity at the poles [m/s²]
GAMMA_MEAN = 9.7976432222            # surface mean of normal gravity [m/s²]
POLAR_RADIUS_OF_CURVATURE = 6399593.6258   # c = a²/b [m]
AREA = 5.10065621724e14              # ellipsoid surface area [m²]
M = 0.00344978650684                 # ω²a²b/GM


def test_defining_and_derived_constants():
    assert earth.A == A
    assert earth.B == pytest.approx(B, abs=1e-4)
    assert earth.E2 == pytest.approx(E2, rel=1e-11)
    assert earth.OMEGA_IE == OMEGA
    assert earth.M_RATIO == pytest.approx(M, rel=1e-11)


def test_normal_gravity_at_equator_and_poles():
    assert earth.gravity(0.0, 0.0) == pytest.approx(GAMMA_E, abs=1e-10)
    assert earth.gravity(np.pi / 2, 0.0) == pytest.approx(GAMMA_P, abs=1e-9)
    assert earth.gravity(-np.pi / 2, 0.0) == pytest.approx(GAMMA_P, abs=1e-9)


def test_surface_mean_of_normal_gravity():
    """The area-weighted mean over the ellipsoid tests the whole latitude law."""
    x, w = np.polynomial.legendre.leggauss(200)
    lat, w = 0.5 * np.pi * x, 0.5 * np.pi * w
    rm, rn = earth.radii(lat)
    dS = rm * rn * np.cos(lat)                       # area element per dL dl
    assert 2 * np.pi * np.sum(w * dS) == pytest.approx(AREA, rel=1e-10)
    assert np.sum(w * dS * earth.gravity(lat, 0.0)) / np.sum(w * dS) == pytest.approx(GAMMA_MEAN, abs=1e-9)


def test_radii_of_curvature():
    rm, rn = earth.radii(0.0)
    assert rm == pytest.approx(B**2 / A, abs=1e-3)       # 6 335 439.327 m
    assert rn == pytest.approx(A, abs=1e-6)
    rm, rn = earth.radii(np.pi / 2)
    assert rm == pytest.approx(POLAR_RADIUS_OF_CURVATURE, abs=1e-3)
    assert rn == pytest.approx(POLAR_RADIUS_OF_CURVATURE, abs=1e-3)


def test_free_air_gradient():
    """TR8350.2 eq (4-3): −2γ/a(1 + f + m − 2f sin²L) at h = 0, about −0.3086 mGal/m."""
    f = 1 / 298.257223563
    for lat in (0.0, np.pi / 4, np.pi / 2):
        g0 = earth.gravity(lat, 0.0)
        expected = -2 * g0 / A * (1 + f + M - 2 * f * np.sin(lat) ** 2)
        assert earth.gravity_derivatives(lat, 0.0)[1] == pytest.approx(expected, rel=1e-12)
    assert earth.gravity_derivatives(np.pi / 4, 0.0)[1] * 1e5 == pytest.approx(-0.3086, abs=5e-4)
    # the second-order term: 3γh²/a² at 10 km
    h = 1.0e4
    lin = earth.gravity(0.0, 0.0) * (1 - 2 * h / A * (1 + f + M))
    assert earth.gravity(0.0, h) - lin == pytest.approx(3 * GAMMA_E * h * h / A**2, rel=1e-9)


def test_ecef_of_cardinal_points():
    np.testing.assert_allclose(earth.llh_to_ecef(0.0, 0.0, 0.0), [A, 0, 0], atol=1e-6)
    np.testing.assert_allclose(earth.llh_to_ecef(0.0, np.pi / 2, 100.0), [0, A + 100, 0], atol=1e-6)
    np.testing.assert_allclose(earth.llh_to_ecef(np.pi / 2, 0.3, 0.0), [0, 0, B], atol=1e-4)


def test_earth_rate_vector():
    lat = np.deg2rad(37.5)
    w = earth.earth_rate_n(lat)
    np.testing.assert_allclose(w, [OMEGA * np.cos(lat), 0.0, -OMEGA * np.sin(lat)], rtol=1e-15)
