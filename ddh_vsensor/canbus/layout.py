"""The machine's CAN frames as a cantools database, generated from the configuration.

Every frame ID is a CANopen function code plus a configured node ID (0x080 EMCY, 0x180 TPDO1,
0x280 TPDO2, 0x380 TPDO3, 0x580/0x600 SDO, 0x700 heartbeat), message and node names come from
the unit names (``POSITION_<UNIT>_TPDO1``), the I/O module frame is as long as the configured
Hall bits need, with one bit signal per configured switch. The status byte of a position
frame, the flags byte of a diagnostic frame and the active faults of an EMCY are one bit
signal per :class:`~ddh_vsensor.estimator.flags.Flags` member, with value tables for tools.
Cycle times of the sensor's frames are its configured event timer and the template EDS's
defaults. The health frame's cause codes get a value table from the names the caller passes
(``machine_database(cfg, cause_names)``: the diagnosis catalogue's, which this layer does not
import).

Send types are the attribute definitions of Vector's interaction layer (the CANoe IL DBC
template), so an IL or a restbus simulation sends the frames as the machine does: every
periodic frame ``GenMsgSendType`` "Cyclic" with its ``GenMsgCycleTime`` (ms), every event frame
(EMCY, SDO, NMT, SYNC) "NoMsgSendType". The I/O module's frame goes out on a change of state
and on its event timer as refresh: "Cyclic" at the refresh, its switch signals
``GenSigSendType`` "OnChange".
``ddh-vsensor dbc`` writes this database as a DBC; ``dbc/ddh_vsensor.dbc`` is the one of the
reference loader.
"""

from __future__ import annotations

import re
from collections import OrderedDict
from collections.abc import Iterator, Sequence
from pathlib import Path

from cantools.database.can import Bus, Database, Message, Node, Signal
from cantools.database.can.formats.dbc import (DbcAttribute, DbcAttributeDefinition,
                                               DbcSpecifics)
from cantools.database.conversion import BaseConversion

from ddh_vsensor.config import Config, ConfigError
from ddh_vsensor.estimator.flags import Flags
from ddh_vsensor.canbus.eds import template_od

VERSION = "ddh-vsensor 2"

OIL_TEMP = "OIL_TEMP_TPDO1"
IO_MODULE = "IO_MODULE_TPDO1"
NMT_COMMAND = "NMT_COMMAND"
SYNC = "SYNC"
# kind -> (message name pattern, CANopen function code, which node ID: Sevcon or sensor)
_PER_UNIT = {
    "sevcon": ("SEVCON_{}_TPDO1", 0x180, "sevcon"),
    "heartbeat": ("SEVCON_{}_HEARTBEAT", 0x700, "sevcon"),
    "position": ("POSITION_{}_TPDO1", 0x180, "sensor"),
    "diag": ("DIAG_{}_TPDO2", 0x280, "sensor"),
    "health": ("HEALTH_{}_TPDO3", 0x380, "sensor"),
    "sensor_heartbeat": ("SENSOR_{}_HEARTBEAT", 0x700, "sensor"),
    "emcy": ("SENSOR_{}_EMCY", 0x080, "sensor"),
    "sdo_tx": ("SENSOR_{}_SDO_TX", 0x580, "sensor"),
    "sdo_rx": ("SENSOR_{}_SDO_RX", 0x600, "sensor"),
}
KINDS = tuple(_PER_UNIT)

# DBC nodes
DAEMON, NMT_MASTER, SDO_CLIENT = "DDH_VSENSOR", "NMT_MASTER", "SDO_CLIENT"
OIL_TEMP_SENSOR, IO_NODE = "OIL_TEMP_SENSOR", "IO_MODULE"

# What the frames the daemon reads are known to carry (one known setup, the simulated logs).
SEVCON_TPDO_MS, SEVCON_HEARTBEAT_MS, OIL_TEMP_MS = 10, 100, 10
IO_MODULE_MS = 100      # the I/O module's refresh (event timer; ddh_vsensor.io.log's logs)

