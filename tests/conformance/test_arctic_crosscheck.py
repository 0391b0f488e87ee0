"""tests/conformance/arctic_crosscheck.py: its pure parts (no ARCTIC checkout needed).

The script itself runs ARCTIC's code, which CI does not have; these tests cover the
comparison and judging functions, the package/stub planning and listing, the stubs, and
the missing-files listing on a temporary folder.
"""

from __future__ import annotations

import importlib
import json
import pickle
import sys
import types
from pathlib import Path

import numpy as np
import pytest
import torch

pytestmark = pytest.mark.conformance

ROOT = Path(__file__).resolve().parents[2]


@pytest.fixture(scope="module")
def xc():
    return importlib.import_module("arctic_crosscheck")


def _item(img, j2d, name="./data/arctic_data/data/images/s01/box_use_01/1/00010.jpg"):
    inputs = {"img": img}
    targets = {"mano.j2d.norm.r": j2d, "object.radian": torch.tensor(0.5), "is_valid": 1.0}
    meta = {"imgname": name, "dist": torch.tensor([float("nan"), 1.0]), "center": np.array([1.0, 2.0], np.float32)}
    return inputs, targets, meta


def test_compare_and_judge_fields(xc):
    img = torch.zeros(3, 4, 4)
    j2d = torch.tensor([[0.25, -0.5]])
    a = _item(img, j2d)
    b = _item(img + 0.004, j2d.clone())
    c = xc.compare_samples(a, b)
    assert all(not k["arctic_only"] and not k["ours_only"] and k["same_order"] for k in c["keys"].values())
    f = c["fields"]
    assert f["inputs.img"]["max_abs"] == pytest.approx(0.004)
    assert f["targets.mano.j2d.norm.r"]["equal"]
    assert f["meta_info.dist"]["nan_match"] and f["meta_info.dist"]["max_abs"] == 0.0
    assert f["meta_info.imgname"]["equal"] and not f["meta_info.imgname"]["numeric"]
    agg = xc.aggregate_fields([c], img_tol=0.05)
    assert all(v["ok"] for v in agg.values()), {k: v for k, v in agg.items() if not v["ok"]}

    # a 2D label one patch pixel off fails (exact), an image beyond tolerance fails,
    # a different name fails, a dtype change fails even with equal values
    b2 = _item(img + 0.2, j2d + 2 / 224, name="other.jpg")
    b2[1]["object.radian"] = torch.tensor(0.5, dtype=torch.float64)
    agg = xc.aggregate_fields([c, xc.compare_samples(a, b2)], img_tol=0.05)
    bad = sorted(k for k, v in agg.items() if not v["ok"])
    assert bad == ["inputs.img", "meta_info.imgname", "targets.mano.j2d.norm.r", "targets.object.radian"]
    assert agg["targets.mano.j2d.norm.r"]["max_abs"] == pytest.approx(2 / 224)

    # keys on one side only, or in another order, are reported
    b3 = _item(img, j2d)
    b3[1]["extra"] = 1.0
    del b3[1]["is_valid"]
    k = xc.compare_samples(a, b3)["keys"]["targets"]
    assert k["arctic_only"] == ["is_valid"] and k["ours_only"] == ["extra"]
    # NaNs at other places and shape changes are not comparable
    v = xc.compare_values(torch.tensor([float("nan"), 1.0]), torch.tensor([0.0, 1.0]))
    assert not v["nan_match"] and not v["equal"]
    assert xc.compare_values(np.zeros(3), np.zeros(4))["max_abs"] is None


