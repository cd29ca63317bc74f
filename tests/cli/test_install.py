"""The install path a technician takes: build the wheel, pip-install it into a fresh venv, run
``ddh-vsensor install`` into a staging root (twice: idempotent; then with an edited config:
kept), and ``systemd-analyze verify`` the installed unit.

The venv is created without the system site (whose editable install of this repository would
otherwise win the import); the dependencies (numpy, canopen, ...) come from the directories
they are installed in, added by a .pth *path* line, which does not run those directories' own
.pth files. So ``ddh_vsensor`` and its data files can only come from the wheel, and the test
checks that they do."""

from __future__ import annotations

import importlib.util
import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[2]
SOURCES = ("pyproject.toml", "setup.py", "README.md", "ddh_vsensor", "config", "dbc", "systemd")
DEPENDENCIES = ("numpy", "scipy", "yaml", "can", "canopen", "cantools", "matplotlib")
DATA_FILES = ("loader.yaml", "ddh_vsensor.dbc", "cia406_position_sensor.eds",
              "ddh-vsensor@.service", "README.md")
STEP_TIMEOUT_S = 120          # a hang guard, not a speed assertion

pytestmark = pytest.mark.slow


def _run(cmd: list[str], cwd: Path, check: bool = True, **kwargs) -> subprocess.CompletedProcess:
    env = {k: v for k, v in os.environ.items() if k not in ("PYTHONPATH", "PYTHONHOME")}
    env.update(kwargs.pop("env", {}))
    result = subprocess.run([str(c) for c in cmd], cwd=cwd, env=env, capture_output=True,
                            text=True, timeout=STEP_TIMEOUT_S, **kwargs)
    if check:
        assert result.returncode == 0, f"{cmd}:\n{result.stdout}\n{result.stderr}"
    return result


@pytest.fixture(scope="module")
def venv(tmp_path_factory) -> Path:
    """A fresh venv with the wheel of this working tree installed (no dependencies)."""
    base = tmp_path_factory.mktemp("install")
    src = base / "src"                  # a copy: the build writes build/ and *.egg-info
    src.mkdir()
    for name in SOURCES:
        path = REPO / name
        if path.is_dir():
            shutil.copytree(path, src / name, symlinks=True,
                            ignore=shutil.ignore_patterns("__pycache__"))
        else:
            shutil.copy2(path, src / name)
    wheels = base / "wheels"
    _run([sys.executable, "-m", "pip", "wheel", src, "--no-deps", "-q", "-w", wheels], base)
    (wheel,) = wheels.glob("ddh_vsensor-*.whl")
    venv = base / "venv"
    _run([sys.executable, "-m", "venv", "--without-pip", venv], base)
    purelib = Path(_run([venv / "bin" / "python", "-c",
                         "import sysconfig; print(sysconfig.get_paths()['purelib'])"],
                        base).stdout.strip())
    dep_dirs = {str(Path(importlib.util.find_spec(m).origin).parents[1]) for m in DEPENDENCIES}
    (purelib / "_ddh_test_dependencies.pth").write_text("\n".join(sorted(dep_dirs)) + "\n")
    _run([sys.executable, "-m", "pip", "--python", venv / "bin" / "python", "install",
          "--no-deps", "--no-index", "-q", wheel], base)
    return venv


def test_the_wheel_carries_its_data_as_real_files(venv: Path, tmp_path: Path) -> None:
    out = _run([venv / "bin" / "python", "-c", "import ddh_vsensor; print(ddh_vsensor.__file__)"],
               tmp_path).stdout.strip()
    package = Path(out).parent
    assert package.is_relative_to(venv), out
    for name in DATA_FILES:
        path = package / "data" / name
        assert path.is_file() and not path.is_symlink(), path
        assert path.read_bytes() == (REPO / "ddh_vsensor" / "data" / name).read_bytes(), name
    # the chamber models' compiled steps are built into the wheel where a compiler exists
    if shutil.which("cc") or shutil.which("gcc"):
        for module in ("dynamic", "chambers"):
            assert _run([venv / "bin" / "python", "-c", f"from ddh_vsensor.estimator.{module} "
                         "import library; assert library() is not None"], tmp_path)
    # the module entry point and the script both answer
    for cmd in ([venv / "bin" / "python", "-m", "ddh_vsensor", "--version"],
                [venv / "bin" / "ddh-vsensor", "--version"]):
        assert _run(cmd, tmp_path).stdout.startswith("ddh-vsensor ")


def _install(venv: Path, root: Path) -> list[str]:
    return _run([venv / "bin" / "ddh-vsensor", "install", "--force", "--root", root], root.parent
                ).stdout.splitlines()


def test_install_puts_everything_in_place_idempotently(venv: Path, tmp_path: Path) -> None:
    root = tmp_path / "root"
    first = _install(venv, root)
    unit = root / "etc/systemd/system/ddh-vsensor@.service"
    config = root / "etc/ddh-vsensor/loader.yaml"
    readme = root / "usr/local/share/doc/ddh-vsensor/README.md"
    state = root / "var/lib/ddh-vsensor"
    assert [line.split()[-1] for line in first] == ["written", "written", "written", "created"]
    assert config.read_text() == (REPO / "config" / "loader.yaml").read_text()
    assert readme.read_text() == (REPO / "README.md").read_text()
    assert state.is_dir() and state.stat().st_mode & 0o777 == 0o700
    text = unit.read_text()
    assert f"ExecStart={venv}/bin/ddh-vsensor run --config /etc/ddh-vsensor/loader.yaml " \
           "--channel %i\n" in text
    assert "Documentation=file:///usr/local/share/doc/ddh-vsensor/README.md\n" in text
    assert "RestartPreventExitStatus=2\n" in text

    second = _install(venv, root)
    assert [line.split()[-1] for line in second] == ["unchanged", "unchanged", "unchanged",
                                                     "exists"]
    assert unit.read_text() == text

    edited = config.read_text().replace("channel: can0", "channel: can1")
    config.write_text(edited)
    third = _install(venv, root)
    assert "kept (differs from the default; valid:" in third[2]
    assert "channel=can1" in third[2]
    assert config.read_text() == edited

    config.write_text(edited.replace("stroke_mm: 311.15", "stroke_mm: -1"))
    broken = _run([venv / "bin" / "ddh-vsensor", "install", "--force", "--root", root], tmp_path,
                  check=False)
    assert broken.returncode == 2
    assert "NOT VALID" in broken.stdout
    assert "units.boom.stroke_mm" in broken.stderr and "Traceback" not in broken.stderr
    assert state.is_dir()


@pytest.mark.skipif(shutil.which("systemd-analyze") is None,
                    reason="systemd-analyze is not installed (no systemd here)")
def test_systemd_analyze_verifies_the_installed_unit(venv: Path, tmp_path: Path) -> None:
    root = tmp_path / "root"
    _install(venv, root)
    unit_dir = root / "etc/systemd/system"
    result = _run(["systemd-analyze", "verify", "ddh-vsensor@can0.service"], tmp_path,
                  check=False, env={"SYSTEMD_UNIT_PATH": f"{unit_dir}:"})
    assert result.returncode == 0, result.stderr
    assert "ddh-vsensor@" not in result.stderr, result.stderr
