"""The saved extended model: the file, and the estimator that applies it (both faces)."""

from __future__ import annotations

import dataclasses
import json

import numpy as np
import pytest

from ddh_vsensor.cli.main import main
from ddh_vsensor.estimator.extension import (RESIDUAL_FEATURES, Extension, ExtensionError,
                                             ResidualModel)
from ddh_vsensor.estimator.estimator import Estimator
from ddh_vsensor.io.csv import read_csv
from ddh_vsensor.sim import RunSpec, simulate

from .conftest import BASE_SEED


def _ext(cfg, cause, causes=(), residual=None, **params) -> Extension:
    return Extension(cause, params, "boom", cfg.physics_hash(), causes=causes,
                     residual=residual)


# a residual model that takes 2 % of the velocity off and drifts with the torque
RESIDUAL = ResidualModel(tuple({"velocity": 0.02, "torque_above_1": 0.05}.get(f, 0.0)
                               for f in RESIDUAL_FEATURES),
                         (1.0,) * len(RESIDUAL_FEATURES), (5.0, 10.0, 25.0))


def test_file_round_trip_and_refusals(cfg, tmp_path):
    ext = _ext(cfg, "pump_leakage", leakage_factor=1.7)
    path = ext.save(tmp_path / "ext.json")
    back = Extension.load(path, cfg, "boom")
    assert (back.cause, back.parameters, back.actuator) == ("pump_leakage",
                                                            {"leakage_factor": 1.7}, "boom")
    with pytest.raises(ExtensionError, match="fitted for the boom, not the bucket"):
        Extension.load(path, cfg, "bucket")
    other = dataclasses.replace(cfg, oil=dataclasses.replace(cfg.oil, bulk_modulus_pa=1.0e9))
    with pytest.raises(ExtensionError, match="another configuration"):
        Extension.load(path, other, "boom")
    (tmp_path / "bad.json").write_text("{not json")
    with pytest.raises(ExtensionError, match="bad.json: not an extension file"):
        Extension.load(tmp_path / "bad.json")
    data = json.loads(path.read_text())
    data["cause"] = "gremlins"
    (tmp_path / "unknown.json").write_text(json.dumps(data))
    with pytest.raises(ExtensionError, match="unknown cause 'gremlins'"):
        Extension.load(tmp_path / "unknown.json")
    del data["parameters"]
    data["cause"] = "belt_slip"
    (tmp_path / "noparam.json").write_text(json.dumps(data))
    with pytest.raises(ExtensionError, match="malformed|needs parameter"):
        Extension.load(tmp_path / "noparam.json")
    joint = _ext(cfg, "pump_leakage", ("pump_leakage", "torque_gain"), RESIDUAL,
                 leakage_factor=1.5, torque_gain=0.9)
    back = Extension.load(joint.save(tmp_path / "joint.json"), cfg, "boom")
    assert back == joint
    data = json.loads((tmp_path / "joint.json").read_text())
    data["residual"]["weights"] = [1.0]
    (tmp_path / "short.json").write_text(json.dumps(data))
    with pytest.raises(ExtensionError, match="malformed"):
        Extension.load(tmp_path / "short.json")


@pytest.fixture(scope="module")
def nominal_run(campaigns):
    _, paths = campaigns.get("sensor")           # the boom has no effect
    return read_csv(paths["boom"][-1])


@pytest.mark.parametrize("cause, params", [
    ("none", {}), ("low_speed_leakage", {}), ("pump_leakage", {"leakage_factor": 1.8}),
    ("displacement", {"displacement_factor": 0.97}),
    ("belt_slip", {"slip_percent_per_100nm": 8.0}), ("time_offset", {"time_offset_s": 0.05}),
    ("time_offset", {"time_offset_s": -0.08}), ("compressibility", {"air_fraction": 0.03}),
    ("torque_gain", {"torque_gain": 0.9}), ("torque_offset", {"torque_offset_nm": 2.0}),
    ("oil_temp_offset", {"oil_temp_offset_c": -10.0}),
    ("pump_leakage+belt_slip", {"leakage_factor": 1.5, "slip_percent_per_100nm": 5.0}),
    ("compressibility+torque_gain", {"air_fraction": 0.02, "torque_gain": 1.1}),
    ("unexplained", {})])
