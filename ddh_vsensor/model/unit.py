"""One DDH unit's discrete-time dynamics (``_unit.c``) and its ctypes binding.

Continuous state (SI, n in rpm): rod position x and velocity v, chamber pressures over the
reservoir dp_a, dp_b, motor speed n.

    J dw/dt          = tau - tau_pump(dp_a, dp_b, n)               (w = n * 2pi/60)
    V_s(x)/beta dp_s/dt = q_pump,s(n) - g_leak,s dp_s + q_anticav(dp_s) - q_relief(dp_s)
                         - sign_s * A_s * v                        (s = a, b)
    m dv/dt          = A_a dp_a - A_b dp_b - F_load - friction(v)

with V_a = dead + A_a x and V_b = dead + A_b (stroke - x). Every element is the one of
``physics/`` (same pump, leakage, torque-efficiency and valve laws), so the steady state of
this model is exactly ``physics.steady.steady_state``.

Integration is fixed-step backward (implicit) Euler on (v, dp_a, dp_b, n), position by
x_{k+1} = x_k + h v_{k+1}, chamber volumes taken at x_k; the pumps deliver over the step at
the mean of its start and end speeds, (n_k + n_{k+1}) / 2 (the trapezoid: the oil delivered
is the speed's integral to second order in h, so the rod's travel is, and a plant stepped at
1 ms and a filter at 2 ms agree on it). Each element is piecewise linear, so
for a given set of discrete states - per side the valve regime (anti-cavitation, closed below
or above the reservoir pressure, relief), the friction state (moving up, moving down, stuck,
hitting an end stop) and the motor state (turning either way, held in the pump's own friction
band at zero speed, at the speed limit, speed-controlled) - a step is a 2x2 linear solve in
(n, v). The discrete states start from the previous step's and are updated from the solution
until they are self-consistent (an active-set iteration; one pass almost always). The fixed
points of backward Euler are the steady-state equations, which is why it converges to
``steady_state`` exactly.

Stick-slip: a stuck rod stays stuck while the force it needs from static friction (including
the inertia term of the step) is within the static value; a moving rod keeps moving while its
velocity keeps its sign, and sticks when it would reverse. The motor has the same structure
at zero speed because the pump torque switches between pumping (1/eta_hm) and motoring
(x eta_hm): between those two torques the shaft stands still.

The drive's speed limit acts like the Sevcon's in torque mode: when the commanded torque would
take the motor past the limit, the speed is held at the limit and the reported torque is the
one needed to hold it. In speed mode the motor follows the commanded speed and the torque is
again the one that takes.

Effects that are plant changes enter per row: pump leakage and displacement through the
``DDHUnit`` (``unit.with_pumps``), entrained air through the effective bulk modulus
(:func:`ddh_vsensor.physics.air.compliance`; secant over the step, iterated with the
pressures, so the compression is exact; near vacuum the air's compliance changes by orders of
magnitude within a step, and where the iteration does not settle the step is taken as two
halves, recursively), belt slip as a speed-ratio drop proportional to
|motor torque| (the torque of the previous step: slip is slow, this keeps the step linear),
the pumps' fill loss at speed, a scored bore passing oil across the piston in the stroke's
middle third.

Plant structure the nominal model lacks enters the same way, each with its coefficient zero
in a row that does not have it, so that row's arithmetic is the nominal one to the bit. A
machine's configuration sets it (:class:`Structure`, :meth:`RowSpec.from_config`) and the
simulator's effects (``sim.effects``: ``leak_orifice``, ``leak_speed``, ``seal_friction``,
``hose_expansion``) add to it; :meth:`Structure.row` is the one conversion from its physical
parameters to the row's coefficients. The nonlinear parts are taken at the step's start (they
move little within a step and the fixed point, the steady state, is exact):

- pump leakage  q = [k_lam dp / mu + k_orf dp / sqrt(max(|dp|, p_t))] (b + s_pump |n|), the
  orifice share's conductance at the start pressure (laminar below p_t = 1 bar, where a gap's
  Reynolds number is low), the speed factor at the start speed;
- seal friction F_c + F_p and F_s + F_p, F_p = c_a max(dp_a, 0) + c_b max(dp_b, 0);
- hose wall compliance: a chamber's capacitance V/beta + V_dead e_hose (implicit, linear).

The binding: :class:`Params`, :class:`State`, :class:`Input` and :class:`Counters` mirror the
C structs; :func:`library` checks every field's name, offset and size against the table the C
exports before it hands the library out, so the two cannot drift apart unnoticed.
"""

