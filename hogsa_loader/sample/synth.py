"""The synthetic pipeline: one render batch of one HOGS model → SynthFrames.

:class:`SynthPipeline` renders a :class:`~hogsa_loader.sample.plan.BatchPlan` through named
stages (listed in its docstring). :func:`frame_to_sample` then applies ARCTIC's augmentation
and target construction through :func:`~hogsa_loader.sample.targets.make_arctic_sample`,
the function real samples go through. Every random draw comes from the streams of
:mod:`~hogsa_loader.sample.plan`.
"""

from __future__ import annotations

import time
from contextlib import contextmanager
from dataclasses import dataclass, field
from typing import Any, Callable, Iterator, Mapping, Optional

import numpy as np
import torch
from torch import Tensor

from hogsa_loader.assets.arctic import ArcticRoot
from hogsa_loader.assets.conventions import BBOX_PIXELS_PER_SCALE, CROP_ENLARGE, CROPPED_SIZE, EGO_IMAGE_SCALE
from hogsa_loader.compose import BackgroundSource, composite
from hogsa_loader.geometry.rotations import axis_angle_to_matrix, matrix_to_axis_angle
from hogsa_loader.models.gaussians.recombine import swap_hands
from hogsa_loader.sample.augment import ArcticConfig, AugParams
from hogsa_loader.sample.cameras import NOVEL_VIEW, CameraSampler
from hogsa_loader.sample.config import SampleChecks
from hogsa_loader.sample.frame import SynthFrame
from hogsa_loader.sample.plan import STREAM_AUG, BatchPlan, sample_rng
from hogsa_loader.sample.poses import PoseBatch, PoseSource
from hogsa_loader.sample.targets import HandLabels, ObjectLabels, make_arctic_sample
from hogsa_loader.sample.views import ViewGeometry, allocentric_views, apply_warp, egocentric_views

__all__ = [
    "STAGES",
    "DROP_REASONS",
    "SampleChecks",
    "SynthStats",
    "SynthPipeline",
    "Refiner",
    "BatchPlan",
    "STREAM_AUG",
    "frame_to_sample",
    "source_scale",
    "sample_rng",
    "synthetic_imgname",
    "parse_synthetic_imgname",
    "is_synthetic",
    "joints_on_alpha",
]

#: Timed stages, in pipeline order (keys of :attr:`SynthStats.seconds`).
STAGES: tuple[str, ...] = ("pose", "pom", "render", "srm", "composite", "targets")
#: Reasons a sample is dropped (keys of :attr:`SynthStats.dropped`).
DROP_REASONS: tuple[str, ...] = ("nan", "behind_camera", "empty_alpha", "out_of_crop", "label_pixel_mismatch", "pom")
#: Prefix of synthetic ``meta_info["imgname"]`` values.
SYNTH_PREFIX = "./hogsa_synth/"

Refiner = Callable[[Tensor, Tensor], Tensor]
#: The default drop rules.
DEFAULT_CHECKS = SampleChecks()


def synthetic_imgname(subject: str, obj: str, seed: int, epoch: int, view: int, index: int) -> str:
    """``meta_info["imgname"]`` of a synthetic sample.

    ``./hogsa_synth/<sid>/<obj>_synth_s<seed>e<epoch>/<view>/<index:09d>.jpg`` — parsed by
    :func:`~hogsa_loader.sample.arctic_dataset.parse_imgname` like a real ARCTIC name
    (``seq = <obj>_synth_...`` so the object name comes first); ``view`` is the dataset
    view used or :data:`~hogsa_loader.sample.cameras.NOVEL_VIEW`.
    """
    return f"{SYNTH_PREFIX}{subject}/{obj}_synth_s{int(seed)}e{int(epoch)}/{int(view)}/{int(index):09d}.jpg"


def is_synthetic(imgname: str) -> bool:
    """True for ``imgname`` values made by :func:`synthetic_imgname`."""
    return str(imgname).startswith(SYNTH_PREFIX)


