"""MANO file I/O: legacy pickle schema, restricted unpickling, npz conversion, validation."""

from __future__ import annotations

import io
import os
import pickle
import pickletools

import numpy as np
import pytest

from hogsa_loader.assets.hands.mano_io import RestrictedUnpickler, convert_mano_to_npz, load_mano
from hogsa_loader.errors import AssetError, UnsafePickleError
from hogsa_world.mano_pickle import write_mano_pickle


def _globals_in(path) -> set[str]:
    data = open(path, "rb").read()
    return {arg for op, arg, _ in pickletools.genops(data) if op.name == "GLOBAL"}


def test_written_pickle_uses_the_legacy_mano_schema(mano_dir):
    names = _globals_in(mano_dir / "MANO_RIGHT.pkl")
    assert "chumpy.ch Ch" in names
    assert "numpy.core.multiarray _reconstruct" in names
    assert "scipy.sparse.csc csc_matrix" in names
    assert "copy_reg _reconstructor" in names
    # like the official file, a plain unpickle needs chumpy
    with pytest.raises(ModuleNotFoundError, match="chumpy"):
        with open(mano_dir / "MANO_RIGHT.pkl", "rb") as fh:
            pickle.load(fh, encoding="latin1")


def test_raw_keys_and_types_match_mano(mano_dir, chumpy_shim):
    with open(mano_dir / "MANO_LEFT.pkl", "rb") as fh:
        raw = pickle.load(fh, encoding="latin1")
    for key in (
        "v_template",
        "shapedirs",
        "posedirs",
        "J_regressor",
        "weights",
        "kintree_table",
        "f",
        "hands_components",
        "hands_mean",
        "hands_coeffs",
        "J",
        "bs_style",
        "bs_type",
    ):
        assert key in raw, key
    import scipy.sparse as sp

    V = raw["v_template"].shape[0]
    assert sp.issparse(raw["J_regressor"]) and raw["J_regressor"].shape == (16, V)
    assert raw["posedirs"].shape == (V, 3, 135)
    assert raw["shapedirs"].shape == (V, 3, 10)
    assert raw["kintree_table"].shape == (2, 16)
    assert raw["hands_components"].shape == (45, 45)
    assert raw["hands_coeffs"].shape[1] == 45 and raw["hands_coeffs"].shape[0] > 1000


def test_pickle_round_trip_is_exact(mano_dir, hand_pair):
    right, left = hand_pair
    for model, name in ((right, "MANO_RIGHT.pkl"), (left, "MANO_LEFT.pkl")):
        got = load_mano(mano_dir / name)
        assert got.side == model.side
        for field in (
            "v_template",
            "shapedirs",
            "posedirs",
            "J_regressor",
            "weights",
            "hands_components",
            "hands_mean",
            "hands_coeffs",
        ):
            np.testing.assert_array_equal(getattr(got, field), getattr(model, field), err_msg=field)
        np.testing.assert_array_equal(got.faces, model.faces)
        np.testing.assert_array_equal(got.parents, model.parents)
        np.testing.assert_array_equal(got.tip_vertex_ids, model.tip_vertex_ids)
        assert set(got.contact_vertex_ids) == set(model.contact_vertex_ids)
        np.testing.assert_allclose(got.vertex_colors, model.vertex_colors, atol=1e-6)


def test_folder_and_side(mano_dir):
    assert load_mano(mano_dir, side="left").side == "left"
    with pytest.raises(AssetError, match="side"):
        load_mano(mano_dir)


class _Evil:
    def __init__(self, cmd):
        self.cmd = cmd

    def __reduce__(self):
        return (os.system, (self.cmd,))


class _EvalEvil:
    def __reduce__(self):
        return (eval, ("__import__('os').getcwd()",))


@pytest.mark.parametrize("payload_kind", ["os.system", "eval", "nested"])
def test_code_executing_pickle_is_refused(tmp_path, payload_kind):
    marker = tmp_path / "pwned"
    if payload_kind == "os.system":
        payload = {"v_template": _Evil(f"touch {marker}")}
    elif payload_kind == "eval":
        payload = {"v_template": np.zeros((3, 3)), "f": _EvalEvil()}
    else:
        payload = {"shapedirs": [np.zeros(3), {"deep": _Evil(f"touch {marker}")}]}
    bad = tmp_path / "MANO_RIGHT.pkl"
    bad.write_bytes(pickle.dumps(payload, protocol=2))
    with pytest.raises(UnsafePickleError) as info:
        load_mano(bad)
    assert str(bad) in str(info.value)
    assert "refusing" in str(info.value)
    assert not marker.exists()


