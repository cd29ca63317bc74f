"""The service checks each reference switch's travel between its edges against its configured
window and hysteresis: a drift is logged once, shown in the systemd status line and by
``ddh-vsensor status``, kept across a restart, and changes nothing that is published."""

from __future__ import annotations

import dataclasses
import json
import logging
import re
from pathlib import Path

import numpy as np
import pytest

from ddh_vsensor.cli.main import main
from ddh_vsensor.config import ConfigError, parse_config
from ddh_vsensor.estimator.switch_drift import SwitchDrift
from ddh_vsensor.master.replay import machine_frames
from ddh_vsensor.measured import Run
from ddh_vsensor.service import Service, ServiceOptions
from ddh_vsensor.sim.cycles import Profile, Trajectory, move_time, work_unit
from ddh_vsensor.sim.run import RunSpec, simulate_with_truth
from ddh_vsensor.sim.sensors import hall_edge_times, hall_switch

from .conftest import channel_name
from .test_cli import ServiceThread

SIM_S = 90.0
MID_WINDOW_MM = 2.0        # the boom's middle switch's true window; the configuration says 3


def _around_mid(cfg, seed: int) -> Profile:
    """Both units work around their middle switch: random targets within its window plus
    5 mm on either side, at 20 to 100 % of travel speed, short holds."""
    rng = np.random.default_rng(seed)
    trajectories = {}
    for a in cfg.unit_names:
        u = cfg.unit(a)
        p = u.references_mm["mid"]
        reach = u.reference_window_mm + u.reference_hysteresis_mm + 5.0
        v_top = work_unit(cfg, a).travel_speed_mm_s
        t, x, knots = 0.0, p - reach, [(0.0, p - reach)]
        while True:
            target = p + rng.uniform(-reach, reach)
            hold = rng.uniform(0.0, 0.3)
            move = move_time(target - x, rng.uniform(0.2, 1.0) * v_top)
            if t + hold + move + 0.5 > SIM_S:
                break
            knots += [(t + hold, x), (t + hold + move, target)]
            t, x = t + hold + move, target
        knots.append((SIM_S, x))
        trajectories[a] = Trajectory(np.array([k[0] for k in knots]),
                                     np.array([k[1] for k in knots]))
    return Profile("around the middle switches", trajectories, SIM_S)


def _switched(run: Run, x_mm: np.ndarray, geometry: dict[str, tuple[float, float, float]]
              ) -> Run:
    refs = {name: hall_switch(x_mm, p, w, h) for name, (p, w, h) in geometry.items()}
    edges = {name: hall_edge_times(run.time_s, x_mm, refs[name], p, w, h)
             for name, (p, w, h) in geometry.items()}
    return dataclasses.replace(run, refs=refs, ref_edge_s=edges)


@pytest.fixture(scope="module")
def drifted_frames(cfg) -> list:
    """The machine's frames with the boom's middle switch 1 mm narrower on each side than
    configured (its span passing through 2 mm short); every other switch as configured."""
    runs = {}
    for a, (run, truth) in simulate_with_truth(
            cfg, [RunSpec(cycle=_around_mid(cfg, 5), seed=5)])[0].items():
        u = cfg.unit(a)
        geometry = {n: (p, u.reference_window_mm, u.reference_hysteresis_mm)
                    for n, p in u.references_mm.items()}
        if a == "boom":
            geometry["mid"] = (u.references_mm["mid"], MID_WINDOW_MM,
                               u.reference_hysteresis_mm)
        runs[a] = _switched(run, truth.x_m * 1e3, geometry)
    frames = list(machine_frames(cfg, runs, heartbeat_period_s=None))
    for msg in frames:
        msg.timestamp += 100.0      # a stamp of 0 is an interface without stamps: none here
    return frames


def _service(cfg, unit_tables, state_dir: Path) -> Service:
    """A service never started, on its own clock, its estimates kept in ``state_dir``."""
    return Service(cfg, unit_tables, {"interface": "virtual", "channel": channel_name()},
                   ServiceOptions(state_dir=state_dir), clock=lambda: 0.0)


def _drifts(caplog) -> list[str]:
    return [r.getMessage() for r in caplog.records
            if re.match(r"\w+: reference switch \w+ (drifted|back within)", r.getMessage())]


