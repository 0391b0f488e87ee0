"""``hogsa view``: orbit cameras, pose transfer between subjects, the CLI and its pictures."""

from __future__ import annotations

import json

import cv2
import numpy as np
import pytest
import torch
from conftest import tiny_srm

from hogsa_loader.cli.main import main
from hogsa_loader.view import (
    PartLights,
    ViewConfig,
    align_wrists,
    frame_pose,
    orbit_azimuth,
    orbit_cameras,
    orbit_intrinsics,
    project,
    subject_betas,
    swap_hands,
    transfer_pose,
    transfer_report,
)

pytestmark = pytest.mark.usefixtures("one_thread")


# --------------------------------------------------------------------------------------
# Orbit cameras
# --------------------------------------------------------------------------------------


@pytest.mark.parametrize("n", [1, 5, 16])
@pytest.mark.parametrize("up", [(0.0, 0.0, 1.0), (0.3, -1.0, 0.2)])
def test_orbit_covers_the_full_circle(n, up):
    centre = np.array([0.1, -0.4, 0.8])
    w2c = orbit_cameras(centre, n, elevation_deg=25.0, distance=1.3, up=up, azimuth0_deg=40.0)
    assert w2c.shape == (n, 4, 4)
    R, t = w2c[:, :3, :3], w2c[:, :3, 3]
    np.testing.assert_allclose(R @ R.transpose(0, 2, 1), np.broadcast_to(np.eye(3), (n, 3, 3)), atol=1e-12)
    eyes = -np.einsum("nji,nj->ni", R, t)
    np.testing.assert_allclose(np.linalg.norm(eyes - centre, axis=1), 1.3, rtol=1e-12)  # equidistant
    u = np.asarray(up) / np.linalg.norm(up)
    rel = eyes - centre
    np.testing.assert_allclose(np.degrees(np.arcsin(rel @ u / 1.3)), 25.0, atol=1e-9)  # one elevation
    az = np.array([orbit_azimuth(centre, e, up) for e in eyes])
    steps = np.diff(np.unwrap(np.radians(az)))
    np.testing.assert_allclose(np.degrees(steps), 360.0 / n, atol=1e-9)  # evenly spaced, one turn in all
    assert abs(((az[0] - 40.0) + 180.0) % 360.0 - 180.0) < 1e-9
    # every camera looks at the centre, image up along the world up
    K = orbit_intrinsics(64, 1.3, 0.2)
    np.testing.assert_allclose(project(centre[None], w2c, K)[:, 0], 31.5, atol=1e-9)
    above = project((centre + 0.05 * u)[None], w2c, K)[:, 0]
    assert (above[:, 1] < 31.5).all() and np.allclose(above[:, 0], 31.5, atol=1e-6)


def test_orbit_intrinsics_frame_the_sphere():
    K = orbit_intrinsics(100, 2.0, 0.25, fill=0.8)
    half = np.arcsin(0.25 / 2.0)  # the sphere's angular radius
    assert 2 * K[0, 0] * np.tan(half) == pytest.approx(80.0)
    with pytest.raises(ValueError, match="not outside"):
        orbit_intrinsics(100, 0.2, 0.25)
    with pytest.raises(ValueError):
        orbit_cameras(np.zeros(3), 0, 10.0, 1.0)


# --------------------------------------------------------------------------------------
# Pose transfer
# --------------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def pom(tiny_world):
    from hogsa_loader.assets.arctic import ArcticRoot
    from hogsa_loader.models.pom import ObjectSet, hand_infos

    root = ArcticRoot(tiny_world)
    objects = ObjectSet({"box": root.object_templates(load_texture=False)["box"]}, sdf_voxel=0.004)
    return root, hand_infos(root.mano_layers()), objects


@pytest.fixture(scope="module")
def transferred(pom):
    root, infos, objects = pom
    seq = root.sequences("s01")[0].split("/", 1)[1]
    src = frame_pose(root, "s01", seq, 40)
    target = subject_betas(root, "s05")
    return src, target, transfer_pose(src.state, target, infos, objects, steps=20)


def test_transfer_keeps_articulation_object_and_target_betas(transferred, pom):
    from hogsa_loader.models.pom.state import hand_forward

    _, infos, _ = pom
    src, target, tr = transferred
    s, out = src.state, tr.state
    for side in ("right", "left"):
        assert torch.equal(out.hands[side].pose, s.hands[side].pose)  # articulation: the source's, bit for bit
        assert torch.equal(out.hands[side].betas[0], torch.as_tensor(target[side]))
        assert not torch.equal(out.hands[side].betas, s.hands[side].betas)
        # before the re-solve, the wrist joint is where the source wrist was
        w_src = hand_forward(infos[side], s.hands[side]).joints[:, 0]
        w_al = hand_forward(infos[side], tr.aligned.hands[side]).joints[:, 0]
        torch.testing.assert_close(w_al, w_src, atol=1e-6, rtol=0)
        assert torch.equal(tr.aligned.hands[side].rot, s.hands[side].rot)
    for k in ("obj_arti", "obj_rot", "obj_trans"):
        assert torch.equal(getattr(out, k), getattr(s, k))
    assert out.obj_names == s.obj_names == ["box"]


