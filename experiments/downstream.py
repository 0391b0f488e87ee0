"""Does HOGSA improve the baseline? ArcticNet-SF trained with and without synthetic samples.

One command reproduces the shape of the HOGSA paper's Table 1 and ablation on an
ARCTIC-format world: ArcticNet-SF is trained on the world's ``p1_train`` real loader alone
and on real + HOGSA samples (:class:`~hogsa_loader.sample.mixing.MixedLoader`, the
machinery of ``wrap_train_loader``) with the same steps, batch size (real batches with
``--synthetic-mix add``), optimiser, augmentation and seed, and every model is evaluated on
the held-out subject (``p1_val``) with ARCTIC's metrics.

Arms (``--arms``):

* ``real`` — real frames only;
* ``hogsa`` — real + HOGSA: POM pose bank + SRM;
* ``hogsa_no_pom`` — annotated training poses (no POM), novel views, SRM;
* ``hogsa_no_srm`` — POM pose bank, no SRM;
* ``hogsa_free`` — the free-3DGS HOGS variant (needs ``--setup-free``, which builds it beside
  the setup, or ``--setup-free-bundle``; skipped and recorded otherwise);
* ``real_low`` / ``hogsa_low`` — the same with ``--low-data`` of the real training frames
  (a fixed random subset, the same for every seed and arm).

Mixing (``--synthetic-mix``): ``replace`` (default), synthetic samples take
``--synthetic-share`` of every batch, so a HOGSA arm sees fewer real samples per step than
its real arm; ``add``, each HOGSA batch is its real arm's batch, whole, with synthetic
samples appended (larger batches, the same real samples in the same order); its HOGSA runs
are kept apart from the replace runs (``runs/<arm>+add/``).

Runs start from random weights (every head's camera at the mean training camera), or, with
``--model-init``, from a whole ArcticNet-SF checkpoint per seed: ARCTIC's released one, or
this script's own real-only models (``OUT/runs/real/seed{seed}/model.safetensors``), so
that real + HOGSA is compared with real data alone as a fine-tuning of the same model.

Synthetic frames are rendered once per variant with ``hogsa export``'s writer
(``OUT/synthetic/<variant>/``, resumable) and read back shuffled
(:class:`~hogsa_loader.sample.export.SynthShardSamples`) with fresh ARCTIC augmentation per epoch,
so rendering is paid once. Without ``--setup-data``/``--setup-bundle`` the world and the
bundle (HOGS for every training (subject, object), ContactNet, pose bank, SRM) are built by
``hogsa demo``'s cached stages in ``OUT/setup``.

Outputs in ``OUT``: ``runs/<arm>/seed<k>/result.json`` (+ ``model.safetensors``) per run
(``runs/<arm>+add/`` for HOGSA arms with ``--synthetic-mix add``, ``+ft-<hash>`` appended for
runs from a ``--model-init``) —
a finished run is reused when its settings are unchanged, and an unfinished one continues
from its last saved state (``checkpoints/``, every ``--train-checkpoint-every`` steps) on
exactly the batches it would have seen, so an interrupted command continues where it
stopped; ``downstream.json`` (per seed, mean ± std, paired differences real+HOGSA − real
per seed, each with its 95 % interval over the validation clips and its range with one clip
left out), ``downstream.md`` (tables) and ``downstream.png`` (validation curves per arm,
metric bars with the seed spread). Each result keeps its MPJPE_h and CDev_ho per validation
clip (one subject, sequence and camera view: ``result.json``'s ``clips``); a result saved
without them has its model evaluated once more when it is reported.

Usage::

    python experiments/downstream.py --out runs/downstream            # full run, small world
    python experiments/downstream.py --out /tmp/ds_quick --quick      # tiny world, minutes
    python experiments/downstream.py --out runs/downstream_gpu --device cuda   # ARCTIC's settings

Defaults on the CPU (2 cores): ResNet-18 at 96², 200 steps of 32 per run, chosen so that
6 arms × 3 seeds, the small world's setup and the exports aim at about 90 minutes: the
backbone's forward + backward at 96² × 32 measured 1.8 s on one core of a busy 2-core
machine (2.9 s at 128², 0.9 s at 64²). ``--device cuda``
switches the defaults to ARCTIC's network settings (ResNet-50 at 224², batch 64) and
longer runs; any flag still overrides them.
"""

from __future__ import annotations

import argparse
import hashlib
import json
import os
import platform
import shutil
import sys
import time
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path
from typing import Any, Iterator, Literal, Optional

import numpy as np
import torch
from torch.utils.data import DataLoader, Dataset, Subset, default_collate
from tqdm import tqdm

from hogsa_loader.assets.arctic import ArcticRoot
from hogsa_loader.baselines.arcticnet_sf import ArcticNetSF, load_arctic_checkpoint, load_saved_model
from hogsa_loader.baselines.clips import (
    CLIP_METRICS,
    clip_mean,
    clip_sums,
    clip_uncertainty,
    interval_text,
    left_out_text,
)
from hogsa_loader.baselines.engine import BodyLayers, evaluate, mean_cameras, temporal_order, training_step
from hogsa_loader.baselines.interfield_sf import (
    InterFieldSF,
    evaluate_field,
    field_training_step,
    load_field_weights,
    read_mano_decimator,
)
from hogsa_loader.baselines.resnet import load_backbone_weights
from hogsa_loader.baselines.targets import prepare_targets
from hogsa_loader.cli.dataclass_args import add_dataclass_arguments, dataclass_from_args
from hogsa_loader.compose.plates import PLATES_MANIFEST, PlateConfig, build_plates, data_fingerprint
from hogsa_loader.errors import AssetError
from hogsa_loader.io.atomic import atomic_write_json
from hogsa_loader.io.hashing import settings_key, sha256_file
from hogsa_loader.io.tensors import write_tensors_and_manifest
from hogsa_loader.sample import HOGSADataset, with_options
from hogsa_loader.sample.arctic_dataset import ArcticDataset
from hogsa_loader.sample.augment import ArcticConfig
from hogsa_loader.sample.cameras import CameraConfig
from hogsa_loader.sample.export import SynthShardSamples, dataset_frames_for_shard, write_shards
from hogsa_loader.sample.mixing import MixedLoader, MixMode, added_synthetic, num_synthetic
from hogsa_loader.system import available_cores
from hogsa_loader.train.run_folder import (
    commit_checkpoint,
    load_network_and_adam,
    network_and_adam_tensors,
    read_latest_trainer_state,
    save_trainer_state,
)
from hogsa_loader.view.pictures import demo_photographs
from hogsa_world import get_preset
from hogsa_world.demo import DemoConfig, build_bundle_stages

ARMS = ("real", "hogsa", "hogsa_no_pom", "hogsa_no_srm", "hogsa_free", "real_low", "hogsa_low")
#: arm → (real share of p1_train, synthetic variant or None)
ARM_SPECS: dict[str, tuple[str, Optional[str]]] = {
    "real": ("all", None),
    "hogsa": ("all", "full"),
    "hogsa_no_pom": ("all", "no_pom"),
    "hogsa_no_srm": ("all", "no_srm"),
    "hogsa_free": ("all", "free"),
    "real_low": ("low", None),
    "hogsa_low": ("low", "full"),
}
#: Metrics of the tables, in ARCTIC's order, with their direction (True: lower is better).
METRICS = {
    "mpjpe/ra/h": ("MPJPE_h (mm)", True),
    "cdev/ho": ("CDev_ho (mm)", True),
    "mrrpe/r/l": ("MRRPE_rl (mm)", True),
    "mrrpe/r/o": ("MRRPE_ro (mm)", True),
    "mdev/h": ("MDev_h (mm)", True),
    "acc/h": ("ACC_h (m/s²)", True),
    "acc/o": ("ACC_o (m/s²)", True),
    "aae": ("AAE (°)", True),
    "success_rate/0.05": ("Success (%)", False),
}
#: InterField-SF's table (``--model-kind interfield_sf``): ARCTIC's average distance error and
#: acceleration error of the interaction field, hands → object and object → hands.
FIELD_TABLE_METRICS = {
    "avg/ho": ("avg. dist. err. h→o (mm)", True),
    "avg/oh": ("avg. dist. err. o→h (mm)", True),
    "acc/ho": ("ACC h→o (m/s²)", True),
    "acc/oh": ("ACC o→h (m/s²)", True),
}
#: Per model kind: the table's metrics and the two metrics paired per seed and over clips.
KIND_METRICS: dict[str, tuple[dict[str, tuple[str, bool]], tuple[str, str]]] = {
    "arcticnet_sf": (METRICS, ("mpjpe/ra/h", "cdev/ho")),
    "interfield_sf": (FIELD_TABLE_METRICS, ("avg/ho", "avg/oh")),
}
#: The short names of the paired metrics in the tables.
PAIRED_NAMES = {"mpjpe/ra/h": "MPJPE_h", "cdev/ho": "CDev_ho", "avg/ho": "avg. h→o", "avg/oh": "avg. o→h"}
RESULT_VERSION = 2
#: Resamples of the validation clips behind each paired difference's interval.
CLIP_RESAMPLES = 2000


