"""The unit's health as a generic master sees it (issue 38 item 1): record 0x2010 over SDO (the
REAL32 sub-indices included), TPDO3 on its own event timer decoded with the machine's DBC, the
EMCY warning FF30 "maintenance due" with error register bit 7 while the alarm lasts, kept over
NMT resets, TPDO3 configured by a master like TPDO1 and TPDO2.

The service runs in its thread as in the other device tests; the health is handed to the node
in the service's loop (as the service's own wiring does). Every "nothing came" is counted
against frames that did come (TPDO1s on their timer), never against the wall clock."""

from __future__ import annotations

import dataclasses
import math
import threading

import canopen
import cantools
import pytest

from ddh_vsensor.canbus.layout import camel, machine_database, message_name
from ddh_vsensor.device.emcy import FAULT_FLAGS
from ddh_vsensor.device.objects import (ABORT_NOT_MAPPABLE, ABORT_READ_ONLY,
                                         ABORT_UNSUPPORTED_ACCESS, ABORT_VALUE_RANGE,
                                         ABORT_VALUE_TOO_LOW, PDO_INVALID, PDO_NO_RTR, Health)
from ddh_vsensor.diagnosis.causes import CAUSE_NAMES
from ddh_vsensor.estimator.flags import Flags
from ddh_vsensor.service import Service, ServiceOptions

from .conftest import WAIT_S, FlaggedService, master_on, service_thread, wait_for

BOOM_TPDO1, BOOM_TPDO3, BOOM_EMCY, BOOM_BOOT_UP = 0x1B1, 0x3B1, 0xB1, 0x731
BUCKET_TPDO1 = 0x1B2
OPTIONS = ServiceOptions(stale_periods=50.0)

# 3: the catalogue's third cause; 1.234 mm now, 2.5 mm at the horizon, 7.3 days to go
HEALTH = Health(cause_code=3, alarm=False, days_needed=0, days=12, error_now_mm=1.234,
                error_projected_mm=2.5, days_to_tolerance=7.3, value=1.02,
                interval=(1.01, 1.03))
HEALTH_DATA = bytes([3, 0x00]) + (123).to_bytes(2, "little") + (250).to_bytes(2, "little") \
    + (73).to_bytes(2, "little")
ALARM = dataclasses.replace(HEALTH, alarm=True, error_projected_mm=3.4, days_to_tolerance=9.6)
ALARM_DATA = bytes([3, 0x01]) + (123).to_bytes(2, "little") + (340).to_bytes(2, "little") \
    + (96).to_bytes(2, "little")


def set_health(service: Service, unit: str, health: Health | None) -> None:
    """``unit``'s node gets ``health`` in the service's loop (as the service hands it)."""
    done = threading.Event()

    def apply() -> None:
        try:
            service.units[unit].node.set_health(health)
        finally:
            done.set()
    assert service._loop is not None                                    # noqa: SLF001
    service._loop.call_soon_threadsafe(apply)                           # noqa: SLF001
    assert done.wait(WAIT_S), "the service's loop did not run the call"


def _tpdo3_with(master, mark: int, data: bytes, what: str) -> None:
    wait_for(lambda: any(bytes(m.data) == data for m in master.frames.since(mark, BOOM_TPDO3)),
             what)


def _codes(emcy, start: int = 0) -> list[int]:
    return [e.code for e in emcy.log[start:]]


def _emcy(emcy, start: int, code: int):
    """The first EMCY with ``code`` since ``start`` (None: none yet)."""
    return next((e for e in emcy.log[start:] if e.code == code), None)


def _aborts(write) -> int:
    with pytest.raises(canopen.SdoAbortedError) as exc:
        write()
    return exc.value.code


def _tpdo1s_without_tpdo3(master, count: int) -> None:
    """``count`` of boom's TPDO1s go out and no TPDO3 among them."""
    mark = master.frames.mark()
    master.frames.wait_count(mark, BOOM_TPDO1, count, "boom's TPDO1 on its timer")
    assert master.frames.since(mark, BOOM_TPDO3) == []


@pytest.fixture
def quiet(cfg, unit_tables, channel):
    """Master and service, the faults hidden at the service's boundary: the error register
    is the health's alone."""
    with master_on(cfg, channel) as master, \
            service_thread(cfg, unit_tables, channel, OPTIONS, FlaggedService) as service:
        service.extra_flags = {}
        service.masked_flags = FAULT_FLAGS
        sdo = master.nodes["boom"].sdo
        wait_for(lambda: sdo[0x1001].raw == 0, "error register 0 (faults masked)")
        yield service, master


