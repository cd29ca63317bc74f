"""CAN logs as measured runs: runs -> the frames the machine would carry (BLF), logs -> runs.

A CSV run and the BLF written from it describe the same data, up to the quantisation of the
frames (torque 1/16 N·m, speed 1 rpm, oil 0.1 °C, position one measuring step).
"""

from __future__ import annotations

import io
from collections.abc import Iterator, Mapping
from pathlib import Path

import can
import cantools
import numpy as np
from can.io.player import MESSAGE_READERS

from ddh_vsensor.config import Config, ConfigError
from ddh_vsensor.atomic import atomic_path
from ddh_vsensor.measured import MeasuredDataError, Run
from ddh_vsensor.canbus.dbc import IO_MODULE, OIL_TEMP, FrameCodec, message_name
from ddh_vsensor.canbus.layout import SEVCON_HEARTBEAT_MS

# python-can's BLF header holds wall-clock start times only (from 1990 on); earlier, relative
# times would be shifted to the first frame, so the writer is pinned to a zero start instead.
_BLF_WALL_CLOCK_MIN_S = 631152000.0
# Frame order within one timestamp: the oil temperature and Hall inputs of a sample come before
# its Sevcon frame, so a reader integrating on Sevcon frames sees them in the same step.
_OIL, _IO, _SEVCON, _POSITION, _HEARTBEAT = range(5)
NMT_OPERATIONAL = 0x05          # CiA 301 heartbeat byte of a node in OPERATIONAL


# The I/O module's event timer: without a change of its inputs it sends at least this often.
IO_REFRESH_S = 0.1


def _latest(event_time_s: np.ndarray, time_s: np.ndarray) -> np.ndarray:
    """Index of the latest event at or before each time (the first event before any)."""
    return np.maximum(np.searchsorted(event_time_s, time_s, "right") - 1, 0)


def io_frames(runs: Mapping[str, Run]) -> tuple[np.ndarray, dict[str, dict[str, np.ndarray]]]:
    """When the I/O module sends, with every switch's state in each frame (actuator ->
    switch -> 0/1 per frame). Where the runs timed their switches' changes, as CiA 401
    modules do by default (can-facts): on every change, at its own time, and every
    :data:`IO_REFRESH_S` at the samples. Else (a CSV's rows) at every sample: a log that
    knows the changes no finer than its samples must not claim to."""
    sample_t = np.unique(np.concatenate([run.time_s for run in runs.values()]))
    on_change = all(set(run.ref_edge_s) == set(run.refs) for run in runs.values())
    tick = np.floor((sample_t - sample_t[0]) / IO_REFRESH_S + 1e-9)
    times = [sample_t[np.concatenate([[True], np.diff(tick) > 0])] if on_change else sample_t]
    since: dict[tuple[str, str], np.ndarray] = {}     # from when each sample's state holds
    for a, run in runs.items():
        for name, state in run.refs.items():
            start = run.time_s.copy()
            k = np.flatnonzero(state[1:] != state[:-1]) + 1
            edge = run.ref_edge_s.get(name)
            if on_change and edge is not None:
                timed = k[np.isfinite(edge[k])]
                start[timed] = edge[timed]
            since[a, name] = start
            times.append(start[k])
    io_t = np.unique(np.concatenate(times))
    return io_t, {a: {name: run.refs[name][_latest(since[a, name], io_t)]
                      for name in run.refs} for a, run in runs.items()}


def io_sends_on_change(io_time_s: np.ndarray, sample_time_s: np.ndarray) -> bool:
    """Whether the I/O module's frames time the switches' changes: it sends on change of
    state, so less often than the drives are sampled. A module sending at every sample
    (cyclic, synchronous) says nothing finer than the samples."""
    if len(io_time_s) < 2 or len(sample_time_s) < 2:
        return False
    return bool(np.median(np.diff(io_time_s)) > 1.5 * np.median(np.diff(sample_time_s)))


