"""``ddh-vsensor demo``: the whole product on a virtual bus, nothing to set up.

The plant simulator runs the machine's work cycle (the first of its configuration's
``work_cycle.cycles``; the reference loader's: the paper's); its Sevcon, oil temperature,
Hall-switch and heartbeat frames are replayed onto a python-can ``virtual`` bus in real time
(``--rate`` for faster); the service, unchanged, estimates and publishes every cylinder as a
CiA 406 sensor; a listener on the same bus shows the published positions next to the
simulator's true ones; a summary of the errors and a figure (true against published position
per cylinder, the paper's Figures 6/8) end it. Before the cycle starts the demo writes the
true start positions to the sensors' preset objects over SDO (as at commissioning) and sets
the diagnostic frame's timer to the position frame's, so that every published position can be
paired with the input frame it includes (the diag frame's input counter).
"""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import dataclasses
import logging
import math
import os
import sys
import time
from pathlib import Path

import numpy as np

from ddh_vsensor.atomic import output_dir, output_file
from ddh_vsensor.errors import UserError
from ddh_vsensor.cli.common import add_config_arg, add_extension_arg, config_from, extensions_from

PAPER_MAX_ERROR_MM = 30.0     # the source paper: about 30 mm maximum error per work cycle
HEARTBEAT_PERIOD_S = 0.1      # the simulated controllers' heartbeat
DEFAULT_FIGURE = "ddh-vsensor-demo.png"


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("demo", help="simulated machine + service on a virtual bus, live view",
                       description="Runs the machine's work cycle (--config; default the "
                       "reference loader and the paper's cycle) on the plant simulator, "
                       "replays its frames onto a virtual CAN bus, runs the service on them "
                       "and shows true against estimated positions live, then an error "
                       "summary.")
    add_config_arg(p)
    p.add_argument("--rate", type=float, default=1.0,
                   help="replay speed-up (default 1: real time)")
    p.add_argument("--speed", type=int, default=4, choices=(1, 2, 3, 4),
                   help="work cycle speed level (default 4, the fastest; the reference "
                        "loader's paper cycle: about 25 s)")
    p.add_argument("--cycles", type=int, default=1, help="work cycles (default 1)")
    p.add_argument("--payload-kg", type=float, default=0.0)
    p.add_argument("--oil-temp-c", type=float, default=27.0)
    add_extension_arg(p)
    p.add_argument("--figure", metavar="FILE.png", default=DEFAULT_FIGURE,
                   help=f"where the figure of true against published position goes (default "
                        f"{DEFAULT_FIGURE} in the current directory)")
    p.add_argument("--no-figure", action="store_true", help="do not write the figure")
    p.add_argument("--log-level", default="warning",
                   choices=("debug", "info", "warning", "error"),
                   help="service log level (default warning)")
    p.set_defaults(func=_run)


@dataclasses.dataclass
class _Pairing:
    """Bus-side pairing of published positions with the truth."""

    times: np.ndarray          # log time of each Sevcon frame of the unit, in send order
    truth_t: np.ndarray
    truth_mm: np.ndarray
    skip: int = 0              # Sevcon frames of the standing machine before the cycle
    pending_mm: float | None = None
    received: int = 0          # unwrapped diag input counter
    last_raw: int = 0
    errors: list[tuple[float, float]] = dataclasses.field(default_factory=list)
    samples: list[tuple[float, float, float, float]] = dataclasses.field(default_factory=list)

    def on_position(self, position_mm: float) -> None:
        self.pending_mm = position_mm

    def on_diag(self, input_frames: int, uncertainty_mm: float
                ) -> tuple[float, float, float] | None:
        """Pair the pending position with the truth; (log time, published, true). Only
        values that include a Sevcon frame of the cycle count: not those of the standing
        machine before it (commissioning) or after it (the service stopping)."""
        self.received += (input_frames - self.last_raw) % 0x10000
        self.last_raw = input_frames
        n = self.received - self.skip
        if self.pending_mm is None or not 1 <= n <= len(self.times):
            return None
        t = float(self.times[n - 1])
        true_mm = float(np.interp(t, self.truth_t, self.truth_mm))
        est, self.pending_mm = self.pending_mm, None
        self.errors.append((t, est - true_mm))
        self.samples.append((t, est, true_mm, uncertainty_mm))
        return t, est, true_mm


