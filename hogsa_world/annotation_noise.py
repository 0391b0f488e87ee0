"""Annotation noise: a copy of a world whose hand annotations carry ARCTIC-like fitting error.

A generated world's ``.mano.npy`` parameters are exactly the ones its images were rendered
from. ARCTIC's are not: its MANO parameters are fitted to motion-capture markers and miss
the imaged hands by a few millimetres (the per-frame ``fitting_err`` field). HOGS trained on
such labels averages misaligned observations into blur — one of the artefacts the paper's
SRM is meant to remove. :func:`add_annotation_noise` writes a world that reproduces this:
"""

from __future__ import annotations

import json
import os
import shutil
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch
from scipy.spatial.transform import Rotation

from hogsa_loader.assets.arctic import ArcticRoot, read_npy
from hogsa_loader.assets.arctic_processing import write_processed_splits
from hogsa_loader.errors import AssetError, PathLike
from hogsa_world.stand_ins import add_split_stand_ins
from hogsa_world.writer import _save_npy

__all__ = ["AnnotationNoise", "perturb_hand", "add_annotation_noise"]

_DATA = Path("arctic_data") / "data"


@dataclass(frozen=True)
class AnnotationNoise:
    """Noise std per component (half per-sequence offset, half smoothed per-frame jitter, in variance).

    The world :func:`add_annotation_noise` writes:

    * images, cameras, object poses and meta are the source world's (symlinked); the part
      masks are left out, as ARCTIC ships none (HOGS then renders them from the noisy labels);
    * each hand's ``rot``/``trans``/``pose`` get noise: per frame, a fixed per-sequence offset
      plus a frame-to-frame jitter smoothed over ``smooth`` frames (fitting error is partly
      systematic, partly per-frame), scaled so that each component has the requested std;
    * ``fitting_err`` becomes the realised mean vertex distance (m) between the written and the
      imaged hand, so the noise level can be read back from the world itself;
    * object poses stay exact: ARCTIC's crop boxes are computed from them, and the cropped
      images (the source's) were cut with the exact ones.

    The processed ``splits/`` are not copied (they hold the exact labels): they are rebuilt
    from the noisy labels by
    :func:`hogsa_loader.assets.arctic_processing.write_processed_splits` for the protocols of
    the source's ``splits_json/`` (linked: sequence lists only), so the loader's real-data path
    reads the same noisy labels as HOGS training (``process_splits=False`` skips this; HOGS
    training reads ``raw_seqs`` and needs nothing else).

    Attributes:
        trans_mm: wrist translation, per axis (mm).
        rot_deg: global orientation, per axis of the rotation vector (degrees).
        pose_rad: finger articulation, per axis-angle component (rad).
        smooth: frames of the moving average applied to the per-frame part (1: none).
        seed: noise seed.
    """

    trans_mm: float = 2.0
    rot_deg: float = 1.5
    pose_rad: float = 0.04
    smooth: int = 5
    seed: int = 0

    def __post_init__(self) -> None:
        if min(self.trans_mm, self.rot_deg, self.pose_rad) < 0 or self.smooth < 1:
            raise ValueError("noise stds must be >= 0 and smooth >= 1")


def _noise(rng: np.random.Generator, F: int, dims: int, std: float, smooth: int) -> np.ndarray:
    """(F, dims) noise with std ``std`` per entry: offset (variance ½) + smoothed jitter (variance ½)."""
    offset = rng.normal(0.0, 1.0, (1, dims))
    jitter = rng.normal(0.0, 1.0, (F + smooth - 1, dims))
    if smooth > 1:
        k = np.ones(smooth) / smooth
        jitter = np.stack([np.convolve(jitter[:, d], k, mode="valid") for d in range(dims)], 1) * np.sqrt(smooth)
    return (offset + jitter[:F]) * std * np.sqrt(0.5)


def perturb_hand(
    params: dict[str, np.ndarray], noise: AnnotationNoise, rng: np.random.Generator
) -> dict[str, np.ndarray]:
    """One hand's ``.mano.npy`` entry with noisy ``rot`` (composed on the left, about the wrist
    joint), ``trans`` and ``pose``; ``shape`` is kept; float32 as ARCTIC's."""
    F = params["rot"].shape[0]
    n_pose = params["pose"].shape[1]
    out = {k: np.array(v, copy=True) for k, v in params.items()}
    d_rot = Rotation.from_rotvec(_noise(rng, F, 3, np.deg2rad(noise.rot_deg), noise.smooth))
    out["rot"] = (d_rot * Rotation.from_rotvec(np.asarray(params["rot"], np.float64))).as_rotvec().astype(np.float32)
    out["trans"] = (params["trans"] + _noise(rng, F, 3, noise.trans_mm / 1000.0, noise.smooth)).astype(np.float32)
    out["pose"] = (params["pose"] + _noise(rng, F, n_pose, noise.pose_rad, noise.smooth)).astype(np.float32)
    return out


