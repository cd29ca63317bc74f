"""The README's commands run as written, from a fresh clone.

Every fenced ``bash``/``sh``/``console`` block is run line by line in a temporary directory that
holds the repository's files (as a clone has them), in order, so a later block finds what an
earlier one wrote (a command that replays in real time and writes nothing a later one reads,
:data:`IN_BACKGROUND`, alongside the commands after it). A block that cannot run here
(systemd, root, a real CAN interface, the test suite itself) says so in an HTML comment on the
line before it: ``<!-- not run in tests: why -->``.
"""

from __future__ import annotations

import json
import os
import re
import subprocess
import sys
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path
from typing import IO

import pytest

REPO = Path(__file__).resolve().parents[2]
README = REPO / "README.md"
NOT_RUN = re.compile(r"^<!-- not run in tests: (.+\S) -->$")
FENCE = re.compile(r"^```(\w*)\s*$")
SHELLS = ("bash", "sh", "console")
COMMAND_TIMEOUT_S = 120
# Commands that replay in real time, mostly waiting on the clock, and write nothing a later
# command reads (the demo: its figure): each starts in the background where the README has
# it, the commands after it run meanwhile, and it is awaited and judged at the end.
IN_BACKGROUND = ("ddh-vsensor demo ",)


@dataclass
class Block:
    line: int                  # 1-based line of the opening fence
    lang: str
    commands: list[str]
    not_run: str | None        # the reason given, or None: the block is run


def blocks(text: str) -> list[Block]:
    """The README's shell blocks, each with its commands (continuations joined; ``$ `` lines
    only in console blocks) and the not-run reason on the line before it, if any."""
    lines = text.splitlines()
    out, i = [], 0
    while i < len(lines):
        m = FENCE.match(lines[i])
        if not m:
            i += 1
            continue
        start, lang, body = i, m.group(1), []
        i += 1
        while i < len(lines) and not lines[i].startswith("```"):
            body.append(lines[i])
            i += 1
        i += 1
        if lang not in SHELLS:
            continue
        if lang == "console":
            body = [b[2:] for b in body if b.startswith("$ ")]
        commands, pending = [], ""
        for raw in body:
            if raw.rstrip().endswith("\\"):
                pending += raw.strip()[:-1].strip() + " "
                continue
            command = (pending + raw.strip()).strip()
            pending = ""
            if command and not command.startswith("#"):
                commands.append(command)
        prev = next((lines[j] for j in range(start - 1, -1, -1) if lines[j].strip()), "")
        reason = NOT_RUN.match(prev.strip())
        out.append(Block(start + 1, lang, commands, reason.group(1) if reason else None))
    return out


def _clone_like(dest: Path) -> None:
    """The files a fresh clone has (tracked, or new and not ignored), linked into dest."""
    listed = subprocess.run(["git", "ls-files", "-co", "--exclude-standard"], cwd=REPO,
                            capture_output=True, text=True, check=True).stdout.split()
    for top in sorted({p.split("/", 1)[0] for p in listed}):
        if (REPO / top).exists():
            (dest / top).symlink_to(REPO / top)


def _env() -> dict[str, str]:
    env = dict(os.environ)
    env["PATH"] = f"{Path(sys.executable).parent}{os.pathsep}{env.get('PATH', '')}"
    env["MPLBACKEND"] = "Agg"
    return env


README_BLOCKS = blocks(README.read_text(encoding="utf-8"))


def test_readme_has_runnable_blocks_and_every_skip_says_why():
    run = [b for b in README_BLOCKS if b.not_run is None]
    assert len(run) >= 6, [b.line for b in run]
    assert all(b.commands for b in README_BLOCKS)
    for b in README_BLOCKS:
        assert b.not_run is None or len(b.not_run) > 10, (b.line, b.not_run)


@dataclass
class Background:
    """A command of :data:`IN_BACKGROUND` running, its output going to files (a pipe left
    unread could fill and stall it)."""
    line: int
    command: str
    proc: subprocess.Popen
    out: IO[str]
    err: IO[str]
    started_s: float


def _failure(line: int, command: str, code: int, out: str, err: str) -> str:
    return f"README line {line}: {command}: exit {code}\n{out[-1500:]}{err[-1500:]}"


