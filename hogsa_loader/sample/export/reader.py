"""Reading exported shards back: :class:`SynthShardDataset` (torch ``IterableDataset``).

Start with :class:`SynthShardDataset` (streams the shards; its docstring describes the shard
format, the items, the checks and how work is split) or :class:`SynthShardSamples` (a
map-style dataset of the same samples); :func:`expand_shards` resolves shard lists.
"""

from __future__ import annotations

import glob
import hashlib
import itertools
import json
import os
import re
import tarfile
from pathlib import Path
from typing import Any, Iterator, Optional, Sequence, Union

import numpy as np
import torch
from torch.utils.data import Dataset, IterableDataset, get_worker_info

from hogsa_loader.errors import AssetError, PathLike, read_json
from hogsa_loader.sample.augment import ArcticConfig, sample_aug_params
from hogsa_loader.sample.export.codec import decode_frame, split_member_name
from hogsa_loader.sample.frame import SynthFrame
from hogsa_loader.sample.plan import STREAM_AUG, sample_rng, shard_order
from hogsa_loader.sample.synth import frame_to_sample

__all__ = [
    "AUG_STREAM",
    "SynthShardDataset",
    "SynthShardSamples",
    "expand_shards",
    "iter_tar_samples",
    "member_checksums",
    "frame_to_arctic_sample",
]

_BRACE = re.compile(r"\{([^{}]*)\}")


def _expand_braces(pattern: str) -> list[str]:
    m = _BRACE.search(pattern)
    if m is None:
        return [pattern]
    body = m.group(1)
    rng = re.fullmatch(r"(\d+)\.\.(\d+)", body)
    if rng:
        a, b = rng.group(1), rng.group(2)
        width = len(a) if a.startswith("0") or len(a) == len(b) else 0
        items = [str(i).zfill(width) for i in range(int(a), int(b) + 1)]
    else:
        items = body.split(",")
    out: list[str] = []
    for it in items:
        out.extend(_expand_braces(pattern[: m.start()] + it + pattern[m.end() :]))
    return out


def _indexed_shards(folder: Path, incomplete: bool) -> list[Path]:
    """The shards an export's ``index.json`` lists as complete, in shard order."""
    ipath = folder / "index.json"
    index = read_json(ipath)
    shards = index.get("shards") if isinstance(index, dict) else None
    if not isinstance(shards, list) or not all(isinstance(r, dict) for r in shards):
        raise AssetError(ipath, "not an export index: no list of shards")
    if index.get("complete") is not True and not incomplete:
        raise AssetError(
            ipath,
            f"the export is incomplete: {len(shards)} of {index.get('num_shards')} shards written "
            f"({index.get('num_samples_written')} samples); run it again to finish it, or read "
            "its complete shards with incomplete=True",
        )
    out = []
    for rec in shards:
        name = rec.get("file")
        if (
            not isinstance(name, str)
            or not name.endswith(".tar")
            or "/" in name
            or "\\" in name
            or name.startswith(".")
        ):
            raise AssetError(ipath, f"lists a shard file {name!r} that is not a .tar file of the folder")
        shard = folder / name
        if not shard.is_file():
            raise AssetError(shard, f"shard listed in {ipath.name} is missing")
        if isinstance(rec.get("bytes"), int) and shard.stat().st_size != rec["bytes"]:
            raise AssetError(
                shard,
                f"size {shard.stat().st_size} differs from the {rec['bytes']} bytes in {ipath.name} "
                "(torn or modified shard)",
            )
        out.append(shard)
    if not out:
        raise AssetError(ipath, "the export has no complete shard")
    return out


def expand_shards(paths: Union[PathLike, Sequence[PathLike]], incomplete: bool = False) -> list[Path]:
    """Shard files of a folder, a glob, a brace pattern or a list.

    A folder with an ``index.json`` (an export of :func:`~hogsa_loader.sample.export.writer.write_shards`)
    gives the shards that index lists as complete, in shard order; any other folder its
    ``*.tar`` files, sorted.

    Args:
        paths: folder, glob, brace pattern, file, or a list of them.
        incomplete: accept an export whose index says it is incomplete (its complete shards).

    Raises:
        AssetError: a named file or folder is missing, nothing matched, an export is
            incomplete (without ``incomplete``), or its index is malformed or lists a
            missing or resized shard.
    """
    items = [paths] if isinstance(paths, (str, os.PathLike)) else list(paths)
    out: list[Path] = []
    for item in items:
        s = os.fspath(item)
        for pat in _expand_braces(s):
            p = Path(pat)
            if p.is_dir() and (p / "index.json").is_file():
                out.extend(_indexed_shards(p, incomplete))
            elif p.is_dir():
                found = sorted(p.glob("*.tar"))
                if not found:
                    raise AssetError(p, "no .tar shards in folder")
                out.extend(found)
            elif any(c in pat for c in "*?["):
                found = sorted(Path(x) for x in glob.glob(pat))
                if not found:
                    raise AssetError(pat, "no shard matches the pattern")
                out.extend(found)
            elif p.is_file():
                out.append(p)
            else:
                raise AssetError(p, "shard file is missing")
    return out


