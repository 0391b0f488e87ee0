"""Careless and hostile use : every reproduction refused cleanly, at its source.

Each test names the item it covers: existing runs never silently replaced, checkpoint and
bundle files hash-checked and confined, pickle bombs refused before allocation, arguments
checked before any work, no leftovers after failures, exports read as their index says,
checkpoint bytes reproducible.
"""

from __future__ import annotations

import hashlib
import json
import pickle
import shutil
import time
from pathlib import Path

import numpy as np
import pytest
import torch
from conftest import job

from hogsa_loader.errors import AssetError

pytestmark = pytest.mark.robustness

ROOT = Path(__file__).resolve().parents[2]


_JOBS = {"train_hogs": "hogs", "train_srm": "srm", "train_contactnet": "contactnet", "build_pose_bank": "bank"}


def _script(name: str):
    mod = job(_JOBS.get(name, name))
    return mod


def _one_line(err: str, *needles: str) -> None:
    assert err.count("\n") == 1 and "Traceback" not in err, err
    for n in needles:
        assert n in err, (n, err)


def _hogs_args(world: Path, out: Path, iters: int = 2) -> list[str]:
    return [
        "--data",
        str(world),
        "--subject",
        "s01",
        "--object",
        "box",
        "--out",
        str(out),
        "--image-size",
        "32",
        "--frame-stride",
        "8",
        "--eval-every-frame",
        "2",
        "--max-eval",
        "1",
        "--run-eval-every",
        "0",
        "--run-ckpt-every",
        "1",
        "--model-k",
        "1",
        "--model-sh-degree",
        "0",
        "--optim-sh-warmup",
        "0",
        "--run-strip-views",
        "1",
        "--optim-iters",
        str(iters),
        "--quiet",
    ]


@pytest.fixture(scope="module")
def hogs_run(tiny_world, tmp_path_factory) -> Path:
    """A finished 2-step HOGS run (checkpointed every step) written by train_hogs.py."""
    out = tmp_path_factory.mktemp("hogs") / "run"
    assert _script("train_hogs").main(_hogs_args(tiny_world, out)) == 0
    return out


# ---------------------------------------------------------------------------- training runs are not replaced silently
def test_rerun_without_resume_is_refused_and_keeps_the_checkpoints(tiny_world, hogs_run, tmp_path, capsys):
    run = tmp_path / "run"
    shutil.copytree(hogs_run, run)
    before = sorted(p.name for p in (run / "checkpoints").iterdir())
    capsys.readouterr()
    assert _script("train_hogs").main(_hogs_args(tiny_world, run)) == 2
    _one_line(capsys.readouterr().err, "hogsa train hogs: error:", "--resume", "--overwrite")
    assert sorted(p.name for p in (run / "checkpoints").iterdir()) == before
    # the library refuses too, at the start of training
    from hogsa_loader.train import HogsTrainer
    from hogsa_loader.train.run_folder import RunExistsError

    cfg = _script("train_hogs").parse_args(_hogs_args(tiny_world, run))
    with pytest.raises(RunExistsError, match="--resume"):
        HogsTrainer(cfg, progress=False).train()
    assert sorted(p.name for p in (run / "checkpoints").iterdir()) == before
    # --overwrite starts again from step 0 in an emptied folder (nothing of the old run is left)
    (run / "stale.txt").write_text("old")
    (run / "metrics.json").write_text("{}")
    assert _script("train_hogs").main(_hogs_args(tiny_world, run, iters=1) + ["--overwrite"]) == 0
    assert json.loads((run / "checkpoints" / "latest.json").read_text())["step"] == 1
    assert not (run / "stale.txt").exists() and json.loads((run / "metrics.json").read_text())
    assert _script("train_hogs").main(_hogs_args(tiny_world, run) + ["--resume", "--overwrite"]) == 2


