"""Tests of the ARCTIC reader (datasets/arctic.py) and processing (datasets/arctic_processing.py).

The fixture is a small ARCTIC root in the real on-disk format: ``hogsa assets`` output
(MANO pickles, object templates) plus raw_seqs written with ``np.save`` of dicts, a
misc.json and protocol files. Oracles are computed independently (numpy, OpenCV) rather
than with the functions under test.
"""

from __future__ import annotations

import copy
import json
import pickle
import shutil
from pathlib import Path

import cv2
import numpy as np
import pytest
import torch
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from scipy.spatial.transform import Rotation

from hogsa_loader.assets.arctic import ArcticRoot, WorldMeta, read_npy
from hogsa_loader.assets.arctic_processing import build_split, process_sequence, write_processed_splits
from hogsa_loader.errors import AssetError, UnsafePickleError

F64 = torch.float64

# sequences of the fixture world: "sid/seq" -> number of frames
SEQS = {"s01/box_grab_01": 34, "s01/laptop_use_02": 30, "s02/notebook_use_01": 32, "s05/box_use_01": 30}
IOI = {"s01": 2, "s02": 0, "s05": 1}
EGO_SIZE = (2800, 2000)


# --------------------------------------------------------------------------------------
# fixture world (real ARCTIC format)
# --------------------------------------------------------------------------------------


def look_at(centre: np.ndarray, target: np.ndarray, up=(0.0, 0.0, 1.0)) -> np.ndarray:
    """4x4 world->camera (OpenCV axes: z forward) for a camera at ``centre`` looking at ``target``."""
    z = target - centre
    z = z / np.linalg.norm(z)
    x = np.cross(z, np.asarray(up))
    x = x / np.linalg.norm(x)
    y = np.cross(z, x)
    R = np.stack([x, y, z])
    M = np.eye(4)
    M[:3, :3] = R
    M[:3, 3] = -R @ centre
    return M


def make_misc(rng: np.random.Generator, sids) -> dict:
    misc = {}
    for sid in sids:
        w2c, Ks, sizes = [], [], [[2800, 2000]]
        for v in range(8):
            ang = 2 * np.pi * v / 8 + rng.uniform(-0.2, 0.2)
            dist = 0.9 if v % 2 == 0 else 2.6  # near cameras: large boxes; far: clamped boxes
            C = np.array([dist * np.cos(ang), dist * np.sin(ang), rng.uniform(0.2, 0.6)])
            w2c.append(look_at(C, np.zeros(3)).tolist())
            W, H = (2800, 2000) if v != 4 else (2000, 2800)
            f = 2200.0 + 40 * v
            Ks.append(
                [
                    [f, 0.0, W / 2 + rng.uniform(-20, 20)],
                    [0.0, f * 1.001, H / 2 + rng.uniform(-20, 20)],
                    [0.0, 0.0, 1.0],
                ]
            )
            sizes.append([W, H])
        misc[sid] = {
            "world2cam": w2c,
            "intris_mat": Ks,
            "image_size": sizes,
            "ioi_offset": IOI.get(sid, 0),
            "gender": "female" if sid != "s02" else "male",
        }
    return misc


def make_raw(rng: np.random.Generator, F: int) -> tuple[dict, np.ndarray, dict]:
    """Plausible random raw arrays: (mano dict, object (F,7) mm, egocam dict)."""
    t = np.linspace(0, 1, F)[:, None]

    def hand(offset):
        rot0 = Rotation.random(random_state=int(rng.integers(1 << 30))).as_rotvec()
        return {
            "rot": rot0 + 0.3 * np.sin(3 * t + rng.uniform(0, 6, 3)),
            "pose": rng.normal(0, 0.15, (F, 45)),
            # wanders up to ~0.2 m from its rest place: in and out of the object-centred crops
            "trans": np.asarray(offset) + 0.2 * np.sin(2 * np.pi * t + rng.uniform(0, 6, 3)),
            "shape": rng.normal(0, 0.8, 10),
            "fitting_err": np.abs(rng.normal(0.004, 0.001, F)),
        }

    mano = {"right": hand([-0.12, 0.05, 0.02]), "left": hand([0.10, -0.06, 0.03])}
    obj = np.zeros((F, 7))
    obj[:, 0] = 0.2 + 0.8 * t[:, 0]
    obj[:, 1:4] = Rotation.random(random_state=int(rng.integers(1 << 30))).as_rotvec() * 0.5 + 0.1 * t
    obj[:, 4:7] = rng.uniform(-30, 30, 3) + 20 * np.sin(4 * t)
    R, T = [], []
    for i in range(F):
        C = np.array([0.05 * np.sin(i / 5), 0.55, 0.45]) + rng.normal(0, 0.005, 3)
        M = look_at(C, np.array([0.0, 0.0, 0.02]))
        R.append(M[:3, :3])
        T.append(M[:3, 3:4])
    ego = {
        "R_k_cam_np": np.stack(R),
        "T_k_cam_np": np.stack(T),
        "intrinsics": np.array([[1500.0, 0.0, 1390.0], [0.0, 1500.0, 1010.0], [0.0, 0.0, 1.0]]),
        "dist8": np.array([-0.08, 0.012, 0.0007, -0.0004, 0.001, 0.02, -0.003, 0.0005]),
        "R0": np.eye(3),
        "T0": np.zeros(3),
        "ego_markers.ref": rng.normal(0, 0.1, (4, 3)),
        "ego_markers.label": np.array(["a", "b", "c", "d"]),
    }
    return mano, obj, ego


def write_raw(raw_dir: Path, key: str, mano: dict, obj: np.ndarray, ego: dict) -> None:
    sid, seq = key.split("/")
    d = raw_dir / sid
    d.mkdir(parents=True, exist_ok=True)
    np.save(d / f"{seq}.mano.npy", mano, allow_pickle=True)
    np.save(d / f"{seq}.object.npy", obj)
    np.save(d / f"{seq}.egocam.dist.npy", ego, allow_pickle=True)


def write_world(data_root: Path, seqs: dict, seed: int = 0) -> dict:
    """misc.json + raw_seqs + protocols under ``data_root`` (assets written separately)."""
    rng = np.random.default_rng(seed)
    arctic = data_root / "arctic_data" / "data"
    (arctic / "meta").mkdir(parents=True, exist_ok=True)
    sids = sorted({k.split("/")[0] for k in seqs})
    misc = make_misc(rng, sids)
    (arctic / "meta" / "misc.json").write_text(json.dumps(misc))
    raws = {}
    for key, F in seqs.items():
        raws[key] = make_raw(rng, F)
        write_raw(arctic / "raw_seqs", key, *raws[key])
    (arctic / "splits_json").mkdir(parents=True, exist_ok=True)
    train = [k for k in seqs if not k.startswith("s05/")]
    val = [k for k in seqs if k.startswith("s05/")]
    # the json train list also names the val sequence: ARCTIC recomputes train = all - val - test
    for p in ("p1", "p2"):
        (arctic / "splits_json" / f"protocol_{p}.json").write_text(
            json.dumps({"train": train + val, "val": val, "test": []})
        )
    return {"misc": misc, "raw": raws}


@pytest.fixture(scope="session")
def arctic_world(tmp_path_factory):
    """(data_root, written values): ``hogsa assets`` + raw_seqs + images/masks for one view."""
    from hogsa_loader.cli.main import main

    root = tmp_path_factory.mktemp("arctic") / "data"
    assert main(["assets", "--out", str(root), "--no-preview", "--quiet"]) == 0
    written = write_world(root, SEQS)
    arctic = root / "arctic_data" / "data"
    # a few images / masks so that the path listing can be checked
    for folder, view, gts, ext in (
        ("cropped_images", 3, range(0, 5), ".jpg"),
        ("images", 0, range(2, 4), ".jpg"),
        ("masks", 3, range(1, 3), ".png"),
    ):
        d = arctic / folder / "s01" / "box_grab_01" / str(view)
        d.mkdir(parents=True)
        for g in gts:
            (d / f"{g + IOI['s01']:05d}{ext}").write_bytes(b"")
    return root, written


@pytest.fixture(scope="session")
def root(arctic_world) -> ArcticRoot:
    return ArcticRoot(arctic_world[0])


@pytest.fixture(scope="session")
def processed(root):
    """Processing (no vertices) of every fixture sequence."""
    layers = root.mano_layers()
    obj = root.object_layer()
    return {key: process_sequence(root.sequence(*key.split("/")), layers, obj) for key in SEQS}


@pytest.fixture(scope="session")
def processed_verts(root):
    """export_verts processing of s01/box_grab_01."""
    return process_sequence(
        root.sequence("s01", "box_grab_01"), root.mano_layers(), root.object_layer(), export_verts=True
    )


def sub_sequence(seq, idx):
    """The frames ``idx`` of a SequenceData (deep copy)."""
    s = copy.deepcopy(seq)
    for h in (s.right, s.left):
        h.rot, h.pose, h.trans, h.valid, h.fitting_err = (
            h.rot[idx],
            h.pose[idx],
            h.trans[idx],
            h.valid[idx],
            h.fitting_err[idx],
        )
    o = s.object
    o.arti, o.rot, o.trans, o.valid = o.arti[idx], o.rot[idx], o.trans[idx], o.valid[idx]
    for c in s.cameras.values():
        c.world2cam, c.K = c.world2cam[idx], c.K[idx]
    s.frame_ids = s.frame_ids[idx]
    s.image_paths, s.full_image_paths, s.mask_paths = {}, {}, {}
    return s


def mini_root(tmp: Path, key: str = "s01/box_grab_01", F: int = 30, seed: int = 3) -> tuple[ArcticRoot, dict]:
    """A reader-only root (misc + raw_seqs of one sequence, no models)."""
    data_root = tmp / "data"
    written = write_world(data_root, {key: F}, seed=seed)
    return ArcticRoot(data_root), written


# --------------------------------------------------------------------------------------
# reader: values
# --------------------------------------------------------------------------------------


def test_misc_subjects_sequences(root, arctic_world):
    misc = root.misc()
    assert list(misc) == ["s01", "s02", "s05"] == root.subjects()
    m = misc["s01"]
    ref = arctic_world[1]["misc"]["s01"]
    assert m.world2cam.shape == (8, 4, 4) and m.intris_mat.shape == (8, 3, 3)
    np.testing.assert_array_equal(m.world2cam, np.array(ref["world2cam"]))
    np.testing.assert_array_equal(m.intris_mat, np.array(ref["intris_mat"]))
    assert m.image_size.shape == (9, 2) and m.image_size[5].tolist() == [2000, 2800]
    assert m.ioi_offset == 2 and misc["s02"].gender == "male"
    assert root.sequences() == sorted(SEQS)
    assert root.sequences("s01") == ["s01/box_grab_01", "s01/laptop_use_02"]
    # the arctic_data/data folder itself is accepted as root
    assert ArcticRoot(root.arctic_dir).data_root == root.data_root


