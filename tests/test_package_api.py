"""The package's front: the main names at the top level, and a command line whose help and
version import neither torch nor the library's modules."""

from __future__ import annotations

import subprocess
import sys

import hogsa_loader


def test_main_names_at_the_top_level_are_the_library_objects():
    from hogsa_loader.integrations.arctic import wrap_train_loader
    from hogsa_loader.models.bundle import load_bundle
    from hogsa_loader.sample.dataset import HOGSADataset
    from hogsa_loader.sample.export.reader import SynthShardDataset
    from hogsa_loader.sample.mixing import MixedLoader

    assert hogsa_loader.HOGSADataset is HOGSADataset and hogsa_loader.wrap_train_loader is wrap_train_loader
    assert hogsa_loader.load_bundle is load_bundle and hogsa_loader.MixedLoader is MixedLoader
    assert hogsa_loader.SynthShardDataset is SynthShardDataset
    assert set(hogsa_loader.__all__) <= set(dir(hogsa_loader))
    try:
        hogsa_loader.no_such_name  # noqa: B018
    except AttributeError as exc:
        assert "no_such_name" in str(exc)
    else:
        raise AssertionError("an unknown name resolved")


def _modules_after(code: str) -> set[str]:
    out = subprocess.run(
        [sys.executable, "-c", code + "\nimport sys\nprint(' '.join(sorted(sys.modules)))"],
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert out.returncode == 0, out.stderr[-2000:]
    return set(out.stdout.split())


def test_package_import_and_cli_help_import_no_torch():
    assert "torch" not in _modules_after("import hogsa_loader")
    for flag in ("--help", "--version"):
        mods = _modules_after(
            "from hogsa_loader.cli.main import main\n"
            f"try:\n    main([{flag!r}])\nexcept SystemExit as exc:\n    assert not exc.code\n"
        )
        heavy = {m for m in mods if m in ("torch", "numpy", "scipy", "cv2") or m.startswith("hogsa_loader.sample")}
        assert not heavy, (flag, sorted(heavy))
        assert "hogsa_loader.cli.commands" not in mods and "hogsa_loader.cli.train" not in mods


def test_a_sub_command_gets_its_full_flags_and_the_others_stay_listed(capsys):
    from hogsa_loader.cli.main import build_parser
    from hogsa_loader.cli.registry import COMMANDS

    full = build_parser()
    ns = full.parse_args(["convert-mano", "a.pkl", "b.npz", "--side", "left"])
    assert ns.command == "convert-mano" and ns.side == "left" and callable(ns.func)
    only = build_parser([])
    sub = next(a for a in only._actions if a.dest == "command")
    assert list(sub.choices) == list(COMMANDS)
    from hogsa_loader.cli.main import main

    assert main(["no-such-command"]) == 2
    assert "invalid choice" in capsys.readouterr().err


_BLOCK_EXTRAS = (
    "import sys\n"
    "for name in ('skimage', 'numba', 'pycocotools', 'gsplat'):\n"
    "    sys.modules[name] = None  # as if the extra were not installed: importing it raises ImportError\n"
)


def test_the_runtime_imports_without_any_extra():
    """The core install is enough for the loader: with scikit-image, numba, pycocotools and
    gsplat missing, the main names import and the extras are reported as absent."""
    code = _BLOCK_EXTRAS + (
        "from hogsa_loader import HOGSADataset, wrap_train_loader, load_bundle, MixedLoader\n"
        "from hogsa_loader.render import raster_kernels\n"
        "assert not raster_kernels.AVAILABLE\n"
        "print('ok')\n"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=300)
    assert out.returncode == 0 and out.stdout.split()[-1] == "ok", out.stderr[-3000:]


def test_a_command_that_needs_an_extra_names_it(tmp_path):
    code = _BLOCK_EXTRAS + (
        f"from hogsa_loader.cli.main import main\nsys.exit(main(['demo', '--out', {str(tmp_path / 'demo')!r}]))\n"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=300)
    assert out.returncode == 1, (out.returncode, out.stderr[-3000:])
    assert out.stderr.strip().splitlines() == [
        "hogsa demo: error: hogsa demo needs the package that provides 'skimage' (skimage is not installed): "
        "pip install 'hogsa-loader[demo]'"
    ]
    assert not (tmp_path / "demo").exists()
    from hogsa_loader.extras import MissingExtraError, require

    try:
        require("no_such_module_xyz", "coco", "COCO backgrounds")
    except MissingExtraError as exc:
        assert "COCO backgrounds" in str(exc) and "hogsa-loader[coco]" in str(exc)
    else:
        raise AssertionError("a missing module was imported")