from __future__ import annotations

import ctypes
import math
from collections.abc import Sequence
from dataclasses import dataclass, fields, replace
from typing import Any

import numpy as np

from ddh_vsensor.compiled import required_library
from ddh_vsensor.config import Config, HydraulicsConfig
from ddh_vsensor.physics.conversions import BAR_PA
from ddh_vsensor.physics.pump import rating_viscosity_pa_s
from ddh_vsensor.physics.unit import DDHUnit

# friction states
F_DOWN, F_STUCK, F_UP, F_IMPACT = -1, 0, 1, 2
# motor states
M_LIM_NEG, M_NEG, M_STUCK, M_POS, M_LIM_POS, M_SPEED = -2, -1, 0, 1, 2, 3
# valve regimes per side
R_ANTICAV, R_BELOW, R_ABOVE, R_RELIEF = 0, 1, 2, 3
SEAL_CONTACT_M = 4.0e-3         # contact width of a compact piston or rod seal


@dataclass(frozen=True)
class RowSpec:
    """One row of a batch: a unit (pump effects already applied) and its extras."""

    unit: DDHUnit
    payload_kg: float = 0.0
    air_fraction: float = 0.0       # entrained air volume fraction at atmospheric pressure
    belt_slip_per_nm: float = 0.0   # fractional speed-ratio drop per N*m of |motor torque|
    fill_loss: float = 0.0          # share of the flow lost at the speed limit (~ speed^2)
    bore_leak_m3_s_pa: float = 0.0  # A -> B across the piston in the stroke's middle third
    # orifice (turbulent) leakage of each side's pumps, q = k sign(dp) sqrt(|dp|)
    orifice_leak_a_m3_s_sqrt_pa: float = 0.0
    orifice_leak_b_m3_s_sqrt_pa: float = 0.0
    # each side's leakage x (1 + gain |n_pump| / rated) / (1 + gain): the rating point's kept
    leak_speed_gain_a: float = 0.0
    leak_speed_gain_b: float = 0.0
    leak_rated_pump_speed_rpm: float = 1.0
    # seal friction per pascal of each chamber's (positive) gauge pressure, N/Pa
    seal_friction_a_n_per_pa: float = 0.0
    seal_friction_b_n_per_pa: float = 0.0
    hose_compliance_per_pa: float = 0.0   # hoses' (dead volume's) wall expansion dV/V per Pa

    @classmethod
    def from_config(cls, cfg: Config, actuator: str, payload_kg: float = 0.0) -> RowSpec:
        """The configured machine's row of ``actuator``: its unit with its structure."""
        return Structure.from_config(cfg, actuator).row(DDHUnit.from_config(cfg, actuator),
                                                       cfg.hydraulics, payload_kg)


@dataclass(frozen=True)
class Structure:
    """Plant structure the nominal model lacks, in physical terms (all 0: the nominal model).

    The configuration's keys of the same names set it; a simulator effect adds its own
    (:meth:`plus`: shares and gains add). Per side, the share of the rating point's leakage
    through orifices and the leakage's gain with shaft speed; per unit, the share of the
    chamber pressures' force on the seal rings that is friction; the dead volume's growth per
    100 bar; the oil's entrained air."""

    leakage_orifice_share_a: float = 0.0
    leakage_orifice_share_b: float = 0.0
    leakage_speed_gain_a: float = 0.0
    leakage_speed_gain_b: float = 0.0
    seal_friction_share: float = 0.0
    hose_expansion_per_100bar: float = 0.0
    air_fraction: float = 0.0

    @classmethod
    def from_config(cls, cfg: Config, actuator: str) -> Structure:
        u = cfg.unit(actuator)
        return cls(leakage_orifice_share_a=u.pump_a.leakage_orifice_share,
                   leakage_orifice_share_b=u.pump_b.leakage_orifice_share,
                   leakage_speed_gain_a=u.pump_a.leakage_speed_gain,
                   leakage_speed_gain_b=u.pump_b.leakage_speed_gain,
                   seal_friction_share=u.seal_friction_share,
                   hose_expansion_per_100bar=cfg.hydraulics.hose_expansion_per_100bar,
                   air_fraction=cfg.hydraulics.air_fraction)

    def plus(self, other: Structure) -> Structure:
        """Both together: every share and gain is the sum (a 0 adds nothing, to the bit)."""
        return Structure(**{f.name: getattr(self, f.name) + getattr(other, f.name)
                            for f in fields(self)})

    def row(self, unit: DDHUnit, hydraulics: HydraulicsConfig | None, payload_kg: float = 0.0,
            **extras: Any) -> RowSpec:
        """The row of ``unit`` (pump effects already applied) with this structure;
        ``hydraulics`` is the pumps' rating point the leakage terms keep (needed only where
        they are set); ``extras`` are the row's other fields."""
        shares = (self.leakage_orifice_share_a, self.leakage_orifice_share_b)
        gains = (self.leakage_speed_gain_a, self.leakage_speed_gain_b)
        if hydraulics is None and any(shares + gains):
            raise ValueError("the orifice share and the speed gain need the pumps' rating point")
        orifice = (0.0, 0.0)
        if any(shares):
            unit, orifice = orifice_leakage(unit, shares, hydraulics)
        ring_a, ring_b = seal_rings_m2(unit)
        return RowSpec(unit=unit, payload_kg=payload_kg,
                       orifice_leak_a_m3_s_sqrt_pa=orifice[0],
                       orifice_leak_b_m3_s_sqrt_pa=orifice[1],
                       leak_speed_gain_a=gains[0], leak_speed_gain_b=gains[1],
                       leak_rated_pump_speed_rpm=(hydraulics.nominal_pump_speed_rpm
                                                  if hydraulics else 1.0),
                       seal_friction_a_n_per_pa=self.seal_friction_share * ring_a,
                       seal_friction_b_n_per_pa=self.seal_friction_share * ring_b,
                       hose_compliance_per_pa=self.hose_expansion_per_100bar / (100.0 * BAR_PA),
                       air_fraction=self.air_fraction, **extras)


