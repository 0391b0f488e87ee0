"""Cached build stages: run a stage unless its record says it is built with the same key.

A stage writes its outputs and then ``OUT/stages/<name>.json`` (``{"key", "seconds",
"result"}``, written atomically); a stage whose key and outputs are there is reused.
:func:`run_stage_graph` runs a graph of stages (:class:`StageNode`), side by side on forked
processes where the graph and the machine allow. Used by ``hogsa build``
(:mod:`hogsa_loader.train.build`).
"""

from __future__ import annotations

import json
import shutil
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable, Optional, Sequence

import torch

from hogsa_loader.io.atomic import atomic_write
from hogsa_loader.io.hashing import settings_key
from hogsa_loader.system import available_cores, can_fork, run_forked

__all__ = ["StageNode", "StageRecords", "in_stage_process", "run_stage_graph", "stage_key"]


def stage_key(*parts: Any) -> str:
    """The cache key of a stage built from ``parts`` (settings and the keys of the stages it needs)."""
    return settings_key(parts)


class StageRecords:
    """Stage records in ``out/stages/``: run a stage unless its key is unchanged."""

    def __init__(self, out: Path, say: Callable[[str], None]) -> None:
        self.dir = Path(out) / "stages"
        self.dir.mkdir(parents=True, exist_ok=True)
        self.say = say
        self.seconds: dict[str, float] = {}
        self.reused: list[str] = []

    def path(self, name: str) -> Path:
        """The record file of stage ``name``."""
        return self.dir / f"{name.replace('/', '_')}.json"

    def record(self, name: str) -> Optional[dict]:
        """The stage's record, or None (absent or unreadable: a build interrupted mid-write)."""
        rec_path = self.path(name)
        try:
            rec = json.loads(rec_path.read_text()) if rec_path.is_file() else None
        except (OSError, ValueError):
            return None
        return rec if isinstance(rec, dict) else None

    def is_cached(self, name: str, key: str, outputs: Sequence[Path]) -> bool:
        """Whether :meth:`run` would reuse ``name`` (its record has ``key`` and its outputs exist)."""
        rec = self.record(name)
        return rec is not None and rec.get("key") == key and all(p.exists() for p in outputs)

    def run(self, name: str, key: str, outputs: Sequence[Path], fn: Callable[[], Any], resumable: bool = False) -> Any:
        """Run ``fn`` unless a record of ``name`` with ``key`` exists and its outputs do. Stale
        outputs are removed first — but a ``resumable`` stage's outputs with no record (an
        interrupted build) are left for ``fn`` to resume from."""
        rec_path = self.path(name)
        rec = self.record(name)
        if rec is not None and rec.get("key") == key and all(p.exists() for p in outputs):
            self.say(f"[{name}] cached ({rec['seconds']:.0f} s when built)")
            self.reused.append(name)
            self.seconds[name] = 0.0
            return rec.get("result")
        for p in outputs if rec is not None or not resumable else ():  # stale: rebuild from scratch
            if p.is_dir():
                shutil.rmtree(p)
            elif p.exists():
                p.unlink()
        if rec_path.exists():  # an interruption of the rebuild leaves no stale record behind
            rec_path.unlink()
        self.say(f"[{name}] building ...")
        t0 = time.perf_counter()
        result = fn()
        dt = time.perf_counter() - t0
        self.seconds[name] = dt
        atomic_write(
            rec_path, json.dumps({"key": key, "seconds": dt, "result": result}, indent=1, default=str).encode()
        )
        self.say(f"[{name}] done in {dt:.0f} s")
        return result


@dataclass
class StageNode:
    """A stage of a build graph: :meth:`StageRecords.run` arguments and the stages it needs."""

    name: str
    key: str
    outputs: list[Path]
    build: Callable[[], Any]
    needs: tuple[str, ...] = ()


