"""InterField-SF (single frame): image -> the hand↔object interaction field.

A re-implementation of ARCTIC's InterField-SF baseline: for every vertex of each hand the
distance to the nearest object vertex (``dist.ro``, ``dist.lo``), and for every object vertex
the distance to the nearest vertex of each hand (``dist.or``, ``dist.ol``), clamped to 0.1 m
by the targets. :class:`InterFieldSF` is the network, :func:`field_training_step` one
optimisation step, :func:`interfield_loss` ARCTIC's loss, :func:`field_metrics` and
:func:`field_acceleration` ARCTIC's average distance error and acceleration error, and
:func:`evaluate_field` both over a split.
"""

from __future__ import annotations

from typing import Any, Callable, Iterable, Literal, Mapping, Optional

import numpy as np
import torch
from torch import Tensor, nn

from hogsa_loader.assets.hands.mano import MANOLayer
from hogsa_loader.assets.objects.articulated import ArticulatedObjectLayer
from hogsa_loader.baselines.arcticnet_sf import read_arctic_weights
from hogsa_loader.baselines.engine import BodyLayers, apply_losses, evaluate_split, prepare_batch
from hogsa_loader.baselines.resnet import BACKBONE_CHANNELS, build_backbone, check_state_keys
from hogsa_loader.errors import AssetError, PathLike
from hogsa_loader.io.npy import read_npy

__all__ = [
    "FIELD_KEYS",
    "FIELD_LOSS_WEIGHT",
    "InterFieldSF",
    "read_mano_decimator",
    "load_field_weights",
    "interfield_loss",
    "field_metrics",
    "field_acceleration",
    "field_training_step",
    "evaluate_field",
    "FIELD_METRICS",
]

#: The split-level figures of :func:`evaluate_field`: average distance error (mm) and
#: acceleration error (m/s²), hands → object and object → hands.
FIELD_METRICS = ("avg/ho", "avg/oh", "acc/ho", "acc/oh")

#: The four distance outputs: right hand → object, left → object, object → right, object → left.
FIELD_KEYS = ("dist.ro", "dist.lo", "dist.or", "dist.ol")
#: ARCTIC's weight of each direction's loss term.
FIELD_LOSS_WEIGHT = 100.0
#: ARCTIC's weight of the terms whose target sits at the clamp (there are many; they are
#: down-weighted so the network does not fit only them).
AT_CLAMP_WEIGHT = 0.1


def read_mano_decimator(path: PathLike, num_verts: int) -> dict[str, Tensor]:
    """The hands' decimation matrices of a data root.

    Args:
        path: ``meta/mano_decimator_195.npy`` (``np.save`` of a dict with ``D_right`` and
            ``D_left``, each (S, V); read without running pickle code).
        num_verts: MANO vertex count V of the layers the matrices apply to.

    Returns:
        ``{"right": (S, V), "left": (S, V)}`` float32.

    Raises:
        AssetError: naming the file when it is missing, not such a dict, or a matrix has
            the wrong shape or non-finite entries.
    """
    data = read_npy(path)
    if not isinstance(data, dict):
        raise AssetError(path, f"expected a dict with D_right / D_left, got {type(data).__name__}")
    out: dict[str, Tensor] = {}
    for side in ("right", "left"):
        D = data.get(f"D_{side}")
        if hasattr(D, "toarray"):  # a scipy.sparse matrix
            D = D.toarray()
        if not isinstance(D, np.ndarray) or D.ndim != 2 or D.shape[1] != num_verts or D.shape[0] < 1:
            got = getattr(D, "shape", type(D).__name__)
            raise AssetError(path, f"D_{side} must be an (S, {num_verts}) matrix, got {got}")
        if not np.isfinite(D).all():
            raise AssetError(path, f"D_{side} has non-finite entries")
        out[side] = torch.from_numpy(np.asarray(D, dtype=np.float32))
    if out["right"].shape != out["left"].shape:
        raise AssetError(path, f"D_right {tuple(out['right'].shape)} and D_left {tuple(out['left'].shape)} differ")
    return out


