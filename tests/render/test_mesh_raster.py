"""Tests of the classical mesh rasteriser (hogsa_loader.render.mesh_raster).

Expected values come from independent numpy computations (point-in-triangle tests, ray /
plane intersections, analytic pixel counts), not from the module under test. Every test
runs on both backends (the vectorised PyTorch path and the compiled CPU kernels).
"""

from __future__ import annotations

import functools
import math

import cv2
import numpy as np
import pytest
import torch
import trimesh

import hogsa_loader.render.mesh_raster as mr
from hogsa_loader.render.mesh_raster import (
    Light,
    MeshPart,
    camera_look_at,
    intrinsics_from_fov,
    project_points,
    rasterize,
    render_meshes,
    save_png,
    scale_intrinsics,
    transform_points,
)

# A camera with skew and non-square pixels, used by the single-triangle tests.
K_SKEW = np.array([[40.0, 3.0, 17.3], [0.0, 37.0, 14.1], [0.0, 0.0, 1.0]])
IDENTITY = torch.eye(4)


def _np_project(points: np.ndarray, K: np.ndarray) -> np.ndarray:
    """(N, 3) camera points -> (N, 2) pixels, straight from the pinhole formula."""
    h = points @ K.T
    return h[:, :2] / h[:, 2:3]


def _np_inside(tri_uv: np.ndarray, height: int, width: int) -> tuple[np.ndarray, np.ndarray]:
    """Brute-force strict point-in-triangle test of every pixel centre.

    Returns:
        (H, W) bool inside mask and (H, W) distance (px) of each centre to the nearest edge
        line, to check that no centre is ambiguous.
    """
    jj, ii = np.meshgrid(np.arange(width) + 0.5, np.arange(height) + 0.5)
    signs, dists = [], []
    for k in range(3):
        a, b = tri_uv[k], tri_uv[(k + 1) % 3]
        cross = (b[0] - a[0]) * (ii - a[1]) - (b[1] - a[1]) * (jj - a[0])
        signs.append(np.sign(cross))
        dists.append(np.abs(cross) / np.linalg.norm(b - a))
    signs = np.stack(signs)
    inside = np.all(signs > 0, axis=0) | np.all(signs < 0, axis=0)
    return inside, np.min(np.stack(dists), axis=0)


def _plane_depth(tri_cam: np.ndarray, K: np.ndarray, height: int, width: int) -> np.ndarray:
    """(H, W) z of the intersection of each pixel-centre ray with the triangle's plane."""
    n = np.cross(tri_cam[1] - tri_cam[0], tri_cam[2] - tri_cam[0])
    d = n @ tri_cam[0]
    jj, ii = np.meshgrid(np.arange(width) + 0.5, np.arange(height) + 0.5)
    pix = np.stack([jj, ii, np.ones_like(jj)], axis=-1)
    rays = pix @ np.linalg.inv(K).T  # z component is 1
    return d / (rays @ n)


def _tilted_triangle() -> np.ndarray:
    return np.array([[-0.31, -0.27, 1.1], [0.42, -0.05, 2.3], [-0.07, 0.36, 1.6]])


def _t(x: np.ndarray, dtype: torch.dtype = torch.float32) -> torch.Tensor:
    return torch.tensor(x, dtype=dtype)


@pytest.fixture(autouse=True, params=["torch", "numba"])
def backend(request: pytest.FixtureRequest, monkeypatch: pytest.MonkeyPatch) -> str:
    """Run the test with ``rasterize`` and ``render_meshes`` bound to one backend."""
    for name in ("rasterize", "render_meshes"):
        monkeypatch.setitem(globals(), name, functools.partial(getattr(mr, name), backend=request.param))
    return request.param


# --------------------------------------------------------------------------------------
# Rasterisation
# --------------------------------------------------------------------------------------


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_single_triangle_matches_brute_force_and_plane_depth(dtype: torch.dtype) -> None:
    H, W = 30, 36
    tri = _tilted_triangle()
    frags = rasterize(_t(tri, dtype), torch.tensor([[0, 1, 2]]), _t(K_SKEW, dtype), H, W)
    inside, dist = _np_inside(_np_project(tri, K_SKEW), H, W)
    assert dist.min() > 1e-4  # no pixel centre is ambiguous, the tie rule plays no role
    assert inside.sum() > 50
    got = frags.face_idx.numpy()
    np.testing.assert_array_equal(got == 0, inside)
    assert set(np.unique(got)) == {-1, 0}
    depth = frags.depth.numpy()
    np.testing.assert_allclose(depth[inside], _plane_depth(tri, K_SKEW, H, W)[inside], rtol=0, atol=1e-5)
    assert np.isinf(depth[~inside]).all() and (depth[~inside] > 0).all()
    assert (frags.bary.numpy()[~inside] == 0).all()


