"""The generated frame layout: the shipped DBC is its output for the reference loader, nothing a
tool relies on changed from the hand-written DBC it replaces, and other machines get their own
names, IDs and Hall wiring."""

from __future__ import annotations

import dataclasses
import os
from pathlib import Path

import cantools
import pytest

from ddh_vsensor.canbus.layout import (IO_MODULE, KINDS, MAINTENANCE_EMCY, all_message_names,
                                       camel, frame_ids, machine_database, message_name)
from ddh_vsensor.config import Config, ConfigError, load_config
from ddh_vsensor.diagnosis.causes import CAUSE_NAMES
from ddh_vsensor.estimator.flags import Flags

from .conftest import REPO, machine

SHIPPED = REPO / "dbc" / "ddh_vsensor.dbc"
PACKAGED = REPO / "ddh_vsensor" / "data" / "ddh_vsensor.dbc"
HAND_WRITTEN = Path(__file__).parent / "data" / "handwritten_loader.dbc"
FUNCTION_CODES = {"sevcon": 0x180, "heartbeat": 0x700, "position": 0x180, "diag": 0x280,
                  "health": 0x380, "sensor_heartbeat": 0x700, "emcy": 0x080, "sdo_tx": 0x580,
                  "sdo_rx": 0x600}

# Comments deliberately reworded when the DBC became generated: (message, signal or None).
REWORDED = {(None, None),                                        # the database's
            ("IO_MODULE_TPDO1", None),                           # signals follow the wiring
            ("POSITION_BOOM_TPDO1", None), ("POSITION_BUCKET_TPDO1", None),  # EDS per unit
            ("POSITION_BOOM_TPDO1", "Position"), ("POSITION_BUCKET_TPDO1", "Position"),
            ("SENSOR_BOOM_EMCY", "FlagConcerned"),                # 0: a register-only reset
            ("SENSOR_BUCKET_EMCY", "FlagConcerned"),
            ("SENSOR_BOOM_EMCY", "ErrorCode"),                    # 8130: life guarding too
            ("SENSOR_BUCKET_EMCY", "ErrorCode"),
            ("SENSOR_BOOM_HEARTBEAT", None),                      # node guarding answers
            ("SENSOR_BUCKET_HEARTBEAT", None),
            ("DIAG_BOOM_TPDO2", "Uncertainty"), ("DIAG_BUCKET_TPDO2", "Uncertainty"),  # 32 bits
            ("DIAG_BOOM_TPDO2", "RejectedFrames"), ("DIAG_BUCKET_TPDO2", "RejectedFrames"),
            # maintenance due (the health alarm, FF30): the EMCY, its register bit 7
            ("SENSOR_BOOM_EMCY", None), ("SENSOR_BUCKET_EMCY", None),
            ("SENSOR_BOOM_EMCY", "RegisterManufacturer"),
            ("SENSOR_BUCKET_EMCY", "RegisterManufacturer")}
# Frames described since (the sensors consume SYNC, publish their unit's health), and the
# nodes whose comment says so.
ADDED = {"SYNC", "HEALTH_BOOM_TPDO3", "HEALTH_BUCKET_TPDO3"}
# Value table entries added since: EMCY FF30 maintenance due.
CHOICES_ADDED = {"ErrorCode": {MAINTENANCE_EMCY[0]: MAINTENANCE_EMCY[1]}}
# Reserved bits taken into use since, at the same place: the flags' bit 7 (the Kalman
# filter's self-check), the old name -> the new (its text and value table new).
RESERVED_NOW = {"StatusReserved": "StatusModelInconsistent",
                "FlagReserved": "FlagModelInconsistent",
                "ActiveReserved": "ActiveModelInconsistent"}
RESERVED_CHOICES = {"StatusReserved": {0: "Consistent", 1: "Inconsistent"},
                    "FlagReserved": {0: "Consistent", 1: "Inconsistent"}, "ActiveReserved": None}
