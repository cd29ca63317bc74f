"""Store 0x1010 and restore 0x1011 parameters as a master uses them (CiA 301): the stored
communication parameters come back at the next start and at every NMT reset, a restore makes
the defaults come back from the next reset or start, a wrong signature is refused."""

from __future__ import annotations

import json
import logging
import struct
from pathlib import Path

import canopen
import pytest

from ddh_vsensor.device.objects import ABORT_NOT_STORED
from ddh_vsensor.device.storage import LOAD, SAVE
from ddh_vsensor.service import ServiceOptions

from .conftest import master_on, service_thread, wait_for

BOOT_UP = 0x731                     # boom's sensor, node 49
INT32_MIN = -(2 ** 31)


def _reset(master, command: int) -> None:
    """NMT reset (0x81 node, 0x82 communication) of boom's sensor; back once it booted."""
    mark = master.frames.mark()
    master.nodes["boom"].nmt.send_command(command)
    wait_for(lambda: any(bytes(m.data) == b"\x00" for m in master.frames.since(mark, BOOT_UP)),
             "boot-up after the reset")


def _aborts(write) -> int:
    with pytest.raises(canopen.SdoAbortedError) as exc:
        write()
    return exc.value.code


def test_communication_parameters_survive_a_restart_until_restored(cfg, unit_tables, channel,
                                                                   tmp_path: Path) -> None:
    options = ServiceOptions(state_dir=tmp_path)
    stored = tmp_path / "boom.parameters.json"
    consumer = cfg.faults.heartbeat_node_ids["boom"] << 16
    with master_on(cfg, channel) as master, \
            service_thread(cfg, unit_tables, channel, options) as service:
        sdo = master.nodes["boom"].sdo
        assert [sdo[0x1010][s].raw for s in (1, 2)] == [1, 1]     # stores on command
        assert [sdo[0x1011][s].raw for s in (1, 2)] == [1, 1]
        remote = master.nodes["boom"]
        remote.tpdo.read()
        remote.tpdo[2].clear()                      # TPDO2 remapped: uncertainty, frames in
        remote.tpdo[2].add_variable(0x2001)
        remote.tpdo[2].add_variable(0x2003)
        remote.tpdo[2].save()
        sdo[0x1017].raw = 500                       # heartbeat producer
        sdo[0x1801][5].raw = 200                    # TPDO2 event timer
        sdo[0x1800][2].raw = 1                      # TPDO1 on every SYNC
        sdo[0x100C].raw = 250                       # guard time
        sdo[0x1016][1].raw = consumer | 400         # controller heartbeat consumer, ms
        sdo[0x6401][1].raw = -100                   # work area: an application parameter
        for wrong in (0x1234_5678, LOAD):
            assert _aborts(lambda w=wrong: setattr(sdo[0x1010][2], "raw", w)) == \
                ABORT_NOT_STORED
        assert _aborts(lambda: setattr(sdo[0x1011][2], "raw", SAVE)) == ABORT_NOT_STORED
        assert not stored.exists()
        sdo[0x1010][2].raw = SAVE
        values = json.loads(stored.read_text())
        assert values["node_id"] == 49
        assert {k: values["parameters"][k] for k in ("0x1017.0", "0x1801.5", "0x1800.2",
                                                      "0x100C.0", "0x1016.1")} == \
            {"0x1017.0": 500, "0x1801.5": 200, "0x1800.2": 1, "0x100C.0": 250,
             "0x1016.1": consumer | 400}
        assert not any(k.startswith(("0x6", "0x1010", "0x1011", "0x1003"))
                       for k in values["parameters"])
        sdo[0x1017].raw = 700                       # changed after the store: not kept
        assert not (tmp_path / "bucket.parameters.json").exists()

    with master_on(cfg, channel) as master, \
            service_thread(cfg, unit_tables, channel, options) as service:
        sdo, node = master.nodes["boom"].sdo, service.units["boom"].node
        assert (sdo[0x1017].raw, sdo[0x1801][5].raw, sdo[0x1800][2].raw, sdo[0x100C].raw,
                sdo[0x1016][1].raw) == (500, 200, 1, 250, consumer | 400)
        assert sdo[0x6401][1].raw == INT32_MIN       # sub 2 stores no application parameter
        assert node.tpdo1.trans_type == 1 and node.heartbeat_period_s == 0.5   # in effect
        assert node.diag_timer_ms == 200.0
        assert service.units["boom"].heartbeat.consumer_time_s == pytest.approx(0.4)
        assert master.nodes["bucket"].sdo[0x1017].raw == 1000     # the other node's own
        remote = master.nodes["boom"]
        remote.tpdo.read()
        assert [(v.index, v.length) for v in remote.tpdo[2].map] == [(0x2001, 32), (0x2003, 16)]
        mark = master.frames.mark()
        assert len(master.frames.wait_count(mark, 0x2B1, 1, "remapped TPDO2")[0].data) == 6
        # an NMT reset returns to the stored values, not the EDS defaults
        sdo[0x1017].raw = 900
        sdo[0x1801][5].raw = 50
        _reset(master, 0x82)
        assert (sdo[0x1017].raw, sdo[0x1801][5].raw) == (500, 200)
        # restore: nothing changes now, the defaults come back at the next reset
        sdo[0x1011][2].raw = LOAD
        assert not stored.exists()
        assert sdo[0x1017].raw == 500
        _reset(master, 0x82)
        assert (sdo[0x1017].raw, sdo[0x1801][5].raw, sdo[0x1800][2].raw, sdo[0x100C].raw) == \
            (1000, 100, 254, 0)
        assert [v.index for v in node.tpdo2.map] == [0x2001, 0x2002, 0x2004, 0x2003]
        assert sdo[0x1016][1].raw == consumer | round(cfg.faults.heartbeat_timeout_s * 1000)
        assert service.units["boom"].heartbeat.consumer_time_s == \
            pytest.approx(cfg.faults.heartbeat_timeout_s)

    with master_on(cfg, channel) as master, \
            service_thread(cfg, unit_tables, channel, options):
        assert master.nodes["boom"].sdo[0x1017].raw == 1000