def test_master_reads_the_health_over_sdo(cfg, bus) -> None:
    service, master = bus
    sdo = master.nodes["boom"].sdo
    set_health(service, "boom", None)
    assert sdo[0x2010][0].raw == 9
    assert sdo[0x2010][1].raw == 0 and sdo[0x2010][2].raw == 0x04        # no health yet
    assert [sdo[0x2010][s].raw for s in (3, 4, 5, 6)] == [0xFFFF, 0xFFFF, 0xFFFF, 0]
    assert all(math.isnan(sdo[0x2010][s].raw) for s in (7, 8, 9))
    set_health(service, "boom", HEALTH)
    assert [sdo[0x2010][s].raw for s in range(1, 7)] == [3, 0x00, 123, 250, 73, 12]
    assert [sdo[0x2010][s].raw for s in (7, 8, 9)] == \
        pytest.approx([1.02, 1.01, 1.03], rel=1e-7)                     # REAL32
    # too few days for a trend, nothing known yet, not within the horizon
    set_health(service, "boom", Health(0, False, 2, 1, None, None, None, None, None))
    assert [sdo[0x2010][s].raw for s in range(1, 7)] == [0, 0x02, 0xFFFF, 0xFFFF, 0xFFFF, 1]
    assert math.isnan(sdo[0x2010][7].raw)
    set_health(service, "boom", ALARM)
    assert sdo[0x2010][2].raw == 0x01 and sdo[0x2010][4].raw == 340
    assert master.nodes["bucket"].sdo[0x2010][2].raw == 0x04            # the other unit's
    assert _aborts(lambda: setattr(sdo[0x2010][1], "raw", 1)) == ABORT_READ_ONLY


def test_tpdo3_goes_out_on_its_own_timer_and_decodes_with_the_dbc(cfg, bus) -> None:
    service, master = bus
    node = master.nodes["boom"]
    assert wait_for(lambda: master.frames.since(0, BOOM_TPDO3), "TPDO3 at the first tick")
    _tpdo1s_without_tpdo3(master, 100)          # its default timer: 10 s, 1000 TPDO1 periods
    set_health(service, "boom", HEALTH)
    node.sdo[0x1802][5].raw = 50                # 5 TPDO1 periods
    mark = master.frames.mark()
    _tpdo3_with(master, mark, HEALTH_DATA, "TPDO3 with the health")
    master.frames.wait_count(mark, BOOM_TPDO3, 4, "TPDO3 on its 50 ms timer")
    frames = [m for m in master.frames.since(mark) if m.arbitration_id in (BOOM_TPDO1,
                                                                           BOOM_TPDO3)]
    health = [k for k, m in enumerate(frames) if m.arbitration_id == BOOM_TPDO3]
    for a, b in zip(health, health[1:]):        # at most every 5 ticks: never in between
        assert 1 <= b - a - 1 <= 5
    assert all(frames[k - 1].arbitration_id == BOOM_TPDO1 for k in health if k)  # its tick
    # the machine's DBC as `ddh-vsensor dbc` writes it: the cause names from the catalogue
    db = cantools.database.load_string(machine_database(cfg, CAUSE_NAMES).as_dbc_string(),
                                       database_format="dbc")
    message = db.get_message_by_name(message_name("health", "boom"))
    assert message.frame_id == BOOM_TPDO3
    decoded = message.decode(HEALTH_DATA)
    assert str(decoded["CauseCode"]) == camel(CAUSE_NAMES[3])
    assert (decoded["ErrorNow"], decoded["ErrorAtHorizon"], decoded["DaysToTolerance"]) == \
        pytest.approx((1.23, 2.5, 7.3))
    assert str(decoded["HealthAlarm"]) == "NoAlarm" and str(decoded["HealthNotYet"]) == "Computed"
    set_health(service, "boom", ALARM)
    _tpdo3_with(master, master.frames.mark(), ALARM_DATA, "TPDO3 with the alarm")
    assert str(message.decode(ALARM_DATA)["HealthAlarm"]) == "MaintenanceDue"
    # the master's own PDO map, read over SDO, decodes it too
    node.tpdo.read()
    tpdo3 = node.tpdo[3]
    assert (tpdo3.cob_id, tpdo3.trans_type, tpdo3.event_timer) == (BOOM_TPDO3, 254, 50)
    assert tpdo3.wait_for_reception(WAIT_S) is not None
    assert [v.raw for v in tpdo3.map] == [3, 0x01, 123, 340, 96]