def test_chunking_does_not_change_the_result() -> None:
    H, W = 30, 36
    tri = _tilted_triangle()
    verts = _t(np.concatenate([tri, tri * [1.1, 0.9, 1.2]]))
    faces = torch.tensor([[0, 1, 2], [3, 5, 4]])
    K = _t(K_SKEW)
    ref = rasterize(verts, faces, K, H, W)
    for max_pairs in (1, 7, 100):  # forces many chunks and row bands inside one face
        out = rasterize(verts, faces, K, H, W, max_pairs=max_pairs)
        assert torch.equal(out.face_idx, ref.face_idx)
        assert torch.equal(out.depth, ref.depth)
        assert torch.equal(out.bary, ref.bary)


def _fronto_quad(u0: float, u1: float, v0: float, v1: float, z: float, K: np.ndarray) -> np.ndarray:
    """(4, 3) camera points projecting to the image rectangle [u0, u1] x [v0, v1]."""
    uv = np.array([[u0, v0], [u1, v0], [u1, v1], [u0, v1]])
    xy = (uv - K[:2, 2]) / np.diag(K)[:2] * z
    return np.concatenate([xy, np.full((4, 1), z)], axis=1)


def test_nearest_triangle_wins_regardless_of_order() -> None:
    K = np.array([[20.0, 0, 16], [0, 20.0, 16], [0, 0, 1]])
    near = _fronto_quad(3.3, 20.7, 4.2, 22.9, 1.0, K)[:3]
    far = _fronto_quad(9.1, 29.6, 8.4, 27.3, 2.0, K)[[0, 2, 3]]
    verts = _t(np.concatenate([near, far]))
    a = rasterize(verts, torch.tensor([[0, 1, 2], [3, 4, 5]]), _t(K), 32, 32)
    b = rasterize(verts, torch.tensor([[3, 4, 5], [0, 1, 2]]), _t(K), 32, 32)
    in_near, _ = _np_inside(_np_project(near, K), 32, 32)
    in_far, _ = _np_inside(_np_project(far, K), 32, 32)
    overlap = in_near & in_far
    assert overlap.sum() > 20
    # Same surface in both orders: the near triangle is face 0 in a, face 1 in b.
    assert torch.equal(a.depth, b.depth)
    assert torch.equal(a.face_idx == 0, b.face_idx == 1)
    assert torch.equal(a.face_idx == 1, b.face_idx == 0)
    np.testing.assert_allclose(a.depth.numpy()[overlap], 1.0, atol=1e-6)
    assert (a.face_idx.numpy()[overlap] == 0).all()
    assert (b.face_idx.numpy()[overlap] == 1).all()
    np.testing.assert_allclose(a.depth.numpy()[in_far & ~in_near], 2.0, atol=1e-6)


def test_exact_depth_tie_goes_to_lowest_face_index() -> None:
    tri = _tilted_triangle()
    verts = _t(np.concatenate([tri, tri]))
    for faces in ([[0, 1, 2], [3, 4, 5]], [[3, 5, 4], [0, 2, 1]]):
        out = rasterize(verts, torch.tensor(faces), _t(K_SKEW), 30, 36)
        covered = out.face_idx >= 0
        assert covered.sum() > 50
        assert (out.face_idx[covered] == 0).all()


def _coverage_count(verts: torch.Tensor, faces: torch.Tensor, K: torch.Tensor, H: int, W: int) -> np.ndarray:
    """(H, W) number of faces covering each pixel, rasterising every face on its own."""
    count = np.zeros((H, W), dtype=np.int64)
    for f in faces:
        count += rasterize(verts, f[None], K, H, W).face_idx.numpy() == 0
    return count


def _rect_mask(u0: float, u1: float, v0: float, v1: float, H: int, W: int) -> np.ndarray:
    """Pixels whose centre lies strictly inside [u0, u1] x [v0, v1]."""
    jj, ii = np.meshgrid(np.arange(W) + 0.5, np.arange(H) + 0.5)
    return (jj > u0) & (jj < u1) & (ii > v0) & (ii < v1)


