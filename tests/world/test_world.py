"""`hogsa world`: ARCTIC-format synthetic worlds (layout, formats, images, masks, physics).

Everything is checked from the files alone, with code independent of the generator where it
matters: MANO forward through :class:`MANOLayer` on the stored parameters, object posing with
ARCTIC's articulation, the ``misc.json`` / ``.egocam.dist.npy`` cameras and the conventions
module's crop maps; penetration against the ``mesh.obj`` triangles (each part is convex, so a
point is inside iff it is behind every face plane); contact from dense surface samples.
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
from pathlib import Path

import cv2
import numpy as np
import pytest
import torch
from scipy.spatial import cKDTree
from scipy.spatial.transform import Rotation

from hogsa_loader.assets.conventions import (
    EGO_IMAGE_SIZE,
    allocentric_bbox,
    distort_points,
    full_to_cropped,
    project,
    transform,
)
from hogsa_loader.assets.hands.mano import MANOLayer
from hogsa_loader.assets.hands.mano_io import load_mano
from hogsa_loader.assets.objects.articulated import articulate
from hogsa_loader.assets.objects.template import load_object_template
from hogsa_loader.sample.arctic_dataset import ArcticDataset
from hogsa_loader.sample.augment import ArcticConfig
from hogsa_world import PRESETS, SequencePlan, SubjectPlan, generate_world
from hogsa_world.grasp import grasp_specs, styled_spec

MASK_IDS = {"background": 0, "right": 1, "left": 2, "object_top": 3, "object_bottom": 4}
HAND_ID = {"right": 1, "left": 2}
OBJECT_IDS = (3, 4)


# --------------------------------------------------------------------------------------
# Loading helpers
# --------------------------------------------------------------------------------------
class World:
    """A generated world read back from disk, with annotations projected once."""

    def __init__(self, root: Path) -> None:
        self.root = root
        self.data = root / "arctic_data" / "data"
        self.meta = json.loads((self.data / "meta" / "hogsa_world.json").read_text())
        self.misc = json.loads((self.data / "meta" / "misc.json").read_text())
        mano_dir = root / "body_models" / "mano"
        self.layers = {
            s: MANOLayer(load_mano(mano_dir, side=s), flat_hand_mean=False, dtype=torch.float64)
            for s in ("right", "left")
        }
        self.seqs = [(s["sid"], s["seq"]) for s in self.meta["sequences"]]
        self._cache: dict = {}

    def template(self, name: str):
        key = ("template", name)
        if key not in self._cache:
            self._cache[key] = load_object_template(self.data / "meta" / "object_vtemplates" / name, load_texture=False)
        return self._cache[key]

    def raw(self, sid: str, seq: str) -> tuple[dict, np.ndarray, dict]:
        base = self.data / "raw_seqs" / sid
        return (
            np.load(base / f"{seq}.mano.npy", allow_pickle=True).item(),
            np.load(base / f"{seq}.object.npy", allow_pickle=True),
            np.load(base / f"{seq}.egocam.dist.npy", allow_pickle=True).item(),
        )

    def posed(self, sid: str, seq: str) -> dict:
        """World joints/verts of both hands, object mesh verts and keypoints, all frames."""
        key = ("posed", sid, seq)
        if key in self._cache:
            return self._cache[key]
        mano, obj, _ = self.raw(sid, seq)
        out = {}
        for side, layer in self.layers.items():
            p = mano[side]
            F = p["rot"].shape[0]
            o = layer(
                global_orient=torch.as_tensor(p["rot"], dtype=torch.float64),
                hand_pose=torch.as_tensor(p["pose"], dtype=torch.float64),
                betas=torch.as_tensor(np.repeat(p["shape"][None], F, 0), dtype=torch.float64),
                transl=torch.as_tensor(p["trans"], dtype=torch.float64),
            )
            out[f"joints_{side}"] = o.joints.numpy()
            out[f"verts_{side}"] = o.vertices.numpy()
        t = self.template(seq.split("_")[0])
        op = torch.as_tensor(obj.astype(np.float64))

        def pose(points: np.ndarray, is_top: np.ndarray) -> np.ndarray:
            x = torch.as_tensor(points, dtype=torch.float64)[None].expand(op.shape[0], -1, -1)
            return articulate(x, torch.as_tensor(is_top), op[:, 0], op[:, 1:4], op[:, 4:7] / 1000.0).numpy()

        out["obj_mesh"] = pose(t.verts, t.parts == 0)
        kp = np.concatenate([t.kp_top, t.kp_bottom])
        out["kp"] = pose(kp, np.arange(32) < 16)
        self._cache[key] = out
        return out

    def project(self, sid: str, seq: str, view: int, points: np.ndarray) -> np.ndarray:
        """(F, N, 3) world points -> (F, N, 2) pixels of the cropped image of ``view``."""
        _, _, ego = self.raw(sid, seq)
        F = points.shape[0]
        if view == 0:
            w2c = np.zeros((F, 4, 4))
            w2c[:, :3, :3] = ego["R_k_cam_np"]
            w2c[:, :3, 3] = ego["T_k_cam_np"][..., 0]
            w2c[:, 3, 3] = 1.0
            cam = distort_points(transform(w2c, points), ego["dist8"].astype(np.float64))
            return project(cam, ego["intrinsics"].astype(np.float64)) * self.meta["ego_image_scale"]
        m = self.misc[sid]
        K = np.asarray(m["intris_mat"][view - 1])
        w2c = np.asarray(m["world2cam"][view - 1])
        bbox = allocentric_bbox(project(transform(w2c, self.posed(sid, seq)["obj_mesh"]), K))
        return full_to_cropped(project(transform(w2c, points), K), bbox, self.meta["cropped_size"])

    def frame_ids(self, sid: str) -> int:
        return int(self.misc[sid]["ioi_offset"])

    def mask(self, sid: str, seq: str, view: int, frame: int) -> np.ndarray:
        name = f"{frame + self.frame_ids(sid):05d}.png"
        return cv2.imread(str(self.data / "masks" / sid / seq / str(view) / name), cv2.IMREAD_UNCHANGED)


@pytest.fixture(scope="module")
def world(tiny_world) -> World:
    return World(tiny_world)


def _lookup(mask: np.ndarray, uv: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Mask values at label coordinates (OpenCV: pixel i centred on i) and the in-image flags."""
    h, w = mask.shape
    col = np.rint(uv[:, 0]).astype(int)  # OpenCV/ARCTIC: pixel i is centred on coordinate i
    row = np.rint(uv[:, 1]).astype(int)
    inside = (col >= 0) & (col < w) & (row >= 0) & (row < h)
    vals = np.full(len(uv), -1)
    vals[inside] = mask[row[inside], col[inside]]
    return vals, inside


