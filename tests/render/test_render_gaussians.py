"""Tests of the CPU Gaussian splatting rasteriser (gsplat 1.5.3 conventions); every test runs
with both compositors (vectorised PyTorch and the compiled kernels)."""

from __future__ import annotations

import math

import pytest
import torch

from hogsa_loader.render.gaussians import project_gaussians, quat_scale_to_covar, render_gaussians, sh_colors
from hogsa_loader.render.settings import RenderSettings, SplatInputs


def _gsplat_ref():
    """gsplat's pure-torch reference functions (test extra); a test that needs them is skipped without."""
    return pytest.importorskip("gsplat.cuda._torch_impl", reason="gsplat's reference functions (test extra)")


@pytest.fixture(autouse=True, params=["torch", "numba"])
def compositor(request, monkeypatch):
    """Run the test with ``RenderSettings``' default compositor set to each one."""
    monkeypatch.setitem(RenderSettings.__init__.__kwdefaults__, "compositor", request.param)
    return request.param


# --------------------------------------------------------------------------------------
# helpers
# --------------------------------------------------------------------------------------


def _intrinsics(f: float, cx: float, cy: float, dtype=torch.float32) -> torch.Tensor:
    return torch.tensor([[f, 0.0, cx], [0.0, f, cy], [0.0, 0.0, 1.0]], dtype=dtype)


def _look_at(eye, target=(0.0, 0.0, 0.6), dtype=torch.float32) -> torch.Tensor:
    """World->camera OpenCV matrix of a camera at ``eye`` looking at ``target`` (y down)."""
    eye_t = torch.tensor(eye, dtype=torch.float64)
    fwd = torch.tensor(target, dtype=torch.float64) - eye_t
    fwd = fwd / fwd.norm()
    up = torch.tensor([0.0, -1.0, 0.0], dtype=torch.float64)
    right = torch.linalg.cross(up, fwd)
    right = right / right.norm()
    down = torch.linalg.cross(fwd, right)
    rot = torch.stack([right, down, fwd])  # rows: camera axes in world
    m = torch.eye(4, dtype=torch.float64)
    m[:3, :3] = rot
    m[:3, 3] = -rot @ eye_t
    return m.to(dtype)


def _ball_scene(n: int, seed: int, dtype=torch.float32, radius=0.1, z=0.6):
    g = torch.Generator().manual_seed(seed)
    d = torch.randn(n, 3, generator=g, dtype=torch.float64)
    d = d / d.norm(dim=-1, keepdim=True) * torch.rand(n, 1, generator=g, dtype=torch.float64) ** (1 / 3)
    means = d * radius + torch.tensor([0.0, 0.0, z], dtype=torch.float64)
    quats = torch.randn(n, 4, generator=g, dtype=torch.float64)
    scales = torch.exp(torch.empty(n, 3, dtype=torch.float64).uniform_(math.log(2e-3), math.log(1.5e-2), generator=g))
    opac = torch.empty(n, dtype=torch.float64).uniform_(0.05, 1.0, generator=g)
    cols = torch.rand(n, 3, generator=g, dtype=torch.float64)
    return [t.to(dtype) for t in (means, quats, scales, opac, cols)]


def _brute_force(means, quats, scales, opac, cols, viewmat, K, W, H, bg):
    """Naive reference: gsplat's pure-torch projection, then every Gaussian in stable depth
    order composited onto every pixel (vectorised over pixels only), with the exact rule of
    RasterizeToPixels3DGSFwd.cu. No tiles, no bounding boxes. Float64."""
    covars, _ = _gsplat_ref()._quat_scale_to_covar_preci(quats, scales, compute_preci=False)
    radii, m2d, depths, conics, _ = _gsplat_ref()._fully_fused_projection(means, covars, viewmat[None], K[None], W, H)
    radii, m2d, depths, conics = radii[0], m2d[0], depths[0], conics[0]
    use = (radii > 0).all(-1) & (opac >= 1 / 255)
    order = torch.argsort(depths, stable=True)
    order = order[use[order]]
    py, px = torch.meshgrid(
        torch.arange(H, dtype=torch.float64) + 0.5, torch.arange(W, dtype=torch.float64) + 0.5, indexing="ij"
    )
    T = torch.ones(H, W, dtype=torch.float64)
    rgb = torch.zeros(H, W, 3, dtype=torch.float64)
    dep = torch.zeros(H, W, dtype=torch.float64)
    done = torch.zeros(H, W, dtype=torch.bool)
    n_stops = 0
    for gi in order.tolist():
        dx, dy = m2d[gi, 0] - px, m2d[gi, 1] - py
        a, b, c = conics[gi]
        sigma = 0.5 * (a * dx * dx + c * dy * dy) + b * dx * dy
        alpha = torch.clamp(opac[gi] * torch.exp(-sigma), max=0.999)
        ok = ~done & (sigma >= 0) & (alpha >= 1 / 255)
        next_t = T * (1 - alpha)
        stop = ok & (next_t <= 1e-4)
        n_stops += int(stop.sum())
        done |= stop
        ok &= ~stop
        w = torch.where(ok, alpha * T, 0.0)
        rgb += w[..., None] * cols[gi]
        dep += w * depths[gi]
        T = torch.where(ok, next_t, T)
    alpha_img = 1 - T
    rgb = rgb + T[..., None] * bg
    return rgb, alpha_img[..., None], (dep / alpha_img.clamp(min=1e-10))[..., None], n_stops


