"""Timed replay of CAN frames onto a bus, in the event loop (``can.MessageSync`` blocks).

Frame k is due at start + (t_k - t_0) / rate, an absolute deadline: a late frame does not
delay the ones after it. Frames due together go out back to back. ``stamp="log"`` sets each
sent frame's timestamp to the log's time (start-aligned to now), for buses that keep the
sender's timestamps (python-can ``virtual`` with ``preserve_timestamps=True``): the receiver
then integrates in machine time whatever the replay rate. ``stamp="bus"`` leaves the
timestamp to the bus (a real bus stamps on reception; a rate other than 1 then compresses or
stretches time as the receiver sees it).
"""

from __future__ import annotations

import asyncio
import time
from collections.abc import Callable, Iterable, Iterator, Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

import can

from ddh_vsensor.errors import UserError
from ddh_vsensor.service.scheduler import Sleeper

if TYPE_CHECKING:
    from ddh_vsensor.config import Config
    from ddh_vsensor.measured import Run


@dataclass
class ReplayStats:
    frames: int = 0
    skipped: int = 0
    send_errors: int = 0
    late_max_s: float = 0.0
    duration_s: float = 0.0
    log_span_s: float = 0.0


def read_log(path: str | Path) -> list[can.Message]:
    """All frames of a CAN log python-can reads (BLF, ASC, CSV, candump log, TRC, MF4), read
    as every tool of the project reads a log (a cut-off BLF: its whole part, with a
    warning)."""
    from ddh_vsensor.io.log import read_messages
    return read_messages(path)


async def replay(frames: Iterable[can.Message], send: Callable[[can.Message], object], *,
                 rate: float = 1.0, stamp: str = "bus", skip_ids: Iterable[int] = (),
                 progress: Callable[[float], None] | None = None,
                 stop: asyncio.Event | None = None,
                 use_timerfd: bool | None = None) -> ReplayStats:
    """Send ``frames`` (in log order) at their log times divided by ``rate``; ``rate`` 0
    sends as fast as possible. ``progress(log_time_s)`` is called after each frame."""
    if rate < 0:
        raise UserError(f"rate {rate} must be positive (or 0: as fast as possible)")
    if stamp not in ("bus", "log"):
        raise ValueError("stamp must be 'bus' or 'log'")
    skip = set(skip_ids)
    stats = ReplayStats()
    sleeper = Sleeper(use_timerfd)
    start_mono = time.monotonic() + 0.001
    start_wall = time.time() + 0.001
    t0: float | None = None
    try:
        for msg in frames:
            if stop is not None and stop.is_set():
                break
            if t0 is None:
                t0 = msg.timestamp
            offset = msg.timestamp - t0
            stats.log_span_s = offset
            if msg.arbitration_id in skip or msg.is_error_frame:
                stats.skipped += 1
                continue
            if rate > 0:
                due = start_mono + offset / rate
                await sleeper.until(due)
                stats.late_max_s = max(stats.late_max_s, time.monotonic() - due)
            elif stats.frames % 256 == 255:
                await asyncio.sleep(0)
            out = can.Message(timestamp=start_wall + offset if stamp == "log" else 0.0,
                              arbitration_id=msg.arbitration_id,
                              is_extended_id=msg.is_extended_id,
                              is_remote_frame=msg.is_remote_frame, dlc=msg.dlc,
                              data=msg.data, is_fd=msg.is_fd)
            try:
                ok = send(out)
            except can.CanError:
                ok = False
            if ok is False:
                stats.send_errors += 1
            else:
                stats.frames += 1
            if progress is not None:
                progress(offset)
    finally:
        sleeper.close()
    stats.duration_s = time.monotonic() - start_mono
    return stats


def bus_sender(bus: can.BusABC) -> Callable[[can.Message], bool]:
    """A ``send`` for :func:`replay` that counts instead of raising (full queue, bus-off)."""
    def send(msg: can.Message) -> bool:
        try:
            bus.send(msg, timeout=0.05)
        except can.CanError:
            return False
        return True
    return send


