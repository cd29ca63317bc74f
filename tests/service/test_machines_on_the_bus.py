"""Every shipped machine's daemon on virtual buses, seen by a master that knows only what the
configuration generates: the DBC of ``ddh-vsensor dbc`` decodes every frame the service sends
on every bus, and a canopen ``RemoteNode`` built from ``ddh-vsensor eds`` presets each sensor
and reads its position back over SDO."""

from __future__ import annotations

import asyncio
import dataclasses
from pathlib import Path

import can
import canopen
import cantools
import numpy as np
import pytest

from ddh_vsensor.canbus.dbc import FrameCodec, message_name
from ddh_vsensor.cli.main import main
from ddh_vsensor.config import DEFAULT_BUS, Config, load_config
from ddh_vsensor.measured import Run
from ddh_vsensor.master.client import sdo_network
from ddh_vsensor.master.replay import machine_frames, replay
from ddh_vsensor.sim.cycles import WORK
from ddh_vsensor.sim.run import RunSpec, simulate
from ddh_vsensor.tables.build import build_unit_tables

from .conftest import Recorder, channel_name, running_service
from .test_service_virtual import ticks_after, until

REPO = Path(__file__).resolve().parents[2]
MACHINES = sorted((REPO / "config").glob("*.yaml"))

SECONDS = 10.0          # of the machine's work cycle: every unit moves in it
# Estimated from a preset at the true position: within each machine's worst full-mode figure
# on its work cycle and random strokes (measured in
# tests/machines/test_machines.py: the loader 0.75 mm, the others' shortfalls), plus one step,
# plus one sample's travel: a preset is provisional, so the first reference is taken whole even
# in motion, where its edge is known to a sample (100 Hz here; in which sample depends on how
# the I/O module's frames on the default bus interleave with a unit's on another bus).
MAX_ERROR_MM = {"loader": 0.75, "bench": 1.25, "excavator": 1.95}


def _on_virtual_buses(cfg: Config) -> tuple[Config, dict[str, str]]:
    channels = {name: channel_name() for name in cfg.bus_names}
    virtual = dataclasses.replace(
        cfg, bus={"interface": "virtual", "channel": channels[DEFAULT_BUS]},
        buses={name: {"interface": "virtual", "channel": channels[name]} for name in cfg.buses})
    return virtual, channels


@pytest.fixture(scope="module", params=MACHINES, ids=lambda p: p.stem)
def machine(request: pytest.FixtureRequest) -> Config:
    return load_config(request.param)


def _work_cycle(cfg: Config) -> dict[str, Run]:
    """The machine's own work cycle at speed 4, 27 degC, empty (as tests/machines run it)."""
    return simulate(cfg, RunSpec(cycle=WORK, speed=4, payload_kg=0.0, oil_temp_c=27.0,
                                 step_s=2.0e-3, seed=1))


def _first_seconds(run: Run, seconds: float) -> Run:
    keep = run.time_s < seconds
    return Run(time_s=run.time_s[keep], speed_rpm=run.speed_rpm[keep],
               torque_nm=run.torque_nm[keep], oil_temp_c=run.oil_temp_c[keep],
               position_mm=run.position_mm[keep],
               refs={k: v[keep] for k, v in run.refs.items()}, source=run.source)


def _generated(cfg: Config, tmp_path: Path) -> tuple[cantools.database.can.Database,
                                                      dict[str, Path]]:
    """The machine's DBC and each unit's EDS, written by the CLI from its config file."""
    dbc = tmp_path / "machine.dbc"
    assert main(["dbc", "--config", cfg.source, "--out", str(dbc)]) == 0
    eds = {u: tmp_path / f"{u}.eds" for u in cfg.unit_names}
    for unit, path in eds.items():
        assert main(["eds", "--config", cfg.source, "--unit", unit, "--out", str(path)]) == 0
    return cantools.database.load_file(str(dbc)), eds


