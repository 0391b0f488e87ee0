"""Background-source base classes: image cache, random crops, image lists, folders.

Every source subclasses :class:`BackgroundSource` (draws from an explicit generator, so
results are deterministic; picklable for DataLoader workers). Image sources
(:class:`FolderBackgrounds` here, :class:`~hogsa_loader.compose.coco.CocoBackgrounds`) share
:class:`_ImageListSource` (random crops with :class:`CropSpec`, decoding, the per-process
:class:`ImageCache`).
"""

from __future__ import annotations

import contextlib
import math
import os
import threading
import warnings
from collections import OrderedDict
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from pathlib import Path
from typing import Iterator, Optional, Sequence

import cv2
import numpy as np
import torch

from hogsa_loader.errors import AssetError, PathLike
from hogsa_loader.io.images import read_image
from hogsa_loader.system import available_cores

__all__ = ["BackgroundSource", "CropSpec", "FolderBackgrounds", "IMAGE_EXTENSIONS", "ImageCache"]

#: File endings :class:`FolderBackgrounds` reads (case-insensitive).
IMAGE_EXTENSIONS: tuple[str, ...] = (".jpg", ".jpeg", ".png", ".bmp", ".webp")

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

    Every source draws ``n`` backgrounds of a requested size from an explicit
    :class:`torch.Generator`, so the same generator state gives the same images, whatever the
    cache holds or which DataLoader worker asks.

    Sources are picklable (they hold paths and sizes, not open handles), so they can live in
    DataLoader workers; each worker then has its own cache.
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

    def camera_plate(self, subject: str, view: int, box_full: np.ndarray, size: int) -> Optional[np.ndarray]:
        """The backdrop dataset camera (``subject``, ``view``) sees inside the crop box
        ``box_full`` ((3,) ``(cx, cy, scale)`` in its full-image pixels), as (size, size, 3) uint8
        RGB, for sources that know the dataset's cameras; None (here): draw with :meth:`sample`."""
        return None

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
        self, generators: Sequence[torch.Generator], height: int, width: int, device: Optional[torch.device] = None
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

        workers = self.threads if self.threads is not None else min(8, available_cores())
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


def _crop_resize(
    img: np.ndarray, height: int, width: int, frac: float, u_x: float, u_y: float, flip: bool
) -> np.ndarray:
    """The crop of ``img`` (``frac`` of the largest crop, position ``u_x, u_y`` in [0, 1))
    resized to ``(height, width)`` (area filter when shrinking, bilinear when enlarging)."""
    h, w = img.shape[:2]
    cw, ch = _crop_size((w, h), width / height, frac)
    cw_i, ch_i = max(1, min(w, int(round(cw)))), max(1, min(h, int(round(ch))))
    x0 = min(int(math.floor(u_x * (w - cw_i + 1))), w - cw_i)
    y0 = min(int(math.floor(u_y * (h - ch_i + 1))), h - ch_i)
    patch = img[y0 : y0 + ch_i, x0 : x0 + cw_i]
    interp = cv2.INTER_AREA if (cw_i > width or ch_i > height) else cv2.INTER_LINEAR
    out = cv2.resize(patch, (width, height), interpolation=interp)
    return out[:, ::-1] if flip else out


class _ImageListSource(BackgroundSource):
    """Shared crop/decode logic of sources backed by a list of image files.

    Image sources (:class:`FolderBackgrounds` here,
    :class:`~hogsa_loader.compose.coco.CocoBackgrounds`) share it: a random image, a random crop
    of random scale (:class:`CropSpec`), an optional horizontal flip; decoded images are kept in
    a per-process LRU cache bounded in bytes (:class:`ImageCache`), decoded with OpenCV, COCO
    images at a reduced JPEG scale (``IMREAD_REDUCED_COLOR_{2,4,8}``) when the crop is large
    enough that full resolution is wasted (chosen from the image size known at construction and
    the drawn crop, never from the cache or what was decoded before, so results are
    deterministic). An unreadable image is skipped for the next readable one in list order (with
    the same crop draws), so a bad file changes only the draws that land on it; only a list with
    no readable image at all raises.

    Throughput notes (1 CPU thread, measured on a shared 2-core EPYC): a COCO/folder draw
    from the cache is a crop + resize + float conversion (≈ 1–3 ms at 336²); a cache miss adds
    reading and decoding the JPEG (≈ 3–8 ms for a 640×480 image, less at reduced scale).
    """

    def __init__(
        self,
        paths: Sequence[Path],
        sizes: Optional[Sequence[Optional[tuple[int, int]]]] = None,
        crop: CropSpec = CropSpec(),
        cache_bytes: int = 512 * 2**20,
        reduced_decode: bool = True,
        origin: Optional[PathLike] = None,
    ) -> None:
        self.paths = [Path(p) for p in paths]
        #: (w, h) per image as known at construction (None: unknown, decoded at full size);
        #: never filled in at run time, which would make the decode depend on earlier draws
        self.sizes = list(sizes) if sizes is not None else [None] * len(self.paths)
        #: what errors name: the folder or annotation file the list came from
        self.origin = (
            Path(origin) if origin is not None else (self.paths[0].parent if self.paths else Path("<backgrounds>"))
        )
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
        flag = {
            1: cv2.IMREAD_COLOR,
            2: cv2.IMREAD_REDUCED_COLOR_2,
            4: cv2.IMREAD_REDUCED_COLOR_4,
            8: cv2.IMREAD_REDUCED_COLOR_8,
        }[reduce]
        try:  # the header's size is checked before decoding (a small file can announce a huge image)
            bgr = read_image(path, flag)
        except AssetError:
            return None
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
            raise AssetError(self.origin, "no background images to draw from")
        n = len(self.paths)
        first = int(torch.randint(n, (1,), generator=generator).item())
        u_frac, u_x, u_y, u_flip = _uniform(generator, 4)
        lo, hi = math.log(self.crop.min_fraction), math.log(self.crop.max_fraction)
        frac = math.exp(lo + (hi - lo) * u_frac)
        for k in range(n):  # the drawn image, or the next readable one (same draws either way)
            idx = (first + k) % n
            if idx in self._bad:
                continue
            size = self.sizes[idx]
            reduce = 1 if size is None else self._reduction(idx, *_crop_size(size, width / height, frac), width, height)
            img = self._decode(idx, reduce)
            if img is None:
                self._bad.add(idx)
                warnings.warn(
                    f"background image unreadable (or smaller than 2x2 px), skipped: {self.paths[idx]}",
                    RuntimeWarning,
                    stacklevel=3,
                )
                continue
            return _crop_resize(img, height, width, frac, u_x, u_y, self.crop.hflip and u_flip < 0.5)
        raise AssetError(self.origin, f"none of the {n} background images is readable (e.g. {self.paths[first]})")


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
        self, folder: PathLike, recursive: bool = True, crop: CropSpec = CropSpec(), cache_bytes: int = 512 * 2**20
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
        super().__init__(paths, None, crop, cache_bytes, reduced_decode=False, origin=folder)
        self.folder = folder
