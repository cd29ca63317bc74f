"""The extended model a diagnosis saves, and the estimator that runs it.

An extension is a small JSON file: the causes it corrects (one or several, fitted jointly),
their parameters, an optional data-driven residual model, the actuator, and the physics hash
of the configuration it was fitted under (refused under another). ``ddh-vsensor analyze``
produces it (``diagnosis/``); ``estimate``, ``run`` and ``demo`` run it (``--extension``).
Every parameter that is present is applied, together, in this order:

- ``time_offset_s`` t: the logged motor signals are taken t seconds later (offline, exactly,
  by interpolation). Online, later samples do not exist yet: for t < 0 the motor signals are
  delayed by |t|; for t > 0 the reference switches are delayed by t instead, so the estimate
  runs consistently t behind, and the position is predicted t ahead from the velocity;
- sensor corrections: ``torque_gain`` g and ``torque_offset_nm`` o (the drive's torque reads
  g * true + o), ``oil_temp_offset_c`` o (the tank sensor reads true + o);
- ``slip_percent_per_100nm`` s: the pumps turn at n (1 - s/100 |tau|/100);
- ``leakage_factor``, ``displacement_factor``: tables of the unit with scaled pumps;
- ``air_fraction``: the compressible-chamber model with that air: the estimate plus the
  difference between that model's position and the tables' (references off), counted from
  the start or the last accepted reference;
- ``low_speed_leakage`` (a cause without parameter): the speed-continuous tables;
- ``position_scale`` (the draw-wire reads s * true): the estimate is of the true position, so
  the estimator changes nothing; it is recorded for the comparison with that sensor;
- ``residual``: a linear model of the velocity error on physical features of the inputs
  (:func:`residual_features`), integrated and taken off the estimate like the chamber
  correction (counted from the start or the last reference).

Independently, ``motor_inertia`` switches the estimator's own inertia compensation on or off.
:class:`ExtendedEstimator` has the ``Estimator``'s two faces (``run`` offline, ``step``
online) and otherwise delegates to it.
"""

from __future__ import annotations

import dataclasses
import json
import math
import os
import tempfile
from collections import deque
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import ArrayLike

from ddh_vsensor.config import Config
from ddh_vsensor.errors import UserError
from ddh_vsensor.physics.unit import DDHUnit
from ddh_vsensor.tables.build import build_unit_tables
from ddh_vsensor.tables.lookup import UnitTables
from ddh_vsensor.estimator import chambers
from ddh_vsensor.estimator.estimator import Estimator, RunEstimate, Step
from ddh_vsensor.estimator.state import EstimatorState
from ddh_vsensor.estimator.timing import (shaft_torque_nm, shaft_torques_nm,
                                          torque_at_speed_instant)

FORMAT = "ddh-vsensor-extension"
FORMAT_VERSION = 2

# parameter -> neutral value (the nominal model)
NEUTRAL: dict[str, float] = {
    "leakage_factor": 1.0, "displacement_factor": 1.0, "slip_percent_per_100nm": 0.0,
    "time_offset_s": 0.0, "air_fraction": 0.0, "oil_temp_offset_c": 0.0, "torque_gain": 1.0,
    "torque_offset_nm": 0.0, "position_scale": 1.0}
# cause -> its parameter (None: a cause without one)
CAUSE_PARAMETER: dict[str, str | None] = {
    "none": None, "unexplained": None, "ambiguous": None, "low_speed_leakage": None,
    "pump_leakage": "leakage_factor", "displacement": "displacement_factor",
    "belt_slip": "slip_percent_per_100nm", "time_offset": "time_offset_s",
    "compressibility": "air_fraction", "oil_temp_offset": "oil_temp_offset_c",
    "torque_gain": "torque_gain", "torque_offset": "torque_offset_nm",
    "position_scale": "position_scale"}
RESIDUAL_FEATURES = ("velocity", "torque_per_viscosity", "torque", "speed", "speed_cubed",
                     "velocity_x_torque",
                     "torque_above_1", "torque_above_2", "torque_above_3", "torque_below_1",
                     "torque_below_2", "torque_below_3", "constant")
MU_REF_PA_S = 0.03                  # viscosity the torque-per-viscosity feature is scaled to


class ExtensionError(UserError):
    """An extension file that is unreadable, malformed or fitted for something else."""


