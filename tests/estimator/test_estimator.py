"""The estimator on synthetic runs whose truth is the exact steady state (hence `full` mode:
the tables are that steady state; `dynamic` is tested on simulated runs)."""

import dataclasses

import numpy as np
import pytest

from ddh_vsensor.estimator.bounded import bounded_cumsum
from ddh_vsensor.estimator.estimator import Estimator
from ddh_vsensor.estimator.flags import Flags
from ddh_vsensor.estimator.state import EstimatorState
from ddh_vsensor.physics.steady import holding_speed, steady_state


def _online(est, run, refs=True):
    out = []
    for k in range(len(run.time_s)):
        r = {n: bool(a[k]) for n, a in run.refs.items()} if refs else None
        out.append(est.step(run.time_s[k], run.speed_rpm[k], float(run.torque_nm[k]),
                            run.oil_temp_c[k], r))
    return out


@pytest.mark.parametrize("mode", ["full", "paper", "dynamic"])
def test_online_and_offline_faces_agree(cfg, boom, unit_tables, make_run, mode):
    run = make_run(boom, seconds=40, leakage=2.0, unit_cfg=cfg.unit("boom"))
    run.time_s[1500] = run.time_s[1499]                    # a repeated timestamp
    run.time_s[2000:] += 0.2                               # and a gap
    off = Estimator(cfg, "boom", unit_tables["boom"], mode=mode, initial_position_mm=22.0)
    res = off.run(run.time_s, run.speed_rpm, run.torque_nm, run.oil_temp_c, run.refs)
    on = Estimator(cfg, "boom", unit_tables["boom"], mode=mode, initial_position_mm=22.0)
    steps = _online(on, run)
    assert len(res.events) >= 4
    assert np.max(np.abs(np.array([s.position_mm for s in steps]) - res.position_mm)) < 1e-6
    assert np.max(np.abs(np.array([s.uncertainty_mm for s in steps]) - res.uncertainty_mm)) < 1e-6
    assert [s.flags for s in steps] == res.flags.tolist()
    assert res.flags[2000] & Flags.STALE_INPUT and not res.flags[1999] & Flags.STALE_INPUT
    assert np.allclose(on.gain.gain, off.gain.gain)


@pytest.mark.parametrize("mode", ["full", "dynamic"])
def test_the_faces_agree_with_the_torque_carried_to_the_speeds_instants(
        cfg, boom, unit_tables, make_run, mode):
    """``motor.torque_lag_s``: each torque sample moved along its last change, in both faces
    alike (a gap's first sample has no last change)."""
    lagging = dataclasses.replace(cfg, units={name: dataclasses.replace(
        u, motor=dataclasses.replace(u.motor, torque_lag_s=0.002))
        for name, u in cfg.units.items()})
    run = make_run(boom, seconds=20, unit_cfg=cfg.unit("boom"))
    run.time_s[1000:] += 0.2
    estimates = []
    for c in (cfg, lagging):
        off = Estimator(c, "boom", unit_tables["boom"], mode=mode, references=False,
                        initial_position_mm=22.0)
        res = off.run(run.time_s, run.speed_rpm, run.torque_nm, run.oil_temp_c)
        on = Estimator(c, "boom", unit_tables["boom"], mode=mode, references=False,
                       initial_position_mm=22.0)
        steps = _online(on, run, refs=False)
        assert np.max(np.abs(np.array([s.velocity_mm_s for s in steps]) - res.velocity_mm_s)
                      ) < 1e-6
        estimates.append(res.velocity_mm_s)
    assert np.max(np.abs(estimates[1] - estimates[0])) > 0.01


@pytest.mark.parametrize("gain,offset,speed_offset", [(1.0, 1.5, 2.0), (1.05, 0.0, 0.0),
                                                       (1.05, 1.5, 2.0)])
