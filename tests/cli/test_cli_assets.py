"""`hogsa` command line: version, assets folder layout, previews, converter."""

from __future__ import annotations

import subprocess
import sys

import numpy as np

from hogsa_loader import __version__
from hogsa_loader.assets.hands.mano import MANOLayer
from hogsa_loader.assets.hands.mano_io import load_mano
from hogsa_loader.assets.objects import load_object_template
from hogsa_loader.cli.main import main


def test_version_entry_point():
    out = subprocess.run([sys.executable, "-m", "hogsa_loader.cli.main", "--version"], capture_output=True, text=True)
    assert out.returncode == 0 and __version__ in out.stdout


def test_assets_writes_a_usable_arctic_style_tree(tmp_path):
    assert main(["assets", "--out", str(tmp_path), "--no-preview", "--quiet", "--objects", "box,laptop"]) == 0
    mano = tmp_path / "body_models" / "mano"
    right = load_mano(mano / "MANO_RIGHT.pkl")
    left = load_mano(mano / "MANO_LEFT.pkl")
    assert right.side == "right" and left.side == "left" and right.num_verts == left.num_verts
    assert MANOLayer(mano, side="left")().joints.shape == (1, 21, 3)
    for name in ("box", "laptop"):
        folder = tmp_path / "arctic_data" / "data" / "meta" / "object_vtemplates" / name
        for f in (
            "mesh.obj",
            "parts.json",
            "object_params.json",
            "top_keypoints_300.json",
            "bottom_keypoints_300.json",
        ):
            assert (folder / f).is_file(), f
        assert load_object_template(folder).name == name


def test_convert_mano_cli(tmp_path, mano_dir, capsys):
    assert main(["convert-mano", str(mano_dir / "MANO_LEFT.pkl"), str(tmp_path / "MANO_LEFT.npz")]) == 0
    assert "left hand" in capsys.readouterr().out
    assert load_mano(tmp_path / "MANO_LEFT.npz").side == "left"


def test_cli_reports_bad_input_without_traceback(tmp_path, capsys):
    bad = tmp_path / "MANO_RIGHT.pkl"
    bad.write_bytes(b"not a pickle")
    assert main(["convert-mano", str(bad), str(tmp_path / "x.npz")]) == 1
    err = capsys.readouterr().err
    assert str(bad) in err and "Traceback" not in err


def test_hand_preview_shows_mirrored_hands(hand_pair):
    from hogsa_loader.view.preview import _BG, hand_preview

    sheet = hand_preview(*hand_pair, poses=("flat",), size=96)
    assert sheet.shape == (192, 96, 3)
    fg = np.abs(sheet - np.asarray(_BG)).max(-1) > 0.05
    fg[:24] = False  # the label
    fg[96:120] = False
    right, left = fg[:96], fg[96:]
    assert 0.08 < right.mean() < 0.6  # a hand fills a good part of the cell
    flipped = left[:, ::-1]
    iou = (right & flipped).sum() / (right | flipped).sum()
    assert iou > 0.9, iou  # left view is the mirror image of the right view