def test_raw_sequence_round_trip(root, arctic_world):
    mano, obj, ego = arctic_world[1]["raw"]["s01/box_grab_01"]
    raw = root.raw_sequence("s01", "box_grab_01")
    assert raw.num_frames == 34 and raw.object_name == "box"
    for side in ("right", "left"):
        for key in ("rot", "pose", "trans", "shape", "fitting_err"):
            np.testing.assert_array_equal(raw.mano[side][key], mano[side][key])
        assert raw.shape_layout[side] == "(10,)"
    np.testing.assert_array_equal(raw.object, obj)
    np.testing.assert_array_equal(raw.R_ego, ego["R_k_cam_np"])
    np.testing.assert_array_equal(raw.T_ego, ego["T_k_cam_np"][..., 0])
    np.testing.assert_array_equal(raw.K_ego, ego["intrinsics"])
    np.testing.assert_array_equal(raw.dist8, ego["dist8"])
    assert raw.egocam_extra["ego_markers.label"].tolist() == ["a", "b", "c", "d"]
    w2e = raw.world2ego
    np.testing.assert_array_equal(w2e[:, :3, :3], ego["R_k_cam_np"])
    np.testing.assert_array_equal(w2e[:, :3, 3], ego["T_k_cam_np"][..., 0])
    np.testing.assert_array_equal(w2e[:, 3], np.tile([0.0, 0, 0, 1], (34, 1)))


def test_sequence_values(root, arctic_world):
    misc = arctic_world[1]["misc"]["s01"]
    mano, obj, ego = arctic_world[1]["raw"]["s01/box_grab_01"]
    s = root.sequence("s01", "box_grab_01")
    F = 34
    assert (s.dataset, s.subject, s.name, s.num_frames) == ("arctic", "s01", "box_grab_01", F)
    for side in ("right", "left"):
        h = getattr(s, side)
        np.testing.assert_array_equal(h.rot, mano[side]["rot"])
        np.testing.assert_array_equal(h.pose, mano[side]["pose"])
        np.testing.assert_array_equal(h.trans, mano[side]["trans"])
        np.testing.assert_array_equal(h.betas, mano[side]["shape"])
        np.testing.assert_array_equal(h.fitting_err, mano[side]["fitting_err"])
        assert h.valid.all() and h.valid.shape == (F,)
    assert s.object.name == "box"
    np.testing.assert_array_equal(s.object.arti, obj[:, 0])
    np.testing.assert_array_equal(s.object.rot, obj[:, 1:4])
    np.testing.assert_allclose(s.object.trans, obj[:, 4:7] / 1000.0, rtol=0, atol=1e-15)
    assert sorted(s.cameras) == list(range(9))
    for v in range(1, 9):
        c = s.cameras[v]
        assert c.world2cam.shape == (F, 4, 4) and c.K.shape == (F, 3, 3) and not c.egocentric
        np.testing.assert_array_equal(c.world2cam, np.broadcast_to(np.array(misc["world2cam"][v - 1]), (F, 4, 4)))
        np.testing.assert_array_equal(c.K, np.broadcast_to(np.array(misc["intris_mat"][v - 1]), (F, 3, 3)))
        assert [c.width, c.height] == misc["image_size"][v] and c.dist is None
    e = s.cameras[0]
    assert e.egocentric and (e.width, e.height) == (2800, 2000)
    np.testing.assert_array_equal(e.world2cam[:, :3, :3], ego["R_k_cam_np"])
    np.testing.assert_array_equal(e.world2cam[:, :3, 3], ego["T_k_cam_np"][..., 0])
    np.testing.assert_array_equal(e.K, np.broadcast_to(ego["intrinsics"], (F, 3, 3)))
    np.testing.assert_array_equal(e.dist, ego["dist8"])
    np.testing.assert_array_equal(s.frame_ids, np.arange(F) + 2)
    # images / masks: only where the files exist, numbered GT + ioi_offset
    assert sorted(s.image_paths) == [3] and sorted(s.full_image_paths) == [0] and sorted(s.mask_paths) == [3]
    crop = s.image_paths[3]
    assert len(crop) == F and all(p is not None for p in crop[:5]) and all(p is None for p in crop[5:])
    assert crop[0] == root.arctic_dir / "cropped_images/s01/box_grab_01/3/00002.jpg"
    assert [p is not None for p in s.full_image_paths[0][:5]] == [False, False, True, True, False]
    assert s.full_image_paths[0][2].name == "00004.jpg"
    assert [p is not None for p in s.mask_paths[3][:4]] == [False, True, True, False]
    assert s.mask_paths[3][1].name == "00003.png"
    other = root.sequence("s02", "notebook_use_01")
    assert other.image_paths == {} and other.mask_paths == {} and other.full_image_paths == {}
    np.testing.assert_array_equal(other.frame_ids, np.arange(32))


def test_models_from_root(root):
    layers = root.mano_layers()
    assert set(layers) == {"right", "left"}
    assert layers["right"].num_verts == root.mano_layers()["left"].num_verts  # from the file, not 778
    assert not layers["right"].flat_hand_mean and layers["left"].side == "left"
    assert root.mano_layers() is layers
    assert list(root.object_templates()) == ["box", "laptop", "notebook"]
    assert root.object_layer().names == ["box", "laptop", "notebook"]


def test_object_templates_read_only_the_objects_asked_for(arctic_world, tmp_path):
    """Each object is read when first asked for: a broken template of another object does not
    stop one that is asked for, and is reported (naming its file) when it is read; the
    untextured mapping takes what the textured one read."""
    import shutil

    data = tmp_path / "data"
    shutil.copytree(arctic_world[0] / "arctic_data" / "data" / "meta", data / "arctic_data" / "data" / "meta")
    broken = data / "arctic_data" / "data" / "meta" / "object_vtemplates" / "laptop" / "parts.json"
    broken.write_text("[0, 1")
    root = ArcticRoot(data)
    textured = root.object_templates()
    assert list(textured) == ["box", "laptop", "notebook"] and "laptop" in textured and "mug" not in textured
    box = textured["box"]
    assert box.verts.shape[0] > 0 and repr(textured).endswith("3 objects, 1 read)")
    assert root.object_templates(load_texture=False)["box"] is box
    import copy
    import pickle

    for twin in (copy.deepcopy(textured), pickle.loads(pickle.dumps(textured))):  # DataLoader workers
        assert list(twin) == list(textured) and np.array_equal(twin["box"].verts, box.verts)
    with pytest.raises(AssetError, match="parts.json"):
        textured["laptop"]
    with pytest.raises(KeyError):
        textured["mug"]
    from hogsa_loader.models.pom.objects import ObjectSet

    plain = root.object_templates(load_texture=False)
    assert ObjectSet(plain).templates is plain  # kept, not copied (a copy would read the broken one)
    with pytest.raises(AssetError, match="parts.json"):
        dict(root.object_templates(load_texture=False))  # reading all reads the broken one


def test_shape_per_frame_is_accepted_and_reported(tmp_path):
    r, w = mini_root(tmp_path, F=30)
    mano, obj, ego = w["raw"]["s01/box_grab_01"]
    mano = copy.deepcopy(mano)
    mano["left"]["shape"] = np.tile(mano["left"]["shape"], (30, 1))
    write_raw(r.raw_dir, "s01/box_grab_01", mano, obj, ego)
    raw = r.raw_sequence("s01", "box_grab_01")
    assert raw.shape_layout == {"right": "(10,)", "left": "(F, 10)"}
    np.testing.assert_array_equal(raw.mano["left"]["shape"], mano["left"]["shape"][0])
    mano["left"]["shape"][3, 0] += 0.5  # per-frame betas that vary cannot be one MANO shape
    write_raw(r.raw_dir, "s01/box_grab_01", mano, obj, ego)
    with pytest.raises(AssetError, match=r"left\.shape is stored per frame \(F, 10\) and varies"):
        r.raw_sequence("s01", "box_grab_01")


def test_world_meta(tmp_path):
    r, _ = mini_root(tmp_path)
    wm = r.world_meta()
    assert wm == WorldMeta() and not wm.present
    assert (wm.cropped_size, wm.ego_image_scale, wm.ego_image_size) == (1000, 0.3, (2800, 2000))
    assert wm.arctic_sized and r.require_arctic_sizes() == wm
    path = r.meta_dir / "hogsa_world.json"
    doc = {
        "schema_version": 1,
        "cropped_size": 512,
        "ego_image_scale": 0.25,
        "ego_image_size": [1400, 1000],
        "mask_ids": {"background": 0, "right": 1, "left": 2, "object": 3},
        "generator": "test",
    }
    path.write_text(json.dumps(doc))
    wm = ArcticRoot(r.data_root).world_meta()
    assert wm.present and wm.schema_version == 1 and wm.cropped_size == 512
    assert wm.ego_image_scale == 0.25 and wm.ego_image_size == (1400, 1000)
    assert dict(wm.mask_ids) == doc["mask_ids"] and wm.extra == {"generator": "test"}
    assert not wm.arctic_sized
    with pytest.raises(AssetError, match=r"512-px allocentric crops and ego images 1400x1000 × 0\.25") as ei:
        ArcticRoot(r.data_root).require_arctic_sizes()
    assert ei.value.path == str(path)
    for bad, msg in (
        ({k: v for k, v in doc.items() if k != "cropped_size"}, "key 'cropped_size' is missing"),
        (dict(doc, ego_image_size=[1400]), "ego_image_size must be"),
        (dict(doc, schema_version="1"), "schema_version must be"),
        (dict(doc, mask_ids={"a": -1}), "mask_ids must map"),
        (dict(doc, ego_image_scale=float("nan")), "ego_image_scale must be"),
    ):
        path.write_text(json.dumps(bad))
        with pytest.raises(AssetError, match=msg) as ei:
            ArcticRoot(r.data_root).world_meta()
        assert ei.value.path == str(path)
    path.write_text("{not json")
    with pytest.raises(AssetError, match="malformed JSON"):
        ArcticRoot(r.data_root).world_meta()


