"""Each emulated sensor's EDS: the packaged CiA 406 template with one unit's configured values.

The template (``data/cia406_position_sensor.eds``) describes the device type; a master that
commissions one unit's sensor needs that unit's values: its node ID (written as the
``[DeviceComissioning]`` NodeID, so ``canopen.import_od(path)`` resolves every ``$NODEID``
COB-ID by itself), the measuring step, the stroke as the measuring range, the TPDO1 event timer
and whether the EMCY producer is valid at boot. These are the settings the service's node
stores from the configuration; everything else keeps the template's default.
"""

from __future__ import annotations

import configparser
from pathlib import Path
from typing import TextIO

import canopen
from canopen.objectdictionary import ODVariable, ObjectDictionary
from canopen.objectdictionary import eds as canopen_eds

from ddh_vsensor.config import Config

TEMPLATE_EDS = Path(__file__).resolve().parent.parent / "data" / "cia406_position_sensor.eds"

NANOMETRES_PER_MM = 1_000_000       # 0x6005 sub 1 counts the measuring step in nm
COB_ID_INVALID = 1 << 31            # COB-ID bit 31: the producer is not valid


def template_od(node_id: int | None = None) -> ObjectDictionary:
    """The template's object dictionary (its defaults: diag and heartbeat timers, inhibit)."""
    return canopen.import_od(str(TEMPLATE_EDS), node_id)


def _set_default(var: ODVariable, value: int, node_id: int | None = None) -> None:
    """A new default; relative to ``$NODEID`` (as the template writes COB-IDs) if node_id."""
    var.default = value
    var.default_raw = (f"$NODEID+0x{value - node_id:X}" if node_id is not None
                       else str(value))


def unit_object_dictionary(cfg: Config, unit: str) -> ObjectDictionary:
    """The object dictionary of ``unit``'s emulated sensor, as the service's node starts it."""
    cfg.require_unit(unit)
    can_unit = cfg.can.units[unit]
    node_id = can_unit.sensor_node_id
    od = template_od(node_id)
    od.node_id = node_id
    step_mm = cfg.can.position_step_mm
    step_nm = round(step_mm * NANOMETRES_PER_MM)
    _set_default(od[0x6005][1], step_nm)
    _set_default(od[0x6501], step_nm)
    _set_default(od[0x650A][3], round(cfg.unit(unit).stroke_mm / step_mm))
    _set_default(od[0x1800][5], max(1, round(cfg.can.event_timer_ms)))
    _set_default(od[0x6200], od[0x1800][5].default)       # CiA 406: the same timer
    emcy = 0x80 + node_id | (0 if cfg.can.emcy_enabled else COB_ID_INVALID)
    _set_default(od[0x1014], emcy, node_id)
    od.comments = "\n".join([
        f"Unit {unit}: sensor node {node_id}, stroke {cfg.unit(unit).stroke_mm:g} mm, "
        f"measuring step {step_mm:g} mm, TPDO1 event timer {od[0x1800][5].default} ms.",
        "NMT: " + ("boots to OPERATIONAL by itself (can.nmt_auto_start)."
                   if cfg.can.nmt_auto_start else
                   "stays PRE-OPERATIONAL until a master starts it (can.nmt_auto_start)."),
        "EMCY producer " + ("valid at boot (can.emcy_enabled)." if cfg.can.emcy_enabled else
                            "not valid at boot: 0x1014 bit 31 set (can.emcy_enabled)."),
        od.comments])
    return od


def _template_sections() -> configparser.RawConfigParser:
    parser = configparser.RawConfigParser()
    parser.optionxform = str            # type: ignore[assignment,method-assign]
    parser.read(TEMPLATE_EDS)
    return parser


def write_unit_eds(cfg: Config, unit: str, dest: TextIO, file_name: str) -> None:
    """``unit``'s EDS, written by canopen; the same bytes for the same configuration."""
    od = unit_object_dictionary(cfg, unit)
    template = _template_sections()
    # canopen reads Granularity as a flag; the template's bits per mapping step are kept
    od.device_information.granularity = int(template["DeviceInfo"]["Granularity"])
    file_info = {**template["FileInfo"], "FileName": file_name,
                 "Description": f"ddh-vsensor emulated CiA 406 linear position sensor of the "
                                f"{unit}, node {od.node_id}"}
    # device_commisioning: the node ID goes into the file (export_od leaves it out)
    canopen_eds.export_eds(od, dest, file_info=file_info, device_commisioning=True)
