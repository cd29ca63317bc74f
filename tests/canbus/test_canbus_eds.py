"""The emulated CiA 406 sensor's EDS, the template and each unit's generated one: loadable by
canopen, the configured values in it, its PDOs packing like the frames."""

from __future__ import annotations

import configparser
import dataclasses
from pathlib import Path

import canopen
import pytest

from ddh_vsensor.canbus import FrameCodec, message_name, unit_object_dictionary
from ddh_vsensor.canbus.eds import TEMPLATE_EDS, write_unit_eds
from ddh_vsensor.config import Config, UnknownUnitError

EDS = TEMPLATE_EDS


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
    assert od[0x2001].data_type == canopen.objectdictionary.UNSIGNED32
    assert od[0x1008].default == "ddh-vsensor"                      # the device name
    assert [od[0x1010][s].default for s in (1, 2)] == [1, 1]        # stores on command
    # no 24-bit object anywhere: IEC 61131-3 tools map 8, 16, 32, 64 bits
    variables = [v for obj in od.values() for v in
                 ([obj] if isinstance(obj, canopen.objectdictionary.ODVariable)
                  else obj.values())]
    assert not [v.name for v in variables if len(v) == 24 or v.data_type in
                (canopen.objectdictionary.UNSIGNED24, canopen.objectdictionary.INTEGER24)]
    assert "[DeviceComissioning]" not in EDS.read_text()


def test_eds_lists_every_object_it_defines() -> None:
    """The [..Objects] sections name exactly the objects defined (what tools read first)."""
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


def test_tpdo3_packs_like_the_health_frame(sensor: tuple[str, canopen.LocalNode],
                                           cfg: Config) -> None:
    actuator, node = sensor
    codec = FrameCodec(cfg)
    tpdo = node.tpdo[3]
    assert tpdo.enabled and tpdo.trans_type == 254 and tpdo.event_timer == 10000
    assert tpdo.cob_id == codec.ids[message_name("health", actuator)]
    assert [(v.index, v.subindex) for v in tpdo.map] == [(0x2010, sub) for sub in range(1, 6)]
    for var, value in zip(tpdo.map, (4, 0x01, 123, 456, 0xFFFF)):
        var.raw = value
    expected = codec.messages[message_name("health", actuator)].encode(
        {"CauseCode": 4, "HealthAlarm": 1, "HealthFewDays": 0, "HealthNotYet": 0,
         "HealthReserved": 0, "ErrorNow": 1.23, "ErrorAtHorizon": 4.56,
         "DaysToTolerance": 6553.5})
    assert bytes(tpdo.data) == expected


# --- the EDS generated per unit ------------------------------------------------------------

CONFIGURED = {(0x6005, 1), (0x6501, 0), (0x650A, 3), (0x1800, 5), (0x1014, 0), (0x1008, 0),
              (0x1016, 1), (0x1018, 1), (0x1018, 2), (0x1018, 3), (0x1018, 4)}


def _generated(cfg: Config, unit: str, tmp_path: Path) -> Path:
    path = tmp_path / f"{unit}.eds"
    with open(path, "w", encoding="utf-8") as fh:
        write_unit_eds(cfg, unit, fh, path.name)
    return path


def _defaults(od: canopen.ObjectDictionary) -> dict[tuple[int, int], object]:
    out = {}
    for index in od:
        obj = od[index]
        if isinstance(obj, canopen.objectdictionary.ODVariable):
            out[(obj.index, 0)] = (obj.default, obj.data_type, obj.access_type, obj.pdo_mappable)
        else:
            for sub in obj.values():
                out[(sub.index, sub.subindex)] = (sub.default, sub.data_type, sub.access_type,
                                                  sub.pdo_mappable)
    return out


