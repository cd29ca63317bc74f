"""Position control as in the paper: a PID on the true cylinder position, output motor torque.

The gains are placed, per unit, from the unit's own drive: seen from the motor, a DDH unit
is close to a double integrator from torque to rod position, x = d * theta with d the A-side
pump's geometric stroke per motor radian, and the rotating inertia J_eff = J_motor + m d^2
(the motor's own inertia dominates, the load reflects through d^2). Putting the three
closed-loop poles of PID + double integrator at -w gives

    Kp = 3 w^2 J_eff / d,   Ki = w^3 J_eff / d,   Kd = 3 w J_eff / d

(torque per metre, per metre-second, per metre/second). ``bandwidth_rad_s`` = w sets the
trade-off the paper describes: a slow loop gives smooth motion (and the motor creeping at the
leakage speed while the rod is held), a fast one torque spikes and speed oscillation.
The derivative acts on the position error through a first-order filter, the command passes
a first-order torque filter (the drive's torque response) and is limited to the motor's
torque limit; the integrator is frozen while the output saturates in the direction it would
grow (anti-windup) and starts from the holding torque, so a run starts without a transient.
A feedforward of the setpoint's acceleration (J_eff/d * a_sp) supplies the torque that
accelerates the rotating inertia, so the slow, robust feedback does not have to.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Sequence

import numpy as np

from ddh_vsensor.physics.unit import DDHUnit


@dataclass(frozen=True)
class PIDSettings:
    """Pole placement of the position loop, its two first-order filters, the feedforward.

    The defaults were chosen by scanning the linearised closed loop (motor inertia, pump
    torque pumping and motoring, chamber compliance anywhere in the stroke, load mass,
    viscous friction, leakage at -5..100 degC, payload 0..1500 kg, bulk modulus 0.7..1.4 GPa)
    for the largest stability margin: every pole has a real part below -1.4 1/s. The load's
    hydraulic resonance (40-200 rad/s) is lightly damped and a derivative acting on the rod
    position destabilises it unless filtered; with this margin the motion does not depend on
    the integration step. Tracking comes from the feedforward of the setpoint acceleration
    (J_eff/d * a_sp: the torque that accelerates the rotating inertia), which leaves the
    stability untouched.
    """

    bandwidth_rad_s: float = 4.0
    derivative_filter_s: float = 0.12     # the derivative of the position error, low-passed
    torque_filter_s: float = 0.01         # torque command to motor torque (drive's torque ramp)
    acceleration_feedforward: bool = True  # + J_eff/d * setpoint acceleration


def inertia_per_acceleration(unit: DDHUnit, payload_kg: float) -> float:
    """J_eff / d: motor torque per m/s^2 of rod acceleration (N*m*s^2/m)."""
    pump = unit.a.pump
    d = pump.displacement_m3_rev * pump.speed_ratio / (2.0 * math.pi) / unit.a.area_m2
    j_eff = unit.motor.inertia_kg_m2 + unit.moving_mass_kg(payload_kg) * d * d
    return j_eff / d


def pid_gains(unit: DDHUnit, payload_kg: float, settings: PIDSettings) -> tuple[float, float,
                                                                                   float]:
    """(Kp [N*m/m], Ki [N*m/(m*s)], Kd [N*m*s/m]) for one unit by pole placement."""
    j_d = inertia_per_acceleration(unit, payload_kg)
    w = settings.bandwidth_rad_s
    return 3.0 * w * w * j_d, w ** 3 * j_d, 3.0 * w * j_d


class PositionPID:
    """Vectorised PID, one per plant row: setpoint and true position in, motor torque out."""

    def __init__(self, units: Sequence[DDHUnit], payloads_kg: Sequence[float],
                 settings: PIDSettings = PIDSettings()) -> None:
        gains = np.array([pid_gains(u, p, settings) for u, p in zip(units, payloads_kg)])
        self.settings = settings
        self.kp, self.ki, self.kd = gains.T.copy()
        self.kff = (np.array([inertia_per_acceleration(u, p) for u, p in zip(units, payloads_kg)])
                    if settings.acceleration_feedforward else np.zeros(len(units)))
        self.limit = np.array([u.motor.torque_limit_nm for u in units])
        n = len(units)
        self.integral = np.zeros(n)      # Ki * integral of the error, in N*m
        self.error_filtered = np.zeros(n)
        self.torque = np.zeros(n)        # output of the torque filter
        self._dt = -1.0

    def reset(self, holding_torque_nm: np.ndarray, error_m: np.ndarray | float = 0.0) -> None:
        """Start at rest with the integrator holding the load (no start transient)."""
        self.integral = np.asarray(holding_torque_nm, dtype=float).copy()
        self.torque = self.integral.copy()
        self.error_filtered = np.zeros_like(self.integral) + error_m

    def update(self, dt: float, x_sp: np.ndarray, x: np.ndarray,
               a_sp: np.ndarray | float = 0.0) -> np.ndarray:
        """Torque for the next step (setpoint, position in m, setpoint acceleration in m/s^2;
        N*m out, within the torque limit)."""
        if dt != self._dt:
            s = self.settings
            self._dt = dt
            self._a_d = 1.0 - math.exp(-dt / s.derivative_filter_s)
            self._a_t = 1.0 - math.exp(-dt / s.torque_filter_s)
            self._inv_tf = 1.0 / s.derivative_filter_s
        e = x_sp - x
        de = e - self.error_filtered
        self.error_filtered = self.error_filtered + self._a_d * de
        unsat = self.kp * e + (self.kd * self._inv_tf) * de + self.integral + self.kff * a_sp
        grow = (self.ki * dt) * e
        frozen = ((unsat >= self.limit) & (grow > 0.0)) | ((unsat <= -self.limit) & (grow < 0.0))
        self.integral = self.integral + np.where(frozen, 0.0, grow)
        command = np.minimum(np.maximum(unsat, -self.limit), self.limit)
        self.torque = self.torque + self._a_t * (command - self.torque)
        return self.torque