def test_a_drifted_switch_is_logged_once_shown_and_kept_across_a_restart(
        cfg, unit_tables, drifted_frames, tmp_path, caplog, capsys) -> None:
    caplog.set_level(logging.INFO, logger="ddh_vsensor")
    service = _service(cfg, unit_tables, tmp_path)
    for msg in drifted_frames:
        service.ingest.handle([msg], 1000.0 + msg.timestamp)
    assert service.ingest.canopen_errors == 0
    lines = _drifts(caplog)
    assert len(lines) == 1 and lines[0].startswith("boom: reference switch mid drifted"), lines
    assert re.search(r"passing through \(2 window \+ hysteresis\) 4\.\d\d mm, configured 6\.50",
                     lines[0]), lines[0]
    assert "reference switch drift: boom mid" in service.status_line()
    through = service.units["boom"].switch_drift.switches["mid"].spans["through"]
    assert through.pairs >= 20
    # nothing published changes with it: the same frames, no switch checked, the same values
    unchecked = _service(cfg, unit_tables, tmp_path / "unchecked")
    for unit in unchecked.units.values():
        unit.switch_drift = SwitchDrift((), 1.0, 0.01, 0.01)
    for msg in drifted_frames:
        unchecked.ingest.handle([msg], 1000.0 + msg.timestamp)
    for unit in ("boom", "bucket"):
        assert unchecked.published(unchecked.units[unit]) == service.published(
            service.units[unit])
    service.save_states(clean=True)
    record = json.loads((tmp_path / "boom.switches.json").read_text())
    assert record["switches"]["mid"]["drifted"] is True
    assert not json.loads((tmp_path / "bucket.switches.json").read_text())["switches"][
        "mid"]["drifted"]

    caplog.clear()
    again = _service(cfg, unit_tables, tmp_path)       # a restart
    assert again.units["boom"].switch_drift.drifted == ["mid"]
    assert again.units["bucket"].switch_drift.drifted == []
    assert again.units["boom"].switch_drift.switches["mid"].spans["through"].pairs == \
        through.pairs
    lines = _drifts(caplog)
    assert len(lines) == 1 and "carried over from before the start" in lines[0], lines
    assert "reference switch drift: boom mid" in again.status_line()

    channel = channel_name()
    runner = ServiceThread(cfg, unit_tables, channel)
    try:
        assert main(["status", "--interface", "virtual", "--channel", channel,
                     "--state-dir", str(tmp_path)]) == 0
        out = capsys.readouterr().out
        assert main(["status", "--interface", "virtual", "--channel", channel,
                     "--state-dir", str(tmp_path), "--json"]) == 0
        data = json.loads(capsys.readouterr().out)
        (tmp_path / "unsaved").mkdir()
        assert main(["status", "--interface", "virtual", "--channel", channel,
                     "--state-dir", str(tmp_path / "unsaved")]) == 0
        elsewhere = capsys.readouterr().out
    finally:
        runner.stop()
    assert re.search(r"switch mid\s+DRIFTED\s+through 4\.\d\d mm, configured 6\.50", out), out
    assert re.search(r"switch mid\s+ok\s+through 6\.\d\d mm", out), out
    assert data["boom"]["switches"]["mid"]["drifted"] is True
    assert data["bucket"]["switches"]["mid"]["drifted"] is False
    assert elsewhere.count("switches      no record in") == 2


def test_a_record_for_other_switches_is_not_carried_over(cfg, unit_tables, drifted_frames,
                                                         tmp_path, caplog) -> None:
    """Commissioned again (another window): the old spans say nothing of the new geometry;
    a corrupt record is a warning and a fresh start, never a failed start."""
    service = _service(cfg, unit_tables, tmp_path)
    for msg in drifted_frames:
        service.ingest.handle([msg], 1000.0 + msg.timestamp)
    service.save_states(clean=True)
    narrower = dataclasses.replace(cfg, units={
        a: dataclasses.replace(u, reference_window_mm=MID_WINDOW_MM)
        for a, u in cfg.units.items()})
    assert _service(narrower, unit_tables, tmp_path).units["boom"].switch_drift.drifted == []
    (tmp_path / "bucket.switches.json").write_text("{not json")
    caplog.set_level(logging.WARNING, logger="ddh_vsensor")
    restarted = _service(cfg, unit_tables, tmp_path)
    assert restarted.units["boom"].switch_drift.drifted == ["mid"]
    assert any("bucket: switch record" in r.getMessage() and "ignored" in r.getMessage()
               for r in caplog.records)


@pytest.mark.parametrize("value", [0.0, -1.0, "1 mm"])
def test_a_bad_drift_tolerance_is_one_line_naming_the_key(value) -> None:
    import yaml

    from ddh_vsensor.config import DEFAULT_CONFIG
    raw = yaml.safe_load(DEFAULT_CONFIG.read_text())
    raw["estimator"]["reference_drift_mm"] = value
    with pytest.raises(ConfigError) as err:
        parse_config(raw)
    text = str(err.value)
    assert "\n" not in text and "estimator.reference_drift_mm" in text, text
