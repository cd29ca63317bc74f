"""The estimator's `dynamic` mode: the chamber pressures as states, for the 1 kHz step.

The movement tables hold steady states; where the chamber pressures take long to settle
(cold oil: the leakage that settles them is small) the table's velocity is off for as long as
they do. This model keeps both gauge pressures as states and, per sample, solves by backward
Euler over the sample step h

    C_s (p_s - p_s') / h = q_s(n) - g_s(mu) p_s + q_valves,s(p_s) - sign_s A_s v  (s = A, B)
    (tau + tau') / 2 - J (omega - omega') / h = k_A p_A + k_B p_B

with C_s = V_s(x) / beta the chamber's compliance (chamber plus dead volume of the
configuration; no air) and every other element (pump flow, laminar leakage, valves, torque
gains with their efficiencies) the one of ``physics/``: with h -> infinity a step is exactly
the tables' steady state, and the first sample (and one after an input gap) starts there.

Model errors: a wrong pump parameter moves the steady state the pressures settle to, it
cannot run away — the valves bound every pressure, and leakage pulls it back with the time
constant C/g. ``blend_s`` > 0 adds a pull towards the steady state with that time constant
(a virtual leakage C/blend_s); ``estimator.dynamic_blend_s`` in the configuration says which
value was chosen and why.

Where the torque cannot tell the rod's speed, the step does not ask it: a rod on its end stop (the model's own position at the stroke end) stays there
unless the motor drives it away and the chambers' force has overcome the load the rod held
arriving there (the chamber force of its last moving step less the rod's moving friction
then) and the rod's static friction (or both chambers sit on the valves that push it off,
the most force they make that way), and then takes up speed no faster than the force beyond
that gives the empty machine's mass (its first two moving samples); a rod whose chambers
both sit on a one-way valve stays too; a rod at rest mid-stroke takes up speed only the way
the chambers' force changed beyond its static friction, no faster than the change gives that
mass (plus ``start_tolerance_m_s2``); where the pumps stand at either end of a step or
reverse within it, their static friction lets any torque between the motoring and the
pumping one hold the pressures; and a torque step within one sample larger than
``torque_step_nm``, or any where the speed reaches or leaves the motor's speed limit or did
in the step before (the drive's limiter takes over from the torque command there, and its
torque settles in the next step; a reading one rpm below the limit is a zone of its own, as
the limit may be reached in the sample after it), has an unknown shape, so the step's mean
pump torque is taken nearest the last one; below that, so is one within ``torque_curvature``
of the samples' second difference (a torque bending between its samples, the trapezoid off
by a share of the bend), or within ``speed_disagreement`` of how far the speed's second
difference (the change of the steps' mean motor torque where the pump torque stays)
disagrees with the samples beyond ``speed_disagreement_floor_nm`` (either band up to this
step's or the last step's change past the samples' trapezoid, whichever is larger: a swing
may peak between its samples).

The step is compiled C (``_chambers.c``, built with the package as an optional extension and
loaded with ctypes): the online face calls it per sample, the offline face runs the same
function over a whole log, so both share one arithmetic. The step is counted in the drive's
periods (its learnt cadence; a frame lost is two), not taken from each stamp difference: the
drive samples evenly, its frames' stamps jitter, and a jittered h read as inertia torque turns
into pressure a one-way valve does not give back. For the same
reason the torque balance spans the last samples within ``window_s`` (the speed comes in whole
rpm: over 1 ms one rpm reads as newton-metres); at the drive's 100 Hz that is the one sample. Where the install had no C compiler
the same step runs in Python (:func:`_py_step`), slower but equal.
"""

from __future__ import annotations

import ctypes
import logging
import math

import numpy as np
from numpy.typing import ArrayLike

from ddh_vsensor.compiled import package_library
from ddh_vsensor.physics.conversions import RPM_RAD_S
from ddh_vsensor.physics.oil import Oil
from ddh_vsensor.physics.unit import DDHUnit

log = logging.getLogger(__name__)

_P_SIGN = np.array([-1.0, -1.0, 1.0, 1.0])          # pressure sign of each valve regime
# indices of the parameter and state vectors (the P_* / S_* enums of _chambers.c)
(P_AREA_A, P_AREA_B, P_STROKE, P_DEAD_A, P_DEAD_B, P_Q_A, P_Q_B, P_LEAK_A, P_LEAK_B,
 P_CRACK, P_RELIEF_A, P_RELIEF_B, P_INERTIA, P_BETA, P_BLEND_S, P_MAX_GAP_S,
 P_TORQUE_STEP, P_WINDOW_S, P_SPEED_LIMIT, P_CURVATURE, P_DISAGREE, P_DISAGREE_FLOOR) = range(22)