def test_every_unmarked_readme_command_runs(tmp_path: Path):
    """Each command of each unmarked block exits 0 (run in order, one directory; those of
    :data:`IN_BACKGROUND` alongside the commands after them)."""
    _clone_like(tmp_path)
    env = _env()
    ran, failed = 0, []
    background: list[Background] = []
    try:
        for block in README_BLOCKS:
            if block.not_run is not None:
                continue
            for command in block.commands:
                if command.startswith(IN_BACKGROUND):
                    out, err = tempfile.TemporaryFile("w+"), tempfile.TemporaryFile("w+")
                    proc = subprocess.Popen(["bash", "-o", "pipefail", "-c", command],
                                            cwd=tmp_path, env=env, stdout=out, stderr=err,
                                            text=True, stdin=subprocess.DEVNULL)
                    background.append(Background(block.line, command, proc, out, err,
                                                 time.monotonic()))
                    continue
                try:
                    done = subprocess.run(["bash", "-o", "pipefail", "-c", command],
                                          check=False, cwd=tmp_path,
                                          env=env, capture_output=True, text=True,
                                          stdin=subprocess.DEVNULL, timeout=COMMAND_TIMEOUT_S)
                except subprocess.TimeoutExpired:
                    failed.append(f"README line {block.line}: {command}: timed out")
                    continue
                ran += 1
                if done.returncode != 0:
                    failed.append(_failure(block.line, command, done.returncode, done.stdout,
                                           done.stderr))
        for b in background:
            try:
                b.proc.wait(max(0.0, b.started_s + COMMAND_TIMEOUT_S - time.monotonic()))
            except subprocess.TimeoutExpired:
                failed.append(f"README line {b.line}: {b.command}: timed out")
                continue
            ran += 1
            if b.proc.returncode != 0:
                b.out.seek(0)
                b.err.seek(0)
                failed.append(_failure(b.line, b.command, b.proc.returncode, b.out.read(),
                                       b.err.read()))
    finally:
        for b in background:
            if b.proc.poll() is None:
                b.proc.kill()
                b.proc.wait()
            b.out.close()
            b.err.close()
    assert len(background) == len(IN_BACKGROUND)
    assert not failed, "\n\n".join(failed)
    assert ran >= 15


def test_readme_test_command_is_what_ci_runs():
    ci = (REPO / ".ci" / "run").read_text(encoding="utf-8")
    test_blocks = [b for b in README_BLOCKS if any("pytest" in c for c in b.commands)]
    assert len(test_blocks) == 1
    (command,) = test_blocks[0].commands
    assert command == 'pip install -e ".[test]" && python -m pytest -q -n 2 --dist loadfile'
    assert command in [line.strip() for line in ci.splitlines()]


def test_readme_is_short_and_undated():
    text = README.read_text(encoding="utf-8")
    assert len(text.splitlines()) <= 250
    months = r"\b(Jan|Feb|Mar|Apr|May|Jun|Jul|Aug|Sep|Oct|Nov|Dec)\b"
    assert not re.search(months, text)
    assert not re.search(r"\b20\d\d-\d\d-\d\d\b", text)
    assert "shared/" not in text
    assert not re.search(r"\bissue \d+|#\d+\b", text)


def test_readme_accuracy_figure_is_the_benchmarks():
    """The one figure the README states is the accuracy bench's, as committed."""
    figures = json.loads((REPO / "bench" / "results" / "accuracy.json").read_text())["figures"]
    text = README.read_text(encoding="utf-8")
    line = next(l for l in text.splitlines() if l.startswith("**Accuracy:**"))
    expected = (f"**{figures['dynamic_boom_worst_max_abs_error_mm']} mm (boom) / "
                f"{figures['dynamic_bucket_worst_max_abs_error_mm']} mm (bucket)** in the "
                f"default `dynamic` mode, against {figures['paper_boom_worst_max_abs_error_mm']}"
                f" / {figures['paper_bucket_worst_max_abs_error_mm']} mm")
    assert expected in line
    assert "(docs/accuracy.md)" in line


@pytest.mark.parametrize("text, expected", [
    ("x\n<!-- not run in tests: needs systemd -->\n```bash\na \\\n  b\n# c\nd\n```\n",
     [Block(3, "bash", ["a b", "d"], "needs systemd")]),
    ("```console\n$ ls\nout\n```\n```python\nx\n```\n", [Block(1, "console", ["ls"], None)]),
])
def test_block_parser(text: str, expected: list[Block]):
    assert blocks(text) == expected
