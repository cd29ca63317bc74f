"""The project's CAN frames: the packaged DBC, message names, and IDs for the configured nodes.

cantools does all bit work. The DBC holds the CANopen default frame IDs for the node IDs of
config/loader.yaml; a config with other node IDs keeps each frame's function code
(0x080 EMCY, 0x180 TPDO1, 0x280 TPDO2, 0x580/0x600 SDO, 0x700 heartbeat) and adds its own
node ID, as CANopen does.

The status byte of a position frame and the flags byte of a diagnostic frame are one bit
signal per flag in the DBC (with value tables, for tools); :class:`FrameCodec` takes and
returns them whole as ``Status`` and ``Flags`` as well, the way the service uses them.
"""

from __future__ import annotations

import copy
from collections.abc import Mapping, Sequence
from pathlib import Path

import can
import cantools
from cantools.database.can import Database
from cantools.database.can import Message as DbcMessage

from ..config import Config, ConfigError, load_config
from ..errors import UserError
from ..estimator.flags import Flags

DEFAULT_DBC = Path(__file__).parent.parent / "data" / "ddh_vsensor.dbc"

OIL_TEMP = "OIL_TEMP_TPDO1"
IO_MODULE = "IO_MODULE_TPDO1"
NMT_COMMAND = "NMT_COMMAND"
_PER_ACTUATOR = {
    "sevcon": "SEVCON_{}_TPDO1",
    "heartbeat": "SEVCON_{}_HEARTBEAT",
    "position": "POSITION_{}_TPDO1",
    "diag": "DIAG_{}_TPDO2",
    "sensor_heartbeat": "SENSOR_{}_HEARTBEAT",
    "emcy": "SENSOR_{}_EMCY",
    "sdo_tx": "SENSOR_{}_SDO_TX",
    "sdo_rx": "SENSOR_{}_SDO_RX",
}
_SENSOR_KINDS = ("position", "diag", "sensor_heartbeat", "emcy", "sdo_tx", "sdo_rx")
_FIXED_IDS = {NMT_COMMAND: 0x000}
_NODE_ID_MASK = 0x7F    # CANopen COB-ID = function code (upper 4 bits) + node ID (lower 7)


def _bit_signal(flag: Flags) -> str:
    """STALE_INPUT -> StaleInput: the DBC's name for one flag bit (after its prefix)."""
    return "".join(word.capitalize() for word in (flag.name or "").split("_"))


# Whole byte -> ((bit signal, flag value) per flag, reserved bit 7's signal)
_FLAG_BYTES = {whole: (tuple((prefix + _bit_signal(f), int(f)) for f in Flags),
                       prefix + "Reserved")
               for whole, prefix in (("Status", "Status"), ("Flags", "Flag"))}


def message_name(kind: str, actuator: str) -> str:
    """DBC name of a per-actuator frame; kind is sevcon, heartbeat, position or diag."""
    if kind not in _PER_ACTUATOR:
        raise ValueError(f"unknown frame kind {kind!r} (known: {', '.join(_PER_ACTUATOR)})")
    return _PER_ACTUATOR[kind].format(actuator.upper())


def all_message_names(units: Sequence[str]) -> list[str]:
    """Every message the project needs from a DBC for a machine with these units."""
    return [message_name(kind, a) for a in units for kind in _PER_ACTUATOR] + [
        OIL_TEMP, IO_MODULE, NMT_COMMAND]


def load_dbc(path: str | Path | None = None, cfg: Config | None = None) -> Database:
    """Load a DBC (default: the packaged one) and check it has every frame the project uses."""
    path = Path(path) if path is not None else DEFAULT_DBC
    try:
        db = cantools.database.load_file(str(path), database_format="dbc")
    except OSError as exc:
        raise UserError(f"{path}: cannot read DBC: {exc.strerror or exc}") from None
    except cantools.database.UnsupportedDatabaseFormatError as exc:
        raise UserError(f"{path}: not a valid DBC: {exc}") from None
    units = (cfg or load_config()).unit_names
    missing = [name for name in all_message_names(units)
               if name not in {m.name for m in db.messages}]
    if missing:
        raise UserError(f"{path}: DBC lacks message(s) {', '.join(missing)}")
    return db


