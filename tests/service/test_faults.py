"""Fault injection: lost or non-operational controller, malformed frames, floods, bus errors,
bad config, corrupt state file. The service counts, logs, keeps publishing."""

from __future__ import annotations

import asyncio
import json
import logging
import threading
import time

import can
import pytest

from ddh_vsensor.canbus.dbc import FrameCodec, message_name
from ddh_vsensor.cli.main import main
from ddh_vsensor.estimator.flags import Flags
from ddh_vsensor.estimator.state import EstimatorState, save_state
from ddh_vsensor.service import ServiceOptions

from .conftest import Recorder, channel_name, running_service, settle


async def _feed(bus, codec, t0: float, start: int, n: int, *, boom_rpm: float = 1500.0,
                heartbeat: int | None = None, sleep_s: float = 0.01) -> None:
    for k in range(start, start + n):
        t = t0 + k * 0.01
        bus.send(codec.encode_sevcon("boom", 4.0, boom_rpm, t))
        bus.send(codec.encode_sevcon("bucket", 0.0, 0.0, t))
        if heartbeat is not None and k % 5 == 0:
            bus.send(codec.encode(message_name("heartbeat", "boom"), {"NmtState": heartbeat}, t))
        await asyncio.sleep(sleep_s)


def _boom(service):
    return service.published(service.units["boom"])


async def _boom_as_received(service, frames: int):
    """The boom's publication at the moment its last frame arrived, once ``frames`` are
    integrated: what it says of those frames, not of how late this test ran after them (a
    loaded host can delay it past the stale limit, 30 ms)."""
    unit = service.units["boom"]
    for _ in range(300):
        if unit.integrated >= frames:
            break
        await asyncio.sleep(0.01)
    return service.published(unit, unit.last_rx_s)


def test_controller_heartbeat_raises_a_flag_and_never_discards_motion(cfg, unit_tables) -> None:
    """Consumed by configuration (boom: node 1, bucket: node 2): not OPERATIONAL or lost sets
    Flags.CONTROLLER_NOT_OPERATIONAL; the frames are integrated all the same, nothing is stale for it."""
    channel = channel_name()
    codec = FrameCodec(cfg)

    async def scenario():
        options = ServiceOptions(heartbeat_timeout_s=0.3)
        async with running_service(cfg, unit_tables, channel, options) as service:
            feeder = can.Bus(interface="virtual", channel=channel, preserve_timestamps=True)
            try:
                t0 = 500.0
                feeder.send(codec.encode_oil_temp(30.0, t0))
                await _feed(feeder, codec, t0, 0, 15, heartbeat=5)
                ok = await _boom_as_received(service, 15)
                await _feed(feeder, codec, t0, 15, 15, heartbeat=127)     # pre-operational
                preop = await _boom_as_received(service, 30)
                await _feed(feeder, codec, t0, 30, 10, heartbeat=5)
                await _feed(feeder, codec, t0, 40, 50)                     # heartbeat lost
                lost = _boom(service)
                lost_why = service.units["boom"].heartbeat.status()[1]
                await _feed(feeder, codec, t0, 90, 10, heartbeat=5)
                back = await _boom_as_received(service, 100)
                bucket = service.published(service.units["bucket"])
                unit = service.units["boom"]
            finally:
                feeder.shutdown()
            return ok, preop, lost, lost_why, back, bucket, unit

    ok, preop, lost, lost_why, back, bucket, unit = asyncio.run(scenario())
    assert not ok.flags & (Flags.STALE_INPUT | Flags.CONTROLLER_NOT_OPERATIONAL)
    assert preop.flags & Flags.CONTROLLER_NOT_OPERATIONAL and not preop.flags & Flags.STALE_INPUT
    assert preop.position_mm > ok.position_mm + 1.0            # integrated all the same
    assert lost.flags & Flags.CONTROLLER_NOT_OPERATIONAL and "heartbeat lost" in lost_why
    assert lost.position_mm > preop.position_mm + 1.0
    assert not back.flags & (Flags.STALE_INPUT | Flags.CONTROLLER_NOT_OPERATIONAL)
    assert unit.held == 0 and unit.integrated == 100
    assert bucket.flags & Flags.CONTROLLER_NOT_OPERATIONAL and not bucket.flags & Flags.STALE_INPUT  # never heard


