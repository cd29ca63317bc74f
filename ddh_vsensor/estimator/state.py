"""The estimate's persisted state: written atomically, read back only when it is sound.

Written atomically (``atomic_write``): a power cut leaves the old or the new file, never a torn
one. On reading, anything
corrupt or meant for another machine is reported and ignored, never trusted.
"""

from __future__ import annotations

import json
import logging
import math
import time
from dataclasses import asdict, dataclass
from pathlib import Path

from ..atomic import atomic_write

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
    state.saved_at = time.time()
    Path(path).parent.mkdir(parents=True, exist_ok=True)
    with atomic_write(path) as fh:
        json.dump(asdict(state), fh)


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
