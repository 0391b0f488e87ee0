#!/usr/bin/env python
"""Run one result table from its config file: every step it builds on, in order, resumable.

A config (``experiments/configs/*.toml``) names the table it reproduces and its steps. Each
step runs one script of this repository (``run = "experiments/downstream.py"``) or one
``hogsa`` command (``run = "hogsa demo"``) with the settings of its ``[steps.settings]``
table, written as that script's flags (nested tables become prefixed flags: ``setup.preset``
→ ``--setup-preset``; lists are comma-separated; ``true`` / ``false`` → ``--flag`` /
``--no-flag``). Every step writes into its own folder, ``OUT/<step name>``, passed as
``--out`` (``out = false`` in a step for scripts without one).

A setting refers to what an earlier step made with an inline table instead of a path:

* ``{ step = "init", path = "setup/world/arctic_data/data" }`` — a path inside step ``init``'s
  folder (``{ path = "x.json" }``: inside the step's own folder);
* ``{ step = "finetune", arm = "hogsa" }`` — the folder of an arm's runs of the downstream
  step ``finetune`` (the ``seed<k>/`` folders ``heldout.py --runs`` reads);
* ``{ step = "init", arm = "real", file = "model.safetensors" }`` — that arm's file of each
  seed (``.../seed{seed}/model.safetensors``: ``downstream.py --model-init``);
* a reference with a ``label`` becomes ``LABEL=PATH`` (``runs = [{ label = "real", step =
  "finetune", arm = "real" }, ...]``: ``heldout.py --runs``).

The scripts cache what they finish and resume what they had begun, so running a config again
continues where it stopped and then only reports.

A script a config runs has ``parse_args(argv)`` (its settings; the runner checks every step's
flags with it before the first step runs) and ``main(argv)`` (its exit status).

Usage::

    python experiments/run.py experiments/configs/speed.toml                 # OUT: runs/speed
    python experiments/run.py experiments/configs/downstream.toml --print    # the commands only
    python experiments/run.py experiments/configs/downstream.toml --steps init --out runs/ds
"""

from __future__ import annotations

import argparse
import functools
import importlib.util
import shlex
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path
from types import ModuleType
from typing import Any, NoReturn, Optional

from hogsa_loader.cli.dataclass_args import flag_name

try:
    import tomllib
except ModuleNotFoundError:  # Python 3.10
    import tomli as tomllib

ROOT = Path(__file__).resolve().parent.parent
STEP_KEYS = {"name", "run", "about", "settings", "out"}
CONFIG_KEYS = {"title", "table", "out", "steps"}


@dataclass
class Step:
    """One command of a config: what it runs, its settings, and whether it is given ``--out``."""

    name: str
    run: str
    settings: dict[str, Any] = field(default_factory=dict)
    about: str = ""
    out: bool = True


@dataclass
class Experiment:
    """A parsed config file."""

    path: Path
    title: str
    table: str
    out: str
    steps: list[Step]


def _fail(path: Path, msg: str) -> NoReturn:
    raise SystemExit(f"run: error: {path}: {msg}")


def load_config(path: Path) -> Experiment:
    """Parse and check a config file: known keys only, unique step names, references only to
    earlier steps, scripts that exist."""
    try:
        raw = tomllib.loads(path.read_text(encoding="utf-8"))
    except (OSError, tomllib.TOMLDecodeError) as e:
        _fail(path, f"cannot read the config: {e}")
    unknown = set(raw) - CONFIG_KEYS
    if unknown:
        _fail(path, f"unknown keys {sorted(unknown)}; known: {sorted(CONFIG_KEYS)}")
    for key in ("title", "table", "out"):
        if not isinstance(raw.get(key), str):
            _fail(path, f"needs a string {key!r}")
    steps: list[Step] = []
    for i, entry in enumerate(raw.get("steps", [])):
        bad = set(entry) - STEP_KEYS
        if bad or not isinstance(entry.get("name"), str) or not isinstance(entry.get("run"), str):
            _fail(path, f"step {i + 1}: needs 'name' and 'run' and takes only {sorted(STEP_KEYS)}")
        if not isinstance(entry.get("settings", {}), dict) or not isinstance(entry.get("out", True), bool):
            _fail(path, f"step {i + 1}: 'settings' must be a table and 'out' true or false")
        step = Step(
            entry["name"], entry["run"], entry.get("settings", {}), entry.get("about", ""), entry.get("out", True)
        )
        if step.name in {s.name for s in steps}:
            _fail(path, f"two steps named {step.name!r}")
        for ref in _references(step.settings):
            if ("arm" in ref or "file" in ref) and "step" not in ref or "file" in ref and "arm" not in ref:
                _fail(path, f"step {step.name!r}: a reference with 'arm' names its 'step', one with 'file' its 'arm'")
            if "step" in ref and ref["step"] not in {s.name for s in steps}:
                _fail(path, f"step {step.name!r} refers to {ref['step']!r}, which is not an earlier step")
        if not step.run.startswith("hogsa ") and not (ROOT / step.run).is_file():
            _fail(path, f"step {step.name!r}: no script {step.run}")
        steps.append(step)
    if not steps:
        _fail(path, "no [[steps]]")
    return Experiment(path, raw["title"], raw["table"], raw["out"], steps)


def _is_reference(value: Any) -> bool:
    """A table with ``step``, ``arm`` or ``file``, or ``path`` alone (with an optional
    ``label``), is a reference; any other table is a nested settings table."""
    if not isinstance(value, dict) or not value or not set(value) <= {"step", "path", "arm", "file", "label"}:
        return False
    return bool({"step", "arm", "file"} & set(value)) or set(value) - {"label"} == {"path"}


