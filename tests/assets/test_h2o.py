"""Tests of the H2O reader/writer (hogsa_loader.assets.h2o, h2o_io).

A tiny H2O tree (4 frames with a gap, static cam0/cam1 + moving ego cam4) is written with
known MANO labels (flat_hand_mean=True, camera frames), object poses and cameras, then read
back. Checks are made on posed MANO vertices/joints with independent float64 layers, so a
wrong mean convention, frame change, side swap or slicing shows up as geometry error.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import torch
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from scipy.spatial.transform import Rotation

from hogsa_loader.assets.h2o import H2ORoot, change_mano_frame, h2o_mano_from_tracks, mano_root_joint, read_h2o_rgb
from hogsa_loader.assets.h2o_io import (
    H2O_COUNTS,
    H2O_IMAGE_SIZE,
    H2OIntrinsics,
    H2OManoHand,
    H2OManoLabels,
    format_h2o_line,
    parse_h2o_action_label,
    parse_h2o_cam_intrinsics,
    parse_h2o_cam_pose,
    parse_h2o_hand_pose,
    parse_h2o_hand_pose_mano,
    parse_h2o_obj_pose,
    parse_h2o_obj_pose_rt_strict,
    parse_h2o_verb_label,
)
from hogsa_loader.assets.hands.mano import MANOLayer
from hogsa_loader.errors import AssetError
from hogsa_world.h2o_writer import H2OCameraRecord, write_h2o_sequence

F64 = torch.float64
FRAMES = [3, 4, 5, 7]  # a gap, as in real sequences with unannotated ranges
F = len(FRAMES)
SUBJ, SCENE, SEQ = "subject1", "k2", 0
LOTION = 3
INTR = H2OIntrinsics(fx=636.6, fy=636.2, cx=635.3, cy=366.9, width=1280, height=720)


# --------------------------------------------------------------------------------------
# Helpers
# --------------------------------------------------------------------------------------
def rigid(seed: int, dist: float = 0.0) -> np.ndarray:
    """A random rigid 4x4 (rotation from scipy, translation ~N(0, 0.5) + dist along z)."""
    rng = np.random.default_rng(seed)
    T = np.eye(4)
    T[:3, :3] = Rotation.random(random_state=seed).as_matrix()
    T[:3, 3] = rng.normal(0.0, 0.5, 3) + np.array([0.0, 0.0, dist])
    return T


def move(M: np.ndarray, pts: np.ndarray) -> np.ndarray:
    """(F, 4, 4) or (4, 4) applied to (F, N, 3)."""
    M = np.broadcast_to(M, (pts.shape[0], 4, 4))
    return np.einsum("fij,fnj->fni", M[:, :3, :3], pts) + M[:, None, :3, 3]


def random_hand(seed: int, valid: np.ndarray, betas_per_frame: bool = False) -> H2OManoHand:
    rng = np.random.default_rng(seed)
    betas = np.repeat(rng.normal(0, 1.0, (1, 10)), F, axis=0)
    if betas_per_frame:
        betas = betas + rng.normal(0, 0.3, (F, 10))
    pose = np.concatenate([rng.normal(0, 1.0, (F, 3)), rng.normal(0, 0.4, (F, 45))], axis=1)
    trans = rng.normal(0, 0.1, (F, 3)) + np.array([0, 0, 0.5])
    hand = H2OManoHand(valid=valid.copy(), trans=trans, pose=pose, betas=betas)
    for a in (hand.trans, hand.pose, hand.betas):
        a[~valid] = 0.0  # what the dataset stores for missing hands
    return hand


@pytest.fixture(scope="module")
def models(hand_pair):
    right, left = hand_pair
    return {"right": right, "left": left}


@pytest.fixture(scope="module")
def layers(models):
    """Float64 layers: flat=True poses on-disk labels, flat=False poses read tracks."""
    return {
        (side, flat): MANOLayer(models[side], flat_hand_mean=flat, dtype=F64)
        for side in ("left", "right")
        for flat in (True, False)
    }


def pose_verts(layer: MANOLayer, rot, pose45, betas, trans) -> tuple[np.ndarray, np.ndarray]:
    """(vertices (F, V, 3), joints (F, 21, 3)) as numpy."""
    t = lambda a: torch.tensor(np.array(a, dtype=np.float64))  # noqa: E731
    n = np.asarray(rot).shape[0]
    out = layer(t(rot), t(pose45), t(np.broadcast_to(betas, (n, 10))), t(trans))
    return out.vertices.numpy(), out.joints.numpy()


def disk_verts(layers, side: str, hand: H2OManoHand):
    """Pose stored labels the way H2O means them (flat_hand_mean=True)."""
    return pose_verts(layers[(side, True)], hand.pose[:, :3], hand.pose[:, 3:], hand.betas, hand.trans)


def read_verts(layers, side: str, track) -> tuple[np.ndarray, np.ndarray]:
    """Pose read tracks the way SequenceData means them (flat_hand_mean=False)."""
    return pose_verts(layers[(side, False)], track.rot, track.pose, track.betas, track.trans)


class Scene:
    """Ground truth of the tiny tree."""

    def __init__(self, models, betas_per_frame: bool = False) -> None:
        self.c2w = {
            0: rigid(10, 0.0),
            1: rigid(11, 0.0),
            4: np.stack([rigid(20 + i, 0.0) for i in range(F)]),  # moving head camera
        }
        left_valid = np.array([True, False, True, True])
        right_valid = np.array([True, True, True, False])
        self.mano4 = H2OManoLabels(
            left=random_hand(1, left_valid, betas_per_frame), right=random_hand(2, right_valid, betas_per_frame)
        )
        self.obj_class = np.array([LOTION, LOTION, 0, LOTION])
        self.obj4 = np.stack([rigid(30 + i, 0.6) for i in range(F)])
        self.obj4[2] = 0.0  # class 0 frame: zero matrix
        # cam0 labels: the same hands/object expressed in cam0 (flat params moved by the
        # root-joint formula; checked independently on vertices in test_label_camera_choice).
        cam4_to_cam0 = np.linalg.inv(self.c2w[0]) @ self.c2w[4]
        hands0 = {}
        for side in ("left", "right"):
            h = self.mano4.hand(side)
            rot, trans = change_mano_frame(h.pose[:, :3], h.trans, h.betas, cam4_to_cam0, models[side])
            pose = np.concatenate([rot, h.pose[:, 3:]], axis=1)
            pose[~h.valid] = 0.0
            trans[~h.valid] = 0.0
            hands0[side] = H2OManoHand(valid=h.valid.copy(), trans=trans, pose=pose, betas=h.betas.copy())
        self.mano0 = H2OManoLabels(left=hands0["left"], right=hands0["right"])
        self.obj0 = cam4_to_cam0 @ self.obj4
        self.obj0[2] = 0.0

    def records(self, ego_rgb: bool = True) -> dict[int, H2OCameraRecord]:
        rng = np.random.default_rng(5)
        return {
            0: H2OCameraRecord(
                cam_pose=self.c2w[0],
                intrinsics=INTR,
                mano=self.mano0,
                obj_class=self.obj_class,
                obj_transform=self.obj0,
            ),
            1: H2OCameraRecord(cam_pose=np.repeat(self.c2w[1][None], F, axis=0), intrinsics=INTR),
            4: H2OCameraRecord(
                cam_pose=self.c2w[4],
                intrinsics=INTR,
                mano=self.mano4,
                obj_class=self.obj_class,
                obj_transform=self.obj4,
                hand_pose=np.c_[np.ones(F), rng.normal(0, 0.2, (F, 63)), np.ones(F), rng.normal(0, 0.2, (F, 63))],
                obj_pose=np.c_[self.obj_class, rng.normal(0, 0.2, (F, 63))],
                action_label=np.array([0, 5, 5, 36]),
                verb_label=np.array([0, 1, 1, 11]),
            ),
        }


@pytest.fixture(scope="module")
def scene(models):
    return Scene(models)


@pytest.fixture(scope="module")
def tree(tmp_path_factory, scene) -> Path:
    root = tmp_path_factory.mktemp("h2o")
    recs = scene.records()
    write_h2o_sequence(root, SUBJ, SCENE, SEQ, FRAMES, recs, placeholder_rgb=True)
    # a second, label-less sequence and junk that listing must ignore
    write_h2o_sequence(root, "subject2", "h1", 1, FRAMES, {4: H2OCameraRecord(cam_pose=scene.c2w[4], intrinsics=INTR)})
    (root / SUBJ / SCENE / str(SEQ) / "cam4" / "hand_pose_mano" / ".DS_Store").write_text("x")
    (root / SUBJ / SCENE / str(SEQ) / "cam4" / "hand_pose_mano" / "notes.txt").write_text("x")
    (root / "README.txt").write_text("not a subject")
    return root


@pytest.fixture(scope="module")
def seq_world(tree, models):
    return H2ORoot(tree).sequence(SUBJ, SCENE, SEQ, mano_layers=models)


# --------------------------------------------------------------------------------------
# Parsers
# --------------------------------------------------------------------------------------
def test_format_parse_roundtrip_every_format():
    T = rigid(1)
    assert np.array_equal(parse_h2o_cam_pose(format_h2o_line(T.ravel())), T)
    cls, M = parse_h2o_obj_pose_rt_strict(format_h2o_line([4, *T.ravel()]) + "\n")
    assert cls == 4 and np.array_equal(M, T)
    intr = parse_h2o_cam_intrinsics("636.6 636.2 635.3 366.9 1280 720\n")
    assert (intr.width, intr.height) == H2O_IMAGE_SIZE and isinstance(intr.width, int)
    np.testing.assert_array_equal(intr.K, [[636.6, 0, 635.3], [0, 636.2, 366.9], [0, 0, 1]])
    joints = np.random.default_rng(0).normal(size=(2, 21, 3))
    line = format_h2o_line(np.r_[0, joints[0].ravel(), 1, joints[1].ravel()])
    hp = parse_h2o_hand_pose(line)
    assert hp.valid.tolist() == [False, True] and np.array_equal(hp.joints, joints)
    c, box = parse_h2o_obj_pose(format_h2o_line(np.r_[8, joints[0].ravel()]))
    assert c == 8 and np.array_equal(box, joints[0])
    assert parse_h2o_action_label("36\n") == 36 and parse_h2o_verb_label("11") == 11
    # fixed-decimal files (the real ones) parse too
    assert np.allclose(parse_h2o_cam_pose(format_h2o_line(T.ravel(), precision=6)), T, atol=5e-7)
    assert format_h2o_line([1.0, 0.5], precision=6) == "1.000000 0.500000"
    assert H2O_COUNTS["hand_pose_mano"] == 124


def test_mano_line_is_left_first_with_62_per_hand():
    """Built with literal offsets, independent of the module's slice table."""
    rng = np.random.default_rng(3)
    L = dict(trans=rng.normal(size=3), pose=rng.normal(size=48), betas=rng.normal(size=10))
    R = dict(trans=rng.normal(size=3), pose=rng.normal(size=48), betas=rng.normal(size=10))
    line = np.concatenate([[0.0], L["trans"], L["pose"], L["betas"], [1.0], R["trans"], R["pose"], R["betas"]])
    assert line.shape == (124,) and line[62] == 1.0
    lab = parse_h2o_hand_pose_mano(format_h2o_line(line))
    assert lab.left.valid.tolist() == [False] and lab.right.valid.tolist() == [True]
    for side, ref in (("left", L), ("right", R)):
        h = lab.hand(side)
        for key in ("trans", "pose", "betas"):
            np.testing.assert_array_equal(getattr(h, key)[0], ref[key])
    # the README's 59-number split would read the right hand's flag inside left data:
    assert not np.array_equal(line[59:62], lab.right.trans[0])
    np.testing.assert_array_equal(lab.to_array()[0], line)
    # a 2 x 59 = 118-number line (what the README's count would give) is refused
    with pytest.raises(AssetError, match="124"):
        parse_h2o_hand_pose_mano(format_h2o_line(np.r_[line[:59], line[62:121]]))