def test_heartbeats_of_unconfigured_nodes_arm_nothing(cfg, unit_tables) -> None:
    """Without a configured consumer a spoofed heartbeat is just an unknown frame."""
    import dataclasses
    quiet = dataclasses.replace(cfg, faults=dataclasses.replace(cfg.faults,
                                                                heartbeat_node_ids={}))
    channel = channel_name()
    codec = FrameCodec(quiet)

    async def scenario():
        async with running_service(quiet, unit_tables, channel) as service:
            feeder = can.Bus(interface="virtual", channel=channel, preserve_timestamps=True)
            try:
                feeder.send(codec.encode_oil_temp(30.0, 600.0))
                await _feed(feeder, codec, 600.0, 0, 10, heartbeat=4)      # "stopped", spoofed
                await _feed(feeder, codec, 600.0, 10, 10)
                return await _boom_as_received(service, 20), service.units["boom"]
            finally:
                feeder.shutdown()

    boom, unit = asyncio.run(scenario())
    assert unit.heartbeat is None
    assert not boom.flags & (Flags.CONTROLLER_NOT_OPERATIONAL | Flags.STALE_INPUT) and unit.integrated == 20


def test_malformed_frames_are_counted_and_ignored(cfg, unit_tables, caplog) -> None:
    channel = channel_name()
    codec = FrameCodec(cfg)
    sevcon_id = codec.ids[message_name("sevcon", "boom")]

    async def scenario():
        async with running_service(cfg, unit_tables, channel) as service:
            feeder = can.Bus(interface="virtual", channel=channel, preserve_timestamps=True)
            try:
                t0 = 700.0
                feeder.send(codec.encode_oil_temp(30.0, t0))
                await _feed(feeder, codec, t0, 0, 10)
                before = _boom(service)
                good = service.units["boom"].integrated
                bad = [
                    can.Message(timestamp=t0 + 0.105, arbitration_id=sevcon_id, data=b"\x01\x02",
                                is_extended_id=False),                         # short
                    can.Message(timestamp=t0 + 0.106, arbitration_id=sevcon_id,
                                data=bytes(8), is_extended_id=False),           # long
                    codec.encode_sevcon("boom", 5.0, 50000.0, t0 + 0.107),      # 50000 rpm
                    codec.encode_sevcon("boom", 2000.0, 100.0, t0 + 0.108),     # 2000 N*m
                    can.Message(timestamp=t0 + 0.109, arbitration_id=sevcon_id,
                                is_remote_frame=True, dlc=6, is_extended_id=False),
                    can.Message(timestamp=t0 + 0.11, arbitration_id=0x123, data=b"x",
                                is_extended_id=False),                          # unknown
                    can.Message(timestamp=t0 + 0.11, arbitration_id=sevcon_id, data=bytes(6),
                                is_extended_id=True),                           # extended
                    codec.encode_oil_temp(900.0, t0 + 0.11),                    # hot oil
                    can.Message(timestamp=t0 + 0.11, arbitration_id=codec.ids["IO_MODULE_TPDO1"],
                                data=b"", is_extended_id=False),                # empty I/O
                    can.Message(timestamp=t0 + 0.11, is_error_frame=True, arbitration_id=0x4),
                ]
                for msg in bad:
                    feeder.send(msg)
                await settle(0.05)
                after_bad = _boom(service)
                ticks = service.ticks
                await _feed(feeder, codec, t0, 12, 10)
                after = _boom(service)
            finally:
                feeder.shutdown()
            return service, before, good, after_bad, after, ticks

    with caplog.at_level(logging.WARNING):
        service, before, good, after_bad, after, ticks = asyncio.run(scenario())
    counters = service.inputs.units["boom"]
    assert counters.rejected == 5                       # short, long, 2 x range, remote
    assert dict(counters.reasons) == {"length": 3, "range": 2}
    assert after_bad.rejected_frames == 5
    assert after_bad.position_mm == before.position_mm  # nothing of them was integrated
    assert service.units["boom"].integrated == good + 10
    assert service.inputs.counts["unknown"] == 2        # 0x123 and the extended frame
    assert service.inputs.counts["oil_rejected"] == 1 and service.inputs.oil_temp_c == 30.0
    assert service.inputs.counts["io_rejected"] == 1
    assert service.ticks > ticks and after.position_mm > before.position_mm
    assert "rejected" in caplog.text


