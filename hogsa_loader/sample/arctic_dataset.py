"""``ArcticDataset``: ArcticNet-SF's training/validation dataset over processed ARCTIC splits.

Equivalent of ``zc-alexfan/arctic`` ``src/datasets/arctic_dataset.py``, built on the shared
sample builder :func:`~hogsa_loader.sample.targets.make_arctic_sample`; the deliberate
differences from ARCTIC are listed on :class:`ArcticDataset`.
"""

from __future__ import annotations

import logging
import random
from dataclasses import replace
from pathlib import Path
from typing import Any, Mapping, Optional, Union

import cv2
import numpy as np
from torch.utils.data import Dataset

from hogsa_loader.assets.arctic import ArcticRoot, canonical_split
from hogsa_loader.assets.conventions import EGO_VIEW, cropped_bbox, full_to_cropped
from hogsa_loader.errors import AssetError, PathLike
from hogsa_loader.io.images import read_image
from hogsa_loader.sample.augment import ArcticConfig, AugParams, patch_intrinsics, sample_aug_params
from hogsa_loader.sample.interfield import interfield_targets
from hogsa_loader.sample.targets import HandLabels, ObjectLabels, make_arctic_sample

__all__ = ["ArcticDataset", "SUBSAMPLE_COUNTS", "parse_imgname", "rewrite_imgname", "subsample_imgnames"]

log = logging.getLogger(__name__)

#: Images kept by the sub-sampled split names (ARCTIC's ``get_num_images``).
SUBSAMPLE_COUNTS: dict[str, int] = {
    "smalltrain": 100000,
    "tinytrain": 12000,
    "minitrain": 300,
    "smallval": 12000,
    "tinyval": 500,
    "minival": 80,
    "smalltest": 12000,
    "tinytest": 6000,
    "minitest": 200,
}
_FULL_SPLITS = ("train", "val", "test")


def subsample_imgnames(imgnames: list[str], split: str) -> list[str]:
    """ARCTIC's ``downsample``: random subset of a sub-sampled split.

    Args:
        imgnames: all image names of the full split, in file order.
        split: split name without the protocol, e.g. ``"minitrain"`` or ``"val"``.

    Returns:
        ``imgnames`` unchanged for ``train/val/test``; otherwise
        ``random.sample(imgnames, count)`` after ``random.seed(1)`` and one
        ``randint(0, 100)`` (ARCTIC's sanity draw), with ``count`` from
        :data:`SUBSAMPLE_COUNTS` capped at ``len(imgnames)``.
    """
    if not any(p in split for p in ("mini", "tiny", "small")):
        if split not in _FULL_SPLITS:
            raise ValueError(f"unknown split {split!r}")
        return list(imgnames)
    if split not in SUBSAMPLE_COUNTS:
        raise ValueError(f"unknown split {split!r}; known: {sorted(SUBSAMPLE_COUNTS)}")
    r = random.Random(1)
    first = r.randint(0, 100)
    if first != 17:  # pragma: no cover - would mean a different CPython RNG
        raise RuntimeError("random.seed(1) no longer reproduces ARCTIC's sub-sampling")
    return r.sample(list(imgnames), min(SUBSAMPLE_COUNTS[split], len(imgnames)))


def parse_imgname(imgname: str) -> tuple[str, str, int, int]:
    """``.../<sid>/<seq>/<view>/<frame>.jpg`` → ``(sid, seq, view, frame)``."""
    parts = imgname.replace("\\", "/").split("/")
    if len(parts) < 4:
        raise ValueError(f"not an ARCTIC image name: {imgname!r}")
    sid, seq, view, fname = parts[-4:]
    return sid, seq, int(view), int(fname.split(".")[0])


def rewrite_imgname(imgname: str, speedup: bool) -> str:
    """The ``meta_info["imgname"]`` string ARCTIC builds from a split entry.

    ``/images/`` → ``/cropped_images/`` (speed-up), then ARCTIC's root rewrite
    ``/arctic_data/`` → ``/data/arctic_data/data/`` followed by ``/data/data/`` →
    ``/data/`` (a no-op for the released ``./data/arctic_data/data/...`` names).
    """
    if speedup:
        imgname = imgname.replace("/images/", "/cropped_images/")
    return imgname.replace("/arctic_data/", "/data/arctic_data/data/").replace("/data/data/", "/data/")


