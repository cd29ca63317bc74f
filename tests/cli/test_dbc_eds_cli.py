"""``ddh-vsensor dbc`` and ``ddh-vsensor eds``: the files they write, one-line errors."""

from __future__ import annotations

import re
from pathlib import Path

import canopen
import cantools
import pytest
import yaml

from ddh_vsensor.cli.main import main

REPO = Path(__file__).resolve().parents[2]


@pytest.fixture
def lift_tilt(tmp_path: Path) -> Path:
    """The loader with its units renamed to lift and tilt, as a file."""
    data = yaml.safe_load((REPO / "config" / "loader.yaml").read_text())
    renames = {"boom": "lift", "bucket": "tilt"}
    for section in (data["units"], data["can"]["units"], data["faults"]["heartbeat_node_ids"]):
        for old, new in renames.items():
            section[new] = section.pop(old)
    data.pop("work_cycle")          # its cycles name the loader's units
    path = tmp_path / "lift_tilt.yaml"
    path.write_text(yaml.safe_dump(data))
    return path


def test_dbc_of_the_reference_loader_is_the_shipped_file(tmp_path: Path, capsys) -> None:
    out = tmp_path / "loader.dbc"
    assert main(["dbc", "--config", str(REPO / "config" / "loader.yaml"), "--out",
                 str(out)]) == 0
    assert out.read_bytes() == (REPO / "dbc" / "ddh_vsensor.dbc").read_bytes()
    assert "22 frames of 2 unit(s) (boom, bucket)" in capsys.readouterr().out


def test_dbc_of_another_machine(lift_tilt: Path, tmp_path: Path) -> None:
    out = tmp_path / "lift_tilt.dbc"
    assert main(["dbc", "--config", str(lift_tilt), "--out", str(out)]) == 0
    db = cantools.database.load_file(str(out))
    assert db.get_message_by_name("POSITION_TILT_TPDO1").frame_id == 0x1B2
    assert not any("BOOM" in m.name for m in db.messages)
    cause = db.get_message_by_name("HEALTH_TILT_TPDO3").get_signal_by_name("CauseCode")
    assert cause.choices[0] == "None" and len(cause.choices) > 1    # the catalogue's causes


def test_eds_of_each_unit(lift_tilt: Path, tmp_path: Path, capsys) -> None:
    for unit, node_id in (("lift", 49), ("tilt", 50)):
        out = tmp_path / f"{unit}.eds"
        assert main(["eds", "--config", str(lift_tilt), "--unit", unit, "--out",
                     str(out)]) == 0
        assert "[DeviceComissioning]" not in out.read_text()     # an EDS: the master's ID
        od = canopen.import_od(str(out), node_id)
        assert od[0x1800][1].default == 0x4000_0000 | 0x180 + node_id
        assert f"sensor of the {unit}, node {node_id}" in capsys.readouterr().out


@pytest.mark.parametrize("argv, error", [
    (["eds", "--unit", "arm"], r"unknown unit 'arm' \(this machine's units: lift, tilt\)"),
    (["eds", "--unit", "lift", "--out", "/nonexistent/dir/x.eds"], r"/nonexistent/dir/x\.eds: "
                                                                   r"cannot write"),
    (["dbc", "--out", "/nonexistent/dir/x.dbc"], r"/nonexistent/dir/x\.dbc: cannot write"),
])
def test_errors_are_one_line_exit_2(lift_tilt: Path, tmp_path: Path, capsys,
                                    argv: list[str], error: str) -> None:
    if "--out" not in argv:
        argv = [*argv, "--out", str(tmp_path / "x.eds")]
    assert main([*argv, "--config", str(lift_tilt)]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "Traceback" not in err
    assert re.search(error, err), err
    assert not list(tmp_path.glob("*.eds"))
