"""Dataclasses to JSON schemas inside the subset Foxglove and Lichtblick parse, and back.

:func:`type_schema` turns an annotated field type into a JSON schema: every ``type`` one
string, every object with ``properties``, array items scalars or objects
(:func:`viewer_problems` checks a schema against that subset). Vectors of a system are
objects with one number per name (:class:`Names`); a plug-in's typed detail is a field
whose dataclass the plug-in declares (:class:`Detail`). :func:`convert` builds a dataclass
from decoded JSON; :func:`validate` checks a message against its schema. :func:`field_docs`
reads a dataclass's field descriptions (its docstring's ``Attributes:`` section) for the
manual; the schemas carry none (the logs' schema records do not depend on the wording).
"""

from __future__ import annotations

import dataclasses
import functools
import inspect
import re
import types
import typing
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Annotated, Any

__all__ = ["Detail", "Names", "Nodes", "convert", "field_docs", "flat_keys", "read_record",
           "record_type", "schema_classes", "type_schema", "validate", "viewer_problems"]


@dataclass(frozen=True)
class Names:
    """A vector written as an object with one field per name of a name set.

    ``kind``: ``state``, ``input``, ``disturbance``, ``guard`` (the system's names) or
    ``body`` (the logged body points' coordinates, :func:`~hmpc_cli.log.geometry.body_names`);
    ``value``: the JSON type of each field; ``flat``: the names are fields of the
    enclosing object itself (a plan node's ``px``, ``ux``), not of a nested one.
    """

    kind: str
    value: str = "number"
    flat: bool = False


@dataclass(frozen=True)
class Detail:
    """A plug-in's typed log detail: ``of`` is ``planner`` or ``mpc``."""

    of: str


@dataclass(frozen=True)
class Nodes:
    """Arrays in memory (one row per node), written as an array of ``node`` records."""

    node: type


_SCALARS = {float: "number", int: "integer", str: "string", bool: "boolean"}



@functools.cache
def _hints(cls: type) -> dict[str, Any]:
    return typing.get_type_hints(cls, include_extras=True)


def _strip_optional(tp):
    """(X, nullable) for X | None."""
    if typing.get_origin(tp) in (typing.Union, types.UnionType):
        args = [a for a in typing.get_args(tp) if a is not type(None)]
        if len(args) == 1:
            return args[0], True
    return tp, False


def type_schema(tp, names: Mapping[str, typing.Sequence[str]],
            details: Mapping[str, type | None]) -> dict:
    """JSON schema of a field type (``names``: name sets; ``details``: plug-in detail types)."""
    tp, _ = _strip_optional(tp)
    if typing.get_origin(tp) is Annotated:
        base, *meta = typing.get_args(tp)
        for m in meta:
            if isinstance(m, Names):
                return {"type": "object", "properties": {
                    n: {"type": m.value} for n in names.get(m.kind, ())}}
            if isinstance(m, Detail):  # no declared detail: an empty object (left out)
                cls = details.get(m.of)
                return {"type": "object", "properties": {}} if cls is None else \
                    type_schema(cls, names, details)
            if isinstance(m, Nodes):
                return {"type": "array", "items": type_schema(m.node, names, details)}
        return type_schema(base, names, details)
    if tp in _SCALARS:
        return {"type": _SCALARS[tp]}
    if typing.get_origin(tp) in (tuple, list):
        item = typing.get_args(tp)[0]
        inner = type_schema(item, names, details)
        if inner["type"] == "array":
            raise TypeError(f"array items must be scalars or objects, not {item!r}")
        return {"type": "array", "items": inner}
    if dataclasses.is_dataclass(tp):
        return _object_schema(tp, names, details)
    raise TypeError(f"no JSON schema for {tp!r}")


def _object_schema(tp: type, names: Mapping[str, typing.Sequence[str]],
                   details: Mapping[str, type | None]) -> dict:
    """The object schema of a dataclass (flat name fields spliced into its properties)."""
    hints, props = _hints(tp), {}
    for f in dataclasses.fields(tp):
        flat = _flat(hints[f.name])
        if flat is None:
            props[f.name] = type_schema(hints[f.name], names, details)
            continue
        for n in names.get(flat.kind, ()):
            if n in props:
                raise TypeError(f"{tp.__name__}: name {n!r} of {flat.kind} names collides "
                                "with another field")
            props[n] = {"type": flat.value}
    return {"title": tp.__name__, "type": "object", "properties": props}


def schema_classes(tp, details: Mapping[str, type | None] | None = None) -> tuple[type, ...]:
    """The dataclasses whose fields make up the JSON schema of ``tp``, each once, in order.

    As :func:`type_schema` nests them: ``tp`` itself, its fields' records (tuples of
    records too), a :class:`Nodes` field's node record (not its in-memory arrays) and a
    :class:`Detail` field's declared type (``details``); not a :class:`Names` vector.
    """
    out: dict[type, None] = {}
    _collect(tp, dict(details or {}), out)
    return tuple(out)


