"""Background sources for compositing synthetic hand-object crops.

Every source draws ``n`` backgrounds of a requested size from an explicit
:class:`torch.Generator`, so the same generator state gives the same images, whatever the
cache holds or which DataLoader worker asks:

* :class:`CocoBackgrounds` — a real COCO folder read through ``pycocotools``: random image
  (optionally only images showing given categories, optionally without people), random
  crop of random scale, optional horizontal flip;
* :class:`FolderBackgrounds` — any folder of ``.jpg``/``.png`` images, same crops;
* :class:`ProceduralBackgrounds` — the documented fallback when no image is given:
  gradients, multi-octave value noise, stripes/checkers, soft blobs and "table top"
  planes with lighting falloff and sensor grain (a lazily generated, seed-fixed pool of
  textures, then random crops, flips and colour gains from the generator).

:func:`make_backgrounds` picks one from the loader's arguments. Decoded images are kept in
a per-process LRU cache bounded in bytes (:class:`ImageCache`); images are decoded with
OpenCV, COCO images at a reduced JPEG scale (``IMREAD_REDUCED_COLOR_{2,4,8}``) when the
crop is large enough that full resolution is wasted (the reduction is chosen from the
annotation's image size and the drawn crop, never from the cache, so results are
deterministic).

Sources are picklable (they hold paths and sizes, not open handles), so they can live in
DataLoader workers; each worker then has its own cache. The filtered COCO image list is
memoised in the process and cached on disk (``$HOGSA_CACHE`` or ``~/.cache/hogsa_loader``)
so that workers and later runs do not parse the 450 MB annotation file again.

Throughput notes (1 CPU thread, measured on a shared 2-core EPYC): a COCO/folder draw
from the cache is a crop + resize + float conversion (≈ 1–3 ms at 336²); a cache miss adds
reading and decoding the JPEG (≈ 3–8 ms for a 640×480 image, less at reduced scale); a procedural draw from the warm pool ≈ 1–3 ms, a pool texture
≈ 20–40 ms once (:meth:`ProceduralBackgrounds.warm` builds all of them up front).
"""

from __future__ import annotations

import contextlib
import hashlib
import io
import json
import logging
import math
import os
import threading
import warnings
from collections import OrderedDict
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from pathlib import Path
from typing import Iterator, Optional, Sequence, Union

import cv2
import numpy as np
import torch
import torch.nn.functional as F

from hogsa_loader.errors import AssetError, PathLike, read_json

__all__ = [
    "BackgroundSource",
    "default_cache_dir",
    "CocoBackgrounds",
    "FolderBackgrounds",
    "ProceduralBackgrounds",
    "ImageCache",
    "CropSpec",
    "make_backgrounds",
    "IMAGE_EXTENSIONS",
    "COCO_PERSON",
]

log = logging.getLogger(__name__)

#: File endings :class:`FolderBackgrounds` reads (case-insensitive).
IMAGE_EXTENSIONS: tuple[str, ...] = (".jpg", ".jpeg", ".png", ".bmp", ".webp")
#: COCO category excluded by ``exclude_person=True`` (people, hence hands).
COCO_PERSON: str = "person"
_MAX_REDRAWS = 16
_TEXTURE_LOCK = threading.RLock()
_FALLBACK_WARNED = False


# --------------------------------------------------------------------------------------
# Cache
# --------------------------------------------------------------------------------------


class ImageCache:
    """LRU cache of decoded images bounded by total bytes.

    Args:
        max_bytes: capacity; 0 disables caching. An image larger than the capacity is
            returned but not kept.

    Attributes:
        hits, misses: counters (this process).
    """

    def __init__(self, max_bytes: int = 512 * 2**20) -> None:
        self.max_bytes = int(max_bytes)
        self._lock = threading.Lock()  # sample_many draws from a thread pool
        self._items: "OrderedDict[object, np.ndarray]" = OrderedDict()
        self._bytes = 0
        self.hits = 0
        self.misses = 0

    def __len__(self) -> int:
        return len(self._items)

    @property
    def nbytes(self) -> int:
        """Bytes currently held."""
        return self._bytes

    def get(self, key: object) -> Optional[np.ndarray]:
        """The cached array (marked most recently used) or None."""
        with self._lock:
            arr = self._items.get(key)
            if arr is None:
                self.misses += 1
                return None
            self._items.move_to_end(key)
            self.hits += 1
            return arr

    def put(self, key: object, arr: np.ndarray) -> None:
        """Insert, evicting least recently used entries beyond the capacity."""
        if self.max_bytes <= 0 or arr.nbytes > self.max_bytes:
            return
        with self._lock:
            old = self._items.pop(key, None)
            if old is not None:
                self._bytes -= old.nbytes
            self._items[key] = arr
            self._bytes += arr.nbytes
            while self._bytes > self.max_bytes and self._items:
                _, ev = self._items.popitem(last=False)
                self._bytes -= ev.nbytes

    def clear(self) -> None:
        """Drop everything."""
        with self._lock:
            self._items.clear()
            self._bytes = 0

    def __getstate__(self) -> dict:
        # a pickled source (e.g. sent to a DataLoader worker) starts with an empty cache
        return {"max_bytes": self.max_bytes}

    def __setstate__(self, state: dict) -> None:
        self.__init__(state["max_bytes"])