def _node_settings(cfg: Config) -> dict[str, tuple[int, str]]:
    """Message name -> (configured node ID, config key that sets it)."""
    can_cfg = cfg.can
    nodes = {OIL_TEMP: (can_cfg.oil_temp_node_id, "can.oil_temp_node_id"),
             IO_MODULE: (can_cfg.io_module_node_id, "can.io_module_node_id")}
    for actuator, unit in can_cfg.units.items():
        key = f"can.units.{actuator}"
        for kind in ("sevcon", "heartbeat"):
            nodes[message_name(kind, actuator)] = (unit.sevcon_node_id, f"{key}.sevcon_node_id")
        for kind in _SENSOR_KINDS:
            nodes[message_name(kind, actuator)] = (unit.sensor_node_id, f"{key}.sensor_node_id")
    return nodes


def frame_ids(cfg: Config, db: Database | None = None) -> dict[str, int]:
    """Message name -> frame ID for the configured node IDs; clashing IDs are a config error."""
    db = db or load_dbc(cfg=cfg)
    ids: dict[str, int] = dict(_FIXED_IDS)
    owner: dict[int, str] = {frame_id: name for name, frame_id in _FIXED_IDS.items()}
    for name, (node_id, key) in _node_settings(cfg).items():
        frame_id = (db.get_message_by_name(name).frame_id & ~_NODE_ID_MASK) | node_id
        if frame_id in owner:
            raise ConfigError(cfg.source, key, f"node {node_id} puts {name} on frame ID "
                              f"0x{frame_id:03X}, already used by {owner[frame_id]}")
        ids[name], owner[frame_id] = frame_id, name
    return ids