# ---------------------------------------------------------------------------- trainer state checked on resume
def test_corrupt_trainer_state_is_refused_on_resume(tiny_world, hogs_run, tmp_path, capsys):
    run = tmp_path / "run"
    shutil.copytree(hogs_run, run)
    folder = run / "checkpoints" / json.loads((run / "checkpoints" / "latest.json").read_text())["folder"]
    state = json.loads((folder / "trainer.json").read_text())
    tpath = folder / "trainer.safetensors"
    assert state["tensors_sha256"] == hashlib.sha256(tpath.read_bytes()).hexdigest()
    blob = bytearray(tpath.read_bytes())
    blob[-7] ^= 0xFF  # a flipped byte in an Adam moment
    tpath.write_bytes(bytes(blob))
    capsys.readouterr()
    script = _script("train_hogs")

    def no_trainer(*args, **kwargs):
        raise AssertionError("the trainer was built (data read) before the checkpoint was checked")

    script.HogsTrainer = no_trainer  # every refusal below comes before any data is read
    assert script.main(_hogs_args(tiny_world, run, iters=4) + ["--resume"]) == 1
    _one_line(capsys.readouterr().err, "trainer.safetensors", "sha256")
    # a checkpoint without the hash (pre-1.0) is refused
    del state["tensors_sha256"]
    (folder / "trainer.json").write_text(json.dumps(state))
    assert script.main(_hogs_args(tiny_world, run, iters=4) + ["--resume"]) == 1
    _one_line(capsys.readouterr().err, "trainer.json", "tensors_sha256")
    # NaN moments and truncation are refused even when the hash matches the file
    from safetensors.torch import save

    def put(blob: bytes) -> None:
        tpath.write_bytes(blob)
        (folder / "trainer.json").write_text(json.dumps({**state, "tensors_sha256": hashlib.sha256(blob).hexdigest()}))

    good = _good_trainer_tensors(hogs_run)
    bad = {k: v.clone() for k, v in good.items()}
    name = next(k for k in bad if k.endswith("exp_avg"))
    bad[name].view(-1)[0] = float("nan")
    put(save(bad))
    assert script.main(_hogs_args(tiny_world, run, iters=4) + ["--resume"]) == 1
    _one_line(capsys.readouterr().err, "trainer.safetensors", "NaN")
    put(save(good)[:100])
    assert script.main(_hogs_args(tiny_world, run, iters=4) + ["--resume"]) == 1
    _one_line(capsys.readouterr().err, "trainer.safetensors", "not a valid safetensors")
    # malformed bookkeeping files: one-line errors naming them
    (run / "checkpoints" / "latest.json").write_text("garbage{")
    assert script.main(_hogs_args(tiny_world, run, iters=4) + ["--resume"]) == 1
    _one_line(capsys.readouterr().err, "latest.json", "malformed JSON")
    (run / "checkpoints" / "latest.json").write_text(json.dumps({"step": 1, "folder": "../../etc"}))
    assert script.main(_hogs_args(tiny_world, run, iters=4) + ["--resume"]) == 1
    _one_line(capsys.readouterr().err, "latest.json", "step_N")


def _good_trainer_tensors(run: Path) -> dict[str, torch.Tensor]:
    from safetensors.torch import load_file

    folder = run / "checkpoints" / json.loads((run / "checkpoints" / "latest.json").read_text())["folder"]
    return load_file(str(folder / "trainer.safetensors"))


# ---------------------------------------------------------------------------- moved run folders
def test_moved_run_folder_resumes(tiny_world, hogs_run, tmp_path):
    from hogsa_loader.train import HogsTrainer

    moved = tmp_path / "elsewhere" / "moved_run"
    shutil.copytree(hogs_run, moved)
    cfg = _script("train_hogs").parse_args(_hogs_args(tiny_world, moved, iters=3))
    tr = HogsTrainer(cfg, progress=False)
    assert tr.resume() and tr.step == 2
    cfg_other = _script("train_hogs").parse_args(_hogs_args(tiny_world, moved, iters=3) + ["--seed", "5"])
    with pytest.raises(ValueError, match="seed"):  # other settings still have to match
        HogsTrainer(cfg_other, progress=False).resume()


