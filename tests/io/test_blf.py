"""The bulk BLF reader and writer agree with python-can, cantools and :mod:`.log` on machines
whose Hall inputs go beyond the I/O module's first byte."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import can
import numpy as np
import pytest

from ddh_vsensor.io.blf import frames_to_runs, read_frames, write_blf_inputs
from ddh_vsensor.io.log import read_can_log, write_blf
from ddh_vsensor.config import Config

from .test_log import switching_run, timed_run


def _frames(path: Path) -> list[tuple[float, int, bytes]]:
    with can.BLFReader(path) as reader:
        return [(m.timestamp, m.arbitration_id, bytes(m.data)) for m in reader]


@pytest.mark.parametrize("machine", ["three_units", "wide_inputs"])
def test_runs_equal_the_frame_by_frame_reader(tmp_path: Path, machine: str,
                                              request: pytest.FixtureRequest) -> None:
    cfg: Config = request.getfixturevalue(machine)
    runs = {unit: switching_run(unit, n=250, seed=i + 3) for i, unit in enumerate(cfg.unit_names)}
    path = tmp_path / "machine.blf"
    write_blf(path, runs, cfg)
    fast = frames_to_runs(read_frames(path), cfg, str(path))
    for unit in cfg.unit_names:
        slow = read_can_log(path, unit, cfg)
        np.testing.assert_array_equal(fast[unit].time_s, slow.time_s)
        np.testing.assert_array_equal(fast[unit].speed_rpm, slow.speed_rpm)
        np.testing.assert_array_equal(fast[unit].position_mm, slow.position_mm)
        assert set(fast[unit].refs) == set(slow.refs) == {"bottom", "mid", "top"}
        for name, state in slow.refs.items():
            np.testing.assert_array_equal(fast[unit].refs[name], state)
            assert state.any(), (unit, name)        # every switch seen on: a real check


@pytest.mark.parametrize("machine", ["three_units", "wide_inputs"])
def test_bulk_writer_writes_the_frames_of_the_frame_by_frame_writer(
        tmp_path: Path, machine: str, request: pytest.FixtureRequest) -> None:
    cfg: Config = request.getfixturevalue(machine)
    runs = {unit: dataclasses.replace(switching_run(unit, n=200, seed=i),
                                      position_mm=np.full(200, np.nan))
            for i, unit in enumerate(cfg.unit_names)}
    write_blf(tmp_path / "slow.blf", runs, cfg)
    count = write_blf_inputs(tmp_path / "fast.blf", runs, cfg)
    slow, fast = _frames(tmp_path / "slow.blf"), _frames(tmp_path / "fast.blf")
    assert count == len(fast) and fast == slow


def test_timed_switch_changes_read_and_write_as_frame_by_frame(tmp_path: Path,
                                                               cfg: Config) -> None:
    """An I/O module sending on change of state: both writers send the same frames, both
    readers find the same change times."""
    runs = {a: dataclasses.replace(timed_run(a, seed=i + 5),
                                   position_mm=np.full(1500, np.nan))
            for i, a in enumerate(("boom", "bucket"))}
    write_blf(tmp_path / "slow.blf", runs, cfg)
    count = write_blf_inputs(tmp_path / "fast.blf", runs, cfg)
    assert _frames(tmp_path / "fast.blf") == _frames(tmp_path / "slow.blf")
    assert count == len(_frames(tmp_path / "fast.blf"))
    fast = frames_to_runs(read_frames(tmp_path / "fast.blf"), cfg, "fast")
    for a, run in runs.items():
        slow = read_can_log(tmp_path / "fast.blf", a, cfg)
        assert set(fast[a].ref_edge_s) == set(slow.ref_edge_s) == set(run.refs)
        for name, edge in slow.ref_edge_s.items():
            np.testing.assert_array_equal(fast[a].ref_edge_s[name], edge)
            assert np.isfinite(edge).sum() == np.isfinite(run.ref_edge_s[name]).sum() > 0
