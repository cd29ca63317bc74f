"""CAN logs <-> runs: a BLF written from runs reads back as the same data, within quantisation."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import can
import numpy as np
import pytest

from ddh_vsensor.canbus import FrameCodec
from ddh_vsensor.io.log import read_can_log, write_blf
from ddh_vsensor.config import Config
from ddh_vsensor.measured import MeasuredDataError, Run
from ddh_vsensor.io.csv import read_csv, write_csv

# Half of each frame's quantisation step, plus float slack.
TORQUE_NM, SPEED_RPM, OIL_C, POSITION_MM = 1 / 32 + 1e-9, 0.5 + 1e-9, 0.05 + 1e-9, 0.005 + 1e-9
TIME_S = 1e-6      # BLF stores nanoseconds; at wall-clock times float64 resolves ~0.2 us


def make_run(actuator: str, n: int = 400, start_s: float = 0.0, seed: int = 0) -> Run:
    rng = np.random.default_rng(seed)
    time_s = start_s + np.cumsum(rng.uniform(0.0005, 0.002, n))   # uneven, with gaps
    position_mm = 150.0 + 120.0 * np.sin(time_s)
    sampled = position_mm.copy()
    sampled[rng.random(n) < 0.3] = np.nan
    return Run(time_s=time_s, speed_rpm=rng.normal(0, 1500, n), torque_nm=rng.normal(0, 30, n),
               oil_temp_c=40.0 + (time_s - start_s) + (5.0 if actuator == "bucket" else 0.0),
               position_mm=sampled,
               refs={"top": position_mm > 265, "mid": np.abs(position_mm - 155) < 3,
                     "bottom": position_mm < 35},
               comments=[f"test run {actuator}"], source=f"<{actuator}>")


def switching_run(actuator: str, n: int, seed: int) -> Run:
    """make_run with every switch toggling in runs of 10 samples, each unit differently (so a
    bit read from the wrong unit or byte shows)."""
    rng = np.random.default_rng(seed + 100)
    refs = {name: np.repeat(rng.random(n // 10 + 1) < 0.5, 10)[:n]
            for name in ("bottom", "mid", "top")}
    return dataclasses.replace(make_run(actuator, n=n, seed=seed), refs=refs)


def assert_same_data(read: Run, written: Run, oil: Run) -> None:
    """read is written within quantisation, with the oil temperature held from run oil."""
    np.testing.assert_allclose(read.time_s, written.time_s, rtol=0, atol=TIME_S)
    np.testing.assert_allclose(read.torque_nm, written.torque_nm, rtol=0, atol=TORQUE_NM)
    np.testing.assert_allclose(read.speed_rpm, written.speed_rpm, rtol=0, atol=SPEED_RPM)
    held = np.maximum(np.searchsorted(oil.time_s, written.time_s, "right") - 1, 0)
    np.testing.assert_allclose(read.oil_temp_c, oil.oil_temp_c[held], rtol=0, atol=OIL_C)
    np.testing.assert_array_equal(np.isnan(read.position_mm), np.isnan(written.position_mm))
    np.testing.assert_allclose(read.position_mm, written.position_mm, rtol=0, atol=POSITION_MM)
    assert set(read.refs) == {"bottom", "mid", "top"}
    for name, state in written.refs.items():
        np.testing.assert_array_equal(read.refs[name], state)


def test_blf_round_trip_of_both_units(tmp_path: Path, cfg: Config) -> None:
    runs = {"boom": make_run("boom", seed=1), "bucket": make_run("bucket", n=300, seed=2)}
    path = tmp_path / "both.blf"
    write_blf(path, runs, cfg)
    for actuator, run in runs.items():
        assert_same_data(read_can_log(path, actuator, cfg), run, oil=runs["boom"])
    assert [p.name for p in tmp_path.iterdir()] == ["both.blf"]     # no temp file left


@pytest.mark.parametrize("start_s", [12.3456789, 1.7e9])     # relative and wall-clock times
def test_csv_and_blf_of_one_run_describe_the_same_data(tmp_path: Path, cfg: Config,
                                                       start_s: float) -> None:
    write_csv(tmp_path / "bucket.csv", make_run("bucket", start_s=start_s))
    run = read_csv(tmp_path / "bucket.csv")
    write_blf(tmp_path / "bucket.blf", {"bucket": run}, cfg)
    read = read_can_log(tmp_path / "bucket.blf", "bucket", cfg)
    assert_same_data(read, run, oil=run)
    assert read.source == str(tmp_path / "bucket.blf")


def test_missing_refs_read_back_as_off(tmp_path: Path, cfg: Config) -> None:
    run = dataclasses.replace(make_run("boom"), refs={})
    write_blf(tmp_path / "x.blf", {"boom": run}, cfg)
    read = read_can_log(tmp_path / "x.blf", "boom", cfg)
    assert all(not state.any() for state in read.refs.values())


def test_other_log_formats_and_node_ids(tmp_path: Path, cfg: Config) -> None:
    units = {**cfg.can.units, "bucket": dataclasses.replace(cfg.can.units["bucket"],
                                                            sevcon_node_id=9)}
    moved = dataclasses.replace(cfg, can=dataclasses.replace(cfg.can, units=units))
    codec = FrameCodec(moved)
    path = tmp_path / "log.asc"
    with can.Logger(path) as logger:
        for i, t in enumerate((0.010, 0.020, 0.030)):
            logger.on_message_received(codec.encode_sevcon("bucket", 2.0 * i, 100 * i, t))
            logger.on_message_received(codec.encode_position("bucket", 10.0 * i, 0.0, 0, t))
        logger.on_message_received(codec.encode_oil_temp(55.5, 0.015))
    read = read_can_log(path, "bucket", moved)
    np.testing.assert_allclose(np.diff(read.time_s), [0.01, 0.01], atol=1e-6)  # ASC: relative
    np.testing.assert_allclose(read.position_mm, [0, 10, 20])
    np.testing.assert_allclose(read.speed_rpm, [0, 100, 200])
    np.testing.assert_allclose(read.oil_temp_c, [55.5, 55.5, 55.5])
    assert read.refs == {}
    with pytest.raises(MeasuredDataError, match=r"log\.asc.*SEVCON_BUCKET_TPDO1.*0x182"):
        read_can_log(path, "bucket", cfg)     # default node IDs: the frames are not there


@pytest.mark.parametrize("content, problem", [
    (None, "cannot read: No such file"),
    (b"this is not a BLF file at all" * 10, "cannot read CAN log: not a BLF file"),
])
def test_unreadable_log_names_the_file(tmp_path: Path, cfg: Config, content: bytes | None,
                                       problem: str) -> None:
    path = tmp_path / "broken.blf"
    if content is not None:
        path.write_bytes(content)
    with pytest.raises(MeasuredDataError, match=rf"broken\.blf: {problem}"):
        read_can_log(path, "boom", cfg)


@pytest.mark.parametrize("name", ["passwd", "run.bin", "run.blf.zip"])
def test_a_file_of_no_log_format_says_which_formats_are(tmp_path: Path, cfg: Config,
                                                        name: str) -> None:
    """python-can's own words were 'No read support for unknown log format ""'."""
    path = tmp_path / name
    path.write_bytes(b"root:x:0:0::/root:/bin/sh\n")
    with pytest.raises(MeasuredDataError, match=rf"{name}: cannot read CAN log: its extension "
                                                r"\(.*\) is no log format's \(\.asc, \.blf, "):
        read_can_log(path, "boom", cfg)


