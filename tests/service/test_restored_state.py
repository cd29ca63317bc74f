"""A restored estimate says no more than the machine allows, and a state file of another
format is reported as what it is."""

from __future__ import annotations

import json
import logging

from ddh_vsensor.estimator.state import (
    STATE_FORMAT,
    EstimatorState,
    load_state,
    save_state,
)
from ddh_vsensor.service import Service, ServiceOptions

from .conftest import channel_name


def test_a_restored_uncertainty_beyond_the_stroke_is_the_stroke(cfg, unit_tables,
                                                                tmp_path) -> None:
    stroke = cfg.unit("boom").stroke_mm
    save_state(tmp_path / "boom.json", EstimatorState("boom", cfg.physics_hash(), 100.0,
                                                      stroke + 4.0, clean=True))
    service = Service(cfg, unit_tables, {"interface": "virtual", "channel": channel_name()},
                      ServiceOptions(state_dir=tmp_path))
    assert service.units["boom"].estimator.uncertainty_mm == stroke
    assert service.published(service.units["boom"]).uncertainty_mm <= stroke


def test_a_state_format_given_as_text_is_named_as_text(cfg, tmp_path, caplog) -> None:
    path = tmp_path / "boom.json"
    save_state(path, EstimatorState("boom", cfg.physics_hash(), 100.0, 1.0))
    data = json.loads(path.read_text())
    data["format"] = str(STATE_FORMAT)
    path.write_text(json.dumps(data))
    with caplog.at_level(logging.WARNING):
        assert load_state(path, "boom", cfg.physics_hash()) is None
    assert f"state format '{STATE_FORMAT}', expected {STATE_FORMAT}" in caplog.text