def test_huge_rotation_entries_are_refused():
    R = np.array([[1e200, -1e200, 1e200], [1e200, 1e200, -1e200], [1.0, 1.0, 1.0]])
    T = np.eye(4)
    T[:3, :3] = R
    with pytest.raises(AssetError):
        parse_h2o_obj_pose_rt_strict(format_h2o_line([1, *T.ravel()]))
    with pytest.raises(AssetError):
        parse_h2o_cam_pose(format_h2o_line(T.ravel()))


GOOD = {
    "cam_pose": (parse_h2o_cam_pose, lambda: format_h2o_line(rigid(2).ravel())),
    "obj_pose_rt": (parse_h2o_obj_pose_rt_strict, lambda: format_h2o_line([2, *rigid(2).ravel()])),
    "hand_pose_mano": (parse_h2o_hand_pose_mano, lambda: format_h2o_line(np.r_[1, np.zeros(61), 1, np.zeros(61)])),
    "hand_pose": (parse_h2o_hand_pose, lambda: format_h2o_line(np.r_[1, np.zeros(63), 0, np.zeros(63)])),
    "obj_pose": (parse_h2o_obj_pose, lambda: format_h2o_line(np.r_[1, np.zeros(63)])),
    "cam_intrinsics": (parse_h2o_cam_intrinsics, lambda: "600 600 640 360 1280 720"),
    "action_label": (parse_h2o_action_label, lambda: "3"),
    "verb_label": (parse_h2o_verb_label, lambda: "3"),
}


