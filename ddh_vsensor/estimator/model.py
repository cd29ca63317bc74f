"""Velocity model of the estimator: which table turns speed and torque into motion."""

from __future__ import annotations

from typing import Literal

import numpy as np
from numpy.typing import ArrayLike

from ddh_vsensor.tables.lookup import UnitTables

Mode = Literal["full", "paper", "dynamic"]


class VelocityModel:
    """``full``: velocity from the speed-continuous table. ``paper``: mm per revolution from
    the three-speed-range tables times the motor speed, as the paper did (the baseline).
    ``dynamic`` runs the chamber model of :mod:`.dynamic`; its steady state is the full table."""

    def __init__(self, tables: UnitTables, mode: Mode) -> None:
        if mode not in ("full", "paper", "dynamic"):
            raise ValueError(f"unknown estimator mode {mode!r}")
        self.tables, self.mode = tables, mode
        self._full = tables.full.velocity
        self._paper = tables.paper.movement_mm_per_rev
        if mode != "paper":             # per sample: straight to the table, one call less
            self.velocity = self._full  # type: ignore[method-assign]

    def velocity(self, speed_rpm: float, torque_nm: float,
                 oil_temp_c: float) -> tuple[float, bool]:
        """Cylinder velocity in mm/s, and whether the table had to clamp an input."""
        if self.mode != "paper":
            return self._full(speed_rpm, torque_nm, oil_temp_c)
        mm_rev, clamped = self._paper(speed_rpm, torque_nm, oil_temp_c)
        return mm_rev * speed_rpm / 60.0, clamped

    def velocity_many(self, speed_rpm: ArrayLike, torque_nm: ArrayLike,
                      oil_temp_c: ArrayLike) -> tuple[np.ndarray, np.ndarray]:
        if self.mode != "paper":
            return self.tables.full.velocity_many(speed_rpm, torque_nm, oil_temp_c)
        mm_rev, clamped = self.tables.paper.movement_mm_per_rev_many(speed_rpm, torque_nm,
                                                                     oil_temp_c)
        return mm_rev * np.asarray(speed_rpm, dtype=float) / 60.0, clamped
