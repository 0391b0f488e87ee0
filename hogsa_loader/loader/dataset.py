"""``HOGSADataset``: an endless stream of synthetic ArcticNet-SF samples (torch IterableDataset).

Each item is ``(inputs, targets, meta_info)`` with exactly the keys, shapes, dtypes and
python types of :class:`~hogsa_loader.datasets.arctic_dataset.ArcticDataset` items (both
go through :func:`~hogsa_loader.datasets.sample.make_arctic_sample`), so the default
collate batches them identically and they can be mixed with real samples
(:class:`~hogsa_loader.loader.mixing.MixedLoader`). Synthetic samples are marked by their
``meta_info["imgname"]`` (``./hogsa_synth/<sid>/<obj>_synth_s<seed>e<epoch>/<view>/<index>.jpg``,
see :func:`~hogsa_loader.loader.synth.parse_synthetic_imgname`), which carries the seed,
epoch and global index that reproduce the sample (:meth:`HOGSADataset.sample`).

Determinism and sharding
    The global sample index space is cut into render batches of ``batch_size``
    consecutive indices; batch ``g`` renders one (subject, object) model: the batches
    form blocks of ``len(keys)``, each block uses every model once in an order drawn from
    ``(seed, epoch, g // len(keys))`` (:meth:`HOGSADataset.batch_key`), and every random
    draw of sample ``i`` (pose, camera, background, augmentation) comes from
    ``(seed, epoch, i)``. Batches are dealt round-robin over
    ``world_size × num_workers`` shards (torch.distributed rank, then DataLoader worker),
    so the same seed gives the same samples for the same world size and worker count
    (and the same *set* of samples for any of them). Dropped samples leave a gap.

    The epoch (:meth:`HOGSADataset.set_epoch`) lives in shared memory, so DataLoader
    workers see it even when they persist across epochs (``persistent_workers=True``);
    an iterator reads it once when it starts and keeps it to its end (a ``set_epoch``
    during an iteration applies to the next one). With torch.distributed, shards of one
    rank can hold up to one render batch more than another's (plus their own dropped
    samples): for a fixed number of steps per epoch, iterate an endless dataset (e.g.
    through :class:`~hogsa_loader.loader.mixing.MixedLoader`) rather than a finite one.

Recommended DataLoader settings
    * CPU rendering: ``DataLoader(ds, batch_size=B, num_workers=k, persistent_workers=True)``
      with ``device="cpu"``; each worker renders its own batches (set
      ``torch.set_num_threads(1)`` in ``worker_init_fn`` when k ≥ cores).
    * GPU rendering: ``device="cuda"`` and ``num_workers=0`` — rendering happens batched in
      the main process (``batch_size`` of the dataset = the render batch, e.g. 64).
      DataLoader workers must **never** touch CUDA (forked processes and CUDA do not mix);
      iterating a ``device="cuda"`` dataset inside a worker raises ``RuntimeError``.
    * ``batch_size=None`` gives single samples (what :class:`MixedLoader` consumes).

Statistics
    :attr:`HOGSADataset.stats` (:class:`~hogsa_loader.loader.synth.SynthStats`) counts
    attempted / kept / dropped samples (by reason) and accumulates per-stage seconds
    (``pose``, ``pom``, ``render``, ``srm``, ``composite``, ``targets``) *in the process
    that iterates*. DataLoader workers add theirs to a shared-memory table as they go (one
    row per worker id), so :meth:`HOGSADataset.total_stats` in the main process gives this
    process's counts plus every worker's (per torch.distributed rank: each rank has its own
    dataset).
"""

from __future__ import annotations

import math
import os
from dataclasses import replace
from typing import Any, Iterator, Optional, Sequence, Union

import numpy as np
import torch
from torch.utils.data import IterableDataset, get_worker_info

