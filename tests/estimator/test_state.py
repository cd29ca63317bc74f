"""Persisted estimate: round trip, corrupt or foreign files ignored, power cut mid-write."""

import json
import logging
import os

import pytest

from ddh_vsensor.estimator.estimator import Estimator
from ddh_vsensor.estimator.state import EstimatorState, load_state, save_state


def _state(**kw):
    base = dict(actuator="boom", config_hash="abc", position_mm=123.4, uncertainty_mm=1.5,
                gain_up=1.01, gain_down=0.99)
    base.update(kw)
    return EstimatorState(**base)


def test_round_trip(tmp_path):
    save_state(tmp_path / "boom.json", _state(learned={"compliance": 0.1, "compliance_var": 0.01}))
    back = load_state(tmp_path / "boom.json", "boom", "abc")
    assert back is not None and back.position_mm == 123.4 and back.gain_down == 0.99
    assert back.learned == {"compliance": 0.1, "compliance_var": 0.01}
    assert not [p for p in tmp_path.iterdir() if p.name.startswith(".")]   # no temp files


@pytest.mark.parametrize("content", ["", "{not json", json.dumps({"actuator": "boom"}),
                                     json.dumps({**_state().__dict__, "position_mm": "NaN"}),
                                     json.dumps({**_state().__dict__, "position_mm": float("nan")}),
                                     json.dumps({**_state().__dict__, "learned": {"a": "1"}}),
                                     json.dumps({**_state().__dict__, "learned": [1.0]}),
                                     json.dumps({**_state().__dict__,
                                                 "learned": {str(i): 1.0 for i in range(200)}})])
def test_corrupt_files_are_reported_and_ignored(tmp_path, caplog, content):
    path = tmp_path / "boom.json"
    path.write_text(content)
    with caplog.at_level(logging.WARNING):
        assert load_state(path, "boom", "abc") is None
    assert "ignored" in caplog.text


def test_foreign_state_is_ignored(tmp_path, caplog):
    save_state(tmp_path / "s.json", _state())
    with caplog.at_level(logging.WARNING):
        assert load_state(tmp_path / "s.json", "bucket", "abc") is None
        assert load_state(tmp_path / "s.json", "boom", "other") is None


def test_power_cut_mid_write_leaves_the_old_state(tmp_path, monkeypatch):
    path = tmp_path / "boom.json"
    save_state(path, _state(position_mm=10.0))

    def cut(fd):
        raise OSError("power cut")
    monkeypatch.setattr(os, "fsync", cut)
    with pytest.raises(OSError):
        save_state(path, _state(position_mm=99.0))
    monkeypatch.undo()
    back = load_state(path, "boom", "abc")
    assert back is not None and back.position_mm == 10.0
    assert [p.name for p in tmp_path.iterdir()] == ["boom.json"]


def test_estimator_restart_carries_on(tmp_path, cfg, unit_tables):
    est = Estimator(cfg, "boom", unit_tables["boom"], initial_position_mm=200.0)
    for k in range(100):
        est.step(k * 0.01, 1000.0, 22.0, 27.0)
    save_state(tmp_path / "boom.json", est.snapshot())
    again = Estimator(cfg, "boom", unit_tables["boom"])
    again.restore(load_state(tmp_path / "boom.json", "boom", cfg.physics_hash()))
    assert again.position_mm == pytest.approx(est.position_mm)
    assert again.uncertainty_mm == pytest.approx(est.uncertainty_mm)


@pytest.mark.parametrize("kind", ["symlink", "fifo", "huge", "nested", "negative", "inf",
                                  "bool", "list", "unknown_key", "big_int"])
def test_hostile_files_are_reported_and_ignored(tmp_path, caplog, kind):
    path = tmp_path / "boom.json"
    good = {**_state().__dict__}
    if kind == "symlink":
        path.symlink_to("/dev/zero")
    elif kind == "fifo":
        os.mkfifo(path)                            # would block a plain open()
    elif kind == "huge":
        with open(path, "wb") as fh:
            fh.truncate(300 * 1024 * 1024)         # sparse: no disk used
    elif kind == "nested":
        path.write_text("[" * 200_000 + "]" * 200_000)
    elif kind == "negative":
        path.write_text(json.dumps({**good, "uncertainty_mm": -1000.0}))
    elif kind == "inf":
        path.write_text(json.dumps({**good, "position_mm": float("inf")}))
    elif kind == "bool":
        path.write_text(json.dumps({**good, "position_mm": True}))
    elif kind == "list":
        path.write_text(json.dumps([good]))
    elif kind == "unknown_key":
        path.write_text(json.dumps({**good, "extra": 1}))
    elif kind == "big_int":
        path.write_text(json.dumps({**good, "position_mm": 10 ** 400}))
    with caplog.at_level(logging.WARNING):
        assert load_state(path, "boom", "abc") is None
    assert "corrupt state file ignored" in caplog.text
    assert len(caplog.text) < 1000                 # the reason is truncated


def test_clean_flag_round_trip_and_default(tmp_path):
    save_state(tmp_path / "a.json", _state(clean=True))
    assert load_state(tmp_path / "a.json", "boom", "abc").clean is True
    data = {**_state().__dict__}
    del data["clean"]                              # written before the flag existed
    (tmp_path / "b.json").write_text(json.dumps(data))
    assert load_state(tmp_path / "b.json", "boom", "abc").clean is False


def test_leftover_temp_files_are_removed(tmp_path):
    from ddh_vsensor.atomic import remove_temp_files
    path = tmp_path / "boom.json"
    left = tmp_path / ".boom.json.0123abcd.tmp"
    left.write_text("{half")
    other = tmp_path / ".bucket.json.0123abcd.tmp"
    other.write_text("{")
    assert remove_temp_files(path) == [left]
    assert not left.exists() and other.exists()
