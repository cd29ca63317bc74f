"""The configuration file read defensively: a bounded regular file, YAML without duplicate
keys, alias bombs or runaway nesting, then validated (every failure a ConfigError)."""

from __future__ import annotations

import os
import stat
from pathlib import Path
from typing import Any

import yaml

from ddh_vsensor.config.errors import ConfigError
from ddh_vsensor.config.schema import DEFAULT_CONFIG, Config
from ddh_vsensor.config.validate import parse_config

MAX_CONFIG_BYTES = 1_000_000     # a machine config is a few kB
MAX_CONFIG_NODES = 100_000       # YAML nodes after alias expansion (a "billion laughs" bomb)
MAX_CONFIG_DEPTH = 50


def _read_bounded(path: Path, source: str) -> str:
    """The file's text, refusing anything but a regular file of at most MAX_CONFIG_BYTES
    (a FIFO or device would block or never end)."""
    try:
        fd = os.open(path, os.O_RDONLY | os.O_NONBLOCK | os.O_CLOEXEC)
    except OSError as exc:
        raise ConfigError(source, "", f"cannot read: {exc.strerror or exc}") from None
    if stat.S_ISDIR(os.fstat(fd).st_mode):          # fdopen refuses it with a traceback
        os.close(fd)
        raise ConfigError(source, "", "a directory, not a configuration file")
    with os.fdopen(fd, "rb") as fh:
        st = os.fstat(fh.fileno())
        if not stat.S_ISREG(st.st_mode):
            raise ConfigError(source, "", "not a regular file")
        raw = fh.read(MAX_CONFIG_BYTES + 1)
    if len(raw) > MAX_CONFIG_BYTES:
        raise ConfigError(source, "", f"larger than {MAX_CONFIG_BYTES} bytes: not a config")
    try:
        return raw.decode("utf-8")
    except UnicodeDecodeError as exc:
        raise ConfigError(source, "", f"not UTF-8 text ({exc.reason} at byte {exc.start})") \
            from None


def _check_unique_keys(node: yaml.MappingNode, source: str) -> None:
    """A key given twice in one mapping is an error: YAML readers keep the last silently, so
    an edit above a forgotten copy would change nothing."""
    first_line: dict[str, int] = {}
    for key, _ in node.value:
        if not isinstance(key, yaml.ScalarNode) or key.tag == "tag:yaml.org,2002:merge":
            continue
        line = key.start_mark.line + 1
        if key.value in first_line:
            raise ConfigError(source, "", f"line {line}: key {key.value!r} given twice (first "
                              f"on line {first_line[key.value]})")
        first_line[key.value] = line


def _check_shape(node: yaml.Node, source: str) -> None:
    """Refuse documents that expand (through aliases) into too many nodes or nest too
    deeply, before anything walks them: counted with memoised sizes, no recursion."""
    size: dict[int, int] = {}
    stack: list[tuple[yaml.Node, int, bool]] = [(node, 1, False)]
    while stack:
        current, depth, children_done = stack.pop()
        if depth > MAX_CONFIG_DEPTH:
            raise ConfigError(source, "", f"nested deeper than {MAX_CONFIG_DEPTH} levels")
        if id(current) in size:
            continue
        if isinstance(current, yaml.SequenceNode):
            children = list(current.value)
        elif isinstance(current, yaml.MappingNode):
            _check_unique_keys(current, source)
            children = [n for pair in current.value for n in pair]
        else:
            size[id(current)] = 1
            continue
        if children_done:
            total = 1 + sum(size.get(id(c), 1) for c in children)
            if total > MAX_CONFIG_NODES:
                raise ConfigError(source, "", f"expands to more than {MAX_CONFIG_NODES} "
                                  "values (aliases): not a config")
            size[id(current)] = total
            continue
        stack.append((current, depth, True))
        stack.extend((c, depth + 1, False) for c in children if id(c) not in size)


def parse_yaml(text: str, source: str) -> Any:
    """``yaml.safe_load`` with the document's size and depth bounded; every failure is a
    ConfigError (never a traceback, however hostile the text)."""
    try:
        node = yaml.compose(text, Loader=yaml.SafeLoader)
        if node is None:
            return None
        _check_shape(node, source)
        return yaml.SafeLoader(text).construct_document(node)
    except ConfigError:
        raise
    except yaml.YAMLError as exc:
        raise ConfigError(source, "", f"not valid YAML: {exc}") from None
    except RecursionError:
        raise ConfigError(source, "", "nested too deeply") from None
    except (MemoryError, ValueError, TypeError, OverflowError) as exc:
        raise ConfigError(source, "", f"cannot be read as YAML: {type(exc).__name__}") \
            from None


def load_config(path: str | Path | None = None) -> Config:
    """Load and validate a config file; ``None`` loads the embedded reference machine."""
    path = Path(path) if path is not None else DEFAULT_CONFIG
    source = str(path)
    data = parse_yaml(_read_bounded(path, source), source)
    try:
        return parse_config(data, source)
    except RecursionError:
        raise ConfigError(source, "", "nested too deeply") from None
