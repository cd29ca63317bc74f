"""The package's rooms import downward only (the layers contract in pyproject.toml)."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]


def test_no_upward_import() -> None:
    """import-linter's layers contract: cli > fleet > master > service > device > diagnosis >
    sim > io > canbus > estimator > tables > physics > config > measured > atomic > errors >
    version; a module importing one of a higher layer breaks it."""
    lint = Path(sys.executable).with_name("lint-imports")
    done = subprocess.run([str(lint), "--config", str(REPO / "pyproject.toml")], cwd=REPO,
                          capture_output=True, text=True, timeout=120)
    assert done.returncode == 0, done.stdout[-3000:] + done.stderr[-2000:]
    assert "1 kept, 0 broken" in done.stdout