P_G_A, P_GE_A, P_G_B, P_GE_B, P_K_A, P_K_B = 22, 26, 30, 34, 38, 50
P_FRIC_C, P_FRIC_V, P_FRIC_S, P_MASS = 62, 63, 64, 65   # the rod's friction, its load's mass
P_START_TOL = 66                                     # a start's acceleration beyond the mass's
P_SIZE = 67
REST_SPEED = 2e-3                                    # m/s: a rod at rest (as in _chambers.c)
(S_PA, S_PB, S_V, S_X, S_N, S_TAU, S_RA, S_RB, S_SA, S_SB, S_STARTED, S_HF, S_PUMP_TAU,
 S_LOAD_F, S_HF_COUNT, S_HF_DEV, S_RING_AT, S_RING_COUNT, S_RING) = range(19)
RING, HF_LEARN = 32, 20                              # as in _chambers.c
S_LEARN = S_RING + 3 * RING
S_TAU2 = S_LEARN + HF_LEARN                          # the torque sample before S_TAU
S_LEFT = S_TAU2 + 1                                  # +-1: the rod left its end stop last sample
S_SIZE = S_LEFT + 1
HF_GAIN, LOST_AT, JITTER_SPAN = 0.05, 1.5, 3.6       # as in _chambers.c


def _library() -> ctypes.CDLL | None:
    """The compiled step, built with the package (an optional extension of pyproject.toml);
    None where it could not be built."""
    cdll = package_library("ddh_vsensor.estimator._chambers")
    if cdll is None:
        log.warning("dynamic mode: the compiled chamber step was not built with this install "
                    "(no C compiler?); using the Python step (~50 us per sample, equal results)")
        return None
    if cdll.chambers_sizes(0) != P_SIZE or cdll.chambers_sizes(1) != S_SIZE:
        raise RuntimeError(f"{cdll._name}: layout differs from dynamic.py; reinstall the package")
    ptr, dbl = ctypes.c_void_p, ctypes.c_double
    cdll.chambers_step.argtypes = [ptr, ptr, dbl, dbl, dbl, dbl]
    cdll.chambers_step.restype = dbl
    cdll.chambers_run.argtypes = [ptr, ptr, ctypes.c_long, ptr, ptr, ptr, ptr, ptr, dbl]
    cdll.chambers_run.restype = None
    return cdll


_LIB: ctypes.CDLL | None | bool = False


def library() -> ctypes.CDLL | None:
    global _LIB
    if _LIB is False:
        _LIB = _library()
    return _LIB  # type: ignore[return-value]