class _PointFeatures(nn.Module):
    """PointNet features: (B, C_in, N) -> (B, out_dim + shallow_dim, N), the max-pooled
    global feature repeated per point, then each point's shallow feature."""

    def __init__(self, in_dim: int, shallow_dim: int = 512, mid_dim: int = 512, out_dim: int = 512):
        super().__init__()
        self.shallow_layer = nn.Sequential(nn.Conv1d(in_dim, shallow_dim, 1), nn.BatchNorm1d(shallow_dim))
        self.base_layer = nn.Sequential(
            nn.Conv1d(shallow_dim, mid_dim, 1),
            nn.BatchNorm1d(mid_dim),
            nn.ReLU(),
            nn.Conv1d(mid_dim, out_dim, 1),
            nn.BatchNorm1d(out_dim),
        )

    def forward(self, x: Tensor) -> Tensor:
        shallow = self.shallow_layer(x)
        glob = self.base_layer(shallow).amax(dim=2, keepdim=True)
        return torch.cat([glob.expand(-1, -1, x.shape[2]), shallow], dim=1)


class _DistanceHead(nn.Module):
    """(B, C, N) point features -> (B, N) distances."""

    def __init__(self, in_dim: int):
        super().__init__()
        self.network = nn.Sequential(
            nn.Conv1d(in_dim, 512, 1),
            nn.BatchNorm1d(512),
            nn.ReLU(),
            nn.Conv1d(512, 128, 1),
            nn.BatchNorm1d(128),
            nn.ReLU(),
            nn.Conv1d(128, 1, 1),
        )

    def forward(self, x: Tensor) -> Tensor:
        return self.network(x)[:, 0]


class _Upsampler(nn.Module):
    """(B, S) values on sub-sampled points -> (B, V) values on every vertex (one linear map)."""

    def __init__(self, in_dim: int, out_dim: int):
        super().__init__()
        self.upsampling = nn.Linear(in_dim, out_dim)

    def forward(self, x: Tensor) -> Tensor:
        return self.upsampling(x)


