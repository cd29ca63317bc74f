"""The state flags of a published position: one type for the estimator, the frames (POSITION
``Status``, DIAG ``Flags``, their DBC bit signals), the object dictionary and the logs."""

from __future__ import annotations

import enum


class Flags(enum.IntFlag):
    """Why a position is not (yet) a plain, trusted reading."""

    STALE_INPUT = 0x01                  # input missing or too old: position not integrated
    NOT_REFERENCED = 0x02               # no Hall reference (or a cold start) since power-up
    AT_SOFT_LIMIT = 0x04                # clamped at a stroke end (plus margin)
    ADAPTING = 0x08                     # learning travel gains at references
    TABLE_CLAMPED = 0x10                # an input left the movement table's grid
    PRESET_UNCONFIRMED = 0x20           # set by a preset, not yet confirmed by a reference
    CONTROLLER_NOT_OPERATIONAL = 0x40   # the motor controller's heartbeat says so
    MODEL_INCONSISTENT = 0x80           # the Kalman filter's torque or edges fail its self-check


# The flags that warn a position may be off by more than its uncertainty: a consumer must not
# take it plainly. The others say where the rod is (a stroke end) or what the estimator does.
EXPLAINING = (Flags.STALE_INPUT | Flags.NOT_REFERENCED | Flags.TABLE_CLAMPED
              | Flags.PRESET_UNCONFIRMED | Flags.CONTROLLER_NOT_OPERATIONAL
              | Flags.MODEL_INCONSISTENT)


def flag_text(flags: int) -> str:
    """``stale_input,not_referenced`` or ``ok``: the flags as logs and the CLI print them."""
    return ",".join((f.name or "").lower() for f in Flags if flags & f) or "ok"
