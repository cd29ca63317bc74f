"""The unit's dynamics in C: the binding's layout check, the steady state as the step's fixed
point, one step onto an end stop and one onto the speed limit."""

from __future__ import annotations

import ctypes

import numpy as np
import pytest

from ddh_vsensor.model.unit import (
    F_STUCK,
    M_LIM_POS,
    M_POS,
    Counters,
    Input,
    Params,
    RowSpec,
    State,
    check_layout,
    library,
    params,
)
from ddh_vsensor.physics.steady import steady_state
from ddh_vsensor.physics.unit import DDHUnit

T = 27.0
H = 1e-3


def _swapped(structure: type[ctypes.Structure], i: int) -> type[ctypes.Structure]:
    fields = list(structure._fields_)
    fields[i], fields[i + 1] = fields[i + 1], fields[i]
    return type(structure.__name__, (ctypes.Structure,), {"_fields_": fields})


def test_the_binding_matches_the_c_structs():
    lib = library()
    for kind, structure in enumerate((Params, State, Input, Counters)):
        check_layout(lib, kind, structure)


@pytest.mark.parametrize("kind, structure, i", [(0, Params, 0), (1, State, 0), (1, State, 6),
                                                (2, Input, 0)])
def test_swapped_fields_refuse_to_load(kind, structure, i):
    """Two fields of one type swapped: same size, same offsets, different names there."""
    bad = _swapped(structure, i)
    assert ctypes.sizeof(bad) == ctypes.sizeof(structure)
    with pytest.raises(ImportError, match=structure._fields_[i][0]):
        check_layout(library(), kind, bad)


def test_a_field_of_another_size_refuses_to_load():
    fields = [(n, ctypes.c_long if n == "regime_b" else t) for n, t in State._fields_]
    bad = type("State", (ctypes.Structure,), {"_fields_": fields})
    with pytest.raises(ImportError, match="regime_b"):
        check_layout(library(), 1, bad)


class _Row:
    """One unit stepped through the C directly."""

    def __init__(self, row: RowSpec) -> None:
        self.p, self.s, self.i, self.c = params(row), State(), Input(), Counters()
        self.lib = library()
        self.i.mu_pa_s = float(row.unit.oil.dynamic_viscosity_pa_s(T))

    def start(self, x_m: float, n_rpm: float, dp_a_pa: float, dp_b_pa: float,
              v_m_s: float = 0.0) -> None:
        s = self.s
        s.x_m, s.n_rpm, s.dp_a_pa, s.dp_b_pa, s.v_m_s = x_m, n_rpm, dp_a_pa, dp_b_pa, v_m_s
        self.lib.ddh_settle(ctypes.byref(self.p), ctypes.byref(s), ctypes.byref(self.i))

    def step(self, torque_nm: float, h: float = H) -> int:
        self.i.torque_nm = torque_nm
        return self.lib.ddh_step(ctypes.byref(self.p), ctypes.byref(self.s),
                                 ctypes.byref(self.i), h, ctypes.byref(self.c))


@pytest.mark.parametrize("unit, speed_rpm, payload_kg, x_m", [
    ("boom", 150.0, 0.0, 0.03), ("boom", -100.0, 1040.0, 0.3), ("bucket", 150.0, 0.0, 0.1),
    ("bucket", -150.0, 1040.0, 0.8)])
def test_constant_torque_converges_to_the_steady_state(cfg, unit, speed_rpm, payload_kg, x_m):
    """Held at the steady state's torque from half its pressures, the row settles onto
    physics.steady.steady_state's speed, velocity and pressures. Under torque control the
    last approach is slow (a time constant of ~15 s: the torque fixes the pressures, the
    leakage and the viscous friction the speed), hence 90 s in steps of 50 ms."""
    u = DDHUnit.from_config(cfg, unit)
    ss = steady_state(u, speed_rpm, u.load_force_n(payload_kg), T)
    r = _Row(RowSpec(u, payload_kg))
    r.start(x_m, speed_rpm, 0.5 * float(ss.p_a_pa), 0.5 * float(ss.p_b_pa),
            float(ss.velocity_m_s))
    for _ in range(1800):
        assert r.step(float(ss.torque_nm), 0.05) == 1
    assert 0.0 < r.s.x_m < u.cylinder.stroke_m
    assert r.s.n_rpm == pytest.approx(speed_rpm, rel=1e-4)
    assert r.s.v_m_s == pytest.approx(float(ss.velocity_m_s), rel=1e-4)
    assert r.s.dp_a_pa == pytest.approx(float(ss.p_a_pa), abs=1.0)
    assert r.s.dp_b_pa == pytest.approx(float(ss.p_b_pa), abs=1.0)