from hogsa_loader.bundle import Bundle, load_bundle
from hogsa_loader.datasets.arctic import ArcticRoot, protocol_views
from hogsa_loader.datasets.augment import ArcticConfig, AugParams, sample_aug_params
from hogsa_loader.datasets.interfield import interfield_targets
from hogsa_loader.errors import AssetError, PathLike
from hogsa_loader.loader.cameras import CameraConfig, CameraSampler
from hogsa_loader.loader.frame import SynthFrame
from hogsa_loader.loader.poses import PoseContext, make_pose_source
from hogsa_loader.loader.views import EgoCameras
from hogsa_loader.loader.synth import (
    STREAM_AUG,
    Refiner,
    SampleChecks,
    SynthPipeline,
    SynthStats,
    frame_to_sample,
    sample_rng,
)

__all__ = ["HOGSADataset", "shard_info", "MAX_WORKER_ROWS"]

#: Rows of the shared worker-statistics table (worker ids beyond share rows modulo this).
MAX_WORKER_ROWS = 64

Sample = tuple[dict[str, Any], dict[str, Any], dict[str, Any]]


def shard_info() -> tuple[int, int]:
    """``(shard, num_shards)`` of the calling process: rank × DataLoader worker.

    ``shard = rank · num_workers + worker_id``; ``num_shards = world_size · num_workers``
    (rank 0 / world 1 without an initialised torch.distributed; worker 0 / 1 in the main
    process).
    """
    rank, world = 0, 1
    if torch.distributed.is_available() and torch.distributed.is_initialized():
        rank, world = torch.distributed.get_rank(), torch.distributed.get_world_size()
    info = get_worker_info()
    wid, nw = (info.id, info.num_workers) if info is not None else (0, 1)
    return rank * nw + wid, world * nw


