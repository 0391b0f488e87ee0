"""Command-line flags derived from (nested) config dataclasses.

:func:`add_dataclass_arguments` adds one ``--flag`` per leaf field (``--group-field`` for a
field of a group; help from ``metadata["help"]``); :func:`dataclass_from_args` builds the
config back from the parsed namespace: an option is added in one place, its field. Field
metadata: ``"type"`` (a converter, or the name of one in :mod:`hogsa_loader.cli.checks`),
``"choices"``, ``"required"``, ``"name"`` (the flag is ``--<name>``), ``"cli_type"`` (the type
the flag parses), ``"cli": False`` (no flag); on a group field ``"flat": True`` (no group
prefix). Every list is one comma-separated value (``--views 1,2,3``): tuple fields and fields
marked ``"list": True`` (with ``"count"``: exactly that many items).
"""

from __future__ import annotations

import argparse
import dataclasses
import typing
from typing import Any, Optional, TypeVar

from hogsa_loader.cli import checks

__all__ = ["CommaList", "add_dataclass_arguments", "dataclass_from_args", "flag_name"]

T = TypeVar("T")


class CommaList:
    """argparse converter of a list given as one comma-separated value: ``"a,b"`` →
    ``[convert("a"), convert("b")]`` (with ``count``: exactly that many items)."""

    def __init__(self, convert: Any, count: Optional[int] = None) -> None:
        self.convert, self.count = convert, count
        self.__name__ = getattr(convert, "__name__", "value")

    def __call__(self, text: str) -> list[Any]:
        items = [t.strip() for t in str(text).split(",")]
        if any(not t for t in items):
            raise argparse.ArgumentTypeError(f"empty item in {text!r} (a list is comma-separated: A,B,C)")
        if self.count is not None and len(items) != self.count:
            raise argparse.ArgumentTypeError(f"expected {self.count} comma-separated values, got {text!r}")
        return [self.convert(t) for t in items]


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
    group: Any,
    path: tuple[str, ...],
    f: dataclasses.Field,
    tp: Any,
    default: Any,
    flag_path: tuple[str, ...],
    name_prefix: tuple[str, ...] = (),
) -> None:
    kind, optional = _leaf_type(f.metadata.get("cli_type", tp))
    helptext = f.metadata.get("help", "")
    choices = f.metadata.get("choices")
    flag = flag_name(name_prefix + (f.metadata["name"],) if "name" in f.metadata else flag_path)
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
    if typing.get_origin(kind) is tuple or f.metadata.get("list"):
        item = typing.get_args(kind)[0] if typing.get_origin(kind) is tuple else str
        group.add_argument(
            flag,
            dest=_dest(path),
            type=CommaList(convert or item, f.metadata.get("count")),
            default=default,
            metavar=f"{path[-1].upper()},...",
            help=f"{helptext} (comma-separated; default: {','.join(map(str, default or ())) or 'none'})",
        )
        return
    if f.metadata.get("required") and not default:  # no default: argparse reports the flag missing
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
    skip: frozenset = frozenset(),
    name_prefix: Optional[tuple[str, ...]] = None,
) -> None:
    """Add one flag per leaf field of the dataclass ``cls`` (groups recurse).

    Args:
        parser: the parser (or argument group) to add to.
        cls: the config dataclass.
        default: an instance whose values are the flags' defaults (default ``cls()``).
        prefix: field path of ``cls`` inside the root config (flags ``--a-b-field``).
        flag_prefix: the part of ``prefix`` that names the flags (default all of it).
        skip: field paths (from the root config) that get no flag (their values are set by
            the caller; :func:`dataclass_from_args` keeps the default's).
        name_prefix: what precedes a field's own ``name`` (default: ``flag_prefix``); a group
            field marked ``"job": True`` (a whole job's config) puts its prefix there, so that
            ``--batch-size`` of ``hogsa train hogs`` is ``--hogs-batch-size`` in ``hogsa build``.
    """
    flag_prefix = prefix if flag_prefix is None else flag_prefix
    name_prefix = flag_prefix if name_prefix is None else name_prefix
    default = cls() if default is None else default
    hints = typing.get_type_hints(cls)
    group = parser
    if prefix and hasattr(parser, "add_argument_group"):
        group = parser.add_argument_group(" ".join(prefix), (cls.__doc__ or "").strip().splitlines()[0])
    for f in dataclasses.fields(cls):
        if not f.init or f.metadata.get("cli", True) is False or prefix + (f.name,) in skip:
            continue
        value = getattr(default, f.name)
        if dataclasses.is_dataclass(hints[f.name]):
            flags = flag_prefix if f.metadata.get("flat") else flag_prefix + (f.name,)
            names = flags if f.metadata.get("job") else name_prefix
            add_dataclass_arguments(parser, hints[f.name], value, prefix + (f.name,), flags, skip, names)
        else:
            _add_leaf(group, prefix + (f.name,), f, hints[f.name], value, flag_prefix + (f.name,), name_prefix)


def dataclass_from_args(
    cls: type[T], ns: argparse.Namespace, prefix: tuple[str, ...] = (), default: Optional[Any] = None
) -> T:
    """The config ``cls`` from a namespace parsed with :func:`add_dataclass_arguments`; fields
    without a flag in ``ns`` keep their value in ``default`` (default ``cls()``)."""
    hints = typing.get_type_hints(cls)
    kwargs: dict[str, Any] = {}
    for f in dataclasses.fields(cls):
        if not f.init or f.metadata.get("cli", True) is False:
            continue
        path = prefix + (f.name,)
        if dataclasses.is_dataclass(hints[f.name]):
            sub = getattr(default, f.name) if default is not None else None
            kwargs[f.name] = dataclass_from_args(hints[f.name], ns, path, sub)
            continue
        if not hasattr(ns, _dest(path)):
            if default is not None:
                kwargs[f.name] = getattr(default, f.name)
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
    (``"positive_int"``), ``metadata["type"]`` is a converter itself; a list flag converts
    each of its comma-separated items with it.
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
        convert = None
        if "check" in f.metadata:
            convert = getattr(checks, f.metadata["check"])
        if "type" in f.metadata:
            convert = f.metadata["type"]
        if convert is not None:
            action.type = CommaList(convert, action.type.count) if isinstance(action.type, CommaList) else convert
