"""Machine configuration: the settings as frozen dataclasses, each field with its bounds.

Validation (:mod:`.validate`) is driven by these fields themselves (type hints plus ``metadata``
bounds), so a new setting is one field; cross-field rules are each dataclass's ``check``.
"""

from __future__ import annotations

import dataclasses
import hashlib
import math
import re
import json
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Literal

from ddh_vsensor.config.errors import UnknownUnitError

DEFAULT_CONFIG = Path(__file__).parents[1] / "data" / "loader.yaml"


def _positive(**extra: Any) -> dict[str, Any]:
    return {"gt": 0.0, **extra}


def _structure(**bounds: Any) -> dict[str, Any]:
    """A plant-structure key: physics, but hashed only where it differs from its default 0
    (the nominal model), so that a configuration without it keeps its physics hash and with
    it the state files and table sets keyed by that hash."""
    return {"ge": 0.0, **bounds, "hash_if_set": True}


@dataclass(frozen=True)
class OilConfig:
    """Hydraulic oil: two viscosity points for ASTM D341 and a linear thermal expansion."""

    name: str
    viscosity_cst_at_40c: float = field(metadata=_positive(le=10000.0))
    viscosity_cst_at_100c: float = field(metadata=_positive(le=10000.0))
    density_kg_m3_at_15c: float = field(metadata=_positive(le=5000.0))
    thermal_expansion_per_k: float = field(metadata={"ge": 0.0, "lt": 0.01})
    bulk_modulus_pa: float = field(metadata=_positive(le=1e11))

    def check(self, path: str) -> list[tuple[str, str]]:
        if self.viscosity_cst_at_100c >= self.viscosity_cst_at_40c:
            return [(f"{path}.viscosity_cst_at_100c", "must be below viscosity_cst_at_40c "
                     "(oil thins when it warms)")]
        return []


@dataclass(frozen=True)
class HydraulicsConfig:
    """Circuit-wide settings: reservoir, pump rating point, valve characteristics."""

    reservoir_pressure_bar: float = field(metadata={"ge": -1.0, "le": 100.0})
    nominal_pressure_bar: float = field(metadata=_positive(le=2000.0))
    nominal_pump_speed_rpm: float = field(metadata=_positive(le=100000.0))
    nominal_viscosity_cst: float = field(metadata=_positive(le=10000.0))
    anticavitation_cracking_bar: float = field(metadata={"ge": 0.0, "le": 1.0})
    anticavitation_gradient_lpm_per_bar: float = field(metadata=_positive(le=1e6))
    relief_rise_fraction: float = field(metadata=_positive(le=1.0))
    relief_rise_flow_lpm: float = field(metadata=_positive(le=1e6))
    # the hoses' walls expand with pressure: the dead volume grows by this share per 100 bar
    # (a chamber's capacitance gains dead volume x share / 100 bar beyond the oil's bulk
    # modulus; 0.01 is a wire-braided hose's wall modulus of ~1 GPa). The unit model's, the
    # Kalman filter's and the simulator's; the tables' steady state does not carry it, nor
    # does the `dynamic` mode's chamber model
    hose_expansion_per_100bar: float = field(default=0.0, metadata=_structure(le=0.2))
    # free air entrained in the oil, as a volume share at atmospheric pressure: the chambers'
    # compliance collapses at low pressure where it is not yet compressed (a mobile
    # machine's oil holds a few tenths of a percent; ``physics/air.py``'s mixture law). The
    # unit model's, the Kalman filter's and the simulator's; not the tables' steady state's
    # nor the `dynamic` mode's
    air_fraction: float = field(default=0.0, metadata=_structure(le=0.2))
    # the oil temperature sensor's thermal lag behind the oil the pumps work (s): the pumps'
    # oil is the reading plus this lag times the reading's rate (``physics/tank_sensor.py``;
    # a tank sensor: minutes). The Kalman filter's and the commissioning's; not the tables'
    # nor the `dynamic` mode's
    oil_temp_lag_s: float = field(default=0.0, metadata=_structure(le=3600.0))


@dataclass(frozen=True)
class PumpConfig:
    """One side's pump set (pumps in parallel act as one) and that side's relief valve."""

    displacement_cm3_rev: float = field(metadata=_positive(le=10000.0))
    volumetric_efficiency: float = field(metadata={"gt": 0.0, "le": 1.0})
    hydromechanical_efficiency: float = field(metadata={"gt": 0.0, "le": 1.0})
    max_speed_rpm: float = field(metadata=_positive(le=100000.0))
    speed_ratio: float = field(metadata=_positive(le=100.0))
    relief_bar: float = field(metadata=_positive(le=2000.0))
    # of the leakage at the rating point (nominal pressure and viscosity), the share through
    # orifices (~ sqrt dp, viscosity-free) rather than the laminar gaps (~ dp / viscosity)
    # the volumetric efficiency is rated for; the rating point's leakage is kept. The unit
    # model's, the Kalman filter's and the simulator's; the tables' steady state does not
    # carry it, nor does the `dynamic` mode's chamber model
    leakage_orifice_share: float = field(default=0.0, metadata=_structure(le=0.9))
    # leakage rising with the pump's shaft speed n: x (1 + g |n| / n_rated) / (1 + g), n_rated
    # hydraulics.nominal_pump_speed_rpm (the rating point's leakage kept). The unit model's,
    # the Kalman filter's and the simulator's; the tables' steady state does not carry it,
    # nor does the `dynamic` mode's chamber model
    leakage_speed_gain: float = field(default=0.0, metadata=_structure(le=2.0))
    # this pump's leakage band where commissioning measured it (relative, +-); unset: the
    # machine's tolerances.pump_leakage. What is known, not physics: the tables and the hash
    # do not depend on it
    leakage_tolerance: float | None = field(default=None, metadata={"ge": 0.0, "le": 1.0})