# Vector interaction layer: GenMsgSendType's enum as its DBC template defines it (index 0
# "Cyclic", 7 "IfActive", 8 "NoMsgSendType"; the others unused), GenSigSendType's.
MSG_SEND_TYPES = ("Cyclic", "not_used", "not_used", "not_used", "not_used", "Cyclic",
                  "not_used", "IfActive", "NoMsgSendType")
SEND_TYPES = ("Cyclic", "NoMsgSendType")            # the ones this layout uses
SIG_SEND_TYPES = ("Cyclic", "OnWrite", "OnWriteWithRepetition", "OnChange",
                  "OnChangeWithRepetition", "IfActive", "IfActiveWithRepetition",
                  "NoSigSendType")
_CYCLE_TIME = DbcAttributeDefinition("GenMsgCycleTime", default_value=0, kind="BO_",
                                     type_name="INT", minimum=0, maximum=65535)
_SEND_TYPE = DbcAttributeDefinition("GenMsgSendType", default_value="NoMsgSendType",
                                    kind="BO_", type_name="ENUM", choices=list(MSG_SEND_TYPES))
_SIG_SEND_TYPE = DbcAttributeDefinition("GenSigSendType", default_value="Cyclic", kind="SG_",
                                        type_name="ENUM", choices=list(SIG_SEND_TYPES))

NMT_STATES = {0: "BootUp", 4: "Stopped", 5: "Operational", 127: "PreOperational"}
NMT_COMMANDS = {1: "StartRemoteNode", 2: "StopRemoteNode", 128: "EnterPreOperational",
                129: "ResetNode", 130: "ResetCommunication"}
# Fault flag -> (EMCY error code, its name): the flags the sensor reports by EMCY.
EMCY_CODES = {Flags.STALE_INPUT: (0x8100, "InputStale"),
              Flags.CONTROLLER_NOT_OPERATIONAL: (0x8130, "ControllerHeartbeat"),
              Flags.NOT_REFERENCED: (0xFF02, "NotReferenced"),
              Flags.TABLE_CLAMPED: (0xFF10, "TableClamped"),
              Flags.PRESET_UNCONFIRMED: (0xFF20, "PresetUnconfirmed")}
# The unit's health alarm (no flag): a warning, maintenance due (0x2010 sub 2 bit 0).
MAINTENANCE_EMCY = (0xFF30, "MaintenanceDue")
SDO_ABORTS = {0x05030000: "ToggleBitNotAlternated", 0x05040001: "CommandSpecifierInvalid",
              0x06010000: "UnsupportedAccess", 0x06010002: "ReadOnly",
              0x06020000: "ObjectDoesNotExist", 0x06040041: "NotMappable",
              0x06040042: "MappingTooLong", 0x06070012: "LengthTooHigh",
              0x06090011: "SubIndexDoesNotExist", 0x06090030: "ValueRangeExceeded",
              0x06090036: "MaxBelowMin", 0x08000024: "NoDataAvailable"}
# Flag -> (what it means, value table names for 0 and 1)
_FLAG_TEXT = {
    Flags.STALE_INPUT: ("input stale: no Sevcon frame integrated recently, no oil temperature "
                        "yet, or controller not operational", ("Fresh", "Stale")),
    Flags.NOT_REFERENCED: ("not referenced since start (no Hall switch edge or preset yet)",
                           ("Referenced", "NotReferenced")),
    Flags.AT_SOFT_LIMIT: ("position at a soft limit (stroke end)", ("InRange", "AtSoftLimit")),
    Flags.ADAPTING: ("the gain adaptation is active", ("NotAdapting", "Adapting")),
    Flags.TABLE_CLAMPED: ("the operating point left the tables (clamped)",
                          ("InTable", "Clamped")),
    Flags.PRESET_UNCONFIRMED: ("position set by a preset, not yet confirmed by a reference "
                               "switch", ("Confirmed", "Unconfirmed")),
    Flags.CONTROLLER_NOT_OPERATIONAL: ("the motor controller's heartbeat says it is not "
                                       "operational", ("Operational", "NotOperational")),
    Flags.MODEL_INCONSISTENT: ("the Kalman filter's innovations fail its self-check: its model "
                               "does not explain the machine (uncertainty widened)",
                               ("Consistent", "Inconsistent")),
}
_ERROR_REGISTER = (("Generic", "generic error (any fault)"), ("Current", "current"),
                   ("Voltage", "voltage"), ("Temperature", "temperature"),
                   ("Communication", "communication (inputs stale, controller heartbeat)"),
                   ("Profile", "device profile specific"), ("Reserved", "reserved, 0"),
                   ("Manufacturer", "manufacturer specific (not referenced, table clamped, "
                                    "preset unconfirmed, maintenance due)"))