# --------------------------------------------------------------------------------------
# Base class and crops
# --------------------------------------------------------------------------------------


@dataclass(frozen=True)
class CropSpec:
    """Random crop settings of image sources.

    Attributes:
        min_fraction, max_fraction: side of the crop as a fraction of the largest crop of
            the output aspect ratio that fits in the image; drawn log-uniformly.
        hflip: flip horizontally with probability 0.5.
    """

    min_fraction: float = 0.35
    max_fraction: float = 1.0
    hflip: bool = True

    def __post_init__(self) -> None:
        if not 0.0 < self.min_fraction <= self.max_fraction <= 1.0:
            raise ValueError(f"need 0 < min_fraction <= max_fraction <= 1, got {self}")


class BackgroundSource:
    """Base class: ``sample(n, height, width, generator)`` → ``(n, H, W, 3)`` float32 in [0, 1].

    The output depends only on the generator's state (and on the files, for image
    sources); the generator is advanced by the draws.
    """

    #: short name for logs and benchmark reports
    kind: str = "base"
    #: threads of :meth:`sample_many` (None = min(8, available cores))
    threads: Optional[int] = None

    def __len__(self) -> int:  # pragma: no cover - overridden
        return 0

    def _draw(self, height: int, width: int, generator: torch.Generator) -> tuple[np.ndarray, Optional[np.ndarray]]:
        """One image: ``(H, W, 3)`` uint8 RGB and optional (3,) float32 channel gains."""
        raise NotImplementedError

    @staticmethod
    def _finish(arr: np.ndarray, gains: Optional[np.ndarray], device: Optional[torch.device]) -> torch.Tensor:
        """uint8 ``(n, H, W, 3)`` → float32 in [0, 1] on ``device`` (same arithmetic everywhere)."""
        t = torch.from_numpy(arr)
        if device is not None and torch.device(device).type != "cpu":
            t = t.pin_memory().to(device, non_blocking=True) if torch.cuda.is_available() else t.to(device)
        t = t.float()
        if gains is None:
            return t.div_(255.0)
        scale = torch.from_numpy(np.asarray(gains, dtype=np.float32) / np.float32(255.0)).to(t.device)
        return t.mul_(scale.view(-1, 1, 1, 3)).clamp_(0.0, 1.0)

    def sample(
        self, n: int, height: int, width: int, generator: torch.Generator, device: Optional[torch.device] = None
    ) -> torch.Tensor:
        """Draw ``n`` backgrounds.

        Args:
            n: number of images.
            height, width: output size (px).
            generator: CPU :class:`torch.Generator` all randomness comes from.
            device: where the float result is made (default CPU); the same values on
                every device.

        Returns:
            (n, height, width, 3) float32 RGB in [0, 1].
        """
        h, w = int(height), int(width)
        arr = np.empty((n, h, w, 3), dtype=np.uint8)
        gains: list[Optional[np.ndarray]] = []
        for i in range(n):
            arr[i], gain = self._draw(h, w, generator)
            gains.append(gain)
        return self._finish(arr, _stack_gains(gains), device)

    def sample_many(
        self,
        generators: Sequence[torch.Generator],
        height: int,
        width: int,
        device: Optional[torch.device] = None,
    ) -> torch.Tensor:
        """One background per generator, drawn in parallel.

        Bit-identical to ``torch.cat([self.sample(1, H, W, g) for g in generators])`` (moved
        to ``device``), but the draws run on a thread pool (OpenCV decodes and resizes
        without the GIL) and the uint8 → float conversion happens on ``device`` (4× less
        host→device traffic). Use it for large render batches (e.g. one generator per
        sample index).

        Returns:
            (len(generators), H, W, 3) float32 in [0, 1] on ``device``.
        """
        h, w, n = int(height), int(width), len(generators)
        arr = np.empty((n, h, w, 3), dtype=np.uint8)
        gains: list[Optional[np.ndarray]] = [None] * n

        def one(i: int) -> None:
            arr[i], gains[i] = self._draw(h, w, generators[i])

        workers = self.threads if self.threads is not None else min(8, _available_cores())
        if n >= 4 and workers > 1:
            pool = _executor(workers)
            list(pool.map(one, range(n)))
        else:
            for i in range(n):
                one(i)
        return self._finish(arr, _stack_gains(gains), device)

    def __repr__(self) -> str:
        return f"{type(self).__name__}({len(self)} images)"


def _stack_gains(gains: Sequence[Optional[np.ndarray]]) -> Optional[np.ndarray]:
    if all(g is None for g in gains):
        return None
    return np.stack([np.ones(3, np.float32) if g is None else np.asarray(g, np.float32) for g in gains])


def _available_cores() -> int:
    return len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else (os.cpu_count() or 1)


