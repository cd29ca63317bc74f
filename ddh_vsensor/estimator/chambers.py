"""The unit's chambers as compressible volumes, driven by the measured motor speed and torque.

The movement tables hold steady states: they assume the chamber pressures have settled. This
model drops that assumption. Per sample it solves, by backward Euler over the sample step h,

    C_s (p_s - p_s') / h = q_s(n) - g_s(mu) p_s + q_valves,s(p_s) - sign_s A_s v    (s = A, B)
    tau - J d(omega)/dt  = k_A p_A + k_B p_B                       (pump torque at the motor)

for the rod velocity v and both gauge pressures, with C_s = V_s(x) / beta_eff(p) the chamber's
compliance (oil-air mixture law, ``physics.air``) and V_s the chamber plus dead volume. Every other
element (pump flow and leakage, valve characteristics, torque gains with their efficiencies)
is the one of ``physics/``, so with h -> infinity each step is exactly the tables' steady
state. No load model is needed: the measured torque closes the system.

Each step is piecewise linear in the pressures; the valve regimes of the previous step are
tried first and every row that comes out inconsistent is solved by enumerating all sixteen
(as ``physics.steady`` does). The compliance is taken as the secant over the step (two
passes, where a row has air), so the compression is exact for the pressures found.

The step is compiled C (``_air_chambers.c``, built with the package like the dynamic mode's
step and sharing its valve arithmetic): the diagnosis integrates every run for every air
fraction it tries. Where the install had no C compiler the numpy form below runs instead,
rows in lockstep, equal to rounding.
"""

from __future__ import annotations

import ctypes
import functools
import math
from collections.abc import Sequence
from dataclasses import dataclass, replace

import numpy as np
from numpy.typing import ArrayLike

from ddh_vsensor.compiled import package_library
from ddh_vsensor.estimator.dynamic import parameters
from ddh_vsensor.physics.air import log_density_and_compliance
from ddh_vsensor.physics.conversions import RPM_RAD_S
from ddh_vsensor.physics.steady import steady_state_at_torque
from ddh_vsensor.physics.unit import DDHUnit

_P_SIGN = np.array([-1.0, -1.0, 1.0, 1.0])          # pressure sign of each valve regime
SECANT_MIN_PA = 100.0                               # below: the tangent is the secant
# the state vector of the compiled step (A_* of _air_chambers.c)
A_PA, A_PB, A_V, A_X, A_N, A_TAU, A_RA, A_RB, A_SIZE = range(9)


@functools.cache
def library() -> ctypes.CDLL | None:
    """The compiled step, loaded once; None where the install could not build it (the numpy
    step runs)."""
    cdll = package_library("ddh_vsensor.estimator._air_chambers")
    if cdll is None:
        return None
    if cdll.air_sizes(1) != A_SIZE:
        raise RuntimeError(f"{cdll._name}: layout differs from chambers.py; reinstall the package")
    ptr, dbl, i32 = ctypes.c_void_p, ctypes.c_double, ctypes.c_int
    cdll.air_step.argtypes = [ptr, dbl, dbl, i32, ptr, dbl, dbl, dbl, dbl]
    cdll.air_step.restype = None
    cdll.air_track.argtypes = [ptr, dbl, dbl, i32, ptr, ctypes.c_long, ptr, ptr, ptr, ptr,
                               ptr, ptr, ptr]
    cdll.air_track.restype = None
    return cdll


@dataclass(frozen=True)
class ChamberRow:
    """One run's measured inputs and the air fraction to integrate it with."""

    time_s: np.ndarray
    speed_rpm: np.ndarray
    torque_nm: np.ndarray
    oil_temp_c: np.ndarray
    initial_position_mm: float
    air_fraction: float = 0.0


@dataclass(frozen=True)
class ChamberTrack:
    """Position (mm) and gauge chamber pressures (Pa) of one row, per sample."""

    position_mm: np.ndarray
    p_a_pa: np.ndarray
    p_b_pa: np.ndarray


