"""Each emulated sensor's EDS: the packaged CiA 406 template with one unit's configured values.

The template (``data/cia406_position_sensor.eds``) describes the device type; a master that
commissions one unit's sensor needs that unit's values: the measuring step, the stroke as the
measuring range, the TPDO1 event timer, whether the EMCY producer is valid at boot, the
identity (0x1018 vendor ID, product code, revision, serial number; 0x1008 device name) and the
consumer heartbeat time 0x1016 of the unit's motor controller. These are the settings the
service's node stores from the configuration; everything else keeps the template's default.

An EDS leaves the node ID to the master (COB-IDs stay ``$NODEID+...``, no
``[DeviceComissioning]``, CiA 306); the DCF of a unit (``.dcf``) is the same file with the
node ID in ``[DeviceComissioning]``, so ``canopen.import_od(path)`` resolves the COB-IDs.
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


def _set_default(var: ODVariable, value: int, node_id: int | None = None,
                 hex_digits: int = 0) -> None:
    """A new default; relative to ``$NODEID`` (as the template writes COB-IDs) if node_id,
    in hex with ``hex_digits`` digits if given (identities, packed fields)."""
    var.default = value
    var.default_raw = (f"$NODEID+0x{value - node_id:X}" if node_id is not None
                       else f"0x{value:0{hex_digits}X}" if hex_digits else str(value))


def consumer_heartbeat(cfg: Config, unit: str, timeout_s: float | None = None) -> int:
    """0x1016 sub 1 of ``unit``'s sensor: the configured controller's node ID (bits 16..23)
    and the consumer time in ms (``timeout_s``, default ``faults.heartbeat_timeout_s``); 0 when
    no controller heartbeat is consumed."""
    node_id = cfg.faults.heartbeat_node_ids.get(unit)
    if node_id is None:
        return 0
    time_s = cfg.faults.heartbeat_timeout_s if timeout_s is None else timeout_s
    return node_id << 16 | min(max(round(time_s * 1000.0), 1), 0xFFFF)


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
    can = cfg.can
    identity = (can.vendor_id, can.product_code, can.revision_number, can.serial_number(unit))
    for sub, value in enumerate(identity, 1):
        _set_default(od[0x1018][sub], value, hex_digits=8)
    info = od.device_information
    info.vendor_number, info.product_number, info.revision_number = identity[:3]
    od[0x1008].default = od[0x1008].default_raw = f"{can.device_name} {unit}"
    consumer = consumer_heartbeat(cfg, unit)
    _set_default(od[0x1016][1], consumer, hex_digits=8)
    od.comments = "\n".join([
        f"Unit {unit}: sensor node {node_id}, stroke {cfg.unit(unit).stroke_mm:g} mm, "
        f"measuring step {step_mm:g} mm, TPDO1 event timer {od[0x1800][5].default} ms.",
        "NMT: " + ("boots to OPERATIONAL by itself (can.nmt_auto_start)."
                   if cfg.can.nmt_auto_start else
                   "stays PRE-OPERATIONAL until a master starts it (can.nmt_auto_start)."),
        "EMCY producer " + ("valid at boot (can.emcy_enabled)." if cfg.can.emcy_enabled else
                            "not valid at boot: 0x1014 bit 31 set (can.emcy_enabled)."),
        f"Identity 0x1018: vendor ID 0x{identity[0]:08X}, product code 0x{identity[1]:08X}, "
        f"revision 0x{identity[2]:08X}, serial number {identity[3]} (can: section).",
        ("Consumer heartbeat 0x1016: motor controller node "
         f"{consumer >> 16}, {consumer & 0xFFFF} ms (faults.heartbeat_timeout_s)." if consumer
         else "Consumer heartbeat 0x1016: none (faults.heartbeat_node_ids)."),
        od.comments])
    return od


def _template_sections() -> configparser.RawConfigParser:
    parser = configparser.RawConfigParser()
    parser.optionxform = str            # type: ignore[assignment,method-assign]
    parser.read(TEMPLATE_EDS)
    return parser


def write_unit_eds(cfg: Config, unit: str, dest: TextIO, file_name: str) -> None:
    """``unit``'s EDS, written by canopen; the same bytes for the same configuration. A
    ``file_name`` ending in ``.dcf`` gets its DCF: the node ID in ``[DeviceComissioning]``."""
    od = unit_object_dictionary(cfg, unit)
    template = _template_sections()
    # canopen reads Granularity as a flag; the template's bits per mapping step are kept
    od.device_information.granularity = int(template["DeviceInfo"]["Granularity"])
    file_info = {**template["FileInfo"], "FileName": file_name,
                 "Description": f"ddh-vsensor emulated CiA 406 linear position sensor of the "
                                f"{unit}, node {od.node_id}"}
    dcf = file_name.lower().endswith(".dcf")
    canopen_eds.export_eds(od, dest, file_info=file_info, device_commisioning=dcf)