_EXECUTORS: dict[tuple[int, int], ThreadPoolExecutor] = {}


def _executor(workers: int) -> ThreadPoolExecutor:
    """A per-process thread pool (recreated after fork: keyed by pid)."""
    key = (os.getpid(), int(workers))
    ex = _EXECUTORS.get(key)
    if ex is None:
        ex = ThreadPoolExecutor(max_workers=int(workers), thread_name_prefix="hogsa-bg")
        _EXECUTORS[key] = ex
    return ex


@contextlib.contextmanager
def _torch_threads(n: int) -> Iterator[None]:
    """Run a block with ``n`` intra-op threads (small procedural tensors are slower with more)."""
    old = torch.get_num_threads()
    if old != n:
        torch.set_num_threads(n)
    try:
        yield
    finally:
        if old != n:
            torch.set_num_threads(old)


def _uniform(generator: torch.Generator, n: int = 1) -> np.ndarray:
    return torch.rand(n, generator=generator, dtype=torch.float64).numpy()


def _crop_size(size: tuple[int, int], aspect: float, frac: float) -> tuple[float, float]:
    """Crop ``(w, h)`` of aspect ``aspect``, ``frac`` of the largest one fitting in ``size``."""
    w, h = size
    if w / h >= aspect:
        ch = h * frac
        cw = ch * aspect
    else:
        cw = w * frac
        ch = cw / aspect
    return cw, ch


def _crop_resize(img: np.ndarray, height: int, width: int, frac: float, u_x: float, u_y: float,
                 flip: bool) -> np.ndarray:
    """The crop of ``img`` (``frac`` of the largest crop, position ``u_x, u_y`` in [0, 1))
    resized to ``(height, width)`` (area filter when shrinking, bilinear when enlarging)."""
    h, w = img.shape[:2]
    cw, ch = _crop_size((w, h), width / height, frac)
    cw_i, ch_i = max(1, min(w, int(round(cw)))), max(1, min(h, int(round(ch))))
    x0 = min(int(math.floor(u_x * (w - cw_i + 1))), w - cw_i)
    y0 = min(int(math.floor(u_y * (h - ch_i + 1))), h - ch_i)
    patch = img[y0:y0 + ch_i, x0:x0 + cw_i]
    interp = cv2.INTER_AREA if (cw_i > width or ch_i > height) else cv2.INTER_LINEAR
    out = cv2.resize(patch, (width, height), interpolation=interp)
    return out[:, ::-1] if flip else out


class _ImageListSource(BackgroundSource):
    """Shared crop/decode logic of sources backed by a list of image files."""

    def __init__(
        self,
        paths: Sequence[Path],
        sizes: Optional[Sequence[Optional[tuple[int, int]]]] = None,
        crop: CropSpec = CropSpec(),
        cache_bytes: int = 512 * 2**20,
        reduced_decode: bool = True,
    ) -> None:
        self.paths = [Path(p) for p in paths]
        self.sizes = list(sizes) if sizes is not None else [None] * len(self.paths)
        self.crop = crop
        self.cache = ImageCache(cache_bytes)
        self.reduced_decode = bool(reduced_decode)
        self._bad: set[int] = set()

    def __len__(self) -> int:
        return len(self.paths)

    # -- decoding ------------------------------------------------------------------------

    def _decode(self, idx: int, reduce: int) -> Optional[np.ndarray]:
        key = (idx, reduce)
        img = self.cache.get(key)
        if img is not None:
            return img
        path = self.paths[idx]
        flag = {1: cv2.IMREAD_COLOR, 2: cv2.IMREAD_REDUCED_COLOR_2,
                4: cv2.IMREAD_REDUCED_COLOR_4, 8: cv2.IMREAD_REDUCED_COLOR_8}[reduce]
        bgr = cv2.imread(str(path), flag)
        if bgr is None or bgr.ndim != 3 or bgr.shape[0] < 2 or bgr.shape[1] < 2:
            return None
        img = np.ascontiguousarray(cv2.cvtColor(bgr, cv2.COLOR_BGR2RGB))
        self.cache.put(key, img)
        return img

    def _reduction(self, idx: int, crop_w: float, crop_h: float, width: int, height: int) -> int:
        """Largest JPEG reduction keeping the crop at least at output resolution."""
        if not self.reduced_decode or self.sizes[idx] is None:
            return 1
        if self.paths[idx].suffix.lower() not in (".jpg", ".jpeg"):
            return 1
        r = 1
        for k in (2, 4, 8):
            if crop_w / k >= width and crop_h / k >= height:
                r = k
        return r

    # -- sampling ------------------------------------------------------------------------

    def _draw(self, height: int, width: int, generator: torch.Generator) -> tuple[np.ndarray, Optional[np.ndarray]]:
        return self._one(height, width, generator), None

    def _one(self, height: int, width: int, generator: torch.Generator) -> np.ndarray:
        if not self.paths:
            raise AssetError("<backgrounds>", "no background images to draw from")
        for _ in range(_MAX_REDRAWS):
            idx = int(torch.randint(len(self.paths), (1,), generator=generator).item())
            u_frac, u_x, u_y, u_flip = _uniform(generator, 4)
            if idx in self._bad:
                continue
            size = self.sizes[idx]
            aspect = width / height
            lo, hi = math.log(self.crop.min_fraction), math.log(self.crop.max_fraction)
            frac = math.exp(lo + (hi - lo) * u_frac)
            if size is not None:
                reduce = self._reduction(idx, *_crop_size(size, aspect, frac), width, height)
            else:
                reduce = 1
            img = self._decode(idx, reduce)
            if img is None:
                self._bad.add(idx)
                warnings.warn(f"background image unreadable, skipped: {self.paths[idx]}", RuntimeWarning,
                              stacklevel=3)
                continue
            h, w = img.shape[:2]
            if size is None:
                self.sizes[idx] = (w, h)
            return _crop_resize(img, height, width, frac, u_x, u_y, self.crop.hflip and u_flip < 0.5)
        raise AssetError(self.paths[0].parent, f"{_MAX_REDRAWS} background draws in a row were unreadable "
                         f"({len(self._bad)} bad images so far)")