def edge_times(io_time_s: np.ndarray, io_state: np.ndarray, sample_time_s: np.ndarray,
               state: np.ndarray) -> np.ndarray:
    """Per sample, the time of the frame that brought the state the sample first shows (NaN
    where the sample shows no change); ``state`` is ``io_state`` held at the samples. All NaN
    where every change came at a sample's own time (within 1 % of its period): a module, or
    a logger, that stamps its changes with the samples' times times them no finer."""
    out = np.full(len(sample_time_s), np.nan)
    f = np.flatnonzero(io_state[1:] != io_state[:-1]) + 1
    k = np.searchsorted(sample_time_s, io_time_s[f], "left")
    ok = k < len(sample_time_s)
    np.fmax.at(out, k[ok], io_time_s[f[ok]])   # several in one sample: the last one counts
    out[np.concatenate([[True], state[1:] == state[:-1]])] = np.nan
    timed = np.flatnonzero(np.isfinite(out))
    if len(timed) and len(sample_time_s) > 1:
        tolerance_s = 0.01 * float(np.median(np.diff(sample_time_s)))
        if np.all(sample_time_s[timed] - out[timed] <= tolerance_s):
            out[:] = np.nan
    return out


def heartbeat_ids(cfg: Config, units: list[str]) -> list[int]:
    """The heartbeat COB-ID (0x700 + node ID) of each unit's motor controller: the node the
    service watches (``faults.heartbeat_node_ids``), else its Sevcon's node."""
    return [0x700 + cfg.faults.heartbeat_node_ids.get(
        unit, cfg.can.units[unit].sevcon_node_id) for unit in units]  # type: ignore[index]


def heartbeat_times(runs: Mapping[str, Run]) -> np.ndarray:
    """When the controllers send their heartbeats: every :data:`SEVCON_HEARTBEAT_MS` (the
    producer time of the frame layout) from the first sample to the last."""
    start = min(float(run.time_s[0]) for run in runs.values())
    end = max(float(run.time_s[-1]) for run in runs.values())
    period_s = SEVCON_HEARTBEAT_MS / 1000.0
    return start + period_s * np.arange(int(np.floor((end - start) / period_s + 1e-9)) + 1)


def _position_speed_mm_s(run: Run) -> np.ndarray:
    """Speed a draw-wire sensor would report, from the sampled positions (0 if too few)."""
    speed = np.zeros(len(run.time_s))
    sampled = ~np.isnan(run.position_mm)
    if sampled.sum() >= 2:
        speed[sampled] = np.gradient(run.position_mm[sampled], run.time_s[sampled])
    return speed


def _require_can_unit(cfg: Config, actuator: str) -> None:
    if actuator not in cfg.can.units:
        raise ConfigError(cfg.source, f"can.units.{actuator}", "missing: the frames of the "
                          f"{actuator} have no node IDs")


def _check_refs(runs: Mapping[str, Run], cfg: Config) -> None:
    for actuator, run in runs.items():
        _require_can_unit(cfg, actuator)
        bits = cfg.can.units[actuator].hall_bits  # type: ignore[index]
        unknown = sorted(set(run.refs) - set(bits))
        if unknown:
            raise MeasuredDataError(run.source, f"reference(s) {', '.join(unknown)} have no "
                                    f"input bit in can.units.{actuator}.hall_bits of "
                                    f"{cfg.source}")