def _collect(tp, details: Mapping[str, type | None], out: dict[type, None]) -> None:
    tp, _ = _strip_optional(tp)
    if typing.get_origin(tp) is Annotated:
        base, *meta = typing.get_args(tp)
        for m in meta:
            if isinstance(m, Names):
                return
            if isinstance(m, (Detail, Nodes)):
                sub = details.get(m.of) if isinstance(m, Detail) else m.node
                if sub is not None:
                    _collect(sub, details, out)
                return
        _collect(base, details, out)
    elif typing.get_origin(tp) in (tuple, list):
        _collect(typing.get_args(tp)[0], details, out)
    elif dataclasses.is_dataclass(tp) and tp not in out:
        out[tp] = None
        hints = _hints(tp)
        for f in dataclasses.fields(tp):
            _collect(hints[f.name], details, out)


def _flat(tp) -> Names | None:
    """The flat :class:`Names` of a field annotation, or None."""
    if typing.get_origin(tp) is Annotated:
        return next((m for m in typing.get_args(tp)[1:]
                     if isinstance(m, Names) and m.flat), None)
    return None


def flat_keys(cls: type, names: Mapping[str, typing.Sequence[str]]) -> tuple[str, ...]:
    """The JSON keys of a record with flat name fields, in field order (e.g. PlanNode)."""
    hints, out = _hints(cls), []
    for f in dataclasses.fields(cls):
        flat = _flat(hints[f.name])
        out += list(names.get(flat.kind, ())) if flat is not None else [f.name]
    return tuple(out)


#: an ``Attributes:`` entry's first line: ``name: text`` or ``name (type): text``
_ENTRY = re.compile(r"(\w+)(?:\s*\([^()]*\))?:(?:\s+(.*))?")


def field_docs(cls: type) -> dict[str, str]:
    """Field name -> description, from the ``Attributes:`` sections of ``cls`` and its bases.

    A Google-style section: the line ``Attributes:``, then one entry per field, indented,
    ``name: text`` (or ``name (type): text``), its continuation lines indented further;
    the section ends at the first non-blank line indented no deeper than ``Attributes:``.
    A description is its lines joined by single spaces. A field the sections do not name
    is not in the result; a class without the section gives {}. A base's entry is
    overridden by the subclass's entry of the same name.

    Raises:
        ValueError: an entry line that is not ``name: text``.
    """
    out: dict[str, str] = {}
    for klass in reversed(cls.__mro__):
        if klass is not object:
            out.update(_attributes(inspect.cleandoc(vars(klass).get("__doc__") or ""),
                                   klass.__name__))
    return out


def _attributes(doc: str, owner: str) -> dict[str, str]:
    """The entries of one docstring's ``Attributes:`` section (see :func:`field_docs`)."""
    lines = doc.splitlines()
    head = next((i for i, line in enumerate(lines) if line.strip() == "Attributes:"), None)
    if head is None:
        return {}
    top = _indent(lines[head])
    entries: list[list[str]] = []
    at = None  # the entries' indentation
    for line in lines[head + 1:]:
        if not line.strip():
            continue
        ind = _indent(line)
        if ind <= top:
            break
        if at is None:
            at = ind
        if ind <= at:
            m = _ENTRY.fullmatch(line.strip())
            if m is None:
                raise ValueError(f"{owner}: Attributes: entry {line.strip()!r} is not "
                                 "'name: description'")
            entries.append([m.group(1), m.group(2) or ""])
        else:
            entries[-1][1] += " " + line.strip()
    return {name: text.strip() for name, text in entries}


def _indent(line: str) -> int:
    return len(line) - len(line.lstrip())


def convert(cls, value):
    """``value`` (dicts, lists, dataclasses) as an instance of dataclass ``cls``.

    Nested dataclass fields and tuples of dataclasses are converted recursively; the
    result raises TypeError on unknown or missing fields (a plug-in's detail that does
    not match its declared type).
    """
    if value is None or isinstance(value, cls):
        return value
    if dataclasses.is_dataclass(value):
        value = {f.name: getattr(value, f.name) for f in dataclasses.fields(value)}
    hints = _hints(cls)
    return cls(**{k: _field_value(hints.get(k, Any), v, convert)
                   for k, v in dict(value).items()})


def _field_value(tp, v, record, floats: bool = False):
    """A field's value as its type says.

    Nested records by ``record(cls, value)``, sequences item by item (as tuples), the
    integers of a float field as floats if ``floats``.
    """
    tp, _ = _strip_optional(tp)
    if typing.get_origin(tp) is Annotated:
        tp = typing.get_args(tp)[0]
    if dataclasses.is_dataclass(tp) and isinstance(v, Mapping):
        return record(tp, v)
    if typing.get_origin(tp) in (tuple, list) and isinstance(v, (list, tuple)):
        item = typing.get_args(tp)[0]
        return tuple(_field_value(item, x, record, floats) for x in v)
    if floats and tp is float and isinstance(v, int) and not isinstance(v, bool):
        return float(v)
    return v