def with_inertia_compensation(cfg: Config, on: bool) -> Config:
    """``cfg`` with the estimator's inertia compensation switched on or off."""
    if cfg.estimator.inertia_compensation == on:
        return cfg
    return dataclasses.replace(cfg, estimator=dataclasses.replace(cfg.estimator,
                                                                  inertia_compensation=on))


def slipped_speed(speed_rpm: np.ndarray, torque_nm: np.ndarray, slip: float) -> np.ndarray:
    """Motor speed the pumps see with a belt slip of ``slip`` % per 100 N*m."""
    return speed_rpm * np.maximum(1.0 - slip * 1e-4 * np.abs(torque_nm), 0.0)


def shift_signal(time_s: np.ndarray, signal: np.ndarray, shift_s: float) -> np.ndarray:
    """The signal ``shift_s`` seconds later, by linear interpolation (held at the ends)."""
    if shift_s == 0.0:
        return signal
    return np.interp(time_s + shift_s, time_s, signal)


def corrected_inputs(params: Mapping[str, float], time_s: np.ndarray, speed_rpm: np.ndarray,
                     torque_nm: np.ndarray, oil_temp_c: np.ndarray
                     ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """(motor speed, pump speed, true torque, true oil temperature) from the logged signals
    under the sensor and drive parameters of ``params`` (absent ones neutral)."""
    t_off = params.get("time_offset_s", 0.0)
    n, tau = shift_signal(time_s, speed_rpm, t_off), shift_signal(time_s, torque_nm, t_off)
    tau = (tau - params.get("torque_offset_nm", 0.0)) / params.get("torque_gain", 1.0)
    temp = oil_temp_c - params.get("oil_temp_offset_c", 0.0)
    slip = params.get("slip_percent_per_100nm", 0.0)
    return n, (slipped_speed(n, tau, slip) if slip else n), tau, temp


@dataclass(frozen=True)
class ResidualModel:
    """Velocity error (mm/s) = sum of weights x standardised features; the extension takes
    its integral off the estimate. ``knots_nm``: |torque| where the hinge features start."""

    weights: tuple[float, ...]
    scale: tuple[float, ...]
    knots_nm: tuple[float, float, float]

    def as_dict(self) -> dict[str, Any]:
        return {"features": list(RESIDUAL_FEATURES), "weights": list(self.weights),
                "scale": list(self.scale), "knots_nm": list(self.knots_nm)}

    @classmethod
    def from_dict(cls, d: Mapping[str, Any]) -> "ResidualModel":
        if list(d.get("features", [])) != list(RESIDUAL_FEATURES):
            raise ValueError(f"residual features {d.get('features')} (this version: "
                             f"{list(RESIDUAL_FEATURES)})")
        w, s, k = (tuple(float(x) for x in d[key]) for key in ("weights", "scale", "knots_nm"))
        if len(w) != len(RESIDUAL_FEATURES) or len(s) != len(w) or len(k) != 3:
            raise ValueError("residual model: wrong number of weights, scales or knots")
        return cls(w, s, k)

    def rate(self, speed_rpm: ArrayLike, torque_nm: ArrayLike, mu_pa_s: ArrayLike,
             velocity_mm_s: ArrayLike) -> np.ndarray:
        f = residual_features(speed_rpm, torque_nm, mu_pa_s, velocity_mm_s, self.knots_nm)
        return f @ (np.asarray(self.weights) / np.asarray(self.scale))


def residual_features(speed_rpm: ArrayLike, torque_nm: ArrayLike, mu_pa_s: ArrayLike,
                      velocity_mm_s: ArrayLike, knots_nm: tuple[float, ...]) -> np.ndarray:
    """[samples, features] of :data:`RESIDUAL_FEATURES`: the estimated velocity (error ~
    travel), torque over viscosity (~ pressure / viscosity: leakage), torque (~ pressure),
    motor speed, its cube (a flow loss growing with speed: pumps filling short), velocity x
    |torque| (slip), torque above +knot and below -knot for three
    knots (a valve or seal that gives way above a pressure, on one side), a constant."""
    n = np.atleast_1d(np.asarray(speed_rpm, dtype=float))
    tau = np.atleast_1d(np.asarray(torque_nm, dtype=float))
    v = np.atleast_1d(np.asarray(velocity_mm_s, dtype=float))
    mu = np.broadcast_to(np.asarray(mu_pa_s, dtype=float), tau.shape)
    return np.stack([v, tau * (MU_REF_PA_S / mu), tau, n * 1e-3, (n * 1e-3) ** 3,
                     v * np.abs(tau) * 1e-2,
                     *(np.maximum(tau - k, 0.0) for k in knots_nm),
                     *(np.minimum(tau + k, 0.0) for k in knots_nm), np.ones_like(tau)],
                    axis=-1)


def integrate_rate(time_s: np.ndarray, rate: np.ndarray, max_gap_s: float) -> np.ndarray:
    """Cumulative integral (rectangle rule at the sample's own rate, as online)."""
    dt = np.diff(time_s, prepend=time_s[:1])
    dt = np.where((dt > 0.0) & (dt <= max_gap_s), dt, 0.0)
    return np.cumsum(rate * dt)


@dataclass(frozen=True)
class Extension:
    cause: str                              # the largest contributor, or unexplained
    parameters: dict[str, float]
    actuator: str
    config_hash: str
    mode: str = "full"                      # the estimator mode it extends
    motor_inertia: bool = True              # the estimator's inertia compensation
    fitted_on: tuple[str, ...] = ()
    notes: dict[str, Any] = field(default_factory=dict)
    causes: tuple[str, ...] = ()            # every cause applied (default: ``cause``)
    residual: ResidualModel | None = None

    def __post_init__(self) -> None:
        if not self.causes:
            object.__setattr__(self, "causes", () if self.cause in ("none", "unexplained")
                               else (self.cause,))
        for c in (self.cause, *self.causes):
            if c not in CAUSE_PARAMETER:
                raise ExtensionError(f"unknown cause {c!r} (known: "
                                     f"{', '.join(CAUSE_PARAMETER)})")
        for c in self.causes:
            wanted = CAUSE_PARAMETER[c]
            if wanted is not None and wanted not in self.parameters:
                raise ExtensionError(f"cause {c} needs parameter {wanted!r}")
        for k, v in self.parameters.items():
            if k not in NEUTRAL:
                raise ExtensionError(f"unknown parameter {k!r} (known: {', '.join(NEUTRAL)})")
            if not math.isfinite(v):
                raise ExtensionError(f"parameter {k} = {v!r} is not a finite number")
        for k in ("leakage_factor", "displacement_factor", "torque_gain", "position_scale"):
            if self.parameters.get(k, 1.0) <= 0.0:
                raise ExtensionError(f"parameter {k} must be positive")

    @property
    def value(self) -> float | None:
        p = CAUSE_PARAMETER[self.cause]
        return None if p is None or p not in self.parameters else float(self.parameters[p])

    def param(self, name: str) -> float:
        return float(self.parameters.get(name, NEUTRAL[name]))

    # --- file ------------------------------------------------------------------------------

    def as_dict(self) -> dict[str, Any]:
        return {"format": FORMAT, "format_version": FORMAT_VERSION, "cause": self.cause,
                "causes": list(self.causes), "parameters": dict(self.parameters),
                "residual": None if self.residual is None else self.residual.as_dict(),
                "actuator": self.actuator, "mode": self.mode,
                "motor_inertia": self.motor_inertia, "config_hash": self.config_hash,
                "fitted_on": list(self.fitted_on), "notes": self.notes}

    def save(self, path: str | Path) -> Path:
        """Write atomically (a crash leaves the previous file)."""
        path = Path(path)
        path.parent.mkdir(parents=True, exist_ok=True)
        fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=".tmp")
        try:
            with os.fdopen(fd, "w", encoding="utf-8") as f:
                json.dump(self.as_dict(), f, indent=2)
                f.write("\n")
            os.chmod(tmp, 0o644)
            os.replace(tmp, path)
        except BaseException:
            Path(tmp).unlink(missing_ok=True)
            raise
        return path

    @classmethod
    def load(cls, path: str | Path, cfg: Config | None = None,
             actuator: str | None = None) -> "Extension":
        """Read a file; with ``cfg``/``actuator``, refuse one fitted for something else."""
        source = str(path)
        try:
            data = json.loads(Path(path).read_text(encoding="utf-8"))
        except OSError as exc:
            raise ExtensionError(f"{source}: cannot read: {exc.strerror or exc}") from None
        except (UnicodeDecodeError, json.JSONDecodeError) as exc:
            raise ExtensionError(f"{source}: not an extension file (not JSON: {exc})") \
                from None
        if not isinstance(data, dict) or data.get("format") != FORMAT:
            raise ExtensionError(f"{source}: not a ddh-vsensor extension file (written by "
                                 "'ddh-vsensor analyze --report DIR')")
        if data.get("format_version") not in (1, FORMAT_VERSION):
            raise ExtensionError(f"{source}: extension format {data.get('format_version')}, "
                                 f"this version reads 1 and {FORMAT_VERSION}")
        try:
            params = {str(k): float(v) for k, v in dict(data["parameters"]).items()}
            residual = data.get("residual")
            ext = cls(cause=str(data["cause"]), parameters=params,
                      actuator=str(data["actuator"]), config_hash=str(data["config_hash"]),
                      mode=str(data.get("mode", "full")),
                      motor_inertia=bool(data.get("motor_inertia", True)),
                      fitted_on=tuple(map(str, data.get("fitted_on", []))),
                      notes=dict(data.get("notes", {})),
                      causes=tuple(map(str, data.get("causes", []))),
                      residual=None if residual is None else ResidualModel.from_dict(residual))
        except (KeyError, TypeError, ValueError) as exc:
            raise ExtensionError(f"{source}: malformed extension file ({exc})") from None
        except ExtensionError as exc:
            raise ExtensionError(f"{source}: {exc}") from None
        if actuator is not None and ext.actuator != actuator:
            raise ExtensionError(f"{source}: fitted for the {ext.actuator}, not the {actuator}")
        if cfg is not None and ext.config_hash != cfg.physics_hash():
            raise ExtensionError(f"{source}: fitted under another configuration (physics hash "
                                 f"{ext.config_hash}, {cfg.source} has {cfg.physics_hash()}); "
                                 "run the analysis again with this configuration")
        return ext

    # --- what it changes -------------------------------------------------------------------

    def unit(self, cfg: Config) -> DDHUnit:
        unit = DDHUnit.from_config(cfg, self.actuator)
        if self.changes_tables():
            return unit.with_pumps(leakage=self.param("leakage_factor"),
                                   displacement=self.param("displacement_factor"))
        return unit

    def changes_tables(self) -> bool:
        return (self.param("leakage_factor") != 1.0
                or self.param("displacement_factor") != 1.0)

    def tables(self, cfg: Config, nominal: UnitTables | None = None) -> UnitTables:
        """The table set the extended estimator looks up (``nominal`` if unchanged)."""
        if self.changes_tables() or nominal is None:
            return build_unit_tables(cfg, self.actuator, self.unit(cfg))
        return nominal

    def estimator_mode(self, mode: str | None) -> str:
        """The mode to estimate in: the speed-continuous tables for low_speed_leakage, else
        the one asked for, else the one the extension was fitted in. Fitted in a tables' mode
        and asked for dynamic, it runs in the mode it was fitted in (its parameters make up
        for that mode's own errors, not the chamber model's)."""
        if "low_speed_leakage" in self.causes:
            return "full"
        if mode == "dynamic" and self.mode != "dynamic":
            return self.mode
        return mode or self.mode

    def estimator(self, cfg: Config, tables: UnitTables | None = None, *,
                  mode: str | None = None, references: bool = True,
                  adaptation: bool | None = None,
                  initial_position_mm: float | None = None) -> "ExtendedEstimator":
        """An estimator with this extension applied (``tables``: the nominal set to use
        when the extension does not change the tables)."""
        return ExtendedEstimator(cfg, self, tables, mode=mode, references=references,
                                 adaptation=adaptation, initial_position_mm=initial_position_mm)