class _Constants:
    """Per-unit constants of the step, as arrays indexed by regime and direction."""

    def __init__(self, unit: DDHUnit) -> None:
        a, b, cyl = unit.a, unit.b, unit.cylinder
        self.area_a, self.area_b, self.stroke = a.area_m2, b.area_m2, cyl.stroke_m
        self.dead = unit.dead_volume_m3
        self.q_a = float(a.pump.geometric_flow_m3_s(1.0))      # per motor rpm, into chamber
        self.q_b = float(b.pump.geometric_flow_m3_s(1.0))
        self.leak_a, self.leak_b = a.pump.leak_coeff_m3, b.pump.leak_coeff_m3
        self.crack = a.anticav.cracking_pa
        self.relief_a, self.relief_b = a.relief.setting_pa, b.relief.setting_pa

        def valves(side):
            g_ac, cr = side.anticav.gradient_m3_s_pa, side.anticav.cracking_pa
            g_rv, st = side.relief.gradient_m3_s_pa, side.relief.setting_pa
            return np.array([g_ac, 0.0, 0.0, g_rv]), np.array([g_ac * cr, 0.0, 0.0, g_rv * st])

        self.g_a, self.ge_a = valves(a)
        self.g_b, self.ge_b = valves(b)
        # torque gain [direction (n<0, n=0, n>0), regime]
        self.k_a = np.stack([a.pump.torque_gain_nm_per_pa(_P_SIGN, d) for d in (-1.0, 0.0, 1.0)])
        self.k_b = np.stack([b.pump.torque_gain_nm_per_pa(_P_SIGN, d) for d in (-1.0, 0.0, 1.0)])
        self.inertia = unit.motor.inertia_kg_m2
        self.beta = unit.bulk_modulus_pa
        self.reservoir = unit.reservoir_pa
        # the sixteen regime pairs (A, B) and each regime's pressure range
        self.all_a = np.repeat(np.arange(4), 4)[None, :]
        self.all_b = np.tile(np.arange(4), 4)[None, :]
        self.lo_a = np.array([-np.inf, self.crack, 0.0, self.relief_a])[self.all_a]
        self.hi_a = np.array([self.crack, 0.0, self.relief_a, np.inf])[self.all_a]
        self.lo_b = np.array([-np.inf, self.crack, 0.0, self.relief_b])[self.all_b]
        self.hi_b = np.array([self.crack, 0.0, self.relief_b, np.inf])[self.all_b]

    def regime(self, dp: np.ndarray, relief: float) -> np.ndarray:
        """0 anti-cavitation open, 1 closed below reservoir, 2 closed above, 3 relief open."""
        return (dp >= self.crack).astype(np.intp) + (dp >= 0.0) + (dp > relief)


def _pad(arrays: Sequence[np.ndarray], length: int, fill_last: bool = True) -> np.ndarray:
    out = np.empty((length, len(arrays)))
    for i, a in enumerate(arrays):
        out[:len(a), i] = a
        out[len(a):, i] = a[-1] if fill_last else 0.0
    return out


def _column(k: int, kind: type = float) -> property:
    """Column ``k`` of a model's state as an attribute (a copy; assigning writes it)."""
    def get(self: "ChamberModel") -> np.ndarray:
        return self.state[:, k].astype(kind)

    def put(self: "ChamberModel", value: ArrayLike) -> None:
        self.state[:, k] = value
    return property(get, put)