def member_checksums(shard: PathLike) -> Optional[dict[str, str]]:
    """``{member name: sha256}`` from the shard's own index file (``<name>.index.json``
    next to it), or None for a tar file without such an index.

    Raises:
        AssetError: the index is malformed or records no ``members_sha256``, or the shard's
            size differs from the one it records.
    """
    shard = Path(shard)
    ipath = shard.with_name(shard.name[: -len(".tar")] + ".index.json") if shard.name.endswith(".tar") else None
    if ipath is None or not ipath.is_file():
        return None
    rec = read_json(ipath)
    digests = rec.get("members_sha256") if isinstance(rec, dict) else None
    if digests is None:
        raise AssetError(ipath, "the shard index records no members_sha256 (export the frames again)")
    if not isinstance(digests, dict) or not all(isinstance(v, str) for v in digests.values()):
        raise AssetError(ipath, "members_sha256 must map member names to sha256 strings")
    if rec.get("bytes") != shard.stat().st_size:
        raise AssetError(
            shard,
            f"size {shard.stat().st_size} differs from the {rec.get('bytes')} bytes in "
            f"{ipath.name} (torn or modified shard)",
        )
    return digests


#: Largest shard member read (a sample's image, masks and labels are tens of kB each).
MAX_MEMBER_BYTES = 64 * 2**20


def iter_tar_samples(path: PathLike, verify: bool = True) -> Iterator[tuple[str, dict[str, bytes]]]:
    """``(key, {extension: bytes})`` for each sample of a tar shard, in file order.

    Members of one sample must be consecutive (WebDataset rule); directories and files
    whose base name starts with ``.`` are ignored. With ``verify`` and a shard index that
    records ``members_sha256`` (:func:`member_checksums`), every member must be listed
    there with its sha256, and every listed member present.

    Raises:
        AssetError: unreadable, truncated or corrupt shard (names the file and the member).
    """
    path = Path(path)
    key: Optional[str] = None
    files: dict[str, bytes] = {}
    digests = member_checksums(path) if verify else None
    seen: set[str] = set()
    try:
        with tarfile.open(path, "r|*") as tar:
            for m in tar:
                if not m.isfile():
                    continue
                base = m.name.rsplit("/", 1)[-1]
                if base.startswith("."):
                    continue
                k, ext = split_member_name(m.name)
                if m.size > MAX_MEMBER_BYTES:  # (a sparse member can announce gigabytes in a small file)
                    too_big = f"{m.size} bytes, more than a sample member's {MAX_MEMBER_BYTES}"
                    raise AssetError(path, f"member {m.name}: {too_big}")
                fh = tar.extractfile(m)
                data = fh.read() if fh is not None else b""
                if digests is not None:
                    if m.name not in digests:
                        raise AssetError(path, f"member {m.name} is not listed in the shard's index")
                    if hashlib.sha256(data).hexdigest() != digests[m.name]:
                        raise AssetError(
                            path, f"member {m.name}: sha256 does not match the shard's index (corrupt shard)"
                        )
                    seen.add(m.name)
                if key is not None and k != key:
                    yield key, files
                    files = {}
                key = k
                files[ext] = data
    except (tarfile.TarError, OSError, EOFError) as exc:
        raise AssetError(path, f"unreadable tar shard ({type(exc).__name__}: {exc})") from None
    if digests is not None and len(seen) != len(digests):
        missing = sorted(set(digests) - seen)
        raise AssetError(path, f"members {missing[:3]} listed in the shard's index are missing")
    if key is not None:
        yield key, files


#: The augmentation stream of a sample (``hogsa_loader.sample.plan.sample_rng`` stream 3).
AUG_STREAM = STREAM_AUG