def _sdo(channel: str, cfg: Config, eds: dict[str, Path], units: tuple[str, ...],
         presets: dict[str, float] | None) -> dict[str, float]:
    """Over SDO, as any master would: the preset (0x6010) if given, then the position
    (0x6020) of each unit on this bus, from RemoteNodes of the generated EDS files."""
    step = cfg.can.position_step_mm
    bus = can.Bus(interface="virtual", channel=channel)
    try:
        with sdo_network(bus) as network:
            out = {}
            for unit in units:
                node = network.add_node(cfg.can.units[unit].sensor_node_id, str(eds[unit]))
                assert isinstance(node, canopen.RemoteNode)
                node.sdo.RESPONSE_TIMEOUT = 5.0
                if presets is not None:
                    node.sdo[0x6010][1].raw = round(presets[unit] / step)
                out[unit] = node.sdo[0x6020][1].raw * step
            return out
    finally:
        bus.shutdown()


def test_generated_dbc_and_eds_serve_a_master(machine: Config, tmp_path: Path) -> None:
    db, eds = _generated(machine, tmp_path)
    cfg, channels = _on_virtual_buses(machine)
    tables = {u: build_unit_tables(cfg, u) for u in cfg.unit_names}
    runs = {u: _first_seconds(r, SECONDS) for u, r in _work_cycle(machine).items()}
    start = {u: float(r.position_mm[0]) for u, r in runs.items()}
    truth = {u: float(r.position_mm[-1]) for u, r in runs.items()}
    frames = list(machine_frames(cfg, runs))
    codec = FrameCodec(cfg)
    bus_of = {codec.ids[message_name(kind, u)]: cfg.can.units[u].bus
              for u in cfg.unit_names for kind in ("sevcon", "heartbeat")}
    sevcon = {codec.ids[message_name("sevcon", u)]: u for u in cfg.unit_names}
    sent = {u: sum(sevcon.get(m.arbitration_id) == u for m in frames) for u in cfg.unit_names}
    recorders = {name: Recorder(ch) for name, ch in channels.items()}

    async def scenario() -> dict[str, float]:
        loop = asyncio.get_running_loop()
        async with running_service(cfg, tables, channels[DEFAULT_BUS]) as service:
            for name, ch in channels.items():
                units = cfg.units_on_bus(name)
                if units:
                    await loop.run_in_executor(None, _sdo, ch, cfg, eds, units, start)
            feeders = {name: can.Bus(interface="virtual", channel=ch, preserve_timestamps=True)
                       for name, ch in channels.items()}
            try:
                await replay(frames, lambda m: feeders[bus_of.get(m.arbitration_id,
                                                                  DEFAULT_BUS)].send(m),
                             rate=4.0, stamp="log")
            finally:
                for feeder in feeders.values():
                    feeder.shutdown()
            await until(lambda: all(service.inputs.units[u].received == n
                                    for u, n in sent.items()), "every Sevcon frame received")
            await ticks_after(service)
            read: dict[str, float] = {}
            for name, ch in channels.items():
                units = cfg.units_on_bus(name)
                if units:
                    read |= await loop.run_in_executor(None, _sdo, ch, cfg, eds, units, None)
            return read

    try:
        read = asyncio.run(scenario())
        seen = {name: r.drain() for name, r in recorders.items()}
    finally:
        for r in recorders.values():
            r.close()
    step = cfg.can.position_step_mm
    sensor_ids = {cfg.can.units[u].sensor_node_id for u in cfg.unit_names}
    for name, msgs in seen.items():
        own = [m for m in msgs if m.arbitration_id & 0x7F in sensor_ids
               and m.arbitration_id not in bus_of and m.arbitration_id >= 0x80]
        assert own, f"nothing from the sensors on bus {name}"
        for m in own:     # raises on any frame the generated DBC does not know or cannot decode
            db.decode_message(m.arbitration_id, bytes(m.data))
        on_bus = {m.arbitration_id & 0x7F for m in own}
        assert on_bus == {cfg.can.units[u].sensor_node_id for u in cfg.units_on_bus(name)}
    for unit in cfg.unit_names:
        bound = MAX_ERROR_MM[Path(machine.source).stem] + step \
            + float(np.max(np.abs(np.diff(runs[unit].position_mm))))
        assert read[unit] == pytest.approx(truth[unit], abs=bound), unit
        last = [db.decode_message(m.arbitration_id, bytes(m.data))
                for m in seen[cfg.can.units[unit].bus]
                if m.arbitration_id == codec.ids[message_name("position", unit)]][-1]
        assert last["Position"] == pytest.approx(read[unit], abs=step + 1e-9)
    assert min(np.ptp(r.position_mm) for r in runs.values()) > 10.0  # every unit moved