_SDO_FIELDS = (("Command", 0, 8, "SDO command specifier byte (CiA 301)."),
               ("Index", 8, 16, "Object index (initiate and abort frames)."),
               ("SubIndex", 24, 8, "Object sub-index (initiate and abort frames)."),
               ("Data", 32, 32, "Expedited data, data size or abort code (initiate and abort "
                                "frames)."))


def camel(name: str) -> str:
    """``stale_input`` -> ``StaleInput``: a DBC signal name part from a flag, unit or switch."""
    return "".join(word.capitalize() for word in re.split(r"[^0-9A-Za-z]+", name) if word)


def flag_signal(prefix: str, flag: Flags) -> str:
    """The bit signal of one flag: ``Status``/``Flag``/``Active`` + ``StaleInput`` etc."""
    return prefix + camel(flag.name or "")


def message_name(kind: str, unit: str) -> str:
    """DBC name of a per-unit frame; kind is one of :data:`KINDS` (sevcon, position, ...)."""
    if kind not in _PER_UNIT:
        raise ValueError(f"unknown frame kind {kind!r} (known: {', '.join(_PER_UNIT)})")
    return _PER_UNIT[kind][0].format(unit.upper())


def all_message_names(units: Sequence[str]) -> list[str]:
    """Every message of a machine with these units."""
    return [message_name(kind, u) for u in units for kind in _PER_UNIT] + [
        OIL_TEMP, IO_MODULE, NMT_COMMAND, SYNC]


def sevcon_node(unit: str) -> str:
    """DBC node name of ``unit``'s motor controller."""
    return f"SEVCON_{unit.upper()}"


def _number(value: float) -> float:
    """A signal bound as the DBC writes it: integral values without a fraction, no float
    noise (32767 * 0.1 is 3276.7000000000003)."""
    return int(value) if float(value).is_integer() else round(value, 10)


def _signal(name: str, start: int, length: int, comment: str, *, signed: bool = False,
            scale: float = 1, minimum: float | None = None, maximum: float | None = None,
            unit: str | None = None, choices: dict[int, str] | None = None,
            receivers: Sequence[str] = (), send_type: str | None = None) -> Signal:
    """A little-endian signal; its range is the raw range times the scale unless given;
    ``send_type``: its GenSigSendType if not the default ("Cyclic")."""
    raw_min, raw_max = ((-(1 << (length - 1)), (1 << (length - 1)) - 1) if signed
                        else (0, (1 << length) - 1))
    conversion = BaseConversion.factory(
        scale=_number(scale), offset=0,
        choices=OrderedDict(sorted(choices.items())) if choices else None)
    return Signal(name, start, length, "little_endian", signed, conversion=conversion,
                  minimum=_number(raw_min * scale if minimum is None else minimum),
                  maximum=_number(raw_max * scale if maximum is None else maximum),
                  unit=unit, comment=comment, receivers=list(receivers),
                  dbc_specifics=None if send_type is None else DbcSpecifics(
                      attributes=OrderedDict(GenSigSendType=DbcAttribute(
                          SIG_SEND_TYPES.index(send_type), _SIG_SEND_TYPE))))


def _message(frame_id: int, name: str, length: int, signals: list[Signal], comment: str,
             sender: str, send_type: str, cycle_time_ms: int | None = None) -> Message:
    attributes: OrderedDict[str, DbcAttribute] = OrderedDict()
    if cycle_time_ms is not None:
        attributes["GenMsgCycleTime"] = DbcAttribute(cycle_time_ms, _CYCLE_TIME)
    attributes["GenMsgSendType"] = DbcAttribute(MSG_SEND_TYPES.index(send_type), _SEND_TYPE)
    return Message(frame_id, name, length, signals, comment=comment, senders=[sender],
                   send_type=send_type, cycle_time=cycle_time_ms,
                   dbc_specifics=DbcSpecifics(attributes=attributes))