def test_online_face_follows_the_offline_one(cause, params, cfg, unit_tables, nominal_run):
    run = nominal_run
    causes = tuple(cause.split("+"))
    ext = _ext(cfg, causes[0], causes if cause != "unexplained" else (),
               RESIDUAL if cause == "unexplained" else None, **params)
    cause = causes[0]
    mode = "paper" if cause == "low_speed_leakage" else "full"      # what it was fitted in
    ext = dataclasses.replace(ext, mode=mode)
    # (a time offset the data does not have makes references disagree by design)
    kw = dict(references=cause != "time_offset", initial_position_mm=float(run.position_mm[0]))
    offline = ext.estimator(cfg, unit_tables["boom"], **kw).run(
        run.time_s, run.speed_rpm, run.torque_nm, run.oil_temp_c, run.refs)
    online_est = ext.estimator(cfg, unit_tables["boom"], **kw)
    online = np.array([online_est.step(t, n, q, c, {k: bool(v[i]) for k, v in run.refs.items()})
                       .position_mm for i, (t, n, q, c) in enumerate(zip(
                           run.time_s, run.speed_rpm, run.torque_nm, run.oil_temp_c))])
    plain = Estimator(cfg, "boom", unit_tables["boom"], mode=mode, **kw).run(
        run.time_s, run.speed_rpm, run.torque_nm, run.oil_temp_c, run.refs).position_mm
    gap = np.max(np.abs(online - offline.position_mm))
    if cause == "time_offset" and params["time_offset_s"] > 0:
        assert gap < 0.6                # online: predicted ahead; offline: inputs shifted
    elif cause in ("time_offset", "compressibility", "unexplained"):
        assert gap < 0.05               # delayed inputs / the same model, by step
    else:
        assert gap < 1e-6
    if cause == "none":
        assert np.array_equal(offline.position_mm, plain)
    else:
        assert np.max(np.abs(offline.position_mm - plain)) > 0.05     # it does something


def test_the_air_track_takes_the_torque_at_the_speeds_instants_in_both_faces(
        cfg, unit_tables, nominal_run):
    """``motor.torque_lag_s``: the estimator and the extension's own chamber track both carry
    the torque forward, online as offline."""
    run = nominal_run
    lagging = dataclasses.replace(cfg, units={name: dataclasses.replace(
        u, motor=dataclasses.replace(u.motor, torque_lag_s=0.002))
        for name, u in cfg.units.items()})
    ext = dataclasses.replace(_ext(cfg, "compressibility", air_fraction=0.03), mode="full")
    kw = dict(references=True, initial_position_mm=float(run.position_mm[0]))
    positions = []
    for c in (cfg, lagging):
        offline = ext.estimator(c, unit_tables["boom"], **kw).run(
            run.time_s, run.speed_rpm, run.torque_nm, run.oil_temp_c, run.refs).position_mm
        est = ext.estimator(c, unit_tables["boom"], **kw)
        online = np.array([est.step(t, n, q, T, {k: bool(v[i]) for k, v in run.refs.items()})
                           .position_mm for i, (t, n, q, T) in enumerate(zip(
                               run.time_s, run.speed_rpm, run.torque_nm, run.oil_temp_c))])
        assert np.max(np.abs(online - offline)) < 1e-6        # the same steps (1e-11 here)
        positions.append(offline)
    assert np.max(np.abs(positions[1] - positions[0])) > 0.01