def test_protocol_train_recomputed_and_checked(root, tmp_path):
    p = root.protocol("p1")
    assert p["val"] == ["s05/box_use_01"] and p["test"] == []
    # the json's train list also names s05/box_use_01: ARCTIC removes val/test from train
    assert p["train"] == ["s01/box_grab_01", "s01/laptop_use_02", "s02/notebook_use_01"]
    r, _ = mini_root(tmp_path)
    path = r.protocol_path("p1")
    for doc, msg in (
        ({"train": [], "val": ["s01/a_b_01"], "test": ["s01/a_b_01"]}, "both val and test"),
        ({"train": [], "val": ["s01/a_b_01", "s01/a_b_01"], "test": []}, "'val' lists a sequence twice"),
        ({"train": [], "val": []}, "'test' is missing"),
        ({"train": ["s01"], "val": [], "test": []}, "expected 'sid/seq'"),
    ):
        path.write_text(json.dumps(doc))
        with pytest.raises(AssetError, match=msg) as ei:
            r.protocol("p1")
        assert ei.value.path == str(path)
    with pytest.raises(AssetError, match="file is missing"):
        r.protocol("p2x")


# --------------------------------------------------------------------------------------
# processing: keys, shapes, geometry
# --------------------------------------------------------------------------------------


def test_processed_keys_shapes_dtypes(processed, processed_verts, root):
    out = processed_verts
    F = 34
    V = root.mano_layers()["right"].num_verts
    Vo = root.object_templates()["box"].verts.shape[0]
    assert set(out) == {"world_coord", "cam_coord", "2d", "bbox", "params"}
    pts = {
        "joints.right": 21,
        "joints.left": 21,
        "kp3d": 32,
        "bbox3d": 16,
        "verts.right": V,
        "verts.left": V,
        "verts.object": Vo,
    }
    assert set(out["cam_coord"]) == set(pts) | {
        "rot_r_cam",
        "rot_l_cam",
        "obj_rot_cam",
        "is_valid",
        "left_valid",
        "right_valid",
    }
    assert set(out["2d"]) == set(pts)
    assert set(out["world_coord"]) == set(pts) | {"rot_r", "rot_l", "obj_rot"}
    for k, n in pts.items():
        assert out["cam_coord"][k].shape == (F, 10, n, 3) and out["cam_coord"][k].dtype == np.float32
        assert out["2d"][k].shape == (F, 10, n, 2) and out["2d"][k].dtype == np.float32
        assert out["world_coord"][k].shape == (F, n, 3)
    for k in ("rot_r_cam", "rot_l_cam", "obj_rot_cam"):
        assert out["cam_coord"][k].shape == (F, 9, 3) and out["cam_coord"][k].dtype == np.float32
    for k in ("is_valid", "left_valid", "right_valid"):
        assert out["cam_coord"][k].shape == (F, 9) and out["cam_coord"][k].dtype == np.int64
        assert set(np.unique(out["cam_coord"][k])) <= {0, 1}
    assert out["bbox"].shape == (F, 9, 3) and out["bbox"].dtype == np.float32
    shapes = {
        "rot_r": (F, 3),
        "pose_r": (F, 45),
        "trans_r": (F, 3),
        "shape_r": (F, 10),
        "fitting_err_r": (F,),
        "rot_l": (F, 3),
        "pose_l": (F, 45),
        "trans_l": (F, 3),
        "shape_l": (F, 10),
        "fitting_err_l": (F,),
        "obj_arti": (F,),
        "obj_rot": (F, 3),
        "obj_trans": (F, 3),
        "world2ego": (F, 4, 4),
        "dist": (F, 8),
        "K_ego": (F, 3, 3),
    }
    assert {k: v.shape for k, v in out["params"].items()} == shapes
    assert all(v.dtype == np.float32 for v in out["params"].values())
    assert not any("smplx" in k for g in ("cam_coord", "2d", "world_coord") for k in out[g])
    # without export_verts no vertex keys are stored, the rest is identical
    slim = processed["s01/box_grab_01"]
    assert not any(k.startswith("verts") for g in ("cam_coord", "2d", "world_coord") for k in slim[g])
    for g in ("cam_coord", "2d"):
        for k in slim[g]:
            np.testing.assert_array_equal(slim[g][k], out[g][k])
    np.testing.assert_array_equal(slim["bbox"], out["bbox"])


def test_params_raw_values(processed, arctic_world):
    mano, obj, ego = arctic_world[1]["raw"]["s01/box_grab_01"]
    p = processed["s01/box_grab_01"]["params"]
    f32 = np.float32
    np.testing.assert_array_equal(p["pose_r"], mano["right"]["pose"].astype(f32))
    np.testing.assert_array_equal(p["shape_l"], np.tile(mano["left"]["shape"].astype(f32), (34, 1)))
    np.testing.assert_array_equal(p["fitting_err_l"], mano["left"]["fitting_err"].astype(f32))
    np.testing.assert_array_equal(p["obj_arti"], obj[:, 0].astype(f32))
    np.testing.assert_allclose(p["obj_trans"], obj[:, 4:7], rtol=1e-6)  # raw millimetres
    np.testing.assert_array_equal(p["dist"], np.tile(ego["dist8"].astype(f32), (34, 1)))
    np.testing.assert_array_equal(p["K_ego"], np.tile(ego["intrinsics"].astype(f32), (34, 1, 1)))
    np.testing.assert_array_equal(p["world2ego"][:, :3, :3], ego["R_k_cam_np"].astype(f32))


def test_world_coord_matches_models(processed, root, arctic_world):
    """World joints = MANO(raw params incl. transl) (float64 layer); object = layer(θ, ω, t/1000)."""
    mano, obj, _ = arctic_world[1]["raw"]["s01/box_grab_01"]
    wc = processed["s01/box_grab_01"]["world_coord"]
    layers = root.mano_layers(F64)
    for side in ("right", "left"):
        h = {k: torch.as_tensor(v, dtype=F64) for k, v in mano[side].items()}
        ref = layers[side](h["rot"], h["pose"], h["shape"].expand(34, 10), h["trans"]).joints.numpy()
        np.testing.assert_allclose(wc[f"joints.{side}"], ref, atol=2e-5)
    t = lambda a: torch.as_tensor(a, dtype=F64)  # noqa: E731
    ref = root.object_layer()(t(obj[:, :1]), t(obj[:, 1:4]), t(obj[:, 4:7] / 1000), ["box"] * 34)
    np.testing.assert_allclose(wc["kp3d"], ref["kp3d"].numpy(), atol=1e-6)
    np.testing.assert_allclose(wc["bbox3d"], ref["bbox3d"].numpy(), atol=1e-6)


def test_cam_coord_is_world_moved_by_extrinsics(processed_verts, arctic_world):
    misc = arctic_world[1]["misc"]["s01"]
    _, _, ego = arctic_world[1]["raw"]["s01/box_grab_01"]
    out = processed_verts
    for key in ("joints.right", "joints.left", "kp3d", "bbox3d", "verts.object"):
        world = out["world_coord"][key].astype(np.float64)
        cam = out["cam_coord"][key]
        for v in range(1, 9):
            M = np.array(misc["world2cam"][v - 1])
            ref = world @ M[:3, :3].T + M[:3, 3]
            np.testing.assert_allclose(cam[:, v], ref, atol=2e-5)
        ref0 = np.einsum("fij,fnj->fni", ego["R_k_cam_np"], world) + ego["T_k_cam_np"][:, None, :, 0]
        np.testing.assert_allclose(cam[:, 0], ref0, atol=2e-5)
        assert (cam[:, :9, :, 2] > 0).all()  # the fixture puts everything in front of every camera


def test_2d_is_projection_of_cam_coord(processed_verts, arctic_world):
    misc = arctic_world[1]["misc"]["s01"]
    _, _, ego = arctic_world[1]["raw"]["s01/box_grab_01"]
    out = processed_verts

    def proj(K, p):
        q = p @ K.T
        return q[..., :2] / q[..., 2:]

    for key in ("joints.right", "kp3d", "bbox3d", "verts.left"):
        cam = out["cam_coord"][key].astype(np.float64)
        p2d = out["2d"][key]
        for v in range(1, 9):
            np.testing.assert_allclose(p2d[:, v], proj(np.array(misc["intris_mat"][v - 1]), cam[:, v]), atol=2e-3)
        np.testing.assert_allclose(p2d[:, 0], proj(ego["intrinsics"], cam[:, 0]), atol=2e-3)
        np.testing.assert_allclose(p2d[:, 9], proj(ego["intrinsics"], cam[:, 9]), atol=2e-3)
        # view 9 = OpenCV's distorted projection of the undistorted ego points (independent oracle)
        for f in (0, 17, 33):
            ref, _ = cv2.projectPoints(cam[f, 0], np.zeros(3), np.zeros(3), ego["intrinsics"], ego["dist8"])
            np.testing.assert_allclose(p2d[f, 9], ref[:, 0], atol=2e-3)
        np.testing.assert_array_equal(out["cam_coord"][key][:, 9, :, 2], out["cam_coord"][key][:, 0, :, 2])
    assert np.abs(out["2d"]["kp3d"][:, 9] - out["2d"]["kp3d"][:, 0]).max() > 1.0  # distortion is not a no-op


def _arctic_f32_pixels(world: np.ndarray, world2cam: np.ndarray, K: np.ndarray) -> np.ndarray:
    """ARCTIC's arithmetic, written out: float32 cameras, ``M @ [p, 1]`` and ``K @ p`` as
    batched products, then divisions. (F,N,3), (F,4,4), (F,3,3) -> (F,N,2) float32."""
    p = torch.from_numpy(world)
    M = torch.from_numpy(np.ascontiguousarray(world2cam, dtype=np.float32))
    homo = torch.cat([p, torch.ones(p.shape[0], p.shape[1], 1)], dim=2)
    q = torch.bmm(M, homo.permute(0, 2, 1)).permute(0, 2, 1)
    cam = q[:, :, :3] / q[:, :, 3:4]
    uvw = torch.bmm(torch.from_numpy(np.ascontiguousarray(K, dtype=np.float32)), cam.permute(0, 2, 1)).permute(0, 2, 1)
    return (uvw[:, :, :2] / uvw[:, :, 2:3]).numpy()


