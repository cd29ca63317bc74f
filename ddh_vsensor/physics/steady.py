"""Steady state of a DDH unit, solved exactly.

Every element of the circuit is piecewise linear in the chamber pressures, so for each
combination of valve states (per side: anti-cavitation open, closed below or above reservoir
pressure, relief open) and friction state the balance is a linear equation in the rod velocity.
All combinations are solved at once, vectorised over operating points, and the one whose
solution lies inside its own assumed states is kept. No clamping, no iteration.

The 'closed' state is split at zero pressure only because the pump torque switches between
pumping and motoring efficiency there.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike

from ddh_vsensor.physics.unit import DDHUnit, Side
from ddh_vsensor.physics.conversions import BAR_PA, LPM_M3S

AC, CLOSED_NEG, CLOSED_POS, RELIEF = range(4)
REGIME_NAMES = ("anticav", "closed", "closed", "relief")
_REGIME_PRESSURE_SIGN = np.array([-1.0, -1.0, 1.0, 1.0])
_VELOCITY_WEIGHT_PA_S_M = 1.0e9     # scales a velocity-sign violation to compare with pascals


@dataclass(frozen=True)
class SteadyState:
    """One or many steady operating points (arrays of equal shape); pressures are gauge."""

    speed_rpm: np.ndarray
    oil_temp_c: np.ndarray
    velocity_m_s: np.ndarray
    p_a_pa: np.ndarray
    p_b_pa: np.ndarray
    torque_nm: np.ndarray
    load_force_n: np.ndarray
    pump_a_m3_s: np.ndarray         # displacement flow into chamber A
    pump_b_m3_s: np.ndarray         # displacement flow into chamber B
    leak_a_m3_s: np.ndarray         # leakage out of chamber A through its pump
    leak_b_m3_s: np.ndarray
    relief_a_m3_s: np.ndarray       # relief flow out of chamber A
    relief_b_m3_s: np.ndarray
    anticav_a_m3_s: np.ndarray      # anti-cavitation flow into chamber A
    anticav_b_m3_s: np.ndarray
    regime_a: np.ndarray            # AC, CLOSED_NEG, CLOSED_POS or RELIEF
    regime_b: np.ndarray

    def report(self, index: int | tuple[int, ...] = ()) -> dict[str, float]:
        """The CLI's view of one point: mm/s, bar, N*m, L/min."""
        def f(arr: np.ndarray, scale: float = 1.0) -> float:
            return float(np.asarray(arr)[index]) * scale
        return {
            "velocity_mm_s": f(self.velocity_m_s, 1e3),
            "p_a_bar": f(self.p_a_pa, 1 / BAR_PA),
            "p_b_bar": f(self.p_b_pa, 1 / BAR_PA),
            "torque_nm": f(self.torque_nm),
            "relief_a_lpm": f(self.relief_a_m3_s, 1 / LPM_M3S),
            "relief_b_lpm": f(self.relief_b_m3_s, 1 / LPM_M3S),
            "anticav_a_lpm": f(self.anticav_a_m3_s, 1 / LPM_M3S),
            "anticav_b_lpm": f(self.anticav_b_m3_s, 1 / LPM_M3S),
        }


@dataclass(frozen=True)
class _SideLinear:
    """dp = a + b*v for each of the four valve states (last axis)."""

    a: np.ndarray
    b: np.ndarray
    lo: np.ndarray
    hi: np.ndarray


def _side_linear(side: Side, speed_rpm: np.ndarray, mu: np.ndarray) -> _SideLinear:
    q = side.pump.geometric_flow_m3_s(speed_rpm)[..., None]
    g = side.pump.leak_conductance_m3_s_pa(mu)[..., None]
    g_ac, cr = side.anticav.gradient_m3_s_pa, side.anticav.cracking_pa
    g_rv, st = side.relief.gradient_m3_s_pa, side.relief.setting_pa
    extra_g = np.array([g_ac, 0.0, 0.0, g_rv])
    extra_q = np.array([g_ac * cr, 0.0, 0.0, g_rv * st])
    den = g + extra_g
    lo = np.array([-np.inf, cr, 0.0, st])
    hi = np.array([cr, 0.0, st, np.inf])
    a, b = np.broadcast_arrays((q + extra_q) / den, -side.sign * side.area_m2 / den)
    return _SideLinear(a=a, b=b, lo=lo, hi=hi)


def _outside(x: np.ndarray, lo: np.ndarray, hi: np.ndarray) -> np.ndarray:
    return np.maximum(lo - x, 0.0) + np.maximum(x - hi, 0.0)


def _side_pressure(lin: _SideLinear, v: np.ndarray) -> np.ndarray:
    """Exact chamber pressure over the reservoir for a given velocity."""
    dp = lin.a + lin.b * v[..., None]
    k = np.argmin(_outside(dp, lin.lo, lin.hi), axis=-1)
    return np.take_along_axis(dp, k[..., None], axis=-1)[..., 0]


