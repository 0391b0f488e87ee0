"""SRM training: one StyleUNet for every finished HOGS run of a runs folder.

Start with :class:`SRMTrainer` (built from an ``SRMTrainConfig``; its docstring describes the
training data, :mod:`hogsa_loader.train.srm_pairs`, and model selection);
:meth:`SRMTrainer.train` runs the loop and writes the run folder (described there), and
:meth:`SRMTrainer.train_step` describes one step.
"""

from __future__ import annotations

import copy
import sys
import time
from pathlib import Path
from typing import Any, Optional, Sequence

import numpy as np
import torch
import torch.nn.functional as F
from torch import Tensor

from hogsa_loader.errors import AssetError
from hogsa_loader.models.srm.io import load_srm, save_srm
from hogsa_loader.models.srm.model import SRM, dihedral
from hogsa_loader.models.srm.styleunet import StyleUNetConfig, count_gflops
from hogsa_loader.train.hogs_data import ViewSample, dilate_mask
from hogsa_loader.train.loop import StepLoop
from hogsa_loader.train.losses import box_of, psnr, ssim_map
from hogsa_loader.train.run_folder import write_json
from hogsa_loader.train.srm_config import SRMTrainConfig
from hogsa_loader.train.srm_discriminator import ConditionalDiscriminator
from hogsa_loader.train.srm_losses import (
    PERCEPTUAL_DEFAULT_WEIGHT,
    d_logistic,
    g_nonsaturating,
    l1_loss,
    perceptual_loss,
    r1_penalty,
)
from hogsa_loader.train.srm_pairs import PAIR_MODES, PairSet, find_runs, fold_runs, load_pairs

__all__ = ["SRMTrainConfig", "SRMTrainer", "find_runs", "PairSet", "AUGMENTS", "dihedral"]

AUGMENTS = ("none", "flip", "d4")


def _gt(samples: Sequence[ViewSample]) -> tuple[Tensor, Tensor]:
    """GT (B, H, W, 3) in [0, 1] with the background black, mask (B, H, W) bool."""
    img = torch.as_tensor(np.stack([s.image for s in samples])).float() / 255.0
    mask = torch.as_tensor(np.stack([s.mask for s in samples])) > 0
    return img * mask[..., None], mask


def _adam_state(opt: torch.optim.Optimizer, prefix: str) -> tuple[dict[str, Tensor], list[dict[str, Any]]]:
    sd = opt.state_dict()
    tensors = {
        f"{prefix}.{i}.{k}": torch.as_tensor(v).detach().cpu().contiguous()
        for i, st in sd["state"].items()
        for k, v in st.items()
    }
    groups = [{k: v for k, v in g.items()} for g in sd["param_groups"]]
    return tensors, groups


def _load_adam(
    opt: torch.optim.Optimizer, prefix: str, tensors: dict[str, Tensor], groups: list[dict[str, Any]]
) -> None:
    state: dict[int, dict[str, Tensor]] = {}
    for k, v in tensors.items():
        if k.startswith(prefix + "."):
            i, name = k[len(prefix) + 1 :].split(".", 1)
            state.setdefault(int(i), {})[name] = v
    for g in groups:
        if isinstance(g.get("betas"), list):
            g["betas"] = tuple(g["betas"])
    opt.load_state_dict({"state": state, "param_groups": groups})


