"""Machine configuration: the YAML file, validated into frozen dataclasses.

Validation is driven by the dataclass fields themselves (type hints plus ``metadata`` bounds),
so a new setting is one field, and every error names the file, the key path and the problem.
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import types
import typing
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Literal

import yaml

from .errors import UserError

ACTUATORS = ("boom", "bucket")
DEFAULT_CONFIG = Path(__file__).with_name("data") / "loader.yaml"


class ConfigError(UserError, ValueError):
    """A configuration problem, worded for the person who edits the file."""

    def __init__(self, source: str, key_path: str, problem: str) -> None:
        self.source, self.key_path, self.problem = source, key_path, problem
        where = f"{source}: {key_path}: " if key_path else f"{source}: "
        super().__init__(where + problem)


def _positive(**extra: Any) -> dict[str, Any]:
    return {"gt": 0.0, **extra}


@dataclass(frozen=True)
class OilConfig:
    """Hydraulic oil: two viscosity points for ASTM D341 and a linear thermal expansion."""

    name: str
    viscosity_cst_at_40c: float = field(metadata=_positive())
    viscosity_cst_at_100c: float = field(metadata=_positive())
    density_kg_m3_at_15c: float = field(metadata=_positive())
    thermal_expansion_per_k: float = field(metadata={"ge": 0.0, "lt": 0.01})
    bulk_modulus_pa: float = field(metadata=_positive())

    def check(self, path: str) -> list[tuple[str, str]]:
        if self.viscosity_cst_at_100c >= self.viscosity_cst_at_40c:
            return [(f"{path}.viscosity_cst_at_100c", "must be below viscosity_cst_at_40c "
                     "(oil thins when it warms)")]
        return []


@dataclass(frozen=True)
class HydraulicsConfig:
    """Circuit-wide settings: reservoir, pump rating point, valve characteristics."""

    reservoir_pressure_bar: float
    nominal_pressure_bar: float = field(metadata=_positive())
    nominal_pump_speed_rpm: float = field(metadata=_positive())
    nominal_viscosity_cst: float = field(metadata=_positive())
    anticavitation_cracking_bar: float = field(metadata={"ge": 0.0, "le": 1.0})
    anticavitation_gradient_lpm_per_bar: float = field(metadata=_positive())
    relief_rise_fraction: float = field(metadata=_positive(le=1.0))
    relief_rise_flow_lpm: float = field(metadata=_positive())


@dataclass(frozen=True)
class PumpConfig:
    """One side's pump set (pumps in parallel act as one) and that side's relief valve."""

    displacement_cm3_rev: float = field(metadata=_positive())
    volumetric_efficiency: float = field(metadata={"gt": 0.0, "le": 1.0})
    hydromechanical_efficiency: float = field(metadata={"gt": 0.0, "le": 1.0})
    max_speed_rpm: float = field(metadata=_positive())
    speed_ratio: float = field(metadata=_positive())
    relief_bar: float = field(metadata=_positive())


@dataclass(frozen=True)
class LoadConfig:
    """External load at the rod(s); positive force pushes the rod in (held by the A side)."""

    holding_force_n: float
    force_per_payload_kg_n: float
    mass_kg: float = field(metadata=_positive())
    mass_per_payload_kg: float = field(metadata={"ge": 0.0})


@dataclass(frozen=True)
class MotorConfig:
    """Electric motor limits and the rotating inertia of motor plus pumps."""

    inertia_kg_m2: float = field(metadata=_positive())
    torque_limit_nm: float = field(metadata=_positive())
    speed_limit_rpm: float = field(metadata=_positive())


@dataclass(frozen=True)
class UnitConfig:
    """One DDH unit: motor, two pump sides, cylinder(s) and load."""

    cylinders: int = field(metadata={"ge": 1})
    stroke_mm: float = field(metadata=_positive())
    area_a_mm2: float = field(metadata=_positive())
    area_b_mm2: float = field(metadata=_positive())
    friction_static_n: float = field(metadata={"ge": 0.0})
    friction_coulomb_n: float = field(metadata={"ge": 0.0})
    friction_viscous_n_s_per_m: float = field(metadata={"ge": 0.0})
    dead_volume_l: float = field(metadata=_positive())
    pump_a: PumpConfig
    pump_b: PumpConfig
    load: LoadConfig
    motor: MotorConfig
    references_mm: dict[str, float]
    reference_window_mm: float = field(metadata=_positive())
    reference_hysteresis_mm: float = field(metadata={"ge": 0.0})

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
    speed_step_rpm: float = field(metadata=_positive())
    torque_step_nm: float = field(metadata=_positive())
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

    mode: Literal["full", "paper", "dynamic"]
    dynamic_blend_s: float = field(metadata={"ge": 0.0})
    max_gap_s: float = field(metadata=_positive())
    inertia_compensation: bool
    soft_limit_margin_mm: float = field(metadata={"ge": 0.0})
    debounce_s: float = field(metadata={"ge": 0.0})
    resync_gain_moving: float = field(metadata={"gt": 0.0, "le": 1.0})
    resync_slow_mm_s: float = field(metadata={"ge": 0.0})
    resync_transient_mm: float = field(metadata={"ge": 0.0})
    adaptation: bool
    adaptation_bound: float = field(metadata={"gt": 0.0, "lt": 0.5})
    adaptation_step: float = field(metadata={"gt": 0.0, "le": 1.0})
    adaptation_min_travel_mm: float = field(metadata={"ge": 0.0})
    uncertainty_reference_mm: float = field(metadata={"ge": 0.0})
    uncertainty_per_travel: float = field(metadata={"ge": 0.0})
    uncertainty_hold_mm_per_s: float = field(metadata={"ge": 0.0})
    state_save_interval_s: float = field(metadata=_positive())


@dataclass(frozen=True)
class CanUnitConfig:
    """CAN identity of one unit: its motor controller, its emulated sensor, its Hall inputs."""

    sevcon_node_id: int = field(metadata={"ge": 1, "le": 127})
    sensor_node_id: int = field(metadata={"ge": 1, "le": 127})
    hall_bits: dict[str, int]       # reference name -> bit of the I/O module's input byte

    def check(self, path: str) -> list[tuple[str, str]]:
        for name, bit in self.hall_bits.items():
            if not 0 <= bit <= 7:
                return [(f"{path}.hall_bits.{name}", f"bit {bit} is not in 0..7")]
        return []


@dataclass(frozen=True)
class CanConfig:
    """Node IDs and output settings on the machine's CAN bus (layout in the shipped DBC)."""

    io_module_node_id: int = field(metadata={"ge": 1, "le": 127})
    oil_temp_node_id: int = field(metadata={"ge": 1, "le": 127})
    position_step_mm: float = field(metadata=_positive())
    event_timer_ms: float = field(metadata={"ge": 1.0, "le": 65535.0})
    units: dict[Literal["boom", "bucket"], CanUnitConfig]
    # CiA 301 behaviour of the emulated sensor nodes
    nmt_auto_start: bool = True     # boot to OPERATIONAL; False: PRE-OPERATIONAL, master starts
    emcy_enabled: bool = True       # EMCY producer valid at boot (0x1014 bit 31 clear)


