"""The emulated CiA 406 sensor's EDS: loadable by canopen, its PDOs pack like the DBC frames."""

from __future__ import annotations

from pathlib import Path

import canopen
import pytest

from ddh_vsensor.canbus import FrameCodec, message_name
from ddh_vsensor.config import Config

EDS = Path(__file__).resolve().parents[2] / "ddh_vsensor" / "data" / "cia406_position_sensor.eds"


@pytest.fixture(params=["boom", "bucket"])
def sensor(request: pytest.FixtureRequest, cfg: Config) -> tuple[str, canopen.LocalNode]:
    actuator = request.param
    network = canopen.Network()       # never connected: PDO maps only need somewhere to subscribe
    node = network.create_node(cfg.can.units[actuator].sensor_node_id, str(EDS))
    node.tpdo.read(from_od=True)
    return actuator, node


def test_eds_describes_a_cia406_linear_encoder() -> None:
    od = canopen.import_od(str(EDS), 49)
    assert od[0x1000].default == 0x00080196          # profile 406, absolute linear encoder
    assert od[0x6005][1].default == 10000            # nm: 0.01 mm, the DBC's position step
    assert od[0x6010][1].access_type == "rw"         # preset: the manual reference
    assert od[0x1800][1].default == 0x4000_0000 | (0x180 + 49)     # bit 30: no RTR
    assert od[0x1014].default == 0x80 + 49                          # EMCY
    assert od[0x6005][2].default == 100                             # um/s: 0.1 mm/s
    assert od[0x2001].data_type == canopen.objectdictionary.UNSIGNED24


def test_eds_lists_every_object_it_defines() -> None:
    """The [..Objects] sections name exactly the objects defined (what tools read first)."""
    import configparser
    eds = configparser.ConfigParser()
    eds.optionxform = str
    eds.read(EDS)
    listed = {int(v, 16) for section in ("MandatoryObjects", "OptionalObjects",
                                         "ManufacturerObjects")
              for k, v in eds[section].items() if k != "SupportedObjects"}
    for section in ("MandatoryObjects", "OptionalObjects", "ManufacturerObjects"):
        assert int(eds[section]["SupportedObjects"]) == len(eds[section]) - 1
    defined = {int(s, 16) for s in eds.sections() if len(s) == 4 and s.isalnum()
               and all(c in "0123456789ABCDEFabcdef" for c in s)}
    assert listed == defined


def test_tpdo1_packs_like_the_position_frame(sensor: tuple[str, canopen.LocalNode],
                                              cfg: Config) -> None:
    actuator, node = sensor
    codec = FrameCodec(cfg)
    tpdo = node.tpdo[1]
    assert tpdo.enabled and tpdo.trans_type == 254
    assert tpdo.cob_id == codec.ids[message_name("position", actuator)]
    assert tpdo.event_timer == cfg.can.event_timer_ms
    tpdo[0x6020].raw = -123456          # mapped sub 1 of the CiA 406 arrays
    tpdo[0x6030].raw = -789
    tpdo[0x2000].raw = 0x12
    expected = codec.encode_position(actuator, -1234.56, -78.9, 0x12)
    assert bytes(tpdo.data) == bytes(expected.data)


def test_tpdo2_packs_like_the_diag_frame(sensor: tuple[str, canopen.LocalNode],
                                         cfg: Config) -> None:
    actuator, node = sensor
    codec = FrameCodec(cfg)
    tpdo = node.tpdo[2]
    assert tpdo.cob_id == codec.ids[message_name("diag", actuator)]
    for index, value in ((0x2001, 250), (0x2002, 0x05), (0x2003, 60000), (0x2004, 7)):
        tpdo[index].raw = value
    expected = codec.encode_diag(actuator, 2.5, 0x05, 60000, 7)
    assert bytes(tpdo.data) == bytes(expected.data)
