"""The `dynamic` mode's chamber model: one step in C and Python, settled = the tables, end stops,
bounded under a wrong pump parameter."""

import numpy as np
import pytest

from ddh_vsensor.estimator.dynamic import DynamicModel
from ddh_vsensor.estimator.estimator import Estimator
from ddh_vsensor.physics.steady import holding_speed, steady_state


def _drive(model, run):
    return np.array([model.step(run.time_s[k] - run.time_s[k - 1] if k else 0.0,
                                run.speed_rpm[k], run.torque_nm[k], run.oil_temp_c[k])
                     for k in range(len(run.time_s))])


def test_compiled_and_python_steps_are_the_same_arithmetic(boom, make_run):
    run = make_run(boom, seconds=20, temp_c=-10.0, leakage=1.5)
    run.torque_nm[700:760] += 40.0                         # a torque burst: valves open
    compiled = DynamicModel(boom, 40.0, max_gap_s=0.05)
    if not compiled.compiled:
        pytest.skip("no C compiler: only the Python step exists")
    python = DynamicModel(boom, 40.0, max_gap_s=0.05, use_compiled=False)
    offline = DynamicModel(boom, 40.0, max_gap_s=0.05).run(run.time_s, run.speed_rpm,
                                                            run.torque_nm, run.oil_temp_c)
    v_c, v_py = _drive(compiled, run), _drive(python, run)
    assert np.max(np.abs(v_c - v_py)) < 1e-9
    assert np.max(np.abs(v_c - offline)) < 1e-9
    assert np.allclose(compiled.state, python.state, rtol=1e-12, atol=1e-6)


@pytest.mark.parametrize("temp_c", [-10.0, 27.0, 80.0])
def test_held_inputs_settle_to_the_steady_state(boom, temp_c):
    """With speed and torque held the pressures settle where the tables' steady state is."""
    force = boom.load_force_n(500.0)
    st = steady_state(boom, 1500.0, force, temp_c)
    model = DynamicModel(boom, 150.0)
    model.step(0.0, 0.0, float(st.torque_nm), temp_c)      # starts elsewhere: n = 0
    for _ in range(30000):                                 # 300 s at 100 Hz: cold oil is slow
        v = model.step(0.01, 1500.0, float(st.torque_nm), temp_c)
        model.set_position(150.0)                          # an endless stroke
    assert v == pytest.approx(float(st.velocity_m_s) * 1e3, rel=1e-4)
    p_a, p_b = model.pressures_bar
    assert p_a == pytest.approx(float(st.p_a_pa - boom.reservoir_pa) * 1e-5, abs=0.01)
    assert p_b == pytest.approx(float(st.p_b_pa - boom.reservoir_pa) * 1e-5, abs=0.01)


def test_a_rod_pressed_into_its_end_stop_does_not_travel(cfg, unit_tables):
    """Motor at speed into the top stop, the pressure at the relief: no travel counted."""
    est = Estimator(cfg, "bucket", unit_tables["bucket"], mode="dynamic", references=False,
                    initial_position_mm=849.0)
    relief_torque = 48.0                                   # A side near its 70 bar relief
    t = np.arange(0.0, 10.0, 0.01)
    n = np.minimum(t * 4000.0, 3000.0)
    res = est.run(t, n, np.full_like(t, relief_torque), np.full_like(t, 27.0))
    assert res.position_mm[-1] == pytest.approx(850.0)
    held = res.position_mm >= 850.0
    assert held[-1] and np.all(res.velocity_mm_s[held][1:] == 0.0)


def test_a_wrong_pump_parameter_cannot_run_the_pressures_away(cfg, boom, unit_tables):
    """The model's pumps 3 % larger than the plant's, cold oil, 5 min of holding and moving:
    the valves and the leakage bound the pressures; the error stays the steady state's."""
    plant = boom.with_pumps(displacement=1.03)
    t = np.arange(0.0, 300.0, 0.01)
    force = boom.load_force_n(0.0)
    n = 1000.0 * np.sin(2 * np.pi * t / 10.0) + holding_speed(plant, force, -10.0).speed_rpm
    st = steady_state(plant, n, force, -10.0)
    model = DynamicModel(boom, 150.0, max_gap_s=0.05)
    v = model.run(t, n, st.torque_nm, np.full_like(t, -10.0))
    p_a, p_b = model.pressures_bar
    assert -1.0 < p_a < 270.0 * 1.1 and -1.0 < p_b < 70.0 * 1.1
    table = unit_tables["boom"].full.velocity_many(n, st.torque_nm, np.full_like(t, -10.0))[0]

    def travel(vel):
        return np.concatenate([[0.0], np.cumsum(0.5 * (vel[1:] + vel[:-1]) * np.diff(t))])

    apart = travel(v) - travel(table)                      # dynamic minus table position
    cycle_ends = apart[::1000]                             # every 10 s period, same phase
    assert np.max(np.abs(np.diff(cycle_ends[10:]))) < 0.05  # no growth once settled
    assert np.max(np.abs(apart)) < 10.0


def test_an_unreferenced_estimate_assumes_no_end_stop(cfg, unit_tables):
    """After a provisional preset near the top (the rod really anywhere): the chamber model
    must not stop a moving rod at a stroke end it only believes in. Referenced, the same
    inputs are held at the stop; unreferenced they keep reading travel."""
    t = np.arange(0.0, 3.0, 0.01)
    n = np.minimum(t * 4000.0, 3000.0)
    torque, temp = np.full_like(t, 20.0), np.full_like(t, 27.0)
    velocities = {}
    for referenced in (True, False):
        est = Estimator(cfg, "bucket", unit_tables["bucket"], mode="dynamic", references=False)
        est.preset(845.0, 0.5)
        est.referenced = referenced
        velocities[referenced] = np.array([est.step(tk, nk, qk, ck).velocity_mm_s
                                           for tk, nk, qk, ck in zip(t, n, torque, temp)])
    late = t > 1.5
    assert np.all(velocities[True][late] == 0.0)
    assert np.min(velocities[False][late]) > 50.0
