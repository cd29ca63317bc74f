"""Machines other than the reference loader, built from its YAML: renamed, more units, more
Hall inputs, a second bus."""

from __future__ import annotations

import copy
from pathlib import Path
from typing import Any

import pytest
import yaml

from ddh_vsensor.config import Config, parse_config

REPO = Path(__file__).resolve().parents[2]


def loader_data() -> dict[str, Any]:
    return yaml.safe_load((REPO / "config" / "loader.yaml").read_text())


def machine(units: dict[str, tuple[str, dict[str, Any]]], source: str,
            buses: dict[str, dict[str, Any]] | None = None) -> Config:
    """The loader with these units: name -> (loader unit it copies, its can.units entry)."""
    data = loader_data()
    data.pop("work_cycle")          # the loader's cycles name its own units
    data["units"] = {name: copy.deepcopy(data["units"][like])
                     for name, (like, _) in units.items()}
    data["can"]["units"] = {name: can for name, (_, can) in units.items()}
    data["faults"]["heartbeat_node_ids"] = {name: can["sevcon_node_id"]
                                            for name, (_, can) in units.items()}
    if buses:
        data["buses"] = buses
    return parse_config(data, source)


@pytest.fixture(scope="session")
def three_units() -> Config:
    """lift and tilt where the loader has boom and bucket, and an arm on a second bus whose
    switches are on the I/O module's second input byte."""
    return machine({
        "lift": ("boom", {"sevcon_node_id": 1, "sensor_node_id": 49,
                          "hall_bits": {"bottom": 0, "mid": 1, "top": 2}}),
        "tilt": ("bucket", {"sevcon_node_id": 2, "sensor_node_id": 50,
                            "hall_bits": {"bottom": 3, "mid": 4, "top": 5}}),
        "arm": ("boom", {"sevcon_node_id": 3, "sensor_node_id": 51, "bus": "can1",
                         "hall_bits": {"bottom": 8, "mid": 9, "top": 10}}),
    }, "three.yaml", buses={"can1": {"interface": "virtual", "channel": "arm"}})


@pytest.fixture(scope="session")
def wide_inputs() -> Config:
    """One unit whose switches sit on the I/O module's first, fourth and last input bit."""
    return machine({"ram": ("bucket", {"sevcon_node_id": 7, "sensor_node_id": 70,
                                       "hall_bits": {"bottom": 0, "mid": 31, "top": 63}})},
                   "bench.yaml")
