"""Faults as a generic master sees them: EMCY (node.emcy), error register 0x1001, the
pre-defined error field 0x1003 and the CiA 406 alarms/warnings, from the status flags."""

from __future__ import annotations

import pytest

from ddh_vsensor.estimator.flags import Flags
from ddh_vsensor.service import ServiceOptions
from ddh_vsensor.device.emcy import FAULT_FLAGS
from ddh_vsensor.device.objects import ABORT_VALUE_RANGE

from .conftest import Feeder, FlaggedService, master_on, service_thread, wait_for

# stale after 0.5 s without input: a loaded machine's thread jitter never flips it
OPTIONS = ServiceOptions(stale_periods=50.0)


def _all_clear(emcy) -> bool:
    """Every flag an EMCY set has had its error reset, and the register says 0."""
    last: dict[int, int] = {}
    for e in emcy.log:
        last[e.data[0]] = e.code
    return bool(last) and all(code == 0 for code in last.values()) and \
        emcy.log[-1].register == 0


def _no_fault_left(master, emcy, tpdo1_id: int, mark: int) -> bool:
    """A TPDO1 since ``mark`` without fault flags and one after it (the faults of a tick are
    reported right after its TPDO1), and no EMCY left without its error reset. The faults may
    have cleared before the service's first tick on a loaded machine: then no EMCY came."""
    frames = master.frames.since(mark, tpdo1_id)
    clean = next((k for k, m in enumerate(frames) if not m.data[6] & FAULT_FLAGS), None)
    return clean is not None and len(frames) > clean + 1 and (not emcy.log or _all_clear(emcy))


def _codes(emcy, start: int = 0) -> list[int]:
    return [e.code for e in emcy.log[start:]]


def _last_code(emcy, flag: int) -> int | None:
    """The newest EMCY code concerning one flag (0: its error reset)."""
    codes = [e.code for e in emcy.log if e.data[0] == flag]
    return codes[-1] if codes else None


def test_cold_start_faults_then_cleared_by_inputs_and_a_preset(cfg, unit_tables, channel) -> None:
    with master_on(cfg, channel) as master, \
            service_thread(cfg, unit_tables, channel, OPTIONS):
        node = master.nodes["boom"]
        emcy = node.emcy
        cold = {0x8100, 0xFF02, 0x8130}             # no input, never referenced, no heartbeat
        wait_for(lambda: cold <= set(_codes(emcy)), "EMCY stale + not referenced + controller")
        assert {e.register for e in emcy.active} == {0x91}     # all faults, one register
        assert node.sdo[0x1001].raw == 0x91            # generic, communication, manufacturer
        assert node.sdo[0x1003][0].raw == 3
        history = {node.sdo[0x1003][i].raw for i in (1, 2, 3)}
        assert history == {0x8100 | Flags.STALE_INPUT << 16, 0xFF02 | Flags.NOT_REFERENCED << 16,
                           0x8130 | Flags.CONTROLLER_NOT_OPERATIONAL << 16}
        assert node.sdo[0x6503].raw == 0x0001          # CiA 406 alarm: position error
        assert node.sdo[0x6505].raw & 0x0020           # warning: reference point not reached
        frame = next(m for m in master.frames.since(0, 0xB1) if m.data[:2] == b"\x00\x81")
        assert frame.data[3] == Flags.STALE_INPUT             # the flag concerned

        with Feeder(cfg, channel):
            wait_for(lambda: _last_code(emcy, Flags.STALE_INPUT) == 0
                     and _last_code(emcy, Flags.CONTROLLER_NOT_OPERATIONAL) == 0,
                     "error resets: inputs and heartbeats back")
            assert emcy.log[-1].register == 0x81       # not referenced remains
            assert emcy.log[-1].data[1] == Flags.NOT_REFERENCED
            assert node.sdo[0x6503].raw == 0
            node.sdo[0x6010][1].raw = 10000            # preset: provisional until a switch
            wait_for(lambda: _last_code(emcy, Flags.NOT_REFERENCED) == 0
                     and _last_code(emcy, Flags.PRESET_UNCONFIRMED) == 0xFF20,
                     "error reset of not referenced, preset unconfirmed raised")
            assert node.sdo[0x1001].raw == 0x81
            assert node.sdo[0x6505].raw & 0x0020       # still no reference point reached
        node.sdo[0x1003][0].raw = 0                    # a master clears the history
        assert node.sdo[0x1003][0].raw == 0
        with pytest.raises(Exception) as exc:
            node.sdo[0x1003][0].raw = 3
        assert getattr(exc.value, "code", None) == ABORT_VALUE_RANGE


