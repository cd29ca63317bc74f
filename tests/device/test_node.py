"""The emulated CiA 406 node without a bus: what it sends at each tick, its SDO objects."""

from __future__ import annotations

import can
import pytest
from canopen.sdo import SdoAbortedError

from ddh_vsensor.canbus.dbc import FrameCodec, message_name
from ddh_vsensor.device.network import ServiceNetwork
from ddh_vsensor.device.node import SensorNode
from ddh_vsensor.device.objects import Published


@pytest.fixture
def sent() -> list[can.Message]:
    return []


@pytest.fixture
def node(cfg, sent) -> SensorNode:
    network = ServiceNetwork(lambda m: sent.append(m) or True)
    presets: list[float] = []
    n = SensorNode(network, cfg, "boom",
                   live=lambda: Published(123.456, -45.67, 1.25, 0x0A, 70000, 3),
                   on_preset=presets.append)
    n.presets_seen = presets
    n.boot()
    return n


def test_boot_sends_boot_up_then_is_operational(node, sent) -> None:
    assert [(m.arbitration_id, bytes(m.data)) for m in sent] == [(0x700 + 49, b"\x00")]
    assert node.operational and node.heartbeat_period_s == 1.0


def test_tpdo_schedule_follows_each_timer(cfg, node, sent) -> None:
    codec = FrameCodec(cfg)
    node.event_timer_ms, node.diag_timer_ms = 10.0, 100.0
    node.set_tick(5.0)                              # another node ticks every 5 ms
    sent.clear()
    p = Published(10.0, 1.0, 0.5, 0, 5, 0)
    for tick in range(40):
        node.publish(p, tick)
    pos = [i for i, m in enumerate(sent) if m.arbitration_id == 0x1B1]
    diag = [i for i, m in enumerate(sent) if m.arbitration_id == 0x2B1]
    assert len(pos) == 20 and len(diag) == 2        # every 2nd tick, every 20th tick
    assert all(sent[i - 1].arbitration_id == 0x1B1 for i in diag)   # paired with a position
    decoded = codec.decode(sent[diag[0]])[1]
    assert decoded["Uncertainty"] == pytest.approx(0.5) and decoded["InputFrames"] == 5
    assert codec.ids[message_name("position", "boom")] == 0x1B1


def test_late_ticks_do_not_burst(node, sent) -> None:
    node.set_tick(10.0)
    sent.clear()
    p = Published(10.0, 1.0, 0.5, 0, 5, 0)
    for tick in (0, 1, 7, 8):                       # ticks 2..6 were missed
        node.publish(p, tick)
    assert sum(m.arbitration_id == 0x1B1 for m in sent) == 4


def test_sdo_reads_are_live_and_saturate(node) -> None:
    sdo = node.node.sdo
    assert sdo[0x6020][1].raw == 12346              # 123.456 mm in 0.01 mm steps
    assert sdo[0x6030][1].raw == -457               # 0.1 mm/s
    assert sdo[0x2001].raw == 125 and sdo[0x2002].raw == 0x0A
    assert sdo[0x2003].raw == 70000 % 65536 and sdo[0x2004].raw == 3
    assert sdo[0x6005][1].raw == 10000


def test_preset_within_the_stroke_only(node) -> None:
    sdo = node.node.sdo
    sdo[0x6010][1].raw = 31115                      # 311.15 mm: the top end, allowed
    assert node.presets_seen == [pytest.approx(311.15)]
    for counts in (31116, -1):
        with pytest.raises(SdoAbortedError):
            node.node.set_data(0x6010, 1, counts.to_bytes(4, "little", signed=True))
    assert len(node.presets_seen) == 1


def test_stopped_node_sends_nothing(node, sent) -> None:
    node.node.nmt.on_command(0, bytes([0x02, 49]), 0.0)
    node.after_nmt_command()
    sent.clear()
    assert node.publish(Published(1.0, 0.0, 0.0, 0, 0, 0), 0) == 0 and not sent
    node.error_control_due(100.0)
    assert [bytes(m.data) for m in sent] == [b"\x04"]   # heartbeat says STOPPED


def test_auto_start_off_stays_pre_operational(cfg, sent) -> None:
    import dataclasses
    manual = dataclasses.replace(cfg, can=dataclasses.replace(cfg.can, nmt_auto_start=False))
    n = SensorNode(ServiceNetwork(lambda m: sent.append(m) or True), manual, "boom",
                   live=lambda: Published(1.0, 0.0, 0.0, 0, 0, 0), on_preset=lambda mm: None)
    n.boot()
    assert n.node.nmt.state == "PRE-OPERATIONAL" and not n.operational
    assert n.publish(Published(1.0, 0.0, 0.0, 0, 0, 0), 0) == 0