@pytest.mark.parametrize("diagonal", ["through_centres", "generic"])
def test_quad_split_has_no_cracks_and_no_double_coverage(diagonal: str) -> None:
    H, W = 24, 28
    K = np.array([[30.0, 0, 14], [0, 30.0, 12], [0, 0, 1]])
    # through_centres: the diagonal u - v = 0 runs exactly through pixel centres.
    rect = (2.0, 14.0, 2.0, 14.0) if diagonal == "through_centres" else (2.3, 25.6, 3.1, 20.8)
    quad = _fronto_quad(*rect, z=1.0, K=K)
    for faces in ([[0, 1, 2], [0, 2, 3]], [[0, 2, 1], [0, 2, 3]]):  # also mixed winding
        count = _coverage_count(_t(quad), torch.tensor(faces), _t(K), H, W)
        expected = _rect_mask(*rect, H, W)
        n_cols = sum(1 for j in range(W) if rect[0] < j + 0.5 < rect[1])
        n_rows = sum(1 for i in range(H) if rect[2] < i + 0.5 < rect[3])
        assert expected.sum() == n_cols * n_rows
        assert count.max() == 1
        np.testing.assert_array_equal(count, expected.astype(np.int64))
        full = rasterize(_t(quad), torch.tensor(faces), _t(K), H, W)
        np.testing.assert_array_equal(full.face_idx.numpy() >= 0, expected)


def test_perspective_mesh_is_watertight() -> None:
    """A jittered, perspective-projected grid with random winding tiles its square exactly."""
    rng = np.random.default_rng(0)
    H, W, n = 32, 32, 6
    K = np.array([[25.0, 0, 16], [0, 25.0, 16], [0, 0, 1]])
    lo, hi = 3.25, 28.75
    g = np.linspace(lo, hi, n + 1)
    uu, vv = np.meshgrid(g, g)
    interior = np.zeros_like(uu, dtype=bool)
    interior[1:-1, 1:-1] = True
    uu[interior] += rng.uniform(-1.2, 1.2, interior.sum())
    vv[interior] += rng.uniform(-1.2, 1.2, interior.sum())
    # Some interior vertices on pixel centres, so edges pass exactly through centres.
    uu[2, 2], vv[2, 2] = 10.5, 10.5
    uu[4, 3], vv[4, 3] = 15.5, 20.5
    z = np.where(interior, rng.uniform(0.8, 1.6, uu.shape), 1.0)
    uv = np.stack([uu.ravel(), vv.ravel()], axis=1)
    xy = (uv - K[:2, 2]) / np.diag(K)[:2] * z.ravel()[:, None]
    verts = _t(np.concatenate([xy, z.ravel()[:, None]], axis=1))
    faces = []
    for r in range(n):
        for c in range(n):
            a, b, d, e = r * (n + 1) + c, r * (n + 1) + c + 1, (r + 1) * (n + 1) + c, (r + 1) * (n + 1) + c + 1
            for f in ([a, b, e], [a, e, d]):
                faces.append(f if rng.random() < 0.5 else f[::-1])
    count = _coverage_count(verts, torch.tensor(faces), _t(K), H, W)
    np.testing.assert_array_equal(count, _rect_mask(lo, hi, lo, hi, H, W).astype(np.int64))


def test_shared_edges_through_centres_with_rounded_vertices() -> None:
    """Edges that pass (mathematically) through pixel centres, with float32-rounded ends.

    Each of 64 cells holds two triangles sharing an edge P-Q on the line through two
    pixel centres C0, C1; P and Q are not representable, so the rounded edge passes within
    ~1e-6 px of the centres. Exactly one triangle must own every such centre.
    """
    rng = np.random.default_rng(1)
    H = W = 64
    K = torch.eye(3)  # with z = 1, (u, v) = (x, y)
    left, right, on_edge = [], [], []
    for ci in range(8):
        for cj in range(8):
            c0 = np.array([8 * cj + 1.5, 8 * ci + 1.5]) + rng.integers(0, 2, 2)
            d = rng.integers(1, 4, 2) * rng.choice([-1, 1], 2)
            c0 = np.where(d < 0, c0 + 3, c0)
            c1 = c0 + d
            p = c0 - rng.uniform(0.05, 0.3) * d
            q = c1 + rng.uniform(0.05, 0.3) * d
            perp = np.array([-d[1], d[0]]) / np.linalg.norm(d)
            mid = (p + q) / 2
            left.append([p, q, mid + 2.0 * perp])
            right.append([q, p, mid - 2.0 * perp])
            on_edge += [c0, c1]
    count = np.zeros((H, W), dtype=np.int64)
    for tris in (left, right):
        uv = np.asarray(tris).reshape(-1, 2)
        verts = torch.tensor(np.concatenate([uv, np.ones((len(uv), 1))], 1), dtype=torch.float32)
        faces = torch.arange(len(uv)).reshape(-1, 3)
        count += rasterize(verts, faces, K, H, W).face_idx.numpy() >= 0
    assert count.max() == 1
    cols, rows = np.asarray(on_edge).T.astype(np.int64)
    assert (count[rows, cols] == 1).all()


