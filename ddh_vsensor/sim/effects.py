"""Effects catalogue: what a real machine has that the nominal tables do not.

Each effect is named, documented, has one parameter and composes with the others; each applies
to every unit unless the caller names one (``boom.pump_leakage=1.5``). The nominal plant is
every effect at its neutral value.

``pump_leakage`` (factor, > 0, neutral 1)
    Factor on the laminar leakage coefficient of every pump of the unit (wear). Changes the
    leakage flows, hence the holding creep speed and the mm per revolution under load.
``compressibility`` (air volume fraction at atmospheric pressure, 0 <= X < 0.2, neutral 0)
    Entrained air. The effective bulk modulus follows the oil-air mixture law with adiabatic
    air (kappa = 1.4): 1/beta = [(1-X)/beta_oil + X (p0/p)^(1/k)/(k p)] / [(1-X) + X (p0/p)^(1/k)],
    p absolute, p0 = 1.013 bar (see ``physics.air.compliance``); it collapses at low
    pressure. The chamber balance uses it throughout, so oil is conserved; only the transient
    changes (steady states do not depend on the bulk modulus).
``belt_slip`` (% per 100 N*m, 0 <= s <= 20, neutral 0)
    The belt's pump-to-motor speed ratio drops by s % per 100 N*m of |motor torque|; the
    torque ratio (pulley radii) is unchanged, so the pumps deliver less flow for the same
    motor speed and torque.
``displacement`` (factor, > 0, neutral 1)
    Factor on every pump displacement of the unit (a pump that is not what the data sheet
    says). Flow per revolution and torque per bar scale together.
``time_offset`` (s, -1 <= t <= 1, neutral 0)
    Logging only, not the plant: the logged motor speed and torque lag the logged position
    (and the other channels) by t seconds (t < 0: they lead).

The measurement chain (logging only, not the plant; applied in ``sensors.measure``):

``oil_temp_offset`` (degC, -30..30, neutral 0)
    The tank sensor reads the oil the pumps see plus this offset.
``torque_gain`` (factor, 0.5..2, neutral 1) and ``torque_offset`` (N*m, -20..20, neutral 0)
    The drive's torque (an estimate from current) reads gain x true + offset.
``position_scale`` (factor, 0.8..1.25, neutral 1) and ``position_offset`` (mm, -50..50,
neutral 0)
    The draw-wire reads scale x true + offset.

Deviations the diagnosis' catalogue does not have (for testing it on the unknown):

``valve_leak`` (L/min at 100 bar above 40 bar, 0..20, neutral 0)
    Each chamber's relief valve seeps from 40 bar on, its flow growing linearly with the
    pressure above that and independent of the oil's viscosity (unlike pump leakage).
``pump_fill`` (% of the flow lost at the motor's speed limit, 0..20, neutral 0)
    The pumps' inlets fill short at speed (a suction restriction): the delivered flow drops
    by this share x (motor speed / speed limit)^2, whatever the torque (unlike belt slip)
    and not in proportion to the speed (unlike displacement).
``bore_leak`` (L/min at 100 bar across the piston, 0..20, neutral 0)
    A scored bore: over the middle third of the stroke the piston seal passes oil from the
    higher-pressure chamber to the other, linearly with the pressure difference and
    independent of the viscosity; elsewhere it seals.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, fields, replace
from typing import Callable, Iterable, Mapping, Sequence

from ddh_vsensor.errors import UserError
from ddh_vsensor.physics.unit import DDHUnit
from ddh_vsensor.physics.conversions import BAR_PA, LPM_M3S
from ddh_vsensor.physics.valves import ReliefValve
from ddh_vsensor.sim.plant import RowSpec


@dataclass(frozen=True)
class EffectDef:
    name: str
    parameter: str
    neutral: float
    check: Callable[[float], bool]
    allowed: str
    doc: str


EFFECTS: dict[str, EffectDef] = {e.name: e for e in (
    EffectDef("pump_leakage", "factor", 1.0, lambda v: 0.0 < v <= 100.0, "0 < factor <= 100",
              "factor on every pump's laminar leakage coefficient (wear)"),
    EffectDef("compressibility", "air fraction", 0.0, lambda v: 0.0 <= v < 0.2,
              "0 <= fraction < 0.2",
              "entrained air volume fraction at atmospheric pressure"),
    EffectDef("belt_slip", "% per 100 N*m", 0.0, lambda v: 0.0 <= v <= 20.0, "0 <= % <= 20",
              "pump speed ratio drops by this % per 100 N*m of |motor torque|"),
    EffectDef("displacement", "factor", 1.0, lambda v: 0.0 < v <= 2.0, "0 < factor <= 2",
              "factor on every pump displacement"),
    EffectDef("time_offset", "s", 0.0, lambda v: -1.0 <= v <= 1.0, "-1 <= t <= 1 s",
              "logged speed and torque lag the logged position by t seconds"),
    EffectDef("oil_temp_offset", "degC", 0.0, lambda v: -30.0 <= v <= 30.0, "-30 <= degC <= 30",
              "the oil temperature sensor reads true + offset"),
    EffectDef("torque_gain", "factor", 1.0, lambda v: 0.5 <= v <= 2.0, "0.5 <= factor <= 2",
              "the drive's torque reads gain x true"),
    EffectDef("torque_offset", "N*m", 0.0, lambda v: -20.0 <= v <= 20.0, "-20 <= N*m <= 20",
              "the drive's torque reads true + offset"),
    EffectDef("position_scale", "factor", 1.0, lambda v: 0.8 <= v <= 1.25,
              "0.8 <= factor <= 1.25", "the draw-wire reads scale x true position"),
    EffectDef("position_offset", "mm", 0.0, lambda v: -50.0 <= v <= 50.0, "-50 <= mm <= 50",
              "the draw-wire reads true position + offset"),
    EffectDef("valve_leak", "L/min at 100 bar above 40 bar", 0.0, lambda v: 0.0 <= v <= 20.0,
              "0 <= L/min <= 20", "relief valves seep above 40 bar, viscosity-independent"),
    EffectDef("pump_fill", "% at the speed limit", 0.0, lambda v: 0.0 <= v <= 20.0,
              "0 <= % <= 20", "pumps fill short at speed: flow lost ~ speed squared"),
    EffectDef("bore_leak", "L/min at 100 bar", 0.0, lambda v: 0.0 <= v <= 20.0,
              "0 <= L/min <= 20", "the piston seal leaks over the middle third of the stroke"),
)}

VALVE_LEAK_OPEN_BAR = 40.0


@dataclass(frozen=True)
class UnitEffects:
    """The effects on one unit, each at its value (neutral = nominal plant)."""

    pump_leakage: float = 1.0
    compressibility: float = 0.0
    belt_slip: float = 0.0
    displacement: float = 1.0
    time_offset: float = 0.0
    oil_temp_offset: float = 0.0
    torque_gain: float = 1.0
    torque_offset: float = 0.0
    position_scale: float = 1.0
    position_offset: float = 0.0
    valve_leak: float = 0.0
    pump_fill: float = 0.0
    bore_leak: float = 0.0

    def non_neutral(self) -> dict[str, float]:
        return {f.name: getattr(self, f.name) for f in fields(self)
                if getattr(self, f.name) != EFFECTS[f.name].neutral}

    def row(self, unit: DDHUnit, payload_kg: float) -> RowSpec:
        """The plant row of ``unit`` with these effects applied."""
        if self.pump_leakage != 1.0 or self.displacement != 1.0:
            unit = unit.with_pumps(leakage=self.pump_leakage, displacement=self.displacement)
        if self.valve_leak:
            seep = ReliefValve(VALVE_LEAK_OPEN_BAR * BAR_PA,
                               self.valve_leak * LPM_M3S / (100.0 * BAR_PA))
            unit = replace(unit, a=replace(unit.a, relief=seep), b=replace(unit.b, relief=seep))
        return RowSpec(unit=unit, payload_kg=payload_kg, air_fraction=self.compressibility,
                       belt_slip_per_nm=self.belt_slip / 100.0 / 100.0,
                       fill_loss=self.pump_fill / 100.0,
                       bore_leak_m3_s_pa=self.bore_leak * LPM_M3S / (100.0 * BAR_PA))


NOMINAL = UnitEffects()


def check_effect(name: str, value: float) -> float:
    """Validate one effect value; UserError naming the effect and its allowed range."""
    if name not in EFFECTS:
        raise UserError(f"unknown effect {name!r} (known: {', '.join(EFFECTS)})")
    try:
        value = float(value)
    except (TypeError, ValueError):
        raise UserError(f"effect {name}: value {value!r} is not a number") from None
    spec = EFFECTS[name]
    if not math.isfinite(value) or not spec.check(value):
        raise UserError(f"effect {name}: {value:g} is out of range ({spec.allowed}; "
                        f"{spec.doc})")
    return value


def parse_effect(text: str, units: Sequence[str]) -> tuple[str | None, str, float]:
    """``NAME=VALUE`` or ``UNIT.NAME=VALUE`` -> (unit or None for every unit, name, value)."""
    if "=" not in text:
        raise UserError(f"effect {text!r}: expected NAME=VALUE or UNIT.NAME=VALUE "
                        f"(effects: {', '.join(EFFECTS)})")
    key, raw = (s.strip() for s in text.split("=", 1))
    unit = None
    if "." in key:
        unit, key = (s.strip() for s in key.split(".", 1))
        if unit not in units:
            raise UserError(f"effect {text!r}: unknown unit {unit!r} (units: "
                            f"{', '.join(units)})")
    try:
        value = float(raw)
    except ValueError:
        if key not in EFFECTS:
            raise UserError(f"unknown effect {key!r} (known: {', '.join(EFFECTS)})") from None
        raise UserError(f"effect {key}: value {raw!r} is not a number") from None
    return unit, key, check_effect(key, value)


def build_effects(items: Iterable[str | tuple[str | None, str, float]] | Mapping[str, float]
                  | None, units: Sequence[str]) -> dict[str, UnitEffects]:
    """Effects per unit from CLI strings, (unit, name, value) tuples or a {name: value} map.

    A name without a unit applies to every unit; the same effect twice on a unit is an error.
    """
    if items is None:
        items = []
    if isinstance(items, Mapping):
        items = [f"{k}={v}" for k, v in items.items()]
    out: dict[str, dict[str, float]] = {a: {} for a in units}
    for item in items:
        unit, name, value = parse_effect(item, units) if isinstance(item, str) else item
        value = check_effect(name, value)
        if unit is not None and unit not in units:
            raise UserError(f"unknown unit {unit!r} (units: {', '.join(units)})")
        for a in ([unit] if unit else units):
            if name in out[a]:
                raise UserError(f"effect {name} given twice for the {a}")
            out[a][name] = value
    return {a: replace(NOMINAL, **vals) for a, vals in out.items()}


def describe(effects: Mapping[str, UnitEffects]) -> str:
    """One line for logs and CSV comments, e.g. 'boom: pump_leakage=1.5; bucket: none'."""
    parts = []
    for a in effects:
        vals = effects[a].non_neutral()
        parts.append(f"{a}: " + (", ".join(f"{k}={v:g}" for k, v in vals.items()) or "none"))
    return "; ".join(parts)
