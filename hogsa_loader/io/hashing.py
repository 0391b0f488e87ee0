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


#: Version of every cache key (:func:`settings_key`) and export settings record: raised when
#: the settings a cache is keyed by change meaning, so that every cache is rebuilt once.
CACHE_VERSION = 2


def settings_key(obj: Any) -> str:
    """16 hex digits of the sha256 of ``obj`` (with :data:`CACHE_VERSION`) as JSON with sorted
    keys (values JSON cannot hold are written with ``str``): the cache key of a set of settings."""
    blob = json.dumps([CACHE_VERSION, obj], sort_keys=True, default=str).encode()
    return hashlib.sha256(blob).hexdigest()[:16]
