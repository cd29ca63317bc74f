"""The daemon's day summaries (:mod:`ddh_vsensor.diagnosis.day_summary`): each unit's Sevcon
samples into its :class:`.SampleFeed` (in the loop, per integrated frame: well under a
microsecond), every :data:`BLOCK_S` the kept samples to one worker process, which cuts them
into stretches, runs the fleet analysis' own code on each and writes the machine's day to
``<state_dir>/summaries/<machine>_<YYYY-MM-DD>.summary.json`` (the files are the export:
copy them off the machine as they are).

A process, not a thread: a stretch's analysis holds the interpreter ~0.35 s per unit and
minute of work, which would stall the loop's publishing ticks in slices of the interpreter's
switch interval; the worker runs at a lower priority (nice :data:`NICE`), its tables never
weigh on the daemon's memory, and its imports and start-up (~1 s) are off the loop. It is
started with the first block, restarted (going on from the day's file) when it dies, given
up after :data:`MAX_RESTARTS`; blocks wait for it in a queue, at most :data:`MAX_QUEUED`
(beyond, they are dropped and counted: the worker sees the gap and ends the stretch there).
A stop hands the worker the last samples and waits up to :data:`STOP_WAIT_S` for the day's
file. A killed daemon loses the samples not yet handed over (up to :data:`BLOCK_S`): its
worker, seeing its input end (or on SIGTERM), writes the day; a power cut loses what came
since the worker last wrote it (:data:`SAVE_INTERVAL_S`). The worker judges the machine's
health whenever it writes a day (and as it starts) and hands it back: ``on_health`` gets it
in the loop's thread (from :meth:`SummaryRecorder.ship`).
"""

from __future__ import annotations

import logging
import math
import pickle
import queue
import re
import socket
import struct
import subprocess
import sys
import threading
import time
from collections.abc import Callable
from pathlib import Path
from typing import IO, Any

from ddh_vsensor.config import Config
from ddh_vsensor.estimator.day_samples import (MACHINE_RE, SAVE_INTERVAL_S, SampleFeed,
                                              SummaryError, machine_name)
from ddh_vsensor.errors import UserError

HEALTH_FILE = "health.json"       # ddh_vsensor.diagnosis.health.FILE (not imported: the loop)

log = logging.getLogger(__name__)

BLOCK_S = 10.0                # samples handed to the worker this often
MAX_QUEUED = 60               # blocks waiting for the worker (10 minutes of a unit's work)
MAX_RESTARTS = 3
NICE = 10
STOP_WAIT_S = 5.0            # within the unit's TimeoutStopSec (10 s) with the rest of a stop
SUBDIR = "summaries"


def default_machine() -> str:
    """The host's name, as far as it makes a machine name (see ``run --machine``)."""
    name = re.sub(r"[^A-Za-z0-9._-]", "-", socket.gethostname().split(".")[0])[:64]
    return name if MACHINE_RE.fullmatch(name) else "machine"


def check_machine(name: str) -> str:
    try:
        return machine_name(name)
    except SummaryError as exc:
        raise UserError(f"--machine: {exc}") from None


class SummaryRecorder:
    """The daemon's side: one feed per unit (:attr:`feeds`, set on the units), :meth:`ship`
    from the housekeeping tick, :meth:`close` at a stop."""

    def __init__(self, cfg: Config, machine: str, state_dir: Path,
                 clock: Callable[[], float] = time.monotonic,
                 save_interval_s: float = SAVE_INTERVAL_S,
                 on_health: Callable[[dict], None] | None = None) -> None:
        self.cfg, self.machine = cfg, machine_name(machine)
        self.directory = Path(state_dir) / SUBDIR
        self.health_path = Path(state_dir) / HEALTH_FILE
        self.on_health = on_health
        self.clock, self.save_interval_s = clock, save_interval_s
        self.feeds = {a: SampleFeed(list(cfg.unit(a).references_mm)) for a in cfg.can.units}
        self._worker: Worker | None = None
        self.shipped = 0
        self.dropped = 0              # blocks the worker was too far behind for
        self.restarts = 0
        self.disabled = False
        self._next_ship_s = -math.inf

    def ship(self, force: bool = False) -> None:
        """Every :data:`BLOCK_S` (or now: ``force``), the kept samples to the worker; the
        worker's notes into the log."""
        if self._worker is not None:
            self._collect()
        now = self.clock()
        if not force and now < self._next_ship_s:
            return
        self._next_ship_s = now + BLOCK_S
        for actuator, feed in self.feeds.items():
            block = feed.take()
            if block is None or not self._alive():
                continue
            assert self._worker is not None
            if self._worker.queued >= MAX_QUEUED:
                self.dropped += 1
                log.warning("day summary: the worker is %d blocks behind; a block of %s "
                            "dropped (%d so far)", self._worker.queued, actuator, self.dropped)
                continue
            self._worker.send(("feed", actuator, block))
            self.shipped += 1

    def _alive(self) -> bool:
        """The worker, started (again) if need be; False once given up."""
        if self.disabled:
            return False
        worker = self._worker
        if worker is not None and worker.alive():
            return True
        if worker is not None:
            self.restarts += 1
            if self.restarts > MAX_RESTARTS:
                self.disabled = True
                log.error("day summary: the worker ended (exit %s) %d times; no more day "
                          "summaries until a restart", worker.exitcode, self.restarts)
                return False
            log.warning("day summary: the worker ended (exit %s); started again, going on "
                        "from the day's file", worker.exitcode)
        try:
            self._worker = Worker(("start", self.cfg, self.machine, str(self.directory),
                                   self.save_interval_s, str(self.health_path)))
        except OSError as exc:
            self.disabled = True
            log.error("day summary: cannot start its worker (%s); no day summaries", exc)
            return False
        return True

    def close(self, wait_s: float = STOP_WAIT_S) -> bool:
        """The last samples to the worker, which ends every stretch and writes the day; True
        when it did so within ``wait_s`` (blocking: run it off the loop)."""
        self.ship(force=True)
        worker = self._worker
        if worker is None:
            return True
        done = worker.close(wait_s)
        self._collect()
        if not done:
            log.warning("day summary: the worker did not finish within %g s; the day's file "
                        "is as last written", wait_s)
        return done

    def _collect(self) -> None:
        assert self._worker is not None
        for doc in self._worker.collect():
            if self.on_health is not None:
                self.on_health(doc)