# --------------------------------------------------------------------------------------
# Layout and formats
# --------------------------------------------------------------------------------------
def test_layout_models_and_templates(world):
    d = world.data
    for sub in ("raw_seqs", "meta", "cropped_images", "splits_json", "splits", "masks"):
        assert (d / sub).is_dir(), sub
    for side in ("right", "left"):
        model = load_mano(world.root / "body_models" / "mano" / f"MANO_{side.upper()}.pkl")
        assert model.side == side and model.num_verts == world.layers[side].num_verts
    meta = json.loads((d / "meta" / "object_meta.json").read_text())
    for name in {seq.split("_")[0] for _, seq in world.seqs}:
        folder = d / "meta" / "object_vtemplates" / name
        for f in (
            "mesh.obj",
            "parts.json",
            "object_params.json",
            "top_keypoints_300.json",
            "bottom_keypoints_300.json",
        ):
            assert (folder / f).is_file(), (name, f)
        assert 0.05 < meta[name]["diameter"] < 1.0
    assert (world.root / "world_preview.png").is_file()


def test_raw_seq_files_follow_arctic(world):
    F = world.meta["num_frames"]
    assert F >= 52
    betas = {}
    for sid, seq in world.seqs:
        mano, obj, ego = world.raw(sid, seq)
        assert set(mano) == {"right", "left"}
        for side, p in mano.items():
            assert set(p) >= {"rot", "pose", "trans", "shape", "fitting_err"}
            for key, shape in (
                ("rot", (F, 3)),
                ("pose", (F, 45)),
                ("trans", (F, 3)),
                ("shape", (10,)),
                ("fitting_err", (F,)),
            ):
                assert p[key].shape == shape and p[key].dtype == np.float32, (side, key, p[key].shape)
                assert np.isfinite(p[key]).all()
            assert len(p["fitting_err"]) > 50 and (p["fitting_err"] == 0).all()  # exact labels
            betas[(sid, side)] = p["shape"]
        assert np.array_equal(mano["right"]["shape"], mano["left"]["shape"])
        assert obj.shape == (F, 7) and obj.dtype.kind == "f"
        # translation in mm: the object sits on a table ~0.75 m above the floor
        assert 500 < np.abs(obj[:, 4:7]).max() < 2000
        for key in (
            "R_k_cam_np",
            "T_k_cam_np",
            "intrinsics",
            "dist8",
            "ego_markers.ref",
            "ego_markers.label",
            "R0",
            "T0",
        ):
            assert key in ego, key
        R = ego["R_k_cam_np"].astype(np.float64)
        assert R.shape == (F, 3, 3) and ego["T_k_cam_np"].shape == (F, 3, 1)
        assert np.abs(R @ R.transpose(0, 2, 1) - np.eye(3)).max() < 1e-5
        assert np.abs(np.linalg.det(R) - 1).max() < 1e-5
        K = ego["intrinsics"]
        assert K.shape == (3, 3) and abs(K[0, 2] - 1400) < 60 and abs(K[1, 2] - 1000) < 60
        assert ego["dist8"].shape == (8,) and 0 < np.abs(ego["dist8"]).max() < 0.2  # mild, non-zero
        # the head moves a little (no two frames identical) but not much
        centres = -np.einsum("fji,fj->fi", R, ego["T_k_cam_np"][..., 0])
        assert 0.002 < np.linalg.norm(centres - centres.mean(0), axis=1).max() < 0.08
    # each subject has its own hand shape
    sids = sorted({sid for sid, _ in world.seqs})
    assert not np.allclose(betas[(sids[0], "right")], betas[(sids[1], "right")])


def test_misc_json_structure(world):
    assert set(world.misc) == {s["sid"] for s in world.meta["subjects"]}
    offsets = []
    for m in world.misc.values():
        assert set(m) >= {"world2cam", "intris_mat", "image_size", "ioi_offset", "gender"}
        w2c = np.asarray(m["world2cam"])
        K = np.asarray(m["intris_mat"])
        assert w2c.shape == (8, 4, 4) and K.shape == (8, 3, 3)
        assert np.allclose(w2c[:, 3], [0, 0, 0, 1])
        R = w2c[:, :3, :3]
        assert np.abs(R @ R.transpose(0, 2, 1) - np.eye(3)).max() < 1e-9
        assert np.allclose(K[:, 2], [0, 0, 1]) and (K[:, 0, 0] > 0).all()
        sizes = m["image_size"]
        assert len(sizes) == 9 and all(len(s) == 2 and all(isinstance(x, int) for x in s) for s in sizes)
        assert tuple(sizes[0]) == EGO_IMAGE_SIZE
        # principal points inside their images; 8 distinct camera centres around the table
        assert all(0 < K[i, 0, 2] < sizes[i + 1][0] and 0 < K[i, 1, 2] < sizes[i + 1][1] for i in range(8))
        centres = -np.einsum("kji,kj->ki", R, w2c[:, :3, 3])
        az = np.sort(np.arctan2(centres[:, 1], centres[:, 0]))
        assert np.diff(np.concatenate([az, az[:1] + 2 * np.pi])).max() < np.pi / 2  # a ring, no big gap
        assert np.ptp(centres[:, 2]) > 0.2  # varying heights
        assert isinstance(m["ioi_offset"], int) and m["gender"] in ("male", "female")
        offsets.append(m["ioi_offset"])
    assert any(o != 0 for o in offsets)


def test_splits_json_and_processed_splits(world):
    d = world.data
    subjects = {s["sid"]: s["split"] for s in world.meta["subjects"]}
    assert subjects.get("s05") == "val"
    for p in ("p1", "p2"):
        proto = json.loads((d / "splits_json" / f"protocol_{p}.json").read_text())
        assert set(proto) == {"train", "val", "test"} and proto["test"] == []
        listed = proto["train"] + proto["val"]
        assert sorted(listed) == sorted(f"{sid}/{seq}" for sid, seq in world.seqs)
        assert all(subjects[k.split("/")[0]] == "val" for k in proto["val"])
        assert all(subjects[k.split("/")[0]] == "train" for k in proto["train"])
        for split in ("train", "val"):
            data = np.load(d / "splits" / f"{p}_{split}.npy", allow_pickle=True).item()
            assert set(data["data_dict"]) == set(proto[split])
            assert len(data["imgnames"]) > 0