@dataclass(frozen=True)
class LoadConfig:
    """External load at the rod(s); positive force pushes the rod in (held by the A side)."""

    holding_force_n: float = field(metadata={"ge": -1e8, "le": 1e8})
    force_per_payload_kg_n: float = field(metadata={"ge": -1e4, "le": 1e4})
    mass_kg: float = field(metadata=_positive(le=1e7))
    mass_per_payload_kg: float = field(metadata={"ge": 0.0, "le": 1e4})


@dataclass(frozen=True)
class MotorConfig:
    """Electric motor limits, the rotating inertia of motor plus pumps, and how far behind
    its speed the drive reports its torque (``torque_lag_s``: the inertia torque is the
    speed's change, so the two must describe the same instants; negative where the speed is
    the older)."""

    inertia_kg_m2: float = field(metadata=_positive(le=100.0))
    torque_limit_nm: float = field(metadata=_positive(le=100000.0))
    speed_limit_rpm: float = field(metadata=_positive(le=100000.0))
    torque_lag_s: float = field(default=0.0005, metadata={"ge": -0.005, "le": 0.005})
    # The drive's torque is its estimate from the currents, not the shaft's: it reads
    # torque_gain times the shaft's plus torque_offset_nm, plus torque_speed_offset_nm at the
    # speed limit (the motor's own speed-proportional losses), and trails the shaft's by a
    # first-order filter of torque_filter_s. How the drive reports, not physics (not
    # hashed): every estimator takes the shaft's torque from its reading through them
    # (commissioning measures them where the chamber pressures are logged)
    torque_gain: float = field(default=1.0, metadata={"ge": 0.5, "le": 2.0,
                                                      "hash_if_set": True})
    torque_offset_nm: float = field(default=0.0, metadata={"ge": -100.0, "le": 100.0})
    torque_speed_offset_nm: float = field(default=0.0, metadata={"ge": -100.0, "le": 100.0})
    torque_filter_s: float = field(default=0.0, metadata={"ge": 0.0, "le": 0.05})
    # what is known of the offset (N*m, one sigma); unset: the machine's
    # tolerances.torque_offset_nm. What is known, not physics
    torque_offset_tolerance_nm: float | None = field(default=None,
                                                     metadata={"ge": 0.0, "le": 100.0})


@dataclass(frozen=True)
class UnitConfig:
    """One DDH unit: motor, two pump sides, cylinder(s) and load."""

    cylinders: int = field(metadata={"ge": 1, "le": 16})
    stroke_mm: float = field(metadata=_positive(le=100000.0))
    area_a_mm2: float = field(metadata=_positive(le=1e7))
    area_b_mm2: float = field(metadata=_positive(le=1e7))
    friction_static_n: float = field(metadata={"ge": 0.0, "le": 1e7})
    friction_coulomb_n: float = field(metadata={"ge": 0.0, "le": 1e7})
    friction_viscous_n_s_per_m: float = field(metadata={"ge": 0.0, "le": 1e9})
    dead_volume_l: float = field(metadata=_positive(le=1000.0))
    pump_a: PumpConfig
    pump_b: PumpConfig
    load: LoadConfig
    motor: MotorConfig
    references_mm: dict[str, float]
    reference_window_mm: float = field(metadata=_positive(le=1000.0))
    reference_hysteresis_mm: float = field(metadata={"ge": 0.0, "le": 1000.0})
    # How far each switch's real switching points may lie from the configured ones: a mounting
    # tolerance until commissioning measures them; a reference carries it in its uncertainty.
    reference_tolerance_mm: float = field(default=3.0, metadata={"ge": 0.0, "le": 100.0})
    # seal friction rising with the chamber pressures: the Coulomb and the static friction
    # each gain this share of the gauge pressure's force on the seals' contact rings (4 mm
    # wide: the piston seal's on the bore for A and B, the rod seal's on the rod for B; 0.03
    # is lubricated polyurethane or PTFE on steel). The unit model's, the Kalman filter's and
    # the simulator's; the tables' steady state does not carry it, nor does the `dynamic`
    # mode's chamber model
    seal_friction_share: float = field(default=0.0, metadata=_structure(le=0.2))
    # the unit's delivered displacement band where commissioning measured it (relative, +-);
    # unset: the machine's tolerances.pump_displacement. Not physics (not hashed)
    displacement_tolerance: float | None = field(default=None, metadata={"ge": 0.0, "le": 0.2})

    def check(self, path: str) -> list[tuple[str, str]]:
        problems = []
        if self.area_b_mm2 >= self.area_a_mm2:
            problems.append((f"{path}.area_b_mm2", f"rod-side area {self.area_b_mm2} must be "
                             f"smaller than the piston-side area {self.area_a_mm2}"))
        if self.friction_coulomb_n > self.friction_static_n:
            problems.append((f"{path}.friction_coulomb_n", "must not exceed friction_static_n"))
        for name, ref in self.references_mm.items():
            if not 0.0 <= ref <= self.stroke_mm:
                problems.append((f"{path}.references_mm.{name}",
                                 f"{ref} mm lies outside the stroke 0..{self.stroke_mm} mm"))
        return problems


