"""Shared fixtures: the synthetic MANO-schema hands written as real-format pickles."""

from __future__ import annotations

import fcntl
import importlib
import json
import os
import re
import shlex
import shutil
import sys
import types
from pathlib import Path
from typing import Callable

import cv2
import numpy as np
import pytest
import torch
from hypothesis import settings as hypothesis_settings

from hogsa_loader.system import available_cores
from hogsa_world.hand import synthetic_hand_pair
from hogsa_world.mano_pickle import write_mano_pickle

#: The repository.
ROOT = Path(__file__).resolve().parents[1]

# Each pytest-xdist worker gets its share of the cores, for its own torch and (through
# OMP_NUM_THREADS, unless set) for the processes its tests start: more threads than cores make
# OpenMP's waiting threads spin against the other processes' work (tests up to ten times
# slower on a 2-core machine).
_WORKERS = int(os.environ.get("PYTEST_XDIST_WORKER_COUNT", "1"))
THREADS = max(1, min(2, available_cores() // _WORKERS))
torch.set_num_threads(THREADS)
if "PYTEST_XDIST_WORKER" in os.environ:  # (not in xdist's controller, whose environment the workers inherit)
    os.environ.setdefault("OMP_NUM_THREADS", str(THREADS))

# Property tests draw the same examples on every run and machine (``derandomize``: a seed from
# each test's own code) and keep no example database; ``HOGSA_HYPOTHESIS_PROFILE=random`` draws
# fresh examples each run. The long randomized reader fuzz is ``tests/robustness/fuzz_readers.py``.
hypothesis_settings.register_profile("suite", derandomize=True, database=None, print_blob=True)
hypothesis_settings.register_profile("random", database=None, print_blob=True)
hypothesis_settings.load_profile(os.environ.get("HOGSA_HYPOTHESIS_PROFILE", "suite"))


def page_commands(name: str, runner: str) -> list[list[str]]:
    """The ``hogsa`` commands of the blocks of ``docs/<name>`` marked as run by ``runner``
    (``<!-- block: run by <runner> ...``; continuation lines joined), as argument lists
    without the leading ``hogsa``."""
    lines = (ROOT / "docs" / name).read_text().splitlines()
    commands = []
    for i, line in enumerate(lines):
        if line.startswith(f"<!-- block: run by {runner}"):
            end = next(j for j in range(i + 2, len(lines)) if lines[j].startswith("```"))
            text = re.sub(r"\\\n\s*", " ", "\n".join(lines[i + 2 : end]))
            commands += [shlex.split(c)[1:] for c in text.splitlines() if c.startswith("hogsa ")]
    assert commands, f"no block of docs/{name} is marked as run by {runner}"
    return commands


def placed(argv: list[str], paths: dict[str, Path]) -> list[str]:
    """``argv`` with a page's stand-in paths (a key of ``paths``, or a key followed by
    ``/...``) replaced by the real ones."""
    out = []
    for a in argv:
        key = next((k for k in paths if a == k or a.startswith(k + "/")), None)
        out.append(a if key is None else str(paths[key]) + a[len(key) :])
    return out


def job(name: str) -> types.SimpleNamespace:
    """``main`` and ``parse_args`` of a command-line job, called in-process: ``hogs``, ``srm``,
    ``contactnet``, ``bank`` (``hogsa train NAME``), ``train_all_hogs`` or ``build_bundle``
    (``python -m hogsa_loader.cli.NAME``)."""
    import hogsa_loader.cli.train as train_cli

    if name in ("train_all_hogs", "build_bundle"):
        return importlib.import_module(f"hogsa_loader.cli.{name}")
    main = {"hogs": "train_hogs_main", "srm": "train_srm_main", "contactnet": "train_contactnet_main"}
    main["bank"] = "build_pose_bank_main"
    return types.SimpleNamespace(
        main=getattr(train_cli, main[name]), parse_args=getattr(train_cli, f"parse_{name}_args")
    )


@pytest.fixture(scope="session")
def hand_pair():
    """(right, left) synthetic models (in memory)."""
    return synthetic_hand_pair()


@pytest.fixture(scope="session")
def mano_dir(tmp_path_factory, hand_pair) -> Path:
    """A ``body_models/mano`` folder with MANO_RIGHT.pkl / MANO_LEFT.pkl in the legacy schema."""
    d = tmp_path_factory.mktemp("body_models") / "mano"
    right, left = hand_pair
    write_mano_pickle(right, d / "MANO_RIGHT.pkl")
    write_mano_pickle(left, d / "MANO_LEFT.pkl")
    return d


class _ChumpyShim:
    """Test-only stand-in for ``chumpy.ch.Ch`` so that smplx can read a chumpy pickle
    through plain ``pickle.load`` (what smplx does) without installing chumpy."""

    def __setstate__(self, state):
        self.x = np.asarray(state["x"])

    @property
    def shape(self):
        return self.x.shape

    def __getitem__(self, item):
        return self.x[item]

    def __array__(self, dtype=None, copy=None):
        return self.x if dtype is None else self.x.astype(dtype)


@pytest.fixture
def chumpy_shim(monkeypatch):
    """Install a fake ``chumpy`` package for the duration of one test."""
    pkg = types.ModuleType("chumpy")
    ch = types.ModuleType("chumpy.ch")
    ch.Ch = _ChumpyShim
    pkg.ch = ch
    monkeypatch.setitem(sys.modules, "chumpy", pkg)
    monkeypatch.setitem(sys.modules, "chumpy.ch", ch)
    yield


def shared_folder(tmp_path_factory, name: str, build: Callable[[Path], object]) -> Path:
    """The folder ``name`` built once per test session by ``build(folder)`` (given an empty
    folder), also across pytest-xdist's worker processes: the first worker builds it while
    holding a lock, the others wait for it and reuse it. A build that raises leaves no marker,
    so the next worker builds it again."""
    base = tmp_path_factory.getbasetemp()
    worker = os.environ.get("PYTEST_XDIST_WORKER")
    if worker and base.name == f"popen-{worker}":
        base = base.parent  # the session's folder, shared by its workers (and by them only)
    out = base / name
    with open(base / f"{name}.lock", "w") as lock:
        fcntl.flock(lock, fcntl.LOCK_EX)
        if not (base / f"{name}.built").is_file():
            shutil.rmtree(out, ignore_errors=True)
            out.mkdir()
            build(out)
            (base / f"{name}.built").touch()
    return out


@pytest.fixture(scope="session")
def tiny_world(tmp_path_factory) -> Path:
    """A generated ``tiny`` world (``hogsa world --out DIR --preset tiny --seed 0``), run once.

    Returns the folder that plays ARCTIC's ``./data``: ``arctic_data/data/{raw_seqs, meta,
    cropped_images, masks, splits_json, splits}``, ``body_models/mano``, ``world_preview.png``.
    Treat it as read-only (it is shared by every test of the session).

    For quick local runs, ``HOGSA_TEST_WORLD=DIR`` reuses a world made beforehand with that
    exact command (CI never sets it).
    """
    from hogsa_loader.cli.main import main

    given = os.environ.get("HOGSA_TEST_WORLD")
    if given:
        meta = Path(given) / "arctic_data" / "data" / "meta" / "hogsa_world.json"
        info = json.loads(meta.read_text())
        assert (info["preset"], info["seed"]) == ("tiny", 0), (
            f"HOGSA_TEST_WORLD must be a tiny seed-0 world, got {info}"
        )
        return Path(given)

    def build(out: Path) -> None:
        assert main(["world", "--out", str(out), "--preset", "tiny", "--seed", "0", "--quiet"]) == 0

    return shared_folder(tmp_path_factory, "tiny_world", build)


def tiny_hogs_config(data, out, **overrides):
    """A HOGS training config small enough for tests: s01/box at 64 px, 4 steps, no periodic
    evaluation or checkpoints (``overrides`` are flat ``config.json`` keys)."""
    from hogsa_loader.train import HogsConfig

    base = dict(
        data=str(data),
        subject="s01",
        object="box",
        out=str(out),
        iters=4,
        image_size=64,
        frame_stride=4,
        eval_every_frame=2,
        max_eval=3,
        eval_every=0,
        ckpt_every=0,
        lr_scale=10.0,
        k=1,
        sh_degree=1,
        sh_warmup=0,
        strip_views=2,
    )
    return HogsConfig.from_json({**base, **overrides})


def tiny_srm(folder: Path, scale: int = 1) -> Path:
    """A small untrained SRM saved in ``folder``."""
    from hogsa_loader.models.srm import SRM, save_srm
    from hogsa_loader.models.srm.styleunet import StyleUNetConfig

    torch.manual_seed(0)
    cfg = StyleUNetConfig(channels=[8, 8, 8], style_dim=8, mlp_num=1, scale=scale, extra_channels=4)
    save_srm(SRM(cfg), folder)
    return folder


@pytest.fixture(scope="session")
def untrained_bundle(tiny_world, tmp_path_factory) -> Path:
    """An untrained bundle of the tiny world (colours from the hand albedo / object texture)
    for s01 + box, with a small untrained SRM."""
    from hogsa_world.untrained import write_untrained_bundle

    def build(out: Path) -> None:
        assert write_untrained_bundle(tiny_world, out, "s01", "box", srm=tiny_srm(out / "srm")) == out / "bundle"

    return shared_folder(tmp_path_factory, "untrained_bundle", build) / "bundle"


@pytest.fixture(scope="module")
def layers(tiny_world):
    """The tiny world's MANO and object layers (:class:`~hogsa_loader.baselines.BodyLayers`)."""
    from hogsa_loader.assets.arctic import ArcticRoot
    from hogsa_loader.baselines import BodyLayers

    return BodyLayers.from_root(ArcticRoot(tiny_world))


@pytest.fixture(scope="module")
def batches(tiny_world, untrained_bundle):
    """A real batch of 4 and a mixed batch (2 real + 2 synthetic) of the tiny world, 64 px."""
    from torch.utils.data import DataLoader

    from hogsa_loader.compose import ProceduralBackgrounds
    from hogsa_loader.sample import HOGSADataset, MixedLoader, with_options
    from hogsa_loader.sample.arctic_dataset import ArcticDataset
    from hogsa_loader.sample.augment import ArcticConfig

    cfg = ArcticConfig(img_res=64)
    real = DataLoader(
        ArcticDataset(tiny_world, "p1_train", seed=0, config=cfg),
        batch_size=4,
        shuffle=True,
        generator=torch.Generator().manual_seed(0),
    )
    syn = HOGSADataset(
        untrained_bundle,
        tiny_world,
        with_options(arctic=cfg, batch_size=4, num_samples=8, seed=1),
        backgrounds=ProceduralBackgrounds(),
    )
    return next(iter(real)), next(iter(MixedLoader(real, syn, 0.5)))


@pytest.fixture(scope="module")
def one_thread():
    """One intra-op thread for a module of small-tensor tests (OpenMP hand-offs cost more than
    they gain there, and much more on a busy machine); restored afterwards."""
    before = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(before)


def tiny_build_config(data: Path, out: Path, **data_kw):
    """A build of one pair at toy sizes (seconds per stage on a CPU core)."""
    from dataclasses import replace

    from hogsa_loader.train.build import BuildConfig, BuildDataConfig, BuildRunConfig

    base = BuildConfig()
    return BuildConfig(
        data=BuildDataConfig(root=str(data), **{"pairs": ("s01/box",), **data_kw}),
        run=BuildRunConfig(out=str(out)),
        hogs=replace(
            base.hogs,
            data=replace(base.hogs.data, image_size=64, frame_stride=4, max_eval=2),
            model=replace(base.hogs.model, k=1, sh_degree=0, object_subdivide=0),
            optim=replace(base.hogs.optim, iters=4, sh_warmup=1),
            run=replace(base.hogs.run, eval_every=4, ckpt_every=4, strip_views=1),
        ),
        contactnet=replace(
            base.contactnet,
            optim=replace(base.contactnet.optim, iters=4, points=64),
            run=replace(base.contactnet.run, val_every=4),
        ),
        bank=replace(
            base.bank, data=replace(base.bank.data, per_sequence=1), pom=replace(base.bank.pom, iters=2, batch=4)
        ),
        srm=replace(
            base.srm,
            data=replace(base.srm.data, crop=32, augment="none", max_val=2),
            model=replace(base.srm.model, channels=(8, 8, 8, 8, 8)),
            optim=replace(base.srm.optim, iters=2, batch_size=2),
            run=replace(base.srm.run, eval_every=2, ckpt_every=2, strip_views=1),
        ),
    )


#: The side (px) of :func:`make_frame`'s images.
FRAME_SIDE = 48


def _frame_hand(rng: np.random.Generator, s: float):
    from hogsa_loader.sample.targets import HandLabels

    return HandLabels(
        pose48=rng.normal(size=48).astype(np.float32),
        betas=rng.normal(size=10).astype(np.float32),
        j3d_full=rng.normal(size=(21, 3)) * 0.05 + [0, 0, 0.6],
        j2d=rng.uniform(5, FRAME_SIDE - 5, size=(21, 2)),
        valid=s,
    )


def make_frame(i: int):
    """Synthetic frame ``i`` of the tests (a 48-pixel patch with alpha, parts and labels; a fixed
    draw per ``i``): for the export codec, the image checks and the downstream export."""
    from hogsa_loader.sample.frame import SynthFrame
    from hogsa_loader.sample.targets import ObjectLabels

    rng = np.random.default_rng(100 + i)
    yy, xx = np.mgrid[0:FRAME_SIDE, 0:FRAME_SIDE]
    img = np.stack([xx * 4, yy * 4, (xx + yy) * 2 + 10 * i], -1).clip(0, 255).astype(np.uint8)
    alpha = np.zeros((FRAME_SIDE, FRAME_SIDE), np.float32)
    alpha[10:30, 12:40] = 1.0
    alpha[9, 12:40] = 0.5
    parts = np.zeros((FRAME_SIDE, FRAME_SIDE, 3), np.float32)
    parts[10:30, 12:25, 0] = 1.0
    parts[10:30, 25:40, 2] = 0.75
    kp3d = rng.normal(size=(32, 3)) * 0.05 + [0, 0, 0.7]
    return SynthFrame(
        image=img,
        alpha=alpha,
        part_alpha=parts,
        bbox=np.array([FRAME_SIDE / 2, FRAME_SIDE / 2, FRAME_SIDE / 200.0]),
        K_full=np.array([[1000.0, 0, 320], [0, 1000.0, 240], [0, 0, 1]]) + i,
        image_size=(640, 480),
        right=_frame_hand(rng, 1.0),
        left=_frame_hand(rng, float(i % 2)),
        obj=ObjectLabels(
            name="box",
            radian=float(rng.uniform(0, 1)),
            kp3d_full=kp3d,
            bbox3d_full=rng.normal(size=(16, 3)) * 0.05 + [0, 0, 0.7],
            kp2d=rng.uniform(0, FRAME_SIDE, size=(32, 2)),
            bbox2d=rng.uniform(0, FRAME_SIDE, size=(16, 2)),
            valid=1.0,
            kp_bottom_cano=(rng.normal(size=(16, 3)) * 50).astype(np.float32),
        ),
        imgname=f"./synthetic/s01/box/{i:06d}.jpg",
        meta={"seed": 3, "index": i, "subject": "s01", "pose_source": "bank", "cam": np.int64(i)},
        extra_targets={}
        if i % 2
        else {
            "dist.ro": rng.uniform(0, 0.1, 5).astype(np.float32),
            "idx.ro": np.arange(5, dtype=np.int64) + i,
            "object.v_len": 40 + i,
        },
    )


# A small COCO-format dataset (images of flat colours; a person, a cup, a dining table)
# image id -> (colour RGB, categories present)
_IMAGES = {
    1: ((230, 20, 20), ["dining table"]),
    2: ((20, 230, 20), ["person", "dining table"]),
    3: ((20, 20, 230), ["cup"]),
    4: ((230, 230, 20), ["person"]),
    5: ((20, 230, 230), []),
}
_CATS = [(1, "person", "person"), (44, "cup", "kitchen"), (67, "dining table", "furniture")]


def write_coco(root: Path, layout: str = "images") -> Path:
    """A small COCO-format folder (train2017 images + instances_train2017.json) under ``root``."""
    img_dir = root / "images" / "train2017" if layout == "images" else root / "train2017"
    img_dir.mkdir(parents=True)
    (root / "annotations").mkdir()
    images, anns = [], []
    aid = 1
    cat_id = {name: cid for cid, name, _ in _CATS}
    for iid, (colour, cats) in _IMAGES.items():
        h, w = 96 + 8 * iid, 128 + 16 * iid
        rng = np.random.default_rng(iid)
        img = np.empty((h, w, 3), np.uint8)
        img[:] = colour
        img = np.clip(img.astype(int) + rng.integers(-10, 10, img.shape), 0, 255).astype(np.uint8)
        name = f"{iid:012d}.jpg"
        cv2.imwrite(str(img_dir / name), img[:, :, ::-1], [cv2.IMWRITE_JPEG_QUALITY, 95])
        images.append(
            {
                "license": 1,
                "file_name": name,
                "coco_url": "",
                "height": h,
                "width": w,
                "date_captured": "2013-11-14 17:02:52",
                "flickr_url": "",
                "id": iid,
            }
        )
        for c in cats:
            anns.append(
                {
                    "segmentation": [[10.0, 10.0, 40.0, 10.0, 40.0, 40.0, 10.0, 40.0]],
                    "area": 900.0,
                    "iscrowd": 0,
                    "image_id": iid,
                    "bbox": [10.0, 10.0, 30.0, 30.0],
                    "category_id": cat_id[c],
                    "id": aid,
                }
            )
            aid += 1
    data = {
        "info": {"description": "fake COCO", "version": "1.0", "year": 2017},
        "licenses": [{"url": "", "id": 1, "name": "test"}],
        "images": images,
        "annotations": anns,
        "categories": [{"supercategory": s, "id": cid, "name": n} for cid, n, s in _CATS],
    }
    ann = root / "annotations" / "instances_train2017.json"
    ann.write_text(json.dumps(data))
    return root