class ChamberModel:
    """The chamber model for a batch of rows, one sample at a time (the online face; the
    offline :func:`track_chambers` drives it over whole runs). The state of row i is
    ``state[i]`` (A_* layout), shared by the compiled and the numpy step."""

    def __init__(self, unit: DDHUnit, air_fraction: ArrayLike, speed_rpm: ArrayLike,
                 torque_nm: ArrayLike, oil_temp_c: ArrayLike, position_mm: ArrayLike,
                 inertia: bool = True, max_gap_s: float = math.inf,
                 use_compiled: bool = True) -> None:
        """Start settled: the steady state at the first sample's speed and torque."""
        self.unit, self.c = unit, _Constants(unit)
        c = self.c
        self.air = np.atleast_1d(np.asarray(air_fraction, dtype=float))
        size = len(self.air)
        n, tau, temp = (np.broadcast_to(np.asarray(a, dtype=float), (size,)).copy()
                        for a in (speed_rpm, torque_nm, oil_temp_c))
        st = steady_state_at_torque(unit, n, tau, temp)
        self.state = np.empty((size, A_SIZE))
        self.p_a, self.p_b = st.p_a_pa - c.reservoir, st.p_b_pa - c.reservoir
        self.x = np.broadcast_to(np.asarray(position_mm, dtype=float), (size,)) * 1e-3
        self.v = st.velocity_m_s
        self.n, self.tau = n, tau
        self.regime_a = c.regime(self.p_a, c.relief_a)
        self.regime_b = c.regime(self.p_b, c.relief_b)
        self.has_air = bool(np.any(self.air > 0.0))
        self.inertia, self.max_gap_s = inertia, max_gap_s
        self._lib = library() if use_compiled else None
        self.params = parameters(unit, inertia=inertia, blend_s=0.0, max_gap_s=max_gap_s)

    p_a, p_b, v, x = _column(A_PA), _column(A_PB), _column(A_V), _column(A_X)
    n, tau = _column(A_N), _column(A_TAU)
    regime_a, regime_b = _column(A_RA, np.intp), _column(A_RB, np.intp)

    @property
    def compiled(self) -> bool:
        return self._lib is not None

    @property
    def position_mm(self) -> np.ndarray:
        return self.x * 1e3

    def advance(self, h: ArrayLike, speed_rpm: ArrayLike, torque_nm: ArrayLike,
                mu_pa_s: ArrayLike) -> None:
        """One sample ``h`` seconds after the last (rows with h <= 0 keep their state)."""
        c, air, pa, pb, x = self.c, self.air, self.p_a, self.p_b, self.x
        h, nk, torque, mu_pa_s = (np.broadcast_to(np.asarray(a, dtype=float), x.shape)
                                  for a in (h, speed_rpm, torque_nm, mu_pa_s))
        if self._lib is not None:
            for i, row in enumerate(self.state):
                self._lib.air_step(self.params.ctypes.data, c.reservoir, air[i],
                                   int(self.inertia), row.ctypes.data, h[i], nk[i],
                                   torque[i], mu_pa_s[i])
            return
        raw_torque = torque
        live = h > 0.0
        hs = np.where(live, h, 1.0)
        q_a, q_b = c.q_a * nk, c.q_b * nk
        g_a, g_b = c.leak_a / mu_pa_s, c.leak_b / mu_pa_s
        xv = np.clip(x, 0.0, c.stroke)
        vol_a = c.dead + c.area_a * xv
        vol_b = c.dead + c.area_b * (c.stroke - xv)
        if self.inertia:
            # The speed's backward difference is the rotor's mean acceleration over the step,
            # so it pairs with the step's mean motor torque (not the torque at its end: in a
            # sharp torque ramp that half-sample misalignment is worth many N*m).
            torque = 0.5 * (torque + self.tau) - c.inertia * RPM_RAD_S * (nk - self.n) / hs
        l_a, inv_a = log_density_and_compliance(pa, air, c.beta, c.reservoir)
        l_b, inv_b = log_density_and_compliance(pb, air, c.beta, c.reservoir)
        d = (np.sign(nk) + 1).astype(np.intp)
        ca, cb = vol_a * inv_a / hs, vol_b * inv_b / hs        # tangent at the last pressure
        new_pa, new_pb, new_v, ra, rb = _solve(c, q_a + ca * pa, q_b + cb * pb, ca + g_a,
                                               cb + g_b, torque, d, self.regime_a,
                                               self.regime_b)
        if self.has_air:    # again with the secant compliance over the step: exact compression
            first = new_pa, new_pb, new_v, ra, rb
            l1_a, _ = log_density_and_compliance(new_pa, air, c.beta, c.reservoir)
            l1_b, _ = log_density_and_compliance(new_pb, air, c.beta, c.reservoir)
            dpa, dpb = new_pa - pa, new_pb - pb
            ca = vol_a * np.where(np.abs(dpa) > SECANT_MIN_PA,
                                  (l1_a - l_a) / np.where(dpa == 0.0, 1.0, dpa), inv_a) / hs
            cb = vol_b * np.where(np.abs(dpb) > SECANT_MIN_PA,
                                  (l1_b - l_b) / np.where(dpb == 0.0, 1.0, dpb), inv_b) / hs
            second = _solve(c, q_a + ca * pa, q_b + cb * pb, ca + g_a, cb + g_b, torque, d,
                            ra, rb)
            # rows without air keep the first pass: a row's track does not depend on its batch
            new_pa, new_pb, new_v, ra, rb = (np.where(air > 0.0, b, a)
                                             for a, b in zip(first, second))
        self.p_a = np.where(live, new_pa, pa)
        self.p_b = np.where(live, new_pb, pb)
        # trapezoidal, as the estimator integrates its table velocities
        self.x = np.where(live & (h <= self.max_gap_s), x + 0.5 * h * (self.v + new_v), x)
        self.v = np.where(live, new_v, self.v)
        self.n = np.where(live, nk, self.n)
        self.tau = np.where(live, raw_torque, self.tau)
        self.regime_a = np.where(live, ra, self.regime_a)
        self.regime_b = np.where(live, rb, self.regime_b)