def _vertices(layer: Any, p: dict[str, np.ndarray]) -> np.ndarray:
    dt = torch.float64
    F = p["rot"].shape[0]
    with torch.no_grad():
        out = layer(
            global_orient=torch.as_tensor(p["rot"], dtype=dt),
            hand_pose=torch.as_tensor(p["pose"], dtype=dt),
            betas=torch.as_tensor(np.repeat(np.asarray(p["shape"])[None], F, 0), dtype=dt),
            transl=torch.as_tensor(p["trans"], dtype=dt),
        )
    return out.vertices.numpy()


def _link(src: Path, dst: Path) -> None:
    dst.parent.mkdir(parents=True, exist_ok=True)
    os.symlink(src.resolve(), dst, target_is_directory=src.is_dir())


def add_annotation_noise(
    src: PathLike,
    dst: PathLike,
    noise: AnnotationNoise = AnnotationNoise(),
    *,
    process_splits: bool = True,
    progress: bool = False,
) -> dict[str, Any]:
    """Write the noisy-annotation copy of the world at ``src`` to ``dst`` (see :class:`AnnotationNoise`).

    Args:
        src: a world / ARCTIC ``./data`` root (with ``arctic_data/data`` and ``body_models``).
        dst: output root (must not exist).
        noise: the noise model.
        process_splits: rebuild ``splits/`` from the noisy labels for every protocol of the
            source's ``splits_json/`` (none there: nothing to rebuild).
        progress: progress bar of that processing.

    Returns:
        the summary also written to ``dst/annotation_noise.json``: the noise settings and the
        realised mean vertex error per sequence and hand (mm).

    Raises:
        AssetError: ``src`` is not a world root, or ``dst`` exists.
    """
    src, dst = Path(src), Path(dst)
    data = src / _DATA
    if not (data / "raw_seqs").is_dir():
        raise AssetError(src, "not a world / ARCTIC root: arctic_data/data/raw_seqs is missing")
    if dst.exists():
        raise AssetError(dst, "output folder already exists")
    layers = ArcticRoot(src).mano_layers(dtype=torch.float64)
    rng = np.random.default_rng(noise.seed)
    try:
        for item in sorted(src.iterdir()):
            if item.name != "arctic_data":
                _link(item, dst / item.name)
        for item in sorted(data.iterdir()):
            # left out: what the noisy labels replace (raw_seqs, splits), the GT silhouettes, and
            # ARCTIC's derived folders, which would still hold the exact labels
            if item.name not in ("raw_seqs", "splits", "masks", "processed_seqs", "feat"):
                _link(item, dst / _DATA / item.name)
        errors: dict[str, dict[str, float]] = {}
        for subj in sorted(p for p in (data / "raw_seqs").iterdir() if p.is_dir()):
            for f in sorted(subj.iterdir()):
                out = dst / _DATA / "raw_seqs" / subj.name / f.name
                if not f.name.endswith(".mano.npy"):
                    _link(f, out)
                    continue
                mano = read_npy(f)  # restricted unpickler (ARCTIC's raw sequences are pickled dicts)
                noisy, seq_err = {}, {}
                for side, p in mano.items():
                    q = perturb_hand(p, noise, rng)
                    err = np.linalg.norm(_vertices(layers[side], q) - _vertices(layers[side], p), axis=-1).mean(-1)
                    q["fitting_err"] = err.astype(np.float32)
                    noisy[side] = q
                    seq_err[side] = float(err.mean() * 1000.0)
                _save_npy(out, noisy)
                errors[f"{subj.name}/{f.name.removesuffix('.mano.npy')}"] = seq_err
        protocols = sorted(p.stem.removeprefix("protocol_") for p in (data / "splits_json").glob("protocol_*.json"))
        if process_splits and protocols:
            written = write_processed_splits(dst, protocols=protocols, splits=("train", "val"), progress=progress)
            add_split_stand_ins(written.values())
    except BaseException:
        shutil.rmtree(dst, ignore_errors=True)
        raise
    all_err = [e for s in errors.values() for e in s.values()]
    summary = {
        "source": str(src.resolve()),
        "noise": asdict(noise),
        "mean_vertex_error_mm": errors,
        "overall_mean_vertex_error_mm": float(np.mean(all_err)) if all_err else 0.0,
        "splits": (
            f"rebuilt from the noisy labels ({', '.join(protocols)})" if process_splits and protocols else "not written"
        ),
        "note": "images, cameras and object poses are the source's; hands' .mano.npy are perturbed; masks/ not copied",
    }
    (dst / "annotation_noise.json").write_text(json.dumps(summary, indent=1) + "\n")
    return summary
