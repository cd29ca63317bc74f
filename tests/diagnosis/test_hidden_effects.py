"""The tests that hide effects the way real data does: the simulator hides a measurement-chain
cause, a pair of causes, a deviation the catalogue does not have; the diagnosis sees only the
runs (comment lines stripped) and must name what is there, all of it, or say it cannot,
and its extension must halve the held-out maximum error."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from ddh_vsensor.diagnosis.analyze import diagnose
from ddh_vsensor.diagnosis.causes import ALL_CAUSES
from ddh_vsensor.diagnosis.runs import prepare_run
from ddh_vsensor.diagnosis.selection import OWN_ERROR_RMS_MM
from ddh_vsensor.diagnosis.trials import Trial, draw_trial
from ddh_vsensor.measured import Run

from .conftest import BASE_SEED, hidden, simulate_trials

KEYS = {"actuator", "mode", "runs", "cause", "ranking", "baseline", "extended", "holdout_runs",
        "extension_file", "causes", "ambiguous", "not_observable", "observability",
        "thresholds"}


def _where(trial) -> str:
    return f"{trial.describe()} (DDH_DIAGNOSIS_SEED={BASE_SEED})"


def _seeded_trials() -> dict[int, Trial]:
    """The trials of the tests below that name their seed, by that seed."""
    fill = draw_trial(31000, "none", cycle="paper")
    return {7700: draw_trial(7700, "torque_gain", cycle="paper"),
            9002: draw_trial(9002, "oil_temp_offset", cycle="random"),
            25004: draw_trial(25004, cycle="paper", pair=True),
            25005: draw_trial(25005, cycle="paper", pair=True),
            27003: draw_trial(27003, "none", cycle="random"),
            31000: dataclasses.replace(fill, effect="pump_fill", value=4.285),
            30012: draw_trial(30012, "pump_leakage", cycle="paper"),
            33118: draw_trial(33118, cycle="paper", pair=True)}


@pytest.fixture(scope="module")
def seeded(cfg) -> dict[int, tuple[Trial, list[dict[str, Run]]]]:
    """Every seeded trial simulated, all in one lockstep batch (each run as
    ``simulate_trial`` gives it alone): seed -> (trial, runs)."""
    trials = _seeded_trials()
    runs = simulate_trials(cfg, list(trials.values()))
    return {seed: (trial, r) for (seed, trial), r in zip(trials.items(), runs)}


def _diagnosed(cfg, seeded, seed: int, actuator: str, mode: str | None = None):
    """The seeded trial and one actuator's runs of it diagnosed."""
    trial, runs = seeded[seed]
    return trial, diagnose(cfg, actuator, [prepare_run(r[actuator]) for r in runs], mode)


def _halved(report: dict, trial) -> None:
    before = report["baseline"]["max_abs_error_mm"]
    after = report["extended"]["max_abs_error_mm"]
    assert after <= 0.5 * before, f"held-out max error {before:.2f} -> {after:.2f} mm: " \
        f"{_where(trial)}"


def _named(report: dict) -> set[str]:
    return {c["cause"] for c in report["causes"]}


def _covers(report: dict, truth: dict[str, float]) -> None:
    for c in report["causes"]:
        if c["cause"] in truth:
            (lo, hi), = c["interval"].values()
            assert lo <= truth[c["cause"]] <= hi, f"{c}: true {truth[c['cause']]}"


def test_no_effect_is_none(campaigns):
    trial, paths = campaigns.get("sensor")
    report = campaigns.analyze("sensor", "boom")
    assert set(report) == KEYS
    assert report["cause"] == "none", f"{report['cause']}: {_where(trial)}; " \
        f"{report['ranking'][:3]}"
    assert report["causes"] == [] and report["ambiguous"] == []
    assert sorted(report["holdout_runs"]) == sorted(map(str, paths["boom"]))
    # no --baseline: the answer says whose thresholds it judged by
    assert report["thresholds"]["source"] == "simulator"
    assert report["thresholds"]["baseline"] is None


