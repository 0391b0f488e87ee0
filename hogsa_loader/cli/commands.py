"""The sub-commands of ``hogsa`` (except ``hogsa train``): one ``_NAME_parser(sub)`` that adds
the sub-command's flags, and one ``_cmd_NAME(args)`` that runs it.

:mod:`hogsa_loader.cli.main` imports this module only when one of these commands is run, so
``hogsa --help`` and ``hogsa --version`` stay fast. Environment: CPU renders set glibc's
allocator to keep its memory (HOGSA_KEEP_MEMORY=0 leaves it alone; see README).
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import sys
import time
from pathlib import Path
from typing import Any, Sequence

import torch
from tqdm import tqdm

from hogsa_loader.assets.hands.mano_io import convert_mano_to_npz
from hogsa_loader.assets.objects import load_object_templates
from hogsa_loader.cli import checks
from hogsa_loader.cli.dataclass_args import add_dataclass_arguments, dataclass_from_args
from hogsa_loader.cli.registry import HELP
from hogsa_loader.compose.plates import PlateConfig, build_plates
from hogsa_loader.errors import AssetError, HogsaError, UsageError
from hogsa_loader.extras import require
from hogsa_loader.render.frame_maps import FrameMapsConfig, view_images, write_frame_maps
from hogsa_loader.sample.config import LoaderConfig, export_info
from hogsa_loader.sample.dataset import HOGSADataset
from hogsa_loader.sample.export import ExportMismatchError, dataset_frames_for_shard, num_shards, write_shards
from hogsa_loader.system import process_slot, rank_device
from hogsa_loader.view.config import ViewConfig, check_view_config
from hogsa_loader.view.frame_maps import frame_maps_sheet
from hogsa_loader.view.job import run_view
from hogsa_loader.view.pictures import write_png
from hogsa_loader.view.preview import hand_preview, object_preview, save_sheet
from hogsa_world import generate_world, get_preset
from hogsa_world.annotation_noise import AnnotationNoise, add_annotation_noise
from hogsa_world.demo import DemoConfig, run_demo
from hogsa_world.h2o_export import export_h2o_world
from hogsa_world.hand import synthetic_hand_pair
from hogsa_world.mano_pickle import write_mano_pickle
from hogsa_world.objects.catalogue import PROCEDURAL_NAMES, write_procedural_objects

__all__: list[str] = []


def procedural_objects(names: Sequence[str], flag: str = "--objects") -> list[str]:
    """Names of procedural objects: at least one, each known, none repeated."""
    names = list(names)
    if not names:
        raise UsageError(f"{flag}: name at least one object ({', '.join(PROCEDURAL_NAMES)})")
    unknown = [n for n in names if n not in PROCEDURAL_NAMES]
    if unknown:
        raise UsageError(f"{flag}: unknown object(s) {', '.join(unknown)}; known: {', '.join(PROCEDURAL_NAMES)}")
    dup = sorted({n for n in names if names.count(n) > 1})
    if dup:
        raise UsageError(f"{flag}: {', '.join(dup)} named twice")
    return names


def _cmd_assets(args: argparse.Namespace) -> int:
    require("skimage", "demo", "hogsa assets")
    names = procedural_objects([n for n in args.objects.split(",") if n])
    out = os.path.abspath(checks.output_dir(args.out))
    mano_dir = os.path.join(out, "body_models", "mano")
    meta_dir = os.path.join(out, "arctic_data", "data", "meta")
    steps = ["hands", "objects"] + ([] if args.no_preview else ["hand preview", "object preview"])
    t0 = time.time()
    with tqdm(total=len(steps), desc="hogsa assets", unit="step", disable=args.quiet) as bar:
        bar.set_postfix_str("hands")
        right, left = synthetic_hand_pair(seed=args.seed)
        write_mano_pickle(right, os.path.join(mano_dir, "MANO_RIGHT.pkl"))
        write_mano_pickle(left, os.path.join(mano_dir, "MANO_LEFT.pkl"))
        bar.update()
        bar.set_postfix_str("objects")
        write_procedural_objects(meta_dir, names=names, seed=args.seed)
        bar.update()
        if not args.no_preview:
            bar.set_postfix_str("hand preview")
            save_sheet(os.path.join(mano_dir, "preview.png"), hand_preview(right, left))
            bar.update()
            bar.set_postfix_str("object preview")
            templates = load_object_templates(meta_dir, names=names)
            templates = [templates[n] for n in names] if isinstance(templates, dict) else templates
            save_sheet(os.path.join(meta_dir, "object_vtemplates", "preview.png"), object_preview(templates))
            bar.update()
    print(
        f"hands:   {mano_dir}/MANO_RIGHT.pkl, MANO_LEFT.pkl ({right.num_verts} vertices, {right.faces.shape[0]} faces)"
    )
    print(f"objects: {meta_dir}/object_vtemplates/{{{','.join(names)}}}")
    if not args.no_preview:
        print(f"previews: {mano_dir}/preview.png, {meta_dir}/object_vtemplates/preview.png")
    print(f"done in {time.time() - t0:.1f} s")
    return 0


def _cmd_convert(args: argparse.Namespace) -> int:
    checks.input_file(args.src, "SRC")
    checks.output_file(args.dst, "DST", overwrite=args.overwrite, suffix=".npz", source=args.src)
    model = convert_mano_to_npz(args.src, args.dst, side=args.side, overwrite=args.overwrite)
    print(f"{args.dst}: {model.side} hand, {model.num_verts} vertices, {model.faces.shape[0]} faces")
    return 0


def _cmd_world(args: argparse.Namespace) -> int:
    require("skimage", "demo", "hogsa world")
    try:
        preset = get_preset(args.preset)
    except KeyError as exc:
        raise checks.UsageError(f"--preset: {exc.args[0]}") from None
    checks.output_dir(args.out)
    say = (lambda s: None) if args.quiet else print
    record = generate_world(
        args.out, preset, seed=args.seed, progress=not args.quiet, process_splits=not args.no_splits, log=say
    )
    out = os.path.abspath(args.out)
    n_seq = len(record["sequences"])
    say(
        f"world:   {out}/arctic_data/data ({len(record['subjects'])} subjects, {n_seq} sequences, "
        f"{record['num_frames']} frames, 9 views)"
    )
    say(f"preview: {out}/world_preview.png")
    say("timings: " + ", ".join(f"{k} {v:.1f} s" for k, v in record["timings"].items()))
    return 0


def _cmd_world_noise(args: argparse.Namespace) -> int:
    checks.input_dir(args.src, "--src")
    checks.output_dir(args.out)
    try:
        noise = AnnotationNoise(
            trans_mm=args.trans_mm, rot_deg=args.rot_deg, pose_rad=args.pose_rad, smooth=args.smooth, seed=args.seed
        )
        summary = add_annotation_noise(
            args.src, args.out, noise, process_splits=not args.no_splits, progress=not args.quiet
        )
    except (AssetError, ValueError) as exc:
        print(f"hogsa: error: {exc}", file=sys.stderr)
        return 2
    if not args.quiet:
        print(
            f"world:   {os.path.abspath(args.out)}/arctic_data/data (hand annotations perturbed; "
            f"mean vertex error {summary['overall_mean_vertex_error_mm']:.2f} mm)"
        )
        print(f"splits:  {summary['splits']}")
        print(f"summary: {os.path.abspath(args.out)}/annotation_noise.json")
    return 0


def _export_config(args: argparse.Namespace, world: int) -> LoaderConfig:
    """The loader config of ``hogsa export`` (``--num`` samples; ``cuda`` = the process's local GPU,
    ``cuda:LOCAL_RANK`` under torchrun and ``cuda:SLURM_LOCALID`` under srun)."""
    try:
        config = dataclass_from_args(LoaderConfig, args)
    except ValueError as exc:  # combinations the config refuses (e.g. --srm-tta without --srm)
        raise checks.UsageError(str(exc)) from None
    device = config.run.device
    if world > 1:  # one GPU per local process
        device = rank_device(device)
    return dataclasses.replace(config, run=dataclasses.replace(config.run, device=device, num_samples=args.num))


def _check_export_paths(args: argparse.Namespace, config: LoaderConfig) -> None:
    """Inputs exist and the output folder is usable (before the slow dataset)."""
    checks.input_dir(args.bundle, "--bundle")
    checks.input_dir(args.data, "--data")
    bg = config.backgrounds
    for flag, folder in (("--coco-root", bg.coco_root), ("--background-folder", bg.folder)):
        if folder is not None:
            checks.input_dir(folder, flag)
    if bg.coco_ann is not None:
        checks.input_file(bg.coco_ann, "--coco-ann")
    checks.output_dir(args.out)


def _cmd_export(args: argparse.Namespace) -> int:
    launched = process_slot()  # torchrun's RANK / WORLD_SIZE, srun's SLURM_PROCID / SLURM_STEP_NUM_TASKS
    rank = args.rank if args.rank is not None else launched[0]
    world = args.world_size if args.world_size is not None else launched[1]
    if not 0 <= rank < world:
        raise checks.UsageError(f"rank {rank} outside world size {world}")
    config = _export_config(args, world)
    checks.multiple_of(args.shard_size, config.run.batch_size, "--shard-size", "--batch-size")
    _check_export_paths(args, config)
    if args.threads:
        torch.set_num_threads(args.threads)
    ds = HOGSADataset(args.bundle, args.data, config)
    # the config as recorded (options left at their defaults that the first exports lacked are left out)
    info = {
        "bundle": os.path.abspath(args.bundle),
        "data": os.path.abspath(args.data),
        **export_info(config),
        "render_size": ds.render_size,
        "world_size": world,
    }
    say = (lambda m: None) if args.quiet else print
    say(
        f"hogsa export: rank {rank}/{world}, {args.num} samples in {num_shards(args.num, args.shard_size)} shards "
        f"of {args.shard_size} -> {os.path.abspath(args.out)} (device {config.run.device})"
    )
    try:
        res = write_shards(
            dataset_frames_for_shard(ds, args.num, args.shard_size),
            args.out,
            args.num,
            args.shard_size,
            rank=rank,
            world_size=world,
            progress=not args.quiet,
            image_format=args.image_format,
            alpha_bits=args.alpha_bits,
            info=info,
            overwrite=args.overwrite,
        )
    except ExportMismatchError as exc:
        print(f"hogsa: error: {exc}", file=sys.stderr)
        return 2
    st = ds.stats.as_dict()
    reasons = ", ".join(f"{k} {v}" for k, v in (res["dropped"] or {}).items() if v)
    if res["complete"] and not res["num_samples_written"]:
        print(
            f"hogsa export: error: the export kept no sample ({res['num_dropped']} dropped"
            f"{f': {reasons}' if reasons else ''}); {res['index']} lists none",
            file=sys.stderr,
        )
        return 1
    say(
        f"rank {rank}: wrote {len(res['written'])} shards ({res['samples']} samples, "
        f"{st['num_dropped']} dropped), skipped {len(res['skipped'])} complete shards, "
        f"{res['seconds']:.1f} s; index: {res['index']} ({'complete' if res['complete'] else 'incomplete'}: "
        f"{res['num_samples_written']} samples, {res['num_dropped']} dropped{f' ({reasons})' if reasons else ''})"
    )
    return 0


def _cmd_demo(args: argparse.Namespace) -> int:
    require("skimage", "demo", "hogsa demo")
    checks.output_dir(args.out)
    for flag, folder in (("--background-folder", args.backgrounds), ("--coco-root", args.coco_root)):
        if folder is not None:
            checks.input_dir(folder, flag)
    if args.coco_ann is not None:
        checks.input_file(args.coco_ann, "--coco-ann")
    if args.data is not None:
        checks.data_root_pairs(args.data, DemoConfig().pairs)
    cfg = DemoConfig(
        seed=args.seed,
        data=args.data,
        samples=args.samples,
        num_workers=args.workers,
        backgrounds=args.backgrounds,
        coco_root=args.coco_root,
        coco_ann=args.coco_ann,
        progress=not args.quiet,
    )
    if args.threads:
        torch.set_num_threads(args.threads)
    run_demo(args.out, cfg, log=None if args.quiet else print)
    return 0


def _cmd_view(args: argparse.Namespace) -> int:
    cfg = dataclass_from_args(ViewConfig, args)
    try:
        check_view_config(cfg)
        run_view(cfg, log=None if cfg.quiet else print)
    except (HogsaError, OSError) as exc:  # ViewError is a usage error (exit status 2), a bad file 1
        return checks.report("hogsa view", exc)
    return 0


def _cmd_plates(args: argparse.Namespace) -> int:
    cfg = dataclass_from_args(PlateConfig, args)
    cfg.check()
    checks.input_dir(cfg.data, "--data")
    checks.output_dir(cfg.out)
    manifest = build_plates(cfg, log=None if cfg.quiet else print)
    if not cfg.quiet:
        print(
            f"{len(manifest['plates'])} plates in {cfg.out} ({len(manifest['skipped'])} skipped); "
            "use them with --background-folder"
        )
    return 0


def _cmd_frame_maps(args: argparse.Namespace) -> int:
    cfg = dataclass_from_args(FrameMapsConfig, args)
    cfg.check()
    checks.input_dir(cfg.data, "--data")
    checks.output_dir(cfg.out)
    manifest = write_frame_maps(cfg, log=None if cfg.quiet else print)
    if manifest["views"]:  # a picture of the first view written
        folder, images = view_images(cfg, manifest["views"][0])
        if images:  # (a root with annotations but no cropped images: nothing to show)
            write_png(Path(cfg.out) / "preview.png", frame_maps_sheet(folder, images))
            if not cfg.quiet:
                print(f"[frame-maps] preview: {Path(cfg.out) / 'preview.png'}")
    return 0


def _cmd_h2o_export(args: argparse.Namespace) -> int:
    try:
        w, h = (int(v) for v in args.image_size.split("x"))
        if w <= 0 or h <= 0:
            raise ValueError
    except ValueError:
        print(
            f"hogsa: error: --image-size must be WIDTHxHEIGHT with positive integers, got {args.image_size!r}",
            file=sys.stderr,
        )
        return 2
    checks.input_dir(args.world, "--world")
    checks.output_dir(args.out)
    try:
        rec = export_h2o_world(
            args.world,
            args.out,
            subject=args.subject,
            sequence=args.sequence,
            object_class=args.object_class,
            mesh_name=args.mesh_name,
            image_size=(w, h),
            frame_stride=args.frame_stride,
            overwrite=args.overwrite,
        )
    except ValueError as exc:  # unknown class / mesh name, a sequence that is not rigid
        if isinstance(exc, HogsaError):  # problems with files: main() reports them (exit 1)
            raise
        print(f"hogsa: error: {exc}", file=sys.stderr)
        return 2
    if not args.quiet:
        print(json.dumps(rec, indent=1, default=str)[:2000])
    return 0


def _assets_parser(sub: argparse._SubParsersAction) -> None:
    """The ``hogsa assets`` sub-command."""
    a = sub.add_parser("assets", help=HELP["assets"])
    a.add_argument("--out", required=True, help="output folder (plays the role of ARCTIC's ./data)")
    a.add_argument("--objects", default="box,laptop,notebook", help="comma-separated procedural objects")
    a.add_argument("--seed", type=checks.non_negative_int, default=0)
    a.add_argument("--no-preview", action="store_true", help="skip the PNG previews")
    a.add_argument("--quiet", action="store_true", help="no progress bar")
    a.set_defaults(func=_cmd_assets)


def _convert_parser(sub: argparse._SubParsersAction) -> None:
    """The ``hogsa convert-mano`` sub-command."""
    c = sub.add_parser("convert-mano", help=HELP["convert-mano"])
    c.add_argument("src")
    c.add_argument("dst")
    c.add_argument("--side", choices=("right", "left"), default=None)
    c.add_argument("--overwrite", action="store_true", help="replace an existing DST")
    c.set_defaults(func=_cmd_convert)


def _world_parser(sub: argparse._SubParsersAction) -> None:
    """The ``hogsa world`` sub-command."""
    w = sub.add_parser("world", help=HELP["world"])
    w.add_argument("--out", required=True, help="output folder (plays the role of ARCTIC's ./data)")
    w.add_argument(
        "--preset",
        default="tiny",
        help="tiny (< 1 min, tests), demo (what hogsa demo uses), small (ARCTIC image sizes), small_styles "
        "(small, each subject and sequence with its own grasps) or small_styles_heldout (small_styles with "
        "five times its held-out sequences, to evaluate on)",
    )
    w.add_argument("--seed", type=checks.non_negative_int, default=0)
    w.add_argument("--no-splits", action="store_true", help="skip ARCTIC processing into splits/")
    w.add_argument("--quiet", action="store_true", help="no progress bar or messages")
    w.set_defaults(func=_cmd_world)


def _world_noise_parser(sub: argparse._SubParsersAction) -> None:
    """The ``hogsa world-noise`` sub-command."""
    n = sub.add_parser(
        "world-noise",
        help=HELP["world-noise"],
        description="Write a copy of a world (images, cameras and object poses linked) whose hands' "
        ".mano.npy carry noise (per-sequence offset + smoothed per-frame jitter); fitting_err holds "
        "the realised mean vertex error. Masks are not copied; the processed splits are rebuilt from the "
        "noisy labels.",
    )
    n.add_argument("--src", required=True, help="the world / ARCTIC ./data root")
    n.add_argument("--out", required=True, help="output root (must not exist)")
    n.add_argument(
        "--trans-mm", type=checks.non_negative_float, default=2.0, help="wrist translation std per axis (mm)"
    )
    n.add_argument(
        "--rot-deg", type=checks.non_negative_float, default=1.5, help="global orientation std per axis (degrees)"
    )
    n.add_argument(
        "--pose-rad", type=checks.non_negative_float, default=0.04, help="finger pose std per component (rad)"
    )
    n.add_argument(
        "--smooth", type=checks.positive_int, default=5, help="frames of the moving average of the per-frame part"
    )
    n.add_argument("--seed", type=checks.non_negative_int, default=0)
    n.add_argument("--no-splits", action="store_true", help="do not rebuild splits/ from the noisy labels")
    n.add_argument("--quiet", action="store_true")
    n.set_defaults(func=_cmd_world_noise)


def _export_parser(sub: argparse._SubParsersAction) -> None:
    """The ``hogsa export`` sub-command."""
    e = sub.add_parser(
        "export",
        help=HELP["export"],
        description="Render synthetic frames with a bundle and write them as resumable WebDataset "
        "tar shards (shard i = samples [i*S, (i+1)*S); complete shards are skipped when re-run). "
        "Under torchrun each process writes shards i with i % WORLD_SIZE == RANK.",
    )
    e.add_argument("--bundle", required=True, help="bundle folder (hogsa_loader/cli/build_bundle.py)")
    e.add_argument("--data", required=True, help="ARCTIC(-format) data root the bundle was built on")
    e.add_argument("--out", required=True, help="output folder of the shards")
    e.add_argument(
        "--num", type=checks.positive_int, required=True, help="number of sample indices (dropped ones leave gaps)"
    )
    e.add_argument(
        "--shard-size", type=checks.positive_int, default=1000, help="samples per shard (a multiple of --batch-size)"
    )
    e.add_argument("--image-format", choices=("jpg", "png"), default="jpg", help="jpg (quality 95) or png")
    e.add_argument("--alpha-bits", type=int, choices=(8, 16), default=8)
    e.add_argument(
        "--overwrite",
        action="store_true",
        help="rewrite shards in --out that another export (other settings, --num or --shard-size) wrote",
    )
    e.add_argument(
        "--rank", type=checks.non_negative_int, default=None, help="default: the launcher's (torchrun, srun) or 0"
    )
    e.add_argument(
        "--world-size", type=checks.positive_int, default=None, help="default: the launcher's (torchrun, srun) or 1"
    )
    e.add_argument("--threads", type=checks.non_negative_int, default=0, help="torch CPU threads (0 = default)")
    e.add_argument("--quiet", action="store_true", help="no progress bar or messages")
    add_dataclass_arguments(e, LoaderConfig)  # the loader's options: one flag per LoaderConfig field
    e.set_defaults(func=_cmd_export)


def _demo_parser(sub: argparse._SubParsersAction) -> None:
    """The ``hogsa demo`` sub-command."""
    d = sub.add_parser(
        "demo",
        help=HELP["demo"],
        description="Build (or reuse, cached per stage) the demo world and a small bundle, stream "
        "synthetic samples through a DataLoader, write samples.png (synthetic next to real, 2D labels "
        "drawn), batch.npz and demo.json, and print the throughput.",
    )
    d.add_argument("--out", default="./hogsa_demo", help="demo folder (reused as a cache on later runs)")
    d.add_argument("--seed", type=int, default=0)
    d.add_argument("--data", default=None, help="use this ARCTIC(-format) data root instead of building the demo world")
    d.add_argument("--samples", type=checks.positive_int, default=64, help="synthetic samples to stream")
    d.add_argument("--workers", type=checks.non_negative_int, default=2, help="DataLoader workers rendering on the CPU")
    d.add_argument(
        "--threads", type=checks.non_negative_int, default=0, help="torch CPU threads of the main process (0 = default)"
    )
    d.add_argument(
        "--background-folder",
        dest="backgrounds",
        default=None,
        help="image folder for backgrounds (default: photographs shipped with scikit-image)",
    )
    d.add_argument("--coco-root", default=None, help="COCO folder for backgrounds")
    d.add_argument("--coco-ann", default=None, help="COCO instances json (default under --coco-root)")
    d.add_argument("--quiet", action="store_true", help="no progress bars or messages")
    d.set_defaults(func=_cmd_demo)


def _h2o_export_parser(sub: argparse._SubParsersAction) -> None:
    """The ``hogsa h2o-export`` sub-command."""
    h = sub.add_parser(
        "h2o-export",
        help=HELP["h2o-export"],
        description="Convert a world sequence into an H2O tree (cam0-3 static, cam4 egocentric, MANO and "
        "obj_pose_rt labels, rgb frames, the object mesh under its H2O name) to try H2O code paths.",
    )
    h.add_argument("--world", required=True, help="the world's data root (ARCTIC ./data)")
    h.add_argument("--out", required=True, help="H2O root to write")
    h.add_argument("--subject", default="s05")
    h.add_argument("--sequence", default="box_grab_01", help="a grab sequence (constant articulation)")
    h.add_argument("--object-class", default="book", help="H2O class the object plays")
    h.add_argument("--mesh-name", default=None, help="mesh folder/file name variant (default: the class's last known)")
    h.add_argument("--image-size", default="320x180", help="WxH of the rendered frames")
    h.add_argument("--frame-stride", type=int, default=4)
    h.add_argument("--overwrite", action="store_true", help="replace an existing export of the same H2O sequence")
    h.add_argument("--quiet", action="store_true")
    h.set_defaults(func=_cmd_h2o_export)


def _view_parser(sub: argparse._SubParsersAction) -> None:
    """The ``hogsa view`` sub-command."""
    v = sub.add_parser(
        "view",
        help=HELP["view"],
        description="Render one grasp of a bundle's HOGS model on a full 360° orbit around the "
        "interaction centre, with and without the SRM (orbit_<sid>.png, orbit_<sid>.gif), and the same "
        "poses on other subjects' hand models (their own betas, wrists re-solved to keep the contacts; "
        "transfer.png: rows pose sources, columns subjects; contact / penetration figures in view.json).",
    )
    add_dataclass_arguments(v, ViewConfig)
    v.set_defaults(func=_cmd_view)


def _config_parser(sub: argparse._SubParsersAction, name: str, config: type, description: str, func: Any) -> None:
    """A sub-command whose flags are derived from the dataclass ``config``."""
    parser = sub.add_parser(name, help=HELP[name], description=description)
    add_dataclass_arguments(parser, config)
    parser.set_defaults(func=func)


def _frame_maps_parser(sub: argparse._SubParsersAction) -> None:
    """The ``hogsa frame-maps`` sub-command."""
    description = (
        "Render the annotated hands and object into every allocentric cropped image: "
        "<image>_depth.png (16-bit millimetres), <image>_mask.png (part ids) and cameras.npz (the "
        "crops' intrinsics and extrinsics) per (subject, sequence, view); resumable per view."
    )
    _config_parser(sub, "frame-maps", FrameMapsConfig, description, _cmd_frame_maps)


def _plates_parser(sub: argparse._SubParsersAction) -> None:
    """The ``hogsa plates`` sub-command."""
    description = (
        "Map the cropped frames of each allocentric view back into the full camera "
        "image, mask out the annotated hands and object, and keep the per-pixel median of the "
        "background: one PNG per (subject, view) and plates.json, for --background-folder."
    )
    _config_parser(sub, "plates", PlateConfig, description, _cmd_plates)