class Worker:
    """The worker process (``python -m ddh_vsensor.service.summary_worker``), messages
    pickled both ways: a plain process, so nothing of the daemon's own ``__main__`` runs
    again in it, and its end of the pipe closed by the daemon's death ends it. A thread
    writes (the loop never waits for the pipe), another reads."""

    def __init__(self, start: tuple) -> None:
        self.process = subprocess.Popen(
            [sys.executable, "-m", "ddh_vsensor.service.summary_worker"],
            stdin=subprocess.PIPE, stdout=subprocess.PIPE, close_fds=True)
        self._out: queue.SimpleQueue[tuple | None] = queue.SimpleQueue()
        self._in: queue.SimpleQueue[tuple] = queue.SimpleQueue()
        self.queued = 0               # blocks handed over, not yet done
        assert self.process.stdin is not None and self.process.stdout is not None
        threading.Thread(target=self._write, args=(self.process.stdin,), daemon=True,
                         name="day summary writer").start()
        self._reader = threading.Thread(target=self._read, args=(self.process.stdout,),
                                        daemon=True, name="day summary reader")
        self._reader.start()
        self._out.put(start)

    @property
    def exitcode(self) -> int | None:
        return self.process.poll()

    def alive(self) -> bool:
        return self.process.poll() is None

    def send(self, message: tuple) -> None:
        self.queued += 1
        self._out.put(message)

    def _write(self, pipe: IO[bytes]) -> None:
        try:
            while (message := self._out.get()) is not None:
                write_message(pipe, message)
            pipe.close()
        except (OSError, ValueError):
            pass                      # the worker ended: its exit code says why

    def _read(self, pipe: IO[bytes]) -> None:
        try:
            while (message := read_message(pipe)) is not None:
                self._in.put(message)
        except (OSError, ValueError, EOFError, pickle.UnpicklingError):
            pass

    def collect(self) -> list[dict]:
        """The worker's answers so far: blocks done, notes logged; the health documents it
        handed over, oldest first."""
        health = []
        while True:
            try:
                kind, text = self._in.get_nowait()
            except queue.Empty:
                return health
            if kind == "done":
                self.queued = max(self.queued - 1, 0)
            elif kind == "health":
                health.append(text)
            elif kind == "warning":
                log.warning("day summary: %s", text)
            else:
                log.info("day summary: %s", text)

    def close(self, wait_s: float) -> bool:
        """Ask the worker to finish (every stretch ended, the day written), wait up to
        ``wait_s``; True when it ended by itself."""
        self._out.put(("close",))
        self._out.put(None)
        try:
            self.process.wait(wait_s)
        except subprocess.TimeoutExpired:
            self.process.kill()
            self.process.wait()
        self._reader.join(1.0)
        return self.process.returncode == 0


_HEADER = struct.Struct("<I")


def write_message(pipe: IO[bytes], message: tuple) -> None:
    data = pickle.dumps(message, protocol=pickle.HIGHEST_PROTOCOL)
    pipe.write(_HEADER.pack(len(data)) + data)
    pipe.flush()


def read_message(pipe: IO[bytes]) -> Any:
    """The next message (None: the other side closed the pipe)."""
    head = pipe.read(_HEADER.size)
    if len(head) < _HEADER.size:
        return None
    data = pipe.read(_HEADER.unpack(head)[0])
    return pickle.loads(data)