def parse_synthetic_imgname(imgname: str) -> dict[str, Any]:
    """Inverse of :func:`synthetic_imgname`: ``{"subject", "object", "seed", "epoch", "view", "index"}``."""
    if not is_synthetic(imgname):
        raise ValueError(f"not a synthetic image name: {imgname!r}")
    sid, seq, view, fname = imgname[len(SYNTH_PREFIX) :].split("/")
    obj, _, tag = seq.rpartition("_synth_")
    seed, _, epoch = tag[1:].partition("e")
    return {
        "subject": sid,
        "object": obj,
        "seed": int(seed),
        "epoch": int(epoch),
        "view": int(view),
        "index": int(fname.split(".")[0]),
    }


@dataclass
class SynthStats:
    """Counters of one process's synthetic pipeline.

    Attributes:
        attempted: samples rendered (kept + dropped).
        kept: samples that passed the checks.
        dropped: ``{reason: count}`` over :data:`DROP_REASONS`.
        seconds: ``{stage: seconds}`` over :data:`STAGES` (wall clock, summed).
        batches: render batches made.
    """

    attempted: int = 0
    kept: int = 0
    dropped: dict[str, int] = field(default_factory=lambda: {r: 0 for r in DROP_REASONS})
    seconds: dict[str, float] = field(default_factory=lambda: {s: 0.0 for s in STAGES})
    batches: int = 0

    @property
    def num_dropped(self) -> int:
        """Total dropped samples."""
        return int(sum(self.dropped.values()))

    def reset(self) -> None:
        """Zero every counter."""
        self.__init__()  # type: ignore[misc]

    def to_vector(self) -> np.ndarray:
        """(3 + len(DROP_REASONS) + len(STAGES),) float64: ``attempted``, ``kept``,
        ``batches``, the drops by reason (:data:`DROP_REASONS` order; other reasons count
        under the last one) and the seconds by stage (:data:`STAGES` order)."""
        drops = [float(self.dropped.get(r, 0)) for r in DROP_REASONS]
        drops[-1] += float(sum(v for k, v in self.dropped.items() if k not in DROP_REASONS))
        return np.array(
            [self.attempted, self.kept, self.batches, *drops, *(self.seconds.get(st, 0.0) for st in STAGES)],
            dtype=np.float64,
        )

    @classmethod
    def from_vector(cls, v: Any) -> "SynthStats":
        """Inverse of :meth:`to_vector`."""
        v = np.asarray(v, dtype=np.float64)
        nd = len(DROP_REASONS)
        return cls(
            attempted=int(round(v[0])),
            kept=int(round(v[1])),
            batches=int(round(v[2])),
            dropped={r: int(round(x)) for r, x in zip(DROP_REASONS, v[3 : 3 + nd])},
            seconds={st: float(x) for st, x in zip(STAGES, v[3 + nd :])},
        )

    def as_dict(self) -> dict[str, Any]:
        """JSON-able copy."""
        return {
            "attempted": self.attempted,
            "kept": self.kept,
            "dropped": dict(self.dropped),
            "num_dropped": self.num_dropped,
            "seconds": dict(self.seconds),
            "batches": self.batches,
        }

    @contextmanager
    def timed(self, stage: str, device: Optional[torch.device] = None) -> Iterator[None]:
        """Add the wall time of the block to ``seconds[stage]`` (synchronising CUDA)."""
        sync = device is not None and device.type == "cuda"
        if sync:
            torch.cuda.synchronize(device)
        t0 = time.perf_counter()
        try:
            yield
        finally:
            if sync:
                torch.cuda.synchronize(device)
            self.seconds[stage] = self.seconds.get(stage, 0.0) + time.perf_counter() - t0


def joints_on_alpha(points: np.ndarray, alpha: np.ndarray, threshold: float = 0.5, radius: int = 1) -> np.ndarray:
    """Which 2D points lie on an alpha mask.

    Args:
        points: (N, 2) pixel coordinates (pixel i centred on coordinate i).
        alpha: (H, W) opacity.
        threshold: alpha above this counts as covered.
        radius: look at the (2r+1)² pixels around the nearest one (0 = nearest only).

    Returns:
        (N,) bool; points outside the image are False.
    """
    H, W = alpha.shape
    pts = np.rint(np.asarray(points, dtype=np.float64)).astype(np.int64)
    out = np.zeros(len(pts), dtype=bool)
    for i, (x, y) in enumerate(pts):
        if 0 <= x < W and 0 <= y < H:
            win = alpha[max(0, y - radius) : y + radius + 1, max(0, x - radius) : x + radius + 1]
            out[i] = bool(win.max() > threshold)
    return out


