"""``MixedLoader``: real ARCTIC batches with an exact share of synthetic samples.

Start with :class:`MixedLoader` (its docstring describes the ``"replace"`` and ``"add"``
modes); :func:`num_synthetic` and :func:`added_synthetic` give the synthetic count per batch.
"""

from __future__ import annotations

from typing import Any, Callable, Iterable, Iterator, Literal, Optional

import torch
from torch.utils.data import (
    DataLoader,
    DistributedSampler,
    IterableDataset,
    RandomSampler,
    SequentialSampler,
    default_collate,
)
from torch.utils.data.sampler import BatchSampler

__all__ = ["MixedLoader", "MixMode", "num_synthetic", "added_synthetic", "batch_size_of", "distributed_loader"]

#: How synthetic samples enter a real batch (see :class:`MixedLoader`).
MixMode = Literal["replace", "add"]


def num_synthetic(ratio: float, batch_size: int) -> int:
    """Synthetic samples in a batch of ``batch_size``: ``floor(ratio·B + 0.5)``."""
    return int(ratio * batch_size + 0.5)


def added_synthetic(ratio: float, real: int) -> int:
    """Synthetic samples appended to ``real`` real ones so that their share is ``ratio``:
    ``floor(ratio / (1 - ratio) · real + 0.5)`` (``ratio < 1``; a 1e-9 margin keeps exact
    halves such as 0.6 / 0.4 = 1.5 from rounding down in floating point)."""
    return int(ratio / (1.0 - ratio) * real + 0.5 + 1e-9)


_CONTAINERS = (torch.Tensor, dict, tuple, list)


def batch_size_of(batch: Any) -> int:
    """Number of samples of a collated batch (first tensor / list found)."""
    if isinstance(batch, torch.Tensor):
        return int(batch.shape[0])
    if isinstance(batch, (list, tuple)) and batch and not isinstance(batch[0], _CONTAINERS):
        return len(batch)
    if isinstance(batch, dict):
        for v in batch.values():
            return batch_size_of(v)
    if isinstance(batch, (list, tuple)):
        for v in batch:
            return batch_size_of(v)
    raise TypeError(f"cannot find the batch size of a {type(batch).__name__}")


def _slice(batch: Any, a: int, b: int) -> Any:
    """Samples ``a:b`` of a collated batch."""
    if isinstance(batch, torch.Tensor):
        return batch[a:b]
    if isinstance(batch, dict):
        return {k: _slice(v, a, b) for k, v in batch.items()}
    if isinstance(batch, tuple):
        return tuple(_slice(v, a, b) for v in batch)
    if isinstance(batch, list):
        if batch and isinstance(batch[0], _CONTAINERS):  # structure (default_collate turns tuples into lists)
            return [_slice(v, a, b) for v in batch]
        return batch[a:b]
    raise TypeError(f"cannot slice a collated {type(batch).__name__}")


def _cat(parts: list[Any]) -> Any:
    """Concatenate collated batches along the batch dimension."""
    first = parts[0]
    if isinstance(first, torch.Tensor):
        return torch.cat(parts, 0)
    if isinstance(first, dict):
        keys = list(first)
        for p in parts[1:]:
            if list(p) != keys:
                raise ValueError(f"cannot mix batches with different keys: {sorted(set(keys) ^ set(p))}")
        return {k: _cat([p[k] for p in parts]) for k in keys}
    if isinstance(first, tuple):
        return tuple(_cat([p[i] for p in parts]) for i in range(len(first)))
    if isinstance(first, list):
        if first and isinstance(first[0], _CONTAINERS):
            return [_cat([p[i] for p in parts]) for i in range(len(first))]
        return [x for p in parts for x in p]
    raise TypeError(f"cannot concatenate collated {type(first).__name__}")


def _pinned(batch: Any) -> Any:
    """``batch`` with its tensors in page-locked memory (what a ``pin_memory=True`` loader gives)."""
    if isinstance(batch, torch.Tensor):
        return batch.pin_memory()
    if isinstance(batch, dict):
        return {k: _pinned(v) for k, v in batch.items()}
    if isinstance(batch, (tuple, list)):
        return type(batch)(_pinned(v) for v in batch)
    return batch