class HOGSADataset(IterableDataset):
    """Synthetic ArcticNet-SF samples rendered from a bundle's HOGS models.

    Args:
        bundle: bundle folder or a loaded :class:`~hogsa_loader.bundle.Bundle` (validated
            against ``data_root``).
        data_root: the ARCTIC(-format) data root the bundle was built on (poses, cameras,
            MANO, object templates).
        coco_root: COCO root for backgrounds (pycocotools); see
            :func:`~hogsa_loader.compose.make_backgrounds`.
        coco_ann: COCO annotation file (default found under ``coco_root``).
        background_folder: a plain image folder instead of COCO.
        categories: COCO category names to draw backgrounds from.
        exclude_person: leave out COCO images showing people (their hands would be
            unlabelled hands in the training image).
        coco_image_dir: COCO image folder (default found under ``coco_root``).
        backgrounds: an explicit background source (overrides the six arguments above);
            without any, procedural backgrounds are used (with a warning). The source is
            built here, in the constructing process (a missing or malformed COCO folder
            fails now, and DataLoader workers receive the parsed image list instead of
            each parsing the annotation file).
        poses: pose source name (``"perturb"``, ``"bank"`` (pose banks of the bundle),
            ``"online"`` (POM per render batch with the bundle's ContactNet),
            see :mod:`~hogsa_loader.loader.poses`) or a pose-source object.
        pose_options: keyword arguments of the pose-source factory.
        srm: refine renders with the bundle's SRM (:func:`hogsa_loader.srm.load_srm`,
            loaded lazily in the iterating process; scale-1 models only).
        srm_tta: test-time augmentation of the SRM (``SRM.refine(tta=...)``: 1, 2, 4 or 8
            symmetric copies averaged; +0.13 dB held-out at 8 on the small world, 8× the
            SRM's cost).
        refiner: explicit ``(rgb, alpha) -> rgb`` refiner (premultiplied (B,S,S,3), alpha
            (B,S,S,1)); overrides ``srm``.
        device: where rendering runs (``"cpu"`` or ``"cuda[:i]"``); see module docstring.
        batch_size: render batch (samples per render call, one model per batch).
        seed: base seed of every random draw.
        protocol: ``"p1"`` (allocentric: novel + dataset cameras, ARCTIC crops) or ``"p2"``
            (egocentric: the subject's head camera of the pose's source frame, the whole
            frame, ARCTIC's egocentric sample rules; see :mod:`~hogsa_loader.loader.views`).
        ego_distortion: ``p2``: pass the pixels through the egocentric lens distortion as in
            ARCTIC's images (labels stay undistorted, as ARCTIC's view-0 targets); False
            renders pinhole images whose pixels match the labels exactly.
        split: split whose sequences the pose source may use.
        subjects, objects: restrict the (subject, object) models used.
        cameras: :class:`~hogsa_loader.loader.cameras.CameraConfig`.
        augment: ARCTIC training augmentation (rotation, scale, colour noise).
        num_samples: total samples per epoch (indices ``0..num_samples-1``); None = endless.
        render_size: side of the rendered crop; default ``round(1.5 · img_res)`` (the
            patch then sees the box at 1:1). ARCTIC's own cropped images are larger
            (1000 px) and are blurred (5×5, σ 8) before the warp, so real patches are
            a little sharper; set ``render_size`` to the world's cropped size for parity.
        config: :class:`~hogsa_loader.datasets.augment.ArcticConfig` (``img_res``, focal,
            factors); ``use_gt_k`` False as ArcticNet-SF's allocentric training.
        checks: :class:`~hogsa_loader.loader.synth.SampleChecks` (when samples are dropped).
        backend: renderer backend (``"auto"``, ``"torch"``, ``"gsplat"``).
        epoch: initial epoch (:meth:`set_epoch`).
        interfield: add InterField-SF's interaction-field targets (``dist.*``, ``idx.*``,
            ``object.v_len``; :mod:`~hogsa_loader.datasets.interfield`): False (default),
            True (no clamp, as ArcticNet-SF) or the clamp in metres (InterField-SF: 0.1).
            Give the real :class:`ArcticDataset` the same value so the key sets match.

    Attributes:
        bundle: the :class:`Bundle`; keys: the (subject, object) models used;
        stats: :class:`~hogsa_loader.loader.synth.SynthStats` of this process (workers':
            :meth:`worker_stats`, both: :meth:`total_stats`).
    """

    def __init__(
        self,
        bundle: Union[PathLike, Bundle],
        data_root: PathLike,
        coco_root: Optional[PathLike] = None,
        coco_ann: Optional[PathLike] = None,
        *,
        background_folder: Optional[PathLike] = None,
        categories: Optional[Sequence[str]] = None,
        exclude_person: bool = False,
        coco_image_dir: Optional[PathLike] = None,
        backgrounds: Any = None,
        poses: Any = "perturb",
        pose_options: Optional[dict[str, Any]] = None,
        srm: bool = False,
        srm_tta: int = 1,
        refiner: Optional[Refiner] = None,
        device: str = "cpu",
        batch_size: int = 8,
        seed: int = 0,
        protocol: str = "p1",
        split: str = "train",
        subjects: Optional[Sequence[str]] = None,
        objects: Optional[Sequence[str]] = None,
        cameras: Optional[CameraConfig] = None,
        augment: bool = True,
        num_samples: Optional[int] = None,
        render_size: Optional[int] = None,
        config: Optional[ArcticConfig] = None,
        checks: Optional[SampleChecks] = None,
        backend: str = "auto",
        epoch: int = 0,
        interfield: Union[bool, float] = False,
        ego_distortion: bool = True,
    ) -> None:
        super().__init__()
        if protocol not in ("p1", "p2"):
            raise ValueError(f"protocol must be 'p1' (allocentric) or 'p2' (egocentric), got {protocol!r}")
        if batch_size < 1:
            raise ValueError(f"batch_size must be >= 1, got {batch_size}")
        self.data_root = data_root
        self.bundle = bundle if isinstance(bundle, Bundle) else load_bundle(bundle, data_root=data_root)
        if isinstance(bundle, Bundle):
            self.bundle.check_data_root(data_root)
        self.root = ArcticRoot(data_root)
        meta = self.root.world_meta()
        base = config if config is not None else ArcticConfig()
        self.cfg = replace(base, ego_image_scale=float(meta.ego_image_scale))
        self.render_size = int(render_size) if render_size else int(round(1.5 * self.cfg.img_res))
        self.background_args = dict(coco_root=coco_root, coco_ann=coco_ann, folder=background_folder,
                                    categories=categories, exclude_person=exclude_person, image_dir=coco_image_dir)
        if backgrounds is None:
            from hogsa_loader.compose import make_backgrounds

            backgrounds = make_backgrounds(**self.background_args)
        self.backgrounds = backgrounds
        self.poses_spec = poses
        self.pose_options = dict(pose_options or {})
        self.srm = bool(srm)
        from hogsa_loader.srm.model import TTA_CODES

        if isinstance(srm_tta, bool) or srm_tta not in TTA_CODES:
            raise ValueError(f"srm_tta must be one of {sorted(TTA_CODES)}, got {srm_tta!r}")
        if srm_tta != 1 and (not srm or refiner is not None):
            raise ValueError("srm_tta applies to the bundle's SRM: give srm=True (and no explicit refiner)")
        self.srm_tta = int(srm_tta)
        self.refiner = refiner
        self.device = str(device)
        self.batch_size = int(batch_size)
        self.seed = int(seed)
        self._epoch = torch.zeros((), dtype=torch.int64).share_memory_()  # seen by (persistent) workers
        self.epoch = int(epoch)
        self.protocol = protocol
        self.split = split
        self.views = tuple(protocol_views(protocol))
        self.camera_config = cameras if cameras is not None else CameraConfig()
        self.augment = bool(augment)
        self.num_samples = None if num_samples is None else int(num_samples)
        self.checks = checks if checks is not None else SampleChecks()
        self.backend = backend
        self.interfield = interfield
        self.ego_distortion = bool(ego_distortion)
        keys = [k for k in self.bundle.keys
                if (subjects is None or k[0] in subjects) and (objects is None or k[1] in objects)]
        if not keys:
            raise ValueError(f"no HOGS model left for subjects={subjects} objects={objects}; bundle has {self.bundle.keys}")
        self._requested_keys = keys
        self.stats = SynthStats()
        # DataLoader workers' statistics: row = worker id (a worker adds what it counted since it last did)
        self._worker_stats = torch.zeros(MAX_WORKER_ROWS, len(SynthStats().to_vector()), dtype=torch.float64).share_memory_()
        self._published: Optional[tuple[int, np.ndarray]] = None  # (pid, stats vector already added)
        self._pipe: Optional[SynthPipeline] = None
        if self.srm and self.refiner is None and self.bundle.srm is None:
            raise ValueError(f"srm=True but bundle {self.bundle.path} has no SRM checkpoint")
        if self.srm and self.refiner is None:  # a resolution-changing SRM fails here, not in the first batch
            from hogsa_loader.srm.io import SRM_MANIFEST, read_srm_manifest

            scale = read_srm_manifest(self.bundle.srm.path)["io"].get("scale", 1)
            if scale != 1:
                raise AssetError(self.bundle.srm.path / SRM_MANIFEST,
                                 f"the SRM outputs {scale}x its input size; the loader composites at the render "
                                 "size and needs a scale-1 SRM")  # fmt: skip
        # pose source built eagerly (cheap) so bad configurations fail at construction
        self.keys = self._pose_keys(keys)

    # ------------------------------------------------------------------ setup
    def _pose_keys(self, keys: list[tuple[str, str]]) -> list[tuple[str, str]]:
        src = make_pose_source(self.poses_spec, self._pose_context(keys), self.pose_options)
        have = getattr(src, "keys", keys)
        usable = [k for k in keys if k in have]
        if not usable:
            raise ValueError(f"pose source {getattr(src, 'name', src)!r} has no poses for the bundle's models {keys} "
                             f"in {self.protocol} {self.split}")
        self._pose_source = src
        return usable

    def _pose_context(self, keys: list[tuple[str, str]]) -> PoseContext:
        return PoseContext(root=self.root, keys=keys, protocol=self.protocol, split=self.split,
                           bundle=self.bundle, device=self.device)

    def __getstate__(self) -> dict[str, Any]:
        state = dict(self.__dict__)
        state["_pipe"] = None  # rebuilt lazily in each process
        return state

    def __setstate__(self, state: dict[str, Any]) -> None:
        self.__dict__.update(state)
        for name in ("_epoch", "_worker_stats"):  # a deep copy's tensors: shared again, for its own workers
            t = self.__dict__.get(name)
            if t is not None and not t.is_shared():
                t.share_memory_()

    def _check_device(self) -> torch.device:
        dev = torch.device(self.device)
        if dev.type == "cuda" and get_worker_info() is not None:
            raise RuntimeError(
                "HOGSADataset(device='cuda') is being iterated inside a DataLoader worker process; workers must not "
                "touch CUDA (fork + CUDA breaks). Use num_workers=0 with device='cuda' (rendering is batched in the "
                "main process), or device='cpu' with DataLoader workers."
            )
        return dev

    def _pipeline(self) -> SynthPipeline:
        dev = self._check_device()
        if self._pipe is None:
            bgs = self.backgrounds
            layers = self.root.mano_layers()
            templates = self.root.object_templates()
            cams: dict[str, Any] = {}
            for sid in sorted({k[0] for k in self.keys}):
                if self.protocol == "p2":
                    cams[sid] = EgoCameras(self._sequences_of(sid))
                    continue
                misc = self.root.subject_misc(sid)
                views = [v for v in self.views if v >= 1]
                ref = np.mean([s.object.trans.mean(0) for s in self._sequences_of(sid)], axis=0)
                cams[sid] = CameraSampler(
                    misc.world2cam[[v - 1 for v in views]], misc.intris_mat[[v - 1 for v in views]],
                    misc.image_size[views], views, ref, self.camera_config,
                )  # fmt: skip
            self._pipe = SynthPipeline(
                self.root, lambda key: self.bundle.load_hogs(key, layers, templates, dev), self._pose_source, cams, bgs,
                self.render_size, device=dev, refiner=self._refiner(dev), checks=self.checks, stats=self.stats,
                backend=self.backend, seed=self.seed, epoch=self.epoch,
                interfield=interfield_targets(self.root, self.interfield), protocol=self.protocol,
                ego_distortion=self.ego_distortion,
            )  # fmt: skip
        self._pipe.stats = self.stats
        return self._pipe

    def _refiner(self, dev: torch.device) -> Optional[Refiner]:
        """The explicit refiner, else the bundle's SRM when ``srm=True`` (loaded in this process)."""
        if self.refiner is not None or not self.srm:
            return self.refiner
        from hogsa_loader.srm import load_srm

        model = load_srm(self.bundle.srm.path, device=dev)  # type: ignore[union-attr]

        def refine(rgb: torch.Tensor, alpha: torch.Tensor) -> torch.Tensor:
            out = model.refine(rgb, alpha, tta=self.srm_tta)
            if out.shape != rgb.shape:
                raise ValueError(f"the bundle's SRM changes the image size {tuple(rgb.shape)} -> {tuple(out.shape)}; "
                                 "the loader composites at the render size (use a scale-1 SRM)")
            return out

        return refine

    def _sequences_of(self, sid: str) -> list[Any]:
        src = self._pose_source
        seqs = [s for (s_id, _), lst in getattr(src, "sequences", {}).items() if s_id == sid for s in lst]
        if seqs:
            return seqs
        return [self.root.sequence(sid, n.split("/", 1)[1]) for n in self.root.sequences(sid)]

    # ------------------------------------------------------------------ indices
    @property
    def epoch(self) -> int:
        """The current epoch (shared with DataLoader workers)."""
        return int(self._epoch)

    @epoch.setter
    def epoch(self, value: int) -> None:
        self._epoch.fill_(int(value))

    def set_epoch(self, epoch: int) -> None:
        """Select the epoch (a new stream of samples for the same seed). Workers, persistent
        ones included, use it from their next iteration on."""
        self.epoch = int(epoch)

    def _epoch_or(self, epoch: Optional[int]) -> int:
        return self.epoch if epoch is None else int(epoch)

    def batch_key(self, batch_index: int, epoch: Optional[int] = None) -> tuple[str, str]:
        """The (subject, object) model of render batch ``batch_index`` (at ``epoch``, default the current one).

        Balanced: the batches are taken in blocks of ``len(keys)``, and each block uses every
        model once, in an order drawn from (seed, epoch, block). So every model renders the same
        number of batches, up to one, in any stretch of the stream that starts at a block.
        """
        k = len(self.keys)
        block, slot = divmod(int(batch_index), k)
        order = np.random.default_rng([self.seed, self._epoch_or(epoch), block, 7]).permutation(k)
        return self.keys[int(order[slot])]

    def batch_indices(self, batch_index: int) -> list[int]:
        """Global sample indices of render batch ``batch_index``."""
        start = int(batch_index) * self.batch_size
        stop = start + self.batch_size
        if self.num_samples is not None:
            stop = min(stop, self.num_samples)
        return list(range(start, max(start, stop)))

    @property
    def num_batches(self) -> Optional[int]:
        """Render batches per epoch (None when endless)."""
        return None if self.num_samples is None else math.ceil(self.num_samples / self.batch_size)

    # ------------------------------------------------------------------ production
    def frames(self, batch_index: int, epoch: Optional[int] = None) -> list[Optional[SynthFrame]]:
        """The :class:`SynthFrame` s of render batch ``batch_index`` (None = dropped) at
        ``epoch`` (default the current one)."""
        ep = self._epoch_or(epoch)
        idx = self.batch_indices(batch_index)
        pipe = self._pipeline()
        pipe.epoch = ep
        self._publish_stats()
        out = pipe.frames(self.batch_key(batch_index, ep), idx)
        self._publish_stats()
        return out

    # ------------------------------------------------------------------ statistics
    def _publish_stats(self) -> None:
        """In a DataLoader worker: add what this process counted since it last did to its
        row of the shared table (the first call only records the starting point: a worker
        starts with a copy of the parent's counters)."""
        info = get_worker_info()
        if info is None:
            return
        now, pid = self.stats.to_vector(), os.getpid()
        if self._published is not None and self._published[0] == pid:
            self._worker_stats[info.id % MAX_WORKER_ROWS] += torch.from_numpy(now - self._published[1])
        self._published = (pid, now)

    def worker_stats(self) -> SynthStats:
        """Counts and seconds of this dataset's DataLoader workers so far, summed (shared memory)."""
        return SynthStats.from_vector(self._worker_stats.sum(0).numpy())

    def total_stats(self) -> SynthStats:
        """:attr:`stats` of this process plus :meth:`worker_stats`."""
        return SynthStats.from_vector(self.stats.to_vector() + self._worker_stats.sum(0).numpy())

    def aug_params(self, index: int, epoch: Optional[int] = None) -> AugParams:
        """The ARCTIC augmentation of sample ``index`` at ``epoch`` (default the current one;
        identity with ``augment=False``)."""
        ego = self.protocol == "p2"  # egocentric: ARCTIC forces sc = 1
        rng = sample_rng(self.seed, self._epoch_or(epoch), int(index), STREAM_AUG)
        return sample_aug_params(rng, self.augment, ego, self.cfg)

    def to_sample(self, frame: SynthFrame) -> Sample:
        """ARCTIC augmentation + targets of a frame (its index and epoch fix the augmentation)."""
        with self.stats.timed("targets"):
            out = frame_to_sample(frame, self.aug_params(int(frame.meta["index"]), int(frame.meta["epoch"])), self.cfg)
        self._publish_stats()
        return out

    def samples(self, batch_index: int) -> list[Sample]:
        """The kept samples of render batch ``batch_index``, in index order."""
        return [self.to_sample(f) for f in self.frames(batch_index) if f is not None]

    def sample(self, index: int, epoch: Optional[int] = None) -> Optional[Sample]:
        """Regenerate sample ``index`` alone (same seed, epoch and batch size give the same
        sample as the stream did); None if it is dropped. ``epoch``: default the current one."""
        ep = self._epoch_or(epoch)
        g = int(index) // self.batch_size
        pipe = self._pipeline()
        pipe.epoch = ep
        frame = pipe.frames(self.batch_key(g, ep), [int(index)])[0]
        return None if frame is None else self.to_sample(frame)

    def iter_frames(self) -> Iterator[SynthFrame]:
        """The kept frames of this process's shard, in order (what the offline exporter
        stores), all of the epoch current when the iteration starts."""
        shard, num = shard_info()
        ep = self.epoch
        g = shard
        while self.num_batches is None or g < self.num_batches:
            for f in self.frames(g, ep):
                if f is not None:
                    yield f
            g += num

    def __iter__(self) -> Iterator[Sample]:
        self._check_device()
        for frame in self.iter_frames():
            yield self.to_sample(frame)
