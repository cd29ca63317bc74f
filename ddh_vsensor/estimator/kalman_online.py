"""The Kalman filter fed sample by sample, as the service feeds it, and the service's
estimator face on it.

:class:`OnlineKalman` runs :func:`.kalman.run_many`'s bank and compiled sample on inputs kept
for the last few seconds only; on evenly sampled input it gives the offline run's outputs to
the bit where the tank sensor has no lag (with a lag, the pumps' oil is the reading plus the
lag times its rate over the last minute, :class:`.TrailingRate`, not a minute centred on the
sample). The Hall switches are debounced as they come (:class:`.Debouncer`); a switch's change
is cloned when it is seen and used once accepted, as offline.

The drive samples its speed and torque at its own fixed period (``can.sevcon_period_ms``);
the bus delivers the frames with jitter and now and then loses one. So a frame is placed by
how many periods it comes after the last:

- about one: the next sample (the physics takes the period, not the jitter);
- m >= 2, within ``estimator.max_gap_s``: m - 1 frames were lost; their samples are predicted
  on inputs interpolated between the two frames and measure nothing (no torque update);
- beyond ``estimator.max_gap_s``, or before the last (the frames' clock stepped back):
  nothing is integrated; the filter starts again at the frame (the rod's velocity and the
  chambers' pressures from the steady state there; position, load and parameters kept), the
  switches' states are forgotten and the sample is stale: the caller widens the position by
  the travel it could not integrate (the service: ``Config.max_speed_mm_s`` x the gap);
- less than half a period after the last (a repeated frame): not a sample; refused (the
  service's face keeps the last sample).

:class:`KalmanEstimator` gives the service :class:`.Estimator`'s face (``step``, presets,
restores and the persisted state, widening, switch states forgotten): the published
uncertainty is ``coverage`` x the position's sigma.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Mapping
from dataclasses import dataclass

import numpy as np

from ddh_vsensor.config import Config
from ddh_vsensor.estimator.estimator import ReferenceEvent, Step
from ddh_vsensor.estimator.flags import Flags
from ddh_vsensor.estimator.kalman import (MODEL_INCONSISTENT, KalmanSettings, _Bank, _job,
                                          cusum_threshold, sample_flags,
                                          settings_from_config)
from ddh_vsensor.estimator.references import Debouncer, Switch
from ddh_vsensor.estimator.state import EstimatorState
from ddh_vsensor.estimator.timing import shaft_torque_nm, torque_at_speed_instant
from ddh_vsensor.measured import Run
from ddh_vsensor.model.plant import RowSpec
from ddh_vsensor.physics.tank_sensor import TrailingRate
from ddh_vsensor.physics.unit import DDHUnit

_STALE_INPUT = int(Flags.STALE_INPUT)


@dataclass(slots=True)
class KalmanSample:
    """One sample of an online filter: the published position and what the filter knows of
    the unit's slow states then (made once a frame, not changed after; slotted as
    :class:`.Step` is)."""

    index: int                          # samples since the filter's first (lost ones too)
    position_mm: float
    velocity_mm_s: float
    uncertainty_mm: float
    flags: int
    load_n: float
    temp_offset_c: float
    torque_offset_nm: float
    pressures_bar: tuple[float, float]
    events: tuple[ReferenceEvent, ...]  # references accepted at this sample (global indices)


def _flat(a: np.ndarray) -> memoryview:
    """A C-contiguous array's elements in order, as a memoryview: an element read or set per
    frame is a Python float or bool without numpy's indexing (half the time or less)."""
    return memoryview(a).cast("B").cast(a.dtype.char)