@dataclass(frozen=True)
class TablesConfig:
    """Grid of the movement tables."""

    temperatures_c: tuple[float, ...]
    speed_step_rpm: float = field(metadata=_positive(ge=1.0, le=10000.0))
    torque_step_nm: float = field(metadata=_positive(ge=0.01, le=1000.0))
    paper_speed_ranges_rpm: tuple[float, ...]

    def check(self, path: str) -> list[tuple[str, str]]:
        problems = []
        if len(self.temperatures_c) != 3 or not (
                self.temperatures_c[0] < self.temperatures_c[1] and self.temperatures_c[2] > 0):
            problems.append((f"{path}.temperatures_c", "must be [start, stop, step] with "
                             "start < stop and step > 0"))
        edges = self.paper_speed_ranges_rpm
        if len(edges) != 4 or edges[0] != 0.0 or any(b <= a for a, b in zip(edges, edges[1:])):
            problems.append((f"{path}.paper_speed_ranges_rpm", "must be four increasing edges "
                             "starting at 0 (three speed ranges)"))
        return problems


@dataclass(frozen=True)
class EstimatorConfig:
    """How the position is integrated, referenced, adapted, bounded and persisted."""

    # full, paper, dynamic: the table estimator's modes; kalman: the Kalman filter on the
    # unit's dynamics (ddh_vsensor.estimator.kalman_online.KalmanEstimator)
    mode: Literal["full", "paper", "dynamic", "kalman"]
    dynamic_blend_s: float = field(metadata={"ge": 0.0, "le": 3600.0})
    max_gap_s: float = field(metadata=_positive(ge=0.001, le=1.0))
    inertia_compensation: bool
    soft_limit_margin_mm: float = field(metadata={"ge": 0.0, "le": 1000.0})
    debounce_s: float = field(metadata={"ge": 0.0, "le": 1.0})
    resync_gain_moving: float = field(metadata={"gt": 0.0, "le": 1.0})
    resync_slow_mm_s: float = field(metadata={"ge": 0.0, "le": 10000.0})
    resync_transient_mm: float = field(metadata={"ge": 0.0, "le": 1000.0})
    adaptation: bool
    adaptation_bound: float = field(metadata={"gt": 0.0, "lt": 0.5})
    adaptation_step: float = field(metadata={"gt": 0.0, "le": 1.0})
    adaptation_min_travel_mm: float = field(metadata={"ge": 0.0, "le": 100000.0})
    uncertainty_reference_mm: float = field(metadata={"ge": 0.0, "le": 1000.0})
    uncertainty_per_travel: float = field(metadata={"ge": 0.0, "le": 1.0})
    uncertainty_hold_mm_per_s: float = field(metadata={"ge": 0.0, "le": 1000.0})
    state_save_interval_s: float = field(metadata=_positive(ge=0.1, le=3600.0))
    # `dynamic`: a torque change within one sample larger than this share of the motor's
    # torque limit is read as a step of unknown shape, not a ramp
    dynamic_torque_step: float = field(default=0.45, metadata={"gt": 0.0, "le": 2.0})
    # `dynamic`: below that step, the share of the torque's second difference over the last
    # three samples by which the step's mean may lie off the samples' trapezoid
    dynamic_torque_curvature: float = field(default=0.1, metadata={"ge": 0.0, "le": 1.0})
    # `dynamic`: where the speed's second difference (the change of the steps' mean torque)
    # and the samples' trapezoids disagree by more than the floor (a share of the motor's
    # torque limit), this share of the excess is how far the step's mean may lie off
    dynamic_speed_disagreement: float = field(default=0.75, metadata={"ge": 0.0, "le": 1.0})
    dynamic_speed_disagreement_floor: float = field(default=0.055,
                                                    metadata={"ge": 0.0, "le": 1.0})
    # `dynamic`: the torque balance is taken over the last samples spanning this time, so
    # that the speed's whole-rpm steps do not read as inertia torque at fast sampling
    dynamic_window_s: float = field(default=0.01, metadata={"ge": 0.0, "le": 0.1})
    # `dynamic`: a rod at rest takes up speed no faster than the change of the chambers' force
    # (beyond its static friction) gives the empty machine's mass, plus this acceleration
    # (m/s²) for the pressures' own error; a torque that says more is misread
    dynamic_start_tolerance_m_s2: float = field(default=0.0, metadata={"ge": 0.0, "le": 1000.0})
    # how far a Hall switch's span, the travel between two of its edges (2 window + hysteresis
    # passing through, the hysteresis turning back), may on average depart from the configured
    # one before the service reports the switch drifted (:mod:`.estimator.switch_drift`)
    reference_drift_mm: float = field(default=1.0, metadata={"gt": 0.0, "le": 100.0})


