"""Content digests of files and cache keys of settings."""

from __future__ import annotations

import hashlib
import json
from pathlib import Path
from typing import Any


def sha256_file(path: Path) -> str:
    """Hex sha256 of a file's bytes, read in 1 MiB chunks."""
    h = hashlib.sha256()
    with open(path, "rb") as fh:
        for chunk in iter(lambda: fh.read(1 << 20), b""):
            h.update(chunk)
    return h.hexdigest()


def settings_key(obj: Any) -> str:
    """16 hex digits of the sha256 of ``obj`` as JSON with sorted keys (values JSON cannot
    hold are written with ``str``): the cache key of a set of settings."""
    return hashlib.sha256(json.dumps(obj, sort_keys=True, default=str).encode()).hexdigest()[:16]


def keyed_settings(values: dict[str, Any], unkeyed: dict[str, Any]) -> dict[str, Any]:
    """``values`` without each entry whose value is the one ``unkeyed`` gives for its name.

    A setting added after cache keys were first written is keyed this way only when it holds
    another value than the one that reproduces the behaviour from before it existed, so what
    was cached before keeps its key.
    """
    return {k: v for k, v in values.items() if k not in unkeyed or v != unkeyed[k]}