# ---------------------------------------------------------------------------- convert-mano
def test_convert_mano_dangling_link_destination_and_finite_numbers(mano_dir, tmp_path):
    """A destination that is a dangling symbolic link is an existing file (not a crash), and
    numeric flags refuse infinity."""
    import argparse

    from hogsa_loader.assets.hands.mano_io import convert_mano_to_npz
    from hogsa_loader.cli import checks

    dst = tmp_path / "out.npz"
    dst.symlink_to(tmp_path / "nowhere.npz")
    with pytest.raises(AssetError, match="already exists"):
        convert_mano_to_npz(mano_dir / "MANO_RIGHT.pkl", dst)
    for bad in ("inf", "-inf", "nan", "0"):
        with pytest.raises(argparse.ArgumentTypeError):
            checks.positive_float(bad)
    assert checks.positive_float("1e-3") == 1e-3


def test_convert_mano_never_replaces_its_source_or_leaves_temporaries(mano_dir, tmp_path, capsys):
    from hogsa_loader.assets.hands.mano_io import convert_mano_to_npz
    from hogsa_loader.cli.main import main

    src = tmp_path / "MANO_RIGHT.pkl"
    shutil.copy(mano_dir / "MANO_RIGHT.pkl", src)
    before = src.read_bytes()
    assert main(["convert-mano", str(src), str(src)]) == 2
    _one_line(capsys.readouterr().err, "hogsa convert-mano: error:", ".npz")
    same = tmp_path / "MANO_RIGHT.npz"
    shutil.copy(src, same)  # a pickle named .npz, given as both source and destination
    assert main(["convert-mano", str(same), str(same), "--overwrite"]) == 2
    _one_line(capsys.readouterr().err, "input file itself")
    with pytest.raises(AssetError, match="source model itself"):
        convert_mano_to_npz(same, same, overwrite=True)
    assert src.read_bytes() == before
    folder = tmp_path / "DIR.npz"
    folder.mkdir()
    assert main(["convert-mano", str(src), str(folder)]) == 2
    _one_line(capsys.readouterr().err, "is a folder")
    dst = tmp_path / "out.npz"
    assert main(["convert-mano", str(src), str(dst)]) == 0
    assert main(["convert-mano", str(src), str(dst)]) == 2
    _one_line(capsys.readouterr().err, "already exists", "--overwrite")
    assert main(["convert-mano", str(src), str(dst), "--overwrite"]) == 0
    assert sorted(p.name for p in tmp_path.iterdir()) == ["DIR.npz", "MANO_RIGHT.npz", "MANO_RIGHT.pkl", "out.npz"]


# ---------------------------------------------------------------------------- unpickler caps
def _bomb(levels: int = 9, width: int = 10) -> list:
    x = [0.0] * width
    for _ in range(levels - 1):
        x = [x] * width  # the same list `width` times: one memo entry, `width` GET opcodes
    return x


def test_pickle_bomb_refused_before_allocation(tmp_path):
    from hogsa_loader.assets.arctic import read_npy
    from hogsa_loader.assets.hands.mano_io import load_mano

    pkl = tmp_path / "MANO_RIGHT.pkl"
    pkl.write_bytes(pickle.dumps({"v_template": _bomb()}, protocol=2))  # 10^9 elements
    assert pkl.stat().st_size < 400
    npy = tmp_path / "box_grab_01.mano.npy"
    np.save(npy, np.array({"rot": _bomb()}, dtype=object), allow_pickle=True)
    for read, path in ((load_mano, pkl), (read_npy, npy)):
        t0 = time.perf_counter()
        with pytest.raises(AssetError, match="more than .* elements"):
            read(path)
        assert time.perf_counter() - t0 < 2.0