DEFAULT_BUS = "default"      # the bus of the top-level `bus:` key; `buses:` names the others
HALL_BITS_MAX = 64           # the I/O module's 8 input bytes (CiA 401 0x6000 sub 1..8)
UNITS_MAX = 16
_UNIT_NAME = re.compile(r"[a-z][a-z0-9_]{0,31}")


@dataclass(frozen=True)
class CanUnitConfig:
    """CAN identity of one unit: its motor controller, its emulated sensor, its Hall inputs."""

    sevcon_node_id: int = field(metadata={"ge": 1, "le": 127})
    sensor_node_id: int = field(metadata={"ge": 1, "le": 127})
    hall_bits: dict[str, int]       # reference name -> bit of the I/O module's inputs (0x6000)
    bus: str = DEFAULT_BUS          # the bus this unit's controller and sensor are on
    # the sensor's serial number 0x1018 sub 4 (absent: can.serial_number_base + unit index)
    serial_number: int | None = field(default=None, metadata={"ge": 0, "le": 0xFFFFFFFF})

    def check(self, path: str) -> list[tuple[str, str]]:
        for name, bit in self.hall_bits.items():
            if not 0 <= bit < HALL_BITS_MAX:
                return [(f"{path}.hall_bits.{name}", f"bit {bit} is not in "
                         f"0..{HALL_BITS_MAX - 1}")]
        return []


@dataclass(frozen=True)
class CanConfig:
    """Node IDs and output settings on the machine's CAN buses (`ddh-vsensor dbc`: layout)."""

    io_module_node_id: int = field(metadata={"ge": 1, "le": 127})
    oil_temp_node_id: int = field(metadata={"ge": 1, "le": 127})
    position_step_mm: float = field(metadata=_positive(ge=0.0001, le=10.0))
    event_timer_ms: float = field(metadata={"ge": 1.0, "le": 65535.0})
    units: dict[str, CanUnitConfig]
    # the motor controllers' TPDO period (their event timer): the drive samples its speed and
    # torque at it, and the Kalman filter steps at it (frames come with the bus's jitter)
    sevcon_period_ms: float = field(default=10.0, metadata={"ge": 1.0, "le": 1000.0})
    # CiA 301 behaviour of the emulated sensor nodes
    nmt_auto_start: bool = True     # boot to OPERATIONAL; False: PRE-OPERATIONAL, master starts
    emcy_enabled: bool = True       # EMCY producer valid at boot (0x1014 bit 31 clear)
    # a unit whose newest controller frame is older than this when its TPDO1 is due
    # publishes right after its next frame instead (held at most one input period)
    fresh_input_ms: float = field(default=1.0, metadata={"ge": 0.0, "le": 1000.0})
    # sensor nodes' vendor ID 0x1018 sub 1; 0 is "not assigned" (CiA hands out vendor IDs)
    vendor_id: int = field(default=0, metadata={"ge": 0, "le": 0xFFFFFFFF})
    # product code 0x1018 sub 2 and revision number 0x1018 sub 3 of the sensor nodes
    product_code: int = field(default=0x406, metadata={"ge": 0, "le": 0xFFFFFFFF})
    revision_number: int = field(default=0x00010000, metadata={"ge": 0, "le": 0xFFFFFFFF})
    # serial number 0x1018 sub 4: this plus the unit's index (its own key overrides); the
    # serial numbers must differ between units
    serial_number_base: int = field(default=1, metadata={"ge": 0, "le": 0xFFFFFFFF})
    device_name: str = "ddh-vsensor"    # 0x1008 reads "<device_name> <unit>"

    def serial_number(self, unit: str) -> int:
        """0x1018 sub 4 of ``unit``'s sensor: its own key, else the base + its index."""
        own = self.units[unit].serial_number
        return own if own is not None else self.serial_number_base + list(self.units).index(unit)

    def check(self, path: str) -> list[tuple[str, str]]:
        seen: dict[int, str] = {}
        for unit in self.units:
            serial = self.serial_number(unit)
            if serial > 0xFFFFFFFF:
                return [(f"{path}.serial_number_base", f"unit {unit}'s serial number {serial} "
                         "exceeds UNSIGNED32")]
            if serial in seen:
                return [(f"{path}.units.{unit}.serial_number", f"serial number {serial} is "
                         f"{seen[serial]}'s too: every sensor node needs its own")]
            seen[serial] = unit
        if len(self.device_name.encode()) > 200 or not self.device_name.isprintable():
            return [(f"{path}.device_name", "printable text of up to 200 bytes")]
        return []


END_STOP_OVERTRAVEL_MAX_MM = 100.0     # a cycle setpoint beyond a stroke end presses the rod
                                      # into its stop; further than this is a typo
WORK_SPEED_LEVELS = 4                 # `simulate --speed 1..4`: level N moves at N/4 of a speed


@dataclass(frozen=True)
class CycleStepConfig:
    """One move of a work cycle: ``unit`` travels to ``to_mm`` (beyond a stroke end: pressed
    into its end stop), then the cycle holds; ``with_next`` starts the next step at once, so
    the two moves overlap."""

    unit: str
    to_mm: float = field(metadata={"ge": -END_STOP_OVERTRAVEL_MAX_MM, "le": 100000.0})
    speed_share: float = field(default=1.0, metadata={"gt": 0.0, "le": 1.0})
    hold_s: float | None = field(default=None, metadata={"ge": 0.0, "le": 3600.0})
    with_next: bool = False


