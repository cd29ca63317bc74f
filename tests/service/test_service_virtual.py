"""End to end in one process on python-can's virtual bus: simulated Sevcon frames in,
positions out, equal to the offline estimator within one output step."""

from __future__ import annotations

import asyncio
import dataclasses

import can
import canopen
import numpy as np
import pytest

from ddh_vsensor.canbus.dbc import FrameCodec, message_name
from ddh_vsensor.estimator.flags import Flags
from ddh_vsensor.master.client import SensorClient, commission, sdo_network
from ddh_vsensor.master.replay import replay

from .conftest import (START_MM, Recorder, channel_name, offline_estimate,
                       paired_outputs, running_service)

HANG_GUARD_S = 30.0     # bounds the waits below; no assertion depends on how fast they end


async def until(condition, what: str) -> None:
    """Wait for ``condition()`` (counts of frames, ticks, states), never for a duration."""
    loop = asyncio.get_running_loop()
    end = loop.time() + HANG_GUARD_S
    while not condition():
        if loop.time() > end:
            raise AssertionError(f"still waiting for {what} after {HANG_GUARD_S} s")
        await asyncio.sleep(0.002)


async def ticks_after(service, n: int = 2) -> None:
    """Until ``n`` more ticks went out: what was received is in them."""
    start = service.ticks
    await until(lambda: service.ticks >= start + n, f"{n} ticks")


@pytest.mark.parametrize("mode", ["configured", "kalman"])
def test_positions_on_the_bus_equal_the_offline_estimate(cfg, unit_tables, frames,
                                                         mode) -> None:
    """The configured estimator and the Kalman filter (``estimator.mode: kalman``)."""
    if mode == "kalman":
        cfg = dataclasses.replace(cfg, estimator=dataclasses.replace(cfg.estimator,
                                                                     mode="kalman"))
    channel = channel_name()
    recorder = Recorder(channel)
    codec = FrameCodec(cfg)
    sevcon_ids = {codec.ids[message_name("sevcon", a)] for a in cfg.can.units}
    sevcon_frames = sum(m.arbitration_id in sevcon_ids for m in frames)

    # the service's widenings (a host pause between frames at the start): the Kalman filter's
    # position depends on its spread (its Jacobian's step along x), so its twin applies them
    widened: dict[str, dict[int, float]] = {a: {} for a in cfg.can.units}

    def record(unit):
        add = unit.estimator.add_uncertainty

        def recorded(mm: float) -> None:
            widened[unit.actuator][unit.integrated] = \
                widened[unit.actuator].get(unit.integrated, 0.0) + mm
            add(mm)
        unit.estimator.add_uncertainty = recorded

    async def scenario():
        async with running_service(cfg, unit_tables, channel) as service:
            for unit in service.units.values():
                record(unit)
            await asyncio.get_running_loop().run_in_executor(
                None, lambda: commission({"interface": "virtual", "channel": channel}, cfg,
                                         START_MM, diag_ms=10))
            feeder = can.Bus(interface="virtual", channel=channel, preserve_timestamps=True)
            try:
                stats = await replay(frames, feeder.send, rate=8.0, stamp="log")
            finally:
                feeder.shutdown()
            await until(lambda: sum(u.received for u in service.inputs.units.values())
                        == sevcon_frames, "every Sevcon frame received")
            await ticks_after(service)
            return service, stats

    try:
        service, stats = asyncio.run(scenario())
        seen = recorder.drain()
    finally:
        recorder.close()
    assert stats.frames == len(frames)
    step = cfg.can.position_step_mm
    for actuator in cfg.can.units:
        offline = offline_estimate(cfg, unit_tables, actuator, seen, preset_mm=START_MM[actuator],
                                   widened=widened[actuator])
        pairs = [p for p in paired_outputs(cfg, seen, actuator) if p.input_frames > offline.held]
        # however many ticks the machine managed, the last includes every frame
        assert pairs and pairs[-1].input_frames == service.inputs.units[actuator].received
        for p in pairs:
            expected = offline.position_mm[p.input_frames - 1 - offline.held]
            assert p.position_mm == pytest.approx(expected, abs=step + 1e-9)
            assert not p.status & Flags.NOT_REFERENCED          # the SDO preset referenced it
        assert np.ptp(offline.position_mm) > 20.0              # the rod did move
        unit = service.units[actuator]
        assert unit.estimator.position_mm == pytest.approx(offline.position_mm[-1], abs=1e-9)
        assert unit.references >= 1                            # crossed its mid switch
        assert service.inputs.units[actuator].rejected == 0
    assert service.inputs.counts["unknown"] == 0


