"""Streams at other rates onto the magnetometer's epochs, against exact synthetic streams."""

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from magkf.conventions import euler_to_quaternion, quaternion_to_euler, wrap_deg
from magkf.io.streams import interpolate_linear, interpolate_quaternions


def test_slerp_follows_a_constant_rate_turn_across_the_wrap_exactly():
    """A yaw turning at 30 deg/s through 180 deg, sampled at 5 Hz, interpolated at 50 Hz: slerp between two
    samples of a constant-rate rotation about a fixed axis is that rotation exactly; linear interpolation
    of the Euler angles would jump by 360 deg at the wrap."""
    t_src = np.arange(0.0, 10.0 + 1e-9, 0.2)
    yaw_src = (150.0 + 30.0 * t_src) % 360.0
    q_src = euler_to_quaternion(yaw_src, np.full_like(t_src, 5.0) * 0, np.zeros_like(t_src))
    t = np.arange(0.0, 10.0, 0.02)
    q, valid = interpolate_quaternions(t, t_src, q_src, max_gap_s=0.5)
    assert valid.all()
    yaw, _, _ = quaternion_to_euler(q)
    assert np.abs(wrap_deg(yaw - (150.0 + 30.0 * t))).max() < 1e-9


def test_slerp_equals_the_geodesic_between_random_attitudes():
    rng = np.random.default_rng(4)
    r = Rotation.random(20, random_state=5)
    t_src = np.cumsum(rng.uniform(0.05, 0.2, 20))
    q_src = r.as_quat()[:, [3, 0, 1, 2]]
    t = np.sort(rng.uniform(t_src[0], t_src[-1], 300))
    q, valid = interpolate_quaternions(t, t_src, q_src)
    assert valid.all()
    i = np.searchsorted(t_src, t, side="right") - 1
    i = np.minimum(i, len(t_src) - 2)
    f = (t - t_src[i]) / (t_src[i + 1] - t_src[i])
    step = r[i].inv() * r[i + 1]
    expected = r[i] * Rotation.from_rotvec(step.as_rotvec() * f[:, None])
    got = Rotation.from_quat(q[:, [1, 2, 3, 0]])
    assert (got.inv() * expected).magnitude().max() < 1e-9


def test_linear_interpolation_is_exact_on_a_line_and_marks_gaps_and_the_span():
    t_src = np.array([0.0, 1.0, 2.0, 5.0, 6.0])  # a 3 s gap between 2 and 5
    values = np.column_stack([2.0 * t_src + 1.0, -t_src])
    t = np.array([-0.5, 0.0, 0.5, 1.5, 2.0, 3.0, 4.9, 5.5, 6.0, 6.5])
    out, valid = interpolate_linear(t, t_src, values, max_gap_s=1.5)
    expect_valid = np.array([False, True, True, True, True, False, False, True, True, False])
    assert np.array_equal(valid, expect_valid)
    assert np.allclose(out[valid], np.column_stack([2.0 * t + 1.0, -t])[valid], rtol=0, atol=1e-12)
    assert np.isnan(out[~valid]).all()


@pytest.mark.parametrize("bad", ["nan", "zero"])
def test_a_bad_quaternion_invalidates_only_its_brackets(bad):
    t_src = np.arange(6.0)
    q_src = euler_to_quaternion(10.0 * t_src, 0 * t_src, 0 * t_src)
    q_src[3] = np.nan if bad == "nan" else 0.0
    t = np.array([0.5, 1.5, 2.5, 3.5, 4.5])
    q, valid = interpolate_quaternions(t, t_src, q_src)
    assert np.array_equal(valid, [True, True, False, False, True])
    yaw, _, _ = quaternion_to_euler(q[valid])
    assert np.allclose(yaw, 10.0 * t[valid], atol=1e-9)


def test_a_slow_stream_is_bridged_across_three_of_its_intervals():
    """A stream whose five intervals alternate 0.4 and 0.6 s (median 0.4 s) is bridged across 1.2 s; a fast
    stream keeps ``max_gap_s``; one sample gives no interval to scale."""
    from magkf.io.streams import SLOW_GAP_INTERVALS, slow_gap

    t = np.cumsum([0.0, 0.4, 0.6, 0.4, 0.6, 0.4])
    assert SLOW_GAP_INTERVALS == 3.0 and slow_gap(t, 0.5) == pytest.approx(1.2)
    assert slow_gap(np.arange(10) * 0.01, 0.5) == 0.5
    assert slow_gap(np.array([3.0]), 0.5) == 0.5


def test_time_order_keeps_the_first_of_repeated_times():
    """Out-of-order times are sorted; of two samples at one time the earlier in the input stays."""
    from magkf.io.streams import time_order

    t = np.array([3.0, 1.0, 2.0, 1.0, 3.0, 4.0])
    np.testing.assert_array_equal(time_order(t), [1, 2, 0, 5])
    assert time_order(np.array([], float)).size == 0
