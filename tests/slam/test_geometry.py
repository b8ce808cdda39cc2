"""SE(2) helpers against hand-computed poses."""

from __future__ import annotations

import math

import numpy as np
import pytest

from sensors.types import Pose2
from slam.geometry import between, compose, wrap_angle


def test_wrap_angle_maps_into_minus_pi_pi_for_scalars_and_arrays() -> None:
    assert wrap_angle(3 * math.pi / 2) == pytest.approx(-math.pi / 2)
    assert wrap_angle(math.pi) == pytest.approx(-math.pi)
    np.testing.assert_allclose(
        wrap_angle(np.array([0.1, 2 * math.pi + 0.1, -7.0])), [0.1, 0.1, -7.0 + 2 * math.pi]
    )


def test_compose_moves_a_body_offset_into_the_parent_frame() -> None:
    x, y, yaw = compose(1.0, 2.0, math.pi / 2, 1.0, 0.5, 0.3)
    assert (float(x), float(y), float(yaw)) == pytest.approx((0.5, 3.0, math.pi / 2 + 0.3))


def test_compose_broadcasts_one_pose_over_many() -> None:
    xs = np.array([0.0, 1.0, 2.0])
    x, y, yaw = compose(0.0, 0.0, math.pi, xs, np.zeros(3), np.zeros(3))
    np.testing.assert_allclose(x, -xs, atol=1e-12)
    np.testing.assert_allclose(y, 0.0, atol=1e-12)


def test_between_inverts_compose() -> None:
    a = Pose2(1.0, -2.0, 2.5)
    x, y, yaw = compose(a.x, a.y, a.yaw, 0.3, -0.4, 1.2)
    d = between(a, Pose2(float(x), float(y), float(yaw)))
    assert (d.x, d.y, d.yaw) == pytest.approx((0.3, -0.4, 1.2))


def test_oplus_and_ominus_of_arrays_invert_each_other_and_agree_with_compose() -> None:
    import numpy as np

    from slam.geometry import ominus, oplus

    a = np.array([1.0, -2.0, 3.0])
    b = np.array([0.3, 0.4, -2.9])
    ab = oplus(a, b)
    cx, cy, cyaw = compose(*a, *b)
    np.testing.assert_allclose(ab[:2], [cx, cy], atol=1e-12)
    assert abs(wrap_angle(ab[2] - cyaw)) < 1e-12 and -np.pi <= ab[2] < np.pi
    np.testing.assert_allclose(ominus(a, ab), [b[0], b[1], wrap_angle(b[2])], atol=1e-12)


def test_path_length_sums_the_segments_and_is_zero_for_a_point() -> None:
    from slam.geometry import path_length

    assert path_length([[0.0, 0.0], [3.0, 4.0], [3.0, 5.0]]) == pytest.approx(6.0)
    assert path_length([[1.0, 2.0]]) == 0.0
    assert path_length(np.zeros((0, 2))) == 0.0