# --------------------------------------------------------------------------------------
# COCO
# --------------------------------------------------------------------------------------


def _load_coco(ann_file: Path):
    """A ``pycocotools.coco.COCO`` of ``ann_file``; :class:`AssetError` on bad files."""
    from pycocotools.coco import COCO

    data = read_json(ann_file)
    if not isinstance(data, dict):
        raise AssetError(ann_file, "not a COCO instances file (top level is not an object)")
    for key in ("images", "categories"):
        if not isinstance(data.get(key), list):
            raise AssetError(ann_file, f"not a COCO instances file (no {key!r} list)")
    if "annotations" in data and not isinstance(data["annotations"], list):
        raise AssetError(ann_file, "not a COCO instances file ('annotations' is not a list)")
    for i, im in enumerate(data["images"]):
        if not isinstance(im, dict) or "id" not in im or "file_name" not in im:
            raise AssetError(ann_file, f"images[{i}] lacks 'id' or 'file_name'")
    for i, c in enumerate(data["categories"]):
        if not isinstance(c, dict) or "id" not in c or "name" not in c:
            raise AssetError(ann_file, f"categories[{i}] lacks 'id' or 'name'")
    for i, a in enumerate(data.get("annotations", [])):
        if not isinstance(a, dict) or "image_id" not in a or "category_id" not in a:
            raise AssetError(ann_file, f"annotations[{i}] lacks 'image_id' or 'category_id'")
    coco = COCO()
    coco.dataset = data
    with contextlib.redirect_stdout(io.StringIO()):  # pycocotools prints progress
        coco.createIndex()
    return coco


#: in-process memo of parsed + filtered COCO annotation files (the 450 MB train2017 file
#: takes ~20 s to parse): key (path, size, mtime, categories, exclude_person)
_COCO_MEMO: dict[tuple, tuple[list[int], list[str], list[Optional[tuple[int, int]]]]] = {}


def default_cache_dir() -> Path:
    """``$HOGSA_CACHE`` or ``~/.cache/hogsa_loader``."""
    env = os.environ.get("HOGSA_CACHE")
    return Path(env) if env else Path.home() / ".cache" / "hogsa_loader"


