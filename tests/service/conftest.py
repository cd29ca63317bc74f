"""Shared by the daemon's tests: synthetic machine runs, a running service, recorders, and the
offline estimate of exactly the frames the service saw."""

from __future__ import annotations

import asyncio
import contextlib
import dataclasses
import uuid
from collections.abc import AsyncIterator, Iterable
from dataclasses import dataclass

import can
import numpy as np
import pytest

from ddh_vsensor.canbus.dbc import IO_MODULE, OIL_TEMP, FrameCodec, message_name
from ddh_vsensor.config import Config
from ddh_vsensor.estimator.estimator import Estimator
from ddh_vsensor.estimator.kalman_online import KalmanEstimator
from ddh_vsensor.estimator.state import EstimatorState
from ddh_vsensor.measured import Run
from ddh_vsensor.physics.steady import holding_speed, steady_state
from ddh_vsensor.physics.unit import DDHUnit
from ddh_vsensor.service import Service, ServiceOptions
from ddh_vsensor.service.inputs import Inputs
from ddh_vsensor.master.replay import machine_frames
from ddh_vsensor.sim.sensors import hall_switch

START_MM = {"boom": 120.0, "bucket": 380.0}


def synthetic_run(cfg: Config, actuator: str, seconds: float = 4.0, period_s: float = 0.01,
                  amplitude_rpm: float = 2500.0, cycle_s: float = 3.0, temp_c: float = 30.0,
                  start_mm: float | None = None) -> Run:
    """Sinusoidal motor speed around the holding speed, the truth from the exact steady
    state, Hall switches from the truth: a machine whose rod crosses its mid switch."""
    unit = DDHUnit.from_config(cfg, actuator)
    force = unit.load_force_n(0.0)
    t = np.round(np.arange(0.0, seconds, period_s), 9)
    bias = holding_speed(unit, force, temp_c).speed_rpm
    n = np.round(amplitude_rpm * np.sin(2 * np.pi * t / cycle_s) + bias)
    st = steady_state(unit, n, force, temp_c)
    v = st.velocity_m_s * 1e3
    x0 = START_MM[actuator] if start_mm is None else start_mm
    x = x0 + np.concatenate([[0.0], np.cumsum(0.5 * (v[1:] + v[:-1]) * np.diff(t))])
    ucfg = cfg.unit(actuator)
    refs = {name: hall_switch(x, pos, ucfg.reference_window_mm, ucfg.reference_hysteresis_mm)
            for name, pos in ucfg.references_mm.items()}
    return Run(time_s=t, speed_rpm=n, torque_nm=np.round(st.torque_nm * 16) / 16,
               oil_temp_c=np.full(len(t), temp_c), position_mm=x, refs=refs,
               source=f"synthetic:{actuator}")


@pytest.fixture(scope="session")
def machine_runs(cfg: Config) -> dict[str, Run]:
    return {a: synthetic_run(cfg, a) for a in cfg.can.units}


@pytest.fixture(scope="session")
def frames(cfg: Config, machine_runs: dict[str, Run]) -> list[can.Message]:
    return list(machine_frames(cfg, machine_runs, heartbeat_period_s=0.1))


def channel_name() -> str:
    return f"ddh-test-{uuid.uuid4().hex[:12]}"


class Recorder:
    """A virtual bus that keeps every frame it receives (``drain()`` to collect)."""

    def __init__(self, channel: str) -> None:
        self.bus = can.Bus(interface="virtual", channel=channel)
        self.frames: list[can.Message] = []

    def drain(self) -> list[can.Message]:
        while (msg := self.bus.recv(0.0)) is not None:
            self.frames.append(msg)
        return self.frames

    def close(self) -> None:
        self.bus.shutdown()


@contextlib.asynccontextmanager
async def running_service(cfg: Config, tables: dict, channel: str,
                          options: ServiceOptions | None = None,
                          **kwargs) -> AsyncIterator[Service]:
    service = Service(cfg, tables, {"interface": "virtual", "channel": channel},
                      options or ServiceOptions(), **kwargs)
    await service.start()
    try:
        yield service
    finally:
        await service.shutdown()


async def settle(seconds: float = 0.05) -> None:
    await asyncio.sleep(seconds)


@dataclass
class Published:
    position_mm: float
    status: int
    input_frames: int        # from the diagnostic frame of the same tick


