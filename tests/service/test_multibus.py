"""Units on several buses and machines of any size, in one process on python-can's virtual
buses: each unit's frames in and out on its own bus, every unit integrated and published."""

from __future__ import annotations

import asyncio

import can
import numpy as np
import pytest

from ddh_vsensor.canbus.dbc import FrameCodec, message_name
from ddh_vsensor.config import DEFAULT_BUS
from ddh_vsensor.estimator.flags import Flags
from ddh_vsensor.master.client import commission
from ddh_vsensor.master.replay import replay

from .conftest import (START_MM, Recorder, channel_name, machine_of, offline_estimate, on_buses,
                       paired_outputs, running_service)
from .test_service_virtual import ticks_after, until

SENSOR_KINDS = ("position", "diag", "sensor_heartbeat")


def _handled_in_order(service) -> list[can.Message]:
    """Every frame the service handles, in the order it handles them (across buses)."""
    seen: list[can.Message] = []
    handle = service.ingest.handle

    def recording(batch, now, bus=DEFAULT_BUS, watched_s=None):
        seen.extend(batch)
        handle(batch, now, bus, watched_s)
    service.ingest.handle = recording
    return seen


def test_each_unit_in_and_out_on_its_own_bus(cfg, unit_tables, frames) -> None:
    """The loader with its second unit on a second bus: that unit's Sevcon frames and
    heartbeats come on the second bus, the oil temperature and the I/O module on the default
    one; each unit's sensor frames go out on its own bus only, and each unit's published
    positions equal the offline estimate of the frames in the order the service took them."""
    first, second = cfg.unit_names
    channels = {DEFAULT_BUS: channel_name(), "second": channel_name()}
    two = on_buses(cfg, {second: "second"},
                   {"second": {"interface": "virtual", "channel": channels["second"]}})
    codec = FrameCodec(two)
    second_in = {codec.ids[message_name(k, second)] for k in ("sevcon", "heartbeat")}
    sevcon_ids = {codec.ids[message_name("sevcon", a)]: a for a in two.unit_names}
    sent = {a: sum(sevcon_ids.get(m.arbitration_id) == a for m in frames) for a in two.unit_names}
    recorders = {name: Recorder(ch) for name, ch in channels.items()}

    async def scenario():
        async with running_service(two, unit_tables, channels[DEFAULT_BUS]) as service:
            assert set(service.links) == {DEFAULT_BUS, "second"}
            handled = _handled_in_order(service)
            loop = asyncio.get_running_loop()
            for name, ch in channels.items():
                await loop.run_in_executor(None, lambda ch=ch, name=name: commission(
                    {"interface": "virtual", "channel": ch}, two, START_MM, diag_ms=10,
                    units=two.units_on_bus(name)))
            feeders = {name: can.Bus(interface="virtual", channel=ch, preserve_timestamps=True)
                       for name, ch in channels.items()}

            def send(msg: can.Message) -> None:
                bus = "second" if msg.arbitration_id in second_in else DEFAULT_BUS
                feeders[bus].send(msg)
            try:
                stats = await replay(frames, send, rate=8.0, stamp="log")
            finally:
                for feeder in feeders.values():
                    feeder.shutdown()
            await until(lambda: all(service.inputs.units[a].received == n
                                    for a, n in sent.items()), "every Sevcon frame received")
            await ticks_after(service)
            return service, stats, list(handled)

    try:
        service, stats, handled = asyncio.run(scenario())
        seen = {name: r.drain() for name, r in recorders.items()}
    finally:
        for r in recorders.values():
            r.close()
    assert stats.frames == len(frames) and service.inputs.counts["unknown"] == 0
    step = two.can.position_step_mm
    for actuator, own, other in ((first, DEFAULT_BUS, "second"), (second, "second", DEFAULT_BUS)):
        out_ids = {codec.ids[message_name(k, actuator)] for k in SENSOR_KINDS}
        assert {m.arbitration_id for m in seen[own]} >= out_ids        # all of them on its bus
        assert not out_ids & {m.arbitration_id for m in seen[other]}   # none on the other
        offline = offline_estimate(two, unit_tables, actuator, handled,
                                   preset_mm=START_MM[actuator])
        pairs = [p for p in paired_outputs(two, seen[own], actuator)
                 if p.input_frames > offline.held]
        assert pairs and pairs[-1].input_frames == sent[actuator]
        for p in pairs:
            expected = offline.position_mm[p.input_frames - 1 - offline.held]
            assert p.position_mm == pytest.approx(expected, abs=step + 1e-9)
            assert not p.status & Flags.NOT_REFERENCED
        assert np.ptp(offline.position_mm) > 20.0                      # the rod did move
        unit = service.units[actuator]
        assert unit.integrated + unit.held == sent[actuator]
        assert unit.references >= 1                                    # crossed its mid switch
        assert service.inputs.units[actuator].rejected == 0


