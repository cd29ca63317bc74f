"""The configuration's JSON Schema (draft 2020-12), generated from the dataclasses the loader
validates with, for YAML editors: a machine's file that starts with
``# yaml-language-server: $schema=ddh-vsensor.schema.json`` gets completion, descriptions and
the per-key checks while it is typed.

What the schema says: every key with its type (number, whole number, true/false, text, a
list, a mapping, a fixed set of choices, optional ``null``), its bounds, whether it is required,
its default, no unknown keys, and a description from the class docstring or the comments beside
the field. It uses only keywords that mean the same under draft-07, which the YAML language
server applies. What it cannot say, so ``ddh-vsensor config --validate`` stays the authority: the
cross-field rules of each dataclass's ``check`` (areas, friction, references within the stroke,
unit names and the same units in every section, bus names, work-cycle steps), that a number is
finite, and that a whole number is not written as ``1.0``.
"""

from __future__ import annotations

import ast
import dataclasses
import inspect
import io
import textwrap
import tokenize
import types
import typing
from typing import Any, Literal

from ddh_vsensor.config.schema import Config

DRAFT = "https://json-schema.org/draft/2020-12/schema"
_BOUNDS = (("gt", "exclusiveMinimum"), ("ge", "minimum"), ("lt", "exclusiveMaximum"),
           ("le", "maximum"))
_SCALARS = {float: {"type": "number"}, int: {"type": "integer"}, bool: {"type": "boolean"},
            str: {"type": "string"}}


def _doc(obj: Any) -> str:
    """A docstring as one paragraph of plain text (reST literals unquoted)."""
    return " ".join((inspect.getdoc(obj) or "").replace("``", "").split())


def field_comments(cls: type) -> dict[str, str]:
    """Each field's comments: the comment lines right above it and the one beside it. Empty
    where the source is not installed (the schema then carries the types alone)."""
    try:
        source = textwrap.dedent(inspect.getsource(cls))
    except (OSError, TypeError):
        return {}
    comments = {tok.start[0]: tok.string.lstrip("#").strip()
                for tok in tokenize.generate_tokens(io.StringIO(source).readline)
                if tok.type == tokenize.COMMENT}
    lines = source.splitlines()
    body = ast.parse(source).body[0]
    out = {}
    for node in getattr(body, "body", []):
        if not (isinstance(node, ast.AnnAssign) and isinstance(node.target, ast.Name)):
            continue
        above = []
        row = node.lineno - 1
        while row in comments and lines[row - 1].lstrip().startswith("#"):
            above.insert(0, comments[row])
            row -= 1
        beside = [comments[r] for r in range(node.lineno, (node.end_lineno or node.lineno) + 1)
                  if r in comments]
        text = "; ".join(filter(None, (" ".join(above), " ".join(beside)))).replace("`", "")
        if text:
            out[node.target.id] = text
    return out


def _json_value(value: Any) -> Any:
    """A default as the YAML would spell it (tuples as lists, sections as mappings)."""
    if dataclasses.is_dataclass(value):
        value = dataclasses.asdict(value)
    if isinstance(value, dict):
        return {k: _json_value(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_json_value(v) for v in value]
    return value


class _Builder:
    def __init__(self) -> None:
        self.defs: dict[str, dict[str, Any]] = {}

    def type_schema(self, tp: Any) -> dict[str, Any]:
        origin, args = typing.get_origin(tp), typing.get_args(tp)
        if dataclasses.is_dataclass(tp):
            if tp.__name__ not in self.defs:
                self.defs[tp.__name__] = self.object_schema(tp)
            return {"$ref": f"#/$defs/{tp.__name__}"}
        if tp in _SCALARS:
            return dict(_SCALARS[tp])
        if tp is Any:
            return {}
        if origin is Literal:
            out: dict[str, Any] = {"enum": list(args)}
            if all(isinstance(a, str) for a in args):
                out = {"type": "string", **out}
            return out
        if origin is tuple:
            return {"type": "array", "items": self.type_schema(args[0])}
        if origin is dict:
            out = {"type": "object", "additionalProperties": self.type_schema(args[1])}
            if typing.get_origin(args[0]) is Literal:
                out["propertyNames"] = {"enum": list(typing.get_args(args[0]))}
            return out
        if origin in (typing.Union, types.UnionType):
            return {"anyOf": [{"type": "null"} if a is type(None) else self.type_schema(a)
                              for a in args]}
        raise TypeError(f"no JSON Schema for the config type {tp!r}")  # programming error

    def field_schema(self, f: dataclasses.Field, tp: Any, comment: str | None
                     ) -> dict[str, Any]:
        meta = dict(f.metadata)
        if "ge" in meta and "gt" in meta and meta["gt"] < meta["ge"]:
            del meta["gt"]                      # _positive(ge=...): the tighter bound says it
        more = {word: meta[key] for key, word in _BOUNDS if key in meta}
        if comment:
            more["description"] = comment
        if f.default is not dataclasses.MISSING:
            more["default"] = _json_value(f.default)
        elif f.default_factory is not dataclasses.MISSING:
            more["default"] = _json_value(f.default_factory())
        out = self.type_schema(tp)
        if "$ref" in out and more:              # draft-07 readers ignore a $ref's siblings
            return {"allOf": [out], **more}
        return {**out, **more}

    def object_schema(self, cls: type) -> dict[str, Any]:
        hints = typing.get_type_hints(cls)
        comments = field_comments(cls)
        fields = [f for f in dataclasses.fields(cls) if not f.metadata.get("internal")]
        out: dict[str, Any] = {
            "type": "object",
            "description": _doc(cls),
            "properties": {f.name: self.field_schema(f, hints[f.name], comments.get(f.name))
                           for f in fields},
            "additionalProperties": False}
        required = [f.name for f in fields if f.default is dataclasses.MISSING
                    and f.default_factory is dataclasses.MISSING]
        if required:
            out["required"] = required
        return out


def json_schema(cls: type = Config) -> dict[str, Any]:
    """The JSON Schema of a configuration file whose document is ``cls``."""
    builder = _Builder()
    top = builder.object_schema(cls)
    return {"$schema": DRAFT, "title": "ddh-vsensor machine configuration", **top,
            "$defs": dict(sorted(builder.defs.items()))}