def _coco_selection(
    ann: Path, categories: Optional[Sequence[str]], exclude_person: bool, index_cache: Optional[Path] = None
) -> tuple[list[int], list[str], list[Optional[tuple[int, int]]]]:
    """``(image ids, file names, (w, h) sizes)`` of the COCO images passing the filters.

    Memoised in the process, and on disk in ``index_cache`` (a small JSON keyed by the
    annotation file's path, size and mtime and the filters) so that DataLoader workers and
    later runs skip parsing the annotation file."""
    names = None if categories is None else ([categories] if isinstance(categories, str) else list(categories))
    st = ann.stat()
    key = (str(ann.resolve()), st.st_size, st.st_mtime_ns, None if names is None else tuple(names),
           bool(exclude_person))
    if key in _COCO_MEMO:
        return _COCO_MEMO[key]
    cache_file = None
    if index_cache is not None:
        digest = hashlib.sha256(json.dumps([str(k) for k in key]).encode()).hexdigest()[:20]
        cache_file = Path(index_cache) / f"coco_selection_{digest}.json"
        try:
            with open(cache_file, "r", encoding="utf-8") as fh:
                rec = json.load(fh)
            if rec.get("key") == [str(k) for k in key]:
                sel = (rec["ids"], rec["files"], [tuple(z) if z else None for z in rec["sizes"]])
                _COCO_MEMO.clear()
                _COCO_MEMO[key] = sel
                return sel
        except (OSError, ValueError, KeyError, TypeError):
            pass
    coco = _load_coco(ann)
    img_ids = sorted(coco.imgs)
    if not img_ids:
        raise AssetError(ann, "COCO annotation file lists no images")
    known = {c["name"]: c["id"] for c in coco.loadCats(coco.getCatIds())}
    if names is not None:
        unknown = [c for c in names if c not in known]
        if unknown:
            raise AssetError(ann, f"unknown COCO categories {unknown}; known: {sorted(known)}")
        keep: set[int] = set()
        for c in names:
            keep.update(coco.getImgIds(catIds=[known[c]]))
        img_ids = [i for i in img_ids if i in keep]
    if exclude_person and COCO_PERSON in known:
        people = set(coco.getImgIds(catIds=[known[COCO_PERSON]]))
        img_ids = [i for i in img_ids if i not in people]
    if not img_ids:
        raise AssetError(ann, f"no COCO image left after filtering (categories={names}, "
                         f"exclude_person={exclude_person})")
    files = [str(coco.imgs[i]["file_name"]) for i in img_ids]
    sizes: list[Optional[tuple[int, int]]] = []
    for i in img_ids:
        w, h = coco.imgs[i].get("width"), coco.imgs[i].get("height")
        sizes.append((int(w), int(h)) if w and h else None)
    _COCO_MEMO.clear()  # keep one selection: the lists of train2017 are ~30 MB
    _COCO_MEMO[key] = (img_ids, files, sizes)
    if cache_file is not None:
        try:
            cache_file.parent.mkdir(parents=True, exist_ok=True)
            tmp = cache_file.with_name(f".{cache_file.name}.{os.getpid()}")
            with open(tmp, "w", encoding="utf-8") as fh:
                json.dump({"key": [str(k) for k in key], "ids": img_ids, "files": files,
                           "sizes": [list(z) if z else None for z in sizes]}, fh)
            os.replace(tmp, cache_file)
        except OSError as exc:  # a read-only cache folder only costs speed
            log.debug("cannot write COCO selection cache %s: %s", cache_file, exc)
    return _COCO_MEMO[key]


def _find_coco_image_dir(root: Path, split: str, first_file: Optional[str]) -> Path:
    candidates = [root / "images" / split, root / split, root / "images", root]
    for c in candidates:
        if c.is_dir() and (first_file is None or (c / first_file).is_file()):
            return c
    raise AssetError(root, "no COCO image folder: looked for " + ", ".join(str(c) for c in candidates)
                     + (f" holding {first_file}" if first_file else ""))


class CocoBackgrounds(_ImageListSource):
    """Random crops of COCO images (read through ``pycocotools``).

    Args:
        coco_root: COCO folder holding ``images/<split>/`` (or ``<split>/``) and
            ``annotations/instances_<split>.json``.
        ann_file: annotation file; default ``<coco_root>/annotations/instances_<split>.json``.
        image_dir: image folder; default found under ``coco_root`` (above), or the
            annotation file's ``../images/<split>`` when only ``ann_file`` is given.
        categories: keep only images with at least one instance of one of these category
            names (e.g. ``["dining table", "kitchen"]``); None = all images.
        exclude_person: drop images containing the category ``"person"`` (people and
            their hands would compete with the rendered hands).
        split: ``"train2017"`` etc.
        crop: random crop settings.
        cache_bytes: LRU capacity of decoded images (per process).
        reduced_decode: decode large JPEGs at 1/2, 1/4 or 1/8 scale when the crop allows.
        index_cache: folder of the on-disk cache of the filtered image list (parsing
            ``instances_train2017.json`` takes ~20 s and GBs of memory); True = default
            (``$HOGSA_CACHE`` or ``~/.cache/hogsa_loader``), False/None = off.

    Raises:
        AssetError: missing or malformed annotation file, missing image folder, unknown
            category name, or no image left after filtering.
    """

    kind = "coco"

    def __init__(
        self,
        coco_root: Optional[PathLike] = None,
        ann_file: Optional[PathLike] = None,
        image_dir: Optional[PathLike] = None,
        categories: Optional[Sequence[str]] = None,
        exclude_person: bool = False,
        split: str = "train2017",
        crop: CropSpec = CropSpec(),
        cache_bytes: int = 512 * 2**20,
        reduced_decode: bool = True,
        index_cache: Union[bool, PathLike, None] = True,
    ) -> None:
        if coco_root is None and ann_file is None:
            raise ValueError("CocoBackgrounds needs coco_root or ann_file")
        root = Path(coco_root) if coco_root is not None else None
        if root is not None and not root.is_dir():
            raise AssetError(root, "COCO root folder is missing")
        ann = Path(ann_file) if ann_file is not None else root / "annotations" / f"instances_{split}.json"
        if not ann.is_file():
            raise AssetError(ann, "COCO annotation file is missing")
        cache_dir = (default_cache_dir() if index_cache is True else
                     None if index_cache in (None, False) else Path(index_cache))  # type: ignore[arg-type]
        img_ids, files, sizes = _coco_selection(ann, categories, exclude_person, cache_dir)
        first = files[0]
        if image_dir is not None:
            idir = Path(image_dir)
            if not idir.is_dir():
                raise AssetError(idir, "COCO image folder is missing")
        elif root is not None:
            idir = _find_coco_image_dir(root, split, first)
        else:
            idir = _find_coco_image_dir(ann.parent.parent, split, first)
        if not (idir / first).is_file():
            raise AssetError(idir / first, "COCO image listed in the annotations is missing")

        super().__init__([idir / f for f in files], sizes, crop, cache_bytes, reduced_decode)
        self.ann_file = ann
        self.image_dir = idir
        self.image_ids = img_ids
        self.categories = None if categories is None else list(categories)
        self.exclude_person = bool(exclude_person)