def orifice_leakage(unit: DDHUnit, shares: tuple[float, float], hydraulics: HydraulicsConfig
                    ) -> tuple[DDHUnit, tuple[float, float]]:
    """``unit`` with each side's laminar leakage cut to 1 - its share, and each side's orifice
    coefficient (m^3/s/sqrt(Pa)) carrying that share at the rating point: k_orf sqrt(dp_r) =
    share x k dp_r / mu_r, so the rating point's leakage is kept."""
    dp_r = hydraulics.nominal_pressure_bar * BAR_PA
    mu_r = rating_viscosity_pa_s(unit.oil, hydraulics)
    orifice_a, orifice_b = (share * s.pump.leak_coeff_m3 * math.sqrt(dp_r) / mu_r
                            for share, s in zip(shares, unit.sides))
    return (replace(unit, a=replace(unit.a, pump=unit.a.pump.scaled(leakage=1.0 - shares[0])),
                    b=replace(unit.b, pump=unit.b.pump.scaled(leakage=1.0 - shares[1]))),
            (orifice_a, orifice_b))


def seal_rings_m2(unit: DDHUnit) -> tuple[float, float]:
    """Contact areas the chamber pressures press seals onto (all cylinders): A's the piston
    seal's on the bore, B's the piston seal's and the rod seal's."""
    cyl = unit.cylinder
    bore = math.sqrt(4.0 * cyl.area_a_m2 / (cyl.count * math.pi))
    rod = math.sqrt(4.0 * max(cyl.area_a_m2 - cyl.area_b_m2, 0.0) / (cyl.count * math.pi))
    ring = cyl.count * math.pi * SEAL_CONTACT_M
    return ring * bore, ring * (bore + rod)


_D = ctypes.c_double


class Params(ctypes.Structure):
    """``struct ddh_params``: one row's constants (see ``_unit.c`` for each field)."""

    _fields_ = [(name, _D) for name in (
        "area_a_m2", "area_b_m2", "stroke_m", "dead_volume_m3", "mass_kg", "load_n",
        "static_friction_n", "coulomb_friction_n", "viscous_friction_n_s_m", "inertia_kg_m2",
        "torque_limit_nm", "speed_limit_rpm", "reservoir_pa", "bulk_modulus_pa",
        "air_fraction", "belt_slip_per_nm", "fill_loss", "bore_leak_m3_s_pa",
        "orifice_leak_a_m3_s_sqrt_pa", "orifice_leak_b_m3_s_sqrt_pa", "leak_base",
        "leak_slope_a_per_rpm", "leak_slope_b_per_rpm", "seal_friction_a_n_per_pa",
        "seal_friction_b_n_per_pa", "hose_compliance_per_pa", "flow_a_m3_s_per_rpm",
        "flow_b_m3_s_per_rpm", "leak_a_m3", "leak_b_m3", "crack_a_pa", "crack_b_pa",
        "relief_a_pa", "relief_b_pa")] + [
        ("valve_g_a_m3_s_pa", _D * 4), ("valve_ge_a_m3_s", _D * 4),
        ("valve_g_b_m3_s_pa", _D * 4), ("valve_ge_b_m3_s", _D * 4),
        ("gain_a_nm_per_pa", _D * 4 * 3), ("gain_b_nm_per_pa", _D * 4 * 3)]