def paired_outputs(cfg: Config, frames: Iterable[can.Message], actuator: str) -> list[Published]:
    """Each diag frame with the position frame sent just before it in the same tick."""
    codec = FrameCodec(cfg)
    pos_id = codec.ids[message_name("position", actuator)]
    diag_id = codec.ids[message_name("diag", actuator)]
    out, last = [], None
    for msg in frames:
        if msg.arbitration_id == pos_id:
            last = codec.decode(msg)[1]
        elif msg.arbitration_id == diag_id and last is not None:
            diag = codec.decode(msg)[1]
            out.append(Published(last["Position"], int(last["Status"]),
                                 int(diag["InputFrames"])))
            last = None
    return out


@dataclass
class Offline:
    position_mm: np.ndarray     # estimate after each integrated Sevcon frame
    held: int                   # Sevcon frames received before any oil temperature


def offline_estimate(cfg: Config, tables: dict, actuator: str, frames: Iterable[can.Message],
                     preset_mm: float | None = None,
                     state: EstimatorState | None = None,
                     widened: dict[int, float] | None = None) -> Offline:
    """The estimator stepped over the frames as the service received them (arrival order):
    each Sevcon frame with the latest oil temperature and the Hall states at its time (the
    service's :class:`Inputs` lookup: an I/O frame may come from another bus), and after an
    interval longer than the estimator integrates, not referenced (as the service: a feeder
    stalled under load shows as such a gap in bus-stamped frames). ``widened``: the service's
    widenings (frames stepped before it -> mm), each applied where the service applied it."""
    codec = FrameCodec(cfg)
    inputs = Inputs(cfg, codec)
    sevcon_id = codec.ids[message_name("sevcon", actuator)]
    oil_id, io_id = codec.ids[OIL_TEMP], codec.ids[IO_MODULE]
    est = (KalmanEstimator(cfg, actuator) if cfg.estimator.mode == "kalman"
           else Estimator(cfg, actuator, tables[actuator]))
    if state is not None:
        est.restore(state)
    else:
        est.restore(EstimatorState(actuator, cfg.physics_hash(), 0.0,
                                   cfg.unit(actuator).stroke_mm))
    if preset_mm is not None:
        est.preset(preset_mm, cfg.estimator.uncertainty_reference_mm)
        est.referenced = False      # the service's presets are provisional: never learned from
    oil = None
    last_t = 0.0
    positions: list[float] = []
    held = 0
    for msg in frames:
        if msg.arbitration_id == oil_id:
            oil = codec.decode(msg)[1]["OilTemp"]
        elif msg.arbitration_id == io_id:
            inputs.io(msg, 0.0)
        elif msg.arbitration_id == sevcon_id:
            if oil is None:
                held += 1
                continue
            if positions and msg.timestamp - last_t > est.max_gap_s:
                est.referenced = False      # the service's gap rule (a feeder stalled)
            last_t = msg.timestamp
            if widened and len(positions) in widened:
                est.add_uncertainty(widened[len(positions)])
            s = codec.decode(msg)[1]
            refs = inputs.refs(actuator, msg.timestamp)
            positions.append(est.step(msg.timestamp, s["VelocityActual"], s["TorqueActual"],
                                      oil, refs, inputs.refs_since_s).position_mm)
    return Offline(np.asarray(positions), held)


def on_buses(cfg: Config, placement: dict[str, str],
             buses: dict[str, dict]) -> Config:
    """``cfg`` with units moved to other buses (unit -> bus name) and those buses named."""
    units = {u: dataclasses.replace(c, bus=placement.get(u, c.bus))
             for u, c in cfg.can.units.items()}
    return dataclasses.replace(cfg, buses=buses, can=dataclasses.replace(cfg.can, units=units))


def machine_of(cfg: Config, count: int, tables: dict) -> tuple[Config, dict]:
    """A machine of ``count`` units named u0, u1, ..., copies of the reference loader's
    units in turn, with node IDs of their own (controllers 1.., sensors 49..), Hall bits
    3 per unit; and its tables (the copied units' tables)."""
    names = [f"u{k}" for k in range(count)]
    source = [cfg.unit_names[k % len(cfg.unit_names)] for k in range(count)]
    can_units = {}
    for k, (name, src) in enumerate(zip(names, source)):
        bits = {ref: 3 * k + j for j, ref in enumerate(cfg.can.units[src].hall_bits)}
        can_units[name] = dataclasses.replace(cfg.can.units[src], sevcon_node_id=1 + k,
                                              sensor_node_id=49 + k, hall_bits=bits)
    machine = dataclasses.replace(
        cfg, units={n: cfg.units[s] for n, s in zip(names, source)},
        can=dataclasses.replace(cfg.can, units=can_units),
        faults=dataclasses.replace(cfg.faults, heartbeat_node_ids={
            n: c.sevcon_node_id for n, c in can_units.items()}))
    return machine, {n: tables[s] for n, s in zip(names, source)}