def _raw_copy(world: Path, out: Path) -> Path:
    """misc.json and s01's raw sequences of ``world`` copied under ``out``; the copy's ``arctic_data/data``."""
    src, dst = world / "arctic_data" / "data", out / "arctic_data" / "data"
    (dst / "meta").mkdir(parents=True)
    shutil.copy2(src / "meta" / "misc.json", dst / "meta" / "misc.json")
    shutil.copytree(src / "raw_seqs" / "s01", dst / "raw_seqs" / "s01")
    return dst


def test_bomb_under_the_element_cap_stays_shared_and_is_refused_by_its_shape(tiny_world, tmp_path):
    """A raw sequence field of 10^7 shared numbers (under the 5·10^7 element cap): read_npy
    keeps the references shared (no copy per use) and the reader refuses the shape before
    any conversion."""
    from hogsa_loader.assets.arctic import ArcticRoot, read_npy

    dst = _raw_copy(tiny_world, tmp_path)
    mano_path = dst / "raw_seqs" / "s01" / "box_use_01.mano.npy"
    x: list = [0.5]
    for w in (10, 1000, 1000):
        x = [x] * w
    doc = read_npy(mano_path)
    doc["right"]["pose"] = x
    np.save(mano_path, np.array(doc, dtype=object), allow_pickle=True)
    back = read_npy(mano_path)
    assert back["right"]["pose"][0] is back["right"]["pose"][1]  # one shared row, not 1000 copies
    with pytest.raises(AssetError, match=r"right.pose is a nested list of shape 1000x1000x10x1, expected"):
        ArcticRoot(tmp_path).sequence("s01", "box_use_01")


def test_egocam_extras_are_checked_once_per_shared_container(tiny_world, tmp_path, monkeypatch):
    """Extra keys of an egocam file (kept as stored) are checked container by container: a
    field of 2,500 references to one list costs a handful of checks, not one per reference."""
    from hogsa_loader.assets import arctic
    from hogsa_loader.assets.arctic import ArcticRoot, read_npy

    dst = _raw_copy(tiny_world, tmp_path)
    ego_path = dst / "raw_seqs" / "s01" / "box_use_01.egocam.dist.npy"
    doc = read_npy(ego_path)
    row = [[0.5, 1.5]] * 50
    doc["R0"] = [row] * 50
    np.save(ego_path, np.array(doc, dtype=object), allow_pickle=True)
    calls = []
    check = arctic._plain_data
    monkeypatch.setattr(arctic, "_plain_data", lambda *a, **k: (calls.append(1), check(*a, **k))[1])
    raw = ArcticRoot(tmp_path).raw_sequence("s01", "box_use_01")
    assert raw.egocam_extra["R0"][0] is raw.egocam_extra["R0"][1]  # kept shared
    assert len(calls) < 500  # one check per reference would be > 2,600


def test_mano_list_bomb_under_the_element_cap_is_refused_before_conversion(hand_pair, tmp_path):
    """v_template as 3·10^7 shared numbers (under the 5·10^7 element cap) is refused by its
    shape, before np.asarray; so is a list of 2·10^6 (over the 10^6 list cap), and a list
    holding an integer beyond int64 is refused as not numeric."""
    from hogsa_loader.assets.hands import mano_io
    from hogsa_loader.io.pickle_caps import nested_shape
    from hogsa_world.mano_pickle import release_pickle_bytes

    x: list = [0.5]
    for w in (3, 1000, 10_000):
        x = [x] * w
    assert nested_shape(x) == (10_000, 1000, 3, 1)
    doc = mano_io.schema_dict(hand_pair[0])
    doc.update(v_template=x)
    path = tmp_path / "MANO_RIGHT.pkl"
    path.write_bytes(release_pickle_bytes(doc))
    with pytest.raises(AssetError, match=r"v_template.*nested list of shape 10000x1000x3x1 is far larger than any"):
        mano_io.load_mano(path)
    for value, message in (
        ([[[0.5] * 3] * 1000] * 2000, "nested list of shape 2000x1000x3 is far larger"),
        ([[2**70, 1, 2]], "expected a numeric array, got dtype object"),
    ):
        doc.update(v_template=value)
        path.write_bytes(release_pickle_bytes(doc))
        with pytest.raises(AssetError, match=message):
            mano_io.load_mano(path)