def test_barycentrics_are_perspective_correct() -> None:
    H, W = 30, 36
    tri = _tilted_triangle()
    frags = rasterize(_t(tri), torch.tensor([[0, 1, 2]]), _t(K_SKEW), H, W)
    mask = frags.face_idx.numpy() == 0
    bary = frags.bary.numpy()[mask].astype(np.float64)  # (N, 3)
    assert mask.sum() > 50
    np.testing.assert_allclose(bary.sum(-1), 1.0, atol=1e-6)
    assert (bary >= 0).all()
    points = bary @ tri  # (N, 3) camera-space surface points
    ii, jj = np.nonzero(mask)
    np.testing.assert_allclose(_np_project(points, K_SKEW), np.stack([jj + 0.5, ii + 0.5], 1), rtol=0, atol=1e-4)
    n = np.cross(tri[1] - tri[0], tri[2] - tri[0])
    n /= np.linalg.norm(n)
    np.testing.assert_allclose((points - tri[0]) @ n, 0.0, atol=1e-6)
    np.testing.assert_allclose(frags.depth.numpy()[mask], points[:, 2], atol=1e-5)


def test_near_plane_drops_triangles() -> None:
    K = _t(np.array([[20.0, 0, 16], [0, 20.0, 16], [0, 0, 1]]))
    faces = torch.tensor([[0, 1, 2]])
    in_front = torch.tensor([[-0.5, -0.5, 1.0], [0.5, -0.5, 1.0], [0.0, 0.5, 1.0]])
    assert (rasterize(in_front, faces, K, 32, 32).face_idx == 0).sum() > 50
    behind = in_front * torch.tensor([1.0, 1.0, -1.0])  # would project onto the image
    assert (rasterize(behind, faces, K, 32, 32).face_idx == -1).all()
    straddling = in_front.clone()
    straddling[2, 2] = -0.5
    assert (rasterize(straddling, faces, K, 32, 32).face_idx == -1).all()
    at_near = in_front.clone()
    at_near[2, 2] = 0.1
    assert (rasterize(at_near, faces, K, 32, 32, near=0.1).face_idx == -1).all()
    assert (rasterize(at_near, faces, K, 32, 32, near=0.05).face_idx == 0).any()


def test_backface_culling_option() -> None:
    K = _t(np.array([[20.0, 0, 16], [0, 20.0, 16], [0, 0, 1]]))
    # Seen from the camera (x right, y down): right then up, i.e. counter-clockwise.
    verts = torch.tensor([[-0.5, 0.5, 1.0], [0.5, 0.5, 1.0], [0.0, -0.5, 1.0]])
    front, back = torch.tensor([[0, 1, 2]]), torch.tensor([[0, 2, 1]])
    for faces in (front, back):
        assert (rasterize(verts, faces, K, 32, 32).face_idx == 0).sum() > 50
    assert (rasterize(verts, front, K, 32, 32, cull_backfaces=True).face_idx == 0).sum() > 50
    assert (rasterize(verts, back, K, 32, 32, cull_backfaces=True).face_idx == -1).all()


def test_empty_and_offscreen_meshes() -> None:
    K = _t(np.array([[20.0, 0, 16], [0, 20.0, 16], [0, 0, 1]]))
    empty = rasterize(torch.zeros(0, 3), torch.zeros(0, 3, dtype=torch.int64), K, 8, 8)
    assert (empty.face_idx == -1).all() and torch.isinf(empty.depth).all()
    off = torch.tensor([[5.0, 5.0, 1.0], [6.0, 5.0, 1.0], [5.0, 6.0, 1.0]])
    assert (rasterize(off, torch.tensor([[0, 1, 2]]), K, 8, 8).face_idx == -1).all()


# --------------------------------------------------------------------------------------
# Rendering
# --------------------------------------------------------------------------------------

FLAT = Light(ambient=1.0, diffuse=0.0, specular=0.0)