def _flag_bits(prefix: str, start: int, what: str, *, with_choices: bool) -> list[Signal]:
    """One bit signal per flag (every Flags member has its text): the byte's eight bits."""
    signals = []
    for flag in Flags:
        text, names = _FLAG_TEXT[flag]
        bit = flag.bit_length() - 1
        signals.append(_signal(flag_signal(prefix, flag), start + bit, 1,
                               what.format(bit=bit, text=text),
                               choices=dict(enumerate(names)) if with_choices else None))
    return signals


def _nmt_state(comment: str, receivers: Sequence[str] = ()) -> Signal:
    return _signal("NmtState", 0, 8, comment, maximum=127, choices=NMT_STATES,
                   receivers=receivers)


def _and_list(items: Sequence[object]) -> str:
    """'49', '49 and 50', '49, 50 and 51'."""
    words = [str(i) for i in items]
    return words[0] if len(words) == 1 else f"{', '.join(words[:-1])} and {words[-1]}"


class _Ids:
    """Frame IDs handed out once each: a second owner is the configuration's mistake."""

    def __init__(self, cfg: Config) -> None:
        self.cfg = cfg
        self.owner: dict[int, str] = {}

    def take(self, name: str, function_code: int, node_id: int, key: str) -> int:
        frame_id = function_code + node_id
        if frame_id in self.owner:
            raise ConfigError(self.cfg.source, key, f"node {node_id} puts {name} on frame ID "
                              f"0x{frame_id:03X}, already used by {self.owner[frame_id]}")
        self.owner[frame_id] = name
        return frame_id


def _hall_signals(cfg: Config) -> tuple[int, list[Signal]]:
    """The I/O module frame's length (bytes) and one bit signal per configured switch."""
    wired: dict[int, tuple[str, str]] = {}
    for unit in cfg.unit_names:
        for ref, bit in cfg.can.units[unit].hall_bits.items():
            if bit in wired:
                raise ConfigError(cfg.source, f"can.units.{unit}.hall_bits.{ref}",
                                  f"input bit {bit} is already wired to "
                                  f"{'.'.join(wired[bit])}")
            wired[bit] = (unit, ref)
    signals = [_signal(f"Hall{camel(unit)}{camel(ref)}", bit, 1,
                       f"{unit.capitalize()} {ref} Hall switch, input bit {bit % 8} of 0x6000 "
                       f"sub {bit // 8 + 1}; 1 = switch on.", receivers=[DAEMON],
                       send_type="OnChange")
               for bit, (unit, ref) in sorted(wired.items())]
    length = max(wired, default=0) // 8 + 1
    return length, signals


def _unit_input_messages(cfg: Config, unit: str, ids: _Ids) -> tuple[Message, Message]:
    """The Sevcon TPDO1 and heartbeat of ``unit``'s motor controller."""
    node_id = cfg.can.units[unit].sevcon_node_id
    key = f"can.units.{unit}.sevcon_node_id"
    sender = sevcon_node(unit)
    tpdo = _message(
        ids.take(message_name("sevcon", unit), 0x180, node_id, key), message_name("sevcon", unit),
        6, [_signal("TorqueActual", 0, 16, "Motor torque actual, Sevcon object 0x4602 sub 0x0C, "
                    "INTEGER16, 1/16 Nm.", signed=True, scale=0.0625, unit="Nm",
                    receivers=[DAEMON]),
            _signal("VelocityActual", 16, 32, "Motor velocity actual, CiA 402 object 0x606C, "
                    "INTEGER32, rpm.", signed=True, unit="rpm", receivers=[DAEMON])],
        f"Sevcon {unit} TPDO1 (0x180 + node {node_id}), project mapping: 0x4602 sub 0x0C "
        f"torque actual, 0x606C velocity actual; event timer {SEVCON_TPDO_MS} ms (one known "
        f"setup).", sender, "Cyclic", SEVCON_TPDO_MS)
    heartbeat = _message(
        ids.take(message_name("heartbeat", unit), 0x700, node_id, key),
        message_name("heartbeat", unit), 1,
        [_nmt_state("NMT state of the producer (CiA 301 heartbeat byte).", [DAEMON])],
        f"Sevcon {unit} heartbeat (0x700 + node {node_id}), CiA 301 NMT error control; producer "
        f"time as configured in the controller ({SEVCON_HEARTBEAT_MS} ms in the simulated "
        f"logs).", sender, "Cyclic", SEVCON_HEARTBEAT_MS)
    return tpdo, heartbeat