@dataclass
class SetupSettings:
    """Where the world and the bundle come from."""

    preset: str = field(default="small", metadata={"help": "world preset built when --setup-data is not given"})
    data: Optional[str] = field(default=None, metadata={"help": "an existing ARCTIC(-format) data root"})
    bundle: Optional[str] = field(default=None, metadata={"help": "an existing bundle built on --setup-data"})
    free_bundle: Optional[str] = field(default=None, metadata={"help": "bundle of free-3DGS HOGS runs"})
    free: bool = field(
        default=False,
        metadata={
            "help": "also build a bundle of free-3DGS HOGS runs (plain 3D Gaussians, not bound to the meshes; every "
            "other stage setting the same) in OUT/setup/free, for the hogsa_free arm"
        },
    )
    hogs_iters: int = field(default=400, metadata={"help": "HOGS steps per (subject, object) when building"})
    hogs_image_size: int = field(default=128, metadata={"help": "HOGS training resolution when building"})
    srm_iters: int = field(default=400, metadata={"help": "SRM steps when building"})
    srm_gan: float = field(
        default=0.0,
        metadata={
            "help": "weight of SRM's adversarial term when building (StyleUNet's conditional discriminator; "
            "0: L1 and perceptual terms only)",
            "type": "non_negative_float",
        },
    )
    contactnet_iters: int = field(default=120, metadata={"help": "ContactNet steps when building"})
    bank_per_sequence: int = field(default=6, metadata={"help": "POM frames per sequence in the pose bank"})
    bank_variants: int = field(
        default=1, metadata={"help": "perturbed POM starts per frame in the pose bank (BankDataConfig.variants)"}
    )
    bank_finger_scale: float = field(
        default=0.0,
        metadata={
            "help": "finger noise of the pose bank's POM starts, in standard deviations of the training hands along "
            "their principal directions (BankPOMConfig.finger_scale; 0: the paper's perturbation alone)"
        },
    )
    bank_frames: Literal["contact", "all"] = field(
        default="contact",
        metadata={
            "help": "frames the pose bank starts from (BankDataConfig.frames): contact, frames where a hand touches "
            "the object (grasps only); all, every frame but the first and last 10, so that hands away from the object "
            "keep their share"
        },
    )


@dataclass
class SyntheticSettings:
    """Synthetic frames: exported once per variant, read back shuffled."""

    frames: int = field(default=1536, metadata={"help": "synthetic frames per variant"})
    share: float = field(default=0.5, metadata={"help": "synthetic share of each mixed batch"})
    mix: MixMode = field(
        default="replace",
        metadata={
            "help": "replace: synthetic samples take their share of each batch of --train-batch-size; add: every "
            "real batch kept whole (the real arm's batches), synthetic samples appended (larger batches)"
        },
    )
    render_batch: int = field(default=8, metadata={"help": "samples per render call (one model per call)"})
    seed: int = field(default=1000, metadata={"help": "seed of the exported frames"})
    backgrounds: Literal["plates", "camera_plates", "photos"] = field(
        default="plates",
        metadata={
            "help": "plates: the world's own studio, cleaned of hands and objects (hogsa plates) from the "
            "training subjects' frames, a random crop of a random plate; camera_plates: the same plates, and a "
            "frame seen through a dataset camera gets that camera's own plate cut by its crop box; photos: "
            "scikit-image's colour photographs (a COCO stand-in)"
        },
    )
    cameras: Literal["novel", "dataset"] = field(
        default="novel",
        metadata={
            "help": "novel: viewpoints drawn around the hands and object, the subject's own cameras a quarter of the "
            "time (the loader's default); dataset: the training subjects' own capture cameras only"
        },
    )
    other_hands: float = field(
        default=0.0,
        metadata={
            "help": "share of the synthetic render batches that show another training subject's hands (the "
            "loader's other_hands: poses, object, cameras and labels unchanged); 0: every model's own hands"
        },
    )
    supervise: Literal["all", "touching"] = field(
        default="all",
        metadata={
            "help": "which hands of a synthetic frame the loss sees: all; touching, only hands with a vertex within "
            "5 mm of an object vertex (the others marked invalid, as ARCTIC marks a hand outside the crop), so hands "
            "away from the object are learnt from real frames alone"
        },
    )


@dataclass
class ModelSettings:
    """The baseline trained."""

    kind: Literal["arcticnet_sf", "interfield_sf"] = field(
        default="arcticnet_sf",
        metadata={
            "help": "arcticnet_sf: ArcticNet-SF (MANO and object parameters; MPJPE, CDev, ...); interfield_sf: "
            "InterField-SF (the hand-object interaction field; average distance and acceleration errors)"
        },
    )
    backbone: Literal["resnet18", "resnet50"] = field(default="resnet18", metadata={"help": "image backbone"})
    img_res: int = field(default=96, metadata={"help": "patch side in pixels (ARCTIC: 224)"})
    weights: Optional[str] = field(default=None, metadata={"help": "local backbone weights (.pth/.safetensors)"})
    init: Optional[str] = field(
        default=None,
        metadata={
            "help": "start every run from this whole ArcticNet-SF checkpoint instead of random weights "
            "(fine-tuning, as the paper does): ARCTIC's released .ckpt or a run's model.safetensors; '{seed}' in the "
            "path becomes the run's seed, so each seed continues its own model; the camera prior is not applied"
        },
    )
    camera_prior: int = field(
        default=256,
        metadata={
            "help": "start the cameras at the mean target camera of this many real training frames of the arm "
            "(HMR's mean-parameter start; 0: random start)"
        },
    )


@dataclass
class TrainSettings:
    """Optimisation (the same for every arm)."""

    steps: int = field(default=200, metadata={"help": "optimisation steps per run"})
    batch_size: int = field(
        default=32,
        metadata={"help": "samples per step (real + synthetic; the real ones only with --synthetic-mix add)"},
    )
    lr: float = field(default=3e-4, metadata={"help": "Adam learning rate"})
    lr_schedule: Literal["constant", "linear"] = field(
        default="constant",
        metadata={
            "help": "constant: --train-lr throughout; linear: decayed linearly to 0 at the last step (steadier "
            "final weights, so a run's final metrics depend less on where its last steps happened to go)"
        },
    )
    grad_clip: float = field(default=150.0, metadata={"help": "gradient-norm clip (ARCTIC: 150)"})
    workers: int = field(default=1, metadata={"help": "DataLoader workers per loader"})
    evals: int = field(default=3, metadata={"help": "validation points on the curve (the last is the full eval)"})
    eval_stride: int = field(default=8, metadata={"help": "every k-th val frame for the curve points"})
    checkpoint_every: int = field(
        default=50,
        metadata={
            "help": "save a run's state every this many steps (0: never); an interrupted run resumes from its "
            "last one on the same batches (bit for bit on the CPU; on a GPU as far as its kernels are deterministic)"
        },
    )


@dataclass
class DownstreamConfig:
    """The downstream experiment."""

    out: str = field(default="runs/downstream", metadata={"help": "output and cache folder"})
    seeds: tuple[int, ...] = field(default=(0, 1, 2), metadata={"help": "training seeds"})
    arms: tuple[str, ...] = field(default=ARMS, metadata={"help": f"arms to run, of {', '.join(ARMS)}"})
    low_data: float = field(default=0.25, metadata={"help": "real share of the low-data arms"})
    device: str = field(default="cpu", metadata={"help": "cpu or cuda"})
    threads: int = field(default=0, metadata={"help": "torch CPU threads (0: all available cores)"})
    report_only: bool = field(
        default=False,
        metadata={
            "help": "tables and figures of the finished runs only (partial results): no export, no training; needs "
            "a finished setup"
        },
    )
    setup: SetupSettings = field(default_factory=SetupSettings)
    synthetic: SyntheticSettings = field(default_factory=SyntheticSettings)
    model: ModelSettings = field(default_factory=ModelSettings)
    train: TrainSettings = field(default_factory=TrainSettings)


def quick_config(cfg: DownstreamConfig) -> DownstreamConfig:
    """``--quick``: the tiny world, one seed, a few steps — the whole pipeline in minutes."""
    return replace(
        cfg,
        seeds=(0,),
        setup=replace(
            cfg.setup,
            preset="tiny",
            hogs_iters=40,
            hogs_image_size=64,
            srm_iters=20,
            contactnet_iters=10,
            bank_per_sequence=2,
        ),
        synthetic=replace(cfg.synthetic, frames=32),
        model=replace(cfg.model, backbone="resnet18", img_res=64),
        train=replace(cfg.train, steps=6, batch_size=8, workers=1, evals=2, eval_stride=8),
    )


def gpu_config(cfg: DownstreamConfig) -> DownstreamConfig:
    """Defaults with ``--device cuda``: ARCTIC's network settings (ResNet-50 at 224², batch 64)."""
    return replace(
        cfg,
        device="cuda",
        setup=replace(cfg.setup, hogs_iters=3000, hogs_image_size=256, srm_iters=3000),
        synthetic=replace(cfg.synthetic, frames=20000),
        model=replace(cfg.model, backbone="resnet50", img_res=224),
        train=replace(cfg.train, steps=3000, batch_size=64, lr=1e-4, workers=6, evals=10, eval_stride=2),
    )


