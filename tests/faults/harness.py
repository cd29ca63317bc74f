"""The fault-injection harness: a python-can-remote hub on 127.0.0.1, ``ddh-vsensor run`` as
its own process (READY and WATCHDOG over a fake NOTIFY_SOCKET, RSS from /proc), a recorder,
a real-time feeder whose frames carry their log times aligned to the wall clock, and the
invariant: whenever the published position is further from the truth than the published
uncertainty, a flag says why."""

from __future__ import annotations

import os
import signal
import socket
import struct
import subprocess
import sys
import threading
import time
import uuid
from collections.abc import Callable, Iterable
from dataclasses import dataclass, field
from pathlib import Path

import can
import numpy as np
import yaml

from ddh_vsensor.canbus.dbc import FrameCodec, message_name
from ddh_vsensor.config import Config
from ddh_vsensor.estimator.flags import EXPLAINING

# Published position and uncertainty are quantised to 0.01 mm each; truth interpolated.
TOLERANCE_MM = 0.05
# An output may reflect frames up to this old (handling latency on a loaded machine); beyond
# it, the truth has moved on and the output must cover that too.
LATENCY_S = 0.1
STARTUP_TIMEOUT_S = 40.0
SO_TIMESTAMP = 29                # Linux; the socket module does not name it


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