def test_a_flood_is_rejected_and_publishing_goes_on(cfg, unit_tables) -> None:
    channel = channel_name()
    codec = FrameCodec(cfg)
    recorder = Recorder(channel)
    pos_id = codec.ids[message_name("position", "boom")]
    flood_frames = 20000

    def flood(stop: threading.Event) -> None:
        bus = can.Bus(interface="virtual", channel=channel, preserve_timestamps=True)
        try:
            t = 900.2
            for k in range(flood_frames):
                bus.send(codec.encode_sevcon("boom", 1.0, 100.0, t + k * 1e-5))
                bus.send(can.Message(timestamp=t, arbitration_id=0x7A0, data=bytes(8),
                                     is_extended_id=False))
        finally:
            bus.shutdown()
            stop.set()

    async def scenario():
        async with running_service(cfg, unit_tables, channel) as service:
            feeder = can.Bus(interface="virtual", channel=channel, preserve_timestamps=True)
            try:
                feeder.send(codec.encode_oil_temp(30.0, 900.0))
                await _feed(feeder, codec, 900.0, 0, 10)
                n0 = len(recorder.drain())
                ticks0 = service.ticks
                done = threading.Event()
                thread = threading.Thread(target=flood, args=(done,))
                thread.start()
                while not done.is_set():
                    await settle(0.01)
                    recorder.drain()
                during_ticks = service.ticks - ticks0
                thread.join()
                await settle(0.3)            # let the dispatcher work through the backlog
                during = recorder.drain()[n0:]
                await _feed(feeder, codec, 901.0, 0, 10)
            finally:
                feeder.shutdown()
            return service, during, during_ticks

    try:
        service, during, during_ticks = asyncio.run(scenario())
    finally:
        recorder.close()
    counters = service.inputs.units["boom"]
    assert counters.received >= flood_frames
    assert counters.reasons["flood"] > flood_frames * 0.9
    assert service.inputs.counts["unknown"] == flood_frames
    assert during_ticks > 0
    assert [m for m in during if m.arbitration_id == pos_id]
    assert service.units["boom"].integrated > 10          # integrating again afterwards


class FlakyBus(can.BusABC):
    """A virtual bus whose receive fails once after ``fail_after`` frames."""

    def __init__(self, channel: str, fail_after: int, state: dict) -> None:
        self._inner = can.Bus(interface="virtual", channel=channel)
        self._fail_after, self._state = fail_after, state
        self.channel_info = f"flaky {channel}"
        super().__init__(channel=channel)

    def _recv_internal(self, timeout):
        msg = self._inner.recv(timeout)
        if msg is not None:
            self._state["received"] = self._state.get("received", 0) + 1
            if not self._state.get("failed") and self._state["received"] >= self._fail_after:
                self._state["failed"] = True
                raise can.CanOperationError("simulated bus-off")
        return msg, False

    def send(self, msg, timeout=None):
        self._inner.send(msg, timeout)

    def shutdown(self):
        self._inner.shutdown()
        super().shutdown()


def test_bus_errors_and_a_missing_bus_are_survived(cfg, unit_tables) -> None:
    channel = channel_name()
    codec = FrameCodec(cfg)
    state: dict = {"opens": 0}

    def opener(settings, filters):
        state["opens"] += 1
        if state["opens"] == 1:
            raise OSError(19, "No such device")       # not there at start
        return FlakyBus(channel, fail_after=8, state=state)

    async def scenario():
        async with running_service(cfg, unit_tables, channel, opener=opener) as service:
            link_state_at_start = service.link.state
            await settle(0.3)
            feeder = can.Bus(interface="virtual", channel=channel, preserve_timestamps=True)
            try:
                feeder.send(codec.encode_oil_temp(30.0, 300.0))
                await _feed(feeder, codec, 300.0, 0, 30)
                await settle(0.5)
                await _feed(feeder, codec, 300.0, 30, 10)
                moved = _boom(service)
            finally:
                feeder.shutdown()
            return service, link_state_at_start, moved

    service, at_start, moved = asyncio.run(scenario())
    assert at_start == "reconnecting"
    assert state["failed"] and state["opens"] >= 3
    assert service.link.reconnects >= 2 and service.link.bus_errors >= 2
    assert service.units["boom"].integrated > 20          # the estimate carried on
    assert moved.position_mm > 0.0


def test_corrupt_state_file_is_ignored_the_other_restored(cfg, unit_tables, tmp_path,
                                                           caplog) -> None:
    (tmp_path / "boom.json").write_text("{not json")
    save_state(tmp_path / "bucket.json",
               EstimatorState("bucket", cfg.physics_hash(), 321.0, 1.5, 1.01, 0.99,
                              [[1e-5, 0.0], [0.0, 1e-5]]))
    channel = channel_name()

    async def scenario():
        async with running_service(cfg, unit_tables, channel,
                                   ServiceOptions(state_dir=tmp_path)) as service:
            await settle(0.05)
            return {a: service.published(u) for a, u in service.units.items()}

    with caplog.at_level(logging.WARNING):
        published = asyncio.run(scenario())
    assert "corrupt state file ignored" in caplog.text
    assert published["boom"].position_mm == 0.0
    assert published["boom"].uncertainty_mm >= cfg.unit("boom").stroke_mm
    assert published["bucket"].position_mm == pytest.approx(321.0)
    assert published["bucket"].flags & Flags.NOT_REFERENCED
    # the stop wrote both files again, sound
    assert json.loads((tmp_path / "boom.json").read_text())["actuator"] == "boom"
    assert json.loads((tmp_path / "bucket.json").read_text())["position_mm"] == \
        pytest.approx(321.0)


