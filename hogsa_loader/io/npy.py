"""Reading ``np.save``-d files without running arbitrary pickle code.

ARCTIC stores ``raw_seqs/*.npy`` and ``splits/*.npy`` as ``np.save``-d Python objects, which
``np.load(allow_pickle=True)`` would read by running :mod:`pickle` on the file, so a crafted
file could execute arbitrary code. :func:`read_npy` parses the ``.npy`` header itself, reads
numeric arrays without pickle, and unpickles object payloads with :class:`NpyUnpickler`,
which resolves only the numpy globals needed to rebuild arrays, dtypes and scalars (plus the
built-in containers pickle encodes without globals: dict, list, tuple, str, numbers), and
holds what it built to element and depth caps (:func:`~hogsa_loader.io.pickle_caps.check_unpickled`:
shared references count once per use) before any of it is converted. A pickled
``scipy.sparse`` CSR matrix (as in a world's ``meta/downsamplers.npy``) is unpickled as
inert state and rebuilt from its checked arrays (:func:`~hogsa_loader.io.sparse.sparse_from_state`). Any other
global (``os.system``, ``builtins.exec``, a class) raises
:class:`~hogsa_loader.errors.UnsafePickleError` before anything runs.
"""

from __future__ import annotations

import ast
import io
import math
from pathlib import Path
from typing import Any, Optional

import numpy as np

from hogsa_loader.errors import AssetError, PathLike, UnsafePickleError
from hogsa_loader.io.pickle_caps import CappedUnpickler, numpy_globals
from hogsa_loader.io.sparse import sparse_from_state

__all__ = ["MAX_NPY_HEADER", "NpyUnpickler", "read_npy"]

#: Largest ``.npy`` header accepted (numpy's own default limit).
MAX_NPY_HEADER = 10000


def _npy_allowed_globals() -> dict[tuple[str, str], Any]:
    """The only globals an ARCTIC ``.npy`` pickle may reference (numpy array rebuilding)."""
    frombuffer = np.zeros(1).__reduce_ex__(5)[0]  # numpy._core.numeric._frombuffer (protocol 5)
    return numpy_globals(frombuffer)


class _PickledCSR:
    """Inert holder of a pickled CSR matrix's state (nothing of scipy runs on unpickling)."""

    state: Any = None

    def __setstate__(self, state: Any) -> None:
        self.state = state


_NPY_ALLOWED = _npy_allowed_globals()
for _mod in ("scipy.sparse._csr", "scipy.sparse.csr"):
    _NPY_ALLOWED[(_mod, "csr_matrix")] = _PickledCSR


def _csr_from_state(holder: _PickledCSR, path: Path) -> Any:
    """A ``scipy.sparse.csr_matrix`` from the checked arrays of a pickled one."""
    state = holder.state[0] if isinstance(holder.state, tuple) and holder.state else holder.state
    return sparse_from_state(state, "csr", path)


def _rebuild_sparse(obj: Any, path: Path, memo: Optional[dict[int, Any]] = None) -> Any:
    """Replace every :class:`_PickledCSR` inside dicts, lists, tuples and object arrays by its matrix.

    Each distinct container is visited once (shared references stay shared) and one without
    a sparse matrix inside is returned as it is, so the cost follows the size of the file,
    not the size its shared references expand to.
    """
    memo = {} if memo is None else memo
    if not isinstance(obj, (_PickledCSR, dict, list, tuple, np.ndarray)) or (
        isinstance(obj, np.ndarray) and obj.dtype != object
    ):
        return obj
    key = id(obj)  # every object stays alive through the root for the whole walk: ids are not reused
    if key in memo:
        return memo[key]
    out: Any = obj
    if isinstance(obj, _PickledCSR):
        out = _csr_from_state(obj, path)
    elif isinstance(obj, dict):
        items = {k: _rebuild_sparse(v, path, memo) for k, v in obj.items()}
        if any(items[k] is not v for k, v in obj.items()):
            out = items
    elif isinstance(obj, (list, tuple)):
        values = [_rebuild_sparse(v, path, memo) for v in obj]
        if any(a is not b for a, b in zip(values, obj, strict=True)):
            out = type(obj)(values)
    else:
        values = [_rebuild_sparse(v, path, memo) for v in obj.reshape(-1)]
        if any(a is not b for a, b in zip(values, obj.reshape(-1), strict=True)):
            out = np.empty(obj.shape, dtype=object)
            for i, v in enumerate(values):
                out.flat[i] = v
    memo[key] = out
    return out


class NpyUnpickler(CappedUnpickler):
    """Unpickler for the object payload of ``np.save``-d dicts/arrays.

    Resolves only numpy's array/dtype/scalar reconstructors; dicts, lists, tuples, strings
    and numbers need no global. Anything else raises :class:`UnsafePickleError` naming the
    file and the refused global — nothing from the file is executed. :meth:`load` refuses
    data past the element / depth caps of :func:`~hogsa_loader.io.pickle_caps.check_unpickled`
    (``file_size``: the file's size in bytes, which raises the element cap to it).
    """

    file_kind = "an ARCTIC .npy file"

    def __init__(self, file: Any, path: PathLike = "<npy>", file_size: int = 0) -> None:
        super().__init__(file, path, file_size)

    def resolve(self, module: str, name: str) -> Any:
        try:
            return _NPY_ALLOWED[(module, name)]
        except KeyError:
            raise UnsafePickleError(
                self._path,
                f"refusing to load global '{module}.{name}': only numpy arrays, numbers, "
                "strings, lists and dicts may appear in an ARCTIC .npy file (nothing was executed)",
            ) from None