def _settings(**kw) -> RenderSettings:
    """Settings with expected depth ("RGB+ED") unless ``render_mode`` says otherwise."""
    return RenderSettings(**{"render_mode": "RGB+ED", **kw})


def _render1(means, quats, scales, opac, cols, viewmat, K, W, H, settings=None, **tensors):
    """Single-sample, single-camera wrapper; ``tensors``: backgrounds, part_ids, valid."""
    x = SplatInputs(
        means[None],
        quats[None],
        scales[None],
        opac[None],
        cols[None],
        viewmat[None, None],
        K[None, None],
        W,
        H,
        **tensors,
    )
    return render_gaussians(x, _settings() if settings is None else settings)


# --------------------------------------------------------------------------------------
# projection / covariance / SH against gsplat's pure-torch reference
# --------------------------------------------------------------------------------------


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_covariance_matches_gsplat(dtype):
    g = torch.Generator().manual_seed(0)
    quats = torch.randn(500, 4, generator=g).to(dtype) * 3
    scales = torch.rand(500, 3, generator=g).to(dtype) + 0.01
    ref, _ = _gsplat_ref()._quat_scale_to_covar_preci(quats, scales, compute_preci=False)
    tol = 1e-6 if dtype == torch.float32 else 1e-12
    torch.testing.assert_close(quat_scale_to_covar(quats, scales), ref, rtol=tol, atol=tol)


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_projection_matches_gsplat(dtype):
    B, C, N, W, H = 2, 3, 400, 96, 64
    g = torch.Generator().manual_seed(1)
    means = (torch.rand(B, N, 3, generator=g) - 0.5) * torch.tensor([1.2, 0.8, 1.6]) + torch.tensor([0, 0, 0.4])
    quats = torch.randn(B, N, 4, generator=g)
    scales = torch.exp(torch.empty(B, N, 3).uniform_(math.log(1e-3), math.log(0.1), generator=g))
    eyes = [(0.0, 0.0, -0.5), (0.4, -0.2, -0.3), (-0.3, 0.1, -0.6)]
    viewmats = torch.stack([torch.stack([_look_at(e, (0, 0, 0.3)) for e in eyes])] * B)
    Ks = torch.stack([torch.stack([_intrinsics(80.0 + 10 * c, 45.0 + c, 33.0 - c) for c in range(C)])] * B)
    means, quats, scales, viewmats, Ks = (t.to(dtype) for t in (means, quats, scales, viewmats, Ks))

    covars = quat_scale_to_covar(quats, scales)
    radii, m2d, depths, conics = project_gaussians(means, covars, viewmats, Ks, W, H, 0.3, 0.01, 1e10)
    ref_covars, _ = _gsplat_ref()._quat_scale_to_covar_preci(quats, scales, compute_preci=False)
    r_radii, r_m2d, r_depths, r_conics, _ = _gsplat_ref()._fully_fused_projection(
        means, ref_covars, viewmats, Ks, W, H, eps2d=0.3, near_plane=0.01, far_plane=1e10
    )
    vis = (r_radii > 0).all(-1)
    assert 0.2 < vis.float().mean() < 0.95  # both culled and visible Gaussians are exercised
    tol = dict(rtol=2e-5, atol=2e-4) if dtype == torch.float32 else dict(rtol=1e-10, atol=1e-9)
    torch.testing.assert_close(depths, r_depths, **tol)
    torch.testing.assert_close(m2d[vis], r_m2d[vis], **tol)
    torch.testing.assert_close(conics[vis], r_conics[vis], rtol=tol["rtol"] * 10, atol=tol["atol"])
    if dtype == torch.float64:
        assert torch.equal(radii, r_radii)
    else:  # ceil() may round differently when 3.33 sigma is within float eps of an integer
        assert (radii - r_radii).abs().max() <= 1
        assert (radii != r_radii).float().mean() < 1e-3


def test_opacity_aware_radius():
    """rasterization() passes opacities: extent = min(3.33, sqrt(2 ln(255 o))), o < 1/255 culled."""
    N = 5
    means = torch.tensor([[0.0, 0.0, 1.0]]).repeat(N, 1)[None]
    covars = torch.eye(3).repeat(N, 1, 1)[None] * 0.01**2
    opac = torch.tensor([[1.0, 0.5, 0.05, 1 / 255 * 0.99, 0.0]])
    K = _intrinsics(500.0, 32.0, 32.0)[None, None]
    radii, _, _, _ = project_gaussians(means, covars, torch.eye(4)[None, None], K, 64, 64, opacities=opac)
    sd = math.sqrt((500 * 0.01) ** 2 + 0.3)
    for i, o in enumerate(opac[0].tolist()[:3]):
        ext = min(3.33, math.sqrt(2 * math.log(o * 255)))
        assert radii[0, 0, i].tolist() == [math.ceil(ext * sd)] * 2
    assert radii[0, 0, 3:].eq(0).all()


