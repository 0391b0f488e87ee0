"""Clean background plates of a dataset's static cameras, assembled from its own frames.

A synthetic sample composited on photographs differs from the dataset's real frames in its
background long before its hands do (colour, brightness, floor, perspective).
:func:`build_plates` (settings: :class:`PlateConfig`) writes one PNG per (subject, view) plus
``plates.json`` into a folder that :class:`~hogsa_loader.compose.sources.FolderBackgrounds`
reads directly; its docstring describes how the plates are made.
"""

# ruff: noqa: UP045  (Optional[...] fields: hogsa_loader.cli.dataclass_args reads typing.Optional)

from __future__ import annotations

import hashlib
import json
import warnings
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Callable, Literal, Optional, Sequence

import cv2
import numpy as np

from hogsa_loader.assets.arctic import ArcticRoot
from hogsa_loader.assets.arctic_processing import crop_boxes
from hogsa_loader.assets.conventions import BBOX_PIXELS_PER_SCALE, CROP_ENLARGE, cropped_intrinsics, render_intrinsics
from hogsa_loader.compose.plate_backgrounds import PLATES_MANIFEST, crop_to_plate
from hogsa_loader.errors import AssetError, UsageError
from hogsa_loader.io.atomic import atomic_write
from hogsa_loader.render.part_masks import pose_meshes, render_camera_mask

__all__ = ["PLATES_MANIFEST", "PlateConfig", "build_plates", "crop_to_plate", "data_fingerprint"]


@dataclass
class PlateConfig:
    """Settings of :func:`build_plates` (``hogsa plates`` derives one flag per field)."""

    data: Optional[str] = field(default=None, metadata={"help": "ARCTIC(-format) data root", "required": True})
    out: Optional[str] = field(default=None, metadata={"help": "output folder of the plates", "required": True})
    subjects: tuple[str, ...] = field(
        default=(), metadata={"help": "subjects (default: the training subjects of protocol p1)"}
    )
    views: tuple[int, ...] = field(default=(1, 2, 3, 4, 5, 6, 7, 8), metadata={"help": "allocentric views"})
    width: int = field(default=960, metadata={"help": "plate width in pixels (the full frame scaled)"})
    frames_per_sequence: int = field(default=12, metadata={"help": "frames per sequence and view, evenly spaced"})
    margin: int = field(default=3, metadata={"help": "plate pixels of background dropped around the hands/object"})
    masks: Literal["auto", "files", "render"] = field(
        default="auto", metadata={"help": "foreground masks: mask files, rendered from the annotations, or auto"}
    )
    min_coverage: float = field(
        default=0.5, metadata={"help": "skip a plate when less of its box than this was seen as background"}
    )
    quiet: bool = field(default=False, metadata={"help": "no progress messages"})

    def check(self) -> None:
        """Raise :class:`UsageError` for settings that cannot work."""
        if self.width < 16:
            raise UsageError(f"--width must be at least 16, got {self.width}")
        if self.frames_per_sequence < 1:
            raise UsageError(f"--frames-per-sequence must be positive, got {self.frames_per_sequence}")
        if self.margin < 0:
            raise UsageError(f"--margin must be non-negative, got {self.margin}")
        if not 0.0 <= self.min_coverage <= 1.0:
            raise UsageError(f"--min-coverage must be in [0, 1], got {self.min_coverage}")
        bad = [v for v in self.views if not 1 <= v <= 8]
        if bad or not self.views:
            raise UsageError(f"--views must be allocentric (static) views 1..8, got {list(self.views)}")


def _frames(num: int, k: int) -> list[int]:
    """``k`` evenly spaced frame indices of ``num`` (all when ``num <= k``)."""
    if num <= k:
        return list(range(num))
    return sorted(set(np.linspace(0, num - 1, k).round().astype(int).tolist()))


@dataclass
class _Sample:
    """One frame's background in plate pixels: ``img`` (h, w, 3) uint8 and ``ok`` (h, w)
    bool (background seen) cover rows ``y0:y0+h`` and columns ``x0:x0+w`` of the plate."""

    y0: int
    x0: int
    img: np.ndarray
    ok: np.ndarray


