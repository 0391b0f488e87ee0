"""Encoding of one :class:`~hogsa_loader.sample.frame.SynthFrame` as WebDataset tar members.

:func:`encode_frame` / :func:`decode_frame` are the two directions; :func:`encode_frame` lists
the members of a sample.
"""

from __future__ import annotations

import io
import json
import zipfile
from typing import Any, Mapping, Optional

import cv2
import numpy as np

from hogsa_loader.io.images import decode_image
from hogsa_loader.sample.frame import SynthFrame
from hogsa_loader.sample.targets import HandLabels, ObjectLabels

__all__ = ["FORMAT_VERSION", "encode_frame", "decode_frame", "frame_labels", "json_default", "split_member_name"]

FORMAT_VERSION = 1
_HAND_FIELDS = ("pose48", "betas", "j3d_full", "j2d", "valid")
_OBJ_FIELDS = ("radian", "kp3d_full", "bbox3d_full", "kp2d", "bbox2d", "valid", "kp_bottom_cano")


def json_default(obj: Any) -> Any:
    """``json.dumps`` fallback: numpy scalars/arrays and torch tensors → lists/numbers,
    paths → str, sets → sorted lists, anything else → ``repr`` (provenance stays readable;
    such values do not round-trip)."""
    if isinstance(obj, np.ndarray):
        return obj.tolist()
    if isinstance(obj, np.generic):
        return obj.item()
    if hasattr(obj, "__fspath__"):
        return str(obj)
    if hasattr(obj, "tolist"):  # torch tensors
        return obj.tolist()
    if isinstance(obj, (set, frozenset)):
        return sorted(obj, key=repr)
    return repr(obj)


def split_member_name(name: str) -> tuple[str, str]:
    """WebDataset's split of a member name into ``(key, extension)``.

    The key is the directory part plus the base name up to its first dot; the extension
    is the rest (``"a/0001.alpha.png"`` → ``("a/0001", "alpha.png")``).
    """
    slash = name.rfind("/")
    dot = name.find(".", slash + 1)
    if dot < 0:
        return name, ""
    return name[:dot], name[dot + 1 :]


#: Prefix of the stored ``SynthFrame.extra_targets`` in ``labels.npz``.
EXTRA_PREFIX = "extra."


def frame_labels(frame: SynthFrame) -> dict[str, np.ndarray]:
    """Every label array of a frame, flat (``right.j2d``, ``obj.kp3d_full``, ``bbox``, ...),
    plus its extra targets under ``extra.<key>``."""
    out: dict[str, np.ndarray] = {}
    for side, hand in (("right", frame.right), ("left", frame.left)):
        for f in _HAND_FIELDS:
            out[f"{side}.{f}"] = np.asarray(getattr(hand, f))
    for f in _OBJ_FIELDS:
        out[f"obj.{f}"] = np.asarray(getattr(frame.obj, f))
    out["bbox"] = np.asarray(frame.bbox)
    out["K_full"] = np.asarray(frame.K_full)
    out["image_size"] = np.asarray(frame.image_size, dtype=np.int64)
    for k, v in frame.extra_targets.items():  # e.g. the interaction field (``extra.dist.ro``, ...)
        out[f"{EXTRA_PREFIX}{k}"] = np.asarray(v)
    for k, v in out.items():
        if v.dtype == object:
            raise TypeError(f"label {k} is an object array; export needs numeric arrays")
    return out


def _png(arr: np.ndarray) -> bytes:
    ok, buf = cv2.imencode(".png", arr, [cv2.IMWRITE_PNG_COMPRESSION, 3])
    if not ok:  # pragma: no cover
        raise RuntimeError("PNG encoding failed")
    return buf.tobytes()


def _quantise(a: np.ndarray, bits: int) -> np.ndarray:
    top = 255 if bits == 8 else 65535
    q = np.rint(np.clip(np.asarray(a, dtype=np.float64), 0.0, 1.0) * top)
    return q.astype(np.uint8 if bits == 8 else np.uint16)