def test_transfer_report_has_contact_and_penetration_figures(transferred, pom):
    _, infos, objects = pom
    _, _, tr = transferred
    (rec,) = transfer_report(tr, infos, objects)
    assert set(rec) == {"source", "aligned", "transferred"}
    for stage in rec.values():
        assert {
            "penetration_depth_mm",
            "intersection_cm3",
            "contact_ratio",
            "contact_right",
            "contact_left",
            "accept",
            "contact_error_mm",
        } <= set(stage)
    assert rec["source"]["contact_error_mm"]["right"] in (0.0, None)
    touching = [s for s in ("right", "left") if rec["source"]["contact_error_mm"][s] is not None]
    assert touching, "the test frame should be a grasp"
    for s in touching:  # the re-solve brings the source contacts back (a new hand shape cannot match exactly)
        assert rec["transferred"]["contact_error_mm"][s] <= rec["aligned"]["contact_error_mm"][s] + 1e-6
        assert rec["transferred"][f"contact_{s}"]


def test_align_wrists_without_betas_change_is_identity(pom, transferred):
    _, infos, _ = pom
    src, _, _ = transferred
    same = {s: src.state.hands[s].betas[0] for s in ("right", "left")}
    out = align_wrists(src.state, same, infos)
    for s in ("right", "left"):
        torch.testing.assert_close(out.hands[s].trans, src.state.hands[s].trans, atol=1e-7, rtol=0)


# --------------------------------------------------------------------------------------
# Models: hands of one run, object of another
# --------------------------------------------------------------------------------------


def _parts(root):
    from hogsa_loader.models.gaussians.hogs_model import HogsModel
    from hogsa_loader.models.gaussians.parts import BindingConfig, HandGaussians, ObjectGaussians
    from hogsa_loader.models.gaussians.shading import DirectionalLight

    layers, templates = root.mano_layers(), root.object_templates()
    binding = BindingConfig(k=1, sh_degree=0)

    def model(light):
        return HogsModel(
            HandGaussians(layers["right"], binding),
            HandGaussians(layers["left"], binding),
            ObjectGaussians(templates["box"], binding),
            light=light,
        )

    return model(DirectionalLight((0.0, 0.0, -1.0), 0.2, 0.9)), model(DirectionalLight((1.0, 0.0, 0.0), 0.9, 0.1))


def test_swap_hands_takes_hands_and_object_with_their_own_lights(pom):
    root, _, _ = pom
    a, b = _parts(root)
    m = swap_hands(b, a)  # b's hands, a's object
    assert m.parts["hand_right"] is b.parts["hand_right"] and m.parts["object"] is a.parts["object"]
    assert isinstance(m.light, PartLights) and swap_hands(a, a) is a
    seq = root.sequences("s01")[0].split("/", 1)[1]
    from hogsa_loader.view.transfer import state_poses

    poses = state_poses(frame_pose(root, "s01", seq, 10).state)
    scene = m.scene(poses)
    w2c = torch.as_tensor(orbit_cameras(np.zeros(3), 2, 10.0, 1.0), dtype=torch.float32)[None]
    cols = m.light(scene, w2c)
    hand = scene.part_ids < 2
    torch.testing.assert_close(cols[:, :, hand], b.light(scene, w2c)[:, :, hand])
    torch.testing.assert_close(cols[:, :, ~hand], a.light(scene, w2c)[:, :, ~hand])


# --------------------------------------------------------------------------------------
# The command
# --------------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def two_subject_bundle(tiny_world, tmp_path_factory):
    """Untrained models of s01/box and s05/box (s05 with a learned-light folder), a tiny
    SRM and a two-row pose bank of s01."""
    from hogsa_loader.assets.arctic import ArcticRoot
    from hogsa_loader.models.bundle import write_bundle
    from hogsa_loader.models.gaussians.shading import DirectionalLight, save_light
    from hogsa_loader.models.pom import save_pose_bank
    from hogsa_loader.models.pom.state import load_frames
    from hogsa_world.untrained import write_untrained_run

    root = ArcticRoot(tiny_world)
    out = tmp_path_factory.mktemp("view_bundle")
    runs = [write_untrained_run(tiny_world, out / "runs" / f"{sid}_box", sid, "box") for sid in ("s01", "s05")]
    save_light(DirectionalLight((0.0, 0.0, -1.0), 0.4, 0.6), runs[1] / "light")
    state, src = load_frames(root, [root.sequences("s01")[0]], stride=30)
    state, src = state.select([0, 1]), src[:2]
    n = state.batch
    metrics = {
        "penetration_depth": np.zeros(n),
        "intersection": np.zeros(n),
        "contact_ratio": np.full(n, 0.1),
        "accept": np.ones(n),
    }
    save_pose_bank(out / "pose_bank", state, src, metrics)
    return write_bundle(out / "bundle", tiny_world, runs, srm=tiny_srm(out / "srm"), pose_banks=[out / "pose_bank"])


