"""The configuration's errors, worded for the person who edits the file."""

from __future__ import annotations

from ddh_vsensor.errors import UserError

MAX_MESSAGE_CHARS = 300


class ConfigError(UserError, ValueError):
    """A configuration problem, worded for the person who edits the file."""

    def __init__(self, source: str, key_path: str, problem: str) -> None:
        self.source, self.key_path, self.problem = source, key_path, problem
        where = f"{source}: {key_path}: " if key_path else f"{source}: "
        text = where + problem
        if len(text) > MAX_MESSAGE_CHARS:
            text = text[:MAX_MESSAGE_CHARS - 3] + "..."
        super().__init__(text)



class UnknownUnitError(UserError, KeyError):
    """A unit name this machine does not have (a CLI argument or a caller's typo)."""

    def __str__(self) -> str:
        return str(self.args[0])