def window_pump_torque(time_s: np.ndarray, speed_rpm: np.ndarray, torque_nm: np.ndarray,
                       inertia_nm_s_per_rpm: float, window_s: float) -> np.ndarray:
    """Per sample, the mean motor torque less J*d(omega)/dt over the last samples spanning
    ``window_s`` (the dynamic mode's window): the speed comes in
    whole rpm, which over one fast sample reads as newton-metres of inertia torque."""
    t = np.asarray(time_s, dtype=float)
    n = np.asarray(speed_rpm, dtype=float)
    tau = np.asarray(torque_nm, dtype=float)
    m = max(1, int(round(window_s / float(np.median(np.diff(t))))))
    k = np.arange(len(t))
    j = np.maximum(k - m, 0)
    area = np.concatenate([[0.0], np.cumsum(0.5 * (tau[1:] + tau[:-1]) * np.diff(t))])
    span = t - t[j]
    safe = np.where(span > 0.0, span, 1.0)
    return np.where(span > 0.0, (area - area[j]) / safe - inertia_nm_s_per_rpm * (n - n[j]) / safe,
                    tau)


def _faster_than(time_s: np.ndarray, window_s: float) -> bool:
    return len(time_s) > 1 and 1.5 * float(np.median(np.diff(time_s))) < window_s


def track_chambers(unit: DDHUnit, rows: Sequence[ChamberRow], inertia: bool = True,
                   max_gap_s: float = math.inf, window_s: float = 0.0) -> list[ChamberTrack]:
    """Integrate every row; ``inertia`` subtracts the motor's J*d(omega)/dt from its torque,
    over ``window_s`` (:func:`window_pump_torque`) where a row is sampled faster than that.
    Over a gap longer than ``max_gap_s`` the position is not advanced (as the estimator)."""
    fast = [inertia and _faster_than(r.time_s, window_s) for r in rows]
    if any(fast):
        # the fast rows with their inertia taken off over the window, the others as they are
        j = unit.motor.inertia_kg_m2 * RPM_RAD_S
        out: list[ChamberTrack | None] = [None] * len(rows)
        for windowed in (True, False):
            picked = [i for i, f in enumerate(fast) if f == windowed]
            group = [replace(rows[i], torque_nm=window_pump_torque(
                rows[i].time_s, rows[i].speed_rpm, rows[i].torque_nm, j, window_s))
                if windowed else rows[i] for i in picked]
            for i, tr in zip(picked, track_chambers(unit, group, not windowed, max_gap_s)
                             if group else ()):
                out[i] = tr
        return out  # type: ignore[return-value]
    lengths = [len(r.time_s) for r in rows]
    firsts = [np.array([r.time_s[0], r.speed_rpm[0], r.torque_nm[0], r.oil_temp_c[0]])
              if len(r.time_s) else np.zeros(4) for r in rows]
    start = np.array(firsts).T
    model = ChamberModel(unit, [r.air_fraction for r in rows], start[1], start[2], start[3],
                         [r.initial_position_mm for r in rows], inertia, max_gap_s)
    if model.compiled:
        return [_track_compiled(model, i, r) for i, r in enumerate(rows)]
    length, size = max(lengths), len(rows)
    t = _pad([r.time_s for r in rows], length)
    n = _pad([r.speed_rpm for r in rows], length)
    tau = _pad([r.torque_nm for r in rows], length)
    mu = unit.oil.dynamic_viscosity_pa_s(_pad([r.oil_temp_c for r in rows], length))
    out_x, out_pa, out_pb = (np.empty((length, size)) for _ in range(3))
    out_x[0], out_pa[0], out_pb[0] = model.x, model.p_a, model.p_b
    for k in range(1, length):
        model.advance(t[k] - t[k - 1], n[k], tau[k], mu[k])
        out_x[k], out_pa[k], out_pb[k] = model.x, model.p_a, model.p_b
    return [ChamberTrack(out_x[:m, i] * 1e3, out_pa[:m, i], out_pb[:m, i])
            for i, m in enumerate(lengths)]


