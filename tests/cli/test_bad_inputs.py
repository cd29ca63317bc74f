"""Every file or directory a subcommand reads or writes, given badly: missing, empty, cut
short, of the other actuator or a wrong value, unwritable, of the wrong type (a directory
for a file, a file for a directory, binary bytes for text). Each gives exactly one line on
stderr and exit 2, never a traceback. The slots are found from the parser (as test_help.py
finds the commands): a new file option without a row here fails the completeness test."""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

from ddh_vsensor.cli.main import build_parser, main

REPO = Path(__file__).resolve().parents[2]
UNWRITABLE = Path("/sys")                     # refuses new files and directories, even root's
pytestmark = pytest.mark.skipif(not UNWRITABLE.is_dir(), reason="needs /sys")

BUS = ["--interface", "virtual", "--channel", "bad-inputs"]
# (command, option) -> (kind of path, the rest of a command line that is valid otherwise;
# "SLOT" is where the bad path goes, RUN a valid measured run, LOG a valid BLF)
SLOTS: dict[tuple[str, str], tuple[str, list[str]]] = {
    ("tables build", "--config"): ("yaml", ["tables", "build", "--config", "SLOT", "--out",
                                            "OUT/tables"]),
    ("tables build", "--out"): ("out-dir", ["tables", "build", "--out", "SLOT"]),
    ("tables plot", "--config"): ("yaml", ["tables", "plot", "--config", "SLOT", "--out",
                                           "OUT/f.png"]),
    ("tables plot", "--tables"): ("in-dir", ["tables", "plot", "--tables", "SLOT", "--out",
                                             "OUT/f.png"]),
    ("tables plot", "--out"): ("out-file", ["tables", "plot", "--tables", "TABLES", "--out",
                                            "SLOT"]),
    ("steady", "--config"): ("yaml", ["steady", "--config", "SLOT", "--actuator", "boom",
                                      "--speed-rpm", "100", "--oil-temp-c", "40"]),
    ("simulate", "--config"): ("yaml", ["simulate", "--config", "SLOT", "--cycle", "work",
                                        "--payload-kg", "0", "--oil-temp-c", "40", "--out",
                                        "OUT/sim"]),
    ("simulate", "--cycle"): ("profile", ["simulate", "--cycle", "SLOT", "--payload-kg", "0",
                                          "--oil-temp-c", "40", "--out", "OUT/sim"]),
    ("simulate", "--out"): ("out-dir", ["simulate", "--cycle", "work", "--payload-kg", "0",
                                        "--oil-temp-c", "40", "--out", "SLOT"]),
    ("estimate", "run"): ("run", ["estimate", "SLOT", "--actuator", "boom"]),
    ("estimate", "--config"): ("yaml", ["estimate", "RUN", "--config", "SLOT", "--actuator",
                                        "boom"]),
    ("estimate", "--tables"): ("in-dir", ["estimate", "RUN", "--actuator", "boom", "--tables",
                                          "SLOT"]),
    ("estimate", "--extension"): ("extension", ["estimate", "RUN", "--actuator", "boom",
                                                "--extension", "SLOT"]),
    ("estimate", "--out"): ("out-file", ["estimate", "RUN", "--actuator", "boom", "--out",
                                         "SLOT"]),
    ("estimate", "--plot"): ("out-file", ["estimate", "RUN", "--actuator", "boom", "--plot",
                                          "SLOT"]),
    ("analyze", "runs"): ("run", ["analyze", "RUN", "SLOT", "--actuator", "boom", "--report",
                                  "OUT/rep"]),
    ("analyze", "--config"): ("yaml", ["analyze", "RUN", "RUN", "--config", "SLOT",
                                       "--actuator", "boom", "--report", "OUT/rep"]),
    ("analyze", "--baseline"): ("baseline", ["analyze", "RUN", "RUN", "--actuator", "boom",
                                             "--report", "OUT/rep", "--baseline", "SLOT"]),
    ("commission", "--baseline"): ("out-file", ["commission", "RUN", "--config", "YAML", "--out",
                                                "OUT/c.yaml", "--baseline", "SLOT"]),
    ("analyze", "--report"): ("out-dir", ["analyze", "RUN", "RUN", "--actuator", "boom",
                                          "--report", "SLOT"]),
    ("run", "--config"): ("yaml", ["run", *BUS, "--no-state", "--config", "SLOT"]),
    ("run", "--tables"): ("in-dir", ["run", *BUS, "--no-state", "--tables", "SLOT"]),
    ("run", "--state-dir"): ("out-dir", ["run", *BUS, "--state-dir", "SLOT"]),
    ("run", "--extension"): ("extensions", ["run", *BUS, "--no-state", "--extension", "SLOT"]),
    ("replay", "log"): ("log", ["replay", "SLOT", *BUS, "--rate", "0"]),
    ("replay", "--config"): ("yaml", ["replay", "LOG", *BUS, "--rate", "0", "--config",
                                      "SLOT"]),
    ("monitor", "--config"): ("yaml", ["monitor", "--log", "LOG", "--config", "SLOT"]),
    ("monitor", "--log"): ("log", ["monitor", "--log", "SLOT"]),
    ("status", "--config"): ("yaml", ["status", *BUS, "--config", "SLOT"]),
    ("demo", "--config"): ("yaml", ["demo", "--no-figure", "--config", "SLOT"]),
    ("demo", "--extension"): ("extensions", ["demo", "--no-figure", "--extension", "SLOT"]),
    ("demo", "--figure"): ("out-png", ["demo", "--figure", "SLOT"]),   # makes its directory
    ("config", "--validate"): ("yaml", ["config", "--validate", "SLOT"]),
    ("config", "--json-schema"): ("out-file", ["config", "--json-schema", "SLOT"]),
    ("config", "--write"): ("out-file-made", ["config", "--write", "SLOT"]),
    ("install", "--root"): ("out-dir", ["install", "--root", "SLOT"]),
    ("install", "--config"): ("yaml", ["install", "--root", "OUT/root", "--config", "SLOT"]),
    ("fleet ingest", "logs"): ("fleet-log", ["fleet", "ingest", "SLOT", "--store",
                                             "OUT/store"]),
    ("fleet ingest", "--store"): ("out-dir", ["fleet", "ingest", "LOG", "--store", "SLOT"]),
    ("fleet ingest", "--config"): ("yaml", ["fleet", "ingest", "LOG", "--store", "OUT/store",
                                            "--config", "SLOT"]),
    ("fleet report", "--store"): ("in-dir", ["fleet", "report", "--store", "SLOT", "--out",
                                             "OUT/r.html"]),
    ("fleet report", "--out"): ("out-file", ["fleet", "report", "--store", "OUT", "--out",
                                             "SLOT"]),
    ("fleet report", "--config"): ("yaml", ["fleet", "report", "--store", "OUT", "--out",
                                            "OUT/r.html", "--config", "SLOT"]),
    ("simulate-fleet", "--out"): ("out-dir", ["simulate", "fleet", "--machines", "1", "--days",
                                              "2", "--out", "SLOT"]),
    ("simulate-fleet", "--config"): ("yaml", ["simulate", "fleet", "--machines", "1", "--days",
                                              "2", "--out", "OUT/f", "--config", "SLOT"]),
    ("dbc", "--config"): ("yaml", ["dbc", "--config", "SLOT", "--out", "OUT/x.dbc"]),
    ("dbc", "--out"): ("out-file", ["dbc", "--out", "SLOT"]),
    ("eds", "--config"): ("yaml", ["eds", "--config", "SLOT", "--unit", "boom", "--out",
                                   "OUT/x.eds"]),
    ("eds", "--out"): ("out-file", ["eds", "--unit", "boom", "--out", "SLOT"]),
    ("commission", "runs"): ("run", ["commission", "SLOT", "--config", "YAML", "--out",
                                     "OUT/c.yaml", "--actuator", "boom"]),
    ("commission", "--config"): ("yaml", ["commission", "RUN", "--config", "SLOT", "--out",
                                          "OUT/c.yaml"]),
    ("commission", "--out"): ("out-file", ["commission", "RUN", "--config", "YAML", "--out",
                                           "SLOT"]),
    ("status", "--state-dir"): ("state-dir", ["status", *BUS, "--state-dir", "SLOT"]),
    ("commission", "--report"): ("out-dir", ["commission", "RUN", "--config", "YAML", "--out",
                                             "OUT/c.yaml", "--report", "SLOT"]),
}
# Paths that name places on the target system, not files on this one.
NOT_FILES = {("install", o) for o in ("--prefix", "--unit-dir", "--config-dir", "--state-dir")}
FILEISH = ("FILE", "DIR", "RUN", "LOG", "PATH", ".csv")
# `run` serves until stopped once its inputs are good: a missed check would hang in-process
SUBPROCESS = {"run"}

