"""The position estimator: one integrator, an online step and an offline run that agree.

Per sample: velocity from the mode's table, trapezoidal integration over the measured time
step (a gap longer than ``max_gap_s`` is not integrated and flags the input stale), the
adapted travel gain per direction, soft limits at the stroke ends, then the reference
switches: a debounced edge sets the estimate to the switch's known switching position (plus
whatever was travelled since the edge) and teaches the gains.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import ArrayLike

from ddh_vsensor.config import Config
from ddh_vsensor.measured import Run
from ddh_vsensor.physics.unit import DDHUnit
from ddh_vsensor.tables.lookup import UnitTables
from ddh_vsensor.estimator.adaptation import DirectionalGain
from ddh_vsensor.estimator.bounded import bounded_cumsum
from ddh_vsensor.estimator.dynamic import DynamicModel
from ddh_vsensor.estimator.model import Mode, VelocityModel
from ddh_vsensor.estimator.flags import Flags
from ddh_vsensor.estimator.references import (Debouncer, Switch, accepted_edges,
                                              share_after_crossing, switches_from_config)
from ddh_vsensor.estimator.state import EstimatorState
from ddh_vsensor.estimator.timing import (shaft_torque_nm, shaft_torques_nm,
                                          torque_at_speed_instant)

HOLD_SPEED_MM_S = 0.5       # below this the rod counts as held: uncertainty grows with time
LATE_EDGE_MAX_S = 0.1       # an I/O frame read later than this: its edge is taken where seen
# The flags as plain ints for the per-sample path (IntFlag arithmetic costs a microsecond)
_NOT_REFERENCED, _ADAPTING, _AT_SOFT_LIMIT, _STALE_INPUT, _TABLE_CLAMPED = (
    int(f) for f in (Flags.NOT_REFERENCED, Flags.ADAPTING, Flags.AT_SOFT_LIMIT,
                     Flags.STALE_INPUT, Flags.TABLE_CLAMPED))


@dataclass(slots=True)
class Step:
    """One step's output, made once a frame and not changed after (slotted, not frozen: a
    frozen dataclass takes 0.65 us more to make, a fifteenth of the filter's frame)."""

    position_mm: float
    velocity_mm_s: float
    uncertainty_mm: float
    flags: int
    # The reference switch whose edge was taken in this step (None: no reference), and the
    # share of its error corrected: 1.0 taken whole, less when taken partly (an error of
    # transient size met at speed, see Estimator._reference).
    reference: str | None = None
    reference_gain: float = 0.0
    # every edge taken in this step, in order (:mod:`.switch_drift` pairs them)
    events: tuple[ReferenceEvent, ...] = ()


@dataclass(frozen=True)
class ReferenceEvent:
    index: int              # sample at which the edge was accepted
    edge_index: int         # sample of the edge itself
    switch: str
    rising: bool
    switch_position_mm: float
    error_mm: float         # estimate minus switching position, at the edge
    adapted: bool
    gain: float = 1.0       # share of the error corrected (1.0: whole)
    # the velocity at the edge sample and over the debounce time after it (the direction of
    # the crossing), and the estimate's travel and standstill time since the previous
    # reference (NaN: not known)
    velocity_mm_s: float = math.nan
    crossing_mm_s: float = math.nan
    path_mm: float = math.nan
    held_s: float = math.nan


@dataclass(frozen=True)
class RunEstimate:
    position_mm: np.ndarray
    velocity_mm_s: np.ndarray
    uncertainty_mm: np.ndarray
    flags: np.ndarray
    events: list[ReferenceEvent]


@dataclass
class _Snapshot:
    index: int
    x: float
    dx: float           # increment applied at the edge sample: the edge's timing resolution
    v: float
    s_up: float
    s_down: float
    after: float = 0.5  # share of dx after the crossing (its time within the sample unknown)


@dataclass
class _Online:
    """Per-sample memory of the online face."""

    t: float | None = None
    v: float = 0.0
    n: float = 0.0
    tau: float = 0.0                # the last torque sample as the drive reported it
    index: int = -1
    s_up: float = 0.0
    s_down: float = 0.0
    debouncers: list[Debouncer] = field(default_factory=list)
    snapshots: list[_Snapshot | None] = field(default_factory=list)