def write_blf(path: str | Path, runs: Mapping[str, Run], cfg: Config) -> None:
    """Write the frames of every sample of every run (actuator -> run) to a BLF; atomic.

    Per sample: the Sevcon TPDO1 of its actuator, the oil temperature (from the first run)
    and the CiA 406 position frame where the position was sampled; frame timestamps are
    time_s. The I/O module's input bytes, every actuator's switch states, as
    :func:`io_frames` schedules them. The controllers' OPERATIONAL heartbeats
    (:func:`heartbeat_times`), as a service replayed this log expects them.
    """
    if not runs:
        raise MeasuredDataError(str(path), "no run to write")
    _check_refs(runs, cfg)
    codec = FrameCodec(cfg)
    actuators = list(runs)
    oil_actuator = actuators[0]
    if min(float(run.time_s[0]) for run in runs.values()) < 0.0:
        raise MeasuredDataError(str(path), "time_s starts below 0 s; BLF holds times from 0 "
                                "or wall-clock times")
    io_time_s, io_states = io_frames(runs)
    # Python lists: cantools and can.Message work per frame, on plain floats.
    refs = {a: {name: state.tolist() for name, state in io_states[a].items()}
            for a in actuators}
    columns = {a: (runs[a].torque_nm.tolist(), runs[a].speed_rpm.tolist(),
                   runs[a].position_mm.tolist(), _position_speed_mm_s(runs[a]).tolist())
               for a in actuators}
    oil_temp_c = runs[oil_actuator].oil_temp_c.tolist()

    # One row per frame: time, kind, actuator index, sample index; sorted by time then kind.
    parts = [(runs[oil_actuator].time_s, _OIL, 0, np.arange(len(runs[oil_actuator].time_s))),
             (io_time_s, _IO, 0, np.arange(len(io_time_s)))]
    hb_time_s, hb_ids = heartbeat_times(runs), heartbeat_ids(cfg, actuators)
    parts += [(hb_time_s, _HEARTBEAT, index, np.zeros(len(hb_time_s), int))
              for index in range(len(actuators))]
    for index, actuator in enumerate(actuators):
        run = runs[actuator]
        sampled = np.flatnonzero(~np.isnan(run.position_mm))
        parts += [(run.time_s, _SEVCON, index, np.arange(len(run.time_s))),
                  (run.time_s[sampled], _POSITION, index, sampled)]
    time_s = np.concatenate([p[0] for p in parts])
    kind = np.concatenate([np.full(len(p[0]), p[1]) for p in parts])
    actuator_index = np.concatenate([np.full(len(p[0]), p[2]) for p in parts])
    sample = np.concatenate([p[3] for p in parts])
    order = np.lexsort((actuator_index, kind, time_s))

    def frame(t: float, k: int, a: int, i: int) -> can.Message:
        actuator = actuators[a]
        torque_nm, speed_rpm, position_mm, speed_mm_s = columns[actuator]
        if k == _SEVCON:
            return codec.encode_sevcon(actuator, torque_nm[i], speed_rpm[i], t)
        if k == _OIL:
            return codec.encode_oil_temp(oil_temp_c[i], t)
        if k == _IO:
            return codec.encode_inputs({b: {name: state[i] for name, state in refs[b].items()}
                                        for b in actuators}, t)
        if k == _HEARTBEAT:
            return can.Message(timestamp=t, arbitration_id=hb_ids[a], is_extended_id=False,
                               data=bytes([NMT_OPERATIONAL]))
        return codec.encode_position(actuator, position_mm[i], speed_mm_s[i], 0, t)

    try:
        with atomic_path(path) as tmp, can.BLFWriter(tmp) as writer:
            if io_time_s[0] < _BLF_WALL_CLOCK_MIN_S:
                writer.start_timestamp = 0.0
            for t, k, a, i in zip(time_s[order].tolist(), kind[order].tolist(),
                                  actuator_index[order].tolist(), sample[order].tolist()):
                try:
                    writer.on_message_received(frame(t, k, a, i))
                except cantools.database.EncodeError as exc:
                    run = runs[oil_actuator if k == _OIL else actuators[a]]
                    raise MeasuredDataError(run.source, f"at time_s {t!r}: cannot encode: "
                                            f"{exc}") from None
    except OSError as exc:
        raise MeasuredDataError(str(path), f"cannot write: {exc.strerror or exc}") from None


def _log_kind(path: Path) -> str:
    """The log format python-can reads a file as: its extension, less a .gz."""
    suffixes = [x.lower() for x in path.suffixes]
    if suffixes and suffixes[-1] == ".gz":
        suffixes.pop()
    return suffixes[-1] if suffixes else ""


def _frames(path: str | Path) -> Iterator[can.Message]:
    """Frames of any log python-can reads; any reader failure means the file is unreadable.
    A BLF goes through the project's one truncation check first (:func:`.blf.whole_part`):
    of a cut-off log, the whole objects are read and the cut is logged."""
    source = str(path)
    if Path(path).is_dir():
        raise MeasuredDataError(source, "cannot read CAN log: a directory, not a file")
    kind = _log_kind(Path(path))
    if kind not in MESSAGE_READERS:
        if not Path(path).exists():
            raise MeasuredDataError(source, "cannot read: no such file")
        raise MeasuredDataError(source, f"cannot read CAN log: its extension ({kind or 'none'}) "
                                f"is no log format's ({', '.join(sorted(MESSAGE_READERS))}, "
                                "each also .gz)")
    if Path(path).suffix.lower() == ".blf":
        from ddh_vsensor.io.blf import read_blf_bytes, whole_part
        raw = whole_part(source, read_blf_bytes(path))
        opened = can.BLFReader(io.BytesIO(raw))
    else:
        try:
            opened = can.LogReader(path)
        except FileNotFoundError:
            raise MeasuredDataError(source, "cannot read: no such file") from None
        except Exception as exc:  # each log format fails in its own way
            raise MeasuredDataError(source, f"cannot read CAN log: {exc}") from None
    try:
        with opened as reader:
            yield from reader
    except Exception as exc:      # each log format fails in its own way
        raise MeasuredDataError(source, f"cannot read CAN log: {exc}") from None


