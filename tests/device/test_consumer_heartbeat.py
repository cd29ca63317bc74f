"""Consumer heartbeat time 0x1016 as a master sets it: the service's consumer of the unit's
motor controller heartbeat takes the new time at once, and a controller whose heartbeats stop
is declared lost (CONTROLLER_NOT_OPERATIONAL in the status byte) after it, not after the
configured time."""

from __future__ import annotations

import dataclasses
import threading

import can
import canopen
import pytest

from ddh_vsensor.canbus.dbc import FrameCodec
from ddh_vsensor.device.objects import ABORT_VALUE_RANGE
from ddh_vsensor.estimator.flags import Flags

from .conftest import WAIT_S, master_on, service_thread, wait_for

POSITION_BOOM = 0x1B1
CONFIGURED_S = 5.0                  # the configuration's consumer time
SET_MS = 300                        # what the master writes


class Inputs:
    """Oil temperature and standstill Sevcon frames every 10 ms, the controllers' OPERATIONAL
    heartbeats every 100 ms; ``heartbeats[node] = False`` stops one controller's."""

    def __init__(self, cfg, channel: str) -> None:
        self.codec, self.cfg = FrameCodec(cfg), cfg
        self.heartbeats = {n: True for n in cfg.faults.heartbeat_node_ids.values()}
        self.bus = can.Bus(interface="virtual", channel=channel)
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="inputs", daemon=True)

    def _run(self) -> None:
        k = 0
        while not self._stop.is_set():
            self.bus.send(self.codec.encode_oil_temp(30.0))
            for actuator in self.cfg.can.units:
                self.bus.send(self.codec.encode_sevcon(actuator, 0.0, 0.0))
            if k % 10 == 0:
                for node, on in list(self.heartbeats.items()):
                    if on:
                        self.bus.send(can.Message(arbitration_id=0x700 + node, data=[0x05],
                                                  is_extended_id=False))
            k += 1
            self._stop.wait(0.01)

    def __enter__(self) -> Inputs:
        self._thread.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self._stop.set()
        self._thread.join(WAIT_S)
        self.bus.shutdown()


def _status(msg: can.Message) -> int:
    return msg.data[6]


def test_master_sets_the_consumer_time_and_the_consumer_acts_on_it(cfg, unit_tables,
                                                                     channel) -> None:
    machine = dataclasses.replace(cfg, faults=dataclasses.replace(
        cfg.faults, heartbeat_timeout_s=CONFIGURED_S))
    controller = machine.faults.heartbeat_node_ids["boom"]
    with master_on(machine, channel) as master, \
            service_thread(machine, unit_tables, channel) as service, \
            Inputs(machine, channel) as inputs:
        sdo = master.nodes["boom"].sdo
        consumer = service.units["boom"].heartbeat
        assert sdo[0x1016][0].raw == 1
        assert sdo[0x1016][1].raw == controller << 16 | round(CONFIGURED_S * 1000)
        # the controller heard and operational: the flag clears
        mark = master.frames.mark()
        wait_for(lambda: any(not _status(m) & Flags.CONTROLLER_NOT_OPERATIONAL
                             for m in master.frames.since(mark, POSITION_BOOM)),
                 "boom's controller operational")
        sdo[0x1016][1].raw = controller << 16 | SET_MS
        assert consumer.consumer_time_s == pytest.approx(SET_MS / 1000)
        assert sdo[0x1016][1].raw == controller << 16 | SET_MS
        # its heartbeats stop: lost after the new time (the bus's time stamps of the last
        # heartbeat and of the first position frame saying so)
        inputs.heartbeats[controller] = False
        mark = master.frames.mark()
        lost = wait_for(lambda: [m for m in master.frames.since(mark, POSITION_BOOM)
                                 if _status(m) & Flags.CONTROLLER_NOT_OPERATIONAL],
                        "boom's controller declared lost")[0]
        last = master.frames.since(0, 0x700 + controller)[-1]
        assert SET_MS / 1000 <= lost.timestamp - last.timestamp < CONFIGURED_S
        # the other unit's controller still beats: its flag stays clear
        bucket = [m for m in master.frames.since(mark, 0x1B2)]
        assert bucket and not any(_status(m) & Flags.CONTROLLER_NOT_OPERATIONAL
                                  for m in bucket)


def test_only_the_configured_controller_and_a_time_are_accepted(bus, cfg) -> None:
    service, master = bus
    sdo = master.nodes["bucket"].sdo
    controller = cfg.faults.heartbeat_node_ids["bucket"]
    before = sdo[0x1016][1].raw
    for value in (0,                                   # "not used": the unit's is consumed
                  controller << 16,                    # time 0
                  (controller + 5) << 16 | 500,        # another node
                  1 << 24 | controller << 16 | 500):   # reserved bits
        with pytest.raises(canopen.SdoAbortedError) as exc:
            sdo[0x1016][1].raw = value
        assert exc.value.code == ABORT_VALUE_RANGE, hex(value)
    assert sdo[0x1016][1].raw == before
    assert service.units["bucket"].heartbeat.consumer_time_s == \
        pytest.approx(cfg.faults.heartbeat_timeout_s)


def test_a_unit_without_a_consumed_controller_reads_0(cfg, unit_tables, channel) -> None:
    faults = dataclasses.replace(cfg.faults, heartbeat_node_ids={"boom": 1})
    machine = dataclasses.replace(cfg, faults=faults)
    with master_on(machine, channel) as master, \
            service_thread(machine, unit_tables, channel) as service:
        sdo = master.nodes["bucket"].sdo
        assert service.units["bucket"].heartbeat is None
        assert sdo[0x1016][1].raw == 0
        sdo[0x1016][1].raw = 0
        with pytest.raises(canopen.SdoAbortedError) as exc:
            sdo[0x1016][1].raw = 2 << 16 | 500
        assert exc.value.code == ABORT_VALUE_RANGE