@pytest.mark.parametrize("count, buses", [(3, 1), (8, 2)])
def test_any_number_of_units_publish_as_many_sensor_nodes(cfg, unit_tables, count,
                                                          buses) -> None:
    """A machine of ``count`` units (the loader's copied under other names and node IDs),
    split over ``buses`` buses: every unit's inputs integrated, ``count`` sensor nodes
    publishing position, diagnostic and heartbeat frames on their unit's bus."""
    machine, tables = machine_of(cfg, count, unit_tables)
    channels = {DEFAULT_BUS: channel_name(), **{f"bus{k}": channel_name()
                                                 for k in range(1, buses)}}
    names = list(channels)
    placement = {u: names[k * buses // count] for k, u in enumerate(machine.unit_names)}
    machine = on_buses(machine, placement, {name: {"interface": "virtual", "channel": ch}
                                            for name, ch in channels.items()
                                            if name != DEFAULT_BUS})
    codec = FrameCodec(machine)
    recorders = {name: Recorder(ch) for name, ch in channels.items()}
    samples = 30

    async def scenario():
        async with running_service(machine, tables, channels[DEFAULT_BUS]) as service:
            assert len(service.units) == count and set(service.links) == set(channels)
            feeders = {n: can.Bus(interface="virtual", channel=ch, preserve_timestamps=True)
                       for n, ch in channels.items()}
            try:
                # the oil temperature first: the buses' frames are handled in no fixed
                # order between buses, and Sevcon frames before it would be held
                feeders[DEFAULT_BUS].send(codec.encode_oil_temp(30.0, 999.99))
                await until(lambda: service.inputs.oil_temp_c is not None, "oil temperature")
                for k in range(samples):
                    t = 1000.0 + 0.01 * k
                    feeders[DEFAULT_BUS].send(codec.encode_oil_temp(30.0, t))
                    for unit in machine.unit_names:
                        feeders[placement[unit]].send(codec.encode_sevcon(unit, 0.0, 0.0, t))
                    await asyncio.sleep(0.001)
            finally:
                for feeder in feeders.values():
                    feeder.shutdown()
            await until(lambda: all(c.received == samples
                                    for c in service.inputs.units.values()), "every frame")
            await ticks_after(service)
            return service

    try:
        service = asyncio.run(scenario())
        seen = {name: {m.arbitration_id for m in r.drain()} for name, r in recorders.items()}
    finally:
        for r in recorders.values():
            r.close()
    publishing = 0
    for unit in machine.unit_names:
        out_ids = {codec.ids[message_name(k, unit)] for k in SENSOR_KINDS}
        assert seen[placement[unit]] >= out_ids, unit
        assert not any(out_ids & ids for name, ids in seen.items() if name != placement[unit])
        assert service.units[unit].integrated == samples
        assert service.inputs.units[unit].rejected == 0
        publishing += 1
    assert publishing == count and service.inputs.counts["unknown"] == 0


def test_a_broadcast_nmt_command_reaches_the_nodes_of_its_own_bus(cfg, unit_tables) -> None:
    """"Stop all nodes" on the second bus stops the sensor there; the one on the default bus
    stays OPERATIONAL (one canopen network per bus)."""
    first, second = cfg.unit_names
    channels = {DEFAULT_BUS: channel_name(), "second": channel_name()}
    two = on_buses(cfg, {second: "second"},
                   {"second": {"interface": "virtual", "channel": channels["second"]}})

    async def scenario():
        async with running_service(two, unit_tables, channels[DEFAULT_BUS]) as service:
            ingest = service.ingest
            handled = ingest.inputs.counts.copy()
            with can.Bus(interface="virtual", channel=channels["second"]) as master:
                master.send(can.Message(arbitration_id=0, data=[0x02, 0], is_extended_id=False))
            await until(lambda: service.units[second].node.node.nmt.state == "STOPPED",
                        "the second bus's sensor stopped")
            await ticks_after(service)
            return {u: service.units[u].node.node.nmt.state for u in two.unit_names}, \
                handled == ingest.inputs.counts

    states, nothing_unknown = asyncio.run(scenario())
    assert states == {first: "OPERATIONAL", second: "STOPPED"}
    assert nothing_unknown