@pytest.mark.parametrize("kind", ["list", "tuple", "dict", "set", "object array", "stub state"])
def test_element_cap_counts_every_container_and_shared_reference(kind):
    from hogsa_loader.io.mano_pickle import ChumpyStub
    from hogsa_loader.io.pickle_caps import check_unpickled

    leaf = list(range(10))
    if kind == "list":
        obj = [leaf] * 10
    elif kind == "tuple":
        obj = tuple([tuple(leaf)] * 10)
    elif kind == "dict":
        obj = {i: leaf for i in range(10)}
    elif kind == "set":
        obj = [frozenset(leaf)] * 10
    elif kind == "object array":
        obj = np.empty(10, dtype=object)
        obj[:] = [leaf] * 10
    else:
        obj = ChumpyStub()
        obj.__setstate__({"x": [leaf] * 10})
    n = check_unpickled(obj, "f.pkl", max_elements=200)
    assert 100 <= n <= 200  # shared references count once per use
    with pytest.raises(AssetError, match="more than 99 elements"):
        check_unpickled(obj, "f.pkl", max_elements=99)


def test_long_strings_shared_many_times_count_their_bytes(tmp_path):
    """One 1 MB byte string referenced many times is as large as its bytes times the uses
    once turned into an array: it is counted by its bytes, not as one element per use (also
    through the MANO reader, whose default cap is 50 M elements)."""
    import pickle

    from hogsa_loader.assets.hands.mano_io import load_mano
    from hogsa_loader.io.pickle_caps import check_unpickled

    blob = [b"x" * 1_000_000] * 50
    with pytest.raises(AssetError, match="more than"):
        check_unpickled(blob, "f.pkl", max_elements=1_000_000)
    assert check_unpickled([b"x" * 80] * 3, "f.pkl") == 3 * 10
    assert check_unpickled(np.zeros(2, dtype="S800"), "f.pkl") == 200
    path = tmp_path / "MANO_RIGHT.pkl"
    path.write_bytes(pickle.dumps({"v_template": [b"x" * 1_000_000] * 500}, protocol=2))  # 1 MB file, 500 MB array
    with pytest.raises(AssetError, match="more than"):
        load_mano(path)


def test_depth_cap_and_cycles():
    from hogsa_loader.io.pickle_caps import check_unpickled

    deep: list = []
    for _ in range(40):
        deep = [deep]
    with pytest.raises(AssetError, match="nested more than 32"):
        check_unpickled(deep, "f.pkl")
    cyc: list = []
    cyc.append(cyc)
    with pytest.raises(AssetError, match="cycle"):
        check_unpickled(cyc, "f.pkl")
    # a pickle of a deep nesting (no Python recursion while loading) is refused the same way
    blob = b"\x80\x02" + b"]" * 10_000 + b"a" * 9_999 + b"."
    import io

    from hogsa_loader.assets.hands.mano_io import RestrictedUnpickler

    with pytest.raises(AssetError, match="nested"):
        RestrictedUnpickler(io.BytesIO(blob), "deep.pkl").load()


# ---------------------------------------------------------------------------- bundles
def _edit_bundle(src: Path, dst: Path, edit) -> Path:
    shutil.copytree(src, dst)
    man = json.loads((dst / "manifest.json").read_text())
    edit(man)
    (dst / "manifest.json").write_text(json.dumps(man))
    return dst