def test_alarm_is_emcy_ff30_with_register_bit_7_and_an_error_reset(quiet) -> None:
    service, master = quiet
    node = master.nodes["boom"]
    start = len(node.emcy.log)
    set_health(service, "boom", ALARM)
    got = wait_for(lambda: _emcy(node.emcy, start, 0xFF30), "EMCY FF30")
    assert got.register == 0x81 and got.data[0] == 0        # generic + manufacturer, no flag
    assert node.sdo[0x1001].raw == 0x81
    assert node.sdo[0x1003][1].raw == 0xFF30                # newest first
    set_health(service, "boom", dataclasses.replace(ALARM, days_to_tolerance=8.0))
    set_health(service, "boom", HEALTH)                     # the alarm ends
    wait_for(lambda: 0x0000 in _codes(node.emcy, start), "error reset")
    assert _codes(node.emcy, start) == [0xFF30, 0x0000]     # still alarmed: no second FF30
    assert node.emcy.log[-1].register == 0 and node.sdo[0x1001].raw == 0
    set_health(service, "boom", ALARM)
    wait_for(lambda: _codes(node.emcy, start).count(0xFF30) == 2, "FF30 again")
    set_health(service, "boom", None)                       # no health: no alarm either
    wait_for(lambda: _codes(node.emcy, start)[-1] == 0, "error reset: health gone")
    assert node.sdo[0x2010][2].raw == 0x04
    assert all(m.data[:2] != b"\x30\xff" for m in master.frames.since(0, 0xB2))   # bucket


def test_alarm_follows_the_inhibit_time_and_stopped_rules(quiet) -> None:
    service, master = quiet
    node = master.nodes["boom"]
    node.sdo[0x1014].raw = PDO_INVALID | BOOM_EMCY          # EMCY invalid
    start = len(node.emcy.log)
    set_health(service, "boom", ALARM)
    _quiet_for_bucket(master, 20)
    assert len(node.emcy.log) == start and node.sdo[0x1001].raw == 0x81
    node.sdo[0x1014].raw = BOOM_EMCY                        # valid again: reported
    wait_for(lambda: 0xFF30 in _codes(node.emcy, start), "FF30 once the EMCY is valid")
    node.nmt.state = "STOPPED"
    wait_for(lambda: node.nmt.state == "STOPPED", "heartbeat STOPPED")
    start = len(node.emcy.log)
    set_health(service, "boom", HEALTH)
    _quiet_for_bucket(master, 20)
    assert len(node.emcy.log) == start                      # nothing in STOPPED
    node.nmt.state = "OPERATIONAL"
    wait_for(lambda: 0x0000 in _codes(node.emcy, start), "error reset once operational")
    # a fault and the alarm at once: one EMCY per inhibit time, both told in the end
    node.sdo[0x1015].raw = 500                              # 50 ms
    start = len(node.emcy.log)
    service.extra_flags = {"boom": Flags.TABLE_CLAMPED}
    set_health(service, "boom", ALARM)
    wait_for(lambda: {0xFF10, 0xFF30} <= set(_codes(node.emcy, start)), "FF10 and FF30")
    assert node.emcy.log[-1].register == 0x81


def _quiet_for_bucket(master, periods: int) -> None:
    master.frames.wait_count(master.frames.mark(), BUCKET_TPDO1, periods,
                             "the bucket's TPDO1 on its timer")


def test_health_survives_nmt_resets_and_the_alarm_is_announced_again(quiet) -> None:
    service, master = quiet
    node = master.nodes["boom"]
    set_health(service, "boom", ALARM)
    wait_for(lambda: _emcy(node.emcy, 0, 0xFF30), "EMCY FF30")
    for command in (0x82, 0x81):                            # reset communication, node
        start, mark = len(node.emcy.log), master.frames.mark()
        node.nmt.send_command(command)
        wait_for(lambda: any(bytes(m.data) == b"\x00"
                             for m in master.frames.since(mark, BOOM_BOOT_UP)), "boot-up")
        wait_for(lambda: 0xFF30 in _codes(node.emcy, start), "FF30 after the boot")
        _tpdo3_with(master, mark, ALARM_DATA, "TPDO3 at the first tick after the boot")
        assert [node.sdo[0x2010][s].raw for s in range(1, 7)] == [3, 0x01, 123, 340, 96, 12]
        assert node.sdo[0x2010][7].raw == pytest.approx(1.02)
        assert node.sdo[0x1001].raw == 0x81
        assert node.sdo[0x1003][0].raw == 1 and node.sdo[0x1003][1].raw == 0xFF30