class InterFieldSF(nn.Module):
    """InterField-SF: image -> hand↔object nearest-vertex distances.

    Architecture (ARCTIC's):

    1. a ResNet backbone, average-pooled to one feature vector, reduced by two linear + ReLU
       layers to 512 channels;
    2. template points: each hand's decimated rest mesh (MANO at zero pose and shape, the
       decimation matrix of ``meta/mano_decimator_195.npy``, relative to the wrist joint) and
       the object's sub-sampled points (``v_sub``, 600 points, unarticulated, centred on their
       mean); every point is the 3 coordinates + the image feature;
    3. a PointNet feature network over all points of the frame (per-point shallow features
       concatenated with the max-pooled global feature);
    4. four distance heads (1×1 convolutions) on the right-hand, left-hand and object points,
       and linear up-samplers from the decimated points to every vertex: hands to the MANO
       vertex count, the object to ``object_outputs`` points.

    The module names are those of ARCTIC's ``FieldSF``, so its state dicts load with
    :func:`load_field_weights`.

    Args:
        backbone: ``"resnet18"`` or ``"resnet50"`` (ARCTIC's release: ResNet-50), randomly
            initialised; load ImageNet weights with
            :func:`~hogsa_loader.baselines.resnet.load_backbone_weights` on ``.backbone``.
        mano_r: right :class:`~hogsa_loader.assets.hands.mano.MANOLayer` (its rest mesh
            gives the right hand's template points).
        mano_l: the left one.
        object_layer: the :class:`~hogsa_loader.assets.objects.articulated.ArticulatedObjectLayer`
            holding every object of ``query_names`` (its sub-sampled points are the object
            template; its longest template is the length of ``dist.or/ol``).
        decimator: ``{"right": (S, V), "left": (S, V)}`` from :func:`read_mano_decimator`.
        object_outputs: L, the length of ``dist.or`` / ``dist.ol``: at least the object
            layer's longest template (the default); ARCTIC's released model has 4000.

    ``forward`` returns ``dist.ro``, ``dist.lo`` (B, V), ``dist.or``, ``dist.ol`` (B, L)
    in metres (entries past an object's own vertex count are padding), and ``feat_vec``
    (B, C) the pooled image feature.
    """

    def __init__(
        self,
        backbone: Literal["resnet18", "resnet50"],
        mano_r: MANOLayer,
        mano_l: MANOLayer,
        object_layer: ArticulatedObjectLayer,
        decimator: Mapping[str, Tensor],
        object_outputs: Optional[int] = None,
    ):
        super().__init__()
        self.backbone = build_backbone(backbone)
        self.backbone_name = backbone
        feat_dim = BACKBONE_CHANNELS[backbone]
        self.down = nn.Sequential(nn.Linear(feat_dim, 512), nn.ReLU(), nn.Linear(512, 512), nn.ReLU())
        self.point_backbone = _PointFeatures(3 + 512)
        self.dist_head_ro, self.dist_head_lo = _DistanceHead(1024), _DistanceHead(1024)
        self.dist_head_or, self.dist_head_ol = _DistanceHead(1024), _DistanceHead(1024)
        hands = {s: self._hand_template(m, decimator[s]) for s, m in (("right", mano_r), ("left", mano_l))}
        self.register_buffer("points_r", hands["right"], persistent=False)
        self.register_buffer("points_l", hands["left"], persistent=False)
        self.object_layer = object_layer
        v_sub = object_layer.v_sub.float()  # (K, 600, 3) at zero articulation: fixed per object
        self.register_buffer("template_o", v_sub - v_sub.mean(dim=1, keepdim=True), persistent=False)
        n_sub, n_verts = int(hands["right"].shape[0]), int(decimator["right"].shape[1])
        n_obj_sub, longest = int(object_layer.v_sub.shape[1]), int(object_layer.v_len.max())
        n_obj = longest if object_outputs is None else int(object_outputs)
        if n_obj < longest:
            raise ValueError(f"object_outputs={n_obj} is shorter than the longest object template ({longest})")
        self.upsampling_r = _Upsampler(n_sub, n_verts)
        self.upsampling_l = _Upsampler(n_sub, n_verts)
        self.upsampling_o = _Upsampler(n_obj_sub, n_obj)

    @staticmethod
    @torch.no_grad()
    def _hand_template(mano: MANOLayer, D: Tensor) -> Tensor:
        """(S, 3) decimated rest mesh (zero pose and shape) relative to the wrist joint."""
        dt = mano.v_template.dtype
        z = torch.zeros(1, 3, dtype=dt)
        out = mano(global_orient=z, hand_pose=torch.zeros(1, 45, dtype=dt), betas=torch.zeros(1, 10, dtype=dt))
        if D.shape[1] != out.vertices.shape[1]:
            raise ValueError(f"decimator has {D.shape[1]} columns, the MANO layer {out.vertices.shape[1]} vertices")
        return (D.to(dt) @ out.vertices[0] - out.joints[0, :1]).float()

    def network_state_dict(self) -> dict[str, Tensor]:
        """The learned weights only (backbone, PointNet, heads, up-samplers; no object templates)."""
        return {k: v for k, v in self.state_dict().items() if not k.startswith("object_layer.")}

    def object_points(self, names: list[str]) -> Tensor:
        """(B, 600, 3) sub-sampled object points, unarticulated and unrotated, centred on their mean."""
        return self.template_o[self.object_layer.indices(names).to(self.template_o.device)]

    def forward(self, inputs: Mapping[str, Tensor], meta_info: Mapping[str, Any]) -> dict[str, Tensor]:
        """Predict the interaction field.

        Args:
            inputs: ``img`` (B, 3, H, W) normalised patches.
            meta_info: ``query_names`` (B object names).

        Returns:
            ``dist.ro``, ``dist.lo`` (B, V); ``dist.or``, ``dist.ol`` (B, L); ``feat_vec`` (B, C).
        """
        img = inputs["img"]
        B = img.shape[0]
        names = list(meta_info["query_names"])
        if len(names) != B:
            raise ValueError(f"{len(names)} query_names for a batch of {B} images")
        feat = self.backbone(img).mean(dim=(2, 3))
        pts_o = self.object_points(names).to(img.dtype)
        pts = [self.points_r.expand(B, -1, -1), self.points_l.expand(B, -1, -1), pts_o]
        sizes = [p.shape[1] for p in pts]
        points = torch.cat(pts, dim=1).transpose(1, 2)  # (B, 3, N)
        down = self.down(feat)[:, :, None].expand(-1, -1, points.shape[2])
        f_r, f_l, f_o = torch.split(self.point_backbone(torch.cat([points, down], dim=1)), sizes, dim=2)
        return {
            "dist.ro": self.upsampling_r(self.dist_head_ro(f_r)),
            "dist.lo": self.upsampling_l(self.dist_head_lo(f_l)),
            "dist.or": self.upsampling_o(self.dist_head_or(f_o)),
            "dist.ol": self.upsampling_o(self.dist_head_ol(f_o)),
            "feat_vec": feat,
        }