def validate(cfg: DownstreamConfig) -> None:
    """Refuse settings that cannot run, before any work."""
    unknown = [a for a in cfg.arms if a not in ARM_SPECS]
    if unknown:
        raise SystemExit(f"downstream: error: unknown arms {unknown}; known: {', '.join(ARMS)}")
    checks = [
        (cfg.seeds, "--seeds needs at least one seed"),
        (0.0 < cfg.low_data <= 1.0, "--low-data must be in (0, 1]"),
        (0.0 < cfg.synthetic.share < 1.0, "--synthetic-share must be in (0, 1)"),
        (0.0 <= cfg.synthetic.other_hands <= 1.0, "--synthetic-other-hands must be in [0, 1]"),
        (cfg.synthetic.frames > 0 and cfg.synthetic.render_batch > 0, "--synthetic-frames/-render-batch must be > 0"),
        (cfg.train.steps > 0 and cfg.train.batch_size > 1, "--train-steps > 0 and --train-batch-size > 1 needed"),
        (cfg.train.evals >= 1 and cfg.train.eval_stride >= 1, "--train-evals and --train-eval-stride must be >= 1"),
        (cfg.train.workers >= 0 and cfg.threads >= 0, "--train-workers and --threads must be >= 0"),
        (cfg.model.img_res >= 32, "--model-img-res must be >= 32"),
        (cfg.model.camera_prior >= 0, "--model-camera-prior must be >= 0"),
        (cfg.setup.bank_finger_scale >= 0, "--setup-bank-finger-scale must be >= 0"),
        (
            cfg.setup.bank_per_sequence >= 1 and cfg.setup.bank_variants >= 1,
            "--setup-bank-per-sequence and --setup-bank-variants must be >= 1",
        ),
        (cfg.train.checkpoint_every >= 0, "--train-checkpoint-every must be >= 0"),
        (not (cfg.model.init and cfg.model.weights), "--model-init and --model-weights exclude each other"),
        (
            cfg.synthetic.supervise == "all" or cfg.model.kind == "arcticnet_sf",
            "--synthetic-supervise touching marks hands invalid, which InterField-SF's loss does not read",
        ),
        (
            cfg.synthetic.mix == "add"
            or num_synthetic(cfg.synthetic.share, cfg.train.batch_size) < cfg.train.batch_size,
            "--synthetic-share leaves no real sample in a batch of --train-batch-size",
        ),
        (
            (cfg.setup.data is None) == (cfg.setup.bundle is None) or cfg.setup.data is not None,
            "--setup-bundle needs --setup-data",
        ),
        (not (cfg.setup.free and cfg.setup.free_bundle), "give --setup-free or --setup-free-bundle, not both"),
        (not cfg.setup.free or "hogsa_free" in cfg.arms, "--setup-free builds for the hogsa_free arm, not in --arms"),
        (
            not (cfg.setup.free and cfg.setup.bundle),
            "--setup-free builds beside the setup built here; with --setup-bundle give --setup-free-bundle",
        ),
    ]
    for ok, msg in checks:
        if not ok:
            raise SystemExit(f"downstream: error: {msg}")
    if cfg.setup.data is not None:
        try:  # an ARCTIC root with a p1 training split
            train_pairs(Path(cfg.setup.data))
        except AssetError as e:
            raise SystemExit(f"downstream: error: --setup-data {e}") from None
    if cfg.synthetic.other_hands > 0 and cfg.setup.bundle is None:
        subjects = sorted({sid for sid, _ in setup_pairs(cfg.setup)})
        if len(subjects) < 2:
            raise SystemExit(
                f"downstream: error: --synthetic-other-hands needs two training subjects; the world has {subjects}"
            )
    _validate_init(cfg)
    if cfg.device.startswith("cuda") and not torch.cuda.is_available():
        raise SystemExit("downstream: error: --device cuda but no CUDA device is available")


_key = settings_key


def _atomic_json(path: Path, obj: Any) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    atomic_write_json(path, obj, allow_nan=False, default=str)


def _validate_init(cfg: DownstreamConfig) -> None:
    """Refuse a ``--model-init`` whose file is missing for a seed."""
    if cfg.model.init is None:
        return
    for seed in cfg.seeds:
        if not init_path(cfg, seed).is_file():
            raise SystemExit(f"downstream: error: --model-init: no checkpoint file {init_path(cfg, seed)}")


def check_inits(cfg: DownstreamConfig, setup: dict[str, Any]) -> None:
    """Load every seed's ``--model-init`` into the configured network once, before any export or
    training, so that a checkpoint of another backbone or a damaged file stops the command at
    once (an :class:`~hogsa_loader.errors.AssetError` naming the file)."""
    if cfg.model.init is None:
        return
    model = build_model(cfg, BodyLayers.from_root(ArcticRoot(setup["data"])), setup["data"])
    for seed in cfg.seeds:
        load_init(cfg, model, init_path(cfg, seed))


def load_init(cfg: DownstreamConfig, model: torch.nn.Module, path: Path) -> None:
    """Load the whole-model checkpoint ``path`` into ``model``: ARCTIC's released ``.ckpt`` or a
    run's ``model.safetensors`` of the configured model kind."""
    if cfg.model.kind == "interfield_sf":
        load_field_weights(model, path)  # type: ignore[arg-type]
    else:
        load_arctic_checkpoint(model, path)  # type: ignore[arg-type]


def _say(msg: str) -> None:
    print(msg, flush=True)


# ----------------------------------------------------------------------------- setup


def train_pairs(data: Path) -> list[tuple[str, str]]:
    """(subject, object) pairs of the ``p1`` training sequences."""
    root = ArcticRoot(data)
    pairs: list[tuple[str, str]] = []
    for sid_seq in root.protocol("p1")["train"]:
        sid, seq = sid_seq.split("/", 1)
        pair = (sid, seq.split("_", 1)[0])
        if pair not in pairs:
            pairs.append(pair)
    return pairs


def setup_pairs(s: SetupSettings) -> list[tuple[str, str]]:
    """The training (subject, object) pairs the setup builds HOGS for: the preset's training
    subjects' sequences, or those of ``--setup-data``'s ``p1`` training split."""
    if s.data is None:
        preset = get_preset(s.preset)
        pairs = [(p.sid, q.object) for p in preset.subjects if p.split == "train" for q in p.sequences]
    else:
        pairs = train_pairs(Path(s.data))
    return list(dict.fromkeys(pairs))


def build_setup(cfg: DownstreamConfig, out: Path) -> dict[str, Any]:
    """Data root and bundle: given, or built by the demo's cached stages in ``out/setup``."""
    given = Path(cfg.setup.free_bundle).resolve() if cfg.setup.free_bundle else None
    if cfg.setup.bundle is not None:
        data = Path(cfg.setup.data).resolve()
        return {
            "data": data,
            "bundle": Path(cfg.setup.bundle).resolve(),
            "free_bundle": given,
            "backgrounds": background_folder(cfg, data, out),
            "stage_seconds": {},
        }
    s = cfg.setup
    pairs = setup_pairs(s)
    demo = DemoConfig(
        preset=s.preset,
        data=s.data,
        pairs=tuple(pairs),
        hogs_iters=s.hogs_iters,
        hogs_image_size=s.hogs_image_size,
        srm_iters=s.srm_iters,
        srm_gan=s.srm_gan,
        contactnet_iters=s.contactnet_iters,
        bank_per_sequence=s.bank_per_sequence,
        bank_variants=s.bank_variants,
        bank_finger_scale=s.bank_finger_scale,
        bank_frames=s.bank_frames,
    )
    data, bundle, seconds = build_bundle_stages(out / "setup", demo, log=_say)
    data, bundle = Path(data).resolve(), Path(bundle).resolve()  # one name per setup, also through links
    setup = {
        "data": data,
        "bundle": bundle,
        "backgrounds": background_folder(cfg, data, out),
        "stage_seconds": seconds,
        "pairs": pairs,
        "free_bundle": given,
    }
    if s.free and (not cfg.report_only or (out / "setup" / "free" / "stages" / "bundle.json").is_file()):
        _, free, free_seconds = build_bundle_stages(out / "setup", demo, log=_say, gaussians="free")
        setup["free_bundle"] = Path(free).resolve()
        setup["stage_seconds"] = {**seconds, **{f"free/{k}": v for k, v in free_seconds.items() if k != "world"}}
    return setup


def background_folder(cfg: DownstreamConfig, data: Path, out: Path) -> Path:
    """Folder of the synthetic frames' backgrounds (plates built once, cached by settings)."""
    if cfg.synthetic.backgrounds == "photos":
        return demo_photographs(out / "backgrounds")
    plates = PlateConfig(data=str(data), out=str(out / "setup" / "plates"))
    manifest = Path(plates.out) / PLATES_MANIFEST
    old = json.loads(manifest.read_text()) if manifest.is_file() else {}
    wanted = json.loads(json.dumps(asdict(plates)))  # as stored (tuples become lists)
    # where the plates live is not what they are: an OUT that reaches the setup through another path reuses them
    saved = old.get("settings") if isinstance(old.get("settings"), dict) else {}
    same = {k: v for k, v in saved.items() if k != "out"} == {k: v for k, v in wanted.items() if k != "out"}
    if not same or old.get("data_fingerprint") != data_fingerprint(ArcticRoot(data)):
        _say(f"[setup] background plates of {data} -> {plates.out}")
        build_plates(plates, log=lambda m: _say(f"[plates] {m}"))
    return Path(plates.out)


def synthetic_key(cfg: DownstreamConfig, frames_only: bool = False) -> dict[str, Any]:
    """The synthetic settings in cache keys; ``frames_only``: without the mix and the supervision,
    which the exported frames do not depend on."""
    syn = asdict(cfg.synthetic)
    if frames_only:
        syn.pop("mix", None)
        syn.pop("supervise", None)
    return syn