@dataclass(frozen=True)
class CycleConfig:
    """A named work cycle: every unit's start position, then the steps one after another."""

    start_mm: dict[str, float]
    steps: tuple[CycleStepConfig, ...]
    start_hold_s: float = field(default=1.0, metadata={"ge": 0.0, "le": 3600.0})
    pause_s: float = field(default=0.4, metadata={"ge": 0.0, "le": 3600.0})
    end_hold_s: float = field(default=1.0, metadata={"ge": 0.0, "le": 3600.0})

    def check(self, path: str) -> list[tuple[str, str]]:
        if not self.steps:
            return [(f"{path}.steps", "a cycle needs at least one step")]
        if self.steps[-1].with_next:
            return [(f"{path}.steps[{len(self.steps) - 1}].with_next",
                     "the last step has no next step to overlap with")]
        for i, step in enumerate(self.steps):
            if step.with_next and step.hold_s is not None:
                return [(f"{path}.steps[{i}].hold_s", "a step with with_next does not hold "
                         "(the next step starts at once)")]
        return []


@dataclass(frozen=True)
class WorkUnitConfig:
    """How fast one unit works in the simulator's cycles."""

    travel_speed_mm_s: float = field(metadata=_positive(le=10000.0))  # cycle steps at speed 4
    work_speed_mm_s: float = field(metadata=_positive(le=10000.0))    # random work: top speed
    work_range_mm: tuple[float, ...]    # [low, high]: targets of the diagnosis' random trials

    def check(self, path: str) -> list[tuple[str, str]]:
        r = self.work_range_mm
        if len(r) != 2 or not r[0] < r[1]:
            return [(f"{path}.work_range_mm", "must be [low, high] with low < high")]
        return []


@dataclass(frozen=True)
class WorkCycleConfig:
    """The machine's work for the simulator: per-unit speeds and named cycles (the first is
    the machine's typical cycle, ``simulate --cycle work``)."""

    units: dict[str, WorkUnitConfig]
    cycles: dict[str, CycleConfig]

    def check(self, path: str) -> list[tuple[str, str]]:
        if not self.cycles:
            return [(f"{path}.cycles", "at least one cycle (the machine's typical one)")]
        for name in self.cycles:
            if not _CYCLE_NAME.fullmatch(name) or name in RESERVED_CYCLE_NAMES:
                return [(f"{path}.cycles.{name}", "a cycle name is a lower-case word (letters, "
                         "digits, - and _) other than " + ", ".join(RESERVED_CYCLE_NAMES))]
        return []


_CYCLE_NAME = re.compile(r"[a-z][a-z0-9_-]{0,31}")
RESERVED_CYCLE_NAMES = ("work", "random")   # `simulate --cycle`: the first cycle, random work


def _check_work_cycle(cfg: "Config") -> list[tuple[str, str]]:
    """Every unit has its speeds and start positions; steps name units and stay within a
    stroke (plus the end-stop overtravel)."""
    work = cfg.work_cycle
    if work is None:
        return []
    problems = []
    units = ", ".join(cfg.units)
    for name in cfg.units:
        if name not in work.units:
            problems.append((f"work_cycle.units.{name}", "missing: every unit needs its speeds"))
    for name, wu in work.units.items():
        if name not in cfg.units:
            problems.append((f"work_cycle.units.{name}", f"no such unit (units: {units})"))
        elif not 0.0 <= wu.work_range_mm[0] < wu.work_range_mm[1] <= cfg.units[name].stroke_mm:
            problems.append((f"work_cycle.units.{name}.work_range_mm",
                             f"must lie within the stroke 0..{cfg.units[name].stroke_mm:g} mm"))
    for cname, cycle in work.cycles.items():
        base = f"work_cycle.cycles.{cname}"
        for name in cfg.units:
            if name not in cycle.start_mm:
                problems.append((f"{base}.start_mm.{name}", "missing: every unit starts "
                                 "somewhere"))
        for name, x in cycle.start_mm.items():
            if name not in cfg.units:
                problems.append((f"{base}.start_mm.{name}", f"no such unit (units: {units})"))
            elif not 0.0 <= x <= cfg.units[name].stroke_mm:
                problems.append((f"{base}.start_mm.{name}", f"{x:g} mm lies outside the stroke "
                                 f"0..{cfg.units[name].stroke_mm:g} mm"))
        for i, step in enumerate(cycle.steps):
            if step.unit not in cfg.units:
                problems.append((f"{base}.steps[{i}].unit", f"no such unit {step.unit!r} "
                                 f"(units: {units})"))
            elif not (-END_STOP_OVERTRAVEL_MAX_MM <= step.to_mm
                      <= cfg.units[step.unit].stroke_mm + END_STOP_OVERTRAVEL_MAX_MM):
                problems.append((f"{base}.steps[{i}].to_mm", f"{step.to_mm:g} mm is more than "
                                 f"{END_STOP_OVERTRAVEL_MAX_MM:g} mm beyond the stroke "
                                 f"0..{cfg.units[step.unit].stroke_mm:g} mm"))
    return problems


PresetMode = Literal["disabled", "pre-operational only", "enabled"]


