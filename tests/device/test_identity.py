"""The emulated sensor as a generic master or PLC configurator reads it: identity 0x1018 and
device name 0x1008 from the configuration (each node its own serial number), TPDOs of types
IEC 61131-3 tools map (no 24-bit object), and an SDO server that answers a malformed sequence
with an abort, never with a traceback."""

from __future__ import annotations

import dataclasses
import logging
import random
import struct
from pathlib import Path

import canopen
import pytest
import yaml

from ddh_vsensor.config import Config, ConfigError
from ddh_vsensor.config.validate import parse_config
from ddh_vsensor.device.objects import ABORT_COMMAND, ABORT_READ_ONLY

from .conftest import master_on, service_thread, wait_for

SDO_RX, SDO_TX = 0x631, 0x5B1            # boom's sensor, node 49
LOADER = Path(__file__).resolve().parents[2] / "config" / "loader.yaml"


def _with_identity(cfg: Config, **can: object) -> Config:
    return dataclasses.replace(cfg, can=dataclasses.replace(cfg.can, **can))


def test_master_reads_the_configured_identity_and_name(cfg, unit_tables, channel) -> None:
    machine = _with_identity(cfg, vendor_id=0x0000_0ABC, product_code=0x0406_0002,
                             revision_number=0x0002_0001, serial_number_base=41000,
                             device_name="loader ddh")
    with master_on(machine, channel) as master, \
            service_thread(machine, unit_tables, channel):
        serials = {}
        for unit, node in master.nodes.items():
            assert node.sdo[0x1008].raw == f"loader ddh {unit}"      # a segmented upload
            identity = [node.sdo[0x1018][sub].raw for sub in (1, 2, 3, 4)]
            assert identity[:3] == [0x0ABC, 0x0406_0002, 0x0002_0001]
            serials[unit] = identity[3]
            assert node.sdo[0x1018][0].raw == 4
    assert serials == {"boom": 41000, "bucket": 41001}                 # unique per node


def test_default_identity_is_unassigned_vendor_and_distinct_serials(bus) -> None:
    service, master = bus
    read = {unit: [node.sdo[0x1018][sub].raw for sub in (1, 2, 3, 4)]
            for unit, node in master.nodes.items()}
    assert read == {"boom": [0, 0x406, 0x0001_0000, 1], "bucket": [0, 0x406, 0x0001_0000, 2]}
    assert master.nodes["bucket"].sdo[0x1008].raw == "ddh-vsensor bucket"


def _loader_data() -> dict:
    return yaml.safe_load(LOADER.read_text())


def test_duplicate_serial_numbers_are_a_config_error() -> None:
    data = _loader_data()
    data["can"]["serial_number_base"] = 7
    data["can"]["units"]["bucket"]["serial_number"] = 7           # boom's: base + 0
    with pytest.raises(ConfigError, match=r"can\.units\.bucket\.serial_number.*serial number 7"):
        parse_config(data, "dup.yaml")
    data["can"]["units"]["bucket"]["serial_number"] = 9
    assert parse_config(data, "own.yaml").can.serial_number("bucket") == 9
    data["can"]["serial_number_base"] = 0xFFFF_FFFF                 # bucket would be 2^32
    del data["can"]["units"]["bucket"]["serial_number"]
    with pytest.raises(ConfigError, match="exceeds UNSIGNED32"):
        parse_config(data, "wrap.yaml")


def test_tpdos_map_no_24_bit_object(bus) -> None:
    """What a PLC configurator reads over SDO: every mapped entry and every mappable object
    is 8, 16, 32 or 64 bits, and TPDO2 still carries uncertainty, flags and both counters."""
    service, master = bus
    node = master.nodes["boom"]
    node.tpdo.read()
    for pdo in (node.tpdo[1], node.tpdo[2]):
        assert all(var.length in (8, 16, 32, 64) for var in pdo.map), pdo.name
    assert [(v.index, v.length) for v in node.tpdo[2].map] == \
        [(0x2001, 32), (0x2002, 8), (0x2004, 8), (0x2003, 16)]
    od = node.object_dictionary
    mappable = [var for obj in od.values()
                for var in ([obj] if isinstance(obj, canopen.objectdictionary.ODVariable)
                            else obj.values()) if var.pdo_mappable]
    assert mappable and all(len(var) in (8, 16, 32, 64) for var in mappable)
    assert node.tpdo[2].wait_for_reception(10.0) is not None
    assert len(node.tpdo[2].data) == 8


def _responses(master, mark: int) -> list[bytes]:
    return [bytes(m.data) for m in master.frames.since(mark, SDO_TX)]