def load_field_weights(model: InterFieldSF, path: PathLike, weights_only: bool = True) -> None:
    """Load whole InterField-SF weights into ``model``.

    Args:
        model: the :class:`InterFieldSF` (its backbone and layers' vertex counts must be the
            file's).
        path: a run's ``model.safetensors``, a ``torch.save`` state dict or a Lightning
            ``.ckpt`` (its ``state_dict``; the ``model.`` prefix removed, the training
            wrapper's MANO layers dropped).
        weights_only: see :func:`~hogsa_loader.baselines.resnet.read_state_dict`.

    Raises:
        AssetError: naming the file and the missing / unexpected / mis-shaped keys.
    """
    state = read_arctic_weights(path, weights_only)
    check_state_keys(path, model.network_state_dict(), state, f"an InterField-SF with a {model.backbone_name} backbone")
    model.load_state_dict(state, strict=False)


def _object_mask(v_len: Tensor, length: int) -> Tensor:
    """(B, length) 1.0 where the vertex index is below the object's own count."""
    return (torch.arange(length, device=v_len.device)[None] < v_len.reshape(-1, 1)).float()


def interfield_loss(
    pred: Mapping[str, Tensor], targets: Mapping[str, Tensor], max_dist: float = 0.1
) -> dict[str, Tensor]:
    """ARCTIC's InterField loss.

    Per direction, the squared error of every vertex's distance, zero on invalid frames
    (``is_valid``) and on object padding (``object.v_len``), times 0.1 where the target is
    at the clamp ``max_dist``; the mean over (frames, vertices) weighted by 100.

    Args:
        pred: the model's ``dist.*``; the object directions may be longer than the
            targets' (both are cut to the shorter).
        targets: ``dist.*`` clamped to ``max_dist``, ``is_valid`` (B,), ``object.v_len`` (B,).
        max_dist: the targets' clamp (m; ARCTIC: 0.1).

    Returns:
        ``loss/dist/{ro,lo,or,ol}`` weighted terms and their sum ``loss``.
    """
    valid = torch.as_tensor(targets["is_valid"]).reshape(-1, 1).float()
    out: dict[str, Tensor] = {}
    for key in FIELD_KEYS:
        gt = targets[key]
        p = pred[key]
        n = min(p.shape[1], gt.shape[1])
        p, gt = p[:, :n], gt[:, :n].to(p.dtype)
        term = (p - gt) ** 2 * valid.to(p.dtype)
        if key in ("dist.or", "dist.ol"):
            term = term * _object_mask(torch.as_tensor(targets["object.v_len"]).to(p.device), n).to(p.dtype)
        term = torch.where(gt == max_dist, term * AT_CLAMP_WEIGHT, term)
        out[f"loss/dist/{key[-2:]}"] = FIELD_LOSS_WEIGHT * term.mean()
    out["loss"] = sum(out.values())  # type: ignore[assignment]
    return out


def _per_frame_errors(pred: Mapping[str, Tensor], targets: Mapping[str, Tensor]) -> dict[str, Tensor]:
    """(B,) mean |pred - gt| per direction, object directions over the object's own vertices."""
    v_len = torch.as_tensor(targets["object.v_len"]).reshape(-1)
    out = {}
    for key in FIELD_KEYS:
        gt, p = targets[key].double(), pred[key].detach().double()
        n = min(p.shape[1], gt.shape[1])
        err = (p[:, :n] - gt[:, :n]).abs()
        if key in ("dist.or", "dist.ol"):
            mask = _object_mask(v_len.to(err.device), n).double()
            out[key] = (err * mask).sum(1) / mask.sum(1)
        else:
            out[key] = err.mean(1)
    return out