def machine_frames(cfg: Config, runs: Mapping[str, Run],
                   heartbeat_period_s: float | None = 0.1) -> Iterator[can.Message]:
    """The frames a machine with these runs would put on the bus for the service, one at a
    time: per sample the oil temperature (from the first run) and the unit's Sevcon TPDO1,
    the I/O module's Hall inputs (every unit's switch states) as it sends them
    (:func:`.canbus.log.io_frames`), as ``write_blf`` orders them (no draw-wire position
    frames: those are the service's own IDs), plus, optionally, the controllers'
    OPERATIONAL heartbeats; in log order, timestamps the runs' times."""
    import heapq

    frames = _input_frames(cfg, runs)
    if not heartbeat_period_s:
        yield from frames
        return
    yield from heapq.merge(frames, _heartbeats(cfg, runs, heartbeat_period_s),
                           key=lambda m: m.timestamp)      # equal times: inputs first


def _input_frames(cfg: Config, runs: Mapping[str, Run]) -> Iterator[can.Message]:
    import numpy as np

    from ddh_vsensor.canbus.dbc import FrameCodec
    from ddh_vsensor.io.log import io_frames
    from ddh_vsensor.measured import MeasuredDataError
    if not runs:
        raise MeasuredDataError("<runs>", "no run to send")
    for unit, run in runs.items():
        unknown = sorted(set(run.refs) - set(cfg.can.units[cfg.require_unit(unit)].hall_bits))
        if unknown:
            raise MeasuredDataError(run.source, f"reference(s) {', '.join(unknown)} have no "
                                    f"input bit in can.units.{unit}.hall_bits of {cfg.source}")
    codec = FrameCodec(cfg)
    units = list(runs)
    oil_run = runs[units[0]]
    io_time_s, io_states = io_frames(runs)
    # Rows (time, kind, unit index, sample), sorted by time, then kind (oil, I/O, Sevcon:
    # a sample's inputs before its Sevcon frame), then unit.
    parts = [(oil_run.time_s, 0, 0), (io_time_s, 1, 0)]
    parts += [(runs[u].time_s, 2, k) for k, u in enumerate(units)]
    time_s = np.concatenate([p[0] for p in parts])
    kind = np.concatenate([np.full(len(p[0]), p[1]) for p in parts])
    unit_index = np.concatenate([np.full(len(p[0]), p[2]) for p in parts])
    sample = np.concatenate([np.arange(len(p[0])) for p in parts])
    order = np.lexsort((unit_index, kind, time_s))
    refs = {u: {name: state.tolist() for name, state in io_states[u].items()} for u in units}
    columns = {u: (runs[u].torque_nm.tolist(), runs[u].speed_rpm.tolist()) for u in units}
    oil_temp_c = oil_run.oil_temp_c.tolist()
    for t, k, a, i in zip(time_s[order].tolist(), kind[order].tolist(),
                          unit_index[order].tolist(), sample[order].tolist()):
        if k == 0:
            yield codec.encode_oil_temp(oil_temp_c[i], t)
        elif k == 1:
            yield codec.encode_inputs({u: {name: state[i] for name, state in refs[u].items()}
                                       for u in units}, t)
        else:
            torque_nm, speed_rpm = columns[units[a]]
            yield codec.encode_sevcon(units[a], torque_nm[i], speed_rpm[i], t)


def _heartbeats(cfg: Config, runs: Mapping[str, Run],
                period_s: float) -> Iterator[can.Message]:
    """Every unit's controller reporting OPERATIONAL every ``period_s`` from the first sample
    to the end of the longest run (the IDs the log writers use: :func:`.io.log.heartbeat_ids`;
    runs on the wall clock start at 1.7e9 s, not 0)."""
    import numpy as np

    from ddh_vsensor.io.log import NMT_OPERATIONAL, heartbeat_ids
    ids = heartbeat_ids(cfg, list(runs))
    start = min(float(r.time_s[0]) for r in runs.values())
    end = max(float(r.time_s[-1]) for r in runs.values())
    for t in (start + np.arange(0.0, end - start + 1e-9, period_s)).tolist():
        for frame_id in ids:
            yield can.Message(timestamp=t, arbitration_id=frame_id, is_extended_id=False,
                              data=bytes([NMT_OPERATIONAL]))