_NODES: list[StageNode] = []  # the stage graph, set in the parent before the stage processes fork
_IN_STAGE: bool = False  # True inside a stage process (no progress bars there)
_SAY: Callable[[str], None] = print  # the parent's line printer, inherited by the stage processes
_OUT = Path(".")  # the build folder, inherited by the stage processes


def in_stage_process() -> bool:
    """True while a stage builds on a stage process of :func:`run_stage_graph` (draw no progress bars)."""
    return _IN_STAGE


def _run_node(i: int) -> tuple[float, bool]:
    """Build stage ``i`` in a stage process; returns its seconds and whether it was reused."""
    stages = StageRecords(_OUT, _SAY)
    node = _NODES[i]
    stages.run(node.name, node.key, node.outputs, node.build)
    return stages.seconds[node.name], node.name in stages.reused


def warm_up_optimizers() -> None:
    """Make one Adam optimizer now: torch.optim imports ``torch._dynamo`` the first time an
    optimizer is made (several seconds of CPU), so a parent that does it before forking
    stages spares every stage process the import."""
    torch.optim.Adam([torch.zeros(1, requires_grad=True)])


def _stage_process_init() -> None:
    global _IN_STAGE
    _IN_STAGE = True


def check_graph(nodes: Sequence[StageNode]) -> None:
    """Every stage needs only stages listed before it (so list order is a valid build order).

    Raises:
        ValueError: a stage needs one listed after it, or one not listed.
    """
    seen: set[str] = set()
    for n in nodes:
        missing = [d for d in n.needs if d not in seen]
        if missing:
            raise ValueError(f"stage {n.name!r} needs {missing}, which are not listed before it")
        seen.add(n.name)


def run_stage_graph(stages: StageRecords, nodes: list[StageNode], say: Callable[[str], None]) -> None:
    """Run the stages, each once the stages it needs are done. Where forking is safe
    (:func:`hogsa_loader.system.can_fork`), with more than one core and more than one stage to
    build, they run on forked processes, side by side where the graph allows (no progress bars;
    a stage that is the only one able to run builds in this process); else one after the other
    in list order. Every stage runs on one torch thread wherever it runs, so what it builds does
    not depend on the schedule (CPU reductions over more threads round differently). Cached
    stages are reported and skipped in the parent. On an error the other stage processes are
    stopped and the error is raised."""
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        _run_graph(stages, nodes, say)
    finally:
        torch.set_num_threads(threads)


def _run_graph(stages: StageRecords, nodes: list[StageNode], say: Callable[[str], None]) -> None:
    global _NODES, _SAY, _OUT, _IN_STAGE
    check_graph(nodes)
    todo = [n for n in nodes if not stages.is_cached(n.name, n.key, n.outputs)]
    workers = min(len(todo), available_cores())
    if workers < 2 or not can_fork():
        for n in nodes:
            stages.run(n.name, n.key, n.outputs, n.build)
        return
    for n in nodes:
        if n not in todo:
            stages.run(n.name, n.key, n.outputs, n.build)
    say(f"[stages] building {', '.join(n.name for n in todo)} on up to {workers} processes")
    from hogsa_loader.render.gaussians import warm_up_compositor  # deferred: numba kernels, only when stages fork

    warm_up_compositor()  # the stage processes inherit the compiled kernels
    warm_up_optimizers()  # and torch.optim's first-use import of torch._dynamo
    index = {n.name: i for i, n in enumerate(todo)}
    needs = [tuple(index[d] for d in n.needs if d in index) for n in todo]  # cached needs are done

    def record(i: int, result: tuple[float, bool]) -> None:
        stages.seconds[todo[i].name] = result[0]
        if result[1]:
            stages.reused.append(todo[i].name)

    _NODES, _SAY, _OUT = todo, say, stages.dir.parent
    try:
        run_forked(_run_node, needs, workers, on_result=record, initializer=_stage_process_init)
    finally:
        _NODES, _IN_STAGE = [], False  # (a stage built in this process ran the initializer here)