def test_2d_and_boxes_use_arctic_float32_arithmetic(processed_verts, arctic_world):
    """Bit-equal to float32 geometry on the stored float32 world points (float64 geometry
    rounded to float32 differs in the last bits, which moves truncated pixels)."""
    misc = arctic_world[1]["misc"]["s01"]
    _, _, ego = arctic_world[1]["raw"]["s01/box_grab_01"]
    out = processed_verts
    F = out["bbox"].shape[0]
    w2e = np.zeros((F, 4, 4), np.float32)
    w2e[:, :3, :3], w2e[:, :3, 3], w2e[:, 3, 3] = ego["R_k_cam_np"], ego["T_k_cam_np"][..., 0], 1
    for key in ("joints.right", "joints.left", "kp3d", "bbox3d", "verts.object"):
        world = out["world_coord"][key]
        assert world.dtype == np.float32
        for v in range(9):
            M = w2e if v == 0 else np.broadcast_to(np.array(misc["world2cam"][v - 1]), (F, 4, 4))
            K = np.broadcast_to(ego["intrinsics"] if v == 0 else np.array(misc["intris_mat"][v - 1]), (F, 3, 3))
            np.testing.assert_array_equal(out["2d"][key][:, v], _arctic_f32_pixels(world, M, K), err_msg=f"{key} {v}")
    v2d = torch.from_numpy(out["2d"]["verts.object"][:, 1:9])
    lo, hi = v2d.min(dim=2).values, v2d.max(dim=2).values
    w, h = hi[..., 0] - lo[..., 0], hi[..., 1] - lo[..., 1]
    side = torch.where(w / h > 1, w, h) * 1.1 + torch.maximum(w, h) * 0.6
    ref = torch.stack([lo[..., 0] + w / 2, lo[..., 1] + h / 2, torch.clamp(side / 200.0, min=3.0)], dim=-1)
    np.testing.assert_array_equal(out["bbox"][:, 1:], ref.numpy())


# ARCTIC's float32 posing, written out for the test (smplx MANO lbs, ObjectTensors' and
# common/rot.py's quaternions): the same torch operations, shapes and layouts in the same
# order, so the results are bit-equal to ARCTIC's processing.
def _smplx_mano_f32(layer, rot, pose, betas, transl):
    """smplx ``MANO(use_pca=False, flat_hand_mean=False)`` + 5 fingertips -> (verts, joints21)."""
    B, V = rot.shape[0], layer.v_template.shape[0]
    par = layer.parents.tolist()
    J = len(par)
    full = torch.cat([rot, pose], dim=1) + torch.cat([torch.zeros(3), layer.hand_mean])
    shaped = layer.v_template + torch.einsum("bl,mkl->bmk", betas, layer.shapedirs)
    rest = torch.einsum("bik,ji->bjk", shaped, layer.J_regressor.T.contiguous().T)  # smplx: column-major
    aa = full.reshape(-1, 3)
    ang = torch.norm(aa + 1e-8, dim=1, keepdim=True)
    d = aa / ang
    z = torch.zeros(aa.shape[0], 1)
    K = torch.cat([z, -d[:, 2:3], d[:, 1:2], d[:, 2:3], z, -d[:, 0:1], -d[:, 1:2], d[:, 0:1], z], dim=1).view(-1, 3, 3)
    R = torch.eye(3)[None] + torch.sin(ang)[:, :, None] * K + (1 - torch.cos(ang)[:, :, None]) * torch.bmm(K, K)
    R = R.view(B, J, 3, 3)
    posedirs = layer.posedirs.reshape(V * 3, -1).T  # smplx: (P, V*3), a transposed view
    posed = torch.matmul((R[:, 1:] - torch.eye(3)).view(B, -1), posedirs).view(B, -1, 3) + shaped
    rel = rest.clone()
    rel[:, 1:] -= rest[:, par[1:]]
    local = torch.zeros(B, J, 4, 4)
    local[..., :3, :3], local[..., :3, 3], local[..., 3, 3] = R, rel, 1.0
    G = [local[:, 0]]
    for j in range(1, J):
        G.append(torch.matmul(G[par[j]], local[:, j]))
    G = torch.stack(G, dim=1)
    A = G.clone()
    A[..., 3] = G[..., 3] - torch.matmul(G, torch.cat([rest, torch.zeros(B, J, 1)], dim=2)[..., None])[..., 0]
    T = torch.matmul(layer.lbs_weights[None].expand(B, -1, -1), A.view(B, J, 16)).view(B, -1, 4, 4)
    verts = torch.matmul(T, torch.cat([posed, torch.ones(B, V, 1)], dim=2)[..., None])[:, :, :3, 0] + transl[:, None]
    joints = G[:, :, :3, 3] + transl[:, None]
    return verts, torch.cat([joints, verts[:, layer.tip_ids]], dim=1)


def _q_from_aa(aa):
    ang = torch.norm(aa, p=2, dim=-1, keepdim=True)
    half, small = ang * 0.5, ang.abs() < 1e-6
    r = torch.empty_like(ang)
    r[~small] = torch.sin(half[~small]) / ang[~small]
    r[small] = 0.5 - (ang[small] * ang[small]) / 48
    return torch.cat([torch.cos(half), aa * r], dim=-1)


def _q_mul(a, b):
    aw, ax, ay, az = a.unbind(-1)
    bw, bx, by, bz = b.unbind(-1)
    return torch.stack(
        (
            aw * bw - ax * bx - ay * by - az * bz,
            aw * bx + ax * bw + ay * bz - az * by,
            aw * by - ax * bz + ay * bw + az * bx,
            aw * bz + ax * by - ay * bx + az * bw,
        ),
        -1,
    )


def _q_apply(q, p):
    pq = torch.cat([torch.zeros(p.shape[:-1] + (1,)), p], dim=-1)
    return _q_mul(_q_mul(q, pq), q * torch.tensor([1.0, -1.0, -1.0, -1.0]))[..., 1:]


def _q_to_aa(q):
    half = torch.atan2(torch.norm(q[..., 1:], p=2, dim=-1, keepdim=True), q[..., :1])
    ang = 2 * half
    small = ang.abs() < 1e-6
    r = torch.empty_like(ang)
    r[~small] = torch.sin(half[~small]) / ang[~small]
    r[small] = 0.5 - (ang[small] * ang[small]) / 48
    return q[..., 1:] / r


def _q_from_matrix(R):
    m = R.reshape(R.shape[:-2] + (9,)).unbind(-1)
    (m00, m01, m02, m10, m11, m12, m20, m21, m22) = m
    x = torch.stack([1.0 + m00 + m11 + m22, 1.0 + m00 - m11 - m22, 1.0 - m00 + m11 - m22, 1.0 - m00 - m11 + m22], -1)
    qa = torch.zeros_like(x)
    qa[x > 0] = torch.sqrt(x[x > 0])
    c = torch.stack(
        [
            torch.stack([qa[..., 0] ** 2, m21 - m12, m02 - m20, m10 - m01], -1),
            torch.stack([m21 - m12, qa[..., 1] ** 2, m10 + m01, m02 + m20], -1),
            torch.stack([m02 - m20, m10 + m01, qa[..., 2] ** 2, m12 + m21], -1),
            torch.stack([m10 - m01, m20 + m02, m21 + m12, qa[..., 3] ** 2], -1),
        ],
        -2,
    )
    c = c / (2.0 * qa[..., None].max(torch.tensor(0.1)))
    return c[torch.nn.functional.one_hot(qa.argmax(-1), 4) > 0.5, :].reshape(R.shape[:-2] + (4,))


def test_world_points_and_rotations_use_arctic_float32_arithmetic(processed_verts, root, arctic_world):
    """World points, pixels and camera rotations are bit-equal to ARCTIC's float32 posing
    (smplx MANO, ObjectTensors on float32(mm)/1000 templates, transform_mano_rot_cam).
    Float64 posing rounded to float32 differs in the last bits: ~5e-4 px at 1000 px."""
    import trimesh

    mano, obj, ego = arctic_world[1]["raw"]["s01/box_grab_01"]
    misc = arctic_world[1]["misc"]["s01"]
    out = processed_verts
    F = obj.shape[0]
    f32 = lambda a: torch.from_numpy(np.ascontiguousarray(a, dtype=np.float32))  # noqa: E731
    layers = root.mano_layers()
    world = {}
    for side in ("right", "left"):
        h = mano[side]
        v, j = _smplx_mano_f32(
            layers[side], f32(h["rot"]), f32(h["pose"]), f32(np.tile(h["shape"], (F, 1))), f32(h["trans"])
        )
        world[f"joints.{side}"], world[f"verts.{side}"] = j.numpy(), v.numpy()
        # float64 posing rounded to float32 is not ARCTIC's (what this test tells apart)
        l64 = root.mano_layers(F64)[side]
        j64 = l64(
            *(torch.as_tensor(h[k], dtype=F64) for k in ("rot", "pose")),
            torch.as_tensor(np.tile(h["shape"], (F, 1)), dtype=F64),
            torch.as_tensor(h["trans"], dtype=F64),
        ).joints.float()
        assert not np.array_equal(j64.numpy(), world[f"joints.{side}"])
    # the object, from the template files in mm as ARCTIC's ObjectTensors reads them
    folder = root.meta_dir / "object_vtemplates" / "box"
    params = json.loads((folder / "object_params.json").read_text())
    top = torch.from_numpy(np.array(json.loads((folder / "parts.json").read_text())) == 0)
    tmpl = {
        "verts.object": (torch.FloatTensor(trimesh.load(folder / "mesh.obj", process=False).vertices), top),
        "kp3d": (torch.FloatTensor(params["keypoints_top"] + params["keypoints_bottom"]), torch.arange(32) < 16),
        "bbox3d": (torch.FloatTensor(params["bbox_top"] + params["bbox_bottom"]), torch.arange(16) < 8),
    }
    q_arti = _q_from_aa(torch.tensor([[0.0, 0.0, -1.0]]) * f32(obj[:, :1]))[:, None]
    q_glob = _q_from_aa(f32(obj[:, 1:4]))[:, None]
    t = (f32(obj[:, 4:7]) / 1000)[:, None]
    for key, (mm, is_top) in tmpl.items():
        p = (mm / 1000)[None].expand(F, -1, -1)
        world[key] = torch.where(
            is_top[None, :, None], _q_apply(q_glob, _q_apply(q_arti, p)) + t, _q_apply(q_glob, p) + t
        ).numpy()
    w2e = np.zeros((F, 4, 4), np.float32)
    w2e[:, :3, :3], w2e[:, :3, 3], w2e[:, 3, 3] = ego["R_k_cam_np"], ego["T_k_cam_np"][..., 0], 1
    for key, ref in world.items():
        np.testing.assert_array_equal(out["world_coord"][key], ref, err_msg=key)
        for v in range(9):
            M = w2e if v == 0 else np.broadcast_to(np.array(misc["world2cam"][v - 1]), (F, 4, 4))
            K = np.broadcast_to(ego["intrinsics"] if v == 0 else np.array(misc["intris_mat"][v - 1]), (F, 3, 3))
            np.testing.assert_array_equal(out["2d"][key][:, v], _arctic_f32_pixels(ref, M, K), err_msg=f"{key} {v}")
    # camera-frame rotations: axis-angle of q(R_world2cam) * q(rot), real part >= 0
    for key, aa in (
        ("rot_r_cam", mano["right"]["rot"]),
        ("rot_l_cam", mano["left"]["rot"]),
        ("obj_rot_cam", obj[:, 1:4]),
    ):
        for v in range(9):
            M = f32(w2e if v == 0 else np.broadcast_to(np.array(misc["world2cam"][v - 1]), (F, 4, 4)))
            q = _q_mul(_q_from_matrix(M[:, :3, :3]), _q_from_aa(f32(aa)))
            ref = _q_to_aa(torch.where(q[..., 0:1] < 0, -q, q)).numpy()
            np.testing.assert_array_equal(out["cam_coord"][key][:, v], ref, err_msg=f"{key} {v}")