REWORDED_NODES = {"NMT_MASTER"}
# Send types as Vector's interaction layer defines them (hand-written -> generated), and the
# I/O module's refresh as its cycle time.
SEND_TYPE_NOW = {"Cyclic": "Cyclic", "OnChange": "Cyclic", "Spontaneous": "NoMsgSendType"}
CYCLE_TIME_ADDED = {IO_MODULE: 100}
VECTOR_IL_DEFINITIONS = {
    "GenMsgCycleTime": ("BO_", "INT", 0, 65535, [], 0),
    "GenMsgSendType": ("BO_", "ENUM", None, None, ["Cyclic", "not_used", "not_used", "not_used",
                       "not_used", "Cyclic", "not_used", "IfActive", "NoMsgSendType"],
                       "NoMsgSendType"),
    "GenSigSendType": ("SG_", "ENUM", None, None, ["Cyclic", "OnWrite", "OnWriteWithRepetition",
                       "OnChange", "OnChangeWithRepetition", "IfActive",
                       "IfActiveWithRepetition", "NoSigSendType"], "Cyclic")}
# TPDO2 without a 24-bit object: (start, length) of the re-laid-out diagnostic signals.
DIAG_LAYOUT = {"Uncertainty": (0, 32), "RejectedFrames": (40, 8), "InputFrames": (48, 16),
               **{"Flag" + "".join(w.capitalize() for w in (f.name or "").split("_")):
                  (32 + f.bit_length() - 1, 1) for f in Flags}}


def test_packaged_dbc_is_a_relative_link_to_the_repo_dbc() -> None:
    assert os.readlink(PACKAGED) == "../../dbc/ddh_vsensor.dbc"
    assert PACKAGED.resolve() == SHIPPED.resolve()


def test_shipped_dbc_is_the_generated_one_byte_for_byte() -> None:
    generated = machine_database(load_config(), CAUSE_NAMES).as_dbc_string()
    assert SHIPPED.read_bytes() == generated.encode("cp1252")     # cantools writes DBC so


def _choices(signal: cantools.database.can.Signal) -> dict[int, str] | None:
    return None if signal.choices is None else {k: str(v) for k, v in signal.choices.items()}


def test_nothing_a_tool_relies_on_changed_from_the_hand_written_dbc() -> None:
    old = cantools.database.load_file(str(HAND_WRITTEN))
    new = cantools.database.load_file(str(SHIPPED))
    assert new.version == old.version
    assert [n.name for n in new.nodes] == [n.name for n in old.nodes]
    assert [(n.name, n.comment) for n in new.nodes if n.name not in REWORDED_NODES] == \
        [(n.name, n.comment) for n in old.nodes if n.name not in REWORDED_NODES]
    assert [m.name for m in new.messages if m.name not in ADDED] == \
        [m.name for m in old.messages]
    assert {name: (d.kind, d.type_name, d.minimum, d.maximum, d.choices, d.default_value)
            for name, d in new.dbc.attribute_definitions.items()} == VECTOR_IL_DEFINITIONS
    reworded = set()
    for was in old.messages:
        now = new.get_message_by_name(was.name)
        diag = was.name.startswith("DIAG_")
        assert (now.frame_id, now.length, now.cycle_time, now.send_type, now.senders,
                now.is_extended_frame) == (was.frame_id, was.length,
                                           CYCLE_TIME_ADDED.get(was.name, was.cycle_time),
                                           SEND_TYPE_NOW[was.send_type], was.senders,
                                           was.is_extended_frame), was.name
        if now.comment != was.comment:
            reworded.add((was.name, None))
        assert sorted(s.name for s in now.signals) == \
            sorted(RESERVED_NOW.get(s.name, s.name) for s in was.signals)
        for old_signal in was.signals:
            signal = now.get_signal_by_name(RESERVED_NOW.get(old_signal.name, old_signal.name))
            fields = ("byte_order", "is_signed", "scale", "offset", "unit", "receivers",
                      "is_float") + (() if diag else ("start", "length", "minimum", "maximum"))
            assert {f: getattr(signal, f) for f in fields} == \
                {f: getattr(old_signal, f) for f in fields}, (was.name, signal.name)
            if diag:
                assert (signal.start, signal.length) == DIAG_LAYOUT[signal.name], signal.name
            if old_signal.name in RESERVED_NOW:
                assert _choices(signal) == RESERVED_CHOICES[old_signal.name], signal.name
                continue
            expected = _choices(old_signal)
            if expected is not None and signal.name in CHOICES_ADDED:
                expected = {**expected, **CHOICES_ADDED[signal.name]}
            assert _choices(signal) == expected, (was.name, signal.name)
            if signal.comment != old_signal.comment:
                reworded.add((was.name, signal.name))
    if new.buses[0].comment != old.buses[0].comment:
        reworded.add((None, None))
    assert reworded == REWORDED


