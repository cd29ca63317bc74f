"""BLF logs as arrays: the frames of a log read in bulk, decoded and encoded a column at a time.

python-can reads a BLF one ``Message`` at a time (~0.4 M frames/s per core here) and cantools
decodes one frame at a time; a fleet's logs are mostly classic CAN frames of a few IDs, so
this reads the decompressed containers with one numpy view and decodes every frame of an ID
at once from the DBC's signal definitions. The header is parsed with python-can's own
structures; a log holding anything but classic CAN frames (CAN FD, error frames, markers) is
read through python-can instead. Equality with python-can and cantools is what the tests
check: same timestamps, IDs and data; same run as :func:`.log.read_can_log`.
"""

from __future__ import annotations

import io
import logging
import zlib
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path

import can
import numpy as np
from can.io import blf

from ddh_vsensor.config import Config
from ddh_vsensor.measured import MeasuredDataError, Run
from ddh_vsensor.canbus.dbc import IO_MODULE, OIL_TEMP, FrameCodec, message_name
from ddh_vsensor.io.log import (_BLF_WALL_CLOCK_MIN_S, NMT_OPERATIONAL, _latest, edge_times,
                                heartbeat_ids, heartbeat_times, io_frames, io_sends_on_change)

# One classic CAN frame with a v1 object header: base (16) + v1 (16) + CAN_MSG (16) bytes.
_FRAME = np.dtype([("sig", "S4"), ("hsize", "<u2"), ("hver", "<u2"), ("size", "<u4"),
                   ("type", "<u4"), ("flags", "<u4"), ("client", "<u2"), ("ver", "<u2"),
                   ("ts", "<u8"), ("channel", "<u2"), ("mflags", "u1"), ("dlc", "u1"),
                   ("id", "<u4"), ("data", "u1", (8,))])


log = logging.getLogger(__name__)


@dataclass(frozen=True)
class Cut:
    """Where a BLF stops in the middle of an object (a copy or a logger stopped short): the
    objects before ``at_byte`` are whole, the rest of the file is not read."""

    at_byte: int
    size_bytes: int

    @property
    def problem(self) -> str:
        return f"object at byte {self.at_byte} cut off"

    def warning(self, source: str) -> str:
        return (f"{source}: truncated BLF: {self.problem}; read the whole objects before it, "
                f"{self.at_byte} of {self.size_bytes} bytes "
                f"({100.0 * self.at_byte / self.size_bytes:.0f} %)")


def whole_part(source: str, raw: bytes, need_whole: bool = False) -> bytes:
    """The bytes of a BLF up to the end of its last whole object: the one truncation check
    of every reader of the project (bulk here, python-can's in :mod:`.log`). A cut is logged
    as a warning naming the file and how much was read, or, with ``need_whole`` (a tool
    that must not work on part of a log), refused. MeasuredDataError when the file is empty
    or not a BLF."""
    hs, base = blf.FILE_HEADER_STRUCT, blf.OBJ_HEADER_BASE_STRUCT
    if not raw:
        raise MeasuredDataError(source, "cannot read CAN log: the file is empty")
    if len(raw) < hs.size or raw[:4] != b"LOGG":
        raise MeasuredDataError(source, "cannot read CAN log: not a BLF file (no BLF header)")
    pos = hs.unpack_from(raw)[1]
    while pos < len(raw):
        if pos + base.size > len(raw):
            break
        sig, _, _, size, _ = base.unpack_from(raw, pos)
        if sig != b"LOBJ" or size < base.size:
            raise MeasuredDataError(source, f"cannot read CAN log: no object at byte {pos}")
        if pos + size > len(raw):
            break
        pos += size + size % 4
    if pos >= len(raw):
        return raw
    cut = Cut(pos, len(raw))
    if pos == hs.unpack_from(raw)[1]:
        raise MeasuredDataError(source, f"cannot read CAN log: {cut.problem}, the first: no "
                                "whole frame")
    if need_whole:
        raise MeasuredDataError(source, f"cannot read CAN log: {cut.problem}")
    log.warning(cut.warning(source))
    return raw[:pos]


