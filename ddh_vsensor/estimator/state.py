"""The estimate's persisted state: written atomically, read back only when it is sound.

Written atomically (``atomic_write``): a power cut leaves the old or the new file, never a torn
one. ``clean`` is true only in the state written at a clean stop; a periodic save (the one a
kill or power cut leaves) says false, and whoever restores it must allow for the time since
``saved_at``.

On reading, the file is opened with ``O_NOFOLLOW`` and ``O_NONBLOCK`` (a symlink, a FIFO or a
device is refused, never followed, blocked on or read endlessly), must be a regular file of at
most ``max_bytes``, and every parse problem (bad JSON, too deeply nested, out of memory,
wrong types, non-finite or negative values, another machine's state) is reported and the file
ignored, never trusted.
"""

from __future__ import annotations

import errno
import json
import logging
import math
import os
import stat
import time
from dataclasses import asdict, dataclass, field, fields
from pathlib import Path

from ddh_vsensor.atomic import atomic_write

log = logging.getLogger(__name__)

STATE_FORMAT = 2
DEFAULT_MAX_BYTES = 65536
_REASON_CHARS = 120
LEARNED_MAX = 128


@dataclass
class EstimatorState:
    actuator: str
    config_hash: str
    position_mm: float
    uncertainty_mm: float
    gain_up: float = 1.0
    gain_down: float = 1.0
    saved_at: float = 0.0          # time.time() of the write
    format: int = STATE_FORMAT
    clean: bool = False            # written at a clean stop
    # what the estimator learnt that outlives a restart, name -> value (the Kalman filter's
    # constant and slow states, each with its variance)
    learned: dict[str, float] = field(default_factory=dict)


def save_state(path: str | Path, state: EstimatorState) -> None:
    state.saved_at = time.time()
    Path(path).parent.mkdir(parents=True, exist_ok=True)
    with atomic_write(path) as fh:
        json.dump(asdict(state), fh)


def _read_regular(path: Path, max_bytes: int) -> bytes | None:
    """The file's bytes; None when it does not exist; ValueError when it is not a small
    regular file (or a symlink)."""
    flags = os.O_RDONLY | os.O_NOFOLLOW | os.O_NONBLOCK | os.O_CLOEXEC
    try:
        fd = os.open(path, flags)
    except FileNotFoundError:
        return None
    except OSError as exc:
        if exc.errno == errno.ELOOP:
            raise ValueError("a symbolic link (not followed)") from None
        raise
    with os.fdopen(fd, "rb") as fh:
        st = os.fstat(fh.fileno())
        if not stat.S_ISREG(st.st_mode):
            raise ValueError("not a regular file")
        if st.st_size > max_bytes:
            raise ValueError(f"{st.st_size} bytes, more than {max_bytes}")
        raw = fh.read(max_bytes + 1)
    if len(raw) > max_bytes:
        raise ValueError(f"more than {max_bytes} bytes")
    return raw


def _parse(raw: bytes) -> EstimatorState:
    data = json.loads(raw.decode("utf-8"))
    if not isinstance(data, dict):
        raise ValueError("not a JSON object")
    known = {f.name for f in fields(EstimatorState)}
    unknown = set(data) - known
    if unknown:
        raise ValueError(f"unknown keys {sorted(unknown)[:3]}")
    state = EstimatorState(**data)
    if not isinstance(state.actuator, str) or not isinstance(state.config_hash, str):
        raise ValueError("actuator and config_hash must be text")
    numbers = (state.position_mm, state.uncertainty_mm, state.gain_up, state.gain_down,
               state.saved_at)
    if not all(isinstance(x, (int, float)) and not isinstance(x, bool) and math.isfinite(x)
               for x in numbers):
        raise ValueError("non-finite or non-numeric values")
    if state.uncertainty_mm < 0.0 or state.gain_up <= 0.0 or state.gain_down <= 0.0 \
            or state.saved_at < 0.0:
        raise ValueError("negative uncertainty, gain or time")
    if not isinstance(state.clean, bool):
        raise ValueError("clean must be true or false")
    learned = state.learned
    if not isinstance(learned, dict) or len(learned) > LEARNED_MAX or not all(
            isinstance(k, str) and len(k) <= _REASON_CHARS and isinstance(v, (int, float))
            and not isinstance(v, bool) and math.isfinite(v) for k, v in learned.items()):
        raise ValueError(f"learned must map at most {LEARNED_MAX} names to finite numbers")
    return state


def load_state(path: str | Path, actuator: str, config_hash: str,
               max_bytes: int = DEFAULT_MAX_BYTES) -> EstimatorState | None:
    """The saved state, or None (with a warning saying why) when it must not be trusted."""
    path = Path(path)
    try:
        raw = _read_regular(path, max_bytes)
        if raw is None:
            return None
        state = _parse(raw)
    except (OSError, ValueError, TypeError, OverflowError, RecursionError, MemoryError) as exc:
        reason = f"{type(exc).__name__}: {exc}"
        if len(reason) > _REASON_CHARS:
            reason = reason[:_REASON_CHARS - 3] + "..."
        log.warning("%s: corrupt state file ignored (%s)", path, reason)
        return None
    if type(state.format) is not int or state.format != STATE_FORMAT:
        log.warning("%s: state format %r, expected %r; ignored", path, state.format,
                    STATE_FORMAT)
        return None
    if state.actuator != actuator or state.config_hash != config_hash:
        log.warning("%s: state belongs to %.40s with config %.40s, not %s with %s; ignored",
                    path, state.actuator, state.config_hash, actuator, config_hash)
        return None
    return state