def parameters(unit: DDHUnit, *, inertia: bool, blend_s: float, max_gap_s: float,
               torque_step_nm: float = math.inf, window_s: float = 0.0,
               torque_curvature: float = 0.0, speed_disagreement: float = 0.0,
               speed_disagreement_floor_nm: float = 0.0,
               start_tolerance_m_s2: float = math.inf) -> np.ndarray:
    """The step's parameter vector for one unit (SI units, speeds in motor rpm)."""
    a, b = unit.a, unit.b
    p = np.zeros(P_SIZE)
    p[P_AREA_A], p[P_AREA_B] = a.area_m2, b.area_m2
    p[P_STROKE] = unit.cylinder.stroke_m
    p[P_DEAD_A] = p[P_DEAD_B] = unit.dead_volume_m3
    p[P_Q_A] = float(a.pump.geometric_flow_m3_s(1.0))
    p[P_Q_B] = float(b.pump.geometric_flow_m3_s(1.0))
    p[P_LEAK_A], p[P_LEAK_B] = a.pump.leak_coeff_m3, b.pump.leak_coeff_m3
    p[P_CRACK] = a.anticav.cracking_pa
    p[P_RELIEF_A], p[P_RELIEF_B] = a.relief.setting_pa, b.relief.setting_pa
    p[P_INERTIA] = unit.motor.inertia_kg_m2 * RPM_RAD_S if inertia else 0.0
    p[P_BETA] = unit.bulk_modulus_pa
    p[P_BLEND_S] = blend_s
    p[P_MAX_GAP_S] = max_gap_s
    p[P_TORQUE_STEP] = torque_step_nm
    p[P_WINDOW_S] = window_s
    p[P_SPEED_LIMIT] = unit.motor.speed_limit_rpm - 1.0     # within the speed's whole rpm
    p[P_CURVATURE] = torque_curvature
    p[P_DISAGREE] = speed_disagreement
    p[P_DISAGREE_FLOOR] = speed_disagreement_floor_nm
    cyl = unit.cylinder
    p[P_FRIC_C], p[P_FRIC_V], p[P_FRIC_S] = (cyl.coulomb_friction_n,
                                             cyl.viscous_friction_n_s_m,
                                             cyl.static_friction_n)
    p[P_MASS] = unit.moving_mass_kg(0.0)                    # the empty machine's: the least
    p[P_START_TOL] = start_tolerance_m_s2
    for side, g, ge, k in ((a, P_G_A, P_GE_A, P_K_A), (b, P_G_B, P_GE_B, P_K_B)):
        g_ac, cr = side.anticav.gradient_m3_s_pa, side.anticav.cracking_pa
        g_rv, st = side.relief.gradient_m3_s_pa, side.relief.setting_pa
        p[g:g + 4] = (g_ac, 0.0, 0.0, g_rv)
        p[ge:ge + 4] = (g_ac * cr, 0.0, 0.0, g_rv * st)
        p[k:k + 12] = np.concatenate([side.pump.torque_gain_nm_per_pa(_P_SIGN, d)
                                      for d in (-1.0, 0.0, 1.0)])
    return p