@settings(max_examples=60, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(
    which=st.sampled_from(sorted(GOOD)),
    tokens=st.lists(
        st.one_of(
            st.floats(allow_nan=True, allow_infinity=True).map(repr),
            st.floats(min_value=-2, max_value=2).map(lambda x: f"{x:.6f}"),
            st.integers(-(10**30), 10**30).map(str),
            st.sampled_from(["nan", "-inf", "Infinity", "1_0", "0x1f", "1,2", "1e999", "--1", ".", "e5", "١"]),
            st.text(max_size=6),
        ),
        max_size=140,
    ),
)
def test_fuzz_random_tokens_only_asset_errors(which, tokens):
    parse, _ = GOOD[which]
    try:
        parse(" ".join(tokens), "fuzz.txt")
    except AssetError as exc:
        assert exc.path == "fuzz.txt"


@settings(max_examples=60, deadline=None)
@given(
    which=st.sampled_from(sorted(GOOD)), cut=st.integers(0, 2000), junk=st.binary(max_size=8), mode=st.integers(0, 3)
)
def test_fuzz_truncated_and_garbled_lines_only_asset_errors(which, cut, junk, mode):
    parse, good = GOOD[which]
    line = good()
    assert parse(line, "ok.txt") is not None  # the untouched line is valid
    if mode == 0:
        data = line[: cut % (len(line) + 1)]
    elif mode == 1:
        data = line.encode()[: cut % (len(line) + 1)] + junk  # bytes, maybe not UTF-8
    elif mode == 2:
        toks = line.split()
        data = " ".join(toks[: cut % (len(toks) + 1)] + toks)  # wrong count
    else:
        toks = line.split()
        toks[cut % len(toks)] = junk.decode("latin1") or "nan"
        data = " ".join(toks)
    try:
        parse(data, "fuzz.txt")
    except AssetError as exc:
        assert exc.path == "fuzz.txt"


# --------------------------------------------------------------------------------------
# Listing
# --------------------------------------------------------------------------------------
def test_listing(tree):
    r = H2ORoot(tree)
    assert r.subjects() == ["subject1", "subject2"]
    assert r.sequences() == [(SUBJ, SCENE, "0"), ("subject2", "h1", "1")]
    assert r.sequences("subject2") == [("subject2", "h1", "1")]
    assert r.cameras(SUBJ, SCENE, SEQ) == [0, 1, 4]
    assert r.frames(SUBJ, SCENE, SEQ) == FRAMES  # junk files ignored
    assert r.frames(SUBJ, SCENE, SEQ, cam=1, modality="rgb") == FRAMES
    assert r.frame_path(SUBJ, SCENE, SEQ, 4, "hand_pose_mano", 7).name == "000007.txt"
    assert np.array_equal(r.read_labels(SUBJ, SCENE, SEQ, 4, FRAMES), [0, 5, 5, 36])
    assert np.array_equal(r.read_labels(SUBJ, SCENE, SEQ, 4, FRAMES, kind="verb_label"), [0, 1, 1, 11])
    joints = r.read_hand_joints(SUBJ, SCENE, SEQ, 4, FRAMES)
    assert joints.valid.shape == (F, 2) and joints.valid.all() and joints.joints.shape == (F, 2, 21, 3)
    cls, box = r.read_obj_boxes(SUBJ, SCENE, SEQ, 4, FRAMES)
    assert cls.tolist() == [LOTION, LOTION, 0, LOTION] and box.shape == (F, 21, 3)
    with pytest.raises(AssetError, match="sequence folder not found"):
        r.sequence_dir(SUBJ, SCENE, 9)
    with pytest.raises(AssetError, match="not found"):
        H2ORoot(tree / "nope")


def test_listing_ego_and_pose_download_folders(tree, tmp_path):
    """The ``ego`` and ``pose`` downloads unpack to ``subjectN_ego`` / ``subjectN_pose``."""
    import shutil

    root = tmp_path / "h2o"
    shutil.copytree(tree / SUBJ, root / f"{SUBJ}_ego")
    shutil.copytree(tree / "subject2", root / "subject2_pose")
    (root / "subjects_notes").mkdir()
    r = H2ORoot(root)
    assert r.subjects() == [f"{SUBJ}_ego", "subject2_pose"]
    assert r.sequences() == [(f"{SUBJ}_ego", SCENE, "0"), ("subject2_pose", "h1", "1")]
    assert r.frames(f"{SUBJ}_ego", SCENE, SEQ) == FRAMES
    # the full download next to the ego one: listed once, the full one
    shutil.copytree(tree / SUBJ, root / SUBJ)
    assert H2ORoot(root).subjects() == [SUBJ, "subject2_pose"]


# --------------------------------------------------------------------------------------
# Hands
# --------------------------------------------------------------------------------------
def test_flat_mean_conversion_gives_same_vertices(tree, scene, models, layers):
    """Label camera frame (world="cam4"): only the mean convention changes."""
    seq = H2ORoot(tree).sequence(SUBJ, SCENE, SEQ, mano_layers=models, world="cam4")
    for side in ("left", "right"):
        disk, track = scene.mano4.hand(side), getattr(seq, side)
        v = disk.valid
        np.testing.assert_array_equal(track.valid, v)
        np.testing.assert_array_equal(track.betas, disk.betas[v][0])
        np.testing.assert_allclose(track.pose[v], disk.pose[v, 3:] - models[side].hands_mean, atol=1e-12)
        verts_disk, _ = disk_verts(layers, side, disk)
        verts_read, _ = read_verts(layers, side, track)
        np.testing.assert_allclose(verts_read[v], verts_disk[v], atol=1e-10)
        # and the finger pose really differs from the flat one (the test would see a no-op)
        assert np.abs(track.pose[v] - disk.pose[v, 3:]).max() > 1e-3
    assert np.abs(models["left"].hands_mean - models["right"].hands_mean).max() > 1e-3


def test_world_frame_and_every_camera(seq_world, scene, layers):
    """Joints of the read world-frame hands seen from camera K equal the stored cam4
    hands moved by cam4's pose into the world and then into camera K."""
    for side in ("left", "right"):
        disk, track = scene.mano4.hand(side), getattr(seq_world, side)
        v = disk.valid
        verts_disk, joints_disk = disk_verts(layers, side, disk)
        verts_read, joints_read = read_verts(layers, side, track)
        for K, cam in seq_world.cameras.items():
            c2w_K = np.broadcast_to(scene.c2w[K], (F, 4, 4))
            cam4_to_K = np.linalg.inv(c2w_K) @ scene.c2w[4]
            exp = move(cam4_to_K, joints_disk)
            got = move(cam.world2cam, joints_read)
            np.testing.assert_allclose(got[v], exp[v], atol=1e-9)
            np.testing.assert_allclose(cam.world2cam, np.linalg.inv(c2w_K), atol=1e-12)
        np.testing.assert_allclose(verts_read[v], move(scene.c2w[4], verts_disk)[v], atol=1e-9)
        # invalid frames are zeros
        assert not track.rot[~v].any() and not track.trans[~v].any() and not track.pose[~v].any()


def test_label_camera_choice(tree, models, layers, scene, seq_world):
    """Labels read from cam0 (another frame on disk) give the same world hands."""
    seq0 = H2ORoot(tree).sequence(SUBJ, SCENE, SEQ, mano_layers=models, label_cam=0)
    for side in ("left", "right"):
        v = scene.mano4.hand(side).valid
        # independent of change_mano_frame: cam0 labels posed and moved by cam0's pose
        verts0, _ = disk_verts(layers, side, scene.mano0.hand(side))
        verts4, _ = disk_verts(layers, side, scene.mano4.hand(side))
        np.testing.assert_allclose(move(scene.c2w[0], verts0)[v], move(scene.c2w[4], verts4)[v], atol=1e-9)
        a, _ = read_verts(layers, side, getattr(seq0, side))
        b, _ = read_verts(layers, side, getattr(seq_world, side))
        np.testing.assert_allclose(a[v], b[v], atol=1e-9)
    np.testing.assert_allclose(seq0.object.trans, seq_world.object.trans, atol=1e-12)
    only4 = H2ORoot(tree).sequence(SUBJ, SCENE, SEQ, mano_layers=models, label_cam=0, cameras=[4])
    assert list(only4.cameras) == [4] and list(only4.image_paths) == [4]
    np.testing.assert_array_equal(only4.cameras[4].world2cam, seq_world.cameras[4].world2cam)


def test_output_frame_of_a_static_camera(tree, models, layers, scene):
    seq = H2ORoot(tree).sequence(SUBJ, SCENE, SEQ, mano_layers=models, world="cam1")
    np.testing.assert_array_equal(seq.cameras[1].world2cam, np.repeat(np.eye(4)[None], F, axis=0))
    np.testing.assert_allclose(seq.cameras[4].world2cam, np.linalg.inv(scene.c2w[4]) @ scene.c2w[1], atol=1e-12)
    for side in ("left", "right"):
        v = scene.mano4.hand(side).valid
        _, j_disk = disk_verts(layers, side, scene.mano4.hand(side))
        _, j_read = read_verts(layers, side, getattr(seq, side))
        exp = move(np.linalg.inv(scene.c2w[1]) @ scene.c2w[4], j_disk)
        np.testing.assert_allclose(j_read[v], exp[v], atol=1e-9)
    with pytest.raises(ValueError, match="world"):
        H2ORoot(tree).sequence(SUBJ, SCENE, SEQ, mano_layers=models, world="camera1")


def test_left_right_not_swapped(seq_world, scene, layers):
    """Each read hand matches its own stored hand, and not the other one."""
    _, jl = read_verts(layers, "left", seq_world.left)
    _, jr = read_verts(layers, "right", seq_world.right)
    _, dl = disk_verts(layers, "left", scene.mano4.left)
    _, dr = disk_verts(layers, "right", scene.mano4.right)
    both = scene.mano4.left.valid & scene.mano4.right.valid
    dl, dr = move(scene.c2w[4], dl), move(scene.c2w[4], dr)
    np.testing.assert_allclose(jl[both], dl[both], atol=1e-9)
    assert np.abs(jl[both] - dr[both]).max() > 1e-2
    assert np.abs(jr[both] - dl[both]).max() > 1e-2


def test_validity_flags(seq_world):
    assert seq_world.left.valid.tolist() == [True, False, True, True]
    assert seq_world.right.valid.tolist() == [True, True, True, False]
    assert seq_world.object.valid.tolist() == [True, True, False, True]


def test_per_frame_betas_median_and_root_joint(tmp_path, models, layers):
    sc = Scene(models, betas_per_frame=True)
    write_h2o_sequence(tmp_path, SUBJ, SCENE, SEQ, FRAMES, sc.records())
    r = H2ORoot(tmp_path)
    seq = r.sequence(SUBJ, SCENE, SEQ, mano_layers=models)
    exact = r.read_mano(SUBJ, SCENE, SEQ, 4, FRAMES)
    for side in ("left", "right"):
        disk, track = sc.mano4.hand(side), getattr(seq, side)
        v = disk.valid
        np.testing.assert_array_equal(exact.hand(side).betas, disk.betas)  # per-frame access is exact
        np.testing.assert_allclose(track.betas, np.median(disk.betas[v], axis=0), atol=0)
        assert np.abs(disk.betas[v] - track.betas).max() > 1e-3  # betas really vary
        _, j_disk = disk_verts(layers, side, disk)
        _, j_read = read_verts(layers, side, track)
        np.testing.assert_allclose(j_read[v, 0], move(sc.c2w[4], j_disk)[v, 0], atol=1e-9)


def test_tracks_back_to_labels(seq_world, scene, models):
    """h2o_mano_from_tracks inverts the reading (constant betas: exact)."""
    w2c4 = seq_world.cameras[4].world2cam
    lab = h2o_mano_from_tracks(seq_world.left, seq_world.right, w2c4, models)
    for side in ("left", "right"):
        a, b = lab.hand(side), scene.mano4.hand(side)
        np.testing.assert_array_equal(a.valid, b.valid)
        np.testing.assert_allclose(a.trans, b.trans, atol=1e-10)
        np.testing.assert_allclose(a.betas, b.betas, atol=1e-12)
        # axis-angle may differ by 2π wraps; compare rotations
        Ra = Rotation.from_rotvec(a.pose[:, :3]).as_matrix()
        Rb = Rotation.from_rotvec(b.pose[:, :3]).as_matrix()
        np.testing.assert_allclose(Ra, Rb, atol=1e-10)
        np.testing.assert_allclose(a.pose[:, 3:], b.pose[:, 3:], atol=1e-12)


def test_root_joint_and_model_checks(models, layers):
    betas = np.random.default_rng(0).normal(size=(3, 10))
    j0 = mano_root_joint(models["right"], betas)
    _, joints = pose_verts(layers[("right", True)], np.zeros((3, 3)), np.zeros((3, 45)), betas, np.zeros((3, 3)))
    np.testing.assert_allclose(j0, joints[:, 0], atol=1e-12)
    np.testing.assert_allclose(mano_root_joint(layers[("right", False)], betas), j0, atol=1e-12)
    np.testing.assert_allclose(mano_root_joint(layers[("right", True)], betas), j0, atol=1e-12)  # J0 is pose-free


def test_mano_layers_checked(tree, models, mano_dir, layers):
    r = H2ORoot(tree)
    with pytest.raises(ValueError, match="right hand"):
        r.sequence(SUBJ, SCENE, SEQ, mano_layers={"left": models["right"], "right": models["right"]})
    # the tracks are converted for flat_hand_mean=False layers: a flat (or PCA) layer is refused, not misposed
    with pytest.raises(ValueError, match="flat_hand_mean=True"):
        r.sequence(SUBJ, SCENE, SEQ, mano_layers={s: layers[(s, True)] for s in ("left", "right")})
    pca = {s: MANOLayer(models[s], use_pca=True, dtype=F64) for s in ("left", "right")}
    with pytest.raises(ValueError, match="use_pca=True"):
        r.sequence(SUBJ, SCENE, SEQ, mano_layers=pca)
    r.sequence(SUBJ, SCENE, SEQ, mano_layers={s: layers[(s, False)] for s in ("left", "right")})
    with pytest.raises(ValueError, match="missing"):
        r.sequence(SUBJ, SCENE, SEQ, mano_layers={"right": models["right"]})
    # a MANO folder works like the in-memory models
    a = r.sequence(SUBJ, SCENE, SEQ, mano_layers=mano_dir)
    b = r.sequence(SUBJ, SCENE, SEQ, mano_layers=models)
    np.testing.assert_allclose(a.left.trans, b.left.trans, atol=1e-12)


# --------------------------------------------------------------------------------------
# Object, cameras, images
# --------------------------------------------------------------------------------------
def test_object_roundtrip(seq_world, scene):
    obj = seq_world.object
    assert obj.name == "lotion" and not obj.arti.any()
    world = scene.c2w[4] @ scene.obj4
    for f in (0, 1, 3):
        np.testing.assert_allclose(Rotation.from_rotvec(obj.rot[f]).as_matrix(), world[f, :3, :3], atol=1e-10)
        np.testing.assert_allclose(obj.trans[f], world[f, :3, 3], atol=1e-12)
    assert not obj.rot[2].any() and not obj.trans[2].any()


def test_cameras_intrinsics_images(seq_world, tree):
    assert seq_world.dataset == "h2o" and seq_world.subject == SUBJ and seq_world.name == f"{SCENE}/{SEQ}"
    assert seq_world.frame_ids.tolist() == FRAMES and seq_world.num_frames == F
    assert sorted(seq_world.cameras) == [0, 1, 4]
    for K, cam in seq_world.cameras.items():
        assert cam.view == K and cam.egocentric == (K == 4) and cam.dist is None
        assert (cam.width, cam.height) == (1280, 720)
        assert cam.K.shape == (F, 3, 3) and cam.world2cam.shape == (F, 4, 4)
        np.testing.assert_array_equal(cam.K[2], INTR.K)
        paths = seq_world.image_paths[K]
        assert [p.name for p in paths] == [f"{f:06d}.png" for f in FRAMES]
        img = read_h2o_rgb(paths[0], expected_size=(cam.width, cam.height))
        assert img.shape == (720, 1280, 3) and img.dtype == np.uint8
    # static cameras repeat one matrix; the ego camera moves
    assert np.allclose(seq_world.cameras[0].world2cam, seq_world.cameras[0].world2cam[:1])
    assert not np.allclose(seq_world.cameras[4].world2cam[0], seq_world.cameras[4].world2cam[1])
    with pytest.raises(AssetError, match="expected 640x480"):
        read_h2o_rgb(paths[0], expected_size=(640, 480))


def test_missing_images_are_none_and_rgb_written(tmp_path, scene, models):
    recs = scene.records()
    img = np.zeros((720, 1280, 3), np.uint8)
    img[..., 0] = 255  # red
    recs[4].rgb = [img] * F
    write_h2o_sequence(tmp_path, SUBJ, SCENE, SEQ, FRAMES, recs)
    (tmp_path / SUBJ / SCENE / "0" / "cam4" / "rgb" / "000005.png").unlink()
    seq = H2ORoot(tmp_path).sequence(SUBJ, SCENE, SEQ, mano_layers=models)
    assert seq.image_paths[0] == [None] * F  # no rgb folder
    assert [p is None for p in seq.image_paths[4]] == [False, False, True, False]
    got = read_h2o_rgb(seq.image_paths[4][0])
    assert got[0, 0].tolist() == [255, 0, 0]


def test_upper_case_folders(tmp_path, scene, models, seq_world):
    write_h2o_sequence(tmp_path, SUBJ, SCENE, SEQ, FRAMES, scene.records(), upper_case=True, placeholder_rgb=True)
    cam4 = tmp_path / SUBJ / SCENE / "0" / "cam4"
    assert (cam4 / "hand_pose_MANO").is_dir() and (cam4 / "obj_pose_RT").is_dir()
    seq = H2ORoot(tmp_path).sequence(SUBJ, SCENE, SEQ, mano_layers=models)
    for side in ("left", "right"):
        for key in ("rot", "pose", "trans", "betas", "valid"):
            np.testing.assert_array_equal(getattr(getattr(seq, side), key), getattr(getattr(seq_world, side), key))
    np.testing.assert_array_equal(seq.object.trans, seq_world.object.trans)
    # both spellings at once is ambiguous
    (cam4 / "hand_pose_mano").mkdir()
    with pytest.raises(AssetError, match="both"):
        H2ORoot(tmp_path).sequence(SUBJ, SCENE, SEQ, mano_layers=models)


def test_fixed_precision_files(tmp_path, scene, models, layers):
    write_h2o_sequence(tmp_path, SUBJ, SCENE, SEQ, FRAMES, scene.records(), precision=6)
    text = (tmp_path / SUBJ / SCENE / "0" / "cam4" / "hand_pose_mano" / "000003.txt").read_text()
    assert len(text.split()) == 124 and all(len(t.split(".")[1]) == 6 for t in text.split())
    seq = H2ORoot(tmp_path).sequence(SUBJ, SCENE, SEQ, mano_layers=models)
    v = scene.mano4.left.valid
    _, j_read = read_verts(layers, "left", seq.left)
    _, j_disk = disk_verts(layers, "left", scene.mano4.left)
    # 6 decimals on pose/cam_pose values move joints by well under a millimetre
    assert np.abs(j_read[v] - move(scene.c2w[4], j_disk)[v]).max() < 1e-4


def test_several_object_classes_refused(tmp_path, scene, models):
    recs = scene.records()
    recs[4].obj_class = np.array([LOTION, 1, 0, LOTION])
    write_h2o_sequence(tmp_path, SUBJ, SCENE, SEQ, FRAMES, recs)
    with pytest.raises(AssetError, match="several object classes") as exc:
        H2ORoot(tmp_path).sequence(SUBJ, SCENE, SEQ, mano_layers=models)
    assert exc.value.path.endswith("obj_pose_rt")
    book = H2ORoot(tmp_path).sequence(SUBJ, SCENE, SEQ, mano_layers=models, object_class=1)
    assert book.object.name == "book" and book.object.valid.tolist() == [False, True, False, False]
    lotion = H2ORoot(tmp_path).sequence(SUBJ, SCENE, SEQ, mano_layers=models, object_class=LOTION)
    assert lotion.object.valid.tolist() == [True, False, False, True]
    assert not lotion.object.trans[1].any()


def test_writer_checks_shapes_and_values(tmp_path, scene):
    recs = scene.records()
    recs[4].obj_transform = recs[4].obj_transform[:2]
    with pytest.raises(ValueError, match="obj_transform"):
        write_h2o_sequence(tmp_path, SUBJ, SCENE, SEQ, FRAMES, recs)
    with pytest.raises(ValueError, match="frame_ids"):
        write_h2o_sequence(tmp_path, SUBJ, SCENE, SEQ, [1, 1], recs)
    recs = scene.records()
    recs[4].action_label = np.array([0, 5, 5, 37])
    with pytest.raises(AssetError, match="action_label") as exc:
        write_h2o_sequence(tmp_path, SUBJ, SCENE, SEQ, FRAMES, recs)
    assert exc.value.path.endswith("000007.txt")


# --------------------------------------------------------------------------------------
# Malformed files: AssetError naming the file
# --------------------------------------------------------------------------------------
MANO_OK = format_h2o_line(np.r_[1, np.zeros(61), 1, np.zeros(61)])
BAD_FILES = [
    ("cam4/cam_pose/000004.txt", " ".join(["1"] * 15), "16 numbers"),
    ("cam0/cam_pose/000004.txt", format_h2o_line(np.r_[np.eye(4)[:3].ravel(), 0.1, 0, 0, 1]), "last row"),
    ("cam1/cam_pose/000004.txt", format_h2o_line(np.diag([1.5, 1.5, 1.5, 1.0]).ravel()), "orthonormal"),
    ("cam4/hand_pose_mano/000004.txt", format_h2o_line(np.zeros(118)), "124 numbers"),
    ("cam4/hand_pose_mano/000004.txt", MANO_OK.replace("1", "0.5", 1), "valid flag"),
    ("cam4/hand_pose_mano/000004.txt", MANO_OK.replace(" 0 ", " nan ", 1), "NaN"),
    ("cam4/hand_pose_mano/000004.txt", MANO_OK.replace(" 0 ", " 1e999 ", 1), "not a plain decimal|NaN or infinite"),
    ("cam4/hand_pose_mano/000004.txt", MANO_OK.replace(" 0 ", " zero ", 1), "not a plain decimal"),
    ("cam4/hand_pose_mano/000004.txt", "", "124 numbers, got 0"),
    ("cam4/hand_pose_mano/000004.txt", b"\xff\xfe1 2", "UTF-8"),
    ("cam4/obj_pose_rt/000004.txt", format_h2o_line([9, *np.eye(4).ravel()]), "class id"),
    ("cam4/obj_pose_rt/000004.txt", format_h2o_line([1.5, *np.eye(4).ravel()]), "class id"),
    ("cam4/obj_pose_rt/000004.txt", format_h2o_line([1, *np.eye(4).ravel(), 0]), "17 numbers"),
    ("cam4/obj_pose_rt/000004.txt", format_h2o_line([1, *np.r_[np.eye(4)[:3].ravel(), 0, 0, 2, 1]]), "last row"),
    ("cam4/cam_intrinsics.txt", "600 600 640 360 1280", "6 numbers"),
    ("cam0/cam_intrinsics.txt", "-600 600 640 360 1280 720", "positive"),
    ("cam1/cam_intrinsics.txt", "600 600 640 360 1280.5 720", "width"),
    ("cam4/hand_pose/000004.txt", " ".join(["0"] * 127), "128 numbers"),
    ("cam4/hand_pose/000004.txt", " ".join(["2"] + ["0"] * 127), "valid flag"),
    ("cam4/obj_pose/000004.txt", " ".join(["12"] + ["0"] * 63), "class id"),
    ("cam4/obj_pose/000004.txt", " ".join(["1"] + ["0"] * 64), "64 numbers"),
    ("cam4/action_label/000004.txt", "37", "action_label"),
    ("cam4/action_label/000004.txt", "1 2", "1 numbers"),
    ("cam4/verb_label/000004.txt", "-1", "verb_label"),
]


def _read_all(r: H2ORoot, models) -> None:
    r.sequence(SUBJ, SCENE, SEQ, mano_layers=models)
    r.read_hand_joints(SUBJ, SCENE, SEQ, 4, FRAMES)
    r.read_obj_boxes(SUBJ, SCENE, SEQ, 4, FRAMES)
    r.read_labels(SUBJ, SCENE, SEQ, 4, FRAMES, "action_label")
    r.read_labels(SUBJ, SCENE, SEQ, 4, FRAMES, "verb_label")


@pytest.fixture(scope="module")
def clean_tree(tmp_path_factory, scene) -> Path:
    root = tmp_path_factory.mktemp("h2o_bad")
    write_h2o_sequence(root, SUBJ, SCENE, SEQ, FRAMES, scene.records())
    return root


@pytest.mark.parametrize("rel,content,message", BAD_FILES, ids=[f"{b[0]}:{b[2]}" for b in BAD_FILES])
def test_malformed_file_named(clean_tree, models, rel, content, message):
    r = H2ORoot(clean_tree)
    _read_all(r, models)  # clean tree reads
    path = clean_tree / SUBJ / SCENE / "0" / rel
    backup = path.read_bytes()
    try:
        path.write_bytes(content if isinstance(content, bytes) else content.encode())
        with pytest.raises(AssetError, match=message) as exc:
            _read_all(r, models)
        assert Path(exc.value.path) == path
    finally:
        path.write_bytes(backup)


@pytest.mark.parametrize(
    "rel",
    [
        "cam4/hand_pose_mano/000007.txt",
        "cam4/obj_pose_rt/000005.txt",
        "cam1/cam_pose/000003.txt",
        "cam0/cam_intrinsics.txt",
    ],
)
def test_missing_file_named(clean_tree, models, rel):
    path = clean_tree / SUBJ / SCENE / "0" / rel
    backup = path.read_bytes()
    try:
        path.unlink()
        frames = FRAMES  # pass frames explicitly so a missing label file is not just skipped
        with pytest.raises(AssetError, match="missing") as exc:
            H2ORoot(clean_tree).sequence(SUBJ, SCENE, SEQ, mano_layers=models, frames=frames)
        assert Path(exc.value.path) == path
    finally:
        path.write_bytes(backup)


def test_missing_folders_named(tmp_path, scene, models):
    recs = scene.records()
    recs[4].obj_class = recs[4].obj_transform = None
    write_h2o_sequence(tmp_path, SUBJ, SCENE, SEQ, FRAMES, recs)
    with pytest.raises(AssetError, match="obj_pose_rt folder not found") as exc:
        H2ORoot(tmp_path).sequence(SUBJ, SCENE, SEQ, mano_layers=models)
    assert exc.value.path.endswith("cam4/obj_pose_rt")
    with pytest.raises(AssetError, match="camera folder not found"):
        H2ORoot(tmp_path).sequence(SUBJ, SCENE, SEQ, mano_layers=models, label_cam=3)