# --------------------------------------------------------------------------------------
# Folder
# --------------------------------------------------------------------------------------


class FolderBackgrounds(_ImageListSource):
    """Random crops of the images in a folder (``.jpg``, ``.jpeg``, ``.png``, ``.bmp``, ``.webp``).

    Args:
        folder: the folder; sub-folders are searched too when ``recursive``.
        recursive: search sub-folders.
        crop: random crop settings.
        cache_bytes: LRU capacity of decoded images (per process).

    Raises:
        AssetError: missing folder or no image in it.
    """

    kind = "folder"

    def __init__(
        self,
        folder: PathLike,
        recursive: bool = True,
        crop: CropSpec = CropSpec(),
        cache_bytes: int = 512 * 2**20,
    ) -> None:
        folder = Path(folder)
        if not folder.is_dir():
            raise AssetError(folder, "background image folder is missing")
        it = folder.rglob("*") if recursive else folder.iterdir()
        paths = sorted(p for p in it if p.is_file() and p.suffix.lower() in IMAGE_EXTENSIONS)
        if not paths:
            raise AssetError(folder, f"no background images ({', '.join(IMAGE_EXTENSIONS)}) in folder")
        # sizes unknown: always decode at full scale (a reduction learnt from the cache
        # would make results depend on what was drawn before)
        super().__init__(paths, None, crop, cache_bytes, reduced_decode=False)
        self.folder = folder


# --------------------------------------------------------------------------------------
# Procedural fallback
# --------------------------------------------------------------------------------------