def test_input_stops_then_returns_stale_held_growing_then_clear(cfg, unit_tables) -> None:
    """Staleness is judged at given instants after the last frame (``published(unit, now)``),
    so the flags do not depend on how promptly a loaded machine runs the test; on the bus,
    the frames sent after the input stopped end stale, speed 0."""
    channel = channel_name()
    recorder = Recorder(channel)
    codec = FrameCodec(cfg)
    pos_id = codec.ids[message_name("position", "boom")]

    def feed(bus, t0: float, n: int, speed_rpm: float, start: int = 0) -> None:
        for k in range(start, start + n):
            t = t0 + k * 0.01
            bus.send(codec.encode_sevcon("boom", 5.0, speed_rpm, t))
            bus.send(codec.encode_sevcon("bucket", 0.0, 0.0, t))

    async def scenario():
        async with running_service(cfg, unit_tables, channel) as service:
            boom = service.units["boom"]
            counters = service.inputs.units["boom"]
            feeder = can.Bus(interface="virtual", channel=channel, preserve_timestamps=True)
            try:
                t0 = 1000.0
                service.units["boom"].estimator.preset(100.0, 0.5)   # a small bound to grow
                feeder.send(codec.encode_oil_temp(30.0, t0))
                feed(feeder, t0, 20, 2000.0)
                await until(lambda: counters.received == 20, "20 boom frames")
                last = boom.last_rx_s
                moving = service.published(boom, last)
                stale1 = service.published(boom, last + 0.3)       # > 3 periods
                stale2 = service.published(boom, last + 0.5)
                # on the bus: once stale, the position frames keep coming, flagged
                n0 = len(recorder.drain())

                def stale_frames() -> list[dict]:
                    return [d for d in (codec.decode(m)[1] for m in recorder.drain()[n0:]
                                        if m.arbitration_id == pos_id) if d["Status"] & Flags.STALE_INPUT]

                await until(lambda: len(stale_frames()) >= 5, "5 stale position frames")
                window = recorder.drain()[n0:]
                feed(feeder, t0, 5, 2000.0, start=60)
                await until(lambda: counters.received == 25, "5 more boom frames")
                back = service.published(boom, boom.last_rx_s)
            finally:
                feeder.shutdown()
            return moving, stale1, stale2, back, window

    try:
        moving, stale1, stale2, back, window = asyncio.run(scenario())
    finally:
        recorder.close()
    assert not moving.flags & Flags.STALE_INPUT and moving.speed_mm_s > 0
    assert stale1.flags & Flags.STALE_INPUT and stale2.flags & Flags.STALE_INPUT
    assert stale1.position_mm == stale2.position_mm == moving.position_mm   # held
    assert stale1.speed_mm_s == 0.0
    assert stale2.uncertainty_mm > stale1.uncertainty_mm > moving.uncertainty_mm
    assert not back.flags & Flags.STALE_INPUT
    # the gap (0.4 s > max_gap) was not integrated: its worst-case travel (max speed x gap)
    # stays in the uncertainty until a reference
    gap_s = 0.41
    assert back.uncertainty_mm >= moving.uncertainty_mm + cfg.max_speed_mm_s("boom") * gap_s
    published = [codec.decode(m)[1] for m in window if m.arbitration_id == pos_id]
    assert all(p["Status"] & Flags.STALE_INPUT and p["Speed"] == 0 for p in published[-5:])


def test_sdo_reads_live_values_and_refuses_presets_outside_the_stroke(cfg, unit_tables) -> None:
    channel = channel_name()

    def client() -> dict:
        out = {}
        with can.Bus(interface="virtual", channel=channel) as bus, sdo_network(bus) as network:
            boom = SensorClient(network, cfg, "boom")
            boom.preset(42.5)
            out["position"] = boom.position_steps
            out["step"] = boom.sdo[0x6005][1].raw
            out["flags"] = boom.flags
            out["device"] = boom.sdo[0x1000].raw
            with pytest.raises(canopen.SdoAbortedError) as exc:
                boom.preset(400.0)                                   # > 311 mm
            out["abort"] = exc.value.code
            with pytest.raises(canopen.SdoAbortedError):
                boom.sdo[0x6010][1].raw = -100
            boom.sdo[0x1800][5].raw = 5
            out["timer"] = boom.event_timer_ms
        return out

    async def scenario():
        async with running_service(cfg, unit_tables, channel) as service:
            out = await asyncio.get_running_loop().run_in_executor(None, client)
            return service, out

    service, out = asyncio.run(scenario())
    assert out["position"] == 4250
    assert out["step"] == 10000                       # nm: 0.01 mm
    assert out["device"] == 0x00080196
    assert not out["flags"] & Flags.NOT_REFERENCED     # a preset is a reference
    assert out["abort"] == 0x06090030                 # value range exceeded
    assert service.units["boom"].estimator.position_mm == pytest.approx(42.5)
    assert service.units["bucket"].estimator.position_mm == 0.0
    assert out["timer"] == 5 and service.ticker.period_s == pytest.approx(0.005)