class ExtendedEstimator:
    """An ``Estimator`` with an extension applied: the same faces (``run``, ``step``), and
    every other attribute read from and written to the wrapped estimator, except that
    ``position_mm``, ``snapshot`` and ``restore`` deal in the extended position. Code that
    drives an ``Estimator`` (the service's units, presets, persistence) can drive this."""

    _OWN = frozenset({"extension", "estimator", "_cfg", "_unit", "_tables_x", "_max_gap_s",
                      "_chambers", "_t", "_v", "_delayed", "_offset_mm", "_out", "_params",
                      "_air", "_resid_mm"})

    def __init__(self, cfg: Config, extension: Extension, tables: UnitTables | None = None,
                 **kwargs: Any) -> None:
        self.extension = extension
        mode = extension.estimator_mode(kwargs.pop("mode", None))
        cfg = with_inertia_compensation(cfg, extension.motor_inertia)
        self._unit = extension.unit(cfg)
        self.estimator = Estimator(cfg, extension.actuator, extension.tables(cfg, tables),
                                   mode=mode, unit=self._unit, **kwargs)
        self._cfg = cfg
        self._params = dict(extension.parameters)
        self._air = extension.param("air_fraction") > 0.0 or "compressibility" in \
            extension.causes
        self._tables_x: float | None = None     # compressibility: tables, no references
        self._v = 0.0
        self._max_gap_s = cfg.estimator.max_gap_s
        self._chambers = None
        self._t: float | None = None
        self._delayed: deque = deque()          # time_offset: (t, values) not yet due
        self._offset_mm = 0.0                   # corrections at the last reset
        self._resid_mm = 0.0                    # integrated residual model
        self._out: float | None = None          # the last extended position (online)

    def __getattr__(self, name: str) -> Any:
        return getattr(self.__dict__["estimator"], name)

    def __setattr__(self, name: str, value: Any) -> None:
        if name in self._OWN:
            object.__setattr__(self, name, value)
        else:
            setattr(self.estimator, name, value)

    @property
    def position_mm(self) -> float:
        return self.estimator.position_mm if self._out is None else self._out

    def snapshot(self) -> EstimatorState:
        state = self.estimator.snapshot()
        state.position_mm = self.position_mm
        return state

    def restore(self, state: EstimatorState) -> None:
        """Carry on from ``state`` (its position is the extended one): the corrections count
        afresh from here."""
        self.estimator.restore(state)
        self._out = None
        self._offset_mm = self._correction()

    def _correction(self) -> float:
        c = -self._resid_mm
        if self._chambers is not None and self._tables_x is not None:
            c += float(self._chambers.position_mm[0]) - self._tables_x
        return c

    # --- offline -------------------------------------------------------------------------

    def run(self, time_s: ArrayLike, speed_rpm: ArrayLike, torque_nm: ArrayLike,
            oil_temp_c: ArrayLike, refs: Mapping[str, ArrayLike] | None = None,
            ref_edge_s: Mapping[str, ArrayLike] | None = None) -> RunEstimate:
        ext = self.extension
        t = np.asarray(time_s, dtype=float)
        n, pumps_n, tau, temp = corrected_inputs(
            self._params, t, np.asarray(speed_rpm, dtype=float),
            np.asarray(torque_nm, dtype=float), np.asarray(oil_temp_c, dtype=float))
        referenced = self.estimator.referenced
        start = self.estimator.position_mm
        res = self.estimator.run(t, pumps_n, tau, temp, refs, ref_edge_s)
        if (not self._air and ext.residual is None) or len(t) == 0:
            return res
        correction = np.zeros(len(t))
        # the air acts by the chamber volumes, so it is tracked from a known position only:
        # from the start if referenced, else from the first reference on
        s0 = 0 if referenced else (res.events[0].index if res.events else len(t))
        if self._air and s0 < len(t):
            x0 = start if s0 == 0 else float(res.position_mm[s0])
            plain = Estimator(self._cfg, ext.actuator, self.estimator.model.tables,
                              mode=self.estimator.model.mode, references=False,
                              adaptation=False, initial_position_mm=x0, unit=self._unit)
            tables_x = plain.run(t[s0:], pumps_n[s0:], tau[s0:], temp[s0:]).position_mm
            ch = chambers
            air = ch.track_chambers(self._unit, [ch.ChamberRow(
                t[s0:], pumps_n[s0:],
                shaft_torques_nm(t[s0:], tau[s0:], pumps_n[s0:], self.estimator.motor,
                                 self._max_gap_s),
                temp[s0:], x0, ext.param("air_fraction"))], max_gap_s=self._max_gap_s)[0]
            correction[s0:] += air.position_mm - tables_x
        if ext.residual is not None:
            mu = self._unit.oil.dynamic_viscosity_pa_s(temp)
            correction -= integrate_rate(t, ext.residual.rate(n, tau, mu, res.velocity_mm_s),
                                         self._max_gap_s)
        since = np.zeros(len(t), dtype=np.intp)         # sample of the last reference
        for event in res.events:
            since[event.index:] = event.index
        x = res.position_mm + correction - np.where(since > 0, correction[since], 0.0)
        x = np.clip(x, self.estimator.lower_mm, self.estimator.upper_mm)
        self._out = float(x[-1])
        return RunEstimate(x, res.velocity_mm_s, res.uncertainty_mm, res.flags, res.events)

    # --- online --------------------------------------------------------------------------

    def step(self, t_s: float, speed_rpm: float, torque_nm: float, oil_temp_c: float,
             refs: Mapping[str, bool] | None = None, refs_since_s: float | None = None,
             refs_timed: bool = False) -> Step:
        """As :meth:`.Estimator.step`, on the corrected inputs."""
        ext, p = self.extension, self._params
        t_off = p.get("time_offset_s", 0.0)
        if t_off < 0.0:
            speed_rpm, torque_nm = self._delay(t_s, -t_off, (speed_rpm, torque_nm))
        elif t_off > 0.0 and refs is not None:
            refs = self._delay(t_s, t_off, refs)
            refs_since_s = None if refs_since_s is None else refs_since_s + t_off
        tau = (torque_nm - p.get("torque_offset_nm", 0.0)) / p.get("torque_gain", 1.0)
        temp = oil_temp_c - p.get("oil_temp_offset_c", 0.0)
        slip = p.get("slip_percent_per_100nm", 0.0)
        pumps_n = float(speed_rpm * max(1.0 - slip * 1e-4 * abs(tau), 0.0)) if slip \
            else speed_rpm
        reported = self.estimator.reported_torque_nm     # the sample before this one
        step = self.estimator.step(t_s, pumps_n, tau, temp, refs, refs_since_s, refs_timed)
        x = step.position_mm
        if t_off > 0.0:
            x += t_off * step.velocity_mm_s
        if not self._air and ext.residual is None:
            return self._output(step, x) if t_off > 0.0 else step
        h = None if self._t is None else t_s - self._t
        ok = h is not None and 0.0 < h <= self._max_gap_s
        mu = float(self._unit.oil.dynamic_viscosity_pa_s(temp))
        if self._air and self.estimator.referenced:     # tracked from a known position
            shaft = (shaft_torque_nm(tau, pumps_n, self.estimator.motor)
                     if self.estimator.drive_offsets else tau)
            if self._chambers is None:
                ch = chambers
                self._chambers = ch.ChamberModel(self._unit, [ext.param("air_fraction")],
                                                 pumps_n, shaft, temp, step.position_mm,
                                                 max_gap_s=self._max_gap_s)
                self._tables_x = step.position_mm
            else:
                lag_s = self.estimator.torque_lag_s
                self._chambers.advance(h, pumps_n, torque_at_speed_instant(
                    shaft, reported, h, lag_s) if ok and lag_s else shaft, mu)
                if ok:                  # the tables' own integration, no references
                    self._tables_x += 0.5 * (self._v + step.velocity_mm_s) * h
        if ext.residual is not None and ok:
            self._resid_mm += float(ext.residual.rate(speed_rpm, tau, mu,
                                                      step.velocity_mm_s)[0]) * h
        self._v = step.velocity_mm_s
        self._t = t_s
        correction = self._correction()
        if step.reference is not None:
            self._offset_mm = correction          # a reference was just accepted
        return self._output(step, x + correction - self._offset_mm)

    def _output(self, step: Step, x: float) -> Step:
        x = min(max(x, self.estimator.lower_mm), self.estimator.upper_mm)
        self._out = x
        return dataclasses.replace(step, position_mm=x)

    def _delay(self, t_s: float, delay_s: float, values: Any) -> Any:
        """``values`` as they were ``delay_s`` ago: motor signals interpolated linearly, switch
        states held (the first ones until the buffer reaches back far enough)."""
        buf = self._delayed
        buf.append((t_s, values))
        due = t_s - delay_s
        while len(buf) > 1 and buf[1][0] <= due:
            buf.popleft()
        t0, v0 = buf[0]
        if isinstance(v0, Mapping) or len(buf) == 1 or due <= t0:
            return v0
        t1, v1 = buf[1]
        w = (due - t0) / (t1 - t0)
        return tuple(a + (b - a) * w for a, b in zip(v0, v1))