@dataclass
class Frames:
    """Every frame of a log: timestamp (s), ID, length, data bytes (N x 8)."""

    timestamp_s: np.ndarray
    arbitration_id: np.ndarray
    dlc: np.ndarray
    data: np.ndarray
    start_timestamp_s: float

    def __len__(self) -> int:
        return len(self.timestamp_s)


def _via_python_can(raw: bytes) -> Frames:
    with can.BLFReader(io.BytesIO(raw)) as reader:
        start = reader.start_timestamp
        msgs = [m for m in reader if not (m.is_error_frame or m.is_fd)]
    data = np.zeros((len(msgs), 8), np.uint8)
    for i, m in enumerate(msgs):
        data[i, :len(m.data)] = np.frombuffer(bytes(m.data), np.uint8)
    return Frames(np.array([m.timestamp for m in msgs], float),
                  np.array([m.arbitration_id for m in msgs], np.uint32),
                  np.array([m.dlc for m in msgs], np.uint8), data, start)


def read_blf_bytes(path: str | Path) -> bytes:
    """A BLF file's bytes, MeasuredDataError when it cannot be read."""
    try:
        return Path(path).read_bytes()
    except OSError as exc:
        raise MeasuredDataError(str(path), f"cannot read: {exc.strerror or exc}") from None


def read_frames(path: str | Path, raw: bytes | None = None, need_whole: bool = False) -> Frames:
    """The frames of a BLF file (its bytes ``raw`` when the caller has read them already),
    of its whole objects if it is cut off (:func:`whole_part`); MeasuredDataError when it is
    not a readable BLF."""
    source = str(path)
    raw = whole_part(source, read_blf_bytes(path) if raw is None else raw, need_whole)
    header = blf.FILE_HEADER_STRUCT.unpack_from(raw)
    start = blf.systemtime_to_timestamp(header[14:22])
    pos, chunks = header[1], []
    base, cont = blf.OBJ_HEADER_BASE_STRUCT, blf.LOG_CONTAINER_STRUCT
    try:
        while pos + base.size <= len(raw):
            sig, _, _, size, kind = base.unpack_from(raw, pos)
            if sig != b"LOBJ" or size < base.size + cont.size:
                raise ValueError(f"no object at byte {pos}")
            if kind != blf.LOG_CONTAINER:
                return _via_python_can(raw)
            method, _ = cont.unpack_from(raw, pos + base.size)
            body = raw[pos + base.size + cont.size:pos + size]
            if method == blf.ZLIB_DEFLATE:
                chunks.append(zlib.decompress(body))
            elif method == blf.NO_COMPRESSION:
                chunks.append(body)
            else:
                return _via_python_can(raw)
            pos += size + size % 4
    except (ValueError, zlib.error) as exc:
        raise MeasuredDataError(source, f"cannot read CAN log: {exc}") from None
    data = b"".join(chunks)
    if len(data) % _FRAME.itemsize:
        return _via_python_can(raw)
    rec = np.frombuffer(data, _FRAME)
    if not (np.all(rec["sig"] == b"LOBJ") and np.all(rec["size"] == _FRAME.itemsize)
            and np.all(rec["hver"] == 1) and np.all(np.isin(rec["type"], (1, 86)))
            and not np.any(rec["mflags"] & 0x80) and not np.any(rec["id"] & 0x80000000)):
        return _via_python_can(raw)
    factor = np.where(rec["flags"] == 1, 1e5, 1e9)
    ts = rec["ts"].astype(np.float64) / factor + start
    return Frames(ts, rec["id"].astype(np.uint32), rec["dlc"].copy(), rec["data"].copy(), start)


def _raw(data: np.ndarray) -> np.ndarray:
    return np.ascontiguousarray(data).view("<u8")[:, 0]


def _byte_mask(length: int) -> np.uint64:
    """The bits of a frame's first ``length`` data bytes (the rest of the 8 is padding)."""
    return np.uint64((1 << (8 * length)) - 1)