@dataclass(frozen=True)
class TolerancesConfig:
    """What is known about the parameters the model takes as given: each key the half-width
    of the band the machine's true value may lie in (relative where a share). A datasheet
    gives a pump's efficiencies to tens of percent; a machine measured on a test stand (the
    reference loader's pumps, from the paper) to a few. The Kalman filter's uncertainty
    follows from these bands until references and holds narrow them; nothing else reads
    them (not a physics change: the tables and the hash do not depend on them)."""

    # the pumps' leakage (1 - volumetric efficiency) against the configured efficiency
    pump_leakage: float = field(default=0.1, metadata={"ge": 0.0, "le": 1.0})
    # the flow the pumps deliver per motor revolution per the cylinder's area (displacement,
    # belt ratio, bore) against the configured: a percent off moves the rod a percent of
    # every stroke
    pump_displacement: float = field(default=0.005, metadata={"ge": 0.0, "le": 0.2})
    # of the rating point's leakage, the share that may flow through orifices (~ sqrt dp)
    # instead of the laminar gaps the model assumes
    leakage_orifice_share: float = field(default=0.1, metadata={"ge": 0.0, "le": 1.0})
    # of the pumps' displacement, the trapped volume compressed to the port's pressure and
    # lost each revolution
    trapped_volume_share: float = field(default=0.1, metadata={"ge": 0.0, "le": 1.0})
    # the chambers' effective compliance (entrained air, hose walls) against the oil's
    compliance: float = field(default=0.1, metadata={"ge": 0.0, "le": 1.0})
    # the pumps' oil against the tank sensor's reading (degC, one sigma): the sensor trails
    # the oil the pumps work by its thermal lag
    oil_temp_c: float = field(default=3.0, metadata={"ge": 0.0, "le": 50.0})
    # the drive's torque estimate: its offset (calibration) and its error per sample (N*m)
    torque_offset_nm: float = field(default=2.0, metadata={"ge": 0.0, "le": 100.0})
    torque_noise_nm: float = field(default=1.0, metadata={"gt": 0.0, "le": 100.0})


# A datasheet's tolerances: what `config --write --datasheet` puts in a new machine's file.
DATASHEET_TOLERANCES = TolerancesConfig(pump_leakage=0.3, pump_displacement=0.01,
                                        leakage_orifice_share=0.3,
                                        trapped_volume_share=0.3, compliance=0.3,
                                        oil_temp_c=3.0, torque_offset_nm=2.0,
                                        torque_noise_nm=1.0)


@dataclass(frozen=True)
class FaultsConfig:
    """How the service behaves under faults and hostile input (docs: operations, Faults).
    Every key has a default, so a config without this section behaves as documented."""

    # unit -> node ID of the motor controller whose heartbeat is consumed (absent: none)
    heartbeat_node_ids: dict[str, int] = field(default_factory=dict)
    heartbeat_timeout_s: float = field(default=1.5, metadata={"ge": 0.05, "le": 60.0})
    # worst-case rod speed = this factor x the speed at the motor's speed limit (see
    # Config.max_speed_mm_s); it bounds the travel in any interval nothing was integrated
    max_speed_factor: float = field(default=1.5, metadata={"ge": 1.0, "le": 10.0})
    preset: PresetMode = "enabled"
    preset_standstill_mm_s: float = field(default=2.0, metadata={"ge": 0.0, "le": 100.0})
    preset_max_jump_mm: float = field(default=5.0, metadata={"ge": 0.0, "le": 100000.0})
    event_timer_min_ms: float = field(default=1.0, metadata={"ge": 1.0, "le": 1000.0})
    event_timer_max_ms: float = field(default=1000.0, metadata={"ge": 1.0, "le": 10000.0})
    housekeeping_tick_ms: float = field(default=10.0, metadata={"ge": 1.0, "le": 100.0})
    log_interval_s: float = field(default=5.0, metadata={"ge": 0.1, "le": 3600.0})
    unknown_ids_max: int = field(default=256, metadata={"ge": 0, "le": 65536})
    backlog_max_frames: int = field(default=20000, metadata={"ge": 1000, "le": 1000000})
    state_file_max_bytes: int = field(default=65536, metadata={"ge": 1024, "le": 16777216})

    def check(self, path: str) -> list[tuple[str, str]]:
        if self.event_timer_min_ms > self.event_timer_max_ms:
            return [(f"{path}.event_timer_min_ms", "must not exceed event_timer_max_ms")]
        for name, node_id in self.heartbeat_node_ids.items():
            if not 1 <= node_id <= 127:
                return [(f"{path}.heartbeat_node_ids.{name}", f"node ID {node_id} is not in "
                         "1..127")]
        return []


@dataclass(frozen=True)
class HealthConfig:
    """The daemon's own health (docs: operations, Health): from its day summaries, each
    unit's slow parameters, their trend, and when the position error they cause at the
    references will pass the tolerance. The fleet report's defaults."""

    # the position error at the references (mm) a maintenance engineer wants to hear of
    tolerance_mm: float = field(default=3.0, metadata={"gt": 0.0, "le": 1000.0})
    # a crossing expected within this many days raises the EMCY warning
    horizon_days: float = field(default=14.0, metadata={"gt": 0.0, "le": 365.0})