def _process_group() -> tuple[int, int]:
    """``(rank, world size)`` of the initialised torch.distributed process group, else ``(0, 1)``."""
    if torch.distributed.is_available() and torch.distributed.is_initialized():
        return torch.distributed.get_rank(), torch.distributed.get_world_size()
    return 0, 1


def _is_distributed(loader: Any) -> bool:
    """Whether ``loader`` is left as it is on several processes: it already draws a per-rank
    share (a sampler with ``num_replicas``), its dataset is an ``IterableDataset`` (which splits
    itself), or it is not a DataLoader (an iterable of batches that says nothing of samplers)."""
    if not isinstance(loader, DataLoader) or isinstance(loader.dataset, IterableDataset):
        return True
    samplers = [getattr(loader, "sampler", None), getattr(getattr(loader, "batch_sampler", None), "sampler", None)]
    return any(hasattr(s, "num_replicas") for s in samplers)


def distributed_loader(loader: DataLoader, rank: int, world: int, seed: int = 0) -> DataLoader:
    """``loader`` with a :class:`~torch.utils.data.DistributedSampler` in place of its sampler:
    rank ``rank``'s share of ``world`` (what PyTorch Lightning and ``accelerate`` do to the
    DataLoaders they are given).

    The sampler shuffles (with ``seed``, reshuffled by ``set_epoch``) when ``loader``'s sampler is
    a ``RandomSampler`` and keeps the order when it is a ``SequentialSampler``; it drops the last
    ``len(dataset) % world`` samples so that no sample is on two ranks in one epoch. Every other
    setting of ``loader`` is kept (batch size, ``drop_last``, workers, ``collate_fn``,
    ``pin_memory``, generator, ...).

    Raises:
        ValueError: ``loader`` is not a plain :class:`~torch.utils.data.DataLoader` made with
            ``batch_size``, or its sampler / batch sampler is a custom one or samples with
            replacement (which this function cannot split between ranks): give it a
            distributed sampler of its own.
    """
    sampler = getattr(loader, "sampler", None)
    bs = getattr(loader, "batch_sampler", None)
    kind = type(sampler).__name__
    plain = type(loader) is DataLoader and type(bs) is BatchSampler and loader.batch_size is not None
    if isinstance(sampler, RandomSampler) and (sampler.replacement or sampler._num_samples is not None):
        plain = False  # (drawn with replacement, or a number of samples of its own)
    if not plain or not isinstance(sampler, (RandomSampler, SequentialSampler)):
        raise ValueError(
            f"the real loader ({type(loader).__name__}, sampler {kind}, batch sampler {type(bs).__name__}) "
            f"runs on {world} processes without a distributed sampler, and only a DataLoader made with "
            "batch_size= and shuffle (a RandomSampler without replacement) or a SequentialSampler can be "
            "given one; pass a DataLoader with sampler=DistributedSampler(dataset, ...), or distribute=False "
            "when each process's dataset is already its own share"
        )
    dist = DistributedSampler(
        loader.dataset,  # type: ignore[arg-type]
        num_replicas=world,
        rank=rank,
        shuffle=isinstance(sampler, RandomSampler),
        seed=int(seed),
        drop_last=True,
    )
    kwargs = dict(
        batch_size=loader.batch_size,
        sampler=dist,
        num_workers=loader.num_workers,
        collate_fn=loader.collate_fn,
        pin_memory=loader.pin_memory,
        drop_last=loader.drop_last,
        timeout=loader.timeout,
        worker_init_fn=loader.worker_init_fn,
        multiprocessing_context=loader.multiprocessing_context,
        generator=loader.generator,
        persistent_workers=loader.persistent_workers,
        pin_memory_device=loader.pin_memory_device,
        in_order=getattr(loader, "in_order", True),
    )
    if loader.num_workers > 0:
        kwargs["prefetch_factor"] = loader.prefetch_factor
    return DataLoader(loader.dataset, **kwargs)  # type: ignore[arg-type]