def decode_signal(message, name: str, data: np.ndarray) -> np.ndarray:
    """A little-endian signal of ``message`` (cantools) for every row of ``data`` (N x 8)."""
    sig = message.get_signal_by_name(name)
    if sig.byte_order != "little_endian":
        raise ValueError(f"{message.name}.{name}: only little-endian signals")
    raw = (_raw(data) >> np.uint64(sig.start)) & np.uint64((1 << sig.length) - 1)
    value = raw.astype(np.int64)
    if sig.is_signed:
        value = np.where(value >= 1 << (sig.length - 1), value - (1 << sig.length), value)
    return value * sig.scale + sig.offset


def encode_signals(message, signals: Mapping[str, np.ndarray]) -> np.ndarray:
    """Data bytes (N x 8) of ``message`` with each little-endian signal's scaled values."""
    raw = None
    for name, values in signals.items():
        sig = message.get_signal_by_name(name)
        v = np.round((np.asarray(values, float) - sig.offset) / sig.scale).astype(np.int64)
        lo, hi = (-(1 << (sig.length - 1)), (1 << (sig.length - 1)) - 1) if sig.is_signed \
            else (0, (1 << sig.length) - 1)
        if np.any((v < lo) | (v > hi)):
            raise ValueError(f"{message.name}.{name}: value outside the signal's range")
        part = (v.astype(np.uint64) & np.uint64((1 << sig.length) - 1)) << np.uint64(sig.start)
        raw = part if raw is None else raw | part
    return raw.astype("<u8").view(np.uint8).reshape(-1, 8)


_CODECS: dict[int, tuple[Config, FrameCodec]] = {}


def _codec(cfg: Config) -> FrameCodec:
    """One codec per config object (generating its database costs ~30 ms)."""
    if id(cfg) not in _CODECS:
        _CODECS[id(cfg)] = (cfg, FrameCodec(cfg))       # holds cfg: its id stays its own
    return _CODECS[id(cfg)][1]


def frames_to_runs(frames: Frames, cfg: Config, source: str,
                   actuators: tuple[str, ...] | None = None) -> dict[str, Run]:
    """Each actuator's run from the frames, as :func:`.log.read_can_log` builds it."""
    codec = _codec(cfg)
    msgs = codec.messages
    ids = frames.arbitration_id
    order = np.argsort(frames.timestamp_s, kind="stable")
    oil = order[ids[order] == codec.ids[OIL_TEMP]]
    io = order[ids[order] == codec.ids[IO_MODULE]]
    out = {}
    for actuator in actuators or tuple(cfg.can.units):
        sevcon, position = message_name("sevcon", actuator), message_name("position", actuator)
        rows = np.flatnonzero(ids == codec.ids[sevcon])        # in file order, as python-can
        if not len(rows) or not len(oil):
            missing = sevcon if not len(rows) else OIL_TEMP
            raise MeasuredDataError(source, f"no {missing} frames (ID "
                                    f"0x{codec.ids[missing]:03X}) for the {actuator}")
        time_s = frames.timestamp_s[rows]
        step = np.diff(time_s)
        if (step <= 0.0).any():
            row = int(np.argmax(step <= 0.0)) + 1
            raise MeasuredDataError(source, f"{sevcon} frames not in increasing time at "
                                    f"{time_s[row]!r} s")
        d = frames.data[rows]
        oil_t = frames.timestamp_s[oil]
        oil_c = decode_signal(msgs[OIL_TEMP], "OilTemp", frames.data[oil])
        position_mm = np.full(len(time_s), np.nan)
        prow = order[ids[order] == codec.ids[position]]
        if len(prow):
            pt = frames.timestamp_s[prow]
            pmm = decode_signal(msgs[position], "Position", frames.data[prow])
            at = np.minimum(np.searchsorted(time_s, pt), len(time_s) - 1)
            same = time_s[at] == pt
            position_mm[at[same]] = pmm[same]
        refs, edges = {}, {}
        if len(io):
            io_t = frames.timestamp_s[io]
            held = _latest(io_t, time_s)
            timed = io_sends_on_change(io_t, time_s)
            inputs = _raw(frames.data[io]) & _byte_mask(msgs[IO_MODULE].length)
            bits = cfg.can.units[actuator].hall_bits
            for name in cfg.unit(actuator).references_mm:
                io_state = ((inputs >> np.uint64(bits[name])) & np.uint64(1)).astype(np.uint8)
                refs[name] = io_state[held]
                if timed:
                    edges[name] = edge_times(io_t, io_state, time_s, refs[name])
        out[actuator] = Run(time_s=time_s,
                            speed_rpm=decode_signal(msgs[sevcon], "VelocityActual", d),
                            torque_nm=decode_signal(msgs[sevcon], "TorqueActual", d),
                            oil_temp_c=oil_c[_latest(oil_t, time_s)], position_mm=position_mm,
                            refs=refs, comments=[f"CAN log {source}, actuator {actuator}"],
                            source=source, ref_edge_s=edges)
    return out