def test_names_a_faulty_sensor(campaigns):
    trial, _ = campaigns.get("sensor")
    truth = hidden(trial, "bucket")
    report = campaigns.analyze("sensor", "bucket")
    assert report["cause"] in truth and _named(report) == set(truth), \
        f"named {report['cause']} {_named(report)}: {_where(trial)}"
    assert report["ranking"][0]["cause"] in ALL_CAUSES
    _halved(report, trial)
    _covers(report, truth)


def test_names_both_causes_of_a_pair(campaigns):
    """On the boom, unless the pair has air in it: the boom's chambers stay pressurised and
    air errs by 1-2 mm there (diagnosis/README.md); the bucket's A chamber shows it."""
    trial, _ = campaigns.get("pair")
    actuator = "bucket" if "compressibility" in trial.effects else "boom"
    truth = hidden(trial, actuator)
    report = campaigns.analyze("pair", actuator)
    assert _named(report) == set(truth), f"named {_named(report)}, ambiguous " \
        f"{report['ambiguous']}: {_where(trial)}"
    assert report["cause"] == max(report["causes"], key=lambda c: c["share"])["cause"]
    _halved(report, trial)


def test_a_deviation_outside_the_catalogue_is_not_given_a_wrong_name(campaigns):
    """A relief valve that seeps above 40 bar (not viscous, not a pump): the answer must be
    unexplained, or an ambiguity that says so; the residual model still halves the error."""
    trial, _ = campaigns.get("open")
    report = campaigns.analyze("open", "boom")
    named = _named(report) - {"unexplained"}
    in_ambiguity = any("unexplained" in pair for pair in report["ambiguous"])
    assert report["cause"] == "unexplained" or in_ambiguity, \
        f"confident {report['cause']} {named}: {_where(trial)}"
    _halved(report, trial)


def test_names_a_catalogued_cause(campaigns):
    trial, _ = campaigns.get("open")
    truth = hidden(trial, "bucket")
    report = campaigns.analyze("open", "bucket")
    assert _named(report) == set(truth), f"named {_named(report)}: {_where(trial)}"
    _halved(report, trial)


def test_paper_mode_names_low_speed_leakage_and_reaches_full_mode(campaigns):
    trial, _ = campaigns.get("sensor")
    full = campaigns.analyze("sensor", "boom", "--mode", "full")
    paper = campaigns.analyze("sensor", "boom", "--mode", "paper")
    assert paper["mode"] == "paper" and paper["cause"] == "low_speed_leakage", trial
    assert paper["baseline"]["max_abs_error_mm"] > 5.0       # the paper's creep
    assert paper["extended"]["max_abs_error_mm"] <= full["baseline"]["max_abs_error_mm"] + 0.05
    assert paper["extended"]["rms_error_mm"] <= full["baseline"]["rms_error_mm"] + 0.05


def test_a_small_effect_left_with_only_the_models_own_error_is_named(cfg, seeded):
    """A drive torque reading 11 % low (seed 7700, the paper's cycle): torque_gain explains
    96 % and leaves 0.27 mm RMS, the model's own error on runs without an effect (0.10-0.79
    mm), three quarters of which the residual model takes as it does of any own error. That
    is no structured error left; it had been answered `unexplained`."""
    _, d = _diagnosed(cfg, seeded, 7700, "boom", "full")
    assert d.cause == "torque_gain", d.decision.reason
    assert d.decision.rms_after_mm <= OWN_ERROR_RMS_MM


def test_an_oil_temperature_offset_is_not_taken_for_pump_leakage(cfg, seeded):
    """The tank sensor reading 8.7 degC low (seed 9002, random cycles at 26 and 44 degC, the
    bucket). Diagnosed on the tables (`full`), whose own error on these runs without any
    effect fits as leakage x 0.95 or an offset of +1.3 degC, leakage x 1.36 explained more
    (99.1 %) than the offset (98.6 %, fitted -7.4) and was named. The configured `dynamic`
    model's own error fits as x 0.996 or +0.1 degC: the offset is named, -8.6 degC."""
    trial, d = _diagnosed(cfg, seeded, 9002, "bucket")
    assert d.mode == "dynamic" and d.cause == "oil_temp_offset", d.decision.reason
    lo, hi = d.chosen_set.intervals["oil_temp_offset_c"]
    assert lo <= trial.value <= hi


