"""Every frame the service sends decodes with the machine's generated database: PDOs, heartbeats and boot-ups,
EMCYs, SDO responses (aborts included), before and after an NMT reset."""

from __future__ import annotations

import canopen
import pytest

from ddh_vsensor.canbus.dbc import FrameCodec

from .conftest import wait_for


def test_every_frame_the_service_sends_decodes_with_the_dbc(cfg, bus) -> None:
    service, master = bus
    node = master.nodes["bucket"]
    wait_for(lambda: len(node.emcy.log) >= 2, "EMCYs (cold start: stale, not referenced)")
    node.sdo[0x6010][1].raw = 15000
    wait_for(lambda: any(e.code == 0 for e in node.emcy.log), "error reset: referenced")
    with pytest.raises(canopen.SdoAbortedError):
        node.sdo[0x6020][1].raw = 1                               # read-only: abort frame
    mark = master.frames.mark()
    node.nmt.send_command(0x81)
    wait_for(lambda: any(m.data[0] == 0 for m in master.frames.since(mark, 0x732)), "boot-up")
    master.frames.wait_count(master.frames.mark(), 0x2B2, 2, "TPDO2 after the reset")
    frames = master.frames.since(0)
    codec = FrameCodec(cfg)
    db = codec.database
    names = set()
    for msg in frames:
        decoded = codec.decode(msg)
        assert decoded is not None, f"0x{msg.arbitration_id:03X} is not in the DBC"
        name, _ = decoded
        db.decode_message(msg.arbitration_id, bytes(msg.data))   # with value tables too
        names.add(name)
    assert {"POSITION_BUCKET_TPDO1", "DIAG_BUCKET_TPDO2", "SENSOR_BUCKET_HEARTBEAT",
            "SENSOR_BUCKET_EMCY", "SENSOR_BUCKET_SDO_TX", "POSITION_BOOM_TPDO1"} <= names
    emcy = [codec.decode(m)[1] for m in frames if m.arbitration_id == 0xB2]
    assert {e["ErrorCode"] for e in emcy} >= {0x8100, 0xFF02, 0x0000}
    assert all(e["RegisterGeneric"] == (e["ErrorCode"] != 0 or e["ActiveStaleInput"] > 0)
               for e in emcy)
