"""H2O: object mesh reader, the H2O export of the tiny world, HOGS data, training and quality,
and the pose stages (ContactNet, the POM pose bank) on H2O's grasps.

The H2O tree is exported from the tiny world's ``s05/box_grab_01`` (16 frames, cams 0-3 =
world views 1-4, cam 4 = ego, 320x180 frames, the box as H2O's ``book``).
"""

from __future__ import annotations

import importlib
import json
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
import torch
from conftest import job, page_commands, placed, tiny_build_config

from hogsa_loader.assets.arctic import ArcticRoot
from hogsa_loader.assets.conventions import project, transform
from hogsa_loader.assets.h2o import H2ORoot
from hogsa_loader.assets.h2o_meshes import H2O_MESH_NAMES, find_h2o_mesh, h2o_mesh_candidates, load_h2o_object
from hogsa_loader.assets.h2o_poses import H2OPoseRoot
from hogsa_loader.assets.objects.template import BOTTOM, TOP
from hogsa_loader.assets.protocol import held_out_subjects, training_subjects
from hogsa_loader.errors import AssetError, UsageError
from hogsa_loader.geometry.rotations import axis_angle_to_matrix
from hogsa_loader.models.gaussians.hogs_model import HogsModel
from hogsa_loader.models.pom.bank import load_pose_bank
from hogsa_loader.models.pom.objects import ABSENT_PART_DISTANCE, ObjectSet
from hogsa_loader.train import HogsConfig, HogsTrainer
from hogsa_loader.train.hogs_data import FrameSelection
from hogsa_loader.train.hogs_data_h2o import crop_image, load_h2o_hogs_data, square_box
from hogsa_loader.train.hogs_source import mano_layers_from_dir, open_hogs_source
from hogsa_loader.train.pom_config import BankDataConfig, ContactNetDataConfig, PoseBankConfig
from hogsa_loader.train.pom_jobs import _bank_sequences, _split_subjects, open_pose_root
from hogsa_world.h2o_export import EXPORT_RECORD, export_h2o_world, write_obj_mesh

ROOT = Path(__file__).resolve().parents[2]


def _script(rel: str):
    spec = importlib.util.spec_from_file_location(Path(rel).stem, ROOT / rel)
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


@pytest.fixture(scope="module")
def h2o_world(tiny_world, tmp_path_factory):
    out = tmp_path_factory.mktemp("h2o") / "h2o"
    return out, export_h2o_world(tiny_world, out)


def _box_mesh(scale: float = 0.05) -> tuple[np.ndarray, np.ndarray]:
    import trimesh

    box = trimesh.creation.box(extents=(scale, 2 * scale, 3 * scale))
    return np.asarray(box.vertices), np.asarray(box.faces)


# ---------------------------------------------------------------------------------- meshes
def test_mesh_reader_finds_every_name_variant(tmp_path):
    import trimesh

    verts, faces = _box_mesh()
    n = 0
    for cls, names in H2O_MESH_NAMES.items():
        for path in h2o_mesh_candidates(tmp_path / "x", cls):
            d = tmp_path / f"case{n}"
            target = d / path.relative_to(tmp_path / "x")
            target.parent.mkdir(parents=True)
            trimesh.Trimesh(verts, faces, process=False).export(str(target))
            assert find_h2o_mesh(d, cls) == target
            t = load_h2o_object(d, names[-1])  # a mesh-name variant gives the class's README name
            assert t.name == cls and (t.parts == BOTTOM).all() and len(t.verts) == 8 and len(t.faces) == 12
            assert t.kp_top.shape == t.kp_bottom.shape == (16, 3) and t.sub_top.shape == (300, 3)
            assert t.diameter == pytest.approx(np.sqrt(14) * 0.05)
            n += 1
    assert n == sum(2 * len(v) ** 2 for v in H2O_MESH_NAMES.values()) == 40
    with pytest.raises(AssetError, match=r"tried .*ovomaltine/ovomaltine\.ply"):
        load_h2o_object(tmp_path / "case0", "cocoa")
    with pytest.raises(ValueError, match="unknown H2O object 'mug'"):
        load_h2o_object(tmp_path / "case0", "mug")
    big = tmp_path / "mm" / "book" / "book.obj"
    big.parent.mkdir(parents=True)
    trimesh.Trimesh(verts * 1000, faces, process=False).export(str(big))
    with pytest.raises(AssetError, match="metres"):
        load_h2o_object(tmp_path / "mm", "book")


