"""Each unit's health on its node: the health file the day-summary worker writes
(:mod:`ddh_vsensor.diagnosis.health`, ``<state_dir>/health.json``) as the nodes' objects,
read at start (a restart, even after a kill, publishes the last health at once) and taken
again whenever the worker hands over a new one. Plain JSON here: the loop does not import
the diagnosis."""

from __future__ import annotations

import json
import logging
import math
from collections.abc import Mapping
from pathlib import Path
from typing import Any

from ddh_vsensor.device.objects import Health

log = logging.getLogger(__name__)

FORMAT = "ddh-vsensor health"         # as diagnosis.health writes it


def _number(u: Mapping[str, Any], key: str) -> float | None:
    v = u.get(key)
    if v is None:
        return None
    v = float(v)
    if not math.isfinite(v):
        raise ValueError(f"{key} {v} is not finite")
    return v


def node_health(doc: Mapping[str, Any]) -> dict[str, Health]:
    """The units' health objects of a health document; ValueError if it is not one."""
    if not isinstance(doc, Mapping) or doc.get("format") != FORMAT or \
            not isinstance(doc.get("units"), Mapping):
        raise ValueError(f"not a {FORMAT} document")
    out = {}
    for actuator, u in doc["units"].items():
        try:
            interval = u.get("interval")
            out[actuator] = Health(
                cause_code=int(u["cause_code"]), alarm=bool(u["alarm"]),
                days_needed=int(u["days_needed"]), days=int(u["days"]),
                error_now_mm=_number(u, "error_now_mm"),
                error_projected_mm=_number(u, "error_projected_mm"),
                days_to_tolerance=_number(u, "days_to_tolerance"),
                value=_number(u, "value"),
                interval=None if interval is None else (float(interval[0]),
                                                        float(interval[1])))
        except (KeyError, TypeError, ValueError, IndexError) as exc:
            raise ValueError(f"unit {actuator!r}: {exc}") from None
    return out


def load_health(path: Path) -> dict[str, Health]:
    """The health as last written (none: empty); a file that cannot be read is logged and
    taken as none (the worker writes a new one with its next day)."""
    try:
        return node_health(json.loads(Path(path).read_text(encoding="utf-8")))
    except FileNotFoundError:
        return {}
    except (OSError, ValueError) as exc:
        log.warning("health: %s not read (%s); none published until the next day's "
                    "summary", path, exc)
        return {}