def _first_seq(world) -> str:
    from hogsa_loader.assets.arctic import ArcticRoot

    return ArcticRoot(world).sequences("s01")[0].split("/", 1)[1]


def _args(bundle, world, out, *extra):
    return [
        "view",
        "--bundle",
        str(bundle),
        "--data",
        str(world),
        "--subject",
        "s01",
        "--object",
        "box",
        "--out",
        str(out),
        *extra,
    ]


@pytest.fixture(scope="module")
def view_run(two_subject_bundle, tiny_world, tmp_path_factory):
    out = tmp_path_factory.mktemp("view")
    seq = _first_seq(tiny_world)
    rc = main(
        _args(
            two_subject_bundle,
            tiny_world,
            out,
            "--orbit",
            "4",
            "--size",
            "32",
            "--transfer-to",
            "s05",
            "--frame",
            f"{seq}:40",
            "--pose-bank",
            "pose_bank:1",
            "--keypoints",
            "--background",
            "photo",
            "--contact-voxel",
            "0.004",
            "--quiet",
        )
    )
    assert rc == 0
    return out, json.loads((out / "view.json").read_text())


def test_view_writes_orbits_grid_and_record(view_run):
    out, rec = view_run
    assert rec["subjects"] == ["s01", "s05"] and rec["hand_models"] == {"s01": "s01/box", "s05": "s05/box"}
    for sid in ("s01", "s05"):
        orb = rec["orbits"][sid]
        assert orb["views"] == 4 and np.allclose(np.diff(orb["azimuth_deg"]), 90.0)
        img = cv2.imread(orb["png"])
        assert img is not None and img.shape[0] > 2 * 32  # a HOGS row and a HOGS + SRM row
        import imageio.v3 as iio

        frames = iio.imread(orb["video"], index=None)
        assert frames.shape[:3] == (4, 32, 64)  # HOGS | HOGS + SRM side by side
        hogs, srm = frames[..., :32, :3].astype(float), frames[..., 32:, :3].astype(float)
        # every view shows something different (the camera moves), and the SRM changes the pixels
        assert min(np.abs(hogs[i] - hogs[j]).mean() for i in range(4) for j in range(i + 1, 4)) > 0.5
        assert np.abs(hogs - srm).mean() > 0.5
    grid = cv2.imread(str(out / "transfer.png"))
    assert grid is not None and grid.shape[0] > 4 * 32 and grid.shape[1] > 2 * 32  # 2 poses x (HOGS, SRM) x 2 subjects
    assert [p["kind"] for p in rec["poses"]] == ["frame", "pose_bank"]


def test_view_reports_the_transferred_grasps(view_run):
    _, rec = view_run
    assert len(rec["transfers"]) == 2  # both pose sources moved onto s05's hands
    for t in rec["transfers"]:
        assert (t["from"], t["to"]) == ("s01", "s05")
        for stage in ("source", "aligned", "transferred"):
            assert t[stage]["penetration_depth_mm"] >= 0.0 and t[stage]["intersection_cm3"] >= 0.0
        assert all(np.isfinite(t[stage]["penetration_depth_mm"]) for stage in ("source", "aligned", "transferred"))


def test_view_without_transfer_or_srm(two_subject_bundle, tiny_world, tmp_path):
    rc = main(
        _args(
            two_subject_bundle,
            tiny_world,
            tmp_path,
            "--orbit",
            "3",
            "--size",
            "32",
            "--no-srm",
            "--video",
            "none",
            "--quiet",
        )
    )
    assert rc == 0
    rec = json.loads((tmp_path / "view.json").read_text())
    assert rec["transfers"] == [] and "video" not in rec["orbits"]["s01"]
    assert rec["poses"][0]["kind"] == "frame"  # the default: a middle frame of the subject's sequence