def frame_to_arctic_sample(
    frame: SynthFrame,
    index: int,
    seed: int = 0,
    epoch: int = 0,
    augment: bool = True,
    cfg: ArcticConfig = ArcticConfig(),
) -> tuple[dict[str, Any], dict[str, Any], dict[str, Any]]:
    """ArcticNet-SF sample of a stored frame, augmentation from ``default_rng([seed, epoch, index, 3])``.

    The live loader's own path (:func:`~hogsa_loader.sample.synth.frame_to_sample`): the
    source blur scaled to the frame's pixel size and the frame's extra targets (e.g. the
    interaction field) appended, so a sample read back equals the live one up to JPEG.
    ``frame.egocentric`` and ``frame.dist`` (restored from ``meta``) select the egocentric
    rules of :func:`~hogsa_loader.sample.targets.make_arctic_sample`.
    """
    rng = sample_rng(seed, epoch, index, AUG_STREAM)
    aug = sample_aug_params(rng, bool(augment), bool(frame.egocentric), cfg)
    return frame_to_sample(frame, aug, cfg)


class SynthShardDataset(IterableDataset):
    """Iterate exported synthetic frames (or ArcticNet-SF samples made from them).

    Reads the tar shards of :mod:`hogsa_loader.sample.export.writer` with the standard library's
    ``tarfile`` (streaming; no extra dependency). Names follow the ``webdataset`` package's
    conventions (key = member name up to the first dot of its base name, a sample's members
    consecutive), so the same shards also open with ``webdataset.WebDataset(urls)``, and
    shard lists may be given as WebDataset brace patterns (``"synth-{000000..000009}.tar"``).

    Each item is either the stored :class:`~hogsa_loader.sample.frame.SynthFrame`, or, with
    ``arctic_samples=True``, ArcticNet-SF's ``(inputs, targets, meta_info)`` built by
    :func:`~hogsa_loader.sample.targets.make_arctic_sample` with ARCTIC's augmentation drawn
    from ``numpy.random.default_rng([seed, epoch, index, 3])`` — ``index`` is the global
    sample index stored with the frame, ``seed``/``epoch`` default to the frame's own
    (``meta["seed"]``, ``meta["epoch"]``) — which is the augmentation stream of
    :class:`~hogsa_loader.sample.dataset.HOGSADataset`
    (:func:`~hogsa_loader.sample.plan.sample_rng`, stream 3). So by default a sample read
    back equals the one the live loader made with the same seed; it does not depend on the
    worker count; and batches collate exactly like real ARCTIC ones.

    A folder written by :func:`~hogsa_loader.sample.export.writer.write_shards` is read as its
    ``index.json`` says: only the shards it lists as complete, in shard order (other ``*.tar``
    files in the folder are ignored); an incomplete export is refused unless ``incomplete=True``
    asks for its complete shards. When a shard's own index records ``members_sha256``, every
    member is checked against it while reading (a flipped byte in an image is an
    :class:`~hogsa_loader.errors.AssetError`, not a silently different sample).

    Work is split over ``world_size × num_workers`` readers (rank from the arguments or
    ``torch.distributed``; worker from ``get_worker_info``): whole shards round-robin when
    there are at least as many shards as readers, otherwise samples round-robin.

    Args:
        paths: shard folder, glob, brace pattern, file, or a list of them.
        arctic_samples: yield ``(inputs, targets, meta_info)`` instead of frames.
        augment: ARCTIC training augmentation (``arctic_samples`` only).
        seed: seed of the augmentation draws; None = each frame's ``meta["seed"]`` (0
            when absent), reproducing the live loader's samples.
        epoch: epoch of the augmentation draws (:meth:`set_epoch`); None = each frame's
            ``meta["epoch"]`` (0 when absent). Set a new epoch per training epoch to get
            new augmentations of the same frames.
        shuffle_shards: visit shards in a permutation drawn from ``(seed, epoch)``.
        cfg: ArcticNet-SF settings for the samples.
        rank: this reader's rank; default ``torch.distributed``'s when initialised, else 0.
        world_size: the number of readers; default ``torch.distributed``'s, else 1.
        incomplete: read the complete shards of an export whose ``index.json`` says it is
            incomplete (otherwise refused, :func:`expand_shards`).

    Attributes:
        shards: the shard files.

    Example:
        >>> ds = SynthShardDataset("export/", arctic_samples=True, seed=1)
        >>> loader = DataLoader(ds, batch_size=64, num_workers=4)  # default collate
    """

    def __init__(
        self,
        paths: Union[PathLike, Sequence[PathLike]],
        arctic_samples: bool = False,
        augment: bool = True,
        seed: Optional[int] = None,
        epoch: Optional[int] = None,
        shuffle_shards: bool = False,
        cfg: Optional[ArcticConfig] = None,
        rank: Optional[int] = None,
        world_size: Optional[int] = None,
        incomplete: bool = False,
    ) -> None:
        super().__init__()
        self.shards = expand_shards(paths, incomplete=incomplete)
        self.arctic_samples = bool(arctic_samples)
        self.augment = bool(augment)
        self.seed = None if seed is None else int(seed)
        self.epoch = None if epoch is None else int(epoch)
        self.shuffle_shards = bool(shuffle_shards)
        self.cfg = cfg if cfg is not None else ArcticConfig()
        self.rank = rank
        self.world_size = world_size

    def set_epoch(self, epoch: int) -> None:
        """Epoch of the augmentation draws and of the shard permutation."""
        self.epoch = int(epoch)

    def _reader(self) -> tuple[int, int]:
        rank, ws = self.rank, self.world_size
        if rank is None or ws is None:
            if torch.distributed.is_available() and torch.distributed.is_initialized():
                rank, ws = torch.distributed.get_rank(), torch.distributed.get_world_size()
            else:
                rank, ws = 0, 1
        info = get_worker_info()
        wid, nw = (info.id, info.num_workers) if info is not None else (0, 1)
        return int(rank) * nw + wid, int(ws) * nw

    def _order(self) -> list[Path]:
        shards = list(self.shards)
        if self.shuffle_shards:
            perm = shard_order(self.seed or 0, self.epoch or 0, len(shards))
            shards = [shards[i] for i in perm]
        return shards

    def iter_raw(self) -> Iterator[tuple[Path, str, dict[str, bytes]]]:
        """``(shard, key, members)`` of this reader's samples (undecoded)."""
        me, total = self._reader()
        shards = self._order()
        if len(shards) >= total:
            for sh in shards[me::total]:
                for key, files in iter_tar_samples(sh):
                    yield sh, key, files
        else:
            counter = itertools.count()
            for sh in shards:
                for key, files in iter_tar_samples(sh):
                    if next(counter) % total == me:
                        yield sh, key, files

    def __iter__(self) -> Iterator[Any]:
        for sh, key, files in self.iter_raw():
            where = f"{sh}:{key}"
            try:
                frame = decode_frame(files, where)
            except ValueError as exc:
                raise AssetError(sh, str(exc)) from None
            if not self.arctic_samples:
                yield frame
                continue
            info = json.loads(files["json"].decode("utf-8"))
            index = info.get("index")
            if index is None:
                try:
                    index = int(key.rsplit("/", 1)[-1])
                except ValueError:
                    raise AssetError(sh, f"{key}: no global index to seed the augmentation") from None
            seed = self.seed if self.seed is not None else int(frame.meta.get("seed", 0))
            epoch = self.epoch if self.epoch is not None else int(frame.meta.get("epoch", 0))
            yield _arctic_sample(sh, key, frame, int(index), seed, epoch, self.augment, self.cfg)