def _track_compiled(model: ChamberModel, i: int, row: ChamberRow) -> ChamberTrack:
    """Row ``i`` of a model over its whole run, in one call of the compiled step."""
    m = len(row.time_s)
    state = model.state[i].copy()
    inputs = [np.ascontiguousarray(a, dtype=float)
              for a in (row.time_s, row.speed_rpm, row.torque_nm,
                        model.unit.oil.dynamic_viscosity_pa_s(np.asarray(row.oil_temp_c)))]
    out = [np.empty(m) for _ in range(3)]
    model._lib.air_track(model.params.ctypes.data, model.c.reservoir, model.air[i],  # type: ignore[union-attr]
                         int(model.inertia), state.ctypes.data, m,
                         *(a.ctypes.data for a in inputs), *(o.ctypes.data for o in out))
    return ChamberTrack(out[0] * 1e3, out[1], out[2])


def _solve(c: _Constants, fa, fb, da, db, torque, d, ra, rb):
    """One step for every row: pressures and velocity for inflows ``f`` at zero pressure and
    conductances ``d`` (compliance over the step plus leakage), valves by regime."""
    def attempt(ra_, rb_, fa_, fb_, da_, db_, torque_, d_):
        den_a = da_ + c.g_a[ra_]
        den_b = db_ + c.g_b[rb_]
        al_a, be_a = (fa_ + c.ge_a[ra_]) / den_a, -c.area_a / den_a
        al_b, be_b = (fb_ + c.ge_b[rb_]) / den_b, c.area_b / den_b
        k_a, k_b = c.k_a[d_, ra_], c.k_b[d_, rb_]
        v = (torque_ - k_a * al_a - k_b * al_b) / (k_a * be_a + k_b * be_b)
        return al_a + be_a * v, al_b + be_b * v, v

    pa, pb, v = attempt(ra, rb, fa, fb, da, db, torque, d)
    na, nb = c.regime(pa, c.relief_a), c.regime(pb, c.relief_b)
    bad = np.flatnonzero((na != ra) | (nb != rb))
    if bad.size:
        # enumerate all sixteen regime pairs for those rows; keep the self-consistent one
        col = (slice(None), None)
        ppa, ppb, vv = attempt(c.all_a, c.all_b, fa[bad][col], fb[bad][col], da[bad][col],
                               db[bad][col], torque[bad][col], d[bad][col])
        outside = (np.maximum(c.lo_a - ppa, 0.0) + np.maximum(ppa - c.hi_a, 0.0)
                   + np.maximum(c.lo_b - ppb, 0.0) + np.maximum(ppb - c.hi_b, 0.0))
        best = np.argmin(outside, axis=1)
        pick = np.arange(bad.size)
        pa[bad], pb[bad], v[bad] = ppa[pick, best], ppb[pick, best], vv[pick, best]
        na[bad], nb[bad] = best // 4, best % 4
    return pa, pb, v, na, nb