@pytest.mark.parametrize(
    "extra, message",
    [
        (["--orbit", "-2"], "--orbit must be in 0..360"),
        (["--orbit", "many"], "argument --orbit: invalid int value"),
        (["--frame", "box_use_01"], "--frame expects SEQ:IDX"),
        (["--frame", "nope_01:3"], "has no sequence 'nope_01'"),
        (["--frame", "SEQ:100000"], "has frames 0.."),
        (["--pose-bank", "other:0"], "no pose bank 'other'"),
        (["--pose-bank", "pose_bank:7"], "pose_bank has rows 0..1"),
        (["--elevation", "95"], "--elevation must be in"),
        (["--size", "8"], "--size must be in"),
        (["--transfer-to", "s09"], "no HOGS model of that subject"),
        (["--transfer-to", "s01"], "lists the shown subject"),
        (["--background", "fancy"], "argument --background: invalid choice"),
        (["--background-folder", "/nonexistent"], "applies to --background photo"),
        (["--distance", "0"], "--distance must be a positive"),
        (["--device", "tpu"], "--device must be cpu or cuda"),
        (["--contact-voxel", "0.5"], "--contact-voxel must be in"),
    ],
)
def test_view_bad_arguments_give_one_line_errors(two_subject_bundle, tiny_world, tmp_path, capsys, extra, message):
    seq = _first_seq(tiny_world)
    extra = [e.replace("SEQ", seq) for e in extra]
    _one_line_error(_args(two_subject_bundle, tiny_world, tmp_path / "o", *extra), message, capsys)
    assert not (tmp_path / "o").exists()  # nothing written


def _one_line_error(argv, message, capsys):
    try:
        rc = main(argv)
    except SystemExit as exc:  # argparse-level errors
        rc = exc.code
    err = capsys.readouterr().err
    assert rc == 2
    assert err.startswith("hogsa view: error: ") and err.count("\n") == 1 and "Traceback" not in err, err
    assert message in err, err


def test_view_missing_or_broken_inputs(two_subject_bundle, tiny_world, tmp_path, capsys):
    cases = [
        (
            ["view", "--data", str(tiny_world), "--subject", "s01", "--object", "box", "--out", str(tmp_path)],
            "the following arguments are required: --bundle",
        ),
        (_args(tmp_path, tiny_world, tmp_path / "o"), "not a bundle folder"),
        (_args(two_subject_bundle, tmp_path / "none", tmp_path / "o"), "no such folder"),
        (
            [
                "view",
                "--bundle",
                str(two_subject_bundle),
                "--data",
                str(tiny_world),
                "--subject",
                "s05",
                "--object",
                "laptop",
                "--out",
                str(tmp_path / "o"),
            ],
            "no HOGS model for s05/laptop",
        ),
    ]
    for argv, message in cases:
        _one_line_error(argv, message, capsys)


def test_view_config_flags_come_from_the_dataclass():
    from hogsa_loader.cli.main import build_parser

    argv = _args("B", "D", "O", "--transfer-to", "s02,s05", "--no-srm", "--distance", "1.5")
    ns = build_parser().parse_args(argv)
    from hogsa_loader.cli.dataclass_args import dataclass_from_args

    cfg = dataclass_from_args(ViewConfig, ns)
    assert cfg.transfer_to == ("s02", "s05") and cfg.srm is False and cfg.distance == 1.5 and cfg.orbit == 16
    assert (cfg.bundle, cfg.data, cfg.subject, cfg.object, cfg.out) == ("B", "D", "s01", "box", "O")


def test_view_keypoints_and_sample_labels_are_drawn_by_one_helper() -> None:
    from hogsa_loader.view.grid import COLORS, draw_labels, draw_skeletons
    from hogsa_loader.view.pictures import draw_keypoints

    img = np.zeros((64, 64, 3), np.uint8)
    r = np.stack([np.linspace(10, 50, 21), np.full(21, 20.0)], 1)
    l_ = np.stack([np.linspace(10, 50, 21), np.full(21, 44.0)], 1)
    obj = np.array([[32.0, 32.0], [5.0, 5.0]])
    drawn = draw_keypoints(img, {"joints.right": r, "joints.left": l_, "kp3d": obj})
    assert np.array_equal(drawn, draw_skeletons(img, {"r": r, "l": l_}, obj))
    assert tuple(drawn[20, 30]) == COLORS["r"] and tuple(drawn[44, 30]) == COLORS["l"]
    assert tuple(drawn[5, 5]) == COLORS["object"] and not img.any()  # a copy is drawn
    # the sample labels (normalised to the patch) land on the same pixels
    norm = {
        k: torch.as_tensor(v / 32.0 - 1.0, dtype=torch.float32)
        for k, v in (("mano.j2d.norm.r", r), ("mano.j2d.norm.l", l_), ("object.kp2d.norm", obj))
    }
    targets = {**norm, "is_valid": 1.0, "right_valid": 1.0, "left_valid": 0.0}
    assert np.array_equal(draw_labels(img, targets, img_res=64), draw_skeletons(img, {"r": r}, obj))