def field_metrics(pred: Mapping[str, Tensor], targets: Mapping[str, Tensor]) -> dict[str, np.ndarray]:
    """ARCTIC's average distance error per frame.

    Args:
        pred: the model's ``dist.*``.
        targets: ``dist.*`` (clamped as in training), ``is_valid`` (B,) and
            ``object.v_len`` (B,).

    Returns:
        ``avg/ho`` (hands → object: mean of the right and left errors) and ``avg/oh``
        (object → hands), each (B,) in mm, NaN on invalid frames. As in ARCTIC, a hand
        outside the image still counts: the model should then predict long distances.
    """
    err = _per_frame_errors(pred, targets)
    valid = torch.as_tensor(targets["is_valid"]).reshape(-1).bool().cpu()
    out = {}
    for name, (a, b) in (("avg/ho", ("dist.ro", "dist.lo")), ("avg/oh", ("dist.or", "dist.ol"))):
        m = (err[a] + err[b]).cpu() / 2 * 1000.0
        out[name] = torch.where(valid, m, torch.full_like(m, float("nan"))).numpy()
    return out


def field_acceleration(
    pred: Mapping[str, Tensor], targets: Mapping[str, Tensor], fps: float = 30.0
) -> dict[str, np.ndarray]:
    """ARCTIC's acceleration error of the field over one clip (frames in temporal order).

    The second difference ``(x[t-1] - 2 x[t] + x[t+1]) fps²`` of every vertex's distance,
    predicted minus ground truth, its absolute value averaged over vertices (m/s²). A frame
    counts when it and both neighbours are valid (``right_valid`` / ``left_valid`` for the
    hands, ``is_valid`` for the object, all times ``is_valid``); the first and last frames
    are NaN.

    Args:
        pred: the model's ``dist.*`` (F, ·) of the clip's F frames.
        targets: ``dist.*`` (F, ·), ``is_valid``, ``right_valid``, ``left_valid`` (F,) and
            ``object.v_len`` (F,) (one object per clip: the object directions are cut to
            its vertex count).
        fps: frame rate (ARCTIC: 30).

    Returns:
        ``acc/ho`` and ``acc/oh`` (F,) in m/s²: the mean of the two directions where both
        count, the one that counts otherwise, NaN where neither does.
    """
    n_o = int(torch.as_tensor(targets["object.v_len"]).reshape(-1)[0])
    is_valid = torch.as_tensor(targets["is_valid"]).reshape(-1).double().cpu()
    flags = {
        "r": torch.as_tensor(targets["right_valid"]).reshape(-1).double().cpu() * is_valid,
        "l": torch.as_tensor(targets["left_valid"]).reshape(-1).double().cpu() * is_valid,
        "o": is_valid,
    }
    F = is_valid.shape[0]
    acc: dict[str, Tensor] = {}
    for key in FIELD_KEYS:
        gt, p = targets[key].double().cpu(), pred[key].detach().double().cpu()
        if key in ("dist.or", "dist.ol"):
            gt, p = gt[:, :n_o], p[:, :n_o]
        nan = torch.full((F,), float("nan"), dtype=torch.float64)
        if F >= 3:
            d = p - gt
            a = ((d[:-2] - 2 * d[1:-1] + d[2:]) * fps**2).abs().mean(1)
            flag = flags[key[-2]]  # the side whose vertices the direction starts from
            ok = (flag[:-2] + flag[1:-1] + flag[2:]) == 3
            nan[1:-1] = torch.where(ok, a, torch.full_like(a, float("nan")))
        acc[key] = nan
    out = {}
    for name, (a, b) in (("acc/ho", ("dist.ro", "dist.lo")), ("acc/oh", ("dist.or", "dist.ol"))):
        both = torch.stack([acc[a], acc[b]], dim=1)
        out[name] = torch.nanmean(both, dim=1).numpy()
    return out


