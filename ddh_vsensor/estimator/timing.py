"""The shaft's torque at the speed's instants, from the drive's reading of it.

The drive's torque is its estimate from the motor's currents: it reads ``motor.torque_gain``
times the shaft's plus ``motor.torque_offset_nm``, plus ``motor.torque_speed_offset_nm`` at the
speed limit (the motor's own losses, in proportion to its speed), and trails the shaft's by a
first-order filter of ``motor.torque_filter_s``, undone to first order by carrying each sample
that much further along its last change (a first-order lag delays a ramp by its time
constant). The rotor's inertia torque is J times the speed's change, and the pump torque is
the reported torque less it, so the two signals must describe the same instants: where the
torque swings 30 N·m per sample a millisecond between them is several N·m of pump torque,
which the chamber model reads as pressure. A drive that reports its torque ``lag_s`` behind
its speed (a filter, the order it samples in, a simulator's step) has each sample carried
forward along its last change; the first sample after a gap has none and stays.
"""

from __future__ import annotations

from typing import Any

import numpy as np
from numpy.typing import ArrayLike

from ddh_vsensor.config import MotorConfig


def torque_at_speed_instants(time_s: ArrayLike, torque_nm: ArrayLike, lag_s: float,
                             max_gap_s: float) -> np.ndarray:
    """Each torque sample moved ``lag_s`` forward along the change from the sample before
    (within ``max_gap_s`` of it); a copy, equal to the samples where ``lag_s`` is 0."""
    torque = np.array(torque_nm, dtype=float)
    if lag_s and torque.size > 1:
        dt = np.diff(np.asarray(time_s, dtype=float))
        valid = (dt > 0.0) & (dt <= max_gap_s)
        torque[1:] += np.where(valid, lag_s * np.diff(torque) / np.where(valid, dt, 1.0), 0.0)
    return torque


def torque_at_speed_instant(torque_nm: float, last_torque_nm: float, dt_s: float,
                            lag_s: float) -> float:
    """One sample of :func:`torque_at_speed_instants` (``dt_s`` within the gap limit), with
    the same arithmetic."""
    return torque_nm + lag_s * (torque_nm - last_torque_nm) / dt_s


def shaft_torques_nm(time_s: ArrayLike, torque_nm: ArrayLike, speed_rpm: ArrayLike,
                     motor: MotorConfig, max_gap_s: float) -> np.ndarray:
    """The shaft's torque at the speed's instants from the drive's reading (a copy, equal to
    the reading where the motor's torque keys are at their defaults and the lag is 0)."""
    shaft = shaft_torque_nm(np.asarray(torque_nm, dtype=float),
                            np.asarray(speed_rpm, dtype=float), motor)
    return torque_at_speed_instants(time_s, shaft, motor.torque_lag_s + motor.torque_filter_s,
                                    max_gap_s)


def shaft_torque_nm(torque_nm: ArrayLike, speed_rpm: ArrayLike, motor: MotorConfig) -> Any:
    """A reading (or an array of them) less the drive's offsets, over its gain;
    :func:`torque_at_speed_instant` then carries it."""
    return ((torque_nm - motor.torque_offset_nm
             - motor.torque_speed_offset_nm / motor.speed_limit_rpm * speed_rpm)
            / motor.torque_gain)
