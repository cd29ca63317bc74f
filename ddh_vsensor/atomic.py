"""Output files that are either wholly old or wholly new: write a temp file beside the target,
fsync, rename over it, fsync the directory. A crash or power cut mid-write leaves the old
file, and a kill may leave a temp file behind: :func:`remove_temp_files` clears those at the
next start. Also the checks that an output directory or file can be written, made before
the work that produces it."""

from __future__ import annotations

import glob
import os
import tempfile
import uuid
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import IO

from ddh_vsensor.errors import UserError


def _fsync_dir(directory: Path) -> None:
    fd = os.open(directory, os.O_RDONLY)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)


def _temp_name(path: Path) -> Path:
    return path.with_name(f".{path.name}.{uuid.uuid4().hex[:8]}.tmp")


def remove_temp_files(path: str | Path) -> list[Path]:
    """Delete the temp files an interrupted atomic write of ``path`` left behind (only
    names of the form this module writes; symlinks are removed, never followed)."""
    path = Path(path)
    removed = []
    try:
        candidates = list(path.parent.glob(f".{glob.escape(path.name)}.*.tmp"))
    except OSError:
        return removed
    for tmp in candidates:
        if len(tmp.name) != len(path.name) + 14:          # "." + name + ".xxxxxxxx.tmp"
            continue
        try:
            tmp.unlink()
            removed.append(tmp)
        except (IsADirectoryError, PermissionError, OSError):
            continue
    return removed


@contextmanager
def atomic_path(path: str | Path) -> Iterator[Path]:
    """A temporary path for a writer that opens the file itself; it replaces ``path`` (made
    durable) only if the block succeeds."""
    path = Path(path)
    tmp = _temp_name(path)
    try:
        yield tmp
        with open(tmp, "rb+") as fh:
            os.fsync(fh.fileno())
        os.replace(tmp, path)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise
    _fsync_dir(path.parent)


@contextmanager
def atomic_write(path: str | Path, mode: str = "w") -> Iterator[IO]:
    """An open temporary file (``"w"`` text UTF-8, or ``"wb"``) that atomically becomes
    ``path`` when the block succeeds."""
    with atomic_path(path) as tmp:
        encoding = None if "b" in mode else "utf-8"
        with open(tmp, mode, encoding=encoding, newline=None if encoding is None else "\n") as fh:
            yield fh


def _probe(directory: Path, out: Path, what: str) -> None:
    """Create and delete a file in ``directory``: the only sure test that writing there
    works (permissions, read-only mounts, root's override of mode bits)."""
    try:
        tempfile.TemporaryFile(dir=directory, prefix=".ddh-vsensor-probe-").close()
    except OSError as exc:
        raise UserError(f"{out}: cannot write the {what} in {directory}: "
                        f"{exc.strerror or exc}") from None


def output_dir(path: str | Path, what: str = "output directory", create: bool = True) -> Path:
    """Create a directory for output and check it can be written (early, so a bad path
    fails before long work). ``create=False`` checks only, where a later check of the other
    inputs must leave nothing behind: the directory, or the nearest part of its path that
    exists, takes new files."""
    out = Path(path)
    if out.exists() and not out.is_dir():
        raise UserError(f"{out}: cannot create the {what}: a file of that name exists")
    if not create:
        base = next(p for p in (out, *out.absolute().parents) if p.exists())
        if not base.is_dir():
            raise UserError(f"{out}: cannot create the {what}: {base} is a file")
        _probe(base, out, what)
        return out
    try:
        out.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise UserError(f"{out}: cannot create the {what}: {exc.strerror or exc}") from None
    _probe(out, out, what)
    return out


def output_file(path: str | Path, what: str = "output file",
                suffixes: tuple[str, ...] = ()) -> Path:
    """Check that ``path`` can be written before the work that produces it: a known
    extension (``suffixes``, lower case with the dot, when the writer picks the format by
    it), not a directory, in an existing directory that takes new files."""
    out = Path(path)
    if suffixes and out.suffix.lower() not in suffixes:
        raise UserError(f"{out}: cannot write the {what}: its extension must be one of "
                        f"{', '.join(suffixes)} (not {out.suffix or 'none'})")
    if out.is_dir():
        raise UserError(f"{out}: cannot write the {what}: a directory of that name exists")
    parent = out.parent
    if not parent.is_dir():
        raise UserError(f"{out}: cannot write the {what}: no directory {parent}")
    _probe(parent, out, what)
    return out
