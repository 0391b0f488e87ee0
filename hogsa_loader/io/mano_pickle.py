"""Restricted unpickling of MANO ``.pkl`` model files.

The official ``MANO_RIGHT.pkl`` / ``MANO_LEFT.pkl`` are Python-2 pickles (read with
``encoding="latin1"``) that hold numpy arrays, a ``scipy.sparse`` ``J_regressor`` and chumpy
objects. :class:`RestrictedUnpickler` resolves only an allow-list of numpy / scipy.sparse /
copyreg globals, maps every ``chumpy.*`` class to an inert :class:`ChumpyStub` that keeps its
pickled state, and refuses anything else with :class:`~hogsa_loader.errors.UnsafePickleError`;
nothing from the file runs. What it builds is held to element and depth caps
(:func:`~hogsa_loader.io.pickle_caps.check_unpickled`) before :func:`as_array` turns any value
into an array; a sparse matrix is rebuilt from its checked parts
(:func:`~hogsa_loader.io.sparse.sparse_from_state`) before scipy's compiled code touches it.
"""

from __future__ import annotations

import copyreg
import io
import math
import os
from typing import Any

import numpy as np
import scipy.sparse as sp

from hogsa_loader.errors import AssetError, PathLike, UnsafePickleError
from hogsa_loader.io.pickle_caps import CappedUnpickler, nested_shape, numpy_globals
from hogsa_loader.io.sparse import sparse_from_state

__all__ = ["MAX_LIST_ELEMENTS", "ChumpyStub", "RestrictedUnpickler", "as_array"]


class ChumpyStub:
    """Inert stand-in for any ``chumpy`` class found in a pickle.

    It never runs chumpy code: unpickling only stores the pickled state, and
    :meth:`to_array` reads the value out of it (``x`` for ``Ch``; ``a``/``idxs``/
    ``preferred_shape`` for ``chumpy.reordering.Select``).
    """

    chumpy_name = "chumpy.ch.Ch"

    def __setstate__(self, state: Any) -> None:
        self.__dict__["_state"] = state

    def to_array(self, where: str = "<pickle>", depth: int = 0) -> np.ndarray:
        state = self.__dict__.get("_state")
        if not isinstance(state, dict):
            raise AssetError(where, f"chumpy object {self.chumpy_name} has no readable state")
        if "x" in state:
            return as_array(state["x"], where, depth)
        if "a" in state and "idxs" in state:  # chumpy.reordering.Select
            base = as_array(state["a"], where, depth).ravel()
            out = base[np.asarray(state["idxs"]).ravel()]
            shape = state.get("preferred_shape")
            return out.reshape(shape) if shape is not None else out
        if "r" in state:
            return as_array(state["r"], where, depth)
        raise AssetError(
            where,
            f"chumpy object {self.chumpy_name} with state keys {sorted(state)} cannot be "
            "turned into an array without chumpy; convert the file where chumpy is installed",
        )


_STUB_CLASSES: dict[str, type] = {}


def _chumpy_stub(module: str, name: str) -> type:
    full = f"{module}.{name}"
    if full not in _STUB_CLASSES:
        _STUB_CLASSES[full] = type(f"Chumpy_{name}", (ChumpyStub,), {"chumpy_name": full})
    return _STUB_CLASSES[full]


_SPARSE_FORMATS = (("csc", sp.csc_matrix), ("csr", sp.csr_matrix), ("coo", sp.coo_matrix))


def _allowed_globals() -> dict[tuple[str, str], Any]:
    allowed = numpy_globals(_frombuffer)
    allowed.update(
        {
            ("copyreg", "_reconstructor"): copyreg._reconstructor,
            ("builtins", "object"): object,
            ("builtins", "set"): set,
            ("builtins", "frozenset"): frozenset,
            ("builtins", "slice"): slice,
        }
    )
    for fmt, cls in _SPARSE_FORMATS:
        # a fresh subclass per unpickler: pickle's BUILD can set attributes on a class it was
        # handed, and must never reach scipy's own classes (or a later load's)
        private = type(f"Pickled_{fmt}_matrix", (cls,), {})
        for mod in (f"scipy.sparse.{fmt}", f"scipy.sparse._{fmt}", "scipy.sparse"):
            allowed[(mod, f"{fmt}_matrix")] = private
    return allowed