def _regime(dp: np.ndarray, side: Side) -> np.ndarray:
    return np.select([dp < side.anticav.cracking_pa, dp < 0.0, dp <= side.relief.setting_pa],
                     [AC, CLOSED_NEG, CLOSED_POS], RELIEF)


def _assemble(unit: DDHUnit, n: np.ndarray, t: np.ndarray, mu: np.ndarray, v: np.ndarray,
              dp_a: np.ndarray, dp_b: np.ndarray) -> SteadyState:
    a, b, cyl = unit.a, unit.b, unit.cylinder
    p_a, p_b = dp_a + unit.reservoir_pa, dp_b + unit.reservoir_pa
    force = cyl.hydraulic_force_n(p_a, p_b) - cyl.moving_friction_n(v)
    return SteadyState(
        speed_rpm=n, oil_temp_c=t, velocity_m_s=v, p_a_pa=p_a, p_b_pa=p_b,
        torque_nm=unit.motor_torque_nm(dp_a, dp_b, n), load_force_n=force,
        pump_a_m3_s=a.pump.geometric_flow_m3_s(n), pump_b_m3_s=b.pump.geometric_flow_m3_s(n),
        leak_a_m3_s=a.pump.leak_conductance_m3_s_pa(mu) * dp_a,
        leak_b_m3_s=b.pump.leak_conductance_m3_s_pa(mu) * dp_b,
        relief_a_m3_s=a.relief.flow_m3_s(dp_a), relief_b_m3_s=b.relief.flow_m3_s(dp_b),
        anticav_a_m3_s=a.anticav.flow_m3_s(dp_a), anticav_b_m3_s=b.anticav.flow_m3_s(dp_b),
        regime_a=_regime(dp_a, a), regime_b=_regime(dp_b, b))


def _inputs(unit: DDHUnit, *arrays: ArrayLike) -> list[np.ndarray]:
    return [np.asarray(x, dtype=float) for x in np.broadcast_arrays(*arrays)]


def steady_state(unit: DDHUnit, speed_rpm: ArrayLike, load_force_n: ArrayLike,
                 oil_temp_c: ArrayLike) -> SteadyState:
    """Steady state at a motor speed against an external load (+ pushes the rod in).

    Static friction holds the rod when the net force at standstill is within it; otherwise
    the rod moves against Coulomb plus viscous friction.
    """
    n, f_load, t = _inputs(unit, speed_rpm, load_force_n, oil_temp_c)
    mu = unit.oil.dynamic_viscosity_pa_s(t)
    la, lb = _side_linear(unit.a, n, mu), _side_linear(unit.b, n, mu)
    cyl = unit.cylinder
    res_force = unit.reservoir_pa * (cyl.area_a_m2 - cyl.area_b_m2)

    # Standstill: each side's pressure follows from its own balance at v = 0.
    zero = np.zeros_like(n)
    dp_a0, dp_b0 = _side_pressure(la, zero), _side_pressure(lb, zero)
    net0 = cyl.area_a_m2 * dp_a0 - cyl.area_b_m2 * dp_b0 + res_force - f_load
    stuck = np.abs(net0) <= cyl.static_friction_n

    # Moving: direction s, valve states (ra, rb) -> linear in v. Axes: (..., s, ra, rb).
    s = np.array([1.0, -1.0])[:, None, None]
    aa, ba = la.a[..., None, :, None], la.b[..., None, :, None]
    ab, bb = lb.a[..., None, None, :], lb.b[..., None, None, :]
    num = (cyl.area_a_m2 * aa - cyl.area_b_m2 * ab + res_force
           - f_load[..., None, None, None] - s * cyl.coulomb_friction_n)
    den = cyl.viscous_friction_n_s_m - cyl.area_a_m2 * ba + cyl.area_b_m2 * bb
    v = num / den
    dpa, dpb = aa + ba * v, ab + bb * v
    bad = (_outside(dpa, la.lo[:, None], la.hi[:, None])
           + _outside(dpb, lb.lo, lb.hi)
           + _VELOCITY_WEIGHT_PA_S_M * np.maximum(-s * v, 0.0))
    flat = bad.reshape(*bad.shape[:-3], -1)
    k = np.argmin(flat, axis=-1)[..., None]
    v_move = np.take_along_axis(v.reshape(flat.shape), k, -1)[..., 0]
    v_sol = np.where(stuck, 0.0, v_move)
    dp_a = np.where(stuck, dp_a0, np.take_along_axis(dpa.reshape(flat.shape), k, -1)[..., 0])
    dp_b = np.where(stuck, dp_b0, np.take_along_axis(dpb.reshape(flat.shape), k, -1)[..., 0])
    out = _assemble(unit, n, t, mu, v_sol, dp_a, dp_b)
    # The load the caller asked for, not the one re-derived through friction.
    return SteadyState(**{**out.__dict__, "load_force_n": f_load})


