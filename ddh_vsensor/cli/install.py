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
import logging
import os
import sys
from pathlib import Path, PurePosixPath

from ddh_vsensor.config import DEFAULT_CONFIG, ConfigError, load_config
from ddh_vsensor.errors import UserError
from ddh_vsensor.cli.config import describe, write_default

log = logging.getLogger(__name__)

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
# What the unit's sandbox hides from the service: an installation there cannot start.
HIDDEN = (("/tmp", "PrivateTmp=yes"), ("/var/tmp", "PrivateTmp=yes"),
          ("/home", "ProtectHome=yes"), ("/root", "ProtectHome=yes"),
          ("/run/user", "ProtectHome=yes"))


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
    p.add_argument("--config", metavar="FILE", default=None,
                   help=f"the machine's configuration to install into --config-dir under its "
                        f"own name (default: the packaged {CONFIG_NAME}); validated first, "
                        "never overwrites a configuration that is there")
    p.add_argument("--force", action="store_true",
                   help="install even where the unit's sandbox hides this installation from "
                        "the service (under /tmp or /home: PrivateTmp=, ProtectHome=)")
    p.set_defaults(func=_run)


def _script() -> Path | None:
    script = Path(sys.executable).parent / "ddh-vsensor"
    return script if script.is_file() and os.access(script, os.X_OK) else None


def service_command() -> str:
    """This installation's ``ddh-vsensor``: the script next to the interpreter, else
    ``python -m ddh_vsensor``."""
    script = _script()
    if script is not None:
        return _unit_word(str(script))
    return f"{_unit_word(sys.executable)} -m ddh_vsensor"


def hidden_by_sandbox(path: str | PurePosixPath) -> str | None:
    """The unit's setting that hides ``path`` from the service, None if it is visible."""
    posix = PurePosixPath(path)
    for base, setting in HIDDEN:
        if posix == PurePosixPath(base) or posix.is_relative_to(base):
            return setting
    return None


def check_visible(force: bool, staged: bool = False) -> None:
    """Refuse an installation the service could not run from: its ``ddh-vsensor`` lies
    where the hardened unit hides it (a venv in /tmp or a home directory). Staged below
    another root (an image, a look at what would be written) it is said, not refused."""
    executable = _script() or Path(sys.executable)
    setting = hidden_by_sandbox(os.path.abspath(executable))
    if setting is None or force:
        return
    problem = (f"{executable}: the unit's {setting} hides this from the service, which could "
               "not start; install ddh-vsensor elsewhere (e.g. a venv in /opt)")
    if staged:
        log.warning("%s before the staged unit is used", problem)
        return
    raise UserError(f"{problem} or give --force")


def unit_description(cfg) -> str:
    """The unit's Description=: the machine's cylinders, named by its configuration."""
    names = list(cfg.unit_names)
    listed = names[0] if len(names) == 1 else f"{', '.join(names[:-1])} and {names[-1]}"
    return (f"ddh-vsensor virtual position sensor on %i (DDH {listed.replace('%', '%%')} "
            f"cylinder{'s' if len(names) > 1 else ''})")


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
                config_dir: PurePosixPath, description: str | None = None) -> str:
    """The shipped unit with this installation's paths and, given, its Description=."""
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
        elif key == "Description" and description is not None:
            line = f"Description={description}"
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


def _write_config(path: Path, source: Path | None) -> str:
    """The packaged default, or ``source``, to ``path`` unless a file is there."""
    if source is None:
        return write_default(path)
    text = source.read_text(encoding="utf-8")
    if path.exists():
        return "unchanged" if path.is_file() and path.read_text(
            encoding="utf-8", errors="replace") == text else "kept"
    return _write_if_changed(path, text)


def install(root: Path, *, prefix: PurePosixPath, unit_dir: PurePosixPath,
            config_dir: PurePosixPath, state_dir: PurePosixPath,
            config: Path | None = None) -> list[str]:
    """Put everything in place; returns one line per step. ``config`` is the machine's
    configuration (default: the packaged one), checked before anything is written. A step
    that cannot be done raises UserError; an existing configuration that does not load is
    reported (every other step done) and raised."""
    cfg = load_config(config)
    config_path = config_dir / (config.name if config is not None else CONFIG_NAME)
    installed = _below(root, config_path)
    if installed.is_file():               # kept: the unit runs the machine's own
        try:
            cfg = load_config(installed)
        except ConfigError:
            pass                          # reported below
    doc_path = prefix / "share" / "doc" / "ddh-vsensor" / "README.md"
    unit = render_unit((DATA / UNIT_NAME).read_text(encoding="utf-8"),
                       command=service_command(), config_path=config_path,
                       doc_path=doc_path, state_dir=state_dir, config_dir=config_dir,
                       description=unit_description(cfg))
    report, invalid = [], None
    try:
        path = _below(root, unit_dir / UNIT_NAME)
        report.append(f"unit    {path}: {_write_if_changed(path, unit)}")
        path = _below(root, doc_path)
        readme = (DATA / "README.md").read_text(encoding="utf-8")
        report.append(f"readme  {path}: {_write_if_changed(path, readme)}")
        path = _below(root, config_path)
        done = _write_config(path, config)
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
    check_visible(args.force, staged=root.resolve() != Path("/"))
    report = install(root, prefix=_absolute("--prefix", args.prefix),
                     unit_dir=_absolute("--unit-dir", args.unit_dir),
                     config_dir=_absolute("--config-dir", args.config_dir),
                     state_dir=_absolute("--state-dir", args.state_dir),
                     config=Path(args.config) if args.config else None)
    for line in report:
        print(line)
    if str(root) == "/":
        print("next: systemctl daemon-reload && systemctl enable --now ddh-vsensor@can0 "
              "(the instance is the SocketCAN interface)")
    return 0
