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
from collections.abc import Callable, Iterable, Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

import can

from ..errors import UserError
from .scheduler import Sleeper

if TYPE_CHECKING:
    from ..config import Config
    from ..measured import Run


@dataclass
class ReplayStats:
    frames: int = 0
    skipped: int = 0
    send_errors: int = 0
    late_max_s: float = 0.0
    duration_s: float = 0.0
    log_span_s: float = 0.0


def read_log(path: str | Path) -> list[can.Message]:
    """All frames of a CAN log python-can reads (BLF, ASC, CSV, candump log, TRC, MF4)."""
    try:
        with can.LogReader(path) as reader:
            frames = list(reader)
    except FileNotFoundError:
        raise UserError(f"{path}: no such file") from None
    except Exception as exc:      # each format fails in its own way
        raise UserError(f"{path}: cannot read CAN log: {exc}") from None
    if not frames:
        raise UserError(f"{path}: the log holds no frames")
    return frames


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
                   heartbeat_period_s: float | None = 0.1) -> list[can.Message]:
    """The frames a machine with these runs would put on the bus for the service: Sevcon,
    oil temperature and Hall inputs (the project's BLF writer, without the logged position
    frames, which are the service's own IDs) plus, optionally, the controllers' OPERATIONAL
    heartbeats; in log order, timestamps the runs' times."""
    import dataclasses
    import tempfile

    import numpy as np

    from ..canbus.dbc import FrameCodec, message_name
    from ..canbus.log import write_blf
    inputs_only = {a: dataclasses.replace(r, position_mm=np.full(len(r.time_s), np.nan))
                   for a, r in runs.items()}
    with tempfile.TemporaryDirectory(prefix="ddh-vsensor-frames-") as tmp:
        path = Path(tmp) / "machine.blf"
        write_blf(path, inputs_only, cfg)
        frames = read_log(path)
    if heartbeat_period_s:
        codec = FrameCodec(cfg)
        end = max(float(r.time_s[-1]) for r in runs.values())
        for a in runs:
            frame_id = codec.ids[message_name("heartbeat", a)]
            frames += [can.Message(timestamp=float(t), arbitration_id=frame_id,
                                   is_extended_id=False, data=bytes([5]))
                       for t in np.arange(0.0, end + 1e-9, heartbeat_period_s)]
        frames.sort(key=lambda m: m.timestamp)     # stable: the log's order within a time
    return frames
