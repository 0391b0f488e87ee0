"""The compiled CPU kernels of the mesh rasteriser against its vectorised PyTorch path.

Fragments (visible face, barycentrics, depth) must be bit-identical; shaded colours agree
to float rounding; coverage, depth and part ids exactly.
"""

from __future__ import annotations

import pytest
import torch

import hogsa_loader.render.mesh_raster as mr
from hogsa_loader.render import raster_kernels
from hogsa_loader.render.mesh_raster import Light, MeshPart, rasterize, render_meshes


def test_numba_is_installed() -> None:
    assert raster_kernels.AVAILABLE, "numba is a declared dependency (setup.cfg); install it"


def _soup(n: int, dtype: torch.dtype, seed: int, snap: bool) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Random overlapping triangles in front of a skewed camera; ``snap`` puts vertices on
    pixel centres and shares edges so that top-left ties and exact depth ties occur."""
    g = torch.Generator().manual_seed(seed)
    K = torch.tensor([[60.0, 2.5, 40.3], [0.0, 55.0, 31.7], [0.0, 0.0, 1.0]], dtype=dtype)
    centre = torch.rand(n, 1, 3, generator=g, dtype=dtype) * torch.tensor([1.2, 1.0, 1.0], dtype=dtype) + torch.tensor(
        [-0.6, -0.5, 1.0], dtype=dtype
    )
    verts = (centre + 0.15 * torch.randn(n, 3, 3, generator=g, dtype=dtype)).reshape(-1, 3)
    if snap:  # move every vertex so that it projects onto a pixel centre, at depth 1.5 or 2
        z = torch.where(torch.rand(verts.shape[0], generator=g) < 0.5, 1.5, 2.0).to(dtype)
        uv = torch.randint(0, 60, (verts.shape[0], 2), generator=g).to(dtype) + 0.5
        y = (uv[:, 1] - K[1, 2]) / K[1, 1]
        x = (uv[:, 0] - K[0, 2] - K[0, 1] * y) / K[0, 0]
        verts = torch.stack([x * z, y * z, z], dim=1)
    faces = torch.arange(verts.shape[0]).reshape(-1, 3)
    if snap:  # half of the triangles share an edge with the previous one
        faces[1::2, :2] = faces[0:-1:2, 1:3]
    return verts, faces, K


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
@pytest.mark.parametrize("snap", [False, True])
@pytest.mark.parametrize("cull", [False, True])
def test_fragments_are_bit_identical(dtype: torch.dtype, snap: bool, cull: bool) -> None:
    verts, faces, K = _soup(300, dtype, seed=3 + snap, snap=snap)
    ref = rasterize(verts, faces, K, 64, 80, cull_backfaces=cull, backend="torch")
    out = rasterize(verts, faces, K, 64, 80, cull_backfaces=cull, backend="numba")
    assert (ref.face_idx >= 0).float().mean() > 0.3  # the case covers much of the image
    assert torch.equal(out.face_idx, ref.face_idx)
    assert torch.equal(out.bary, ref.bary)
    assert torch.equal(out.depth, ref.depth)


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
@pytest.mark.parametrize("cull", [False, True])
def test_face_tables_are_bit_identical(dtype: torch.dtype, cull: bool) -> None:
    verts, faces, K = _soup(200, dtype, seed=7, snap=False)
    special = torch.tensor(
        [
            [0.0, 0.0, 1.0],
            [0.1, 0.0, 1.0],
            [float("nan"), 0.1, 1.0],  # non-finite
            [0.0, 0.0, -1.0],
            [0.1, 0.0, 1.0],
            [0.0, 0.1, 1.0],  # straddles the near plane
            [0.0, 0.0, 1.0],
            [0.1, 0.1, 1.0],
            [0.2, 0.2, 1.0],  # collinear
            [5.0, 5.0, 1.0],
            [5.1, 5.0, 1.0],
            [5.0, 5.1, 1.0],  # off-screen
            [0.0, 0.0, 1.0],
            [0.001, 0.0, 1.0],
            [0.0, 0.001, 1.0],  # between pixel centres
        ],
        dtype=dtype,
    )
    faces = torch.cat([faces, torch.arange(15).reshape(5, 3) + verts.shape[0]])
    verts = torch.cat([verts, special])
    ref = mr._setup_faces(verts, faces, K, 64, 80, 1e-3, cull)
    out = mr._setup_faces_kernel(verts, faces, K, 64, 80, 1e-3, cull)
    assert 0 < ref.face_ids.numel() < faces.shape[0] - 4
    for name in (
        "face_ids",
        "edge_a",
        "edge_b",
        "edge_x",
        "edge_y",
        "edge_tl",
        "inv_z",
        "row0",
        "col0",
        "nrows",
        "ncols",
    ):
        assert torch.equal(getattr(out, name), getattr(ref, name)), name


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_shaded_render_matches_the_pytorch_path(dtype: torch.dtype) -> None:
    g = torch.Generator().manual_seed(0)
    verts, faces, K = _soup(200, dtype, seed=5, snap=False)
    third = faces.shape[0] // 3
    tex = torch.rand(7, 9, 3, generator=g)
    parts = [
        MeshPart(verts, faces[:third], 3, vertex_colors=torch.rand(verts.shape[0], 3, generator=g)),
        MeshPart(verts, faces[third:], 7, uv=torch.rand(verts.shape[0], 2, generator=g) * 1.2 - 0.1, texture=tex),
        MeshPart(verts + 0.01, faces[third:], 9, uv=torch.rand(verts.shape[0], 2, generator=g), texture=tex),
        MeshPart(
            verts - 0.01,
            faces[:third],
            11,
            uv=torch.rand(verts.shape[0], 2, generator=g),
            texture=torch.rand(1, 1, 3, generator=g),
        ),  # a one-texel texture
    ]
    bg = torch.rand(32, 40, 3, generator=g, dtype=dtype)
    light = Light(direction=(0.3, -0.2, 1.0), specular=0.4, shininess=12.0)
    for smooth in (True, False):
        kw = dict(light=light, background=bg, supersample=2, smooth_normals=smooth)
        Kh = K * torch.tensor([[0.5], [0.5], [1.0]], dtype=dtype)
        ref = render_meshes(parts, torch.eye(4, dtype=dtype), Kh, 32, 40, backend="torch", **kw)
        out = render_meshes(parts, torch.eye(4, dtype=dtype), Kh, 32, 40, backend="numba", **kw)
        assert out.rgb.dtype == dtype
        assert torch.equal(out.part_id, ref.part_id) and set(ref.part_id.unique().tolist()) == {0, 3, 7, 9, 11}
        assert torch.equal(out.alpha, ref.alpha)
        assert torch.equal(out.depth, ref.depth)
        torch.testing.assert_close(out.rgb, ref.rgb, rtol=0, atol=2e-6)
        torch.testing.assert_close(out.normal, ref.normal, rtol=0, atol=2e-6)


def test_backend_choice_and_errors() -> None:
    verts, faces, K = _soup(20, torch.float32, seed=1, snap=False)
    with pytest.raises(ValueError, match="backend must be"):
        rasterize(verts, faces, K, 16, 16, backend="cuda")
    grad_verts = verts.clone().requires_grad_(True)
    with pytest.raises(ValueError, match="requires grad"):
        rasterize(grad_verts, faces, K, 16, 16, backend="numba")
    with pytest.raises(ValueError, match="float32 or float64"):
        rasterize(verts.half(), faces, K.half(), 16, 16, backend="numba")
    auto = rasterize(grad_verts, faces, K, 16, 16)  # falls back to the PyTorch path
    assert torch.equal(auto.face_idx, rasterize(verts, faces, K, 16, 16, backend="torch").face_idx)


def test_auto_runs_the_kernels_on_cpu(monkeypatch: pytest.MonkeyPatch) -> None:
    calls = []
    for name in ("setup_faces", "zbuffer", "resolve", "shade"):
        fn = getattr(raster_kernels, name)
        monkeypatch.setattr(raster_kernels, name, lambda *a, _fn=fn, _name=name: calls.append(_name) or _fn(*a))
    verts, faces, K = _soup(20, torch.float32, seed=2, snap=False)
    part = MeshPart(verts, faces, 1, vertex_colors=torch.ones(verts.shape[0], 3))
    assert (render_meshes([part], torch.eye(4), K, 64, 80).part_id == 1).any()
    assert calls == ["setup_faces", "zbuffer", "resolve", "shade"]
    calls.clear()
    render_meshes([part], torch.eye(4), K, 64, 80, backend="torch")
    assert calls == []


def test_nan_texture_coordinates_read_inside_the_texture() -> None:
    verts = torch.tensor([[-0.5, -0.5, 1.0], [0.5, -0.5, 1.0], [0.0, 0.5, 1.0]])
    uv = torch.tensor([[float("nan"), 0.2], [0.5, float("nan")], [0.3, 0.3]])
    part = MeshPart(verts, torch.tensor([[0, 1, 2]]), 1, uv=uv, texture=torch.full((4, 4, 3), 0.5))
    out = render_meshes(
        [part], torch.eye(4), torch.tensor([[8.0, 0, 8], [0, 8.0, 8], [0, 0, 1]]), 16, 16, backend="numba"
    )
    assert (out.part_id == 1).sum() > 20
    assert torch.isfinite(out.rgb).all()