def source_scale(frame: SynthFrame) -> float:
    """Pixels of ``frame.image`` per pixel of the image the real dataset reads for this view.

    Allocentric: a cropped image shows the box enlarged 1.5× at ``cropped_size`` px
    (ARCTIC: 1000), so the box spans ``cropped_size / 1.5`` px there and ``200 · scale`` px
    here. Egocentric: the whole frame is read at ``ego_image_scale`` of its size (ARCTIC:
    0.3); the synthetic frame is the whole frame at ``width / W``. Both sizes are the
    world's (``frame.meta["cropped_size"]`` / ``["ego_image_scale"]``, recorded by the
    pipeline from ``world_meta()``; ARCTIC's values when absent).
    """
    if frame.egocentric:
        ego_scale = float(frame.meta.get("ego_image_scale", EGO_IMAGE_SCALE))
        return float(frame.image.shape[1]) / float(frame.image_size[0]) / ego_scale
    cropped = float(frame.meta.get("cropped_size", CROPPED_SIZE))
    return float(frame.bbox[2]) * BBOX_PIXELS_PER_SCALE * CROP_ENLARGE / cropped


def frame_to_sample(
    frame: SynthFrame, aug: AugParams, cfg: ArcticConfig = ArcticConfig()
) -> tuple[dict[str, Any], dict[str, Any], dict[str, Any]]:
    """ARCTIC's augmentation and targets of one synthetic frame (real samples' code path).

    Args:
        frame: the composited crop and its labels.
        aug: augmentation (e.g. :func:`~hogsa_loader.sample.augment.sample_aug_params`).
        cfg: sample settings (those of the real dataset being matched).

    Returns:
        ``(inputs, targets, meta_info)`` exactly like
        :class:`~hogsa_loader.sample.arctic_dataset.ArcticDataset` items. The one
        difference from a real sample's path: ARCTIC's source blur is scaled to the
        synthetic image's pixel size (:func:`source_scale`), so both blur the patch alike.
    """
    inputs, targets, meta = make_arctic_sample(
        image=frame.image,
        bbox=frame.bbox,
        K_full=frame.K_full,
        image_size=frame.image_size,
        right=frame.right,
        left=frame.left,
        obj=frame.obj,
        egocentric=frame.egocentric,
        dist=frame.dist,
        aug=aug,
        imgname=frame.imgname,
        query_name=frame.obj.name,
        cfg=cfg,
        source_scale=source_scale(frame),
    )
    targets.update(frame.extra_targets)
    return inputs, targets, meta


def _finite(*arrays: Any) -> bool:
    return all(bool(np.isfinite(np.asarray(a, dtype=np.float64)).all()) for a in arrays)


@dataclass
class _Posed:
    """Output of the ``poses`` stage: the pose batch, world-frame label points (float64
    ``joints.right|left`` (B,21,3), ``kp3d`` (B,32,3), ``bbox3d`` (B,16,3), ``verts``
    (B,V,3)) and the posed hand vertices ``{side: (B, Vh, 3)}``."""

    batch: PoseBatch
    geo: dict[str, np.ndarray]
    hand_verts: dict[str, Tensor]


@dataclass
class _Viewed:
    """Output of the ``views`` stage: the view geometry, the hands' camera-frame global
    orientations ``{side: (B, 3)}`` and the positions of the samples to render."""

    vg: ViewGeometry
    rot_cam: dict[str, np.ndarray]
    keep: list[int]


@dataclass
class _Pixels:
    """Output of the ``composite`` stage, for the kept samples (b = len(keep)): images
    (b, Ho, Wo, 3) uint8, alpha (b, Ho, Wo), part alpha (b, Ho, Wo, 3), finite rgb (b,)."""

    images: np.ndarray
    alpha: np.ndarray
    parts: np.ndarray
    rgb_finite: np.ndarray


