"""The MANO release's pickle format, written: the generated world's hands in exactly the files
a real MANO download holds (protocol 2, Python-2 global names, chumpy ``Ch`` for
``shapedirs``, a CSC ``J_regressor``), so that every reader is exercised on the real format."""

from __future__ import annotations

import copyreg
import io
import os
import pickle
from _compat_pickle import REVERSE_IMPORT_MAPPING, REVERSE_NAME_MAPPING
from typing import Any, Optional

import numpy as np

from hogsa_loader.assets.hands.mano_io import ManoModelData, schema_dict
from hogsa_loader.errors import PathLike
from hogsa_loader.io.atomic import atomic_write

__all__ = ["release_pickle_bytes", "write_mano_pickle"]


class _ChumpyCh:
    """Writer-side placeholder pickled as ``chumpy.ch.Ch`` with state ``{'x': array}``."""

    def __init__(self, x: np.ndarray) -> None:
        self.x = x

    def __reduce__(self) -> tuple:
        return (copyreg._reconstructor, (_ChumpyCh, object, None), {"x": self.x})


class _LegacyPickler(pickle._Pickler):  # type: ignore[name-defined]
    """Protocol-2 pickler that writes the global names of a Python-2 MANO file.

    numpy's ``_core`` is written as ``core``, scipy's private ``_csc`` module as ``csc``, the
    chumpy placeholder as ``chumpy.ch.Ch``, and ``bytes`` as Python-2 ``str`` (BINSTRING), so
    that readers meet exactly what the official files contain.
    """

    _RENAMES = {
        "numpy._core.multiarray": "numpy.core.multiarray",
        "numpy._core.numeric": "numpy.core.numeric",
        "scipy.sparse._csc": "scipy.sparse.csc",
    }
    dispatch = dict(pickle._Pickler.dispatch)  # type: ignore[attr-defined]

    def save_global(self, obj: Any, name: Optional[str] = None) -> None:  # noqa: D401
        if obj is _ChumpyCh:
            module, qual = "chumpy.ch", "Ch"
        else:
            module, qual = obj.__module__, name or obj.__qualname__
            module = self._RENAMES.get(module, module)
        if (module, qual) in REVERSE_NAME_MAPPING:
            module, qual = REVERSE_NAME_MAPPING[(module, qual)]
        module = REVERSE_IMPORT_MAPPING.get(module, module)
        self.write(pickle.GLOBAL + f"{module}\n{qual}\n".encode("latin1"))
        self.memoize(obj)

    def save_bytes_py2(self, obj: bytes) -> None:
        n = len(obj)
        if n < 256:
            self.write(pickle.SHORT_BINSTRING + bytes([n]) + obj)
        else:
            self.write(pickle.BINSTRING + n.to_bytes(4, "little") + obj)
        self.memoize(obj)

    dispatch[bytes] = save_bytes_py2


def release_pickle_bytes(doc: dict[str, Any]) -> bytes:
    """``doc`` (a MANO dictionary, e.g. :func:`~hogsa_loader.assets.hands.mano_io.schema_dict`'s,
    or a crafted one) as the bytes of a release-style pickle; an array ``shapedirs`` is stored
    as a chumpy ``Ch``, as in the release."""
    doc = dict(doc)
    if isinstance(doc.get("shapedirs"), np.ndarray):
        doc["shapedirs"] = _ChumpyCh(np.ascontiguousarray(doc["shapedirs"]))
    buf = io.BytesIO()
    _LegacyPickler(buf, protocol=2, fix_imports=True).dump(doc)
    return buf.getvalue()


def write_mano_pickle(model: ManoModelData, path: PathLike) -> None:
    """Write ``model`` as a MANO pickle in the release's schema (the schema of ``MANO_RIGHT.pkl``).

    ``shapedirs`` is stored as a chumpy ``Ch`` (as in the release), ``J_regressor`` as a
    ``scipy.sparse`` CSC matrix, ``kintree_table`` with the uint32 root sentinel, and the
    project metadata (side, fingertips, contact sets, colours) under ``hogsa_meta``.
    Readers that ignore ``hogsa_meta`` (smplx, ARCTIC) take the fingertips at
    ``MANO_RELEASE_TIP_IDS``, so a model meant for them has its tips there (the
    synthetic hand does). The file is written atomically.
    """
    p = os.fspath(path)
    os.makedirs(os.path.dirname(os.path.abspath(p)), exist_ok=True)
    atomic_write(p, release_pickle_bytes(schema_dict(model)))
