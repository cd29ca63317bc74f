"""A DDH unit: one motor driving an A-side and a B-side pump set into one cylinder group.

Each side is a chamber connected to its pump, its relief valve, its anti-cavitation valve and
the reservoir. With dp the chamber pressure over the reservoir and v the rod velocity
(+ extending), a side's volume balance is

    sign * area * v = q_pump(n) - g_leak * dp + q_anticav(dp) - q_relief(dp)

where ``sign`` is +1 for the A side (its volume grows when extending) and -1 for the B side.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np
from numpy.typing import ArrayLike

from ddh_vsensor.config import Config, LoadConfig, MotorConfig
from ddh_vsensor.physics.cylinder import Cylinder
from ddh_vsensor.physics.oil import Oil
from ddh_vsensor.physics.pump import Pump
from ddh_vsensor.physics.conversions import BAR_PA
from ddh_vsensor.physics.valves import AntiCavitationValve, ReliefValve


@dataclass(frozen=True)
class Side:
    """One chamber with its pump set and valves."""

    name: str
    sign: int
    area_m2: float
    pump: Pump
    relief: ReliefValve
    anticav: AntiCavitationValve

    def net_inflow_m3_s(self, dp_pa: ArrayLike, speed_rpm: ArrayLike,
                        mu_pa_s: ArrayLike) -> np.ndarray:
        """Oil entering the chamber from pump, leakage and valves (not the piston motion)."""
        dp = np.asarray(dp_pa, dtype=float)
        return (self.pump.geometric_flow_m3_s(speed_rpm)
                - self.pump.leak_conductance_m3_s_pa(mu_pa_s) * dp
                + self.anticav.flow_m3_s(dp) - self.relief.flow_m3_s(dp))


@dataclass(frozen=True)
class DDHUnit:
    """Everything the physics needs to know about one actuator's drive."""

    name: str
    oil: Oil
    reservoir_pa: float
    a: Side
    b: Side
    cylinder: Cylinder
    load: LoadConfig
    motor: MotorConfig
    dead_volume_m3: float
    bulk_modulus_pa: float

    @classmethod
    def from_config(cls, cfg: Config, actuator: str) -> "DDHUnit":
        u = cfg.unit(actuator)
        oil = Oil(cfg.oil)
        hyd = cfg.hydraulics
        cyl = Cylinder.from_config(u)
        anticav = AntiCavitationValve.from_config(hyd)
        a = Side("a", +1, cyl.area_a_m2, Pump.from_config(u.pump_a, hyd, oil, +1),
                 ReliefValve.from_config(u.pump_a.relief_bar, hyd), anticav)
        b = Side("b", -1, cyl.area_b_m2, Pump.from_config(u.pump_b, hyd, oil, -1),
                 ReliefValve.from_config(u.pump_b.relief_bar, hyd), anticav)
        return cls(name=actuator, oil=oil, reservoir_pa=hyd.reservoir_pressure_bar * BAR_PA,
                   a=a, b=b, cylinder=cyl, load=u.load, motor=u.motor,
                   dead_volume_m3=u.dead_volume_l * 1e-3, bulk_modulus_pa=cfg.oil.bulk_modulus_pa)

    @property
    def sides(self) -> tuple[Side, Side]:
        return (self.a, self.b)

    def with_pumps(self, leakage: float = 1.0, displacement: float = 1.0) -> "DDHUnit":
        """The unit with every pump's leakage and displacement scaled (wear, diagnosis)."""
        return replace(self, a=replace(self.a, pump=self.a.pump.scaled(leakage, displacement)),
                       b=replace(self.b, pump=self.b.pump.scaled(leakage, displacement)))

    def load_force_n(self, payload_kg: float) -> float:
        return self.load.holding_force_n + self.load.force_per_payload_kg_n * payload_kg

    def moving_mass_kg(self, payload_kg: float) -> float:
        return self.load.mass_kg + self.load.mass_per_payload_kg * payload_kg

    def motor_torque_nm(self, dp_a_pa: ArrayLike, dp_b_pa: ArrayLike,
                        speed_rpm: ArrayLike) -> np.ndarray:
        return (self.a.pump.motor_torque_nm(dp_a_pa, speed_rpm)
                + self.b.pump.motor_torque_nm(dp_b_pa, speed_rpm))