def _health_message(cfg: Config, unit: str, frame_id: int, node_id: int, timer_ms: int,
                    cause_names: Sequence[str]) -> Message:
    """TPDO3: the unit's health, 0x2010 sub 1..5 (the template EDS's mapping)."""
    status = (("Alarm", "the expected error passes the tolerance within the horizon "
               "(EMCY FF30 while it lasts)", ("NoAlarm", "MaintenanceDue")),
              ("FewDays", "too few days of evidence for a trend", ("Enough", "TooFewDays")),
              ("NotYet", "no health computed yet", ("Computed", "NotYet")))
    unknown = {0xFFFF: "Unknown"}
    return _message(
        frame_id, message_name("health", unit), 8,
        [_signal("CauseCode", 0, 8, "The cause the unit's recent days point to, manufacturer "
                 "object 0x2010 sub 1, UNSIGNED8: 0 none, else its number in the diagnosis "
                 "catalogue (value table).",
                 choices={code: camel(name) for code, name in enumerate(cause_names)} or None),
         *[_signal(f"Health{name}", 8 + bit, 1, f"Health status 0x2010 sub 2 bit {bit}: "
                   f"{text}.", choices=dict(enumerate(names)))
           for bit, (name, text, names) in enumerate(status)],
         _signal("HealthReserved", 11, 5, "Health status 0x2010 sub 2 bits 3..7: reserved, 0."),
         _signal("ErrorNow", 16, 16, "Expected position error at the references now, "
                 "manufacturer object 0x2010 sub 3, UNSIGNED16, 0.01 mm; 0xFFFF unknown.",
                 scale=0.01, unit="mm", choices=unknown),
         _signal("ErrorAtHorizon", 32, 16, "Expected position error at the references at the "
                 f"horizon (health.horizon_days, {cfg.health.horizon_days:g} days), "
                 "manufacturer object 0x2010 sub 4, UNSIGNED16, 0.01 mm; 0xFFFF unknown.",
                 scale=0.01, unit="mm", choices=unknown),
         _signal("DaysToTolerance", 48, 16, "Days until the expected error passes the "
                 f"tolerance (health.tolerance_mm, {cfg.health.tolerance_mm:g} mm), "
                 "manufacturer object 0x2010 sub 5, UNSIGNED16, 0.1 day; 0xFFFF not within the "
                 "horizon.", scale=0.1, unit="d", choices={0xFFFF: "NotWithinHorizon"})],
        f"Health of the {unit} unit from the daemon's day summaries, TPDO3 (0x380 + node "
        f"{node_id}), event timer 0x1802 sub 5 ({timer_ms} ms), sent in the tick of a TPDO1. "
        f"0x2010 sub 6..9 (days of evidence, the cause's parameter and its interval) are read "
        f"over SDO. No RTR.", DAEMON, "Cyclic", timer_ms)


