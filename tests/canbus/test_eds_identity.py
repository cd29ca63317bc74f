"""A unit's EDS and DCF as a master's configurator loads them: no node ID in the EDS (CiA 306
keeps [DeviceComissioning] for the DCF), the identity, device name and consumer heartbeat
time from the configuration."""

from __future__ import annotations

import configparser
import dataclasses
from pathlib import Path

import canopen

from ddh_vsensor.canbus.eds import write_unit_eds
from ddh_vsensor.config import Config


def _generated(cfg: Config, unit: str, tmp_path: Path, suffix: str = ".eds") -> Path:
    path = tmp_path / f"{unit}{suffix}"
    with open(path, "w", encoding="utf-8") as fh:
        write_unit_eds(cfg, unit, fh, path.name)
    return path


def test_a_unit_s_dcf_carries_its_node_id(cfg: Config, tmp_path: Path) -> None:
    """The DCF is the EDS with the node ID commissioned: canopen resolves the COB-IDs."""
    path = _generated(cfg, "bucket", tmp_path, ".dcf")
    assert "[DeviceComissioning]" in path.read_text()
    od = canopen.import_od(str(path))
    assert od.node_id == 50 and od[0x1800][1].default == 0x4000_0000 | 0x1B2


def test_identity_name_and_consumer_heartbeat_follow_the_configuration(
        cfg: Config, tmp_path: Path) -> None:
    units = {**cfg.can.units, "bucket": dataclasses.replace(cfg.can.units["bucket"],
                                                            serial_number=7000)}
    other = dataclasses.replace(cfg, can=dataclasses.replace(
        cfg.can, vendor_id=0x1234, product_code=0x406_0001, revision_number=0x20003,
        serial_number_base=500, device_name="loader sensor", units=units),
        faults=dataclasses.replace(cfg.faults, heartbeat_timeout_s=0.25))
    for unit, serial in (("boom", 500), ("bucket", 7000)):
        path = _generated(other, unit, tmp_path)
        od = canopen.import_od(str(path), other.can.units[unit].sensor_node_id)
        assert [od[0x1018][s].default for s in (1, 2, 3, 4)] == \
            [0x1234, 0x406_0001, 0x20003, serial]
        assert od[0x1008].default == f"loader sensor {unit}"
        controller = other.faults.heartbeat_node_ids[unit]
        assert od[0x1016][1].default == controller << 16 | 250
        info = configparser.ConfigParser()
        info.read(path)
        assert int(info["DeviceInfo"]["VendorNumber"], 0) == 0x1234