class Estimator:
    """One cylinder's position estimate."""

    def __init__(self, cfg: Config, actuator: str, tables: UnitTables, *,
                 mode: Mode | None = None, references: bool = True,
                 adaptation: bool | None = None,
                 initial_position_mm: float | None = None,
                 unit: DDHUnit | None = None) -> None:
        """``unit``: the physics `dynamic` mode's chamber model runs (default: the configured
        unit's), as ``tables`` are the other modes' (an extension's scaled pumps).
        ``initial_position_mm`` None: the rod's position is not known (a cold start: not
        referenced until a reference or preset, which then sets it and teaches nothing)."""
        ecfg, ucfg = cfg.estimator, cfg.unit(actuator)
        self.cfg, self.actuator = cfg, actuator
        self.mode: Mode = mode or ecfg.mode     # type: ignore[assignment]
        if self.mode == "kalman":
            raise ValueError("estimator.mode kalman is the Kalman filter's "
                             "(ddh_vsensor.estimator.kalman_online.KalmanEstimator); this "
                             "estimator runs full, paper or dynamic")
        self.model = VelocityModel(tables, self.mode)
        self.lower_mm = ecfg.soft_limit_margin_mm
        self.upper_mm = ucfg.stroke_mm - ecfg.soft_limit_margin_mm
        self.max_gap_s = ecfg.max_gap_s
        # The tables hold steady states, where motor torque equals pump torque; while the
        # motor accelerates part of its torque goes into the rotating inertia instead.
        self.inertia_nm_per_rpm_s = (ucfg.motor.inertia_kg_m2 * 2.0 * np.pi / 60.0
                                     if ecfg.inertia_compensation else 0.0)
        # that term is the speed's change: the torque is taken at the speed's instants, and
        # the shaft's, not the drive's reading of it (:mod:`.timing`)
        self.motor = ucfg.motor
        self.torque_lag_s = ucfg.motor.torque_lag_s + ucfg.motor.torque_filter_s
        self.drive_offsets = bool(ucfg.motor.torque_offset_nm
                                  or ucfg.motor.torque_speed_offset_nm
                                  or ucfg.motor.torque_gain != 1.0)
        self.debounce_s = ecfg.debounce_s
        self.resync_gain_moving = ecfg.resync_gain_moving
        self.resync_slow_mm_s = ecfg.resync_slow_mm_s
        self.resync_transient_mm = ecfg.resync_transient_mm
        self.switches: tuple[Switch, ...] = switches_from_config(ucfg) if references else ()
        self.gain = DirectionalGain(ecfg.adaptation_bound, ecfg.adaptation_step,
                                    ecfg.adaptation_min_travel_mm,
                                    ecfg.adaptation if adaptation is None else adaptation)
        self.u_ref = ecfg.uncertainty_reference_mm
        self.per_travel = ecfg.uncertainty_per_travel
        self.hold_rate = ecfg.uncertainty_hold_mm_per_s
        self.position_mm = 0.0 if initial_position_mm is None else float(initial_position_mm)
        # `dynamic`: the chamber pressures are states; the model carries its own rod position
        # for the chamber volumes (it sees no references, so both faces feed it alike)
        limit_nm = ucfg.motor.torque_limit_nm
        self.dynamic = (DynamicModel(unit or DDHUnit.from_config(cfg, actuator), self.position_mm,
                                     inertia=ecfg.inertia_compensation,
                                     blend_s=ecfg.dynamic_blend_s, max_gap_s=self.max_gap_s,
                                     torque_step_nm=ecfg.dynamic_torque_step * limit_nm,
                                     window_s=ecfg.dynamic_window_s,
                                     torque_curvature=ecfg.dynamic_torque_curvature,
                                     speed_disagreement=ecfg.dynamic_speed_disagreement,
                                     speed_disagreement_floor_nm=(
                                         ecfg.dynamic_speed_disagreement_floor * limit_nm),
                                     start_tolerance_m_s2=ecfg.dynamic_start_tolerance_m_s2)
                        if self.mode == "dynamic" else None)
        self.u_base = self.u_ref
        # False with no start position, after a restore or a provisional preset
        self.referenced = initial_position_mm is not None
        # The switch whose edge disagreed with the estimate beyond both their tolerances, and by
        # how much: the model or that switch is off, and its own edges cannot tell which. The
        # position carries the disagreement and is flagged until another switch agrees.
        self.suspect_switch: str | None = None
        self.suspect_mm = 0.0
        self.travel_mm = 0.0
        self.hold_s = 0.0
        self.s_ref = (0.0, 0.0)         # raw travel sums at the last reference's edge
        self._on = _Online(debouncers=[Debouncer(self.debounce_s) for _ in self.switches],
                           snapshots=[None] * len(self.switches))

    @classmethod
    def from_config(cls, cfg: Config | None, unit: str, *,
                    tables: UnitTables | str | Path | None = None,
                    **options: Any) -> "Estimator":
        """An estimator for one unit of a machine (``cfg`` None: the reference loader).
        ``tables``: a table set, the directory ``ddh-vsensor tables build`` wrote (refused if
        built for another configuration), or None to build them now (well under a second).
        ``options`` are the constructor's (mode, references, adaptation, initial_position_mm)."""
        from ddh_vsensor.config import load_config
        from ddh_vsensor.tables.build import build_unit_tables
        from ddh_vsensor.tables.store import load_unit_tables
        cfg = cfg if cfg is not None else load_config()
        cfg.require_unit(unit)
        if tables is None:
            tables = build_unit_tables(cfg, unit)
        elif isinstance(tables, (str, Path)):
            tables = load_unit_tables(tables, unit, cfg)
        return cls(cfg, unit, tables, **options)

    # --- shared pieces -------------------------------------------------------------------

    @property
    def reported_torque_nm(self) -> float:
        """The last torque sample less the drive's offsets, before :mod:`.timing` moved it
        along its change (kept only where that lag is set)."""
        return self._on.tau

    @property
    def referenced(self) -> bool:
        """Whether the position is known (since a reference or preset); False after a restore,
        a provisional preset or motion not integrated, until the next reference."""
        return self._referenced

    @referenced.setter
    def referenced(self, value: bool) -> None:
        # The chamber model stops its rod at the stroke ends it believes it is at. Where the
        # position is not known that belief is made up (a wrong preset, a gap): the model
        # would read a moving rod as held on an end stop, and the travel through the next
        # reference's debounce time would be lost. Its rod is unknown until the next
        # reference or preset sets it.
        self._referenced = bool(value)
        if not value and self.dynamic is not None:
            self.dynamic.set_position(None)

    @property
    def reference_suspect(self) -> bool:
        return self.suspect_switch is not None

    @property
    def uncertainty_mm(self) -> float:
        return self.u_base + self.per_travel * self.travel_mm + self.hold_rate * self.hold_s

    def _clip(self, x: float) -> float:
        return min(max(x, self.lower_mm), self.upper_mm)

    def state_flags(self) -> int:
        """The flags that follow from the estimator's state alone (not from one input)."""
        flags = 0 if self.referenced and not self.reference_suspect else Flags.NOT_REFERENCED
        if self.gain.active:
            flags |= Flags.ADAPTING
        if self.position_mm <= self.lower_mm or self.position_mm >= self.upper_mm:
            flags |= Flags.AT_SOFT_LIMIT
        return flags

    def _reference(self, sw: Switch, rising: bool, snap: _Snapshot, x_now: float,
                   s_now: tuple[float, float], index: int) -> tuple[float, ReferenceEvent]:
        """Apply an accepted edge: returns the corrected position and what happened.
        ``s_now`` holds the raw travel sums (up, down) at acceptance."""
        if not self.referenced:
            # A cold estimate may sit clipped at a soft limit while the rod moves on through
            # the debounce time: take that travel unclipped, or the clipping is published.
            g_up, g_down = self.gain.gain
            x_now = snap.x + g_up * (s_now[0] - snap.s_up) + g_down * (s_now[1] - snap.s_down)
        # Which way the rod crossed: one sample's velocity can point the wrong way where the
        # torque chatters (in `dynamic` the velocity rings for a few samples around a slow
        # motion, e.g. after an input gap), the travel from the edge to its acceptance cannot;
        # its mean over the debounce time stands for the velocity (the sample's own without one).
        after = (s_now[0] - snap.s_up) + (s_now[1] - snap.s_down)
        v_cross = after / self.debounce_s if after != 0.0 and self.debounce_s > 0.0 else snap.v
        p = sw.edge_position_mm(rising, v_cross, snap.x)
        # The switch changed state somewhere within the edge sample's travel dx: where the
        # I/O module timed the change, after that share of it; else at any moment alike, so
        # the estimate at the crossing is, on average, x - dx/2 (at speed, dx is millimetres:
        # taking x itself would bias every edge met in motion by half of it).
        error = snap.x - snap.after * snap.dx - p
        # An estimate within its uncertainty and a switch within its tolerance differ by at most
        # their sum (plus the edge sample's travel); beyond it one of them is wrong, and the edge
        # cannot say which: the position then carries both (its uncertainty covers the error)
        # and is flagged, and the error teaches no gain.
        consistent = (not self.referenced or abs(error) <= self.uncertainty_mm + sw.tolerance_mm
                      + self.u_ref + abs(snap.dx))
        if not consistent:
            self.suspect_switch, self.suspect_mm = sw.name, abs(error)
        elif sw.name != self.suspect_switch:
            self.suspect_switch, self.suspect_mm = None, 0.0
        # Within +-dx/2 the error is no evidence against the model, and learning from it
        # only fits sampling noise. An estimate that was not referenced (cold start, restore)
        # carries an unknown offset, not the model's travel error: its first edge only sets
        # the position.
        adapted = (self.referenced and consistent and abs(error) > 0.5 * abs(snap.dx)
                   and self.gain.update(error, snap.s_up - self.s_ref[0],
                                        snap.s_down - self.s_ref[1]))
        path_mm, held_s = self.travel_mm, self.hold_s
        self.s_ref = (snap.s_up, snap.s_down)
        # An edge met at speed is exact, but the estimate then carries a transient offset (oil
        # compression, not in the steady-state tables) that vanishes when the rod stops: take
        # only part of an error of that size; all of it when the rod is nearly still, when the
        # error is larger than such transients, or when the estimate was never referenced.
        transient = (abs(snap.v) > self.resync_slow_mm_s
                     and abs(error) <= self.resync_transient_mm and self.referenced)
        k = self.resync_gain_moving if transient else 1.0
        self.travel_mm, self.hold_s = 0.0, 0.0
        # the edge lies somewhere within its sample's travel and the switch within its
        # tolerance: that much is not known better
        self.u_base = (self.u_ref + sw.tolerance_mm + abs(snap.dx) + (1.0 - k) * abs(error)
                       + self.suspect_mm)
        self.referenced = True
        return self._clip(x_now - k * error), ReferenceEvent(
            index, snap.index, sw.name, rising, p, error, adapted, k, snap.v, v_cross, path_mm,
            held_s)

    def _edge_snapshot(self, index: int, x: float, dx: float, v: float, t_s: float,
                       dt: float, since_s: float | None, timed: bool = False) -> _Snapshot:
        """The estimate at an edge seen in this sample (``t_s``, ``dt`` after the one before).
        A state that holds since before the previous sample changed whole samples ago: their
        travel (at this sample's velocity, up to :data:`LATE_EDGE_MAX_S`; later than that, the
        edge is taken here) is taken out, as if the edge had been seen in the first sample
        after it."""
        on = self._on
        lag_s, after = 0.0, 0.5
        if since_s is not None and dt > 0.0:
            lag_s = math.floor((t_s - since_s) / dt) * dt
            if timed and 0.0 <= t_s - since_s <= LATE_EDGE_MAX_S:
                after = min(max((t_s - since_s - lag_s) / dt, 0.0), 1.0)
        if not 0.0 < lag_s <= LATE_EDGE_MAX_S:
            return _Snapshot(index, x, dx, v, on.s_up, on.s_down, after)
        back = v * lag_s                                   # raw travel since the edge
        gain = self.gain._up if back > 0.0 else self.gain._down
        return _Snapshot(index, x - gain * back, dx, v, on.s_up - max(back, 0.0),
                         on.s_down - min(back, 0.0), after)

    # --- online face -----------------------------------------------------------------------

    def step(self, t_s: float, speed_rpm: float, torque_nm: float, oil_temp_c: float,
             refs: Mapping[str, bool] | None = None, refs_since_s: float | None = None,
             refs_timed: bool = False) -> Step:
        """One sample in, position out. ``refs`` holds the Hall switch states by name, and
        ``refs_since_s`` (when known) the time since which they hold: before the previous
        sample (the I/O frame read late, e.g. from another bus), an edge in them is taken
        back to that time (:meth:`_edge_snapshot`); ``refs_timed``: that time is the
        change's own, finer than the samples (an I/O module sending on change of state).

        Runs per Sevcon frame: plain floats and locals throughout; :meth:`_clip`,
        :meth:`.DirectionalGain.scale`, :meth:`state_flags` and :attr:`uncertainty_mm` are
        written out with the same operations, so the result equals theirs to the bit."""
        on = self._on
        t_last = on.t
        dt = t_s - t_last if t_last is not None else 0.0
        valid = 0.0 < dt <= self.max_gap_s
        if self.drive_offsets:
            torque_nm = shaft_torque_nm(torque_nm, speed_rpm, self.motor)
        if self.torque_lag_s:
            reported, on.tau = on.tau, torque_nm
            if valid:
                torque_nm = torque_at_speed_instant(torque_nm, reported, dt, self.torque_lag_s)
        if self.dynamic is not None:
            v, clamped = self.dynamic.step(dt, speed_rpm, torque_nm, oil_temp_c), False
        else:
            pump_torque = torque_nm - (self.inertia_nm_per_rpm_s * (speed_rpm - on.n) / dt
                                       if valid else 0.0)
            v, clamped = self.model.velocity(speed_rpm, pump_torque, oil_temp_c)
        stale = False
        dx_raw = 0.0
        if t_last is not None:
            if valid:
                dx_raw = 0.5 * (on.v + v) * dt
                if abs(v) < HOLD_SPEED_MM_S:
                    self.hold_s += dt
            else:
                stale = dt > 0.0
                self.hold_s += max(dt, 0.0)
        index = on.index + 1
        on.t, on.v, on.n, on.index = t_s, v, speed_rpm, index
        gain = self.gain
        dx = dx_raw * (gain._up if dx_raw > 0.0 else gain._down)
        before = self.position_mm
        lower, upper = self.lower_mm, self.upper_mm
        x = min(max(before + dx, lower), upper)
        self.position_mm = x
        self.travel_mm += abs(dx)
        if dx_raw > 0.0:
            on.s_up += dx_raw
        else:
            on.s_down += dx_raw
        taken: ReferenceEvent | None = None
        events: tuple[ReferenceEvent, ...] = ()
        if refs:
            accepted = None
            for i, deb in enumerate(on.debouncers):
                sw = self.switches[i]
                raw = refs.get(sw.name)
                if raw is None or (raw == deb.state and deb.candidate_since_s is None):
                    continue            # no input, or no change: the debouncer has nothing to do
                waiting = deb.candidate_since_s is not None
                edge = deb.update(t_s, bool(raw), index)
                if deb.candidate_since_s is not None and not waiting or (
                        edge is not None and edge[0] == index):
                    on.snapshots[i] = self._edge_snapshot(index, x, x - before, v, t_s, dt,
                                                          refs_since_s, refs_timed)
                if edge is not None:
                    accepted = accepted or []
                    accepted.append((sw, edge[1], on.snapshots[i]))
            if accepted:
                for sw, rising, snap in accepted:
                    self.position_mm, taken = self._reference(sw, rising, snap, self.position_mm,
                                                              (on.s_up, on.s_down), index)
                    events += (taken,)
                    if self.dynamic is not None:
                        self.dynamic.set_position(self.position_mm)
                x = self.position_mm
        flags = 0 if self._referenced and self.suspect_switch is None else _NOT_REFERENCED
        if gain.enabled and (gain._up != 1.0 or gain._down != 1.0):
            flags |= _ADAPTING
        if x <= lower or x >= upper:
            flags |= _AT_SOFT_LIMIT
        if stale:
            flags |= _STALE_INPUT
        if clamped:
            flags |= _TABLE_CLAMPED
        u = self.u_base + self.per_travel * self.travel_mm + self.hold_rate * self.hold_s
        if taken is None:
            return Step(x, v, u, flags)
        return Step(x, v, u, flags, taken.switch, taken.gain, events)

    # --- offline face ----------------------------------------------------------------------

    def run(self, time_s: ArrayLike | Run, speed_rpm: ArrayLike | None = None,
            torque_nm: ArrayLike | None = None, oil_temp_c: ArrayLike | None = None,
            refs: Mapping[str, ArrayLike] | None = None,
            ref_edge_s: Mapping[str, ArrayLike] | None = None) -> RunEstimate:
        """A whole run at once, from this (fresh) estimator's state; equal to feeding
        :meth:`step` sample by sample. Takes the columns, or a measured :class:`Run` whole
        (its switch states and their changes' times included); ``ref_edge_s`` as
        :attr:`.Run.ref_edge_s`."""
        if isinstance(time_s, Run):
            run = time_s
            return self.run(run.time_s, run.speed_rpm, run.torque_nm, run.oil_temp_c, run.refs,
                            run.ref_edge_s)
        if speed_rpm is None or torque_nm is None or oil_temp_c is None:
            raise TypeError("run() takes a Run, or time_s, speed_rpm, torque_nm and oil_temp_c")
        if self._on.t is not None:
            raise RuntimeError("run() starts from a fresh estimator; use step() to continue")
        t = np.asarray(time_s, dtype=float)
        n = len(t)
        dt = np.diff(t)
        valid = (dt > 0.0) & (dt <= self.max_gap_s)
        speed = np.asarray(speed_rpm, dtype=float)
        torque = shaft_torques_nm(t, torque_nm, speed, self.motor, self.max_gap_s)
        stale = np.zeros(n, dtype=bool)
        stale[1:] = ~valid & (dt > 0.0)
        v, dx_raw, hold_dt, s_up, s_down = (np.zeros(n) for _ in range(5))

        def integrate(lo: int, hi: int) -> None:
            """Travel of samples lo..hi-1 from their velocities (and v[lo - 1])."""
            a = max(lo, 1)
            dx_raw[a:hi] = np.where(valid[a - 1:hi - 1],
                                    0.5 * (v[a - 1:hi - 1] + v[a:hi]) * dt[a - 1:hi - 1], 0.0)
            hold_dt[a:hi] = np.where(valid[a - 1:hi - 1],
                                     np.where(np.abs(v[a:hi]) < HOLD_SPEED_MM_S,
                                              dt[a - 1:hi - 1], 0.0),
                                     np.maximum(dt[a - 1:hi - 1], 0.0))
            up0, down0 = (s_up[lo - 1], s_down[lo - 1]) if lo else (0.0, 0.0)
            s_up[lo:hi] = up0 + np.cumsum(np.maximum(dx_raw[lo:hi], 0.0))
            s_down[lo:hi] = down0 + np.cumsum(np.minimum(dx_raw[lo:hi], 0.0))

        dynamic = self.dynamic
        if dynamic is not None:
            # The chamber model's rod follows every reference (end stops, volumes), so it
            # runs segment by segment, up to each accepted edge, as step() does.
            clamped = np.zeros(n, dtype=bool)
            temp = np.broadcast_to(np.asarray(oil_temp_c, dtype=float), t.shape)

            def advance(lo: int, hi: int) -> None:
                v[lo:hi] = dynamic.run(t[lo:hi], speed[lo:hi], torque[lo:hi], temp[lo:hi],
                                       t_last_s=float(t[lo - 1]) if lo else 0.0)
                integrate(lo, hi)
        else:
            pump_torque = torque                # the run's own copy, less the inertia term
            safe_dt = np.where(valid, dt, 1.0)
            pump_torque[1:] -= np.where(valid, self.inertia_nm_per_rpm_s * np.diff(speed)
                                        / safe_dt, 0.0)
            v[:], clamped = self.model.velocity_many(speed, pump_torque, oil_temp_c)
            integrate(0, n)

        events = []
        for order, sw in enumerate(self.switches):
            if refs is None or sw.name not in refs:
                continue
            timed = None if ref_edge_s is None or sw.name not in ref_edge_s else \
                np.asarray(ref_edge_s[sw.name], dtype=float)
            for k, c, rising in accepted_edges(t, np.asarray(refs[sw.name]), self.debounce_s):
                events.append((k, order, c, rising, sw, share_after_crossing(t, timed, c)))
        events.sort(key=lambda e: (e[0], e[1]))

        x = np.empty(n)
        u = np.empty(n)
        not_ref = np.zeros(n, dtype=bool)
        adapting = np.zeros(n, dtype=bool)
        pre_correction: dict[int, float] = {}
        log: list[ReferenceEvent] = []
        i, start = 0, self.position_mm
        x_start = start
        for k, _, c, rising, sw, after in events + [(n - 1, -1, -1, False, None, 0.5)]:
            if k >= i:
                if dynamic is not None:
                    advance(i, k + 1)
                dx = self.gain.scale_many(dx_raw[i:k + 1])
                x[i:k + 1], _ = bounded_cumsum(start, dx, self.lower_mm, self.upper_mm)
                travel = self.travel_mm + np.cumsum(np.abs(dx))
                hold = self.hold_s + np.cumsum(hold_dt[i:k + 1])
                u[i:k + 1] = self.u_base + self.per_travel * travel + self.hold_rate * hold
                self.travel_mm, self.hold_s = float(travel[-1]), float(hold[-1])
                not_ref[i:k + 1] = not self.referenced or self.reference_suspect
                adapting[i:k + 1] = self.gain.active
                i = k + 1
            if sw is None:
                break
            pre_correction.setdefault(k, float(x[k]))
            x_c = pre_correction.get(c, float(x[c]))
            x_before = float(x[c - 1]) if c > 0 else x_start
            snap = _Snapshot(c, x_c, x_c - x_before, float(v[c]), float(s_up[c]),
                             float(s_down[c]), after)
            x[k], event = self._reference(sw, rising, snap, float(x[k]),
                                         (float(s_up[k]), float(s_down[k])), k)
            if dynamic is not None:
                dynamic.set_position(float(x[k]))
            u[k] = self.uncertainty_mm
            not_ref[k] = self.reference_suspect
            adapting[k] = self.gain.active
            log.append(event)
            start = float(x[k])
        self.position_mm = float(x[-1]) if n else self.position_mm
        flags = (np.where(stale, Flags.STALE_INPUT, 0) | np.where(clamped, Flags.TABLE_CLAMPED, 0)
                 | np.where(not_ref, Flags.NOT_REFERENCED, 0)
                 | np.where(adapting, Flags.ADAPTING, 0)
                 | np.where((x <= self.lower_mm) | (x >= self.upper_mm), Flags.AT_SOFT_LIMIT, 0))
        return RunEstimate(x, v, u, flags.astype(np.uint8), log)

    def preset(self, position_mm: float, uncertainty_mm: float) -> None:
        """A manual reference (CiA 406 preset): position and uncertainty are set, and travel
        for the next adaptation counts from here."""
        self.position_mm = self._clip(position_mm)
        if self.dynamic is not None:
            self.dynamic.set_position(self.position_mm)
        self.u_base, self.travel_mm, self.hold_s = uncertainty_mm, 0.0, 0.0
        self.referenced, self.suspect_switch, self.suspect_mm = True, None, 0.0
        self.s_ref = (self._on.s_up, self._on.s_down)

    def add_uncertainty(self, mm: float) -> None:
        """Motion the estimator could not integrate (e.g. input lost): widen the bound."""
        self.u_base += abs(mm)

    def forget_switch_states(self) -> None:
        """After motion not integrated: a switch state that changed meanwhile is no edge at
        a known position; the next sample sets the state afresh."""
        for deb in self._on.debouncers:
            deb.state, deb.candidate_since_s = None, None

    # --- persistence -----------------------------------------------------------------------

    def snapshot(self) -> EstimatorState:
        return EstimatorState(actuator=self.actuator, config_hash=self.cfg.physics_hash(),
                              position_mm=self.position_mm, uncertainty_mm=self.uncertainty_mm,
                              gain_up=float(self.gain.gain[0]),
                              gain_down=float(self.gain.gain[1]))

    def restore(self, state: EstimatorState) -> None:
        """Carry on from a saved state: trusted for position, flagged until a reference (the
        chamber model's rod, see :attr:`referenced`, unknown until then)."""
        self.position_mm = self._clip(state.position_mm)
        self.u_base = state.uncertainty_mm
        self.travel_mm = self.hold_s = 0.0
        self.gain.gain = np.clip([state.gain_up, state.gain_down], 1 - self.gain.bound,
                                 1 + self.gain.bound)
        self.referenced = False
