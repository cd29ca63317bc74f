"""``ddh-vsensor install``: the systemd unit, the machine's configuration, the README and the
state directory put in place from the installed package.

Idempotent: files equal to what would be written are left alone, the unit is rewritten when it
differs (it is generated: local changes belong in a drop-in, ``systemctl edit``), and an
existing configuration is never overwritten (it is the machine's; it is validated instead).
Every step is reported on one line. ``--root`` installs into a staging tree (as DESTDIR does):
the files go below it, the paths written into the unit do not include it.
"""

from __future__ import annotations

import argparse
import os
import sys
from pathlib import Path, PurePosixPath

from ddh_vsensor.config import DEFAULT_CONFIG, ConfigError, load_config
from ddh_vsensor.errors import UserError
from ddh_vsensor.cli.config import describe, write_default

DATA = DEFAULT_CONFIG.parent
UNIT_NAME = "ddh-vsensor@.service"
CONFIG_NAME = "loader.yaml"
# Paths in the shipped unit that this command replaces with the installation's own.
SHIPPED_EXEC = "/opt/ddh-vsensor/bin/ddh-vsensor"
SHIPPED_CONFIG = "/etc/ddh-vsensor/loader.yaml"

DEFAULT_UNIT_DIR = "/etc/systemd/system"
DEFAULT_CONFIG_DIR = "/etc/ddh-vsensor"
DEFAULT_STATE_DIR = "/var/lib/ddh-vsensor"
DEFAULT_PREFIX = "/usr/local"
STATE_BASE = PurePosixPath("/var/lib")      # systemd's StateDirectory= is relative to it
CONFIG_BASE = PurePosixPath("/etc")         # ... and ConfigurationDirectory= to this


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "install", help="put the systemd unit, config and state directory in place",
        description="Installs ddh-vsensor@.service (instance = SocketCAN interface: "
        "systemctl enable --now ddh-vsensor@can0), the default configuration unless one is "
        "there, the README the unit's Documentation= points to, and the state directory. "
        "Safe to run again: it says what it did and never overwrites a configuration. It "
        "does not run systemctl.")
    p.add_argument("--root", metavar="DIR", default="/",
                   help="install below DIR (a staging tree or an image; default /)")
    p.add_argument("--prefix", metavar="DIR", default=DEFAULT_PREFIX,
                   help=f"documentation goes to PREFIX/share/doc/ddh-vsensor (default "
                        f"{DEFAULT_PREFIX})")
    p.add_argument("--unit-dir", metavar="DIR", default=DEFAULT_UNIT_DIR,
                   help=f"default {DEFAULT_UNIT_DIR}")
    p.add_argument("--config-dir", metavar="DIR", default=DEFAULT_CONFIG_DIR,
                   help=f"where {CONFIG_NAME} goes (default {DEFAULT_CONFIG_DIR})")
    p.add_argument("--state-dir", metavar="DIR", default=DEFAULT_STATE_DIR,
                   help=f"persisted estimates, below {STATE_BASE} as systemd's StateDirectory= "
                        f"requires (default {DEFAULT_STATE_DIR})")
    p.set_defaults(func=_run)


def service_command() -> str:
    """This installation's ``ddh-vsensor``: the script next to the interpreter, else
    ``python -m ddh_vsensor``."""
    script = Path(sys.executable).parent / "ddh-vsensor"
    if script.is_file() and os.access(script, os.X_OK):
        return _unit_word(str(script))
    return f"{_unit_word(sys.executable)} -m ddh_vsensor"


def _unit_word(text: str) -> str:
    text = text.replace("%", "%%")          # unit files expand % specifiers
    return f'"{text}"' if any(c.isspace() for c in text) else text


def _absolute(option: str, value: str) -> PurePosixPath:
    path = PurePosixPath(value)
    if not path.is_absolute():
        raise UserError(f"{option} {value}: must be an absolute path")
    return path


def _relative(option: str, path: PurePosixPath, base: PurePosixPath) -> str:
    try:
        rel = path.relative_to(base)
    except ValueError:
        raise UserError(f"{option} {path}: must be below {base} (systemd manages it "
                        f"there)") from None
    if str(rel) == ".":
        raise UserError(f"{option} {path}: must be a directory below {base}, not {base}")
    return str(rel)


