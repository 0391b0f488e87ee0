"""``experiments/run.py``: every result table's config, and the runner that executes it."""

from __future__ import annotations

import importlib
import json
import shlex
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]
CONFIGS = sorted((ROOT / "experiments" / "configs").glob("*.toml"))


def _run():
    return importlib.import_module("experiments.run")


def test_every_table_of_the_results_page_has_a_config():
    run = _run()
    tables = {run.load_config(c).table for c in CONFIGS}
    results = (ROOT / "docs" / "results.md").read_text()
    headings = [line[3:].strip() for line in results.splitlines() if line.startswith("## ")]
    anchors = {"docs/results.md#" + h.lower().replace(" ", "-") for h in headings}
    assert tables <= anchors, tables - anchors
    assert {"docs/results.md#speed", "docs/results.md#arcticnet-sf-fine-tuned-with-and-without-hogsa"} <= tables
    for config in CONFIGS:  # the page gives each table's one command
        assert f"python experiments/run.py experiments/configs/{config.name}" in results


@pytest.mark.parametrize("config", CONFIGS, ids=[c.stem for c in CONFIGS])
def test_config_steps_are_accepted_by_their_scripts(config, tmp_path, capsys):
    run = _run()
    assert run.main([str(config), "--out", str(tmp_path), "--print"]) == 0
    printed = capsys.readouterr().out
    exp = run.load_config(config)
    assert printed.count("[run] step ") == len(exp.steps)
    assert not any(tmp_path.iterdir())  # --print runs nothing


def _documented_finetune_flags(out: Path, init: str) -> list[str]:
    """The fine-tuning flags of the published table's runs, as its research log gives them."""
    flags = (
        "--setup-preset small_styles_heldout --setup-bank-per-sequence 64 --setup-bank-finger-scale 0.5 "
        "--setup-bank-frames all --setup-srm-iters 4000 --synthetic-mix add --synthetic-share 0.3333 "
        "--train-batch-size 64 --synthetic-cameras dataset --synthetic-backgrounds camera_plates "
        "--train-lr-schedule linear --train-lr 1e-4 --synthetic-other-hands 0.5"
    )
    return shlex.split(flags) + ["--model-init", init, "--out", str(out)]


def test_downstream_config_is_the_published_runs(tmp_path):
    """The config's steps parse to exactly the settings of the commands the table was made with."""
    run = _run()
    exp = run.load_config(ROOT / "experiments" / "configs" / "downstream.toml")
    steps = {s.name: s for s in exp.steps}
    downstream = run.load_script("experiments/downstream.py")
    parse = downstream.parse_args
    init = parse(run.step_argv(exp, tmp_path, steps["init"]))
    published_init = parse(
        shlex.split(
            "--setup-preset small_styles_heldout --setup-bank-per-sequence 64 --setup-bank-finger-scale 0.5 "
            "--synthetic-mix add --arms real --train-batch-size 64 --train-steps 600 --train-evals 6"
        )
        + ["--out", str(tmp_path / "init")]
    )
    assert init == published_init
    model = str(tmp_path / "init" / "runs" / "real" / "seed{seed}" / "model.safetensors")
    finetune = parse(run.step_argv(exp, tmp_path, steps["finetune"]))
    published = parse(_documented_finetune_flags(tmp_path / "finetune", model))
    # the published arms, and the plain-3DGS arm on models built beside the setup (its runs'
    # keys, and so the published runs, do not depend on that setting)
    assert finetune == downstream.replace(
        published,
        arms=("real", "hogsa", "hogsa_no_srm", "hogsa_no_pom", "hogsa_free"),
        setup=downstream.replace(published.setup, free=True),
    )
    for arm in ("real", "hogsa", "hogsa_no_srm", "hogsa_no_pom"):
        assert downstream.arm_folder(arm, finetune) == downstream.arm_folder(arm, published)
    gan = parse(run.step_argv(exp, tmp_path, steps["finetune_srm_gan"]))
    published_gan = parse(
        _documented_finetune_flags(tmp_path / "finetune_srm_gan", model) + ["--setup-srm-gan", "1.0", "--arms", "hogsa"]
    )
    assert gan == published_gan
    table = run.load_script("experiments/heldout.py").parse_args(run.step_argv(exp, tmp_path, steps["table"]))
    runs = dict(r.split("=", 1) for r in table.runs)
    assert runs["real"] == str(downstream.arm_folder("real", finetune).resolve())
    assert runs["srm_gan"] == str(downstream.arm_folder("hogsa", gan).resolve())
    assert runs["free_3dgs"] == str(downstream.arm_folder("hogsa_free", finetune).resolve())
    assert Path(runs["hogsa"]).name.startswith("hogsa+add+ft-") and runs["hogsa"].endswith("+linear+hands0.5")
    assert table.data == str(tmp_path / "finetune" / "setup" / "world" / "arctic_data" / "data")


