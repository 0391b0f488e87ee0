"""The ``hogsa`` sub-commands: name, one-line help, and where the flags are added.

Nothing here imports torch or the library: ``hogsa --help`` and ``hogsa --version`` read this
table alone, and a sub-command's module is imported only when that sub-command is parsed.
"""

from __future__ import annotations

__all__ = ["COMMANDS", "HELP"]

#: name -> (one-line help, "module:function" that adds the sub-command to a subparsers action)
COMMANDS: dict[str, tuple[str, str]] = {
    "assets": (
        "write the synthetic MANO-format hands, procedural objects and previews",
        "hogsa_loader.cli.commands:_assets_parser",
    ),
    "convert-mano": ("convert a MANO .pkl into a chumpy-free .npz", "hogsa_loader.cli.commands:_convert_parser"),
    "world": (
        "generate a synthetic ARCTIC-format world with rendered images",
        "hogsa_loader.cli.commands:_world_parser",
    ),
    "world-noise": (
        "copy a world with ARCTIC-like fitting error in its hand annotations",
        "hogsa_loader.cli.commands:_world_noise_parser",
    ),
    "build": (
        "train every model of a dataset root and write the bundle (cached per stage, resumable)",
        "hogsa_loader.cli.build:add_build_command",
    ),
    "finetune": (
        "fine-tune ArcticNet-SF on real + HOGSA batches (one process, or DDP under torchrun / srun)",
        "hogsa_loader.cli.finetune:add_finetune_command",
    ),
    "export": (
        "write synthetic frames as WebDataset tar shards (offline mode)",
        "hogsa_loader.cli.commands:_export_parser",
    ),
    "demo": (
        "the main job: world, brief HOGS/ContactNet/POM/SRM training, bundle, stream",
        "hogsa_loader.cli.commands:_demo_parser",
    ),
    "h2o-export": (
        "write one grab sequence of a generated world in the H2O layout",
        "hogsa_loader.cli.commands:_h2o_export_parser",
    ),
    "view": ("360° orbits and pose transfer between subjects, as pictures", "hogsa_loader.cli.commands:_view_parser"),
    "plates": (
        "clean background plates of the dataset's static cameras, from its own frames",
        "hogsa_loader.cli.commands:_plates_parser",
    ),
    "frame-maps": (
        "depth maps, part masks and intrinsics of the dataset's cropped images, from its annotations",
        "hogsa_loader.cli.commands:_frame_maps_parser",
    ),
    "train": (
        "train a HOGS model, the SRM or ContactNet, or build a pose bank",
        "hogsa_loader.cli.train_commands:add_train_commands",
    ),
}

#: name -> one-line help
HELP: dict[str, str] = {name: text for name, (text, _) in COMMANDS.items()}
