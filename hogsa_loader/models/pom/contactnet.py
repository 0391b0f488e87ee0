"""ContactNet: per-object-point contact from an object point cloud and one hand's vertices.

:class:`ContactNet` (its docstring describes the architecture, which works for any hand
topology and object point count) with :class:`ContactNetConfig`; :func:`save_contactnet` and
:func:`load_contactnet` store it. Coordinates are expected in the object's canonical frame
(metres); they are scaled by :data:`COORD_SCALE` inside. Targets are GraspTTA's map
:func:`contact_map`.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Optional

import torch
from torch import Tensor, nn

from hogsa_loader.errors import AssetError, PathLike
from hogsa_loader.io.tensors import ManifestFormat, read_manifest, read_tensors, save_checkpoint

__all__ = [
    "ContactNetConfig",
    "ContactNet",
    "contact_map",
    "save_contactnet",
    "load_contactnet",
    "CONTACTNET_SCHEMA",
    "CONTACTNET_VERSION",
    "CONTACTNET_FORMAT",
]

#: Metres -> network units (decimetres).
COORD_SCALE = 10.0
CONTACTNET_SCHEMA = "hogsa.contactnet"
CONTACTNET_VERSION = 1
WEIGHTS_FILE = "contactnet.safetensors"
MANIFEST_FILE = "manifest.json"
#: The shared checkpoint header of a ContactNet.
CONTACTNET_FORMAT = ManifestFormat(
    CONTACTNET_SCHEMA,
    CONTACTNET_VERSION,
    "a ContactNet checkpoint",
    WEIGHTS_FILE,
    name_key="schema",
    file_key="weights",
    specs="shape",
    library_version=False,
    manifest_file=MANIFEST_FILE,
)


def contact_map(dist: Tensor) -> Tensor:
    """GraspTTA's pseudo contact map ``2 - 2 sigmoid(2 d_cm)`` (1 at contact, ~0 beyond 3 cm).

    Args:
        dist: (...) non-negative distances in metres (object point -> nearest hand vertex).

    Returns:
        (...) values in (0, 1].
    """
    return 2.0 - 2.0 * torch.sigmoid(2.0 * 100.0 * dist)


def _mlp(sizes: list[int], last_act: bool = True) -> nn.Sequential:
    layers: list[nn.Module] = []
    for i in range(len(sizes) - 1):
        layers.append(nn.Linear(sizes[i], sizes[i + 1]))
        if i < len(sizes) - 2 or last_act:
            layers.append(nn.ReLU(inplace=True))
    return nn.Sequential(*layers)


@dataclass
class ContactNetConfig:
    """Sizes of :class:`ContactNet`.

    Attributes:
        local: object local feature width; global_obj / global_hand: pooled widths;
        knn: nearest hand vertices per object point; knn_width: their feature width;
        head: hidden widths of the head;
        hand_points: at most this many hand vertices (a strided subset) feed the global hand
            feature (the nearest-vertex features always use every vertex).
    """

    local: int = 64
    global_obj: int = 128
    global_hand: int = 128
    knn: int = 8
    knn_width: int = 32
    head: tuple[int, ...] = (128, 64)
    hand_points: int = 512


class ContactNet(nn.Module):
    """Topology-free ContactNet.

    GraspTTA's ContactNet fuses the two PointNet outputs with a
    ``Conv1d(3778 -> 3000)`` over point indices, which fixes 3000 object points and 778 MANO
    vertices. This variant works for any hand topology and any object point count:

    * object branch: a shared per-point MLP (PointNet) -> local feature ``f_o`` (64) and a
      max-pooled global feature ``g_o``;
    * hand branch: a shared per-vertex MLP on (xyz, prior-contact flag, side) -> max-pooled
      global feature ``g_h`` (any vertex count; a strided subset of at most ``hand_points``);
    * nearest-hand features: for each object point its ``k`` nearest hand vertices give
      (offset, distance, GraspTTA map of the distance, prior flag) -> shared MLP -> max over
      the k neighbours -> ``f_n``;
    * head: shared MLP on ``[f_o ; g_o ; g_h ; f_n ; side]`` -> sigmoid contact in (0, 1).

    Args:
        config: :class:`ContactNetConfig` (defaults when None).
    """

    def __init__(self, config: Optional[ContactNetConfig] = None) -> None:
        super().__init__()
        c = config or ContactNetConfig()
        self.config = c
        self.obj_local = _mlp([3, 64, c.local])
        self.obj_global = _mlp([c.local, 128, c.global_obj])
        self.hand_mlp = _mlp([5, 64, 128, c.global_hand])
        self.knn_mlp = _mlp([6, 32, c.knn_width])
        width = c.local + c.global_obj + c.global_hand + c.knn_width + 1
        self.head = _mlp([width, *c.head])
        self.out = nn.Linear(c.head[-1], 1)

    def forward(self, obj_points: Tensor, hand_verts: Tensor, hand_prior: Tensor, side: Tensor) -> Tensor:
        """Predict contact.

        Args:
            obj_points: (B, N, 3) object points (canonical frame, metres), any N.
            hand_verts: (B, V, 3) hand vertices in the same frame, any V.
            hand_prior: (V,) or (B, V) bool/float prior-contact flag of each vertex.
            side: (B,) +1 right, -1 left.

        Returns:
            (B, N) contact in (0, 1).
        """
        B, N, _ = obj_points.shape
        V = hand_verts.shape[1]
        dtype = obj_points.dtype
        o = obj_points * COORD_SCALE
        h = hand_verts.to(dtype) * COORD_SCALE
        prior = hand_prior.to(dtype)
        if prior.dim() == 1:
            prior = prior[None].expand(B, V)
        s = side.to(dtype).reshape(B, 1)
        f_o = self.obj_local(o)  # (B, N, local)
        g_o = self.obj_global(f_o).max(1).values  # (B, G)
        step = max(1, -(-V // self.config.hand_points))  # strided vertex subset for the global feature
        hin = torch.cat([h[:, ::step], prior[:, ::step, None], s[:, None].expand(B, h[:, ::step].shape[1], 1)], -1)
        g_h = self.hand_mlp(hin).max(1).values  # (B, G)
        k = min(self.config.knn, V)
        with torch.no_grad():
            idx = torch.cdist(o, h).topk(k, dim=-1, largest=False).indices  # (B, N, k)
        flat = (idx + V * torch.arange(B, device=idx.device)[:, None, None]).reshape(-1)
        nb = h.reshape(B * V, 3)[flat].reshape(B, N, k, 3)
        off = nb - o[:, :, None]
        dist = off.norm(dim=-1, keepdim=True)
        pf = prior.reshape(B * V)[flat].reshape(B, N, k, 1)
        cm = contact_map(dist / COORD_SCALE)  # GraspTTA's map of each neighbour (resolves mm)
        f_n = self.knn_mlp(torch.cat([off, dist, cm, pf], -1)).max(2).values  # (B, N, knn_width)
        feat = torch.cat(
            [f_o, g_o[:, None].expand(B, N, -1), g_h[:, None].expand(B, N, -1), f_n, s[:, None].expand(B, N, 1)], -1
        )
        return torch.sigmoid(self.out(self.head(feat))[..., 0])


def save_contactnet(model: ContactNet, run_dir: PathLike, extra: Optional[dict] = None) -> Path:
    """Write ``contactnet.safetensors`` and ``manifest.json`` (with the weights' ``tensors_sha256``,
    checked by :func:`load_contactnet`) into ``run_dir``.

    Args:
        model: the network; run_dir: output folder (created); extra: more manifest keys.

    Returns:
        the manifest path.
    """
    tensors = {k: v.detach().cpu().contiguous() for k, v in model.state_dict().items()}
    cfg = asdict(model.config)
    cfg["head"] = list(cfg["head"])
    fields = {"config": cfg, "coord_scale": COORD_SCALE, **(extra or {})}
    return save_checkpoint(run_dir, CONTACTNET_FORMAT, tensors, fields, indent=2)


def load_contactnet(run_dir: PathLike, device: str | torch.device = "cpu") -> ContactNet:
    """Load a ContactNet run written by :func:`save_contactnet` (eval mode).

    Raises:
        AssetError: missing/malformed manifest or weights, wrong schema/version, shapes.
    """
    run = Path(run_dir)
    mpath = run / MANIFEST_FILE
    man = read_manifest(run, CONTACTNET_FORMAT)
    try:
        cfg = dict(man["config"])
        cfg["head"] = tuple(cfg["head"])
        model = ContactNet(ContactNetConfig(**cfg))
    except (KeyError, TypeError, ValueError) as exc:
        raise AssetError(mpath, f"bad 'config' ({exc})") from None
    wpath = run / WEIGHTS_FILE
    state = read_tensors(run, man, CONTACTNET_FORMAT)  # (listed names and shapes; finite)
    bad = [k for k, v in state.items() if not v.is_floating_point()]
    if bad:
        raise AssetError(wpath, f"tensor {bad[0]!r} is not floating point")
    try:
        model.load_state_dict(state, strict=True)
    except RuntimeError as exc:
        raise AssetError(wpath, f"weights do not match the manifest config ({str(exc).splitlines()[0]})") from None
    return model.to(device).eval()
