"""Rotations and quaternions (x, y, z, w): every function against SciPy's ``Rotation`` and by hand."""

from __future__ import annotations

import warnings

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from stablecues.errors import InputError
from stablecues.geometry.rotations import (
    euler_zyx_to_quat,
    matrix_to_quat,
    quat_conjugate,
    quat_from_rotvec,
    quat_multiply,
    quat_normalize,
    quat_slerp,
    quat_to_euler_zyx,
    quat_to_matrix,
    quat_to_rotvec,
    wxyz_to_xyzw,
    xyzw_to_wxyz,
    yaw_of,
)

S = np.sqrt(0.5)


def _random_quats(n: int, seed: int = 0) -> np.ndarray:
    return Rotation.random(n, random_state=seed).as_quat()


def _same_rotation(a: np.ndarray, b: np.ndarray, atol: float = 1e-12) -> None:
    """Quaternions equal up to sign, row by row."""
    a, b = np.atleast_2d(a), np.atleast_2d(b)
    sign = np.where(np.sum(a * b, axis=-1, keepdims=True) < 0, -1.0, 1.0)
    np.testing.assert_allclose(a, sign * b, atol=atol)


def test_normalize_gives_unit_quaternions_with_w_non_negative() -> None:
    q = np.array([[0.0, 0.0, 0.0, -2.0], [1.0, 2.0, 3.0, 4.0], [0.0, 3.0, 0.0, 4.0]])
    n = quat_normalize(q)
    np.testing.assert_allclose(n[0], [0.0, 0.0, 0.0, 1.0])  # -identity flipped
    np.testing.assert_allclose(n[1], np.array([1.0, 2.0, 3.0, 4.0]) / np.sqrt(30.0))
    np.testing.assert_allclose(n[2], [0.0, 0.6, 0.0, 0.8])
    np.testing.assert_allclose(np.linalg.norm(n, axis=-1), 1.0)
    # one quaternion takes a faster path: same result as the array path
    for row in np.r_[q, -_random_quats(5)]:
        np.testing.assert_allclose(quat_normalize(row), quat_normalize(row[None])[0], atol=1e-15)
        assert quat_normalize(row)[3] >= 0
    assert quat_normalize(np.zeros((2, 3, 4)) + [0, 0, 0, 1]).shape == (2, 3, 4)


@pytest.mark.parametrize(
    "bad", [np.zeros(4), np.zeros((2, 4)), np.array([np.nan, 0, 0, 1]), np.array([[0, 0, 0, np.inf]])]
)
def test_zero_or_non_finite_quaternions_are_no_rotation(bad: np.ndarray) -> None:
    with pytest.raises(InputError, match="zero or non-finite"):
        quat_normalize(bad)
    with pytest.raises(InputError):
        quat_to_matrix(bad)


def test_wrong_shapes_raise() -> None:
    for fn in (quat_normalize, quat_conjugate, quat_to_matrix, quat_to_rotvec, wxyz_to_xyzw, xyzw_to_wxyz):
        with pytest.raises(InputError, match=r"\(\.\.\., 4\)"):
            fn(np.ones((2, 3)))
    with pytest.raises(InputError):
        quat_multiply(np.ones(3), np.ones(4))
    with pytest.raises(InputError, match="3, 3"):
        matrix_to_quat(np.eye(4))


def test_product_order_and_scipy() -> None:
    # a * b applies b first: 90 deg about x (y -> z, z -> -y), then 90 deg about z (z -> z, -y -> x)
    qx = np.array([S, 0.0, 0.0, S])
    qz = np.array([0.0, 0.0, S, S])
    r = quat_to_matrix(quat_multiply(qz, qx))
    np.testing.assert_allclose(r @ [0.0, 1.0, 0.0], [0.0, 0.0, 1.0], atol=1e-15)
    np.testing.assert_allclose(r @ [0.0, 0.0, 1.0], [1.0, 0.0, 0.0], atol=1e-15)
    np.testing.assert_allclose(r, quat_to_matrix(qz) @ quat_to_matrix(qx), atol=1e-15)
    a, b = _random_quats(50, 1), _random_quats(50, 2)
    want = (Rotation.from_quat(a) * Rotation.from_quat(b)).as_quat()
    _same_rotation(quat_multiply(a, b), want)
    # one pair (fast path) and broadcasting (4,) against (N, 4) agree with the array path
    np.testing.assert_allclose(quat_multiply(a[0], b[0]), quat_multiply(a[:1], b[:1])[0], atol=1e-15)
    np.testing.assert_allclose(quat_multiply(a[0], b), quat_multiply(np.tile(a[0], (50, 1)), b), atol=1e-15)
    # identity and inverse
    ident = np.array([0.0, 0.0, 0.0, 1.0])
    np.testing.assert_allclose(quat_multiply(ident, a), a)
    _same_rotation(quat_multiply(a, quat_conjugate(a)), np.tile(ident, (50, 1)))
    _same_rotation(quat_conjugate(a), Rotation.from_quat(a).inv().as_quat())