def field_training_step(
    model: InterFieldSF,
    batch: Any,
    layers: BodyLayers,
    optimizer: torch.optim.Optimizer,
    img_res: int,
    max_dist: float = 0.1,
    grad_clip: float = 150.0,
    device: Any = "cpu",
) -> dict[str, float]:
    """One step of InterField-SF training on a collated ``(inputs, targets, meta_info)`` batch.

    The field targets of both directions are prepared from the batch's labels (clamped to
    ``max_dist``), then the model, :func:`interfield_loss`, and Adam with gradient-norm
    clipping (ARCTIC: 150).

    Args:
        model: the :class:`InterFieldSF` (put in train mode).
        batch: real, synthetic or mixed batch.
        layers: the :class:`~hogsa_loader.baselines.engine.BodyLayers` of the targets.
        optimizer: the optimiser of ``model``'s parameters.
        img_res: patch side (px) of the samples.
        max_dist: the targets' clamp (m; ARCTIC: 0.1).
        grad_clip: gradient-norm clip; 0 = none.
        device: where the step runs.

    Returns:
        ``{loss key: value}`` of the weighted terms and the total ``loss``.

    Raises:
        FloatingPointError: the loss is not finite (the step is not applied).
    """
    model.train()
    inputs, targets, meta_info = prepare_batch(batch, layers, img_res, device, max_dist=max_dist, field="both")
    return apply_losses(interfield_loss(model(inputs, meta_info), targets, max_dist), model, optimizer, grad_clip)


_CLIP_TARGETS = ("is_valid", "right_valid", "left_valid")


def _clip_entries(pred: Mapping[str, Tensor], targets: Mapping[str, Tensor], _: Any) -> list[dict[str, Tensor]]:
    """Each frame of a batch as :func:`field_acceleration` reads it (moved to the CPU once per
    batch), the object directions cut to the frame's own vertex count (batches pad them to
    their longest object)."""
    v_len = torch.as_tensor(targets["object.v_len"]).reshape(-1).cpu()
    p = {k: pred[k].detach().float().cpu() for k in FIELD_KEYS}
    t = {k: targets[k].detach().float().cpu() for k in FIELD_KEYS}
    flags = {k: torch.as_tensor(targets[k]).reshape(-1).cpu() for k in _CLIP_TARGETS}
    entries = []
    for b, n in enumerate(v_len.tolist()):
        entry = {k: v[b] for k, v in flags.items()}
        for key in FIELD_KEYS:
            cut = n if key in ("dist.or", "dist.ol") else None
            entry["pred." + key], entry[key] = p[key][b, :cut], t[key][b, :cut]
        entry["object.v_len"] = torch.tensor(n)
        entries.append(entry)
    return entries


def _clip_acceleration(entries: list[dict[str, Tensor]]) -> dict[str, np.ndarray]:
    """:func:`field_acceleration` of one clip's entries (in frame order)."""
    stacked = {k: torch.stack([e[k] for e in entries]) for k in entries[0]}
    pred = {k: stacked.pop("pred." + k) for k in FIELD_KEYS}
    return field_acceleration(pred, stacked)


def evaluate_field(
    model: InterFieldSF,
    batches: Iterable[Any],
    layers: BodyLayers,
    img_res: int,
    device: Any = "cpu",
    temporal: bool = True,
    max_dist: float = 0.1,
    on_batch: Optional[Callable[[int], None]] = None,
) -> dict[str, Any]:
    """ARCTIC's InterField-SF figures of ``model`` over a split.

    Args:
        model: the model (put in eval mode here).
        batches: collated batches of the split, the frames of a (subject, sequence, view) in
            consecutive batches (a DataLoader over
            :func:`~hogsa_loader.baselines.engine.temporal_order`) when ``temporal``.
        layers: the layers the targets are prepared with.
        img_res: patch side (px).
        device: where the model runs.
        temporal: also compute the acceleration error per (subject, sequence, view).
        max_dist: the targets' clamp (m; ARCTIC: 0.1), as in training.
        on_batch: called with the number of frames after each batch (progress).

    Returns:
        ``{"summary": {metric: value}, "frames": n, "per_frame": {"avg/ho", "avg/oh": (n,)
        arrays}, "imgnames": [...]}``; the summary holds :data:`FIELD_METRICS` (the
        acceleration ones only when ``temporal``), each a nan-mean over the split's frames as
        ARCTIC reports them.
    """
    return evaluate_split(
        model,
        batches,
        lambda batch: prepare_batch(batch, layers, img_res, device, max_dist=max_dist, field="both"),
        lambda pred, targets, _: field_metrics(pred, targets),
        _clip_entries,
        _clip_acceleration,
        temporal=temporal,
        keys=FIELD_METRICS if temporal else FIELD_METRICS[:2],
        on_batch=on_batch,
    )