def test_unpickler_allows_only_listed_globals():
    buf = io.BytesIO(pickle.dumps(np.arange(3.0), protocol=2))
    np.testing.assert_array_equal(RestrictedUnpickler(buf).load(), np.arange(3.0))
    buf = io.BytesIO(pickle.dumps(io.BytesIO, protocol=2))
    with pytest.raises(UnsafePickleError, match="_io.BytesIO"):
        RestrictedUnpickler(buf).load()


def test_crafted_pickles_cannot_patch_scipy_or_escape_the_error_handling(tmp_path, mano_dir):
    import scipy.sparse as sp

    from hogsa_loader.assets.hands.mano_io import model_from_dict
    from hogsa_loader.io.mano_pickle import _chumpy_stub

    original = sp.csc_matrix.toarray
    # BUILD on the allow-listed class object: setattr(csc_matrix, "toarray", codecs.encode)
    patch = b"\x80\x02cscipy.sparse\ncsc_matrix\nN}Vtoarray\nc_codecs\nencode\ns\x86b0}."
    bad = tmp_path / "MANO_RIGHT.pkl"
    bad.write_bytes(patch)
    with pytest.raises(AssetError, match="missing MANO keys"):
        load_mano(bad)
    assert sp.csc_matrix.toarray is original and sp.csc_matrix([[1.0]]).toarray()[0, 0] == 1.0
    # an allow-listed callable raising an unusual error: still an AssetError naming the file
    bad.write_bytes(b"\x80\x02c_codecs\nencode\nVabc\nVno-such-codec\n\x86R.")
    with pytest.raises(AssetError, match="not a readable MANO pickle") as info:
        load_mano(bad)
    assert str(bad) in str(info.value)
    with open(mano_dir / "MANO_RIGHT.pkl", "rb") as fh:
        good = RestrictedUnpickler(fh).load()
    # a chumpy object holding itself, and a sparse matrix of absurd size
    stub = _chumpy_stub("chumpy.ch", "Ch")
    loop = stub.__new__(stub)
    loop.__setstate__({"x": loop})
    with pytest.raises(AssetError, match="nested too deeply"):
        model_from_dict({**good, "v_template": loop}, source="loop.pkl")
    with pytest.raises(AssetError, match="larger than 50000000 elements dense"):
        model_from_dict({**good, "J_regressor": sp.csc_matrix((10**6, 10**6))}, source="huge.pkl")
    ref = model_from_dict(good, source="MANO_RIGHT.pkl")  # the real file still loads
    # any in-memory sparse type still densifies (csr_array is not one of the pickled classes)
    other = model_from_dict({**good, "J_regressor": sp.csr_array(ref.J_regressor)}, source="MANO_RIGHT.pkl")
    np.testing.assert_array_equal(other.J_regressor, ref.J_regressor)


def test_npz_conversion_round_trip_and_no_pickle(mano_dir, tmp_path, hand_pair):
    out = tmp_path / "MANO_RIGHT.npz"
    convert_mano_to_npz(mano_dir / "MANO_RIGHT.pkl", out)
    got = load_mano(out)
    np.testing.assert_array_equal(got.v_template, hand_pair[0].v_template)
    np.testing.assert_array_equal(got.J_regressor, hand_pair[0].J_regressor)
    np.testing.assert_array_equal(got.tip_vertex_ids, hand_pair[0].tip_vertex_ids)
    # an npz carrying pickled objects is refused
    evil = tmp_path / "MANO_LEFT.npz"
    np.savez(evil, v_template=np.array([_Evil("true")], dtype=object))
    with pytest.raises(AssetError, match="pickled objects"):
        load_mano(evil)