@dataclass(frozen=True)
class Config:
    """The whole machine configuration."""

    oil: OilConfig
    hydraulics: HydraulicsConfig
    units: dict[str, UnitConfig]
    tables: TablesConfig
    estimator: EstimatorConfig
    can: CanConfig
    bus: dict[str, Any]
    # further buses by name (can.units.*.bus picks one; `bus:` is the one named "default")
    buses: dict[str, dict[str, Any]] = field(default_factory=dict)
    faults: FaultsConfig = field(default_factory=FaultsConfig)
    tolerances: TolerancesConfig = field(default_factory=TolerancesConfig)
    health: HealthConfig = field(default_factory=HealthConfig)
    # the simulator's work cycles (absent: random work only, speeds from the motor limits)
    work_cycle: WorkCycleConfig | None = None
    source: str = field(default="<memory>", compare=False, metadata={"internal": True})

    @property
    def unit_names(self) -> tuple[str, ...]:
        """The machine's units in configuration order; nothing else knows their names."""
        return tuple(self.units)

    def check(self, path: str) -> list[tuple[str, str]]:
        problems = _check_unit_names(self)
        problems += _check_work_cycle(self)
        problems += _check_table_size(self)
        for name, unit in self.units.items():
            missing = set(unit.references_mm) - set(self.can.units[name].hall_bits) \
                if name in self.can.units else set()
            if missing:
                problems.append((f"can.units.{name}.hall_bits",
                                 f"no input bit for reference(s) {', '.join(sorted(missing))}"))
        if "interface" not in self.bus:
            problems.append(("bus.interface", "missing key (a python-can interface name)"))
        for name, kwargs in self.buses.items():
            if name == DEFAULT_BUS or not _UNIT_NAME.fullmatch(name):
                problems.append((f"buses.{name}", f"a bus name is a lower-case identifier other "
                                 f"than {DEFAULT_BUS!r} (that one is `bus:`)"))
            elif "interface" not in kwargs:
                problems.append((f"buses.{name}.interface",
                                 "missing key (a python-can interface name)"))
        for name, unit_can in self.can.units.items():
            if unit_can.bus != DEFAULT_BUS and unit_can.bus not in self.buses:
                problems.append((f"can.units.{name}.bus", f"unknown bus {unit_can.bus!r} "
                                 f"(known: {', '.join(self.bus_names)})"))
        lo, hi = self.faults.event_timer_min_ms, self.faults.event_timer_max_ms
        if not lo <= self.can.event_timer_ms <= hi:
            problems.append(("can.event_timer_ms", f"{self.can.event_timer_ms} ms is outside "
                             f"faults.event_timer_min_ms..event_timer_max_ms ({lo}..{hi})"))
        return problems

    def max_speed_mm_s(self, actuator: str) -> float:
        """The fastest the rod can move: the geometric flow of the faster pump side at the
        motor's speed limit, over that side's area, divided by the volumetric efficiency
        (a pump driven by the load passes more than its displacement), times
        ``faults.max_speed_factor`` (motor overspeed, relief and anti-cavitation flows)."""
        u = self.unit(actuator)
        speeds = [u.motor.speed_limit_rpm / 60.0 * pump.speed_ratio
                  * pump.displacement_cm3_rev * 1e3 / (u.cylinders * area)
                  / pump.volumetric_efficiency
                  for pump, area in ((u.pump_a, u.area_a_mm2), (u.pump_b, u.area_b_mm2))]
        return max(speeds) * self.faults.max_speed_factor

    def unit(self, actuator: str) -> UnitConfig:
        return self.units[self.require_unit(actuator)]

    def require_unit(self, name: str) -> str:
        """``name`` if it is one of the machine's units, else an error listing them."""
        if name not in self.units:
            raise UnknownUnitError(f"{self.source}: unknown unit {name!r} (this machine's "
                                   f"units: {', '.join(self.units)})")
        return name

    @property
    def bus_names(self) -> tuple[str, ...]:
        return (DEFAULT_BUS, *self.buses)

    def bus_kwargs(self, name: str = DEFAULT_BUS) -> dict[str, Any]:
        """Keyword arguments for ``can.Bus`` of the named bus."""
        return dict(self.bus) if name == DEFAULT_BUS else dict(self.buses[name])

    def units_on_bus(self, name: str) -> tuple[str, ...]:
        return tuple(u for u in self.units if self.can.units[u].bus == name)


    def physics_hash(self) -> str:
        """Hash of everything the physics and tables depend on (not the bus, not the source).
        Computed once and kept on the instance (the configuration is frozen): every state
        save asks for it, and a deep ``asdict`` of the whole configuration per save would be
        the service's largest allocation site, for a value that never changes."""
        cached = self.__dict__.get("_physics_hash_value")
        if cached is None:
            cached = self._hash_physics()
            object.__setattr__(self, "_physics_hash_value", cached)
        return cached

    def _hash_physics(self) -> str:
        data = dataclasses.asdict(self)
        for key in ("bus", "buses", "can", "estimator", "faults", "tolerances", "health",
                    "work_cycle", "source"):
            data.pop(key)
        for unit in data["units"].values():
            for key in ("references_mm", "reference_window_mm", "reference_hysteresis_mm",
                        "reference_tolerance_mm"):
                unit.pop(key)
            for key in ("torque_lag_s", "torque_gain", "torque_offset_nm",
                        "torque_speed_offset_nm", "torque_filter_s",
                        "torque_offset_tolerance_nm"):
                unit["motor"].pop(key)                 # how the drive reports, not physics
            unit.pop("displacement_tolerance")         # what is known, not physics
            unit["pump_a"].pop("leakage_tolerance")
            unit["pump_b"].pop("leakage_tolerance")
            _drop_unset(unit, UnitConfig)
            _drop_unset(unit["pump_a"], PumpConfig)
            _drop_unset(unit["pump_b"], PumpConfig)
        _drop_unset(data["hydraulics"], HydraulicsConfig)
        blob = json.dumps(data, sort_keys=True, default=str).encode()
        return hashlib.sha256(blob).hexdigest()[:16]

    def estimate_hash(self) -> str:
        """Hash of everything an estimate of a recorded run depends on: the physics, the
        reference switches, the drive's torque reading, the bands of what is known (the
        Kalman filter's) and the estimator's settings; not the buses, the CAN layout, the
        handling of faults or the health. What was measured of an estimate (a diagnosis
        baseline) holds for this hash only."""
        data = dataclasses.asdict(self)
        for key in ("bus", "buses", "can", "faults", "health", "work_cycle", "source"):
            data.pop(key)
        for unit in data["units"].values():
            _drop_unset(unit["motor"], MotorConfig)     # the drive's gain, where 1
        blob = json.dumps(data, sort_keys=True, default=str).encode()
        return hashlib.sha256(blob).hexdigest()[:16]



