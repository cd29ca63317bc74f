"""Node and life guarding of one node without a bus, in the service's own (monotonic) time:
the answer byte, the life time counted from the last request, the EMCY it brings."""

from __future__ import annotations

import struct

import can
import pytest

from ddh_vsensor.device.emcy import LIFE_GUARD_CODE
from ddh_vsensor.device.network import ServiceNetwork
from ddh_vsensor.device.node import SensorNode
from ddh_vsensor.device.objects import Published

GUARD_ID, EMCY_ID = 0x700 + 49, 0x80 + 49
QUIET = Published(100.0, 0.0, 0.1, 0, 1, 0)          # no fault flag of the estimate


@pytest.fixture
def sent() -> list[can.Message]:
    return []


@pytest.fixture
def node(cfg, sent) -> SensorNode:
    n = SensorNode(ServiceNetwork(lambda m: sent.append(m) or True), cfg, "boom",
                   live=lambda: QUIET, on_preset=lambda mm: None)
    n.boot()
    n.node.sdo[0x1017].raw = 0
    sent.clear()
    return n


def _life_time(node: SensorNode, guard_ms: int, factor: int) -> None:
    node.node.sdo[0x100C].raw = guard_ms
    node.node.sdo[0x100D].raw = factor


def _emcy(node: SensorNode, sent: list[can.Message], now_s: float) -> list[tuple[int, int, int]]:
    """The tick at ``now_s``: (code, register, flag) of the EMCYs it sends."""
    mark = len(sent)
    node.error_control_due(now_s)
    node.report_faults(QUIET, now_s)
    return [(struct.unpack_from("<H", m.data)[0], m.data[2], m.data[3])
            for m in sent[mark:] if m.arbitration_id == EMCY_ID]


def test_answers_carry_the_state_and_a_toggle_from_zero(node, sent) -> None:
    for k in range(4):
        node.guarding.on_request(float(k))
    assert [bytes(m.data) for m in sent] == [b"\x05", b"\x85", b"\x05", b"\x85"]
    node.node.nmt.on_command(0, bytes([0x80, 0]), 0.0)        # pre-operational: no reset
    node.after_nmt_command()
    node.guarding.on_request(5.0)
    assert bytes(sent[-1].data) == b"\x7f"
    node.boot()
    sent.clear()
    node.guarding.on_request(6.0)
    assert bytes(sent[-1].data) == b"\x05"


def test_life_time_counts_from_the_last_request(node, sent) -> None:
    _life_time(node, 100, 3)                                  # 0.3 s
    assert _emcy(node, sent, 10.0) == []                      # no request yet: not started
    node.guarding.on_request(10.0)
    node.guarding.on_request(10.2)
    assert _emcy(node, sent, 10.49) == []
    assert _emcy(node, sent, 10.51) == [(LIFE_GUARD_CODE, 0x11, 0)]
    assert _emcy(node, sent, 11.0) == []                      # one EMCY per event
    assert node.node.sdo[0x1001].raw == 0x11 and node.node.sdo[0x1003][1].raw == LIFE_GUARD_CODE
    node.guarding.on_request(11.2)
    assert _emcy(node, sent, 11.21) == [(0x0000, 0x00, 0)]
    assert node.node.sdo[0x1001].raw == 0


def test_life_guarding_off_ends_the_event(node, sent) -> None:
    node.guarding.on_request(0.0)
    assert _emcy(node, sent, 100.0) == []                     # 0 x 0: never lost
    _life_time(node, 50, 2)
    node.guarding.on_request(100.0)
    assert _emcy(node, sent, 100.2)[0][0] == LIFE_GUARD_CODE
    _life_time(node, 0, 2)
    assert _emcy(node, sent, 100.3) == [(0x0000, 0x00, 0)]


def test_the_node_answers_nothing_while_initialising(node, sent) -> None:
    node.node.nmt._state = 0                                  # noqa: SLF001
    node.guarding.on_request(0.0)
    assert sent == [] and node.guarding.requests == 0