def render_unit(template: str, *, command: str, config_path: PurePosixPath,
                doc_path: PurePosixPath, state_dir: PurePosixPath,
                config_dir: PurePosixPath) -> str:
    """The shipped unit with this installation's paths."""
    state_rel = _relative("--state-dir", state_dir, STATE_BASE)
    try:
        config_rel: str | None = _relative("--config-dir", config_dir, CONFIG_BASE)
    except UserError:
        config_rel = None          # elsewhere: readable all the same (ProtectSystem=strict)
    seen: set[str] = set()
    out = []
    for line in template.splitlines():
        key = line.split("=", 1)[0] if "=" in line and not line.startswith("#") else ""
        if key == "ExecStart":
            if SHIPPED_EXEC not in line or SHIPPED_CONFIG not in line:
                raise RuntimeError(f"the shipped unit's ExecStart changed: {line}")
            line = line.replace(SHIPPED_EXEC, command).replace(
                SHIPPED_CONFIG, _unit_word(str(config_path)))
        elif key == "Documentation":
            line = f"Documentation=file://{_unit_word(str(doc_path))}"
        elif key == "StateDirectory":
            line = f"StateDirectory={state_rel}"
        elif key == "ConfigurationDirectory":
            if config_rel is None:
                continue
            line = f"ConfigurationDirectory={config_rel}"
        seen.add(key)
        out.append(line)
    missing = {"ExecStart", "Documentation", "StateDirectory"} - seen
    if missing:
        raise RuntimeError(f"the shipped unit lacks {', '.join(sorted(missing))}")
    return "\n".join(out) + "\n"


def _write_if_changed(path: Path, text: str, mode: int = 0o644) -> str:
    if path.is_file() and path.read_text(encoding="utf-8", errors="replace") == text:
        return "unchanged"
    existed = path.exists()
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(path.name + ".tmp")
    tmp.write_text(text, encoding="utf-8")
    tmp.chmod(mode)
    tmp.replace(path)
    return "updated" if existed else "written"


def _below(root: Path, path: PurePosixPath) -> Path:
    return root / str(path).lstrip("/")


def install(root: Path, *, prefix: PurePosixPath, unit_dir: PurePosixPath,
            config_dir: PurePosixPath, state_dir: PurePosixPath) -> list[str]:
    """Put everything in place; returns one line per step. A step that cannot be done raises
    UserError; an existing configuration that does not load is reported (every other step
    done) and raised."""
    config_path = config_dir / CONFIG_NAME
    doc_path = prefix / "share" / "doc" / "ddh-vsensor" / "README.md"
    unit = render_unit((DATA / UNIT_NAME).read_text(encoding="utf-8"),
                       command=service_command(), config_path=config_path,
                       doc_path=doc_path, state_dir=state_dir, config_dir=config_dir)
    report, invalid = [], None
    try:
        path = _below(root, unit_dir / UNIT_NAME)
        report.append(f"unit    {path}: {_write_if_changed(path, unit)}")
        path = _below(root, doc_path)
        readme = (DATA / "README.md").read_text(encoding="utf-8")
        report.append(f"readme  {path}: {_write_if_changed(path, readme)}")
        path = _below(root, config_path)
        done = write_default(path)
        if done == "kept":
            try:
                done = f"kept (differs from the default; valid: {describe(load_config(path))})"
            except ConfigError as exc:
                invalid, done = exc, "kept (differs from the default; NOT VALID, see below)"
        report.append(f"config  {path}: {done}")
        path = _below(root, state_dir)
        existed = path.is_dir()
        path.mkdir(mode=0o700, parents=True, exist_ok=True)
        report.append(f"state   {path}: {'exists' if existed else 'created'}")
    except OSError as exc:
        raise UserError(f"cannot install: {exc.filename or ''}: {exc.strerror or exc}") from None
    if invalid is not None:
        for line in report:
            print(line)
        raise invalid
    return report


def _run(args: argparse.Namespace) -> int:
    root = Path(args.root)
    report = install(root, prefix=_absolute("--prefix", args.prefix),
                     unit_dir=_absolute("--unit-dir", args.unit_dir),
                     config_dir=_absolute("--config-dir", args.config_dir),
                     state_dir=_absolute("--state-dir", args.state_dir))
    for line in report:
        print(line)
    if str(root) == "/":
        print("next: systemctl daemon-reload && systemctl enable --now ddh-vsensor@can0 "
              "(the instance is the SocketCAN interface)")
    return 0