def test_package_plan_and_stub_listing(xc):
    importable = {
        "loguru": True,
        "easydict": True,
        "pytorch_lightning": False,
        "pytorch3d": False,
        "torchvision": True,
        "chumpy": False,
        "pyrender": False,
        "comet_ml": True,
    }
    stubs, pip_missing = xc.plan_packages(importable, ["dataset", "processing"])
    assert stubs == ["pytorch3d", "chumpy", "pyrender"] and pip_missing == []
    assert xc.plan_packages(importable, ["train"])[1] == ["pytorch_lightning"]
    assert xc.plan_packages({}, ["dataset"])[1] == ["loguru", "easydict"]

    notes = xc.Notes()
    for name in stubs:
        notes.stub(name)
    notes.stub("pytorch3d")  # listed once
    notes.patch("Tensor.cuda", "no-op", "ARCTIC calls .cuda()")
    text = xc.format_notes(notes, ["pytorch_lightning"])
    assert [s["module"] for s in notes.stubs] == stubs
    for name in stubs:
        assert name in text and xc.STUB_REASONS[name][1][:30] in text
    assert "Tensor.cuda" in text and "pip install pytorch_lightning" in text


def test_pytorch3d_and_torchvision_stubs(xc):
    p3d = xc.make_pytorch3d_stub()
    rc = p3d["pytorch3d.transforms.rotation_conversions"]
    g = torch.Generator().manual_seed(0)
    aa = torch.randn(5, 3, generator=g)
    R = rc.axis_angle_to_matrix(aa)
    assert torch.allclose(R @ R.transpose(-1, -2), torch.eye(3).expand(5, 3, 3), atol=1e-5)
    assert torch.allclose(rc.rotation_6d_to_matrix(rc.matrix_to_rotation_6d(R)), R, atol=1e-5)
    assert torch.allclose(rc.axis_angle_to_matrix(rc.matrix_to_axis_angle(R)), R, atol=1e-5)
    p1, p2 = torch.randn(2, 6, 3, generator=g), torch.randn(2, 9, 3, generator=g)
    lengths2 = torch.tensor([9, 4])
    d, idx, _ = p3d["pytorch3d.ops"].knn_points(p1, p2, None, lengths2, K=1, return_nn=True)
    for b in range(2):
        full = ((p1[b, :, None] - p2[b, None, : lengths2[b]]) ** 2).sum(-1)
        assert torch.equal(idx[b, :, 0], full.argmin(1))
        assert torch.allclose(d[b, :, 0], full.min(1).values, atol=1e-5)
    norm = xc.make_torchvision_stub()["torchvision.transforms"].Normalize([0.5, 0.25, 0.0], [0.5, 0.5, 1.0])
    x = torch.ones(3, 2, 2)
    assert torch.allclose(norm(x)[:, 0, 0], torch.tensor([1.0, 1.5, 1.0])) and torch.equal(x, torch.ones(3, 2, 2))


def test_chumpy_stub_reads_pickled_state(xc):
    # pickle an object of a class that claims to be chumpy.ch.Ch, then read it with the stub
    fake_pkg, fake_ch = types.ModuleType("chumpy"), types.ModuleType("chumpy.ch")
    Ch = type("Ch", (), {"__module__": "chumpy.ch"})
    fake_ch.Ch = Ch
    saved = {k: sys.modules.get(k) for k in ("chumpy", "chumpy.ch")}
    sys.modules.update({"chumpy": fake_pkg, "chumpy.ch": fake_ch})
    obj = Ch()
    obj.__dict__.update({"x": np.arange(6.0).reshape(2, 3)})
    blob = pickle.dumps({"shapedirs": obj}, protocol=2)
    finder = xc._ChumpyFinder()
    for k in ("chumpy", "chumpy.ch"):
        sys.modules.pop(k)
    sys.meta_path.insert(0, finder)
    try:
        data = pickle.loads(blob)
        sd = data["shapedirs"]
        assert sd.shape == (2, 3) and np.array_equal(np.asarray(sd), np.arange(6.0).reshape(2, 3))
        assert np.array_equal(sd[:, :2], np.arange(6.0).reshape(2, 3)[:, :2])
    finally:
        sys.meta_path.remove(finder)
        for k in ("chumpy", "chumpy.ch"):
            sys.modules.pop(k, None)
            if saved[k] is not None:
                sys.modules[k] = saved[k]