def test_a_torque_offset_hidden_by_air_is_found_with_it(cfg, seeded):
    """A torque offset of +3.3 N*m with 3.6 % air (seed 25004, the bucket): neither fits
    alone (air alone 0.0035, within its resolution; the offset alone makes the runs worse),
    so no single cause was resolved and the pair was answered `unexplained`, although the
    pressures measure the offset. Grown from the best fits as they are, the pair is found;
    air is fitted as the second cause exactly (a linearised screen ranked it seventh)."""
    _, d = _diagnosed(cfg, seeded, 25004, "bucket")
    assert set(d.named) == {"torque_offset", "compressibility"}, d.decision.reason
    assert d.chosen_set.params["torque_offset_nm"] == pytest.approx(3.29, abs=0.3)


def test_the_pressures_tell_leakage_from_an_oil_offset_next_to_a_torque_gain(cfg, seeded):
    """A torque gain of 0.86 with pump leakage x 0.59 (seed 25005, the bucket): the gain
    hides the leakage and an oil temperature offset of +11 degC alike, and the offset fitted
    one step better alone, so the set was grown from it only and the gain the pressures
    measured joined it (an offset with a torque gain named). Grown from the two best, the
    pair that describes every run is chosen."""
    _, d = _diagnosed(cfg, seeded, 25005, "bucket")
    assert set(d.named) == {"pump_leakage", "torque_gain"}, d.decision.reason
    assert d.chosen_set.params["leakage_factor"] == pytest.approx(0.59, rel=0.05)


def test_an_error_within_the_models_own_is_not_unexplained(cfg, seeded):
    """No effect, the boom on random cycles (seed 27003): the model's held-out error is
    0.38 mm at most, within its own; the residual model still found 'structure' in it
    (the answer was `unexplained`)."""
    _, d = _diagnosed(cfg, seeded, 27003, "boom")
    assert d.cause == "none", d.decision.reason
    assert d.decision.rms_before_mm <= OWN_ERROR_RMS_MM


def test_pumps_filling_short_at_speed_are_unexplained_and_the_residual_model_follows(cfg,
                                                                                     seeded):
    """The pumps fill 4.3 % short at the speed limit (seed 31000, the boom; no catalogue
    cause): `unexplained`, and the residual model, with the speed cubed among its features,
    takes the held-out maximum error from 5.8 mm to within the model's own (it left 2.7 mm
    without that feature)."""
    _, d = _diagnosed(cfg, seeded, 31000, "boom")
    assert d.cause == "unexplained", d.decision.reason
    before = max(float(np.nanmax(np.abs(e))) for e in d.baseline)
    after = max(float(np.max(np.abs(h))) for h in d.heldout)
    assert before > 5.0 and after <= 0.5, (before, after)


def test_no_cause_joins_a_set_that_leaves_only_the_models_own_error(cfg, seeded):
    """Pump leakage x 0.57 alone (seed 30012, the boom): it leaves 0.04 mm RMS, and a torque
    gain of 1.03 took half of that (resolved, and within the pressures' tolerance) and was
    named with it once every cause was tried as the second."""
    _, d = _diagnosed(cfg, seeded, 30012, "boom")
    assert list(d.named) == ["pump_leakage"], d.decision.reason


def test_a_second_cause_joins_a_set_that_leaves_more_than_the_models_own_error(cfg, seeded):
    """Pump leakage x 1.74 with 2.4 % air (seed 33118, the boom): the leakage alone leaves
    0.45 mm RMS (2.3 mm at most), far above the chamber model's own 0.03-0.10 mm; with the
    floor at the tables' 0.5 mm air was kept out."""
    _, d = _diagnosed(cfg, seeded, 33118, "boom")
    assert set(d.named) == {"pump_leakage", "compressibility"}, d.decision.reason