def test_rot_cam_poses_mano_in_camera_frame(processed, root):
    """MANO(rot_r_cam, pose, β) equals the camera-frame joints up to one translation."""
    out = processed["s01/box_grab_01"]
    p = out["params"]
    layers = root.mano_layers(F64)
    frames = np.array([0, 11, 33])
    n = len(frames) * 9  # every (frame, view) pair in one batch

    def per_view(a):  # (3, ...) per-frame values -> (27, ...) repeated for the 9 views
        return torch.as_tensor(np.repeat(a[frames], 9, axis=0), dtype=F64)

    for side, sfx in (("right", "r"), ("left", "l")):
        rc = torch.as_tensor(out["cam_coord"][f"rot_{sfx}_cam"][frames].reshape(n, 3), dtype=F64)
        j = layers[side](rc, per_view(p[f"pose_{sfx}"]), per_view(p[f"shape_{sfx}"])).joints.numpy()
        d = out["cam_coord"][f"joints.{side}"][frames, :9].reshape(n, 21, 3) - j
        assert np.abs(d - d.mean(axis=1, keepdims=True)).max() < 2e-5
    # the object: layer(θ, obj_rot_cam, no translation) gives camera-frame keypoints up to translation
    rc = torch.as_tensor(out["cam_coord"]["obj_rot_cam"][frames].reshape(n, 3), dtype=F64)
    kp = root.object_layer()(per_view(p["obj_arti"])[:, None], rc, None, ["box"] * n)["kp3d"].numpy()
    d = out["cam_coord"]["kp3d"][frames, :9].reshape(n, 32, 3) - kp
    assert np.abs(d - d.mean(axis=1, keepdims=True)).max() < 2e-5
    # rotation vectors: angle in [0, pi]
    assert (np.linalg.norm(out["cam_coord"]["rot_r_cam"], axis=-1) <= np.pi + 1e-5).all()


def test_bbox_rule(processed_verts, processed):
    clamped = unclamped = 0
    for out in (processed_verts,):
        v2d = out["2d"]["verts.object"].astype(np.float64)
        bbox = out["bbox"]
        for v in range(1, 9):
            lo, hi = v2d[:, v].min(axis=1), v2d[:, v].max(axis=1)
            D = (hi - lo).max(axis=1)
            scale = np.maximum(1.7 * D / 200.0, 3.0)
            np.testing.assert_allclose(bbox[:, v, :2], (lo + hi) / 2, atol=1e-2)
            np.testing.assert_allclose(bbox[:, v, 2], scale, rtol=1e-5)
            clamped += int((1.7 * D / 200.0 < 3.0).sum())
            unclamped += int((1.7 * D / 200.0 > 3.0).sum())
        np.testing.assert_array_equal(bbox[:, 0], np.tile([1400.0, 1000.0, 14.0], (bbox.shape[0], 1)))
    assert clamped > 0 and unclamped > 0  # both branches of the rule are exercised
    for out in processed.values():
        assert (out["bbox"][:, 1:, 2] >= 3.0).all()
        np.testing.assert_array_equal(out["bbox"][:, 0], np.tile([1400.0, 1000.0, 14.0], (out["bbox"].shape[0], 1)))


def _flags_oracle(out, sizes):
    """ARCTIC forward_valid, written out: region = box clipped to the image; ego = [1,2800]x[1,2000]."""
    F = out["bbox"].shape[0]
    order = [9] + list(range(1, 9))
    res = {k: np.zeros((F, 9), dtype=np.int64) for k in ("is_valid", "right_valid", "left_valid")}
    for i, v in enumerate(order):
        cx, cy, s = (out["bbox"][:, i, j].astype(np.float64) for j in range(3))
        if i == 0:
            x0, x1, y0, y1 = 1.0, 2800.0, 1.0, 2000.0
        else:
            W, H = sizes[i]
            x0, x1 = np.maximum(cx - 100 * s, 1), np.minimum(cx + 100 * s, W)
            y0, y1 = np.maximum(cy - 100 * s, 1), np.minimum(cy + 100 * s, H)
        x0, x1, y0, y1 = (np.broadcast_to(a, (F,))[:, None] for a in (x0, x1, y0, y1))

        def inside(p, x0=x0, x1=x1, y0=y0, y1=y1):
            return (p[..., 0] >= x0) & (p[..., 0] <= x1) & (p[..., 1] >= y0) & (p[..., 1] <= y1)

        c = out["2d"]["verts.object"][:, v].astype(np.float64).mean(axis=1, keepdims=True)
        res["is_valid"][:, i] = inside(c)[:, 0]
        for side in ("right", "left"):
            ins = inside(out["2d"][f"joints.{side}"][:, v])
            res[f"{side}_valid"][:, i] = ins[:, 0] & (ins.sum(axis=1) >= 3)
    return res


def test_validity_flags_follow_rule(processed_verts, arctic_world):
    seen = {0: 0, 1: 0}
    for key, out in (("s01/box_grab_01", processed_verts),):
        sizes = arctic_world[1]["misc"][key.split("/")[0]]["image_size"]
        ref = _flags_oracle(out, sizes)
        for k, v in ref.items():
            np.testing.assert_array_equal(out["cam_coord"][k], v, err_msg=f"{key} {k}")
        for val in (0, 1):
            seen[val] += int((out["cam_coord"]["right_valid"] == val).sum())
    assert seen[0] > 0 and seen[1] > 0


def _ego_camera_at(seq, frames, target, normal, dist_m, focal, shift=(0.0, 0.0)):
    """Point the ego camera of ``frames`` at ``target`` from ``dist_m`` along ``normal``; no distortion."""
    seq = copy.deepcopy(seq)
    e = seq.cameras[0]
    e.dist = np.zeros(8)
    for f in frames:
        d = normal[f] / np.linalg.norm(normal[f])
        up = (0.0, 0.0, 1.0) if abs(d[2]) < 0.9 else (1.0, 0.0, 0.0)
        e.world2cam[f] = look_at(target[f] + dist_m * d, target[f], up=up)
        e.K[f] = np.array([[focal[f], 0, 1400 + shift[0]], [0, focal[f], 1000 + shift[1]], [0, 0, 1]])
    return seq


def test_validity_hand_made_cases(root):
    seq = sub_sequence(root.sequence("s01", "box_grab_01"), [0, 1])
    layers = root.mano_layers()
    obj_layer = root.object_layer()
    t = lambda a: torch.as_tensor(a, dtype=torch.float32)  # noqa: E731
    h = seq.right
    joints = layers["right"](t(h.rot), t(h.pose), t(np.tile(h.betas, (2, 1))), t(h.trans)).joints.double().numpy()
    frames = [0, 1]
    # palm normal: direction of least spread of the 21 joints
    normal = np.stack([np.linalg.svd(j - j.mean(axis=0))[2][2] for j in joints])
    centre = joints[:, 1:].mean(axis=1)
    wide = np.full(2, 900.0)

    # control: ego camera 0.4 m above the palm, looking at the hand: every joint inside -> valid
    ok = process_sequence(_ego_camera_at(seq, frames, centre, normal, 0.4, wide), layers, obj_layer)
    assert (ok["cam_coord"]["right_valid"][frames, 0] == 1).all()
    j2d = ok["2d"]["joints.right"][frames, 9]
    assert ((j2d >= [1, 1]) & (j2d <= [2800, 2000])).all()

    # wrist just outside the image, most other joints inside -> invalid
    wrist, rest = j2d[:, 0], j2d[:, 1:].mean(axis=1)
    axis = int(np.argmax(np.abs(wrist - rest).mean(axis=0)))
    shift = [0.0, 0.0]
    if (wrist[:, axis] < rest[:, axis]).all():
        shift[axis] = -(wrist[:, axis].max() + 30.0)  # the wrist lands at <= -30 px
    else:
        shift[axis] = (2800, 2000)[axis] - wrist[:, axis].min() + 30.0
    out = process_sequence(_ego_camera_at(seq, frames, centre, normal, 0.4, wide, shift), layers, obj_layer)
    j2d = out["2d"]["joints.right"][frames, 9]
    inside = ((j2d >= [1, 1]) & (j2d <= [2800, 2000])).all(axis=-1)
    assert not inside[:, 0].any() and (inside.sum(axis=1) >= 10).all()
    assert (out["cam_coord"]["right_valid"][frames, 0] == 0).all()

    # wrist inside but fewer than 3 joints inside: narrow camera on the wrist along the palm
    # normal, so that every other joint (>= r_min away in the palm plane) falls off the image
    off_plane = joints - joints[:, :1]
    lateral = off_plane - (off_plane * normal[:, None]).sum(-1, keepdims=True) * normal[:, None]
    r_min = np.linalg.norm(lateral[:, 1:], axis=-1).min(axis=1)
    narrow = 4000.0 * 0.3 / r_min  # r_min maps to 4000 px at 0.3 m
    close = process_sequence(_ego_camera_at(seq, frames, joints[:, 0], normal, 0.3, narrow), layers, obj_layer)
    j2d = close["2d"]["joints.right"][frames, 9]
    inside = ((j2d >= [1, 1]) & (j2d <= [2800, 2000])).all(axis=-1)
    assert inside[:, 0].all() and (inside.sum(axis=1) < 3).all()
    assert (close["cam_coord"]["right_valid"][frames, 0] == 0).all()

    # object far outside allocentric view 1 (principal point moved away): nothing is valid there
    off = copy.deepcopy(seq)
    off.cameras[1].K[:, 0, 2] = -1.0e5
    res = process_sequence(off, layers, obj_layer)
    for k in ("is_valid", "right_valid", "left_valid"):
        assert (res["cam_coord"][k][:, 1] == 0).all()
    assert res["cam_coord"]["is_valid"][:, 2:].any()