def read_messages(path: str | Path) -> list[can.Message]:
    """Every frame of a CAN log (BLF, ASC, candump, CSV, TRC, MF4 ...), for a tool that
    sends or shows them one by one; MeasuredDataError when there is none."""
    frames = list(_frames(path))
    if not frames:
        raise MeasuredDataError(str(path), "the log holds no frames")
    return frames


def read_can_log(path: str | Path, actuator: str, cfg: Config) -> Run:
    """One actuator's run from a CAN log, sampled at each of its Sevcon TPDO1 frames.

    Oil temperature and switch states are the latest before each sample (the first one for
    samples before it), with the times of the switches' changes where the I/O module sends
    on change of state (:func:`io_sends_on_change`); the position is that of a CiA 406
    frame with the same timestamp, NaN where there is none.
    """
    source = str(path)
    _require_can_unit(cfg, actuator)
    codec = FrameCodec(cfg)
    sevcon, position = message_name("sevcon", actuator), message_name("position", actuator)
    wanted = {codec.ids[name] for name in (sevcon, position, OIL_TEMP, IO_MODULE)}
    streams: dict[str, list[tuple[float, dict[str, float]]]] = {
        sevcon: [], position: [], OIL_TEMP: []}
    inputs: list[tuple[float, dict[str, int]]] = []
    for msg in _frames(path):
        if msg.arbitration_id not in wanted:
            continue
        try:
            decoded = codec.decode(msg)
            if decoded is None:
                continue
            name, signals = decoded
            if name == IO_MODULE:
                inputs.append((msg.timestamp, codec.hall_states(actuator, msg.data)))
            else:
                streams[name].append((msg.timestamp, signals))
        except cantools.database.DecodeError as exc:
            raise MeasuredDataError(source, f"frame 0x{msg.arbitration_id:03X} at "
                                    f"{msg.timestamp!r} s: {exc}") from None

    for name in (sevcon, OIL_TEMP):
        if not streams[name]:
            raise MeasuredDataError(source, f"no {name} frames (ID 0x{codec.ids[name]:03X}) "
                                    f"for the {actuator}")
    time_s = np.array([t for t, _ in streams[sevcon]])
    step_s = np.diff(time_s)
    if (step_s <= 0.0).any():
        row = int(np.argmax(step_s <= 0.0)) + 1
        raise MeasuredDataError(source, f"{sevcon} frames not in increasing time at "
                                f"{time_s[row]!r} s")

    def stream(name: str, signal: str) -> tuple[np.ndarray, np.ndarray]:
        t = np.array([t for t, _ in streams[name]])
        v = np.array([s[signal] for _, s in streams[name]], dtype=np.float64)
        order = np.argsort(t, kind="stable")
        return t[order], v[order]

    oil_time_s, oil_temp_c = stream(OIL_TEMP, "OilTemp")
    position_mm = np.full(len(time_s), np.nan)
    if streams[position]:
        pos_time_s, pos_mm = stream(position, "Position")
        at = np.minimum(np.searchsorted(time_s, pos_time_s), len(time_s) - 1)
        same = time_s[at] == pos_time_s
        position_mm[at[same]] = pos_mm[same]
    refs: dict[str, np.ndarray] = {}
    edges: dict[str, np.ndarray] = {}
    if inputs:
        inputs.sort(key=lambda item: item[0])
        io_time_s = np.array([t for t, _ in inputs])
        held = _latest(io_time_s, time_s)
        timed = io_sends_on_change(io_time_s, time_s)
        for name in cfg.unit(actuator).references_mm:
            io_state = np.array([states[name] for _, states in inputs], dtype=np.uint8)
            refs[name] = io_state[held]
            if timed:
                edges[name] = edge_times(io_time_s, io_state, time_s, refs[name])
    return Run(time_s=time_s,
               speed_rpm=np.array([s["VelocityActual"] for _, s in streams[sevcon]], float),
               torque_nm=np.array([s["TorqueActual"] for _, s in streams[sevcon]], float),
               oil_temp_c=oil_temp_c[_latest(oil_time_s, time_s)],
               position_mm=position_mm, refs=refs,
               comments=[f"CAN log {source}, actuator {actuator}"], source=source,
               ref_edge_s=edges)
