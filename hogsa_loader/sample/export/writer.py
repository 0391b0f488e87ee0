"""Resumable, multi-process export of synthetic frames into WebDataset tar shards.

Start with :func:`write_shards` and :func:`dataset_frames_for_shard`, which feeds it from a
:class:`~hogsa_loader.sample.dataset.HOGSADataset`. The folder layout is described by :func:`shard_range`
(the tar shards), :func:`_write_shard` (per-shard index files, temporary names and resuming) and
:func:`rebuild_index` (``index.json``); :func:`shards_of_rank` shares the shards among ranks and
:class:`ExportMismatchError` says when a folder of another export is refused.
"""

from __future__ import annotations

import hashlib
import io
import json
import math
import os
import tarfile
import time
from dataclasses import dataclass
from pathlib import Path
from typing import IO, Any, Callable, Iterable, Iterator, Optional, Sequence

from tqdm import tqdm

from hogsa_loader.errors import PathLike
from hogsa_loader.io.atomic import atomic_open, temp_glob
from hogsa_loader.io.hashing import CACHE_VERSION, sha256_file
from hogsa_loader.io.locks import writer_lock
from hogsa_loader.sample.export.codec import encode_frame, json_default
from hogsa_loader.sample.frame import SynthFrame

__all__ = [
    "ExportMismatchError",
    "export_settings",
    "write_shards",
    "dataset_frames_for_shard",
    "ShardFrames",
    "shard_name",
    "shard_range",
    "shards_of_rank",
    "num_shards",
    "rebuild_index",
    "sample_key",
    "INDEX_NAME",
]

INDEX_NAME = "index.json"
SHARD_PREFIX = "synth"
#: ``info`` keys that do not change the samples (left out of the settings hash).
_INFO_IGNORED = ("world_size", "rank")


class ExportMismatchError(ValueError):
    """The output folder holds shards of a different export (settings, range or count).

    A shard counts as complete only if its index file records this export's sample range
    (first, last) and *settings* (image format, JPEG quality, alpha bits, parts, and a hash of
    ``info`` without its ``world_size`` / ``rank`` keys). Running an export into a folder whose
    shards were written with other settings (another seed, ``--num``, ``--shard-size``...)
    raises :class:`ExportMismatchError` naming the shard and the difference, as do shard files
    beyond this export's last shard; ``overwrite=True`` rewrites (or removes) them instead.
    """


def export_settings(
    image_format: str, jpeg_quality: int, alpha_bits: int, parts: bool, info: Optional[dict[str, Any]]
) -> dict[str, Any]:
    """What a shard's bytes depend on besides its sample range (recorded per shard)."""
    kept = {k: v for k, v in (info or {}).items() if k not in _INFO_IGNORED}
    blob = json.dumps(kept, sort_keys=True, default=json_default).encode("utf-8")
    return {
        "image_format": image_format,
        "jpeg_quality": int(jpeg_quality) if image_format == "jpg" else None,
        "alpha_bits": int(alpha_bits),
        "parts": bool(parts),
        "info_sha256": hashlib.sha256(blob).hexdigest(),
        "cache_version": CACHE_VERSION,
    }


def sample_key(index: int) -> str:
    """Key of global sample ``index`` (``"%010d"``)."""
    return f"{int(index):010d}"


def shard_name(shard: int, prefix: str = SHARD_PREFIX) -> str:
    """``synth-000123.tar``."""
    return f"{prefix}-{int(shard):06d}.tar"


def num_shards(num: int, shard_size: int) -> int:
    """``ceil(num / shard_size)``."""
    return int(math.ceil(int(num) / int(shard_size)))


def shard_range(shard: int, num: int, shard_size: int) -> range:
    """Global sample indices of ``shard``.

    An export of ``num`` samples in shards of ``S`` writes the tar files ``synth-000000.tar`` …
    into its folder: shard ``i`` holds global samples ``[i·S, min((i+1)·S, num))`` under the
    keys ``"%010d" % index`` (members: see :func:`hogsa_loader.sample.export.codec.encode_frame`).
    """
    lo = int(shard) * int(shard_size)
    return range(lo, min(lo + int(shard_size), int(num)))


