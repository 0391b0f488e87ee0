"""COCO backgrounds: random crops of COCO images read through ``pycocotools``.

Random image (optionally only images showing given categories, optionally without people),
random crop of random scale, optional horizontal flip (:class:`CocoBackgrounds`). The
filtered image list is memoised in the process and cached on disk (``$HOGSA_CACHE`` or
``~/.cache/hogsa_loader``) so that DataLoader workers and later runs do not parse the 450 MB
annotation file again.
"""

from __future__ import annotations

import contextlib
import hashlib
import io
import json
import logging
import os
from pathlib import Path
from typing import Optional, Sequence, Union

from hogsa_loader.compose.sources import CropSpec, _ImageListSource
from hogsa_loader.errors import AssetError, PathLike, read_json
from hogsa_loader.extras import require
from hogsa_loader.io.atomic import atomic_open

__all__ = ["COCO_PERSON", "CocoBackgrounds", "default_cache_dir"]

log = logging.getLogger(__name__)

#: COCO category excluded by ``exclude_person=True`` (people, hence hands).
COCO_PERSON: str = "person"

# --------------------------------------------------------------------------------------
# COCO
# --------------------------------------------------------------------------------------


def _load_coco(ann_file: Path):
    """A ``pycocotools.coco.COCO`` of ``ann_file``; :class:`AssetError` on bad files."""
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
        if not isinstance(a, dict) or "id" not in a or "image_id" not in a or "category_id" not in a:
            raise AssetError(ann_file, f"annotations[{i}] lacks 'id', 'image_id' or 'category_id'")
    coco = require("pycocotools.coco", "coco", "COCO backgrounds").COCO()
    coco.dataset = data
    try:
        with contextlib.redirect_stdout(io.StringIO()):  # pycocotools prints progress
            coco.createIndex()
    except (KeyError, TypeError, ValueError) as e:
        raise AssetError(ann_file, f"not a valid COCO instances file ({type(e).__name__}: {e})") from e
    return coco


#: in-process memo of parsed + filtered COCO annotation files (the 450 MB train2017 file
#: takes ~20 s to parse): key (path, size, mtime, categories, exclude_person)
_COCO_MEMO: dict[tuple, tuple[list[int], list[str], list[Optional[tuple[int, int]]]]] = {}


def default_cache_dir() -> Path:
    """``$HOGSA_CACHE`` or ``~/.cache/hogsa_loader``."""
    env = os.environ.get("HOGSA_CACHE")
    return Path(env) if env else Path.home() / ".cache" / "hogsa_loader"


def _category_names(categories: Union[str, Sequence[str], None]) -> Optional[list[str]]:
    """``"cup"`` or ``["cup", ...]`` → a list of names (None: no filter)."""
    return None if categories is None else ([categories] if isinstance(categories, str) else list(categories))


def _coco_selection(
    ann: Path, categories: Optional[Sequence[str]], exclude_person: bool, index_cache: Optional[Path] = None
) -> tuple[list[int], list[str], list[Optional[tuple[int, int]]]]:
    """``(image ids, file names, (w, h) sizes)`` of the COCO images passing the filters.

    Memoised in the process, and on disk in ``index_cache`` (a small JSON keyed by the
    annotation file's path, size and mtime and the filters) so that DataLoader workers and
    later runs skip parsing the annotation file."""
    names = _category_names(categories)
    st = ann.stat()
    key = (
        str(ann.resolve()),
        st.st_size,
        st.st_mtime_ns,
        None if names is None else tuple(names),
        bool(exclude_person),
    )
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
        raise AssetError(
            ann, f"no COCO image left after filtering (categories={names}, exclude_person={exclude_person})"
        )
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
            with atomic_open(cache_file, "w", encoding="utf-8") as fh:
                json.dump(
                    {
                        "key": [str(k) for k in key],
                        "ids": img_ids,
                        "files": files,
                        "sizes": [list(z) if z else None for z in sizes],
                    },
                    fh,
                )
        except OSError as exc:  # a read-only cache folder only costs speed
            log.debug("cannot write COCO selection cache %s: %s", cache_file, exc)
    return _COCO_MEMO[key]


def _find_coco_image_dir(root: Path, split: str, first_file: Optional[str]) -> Path:
    candidates = [root / "images" / split, root / split, root / "images", root]
    for c in candidates:
        if c.is_dir() and (first_file is None or (c / first_file).is_file()):
            return c
    raise AssetError(
        root,
        "no COCO image folder: looked for "
        + ", ".join(str(c) for c in candidates)
        + (f" holding {first_file}" if first_file else ""),
    )


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
        cache_dir = (
            default_cache_dir() if index_cache is True else None if index_cache in (None, False) else Path(index_cache)
        )  # type: ignore[arg-type]
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

        super().__init__([idir / f for f in files], sizes, crop, cache_bytes, reduced_decode, origin=ann)
        self.ann_file = ann
        self.image_dir = idir
        self.image_ids = img_ids
        self.categories = _category_names(categories)
        self.exclude_person = bool(exclude_person)