@pytest.mark.parametrize(
    "mutate, message",
    [
        (lambda d: d.pop("weights"), "missing MANO keys"),
        (lambda d: d.__setitem__("posedirs", np.zeros((5, 3, 135))), "posedirs must be"),
        (lambda d: d.__setitem__("v_template", np.full_like(d["v_template"], np.nan)), "NaN"),
        (lambda d: d.__setitem__("f", np.array([[0, 1, 10**7]])), "faces must be"),
        (
            lambda d: d.__setitem__("kintree_table", np.array([[0, 5, 0], [0, 1, 2]])),
            "J_regressor must be|posedirs must be|kintree",
        ),
    ],
)
def test_bad_model_files_raise_clear_errors(tmp_path, mano_dir, chumpy_shim, mutate, message):
    with open(mano_dir / "MANO_RIGHT.pkl", "rb") as fh:
        raw = pickle.load(fh, encoding="latin1")
    raw["shapedirs"] = np.asarray(raw["shapedirs"])
    mutate(raw)
    path = tmp_path / "MANO_RIGHT.npz"
    raw.pop("hogsa_meta")
    np.savez(path, **{k: (np.asarray(v.toarray()) if hasattr(v, "toarray") else np.asarray(v)) for k, v in raw.items()})
    with pytest.raises(AssetError, match=message) as info:
        load_mano(path, tip_vertex_ids=(0, 1, 2, 3, 4))
    assert str(path) in str(info.value)


def test_missing_file_says_what_to_do(tmp_path):
    with pytest.raises(AssetError, match="not found") as info:
        load_mano(tmp_path / "MANO_RIGHT.pkl")
    assert "hogsa assets" in str(info.value)


