"""Element and depth caps for what the restricted unpicklers build.

A pickle can reference one container many times (its memo), so a file of a few hundred
bytes can describe a nested list of 10⁹ numbers that only becomes large when it is turned
into an array. :func:`check_unpickled` counts what an unpickler built before anything is
converted and refuses it past the caps; :class:`CappedUnpickler` is the base of the
restricted unpicklers that apply it.
"""

from __future__ import annotations

import codecs
import os
import pickle
from _compat_pickle import IMPORT_MAPPING, NAME_MAPPING
from typing import Any, BinaryIO, Callable

import numpy as np

from hogsa_loader.errors import AssetError, PathLike, UnsafePickleError

__all__ = ["MAX_ELEMENTS", "MAX_DEPTH", "CappedUnpickler", "check_unpickled", "nested_shape", "numpy_globals"]

#: Default cap of the elements an unpickled object may expand to (a file larger than this
#: many bytes raises the cap to its size).
MAX_ELEMENTS = 50_000_000
#: Default cap of container nesting (numpy arrays have at most 64 dimensions).
MAX_DEPTH = 32

_ATOMS = (int, float, complex, bool, str, bytes, bytearray, type(None), slice, np.generic, np.dtype, type)


#: Exact types whose values count one element (the common leaves of pickled lists).
_UNITS = frozenset({int, float, bool, type(None)})


