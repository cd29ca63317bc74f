"""The estimate's persisted state: written atomically, read back only when it is sound.

Write: temp file in the same directory, fsync, rename over the old file, fsync the directory.
A power cut leaves either the old or the new file, never a torn one. On reading, anything
corrupt or meant for another machine is reported and ignored, never trusted.
"""

from __future__ import annotations

import json
import logging
import math
import os
import tempfile
import time
from dataclasses import asdict, dataclass
from pathlib import Path

log = logging.getLogger(__name__)

STATE_FORMAT = 2


@dataclass
class EstimatorState:
    actuator: str
    config_hash: str
    position_mm: float
    uncertainty_mm: float
    gain_up: float = 1.0
    gain_down: float = 1.0
    saved_at: float = 0.0
    format: int = STATE_FORMAT


def save_state(path: str | Path, state: EstimatorState) -> None:
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    state.saved_at = time.time()
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=".tmp")
    try:
        with os.fdopen(fd, "w", encoding="utf-8") as fh:
            json.dump(asdict(state), fh)
            fh.flush()
            os.fsync(fh.fileno())
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise
    dir_fd = os.open(path.parent, os.O_RDONLY)
    try:
        os.fsync(dir_fd)
    finally:
        os.close(dir_fd)


def load_state(path: str | Path, actuator: str, config_hash: str) -> EstimatorState | None:
    """The saved state, or None (with a warning saying why) when it must not be trusted."""
    path = Path(path)
    if not path.exists():
        return None
    try:
        data = json.loads(path.read_text(encoding="utf-8"))
        state = EstimatorState(**data)
        numbers = (state.position_mm, state.uncertainty_mm, state.gain_up, state.gain_down)
        if not all(isinstance(x, (int, float)) and math.isfinite(x) for x in numbers):
            raise ValueError("non-finite or non-numeric values")
    except (OSError, ValueError, TypeError) as exc:
        log.warning("%s: corrupt state file ignored (%s)", path, exc)
        return None
    if state.format != STATE_FORMAT:
        log.warning("%s: state format %s, expected %s; ignored", path, state.format, STATE_FORMAT)
        return None
    if state.actuator != actuator or state.config_hash != config_hash:
        log.warning("%s: state belongs to %s with config %s, not %s with %s; ignored", path,
                    state.actuator, state.config_hash, actuator, config_hash)
        return None
    return state