def test_all_parameters_include_the_work_area(cfg, unit_tables, channel,
                                              tmp_path: Path) -> None:
    options = ServiceOptions(state_dir=tmp_path)
    with master_on(cfg, channel) as master, \
            service_thread(cfg, unit_tables, channel, options):
        sdo = master.nodes["boom"].sdo
        sdo[0x6401][1].raw, sdo[0x6402][1].raw = -100, 5000
        sdo[0x1015].raw = 200
        sdo[0x1010][1].raw = SAVE
        sdo[0x6401][1].raw = 0
        _reset(master, 0x81)                         # reset node: all parameters
        assert (sdo[0x6401][1].raw, sdo[0x6402][1].raw, sdo[0x1015].raw) == (-100, 5000, 200)
        # restoring the communication parameters keeps the application ones stored
        sdo[0x1011][2].raw = LOAD
        _reset(master, 0x81)
        assert (sdo[0x6401][1].raw, sdo[0x6402][1].raw, sdo[0x1015].raw) == (-100, 5000, 100)
        sdo[0x1011][1].raw = LOAD
        assert not (tmp_path / "boom.parameters.json").exists()
        _reset(master, 0x81)
        assert (sdo[0x6401][1].raw, sdo[0x6402][1].raw) == (INT32_MIN, 2 ** 31 - 1)


def test_a_stored_set_the_node_refuses_is_ignored(cfg, unit_tables, channel, tmp_path: Path,
                                                  caplog) -> None:
    """Stored values pass the checks a master's writes pass (here an event timer the
    configuration no longer allows): one refused, all ignored, the defaults apply."""
    (tmp_path / "boom.parameters.json").write_text(json.dumps({
        "format": "ddh-vsensor stored parameters 1", "node_id": 49,
        "parameters": {"0x1017.0": 300, "0x1800.5": 0}}))
    (tmp_path / "bucket.parameters.json").write_text(json.dumps({
        "format": "ddh-vsensor stored parameters 1", "node_id": 49,   # not bucket's node
        "parameters": {"0x1017.0": 300}}))
    caplog.set_level(logging.WARNING)
    with master_on(cfg, channel) as master, \
            service_thread(cfg, unit_tables, channel, ServiceOptions(state_dir=tmp_path)):
        assert [master.nodes[u].sdo[0x1017].raw for u in ("boom", "bucket")] == [1000, 1000]
        assert master.nodes["boom"].sdo[0x1800][5].raw == round(cfg.can.event_timer_ms)
    text = caplog.text
    assert "boom: stored parameters" in text and "ignored (abort 0x06090032)" in text
    assert "stored for node 49, this is node 50" in text


def test_without_a_state_directory_nothing_is_stored(bus) -> None:
    service, master = bus
    sdo = master.nodes["boom"].sdo
    assert [sdo[0x1010][s].raw for s in (1, 2)] == [0, 0]
    assert _aborts(lambda: sdo.download(0x1010, 2, struct.pack("<I", SAVE))) == \
        ABORT_NOT_STORED
    assert _aborts(lambda: sdo.download(0x1011, 1, struct.pack("<I", LOAD))) == \
        ABORT_NOT_STORED
