"""Every shipped machine: its configuration loads, its tables build, its work cycle simulates
and the estimator (full and dynamic mode) follows every unit, compared with the reference
loader's accuracy on the same test (reached, or the shortfall stated with its measured
figure)."""

from __future__ import annotations

import numpy as np
import pytest

from ddh_vsensor.config import Config, load_config
from ddh_vsensor.estimator.accuracy import accuracy
from ddh_vsensor.estimator.estimator import Estimator
from ddh_vsensor.sim.cycles import cycle_names, work_cycle
from ddh_vsensor.tables.build import build_unit_tables

from .conftest import MACHINES, REPO

# The reference loader on this same test (work cycle + random partial strokes, step 2 ms),
# measured: full mode 0.63 mm (boom, work cycle; bucket 0.54; random cycle 0.49 and 0.39 mm),
# dynamic mode 0.22 mm (bucket, work cycle 0.216; boom 0.14 and 0.15). Margin 20 % for noise.
LOADER_MAX_ERROR_MM = {"full": 0.63, "dynamic": 0.22}
MARGIN = 1.2
# Not reached (measured, same test). Full mode, where the error grows: a lightly loaded unit
# holds for seconds while another moves, its motor standing (speed 0, the torque inside the
# pumps' friction band); the true rod nearly stands (< 0.2 mm/s), the estimate drifts
# 0.1-0.4 mm/s (the tables' leakage at that torque). The loader's holds are heavily loaded:
# its motors creep at tens of rpm and the tables follow. Dynamic mode has no such drift; its
# units over the bound are the excavator's on the random cycle (boom 0.497, stick 0.292)
# and its bucket on the work cycle (0.414).
# Strict: a unit that comes within the loader's figure must drop its entry here; one that
# gets worse than measured fails.
NOT_REACHED = {
    "full": {("bench", "ram"): 1.43, ("excavator", "boom"): 1.55,
             ("excavator", "stick"): 1.64, ("excavator", "bucket"): 2.19},
    "dynamic": {("excavator", "boom"): 0.497, ("excavator", "stick"): 0.292,
                ("excavator", "bucket"): 0.414},
}


def test_every_shipped_machine_is_here():
    assert {p.stem for p in MACHINES} >= {"loader", "excavator", "bench"}


def test_a_shipped_machine_splits_its_units_over_two_buses():
    cfg = load_config(REPO / "config" / "excavator.yaml")
    assert cfg.bus_names == ("default", "can1")
    assert cfg.units_on_bus("default") == ("boom", "stick")
    assert cfg.units_on_bus("can1") == ("bucket",)
    assert cfg.bus_kwargs("can1")["channel"] == "can1"


@pytest.mark.parametrize("path", MACHINES, ids=lambda p: p.stem)
def test_every_value_says_where_it_comes_from(path):
    for line in path.read_text().splitlines():
        body = line.split("#", 1)[0].strip()
        if body and not body.endswith(":") and ":" in body:
            comment = line.split("#", 1)[1] if "#" in line else ""
            nested = line.strip().startswith(("bottom", "top", "interface", "channel"))
            assert "paper" in comment or "chosen" in comment or nested, (path.name, line)


def test_config_and_work_cycle(machine: Config):
    assert 1 <= len(machine.unit_names) <= 8
    assert cycle_names(machine)
    p = work_cycle(machine)
    t = np.arange(0.0, p.duration_s, 0.01)
    for a in machine.unit_names:
        x, _ = p.evaluate(a, t)
        unit = machine.unit(a)
        assert x[0] == x[-1]                                  # the cycle repeats
        assert x.min() < unit.references_mm["mid"] < x.max(), a    # it crosses a switch
        assert machine.can.units[a].hall_bits.keys() >= unit.references_mm.keys()


def test_every_cycle_at_every_speed(machine: Config):
    """Each configured cycle: slower at lower levels, back to its start, within the strokes
    (plus the end-stop overtravel)."""
    for name in cycle_names(machine):
        durations = []
        for speed in (1, 2, 3, 4):
            p = work_cycle(machine, name, speed, cycles=2)
            durations.append(p.cycle_s)
            for a, tr in p.trajectories.items():
                assert tr.position_mm[0] == tr.position_mm[-1], (name, a)
                assert -100.0 <= tr.position_mm.min() <= tr.position_mm.max() \
                    <= machine.unit(a).stroke_mm + 100.0, (name, a)
        assert durations == sorted(durations, reverse=True), name


def test_tables_build_for_every_unit(machine: Config):
    for a in machine.unit_names:
        tables = build_unit_tables(machine, a)
        assert tables.actuator == a


def test_simulated_runs_have_every_unit(machine: Config, machine_runs):
    for runs in machine_runs:
        assert list(runs) == list(machine.unit_names)
        for a, run in runs.items():
            assert run.time_s[-1] >= 15.0
            assert np.ptp(run.position_mm) > 100.0, a          # the unit really moved
            assert any(state.any() for state in run.refs.values()), a


@pytest.mark.parametrize("mode", ["full", "dynamic"])
def test_estimate_against_the_loaders_accuracy(machine: Config, machine_runs, mode: str):
    name = machine.source.rsplit("/", 1)[-1].removesuffix(".yaml")
    worst = {}
    for a in machine.unit_names:
        tables = build_unit_tables(machine, a)
        errors = []
        for runs in machine_runs:
            run = runs[a]
            est = Estimator(machine, a, tables, mode=mode,
                            initial_position_mm=float(run.position_mm[0]))
            res = est.run(run.time_s, run.speed_rpm, run.torque_nm, run.oil_temp_c, run.refs)
            errors.append(accuracy(res.position_mm, run.position_mm).max_abs_error_mm)
        worst[a] = max(errors)
    bound = LOADER_MAX_ERROR_MM[mode] * MARGIN
    short = NOT_REACHED[mode]
    reached = {a: e for a, e in worst.items() if (name, a) not in short}
    missed = {a: e for a, e in worst.items() if (name, a) in short}
    assert all(e <= bound for e in reached.values()), (worst, bound)
    for a, e in missed.items():
        # documented shortfall: still there (else tighten), and no worse than measured
        assert bound < e <= short[(name, a)] * MARGIN, (a, e, bound)