def test_bundle_paths_are_confined(untrained_bundle, tmp_path):
    from hogsa_loader.models.bundle import load_bundle

    load_bundle(untrained_bundle)
    secret = tmp_path / "secret.txt"
    secret.write_text("not for the loader")
    sha = hashlib.sha256(secret.read_bytes()).hexdigest()

    def escape(man):
        rel = "../" * (len(Path(man["srm"]["path"]).parts) + 1) + "secret.txt"
        man["srm"]["files"][rel] = sha

    b = _edit_bundle(untrained_bundle, tmp_path / "b1", escape)
    with pytest.raises(AssetError, match="not a relative path inside the bundle"):
        load_bundle(b)

    def absolute(man):
        man["hogs"][0]["path"] = str((untrained_bundle / man["hogs"][0]["path"]).resolve())

    with pytest.raises(AssetError, match="not a relative path inside the bundle"):
        load_bundle(_edit_bundle(untrained_bundle, tmp_path / "b2", absolute))
    b3 = _edit_bundle(untrained_bundle, tmp_path / "b3", lambda man: None)
    link = b3 / "srm_link"
    link.symlink_to(tmp_path, target_is_directory=True)
    man = json.loads((b3 / "manifest.json").read_text())
    man["srm"]["path"] = "srm_link"
    (b3 / "manifest.json").write_text(json.dumps(man))
    with pytest.raises(AssetError, match="not a relative path inside the bundle"):
        load_bundle(b3)
    # a part folder that is a symbolic link out of the bundle (its files copied outside)
    b4 = _edit_bundle(untrained_bundle, tmp_path / "b4", lambda man: None)
    man = json.loads((b4 / "manifest.json").read_text())
    part = b4 / man["hogs"][0]["path"] / "hand_right"
    outside = tmp_path / "outside_part"
    shutil.move(str(part), str(outside))
    part.symlink_to(outside, target_is_directory=True)
    with pytest.raises(AssetError, match="leads out of the bundle"):
        load_bundle(b4)


def test_bundle_manifest_with_nan_is_an_asset_error(untrained_bundle, tmp_path):
    from hogsa_loader.models.bundle import load_bundle

    def nan(man):
        man["hogs"][0]["num_gaussians"] = float("nan")

    with pytest.raises(AssetError, match="NaN is not a JSON value"):
        load_bundle(_edit_bundle(untrained_bundle, tmp_path / "b", nan))


# ---------------------------------------------------------------------------- arguments checked before work
def _cli_error(capsys, argv: list[str], *needles: str, status: int = 2) -> None:
    from hogsa_loader.cli.main import main

    t0 = time.perf_counter()
    capsys.readouterr()
    assert main(argv) == status, argv
    assert time.perf_counter() - t0 < 20.0  # refused before any work
    _one_line(capsys.readouterr().err, f"hogsa {argv[0]}: error:", *needles)


def test_demo_checks_its_arguments_first(tiny_world, tmp_path, capsys):
    out = tmp_path / "demo"
    _cli_error(capsys, ["demo", "--out", str(out), "--workers", "-1"], "--workers", "must be >= 0")
    _cli_error(capsys, ["demo", "--out", str(out), "--samples", "-1"], "--samples", "must be > 0")
    _cli_error(capsys, ["demo", "--out", str(out), "--samples", "0"], "--samples")
    _cli_error(capsys, ["demo", "--out", str(out), "--threads", "-2"], "--threads")
    _cli_error(capsys, ["demo", "--out", str(out), "--data", str(tiny_world)], "no sequence of subject s02")
    _cli_error(capsys, ["demo", "--out", str(out), "--data", str(tmp_path / "nowhere")], "no such folder")
    assert not out.exists()


