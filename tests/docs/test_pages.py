"""The commands of the H2O and export pages, run on the generated world with toy sizes."""

from __future__ import annotations

import json
from pathlib import Path

from conftest import page_commands, placed

from hogsa_loader.cli.main import main as hogsa

#: How the pages name this file in a block's marker.
RUNNER = "tests/docs/test_pages.py"


def test_h2o_page_commands_run_on_a_generated_world(tiny_world, tmp_path):
    train_cmd, world_cmd, export_cmd = page_commands("h2o.md", RUNNER)
    # the suite's tiny world is the one `hogsa world --preset tiny` makes
    assert world_cmd[:3] == ["world", "--preset", "tiny"]
    info = json.loads((Path(tiny_world) / "arctic_data" / "data" / "meta" / "hogsa_world.json").read_text())
    assert info["preset"] == "tiny"
    paths = {
        "world": Path(tiny_world),
        "H2O": tmp_path / "H2O",
        "MANO": Path(tiny_world) / "body_models" / "mano",
        "runs": tmp_path / "runs",
    }
    assert hogsa(placed(export_cmd, paths) + ["--quiet"]) == 0
    assert {"object", "subject1"} <= {p.name for p in (tmp_path / "H2O").iterdir()}
    toy = ["--optim-iters", "4", "--image-size", "32", "--max-eval", "1", "--run-eval-every", "0", "--quiet"]
    assert hogsa(placed(train_cmd, paths) + toy) == 0
    metrics = json.loads((tmp_path / "runs" / "h2o_subject1_book" / "metrics.json").read_text())
    assert metrics["dataset"] == "h2o" and metrics["eval_views"] == [3] and metrics["psnr"] > 0


def test_export_page_command_runs_on_a_generated_world(tiny_world, untrained_bundle, tmp_path):
    (cmd,) = page_commands("export.md", RUNNER)
    paths = {"build/bundle": untrained_bundle, "data": Path(tiny_world), "shards": tmp_path / "shards"}
    argv = placed(cmd, paths)
    small = {"--num": "8", "--shard-size": "4"}
    argv = [small.get(argv[i - 1], a) if i else a for i, a in enumerate(argv)]
    assert hogsa(argv + ["--batch-size", "4", "--render-size", "64", "--quiet"]) == 0
    index = json.loads((tmp_path / "shards" / "index.json").read_text())
    assert index["complete"] is True and len(index["shards"]) == 2