def test_reworded_comments_say_what_is_now_true() -> None:
    db = cantools.database.load_file(str(SHIPPED))
    assert "Generated by `ddh-vsensor dbc` from loader.yaml" in db.buses[0].comment
    assert "the signals follow it" in db.get_message_by_name(IO_MODULE).comment
    assert "`ddh-vsensor eds --unit bucket`" in \
        db.get_message_by_name("POSITION_BUCKET_TPDO1").comment
    assert "(0.01 mm, can.position_step_mm)" in db.get_message_by_name(
        "POSITION_BOOM_TPDO1").get_signal_by_name("Position").comment
    assert "0 in an error reset that only brings the register up to date" in \
        db.get_message_by_name("SENSOR_BUCKET_EMCY").get_signal_by_name("FlagConcerned").comment


@pytest.fixture(params=["loader", "three_units", "wide_inputs"])
def any_machine(request: pytest.FixtureRequest, cfg: Config) -> Config:
    return cfg if request.param == "loader" else request.getfixturevalue(request.param)


def test_every_frame_is_there_with_comments(any_machine: Config) -> None:
    db = machine_database(any_machine)
    assert sorted(m.name for m in db.messages) == sorted(all_message_names(
        any_machine.unit_names))
    for message in db.messages:
        assert message.comment and not message.is_extended_frame
        assert all(signal.comment for signal in message.signals), message.name
        assert all(signal.byte_order == "little_endian" for signal in message.signals)


def test_each_message_round_trips_through_the_dbc_text(any_machine: Config) -> None:
    """Written as DBC and read back, every signal's extreme values encode and decode."""
    db = cantools.database.load_string(machine_database(any_machine).as_dbc_string(),
                                       database_format="dbc")
    for message in db.messages:
        # The extreme of each signal's range: catches a wrong sign, length or scale.
        signals = {s.name: s.minimum if s.is_signed else s.maximum for s in message.signals}
        assert message.decode(message.encode(signals), decode_choices=False) == \
            pytest.approx(signals), message.name


def test_frame_ids_are_function_code_plus_configured_node(any_machine: Config) -> None:
    ids = frame_ids(any_machine)
    for unit in any_machine.unit_names:
        can_unit = any_machine.can.units[unit]
        for kind in KINDS:
            node = can_unit.sevcon_node_id if kind in ("sevcon", "heartbeat") \
                else can_unit.sensor_node_id
            assert ids[message_name(kind, unit)] == FUNCTION_CODES[kind] + node, (unit, kind)
    assert ids["OIL_TEMP_TPDO1"] == 0x180 + any_machine.can.oil_temp_node_id
    assert ids[IO_MODULE] == 0x180 + any_machine.can.io_module_node_id
    assert ids["NMT_COMMAND"] == 0
    assert len(set(ids.values())) == len(ids)


