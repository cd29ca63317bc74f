"""A measured run: one actuator's samples, as every reader (:mod:`ddh_vsensor.io`) returns it and
every consumer (estimator, diagnosis, fleet) takes it."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from ddh_vsensor.errors import UserError

REQUIRED = ("time_s", "speed_rpm", "torque_nm", "oil_temp_c", "position_mm")
PRESSURES = ("p_a_bar", "p_b_bar")
REF_PREFIX = "ref_"
MAY_BE_EMPTY = ("position_mm", *PRESSURES)   # not sampled on every row


class MeasuredDataError(UserError, ValueError):
    """A problem in a measured-data file, worded as file:line: problem."""

    def __init__(self, source: str, problem: str, line: int | None = None) -> None:
        self.source, self.problem, self.line = source, problem, line
        where = f"{source}:{line}" if line is not None else source
        super().__init__(f"{where}: {problem}")


@dataclass(eq=False)
class Run:
    """One actuator's measured samples; position_mm (and pressures) NaN where not sampled."""

    time_s: np.ndarray
    speed_rpm: np.ndarray
    torque_nm: np.ndarray
    oil_temp_c: np.ndarray
    position_mm: np.ndarray
    p_a_bar: np.ndarray | None = None
    p_b_bar: np.ndarray | None = None
    refs: dict[str, np.ndarray] = field(default_factory=dict)   # "top" -> 0/1 per sample
    comments: list[str] = field(default_factory=list)
    source: str = "<memory>"
    # "top" -> per sample, the time its switch changed to the state the sample first shows,
    # where the log timed it finer than the samples (an I/O module that sends on change of
    # state); NaN elsewhere. The CSV format has no such column: rows are its only times.
    ref_edge_s: dict[str, np.ndarray] = field(default_factory=dict)

    def __post_init__(self) -> None:
        for name in (*REQUIRED, *PRESSURES):
            value = getattr(self, name)
            if value is not None:
                setattr(self, name, np.asarray(value, dtype=np.float64))
        self.refs = {name: np.asarray(state, dtype=np.uint8) for name, state in self.refs.items()}
        lengths = {name: len(getattr(self, name)) for name in (*REQUIRED, *PRESSURES)
                   if getattr(self, name) is not None}
        lengths.update({REF_PREFIX + name: len(state) for name, state in self.refs.items()})
        self.ref_edge_s = {name: np.asarray(t, dtype=np.float64)
                           for name, t in self.ref_edge_s.items()}
        lengths.update({f"edge time of {name}": len(t) for name, t in self.ref_edge_s.items()})
        if len(set(lengths.values())) > 1:
            raise ValueError(f"run {self.source}: columns differ in length: {lengths}")
        unknown = sorted(set(self.ref_edge_s) - set(self.refs))
        if unknown:
            raise ValueError(f"run {self.source}: edge times of switch(es) without states: "
                             f"{', '.join(unknown)}")
        for name, t in self.ref_edge_s.items():
            k = np.flatnonzero(np.isfinite(t))
            bad = (k == 0) | (t[k] > self.time_s[k]) | (t[k] <= self.time_s[k - 1])
            if bad.any():
                raise ValueError(f"run {self.source}: the {name} switch's edge time "
                                 f"{t[k[bad][0]]!r} s is not within its sample's period")

    def head(self, count: int) -> Run:
        """The run's first ``count`` samples (every column, switches and edge times too), as
        views of this run's arrays: copy a column before writing into it."""
        cut = {name: getattr(self, name)[:count] for name in (*REQUIRED, *PRESSURES)
               if getattr(self, name) is not None}
        return Run(**cut, refs={k: v[:count] for k, v in self.refs.items()},
                   comments=list(self.comments), source=self.source,
                   ref_edge_s={k: v[:count] for k, v in self.ref_edge_s.items()})

    def shift_time(self, offset_s: float) -> None:
        """Move the run in time (e.g. onto the wall clock), its switches' edge times along
        (kept within their samples' periods where the coarser float of a larger time would
        round one onto the sample before)."""
        self.time_s = self.time_s + offset_s
        after = np.nextafter(np.concatenate([[-np.inf], self.time_s[:-1]]), np.inf)
        self.ref_edge_s = {name: np.clip(t + offset_s, after, self.time_s)
                           for name, t in self.ref_edge_s.items()}
