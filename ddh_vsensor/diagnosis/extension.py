"""The extended model a diagnosis saves, and the estimator that applies it.

An extension is a small JSON file: the cause, its fitted parameters, the actuator, and the
physics hash of the configuration it was fitted under (refused under another). What it does
to the estimator is the cause's physical extension (:mod:`.causes`):

- ``pump_leakage``, ``displacement``: tables built from the unit with scaled pumps;
- ``low_speed_leakage``: the speed-continuous (``full``) tables instead of the paper's;
- ``belt_slip``: the motor speed the pumps see, n (1 - s/100 |tau|/100), into the lookup;
- ``time_offset``: the motor signals taken ``t`` seconds later (offline, exactly, by
  interpolation). Online, later samples do not exist yet: for t < 0 the motor signals are
  delayed by |t| (as offline); for t > 0 the reference switches are delayed by t instead, so
  the estimate runs consistently t behind, and the position is predicted t ahead from the
  estimated velocity;
- ``compressibility``: the compressible-chamber model with the fitted air fraction: the
  estimate plus the difference between that model's position and the tables' (references
  off), counted from the start or the last accepted reference;
- ``none``: the model unchanged.

Independently of the cause, ``motor_inertia`` switches the estimator's own inertia
compensation (pump torque = motor torque less J dw/dt, :mod:`.inertia`) on or off, whichever
explained the analysed runs better.

:class:`ExtendedEstimator` has the ``Estimator``'s two faces (``run`` offline, ``step``
online) and otherwise delegates to it, so any command that builds an ``Estimator`` can build
one of these from the file instead (``extension.estimator(...)``).
"""

from __future__ import annotations

import json
import os
from collections import deque
import tempfile
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import ArrayLike

from ..config import Config
from ..errors import UserError
from ..estimator.estimator import Estimator, RunEstimate, Step
from ..estimator.state import EstimatorState
from ..physics.unit import DDHUnit
from ..tables.build import build_unit_tables
from ..tables.lookup import UnitTables
from .causes import ALL_CAUSES, slipped_speed
from ..estimator.chambers import ChamberModel, ChamberRow, track_chambers
from .inertia import with_inertia_compensation
from .workbench import shift_signal

FORMAT = "ddh-vsensor-extension"
FORMAT_VERSION = 1


class ExtensionError(UserError):
    """An extension file that is unreadable, malformed or fitted for something else."""