def test_textured_mesh_keeps_uv_and_texture(tmp_path):
    verts, faces = _box_mesh()
    # split every face's corners (as UV seams do) so welding has something to weld
    tv, tf = verts[faces.reshape(-1)], np.arange(faces.size).reshape(-1, 3)
    uv = np.random.default_rng(0).random((len(tv), 2))
    tex = np.random.default_rng(1).integers(0, 256, (16, 16, 3), dtype=np.uint8)
    write_obj_mesh(tmp_path / "pringles", "chips", tv, tf, uv, tex)
    t = load_h2o_object(tmp_path, "chips")
    assert t.has_texture and (t.tex_parts == BOTTOM).all()
    np.testing.assert_allclose(t.tex_verts, tv, atol=1e-7)
    np.testing.assert_allclose(t.tex_uv, uv, atol=1e-7)
    np.testing.assert_array_equal(t.texture, tex)
    assert len(t.verts) == 8 and len(t.faces) == 12  # geometry welded


# ---------------------------------------------------------------------------------- export
def test_export_round_trip(h2o_world, tiny_world):
    out, record = h2o_world
    src_root = ArcticRoot(tiny_world)
    assert record["source"]["stage_seed"] == src_root.world_meta().extra["seed"]  # the world's table and room
    src = src_root.sequence("s05", "box_grab_01")
    layers = src_root.mano_layers(dtype=torch.float64)
    root = H2ORoot(out)
    assert root.sequences() == [("subject1", "h1", "0")]
    seq = root.sequence("subject1", "h1", 0, layers)
    idx = np.arange(0, 64, 4)
    assert seq.frame_ids.tolist() == idx.tolist() and seq.object.name == "book"

    def verts(track, side, rows):
        o = layers[side](
            global_orient=torch.as_tensor(track.rot[rows]),
            hand_pose=torch.as_tensor(track.pose[rows]),
            betas=torch.as_tensor(np.repeat(track.betas[None], len(rows), 0)),
            transl=torch.as_tensor(track.trans[rows]),
        )
        return o.vertices.numpy()

    for side in ("right", "left"):
        a, b = verts(getattr(seq, side), side, np.arange(16)), verts(getattr(src, side), side, idx)
        assert np.abs(a - b).max() < 1e-6, side
    np.testing.assert_allclose(seq.object.rot, src.object.rot[idx], atol=1e-9)
    np.testing.assert_allclose(seq.object.trans, src.object.trans[idx], atol=1e-9)
    for cam, view in enumerate((1, 2, 3, 4, 0)):
        np.testing.assert_allclose(seq.cameras[cam].world2cam, src.cameras[view].world2cam[idx], atol=1e-9)
        assert (seq.cameras[cam].width, seq.cameras[cam].height) == (320, 180)
        assert seq.cameras[cam].egocentric == (cam == 4)
        assert all(p is not None for p in seq.image_paths[cam])
    # the rigid mesh is the template at the sequence's articulation, in the object frame
    mesh = load_h2o_object(out / "object", "book")
    box = src_root.object_templates()["box"]
    assert np.abs(mesh.tex_verts - box.tex_verts).max() < 1e-6  # articulation 0 in this sequence
    np.testing.assert_array_equal(mesh.texture, box.texture)
    assert json.loads((out / EXPORT_RECORD).read_text())["h2o"]["mesh"] == "object/book/book.obj"
    with pytest.raises(ValueError, match="articulation varies"):
        export_h2o_world(tiny_world, out.parent / "bad", subject="s01", sequence="box_use_01")