@pytest.mark.parametrize("flag, code, register", [
    (Flags.TABLE_CLAMPED, 0xFF10, 0x81), (Flags.PRESET_UNCONFIRMED, 0xFF20, 0x81), (Flags.CONTROLLER_NOT_OPERATIONAL, 0x8130, 0x11)])
def test_each_fault_flag_has_its_emcy_and_error_reset(cfg, unit_tables, channel, flag, code,
                                                      register) -> None:
    with master_on(cfg, channel) as master, \
            service_thread(cfg, unit_tables, channel, OPTIONS, FlaggedService) as service:
        node = master.nodes["bucket"]
        service.extra_flags = {}
        service.masked_flags = 0 if flag == Flags.PRESET_UNCONFIRMED else Flags.PRESET_UNCONFIRMED
        with Feeder(cfg, channel):
            node.sdo[0x6010][1].raw = 10000
            if flag == Flags.PRESET_UNCONFIRMED:
                service.masked_flags = Flags.PRESET_UNCONFIRMED     # the preset's own, until injected
            mark = master.frames.mark()
            wait_for(lambda: _no_fault_left(master, node.emcy, 0x1B2, mark),
                     "no fault left (error resets seen)")
            start, mark = len(node.emcy.log), master.frames.mark()
            service.extra_flags = {"bucket": flag}
            got = wait_for(lambda: node.emcy.wait(code, 0.1), f"EMCY {code:04X}")
            assert got.register == register and got.data[0] == flag and got.data[1] == flag
            assert node.sdo[0x1001].raw == register
            assert node.sdo[0x1003][1].raw == code | flag << 16       # newest first
            service.extra_flags = {}
            wait_for(lambda: 0x0000 in _codes(node.emcy, start), "error reset")
            assert node.emcy.log[-1].register == 0 and node.sdo[0x1001].raw == 0
            assert _codes(node.emcy, start) == [code, 0x0000]
            assert all(m.data[3] != flag for m in master.frames.since(mark, 0xB1))  # boom


def test_emcy_can_be_disabled_and_is_not_sent_while_stopped(cfg, unit_tables, channel) -> None:
    with master_on(cfg, channel) as master, \
            service_thread(cfg, unit_tables, channel, OPTIONS, FlaggedService) as service:
        node = master.nodes["boom"]
        service.extra_flags = {}
        wait_for(lambda: 0xFF02 in _codes(node.emcy), "not referenced at start")
        node.sdo[0x1014].raw = 0x8000_0000 | 0xB1         # EMCY invalid
        with pytest.raises(Exception) as exc:
            node.sdo[0x1014].raw = 0xC1                    # another COB-ID: refused
        assert getattr(exc.value, "code", None) == ABORT_VALUE_RANGE
        start = len(node.emcy.log)
        service.extra_flags = {"boom": Flags.TABLE_CLAMPED}
        mark = master.frames.mark()
        master.frames.wait_count(mark, 0x1B1, 20, "TPDO1 with the flag set")
        assert node.sdo[0x1001].raw & 0x80                 # the register shows it
        assert len(node.emcy.log) == start                 # no EMCY: producer disabled
        node.sdo[0x1014].raw = 0xB1                        # valid again: reported
        wait_for(lambda: 0xFF10 in _codes(node.emcy, start), "EMCY after enabling")

        node.nmt.state = "STOPPED"
        wait_for(lambda: node.nmt.state == "STOPPED", "heartbeat STOPPED")
        start = len(node.emcy.log)
        service.extra_flags = {}
        mark = master.frames.mark()
        wait_for(lambda: len([m for m in master.frames.since(mark, 0x1B2)]) >= 20,
                 "ticks while stopped (the other node's TPDO1)")
        assert len(node.emcy.log) == start                 # nothing in STOPPED
        node.nmt.state = "PRE-OPERATIONAL"
        wait_for(lambda: 0x0000 in _codes(node.emcy, start), "error reset after STOPPED")