def _median(samples: Sequence[_Sample], hw: tuple[int, int], rows: int = 32) -> tuple[np.ndarray, np.ndarray]:
    """Per-pixel median of the valid samples: (H, W, 3) uint8 and the (H, W) sample count.

    Rows are processed in bands of ``rows``; a band stacks only the samples whose window
    meets it (memory ~ samples per band x band size)."""
    h, w = hw
    plate = np.zeros((h, w, 3), np.uint8)
    count = np.zeros((h, w), np.int64)
    for r0 in range(0, h, rows):
        r1 = min(h, r0 + rows)
        hit = [sm for sm in samples if sm.y0 < r1 and sm.y0 + sm.ok.shape[0] > r0]
        if not hit:
            continue
        img = np.full((len(hit), r1 - r0, w, 3), np.nan, np.float32)
        for k, sm in enumerate(hit):
            a0, a1 = max(r0, sm.y0), min(r1, sm.y0 + sm.ok.shape[0])
            part = sm.img[a0 - sm.y0 : a1 - sm.y0].astype(np.float32)
            part[~sm.ok[a0 - sm.y0 : a1 - sm.y0]] = np.nan
            img[k, a0 - r0 : a1 - r0, sm.x0 : sm.x0 + sm.ok.shape[1]] = part
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", RuntimeWarning)  # all-NaN pixels: nobody saw them
            med = np.nanmedian(img, axis=0)
        count[r0:r1] = (~np.isnan(img[..., 0])).sum(0)
        plate[r0:r1] = np.nan_to_num(med, nan=0.0).round().clip(0, 255).astype(np.uint8)
    return plate, count


def _foreground(seq, view: int, frame: int, resized: int, crop: int, cfg: PlateConfig, cache: dict) -> np.ndarray:
    """(resized, resized) bool: hands or object in the cropped image of (view, frame)."""
    mpaths = seq.mask_paths.get(view) if seq.mask_paths else None
    mp = mpaths[frame] if mpaths is not None else None
    if cfg.masks == "files" and mp is None:
        raise AssetError(seq.image_paths[view][frame], "has no mask file (masks='files'; use 'auto' or 'render')")
    if mp is not None and cfg.masks != "render":
        m = cv2.imread(str(mp), cv2.IMREAD_UNCHANGED)
        if m is None:
            raise AssetError(mp, "cannot be read as an image")
        fg = cv2.resize((m > 0).astype(np.float32), (resized, resized), interpolation=cv2.INTER_AREA)
        return fg > 0  # a pixel with any foreground in it is foreground
    cam = seq.cameras[view]
    K_crop = render_intrinsics(cropped_intrinsics(cam.K[frame], cache["boxes"][view][frame], crop))
    Ks = np.diag([resized / crop, resized / crop, 1.0]) @ K_crop
    if "posed" not in cache:
        cache["posed"] = cache["pose"]()
    mask = render_camera_mask(cache["posed"], cam, frame, Ks, resized, supersample=2)
    return mask > 0


def _plate_samples(root, sid: str, view: int, seqs: Sequence[str], cfg: PlateConfig, posed_cache: dict):
    """Background samples of one (subject, view) in plate pixels, the plate size (H, W) and
    the full image size (W, H)."""
    samples, size, plate_hw = [], None, None
    crop = root.world_meta().cropped_size
    k_dilate = np.ones((2 * cfg.margin + 1, 2 * cfg.margin + 1), np.uint8) if cfg.margin else None
    for name in seqs:
        seq, cache = posed_cache[name]
        if view not in seq.image_paths:
            continue
        cam = seq.cameras[view]
        full = (int(cam.width), int(cam.height))
        if size is not None and full != size:
            raise AssetError(root.misc_path, f"{sid} view {view}: image size differs by sequence ({size}, {full})")
        size = full
        gain = cfg.width / full[0]
        plate_hw = (max(1, round(full[1] * gain)), cfg.width)
        for f in cache["frames"]:
            path = seq.image_paths[view][f]
            if path is None:
                continue
            box = cache["boxes"][view][f]
            resized = max(8, int(round(CROP_ENLARGE * BBOX_PIXELS_PER_SCALE * float(box[2]) * gain)))
            M = crop_to_plate(box, crop, resized, gain)
            # the crop's window in the plate (one pixel of margin), clipped to the plate
            lo = np.floor(M[:, 2] - 1).astype(int)
            hi = np.ceil(M[:, 2] + M[0, 0] * resized + 1).astype(int)
            x0, y0 = max(0, lo[0]), max(0, lo[1])
            x1, y1 = min(plate_hw[1], hi[0]), min(plate_hw[0], hi[1])
            if x1 <= x0 or y1 <= y0:
                continue
            img = cv2.imread(str(path), cv2.IMREAD_COLOR)
            if img is None:
                raise AssetError(path, "cannot be read as an image")
            if img.shape[0] != crop or img.shape[1] != crop:
                raise AssetError(path, f"is {img.shape[1]}x{img.shape[0]}, expected the cropped size {crop}x{crop}")
            small = cv2.resize(img, (resized, resized), interpolation=cv2.INTER_AREA)
            bg = (~_foreground(seq, view, f, resized, crop, cfg, cache)).astype(np.uint8)
            Mw = M.copy()
            Mw[:, 2] -= (x0, y0)
            dsize = (x1 - x0, y1 - y0)
            warped = cv2.warpAffine(small, Mw, dsize, flags=cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT)
            inside = cv2.warpAffine(np.ones((resized, resized), np.uint8), Mw, dsize, flags=cv2.INTER_NEAREST)
            keep = cv2.warpAffine(bg, Mw, dsize, flags=cv2.INTER_NEAREST, borderValue=0)
            fg = (inside > 0) & (keep == 0)
            if k_dilate is not None:
                fg = cv2.dilate(fg.astype(np.uint8), k_dilate) > 0
            # a crop's outer pixel row mixes in what lies beyond it: drop it
            ok = (cv2.erode(inside, np.ones((3, 3), np.uint8)) > 0) & ~fg
            # so does the plate's own border row (crop padding beyond the full image is black)
            ok[:, : max(0, 1 - x0)] = False
            ok[: max(0, 1 - y0)] = False
            ok[:, max(0, plate_hw[1] - 1 - x0) :] = False
            ok[max(0, plate_hw[0] - 1 - y0) :] = False
            samples.append(_Sample(y0, x0, warped, ok))
    return samples, plate_hw, size