def _sensor_messages(cfg: Config, unit: str, ids: _Ids, timers_ms: dict[str, int],
                     cause_names: Sequence[str]) -> Iterator[Message]:
    """The frames of ``unit``'s emulated CiA 406 sensor: TPDO1, TPDO2, TPDO3, heartbeat, EMCY,
    SDO."""
    node_id = cfg.can.units[unit].sensor_node_id
    key = f"can.units.{unit}.sensor_node_id"

    def frame_id(kind: str) -> int:
        return ids.take(message_name(kind, unit), _PER_UNIT[kind][1], node_id, key)

    step_mm = cfg.can.position_step_mm
    event_ms = max(1, round(cfg.can.event_timer_ms))
    yield _message(
        frame_id("position"), message_name("position", unit), 7,
        [_signal("Position", 0, 32, "Cylinder position, CiA 406 object 0x6020 sub 1, INTEGER32, "
                 f"measuring step 0x6005 sub 1 ({step_mm:g} mm, can.position_step_mm).",
                 signed=True, scale=step_mm, unit="mm"),
         _signal("Speed", 32, 16, "Cylinder speed, CiA 406 object 0x6030 sub 1, INTEGER16, "
                 "0.1 mm/s (0x6005 sub 2).", signed=True, scale=0.1, unit="mm/s"),
         *_flag_bits("Status", 48, "Status 0x2000 bit {bit}: {text}.", with_choices=True)],
        f"Emulated CiA 406 linear position sensor of the {unit}, TPDO1 (0x180 + node {node_id}), "
        f"transmission type 254, event timer 0x1800 sub 5 (can.event_timer_ms, {event_ms} ms); "
        f"EDS from `ddh-vsensor eds --unit {unit}`. No RTR (COB-ID bit 30 set).",
        DAEMON, "Cyclic", event_ms)
    yield _message(
        frame_id("diag"), message_name("diag", unit), 8,
        [_signal("Uncertainty", 0, 32, "Estimated position uncertainty, manufacturer object "
                 "0x2001, UNSIGNED32, 0.01 mm (covers any stroke).", scale=0.01, unit="mm"),
         *_flag_bits("Flag", 32, "Flags 0x2002 bit {bit}: {text}.", with_choices=True),
         _signal("RejectedFrames", 40, 8, "Sevcon frames rejected as implausible, manufacturer "
                 "object 0x2004, UNSIGNED8, wraps."),
         _signal("InputFrames", 48, 16, "Sevcon frames received, manufacturer object 0x2003, "
                 "UNSIGNED16, wraps.")],
        f"Diagnostics of the emulated {unit} sensor, TPDO2 (0x280 + node {node_id}), event "
        f"timer 0x1801 sub 5 ({timers_ms['diag']} ms), sent in the tick of a TPDO1. No RTR.",
        DAEMON, "Cyclic", timers_ms["diag"])
    yield _health_message(cfg, unit, frame_id("health"), node_id, timers_ms["health"],
                          cause_names)
    yield _message(
        frame_id("sensor_heartbeat"), message_name("sensor_heartbeat", unit), 1,
        [_nmt_state("NMT state of the sensor node (CiA 301 heartbeat byte).")],
        f"Heartbeat of the emulated {unit} sensor (0x700 + node {node_id}), producer time "
        f"0x1017 ({timers_ms['heartbeat']} ms); NmtState 0 is its boot-up message. Also the "
        f"answer to a node guarding request (RTR on this ID): NmtState plus 128 every second "
        f"answer (the toggle bit).",
        DAEMON, "Cyclic", timers_ms["heartbeat"])
    register = [_signal(f"Register{name}", 16 + bit, 1,
                        f"Error register 0x1001 bit {bit}: {text}.")
                for bit, (name, text) in enumerate(_ERROR_REGISTER)]
    active = _flag_bits("Active", 32, "Fault still active after this EMCY: flag bit {bit}, "
                        "{text}.", with_choices=False)
    yield _message(
        frame_id("emcy"), message_name("emcy", unit), 8,
        [_signal("ErrorCode", 0, 16, "CiA 301 emergency error code; 0 = error reset (one fault "
                 "cleared, the register shows what remains). 8130 with FlagConcerned 0: the "
                 "node's life guarding event (guard requests stopped for 0x100C x 0x100D ms). "
                 "FF30 (FlagConcerned 0): maintenance due, the unit's health alarm (HEALTH "
                 "frame HealthAlarm), a warning.",
                 choices={0: "ErrorReset", **dict(EMCY_CODES.values()),
                          MAINTENANCE_EMCY[0]: MAINTENANCE_EMCY[1]}),
         *register,
         _signal("FlagConcerned", 24, 8, "The status flag (0x2002 bit) that was set or cleared; "
                 "0 in an error reset that only brings the register up to date (a fault came "
                 "and went within the inhibit time), and for the life guarding event and "
                 "maintenance due.",
                 choices={int(f): camel(f.name or "") for f in EMCY_CODES}),
         *active,
         _signal("Reserved", 40, 24, "Manufacturer-specific error field bytes 5..7, 0.")],
        f"EMCY of the emulated {unit} sensor (0x1014: 0x80 + node {node_id}), sent when a fault "
        f"flag is set (its error code) or cleared (error reset), and so for the life guarding "
        f"event and maintenance due, at most one per inhibit time 0x1015 "
        f"({timers_ms['inhibit']} ms), not in STOPPED.", DAEMON, "NoMsgSendType")
    for kind, sender, receivers, text in (
            ("sdo_tx", DAEMON, (), f"SDO server response of the emulated {unit} sensor (0x580 + "
             f"node {node_id}); segment frames carry 7 data bytes after the command byte."),
            ("sdo_rx", SDO_CLIENT, (DAEMON,), f"SDO client request to the emulated {unit} "
             f"sensor (0x600 + node {node_id}); not answered in STOPPED.")):
        yield _message(
            frame_id(kind), message_name(kind, unit), 8,
            [_signal(name, start, length, comment, receivers=receivers,
                     choices=SDO_ABORTS if kind == "sdo_tx" and name == "Data" else None)
             for name, start, length, comment in _SDO_FIELDS], text, sender, "NoMsgSendType")