BINARY = bytes(range(256)) * 8


def _bad_inputs(kind: str, tmp: Path, good: dict[str, Path]) -> dict[str, Path]:
    """The bad paths for one kind of slot, by name."""
    out: dict[str, Path] = {}
    directory = tmp / "a_directory.d"
    directory.mkdir(exist_ok=True)
    binary = tmp / "binary"
    if kind in ("yaml", "run", "log", "fleet-log", "extension", "extensions", "profile",
                "baseline"):
        suffix = {"yaml": ".yaml", "run": ".csv", "log": ".blf", "fleet-log": ".blf",
                  "extension": ".json", "extensions": ".json", "profile": ".csv",
                  "baseline": ".json"}[kind]
        out["missing"] = tmp / f"missing{suffix}"
        out["empty"] = tmp / f"empty{suffix}"
        out["empty"].write_bytes(b"")
        out["binary"] = binary.with_suffix(suffix)
        out["binary"].write_bytes(BINARY)
        if kind != "fleet-log":                   # a directory of logs is an input there
            out["directory"] = tmp / f"a_directory{suffix}"
            out["directory"].mkdir(exist_ok=True)
        source = {"yaml": good["yaml"], "run": good["run"], "log": good["log"],
                  "fleet-log": good["log"], "extension": good["extension"],
                  "extensions": good["extension"], "profile": good["profile"],
                  "baseline": good["extension"]}[kind]
        raw = source.read_bytes()
        out["truncated"] = tmp / f"truncated{suffix}"
        # cut a few bytes into a line past the middle: a file cut off, not a shorter whole one
        out["truncated"].write_bytes(raw[:300] if kind in ("log", "fleet-log")
                                     else raw[:raw.find(b"\n", len(raw) // 2) + 4])
        wrong = tmp / f"wrong{suffix}"
        if kind == "yaml":
            text = good["yaml"].read_text().replace("stroke_mm: ", "stroke_mm: -", 1)
            wrong.write_text(text)
        elif kind == "run":
            wrong = good["bucket_run"]
        elif kind == "extension":
            wrong = good["bucket_extension"]
        elif kind == "baseline":
            wrong = good["extension"]                 # a JSON, not a baseline
        elif kind == "profile":
            wrong.write_text("time_s,arm_mm\n0,10\n1,20\n")
        else:
            wrong.write_bytes(good["run"].read_bytes())      # a CSV where a BLF belongs
        out["wrong"] = wrong
    elif kind == "state-dir":
        out["missing"] = tmp / "no_such_dir"
        out["file"] = binary
        binary.write_bytes(BINARY)
    elif kind == "in-dir":
        out["missing"] = tmp / "no_such_dir"
        out["empty"] = tmp / "empty_dir"
        out["empty"].mkdir(exist_ok=True)
        out["file"] = binary
        binary.write_bytes(BINARY)
    elif kind in ("out-file", "out-png", "out-file-made"):
        name = "x.png" if kind == "out-png" else "x.out"
        out["unwritable"] = UNWRITABLE / name
        out["no parent"] = tmp / "no_such_dir" / name
        out["directory"] = directory
    elif kind == "out-dir":
        out["unwritable"] = UNWRITABLE / "ddh-out"
        out["file"] = binary
        binary.write_bytes(BINARY)
    return out


@pytest.fixture(scope="module")
def good(tmp_path_factory) -> dict[str, Path]:
    """Valid inputs to build command lines around the bad one."""
    base = tmp_path_factory.mktemp("good")
    assert main(["-q", "simulate", "--cycle", "work", "--payload-kg", "0", "--oil-temp-c", "40",
                 "--out", str(base / "runs")]) == 0
    assert main(["-q", "tables", "build", "--out", str(base / "tables")]) == 0
    assert main(["-q", "analyze", str(base / "runs" / "bucket.csv"),
                 str(base / "runs" / "bucket.csv"), "--actuator", "bucket", "--report",
                 str(base / "rep")]) == 0
    extension = json.loads((base / "rep" / "extension.json").read_text())
    assert extension["actuator"] == "bucket"
    profile = base / "profile.csv"
    profile.write_text("time_s,boom_mm,bucket_mm\n0,10,300\n10,200,400\n")
    return {"yaml": REPO / "config" / "loader.yaml", "run": base / "runs" / "boom.csv",
            "bucket_run": base / "runs" / "bucket.csv", "log": base / "runs" / "run.blf",
            "tables": base / "tables", "extension": base / "rep" / "extension.json",
            "bucket_extension": base / "rep" / "extension.json", "profile": profile}


def _slots() -> set[tuple[str, str]]:
    """Every (command, option) of the parser whose value names a file or directory."""
    found = set()

    def walk(parser: argparse.ArgumentParser, prefix: tuple[str, ...]) -> None:
        for action in parser._actions:                          # noqa: SLF001
            if isinstance(action, argparse._SubParsersAction):   # noqa: SLF001
                for name, sub in action.choices.items():
                    walk(sub, (*prefix, name))
            elif action.metavar and any(w in action.metavar for w in FILEISH):
                found.add((" ".join(prefix), action.option_strings[0] if action.option_strings
                           else action.dest))
    walk(build_parser(), ())
    return found


def test_every_file_option_of_the_parser_has_a_row() -> None:
    assert _slots() - NOT_FILES == set(SLOTS), (_slots() - NOT_FILES) ^ set(SLOTS)


CASES = [(slot, bad) for slot, (kind, _) in SLOTS.items()
         for bad in {"yaml": ("missing", "empty", "truncated", "wrong", "directory", "binary"),
                     "run": ("missing", "empty", "truncated", "wrong", "directory", "binary"),
                     "log": ("missing", "empty", "truncated", "wrong", "directory", "binary"),
                     "fleet-log": ("missing",),
                     "extension": ("missing", "empty", "truncated", "wrong", "directory",
                                   "binary"),
                     "baseline": ("missing", "empty", "truncated", "wrong", "directory",
                                  "binary"),
                     # one file per actuator: the bucket's is right for these commands
                     "extensions": ("missing", "empty", "truncated", "directory", "binary"),
                     "profile": ("missing", "empty", "truncated", "wrong", "directory",
                                 "binary"),
                     "in-dir": ("missing", "empty", "file"),
                     # the service's state directory: empty until its first save
                     "state-dir": ("missing", "file"),
                     "out-file": ("unwritable", "no parent", "directory"),
                     # the tools that make the file's directory
                     "out-png": ("unwritable", "directory"),
                     "out-file-made": ("unwritable", "directory"),
                     "out-dir": ("unwritable", "file")}[kind]]


def _argv(slot: tuple[str, str], bad: str, good: dict[str, Path], tmp: Path) -> list[str]:
    kind, template = SLOTS[slot]
    path = _bad_inputs(kind, tmp, good)[bad]
    fills = {"SLOT": str(path), "RUN": str(good["run"]), "LOG": str(good["log"]),
             "TABLES": str(good["tables"]), "YAML": str(good["yaml"])}
    out = []
    for word in template:
        word = fills.get(word, word)
        out.append(word.replace("OUT", str(tmp)) if word.startswith("OUT") else word)
    return out


@pytest.mark.parametrize("slot, bad", CASES, ids=[f"{s[0]} {s[1]}: {b}" for s, b in CASES])
def test_a_bad_path_is_one_line_and_exit_2(slot: tuple[str, str], bad: str,
                                           good: dict[str, Path], tmp_path: Path,
                                           monkeypatch, capsys) -> None:
    argv = _argv(slot, bad, good, tmp_path)
    if slot[0] in SUBPROCESS:
        result = subprocess.run([sys.executable, "-m", "ddh_vsensor", *argv],
                                capture_output=True, text=True, timeout=120,
                                env={**os.environ, "PYTHONWARNINGS": "ignore"})
        code, err = result.returncode, result.stderr
    else:
        # install questions a venv the unit's sandbox hides; here the path under test counts
        # (install only: multiprocessing starts its resource tracker from sys.executable)
        if slot[0] == "install":
            monkeypatch.setattr(sys, "executable", "/opt/ddh-vsensor/bin/python")
        code = main(argv)
        err = capsys.readouterr().err
    assert code == 2, (argv, err)
    lines = err.splitlines()
    assert len(lines) == 1 and "Traceback" not in err, (argv, err)
    assert lines[0].startswith("ddh-vsensor "), lines


@pytest.mark.parametrize("argv", [
    ["estimate", "EMPTY", "--actuator", "boom"],
    ["monitor", "--log", "EMPTY_BLF"],
    ["tables", "build", "--out", "/sys/ddh-tables"],
])
def test_no_traceback_reaches_stderr_of_the_process(argv: list[str], tmp_path: Path) -> None:
    (tmp_path / "empty.csv").write_bytes(b"")
    (tmp_path / "empty.blf").write_bytes(b"")
    argv = [{"EMPTY": str(tmp_path / "empty.csv"),
             "EMPTY_BLF": str(tmp_path / "empty.blf")}.get(a, a) for a in argv]
    result = subprocess.run([sys.executable, "-m", "ddh_vsensor", *argv], capture_output=True,
                            text=True, timeout=120)
    assert result.returncode == 2, result.stderr
    assert len(result.stderr.splitlines()) == 1 and "Traceback" not in result.stderr