class State(ctypes.Structure):
    """``struct ddh_state``: one row's state between steps."""

    _fields_ = [("x_m", _D), ("v_m_s", _D), ("dp_a_pa", _D), ("dp_b_pa", _D), ("n_rpm", _D),
                ("torque_nm", _D), ("friction_state", ctypes.c_int),
                ("motor_state", ctypes.c_int), ("regime_a", ctypes.c_int),
                ("regime_b", ctypes.c_int)]


class Input(ctypes.Structure):
    """``struct ddh_input``: one row's input over a step."""

    _fields_ = [("torque_nm", _D), ("mu_pa_s", _D), ("speed_rpm", _D),
                ("speed_controlled", ctypes.c_int)]


class Counters(ctypes.Structure):
    """``struct ddh_counters``: linear solves and unsettled row steps, accumulated."""

    _fields_ = [("iterations", ctypes.c_long), ("unconverged", ctypes.c_long)]


STRUCTS: tuple[type[ctypes.Structure], ...] = (Params, State, Input, Counters)


def check_layout(lib: ctypes.CDLL, kind: int, structure: type[ctypes.Structure]) -> None:
    """Raise ImportError unless ``structure`` has exactly the fields of the C struct ``kind``
    (0 params, 1 state, 2 input, 3 counters), by name, in order, at the same offsets and of
    the same sizes."""
    name_p, size = ctypes.c_char_p(), ctypes.c_long()
    c_fields = []
    while (offset := lib.ddh_field(kind, len(c_fields), ctypes.byref(name_p),
                                   ctypes.byref(size))) >= 0:
        c_fields.append((name_p.value.decode(), offset, size.value))
    py_fields = [(f[0], getattr(structure, f[0]).offset, getattr(structure, f[0]).size)
                 for f in structure._fields_]
    if py_fields != c_fields or ctypes.sizeof(structure) != lib.ddh_struct_size(kind):
        c_only = [f for f in c_fields if f not in py_fields]
        py_only = [f for f in py_fields if f not in c_fields]
        raise ImportError(
            f"ddh_vsensor.model._unit: {structure.__name__} does not match the C struct "
            f"(name, offset, size): C has {c_only or 'nothing else'}, Python has "
            f"{py_only or 'nothing else'}; sizeof {ctypes.sizeof(structure)}, in C "
            f"{lib.ddh_struct_size(kind)}")


def check_layouts(lib: ctypes.CDLL) -> None:
    """Raise ImportError unless every struct of the unit model compiled into ``lib`` (this
    package's ``_unit`` or a library that compiles it in) matches its Python mirror."""
    ptr, long_ = ctypes.c_void_p, ctypes.c_long
    lib.ddh_field.argtypes = [ctypes.c_int, ctypes.c_int, ptr, ptr]
    lib.ddh_field.restype = long_
    lib.ddh_struct_size.argtypes = [ctypes.c_int]
    lib.ddh_struct_size.restype = long_
    for kind, structure in enumerate(STRUCTS):
        check_layout(lib, kind, structure)


def _load() -> ctypes.CDLL:
    """The library from the package's own directory, its layouts checked."""
    lib = required_library("ddh_vsensor.model._unit")
    check_layouts(lib)
    ptr, long_ = ctypes.c_void_p, ctypes.c_long
    lib.ddh_step.argtypes = [ptr, ptr, ptr, ctypes.c_double, ptr]
    lib.ddh_step.restype = ctypes.c_int
    lib.ddh_step_rows.argtypes = [long_, ptr, ptr, ptr, ctypes.c_double, ptr]
    lib.ddh_step_rows.restype = long_
    lib.ddh_settle.argtypes = [ptr, ptr, ptr]
    lib.ddh_settle.restype = None
    lib.ddh_settle_rows.argtypes = [long_, ptr, ptr, ptr]
    lib.ddh_settle_rows.restype = None
    lib.ddh_stored_pa.argtypes = [ptr, ctypes.c_double]
    lib.ddh_stored_pa.restype = ctypes.c_double
    lib.ddh_pressure_pa.argtypes = [ptr, ctypes.c_double, ctypes.c_double]
    lib.ddh_pressure_pa.restype = ctypes.c_double
    return lib