def shards_of_rank(n_shards: int, rank: int, world_size: int) -> list[int]:
    """Round-robin assignment: the shards ``rank`` writes.

    Shards go to ranks round-robin (``shard % world_size == rank``).
    """
    if not 0 <= rank < world_size:
        raise ValueError(f"rank {rank} outside [0, {world_size})")
    return list(range(int(rank), int(n_shards), int(world_size)))


def _index_path(out_dir: Path, shard: int, prefix: str) -> Path:
    return out_dir / f"{prefix}-{int(shard):06d}.index.json"


def _atomic_write_json(path: Path, obj: Any) -> None:
    with atomic_open(path, "w", encoding="utf-8") as fh:
        json.dump(obj, fh, indent=1, default=json_default)


def _shard_state(out_dir: Path, shard: int, prefix: str, rng: range, settings: Optional[dict[str, Any]]) -> str:
    """``"missing"`` (absent, partial or torn: rewrite it), ``"complete"`` (this export's) or
    ``"stale: <reason>"`` (a whole shard of another export). ``settings=None`` skips that check."""
    tar, idx = out_dir / shard_name(shard, prefix), _index_path(out_dir, shard, prefix)
    if not (tar.is_file() and idx.is_file()):
        return "missing"
    try:
        with open(idx, "r", encoding="utf-8") as fh:
            rec = json.load(fh)
        if int(rec.get("bytes", -1)) != tar.stat().st_size or rec.get("sha256") != sha256_file(tar):
            return "missing"  # (tar pads to 10,240-byte records: a torn rewrite can have the right size)
    except (OSError, ValueError, AttributeError, TypeError):
        return "missing"
    if (rec.get("first"), rec.get("last")) != (rng.start, rng.stop - 1):
        held, ours = f"{rec.get('first')}..{rec.get('last')}", f"{rng.start}..{rng.stop - 1}"
        return f"stale: it holds samples {held}, this export's are {ours}"
    if settings is not None and rec.get("settings") != settings:
        old = rec.get("settings") or {}
        diff = sorted(k for k in settings if old.get(k) != settings[k]) or ["settings"]
        return f"stale: written with other {', '.join(diff)} ({', '.join(f'{k}={old.get(k)!r}' for k in diff[:3])})"
    return "complete"


class _HashingWriter:
    """A write-only file wrapper that hashes what passes through (for the shard's sha256)."""

    def __init__(self, fh: IO[bytes]) -> None:
        self.fh, self.sha = fh, hashlib.sha256()

    def write(self, data: bytes) -> int:
        self.sha.update(data)
        return self.fh.write(data)

    def tell(self) -> int:
        return self.fh.tell()


def _extra_shards(out_dir: Path, n: int, prefix: str) -> list[int]:
    """Numbers of the shard files in ``out_dir`` numbered ``n`` or more (left by a larger export)."""
    found = (int(p.name[len(prefix) + 1 : -4]) for p in out_dir.glob(f"{prefix}-[0-9][0-9][0-9][0-9][0-9][0-9].tar"))
    return sorted(s for s in found if s >= n)


def _add_member(tar: tarfile.TarFile, name: str, data: bytes, digests: dict[str, str]) -> None:
    digests[name] = hashlib.sha256(data).hexdigest()
    ti = tarfile.TarInfo(name)
    ti.size = len(data)
    ti.mtime = 0  # byte-identical shards for identical frames
    ti.mode = 0o644
    ti.uname = ti.gname = "hogsa"
    tar.addfile(ti, io.BytesIO(data))


def _locked(out_dir: Path) -> Any:
    """The export index's lock: the ranks rebuild ``index.json`` one at a time."""
    return writer_lock(out_dir, ".index.lock", "the export index", wait=True)


