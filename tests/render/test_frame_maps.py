"""Depth maps, part masks and intrinsics of the dataset's cropped images (``hogsa frame-maps``):
the masks equal the generated world's mask files, depth and parts equal ray casts through the
same pixels (Möller-Trumbore, written here), the resized maps' intrinsics follow ``cv2.resize``'s pixel grid."""

from __future__ import annotations

import json
import subprocess
import sys

import cv2
import numpy as np
import pytest

from hogsa_loader.assets.arctic import ArcticRoot
from hogsa_loader.render.frame_maps import DEPTH_PNG_METRES, cropped_cameras, render_frame_maps
from hogsa_loader.render.part_masks import pose_meshes


@pytest.fixture(scope="module")
def seq(tiny_world):
    root = ArcticRoot(tiny_world)
    return root, root.sequence("s01", "box_use_01")


def test_masks_equal_the_worlds_mask_files(seq):
    root, s = seq
    for view in (1, 4, 7):
        for m in render_frame_maps(root, s, view, [5, 25]):
            ref = cv2.imread(str(s.mask_paths[view][m.frame]), cv2.IMREAD_UNCHANGED)
            assert m.mask.shape == ref.shape and np.array_equal(m.mask, ref), (view, m.frame)
            assert ((m.depth > 0) == (m.mask > 0)).all()


def _ray_cast(dirs: np.ndarray, tris: np.ndarray) -> np.ndarray:
    """(R,) camera-space z of the nearest hit of rays from the origin along ``dirs`` (R, 3)
    with the triangles ``tris`` (T, 3, 3) (Möller-Trumbore), inf where none is hit."""
    a, e1, e2 = tris[:, 0], tris[:, 1] - tris[:, 0], tris[:, 2] - tris[:, 0]
    out = np.full(len(dirs), np.inf)
    for r, d in enumerate(dirs):
        p = np.cross(d, e2)
        det = np.einsum("ij,ij->i", e1, p)
        ok = np.abs(det) > 1e-12
        inv = np.where(ok, 1.0 / np.where(ok, det, 1.0), 0.0)
        tv = -a
        u = np.einsum("ij,ij->i", tv, p) * inv
        q = np.cross(tv, e1)
        v = (q @ d) * inv
        dist = np.einsum("ij,ij->i", e2, q) * inv
        hit = ok & (u >= 0) & (v >= 0) & (u + v <= 1) & (dist > 0)
        if hit.any():
            out[r] = (dist[hit] * d[2]).min()
    return out


def test_depth_and_parts_equal_ray_casts_through_the_pixel_centres(seq):
    root, s = seq
    view, frame = 3, 30
    (m,) = render_frame_maps(root, s, view, [frame])
    posed = pose_meshes(s, [frame], root.mano_layers(), root.object_templates()[s.object.name])
    R, t = m.world2cam[:3, :3], m.world2cam[:3, 3]
    meshes = [(pid, v[0].double().numpy() @ R.T + t, f.numpy()) for pid, v, f in posed.meshes]
    rng = np.random.default_rng(0)
    fg = np.argwhere(m.mask > 0)
    pix = np.concatenate([fg[rng.choice(len(fg), 150, replace=False)], rng.integers(0, m.mask.shape[0], (50, 2))])
    # pixel (row y, column x) shows the ray of label coordinate (x, y): K⁻¹ (x, y, 1)
    dirs = np.stack([pix[:, 1], pix[:, 0], np.ones(len(pix))], 1) @ np.linalg.inv(m.K).T
    best_z = np.full(len(pix), np.inf)
    best_id = np.zeros(len(pix), np.uint8)
    for pid, verts, faces in meshes:
        z = _ray_cast(dirs, verts[faces])
        closer = z < best_z
        best_z[closer], best_id[closer] = z[closer], pid
    got_z, got_id = m.depth[pix[:, 0], pix[:, 1]], m.mask[pix[:, 0], pix[:, 1]]
    hit = np.isfinite(best_z)
    assert np.mean(got_id == best_id) >= 0.98  # (a ray grazing a triangle edge may fall either side)
    same = hit & (got_id == best_id) & (got_id > 0)
    assert same.sum() >= 140 and np.abs(got_z[same] - best_z[same]).max() < 1e-4  # metres
    assert (got_z[~hit] == 0).all()