@pytest.mark.parametrize("degree", [0, 1, 2, 3, 4])
def test_sh_matches_gsplat(degree):
    g = torch.Generator().manual_seed(degree)
    dirs = torch.randn(300, 3, generator=g) * 5
    k = max((degree + 1) ** 2, 16)  # extra coefficients beyond the degree must be ignored
    coeffs = torch.randn(300, k, 3, generator=g)
    ref = _gsplat_ref()._spherical_harmonics(degree, dirs, coeffs)
    torch.testing.assert_close(sh_colors(degree, dirs, coeffs), ref, rtol=1e-5, atol=1e-5)


def test_sh_colours_in_render_use_offset_and_view_direction():
    """colour = max(SH(mean - camera centre) + 0.5, 0) (rendering.py: rasterization)."""
    means, quats, scales, opac, _ = _ball_scene(50, 3)
    g = torch.Generator().manual_seed(3)
    sh = torch.randn(50, 9, 3, generator=g) * 0.6
    view = _look_at((0.2, -0.1, 0.0))
    K = _intrinsics(60.0, 16.0, 16.0)
    out = _render1(means, quats, scales, opac, sh, view, K, 32, 32, _settings(sh_degree=2))
    campos = torch.linalg.inv(view)[:3, 3]
    expect = torch.clamp_min(_gsplat_ref()._spherical_harmonics(2, means - campos, sh) + 0.5, 0.0)
    torch.testing.assert_close(out.meta["colors"][0, 0], expect, rtol=1e-5, atol=1e-5)
    assert (expect == 0).any()  # the clamp is exercised


# --------------------------------------------------------------------------------------
# compositing against an independent brute-force renderer
# --------------------------------------------------------------------------------------


def _brute_force_scene():
    W, H, N = 64, 48, 200
    g = torch.Generator().manual_seed(7)
    # camera at the origin looking down +z; identity rotation so equal world z => equal depth
    f = 70.0
    K = _intrinsics(f, 31.3, 24.7, torch.float64)
    view = torch.eye(4, dtype=torch.float64)
    u = torch.empty(N).uniform_(-6, W + 6, generator=g).double()  # some straddle the image border
    v = torch.empty(N).uniform_(-6, H + 6, generator=g).double()
    z = torch.empty(N).uniform_(0.5, 1.5, generator=g).double()
    u[:12] = torch.tensor([16.0, 32.0, 48.0, 15.6, 31.9, 47.7, 16.3, 0.2, 63.8, 32.0, 16.0, 48.1]).double()
    v[:12] = torch.tensor([16.0, 16.0, 32.0, 31.8, 32.4, 16.2, 47.9, 20.0, 30.0, 0.3, 47.6, 24.0]).double()
    z[40:60] = z[60:80]  # 20 exact depth ties (different screen positions / colours)
    z[80:85] = z[85]
    u[12:30] = 40.0 + 4 * torch.randn(18, generator=g).double()  # an opaque cluster
    v[12:30] = 20.0 + 4 * torch.randn(18, generator=g).double()
    means = torch.stack([(u - K[0, 2]) * z / f, (v - K[1, 2]) * z / f, z], -1)
    means[60:80, :2] = means[40:60, :2] + 0.002 * torch.randn(20, 2, generator=g).double()
    quats = torch.randn(N, 4, generator=g).double()
    scales = torch.exp(torch.empty(N, 3).uniform_(math.log(0.004), math.log(0.06), generator=g)).double()
    opac = torch.empty(N).uniform_(0.02, 1.0, generator=g).double()
    opac[:30] = torch.empty(30).uniform_(0.9, 1.0, generator=g).double()  # saturate some pixels
    scales[12:30] = scales[12:30].clamp(min=0.05)
    cols = torch.rand(N, 3, generator=g).double()
    bg = torch.tensor([0.1, 0.2, 0.3], dtype=torch.float64)
    return means, quats, scales, opac, cols, view, K, W, H, bg