def test_process_sequence_needs_all_cameras(root):
    seq = root.sequence("s01", "box_grab_01")
    del seq.cameras[5]
    with pytest.raises(ValueError, match=r"cameras \[5\] are missing"):
        process_sequence(seq, root.mano_layers(), root.object_layer())


# --------------------------------------------------------------------------------------
# splits
# --------------------------------------------------------------------------------------


def test_build_split_imgnames(root, processed):
    p1 = build_split(root, "p1", "train", processed)
    assert list(p1["data_dict"]) == ["s01/box_grab_01", "s01/laptop_use_02", "s02/notebook_use_01"]
    for v in p1["data_dict"].values():
        assert set(v) == {"cam_coord", "2d", "bbox", "params"}
    expected = []
    for key in ("s01/box_grab_01", "s01/laptop_use_02", "s02/notebook_use_01"):
        sid, seq = key.split("/")
        for n in range(10, SEQS[key] - 10):  # ARCTIC's file numbers, whatever the ioi_offset
            for view in range(1, 9):
                expected.append(f"./data/arctic_data/data/images/{sid}/{seq}/{view}/{n:05d}.jpg")
    assert p1["imgnames"] == expected
    assert p1["imgnames"][0] == "./data/arctic_data/data/images/s01/box_grab_01/1/00010.jpg"
    assert p1["imgnames"][-1] == "./data/arctic_data/data/images/s02/notebook_use_01/8/00021.jpg"
    p2 = build_split(root, "p2", "minival", processed)
    assert list(p2["data_dict"]) == ["s05/box_use_01"]
    assert p2["imgnames"] == [f"./data/arctic_data/data/images/s05/box_use_01/0/{n:05d}.jpg" for n in range(10, 20)]
    short = build_split(root, "p2", "val", processed, frame_margin=14)
    assert [n[-9:-4] for n in short["imgnames"]] == ["00014", "00015"]
    with pytest.raises(AssetError, match="subject s01: ioi_offset 2 exceeds the split's frame margin 1"):
        build_split(root, "p1", "train", processed, frame_margin=1)
    with pytest.raises(ValueError, match="unknown protocol"):
        build_split(root, "p3", "train", processed)


def test_split_images_pair_with_arctic_labels(root, processed, monkeypatch):
    """s01 has ioi_offset 2: its split lists files 00010 .. F − 11 and the dataset pairs file n
    with GT frame n − 2 (the frame that file shows), as ARCTIC's split files and loader do."""
    from hogsa_loader.sample.arctic_dataset import ArcticDataset

    split = build_split(root, "p1", "train", processed)
    monkeypatch.setattr(ArcticRoot, "load_split", lambda self, setup, name: split)
    ds = ArcticDataset(root.data_root, "p1_train", augment=False, cache_ego_k=False)
    F = SEQS["s01/box_grab_01"]
    mine = [i for i, n in enumerate(ds.imgnames) if "/s01/box_grab_01/" in n]
    assert [ds.imgnames[i][-9:-4] for i in mine[::8]] == [f"{n:05d}" for n in range(10, F - 10)]
    cam = processed["s01/box_grab_01"]["cam_coord"]
    for i in (mine[0], mine[9], mine[-1]):
        view, n = int(ds.imgnames[i].split("/")[-2]), int(ds.imgnames[i][-9:-4])
        _, targets, meta = ds.getitem(i, load_rgb=False)
        np.testing.assert_array_equal(targets["mano.j3d.full.r"].numpy(), cam["joints.right"][n - IOI["s01"], view])
        assert targets["is_valid"] == float(cam["is_valid"][n - IOI["s01"], view])


def test_write_processed_splits_round_trip(tmp_path, capsys):
    """The function the world generator calls, on a small separate world (2 sequences)."""
    from hogsa_loader.cli.main import main

    data_root = tmp_path / "data"
    assert main(["assets", "--out", str(data_root), "--no-preview", "--quiet", "--objects", "box"]) == 0
    write_world(data_root, {"s01/box_grab_01": 22, "s05/box_use_01": 21}, seed=5)
    capsys.readouterr()
    paths = write_processed_splits(data_root, progress=True)
    err = capsys.readouterr().err
    assert "ARCTIC process_seq" in err and "2/2" in err  # each sequence processed once for 4 files
    assert sorted(paths) == ["p1_train", "p1_val", "p2_train", "p2_val"]
    r = ArcticRoot(data_root)
    assert paths["p2_val"] == r.arctic_dir / "splits" / "p2_val.npy"
    ref = process_sequence(r.sequence("s01", "box_grab_01"), r.mano_layers(), r.object_layer())
    loaded = r.load_split("p1_minitrain")  # prefix stripped as ARCTIC
    assert list(loaded["data_dict"]) == ["s01/box_grab_01"]
    got = loaded["data_dict"]["s01/box_grab_01"]
    assert set(got) == {"cam_coord", "2d", "bbox", "params"}
    for group in ("cam_coord", "2d", "params"):
        assert set(got[group]) == set(ref[group])
        for k, v in got[group].items():
            np.testing.assert_array_equal(v, ref[group][k], err_msg=f"{group} {k}")
    np.testing.assert_array_equal(got["bbox"], ref["bbox"])
    names = [f"./data/arctic_data/data/images/s01/box_grab_01/{v}/{n:05d}.jpg" for n in (10, 11) for v in range(1, 9)]
    assert loaded["imgnames"] == names
    assert r.load_split("p2", "tinyval")["imgnames"] == ["./data/arctic_data/data/images/s05/box_use_01/0/00010.jpg"]
    assert len(r.load_split("p2_train")["imgnames"]) == 2 and len(r.load_split("p1_val")["imgnames"]) == 8
    # the file is what ARCTIC's own loader reads (np.load with allow_pickle, .item())
    raw = np.load(paths["p1_val"], allow_pickle=True).item()
    assert set(raw) == {"data_dict", "imgnames"} and list(raw["data_dict"]) == ["s05/box_use_01"]
    # deterministic, and quiet without progress
    first = paths["p2_val"].read_bytes()
    again = write_processed_splits(data_root, protocols=("p2",), splits=("val",), progress=False)
    assert list(again) == ["p2_val"] and again["p2_val"].read_bytes() == first
    assert "ARCTIC process_seq" not in capsys.readouterr().err


# --------------------------------------------------------------------------------------
# errors
# --------------------------------------------------------------------------------------


def _raise(fn):
    with pytest.raises(AssetError) as ei:
        fn()
    return ei.value


def test_missing_misc_and_subject(tmp_path):
    r, w = mini_root(tmp_path)
    e = _raise(lambda: ArcticRoot(tmp_path / "nothing"))
    assert "not an ARCTIC data root" in e.problem
    misc_path = r.misc_path
    doc = json.loads(misc_path.read_text())
    misc_path.unlink()
    e = _raise(lambda: ArcticRoot(r.data_root).sequence("s01", "box_grab_01"))
    assert e.path == str(misc_path) and e.problem == "file is missing"
    misc_path.write_text(json.dumps({"s02": doc["s01"]}))
    e = _raise(lambda: ArcticRoot(r.data_root).sequence("s01", "box_grab_01"))
    assert e.path == str(misc_path) and "subject s01 is missing" in e.problem


@pytest.mark.parametrize(
    "edit, message",
    [
        (lambda d: d["s01"]["world2cam"].pop(), "subject s01 has 7 world2cam matrices, expected 8"),
        (lambda d: d["s01"]["intris_mat"].append(d["s01"]["intris_mat"][0]), "has 9 intris_mat matrices, expected 8"),
        (lambda d: d["s01"]["image_size"].pop(), "has 8 image_size entries, expected 9"),
        (lambda d: d["s01"].pop("ioi_offset"), "subject s01 has no 'ioi_offset'"),
        (lambda d: d["s01"].update(ioi_offset=1.5), "ioi_offset must be an integer"),
        (lambda d: d["s01"].update(gender="x"), "gender must be one of"),
        (lambda d: d["s01"]["world2cam"][2][0].__setitem__(0, float("nan")), "contains NaN or inf"),
        (lambda d: d["s01"]["world2cam"][2][0].__setitem__(0, 5.0), "world2cam[2] is not a rotation"),
        (lambda d: d["s01"]["world2cam"][1].__setitem__(3, [0, 0, 1, 1]), "must end with the row (0, 0, 0, 1)"),
        (lambda d: d["s01"]["intris_mat"][0].__setitem__(2, [0, 1, 1]), "intris_mat[0] is not a pinhole"),
        (lambda d: d["s01"]["intris_mat"][3].__setitem__(1, [0, "f", 1]), "expected real numbers"),
        (lambda d: d["s01"]["image_size"].__setitem__(3, [0, 10]), "image_size entries must be positive"),
    ],
)
def test_misc_errors(tmp_path, edit, message):
    r, _ = mini_root(tmp_path)
    doc = json.loads(r.misc_path.read_text())
    edit(doc)
    r.misc_path.write_text(json.dumps(doc))
    e = _raise(lambda: ArcticRoot(r.data_root).misc())
    assert e.path == str(r.misc_path)
    assert message in e.problem, e.problem
    assert message in str(e) and "misc.json" in str(e)


def test_missing_models_and_folders(tmp_path):
    r, _ = mini_root(tmp_path)  # misc + raw_seqs only
    e = _raise(r.mano_layers)
    assert e.path == str(r.data_root / "body_models" / "mano") and "MANO model folder is missing" in e.problem
    e = _raise(r.object_layer)
    assert e.path == str(r.meta_dir / "object_vtemplates")
    e = _raise(lambda: r.sequences("s09"))
    assert e.path == str(r.raw_dir / "s09")
    e = _raise(lambda: r.sequence("s01", "box_grab_99"))
    assert e.path == str(r.raw_paths("s01", "box_grab_99")["mano"]) and e.problem == "file is missing"
    shutil.rmtree(r.raw_dir)
    e = _raise(lambda: ArcticRoot(r.data_root).sequences())
    assert e.path == str(r.raw_dir) and "raw_seqs folder is missing" in e.problem