def test_master_remaps_disables_and_synchronises_tpdo3(cfg, bus) -> None:
    service, master = bus
    node = master.nodes["boom"]
    sdo = node.sdo
    set_health(service, "boom", HEALTH)
    cob_id = PDO_NO_RTR | BOOM_TPDO3
    # mapping while valid, objects that cannot be mapped, 0 ms: refused as for TPDO1/2
    assert _aborts(lambda: setattr(sdo[0x1A02][0], "raw", 0)) == ABORT_UNSUPPORTED_ACCESS
    assert _aborts(lambda: setattr(sdo[0x1802][5], "raw", 0)) == ABORT_VALUE_TOO_LOW
    assert _aborts(lambda: setattr(sdo[0x1802][1], "raw", 0x3B2)) == ABORT_VALUE_RANGE
    sdo[0x1802][1].raw = cob_id | PDO_INVALID
    sdo[0x1A02][0].raw = 0
    for sub in (6, 7, 0):                                   # days, REAL32, the count
        assert _aborts(lambda s=sub: setattr(sdo[0x1A02][1], "raw", 0x2010_0000 | s << 8 | (
            32 if s == 7 else 16 if s == 6 else 8))) == ABORT_NOT_MAPPABLE
    _tpdo1s_without_tpdo3(master, 10)                        # disabled
    # remapped by the CiA 301 procedure: status, cause, position; 20 ms
    node.tpdo.read()
    tpdo3 = node.tpdo[3]
    tpdo3.clear()
    tpdo3.add_variable(0x2010, 2)
    tpdo3.add_variable(0x2010, 1)
    tpdo3.add_variable(0x6020, 1)
    tpdo3.event_timer = 20
    tpdo3.enabled = True
    tpdo3.save()
    node.tpdo.read()
    assert [(v.index, v.subindex, v.length) for v in node.tpdo[3].map] == \
        [(0x2010, 2, 8), (0x2010, 1, 8), (0x6020, 1, 32)]
    mark = master.frames.mark()
    frames = master.frames.wait_count(mark, BOOM_TPDO3, 3, "remapped TPDO3")
    assert all(len(m.data) == 6 and bytes(m.data[:2]) == b"\x00\x03" for m in frames)
    # synchronous: every 2nd SYNC, no timer
    sdo[0x1802][2].raw = 2
    _tpdo1s_without_tpdo3(master, 10)
    assert service.units["boom"].node.synchronous
    sent = []
    for _ in range(4):
        mark = master.frames.mark()
        master.network.sync.transmit()
        _quiet_for_bucket(master, 3)
        sent.append(len(master.frames.since(mark, BOOM_TPDO3)))
    assert sent == [0, 1, 0, 1]
    # reset communication: TPDO3 back to its defaults (8 bytes, 10 s, on its timer)
    mark = master.frames.mark()
    node.nmt.send_command(0x82)
    _tpdo3_with(master, mark, HEALTH_DATA, "default TPDO3 after the reset")
    assert (sdo[0x1802][2].raw, sdo[0x1802][5].raw, sdo[0x1A02][0].raw) == (254, 10000, 5)
    assert not service.units["boom"].node.synchronous
    sdo[0x1802][5].raw = 60000                              # a slow TPDO: beyond TPDO1's bound
    assert sdo[0x1802][5].raw == 60000


