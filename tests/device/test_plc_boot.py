"""A PLC master's whole boot-up of the sensors, as configuration tools generate it from the
EDS: reset communication, check identity against the EDS, guarding instead of heartbeats,
TPDO1 remapped to the position alone and made synchronous, start, then a SYNC cycle and
guarding running together. Each step is one the node tests elsewhere; this checks that they
hold together, on both nodes at once."""

from __future__ import annotations

import contextlib
from collections.abc import Iterator

import can

from .conftest import NOTIFIER_CYCLE_S, Feeder, Frames, wait_for

SYNC_PERIOD_S = 0.01
EVERY_NTH_SYNC = 2
GUARD_MS, LIFE_FACTOR = 100, 10          # 1 s life time: no stall of the test's threads trips it


@contextlib.contextmanager
def _tap(channel: str) -> Iterator[Frames]:
    """Every frame on the bus as a third node sees it, the master's SYNCs included."""
    frames = Frames()
    with can.Bus(interface="virtual", channel=channel) as tap:
        notifier = can.Notifier(tap, [frames], NOTIFIER_CYCLE_S)
        try:
            yield frames
        finally:
            notifier.stop()


def test_a_plc_boot_sequence_then_sync_and_guarding_together(cfg, bus, channel) -> None:
    service, master = bus
    nodes = master.nodes
    ids = {unit: node.id for unit, node in nodes.items()}
    mark = master.frames.mark()
    master.network.nmt.send_command(0x82)                    # reset communication, all
    for unit, node_id in ids.items():
        wait_for(lambda node_id=node_id: any(m.data[:1] == b"\x00" for m in
                                             master.frames.since(mark, 0x700 + node_id)),
                 f"{unit}'s boot-up")
    for unit, node in nodes.items():
        od = node.object_dictionary
        assert node.sdo[0x1000].raw == od[0x1000].default          # device type: CiA 406
        for sub in (1, 2, 3):                                       # vendor, product, revision
            assert node.sdo[0x1018][sub].raw == od[0x1018][sub].default
        node.sdo[0x1017].raw = 0
        node.sdo[0x100C].raw = GUARD_MS
        node.sdo[0x100D].raw = LIFE_FACTOR
        node.tpdo.read()
        tpdo = node.tpdo[1]
        tpdo.clear()
        tpdo.add_variable(0x6020, 1)
        tpdo.trans_type = EVERY_NTH_SYNC
        tpdo.enabled = True
        tpdo.save()
        node.tpdo[2].enabled = False
        node.tpdo[2].save()
    master.network.nmt.send_command(0x01)                     # start, all
    with Feeder(cfg, channel), _tap(channel) as observer:
        for node in nodes.values():
            node.nmt.start_node_guarding(GUARD_MS / 1000.0)
        master.network.sync.start(SYNC_PERIOD_S)
        try:
            wait_for(lambda: observer.since(0, 0x80), "the first SYNC")
            mark, seen = master.frames.mark(), observer.mark()
            for unit, node_id in ids.items():
                got = master.frames.wait_count(mark, 0x180 + node_id, 100, f"{unit}'s TPDO1s")
                assert {len(m.data) for m in got} == {4}              # the remapped layout
                master.frames.wait_count(mark, 0x700 + node_id, 10, f"{unit}'s answers")
        finally:
            master.network.sync.stop()
            for node in nodes.values():
                node.nmt.stop_node_guarding()
    for unit, node_id in ids.items():
        answers = [m.data[0] for m in master.frames.since(mark, 0x700 + node_id)]
        assert {a & 0x7F for a in answers} == {0x05}, unit          # OPERATIONAL throughout
        toggles = [a & 0x80 for a in answers]
        assert all(a != b for a, b in zip(toggles, toggles[1:])), unit
        emcy = [int.from_bytes(m.data[:2], "little") for m in
                master.frames.since(mark, 0x80 + node_id) if m.data[3] == 0]
        assert 0x8130 not in emcy, unit                             # guarded in time
        assert nodes[unit].nmt.state == "OPERATIONAL"
        # on the tap: one TPDO1 per two SYNCs (on the 10 ms event timer it would be one per
        # SYNC); counted, so a late frame at either end of the window is the only slack
        syncs = len(observer.since(seen, 0x80))
        sent = len(observer.since(seen, 0x180 + node_id))
        assert syncs >= 190 and abs(sent - syncs / EVERY_NTH_SYNC) <= 1, (unit, syncs, sent)
        assert not master.frames.since(mark, 0x280 + node_id), unit  # TPDO2 disabled