def test_load_split_errors(tmp_path):
    r, _ = mini_root(tmp_path)
    path = r.arctic_dir / "splits" / "p1_val.npy"
    e = _raise(lambda: r.load_split("p1_smallval"))
    assert e.path == str(path) and e.problem == "file is missing"
    path.parent.mkdir()
    for doc, msg in (
        ([1, 2], "expected a dict with 'data_dict' and 'imgnames'"),
        ({"data_dict": {"s01/a_b_01": {}}, "imgnames": []}, "has no 'cam_coord'"),
        ({"data_dict": {}, "imgnames": [1]}, "'imgnames' must be a list of strings"),
        ({"data_dict": [], "imgnames": []}, "'data_dict' must map"),
    ):
        boxed = np.empty((), dtype=object)
        boxed[()] = doc
        np.save(path, boxed, allow_pickle=True)
        e = _raise(lambda: r.load_split("p1", "val"))
        assert e.path == str(path) and msg in e.problem, e.problem
    with pytest.raises(ValueError, match="unknown split"):
        r.load_split("p1_holdout")
    with pytest.raises(ValueError, match="must look like"):
        r.load_split("p1")


@pytest.mark.parametrize(
    "edit, message",
    [
        (
            lambda q: q["params"].__setitem__("K_ego", q["params"]["K_ego"][0]),
            ".params.K_ego has shape (3, 3), expected (F, 3, 3)",
        ),  # data_doc.md's unbatched layout
        (
            lambda q: q["params"].__setitem__("dist", q["params"]["dist"][0]),
            ".params.dist has shape (8,), expected (F, 8)",
        ),
        (lambda q: q["2d"].pop("kp3d"), ".2d.kp3d is missing"),
        (lambda q: q["cam_coord"].pop("is_valid"), ".cam_coord.is_valid is missing"),
        (lambda q: q.__setitem__("bbox", q["bbox"][..., :2]), ".bbox has shape"),
        (lambda q: q["params"].__setitem__("obj_arti", q["params"]["obj_arti"][:, None]), ".params.obj_arti has shape"),
        (lambda q: q["2d"].__setitem__("joints.left", q["2d"]["joints.left"][:-1]), ".2d.joints.left has shape"),
        (lambda q: q["params"]["K_ego"].__setitem__((0, 0, 0), np.nan), ".params.K_ego contains NaN or inf"),
        (lambda q: q["params"]["K_ego"].__setitem__((1, 2), (0.0, 1.0, 1.0)), ".params.K_ego[1] is not a pinhole"),
        (
            lambda q: q["cam_coord"]["is_valid"].__setitem__((0, 1), 2),
            ".cam_coord.is_valid holds values other than 0 and 1",
        ),
        (
            lambda q: q["params"].__setitem__("pose_r", q["params"]["pose_r"].astype(object)),
            ".params.pose_r is a ndarray of object",
        ),
        (lambda q: q["params"].__setitem__("trans_l", q["params"]["trans_l"][:, :2]), ".params.trans_l has shape"),
    ],
)
def test_load_split_checks_every_array(tiny_world, tmp_path, monkeypatch, edit, message):
    """The arrays inside a split file are checked when it is loaded (not at the first
    sample, with an IndexError), naming the file, the sequence and the key."""
    r = ArcticRoot(tiny_world)
    src = r.split_path("p2", "val")
    doc = read_npy(src)
    key = next(iter(doc["data_dict"]))
    edit(doc["data_dict"][key])
    path = tmp_path / "p2_val.npy"
    boxed = np.empty((), dtype=object)
    boxed[()] = doc
    np.save(path, boxed, allow_pickle=True)
    monkeypatch.setattr(r, "split_path", lambda protocol, split: path)
    e = _raise(lambda: r.load_split("p2", "val"))
    assert e.path == str(path) and f"data_dict[{key!r}]{message}" in e.problem, e.problem


def _edit_mano(key, fn):
    def edit(mano, obj, ego):
        side, k = key.split(".")
        mano[side][k] = fn(mano[side][k])
        return mano, obj, ego

    return edit


@pytest.mark.parametrize(
    "edit, which, message",
    [
        (
            _edit_mano("right.pose", lambda a: a[:, :44]),
            "mano",
            "right.pose has shape (30, 44), expected (F, 45) with F = 30",
        ),
        (
            _edit_mano("left.trans", lambda a: a[:-1]),
            "mano",
            "left.trans has shape (29, 3), expected (F, 3) with F = 30",
        ),
        (_edit_mano("left.shape", lambda a: a[:9]), "mano", "left.shape has shape (9,), expected (10,)"),
        (
            _edit_mano("right.rot", lambda a: np.where(np.arange(30)[:, None] == 4, np.nan, a)),
            "mano",
            "right.rot contains NaN or inf (3 values)",
        ),
        (
            _edit_mano("left.fitting_err", lambda a: np.full_like(a, np.inf)),
            "mano",
            "left.fitting_err contains NaN or inf",
        ),
        (_edit_mano("right.pose", lambda a: a.astype(np.complex128)), "mano", "right.pose has dtype complex128"),
        (_edit_mano("right.pose", lambda a: a > 0), "mano", "right.pose has dtype bool"),
        (_edit_mano("right.trans", lambda a: np.array(list(a), dtype=object)), "mano", "right.trans has dtype object"),
        (_edit_mano("right.trans", lambda a: "x"), "mano", "right.trans is a str"),
        (lambda m, o, e: ({"right": m["right"]}, o, e), "mano", "'left' is missing or not a dict"),
        (lambda m, o, e: ([m], o, e), "mano", "expected a dict with 'right' and 'left'"),
        (
            lambda m, o, e: (m, o[:, :6], e),
            "object",
            "object parameters has shape (30, 6), expected (F, 7) with F = 30",
        ),
        (lambda m, o, e: (m, o[:29], e), "object", "has 29 frames, but box_grab_01.mano.npy has 30"),
        (lambda m, o, e: (m, np.where(o == o[3, 5], np.nan, o), e), "object", "object parameters contains NaN"),
        (lambda m, o, e: (m, o, {k: v for k, v in e.items() if k != "dist8"}), "egocam", "key 'dist8' is missing"),
        (lambda m, o, e: (m, o, dict(e, dist8=e["dist8"][:5])), "egocam", "dist8 has shape (5,), expected (8,)"),
        (lambda m, o, e: (m, o, dict(e, R_k_cam_np=e["R_k_cam_np"][:20])), "egocam", "R_k_cam_np has 20 frames"),
        (lambda m, o, e: (m, o, dict(e, R_k_cam_np=e["R_k_cam_np"] * 2)), "egocam", "R_k_cam_np[0] is not a rotation"),
        (
            lambda m, o, e: (m, o, dict(e, intrinsics=np.eye(4))),
            "egocam",
            "intrinsics has shape (4, 4), expected (3, 3)",
        ),
        (
            lambda m, o, e: (m, o, dict(e, T_k_cam_np=e["T_k_cam_np"][..., 0] * np.nan)),
            "egocam",
            "T_k_cam_np contains NaN or inf",
        ),
    ],
)
def test_raw_errors_name_file_and_problem(tmp_path, edit, which, message):
    r, w = mini_root(tmp_path)
    mano, obj, ego = copy.deepcopy(w["raw"]["s01/box_grab_01"])
    write_raw(r.raw_dir, "s01/box_grab_01", *edit(mano, obj, ego))
    e = _raise(lambda: r.sequence("s01", "box_grab_01"))
    assert e.path == str(r.raw_paths("s01", "box_grab_01")[which])
    assert message in e.problem, e.problem


def test_T_as_F3_is_accepted(tmp_path):
    r, w = mini_root(tmp_path)
    mano, obj, ego = w["raw"]["s01/box_grab_01"]
    write_raw(r.raw_dir, "s01/box_grab_01", mano, obj, dict(ego, T_k_cam_np=ego["T_k_cam_np"][..., 0]))
    np.testing.assert_array_equal(r.raw_sequence("s01", "box_grab_01").T_ego, ego["T_k_cam_np"][..., 0])


