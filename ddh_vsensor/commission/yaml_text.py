"""Known keys of a configuration file set in its own text: the values replaced where the YAML
parser's marks place them, each line's comment replaced by the evidence, everything else of
the user's file (order, other comments, spacing) left as it was."""

from __future__ import annotations

from dataclasses import dataclass

import yaml

from ddh_vsensor.errors import UserError


@dataclass(frozen=True)
class Setting:
    """A value for the key at ``path`` (None: the value stays, only the comment is set)."""

    path: tuple[str, ...]
    value: str | None
    comment: str
    after: str | None = None    # a missing key goes after this sibling's line


def _child(node: yaml.Node, key: str) -> tuple[yaml.Node, yaml.Node] | None:
    if isinstance(node, yaml.MappingNode):
        for k, v in node.value:
            if isinstance(k, yaml.ScalarNode) and k.value == key:
                return k, v
    return None


def _comment_at(line: str, start: int) -> int | None:
    """Column of the comment on ``line`` after ``start`` (a # after a blank), if any."""
    for i in range(start, len(line)):
        if line[i] == "#" and (i == 0 or line[i - 1] in " \t"):
            return i
    return None


def set_values(text: str, source: str, settings: list[Setting]) -> str:
    """``text`` with every setting applied (UserError where the file's shape forbids it)."""
    root = yaml.compose(text, Loader=yaml.SafeLoader)
    lines = text.splitlines(keepends=True)
    # (start col, end col, new text or None: kept) per line; comments per line; inserts
    spans: dict[int, list[tuple[int, int, str | None]]] = {}
    comments: dict[int, list[str]] = {}
    inserts: dict[int, list[str]] = {}
    for s in settings:
        node: yaml.Node = root
        for part in s.path[:-1]:
            found = _child(node, part)
            if found is None:
                raise UserError(f"{source}: no {'.'.join(s.path[:-1])} to commission")
            node = found[1]
        found = _child(node, s.path[-1])
        if found is None:
            sibling = _child(node, s.after) if s.after else None
            if sibling is None or node.flow_style or s.value is None:
                raise UserError(f"{source}: cannot add {'.'.join(s.path)}: write the key "
                                f"into the file and commission again")
            key, value = sibling
            line = value.end_mark.line if value.end_mark.column else value.end_mark.line - 1
            inserts.setdefault(line, []).append(
                f"{' ' * key.start_mark.column}{s.path[-1]}: {s.value}  # {s.comment}\n")
            continue
        _, value = found
        if not isinstance(value, yaml.ScalarNode) or value.start_mark.line != \
                value.end_mark.line:
            raise UserError(f"{source}: {'.'.join(s.path)} is not a number on one line")
        line = value.start_mark.line
        spans.setdefault(line, []).append(
            (value.start_mark.column, value.end_mark.column, s.value))
        comments.setdefault(line, []).append(s.comment)
    for n in sorted(spans):
        text_n = lines[n].rstrip("\r\n")
        ending = lines[n][len(text_n):] or "\n"
        offset = 0
        for start, end, new in sorted(spans[n]):
            new = text_n[start + offset:end + offset] if new is None else new
            text_n = text_n[:start + offset] + new + text_n[end + offset:]
            offset += len(new) - (end - start)
        # the comment (if any) stays at its column where the new values leave room
        col = _comment_at(lines[n], max(end for _, end, _ in spans[n]))
        body = (text_n if col is None else text_n[:col + offset]).rstrip()
        pad = max(col - len(body), 2) if col is not None else 2
        lines[n] = f"{body}{' ' * pad}# {'; '.join(comments.get(n, []))}{ending}"
    for n in sorted(inserts, reverse=True):
        lines[n + 1:n + 1] = inserts[n]
    return "".join(lines)
