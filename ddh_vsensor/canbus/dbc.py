"""Encode and decode the machine's frames, at the layout its configuration generates.

cantools does all bit work on :func:`.layout.machine_database`. The status byte of a position
frame and the flags byte of a diagnostic frame are one bit signal per flag in the database
(with value tables, for tools); :class:`FrameCodec` takes and returns them whole as ``Status``
and ``Flags`` as well, the way the service uses them.
"""

from __future__ import annotations

import struct
from collections.abc import Callable, Mapping

import can
import cantools
from cantools.database.can import Database, Message

from ddh_vsensor.config import Config
from ddh_vsensor.estimator.flags import Flags
from ddh_vsensor.canbus.layout import (IO_MODULE, NMT_COMMAND, OIL_TEMP, all_message_names,
                                       flag_signal, frame_ids, machine_database, message_name)

__all__ = ["IO_MODULE", "NMT_COMMAND", "OIL_TEMP", "FrameCodec", "all_message_names",
           "frame_ids", "message_name"]

# Whole byte -> (bit signal, flag value) per flag: the byte's eight bits
_FLAG_BYTES = {whole: tuple((flag_signal(prefix, f), int(f)) for f in Flags)
               for whole, prefix in (("Status", "Status"), ("Flags", "Flag"))}


# (signed?, bits) -> struct code of a whole-byte little-endian integer signal
_INT_CODES = {(True, 8): "b", (True, 16): "h", (True, 32): "i", (True, 64): "q",
              (False, 8): "B", (False, 16): "H", (False, 32): "I", (False, 64): "Q"}
_FLOAT_CODES = {32: "f", 64: "d"}