@pytest.mark.parametrize("mode", ["full", "dynamic"])
def test_the_faces_agree_on_the_shaft_torque_from_the_drives_reading(
        cfg, boom, unit_tables, make_run, mode, gain, offset, speed_offset):
    """The drive's gain, offset, speed offset and filter (``motor.torque_gain``,
    ``torque_offset_nm``, ``torque_speed_offset_nm``, ``torque_filter_s``): a reading made by
    them, taken back through them, gives the estimate of the shaft's torque read as it is, in
    both faces (a gain alone too)."""
    motor = cfg.unit("boom").motor
    drive = dataclasses.replace(cfg, units={name: dataclasses.replace(
        u, motor=dataclasses.replace(u.motor, torque_gain=gain, torque_offset_nm=offset,
                                     torque_speed_offset_nm=speed_offset, torque_filter_s=0.0))
        for name, u in cfg.units.items()})
    run = make_run(boom, seconds=20, unit_cfg=cfg.unit("boom"))
    read = gain * run.torque_nm + offset + speed_offset * run.speed_rpm / motor.speed_limit_rpm
    base = Estimator(cfg, "boom", unit_tables["boom"], mode=mode, references=False,
                     initial_position_mm=22.0).run(run.time_s, run.speed_rpm, run.torque_nm,
                                                   run.oil_temp_c)
    off = Estimator(drive, "boom", unit_tables["boom"], mode=mode, references=False,
                    initial_position_mm=22.0).run(run.time_s, run.speed_rpm, read,
                                                  run.oil_temp_c)
    on = Estimator(drive, "boom", unit_tables["boom"], mode=mode, references=False,
                   initial_position_mm=22.0)
    steps = _online(on, dataclasses.replace(run, torque_nm=read), refs=False)
    assert np.max(np.abs(off.velocity_mm_s - base.velocity_mm_s)) < 1e-6
    assert np.max(np.abs(np.array([s.velocity_mm_s for s in steps]) - off.velocity_mm_s)) < 1e-6


def test_full_mode_tracks_the_truth_without_references(cfg, boom, unit_tables, make_run):
    run = make_run(boom, seconds=60, )
    est = Estimator(cfg, "boom", unit_tables["boom"], mode="full", references=False,
                    initial_position_mm=run.position_mm[0])
    res = est.run(run.time_s, run.speed_rpm, run.torque_nm, run.oil_temp_c)
    assert np.max(np.abs(res.position_mm - run.position_mm)) < 0.5


def test_standstill_at_the_holding_speed_in_full_mode(cfg, boom, unit_tables):
    f = boom.load_force_n(0)
    h = holding_speed(boom, f, 27.0)
    torque = float(steady_state(boom, h.speed_rpm, f, 27.0).torque_nm)
    t = np.arange(0, 60, 0.01)
    for mode, bound in (("full", 0.5), ("paper", None)):
        est = Estimator(cfg, "boom", unit_tables["boom"], mode=mode, references=False,
                        initial_position_mm=290.0)
        res = est.run(t, np.full_like(t, h.speed_rpm), np.full_like(t, torque),
                      np.full_like(t, 27.0))
        creep = res.position_mm[-1] - 290.0
        if bound is not None:
            assert abs(creep) < bound                     # full: the held boom stands still
        else:
            assert creep > 5.0                            # paper: creeps up, as published


def test_resync_corrects_a_planted_offset(cfg, boom, unit_tables, make_run):
    """A start 12 mm off at a claimed +-0.5 mm: the first edge disagrees beyond both tolerances,
    so the position is corrected, flagged and widened to cover the error (which of the model and
    that switch was wrong its own edges cannot tell); another switch's edge agrees and the flag
    clears."""
    run = make_run(boom, seconds=60, x0=6.0, unit_cfg=cfg.unit("boom"))
    est = Estimator(cfg, "boom", unit_tables["boom"], mode="full", adaptation=False,
                    initial_position_mm=run.position_mm[0] + 12.0)
    res = est.run(run.time_s, run.speed_rpm, run.torque_nm, run.oil_temp_c, run.refs)
    first = res.events[0]
    other = next(e for e in res.events if e.switch != first.switch)
    assert first.error_mm == pytest.approx(12.0, abs=0.5)
    after = slice(first.index + 1, None)
    assert np.max(np.abs(res.position_mm[after] - run.position_mm[after])) < 1.0
    u_ref = cfg.estimator.uncertainty_reference_mm        # plus the edge's sample travel
    tol = cfg.unit("boom").reference_tolerance_mm         # and the switch's mounting tolerance
    sample_mm = np.max(np.abs(res.velocity_mm_s)) * np.max(np.diff(run.time_s))
    assert np.all(res.uncertainty_mm[first.index:other.index] >= abs(first.error_mm) + u_ref + tol)
    assert np.all(res.flags[first.index:other.index] & Flags.NOT_REFERENCED)
    assert abs(other.error_mm) < 1.0
    assert u_ref + tol <= res.uncertainty_mm[other.index] <= u_ref + tol + sample_mm
    assert not res.flags[other.index] & Flags.NOT_REFERENCED


