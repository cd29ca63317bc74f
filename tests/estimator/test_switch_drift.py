"""A switch's travel between its edges against its configured window and hysteresis: which
pairs measure which span, which are not taken, how far one pair moves the verdict, the record
a restart keeps; and on a simulated machine whose switches are not what the configuration
says (and one whose are)."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest

from ddh_vsensor.config import Config
from ddh_vsensor.estimator.estimator import Estimator, ReferenceEvent
from ddh_vsensor.estimator.references import Switch
from ddh_vsensor.estimator.switch_drift import (HYSTERESIS, MIN_PAIRS, THROUGH, WEIGHT,
                                                SwitchDrift)
from ddh_vsensor.measured import Run
from ddh_vsensor.sim.cycles import Profile, Trajectory, move_time, work_unit
from ddh_vsensor.sim.effects import STRUCTURE_TYPICAL
from ddh_vsensor.sim.run import RunSpec, simulate_with_truth
from ddh_vsensor.sim.sensors import hall_edge_times, hall_switch

W_MM, H_MM = 3.0, 0.5               # the reference loader's window and hysteresis
MID = Switch("mid", 155.0, W_MM, H_MM)
TOP = Switch("top", 311.15, W_MM, H_MM)


def _tracker(tolerance_mm: float = 1.0) -> SwitchDrift:
    return SwitchDrift((MID, TOP), tolerance_mm, per_travel=0.01, hold_mm_per_s=0.01)


def _edge(sw: Switch, rising: bool, up: bool, error_mm: float = 0.0, gain: float = 1.0,
          speed_mm_s: float = 50.0, path_mm: float = 7.0, held_s: float = 0.0
          ) -> ReferenceEvent:
    v = speed_mm_s if up else -speed_mm_s
    return ReferenceEvent(0, 0, sw.name, rising, sw.switching_position_mm(rising, up),
                          error_mm, False, gain, v, v, path_mm, held_s)


def _pair(drift: SwitchDrift, first: ReferenceEvent, second: ReferenceEvent,
          dt_s: float = 0.2) -> None:
    drift.interrupt()
    drift.edges([first], 0.0)
    drift.edges([second], dt_s)


@pytest.mark.parametrize("kinds, span", [
    (((True, True), (False, True)), THROUGH),           # on from below, off above
    (((True, False), (False, False)), THROUGH),         # on from above, off below
    (((True, True), (False, False)), HYSTERESIS),       # on from below, turned, off below
    (((True, False), (False, True)), HYSTERESIS),
    (((False, True), (True, False)), HYSTERESIS),       # off above, turned, on again
    (((False, False), (True, True)), HYSTERESIS)])
def test_each_pairing_measures_its_span_longer_as_positive(kinds, span) -> None:
    """The second edge 0.4 mm further along its travel than configured: the span reads
    0.4 mm longer, whichever way the rod went; the first edge's error, as far as it was
    corrected, does not count."""
    (r1, up1), (r2, up2) = kinds
    drift = _tracker()
    along = 0.4 if up2 else -0.4
    _pair(drift, _edge(MID, r1, up1, error_mm=-2.0, gain=0.1),
          _edge(MID, r2, up2, error_mm=-0.9 * 2.0 + along))
    stats = drift.switches["mid"].spans
    other = HYSTERESIS if span == THROUGH else THROUGH
    assert stats[span].pairs == 1 and stats[other].pairs == 0
    assert stats[span].last_mm == pytest.approx(0.4)


def test_pairs_that_do_not_measure_the_switch_are_not_taken() -> None:
    drift = _tracker()
    cases = {
        "an edge missed": (_edge(MID, False, True), _edge(MID, True, True)),
        "direction not told": (_edge(MID, True, True, speed_mm_s=5.0), _edge(MID, False, True)),
        "too long": (_edge(MID, True, True), _edge(MID, False, False, path_mm=30.0)),
    }
    for why, (a, b) in cases.items():
        _pair(drift, a, b)
        assert drift.ignored.get(why) == 1, why
    # the velocity at the edge and over the debounce time disagree: the rod turned there
    turned = dataclasses.replace(_edge(MID, False, True), velocity_mm_s=-20.0)
    _pair(drift, _edge(MID, True, True), turned)
    assert drift.ignored["direction not told"] == 2
    _pair(drift, _edge(MID, True, True), _edge(MID, False, True, held_s=30.0))
    _pair(drift, _edge(MID, True, True), _edge(MID, False, True), dt_s=61.0)
    assert drift.ignored["too long"] == 3
    _pair(drift, _edge(MID, True, True), _edge(TOP, False, True))
    assert drift.ignored["another switch between"] == 1
    drift.edges([_edge(MID, True, True)], 0.0)
    drift.interrupt()                                     # a gap, a preset, a soft limit
    drift.edges([_edge(MID, False, True)], 0.1)
    assert all(st.pairs == 0 for s in drift.switches.values() for st in s.spans.values())


def test_a_misread_pair_moves_the_mean_by_a_tenth_of_the_tolerance_at_most() -> None:
    """An edge misread at a reversal puts the span off by twice the window: one such pair
    among good ones cannot raise a drift, and a real departure of twice the tolerance is
    reported after a handful of pairs (the delay the docstring states, plus the clip's)."""
    drift = _tracker()
    for _ in range(20):
        _pair(drift, _edge(MID, True, True), _edge(MID, False, True, error_mm=0.05))
    before = drift.switches["mid"].spans[THROUGH].departure_mm
    _pair(drift, _edge(MID, True, True), _edge(MID, False, True, error_mm=2 * W_MM + 2 * H_MM))
    after = drift.switches["mid"].spans[THROUGH].departure_mm
    assert abs(after - before) <= WEIGHT * 1.0 + 1e-12
    assert drift.drifted == []
    fresh = _tracker()
    changes = []
    for n in range(1, 30):
        pair_changes = []
        fresh.interrupt()
        fresh.edges([_edge(MID, True, True)], 0.0)
        pair_changes += fresh.edges([_edge(MID, False, True, error_mm=2.0)], 0.2)
        if pair_changes:
            changes.append((n, pair_changes))
    assert [c.drifted for _, cs in changes for c in cs] == [True]
    first = changes[0][0]
    assert MIN_PAIRS <= first <= 10
    assert fresh.switches["mid"].spans[THROUGH].measured_mm == pytest.approx(2.0, abs=0.05)
    assert "passing through" in changes[0][1][0].text


def test_the_verdict_clears_only_well_within_the_tolerance() -> None:
    drift = _tracker()
    for _ in range(30):
        _pair(drift, _edge(MID, True, True), _edge(MID, False, True, error_mm=2.0))
    assert drift.drifted == ["mid"]
    cleared_at = None
    for n in range(1, 40):
        drift.interrupt()
        drift.edges([_edge(MID, True, True)], 0.0)
        if drift.edges([_edge(MID, False, True, error_mm=0.0)], 0.2):
            cleared_at = n
            break
    mean = drift.switches["mid"].spans[THROUGH].departure_mm
    assert cleared_at is not None and drift.drifted == [] and mean <= 0.5


def test_the_record_round_trips_and_a_changed_geometry_starts_afresh() -> None:
    drift = _tracker()
    for _ in range(30):
        _pair(drift, _edge(MID, True, True), _edge(MID, False, True, error_mm=2.0))
        _pair(drift, _edge(TOP, False, True), _edge(TOP, True, False, error_mm=-0.02))
    record = drift.record()
    again = _tracker()
    assert sorted(again.restore(record)) == ["mid", "top"]
    assert again.drifted == ["mid"]
    assert again.record() == record
    recommissioned = SwitchDrift((dataclasses.replace(MID, window_mm=2.0), TOP), 1.0, 0.01, 0.01)
    assert recommissioned.restore(record) == ["top"]
    assert recommissioned.drifted == []
    for bad in ({"format": "other"}, {**record, "switches": []},
                {**record, "switches": {"mid": {**record["switches"]["mid"], "drifted": 1}}},
                {**record, "switches": {"mid": {**record["switches"]["mid"],
                                                "window_mm": math.inf}}}):
        with pytest.raises(ValueError):
            _tracker().restore(bad)


def test_online_steps_hand_out_the_edges_the_offline_run_takes(cfg, boom, unit_tables,
                                                               make_run) -> None:
    """``Step.events`` online and ``RunEstimate.events`` offline measure the same spans."""
    run = make_run(boom, seconds=60, unit_cfg=cfg.unit("boom"), x0=150.0, period_s=6.0,
                   amplitude_rpm=1500.0)
    est = Estimator(cfg, "boom", unit_tables["boom"], initial_position_mm=150.0)
    res = est.run(run.time_s, run.speed_rpm, run.torque_nm, run.oil_temp_c, run.refs)
    offline = SwitchDrift.from_config(cfg, "boom")
    offline.feed(res, run.time_s)
    online = SwitchDrift.from_config(cfg, "boom")
    est = Estimator(cfg, "boom", unit_tables["boom"], initial_position_mm=150.0)
    for k, t in enumerate(run.time_s):
        step = est.step(t, run.speed_rpm[k], float(run.torque_nm[k]), run.oil_temp_c[k],
                        {n: bool(a[k]) for n, a in run.refs.items()})
        online.edges(step.events, t)
    assert len(res.events) >= 8
    assert online.record() == offline.record()
    assert sum(st.pairs for s in online.switches.values() for st in s.spans.values()) >= 4


# --- a simulated machine ---------------------------------------------------------------------

SIM_S = 240.0                       # 4 min of work around the switches: ~200 pairs per unit


def _around_switches(cfg: Config, seed: int, duration_s: float) -> Profile:
    """Work around each switch in turn, 30 moves each: random targets within the window
    plus 5 mm on either side (one in ten at an end switch pressed into the stop), at 20 to
    100 % of travel speed, short holds; the moves cross, turn inside and turn just beyond."""
    rng = np.random.default_rng(seed)
    trajectories = {}
    for a in cfg.unit_names:
        u = cfg.unit(a)
        reach = u.reference_window_mm + u.reference_hysteresis_mm + 5.0
        v_top = work_unit(cfg, a).travel_speed_mm_s
        switches = list(u.references_mm.values())
        t, x, n = 0.0, switches[0], 0
        knots = [(0.0, x)]
        while True:
            p = switches[(n // 30) % len(switches)]
            n += 1
            target = p + rng.uniform(-reach, reach)
            if not 0.0 < target < u.stroke_mm:
                pressed = rng.random() < 0.1
                target = -2.0 if target <= 0.0 else u.stroke_mm + 2.0
                if not pressed:
                    target = float(np.clip(target, 0.5, u.stroke_mm - 0.5))
            hold = rng.uniform(0.0, 0.3)
            move = move_time(target - x, rng.uniform(0.2, 1.0) * v_top)
            if t + hold + move + 0.5 > duration_s:
                break
            t += hold
            knots.append((t, x))
            t += move
            knots.append((t, target))
            x = target
        knots.append((duration_s, x))
        trajectories[a] = Trajectory(np.array([k[0] for k in knots]),
                                     np.array([k[1] for k in knots]))
    return Profile(f"around the switches {seed}", trajectories, duration_s)


def switched(run: Run, x_mm: np.ndarray, geometry: dict[str, tuple[float, float, float]]
             ) -> Run:
    """``run`` with its Hall switches as switches of this true geometry (name -> position,
    window, hysteresis) would have switched on the true path ``x_mm``."""
    refs = {name: hall_switch(x_mm, p, w, h) for name, (p, w, h) in geometry.items()}
    edges = {name: hall_edge_times(run.time_s, x_mm, refs[name], p, w, h)
             for name, (p, w, h) in geometry.items()}
    return dataclasses.replace(run, refs=refs, ref_edge_s=edges)


def geometry(cfg: Config, actuator: str, **true: tuple[float, float]
             ) -> dict[str, tuple[float, float, float]]:
    """The configured geometry of ``actuator``'s switches, some with a true (w, h)."""
    u = cfg.unit(actuator)
    return {name: (p, *true.get(name, (u.reference_window_mm, u.reference_hysteresis_mm)))
            for name, p in u.references_mm.items()}


@pytest.fixture(scope="module")
def machine(cfg):
    """One simulated run of both units with the structure the estimator's model lacks at its
    typical values (the noise a real machine's pairs carry): {unit: (Run, true x in mm)}."""
    spec = RunSpec(cycle=_around_switches(cfg, 3, SIM_S), seed=3,
                   effects=[f"{k}={v}" for k, v in STRUCTURE_TYPICAL.items()])
    runs = simulate_with_truth(cfg, [spec])[0]
    return {a: (run, truth.x_m * 1e3) for a, (run, truth) in runs.items()}


def _spans(cfg, unit_tables, actuator, run) -> tuple[SwitchDrift, list]:
    drift = SwitchDrift.from_config(cfg, actuator)
    res = Estimator(cfg, actuator, unit_tables[actuator]).run(run)
    return drift, drift.feed(res, run.time_s)


def test_switches_off_their_configuration_are_reported_and_only_they(cfg, unit_tables,
                                                                      machine) -> None:
    """The boom's middle switch with a 2 mm window where the configuration says 3 (its span
    through it 2 mm short), the bucket's with 2.5 mm of hysteresis where it says 0.5 (both
    its spans 2 mm long): each reported once, the other switches not."""
    true = {"boom": {"mid": (2.0, H_MM)}, "bucket": {"mid": (W_MM, 2.5)}}
    for actuator, (span, expected_mm) in {"boom": (THROUGH, -2.0),
                                          "bucket": (HYSTERESIS, 2.0)}.items():
        run, x_mm = machine[actuator]
        name = next(iter(true[actuator]))
        drift, changes = _spans(cfg, unit_tables, actuator,
                                switched(run, x_mm, geometry(cfg, actuator, **true[actuator])))
        assert [(c.switch, c.drifted) for c in changes] == [(name, True)], changes
        stats = drift.switches[name].spans[span]
        assert stats.measured_mm == pytest.approx(expected_mm, abs=0.3)
        assert stats.pairs >= 20


def test_switches_as_configured_raise_nothing_over_a_long_run(cfg, unit_tables,
                                                              machine) -> None:
    """The false-alarm check: every switch as configured, about 200 pairs per unit with the
    drives' unmodelled structure, no drift, and no mean beyond half the tolerance."""
    tol = cfg.estimator.reference_drift_mm
    pairs = 0
    for actuator, (run, x_mm) in machine.items():
        drift, changes = _spans(cfg, unit_tables, actuator,
                                switched(run, x_mm, geometry(cfg, actuator)))
        assert changes == []
        for s in drift.switches.values():
            for st in s.spans.values():
                pairs += st.pairs
                assert abs(st.departure_mm) < 0.5 * tol
    assert pairs >= 350