@dataclass(frozen=True)
class Config:
    """The whole machine configuration."""

    oil: OilConfig
    hydraulics: HydraulicsConfig
    units: dict[Literal["boom", "bucket"], UnitConfig]
    tables: TablesConfig
    estimator: EstimatorConfig
    can: CanConfig
    bus: dict[str, Any]
    source: str = field(default="<memory>", compare=False, metadata={"internal": True})

    def check(self, path: str) -> list[tuple[str, str]]:
        problems = []
        for name in ACTUATORS:
            if name not in self.units:
                problems.append((f"units.{name}", "missing unit"))
        for name, unit in self.units.items():
            missing = set(unit.references_mm) - set(self.can.units[name].hall_bits) \
                if name in self.can.units else set()
            if missing:
                problems.append((f"can.units.{name}.hall_bits",
                                 f"no input bit for reference(s) {', '.join(sorted(missing))}"))
        if "interface" not in self.bus:
            problems.append(("bus.interface", "missing key (a python-can interface name)"))
        return problems

    def unit(self, actuator: str) -> UnitConfig:
        return self.units[actuator]  # type: ignore[index]

    def physics_hash(self) -> str:
        """Hash of everything the physics and tables depend on (not the bus, not the source)."""
        data = dataclasses.asdict(self)
        for key in ("bus", "can", "estimator", "source"):
            data.pop(key)
        for unit in data["units"].values():
            for key in ("references_mm", "reference_window_mm", "reference_hysteresis_mm"):
                unit.pop(key)
        blob = json.dumps(data, sort_keys=True, default=str).encode()
        return hashlib.sha256(blob).hexdigest()[:16]


# --- generic validation --------------------------------------------------------------------

def _type_name(tp: Any) -> str:
    return getattr(tp, "__name__", str(tp))