def setup_fingerprints(cfg: DownstreamConfig, setup: dict[str, Any]) -> dict[str, str]:
    """Hashes of what the setup holds, one per depth a run reads it to (a world or bundle
    rebuilt in place gets new ones):

    * ``"world"``: the data (world record) -- the real arms;
    * ``"bundle"``: also the bundle without its pose banks -- variants that do not draw from
      the bank;
    * ``"all"``: also the pose banks -- variants that draw from the bank;
    * ``"free"``: the data and the free-3DGS bundle -- the free variant.
    """

    def digest(f: Path, drop: tuple[str, ...] = ()) -> Optional[str]:
        if not f.is_file():
            return None
        if not drop:
            return hashlib.sha256(f.read_bytes()).hexdigest()
        body = {k: v for k, v in json.loads(f.read_text()).items() if k not in drop}
        return hashlib.sha256(json.dumps(body, sort_keys=True).encode()).hexdigest()

    # ``free`` is read through the free bundle's manifest below, by the free variant alone (the
    # "all" key digests only a given --setup-free-bundle), so that the other arms' keys do not change with it
    s = {k: v for k, v in asdict(cfg.setup).items() if k != "free"}
    free_manifest = Path(setup.get("free_bundle") or "/nonexistent") / "manifest.json"
    world = digest(Path(setup["data"]) / "meta" / "hogsa_world.json")
    manifest = Path(setup["bundle"]) / "manifest.json"
    no_bank = {k: v for k, v in s.items() if not k.startswith("bank_") and k != "free_bundle"}  # bank_*: the banks
    return {
        "world": _key([{"preset": s["preset"], "data": s["data"]}, world]),
        "bundle": _key([no_bank, world, digest(manifest, drop=("pose_banks",))]),
        "all": _key(
            [s, world, digest(manifest), digest(Path(cfg.setup.free_bundle or "/nonexistent") / "manifest.json")]
        ),
        "free": _key(
            [{"data": s["data"], "preset": s["preset"], "free_bundle": s["free_bundle"]}, world, digest(free_manifest)]
        ),
    }


def reads(arm_or_variant: Optional[str]) -> str:
    """Which :func:`setup_fingerprints` entry a run or an export depends on."""
    variant = ARM_SPECS[arm_or_variant][1] if arm_or_variant in ARM_SPECS else arm_or_variant
    return {None: "world", "no_pom": "bundle", "free": "free"}.get(variant, "all")


def variant_options(variant: str, cfg: DownstreamConfig, setup: dict[str, Any]) -> Optional[dict[str, Any]]:
    """HOGSADataset arguments of a synthetic variant (None: not available)."""
    bundle = setup["bundle"]
    if variant == "free":
        if setup.get("free_bundle") is None:
            return None
        bundle = setup["free_bundle"]
    poses: dict[str, Any] = {"poses": "bank"}
    if variant == "no_pom":  # the annotated training poses, unperturbed
        poses = {"poses": "perturb", "pose_options": {"finger_std": 0.0}}
    return {"bundle": str(bundle), "srm": variant != "no_srm", **poses}


def export_dir(variant: str, cfg: DownstreamConfig, setup: dict[str, Any], out: Path) -> Path:
    """Folder of a variant's export, named by everything its frames depend on."""
    key = _key(
        [
            variant_options(variant, cfg, setup),
            setup["fingerprints"][reads(variant)],
            synthetic_key(cfg, frames_only=True),
            cfg.model.img_res,
        ]
    )
    return out / "synthetic" / f"{variant}-{key[:10]}"


