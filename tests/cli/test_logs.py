"""Logging a journal can live with: -v/-q move the level, canopen's per-request INFO lines
are folded into a summary line unless at debug."""

from __future__ import annotations

import logging

import pytest

from ddh_vsensor.cli.logs import ActivitySummary, configure_logging, effective_level
from ddh_vsensor.cli.main import build_parser


@pytest.mark.parametrize("base, verbosity, level", [
    (None, 0, logging.WARNING), (None, 1, logging.INFO), (None, 2, logging.DEBUG),
    ("info", 0, logging.INFO), ("info", 1, logging.DEBUG), ("info", -1, logging.WARNING),
    ("info", -9, logging.CRITICAL), ("debug", 5, logging.DEBUG)])
def test_effective_level(base, verbosity, level) -> None:
    assert effective_level(base, verbosity) == level


def test_global_flags_before_the_command() -> None:
    args = build_parser().parse_args(["-vv", "-q", "run"])
    assert args.verbose - args.quiet == 1


def _record(name: str, level: int, msg: str, *args) -> logging.LogRecord:
    return logging.LogRecord(name, level, __file__, 1, msg, args, None)


def test_canopen_info_lines_become_one_summary(caplog) -> None:
    summary = ActivitySummary(interval_s=3600.0)       # flushed by hand below
    try:
        for k in range(50):
            assert not summary.filter(_record("canopen.sdo.server", logging.INFO,
                                              "Expedited upload for 0x%04X:%02X", 0x6020, 1))
        assert not summary.filter(_record("canopen.nmt", logging.INFO, "Sending boot-up message"))
        assert summary.filter(_record("canopen.sdo.server", logging.WARNING, "abort"))
        assert summary.filter(_record("ddh_vsensor.service", logging.INFO, "ours"))
        with caplog.at_level(logging.INFO, logger="ddh_vsensor.cli.logs"):
            summary.flush()
            summary.flush()                              # nothing new: no second line
    finally:
        summary.flush()
    lines = [r.getMessage() for r in caplog.records if r.name == "ddh_vsensor.cli.logs"]
    assert len(lines) == 1
    assert "51 events" in lines[0]
    assert "50 x server: Expedited upload for 0x6020:01" in lines[0]
    assert "1 x nmt: Sending boot-up message" in lines[0]


def test_configure_logging_folds_only_at_info() -> None:
    root = logging.getLogger()
    saved = root.level
    try:
        assert configure_logging("info", 0) == logging.INFO
        handler = root.handlers[-1]
        assert any(isinstance(f, ActivitySummary) for f in handler.filters)
        assert configure_logging("info", 1) == logging.DEBUG
        assert root.handlers[-1] is not handler and handler not in root.handlers
        assert not root.handlers[-1].filters                   # -v: every line
        assert configure_logging(None, -1) == logging.ERROR
    finally:
        configure_logging(None, 0)
        root.setLevel(saved)
