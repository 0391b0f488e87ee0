"""``HOGSADataset``: an endless stream of synthetic ArcticNet-SF samples (torch IterableDataset).

Each item is ``(inputs, targets, meta_info)`` with exactly the keys, shapes, dtypes and
python types of :class:`~hogsa_loader.sample.arctic_dataset.ArcticDataset` items (both
go through :func:`~hogsa_loader.sample.targets.make_arctic_sample`), so the default
collate batches them identically and they can be mixed with real samples
(:class:`~hogsa_loader.sample.mixing.MixedLoader`). Synthetic samples are marked by their
``meta_info["imgname"]`` (``./hogsa_synth/<sid>/<obj>_synth_s<seed>e<epoch>/<view>/<index>.jpg``,
see :func:`~hogsa_loader.sample.synth.parse_synthetic_imgname`), which carries the seed,
epoch and global index that reproduce the sample (:meth:`HOGSADataset.sample`).
"""

from __future__ import annotations

import math
import os
import warnings
from dataclasses import replace
from typing import Any, Iterator, Optional, Union

import numpy as np
import torch
from torch.utils.data import IterableDataset, get_worker_info

from hogsa_loader.assets.arctic import ArcticRoot, protocol_views
from hogsa_loader.assets.protocol import held_out_subjects, training_subjects
from hogsa_loader.compose import make_backgrounds
from hogsa_loader.errors import AssetError, HogsaError, PathLike
from hogsa_loader.models.bundle import Bundle, bundle_dataset, load_bundle
from hogsa_loader.models.gaussians.recombine import hands_run
from hogsa_loader.models.srm import load_srm
from hogsa_loader.models.srm.io import SRM_MANIFEST, read_srm_manifest
from hogsa_loader.sample.augment import AugParams, sample_aug_params
from hogsa_loader.sample.cameras import CameraSampler
from hogsa_loader.sample.config import LoaderConfig, SampleChecks, is_default
from hogsa_loader.sample.frame import SynthFrame
from hogsa_loader.sample.interfield import interfield_targets
from hogsa_loader.sample.plan import STREAM_AUG, BatchPlan, batch_order, hands_rng, sample_rng
from hogsa_loader.sample.poses import PoseContext, PoseSource, make_pose_source
from hogsa_loader.sample.synth import Refiner, SynthPipeline, SynthStats, frame_to_sample
from hogsa_loader.sample.views import EgoCameras

__all__ = ["DropGuard", "DroppedSamplesError", "HOGSADataset", "MAX_WORKER_ROWS", "shard_info"]

#: Rows of the shared worker-statistics table (worker ids beyond share rows modulo this).
MAX_WORKER_ROWS = 64