def test_interfield_config_is_the_downstream_protocol_with_interfield_sf(tmp_path):
    """interfield.toml's steps are downstream.toml's with InterField-SF and the real and HOGSA
    arms, and its fine-tunes start from the InterField-SF models of its own first step."""
    run = _run()
    downstream = run.load_script("experiments/downstream.py")
    parse, replace = downstream.parse_args, downstream.replace
    steps = {}
    for name in ("downstream", "interfield"):
        exp = run.load_config(ROOT / "experiments" / "configs" / f"{name}.toml")
        steps[name] = {s.name: parse(run.step_argv(exp, tmp_path / name, s)) for s in exp.steps if s.name != "table"}
    field, arctic = steps["interfield"], steps["downstream"]
    assert set(field) == {"init", "finetune"}
    init = field["init"]
    assert init.model.kind == "interfield_sf"
    expected = replace(arctic["init"], out=init.out, model=replace(arctic["init"].model, kind="interfield_sf"))
    assert init == expected
    model = tmp_path / "interfield" / "init" / "runs" / "real+interfield_sf" / "seed{seed}" / "model.safetensors"
    assert field["finetune"].model.init == str(model)
    assert downstream.arm_folder("real", init) / "seed{seed}" / "model.safetensors" == model
    ft = arctic["finetune"]
    assert field["finetune"] == replace(
        ft,
        out=field["finetune"].out,
        arms=("real", "hogsa"),
        setup=replace(ft.setup, free=False),  # no plain-3DGS arm
        model=replace(ft.model, kind="interfield_sf", init=str(model)),
    )


def _script(tmp_path: Path, name: str, body: str) -> Path:
    path = tmp_path / f"{name}.py"
    path.write_text(
        "import argparse, json, pathlib\n"
        "def parse_args(argv):\n"
        "    p = argparse.ArgumentParser()\n"
        "    p.add_argument('--out'); p.add_argument('--source', default=None)\n"
        "    p.add_argument('--runs', default=''); p.add_argument('--fast', action=argparse.BooleanOptionalAction)\n"
        "    p.add_argument('--group-size', type=int, default=1)\n"
        "    return p.parse_args(argv)\n"
        "def main(argv):\n"
        "    a = parse_args(argv)\n" + body
    )
    return path


def _config(tmp_path: Path, text: str) -> Path:
    config = tmp_path / "exp.toml"
    config.write_text('title = "toy"\ntable = "docs/results.md#toy"\nout = "unused"\n' + text)
    return config


def test_runner_runs_steps_in_order_with_references(tmp_path):
    make = _script(
        tmp_path,
        "make",
        "    out = pathlib.Path(a.out); out.mkdir(parents=True)\n"
        "    (out / 'made.json').write_text(json.dumps(vars(a)))\n"
        "    return 0\n",
    )
    use = _script(
        tmp_path,
        "use",
        "    made = json.loads(pathlib.Path(a.source).read_text())\n"
        "    out = pathlib.Path(a.out); out.mkdir(parents=True)\n"
        "    (out / 'used.json').write_text(json.dumps({'made': made, 'runs': a.runs, 'fast': a.fast}))\n"
        "    return 0\n",
    )
    config = _config(
        tmp_path,
        f'[[steps]]\nname = "a"\nrun = "{make}"\n[steps.settings]\nfast = true\ngroup = {{ size = 3 }}\n'
        f'[[steps]]\nname = "b"\nrun = "{use}"\n[steps.settings]\nsource = {{ step = "a", path = "made.json" }}\n'
        'fast = false\nruns = [{ label = "x", step = "a", path = "p" }, { label = "y", path = "q" }]\n',
    )
    out = tmp_path / "out"
    assert _run().main([str(config), "--out", str(out)]) == 0
    made = json.loads((out / "a" / "made.json").read_text())
    assert made["fast"] is True and made["group_size"] == 3 and made["out"] == str(out / "a")
    used = json.loads((out / "b" / "used.json").read_text())
    assert used["made"] == made and used["fast"] is False
    assert used["runs"] == f"x={out / 'a' / 'p'},y={out / 'b' / 'q'}"
    sys.modules.pop("_run_make", None), sys.modules.pop("_run_use", None)


def test_runner_refuses_bad_configs_before_running(tmp_path, capsys):
    marker = tmp_path / "ran"
    ok = _script(tmp_path, "ok", f"    pathlib.Path({str(marker)!r}).write_text('x')\n    return 0\n")
    fails = _script(tmp_path, "fails", "    return 3\n")
    run = _run()
    cases = {
        "not an earlier step": f'[[steps]]\nname = "a"\nrun = "{ok}"\n[steps.settings]\nsource = {{ step = "b" }}\n',
        "two steps named": f'[[steps]]\nname = "a"\nrun = "{ok}"\n[[steps]]\nname = "a"\nrun = "{ok}"\n',
        "no script": '[[steps]]\nname = "a"\nrun = "experiments/none.py"\n',
        "unknown keys": f'colour = "red"\n[[steps]]\nname = "a"\nrun = "{ok}"\n',
        "refuses its settings": f'[[steps]]\nname = "a"\nrun = "{ok}"\n[[steps]]\nname = "b"\nrun = "{ok}"\n'
        "[steps.settings]\nnope = 1\n",
        "failed with status 3": f'[[steps]]\nname = "a"\nrun = "{fails}"\n',
        "names its 'step'": f'[[steps]]\nname = "a"\nrun = "{ok}"\n[steps.settings]\nmodel = {{ arm = "real" }}\n',
        "'settings' must be a table": f'[[steps]]\nname = "a"\nrun = "{ok}"\nsettings = 5\n',
        "'out' true or false": f'[[steps]]\nname = "a"\nrun = "{ok}"\nout = "no"\n',
    }
    for message, text in cases.items():
        with pytest.raises(SystemExit) as e:
            run.main([_config(tmp_path, text).as_posix(), "--out", str(tmp_path / "out")])
        assert message in str(e.value), (message, e.value)
        assert not marker.exists(), message  # nothing ran before the refusal
    with pytest.raises(SystemExit, match="empty step name"):
        run.main([_config(tmp_path, f'[[steps]]\nname = "a"\nrun = "{ok}"\n').as_posix(), "--steps", ""])
    assert not marker.exists()
    capsys.readouterr()