class OnlineKalman:
    """One unit's filter fed sample by sample (see the module's docstring for how a frame is
    placed), on inputs kept for the last :attr:`capacity` samples only (older ones are moved
    out as the window fills)."""

    def __init__(self, cfg: Config, actuator: str, period_s: float, *,
                 references: bool = True, initial_position_mm: float | None = None,
                 settings: KalmanSettings = KalmanSettings(), capacity: int | None = None,
                 max_gap_s: float | None = None) -> None:
        self.cfg, self.actuator, self.period_s = cfg, actuator, period_s
        self.references, self.x0_mm, self.settings = references, initial_position_mm, settings
        self.max_gap_s = cfg.estimator.max_gap_s if max_gap_s is None else max_gap_s
        if self.max_gap_s < 1.5 * period_s:
            raise ValueError(f"max_gap_s {self.max_gap_s:g} s: a lost frame ({period_s:g} s "
                             f"samples) would be a gap")
        debounce_n = math.ceil(cfg.estimator.debounce_s / period_s)
        # what a step reads back: the torque window's samples, an edge's, three for the speed
        self.keep = max(1, int(round(settings.nis_window_s / period_s))) + debounce_n + 3
        self.capacity = capacity if capacity is not None else 4 * self.keep + \
            math.ceil(self.max_gap_s / period_s)
        if self.capacity <= self.keep + math.ceil(self.max_gap_s / period_s):
            raise ValueError(f"capacity {self.capacity}: more than "
                             f"{self.keep + math.ceil(self.max_gap_s / period_s)} samples "
                             "needed")
        # the edges' CUSUM threshold now (a few hundred ms, once a process), not on the first
        # frame, which a service must integrate while the bus keeps sending
        cusum_threshold(settings.edge_cusum_ratio, settings.edge_false_alarm)
        self.motor, self.lag_s = cfg.unit(actuator).motor, cfg.hydraulics.oil_temp_lag_s
        self.stroke_mm = cfg.unit(actuator).stroke_mm
        self.rate = TrailingRate()
        self.bank: _Bank | None = None
        self.end_mm = math.nan          # the bank's stroke end (mm), set with the bank
        self.base = 0                   # global index of the bank's sample 0
        self.k = 0                      # the bank's index of the next sample
        self.last: tuple[float, float] | None = None      # (time, shaft torque) before
        # per switch of the filter: (name, switch, its debouncer), set with the bank
        self._switches: list[tuple[str, Switch, Debouncer]] = []
        # flat views (:func:`_flat`) of the bank's inputs and outputs, set with the bank: its
        # one filter's arrays are (N, 1), sample k element k (the pressures' (N, 1, 2): 2k, 2k + 1)
        self._inputs: tuple[memoryview, ...] = ()
        self._outputs: tuple[memoryview, ...] = ()
        # before the first sample: a preset's (position, sigma) and whether it is referenced
        self.pending: tuple[float, float] | None = None
        self.pending_referenced: bool | None = None
        self.pending_learned: dict[str, float] = {}
        self.last_sample: KalmanSample | None = None

    # --- what the service reads and sets ---------------------------------------------------

    @property
    def position_mm(self) -> float:
        if self.bank is None:
            if self.pending is not None:
                return self.pending[0]
            return 0.5 * self.stroke_mm if self.x0_mm is None else self.x0_mm
        return float(self.bank.z[0, 0]) * 1e3

    @property
    def sd_mm(self) -> float:
        """The position's sigma now."""
        if self.bank is None:
            if self.pending is not None:
                return self.pending[1]
            return (self.stroke_mm / math.sqrt(12.0) if self.x0_mm is None
                    else self.settings.position_mm)
        return math.sqrt(max(float(self.bank.P[0, 0, 0]), 0.0)) * 1e3

    @property
    def referenced(self) -> bool:
        """Whether the position is known; False: the next edge sets it (a cold start's)."""
        if self.bank is None:
            return (self.pending_referenced if self.pending_referenced is not None
                    else self.x0_mm is not None or self.pending is not None)
        return bool(self.bank.referenced[0])

    @referenced.setter
    def referenced(self, value: bool) -> None:
        if self.bank is None:
            self.pending_referenced = bool(value)
        else:
            self.bank.referenced[0] = bool(value)

    @property
    def reference_suspect(self) -> bool:
        return self.bank is not None and self.bank.suspect[0] is not None

    def preset(self, position_mm: float, sd_mm: float) -> None:
        """The rod is at ``position_mm`` within ``sd_mm`` (sigma), referenced, no switch
        suspect."""
        if self.bank is None:
            self.pending, self.pending_referenced = (position_mm, sd_mm), True
            return
        self.bank.preset(position_mm * 1e-3, sd_mm * 1e-3)
        self.bank.filters["referenced"][0] = True
        self.bank.suspect[0] = None
        self.bank.filters["held"][0] = self.bank.cusum[0] > self.bank.cusum_h

    def widen(self, sd_mm: float) -> None:
        """The position's sigma grows by ``sd_mm`` (travel not integrated)."""
        if self.bank is None:
            self.pending = (self.position_mm, self.sd_mm + sd_mm)
            return
        self.bank.widen(sd_mm * 1e-3)

    def learned(self) -> dict[str, float]:
        """What outlives a restart (:meth:`.kalman._Bank.learned`)."""
        return self.pending_learned if self.bank is None else self.bank.learned()

    def teach(self, learned: dict[str, float]) -> None:
        """Carry on from an earlier run's :meth:`learned`."""
        if self.bank is None:
            self.pending_learned = dict(learned)
        else:
            self.bank.teach(learned)

    def forget_switch_states(self) -> None:
        """After motion not integrated: a switch state that changed meanwhile is no edge."""
        for _, _, deb in self._switches:
            deb.state, deb.candidate_since_s = None, None

    # --- the samples -----------------------------------------------------------------------

    def repeats(self, time_s: float) -> bool:
        """Whether a frame at ``time_s`` is no new sample: within half a period after the
        last."""
        return self.last is not None and 0.0 <= time_s - self.last[0] < 0.5 * self.period_s

    def _begin(self, time_s: float, speed_rpm: float, torque_nm: float,
               oil_temp_c: float) -> _Bank:
        n = self.capacity
        run = Run(time_s + self.period_s * np.arange(n), np.full(n, speed_rpm),
                  np.full(n, torque_nm), np.full(n, oil_temp_c), np.full(n, np.nan),
                  source=f"<online {self.actuator}>")
        x0 = self.pending[0] if self.pending is not None else self.x0_mm
        job = _job(self.cfg, self.actuator, DDHUnit.from_config(self.cfg, self.actuator), run,
                   self.references, x0, self.settings)
        self._switches = [(sw.name, sw, Debouncer(self.cfg.estimator.debounce_s))
                          for sw in job.switches]
        return _Bank([job], self.period_s, self.settings, self.cfg.estimator.debounce_s,
                     self.cfg.hydraulics, {self.actuator: RowSpec.from_config(
                         self.cfg, self.actuator)})

    def _rebase(self) -> None:
        """Move the last :attr:`keep` samples to the window's start."""
        b, shift = self.bank, self.k - self.keep
        assert b is not None
        for a in (b.speed, b.torque, b.temp, b.time, b.measured, b.nis, b.nis_win, b.flagged,
                  b.not_ref, *b.out):
            a[:self.keep] = a[shift:self.k]
        b.seen.clear()
        b.edges.clear()
        b.filters["since"] = max(int(b.filters["since"][0]) - shift, 0)
        self.base += shift
        self.k -= shift

    def _put(self, time_s: float, speed_rpm: float, torque_nm: float, temp_c: float,
             measured: bool) -> int:
        """The next sample's inputs into the window; its index there."""
        if self.k == self.capacity:
            self._rebase()
        k = self.k
        times, speeds, torques, temps, measureds = self._inputs
        times[k], speeds[k], torques[k], temps[k], measureds[k] = (
            time_s, speed_rpm, torque_nm, temp_c, measured)
        return k

    def update(self, time_s: float, speed_rpm: float, torque_nm: float, oil_temp_c: float,
               refs: Mapping[str, bool] | None = None,
               ref_edge_s: Mapping[str, float] | None = None) -> KalmanSample:
        """One frame: the drive's speed and torque reading, the tank sensor's oil
        temperature, each Hall switch's state (and the time it changed, where the I/O
        module timed it)."""
        first = self.bank is None
        shaft = float(shaft_torque_nm(torque_nm, speed_rpm, self.motor))
        carried, gap, lost = shaft, False, 0
        if self.last is not None:
            dt = time_s - self.last[0]
            if self.repeats(time_s):
                raise ValueError(f"a frame {dt:g} s after the last is no new sample of the "
                                 f"drive's ({self.period_s:g} s)")
            gap = dt > self.max_gap_s or dt < 0.0
            if dt < 0.0:
                self.rate = TrailingRate()      # its readings' times are another clock's
            if not gap:
                lost = max(int(round(dt / self.period_s)) - 1, 0)
                if self.motor.torque_filter_s:
                    carried = torque_at_speed_instant(shaft, self.last[1], dt,
                                                      self.motor.torque_filter_s)
        self.last = (time_s, shaft)
        temp = (oil_temp_c + self.lag_s * self.rate.update(time_s, oil_temp_c)
                if self.lag_s else oil_temp_c)
        if first:
            self.bank = b = self._begin(time_s, speed_rpm, carried, temp)
            self.end_mm = float(b.stroke[0]) * 1e3
            self._inputs = tuple(_flat(a) for a in (b.time, b.speed, b.torque, b.temp,
                                                    b.measured))
        b = self.bank
        assert b is not None
        if lost:
            k0 = self.k - 1
            t0, n0 = b.time[k0, 0], b.speed[k0, 0]
            tq0, temp0 = b.torque[k0, 0], b.temp[k0, 0]
            for i in range(1, lost + 1):
                w = i / (lost + 1)
                k = self._put(t0 + i * self.period_s, n0 + w * (speed_rpm - n0),
                              tq0 + w * (carried - tq0), temp0 + w * (temp - temp0), False)
                b.step(k)
                self.k += 1
        k = self._put(time_s, speed_rpm, carried, temp, True)
        if gap:
            self.forget_switch_states()
        for name, sw, deb in self._switches if refs is not None else ():
            if name not in refs:
                continue
            raw = bool(refs[name])
            if raw == deb.state and deb.candidate_since_s is None:
                continue            # no change: the debouncer has nothing to do
            starts = deb.state is not None and raw != deb.state and deb.candidate_since_s is None
            accepted = deb.update(time_s, raw, self.base + k)
            if starts:
                te = (ref_edge_s or {}).get(name, math.nan)
                b.seen.setdefault(k, []).append((0, sw, float(te)))
            if accepted is not None:
                c, rising = accepted
                b.edges.setdefault(k, []).append((0, c - self.base, rising, sw))
        if first:
            b.start()
            out_x, out_v, out_sd, out_load, out_dt, out_toff, _, _, out_p = b.out
            self._outputs = tuple(_flat(a) for a in (out_x, out_v, out_sd, out_load, out_dt,
                                                     out_toff, out_p, b.flagged, b.not_ref))
            if self.pending is not None:
                b.preset(self.pending[0] * 1e-3, self.pending[1] * 1e-3)
            if self.pending_referenced is not None:
                b.filters["referenced"][0] = self.pending_referenced
            b.teach(self.pending_learned)
            self.pending = self.pending_referenced = None
            self.pending_learned = {}
        elif gap:
            b.restart(k)
        before = len(b.events[0])
        b.step(k)
        b.seen.pop(k, None)
        b.edges.pop(k, None)
        self.k += 1
        out_x, out_v, out_sd, out_load, out_dt, out_toff, out_p, flagged, not_ref = \
            self._outputs
        x_mm = out_x[k] * 1e3
        flags = (int(sample_flags(flagged[k], not_ref[k], x_mm, self.end_mm))
                 | (_STALE_INPUT if gap else 0))
        events = tuple(dataclasses.replace(e, index=e.index + self.base,
                                           edge_index=e.edge_index + self.base)
                       for e in b.events[0][before:]) if len(b.events[0]) > before else ()
        self.last_sample = KalmanSample(
            self.base + k, x_mm, out_v[k] * 1e3, self.settings.coverage * out_sd[k] * 1e3,
            flags, out_load[k], out_dt[k], out_toff[k], (out_p[2 * k], out_p[2 * k + 1]),
            events)
        return self.last_sample