Sample = tuple[dict[str, Any], dict[str, Any], dict[str, Any]]
#: The settings of ``HOGSADataset(bundle, data_root)``.
DEFAULT_CONFIG = LoaderConfig()


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

    Determinism and sharding
        The global sample index space is cut into render batches of ``batch_size``
        consecutive indices; batch ``g`` renders one (subject, object) model: the batches
        form blocks of ``len(keys)``, each block uses every model once in an order drawn from
        ``(seed, epoch, g // len(keys))`` (:meth:`HOGSADataset.batch_key`), its hands too where
        ``sample.other_hands`` > 0 (:meth:`HOGSADataset.batch_hands`), and every random
        draw of sample ``i`` (pose, camera, background, augmentation) comes from
        ``(seed, epoch, i)`` (the streams of :mod:`~hogsa_loader.sample.plan`); batch ``g`` is
        rendered from its :class:`~hogsa_loader.sample.plan.BatchPlan` (:meth:`plan`).
        Batches are dealt round-robin over
        ``world_size × num_workers`` shards (torch.distributed rank, then DataLoader worker),
        so the same seed gives the same samples for the same world size and worker count
        (and the same *set* of samples for any of them). Dropped samples leave a gap.

        The epoch (:meth:`HOGSADataset.set_epoch`) lives in shared memory, so DataLoader
        workers see it even when they persist across epochs (``persistent_workers=True``);
        an iterator reads it once when it starts and keeps it to its end (a ``set_epoch``
        during an iteration applies to the next one). With torch.distributed, shards of one
        rank can hold up to one render batch more than another's (plus their own dropped
        samples): for a fixed number of steps per epoch, iterate an endless dataset (e.g.
        through :class:`~hogsa_loader.sample.mixing.MixedLoader`) rather than a finite one.

    Recommended DataLoader settings (``device``, ``batch_size``: :class:`~hogsa_loader.sample.config.RunConfig`)
        * CPU rendering: ``DataLoader(ds, batch_size=B, num_workers=k, persistent_workers=True)``
          with ``device="cpu"``; each worker renders its own batches (set
          ``torch.set_num_threads(1)`` in ``worker_init_fn`` when k ≥ cores).
        * GPU rendering: ``device="cuda"`` and ``num_workers=0`` — rendering happens batched in
          the main process (the config's ``batch_size`` = the render batch, e.g. 64).
          DataLoader workers must **never** touch CUDA (forked processes and CUDA do not mix);
          iterating a ``device="cuda"`` dataset inside a worker raises ``RuntimeError``.
        * ``batch_size=None`` gives single samples (what :class:`MixedLoader` consumes).

    Statistics
        :attr:`HOGSADataset.stats` (:class:`~hogsa_loader.sample.synth.SynthStats`) counts
        attempted / kept / dropped samples (by reason) and accumulates per-stage seconds
        (``pose``, ``pom``, ``render``, ``srm``, ``composite``, ``targets``) *in the process
        that iterates*. DataLoader workers add theirs to a shared-memory table as they go (one
        row per worker id), so :meth:`HOGSADataset.total_stats` in the main process gives this
        process's counts plus every worker's (per torch.distributed rank: each rank has its own
        dataset).

    Args:
        bundle: bundle folder or a loaded :class:`~hogsa_loader.models.bundle.Bundle` (validated
            against ``data_root``).
        data_root: the ARCTIC(-format) data root the bundle was built on (poses, cameras,
            MANO, object templates).
        config: :class:`~hogsa_loader.sample.config.LoaderConfig`, every setting in groups
            (backgrounds, poses, refinement, cameras, sample, checks, run).
        backgrounds: an explicit background source (a
            :class:`~hogsa_loader.compose.BackgroundSource`) instead of ``config.backgrounds``.
            Without either, procedural backgrounds are used (with a warning). A source from
            the config is built here, in the constructing process (a missing or malformed
            COCO folder fails now, and DataLoader workers receive the parsed image list).
        poses: an explicit pose source (an object with ``sample(key, rngs)``, see
            :mod:`~hogsa_loader.sample.poses`) instead of ``config.poses``.
        refiner: an explicit ``(rgb, alpha) -> rgb`` refiner (premultiplied (B,S,S,3),
            alpha (B,S,S,1)) instead of ``config.refinement`` (the bundle's SRM).

    An explicit object together with non-default settings of its config group is refused
    (``ValueError``): one of the two would be ignored.

    Attributes:
        bundle: the :class:`Bundle`; config: the :class:`LoaderConfig`; keys: the
        (subject, object) models used; cfg: the :class:`ArcticConfig` of the samples
        (``ego_image_scale`` from the world); render_size: side of the rendered crop
        (default ``round(1.5 · img_res)``); stats: :class:`~hogsa_loader.sample.synth.SynthStats`
        of this process (workers': :meth:`worker_stats`, both: :meth:`total_stats`).
    """

    def __init__(
        self,
        bundle: Union[PathLike, Bundle],
        data_root: PathLike,
        config: LoaderConfig = DEFAULT_CONFIG,
        *,
        backgrounds: Any = None,
        poses: Optional[PoseSource] = None,
        refiner: Optional[Refiner] = None,
    ) -> None:
        super().__init__()
        _refuse_overrides(config, backgrounds, poses, refiner)
        self.config = config
        self.data_root = data_root
        built_on = bundle.dataset if isinstance(bundle, Bundle) else bundle_dataset(bundle)
        if built_on != "arctic":
            raise AssetError(
                bundle.path if isinstance(bundle, Bundle) else bundle,
                f"the bundle was built on {built_on}: HOGSADataset streams bundles of ARCTIC(-format) "
                f"roots only (streaming {built_on} samples is not implemented)",
            )
        self.bundle = bundle if isinstance(bundle, Bundle) else load_bundle(bundle, data_root=data_root)
        if isinstance(bundle, Bundle):
            self.bundle.check_data_root(data_root)
        self.root = ArcticRoot(data_root)
        sample = config.sample
        self.cfg = replace(sample.arctic, ego_image_scale=float(self.root.world_meta().ego_image_scale))
        self.render_size = int(sample.render_size) if sample.render_size else int(round(1.5 * self.cfg.img_res))
        self.views = tuple(protocol_views(sample.protocol))
        self.backgrounds = (
            backgrounds if backgrounds is not None else make_backgrounds(**config.backgrounds.make_kwargs())
        )
        self.refiner = refiner
        self._check_srm()
        self._epoch = torch.zeros((), dtype=torch.int64).share_memory_()  # seen by (persistent) workers
        self.epoch = config.run.epoch
        self.stats = SynthStats()
        # DataLoader workers' statistics: row = worker id (a worker adds what it counted since it last did)
        self._worker_stats = torch.zeros(
            MAX_WORKER_ROWS, len(SynthStats().to_vector()), dtype=torch.float64
        ).share_memory_()
        self._published: Optional[tuple[int, np.ndarray]] = None  # (pid, stats vector already added)
        self._pipe: Optional[SynthPipeline] = None
        self._position: Optional[dict[str, int]] = None  # where the running iterator is (state_dict)
        self._resume_at: Optional[dict[str, int]] = None  # where the next iterator starts (load_state_dict)
        # pose source built eagerly (cheap) so bad configurations fail at construction
        self.keys = self._pose_keys(self._requested_keys(), poses)
        if sample.other_hands > 0 and len({k[0] for k in self.keys}) < 2:
            raise ValueError(
                f"other_hands={sample.other_hands} shows other subjects' hands, but the models used {self.keys} "
                "are of one subject"
            )

    # ------------------------------------------------------------------ settings
    @property
    def device(self) -> str:
        """Where rendering runs (``config.run.device``)."""
        return str(self.config.run.device)

    @property
    def batch_size(self) -> int:
        """Render batch (``config.run.batch_size``)."""
        return int(self.config.run.batch_size)

    @property
    def seed(self) -> int:
        """Base seed of every random draw (``config.run.seed``)."""
        return int(self.config.run.seed)

    @property
    def num_samples(self) -> Optional[int]:
        """Samples per epoch (None: endless)."""
        n = self.config.run.num_samples
        return None if n is None else int(n)

    @property
    def protocol(self) -> str:
        """``"p1"`` (allocentric) or ``"p2"`` (egocentric)."""
        return self.config.sample.protocol

    @property
    def split(self) -> str:
        """Split whose sequences the pose source may use."""
        return self.config.sample.split

    @property
    def interfield(self) -> Union[bool, float]:
        """InterField-SF targets: False, True or the clamp in metres."""
        return self.config.sample.interfield

    @property
    def checks(self) -> SampleChecks:
        """When samples are dropped."""
        return self.config.checks

    # ------------------------------------------------------------------ setup
    def _check_srm(self) -> None:
        """With ``srm=True`` and no explicit refiner: the bundle has a scale-1 SRM (fails here, not in the first
        batch)."""
        if not self.config.refinement.srm or self.refiner is not None:
            return
        if self.bundle.srm is None:
            raise ValueError(f"srm=True but bundle {self.bundle.path} has no SRM checkpoint")
        scale = read_srm_manifest(self.bundle.srm.path)["io"].get("scale", 1)
        if scale != 1:
            raise AssetError(
                self.bundle.srm.path / SRM_MANIFEST,
                f"the SRM outputs {scale}x its input size; the loader composites at the render "
                "size and needs a scale-1 SRM",
            )

    def _requested_keys(self) -> list[tuple[str, str]]:
        """The bundle's models allowed by ``config.run.subjects`` / ``objects`` and by the data
        root's protocol: a model of a held-out subject is streamed only when that subject is named
        in ``config.run.allow_held_out`` (with ``subjects=None`` the other held-out models are left
        out, with a warning; a held-out subject named in ``subjects`` alone is refused)."""
        run = self.config.run
        subjects, objects, allowed = run.subjects, run.objects, run.allow_held_out or ()
        keys = [
            k
            for k in self.bundle.keys
            if (subjects is None or k[0] in subjects) and (objects is None or k[1] in objects)
        ]
        held = held_out_subjects(self.root)
        if subjects is None:
            left_out = sorted({k[0] for k in keys if k[0] in held and k[0] not in allowed})
            if left_out:
                keys = [k for k in keys if k[0] not in left_out]
                warnings.warn(
                    f"bundle {self.bundle.path}: models of {left_out}, held out by {self.root}'s protocol, "
                    "are not streamed (name them in allow_held_out to stream them)",
                    stacklevel=3,
                )
        if not keys:
            raise ValueError(
                f"no HOGS model left for subjects={subjects} objects={objects} (held out: {sorted(held)}, "
                f"allowed: {sorted(allowed)}); bundle has {self.bundle.keys}"
            )
        training_subjects(self.root, sorted({k[0] for k in keys}), allowed, "the synthetic stream")
        return keys

    def _pose_keys(self, keys: list[tuple[str, str]], poses: Optional[PoseSource]) -> list[tuple[str, str]]:
        spec = poses if poses is not None else self.config.poses.kind
        src = make_pose_source(spec, self._pose_context(keys), self.config.poses.options)
        have = getattr(src, "keys", keys)
        usable = [k for k in keys if k in have]
        if not usable:
            raise ValueError(
                f"pose source {getattr(src, 'name', src)!r} has no poses for the bundle's models {keys} "
                f"in {self.protocol} {self.split}"
            )
        self._pose_source = src
        return usable

    def _pose_context(self, keys: list[tuple[str, str]]) -> PoseContext:
        return PoseContext(
            root=self.root, keys=keys, protocol=self.protocol, split=self.split, bundle=self.bundle, device=self.device
        )

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
            layers = self.root.mano_layers()
            templates = self.root.object_templates()
            sample = self.config.sample
            self._pipe = SynthPipeline(
                self.root,
                lambda key: self.bundle.load_hogs(key, layers, templates, dev),
                self._pose_source,
                self._cameras(),
                self.backgrounds,
                self.render_size,
                device=dev,
                refiner=self._refiner(dev),
                checks=self.checks,
                stats=self.stats,
                backend=self.config.run.backend,
                interfield=interfield_targets(self.root, sample.interfield),
                protocol=sample.protocol,
                ego_distortion=sample.ego_distortion,
            )
        self._pipe.stats = self.stats
        return self._pipe

    def _cameras(self) -> dict[str, Any]:
        """``subject -> CameraSampler`` (``p1``) or ``EgoCameras`` (``p2``) of the models' subjects."""
        cams: dict[str, Any] = {}
        for sid in sorted({k[0] for k in self.keys}):
            if self.protocol == "p2":
                cams[sid] = EgoCameras(self._sequences_of(sid))
                continue
            misc = self.root.subject_misc(sid)
            views = [v for v in self.views if v >= 1]
            ref = np.mean([s.object.trans.mean(0) for s in self._sequences_of(sid)], axis=0)
            cams[sid] = CameraSampler(
                misc.world2cam[[v - 1 for v in views]],
                misc.intris_mat[[v - 1 for v in views]],
                misc.image_size[views],
                views,
                ref,
                self.config.cameras,
            )
        return cams

    def _refiner(self, dev: torch.device) -> Optional[Refiner]:
        """The explicit refiner, else the bundle's SRM when ``srm=True`` (loaded in this process)."""
        if self.refiner is not None or not self.config.refinement.srm:
            return self.refiner
        model = load_srm(self.bundle.srm.path, device=dev)  # type: ignore[union-attr]
        tta = self.config.refinement.srm_tta

        def refine(rgb: torch.Tensor, alpha: torch.Tensor) -> torch.Tensor:
            out = model.refine(rgb, alpha, tta=tta)
            if out.shape != rgb.shape:
                raise ValueError(
                    f"the bundle's SRM changes the image size {tuple(rgb.shape)} -> {tuple(out.shape)}; "
                    "the loader composites at the render size (use a scale-1 SRM)"
                )
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
        ones included, use it from their next iteration on. A stream state loaded for another
        epoch is dropped (one for this epoch stands); :meth:`state_dict` then says the start."""
        epoch = int(epoch)
        if self._resume_at is not None and self._resume_at["epoch"] != epoch:
            self._resume_at = None
        self._position = None
        self.epoch = epoch

    def _epoch_or(self, epoch: Optional[int]) -> int:
        return self.epoch if epoch is None else int(epoch)

    def batch_key(self, batch_index: int, epoch: Optional[int] = None) -> tuple[str, str]:
        """The (subject, object) model of render batch ``batch_index`` (at ``epoch``, default the current one).

        Balanced: the batches are taken in blocks of ``len(keys)``, and each block uses every
        model once, in an order drawn from (seed, epoch, block) (:func:`~hogsa_loader.sample.plan.batch_order`).
        So every model renders the same number of batches, up to one, in any stretch of the
        stream that starts at a block.
        """
        k = len(self.keys)
        block, slot = divmod(int(batch_index), k)
        return self.keys[int(batch_order(self.seed, self._epoch_or(epoch), block, k)[slot])]

    def batch_indices(self, batch_index: int) -> list[int]:
        """Global sample indices of render batch ``batch_index``."""
        start = int(batch_index) * self.batch_size
        stop = start + self.batch_size
        if self.num_samples is not None:
            stop = min(stop, self.num_samples)
        return list(range(start, max(start, stop)))

    def batch_hands(self, batch_index: int, epoch: Optional[int] = None) -> Optional[tuple[str, str]]:
        """The run whose hand Gaussians render batch ``batch_index`` shows (at ``epoch``,
        default the current one): None (the model's own hands), except in a share
        ``sample.other_hands`` of the batches, drawn from (seed, epoch, batch index)
        (:func:`~hogsa_loader.sample.plan.hands_rng`), which show the hands of another
        subject of :attr:`keys`, drawn uniformly: its run with the batch's object when it has
        one, else its first (:func:`~hogsa_loader.models.gaussians.recombine.hands_run`)."""
        ep = self._epoch_or(epoch)
        return self._hands(batch_index, ep, self.batch_key(batch_index, ep))

    def _hands(self, batch_index: int, epoch: int, key: tuple[str, str]) -> Optional[tuple[str, str]]:
        share = self.config.sample.other_hands
        if share <= 0.0:
            return None
        rng = hands_rng(self.seed, epoch, batch_index)
        if rng.random() >= share:
            return None
        others = sorted({k[0] for k in self.keys} - {key[0]})
        return hands_run(self.keys, others[int(rng.integers(len(others)))], key[1])

    def plan(self, batch_index: int, epoch: Optional[int] = None) -> BatchPlan:
        """The :class:`~hogsa_loader.sample.plan.BatchPlan` of render batch ``batch_index`` at
        ``epoch`` (default the current one)."""
        ep = self._epoch_or(epoch)
        key = self.batch_key(batch_index, ep)
        indices = tuple(self.batch_indices(batch_index))
        return BatchPlan(self.seed, ep, key, indices, self._hands(batch_index, ep, key))

    @property
    def num_batches(self) -> Optional[int]:
        """Render batches per epoch (None when endless)."""
        return None if self.num_samples is None else math.ceil(self.num_samples / self.batch_size)

    # ------------------------------------------------------------------ production
    def render(self, plan: BatchPlan) -> list[Optional[SynthFrame]]:
        """The :class:`SynthFrame` s of ``plan`` (None = dropped), statistics published."""
        pipe = self._pipeline()
        self._publish_stats()
        out = pipe.frames(plan)
        self._publish_stats()
        return out

    def frames(self, batch_index: int, epoch: Optional[int] = None) -> list[Optional[SynthFrame]]:
        """The :class:`SynthFrame` s of render batch ``batch_index`` (None = dropped) at
        ``epoch`` (default the current one)."""
        return self.render(self.plan(batch_index, epoch))

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
        return sample_aug_params(rng, self.config.sample.augment, ego, self.cfg)

    def _to_sample(self, frame: SynthFrame, index: int, epoch: int) -> Sample:
        """ARCTIC augmentation (of sample ``index`` at ``epoch``) and targets of a frame."""
        with self.stats.timed("targets"):
            out = frame_to_sample(frame, self.aug_params(index, epoch), self.cfg)
        self._publish_stats()
        return out

    def to_sample(self, frame: SynthFrame) -> Sample:
        """ARCTIC augmentation + targets of a frame; the index and epoch it records
        (``frame.meta``) fix the augmentation."""
        return self._to_sample(frame, int(frame.meta["index"]), int(frame.meta["epoch"]))

    def _plan_samples(self, plan: BatchPlan, frames: list[Optional[SynthFrame]]) -> Iterator[Sample]:
        for index, frame in zip(plan.indices, frames):
            if frame is not None:
                yield self._to_sample(frame, index, plan.epoch)

    def samples(self, batch_index: int) -> list[Sample]:
        """The kept samples of render batch ``batch_index``, in index order."""
        plan = self.plan(batch_index)
        return list(self._plan_samples(plan, self.render(plan)))

    def sample(self, index: int, epoch: Optional[int] = None) -> Optional[Sample]:
        """Regenerate sample ``index`` alone (same seed, epoch and batch size give the same
        sample as the stream did); None if it is dropped. ``epoch``: default the current one."""
        ep = self._epoch_or(epoch)
        plan = replace(self.plan(int(index) // self.batch_size, ep), indices=(int(index),))
        frame = self._pipeline().frames(plan)[0]
        return None if frame is None else self._to_sample(frame, int(index), ep)

    def _shard_plans(self, start: Optional[int] = None, epoch: Optional[int] = None) -> Iterator[BatchPlan]:
        """The plans of this process's shard from render batch ``start`` (default its first), all
        at ``epoch`` (default the epoch current when the iteration starts)."""
        shard, num = shard_info()
        ep = self.epoch if epoch is None else int(epoch)
        g = shard if start is None else int(start)
        while self.num_batches is None or g < self.num_batches:
            yield self.plan(g, ep)
            g += num

    # ------------------------------------------------------------------ resumable stream
    def state_dict(self) -> dict[str, int]:
        """Where this process's shard of the stream is (a few integers): the state that
        :meth:`load_state_dict` resumes exactly, the next sample being the one an uninterrupted
        iteration would yield next. Before an iteration, its start; in a DataLoader worker,
        that worker's shard (what torchdata's ``StatefulDataLoader`` collects per worker).

        Keys: ``epoch``, ``batch`` (the render batch the next sample comes from; -1: the shard's
        first), ``skip`` (kept samples of that batch already yielded), and what the position
        depends on (``seed``, ``batch_size``, ``num_shards``; -1 before an iteration has told).
        """
        if self._position is not None:
            return dict(self._position)
        if self._resume_at is not None:
            return dict(self._resume_at)
        return {**self._state_base(-1, self.epoch), "batch": -1, "skip": 0}

    def _state_base(self, num_shards: int, epoch: int) -> dict[str, int]:
        """What a stream position depends on (the keys of a state besides ``batch`` and ``skip``)."""
        return {"seed": self.seed, "batch_size": self.batch_size, "num_shards": num_shards, "epoch": epoch}

    def load_state_dict(self, state: dict[str, int]) -> None:
        """Start the next iteration where ``state`` (:meth:`state_dict`) was: same epoch, same
        render batch, its first ``skip`` kept samples left out. The epoch becomes ``state``'s.

        Raises:
            ValueError: ``state`` is not a stream state, or it was taken with another seed or
                render batch size (its positions would name other samples). A state of another
                number of shards (world size × DataLoader workers) is refused when the
                iteration starts.
        """
        need = ("seed", "batch_size", "num_shards", "epoch", "batch", "skip")
        if not isinstance(state, dict) or any(not isinstance(state.get(k), int) for k in need):
            raise ValueError(f"not a HOGSADataset stream state (integers {need}): {state!r}")
        for k, mine in (("seed", self.seed), ("batch_size", self.batch_size)):
            if state[k] != mine:
                raise ValueError(f"the stream state was taken with {k}={state[k]}, this dataset has {k}={mine}")
        self._resume_at = {k: int(state[k]) for k in need}
        self._position = None
        self.epoch = int(state["epoch"])

    def _start(self) -> tuple[Optional[int], int, int]:
        """``(first render batch or None, kept samples of it to skip, epoch)`` of a new iteration
        (consuming a loaded state); the running position set to its start."""
        shard, num = shard_info()
        at, self._resume_at = self._resume_at, None
        if at is not None and at["num_shards"] not in (-1, num):
            raise ValueError(
                f"the stream state was taken over {at['num_shards']} shards (processes × DataLoader workers); "
                f"this iteration has {num}: resume with the same world size and workers"
            )
        if at is not None and at["batch"] >= 0 and at["batch"] % num != shard:
            raise ValueError(f"the stream state is of shard {at['batch'] % num}, this process iterates shard {shard}")
        start = None if at is None or at["batch"] < 0 else at["batch"]
        skip = 0 if at is None else at["skip"]
        epoch = self.epoch if at is None else at["epoch"]
        first = shard if start is None else start
        self._position = {**self._state_base(num, epoch), "batch": first, "skip": skip}
        return start, skip, epoch

    def iter_frames(self) -> Iterator[SynthFrame]:
        """The kept frames of this process's shard, in order (what the offline exporter
        stores), all of the epoch current when the iteration starts."""
        guard = DropGuard(self.checks, self.stats)
        for plan in self._shard_plans():
            frames = self.render(plan)
            yield from (f for f in frames if f is not None)
            guard.update(frames)

    def __iter__(self) -> Iterator[Sample]:
        self._check_device()
        guard = DropGuard(self.checks, self.stats)
        start, skip, epoch = self._start()
        base = self._state_base(shard_info()[1], epoch)
        _, num = shard_info()
        for plan in self._shard_plans(start, epoch):
            g = plan.indices[0] // self.batch_size if plan.indices else 0
            frames = self.render(plan)
            kept = [(i, f) for i, f in zip(plan.indices, frames) if f is not None]
            for j, (index, frame) in enumerate(kept[skip:], start=skip):
                sample = self._to_sample(frame, index, plan.epoch)
                last = j == len(kept) - 1  # the position after this sample: the next batch, or this one
                self._position = {**base, "batch": g + num if last else g, "skip": 0 if last else j + 1}
                yield sample
            if not kept[skip:]:
                self._position = {**base, "batch": g + num, "skip": 0}
            skip = 0
            guard.update(frames)


class DroppedSamplesError(HogsaError, RuntimeError):
    """So many synthetic samples in a row were dropped that the inputs must be wrong; the
    message gives the drops by reason."""


#: Attempts before a high drop share is warned about.
_WARN_AFTER = 256


class DropGuard:
    """Counts dropped samples in a row over a stream's render batches: past
    ``checks.max_consecutive_drops`` it raises :class:`DroppedSamplesError`; once the stream's
    drop share exceeds ``checks.warn_drop_share`` (after 256 attempts) it warns once.

    Args:
        checks: the stream's :class:`~hogsa_loader.sample.config.SampleChecks`.
        stats: the counters whose drop reasons the messages report.
    """

    def __init__(self, checks: SampleChecks, stats: SynthStats) -> None:
        self.checks, self.stats = checks, stats
        self.start = dict(stats.dropped)  # (a DataLoader worker starts with its parent's counts)
        self.in_a_row = self.seen = self.dropped = 0
        self.warned = False

    def _reasons(self) -> str:
        since = {k: v - self.start.get(k, 0) for k, v in self.stats.dropped.items()}
        return ", ".join(f"{k} {v}" for k, v in since.items() if v) or "none counted here"

    def update(self, frames: list[Optional[SynthFrame]]) -> None:
        """Count one render batch's frames (None = dropped), in index order."""
        for frame in frames:
            self.seen += 1
            if frame is not None:
                self.in_a_row = 0
                continue
            self.dropped += 1
            self.in_a_row += 1
            if self.in_a_row >= self.checks.max_consecutive_drops:
                raise DroppedSamplesError(
                    f"{self.in_a_row} synthetic samples in a row were dropped ({self.dropped} of {self.seen} in this "
                    f"stream; by reason: {self._reasons()}): the poses, cameras or models give no valid sample "
                    "(SampleChecks.max_consecutive_drops)"
                )
        if not self.warned and self.seen >= _WARN_AFTER and self.dropped > self.checks.warn_drop_share * self.seen:
            self.warned = True
            warnings.warn(
                f"{self.dropped} of {self.seen} synthetic samples were dropped ({self._reasons()})", stacklevel=3
            )


def _refuse_overrides(config: LoaderConfig, backgrounds: Any, poses: Any, refiner: Any) -> None:
    """An explicit object replaces its config group: refuse non-default settings of that group beside it."""
    for arg, obj, field in (
        ("backgrounds", backgrounds, "backgrounds"),
        ("poses", poses, "poses"),
        ("refiner", refiner, "refinement"),
    ):
        group = getattr(config, field)
        if obj is not None and not is_default(group):
            raise ValueError(
                f"{arg}= is given together with non-default config.{field} settings ({group}); give one of the two"
            )
