"""Typed records from plain data (TOML, JSON) and back, with errors that name the field.

`coerce(value, annotation, where)` checks one value against a type hint; `from_plain(cls,
data, where)` builds a (nested) frozen dataclass from dicts and lists, rejecting unknown and
missing fields; `to_plain(record)` is the inverse (tuples become lists). The experiment config
and the model manifest are both read through here. Standard library only.

Supported hints: dataclasses, int, float (ints accepted), str, bool, None, X | None,
tuple[X, ...], tuple[X, Y], list[X], dict[str, X] and Any.
"""

from __future__ import annotations

import dataclasses
import types
import typing
from typing import Any


class RecordError(ValueError):
    """A value that does not fit its field; the message starts with the field's path."""


def _type_name(annotation: Any) -> str:
    return getattr(annotation, "__name__", str(annotation))


def coerce(value: Any, annotation: Any, where: str) -> Any:
    """value checked against annotation; lists become tuples where a tuple is expected and
    dicts become dataclasses. Raises RecordError naming `where`."""
    if annotation is Any:
        return value
    if dataclasses.is_dataclass(annotation) and isinstance(annotation, type):
        return from_plain(annotation, value, where)
    origin = typing.get_origin(annotation)
    args = typing.get_args(annotation)
    if origin in (typing.Union, types.UnionType):
        if value is None and type(None) in args:
            return None
        options = [a for a in args if a is not type(None)]
        errors = []
        for option in options:
            try:
                return coerce(value, option, where)
            except RecordError as error:
                errors.append(str(error))
        if len(options) == 1:
            raise RecordError(errors[0])
        names = " or ".join(_type_name(a) for a in args)
        raise RecordError(f"{where} must be {names}, got {value!r}")
    if origin is tuple:
        if not isinstance(value, list | tuple):
            raise RecordError(f"{where} must be a list, got {value!r}")
        if len(args) == 2 and args[1] is Ellipsis:
            return tuple(coerce(v, args[0], f"{where}[{i}]") for i, v in enumerate(value))
        if len(value) != len(args):
            raise RecordError(f"{where} needs {len(args)} values, got {len(value)}")
        return tuple(
            coerce(v, a, f"{where}[{i}]") for i, (v, a) in enumerate(zip(value, args, strict=True))
        )
    if origin is list:
        if not isinstance(value, list | tuple):
            raise RecordError(f"{where} must be a list, got {value!r}")
        return [coerce(v, args[0], f"{where}[{i}]") for i, v in enumerate(value)]
    if origin is dict:
        if not isinstance(value, dict):
            raise RecordError(f"{where} must be a table, got {value!r}")
        return {
            coerce(k, args[0], f"{where} key"): coerce(v, args[1], f"{where}.{k}")
            for k, v in value.items()
        }
    if annotation is float:
        if isinstance(value, int | float) and not isinstance(value, bool):
            return float(value)
        raise RecordError(f"{where} must be float, got {value!r}")
    if annotation in (int, str, bool):
        if type(value) is not annotation:
            raise RecordError(f"{where} must be {annotation.__name__}, got {value!r}")
        return value
    if annotation is type(None):
        if value is not None:
            raise RecordError(f"{where} must be null, got {value!r}")
        return None
    raise TypeError(f"{where}: unsupported type hint {annotation!r}")


def from_plain(cls: type, data: Any, where: str) -> Any:
    """A dataclass instance from a dict: every field must be present unless it has a default;
    unknown keys are errors. Errors from the dataclass's own __post_init__ (ValueError) are
    re-raised as RecordError prefixed with `where`."""
    prefix = f"{where}: " if where else ""
    if not isinstance(data, dict):
        raise RecordError(f"{where or 'the record'} must be a table, got {data!r}")
    fields = {f.name: f for f in dataclasses.fields(cls)}
    unknown = sorted(set(data) - set(fields))
    if unknown:
        raise RecordError(
            f"{prefix}unknown field {unknown[0]!r}; known fields: {', '.join(sorted(fields))}"
        )
    hints = typing.get_type_hints(cls)
    values = {}
    for name, field in fields.items():
        if name in data:
            values[name] = coerce(data[name], hints[name], f"{where}.{name}" if where else name)
        elif field.default is dataclasses.MISSING and field.default_factory is dataclasses.MISSING:
            raise RecordError(f"{prefix}missing field {name!r}")
    try:
        return cls(**values)
    except RecordError:
        raise
    except ValueError as error:
        raise RecordError(f"{prefix}{error}") from None


def to_plain(value: Any) -> Any:
    """Dataclasses to dicts and tuples to lists, recursively (JSON- and TOML-ready)."""
    if dataclasses.is_dataclass(value) and not isinstance(value, type):
        return {f.name: to_plain(getattr(value, f.name)) for f in dataclasses.fields(value)}
    if isinstance(value, tuple | list):
        return [to_plain(v) for v in value]
    if isinstance(value, dict):
        return {k: to_plain(v) for k, v in value.items()}
    return value
