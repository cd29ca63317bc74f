"""``ddh-vsensor simulate``: the issue's 'done when' run, file identity, bad input."""

from __future__ import annotations

import subprocess
import sys

import numpy as np
import pytest

from ddh_vsensor.io.log import read_can_log
from ddh_vsensor.cli.main import main
from ddh_vsensor.io.csv import read_csv
from ddh_vsensor.sim.cycles import work_cycle


def test_paper_speed4_timing_and_peaks(paper_run_dir):
    for a in ("boom", "bucket"):
        run = read_csv(paper_run_dir / f"{a}.csv")
        assert 20.0 <= run.time_s[-1] <= 32.0
        peak = np.max(np.abs(run.speed_rpm))
        assert 4500 <= peak <= 6500, (a, peak)
        assert np.max(np.abs(run.torque_nm)) < 90.0
        assert any(c.startswith("seed: 0") for c in run.comments)
        assert run.refs["mid"].any()
    boom = read_csv(paper_run_dir / "boom.csv")
    assert boom.refs["bottom"][0] == 1 and boom.refs["bottom"][-1] == 1
    assert not boom.refs["top"].any()


def test_boom_top_hold_creeps_while_the_rod_stands(cfg, paper_run_dir):
    """The paper's Figure 7: tens of rpm at the top while the cylinder stays put."""
    run = read_csv(paper_run_dir / "boom.csv")
    knots = work_cycle(cfg, "paper", 4).trajectories["boom"].time_s  # ..., top, lowering starts
    hold = (run.time_s >= knots[2] + 1.0) & (run.time_s <= knots[3])
    assert hold.sum() > 500
    creep = run.speed_rpm[hold]
    assert 10.0 <= np.mean(creep) <= 99.0
    assert np.all(creep > 0)                               # feeding the leakage, not hunting
    assert np.ptp(run.position_mm[hold]) < 0.5


def test_blf_decodes_to_the_csv_values(cfg, paper_run_dir):
    for a in ("boom", "bucket"):
        csv_run = read_csv(paper_run_dir / f"{a}.csv")
        can_run = read_can_log(paper_run_dir / "run.blf", a, cfg)
        np.testing.assert_allclose(can_run.time_s, csv_run.time_s, atol=1e-6)
        for name in ("speed_rpm", "torque_nm", "oil_temp_c", "position_mm"):
            np.testing.assert_allclose(getattr(can_run, name), getattr(csv_run, name),
                                       atol=1e-9, err_msg=name)
        for name, state in csv_run.refs.items():
            np.testing.assert_array_equal(can_run.refs[name], state)


@pytest.fixture(scope="module")
def profile_csv(tmp_path_factory):
    path = tmp_path_factory.mktemp("profile") / "short.csv"
    t = np.arange(0.0, 4.01, 0.05)
    boom = 1.5 + 80.0 * np.sin(np.pi * t / 4.0) ** 2
    bucket = 600.0 - 200.0 * np.sin(np.pi * t / 4.0) ** 2
    rows = "\n".join(f"{a:.2f},{b:.4f},{c:.4f}" for a, b, c in zip(t, boom, bucket))
    path.write_text("time_s,boom_mm,bucket_mm\n" + rows + "\n")
    return path


def _simulate(out, profile, seed, *extra):
    return main(["simulate", "--cycle", str(profile), "--payload-kg", "1040", "--oil-temp-c",
                 "35", "--seed", str(seed), "--out", str(out), *extra])


def test_same_seed_same_files(tmp_path, profile_csv):
    assert _simulate(tmp_path / "a", profile_csv, 3) == 0
    assert _simulate(tmp_path / "b", profile_csv, 3) == 0
    assert _simulate(tmp_path / "c", profile_csv, 4, "--no-blf") == 0
    for name in ("boom.csv", "bucket.csv", "run.blf"):
        assert (tmp_path / "a" / name).read_bytes() == (tmp_path / "b" / name).read_bytes()
    a, c = read_csv(tmp_path / "a" / "boom.csv"), read_csv(tmp_path / "c" / "boom.csv")
    assert np.array_equal(a.speed_rpm, c.speed_rpm)       # noise is on the position only
    assert not np.array_equal(a.position_mm, c.position_mm)
    assert np.abs(a.position_mm - c.position_mm).max() < 0.2
    assert not (tmp_path / "c" / "run.blf").exists()


@pytest.mark.parametrize("args, words", [
    (["--speed", "5"], "speed must be one of"),
    (["--effect", "wear=2"], "unknown effect"),
    (["--effect", "pump_leakage=-1"], "out of range"),
    (["--payload-kg", "9000"], "too heavy"),
    (["--oil-temp-c", "150"], "oil temperature"),
    (["--cycles", "0"], "cycles"),
    (["--rate-hz", "300"], "whole number"),
    (["--cycle", "nothere.csv"], "work, paper, dig-dump"),
    (["--cycle", "random", "--duration-s", "1"], "--duration-s"),
])
def test_bad_input_exits_2(tmp_path, capsys, args, words):
    base = {"--cycle": "paper", "--payload-kg": "0", "--oil-temp-c": "27",
            "--out": str(tmp_path / "x")}
    for key, value in zip(args[::2], args[1::2]):
        base[key] = value
    argv = ["simulate"] + [s for kv in base.items() for s in kv]
    assert main(argv) == 2
    assert words in capsys.readouterr().err
    assert not (tmp_path / "x").exists()


def test_bad_input_no_traceback(tmp_path):
    proc = subprocess.run([sys.executable, "-m", "ddh_vsensor.cli.main", "simulate", "--cycle",
                           "paper", "--payload-kg", "0", "--oil-temp-c", "27", "--effect",
                           "boom.compressibility=0.5", "--out", str(tmp_path)],
                          capture_output=True, text=True)
    assert proc.returncode == 2 and "compressibility" in proc.stderr
    assert "Traceback" not in proc.stderr