class Hub:
    """``python -m can_remote`` on a virtual channel of its own."""

    def __init__(self) -> None:
        self.port = free_port()
        self.proc = subprocess.Popen(
            [sys.executable, "-m", "can_remote", "-i", "virtual", "-c",
             f"faults-{uuid.uuid4().hex[:8]}", "-H", "127.0.0.1", "-p", str(self.port)],
            stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
        end = time.monotonic() + 20.0
        while time.monotonic() < end:
            if self.proc.poll() is not None:
                raise RuntimeError(f"can_remote exited with {self.proc.returncode}")
            try:
                with socket.create_connection(("127.0.0.1", self.port), timeout=0.2):
                    break
            except OSError:
                time.sleep(0.05)
        else:
            self.close()
            raise TimeoutError("can_remote did not listen")
        self.url = f"ws://127.0.0.1:{self.port}/"

    def bus(self, **kwargs) -> can.BusABC:
        return can.Bus(interface="remote", channel=self.url, **kwargs)

    def close(self) -> None:
        if self.proc.poll() is None:
            self.proc.terminate()
            try:
                self.proc.wait(5)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait(5)


def write_config(cfg_raw: dict, path: Path, **overrides: object) -> Path:
    """The reference config with ``section.key`` overrides, written to ``path``."""
    import copy
    data = copy.deepcopy(cfg_raw)
    for dotted, value in overrides.items():
        node = data
        keys = dotted.split(".")
        for k in keys[:-1]:
            node = node.setdefault(k, {})
        node[keys[-1]] = value
    path.write_text(yaml.safe_dump(data))
    return path


class Daemon:
    """``ddh-vsensor run`` in its own process; notify messages kept with their arrival time."""

    def __init__(self, url: str, workdir: Path, name: str, *, config: Path | None = None,
                 state_dir: Path | None = None, watchdog_usec: int | None = None,
                 extra: Iterable[str] = ()) -> None:
        self.notify_path = str(workdir / f"{name}.notify")
        self.sock = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
        self.sock.bind(self.notify_path)
        self.log_path = workdir / f"{name}.log"
        env = {**os.environ, "NOTIFY_SOCKET": self.notify_path, "PYTHONUNBUFFERED": "1"}
        env.pop("WATCHDOG_USEC", None)
        env.pop("WATCHDOG_PID", None)
        if watchdog_usec:
            env["WATCHDOG_USEC"] = str(watchdog_usec)
        args = [sys.executable, "-m", "ddh_vsensor.cli.main", "run", "--interface", "remote",
                "--channel", url]
        args += ["--state-dir", str(state_dir)] if state_dir is not None else ["--no-state"]
        if config is not None:
            args += ["--config", str(config)]
        self._log = open(self.log_path, "wb")
        self.proc = subprocess.Popen([*args, *extra], stdout=self._log,
                                     stderr=subprocess.STDOUT, env=env)
        self.messages: list[tuple[float, str]] = []
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._listen, daemon=True)
        self._thread.start()

    def _listen(self) -> None:
        """Each datagram with the kernel's receive time (SO_TIMESTAMP): a busy test process
        reading late does not shift it."""
        self.sock.setsockopt(socket.SOL_SOCKET, SO_TIMESTAMP, 1)
        self.sock.settimeout(0.1)
        while not self._stop.is_set():
            try:
                data, ancillary, _, _ = self.sock.recvmsg(65536, socket.CMSG_SPACE(16))
            except socket.timeout:
                continue
            except OSError:
                return
            now = time.time()
            for level, kind, value in ancillary:
                if level == socket.SOL_SOCKET and kind == SO_TIMESTAMP:
                    sec, usec = struct.unpack("qq", value[:16])
                    now = sec + usec * 1e-6
            for line in data.decode(errors="replace").splitlines():
                self.messages.append((now, line))

    def wait_for(self, key: str, timeout_s: float = STARTUP_TIMEOUT_S) -> None:
        end = time.monotonic() + timeout_s
        while time.monotonic() < end:
            if any(m.startswith(key) for _, m in list(self.messages)):
                return
            if self.proc.poll() is not None:
                raise AssertionError(f"daemon exited ({self.proc.returncode}):\n{self.log()}")
            time.sleep(0.05)
        raise AssertionError(f"no {key} from the daemon within {timeout_s} s:\n{self.log()}")

    def times(self, key: str) -> list[float]:
        return [t for t, m in list(self.messages) if m.startswith(key)]

    def rss_kb(self) -> int:
        for line in Path(f"/proc/{self.proc.pid}/status").read_text().splitlines():
            if line.startswith("VmRSS:"):
                return int(line.split()[1])
        raise RuntimeError("no VmRSS")

    def log(self) -> str:
        if not self._log.closed:
            self._log.flush()
        return self.log_path.read_text(errors="replace")

    def send_signal(self, sig: int) -> None:
        self.proc.send_signal(sig)

    def stop(self, sig: int = signal.SIGTERM, timeout_s: float = 15.0) -> int | None:
        if self.proc.poll() is None:
            self.proc.send_signal(sig)
            try:
                self.proc.wait(timeout_s)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait(5)
        time.sleep(0.1)
        self._stop.set()
        self._thread.join(2)
        self.sock.close()
        self._log.close()
        return self.proc.returncode


class Recorder:
    """Every frame on the hub, in a thread."""

    def __init__(self, hub: Hub) -> None:
        self.bus = hub.bus()
        self.frames: list[can.Message] = []
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True)
        self._thread.start()

    def _run(self) -> None:
        while not self._stop.is_set():
            msg = self.bus.recv(0.1)
            if msg is not None:
                self.frames.append(msg)

    def close(self) -> None:
        self._stop.set()
        self._thread.join(5)
        self.bus.shutdown()


def feed(hub: Hub, frames: list[can.Message], *, base_wall: float | None = None,
         hook: Callable[[float, can.BusABC], None] | None = None,
         stamp: Callable[[float, float], float] | None = None) -> float:
    """Send ``frames`` (log time order) in real time, each stamped with its log time moved
    to the wall clock: ``base_wall + t``, or ``stamp(t, base_wall)`` (a sender's clock that
    steps). ``hook(t, bus)`` runs before each frame (inject faults). Returns ``base_wall``."""
    bus = hub.bus(preserve_timestamps=True)
    try:
        t0 = frames[0].timestamp
        if base_wall is None:
            base_wall = time.time() + 0.2 - t0
        for msg in frames:
            due = base_wall + msg.timestamp
            delay = due - time.time()
            if delay > 0:
                time.sleep(delay)
            if hook is not None:
                hook(msg.timestamp, bus)
            out = can.Message(timestamp=due if stamp is None else stamp(msg.timestamp,
                                                                         base_wall),
                              arbitration_id=msg.arbitration_id,
                              data=msg.data, dlc=msg.dlc, is_extended_id=msg.is_extended_id,
                              is_remote_frame=msg.is_remote_frame)
            bus.send(out)
    finally:
        bus.shutdown()
    return base_wall