class SRMTrainer(StepLoop):
    """Builds the data (all runs) and networks; :meth:`train` runs the loop.

    Data (:mod:`hogsa_loader.train.srm_pairs`). Every finished HOGS run under ``data.hogs`` (a folder
    with ``hand_right/``, ``hand_left/``, ``object/`` manifests and ``config.json``) contributes
    its training (frame, view) samples, selected exactly as its HOGS training did, so held-out
    views and frames are never seen. Inputs are frozen HOGS renders (premultiplied on black +
    alpha) at ``image_size / scale`` — by the run itself (``pairs="own"``), by view-fold runs
    under ``data.cross_hogs`` that did not see the sample's view (``"cross"``), or both; targets
    are the ground-truth crops at ``image_size`` with the background masked to black (as HOGS
    training does). Renders are cached under ``RUN/cache/`` or ``cache`` (a folder several SRM
    runs may share: entries are keyed by the HOGS run's weights, the samples with their labels and
    cameras, the body model and the resolution).
    Evaluation always uses the run's own renders of its held-out views.

    Model selection. The SRM over-fits its training pairs when trained long (small world, 4
    folds: held-out gain +0.29 dB at 4000 steps, −0.02 dB at 8000; with ``augment="d4"`` the
    gain still rose at 10000 steps, +0.36 dB, so ``d4`` is the default; in a 400-step run it
    gains less than no augmentation, +0.06 against +0.24 dB). With ``val_views`` the
    pairs of those *training* views are kept out of training; every ``eval_every`` steps the EMA
    generator is scored on them (fold renders: novel-view errors) and the best one is kept. The
    final model is that best one, so the held-out views play no part in choosing it. Refitting
    on every training view for the selected number of steps then gives those views back
    (d4, all 7 training views: +0.44 dB at 10000 steps and +0.51 dB at 16000, the lengths the
    validated runs chose with those budgets).
    """

    desc = "srm"

    def __init__(self, cfg: SRMTrainConfig, *, progress: bool = True, log=None) -> None:
        if cfg.model.scale not in (1, 2):
            raise ValueError("--model-scale must be 1 or 2")
        if cfg.data.augment not in AUGMENTS:
            raise ValueError(f"augment must be one of {AUGMENTS}, got {cfg.data.augment!r}")
        if cfg.optim.iters < 0 or cfg.optim.batch_size < 1:
            raise ValueError("iters must be >= 0 and batch_size >= 1")
        self.cfg = cfg
        self.progress = progress
        self.log = log or (lambda msg: print(msg, file=sys.stderr))
        self.device = torch.device(cfg.run.device)
        self.out = Path(cfg.run.out)
        t0 = time.perf_counter()
        if cfg.data.pairs not in PAIR_MODES:
            raise ValueError(f"pairs must be one of {PAIR_MODES}, got {cfg.data.pairs!r}")
        self.runs = find_runs(cfg.data.hogs, cfg.data.runs)
        cands = find_runs(cfg.data.cross_hogs) if cfg.data.cross_hogs else []
        cache = Path(cfg.data.cache) if cfg.data.cache else self.out / "cache"
        d = cfg.data
        self.sets = [
            load_pairs(
                d.root,
                r,
                cache,
                d.image_size,
                cfg.model.scale,
                d.pairs,
                fold_runs(r, cands),
                self.log,
                d.val_views or (),
            )
            for r in self.runs
        ]
        self.timings: dict[str, float] = {"data_s": time.perf_counter() - t0}
        self.size = self.sets[0].data.image_size
        if any(s.data.image_size != self.size for s in self.sets):
            raise ValueError("runs have different image sizes; pass --image-size")
        torch.manual_seed(cfg.run.seed)
        ucfg = StyleUNetConfig(
            channels=list(cfg.model.channels),
            style_dim=cfg.model.style_dim,
            scale=cfg.model.scale,
            wavelet=cfg.model.wavelet,
        )
        self.g = SRM(ucfg).to(self.device)
        self.g_ema = copy.deepcopy(self.g).eval()
        for p in self.g_ema.parameters():
            p.requires_grad_(False)
        crop = cfg.data.crop or self.size
        if crop > self.size or crop % (self.g.net.multiple * cfg.model.scale):
            multiple = self.g.net.multiple * cfg.model.scale
            raise ValueError(f"--crop {crop} must be <= image size {self.size} and a multiple of {multiple}")
        self.crop = crop
        self.perc = perceptual_loss(cfg.loss.vgg_weights).to(self.device)
        self.lambda_perc = (
            cfg.loss.lambda_perc if cfg.loss.lambda_perc is not None else PERCEPTUAL_DEFAULT_WEIGHT[self.perc.kind]
        )
        self.use_gan = cfg.loss.lambda_gan > 0
        rg, rd = 4 / 5, cfg.loss.r1_every / (cfg.loss.r1_every + 1)
        self.opt_g = torch.optim.Adam(self.g.parameters(), lr=cfg.optim.lr * rg, betas=(0.0, 0.99**rg))
        self.d: Optional[ConditionalDiscriminator] = None
        self.opt_d: Optional[torch.optim.Adam] = None
        if self.use_gan:
            self.d = ConditionalDiscriminator(crop, cond_channels=4).to(self.device)
            self.opt_d = torch.optim.Adam(self.d.parameters(), lr=cfg.optim.lr * rd, betas=(0.0, 0.99**rd))
        self.gen = torch.Generator().manual_seed(cfg.run.seed)
        self.step = 0
        self.history: list[dict[str, float]] = []
        self.evals: list[dict[str, Any]] = []
        self._train_time = 0.0
        self.use_val = bool(cfg.data.val_views)
        #: best validation score so far {"step", "psnr", "ssim"} and that EMA generator's weights
        self.best: Optional[dict[str, Any]] = None
        self.best_state: Optional[dict[str, Tensor]] = None
        # flat index over (set, sample)
        self.index = [(si, i) for si, s in enumerate(self.sets) for i in range(len(s.train_rows))]
        self.gflops = count_gflops(self.g.net, 256)
        self.resumed = False

    # ------------------------------------------------------------------ batches
    def batch(self) -> tuple[Tensor, Tensor, Tensor]:
        """Random training batch: coarse rgb (B,3,h,w), alpha (B,1,h,w), GT (B,3,H,W), crops."""
        cfg, s = self.cfg, self.cfg.model.scale
        idx = torch.randint(len(self.index), (cfg.optim.batch_size,), generator=self.gen).tolist()
        c_lo = self.crop // s
        lo = self.size // s
        offs = torch.randint(lo - c_lo + 1, (cfg.optim.batch_size, 2), generator=self.gen).tolist()
        rgbs, alphas, gts = [], [], []
        for (si, i), (y, x) in zip((self.index[j] for j in idx), offs):
            ps = self.sets[si]
            rgbs.append(ps.train_rgb[i, y : y + c_lo, x : x + c_lo])
            alphas.append(ps.train_alpha[i, y : y + c_lo, x : x + c_lo])
            smp = ps.data.train[int(ps.train_rows[i])]
            img = torch.as_tensor(smp.image[y * s : (y + c_lo) * s, x * s : (x + c_lo) * s]).float() / 255.0
            m = torch.as_tensor(smp.mask[y * s : (y + c_lo) * s, x * s : (x + c_lo) * s]) > 0
            gts.append(img * m[..., None])
        dev = self.device
        rgb = (torch.stack(rgbs).float() / 255.0).permute(0, 3, 1, 2)
        alpha = (torch.stack(alphas).float() / 255.0)[:, None]
        gt = torch.stack(gts).permute(0, 3, 1, 2)
        if cfg.data.augment != "none":
            n = 2 if cfg.data.augment == "flip" else 8
            codes = torch.randint(n, (cfg.optim.batch_size,), generator=self.gen).tolist()
            rgb, alpha, gt = (torch.stack([dihedral(t[b], c) for b, c in enumerate(codes)]) for t in (rgb, alpha, gt))
        return rgb.to(dev), alpha.to(dev), gt.to(dev)

    def discriminator_real(self, gt: Tensor, alpha: Tensor) -> Tensor:
        """What D sees as real (B, 3, H, W) in [0, 1]: the GT clipped to the rendered alpha,
        ``min(gt, α)``, the closest image the generator can produce (its output is
        ``c · α`` with c in [0, 1]). With the raw GT (masked by the *GT* silhouette) D could
        tell every fake by its outline alone, which the generator can never change."""
        return torch.minimum(gt, self.g.output_alpha(alpha))

    def condition(self, rgb: Tensor, alpha: Tensor) -> Tensor:
        """D's condition (B, 4, H, W) in [−1, 1]: coarse premultiplied rgb + alpha at output size."""
        c = torch.cat([rgb, alpha], 1)
        if self.cfg.model.scale != 1:
            c = F.interpolate(c, scale_factor=float(self.cfg.model.scale), mode="bilinear", align_corners=False)
        return c * 2.0 - 1.0

    # ------------------------------------------------------------------ training
    def train_step(self) -> dict[str, float]:
        """One training step.

        Random ``crop``-sized windows (full images when ``crop`` = 0) of a random batch:
        D step (logistic loss against real = GT clipped to the rendered alpha, the closest image the
        generator can reach; lazy R1 every ``r1_every`` steps with weight γ/2·r1_every), then
        G step ``λ_L1·L1 + λ_P·perceptual + λ_GAN·softplus(−D(G))`` (all in [−1, 1]), then EMA.
        Adam(lr·r, betas (0, 0.99^r)) with r = 4/5 (G) and 16/17 (D) as in StyleUNet.
        """
        cfg = self.cfg
        rgb, alpha, gt = self.batch()
        real = gt * 2.0 - 1.0
        real_d = self.discriminator_real(gt, alpha) * 2.0 - 1.0
        cond = self.condition(rgb, alpha)
        terms: dict[str, float] = {}
        z = torch.randn(cfg.optim.batch_size, cfg.model.style_dim, device=self.device)
        if self.use_gan:
            assert self.d is not None and self.opt_d is not None
            self.d.requires_grad_(True)
            with torch.no_grad():
                fake = self.g(rgb, alpha, z) * 2.0 - 1.0
            d_loss = d_logistic(self.d(real_d, cond), self.d(fake, cond))
            self.opt_d.zero_grad(set_to_none=True)
            d_loss.backward()
            self.opt_d.step()
            terms["d"] = float(d_loss.detach())
            if cfg.loss.r1_every > 0 and self.step % cfg.loss.r1_every == 0:
                r1, real_logits = r1_penalty(lambda x: self.d(x, cond), real_d)  # type: ignore[misc]
                self.opt_d.zero_grad(set_to_none=True)
                (cfg.loss.r1_gamma / 2 * r1 * cfg.loss.r1_every + 0 * real_logits[0]).backward()
                self.opt_d.step()
                terms["r1"] = float(r1.detach())
            self.d.requires_grad_(False)
        z = torch.randn(cfg.optim.batch_size, cfg.model.style_dim, device=self.device)
        fake = self.g(rgb, alpha, z) * 2.0 - 1.0
        l1 = l1_loss(fake, real)
        perc = self.perc(fake, real)
        loss = cfg.loss.lambda_l1 * l1 + self.lambda_perc * perc
        terms.update(l1=float(l1.detach()), perc=float(perc.detach()))
        if self.use_gan:
            gan = g_nonsaturating(self.d(fake, cond))  # type: ignore[misc]
            loss = loss + cfg.loss.lambda_gan * gan
            terms["gan"] = float(gan.detach())
        self.opt_g.zero_grad(set_to_none=True)
        loss.backward()
        self.opt_g.step()
        self._update_ema()
        self.step += 1
        terms["loss"] = float(loss.detach())
        terms["step"] = self.step
        return terms

    @torch.no_grad()
    def _update_ema(self) -> None:
        # ramp: short runs would otherwise evaluate a mostly-untrained EMA
        decay = min(self.cfg.optim.ema_decay, (1 + self.step) / (10 + self.step))
        for pe, p in zip(self.g_ema.parameters(), self.g.parameters()):
            pe.lerp_(p, 1.0 - decay)
        for be, b in zip(self.g_ema.buffers(), self.g.buffers()):
            be.copy_(b)

    # ------------------------------------------------------------------ evaluation
    @torch.no_grad()
    def _score(self, ps: PairSet, smp: ViewSample, rgb: Tensor, alpha: Tensor, model: SRM) -> dict[str, Any]:
        """PSNR/SSIM of one coarse render (1,h,w,3)/(1,h,w) in [0, 1] without vs with ``model``,
        inside the sample's foreground box (bbox of the mask dilated by the HOGS margin)."""
        gt, mask = _gt([smp])
        region = dilate_mask(mask, ps.margin_px)[0]
        ref = model.refine(rgb.to(self.device), alpha.to(self.device)).cpu()
        coarse = rgb.cpu()
        scale = float(self.cfg.model.scale)
        if scale != 1:
            coarse = (
                F.interpolate(coarse.permute(0, 3, 1, 2), scale_factor=scale, mode="bilinear", align_corners=False)
                .permute(0, 2, 3, 1)
                .clamp(0, 1)
            )
        y0, y1, x0, x1 = box_of(region)
        g = gt[:, y0:y1, x0:x1]
        win = 11 if min(y1 - y0, x1 - x0) >= 11 else 3
        row: dict[str, Any] = {}
        for tag, img in (("without_srm", coarse), ("with_srm", ref)):
            p = img[:, y0:y1, x0:x1].clamp(0, 1)
            row[tag] = {"psnr": psnr(p, g), "ssim": float(ssim_map(p, g, win).mean())}
        return row

    @torch.no_grad()
    def validate(self, model: Optional[SRM] = None) -> dict[str, Any]:
        """Mean PSNR/SSIM without vs with SRM on the validation pairs (``val_views``; at most
        ``max_val`` per run, evenly spaced), same metric as :meth:`evaluate`."""
        model = self.g_ema if model is None else model
        rows = []
        for ps in self.sets:
            n = len(ps.val_rows)
            for j in np.unique(np.linspace(0, n - 1, min(n, self.cfg.data.max_val)).round().astype(int)) if n else []:
                smp = ps.data.train[int(ps.val_rows[j])]
                rgb, a = ps.val_rgb[j : j + 1].float() / 255.0, ps.val_alpha[j : j + 1].float() / 255.0
                rows.append(self._score(ps, smp, rgb, a, model))
        if not rows:
            raise ValueError("no validation pairs (set val_views)")
        out: dict[str, Any] = {"step": self.step, "n": len(rows)}
        for tag in ("without_srm", "with_srm"):
            out[tag] = {m: float(np.mean([r[tag][m] for r in rows])) for m in ("psnr", "ssim")}
        return out

    @torch.no_grad()
    def evaluate(self, model: Optional[SRM] = None) -> dict[str, Any]:
        """Held-out PSNR/SSIM without vs with SRM, inside each sample's foreground box
        (bbox of the mask dilated by the HOGS margin), GT background black — the HOGS
        trainer's metric."""
        model = self.g_ema if model is None else model
        rows = []
        for ps in self.sets:
            for k, smp in enumerate(ps.data.eval):
                row: dict[str, Any] = {
                    "run": ps.name,
                    "sequence": ps.data.sequences[smp.seq_index].name,
                    "frame": smp.frame,
                    "view": smp.view,
                }
                row.update(self._score(ps, smp, ps.eval_rgb[k : k + 1], ps.eval_alpha[k : k + 1], model))
                rows.append(row)
        per_view = []
        for key in sorted({(r["run"], r["view"]) for r in rows}):
            rv = [r for r in rows if (r["run"], r["view"]) == key]
            entry: dict[str, Any] = {"run": key[0], "view": key[1], "n": len(rv)}
            for tag in ("without_srm", "with_srm"):
                entry[tag] = {m: float(np.mean([r[tag][m] for r in rv])) for m in ("psnr", "ssim")}
            entry["delta_psnr"] = entry["with_srm"]["psnr"] - entry["without_srm"]["psnr"]
            entry["delta_ssim"] = entry["with_srm"]["ssim"] - entry["without_srm"]["ssim"]
            per_view.append(entry)
        out: dict[str, Any] = {"step": self.step}
        for tag in ("without_srm", "with_srm"):
            out[tag] = {
                "psnr": float(np.mean([r[tag]["psnr"] for r in rows])),
                "ssim": float(np.mean([r[tag]["ssim"] for r in rows])),
                "lpips": None,
            }
        out["delta_psnr"] = out["with_srm"]["psnr"] - out["without_srm"]["psnr"]
        out["delta_ssim"] = out["with_srm"]["ssim"] - out["without_srm"]["ssim"]
        out["per_view"] = per_view
        out["per_sample"] = rows
        return out

    def train(self, overwrite: bool = False) -> dict[str, Any]:
        """Train to ``cfg.optim.iters`` steps (from the current step), evaluating and checkpointing.

        Args:
            overwrite: when the run was not resumed and its folder holds checkpoints, empty
                the folder and start again (otherwise :class:`RunExistsError`).

        Run folder::

            config.json, metrics.json, samples.png (coarse | refined | GT), curves.png
            manifest.json + srm.safetensors      the final EMA generator (load_srm(RUN)); with
                                                 val_views, the one with the best validation PSNR
            checkpoints/latest.json              {"step", "folder"} (written last)
            checkpoints/step_N/{g, g_ema}/       save_srm folders (+ g_best with val_views)
            checkpoints/step_N/trainer.safetensors   D weights, Adam states, RNG states
            checkpoints/step_N/trainer.json      step, history, evals, Adam param groups, sha256 of
                                                 trainer.safetensors (checked on resuming)
            cache/                               coarse renders (unless ``cache`` names another folder)

        :meth:`SRMTrainer.train` refuses to start from step 0 in a folder that holds checkpoints
        (:class:`~hogsa_loader.train.run_folder.RunExistsError`) unless the run was resumed first
        or ``overwrite=True``.
        """
        last = self.run_steps(overwrite)
        model, final, step = self.g_ema, last, self.step
        if self.use_val:
            assert self.best is not None
            model, step = self.best_model(), int(self.best["step"])
            final = self.evaluate(model)
        metrics = self.write_metrics(final, last)
        save_srm(model, self.out, extra=self._provenance(final, step))
        self.write_pngs(model)
        return metrics

    def _postfix(self, terms: dict[str, float]) -> dict[str, str]:
        return {"l1": f"{terms['l1']:.4f}", "perc": f"{terms['perc']:.4f}", "gan": f"{terms.get('gan', 0):.3f}"}

    def _eval_message(self, ev: dict[str, Any]) -> str:
        val = f", validation {self.evals[-1]['val_with_srm']:.2f} dB" if self.use_val else ""
        return (
            f"step {self.step}: held-out PSNR {ev['without_srm']['psnr']:.2f} -> {ev['with_srm']['psnr']:.2f} "
            "dB, "
            f"SSIM {ev['without_srm']['ssim']:.4f} -> {ev['with_srm']['ssim']:.4f}{val}"
        )

    def _eval_point(self, ev: dict[str, Any]) -> dict[str, Any]:
        """Summary of a held-out evaluation at the current step; with validation views also
        scores the EMA generator on them and keeps it if it is the best so far."""
        summary = _summary(ev)
        if self.use_val:
            v = self.validate()
            summary.update(
                val_without_srm=v["without_srm"]["psnr"],
                val_with_srm=v["with_srm"]["psnr"],
                val_ssim_with_srm=v["with_srm"]["ssim"],
                val_n=v["n"],
            )
            if self.best is None or v["with_srm"]["psnr"] > self.best["psnr"]:
                self.best = {
                    "step": self.step,
                    "psnr": v["with_srm"]["psnr"],
                    "ssim": v["with_srm"]["ssim"],
                    "psnr_without_srm": v["without_srm"]["psnr"],
                    "n": v["n"],
                }
                self.best_state = {k: t.detach().clone() for k, t in self.g_ema.net.state_dict().items()}
        return summary

    def best_model(self) -> SRM:
        """The EMA generator with the best validation PSNR so far (a copy)."""
        if self.best_state is None:
            raise ValueError("no validated model yet (val_views unset or no evaluation run)")
        m = copy.deepcopy(self.g_ema)
        m.net.load_state_dict(self.best_state)
        return m

    # ------------------------------------------------------------------ checkpoints
    def targets(self) -> list[dict[str, Any]]:
        """What the SRM has seen, per run: subject, object, sequences and the views whose
        ground-truth images were training targets (``"views"``) or validation targets
        (``"val_views"``). Recorded in every saved SRM so that an evaluation can refuse
        views the SRM was trained or selected on (``experiments/render_quality.py --srm``)."""
        out = []
        for ps in self.sets:
            views = sorted({int(ps.data.train[int(i)].view) for i in ps.train_rows})
            val = sorted({int(ps.data.train[int(i)].view) for i in ps.val_rows})
            out.append(
                {
                    "run": ps.name,
                    "subject": ps.data.subject,
                    "object": ps.data.object_name,
                    "sequences": [s.name for s in ps.data.sequences],
                    "views": views,
                    "val_views": val,
                }
            )
        return out

    def _provenance(self, final: Optional[dict[str, Any]] = None, step: Optional[int] = None) -> dict[str, Any]:
        d: dict[str, Any] = {
            "step": self.step if step is None else step,
            "runs": [s.name for s in self.sets],
            "image_size": self.size,
            "perceptual": self.perc.kind,
            "gflops_256": self.gflops,
            "targets": self.targets(),
        }
        if final is not None:
            d["held_out"] = {k: final[k] for k in ("without_srm", "with_srm")}
        if self.best is not None:
            d["selection"] = {"val_views": list(self.cfg.data.val_views or []), "best": self.best}
        return d

    def _save_state(self, folder: Path) -> tuple[dict[str, Tensor], dict[str, Any]]:
        """The generators (and the best validated one) into ``folder``; RNG states, Adam
        moments and the discriminator as tensors."""
        targets = self.targets()
        save_srm(self.g, folder / "g", extra={"step": self.step, "targets": targets})
        save_srm(self.g_ema, folder / "g_ema", extra={"step": self.step, "targets": targets})
        if self.best is not None:
            save_srm(self.best_model(), folder / "g_best", extra={"step": int(self.best["step"]), "targets": targets})
        tensors: dict[str, Tensor] = {"rng.sampler": self.gen.get_state(), "rng.torch": torch.get_rng_state()}
        if self.device.type == "cuda":
            tensors["rng.cuda"] = torch.cuda.get_rng_state(self.device)
        t, groups_g = _adam_state(self.opt_g, "adam_g")
        tensors.update(t)
        groups_d: list[dict[str, Any]] = []
        if self.d is not None and self.opt_d is not None:
            t, groups_d = _adam_state(self.opt_d, "adam_d")
            tensors.update(t)
            tensors.update({f"d.{k}": v.detach().cpu().contiguous() for k, v in self.d.state_dict().items()})
        return tensors, {"adam_g_groups": groups_g, "adam_d_groups": groups_d, "best": self.best}

    def _load_state(self, folder: Path, state: dict[str, Any], tensors: dict[str, Tensor]) -> None:
        """Generators, optimisers, discriminator, best model and RNG states (state that does not
        fit the networks: AssetError)."""
        tpath = folder / "trainer.safetensors"
        if not isinstance(state.get("adam_g_groups"), list) or not isinstance(state.get("adam_d_groups", []), list):
            raise AssetError(folder / "trainer.json", "'adam_g_groups' / 'adam_d_groups' must be lists")
        self.g.net.load_state_dict(load_srm(folder / "g").net.state_dict())
        self.g_ema.net.load_state_dict(load_srm(folder / "g_ema").net.state_dict())
        try:
            _load_adam(
                self.opt_g,
                "adam_g",
                {k: v.to(self.device) if not k.endswith(".step") else v for k, v in tensors.items()},
                state["adam_g_groups"],
            )
            if self.d is not None and self.opt_d is not None:
                self.d.load_state_dict({k[2:]: v for k, v in tensors.items() if k.startswith("d.")})
                _load_adam(
                    self.opt_d,
                    "adam_d",
                    {k: v.to(self.device) if not k.endswith(".step") else v for k, v in tensors.items()},
                    state["adam_d_groups"],
                )
        except (RuntimeError, ValueError, KeyError, TypeError) as exc:
            raise AssetError(tpath, f"optimiser or discriminator state does not fit the networks ({exc})") from None
        for opt in (self.opt_g, self.opt_d):
            for p, st in opt.state.items() if opt is not None else ():
                for k in ("exp_avg", "exp_avg_sq"):
                    if k in st and st[k].shape != p.shape:
                        raise AssetError(
                            tpath, f"Adam {k} of shape {tuple(st[k].shape)} for a parameter {tuple(p.shape)}"
                        )
        self.best = state.get("best")
        if self.best is not None:  # before the RNG is restored: building a model draws random numbers
            self.best_state = load_srm(folder / "g_best").net.state_dict()
        try:
            self.gen.set_state(tensors["rng.sampler"])
            torch.set_rng_state(tensors["rng.torch"])
            if "rng.cuda" in tensors and self.device.type == "cuda":
                torch.cuda.set_rng_state(tensors["rng.cuda"], self.device)
        except (RuntimeError, TypeError) as exc:
            raise AssetError(tpath, f"unusable RNG state ({exc})") from None

    # ------------------------------------------------------------------ reports
    def write_metrics(self, final: dict[str, Any], last: Optional[dict[str, Any]] = None) -> dict[str, Any]:
        """``metrics.json``: ``final`` is the evaluation of the saved model (the best validated
        one with ``val_views``), ``last`` that of the last step's EMA generator."""
        n = max(1, len(self.history))
        metrics = {
            "without_srm": final["without_srm"],
            "with_srm": final["with_srm"],
            "delta_psnr": final["delta_psnr"],
            "delta_ssim": final["delta_ssim"],
            "lpips_note": "LPIPS not computed (no local weights)",
            "per_view": final["per_view"],
            "per_sample": final["per_sample"],
            "region": "foreground box (bbox of the part mask dilated by the HOGS margin); GT background black",
            "iters": self.step,
            "selected_step": int(self.best["step"]) if self.best is not None else self.step,
            "selection": (
                {
                    "rule": "best validation PSNR with SRM (EMA generator, every eval_every steps)",
                    "val_views": list(self.cfg.data.val_views or []),
                    "best": self.best,
                    "last_step": {
                        k: (last or final)[k] for k in ("without_srm", "with_srm", "delta_psnr", "delta_ssim")
                    },
                }
                if self.use_val
                else None
            ),
            "evals": self.evals,
            "runs": [
                {
                    "name": s.name,
                    "subject": s.data.subject,
                    "object": s.data.object_name,
                    "num_train_images": len(s.data.train),
                    "num_eval_images": len(s.data.eval),
                    "train_views": list(s.data.train_views),
                    "eval_views": list(s.data.eval_views),
                    "pair_sources": s.sources,
                }
                for s in self.sets
            ],
            "image_size": self.size,
            "crop": self.crop,
            "scale": self.cfg.model.scale,
            "perceptual": {"kind": self.perc.kind, "weight": self.lambda_perc},
            "losses": {
                "l1": self.cfg.loss.lambda_l1,
                "gan": self.cfg.loss.lambda_gan,
                "r1_gamma": self.cfg.loss.r1_gamma,
                "r1_every": self.cfg.loss.r1_every,
            },
            "gflops_256": self.gflops,
            "num_params": sum(p.numel() for p in self.g.parameters()),
            "device": str(self.device),
            "torch_threads": torch.get_num_threads(),
            "timings": {**self.timings, "train_s": self._train_time, "s_per_iter": self._train_time / n},
        }
        write_json(self.out / "metrics.json", metrics)
        return metrics

    @torch.no_grad()
    def write_pngs(self, model: Optional[SRM] = None) -> None:
        """``samples.png`` (held-out: coarse | refined | GT, each cropped to the sample's square
        foreground box and enlarged to the image size, nearest neighbour) and ``curves.png``."""
        import matplotlib  # deferred: start-up cost, only the PNG writers need it

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt  # deferred: after the Agg backend is chosen

        model = self.g_ema if model is None else model
        rows = []
        items = [(ps, k) for ps in self.sets for k in range(len(ps.data.eval))]
        pick = items[:: max(1, len(items) // max(1, self.cfg.run.strip_views))][: self.cfg.run.strip_views]
        S = self.size
        for ps, k in pick:
            gt, mask = _gt([ps.data.eval[k]])
            rgb = ps.eval_rgb[k : k + 1].to(self.device)
            ref = model.refine(rgb, ps.eval_alpha[k : k + 1].to(self.device)).cpu()
            coarse = rgb.cpu()
            if self.cfg.model.scale != 1:
                coarse = F.interpolate(coarse.permute(0, 3, 1, 2), size=(S, S), mode="nearest").permute(0, 2, 3, 1)
            y0, y1, x0, x1 = box_of(dilate_mask(mask, ps.margin_px)[0])
            side = max(y1 - y0, x1 - x0)  # square box around the foreground, enlarged to S (nearest)
            cy, cx = (y0 + y1) // 2, (x0 + x1) // 2
            y0, x0 = min(max(0, cy - side // 2), S - side), min(max(0, cx - side // 2), S - side)
            cells = [
                F.interpolate(
                    im[:, y0 : y0 + side, x0 : x0 + side].permute(0, 3, 1, 2), size=(S, S), mode="nearest"
                ).permute(0, 2, 3, 1)[0]
                for im in (coarse, ref, gt)
            ]
            rows.append(torch.cat(cells, 1).clamp(0, 1))
        strip = (torch.cat(rows, 0).numpy() * 255).round().astype(np.uint8)
        plt.imsave(self.out / "samples.png", strip)
        fig, ax = plt.subplots(1, 2, figsize=(11, 4))
        steps = [h["step"] for h in self.history]
        for key in ("l1", "perc", "gan", "d"):
            vals = [(h["step"], h[key]) for h in self.history if key in h]
            if vals:
                xs, ys = zip(*vals)
                k = max(1, len(ys) // 100)
                ys_s = np.convolve(ys, np.ones(k) / k, mode="valid")
                ax[0].plot(xs[k - 1 :], ys_s, lw=0.8, label=key)
        ax[0].set_xlabel("step")
        ax[0].set_yscale("log")
        ax[0].legend()
        ev = [e for e in self.evals if e["step"] > 0]  # step 0: the untrained SRM, off the scale
        ax[1].axhline(0.0, color="0.5", lw=0.8, ls="--", label="HOGS only")
        ax[1].plot([e["step"] for e in ev], [e["with_srm"] - e["without_srm"] for e in ev], "o-", label="held-out")
        if self.use_val:
            ax[1].plot(
                [e["step"] for e in ev],
                [e["val_with_srm"] - e["val_without_srm"] for e in ev],
                "s-",
                label=f"validation (views {list(self.cfg.data.val_views or [])})",
            )
            if self.best is not None:
                ax[1].axvline(self.best["step"], color="k", lw=0.6, label=f"selected (step {self.best['step']})")
        ax[1].set_xlabel("step")
        ax[1].set_ylabel("PSNR gain over HOGS (dB)")
        ax[1].legend()
        fig.tight_layout()
        fig.savefig(self.out / "curves.png", dpi=80)
        plt.close(fig)
        del steps


def _summary(ev: dict[str, Any]) -> dict[str, Any]:
    return {
        "step": ev["step"],
        "without_srm": ev["without_srm"]["psnr"],
        "with_srm": ev["with_srm"]["psnr"],
        "ssim_without_srm": ev["without_srm"]["ssim"],
        "ssim_with_srm": ev["with_srm"]["ssim"],
    }
