"""Time-domain plant of DDH units: motor, pumps, chambers, valves, cylinder, load.

States per row (one row = one unit of one run; rows run in lockstep, numpy arrays of shape
``(rows,)``): rod position x and velocity v, chamber pressures over the reservoir dp_a, dp_b,
motor speed n (rpm).

    J dw/dt          = tau - tau_pump(dp_a, dp_b, n)               (w = n * 2pi/60)
    V_s(x)/beta dp_s/dt = q_pump,s(n) - g_leak,s dp_s + q_anticav(dp_s) - q_relief,s(dp_s)
                         - sign_s * A_s * v                        (s = a, b)
    m dv/dt          = A_a dp_a - A_b dp_b - F_load - friction(v)

with V_a = dead + A_a x and V_b = dead + A_b (stroke - x). Every element is the one of
``physics/`` (same pump, leakage, torque-efficiency and valve laws), so the steady state of
this model is exactly ``physics.steady.steady_state``.

Integration is fixed-step backward (implicit) Euler on (v, dp_a, dp_b, n), position by
x_{k+1} = x_k + h v_{k+1}, chamber volumes taken at x_k. Each element is piecewise linear, so
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
one needed to hold it.

Effects that are plant changes enter per row: pump leakage and displacement through the
``DDHUnit`` (``unit.with_pumps``), entrained air through the effective bulk modulus
(:func:`ddh_vsensor.physics.air.compliance`), belt slip as a speed-ratio drop proportional to |motor torque|
(the torque of the previous step: slip is slow, this keeps the step linear).

Plant structure the estimator's model does not share (``effects``: ``leak_orifice``,
``leak_speed``, ``seal_friction``, ``hose_expansion``) enters the same way, each with its
coefficient zero in a row that does not have it, so that row's arithmetic is the nominal one
to the bit. The nonlinear parts are taken at the step's start (they move little within a
step and the fixed point, the steady state, is exact):

- pump leakage  q = [k_lam dp / mu + k_orf dp / sqrt(max(|dp|, p_t))] (b + s_pump |n|), the
  orifice share's conductance at the start pressure (laminar below p_t = 1 bar, where a gap's
  Reynolds number is low), the speed factor at the start speed;
- seal friction F_c + F_p and F_s + F_p, F_p = c_a max(dp_a, 0) + c_b max(dp_b, 0);
- hose wall compliance: a chamber's capacitance V/beta + V_dead e_hose (implicit, linear).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Sequence

import numpy as np

from ddh_vsensor.physics.air import compliance, secant_compliance
from ddh_vsensor.physics.conversions import RPM_RAD_S
from ddh_vsensor.physics.unit import DDHUnit

# friction states
F_UP, F_DOWN, F_STUCK, F_IMPACT = 1, -1, 0, 2
# motor states
M_POS, M_NEG, M_STUCK, M_LIM_POS, M_LIM_NEG, M_SPEED = 1, -1, 0, 2, -2, 3
MAX_ITERATIONS = 16
AIR_PASSES = 8                     # secant bulk-modulus updates per step at most (with air)
AIR_TOLERANCE_PA = 1.0             # ... until the pressures move less than this between them
ORIFICE_LAMINAR_PA = 1.0e5         # below this an orifice leak path flows laminar (linear)
# gain-table offset (direction * 4) of each motor state + 2: -2, -1 -> negative; 0 -> standstill;
# 1, 2 -> positive; 3 (speed mode) is looked up from the command's sign instead
_DIRECTION4 = np.array([0, 0, 4, 8, 8, 4], dtype=np.int64)


@dataclass(frozen=True)
class RowSpec:
    """One row of a plant batch: a unit (pump effects already applied) and its extras."""

    unit: DDHUnit
    payload_kg: float = 0.0
    air_fraction: float = 0.0       # entrained air volume fraction at atmospheric pressure
    belt_slip_per_nm: float = 0.0   # fractional speed-ratio drop per N*m of |motor torque|
    fill_loss: float = 0.0          # share of the flow lost at the speed limit (~ speed^2)
    bore_leak_m3_s_pa: float = 0.0  # A -> B across the piston in the stroke's middle third
    # orifice (turbulent) leakage of each side's pumps, q = k sign(dp) sqrt(|dp|)
    orifice_leak_a_m3_s_sqrt_pa: float = 0.0
    orifice_leak_b_m3_s_sqrt_pa: float = 0.0
    # leakage x (1 + gain |n_pump| / rated) / (1 + gain): the rating point's leakage kept
    leak_speed_gain: float = 0.0
    leak_rated_pump_speed_rpm: float = 1.0
    # seal friction per pascal of each chamber's (positive) gauge pressure, N/Pa
    seal_friction_a_n_per_pa: float = 0.0
    seal_friction_b_n_per_pa: float = 0.0
    hose_compliance_per_pa: float = 0.0   # hoses' (dead volume's) wall expansion dV/V per Pa


class Plant:
    """A batch of independent DDH units integrated in lockstep by backward Euler.

    Public state arrays (shape ``(rows,)``, SI units, n in rpm): ``x``, ``v``, ``dp_a``,
    ``dp_b``, ``n``, ``torque`` (the motor's actual torque over the last step) and the
    discrete states ``friction_state``, ``motor_state``, ``regime_a``, ``regime_b``.
    """

    def __init__(self, rows: Sequence[RowSpec], step_s: float) -> None:
        if not rows:
            raise ValueError("a plant needs at least one row")
        if step_s <= 0.0:
            raise ValueError("step must be positive")
        self.rows = tuple(rows)
        self.h = float(step_s)
        self.size = len(rows)
        self._idx = np.arange(self.size)

        def col(fn) -> np.ndarray:
            return np.array([float(fn(r)) for r in rows])

        u = lambda r: r.unit  # noqa: E731
        self.area_a = col(lambda r: u(r).a.area_m2)
        self.area_b = col(lambda r: u(r).b.area_m2)
        self.stroke = col(lambda r: u(r).cylinder.stroke_m)
        self.dead = col(lambda r: u(r).dead_volume_m3)
        self.mass = col(lambda r: u(r).moving_mass_kg(r.payload_kg))
        self.load = col(lambda r: u(r).load_force_n(r.payload_kg))
        self.f_static = col(lambda r: u(r).cylinder.static_friction_n)
        self.f_coulomb = col(lambda r: u(r).cylinder.coulomb_friction_n)
        self.c_viscous = col(lambda r: u(r).cylinder.viscous_friction_n_s_m)
        self.inertia = col(lambda r: u(r).motor.inertia_kg_m2)
        self.torque_limit = col(lambda r: u(r).motor.torque_limit_nm)
        self.speed_limit = col(lambda r: u(r).motor.speed_limit_rpm)
        self.reservoir = col(lambda r: u(r).reservoir_pa)
        self.beta_oil = col(lambda r: u(r).bulk_modulus_pa)
        self.air = col(lambda r: r.air_fraction)
        self.slip = col(lambda r: r.belt_slip_per_nm)
        self.has_air = bool(np.any(self.air > 0.0))
        self.has_slip = bool(np.any(self.slip > 0.0))
        self.fill = col(lambda r: r.fill_loss)
        self.has_fill = bool(np.any(self.fill > 0.0))
        self.bore_leak = col(lambda r: r.bore_leak_m3_s_pa)
        self.has_bore_leak = bool(np.any(self.bore_leak > 0.0))
        self.orifice_a = col(lambda r: r.orifice_leak_a_m3_s_sqrt_pa)
        self.orifice_b = col(lambda r: r.orifice_leak_b_m3_s_sqrt_pa)
        gain = col(lambda r: r.leak_speed_gain)
        rated = col(lambda r: r.leak_rated_pump_speed_rpm)
        self.has_leak_shape = bool(np.any(self.orifice_a > 0.0) or np.any(self.orifice_b > 0.0)
                                   or np.any(gain > 0.0))
        # leakage factor base + slope |n| per side, 1 and 0 without the effect
        self.leak_base = 1.0 / (1.0 + gain)
        self.leak_slope_a = col(lambda r: abs(u(r).a.pump.speed_ratio)) * gain / rated \
            * self.leak_base
        self.leak_slope_b = col(lambda r: abs(u(r).b.pump.speed_ratio)) * gain / rated \
            * self.leak_base
        self.seal_a = col(lambda r: r.seal_friction_a_n_per_pa)
        self.seal_b = col(lambda r: r.seal_friction_b_n_per_pa)
        self.has_seal = bool(np.any(self.seal_a > 0.0) or np.any(self.seal_b > 0.0))
        self.hose = col(lambda r: r.hose_compliance_per_pa)
        self.has_hose = bool(np.any(self.hose > 0.0))
        # pump flow per motor rpm, signed into the chamber; leakage coefficient (m^3)
        self.q_a = col(lambda r: u(r).a.pump.geometric_flow_m3_s(1.0))
        self.q_b = col(lambda r: u(r).b.pump.geometric_flow_m3_s(1.0))
        self.leak_a = col(lambda r: u(r).a.pump.leak_coeff_m3)
        self.leak_b = col(lambda r: u(r).b.pump.leak_coeff_m3)
        # valve tables per regime: conductance G and G * (pressure where the flow is zero)
        self.crack_a = col(lambda r: u(r).a.anticav.cracking_pa)
        self.crack_b = col(lambda r: u(r).b.anticav.cracking_pa)
        self.relief_a = col(lambda r: u(r).a.relief.setting_pa)
        self.relief_b = col(lambda r: u(r).b.relief.setting_pa)
        zero = np.zeros(self.size)

        def valve_tables(side: str) -> tuple[np.ndarray, np.ndarray]:
            g_ac = col(lambda r: getattr(u(r), side).anticav.gradient_m3_s_pa)
            cr = col(lambda r: getattr(u(r), side).anticav.cracking_pa)
            g_rv = col(lambda r: getattr(u(r), side).relief.gradient_m3_s_pa)
            st = col(lambda r: getattr(u(r), side).relief.setting_pa)
            g = np.stack([g_ac, zero, zero, g_rv], axis=1)
            ge = np.stack([g_ac * cr, zero, zero, g_rv * st], axis=1)
            return g, ge

        self._g_a, self._ge_a = valve_tables("a")
        self._g_b, self._ge_b = valve_tables("b")
        # torque gain tables [row, direction (neg, standstill, pos), regime]
        self._k_a = self._gain_table("a")
        self._k_b = self._gain_table("b")
        # state
        n = self.size
        self.x = np.zeros(n)
        self.v = np.zeros(n)
        self.dp_a = np.zeros(n)
        self.dp_b = np.zeros(n)
        self.n = np.zeros(n)
        self.torque = np.zeros(n)
        self.friction_state = np.zeros(n, dtype=np.int64)
        self.motor_state = np.zeros(n, dtype=np.int64)
        self.regime_a = np.full(n, 2, dtype=np.int8)
        self.regime_b = np.full(n, 2, dtype=np.int8)
        self.speed_controlled = np.zeros(n, dtype=bool)
        self.speed_command = np.zeros(n)
        self.any_speed_controlled = False
        self._dir_cmd = np.ones(n, dtype=np.int64)
        # step-size dependent constants
        h = self.h
        self._hq_a, self._hq_b = h * self.q_a, h * self.q_b
        self._hg_a, self._hge_a = h * self._g_a, h * self._ge_a
        self._hg_b, self._hge_b = h * self._g_b, h * self._ge_b
        self._nha, self._hb = -h * self.area_a, h * self.area_b
        self._inv_beta = 1.0 / self.beta_oil
        self._h_leak_a, self._h_leak_b = h * self.leak_a, h * self.leak_b
        self._h_orifice_a, self._h_orifice_b = h * self.orifice_a, h * self.orifice_b
        self._hose_c = self.dead * self.hose          # m^3/Pa of wall expansion per side
        self._mu = None
        self._jp = self.inertia * RPM_RAD_S / h      # N*m per rpm of speed change in a step
        self._mp = self.mass / h
        self._mpc = self._mp + self.c_viscous
        # flat lookup tables: [row * 4 + regime], [row * 12 + direction * 4 + regime]
        self._base4 = self._idx * 4
        self._base12 = self._idx * 12
        self._hg_a_f, self._hge_a_f = self._hg_a.ravel(), self._hge_a.ravel()
        self._hg_b_f, self._hge_b_f = self._hg_b.ravel(), self._hge_b.ravel()
        self._k_a_f, self._k_b_f = self._k_a.ravel(), self._k_b.ravel()
        self.unconverged_steps = 0
        self.iterations = 0
        self.steps = 0

    # --- construction helpers ----------------------------------------------------------

    def _gain_table(self, side: str) -> np.ndarray:
        out = np.empty((self.size, 3, 4))
        p_sign = np.array([-1.0, -1.0, 1.0, 1.0])
        for i, r in enumerate(self.rows):
            pump = getattr(r.unit, side).pump
            for d, direction in enumerate((-1.0, 0.0, 1.0)):
                out[i, d] = pump.torque_gain_nm_per_pa(p_sign, direction)
        return out

    def set_speed_control(self, mask: np.ndarray, speed_rpm: np.ndarray | float = 0.0) -> None:
        """Rows in ``mask`` follow ``speed_rpm`` exactly (the drive in speed mode); the others
        are torque-controlled. The torque then reported is the one the drive needs."""
        mask = np.asarray(mask, dtype=bool) & np.ones(self.size, dtype=bool)
        self.speed_command = np.where(mask, speed_rpm, 0.0) * np.ones(self.size)
        self._dir_cmd = (np.sign(self.speed_command) + 1).astype(np.int64)
        released = self.speed_controlled & ~mask
        self.motor_state = np.where(released, np.sign(self.n).astype(np.int64),
                                    np.where(mask, M_SPEED, self.motor_state))
        self.speed_controlled = mask
        self.any_speed_controlled = bool(mask.any())

    def set_state(self, x_m: np.ndarray, speed_rpm: np.ndarray, dp_a: np.ndarray,
                  dp_b: np.ndarray, velocity_m_s: np.ndarray | None = None) -> None:
        """Start from given states; discrete states are derived from them."""
        self.x = np.clip(np.asarray(x_m, dtype=float).copy(), 0.0, self.stroke)
        self.n = np.asarray(speed_rpm, dtype=float).copy()
        self.dp_a = np.asarray(dp_a, dtype=float).copy()
        self.dp_b = np.asarray(dp_b, dtype=float).copy()
        self.v = (np.zeros(self.size) if velocity_m_s is None
                  else np.asarray(velocity_m_s, dtype=float).copy())
        self.friction_state = np.sign(self.v).astype(np.int64)
        self.motor_state = np.where(self.speed_controlled, M_SPEED,
                                    np.sign(self.n).astype(np.int64))
        self.regime_a = self._regime(self.dp_a, self.crack_a, self.relief_a)
        self.regime_b = self._regime(self.dp_b, self.crack_b, self.relief_b)
        self.torque = self.pump_torque(self.dp_a, self.dp_b, self.n)

    def _capacitances(self, va: np.ndarray, vb: np.ndarray, inv_ba: np.ndarray,
                      inv_bb: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Oil taken in per pascal by each chamber: the oil's (and air's) compression, plus
        the hoses' wall expansion."""
        ca, cb = va * inv_ba, vb * inv_bb
        if self.has_hose:
            ca, cb = ca + self._hose_c, cb + self._hose_c
        return ca, cb

    def _leak_conductances(self, pa0: np.ndarray, pb0: np.ndarray, n0: np.ndarray,
                           mu_pa_s: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """h x the leakage conductance per side (m^3/Pa) with an orifice share and speed
        dependence, both taken at the step's start."""
        ga = (self._h_leak_a / mu_pa_s + self._h_orifice_a
              / np.sqrt(np.maximum(np.abs(pa0), ORIFICE_LAMINAR_PA)))
        gb = (self._h_leak_b / mu_pa_s + self._h_orifice_b
              / np.sqrt(np.maximum(np.abs(pb0), ORIFICE_LAMINAR_PA)))
        speed = np.abs(n0)
        return (ga * (self.leak_base + self.leak_slope_a * speed),
                gb * (self.leak_base + self.leak_slope_b * speed))

    def _air_only(self, inv_beta: np.ndarray) -> np.ndarray:
        """Rows without air keep exactly 1/beta_oil (results independent of the batch)."""
        return np.where(self.air > 0.0, inv_beta, self._inv_beta)

    @staticmethod
    def _regime(dp: np.ndarray, crack: np.ndarray, relief: np.ndarray) -> np.ndarray:
        """0 anti-cavitation open, 1 closed below reservoir, 2 closed above, 3 relief open."""
        return ((dp >= crack).view(np.int8) + (dp >= 0.0).view(np.int8)
                + (dp > relief).view(np.int8))

    def pump_torque(self, dp_a: np.ndarray, dp_b: np.ndarray, n: np.ndarray) -> np.ndarray:
        """Pump torque at the motor for given pressures and speeds (physics' efficiency law)."""
        d = (np.sign(n) + 1).astype(np.int64)
        ra = self._regime(dp_a, self.crack_a, self.relief_a)
        rb = self._regime(dp_b, self.crack_b, self.relief_b)
        return self._k_a[self._idx, d, ra] * dp_a + self._k_b[self._idx, d, rb] * dp_b

    # --- the step ----------------------------------------------------------------------

    def step(self, torque_cmd: np.ndarray, mu_pa_s: np.ndarray) -> None:
        """Advance one step with the commanded motor torque (clipped to the limit)."""
        h = self.h
        tau = np.minimum(np.maximum(torque_cmd, -self.torque_limit), self.torque_limit)
        x, v0, pa0, pb0, n0 = self.x, self.v, self.dp_a, self.dp_b, self.n
        va = self.dead + self.area_a * x
        vb = self.dead + self.area_b * (self.stroke - x)
        if mu_pa_s is not self._mu:                # the viscosity changes once per sample
            self._mu = mu_pa_s
            self._ga, self._gb = self._h_leak_a / mu_pa_s, self._h_leak_b / mu_pa_s
        ga, gb = self._ga, self._gb
        if self.has_leak_shape:
            ga, gb = self._leak_conductances(pa0, pb0, n0, mu_pa_s)
        qa, qb = self._hq_a, self._hq_b
        if self.has_slip:
            ratio = np.maximum(1.0 - self.slip * np.abs(self.torque), 0.0)
            qa, qb = qa * ratio, qb * ratio
        if self.has_fill:
            filled = 1.0 - self.fill * (n0 / self.speed_limit) ** 2
            qa, qb = qa * filled, qb * filled
        if self.has_air:
            inv_ba = self._air_only(compliance(pa0, self.air, self.beta_oil,
                                                         self.reservoir))
            inv_bb = self._air_only(compliance(pb0, self.air, self.beta_oil,
                                                         self.reservoir))
        else:
            inv_ba = inv_bb = self._inv_beta
        ca, cb = self._capacitances(va, vb, inv_ba, inv_bb)
        gca, gcb = ca + ga, cb + gb
        cross = 0.0                                # oil passing the piston (m^3), explicit
        if self.has_bore_leak:                     # (slow next to the step)
            scored = np.abs(x / self.stroke - 0.5) < 1.0 / 6.0
            cross = np.where(scored, h * self.bore_leak * (pa0 - pb0), 0.0)
        cpa, cpb = ca * pa0 - cross, cb * pb0 + cross
        f_coulomb, f_static = self.f_coulomb, self.f_static
        if self.has_seal:                          # seals pressed by the start pressures
            seal = (self.seal_a * np.maximum(pa0, 0.0) + self.seal_b * np.maximum(pb0, 0.0))
            f_coulomb, f_static = f_coulomb + seal, f_static + seal
        jp = self._jp
        area_a, area_b = self.area_a, self.area_b
        psi = tau + jp * n0                        # torque the pump must take at n = 0
        inertia_force = self._mp * v0 - self.load  # force balance at v = 0, without friction
        lim = self.speed_limit
        k_a_f, k_b_f, base12 = self._k_a_f, self._k_b_f, self._base12

        mf = self.friction_state
        mm = self.motor_state
        ra, rb = self.regime_a, self.regime_b
        v_fix = x_stop = None
        air_passes = AIR_PASSES if self.has_air else 0
        p_prev = None
        converged = False
        for _ in range(MAX_ITERATIONS):
            ia, ib = self._base4 + ra, self._base4 + rb
            den_a = gca + self._hg_a_f[ia]
            den_b = gcb + self._hg_b_f[ib]
            al_a = (cpa + self._hge_a_f[ia]) / den_a
            al_b = (cpb + self._hge_b_f[ib]) / den_b
            a_a, a_b = qa / den_a, qb / den_b            # pressure per rpm
            b_a, b_b = self._nha / den_a, self._hb / den_b   # pressure per m/s
            kd = _DIRECTION4[mm + 2]
            if self.any_speed_controlled:
                kd = np.where(mm == M_SPEED, self._dir_cmd * 4, kd)
            kd = kd + base12
            k_a, k_b = k_a_f[kd + ra], k_b_f[kd + rb]
            torque_mode = mm * mm == 1
            moving = mf * mf == 1
            all_torque, all_moving = torque_mode.all(), moving.all()
            m11 = jp + k_a * a_a + k_b * a_b
            m12 = k_a * b_a + k_b * b_b
            r1 = psi - k_a * al_a - k_b * al_b
            if not all_torque:
                n_fix = np.where(mm == M_SPEED, self.speed_command,
                                 np.where(mm == M_LIM_POS, lim,
                                          np.where(mm == M_LIM_NEG, -lim, 0.0)))
                m11 = np.where(torque_mode, m11, 1.0)
                m12 = np.where(torque_mode, m12, 0.0)
                r1 = np.where(torque_mode, r1, n_fix)
            m21 = area_b * a_b - area_a * a_a
            m22 = self._mpc + area_b * b_b - area_a * b_a
            r2 = inertia_force - mf * f_coulomb + area_a * al_a - area_b * al_b
            if not all_moving:
                m21 = np.where(moving, m21, 0.0)
                m22 = np.where(moving, m22, 1.0)
                r2 = np.where(moving, r2, 0.0 if v_fix is None else v_fix)
            det = m11 * m22 - m12 * m21
            n = (r1 * m22 - m12 * r2) / det
            v = (m11 * r2 - m21 * r1) / det
            pa = al_a + a_a * n + b_a * v
            pb = al_b + a_b * n + b_b * v
            self.iterations += 1

            # --- are the discrete states self-consistent? ------------------------------
            new_ra = self._regime(pa, self.crack_a, self.relief_a)
            new_rb = self._regime(pb, self.crack_b, self.relief_b)
            bad = (new_ra != ra) | (new_rb != rb)
            bad |= torque_mode & ((mm * n <= 0.0) | (np.abs(n) > lim))
            x_new = x + h * v
            past_stop = (x_new < 0.0) | (x_new > self.stroke)
            bad |= moving & ((mf * v <= 0.0) | past_stop)
            stuck = mf == F_STUCK
            if not all_moving:
                force0 = inertia_force + area_a * pa - area_b * pb
                f_hi = np.where(x >= self.stroke, np.inf, f_static)   # an end stop
                f_lo = np.where(x <= 0.0, -np.inf, -f_static)         # takes any force
                bad |= stuck & ((force0 > f_hi) | (force0 < f_lo))
            other_motor = (not all_torque) and bool(((mm != M_SPEED) & ~torque_mode).any())
            if other_motor:
                t_pos = k_a_f[base12 + 8 + new_ra] * pa + k_b_f[base12 + 8 + new_rb] * pb
                t_neg = k_a_f[base12 + new_ra] * pa + k_b_f[base12 + new_rb] * pb
                bad |= (((mm == M_STUCK) & ((psi > t_pos) | (psi < t_neg)))
                        | ((mm == M_LIM_POS) & (jp * lim + t_pos > psi))
                        | ((mm == M_LIM_NEG) & (-jp * lim + t_neg < psi)))
            any_bad = bad.any()
            if air_passes > 0:
                # secant bulk modulus over the step, iterated until the pressures it gives
                # agree with the ones it was taken over: the compression is then exact
                moved = (np.inf if p_prev is None else
                         max(np.max(np.abs(pa - p_prev[0])), np.max(np.abs(pb - p_prev[1]))))
                if moved > AIR_TOLERANCE_PA:
                    p_prev = (pa, pb)
                    inv_ba = self._air_only(secant_compliance(
                        pa0, pa, self.air, self.beta_oil, self.reservoir))
                    inv_bb = self._air_only(secant_compliance(
                        pb0, pb, self.air, self.beta_oil, self.reservoir))
                    ca, cb = self._capacitances(va, vb, inv_ba, inv_bb)
                    gca, gcb = ca + ga, cb + gb
                    cpa, cpb = ca * pa0 - cross, cb * pb0 + cross
                    air_passes -= 1
                    if not any_bad:
                        continue
            if not any_bad:
                converged = True
                break
            # --- slow path: move each row to the states its solution implies -----------
            if all_moving:              # no stuck row: the stuck conditions are all False
                force0 = f_hi = f_lo = 0.0
            new_mf = np.select(
                [moving & (mf * v <= 0.0), moving & past_stop,
                 stuck & (force0 > f_hi), stuck & (force0 < f_lo)],
                [F_STUCK, F_IMPACT, F_UP, F_DOWN], mf)
            # the stop an impact meets is the nearer end (mf may already read F_IMPACT here)
            stop = np.where(x > 0.5 * self.stroke, self.stroke, 0.0)
            x_stop = np.where(new_mf == F_IMPACT, stop,
                              x if x_stop is None else np.where(mf == F_IMPACT, x_stop, x))
            v_fix = (x_stop - x) / h                  # the velocity that reaches the stop
            if not other_motor:
                t_pos = t_neg = psi
            new_mm = np.select(
                [torque_mode & (mm * n <= 0.0), (mm == M_POS) & (n > lim),
                 (mm == M_NEG) & (n < -lim),
                 (mm == M_STUCK) & (psi > t_pos), (mm == M_STUCK) & (psi < t_neg),
                 (mm == M_LIM_POS) & (jp * lim + t_pos > psi),
                 (mm == M_LIM_NEG) & (-jp * lim + t_neg < psi)],
                [M_STUCK, M_LIM_POS, M_LIM_NEG, M_POS, M_NEG, M_POS, M_NEG], mm)
            ra, rb, mf, mm = new_ra, new_rb, new_mf, new_mm
        if not converged:
            self.unconverged_steps += 1
        self.steps += 1

        # actual motor torque: the command, unless the speed is imposed (limit, speed mode)
        if not all_torque:
            imposed = (mm == M_LIM_POS) | (mm == M_LIM_NEG) | (mm == M_SPEED)
            if imposed.any():
                d4 = (np.sign(n).astype(np.int64) + 1) * 4
                t_pump = k_a_f[base12 + d4 + ra] * pa + k_b_f[base12 + d4 + rb] * pb
                tau = np.where(imposed, jp * (n - n0) + t_pump, tau)
        if x_stop is not None:                    # an end stop reached exactly
            x_new = np.where(mf == F_IMPACT, x_stop, x_new)
        self.x = np.minimum(np.maximum(x_new, 0.0), self.stroke)
        self.v = v
        self.dp_a, self.dp_b, self.n, self.torque = pa, pb, n, tau
        self.regime_a, self.regime_b = ra, rb
        self.friction_state = mf if all_moving else np.where(mf == F_IMPACT, F_STUCK, mf)
        self.motor_state = mm

    # --- diagnostics used by the tests -------------------------------------------------

    def chamber_volumes_m3(self, x: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
        x = self.x if x is None else x
        return self.dead + self.area_a * x, self.dead + self.area_b * (self.stroke - x)
