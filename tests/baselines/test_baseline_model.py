"""ArcticNet-SF baseline: ResNet trunk, model forward/backward, training targets, checkpoints.

Samples are built here with the project's sample builder from posed synthetic hands and
small in-memory object templates, in an egocentric-style setup whose patch camera is
exact (whole-image box, GT-K rule, principal point at the image centre), so the 3D
labels, the 2D labels and the intrinsics agree up to the HMR integer truncation of the
2D labels (< 1 px).
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest
import torch
from torch.utils.data import default_collate

from hogsa_loader.assets.hands.mano import MANOLayer
from hogsa_loader.assets.objects.articulated import ArticulatedObjectLayer
from hogsa_loader.assets.objects.template import ObjectTemplate, bbox_corners
from hogsa_loader.baselines import (
    ArcticNetSF,
    arctic_key_map,
    build_backbone,
    estimate_translation_k,
    load_arctic_checkpoint,
    load_backbone_weights,
    matrix_to_rotation_6d,
    perspective_to_weak_perspective,
    prepare_targets,
    resnet18,
    resnet50,
    rotation_6d_to_matrix,
    solve_rigid_transform,
    weak_perspective_to_perspective,
)
from hogsa_loader.baselines.arcticnet_sf import ArtiHead, ManoHead, patch_intrinsics_wp, project2d
from hogsa_loader.errors import AssetError
from hogsa_loader.geometry.rotations import axis_angle_to_matrix
from hogsa_loader.sample.augment import ArcticConfig, AugParams, normalize_kp2d, rot_aa
from hogsa_loader.sample.interfield import interaction_field
from hogsa_loader.sample.targets import HandLabels, ObjectLabels, make_arctic_sample
from hogsa_world.hand import HandSpec, synthetic_hand_pair

pytestmark = pytest.mark.usefixtures("one_thread")


K_FULL = np.array([[600.0, 0.0, 320.0], [0.0, 600.0, 240.0], [0.0, 0.0, 1.0]])
IMAGE_SIZE = (640, 480)

# --------------------------------------------------------------------------------------
# torchvision's ResNet names and shapes, written out independently of the implementation
# --------------------------------------------------------------------------------------


def _bn(prefix: str, c: int) -> dict[str, tuple[int, ...]]:
    return {
        f"{prefix}.weight": (c,),
        f"{prefix}.bias": (c,),
        f"{prefix}.running_mean": (c,),
        f"{prefix}.running_var": (c,),
        f"{prefix}.num_batches_tracked": (),
    }


def torchvision_resnet_shapes(arch: str) -> dict[str, tuple[int, ...]]:
    """torchvision ``resnet18`` / ``resnet50`` state-dict shapes without ``fc``."""
    bottleneck = arch == "resnet50"
    layers = (3, 4, 6, 3) if bottleneck else (2, 2, 2, 2)
    exp = {"conv1.weight": (64, 3, 7, 7), **_bn("bn1", 64)}
    c_in = 64
    for s, (planes, n) in enumerate(zip((64, 128, 256, 512), layers), start=1):
        c_out = planes * (4 if bottleneck else 1)
        for b in range(n):
            p = f"layer{s}.{b}"
            if bottleneck:
                exp.update(
                    {
                        f"{p}.conv1.weight": (planes, c_in, 1, 1),
                        **_bn(f"{p}.bn1", planes),
                        f"{p}.conv2.weight": (planes, planes, 3, 3),
                        **_bn(f"{p}.bn2", planes),
                        f"{p}.conv3.weight": (c_out, planes, 1, 1),
                        **_bn(f"{p}.bn3", c_out),
                    }
                )
            else:
                exp.update(
                    {
                        f"{p}.conv1.weight": (planes, c_in, 3, 3),
                        **_bn(f"{p}.bn1", planes),
                        f"{p}.conv2.weight": (planes, planes, 3, 3),
                        **_bn(f"{p}.bn2", planes),
                    }
                )
            if b == 0 and (s > 1 or c_in != c_out):
                exp.update({f"{p}.downsample.0.weight": (c_out, c_in, 1, 1), **_bn(f"{p}.downsample.1", c_out)})
            c_in = c_out
    return exp


@pytest.mark.parametrize("arch,n_params,n_entries", [("resnet18", 11_176_512, 120), ("resnet50", 23_508_032, 318)])
def test_resnet_matches_torchvision_layout(arch: str, n_params: int, n_entries: int) -> None:
    torch.manual_seed(0)
    model = {"resnet18": resnet18, "resnet50": resnet50}[arch]()
    shapes = {k: tuple(v.shape) for k, v in model.state_dict().items()}
    assert shapes == torchvision_resnet_shapes(arch)
    assert len(shapes) == n_entries
    assert sum(p.numel() for p in model.parameters()) == n_params  # torchvision's count minus fc
    assert not any(k.startswith(("fc.", "avgpool")) for k in shapes)
    # torchvision init: kaiming normal (fan_out, relu) convs, BN weight 1 / bias 0
    std = model.conv1.weight.std().item()
    assert abs(std - math.sqrt(2.0 / (64 * 7 * 7))) < 0.1 * std
    assert torch.all(model.layer2[0].bn1.weight == 1) and torch.all(model.layer2[0].bn1.bias == 0)
    with torch.no_grad():
        out = model.eval()(torch.randn(1, 3, 64, 96))
    assert out.shape == (1, model.out_channels, 2, 3)


@pytest.mark.parametrize("arch", ["resnet18", "resnet50"])
def test_resnet_equals_torchvision_on_the_same_weights(arch: str) -> None:
    """The trunk computes what torchvision's ResNet computes with the same weights. Reported as
    skipped where no torchvision matching the installed torch loads (PyPI's torchvision wheels
    are CUDA builds, which a CPU-only torch cannot load: so on CI's machines)."""
    try:
        import torchvision.models as tvm
    except Exception as exc:  # missing, or built for another torch (RuntimeError / OSError on load)
        pytest.skip(f"no torchvision matching the installed torch ({type(exc).__name__})")
    torch.manual_seed(0)
    model = {"resnet18": resnet18, "resnet50": resnet50}[arch]()
    ref = getattr(tvm, arch)().eval()
    state = model.state_dict()
    ref.load_state_dict({**state, "fc.weight": ref.fc.weight, "fc.bias": ref.fc.bias})
    trunk = torch.nn.Sequential(*list(ref.children())[:-2])
    x = torch.randn(2, 3, 64, 64)
    with torch.no_grad():
        torch.testing.assert_close(model(x), trunk(x), rtol=1e-4, atol=1e-5)


def test_load_backbone_weights_pth_safetensors_and_errors(tmp_path: Path) -> None:
    from safetensors.torch import save_file

    torch.manual_seed(1)
    src = resnet18()
    for m in src.modules():  # non-trivial BN statistics
        if isinstance(m, torch.nn.BatchNorm2d):
            m.running_mean.uniform_(-0.1, 0.1)
            m.running_var.uniform_(0.5, 1.5)
    state = {**src.state_dict(), "fc.weight": torch.randn(1000, 512), "fc.bias": torch.randn(1000)}
    old_style = {k: v for k, v in state.items() if not k.endswith("num_batches_tracked")}
    torch.save(old_style, tmp_path / "resnet18.pth")
    save_file({k: v.contiguous() for k, v in state.items()}, str(tmp_path / "resnet18.safetensors"))
    x = torch.randn(1, 3, 64, 64)
    with torch.no_grad():
        want = src.eval()(x)
        for name in ("resnet18.pth", "resnet18.safetensors"):
            dst = build_backbone("resnet18", tmp_path / name).eval()
            torch.testing.assert_close(dst(x), want)
    bad = dict(old_style)
    bad.pop("layer4.1.bn2.weight")
    bad["extra.weight"] = torch.zeros(1)
    bad["conv1.weight"] = torch.zeros(64, 3, 3, 3)
    torch.save(bad, tmp_path / "bad.pth")
    with pytest.raises(AssetError, match=r"bad\.pth.*layer4\.1\.bn2\.weight.*extra\.weight.*shape mismatch.*conv1"):
        load_backbone_weights(resnet18(), tmp_path / "bad.pth")
    with pytest.raises(AssetError, match="missing"):
        load_backbone_weights(resnet18(), tmp_path / "nope.pth")


# --------------------------------------------------------------------------------------
# Rotations and cameras
# --------------------------------------------------------------------------------------


def test_rotation_6d_round_trip_and_row_convention() -> None:
    g = torch.Generator().manual_seed(0)
    R = axis_angle_to_matrix(torch.randn(200, 3, generator=g) * 1.5)
    torch.testing.assert_close(rotation_6d_to_matrix(matrix_to_rotation_6d(R)), R, atol=1e-6, rtol=0)
    d6 = torch.randn(50, 6, generator=g)
    M = rotation_6d_to_matrix(d6)
    torch.testing.assert_close(M @ M.transpose(1, 2), torch.eye(3).expand(50, 3, 3), atol=1e-6, rtol=0)
    torch.testing.assert_close(torch.linalg.det(M), torch.ones(50), atol=1e-6, rtol=0)
    # rows: the first row is the normalised first 3-vector, the second lies in its plane
    torch.testing.assert_close(M[:, 0], d6[:, :3] / d6[:, :3].norm(dim=1, keepdim=True))
    assert torch.allclose((torch.linalg.cross(d6[:, :3], d6[:, 3:]) * M[:, 1]).sum(1), torch.zeros(50), atol=1e-5)
    torch.testing.assert_close(M[:, 2], torch.linalg.cross(M[:, 0], M[:, 1]))


def test_weak_perspective_round_trip_and_min_scale() -> None:
    g = torch.Generator().manual_seed(0)
    cam_t = torch.cat([torch.randn(64, 2, generator=g) * 0.1, 0.3 + 2 * torch.rand(64, 1, generator=g)], 1)
    focal = 800 + 400 * torch.rand(64, generator=g)
    wp = perspective_to_weak_perspective(cam_t, focal, 224)
    torch.testing.assert_close(wp[:, 0], 2 * focal / (224 * cam_t[:, 2]))
    torch.testing.assert_close(weak_perspective_to_perspective(wp, focal, 224), cam_t, rtol=1e-6, atol=1e-6)
    # s below 0.1 is clamped: tz = 2 f / (224 · 0.1)
    tz = weak_perspective_to_perspective(torch.tensor([[0.01, 0.2, -0.1], [-3.0, 0.0, 0.0]]), 1000.0, 224)[:, 2]
    torch.testing.assert_close(tz, torch.full((2,), 2000.0 / 22.4))


def test_translation_and_rigid_solvers_are_exact_on_exact_data() -> None:
    g = torch.Generator().manual_seed(0)
    X = torch.randn(4, 16, 3, generator=g) * 0.08
    t = torch.tensor([[0.05, -0.02, 0.6], [0.0, 0.1, 0.9], [-0.1, 0.0, 0.45], [0.02, 0.03, 1.2]])
    K = torch.tensor([[500.0, 0, 110], [0, 520.0, 115], [0, 0, 1]]).expand(4, 3, 3)
    uv = project2d(K, X + t[:, None])
    torch.testing.assert_close(estimate_translation_k(X, uv, K), t, atol=1e-5, rtol=0)
    w = torch.ones(4, 16)
    w[:, 0] = 0.0  # a zero-weight outlier does not matter
    uv_bad = uv.clone()
    uv_bad[:, 0] += 40.0
    torch.testing.assert_close(estimate_translation_k(X, uv_bad, K, w), t, atol=1e-5, rtol=0)
    R = axis_angle_to_matrix(torch.randn(4, 3, generator=g))
    R_est, t_est = solve_rigid_transform(X, X @ R.transpose(1, 2) + t[:, None])
    torch.testing.assert_close(R_est, R, atol=1e-5, rtol=0)
    torch.testing.assert_close(t_est, t, atol=1e-5, rtol=0)


# --------------------------------------------------------------------------------------
# A small world: synthetic hands, two in-memory objects, samples from the sample builder
# --------------------------------------------------------------------------------------


def _template(name: str, n_verts: int, size: float, seed: int) -> ObjectTemplate:
    rng = np.random.default_rng(seed)
    verts = rng.uniform(-size, size, (n_verts, 3)) * np.array([1.0, 1.0, 0.5])
    parts = (verts[:, 2] < 0).astype(np.int64)  # top (0) above the hinge plane
    top, bottom = verts[parts == 0], verts[parts == 1]
    faces = np.array([[i, i + 1, i + 2] for i in range(n_verts - 2)])
    return ObjectTemplate(
        name=name,
        verts=verts,
        faces=faces,
        parts=parts,
        kp_top=top[:16],
        kp_bottom=bottom[:16],
        bbox_top=bbox_corners(top),
        bbox_bottom=bbox_corners(bottom),
        mocap_top=np.zeros((0, 3)),
        mocap_bottom=np.zeros((0, 3)),
        sub_top=top[rng.integers(0, len(top), 300)],
        sub_bottom=bottom[rng.integers(0, len(bottom), 300)],
        diameter=2 * size,
    )


@pytest.fixture(scope="module")
def world():
    right, left = synthetic_hand_pair(HandSpec(voxel=0.007))  # coarse mesh: fast to build
    mano = {s: MANOLayer(m, flat_hand_mean=False).eval() for s, m in (("r", right), ("l", left))}
    templates = [_template("box", 300, 0.06, 0), _template("laptop", 420, 0.08, 1)]
    return {"mano": mano, "objects": ArticulatedObjectLayer(templates), "templates": templates}


def _scene(world, i: int) -> dict:
    """Camera-frame GT of one frame: hands and object near the optical axis at ~0.6 m."""
    g = torch.Generator().manual_seed(100 + i)
    name = ("box", "laptop")[i % 2]
    t_o = torch.tensor([[0.02 * i, -0.01, 0.55 + 0.05 * i]])
    obj = world["objects"](
        angles=torch.tensor([[0.3 + 0.2 * i]]), global_orient=torch.randn(1, 3, generator=g), transl=t_o, names=[name]
    )
    out = {
        "name": name,
        "radian": 0.3 + 0.2 * i,
        "kp3d": obj["kp3d"][0],
        "bbox3d": obj["bbox3d"][0],
        "v_o": obj["v"][0, : int(obj["v_len"][0])],
    }
    for s, dx in (("r", -0.07), ("l", 0.07)):
        pose = torch.cat([torch.randn(1, 3, generator=g), 0.3 * torch.randn(1, 45, generator=g)], 1)
        betas = 0.5 * torch.randn(1, 10, generator=g)
        m = world["mano"][s](
            global_orient=pose[:, :3], hand_pose=pose[:, 3:], betas=betas, transl=t_o + torch.tensor([[dx, 0.02, 0.01]])
        )
        out.update({f"pose.{s}": pose[0], f"betas.{s}": betas[0], f"j3d.{s}": m.joints[0], f"v3d.{s}": m.vertices[0]})
    return {k: (v.numpy().astype(np.float64) if torch.is_tensor(v) else v) for k, v in out.items()}


def _sample(world, scene: dict, aug: AugParams, cfg: ArcticConfig, image: np.ndarray):
    K = torch.as_tensor(K_FULL)[None]

    def px(p: np.ndarray) -> np.ndarray:
        return project2d(K, torch.as_tensor(p)[None])[0].numpy()

    hands = {
        s: HandLabels(
            pose48=scene[f"pose.{s}"],
            betas=scene[f"betas.{s}"],
            j3d_full=scene[f"j3d.{s}"],
            j2d=px(scene[f"j3d.{s}"]),
            valid=1.0,
        )
        for s in "rl"
    }
    tpl = next(t for t in world["templates"] if t.name == scene["name"])
    obj = ObjectLabels(
        name=scene["name"],
        radian=scene["radian"],
        kp3d_full=scene["kp3d"],
        bbox3d_full=scene["bbox3d"],
        kp2d=px(scene["kp3d"]),
        bbox2d=px(scene["bbox3d"]),
        valid=1.0,
        kp_bottom_cano=tpl.kp_bottom,
    )
    box = (IMAGE_SIZE[0] / 2, IMAGE_SIZE[1] / 2, max(IMAGE_SIZE) / 200)  # whole image: GT-K is exact
    return make_arctic_sample(
        image,
        box,
        K_FULL,
        IMAGE_SIZE,
        hands["r"],
        hands["l"],
        obj,
        egocentric=True,
        dist=None,
        aug=aug,
        imgname=f"s01/{scene['name']}_use_01/0/{scene['name']}.jpg",
        cfg=cfg,
    )


def _batch(world, n: int, aug: AugParams, img_res: int = 224):
    cfg = ArcticConfig(img_res=img_res)
    rng = np.random.default_rng(0)
    scenes = [_scene(world, i) for i in range(n)]
    image = rng.integers(0, 255, (IMAGE_SIZE[1], IMAGE_SIZE[0], 3)).astype(np.uint8)
    inputs, targets, meta = default_collate([_sample(world, s, aug, cfg, image) for s in scenes])
    return inputs, targets, meta, scenes


def _model(world, img_res: int) -> ArcticNetSF:
    torch.manual_seed(0)
    return ArcticNetSF("resnet18", world["mano"]["r"], world["mano"]["l"], world["objects"], img_res=img_res)


# --------------------------------------------------------------------------------------
# Model
# --------------------------------------------------------------------------------------

EXPECTED_KEYS = (
    [
        f"mano.{k}.{s}"
        for s in "rl"
        for k in (
            "cam_t.wp",
            "cam_t",
            "joints3d",
            "vertices",
            "j3d.cam",
            "v3d.cam",
            "j2d.norm",
            "beta",
            "pose",
            "cam_t.wp.init",
        )
    ]
    + [
        f"object.{k}"
        for k in (
            "rot",
            "cam_t.wp",
            "cam_t",
            "kp3d",
            "bbox3d",
            "bbox3d.cam",
            "kp3d.cam",
            "kp2d.norm",
            "kp2d.norm.t",
            "kp2d.norm.b",
            "bbox2d.norm.t",
            "bbox2d.norm.b",
            "radian",
            "v.cam",
            "v_len",
            "f",
            "f_len",
            "parts_ids",
            "cam_t.wp.init",
        )
    ]
    + ["feat_vec"]
)


def test_forward_backward_shapes_and_gradients(world) -> None:
    inputs, targets, meta, _ = _batch(world, 2, AugParams(), img_res=64)
    model = _model(world, 64).train()
    out = model(inputs, meta)
    assert list(out) == EXPECTED_KEYS
    V, J = world["mano"]["r"].num_verts, 21
    L = int(world["objects"].v_len.max())  # one box and one laptop: padded to the laptop
    shapes = {
        "mano.pose.r": (2, 16, 3, 3),
        "mano.beta.l": (2, 10),
        "mano.j3d.cam.r": (2, J, 3),
        "mano.v3d.cam.l": (2, V, 3),
        "mano.vertices.r": (2, V, 3),
        "mano.j2d.norm.r": (2, J, 2),
        "mano.cam_t.wp.init.l": (2, 3),
        "mano.cam_t.r": (2, 3),
        "object.rot": (2, 3),
        "object.radian": (2, 1),
        "object.kp3d.cam": (2, 32, 3),
        "object.kp2d.norm": (2, 32, 2),
        "object.kp2d.norm.t": (2, 16, 2),
        "object.bbox3d.cam": (2, 16, 3),
        "object.bbox2d.norm.b": (2, 8, 2),
        "object.v.cam": (2, L, 3),
        "object.v_len": (2,),
        "object.parts_ids": (2, L),
        "feat_vec": (2, 512),
    }
    for k, shape in shapes.items():
        assert tuple(out[k].shape) == shape, k
    for k, v in out.items():
        if v.is_floating_point():
            assert torch.isfinite(v).all(), k
    R = out["mano.pose.r"]
    torch.testing.assert_close(R @ R.transpose(-1, -2), torch.eye(3).expand_as(R).contiguous(), atol=1e-5, rtol=0)
    # camera: cam_t follows the weak-perspective output, j3d.cam = joints + cam_t
    f = 0.5 * (meta["intrinsics"][:, 0, 0] + meta["intrinsics"][:, 1, 1])
    torch.testing.assert_close(out["mano.cam_t.r"], weak_perspective_to_perspective(out["mano.cam_t.wp.r"], f, 64))
    torch.testing.assert_close(out["mano.j3d.cam.l"], out["mano.joints3d.l"] + out["mano.cam_t.l"][:, None])
    loss = sum(
        out[k].square().mean()
        for k in (
            "mano.j2d.norm.r",
            "mano.v3d.cam.l",
            "mano.beta.r",
            "object.kp2d.norm",
            "object.radian",
            "object.kp3d.cam",
        )
    )
    loss.backward()
    for name in (
        "backbone.conv1.weight",
        "backbone.layer4.1.conv2.weight",
        "head_r.cam_init.0.weight",
        "head_l.hmr_layer.decoders.pose_6d.weight",
        "head_o.hmr_layer.decoders.radian.weight",
        "head_o.hmr_layer.refine.0.weight",
    ):
        grad = dict(model.named_parameters())[name].grad
        assert grad is not None and torch.isfinite(grad).all() and grad.abs().sum() > 0, name
    assert not out["feat_vec"].requires_grad
    # no intrinsics: the fixed patch camera of focal_length
    model.eval()
    with torch.no_grad():
        K = patch_intrinsics_wp(1000.0, 64, 2)
        a = model(inputs, {"query_names": meta["query_names"]})
        b = model(inputs, {"query_names": meta["query_names"], "intrinsics": K})
    torch.testing.assert_close(a["object.kp2d.norm"], b["object.kp2d.norm"])


def test_refine_input_layout_and_initial_state(world) -> None:
    """The refine MLP sees [features, state] with ARCTIC's state order (checkpoint layout):
    hands: 6D pose (identity), betas (0), camera; object: rotation (0), angle (0), camera."""
    inputs, _, meta, _ = _batch(world, 2, AugParams(), img_res=64)
    model = _model(world, 64).eval()
    seen = {}
    for name in ("head_r", "head_o"):
        head = getattr(model, name)
        head.hmr_layer.refine[0].register_forward_pre_hook(lambda m, a, n=name: seen.setdefault(n, a[0].clone()))
        head.cam_init.register_forward_hook(lambda m, a, out, n=name: seen.setdefault(n + ".cam", out.clone()))
    with torch.no_grad():
        model(inputs, meta)
    C = 512
    x = seen["head_r"]
    assert x.shape == (2, C + 96 + 10 + 3)
    assert torch.equal(x[:, C : C + 96], torch.tensor([1.0, 0, 0, 0, 1, 0]).repeat(2, 16))
    assert torch.equal(x[:, C + 96 : C + 106], torch.zeros(2, 10))
    assert torch.equal(x[:, C + 106 :], seen["head_r.cam"])
    x = seen["head_o"]
    assert x.shape == (2, C + 3 + 1 + 3)
    assert torch.equal(x[:, C : C + 4], torch.zeros(2, 4)) and torch.equal(x[:, C + 4 :], seen["head_o.cam"])


# --------------------------------------------------------------------------------------
# Targets
# --------------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def prepared(world):
    inputs, targets, meta, scenes = _batch(world, 3, AugParams())
    t, m = prepare_targets(targets, meta, world["mano"]["r"], world["mano"]["l"], world["objects"])
    return targets, meta, scenes, t, m


def test_prepare_targets_reproduces_dataset_labels(world, prepared) -> None:
    targets, meta, scenes, t, m = prepared
    px = 2.0 / 224  # one patch pixel in normalised units; labels are truncated to pixels
    for s in "rl":
        j_full = targets[f"mano.j3d.full.{s}"]
        rr = t[f"mano.j3d.cam.{s}"] - t[f"mano.j3d.cam.{s}"][:, :1]
        torch.testing.assert_close(rr, j_full - j_full[:, :1], atol=1e-5, rtol=0)
        # the mesh sits on the joints as in the scene (vertices relative to the root joint)
        v_gt = torch.stack([torch.as_tensor(sc[f"v3d.{s}"]) for sc in scenes]).float()
        v_rel = t[f"mano.v3d.cam.{s}"] - t[f"mano.j3d.cam.{s}"][:, :1]
        torch.testing.assert_close(v_rel, v_gt - j_full[:, :1], atol=1e-5, rtol=0)
        # absolute position: off only by the translation fitted to truncated 2D labels
        assert (t[f"mano.j3d.cam.{s}"] - j_full).norm(dim=-1).max() < 0.01
        j2d = normalize_kp2d(project2d(meta["intrinsics"], t[f"mano.j3d.cam.{s}"]), 224)
        assert (j2d - targets[f"mano.j2d.norm.{s}"]).abs().max() < 1.5 * px
        assert t[f"mano.v3d.cam.{s}"].shape[1] == world["mano"][s].num_verts
    kp2d = normalize_kp2d(project2d(meta["intrinsics"], t["object.kp3d.cam"]), 224)
    assert (kp2d - targets["object.kp2d.norm"]).abs().max() < 1.5 * px
    kp_full = torch.cat([targets["object.kp3d.full.t"], targets["object.kp3d.full.b"]], 1)
    assert (t["object.kp3d.cam"] - kp_full).norm(dim=-1).max() < 0.01
    torch.testing.assert_close(
        t["object.kp3d.cam"] - t["object.kp3d.cam"][:, :1], kp_full - kp_full[:, :1], atol=1e-5, rtol=0
    )
    assert m["diameter"].tolist() == pytest.approx([0.12, 0.16, 0.12])
    assert m["part_ids"].shape == t["object.v.cam"].shape[:2] and "part_ids" not in meta
    assert t["object.v_len"].tolist() == [300, 420, 300]
    for k in ("mano.pose.r", "object.kp2d.norm.b", "is_valid"):  # inputs are kept
        assert t[k] is targets[k]


def test_targets_agree_with_the_model_heads(world, prepared) -> None:
    """Feeding the GT parameters and target cameras to the heads gives back the targets."""
    targets, meta, _, t, _ = prepared
    K = meta["intrinsics"]
    for s in "rl":
        head = ManoHead(world["mano"][s], 224)
        rot = axis_angle_to_matrix(targets[f"mano.pose.{s}"].view(-1, 16, 3))
        out = head(rot, targets[f"mano.beta.{s}"], t[f"mano.cam_t.wp.{s}"], K)
        torch.testing.assert_close(out["cam_t"], t[f"mano.cam_t.{s}"], atol=1e-5, rtol=1e-5)
        torch.testing.assert_close(out["j3d.cam"], t[f"mano.j3d.cam.{s}"], atol=2e-5, rtol=0)
    arti = ArtiHead(world["objects"], 224)
    out = arti(
        targets["object.rot"].view(-1, 3),
        targets["object.radian"].view(-1, 1),
        meta["query_names"],
        t["object.cam_t.wp"],
        K,
    )
    for k in ("kp3d.cam", "bbox3d.cam", "v.cam"):
        torch.testing.assert_close(out[k], t[f"object.{k}"], atol=2e-5, rtol=0)


def test_prepare_targets_interaction_field(world, prepared) -> None:
    _, _, _, t, _ = prepared
    L = t["object.v.cam"].shape[1]
    for b in range(3):
        n = int(t["object.v_len"][b])
        ref = interaction_field(t["mano.v3d.cam.r"][b], t["mano.v3d.cam.l"][b], t["object.v.cam"][b, :n], L)
        for k in ("ro", "lo", "or", "ol"):
            np.testing.assert_allclose(t[f"dist.{k}"][b].numpy(), ref[f"dist.{k}"], atol=1e-5, err_msg=k)
        assert (t["idx.or"][b, n:] == 0).all() and (t["dist.ol"][b, n:] == 0).all()
        # the index points at a vertex at that distance
        d = (t["mano.v3d.cam.r"][b] - t["object.v.cam"][b, t["idx.ro"][b]]).norm(dim=-1)
        torch.testing.assert_close(d, t["dist.ro"][b], atol=1e-5, rtol=0)
    assert t["dist.ro"].shape == t["mano.v3d.cam.r"].shape[:2] and t["dist.or"].shape == (3, L)


def test_prepare_targets_hand_field_only_keeps_every_other_target(world, prepared) -> None:
    targets, meta, _, t, _ = prepared
    t2, _ = prepare_targets(targets, meta, world["mano"]["r"], world["mano"]["l"], world["objects"], field="hands")
    dropped = {f"{k}.{d}" for k in ("dist", "idx") for d in ("or", "ol")}
    assert dropped <= set(t) and set(t2) == set(t) - dropped
    for k in t2:
        if isinstance(t2[k], torch.Tensor):
            torch.testing.assert_close(t2[k], t[k], atol=0, rtol=0, msg=k)


def test_prepare_targets_follow_the_rotation_augmentation(world) -> None:
    aug = AugParams(rot=25.0)
    _, targets, meta, _ = _batch(world, 2, aug)
    t, _ = prepare_targets(targets, meta, world["mano"]["r"], world["mano"]["l"], world["objects"])
    R_aug = torch.as_tensor(axis_angle_to_matrix(torch.as_tensor(rot_aa(np.zeros(3), aug.rot)))).float()
    j_full = targets["mano.j3d.full.r"]
    rr = t["mano.j3d.cam.r"] - t["mano.j3d.cam.r"][:, :1]
    torch.testing.assert_close(rr, (j_full - j_full[:, :1]) @ R_aug.T, atol=1e-5, rtol=0)
    kp2d = normalize_kp2d(project2d(meta["intrinsics"], t["object.kp3d.cam"]), 224)
    assert (kp2d - targets["object.kp2d.norm"]).abs().max() < 1.5 * 2.0 / 224


# --------------------------------------------------------------------------------------
# ARCTIC checkpoints
# --------------------------------------------------------------------------------------


def arctic_head_shapes(feat: int, hand: bool) -> dict[str, tuple[int, ...]]:
    """ARCTIC's HandHMR / ObjectHMR parameter names and shapes."""
    specs = {"pose_6d": 96, "cam_t/wp": 3, "shape": 10} if hand else {"rot": 3, "cam_t/wp": 3, "radian": 1}
    n_in = feat + sum(specs.values())
    out = {
        "hmr_layer.refine.0.weight": (1024, n_in),
        "hmr_layer.refine.0.bias": (1024,),
        "hmr_layer.refine.3.weight": (1024, 1024),
        "hmr_layer.refine.3.bias": (1024,),
    }
    for k, n in specs.items():
        out.update({f"hmr_layer.decoders.{k}.weight": (n, 1024), f"hmr_layer.decoders.{k}.bias": (n,)})
    out.update(
        {
            "cam_init.0.weight": (512, feat),
            "cam_init.0.bias": (512,),
            "cam_init.2.weight": (512, 512),
            "cam_init.2.bias": (512,),
            "cam_init.4.weight": (3, 512),
            "cam_init.4.bias": (3,),
        }
    )
    return out


def smplx_mano_shapes(V: int, F: int) -> dict[str, tuple[int, ...]]:
    """State dict of smplx 0.1.28 ``MANO(use_pca=False, flat_hand_mean=False, create_transl=False)``."""
    return {
        "betas": (1, 10),
        "global_orient": (1, 3),
        "body_pose": (1, 3),
        "hand_pose": (1, 45),
        "shapedirs": (V, 3, 10),
        "faces_tensor": (F, 3),
        "v_template": (V, 3),
        "J_regressor": (16, V),
        "posedirs": (135, 3 * V),
        "parents": (16,),
        "lbs_weights": (V, 16),
        "hand_mean": (45,),
        "pose_mean": (48,),
        "vertex_joint_selector.extra_joints_idxs": (5,),
    }


@pytest.mark.filterwarnings("ignore::DeprecationWarning")  # smplx imports scipy.sparse.csc
def test_smplx_mano_state_dict_names(world, tmp_path: Path, chumpy_shim) -> None:
    """The smplx MANO names listed above are the real ones (smplx is a test dependency)."""
    smplx = pytest.importorskip("smplx")
    from hogsa_world.mano_pickle import write_mano_pickle

    data = world["mano"]["r"].data
    write_mano_pickle(data, tmp_path / "MANO_RIGHT.pkl")
    m = smplx.MANO(str(tmp_path), create_transl=False, use_pca=False, flat_hand_mean=False, is_rhand=True)
    V, F = data.v_template.shape[0], data.faces.shape[0]
    assert {k: tuple(v.shape) for k, v in m.state_dict().items()} == smplx_mano_shapes(V, F)


def _arctic_lightning_state(feat: int, backbone: dict, random: bool = True) -> dict[str, torch.Tensor]:
    g = torch.Generator().manual_seed(3)
    net = {f"backbone.{k}": s for k, s in backbone.items()}
    for head, hand in (("head_r", True), ("head_l", True), ("head_o", False)):
        net.update({f"{head}.{k}": s for k, s in arctic_head_shapes(feat, hand).items()})
    mano = smplx_mano_shapes(778, 1538)
    state = {}
    for k, s in net.items():
        if k.endswith("num_batches_tracked"):
            state[f"model.{k}"] = torch.randint(0, 9, s, generator=g)
        else:
            state[f"model.{k}"] = torch.randn(s, generator=g) if random else torch.zeros(s)
    for prefix in ("model.mano_r.mano.", "model.mano_l.mano.", "mano_r.", "mano_l."):
        state.update({prefix + k: torch.zeros(s) for k, s in mano.items()})
    return state


def test_arctic_checkpoint_key_map_and_loading(world, tmp_path: Path) -> None:
    model = _model(world, 224)
    state = _arctic_lightning_state(512, torchvision_resnet_shapes("resnet18"))
    mapped = arctic_key_map(state)
    assert set(mapped) == set(model.network_state_dict())
    assert "head_r.hmr_layer.decoders.cam_t/wp.weight" in mapped
    assert not any(k.startswith(("mano_", "model.", "arti_head")) for k in mapped)
    # round trip: our own network weights under ARCTIC's Lightning prefix map back unchanged
    own = model.network_state_dict()
    back = arctic_key_map({**{f"model.{k}": v for k, v in own.items()}, "mano_r.v_template": torch.zeros(1)})
    assert back.keys() == own.keys() and all(back[k] is own[k] for k in own)
    assert arctic_key_map(own).keys() == own.keys()  # already un-prefixed
    torch.save({"state_dict": state, "epoch": 3, "global_step": 100}, tmp_path / "last.ckpt")
    load_arctic_checkpoint(model, tmp_path / "last.ckpt")
    now = model.state_dict()
    for k, v in state.items():
        if k.startswith("model.") and k[6:] in now:
            assert torch.equal(now[k[6:]], v.to(now[k[6:]].dtype)), k
    assert int(model.arti_head.object_tensors.v_len.max()) == 420  # our templates untouched
    broken = {k: v for k, v in state.items() if k != "model.head_o.hmr_layer.decoders.radian.bias"}
    broken["model.head_o.extra.weight"] = torch.zeros(1)
    torch.save({"state_dict": broken}, tmp_path / "broken.ckpt")
    with pytest.raises(AssetError, match=r"broken\.ckpt.*decoders\.radian\.bias.*head_o\.extra\.weight"):
        load_arctic_checkpoint(model, tmp_path / "broken.ckpt")
    r50 = _arctic_lightning_state(2048, torchvision_resnet_shapes("resnet50"), random=False)
    torch.save({"state_dict": r50}, tmp_path / "r50.ckpt")
    with pytest.raises(AssetError, match="resnet18 backbone"):
        load_arctic_checkpoint(model, tmp_path / "r50.ckpt")