def test_world_meta_record(world):
    m = world.meta
    for key in (
        "schema_version",
        "generator",
        "preset",
        "seed",
        "cropped_size",
        "ego_image_scale",
        "ego_image_size",
        "mask_dir",
        "mask_ids",
        "subjects",
        "sequences",
        "timings",
    ):
        assert key in m, key
    assert m["preset"] == "tiny" and m["mask_dir"] == "masks" and m["mask_ids"] == MASK_IDS
    assert m["ego_image_size"] == list(EGO_IMAGE_SIZE)
    tones = [tuple(s["skin_rgb"]) for s in m["subjects"]]
    assert len(set(tones)) == len(tones)  # per-subject skin tone


def test_reader_opens_every_sequence(world):
    from hogsa_loader.assets.arctic import ArcticRoot

    root = ArcticRoot(world.root)
    assert root.world_meta().cropped_size == world.meta["cropped_size"]
    for sid, seq in world.seqs:
        s = root.sequence(sid, seq)
        assert all(p is not None for v in range(9) for p in s.image_paths[v])
        assert all(p is not None for v in range(9) for p in s.mask_paths[v])


def test_every_arctic_object_template_is_in_the_world(world):
    """ARCTIC's ObjectTensors opens all 11 objects; sequences still use the preset's."""
    from hogsa_loader.assets.arctic import ArcticRoot
    from hogsa_loader.assets.objects.template import OBJECT_NAMES

    templates = ArcticRoot(world.root).object_templates()
    assert tuple(templates) == OBJECT_NAMES
    meta = json.loads((world.data / "meta" / "object_meta.json").read_text())
    shapes = set()
    for name, t in templates.items():
        assert t.has_texture and 0.1 <= meta[name]["diameter"] <= 0.45, name
        for part in (0, 1):
            v, f = t.part_mesh(part)
            assert len(v) > 300 and len(f) > 300, (name, part)
        # ARCTIC labels its 600 sub-points by the nearest mesh vertex: 300 top, then 300 bottom
        sub = np.concatenate([t.sub_top, t.sub_bottom])
        labels = t.parts[cKDTree(t.verts).query(sub)[1]]
        assert (labels[:300] == 0).all() and (labels[300:] == 1).all(), name
        shapes.add((len(t.verts), tuple(np.round((t.verts.max(0) - t.verts.min(0)) * 1000))))
    assert len(shapes) == len(OBJECT_NAMES)  # eleven different shapes, no copies
    assert {s["object"] for s in world.meta["sequences"]} == {"box"}
    assert world.meta["object_templates"] == list(OBJECT_NAMES)


def test_decimation_files_have_arctic_structure(world):
    """mano_decimator_195.npy: dense (195, V) selections ARCTIC's MANODecimator multiplies
    with the MANO vertices; downsamplers.npy: per object a sparse (600, V) map onto the
    template's sub-sampled points. Read as ARCTIC does and through the restricted reader."""
    from scipy.sparse import csr_matrix

    from hogsa_loader.assets.arctic import ArcticRoot, read_npy
    from hogsa_loader.assets.objects.template import OBJECT_NAMES

    meta = world.data / "meta"
    dec = np.load(meta / "mano_decimator_195.npy", allow_pickle=True).item()
    assert sorted(k for k in dec if "D" in k) == ["D_left", "D_right"]
    for side in ("right", "left"):
        D, ids = dec[f"D_{side}"], dec[f"vertex_ids_{side}"]
        V = world.layers[side].num_verts
        assert D.shape == (195, V) and D.dtype == np.float32 and len(set(ids.tolist())) == 195
        assert ids.min() >= 0 and ids.max() < V
        np.testing.assert_array_equal(D.sum(1), 1.0)
        assert (np.count_nonzero(D, axis=1) == 1).all() and (D[np.arange(195), ids] == 1).all()
        verts = world.layers[side](betas=torch.zeros(2, 10, dtype=torch.float64)).vertices.float()
        sub = torch.bmm(torch.FloatTensor(D)[None].repeat(2, 1, 1), verts)  # ARCTIC's downsample
        torch.testing.assert_close(sub, verts[:, ids])
    samplers = np.load(meta / "downsamplers.npy", allow_pickle=True).item()
    assert tuple(samplers) == OBJECT_NAMES
    restricted = read_npy(meta / "downsamplers.npy")
    for name, t in ArcticRoot(world.root).object_templates(load_texture=False).items():
        D = samplers[name]["D"]
        assert isinstance(D, csr_matrix) and D.shape == (600, len(t.verts))
        np.testing.assert_array_equal(np.asarray(D.sum(1)).ravel(), 1.0)
        assert D.indices.min() >= 0 and D.indices.max() < len(t.verts)
        sub = np.concatenate([t.sub_top, t.sub_bottom]).astype(np.float64)
        np.testing.assert_allclose(D @ t.verts.astype(np.float64), sub, atol=1e-6)
        assert (restricted[name]["D"] != D).nnz == 0
        np.testing.assert_array_equal(restricted[name]["vertex_ids"], samplers[name]["vertex_ids"])


def test_body_stand_ins_are_nan_and_recorded(world):
    """No body: SMPL-X fields are NaN with ARCTIC's shapes, listed in hogsa_world.json with
    the files left out (no fabricated SMPL-X model)."""
    from hogsa_loader.assets.arctic import ArcticRoot, read_npy
    from hogsa_world.stand_ins import SMPLX_PARAMS

    rec = world.meta
    paths = {e["path"]: e for e in rec["stand_ins"]}
    assert set(paths) == {
        "arctic_data/data/raw_seqs/<sid>/<seq>.smplx.npy",
        "arctic_data/data/splits/<protocol>_<split>.npy",
    }
    assert all(e["reason"] and e["content"] and e["keys"] for e in rec["stand_ins"])
    assert "cam_coord/joints.smplx" in paths["arctic_data/data/splits/<protocol>_<split>.npy"]["keys"]
    missing = {e["path"] for e in rec["not_provided"]}
    assert missing == {
        "body_models/smplx/SMPLX_{MALE,FEMALE,NEUTRAL}.npz",
        "arctic_data/data/meta/subject_vtemplates/<sid>.obj",
    }
    assert (
        not (world.root / "body_models" / "smplx").exists()
        and not (world.data / "meta" / "subject_vtemplates").exists()
    )
    F = rec["num_frames"]
    for sid, seq in world.seqs:
        raw = read_npy(world.data / "raw_seqs" / sid / f"{seq}.smplx.npy")
        assert {k: v.shape for k, v in raw.items()} == {k: (F, w) for k, w in SMPLX_PARAMS.items()}
        assert all(v.dtype == np.float32 and np.isnan(v).all() for v in raw.values())
    root = ArcticRoot(world.root)
    for name in ("p1_train", "p1_val", "p2_train", "p2_val"):
        for seq in root.load_split(name)["data_dict"].values():  # the reader accepts the NaN keys
            assert seq["cam_coord"]["joints.smplx"].shape == (F, 10, 127, 3)
            assert seq["2d"]["joints.smplx"].shape == (F, 10, 127, 2)
            smplx = [seq["cam_coord"]["joints.smplx"], seq["2d"]["joints.smplx"]]
            smplx += [seq["params"][f"smplx_{k}"] for k in SMPLX_PARAMS]
            assert all(np.isnan(a).all() for a in smplx)
            assert np.isfinite(seq["cam_coord"]["joints.right"]).all()