def test_online_time_offset_with_references_on_lagging_signals(cfg, unit_tables):
    lag = float(np.random.default_rng(BASE_SEED).uniform(0.05, 0.3))
    run = simulate(cfg, RunSpec(speed=4, payload_kg=1040.0, oil_temp_c=35.0,
                                effects=[f"time_offset={lag}"], seed=BASE_SEED))["boom"]
    trial = f"time offset {lag:.3f} s"
    ext = _ext(cfg, "time_offset", time_offset_s=lag)
    kw = dict(initial_position_mm=float(run.position_mm[0]))
    est = ext.estimator(cfg, unit_tables["boom"], **kw)
    online = np.array([est.step(t, n, q, c, {k: bool(v[i]) for k, v in run.refs.items()})
                       .position_mm for i, (t, n, q, c) in enumerate(zip(
                           run.time_s, run.speed_rpm, run.torque_nm, run.oil_temp_c))])
    plain = Estimator(cfg, "boom", unit_tables["boom"], **kw).run(
        run.time_s, run.speed_rpm, run.torque_nm, run.oil_temp_c, run.refs).position_mm
    err = lambda x: np.nanmax(np.abs(x - run.position_mm))          # noqa: E731
    assert err(online) < 0.5 * err(plain), trial


def test_estimate_applies_the_extension_an_analysis_saved(campaigns, tmp_path, capsys):
    """The boom of the open-set campaign: a deviation outside the catalogue, so the
    extension is the residual model (or what the analysis decided instead)."""
    trial, paths = campaigns.get("open")
    runs = paths["boom"]
    report = campaigns.analyze("open", "boom")
    capsys.readouterr()
    for extra in ([], ["--extension", report["extension_file"]]):
        assert main(["estimate", str(runs[0]), "--actuator", "boom", "--no-references",
                     "--json", *extra]) == 0
    plain, extended = (json.loads(line) for line in capsys.readouterr().out.splitlines())
    assert extended["max_abs_error_mm"] < 0.5 * plain["max_abs_error_mm"], trial
    assert extended["max_abs_error_mm"] <= report["extended"]["max_abs_error_mm"] + 0.2
    assert main(["estimate", str(runs[0]), "--actuator", "bucket", "--extension",
                 report["extension_file"]]) == 2
    assert "fitted for the boom, not the bucket" in capsys.readouterr().err


def test_the_wrapper_stands_in_for_an_estimator(cfg, unit_tables, nominal_run):
    """What the service does with an Estimator: step, read and write its state, snapshot,
    restore (a preset)."""
    run = nominal_run
    est = _ext(cfg, "time_offset", time_offset_s=0.05).estimator(
        cfg, unit_tables["boom"], initial_position_mm=float(run.position_mm[0]))
    for i in range(len(run.time_s) // 2):
        step = est.step(run.time_s[i], run.speed_rpm[i], run.torque_nm[i], run.oil_temp_c[i])
    assert est.position_mm == step.position_mm != est.estimator.position_mm
    est.referenced = False                              # writes reach the estimator
    assert est.estimator.referenced is False and est.referenced is False
    state = est.snapshot()
    assert state.position_mm == est.position_mm
    state.position_mm = 123.0
    est.restore(state)
    assert est.position_mm == est.estimator.position_mm == 123.0
    assert est.max_gap_s == cfg.estimator.max_gap_s     # reads too


def test_a_cold_started_air_extension_meets_no_made_up_end_stop(cfg, unit_tables, nominal_run):
    """Not referenced, the rod's position is unknown: the air correction's table estimate
    must not run from a made-up start into an end stop that is not there. After the first
    reference the cold start follows the start from the true position."""
    run = nominal_run
    ext = _ext(cfg, "compressibility", ("compressibility",), air_fraction=0.03)
    args = (run.time_s, run.speed_rpm, run.torque_nm, run.oil_temp_c, run.refs)
    warm = ext.estimator(cfg, unit_tables["boom"],
                         initial_position_mm=float(run.position_mm[0])).run(*args)
    cold_est = ext.estimator(cfg, unit_tables["boom"])
    assert not cold_est.estimator.referenced
    cold = cold_est.run(*args)
    first = cold.events[0].index
    gap = np.max(np.abs(cold.position_mm[first:] - warm.position_mm[first:]))
    assert gap < 0.15, gap      # (the warm track's chamber pressures differ at the reference)
    online_est = ext.estimator(cfg, unit_tables["boom"])
    online = np.array([online_est.step(t, n, q, c, {k: bool(v[i]) for k, v in run.refs.items()})
                       .position_mm for i, (t, n, q, c) in enumerate(zip(*args[:4]))])
    assert np.max(np.abs(online[first:] - cold.position_mm[first:])) < 0.05