@pytest.mark.parametrize("offset_mm", [2.0, -2.5, 6.0, -9.0])
def test_a_switch_off_its_configured_position_is_never_trusted_beyond_its_tolerance(
        cfg, boom, unit_tables, make_run, offset_mm):
    """The middle switch switches ``offset_mm`` from where the configuration says (the data's
    switch at the configured position, the configuration's shifted): within the mounting
    tolerance the uncertainty covers the offset; beyond it its edges disagree with the estimate
    and flag, until another switch agrees. No published position errs beyond its uncertainty
    without a flag."""
    unit = cfg.unit("boom")
    run = make_run(boom, seconds=60, unit_cfg=unit)
    shifted = dataclasses.replace(unit, references_mm={
        **unit.references_mm, "mid": unit.references_mm["mid"] + offset_mm})
    cfg_off = dataclasses.replace(cfg, units={**cfg.units, "boom": shifted})
    est = Estimator(cfg_off, "boom", unit_tables["boom"], mode="full", adaptation=False,
                    initial_position_mm=run.position_mm[0])
    res = est.run(run.time_s, run.speed_rpm, run.torque_nm, run.oil_temp_c, run.refs)
    assert len(res.events) >= 4
    error = np.abs(res.position_mm - run.position_mm)
    unflagged = (res.flags & Flags.NOT_REFERENCED) == 0
    assert not np.any(unflagged & (error > res.uncertainty_mm))
    flagged_edges = [e for e in res.events if res.flags[e.index] & Flags.NOT_REFERENCED]
    if abs(offset_mm) <= unit.reference_tolerance_mm:
        assert not flagged_edges
    else:
        assert flagged_edges


def _cycle_errors(cfg, boom, unit_tables, make_run, adaptation, leakage, seed=1):
    run = make_run(boom, seconds=240, leakage=leakage, unit_cfg=cfg.unit("boom"),
                   seed=seed)
    est = Estimator(cfg, "boom", unit_tables["boom"], mode="full", adaptation=adaptation,
                    initial_position_mm=run.position_mm[0])
    res = est.run(run.time_s, run.speed_rpm, run.torque_nm, run.oil_temp_c, run.refs)
    return [abs(e.error_mm) for e in res.events if e.switch == "mid"], est


def test_adaptation_converges_on_a_planted_leakage_error(cfg, boom, unit_tables, make_run):
    errs, est = _cycle_errors(cfg, boom, unit_tables, make_run, True, leakage=4.0)
    fixed, _ = _cycle_errors(cfg, boom, unit_tables, make_run, False, leakage=4.0)
    assert np.mean(fixed[-6:]) > 0.3                      # the planted error shows
    assert np.mean(errs[-6:]) < 0.5 * np.mean(fixed[-6:])  # and learning removes most of it
    assert np.all(np.abs(est.gain.gain - 1) <= cfg.estimator.adaptation_bound)


def test_adaptation_stays_bounded_on_noise(cfg, boom, unit_tables, make_run):
    rng = np.random.default_rng(4)
    run = make_run(boom, seconds=240, unit_cfg=cfg.unit("boom"))
    noisy_torque = run.torque_nm + rng.normal(0, 2.0, len(run.torque_nm))
    est = Estimator(cfg, "boom", unit_tables["boom"], mode="full",
                    initial_position_mm=run.position_mm[0])
    res = est.run(run.time_s, run.speed_rpm, noisy_torque, run.oil_temp_c, run.refs)
    assert np.all(np.abs(est.gain.gain - 1) < 0.02)
    assert np.max(np.abs(res.position_mm - run.position_mm)) < 3.0


def test_soft_limits_act_and_are_flagged(cfg, boom, unit_tables):
    t = np.arange(0, 10, 0.01)
    est = Estimator(cfg, "boom", unit_tables["boom"], mode="full", references=False,
                    initial_position_mm=300.0)
    res = est.run(t, np.full_like(t, 3000.0), np.full_like(t, 22.0), np.full_like(t, 27.0))
    assert res.position_mm.max() == pytest.approx(cfg.unit("boom").stroke_mm)
    assert res.flags[-1] & Flags.AT_SOFT_LIMIT and not res.flags[0] & Flags.AT_SOFT_LIMIT


