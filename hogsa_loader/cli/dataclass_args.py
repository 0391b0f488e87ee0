"""Command-line flags derived from (nested) config dataclasses.

A job's settings live in one dataclass whose fields are plain values or further
dataclasses (groups). :func:`add_dataclass_arguments` adds one ``--flag`` per leaf field
(``--group-field`` for a field of a group, an argparse group per dataclass group, help
from the field's ``metadata["help"]``, a flag that must be given where
``metadata["required"]`` is true); :func:`dataclass_from_args` builds the config back
from the parsed namespace. An option is therefore added in one place: its field.

More field metadata: ``"type"`` (an argparse converter, or the name of one in
:mod:`hogsa_loader.cli.checks`), ``"choices"``, ``"name"`` (the
flag is ``--<name>`` instead of one made from the field path), ``"cli_type"`` (the type
the flag parses, for a field whose annotation is not a flag type), ``"cli": False`` (no
flag: the field keeps its default); on a group field, ``"flat": True`` (its flags carry
no group prefix).
"""

from __future__ import annotations

import argparse
import dataclasses
import typing
from typing import Any, Optional, TypeVar

from hogsa_loader.cli import checks

__all__ = ["add_dataclass_arguments", "dataclass_from_args", "flag_name"]

T = TypeVar("T")


def flag_name(path: tuple[str, ...]) -> str:
    """``("train", "batch_size")`` → ``"--train-batch-size"``."""
    return "--" + "-".join(p.replace("_", "-") for p in path)


def _dest(path: tuple[str, ...]) -> str:
    return "__".join(path)


def _leaf_type(tp: Any) -> tuple[Any, bool]:
    """``(scalar type, optional)`` of a field annotation (``Optional[X]`` → X, True)."""
    args = typing.get_args(tp)
    if typing.get_origin(tp) is typing.Union and type(None) in args:
        rest = [a for a in args if a is not type(None)]
        return rest[0], True
    return tp, False


def _add_leaf(
    group: Any, path: tuple[str, ...], f: dataclasses.Field, tp: Any, default: Any, flag_path: tuple[str, ...]
) -> None:
    kind, optional = _leaf_type(f.metadata.get("cli_type", tp))
    helptext = f.metadata.get("help", "")
    choices = f.metadata.get("choices")
    flag = flag_name((f.metadata["name"],) if "name" in f.metadata else flag_path)
    convert = f.metadata.get("type")
    convert = getattr(checks, convert) if isinstance(convert, str) else convert
    if typing.get_origin(kind) is typing.Literal:
        choices, kind = typing.get_args(kind), type(typing.get_args(kind)[0])
    if kind is bool:
        group.add_argument(
            flag,
            dest=_dest(path),
            action=argparse.BooleanOptionalAction,
            default=default,
            help=f"{helptext} (default: {default})",
        )
        return
    if typing.get_origin(kind) is tuple:
        item = typing.get_args(kind)[0]
        group.add_argument(
            flag,
            dest=_dest(path),
            type=convert or item,
            nargs="+",
            default=default,
            metavar=path[-1].upper(),
            help=f"{helptext} (default: {' '.join(map(str, default or ())) or 'none'})",
        )
        return
    if f.metadata.get("required"):  # no default: argparse reports the flag missing
        given: dict[str, Any] = dict(required=True, help=f"{helptext} (required)")
    else:
        given = dict(default=default, help=f"{helptext} (default: {default}{', optional' if optional else ''})")
    group.add_argument(
        flag,
        dest=_dest(path),
        type=convert or (kind if kind in (int, float, str) else str),
        choices=choices,
        metavar=None if choices else path[-1].upper(),
        **given,
    )


def add_dataclass_arguments(
    parser: argparse.ArgumentParser,
    cls: type,
    default: Optional[Any] = None,
    prefix: tuple[str, ...] = (),
    flag_prefix: Optional[tuple[str, ...]] = None,
) -> None:
    """Add one flag per leaf field of the dataclass ``cls`` (groups recurse).

    Args:
        parser: the parser (or argument group) to add to.
        cls: the config dataclass.
        default: an instance whose values are the flags' defaults (default ``cls()``).
        prefix: field path of ``cls`` inside the root config (flags ``--a-b-field``).
        flag_prefix: the part of ``prefix`` that names the flags (default all of it).
    """
    flag_prefix = prefix if flag_prefix is None else flag_prefix
    default = cls() if default is None else default
    hints = typing.get_type_hints(cls)
    group = parser
    if prefix and hasattr(parser, "add_argument_group"):
        group = parser.add_argument_group(" ".join(prefix), (cls.__doc__ or "").strip().splitlines()[0])
    for f in dataclasses.fields(cls):
        if not f.init or f.metadata.get("cli", True) is False:
            continue
        value = getattr(default, f.name)
        if dataclasses.is_dataclass(hints[f.name]):
            flags = flag_prefix if f.metadata.get("flat") else flag_prefix + (f.name,)
            add_dataclass_arguments(parser, hints[f.name], value, prefix + (f.name,), flags)
        else:
            _add_leaf(group, prefix + (f.name,), f, hints[f.name], value, flag_prefix + (f.name,))


def dataclass_from_args(cls: type[T], ns: argparse.Namespace, prefix: tuple[str, ...] = ()) -> T:
    """The config ``cls`` from a namespace parsed with :func:`add_dataclass_arguments`."""
    hints = typing.get_type_hints(cls)
    kwargs: dict[str, Any] = {}
    for f in dataclasses.fields(cls):
        if not f.init or f.metadata.get("cli", True) is False:
            continue
        path = prefix + (f.name,)
        if dataclasses.is_dataclass(hints[f.name]):
            kwargs[f.name] = dataclass_from_args(hints[f.name], ns, path)
            continue
        value = getattr(ns, _dest(path))
        kind, _ = _leaf_type(hints[f.name])
        if typing.get_origin(kind) is tuple and value is not None:
            value = tuple(value)
        kwargs[f.name] = value
    return cls(**kwargs)  # type: ignore[call-arg]


def apply_field_checks(parser: argparse.ArgumentParser, cls: type, prefix: tuple[str, ...] = ()) -> None:
    """Give the flags :func:`add_dataclass_arguments` added for ``cls`` their field's converter.

    A field's ``metadata["check"]`` names a validator of :mod:`hogsa_loader.cli.checks`
    (``"positive_int"``), ``metadata["type"]`` is a converter itself; ``metadata["nargs"]``
    makes the flag take several values (the field gets the list of converted values).
    """
    actions = {a.dest: a for a in parser._actions}
    hints = typing.get_type_hints(cls)
    for f in dataclasses.fields(cls):
        if not f.init:
            continue
        path = prefix + (f.name,)
        if dataclasses.is_dataclass(hints[f.name]):
            apply_field_checks(parser, hints[f.name], path)
            continue
        action = actions.get(_dest(path))
        if action is None:
            continue
        if "check" in f.metadata:
            action.type = getattr(checks, f.metadata["check"])
        if "type" in f.metadata:
            action.type = f.metadata["type"]
        if "nargs" in f.metadata:
            action.nargs = f.metadata["nargs"]