@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
def test_matches_brute_force(dtype):
    means, quats, scales, opac, cols, view, K, W, H, bg = _brute_force_scene()
    ref_rgb, ref_alpha, ref_depth, n_stops = _brute_force(means, quats, scales, opac, cols, view, K, W, H, bg)
    assert n_stops > 50  # the termination rule is exercised
    assert 0.3 < (ref_alpha > 0.5).float().mean() < 0.99
    args = [t.to(dtype) for t in (means, quats, scales, opac, cols, view, K)]
    out = _render1(*args, W, H, _settings(chunk=16), backgrounds=bg.to(dtype)[None, None])
    tol = 1e-5 if dtype == torch.float64 else 1e-4
    torch.testing.assert_close(out.rgb[0, 0].double(), ref_rgb, atol=tol, rtol=0)
    torch.testing.assert_close(out.alpha[0, 0].double(), ref_alpha, atol=tol, rtol=0)
    torch.testing.assert_close(out.depth[0, 0].double(), ref_depth, atol=tol * 10, rtol=0)
    if dtype == torch.float32:  # typical float32 error is far below the worst case
        assert (out.rgb[0, 0].double() - ref_rgb).abs().mean() < 2e-6


def test_depth_ties_follow_index_order():
    """Two Gaussians at exactly the same depth: the lower index is composited first."""
    K = _intrinsics(50.0, 8.0, 8.0)
    means = torch.tensor([[0.0, 0.0, 1.0], [0.0, 0.0, 1.0]])
    quats = torch.tensor([[1.0, 0, 0, 0]] * 2)
    scales = torch.full((2, 3), 0.5)
    opac = torch.tensor([0.6, 0.6])
    cols = torch.tensor([[1.0, 0, 0], [0, 1.0, 0]])
    out = _render1(means, quats, scales, opac, cols, torch.eye(4), K, 16, 16)
    c = out.rgb[0, 0, 8, 8]
    assert c[0] > c[1]  # red (index 0) in front
    out2 = _render1(means, quats, scales, opac, cols.flip(0), torch.eye(4), K, 16, 16)
    assert out2.rgb[0, 0, 8, 8, 1] > out2.rgb[0, 0, 8, 8, 0]


@pytest.mark.parametrize("chunk,tile_batch", [(8, 3), (64, 2048)])
def test_independent_of_chunking(chunk, tile_batch):
    means, quats, scales, opac, cols = _ball_scene(600, 11)
    K = _intrinsics(100.0, 24.0, 20.0)
    view = _look_at((0.05, 0.0, 0.0))
    ref = _render1(means, quats, scales, opac, cols, view, K, 50, 40)
    out = _render1(means, quats, scales, opac, cols, view, K, 50, 40, _settings(chunk=chunk, tile_batch=tile_batch))
    torch.testing.assert_close(out.rgb, ref.rgb, atol=1e-5, rtol=0)  # float32 summation order
    torch.testing.assert_close(out.alpha, ref.alpha, atol=1e-5, rtol=0)


# --------------------------------------------------------------------------------------
# gradients
# --------------------------------------------------------------------------------------


def _grad_scene():
    """4 large, semi-transparent Gaussians covering an 8x8 image: every pixel is far from
    the 1/255 cut-off, the 0.999 clamp and the 1e-4 termination."""
    means = torch.tensor(
        [[0.01, -0.02, 1.0], [-0.03, 0.02, 1.2], [0.02, 0.03, 1.5], [-0.01, -0.01, 0.9]], dtype=torch.float64
    )
    quats = torch.tensor(
        [[1.0, 0.1, -0.2, 0.05], [0.9, -0.1, 0.3, 0.2], [0.7, 0.2, 0.1, -0.4], [1.0, 0.0, 0.2, 0.1]],
        dtype=torch.float64,
    )
    scales = torch.tensor(
        [[0.08, 0.05, 0.03], [0.06, 0.09, 0.04], [0.1, 0.07, 0.05], [0.05, 0.06, 0.07]], dtype=torch.float64
    )
    opac = torch.tensor([0.5, 0.6, 0.7, 0.4], dtype=torch.float64)
    K = _intrinsics(20.0, 4.2, 3.9, torch.float64)
    return means, quats, scales, opac, K


def test_gradcheck_rgb_parts_depth():
    means, quats, scales, opac, K = _grad_scene()
    cols = torch.tensor([[0.9, 0.2, 0.1], [0.1, 0.8, 0.3], [0.2, 0.3, 0.9], [0.5, 0.5, 0.5]], dtype=torch.float64)
    bg = torch.tensor([[[0.3, 0.1, 0.2]]], dtype=torch.float64)
    part_ids = torch.tensor([[0, 1, 1, -1]])

    def fn(m, q, s, o, c):
        x = SplatInputs(
            m[None],
            q[None],
            s[None],
            o[None],
            c[None],
            torch.eye(4, dtype=torch.float64)[None, None],
            K[None, None],
            8,
            8,
            backgrounds=bg,
            part_ids=part_ids,
        )
        out = render_gaussians(x, _settings(num_parts=2, tile_size=4))
        return out.rgb, out.alpha, out.depth, out.part_alpha

    inputs = [t.clone().requires_grad_(True) for t in (means, quats, scales, opac, cols)]
    assert torch.autograd.gradcheck(fn, inputs, eps=1e-6, atol=1e-6, rtol=1e-4)