class _CappedReader:
    """File wrapper that never asks the OS for more bytes than the file has left.

    A corrupted length field in a pickle then reads a short block (pickle reports the
    truncation) instead of allocating the corrupted size.
    """

    def __init__(self, fh: io.BufferedReader, end: int) -> None:
        self._fh = fh
        self._end = end

    def _left(self) -> int:
        return max(self._end - self._fh.tell(), 0)

    def read(self, n: int = -1) -> bytes:
        left = self._left()
        return self._fh.read(left if n is None or n < 0 or n > left else n)

    def readline(self, size: int = -1) -> bytes:
        left = self._left()
        return self._fh.readline(left if size is None or size < 0 or size > left else size)

    def readinto(self, buf: Any) -> int:
        # every view is released before returning: the caller may free ``buf`` right after
        with memoryview(buf) as mv, mv.cast("B") as view:
            n = min(len(view), self._left())
            with view[:n] as part:
                return self._fh.readinto(part) or 0


def _read_npy_header(fh: io.BufferedReader, path: Path) -> tuple[np.dtype, bool, tuple[int, ...]]:
    """Parse the ``.npy`` magic and header dict (versions 1, 2 and 3) without numpy's loader."""
    magic = fh.read(8)
    if len(magic) < 8 or magic[:6] != b"\x93NUMPY":
        raise AssetError(path, "not a .npy file (bad magic bytes, or the file is empty/truncated)")
    major = magic[6]
    if major == 1:
        raw_len = fh.read(2)
        hlen = int.from_bytes(raw_len, "little") if len(raw_len) == 2 else -1
    elif major in (2, 3):
        raw_len = fh.read(4)
        hlen = int.from_bytes(raw_len, "little") if len(raw_len) == 4 else -1
    else:
        raise AssetError(path, f"unsupported .npy format version {major}.{magic[7]}")
    if hlen < 0 or hlen > MAX_NPY_HEADER:
        raise AssetError(path, f".npy header length {hlen} is invalid (file truncated or corrupt)")
    header = fh.read(hlen)
    if len(header) != hlen:
        raise AssetError(path, ".npy header is truncated")
    try:
        text = header.decode("utf8" if major == 3 else "latin1")
        d = ast.literal_eval(text)
    except (ValueError, SyntaxError, UnicodeDecodeError, MemoryError, RecursionError) as exc:
        raise AssetError(path, f".npy header cannot be parsed ({type(exc).__name__})") from None
    if not isinstance(d, dict) or set(d) != {"descr", "fortran_order", "shape"}:
        raise AssetError(path, ".npy header must be a dict with keys descr, fortran_order, shape")
    shape = d["shape"]
    if not isinstance(shape, tuple) or not all(
        isinstance(s, int) and not isinstance(s, bool) and s >= 0 for s in shape
    ):
        raise AssetError(path, f".npy header has an invalid shape {shape!r}")
    if not isinstance(d["fortran_order"], bool):
        raise AssetError(path, ".npy header has a non-boolean fortran_order")
    try:
        dtype = np.lib.format.descr_to_dtype(d["descr"])
    except Exception as exc:  # numpy raises TypeError/ValueError/KeyError on bad descr
        raise AssetError(path, f".npy header has an invalid dtype {d['descr']!r} ({exc})") from None
    return dtype, d["fortran_order"], shape


def read_npy(path: PathLike) -> Any:
    """Read an ``np.save``-d file without ever running arbitrary pickle code.

    Numeric (non-object) arrays are read directly from the bytes after the header.
    Object arrays (``np.save`` of a dict, as ARCTIC's raw sequences) are unpickled with
    :class:`NpyUnpickler`; a 0-d object array is unwrapped (``.item()``), as ARCTIC does.

    Args:
        path: the ``.npy`` file.

    Returns:
        a numpy array, or the Python object (usually a dict) stored in a 0-d object array.

    Raises:
        AssetError: missing, truncated or corrupt file (message names it).
        UnsafePickleError: the pickle references a global outside the allow-list.
    """
    p = Path(path)
    if not p.is_file():
        raise AssetError(p, "file is missing")
    try:
        size = p.stat().st_size
        with open(p, "rb") as fh:
            dtype, fortran, shape = _read_npy_header(fh, p)
            if dtype.hasobject:
                try:
                    obj = NpyUnpickler(_CappedReader(fh, size), p, file_size=size).load()
                except AssetError:  # refused global, element / depth caps
                    raise
                except Exception as exc:  # the unpickler runs no user code; any failure = corrupt
                    raise AssetError(
                        p, f"pickled payload is corrupt or truncated ({type(exc).__name__}: {exc})"
                    ) from None
                if not isinstance(obj, np.ndarray) or obj.dtype != object or obj.shape != shape:
                    raise AssetError(p, f"pickled payload is not the object array announced by the header {shape}")
                return _rebuild_sparse(obj.item() if obj.shape == () else obj, p)
            count = math.prod(shape)
            nbytes = count * dtype.itemsize
            left = size - fh.tell()
            if nbytes > left:
                raise AssetError(p, f"file is truncated: array {shape} {dtype} needs {nbytes} bytes, {left} present")
            data = fh.read(nbytes)
    except OSError as exc:
        raise AssetError(p, f"cannot read file ({exc})") from None
    if dtype.itemsize == 0:
        raise AssetError(p, f"array dtype {dtype} has zero-sized items")
    arr = np.frombuffer(data, dtype=dtype, count=count)
    return arr.reshape(shape, order="F" if fortran else "C").copy()
