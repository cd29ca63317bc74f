"""SDO as a master uses it: segmented downloads bounded by the object's size (an endless
one is aborted, never buffered) and the CiA 406 objects a master expects."""

from __future__ import annotations

import struct

import canopen
import pytest

from ddh_vsensor.device.objects import (ABORT_COMMAND, ABORT_LENGTH_TOO_HIGH,
                                         ABORT_MAX_BELOW_MIN, ABORT_READ_ONLY,
                                         ABORT_VALUE_RANGE, ABORT_VALUE_TOO_LOW)

from .conftest import wait_for


def _responses(master, mark: int) -> list[bytes]:
    return [bytes(m.data) for m in master.frames.since(mark, 0x5B1)]


def _abort_code(response: bytes) -> int | None:
    return struct.unpack_from("<I", response, 4)[0] if response[0] == 0x80 else None


def test_segmented_downloads_are_bounded_by_the_object_size(cfg, bus) -> None:
    service, master = bus
    node = master.nodes["boom"]
    # the canopen client's own segmented transfer: too long for a 2-byte object
    with pytest.raises(canopen.SdoAbortedError) as exc:
        node.sdo.download(0x1017, 0, bytes(100), force_segment=True)
    assert exc.value.code == ABORT_LENGTH_TOO_HIGH
    # one that fits is taken: a 4-byte object written in a segment
    node.sdo.download(0x6401, 1, struct.pack("<i", -5), force_segment=True)
    assert node.sdo[0x6401][1].raw == -5
    # an "endless" download without a size: the first segment beyond 2 bytes is aborted,
    # every further segment is refused, nothing is buffered
    send = master.network.send_message
    mark = master.frames.mark()
    send(0x631, bytes([0x20, 0x17, 0x10, 0x00, 0, 0, 0, 0]))     # initiate, size not given
    wait_for(lambda: _responses(master, mark), "initiate response")
    assert _responses(master, mark)[0][0] == 0x60
    # one request per response, as a client does (a flood of requests is rate-limited)
    for k in range(50):
        send(0x631, bytes([0x10 * (k % 2)]) + bytes(7))           # 7 bytes per segment
        wait_for(lambda n=k + 2: len(_responses(master, mark)) >= n, f"segment {k} answered")
    responses = _responses(master, mark)
    assert len(responses) == 51
    codes = [_abort_code(r) for r in responses[1:]]
    assert codes[0] == ABORT_LENGTH_TOO_HIGH
    assert set(codes[1:]) == {ABORT_COMMAND}                      # no transfer in progress
    sdo_server = service.units["boom"].node.node.sdo
    assert sdo_server._buffer is None                             # noqa: SLF001
    # a size given up front beyond the object: aborted at once
    mark = master.frames.mark()
    send(0x631, bytes([0x21, 0x17, 0x10, 0x00]) + struct.pack("<I", 1_400_000))
    response = wait_for(lambda: _responses(master, mark), "abort")[0]
    assert _abort_code(response) == ABORT_LENGTH_TOO_HIGH
    mark = master.frames.mark()
    send(0x631, bytes([0x20, 0x20, 0x60, 0x01, 0, 0, 0, 0]))     # read-only position
    assert _abort_code(wait_for(lambda: _responses(master, mark), "abort")[0]) == \
        ABORT_READ_ONLY
    assert node.sdo[0x1017].raw == 1000                           # unchanged throughout


def test_cia406_objects(cfg, bus) -> None:
    service, master = bus
    node = master.nodes["boom"]
    step = cfg.can.position_step_mm
    stroke_steps = round(cfg.unit("boom").stroke_mm / step)
    assert node.sdo[0x1000].raw == 0x00080196                     # CiA 406, linear encoder
    assert node.sdo[0x6000].raw == 0                              # operating parameters
    node.sdo[0x6000].raw = 0
    with pytest.raises(canopen.SdoAbortedError) as exc:
        node.sdo[0x6000].raw = 0x0004                              # scaling: fixed
    assert exc.value.code == ABORT_VALUE_RANGE
    assert node.sdo[0x6500].raw == 0                              # operating status
    assert node.sdo[0x6005][1].raw == node.sdo[0x6501].raw == round(step * 1e6)   # nm
    assert node.sdo[0x6005][2].raw == 100                         # um/s: 0x6030 in 0.1 mm/s
    assert [node.sdo[0x650A][i].raw for i in (1, 2, 3)] == [0, 0, stroke_steps]
    assert node.sdo[0x6504].raw == 0x0001 and node.sdo[0x6506].raw == 0x3020

    node.sdo[0x6010][1].raw = round(200.0 / step)                 # preset: 200 mm
    assert node.sdo[0x6400][1].raw == 0                           # inside, no work area
    node.sdo[0x6401][1].raw = round(250.0 / step)                 # low limit above it
    assert node.sdo[0x6400][1].raw == 0x04                        # range underflow
    node.sdo[0x6401][1].raw = 0
    node.sdo[0x6402][1].raw = round(150.0 / step)                 # high limit below it
    assert node.sdo[0x6400][1].raw == 0x02                        # range overflow
    with pytest.raises(canopen.SdoAbortedError) as exc:
        node.sdo[0x6401][1].raw = round(160.0 / step)              # low above high
    assert exc.value.code == ABORT_MAX_BELOW_MIN
    with pytest.raises(canopen.SdoAbortedError) as exc:
        node.sdo[0x6400][1].raw = 0                                # read only
    assert exc.value.code == ABORT_READ_ONLY


def test_the_cia406_cyclic_timer_is_tpdo1s_event_timer(cfg, bus) -> None:
    """A master written for encoders sets the cycle through 0x6200: TPDO1 then goes out at
    that period (counted against the other node's TPDO1 at 10 ms), and 0x1800 sub 5 says so;
    either object written, both read the same; outside the bounds, refused."""
    service, master = bus
    sdo = master.nodes["boom"].sdo
    assert sdo[0x6200].raw == sdo[0x1800][5].raw == cfg.can.event_timer_ms
    sdo[0x6200].raw = 40
    assert sdo[0x1800][5].raw == 40
    mark = master.frames.mark()
    master.frames.wait_count(mark, 0x1B2, 41, "the bucket's TPDO1 at 10 ms")
    assert 9 <= len(master.frames.since(mark, 0x1B1)) <= 11          # 400 ms at 40 ms
    sdo[0x1800][5].raw = 20
    assert sdo[0x6200].raw == 20
    with pytest.raises(canopen.SdoAbortedError) as exc:
        sdo[0x6200].raw = 0
    assert exc.value.code == ABORT_VALUE_TOO_LOW
    assert sdo[0x6200].raw == 20