def test_gradcheck_sh():
    means, quats, scales, opac, K = _grad_scene()
    g = torch.Generator().manual_seed(5)
    sh = torch.randn(4, 9, 3, generator=g, dtype=torch.float64) * 0.1
    view = _look_at((0.1, -0.05, 0.0), (0.0, 0.0, 1.0), torch.float64)

    def fn(m, q, s, o, c):
        x = SplatInputs(m[None], q[None], s[None], o[None], c[None], view[None, None], K[None, None], 8, 8)
        out = render_gaussians(x, RenderSettings(sh_degree=2))
        return out.rgb, out.alpha

    inputs = [t.clone().requires_grad_(True) for t in (means, quats, scales, opac, sh)]
    assert torch.autograd.gradcheck(fn, inputs, eps=1e-6, atol=1e-6, rtol=1e-4)


def test_checkpoint_gives_same_gradients():
    means, quats, scales, opac, cols = _ball_scene(300, 9)
    K = _intrinsics(80.0, 20.0, 20.0)
    grads = []
    for ckpt in (False, True):
        ins = [t.clone().requires_grad_(True) for t in (means, quats, scales, opac, cols)]
        out = _render1(*ins, torch.eye(4), K, 40, 40, _settings(checkpoint=ckpt, tile_batch=2))
        (out.rgb * torch.linspace(0, 1, 3)).sum().add(out.depth.sum()).backward()
        grads.append([t.grad for t in ins])
    for g0, g1 in zip(*grads):
        torch.testing.assert_close(g1, g0, rtol=1e-5, atol=1e-6)


def test_means2d_gradient_available():
    means, quats, scales, opac, cols = _ball_scene(100, 2)
    out = _render1(means.requires_grad_(), quats, scales, opac, cols, torch.eye(4), _intrinsics(60.0, 16, 16), 32, 32)
    m2d = out.meta["means2d"]
    m2d.retain_grad()
    out.rgb.sum().backward()
    vis = (out.meta["radii"] > 0).all(-1)
    assert m2d.grad is not None and m2d.grad[vis].abs().sum() > 0
    assert m2d.grad[~vis].abs().sum() == 0


# --------------------------------------------------------------------------------------
# analytic cases
# --------------------------------------------------------------------------------------


def _one(mean, opacity, colour, scale=1.0):
    return (
        torch.tensor([mean]),
        torch.tensor([[1.0, 0.0, 0.0, 0.0]]),
        torch.full((1, 3), scale),
        torch.tensor([opacity]),
        torch.tensor([colour]),
    )


@pytest.mark.parametrize("opacity", [0.7, 1.0])
def test_single_large_gaussian_at_principal_point(opacity):
    W = H = 33  # odd: the centre pixel (16, 16) is sampled at (16.5, 16.5) = principal point
    K = _intrinsics(40.0, 16.5, 16.5)
    m, q, s, o, c = _one([0.0, 0.0, 2.0], opacity, [0.2, 0.4, 0.8])
    out = _render1(m, q, s, o, c, torch.eye(4), K, W, H)
    a = min(0.999, opacity)
    torch.testing.assert_close(out.alpha[0, 0, 16, 16, 0], torch.tensor(a), atol=1e-6, rtol=0)
    torch.testing.assert_close(out.rgb[0, 0, 16, 16], torch.tensor([0.2, 0.4, 0.8]) * a, atol=1e-6, rtol=0)
    torch.testing.assert_close(out.depth[0, 0, 16, 16, 0], torch.tensor(2.0), atol=1e-5, rtol=0)
    assert out.meta["means2d"][0, 0, 0].tolist() == [16.5, 16.5]


def test_nearer_gaussian_dominates_regardless_of_order():
    K = _intrinsics(40.0, 16.0, 16.0)
    near = _one([0.0, 0.0, 1.0], 1.0, [1.0, 0.0, 0.0])
    far = _one([0.0, 0.0, 3.0], 0.5, [0.0, 1.0, 0.0])
    cat = [torch.cat([a, b]) for a, b in zip(near, far)]
    cat_rev = [torch.cat([b, a]) for a, b in zip(near, far)]
    o1 = _render1(*cat, torch.eye(4), K, 32, 32)
    o2 = _render1(*cat_rev, torch.eye(4), K, 32, 32)
    torch.testing.assert_close(o1.rgb, o2.rgb, atol=1e-7, rtol=0)
    px = o1.rgb[0, 0, 16, 16]
    assert px[0] > 0.99  # red (alpha 0.999) in front; green sees T = 0.001
    torch.testing.assert_close(px[1], torch.tensor(0.5 * 0.001), atol=2e-5, rtol=0)
    # an opaque far Gaussian would bring T to 1e-6 <= 1e-4: gsplat stops before it
    cat[3][1] = 1.0
    px = _render1(*cat, torch.eye(4), K, 32, 32).rgb[0, 0, 16, 16]
    assert px[1] == 0.0