def _exchange(master, request: bytes) -> bytes:
    """One request, its response (every request here is answered)."""
    mark = master.frames.mark()
    master.network.send_message(SDO_RX, request)
    return wait_for(lambda: _responses(master, mark), f"answer to {request.hex()}")[0]


def _abort_code(response: bytes) -> int | None:
    return struct.unpack_from("<I", response, 4)[0] if response[0] == 0x80 else None


def _tracebacks(caplog) -> list[logging.LogRecord]:
    return [r for r in caplog.records if r.exc_info or "Traceback" in r.getMessage()]


def test_upload_segment_without_an_upload_is_aborted(bus, caplog) -> None:
    caplog.set_level(logging.DEBUG)
    service, master = bus
    # before any transfer: an upload segment request and an unknown command specifier
    assert _abort_code(_exchange(master, bytes([0x60]) + bytes(7))) == ABORT_COMMAND
    assert _abort_code(_exchange(master, bytes([0xE0]) + bytes(7))) == ABORT_COMMAND
    # after an expedited upload: nothing to segment
    assert _exchange(master, bytes([0x40, 0x18, 0x10, 0x02, 0, 0, 0, 0]))[0] == 0x43
    assert _abort_code(_exchange(master, bytes([0x60]) + bytes(7))) == ABORT_COMMAND
    # after a segmented download: its data is never sent back as an upload
    work_area = bytes([0x21, 0x01, 0x64, 0x01]) + struct.pack("<I", 4)
    assert _exchange(master, work_area)[0] == 0x60
    assert _exchange(master, bytes([0x00 | 0x06 | 0x01]) + b"\x07\x00\x00\x00" + bytes(3))[0] \
        == 0x20                                     # 4 bytes, last segment
    response = _exchange(master, bytes([0x60]) + bytes(7))
    assert _abort_code(response) == ABORT_COMMAND
    # a whole segmented upload still works, and a segment request after its last is refused
    name = b"ddh-vsensor boom"
    first = _exchange(master, bytes([0x40, 0x08, 0x10, 0x00, 0, 0, 0, 0]))
    assert first[0] == 0x41 and struct.unpack_from("<I", first, 4)[0] == len(name)
    received, toggle = b"", 0
    while True:
        segment = _exchange(master, bytes([0x60 | toggle]) + bytes(7))
        assert segment[0] & 0xE0 == 0x00 and segment[0] & 0x10 == toggle
        received += segment[1:8 - ((segment[0] >> 1) & 0x07)]
        toggle ^= 0x10
        if segment[0] & 0x01:
            break
    assert received == name
    assert _abort_code(_exchange(master, bytes([0x60 | toggle]) + bytes(7))) == ABORT_COMMAND
    assert master.nodes["boom"].sdo[0x1018][4].raw == 1             # the server still serves
    assert not _tracebacks(caplog)


def test_random_sdo_requests_get_answers_not_tracebacks(bus, caplog) -> None:
    """Random command bytes on the objects a master reads and one it may write: every
    request but a client's abort is answered, nothing raises inside the server, and upload
    segments come only within a segmented upload (CiA 301's sequence, as the client sees it)."""
    caplog.set_level(logging.DEBUG)
    service, master = bus
    rng = random.Random(406)
    objects = [(0x1008, 0), (0x1018, 4), (0x6020, 1), (0x1000, 0), (0x6401, 1), (0x2001, 0)]
    answered = segments = 0
    uploading = False                   # a segmented upload is open, as the client sees it
    for _ in range(600):
        command = rng.randrange(256)
        if command & 0xE0 == 0x80:                  # a client's abort: not answered
            continue
        index, sub = rng.choice(objects)
        request = struct.pack("<BHB", command, index, sub) + rng.randbytes(4)
        response = _exchange(master, request)
        assert response[0] != 0x80 or _abort_code(response) != 0x0800_0000   # not "general"
        answered += 1
        if command & 0xE0 == 0x60 and response[0] & 0xE0 == 0x00:      # an upload segment
            assert uploading, f"upload segment {response.hex()} outside an upload"
            segments += 1
            uploading = not response[0] & 0x01
        else:
            uploading = response[0] == 0x41          # initiate upload answer, segmented
    assert answered > 400 and segments > 0
    assert master.nodes["boom"].sdo[0x1008].raw == "ddh-vsensor boom"
    assert not _tracebacks(caplog)


def test_writing_the_identity_is_refused(bus) -> None:
    service, master = bus
    with pytest.raises(canopen.SdoAbortedError) as exc:
        master.nodes["boom"].sdo.download(0x1018, 4, struct.pack("<I", 99))
    assert exc.value.code == ABORT_READ_ONLY
