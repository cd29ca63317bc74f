"""The estimates across restarts: one state file per unit in the state directory, written
atomically (in a worker thread while running), read back at start.

A restored estimate is trusted at its saved uncertainty only when it was written at a clean
stop; a periodic save (what a kill leaves) is widened by the worst travel possible since it
was written (wall clock), a save from the future or of unknown age by the whole stroke.
Restored or not, the unit starts not referenced, until a reference switch or an SDO preset.

Beside each estimate, ``<unit>.parameters.json``: the CANopen parameters a master stored in
that unit's sensor node (0x1010, :mod:`ddh_vsensor.device.storage`), applied before it boots.
"""

from __future__ import annotations

import logging
import math
import time
from collections.abc import Callable, Mapping
from pathlib import Path

from ddh_vsensor.atomic import remove_temp_files
from ddh_vsensor.config import Config
from ddh_vsensor.estimator.state import EstimatorState, load_state, save_state
from ddh_vsensor.device.objects import Published
from ddh_vsensor.device.storage import ParameterStore
from ddh_vsensor.service.unit_state import Unit

log = logging.getLogger(__name__)


class StateStore:
    """``restore(units)`` once at start; ``snapshots(...)`` and :func:`write_states` to save.
    ``state_dir`` None: nothing persisted."""

    def __init__(self, cfg: Config, state_dir: Path | None) -> None:
        self.cfg, self.state_dir = cfg, state_dir

    def path(self, actuator: str) -> Path | None:
        return None if self.state_dir is None else Path(self.state_dir) / f"{actuator}.json"

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
