"""Synchronous TPDOs as a master configures them (CiA 301): transmission type n sends at every
n-th SYNC and never on the event timer, type 0 at a SYNC after the data changed; the SYNC
COB-ID 0x1005 is consumed, not produced. Every "nothing came" is counted against frames that
did come (the other node's TPDO1s on their timer)."""

from __future__ import annotations

import canopen
import pytest

from ddh_vsensor.device.objects import ABORT_VALUE_RANGE

BOOM_TPDO1, BOOM_TPDO2, BUCKET_TPDO1 = 0x1B1, 0x2B1, 0x1B2


def _quiet_for(master, mark: int, periods: int) -> None:
    """``periods`` of the bucket's TPDO1 (10 ms each) pass after ``mark``."""
    master.frames.wait_count(mark, BUCKET_TPDO1, periods, "the bucket's TPDO1 on its timer")


def test_a_tpdo_of_type_n_goes_out_at_every_nth_sync_only(cfg, bus) -> None:
    service, master = bus
    sdo = master.nodes["boom"].sdo
    sdo[0x1800][2].raw = 2
    mark = master.frames.mark()
    _quiet_for(master, mark, 5)
    assert master.frames.since(mark, BOOM_TPDO1) == []          # no timer any more
    for k in range(1, 7):
        mark = master.frames.mark()
        master.network.sync.transmit()
        if k % 2 == 0:
            master.frames.wait_count(mark, BOOM_TPDO1, 1, f"TPDO1 after SYNC {k}")
        _quiet_for(master, mark, 3)
        assert len(master.frames.since(mark, BOOM_TPDO1)) == (k % 2 == 0)
    master.frames.wait_count(master.frames.mark(), BOOM_TPDO2, 2, "TPDO2 on its own timer")
    sdo[0x1800][2].raw = 254                                     # back on the event timer
    master.frames.wait_count(master.frames.mark(), BOOM_TPDO1, 5, "TPDO1 on its timer again")


def test_a_tpdo_of_type_0_goes_out_at_a_sync_after_its_data_changed(cfg, bus) -> None:
    service, master = bus
    node = master.nodes["boom"]
    node.sdo[0x1800][2].raw = 0
    sent = []
    for k, preset_mm in enumerate((100.0, None, 102.0, None)):   # within the jump bound
        if preset_mm is not None:
            node.sdo[0x6010][1].raw = round(preset_mm / cfg.can.position_step_mm)
        mark = master.frames.mark()
        master.network.sync.transmit()
        if preset_mm is not None:
            frame = master.frames.wait_count(mark, BOOM_TPDO1, 1, f"TPDO1 after SYNC {k + 1}")[0]
            position_steps = int.from_bytes(frame.data[:4], "little", signed=True)  # 0x6020
            assert position_steps == round(preset_mm / cfg.can.position_step_mm)
        _quiet_for(master, mark, 3)
        sent.append(len(master.frames.since(mark, BOOM_TPDO1)))
    assert sent == [1, 0, 1, 0]


def test_sync_cob_id_writes_outside_a_consumer_of_0x80_are_refused(cfg, bus) -> None:
    service, master = bus
    sdo = master.nodes["boom"].sdo
    assert sdo[0x1005].raw == 0x80
    for value in (0x81, 0x4000_0080, 0x2000_0080):      # another ID, produce SYNC, 29 bit
        with pytest.raises(canopen.SdoAbortedError) as exc:
            sdo[0x1005].raw = value
        assert exc.value.code == ABORT_VALUE_RANGE
    sdo[0x1005].raw = 0x80
    assert sdo[0x1005].raw == 0x80


def test_reset_communication_puts_a_synchronous_tpdo_back_on_its_timer(cfg, bus) -> None:
    service, master = bus
    node = master.nodes["boom"]
    node.sdo[0x1800][2].raw = 1
    mark = master.frames.mark()
    _quiet_for(master, mark, 5)
    assert master.frames.since(mark, BOOM_TPDO1) == []
    node.nmt.send_command(0x82)
    master.frames.wait_count(master.frames.mark(), BOOM_TPDO1, 5, "TPDO1 after the reset")
    assert node.sdo[0x1800][2].raw == 254
