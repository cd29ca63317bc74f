"""The estimates across restarts: one state file per unit in the state directory, written
atomically (in a worker thread while running), read back at start.

A restored estimate is trusted at its saved uncertainty only when it was written at a clean
stop; a periodic save (what a kill leaves) is widened by the worst travel possible since it
was written (wall clock), a save from the future or of unknown age by the whole stroke.
Restored or not, the unit starts not referenced, until a reference switch or an SDO preset.

Beside each estimate, ``<unit>.parameters.json``: the CANopen parameters a master stored in
that unit's sensor node (0x1010, :mod:`ddh_vsensor.device.storage`), applied before it boots;
and ``<unit>.switches.json``: its reference switches' spans and drift verdicts
(:mod:`ddh_vsensor.estimator.switch_drift`), written atomically with the estimates when they
changed. A file of their own: they stand whatever becomes of the estimate (widened after a
kill, ignored under another physics hash), and each switch's are kept as long as its
configured window and hysteresis stay as they were.
"""

from __future__ import annotations

import json
import logging
import math
import time
from collections.abc import Callable, Mapping
from pathlib import Path
from typing import Any

from ddh_vsensor.atomic import atomic_write, remove_temp_files
from ddh_vsensor.config import Config
from ddh_vsensor.estimator.state import EstimatorState, _read_regular, load_state, save_state
from ddh_vsensor.estimator.switch_drift import Change
from ddh_vsensor.device.objects import Published
from ddh_vsensor.device.storage import ParameterStore
from ddh_vsensor.service.unit_state import Unit

log = logging.getLogger(__name__)


class StateStore:
    """``restore(units)`` once at start; ``snapshots(...)`` and :func:`write_states` to save.
    ``state_dir`` None: nothing persisted."""

    def __init__(self, cfg: Config, state_dir: Path | None) -> None:
        self.cfg, self.state_dir = cfg, state_dir
        self._recorded: dict[str, int] = {}     # unit -> switch_drift.version last written

    def path(self, actuator: str) -> Path | None:
        return None if self.state_dir is None else Path(self.state_dir) / f"{actuator}.json"

    def switches_path(self, actuator: str) -> Path | None:
        """Where ``actuator``'s reference switches' spans are kept."""
        return switches_path(self.state_dir, actuator)

    def parameters_path(self, actuator: str) -> Path | None:
        """Where ``actuator``'s sensor node keeps the parameters stored over 0x1010."""
        return None if self.state_dir is None else \
            Path(self.state_dir) / f"{actuator}.parameters.json"

    def restore(self, units: Mapping[str, Unit]) -> None:
        cfg = self.cfg
        for actuator, unit in units.items():
            parameters = self.parameters_path(actuator)
            if parameters is not None and unit.node is not None:
                unit.node.attach_storage(ParameterStore(parameters, unit.node.node_id))
            path = self.path(actuator)
            state = None
            if path is not None:
                for tmp in remove_temp_files(path):
                    log.info("%s: removed %s, left by an interrupted save", actuator, tmp.name)
                state = load_state(path, actuator, cfg.physics_hash(),
                                   max_bytes=cfg.faults.state_file_max_bytes)
            self._restore_switches(actuator, unit)
            est = unit.estimator
            if state is not None:
                est.restore(state)
                unit.restored = True
                if not state.clean:
                    age_s = time.time() - state.saved_at
                    if not math.isfinite(age_s) or age_s < 0.0:
                        unit.widen(math.inf, "a saved state from the future")
                    else:
                        unit.widen(unit.max_speed_mm_s * age_s,
                                   f"{age_s:.1f} s since the last periodic save (no clean "
                                   "stop)")
                log.info("%s: estimate restored from %s (%s): %.2f mm +-%.2f mm (not "
                         "referenced until the next reference switch)", actuator, path,
                         "clean stop" if state.clean else "periodic save", est.position_mm,
                         est.uncertainty_mm)
            else:
                stroke = cfg.unit(actuator).stroke_mm
                est.restore(EstimatorState(actuator, cfg.physics_hash(), 0.0, stroke))
                log.info("%s: no saved estimate; starting at 0 mm, uncertainty the whole stroke "
                         "(%g mm), until a reference switch or an SDO preset", actuator, stroke)

    def _restore_switches(self, actuator: str, unit: Unit) -> None:
        path = self.switches_path(actuator)
        if path is None:
            return
        for tmp in remove_temp_files(path):
            log.info("%s: removed %s, left by an interrupted save", actuator, tmp.name)
        drift = unit.switch_drift
        try:
            record = load_switch_record(path, actuator, self.cfg.faults.state_file_max_bytes)
            if record is None:
                return
            restored = drift.restore(record)
        except (OSError, ValueError, TypeError, RecursionError, MemoryError) as exc:
            log.warning("%s: switch record %s ignored (%s: %.120s): spans measured afresh",
                        actuator, path, type(exc).__name__, exc)
            return
        self._recorded[actuator] = drift.version
        for name in restored:
            spans = drift.switches[name]
            if spans.drifted:
                unit.report_drift(Change(name, True, spans.describe()), restored=True)

    def switch_records(self, units: Mapping[str, Unit]) -> list[tuple[Path, dict[str, Any]]]:
        """The switch records changed since they were last taken."""
        out = []
        for actuator, unit in units.items():
            path = self.switches_path(actuator)
            version = unit.switch_drift.version
            if path is not None and self._recorded.get(actuator) != version:
                self._recorded[actuator] = version
                out.append((path, {"actuator": actuator, **unit.switch_drift.record()}))
        return out

    def snapshots(self, units: Mapping[str, Unit], published: Callable[[Unit], Published],
                  clean: bool = False) -> list[tuple[Path, EstimatorState]]:
        """Every unit's estimate now, at its published uncertainty (a stale unit's grown
        bound included); ``clean`` only at a clean stop."""
        out = []
        for actuator, unit in units.items():
            path = self.path(actuator)
            if path is not None:
                state = unit.estimator.snapshot()
                state.uncertainty_mm = published(unit).uncertainty_mm
                state.clean = clean
                out.append((path, state))
        return out


def write_states(snapshots: list[tuple[Path, EstimatorState]]) -> None:
    for path, state in snapshots:
        try:
            save_state(path, state)
        except OSError as exc:
            log.error("cannot save the estimate to %s: %s", path, exc)


def switches_path(state_dir: Path | None, actuator: str) -> Path | None:
    return None if state_dir is None else Path(state_dir) / f"{actuator}.switches.json"


def load_switch_record(path: Path, actuator: str, max_bytes: int) -> dict[str, Any] | None:
    """A unit's switch record as written (None: no file); ValueError when it is not a small
    regular file of JSON for ``actuator``, OSError when it cannot be read."""
    raw = _read_regular(Path(path), max_bytes)
    if raw is None:
        return None
    record = json.loads(raw.decode("utf-8"))
    if not isinstance(record, dict) or record.get("actuator") != actuator:
        raise ValueError(f"not {actuator}'s switch record")
    return record


def write_switch_records(records: list[tuple[Path, dict[str, Any]]]) -> None:
    for path, record in records:
        try:
            path.parent.mkdir(parents=True, exist_ok=True)
            with atomic_write(path) as fh:
                json.dump({**record, "saved_at": time.time()}, fh)
        except OSError as exc:
            log.error("cannot save the switch record to %s: %s", path, exc)