def encode_frame(
    frame: SynthFrame,
    key: str,
    index: Optional[int] = None,
    shard: Optional[int] = None,
    image_format: str = "jpg",
    jpeg_quality: int = 95,
    alpha_bits: int = 8,
    parts: bool = True,
) -> dict[str, bytes]:
    """Tar members of one frame: ``{member name: bytes}`` in writing order.

    A sample with key ``K`` (no dot in it; the WebDataset convention splits member names at
    the first dot of the base name) is stored as consecutive tar members:

    * ``K.jpg`` — the composited crop, JPEG quality 95 (``K.png`` when written losslessly);
    * ``K.alpha.png`` — the rendered opacity, single-channel PNG, uint8 (``round(255 α)``) or
      uint16 (``round(65535 α)``);
    * ``K.parts.png`` — per-part opacity (right hand, left hand, object) as a 3-channel PNG
      of the same depth (R, G, B = right, left, object);
    * ``K.labels.npz`` — every label array (``np.savez``, no object arrays: it loads with
      ``allow_pickle=False``), dtypes kept, so labels round-trip bit-exactly;
    * ``K.json`` — ``imgname``, ``meta``, ``bbox``, ``K_full``, ``image_size``, object
      name, the global sample index, the shard, the image/alpha encodings, the format version.

    Args:
        frame: the frame.
        key: sample key (no ``.``; ``/`` allowed).
        index: global sample index (stored in the JSON; used as the augmentation seed on
            reading).
        shard: shard number (stored in the JSON).
        image_format: ``"jpg"`` (lossy, quality ``jpeg_quality``) or ``"png"`` (lossless).
        alpha_bits: 8 or 16 (PNG depth of the alpha and part-alpha images).
        parts: also store ``part_alpha``.

    Returns:
        ``{"K.jpg": ..., "K.alpha.png": ..., "K.parts.png": ..., "K.labels.npz": ..., "K.json": ...}``.
    """
    if "." in key.rsplit("/", 1)[-1]:
        raise ValueError(f"sample key must not contain a dot: {key!r}")
    if image_format not in ("jpg", "png"):
        raise ValueError(f"image_format must be 'jpg' or 'png', got {image_format!r}")
    if alpha_bits not in (8, 16):
        raise ValueError(f"alpha_bits must be 8 or 16, got {alpha_bits}")
    img = np.asarray(frame.image)
    if img.dtype != np.uint8 or img.ndim != 3 or img.shape[2] != 3:
        raise ValueError(f"frame.image must be (S, S, 3) uint8, got {img.shape} {img.dtype}")
    bgr = np.ascontiguousarray(img[:, :, ::-1])
    if image_format == "jpg":
        ok, buf = cv2.imencode(".jpg", bgr, [cv2.IMWRITE_JPEG_QUALITY, int(jpeg_quality)])
        if not ok:  # pragma: no cover
            raise RuntimeError("JPEG encoding failed")
        img_bytes = buf.tobytes()
    else:
        img_bytes = _png(bgr)
    members: dict[str, bytes] = {f"{key}.{image_format}": img_bytes}
    members[f"{key}.alpha.png"] = _png(_quantise(np.asarray(frame.alpha).reshape(img.shape[:2]), alpha_bits))
    if parts and frame.part_alpha is not None:
        pa = _quantise(np.asarray(frame.part_alpha), alpha_bits)
        members[f"{key}.parts.png"] = _png(np.ascontiguousarray(pa[:, :, ::-1]))
    bio = io.BytesIO()
    np.savez(bio, **frame_labels(frame))
    members[f"{key}.labels.npz"] = bio.getvalue()
    info = {
        "version": FORMAT_VERSION,
        "key": key,
        "index": None if index is None else int(index),
        "shard": None if shard is None else int(shard),
        "imgname": frame.imgname,
        "object": frame.obj.name,
        "bbox": np.asarray(frame.bbox, dtype=np.float64).tolist(),
        "K_full": np.asarray(frame.K_full, dtype=np.float64).tolist(),
        "image_size": [int(v) for v in frame.image_size],
        "image_format": image_format,
        "jpeg_quality": int(jpeg_quality) if image_format == "jpg" else None,
        "alpha_bits": int(alpha_bits),
        "meta": frame.meta,
    }
    members[f"{key}.json"] = json.dumps(info, default=json_default).encode("utf-8")
    return members


#: Largest uncompressed ``labels.npz`` of one sample (its arrays hold a few kB).
MAX_LABEL_BYTES = 4 * 2**20


def _decode_png(data: bytes, where: str = "<shard member>", max_pixels: Optional[int] = None) -> np.ndarray:
    if max_pixels is None:
        return decode_image(data, where, cv2.IMREAD_UNCHANGED)
    return decode_image(data, where, cv2.IMREAD_UNCHANGED, max_pixels=max_pixels)


def _labels(data: bytes, where: str) -> dict[str, np.ndarray]:
    """The arrays of a ``labels.npz`` member, its uncompressed size checked before anything
    is decompressed."""
    try:
        with zipfile.ZipFile(io.BytesIO(data)) as zf:
            size = sum(i.file_size for i in zf.infolist())
    except (zipfile.BadZipFile, OSError, EOFError) as exc:
        raise ValueError(f"{where}.labels.npz: not an npz archive ({exc})") from None
    if size > MAX_LABEL_BYTES:
        raise ValueError(f"{where}.labels.npz: {size} bytes uncompressed, more than labels hold ({MAX_LABEL_BYTES})")
    try:
        with np.load(io.BytesIO(data), allow_pickle=False) as z:
            return {k: z[k] for k in z.files}
    except (ValueError, OSError, EOFError, zipfile.BadZipFile) as exc:
        raise ValueError(f"{where}.labels.npz: unreadable ({type(exc).__name__}: {exc})") from None