class _EpochOf:
    """What ``MixedLoader.sampler`` is: an object whose ``set_epoch`` is the mixed loader's
    (PyTorch Lightning calls ``set_epoch`` on a train loader's ``.sampler`` before each epoch)."""

    def __init__(self, mixed: "MixedLoader") -> None:
        self._mixed = mixed

    @property
    def epoch(self) -> int:
        return self._mixed.epoch

    def set_epoch(self, epoch: int) -> None:
        self._mixed.set_epoch(epoch)


class MixedLoader:
    """Real batches with exactly ``round(ratio·B)`` synthetic samples each (``mode="replace"``),
    or real batches with ``added_synthetic(ratio, b)`` synthetic samples appended (``"add"``).

    With the default ``mode="replace"``, every yielded batch of size B holds exactly
    ``n_syn = floor(ratio·B + 0.5)`` synthetic samples (round half up) after ``B − n_syn`` real
    ones, collated exactly like the real batches: the synthetic samples go through the real
    loader's ``collate_fn`` and are concatenated with the real part along the batch dimension
    (tensors with ``torch.cat``, lists of strings by concatenation, dicts / tuples recursively).

    No real sample is wasted: the real samples a mixed batch does not use are kept for the
    next one, so one epoch of a ``MixedLoader`` yields ``len(real) // (B − n_syn)`` batches and
    covers the real epoch (the last real samples that cannot fill a batch are dropped when
    ``drop_last`` is True, else they form a smaller last batch with its own rounded share).

    ``mode="add"`` instead keeps every real batch as the real loader yields it (its own
    ``drop_last`` applies) and appends ``n_syn = added_synthetic(ratio, b)`` synthetic samples to
    a batch of b real ones, so that a training run sees the same real batches as without
    synthetic data (larger batches, synthetic share ``n_syn / (b + n_syn)`` ≈ ratio).

    Args:
        real_loader: the real DataLoader (collated ``(inputs, targets, meta_info)`` batches,
            so not ``batch_size=None``); its ``batch_size`` is B (else the first batch's size).
        synthetic: an iterable of **single** synthetic samples — a
            :class:`~hogsa_loader.sample.dataset.HOGSADataset` (iterated in this process)
            or ``DataLoader(hogsa_dataset, batch_size=None, num_workers=k)``. It is
            iterated again when exhausted.
        ratio: synthetic share in [0, 1].
        collate_fn: collate of the synthetic samples; default the real loader's own
            ``collate_fn`` (or torch's ``default_collate``).
        drop_last: drop the real samples that cannot fill a last batch (``"replace"``; with
            ``"add"`` the real loader's own ``drop_last`` applies).
        mode: ``"replace"``, batches of B with ``num_synthetic(ratio, B)`` of them synthetic;
            ``"add"``, each real batch unchanged plus ``added_synthetic(ratio, b)`` synthetic
            samples (ratio < 1).
        seed: the shuffle seed of the ``DistributedSampler`` the real loader gets when it has
            none (below).
        distribute: give a real loader without a distributed sampler one on several
            processes (below); False when each process's real dataset is already its own share.

    **Several processes.** Under an initialised torch.distributed process group of N > 1
    processes (torchrun, ``srun``, PyTorch Lightning's or ``accelerate``'s DDP), a real
    DataLoader of a map-style dataset without a distributed sampler is given one
    (:func:`distributed_loader`: each rank its own share, shuffled with ``seed`` when the
    loader shuffles), as Lightning does for the DataLoaders it is given (it cannot see inside
    a ``MixedLoader``); a loader with one is kept (and any with ``distribute=False``). The
    synthetic stream splits itself by rank
    (:class:`~hogsa_loader.sample.dataset.HOGSADataset`).

    :meth:`set_epoch` reaches both halves; so does ``.sampler.set_epoch`` (where PyTorch
    Lightning calls it). When the real loader pins its memory (``pin_memory=True``, with CUDA),
    the mixed batches are pinned too.

    **Resuming mid-epoch.** :meth:`state_dict` says where the loader is (epoch, batches
    yielded, the synthetic stream's own state where it has one); after
    :meth:`load_state_dict` the next iteration yields exactly the batches an uninterrupted one
    would have yielded next. The real loader is iterated again from the epoch's start to the
    same place (its batches are loaded and passed over); the synthetic stream resumes from its
    state without rendering the samples already used (a stream without ``state_dict``, e.g. a
    DataLoader with workers, is drawn again up to the same place).
    """

    def __init__(
        self,
        real_loader: Iterable[Any],
        synthetic: Iterable[Any],
        ratio: float,
        collate_fn: Optional[Callable[[list[Any]], Any]] = None,
        drop_last: bool = True,
        mode: MixMode = "replace",
        seed: int = 0,
        distribute: bool = True,
    ) -> None:
        if not 0.0 <= float(ratio) <= 1.0:
            raise ValueError(f"ratio must be in [0, 1], got {ratio}")
        if mode not in ("replace", "add"):
            raise ValueError(f"mode must be 'replace' or 'add', got {mode!r}")
        if mode == "add" and not float(ratio) < 1.0:
            raise ValueError("mode='add' needs ratio < 1 (real samples in every batch)")
        if hasattr(real_loader, "batch_sampler") and real_loader.batch_sampler is None:
            raise ValueError(
                "the real loader yields single samples (batch_size=None); MixedLoader needs collated batches"
            )
        self.mode = mode
        self.given_loader = real_loader
        self.seed = int(seed)
        self.distribute = bool(distribute)
        self._per_rank: dict[tuple[int, int], Iterable[Any]] = {}
        self.synthetic = synthetic
        self.ratio = float(ratio)
        self.collate_fn = collate_fn or getattr(real_loader, "collate_fn", None) or default_collate
        self.drop_last = bool(drop_last)
        self.pin_memory = bool(getattr(real_loader, "pin_memory", False)) and torch.cuda.is_available()
        self._syn_iter: Optional[Iterator[Any]] = None
        self.epoch = 0
        self.sampler = _EpochOf(self)
        self._batches = 0  # batches yielded in this epoch
        self._syn_taken = 0  # synthetic samples taken in this epoch
        self._resume: Optional[dict[str, Any]] = None
        self._resume_rank = 0

    @property
    def real_loader(self) -> Iterable[Any]:
        """The real loader this process iterates: the one given, or (several processes, none
        of its samplers distributed) that loader with a ``DistributedSampler``."""
        rank, world = _process_group()
        if world == 1 or not self.distribute or _is_distributed(self.given_loader):
            return self.given_loader
        if (rank, world) not in self._per_rank:
            self._per_rank[(rank, world)] = distributed_loader(self.given_loader, rank, world, self.seed)  # type: ignore[arg-type]
        return self._per_rank[(rank, world)]

    def set_epoch(self, epoch: int) -> None:
        """Start epoch ``epoch`` of both halves: the real loader's sampler (a
        ``DistributedSampler``'s shuffle) and dataset (ARCTIC's augmentation draws) and the
        synthetic stream (its dataset's epoch, restarted from its first sample) — what a
        training loop or PyTorch Lightning calls before each epoch."""
        if self._resume is not None and int(epoch) == self._resume["epoch"]:
            return  # the resume loaded for this epoch stands
        self.epoch = int(epoch)
        real = self.real_loader
        sources = [getattr(real, "sampler", None), getattr(real, "dataset", None)]
        sources.append(getattr(getattr(real, "batch_sampler", None), "sampler", None))
        sources += [self.synthetic, getattr(self.synthetic, "dataset", None)]
        done: set[int] = set()
        for src in sources:
            if src is not None and id(src) not in done and callable(getattr(src, "set_epoch", None)):
                src.set_epoch(self.epoch)
                done.add(id(src))
        self._syn_iter = None  # the synthetic stream of this epoch, from its start
        self._batches = self._syn_taken = 0
        self._resume = None

    def state_dict(self) -> dict[str, Any]:
        """Where this loader is in its epoch (JSON-able when the synthetic stream's state is):
        ``{"epoch", "batches"`` (yielded in it), ``"synthetic_taken"`` (synthetic samples used
        since the stream's start in this epoch: a new pass without :meth:`set_epoch` goes on
        with the same stream), ``"synthetic"`` (a list, one per process, of the stream's own
        ``state_dict()`` or None when it has none)``}``; a resume loaded and not yet started
        is returned as loaded.

        Under an initialised torch.distributed group this is a collective call (every rank
        gathers every rank's stream state; PyTorch Lightning's checkpointing and
        ``hogsa finetune`` call it on every rank), so that any rank's copy resumes all of them.
        """
        if self._resume is not None:
            return dict(self._resume)
        stream = getattr(self.synthetic, "state_dict", None)
        mine = stream() if callable(stream) and self._syn_iter is not None else None
        _, world = _process_group()
        every: list[Any] = [mine]
        if world > 1:
            every = [None] * world
            torch.distributed.all_gather_object(every, mine)
        return {"epoch": self.epoch, "batches": self._batches, "synthetic_taken": self._syn_taken, "synthetic": every}

    def load_state_dict(self, state: dict[str, Any]) -> None:
        """Resume where ``state`` (:meth:`state_dict`) was: its epoch is set on both halves
        (:meth:`set_epoch`; a later ``set_epoch`` of the same epoch keeps the resume, as
        PyTorch Lightning calls it after loading), and the next iteration leaves out the
        batches already yielded. Exact when the real loader's order and augmentation depend
        on the epoch alone (a ``DistributedSampler``, a seeded ``ArcticDataset``); a
        ``RandomSampler`` draws another order after a restart.

        Raises:
            ValueError: ``state`` is not a ``MixedLoader`` state, or was taken over another
                number of processes.
        """
        need = ("epoch", "batches", "synthetic_taken")
        streams = state.get("synthetic") if isinstance(state, dict) else None
        if (
            not isinstance(state, dict)
            or any(not isinstance(state.get(k), int) or state[k] < 0 for k in need)
            or not isinstance(streams, list)
        ):
            raise ValueError(f"not a MixedLoader state (non-negative integers {need}, 'synthetic' list): {state!r}")
        rank, world = _process_group()
        if len(streams) != world:
            raise ValueError(f"the loader state was taken over {len(streams)} process(es); this run has {world}")
        self.set_epoch(state["epoch"])
        self._resume = {**state, "synthetic": list(streams)}
        self._resume_rank = rank

    def _restore_synthetic(self, state: dict[str, Any]) -> None:
        """The synthetic stream where ``state`` left it: from its own state, else drawn again
        (and passed over, one sample at a time)."""
        self._syn_taken = int(state["synthetic_taken"])
        mine = state["synthetic"][self._resume_rank]
        load = getattr(self.synthetic, "load_state_dict", None)
        if mine is not None and callable(load):
            load(mine)
            self._syn_iter = iter(self.synthetic)
            return
        for _ in range(self._syn_taken):
            self._next_synthetic(1)

    @property
    def batch_size(self) -> Optional[int]:
        """Samples per mixed batch (None when the real loader's batch size is unknown)."""
        B = getattr(self.real_loader, "batch_size", None)
        if self.mode == "add" and B:
            return B + added_synthetic(self.ratio, B)
        return B

    def _real_samples(self) -> int:
        """Real samples one pass of the real loader yields: its sampler's length (per rank
        with a ``DistributedSampler``), less the last incomplete batch with ``drop_last``."""
        bs = getattr(self.real_loader, "batch_sampler", None)
        sampler = getattr(bs, "sampler", None)
        size = getattr(bs, "batch_size", None) or getattr(self.real_loader, "batch_size", None)
        drop = bool(getattr(bs, "drop_last", getattr(self.real_loader, "drop_last", False)))
        if bs is not None and sampler is not None and hasattr(sampler, "__len__"):
            n = len(sampler)
        elif hasattr(getattr(self.real_loader, "dataset", None), "__len__"):  # e.g. a sized IterableDataset
            n = len(self.real_loader.dataset)  # type: ignore[attr-defined]
        else:
            raise TypeError(
                f"length unknown: the real loader ({type(self.real_loader).__name__}) has neither a "
                "sized sampler nor a sized dataset"
            )
        return (n // size) * size if drop and size else n

    def __len__(self) -> int:
        if self.mode == "add":
            return len(self.real_loader)  # type: ignore[arg-type]
        B = self.batch_size
        if B is None:
            raise TypeError("length unknown: the real loader has no batch_size")
        n_real = self._real_samples()
        per = B - num_synthetic(self.ratio, B)
        if per == 0:
            return len(self.real_loader)  # type: ignore[arg-type]
        return n_real // per if self.drop_last else -(-n_real // per)

    def _next_synthetic(self, n: int) -> list[Any]:
        out: list[Any] = []
        fresh = False  # the iterator was (re)started during this call and gave nothing yet
        while len(out) < n:
            if self._syn_iter is None:
                self._syn_iter = iter(self.synthetic)
                fresh = True
            try:
                out.append(next(self._syn_iter))
                fresh = False
            except StopIteration:
                self._syn_iter = None
                if fresh:
                    raise RuntimeError("the synthetic source yields no samples") from None
        return out

    def _draw(self, n: int) -> list[Any]:
        """``n`` synthetic samples for a batch (counted)."""
        out = self._next_synthetic(n)
        self._syn_taken += n
        return out

    def _mixed(self, real: Optional[Any], n_syn: int) -> Any:
        parts = [] if real is None else [real]
        if n_syn:
            parts.append(self.collate_fn(self._draw(n_syn)))
        batch = _cat(parts) if len(parts) > 1 else parts[0]
        return _pinned(batch) if self.pin_memory else batch

    def __iter__(self) -> Iterator[Any]:
        resume, self._resume = self._resume, None
        skip = 0 if resume is None else int(resume["batches"])
        if resume is not None:
            self._restore_synthetic(resume)
        self._batches = skip
        for batch in self._batches_from(skip):
            self._batches += 1
            yield batch

    def _batches_from(self, skip: int) -> Iterator[Any]:
        """The epoch's mixed batches after the first ``skip`` (whose synthetic samples are not
        drawn: the stream is already past them)."""
        for i, spec in enumerate(self._plan()):
            if i < skip:
                continue
            real, n_syn = spec
            yield self._mixed(real, n_syn)

    def _plan(self) -> Iterator[tuple[Optional[Any], int]]:
        """``(real part or None, synthetic count)`` of each batch of the epoch, in order."""
        if self.mode == "add":
            for batch in self.real_loader:
                yield batch, added_synthetic(self.ratio, batch_size_of(batch))
            return
        B = self.batch_size
        buf: list[Any] = []  # collated real chunks not used yet
        have = 0
        for batch in self.real_loader:
            n = batch_size_of(batch)
            if B is None:
                B = n
            n_syn = num_synthetic(self.ratio, B)
            n_real = B - n_syn
            if n_real == 0:  # all synthetic: one batch per real batch
                yield None, n_syn
                continue
            buf.append(batch)
            have += n
            while have >= n_real:
                real = _cat(buf) if len(buf) > 1 else buf[0]
                take, rest = _slice(real, 0, n_real), _slice(real, n_real, have)
                have -= n_real
                buf = [rest] if have else []
                yield take, n_syn
        if have and not self.drop_last:
            real = _cat(buf) if len(buf) > 1 else buf[0]
            # a smaller last batch: the smallest share s with round(ratio·(have+s)) == s. It
            # exists: s ↦ round(ratio·(have+s)) − s starts ≥ 0 and falls by 0 or 1 per step
            # (ratio < 1 here, since n_real > 0), so it reaches 0; have + s ≤ B.
            s = 0
            while num_synthetic(self.ratio, have + s) != s:
                s += 1
            yield real, s