def test_missing_files_listing(xc, tmp_path):
    arctic = tmp_path / "arctic_data" / "data"
    (arctic / "meta").mkdir(parents=True)
    (arctic / "meta" / "misc.json").write_text(
        json.dumps({"s01": {"world2cam": [], "intris_mat": [], "image_size": [], "ioi_offset": 0}})
    )
    (arctic / "meta" / "object_meta.json").write_text("{}")
    for f in xc.OBJECT_TEMPLATE_FILES:
        (arctic / "meta" / "object_vtemplates" / "box").mkdir(parents=True, exist_ok=True)
        (arctic / "meta" / "object_vtemplates" / "box" / f).write_text("")
    (arctic / "raw_seqs" / "s01").mkdir(parents=True)
    for kind in ("mano", "object", "egocam.dist"):
        (arctic / "raw_seqs" / "s01" / f"box_use_01.{kind}.npy").write_bytes(b"")
    (arctic / "splits").mkdir()
    (arctic / "splits" / "p1_train.npy").write_bytes(b"")
    (tmp_path / "body_models" / "mano").mkdir(parents=True)
    for side in ("RIGHT", "LEFT"):
        (tmp_path / "body_models" / "mano" / f"MANO_{side}.pkl").write_bytes(b"")
    img = "./data/arctic_data/data/images/s01/box_use_01/1/00010.jpg"
    (arctic / "cropped_images" / "s01" / "box_use_01" / "1").mkdir(parents=True)
    (arctic / "cropped_images" / "s01" / "box_use_01" / "1" / "00010.jpg").write_bytes(b"")
    names = {"p1_train": [img, img.replace("00010", "00011")]}
    entries = xc.required_files(tmp_path, ["box", "phone"], ["p1_train", "p1_val"], names)
    missing = {e["path"] for e in entries if not e["exists"]}
    base = "arctic_data/data"
    for must in (
        f"{base}/meta/downsamplers.npy",
        f"{base}/meta/mano_decimator_195.npy",
        f"{base}/meta/object_vtemplates/phone/mesh.obj",
        f"{base}/splits/p1_val.npy",
        f"{base}/raw_seqs/s01/box_use_01.smplx.npy",
        "body_models/smplx/SMPLX_NEUTRAL.npz",
        f"{base}/meta/subject_vtemplates/s01.obj",
        f"{base}/splits_json/protocol_p1.json",
        f"{base}/meta/misc.json [s01].gender",
    ):
        assert must in missing, must
    for present in (
        f"{base}/meta/misc.json",
        f"{base}/meta/object_vtemplates/box/mesh.obj",
        f"{base}/splits/p1_train.npy",
        "body_models/mano/MANO_RIGHT.pkl",
        f"{base}/raw_seqs/s01/box_use_01.object.npy",
    ):
        assert present not in missing, present
    images = [e for e in entries if "count" in e]
    assert len(images) == 1 and images[0]["soft"] and images[0]["count"] == 1 and "00011.jpg" in images[0]["path"]
    # what blocks which check
    assert f"{base}/meta/downsamplers.npy" in xc.blocking_missing(entries, "train")
    assert f"{base}/meta/downsamplers.npy" not in xc.blocking_missing(entries, "dataset")
    assert not any(".jpg" in p for p in xc.blocking_missing(entries, "dataset"))
    # SMPL-X models are soft (NaN stand-in) unless required
    assert "body_models/smplx/SMPLX_NEUTRAL.npz" not in xc.blocking_missing(entries, "processing")
    assert f"{base}/raw_seqs/s01/box_use_01.smplx.npy" in xc.blocking_missing(entries, "processing")
    strict = xc.required_files(tmp_path, ["box", "phone"], ["p1_train"], names, require_smplx=True)
    assert "body_models/smplx/SMPLX_NEUTRAL.npz" in xc.blocking_missing(strict, "processing")
    text = xc.format_missing(entries)
    assert f"{base}/meta/downsamplers.npy" in text and "train" in text
    rows = {r["path"]: r for r in xc.group_missing(entries)}  # one row per group of files
    objs = rows[f"{base}/meta/object_vtemplates/<object>/<file>"]
    assert objs["detail"] == "1 objects entirely: phone" and len(objs["members"]) == len(xc.OBJECT_TEMPLATE_FILES)
    assert rows[f"{base}/raw_seqs/<sid>/<seq>.smplx.npy"]["detail"] == "1: s01/box_use_01"
    assert xc.format_missing([e for e in entries if e["exists"]]).endswith("(none)")
    assert xc.cropped_image_rel(img) == "arctic_data/data/cropped_images/s01/box_use_01/1/00010.jpg"