def test_one_step_onto_the_top_end_stop_stops_there(bucket):
    """A rod that would pass the top end in this step ends it at the end exactly, with the
    velocity that reaches it, and stands there from the next step on."""
    stroke = bucket.cylinder.stroke_m
    ss = steady_state(bucket, 3000.0, bucket.load_force_n(0.0), T)
    v = float(ss.velocity_m_s)
    assert v > 0.05
    r = _Row(RowSpec(bucket))
    r.start(stroke - 0.2 * v * H, 3000.0, float(ss.p_a_pa), float(ss.p_b_pa), v)
    assert r.step(float(ss.torque_nm)) == 1
    assert r.s.x_m == stroke
    assert r.s.v_m_s == pytest.approx(0.2 * v, rel=1e-6)
    assert r.s.friction_state == F_STUCK
    x, pa = r.s.x_m, r.s.dp_a_pa
    assert r.step(float(ss.torque_nm)) == 1
    assert r.s.x_m == x and r.s.v_m_s == 0.0
    assert r.s.dp_a_pa > pa                       # the pumps press on against the stop


def test_one_step_onto_the_speed_limit_holds_it(bucket):
    """Full torque just below the limit: the step ends at the limit exactly and reports the
    torque that takes (inertia plus pump torque), below the command; with a small torque the
    motor leaves the limit again."""
    limit = bucket.motor.speed_limit_rpm
    ss = steady_state(bucket, limit - 20.0, bucket.load_force_n(0.0), T)
    r = _Row(RowSpec(bucket))
    r.start(0.4, limit - 20.0, float(ss.p_a_pa), float(ss.p_b_pa), float(ss.velocity_m_s))
    command = bucket.motor.torque_limit_nm
    assert r.step(command) == 1
    assert r.s.n_rpm == pytest.approx(limit, rel=1e-15)
    assert r.s.motor_state == M_LIM_POS
    assert float(ss.torque_nm) < r.s.torque_nm < command
    assert r.step(command) == 1
    assert r.s.n_rpm == pytest.approx(limit, rel=1e-15)
    assert r.step(0.5 * float(ss.torque_nm)) == 1
    assert r.s.n_rpm < limit and r.s.motor_state == M_POS
    assert r.s.torque_nm == 0.5 * float(ss.torque_nm)


def test_rows_step_as_one_row_each(boom, bucket):
    """ddh_step_rows is ddh_step row by row, to the bit."""
    rows = [RowSpec(boom), RowSpec(bucket, 1040.0), RowSpec(boom, 0.0, air_fraction=0.01)]
    lib = library()
    p = (Params * 3)(*(params(r) for r in rows))
    s, i, c = (State * 3)(), (Input * 3)(), Counters()
    singles = []
    for k, r in enumerate(rows):
        one = _Row(r)
        one.start(0.1 + 0.1 * k, 1000.0 * (k - 1), 30e5, 2e5)
        s[k], i[k] = one.s, one.i
        for _ in range(50):
            one.step(25.0 - 10.0 * k)
        singles.append((one.s.x_m, one.s.v_m_s, one.s.dp_a_pa, one.s.dp_b_pa, one.s.n_rpm))
    for k in range(3):
        i[k].torque_nm = 25.0 - 10.0 * k
    for _ in range(50):
        assert lib.ddh_step_rows(3, p, s, i, H, ctypes.byref(c)) == 0
    assert [(r.x_m, r.v_m_s, r.dp_a_pa, r.dp_b_pa, r.n_rpm) for r in s] == singles
    assert np.all(np.isfinite(singles))


def test_a_chamber_with_air_near_vacuum_fills_alike_at_any_step(bucket):
    """The rod pressed on its bottom stop by the drive, its piston side sucked to vacuum
    through the anti-cavitation valve with 0.6 % entrained air, then the motor reversed: the
    pumps fill the piston side's air before the rod moves. In steps of 2 ms (the filter's)
    the air's compression must be what it is in steps of 0.25 ms: without splitting the steps
    the secant iteration does not settle and the 2 ms row pressurised the side at once (63
    bar and the rod 1 mm up where the fine row stood at vacuum)."""
    ends = {}
    for h in (2e-3, 2.5e-4):
        r = _Row(RowSpec(bucket, 0.0, air_fraction=0.006))
        r.start(0.0, -440.0, -1.09e5, 177e5)
        r.i.speed_controlled = 1
        trace = []
        steps = round(0.2 / h)
        for k in range(steps):
            r.i.speed_rpm = -440.0 + 5000.0 * (k + 1) / steps
            assert r.step(0.0, h) == 1
            if (k + 1) % round(0.02 / h) == 0:
                trace.append((r.s.x_m, r.s.dp_a_pa))
        ends[h] = np.array(trace)
    coarse, fine = ends[2e-3], ends[2.5e-4]
    assert np.all(fine[:-2, 0] == 0.0)            # the rod stands while the air fills
    assert np.abs(coarse[:, 0] - fine[:, 0]).max() < 0.3e-3    # Euler's O(h) once moving
    assert np.abs(coarse[:, 1] - fine[:, 1]).max() < 1e5