def test_nmt_stop_silences_the_pdos_and_reset_reboots(cfg, unit_tables) -> None:
    channel = channel_name()
    recorder = Recorder(channel)
    codec = FrameCodec(cfg)
    node_id = cfg.can.units["boom"].sensor_node_id
    pos_id = codec.ids[message_name("position", "boom")]

    bucket_pos_id = codec.ids[message_name("position", "bucket")]

    def count(frames, frame_id: int) -> int:
        return sum(m.arbitration_id == frame_id for m in frames)

    async def scenario():
        async with running_service(cfg, unit_tables, channel) as service:
            node = service.units["boom"].node
            master = can.Bus(interface="virtual", channel=channel)
            try:
                await until(lambda: count(recorder.drain(), pos_id) >= 1, "a boom position")
                master.send(can.Message(arbitration_id=0, data=[0x02, node_id],
                                        is_extended_id=False))       # stop
                await until(lambda: not node.operational, "the boom node STOPPED")
                await ticks_after(service, 1)
                n_stopped = len(recorder.drain())
                # while stopped: the bucket's frames go on (five of them), the boom's do not
                await until(lambda: count(recorder.drain()[n_stopped:], bucket_pos_id) >= 5,
                            "5 bucket positions")
                during = recorder.drain()[n_stopped:]
                master.send(can.Message(arbitration_id=0, data=[0x81, 0],
                                        is_extended_id=False))       # reset all nodes
                n_reset = len(during) + n_stopped
                await until(lambda: count(recorder.drain()[n_reset:], pos_id) >= 1,
                            "a boom position after the reset")
                after = recorder.drain()[n_reset:]
            finally:
                master.shutdown()
            return during, after

    try:
        during, after = asyncio.run(scenario())
    finally:
        recorder.close()
    assert not [m for m in during if m.arbitration_id == pos_id]
    assert count(during, bucket_pos_id) >= 5
    boot = [m for m in after if m.arbitration_id == 0x700 + node_id and m.data[0] == 0]
    assert boot, "a reset node sends its boot-up message"
    assert [m for m in after if m.arbitration_id == pos_id], "auto start after the reset"


def test_one_millisecond_inputs_and_event_timer(cfg, unit_tables) -> None:
    """Sevcon TPDOs every 1 ms and the sensors' event timer at 1 ms work as well. Nothing is
    asserted about how many ticks a (possibly loaded) machine manages: every frame is taken,
    none rejected, every tick sends its position frame, every published position equals the
    offline estimate of the frames it includes, and the last one includes all of them."""
    import dataclasses

    from ddh_vsensor.master.replay import machine_frames

    from .conftest import synthetic_run

    fast = dataclasses.replace(cfg, can=dataclasses.replace(cfg.can, event_timer_ms=1.0))
    runs = {a: synthetic_run(fast, a, seconds=1.0, period_s=0.001, cycle_s=1.0)
            for a in fast.can.units}
    fast_frames = list(machine_frames(fast, runs, heartbeat_period_s=0.1))
    codec = FrameCodec(fast)
    sent = {a: sum(m.arbitration_id == codec.ids[message_name("sevcon", a)]
                   for m in fast_frames) for a in fast.can.units}
    channel = channel_name()
    recorder = Recorder(channel)

    async def scenario():
        async with running_service(fast, unit_tables, channel) as service:
            await asyncio.get_running_loop().run_in_executor(
                None, lambda: commission({"interface": "virtual", "channel": channel}, fast,
                                         START_MM, diag_ms=1))
            feeder = can.Bus(interface="virtual", channel=channel, preserve_timestamps=True)
            try:
                await replay(fast_frames, feeder.send, rate=2.0, stamp="log")
            finally:
                feeder.shutdown()
            # until a tick has included every frame (a hang guard bounds it, not a speed)
            for _ in range(10000):
                if all(service.inputs.units[a].received == sent[a] for a in sent):
                    break
                await asyncio.sleep(0.001)
            ticks = service.ticks
            while service.ticks < ticks + 2:
                await asyncio.sleep(0.001)
            return service

    try:
        service = asyncio.run(scenario())
        seen = recorder.drain()
    finally:
        recorder.close()
    assert service.ticker.period_s == pytest.approx(0.001)
    for actuator in fast.can.units:
        counters = service.inputs.units[actuator]
        assert counters.received == sent[actuator] and counters.rejected == 0  # no flood
        pos_id = codec.ids[message_name("position", actuator)]
        # the 1 ms event timer: a position frame at every tick the service made
        assert sum(m.arbitration_id == pos_id for m in seen) == service.ticks, actuator
        offline = offline_estimate(fast, unit_tables, actuator, seen,
                                   preset_mm=START_MM[actuator])
        pairs = [p for p in paired_outputs(fast, seen, actuator) if p.input_frames > offline.held]
        assert pairs and pairs[-1].input_frames == sent[actuator], actuator
        for p in pairs:
            expected = offline.position_mm[p.input_frames - 1 - offline.held]
            assert p.position_mm == pytest.approx(expected, abs=fast.can.position_step_mm + 1e-9)