@dataclass(frozen=True)
class Extension:
    cause: str
    parameters: dict[str, float]
    actuator: str
    config_hash: str
    mode: str = "full"                      # the estimator mode it extends
    motor_inertia: bool = True              # the estimator's inertia compensation (:mod:`.inertia`)
    fitted_on: tuple[str, ...] = ()
    notes: dict[str, Any] = field(default_factory=dict)

    def __post_init__(self) -> None:
        if self.cause not in ALL_CAUSES:
            raise ExtensionError(f"unknown cause {self.cause!r} (known: "
                                 f"{', '.join(ALL_CAUSES)})")
        wanted = ALL_CAUSES[self.cause].parameter
        if wanted is not None and wanted not in self.parameters:
            raise ExtensionError(f"cause {self.cause} needs parameter {wanted!r}")

    @property
    def value(self) -> float | None:
        p = ALL_CAUSES[self.cause].parameter
        return None if p is None else float(self.parameters[p])

    # --- file ------------------------------------------------------------------------------

    def as_dict(self) -> dict[str, Any]:
        return {"format": FORMAT, "format_version": FORMAT_VERSION, "cause": self.cause,
                "parameters": dict(self.parameters), "actuator": self.actuator,
                "mode": self.mode, "motor_inertia": self.motor_inertia,
                "config_hash": self.config_hash,
                "fitted_on": list(self.fitted_on), "summary": ALL_CAUSES[self.cause].summary,
                "notes": self.notes}

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
        if data.get("format_version") != FORMAT_VERSION:
            raise ExtensionError(f"{source}: extension format {data.get('format_version')}, "
                                 f"this version reads {FORMAT_VERSION}")
        try:
            params = {str(k): float(v) for k, v in dict(data["parameters"]).items()}
            ext = cls(cause=str(data["cause"]), parameters=params,
                      actuator=str(data["actuator"]), config_hash=str(data["config_hash"]),
                      mode=str(data.get("mode", "full")),
                      motor_inertia=bool(data.get("motor_inertia", True)),
                      fitted_on=tuple(map(str, data.get("fitted_on", []))),
                      notes=dict(data.get("notes", {})))
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
        if self.cause == "pump_leakage":
            return unit.with_pumps(leakage=self.value)
        if self.cause == "displacement":
            return unit.with_pumps(displacement=self.value)
        return unit

    def changes_tables(self) -> bool:
        return self.cause in ("pump_leakage", "displacement")

    def tables(self, cfg: Config, nominal: UnitTables | None = None) -> UnitTables:
        """The table set the extended estimator looks up (``nominal`` if unchanged)."""
        if self.changes_tables() or nominal is None:
            return build_unit_tables(cfg, self.actuator, self.unit(cfg))
        return nominal

    def estimator_mode(self, mode: str | None) -> str:
        """The mode to estimate in: the speed-continuous tables for low_speed_leakage, else
        the one asked for, else the one the extension was fitted in."""
        return "full" if self.cause == "low_speed_leakage" else mode or self.mode

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
                      "_chambers", "_t", "_v", "_delayed", "_offset_mm", "_out"})

    def __init__(self, cfg: Config, extension: Extension, tables: UnitTables | None = None,
                 **kwargs: Any) -> None:
        self.extension = extension
        mode = extension.estimator_mode(kwargs.pop("mode", None))
        cfg = with_inertia_compensation(cfg, extension.motor_inertia)
        self.estimator = Estimator(cfg, extension.actuator, extension.tables(cfg, tables),
                                   mode=mode, **kwargs)
        self._cfg = cfg
        self._unit = DDHUnit.from_config(cfg, extension.actuator)
        self._tables_x: float | None = None     # compressibility: tables, no references
        self._v = 0.0
        self._max_gap_s = cfg.estimator.max_gap_s
        self._chambers: ChamberModel | None = None
        self._t: float | None = None
        self._delayed: deque = deque()          # time_offset: (t, values) not yet due
        self._offset_mm = 0.0                   # compressibility: correction at the last reset
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
        if self._chambers is not None and self._tables_x is not None:
            self._offset_mm = float(self._chambers.position_mm[0]) - self._tables_x

    # --- offline -------------------------------------------------------------------------

    def run(self, time_s: ArrayLike, speed_rpm: ArrayLike, torque_nm: ArrayLike,
            oil_temp_c: ArrayLike, refs: Mapping[str, ArrayLike] | None = None) -> RunEstimate:
        ext = self.extension
        t = np.asarray(time_s, dtype=float)
        n = np.asarray(speed_rpm, dtype=float)
        tau = np.asarray(torque_nm, dtype=float)
        temp = np.asarray(oil_temp_c, dtype=float)
        if ext.cause == "time_offset":
            n, tau = shift_signal(t, n, ext.value), shift_signal(t, tau, ext.value)
        pumps_n = slipped_speed(n, tau, ext.value) if ext.cause == "belt_slip" else n
        start = self.estimator.position_mm
        if ext.cause == "compressibility" and len(t):
            plain = Estimator(self._cfg, ext.actuator, self.estimator.model.tables,
                              mode=self.estimator.model.mode, references=False,
                              adaptation=False, initial_position_mm=start)
            tables_x = plain.run(t, pumps_n, tau, temp).position_mm
        res = self.estimator.run(t, pumps_n, tau, temp, refs)
        if ext.cause != "compressibility" or len(t) == 0:
            return res
        air = track_chambers(self._unit, [ChamberRow(t, n, tau, temp, start, ext.value)],
                             max_gap_s=self._max_gap_s)[0]
        correction = air.position_mm - tables_x
        since = np.zeros(len(t), dtype=np.intp)         # sample of the last reference
        for event in res.events:
            since[event.index:] = event.index
        x = res.position_mm + correction - np.where(since > 0, correction[since], 0.0)
        x = np.clip(x, self.estimator.lower_mm, self.estimator.upper_mm)
        self._out = float(x[-1])
        return RunEstimate(x, res.velocity_mm_s, res.uncertainty_mm, res.flags, res.events)

    # --- online --------------------------------------------------------------------------

    def step(self, t_s: float, speed_rpm: float, torque_nm: float, oil_temp_c: float,
             refs: Mapping[str, bool] | None = None) -> Step:
        ext = self.extension
        if ext.cause == "time_offset":
            if ext.value < 0.0:
                speed_rpm, torque_nm = self._delay(t_s, -ext.value, (speed_rpm, torque_nm))
            elif refs is not None:
                refs = self._delay(t_s, ext.value, refs)
        pumps_n = speed_rpm
        if ext.cause == "belt_slip":
            pumps_n = float(slipped_speed(np.array(speed_rpm), np.array(torque_nm), ext.value))
        step = self.estimator.step(t_s, pumps_n, torque_nm, oil_temp_c, refs)
        if ext.cause == "time_offset" and ext.value > 0.0:
            x = step.position_mm + ext.value * step.velocity_mm_s
            return self._output(step, x)
        if ext.cause != "compressibility":
            return step
        mu = float(self._unit.oil.dynamic_viscosity_pa_s(oil_temp_c))
        if self._chambers is None:
            self._chambers = ChamberModel(self._unit, [ext.value], speed_rpm, torque_nm,
                                          oil_temp_c, step.position_mm,
                                          max_gap_s=self._max_gap_s)
            self._tables_x, self._v = step.position_mm, step.velocity_mm_s
        else:
            h = t_s - self._t
            self._chambers.advance(h, speed_rpm, torque_nm, mu)
            if 0.0 < h <= self._max_gap_s:      # the tables' own integration, no references
                self._tables_x += 0.5 * (self._v + step.velocity_mm_s) * h
            self._v = step.velocity_mm_s
        self._t = t_s
        correction = float(self._chambers.position_mm[0]) - self._tables_x
        if refs and self.estimator.travel_mm == 0.0 and self.estimator.hold_s == 0.0:
            self._offset_mm = correction          # a reference was just accepted
        return self._output(step, step.position_mm + correction - self._offset_mm)

    def _output(self, step: Step, x: float) -> Step:
        x = min(max(x, self.estimator.lower_mm), self.estimator.upper_mm)
        self._out = x
        return Step(x, step.velocity_mm_s, step.uncertainty_mm, step.flags)

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