def test_emcy_per_fault_flag_and_error_reset(node, sent) -> None:
    node.node.sdo[0x1015].raw = 0                                   # no inhibit time
    sent.clear()
    p = Published(1.0, 0.0, 0.1, 0x01 | 0x02 | 0x04 | 0x08, 0, 0)   # soft limit, adapting:
    assert node.report_faults(p) == 2                               # not faults
    assert [bytes(m.data) for m in sent] == [
        bytes([0x00, 0x81, 0x91, 0x01, 0x03, 0, 0, 0]),
        bytes([0x02, 0xFF, 0x91, 0x02, 0x03, 0, 0, 0])]
    assert all(m.arbitration_id == 0xB1 for m in sent)
    assert node.report_faults(p) == 0                               # once per change
    sent.clear()
    assert node.report_faults(Published(1.0, 0.0, 0.1, 0x02 | 0x40, 0, 0)) == 2
    assert [bytes(m.data[:5]) for m in sent] == [
        bytes([0x00, 0x00, 0x91, 0x01, 0x42]),                      # stale cleared
        bytes([0x30, 0x81, 0x91, 0x40, 0x42])]                      # controller lost
    assert node.node.sdo[0x1003][0].raw == 3
    assert node.node.sdo[0x1003][1].raw == 0x8130 | 0x40 << 16      # newest first


def test_reset_communication_keeps_the_application_area(node, sent) -> None:
    sdo = node.node.sdo
    sdo[0x1017].raw = 100
    sdo[0x6401][1].raw = 7
    node.network.notify(0, bytes([0x82, 49]), 0.0)                 # as the service routes it
    node.after_nmt_command()
    assert sdo[0x1017].raw == 1000 and sdo[0x6401][1].raw == 7
    assert node.heartbeat_period_s == 1.0 and node.operational
    node.network.notify(0, bytes([0x81, 0]), 0.0)                  # reset node, broadcast
    node.after_nmt_command()
    assert sdo[0x6401][1].raw == -2 ** 31


def test_emcy_inhibit_time_bounds_a_flapping_flag(node, sent) -> None:
    assert node.node.sdo[0x1015].raw == 100                         # 10 ms, EDS default
    sent.clear()
    flapping = [Published(1.0, 0.0, 0.1, 0x40 * (k % 2), 0, 0) for k in range(100)]
    sent_at_ms = [k for k, p in enumerate(flapping)                 # a change every 1 ms
                  if node.report_faults(p, now_s=k * 0.001)]
    gaps = [b - a for a, b in zip(sent_at_ms, sent_at_ms[1:])]
    assert len(sent) == len(sent_at_ms) >= 8 and min(gaps) >= 10    # one per 10 ms at most
    both = Published(1.0, 0.0, 0.1, 0x01 | 0x02, 0, 0)              # two at once
    first = len(sent)
    assert node.report_faults(both, now_s=1.0) == 1
    assert node.report_faults(both, now_s=1.005) == 0                # the second waits
    assert node.report_faults(both, now_s=1.010) == 1
    assert [int.from_bytes(m.data[:2], "little") for m in sent[first:]] == [0x8100, 0xFF02]
    assert node.node.sdo[0x1003][1].raw & 0xFFFF == 0xFF02           # the field: at once


def test_a_fault_gone_before_its_emcy_leaves_no_stale_register(node, sent) -> None:
    """Stale clears while a preset's unconfirmed flag waits for the inhibit time, which then
    clears too: the error reset of stale counted it, a last reset says the register is 0."""
    sent.clear()
    assert node.report_faults(Published(1.0, 0.0, 0.1, 0x01, 0, 0), now_s=1.0) == 1
    assert node.report_faults(Published(1.0, 0.0, 0.1, 0x20, 0, 0), now_s=1.010) == 1
    assert bytes(sent[-1].data[:5]) == bytes([0x00, 0x00, 0x81, 0x01, 0x20])   # stale cleared
    assert node.report_faults(Published(1.0, 0.0, 0.1, 0x00, 0, 0), now_s=1.015) == 0
    assert node.report_faults(Published(1.0, 0.0, 0.1, 0x00, 0, 0), now_s=1.020) == 1
    assert bytes(sent[-1].data[:5]) == bytes([0x00, 0x00, 0x00, 0x00, 0x00])   # register 0
    assert node.report_faults(Published(1.0, 0.0, 0.1, 0x00, 0, 0), now_s=1.030) == 0
