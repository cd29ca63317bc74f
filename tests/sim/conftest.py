"""Shared simulator fixtures: the speed-4 paper run via the CLI."""

from __future__ import annotations

from pathlib import Path

import pytest

from ddh_vsensor.cli.main import main


@pytest.fixture(scope="session")
def paper_run_dir(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """The issue's 'done when' command: speed 4, empty, 27 degC."""
    out = tmp_path_factory.mktemp("paper_run")
    assert main(["simulate", "--cycle", "paper", "--speed", "4", "--payload-kg", "0",
                 "--oil-temp-c", "27", "--out", str(out)]) == 0
    return out