def test_truncated_pickle_is_a_clear_error(tmp_path, mano_dir):
    data = (mano_dir / "MANO_RIGHT.pkl").read_bytes()
    bad = tmp_path / "MANO_RIGHT.pkl"
    bad.write_bytes(data[: len(data) // 3])
    with pytest.raises(AssetError, match="not a readable MANO pickle"):
        load_mano(bad)


def test_unknown_vertex_count_needs_tips(tmp_path, hand_pair):
    m = hand_pair[0]
    stripped = m.replace(meta={})
    path = tmp_path / "MANO_RIGHT.pkl"
    write_mano_pickle(stripped, path)
    # metadata written by the writer always carries tips; remove them to mimic a foreign file
    with open(path, "rb") as fh:
        raw = RestrictedUnpickler(fh, path).load()
    raw.pop("hogsa_meta")
    raw["shapedirs"] = raw["shapedirs"].to_array()
    raw["J_regressor"] = raw["J_regressor"].toarray()
    np.savez(tmp_path / "MANO_RIGHT.npz", **{k: np.asarray(v) for k, v in raw.items()})
    with pytest.raises(AssetError, match="no fingertip metadata"):
        load_mano(tmp_path / "MANO_RIGHT.npz")
    assert load_mano(tmp_path / "MANO_RIGHT.npz", tip_vertex_ids=(1, 2, 3, 4, 5)).tip_vertex_ids.tolist() == [
        1,
        2,
        3,
        4,
        5,
    ]


def _crafted_j_regressor(src, dst, tamper) -> None:
    """Copy the MANO pickle ``src`` to ``dst`` with the bytes of its J_regressor's CSC arrays
    replaced by ``tamper(indices, indptr)`` (arrays of the same byte length)."""
    import scipy.sparse as sp

    raw = src.read_bytes()
    jreg = sp.csc_matrix(load_mano(src).J_regressor)
    indices, indptr = jreg.indices.copy(), jreg.indptr.copy()
    new_indices, new_indptr = tamper(indices.copy(), indptr.copy())
    for old, new in ((indices, new_indices), (indptr, new_indptr)):
        assert raw.count(old.tobytes()) == 1 and len(new.tobytes()) == len(old.tobytes())
        raw = raw.replace(old.tobytes(), new.tobytes())
    dst.write_bytes(raw)


def _set(a, value):
    a[:] = value
    return a


_CRAFTED = [
    (lambda i, p: (_set(i, 2**30), p), r"'indices' holds indices in \[1073741824, 1073741824\], outside"),
    (lambda i, p: (_set(i, -5), p), r"'indices' holds indices in \[-5, -5\]"),
    (lambda i, p: (i, p[::-1].copy()), "'indptr' must start at 0, never decrease"),
    (lambda i, p: (i, _set(p, 2**30)), "'indptr' must start at 0"),
]


def test_crafted_sparse_j_regressor_is_refused_not_a_crash(tmp_path, mano_dir):
    """MANO pickles whose J_regressor has CSC indices out of range (once an out-of-bounds
    write in scipy's ``toarray``: SIGSEGV) or a broken ``indptr`` are refused with an
    AssetError naming the file and the field, by ``load_mano`` and by ``hogsa convert-mano``;
    they run in child processes so that a crash fails this test instead of killing the suite."""
    import re
    import subprocess
    import sys

    bad = []
    for k, (tamper, _) in enumerate(_CRAFTED):
        (tmp_path / str(k)).mkdir()
        bad.append(tmp_path / str(k) / "MANO_RIGHT.pkl")
        _crafted_j_regressor(mano_dir / "MANO_RIGHT.pkl", bad[-1], tamper)
    code = (
        "import sys\nfrom hogsa_loader.errors import AssetError\n"
        "from hogsa_loader.assets.hands.mano_io import load_mano\n"
        "for path in sys.argv[1:]:\n    try:\n        load_mano(path)\n        print('LOADED', path)\n"
        "    except AssetError as exc:\n        print('REFUSED', exc)\n"
    )
    run = subprocess.run([sys.executable, "-c", code, *map(str, bad)], capture_output=True, text=True, timeout=120)
    assert run.returncode == 0, (run.returncode, run.stderr[-2000:])
    lines = run.stdout.strip().splitlines()
    assert len(lines) == len(bad)
    for line, path, (_, message) in zip(lines, bad, _CRAFTED):
        assert line.startswith(f"REFUSED {path}") and "J_regressor" in line and re.search(message, line), line
    out = tmp_path / "out.npz"
    cli = subprocess.run(
        [sys.executable, "-m", "hogsa_loader.cli.main", "convert-mano", str(bad[0]), str(out)],
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert cli.returncode == 1, (cli.returncode, cli.stderr[-2000:])
    assert str(bad[0]) in cli.stderr and "J_regressor" in cli.stderr and not out.exists()


def test_sparse_from_state_checks_every_part():
    import scipy.sparse as sp

    from hogsa_loader.io.sparse import sparse_from_state

    dense = np.array([[0.0, 2.0, 0.0], [1.0, 0.0, 3.0]])
    for fmt, cls in (("csr", sp.csr_matrix), ("csc", sp.csc_matrix), ("coo", sp.coo_matrix)):
        state = dict(cls(dense).__dict__)
        np.testing.assert_array_equal(sparse_from_state(state, fmt, "m.pkl").toarray(), dense)
    good = dict(sp.csr_matrix(dense).__dict__)
    cases = [
        ({"data": good["data"][:-1]}, "lengths differ"),
        ({"indices": good["indices"].astype(np.float64)}, "'indices' must be a 1-D array"),
        ({"indices": np.full_like(good["indices"], 3)}, r"outside \[0, 3\)"),
        ({"indptr": good["indptr"][:-1]}, "'indptr' has 2 entries, the shape needs 3"),
        ({"indptr": np.array([1, 2, 3])}, "'indptr' must start at 0"),
        ({"indptr": np.array([0, 2, 1])}, "never decrease and end"),
        ({"_shape": (2, -3)}, "non-negative"),
        ({"_shape": (10**6, 10**6)}, "larger than"),
        ({"_shape": "2x3"}, "not a pair"),
        ({"data": None}, "'data' is missing"),
    ]
    for change, message in cases:
        state = {**good, **change}
        with pytest.raises(AssetError, match=message) as info:
            sparse_from_state(state, "csr", "m.pkl")
        assert "m.pkl" in str(info.value)
    coo = dict(sp.coo_matrix(dense).__dict__)
    row, col = coo["coords"]
    with pytest.raises(AssetError, match=r"'col' holds indices in \[0, 7\]"):
        sparse_from_state({**coo, "coords": (row, np.where(col == 2, 7, col))}, "coo", "m.pkl")
    with pytest.raises(AssetError, match="lengths differ"):
        sparse_from_state({**coo, "coords": (row[:-1], col)}, "coo", "m.pkl")