class ProceduralBackgrounds(BackgroundSource):
    """Deterministic procedural backgrounds (the fallback when no image is given).

    Textures come from five families, in random colours:

    0. linear gradient between two colours at a random angle;
    1. multi-octave value noise (3–5 octaves of bicubically upsampled random grids) mapped
       onto a two-colour palette — cloth, stone, foliage-like textures;
    2. stripes or checkers (random period, angle, softness) — tiles, fabric;
    3. soft blobs: 3–8 Gaussian ellipses of random colours on a plain base — clutter;
    4. a "table top": a planar wood-like grain (stretched noise) under a vertical
       gradient (wall/plane horizon).

    Every texture gets a radial lighting falloff and per-pixel sensor grain.

    Speed: generating a texture costs tens of ms, so by default a **pool** of
    ``pool_size`` textures of side ``tile`` is used: texture ``k`` is generated on first
    use from a generator seeded with ``(pool_seed, k)`` alone (so it is the same in every
    process, whatever was drawn before) and kept; each sample draws a texture, a random
    crop (``crop``), a flip and a per-channel colour gain (``colour_jitter``) from the
    caller's generator — about a millisecond per image once the pool is warm.
    ``pool_size=0`` generates every image from the caller's generator directly.

    Everything is deterministic given the generator. These are not photographs: use COCO
    or a folder of photos for training.

    Args:
        pool_size: textures in the pool (0 = no pool).
        tile: side of the pool textures.
        pool_seed: seed of the pool.
        crop: random crop settings of pool textures.
        colour_jitter: per-channel gains ``U(1 − j, 1 + j)`` applied to pool crops.
        grain: std of the additive per-pixel noise.
    """

    kind = "procedural"
    FAMILIES: tuple[str, ...] = ("gradient", "noise", "pattern", "blobs", "table")

    def __init__(
        self,
        pool_size: int = 64,
        tile: int = 320,
        pool_seed: int = 0,
        crop: CropSpec = CropSpec(min_fraction=0.5),
        colour_jitter: float = 0.15,
        grain: float = 0.015,
    ) -> None:
        self.pool_size = int(pool_size)
        self.tile = int(tile)
        self.pool_seed = int(pool_seed)
        self.crop = crop
        self.colour_jitter = float(colour_jitter)
        self.grain = float(grain)
        self._pool: dict[int, np.ndarray] = {}

    def __len__(self) -> int:
        return self.pool_size

    def __repr__(self) -> str:
        return f"ProceduralBackgrounds(pool_size={self.pool_size}, tile={self.tile}, families={self.FAMILIES})"

    def __getstate__(self) -> dict:
        state = dict(self.__dict__)
        state["_pool"] = {}  # regenerated lazily (deterministically) in each process
        return state

    def warm(self) -> "ProceduralBackgrounds":
        """Generate the whole pool now (e.g. before a timed run or before forking workers)."""
        for k in range(self.pool_size):
            self.texture(k)
        return self

    def texture(self, k: int) -> np.ndarray:
        """Pool texture ``k``: (tile, tile, 3) uint8 RGB (generated on first use)."""
        tex = self._pool.get(k)
        if tex is None:
            with _TEXTURE_LOCK:  # one generator at a time (torch thread setting is global)
                tex = self._pool.get(k)
                if tex is None:
                    seed = int(np.random.SeedSequence([self.pool_seed, int(k), 0x70C]).generate_state(1, np.uint64)[0]
                               >> 1)
                    g = torch.Generator().manual_seed(seed)
                    with _torch_threads(1):
                        img = self._one(self.tile, self.tile, g)
                    tex = (img * 255.0).round_().to(torch.uint8).numpy()
                    self._pool[k] = tex
        return tex

    @staticmethod
    def _grid(h: int, w: int) -> tuple[torch.Tensor, torch.Tensor]:
        ys = (torch.arange(h, dtype=torch.float32) + 0.5) / h
        xs = (torch.arange(w, dtype=torch.float32) + 0.5) / w
        return torch.meshgrid(ys, xs, indexing="ij")

    @staticmethod
    def _noise(h: int, w: int, g: torch.Generator, octaves: int, base: int, aniso: float = 1.0) -> torch.Tensor:
        """(h, w) value noise in ≈[0, 1]."""
        acc = torch.zeros(1, 1, h, w)
        amp, total = 1.0, 0.0
        for o in range(octaves):
            gh = max(2, int(base * 2**o))
            gw = max(2, int(base * 2**o * aniso))
            grid = torch.rand(1, 1, gh, gw, generator=g)
            acc += amp * F.interpolate(grid, size=(h, w), mode="bicubic", align_corners=False)
            total += amp
            amp *= 0.5
        n = (acc / total)[0, 0]
        lo, hi = n.min(), n.max()
        return (n - lo) / (hi - lo).clamp_min(1e-6)

    @staticmethod
    def _colour(g: torch.Generator) -> torch.Tensor:
        """A random RGB colour, saturation kept moderate (indoor-like palettes)."""
        base = torch.rand(3, generator=g)
        grey = base.mean()
        sat = 0.2 + 0.6 * torch.rand(1, generator=g)
        val = 0.15 + 0.8 * torch.rand(1, generator=g)
        c = grey + sat * (base - grey)
        return (c / c.max().clamp_min(1e-3) * val).clamp(0, 1)

    def _one(self, h: int, w: int, g: torch.Generator) -> torch.Tensor:
        yy, xx = self._grid(h, w)
        fam = int(torch.randint(len(self.FAMILIES), (1,), generator=g).item())
        c0, c1 = self._colour(g), self._colour(g)
        if fam == 0:
            ang = float(torch.rand(1, generator=g)) * 2 * math.pi
            t = (xx - 0.5) * math.cos(ang) + (yy - 0.5) * math.sin(ang) + 0.5
            t = t.clamp(0, 1)[..., None]
            img = c0 * (1 - t) + c1 * t
        elif fam == 1:
            octv = 3 + int(torch.randint(3, (1,), generator=g).item())
            base = 2 + int(torch.randint(6, (1,), generator=g).item())
            t = self._noise(h, w, g, octv, base)[..., None]
            gamma = 0.5 + 1.5 * float(torch.rand(1, generator=g))
            img = c0 * (1 - t**gamma) + c1 * t**gamma
        elif fam == 2:
            ang = float(torch.rand(1, generator=g)) * math.pi
            period = 0.03 + 0.25 * float(torch.rand(1, generator=g))
            soft = 0.02 + 0.3 * float(torch.rand(1, generator=g))
            checker = bool(torch.rand(1, generator=g) < 0.4)
            u = ((xx - 0.5) * math.cos(ang) + (yy - 0.5) * math.sin(ang)) / period
            s = torch.sin(u * 2 * math.pi)
            if checker:
                v = ((yy - 0.5) * math.cos(ang) - (xx - 0.5) * math.sin(ang)) / period
                s = s * torch.sin(v * 2 * math.pi)
            t = torch.sigmoid(s / soft)[..., None]
            img = c0 * (1 - t) + c1 * t
        elif fam == 3:
            img = c0.expand(h, w, 3).clone()
            k = 3 + int(torch.randint(6, (1,), generator=g).item())
            for _ in range(k):
                cx, cy = torch.rand(2, generator=g).tolist()
                sx, sy = (0.05 + 0.3 * torch.rand(2, generator=g)).tolist()
                ang = float(torch.rand(1, generator=g)) * math.pi
                dx, dy = xx - cx, yy - cy
                u = dx * math.cos(ang) + dy * math.sin(ang)
                v = -dx * math.sin(ang) + dy * math.cos(ang)
                a = torch.exp(-0.5 * ((u / sx) ** 2 + (v / sy) ** 2))[..., None]
                a = a * (0.5 + 0.5 * float(torch.rand(1, generator=g)))
                img = img * (1 - a) + self._colour(g) * a
        else:
            horizon = 0.2 + 0.5 * float(torch.rand(1, generator=g))
            wood = self._noise(h, w, g, 4, 3, aniso=0.15)
            rings = 0.5 + 0.5 * torch.sin(wood * (10 + 30 * float(torch.rand(1, generator=g))))
            t = (0.6 * wood + 0.4 * rings)[..., None]
            table = c0 * (0.75 + 0.25 * t)
            wall_t = (yy / max(horizon, 1e-3)).clamp(0, 1)[..., None]
            wall = c1 * (0.7 + 0.3 * wall_t)
            edge = torch.sigmoid((yy - horizon) / 0.01)[..., None]
            img = wall * (1 - edge) + table * edge
        # lighting falloff and grain
        lx, ly = torch.rand(2, generator=g).tolist()
        strength = 0.45 * float(torch.rand(1, generator=g))
        r2 = (xx - lx) ** 2 + (yy - ly) ** 2
        img = img * (1 - strength * r2.clamp(0, 1))[..., None]
        img = img + self.grain * torch.randn(h, w, 3, generator=g)
        return img.clamp(0, 1)

    def _draw(self, height: int, width: int, generator: torch.Generator) -> tuple[np.ndarray, Optional[np.ndarray]]:
        k = int(torch.randint(self.pool_size, (1,), generator=generator).item())
        u = _uniform(generator, 7)
        lo, hi = math.log(self.crop.min_fraction), math.log(self.crop.max_fraction)
        frac = math.exp(lo + (hi - lo) * u[0])
        img = _crop_resize(self.texture(k), height, width, frac, u[1], u[2], self.crop.hflip and u[3] < 0.5)
        gain = (1.0 - self.colour_jitter + 2.0 * self.colour_jitter * u[4:7]).astype(np.float32)
        return img, gain

    def _direct(self, n: int, h: int, w: int, generator: torch.Generator) -> torch.Tensor:
        out = torch.empty(n, h, w, 3, dtype=torch.float32)
        with _TEXTURE_LOCK, _torch_threads(1):
            for i in range(n):
                out[i] = self._one(h, w, generator)
        return out

    def sample(
        self, n: int, height: int, width: int, generator: torch.Generator, device: Optional[torch.device] = None
    ) -> torch.Tensor:
        """See :meth:`BackgroundSource.sample`: ``(n, H, W, 3)`` float32 in [0, 1]."""
        if self.pool_size <= 0:
            out = self._direct(n, int(height), int(width), generator)
            return out if device is None else out.to(device)
        return super().sample(n, height, width, generator, device)

    def sample_many(
        self,
        generators: Sequence[torch.Generator],
        height: int,
        width: int,
        device: Optional[torch.device] = None,
    ) -> torch.Tensor:
        """See :meth:`BackgroundSource.sample_many`."""
        if self.pool_size <= 0:
            out = torch.cat([self._direct(1, int(height), int(width), g) for g in generators])
            return out if device is None else out.to(device)
        return super().sample_many(generators, height, width, device)


