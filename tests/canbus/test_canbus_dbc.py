"""The frame codec: every frame encoded and decoded at the configured IDs, step and wiring."""

from __future__ import annotations

import dataclasses

import cantools
import pytest

from ddh_vsensor.estimator.flags import Flags
from ddh_vsensor.canbus import IO_MODULE, FrameCodec, frame_ids, message_name
from ddh_vsensor.config import Config, ConfigError


def with_can_unit(cfg: Config, actuator: str, **changes: int) -> Config:
    units = {**cfg.can.units, actuator: dataclasses.replace(cfg.can.units[actuator], **changes)}
    return dataclasses.replace(cfg, can=dataclasses.replace(cfg.can, units=units))


def test_documented_layout(cfg: Config) -> None:
    codec = FrameCodec(cfg)
    msg = codec.encode_sevcon("bucket", torque_nm=-1.5, speed_rpm=-1000)
    assert msg.arbitration_id == 0x182 and not msg.is_extended_id
    assert bytes(msg.data) == (-24).to_bytes(2, "little", signed=True) + \
        (-1000).to_bytes(4, "little", signed=True)
    msg = codec.encode_position("boom", position_mm=123.456, speed_mm_s=-12.34, status=3)
    assert msg.arbitration_id == 0x1B1
    assert bytes(msg.data) == (12346).to_bytes(4, "little", signed=True) + \
        (-123).to_bytes(2, "little", signed=True) + b"\x03"
    msg = codec.encode_diag("bucket", uncertainty_mm=1.5, flags=Flags.ADAPTING,
                            input_frames=70000, rejected_frames=258)
    assert msg.arbitration_id == 0x2B2
    # uncertainty UNSIGNED32, flags, rejected frames UNSIGNED8, input frames UNSIGNED16
    assert bytes(msg.data) == bytes([150, 0, 0, 0, 8, 2]) + (70000 - 65536).to_bytes(2, "little")
    assert bytes(codec.encode_oil_temp(-4.5).data) == (-45).to_bytes(2, "little", signed=True)


def test_decode_returns_names_and_numbers(cfg: Config) -> None:
    codec = FrameCodec(cfg)
    name, signals = codec.decode(codec.encode("SEVCON_BOOM_HEARTBEAT", {"NmtState": 5}))
    assert (name, signals) == ("SEVCON_BOOM_HEARTBEAT", {"NmtState": 5})
    other = codec.encode_sevcon("boom", 1.0, 2.0)
    other.arbitration_id = 0x123
    assert codec.decode(other) is None


def test_sensor_output_saturates_like_a_sensor(cfg: Config) -> None:
    codec = FrameCodec(cfg)
    pos = codec.decode(codec.encode_position("boom", 10.0, speed_mm_s=1e6, status=0))[1]
    assert pos["Speed"] == pytest.approx(3276.7)
    diag = codec.decode(codec.encode_diag("boom", 1e12, 0, 0, 0))[1]
    assert diag["Uncertainty"] == pytest.approx((2 ** 32 - 1) * 0.01)
    assert codec.decode(codec.encode_diag("boom", 1e6, 0, 0, 0))[1]["Uncertainty"] == 1e6


def test_uncertainty_range_covers_every_stroke(cfg: Config) -> None:
    """A cold start publishes the whole stroke as uncertainty: it must not saturate."""
    codec = FrameCodec(cfg)
    for actuator in cfg.can.units:
        stroke = cfg.unit(actuator).stroke_mm
        diag = codec.decode(codec.encode_diag(actuator, 2 * stroke, 0, 0, 0))[1]
        assert diag["Uncertainty"] == pytest.approx(2 * stroke, abs=0.005)


def test_flag_bytes_are_bit_signals_with_value_tables(cfg: Config) -> None:
    codec = FrameCodec(cfg)
    db = codec.database
    for actuator in cfg.can.units:
        for kind, prefix in (("position", "Status"), ("diag", "Flag")):
            message = db.get_message_by_name(message_name(kind, actuator))
            for flag in Flags:
                bit = flag.bit_length() - 1
                name = prefix + "".join(w.capitalize() for w in flag.name.split("_"))
                signal = message.get_signal_by_name(name)
                assert signal.length == 1 and signal.start % 8 == bit, name
                assert set(signal.choices) == {0, 1}, name
        for flags in (0x20, 0x40, 0x7F, 0x15):
            pos = codec.decode(codec.encode_position(actuator, 1.0, 0.0, flags))[1]
            diag = codec.decode(codec.encode_diag(actuator, 1.0, flags, 0, 0))[1]
            assert pos["Status"] == diag["Flags"] == flags
    pos = codec.decode(codec.encode_position("boom", 1.0, 0.0, Flags.PRESET_UNCONFIRMED))[1]
    assert pos["StatusPresetUnconfirmed"] == 1 and pos["StatusStaleInput"] == 0
    decoded = db.decode_message(0x1B1, bytes(codec.encode_position("boom", 1, 0, 0x40).data))
    assert str(decoded["StatusControllerNotOperational"]) == "NotOperational"