def _run(args: argparse.Namespace) -> int:
    from ddh_vsensor.master.replay import machine_frames
    from ddh_vsensor.sim import RunSpec, simulate_with_truth
    from ddh_vsensor.sim.cycles import WORK, require_cycle
    from ddh_vsensor.cli.progress import ProgressBar

    if not 0.05 <= args.rate <= 1000:
        raise UserError(f"--rate {args.rate}: outside 0.05..1000")
    if not 1 <= args.cycles <= 100:
        raise UserError(f"--cycles {args.cycles}: outside 1..100")
    if not args.no_figure:
        if Path(args.figure).suffix.lower() != ".png":
            raise UserError(f"--figure {args.figure}: a .png file name")
        output_dir(Path(args.figure).parent, "figure's directory")
        output_file(args.figure, "figure")
    cfg = config_from(args)
    extensions = extensions_from(args, cfg)
    spec = RunSpec(speed=args.speed, cycles=args.cycles, payload_kg=args.payload_kg,
                   oil_temp_c=args.oil_temp_c)
    print(f"ddh-vsensor demo: the {require_cycle(cfg, WORK)} work cycle at speed {args.speed} "
          f"({args.cycles} cycle{'s' if args.cycles > 1 else ''}, payload {args.payload_kg:g} kg, "
          f"oil {args.oil_temp_c:g} degC) on a virtual CAN bus")
    bar = ProgressBar("simulating the machine")
    result = simulate_with_truth(cfg, [spec], bar.update)[0]
    bar.close()
    runs = {a: run for a, (run, _) in result.items()}
    truths = {a: truth for a, (_, truth) in result.items()}
    frames = list(machine_frames(cfg, runs, HEARTBEAT_PERIOD_S))
    pairing = asyncio.run(_demo(cfg, frames, truths, args.rate, extensions))
    if not args.no_figure:
        path = write_figure(pairing, truths, args.figure)
        print(f"figure: {path.resolve()} (true against published position, and their "
              f"difference, per cylinder)")
    return 0


def write_figure(pairing: dict[str, "_Pairing"], truths: dict, path: str) -> Path:
    """The paper's Figures 6/8 for each cylinder (:func:`figure`) as a PNG."""
    import matplotlib.pyplot as plt
    out = Path(path)
    fig = figure(pairing, truths)
    try:
        fig.savefig(out, dpi=110)
    except OSError as exc:
        raise UserError(f"--figure {path}: {exc.strerror or exc}") from None
    finally:
        plt.close(fig)
    return out