class SynthPipeline:
    """Synthetic frames of the bundle's HOGS models.

    It renders a :class:`~hogsa_loader.sample.plan.BatchPlan` (seed,
    epoch, model, sample indices, hands) through named stages, each a method:

    1. ``poses`` — the pose source's B poses (world frame), its optional POM ``optimize``
       step, and the labels' 3D points from the MANO and object layers;
    2. ``views`` — cameras, the ARCTIC crop box and validity flags; samples behind the camera
       or with NaN poses are dropped here, before rendering;
    3. ``render`` — ONE :meth:`HogsModel.render` call straight into the ``S × S`` crop (laid
       out like ARCTIC's cropped images), lens distortion resampled where the view has one;
       the plan's model, with another run's hand Gaussians where the plan names one (``hands``);
    4. ``refine`` — optional ``refiner(rgb, alpha) -> rgb`` (premultiplied (B, S, S, 3), alpha
       (B, S, S, 1));
    5. ``composite`` — premultiplied "over" onto backgrounds (:mod:`hogsa_loader.compose`);
    6. ``labels`` and ``checks`` — the camera-frame labels of each sample, then the sanity
       checks (dropped samples are counted by reason in :class:`SynthStats`) and the frame.

    Args:
        root: the data root (MANO layers, object templates).
        models: ``key -> HogsModel`` loader (called once per key, the keys of plans' ``hands``
            included; result cached), e.g.
            ``lambda key: bundle.load_hogs(key, layers, templates, device)``.
        pose_source: the :class:`~hogsa_loader.sample.poses.PoseSource`.
        cameras: ``subject -> CameraSampler`` (``p1``) or ``EgoCameras`` (``p2``).
        backgrounds: a :class:`~hogsa_loader.compose.BackgroundSource`.
        render_size: side S of the rendered crop (ARCTIC's cropped-image layout: the box
            covers the central 2/3).
        device: where models render.
        refiner: optional ``(rgb, alpha) -> rgb`` applied after rendering (SRM).
        checks: :class:`SampleChecks`.
        stats: counters to update (a new :class:`SynthStats` by default).
        backend: renderer backend (``"auto"``, ``"torch"``, ``"gsplat"``).
        interfield: optional :class:`~hogsa_loader.sample.interfield.InterFieldTargets`;
            its targets are attached to every kept frame (``SynthFrame.extra_targets``).
        protocol: ``"p1"`` (allocentric; ``cameras`` maps subject → CameraSampler) or
            ``"p2"`` (egocentric; subject → :class:`~hogsa_loader.sample.views.EgoCameras`),
            see :mod:`~hogsa_loader.sample.views`.
        ego_distortion: ``p2`` only: apply the egocentric lens distortion to the pixels.
    """

    def __init__(
        self,
        root: ArcticRoot,
        models: Callable[[tuple[str, str]], Any],
        pose_source: PoseSource,
        cameras: Mapping[str, CameraSampler],
        backgrounds: Any,
        render_size: int,
        device: torch.device | str = "cpu",
        refiner: Optional[Refiner] = None,
        checks: SampleChecks = DEFAULT_CHECKS,
        stats: Optional[SynthStats] = None,
        backend: str = "auto",
        interfield: Optional[Any] = None,
        protocol: str = "p1",
        ego_distortion: bool = True,
    ) -> None:
        if protocol not in ("p1", "p2"):
            raise ValueError(f"protocol must be 'p1' or 'p2', got {protocol!r}")
        self.root = root
        self.interfield = interfield
        self.protocol = protocol
        self.ego_distortion = bool(ego_distortion)
        self._model_fn = models
        self._models: dict[tuple[str, str], Any] = {}
        self._swapped: dict[tuple[tuple[str, str], tuple[str, str]], Any] = {}
        self.pose_source = pose_source
        self.cameras = dict(cameras)
        self.backgrounds = backgrounds
        self.render_size = int(render_size)
        self.device = torch.device(device)
        self.refiner = refiner
        self.checks = checks
        self.stats = stats if stats is not None else SynthStats()
        self.backend = backend
        self.last_backend: Optional[str] = None  # the renderer "auto" resolved to, at the last render
        self.layers = root.mano_layers(torch.float64)
        self.object_layer = root.object_layer()
        self.kp_bottom = {
            n: np.asarray(t.kp_bottom, dtype=np.float32) for n, t in root.object_templates(load_texture=False).items()
        }
        wm = root.world_meta()  # the real images' sizes, for the source blur (source_scale)
        self.source_sizes = {"cropped_size": int(wm.cropped_size), "ego_image_scale": float(wm.ego_image_scale)}

    def model(self, key: tuple[str, str], hands: Optional[tuple[str, str]] = None) -> Any:
        """The (cached) HOGS model of ``key``; with ``hands``, that model with the hand
        Gaussians of run ``hands`` (:func:`~hogsa_loader.models.gaussians.recombine.swap_hands`)."""
        for k in (key, hands):
            if k is not None and k not in self._models:
                self._models[k] = self._model_fn(k)
        if hands is None:
            return self._models[key]
        if (key, hands) not in self._swapped:  # swap_hands gives the model itself for its own hands
            self._swapped[(key, hands)] = swap_hands(self._models[hands], self._models[key])
        return self._swapped[(key, hands)]

    def _drop(self, reason: str) -> None:
        self.stats.dropped[reason] = self.stats.dropped.get(reason, 0) + 1

    # ------------------------------------------------------------------ main entry
    def frames(self, plan: BatchPlan) -> list[Optional[SynthFrame]]:
        """Render the samples of ``plan`` (one model, one batch).

        Returns:
            one entry per index of ``plan.indices``: the :class:`SynthFrame`, or None when
            the sample was dropped (the reason is counted in :attr:`stats`).
        """
        B = len(plan.indices)
        results: list[Optional[SynthFrame]] = [None] * B
        if B == 0:
            return results
        self.stats.batches += 1
        self.stats.attempted += B
        posed = self._poses(plan)
        viewed = self._views(plan, posed)
        if viewed.keep:
            rgb, alpha, part_alpha = self._render(plan, posed, viewed)
            rgb = self._refine(rgb, alpha)
            pixels = self._composite(plan, viewed, rgb, alpha, part_alpha)
            with self.stats.timed("targets"):
                for j, b in enumerate(viewed.keep):
                    results[b] = self._frame(plan, b, posed, viewed, pixels, j)
                self._interfield(plan, posed, results)
        self.stats.kept += sum(r is not None for r in results)
        return results

    # ------------------------------------------------------------------ stages
    def _poses(self, plan: BatchPlan) -> _Posed:
        """Stage ``poses``: B poses of the pose source (and its POM step), posed label points."""
        st = self.stats
        with st.timed("pose"):
            batch = self.pose_source.sample(plan.key, plan.rngs("pose"))
        optimize = getattr(self.pose_source, "optimize", None)
        if optimize is not None:
            with st.timed("pom", self.device):
                batch = optimize(plan.key, batch)
        with st.timed("pose"):
            geo, hand_verts = self._geometry(plan.key, batch)
        return _Posed(batch, geo, hand_verts)

    def _geometry(self, key: tuple[str, str], batch: PoseBatch) -> tuple[dict[str, np.ndarray], dict[str, Tensor]]:
        """World-frame label points: joints (B,21,3) per hand, kp3d (B,32,3), bbox3d (B,16,3),
        object vertices (B,V,3), float64; and the hand vertices ``{side: (B, Vh, 3)}`` (kept
        apart: only the interaction field needs them, nothing is projected)."""
        P = batch.poses
        out: dict[str, np.ndarray] = {}
        hand_verts: dict[str, Tensor] = {}
        with torch.no_grad():
            for side in ("right", "left"):
                res = self.layers[side](
                    global_orient=P[f"{side}_rot"],
                    hand_pose=P[f"{side}_pose"],
                    betas=P[f"{side}_betas"],
                    transl=P[f"{side}_trans"],
                )
                out[f"joints.{side}"] = res.joints.double().numpy()
                hand_verts[side] = res.vertices
            B = len(batch)
            res = self.object_layer(
                angles=P["obj_arti"].reshape(B, 1),
                global_orient=P["obj_rot"],
                transl=P["obj_trans"],
                names=[key[1]] * B,
            )
        out["kp3d"] = res["kp3d"].double().numpy()
        out["bbox3d"] = res["bbox3d"].double().numpy()
        out["verts"] = res["v"].double().numpy()
        return out, hand_verts

    def _views(self, plan: BatchPlan, posed: _Posed) -> _Viewed:
        """Stage ``views``: cameras and crops; drops NaN poses, samples behind the camera and
        those the pose source marked ``provenance["dropped"]``."""
        batch, B, S = posed.batch, len(plan.indices), self.render_size
        with self.stats.timed("pose"):
            cam_rngs = plan.rngs("camera")
            cams = self.cameras[plan.key[0]]
            if self.protocol == "p2":
                prov = batch.provenance or [{}] * B
                vg = egocentric_views(cams, posed.geo, prov, cam_rngs, S, self.ego_distortion)
            else:
                vg = allocentric_views(cams, posed.geo, cam_rngs, S)
            R_w2c = torch.as_tensor(vg.world2cam[:, :3, :3])
            rot_cam = {
                side: matrix_to_axis_angle(R_w2c @ axis_angle_to_matrix(batch.poses[f"{side}_rot"])).numpy()
                for side in ("right", "left")
            }
            min_z = np.minimum.reduce([vg.cam[k][..., 2].min(1) for k in ("verts", "joints.right", "joints.left")])
            finite = np.isfinite(min_z)  # (a NaN pose would otherwise fail the depth test as "behind")
            front = finite & (min_z > self.checks.near_m)
        pose_drop = [p.get("dropped") for p in batch.provenance] if batch.provenance else [None] * B
        for b in range(B):
            if pose_drop[b]:
                self._drop(str(pose_drop[b]))
            elif not finite[b]:
                self._drop("nan")
            elif not front[b]:
                self._drop("behind_camera")
        return _Viewed(vg, rot_cam, [b for b in range(B) if front[b] and not pose_drop[b]])

    def _render(self, plan: BatchPlan, posed: _Posed, viewed: _Viewed) -> tuple[Tensor, Tensor, Tensor]:
        """Stage ``render``: one render call for the kept samples (b of them).

        Returns:
            rgb (b, Ho, Wo, 3) premultiplied on black, alpha (b, Ho, Wo, 1), part alpha
            (b, Ho, Wo, 3), distortion applied where the view has one.
        """
        model, dev, vg, keep = self.model(plan.key, plan.hands), self.device, viewed.vg, viewed.keep
        Hr, Wr = vg.render_hw
        with self.stats.timed("render", dev):
            dtype = next(model.parameters()).dtype
            poses = {k: v[keep].to(device=dev, dtype=dtype) for k, v in posed.batch.poses.items()}
            viewmats = torch.as_tensor(vg.world2cam[keep], dtype=dtype, device=dev)[:, None]
            Ks = torch.as_tensor(vg.K_render[keep], dtype=dtype, device=dev)[:, None]
            with torch.no_grad():
                out = model.render(poses, viewmats, Ks, Wr, Hr, render_mode="RGB", backend=self.backend)
            self.last_backend = str(out.meta.get("backend", self.backend))
            rgb, alpha, part_alpha = out.rgb[:, 0], out.alpha[:, 0], out.part_alpha[:, 0]
            if vg.warp is not None:  # lens distortion: resample the undistorted render
                warped = apply_warp(torch.cat([rgb, alpha, part_alpha], -1), vg.warp[keep])
                rgb, alpha, part_alpha = warped[..., :3], warped[..., 3:4], warped[..., 4:]
        return rgb, alpha, part_alpha

    def _refine(self, rgb: Tensor, alpha: Tensor) -> Tensor:
        """Stage ``refine``: the refiner (SRM) on rgb (b, H, W, 3) given alpha (b, H, W, 1)."""
        if self.refiner is None:
            return rgb
        with self.stats.timed("srm", self.device):
            with torch.no_grad():
                return self.refiner(rgb, alpha)

    def _composite(self, plan: BatchPlan, viewed: _Viewed, rgb: Tensor, alpha: Tensor, part_alpha: Tensor) -> _Pixels:
        """Stage ``composite``: each kept sample over its background (stream ``background``)."""
        dev, (Ho, Wo) = self.device, viewed.vg.out_hw
        with self.stats.timed("composite", dev):
            bgs = []
            for b in viewed.keep:
                g = torch.Generator().manual_seed(int(plan.rng(b, "background").integers(2**62)))
                plate = self._camera_plate(plan, viewed.vg, b)
                bgs.append(self.backgrounds.sample(1, Ho, Wo, g) if plate is None else plate)
            bg = torch.cat(bgs, 0).to(device=dev, dtype=rgb.dtype)
            img = composite(rgb, alpha, bg, clamp=True)
            return _Pixels(
                images=(img * 255.0).round_().to(torch.uint8).cpu().numpy(),
                alpha=alpha[..., 0].float().cpu().numpy(),
                parts=part_alpha.float().cpu().numpy(),
                rgb_finite=torch.isfinite(rgb.reshape(len(viewed.keep), -1)).all(1).cpu().numpy(),
            )

    def _camera_plate(self, plan: BatchPlan, vg: ViewGeometry, b: int) -> Optional[Tensor]:
        """Sample ``b``'s own camera backdrop (1, H, W, 3) in [0, 1] when the background source
        has one for its dataset camera (:meth:`BackgroundSource.camera_plate`), else None."""
        Ho, Wo = vg.out_hw
        if vg.box_full is None or int(vg.view[b]) == NOVEL_VIEW or Ho != Wo:
            return None
        img = self.backgrounds.camera_plate(plan.key[0], int(vg.view[b]), vg.box_full[b], Ho)
        return None if img is None else BackgroundSource._finish(img[None], None, None)

    def _labels(
        self, plan: BatchPlan, b: int, posed: _Posed, viewed: _Viewed
    ) -> tuple[HandLabels, HandLabels, ObjectLabels]:
        """Stage ``labels``: the camera-frame hand and object labels of sample ``b``."""
        is_valid, right_valid, left_valid = (float(f[b]) for f in viewed.vg.flags)
        P, cam, lab = posed.batch.poses, viewed.vg.cam, viewed.vg.label2d

        def hand(side: str, valid: float) -> HandLabels:
            return HandLabels(
                pose48=np.concatenate([viewed.rot_cam[side][b], P[f"{side}_pose"][b].numpy()]).astype(np.float32),
                betas=P[f"{side}_betas"][b].numpy().astype(np.float32),
                j3d_full=cam[f"joints.{side}"][b].astype(np.float32),
                j2d=lab[f"joints.{side}"][b],
                valid=valid,
            )

        obj = plan.key[1]
        objl = ObjectLabels(
            name=obj,
            radian=float(P["obj_arti"][b].reshape(-1)[0]),
            kp3d_full=cam["kp3d"][b].astype(np.float32),
            bbox3d_full=cam["bbox3d"][b].astype(np.float32),
            kp2d=lab["kp3d"][b],
            bbox2d=lab["bbox3d"][b],
            valid=is_valid,
            kp_bottom_cano=self.kp_bottom[obj],
        )
        return hand("right", right_valid), hand("left", left_valid), objl

    def _check(
        self,
        b: int,
        vg: ViewGeometry,
        labels: tuple[HandLabels, HandLabels, ObjectLabels],
        alpha: np.ndarray,
        part_alpha: np.ndarray,
        rgb_finite: bool,
    ) -> Optional[str]:
        """Stage ``checks``: the drop reason of sample ``b`` (None: kept); alpha (S, S), part alpha (S, S, 3)."""
        right, left, objl = labels
        if not rgb_finite or not _finite(
            right.pose48,
            left.pose48,
            right.j2d,
            left.j2d,
            right.j3d_full,
            left.j3d_full,
            objl.kp2d,
            objl.bbox2d,
            objl.kp3d_full,
            objl.radian,
        ):
            return "nan"
        c = self.checks
        if int((alpha > 0.5).sum()) < c.min_alpha_pixels or int((part_alpha[..., 2] > 0.5).sum()) < c.min_alpha_pixels:
            return "empty_alpha"
        n_bad_hands = int(right.valid == 0) + int(left.valid == 0)
        if objl.valid == 0 or (c.hands == "any" and n_bad_hands) or (c.hands == "both" and n_bad_hands == 2):
            return "out_of_crop"
        x0, y0, x1, y1 = vg.check_box

        def on_alpha(pts: np.ndarray) -> Optional[float]:
            inside = (pts[:, 0] >= x0) & (pts[:, 0] <= x1) & (pts[:, 1] >= y0) & (pts[:, 1] <= y1)
            if not inside.any():
                return None
            return float(joints_on_alpha(pts[inside], alpha).mean())

        points = [vg.pix2d[f"joints.{side}"][b] for side, h in (("right", right), ("left", left)) if h.valid]
        for pts in [*points, vg.pix2d["kp3d"][b]]:
            frac = on_alpha(pts)
            if frac is not None and frac < c.min_on_alpha:
                return "label_pixel_mismatch"
        return None

    def _frame(
        self, plan: BatchPlan, b: int, posed: _Posed, viewed: _Viewed, pixels: _Pixels, j: int
    ) -> Optional[SynthFrame]:
        """Labels, checks and the :class:`SynthFrame` of sample ``b`` (``j``-th kept one); None: dropped."""
        vg = viewed.vg
        labels = self._labels(plan, b, posed, viewed)
        reason = self._check(b, vg, labels, pixels.alpha[j], pixels.parts[j], bool(pixels.rgb_finite[j]))
        if reason is not None:
            self._drop(reason)
            return None
        (sid, obj), index, view = plan.key, plan.indices[b], int(vg.view[b])
        batch = posed.batch
        # the pose source's provenance first: the sample's own identity keys always win
        meta = {
            **(batch.provenance[b] if batch.provenance else {}),
            **self.source_sizes,
            "seed": plan.seed,
            "epoch": plan.epoch,
            "index": int(index),
            "subject": sid,
            "object": obj,
            "view": view,
            "camera": "egocentric" if vg.egocentric else ("dataset" if view != 100 else "novel"),
        }
        if plan.hands is not None and plan.hands != plan.key:
            meta["hands_from"] = "/".join(plan.hands)
        if vg.egocentric:  # read back by the offline export (hogsa_loader.sample.export.reader.frame_to_arctic_sample)
            meta["egocentric"] = True
            meta["dist"] = [float(x) for x in vg.dist[b]]  # type: ignore[index]
        right, left, objl = labels
        return SynthFrame(
            image=pixels.images[j],
            alpha=pixels.alpha[j].astype(np.float32),
            part_alpha=pixels.parts[j].astype(np.float32),
            bbox=np.asarray(vg.box_img[b], dtype=np.float64),
            K_full=np.asarray(vg.K_full[b], dtype=np.float64),
            image_size=(int(vg.image_size[b, 0]), int(vg.image_size[b, 1])),
            right=right,
            left=left,
            obj=objl,
            imgname=synthetic_imgname(sid, obj, plan.seed, plan.epoch, view, index),
            meta=meta,
            egocentric=vg.egocentric,
            dist=None if vg.dist is None else np.asarray(vg.dist[b], dtype=np.float64),
        )

    def _interfield(self, plan: BatchPlan, posed: _Posed, results: list[Optional[SynthFrame]]) -> None:
        """The InterField-SF targets of the kept frames, from the meshes posed in ``poses``."""
        kept = [b for b, r in enumerate(results) if r is not None]
        if self.interfield is None or not kept:
            return
        n_o = int(self.object_layer.v_len[self.object_layer.indices([plan.key[1]])][0])
        for b in kept:
            results[b].extra_targets = self.interfield.from_vertices(  # type: ignore[union-attr]
                posed.hand_verts["right"][b], posed.hand_verts["left"][b], posed.geo["verts"][b, :n_o]
            )
