"""Sensor models: what the machine's logger would have recorded of a simulated unit.

Sampled at a configurable rate (default 100 Hz, the draw-wire sensors' 10 ms event timer):

- motor speed in whole rpm and motor torque in 1/16 N*m, as the Sevcon reports them;
- oil temperature to 0.1 degC; the oil warms slowly during work: the default drift is
  +0.01 degC/s (0.6 degC/min, a typical warm-up rate of a working machine's hydraulics: the
  paper's runs stayed within 25-30 degC). The plant's viscosity follows the same temperature;
- draw-wire position to the configured measuring step (0.01 mm) with small Gaussian noise
  (0.02 mm by default), seeded per run and unit: the same seed gives the same samples,
  whatever else is simulated in the same batch;
- chamber pressures, gauge, in bar to 0.01 bar (no noise);
- Hall reference switches ``ref_<name>`` from the true position: on when within the
  configured window of the switch position, off only beyond window + hysteresis; and the
  time of each change, the true position interpolated between the samples (what an I/O
  module that sends on change of state puts on the bus).

The effects of the measurement chain are applied here (``effects.UnitEffects``): the
logged speed and torque are the true ones ``time_offset`` seconds earlier (linear
interpolation between samples), i.e. they lag the logged position; the torque reads
``torque_gain`` x true + ``torque_offset``, the oil temperature true + ``oil_temp_offset``,
the draw-wire ``position_scale`` x true + ``position_offset`` (the Hall switches see the
true position).

The drive's torque is an estimate, not the shaft's torque (``torque_lag``, ``torque_ripple``,
``torque_speed_offset``): a first-order lag of the shaft torque, plus ripple with the rotor
angle (``effects.RIPPLE_ORDER`` periods per revolution), plus the motor's own losses
proportional to speed; the logging effects above then apply to that estimate. The tank's
temperature sensor (``oil_temp_lag``) is a first-order lag of the pumps' oil, started in the
steady state of the run's warm-up. Both lags take the signal linear between samples.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from ddh_vsensor.config import UnitConfig
from ddh_vsensor.measured import Run
from ddh_vsensor.physics.conversions import BAR_PA

if TYPE_CHECKING:
    from ddh_vsensor.sim.effects import UnitEffects


@dataclass(frozen=True)
class SensorSettings:
    rate_hz: float = 100.0
    oil_temp_drift_c_per_s: float = 0.01
    position_noise_mm: float = 0.02
    speed_step_rpm: float = 1.0
    torque_step_nm: float = 1.0 / 16.0
    oil_temp_step_c: float = 0.1
    pressure_step_bar: float = 0.01


@dataclass
class Truth:
    """True signals of one unit at the sample times (SI inside, speed in rpm)."""

    time_s: np.ndarray
    x_m: np.ndarray
    v_m_s: np.ndarray
    dp_a_pa: np.ndarray
    dp_b_pa: np.ndarray
    speed_rpm: np.ndarray
    torque_nm: np.ndarray
    oil_temp_c: np.ndarray
    reservoir_pa: float = 0.0


def quantise(values: np.ndarray, step: float) -> np.ndarray:
    """Round to a multiple of ``step``, as clean decimals (no -0.0, no 0.30000000000000004)."""
    decimals = next((d for d in range(12) if abs(step * 10 ** d - round(step * 10 ** d))
                     < 1e-9 * 10 ** d), 12)
    return np.round(np.round(np.asarray(values, dtype=float) / step) * step, decimals) + 0.0


def hall_switch(x_mm: np.ndarray, position_mm: float, window_mm: float,
                hysteresis_mm: float) -> np.ndarray:
    """0/1 state of a Hall switch: on within the window, off beyond window + hysteresis."""
    d = np.abs(np.asarray(x_mm) - position_mm)
    on, off = d < window_mm, d > window_mm + hysteresis_mm
    events = np.where(on, 1, np.where(off, 0, -1))
    # between the thresholds the switch keeps its last state (off before any event)
    idx = np.where(events >= 0, np.arange(len(d)), -1)
    last = np.maximum.accumulate(idx)
    state = np.where(last >= 0, events[np.maximum(last, 0)], 0)
    return state.astype(np.uint8)


def hall_edge_times(time_s: np.ndarray, x_mm: np.ndarray, state: np.ndarray,
                    position_mm: float, window_mm: float, hysteresis_mm: float) -> np.ndarray:
    """Per sample, the time the switch changed to the state the sample first shows (NaN
    elsewhere): where the rod, linear between the two samples, crossed the switching
    distance (within 0.02 mm of the plant's own path at 1 m/s^2 and 10 ms samples)."""
    out = np.full(len(time_s), np.nan)
    k = np.flatnonzero(state[1:] != state[:-1]) + 1
    if not len(k):
        return out
    s0, s1 = x_mm[k - 1] - position_mm, x_mm[k] - position_mm
    on = state[k] == 1
    # entering: at the window on the side it came from; leaving: beyond the hysteresis on the
    # side it went to
    side = np.where(on, np.sign(s0), np.sign(s1))
    target = side * np.where(on, window_mm, window_mm + hysteresis_mm)
    span = s1 - s0
    frac = np.divide(target - s0, span, out=np.ones(len(k)), where=span != 0.0)
    t = time_s[k - 1] + np.clip(frac, 0.0, 1.0) * (time_s[k] - time_s[k - 1])
    # within the sample's period, after the sample before it, in floating point too
    out[k] = np.clip(t, np.nextafter(time_s[k - 1], np.inf), time_s[k])
    return out


def lagged(time_s: np.ndarray, signal: np.ndarray, lag_s: float) -> np.ndarray:
    """The signal ``lag_s`` seconds earlier (held at the ends)."""
    if lag_s == 0.0:
        return signal
    return np.interp(time_s - lag_s, time_s, signal)


def first_order_lag(time_s: np.ndarray, signal: np.ndarray, tau_s: float,
                    start_slope_per_s: float = 0.0) -> np.ndarray:
    """y' = (u - y) / tau for u linear between the (evenly spaced) samples, exactly; y starts
    settled on a ramp of ``start_slope_per_s`` (tau x slope below u; 0: at u)."""
    u = np.asarray(signal, dtype=float)
    if tau_s == 0.0 or len(u) < 2:
        return u
    dt = np.diff(time_s)
    if np.ptp(dt) > 1e-9 * dt[0]:
        raise ValueError("first_order_lag needs evenly spaced samples")
    a = math.exp(-float(dt[0]) / tau_s)
    # e = y - u: e_{k+1} = a e_k - (1 - a) tau (u_{k+1} - u_k) / dt
    e0 = -tau_s * start_slope_per_s
    drive = -(1.0 - a) * tau_s * np.diff(u) / dt[0]
    from scipy.signal import lfilter   # here: scipy.signal costs every process 0.4 s
    e = lfilter([1.0], [1.0, -a], drive, zi=[a * e0])[0]
    return u + np.concatenate(([e0], e))


def drive_torque(time_s: np.ndarray, torque_nm: np.ndarray, speed_rpm: np.ndarray,
                 unit_cfg: UnitConfig, e: UnitEffects) -> np.ndarray:
    """The drive's torque estimate of the shaft torque (the true one without the effects)."""
    if not (e.torque_lag or e.torque_ripple or e.torque_speed_offset):
        return torque_nm
    from ddh_vsensor.sim.effects import RIPPLE_ORDER
    out = first_order_lag(time_s, torque_nm, e.torque_lag * 1e-3)
    if e.torque_ripple:
        revs = np.concatenate(([0.0], np.cumsum(0.5 * (speed_rpm[1:] + speed_rpm[:-1])
                                               * np.diff(time_s)))) / 60.0
        out = out + (e.torque_ripple / 100.0 * unit_cfg.motor.torque_limit_nm
                     * np.sin(2.0 * math.pi * RIPPLE_ORDER * revs))
    if e.torque_speed_offset:
        out = out + e.torque_speed_offset * speed_rpm / unit_cfg.motor.speed_limit_rpm
    return out


def tank_temperature(time_s: np.ndarray, oil_temp_c: np.ndarray, lag_s: float) -> np.ndarray:
    """The tank sensor's reading of the pumps' oil: lagging it, settled on its warm-up."""
    if lag_s == 0.0 or len(time_s) < 2:
        return oil_temp_c
    slope = (oil_temp_c[1] - oil_temp_c[0]) / (time_s[1] - time_s[0])
    return first_order_lag(time_s, oil_temp_c, lag_s, slope)


def measure(truth: Truth, unit_cfg: UnitConfig, settings: SensorSettings,
            rng: np.random.Generator, position_step_mm: float,
            chain: "UnitEffects | None" = None, comments: list[str] | None = None,
            source: str = "<simulated>") -> Run:
    """The logged run of one unit (``chain``: its measurement-chain effects, if any)."""
    from ddh_vsensor.sim.effects import NOMINAL
    e = chain or NOMINAL
    t = truth.time_s
    speed = quantise(lagged(t, truth.speed_rpm, e.time_offset), settings.speed_step_rpm)
    drive = drive_torque(t, truth.torque_nm, truth.speed_rpm, unit_cfg, e)
    torque = quantise(e.torque_gain * lagged(t, drive, e.time_offset)
                      + e.torque_offset, settings.torque_step_nm)
    x_mm = truth.x_m * 1e3
    noise = rng.standard_normal(len(t)) * settings.position_noise_mm
    position = quantise(e.position_scale * x_mm + e.position_offset + noise, position_step_mm)
    w, hy = unit_cfg.reference_window_mm, unit_cfg.reference_hysteresis_mm
    refs = {name: hall_switch(x_mm, pos, w, hy) for name, pos in unit_cfg.references_mm.items()}
    t_out = np.round(t, 9)
    edges = {name: hall_edge_times(t_out, x_mm, refs[name], pos, w, hy)
             for name, pos in unit_cfg.references_mm.items()}
    p_a = quantise((truth.dp_a_pa + truth.reservoir_pa) / BAR_PA, settings.pressure_step_bar)
    p_b = quantise((truth.dp_b_pa + truth.reservoir_pa) / BAR_PA, settings.pressure_step_bar)
    return Run(time_s=t_out, speed_rpm=speed, torque_nm=torque,
               oil_temp_c=quantise(tank_temperature(t, truth.oil_temp_c, e.oil_temp_lag)
                                   + e.oil_temp_offset, settings.oil_temp_step_c),
               position_mm=position, p_a_bar=p_a, p_b_bar=p_b, refs=refs,
               comments=list(comments or []), source=source, ref_edge_s=edges)