def test_bounded_cumsum_equals_the_clipped_loop():
    rng = np.random.default_rng(0)
    for _ in range(100):
        dx = rng.normal(0.3 * rng.normal(), 1.0, 3000)
        x0 = rng.uniform(0, 100)
        x, _ = bounded_cumsum(x0, dx, 0.0, 100.0)
        ref, p = [], x0
        for d in dx:
            p = min(max(p + d, 0.0), 100.0)
            ref.append(p)
        assert np.max(np.abs(np.array(ref) - x)) < 1e-9


def test_restored_estimate_is_flagged_until_a_reference(cfg, boom, unit_tables, make_run):
    run = make_run(boom, seconds=30, unit_cfg=cfg.unit("boom"))
    first = Estimator(cfg, "boom", unit_tables["boom"], mode="full",
                      initial_position_mm=run.position_mm[0])
    half = len(run.time_s) // 3
    for k in range(half):
        first.step(run.time_s[k], run.speed_rpm[k], float(run.torque_nm[k]), 27.0)
    second = Estimator(cfg, "boom", unit_tables["boom"])
    second.restore(first.snapshot())
    assert second.position_mm == pytest.approx(first.position_mm)
    flags = []
    for k in range(half, len(run.time_s)):
        refs = {n: bool(a[k]) for n, a in run.refs.items()}
        flags.append(second.step(run.time_s[k], run.speed_rpm[k], float(run.torque_nm[k]),
                                 27.0, refs).flags)
    assert flags[0] & Flags.NOT_REFERENCED and not flags[-1] & Flags.NOT_REFERENCED


def test_a_cold_start_does_not_learn_from_its_first_reference(cfg, boom, unit_tables, make_run):
    """No state, no preset: the first edge corrects hundreds of mm of unknown offset, which
    says nothing about the model's travel gain; the next edges (referenced) may adapt."""
    run = make_run(boom, seconds=60, leakage=1.3, unit_cfg=cfg.unit("boom"))
    stroke = cfg.unit("boom").stroke_mm
    cold = Estimator(cfg, "boom", unit_tables["boom"])
    cold.restore(EstimatorState("boom", cfg.physics_hash(), 0.0, stroke))
    res = cold.run(run.time_s, run.speed_rpm, run.torque_nm, run.oil_temp_c, run.refs)
    assert len(res.events) >= 3
    assert abs(res.events[0].error_mm) > 20.0 and not res.events[0].adapted
    assert any(e.adapted for e in res.events[1:])
    assert np.all(np.abs(cold.gain.gain - 1.0) < cold.gain.bound)


def test_step_carries_the_reference_taken_in_it(cfg, boom, unit_tables, make_run):
    """Each step names the switch whose edge it took, and how much of the error it
    corrected: exactly the offline run's events, nothing in any other step. Started 20 mm
    off, the first edge is taken whole; later ones, met at speed with a transient-sized
    error, partly."""
    run = make_run(boom, seconds=40, leakage=1.02, unit_cfg=cfg.unit("boom"))
    start_mm = run.position_mm[0] + 20.0
    off = Estimator(cfg, "boom", unit_tables["boom"], initial_position_mm=start_mm)
    res = off.run(run.time_s, run.speed_rpm, run.torque_nm, run.oil_temp_c, run.refs)
    on = Estimator(cfg, "boom", unit_tables["boom"], initial_position_mm=start_mm)
    steps = _online(on, run)
    taken = {k: (s.reference, s.reference_gain) for k, s in enumerate(steps)
             if s.reference is not None}
    assert len(res.events) >= 4
    assert taken == {e.index: (e.switch, e.gain) for e in res.events}
    gains = {g for _, g in taken.values()}
    assert 1.0 in gains and cfg.estimator.resync_gain_moving in gains
    assert all(s.reference_gain == 0.0 for s in steps if s.reference is None)


def test_the_direction_of_crossing_is_the_travel_after_the_edge(cfg, unit_tables):
    """An edge sample whose own velocity points the wrong way (torque chatter): the switch's
    edge position follows the travel from the edge to its acceptance."""
    from ddh_vsensor.estimator.estimator import _Snapshot
    est = Estimator(cfg, "boom", unit_tables["boom"], mode="full")
    mid = next(sw for sw in est.switches if sw.name == "mid")
    snap = _Snapshot(index=10, x=158.0, dx=0.01, v=+18.0, s_up=5.0, s_down=-3.0)
    x, event = est._reference(mid, True, snap, 157.86, (5.0, -3.14), 12)   # 0.14 mm down
    assert event.switch_position_mm == pytest.approx(mid.switching_position_mm(True, False))