def rebuild_index(
    out_dir: PathLike,
    num: int,
    shard_size: int,
    info: Optional[dict[str, Any]] = None,
    prefix: str = SHARD_PREFIX,
    settings: Optional[dict[str, Any]] = None,
) -> dict[str, Any]:
    """Write ``index.json`` from the complete shards found in ``out_dir`` and return it.

    A shard is listed when it is whole, holds its range of this ``num`` / ``shard_size``
    and (given ``settings``, see :func:`export_settings`) was written with them.

    ``index.json`` describes the whole export: parameters, caller's ``info`` and every complete
    shard, ``complete`` true once all shards exist, ``num_dropped`` (samples of the complete
    shards that are missing) and ``dropped`` (those by reason, when every complete shard recorded
    them, else null). Rebuilt by every rank after it finishes
    (under an ``fcntl`` lock where available), so the last rank to finish leaves it full.
    """
    out = Path(out_dir)
    n = num_shards(num, shard_size)
    with _locked(out):
        shards = []
        for s in range(n):
            if _shard_state(out, s, prefix, shard_range(s, num, shard_size), settings) == "complete":
                with open(_index_path(out, s, prefix), "r", encoding="utf-8") as fh:
                    rec = json.load(fh)
                entry = {k: rec[k] for k in ("shard", "file", "count", "first", "last", "bytes")}
                if _explains_gaps(rec.get("dropped"), rec["last"] - rec["first"] + 1 - rec["count"]):
                    entry["dropped"] = rec["dropped"]
                shards.append(entry)
        if info is None and (out / INDEX_NAME).is_file():
            try:
                with open(out / INDEX_NAME, "r", encoding="utf-8") as fh:
                    info = json.load(fh).get("info")
            except (OSError, ValueError, AttributeError):
                info = None
        index = {
            "format": "webdataset",
            "sample_format": "hogsa SynthFrame v1 (.jpg|.png, .alpha.png, .parts.png, .labels.npz, .json)",
            "num": int(num),
            "shard_size": int(shard_size),
            "num_shards": n,
            "settings": settings,
            "complete": len(shards) == n,
            "num_samples_written": int(sum(s["count"] for s in shards)),
            "num_dropped": int(sum(s["last"] - s["first"] + 1 - s["count"] for s in shards)),
            "dropped": _dropped_by_reason(shards),
            "shards": shards,
            "info": info or {},
        }
        _atomic_write_json(out / INDEX_NAME, index)
    return index


def _explains_gaps(dropped: Any, gaps: int) -> bool:
    """Whether ``dropped`` is ``{reason: count}`` with whole, non-negative counts that add up to
    the ``gaps`` (samples missing from the shard)."""
    return (
        isinstance(dropped, dict)
        and all(
            isinstance(k, str) and isinstance(v, int) and not isinstance(v, bool) and v >= 0 for k, v in dropped.items()
        )
        and sum(dropped.values()) == gaps
    )


def _dropped_by_reason(shards: list[dict[str, Any]]) -> Optional[dict[str, int]]:
    """Drops by reason summed over ``shards`` (None unless every shard recorded its reasons)."""
    if not shards or not all(isinstance(s.get("dropped"), dict) for s in shards):
        return None
    total: dict[str, int] = {}
    for s in shards:
        for reason, n in s["dropped"].items():
            total[reason] = total.get(reason, 0) + int(n)
    return total


def _frame_index(frame: SynthFrame, rng: range, position: int, last: int, shard: int) -> int:
    """Global index of the ``position``-th frame of a shard (``meta["index"]`` or the position)."""
    meta_index = frame.meta.get("index") if isinstance(frame.meta, dict) else None
    idx = rng.start + position if meta_index is None else int(meta_index)
    if not rng.start <= idx < rng.stop:
        raise ValueError(f"shard {shard}: frame index {idx} outside the shard's samples [{rng.start}, {rng.stop})")
    if idx <= last:
        raise ValueError(f"shard {shard}: frame indices must increase (got {idx} after {last})")
    return idx