def _convert(value: Any, tp: Any, path: str, source: str) -> Any:
    origin = typing.get_origin(tp)
    args = typing.get_args(tp)
    if dataclasses.is_dataclass(tp):
        return _build(tp, value, path, source)
    if tp is float:
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            raise ConfigError(source, path, f"expected a number, got {value!r}")
        if value != value or value in (float("inf"), float("-inf")):
            raise ConfigError(source, path, f"expected a finite number, got {value!r}")
        return float(value)
    if tp is int:
        if isinstance(value, bool) or not isinstance(value, int):
            raise ConfigError(source, path, f"expected a whole number, got {value!r}")
        return value
    if origin is Literal:
        if value not in args:
            raise ConfigError(source, path, f"{value!r} is not one of "
                              f"{', '.join(map(str, args))}")
        return value
    if tp is bool:
        if not isinstance(value, bool):
            raise ConfigError(source, path, f"expected true or false, got {value!r}")
        return value
    if tp is str:
        if not isinstance(value, str):
            raise ConfigError(source, path, f"expected text, got {value!r}")
        return value
    if origin is tuple:
        if not isinstance(value, list):
            raise ConfigError(source, path, f"expected a list, got {value!r}")
        return tuple(_convert(v, args[0], f"{path}[{i}]", source) for i, v in enumerate(value))
    if origin is dict:
        if not isinstance(value, dict):
            raise ConfigError(source, path, f"expected a mapping, got {value!r}")
        key_tp, val_tp = args
        allowed = typing.get_args(key_tp) if typing.get_origin(key_tp) is Literal else None
        out = {}
        for k, v in value.items():
            if allowed is not None and k not in allowed:
                raise ConfigError(source, f"{path}.{k}", f"unknown key (expected one of "
                                  f"{', '.join(allowed)})")
            out[k] = v if val_tp is Any else _convert(v, val_tp, f"{path}.{k}", source)
        return out
    if tp is Any:
        return value
    if origin in (typing.Union, types.UnionType):  # Optional[...] fields
        if value is None and type(None) in args:
            return None
        inner = [a for a in args if a is not type(None)]
        return _convert(value, inner[0], path, source)
    raise TypeError(f"unsupported config type {_type_name(tp)} at {path}")  # programming error


def _check_bounds(value: Any, meta: typing.Mapping[str, Any], path: str, source: str) -> None:
    bounds = {"gt": (lambda v, b: v > b, "greater than"),
              "ge": (lambda v, b: v >= b, "at least"),
              "lt": (lambda v, b: v < b, "less than"),
              "le": (lambda v, b: v <= b, "at most")}
    for key, (ok, words) in bounds.items():
        if key in meta and not ok(value, meta[key]):
            raise ConfigError(source, path, f"{value!r} is not physical here: must be {words} "
                              f"{meta[key]}")


def _build(cls: type, data: Any, path: str, source: str) -> Any:
    if not isinstance(data, dict):
        raise ConfigError(source, path or "(top level)", f"expected a mapping, got {data!r}")
    hints = typing.get_type_hints(cls)
    fields = {f.name: f for f in dataclasses.fields(cls) if not f.metadata.get("internal")}
    for key in data:
        if key not in fields:
            raise ConfigError(source, f"{path}.{key}" if path else str(key),
                              f"unknown key (known: {', '.join(fields)})")
    kwargs = {}
    for name, f in fields.items():
        sub = f"{path}.{name}" if path else name
        if name not in data:
            if f.default is dataclasses.MISSING and f.default_factory is dataclasses.MISSING:
                raise ConfigError(source, sub, "missing key")
            continue
        value = _convert(data[name], hints[name], sub, source)
        if isinstance(value, (int, float)):
            _check_bounds(value, f.metadata, sub, source)
        kwargs[name] = value
    obj = cls(**kwargs)
    if hasattr(obj, "check"):
        problems = obj.check(path or "(top level)")
        if problems:
            raise ConfigError(source, *problems[0])
    return obj


def parse_config(data: Any, source: str = "<memory>") -> Config:
    """Validate a decoded YAML document into a :class:`Config`."""
    cfg = _build(Config, data, "", source)
    return dataclasses.replace(cfg, source=source)


def load_config(path: str | Path | None = None) -> Config:
    """Load and validate a config file; ``None`` loads the embedded reference machine."""
    path = Path(path) if path is not None else DEFAULT_CONFIG
    source = str(path)
    try:
        text = path.read_text(encoding="utf-8")
    except OSError as exc:
        raise ConfigError(source, "", f"cannot read: {exc.strerror or exc}") from None
    try:
        data = yaml.safe_load(text)
    except yaml.YAMLError as exc:
        raise ConfigError(source, "", f"not valid YAML: {exc}") from None
    return parse_config(data, source)