def test_background_compositing():
    means, quats, scales, opac, cols = _ball_scene(300, 4)
    K = _intrinsics(80.0, 20.0, 20.0)
    bg = torch.tensor([0.3, 0.6, 0.9])
    o0 = _render1(means, quats, scales, opac, cols, torch.eye(4), K, 40, 40)
    o1 = _render1(means, quats, scales, opac, cols, torch.eye(4), K, 40, 40, backgrounds=bg[None, None])
    torch.testing.assert_close(o1.rgb, o0.rgb + (1 - o0.alpha) * bg, atol=1e-6, rtol=0)
    assert 0.05 < (o0.alpha < 0.5).float().mean() < 0.95
    torch.testing.assert_close(o1.alpha, o0.alpha)


def test_part_alpha_sums_to_alpha():
    means, quats, scales, opac, cols = _ball_scene(300, 5)
    K = _intrinsics(80.0, 20.0, 20.0)
    part_ids = torch.randint(0, 3, (1, 300), generator=torch.Generator().manual_seed(0))
    x = SplatInputs(
        means[None],
        quats[None],
        scales[None],
        opac[None],
        cols[None],
        torch.eye(4)[None, None],
        K[None, None],
        40,
        40,
        part_ids=part_ids,
    )
    out = render_gaussians(x, _settings(num_parts=3))
    assert out.part_alpha.shape == (1, 1, 40, 40, 3)
    torch.testing.assert_close(out.part_alpha.sum(-1, keepdim=True), out.alpha, atol=2e-6, rtol=0)
    assert (out.part_alpha > 0.1).flatten(0, 3).any(0).all()  # every part visible somewhere


def test_batching_equals_separate_renders():
    B, C, N, W, H = 2, 3, 250, 40, 30
    scenes = [_ball_scene(N, 20 + b) for b in range(B)]
    means, quats, scales, opac, cols = (torch.stack([s[i] for s in scenes]) for i in range(5))
    eyes = [[(0.0, 0.0, 0.0), (0.2, 0.0, 0.1), (0.0, -0.2, 0.1)], [(0.1, 0.1, 0.0), (-0.2, 0.0, 0.1), (0.0, 0.0, 0.2)]]
    viewmats = torch.stack([torch.stack([_look_at(e) for e in eb]) for eb in eyes])
    Ks = torch.stack([torch.stack([_intrinsics(60.0 + 5 * c + b, 20.0, 15.0 + b) for c in range(C)]) for b in range(B)])
    bg = torch.rand(B, C, 3, generator=torch.Generator().manual_seed(1))
    part_ids = torch.randint(0, 2, (B, N), generator=torch.Generator().manual_seed(2))
    out = render_gaussians(
        SplatInputs(means, quats, scales, opac, cols, viewmats, Ks, W, H, backgrounds=bg, part_ids=part_ids),
        _settings(num_parts=2),
    )
    assert out.rgb.shape == (B, C, H, W, 3) and out.alpha.shape == (B, C, H, W, 1)
    for b in range(B):
        for c in range(C):
            x = SplatInputs(
                means[b : b + 1],
                quats[b : b + 1],
                scales[b : b + 1],
                opac[b : b + 1],
                cols[b : b + 1],
                viewmats[b : b + 1, c : c + 1],
                Ks[b : b + 1, c : c + 1],
                W,
                H,
                backgrounds=bg[b : b + 1, c : c + 1],
                part_ids=part_ids[b : b + 1],
            )
            o = render_gaussians(x, _settings(num_parts=2))
            # float32: batched matmuls may round differently
            torch.testing.assert_close(out.rgb[b, c], o.rgb[0, 0], atol=2e-5, rtol=0)
            torch.testing.assert_close(out.alpha[b, c], o.alpha[0, 0], atol=2e-5, rtol=0)
            torch.testing.assert_close(out.depth[b, c], o.depth[0, 0], atol=1e-4, rtol=0)
            torch.testing.assert_close(out.part_alpha[b, c], o.part_alpha[0, 0], atol=2e-5, rtol=0)
            assert torch.equal(out.meta["radii"][b, c], o.meta["radii"][0, 0])
    assert out.alpha.amax(dim=(2, 3, 4)).min() > 0.5  # every image sees the scene


def test_valid_mask_equals_dropping_gaussians():
    means, quats, scales, opac, cols = _ball_scene(200, 8)
    K = _intrinsics(80.0, 20.0, 20.0)
    keep = torch.rand(200, generator=torch.Generator().manual_seed(3)) > 0.4
    x = SplatInputs(
        means[None],
        quats[None],
        scales[None],
        opac[None],
        cols[None],
        torch.eye(4)[None, None],
        K[None, None],
        40,
        40,
        valid=keep[None],
    )
    full = render_gaussians(x, _settings())
    sub = _render1(means[keep], quats[keep], scales[keep], opac[keep], cols[keep], torch.eye(4), K, 40, 40)
    zero = _render1(means, quats, scales, torch.where(keep, opac, 0.0), cols, torch.eye(4), K, 40, 40)
    torch.testing.assert_close(full.rgb, sub.rgb, atol=1e-6, rtol=0)
    torch.testing.assert_close(zero.rgb, sub.rgb, atol=1e-6, rtol=0)