def _cut_and_fill(plate: np.ndarray, count: np.ndarray) -> tuple[np.ndarray, dict]:
    """Cut the plate to the box of seen pixels and inpaint the holes inside it."""
    seen = count > 0
    ys, xs = np.nonzero(seen)
    y0, y1, x0, x1 = int(ys.min()), int(ys.max()) + 1, int(xs.min()), int(xs.max()) + 1
    cut = plate[y0:y1, x0:x1].copy()
    holes = (~seen[y0:y1, x0:x1]).astype(np.uint8)
    coverage = float(1.0 - holes.mean())
    if holes.any():
        cut = cv2.inpaint(cut, holes, 5, cv2.INPAINT_TELEA)
    return cut, {
        "box": [x0, y0, x1, y1],
        "coverage": round(coverage, 4),
        "median_samples": float(np.median(count[seen])),
    }


def _subjects(cfg: PlateConfig, root: ArcticRoot) -> list[str]:
    """The subjects to build: ``cfg.subjects``, or the training subjects of protocol p1.

    Raises:
        UsageError: a subject the data root does not have.
    """
    subjects = list(cfg.subjects) or sorted({s.split("/", 1)[0] for s in root.protocol("p1")["train"]})
    unknown = [s for s in subjects if s not in root.subjects()]
    if unknown:
        raise UsageError(f"subjects {unknown} are not in {root.misc_path} (have {root.subjects()})")
    return subjects


def _sequence_cache(root: ArcticRoot, sid: str, seqs: Sequence[str], cfg: PlateConfig) -> dict:
    """Per sequence name of subject ``sid``: ``(seq, {"frames", "boxes", "pose"})``, where ``pose``
    poses the meshes of the sampled frames lazily (only when a mask is rendered)."""
    cache: dict = {}
    for name in seqs:
        seq = root.sequence(sid, name)
        frames = _frames(seq.num_frames, cfg.frames_per_sequence)
        c = {
            "frames": frames,
            "boxes": crop_boxes(root, seq, cfg.views),
            "pose": lambda seq=seq, frames=frames: pose_meshes(  # only when a mask is rendered
                seq, frames, root.mano_layers(), root.object_templates()[seq.object.name]
            ),
        }
        cache[name] = (seq, c)
    return cache