def export_variant(variant: str, cfg: DownstreamConfig, setup: dict[str, Any], out: Path) -> dict[str, Any]:
    """Render the frames of one synthetic variant once (resumable ``hogsa export`` shards)."""
    opts = variant_options(variant, cfg, setup)
    assert opts is not None
    s = cfg.synthetic
    shard = s.render_batch * max(1, 256 // s.render_batch)
    config = with_options(
        background_folder=setup["backgrounds"],
        camera_plates=s.backgrounds == "camera_plates",
        poses=opts["poses"],
        pose_options=opts.get("pose_options") or {},
        srm=opts["srm"],
        device=cfg.device,
        batch_size=s.render_batch,
        seed=s.seed,
        num_samples=s.frames,
        split="train",
        arctic=ArcticConfig(img_res=cfg.model.img_res),
        cameras=CameraConfig(dataset_prob=1.0) if s.cameras == "dataset" else CameraConfig(),
        other_hands=s.other_hands,
    )
    ds = HOGSADataset(opts["bundle"], setup["data"], config)
    info = {
        "variant": variant,
        **opts,
        "data": str(setup["data"]),
        "seed": s.seed,
        "img_res": cfg.model.img_res,
        "setup": setup["fingerprints"][reads(variant)],
        "other_hands": s.other_hands,
    }
    folder = export_dir(variant, cfg, setup, out)
    t0 = time.perf_counter()
    rec = write_shards(dataset_frames_for_shard(ds, s.frames, shard), folder, s.frames, shard, info=info, progress=True)
    kept = int(rec["num_samples_written"])
    return {
        "variant": variant,
        "requested": s.frames,
        "samples": kept,
        "seconds": round(time.perf_counter() - t0, 1),
        "written": len(rec["written"]),
        "skipped": len(rec["skipped"]),
        "dropped": rec["dropped"],  # by reason; None where a shard did not record its reasons
        "dropped_total": rec["num_dropped"] if rec["complete"] else None,
        "settings": info,
    }


# ----------------------------------------------------------------------------- one run


def _single_thread(_: int) -> None:
    torch.set_num_threads(1)


def _loader(ds: Any, batch_size: Optional[int], order: Optional[np.ndarray], workers: int) -> DataLoader:
    """Samples of ``ds`` in ``order`` (None: in index order), batched unless ``batch_size`` is None."""
    return DataLoader(
        ds,
        batch_size=batch_size,
        sampler=None if order is None else order.tolist(),
        num_workers=workers,
        worker_init_fn=_single_thread if workers else None,
        generator=torch.Generator().manual_seed(0),  # workers' base seed; samples draw from (seed, epoch, index)
    )


def epoch_order(n: int, seed: int, epoch: int, stream: int) -> np.ndarray:
    """The shuffled order of one pass over ``n`` samples: a fixed draw per (seed, epoch, stream),
    so a run can start anywhere in it (stream 0: real frames, 1: synthetic frames)."""
    return np.random.default_rng([seed, epoch, stream]).permutation(n)


def _synthetic_stream(ds: Any, seed: int, workers: int, start: int = 0) -> Iterator[Any]:
    """Endless single samples of an export, reshuffled and re-augmented each pass, from the
    ``start``-th sample of the stream on."""
    n = len(ds)
    epoch, offset = divmod(start, n)
    while True:
        ds.set_epoch(epoch)
        yield from _loader(ds, None, epoch_order(n, seed, epoch, 1)[offset:], workers)
        epoch, offset = epoch + 1, 0


#: A hand touches the object when one of its vertices is this close to an object vertex (m;
#: the nearest-vertex distances of ArcticNet-SF's targets, which CDev_ho also reads).
TOUCH_M = 0.005


class TouchingHandsOnly(Dataset):
    """Samples whose hands that do not touch the object are marked invalid (``right_valid`` /
    ``left_valid`` and every ``joints_valid_{r,l}`` 0, as ARCTIC marks a hand outside the crop),
    so that ArcticNet-SF's loss supervises only the touching hands of each sample. As for an
    out-of-crop hand, the object's translation terms relative to that hand go with it. Whether a
    hand touches does not depend on the augmentation (which turns hands and object together), so
    it is worked out once per sample and remembered across epochs.

    Args:
        samples: ``(inputs, targets, meta_info)`` samples (with ``set_epoch``).
        layers: the layers the targets are prepared with (the hand-object distances).
        img_res: patch side (px) of the samples.
    """

    def __init__(self, samples: Any, layers: BodyLayers, img_res: int) -> None:
        self.samples, self.layers, self.img_res = samples, layers, img_res
        self._touching: dict[int, tuple[bool, bool]] = {}

    def __len__(self) -> int:
        return len(self.samples)

    def set_epoch(self, epoch: int) -> None:
        self.samples.set_epoch(epoch)

    def touching(self, i: int, targets: dict, meta_info: dict) -> tuple[bool, bool]:
        """(right, left) of sample ``i`` touch the object (prepared once per sample)."""
        if i not in self._touching:
            one_t, one_m = default_collate([targets]), default_collate([meta_info])
            with torch.no_grad():
                prepared, _ = prepare_targets(
                    one_t,
                    one_m,
                    self.layers.mano_r,
                    self.layers.mano_l,
                    self.layers.objects,
                    self.img_res,
                    field="hands",
                )
            self._touching[i] = (float(prepared["dist.ro"].min()) < TOUCH_M, float(prepared["dist.lo"].min()) < TOUCH_M)
        return self._touching[i]

    def __getitem__(self, i: int) -> tuple[dict, dict, dict]:
        inputs, targets, meta_info = self.samples[i]
        targets = dict(targets)
        for side, key, touches in zip("rl", ("right_valid", "left_valid"), self.touching(i, targets, meta_info)):
            if not touches:
                targets[key] = targets[key] * 0
                targets[f"joints_valid_{side}"] = targets[f"joints_valid_{side}"] * 0
        return inputs, targets, meta_info


def low_data_indices(n: int, fraction: float) -> list[int]:
    """The fixed subset of the low-data arms (seed-independent, sorted)."""
    k = max(1, int(round(n * fraction)))
    return sorted(np.random.default_rng(20250125).permutation(n)[:k].tolist())


def batch_composition(arm: str, cfg: DownstreamConfig) -> tuple[int, int]:
    """(real, synthetic) samples in each training batch of an arm."""
    B = cfg.train.batch_size
    if ARM_SPECS[arm][1] is None:
        return B, 0
    if cfg.synthetic.mix == "add":
        return B, added_synthetic(cfg.synthetic.share, B)
    n_syn = num_synthetic(cfg.synthetic.share, B)
    return B - n_syn, n_syn


def train_batches(
    arm: str, seed: int, cfg: DownstreamConfig, setup: dict[str, Any], out: Path, start: int = 0
) -> Iterator[Any]:
    """Endless training batches of an arm from batch ``start`` on (0-based): real epochs, mixed
    with synthetic samples when the arm has them.

    Every batch is a function of (arm, seed, its index) only: each real epoch takes the real
    loader's whole batches (``--train-batch-size``, the last incomplete one dropped) of a fixed
    shuffle, :func:`epoch_order`, and the mixed batches use those real samples in order; the
    synthetic samples are one endless shuffled stream, ``n_syn`` per batch. So a resumed run
    starts its stream at batch ``start`` without loading the batches before it.
    """
    share, variant = ARM_SPECS[arm]
    acfg = ArcticConfig(img_res=cfg.model.img_res)
    real = ArcticDataset(setup["data"], split="p1_train", seed=seed, config=acfg)
    real_part: Any = real if share == "all" else Subset(real, low_data_indices(len(real), cfg.low_data))
    B, (n_real, n_syn) = cfg.train.batch_size, batch_composition(arm, cfg)
    usable = len(real_part) // B * B  # the real loader drops its last incomplete batch
    per_epoch = usable // n_real
    if per_epoch == 0:
        raise RuntimeError(f"{arm}: the real training set ({len(real_part)} frames) is smaller than one batch")
    epoch, offset = divmod(start, per_epoch)
    syn_stream = None
    if variant is not None:
        syn: Any = SynthShardSamples(export_dir(variant, cfg, setup, out), seed=seed, cfg=acfg)
        if cfg.synthetic.supervise == "touching":
            syn = TouchingHandsOnly(syn, BodyLayers.from_root(ArcticRoot(setup["data"])), cfg.model.img_res)
        syn_stream = _synthetic_stream(syn, seed, cfg.train.workers, start=start * n_syn)
    while True:
        real.set_epoch(epoch)
        order = epoch_order(len(real_part), seed, epoch, 0)[offset * n_real : usable]
        loader = _loader(real_part, B, order, cfg.train.workers)
        source: Any = (
            loader
            if syn_stream is None
            else MixedLoader(loader, syn_stream, cfg.synthetic.share, mode=cfg.synthetic.mix)
        )
        yield from source
        epoch, offset = epoch + 1, 0


def build_model(cfg: DownstreamConfig, layers: Any, data: Optional[Path] = None) -> torch.nn.Module:
    """The model of ``cfg.model.kind`` on ``layers``; InterField-SF reads the MANO decimator
    (``meta/mano_decimator_195.npy``) of the dataset root ``data``."""
    model: torch.nn.Module
    if cfg.model.kind == "interfield_sf":
        assert data is not None, "InterField-SF needs the dataset root (its MANO decimator)"
        path = ArcticRoot(data).meta_dir / "mano_decimator_195.npy"
        decimator = read_mano_decimator(path, int(layers.mano_r.v_template.shape[0]))
        model = InterFieldSF(cfg.model.backbone, layers.mano_r, layers.mano_l, layers.objects, decimator)
    else:
        model = ArcticNetSF(
            cfg.model.backbone,
            layers.mano_r,
            layers.mano_l,
            layers.objects,
            focal_length=1000.0,
            img_res=cfg.model.img_res,
        )
    if cfg.model.weights:
        load_backbone_weights(model.backbone, cfg.model.weights)
    return model


def start_weights(
    model: torch.nn.Module, arm: str, seed: int, cfg: DownstreamConfig, setup: dict[str, Any], layers: Any
) -> None:
    """A run's starting point: the ``--model-init`` checkpoint of its seed, else the random
    weights with every head's camera started at the arm's :func:`camera_prior`."""
    tag = f"[{arm} seed {seed}]"
    if cfg.model.init is not None:
        path = init_path(cfg, seed)
        load_init(cfg, model, path)
        _say(f"{tag} started from {path}")
    elif cfg.model.camera_prior > 0 and cfg.model.kind == "arcticnet_sf":
        prior = camera_prior(arm, cfg, setup, layers)
        model.init_cameras(prior)
        _say(
            f"{tag} camera prior (s, tx, ty): "
            + ", ".join(f"{k} {[round(float(x), 3) for x in v]}" for k, v in prior.items())
        )


def camera_prior(arm: str, cfg: DownstreamConfig, setup: dict[str, Any], layers: Any) -> dict[str, torch.Tensor]:
    """Mean target camera of ``cfg.model.camera_prior`` real training frames of the arm (a fixed
    draw, unaugmented: the same for every seed, and for the real and HOGSA arms of one real share)."""
    real = ArcticDataset(
        setup["data"], split="p1_train", seed=0, augment=False, config=ArcticConfig(img_res=cfg.model.img_res)
    )
    pool = list(range(len(real))) if ARM_SPECS[arm][0] == "all" else low_data_indices(len(real), cfg.low_data)
    pick = np.random.default_rng(7).permutation(len(pool))[: cfg.model.camera_prior]
    loader = _loader(Subset(real, [pool[i] for i in sorted(pick)]), cfg.train.batch_size, None, cfg.train.workers)
    return mean_cameras(loader, layers, cfg.model.img_res, cfg.device)


def val_dataset(cfg: DownstreamConfig, setup: dict[str, Any]) -> tuple[Any, list[int]]:
    """The held-out subject's frames (``p1_val``, no augmentation) and their temporal order."""
    val = ArcticDataset(
        setup["data"], split="p1_val", seed=0, augment=False, config=ArcticConfig(img_res=cfg.model.img_res)
    )
    return val, temporal_order(val.imgnames)


def val_batches(cfg: DownstreamConfig, val: tuple[Any, list[int]], stride: int) -> tuple[DataLoader, int]:
    """Every ``stride``-th frame of :func:`val_dataset` in temporal order."""
    order = val[1][::stride]
    return _loader(Subset(val[0], order), cfg.train.batch_size, None, cfg.train.workers), len(order)


def eval_steps(cfg: DownstreamConfig) -> list[int]:
    n, steps = cfg.train.evals, cfg.train.steps
    return sorted({max(1, round(steps * (i + 1) / n)) for i in range(n)})


def init_path(cfg: DownstreamConfig, seed: int) -> Path:
    """The checkpoint a run of ``seed`` starts from (``--model-init`` with ``{seed}`` replaced)."""
    assert cfg.model.init is not None
    return Path(cfg.model.init.replace("{seed}", str(seed)))


_DIGESTS: dict[tuple[str, int, int], str] = {}


def file_digest(path: Path) -> str:
    """sha256 of a file's bytes (remembered per path, size and modification time)."""
    st = path.stat()
    tag = (str(path.resolve()), st.st_size, st.st_mtime_ns)
    if tag not in _DIGESTS:
        _DIGESTS[tag] = sha256_file(path)
    return _DIGESTS[tag]


def model_key(cfg: DownstreamConfig, seed: int) -> dict[str, Any]:
    """The model settings in a run's cache key: backbone, patch side and backbone weights; the
    sha256 of the seed's ``--model-init`` file (its bytes, wherever it lies) for a run from a
    checkpoint, else the camera prior when it is on (absent for a random camera start and for
    InterField-SF, which has no camera)."""
    model = asdict(cfg.model)
    init = model.pop("init")
    if init is not None:
        model["init_sha256"] = file_digest(init_path(cfg, seed))
        del model["camera_prior"]  # not applied to a checkpoint
    elif model["camera_prior"] == 0 or cfg.model.kind != "arcticnet_sf":
        del model["camera_prior"]
    return model


def train_key(cfg: DownstreamConfig) -> dict[str, Any]:
    """The optimisation settings in cache keys: ``checkpoint_every`` left out, ``workers`` keyed
    as 1 (the batches do not depend on it)."""
    train = asdict(cfg.train)
    del train["checkpoint_every"]
    train["workers"] = 1
    return train


def learning_rate(step: int, cfg: DownstreamConfig) -> float:
    """The learning rate of optimisation step ``step`` (1-based): a function of the step alone, so
    a resumed run continues on the same schedule."""
    if cfg.train.lr_schedule == "linear":
        return cfg.train.lr * (cfg.train.steps - step + 1) / cfg.train.steps
    return cfg.train.lr


def run_settings(arm: str, seed: int, cfg: DownstreamConfig, setup: dict[str, Any]) -> dict[str, Any]:
    """What a run's result depends on (its cache key)."""
    _, variant = ARM_SPECS[arm]
    syn = synthetic_key(cfg) if variant else None
    return {
        "version": RESULT_VERSION,
        "arm": arm,
        "seed": seed,
        "data": str(setup["data"]),
        "setup": setup["fingerprints"][reads(arm)],
        "bundle": str(setup["bundle"]) if variant else None,
        "variant": variant and variant_options(variant, cfg, setup),
        "synthetic": syn,
        "model": model_key(cfg, seed),
        "train": train_key(cfg),
        "low_data": cfg.low_data if ARM_SPECS[arm][0] == "low" else None,
    }


def run_dir(arm: str, seed: int, cfg: DownstreamConfig, out: Path) -> Path:
    """Folder of one (arm, seed) run: HOGSA arms with appended synthetic samples apart from
    the replace runs, runs from each ``--model-init`` (``+ft-<hash of the option>``) apart
    from those from random weights, and runs with the linear learning-rate schedule
    (``+linear``) apart from those at a constant rate, and HOGSA runs that supervise only the
    touching hands (``+touching``) and those showing other subjects' hands (``+hands<share>``)
    apart from the others, and InterField-SF runs (``+interfield_sf``) apart from ArcticNet-SF
    runs, so that all of them can share one OUT
    (and its exports)."""
    synthetic = ARM_SPECS[arm][1] is not None
    add = synthetic and cfg.synthetic.mix == "add"
    name = f"{arm}+add" if add else arm
    if cfg.model.kind != "arcticnet_sf":  # another model's runs: folders of their own
        name += "+" + cfg.model.kind
    if cfg.model.init is not None:  # one folder per --model-init, so fine-tunings of several models coexist
        name += "+ft-" + hashlib.sha256(cfg.model.init.encode()).hexdigest()[:8]
    if cfg.train.lr_schedule != "constant":
        name += "+" + cfg.train.lr_schedule
    if synthetic and cfg.synthetic.supervise != "all":
        name += "+" + cfg.synthetic.supervise
    if synthetic and cfg.synthetic.other_hands > 0:
        name += f"+hands{cfg.synthetic.other_hands:g}"
    return out / "runs" / name / f"seed{seed}"


def _result_at(res_path: Path, key: str) -> Optional[dict[str, Any]]:
    """The result saved at ``res_path`` when its key is ``key``, else None."""
    if not res_path.is_file():
        return None
    old = json.loads(res_path.read_text())
    return old if old.get("key") == key else None


def finished_run(
    arm: str, seed: int, cfg: DownstreamConfig, setup: dict[str, Any], out: Path
) -> Optional[dict[str, Any]]:
    """The saved result of (arm, seed) when it was run with the current settings, else None."""
    return _result_at(run_dir(arm, seed, cfg, out) / "result.json", _key(run_settings(arm, seed, cfg, setup)))


def adopt_shared_folder_runs(cfg: DownstreamConfig, setup: dict[str, Any], out: Path) -> None:
    """Move finished linear-schedule runs that sit in the constant-rate folder of their (arm,
    seed) -- where such runs were written before they had folders of their own -- to their own
    folder; a result is moved only when its key is the current run's."""
    if cfg.train.lr_schedule == "constant":
        return
    shared = replace(cfg, train=replace(cfg.train, lr_schedule="constant"))
    for arm in cfg.arms:
        for seed in cfg.seeds:
            own, there = run_dir(arm, seed, cfg, out), run_dir(arm, seed, shared, out)
            if own.exists() or _result_at(there / "result.json", _key(run_settings(arm, seed, cfg, setup))) is None:
                continue
            own.parent.mkdir(parents=True, exist_ok=True)
            os.replace(there, own)
            _say(f"[{arm} seed {seed}] linear-schedule run moved from {there} to {own}")


def _save_progress(folder: Path, step: int, model: Any, opt: torch.optim.Optimizer, state: dict[str, Any]) -> None:
    """Write ``checkpoints/step_N`` (network, Adam moments, progress) and point ``latest.json`` at it."""
    tensors = network_and_adam_tensors(model, opt)
    tensors["rng.torch"] = torch.get_rng_state()
    device = opt.param_groups[0]["params"][0].device
    if device.type == "cuda":  # dropout on a GPU draws from its own generator
        tensors["rng.cuda"] = torch.cuda.get_rng_state(device)
    ck = folder / "checkpoints" / f"step_{step:07d}"
    save_trainer_state(ck, tensors, {**state, "step": step})
    commit_checkpoint(ck, step)


def _load_progress(folder: Path, key: str, model: Any, opt: torch.optim.Optimizer) -> Optional[dict[str, Any]]:
    """Restore the last saved state of a run with this ``key`` into ``model`` and ``opt``; None
    when there is none (or it belongs to other settings)."""
    found = read_latest_trainer_state(folder, required=("rng.torch",))
    if found is None:
        return None
    latest, state, tensors = found
    if state.get("key") != key:
        _say(f"[{folder}] the saved state (step {state['step']}) belongs to other settings: starting again")
        return None
    load_network_and_adam(latest, tensors, model, opt)
    torch.set_rng_state(tensors["rng.torch"])
    p = opt.param_groups[0]["params"][0]
    if p.is_cuda:
        if "rng.cuda" not in tensors:
            raise AssetError(latest, "the saved state has no CUDA generator state (saved by a CPU run)")
        torch.cuda.set_rng_state(tensors["rng.cuda"], p.device)
    return state


def train_step(cfg: DownstreamConfig, model: Any, batch: Any, layers: BodyLayers, opt: torch.optim.Optimizer) -> dict:
    """One optimisation step of the configured model kind (its own loss, ARCTIC's gradient clip)."""
    step = field_training_step if cfg.model.kind == "interfield_sf" else training_step
    return step(model, batch, layers, opt, cfg.model.img_res, grad_clip=cfg.train.grad_clip, device=cfg.device)


def evaluate_model(cfg: DownstreamConfig, model: Any, loader: Any, layers: BodyLayers, temporal: bool) -> dict:
    """ARCTIC's metrics of the configured model kind over ``loader``."""
    run = evaluate_field if cfg.model.kind == "interfield_sf" else evaluate
    return run(model, loader, layers, cfg.model.img_res, cfg.device, temporal=temporal)


def run_arm(arm: str, seed: int, cfg: DownstreamConfig, setup: dict[str, Any], out: Path) -> dict[str, Any]:
    """Train one (arm, seed), evaluate it along the way; reuse a finished run with the same
    settings, and continue an interrupted one from its last saved state (``checkpoints/``)."""
    folder = run_dir(arm, seed, cfg, out)
    settings = run_settings(arm, seed, cfg, setup)
    key = _key(settings)
    res_path = folder / "result.json"
    old = finished_run(arm, seed, cfg, setup, out)
    if old is not None:
        _say(f"[{arm} seed {seed}] finished earlier: reused")
        return old
    if res_path.is_file():
        _say(f"[{arm} seed {seed}] settings changed since the saved result: run again")
    torch.manual_seed(seed)
    layers = BodyLayers.from_root(ArcticRoot(setup["data"])).to(cfg.device)
    model = build_model(cfg, layers, setup["data"]).to(cfg.device)
    start_weights(model, arm, seed, cfg, setup, layers)
    opt = torch.optim.Adam(model.parameters(), lr=cfg.train.lr)
    progress = _load_progress(folder, key, model, opt)
    state: dict[str, Any] = progress or {
        "key": key,
        "step": 0,
        "history": [],  # per step: {"loss", loss terms...}
        "evals": [],  # the curve
        "train_time_s": 0.0,
        "eval_time_s": 0.0,
        "resumed_at": [],
    }
    done = int(state["step"])
    if done:
        _say(f"[{arm} seed {seed}] resumed after step {done}")
        state["resumed_at"] = [*state.get("resumed_at", []), done]
    batches = train_batches(arm, seed, cfg, setup, out, start=done)
    val = val_dataset(cfg, setup)
    points = eval_steps(cfg)
    t0 = time.perf_counter() - state["train_time_s"] - state["eval_time_s"]
    bar = tqdm(total=cfg.train.steps, initial=done, desc=f"{arm} seed {seed}", unit="step", dynamic_ncols=True)
    final: dict[str, Any] = {}
    for step in range(done + 1, cfg.train.steps + 1):
        for group in opt.param_groups:
            group["lr"] = learning_rate(step, cfg)
        try:
            rec = train_step(cfg, model, next(batches), layers, opt)
        except FloatingPointError as exc:  # recorded as diverged; the other runs go on
            bar.close()
            _say(f"[{arm} seed {seed}] diverged at step {step}: {exc}")
            result = {
                "key": key,
                "settings": settings,
                "diverged": step,
                "summary": {m: None for m in KIND_METRICS[cfg.model.kind][0]},
                "curve": state["evals"],
                "val_frames": 0,
            }
            _atomic_json(res_path, result)
            shutil.rmtree(folder / "checkpoints", ignore_errors=True)
            return result
        state["history"].append({k: float(v) for k, v in rec.items()})
        bar.update(1)
        bar.set_postfix(loss=f"{rec['loss']:.3f}")
        if step in points:
            te = time.perf_counter()
            last = step == points[-1]
            loader, n = val_batches(cfg, val, 1 if last else cfg.train.eval_stride)
            ev = evaluate_model(cfg, model, loader, layers, temporal=last)
            state["eval_time_s"] += time.perf_counter() - te
            state["evals"].append({"step": step, "frames": n, **{k: _num(v) for k, v in ev["summary"].items()}})
            if last:
                final = ev
            a, b = KIND_METRICS[cfg.model.kind][1]
            bar.write(
                f"[{arm} seed {seed}] step {step}: {PAIRED_NAMES[a]} {ev['summary'].get(a, float('nan')):.2f} mm,"
                f" {PAIRED_NAMES[b]} {ev['summary'].get(b, float('nan')):.2f} mm ({n} val frames)"
            )
        state["train_time_s"] = time.perf_counter() - t0 - state["eval_time_s"]
        every = cfg.train.checkpoint_every
        if every and step % every == 0 and step < cfg.train.steps:
            _save_progress(folder, step, model, opt, state)
    bar.close()
    net = {k: v.detach().cpu().contiguous() for k, v in model.network_state_dict().items()}
    write_tensors_and_manifest(
        folder, "model.safetensors", net, "model.json", {"kind": cfg.model.kind, "settings": settings}
    )
    losses = [h["loss"] for h in state["history"]]
    terms = [{k: v for k, v in h.items() if k != "loss"} for h in state["history"]]
    result = {
        "key": key,
        "settings": settings,
        "summary": {k: _num(v) for k, v in final["summary"].items()},
        "val_frames": final["frames"],
        "clips": clip_sums(final, KIND_METRICS[cfg.model.kind][1]),
        "curve": state["evals"],
        "loss_first": losses[0],
        "loss_last": losses[-1],
        "loss_curve": [float(np.mean(losses[i : i + 10])) for i in range(0, len(losses), 10)],
        "loss_terms_last": {k: float(np.mean([t.get(k, np.nan) for t in terms[-20:]])) for k in terms[-1]},
        "train_seconds": round(state["train_time_s"], 1),
        "eval_seconds": round(state["eval_time_s"], 1),
        "resumed_at": state["resumed_at"],
        "init_file": str(init_path(cfg, seed)) if cfg.model.init is not None else None,
    }
    _atomic_json(res_path, result)
    shutil.rmtree(folder / "checkpoints", ignore_errors=True)
    return result


def with_clips(
    arm: str, seed: int, cfg: DownstreamConfig, setup: dict[str, Any], out: Path, result: dict[str, Any]
) -> dict[str, Any]:
    """``result`` with its per-clip sums (``clips``): a result saved without them has its model
    evaluated once more on every validation frame and the sums added to its ``result.json``
    when they reproduce its MPJPE_h and CDev_ho (to 0.01 mm); otherwise it is returned as is."""
    folder = run_dir(arm, seed, cfg, out)
    weights = folder / "model.safetensors"
    if "clips" in result or result.get("diverged") or not weights.is_file() or cfg.model.kind != "arcticnet_sf":
        return result
    _say(f"[{arm} seed {seed}] per-clip metrics: evaluating the saved model once more")
    layers = BodyLayers.from_root(ArcticRoot(setup["data"])).to(cfg.device)
    model, _ = load_saved_model(weights, layers.mano_r, layers.mano_l, layers.objects)
    loader, _ = val_batches(cfg, val_dataset(cfg, setup), 1)
    ev = evaluate(model.to(cfg.device), loader, layers, cfg.model.img_res, cfg.device, temporal=False)
    clips = clip_sums(ev, CLIP_METRICS)
    for m in CLIP_METRICS:
        again, saved = clip_mean(clips, m), result["summary"].get(m)
        if again is None or saved is None or abs(again - saved) > 0.01:
            _say(f"[{arm} seed {seed}] {weights} gives {m} {again}, its result {saved}: clips not added")
            return result
    result = {**result, "clips": clips}
    _atomic_json(folder / "result.json", result)
    return result


def _num(x: Any) -> Optional[float]:
    x = float(x)
    return x if np.isfinite(x) else None


# ----------------------------------------------------------------------------- report


def aggregate(results: dict[str, dict[int, dict[str, Any]]], kind: str = "arcticnet_sf") -> dict[str, Any]:
    """Mean ± std over seeds per arm, and paired differences against the matching real arm, of
    the metrics of model ``kind`` (:data:`KIND_METRICS`)."""
    metrics, paired_metrics = KIND_METRICS[kind]
    agg: dict[str, Any] = {}
    for arm, by_seed in results.items():
        rows = {}
        for m in metrics:
            vals = [r["summary"].get(m) for r in by_seed.values()]
            vals = [v for v in vals if v is not None]
            rows[m] = {
                "mean": float(np.mean(vals)) if vals else None,
                "std": float(np.std(vals, ddof=1)) if len(vals) > 1 else None,
                "n": len(vals),
            }
        agg[arm] = rows
    paired: dict[str, Any] = {}
    for arm, by_seed in results.items():
        ref = "real_low" if ARM_SPECS[arm][0] == "low" else "real"
        if ARM_SPECS[arm][1] is None or ref not in results:
            continue
        diffs = {}
        for m in paired_metrics:
            d = {
                s: r["summary"][m] - results[ref][s]["summary"][m]
                for s, r in by_seed.items()
                if s in results[ref]
                and r["summary"].get(m) is not None
                and results[ref][s]["summary"].get(m) is not None
            }
            v = list(d.values())
            diffs[m] = {
                "per_seed": d,
                "mean": float(np.mean(v)) if v else None,
                "std": float(np.std(v, ddof=1)) if len(v) > 1 else None,
            }
            if m in paired_metrics:
                diffs[m]["clips"] = clip_uncertainty(
                    [(r.get("clips"), results[ref][s].get("clips")) for s, r in by_seed.items() if s in d],
                    m,
                    CLIP_RESAMPLES,
                )
        paired[f"{arm} - {ref}"] = diffs
    return {"arms": agg, "paired": paired}


def _cell(row: dict[str, Any]) -> str:
    if row["mean"] is None:
        return "n/a"
    return f"{row['mean']:.2f}" + (f" ± {row['std']:.2f}" if row["std"] is not None else "")


def markdown(agg: dict[str, Any], cfg: DownstreamConfig, machine: str, skipped: dict[str, str]) -> str:
    """The Table 1 / ablation / low-data tables and the paired differences."""
    metrics, (pa, pb) = KIND_METRICS[cfg.model.kind]
    model = "InterField-SF" if cfg.model.kind == "interfield_sf" else "ArcticNet-SF"
    head = "| method | " + " | ".join(metrics[m][0] + (" ↓" if metrics[m][1] else " ↑") for m in metrics) + " |"
    sep = "|" + "---|" * (len(metrics) + 1)
    names = {
        "real": f"{model} (real)",
        "hogsa": f"{model} + HOGSA",
        "hogsa_no_pom": "+ HOGSA w/o POM",
        "hogsa_no_srm": "+ HOGSA w/o SRM",
        "hogsa_free": "+ HOGSA, free 3DGS",
        "real_low": f"real {cfg.low_data:.0%}",
        "hogsa_low": f"real {cfg.low_data:.0%} + HOGSA",
    }

    def table(arms: list[str]) -> list[str]:
        rows = [head, sep]
        for a in arms:
            if a in agg["arms"]:
                rows.append(f"| {names[a]} | " + " | ".join(_cell(agg["arms"][a][m]) for m in metrics) + " |")
            elif a in skipped:
                rows.append(f"| {names[a]} | " + " | ".join("—" for _ in metrics) + f" |  ({skipped[a]})")
        return rows

    done = {a: agg["arms"][a][pa]["n"] for a in agg["arms"]}
    finished = ", ".join(f"{a}: {n}" for a, n in done.items())
    lines = [
        f"Seeds {list(cfg.seeds)} ({finished} finished), mean ± std; "
        f"{cfg.model.backbone} at {cfg.model.img_res}², "
        f"{cfg.train.steps} steps of {cfg.train.batch_size}"
        f"{' real + synthetic appended' if cfg.synthetic.mix == 'add' else ''}, "
        f"synthetic share {cfg.synthetic.share}, "
        f"{cfg.synthetic.frames} synthetic frames per variant; {machine}."
        + (f" Every run fine-tuned from `{cfg.model.init}`." if cfg.model.init is not None else ""),
        "",
        "**Table 1** (p1, held-out subject)",
        "",
    ] + table(["real", "hogsa"])
    lines += ["", "**Ablation**", ""] + table(["hogsa_no_srm", "hogsa_no_pom", "hogsa_free", "hogsa"])
    lines += ["", f"**Low data** ({cfg.low_data:.0%} of the real training frames)", ""] + table(
        ["real_low", "hogsa_low"]
    )
    lines += [
        "",
        "**Paired difference per seed** (negative = HOGSA better)",
        "",
        f"| pair | Δ{PAIRED_NAMES[pa]} (mm) per seed | mean ± std | Δ{PAIRED_NAMES[pb]} (mm) per seed | mean ± std |",
        "|---|---|---|---|---|",
    ]
    for pair, d in agg["paired"].items():
        cells = []
        for m in (pa, pb):
            per = ", ".join(f"{v:+.2f}" for v in d[m]["per_seed"].values())
            ms = (
                "n/a"
                if d[m]["mean"] is None
                else f"{d[m]['mean']:+.2f}" + (f" ± {d[m]['std']:.2f}" if d[m]["std"] is not None else "")
            )
            cells += [per or "n/a", ms]
        lines.append(f"| {pair} | " + " | ".join(cells) + " |")
    lines += clip_table(agg, cfg.model.kind)
    return "\n".join(lines) + "\n"


def clip_table(agg: dict[str, Any], kind: str = "arcticnet_sf") -> list[str]:
    """The paired differences' dependence on the validation clips (:func:`clip_uncertainty`)."""
    paired = KIND_METRICS[kind][1]
    a, b = (PAIRED_NAMES[m] for m in paired)
    rows = []
    for pair, d in agg["paired"].items():
        cells: list[str] = []
        for m in paired:
            cells += [interval_text(d[m].get("clips")), left_out_text(d[m].get("clips"))]
        rows.append(f"| {pair} | " + " | ".join(cells) + " |")
    if not rows:
        return []
    n = next((d[m]["clips"]["clips"] for d in agg["paired"].values() for m in paired if d[m].get("clips")), None)
    return [
        "",
        f"**Over validation clips** ({n if n is not None else '?'} clips: subject, sequence, camera view;"
        " 95 % interval of the seed-mean difference with the clips resampled, and its range when one clip is left out)",
        "",
        f"| pair | Δ{a} 95 % interval | Δ{a}, one clip left out | Δ{b} 95 % interval | Δ{b}, one clip left out |",
        "|---|---|---|---|---|",
        *rows,
    ]


def plot(
    results: dict[str, dict[int, dict[str, Any]]], agg: dict[str, Any], path: Path, kind: str = "arcticnet_sf"
) -> None:
    """Validation curves per arm (mean over seeds, min–max band) and metric bars with the seed spread."""
    import matplotlib  # deferred: the Agg backend is chosen before pyplot loads

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt  # deferred: after matplotlib.use

    arms = list(results)
    fig, axes = plt.subplots(2, 2, figsize=(13, 9))
    colors = plt.rcParams["axes.prop_cycle"].by_key()["color"]
    metrics, paired = KIND_METRICS[kind]
    for ax, m in zip(axes[0], paired):
        for i, arm in enumerate(arms):
            curves = [r["curve"] for r in results[arm].values() if not r.get("diverged")]
            if not curves:
                continue
            n = min(len(c) for c in curves)
            curves = [c[:n] for c in curves]
            steps = [p["step"] for p in curves[0]]
            vals = np.array([[p.get(m) if p.get(m) is not None else np.nan for p in c] for c in curves], float)
            mean = np.nanmean(vals, 0)
            ax.plot(steps, mean, "-o", color=colors[i % len(colors)], label=arm, ms=3)
            if len(curves) > 1:
                ax.fill_between(
                    steps, np.nanmin(vals, 0), np.nanmax(vals, 0), color=colors[i % len(colors)], alpha=0.15
                )
        shown = np.array(
            [
                p.get(m)
                for a in arms
                for r in results[a].values()
                if not r.get("diverged")
                for p in r["curve"]
                if p.get(m) is not None
            ],
            float,
        )
        shown = shown[np.isfinite(shown) & (shown > 0)]
        if shown.size and shown.max() / shown.min() > 50:  # outliers (e.g. a far object) dominate
            ax.set_yscale("log")
        ax.set_xlabel("step (last point: all val frames; earlier: a strided subset)")
        ax.set_ylabel(metrics[m][0])
        ax.set_title(f"validation {metrics[m][0]} (p1_val)")
        ax.grid(alpha=0.3)
        ax.legend(fontsize=8)
    for ax, m in zip(axes[1], paired):
        for i, arm in enumerate(arms):
            vals = [r["summary"].get(m) for r in results[arm].values()]
            vals = [v for v in vals if v is not None]
            if not vals:
                continue
            ax.bar(i, np.mean(vals), color=colors[i % len(colors)], alpha=0.6)
            ax.scatter([i] * len(vals), vals, color="k", s=12, zorder=3)
        tops = [
            np.nanmax([v for v in (r["summary"].get(m) for r in results[a].values()) if v is not None] or [np.nan])
            for a in arms
        ]
        if np.nanmin(tops) > 0 and np.nanmax(tops) / np.nanmin(tops) > 50:  # e.g. a diverged arm
            ax.set_yscale("log")
        ax.set_xticks(range(len(arms)))
        ax.set_xticklabels(arms, rotation=20, fontsize=8)
        ax.set_ylabel(metrics[m][0])
        ax.set_title(f"final {metrics[m][0]}: mean (bar) and seeds (dots)")
        ax.grid(axis="y", alpha=0.3)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


# ----------------------------------------------------------------------------- main


def machine_description(cfg: DownstreamConfig) -> str:
    if cfg.device.startswith("cuda"):
        return f"{torch.cuda.get_device_name(0)}, torch {torch.__version__}"
    return f"{available_cores()} CPU cores ({platform.processor() or platform.machine()}), torch {torch.__version__}"


def run(cfg: DownstreamConfig) -> dict[str, Any]:
    """The whole experiment; returns the ``downstream.json`` record."""
    validate(cfg)
    torch.set_num_threads(cfg.threads or available_cores())
    out = Path(cfg.out).resolve()
    out.mkdir(parents=True, exist_ok=True)
    t0 = time.perf_counter()
    previous = json.loads((out / "downstream.json").read_text()) if (out / "downstream.json").is_file() else {}
    if cfg.report_only and cfg.setup.bundle is None and not (out / "setup" / "stages" / "bundle.json").is_file():
        raise SystemExit(
            f"downstream: error: --report-only needs a finished setup in {out / 'setup'} "
            "(or --setup-data/--setup-bundle); nothing has been built yet"
        )
    setup = build_setup(cfg, out)
    setup["fingerprints"] = setup_fingerprints(cfg, setup)
    check_inits(cfg, setup)
    adopt_shared_folder_runs(cfg, setup, out)
    skipped: dict[str, str] = {}
    exports: dict[str, Any] = dict(previous.get("exports", {})) if cfg.report_only else {}
    for arm in cfg.arms:
        variant = ARM_SPECS[arm][1]
        if cfg.report_only or variant is None or variant in exports:
            continue
        if variant_options(variant, cfg, setup) is None:
            skipped[arm] = "no free-3DGS bundle (--setup-free builds one, --setup-free-bundle gives one)"
            continue
        _say(f"[synthetic] variant {variant}: {cfg.synthetic.frames} frames")
        exports[variant] = export_variant(variant, cfg, setup, out)
    results: dict[str, dict[int, dict[str, Any]]] = {}
    for seed in cfg.seeds:  # seeds outermost: every arm has a result early in a long run
        for arm in cfg.arms:
            if arm in skipped:
                continue
            if cfg.report_only:
                done = finished_run(arm, seed, cfg, setup, out)
                if done is not None:
                    results.setdefault(arm, {})[seed] = done
                elif (run_dir(arm, seed, cfg, out) / "result.json").is_file():
                    _say(f"[{arm} seed {seed}] its result was made with other settings or an older version: left out")
                continue
            results.setdefault(arm, {})[seed] = run_arm(arm, seed, cfg, setup, out)
    for arm, by_seed in results.items():
        for seed, res in by_seed.items():
            by_seed[seed] = with_clips(arm, seed, cfg, setup, out, res)
    if cfg.report_only and not results:
        raise SystemExit(f"downstream: error: no finished run in {out} matches these settings; nothing rewritten")
    agg = aggregate(results, cfg.model.kind)
    machine = machine_description(cfg)
    record = {
        "config": asdict(cfg),
        "machine": machine,
        "setup": {k: str(v) if isinstance(v, Path) else v for k, v in setup.items()},
        "exports": exports,
        "skipped": skipped,
        "results": {a: {str(s): r for s, r in rs.items()} for a, rs in results.items()},
        "aggregate": agg,
        "total_seconds": round(time.perf_counter() - t0, 1),
    }
    _atomic_json(out / "downstream.json", record)
    (out / "downstream.md").write_text(markdown(agg, cfg, machine, skipped))
    plot(results, agg, out / "downstream.png", cfg.model.kind)
    _say((out / "downstream.md").read_text())
    _say(f"[downstream] {out / 'downstream.json'}, downstream.md, downstream.png; {record['total_seconds']:.0f} s")
    return record


def parse_args(argv: Optional[list[str]] = None) -> DownstreamConfig:
    """The experiment's settings from command-line flags (``--quick`` and ``--device cuda`` first
    switch the defaults, other flags still override them)."""
    pre = argparse.ArgumentParser(add_help=False)
    pre.add_argument("--quick", action="store_true")
    pre.add_argument("--device", default="cpu")
    early = pre.parse_known_args(argv)[0]
    base = DownstreamConfig()
    if early.device.startswith("cuda"):
        base = gpu_config(base)
    if early.quick:
        base = quick_config(base)
    p = argparse.ArgumentParser(
        description=__doc__.split("\n\n")[0], formatter_class=argparse.RawDescriptionHelpFormatter
    )
    p.add_argument(
        "--quick",
        action="store_true",
        help="defaults for the tiny world: one seed, a few steps (minutes); other flags still apply",
    )
    add_dataclass_arguments(p, DownstreamConfig, base)
    return dataclass_from_args(DownstreamConfig, p.parse_args(argv))


def arm_folder(arm: str, cfg: DownstreamConfig) -> Path:
    """The folder holding ``seed<k>/`` of ``arm``'s runs under ``cfg.out`` (what ``heldout.py``'s
    ``--runs`` takes)."""
    if arm not in ARM_SPECS:
        raise SystemExit(f"downstream: error: unknown arm {arm!r}; known: {', '.join(ARMS)}")
    return run_dir(arm, 0, cfg, Path(cfg.out)).parent


def main(argv: Optional[list[str]] = None) -> int:
    run(parse_args(argv))
    return 0


if __name__ == "__main__":
    sys.exit(main())