def test_export_checks_its_arguments_first(tmp_path, capsys):
    (tmp_path / "bundle").mkdir()
    (tmp_path / "data").mkdir()
    base = [
        "export",
        "--bundle",
        str(tmp_path / "bundle"),
        "--data",
        str(tmp_path / "data"),
        "--out",
        str(tmp_path / "out"),
        "--num",
        "8",
        "--shard-size",
        "4",
        "--batch-size",
        "2",
    ]
    cases = [
        (["--poses", "nonsense"], "--poses", "invalid choice"),
        (["--device", "potato"], "--device", "not a device"),
        (["--render-size", "-10"], "--render-size", "must be > 0"),
        (["--threads", "-1"], "--threads", "must be >= 0"),
        (["--shard-size", "3"], "--shard-size 3 must be a multiple of --batch-size 2"),
        (["--num", "0"], "--num"),
        (["--world-size", "0"], "--world-size"),
    ]
    for extra, *needles in cases:
        _cli_error(capsys, base + extra, *needles)
    afile = tmp_path / "afile"
    afile.write_text("x")
    _cli_error(capsys, base + ["--out", str(afile)], "exists and is not a folder")
    _cli_error(capsys, base + ["--out", str(afile / "sub")], "is a file")
    _cli_error(capsys, base + ["--bundle", str(tmp_path / "nope")], "--bundle", "no such folder")
    assert not (tmp_path / "out").exists()


def test_outputs_that_are_files_or_read_only(tmp_path, capsys, monkeypatch, mano_dir):
    afile = tmp_path / "afile"
    afile.write_text("x")
    _cli_error(capsys, ["world", "--out", str(afile), "--quiet"], "--out", "not a folder")
    _cli_error(capsys, ["demo", "--out", str(afile)], "--out", "not a folder")
    _cli_error(capsys, ["assets", "--out", str(afile), "--quiet"], "--out", "not a folder")
    _cli_error(capsys, ["convert-mano", str(mano_dir / "MANO_RIGHT.pkl"), str(afile / "x.npz")], "DST", "is a file")
    import os

    ro = tmp_path / "ro"
    ro.mkdir()
    real = os.access
    monkeypatch.setattr(os, "access", lambda p, mode: False if Path(p) == ro and mode & os.W_OK else real(p, mode))
    _cli_error(capsys, ["world", "--out", str(ro), "--quiet"], "not writable")
    _cli_error(capsys, ["world", "--out", str(ro / "new"), "--quiet"], "not writable")
    _cli_error(capsys, ["convert-mano", str(mano_dir / "MANO_RIGHT.pkl"), str(ro / "x.npz")], "not writable")


def test_assets_unknown_object_refused_before_writing(tmp_path, capsys):
    out = tmp_path / "assets"
    _cli_error(capsys, ["assets", "--out", str(out), "--objects", "box,nosuch", "--quiet"], "nosuch", "known:")
    assert not out.exists()  # no half-written body_models/


def test_train_hogs_checks_numbers_first(tiny_world, tmp_path, capsys):
    train = _script("train_hogs")
    for flag, value, needle in (
        ("--image-size", "-64", "must be > 0"),
        ("--image-size", "0", "must be > 0"),
        ("--optim-iters", "-1", "must be >= 0"),
        ("--device", "potato", "not a device"),
        ("--model-sh-degree", "7", "invalid choice"),
    ):
        args = _hogs_args(tiny_world, tmp_path / "r")
        if flag in args:
            args[args.index(flag) + 1] = value
        else:
            args += [flag, value]
        capsys.readouterr()
        with pytest.raises(SystemExit) as exc:
            train.main(args)
        assert exc.value.code == 2
        _one_line(capsys.readouterr().err, f"argument {flag}", needle)
    assert train.main(_hogs_args(tiny_world, tmp_path / "afile") + ["--data", str(tmp_path / "none")]) == 2
    _one_line(capsys.readouterr().err, "hogsa train hogs: error: --data", "no such folder")
    from hogsa_loader.train import HogsTrainer

    cfg = train.parse_args(_hogs_args(tiny_world, tmp_path / "r"))
    cfg.data.image_size = 0  # the library refuses it too
    with pytest.raises(ValueError, match="image_size must be >= 1"):
        HogsTrainer(cfg, progress=False)
    assert not (tmp_path / "r").exists()