def test_textured_quad_reproduces_checkerboard() -> None:
    S = 64  # image and texture size; one texel per pixel
    K = torch.tensor([[S, 0.0, S / 2], [0.0, S, S / 2], [0.0, 0.0, 1.0]])
    verts = torch.tensor([[-0.5, -0.5, 1.0], [0.5, -0.5, 1.0], [0.5, 0.5, 1.0], [-0.5, 0.5, 1.0]])
    # OBJ uv: v = 1 is the top row of the texture image; image top is camera -y.
    uv = torch.tensor([[0.0, 1.0], [1.0, 1.0], [1.0, 0.0], [0.0, 0.0]])
    ii, jj = np.meshgrid(np.arange(S), np.arange(S), indexing="ij")
    checker = ((ii // 8 + jj // 8) % 2).astype(np.float32)
    tex = np.stack([checker, 0.2 * np.ones_like(checker), 1.0 - checker], -1)
    tex[:8, :8] = [0.0, 1.0, 0.0]  # marks the top-left square: catches flips / transposes
    part = MeshPart(
        verts=verts, faces=torch.tensor([[0, 1, 2], [0, 2, 3]]), part_id=3, uv=uv, texture=torch.tensor(tex)
    )
    out = render_meshes([part], IDENTITY, K, S, S, light=FLAT)
    assert (out.alpha == 1).all() and (out.part_id == 3).all()
    np.testing.assert_allclose(out.rgb.numpy(), tex, atol=1e-5)


def _sphere_part(albedo: tuple[float, float, float], subdivisions: int = 3) -> MeshPart:
    s = trimesh.creation.icosphere(subdivisions=subdivisions, radius=1.0)
    verts = torch.tensor(s.vertices, dtype=torch.float32)
    colours = torch.tensor(albedo).expand(verts.shape[0], 3).clone()
    return MeshPart(verts=verts, faces=torch.tensor(s.faces), part_id=1, vertex_colors=colours)


def _sphere_camera(size: int) -> tuple[torch.Tensor, torch.Tensor]:
    return camera_look_at((0.0, 0.0, -4.0), (0.0, 0.0, 0.0), (0.0, 1.0, 0.0)), intrinsics_from_fov(40.0, size, size)


def test_sphere_headlight_is_brightest_at_centre() -> None:
    size = 64
    w2c, K = _sphere_camera(size)
    out = render_meshes([_sphere_part((0.8, 0.8, 0.8))], w2c, K, size, size)
    lum = out.rgb.mean(-1).numpy()
    covered = out.alpha.numpy() > 0
    assert covered[size // 2].sum() > 20
    row = lum[size // 2, size // 2 :][covered[size // 2, size // 2 :]]  # centre -> silhouette
    # Centre: n = l = v, so ambient + diffuse + specular = 0.8 * (0.35 + 0.65) + 0.1.
    assert row[0] == pytest.approx(0.9, abs=0.02)
    assert lum[covered].max() == pytest.approx(row[0], abs=0.02)
    assert (np.diff(row) <= 1e-3).all()
    assert row[-1] < 0.6 * row[0]
    normal = out.normal.numpy()
    np.testing.assert_allclose(np.linalg.norm(normal[covered], axis=-1), 1.0, atol=1e-5)
    assert (normal[covered][:, 2] < 0).all()  # facing the camera
    assert (normal[~covered] == 0).all()


def test_sphere_side_light_and_ambient_only() -> None:
    size = 48
    w2c, K = _sphere_camera(size)
    albedo = (0.8, 0.5, 0.2)
    bg = (0.1, 0.2, 0.3)
    part = _sphere_part(albedo, subdivisions=2)
    flat = render_meshes([part], w2c, K, size, size, light=Light(ambient=0.4, diffuse=0.0, specular=0.0), background=bg)
    covered = flat.alpha.numpy() == 1
    np.testing.assert_allclose(
        flat.rgb.numpy()[covered], np.tile(0.4 * np.array(albedo), (covered.sum(), 1)), atol=1e-6
    )
    np.testing.assert_allclose(flat.rgb.numpy()[~covered], np.tile(bg, ((~covered).sum(), 1)), atol=1e-6)
    # Light travelling along +x (camera right) comes from the left: left half brighter.
    side = render_meshes([part], w2c, K, size, size, light=Light(direction=(1.0, 0.0, 0.0)))
    rgb = side.rgb.numpy()
    left = rgb[:, : size // 2][covered[:, : size // 2]]
    right = rgb[:, size // 2 + 3 :][covered[:, size // 2 + 3 :]]
    # Right of the centre the surface faces away from the light: ambient only.
    np.testing.assert_allclose(right, np.tile(0.35 * np.array(albedo), (len(right), 1)), atol=1e-6)
    # Toward the left limb the normal turns to the light: close to the full albedo.
    assert left[:, 0].max() > 0.95 * albedo[0]
    assert left[:, 0].mean() > right[:, 0].mean() + 0.1


def test_flat_normals_are_face_normals() -> None:
    K = torch.tensor([[30.0, 0, 16], [0, 30.0, 16], [0, 0, 1]])
    # A tilted plane (two triangles) seen from its back side: normals are flipped to face us.
    verts = torch.tensor([[-1.0, -1.0, 2.0], [1.0, -1.0, 3.0], [1.0, 1.0, 3.0], [-1.0, 1.0, 2.0]])
    part = MeshPart(verts=verts, faces=torch.tensor([[0, 1, 2], [0, 2, 3]]), part_id=1, vertex_colors=torch.ones(4, 3))
    for smooth in (True, False):
        out = render_meshes([part], IDENTITY, K, 32, 32, smooth_normals=smooth)
        n = out.normal.numpy()[out.alpha.numpy() > 0]
        expected = np.array([1.0, 0.0, -2.0]) / math.sqrt(5.0)  # plane x - 2 z = -5
        np.testing.assert_allclose(n, np.tile(expected, (len(n), 1)), atol=1e-5)


def test_supersampled_edge_alpha_is_exact_fraction() -> None:
    H, W, s = 12, 16, 4
    K = torch.tensor([[20.0, 0, 8], [0, 20.0, 6], [0, 0, 1]], dtype=torch.float64)
    # Half-plane u < 6.3 + 0.37 (v - 0) as a big triangle pair on z = 1 (left part covered).
    top, bottom = (6.3, -2.0), (6.3 + 0.37 * (H + 4.0), H + 2.0)
    corners = np.array([[-5.0, -2.0], top, bottom, [-5.0, H + 2.0]])
    xy = (corners - [8.0, 6.0]) / 20.0
    verts = torch.tensor(np.concatenate([xy, np.ones((4, 1))], 1), dtype=torch.float64)
    colour = np.array([0.9, 0.6, 0.3])
    part = MeshPart(
        verts=verts,
        faces=torch.tensor([[0, 1, 2], [0, 2, 3]]),
        part_id=1,
        vertex_colors=torch.tensor(colour).expand(4, 3).clone(),
    )
    bg = np.array([0.0, 0.1, 0.2])
    out = render_meshes([part], IDENTITY.double(), K, H, W, light=FLAT, background=tuple(bg), supersample=s)
    # Expected alpha: fraction of the s x s sample centres left of the line.
    off = (np.arange(s) + 0.5) / s
    expected = np.zeros((H, W))
    for i in range(H):
        for j in range(W):
            su, sv = np.meshgrid(j + off, i + off)
            line_u = top[0] + (sv - top[1]) * (bottom[0] - top[0]) / (bottom[1] - top[1])
            expected[i, j] = np.mean(su < line_u)
    alpha = out.alpha.numpy()
    np.testing.assert_allclose(alpha, expected, atol=1e-12)
    frac = (alpha > 0) & (alpha < 1)
    assert frac.any(axis=1).all()  # every row has a fractional edge pixel
    assert frac.sum() <= 2 * H  # ... and only along the edge
    np.testing.assert_allclose(out.rgb.numpy(), alpha[..., None] * colour + (1 - alpha[..., None]) * bg, atol=1e-9)


def test_supersampling_keeps_projection_and_takes_nearest_sample() -> None:
    K = torch.tensor([[31.0, 1.5, 13.7], [0.0, 29.0, 9.2], [0.0, 0.0, 1.0]])
    p = torch.tensor([[0.13, -0.21, 1.7], [-0.4, 0.3, 0.9]])
    for s in (2, 3):
        np.testing.assert_allclose(
            project_points(p, scale_intrinsics(K, s)).numpy(), s * project_points(p, K).numpy(), rtol=1e-6
        )
    # Near part 1 covers u < 10.5 (mid-pixel), far part 2 covers everything.
    H, W = 8, 20
    Kr = torch.tensor([[10.0, 0, 10], [0, 10.0, 4], [0, 0, 1]])

    def quad(u0: float, u1: float, z: float) -> torch.Tensor:
        return torch.tensor(_fronto_quad(u0, u1, -5.0, 15.0, z, Kr.numpy()), dtype=torch.float32)

    faces = torch.tensor([[0, 1, 2], [0, 2, 3]])
    white = torch.ones(4, 3)
    parts = [
        MeshPart(quad(-5.0, 10.5, 1.0), faces, 1, vertex_colors=white),
        MeshPart(quad(-5.0, 25.0, 3.0), faces, 2, vertex_colors=white),
    ]
    for s in (1, 2):
        out = render_meshes(parts, IDENTITY, Kr, H, W, supersample=s)
        # Column 10 spans u in [10, 11): at s=1 its centre 10.5 is on the edge (top-left
        # rule: not in part 1, whose interior is to the left); at s=2 sample 10.25 is.
        expect_col10 = (2, 3.0) if s == 1 else (1, 1.0)
        assert (out.part_id[:, :10] == 1).all() and (out.part_id[:, 11:] == 2).all()
        assert (out.part_id[:, 10] == expect_col10[0]).all()
        torch.testing.assert_close(out.depth[:, 10], torch.full((H,), expect_col10[1]))
        assert (out.alpha == 1).all()


def test_camera_look_at_and_fov() -> None:
    eye, target, up = (1.0, 2.0, 3.0), (0.3, -0.2, 0.5), (0.0, 1.0, 0.0)
    w2c = camera_look_at(eye, target, up)
    R = w2c[:3, :3].double()
    torch.testing.assert_close(R @ R.T, torch.eye(3, dtype=torch.float64), atol=1e-6, rtol=0)
    assert torch.linalg.det(R).item() == pytest.approx(1.0, abs=1e-6)
    K = intrinsics_from_fov(50.0, 64, 48)
    t_cam = transform_points(torch.tensor([target]), w2c)
    dist = float(np.linalg.norm(np.subtract(target, eye)))
    torch.testing.assert_close(t_cam, torch.tensor([[0.0, 0.0, dist]]), atol=1e-5, rtol=0)
    torch.testing.assert_close(project_points(t_cam, K), torch.tensor([[32.0, 24.0]]), atol=1e-4, rtol=0)
    above = transform_points(torch.tensor([target]) + 0.2 * torch.tensor([up]), w2c)
    uv = project_points(above, K)[0]
    assert uv[0].item() == pytest.approx(32.0, abs=1e-4)
    assert uv[1].item() < 24.0 - 1.0  # up is image -v
    # intrinsics_from_fov: a ray at half the vertical fov hits the top image edge.
    half = math.radians(25.0)
    top = project_points(torch.tensor([[0.0, -math.tan(half), 1.0]]), K)[0]
    assert top[1].item() == pytest.approx(0.0, abs=1e-4)
    with pytest.raises(ValueError, match="parallel"):
        camera_look_at((0.0, 0.0, 0.0), (0.0, 2.0, 0.0), (0.0, 1.0, 0.0))


def test_save_png_writes_rgb_and_rgba(tmp_path) -> None:
    img = torch.zeros(4, 5, 3)
    img[..., 0] = 1.0  # pure red
    img[0, 0] = torch.tensor([0.0, 0.0, 1.0])
    save_png(tmp_path / "a" / "rgb.png", img)
    back = cv2.imread(str(tmp_path / "a" / "rgb.png"), cv2.IMREAD_UNCHANGED)
    assert back.shape == (4, 5, 3)
    assert tuple(back[1, 1]) == (0, 0, 255) and tuple(back[0, 0]) == (255, 0, 0)  # BGR
    rgba = torch.cat([img, torch.full((4, 5, 1), 0.5)], -1)
    save_png(tmp_path / "rgba.png", rgba)
    back = cv2.imread(str(tmp_path / "rgba.png"), cv2.IMREAD_UNCHANGED)
    assert back.shape == (4, 5, 4) and tuple(back[1, 1]) == (0, 0, 255, 128)
    with pytest.raises(ValueError, match="image must be"):
        save_png(tmp_path / "bad.png", torch.zeros(4, 5, 2))


# --------------------------------------------------------------------------------------
# Validation
# --------------------------------------------------------------------------------------


def _good_part(**kw) -> MeshPart:
    args = dict(verts=torch.zeros(3, 3), faces=torch.tensor([[0, 1, 2]]), part_id=1, vertex_colors=torch.ones(3, 3))
    args.update(kw)
    return MeshPart(**args)


def test_rasterize_validation() -> None:
    K = torch.eye(3)
    v, f = torch.zeros(3, 3), torch.tensor([[0, 1, 2]])
    with pytest.raises(ValueError, match=r"verts_cam must be a \(V, 3\)"):
        rasterize(torch.zeros(3, 2), f, K, 4, 4)
    with pytest.raises(ValueError, match=r"faces must be a \(F, 3\)"):
        rasterize(v, torch.tensor([0, 1, 2]), K, 4, 4)
    with pytest.raises(ValueError, match="integer"):
        rasterize(v, f.float(), K, 4, 4)
    with pytest.raises(ValueError, match="out of range"):
        rasterize(v, torch.tensor([[0, 1, 3]]), K, 4, 4)
    with pytest.raises(ValueError, match=r"K must be a \(3, 3\)"):
        rasterize(v, f, torch.eye(4), 4, 4)
    with pytest.raises(ValueError, match="last row"):
        rasterize(v, f, torch.ones(3, 3), 4, 4)
    with pytest.raises(ValueError, match="height"):
        rasterize(v, f, K, 0, 4)


def test_mesh_part_and_render_validation() -> None:
    with pytest.raises(ValueError, match="no colour source"):
        _good_part(vertex_colors=None)
    with pytest.raises(ValueError, match="not both"):
        _good_part(uv=torch.zeros(3, 2), texture=torch.zeros(2, 2, 3))
    with pytest.raises(ValueError, match="texture is missing"):
        _good_part(vertex_colors=None, uv=torch.zeros(3, 2))
    with pytest.raises(ValueError, match=r"vertex_colors must be \(3, 3\)"):
        _good_part(vertex_colors=torch.ones(4, 3))
    with pytest.raises(ValueError, match=r"uv must be \(3, 2\)"):
        _good_part(vertex_colors=None, uv=torch.zeros(3, 3), texture=torch.zeros(2, 2, 3))
    with pytest.raises(ValueError, match=r"texture must be a \(Ht, Wt, 3\)"):
        _good_part(vertex_colors=None, uv=torch.zeros(3, 2), texture=torch.zeros(2, 2))
    with pytest.raises(ValueError, match="part_id"):
        _good_part(part_id=0)
    with pytest.raises(ValueError, match="out of range"):
        _good_part(faces=torch.tensor([[0, 1, 5]]))
    part = _good_part()
    K = torch.eye(3)
    with pytest.raises(ValueError, match=r"world2cam must be a \(4, 4\)"):
        render_meshes([part], torch.eye(3), K, 4, 4)
    with pytest.raises(ValueError, match="at least one"):
        render_meshes([], IDENTITY, K, 4, 4)
    with pytest.raises(ValueError, match="supersample"):
        render_meshes([part], IDENTITY, K, 4, 4, supersample=0)
    with pytest.raises(ValueError, match="background"):
        render_meshes([part], IDENTITY, K, 4, 4, background=torch.zeros(5, 5, 3))
    part.vertex_colors = None  # mutated after construction: caught at render time
    with pytest.raises(ValueError, match=r"parts\[0\]: no colour source"):
        render_meshes([part], IDENTITY, K, 4, 4)


def test_mixed_colour_sources_and_shading_chunks(monkeypatch: pytest.MonkeyPatch) -> None:
    H, W = 10, 20
    K = torch.tensor([[10.0, 0, 10], [0, 10.0, 5], [0, 0, 1]])
    faces = torch.tensor([[0, 1, 2], [0, 2, 3]])

    def quad(u0: float, u1: float) -> torch.Tensor:
        return torch.tensor(_fronto_quad(u0, u1, -1.0, 11.0, 1.0, K.numpy()), dtype=torch.float32)

    tex_colour, vc_colour = [0.2, 0.7, 0.1], [0.9, 0.1, 0.4]
    parts = [
        MeshPart(
            quad(-1.0, 8.0), faces, 5, uv=torch.rand(4, 2), texture=torch.tensor(tex_colour).expand(3, 4, 3).clone()
        ),
        MeshPart(quad(8.0, 21.0), faces, 9, vertex_colors=torch.tensor(vc_colour).expand(4, 3)),
    ]
    ref = render_meshes(parts, IDENTITY, K, H, W, light=FLAT)
    assert (ref.part_id[:, :8] == 5).all() and (ref.part_id[:, 8:] == 9).all()
    torch.testing.assert_close(ref.rgb[:, :8], torch.tensor(tex_colour).expand(H, 8, 3))
    torch.testing.assert_close(ref.rgb[:, 8:], torch.tensor(vc_colour).expand(H, 12, 3))
    monkeypatch.setattr(mr, "_SHADE_CHUNK", 7)
    out = render_meshes(parts, IDENTITY, K, H, W, light=FLAT)
    for name in ("rgb", "alpha", "depth", "part_id", "normal"):
        assert torch.equal(getattr(out, name), getattr(ref, name)), name