def _view_plate(
    root: ArcticRoot, sid: str, view: int, seqs: Sequence[str], cfg: PlateConfig, cache: dict, out: Path
) -> tuple[Optional[dict], Optional[dict]]:
    """Build and write the plate of (``sid``, ``view``) into ``out``.

    Returns:
        ``(plate entry, None)`` when written, else ``(None, skipped record with its reason)``.

    Raises:
        AssetError: the plate cannot be encoded as PNG (and those of :func:`_plate_samples`).
    """
    samples, plate_hw, size = _plate_samples(root, sid, view, seqs, cfg, cache)
    if not samples:
        return None, {"subject": sid, "view": view, "reason": "no cropped images"}
    plate, count = _median(samples, plate_hw)
    if not (count > 0).any():
        return None, {"subject": sid, "view": view, "reason": "no background pixel seen"}
    cut, rec = _cut_and_fill(plate, count)
    entry = {"subject": sid, "view": view, "frames": len(samples), "full_size": list(size), **rec}
    if rec["coverage"] < cfg.min_coverage:
        return None, {**entry, "reason": f"coverage {rec['coverage']:.2f} < {cfg.min_coverage}"}
    fname = f"{sid}_view{view}.png"
    ok, png = cv2.imencode(".png", cut)
    if not ok:
        raise AssetError(out / fname, "could not be encoded as PNG")
    atomic_write(out / fname, png.tobytes())
    return {"file": fname, **entry}, None


def _remove_old_plates(out: Path, plates: Sequence[dict]) -> None:
    """Delete plate PNGs in ``out`` not in ``plates`` (earlier builds' would be read as backgrounds too)."""
    for old in out.glob("*_view*.png"):
        if old.name not in {p["file"] for p in plates}:
            old.unlink()


def build_plates(cfg: PlateConfig, log: Optional[Callable[[str], None]] = None) -> dict:
    """Write a clean plate per (subject, allocentric view) of a data root.

    For ARCTIC's static allocentric cameras, the backdrop of every view can be recovered from
    the dataset: each cropped image shows the square of side ``1.5 · 200 · scale`` around its
    box centre, so it maps back into the full camera frame by a scale and a shift. With the
    annotated hands and object masked out (the dataset's ``masks/`` when it has them, else
    rasterised from the posed MANO and object meshes), every plate pixel takes the per-pixel
    median of the frames that saw background there. Only hands and object are masked: whatever
    else stays in place in most frames (on real ARCTIC, parts of the subject's arms and body)
    stays in the plate. Plates are cut to the region the crops covered; holes inside it are
    filled by OpenCV's inpainting and their share is recorded per plate.

    Args:
        cfg: settings; ``cfg.data`` and ``cfg.out`` are required.
        log: progress messages (None: silent).

    Returns:
        The manifest written to ``out/plates.json``: settings and, per plate, its file,
        subject, view, frames used, box in the plate frame, share of the box seen as
        background (``coverage``) and median number of samples per seen pixel; and the
        plates skipped for low coverage.

    Raises:
        UsageError: bad settings or no usable subject.
        AssetError: unreadable images or masks, inconsistent cameras.
    """
    cfg.check()
    if cfg.data is None or cfg.out is None:
        raise UsageError("build_plates needs data and out")
    say = log or (lambda _m: None)
    root = ArcticRoot(cfg.data)
    subjects = _subjects(cfg, root)
    out = Path(cfg.out)
    out.mkdir(parents=True, exist_ok=True)
    plates, skipped = [], []
    for sid in subjects:
        seqs = [s.split("/", 1)[1] for s in root.sequences(sid)]
        if not seqs:
            continue
        cache = _sequence_cache(root, sid, seqs, cfg)
        for view in cfg.views:
            entry, skip = _view_plate(root, sid, view, seqs, cfg, cache, out)
            if entry is None:
                skipped.append(skip)
                continue
            plates.append(entry)
            say(f"{sid} view {view}: {entry['frames']} frames, coverage {entry['coverage']:.2f} -> {entry['file']}")
    if not plates:
        raise UsageError(f"no plate could be built from {cfg.data} (skipped: {skipped})")
    _remove_old_plates(out, plates)
    manifest = {
        "kind": "hogsa background plates",
        "version": 1,
        "settings": asdict(cfg),
        "data_fingerprint": data_fingerprint(root),
        "plates": plates,
        "skipped": skipped,
    }
    atomic_write(out / PLATES_MANIFEST, json.dumps(manifest, indent=1).encode())
    return manifest


def data_fingerprint(root) -> str:
    """SHA-256 of the data root's camera file (``misc.json``) and, when present, its world
    record: plates built from another dataset (or a world rebuilt in place) differ."""
    h = hashlib.sha256()
    for path in (root.misc_path, root.arctic_dir / "meta" / "hogsa_world.json"):
        h.update(path.name.encode())
        h.update(path.read_bytes() if path.is_file() else b"-")
    return h.hexdigest()