def test_matrices_against_scipy() -> None:
    q = _random_quats(40, 3)
    np.testing.assert_allclose(quat_to_matrix(q), Rotation.from_quat(q).as_matrix(), atol=1e-14)
    np.testing.assert_allclose(quat_to_matrix(3.0 * q), quat_to_matrix(q), atol=1e-14)  # normalised first
    np.testing.assert_allclose(quat_to_matrix(q[7]), quat_to_matrix(q[None, 7])[0], atol=1e-15)  # fast path
    assert quat_to_matrix(q.reshape(4, 10, 4)).shape == (4, 10, 3, 3)
    np.testing.assert_allclose(
        quat_to_matrix(np.array([0.0, 0.0, S, S])), [[0, -1, 0], [1, 0, 0], [0, 0, 1]], atol=1e-15
    )
    back = matrix_to_quat(Rotation.from_quat(q).as_matrix())
    assert np.all(back[:, 3] >= 0)
    _same_rotation(back, q)
    assert matrix_to_quat(np.eye(3)).tolist() == [0.0, 0.0, 0.0, 1.0]
    assert matrix_to_quat(np.tile(np.eye(3), (2, 5, 1, 1))).shape == (2, 5, 4)


def test_rotation_vectors_against_scipy() -> None:
    rng = np.random.default_rng(4)
    axes = rng.normal(size=(30, 3))
    v = axes / np.linalg.norm(axes, axis=1, keepdims=True) * rng.uniform(0, 3, size=(30, 1))  # < pi
    v[0] = 0.0
    v[1] = [1e-9, -2e-9, 0.0]  # the series branch
    v[2] = [4e-4, 3e-4, 0.0]
    want = Rotation.from_rotvec(v).as_quat()
    np.testing.assert_allclose(quat_from_rotvec(v), want, atol=1e-15)
    for k in range(len(v)):  # one vector (fast path): SciPy's formula
        np.testing.assert_allclose(quat_from_rotvec(v[k]), want[k], atol=1e-15)
    np.testing.assert_allclose(
        quat_from_rotvec(np.array([0.0, 0.0, np.pi / 2])), [0.0, 0.0, S, S], atol=1e-15
    )
    np.testing.assert_allclose(quat_to_rotvec(quat_from_rotvec(v[3:])), v[3:], atol=1e-12)
    assert quat_to_rotvec(_random_quats(6).reshape(2, 3, 4)).shape == (2, 3, 3)


def test_euler_zyx_round_trip_and_scipy() -> None:
    rng = np.random.default_rng(5)
    rpy = rng.uniform([-3, -1.5, -3], [3, 1.5, 3], size=(40, 3))
    q = euler_zyx_to_quat(rpy[:, 0], rpy[:, 1], rpy[:, 2])
    _same_rotation(q, Rotation.from_euler("ZYX", rpy[:, ::-1]).as_quat())
    np.testing.assert_allclose(quat_to_euler_zyx(q), rpy, atol=1e-9)
    # R = Rz(yaw) Ry(pitch) Rx(roll); scalars give one quaternion
    r, p, y = 0.3, -0.2, 1.1
    want = Rotation.from_euler("z", y).as_matrix() @ Rotation.from_euler("y", p).as_matrix()
    want = want @ Rotation.from_euler("x", r).as_matrix()
    np.testing.assert_allclose(quat_to_matrix(euler_zyx_to_quat(r, p, y)), want, atol=1e-14)
    _same_rotation(euler_zyx_to_quat(0.0, 0.0, np.pi / 2), np.array([0.0, 0.0, S, S]))
    assert euler_zyx_to_quat(np.zeros((2, 3)), 0.0, 0.0).shape == (2, 3, 4)
    # gimbal lock: pitch +90 deg comes back without a warning
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        e = quat_to_euler_zyx(euler_zyx_to_quat(0.0, np.pi / 2, 0.0))
    assert e[1] == pytest.approx(np.pi / 2, abs=1e-6)