def steady_state_at_torque(unit: DDHUnit, speed_rpm: ArrayLike, torque_nm: ArrayLike,
                           oil_temp_c: ArrayLike) -> SteadyState:
    """Steady state at a motor speed and motor torque: the operating point the tables hold.

    Sweeping the load at a fixed speed sweeps the torque monotonically, so this is the same
    family of steady states, parametrised the way the estimator reads it. Friction does not
    enter: it only decides which load produced the torque (reported as ``load_force_n``).
    """
    n, tau, t = _inputs(unit, speed_rpm, torque_nm, oil_temp_c)
    mu = unit.oil.dynamic_viscosity_pa_s(t)
    la, lb = _side_linear(unit.a, n, mu), _side_linear(unit.b, n, mu)
    ka = unit.a.pump.torque_gain_nm_per_pa(_REGIME_PRESSURE_SIGN, n[..., None])[..., :, None]
    kb = unit.b.pump.torque_gain_nm_per_pa(_REGIME_PRESSURE_SIGN, n[..., None])[..., None, :]
    aa, ba = la.a[..., :, None], la.b[..., :, None]
    ab, bb = lb.a[..., None, :], lb.b[..., None, :]
    v = (tau[..., None, None] - ka * aa - kb * ab) / (ka * ba + kb * bb)
    dpa, dpb = aa + ba * v, ab + bb * v
    bad = _outside(dpa, la.lo[:, None], la.hi[:, None]) + _outside(dpb, lb.lo, lb.hi)
    flat = bad.reshape(*bad.shape[:-2], -1)
    k = np.argmin(flat, axis=-1)[..., None]

    def pick(x: np.ndarray) -> np.ndarray:
        return np.take_along_axis(x.reshape(flat.shape), k, -1)[..., 0]

    v_sol = pick(v)
    return _assemble(unit, n, t, mu, v_sol, pick(dpa), pick(dpb))


@dataclass(frozen=True)
class HoldingSpeed:
    """Motor speeds at which the rod stands still under a load."""

    speed_rpm: float          # where pressure alone balances the load (no friction)
    band_low_rpm: float       # static friction holds the rod for speeds in this band
    band_high_rpm: float


def holding_speed(unit: DDHUnit, load_force_n: float, oil_temp_c: float) -> HoldingSpeed:
    """The leakage-balance speed: the motor turns only to replace what the pumps leak."""
    mu = unit.oil.dynamic_viscosity_pa_s(oil_temp_c)
    cyl = unit.cylinder
    res_force = unit.reservoir_pa * (cyl.area_a_m2 - cyl.area_b_m2)

    def net(n: float, offset: float) -> float:
        arr = np.array([n])
        dp_a = _side_pressure(_side_linear(unit.a, arr, mu), np.zeros(1))
        dp_b = _side_pressure(_side_linear(unit.b, arr, mu), np.zeros(1))
        return float(cyl.area_a_m2 * dp_a[0] - cyl.area_b_m2 * dp_b[0] + res_force
                     - load_force_n - offset)

    lim = unit.motor.speed_limit_rpm

    from scipy.optimize import brentq   # here: scipy costs every process 0.3 s to import

    def root(offset: float) -> float:
        return brentq(net, -lim, lim, args=(offset,), xtol=1e-9, rtol=1e-14)

    fs = cyl.static_friction_n
    return HoldingSpeed(root(0.0), root(-fs), root(fs))


def velocity_torque_curve(unit: DDHUnit, speed_rpm: ArrayLike,
                          oil_temp_c: float) -> tuple[np.ndarray, np.ndarray]:
    """The exact velocity-torque relation at each given speed, as its breakpoints.

    At a fixed speed and temperature the steady velocity is a continuous, piecewise-linear,
    decreasing function of motor torque; its kinks are where a side's pressure crosses a valve
    threshold or zero. Returns ``(torque_nm, velocity_m_s)``, each ``[speed, 8]``, torque
    ascending: six kinks plus one far point on either side, so linear interpolation (and
    extrapolation) between them is exact.
    """
    n = np.atleast_1d(np.asarray(speed_rpm, dtype=float))
    mu = unit.oil.dynamic_viscosity_pa_s(oil_temp_c)
    kinks = []
    for side in unit.sides:
        q = side.pump.geometric_flow_m3_s(n)
        g = side.pump.leak_conductance_m3_s_pa(mu)
        for level in (side.anticav.cracking_pa, 0.0, side.relief.setting_pa):
            kinks.append(side.sign * (q - g * level) / side.area_m2)
    v = np.stack(kinks, axis=-1)
    v = np.concatenate([v.min(axis=-1, keepdims=True) - 100.0, v,
                        v.max(axis=-1, keepdims=True) + 100.0], axis=-1)
    dp = []
    for side in unit.sides:
        lin = _side_linear(side, n, mu)
        cand = lin.a[:, None, :] + lin.b[:, None, :] * v[..., None]
        k = np.argmin(_outside(cand, lin.lo, lin.hi), axis=-1)
        dp.append(np.take_along_axis(cand, k[..., None], axis=-1)[..., 0])
    tau = unit.motor_torque_nm(dp[0], dp[1], n[:, None])
    order = np.argsort(tau, axis=-1, kind="stable")
    return np.take_along_axis(tau, order, -1), np.take_along_axis(v, order, -1)
