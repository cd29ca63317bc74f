"""Work cycles other than the paper's: random smooth moves, as an independent check would use."""

import numpy as np
import pytest

from ddh_vsensor.estimator.accuracy import accuracy
from ddh_vsensor.estimator.estimator import Estimator
from ddh_vsensor.sim.cycles import Profile, Trajectory
from ddh_vsensor.sim.run import RunSpec, simulate_campaign

RANGES = {"boom": (5.0, 300.0, 80.0), "bucket": (60.0, 800.0, 170.0)}   # lo, hi, mm/s


def random_profile(seed: int, duration_s: float = 60.0) -> Profile:
    """Moves between random positions at random speeds, with random pauses."""
    rng = np.random.default_rng(seed)
    trajectories = {}
    for actuator, (lo, hi, v_max) in RANGES.items():
        t, x = 0.0, rng.uniform(lo, hi)
        knots = [(0.0, x)]
        while t < duration_s - 8.0:
            target = rng.uniform(lo, hi)
            t += rng.uniform(0.5, 4.0)
            knots.append((t, x))
            t += abs(target - x) / (rng.uniform(0.2, 1.0) * v_max) * 1.3 + 0.3
            knots.append((t, target))
            x = target
        knots.append((duration_s, x))
        trajectories[actuator] = Trajectory(np.array([k[0] for k in knots]),
                                            np.array([k[1] for k in knots]), smooth=True)
    return Profile(f"random {seed}", trajectories, duration_s)


@pytest.fixture(scope="module")
def other_runs(cfg):
    specs = [RunSpec(cycle=random_profile(seed), payload_kg=payload, oil_temp_c=temp)
             for seed, payload, temp in ((10, 0.0, 27.0), (11, 1040.0, 27.0), (12, 500.0, 50.0),
                                         (13, 0.0, 70.0))]
    return list(zip(specs, simulate_campaign(cfg, specs)))


@pytest.mark.parametrize("actuator", ["boom", "bucket"])
def test_other_cycles_within_3_mm_without_references(cfg, unit_tables, other_runs, actuator):
    for spec, runs in other_runs:
        run = runs[actuator]
        est = Estimator(cfg, actuator, unit_tables[actuator], references=False,
                        initial_position_mm=float(run.position_mm[0]))
        res = est.run(run.time_s, run.speed_rpm, run.torque_nm, run.oil_temp_c)
        acc = accuracy(res.position_mm, run.position_mm)
        assert acc.max_abs_error_mm <= 3.0, (spec.cycle.name, spec.oil_temp_c, acc)


# On random work cycles the worst error was 26.6 mm without the compensation, <= 3 mm
# with it from 27 degC up. Measured here (boom, these four cycles): 32.6 mm without, 0.32 mm
# with. Margins: without it must still be >= 20 mm (26.6 mm measured less 25 %), with it
# within 3 mm.
WITHOUT_COMPENSATION_MIN_MM = 20.0
WITH_COMPENSATION_MAX_MM = 3.0


def test_inertia_compensation_matters_on_sharp_moves(cfg, unit_tables, other_runs):
    """Without subtracting J dw/dt the PID's torque spikes read as load (`full`, the mode the
    figures are for)."""
    import dataclasses
    off = dataclasses.replace(cfg, estimator=dataclasses.replace(cfg.estimator,
                                                                 inertia_compensation=False))
    worst = {True: 0.0, False: 0.0}
    for _, runs in other_runs:
        run = runs["boom"]
        for comp, c in ((True, cfg), (False, off)):
            est = Estimator(c, "boom", unit_tables["boom"], mode="full", references=False,
                            initial_position_mm=float(run.position_mm[0]))
            res = est.run(run.time_s, run.speed_rpm, run.torque_nm, run.oil_temp_c)
            worst[comp] = max(worst[comp], accuracy(res.position_mm, run.position_mm)
                              .max_abs_error_mm)
    assert worst[True] <= WITH_COMPENSATION_MAX_MM, worst
    assert worst[False] >= WITHOUT_COMPENSATION_MIN_MM, worst