def test_sensor_heartbeat_emcy_and_sdo_frames_decode(cfg: Config) -> None:
    codec = FrameCodec(cfg)
    ids = codec.ids
    assert ids[message_name("sensor_heartbeat", "boom")] == 0x731
    assert ids[message_name("emcy", "bucket")] == 0xB2
    assert (ids[message_name("sdo_tx", "boom")], ids[message_name("sdo_rx", "boom")]) == \
        (0x5B1, 0x631)
    assert ids["NMT_COMMAND"] == 0
    db = codec.database
    signals = {s.name: 0 for s in db.get_message_by_name("SENSOR_BOOM_EMCY").signals}
    signals.update({"ErrorCode": 0x8100, "RegisterGeneric": 1, "RegisterCommunication": 1,
                    "FlagConcerned": 1, "ActiveStaleInput": 1})
    emcy = codec.encode(message_name("emcy", "boom"), signals)
    assert bytes(emcy.data) == bytes([0x00, 0x81, 0x11, 0x01, 0x01, 0, 0, 0])
    decoded = db.decode_message(0xB1, bytes(emcy.data))
    assert str(decoded["ErrorCode"]) == "InputStale"
    boot = codec.decode(codec.encode(message_name("sensor_heartbeat", "bucket"), {"NmtState": 0}))
    assert boot == ("SENSOR_BUCKET_HEARTBEAT", {"NmtState": 0})


def test_other_node_ids_keep_the_function_code(cfg: Config) -> None:
    changed = with_can_unit(cfg, "boom", sevcon_node_id=5, sensor_node_id=0x40)
    ids = frame_ids(changed)
    assert ids[message_name("sevcon", "boom")] == 0x185
    assert ids[message_name("heartbeat", "boom")] == 0x705
    assert ids[message_name("position", "boom")] == 0x1C0
    assert ids[message_name("diag", "boom")] == 0x2C0
    assert ids[message_name("emcy", "boom")] == 0xC0
    assert ids[message_name("sensor_heartbeat", "boom")] == 0x740
    assert ids[message_name("sevcon", "bucket")] == 0x182
    assert FrameCodec(changed).encode_sevcon("boom", 0.0, 0.0).arbitration_id == 0x185


def test_clashing_node_ids_are_a_config_error(cfg: Config) -> None:
    clash = with_can_unit(cfg, "bucket", sensor_node_id=cfg.can.units["boom"].sensor_node_id)
    with pytest.raises(ConfigError, match=r"can\.units\.bucket\.sensor_node_id.*0x1B1"):
        frame_ids(clash)


def test_position_follows_the_configured_step(cfg: Config) -> None:
    coarse = dataclasses.replace(cfg, can=dataclasses.replace(cfg.can, position_step_mm=0.1))
    codec = FrameCodec(coarse)
    msg = codec.encode_position("boom", 123.44, 0.0, 0)
    assert bytes(msg.data[:4]) == (1234).to_bytes(4, "little", signed=True)
    assert codec.decode(msg)[1]["Position"] == pytest.approx(123.4)
    assert codec.messages["POSITION_BOOM_TPDO1"].get_signal_by_name("Position").scale == 0.1
    assert FrameCodec(cfg).messages["POSITION_BOOM_TPDO1"] \
        .get_signal_by_name("Position").scale == 0.01


def test_hall_bits_follow_the_config(cfg: Config) -> None:
    codec = FrameCodec(cfg)
    msg = codec.encode_inputs({"boom": {"top": 1, "mid": 0}, "bucket": {"bottom": 1}})
    assert msg.arbitration_id == 0x190 and bytes(msg.data) == bytes([0b0000_1100])
    decoded = codec.messages[IO_MODULE].decode(bytes(msg.data))
    assert decoded["HallBoomTop"] == 1 and decoded["HallBucketBottom"] == 1
    assert codec.hall_states("bucket", msg.data) == {"bottom": 1, "mid": 0, "top": 0}
    rewired = FrameCodec(with_can_unit(cfg, "bucket", hall_bits={"bottom": 7, "mid": 4,
                                                                 "top": 5}))
    assert rewired.hall_states("bucket", bytes([0x80])) == {"bottom": 1, "mid": 0, "top": 0}
    with pytest.raises(cantools.database.DecodeError):
        codec.hall_states("boom", b"")


def test_message_name_rejects_unknown_kind() -> None:
    assert message_name("diag", "bucket") == "DIAG_BUCKET_TPDO2"
    with pytest.raises(ValueError, match="kind"):
        message_name("speed", "boom")


def test_hall_bits_up_to_63_span_the_io_frame(wide_inputs: Config,
                                              three_units: Config) -> None:
    codec = FrameCodec(wide_inputs)
    msg = codec.encode_inputs({"ram": {"bottom": 0, "mid": 1, "top": 1}})
    assert msg.dlc == 8 and int.from_bytes(msg.data, "little") == (1 << 63) | (1 << 31)
    assert codec.hall_states("ram", msg.data) == {"bottom": 0, "mid": 1, "top": 1}
    name, signals = codec.decode(msg)
    assert name == IO_MODULE
    assert (signals["HallRamBottom"], signals["HallRamMid"], signals["HallRamTop"]) == (0, 1, 1)
    with pytest.raises(cantools.database.DecodeError, match="needs 8 byte"):
        codec.hall_states("ram", msg.data[:7])
    codec = FrameCodec(three_units)
    msg = codec.encode_inputs({"arm": {"top": 1}, "tilt": {"mid": 1}})
    assert bytes(msg.data) == bytes([0b0001_0000, 0b0000_0100])
    assert codec.hall_states("arm", msg.data) == {"bottom": 0, "mid": 0, "top": 1}
    assert codec.hall_states("lift", msg.data) == {"bottom": 0, "mid": 0, "top": 0}


def test_renamed_units_encode_and_decode(three_units: Config) -> None:
    codec = FrameCodec(three_units)
    msg = codec.encode_position("arm", 12.34, -5.0, int(Flags.NOT_REFERENCED))
    assert msg.arbitration_id == 0x180 + 51
    name, signals = codec.decode(msg)
    assert name == "POSITION_ARM_TPDO1" and signals["Status"] == Flags.NOT_REFERENCED
    assert signals["Position"] == pytest.approx(12.34)
    assert codec.decode(codec.encode_sevcon("tilt", 2.0, -300.0))[0] == "SEVCON_TILT_TPDO1"