@dataclass
class Output:
    t_wall: float
    position_mm: float
    flags: int
    uncertainty_mm: float
    input_frames: int


@dataclass
class Verdict:
    outputs: int = 0
    unflagged: int = 0
    violations: list[tuple[float, float, float, int]] = field(default_factory=list)
    max_error_mm: float = 0.0

    def describe(self) -> str:
        head = "; ".join(f"t={t:.2f} err={e:.2f} u={u:.2f} flags={f:#x}"
                         for t, e, u, f in self.violations[:5])
        return (f"{len(self.violations)} violations in {self.outputs} outputs "
                f"({self.unflagged} unflagged): {head}")


def outputs(cfg: Config, frames: list[can.Message], actuator: str) -> list[Output]:
    """Each diagnostic frame with the position frame of the same tick before it."""
    codec = FrameCodec(cfg)
    pos_id = codec.ids[message_name("position", actuator)]
    diag_id = codec.ids[message_name("diag", actuator)]
    out, last = [], None
    for msg in frames:
        if msg.arbitration_id == pos_id and not msg.is_extended_id:
            last = (msg.timestamp, codec.decode(msg)[1])
        elif msg.arbitration_id == diag_id and last is not None and not msg.is_extended_id:
            d = codec.decode(msg)[1]
            out.append(Output(last[0], float(last[1]["Position"]), int(last[1]["Status"]),
                              float(d["Uncertainty"]), int(d["InputFrames"])))
            last = None
    return out


def check_invariant(cfg: Config, frames: list[can.Message], actuator: str,
                    truth_t: np.ndarray, truth_mm: np.ndarray, base_wall: float,
                    until_wall: float | None = None) -> Verdict:
    """Every output (up to ``until_wall``) against the truth over the interval it may stand
    for: from the time of the last Sevcon frame the service had received (its InputFrames
    counter, matched against the frames on the bus) to the output's own time less
    LATENCY_S. Unflagged and further than the uncertainty anywhere in it: a violation."""
    codec = FrameCodec(cfg)
    sevcon_id = codec.ids[message_name("sevcon", actuator)]
    sevcon_t = np.array([m.timestamp for m in frames
                         if m.arbitration_id == sevcon_id and not m.is_extended_id])
    verdict = Verdict()
    t_lo, t_hi = truth_t[0], truth_t[-1]
    for o in outputs(cfg, frames, actuator):
        if until_wall is not None and o.t_wall > until_wall:
            break
        verdict.outputs += 1
        n = o.input_frames
        start = sevcon_t[n - 1] - base_wall if 0 < n <= len(sevcon_t) else o.t_wall - \
            base_wall - LATENCY_S
        end = max(start, o.t_wall - base_wall - LATENCY_S)
        ts = np.clip(np.linspace(start, end, max(2, int((end - start) / 0.01) + 2)), t_lo, t_hi)
        err = float(np.max(np.abs(np.interp(ts, truth_t, truth_mm) - o.position_mm)))
        verdict.max_error_mm = max(verdict.max_error_mm, err)
        if o.flags & EXPLAINING:
            continue
        verdict.unflagged += 1
        if err > o.uncertainty_mm + TOLERANCE_MM:
            verdict.violations.append((o.t_wall - base_wall, err, o.uncertainty_mm, o.flags))
    return verdict