class ArcticDataset(Dataset):
    """ArcticNet-SF samples of one processed ARCTIC split (torch ``Dataset``).

    Each item is ``(inputs, targets, meta_info)`` exactly as ARCTIC's ``getitem`` (types
    listed on :func:`~hogsa_loader.sample.targets.make_arctic_sample`); batches from the
    default collate match ARCTIC's.

    Differences from ARCTIC, all deliberate:

    * **Randomness is explicit.** Sample ``i`` of epoch ``e`` draws its augmentation from
      ``numpy.random.default_rng([seed, e, i])``, so a seed fixes every sample, whatever the
      DataLoader worker count or order. Call :meth:`ArcticDataset.set_epoch` before each
      epoch (with ``persistent_workers=True`` the workers keep the epoch they were started
      with — recreate the iterator instead).
    * **Egocentric K cache.** ARCTIC caches the first egocentric patch K it computes in
      each dataset object (hence per DataLoader worker, in whatever order that worker
      happens to see samples) and reuses it for every later egocentric sample. With
      ``cache_ego_k=True`` (default) this dataset does the same but fixes "first" to the
      first egocentric image **in split order**, computed once at construction, so the result
      does not depend on workers or shuffling. It equals ARCTIC's value whenever all ego K
      in the split agree (the egocentric K is rescaled with ``sc = 1`` only, so only the
      per-sequence full-image K matters) and for a single-process, unshuffled pass.
    * **Missing images.** Like ARCTIC an unreadable image is replaced by a zero image with
      a warning; in addition each occurrence is counted in :attr:`ArcticDataset.missing_images`
      (and the path recorded in :attr:`ArcticDataset.missing_image_paths`). The counters
      live in the process that loaded the sample (DataLoader workers have their own copies).
    * **Sub-sampled splits.** ``mini/tiny/small`` splits take ARCTIC's counts and its
      ``random.seed(1)`` draw (one ``randint(0, 100)`` then ``random.sample``), using a
      private ``random.Random`` so global state is untouched. When the split has fewer
      images than the count (possible on small generated worlds, where ARCTIC would raise),
      all images are taken in that random order.
    * Negative GT indices (``frame < ioi_offset``) raise an :class:`AssetError` instead of
      wrapping around.

    Args:
        data_root: ARCTIC's ``./data`` folder (holding ``arctic_data/data`` with
            ``splits/``, ``meta/``, ``images/``, ``cropped_images/``), or
            ``arctic_data/data`` itself (see :class:`~hogsa_loader.assets.arctic.ArcticRoot`).
        split: ``"<setup>_<split>"``, e.g. ``"p1_train"``, ``"p2_val"``,
            ``"p1_minitrain"``; the file read is ``splits/<setup>_<train|val|test>.npy``.
        augment: augment the samples; None = ARCTIC's rule (split ends with ``train``
            and no single sequence requested).
        seed: base seed of the per-sample generators.
        use_gt_k: patch intrinsics from the GT K (see
            :func:`~hogsa_loader.sample.augment.patch_intrinsics`); egocentric always uses it.
        speedup: read ``cropped_images`` (2D and box moved into cropped pixels).
        seq: only the images of this sequence name (e.g. ``"box_use_01"``).
        cache_ego_k: replicate ARCTIC's egocentric K cache (see above).
        config: sample settings; ``use_gt_k`` and ``ego_image_scale`` are overridden by
            the argument and by the dataset's ``world_meta()`` respectively.
        epoch: initial epoch (see :meth:`set_epoch`).
        interfield: add InterField-SF's interaction-field targets (``dist.*``, ``idx.*``,
            ``object.v_len``) computed from the frame's annotated meshes
            (:mod:`~hogsa_loader.sample.interfield`): False (default), True (no clamp) or
            the clamp in metres (0.1 for InterField-SF).
        arctic_sizes: refuse (:class:`~hogsa_loader.errors.AssetError`) a world whose image
            files are not ARCTIC's sizes (:meth:`~hogsa_loader.assets.arctic.ArcticRoot.require_arctic_sizes`),
            for samples that must equal ARCTIC's own loader's on the same files. Otherwise
            the sizes come from ``world_meta()`` (the ``tiny`` world's 256-px crops work).

    Attributes:
        root: the :class:`~hogsa_loader.assets.arctic.ArcticRoot` read from.
        imgnames: the (sub-sampled) image names.
        missing_images: number of unreadable images replaced by zeros in this process.
        missing_image_paths: their paths.
        cropped_size: side of the allocentric cropped images (``world_meta()``).
        ego_patch_k: the cached egocentric patch K, or None.
        interfield: the ``interfield`` setting (False, True or the clamp).
    """

    def __init__(
        self,
        data_root: PathLike,
        split: str = "p1_train",
        augment: Optional[bool] = None,
        seed: int = 1,
        use_gt_k: bool = False,
        speedup: bool = True,
        seq: Optional[str] = None,
        cache_ego_k: bool = True,
        config: Optional[ArcticConfig] = None,
        epoch: int = 0,
        interfield: Union[bool, float] = False,
        arctic_sizes: bool = False,
    ) -> None:
        if "_" not in split:
            raise ValueError(f"split must look like 'p1_train', got {split!r}")
        self.setup, self.split = split.split("_", 1)
        short = canonical_split(self.split)
        self.root = ArcticRoot(data_root)
        if arctic_sizes:
            self.root.require_arctic_sizes()
        data = self.root.load_split(self.setup, short)
        self.data: Mapping[str, Any] = data["data_dict"]
        imgnames = [str(n) for n in data["imgnames"]]
        if seq is not None:
            imgnames = [n for n in imgnames if f"/{seq}/" in n]
        if len(set(imgnames)) != len(imgnames):
            raise AssetError(self.root.split_path(self.setup, short), "duplicate image names")
        self.imgnames: list[str] = subsample_imgnames(imgnames, self.split)

        meta = self.root.world_meta()
        self.cropped_size = int(meta.cropped_size)
        base = config if config is not None else ArcticConfig()
        self.cfg = replace(base, use_gt_k=bool(use_gt_k), ego_image_scale=float(meta.ego_image_scale))
        self.augment = (self.split.endswith("train") and seq is None) if augment is None else bool(augment)
        self.seed = int(seed)
        self.epoch = int(epoch)
        self.speedup = bool(speedup)
        self.kp_bottom = {
            name: np.asarray(t.kp_bottom, dtype=np.float32)
            for name, t in self.root.object_templates(load_texture=False).items()
        }
        self.missing_images = 0
        self.missing_image_paths: list[str] = []
        self.ego_patch_k: Optional[np.ndarray] = None
        self.interfield = interfield
        self._interfield = interfield_targets(self.root, interfield)
        if cache_ego_k:
            for name in self.imgnames:
                if parse_imgname(name)[2] == EGO_VIEW:
                    self.ego_patch_k = self._ego_k(name)
                    break

    # ----------------------------------------------------------------------------------

    def __len__(self) -> int:
        return len(self.imgnames)

    def set_epoch(self, epoch: int) -> None:
        """Select the epoch whose augmentation the next items use."""
        self.epoch = int(epoch)

    def rng(self, index: int) -> np.random.Generator:
        """The generator of item ``index`` in the current epoch."""
        return np.random.default_rng([self.seed, self.epoch, int(index)])

    def aug_params(self, index: int) -> AugParams:
        """The augmentation item ``index`` gets in the current epoch (identity when off)."""
        ego = parse_imgname(self.imgnames[index])[2] == EGO_VIEW
        return sample_aug_params(self.rng(index), self.augment, ego, self.cfg)

    def image_path(self, imgname: str) -> Path:
        """File read for a split image name (``cropped_images`` with speed-up)."""
        sid, seq, view, frame = parse_imgname(imgname)
        return self.root.image_path(sid, seq, view, frame, cropped=self.speedup)

    def mask_path(self, imgname: str) -> Path:
        """The ``masks/`` file of a split image name (generated worlds only)."""
        sid, seq, view, frame = parse_imgname(imgname)
        return self.root.mask_path(sid, seq, view, frame)

    def _locate(self, imgname: str) -> tuple[str, str, int, int, Mapping[str, Any]]:
        sid, seq, view, frame = parse_imgname(imgname)
        key = f"{sid}/{seq}"
        if key not in self.data:
            raise AssetError(self.root.arctic_dir / "splits", f"{imgname}: sequence {key} not in split")
        seq_data = self.data[key]
        vidx = frame - int(self.root.subject_misc(sid).ioi_offset)
        num = seq_data["2d"]["joints.right"].shape[0]
        if not 0 <= vidx < num:
            raise AssetError(self.root.arctic_dir / "splits", f"{imgname}: GT index {vidx} outside [0, {num}) of {key}")
        return sid, seq, view, vidx, seq_data

    def _full_k(self, sid: str, view: int, vidx: int, seq_data: Mapping[str, Any]) -> np.ndarray:
        if view == EGO_VIEW:
            return np.array(seq_data["params"]["K_ego"][vidx], dtype=np.float64)
        return np.array(self.root.subject_misc(sid).intris_mat[view - 1], dtype=np.float64)

    def _ego_k(self, imgname: str) -> np.ndarray:
        sid, _, view, vidx, seq_data = self._locate(imgname)
        size = self.root.subject_misc(sid).image_size[view]
        return patch_intrinsics(self._full_k(sid, view, vidx, seq_data), size, 1.0, True, self.cfg)

    def _read_image(self, path: Path) -> Optional[np.ndarray]:
        try:  # missing, truncated, oversized or undecodable: counted as missing, like ARCTIC's loader
            img = read_image(path, cv2.IMREAD_COLOR)
        except AssetError as exc:
            img = None
            log.warning("Unable to load %s (%s); using a zero image", path, exc.problem)
        if img is None:
            self.missing_images += 1
            self.missing_image_paths.append(str(path))
            return None
        return cv2.cvtColor(img, cv2.COLOR_BGR2RGB)

    def expected_image_size(self, sid: str, view: int) -> tuple[int, int]:
        """(width, height) of the file read for ``view``: the cropped side, the ego
        image × ``ego_image_scale``, or without speed-up the full image."""
        w, h = (int(v) for v in self.root.subject_misc(sid).image_size[view])
        if not self.speedup:
            return w, h
        if view == EGO_VIEW:
            return int(round(w * self.cfg.ego_image_scale)), int(round(h * self.cfg.ego_image_scale))
        return self.cropped_size, self.cropped_size

    def _check_image_size(self, image: np.ndarray, path: Path, sid: str, view: int) -> None:
        w, h = self.expected_image_size(sid, view)
        if abs(image.shape[1] - w) > 1 or abs(image.shape[0] - h) > 1:  # (1 px: resize rounding)
            raise AssetError(
                path,
                f"image is {image.shape[1]}x{image.shape[0]} px, but its labels are in "
                f"{w}x{h} px ({'cropped_images' if self.speedup else 'images'}, view {view})",
            )

    def to_image_pixels(self, points2d: np.ndarray, bbox_full: np.ndarray, view: int) -> np.ndarray:
        """Full-resolution 2D points → pixels of the image that is read.

        Allocentric cropped images show the box enlarged 1.5× resized to the cropped side;
        egocentric ones the whole frame × ``ego_image_scale``.
        """
        if not self.speedup:
            return np.asarray(points2d, dtype=np.float64)
        if view == EGO_VIEW:
            return np.asarray(points2d, dtype=np.float64) * self.cfg.ego_image_scale
        return full_to_cropped(np.asarray(points2d, dtype=np.float64), bbox_full, self.cropped_size)

    def image_bbox(self, bbox_full: np.ndarray, view: int) -> np.ndarray:
        """The crop box in pixels of the image that is read (see :meth:`to_image_pixels`)."""
        bbox_full = np.asarray(bbox_full, dtype=np.float64)
        if not self.speedup:
            return bbox_full
        if view == EGO_VIEW:
            return bbox_full * self.cfg.ego_image_scale
        return cropped_bbox(bbox_full, self.cropped_size)

    def __getitem__(self, index: int) -> tuple[dict[str, Any], dict[str, Any], dict[str, Any]]:
        return self.getitem(int(index))

    def getitem(self, index: int, load_rgb: bool = True) -> tuple[dict[str, Any], dict[str, Any], dict[str, Any]]:
        """Item ``index`` (negative counts from the end). ``load_rgb=False`` skips
        reading the file (zero image).

        Raises:
            IndexError: ``index`` out of range.
            AssetError: the image file's size is not the one its labels are in.
        """
        n = len(self.imgnames)
        if not -n <= index < n:
            raise IndexError(f"index {index} out of range for {n} items")
        index %= n
        imgname = self.imgnames[index]
        sid, seq, view, vidx, seq_data = self._locate(imgname)
        cam, d2, params = seq_data["cam_coord"], seq_data["2d"], seq_data["params"]
        ego = view == EGO_VIEW
        bbox_full = np.asarray(seq_data["bbox"][vidx, view], dtype=np.float64)

        def px(key: str) -> np.ndarray:
            return self.to_image_pixels(d2[key][vidx, view], bbox_full, view)

        def hand(side: str, s: str) -> HandLabels:
            pose48 = np.concatenate(
                [
                    np.asarray(cam[f"rot_{s}_cam"][vidx, view], dtype=np.float32),
                    np.asarray(params[f"pose_{s}"][vidx], dtype=np.float32),
                ]
            )
            return HandLabels(
                pose48=pose48,
                betas=np.asarray(params[f"shape_{s}"][vidx]),
                j3d_full=np.asarray(cam[f"joints.{side}"][vidx, view]),
                j2d=px(f"joints.{side}"),
                valid=float(cam[f"{side}_valid"][vidx, view]),
            )

        obj_name = seq.split("_")[0]
        if obj_name not in self.kp_bottom:
            raise AssetError(self.root.meta_dir / "object_vtemplates", f"no object template for {obj_name!r}")
        obj = ObjectLabels(
            name=obj_name,
            radian=float(params["obj_arti"][vidx]),
            kp3d_full=np.asarray(cam["kp3d"][vidx, view]),
            bbox3d_full=np.asarray(cam["bbox3d"][vidx, view]),
            kp2d=px("kp3d"),
            bbox2d=px("bbox3d"),
            valid=float(cam["is_valid"][vidx, view]),
            kp_bottom_cano=self.kp_bottom[obj_name],
        )
        path = self.image_path(imgname)
        image = self._read_image(path) if load_rgb else None
        if image is not None:
            self._check_image_size(image, path, sid, view)
        aug = self.aug_params(index)
        sample = make_arctic_sample(
            image=image,
            bbox=self.image_bbox(bbox_full, view),
            K_full=self._full_k(sid, view, vidx, seq_data),
            image_size=tuple(int(v) for v in self.root.subject_misc(sid).image_size[view]),
            right=hand("right", "r"),
            left=hand("left", "l"),
            obj=obj,
            egocentric=ego,
            dist=np.asarray(params["dist"][vidx]),
            aug=aug,
            imgname=rewrite_imgname(imgname, self.speedup),
            query_name=obj_name,
            cfg=self.cfg,
            ego_patch_k=self.ego_patch_k,
        )
        if self._interfield is not None:
            sample[1].update(self._interfield(self._world_poses(params, vidx), [obj_name])[0])
        return sample

    @staticmethod
    def _world_poses(params: Mapping[str, Any], vidx: int) -> dict[str, np.ndarray]:
        """World-frame MANO and object parameters of GT frame ``vidx`` (object translation in m)."""
        out = {}
        for side, s in (("right", "r"), ("left", "l")):
            for key, src in (("rot", "rot"), ("pose", "pose"), ("trans", "trans"), ("betas", "shape")):
                out[f"{side}_{key}"] = np.asarray(params[f"{src}_{s}"][vidx : vidx + 1], dtype=np.float64)
        out["obj_arti"] = np.asarray(params["obj_arti"][vidx : vidx + 1], dtype=np.float64).reshape(1, 1)
        out["obj_rot"] = np.asarray(params["obj_rot"][vidx : vidx + 1], dtype=np.float64)
        out["obj_trans"] = np.asarray(params["obj_trans"][vidx : vidx + 1], dtype=np.float64) / 1000.0
        return out
