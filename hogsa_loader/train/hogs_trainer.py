"""HOGS training of one (subject, object): right hand, left hand and object Gaussians jointly.

Start with :class:`HogsTrainer` (built from a ``HogsConfig``); :meth:`HogsTrainer.train`
runs the loop and writes the run folder (described there); :meth:`HogsTrainer.train_step`
describes one step. The data comes from an ARCTIC(-format) or an H2O root
(:mod:`hogsa_loader.train.hogs_source`).
"""

from __future__ import annotations

import time
from dataclasses import replace
from pathlib import Path
from typing import Any, Optional, Sequence

import numpy as np
import torch
from torch import Tensor

from hogsa_loader.assets.objects.template import ObjectTemplate
from hogsa_loader.errors import AssetError
from hogsa_loader.models.gaussians import BindingConfig, HandGaussians, ObjectGaussians, load_state, save_part
from hogsa_loader.models.gaussians.hogs_model import LIGHT_DIR, HogsModel
from hogsa_loader.models.gaussians.shading import DirectionalLight, load_light, save_light
from hogsa_loader.train.hogs_config import HogsConfig
from hogsa_loader.train.hogs_data import MASK_MODES, FrameSelection, HogsData, ViewSample, dilate_mask
from hogsa_loader.train.hogs_eval import evaluate_samples
from hogsa_loader.train.hogs_source import open_hogs_source
from hogsa_loader.train.loop import StepLoop
from hogsa_loader.train.losses import hogs_loss
from hogsa_loader.train.run_folder import write_json

__all__ = ["HogsTrainer", "BASE_LRS", "PART_NAMES", "POSITION_PARAMS"]

PART_NAMES = ("hand_right", "hand_left", "object")
#: Adam learning rates by parameter name (the GaMeS paper's table; free/avatar
#: geometry the 3DGS position/rotation/scale rates). Canonical offsets get a tenth of
#: GaMeS's optional vertex rate: at 1.6e-4 (and more so with ``lr_scale``) Adam's
#: sign-like first steps inflated the meshes by ~1 mm per step and alpha spilled outside
#: the masks.
BASE_LRS = {
    "offsets": 1.6e-5,
    "bary_logits": 1e-3,
    "log_scale_factor": 5e-3,
    "sh_dc": 2.5e-3,
    "sh_rest": 2.5e-3 / 20,
    "opacity_logits": 5e-2,
    "means": 1.6e-4,
    "quats": 1e-3,
    "log_scales": 5e-3,
    "local_means": 1.6e-3,
    "local_quats": 1e-3,
    "local_log_scales": 5e-3,
    # the learned light (shading="lambert"); not multiplied by lr_scale
    "direction": 5e-3,
    "ambient_raw": 5e-3,
    "diffuse_raw": 5e-3,
}

#: Shading models of a HOGS run.
SHADINGS = ("none", "lambert")

#: Positions in metres: ``lr_scale`` leaves their rates alone.
POSITION_PARAMS = ("offsets", "means", "local_means")


def _list(x: Optional[Sequence[Any]]) -> Optional[list[Any]]:
    return None if x is None else list(x)


def _t(x: np.ndarray, device: torch.device) -> Tensor:
    return torch.as_tensor(np.asarray(x), dtype=torch.float32, device=device)


def _check_config(cfg: HogsConfig) -> None:
    """Raises ValueError for a setting :class:`HogsTrainer` cannot run with."""
    if cfg.model.gaussians not in ("mesh", "free"):
        raise ValueError(f"--model-gaussians must be 'mesh' or 'free', got {cfg.model.gaussians!r}")
    unknown = sorted(set(cfg.optim.lr_overrides) - set(BASE_LRS))
    if unknown:
        raise ValueError(f"lr overrides for unknown parameters {unknown}; known: {sorted(BASE_LRS)}")
    if cfg.model.shading not in SHADINGS:
        raise ValueError(f"shading must be one of {SHADINGS}, got {cfg.model.shading!r}")
    if cfg.optim.iters < 0 or cfg.optim.batch_size < 1:
        raise ValueError("iters must be >= 0 and batch_size >= 1")
    if cfg.data.image_size is not None and cfg.data.image_size < 1:
        raise ValueError(f"image_size must be >= 1 (or None: the dataset's crop size), got {cfg.data.image_size}")
    if cfg.data.masks not in MASK_MODES:
        raise ValueError(f"masks must be one of {MASK_MODES}, got {cfg.data.masks!r}")


