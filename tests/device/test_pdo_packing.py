"""The node's compiled TPDO packing gives the bytes canopen's per-variable encoding gives, for
the default mappings and for mappings a master writes over SDO (recompiled on every change)."""

from __future__ import annotations

import random
import struct

import can
import pytest

from ddh_vsensor.device.network import ServiceNetwork
from ddh_vsensor.device.node import SensorNode
from ddh_vsensor.device.objects import PDO_INVALID, Published


def records(count: int) -> list[Published]:
    rng = random.Random(406)
    edge = [Published(0.0, 0.0, 0.0, 0, 0, 0),
            Published(1e12, 1e9, 1e9, 0xFFF, 2 ** 40, 2 ** 40),      # saturate every field
            Published(-1e12, -1e9, -5.0, 0x7F, 65535, 65536)]
    return edge + [Published(rng.uniform(-50, 3000), rng.uniform(-5000, 5000),
                             rng.uniform(0, 2e5), rng.getrandbits(8), rng.getrandbits(20),
                             rng.getrandbits(17)) for _ in range(count)]


@pytest.fixture
def node(cfg) -> SensorNode:
    sent: list[can.Message] = []
    n = SensorNode(ServiceNetwork(lambda m: sent.append(m) or True), cfg, cfg.unit_names[0],
                   live=lambda: Published(1.0, 0.0, 0.5, 0, 0, 0), on_preset=lambda mm: None)
    n.boot()
    return n


def assert_packs_like_canopen(node: SensorNode, pdo, expect_compiled: bool = True) -> None:
    for p in records(300):
        node.pdos.packers.pop(pdo, None)
        node._encode(pdo, p)                            # noqa: SLF001 - compiled
        fast = bytes(pdo.data)
        assert (node.pdos.packers[pdo] is not None) == expect_compiled
        node.pdos.packers[pdo] = None                   # canopen encodes every variable
        pdo.data[:] = bytes(len(pdo.data))
        node._encode(pdo, p)                            # noqa: SLF001
        assert fast == bytes(pdo.data), p


def remap(node: SensorNode, tpdo: int, entries: list[tuple[int, int, int]]) -> None:
    """The CiA 301 procedure over the node's SDO server: disable, sub 0 = 0, entries,
    sub 0 = n, enable."""
    local = node.node
    com, mapping = 0x1800 + tpdo - 1, 0x1A00 + tpdo - 1
    cob_id = struct.unpack("<I", local.get_data(com, 1))[0] & ~PDO_INVALID
    local.set_data(com, 1, struct.pack("<I", cob_id | PDO_INVALID), check_writable=True)
    local.set_data(mapping, 0, b"\x00", check_writable=True)
    for sub, (index, subindex, bits) in enumerate(entries, start=1):
        local.set_data(mapping, sub, struct.pack("<I", index << 16 | subindex << 8 | bits),
                       check_writable=True)
    local.set_data(mapping, 0, bytes([len(entries)]), check_writable=True)
    local.set_data(com, 1, struct.pack("<I", cob_id), check_writable=True)


def test_default_mappings_pack_like_canopen(node) -> None:
    assert_packs_like_canopen(node, node.tpdo1)
    assert_packs_like_canopen(node, node.tpdo2)


@pytest.mark.parametrize("entries", [
    [(0x2001, 0, 32), (0x6020, 1, 32)],
    [(0x0005, 0, 8), (0x6400, 1, 8), (0x6503, 0, 16), (0x6505, 0, 16), (0x2004, 0, 8),
     (0x1001, 0, 8)],
    [(0x2003, 0, 16), (0x6030, 1, 16), (0x0005, 0, 8), (0x2000, 0, 8)],
], ids=["uncertainty-position", "dummy-area-alarms-warnings-register",
        "counter-speed-dummy"])
def test_remapped_tpdo_packs_like_canopen(node, entries) -> None:
    node._encode(node.tpdo1, records(1)[0])             # noqa: SLF001 - compiled, cached
    assert node.pdos.packers[node.tpdo1] is not None
    remap(node, 1, entries)
    assert node.tpdo1 not in node.pdos.packers          # a new mapping: compiled anew
    assert [(v.index, v.subindex, v.length) for v in node.tpdo1.map] == entries
    assert len(node.tpdo1.data) == sum(bits for *_, bits in entries) // 8
    assert_packs_like_canopen(node, node.tpdo1)


def test_a_reset_communication_recompiles_the_default_mapping(node) -> None:
    remap(node, 2, [(0x6020, 1, 32)])
    node._encode(node.tpdo2, records(1)[0])             # noqa: SLF001
    node.restore_defaults(communication_only=True)
    assert node.tpdo2 not in node.pdos.packers
    assert [v.index for v in node.tpdo2.map] == [0x2001, 0x2002, 0x2004, 0x2003]
    assert_packs_like_canopen(node, node.tpdo2)
