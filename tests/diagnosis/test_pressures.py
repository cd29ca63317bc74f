"""The pressures' evidence under a logging offset: a candidate time offset is judged against
the line fitted at its own lag, not against the lag's bias."""

from __future__ import annotations

import math

import pytest

from ddh_vsensor.diagnosis.pressures import GAIN_TOLERANCE, torque_evidence
from ddh_vsensor.diagnosis.runs import prepare_run
from ddh_vsensor.diagnosis.trials import Trial, simulate_trial
from ddh_vsensor.diagnosis.workbench import Workbench

OFFSET_S = 0.3


@pytest.fixture(scope="module")
def lagging_runs(cfg):
    """The paper cycle at speed 4, 0 and 1040 kg, the drive's signals 0.3 s behind."""
    return simulate_trial(cfg, Trial(11, "time_offset", OFFSET_S, (4,), (40.0, 40.0), "paper"))


@pytest.mark.parametrize("actuator", ["boom", "bucket"])
def test_a_time_offset_is_checked_against_the_pressures_at_its_own_lag(cfg, lagging_runs,
                                                                        actuator):
    bench = Workbench(cfg, actuator, [prepare_run(r[actuator]) for r in lagging_runs], "full")
    ev = torque_evidence(bench)
    assert ev is not None
    # sample by sample the lag reads as a torque error beyond the tolerance (3-3.5 %)...
    assert abs(math.log(ev.gain)) > GAIN_TOLERANCE
    assert not ev.consistent({})
    # ...at the candidate's own lag the line is the nominal one, and the candidate stands
    at_lag = ev.at({"time_offset_s": OFFSET_S})
    assert at_lag.lag_s == OFFSET_S
    assert abs(math.log(at_lag.gain)) < 0.5 * GAIN_TOLERANCE
    assert ev.consistent({"time_offset_s": OFFSET_S})
    # without a time offset the evidence is the unlagged line itself
    assert ev.at({"pump_leakage": 1.5}) is ev