# --------------------------------------------------------------------------------------
# Factory
# --------------------------------------------------------------------------------------


def make_backgrounds(
    coco_root: Optional[PathLike] = None,
    coco_ann: Optional[PathLike] = None,
    folder: Optional[PathLike] = None,
    categories: Optional[Sequence[str]] = None,
    exclude_person: bool = False,
    image_dir: Optional[PathLike] = None,
    crop: CropSpec = CropSpec(),
    cache_bytes: int = 512 * 2**20,
    index_cache: Union[bool, PathLike, None] = True,
) -> BackgroundSource:
    """The background source the loader's arguments ask for.

    * ``coco_root`` and/or ``coco_ann`` → :class:`CocoBackgrounds` (``categories``,
      ``exclude_person``, ``image_dir`` and ``index_cache`` apply);
    * else ``folder`` → :class:`FolderBackgrounds`;
    * else → :class:`ProceduralBackgrounds`, with a one-time warning (per process).

    Giving both a COCO source and a folder is an error.

    Raises:
        AssetError: missing or malformed files (see the classes).
    """
    global _FALLBACK_WARNED
    if (coco_root is not None or coco_ann is not None) and folder is not None:
        raise ValueError("give either a COCO source (coco_root/coco_ann) or a folder, not both")
    if coco_root is not None or coco_ann is not None:
        return CocoBackgrounds(coco_root, coco_ann, image_dir=image_dir, categories=categories,
                               exclude_person=exclude_person, crop=crop, cache_bytes=cache_bytes,
                               index_cache=index_cache)
    if categories is not None:
        raise ValueError("categories filter COCO images; give coco_root/coco_ann")
    if folder is not None:
        return FolderBackgrounds(folder, crop=crop, cache_bytes=cache_bytes)
    if not _FALLBACK_WARNED:
        _FALLBACK_WARNED = True
        warnings.warn("no background images given (coco_root / coco_ann / folder): using procedural "
                      "backgrounds (gradients, noise, patterns); pass COCO for photoreal training data",
                      UserWarning, stacklevel=2)
    return ProceduralBackgrounds()

