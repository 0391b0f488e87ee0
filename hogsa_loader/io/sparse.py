"""Sparse matrices from untrusted files, checked before any compiled code touches them.

A pickled ``scipy.sparse`` matrix is only its state: ``data``, ``indices``, ``indptr`` (CSR /
CSC) or ``row``/``col`` (COO) and a shape. scipy's compiled routines (``toarray``,
``tocsr``, arithmetic) trust those arrays: an index out of range is an out-of-bounds write,
which crashes the process (SIGSEGV) instead of raising. :func:`sparse_from_state` checks every
part with numpy — types, dimensions, lengths, index ranges, a monotone ``indptr`` starting at
0, a bounded shape — and only then builds the matrix with scipy's public constructor. Every
reader of a file that may hold a sparse matrix goes through it.
"""

from __future__ import annotations

import math
from typing import Any, Literal, Mapping

import numpy as np
import scipy.sparse as sp

from hogsa_loader.errors import AssetError, PathLike

__all__ = ["MAX_SPARSE_DENSE", "MAX_SPARSE_NNZ", "sparse_from_state"]

#: Largest dense size (rows × columns) a sparse matrix read from a file may have. The largest
#: sparse arrays of the formats read here (MANO's ``J_regressor``, ARCTIC's object
#: downsamplers: 600 × vertices) are under 10 M elements.
MAX_SPARSE_DENSE = 50_000_000
#: Largest number of stored entries.
MAX_SPARSE_NNZ = 50_000_000

Format = Literal["csr", "csc", "coo"]


def _vector(state: Mapping[str, Any], key: str, kinds: str, where: PathLike, what: str) -> np.ndarray:
    value = state.get(key)
    if not isinstance(value, np.ndarray):
        raise AssetError(where, f"{what}: '{key}' is missing or not an array (found {type(value).__name__})")
    if value.ndim != 1 or value.dtype.kind not in kinds:
        raise AssetError(
            where, f"{what}: '{key}' must be a 1-D array of kind {kinds!r}, got {value.dtype} {value.shape}"
        )
    if value.dtype == np.float16:  # scipy's sparse routines have no half-precision kernels
        raise AssetError(where, f"{what}: '{key}' is float16, which scipy's sparse matrices do not support")
    if value.size > MAX_SPARSE_NNZ + 1:
        raise AssetError(where, f"{what}: '{key}' has {value.size} entries, more than {MAX_SPARSE_NNZ}")
    return value


def _in_range(values: np.ndarray, n: int, key: str, where: PathLike, what: str) -> None:
    if values.size and (int(values.min()) < 0 or int(values.max()) >= n):
        raise AssetError(
            where, f"{what}: '{key}' holds indices in [{int(values.min())}, {int(values.max())}], outside [0, {n})"
        )


def _shape(state: Mapping[str, Any], where: PathLike, what: str) -> tuple[int, int]:
    shape = state.get("_shape", state.get("shape"))
    if not isinstance(shape, (tuple, list)) or len(shape) != 2:
        raise AssetError(where, f"{what}: shape {shape!r:.60} is not a pair of sizes")
    if any(isinstance(s, (bool, np.bool_)) or not isinstance(s, (int, np.integer)) for s in shape):
        raise AssetError(where, f"{what}: shape {shape!r:.60} is not a pair of integers")
    dims = tuple(int(s) for s in shape)
    if any(s < 0 for s in dims):
        raise AssetError(where, f"{what}: shape {shape!r:.60} is not a pair of non-negative integers")
    if math.prod(dims) > MAX_SPARSE_DENSE:
        raise AssetError(where, f"{what}: shape {dims} is larger than {MAX_SPARSE_DENSE} elements dense")
    return dims  # type: ignore[return-value]


def sparse_from_state(state: Mapping[str, Any], fmt: Format, where: PathLike) -> sp.spmatrix:
    """A scipy sparse matrix rebuilt from the checked parts of a pickled one.

    Args:
        state: the pickled matrix's attribute dict: ``data`` (nnz,) numeric; ``indices``
            (nnz,) and ``indptr`` (major + 1,) integers for ``"csr"`` / ``"csc"``; ``row``,
            ``col`` (nnz,) integers, or ``coords`` (a pair of them), for ``"coo"``; ``_shape``
            (or ``shape``) a pair of non-negative integers. Other keys are ignored.
        fmt: the matrix's format.
        where: the file, named in errors.

    Returns:
        a new ``csr_matrix`` / ``csc_matrix`` / ``coo_matrix`` of the checked arrays (copies).

    Raises:
        AssetError: a part missing, of the wrong type or dimension, lengths that disagree,
            an index outside the shape, an ``indptr`` that does not start at 0 or decreases,
            or a shape past :data:`MAX_SPARSE_DENSE`. Nothing compiled has run on the parts.
    """
    what = f"pickled {fmt} sparse matrix"
    if not isinstance(state, Mapping):
        raise AssetError(where, f"{what} has no state dict")
    rows, cols = _shape(state, where, what)
    data = _vector(state, "data", "biuf", where, what)
    if fmt == "coo":
        coords = state.get("coords")
        if coords is not None:
            if not isinstance(coords, (tuple, list)) or len(coords) != 2:
                raise AssetError(where, f"{what}: 'coords' is not a pair of index arrays")
            coords_state = {"row": coords[0], "col": coords[1]}
        else:
            coords_state = state
        row = _vector(coords_state, "row", "iu", where, what)
        col = _vector(coords_state, "col", "iu", where, what)
        if not (len(row) == len(col) == len(data)):
            raise AssetError(where, f"{what}: row, col and data lengths differ ({len(row)}, {len(col)}, {len(data)})")
        _in_range(row, rows, "row", where, what)
        _in_range(col, cols, "col", where, what)
        return sp.coo_matrix((data.copy(), (row.astype(np.int64), col.astype(np.int64))), shape=(rows, cols))
    major, minor = (rows, cols) if fmt == "csr" else (cols, rows)
    indices = _vector(state, "indices", "iu", where, what)
    indptr = _vector(state, "indptr", "iu", where, what)
    if len(indptr) != major + 1:
        raise AssetError(where, f"{what}: 'indptr' has {len(indptr)} entries, the shape needs {major + 1}")
    if len(indices) != len(data):
        raise AssetError(where, f"{what}: 'indices' ({len(indices)}) and 'data' ({len(data)}) lengths differ")
    ptr = indptr.astype(np.int64)
    if int(ptr[0]) != 0 or int(ptr[-1]) != len(indices) or (len(ptr) > 1 and bool(np.any(np.diff(ptr) < 0))):
        raise AssetError(
            where, f"{what}: 'indptr' must start at 0, never decrease and end at the {len(indices)} stored entries"
        )
    _in_range(indices, minor, "indices", where, what)
    cls = sp.csr_matrix if fmt == "csr" else sp.csc_matrix
    mat = cls((data.copy(), indices.astype(np.int64), ptr), shape=(rows, cols))
    mat.check_format(full_check=True)
    return mat
