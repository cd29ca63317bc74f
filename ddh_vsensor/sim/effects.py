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

Plant structure the estimator's model does not share (:data:`STRUCTURE_TYPICAL` holds each
at its typical value; every one is neutral at 0). A machine's configuration may carry the same
structure (``pump_a``/``pump_b.leakage_orifice_share``, ``leakage_speed_gain``,
``seal_friction_share``, ``hydraulics.hose_expansion_per_100bar``, ``hydraulics.air_fraction``:
the ``compressibility`` effect's); each of these five effects
adds to the configured value (:meth:`ddh_vsensor.model.unit.Structure.plus`: the effect's
percentage as a share, the gain as a gain, summed), the orifice shares together at most 90 %:

``leak_orifice`` (% of the pumps' leakage at the rating point, 0..90, neutral 0, typical 30)
    Part of each pump's leakage passes orifice-like paths (gear tip and side-plate gaps at
    their narrowest, relief of the trapped volume) where the flow is turbulent:
    q = k_lam dp / mu + k_orf sign(dp) sqrt(|dp|), the orifice part this share of the total
    at the rating point (hydraulics' nominal pressure and viscosity), the total there
    unchanged. Below the rating pressure the orifice part leaks more than laminar leakage
    would, and it does not thin with temperature. Typical 30 %: a gear pump's leakage paths
    are neither purely laminar nor purely turbulent (its volumetric efficiency falls less
    with warm, thin oil than 1/mu predicts); about a third turbulent at the rating point is
    taken as the middle of that mixed regime, not fitted to anything.
``leak_speed`` (gain c, 0..2, neutral 0, typical 0.25)
    Pump leakage grows with shaft speed: q_leak x (1 + c |n_pump| / n_rated) / (1 + c), the
    rating speed's leakage unchanged, standstill's 1/(1 + c) of it. Typical 0.25: the
    compression of the pump's trapped volumes alone loses ~dp n V_trapped / beta, about a
    tenth of the leakage at the rating point (trapped ~0.3 x displacement, 250 bar over
    1.6 GPa, against 5..7 % leakage); the gaps' flow dragged by the moving gears and the
    shorter sealing time per tooth add to it, hence 0.2..0.3.
``seal_friction`` (% friction coefficient, 0..20, neutral 0, typical 3)
    The seals' friction rises with the pressure pressing their lips: the Coulomb and static
    friction each gain mu_p (p_a A_a,ring + p_b A_b,ring), gauge pressures above zero, over
    the seals' contact rings of width :data:`ddh_vsensor.model.unit.SEAL_CONTACT_M` (4 mm):
    the piston seal's on the bore for both chambers, the rod seal's on the rod for B. Typical
    3 %: lubricated polyurethane and PTFE compound seals on honed or chromed steel run at
    friction coefficients of a few percent under their contact pressure, which a chamber
    pressure adds to; for the reference boom (2 x 114 mm bore) at its 60 bar holding pressure it is
    ~0.5 kN, of the order of the configured Coulomb friction.
``hose_expansion`` (% of the dead volume per 100 bar, 0..20, neutral 0, typical 1)
    The dead volume (hoses and fittings between pumps and cylinder) expands with pressure:
    a chamber's capacitance gains V_dead e_hose, i.e. 1/beta_eff = 1/beta_oil +
    1/beta_hose with beta_hose = 100 bar / e over the dead volume, beyond what the
    configured bulk modulus holds. Typical 1 %/100 bar (beta_hose = 1 GPa): wire-braided
    high-pressure hose has an effective wall modulus of the order of 1 GPa (hydraulics texts
    put a hose's effective bulk modulus well below the oil's 1.4..1.8 GPa; hose makers
    publish the volumetric expansion for that reason). The pressure dependence of the
    effective modulus is entrained air's (``compressibility``), which the structure set
    turns on as well (typical 0.5 % at atmospheric pressure: a mobile machine's oil, well
    below foaming).
``torque_lag`` (ms, 0..50, neutral 0, typical 3), ``torque_ripple`` (% of the motor's
torque limit, 0..20, neutral 0, typical 1) and ``torque_speed_offset`` (N*m at the speed
limit, -20..20, neutral 0, typical 1.5)
    The drive's torque is an estimate from its currents, not the shaft's torque. It trails
    the shaft torque by a first-order lag (the estimate's filter: a few ms is typical of
    a drive's reported torque, well above the ~0.2 ms of its current loop), carries ripple
    with the rotor angle (:data:`RIPPLE_ORDER` per revolution: cogging and the current
    ripple of a 4-pole-pair machine's 6th harmonic; 1 % of rated torque is a typical
    permanent-magnet motor's, aliased to noise at the logger's rate), and includes the
    motor's own losses (iron and windage) as an offset proportional to the speed, in the
    direction of turning: 1.5 N*m at 6000 rpm is ~1 kW, typical of a 20..30 kW machine.
``oil_temp_lag`` (s, 0..3600, neutral 0, typical 180)
    The tank's temperature sensor reads the tank's mixed oil, which trails the oil the pumps
    work (a DDH circuit exchanges only its leakage and the rod's volume with the tank): a
    first-order lag, started in the steady state of the run's warm-up (the sensor
    drift x tau below the pumps' oil). Typical 3 min: a few litres of circuit oil exchanged
    at a few L/min, plus an immersion sensor's own tens of seconds.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, fields, replace
from typing import Callable, Iterable, Mapping, Sequence

from ddh_vsensor.config import HydraulicsConfig
from ddh_vsensor.errors import UserError
from ddh_vsensor.physics.unit import DDHUnit
from ddh_vsensor.physics.conversions import BAR_PA, LPM_M3S
from ddh_vsensor.physics.valves import ReliefValve
from ddh_vsensor.model.unit import RowSpec, Structure


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
    EffectDef("leak_orifice", "% at the rating point", 0.0, lambda v: 0.0 <= v <= 90.0,
              "0 <= % <= 90", "share of the pumps' leakage through orifices (~ sqrt dp)"),
    EffectDef("leak_speed", "gain", 0.0, lambda v: 0.0 <= v <= 2.0, "0 <= gain <= 2",
              "pump leakage x (1 + gain |n| / n_rated) / (1 + gain)"),
    EffectDef("seal_friction", "% of the pressure force on the seal rings", 0.0,
              lambda v: 0.0 <= v <= 20.0, "0 <= % <= 20",
              "seal friction rising with the chamber pressures"),
    EffectDef("hose_expansion", "% of the dead volume per 100 bar", 0.0,
              lambda v: 0.0 <= v <= 20.0, "0 <= % <= 20", "the hoses' walls expand with pressure"),
    EffectDef("torque_lag", "ms", 0.0, lambda v: 0.0 <= v <= 50.0, "0 <= ms <= 50",
              "the drive's torque trails the shaft's by a first-order lag"),
    EffectDef("torque_ripple", "% of the torque limit", 0.0, lambda v: 0.0 <= v <= 20.0,
              "0 <= % <= 20", "the drive's torque carries ripple with the rotor angle"),
    EffectDef("torque_speed_offset", "N*m at the speed limit", 0.0,
              lambda v: -20.0 <= v <= 20.0, "-20 <= N*m <= 20",
              "the drive's torque includes the motor's speed-proportional losses"),
    EffectDef("oil_temp_lag", "s", 0.0, lambda v: 0.0 <= v <= 3600.0, "0 <= s <= 3600",
              "the tank sensor trails the pumps' oil by a first-order lag"),
)}

# The structure the estimator's model does not share, each effect at its typical value
# (the module docstring argues each), entrained air included.
STRUCTURE_TYPICAL: dict[str, float] = {
    "leak_orifice": 30.0, "leak_speed": 0.25, "seal_friction": 3.0, "hose_expansion": 1.0,
    "compressibility": 0.005, "torque_lag": 3.0, "torque_ripple": 1.0,
    "torque_speed_offset": 1.5, "oil_temp_lag": 180.0}
RIPPLE_ORDER = 24               # torque ripple periods per motor revolution

VALVE_LEAK_OPEN_BAR = 40.0
ORIFICE_SHARE_MAX = 0.9         # configured and effect together: some laminar leakage is left


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
    leak_orifice: float = 0.0
    leak_speed: float = 0.0
    seal_friction: float = 0.0
    hose_expansion: float = 0.0
    torque_lag: float = 0.0
    torque_ripple: float = 0.0
    torque_speed_offset: float = 0.0
    oil_temp_lag: float = 0.0

    def non_neutral(self) -> dict[str, float]:
        return {f.name: getattr(self, f.name) for f in fields(self)
                if getattr(self, f.name) != EFFECTS[f.name].neutral}

    def structure(self) -> Structure:
        """The plant structure these effects stand for, in the configuration's terms (the
        effects' percentages as shares, on both pump sides)."""
        share = self.leak_orifice / 100.0
        return Structure(leakage_orifice_share_a=share, leakage_orifice_share_b=share,
                         leakage_speed_gain_a=self.leak_speed,
                         leakage_speed_gain_b=self.leak_speed,
                         seal_friction_share=self.seal_friction / 100.0,
                         hose_expansion_per_100bar=self.hose_expansion / 100.0,
                         air_fraction=self.compressibility)

    def row(self, unit: DDHUnit, payload_kg: float, hydraulics: HydraulicsConfig | None = None,
            configured: Structure = Structure()) -> RowSpec:
        """The plant row of ``unit`` with these effects applied (``hydraulics``: the pumps'
        rating point, which ``leak_orifice`` and ``leak_speed`` keep). The structure effects
        add to the ``configured`` machine's (``Structure.plus``): the orifice shares of the
        rating point's leakage, the speed gains, the seal friction shares and the hoses'
        expansions are sums; the orifice shares together at most 90 %."""
        structure = configured.plus(self.structure())
        for side in ("a", "b"):
            share = getattr(structure, f"leakage_orifice_share_{side}")
            if share > ORIFICE_SHARE_MAX:
                raise UserError(f"effect leak_orifice: {self.leak_orifice:g} % on top of the "
                                f"configured pump_{side}.leakage_orifice_share "
                                f"{getattr(configured, f'leakage_orifice_share_{side}'):g} is "
                                f"{share:.3g} of the leakage, above {ORIFICE_SHARE_MAX:g}")
        if self.pump_leakage != 1.0 or self.displacement != 1.0:
            unit = unit.with_pumps(leakage=self.pump_leakage, displacement=self.displacement)
        if self.valve_leak:
            seep = ReliefValve(VALVE_LEAK_OPEN_BAR * BAR_PA,
                               self.valve_leak * LPM_M3S / (100.0 * BAR_PA))
            unit = replace(unit, a=replace(unit.a, relief=seep), b=replace(unit.b, relief=seep))
        return structure.row(unit, hydraulics, payload_kg,
                             belt_slip_per_nm=self.belt_slip / 100.0 / 100.0,
                             fill_loss=self.pump_fill / 100.0,
                             bore_leak_m3_s_pa=self.bore_leak * LPM_M3S / (100.0 * BAR_PA))


NOMINAL = UnitEffects()


def structure_effects(scale: float = 1.0) -> UnitEffects:
    """Every unit's effects with the structure at ``scale`` x its typical values."""
    return replace(NOMINAL, **{k: v * scale for k, v in STRUCTURE_TYPICAL.items()})


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
