"""The physical-navigation transform (covtool.lincov.dynamics.nav_error_matrix) against first principles.

Oracles, independent of the transform: the NED displacement between two
geodetic positions through ECEF (WGS-84, covtool.nav.earth.llh_to_ecef and
the ECEF→NED rotation), and the small rotation between two attitudes read
off ``Ĉ Cᵀ = I − [φ×]`` (error = computed − true, seed 002 eq (1)).
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from covtool.lincov.dynamics import nav_error_matrix
from covtool.nav import attitude as quat, earth

RNG = np.random.default_rng(12)


def _unit(q):
    return q / np.linalg.norm(q)


@pytest.mark.parametrize("lat_deg", [0.0, 36.37, -61.0, 80.0])
def test_position_rows_are_the_ned_displacement(lat_deg):
    lat, lon, h = math.radians(lat_deg), math.radians(127.36), 850.0
    d = np.array([3e-8, -5e-8, 0.4])                               # δL, δl [rad], δh [m]: decimetres
    q = _unit(RNG.standard_normal(4))
    T = nav_error_matrix(q, lat, h)
    x = np.zeros(10)
    x[:3] = d
    ecef = earth.llh_to_ecef(lat + d[0], lon + d[1], h + d[2]) - earth.llh_to_ecef(lat, lon, h)
    ned = earth.dcm_ecef_to_ned(lat, lon) @ ecef
    np.testing.assert_allclose(T[:3] @ x, ned, rtol=2e-6, atol=1e-9)


def test_attitude_rows_are_the_small_rotation_between_attitudes():
    for _ in range(20):
        q = _unit(RNG.standard_normal(4))
        dq = 1e-7 * RNG.standard_normal(4)                           # additive quaternion error
        A = quat.dcm(q + dq) @ quat.dcm(q).T                          # Ĉ Cᵀ = I − [φ×]
        S = np.eye(3) - A
        phi = 0.5 * np.array([S[2, 1] - S[1, 2], S[0, 2] - S[2, 0], S[1, 0] - S[0, 1]])
        x = np.zeros(10)
        x[6:] = dq
        got = nav_error_matrix(q, 0.3, 10.0)[6:] @ x
        np.testing.assert_allclose(got, phi, rtol=1e-5, atol=1e-14 * np.abs(phi).max())


def test_velocity_rows_and_the_unscaled_position_rows_are_identities():
    q = np.stack([_unit(RNG.standard_normal(4)) for _ in range(5)])
    T = nav_error_matrix(q)
    assert T.shape == (5, 9, 10)
    np.testing.assert_array_equal(T[:, :6, :6], np.broadcast_to(np.eye(6), (5, 6, 6)))
    np.testing.assert_array_equal(T[:, :6, 6:], 0.0)
    np.testing.assert_array_equal(T[:, 6:, :6], 0.0)
    # the quaternion-norm direction is structurally null: φ does not see q itself
    np.testing.assert_allclose(np.einsum("kij,kj->ki", T[:, 6:, 6:], q), 0.0, atol=1e-15)