def _references(value: Any) -> list[dict[str, Any]]:
    if _is_reference(value):
        return [value]
    if isinstance(value, dict):
        return [r for v in value.values() for r in _references(v)]
    if isinstance(value, list):
        return [r for v in value for r in _references(v)]
    return []


@functools.cache
def load_script(relpath: str) -> ModuleType:
    """A script of this repository as a module (its ``main(argv)`` is called)."""
    path = ROOT / relpath
    spec = importlib.util.spec_from_file_location(f"_run_{path.stem}", path)
    assert spec is not None and spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = module
    spec.loader.exec_module(module)
    return module


def _downstream_config(exp: Experiment, out: Path, name: str) -> Any:
    """The downstream settings of step ``name`` (for references to its arms)."""
    step = next(s for s in exp.steps if s.name == name)
    if not step.run.endswith("downstream.py"):
        _fail(exp.path, f"'arm' refers to a downstream step; {name!r} runs {step.run}")
    downstream = load_script(step.run)
    return downstream, downstream.parse_args(step_argv(exp, out, step))


def resolve(ref: dict[str, Any], exp: Experiment, out: Path, own: str) -> str:
    """The path a reference stands for (see the module docstring)."""
    folder = out / ref.get("step", own)
    if "arm" not in ref:
        return str(folder / ref.get("path", ""))
    downstream, cfg = _downstream_config(exp, out, ref["step"])
    arm = downstream.arm_folder(ref["arm"], cfg).resolve()
    return str(arm / "seed{seed}" / ref["file"]) if "file" in ref else str(arm)


def _value(value: Any, exp: Experiment, out: Path, own: str) -> str:
    if _is_reference(value):
        path = resolve(value, exp, out, own)
        return f"{value['label']}={path}" if "label" in value else path
    if isinstance(value, list):
        return ",".join(_value(v, exp, out, own) for v in value)
    return str(value)


def _flags(settings: dict[str, Any], exp: Experiment, out: Path, own: str, prefix: tuple[str, ...] = ()) -> list[str]:
    argv: list[str] = []
    for key, value in settings.items():
        path = (*prefix, key)
        if isinstance(value, dict) and not _is_reference(value):
            argv += _flags(value, exp, out, own, prefix=path)
        elif isinstance(value, bool):
            argv.append(flag_name(path) if value else "--no-" + flag_name(path)[2:])
        else:
            argv += [flag_name(path), _value(value, exp, out, own)]
    return argv


def step_argv(exp: Experiment, out: Path, step: Step) -> list[str]:
    """The step's arguments (after the script or the ``hogsa`` command)."""
    argv = _flags(step.settings, exp, out, step.name)
    return argv + (["--out", str(out / step.name)] if step.out else [])


def command_line(exp: Experiment, out: Path, step: Step) -> str:
    """The shell command a step runs."""
    head = step.run if step.run.startswith("hogsa ") else f"python {step.run}"
    return f"{head} {shlex.join(step_argv(exp, out, step))}"


def check_step(exp: Experiment, out: Path, step: Step) -> None:
    """Parse a step's arguments with its script's or command's own parser, running nothing: a
    config with a flag its script does not take stops before the first step runs."""
    argv = step_argv(exp, out, step)
    try:
        if step.run.startswith("hogsa "):
            from hogsa_loader.cli.main import build_parser

            command = step.run.split()[1:]
            build_parser(command[:1]).parse_args(command + argv)
        else:
            load_script(step.run).parse_args(argv)
    except SystemExit as e:
        if e.code:
            _fail(exp.path, f"step {step.name!r}: {step.run} refuses its settings (see above)")


def run_step(exp: Experiment, out: Path, step: Step) -> None:
    """Run one step in this process; a failing step stops the config with its status."""
    argv = step_argv(exp, out, step)
    if step.run.startswith("hogsa "):
        from hogsa_loader.cli.main import main as hogsa

        status = hogsa(step.run.split()[1:] + argv)
    else:
        status = load_script(step.run).main(argv)
    if status:
        raise SystemExit(f"run: error: step {step.name!r} ({step.run}) failed with status {status}")


def main(argv: Optional[list[str]] = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("config", help="a config file, e.g. experiments/configs/speed.toml")
    p.add_argument("--out", default=None, help="output folder (default: the config's 'out'); one folder per step")
    p.add_argument("--steps", default=None, help="comma-separated step names to run (default: all, in order)")
    p.add_argument(
        "--print", action="store_true", help="print every step's command (checked by its parser) and run nothing"
    )
    args = p.parse_args(argv)
    exp = load_config(Path(args.config))
    out = Path(args.out or exp.out).resolve()
    if args.steps is not None and not all(args.steps.split(",")):
        raise SystemExit(f"run: error: --steps: empty step name in {args.steps!r}")
    wanted = exp.steps if args.steps is None else [s for s in exp.steps if s.name in args.steps.split(",")]
    missing = set(args.steps.split(",")) - {s.name for s in exp.steps} if args.steps else set()
    if missing:
        raise SystemExit(f"run: error: --steps: no step {sorted(missing)} in {exp.path}")
    print(f"[run] {exp.title} → {exp.table}; OUT {out}", flush=True)
    for step in wanted:
        check_step(exp, out, step)
    for i, step in enumerate(wanted, 1):
        print(f"[run] step {i}/{len(wanted)} {step.name}: {command_line(exp, out, step)}", flush=True)
        if not args.print:
            t0 = time.perf_counter()
            run_step(exp, out, step)
            print(f"[run] step {step.name} done in {time.perf_counter() - t0:.0f} s", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