def _template_timers_ms() -> dict[str, int]:
    """The sensor's timers the configuration leaves at the template EDS's defaults."""
    od = template_od()
    return {"diag": od[0x1801][5].default, "health": od[0x1802][5].default,
            "heartbeat": od[0x1017].default,
            "inhibit": od[0x1015].default // 10}          # 0x1015 counts 100 us


def _comments(cfg: Config) -> tuple[str, dict[str, str]]:
    """The database's comment and each node's."""
    source = Path(cfg.source).name
    text = ("ddh-vsensor: every frame the virtual position sensor reads or writes. CANopen "
            f"layout, little-endian. Generated by `ddh-vsensor dbc` from {source}: each frame ID "
            "is the CANopen function code (0x080 EMCY, 0x180 TPDO1, 0x280 TPDO2, 0x380 TPDO3, "
            "0x580/0x600 SDO, 0x700 heartbeat) plus the node ID configured in its can: section. "
            "Send types as Vector's interaction layer defines them: GenMsgSendType Cyclic "
            "(every GenMsgCycleTime ms) or NoMsgSendType (event frames: EMCY, SDO, NMT, SYNC); "
            "the I/O module frame also goes out on a change of its inputs (GenSigSendType "
            "OnChange).")
    buses = {cfg.can.units[u].bus for u in cfg.unit_names}
    if len(buses) > 1:
        text += " Buses: " + "; ".join(
            f"{bus}: {', '.join(cfg.units_on_bus(bus))}" for bus in cfg.bus_names
            if cfg.units_on_bus(bus)) + "."
    nodes = {sevcon_node(u): f"Sevcon Gen4 motor controller of the {u} unit, CANopen node "
                             f"{cfg.can.units[u].sevcon_node_id}." for u in cfg.unit_names}
    sensor_ids = [cfg.can.units[u].sensor_node_id for u in cfg.unit_names]
    nodes.update({
        OIL_TEMP_SENSOR: f"Hydraulic oil temperature sensor, CANopen node "
                         f"{cfg.can.oil_temp_node_id}.",
        IO_NODE: f"CiA 401 digital input module wired to the Hall-effect reference switches, "
                 f"CANopen node {cfg.can.io_module_node_id}.",
        DAEMON: f"The ddh-vsensor daemon: reads the Sevcon, oil and I/O frames, emulates one "
                f"CiA 406 linear position sensor per unit "
                f"(node{'s' if len(sensor_ids) > 1 else ''} {_and_list(sensor_ids)}).",
        NMT_MASTER: "The CANopen network master, if any (NMT commands, SYNC).",
        SDO_CLIENT: "Any SDO client: a master or a configuration tool."})
    return text, nodes


def machine_database(cfg: Config, cause_names: Sequence[str] = ()) -> Database:
    """Every frame the daemon reads or writes on this machine, as a cantools database.

    ``cause_names``: the health frame's cause codes in order (code 0 first, "none"), as the
    diagnosis catalogue numbers them (``diagnosis.causes.CAUSE_NAMES``), for its value
    table; none given, the codes go without one. Two frames on one ID (node IDs that collide,
    a Hall bit wired twice) are a ConfigError naming the key that sets the second one.
    """
    ids = _Ids(cfg)
    ids.owner[0x000] = NMT_COMMAND
    ids.owner[0x080] = SYNC
    units = cfg.unit_names
    inputs = [_unit_input_messages(cfg, u, ids) for u in units]
    messages = [tpdo for tpdo, _ in inputs] + [hb for _, hb in inputs]
    messages.append(_message(
        ids.take(OIL_TEMP, 0x180, cfg.can.oil_temp_node_id, "can.oil_temp_node_id"), OIL_TEMP, 2,
        [_signal("OilTemp", 0, 16, "Hydraulic oil temperature, INTEGER16, 0.1 degC.",
                 signed=True, scale=0.1, unit="degC", receivers=[DAEMON])],
        f"Oil temperature sensor TPDO1 (0x180 + node {cfg.can.oil_temp_node_id}); "
        f"{OIL_TEMP_MS} ms in the simulated logs.", OIL_TEMP_SENSOR, "Cyclic", OIL_TEMP_MS))
    io_length, hall = _hall_signals(cfg)
    subs = "sub 1" if io_length == 1 else f"sub 1..{io_length}"
    messages.append(_message(
        ids.take(IO_MODULE, 0x180, cfg.can.io_module_node_id, "can.io_module_node_id"),
        IO_MODULE, io_length, hall,
        f"I/O module TPDO1 (0x180 + node {cfg.can.io_module_node_id}): CiA 401 object 0x6000 "
        f"{subs} read input 8-bit, sent on change of state and every {IO_MODULE_MS} ms (event "
        f"timer as refresh, as in the simulated logs). Bit per "
        f"switch is configuration (can.units.*.hall_bits); the signals follow it.",
        IO_NODE, "Cyclic", IO_MODULE_MS))
    messages.append(_message(
        0x000, NMT_COMMAND, 2,
        [_signal("Command", 0, 8, "NMT command specifier.", choices=NMT_COMMANDS,
                 receivers=[DAEMON]),
         _signal("NodeId", 8, 8, "Addressed node, 0 = all nodes.", maximum=127,
                 receivers=[DAEMON])],
        "CiA 301 NMT command (COB-ID 0) from the network master; the sensor nodes act on the "
        "ones addressed to them or to all (node 0).", NMT_MASTER, "NoMsgSendType"))
    messages.append(_message(
        0x080, SYNC, 0, [],
        "CiA 301 SYNC (COB-ID 0x1005 = 0x80) from the network master: the sensor nodes send "
        "the TPDOs a master made synchronous (transmission type 0..240) on it, at the "
        "master's communication cycle period (its configuration, not known here).", NMT_MASTER,
        "NoMsgSendType"))
    timers_ms = _template_timers_ms()
    for unit in units:
        messages.extend(_sensor_messages(cfg, unit, ids, timers_ms, cause_names))
    comment, node_comments = _comments(cfg)
    nodes = [Node(name, comment=text) for name, text in node_comments.items()]
    definitions = OrderedDict(GenMsgCycleTime=_CYCLE_TIME, GenMsgSendType=_SEND_TYPE,
                              GenSigSendType=_SIG_SEND_TYPE)
    return Database(messages, nodes, buses=[Bus("", comment=comment)], version=VERSION,
                    dbc_specifics=DbcSpecifics(attribute_definitions=definitions))


def frame_ids(cfg: Config) -> dict[str, int]:
    """Message name -> frame ID on this machine."""
    return {m.name: m.frame_id for m in machine_database(cfg).messages}