def test_tpdo3_parameters_are_stored_and_restored_like_the_others(cfg, unit_tables, channel,
                                                                  tmp_path) -> None:
    from ddh_vsensor.device.storage import LOAD, SAVE
    options = ServiceOptions(state_dir=tmp_path)
    with master_on(cfg, channel) as master, \
            service_thread(cfg, unit_tables, channel, options) as service:
        node = master.nodes["boom"]
        set_health(service, "boom", HEALTH)
        node.tpdo.read()
        tpdo3 = node.tpdo[3]
        tpdo3.clear()
        tpdo3.add_variable(0x2010, 1)
        tpdo3.add_variable(0x2010, 3)
        tpdo3.event_timer = 500
        tpdo3.save()
        node.sdo[0x1010][2].raw = SAVE                      # communication parameters
        for command in (0x82, 0x81):                        # the stored values come back
            node.sdo[0x1802][5].raw = 40
            mark = master.frames.mark()
            node.nmt.send_command(command)
            _tpdo3_with(master, mark, bytes([3]) + (123).to_bytes(2, "little"),
                        "the stored TPDO3 after the reset")
            assert node.sdo[0x1802][5].raw == 500
            assert service.units["boom"].node.health_timer_ms == 500.0
        node.sdo[0x1011][2].raw = LOAD                      # defaults from the next reset
        mark = master.frames.mark()
        node.nmt.send_command(0x82)
        _tpdo3_with(master, mark, HEALTH_DATA, "the default TPDO3 after the reset")
        assert node.sdo[0x1802][5].raw == 10000 and node.sdo[0x1A02][0].raw == 5


# --- the node alone (no bus): schedule, packing, encodings ---------------------------------------

@pytest.fixture
def lone(cfg):
    """boom's node sending into a list, ticked by the test."""
    from ddh_vsensor.device.network import ServiceNetwork
    from ddh_vsensor.device.node import SensorNode
    from ddh_vsensor.device.objects import Published
    sent: list = []
    node = SensorNode(ServiceNetwork(lambda m: sent.append(m) or True), cfg, "boom",
                      live=lambda: Published(1.0, 0.0, 0.5, 0, 0, 0), on_preset=lambda mm: None)
    node.boot()
    node.sent = sent
    return node


def test_tpdo3_every_whole_number_of_tpdo1_periods_in_a_tpdo1_tick(lone) -> None:
    from ddh_vsensor.device.objects import Published
    lone.event_timer_ms, lone.diag_timer_ms, lone.health_timer_ms = 10.0, 100.0, 1000.0
    lone.set_tick(5.0)                              # another node ticks every 5 ms
    lone.set_health(HEALTH)
    lone.sent.clear()
    p = Published(10.0, 1.0, 0.5, 0, 5, 0)
    for tick in range(800):
        lone.publish(p, tick)
    ids = [m.arbitration_id for m in lone.sent]
    health = [i for i, c in enumerate(ids) if c == BOOM_TPDO3]
    assert len(health) == 4 and ids.count(BOOM_TPDO1) == 400     # every 200th, every 2nd
    assert all(ids[i - 2:i] == [BOOM_TPDO1, 0x2B1] for i in health)   # TPDO1's tick, TPDO2's
    assert all(bytes(lone.sent[i].data) == HEALTH_DATA for i in health)
    lone.node.nmt.state = "STOPPED"                 # a start sends every TPDO at once
    lone.publish(p, 800)
    lone.node.nmt.state = "OPERATIONAL"
    lone.sent.clear()
    lone.publish(p, 801)
    assert [m.arbitration_id for m in lone.sent] == [BOOM_TPDO1, 0x2B1, BOOM_TPDO3]


def test_tpdo3_packs_like_canopen_whatever_is_mapped(lone) -> None:
    from .test_pdo_packing import assert_packs_like_canopen, remap
    for health in (None, HEALTH, ALARM, Health(300, True, 9, 70000, 1e9, -1.0, 1e9, 1e40,
                                                (-math.inf, math.nan))):
        lone.set_health(health)
        assert_packs_like_canopen(lone, lone.tpdo3)
    remap(lone, 3, [(0x2010, 5, 16), (0x6020, 1, 32), (0x2010, 2, 8), (0x0005, 0, 8)])
    assert_packs_like_canopen(lone, lone.tpdo3)
    remap(lone, 1, [(0x6020, 1, 32), (0x2010, 1, 8), (0x2010, 3, 16)])   # in TPDO1 too
    assert_packs_like_canopen(lone, lone.tpdo1)


def test_health_values_saturate_and_mark_the_unknown() -> None:
    from ddh_vsensor.device.objects import health_values
    values = health_values(Health(300, True, 9, 70000, 1e9, -1.0, 1e9, 1e40,
                                  (-math.inf, math.nan)))
    assert values[1:7] == (255, 0x03, 0xFFFE, 0, 0xFFFE, 0xFFFF)   # never read as unknown
    assert values[7] == math.inf and values[8] == -math.inf and math.isnan(values[9])
    assert health_values(dataclasses.replace(HEALTH, error_now_mm=math.nan))[3] == 0xFFFF
