"""A BLF cut off mid-object (a logger stopped short, a copy interrupted), an empty one, one
that is no BLF: every reader of the project (the bulk one, python-can's behind
``read_can_log`` / ``read_messages``) gives the same frames and the same one-line word, and
the fleet, which needs whole logs, refuses a cut one."""

from __future__ import annotations

import logging
import re
from pathlib import Path

import numpy as np
import pytest

from ddh_vsensor.config import load_config
from ddh_vsensor.io.blf import read_frames, whole_part, write_blf_inputs
from ddh_vsensor.io.log import read_can_log, read_messages
from ddh_vsensor.measured import MeasuredDataError, Run

SAMPLES = 12000          # 120 s at 100 Hz: a dozen of python-can's BLF containers
CUT = re.compile(r"(\S+cut\.blf): truncated BLF: object at byte (\d+) cut off; read the whole "
                 r"objects before it, \2 of (\d+) bytes \((\d+) %\)")


@pytest.fixture(scope="module")
def cfg():
    return load_config()


@pytest.fixture(scope="module")
def whole(cfg, tmp_path_factory) -> Path:
    t = np.arange(SAMPLES) * 0.01
    runs = {a: Run(time_s=t, speed_rpm=np.round(1500 * np.sin(t / (3 + k))),
                   torque_nm=np.round(16 * 20 * np.cos(t / 5)) / 16,
                   oil_temp_c=40 + 0.01 * t, position_mm=np.full(SAMPLES, np.nan),
                   source=a)
            for k, a in enumerate(cfg.unit_names)}
    path = tmp_path_factory.mktemp("blf") / "whole.blf"
    write_blf_inputs(path, runs, cfg)
    return path


@pytest.fixture
def cut(whole: Path, tmp_path: Path) -> Path:
    path = tmp_path / "cut.blf"
    raw = whole.read_bytes()
    path.write_bytes(raw[:int(len(raw) * 0.6)])
    return path


def _warning(caplog) -> re.Match:
    lines = [r.getMessage() for r in caplog.records if r.levelno == logging.WARNING]
    assert len(lines) == 1, lines
    match = CUT.fullmatch(lines[0])
    assert match, lines[0]
    return match


def test_every_reader_reads_the_whole_part_of_a_cut_log_and_says_so(cfg, whole: Path,
                                                                    cut: Path, caplog) -> None:
    full = read_frames(whole)
    with caplog.at_level(logging.WARNING):
        bulk = read_frames(cut)
    match = _warning(caplog)
    assert match.group(1) == str(cut) and int(match.group(3)) == cut.stat().st_size
    at_byte = int(match.group(2))
    assert 0 < at_byte < cut.stat().st_size
    assert int(match.group(4)) == round(100 * at_byte / cut.stat().st_size)
    # what is read is a prefix of the whole log: about the 60 % kept, less the cut container
    assert 0.4 * len(full) < len(bulk) < 0.6 * len(full)
    np.testing.assert_array_equal(bulk.timestamp_s, full.timestamp_s[:len(bulk)])
    np.testing.assert_array_equal(bulk.data, full.data[:len(bulk)])

    caplog.clear()
    with caplog.at_level(logging.WARNING):
        messages = read_messages(cut)          # python-can: replay, monitor
    assert _warning(caplog).group(2) == str(at_byte)
    assert len(messages) == len(bulk)
    np.testing.assert_array_equal([m.timestamp for m in messages], bulk.timestamp_s)

    caplog.clear()
    with caplog.at_level(logging.WARNING):
        run = read_can_log(cut, "boom", cfg)    # estimate, analyze
    assert _warning(caplog).group(2) == str(at_byte)
    sevcon = bulk.arbitration_id == 0x180 + cfg.can.units["boom"].sevcon_node_id
    np.testing.assert_array_equal(run.time_s, bulk.timestamp_s[sevcon])


def test_a_whole_log_reads_without_a_word(whole: Path, caplog) -> None:
    with caplog.at_level(logging.WARNING):
        assert len(read_frames(whole)) == len(read_messages(whole))
    assert not caplog.records


def test_a_tool_that_needs_the_whole_log_refuses_a_cut_one(cfg, cut: Path, caplog) -> None:
    pytest.importorskip("pyarrow")
    from ddh_vsensor.fleet.ingest import read_log
    with pytest.raises(MeasuredDataError, match=r"cut\.blf: cannot read CAN log: object at "
                                                r"byte \d+ cut off$"):
        read_frames(cut, need_whole=True)
    with pytest.raises(MeasuredDataError, match=r"cannot read CAN log: object at byte \d+ "
                                                r"cut off$"):
        read_log(str(cut), cfg, cut.read_bytes())
    assert not caplog.records


@pytest.mark.parametrize("content, problem", [
    (b"", "cannot read CAN log: the file is empty"),
    (b"LOGG", "cannot read CAN log: not a BLF file"),
    (b"\x00\xff garbage " * 40, "cannot read CAN log: not a BLF file"),
])
def test_an_empty_or_foreign_file_is_one_line_from_every_reader(cfg, tmp_path: Path,
                                                                content: bytes,
                                                                problem: str) -> None:
    path = tmp_path / "bad.blf"
    path.write_bytes(content)
    for read in (read_frames, read_messages, lambda p: read_can_log(p, "boom", cfg)):
        with pytest.raises(MeasuredDataError) as info:
            read(path)
        assert str(info.value).startswith(f"{path}: {problem}"), str(info.value)
        assert "\n" not in str(info.value) and "unpack" not in str(info.value)


def test_a_cut_within_an_object_header_is_a_cut(whole: Path, tmp_path: Path, caplog) -> None:
    raw = whole.read_bytes()
    first_end = len(whole_part("w", raw[:len(raw) // 2]))    # the end of a whole object
    with caplog.at_level(logging.WARNING):
        assert whole_part("x.blf", raw[:first_end + 8]) == raw[:first_end]
    assert f"object at byte {first_end} cut off" in caplog.records[0].getMessage()