def write_blf_inputs(path: str | Path, runs: Mapping[str, Run], cfg: Config) -> int:
    """The frames :func:`.log.write_blf` writes for runs without positions (Sevcon, oil,
    I/O module, the controllers' heartbeats), encoded a column at a time; returns the
    number of frames."""
    from ddh_vsensor.atomic import atomic_path
    codec = FrameCodec(cfg)
    actuators = list(runs)
    oil_actuator = actuators[0]
    io_time, io_states = io_frames(runs)
    inputs = np.zeros(len(io_time), np.uint64)
    for a in actuators:
        for name, state in io_states[a].items():
            inputs |= state.astype(np.uint64) << np.uint64(cfg.can.units[a].hall_bits[name])
    parts = [(runs[oil_actuator].time_s, 0, 0, encode_signals(
        codec.messages[OIL_TEMP], {"OilTemp": runs[oil_actuator].oil_temp_c}),
        codec.ids[OIL_TEMP], codec.messages[OIL_TEMP].length)]
    io_data = inputs.astype("<u8").view(np.uint8).reshape(-1, 8)
    parts.append((io_time, 1, 0, io_data, codec.ids[IO_MODULE],
                  codec.messages[IO_MODULE].length))
    for i, a in enumerate(actuators):
        name = message_name("sevcon", a)
        parts.append((runs[a].time_s, 2, i, encode_signals(
            codec.messages[name], {"TorqueActual": runs[a].torque_nm,
                                    "VelocityActual": runs[a].speed_rpm}),
            codec.ids[name], codec.messages[name].length))
    hb_time = heartbeat_times(runs)
    hb_data = np.zeros((len(hb_time), 8), np.uint8)
    hb_data[:, 0] = NMT_OPERATIONAL
    parts += [(hb_time, 3, i, hb_data, frame_id, 1)
              for i, frame_id in enumerate(heartbeat_ids(cfg, actuators))]
    t = np.concatenate([p[0] for p in parts])
    kind = np.concatenate([np.full(len(p[0]), p[1]) for p in parts])
    act = np.concatenate([np.full(len(p[0]), p[2]) for p in parts])
    data = np.concatenate([p[3] for p in parts])
    fid = np.concatenate([np.full(len(p[0]), p[4]) for p in parts])
    dlc = np.concatenate([np.full(len(p[0]), p[5]) for p in parts])
    order = np.lexsort((act, kind, t))
    payload = [bytes(row[:n]) for row, n in zip(data[order], dlc[order].tolist())]
    with atomic_path(path) as tmp, can.BLFWriter(tmp) as writer:
        if io_time[0] < _BLF_WALL_CLOCK_MIN_S:
            writer.start_timestamp = 0.0
        for ts, i, p in zip(t[order].tolist(), fid[order].tolist(), payload):
            writer.on_message_received(can.Message(timestamp=ts, arbitration_id=i,
                                                   is_extended_id=False, data=p))
    return len(order)