def test_resized_maps_have_the_intrinsics_of_the_resized_crop(seq):
    root, s = seq
    K, w2c, crop = cropped_cameras(root, s, 2)
    assert K.shape == (s.num_frames, 3, 3) and w2c.shape == (s.num_frames, 4, 4)
    (m,) = render_frame_maps(root, s, 2, [10], size=crop // 2)
    assert m.mask.shape == (crop // 2, crop // 2)
    pts = np.array([[0.01, 0.02, 1.0], [-0.05, 0.03, 1.3]])
    full = pts @ K[10].T
    half = pts @ m.K.T
    full, half = full[:, :2] / full[:, 2:], half[:, :2] / half[:, 2:]
    assert np.allclose(half, (full + 0.5) * 0.5 - 0.5)  # cv2.resize's map of pixel centres
    assert np.mean(m.mask > 0) == pytest.approx(np.mean(render_frame_maps(root, s, 2, [10])[0].mask > 0), abs=0.01)
    with pytest.raises(ValueError, match="egocentric"):
        cropped_cameras(root, s, 0)


def test_the_command_writes_depth_masks_and_cameras_and_resumes(tiny_world, tmp_path):
    argv = [sys.executable, "-m", "hogsa_loader.cli.main", "frame-maps", "--data", str(tiny_world)]
    argv += ["--out", str(tmp_path / "maps"), "--subjects", "s01", "--views", "2", "--frame-stride", "20"]
    first = subprocess.run(argv, capture_output=True, text=True, timeout=600)
    assert first.returncode == 0, first.stderr[-3000:]
    folder = tmp_path / "maps" / "s01" / "box_use_01" / "2"
    with np.load(folder / "cameras.npz", allow_pickle=False) as cams:
        frames, names, K = cams["frames"].tolist(), cams["names"].tolist(), cams["K"]
    root = ArcticRoot(tiny_world)
    s = root.sequence("s01", "box_use_01")
    assert frames == list(range(0, s.num_frames, 20)) and names == [s.image_paths[2][f].stem for f in frames]
    maps = render_frame_maps(root, s, 2, frames)
    for m, name, k in zip(maps, names, K):
        depth = cv2.imread(str(folder / f"{name}_depth.png"), cv2.IMREAD_UNCHANGED)
        assert (
            depth.dtype == np.uint16 and np.abs(depth * DEPTH_PNG_METRES - m.depth).max() <= DEPTH_PNG_METRES / 2 + 1e-6
        )
        assert np.array_equal(cv2.imread(str(folder / f"{name}_mask.png"), cv2.IMREAD_UNCHANGED), m.mask)
        assert np.array_equal(k, m.K)
    manifest = json.loads((tmp_path / "maps" / "maps.json").read_text())
    assert manifest["views"] == ["s01/box_use_01/2"] and manifest["mask_ids"]["right"] == 1
    assert (tmp_path / "maps" / "preview.png").is_file()
    again = subprocess.run(argv, capture_output=True, text=True, timeout=600)
    assert again.returncode == 0 and "(0 frames written now)" in again.stdout
    other = subprocess.run([*argv, "--size", "100"], capture_output=True, text=True, timeout=600)
    assert other.returncode == 2 and "written with --size 0 --frame-stride 20" in other.stderr
    ego = subprocess.run(argv[:-4] + ["--views", "0"], capture_output=True, text=True, timeout=600)
    assert ego.returncode == 2 and "allocentric" in ego.stderr