def test_export_refuses_to_mix_exports_and_cli_errors(tiny_world, tmp_path, capsys):
    """A second export into the same H2O sequence folder is refused (frames would mix)
    unless overwrite; the CLI reports bad arguments as errors, not tracebacks."""
    from hogsa_loader.cli.main import main as cli

    out = tmp_path / "h2o"
    export_h2o_world(tiny_world, out, image_size=(48, 27), frame_stride=32)
    with pytest.raises(AssetError, match="already holds an H2O sequence"):
        export_h2o_world(tiny_world, out, image_size=(48, 27), frame_stride=16)
    with pytest.raises(ValueError, match="articulation varies"):  # a failed overwrite keeps the old export
        export_h2o_world(tiny_world, out, subject="s01", sequence="box_use_01", image_size=(48, 27), overwrite=True)
    assert H2ORoot(out).frames("subject1", "h1", 0) == [0, 32]
    rec = export_h2o_world(tiny_world, out, image_size=(48, 27), frame_stride=16, overwrite=True)
    root = H2ORoot(out)
    assert root.frames("subject1", "h1", 0) == rec["frames"] and len(rec["frames"]) > 2
    base = ["h2o-export", "--world", str(tiny_world), "--out", str(tmp_path / "x"), "--quiet"]
    for extra, msg in (
        (["--object-class", "foo"], "unknown H2O object 'foo'"),
        (["--mesh-name", "pringles"], "not a known name of H2O class"),
        (["--subject", "s01", "--sequence", "box_use_01"], "articulation varies"),
        (["--frame-stride", "0"], "frame stride must be >= 1"),
    ):
        assert cli(base + extra) == 2
        assert msg in capsys.readouterr().err
    assert cli(base[:3] + ["--out", str(out), "--quiet"]) == 1
    assert "already holds an H2O sequence" in capsys.readouterr().err