def test_names_come_from_the_units(three_units: Config) -> None:
    db = machine_database(three_units)
    names = {m.name for m in db.messages}
    assert {"SEVCON_LIFT_TPDO1", "POSITION_ARM_TPDO1", "DIAG_TILT_TPDO2",
            "SENSOR_ARM_SDO_RX"} <= names
    assert not any("BOOM" in n or "BUCKET" in n for n in names)
    assert [n.name for n in db.nodes][:3] == ["SEVCON_LIFT", "SEVCON_TILT", "SEVCON_ARM"]
    daemon = next(n for n in db.nodes if n.name == "DDH_VSENSOR")
    assert "(nodes 49, 50 and 51)" in daemon.comment
    assert "Buses: default: lift, tilt; can1: arm." in db.buses[0].comment
    assert "Sevcon arm TPDO1 (0x180 + node 3)" in db.get_message_by_name(
        "SEVCON_ARM_TPDO1").comment


def test_io_module_frame_follows_the_wiring(three_units: Config, wide_inputs: Config) -> None:
    io = machine_database(three_units).get_message_by_name(IO_MODULE)
    assert io.length == 2
    assert [(s.name, s.start) for s in io.signals] == [
        ("HallLiftBottom", 0), ("HallLiftMid", 1), ("HallLiftTop", 2), ("HallTiltBottom", 3),
        ("HallTiltMid", 4), ("HallTiltTop", 5), ("HallArmBottom", 8), ("HallArmMid", 9),
        ("HallArmTop", 10)]
    assert io.get_signal_by_name("HallArmMid").comment == \
        "Arm mid Hall switch, input bit 1 of 0x6000 sub 2; 1 = switch on."
    assert "0x6000 sub 1..2" in io.comment
    assert io.decode(bytes([0x00, 0x04]))["HallArmTop"] == 1
    wide = machine_database(wide_inputs).get_message_by_name(IO_MODULE)
    assert wide.length == 8
    assert [(s.name, s.start) for s in wide.signals] == [
        ("HallRamBottom", 0), ("HallRamMid", 31), ("HallRamTop", 63)]
    assert wide.decode((1 << 63).to_bytes(8, "little"))["HallRamTop"] == 1


def test_timers_follow_the_configuration(cfg: Config) -> None:
    slow = dataclasses.replace(cfg, can=dataclasses.replace(cfg.can, event_timer_ms=20.0))
    position = machine_database(slow).get_message_by_name("POSITION_BOOM_TPDO1")
    assert position.cycle_time == 20 and "(can.event_timer_ms, 20 ms)" in position.comment


def test_cycle_times_and_send_types(cfg: Config) -> None:
    db = machine_database(cfg)
    expected = {"POSITION_BOOM_TPDO1": (10, "Cyclic"), "DIAG_BOOM_TPDO2": (100, "Cyclic"),
                "SENSOR_BOOM_HEARTBEAT": (1000, "Cyclic"), "SEVCON_BOOM_TPDO1": (10, "Cyclic"),
                "SENSOR_BOOM_EMCY": (None, "NoMsgSendType"), "IO_MODULE_TPDO1": (100, "Cyclic"),
                "SENSOR_BOOM_SDO_TX": (None, "NoMsgSendType"), "SYNC": (None, "NoMsgSendType")}
    for name, (cycle_ms, send_type) in expected.items():
        message = db.get_message_by_name(name)
        assert (message.cycle_time, message.send_type) == (cycle_ms, send_type), name
    for message in db.messages:
        assert message.send_type in ("Cyclic", "NoMsgSendType"), message.name
        assert (message.cycle_time is not None) == (message.send_type == "Cyclic"), message.name
    # as a Vector tool reads the DBC: the attribute values index the IL's enum
    text = cantools.database.load_string(db.as_dbc_string(), database_format="dbc")
    for message in text.messages:
        attributes = message.dbc.attributes
        assert attributes["GenMsgSendType"].value == (0 if message.cycle_time else 8)
        if message.cycle_time:
            assert attributes["GenMsgCycleTime"].value == message.cycle_time
    hall = text.get_message_by_name(IO_MODULE).signals
    assert hall and {s.dbc.attributes["GenSigSendType"].value for s in hall} == {3}  # OnChange