def _dequantise(q: np.ndarray) -> np.ndarray:
    top = 65535.0 if q.dtype == np.uint16 else 255.0
    return (q.astype(np.float32) / np.float32(top)).astype(np.float32)


def decode_frame(files: Mapping[str, bytes], where: str = "<sample>") -> SynthFrame:
    """Inverse of :func:`encode_frame`.

    Args:
        files: ``{extension: bytes}`` of one sample (``"jpg"``/``"png"``, ``"alpha.png"``,
            optional ``"parts.png"``, ``"labels.npz"``, ``"json"``).
        where: name used in error messages (shard and key).

    Returns:
        The :class:`SynthFrame` (``image`` uint8 RGB, ``alpha``/``part_alpha`` float32 in
        [0, 1]; label arrays as written; ``part_alpha`` zeros when not stored).

    Raises:
        ValueError: a member is missing, undecodable or malformed (a label missing or not
            finite, a record of the wrong type); the message names ``where`` and the member.
    """
    try:
        return _decode_frame(files, where)
    except (KeyError, TypeError, AttributeError, IndexError, UnicodeDecodeError) as exc:
        raise ValueError(f"{where}: malformed sample ({type(exc).__name__}: {exc})") from None


def _decode_frame(files: Mapping[str, bytes], where: str) -> SynthFrame:
    for need in ("labels.npz", "json", "alpha.png"):
        if need not in files:
            raise ValueError(f"{where}: member .{need} missing")
    info = json.loads(files["json"].decode("utf-8"))
    ext = "jpg" if "jpg" in files else "png" if "png" in files else None
    if ext is None:
        raise ValueError(f"{where}: no image member (.jpg or .png)")
    bgr = decode_image(files[ext], f"{where}.{ext}", cv2.IMREAD_COLOR)
    image = np.ascontiguousarray(bgr[:, :, ::-1])
    pixels = image.shape[0] * image.shape[1]  # alpha and parts: the image's size, no larger
    alpha = _dequantise(_decode_png(files["alpha.png"], f"{where}.alpha.png", max_pixels=pixels))
    if alpha.shape[:2] != image.shape[:2]:
        raise ValueError(
            f"{where}: alpha is {alpha.shape[1]}x{alpha.shape[0]}, the image {image.shape[1]}x{image.shape[0]}"
        )
    if "parts.png" in files:
        parts = _decode_png(files["parts.png"], f"{where}.parts.png", max_pixels=pixels)
        if parts.shape[:2] != image.shape[:2]:
            raise ValueError(f"{where}: parts.png is {parts.shape[1]}x{parts.shape[0]}, the image differs")
        part_alpha = _dequantise(np.ascontiguousarray(parts[:, :, ::-1]))
    else:
        part_alpha = np.zeros(image.shape[:2] + (3,), np.float32)
    lab = _labels(files["labels.npz"], where)
    bad = [
        k for k, v in lab.items() if not k.startswith(EXTRA_PREFIX) and v.dtype.kind == "f" and not np.isfinite(v).all()
    ]
    if bad:
        raise ValueError(f"{where}.labels.npz: labels that are not finite: {', '.join(sorted(bad))}")

    def hand(side: str) -> HandLabels:
        return HandLabels(
            pose48=lab[f"{side}.pose48"],
            betas=lab[f"{side}.betas"],
            j3d_full=lab[f"{side}.j3d_full"],
            j2d=lab[f"{side}.j2d"],
            valid=float(lab[f"{side}.valid"]),
        )

    obj = ObjectLabels(
        name=str(info["object"]),
        radian=float(lab["obj.radian"]),
        kp3d_full=lab["obj.kp3d_full"],
        bbox3d_full=lab["obj.bbox3d_full"],
        kp2d=lab["obj.kp2d"],
        bbox2d=lab["obj.bbox2d"],
        valid=float(lab["obj.valid"]),
        kp_bottom_cano=lab["obj.kp_bottom_cano"],
    )
    size = lab["image_size"]
    meta = dict(info.get("meta") or {})
    n = len(EXTRA_PREFIX)
    extra = {k[n:]: (v.item() if v.ndim == 0 else v) for k, v in lab.items() if k.startswith(EXTRA_PREFIX)}
    return SynthFrame(
        image=image,
        alpha=alpha,
        part_alpha=part_alpha,
        bbox=lab["bbox"],
        K_full=lab["K_full"],
        image_size=(int(size[0]), int(size[1])),
        right=hand("right"),
        left=hand("left"),
        obj=obj,
        imgname=str(info["imgname"]),
        meta=meta,
        egocentric=bool(meta.get("egocentric", False)),
        dist=None if meta.get("dist") is None else np.asarray(meta["dist"], dtype=np.float64),
        extra_targets=extra,
    )
