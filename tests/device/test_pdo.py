"""PDOs as a master sees them: configuration read back over SDO, frames decoded by the
master's own PDO map, remapping by the CiA 301 procedure, refusals with their abort codes
(synchronous TPDOs: test_sync.py)."""

from __future__ import annotations

import canopen
import pytest

from ddh_vsensor.device.objects import (ABORT_MAP_LENGTH, ABORT_NOT_MAPPABLE,
                                         ABORT_UNSUPPORTED_ACCESS, ABORT_VALUE_RANGE)

PRESET_MM = 123.45


def _abort(call) -> int:
    with pytest.raises(canopen.SdoAbortedError) as exc:
        call()
    return exc.value.code


def test_master_reads_the_pdo_configuration_and_decodes_tpdos(cfg, bus) -> None:
    service, master = bus
    node = master.nodes["boom"]
    node.sdo[0x6010][1].raw = round(PRESET_MM / cfg.can.position_step_mm)
    node.tpdo.read()                                   # over SDO, as a master does
    tpdo1, tpdo2 = node.tpdo[1], node.tpdo[2]
    assert (tpdo1.cob_id, tpdo1.enabled, tpdo1.rtr_allowed, tpdo1.trans_type) == \
        (0x1B1, True, False, 254)                      # RTR not served: COB-ID bit 30 set
    assert tpdo1.event_timer == cfg.can.event_timer_ms and tpdo2.event_timer == 100
    assert [(v.index, v.subindex, v.length) for v in tpdo1.map] == \
        [(0x6020, 1, 32), (0x6030, 1, 16), (0x2000, 0, 8)]
    assert [(v.index, v.length) for v in tpdo2.map] == \
        [(0x2001, 32), (0x2002, 8), (0x2004, 8), (0x2003, 16)]
    assert tpdo1.wait_for_reception(10.0) is not None
    assert tpdo1[0x6020].raw == 12345                  # the preset, decoded by the master
    assert tpdo1[0x6030].raw == 0
    assert tpdo2.wait_for_reception(10.0) is not None
    assert _uncertainty_after_preset(cfg, tpdo2[0x2001].raw)
    flags = tpdo2[0x2002].raw
    assert flags & 0x01 and not flags & 0x02           # stale (no inputs), referenced


def _uncertainty_after_preset(cfg, counts: int) -> bool:
    """The preset's uncertainty, plus what standing stale (no inputs) adds: the worst-case
    travel since the preset, at most the stroke (32-bit counts of 0.01 mm decode it whole)."""
    low = cfg.estimator.uncertainty_reference_mm
    return round(low / 0.01) <= counts <= round(cfg.unit("bucket").stroke_mm / 0.01)


def test_master_remaps_a_tpdo_and_decodes_the_new_layout(cfg, bus) -> None:
    service, master = bus
    node = master.nodes["bucket"]
    node.sdo[0x6010][1].raw = 20000                   # 200.00 mm
    node.tpdo.read()
    tpdo = node.tpdo[1]
    tpdo.clear()
    tpdo.add_variable(0x6020, 1)
    tpdo.add_variable(0x2001)                          # uncertainty, 32 bits: 64 in all
    tpdo.save()                                        # disable, map, enable: CiA 301
    node.tpdo.read()                                   # what the node now says it sends
    assert [(v.index, v.length) for v in node.tpdo[1].map] == \
        [(0x6020, 32), (0x2001, 32)]
    tpdo = node.tpdo[1]
    mark = master.frames.mark()
    master.frames.wait_count(mark, 0x1B2, 3, "remapped TPDO1")
    assert tpdo.wait_for_reception(10.0) is not None
    assert len(tpdo.data) == 8
    assert tpdo[0x6020].raw == 20000
    assert _uncertainty_after_preset(cfg, tpdo[0x2001].raw)
    # the other node and TPDO2 are untouched
    assert len(master.frames.since(mark, 0x1B1)[-1].data) == 7


def test_pdo_writes_outside_the_supported_set_are_refused(cfg, bus) -> None:
    service, master = bus
    sdo = master.nodes["boom"].sdo
    valid = 0x4000_0000 | 0x1B1
    # mapping while the PDO is valid (CiA 301: disable first)
    assert _abort(lambda: sdo[0x1A00][0].__setattr__("raw", 0)) == ABORT_UNSUPPORTED_ACCESS
    # COB-ID: another ID, RTR allowed (bit 30 clear), a 29-bit ID: refused
    for cob_id in (0x4000_0000 | 0x1C0, 0x1B1, valid | 0x2000_0000):
        assert _abort(lambda c=cob_id: sdo[0x1800][1].__setattr__("raw", c)) == \
            ABORT_VALUE_RANGE
    for trans_type in (241, 252, 253):                # reserved, RTR only
        assert _abort(lambda t=trans_type: sdo[0x1800][2].__setattr__("raw", t)) == \
            ABORT_VALUE_RANGE
    assert _abort(lambda: sdo[0x1800][3].__setattr__("raw", 10)) == ABORT_VALUE_RANGE
    sdo[0x1800][2].raw = 255                          # event-driven, profile: accepted
    sdo[0x1800][1].raw = valid | 0x8000_0000          # disable
    assert _abort(lambda: sdo[0x1A00][1].__setattr__("raw", 0x60200120)) == \
        ABORT_UNSUPPORTED_ACCESS                       # sub 0 must be 0 first
    sdo[0x1A00][0].raw = 0
    assert _abort(lambda: sdo[0x1800][1].__setattr__("raw", valid)) == ABORT_VALUE_RANGE
    for entry in (0x60050120, 0x60200110, 0x70000008, 0x10170010):  # not mappable / length
        assert _abort(lambda e=entry: sdo[0x1A00][1].__setattr__("raw", e)) == \
            ABORT_NOT_MAPPABLE
    for sub in (1, 2, 3):
        sdo[0x1A00][sub].raw = 0x60200120              # 3 x 32 bits
    assert _abort(lambda: sdo[0x1A00][0].__setattr__("raw", 3)) == ABORT_MAP_LENGTH
    assert _abort(lambda: sdo[0x1A00][0].__setattr__("raw", 9)) == ABORT_MAP_LENGTH
    sdo[0x1A00][2].raw = 0x60300110
    sdo[0x1A00][3].raw = 0x20000008
    sdo[0x1A00][0].raw = 3
    sdo[0x1800][1].raw = valid                         # the default mapping, valid again
    assert sdo[0x1800][1].raw == valid and sdo[0x1800][2].raw == 255


def test_a_disabled_tpdo_is_not_sent(cfg, bus) -> None:
    service, master = bus
    sdo = master.nodes["boom"].sdo
    sdo[0x1801][1].raw = 0x8000_0000 | 0x4000_0000 | 0x2B1
    mark = master.frames.mark()
    master.frames.wait_count(mark, 0x1B1, 40, "TPDO1 while TPDO2 is disabled")  # 4 periods
    assert master.frames.since(mark, 0x2B1) == []
    assert master.frames.since(mark, 0x2B2)            # the other node's TPDO2 goes on
    sdo[0x1801][1].raw = 0x4000_0000 | 0x2B1
    master.frames.wait_count(master.frames.mark(), 0x2B1, 2, "TPDO2 enabled again")
