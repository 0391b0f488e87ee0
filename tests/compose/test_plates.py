"""Background plates: the masked median, the crop → plate geometry, plates that reproduce
the background of every frame they were made from, and the ``hogsa plates`` command."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import cv2
import numpy as np
import pytest

from hogsa_loader.assets.arctic import ArcticRoot
from hogsa_loader.assets.arctic_processing import crop_boxes
from hogsa_loader.assets.conventions import full_to_cropped
from hogsa_loader.cli.main import main
from hogsa_loader.compose import FolderBackgrounds
from hogsa_loader.compose.plates import PlateConfig, _foreground, _frames, _median, _Sample, build_plates, crop_to_plate
from hogsa_loader.render.part_masks import pose_meshes


def test_median_uses_only_background_samples() -> None:
    imgs = [np.full((2, 3, 3), v, np.uint8) for v in (10, 200, 30, 250)]
    oks = [np.ones((2, 3), bool) for _ in imgs]
    oks[1][0, 0] = oks[3][0, 0] = False  # the bright frames are foreground at (0, 0)
    oks[0][1, 2] = oks[1][1, 2] = oks[2][1, 2] = False  # only frame 3 saw (1, 2)
    for o in oks:
        o[0, 1] = False  # nobody saw (0, 1)
    samples = [_Sample(0, 0, i, o) for i, o in zip(imgs, oks, strict=True)]
    samples.append(_Sample(1, 1, np.full((1, 1, 3), 99, np.uint8), np.ones((1, 1), bool)))  # a window at (1, 1)
    plate, count = _median(samples, (2, 3), rows=1)
    assert plate[0, 0].tolist() == [20, 20, 20]  # median of 10 and 30, not of all four
    assert plate[1, 2].tolist() == [250] * 3
    assert plate[1, 0].tolist() == [115] * 3  # median of all four
    assert plate[1, 1].tolist() == [99] * 3  # median of 10, 200, 30, 250 and the window's 99
    assert count.tolist() == [[2, 0, 4], [4, 5, 1]]


def test_plate_of_a_known_image_equals_the_image_downscaled() -> None:
    """Crops made with ``full_to_cropped`` from a known full image land where the image is:
    the warped crop equals the downscaled full image (a 0.5-pixel error fails)."""
    W, H, crop, width = 700, 500, 256, 350
    yy, xx = np.mgrid[0:H, 0:W].astype(np.float64)
    full = np.stack(
        [127 + 120 * np.sin(xx / 7.0), 127 + 120 * np.cos(yy / 9.0), 127 + 100 * np.sin((xx + yy) / 11.0)], -1
    ).astype(np.float32)
    gain = width / W
    ref = cv2.resize(full, (width, round(H * gain)), interpolation=cv2.INTER_AREA)
    for bbox in (np.array([350.0, 260.0, 1.0]), np.array([301.3, 222.7, 0.83])):
        src = np.array([[0.0, 0.0], [100.0, 0.0], [0.0, 100.0]])
        dst = full_to_cropped(src, bbox, crop)  # full -> crop, as the dataset defines it
        A = cv2.getAffineTransform(src.astype(np.float32), dst.astype(np.float32))
        cropped = cv2.warpAffine(full, A, (crop, crop), flags=cv2.INTER_LINEAR)
        resized = int(round(1.5 * bbox[2] * 200 * gain))
        small = cv2.resize(cropped, (resized, resized), interpolation=cv2.INTER_AREA)
        errs = []
        for shift in (0.0, 0.5):
            M = crop_to_plate(bbox, crop, resized, gain)
            M[:, 2] += shift
            plate = cv2.warpAffine(small, M, (ref.shape[1], ref.shape[0]), flags=cv2.INTER_LINEAR)
            seen = cv2.warpAffine(np.ones((resized, resized), np.uint8), M, (ref.shape[1], ref.shape[0]))
            seen = cv2.erode(seen, np.ones((5, 5), np.uint8)) > 0
            errs.append(float(np.abs(plate - ref)[seen].mean()))
        assert errs[0] < 3.0 and errs[1] > 1.5 * errs[0], errs


def test_crop_to_plate_inverts_the_crop() -> None:
    bbox = np.array([1234.5, 876.25, 3.4])
    crop, resized, gain = 1000, 317, 960 / 2800
    full = np.array([[1000.0, 700.0], [1500.2, 1111.7], [1234.5, 876.25]])
    j = full_to_cropped(full, bbox, crop)  # cropped-image pixels
    r = (j + 0.5) * resized / crop - 0.5  # the same points in the resized crop (OpenCV centres)
    M = crop_to_plate(bbox, crop, resized, gain)
    plate = r @ M[:, :2].T + M[:, 2]
    np.testing.assert_allclose(plate, (full + 0.5) * gain - 0.5, atol=1e-9)


@pytest.fixture(scope="module", params=["files", "render"])
def plates(tiny_world, tmp_path_factory, request):
    """Plates from the mask files, and from masks rendered from the annotations (real ARCTIC)."""
    out = tmp_path_factory.mktemp("plates")
    cfg = PlateConfig(
        data=str(tiny_world),
        out=str(out),
        subjects=("s01",),
        views=(1, 4),
        width=480,
        frames_per_sequence=6,
        masks=request.param,
        quiet=True,
    )
    return cfg, build_plates(cfg)


def test_plates_reproduce_every_frames_background(plates, tiny_world) -> None:
    """Warped into a frame it was made from (at the plate's resolution), a plate equals the
    frame's background pixels (mask files, eroded); shifted by 3 pixels it does not."""
    cfg, manifest = plates
    root = ArcticRoot(tiny_world)
    names = {(p["subject"], p["view"]): p for p in manifest["plates"]}
    assert set(names) == {("s01", 1), ("s01", 4)}
    crop = root.world_meta().cropped_size
    checked = 0
    for sid_seq in root.sequences("s01"):
        seq = root.sequence("s01", sid_seq.split("/", 1)[1])
        boxes = crop_boxes(root, seq, (1, 4))
        used = _frames(seq.num_frames, cfg.frames_per_sequence)
        for view in (1, 4):
            rec = names[("s01", view)]
            x0, y0, x1, y1 = rec["box"]
            gain = cfg.width / seq.cameras[view].width
            canvas = np.zeros((round(seq.cameras[view].height * gain), cfg.width, 3), np.uint8)
            canvas[y0:y1, x0:x1] = cv2.imread(str(Path(cfg.out) / rec["file"]))
            for f in (used[0], used[len(used) // 2]):
                box = boxes[view][f]
                res = int(round(1.5 * float(box[2]) * 200.0 * gain))
                img = cv2.imread(str(seq.image_paths[view][f]))
                bg = (cv2.imread(str(seq.mask_paths[view][f]), cv2.IMREAD_UNCHANGED) == 0) & (img.sum(-1) > 0)
                small = cv2.resize(img, (res, res), interpolation=cv2.INTER_AREA).astype(float)
                bg = cv2.resize(bg.astype(np.float32), (res, res), interpolation=cv2.INTER_AREA) >= 1.0
                bg = cv2.erode(bg.astype(np.uint8), np.ones((5, 5), np.uint8)) > 0
                errs = []
                for shift in (0.0, 3.0):
                    M = crop_to_plate(box, crop, res, gain)
                    M[0, 2] += shift
                    back = cv2.warpAffine(canvas, M, (res, res), flags=cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP)
                    errs.append(float(np.abs(back - small)[bg].mean()))
                assert errs[0] < 4.0, (sid_seq, view, f, errs)
                assert errs[1] > 1.5 * errs[0], (sid_seq, view, f, errs)
                checked += 1
    assert checked >= 4


def test_plates_folder_is_a_background_source(plates) -> None:
    import torch

    cfg, manifest = plates
    on_disk = json.loads((Path(cfg.out) / "plates.json").read_text())
    assert on_disk["plates"] == manifest["plates"]
    assert all(0.5 <= p["coverage"] <= 1.0 and p["frames"] > 0 for p in manifest["plates"])
    src = FolderBackgrounds(cfg.out)
    out = src.sample(3, 64, 64, torch.Generator().manual_seed(0))
    assert out.shape == (3, 64, 64, 3) and float(out.std()) > 0.01


def test_plates_command(tiny_world, tmp_path, capsys) -> None:
    out = tmp_path / "p"
    assert (
        main(
            [
                "plates",
                "--data",
                str(tiny_world),
                "--out",
                str(out),
                "--subjects",
                "s01",
                "--views",
                "2",
                "--width",
                "320",
                "--frames-per-sequence",
                "2",
                "--masks",
                "render",
                "--quiet",
            ]
        )
        == 0
    )
    rec = json.loads((out / "plates.json").read_text())
    assert [p["file"] for p in rec["plates"]] == ["s01_view2.png"] and (out / "s01_view2.png").is_file()
    assert main(["plates", "--data", str(tiny_world), "--out", str(out), "--views", "0"]) == 2
    assert "views 1..8" in capsys.readouterr().err
    assert main(["plates", "--data", str(tiny_world), "--out", str(out), "--subjects", "s99"]) == 2
    assert "s99" in capsys.readouterr().err


def test_rebuild_removes_stale_plates_and_renders_missing_masks(tiny_world, tmp_path) -> None:
    """A rebuild leaves only its own plates in the folder; with masks='auto' a frame whose
    mask file is missing gets a rendered mask (the other frames keep their files)."""
    root = tmp_path / "w"
    data = root / "arctic_data" / "data"
    data.mkdir(parents=True)
    for entry in (Path(tiny_world) / "arctic_data" / "data").iterdir():
        if entry.name != "masks":
            (data / entry.name).symlink_to(entry)
    (root / "body_models").symlink_to(Path(tiny_world) / "body_models")
    shutil.copytree(Path(tiny_world) / "arctic_data" / "data" / "masks", data / "masks")
    gone = sorted((data / "masks" / "s01").glob("*/2/00000.png"))
    assert gone
    for f in gone:
        f.unlink()
    out = tmp_path / "p"
    base = dict(data=str(root), out=str(out), subjects=("s01",), width=240, frames_per_sequence=2, quiet=True)
    build_plates(PlateConfig(views=(2, 3), **base))
    assert sorted(p.name for p in out.glob("*.png")) == ["s01_view2.png", "s01_view3.png"]
    rec = build_plates(PlateConfig(views=(3,), **base))
    assert [p["file"] for p in rec["plates"]] == ["s01_view3.png"]
    assert sorted(p.name for p in out.glob("*.png")) == ["s01_view3.png"]


def test_rendered_foreground_matches_mask_files(tiny_world) -> None:
    """Where a dataset has no masks (real ARCTIC), the rendered foreground is the mask files'."""
    root = ArcticRoot(tiny_world)
    crop = root.world_meta().cropped_size
    seq = root.sequence("s01", "box_use_01")
    frames = _frames(seq.num_frames, 3)
    cache = {
        "boxes": crop_boxes(root, seq, (1, 5)),
        "pose": lambda: pose_meshes(seq, frames, root.mano_layers(), root.object_templates()["box"]),
    }
    ious = []
    for view in (1, 5):
        for f in frames:
            res = 96
            rendered = _foreground(seq, view, f, res, crop, PlateConfig(masks="render"), cache)
            files = _foreground(seq, view, f, res, crop, PlateConfig(masks="files"), cache)
            ious.append((rendered & files).sum() / max(1, (rendered | files).sum()))
    assert min(ious) > 0.9, ious


def test_camera_plate_is_the_backdrop_of_its_camera(plates, tiny_world) -> None:
    """``PlateBackgrounds.camera_plate`` cut by a real frame's box equals that frame's
    background pixels; the other view's plate does not; random draws equal the folder's."""
    import torch

    from hogsa_loader.compose import PlateBackgrounds

    cfg, _ = plates
    src = PlateBackgrounds(cfg.out)
    assert src.has_plate("s01", 1) and not src.has_plate("s01", 2) and not src.has_plate("s02", 1)
    assert src.camera_plate("s01", 2, np.array([100.0, 100.0, 1.0]), 64) is None
    g0, g1 = torch.Generator().manual_seed(3), torch.Generator().manual_seed(3)
    assert torch.equal(src.sample(2, 48, 48, g0), FolderBackgrounds(cfg.out).sample(2, 48, 48, g1))
    root = ArcticRoot(tiny_world)
    crop = root.world_meta().cropped_size
    size, checked = 96, 0
    f2o = np.array([[size / crop, 0.0, 0.0], [0.0, size / crop, 0.0]])  # the dataset's crop → output pixels

    def to_output(img: np.ndarray, shift: float = 0.0) -> np.ndarray:
        sigma = 0.5 * crop / size  # anti-aliased, then sampled with the dataset's pixel convention
        M = f2o.copy()
        M[0, 2] += shift
        return cv2.warpAffine(cv2.GaussianBlur(img, (0, 0), sigma), M, (size, size), flags=cv2.INTER_LINEAR)

    for sid_seq in root.sequences("s01"):
        seq = root.sequence("s01", sid_seq.split("/", 1)[1])
        boxes = crop_boxes(root, seq, (1, 4))
        for view, other in ((1, 4), (4, 1)):
            for f in _frames(seq.num_frames, cfg.frames_per_sequence)[:2]:
                box = boxes[view][f]
                img = cv2.cvtColor(cv2.imread(str(seq.image_paths[view][f])), cv2.COLOR_BGR2RGB).astype(np.float32)
                bg = (cv2.imread(str(seq.mask_paths[view][f]), cv2.IMREAD_UNCHANGED) == 0) & (img.sum(-1) > 0)
                bg = cv2.warpAffine(bg.astype(np.float32), f2o, (size, size), flags=cv2.INTER_NEAREST) > 0
                bg = cv2.erode(bg.astype(np.uint8), np.ones((7, 7), np.uint8)) > 0
                own = src.camera_plate("s01", view, box, size)
                wrong = src.camera_plate("s01", other, box, size)
                assert own.shape == (size, size, 3) and own.dtype == np.uint8
                errs = [float(np.abs(own - to_output(img, shift))[bg].mean()) for shift in (0.0, 1.0, -1.0)]
                err_wrong = float(np.abs(wrong - to_output(img))[bg].mean())
                assert errs[0] < 1.0 and min(errs[1:]) > 4 * errs[0] and err_wrong > 10 * errs[0], (view, f, errs)
                checked += 1
    assert checked >= 4
    # beyond the full frame the crop is black, as the dataset's crops are: output column j shows
    # full-image x = j / k + (cx - side / 2), and the frame's last pixel centre is W - 1
    W = root.sequence("s01", root.sequences("s01")[0].split("/", 1)[1]).cameras[1].width
    box = np.array([W - 1.0, 300.0, 2.0])
    edge = src.camera_plate("s01", 1, box, 64)
    k = 64 / (1.5 * 200.0 * 2.0)
    last = int(np.floor((W - 0.5 - (box[0] - 300.0)) * k))  # the last column whose centre is inside the frame
    assert edge[:, last + 1 :].max() == 0 and edge[:, last].min() > 0


def test_camera_plates_refuse_folders_without_a_manifest(plates, tmp_path) -> None:
    from hogsa_loader.compose import PlateBackgrounds, make_backgrounds
    from hogsa_loader.errors import AssetError

    cfg, _ = plates
    for p in Path(cfg.out).glob("*.png"):
        shutil.copy(p, tmp_path / p.name)
    with pytest.raises(AssetError, match="plates.json"):
        PlateBackgrounds(tmp_path)
    manifest = json.loads((Path(cfg.out) / "plates.json").read_text())
    manifest["plates"][0]["file"] = "gone.png"
    (tmp_path / "plates.json").write_text(json.dumps(manifest))
    with pytest.raises(AssetError, match="gone.png"):
        PlateBackgrounds(tmp_path)
    del manifest["plates"][0]["full_size"]
    manifest["plates"][0]["file"] = manifest["plates"][1]["file"]
    (tmp_path / "plates.json").write_text(json.dumps(manifest))
    with pytest.raises(AssetError, match="not a plate manifest"):
        PlateBackgrounds(tmp_path)
    with pytest.raises(ValueError, match="camera_plates"):
        make_backgrounds(coco_root=tmp_path, camera_plates=True)
    assert isinstance(make_backgrounds(folder=cfg.out, camera_plates=True), PlateBackgrounds)