def _atom_size(x: Any) -> int:
    """Elements an atom stands for: 1, or one per 8 bytes of what it holds."""
    if isinstance(x, (str, bytes, bytearray)):
        return max(1, -(-len(x) // 8))
    if isinstance(x, np.generic):
        return max(1, -(-int(x.nbytes) // 8))
    return 1


def check_unpickled(
    obj: Any, path: PathLike, file_size: int = 0, max_elements: int = MAX_ELEMENTS, max_depth: int = MAX_DEPTH
) -> int:
    """Count the elements ``obj`` expands to; refuse it past the caps.

    Every element is counted once per reference: a container shared by ten parents counts
    ten times, exactly as often as ``np.asarray`` would copy it. Every container type is
    counted (list, tuple, dict, set, frozenset, object arrays, the state of inert stand-in
    objects, whose stored arrays count for a pickled sparse matrix); a numeric array counts
    its elements, and anything that holds bytes (strings, byte strings, numpy scalars, arrays
    of wide items) counts at least one element per 8 bytes, so one long string shared many
    times is refused like a long list. Refused: more than ``max(max_elements, file_size)``
    elements (an element of a file that shares nothing costs at least one byte, so no honest
    file is refused), nesting deeper than ``max_depth``, cycles (a container inside itself).
    Each distinct object is visited once (its count is remembered), so the walk costs time
    proportional to the file, never to the count it refuses.

    Args:
        obj: what the unpickler returned.
        path: the file, named in errors.
        file_size: the file's size in bytes (raises the element cap to it).
        max_elements, max_depth: the caps.

    Returns:
        the element count.

    Raises:
        AssetError: too many elements, too deep, or a cycle.
    """
    limit = max(int(max_elements), int(file_size))
    done: dict[int, int] = {}
    active: set[int] = set()
    keep: list[Any] = []  # keeps visited objects alive so that their ids stay unique

    def too_many() -> AssetError:
        return AssetError(
            path,
            f"pickled data expands to more than {limit} elements (shared references "
            "count once per use); refusing it before anything is allocated",
        )

    def count(x: Any, depth: int) -> int:
        if isinstance(x, _ATOMS) and not isinstance(x, np.ndarray):
            n = _atom_size(x)
            if n > limit:
                raise too_many()
            return n
        key = id(x)
        if key in done:
            return done[key]
        if depth > max_depth:
            raise AssetError(path, f"pickled data is nested more than {max_depth} levels deep")
        if key in active:
            raise AssetError(path, "pickled data contains a cycle (a container inside itself)")
        active.add(key)
        keep.append(x)
        n = 0
        if isinstance(x, np.ndarray):
            if x.dtype.hasobject:
                items = x.ravel(order="K") if x.ndim else [x.item()]
            else:
                items, n = (), max(int(x.size), -(-int(x.nbytes) // 8))
        elif isinstance(x, dict):
            items = [v for kv in x.items() for v in kv]
        elif isinstance(x, (list, tuple, set, frozenset)):
            items = [v for v in x if type(v) not in _UNITS]  # plain numbers count 1 each, no call
            n = len(x) - len(items)
        else:  # an inert stand-in (chumpy stub, pickled sparse matrix): its recorded state
            items = list(getattr(x, "__dict__", {}).values())
        if n > limit:
            raise too_many()
        for item in items:
            n += count(item, depth + 1)
            if n > limit:
                raise too_many()
        active.discard(key)
        done[key] = max(n, 1)
        return done[key]

    return count(obj, 0)


def nested_shape(value: Any, max_depth: int = MAX_DEPTH) -> tuple[int, ...]:
    """Shape of nested lists / tuples read along their first elements (an array leaf adds its
    own shape): what ``np.asarray`` makes of a regular nest, found in time proportional to
    the depth, so a reader can refuse a wrong or huge shape before converting anything.

    Args:
        value: a list, tuple or array (anything else has shape ``()``).
        max_depth: levels followed at most.

    Returns:
        the shape; at most ``max_depth`` list levels (plus the leaf array's dimensions).
    """
    shape: list[int] = []
    node = value
    while isinstance(node, (list, tuple)) and len(shape) < max_depth:
        shape.append(len(node))
        if not node:
            break
        node = node[0]
    if isinstance(node, np.ndarray):
        shape.extend(node.shape)
    return tuple(shape)


def numpy_globals(frombuffer: Callable[..., np.ndarray]) -> dict[tuple[str, str], Any]:
    """The globals a pickle needs to rebuild numpy arrays, dtypes and scalars.

    Both module spellings (``numpy.core`` before numpy 2, ``numpy._core`` after) map to the
    same reconstructors; ``_codecs.encode`` is how protocol <= 2 pickles written by Python 3
    encode bytes (``encode(str, "latin1")``).

    Args:
        frombuffer: what ``numpy._core.numeric._frombuffer`` (protocol 5 arrays) resolves to.

    Returns:
        ``{(module, name): object}``.
    """
    probe = np.zeros(1)
    reconstruct = probe.__reduce_ex__(4)[0]  # numpy._core.multiarray._reconstruct
    scalar = np.float64(0).__reduce__()[0]  # numpy._core.multiarray.scalar
    allowed: dict[tuple[str, str], Any] = {
        ("numpy", "ndarray"): np.ndarray,
        ("numpy", "dtype"): np.dtype,
        ("_codecs", "encode"): codecs.encode,
    }
    for mod in ("numpy.core.multiarray", "numpy._core.multiarray"):
        allowed[(mod, "_reconstruct")] = reconstruct
        allowed[(mod, "scalar")] = scalar
    for mod in ("numpy.core.numeric", "numpy._core.numeric"):
        allowed[(mod, "_frombuffer")] = frombuffer
    return allowed


class CappedUnpickler(pickle.Unpickler):
    """Base of the restricted unpicklers: Python-2 pickles (``latin1``), globals resolved
    only by :meth:`resolve`, no persistent ids, and :meth:`load` refusing data past the caps
    of :func:`check_unpickled` (:class:`AssetError`).

    Subclasses set :attr:`file_kind` and implement :meth:`resolve`.

    Args:
        file: the binary stream holding the pickle.
        path: the file, named in errors.
        file_size: the file's size in bytes (raises the element cap to it).
    """

    #: What the file is, in error messages ("a MANO model file").
    file_kind = "this file"

    def __init__(self, file: BinaryIO, path: PathLike, file_size: int = 0) -> None:
        super().__init__(file, encoding="latin1", fix_imports=True)
        self._path = os.fspath(path)
        self._file_size = int(file_size)

    def load(self) -> Any:
        """Unpickle, then count what was built (:func:`check_unpickled`)."""
        obj = super().load()
        check_unpickled(obj, self._path, self._file_size)
        return obj

    def find_class(self, module: str, name: str) -> Any:  # noqa: D401 - pickle API
        # Python-2 names (copy_reg, __builtin__) -> Python 3, as pickle's fix_imports does
        if (module, name) in NAME_MAPPING:
            module, name = NAME_MAPPING[(module, name)]
        elif module in IMPORT_MAPPING:
            module = IMPORT_MAPPING[module]
        return self.resolve(module, name)

    def resolve(self, module: str, name: str) -> Any:
        """The object a (Python 3) global stands for; raises :class:`UnsafePickleError` for
        one that is not allowed."""
        raise UnsafePickleError(self._path, f"refusing to load global '{module}.{name}'")

    def persistent_load(self, pid: Any) -> Any:
        raise UnsafePickleError(self._path, f"persistent ids are not allowed in {self.file_kind}")