def test_log_without_the_actuator_names_the_file(tmp_path: Path, cfg: Config) -> None:
    write_blf(tmp_path / "boom_only.blf", {"boom": make_run("boom")}, cfg)
    with pytest.raises(MeasuredDataError, match=r"boom_only\.blf: no SEVCON_BUCKET_TPDO1"):
        read_can_log(tmp_path / "boom_only.blf", "bucket", cfg)


def test_reference_without_input_bit_is_refused(tmp_path: Path, cfg: Config) -> None:
    run = make_run("boom")
    run.refs["extra"] = run.refs["top"]
    with pytest.raises(MeasuredDataError, match="extra.*hall_bits"):
        write_blf(tmp_path / "x.blf", {"boom": run}, cfg)
    assert not list(tmp_path.iterdir())


def test_out_of_range_value_names_run_and_time(tmp_path: Path, cfg: Config) -> None:
    run = make_run("boom")
    run.torque_nm[5] = 5000.0                     # beyond INT16 at 1/16 N·m
    with pytest.raises(MeasuredDataError, match=r"<boom>: at time_s .*cannot encode"):
        write_blf(tmp_path / "x.blf", {"boom": run}, cfg)
    assert not list(tmp_path.iterdir())


@pytest.mark.parametrize("machine", ["three_units", "wide_inputs"])
def test_hall_inputs_beyond_the_first_byte_round_trip(tmp_path: Path, machine: str,
                                                      request: pytest.FixtureRequest) -> None:
    cfg = request.getfixturevalue(machine)
    runs = {unit: switching_run(unit, n=300, seed=i) for i, unit in enumerate(cfg.unit_names)}
    path = tmp_path / "machine.blf"
    write_blf(path, runs, cfg)
    first = runs[cfg.unit_names[0]]
    for unit, run in runs.items():
        assert_same_data(read_can_log(path, unit, cfg), run, oil=first)
    io_id = FrameCodec(cfg).ids["IO_MODULE_TPDO1"]
    with can.BLFReader(path) as reader:
        lengths = {m.dlc for m in reader if m.arbitration_id == io_id}
    assert lengths == {max(b for u in cfg.can.units.values() for b in u.hall_bits.values())
                       // 8 + 1}


def timed_run(actuator: str, seed: int) -> Run:
    """make_run with its switches toggling in runs of 50 samples, each change timed at a
    random instant of its sample's period."""
    rng = np.random.default_rng(seed + 200)
    n = 1500
    refs = {name: np.repeat(rng.random(n // 50 + 1) < 0.5, 50)[:n]
            for name in ("bottom", "mid", "top")}
    run = dataclasses.replace(make_run(actuator, n=n, seed=seed), refs=refs)
    edges = {}
    for name, state in run.refs.items():
        edge = np.full(len(state), np.nan)
        k = np.flatnonzero(state[1:] != state[:-1]) + 1
        edge[k] = run.time_s[k - 1] + rng.uniform(0.01, 1.0, len(k)) * np.diff(run.time_s)[k - 1]
        edges[name] = edge
    return dataclasses.replace(run, ref_edge_s=edges)


@pytest.mark.parametrize("start_s", [0.0, 1.7e9])
def test_switch_changes_timed_between_samples_survive_the_log(tmp_path: Path, cfg: Config,
                                                              start_s: float) -> None:
    """Timed changes go on the bus as an I/O module sending on change of state does (fewer
    frames than samples, each change at its own time) and read back as the same times; a
    run timed no finer than its samples (a CSV's) is written at every sample and reads back
    untimed."""
    runs = {a: timed_run(a, seed=i + 1) for i, a in enumerate(("boom", "bucket"))}
    for run in runs.values():
        run.shift_time(start_s)
        assert sum(int(np.isfinite(e).sum()) for e in run.ref_edge_s.values()) >= 20
    write_blf(tmp_path / "timed.blf", runs, cfg)
    io_id = FrameCodec(cfg).ids["IO_MODULE_TPDO1"]
    with can.BLFReader(tmp_path / "timed.blf") as reader:
        n_io = sum(m.arbitration_id == io_id for m in reader)
    assert n_io < len(runs["boom"].time_s) / 4
    for actuator, run in runs.items():
        read = read_can_log(tmp_path / "timed.blf", actuator, cfg)
        assert_same_data(read, run, oil=runs["boom"])
        assert set(read.ref_edge_s) == set(run.refs)
        for name, edge in run.ref_edge_s.items():
            np.testing.assert_array_equal(np.isnan(read.ref_edge_s[name]), np.isnan(edge))
            np.testing.assert_allclose(read.ref_edge_s[name], edge, rtol=0, atol=TIME_S)
    plain = {a: dataclasses.replace(run, ref_edge_s={}) for a, run in runs.items()}
    write_blf(tmp_path / "rows.blf", plain, cfg)
    read = read_can_log(tmp_path / "rows.blf", "boom", cfg)
    assert_same_data(read, plain["boom"], oil=plain["boom"])
    assert read.ref_edge_s == {}


def test_changes_stamped_with_the_samples_times_are_not_taken_as_timed(tmp_path: Path,
                                                                       cfg: Config) -> None:
    """An I/O module sending on change whose frames carry the samples' own times (a logger
    or a simulator that stamps them so) says nothing finer than the samples: read untimed,
    or every edge would be taken half a sample's travel off."""
    runs = {a: timed_run(a, seed=i + 7) for i, a in enumerate(("boom", "bucket"))}
    for run in runs.values():
        for name, edge in run.ref_edge_s.items():
            k = np.flatnonzero(np.isfinite(edge))
            edge[k] = run.time_s[k]                        # stamped at the sample
    write_blf(tmp_path / "stamped.blf", runs, cfg)
    io_id = FrameCodec(cfg).ids["IO_MODULE_TPDO1"]
    with can.BLFReader(tmp_path / "stamped.blf") as reader:
        assert sum(m.arbitration_id == io_id for m in reader) < len(runs["boom"].time_s) / 4
    read = read_can_log(tmp_path / "stamped.blf", "boom", cfg)
    assert_same_data(read, runs["boom"], oil=runs["boom"])
    assert all(np.isnan(e).all() for e in read.ref_edge_s.values())