def _drop_unset(section: dict[str, Any], cls: type) -> None:
    """Remove from ``section`` (``cls`` as a dict) the keys marked ``hash_if_set`` at their
    default: the hash of a configuration that does not set them is the one it had before
    they existed."""
    for f in dataclasses.fields(cls):
        if f.metadata.get("hash_if_set") and section[f.name] == f.default:
            del section[f.name]


# The movement tables of all units together (float64 cells, both kinds), at most: 2.4 times
# the largest shipped machine's (config/excavator.yaml, 212 MiB by this count). The unit's
# MemoryMax (systemd) leaves room for them beside the process.
TABLE_BYTES_MAX = 512 * 2**20
# The torque axis spans the relief valves' torque or the motor's limit, whichever is larger
# (tables/build.py: torque_span_nm, physics this layer cannot import); the shipped machines'
# span is 1.05..2.05 times the limit: counted here as this multiple of it.
TORQUE_SPAN_FACTOR = 2.5


def table_cells(cfg: Config) -> int:
    """The cells of every unit's movement tables (full and paper) the grid keys ask for."""
    tc = cfg.tables
    t0, t1, dt = tc.temperatures_c
    temps = round((t1 - t0) / dt) + 1
    cells = 0
    for unit in cfg.units.values():
        speeds = 2 * math.ceil(unit.motor.speed_limit_rpm / tc.speed_step_rpm) + 1
        torques = 2 * math.ceil(TORQUE_SPAN_FACTOR * unit.motor.torque_limit_nm
                                / tc.torque_step_nm) + 1
        cells += temps * torques * (speeds + 6)
    return cells


def _size(n_bytes: float) -> str:
    for unit in ("B", "KiB", "MiB", "GiB", "TiB", "PiB"):
        if n_bytes < 1024 or unit == "PiB":
            return f"{n_bytes:.3g} {unit}"
        n_bytes /= 1024
    return ""


def _check_table_size(cfg: Config) -> list[tuple[str, str]]:
    """Each grid key is bounded on its own; together they must not ask for more memory than
    the tables may take (else numpy fails, or the host swaps, at the start)."""
    n_bytes = 8 * table_cells(cfg)
    if n_bytes <= TABLE_BYTES_MAX:
        return []
    return [("tables", f"temperatures_c, speed_step_rpm and torque_step_nm ask for "
             f"{_size(n_bytes)} of movement tables ({len(cfg.units)} units, "
             f"{n_bytes // 8:.3g} cells); at most {_size(TABLE_BYTES_MAX)}: a coarser "
             "grid or a narrower temperature range")]


def _check_unit_names(cfg: Config) -> list[tuple[str, str]]:
    """Unit names are lower-case identifiers (they become frame, file and column names), the
    same set in every section that is keyed by unit."""
    problems = []
    if not 1 <= len(cfg.units) <= UNITS_MAX:
        problems.append(("units", f"{len(cfg.units)} units: a machine has 1..{UNITS_MAX}"))
    for name in cfg.units:
        if not isinstance(name, str) or not _UNIT_NAME.fullmatch(name):
            problems.append((f"units.{name}", "a unit name is a lower-case identifier of up to "
                             "32 characters (letters, digits, _; a letter first)"))
    for section, keys in (("can.units", cfg.can.units),
                          ("faults.heartbeat_node_ids", cfg.faults.heartbeat_node_ids)):
        for name in keys:
            if name not in cfg.units:
                problems.append((f"{section}.{name}", f"no such unit (units: "
                                 f"{', '.join(map(str, cfg.units))})"))
    for name in cfg.units:
        if name not in cfg.can.units:
            problems.append((f"can.units.{name}", "missing: every unit needs its CAN identity"))
    return problems