@pytest.mark.parametrize("machine", ["cfg", "three_units"])
def test_generated_eds_loads_with_the_configured_values(machine: str, tmp_path: Path,
                                                        request: pytest.FixtureRequest) -> None:
    cfg: Config = request.getfixturevalue(machine)
    for unit in cfg.unit_names:
        node_id = cfg.can.units[unit].sensor_node_id
        path = _generated(cfg, unit, tmp_path)
        # an EDS leaves the node ID to the master (CiA 306: [DeviceComissioning] is a DCF's)
        assert "[DeviceComissioning]" not in path.read_text()
        assert canopen.import_od(str(path)).node_id is None
        od = canopen.import_od(str(path), node_id)         # the master's node ID
        assert od[0x1800][1].default == 0x4000_0000 | (0x180 + node_id)
        assert od[0x1801][1].default == 0x4000_0000 | (0x280 + node_id)
        assert od[0x1014].default == 0x80 + node_id
        step_nm = round(cfg.can.position_step_mm * 1e6)
        assert od[0x6005][1].default == od[0x6501].default == step_nm
        assert od[0x650A][3].default == round(cfg.unit(unit).stroke_mm
                                              / cfg.can.position_step_mm)
        assert od[0x1800][5].default == cfg.can.event_timer_ms
        assert "\nGranularity=8\n" in path.read_text()     # canopen reads it as a flag
        # everything the configuration does not set is the template's, for this node
        template = _defaults(canopen.import_od(str(EDS), node_id))
        generated = _defaults(od)
        assert generated.keys() == template.keys()
        assert {k: v for k, v in generated.items() if k not in CONFIGURED} == \
            {k: v for k, v in template.items() if k not in CONFIGURED}
        assert f"Unit {unit}: sensor node {node_id}" in od.comments


def test_generated_eds_follows_step_timer_emcy_and_nmt(cfg: Config, tmp_path: Path) -> None:
    other = dataclasses.replace(cfg, can=dataclasses.replace(
        cfg.can, position_step_mm=0.1, event_timer_ms=25.0, emcy_enabled=False,
        nmt_auto_start=False))
    path = _generated(other, "bucket", tmp_path)
    od = canopen.import_od(str(path), 50)
    assert od[0x6005][1].default == 100_000
    assert od[0x650A][3].default == round(cfg.unit("bucket").stroke_mm / 0.1)
    assert od[0x1800][5].default == 25
    assert od[0x1014].default == (1 << 31) | (0x80 + 50)           # not valid at boot
    assert "$NODEID" in path.read_text()                           # COB-IDs stay relative
    assert "stays PRE-OPERATIONAL until a master starts it" in od.comments
    assert "0x1014 bit 31 set" in od.comments


def test_generated_eds_is_the_same_for_the_same_config(cfg: Config, tmp_path: Path) -> None:
    first = _generated(cfg, "boom", tmp_path).read_bytes()
    assert _generated(cfg, "boom", tmp_path).read_bytes() == first
    assert b"ModificationDate=01-01-2025" in first                 # the template's, not today


def test_generated_eds_lists_every_object_it_defines(cfg: Config, tmp_path: Path) -> None:
    eds = configparser.ConfigParser()
    eds.optionxform = str
    eds.read(_generated(cfg, "boom", tmp_path))
    listed = {int(v, 16) for section in ("MandatoryObjects", "OptionalObjects",
                                         "ManufacturerObjects")
              for k, v in eds[section].items() if k != "SupportedObjects"}
    defined = {int(s, 16) for s in eds.sections() if len(s) == 4
               and all(c in "0123456789ABCDEFabcdef" for c in s)}
    assert listed == defined and 0x6020 in listed


def test_generated_eds_pdos_pack_like_the_frames(three_units: Config, tmp_path: Path) -> None:
    codec = FrameCodec(three_units)
    for unit in three_units.unit_names:
        network = canopen.Network()
        node = network.create_node(three_units.can.units[unit].sensor_node_id,
                                   str(_generated(three_units, unit, tmp_path)))
        node.tpdo.read(from_od=True)
        tpdo1, tpdo2 = node.tpdo[1], node.tpdo[2]
        assert tpdo1.cob_id == codec.ids[message_name("position", unit)]
        assert tpdo2.cob_id == codec.ids[message_name("diag", unit)]
        tpdo1[0x6020].raw, tpdo1[0x6030].raw, tpdo1[0x2000].raw = 54321, 77, 0x22
        assert bytes(tpdo1.data) == bytes(codec.encode_position(unit, 543.21, 7.7, 0x22).data)
        for index, value in ((0x2001, 1234), (0x2002, 0x41), (0x2003, 9), (0x2004, 1)):
            tpdo2[index].raw = value
        assert bytes(tpdo2.data) == bytes(codec.encode_diag(unit, 12.34, 0x41, 9, 1).data)


def test_unknown_unit_lists_the_machine_s_units(three_units: Config) -> None:
    with pytest.raises(UnknownUnitError, match=r"unknown unit 'boom' \(this machine's units: "
                                               r"lift, tilt, arm\)"):
        unit_object_dictionary(three_units, "boom")