_LIB: ctypes.CDLL | None = None


def library() -> ctypes.CDLL:
    """The compiled dynamics (loaded and checked once); ImportError where it was not built
    or does not match this binding."""
    global _LIB
    if _LIB is None:
        _LIB = _load()
    return _LIB


def params(row: RowSpec) -> Params:
    """One row's constants: everything of the unit and its extras the step reads."""
    u = row.unit
    cyl, pa, pb = u.cylinder, u.a.pump, u.b.pump
    gain_a, gain_b = row.leak_speed_gain_a, row.leak_speed_gain_b
    rated = row.leak_rated_pump_speed_rpm
    base = 1.0 / (1.0 + gain_a)
    # the C takes one base for both sides: B's leakage (laminar and orifice) is scaled by its
    # own base over A's (exactly 1 where the gains are equal), its slope taken over A's base
    scale_b = (1.0 + gain_a) / (1.0 + gain_b)
    p = Params(
        area_a_m2=u.a.area_m2, area_b_m2=u.b.area_m2, stroke_m=cyl.stroke_m,
        dead_volume_m3=u.dead_volume_m3, mass_kg=u.moving_mass_kg(row.payload_kg),
        load_n=u.load_force_n(row.payload_kg), static_friction_n=cyl.static_friction_n,
        coulomb_friction_n=cyl.coulomb_friction_n,
        viscous_friction_n_s_m=cyl.viscous_friction_n_s_m, inertia_kg_m2=u.motor.inertia_kg_m2,
        torque_limit_nm=u.motor.torque_limit_nm, speed_limit_rpm=u.motor.speed_limit_rpm,
        reservoir_pa=u.reservoir_pa, bulk_modulus_pa=u.bulk_modulus_pa,
        air_fraction=row.air_fraction, belt_slip_per_nm=row.belt_slip_per_nm,
        fill_loss=row.fill_loss, bore_leak_m3_s_pa=row.bore_leak_m3_s_pa,
        orifice_leak_a_m3_s_sqrt_pa=row.orifice_leak_a_m3_s_sqrt_pa,
        orifice_leak_b_m3_s_sqrt_pa=row.orifice_leak_b_m3_s_sqrt_pa * scale_b, leak_base=base,
        leak_slope_a_per_rpm=abs(pa.speed_ratio) * gain_a / rated * base,
        leak_slope_b_per_rpm=abs(pb.speed_ratio) * gain_b / rated * base,
        seal_friction_a_n_per_pa=row.seal_friction_a_n_per_pa,
        seal_friction_b_n_per_pa=row.seal_friction_b_n_per_pa,
        hose_compliance_per_pa=row.hose_compliance_per_pa,
        flow_a_m3_s_per_rpm=float(pa.geometric_flow_m3_s(1.0)),
        flow_b_m3_s_per_rpm=float(pb.geometric_flow_m3_s(1.0)),
        leak_a_m3=pa.leak_coeff_m3, leak_b_m3=pb.leak_coeff_m3 * scale_b,
        crack_a_pa=u.a.anticav.cracking_pa, crack_b_pa=u.b.anticav.cracking_pa,
        relief_a_pa=u.a.relief.setting_pa, relief_b_pa=u.b.relief.setting_pa)
    p_sign = np.array([-1.0, -1.0, 1.0, 1.0])          # the pressure's sign in each regime
    for side in u.sides:
        g_ac, crack = side.anticav.gradient_m3_s_pa, side.anticav.cracking_pa
        g_rv, setting = side.relief.gradient_m3_s_pa, side.relief.setting_pa
        getattr(p, f"valve_g_{side.name}_m3_s_pa")[:] = [g_ac, 0.0, 0.0, g_rv]
        getattr(p, f"valve_ge_{side.name}_m3_s")[:] = [g_ac * crack, 0.0, 0.0, g_rv * setting]
        table = getattr(p, f"gain_{side.name}_nm_per_pa")
        for d, direction in enumerate((-1.0, 0.0, 1.0)):
            table[d][:] = [float(k) for k in side.pump.torque_gain_nm_per_pa(p_sign, direction)]
    return p


def rows_array(rows: Sequence[RowSpec]) -> np.ndarray:
    """The rows' constants as a numpy array of ``struct ddh_params`` (fields by name)."""
    out = np.zeros(len(rows), dtype=np.dtype(Params))
    for i, row in enumerate(rows):
        out[i] = np.frombuffer(bytes(params(row)), dtype=out.dtype)[0]
    return out