class KalmanEstimator:
    """The service's estimator (``estimator.mode: kalman``): :class:`.Estimator`'s face on
    an :class:`OnlineKalman`. Its uncertainty is ``coverage`` sigma; a preset's or a restored
    state's uncertainty is taken as that many sigma too."""

    def __init__(self, cfg: Config, actuator: str, *,
                 initial_position_mm: float | None = None) -> None:
        self.cfg, self.actuator = cfg, actuator
        self.settings = settings_from_config(cfg)
        self.max_gap_s = cfg.estimator.max_gap_s
        self.filter = OnlineKalman(cfg, actuator, cfg.can.sevcon_period_ms * 1e-3,
                                   initial_position_mm=initial_position_mm,
                                   settings=self.settings)
        self.stroke_mm = self.filter.stroke_mm
        self.lower_mm, self.upper_mm = 0.0, self.stroke_mm     # its estimate's bounds

    @property
    def position_mm(self) -> float:
        return self.filter.position_mm

    @property
    def uncertainty_mm(self) -> float:
        return self.settings.coverage * self.filter.sd_mm

    @property
    def referenced(self) -> bool:
        return self.filter.referenced

    @referenced.setter
    def referenced(self, value: bool) -> None:
        self.filter.referenced = value

    @property
    def reference_suspect(self) -> bool:
        return self.filter.reference_suspect

    def state_flags(self) -> int:
        """The flags that follow from the filter's state alone."""
        s = self.filter.last_sample
        return int(sample_flags(s is not None and bool(s.flags & MODEL_INCONSISTENT),
                                not self.referenced or self.reference_suspect,
                                self.position_mm, self.stroke_mm))

    def step(self, t_s: float, speed_rpm: float, torque_nm: float, oil_temp_c: float,
             refs: Mapping[str, bool] | None = None, refs_since_s: float | None = None,
             refs_timed: bool = False) -> Step:
        """One Sevcon frame in, position out (``refs_since_s`` with ``refs_timed``: the
        time the switches' states changed, as the I/O module timed it)."""
        if self.filter.repeats(t_s):
            # not a new sample of the drive's: the last one stands
            s = self.filter.last_sample
            assert s is not None
            return Step(s.position_mm, s.velocity_mm_s, self.uncertainty_mm, s.flags)
        edge_s = (dict.fromkeys(refs, refs_since_s) if refs and refs_timed
                  and refs_since_s is not None else None)
        s = self.filter.update(t_s, speed_rpm, torque_nm, oil_temp_c, refs, edge_s)
        if not s.events:
            return Step(s.position_mm, s.velocity_mm_s, s.uncertainty_mm, s.flags)
        last_event = s.events[-1]
        return Step(s.position_mm, s.velocity_mm_s, s.uncertainty_mm, s.flags,
                    last_event.switch, last_event.gain, s.events)

    def preset(self, position_mm: float, uncertainty_mm: float) -> None:
        """A manual reference (CiA 406 preset), clipped to the stroke."""
        self.filter.preset(min(max(position_mm, 0.0), self.stroke_mm),
                           uncertainty_mm / self.settings.coverage)

    def add_uncertainty(self, mm: float) -> None:
        """Motion not integrated: the published uncertainty grows by ``mm``."""
        self.filter.widen(abs(mm) / self.settings.coverage)

    def forget_switch_states(self) -> None:
        self.filter.forget_switch_states()

    def snapshot(self) -> EstimatorState:
        return EstimatorState(actuator=self.actuator, config_hash=self.cfg.physics_hash(),
                              position_mm=self.position_mm, uncertainty_mm=self.uncertainty_mm,
                              learned=self.filter.learned())

    def restore(self, state: EstimatorState) -> None:
        """Carry on from a saved state: trusted for position within its uncertainty, not
        referenced until the next edge (which then sets it); what it learnt taught."""
        self.preset(state.position_mm, state.uncertainty_mm)
        self.referenced = False
        self.filter.teach(state.learned)