def _with_default_views(cfg: HogsConfig, views: Sequence[int], eval_views: Sequence[int]) -> HogsConfig:
    """``cfg`` with unset ``views`` / ``eval_views`` filled in with the dataset's defaults."""
    data = replace(cfg.data, views=tuple(cfg.data.views or views), eval_views=tuple(cfg.data.eval_views or eval_views))
    return replace(cfg, data=data)


def _object_subdivide_levels(template: ObjectTemplate, levels: Optional[int], min_faces: int) -> int:
    """``levels``, or when None the fewest (at most 2) that give the object ``min_faces`` faces.

    Each level multiplies the faces by 4; the textured faces count when the template has a texture.
    """
    if levels is not None:
        return levels
    faces = (template.tex_faces if template.has_texture else template.faces).shape[0]
    levels = 0
    while faces * 4**levels < min_faces and levels < 2:
        levels += 1
    return levels


class HogsTrainer(StepLoop):
    """Builds the parts and data of one (subject, object) and trains them."""

    desc = "hogs"

    def __init__(self, cfg: HogsConfig, *, progress: bool = True) -> None:
        _check_config(cfg)
        t0 = time.perf_counter()
        self.source = open_hogs_source(
            cfg.data.dataset,
            cfg.data.root,
            cfg.data.object,
            mano_dir=cfg.data.mano_dir,
            object_mesh_dir=cfg.data.object_mesh_dir,
        )
        # the dataset's default views are written into config.json (what render_quality rebuilds)
        cfg = _with_default_views(cfg, self.source.views, self.source.eval_views)
        self.cfg = cfg
        self.progress = progress
        self.device = torch.device(cfg.run.device)
        self.out = Path(cfg.run.out)
        self.root = self.source.root
        self.data: HogsData = self._load_data()
        self.timings: dict[str, float] = {"load_s": time.perf_counter() - t0}
        torch.manual_seed(cfg.run.seed)
        self.model = self._build_model()
        self.parts = self.model.parts
        if cfg.model.shading == "lambert":
            self.model.light = DirectionalLight(direction=self._mean_view_direction()).to(self.device)
        self.optimizer = torch.optim.Adam(self._param_groups(), eps=1e-15)
        self.gen = torch.Generator().manual_seed(cfg.run.seed)
        self.step = 0
        self.history: list[dict[str, float]] = []
        self.evals: list[dict[str, Any]] = []
        self._train_time = 0.0
        self.resumed = False

    def _load_data(self) -> HogsData:
        """The training and held-out samples the data settings select."""
        data = self.cfg.data
        return self.source.load(
            data.subject,
            data.object,
            FrameSelection(
                sequences=_list(data.sequences),
                views=list(data.views),
                eval_views=list(data.eval_views),
                eval_every_frame=data.eval_every_frame,
                frame_stride=data.frame_stride,
                image_size=data.image_size,
                max_eval=data.max_eval,
            ),
            masks=data.masks,
            window=data.window,
        )

    def _build_model(self) -> HogsModel:
        """Both hands and the object as Gaussians (no light), on the run's device."""
        model = self.cfg.model
        variant = "games" if model.gaussians == "mesh" else "free"
        layers = self.source.mano_layers
        template = self.source.object_templates[self.cfg.data.object]
        levels = _object_subdivide_levels(template, model.object_subdivide, model.min_object_faces)
        binding = BindingConfig(variant=variant, k=model.k, sh_degree=model.sh_degree)
        hands = replace(binding, subdivide_levels=model.hand_subdivide)
        return HogsModel(
            HandGaussians(layers["right"], hands),
            HandGaussians(layers["left"], hands),
            ObjectGaussians(template, replace(binding, subdivide_levels=levels)),
            source=self._source(),
        ).to(self.device)

    def _param_groups(self) -> list[dict[str, Any]]:
        """One Adam group per parameter of the parts and light, with its learning rate.

        Raises:
            KeyError: a part parameter has no entry in :data:`BASE_LRS`.
        """
        optim = self.cfg.optim
        groups = []
        for pname, part in self.parts.items():
            for name, p in part.splats.named_parameters():
                lr = BASE_LRS.get(name)
                if lr is None:
                    raise KeyError(f"no learning rate for parameter {name!r}")
                scale = 1.0 if name in POSITION_PARAMS else optim.lr_scale
                lr = optim.lr_overrides.get(name, lr * scale)
                groups.append({"params": [p], "lr": lr, "base_lr": lr, "name": f"{pname}.{name}"})
        if self.model.light is not None:
            for name, p in self.model.light.named_parameters():
                lr = optim.lr_overrides.get(name, BASE_LRS[name])
                groups.append({"params": [p], "lr": lr, "base_lr": lr, "name": f"light.{name}"})
        return groups

    # ------------------------------------------------------------------ rendering
    def active_sh_degree(self, step: Optional[int] = None) -> int:
        step = self.step if step is None else step
        if self.cfg.optim.sh_warmup <= 0:
            return self.cfg.model.sh_degree
        return min(self.cfg.model.sh_degree, step // self.cfg.optim.sh_warmup)

    def render(self, samples: Sequence[ViewSample], sh_degree: Optional[int] = None) -> tuple[Tensor, Tensor]:
        """Render samples: rgb (B, H, W, 3) on black, alpha (B, H, W)."""
        dev = self.device
        p = {k: v.to(dev) for k, v in self.data.poses(samples).items()}
        deg = self.active_sh_degree() if sh_degree is None else sh_degree
        viewmats = _t(np.stack([s.world2cam for s in samples]), dev)[:, None]
        Ks = _t(np.stack([s.K for s in samples]), dev)[:, None]
        S = self.data.image_size
        out = self.model.render(p, viewmats, Ks, S, S, sh_degree=deg, render_mode="RGB")
        return out.rgb[:, 0], out.alpha[:, 0, ..., 0]

    def targets(self, samples: Sequence[ViewSample]) -> tuple[Tensor, Tensor, Tensor]:
        """GT with background masked to black (B, H, W, 3), mask (B, H, W), loss region (dilated).

        The same for mask files and rendered masks: every pixel outside the part mask is
        black in the GT, so the photometric loss (on the dilated region) asks for an empty
        render there and never takes the picture's real background (kept in the images
        of rendered-mask samples) as a colour target; beyond the region the alpha loss
        applies. With rendered masks, edge pixels partly covered by the mask keep their
        area-averaged share of background colour (no native-resolution cut, the mask being
        an estimate from the annotations).
        """
        img = torch.as_tensor(np.stack([s.image for s in samples]), device=self.device).float() / 255.0
        mask = torch.as_tensor(np.stack([s.mask for s in samples]), device=self.device) > 0
        return img * mask[..., None], mask, dilate_mask(mask, self.margin_px)

    @torch.no_grad()
    def photometric_loss(self, samples: Sequence[ViewSample]) -> float:
        """The photometric term of the loss on ``samples`` (no gradient; e.g. a fixed probe set)."""
        gt, _, region = self.targets(samples)
        rgb, alpha = self.render(samples)
        return hogs_loss(rgb, gt, alpha, region, self.l_r(), lambda_ssim=self.cfg.loss.lambda_ssim)[1]["photo"]

    @property
    def margin_px(self) -> int:
        """``cfg.loss.margin`` (cropped-image pixels) at the training resolution."""
        return int(round(self.cfg.loss.margin * self.data.image_size / self.data.crop_size))

    # ------------------------------------------------------------------ training
    def l_r(self) -> Tensor:
        return sum(part.offset_regulariser() for part in self.parts.values()) / len(self.parts)

    def train_step(self) -> dict[str, float]:
        """One training step.

        Each step renders a random batch of training (frame, view) crops with the annotated poses
        and minimises :func:`~hogsa_loader.train.losses.hogs_loss` against the image with its
        background masked to black, inside the hand/object mask dilated by ``margin`` px; outside
        that region the rendered alpha is pushed to 0. The data comes from an ARCTIC(-format) or
        an H2O root (:mod:`hogsa_loader.train.hogs_source`), the masks from the dataset's files
        or rendered from the annotated meshes (``masks``, :func:`~hogsa_loader.train.hogs_data.load_hogs_data`).
        Adam with per-parameter learning rates (GaMeS table; ``lr_scale`` multiplies all but the
        position rates), SH degree raised every ``sh_warmup`` steps.
        """
        idx = torch.randint(len(self.data.train), (self.cfg.optim.batch_size,), generator=self.gen).tolist()
        samples = [self.data.train[i] for i in idx]
        gt, mask, region = self.targets(samples)
        rgb, alpha = self.render(samples)
        inside = ~dilate_mask(~mask, 1)  # eroded by 1 px: partly covered edge pixels are left free
        loss, terms = hogs_loss(
            rgb,
            gt,
            alpha,
            region,
            self.l_r(),
            lambda_ssim=self.cfg.loss.lambda_ssim,
            lambda_r=self.cfg.loss.lambda_r,
            lambda_alpha=self.cfg.loss.lambda_alpha,
            inside=inside,
            lambda_alpha_in=self.cfg.loss.lambda_alpha_in,
        )
        self.optimizer.zero_grad(set_to_none=True)
        loss.backward()
        frozen = self.step < self.cfg.optim.opacity_warmup
        for group in self.optimizer.param_groups:
            if group["name"].endswith(".opacity_logits"):
                group["lr"] = 0.0 if frozen else group["base_lr"]
        self.optimizer.step()
        self.step += 1
        terms["loss"] = float(loss.detach())
        terms["step"] = self.step
        return terms

    @torch.no_grad()
    def evaluate(self, samples: Optional[Sequence[ViewSample]] = None) -> dict[str, Any]:
        """PSNR / SSIM inside each sample's foreground box (:func:`evaluate_samples`)."""
        samples = self.data.eval if samples is None else samples
        names = [seq.name for seq in self.data.sequences]
        ev = evaluate_samples(self.render, samples, names, self.margin_px, device=self.device)
        ev.pop("lpips", None)
        return {"step": self.step, **ev}

    def train(self, overwrite: bool = False) -> dict[str, Any]:
        """Train up to ``cfg.optim.iters`` steps (from the current step), evaluating and checkpointing.

        Args:
            overwrite: when the run was not resumed and its folder holds checkpoints, empty
                the folder and start again (otherwise :class:`RunExistsError`).

        Run folder::

            config.json                       the settings (resume refuses different ones)
            checkpoints/latest.json           {"step", "folder"}, written last (atomic)
            checkpoints/step_XXXXXXX/         hand_right/, hand_left/, object/ (save_part),
                                              trainer.safetensors (Adam moments + RNG state),
                                              trainer.json (step, history, sha256 of the tensors)
            hand_right/, hand_left/, object/  final parts
            metrics.json, strip.png, curves.png

        No pickle anywhere; every file is written atomically. :meth:`HogsTrainer.train` refuses to
        start from step 0 in a folder that holds checkpoints (:class:`~hogsa_loader.train.run_folder.RunExistsError`)
        unless the run was resumed first or ``overwrite=True``.
        """
        final = self.run_steps(overwrite)
        self._save_parts(self.out)
        metrics = self.write_metrics(final)
        self.write_pngs()
        return metrics

    def _eval_point(self, ev: dict[str, Any]) -> dict[str, Any]:
        return _summary(ev)

    def _postfix(self, terms: dict[str, float]) -> dict[str, str]:
        return {"loss": f"{terms['loss']:.4f}", "l1": f"{terms['l1']:.4f}"}

    def _eval_message(self, ev: dict[str, Any]) -> str:
        return f"step {self.step}: held-out PSNR {ev['psnr']:.2f} dB SSIM {ev['ssim']:.4f}"

    def _out_of_time(self) -> Optional[str]:
        minutes = self.cfg.run.max_minutes
        if minutes is not None and self._train_time >= 60.0 * minutes:
            return f"time budget of {minutes} min reached at step {self.step}"
        return None

    # ------------------------------------------------------------------ checkpoints
    def _source(self) -> dict[str, str]:
        return {
            "dataset": self.cfg.data.dataset,
            "subject": self.cfg.data.subject,
            "sequence": ",".join(s.name for s in self.data.sequences),
        }

    def _save_parts(self, folder: Path) -> None:
        for name, part in self.parts.items():
            extra: dict[str, Any] = {"step": self.step, "shading": self.cfg.model.shading}
            if name == "object" and self.source.object_provenance:
                extra["object_mesh"] = self.source.object_provenance
            save_part(part, folder / name, **self._source(), extra=extra)
        if self.model.light is not None:
            save_light(self.model.light, folder / LIGHT_DIR)

    def _mean_view_direction(self) -> list[float]:
        """Mean viewing direction (world frame) of the training cameras: the light's start."""
        fwd = np.stack([s.world2cam[2, :3] for s in self.data.train])  # camera z axis in the world
        d = fwd.mean(0)
        return (d / max(np.linalg.norm(d), 1e-9)).tolist()

    def _save_state(self, folder: Path) -> tuple[dict[str, Tensor], dict[str, Any]]:
        """The parts (and light) into ``folder``; RNG states and Adam moments as tensors."""
        self._save_parts(folder)
        tensors: dict[str, Tensor] = {"rng.sampler": self.gen.get_state(), "rng.torch": torch.get_rng_state()}
        for group in self.optimizer.param_groups:
            st = self.optimizer.state.get(group["params"][0], {})
            for key, val in st.items():
                tensors[f"adam.{group['name']}.{key}"] = torch.as_tensor(val).detach().cpu().contiguous()
        return tensors, {}

    def _load_state(self, folder: Path, state: dict[str, Any], tensors: dict[str, Tensor]) -> None:
        """Parts, light, RNG states and Adam moments (moments that do not fit the model: AssetError)."""
        for group in self.optimizer.param_groups:
            p = group["params"][0]
            prefix = f"adam.{group['name']}."
            for k, v in tensors.items():
                if k.startswith(prefix) and k[len(prefix) :] in ("exp_avg", "exp_avg_sq") and v.shape != p.shape:
                    raise AssetError(
                        folder / "trainer.safetensors",
                        f"{k} has shape {tuple(v.shape)}, the model's parameter {tuple(p.shape)}",
                    )
        for name, part in self.parts.items():
            load_state(part, folder / name)
        if self.model.light is not None:
            load_light(folder / LIGHT_DIR, into=self.model.light)
        try:
            self.gen.set_state(tensors["rng.sampler"])
            torch.set_rng_state(tensors["rng.torch"])
        except (RuntimeError, TypeError) as exc:
            raise AssetError(folder / "trainer.safetensors", f"unusable RNG state ({exc})") from None
        for group in self.optimizer.param_groups:
            p = group["params"][0]
            prefix = f"adam.{group['name']}."
            st = {k[len(prefix) :]: v.to(p.device) for k, v in tensors.items() if k.startswith(prefix)}
            if st:
                st["step"] = st["step"].cpu()  # Adam keeps its step count on the CPU
                self.optimizer.state[p] = st

    # ------------------------------------------------------------------ reports
    def write_metrics(self, final: dict[str, Any]) -> dict[str, Any]:
        n_train = max(1, len(self.history))
        metrics = {
            "psnr": final["psnr"],
            "ssim": final["ssim"],
            "lpips": None,
            "lpips_note": "LPIPS not computed (no local weights)",
            "per_view": final["per_view"],
            "per_sample": final["per_sample"],
            "alpha_outside": final["alpha_outside"],
            "region": "foreground box (bbox of the part mask dilated by margin px); GT background masked to black",
            "dataset": self.cfg.data.dataset,
            "masks": self.data.mask_source,
            "iters": self.step,
            "initial": self.evals[0] if self.evals else None,
            "evals": self.evals,
            "subject": self.cfg.data.subject,
            "object": self.cfg.data.object,
            "sequences": [s.name for s in self.data.sequences],
            "train_views": list(self.data.train_views),
            "eval_views": list(self.data.eval_views),
            "num_train_images": len(self.data.train),
            "num_eval_images": len(self.data.eval),
            "image_size": self.data.image_size,
            "gaussians": self.cfg.model.gaussians,
            "shading": self.cfg.model.shading,
            "light": self.model.light.describe() if self.model.light is not None else None,
            "num_gaussians": {k: p.num_gaussians for k, p in self.parts.items()},
            "binding_mesh": {k: p.binding_mesh for k, p in self.parts.items()},
            "device": str(self.device),
            "timings": {**self.timings, "train_s": self._train_time, "s_per_iter": self._train_time / n_train},
        }
        write_json(self.out / "metrics.json", metrics)
        return metrics

    @torch.no_grad()
    def write_pngs(self) -> None:
        import matplotlib  # deferred: start-up cost, only the PNG writers need it

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt  # deferred: after the Agg backend is chosen

        rows = []
        pick = self.data.eval[:: max(1, len(self.data.eval) // max(1, self.cfg.run.strip_views))][
            : self.cfg.run.strip_views
        ]
        for s in pick:
            gt, _, _ = self.targets([s])
            rgb, _ = self.render([s])
            pr = rgb[0].clamp(0, 1)
            err = (pr - gt[0]).abs().mean(-1, keepdim=True).expand(-1, -1, 3).clamp(0, 1)
            rows.append(torch.cat([gt[0], pr, err], 1))
        strip = (torch.cat(rows, 0).cpu().numpy() * 255).round().astype(np.uint8)
        plt.imsave(self.out / "strip.png", strip)
        fig, ax = plt.subplots(1, 2, figsize=(10, 4))
        steps = [h["step"] for h in self.history]
        ax[0].plot(steps, [h["loss"] for h in self.history], lw=0.8, label="loss")
        ax[0].plot(steps, [h["photo"] for h in self.history], lw=0.8, label="photometric")
        ax[0].set_xlabel("step")
        ax[0].set_yscale("log")
        ax[0].legend()
        ax[1].plot([e["step"] for e in self.evals], [e["psnr"] for e in self.evals], "o-")
        ax[1].set_xlabel("step")
        ax[1].set_ylabel("held-out PSNR (dB)")
        fig.tight_layout()
        fig.savefig(self.out / "curves.png", dpi=80)
        plt.close(fig)


def _summary(ev: dict[str, Any]) -> dict[str, Any]:
    return {"step": ev["step"], "psnr": ev["psnr"], "ssim": ev["ssim"], "alpha_outside": ev["alpha_outside"]}