def test_flag_bits_have_value_tables(three_units: Config) -> None:
    db = machine_database(three_units)
    for kind, prefix in (("position", "Status"), ("diag", "Flag")):
        message = db.get_message_by_name(message_name(kind, "arm"))
        for flag in Flags:
            name = prefix + "".join(w.capitalize() for w in (flag.name or "").split("_"))
            signal = message.get_signal_by_name(name)
            assert signal.length == 1 and signal.start % 8 == flag.bit_length() - 1, name
            assert set(signal.choices) == {0, 1}, name


def test_a_hall_bit_wired_twice_is_a_config_error() -> None:
    twice = {"lift": ("boom", {"sevcon_node_id": 1, "sensor_node_id": 49,
                               "hall_bits": {"bottom": 0, "mid": 1, "top": 2}}),
             "tilt": ("bucket", {"sevcon_node_id": 2, "sensor_node_id": 50,
                                 "hall_bits": {"bottom": 3, "mid": 2, "top": 5}})}
    with pytest.raises(ConfigError, match=r"can\.units\.tilt\.hall_bits\.mid: input bit 2 is "
                                          r"already wired to lift\.top"):
        machine_database(machine(twice, "twice.yaml"))


@pytest.mark.parametrize("key, value, error", [
    # the bucket's sensor TPDO1 on the boom controller's
    ("sensor_node_id", 1, r"can\.units\.bucket\.sensor_node_id: node 1 puts "
                          r"POSITION_BUCKET_TPDO1 on frame ID 0x181, already used by "
                          r"SEVCON_BOOM_TPDO1"),
    # the bucket controller on the boom sensor's node: the sensor, generated later, is named
    ("sevcon_node_id", 49, r"can\.units\.boom\.sensor_node_id: node 49 puts "
                           r"POSITION_BOOM_TPDO1 on frame ID 0x1B1, already used by "
                           r"SEVCON_BUCKET_TPDO1"),
])
def test_clashing_node_ids_name_the_key(cfg: Config, key: str, value: int, error: str) -> None:
    units = {**cfg.can.units,
             "bucket": dataclasses.replace(cfg.can.units["bucket"], **{key: value})}
    clash = dataclasses.replace(cfg, can=dataclasses.replace(cfg.can, units=units))
    with pytest.raises(ConfigError, match=error):
        machine_database(clash)


def test_oil_and_io_nodes_may_not_share_an_id(cfg: Config) -> None:
    clash = dataclasses.replace(cfg, can=dataclasses.replace(
        cfg.can, io_module_node_id=cfg.can.oil_temp_node_id))
    with pytest.raises(ConfigError, match=r"can\.io_module_node_id: .*OIL_TEMP_TPDO1"):
        machine_database(clash)


def test_emcy_value_table_is_what_the_sensor_node_sends() -> None:
    from ddh_vsensor.canbus.layout import EMCY_CODES
    from ddh_vsensor.device.emcy import EMCY_FAULTS
    assert {flag: code for flag, (code, _) in EMCY_CODES.items()} == \
        {flag: code for flag, (code, _) in EMCY_FAULTS.items()}


# --- the unit's health (TPDO3) ------------------------------------------------------------------

