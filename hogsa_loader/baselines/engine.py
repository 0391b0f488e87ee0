"""Training and evaluation of the ArcticNet-SF baseline on ARCTIC-format batches.

:func:`training_step` runs one optimisation step on a collated ``(inputs, targets,
meta_info)`` batch (real, synthetic or mixed): ARCTIC's target preparation, the model,
ARCTIC's loss, Adam with gradient-norm clipping. :func:`evaluate` runs a model over a
split in temporal order and returns ARCTIC's per-frame and per-sequence metrics.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any, Callable, Iterable, Literal, Mapping, Optional

import numpy as np
import torch
from torch import Tensor, nn

from hogsa_loader.baselines.loss import arcticnet_sf_loss
from hogsa_loader.baselines.metrics import per_frame_metrics, sequence_metrics, summarize
from hogsa_loader.baselines.targets import prepare_targets
from hogsa_loader.sample.arctic_dataset import parse_imgname

__all__ = [
    "BodyLayers",
    "to_device",
    "prepare_batch",
    "training_step",
    "apply_losses",
    "evaluate",
    "evaluate_split",
    "temporal_order",
    "mean_cameras",
    "SEQUENCE_KEYS",
]

#: Per-frame tensors kept for the temporal metrics (prediction and ground truth).
SEQUENCE_KEYS = ("mano.v3d.cam.r", "mano.v3d.cam.l", "mano.j3d.cam.r", "mano.j3d.cam.l", "object.v.cam")
_TARGET_ONLY = ("is_valid", "right_valid", "left_valid", "dist.ro", "dist.lo", "idx.ro", "idx.lo", "object.v_len")


@dataclass
class BodyLayers:
    """The MANO layers and object layer a model and its targets are built with.

    Attributes:
        mano_r, mano_l: right / left :class:`~hogsa_loader.assets.hands.mano.MANOLayer`.
        objects: :class:`~hogsa_loader.assets.objects.articulated.ArticulatedObjectLayer`.
    """

    mano_r: nn.Module
    mano_l: nn.Module
    objects: nn.Module

    @classmethod
    def from_root(cls, root: Any) -> "BodyLayers":
        """The layers of an :class:`~hogsa_loader.assets.arctic.ArcticRoot`."""
        layers = root.mano_layers()
        return cls(layers["right"], layers["left"], root.object_layer())

    def to(self, device: Any) -> "BodyLayers":
        return BodyLayers(self.mano_r.to(device), self.mano_l.to(device), self.objects.to(device))


def to_device(batch: Any, device: Any) -> Any:
    """Tensors of a nested batch moved to ``device`` (other values kept)."""
    if isinstance(batch, Tensor):
        return batch.to(device, non_blocking=True)
    if isinstance(batch, dict):
        return {k: to_device(v, device) for k, v in batch.items()}
    if isinstance(batch, (list, tuple)) and batch and isinstance(batch[0], (Tensor, dict)):
        return type(batch)(to_device(v, device) for v in batch)
    return batch


def prepare_batch(
    batch: Any,
    layers: BodyLayers,
    img_res: int,
    device: Any,
    max_dist: float = math.inf,
    field: Literal["both", "hands"] = "hands",
) -> tuple[dict, dict, dict]:
    """A collated ``(inputs, targets, meta_info)`` batch on ``device`` with its targets
    prepared (ARCTIC's target preparation, no gradients). The defaults are ArcticNet-SF's
    (unclamped hand-to-object distances only, what
    :func:`~hogsa_loader.baselines.loss.arcticnet_sf_loss` reads); InterField-SF takes
    ``max_dist=0.1, field="both"`` (see :func:`~hogsa_loader.baselines.targets.prepare_targets`)."""
    inputs, targets, meta_info = to_device(batch, device)
    with torch.no_grad():
        targets, meta_info = prepare_targets(
            dict(targets),
            dict(meta_info),
            layers.mano_r,
            layers.mano_l,
            layers.objects,
            img_res=img_res,
            max_dist=max_dist,
            field=field,
        )
    return inputs, targets, meta_info


@torch.no_grad()
def mean_cameras(batches: Iterable[Any], layers: BodyLayers, img_res: int, device: Any = "cpu") -> dict[str, Tensor]:
    """Mean target weak-perspective cameras of some batches (a prior for
    :meth:`~hogsa_loader.baselines.arcticnet_sf.ArcticNetSF.init_cameras`).

    Args:
        batches: collated ``(inputs, targets, meta_info)`` batches.
        layers: the layers the targets are prepared with.
        img_res: patch side (px) of the samples.
        device: where the targets are prepared.

    Returns:
        ``{"r": (3,), "l": (3,), "o": (3,)}`` mean ``(s, tx, ty)`` over the frames where
        that hand (``right_valid`` / ``left_valid``) or the object (``is_valid``) is valid.

    Raises:
        ValueError: no valid frame of a hand or the object among the batches.
    """
    keys = {
        "r": ("mano.cam_t.wp.r", "right_valid"),
        "l": ("mano.cam_t.wp.l", "left_valid"),
        "o": ("object.cam_t.wp", "is_valid"),
    }
    sums = {k: torch.zeros(3, dtype=torch.float64) for k in keys}
    counts = dict.fromkeys(keys, 0)
    for batch in batches:
        _, targets, _ = prepare_batch(batch, layers, img_res, device)
        for k, (cam, valid) in keys.items():
            ok = targets[valid].reshape(-1).bool()
            sums[k] += targets[cam][ok].double().sum(0).cpu()
            counts[k] += int(ok.sum())
    empty = [k for k, n in counts.items() if n == 0]
    if empty:
        raise ValueError(f"mean_cameras: no valid frame for {empty} in the given batches")
    return {k: (sums[k] / counts[k]).float() for k in keys}


def training_step(
    model: nn.Module,
    batch: Any,
    layers: BodyLayers,
    optimizer: torch.optim.Optimizer,
    img_res: int,
    grad_clip: float = 150.0,
    device: Any = "cpu",
) -> dict[str, float]:
    """One step of ArcticNet-SF training.

    Args:
        model: :class:`~hogsa_loader.baselines.arcticnet_sf.ArcticNetSF` (put in train mode).
        batch: collated ``(inputs, targets, meta_info)``.
        layers: the layers the targets are prepared with.
        optimizer: the optimiser of ``model``'s parameters.
        img_res: patch side (px) of the samples.
        grad_clip: gradient-norm clip (ARCTIC: 150).
        device: where the step runs.

    Returns:
        ``{loss key: value}`` of the weighted terms and the total ``loss``.

    Raises:
        FloatingPointError: the loss is not finite (the step is not applied).
    """
    model.train()
    inputs, targets, meta_info = prepare_batch(batch, layers, img_res, device)
    return apply_losses(arcticnet_sf_loss(model(inputs, meta_info), targets), model, optimizer, grad_clip)


def apply_losses(
    losses: Mapping[str, Tensor], model: nn.Module, optimizer: torch.optim.Optimizer, grad_clip: float
) -> dict[str, float]:
    """Back-propagate ``losses["loss"]``, clip the gradient norm (0 = no clip) and step.

    Returns:
        ``{loss key: value}`` of every term.

    Raises:
        FloatingPointError: the loss is not finite (the step is not applied).
    """
    if not torch.isfinite(losses["loss"]):
        bad = [k for k, v in losses.items() if not torch.isfinite(v).all()]
        raise FloatingPointError(f"non-finite loss terms: {bad}")
    optimizer.zero_grad(set_to_none=True)
    losses["loss"].backward()
    if grad_clip and grad_clip > 0:
        torch.nn.utils.clip_grad_norm_(model.parameters(), grad_clip)
    optimizer.step()
    return {k: float(v.detach()) for k, v in losses.items()}


def temporal_order(imgnames: Iterable[str]) -> list[int]:
    """Indices of ``imgnames`` sorted by (subject, sequence, view, frame)."""
    keys = [parse_imgname(n) for n in imgnames]
    return sorted(range(len(keys)), key=lambda i: keys[i])


def _sequence_entries(
    pred: Mapping[str, Tensor], targets: Mapping[str, Tensor], meta_info: Mapping[str, Any]
) -> list[dict[str, Any]]:
    """What :func:`sequence_metrics` needs of each frame of a batch (moved to the CPU once per
    batch, predictions as float32), the object vertices trimmed to the frame's own count
    (batches pad them to their longest object)."""
    v_len = torch.as_tensor(targets.get("object.v_len", meta_info.get("object.v_len"))).reshape(-1).cpu()
    p = {k: pred[k].detach().float().cpu() for k in SEQUENCE_KEYS}
    t = {k: targets[k].detach().cpu() for k in SEQUENCE_KEYS + _TARGET_ONLY if k in targets}
    part_ids = torch.as_tensor(meta_info["part_ids"]).cpu()
    entries = []
    for b, n in enumerate(v_len.tolist()):
        pb, tb = {k: v[b] for k, v in p.items()}, {k: v[b] for k, v in t.items()}
        pb["object.v.cam"], tb["object.v.cam"] = pb["object.v.cam"][:n], tb["object.v.cam"][:n]
        tb["object.v_len"] = torch.tensor(n)
        entries.append({"pred": pb, "targets": tb, "part_ids": part_ids[b, :n]})
    return entries


def _sequence_figures(entries: list[dict[str, Any]]) -> dict[str, np.ndarray]:
    """:func:`sequence_metrics` of one clip's entries (in frame order)."""
    pred = {k: torch.stack([e["pred"][k] for e in entries]) for k in entries[0]["pred"]}
    targets = {k: torch.stack([e["targets"][k] for e in entries]) for k in entries[0]["targets"]}
    meta = {"part_ids": torch.stack([e["part_ids"] for e in entries])}
    return sequence_metrics(pred, targets, meta)


@torch.no_grad()
def evaluate_split(
    model: nn.Module,
    batches: Iterable[Any],
    prepare: Callable[[Any], tuple[dict, dict, dict]],
    frame_metrics: Callable[[dict, dict, dict], dict[str, np.ndarray]],
    clip_entries: Callable[[dict, dict, dict], list[Any]],
    clip_metrics: Callable[[list[Any]], dict[str, np.ndarray]],
    temporal: bool = True,
    keys: Optional[Iterable[str]] = None,
    on_batch: Optional[Callable[[int], None]] = None,
) -> dict[str, Any]:
    """The evaluation loop of the baselines, with what a model is scored on passed in.

    Each batch is prepared (``prepare(batch)`` -> ``(inputs, targets, meta_info)``), the model
    runs on it and ``frame_metrics(pred, targets, meta_info)`` gives its per-frame arrays. When
    ``temporal``, ``clip_entries(pred, targets, meta_info)`` gives one entry per frame, the
    entries of each (subject, sequence, view) clip are gathered across batches, and
    ``clip_metrics(entries)`` scores each clip with its entries in frame order.

    Args:
        model: the model (put in eval mode here).
        batches: collated batches of the split, the frames of a clip in consecutive batches
            (e.g. a DataLoader over :func:`temporal_order`) when ``temporal``.
        prepare: batch -> ``(inputs, targets, meta_info)`` on the model's device.
        frame_metrics: per-frame figures of a batch, ``{metric: (B,) array}``.
        clip_entries: what ``clip_metrics`` needs of each frame of a batch.
        clip_metrics: a clip's figures, ``{metric: array}``.
        temporal: also score each clip.
        keys: the metrics of the summary; default every key seen.
        on_batch: called with the number of frames after each batch (progress).

    Returns:
        ``{"summary": {metric: value}, "frames": n, "per_frame": {metric: (n,) array},
        "imgnames": [...]}``; the summary is :func:`summarize` over the frames and clips.
    """
    model.eval()
    per_frame: list[dict[str, np.ndarray]] = []
    per_clip: list[dict[str, np.ndarray]] = []
    names: list[str] = []
    current: Optional[tuple[str, str, int]] = None
    frames: list[tuple[int, Any]] = []

    def flush() -> None:
        frames.sort(key=lambda x: x[0])
        per_clip.append(clip_metrics([e for _, e in frames]))
        frames.clear()

    for batch in batches:
        inputs, targets, meta_info = prepare(batch)
        pred = model(inputs, meta_info)
        per_frame.append(frame_metrics(pred, targets, meta_info))
        batch_names = list(meta_info["imgname"])
        names += batch_names
        if temporal:
            for name, entry in zip(batch_names, clip_entries(pred, targets, meta_info)):
                sid, seq, view, frame = parse_imgname(name)
                if (sid, seq, view) != current and frames:
                    flush()
                current = (sid, seq, view)
                frames.append((frame, entry))
        if on_batch is not None:
            on_batch(len(batch_names))
    if frames:
        flush()
    merged = {k: np.concatenate([p[k] for p in per_frame]) for k in per_frame[0]} if per_frame else {}
    summary = summarize(per_frame + per_clip, keys)
    return {"summary": summary, "frames": len(names), "per_frame": merged, "imgnames": names}


def evaluate(
    model: nn.Module,
    batches: Iterable[Any],
    layers: BodyLayers,
    img_res: int,
    device: Any = "cpu",
    temporal: bool = True,
    on_batch: Optional[Callable[[int], None]] = None,
) -> dict[str, Any]:
    """ARCTIC's metrics of ``model`` over a split.

    Args:
        model: the model (put in eval mode here).
        batches: collated batches of the split, frames of a (subject, sequence, view) in
            consecutive batches (e.g. a DataLoader over :func:`temporal_order`) when
            ``temporal``.
        layers: the layers the targets are prepared with.
        img_res: patch side (px).
        device: where the model runs.
        temporal: also compute MDev and ACC per (subject, sequence, view).
        on_batch: called with the number of frames after each batch (progress).

    Returns:
        ``{"summary": {metric: value}, "frames": n, "per_frame": {metric: (n,) array},
        "imgnames": [...]}``.
    """
    return evaluate_split(
        model,
        batches,
        lambda batch: prepare_batch(batch, layers, img_res, device),
        per_frame_metrics,
        _sequence_entries,
        _sequence_figures,
        temporal=temporal,
        on_batch=on_batch,
    )