def test_bad_config_and_bad_bus_settings_exit_2(tmp_path, capsys) -> None:
    bad = tmp_path / "bad.yaml"
    bad.write_text("oil: {name: x}\n")
    assert main(["run", "--config", str(bad), "--no-state"]) == 2
    assert "bad.yaml" in capsys.readouterr().err
    assert main(["run", "--interface", "no-such-interface", "--no-state"]) == 2
    assert "no-such-interface" in capsys.readouterr().err


@pytest.mark.parametrize("mode", ["disabled", "pre-operational only", "enabled"])
def test_preset_modes_and_their_abort_codes(cfg, unit_tables, mode) -> None:
    """SDO presets per ``faults.preset``; the jump bound once referenced; Flags.PRESET_UNCONFIRMED until a
    reference confirms; every one counted in the status line."""
    import dataclasses

    import canopen

    from ddh_vsensor.estimator.flags import Flags
    from ddh_vsensor.master.client import SensorClient, sdo_network
    modal = dataclasses.replace(cfg, faults=dataclasses.replace(cfg.faults, preset=mode))
    channel = channel_name()
    node_id = cfg.can.units["boom"].sensor_node_id

    def client() -> dict:
        out: dict = {}
        with can.Bus(interface="virtual", channel=channel) as bus, sdo_network(bus) as network:
            boom = SensorClient(network, cfg, "boom")

            def write(name: str, mm: float) -> None:
                try:
                    boom.preset(mm)
                    out[name] = "accepted"
                except canopen.SdoAbortedError as exc:
                    out[name] = exc.code
            write("operational", 100.0)
            bus.send(can.Message(arbitration_id=0, data=[0x80, node_id], is_extended_id=False))
            time.sleep(0.1)                                   # -> PRE-OPERATIONAL
            write("pre-operational", 100.0)
            write("jump", 160.0)                              # 60 mm from a referenced 100
            write("small", 103.0)
        return out

    async def scenario():
        async with running_service(modal, unit_tables, channel) as service:
            out = await asyncio.get_running_loop().run_in_executor(None, client)
            return out, service.published(service.units["boom"]), service.status_line()

    out, boom, status = asyncio.run(scenario())
    if mode == "disabled":
        assert set(out.values()) == {0x06010002}
    elif mode == "pre-operational only":
        assert out == {"operational": 0x08000022, "pre-operational": "accepted",
                       "jump": 0x06090030, "small": "accepted"}
    else:
        assert out == {"operational": "accepted", "pre-operational": "accepted",
                       "jump": 0x06090030, "small": "accepted"}
    if mode != "disabled":
        assert boom.flags & Flags.PRESET_UNCONFIRMED and not boom.flags & Flags.NOT_REFERENCED
        assert boom.position_mm == pytest.approx(103.0)
        accepted = sum(v == "accepted" for v in out.values())
        assert f"boom {accepted}/{len(out) - accepted}" in status


def test_a_signal_during_a_slow_save_is_saved_after_it(cfg, unit_tables, tmp_path,
                                                       monkeypatch) -> None:
    """SIGHUP/USR1/USR2 save the estimates. A request that arrives while the last save is
    still writing (a slow disk) must not be dropped: one more save follows, with the estimates
    of after the request, and a stop still ends with a clean save."""
    from ddh_vsensor.service import service as service_module
    written: list[bool] = []
    release = threading.Event()

    def slow_write(snapshots):
        release.wait(10.0)
        written.append(any(s.clean for _, s in snapshots))

    monkeypatch.setattr(service_module, "write_states", slow_write)
    channel = channel_name()

    async def scenario():
        options = ServiceOptions(state_dir=tmp_path)
        async with running_service(cfg, unit_tables, channel, options) as service:
            service.on_signal("SIGHUP")          # starts a save that cannot finish yet
            service.on_signal("SIGUSR1")         # arrives while it writes
            await settle(0.1)
            assert written == []
            release.set()
            for _ in range(200):
                if len(written) >= 2:
                    break
                await settle(0.02)
            assert written == [False, False]
        assert written[-1] is True               # the stop's own clean save comes last

    asyncio.run(scenario())