def _arctic_sample(shard: Path, key: str, frame: SynthFrame, index: int, *args: Any) -> Any:
    """:func:`frame_to_arctic_sample` of a stored frame; a frame it cannot use (crafted labels:
    a singular camera, wrong shapes) is an :class:`AssetError` naming the shard and the sample."""
    try:
        return frame_to_arctic_sample(frame, index, *args)
    except (ValueError, KeyError, TypeError, IndexError, np.linalg.LinAlgError) as exc:
        raise AssetError(
            shard, f"{key}: its labels make no ArcticNet-SF sample ({type(exc).__name__}: {exc})"
        ) from None


def _member_places(shard: Path) -> Optional[dict[tuple[str, str], tuple[int, int]]]:
    """``(key, extension) -> (offset, size)`` of the data of every member of an uncompressed
    tar shard; None for a compressed one (no offsets into the file)."""
    try:
        with tarfile.open(shard, "r:") as tar:
            return {split_member_name(m.name): (m.offset_data, m.size) for m in tar.getmembers() if m.isfile()}
    except tarfile.ReadError:
        return None
    except (tarfile.TarError, OSError, EOFError) as exc:
        raise AssetError(shard, f"unreadable tar shard ({type(exc).__name__}: {exc})") from None


def _sample_index(shard: Path, key: str, files: dict[str, bytes]) -> int:
    """Global sample index of a stored sample (``index`` of its JSON, else its key)."""
    try:
        info = json.loads(files["json"].decode("utf-8"))
    except (KeyError, UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise AssetError(shard, f"{key}: unreadable sample record ({type(exc).__name__})") from None
    index = info.get("index")
    if index is not None:
        return int(index)
    try:
        return int(key.rsplit("/", 1)[-1])
    except ValueError:
        raise AssetError(shard, f"{key}: no global index to seed the augmentation") from None


class SynthShardSamples(Dataset):
    """Exported synthetic frames as a map-style dataset of ArcticNet-SF samples.

    The shards are read once when the dataset is made (every member checked against the
    sha256 its shard index records, where it records them) and then indexed: each sample is
    read from its shard by offset when it is accessed (its sha256 checked again), so each rank
    and DataLoader worker holds only
    the index (a few hundred bytes per sample), and a ``DataLoader(shuffle=True)`` draws
    samples from every model and pose of the export in each batch (:class:`SynthShardDataset`
    streams them in shard order). Compressed shards (``.tar.gz``), which cannot be read by
    offset, are held in memory instead (a few tens of kB per sample).

    Sample ``i`` is augmented from ``default_rng([seed, epoch, index, 3])`` with ``index`` its
    global export index — the same draw as :class:`SynthShardDataset` and the live loader.

    Args:
        paths: shard folder, glob, brace pattern, file, or a list of them.
        augment: ARCTIC training augmentation.
        seed: seed of the augmentation draws; None = each frame's ``meta["seed"]``.
        epoch: epoch of the augmentation draws (:meth:`set_epoch`).
        cfg: ArcticNet-SF settings of the samples.
        incomplete: read the complete shards of an export whose ``index.json`` says it is
            incomplete (otherwise refused, :func:`expand_shards`).
    """

    def __init__(
        self,
        paths: Union[PathLike, Sequence[PathLike]],
        augment: bool = True,
        seed: Optional[int] = None,
        epoch: int = 0,
        cfg: Optional[ArcticConfig] = None,
        incomplete: bool = False,
    ) -> None:
        super().__init__()
        self.shards = expand_shards(paths, incomplete=incomplete)
        self.augment = bool(augment)
        self.seed = None if seed is None else int(seed)
        self.epoch = int(epoch)
        self.cfg = cfg if cfg is not None else ArcticConfig()
        # (shard, key, global index, {extension: bytes, or (offset, size, sha256) in the shard})
        self._items: list[tuple[Path, str, int, dict[str, Any]]] = []
        for sh in self.shards:
            places = _member_places(sh)
            for key, files in iter_tar_samples(sh):
                index = _sample_index(sh, key, files)
                if places is not None:
                    files = {ext: (*places[(key, ext)], hashlib.sha256(data).digest()) for ext, data in files.items()}
                self._items.append((sh, key, index, files))
        if not self._items:
            raise AssetError(self.shards[0], "no samples in the export")
        self._handles: dict[Path, Any] = {}
        self._pid = os.getpid()

    def __getstate__(self) -> dict[str, Any]:
        return {**self.__dict__, "_handles": {}}  # (open files stay in the process that opened them)

    def __del__(self) -> None:
        if getattr(self, "_pid", None) == os.getpid():
            for fd in getattr(self, "_handles", {}).values():
                os.close(fd)

    def _files(self, i: int) -> dict[str, bytes]:
        """The encoded members of item ``i``, read from its shard (and checked) when indexed."""
        sh, key, _, files = self._items[i]
        if os.getpid() != self._pid:  # a forked worker: files of its own
            self._handles, self._pid = {}, os.getpid()
        out = {}
        for ext, place in files.items():
            if isinstance(place, bytes):
                out[ext] = place
                continue
            offset, size, digest = place
            fd = self._handles.get(sh)
            if fd is None:
                fd = self._handles[sh] = os.open(sh, os.O_RDONLY)
            data = os.pread(fd, size, offset)  # (no shared file position: safe across threads)
            if len(data) != size or hashlib.sha256(data).digest() != digest:
                raise AssetError(sh, f"{key}.{ext} changed since the dataset was made (truncated or rewritten shard)")
            out[ext] = data
        return out

    def __len__(self) -> int:
        return len(self._items)

    def set_epoch(self, epoch: int) -> None:
        """Epoch of the augmentation draws."""
        self.epoch = int(epoch)

    def frame(self, i: int) -> SynthFrame:
        """The stored frame of item ``i``."""
        sh, key, _, _ = self._items[i]
        files = self._files(i)
        try:
            return decode_frame(files, f"{sh}:{key}")
        except ValueError as exc:
            raise AssetError(sh, str(exc)) from None

    def __getitem__(self, i: int) -> tuple[dict[str, Any], dict[str, Any], dict[str, Any]]:
        frame = self.frame(i)
        index = self._items[i][2]
        seed = self.seed if self.seed is not None else int(frame.meta.get("seed", 0))
        return _arctic_sample(
            self._items[i][0], self._items[i][1], frame, index, seed, self.epoch, self.augment, self.cfg
        )