@pytest.mark.parametrize("which", ["mano", "object", "egocam"])
def test_truncated_and_missing_npy(tmp_path, which):
    r, _ = mini_root(tmp_path)
    path = r.raw_paths("s01", "box_grab_01")[which]
    data = path.read_bytes()
    for cut in (0, 5, 100, len(data) // 2, len(data) - 1):
        path.write_bytes(data[:cut])
        e = _raise(lambda: r.raw_sequence("s01", "box_grab_01"))
        assert e.path == str(path)
        assert any(w in e.problem for w in ("truncated", "not a .npy file", "corrupt")), e.problem
    path.unlink()
    e = _raise(lambda: r.raw_sequence("s01", "box_grab_01"))
    assert e.path == str(path) and e.problem == "file is missing"


class _Evil:
    """Pickles as a call to ``exec`` (what an attacker would put in an .npy)."""

    def __init__(self, sentinel: Path) -> None:
        self.sentinel = sentinel

    def __reduce__(self):
        return (exec, (f"open({str(self.sentinel)!r}, 'w').write('pwned')",))


def test_malicious_npy_is_refused_and_never_executed(tmp_path):
    r, w = mini_root(tmp_path)
    sentinel = tmp_path / "pwned.txt"
    mano, obj, ego = w["raw"]["s01/box_grab_01"]
    evil_mano = dict(mano, right=dict(mano["right"], rot=_Evil(sentinel)))
    write_raw(r.raw_dir, "s01/box_grab_01", evil_mano, obj, ego)
    path = r.raw_paths("s01", "box_grab_01")["mano"]
    with pytest.raises(UnsafePickleError) as ei:
        r.sequence("s01", "box_grab_01")
    assert isinstance(ei.value, AssetError) and ei.value.path == str(path)
    assert "builtins.exec" in ei.value.problem
    assert not sentinel.exists()
    # a split file carrying the same payload is refused too
    split = r.arctic_dir / "splits" / "p1_train.npy"
    split.parent.mkdir(parents=True)
    np.save(split, {"data_dict": {}, "imgnames": [_Evil(sentinel)]}, allow_pickle=True)
    with pytest.raises(UnsafePickleError):
        r.load_split("p1_train")
    assert not sentinel.exists()
    # other globals are refused as well (os.system through a protocol-0 pickle)
    payload = b"cos\nsystem\n(S'true'\ntR."
    header = b"\x93NUMPY\x01\x00" + (118).to_bytes(2, "little")
    text = "{'descr': '|O', 'fortran_order': False, 'shape': (), }".ljust(117) + "\n"
    path.write_bytes(header + text.encode() + payload)
    with pytest.raises(UnsafePickleError, match="os.system"):
        r.raw_sequence("s01", "box_grab_01")
    # control: the payload is live — numpy's own loader runs it
    np.save(path, evil_mano, allow_pickle=True)
    np.load(path, allow_pickle=True)
    assert sentinel.read_text() == "pwned"


def test_sparse_matrices_are_rebuilt_from_checked_arrays(tmp_path):
    """A world's downsamplers.npy pickles scipy CSR matrices: read_npy rebuilds them with
    scipy's constructor and refuses inconsistent ones."""
    from scipy.sparse import csr_matrix

    from hogsa_loader.assets.arctic import read_npy

    D = csr_matrix((np.ones(3, np.float32), (np.arange(3), np.array([4, 0, 2]))), shape=(3, 5))
    path = tmp_path / "downsamplers.npy"
    np.save(path, np.array({"box": {"D": D, "vertex_ids": np.array([4, 0, 2])}}, dtype=object), allow_pickle=True)
    got = read_npy(path)["box"]["D"]
    assert isinstance(got, csr_matrix) and got.dtype == np.float32 and (got != D).nnz == 0
    bad = D.copy()
    bad.indices = np.array([4, 9, 2], dtype=bad.indices.dtype)  # column 9 of a 5-column matrix
    np.save(path, np.array({"D": bad}, dtype=object), allow_pickle=True)
    with pytest.raises(AssetError, match=r"csr sparse matrix: 'indices' holds indices in \[2, 9\], outside \[0, 5\)"):
        read_npy(path)


def test_read_npy_formats(tmp_path):
    a = np.arange(12, dtype=np.float32).reshape(3, 4)
    np.save(tmp_path / "c.npy", a)
    np.save(tmp_path / "f.npy", np.asfortranarray(a))
    for name in ("c.npy", "f.npy"):
        out = read_npy(tmp_path / name)
        np.testing.assert_array_equal(out, a)
        assert out.dtype == np.float32
    d = {"x": np.ones((2, 2)), "s": "text", "n": [1, 2.5], "k": np.float32(3)}
    arr = np.asarray(d, dtype=object)
    for proto in (2, 4, 5):  # 2: bytes via _codecs.encode; 5: numpy _frombuffer
        with open(tmp_path / f"p{proto}.npy", "wb") as fh:
            np.lib.format.write_array_header_1_0(fh, np.lib.format.header_data_from_array_1_0(arr))
            pickle.dump(arr, fh, protocol=proto)
        out = read_npy(tmp_path / f"p{proto}.npy")
        assert set(out) == set(d) and out["s"] == "text" and out["n"] == [1, 2.5] and out["k"] == 3
        np.testing.assert_array_equal(out["x"], d["x"])
        assert np.load(tmp_path / f"p{proto}.npy", allow_pickle=True).item()["s"] == "text"
    # version-2 header
    with open(tmp_path / "v2.npy", "wb") as fh:
        np.lib.format.write_array(fh, a, version=(2, 0))
    np.testing.assert_array_equal(read_npy(tmp_path / "v2.npy"), a)


# --------------------------------------------------------------------------------------
# fuzz: corrupt raw files -> AssetError only
# --------------------------------------------------------------------------------------

_MANO_KEYS = [f"{s}.{k}" for s in ("right", "left") for k in ("rot", "pose", "trans", "shape", "fitting_err")]
_EGO_KEYS = ["R_k_cam_np", "T_k_cam_np", "intrinsics", "dist8"]


def _corrupt_array(a, kind: str, draw):
    a = np.asarray(a)
    if kind == "shape":
        op = draw(st.sampled_from(["drop_last", "add_col", "flatten", "scalar", "transpose", "empty", "extra_dim"]))
        if op == "drop_last":
            return a[..., :-1] if a.ndim else a
        if op == "add_col":
            return np.concatenate([a, a[..., :1]], axis=-1) if a.ndim else np.array([a, a])
        if op == "flatten":
            return a.reshape(-1)[: max(a.size - 1, 0)]
        if op == "scalar":
            return np.float64(1.0)
        if op == "transpose":
            return a.T if a.ndim > 1 and a.shape[0] != a.shape[-1] else a[None]
        if op == "empty":
            return np.zeros((0,) + a.shape[1:])
        return a[None]
    if kind in ("nan", "inf"):
        b = a.astype(np.float64).copy()
        if b.size == 0:
            return np.float64(np.nan)
        idx = draw(st.integers(0, b.size - 1))
        b.reshape(-1)[idx] = np.nan if kind == "nan" else -np.inf
        return b
    dt = draw(st.sampled_from(["complex", "str", "bool", "object", "bytes"]))
    if dt == "complex":
        return a.astype(np.complex64)
    if dt == "str":
        return a.astype(str)
    if dt == "bool":
        return a > 0
    if dt == "object":
        return np.array([None] * max(a.size, 1), dtype=object)
    return a.tobytes()[:16]


@settings(
    max_examples=200,
    deadline=None,
    database=None,
    suppress_health_check=[HealthCheck.function_scoped_fixture, HealthCheck.too_slow],
)
@given(data=st.data())
def test_fuzz_corrupt_raw_files_raise_only_asset_error(data, fuzz_template):
    which = data.draw(st.sampled_from(["mano", "object", "egocam"]))
    kind = data.draw(st.sampled_from(["truncate", "flip", "shape", "nan", "inf", "dtype", "missing", "container"]))
    r = _restore(fuzz_template)
    path = r.raw_paths("s01", "box_grab_01")[which]
    mano, obj, ego = copy.deepcopy(fuzz_template["raw"])
    must_fail = kind not in ("flip",)
    if kind in ("truncate", "flip"):
        raw = bytearray(path.read_bytes())
        if kind == "truncate":
            raw = raw[: data.draw(st.integers(0, len(raw) - 1))]
        else:
            for _ in range(data.draw(st.integers(1, 8))):
                i = data.draw(st.integers(0, len(raw) - 1))
                raw[i] ^= data.draw(st.integers(1, 255))
        path.write_bytes(bytes(raw))
    else:
        if which == "mano":
            side, key = data.draw(st.sampled_from(_MANO_KEYS)).split(".")
            if kind == "missing":
                del mano[side][key]
            elif kind == "container":
                mano[side] = data.draw(st.sampled_from([[1, 2], "hand", 3, None]))
            else:
                mano[side][key] = _corrupt_array(mano[side][key], kind, data.draw)
        elif which == "object":
            if kind in ("missing", "container"):
                obj = data.draw(st.sampled_from([{"obj": obj}, [list(row) for row in obj[:, :3]], "object"]))
            else:
                obj = _corrupt_array(obj, kind, data.draw)
        else:
            key = data.draw(st.sampled_from(_EGO_KEYS))
            if kind == "missing":
                del ego[key]
            elif kind == "container":
                ego = data.draw(st.sampled_from([list(ego.values())[:2], "ego", 7]))
            else:
                ego[key] = _corrupt_array(ego[key], kind, data.draw)
        value = {"mano": mano, "object": obj, "egocam": ego}[which]
        if not isinstance(value, np.ndarray):  # wrap as np.save does for a dict (works for ragged lists)
            boxed = np.empty((), dtype=object)
            boxed[()] = value
            value = boxed
        np.save(path, value, allow_pickle=True)
    try:
        r.sequence("s01", "box_grab_01")
    except AssetError as exc:
        assert exc.path == str(path) or exc.path.endswith(".npy"), exc
    else:
        assert not must_fail, f"{which}/{kind} was accepted"


@pytest.fixture(scope="module")
def fuzz_template(tmp_path_factory):
    """A reader-only root whose files are restored from ``originals`` before each example."""
    tmp = tmp_path_factory.mktemp("fuzz")
    r, w = mini_root(tmp, F=8, seed=11)
    files = list(r.raw_paths("s01", "box_grab_01").values()) + [r.misc_path]
    return {"root": r.data_root, "raw": w["raw"]["s01/box_grab_01"], "originals": {f: f.read_bytes() for f in files}}


def _restore(template) -> ArcticRoot:
    for f, data in template["originals"].items():
        f.write_bytes(data)
    return ArcticRoot(template["root"])  # fresh root: no cached misc


_JSON = st.recursive(
    st.none()
    | st.booleans()
    | st.integers(-(2**70), 2**70)
    | st.floats(allow_nan=True, allow_infinity=True)
    | st.text(max_size=5),
    lambda children: st.lists(children, max_size=5) | st.dictionaries(st.text(max_size=4), children, max_size=4),
    max_leaves=12,
)


def _replace_random_node(doc, draw):
    """Replace one node (dict entry or list item) of a JSON document by random JSON."""
    node = doc
    while True:
        keys = list(node.keys()) if isinstance(node, dict) else list(range(len(node)))
        if not keys:
            return
        k = draw(st.sampled_from(keys))
        child = node[k]
        if isinstance(child, (dict, list)) and child and draw(st.booleans()):
            node = child
            continue
        node[k] = draw(_JSON)
        return


@settings(
    max_examples=150,
    deadline=None,
    database=None,
    suppress_health_check=[HealthCheck.function_scoped_fixture, HealthCheck.too_slow],
)
@given(data=st.data())
def test_fuzz_corrupt_misc_json_raises_only_asset_error(data, fuzz_template):
    misc_path = fuzz_template["root"] / "arctic_data/data/meta/misc.json"
    doc = json.loads(fuzz_template["originals"][misc_path])
    for _ in range(data.draw(st.integers(1, 3))):
        _replace_random_node(doc, data.draw)
    r = _restore(fuzz_template)
    r.misc_path.write_text(json.dumps(doc))
    try:
        r.sequence("s01", "box_grab_01")
    except AssetError as exc:
        assert exc.path == str(r.misc_path), exc


@pytest.mark.parametrize(
    "field, value, message",
    [
        ("trans", 1e30, r"right\.trans reaches 1e\+30 m, beyond any real capture"),
        ("rot", 1e30, r"right\.rot reaches 1\.73e\+30 rad"),
        ("pose", -1e6, r"right\.pose reaches 1\.73e\+06 rad"),
    ],
)
def test_physically_impossible_hand_values_are_refused(tiny_world, tmp_path, field, value, message):
    """Finite but absurd annotations (a hand 10³⁰ m away) are refused by the reader, naming the
    file and the field, instead of yielding samples that are all dropped."""
    from hogsa_loader.assets.arctic import ArcticRoot, read_npy

    src = next((tiny_world / "arctic_data" / "data" / "raw_seqs").rglob("*.mano.npy"))
    data = read_npy(src)
    ArcticRoot._read_mano(src)  # the untouched file is accepted
    data["right"][field] = np.full_like(np.asarray(data["right"][field], dtype=np.float64), value)
    bad = tmp_path / src.name
    np.save(bad, np.array(data, dtype=object), allow_pickle=True)
    with pytest.raises(AssetError, match=message) as info:
        ArcticRoot._read_mano(bad)
    assert str(bad) in str(info.value)
