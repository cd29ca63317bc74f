"""The work cycles come from the configuration; the reference loader's give exactly the
profiles the simulator produced before (its figures do not change).

``data/profiles_before_config.npz`` holds the knots of the profiles as the code produced them
before the cycles moved into ``work_cycle`` (paper and dig-dump cycles at speeds 1..4, the
random cycles of seeds 7 and 301, a fleet work day and a diagnosis random trial): compared
bit for bit, so every sample of every run is the same.
"""

from __future__ import annotations

import copy
from pathlib import Path

import numpy as np
import pytest
import yaml

from ddh_vsensor.config import ConfigError, parse_config
from ddh_vsensor.diagnosis.trials import random_cycle as trial_random_cycle
from ddh_vsensor.errors import UserError
from ddh_vsensor.sim.cycles import (Profile, cycle_names, random_cycle, require_cycle, work_cycle,
                                    work_unit)
from ddh_vsensor.sim.fleet import work_profile

from ..conftest import REPO

BEFORE = np.load(Path(__file__).with_name("data") / "profiles_before_config.npz")
RAW = yaml.safe_load((REPO / "config" / "loader.yaml").read_text())


def _same(key: str, p: Profile) -> None:
    assert p.cycle_s == BEFORE[f"{key}/cycle_s"]
    assert list(p.trajectories) == ["boom", "bucket"]
    for a, tr in p.trajectories.items():
        np.testing.assert_array_equal(tr.time_s, BEFORE[f"{key}/{a}/time_s"])
        np.testing.assert_array_equal(tr.position_mm, BEFORE[f"{key}/{a}/position_mm"])


@pytest.mark.parametrize("speed", [1, 2, 3, 4])
def test_configured_cycles_equal_the_former_code(cfg, speed):
    _same(f"paper{speed}", work_cycle(cfg, "paper", speed))
    _same(f"paper{speed}", work_cycle(cfg, "work", speed))        # the first cycle
    _same(f"digdump{speed}", work_cycle(cfg, "dig-dump", speed))
    assert work_cycle(cfg, "work", speed).name == f"paper speed {speed}"


def test_random_work_equals_the_former_code(cfg):
    for seed in (7, 301):
        _same(f"random{seed}", random_cycle(cfg, seed, 60.0))
    _same("fleet", work_profile(cfg, np.random.default_rng([0, 1, 2]), 60.0))
    _same("trial", trial_random_cycle(cfg, np.random.default_rng([5, 1])))


def test_overlapping_moves_and_holds(cfg):
    """``with_next`` starts the next step with this one; ``hold_s`` holds after a step."""
    p = work_cycle(cfg, "dig-dump", 4)
    boom, bucket = p.trajectories["boom"], p.trajectories["bucket"]
    assert boom.time_s[1] == bucket.time_s[1] == 0.5          # both start after start_hold_s
    steps = cfg.work_cycle.cycles["dig-dump"].steps
    assert steps[2].hold_s == 0.6
    # bucket: start, (tilt), (curl) -> the curl starts 0.2 s (pause) after the tilt ends
    assert bucket.time_s[3] == pytest.approx(bucket.time_s[2] + 0.2)
    assert boom.time_s[3] == pytest.approx(bucket.time_s[4] + 0.6)       # after the curl holds


def test_steps_that_do_not_move_and_zero_holds_leave_no_empty_segment():
    data = copy.deepcopy(RAW)
    cycle = data["work_cycle"]["cycles"]["paper"]
    cycle["end_hold_s"] = 0.0
    cycle["steps"] = [{"unit": "boom", "to_mm": 1.5},                 # already there
                      {"unit": "boom", "to_mm": 150.0, "hold_s": 0.0},
                      {"unit": "boom", "to_mm": 1.5, "hold_s": 0.0}]
    p = work_cycle(parse_config(data, "m.yaml"), "paper", cycles=2)
    for tr in p.trajectories.values():
        assert np.all(np.diff(tr.time_s) > 0.0)
    with np.errstate(all="raise"):
        x, _ = p.evaluate("boom", np.linspace(0.0, p.duration_s, 2001))
    assert np.all(np.isfinite(x)) and x.max() == pytest.approx(150.0)


def test_unknown_cycle_lists_the_names(cfg):
    assert cycle_names(cfg) == ("paper", "dig-dump")
    assert require_cycle(cfg, "work") == "paper"
    with pytest.raises(UserError, match="work, paper, dig-dump"):
        work_cycle(cfg, "trench")
    with pytest.raises(UserError, match="speed"):
        work_cycle(cfg, "paper", 5)


def test_without_a_work_cycle_section_random_work_still_runs(cfg):
    data = copy.deepcopy(RAW)
    del data["work_cycle"]
    bare = parse_config(data, "bare.yaml")
    with pytest.raises(UserError, match="no work_cycle section"):
        work_cycle(bare)
    speeds = work_unit(bare, "boom")
    top = bare.max_speed_mm_s("boom") / bare.faults.max_speed_factor
    assert speeds.travel_speed_mm_s == pytest.approx(0.8 * top)
    assert 0.0 < speeds.work_range_mm[0] < speeds.work_range_mm[1] < 311.15
    assert set(random_cycle(bare, 1, 20.0).trajectories) == {"boom", "bucket"}


def _mutate(path: str, value) -> dict:
    data = copy.deepcopy(RAW)
    node = data
    keys = path.split(".")
    for k in keys[:-1]:
        node = node[int(k)] if isinstance(node, list) else node[k]
    node[int(keys[-1]) if isinstance(node, list) else keys[-1]] = value
    return data


@pytest.mark.parametrize("path,value,words", [
    ("work_cycle.units.stick", {"travel_speed_mm_s": 1.0, "work_speed_mm_s": 1.0,
                                "work_range_mm": [0.0, 1.0]}, "no such unit"),
    ("work_cycle.units.boom.work_range_mm", [200.0, 100.0], "low < high"),
    ("work_cycle.units.boom.work_range_mm", [5.0, 400.0], "within the stroke"),
    ("work_cycle.units.boom.travel_speed_mm_s", 0.0, "greater than 0"),
    ("work_cycle.cycles.paper.steps.0.unit", "stick", "no such unit 'stick'"),
    ("work_cycle.cycles.paper.steps.0.to_mm", 1000.0, "beyond the stroke"),
    ("work_cycle.cycles.paper.steps.0.to_mm", -150.0, "at least -100"),
    ("work_cycle.cycles.paper.steps.0.speed_share", 1.5, "at most 1"),
    ("work_cycle.cycles.paper.steps.5.with_next", True, "last step"),
    ("work_cycle.cycles.paper.steps", [], "at least one step"),
    ("work_cycle.cycles.paper.start_mm", {"boom": 1.5}, "start_mm.bucket: missing"),
    ("work_cycle.cycles.paper.start_mm.bucket", 900.0, "outside the stroke"),
    ("work_cycle.cycles.work", {"start_mm": {}, "steps": [{"unit": "boom", "to_mm": 5.0}]},
     "other than work, random"),
    ("work_cycle.cycles.dig-dump.steps.0.hold_s", 1.0, "with_next does not hold"),
])
def test_bad_work_cycle_values_are_named(path, value, words):
    with pytest.raises(ConfigError, match=words) as err:
        parse_config(_mutate(path, value), "m.yaml")
    assert "work_cycle" in str(err.value)


def test_missing_unit_speeds_are_named():
    data = copy.deepcopy(RAW)
    del data["work_cycle"]["units"]["bucket"]
    with pytest.raises(ConfigError, match="work_cycle.units.bucket: missing"):
        parse_config(data, "m.yaml")
