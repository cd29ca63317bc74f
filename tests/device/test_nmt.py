"""NMT as a master drives it: auto start or not, stop / pre-operational / start, and the two
resets restoring their areas of the object dictionary (the estimate is kept)."""

from __future__ import annotations

import dataclasses

import canopen
import pytest

from .conftest import master_on, service_thread, wait_for

HEARTBEAT_MS = 50


def _heartbeats(master, mark: int, node_id: int) -> list[int]:
    return [m.data[0] for m in master.frames.since(mark, 0x700 + node_id)]


def _state_after(master, node_id: int, state: int, count: int = 3) -> int:
    """Wait for ``count`` heartbeats saying ``state``; the mark just after the first of them.

    The node acts on an NMT command at its next tick, so frames between the command and
    that first heartbeat may still belong to the old state; none after it may."""
    mark = master.frames.mark()
    wait_for(lambda: _heartbeats(master, mark, node_id).count(state) >= count,
             f"{count} heartbeats in state {state}")
    frames = master.frames.since(mark)
    first = next(i for i, m in enumerate(frames)
                 if m.arbitration_id == 0x700 + node_id and m.data[0] == state)
    return mark + first + 1


def test_auto_start_off_boots_pre_operational_until_the_master_starts_it(
        cfg, unit_tables, channel) -> None:
    manual = dataclasses.replace(cfg, can=dataclasses.replace(cfg.can, nmt_auto_start=False))
    with master_on(manual, channel) as master, \
            service_thread(manual, unit_tables, channel):
        node = master.nodes["boom"]
        node.sdo[0x1017].raw = HEARTBEAT_MS                  # SDO works in PRE-OPERATIONAL
        boot = master.frames.since(0, 0x731)
        assert boot and boot[0].data[0] == 0                  # boot-up message first
        mark = _state_after(master, 49, 0x7F, count=5)
        assert master.frames.since(mark, 0x1B1) == []         # no PDO before start
        node.nmt.state = "OPERATIONAL"
        master.frames.wait_count(master.frames.mark(), 0x1B1, 3, "TPDO1 after start")
        assert master.frames.since(0, 0x1B2) == []            # the other node still waits


def test_stop_pre_operational_start_and_no_sdo_in_stopped(cfg, bus) -> None:
    service, master = bus
    node = master.nodes["boom"]
    node.sdo[0x1017].raw = HEARTBEAT_MS
    assert _heartbeats(master, 0, 49)[0] == 0                 # boot-up
    _state_after(master, 49, 5)                               # auto start: OPERATIONAL

    node.nmt.state = "STOPPED"
    mark = _state_after(master, 49, 4, count=5)
    assert master.frames.since(mark, 0x1B1) == [] and master.frames.since(mark, 0x2B1) == []
    assert master.frames.since(mark, 0x1B2)                   # the other node goes on
    node.sdo.RESPONSE_TIMEOUT = 0.3
    with pytest.raises(canopen.SdoCommunicationError):        # CiA 301: no SDO answer
        node.sdo[0x6020][1].raw
    assert master.frames.since(mark, 0x5B1) == []
    node.sdo.RESPONSE_TIMEOUT = 2.0

    node.nmt.state = "PRE-OPERATIONAL"
    mark = _state_after(master, 49, 0x7F, count=5)
    assert node.sdo[0x1017].raw == HEARTBEAT_MS               # SDO again
    assert master.frames.since(mark, 0x1B1) == []            # still no PDO

    node.nmt.state = "OPERATIONAL"
    master.frames.wait_count(master.frames.mark(), 0x1B1, 3, "TPDO1 after start")


def test_reset_communication_and_reset_node_restore_their_areas(cfg, bus) -> None:
    service, master = bus
    node = master.nodes["boom"]
    step = cfg.can.position_step_mm
    node.sdo[0x6010][1].raw = round(100.0 / step)             # the estimate: 100 mm
    node.sdo[0x1017].raw = HEARTBEAT_MS
    node.sdo[0x1800][5].raw = 20
    node.sdo[0x1801][1].raw = 0x8000_0000 | 0x4000_0000 | 0x2B1   # TPDO2 off
    node.sdo[0x1A01][0].raw = 0
    node.sdo[0x6401][1].raw = 1000                            # work area low limit
    node.sdo[0x1003][0].raw = 0                               # error history cleared

    mark = master.frames.mark()
    node.nmt.send_command(0x82)                               # reset communication
    wait_for(lambda: 0 in _heartbeats(master, mark, 49), "boot-up after reset communication")
    assert node.sdo[0x1017].raw == 1000                       # EDS default
    assert node.sdo[0x1800][5].raw == cfg.can.event_timer_ms  # the configured value
    assert node.sdo[0x1801][1].raw == 0x4000_0000 | 0x2B1     # valid again
    assert node.sdo[0x1A01][0].raw == 4
    assert node.sdo[0x6401][1].raw == 1000                    # application area: kept
    assert node.sdo[0x6020][1].raw == round(100.0 / step)     # the estimate is kept
    wait_for(lambda: node.sdo[0x1003][0].raw >= 1, "active faults reported again")
    master.frames.wait_count(master.frames.mark(), 0x2B1, 2, "TPDO2 after the reset")

    mark = master.frames.mark()
    node.nmt.send_command(0x81)                               # reset node
    wait_for(lambda: 0 in _heartbeats(master, mark, 49), "boot-up after reset node")
    assert node.sdo[0x6401][1].raw == -2 ** 31                # EDS default: no limit
    assert node.sdo[0x6005][1].raw == round(step * 1e6)       # configured step kept
    assert node.sdo[0x6020][1].raw == round(100.0 / step)
    assert 0 not in _heartbeats(master, mark, 50)               # addressed to node 49 only