# ---------------------------------------------------------------------------- a run's light
def test_lambert_run_without_its_light_is_refused(tiny_world, hogs_run, tmp_path):
    from hogsa_loader.assets.arctic import ArcticRoot
    from hogsa_loader.models.gaussians.hogs_model import LIGHT_DIR, HogsModel

    root = ArcticRoot(tiny_world)
    layers, templates = root.mano_layers(), root.object_templates()
    assert HogsModel.from_run(hogs_run, layers, templates).light is not None
    run = tmp_path / "run"
    shutil.copytree(hogs_run, run)
    shutil.rmtree(run / LIGHT_DIR)
    with pytest.raises(AssetError, match="trained with shading 'lambert'"):
        HogsModel.from_run(run, layers, templates)
    (run / "config.json").unlink()  # the part manifests record it too (as a bundle's copies do)
    with pytest.raises(AssetError, match="trained with shading 'lambert'"):
        HogsModel.from_run(run, layers, templates)


# ---------------------------------------------------------------------------- reproducible checkpoints
def test_checkpoint_bytes_are_reproducible(tmp_path):
    from safetensors.torch import save

    from hogsa_loader.io.tensors import read_checked_tensors, write_tensors_and_manifest

    tensors = {"b": torch.arange(6.0).reshape(2, 3), "a": torch.ones(4)}
    meta = {k: f"value {k}" for k in ("format", "schema_version", "kind", "subject", "object", "step")}
    blobs, shas = set(), set()
    for i in range(8):  # the safetensors writer orders metadata differently call by call
        write_tensors_and_manifest(tmp_path / f"c{i}", "t.safetensors", tensors, "m.json", {"x": 1}, metadata=meta)
        blobs.add((tmp_path / f"c{i}" / "t.safetensors").read_bytes())
        shas.add(json.loads((tmp_path / f"c{i}" / "m.json").read_text())["tensors_sha256"])
    assert len(blobs) == 1 and len(shas) == 1
    blob = blobs.pop()
    header = json.loads(blob[8 : 8 + int.from_bytes(blob[:8], "little")])
    assert list(header["__metadata__"]) == sorted(meta)
    # a file written in the writer's own order (before sorting) still reads and verifies
    old = save(tensors, metadata=meta)
    (tmp_path / "old.safetensors").write_bytes(old)
    back = read_checked_tensors(
        tmp_path / "old.safetensors", {"tensors_sha256": hashlib.sha256(old).hexdigest()}, tmp_path / "m.json"
    )
    assert torch.equal(back["b"], tensors["b"])


def test_pretrain_scripts_check_first(tiny_world, untrained_bundle, tmp_path, capsys):
    before = (untrained_bundle / "manifest.json").read_bytes()
    build = _script("build_bundle")
    assert build.main(["--data", str(tiny_world), "--hogs", str(tmp_path), "--out", str(untrained_bundle)]) == 2
    _one_line(capsys.readouterr().err, "build_bundle: error:", "already holds a bundle", "--overwrite")
    assert (untrained_bundle / "manifest.json").read_bytes() == before
    for name, argv, flag in (
        (
            "train_contactnet",
            ["--data", str(tiny_world), "--out", str(tmp_path / "cn"), "--optim-points", "0"],
            "--optim-points",
        ),
        (
            "build_pose_bank",
            [
                "--data",
                str(tiny_world),
                "--contactnet",
                str(tmp_path),
                "--out",
                str(tmp_path / "b"),
                "--device",
                "potato",
            ],
            "--device",
        ),
        (
            "train_srm",
            ["--data", str(tiny_world), "--hogs", str(tmp_path), "--out", str(tmp_path / "s"), "--batch-size", "0"],
            "--batch-size",
        ),
    ):
        with pytest.raises(SystemExit) as exc:
            _script(name).main(argv)
        assert exc.value.code == 2
        _one_line(capsys.readouterr().err, f"argument {flag}")
