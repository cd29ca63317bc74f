"""The torque carried to the speed's instants."""

import numpy as np
import pytest

from ddh_vsensor.estimator.timing import torque_at_speed_instant, torque_at_speed_instants


def test_a_ramp_reported_late_is_read_at_the_speeds_instants():
    t = np.arange(0.0, 0.1, 0.01)
    true = 3000.0 * t                                    # 30 N*m per 10 ms sample
    reported = 3000.0 * (t - 0.0005)                     # half a millisecond behind
    assert np.allclose(torque_at_speed_instants(t, reported, 0.0005, 0.05)[1:], true[1:])
    assert torque_at_speed_instants(t, reported, 0.0005, 0.05)[0] == reported[0]


def test_no_lag_leaves_the_samples_and_a_gap_has_no_last_change():
    t = np.array([0.0, 0.01, 0.02, 0.2, 0.21])
    tau = np.array([0.0, 10.0, 20.0, 90.0, 80.0])
    assert np.array_equal(torque_at_speed_instants(t, tau, 0.0, 0.05), tau)
    out = torque_at_speed_instants(t, tau, 0.001, 0.05)
    assert out[3] == 90.0                                 # after the 180 ms gap: as reported
    assert out[4] == pytest.approx(80.0 - 1.0)
    assert out[2] == torque_at_speed_instant(20.0, 10.0, 0.01, 0.001) == pytest.approx(21.0)


def test_a_repeated_stamp_is_a_gap_not_a_division_by_zero():
    out = torque_at_speed_instants([0.0, 0.0, 0.01], [5.0, 7.0, 9.0], 0.001, 0.05)
    assert out.tolist() == pytest.approx([5.0, 7.0, 9.2])
