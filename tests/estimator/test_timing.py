"""The torque carried to the speed's instants."""

import dataclasses

import numpy as np
import pytest

from ddh_vsensor.estimator.timing import (shaft_torque_nm, shaft_torques_nm,
                                          torque_at_speed_instant, torque_at_speed_instants)


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


def test_the_shaft_torque_is_the_reading_less_the_offsets_over_the_gain(cfg):
    """reading = g shaft + o + s n / n_limit: 1.05 x 40 N*m + 1.5 + 2.0 at half the speed
    limit is 40 N*m; at gain 1 the reading less the offsets, to the bit."""
    motor = cfg.unit("boom").motor
    n = 0.5 * motor.speed_limit_rpm
    drive = dataclasses.replace(motor, torque_gain=1.05, torque_offset_nm=1.5,
                                torque_speed_offset_nm=2.0)
    assert shaft_torque_nm(1.05 * 40.0 + 1.5 + 1.0, n, drive) == pytest.approx(40.0, abs=1e-12)
    assert shaft_torque_nm(42.0, 0.0, dataclasses.replace(motor, torque_gain=1.05)) == 40.0
    read = np.array([10.0, -20.0, 43.7])
    unit = dataclasses.replace(drive, torque_gain=1.0)
    assert np.array_equal(shaft_torque_nm(read, n, unit), read - 1.5 - 1.0)
    prompt = dataclasses.replace(drive, torque_lag_s=0.0)      # no lag: nothing carried
    assert np.array_equal(shaft_torques_nm([0.0, 0.01, 0.02], read, [n] * 3, prompt, 0.05),
                          shaft_torque_nm(read, n, drive))