class DynamicModel:
    """One unit's chamber state and its step; positions in mm, velocities in mm/s."""

    def __init__(self, unit: DDHUnit, position_mm: float, *, inertia: bool = True,
                 blend_s: float = 0.0, max_gap_s: float = math.inf,
                 torque_step_nm: float = math.inf, window_s: float = 0.0,
                 torque_curvature: float = 0.0, speed_disagreement: float = 0.0,
                 speed_disagreement_floor_nm: float = 0.0,
                 start_tolerance_m_s2: float = math.inf, use_compiled: bool = True) -> None:
        if not blend_s >= 0.0:
            raise ValueError(f"blend time constant must be >= 0 s, got {blend_s!r}")
        if not window_s >= 0.0:
            raise ValueError(f"torque balance window must be >= 0 s, got {window_s!r}")
        if not torque_step_nm > 0.0:
            raise ValueError(f"torque step must be > 0 N·m, got {torque_step_nm!r}")
        if not 0.0 <= torque_curvature <= 1.0:
            raise ValueError(f"torque curvature share must be 0..1, got {torque_curvature!r}")
        if not 0.0 <= speed_disagreement <= 1.0:
            raise ValueError(f"speed disagreement share must be 0..1, got {speed_disagreement!r}")
        if not speed_disagreement_floor_nm >= 0.0:
            raise ValueError("speed disagreement floor must be >= 0 N·m, got "
                             f"{speed_disagreement_floor_nm!r}")
        if not start_tolerance_m_s2 >= 0.0:
            raise ValueError("start tolerance must be >= 0 m/s², got "
                             f"{start_tolerance_m_s2!r}")
        self.oil: Oil = unit.oil
        self.params = parameters(unit, inertia=inertia, blend_s=blend_s, max_gap_s=max_gap_s,
                                 torque_step_nm=torque_step_nm, window_s=window_s,
                                 torque_curvature=torque_curvature,
                                 speed_disagreement=speed_disagreement,
                                 speed_disagreement_floor_nm=speed_disagreement_floor_nm,
                                 start_tolerance_m_s2=start_tolerance_m_s2)
        self.state = np.zeros(S_SIZE)
        self.state[S_X] = position_mm * 1e-3
        self.state[S_LOAD_F] = math.nan                 # no load seen moving yet
        self.state[S_RA] = self.state[S_RB] = self.state[S_SA] = self.state[S_SB] = 2.0
        self._lib = library() if use_compiled else None
        self._p_list = self.params.tolist()
        self._p_ptr = self.params.ctypes.data
        self._s_ptr = self.state.ctypes.data
        self._temp_c = math.nan
        self._mu = math.nan

    @property
    def compiled(self) -> bool:
        return self._lib is not None

    @property
    def pressures_bar(self) -> tuple[float, float]:
        """Gauge chamber pressures A and B (bar), as the model holds them."""
        return float(self.state[S_PA]) * 1e-5, float(self.state[S_PB]) * 1e-5

    def set_position(self, position_mm: float | None) -> None:
        """The rod is known to be here (preset, reference), or not known at all (None: no
        end stop is assumed, chamber volumes at mid-stroke)."""
        self.state[S_X] = math.nan if position_mm is None else position_mm * 1e-3

    def viscosity_pa_s(self, oil_temp_c: float) -> float:
        """By the offline run's vectorised formula (its scalar twin differs in the last bit,
        and a decision of the step, a valve or the pumps' friction band, can turn on that
        bit); computed only when the temperature changes."""
        if oil_temp_c != self._temp_c:
            self._temp_c = oil_temp_c
            self._mu = float(self.oil.dynamic_viscosity_pa_s(np.array([oil_temp_c]))[0])
        return self._mu

    def step(self, h_s: float, speed_rpm: float, torque_nm: float, oil_temp_c: float) -> float:
        """One sample ``h_s`` after the last (ignored on the first): velocity in mm/s."""
        mu = self.viscosity_pa_s(oil_temp_c)
        if self._lib is not None:
            return self._lib.chambers_step(self._p_ptr, self._s_ptr, h_s, speed_rpm,
                                           torque_nm, mu) * 1e3
        return _py_step(self._p_list, self.state, h_s, speed_rpm, torque_nm, mu) * 1e3

    def run(self, time_s: ArrayLike, speed_rpm: ArrayLike, torque_nm: ArrayLike,
            oil_temp_c: ArrayLike, t_last_s: float = 0.0) -> np.ndarray:
        """A log from this state (``t_last_s``: the previous sample's time when it continues
        one): velocity in mm/s, equal to :meth:`step`."""
        t = np.ascontiguousarray(time_s, dtype=float)
        n = np.ascontiguousarray(speed_rpm, dtype=float)
        tau = np.ascontiguousarray(torque_nm, dtype=float)
        temp = np.ascontiguousarray(oil_temp_c, dtype=float)
        temp = np.broadcast_to(temp, t.shape) if temp.ndim == 0 else temp
        mu = np.ascontiguousarray(self.oil.dynamic_viscosity_pa_s(temp), dtype=float)
        v = np.empty(len(t))
        if self._lib is not None:
            self._lib.chambers_run(self._p_ptr, self._s_ptr, len(t), t.ctypes.data,
                                   n.ctypes.data, tau.ctypes.data, mu.ctypes.data,
                                   v.ctypes.data, t_last_s)
        else:
            last = t_last_s
            for k in range(len(t)):
                h = 0.0 if self.state[S_STARTED] == 0.0 else t[k] - last
                v[k] = _py_step(self._p_list, self.state, h, n[k], tau[k], mu[k])
                last = t[k]
        if len(t):
            self._temp_c, self._mu = float(temp[-1]), float(mu[-1])
        return v * 1e3


# --- the same step in Python (no compiler) ------------------------------------------------

def _regime(dp: float, crack: float, relief: float) -> int:
    # int() each: numpy booleans (a numpy float's comparisons) add as a logical or
    return int(dp >= crack) + int(dp >= 0.0) + int(dp > relief)


def _linear(P, ra, rb, fa, fb, da, db):
    """``linear`` of _chambers.c: (al_a, be_a, al_b, be_b), each pressure al + be * v."""
    den_a = da + P[P_G_A + ra]
    den_b = db + P[P_G_B + rb]
    return ((fa + P[P_GE_A + ra]) / den_a, -P[P_AREA_A] / den_a,
            (fb + P[P_GE_B + rb]) / den_b, P[P_AREA_B] / den_b)


def _rod_speed(P, al_a, be_a, al_b, be_b, v0: float, h: float, resist: float) -> float:
    """``rod_speed`` of _chambers.c: m (v - v0) / h = F(v) - resist - c_v v, solved for v."""
    m = P[P_MASS]
    return ((P[P_AREA_A] * al_a - P[P_AREA_B] * al_b - resist + m * v0 / h)
            / (m / h - P[P_AREA_A] * be_a + P[P_AREA_B] * be_b + P[P_FRIC_V]))