class FrameCodec:
    """Encode and decode the project's frames at the configured IDs and position step."""

    def __init__(self, cfg: Config, db: Database | None = None) -> None:
        db = db or load_dbc(cfg=cfg)
        self.cfg = cfg
        self.ids = frame_ids(cfg, db)
        self._messages = {name: db.get_message_by_name(name) for name in self.ids}
        for actuator in cfg.can.units:
            name = message_name("position", actuator)
            self._messages[name] = self._with_position_step(self._messages[name],
                                                            cfg.can.position_step_mm)
        self._names = {frame_id: name for name, frame_id in self.ids.items()}
        # messages with flag bytes split into bit signals -> those bytes' names
        self._flag_bytes = {name: [w for w, (_, reserved) in _FLAG_BYTES.items()
                                   if any(s.name == reserved for s in m.signals)]
                            for name, m in self._messages.items()}

    @staticmethod
    def _with_position_step(message: DbcMessage, step_mm: float) -> DbcMessage:
        """The DBC's 0.01 mm is the default measuring step; config may choose another."""
        signal = message.get_signal_by_name("Position")
        if signal.scale == step_mm:
            return message
        message = copy.deepcopy(message)
        signal = message.get_signal_by_name("Position")
        signal.scale = step_mm
        signal.minimum = -(2 ** 31) * step_mm
        signal.maximum = (2 ** 31 - 1) * step_mm
        return message

    def encode(self, name: str, signals: Mapping[str, float],
               timestamp_s: float = 0.0) -> can.Message:
        """Frame with all signals of a message (cantools checks names and ranges)."""
        message = self._messages[name]
        signals = dict(signals)
        for whole in self._flag_bytes[name]:
            bits, reserved = _FLAG_BYTES[whole]
            if whole in signals:
                byte = int(signals.pop(whole))
                signals.update({signal: int(bool(byte & value)) for signal, value in bits})
                signals[reserved] = (byte >> 7) & 1
        data = message.encode(signals)
        return can.Message(timestamp=timestamp_s, arbitration_id=self.ids[name],
                           is_extended_id=False, data=data)

    def decode(self, msg: can.Message) -> tuple[str, dict[str, float]] | None:
        """(message name, scaled signals) of one of our frames, None for any other frame."""
        if msg.is_extended_id or msg.is_remote_frame or msg.is_error_frame:
            return None
        name = self._names.get(msg.arbitration_id)
        if name is None:
            return None
        message = self._messages[name]
        signals = message.decode(bytes(msg.data), decode_choices=False)
        for whole in self._flag_bytes[name]:
            bits, reserved = _FLAG_BYTES[whole]
            signals[whole] = sum(value for signal, value in bits if signals[signal]) + \
                (int(signals[reserved]) << 7)
        return name, signals

    def encode_sevcon(self, actuator: str, torque_nm: float, speed_rpm: float,
                      timestamp_s: float = 0.0) -> can.Message:
        """Sevcon TPDO1 as the controller sends it (torque 1/16 N·m, speed 1 rpm)."""
        return self.encode(message_name("sevcon", actuator),
                           {"TorqueActual": torque_nm, "VelocityActual": speed_rpm}, timestamp_s)

    def encode_oil_temp(self, oil_temp_c: float, timestamp_s: float = 0.0) -> can.Message:
        """Oil temperature sensor TPDO1 (0.1 °C)."""
        return self.encode(OIL_TEMP, {"OilTemp": oil_temp_c}, timestamp_s)

    def encode_position(self, actuator: str, position_mm: float, speed_mm_s: float,
                        status: int, timestamp_s: float = 0.0) -> can.Message:
        """CiA 406 TPDO1; speed saturates at the INT16 range like a real sensor's output."""
        signal = self._messages[message_name("position", actuator)].get_signal_by_name("Speed")
        speed_mm_s = min(max(speed_mm_s, signal.minimum), signal.maximum)
        return self.encode(message_name("position", actuator),
                           {"Position": position_mm, "Speed": speed_mm_s, "Status": int(status)},
                           timestamp_s)

    def encode_diag(self, actuator: str, uncertainty_mm: float, flags: int, input_frames: int,
                    rejected_frames: int, timestamp_s: float = 0.0) -> can.Message:
        """Diagnostic TPDO2; counters wrap at 16 bits, uncertainty saturates at 167772.15 mm."""
        name = message_name("diag", actuator)
        limit = self._messages[name].get_signal_by_name("Uncertainty").maximum
        return self.encode(name, {"Uncertainty": min(max(uncertainty_mm, 0.0), limit),
                                  "Flags": int(flags), "InputFrames": input_frames % 0x10000,
                                  "RejectedFrames": rejected_frames % 0x10000},
                           timestamp_s)

    def encode_inputs(self, states: Mapping[str, Mapping[str, int]],
                      timestamp_s: float = 0.0) -> can.Message:
        """I/O module frame from actuator -> reference name -> 0/1, at the configured bits.

        The input byte (0x6000 sub 1) is built whole: which bit is which switch is
        configuration (can.units.*.hall_bits); the DBC's per-bit signals name the default wiring.
        """
        byte = 0
        for actuator, refs in states.items():
            bits = self.cfg.can.units[actuator].hall_bits  # type: ignore[index]
            for name, state in refs.items():
                if state:
                    byte |= 1 << bits[name]
        length = self._messages[IO_MODULE].length
        return can.Message(timestamp=timestamp_s, arbitration_id=self.ids[IO_MODULE],
                           is_extended_id=False, data=byte.to_bytes(length, "little"))

    def hall_states(self, actuator: str, data: bytes) -> dict[str, int]:
        """Reference name -> 0/1 of one actuator's switches, from the I/O module's data bytes."""
        length = self._messages[IO_MODULE].length
        if len(data) < length:
            raise cantools.database.DecodeError(f"{IO_MODULE} needs {length} byte(s), "
                                                f"got {len(data)}")
        byte = int.from_bytes(bytes(data[:length]), "little")
        bits = self.cfg.can.units[actuator].hall_bits  # type: ignore[index]
        return {name: (byte >> bits[name]) & 1 for name in self.cfg.unit(actuator).references_mm}