_EMPTY = {float: float("nan"), int: 0, str: "", bool: False}


def read_record(cls: type, value: Mapping):
    """A logged object (decoded JSON) as dataclass ``cls``, as the log's reader sees it.

    A field left out of the message gets its default, else NaN for a number, 0, "",
    False, () or {} by its type, None for an optional or nested record (a field that was
    None or NaN is left out when written; an older log lacks newer fields). Keys ``cls``
    does not know are dropped (an older layout's). Nested records and tuples of records
    are read the same way; a field typed :class:`Detail` or :class:`Nodes` is the
    caller's to fill (it is passed through).
    """
    hints, kwargs = _hints(cls), {}
    for f in dataclasses.fields(cls):
        if f.name in value and value[f.name] is not None:
            kwargs[f.name] = _field_value(hints[f.name], value[f.name], read_record, True)
        elif f.default is not dataclasses.MISSING:
            kwargs[f.name] = f.default
        elif f.default_factory is not dataclasses.MISSING:
            kwargs[f.name] = f.default_factory()
        else:
            kwargs[f.name] = _empty(hints[f.name])
    return cls(**kwargs)


def _empty(tp):
    tp, optional = _strip_optional(tp)
    if optional:
        return None
    if typing.get_origin(tp) is Annotated:
        tp = typing.get_args(tp)[0]
    if typing.get_origin(tp) in (tuple, list):
        return ()
    if tp is dict or typing.get_origin(tp) is dict:
        return {}
    return _EMPTY.get(tp)


_JSON_TYPES = {"number": float, "integer": int, "string": str, "boolean": bool}


@functools.lru_cache(maxsize=256)
def _record_type(title: str, schema_json: str) -> type:
    import json

    schema = json.loads(schema_json)
    fields = []
    for name, sub in schema.get("properties", {}).items():
        fields.append((name, _schema_type(name, sub) | None,
                       dataclasses.field(default=None)))
    return dataclasses.make_dataclass(title, fields, frozen=True)


def _schema_type(name: str, sub: dict):
    t = sub.get("type")
    if t == "object":
        return record_type(sub, name.title().replace("_", ""))
    if t == "array":
        return tuple[_schema_type(name, sub.get("items") or {}), ...]
    return _JSON_TYPES.get(t, Any)


def record_type(schema: dict, title: str = "Record") -> type:
    """A frozen dataclass for a logged object schema (its ``title`` names it).

    How a log's reader types a record whose class it does not import (a plug-in's
    detail): one field per property (default None), nested objects and arrays of
    objects typed the same way.
    """
    import json

    return _record_type(str(schema.get("title") or title),
                        json.dumps(schema, sort_keys=True))


def viewer_problems(schema: dict, path: str = "") -> list[str]:
    """Where ``schema`` leaves the viewers' subset (empty: Foxglove/Lichtblick parse it)."""
    out = []
    t = schema.get("type")
    where = path or "(root)"
    if not isinstance(t, str):
        return [f"{where}: type {t!r} is not one string"]
    if t == "object":
        if "properties" not in schema:
            out.append(f"{where}: object without properties")
        for k, sub in schema.get("properties", {}).items():
            out += viewer_problems(sub, f"{path}.{k}" if path else k)
    elif t == "array":
        items = schema.get("items")
        if not isinstance(items, dict) or items.get("type") == "array":
            out.append(f"{where}: array items must be scalars or objects")
        else:
            out += viewer_problems(items, f"{path}[]")
    return out


_PY = {"number": (int, float), "integer": (int,), "string": (str,), "boolean": (bool,)}


def validate(schema: dict, value, path: str = "") -> list[str]:
    """Where a decoded JSON ``value`` does not match ``schema``, as a JSON-schema validator.

    Objects may leave properties out (an optional or non-finite value is left out, never
    null) but hold no unknown keys; null matches no type.
    """
    where = path or "(root)"
    t = schema["type"]
    if value is None:
        return [f"{where}: null where the schema says {t}"]
    if t == "object":
        if not isinstance(value, dict):
            return [f"{where}: expected an object"]
        props = schema["properties"]
        out = [f"{where}: unknown field {k!r}" for k in value if k not in props]
        for k, sub in props.items():
            if k in value:
                out += validate(sub, value[k], f"{path}.{k}" if path else k)
        return out
    if t == "array":
        if not isinstance(value, list):
            return [f"{where}: expected an array"]
        return [p for i, v in enumerate(value) for p in validate(schema["items"], v,
                                                                 f"{path}[{i}]")]
    ok = isinstance(value, _PY[t]) and not (t in ("number", "integer")
                                              and isinstance(value, bool))
    return [] if ok else [f"{where}: expected {t}, got {type(value).__name__}"]
