"""Flat views of grouped training configs.

A training job's config is a dataclass of groups (``data``, ``model``, ``loss``, ``optim``,
``run``), each a dataclass of plain fields whose names are unique across the groups. A run
folder's ``config.json`` keeps the settings flat (``{"iters": 2000, "k": 2, ...}``):
:func:`flat_config` writes that dict, :func:`config_from_flat` reads it back and
:func:`flat_defaults` lists the defaults (the values a setting missing from an older
``config.json`` had).
"""

from __future__ import annotations

import dataclasses
import typing
from typing import Any, Literal, Mapping, Optional, TypeVar

__all__ = [
    "Dataset",
    "config_from_flat",
    "dataset_field",
    "field_options",
    "flat_config",
    "flat_defaults",
    "flat_field_names",
    "mano_dir_field",
    "object_mesh_dir_field",
]

#: The dataset formats a training job reads.
Dataset = Literal["arctic", "h2o"]

T = TypeVar("T")


def field_options(help: str, check: Optional[str] = None, **extra: Any) -> dict[str, Any]:
    """A config field's metadata: help text, the name of its validator in
    :mod:`hogsa_loader.cli.checks` and any further keys (``name``, ``required``, ...)."""
    return {"help": help, **({"check": check} if check else {}), **extra}


def dataset_field() -> Any:
    """The ``dataset`` field of a job's data group (``"arctic"`` or ``"h2o"``)."""
    return dataclasses.field(default="arctic", metadata=field_options("dataset format"))


def mano_dir_field() -> Any:
    """The ``mano_dir`` field: H2O keeps the MANO models outside its root."""
    return dataclasses.field(default=None, metadata=field_options("H2O: folder with MANO_RIGHT.pkl / MANO_LEFT.pkl"))


def object_mesh_dir_field() -> Any:
    """The ``object_mesh_dir`` field: H2O keeps the object meshes outside its root."""
    return dataclasses.field(
        default=None, metadata=field_options("H2O: folder of the object meshes (<name>/<name>.obj|.ply)")
    )


def _groups(cls: type) -> dict[str, type]:
    """``{group field name: group dataclass}`` of a grouped config class."""
    hints = typing.get_type_hints(cls)
    return {f.name: hints[f.name] for f in dataclasses.fields(cls) if dataclasses.is_dataclass(hints[f.name])}


def _json_value(value: Any) -> Any:
    """Tuples as lists (what ``json`` writes and reads back); other values unchanged."""
    if isinstance(value, tuple):
        return [_json_value(v) for v in value]
    if isinstance(value, dict):
        return dict(value)
    return value


def flat_field_names(cls: type) -> dict[str, str]:
    """``{flat setting name: group name}`` of a grouped config class (its ``FLAT_NAMES``
    renames a group field, e.g. ``{"root": "data"}``)."""
    rename: Mapping[str, str] = getattr(cls, "FLAT_NAMES", {})
    out: dict[str, str] = {}
    for group, gcls in _groups(cls).items():
        for f in dataclasses.fields(gcls):
            out[rename.get(f.name, f.name)] = group
    return out


def flat_config(cfg: Any) -> dict[str, Any]:
    """The settings of a grouped config as one flat JSON-ready dict (tuples as lists)."""
    rename: Mapping[str, str] = getattr(type(cfg), "FLAT_NAMES", {})
    out: dict[str, Any] = {}
    for group in _groups(type(cfg)):
        for f in dataclasses.fields(getattr(cfg, group)):
            out[rename.get(f.name, f.name)] = _json_value(getattr(getattr(cfg, group), f.name))
    return out


def config_from_flat(cls: type[T], settings: Mapping[str, Any]) -> T:
    """The grouped config ``cls`` from flat settings (unset ones keep their defaults).

    Raises:
        TypeError: a setting ``cls`` does not have.
    """
    names = flat_field_names(cls)
    unknown = sorted(set(settings) - set(names))
    if unknown:
        raise TypeError(f"{cls.__name__} has no settings {unknown}")
    back = {v: k for k, v in getattr(cls, "FLAT_NAMES", {}).items()}
    kwargs: dict[str, dict[str, Any]] = {group: {} for group in _groups(cls)}
    for name, value in settings.items():
        kwargs[names[name]][back.get(name, name)] = value
    groups = _groups(cls)
    return cls(**{g: groups[g](**kw) for g, kw in kwargs.items()})  # type: ignore[call-arg]


def flat_defaults(cls: type) -> dict[str, Any]:
    """``{flat setting name: default}`` of a grouped config class (fields with a default)."""
    rename: Mapping[str, str] = getattr(cls, "FLAT_NAMES", {})
    out: dict[str, Any] = {}
    for gcls in _groups(cls).values():
        for f in dataclasses.fields(gcls):
            if f.default is not dataclasses.MISSING:
                out[rename.get(f.name, f.name)] = _json_value(f.default)
            elif f.default_factory is not dataclasses.MISSING:
                out[rename.get(f.name, f.name)] = _json_value(f.default_factory())
    return out