def _frombuffer(buf: bytes, dtype: Any, shape: tuple, order: str) -> np.ndarray:
    return np.frombuffer(buf, dtype=dtype).reshape(shape, order=order)


class RestrictedUnpickler(CappedUnpickler):
    """Unpickler that resolves only numpy / scipy.sparse / copyreg globals and chumpy stubs.

    Any other global (``os.system``, ``builtins.eval``, a user class, ...) raises
    :class:`UnsafePickleError` naming the file and the refused global; nothing from the
    file runs. :meth:`load` refuses data past the element / depth caps of
    :func:`~hogsa_loader.io.pickle_caps.check_unpickled` (:class:`AssetError`).
    """

    file_kind = "a MANO model file"

    def __init__(self, file: io.BufferedIOBase, path: PathLike = "<pickle>") -> None:
        try:
            file_size = os.fstat(file.fileno()).st_size
        except (AttributeError, OSError, ValueError):  # an in-memory stream
            file_size = len(file.getbuffer()) if isinstance(file, io.BytesIO) else 0
        super().__init__(file, path, file_size)
        self._allowed = _allowed_globals()

    def resolve(self, module: str, name: str) -> Any:
        if module == "chumpy" or module.startswith("chumpy."):
            return _chumpy_stub(module, name)
        try:
            return self._allowed[(module, name)]
        except KeyError:
            raise UnsafePickleError(
                self._path,
                f"refusing to load global '{module}.{name}': only numpy, scipy.sparse and "
                "chumpy data may appear in a MANO model file",
            ) from None


#: Largest nested Python list turned into an array: 1 M numbers, three times the release's
#: largest array. MANO files store numpy arrays, which this does not limit; a list of shared
#: references may stand for up to the unpickler's element cap of 50 M numbers, and
#: converting that many Python floats takes seconds and GBs.
MAX_LIST_ELEMENTS = 1_000_000


def as_array(value: Any, where: str, depth: int = 0) -> np.ndarray:
    """Turn an unpickled value (array, chumpy stub, sparse matrix, list) into a dense array."""
    if depth > 8:
        raise AssetError(where, "chumpy objects nested too deeply (a cycle?)")
    if isinstance(value, ChumpyStub):
        return value.to_array(where, depth + 1)
    if sp.issparse(value):
        fmt = next((f for f, c in _SPARSE_FORMATS if isinstance(value, c)), None)
        if fmt is None:  # another sparse type: only from an in-memory dict (a pickle cannot name one)
            return np.asarray(value.toarray())
        # the pickled state is checked part by part before scipy's compiled code sees it
        return np.asarray(sparse_from_state(value.__dict__, fmt, where).toarray())
    if isinstance(value, (str, bytes)):
        raise AssetError(where, f"expected an array, found a string {value!r:.40}")
    if isinstance(value, (list, tuple)):
        shape = nested_shape(value)
        if math.prod(shape) > MAX_LIST_ELEMENTS:
            raise AssetError(
                where, f"nested list of shape {'x'.join(map(str, shape))} is far larger than any MANO array"
            )
    try:
        arr = np.asarray(value)
    except (ValueError, TypeError, OverflowError) as exc:  # ragged lists, unconvertible items
        raise AssetError(where, f"not a numeric array ({type(exc).__name__}: {exc})") from None
    if arr.dtype.kind not in "biuf":
        raise AssetError(where, f"expected a numeric array, got dtype {arr.dtype}")
    return arr
