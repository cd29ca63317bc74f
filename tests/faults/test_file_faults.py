"""The issue's table, file and signal side, against ``ddh-vsensor run`` as a process: hostile
state files and configs never make it exit with a traceback or hang before READY; signals
never lose state silently."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time

import pytest
import yaml

from ddh_vsensor.estimator.flags import Flags
from ddh_vsensor.estimator.state import EstimatorState, save_state

from .conftest import start_daemon
from .harness import STARTUP_TIMEOUT_S, Recorder, outputs


def _nested_json(depth_bytes: int) -> str:
    depth = depth_bytes // 2
    return "[" * depth + "]" * depth


@pytest.mark.parametrize("boom_kind,bucket_kind", [("nested", "fifo"),
                                                   ("symlink_zero", "huge"),
                                                   ("negative", "leftover_temp")])
def test_hostile_state_files_are_reported_and_ignored(cfg, cfg_raw, hub, tmp_path,
                                                      boom_kind, bucket_kind) -> None:
    state_dir = tmp_path / "state"
    state_dir.mkdir()

    def make(actuator: str, kind: str) -> None:
        path = state_dir / f"{actuator}.json"
        if kind == "nested":
            path.write_text(_nested_json(400_000))                       # 400 KB nesting
        elif kind == "fifo":
            os.mkfifo(path)
        elif kind == "symlink_zero":
            path.symlink_to("/dev/zero")
        elif kind == "huge":
            with open(path, "wb") as fh:                                  # 300 MB, sparse
                fh.truncate(300 * 1024 * 1024)
        elif kind == "negative":
            save_state(path, EstimatorState(actuator, cfg.physics_hash(), 100.0, -1000.0))
        elif kind == "leftover_temp":
            (state_dir / f".{actuator}.json.deadbeef.tmp").write_text("{half a write")
            save_state(path, EstimatorState(actuator, cfg.physics_hash(), 300.0, 1.0,
                                            clean=True))

    make("boom", boom_kind)
    make("bucket", bucket_kind)
    recorder = Recorder(hub)
    started = time.monotonic()
    try:
        daemon = start_daemon(hub, tmp_path, cfg_raw, state_dir=state_dir)
        ready_s = time.monotonic() - started
        time.sleep(0.5)
        code = daemon.stop()
    finally:
        recorder.close()
    log = daemon.log()
    assert code == 0 and "Traceback" not in log, log[-3000:]
    assert ready_s < 40.0
    for actuator, kind in (("boom", boom_kind), ("bucket", bucket_kind)):
        out = outputs(cfg, recorder.frames, actuator)
        assert out, log[-2000:]
        stroke = cfg.unit(actuator).stroke_mm
        if kind == "leftover_temp":          # the clean state is trusted, the temp removed
            assert out[-1].position_mm == pytest.approx(300.0, abs=0.01)
            assert not (state_dir / f".{actuator}.json.deadbeef.tmp").exists()
            assert "interrupted save" in log
        else:                                # ignored: cold start, the whole stroke
            assert f"{actuator}.json: corrupt state file ignored" in log
            assert out[-1].uncertainty_mm >= min(stroke, 655.35) - 0.01   # UINT16 counts
        assert out[-1].flags & Flags.NOT_REFERENCED
    # the stop wrote sound files over the hostile ones (a symlink is replaced, not followed)
    for actuator in cfg.can.units:
        path = state_dir / f"{actuator}.json"
        assert path.is_file() and not path.is_symlink()
        assert json.loads(path.read_text())["clean"] is True


def _bomb() -> str:
    lines = ["a: &a [lol, lol, lol, lol, lol, lol, lol, lol, lol]"]
    for i in range(1, 10):
        prev = chr(ord("a") + i - 1)
        lines.append(f"{chr(ord('a') + i)}: &{chr(ord('a') + i)} [" + ", ".join([f"*{prev}"] * 9)
                     + "]")
    lines.append("oil: {name: *j}")
    return "\n".join(lines) + "\n"


@pytest.mark.parametrize("kind,words", [
    ("bomb", "aliases"),
    ("deep", "nested"),
    ("event_timer", "can.event_timer_ms"),
    ("position_step", "can.position_step_mm"),
    ("max_gap", "estimator.max_gap_s"),
])
def test_hostile_configs_exit_2_with_one_line(cfg_raw, tmp_path, kind, words) -> None:
    path = tmp_path / f"{kind}.yaml"
    if kind == "bomb":
        path.write_text(_bomb())
    elif kind == "deep":
        path.write_text("oil: " + "[" * 20000 + "]" * 20000 + "\n")
    else:
        key, value = {"event_timer": ("can.event_timer_ms", 65535.0),
                      "position_step": ("can.position_step_mm", 1e-12),
                      "max_gap": ("estimator.max_gap_s", 1e300)}[kind]
        data = json.loads(json.dumps(cfg_raw))
        section, name = key.split(".")
        data[section][name] = value
        path.write_text(yaml.safe_dump(data))
    proc = subprocess.run([sys.executable, "-m", "ddh_vsensor.cli.main", "run", "--config",
                           str(path), "--no-state", "--interface", "virtual"],
                          capture_output=True, text=True, timeout=60)
    assert proc.returncode == 2, proc.stderr[-2000:]
    assert "Traceback" not in proc.stderr
    lines = [line for line in proc.stderr.splitlines() if line.strip()]
    assert len(lines) == 1 and len(lines[0]) < 400 and words in lines[0], proc.stderr[-2000:]


def test_signals_save_and_never_kill_silently(cfg, cfg_raw, hub, tmp_path) -> None:
    state_dir = tmp_path / "state"
    daemon = start_daemon(hub, tmp_path, cfg_raw, state_dir=state_dir,
                          overrides={"estimator.state_save_interval_s": 3600.0})
    saved = state_dir / "boom.json"
    try:
        for sig in (signal.SIGHUP, signal.SIGUSR1, signal.SIGUSR2):
            before = saved.stat().st_mtime_ns if saved.exists() else 0
            daemon.send_signal(sig)
            # a bound on "never saved", not on speed: a loaded machine's disk can take seconds
            end = time.monotonic() + STARTUP_TIMEOUT_S
            while time.monotonic() < end and (not saved.exists()
                                              or saved.stat().st_mtime_ns == before):
                time.sleep(0.05)
            assert daemon.proc.poll() is None, daemon.log()[-2000:]
            assert saved.exists() and saved.stat().st_mtime_ns != before
            assert json.loads(saved.read_text())["clean"] is False   # still running
            assert f"{sig.name} received: configuration not reloaded" in daemon.log()
    finally:
        code = daemon.stop(signal.SIGINT)
    assert code == 0
    assert json.loads(saved.read_text())["clean"] is True
    assert "Traceback" not in daemon.log()
