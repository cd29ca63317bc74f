import json
import subprocess
import sys

from ddh_vsensor.cli.main import main


def test_tables_build_and_plot(tmp_path, capsys):
    assert main(["tables", "build", "--out", str(tmp_path / "t")]) == 0
    assert (tmp_path / "t" / "boom.npz").exists() and (tmp_path / "t" / "bucket.npz").exists()
    png = tmp_path / "fig5.png"
    assert main(["tables", "plot", "--tables", str(tmp_path / "t"), "--out", str(png)]) == 0
    assert png.stat().st_size > 10000


def test_steady_json_keys_and_values(capsys):
    assert main(["steady", "--actuator", "boom", "--speed-rpm", "3000", "--oil-temp-c", "27",
                 "--json"]) == 0
    out = json.loads(capsys.readouterr().out)
    assert set(out) == {"velocity_mm_s", "p_a_bar", "p_b_bar", "torque_nm", "relief_a_lpm",
                        "relief_b_lpm", "anticav_a_lpm", "anticav_b_lpm"}
    assert 45 < out["velocity_mm_s"] < 55 and out["anticav_b_lpm"] > 0


def test_steady_holding_speed_is_tens_of_rpm(capsys):
    assert main(["steady", "--actuator", "boom", "--oil-temp-c", "27", "--holding-speed",
                 "--json"]) == 0
    out = json.loads(capsys.readouterr().out)
    assert 10 <= out["holding_speed_rpm"] < 100


def test_plot_without_tables_is_a_clear_error(tmp_path):
    proc = subprocess.run([sys.executable, "-m", "ddh_vsensor.cli.main", "tables", "plot",
                           "--tables", str(tmp_path), "--out", str(tmp_path / "x.png")],
                          capture_output=True, text=True)
    assert proc.returncode == 2 and "no table file" in proc.stderr
    assert "Traceback" not in proc.stderr