# --------------------------------------------------------------------------------------
# culling and empty scenes
# --------------------------------------------------------------------------------------


def test_near_far_culling():
    K = _intrinsics(40.0, 16.0, 16.0)
    m, q, s, o, c = _one([0.0, 0.0, 0.005], 0.9, [1.0, 1.0, 1.0], scale=0.001)
    out = _render1(m, q, s, o, c, torch.eye(4), K, 32, 32, _settings(near_plane=0.01))
    assert out.alpha.max() == 0 and out.meta["radii"].max() == 0
    out = _render1(m, q, s, o, c, torch.eye(4), K, 32, 32, _settings(near_plane=0.001))
    assert out.alpha.max() > 0.5
    m, q, s, o, c = _one([0.0, 0.0, 5.0], 0.9, [1.0, 1.0, 1.0], scale=0.2)
    assert _render1(m, q, s, o, c, torch.eye(4), K, 32, 32, _settings(far_plane=4.0)).alpha.max() == 0
    assert _render1(m, q, s, o, c, torch.eye(4), K, 32, 32, _settings(far_plane=6.0)).alpha.max() > 0.5
    m, q, s, o, c = _one([0.0, 0.0, -1.0], 0.9, [1.0, 1.0, 1.0], scale=0.2)  # behind the camera
    assert _render1(m, q, s, o, c, torch.eye(4), K, 32, 32).alpha.max() == 0


@pytest.mark.parametrize("n", [0, 3])
def test_empty_scene_gives_background(n):
    K = _intrinsics(40.0, 10.0, 8.0)
    means = torch.rand(1, n, 3) + torch.tensor([0.0, 0.0, 1.0])
    quats = torch.randn(1, n, 4)
    scales = torch.full((1, n, 3), 0.01)
    opac = torch.zeros(1, n)  # zero opacity: culled
    cols = torch.rand(1, n, 3)
    bg = torch.tensor([[[0.2, 0.5, 0.7]]])
    x = SplatInputs(
        means,
        quats,
        scales,
        opac,
        cols,
        torch.eye(4)[None, None],
        K[None, None],
        20,
        17,
        backgrounds=bg,
        part_ids=torch.zeros(1, n, dtype=torch.long),
    )
    out = render_gaussians(x, _settings(num_parts=2))
    assert out.rgb.shape == (1, 1, 17, 20, 3)
    assert torch.equal(out.rgb, bg[:, :, None, None, :].expand(1, 1, 17, 20, 3))
    assert out.alpha.eq(0).all() and out.depth.eq(0).all() and out.part_alpha.eq(0).all()
    assert out.meta["n_isects"] == 0


# --------------------------------------------------------------------------------------
# the two compositors
# --------------------------------------------------------------------------------------


def _two_image_scene(dtype):
    """Two samples, two cameras each: RGB + depth + parts, a background, padding Gaussians,
    and Gaussians large enough that many pixels saturate (stop before the list's end)."""
    g = torch.Generator().manual_seed(11)
    B, C, N, W, H = 2, 2, 600, 45, 37
    means = (torch.rand(B, N, 3, generator=g, dtype=torch.float64) - 0.5) * torch.tensor(
        [0.2, 0.2, 0.2]
    ) + torch.tensor([0.0, 0.0, 0.7])
    quats = torch.randn(B, N, 4, generator=g, dtype=torch.float64)
    scales = torch.exp(torch.empty(B, N, 3, dtype=torch.float64).uniform_(math.log(0.004), math.log(0.04), generator=g))
    opac = torch.rand(B, N, generator=g, dtype=torch.float64) * 0.7 + 0.29
    cols = torch.rand(B, N, 3, generator=g, dtype=torch.float64)
    viewmats = torch.stack(
        [
            torch.stack(
                [_look_at((0.0, 0.0, 0.0), dtype=torch.float64), _look_at((0.08, -0.05, 0.02), dtype=torch.float64)]
            )
        ]
        * B
    )
    Ks = _intrinsics(50.0, 22.0, 18.5, torch.float64).expand(B, C, 3, 3)
    valid = torch.rand(B, N, generator=g) > 0.1
    part_ids = torch.randint(-1, 3, (B, N), generator=g)
    bg = torch.rand(B, C, 3, generator=g, dtype=torch.float64)
    tensors = [t.to(dtype) for t in (means, quats, scales, opac, cols, viewmats, Ks, bg)]
    return tensors, dict(W=W, H=H, valid=valid, part_ids=part_ids)