def test_yaw_of_is_the_heading() -> None:
    for a in (-3.0, -1.0, 0.0, 0.5, 2.5):
        assert yaw_of(quat_from_rotvec(np.array([0.0, 0.0, a]))) == pytest.approx(a)
    # a turn about the world vertical adds to the yaw whatever the roll and pitch
    q = euler_zyx_to_quat(np.array([0.4, -0.3]), np.array([0.2, 0.5]), np.array([1.0, -2.0]))
    turn = quat_from_rotvec(np.array([0.0, 0.0, 0.7]))
    d = yaw_of(quat_multiply(turn, q)) - yaw_of(q)
    np.testing.assert_allclose(d, 0.7, atol=1e-12)
    np.testing.assert_allclose(yaw_of(q), [1.0, -2.0], atol=1e-12)  # the ZYX yaw


def test_slerp_endpoints_midpoint_and_clamping() -> None:
    q = np.array([[0.0, 0.0, 0.0, 1.0], [0.0, 0.0, S, S]])  # identity, 90 deg about z
    t = np.array([1.0, 3.0])
    out = quat_slerp(t, q, np.array([0.0, 1.0, 2.0, 3.0, 9.0]))
    np.testing.assert_allclose(out[[0, 1]], [q[0], q[0]], atol=1e-15)  # before the start: clamped
    np.testing.assert_allclose(out[[3, 4]], [q[1], q[1]], atol=1e-15)
    _same_rotation(out[2], quat_from_rotvec(np.array([0.0, 0.0, np.pi / 4])))
    assert np.all(out[:, 3] >= 0)
    # the short way round: -q is the same rotation
    _same_rotation(quat_slerp(t, np.array([q[0], -q[1]]), np.array([2.0]))[0], out[2])
    # against SciPy's Slerp on a random track
    qs = _random_quats(6, 7)
    ts = np.array([0.0, 0.5, 1.7, 2.0, 3.5, 4.0])
    query = np.linspace(0.0, 4.0, 23)
    from scipy.spatial.transform import Slerp

    _same_rotation(quat_slerp(ts, qs, query), Slerp(ts, Rotation.from_quat(qs))(query).as_quat())


def test_slerp_single_repeated_and_bad_times() -> None:
    q = _random_quats(3, 8)
    np.testing.assert_allclose(
        quat_slerp(np.array([2.0]), q[:1], np.array([0.0, 5.0])), [quat_normalize(q[0])] * 2
    )
    # a repeated time stamp: the later sample is used there and after it
    rep = quat_slerp(np.array([0.0, 1.0, 1.0]), q, np.array([1.0]))
    _same_rotation(rep[0], q[2])
    with pytest.raises(InputError, match="non-decreasing"):
        quat_slerp(np.array([0.0, 2.0, 1.0]), q, np.array([0.5]))
    with pytest.raises(InputError, match="M >= 1"):
        quat_slerp(np.zeros(0), np.zeros((0, 4)), np.array([0.5]))
    with pytest.raises(InputError, match="M >= 1"):
        quat_slerp(np.array([0.0, 1.0]), q, np.array([0.5]))


def test_scalar_first_conversions() -> None:
    wxyz = np.array([0.9, 0.1, 0.2, 0.3])
    xyzw = wxyz_to_xyzw(wxyz)
    np.testing.assert_array_equal(xyzw, [0.1, 0.2, 0.3, 0.9])
    np.testing.assert_array_equal(xyzw_to_wxyz(xyzw), wxyz)
    q = _random_quats(8).reshape(2, 4, 4)
    np.testing.assert_array_equal(wxyz_to_xyzw(xyzw_to_wxyz(q)), q)
    # the identity, scalar first (EuRoC, Eigen's constructor) -> scalar last
    np.testing.assert_array_equal(wxyz_to_xyzw(np.array([1.0, 0.0, 0.0, 0.0])), [0.0, 0.0, 0.0, 1.0])