class ShardFrames:
    """The kept frames of one shard drawn from a dataset, and what it dropped meanwhile.

    Iterating renders the batches ``g`` covering global samples ``[lo, hi)``
    (``dataset.frames(g)``) and yields the kept frames of that range. Once the iteration is
    complete, :attr:`dropped` holds the samples the dataset dropped meanwhile, by reason (the
    change of ``dataset.total_stats().dropped``; ``None`` before, or for a dataset without
    statistics). The counts cover whole render batches: a batch that reaches beyond the shard
    counts its drops there too. :func:`write_shards` stores them in the shard's index file when
    they add up to the samples missing from it.
    """

    def __init__(self, dataset: Any, lo: int, hi: int) -> None:
        self.dataset, self.lo, self.hi = dataset, int(lo), int(hi)
        self.dropped: Optional[dict[str, int]] = None

    def _drop_counts(self) -> Optional[dict[str, int]]:
        stats = getattr(self.dataset, "total_stats", None)
        return None if stats is None else {k: int(v) for k, v in stats().dropped.items()}

    def __iter__(self) -> Iterator[SynthFrame]:
        B = int(self.dataset.batch_size)
        before = self._drop_counts()
        for g in range(self.lo // B, (self.hi - 1) // B + 1):
            for f in self.dataset.frames(g):
                if f is not None and self.lo <= int(f.meta["index"]) < self.hi:
                    yield f
        after = self._drop_counts()
        if before is not None and after is not None:
            self.dropped = {k: v - before.get(k, 0) for k, v in after.items() if v != before.get(k, 0)}


def dataset_frames_for_shard(dataset: Any, num: int, shard_size: int) -> Callable[[int], ShardFrames]:
    """``frames_for_shard`` over a :class:`~hogsa_loader.sample.dataset.HOGSADataset`.

    Shard ``i`` gets the kept frames of global indices ``[i·S, min((i+1)·S, num))``: the
    render batches ``g`` covering that range (``dataset.frames(g)``, batches of
    ``dataset.batch_size`` consecutive indices), filtered to the range, as a
    :class:`ShardFrames`. Dropped samples leave gaps (the shard index records ``count`` <
    ``expected``, and the drops by reason). Choose ``S`` a multiple of the batch size, so no
    batch is rendered for two shards and each shard's reasons are its own.
    """
    S = int(shard_size)

    def frames_for_shard(shard: int) -> ShardFrames:
        return ShardFrames(dataset, shard * S, min((shard + 1) * S, int(num)))

    return frames_for_shard


@dataclass(frozen=True)
class _Encoding:
    """How frames are stored: see :func:`~hogsa_loader.sample.export.codec.encode_frame`."""

    image_format: str
    jpeg_quality: int
    alpha_bits: int
    parts: bool


def _shards_to_write(
    out: Path,
    n: int,
    num: int,
    shard_size: int,
    rank: int,
    world_size: int,
    prefix: str,
    settings: dict[str, Any],
    overwrite: bool,
) -> tuple[list[int], list[int]]:
    """``(todo, skipped)``: this rank's shards to write and those already complete.

    Raises :class:`ExportMismatchError` on another export's shards unless ``overwrite`` (then
    shard files beyond this export's last one are removed).
    """
    mine = shards_of_rank(n, rank, world_size)
    state = {s: _shard_state(out, s, prefix, shard_range(s, num, shard_size), settings) for s in mine}
    stale = [s for s in mine if state[s].startswith("stale")]
    extra = _extra_shards(out, n, prefix)
    if (stale or extra) and not overwrite:
        what = (
            f"{out / shard_name(stale[0], prefix)} is {state[stale[0]]}"
            if stale
            else f"{out / shard_name(extra[0], prefix)} lies beyond this export's {n} shard(s) "
            "(an export with a larger num?)"
        )
        raise ExportMismatchError(
            f"{out}: holds shards of another export: {what}; use another folder or "
            "overwrite=True (hogsa export --overwrite)"
        )
    for x in extra:  # (overwrite) a reader globbing *.tar must not find them
        _index_path(out, x, prefix).unlink(missing_ok=True)
        (out / shard_name(x, prefix)).unlink(missing_ok=True)
    todo = [s for s in mine if state[s] != "complete"]
    return todo, [s for s in mine if s not in todo]


def _write_tar(
    fh: IO[bytes], frames: Iterable[SynthFrame], rng: range, shard: int, enc: _Encoding, bar: Optional[Any]
) -> tuple[list[str], dict[str, str]]:
    """Write the frames of ``shard`` (global samples ``rng``) as a tar into the open file ``fh``; its keys and
    member digests."""
    keys: list[str] = []
    digests: dict[str, str] = {}
    with tarfile.open(fileobj=fh, mode="w", format=tarfile.GNU_FORMAT) as tar:
        last = last_seen = rng.start - 1
        for j, frame in enumerate(frames):
            idx = _frame_index(frame, rng, j, last, shard)
            last = idx
            key = sample_key(idx)
            for member, data in encode_frame(
                frame,
                key,
                index=idx,
                shard=shard,
                image_format=enc.image_format,
                jpeg_quality=enc.jpeg_quality,
                alpha_bits=enc.alpha_bits,
                parts=enc.parts,
            ).items():
                _add_member(tar, member, data, digests)
            keys.append(key)
            if bar is not None:  # progress in indices (dropped ones count as done)
                bar.update(idx - max(last_seen, rng.start - 1))
                last_seen = idx
    if bar is not None:
        bar.update(rng.stop - 1 - max(last_seen, rng.start - 1))
    return keys, digests


def _write_shard(
    out: Path,
    shard: int,
    frames: Iterable[SynthFrame],
    rng: range,
    enc: _Encoding,
    prefix: str,
    rank: int,
    world_size: int,
    settings: dict[str, Any],
    bar: Optional[Any],
) -> int:
    """Write one shard under a temporary name, then its index file, then rename it; returns its sample count.

    The index file (``synth-000000.index.json`` …) records per shard: keys, first/last index,
    count, expected count, bytes, seconds, writer rank, ``members_sha256`` (``{member name:
    sha256}``, checked by the readers) and, when ``frames`` reports them (a :class:`ShardFrames`)
    and they add up to the samples missing from the shard, the samples dropped by reason.

    Each shard is written under a hidden temporary name and renamed when complete (after its
    index file), so an interrupted export is resumed by running it again: complete shards are
    skipped, partial ones are rewritten. A failed shard leaves no temporary file behind, and an
    export that failed before completing any shard leaves no ``index.json`` (nor a folder it
    created).
    """
    name = shard_name(shard, prefix)
    for pattern in (temp_glob(out / name), f".{name}.tmp.*"):  # this and the earlier temporary names
        for stale in out.glob(pattern):
            stale.unlink()
    # a shard being rewritten (--overwrite) has no index until it is complete: a torn rewrite reads as missing
    _index_path(out, shard, prefix).unlink(missing_ok=True)
    t0 = time.perf_counter()
    with atomic_open(out / name) as fh:  # renamed once the index file below is written
        hashed = _HashingWriter(fh)
        keys, digests = _write_tar(hashed, frames, rng, shard, enc, bar)
        fh.flush()
        os.fsync(fh.fileno())  # the tar is on disk before its index says it is complete
        rec = {
            "shard": shard,
            "file": name,
            "count": len(keys),
            "expected": len(rng),
            "first": rng.start,
            "last": rng.stop - 1,
            "keys": keys,
            "bytes": fh.tell(),
            "sha256": hashed.sha.hexdigest(),
            "seconds": round(time.perf_counter() - t0, 3),
            "rank": rank,
            "world_size": world_size,
            "settings": settings,
            "members_sha256": digests,
        }
        dropped = getattr(frames, "dropped", None)
        if _explains_gaps(dropped, len(rng) - len(keys)):
            rec["dropped"] = dropped
        _atomic_write_json(_index_path(out, shard, prefix), rec)
    return len(keys)


def _output_folder(out_dir: PathLike, num: int, shard_size: int) -> tuple[Path, bool]:
    """The export folder (created) and whether this call created it.

    Raises:
        ValueError: ``num`` or ``shard_size`` is not positive.
    """
    if num <= 0 or shard_size <= 0:
        raise ValueError(f"num and shard_size must be positive, got {num}, {shard_size}")
    out = Path(out_dir)
    created = not out.exists()
    out.mkdir(parents=True, exist_ok=True)
    return out, created


def _progress_bar(todo: Sequence[int], num: int, shard_size: int, rank: int, world_size: int) -> Any:
    """A tqdm bar over the samples of the shards ``todo``."""
    return tqdm(
        total=sum(len(shard_range(s, num, shard_size)) for s in todo),
        unit="img",
        dynamic_ncols=True,
        desc=f"hogsa export (rank {rank}/{world_size})",
    )


def write_shards(
    frames_for_shard: Callable[[int], Iterable[SynthFrame]],
    out_dir: PathLike,
    num: int,
    shard_size: int,
    rank: int = 0,
    world_size: int = 1,
    progress: bool = True,
    image_format: str = "jpg",
    jpeg_quality: int = 95,
    alpha_bits: int = 8,
    parts: bool = True,
    info: Optional[dict[str, Any]] = None,
    prefix: str = SHARD_PREFIX,
    overwrite: bool = False,
) -> dict[str, Any]:
    """Write this rank's shards of a ``num``-sample export (resumable).

    Args:
        frames_for_shard: ``shard → iterable of SynthFrame``, the frames of global
            samples ``shard_range(shard, num, shard_size)`` in increasing order. A frame's
            global index (its key) is ``frame.meta["index"]`` when present — gaps allowed,
            e.g. dropped samples; the count is recorded in the index — else its position
            in the shard. An index outside the shard's range is an error.
        out_dir: output folder (created).
        num: total number of samples of the export.
        shard_size: samples per shard ``S``.
        rank, world_size: this process and the number of processes (shards
            ``rank, rank + world_size, ...`` are written here).
        progress: tqdm bar (rank 0 only).
        image_format, jpeg_quality, alpha_bits, parts: see
            :func:`~hogsa_loader.sample.export.codec.encode_frame`.
        info: JSON-able description of the export (bundle, seed, ...) for ``index.json``;
            everything in it except ``world_size`` / ``rank`` must be equal for a resume.
        prefix: shard file prefix.
        overwrite: rewrite shards of another export found in ``out_dir`` (see
            :class:`ExportMismatchError`) and remove shard files beyond this export's last one.

    Returns:
        ``{"written": [...], "skipped": [...], "samples": n, "seconds": t, "index": path,
        "complete": bool}`` for this call, and the whole export's ``num_samples_written``,
        ``num_dropped`` and ``dropped`` (by reason or None) as ``index.json`` records them.

    Raises:
        ExportMismatchError: ``out_dir`` holds shards of another export and not ``overwrite``.
    """
    out, created = _output_folder(out_dir, num, shard_size)
    with writer_lock(out, f".rank-{int(rank)}.lock", f"rank {rank} of an export"):  # one writer per rank
        n = num_shards(num, shard_size)
        settings = export_settings(image_format, jpeg_quality, alpha_bits, parts, info)
        todo, skipped = _shards_to_write(out, n, num, shard_size, rank, world_size, prefix, settings, overwrite)
        enc = _Encoding(image_format, jpeg_quality, alpha_bits, parts)
        bar = _progress_bar(todo, num, shard_size, rank, world_size) if progress and rank == 0 else None
        t_all = time.perf_counter()
        failed = True
        if todo:  # the marker first: until the last shard is written, index.json says incomplete
            rebuild_index(out, num, shard_size, info=info, prefix=prefix, settings=settings)
        try:
            sizes = (num, shard_size, rank, world_size)
            written_samples = _write_todo(out, todo, frames_for_shard, sizes, enc, prefix, settings, bar)
            failed = False
        finally:
            if bar is not None:
                bar.close()
            # also after an interruption: index.json always describes what is on disk
            index = rebuild_index(out, num, shard_size, info=info, prefix=prefix, settings=settings)
            if failed and not index["shards"] and world_size == 1:  # nothing of this export exists
                _remove_empty_export(out, created)
        return {
            "written": todo,
            "skipped": skipped,
            "samples": written_samples,
            "seconds": time.perf_counter() - t_all,
            "index": str(out / INDEX_NAME),
            **{k: index[k] for k in ("complete", "num_samples_written", "num_dropped", "dropped")},
        }


def _write_todo(
    out: Path,
    todo: list[int],
    frames_for_shard: Callable[[int], Iterable[SynthFrame]],
    sizes: tuple[int, int, int, int],
    enc: Any,
    prefix: str,
    settings: dict[str, Any],
    bar: Any,
) -> int:
    """Write the shards ``todo`` (``sizes``: samples, shard size, rank, world size); the samples kept."""
    num, shard_size, rank, world_size = sizes
    written, dropped = 0, 0
    for s in todo:
        rng = shard_range(s, num, shard_size)
        count = _write_shard(out, s, frames_for_shard(s), rng, enc, prefix, rank, world_size, settings, bar)
        written += count
        if bar is not None:
            dropped += len(rng) - count
            bar.set_postfix({"dropped": dropped})
    return written


def _remove_empty_export(out: Path, created: bool) -> None:
    """Remove the index and lock of an export that wrote nothing (and its folder, when it made it)."""
    (out / INDEX_NAME).unlink(missing_ok=True)
    (out / ".index.lock").unlink(missing_ok=True)
    for lock in out.glob(".rank-*.lock"):
        lock.unlink(missing_ok=True)
    if created and not any(out.iterdir()):
        out.rmdir()