@pytest.mark.parametrize("compositor", ["both"])  # compares the two itself (overrides the fixture)
@pytest.mark.parametrize("dtype,tol", [(torch.float64, 1e-10), (torch.float32, 5e-5)])
def test_compositors_agree(compositor, dtype, tol):
    """The compiled kernels give the PyTorch compositor's images and gradients (float64:
    to ~1e-10; float32: to rounding of the different evaluation order)."""
    (means, quats, scales, opac, cols, viewmats, Ks, bg), kw = _two_image_scene(dtype)
    wr = torch.rand(2, 2, kw["H"], kw["W"], 8, generator=torch.Generator().manual_seed(3), dtype=dtype)
    results = {}
    for comp in ("torch", "numba"):
        ins = [t.clone().requires_grad_(True) for t in (means, quats, scales, opac, cols)]
        x = SplatInputs(
            *ins, viewmats, Ks, kw["W"], kw["H"], backgrounds=bg, part_ids=kw["part_ids"], valid=kw["valid"]
        )
        out = render_gaussians(x, _settings(num_parts=3, compositor=comp))
        img = torch.cat([out.rgb, out.alpha, out.depth, out.part_alpha], -1)
        (img * wr).sum().backward()
        results[comp] = (img.detach(), [t.grad for t in ins], out.meta["n_isects"])
    img_t, grads_t, n_t = results["torch"]
    img_n, grads_n, n_n = results["numba"]
    assert n_t == n_n > 1000
    saturated = (1.0 - img_t[..., 3]).lt(1e-3).float().mean()
    assert 0.05 < saturated < 0.95  # the stop rule is exercised, and so are unsaturated pixels
    torch.testing.assert_close(img_n, img_t, rtol=0, atol=tol)
    for name, gt, gn in zip(("means", "quats", "scales", "opacities", "colors"), grads_t, grads_n, strict=True):
        scale = gt.abs().max()
        assert scale > 0, name
        torch.testing.assert_close(gn / scale, gt / scale, rtol=0, atol=tol * 10, msg=name)


def test_compositor_choice_is_checked():
    means, quats, scales, opac, cols = _ball_scene(10, 1)
    args = SplatInputs(
        means[None],
        quats[None],
        scales[None],
        opac[None],
        cols[None],
        torch.eye(4)[None, None],
        _intrinsics(30.0, 8.0, 8.0)[None, None],
        16,
        16,
    )
    with pytest.raises(ValueError, match="compositor must be"):
        render_gaussians(args, _settings(compositor="cuda"))
    with pytest.raises(ValueError, match="float32 or float64"):
        render_gaussians(
            SplatInputs(*(a.half() if isinstance(a, torch.Tensor) else a for a in args)), _settings(compositor="numba")
        )
    half = render_gaussians(
        SplatInputs(*(a.bfloat16() if isinstance(a, torch.Tensor) else a for a in args)), _settings(compositor="auto")
    )
    assert half.rgb.dtype == torch.bfloat16  # "auto" falls back to the PyTorch compositor
    # opacities above 1 reach beyond the radius, where the kernels do not look: the PyTorch path
    big = args._replace(scales=scales[None] * 4, opacities=(opac[None] * 3).clamp(min=1.5))
    with pytest.raises(ValueError, match="opacity is above 1"):
        render_gaussians(big, _settings(compositor="numba"))
    torch.testing.assert_close(
        render_gaussians(big, _settings(compositor="auto")).rgb,
        render_gaussians(big, _settings(compositor="torch")).rgb,
        rtol=0,
        atol=0,
    )


def test_second_order_gradients_are_refused_by_the_kernels():
    means, quats, scales, opac, cols = _ball_scene(10, 1)
    m = means[None].clone().requires_grad_(True)
    x = SplatInputs(
        m,
        quats[None],
        scales[None],
        opac[None],
        cols[None],
        torch.eye(4)[None, None],
        _intrinsics(30.0, 8.0, 8.0)[None, None],
        16,
        16,
    )
    out = render_gaussians(x, _settings(compositor="numba"))
    with pytest.raises(RuntimeError, match="first-order gradients only"):
        torch.autograd.grad(out.rgb.sum(), m, create_graph=True)


def test_warm_up_runs_under_no_grad():
    """Called under ``no_grad`` (as a parent process does before forking renderers), the warm-up
    compiles both the forward and the backward kernel for float32 and leaves grad mode as it
    was; checked in a fresh process, where nothing else has compiled them."""
    import subprocess
    import sys

    from hogsa_loader.render import splat_kernels

    if not splat_kernels.AVAILABLE:
        pytest.skip("numba is not installed: no compiled compositor to warm up")
    code = (
        "import torch\n"
        "from hogsa_loader.render import splat_kernels as k\n"
        "from hogsa_loader.render.gaussians import warm_up_compositor\n"
        "assert not k.composite_forward.signatures and not k.composite_backward.signatures\n"
        "with torch.no_grad():\n"
        "    warm_up_compositor()\n"
        "    assert not torch.is_grad_enabled()\n"
        "print(len(k.composite_forward.signatures), len(k.composite_backward.signatures))\n"
        "print(str(k.composite_forward.signatures[0]).count('float32') > 0)\n"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=600)
    assert out.returncode == 0, out.stderr[-2000:]
    assert out.stdout.split() == ["1", "1", "True"]