def test_crop_image_geometry():
    """Crop pixel i shows label coordinate origin + i / k (exact on a linear ramp), also
    when the crop shrinks the image (supersampled + box-filtered); black outside."""
    H, W = 60, 100
    ramp = np.stack(np.broadcast_arrays(np.arange(W)[None, :], np.arange(H)[:, None]), -1).astype(np.float32)
    for box, size in (
        (np.array([40.0, 30.0, 0.1]), 16),
        (np.array([40.0, 30.0, 0.1]), 60),
        (np.array([50, 25, 0.2]), 8),
    ):
        side = 300 * box[2]
        c = crop_image(ramp, box, size)
        want = box[0] - side / 2 + np.arange(size) * side / size
        half = 0.5 * side / size  # a shrunk pixel averages a block this far either side
        inside = (want - half >= 0) & (want + half <= W - 1)
        np.testing.assert_allclose(c[size // 2, inside, 0], want[inside], atol=1e-3)  # a row inside the image
    img = np.full((H, W, 3), 200, np.uint8)
    c = crop_image(img, np.array([5.0, 30.0, 0.1]), 30)  # hangs 10 px over the left edge
    assert (c[:, :8] == 0).all() and (c[:, 12:] == 200).all()
    b = square_box(np.array([[10.0, 20.0], [30.0, 24.0]]), enlarge=1.5)
    np.testing.assert_allclose(b, [20.0, 22.0, 30.0 / 300.0])


def test_h2o_data_alignment(h2o_world, tiny_world):
    out, _ = h2o_world
    layers = mano_layers_from_dir(Path(tiny_world) / "body_models" / "mano")
    tpl = load_h2o_object(out / "object", "book")
    data = load_h2o_hogs_data(
        H2ORoot(out), "subject1", "book", mano_layers=layers, template=tpl, selection=FrameSelection(image_size=64)
    )
    assert data.train_views == (0, 1, 2) and data.eval_views == (3,) and data.mask_source == "render"
    assert {s.view for s in data.train} == {0, 1, 2} and {s.view for s in data.eval} == {3}
    assert len(data.train) >= 30 and data.crop_size == 256
    assert set(np.unique(np.stack([s.mask for s in data.train]))) <= {0, 1, 2, 4}  # rigid: no top part
    seq = data.sequences[0]
    hits = []
    for s in data.train[::5]:
        o = seq.object
        R = axis_angle_to_matrix(torch.as_tensor(o.rot[s.frame])).numpy()
        v = tpl.verts.astype(np.float64) @ R.T + o.trans[s.frame]
        K = s.K.copy()
        K[:2, 2] -= 0.5
        uv = np.rint(project(transform(s.world2cam, v), K)).astype(int)
        ok = (uv >= 0).all(1) & (uv < 64).all(1)
        hits.append(np.isin(s.mask[uv[ok, 1], uv[ok, 0]], (4,)).mean())
    assert np.mean(hits) > 0.6  # occluded vertices land on hand pixels
    # the crop shows the picture: object pixels are not the dark background of the room
    lum = [s.image[s.mask == 4].mean() for s in data.train]
    assert np.mean(lum) > 40
    with pytest.raises(ValueError, match="no sequence with object 'milk'"):
        load_h2o_hogs_data(H2ORoot(out), "subject1", "milk", mano_layers=layers, template=tpl)
    with pytest.raises(ValueError, match="eval views must be among"):
        load_h2o_hogs_data(
            H2ORoot(out),
            "subject1",
            "book",
            mano_layers=layers,
            template=tpl,
            selection=FrameSelection(eval_views=(4,)),
        )
    ego = load_h2o_hogs_data(
        H2ORoot(out),
        "subject1",
        "book",
        mano_layers=layers,
        template=tpl,
        selection=FrameSelection(image_size=32, views=(0, 1, 2, 3, 4), frame_stride=4, eval_every_frame=2),
    )
    assert 4 in {s.view for s in ego.train}


# ---------------------------------------------------------------------------------- training
def test_h2o_training_end_to_end(h2o_world, tiny_world, tmp_path, capsys):
    out, _ = h2o_world
    mano = str(Path(tiny_world) / "body_models" / "mano")
    h2o = dict(
        dataset="h2o",
        data=str(out),
        mano_dir=mano,
        object_mesh_dir=str(out / "object"),
        subject="subject1",
        object="book",
    )
    cfg = HogsConfig.from_json(
        dict(
            **h2o,
            out=str(tmp_path / "run"),
            iters=24,
            image_size=64,
            max_eval=3,
            eval_every=0,
            ckpt_every=12,
            lr_scale=10.0,
            k=1,
            sh_degree=1,
            sh_warmup=0,
            strip_views=2,
        )
    )
    tr = HogsTrainer(cfg, progress=False)
    assert tr.cfg.data.views == (0, 1, 2, 3) and tr.cfg.data.eval_views == (3,)
    fixed = tr.data.train[:: max(1, len(tr.data.train) // 4)][:4]

    p0 = tr.photometric_loss(fixed)
    m = tr.train()
    assert tr.photometric_loss(fixed) < p0 - 0.01
    assert m["psnr"] > m["initial"]["psnr"] + 0.5 and m["dataset"] == "h2o" and m["eval_views"] == [3]
    run = tmp_path / "run"
    for f in ("strip.png", "curves.png", "metrics.json", "config.json", "checkpoints/latest.json"):
        assert (run / f).is_file(), f
    manifest = json.loads((run / "object" / "manifest.json").read_text())
    assert manifest["source"]["dataset"] == "h2o" and manifest["source"]["sequence"] == "h1/0"
    assert manifest["extra"]["object_mesh"]["mesh"].endswith("object/book/book.obj")

    source = open_hogs_source("h2o", out, "book", mano_dir=mano, object_mesh_dir=out / "object")
    model = HogsModel.from_run(run, source.mano_layers, source.object_templates)
    s = tr.data.eval[0]
    poses = tr.data.poses([s])
    vm = torch.as_tensor(s.world2cam, dtype=torch.float32)[None, None]
    K = torch.as_tensor(s.K, dtype=torch.float32)[None, None]
    with torch.no_grad():
        r = model.render(poses, vm, K, 64, 64, render_mode="RGB")
        rgb0, _ = tr.render([s])
    assert torch.allclose(r.rgb[:, 0], rgb0, atol=1e-5)
    assert float(r.alpha[0, 0, ..., 0][torch.as_tensor(s.mask > 0)].mean()) > 0.5

    rq = importlib.import_module("experiments.render_quality")
    qj = tmp_path / "q.json"
    assert (
        rq.main(
            [
                "--dataset",
                "h2o",
                "--data",
                str(out),
                "--mano-dir",
                mano,
                "--object-mesh-dir",
                str(out / "object"),
                "--run",
                str(run),
                "--json",
                str(qj),
                "--png",
                str(tmp_path / "q.png"),
            ]
        )
        == 0
    )
    q = json.loads(qj.read_text())
    assert q["psnr"] == pytest.approx(m["psnr"]) and q["ssim"] == pytest.approx(m["ssim"]) and "lpips" in q
    assert [v["view"] for v in q["per_view"]] == [3] and q["runs"][0]["dataset"] == "h2o"

    cli = job("hogs")
    args = [
        "--dataset",
        "h2o",
        "--data",
        str(out),
        "--subject",
        "subject1",
        "--object",
        "book",
        "--out",
        str(tmp_path / "x"),
    ]
    assert cli.main(args) == 2 and "needs --mano-dir and --object-mesh-dir" in capsys.readouterr().err
    assert cli.main(args + ["--mano-dir", mano, "--object-mesh-dir", str(tmp_path)]) == 2
    assert "no mesh for H2O object 'book'; tried book/book.obj, book/book.ply" in capsys.readouterr().err


def test_train_all_hogs_lists_h2o_pairs(h2o_world, tmp_path, capsys):
    """--dataset h2o: pairs are (subject, object class) read from the obj_pose_rt labels."""
    root, _ = h2o_world
    ta = job("train_all_hogs")
    args, rest = ta.parse_args(
        ["--data", str(root), "--out", str(tmp_path), "--dataset", "h2o", "--dry-run", "--", "--mano-dir", "M"]
    )
    from hogsa_loader.assets.h2o import H2ORoot

    assert ta.list_h2o_pairs(H2ORoot(root), args) == [("subject1", "book", ["h1/0"])] and rest == ["--mano-dir", "M"]
    assert ta.main(["--data", str(root), "--out", str(tmp_path), "--dataset", "h2o", "--dry-run"]) == 0
    assert "1 pairs" in capsys.readouterr().out
    args, _ = ta.parse_args(["--data", str(root), "--out", str(tmp_path), "--dataset", "h2o", "--objects", "milk"])
    assert ta.list_h2o_pairs(H2ORoot(root), args) == []


# ------------------------------------------------------------------------- the pose stages
def _pose_root(h2o_world, tiny_world) -> H2OPoseRoot:
    out, _ = h2o_world
    return H2OPoseRoot(out, ArcticRoot(tiny_world).mano_dir, out / "object")


def test_h2o_pose_root_reads_grasp_sequences(h2o_world, tiny_world, tmp_path):
    root = _pose_root(h2o_world, tiny_world)
    assert root.sequences() == root.sequences("subject1") == ["subject1/book_h1_0"]
    assert root.h2o_sequence("subject1/book_h1_0") == ("subject1", "h1", "0", 1)
    sd = root.sequence("subject1", "book_h1_0")
    assert (sd.dataset, sd.subject, sd.name, sd.object.name) == ("h2o", "subject1", "book_h1_0", "book")
    assert sd.num_frames == 16 and np.all(sd.object.arti == 0) and sd.right.valid.all()
    # the same labels as the H2O reader gives
    direct = H2ORoot(h2o_world[0]).sequence("subject1", "h1", 0, root.mano_layers(torch.float64))
    np.testing.assert_array_equal(sd.right.pose, direct.right.pose)
    np.testing.assert_array_equal(sd.object.trans, direct.object.trans)
    ((name, tpl),) = root.object_templates(load_texture=False).items()
    assert name == "book" and (tpl.parts == BOTTOM).all()
    assert held_out_subjects(root) == {"subject4": "test"}
    with pytest.raises(UsageError, match="subject4 \\(test\\) held out"):
        training_subjects(root, ["subject4"], (), "ContactNet")
    with pytest.raises(KeyError, match="subject/<object>_<scene>_<seq>"):
        root.h2o_sequence("subject1/h1_0")
    with pytest.raises(AssetError, match="needs mano_dir"):
        H2OPoseRoot(h2o_world[0], None, h2o_world[0] / "object")
    with pytest.raises(AssetError, match="object_mesh_dir folder not found"):
        H2OPoseRoot(h2o_world[0], root.mano_dir, tmp_path / "none")
    arctic = ContactNetDataConfig(root=str(tiny_world), mano_dir=str(root.mano_dir))
    with pytest.raises(UsageError, match="--mano-dir: only for --dataset h2o"):
        open_pose_root(arctic)
    with pytest.raises(UsageError, match="--dataset h2o needs --mano-dir"):
        open_pose_root(ContactNetDataConfig(root=str(root.root), dataset="h2o", object_mesh_dir=str(tmp_path)))


def test_the_pose_stages_never_open_the_held_out_subject(h2o_world, tiny_world, tmp_path):
    """subject4 (H2O's test subject) is listed but its labels are broken: the default ContactNet
    and bank selections leave it out without reading them; asked for by name, it is refused."""
    tree = tmp_path / "h2o"
    tree.mkdir()
    for item in h2o_world[0].iterdir():
        (tree / item.name).symlink_to(item, target_is_directory=item.is_dir())
    (tree / "subject4" / "h1" / "0" / "cam4").mkdir(parents=True)  # no labels at all
    root = H2OPoseRoot(tree, ArcticRoot(tiny_world).mano_dir, tree / "object")
    assert root.subjects() == ["subject1", "subject4"]
    with pytest.raises(AssetError):
        root.sequences("subject4")  # its labels cannot be read
    data = {
        "root": str(tree),
        "dataset": "h2o",
        "mano_dir": str(root.mano_dir),
        "object_mesh_dir": str(tree / "object"),
    }
    fresh = open_pose_root(ContactNetDataConfig(**data))
    assert _split_subjects(fresh, ContactNetDataConfig(**data)) == (["subject1"], [])
    bank = PoseBankConfig(data=BankDataConfig(**data, contactnet="unused"))
    assert _bank_sequences(fresh, bank) == ["subject1/book_h1_0"]
    with pytest.raises(UsageError, match="subject4 \\(test\\) held out"):
        asked = BankDataConfig(**data, contactnet="unused", subjects=("subject4",))
        _bank_sequences(fresh, PoseBankConfig(data=asked))


def test_a_rigid_object_has_no_top_part(h2o_world, tiny_world):
    root = _pose_root(h2o_world, tiny_world)
    objects = ObjectSet(root.object_templates(load_texture=False))
    g = objects.geometry("book")
    assert g.parts == (BOTTOM,) and set(g.tris) == set(g.trees) == set(g.voxels) == {BOTTOM}
    assert not g.points_top.any()
    tpl = objects.templates["book"]
    centre = torch.tensor((tpl.verts.min(0) + tpl.verts.max(0)) / 2, dtype=torch.float32)
    pts = torch.stack([centre, centre + torch.tensor([0.0, 0.0, 0.5])])[None].requires_grad_()
    parts = objects.part_sdf(pts, ["book"], torch.zeros(1))
    assert torch.all(parts[TOP] == ABSENT_PART_DISTANCE) and ABSENT_PART_DISTANCE == float("inf")
    d = objects.sdf(pts, ["book"], torch.zeros(1))
    assert torch.equal(d, parts[BOTTOM]) and d[0, 0] < 0 < d[0, 1] < 1.0
    d.sum().backward()
    assert torch.isfinite(pts.grad).all() and pts.grad.abs().sum() > 0


def test_the_pages_contactnet_and_pose_bank_run_on_h2o(h2o_world, tiny_world, tmp_path):
    from hogsa_loader.cli.main import main as hogsa

    root = _pose_root(h2o_world, tiny_world)
    cn_cmd, bank_cmd, _ = page_commands("h2o.md", "tests/train/test_h2o_hogs.py")
    paths = {"H2O": root.root, "MANO": root.mano_dir, "runs": tmp_path / "runs"}
    placed_cmds = [placed(c, paths) for c in (cn_cmd, bank_cmd)]
    assert placed_cmds[0][:2] == ["train", "contactnet"] and placed_cmds[1][:2] == ["train", "bank"]
    assert hogsa(placed_cmds[0] + ["--optim-iters", "10", "--run-val-every", "10", "--quiet"]) == 0
    toy = ["--per-sequence", "2", "--frame-margin", "2", "--pom-iters", "20", "--quiet"]
    assert hogsa(placed_cmds[1] + toy) == 0
    bank = load_pose_bank(tmp_path / "runs" / "h2o_pose_bank")
    assert len(bank.sources) == 2 and bank.info["held_out_read"] == []
    assert {(s, q) for s, q, _ in bank.sources} == {("subject1", "book_h1_0")}
    assert all(2 <= f < 14 for _, _, f in bank.sources)  # within the frame margin
    assert bank.state.obj_names == ["book", "book"] and torch.all(bank.state.obj_arti == 0)
    sd = root.sequence("subject1", "book_h1_0")
    for (_, _, f), trans in zip(bank.sources, bank.state.obj_trans):  # a perturbation of H2O's frame
        assert np.linalg.norm(trans.numpy() - sd.object.trans[f]) < 0.05
    assert torch.isfinite(bank.metrics["penetration_depth"]).all()


def test_the_pages_build_writes_an_h2o_bundle(h2o_world, tiny_world, untrained_bundle, tmp_path, monkeypatch):
    """``hogsa build --dataset h2o`` (the page's command with relative folders, toy settings from
    a config file): every stage is built on H2O's data, the bundle records the dataset and its
    folders (absolute) and checks against the H2O root; a bundle is refused against a root of
    the other dataset, and ``HOGSADataset`` refuses an H2O bundle by name."""
    import os

    from hogsa_loader.cli.main import main as hogsa
    from hogsa_loader.models.bundle import load_bundle
    from hogsa_loader.sample.dataset import HOGSADataset
    from hogsa_loader.train.build import config_toml

    root = _pose_root(h2o_world, tiny_world)
    (build_cmd,) = page_commands("h2o.md", "tests/train/test_h2o_hogs.py")[2:]
    out = tmp_path / "build_h2o"
    monkeypatch.chdir(tmp_path)
    rel = {k: Path(os.path.relpath(v, tmp_path)) for k, v in {"H2O": root.root, "MANO": root.mano_dir}.items()}
    argv = placed(build_cmd, {**rel, "build_h2o": Path("build_h2o")})
    assert argv[0] == "build"
    toml = tmp_path / "toy.toml"
    toy = tiny_build_config(root.root, out, pairs=None)
    toy = replace(  # the tree's sequence has 16 frames: every frame, and a short frame margin
        toy,
        hogs=replace(toy.hogs, data=replace(toy.hogs.data, frame_stride=1)),
        bank=replace(toy.bank, data=replace(toy.bank.data, frame_margin=2)),
    )
    toml.write_text(config_toml(toy))
    assert hogsa([*argv, "--config", str(toml), "--quiet"]) == 0
    assert len(list((out / "stages").rglob("*.json"))) == 5  # hogs/subject1_book, contactnet, bank, srm, bundle
    run_cfg = json.loads((out / "runs" / "hogs" / "subject1_book" / "config.json").read_text())
    assert (run_cfg["dataset"], run_cfg["subject"], run_cfg["object"]) == ("h2o", "subject1", "book")
    assert run_cfg["mano_dir"] == str(root.mano_dir) and run_cfg["sequences"] is None
    bank = load_pose_bank(out / "runs" / "pose_bank")
    assert bank.info["dataset"] == "h2o" and {(s, q) for s, q, _ in bank.sources} == {("subject1", "book_h1_0")}
    manifest = json.loads((out / "bundle" / "manifest.json").read_text())
    assert manifest["dataset"] == {
        "name": "h2o",
        "root": str(root.root),
        "subjects": ["subject1"],
        "cropped_size": 256,
        "mano_dir": str(root.mano_dir),
        "object_mesh_dir": str(root.object_mesh_dir),
    }
    assert list(manifest["objects"]) == ["book"] and manifest["srm"] and manifest["contactnet"]
    bundle = load_bundle(out / "bundle", data_root=root)
    assert bundle.dataset == "h2o" and bundle.keys == [("subject1", "book")]
    with pytest.raises(AssetError, match=r"built on h2o: check it against H2OPoseRoot\(root, mano_dir"):
        load_bundle(out / "bundle", data_root=tiny_world)
    with pytest.raises(AssetError, match="built on arctic, the data root .* is h2o"):
        load_bundle(untrained_bundle, data_root=root)
    with pytest.raises(AssetError, match="built on h2o: HOGSADataset streams bundles of ARCTIC"):
        HOGSADataset(out / "bundle", root.root)
