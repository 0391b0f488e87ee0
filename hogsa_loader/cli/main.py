"""The ``hogsa`` command line.

Subcommands:
    hogsa --version
    hogsa assets --out DIR         synthetic MANO-format hands, procedural ARCTIC-format objects,
                                   and PNG previews of both
    hogsa convert-mano SRC DST     one-shot MANO .pkl -> chumpy-free, pickle-free .npz
    hogsa world --out DIR --preset tiny|small [--seed N]
                                   a synthetic ARCTIC-format world (raw_seqs, misc, cropped
                                   images, masks, splits) rendered with the mesh rasteriser

Environment: on Linux, preloading tcmalloc speeds up large CPU tensor work (see README).
"""

from __future__ import annotations

import argparse
import os
import sys
import time
from typing import Optional, Sequence

from hogsa_loader import __version__

__all__ = ["main", "build_parser"]


def _cmd_assets(args: argparse.Namespace) -> int:
    from tqdm import tqdm

    from hogsa_loader.hands.mano_io import write_mano_pickle
    from hogsa_loader.hands.synthetic import synthetic_hand_pair
    from hogsa_loader.objects import load_object_templates, write_procedural_objects

    out = os.path.abspath(args.out)
    mano_dir = os.path.join(out, "body_models", "mano")
    meta_dir = os.path.join(out, "arctic_data", "data", "meta")
    names = [n for n in args.objects.split(",") if n]
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
            from hogsa_loader.render.preview import hand_preview, object_preview, save_sheet

            bar.set_postfix_str("hand preview")
            save_sheet(os.path.join(mano_dir, "preview.png"), hand_preview(right, left))
            bar.update()
            bar.set_postfix_str("object preview")
            templates = load_object_templates(meta_dir, names=names)
            templates = [templates[n] for n in names] if isinstance(templates, dict) else templates
            save_sheet(os.path.join(meta_dir, "object_vtemplates", "preview.png"), object_preview(templates))
            bar.update()
    print(f"hands:   {mano_dir}/MANO_RIGHT.pkl, MANO_LEFT.pkl ({right.num_verts} vertices, {right.faces.shape[0]} faces)")
    print(f"objects: {meta_dir}/object_vtemplates/{{{','.join(names)}}}")
    if not args.no_preview:
        print(f"previews: {mano_dir}/preview.png, {meta_dir}/object_vtemplates/preview.png")
    print(f"done in {time.time() - t0:.1f} s")
    return 0


def _cmd_convert(args: argparse.Namespace) -> int:
    from hogsa_loader.hands.mano_io import convert_mano_to_npz

    model = convert_mano_to_npz(args.src, args.dst, side=args.side)
    print(f"{args.dst}: {model.side} hand, {model.num_verts} vertices, {model.faces.shape[0]} faces")
    return 0


def _cmd_world(args: argparse.Namespace) -> int:
    from hogsa_loader.world import generate_world, get_preset

    try:
        preset = get_preset(args.preset)
    except KeyError as exc:
        print(f"hogsa: error: {exc.args[0]}", file=sys.stderr)
        return 2
    say = (lambda s: None) if args.quiet else print
    record = generate_world(args.out, preset, seed=args.seed, progress=not args.quiet,
                            process_splits=not args.no_splits, log=say)
    out = os.path.abspath(args.out)
    n_seq = len(record["sequences"])
    say(f"world:   {out}/arctic_data/data ({len(record['subjects'])} subjects, {n_seq} sequences, "
        f"{record['num_frames']} frames, 9 views)")
    say(f"preview: {out}/world_preview.png")
    say("timings: " + ", ".join(f"{k} {v:.1f} s" for k, v in record["timings"].items()))
    return 0


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="hogsa", description="HOGSA augmentation loader tools")
    p.add_argument("--version", action="version", version=f"hogsa-loader {__version__}")
    sub = p.add_subparsers(dest="command")

    a = sub.add_parser("assets", help="write the synthetic MANO-format hands, procedural objects and previews")
    a.add_argument("--out", required=True, help="output folder (plays the role of ARCTIC's ./data)")
    a.add_argument("--objects", default="box,laptop,notebook", help="comma-separated procedural objects")
    a.add_argument("--seed", type=int, default=0)
    a.add_argument("--no-preview", action="store_true", help="skip the PNG previews")
    a.add_argument("--quiet", action="store_true", help="no progress bar")
    a.set_defaults(func=_cmd_assets)

    c = sub.add_parser("convert-mano", help="convert a MANO .pkl into a chumpy-free .npz")
    c.add_argument("src")
    c.add_argument("dst")
    c.add_argument("--side", choices=("right", "left"), default=None)
    c.set_defaults(func=_cmd_convert)

    w = sub.add_parser("world", help="generate a synthetic ARCTIC-format world with rendered images")
    w.add_argument("--out", required=True, help="output folder (plays the role of ARCTIC's ./data)")
    w.add_argument("--preset", default="tiny", help="tiny (< 1 min, tests) or small (ARCTIC image sizes)")
    w.add_argument("--seed", type=int, default=0)
    w.add_argument("--no-splits", action="store_true", help="skip ARCTIC processing into splits/")
    w.add_argument("--quiet", action="store_true", help="no progress bar or messages")
    w.set_defaults(func=_cmd_world)
    return p


def main(argv: Optional[Sequence[str]] = None) -> int:
    from hogsa_loader.errors import HogsaError

    parser = build_parser()
    args = parser.parse_args(argv)
    if not getattr(args, "func", None):
        parser.print_help()
        return 2
    try:
        return int(args.func(args))
    except HogsaError as exc:
        print(f"hogsa: error: {exc}", file=sys.stderr)
        return 1


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