def _struct_layout(message: Message) -> tuple[struct.Struct, list[str]] | None:
    """One ``struct`` that unpacks every signal of ``message`` raw, in start-bit order with
    their names; None when a signal is not whole little-endian bytes (cantools then)."""
    if message.is_multiplexed():
        return None
    fmt, names, pos = "<", [], 0
    for sig in sorted(message.signals, key=lambda s: s.start):
        code = (_FLOAT_CODES.get(sig.length) if sig.is_float
                else _INT_CODES.get((sig.is_signed, sig.length)))
        if sig.byte_order != "little_endian" or sig.start % 8 or code is None \
                or sig.start < pos:
            return None
        fmt += "x" * ((sig.start - pos) // 8) + code
        names.append(sig.name)
        pos = sig.start + sig.length
    if pos > 8 * message.length:
        return None
    return struct.Struct(fmt + "x" * (message.length - pos // 8)), names


class FrameCodec:
    """Encode and decode the machine's frames (IDs, position step, Hall wiring: configuration)."""

    def __init__(self, cfg: Config, db: Database | None = None) -> None:
        """``db``: the machine's database if the caller has built it already."""
        self.cfg = cfg
        self.database = db if db is not None else machine_database(cfg)
        self.messages = {m.name: m for m in self.database.messages}
        self.ids = {name: m.frame_id for name, m in self.messages.items()}
        self._names = {frame_id: name for name, frame_id in self.ids.items()}
        # messages with flag bytes split into bit signals -> those bytes' names
        self._flag_bytes = {name: [w for w, bits in _FLAG_BYTES.items()
                                   if any(s.name == bits[0][0] for s in m.signals)]
                            for name, m in self.messages.items()}

    def encode(self, name: str, signals: Mapping[str, float],
               timestamp_s: float = 0.0) -> can.Message:
        """Frame with all signals of a message (cantools checks names and ranges)."""
        message = self.messages[name]
        signals = dict(signals)
        for whole in self._flag_bytes[name]:
            if whole in signals:
                byte = int(signals.pop(whole))
                signals.update({signal: int(bool(byte & value))
                                for signal, value in _FLAG_BYTES[whole]})
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
        message = self.messages[name]
        signals = message.decode(bytes(msg.data), decode_choices=False)
        for whole in self._flag_bytes[name]:
            signals[whole] = sum(value for signal, value in _FLAG_BYTES[whole]
                                 if signals[signal])
        return name, signals

    def sevcon_decoder(self, actuator: str) -> Callable[[bytes], tuple[float, float]]:
        """(torque_nm, speed_rpm) from the data of ``actuator``'s Sevcon TPDO1, the values
        :meth:`decode` gives, by one ``struct`` compiled from the database's signals (the per
        frame path: cantools' generic decode costs 20 times as much). Data of another length
        raises ``struct.error`` (``cantools`` ``DecodeError`` where the layout needs cantools).
        """
        message = self.messages[message_name("sevcon", actuator)]
        layout = _struct_layout(message)
        if layout is None:
            def decode_generic(data: bytes) -> tuple[float, float]:
                signals = message.decode(data, decode_choices=False)
                return signals["TorqueActual"], signals["VelocityActual"]
            return decode_generic
        unpack, names = layout[0].unpack, layout[1]
        (t, t_scale, t_offset), (v, v_scale, v_offset) = (
            (names.index(n), message.get_signal_by_name(n).scale,
             message.get_signal_by_name(n).offset) for n in ("TorqueActual", "VelocityActual"))

        def decode(data: bytes) -> tuple[float, float]:
            raw = unpack(data)
            return raw[t] * t_scale + t_offset, raw[v] * v_scale + v_offset
        return decode

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
        signal = self.messages[message_name("position", actuator)].get_signal_by_name("Speed")
        speed_mm_s = min(max(speed_mm_s, signal.minimum), signal.maximum)
        return self.encode(message_name("position", actuator),
                           {"Position": position_mm, "Speed": speed_mm_s, "Status": int(status)},
                           timestamp_s)

    def encode_diag(self, actuator: str, uncertainty_mm: float, flags: int, input_frames: int,
                    rejected_frames: int, timestamp_s: float = 0.0) -> can.Message:
        """Diagnostic TPDO2; counters wrap (input frames at 16 bits, rejected frames at 8),
        the uncertainty saturates at the UNSIGNED32 maximum (42 949 672.95 mm)."""
        name = message_name("diag", actuator)
        limit = self.messages[name].get_signal_by_name("Uncertainty").maximum
        return self.encode(name, {"Uncertainty": min(max(uncertainty_mm, 0.0), limit),
                                  "Flags": int(flags), "InputFrames": input_frames % 0x10000,
                                  "RejectedFrames": rejected_frames % 0x100},
                           timestamp_s)

    def encode_inputs(self, states: Mapping[str, Mapping[str, int]],
                      timestamp_s: float = 0.0) -> can.Message:
        """I/O module frame from actuator -> reference name -> 0/1, at the configured bits.

        The input bytes (0x6000 sub 1..n, as many as the configured bits need) are built
        whole from can.units.*.hall_bits, the wiring the database's bit signals describe too.
        """
        inputs = 0
        for actuator, refs in states.items():
            bits = self.cfg.can.units[actuator].hall_bits  # type: ignore[index]
            for name, state in refs.items():
                if state:
                    inputs |= 1 << bits[name]
        length = self.messages[IO_MODULE].length
        return can.Message(timestamp=timestamp_s, arbitration_id=self.ids[IO_MODULE],
                           is_extended_id=False, data=inputs.to_bytes(length, "little"))

    def hall_states(self, actuator: str, data: bytes) -> dict[str, int]:
        """Reference name -> 0/1 of one actuator's switches, from the I/O module's data bytes."""
        length = self.messages[IO_MODULE].length
        if len(data) < length:
            raise cantools.database.DecodeError(f"{IO_MODULE} needs {length} byte(s), "
                                                f"got {len(data)}")
        inputs = int.from_bytes(bytes(data[:length]), "little")
        bits = self.cfg.can.units[actuator].hall_bits  # type: ignore[index]
        return {name: (inputs >> bits[name]) & 1 for name in self.cfg.unit(actuator).references_mm}