def test_health_frame_is_tpdo3_with_the_mapping_s_signals(any_machine: Config) -> None:
    """HEALTH_<UNIT>_TPDO3: 0x380 + sensor node, the template EDS's TPDO3 mapping (0x2010 sub
    1..5) signal for signal, scales and units; cycle time its event timer 0x1802 sub 5."""
    from ddh_vsensor.canbus.eds import template_od
    od = template_od()
    db = machine_database(any_machine)
    for unit in any_machine.unit_names:
        message = db.get_message_by_name(message_name("health", unit))
        assert message.frame_id == 0x380 + any_machine.can.units[unit].sensor_node_id
        assert (message.length, message.send_type, message.cycle_time, message.senders) == \
            (8, "Cyclic", od[0x1802][5].default, ["DDH_VSENSOR"])
        mapped = [od[0x1A02][sub].default for sub in range(1, od[0x1A02][0].default + 1)]
        assert [(e >> 16, (e >> 8) & 0xFF, e & 0xFF) for e in mapped] == \
            [(0x2010, sub, bits) for sub, bits in ((1, 8), (2, 8), (3, 16), (4, 16), (5, 16))]
        layout = {s.name: (s.start, s.length, s.scale, s.unit, s.is_signed)
                  for s in message.signals}
        assert layout == {
            "CauseCode": (0, 8, 1, None, False),
            "HealthAlarm": (8, 1, 1, None, False), "HealthFewDays": (9, 1, 1, None, False),
            "HealthNotYet": (10, 1, 1, None, False), "HealthReserved": (11, 5, 1, None, False),
            "ErrorNow": (16, 16, 0.01, "mm", False),
            "ErrorAtHorizon": (32, 16, 0.01, "mm", False),
            "DaysToTolerance": (48, 16, 0.1, "d", False)}
        for name in ("ErrorNow", "ErrorAtHorizon", "DaysToTolerance"):
            assert 0xFFFF in message.get_signal_by_name(name).choices, name
        raw = bytes([3, 0x03]) + (125).to_bytes(2, "little") + (410).to_bytes(2, "little") \
            + (0xFFFF).to_bytes(2, "little")
        decoded = message.decode(raw, decode_choices=False)
        assert decoded == pytest.approx({
            "CauseCode": 3, "HealthAlarm": 1, "HealthFewDays": 1, "HealthNotYet": 0,
            "HealthReserved": 0, "ErrorNow": 1.25, "ErrorAtHorizon": 4.10,
            "DaysToTolerance": 6553.5})
        assert str(message.decode(raw)["DaysToTolerance"]) == "NotWithinHorizon"


def test_cause_value_table_is_the_names_the_caller_passes(cfg: Config) -> None:
    """The layout does not import the diagnosis (a layer above): the cause names come in as an
    argument, the CLI passes the catalogue's; without them the codes have no value table."""
    bare = machine_database(cfg).get_message_by_name("HEALTH_BOOM_TPDO3")
    assert bare.get_signal_by_name("CauseCode").choices is None
    db = machine_database(cfg, CAUSE_NAMES)
    cause = db.get_message_by_name("HEALTH_BOOM_TPDO3").get_signal_by_name("CauseCode")
    assert _choices(cause) == {code: camel(name) for code, name in enumerate(CAUSE_NAMES)}
    assert cause.choices[0] == "None" and len(CAUSE_NAMES) <= 256
    shipped = cantools.database.load_file(str(SHIPPED))
    assert _choices(shipped.get_message_by_name("HEALTH_BUCKET_TPDO3").get_signal_by_name(
        "CauseCode")) == _choices(cause)


def test_emcy_maintenance_due_is_in_the_value_table(cfg: Config) -> None:
    from ddh_vsensor.device.emcy import MAINTENANCE_CODE, MAINTENANCE_REGISTER
    emcy = machine_database(cfg).get_message_by_name("SENSOR_BOOM_EMCY")
    assert emcy.get_signal_by_name("ErrorCode").choices[0xFF30] == "MaintenanceDue"
    assert MAINTENANCE_CODE == MAINTENANCE_EMCY[0] == 0xFF30
    assert MAINTENANCE_REGISTER == 0x81                 # generic and manufacturer
    assert "maintenance due" in emcy.get_signal_by_name("RegisterManufacturer").comment
