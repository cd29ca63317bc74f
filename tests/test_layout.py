"""The package's rooms import downward only (the layers contract in pyproject.toml)."""

from __future__ import annotations

import os
from pathlib import Path

from importlinter.cli import lint_imports

REPO = Path(__file__).resolve().parents[1]


def test_no_upward_import(capsys, monkeypatch) -> None:
    """import-linter's layers contract (pyproject.toml, top to bottom: cli, fleet, master,
    service, device, ..., estimator, model, tables, physics, config, ...): a module importing one
    of a higher layer breaks it."""
    monkeypatch.chdir(REPO)
    code = lint_imports(config_filename=os.fspath(REPO / "pyproject.toml"), no_cache=True,
                        no_logo=True)
    out = capsys.readouterr().out
    assert code == 0, out[-3000:]
    assert "1 kept, 0 broken" in out