# --------------------------------------------------------------------------------------
# Images and masks
# --------------------------------------------------------------------------------------
def test_images_and_masks_exist_with_recorded_sizes(world):
    F = world.meta["num_frames"]
    size = world.meta["cropped_size"]
    s = world.meta["ego_image_scale"]
    ego_wh = (round(EGO_IMAGE_SIZE[0] * s), round(EGO_IMAGE_SIZE[1] * s))
    allowed = set(MASK_IDS.values())
    for sid, seq in world.seqs:
        off = world.frame_ids(sid)
        expected = {f"{i + off:05d}" for i in range(F)}
        for view in range(9):
            imgs = world.data / "cropped_images" / sid / seq / str(view)
            masks = world.data / "masks" / sid / seq / str(view)
            assert {p.stem for p in imgs.glob("*.jpg")} == expected, (sid, seq, view)
            assert {p.stem for p in masks.glob("*.png")} == expected, (sid, seq, view)
            w, h = ego_wh if view == 0 else (size, size)
            for name in sorted(expected)[:: max(1, F // 8)]:
                img = cv2.imread(str(imgs / f"{name}.jpg"))
                mask = cv2.imread(str(masks / f"{name}.png"), cv2.IMREAD_UNCHANGED)
                assert img.shape == (h, w, 3) and mask.shape == (h, w) and mask.dtype == np.uint8
                assert set(np.unique(mask)) <= allowed
                assert img.std() > 10  # a real picture, not a blank


def _joint_mask_stats(world: World) -> dict:
    """Projected joints / keypoints against the masks, over every frame and view.

    A joint is *visible* when it projects inside the image onto a pixel that is not the
    other hand or the object (those occlude it). The 16 MANO skeleton joints lie inside the
    hand, so they must hit the hand's mask exactly; the 5 fingertip joints are surface
    vertices at the very tip, i.e. on the silhouette, so for them (and for the all-joint
    figure) a 1-pixel tolerance (3x3 neighbourhood) absorbs the pixel quantisation.
    """
    keys = (
        "vis16",
        "in16",
        "vis21",
        "in21_strict",
        "in21_1px",
        "on_object",
        "frames_hand_visible",
        "frames_hand_in_mask",
        "kp_visible",
        "kp_in_mask",
    )
    stats = dict.fromkeys(keys, 0)
    kernel = np.ones((3, 3), np.uint8)
    for sid, seq in world.seqs:
        posed = world.posed(sid, seq)
        for view in range(9):
            uv = {side: world.project(sid, seq, view, posed[f"joints_{side}"]) for side in HAND_ID}
            kp = world.project(sid, seq, view, posed["kp"])
            for i in range(uv["right"].shape[0]):
                mask = world.mask(sid, seq, view, i)
                for side, hid in HAND_ID.items():
                    vals, inside = _lookup(mask, uv[side][i])
                    near, _ = _lookup(cv2.dilate((mask == hid).astype(np.uint8), kernel), uv[side][i])
                    other = HAND_ID["left" if side == "right" else "right"]
                    visible = inside & (vals != other) & ~np.isin(vals, OBJECT_IDS)
                    hit = visible & (vals == hid)
                    stats["vis16"] += int(visible[:16].sum())
                    stats["in16"] += int(hit[:16].sum())
                    stats["vis21"] += int(visible.sum())
                    stats["in21_strict"] += int(hit.sum())
                    stats["in21_1px"] += int((visible & (near == 1)).sum())
                    stats["on_object"] += int((inside & np.isin(vals, OBJECT_IDS)).sum())
                    if visible.sum() >= 5:
                        stats["frames_hand_visible"] += 1
                        stats["frames_hand_in_mask"] += int((mask == hid).any())
                vals, inside = _lookup(mask, kp[i])
                visible = inside & ~np.isin(vals, list(HAND_ID.values()))
                stats["kp_visible"] += int(visible.sum())
                stats["kp_in_mask"] += int((visible & np.isin(vals, OBJECT_IDS)).sum())
    return stats


@pytest.fixture(scope="module")
def joint_stats(world) -> dict:
    return _joint_mask_stats(world)


def test_projected_joints_land_in_their_hand_masks(joint_stats):
    s = joint_stats
    f16 = s["in16"] / s["vis16"]
    f21 = s["in21_1px"] / s["vis21"]
    print(
        f"\njoints in own hand mask: 16 skeleton joints {f16:.4f} (exact pixel, {s['vis16']} visible); "
        f"all 21 joints {f21:.4f} within 1 px, {s['in21_strict'] / s['vis21']:.4f} exact pixel "
        f"({s['vis21']} visible, {s['on_object']} on the object pixels, not counted)"
    )
    assert s["vis21"] > 10000
    assert f16 >= 0.99, f16
    assert f21 >= 0.99, f21


def test_masks_non_empty_where_hands_are_visible(joint_stats):
    s = joint_stats
    assert s["frames_hand_visible"] > 0
    assert s["frames_hand_in_mask"] == s["frames_hand_visible"]


def test_object_keypoints_land_in_object_mask(joint_stats):
    s = joint_stats
    frac = s["kp_in_mask"] / s["kp_visible"]
    print(f"\nobject keypoints in object mask: {frac:.4f} of {s['kp_visible']}")
    assert frac >= 0.9, frac


def test_ego_images_are_distorted_like_the_annotations(world):
    """View 0: joints projected WITH the lens distortion fit the masks better than without."""
    sid, seq = world.seqs[0]
    posed = world.posed(sid, seq)
    _, _, ego = world.raw(sid, seq)
    F = posed["joints_right"].shape[0]
    w2c = np.zeros((F, 4, 4))
    w2c[:, :3, :3] = ego["R_k_cam_np"]
    w2c[:, :3, 3] = ego["T_k_cam_np"][..., 0]
    w2c[:, 3, 3] = 1.0
    K = ego["intrinsics"].astype(np.float64)
    s = world.meta["ego_image_scale"]
    # object mesh vertices: their silhouette is large, so the distortion shift shows at its border
    mesh = posed["obj_mesh"]
    hits = {}
    for name, distort in (("distorted", True), ("pinhole", False)):
        cam = transform(w2c, mesh)
        if distort:
            cam = distort_points(cam, ego["dist8"].astype(np.float64))
        uv = project(cam, K) * s
        n_in = n = 0
        for i in range(F):
            vals, inside = _lookup(world.mask(sid, seq, 0, i), uv[i])
            n += int(inside.sum())
            n_in += int((inside & (vals > 0)).sum())
        hits[name] = n_in / n
    assert hits["distorted"] > hits["pinhole"], hits
    assert hits["distorted"] > 0.95, hits


# --------------------------------------------------------------------------------------
# Physics of the motion
# --------------------------------------------------------------------------------------
def _part_planes(template, part: int) -> tuple[np.ndarray, np.ndarray]:
    """Outward unit normals (P, 3) and offsets (P,) of the convex hull of a part's mesh.

    Each part is a convex rounded box; its triangulated mesh deviates from convexity by less
    than 0.1 mm (quads split along the concave diagonal on the rounded corners), so the
    hull is the mesh up to that: depths measured against it are upper bounds.
    """
    import trimesh

    keep = template.parts == part
    hull = trimesh.Trimesh(template.verts[keep].astype(np.float64), process=False).convex_hull
    mesh = trimesh.Trimesh(
        template.verts[keep].astype(np.float64),
        np.searchsorted(np.flatnonzero(keep), template.faces[keep[template.faces].all(1)]),
        process=False,
    )
    assert abs(hull.volume - mesh.volume) < 1e-3 * mesh.volume  # the part is convex
    n = np.asarray(hull.face_normals)
    d = np.einsum("ij,ij->i", n, hull.vertices[hull.faces[:, 0]])
    planes = np.unique(np.round(np.concatenate([n, d[:, None]], 1), 9), axis=0)
    return planes[:, :3], planes[:, 3]


def _surface_samples(template, part: int, per_edge: int = 4) -> np.ndarray:
    keep = template.parts == part
    faces = template.faces[keep[template.faces].all(1)]
    v = template.verts.astype(np.float64)
    ws = [(i / per_edge, j / per_edge) for i in range(per_edge + 1) for j in range(per_edge + 1 - i)]
    pts = [v[faces[:, 0]] * (1 - a - b) + v[faces[:, 1]] * a + v[faces[:, 2]] * b for a, b in ws]
    return np.concatenate(pts)


def _to_part_frame(points: np.ndarray, obj: np.ndarray, part: int) -> np.ndarray:
    """(F, N, 3) world points -> canonical frame of the part (top: articulation undone)."""
    R = Rotation.from_rotvec(obj[:, 1:4].astype(np.float64)).as_matrix()
    p = np.einsum("fij,fni->fnj", R, points - obj[:, None, 4:7].astype(np.float64) / 1000.0)
    if part == 0:
        Rz = Rotation.from_rotvec(-obj[:, :1].astype(np.float64) * np.array([0.0, 0.0, 1.0])).as_matrix()
        p = np.einsum("fij,fni->fnj", Rz, p)  # undo R_z(-θ): multiply by R_z(-θ)^T row-wise
    return p


@pytest.fixture(scope="module")
def contact_stats(world) -> dict:
    return _contact_stats(world)


def _contact_stats(world: World) -> dict:
    """Per sequence and hand: deepest penetration into the object and nearest surface distance, per frame."""
    out = {}
    for sid, seq in world.seqs:
        _, obj, _ = world.raw(sid, seq)
        posed = world.posed(sid, seq)
        t = world.template(seq.split("_")[0])
        res = {}
        for side in HAND_ID:
            verts = posed[f"verts_{side}"]
            depth = np.zeros(verts.shape[:2])
            dist = np.full(verts.shape[:2], np.inf)
            for part in (0, 1):
                n, d = _part_planes(t, part)
                p = _to_part_frame(verts, obj, part)
                part_verts = t.verts[t.parts == part]
                near = ((p >= part_verts.min(0) - 1e-6) & (p <= part_verts.max(0) + 1e-6)).all(-1)
                signed = p[near] @ n.T - d  # (M, P) > 0 outside a plane; points off the box are outside
                inside = (signed <= 0).all(-1)
                depth[near] = np.maximum(depth[near], np.where(inside, -signed.max(-1), 0.0))
                tree = cKDTree(_surface_samples(t, part))
                dd, _ = tree.query(p.reshape(-1, 3))
                dist = np.minimum(dist, dd.reshape(p.shape[:2]))
            res[side] = {"depth": depth.max(1), "dist": dist.min(1), "verts": verts}
        out[(sid, seq)] = (res, obj)
    return out


def test_hands_touch_without_deep_penetration(world, contact_stats):
    _check_contact(contact_stats)


def _check_contact(contact_stats: dict) -> None:
    lines = []
    for (sid, seq), (res, _) in contact_stats.items():
        for side, r in res.items():
            contact = r["dist"] <= 0.003
            lines.append(
                f"{sid}/{seq} {side}: max penetration {r['depth'].max() * 1000:.2f} mm, "
                f"contact in {contact.mean():.2f} of frames"
            )
            assert r["depth"].max() < 0.002, (sid, seq, side, r["depth"].max())
            assert contact.mean() >= 0.3, (sid, seq, side, contact.mean())
            # first and last frames: hands at rest, away from the object
            assert not contact[0] and not contact[-1]
    print("\n" + "\n".join(lines))


def test_hands_stay_attached_while_in_contact(world, contact_stats):
    """While a hand holds the object (its finger pose constant, in contact) it is rigid in
    the frame of the part it holds, and the object moves meanwhile."""
    for (sid, seq), (res, obj) in contact_stats.items():
        mano, _, _ = world.raw(sid, seq)
        for side, r in res.items():
            pose = mano[side]["pose"]
            touching = np.flatnonzero(r["dist"] <= 0.003)
            same = np.abs(pose - pose[touching[len(touching) // 2]]).max(1) < 1e-6  # the grasp pose
            hold = np.flatnonzero(same & (r["dist"] <= 0.003))
            assert len(hold) >= 10, (sid, seq, side, len(hold))
            assert np.all(np.diff(hold) == 1)  # one uninterrupted hold
            errs = []
            for part in (0, 1):
                p = _to_part_frame(r["verts"][hold], obj[hold], part)
                errs.append(np.abs(p - p[:1]).max())
            assert min(errs) < 2e-4, (sid, seq, side, errs)
            moved = np.linalg.norm(obj[hold[-1], 4:7] - obj[hold, 4:7], axis=1).max()  # mm
            turned = np.abs(obj[hold, 0] - obj[hold[0], 0]).max()
            assert moved > 20 or turned > 0.3, (sid, seq, side, moved, turned)


def test_use_sequences_articulate_smoothly(world):
    for sid, seq in world.seqs:
        _, obj, _ = world.raw(sid, seq)
        theta = obj[:, 0].astype(np.float64)
        if "_use_" in seq:
            assert abs(theta[0]) < 1e-6 and abs(theta[-1]) < 1e-6
            assert 0.2 * np.pi <= theta.max() <= 0.5 * np.pi + 1e-6
            assert np.abs(np.diff(theta)).max() < 0.35
        else:
            assert np.abs(theta).max() < 1e-6


def test_motion_is_smooth(world):
    worst = {"speed": 0.0, "accel": 0.0, "obj_speed": 0.0}
    for sid, seq in world.seqs:
        posed = world.posed(sid, seq)
        for side in HAND_ID:
            j = posed[f"joints_{side}"]
            worst["speed"] = max(worst["speed"], np.linalg.norm(np.diff(j, axis=0), axis=-1).max())
            worst["accel"] = max(worst["accel"], np.linalg.norm(np.diff(j, 2, axis=0), axis=-1).max())
        worst["obj_speed"] = max(worst["obj_speed"], np.linalg.norm(np.diff(posed["obj_mesh"], axis=0), axis=-1).max())
    print(
        f"\nmax joint speed {worst['speed'] * 100:.1f} cm/frame, max joint accel "
        f"{worst['accel'] * 100:.1f} cm/frame^2, max object vertex speed {worst['obj_speed'] * 100:.1f} cm/frame"
    )
    assert worst["speed"] < 0.08 and worst["accel"] < 0.06 and worst["obj_speed"] < 0.08, worst


# --------------------------------------------------------------------------------------
# Determinism and CLI
# --------------------------------------------------------------------------------------
def _hash_tree(root: Path) -> dict[str, str]:
    out = {}
    for p in sorted(root.rglob("*")):
        if not p.is_file():
            continue
        data = p.read_bytes()
        if p.name == "hogsa_world.json":  # identical except for the wall-clock timings
            rec = json.loads(data)
            rec.pop("timings")
            data = json.dumps(rec, sort_keys=True).encode()
        out[str(p.relative_to(root))] = hashlib.sha256(data).hexdigest()
    return out


def _micro_preset(grasp_iters: int = 60):
    """One subject, one ``box`` use sequence, 48-px crops, 52 frames (the fewest ARCTIC takes).
    Tests of files rather than grasps (identity, resumption, added subjects) pass fewer grasp
    iterations: the grasp optimisation is a third of their cost."""
    tiny = PRESETS["tiny"]
    return dataclasses.replace(
        tiny,
        name="micro",
        num_frames=52,
        cropped_size=48,
        ego_image_scale=0.03,
        grasp_iters=grasp_iters,
        subjects=(SubjectPlan("s01", "train", (SequencePlan("box", "use"),)),),
    )


def test_styled_spec_stays_within_its_bounds():
    spec = grasp_specs("box", "grab")["right"]
    rng0, rng1 = np.random.default_rng(1), np.random.default_rng(1)
    assert styled_spec(spec, 0.0, rng0) == spec
    for _ in range(20):
        s = styled_spec(spec, 1.0, rng1)
        p0, p1 = np.asarray(spec.point), np.asarray(s.point)
        assert p1[2] == p0[2] == 1.0  # stays on its face
        assert 0 < np.abs(p1 - p0).max() <= 0.35 + 1e-12
        n0, n1 = (np.asarray(v) / np.linalg.norm(v) for v in (spec.normal, s.normal))
        assert np.degrees(np.arccos(np.clip(n0 @ n1, -1, 1))) <= 8.0 + 1e-9
        f0, f1 = np.asarray(spec.fingers, float), np.asarray(s.fingers)
        assert np.degrees(np.arccos(np.clip(f0 @ f1 / np.linalg.norm(f0) / np.linalg.norm(f1), -1, 1))) <= 25.0 + 1e-9
        assert 0.05 <= s.curl <= spec.curl + 0.2
    rng0.random(19 * 7)  # seven draws per call whatever the amount
    assert rng0.random() == rng1.random()


def test_grasp_style_gives_each_subject_its_own_grasp(tmp_path, monkeypatch):
    """With ``grasp_style`` two subjects hold the same object differently, still touching it
    without penetrating; the style has its own random stream, so the rest of the motion (the
    rest poses of the first frame) is the same as without it. (Grasps are annotations: the
    worlds are written without images.)"""
    import hogsa_world.writer as writer

    monkeypatch.setattr(writer, "_render_task", lambda shared, task, bar, renderers: task.name)
    seqs = (SequencePlan("box", "grab"),)
    base = dataclasses.replace(
        _micro_preset(), subjects=(SubjectPlan("s01", "train", seqs), SubjectPlan("s02", "train", seqs))
    )
    spread, first = {}, {}
    for style in (0.0, 1.0):
        root = tmp_path / f"style{style}"
        preset = dataclasses.replace(base, grasp_style=style)
        generate_world(root, preset, seed=3, progress=False, process_splits=False, preview=False, workers=1)
        w = World(root)
        assert w.meta["grasp_style"] == style
        mid = preset.num_frames // 2  # both hands hold the box
        wrist = {}
        for sid in ("s01", "s02"):
            _, obj, _ = w.raw(sid, "box_grab_01")
            R = Rotation.from_rotvec(obj[mid, 1:4].astype(np.float64)).as_matrix()
            joints = w.posed(sid, "box_grab_01")
            # wrists in the box's frame: where on the box each hand holds it
            wrist[sid] = np.stack([(joints[f"joints_{s}"][mid, 0] - obj[mid, 4:7] / 1000.0) @ R for s in HAND_ID])
        spread[style] = np.linalg.norm(wrist["s01"] - wrist["s02"], axis=-1).min()
        a = w.raw("s01", "box_grab_01")[0]
        first[style] = np.concatenate([a[s]["pose"][0] for s in HAND_ID])
        if style:
            _check_contact(_contact_stats(w))
    # Measured: the nearer hand's wrists 11 mm apart without the style (hand shapes differ), 27 mm with it.
    assert spread[1.0] > 2 * spread[0.0], spread
    np.testing.assert_array_equal(first[0.0], first[1.0])


def test_same_seed_gives_byte_identical_world_and_seeds_differ(tmp_path):
    """Also with the sequences rendered in one process or side by side in two."""
    preset = dataclasses.replace(
        _micro_preset(grasp_iters=10),
        subjects=(SubjectPlan("s01", "train", (SequencePlan("box", "use"), SequencePlan("box", "grab"))),),
    )
    hashes = []
    for name, seed, workers in (("a", 7, 1), ("b", 7, 2), ("c", 8, None)):
        generate_world(tmp_path / name, preset, seed=seed, progress=False, workers=workers)
        hashes.append(_hash_tree(tmp_path / name))
    assert len([k for k in hashes[0] if "box_grab_01/" in k and k.endswith(".jpg")]) == 9 * preset.num_frames
    assert hashes[0] == hashes[1]
    assert set(hashes[0]) == set(hashes[2])
    differ = [k for k in hashes[0] if hashes[0][k] != hashes[2][k]]
    for must in (
        "arctic_data/data/raw_seqs/s01/box_use_01.mano.npy",
        "arctic_data/data/meta/misc.json",
        "arctic_data/data/cropped_images/s01/box_use_01/3/00020.jpg",
    ):
        assert must in differ, must


def test_a_world_with_more_subjects_keeps_the_first_worlds_files(tmp_path):
    """Every subject and sequence draws from its own random stream: a preset with a held-out
    test subject added renders the first preset's sequences byte for byte, and writes the
    test split, which the dataset reads."""
    base = _micro_preset(grasp_iters=10)
    more = dataclasses.replace(
        base, subjects=(*base.subjects, SubjectPlan("s03", "test", (SequencePlan("box", "grab"),)))
    )
    for name, preset in (("a", base), ("b", more)):
        generate_world(tmp_path / name, preset, seed=0, progress=False, preview=False)
    a, b = _hash_tree(tmp_path / "a"), _hash_tree(tmp_path / "b")
    files = [k for k in a if "/cropped_images/" in k or "/raw_seqs/" in k or k.endswith("p1_train.npy")]
    assert len(files) > 9 * base.num_frames and all(a[k] == b.get(k) for k in files)
    assert "arctic_data/data/splits/p1_test.npy" not in a
    test = ArcticDataset(tmp_path / "b", split="p1_test", augment=False, seed=0, config=ArcticConfig(img_res=32))
    assert {n.split("/")[-4] for n in test.imgnames} == {"s03"} and len(test) == 8 * (base.num_frames - 20)
    test[0]


def test_interrupted_world_resumes_only_unfinished_sequences(tmp_path, monkeypatch):
    """resume=True keeps the sequences an interrupted call finished and renders the rest; the
    finished ones are left as they were. A world recorded for another seed is rendered again.
    (The sequence renderer is replaced by a cheap writer of the same files in the same
    order; that a seed gives a byte-identical world is tested above.)"""
    import hogsa_world.writer as writer

    preset = dataclasses.replace(
        _micro_preset(grasp_iters=10),
        subjects=(SubjectPlan("s01", "train", (SequencePlan("box", "use"), SequencePlan("box", "grab"))),),
    )
    rendered: list[str] = []

    def fake_render(data, preset, job, *args, frames=None):
        rendered.append(job.plan.name)
        sid, name = job.subject.sid, job.plan.name
        for i in range(preset.num_frames if frames is None else frames):
            stem = f"{i + job.subject.ioi_offset:05d}"
            for v in range(9):
                img = np.full((4, 4, 3), (i * 9 + v + 7 * len(name)) % 256, np.uint8)
                for folder, ext, pix in (("cropped_images", "jpg", img), (writer.MASK_DIR, "png", img[..., 0])):
                    path = data / folder / sid / name / str(v) / f"{stem}.{ext}"
                    path.parent.mkdir(parents=True, exist_ok=True)
                    cv2.imwrite(str(path), pix)

    def interrupted(data, preset, job, *args):
        if rendered:  # the first sequence finishes; the second stops half-way
            fake_render(data, preset, job, frames=preset.num_frames // 2)
            raise KeyboardInterrupt
        fake_render(data, preset, job)

    kw = dict(seed=7, progress=False, preview=False, process_splits=False, workers=1)
    out = tmp_path / "w"
    monkeypatch.setattr(writer, "_render_sequence", interrupted)
    with pytest.raises(KeyboardInterrupt):
        generate_world(out, preset, **kw)
    assert (out / writer.PARTIAL_RECORD).is_file()
    first = {k: v for k, v in _hash_tree(out).items() if "box_use_01/" in k}
    monkeypatch.setattr(writer, "_render_sequence", fake_render)
    rendered.clear()
    generate_world(out, preset, resume=True, **kw)
    assert rendered == ["box_grab_01"]
    assert not (out / writer.PARTIAL_RECORD).exists()
    after = _hash_tree(out)
    assert {k: after[k] for k in first} == first  # the finished sequence was kept as it was
    grab = [k for k in after if "box_grab_01/" in k and k.startswith("arctic_data/data/cropped_images")]
    assert len(grab) == 9 * preset.num_frames

    (out / writer.PARTIAL_RECORD).write_text(json.dumps(writer._partial_fingerprint(preset, 8)))
    rendered.clear()  # recorded for another seed: not resumed
    generate_world(out, preset, resume=True, **kw)
    assert rendered == ["box_use_01", "box_grab_01"]

    def broken(data, preset, job, *args):
        raise RuntimeError(f"cannot render {job.plan.name}")

    monkeypatch.setattr(writer, "_render_sequence", broken)  # in forked render processes too
    with pytest.raises(RuntimeError, match="cannot render box_"):
        generate_world(out, preset, **{**kw, "workers": 2})


def test_cli_rejects_unknown_preset(tmp_path, capsys):
    from hogsa_loader.cli.main import main

    assert main(["world", "--out", str(tmp_path), "--preset", "huge"]) == 2
    assert "unknown world preset" in capsys.readouterr().err


def test_annotation_noise_world(tiny_world, tmp_path):
    """The noisy copy keeps images/cameras/object poses, perturbs only the hands, and its
    fitting_err is the realised vertex error."""
    import torch

    from hogsa_loader.assets.arctic import ArcticRoot, read_npy
    from hogsa_loader.cli.main import main
    from hogsa_loader.errors import AssetError
    from hogsa_world.annotation_noise import AnnotationNoise, add_annotation_noise, perturb_hand

    # the noise model: requested std per component (offset + smoothed jitter), zero noise = identity
    rng = np.random.default_rng(0)
    F = 4000
    p = {
        "rot": np.zeros((F, 3), np.float32),
        "pose": np.zeros((F, 45), np.float32),
        "trans": np.zeros((F, 3), np.float32),
        "shape": np.zeros(10, np.float32),
    }
    stds = []
    for seed in range(40):  # the per-sequence offset needs many sequences to show its variance
        q = perturb_hand(p, AnnotationNoise(trans_mm=2.0, pose_rad=0.04, smooth=5), np.random.default_rng(seed))
        stds.append((q["trans"].std(0) ** 2 + q["trans"].mean(0) ** 2, q["pose"].std(0) ** 2 + q["pose"].mean(0) ** 2))
    assert np.sqrt(np.mean([s[0] for s in stds])) == pytest.approx(0.002, rel=0.15)
    assert np.sqrt(np.mean([s[1] for s in stds])) == pytest.approx(0.04, rel=0.15)
    q0 = perturb_hand(p, AnnotationNoise(0.0, 0.0, 0.0), rng)
    assert all(np.array_equal(q0[k], p[k]) for k in p)

    out = tmp_path / "noisy"
    assert main(["world-noise", "--src", str(tiny_world), "--out", str(out), "--quiet"]) == 0
    src_d, dst_d = tiny_world / "arctic_data" / "data", out / "arctic_data" / "data"
    assert (dst_d / "cropped_images").resolve() == (src_d / "cropped_images").resolve()
    assert not (dst_d / "masks").exists()
    summary = json.loads((out / "annotation_noise.json").read_text())
    assert summary["splits"].startswith("rebuilt from the noisy labels")
    layers = ArcticRoot(tiny_world).mano_layers(dtype=torch.float64)

    def verts(side, p):  # MANO forward of one hand's .mano.npy entry, (F, V, 3)
        f64 = torch.float64
        return layers[side](
            global_orient=torch.as_tensor(p["rot"], dtype=f64),
            hand_pose=torch.as_tensor(p["pose"], dtype=f64),
            betas=torch.as_tensor(np.repeat(p["shape"][None], len(p["rot"]), 0), dtype=f64),
            transl=torch.as_tensor(p["trans"], dtype=f64),
        ).vertices

    n_seq = 0
    for f in sorted((src_d / "raw_seqs").rglob("*.mano.npy")):
        rel = f.relative_to(src_d)
        clean, noisy = read_npy(f), read_npy(dst_d / rel)
        obj = rel.as_posix().replace(".mano.npy", ".object.npy")
        assert np.array_equal(read_npy(src_d / obj), read_npy(dst_d / obj))  # object poses exact
        for side in ("right", "left"):
            c, n = clean[side], noisy[side]
            assert np.array_equal(c["shape"], n["shape"]) and not np.allclose(c["trans"], n["trans"])
            err = (verts(side, n) - verts(side, c)).norm(dim=-1).mean(-1).numpy()
            np.testing.assert_allclose(n["fitting_err"], err, rtol=1e-5, atol=1e-7)
            assert 1.0 < err.mean() * 1000 < 15.0  # millimetres, as ARCTIC's fitting error
            n_seq += 1
    # the processed splits are rebuilt from the noisy labels (the source's hold the exact ones)
    assert (
        not (dst_d / "splits").is_symlink() and (dst_d / "splits_json").resolve() == (src_d / "splits_json").resolve()
    )
    src_root, dst_root = ArcticRoot(tiny_world), ArcticRoot(out)
    for name in ("p1_train", "p2_val"):
        got, ref = dst_root.load_split(name), src_root.load_split(name)
        assert got["imgnames"] == ref["imgnames"] and got["data_dict"].keys() == ref["data_dict"].keys()
        for key, seq in got["data_dict"].items():
            sid, sname = key.split("/")
            mano = read_npy(dst_d / "raw_seqs" / sid / f"{sname}.mano.npy")
            for side, s in (("right", "r"), ("left", "l")):
                np.testing.assert_array_equal(seq["params"][f"pose_{s}"], mano[side]["pose"])
                np.testing.assert_array_equal(seq["params"][f"trans_{s}"], mano[side]["trans"])
                np.testing.assert_array_equal(seq["params"][f"fitting_err_{s}"], mano[side]["fitting_err"])
                assert not np.allclose(ref["data_dict"][key]["params"][f"trans_{s}"], seq["params"][f"trans_{s}"])
            np.testing.assert_array_equal(seq["params"]["obj_trans"], ref["data_dict"][key]["params"]["obj_trans"])
            assert np.isnan(seq["cam_coord"]["joints.smplx"]).all()  # the body stand-ins are rebuilt too
            assert not np.allclose(seq["cam_coord"]["joints.right"], ref["data_dict"][key]["cam_coord"]["joints.right"])
    skipped = tmp_path / "noisy_no_splits"
    assert main(["world-noise", "--src", str(tiny_world), "--out", str(skipped), "--quiet", "--no-splits"]) == 0
    assert not (skipped / "arctic_data" / "data" / "splits").exists()
    assert json.loads((skipped / "annotation_noise.json").read_text())["splits"] == "not written"
    assert n_seq >= 2 and summary["overall_mean_vertex_error_mm"] > 1.0
    ArcticRoot(out)  # opens as an ARCTIC root
    with pytest.raises(AssetError, match="already exists"):
        add_annotation_noise(tiny_world, out)
    # on a real ARCTIC root, the derived folders holding the exact labels are not linked
    real = tmp_path / "real"
    (real / "arctic_data" / "data").mkdir(parents=True)
    for item in tiny_world.iterdir():
        if item.name != "arctic_data":
            (real / item.name).symlink_to(item.resolve())
    for item in src_d.iterdir():
        (real / "arctic_data" / "data" / item.name).symlink_to(item.resolve())
    for name in ("processed_seqs", "feat"):
        (real / "arctic_data" / "data" / name).mkdir()
    add_annotation_noise(real, tmp_path / "real_noisy", process_splits=False)
    kept = {p.name for p in (tmp_path / "real_noisy" / "arctic_data" / "data").iterdir()}
    assert "cropped_images" in kept and not kept & {"processed_seqs", "feat", "masks"}


def test_a_second_writer_of_a_world_is_refused(tmp_path):
    """Two ``hogsa world`` runs into one folder: the second is refused at once, naming the
    holder, before it writes anything."""
    from hogsa_loader.io.locks import FolderBusyError, writer_lock

    with writer_lock(tmp_path, ".hogsa_world.lock", what="hogsa world"):
        with pytest.raises(FolderBusyError, match=r"hogsa world is being written by process \d+"):
            generate_world(tmp_path, _micro_preset(), progress=False, preview=False)
    assert [p.name for p in tmp_path.iterdir()] == [".hogsa_world.lock"]
