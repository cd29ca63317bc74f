"""Node guarding and life guarding as a master that polls its nodes drives them (CiA 301):
canopen's own ``NmtMaster.start_node_guarding`` sends the remote frames, the node answers
with its state and a toggling bit 7; a life time set over SDO and then missed brings EMCY
8130, and requests coming again its error reset. Every "nothing came" is counted against
frames that did come (answers, TPDO1s)."""

from __future__ import annotations

from ddh_vsensor.device.emcy import LIFE_GUARD_CODE

from .conftest import Feeder, wait_for

BOOM_NODE = 0x31
GUARD_ID, EMCY_ID, BOOM_TPDO1 = 0x700 + BOOM_NODE, 0x80 + BOOM_NODE, 0x1B1
STOPPED, OPERATIONAL, PRE_OPERATIONAL = 0x04, 0x05, 0x7F


def _request(master) -> int:
    """One guard request by hand, with no heartbeat on the bus: its answer byte."""
    mark = master.frames.mark()
    master.network.send_message(GUARD_ID, None, remote=True)
    return master.frames.wait_count(mark, GUARD_ID, 1, "a node guarding answer")[0].data[0]


def _emcys(master, mark: int) -> list[tuple[int, int]]:
    """(error code, error register) of each EMCY since ``mark`` that concerns no flag of
    the estimate (the estimate's own flags, inputs stale here, come and go as they do)."""
    return [(int.from_bytes(m.data[:2], "little"), m.data[2])
            for m in master.frames.since(mark, EMCY_ID) if m.data[3] == 0]


def test_a_guarding_master_gets_the_nmt_state_with_a_toggle_bit(cfg, bus) -> None:
    service, master = bus
    assert cfg.can.units["boom"].sensor_node_id == BOOM_NODE
    node = master.nodes["boom"]
    node.sdo[0x1017].raw = 0                        # guarding instead of the heartbeat
    answers = [_request(master) for _ in range(5)]
    assert answers == [OPERATIONAL, OPERATIONAL | 0x80] * 2 + [OPERATIONAL]
    node.nmt.state = "STOPPED"
    assert wait_for(lambda: _request(master) & 0x7F == STOPPED, "STOPPED in an answer")
    node.nmt.state = "PRE-OPERATIONAL"
    assert wait_for(lambda: _request(master) & 0x7F == PRE_OPERATIONAL,
                    "PRE-OPERATIONAL in an answer")
    node.nmt.state = "OPERATIONAL"
    mark = master.frames.mark()
    node.nmt.start_node_guarding(0.02)              # canopen's master reads the answers
    try:
        got = master.frames.wait_count(mark, GUARD_ID, 10, "answers to canopen's guarding")
        assert node.nmt.state == "OPERATIONAL"
    finally:
        node.nmt.stop_node_guarding()
    toggles = [m.data[0] & 0x80 for m in got]
    assert all(a != b for a, b in zip(toggles, toggles[1:])), toggles
    assert service.units["boom"].node.guarding.requests >= 10 + 5 + 2


def test_a_reset_starts_the_toggle_at_zero_again(cfg, bus) -> None:
    service, master = bus
    node = master.nodes["boom"]
    node.sdo[0x1017].raw = 0
    assert _request(master) == OPERATIONAL                  # the next would carry 0x80
    mark = master.frames.mark()
    node.nmt.send_command(0x82)                             # reset communication
    master.frames.wait_count(mark, GUARD_ID, 1, "the boot-up message")
    node.sdo[0x1017].raw = 0                                # back to the EDS's 1000 ms
    wait_for(lambda: node.sdo[0x1017].raw == 0 and
             service.units["boom"].node.heartbeat_period_s == 0.0, "heartbeat off again")
    assert _request(master) == OPERATIONAL


def test_missed_guard_requests_bring_emcy_8130_and_requests_again_its_reset(
        cfg, bus, channel) -> None:
    service, master = bus
    with Feeder(cfg, channel):                      # fresh inputs: register bit 4 is ours
        wait_for(lambda: not service.units["boom"].node.emcy.register(
            service.published(service.units["boom"]).flags) & 0x10, "inputs fresh")
        _life_guarding(master)


def _life_guarding(master) -> None:
    node = master.nodes["boom"]
    node.sdo[0x1017].raw = 0
    node.sdo[0x100C].raw = 200                      # ms: life time 1 s against 20 ms polls
    node.sdo[0x100D].raw = 5
    assert (node.sdo[0x100C].raw, node.sdo[0x100D].raw) == (200, 5)
    mark = master.frames.mark()
    node.nmt.start_node_guarding(0.02)
    try:
        master.frames.wait_count(mark, GUARD_ID, 60, "answers while guarded")
    finally:
        node.nmt.stop_node_guarding()
    assert _emcys(master, mark) == []               # 60 x 20 ms polls in a 1 s life time
    code, register = wait_for(lambda: _emcys(master, mark), "the life guarding EMCY")[0]
    assert (code, register & 0x11) == (LIFE_GUARD_CODE, 0x11)
    assert node.sdo[0x1001].raw & 0x10
    assert node.sdo[0x1003][1].raw == LIFE_GUARD_CODE
    after = master.frames.mark()                    # the node keeps publishing
    master.frames.wait_count(after, BOOM_TPDO1, 5, "TPDO1 after the event")
    assert _emcys(master, after) == []              # one EMCY per event
    back = master.frames.mark()
    _request(master)
    code, register = wait_for(lambda: _emcys(master, back), "the error reset")[0]
    assert (code, register & 0x10) == (0x0000, 0)
    assert not node.sdo[0x1001].raw & 0x10


def test_a_data_frame_on_the_guarding_id_is_another_sender(cfg, bus) -> None:
    service, master = bus
    master.nodes["boom"].sdo[0x1017].raw = 0        # no heartbeat: nothing else on the ID
    master.frames.wait_count(master.frames.mark(), BOOM_TPDO1, 2, "TPDO1s after the write")
    before = service.inputs.counts["id_clash"]
    mark = master.frames.mark()
    master.network.send_message(GUARD_ID, bytes([OPERATIONAL]))
    master.frames.wait_count(mark, BOOM_TPDO1, 3, "TPDO1s after the frame")
    assert service.inputs.counts["id_clash"] == before + 1
    assert master.frames.since(mark, GUARD_ID) == []        # not answered


def test_guard_requests_are_not_counted_as_remote_requests(cfg, bus) -> None:
    service, master = bus
    master.nodes["boom"].sdo[0x1017].raw = 0
    for _ in range(3):
        _request(master)
    assert service.inputs.counts["remote_requests"] == 0
