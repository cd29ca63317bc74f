"""Hall-effect reference switches: switching positions per travel direction, debouncing.

A switch at position p is on within +-window of p and goes off only beyond window +
hysteresis. So its four switching positions are known: entering from below at p - w, from
above at p + w; leaving upwards at p + w + h, downwards at p - w - h. An edge therefore tells
the position once the travel direction is known, to within the tolerance of where the switch
really switches (its mounting: a datasheet's p, w and h are nominal until commissioning
measures them).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ddh_vsensor.config import UnitConfig

# Below this |velocity| (mm/s) the direction is taken from the estimate instead.
DIRECTION_SPEED_MM_S = 0.5


@dataclass(frozen=True)
class Switch:
    name: str
    position_mm: float
    window_mm: float
    hysteresis_mm: float
    tolerance_mm: float = 0.0       # how far the real switching points may lie from these

    def switching_position_mm(self, rising: bool, moving_up: bool) -> float:
        w, h = self.window_mm, self.hysteresis_mm
        if rising:
            return self.position_mm - w if moving_up else self.position_mm + w
        return self.position_mm + w + h if moving_up else self.position_mm - w - h

    def edge_position_mm(self, rising: bool, velocity_mm_s: float, estimate_mm: float) -> float:
        """Where the rod was at an edge: by direction of travel, else nearest to the estimate."""
        if abs(velocity_mm_s) >= DIRECTION_SPEED_MM_S:
            return self.switching_position_mm(rising, velocity_mm_s > 0)
        up, down = (self.switching_position_mm(rising, d) for d in (True, False))
        return up if abs(up - estimate_mm) <= abs(down - estimate_mm) else down


def share_after_crossing(time_s: np.ndarray, edge_s: np.ndarray | None, index: int) -> float:
    """The share of edge sample ``index``'s period after the switch changed: from the
    change's own time where ``edge_s`` (:attr:`.Run.ref_edge_s`) has it within that period,
    else 0.5 (the crossing at any moment alike)."""
    if edge_s is None or index == 0:
        return 0.5
    t0, t1, te = time_s[index - 1], time_s[index], edge_s[index]
    return float((t1 - te) / (t1 - t0)) if t0 < te <= t1 else 0.5


def switches_from_config(unit: UnitConfig) -> tuple[Switch, ...]:
    return tuple(Switch(name, pos, unit.reference_window_mm, unit.reference_hysteresis_mm,
                        unit.reference_tolerance_mm)
                 for name, pos in unit.references_mm.items())


@dataclass
class Debouncer:
    """Online: a new state counts once it has held for ``debounce_s``; the edge is its first
    sample."""

    debounce_s: float
    state: bool | None = None
    candidate_since_s: float | None = None
    candidate_index: int = -1

    def update(self, t_s: float, raw: bool, index: int) -> tuple[int, bool] | None:
        """Feed one sample; returns (edge sample index, rising) when an edge is accepted."""
        if self.state is None:
            self.state = raw
            return None
        if raw == self.state:
            self.candidate_since_s = None
            return None
        if self.candidate_since_s is None:
            self.candidate_since_s, self.candidate_index = t_s, index
        if t_s - self.candidate_since_s >= self.debounce_s:
            self.state, self.candidate_since_s = raw, None
            return self.candidate_index, raw
        return None


def accepted_edges(time_s: np.ndarray, raw: np.ndarray,
                   debounce_s: float) -> list[tuple[int, int, bool]]:
    """Offline twin of :class:`Debouncer`: (accept index, edge index, rising) per edge."""
    raw = np.asarray(raw).astype(bool)
    changes = np.flatnonzero(raw[1:] != raw[:-1]) + 1
    edges = []
    state = bool(raw[0])
    for pos, c in enumerate(changes):
        if bool(raw[c]) == state:
            continue
        k = int(np.searchsorted(time_s, time_s[c] + debounce_s, side="left"))
        # Floating point: accept where the online test t - t_edge >= debounce first holds.
        while k < len(time_s) and time_s[k] - time_s[c] < debounce_s:
            k += 1
        while k > c and time_s[k - 1] - time_s[c] >= debounce_s:
            k -= 1
        nxt = changes[pos + 1] if pos + 1 < len(changes) else len(raw)
        if k < nxt:
            edges.append((k, int(c), bool(raw[c])))
            state = bool(raw[c])
    return edges