def figure(pairing: dict[str, "_Pairing"], truths: dict):
    """True and published position (left), their difference with the published
    uncertainty (right), per cylinder. The difference's axis is scaled to the difference:
    the band shows where the uncertainty lies within it, a wider one fills the panel."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    fig, axes = plt.subplots(len(pairing), 2, figsize=(12, 3.8 * len(pairing)), squeeze=False)
    for (actuator, p), (left, right) in zip(pairing.items(), axes):
        truth = truths[actuator]
        left.plot(truth.time_s, truth.x_m * 1e3, color="k", lw=1.2, label="true (simulator)")
        right.axhline(0.0, color="k", lw=0.8)
        if p.samples:
            t, est, true, u = (np.array(c) for c in zip(*p.samples))
            left.plot(t, est, color="tab:red", lw=1.0, ls="--", label="published (service)")
            right.plot(t, est - true, color="tab:blue", lw=1.0, label="published − true")
            right.fill_between(t, -u, u, color="tab:blue", alpha=0.12,
                               label="± published uncertainty")
            span_mm = max(float(np.max(np.abs(est - true))), 0.01)
            right.set_ylim(-1.5 * span_mm, 1.5 * span_mm)
        left.set_ylabel(f"{actuator} position (mm)")
        right.set_ylabel(f"{actuator} difference (mm)")
        for ax in (left, right):
            ax.set_xlabel("time (s)")
            ax.grid(True, alpha=0.3)
            ax.legend(loc="best", fontsize="small")
    fig.suptitle("ddh-vsensor demo: the machine's work cycle, the service's output on the bus")
    fig.tight_layout()
    return fig


async def _demo(cfg, frames: list, truths: dict, rate: float, extensions: dict
                ) -> dict[str, _Pairing]:
    import can

    from ddh_vsensor.canbus.dbc import FrameCodec, message_name
    from ddh_vsensor.config import DEFAULT_BUS
    from ddh_vsensor.service import Service, ServiceOptions
    from ddh_vsensor.master.replay import replay
    from ddh_vsensor.master.watch import OutputWatcher, flag_text
    from ddh_vsensor.tables.build import build_unit_tables

    channel = f"ddh-vsensor-demo-{os.getpid()}"
    tables = {a: build_unit_tables(cfg, a) for a in cfg.can.units}
    # one virtual bus for the whole demo, whichever buses the machine's units are on
    on_one_bus = dataclasses.replace(cfg, buses={}, can=dataclasses.replace(cfg.can, units={
        u: dataclasses.replace(c, bus=DEFAULT_BUS) for u, c in cfg.can.units.items()}))
    service = Service(on_one_bus, tables, {"interface": "virtual", "channel": channel},
                      ServiceOptions(state_dir=None, extensions=extensions))
    machine = can.Bus(interface="virtual", channel=channel, preserve_timestamps=True)
    listener = can.Bus(interface="virtual", channel=channel)
    master = can.Bus(interface="virtual", channel=channel)
    codec = FrameCodec(cfg)
    sevcon_ids = {codec.ids[message_name("sevcon", a)]: a for a in cfg.can.units}
    pairing = {a: _Pairing(np.array([m.timestamp for m in frames
                                     if m.arbitration_id == codec.ids[message_name("sevcon", a)]]),
                           truths[a].time_s, truths[a].x_m * 1e3)
               for a in cfg.can.units}
    watcher = OutputWatcher(cfg, codec)
    view = _View(sys.stdout)
    log_end = frames[-1].timestamp
    stand: _Standing | None = None
    standing: asyncio.Task | None = None
    last_stamp = [0.0]
    try:
        # The service opens its bus in start() and reports there that nothing came yet
        # (READY without inputs): true of every start, no news in a demo whose machine
        # starts sending in the same instant. Its later warnings all show.
        with _quiet(logging.getLogger("ddh_vsensor.service")):
            await service.start()
        # The machine stands in its first state (a first round of its frames before the
        # service's first tick) while the service is commissioned, and in its last one
        # while the service stops: inputs never stop under a running service.
        stand = _Standing(machine, frames, True, time.time(), 1.0)
        stand.send_due()
        standing = asyncio.get_running_loop().create_task(stand.run())
        # Commissioning over SDO, from a master node on the bus: true start positions as
        # presets, and the diagnostic frame every position frame. All of it in a thread:
        # closing the network joins its reader, which must not stall the standing machine.
        await asyncio.get_running_loop().run_in_executor(None, _commission, master, cfg,
                                                         truths)
        stand.stop.set()
        await standing
        for a, p in pairing.items():
            p.skip = stand.sent.get(codec.ids[message_name("sevcon", a)], 0)
        # the cycle starts once the service has taken in the standing machine's last frames
        deadline_s = time.monotonic() + 1.0
        while time.monotonic() < deadline_s and any(
                service.inputs.units[a].received < p.skip for a, p in pairing.items()):
            await asyncio.sleep(0.001)
        now_log = [0.0]
        # per unit the last paired value: log time, published, true, uncertainty, flags
        latest: dict[str, tuple[float, float, float, float, int]] = {}
        done = asyncio.Event()

        async def show() -> None:
            next_block = 0.0
            while True:
                while (msg := listener.recv(0.0)) is not None:
                    kind = watcher.feed(msg)
                    if kind is None:
                        continue
                    what, actuator = kind
                    r = watcher.readings[actuator]
                    if what == "position":
                        pairing[actuator].on_position(r.position_mm)
                    elif what == "diag":
                        paired = pairing[actuator].on_diag(r.input_frames, r.uncertainty_mm)
                        if paired is not None:
                            latest[actuator] = (*paired, r.uncertainty_mm, r.flags)
                lines = []
                for a in cfg.can.units:
                    # the view ends with the cycle's last sample, not the standing after it
                    if a not in latest:
                        lines.append(f"  {a:<6}  waiting for the sensor's frames")
                        continue
                    _t, est, true, u, flags = latest[a]
                    lines.append(f"  {a:<6} true {true:7.1f} mm   estimated {est:7.1f} mm   "
                                 f"error {est - true:+6.2f} mm   +-{u:5.2f} mm  "
                                 f"[{flag_text(flags)}]")
                header = f"  t = {now_log[0]:5.1f} s of {log_end:.1f} s (x{rate:g})"
                if view.tty or now_log[0] >= next_block or done.is_set():
                    view.show([header, *lines])
                    next_block = now_log[0] + 2.0
                if done.is_set():
                    return
                await asyncio.sleep(0.1)

        viewer = asyncio.get_running_loop().create_task(show())

        def progress(t: float) -> None:
            now_log[0] = t

        def send(msg: can.Message) -> None:
            last_stamp[0] = msg.timestamp
            machine.send(msg)

        stats = await replay(frames, send, rate=rate, stamp="log", progress=progress)
        stand = _Standing(machine, frames, False, last_stamp[0], rate)
        standing = asyncio.get_running_loop().create_task(stand.run())
        await asyncio.sleep(3 * service.ticker.period_s)      # the cycle's last values out
        done.set()
        await viewer
    finally:
        await service.shutdown()
        if stand is not None and standing is not None:
            stand.stop.set()
            await standing
        for bus in (machine, listener, master):
            bus.shutdown()
    _summary(cfg, service, pairing, stats, sevcon_ids)
    return pairing


@contextlib.contextmanager
def _quiet(logger: logging.Logger):
    """``logger`` and its children log errors only, within the block."""
    level = logger.level
    logger.setLevel(logging.ERROR)
    try:
        yield
    finally:
        logger.setLevel(level)


class _Standing:
    """The machine standing in the cycle's first (or last) state: the frame of each ID that
    the cycle sends first (last), each at its own period in the log (Sevcon and oil every
    10 ms, heartbeats every 100 ms ...), stamped on from ``stamp_s`` in log time, which runs
    ``rate`` times the wall clock."""

    def __init__(self, bus, frames: list, first: bool, stamp_s: float, rate: float) -> None:
        times: dict[int, list[float]] = {}
        for msg in frames:
            times.setdefault(msg.arbitration_id, []).append(msg.timestamp)
        chosen: dict[int, object] = {}
        for msg in frames if first else reversed(frames):
            chosen.setdefault(msg.arbitration_id, msg)
        self.bus, self.rate = bus, rate
        self.frames = list(chosen.values())
        self.period_s = {i: float(np.median(np.diff(t))) if len(t) > 1 else 0.1
                         for i, t in times.items()}
        # before the cycle from ``stamp_s`` on; after it, one period after its last frame
        self.due_s = {i: stamp_s + (0.0 if first else self.period_s[i]) for i in chosen}
        self.stamp_s = stamp_s
        self.sent: dict[int, int] = {}
        self.stop = asyncio.Event()

    def send_due(self) -> None:
        import can
        for msg in self.frames:
            i = msg.arbitration_id
            while self.due_s[i] <= self.stamp_s:
                self.sent[i] = self.sent.get(i, 0) + 1
                self.bus.send(can.Message(timestamp=self.due_s[i], arbitration_id=i,
                                          is_extended_id=msg.is_extended_id, dlc=msg.dlc,
                                          data=msg.data))
                self.due_s[i] += self.period_s[i]

    async def run(self) -> None:
        """Until :attr:`stop`: the due frames every millisecond of wall time."""
        wall_s = time.monotonic()
        while not self.stop.is_set():
            self.send_due()
            try:
                await asyncio.wait_for(self.stop.wait(), 0.001)
            except asyncio.TimeoutError:
                pass
            now = time.monotonic()
            self.stamp_s += (now - wall_s) * self.rate
            wall_s = now


def _commission(bus, cfg, truths: dict) -> None:
    import canopen

    from ddh_vsensor.master.client import clients, sdo_network
    with sdo_network(bus) as network:
        for unit, client in clients(network, cfg).items():
            try:
                client.diag_timer_ms = client.event_timer_ms
                client.preset(float(truths[unit].x_m[0] * 1e3))
            except (canopen.SdoAbortedError, canopen.SdoCommunicationError) as exc:
                raise UserError(f"demo: commissioning the {unit} sensor over SDO failed: "
                                f"{exc}") from None


class _View:
    def __init__(self, stream) -> None:
        self.stream, self.tty = stream, stream.isatty()
        self._lines = 0

    def show(self, lines: list[str]) -> None:
        if self.tty and self._lines:
            self.stream.write(f"\x1b[{self._lines}F")
        for line in lines:
            self.stream.write(("\x1b[2K" if self.tty else "") + line + "\n")
        self.stream.flush()
        self._lines = len(lines) if self.tty else 0


def _summary(cfg, service, pairing: dict, stats, sevcon_ids: dict) -> None:
    print()
    print(f"summary: {stats.frames} machine frames replayed over {stats.log_span_s:.1f} s; "
          f"{service.frames_published} sensor frames published")
    print(f"  {'cylinder':<8} {'max |error|':>12} {'rms error':>10} {'end error':>10} "
          f"{'samples':>8} {'references':>10} {'rejected':>9}")
    worst = 0.0
    for actuator, p in pairing.items():
        if not p.errors:
            print(f"  {actuator:<8} no paired samples")
            continue
        err = np.array([e for _, e in p.errors])
        worst = max(worst, float(np.max(np.abs(err))))
        unit = service.units[actuator]
        counters = service.inputs.units[actuator]
        print(f"  {actuator:<8} {np.max(np.abs(err)):9.2f} mm {math.sqrt(np.mean(err ** 2)):7.2f} mm "
              f"{err[-1]:+7.2f} mm {len(err):8d} {unit.references:10d} {counters.rejected:9d}")
    verdict = "within" if worst <= PAPER_MAX_ERROR_MM else "beyond"
    print(f"  worst error {worst:.2f} mm: {verdict} the paper's ~{PAPER_MAX_ERROR_MM:g} mm per "
          f"work cycle. Errors are published position minus the simulator's true position at "
          f"the last Sevcon frame each published value includes.")
