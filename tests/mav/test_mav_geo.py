"""Flight-data frames: geodetic <-> ENU, NED <-> ENU attitude, unknown attitudes passed through."""

from __future__ import annotations

import numpy as np
import pytest

pytest.importorskip("pymap3d")

from scipy.spatial.transform import Rotation  # noqa: E402

from stablecues.errors import InputError  # noqa: E402
from stablecues.geometry.rotations import (  # noqa: E402
    euler_zyx_to_quat,
    quat_from_rotvec,
    quat_slerp,
    quat_to_euler_zyx,
    quat_to_matrix,
)
from stablecues.mav import geo  # noqa: E402


def test_geo_round_trips() -> None:
    rng = np.random.default_rng(5)
    rpy = rng.uniform([-1, -1.2, -3], [1, 1.2, 3], size=(20, 3))
    q = euler_zyx_to_quat(rpy[:, 0], rpy[:, 1], rpy[:, 2])
    np.testing.assert_allclose(quat_to_euler_zyx(q), rpy, atol=1e-9)
    q_enu = geo.ned_to_enu_quat(q)
    np.testing.assert_allclose(quat_to_matrix(q_enu), geo.R_ENU_NED @ quat_to_matrix(q), atol=1e-12)
    np.testing.assert_allclose(quat_to_euler_zyx(geo.enu_to_ned_quat(q_enu)), rpy, atol=1e-9)
    enu = rng.normal(0, 100, (10, 3))
    llh = geo.enu_to_geodetic(enu, (52.8, -4.1, 20.0))
    np.testing.assert_allclose(
        geo.geodetic_to_enu(llh[:, 0], llh[:, 1], llh[:, 2], (52.8, -4.1, 20.0)), enu, atol=1e-6
    )
    # slerp half-way between identity and 90 deg about z is 45 deg about z
    qz = quat_from_rotvec(np.array([[0.0, 0.0, 0.0], [0.0, 0.0, np.pi / 2]]))
    mid = quat_slerp(np.array([0.0, 1.0]), qz, np.array([0.5]))
    np.testing.assert_allclose(mid[0], quat_from_rotvec(np.array([0.0, 0.0, np.pi / 4])), atol=1e-12)


def test_enu_ned_quaternion_is_the_matrix() -> None:
    np.testing.assert_allclose(quat_to_matrix(geo.Q_ENU_NED), geo.R_ENU_NED, atol=1e-15)
    np.testing.assert_allclose(geo.R_ENU_NED @ [1.0, 0.0, 0.0], [0.0, 1.0, 0.0])  # north is ENU y
    # a level body facing east (NED yaw 90 deg): its nose is ENU x, its (x, y, z, w) has w >= 0
    q = geo.ned_to_enu_quat(euler_zyx_to_quat(0.0, 0.0, np.pi / 2))
    np.testing.assert_allclose(quat_to_matrix(q)[:, 0], [1.0, 0.0, 0.0], atol=1e-12)
    assert q.shape == (4,) and q[3] >= 0


def test_unknown_attitudes_pass_through() -> None:
    q = np.array(
        [[0.0, 0.0, 0.0, 1.0], [np.nan] * 4, [0.0, 0.0, 0.0, 0.0], [0.0, 0.0, np.sin(0.5), np.cos(0.5)]]
    )
    assert geo.known_attitude(q).tolist() == [True, False, False, True]
    enu = geo.ned_to_enu_quat(q)
    assert np.isnan(enu[1:3]).all() and np.isfinite(enu[[0, 3]]).all()
    np.testing.assert_allclose(geo.enu_to_ned_quat(enu)[[0, 3]], q[[0, 3]], atol=1e-12)
    rpy = geo.map_known(quat_to_euler_zyx, q, 3)
    assert rpy.shape == (4, 3) and np.isnan(rpy[1:3]).all()
    np.testing.assert_allclose(rpy[3], [0.0, 0.0, 1.0], atol=1e-12)
    yaw = geo.known_yaw(q)
    assert np.isnan(yaw[1:3]).all() and yaw[0] == 0.0 and yaw[3] == pytest.approx(1.0)
    with pytest.raises(InputError, match="expected shape"):
        geo.map_known(quat_to_euler_zyx, np.zeros((3, 3)), 3)


def test_slerp_known_skips_unknown_samples() -> None:
    t = np.array([0.0, 1.0, 2.0])
    q = np.array([[0.0, 0.0, 0.0, 1.0], [np.nan] * 4, Rotation.from_rotvec([0.0, 0.0, 1.0]).as_quat()])
    mid = geo.slerp_known(t, q, np.array([1.0]))
    np.testing.assert_allclose(mid[0], Rotation.from_rotvec([0.0, 0.0, 0.5]).as_quat(), atol=1e-12)
    assert np.isnan(geo.slerp_known(t, np.full((3, 4), np.nan), np.array([0.5, 1.5]))).all()


def test_wrap_angle() -> None:
    np.testing.assert_allclose(
        geo.wrap_angle(np.array([np.pi, -np.pi, 3 * np.pi / 2, 0.1])), [-np.pi, -np.pi, -np.pi / 2, 0.1]
    )