def _attempt(P, ra, rb, fa, fb, da, db, torque, d):
    al_a, be_a, al_b, be_b = _linear(P, ra, rb, fa, fb, da, db)
    k_a, k_b = P[P_K_A + 4 * d + ra], P[P_K_B + 4 * d + rb]
    v = (torque - k_a * al_a - k_b * al_b) / (k_a * be_a + k_b * be_b)
    return al_a + be_a * v, al_b + be_b * v, v


def _outside(p: float, r: int, crack: float, relief: float) -> float:
    lo = (-math.inf, crack, 0.0, relief)[r]
    hi = (crack, 0.0, relief, math.inf)[r]
    return (lo - p if p < lo else 0.0) + (p - hi if p > hi else 0.0)


def _solve(P, fa, fb, da, db, torque, d, ra, rb):
    crack, rel_a, rel_b = P[P_CRACK], P[P_RELIEF_A], P[P_RELIEF_B]
    pa, pb, v = _attempt(P, ra, rb, fa, fb, da, db, torque, d)
    if _regime(pa, crack, rel_a) == ra and _regime(pb, crack, rel_b) == rb:
        return pa, pb, v, ra, rb
    best = math.inf
    for i in range(4):
        for j in range(4):
            qa, qb, qv = _attempt(P, i, j, fa, fb, da, db, torque, d)
            out = _outside(qa, i, crack, rel_a) + _outside(qb, j, crack, rel_b)
            if out < best:
                best, ra, rb, pa, pb, v = out, i, j, qa, qb, qv
    return pa, pb, v, ra, rb


def _still(P, g: int, ge: int, relief: float, f: float, d: float) -> tuple[float, int]:
    for i in range(4):
        p = (f + P[ge + i]) / (d + P[g + i])
        if _regime(p, P[P_CRACK], relief) == i:
            break
    return p, i


def _at_speed(P, fa: float, fb: float, da: float, db: float, v: float
              ) -> tuple[float, int, float, int]:
    """``at_speed`` of _chambers.c: (pa, ra, pb, rb) at rod speed ``v``, valves included."""
    pa, ra = _still(P, P_G_A, P_GE_A, P[P_RELIEF_A], fa - P[P_AREA_A] * v, da)
    pb, rb = _still(P, P_G_B, P_GE_B, P[P_RELIEF_B], fb + P[P_AREA_B] * v, db)
    return pa, ra, pb, rb


