"""Issue 36's Kalman prototype: covered on the nominal plant and with the structure the model
lacks (its unmodelled flow is a Gauss-Markov error, not a parameter it can learn), a switch
mounted off within its tolerance is an offset, not an alarm; it flags what its model cannot
explain (a switch mounted far from its configured place)."""

import dataclasses

import numpy as np
import pytest

from ddh_vsensor.estimator import kalman
from ddh_vsensor.sim.effects import build_effects, structure_effects
from ddh_vsensor.sim.run import RunSpec, simulate_campaign


@pytest.fixture(scope="module")
def nominal(cfg):
    """The paper cycle at speed 4 with 1040 kg, cold and warm oil."""
    specs = [RunSpec(speed=4, payload_kg=1040.0, oil_temp_c=t) for t in (-10.0, 27.0)]
    return simulate_campaign(cfg, specs)


def _jobs(cfg, runs):
    jobs = [(a, r[a]) for r in runs for a in cfg.unit_names]
    return jobs, [float(r.position_mm[0]) for _, r in jobs]


def test_nominal_error_is_within_the_published_uncertainty(cfg, nominal):
    jobs, x0 = _jobs(cfg, nominal)
    for refs in (False, True):
        results = kalman.run_many(cfg, jobs, references=refs, initial_positions_mm=x0)
        for (a, r), res in zip(jobs, results):
            e = res.estimate
            err = np.abs(e.position_mm - r.position_mm)
            assert np.mean((err > e.uncertainty_mm) & (e.flags == 0)) <= 0.001, (a, refs)
            assert err.max() < 2.5, (a, refs)    # bench: up to 1.9 mm (refs: 2.5 boom)
            # the price of honesty: the flow error's spread over strokes (bench: 5..32 mm)
            assert np.median(e.uncertainty_mm) < 35.0, (a, refs)
            assert not (e.flags & kalman.MODEL_INCONSISTENT).any(), (a, refs)


def test_typical_structure_stays_covered_without_references(cfg):
    """Leakage through orifices and growing with speed, pressure-dependent seal friction, hose
    compliance, a lagging torque and tank sensor: the filter neither runs to a far stop nor
    publishes a trusted reading wrong by more than it says."""
    effects = structure_effects(1.0)
    specs = [RunSpec(speed=4, payload_kg=1040.0, oil_temp_c=t,
                     effects={a: effects for a in cfg.unit_names}) for t in (-10.0, 27.0)]
    jobs, x0 = _jobs(cfg, simulate_campaign(cfg, specs))
    results = kalman.run_many(cfg, jobs, references=False, initial_positions_mm=x0)
    for (a, r), res in zip(jobs, results):
        e = res.estimate
        err = np.abs(e.position_mm - r.position_mm)
        assert err.max() < 15.0, a
        assert np.mean((err > e.uncertainty_mm) & (e.flags == 0)) <= 0.03, a


def test_a_switch_mounted_off_within_its_tolerance_is_an_offset(cfg, nominal):
    """The configuration says the boom's middle switch sits 2 mm higher than it does (within
    its 3 mm tolerance): no alarm, the readings stay covered, and the switch's offset state
    leans the right way."""
    unit = cfg.unit("boom")
    moved = dataclasses.replace(unit, references_mm={**unit.references_mm,
                                                    "mid": unit.references_mm["mid"] + 2.0})
    off = dataclasses.replace(cfg, units={**cfg.units, "boom": moved})
    r = nominal[1]["boom"]
    res = kalman.run_many(off, [("boom", r)], references=True,
                          initial_positions_mm=[float(r.position_mm[0])])[0]
    e = res.estimate
    err = np.abs(e.position_mm - r.position_mm)
    assert not (e.flags & kalman.MODEL_INCONSISTENT).any()
    assert np.all(err <= e.uncertainty_mm)
    assert res.switch_offsets_mm["mid"] < 0.0


def test_a_switch_mounted_elsewhere_is_flagged_model_inconsistent(cfg, nominal):
    """The configuration says the boom's middle switch sits 20 mm higher than it does: its
    edges disagree with the estimate beyond their gate."""
    unit = cfg.unit("boom")
    moved = dataclasses.replace(unit, references_mm={**unit.references_mm,
                                                    "mid": unit.references_mm["mid"] + 20.0})
    wrong = dataclasses.replace(cfg, units={**cfg.units, "boom": moved})
    r = nominal[1]["boom"]
    est = kalman.run(wrong, "boom", r, initial_position_mm=float(r.position_mm[0]))
    mid = [ev for ev in est.events if ev.switch == "mid"]
    assert mid, "the cycle crosses the middle switch"
    first = mid[0].index
    assert est.flags[first] & kalman.MODEL_INCONSISTENT
    err = np.abs(est.position_mm - r.position_mm)
    plain = est.flags == 0
    # what is published unflagged after the wrong edge is still covered
    assert np.all(err[first:][plain[first:]] <= est.uncertainty_mm[first:][plain[first:]])


@pytest.mark.xfail(strict=True, reason="issue 36 finding: the load and torque-offset states "
                   "absorb a torque gain error (boom: no flag, 14 % of samples beyond)")
def test_a_drive_whose_torque_reads_high_fails_the_self_check(cfg):
    """A torque 40 % high (a drive calibrated for another motor) is no offset the filter may
    take up: its torque innovations should fail the chi-square test while the boom moves."""
    effects = build_effects(["torque_gain=1.4"], cfg.unit_names)
    r = simulate_campaign(cfg, [RunSpec(speed=4, payload_kg=1040.0, oil_temp_c=27.0,
                                        effects=effects)])[0]["boom"]
    res = kalman.run_many(cfg, [("boom", r)], references=False,
                          initial_positions_mm=[float(r.position_mm[0])])[0]
    e = res.estimate
    assert (e.flags & kalman.MODEL_INCONSISTENT).any()
    err = np.abs(e.position_mm - r.position_mm)
    assert np.mean((err > e.uncertainty_mm) & (e.flags == 0)) < 0.01
