"""The progress bar: live and rate-limited on a terminal, one final line anywhere else."""

from __future__ import annotations

import fcntl
import io
import os
import re
import struct
import termios

import pytest

from ddh_vsensor.cli import progress
from ddh_vsensor.cli.progress import ProgressBar

FINAL = r"^stage \[#{30}\] 100\.0% \d\d:\d\d, done: 3 files$"


class FakeTerminal(io.StringIO):
    def isatty(self) -> bool:
        return True


class FakeClock:
    """The bar's clock, advanced by the test (no test depends on the machine's speed)."""

    def __init__(self) -> None:
        self.now_s = 1000.0

    def monotonic(self) -> float:
        return self.now_s


@pytest.fixture
def clock(monkeypatch) -> FakeClock:
    fake = FakeClock()
    monkeypatch.setattr(progress, "time", fake)
    return fake


def test_terminal_gets_a_live_bar_redrawn_at_most_ten_times_a_second(clock: FakeClock) -> None:
    term = FakeTerminal()
    bar = ProgressBar("stage", term)
    for k in range(1, 201):                  # 200 updates over 2 s of the clock
        clock.now_s += 0.01
        bar.update(k / 400, f"file {k}")
    bar.close("done: 3 files")
    out = term.getvalue()
    frames = out.split("\r")[1:]
    assert out.endswith("\n") and out.count("\n") == 1
    assert 15 <= len(frames) - 2 <= 20, len(frames)    # initial + at most 10/s + final
    assert frames[0].startswith("stage [" + "-" * 30 + "]   0.0%")
    assert any(re.search(r"\] +[1-4]\d\.\d% 00:0\d, file \d+", f) for f in frames[1:-1])
    assert re.match(FINAL, frames[-1].rstrip("\n"))


def test_fraction_is_clamped_and_may_go_back(clock: FakeClock) -> None:
    term = FakeTerminal()
    bar = ProgressBar("stage", term, width=10)
    for fraction in (1.7, 0.2, -3.0):
        clock.now_s += 1.0
        bar.update(fraction)
    shown = [re.search(r"(\d+\.\d)%", f).group(1) for f in term.getvalue().split("\r")[1:]]
    assert shown == ["0.0", "100.0", "20.0", "0.0"]
    assert "[##--------]  20.0%" in term.getvalue()


def test_elsewhere_only_the_final_line_is_written(capsys) -> None:
    bar = ProgressBar("stage")                 # sys.stderr: captured, not a terminal
    for k in range(1, 101):
        bar.update(k / 100, f"file {k}")
    assert capsys.readouterr().err == ""
    bar.close("done: 3 files")
    err = capsys.readouterr().err
    assert "\r" not in err
    assert re.fullmatch(FINAL + "\n", err, re.MULTILINE), err


def test_an_explicit_stream_that_is_not_a_terminal_gets_one_line() -> None:
    log = io.StringIO()
    bar = ProgressBar("replay", log)
    bar.update(0.5, "half")
    bar.close()
    assert re.fullmatch(r"replay \[#{30}\] 100\.0% \d\d:\d\d\n", log.getvalue())


class SizedTerminal(FakeTerminal):
    """Written to as a string, sized as a pseudo-terminal of 61 columns (tqdm asks the
    stream's file descriptor for its window size)."""

    def __init__(self) -> None:
        super().__init__()
        self.master_fd, self.slave_fd = os.openpty()
        fcntl.ioctl(self.slave_fd, termios.TIOCSWINSZ, struct.pack("HHHH", 24, 61, 0, 0))

    def fileno(self) -> int:
        return self.slave_fd

    def close(self) -> None:
        # once only: IOBase.__del__ closes again, and by then these numbers may be another
        # object's descriptors (a double close once shut multiprocessing's resource tracker)
        if not self.closed:
            os.close(self.slave_fd)
            os.close(self.master_fd)
        super().close()


def test_live_lines_fit_the_terminal_and_the_final_one_is_whole(clock: FakeClock) -> None:
    term = SizedTerminal()
    bar = ProgressBar("stage", term)
    for k in range(1, 11):
        clock.now_s += 0.5
        bar.update(k / 20, "a long stage name that would wrap a narrow terminal " * 2)
    bar.close("done: 3 files, the cause named and the report written")
    frames = term.getvalue().split("\r")[1:]
    term.close()
    assert len(frames) == 1 + 10 + 1
    assert all(len(f) <= 60 for f in frames[:-1])
    assert frames[-1].endswith(", done: 3 files, the cause named and the report written\n")