def _drive_step(S: np.ndarray, h: float) -> float:
    """``drive_step`` of _chambers.c: the step's length in the drive's periods."""
    hf, count, dev = float(S[S_HF]), int(S[S_HF_COUNT]), float(S[S_HF_DEV])
    if count < HF_LEARN:
        learnt = sorted([*S[S_LEARN:S_LEARN + count], h])
        S[S_LEARN:S_LEARN + count + 1] = learnt
        S[S_HF] = 0.5 * (learnt[count // 2] + learnt[(count + 1) // 2])
        S[S_HF_COUNT] = count + 1
        return float(S[S_HF]) if count > 0 else h
    lost_at = max(LOST_AT, 1.0 + JITTER_SPAN * dev)
    periods = 1.0 if h < lost_at * hf else float(math.floor(h / hf + 0.5))
    if periods == 1.0:
        S[S_HF_DEV] = dev + HF_GAIN * (abs(h - hf) / hf - dev)
    S[S_HF] = hf + HF_GAIN * (h / periods - hf)
    return periods * hf


def _limit_zone(P, n: float) -> int:
    """``limit_zone`` of _chambers.c."""
    return int(abs(n) >= P[P_SPEED_LIMIT]) + int(abs(n) >= P[P_SPEED_LIMIT] + 1.0)


def _direction(n: float) -> int:
    return 2 if n > 0.0 else 0 if n < 0.0 else 1


def _py_step(P: list[float], S: np.ndarray, h: float, n: float, tau: float, mu: float
             ) -> float:
    """``chambers_step`` of _chambers.c, line by line (``P`` the parameters as a list)."""
    if S[S_STARTED] == 0.0 or not h > 0.0 or h > P[P_MAX_GAP_S]:
        if S[S_STARTED] == 0.0 or h > 0.0:
            pa, pb, v, ra, rb = _solve(P, P[P_Q_A] * n, P[P_Q_B] * n, P[P_LEAK_A] / mu,
                                       P[P_LEAK_B] / mu, tau, _direction(n), int(S[S_SA]),
                                       int(S[S_SB]))
            S[S_PA], S[S_PB], S[S_V] = pa, pb, v
            S[S_RA] = S[S_SA] = ra
            S[S_RB] = S[S_SB] = rb
            S[S_N], S[S_TAU], S[S_STARTED], S[S_HF], S[S_PUMP_TAU] = n, tau, 1.0, 0.0, tau
            S[S_TAU2] = tau
            S[S_RING_AT] = S[S_RING_COUNT] = S[S_HF_COUNT] = S[S_HF_DEV] = S[S_LEFT] = 0.0
        return float(S[S_V])
    pa, pb, x, stroke = float(S[S_PA]), float(S[S_PB]), float(S[S_X]), P[P_STROKE]
    known = x == x                                      # NaN: position unknown
    xv = min(max(x, 0.0), stroke) if known else 0.5 * stroke
    hn = _drive_step(S, h)
    at, count = int(S[S_RING_AT]), int(S[S_RING_COUNT])
    span, earlier, n_first = hn, 0.0, float(S[S_N])
    for i in range(1, min(count, RING - 1) + 1):
        slot = (at - i) % RING
        d = float(S[S_RING + 2 * RING + slot])
        if not span + 0.5 * d < P[P_WINDOW_S]:
            break
        span += d
        earlier += S[S_RING + slot] * d
        n_first = float(S[S_RING + RING + slot])
    earlier /= span
    w = hn / span
    inertia = P[P_INERTIA] * (n - n_first) / span
    mean = 0.5 * (tau + S[S_TAU])
    torque = earlier + w * mean - inertia
    edge = _limit_zone(P, n) != _limit_zone(P, float(S[S_N]))
    last = (at - 1) % RING              # the last step: its length, the speed before it
    n_before = float(S[S_RING + RING + last]) if count > 0 else float(S[S_N])
    edge = edge or _limit_zone(P, float(S[S_N])) != _limit_zone(P, n_before)
    jump = abs(tau - S[S_TAU])
    excess = 0.0
    if count > 0:
        said = P[P_INERTIA] * ((n - S[S_N]) / hn - (S[S_N] - n_before)
                               / S[S_RING + 2 * RING + last])
        excess = abs(said - 0.5 * (tau - S[S_TAU2])) - P[P_DISAGREE_FLOOR]
    swing = max(jump, abs(S[S_TAU] - S[S_TAU2]))      # this step's change or the last one's
    band = min(max(P[P_CURVATURE] * abs(tau - 2.0 * S[S_TAU] + S[S_TAU2]),
                   P[P_DISAGREE] * excess), swing)
    if jump > P[P_TORQUE_STEP] or edge:
        band = max(band, 0.5 * jump)
    if band > 0.0:
        lo, hi = torque - w * band, torque + w * band
        torque = min(max(float(S[S_PUMP_TAU]), lo), hi)
        mean = (torque + inertia - earlier) / w
    S[S_RING + at], S[S_RING + RING + at], S[S_RING + 2 * RING + at] = mean, S[S_N], hn
    S[S_RING_AT], S[S_RING_COUNT] = (at + 1) % RING, min(count + 1, RING)
    S[S_PUMP_TAU] = torque
    ga, gb = P[P_LEAK_A] / mu, P[P_LEAK_B] / mu
    ca = (P[P_DEAD_A] + P[P_AREA_A] * xv) / (P[P_BETA] * hn)
    cb = (P[P_DEAD_B] + P[P_AREA_B] * (stroke - xv)) / (P[P_BETA] * hn)
    fa, fb = P[P_Q_A] * n + ca * pa, P[P_Q_B] * n + cb * pb
    da, db = ca + ga, cb + gb
    d = _direction(n + S[S_N])
    ra, rb = int(S[S_RA]), int(S[S_RB])
    if n * S[S_N] <= 0.0:
        t_neg = P[P_K_A + ra] * pa + P[P_K_B + rb] * pb
        t_pos = P[P_K_A + 8 + ra] * pa + P[P_K_B + 8 + rb] * pb
        if min(t_neg, t_pos) <= torque <= max(t_neg, t_pos):
            torque = P[P_K_A + 4 * d + ra] * pa + P[P_K_B + 4 * d + rb] * pb
        else:
            d = 2 if (torque > max(t_neg, t_pos)) == (t_pos > t_neg) else 0
    if P[P_BLEND_S] > 0.0:
        qa, qb, _, sa, sb = _solve(P, P[P_Q_A] * n, P[P_Q_B] * n, ga, gb, torque, d,
                                   int(S[S_SA]), int(S[S_SB]))
        S[S_SA], S[S_SB] = sa, sb
        ka, kb = ca * hn / P[P_BLEND_S], cb * hn / P[P_BLEND_S]
        fa += ka * qa
        fb += kb * qb
        da += ka
        db += kb
    load = float(S[S_LOAD_F])
    beyond = -1.0                      # force beyond what holds the rod on its stop
    v = 0.0
    still_done = False
    stopped = known and ((x <= 0.0 and n <= 0.0) or (x >= stroke and n >= 0.0))
    if not stopped and known and (x <= 0.0 or x >= stroke) and load == load:
        sa, qa, sb, qb = _at_speed(P, fa, fb, da, db, 0.0)
        force = sa * P[P_AREA_A] - sb * P[P_AREA_B]
        pinned = (qa, qb) == ((3, 0) if x <= 0.0 else (0, 3))
        beyond = (force - load - P[P_FRIC_S] if x <= 0.0
                  else load - P[P_FRIC_S] - force)
        stopped = still_done = not pinned and beyond < 0.0
        if still_done:
            pa, ra, pb, rb = sa, qa, sb, qb
    if not stopped:
        pa, pb, v, ra, rb = _solve(P, fa, fb, da, db, torque, d, ra, rb)
        stopped = ra in (0, 3) and rb in (0, 3)
        vmax = 0.5 * beyond / P[P_MASS] * h
        if not stopped and beyond > 0.0 and S[S_V] == 0.0 and abs(v) > vmax:
            v = math.copysign(vmax, v)
            pa, ra, pb, rb = _at_speed(P, fa, fb, da, db, v)
        if not stopped and S[S_LEFT] * v > 0.0 and load == load:
            # the sample after leaving the end stop: speed taken up with the mass (_chambers.c)
            al_a, be_a, al_b, be_b = _linear(P, ra, rb, fa, fb, da, db)
            sg = float(S[S_LEFT])
            vd = _rod_speed(P, al_a, be_a, al_b, be_b, S[S_V], hn, load + sg * P[P_FRIC_C])
            if sg * vd > 0.0 and sg * v > sg * vd:
                v = vd
                pa, ra, pb, rb = _at_speed(P, fa, fb, da, db, v)
        if not stopped and beyond <= 0.0 and abs(S[S_V]) <= REST_SPEED:
            # a rod at rest starts with the force that starts it (_chambers.c)
            al_a, be_a, al_b, be_b = _linear(P, ra, rb, fa, fb, da, db)
            v0 = float(S[S_V])
            held = S[S_PA] * P[P_AREA_A] - S[S_PB] * P[P_AREA_B] - P[P_FRIC_V] * v0
            lo = min(v0, _rod_speed(P, al_a, be_a, al_b, be_b, v0, hn,
                                    held + P[P_FRIC_S])) - P[P_START_TOL] * hn
            hi = max(v0, _rod_speed(P, al_a, be_a, al_b, be_b, v0, hn,
                                    held - P[P_FRIC_S])) + P[P_START_TOL] * hn
            if v < lo or v > hi:
                v = lo if v < lo else hi
                pa, pb = al_a + be_a * v, al_b + be_b * v
    if stopped and not still_done:
        pa, ra, pb, rb = _at_speed(P, fa, fb, da, db, 0.0)
    if stopped:
        v = 0.0
    x_new = x + 0.5 * h * (S[S_V] + v)
    S[S_X] = min(max(x_new, 0.0), stroke) if known else math.nan
    S[S_LEFT] = math.copysign(1.0, v) if beyond > 0.0 and S[S_V] == 0.0 and v != 0.0 else 0.0
    S[S_PA], S[S_PB], S[S_V], S[S_N] = pa, pb, v, n
    S[S_TAU2], S[S_TAU] = S[S_TAU], tau
    S[S_RA], S[S_RB] = ra, rb
    if v != 0.0 and known:
        S[S_LOAD_F] = (pa * P[P_AREA_A] - pb * P[P_AREA_B]
                       - math.copysign(P[P_FRIC_C] + P[P_FRIC_V] * abs(v), v))
    return v