def test_image_geometry(xc):
    g = xc.ImageGeometry(cropped_size=256, ego_scale=0.1, ego_full_sizes={"s01": (2800, 2000)})
    allo = "./data/arctic_data/data/images/s01/box_use_01/3/00010.jpg"
    ego = allo.replace("/3/", "/0/")
    assert not g.arctic_sized and g.factor(allo) == pytest.approx(0.256) and g.factor(ego) == pytest.approx(1 / 3)
    assert g.arctic_size(allo) == (1000, 1000) and g.arctic_size(ego) == (840, 600)
    assert xc.ImageGeometry(1000, 0.3, {}).arctic_sized


def test_compare_split_data(xc):
    def split(aa, flag, extra_smplx=False):
        cam = {"rot_r_cam": aa, "is_valid": flag, "joints.right": np.zeros((2, 10, 21, 3), np.float32)}
        if extra_smplx:
            cam["joints.smplx"] = np.zeros((2, 10, 127, 3), np.float32)
        return {
            "imgnames": ["a", "b"],
            "data_dict": {
                "s01/box_use_01": {
                    "cam_coord": cam,
                    "2d": {"kp3d": np.ones((2, 10, 32, 2), np.float32)},
                    "bbox": np.ones((2, 9, 3), np.float32),
                    "params": {"obj_arti": np.zeros(2, np.float32)},
                }
            },
        }

    v = np.array([np.pi - 1e-7, 0.0, 0.0])
    aa_a = np.tile(v, (2, 9, 1)).astype(np.float32)
    aa_b = aa_a.copy()
    aa_b[0, 0] = -v  # the same rotation by pi about x: not a difference
    flags = np.ones((2, 9), np.int64)
    res = xc.compare_split_data(split(aa_a, flags, extra_smplx=True), split(aa_b, flags))
    assert res["imgnames_equal"] and res["sequences_equal"]
    assert res["keys"]["cam_coord/rot_r_cam"]["max_abs"] < 1e-5 and res["keys"]["cam_coord/rot_r_cam"]["ok"]
    smplx = res["keys"]["cam_coord/joints.smplx"]
    assert smplx["only"] == "arctic" and smplx["expected"] and smplx["ok"]
    assert all(k["ok"] for k in res["keys"].values())

    flags_b = flags.copy()
    flags_b[1, 3] = 0
    res = xc.compare_split_data(split(aa_a, flags), split(aa_a, flags_b))
    assert not res["keys"]["cam_coord/is_valid"]["ok"] and res["keys"]["cam_coord/is_valid"]["max_abs"] == 1.0


def test_usage_errors(xc, tmp_path, capsys):
    assert xc.main(["--arctic-src", str(tmp_path / "nope"), "--data", str(tmp_path)]) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("error: --arctic-src") and "\n" not in err
    (tmp_path / "arctic" / "src" / "models" / "arctic_sf").mkdir(parents=True)
    (tmp_path / "arctic" / "common").mkdir()
    assert xc.main(["--arctic-src", str(tmp_path / "arctic"), "--data", str(tmp_path / "nowhere")]) == 2
    assert "--data" in capsys.readouterr().err
    (tmp_path / "w" / "arctic_data" / "data").mkdir(parents=True)
    assert xc.main(["--arctic-src", str(tmp_path / "arctic"), "--data", str(tmp_path / "w"), "--checks", "x"]) == 2
    assert "--checks" in capsys.readouterr().err
